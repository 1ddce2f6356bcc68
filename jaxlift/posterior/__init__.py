"""The posterior over bulk modulus, friction and effect parameters: priors, the AR(1)
likelihood, the emcee sampler, predictive draws and the air content.

Stands on :mod:`jaxlift.model` and :mod:`jaxlift.calibrate` (the least-squares start);
writes nothing: the outputs are written by :mod:`jaxlift.workflows.posterior`.
"""
