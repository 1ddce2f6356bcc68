"""The lift controller and its tuning: controllers, references, the closed-loop
simulation, the figures of "good", and the tuning split into gain space, cost,
parameter draws, optimisation and stability.

Stands on :mod:`jaxlift.model` (and on :mod:`jaxlift.posterior` for parameter draws).
"""
