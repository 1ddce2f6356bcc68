"""Where a model fails: regimes of a log, error per regime and stage, oscillation
frequency, amplitude and decay, residual statistics (NumPy only, no plotting).

Stands on :mod:`jaxlift.model`; used by calibration, reports and workflows.
"""
