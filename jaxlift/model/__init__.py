"""The model layer: parameters, the plant, the candidate effects, simulation.

Everything else in jaxlift stands on this layer and it imports nothing from above:

- :mod:`~jaxlift.model.constants` — the fixed numbers shared by every layer;
- :mod:`~jaxlift.model.params` — parameters with names, units, bounds and transforms;
- :mod:`~jaxlift.model.plant` — the baseline lift (motor, pump, valve, cylinder, mast);
- :mod:`~jaxlift.model.effects` — the candidate effects, one file each, and their registry;
- :mod:`~jaxlift.model.build` — a model (plant + effects) from names and parameter values;
- :mod:`~jaxlift.model.inputs`, :mod:`~jaxlift.model.vector_field`,
  :mod:`~jaxlift.model.stepping`, :mod:`~jaxlift.model.simulate`,
  :mod:`~jaxlift.model.solution` — one open-loop simulation of a test run;
- :mod:`~jaxlift.model.measurement` — the sensors and their noise;
- :mod:`~jaxlift.model.log`, :mod:`~jaxlift.model.sequences` — measurement logs and
  input sequences.
"""
