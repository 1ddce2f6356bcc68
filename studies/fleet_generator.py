"""Synthetic fleet for the fleet study: vehicles × weeks of test-run logs with known
truth, some vehicles drifting.

    python studies/fleet_generator.py --out DIR [--vehicles 50] [--weeks 8] [--seed 0]

Writes ``DIR/<vehicle>/<date>/{fit_1,fit_2,validation}.csv``, a ``run.toml`` manifest
(two logs fitted, one held out) and ``truth.json`` per run, and ``DIR/fleet_truth.json``
(every vehicle's kind and drift). Logs are made by the independent generator of the
detection study (``studies/detection_generator.py``: NumPy/SciPy only, nothing from
jaxlift), 40 to 70 s long (shorter than the detection study's, for the fleet's cost).

Vehicles (fractions of the fleet, at least one of each):
- ``stable`` (the rest): the same truth every week; loads, sequences, start heights
  and noise differ from week to week.
- ``air`` (15 %): the effective bulk modulus falls by 15 % per week (air dissolving
  and entrained in fine bubbles, read as a lower modulus, the thesis's reading).
- ``friction`` (15 %): Coulomb friction grows by 35 % per week.
- ``new_effect`` (one vehicle; 2 with 20+ vehicles): a leaking cylinder (sink speed
  3 mm/s at 10 MPa) appears from the middle week on.
A resumable writer: a run whose ``truth.json`` exists is skipped.
"""

from __future__ import annotations

import argparse
import datetime
import json
import pathlib
import sys

import numpy as np

sys.path.insert(0, str(pathlib.Path(__file__).parent))
import detection_generator as gen  # noqa: E402

START = datetime.date(2026, 9, 7)  # a Monday
AIR_RATE = 0.85  # beta multiplier per week
FRICTION_RATE = 1.35  # cf_con multiplier per week
LEAK_SIZE = 3e-3  # m/s sink speed at 10 MPa
DURATION_S = (40.0, 70.0)


def make_fleet(n_vehicles: int = 50, n_weeks: int = 8, seed: int = 0) -> list[dict]:
    """Vehicle specifications (deterministic in ``seed``)."""
    rng = np.random.default_rng(seed)
    n_air = max(1, round(0.15 * n_vehicles))
    n_fric = max(1, round(0.15 * n_vehicles))
    n_new = 2 if n_vehicles >= 20 else 1
    kinds = ["air"] * n_air + ["friction"] * n_fric + ["new_effect"] * n_new
    kinds += ["stable"] * (n_vehicles - len(kinds))
    kinds = [kinds[i] for i in rng.permutation(len(kinds))]
    vehicles = []
    for i, kind in enumerate(kinds):
        params = {}
        for name, (how, a, b) in gen.PLANT_DRAWS.items():
            if how == "rel":
                params[name] = gen.NOMINAL[name] * float(rng.uniform(1.0 - a, 1.0 + a))
            else:
                params[name] = gen._loguniform(rng, a, b)
        params["beta"] = gen._loguniform(rng, 0.8e9, 1.6e9)  # start healthy
        params["cf_con"] = float(rng.uniform(30.0, 80.0))  # a determinable friction
        vehicles.append({
            "vehicle": f"agv{i + 1:03d}",
            "kind": kind,
            "params": params,
            "vehicle_seed": int(rng.integers(0, 2**31 - 1)),
            "new_effect_week": n_weeks // 2 if kind == "new_effect" else None,
        })  # fmt: skip
    return vehicles


def week_spec(vehicle: dict, week: int) -> dict:
    """The detection generator's case specification of one vehicle's week."""
    rng = np.random.default_rng([vehicle["vehicle_seed"], week])
    params = dict(vehicle["params"])
    effects, sizes = [], {}
    if vehicle["kind"] == "air":
        params["beta"] *= AIR_RATE**week
    elif vehicle["kind"] == "friction":
        params["cf_con"] *= FRICTION_RATE**week
    elif vehicle["kind"] == "new_effect" and week >= vehicle["new_effect_week"]:
        ep, _ = gen.effect_params_from_size("leakage", LEAK_SIZE, rng, 1000.0)
        params.update(ep)
        effects, sizes = ["leakage"], {"leakage": LEAK_SIZE}
    loads = gen._draw_loads(rng)
    logs = []
    for li, name in enumerate(gen.LOG_NAMES):
        bottom = bool(rng.uniform() < 0.5)
        x0 = 0.0 if bottom else float(rng.uniform(0.5, 1.3))
        logs.append({
            "name": name, "role": "held_out" if name == "validation" else "fitted",
            "style": str(rng.choice(gen.STYLES)), "load_kg": loads[li],
            "start": "bottom" if bottom else "mid_mast", "x0_m": x0,
            "duration_range_s": list(DURATION_S),
        })  # fmt: skip
    date = START + datetime.timedelta(weeks=week)
    return {
        "case_id": f"{vehicle['vehicle']}/{date.isoformat()}",
        "seed": vehicle["vehicle_seed"],
        "case_seed": int(rng.integers(0, 2**31 - 1)),
        "kind": "null" if not effects else "single",
        "hidden_effects": effects,
        "effect_sizes": sizes,
        "effect_size_units": {e: gen.EFFECT_SIZE_RANGES[e][0] for e in effects},
        "derived": {},
        "params": params,
        "logs": logs,
    }


def write_fleet(out: str | pathlib.Path, vehicles: list[dict], n_weeks: int) -> None:
    out = pathlib.Path(out)
    out.mkdir(parents=True, exist_ok=True)
    (out / "fleet_truth.json").write_text(json.dumps(
        {"n_weeks": n_weeks, "start": START.isoformat(), "air_rate_per_week": AIR_RATE,
         "friction_rate_per_week": FRICTION_RATE, "leak_size_mps": LEAK_SIZE,
         "vehicles": vehicles}, indent=1) + "\n")  # fmt: skip
    from tqdm.auto import tqdm

    for v in tqdm(vehicles, desc="fleet generator", unit="vehicle"):
        for w in range(n_weeks):
            spec = week_spec(v, w)
            gen.write_case(spec, out, verbose=False)
            (out / spec["case_id"] / "run.toml").write_text(
                'fit = ["fit_1.csv", "fit_2.csv"]\nvalidate = ["validation.csv"]\n'
            )


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--out", required=True)
    p.add_argument("--vehicles", type=int, default=50)
    p.add_argument("--weeks", type=int, default=8)
    p.add_argument("--seed", type=int, default=0)
    a = p.parse_args(argv)
    if a.vehicles < 4 or a.weeks < 3:
        p.error("at least 4 vehicles (one of each kind) and 3 weeks (a trend needs 3 dates)")
    write_fleet(a.out, make_fleet(a.vehicles, a.weeks, a.seed), a.weeks)
    return 0


if __name__ == "__main__":
    sys.exit(main())
