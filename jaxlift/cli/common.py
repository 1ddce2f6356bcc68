"""What every command shares: float64 at the program's start, and reading logs (the
channel map and resampling options, unused columns reported once).
"""

from __future__ import annotations

import argparse
import sys
import warnings


def cache_dir() -> str | None:
    """Where the command line keeps JAX's persistent compilation cache, or None when
    it is switched off (``JAXLIFT_CACHE=off``). ``JAXLIFT_CACHE=DIR`` chooses the
    folder; the default is ``$XDG_CACHE_HOME/jaxlift/jax`` (``~/.cache/jaxlift/jax``)."""
    import os
    import pathlib

    choice = os.environ.get("JAXLIFT_CACHE", "").strip()
    if choice.lower() in ("off", "0", "no", "false"):
        return None
    if choice:
        return choice
    base = os.environ.get("XDG_CACHE_HOME") or str(pathlib.Path.home() / ".cache")
    return str(pathlib.Path(base) / "jaxlift" / "jax")


def setup_jax() -> None:
    import jax

    jax.config.update("jax_enable_x64", True)  # a program's start: the place to do it
    where = cache_dir()
    if where is not None:
        # compiled simulations, Jacobians and samplers are kept between runs: a second
        # `jaxlift fit` on logs of the same lengths skips most of its compilation
        # (benchmarks/bench_cache.py). Every compilation is cached, however short.
        jax.config.update("jax_compilation_cache_dir", where)
        jax.config.update("jax_persistent_cache_min_compile_time_secs", 0.0)
        jax.config.update("jax_persistent_cache_min_entry_size_bytes", 0)


LOG_COLUMNS = "time_s, pwm, height_m, load_kg, speed_mps, pressure_pa"


def _channel_pair(text: str) -> tuple[str, str]:
    column, sep, channel = text.partition("=")
    if not sep or not column.strip() or not channel.strip():
        raise argparse.ArgumentTypeError(f"expected COLUMN=NAME, got {text!r}")
    return column.strip(), channel.strip()


def _period(text: str) -> float:
    import math

    try:
        value = float(text)
    except ValueError:
        value = math.nan
    if not (math.isfinite(value) and value > 0):
        raise argparse.ArgumentTypeError(f"expected a sample period > 0 [s], got {text!r}")
    return value


def add_log_options(p: argparse.ArgumentParser) -> None:
    """The options of every command that reads logs: the channel map and resampling
    (docs/data.md)."""
    g = p.add_argument_group("log files (docs/data.md)")
    g.add_argument(
        "--channel", action="append", default=[], type=_channel_pair, metavar="COLUMN=NAME",
        help=f"read the log column COLUMN ({LOG_COLUMNS}) from the file's column or channel "
        "NAME (values still in SI units); repeatable; overrides --channel-map",
    )  # fmt: skip
    g.add_argument(
        "--channel-map", metavar="FILE.json",
        help='channel map: a JSON object {"COLUMN": "NAME", ...} (keys starting with _ are '
        "comments); default: every column under its own name",
    )  # fmt: skip
    g.add_argument(
        "--resample", type=_period, default=None, metavar="DT",
        help="resample jittered time stamps onto a uniform clock of period DT [s] (height, "
        "speed, pressure interpolated linearly; pwm, load held); default: a time step more "
        "than 1%% off the sample period is an error",
    )  # fmt: skip


def log_options(args) -> dict:
    """``read_log``'s keyword arguments from the options of :func:`add_log_options`
    (``channel_map``, ``resample``); ValueError naming the file for a bad channel map."""
    import json

    from jaxlift.model.log_validation import channel_sources

    channel_map: dict[str, str] = {}
    path = getattr(args, "channel_map", None)
    if path:
        try:
            with open(path, encoding="utf-8") as f:
                spec = json.load(f)
        except (OSError, UnicodeDecodeError, json.JSONDecodeError) as e:
            raise ValueError(f"{path}: expected a JSON channel map, got {e}") from None
        if not isinstance(spec, dict):
            raise ValueError(f"{path}: expected a JSON object {{column: channel name}}")
        channel_map = {k: v for k, v in spec.items() if not k.startswith("_")}
    channel_map.update(dict(getattr(args, "channel", None) or []))
    try:
        channel_sources(channel_map)  # refused before any log is read
    except ValueError as e:
        raise ValueError(f"{path}: {e}" if path else str(e)) from None
    return {"channel_map": channel_map or None, "resample": getattr(args, "resample", None)}


def read_logs(paths, args=None):
    """The logs at ``paths``, read with the options of ``args`` (:func:`add_log_options`),
    unused columns reported once each as a ``note:`` on standard error."""
    import jaxlift as jl

    options = log_options(args) if args is not None else {}
    logs = []
    for p in paths:
        with warnings.catch_warnings(record=True) as caught:
            warnings.simplefilter("always", jl.UnusedColumnsWarning)
            logs.append(jl.read_log(p, **options))
        for w in caught:
            print(f"note: {w.message}", file=sys.stderr)
    return logs
