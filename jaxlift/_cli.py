"""Command-line interface: ``jaxlift COMMAND ...`` (see ``jaxlift --help``)."""

from __future__ import annotations

import argparse
import pathlib
import sys
import warnings


def _setup_jax() -> None:
    import jax

    jax.config.update("jax_enable_x64", True)  # a program's start: the place to do it


def _read_logs(paths):
    import jaxlift as jl

    logs = []
    for p in paths:
        with warnings.catch_warnings(record=True) as caught:
            warnings.simplefilter("always", jl.UnusedColumnsWarning)
            logs.append(jl.read_log(p))
        for w in caught:
            print(f"note: {w.message}", file=sys.stderr)
    return logs


def cmd_simulate(args) -> int:
    import numpy as np

    import jaxlift as jl
    from jaxlift._plots import plot_overlay

    (log,) = _read_logs([args.log])
    plant, effects = jl.load_model(args.params, args.effects)
    inputs = jl.Inputs.from_log(log)
    sol = jl.simulate(plant, effects, inputs).check(f"simulating {log.path}")
    out = pathlib.Path(args.out)
    out.parent.mkdir(parents=True, exist_ok=True)
    data = np.column_stack(
        [
            np.asarray(sol.ts),
            np.asarray(sol.height),
            np.asarray(sol.speed),
            np.asarray(sol.pressure),
        ]
    )
    np.savetxt(
        out,
        data,
        delimiter=",",
        header="time_s,height_m,speed_mps,pressure_pa",
        comments="",
        fmt="%.9g",
    )
    png = out.with_suffix(".png")
    label = "model" + (f" + {', '.join(e.name for e in effects)}" if effects else " (baseline)")
    plot_overlay(
        log,
        [(label, sol.height, sol.speed, sol.pressure if log.pressure_pa is not None else None)],
        png,
        title=f"{log.name}: model vs measurement",
    )
    rms_h = float(np.sqrt(np.mean((np.asarray(sol.height) - log.height_m) ** 2)))
    print(f"wrote {out} ({log.n} samples) and {png}")
    print(f"effects: {[e.name for e in effects] or 'none (baseline)'}")
    print(f"RMS height error against the log: {rms_h * 1e3:.2f} mm")
    if log.speed_mps is not None:
        rms_v = float(np.sqrt(np.mean((np.asarray(sol.speed) - log.speed_mps) ** 2)))
        print(f"RMS speed error against the log: {rms_v * 1e3:.2f} mm/s")
    return 0


def build_parser() -> argparse.ArgumentParser:
    from jaxlift._effects import EFFECTS

    parser = argparse.ArgumentParser(
        prog="jaxlift",
        description="Differentiable digital twin of an AGV's hydraulic lift.",
    )
    sub = parser.add_subparsers(dest="command", required=True)
    p = sub.add_parser("simulate", help="simulate a log's input and compare with the log")
    p.add_argument("log", help="test-run log (CSV, see DATA.md)")
    p.add_argument("--params", help="parameter file (JSON, MODEL.md names); default nominal")
    p.add_argument(
        "--effects",
        default=None,
        help=f"comma-separated effects to switch on ({', '.join(EFFECTS)}); default: "
        "those whose parameters appear in --params",
    )
    p.add_argument("--out", required=True, help="output CSV (a PNG plot is written beside it)")
    p.set_defaults(func=cmd_simulate)
    return parser


def main(argv: list[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    _setup_jax()
    import jaxlift as jl

    try:
        return args.func(args)
    except (jl.LogError, jl.ParameterError, jl.SimulationError, ValueError) as err:
        print(f"jaxlift {args.command}: error: {err}", file=sys.stderr)
        return 2


if __name__ == "__main__":
    sys.exit(main())
