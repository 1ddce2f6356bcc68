"""Make the shipped logs in ``data/``: rerun to get the same bytes.

    python studies/make_data.py            # writes data/*.csv and data/truth.json

The truth behind the logs (documented in data/README.md) is away from the nominal
parameters, has an effective bulk modulus near the thesis's 0.44 GPa, and hides two
effects the baseline lacks: ``stick_slip`` and ``hose_compliance``.
"""

from __future__ import annotations

import argparse
import hashlib
import pathlib

import jax

jax.config.update("jax_enable_x64", True)

import jax.numpy as jnp  # noqa: E402
import numpy as np  # noqa: E402

import jaxlift as jl  # noqa: E402
from jaxlift.model.sequences import THESIS_LIKE_SECTIONS, VALIDATION_SECTIONS, ramped_sequence  # noqa: E402

#: The hidden truth (docs/model.md names, SI units).
TRUTH = {
    "k1": 2.05,
    "k2": 1.95,
    "k3": 1.80,
    "z1": -2.6,
    "z2": -3.3,
    "z3": -4.4,
    "beta": 0.5e9,
    "cf_con": 22.0,
    "cf_in": 14.0,
    "cf_out": 700.0,
    "d": 420.0,
    "dFs": 150.0,
    "v_s": 0.008,
    "C_h": 1.5e-12,
}
HIDDEN_EFFECTS = ("stick_slip", "hose_compliance")

#: (file name, sections, ramp time [s], load [kg], initial height [m], noise seed, role)
RUNS = [
    ("lift_500kg.csv", THESIS_LIKE_SECTIONS, 1.0, 500.0, 0.02, 500, "fit"),
    ("lift_1500kg.csv", THESIS_LIKE_SECTIONS, 1.0, 1500.0, 0.02, 1500, "fit"),
    ("validation_1000kg.csv", VALIDATION_SECTIONS, 0.5, 1000.0, 0.03, 1000, "validation"),
]


def make(out_dir: pathlib.Path) -> list[pathlib.Path]:
    out_dir.mkdir(parents=True, exist_ok=True)
    plant, effects = jl.with_params(jl.Plant(), jl.make_effects(HIDDEN_EFFECTS), TRUTH)
    written = []
    for fname, sections, ramp, load, x0, seed, _role in RUNS:
        ts, pwm = ramped_sequence(sections, ramp_s=ramp, dt=0.01)
        inputs = jl.Inputs.from_arrays(ts, pwm, np.full_like(ts, load), x0)
        sol = jl.simulate(plant, effects, inputs, rtol=1e-8, atol=(1e-9, 1e-9, 1e-2))
        log = jl.to_log(sol, inputs, jl.MeasurementModel(), jax.random.key(seed), name=fname[:-4])
        path = out_dir / fname
        jl.write_log(path, log)
        written.append(path)
    jl.save_params_json(
        out_dir / "truth.json",
        {k: jnp.asarray(v) for k, v in TRUTH.items()},
        comment="hidden truth of the shipped logs; effects: " + ", ".join(HIDDEN_EFFECTS),
    )
    return written


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", default=str(pathlib.Path(__file__).parents[1] / "data"))
    args = parser.parse_args()
    for path in make(pathlib.Path(args.out)):
        digest = hashlib.sha256(path.read_bytes()).hexdigest()[:16]
        print(f"wrote {path}  sha256 {digest}")


if __name__ == "__main__":
    main()
