"""Calibration: experiments and residuals, Levenberg--Marquardt, the staged fit,
independent fits on all cores, and the diagnosis of missing effects.

Stands on :mod:`jaxlift.model` and :mod:`jaxlift.analysis`.
"""
