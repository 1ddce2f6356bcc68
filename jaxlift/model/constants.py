"""The constants shared across jaxlift, in one place (SI units).

The physical numbers of the model and its sensors (see ``docs/model.md`` and
``docs/control.md``). Everything a user may fit or change lives in parameters
(:mod:`jaxlift.model.params`), not here; these are the fixed facts of the lift and
the defaults of its measurement model.
"""

G = 9.81  # gravitational acceleration [m/s^2]
P_ATM = 101325.0  # atmospheric pressure [Pa]
BETA_OIL = 1.4e9  # bulk modulus of ideal, air-free oil [Pa]

X_S1 = 1.5  # stage boundary 1 -> 2 [m]
X_S2 = 3.0  # stage boundary 2 -> 3 [m]
STAGE_BOUNDARIES_M: tuple[float, float] = (X_S1, X_S2)
MAST_HEIGHT_M = 4.5  # full height, the top of stage 3 [m]

SIGMA_HEIGHT_M = 0.5e-3  # white noise of the wire height sensor [m]
SPEED_NOISE_POWER = 1e-7  # power of the band-limited speed-sensor noise [(m/s)^2 s]
SIGMA_PRESSURE_PA = 5e4  # white noise of a pressure sensor, where a vehicle has one [Pa]
SAMPLE_PERIOD_S = 0.01  # default logging / controller period, 100 Hz [s]
OUTPUT_DT = SAMPLE_PERIOD_S  # output grid of closed-loop simulations [s]

# The bottom end stop: a stiff one-sided contact on the carriage (docs/model.md,
# Plant.end_stop_force), whose stiffness scales with the moving mass M (k = M w^2) and
# whose damping grows with the depth (Hunt-Crossley), critical at rest. The fork rests
# g / w^2 = 0.11 mm below 0 whatever the load (far inside the height sensor's noise) and
# the contact's own mode stays at w for the explicit solver. The specification's fixed
# k = 1e8 N/m, c = 5e5 N s/m make the unloaded carriage (100 kg) an overdamped mode at
# c/M = 5000 1/s: Tsit5 then needs steps below 0.7 ms while the fork rests on the stop.
# Same rest depth (the specification's 0.1-0.2 mm); 8 ms steps on the stop.
END_STOP_OMEGA = 300.0  # natural frequency of the contact [rad/s]
END_STOP_ZETA = 1.0  # damping ratio of the contact [-]
#: Every run starts this far above its initial height [m] (so one on the bottom stop
#: starts just above it). Exactly at 0 the
#: fork, held by the oil at static pressure, sits on the contact's tie: round-off moves
#: it across 0 and back, the contact (undamped at zero depth) switches on and off, and
#: the explicit solver, whose steps suit either side but not the switching, lets that
#: chatter grow (measured: 1e-18 m to 1e-9 m in one second of hold, and a
#: forward-mode derivative of 3e10 with respect to the start, which stalled the fit of
#: a 111 kg log at its start). 1 µm is 500 times below the height sensor's noise; the
#: shift applies to every start so that the start height stays continuous in ``x0``
#: with derivative 1 (the fit's initial-height offsets).
START_CLEARANCE = 1e-6
