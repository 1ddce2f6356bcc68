"""``stick_slip``: static (breakaway) friction in the cylinders (thesis 3.1, 4.1.1).

``F_f += dFs * exp(-(v / v_s)^2) * tanh(v / v_eps)``: an extra friction that is
there only near zero speed, so the fork sticks at low speed and slips when the
pressure has built up -- sustained oscillations at low speed that touch zero speed.
Nesting value: ``dFs = 0``.

Where its refit starts (:meth:`StickSlip.starts_from_logs`): a least-squares fit of a
stick-slip stagnates unless it starts near the optimum (every slip's timing moves
with every parameter, so the surface is rough; measured in the detection study). The
slips' statistics per section of constant duty -- slips per second, median peak
speed, median duration -- do not depend on their timing and tell the breakaway force
from the Stribeck speed; a search on them finds the start (studies/DETECTION.md,
eleventh and twelfth sittings). A second search reads only the sections where the
fork also stops: the slips of a fork that never stops depend on every detail of the
model, and against logs of another simulator they led the first search astray
(:func:`slip_feature_search`; fifteenth sitting).
"""

from __future__ import annotations

import itertools
import math
from collections.abc import Callable, Mapping, Sequence
from typing import ClassVar

import jax.numpy as jnp
import numpy as np
import scipy.optimize as so

from ..log import Log
from ..params import param
from ..plant import PLANT_PARAMS
from ..solution import Solution
from .base import AbstractStatelessEffect, Scalar, Signals

#: a slip: the speed (smoothed over 3 samples) above this [m/s]. Well above the speed
#: sensor's noise (3.2 mm/s per sample at 100 Hz, 1.8 mm/s smoothed)
SLIP_SPEED = 0.012
#: sections of constant, positive duty shorter than this [s] are not used
MIN_SECTION_S = 5.0
#: a section of the revealing run (:attr:`StickSlip.revealing_run`: each duty held for
#: at least 10 s) [s]
REVEALING_SECTION_S = 10.0
#: a section "slips" at a rate that gives this many slips in MIN_SECTION_S; with fewer
#: slips in it, a section's peak speed and duration are not measured (0)
MIN_SLIPS = 3
#: a stuck fork reads below this speed [m/s] (smoothed over 3 samples: half SLIP_SPEED,
#: over three standard deviations of the smoothed noise above zero)
STUCK_SPEED = 0.006
#: ... and the second search reads a section's slips only if the fork is stuck in at
#: least this share of it (:func:`section_kinds`). Measured on the 15 stick-slip cases
#: of the detection and coverage studies (studies/DETECTION.md, fifteenth sitting):
#: every section where jaxlift's model *at the truth* missed the log's features (cost
#: 126 to 8 744) had a share of 0.00-0.02, every other one 0.06 or more.
MIN_STUCK_SHARE = 0.05
#: how the search's readings (:func:`slip_feature_search`) take each kind of section
#: (:func:`section_kinds`): matched as ``"slips"``, or left out as ``"ignored"``;
#: kinds not named are taken as they are
READINGS = (
    {"few": "slips", "ignored": "slips"},
    {"few": "ignored"},
)
#: relative errors the features are weighed by: rate, peak speed, duration
FEATURE_REL = np.array([0.03, 0.03, 0.10])
#: slips per second a section without slips in the log may have in the model (1 sigma)
NO_SLIP_RATE = 0.1
#: the grid of the search: breakaway force [N] x Stribeck speed [m/s]
DFS_GRID = (100.0, 200.0, 400.0, 700.0, 1000.0, 1500.0, 2200.0, 3000.0)
VS_GRID = (0.002, 0.003, 0.0045, 0.007, 0.01, 0.015, 0.02)
#: parameters the Nelder--Mead refinement moves (log scale), and its budget
SEARCHED = ("dFs", "v_s", "d", "cf_con", "beta")
MAX_EVALS = 150
#: the ridge of equal slip features (:func:`ridge_starts`): Stribeck speeds [m/s] of its
#: rungs; how much worse than the search's start a rung may match the features (cost
#: units) before the walk stops; how far from its neighbour's a rung's breakaway force
#: may be (factor); the evaluations of the one-dimensional search per rung
RIDGE_VS = tuple(float(v) for v in np.geomspace(0.002, 0.03, 13))
RIDGE_TOL, RIDGE_FACTOR, RIDGE_EVALS = 9.0, 1.6, 15


class StickSlip(AbstractStatelessEffect):
    """Stribeck-like breakaway friction near zero speed."""

    dFs: Scalar = param(
        0.0, "N", 0.0, 1e5, "breakaway friction above Coulomb", nesting=0.0, scale=100.0,
        typical=(20.0, 2000.0),
        typical_why="cylinder seals: tens of N for new, lubricated seals to a few kN for "
        "dry or worn ones",
    )  # fmt: skip
    v_s: Scalar = param(
        0.01, "m/s", 1e-4, 0.2, "Stribeck speed of the breakaway term",
        typical=(0.002, 0.03),
        typical_why="Stribeck speeds of lubricated seals: a few mm/s to a few cm/s",
    )  # fmt: skip

    name: ClassVar[str] = "stick_slip"
    revealing_run: ClassVar[str] = (
        "very slow runs (below 10 mm/s) at two or three duties, each held for at "
        "least 10 s, with holds between: a breakaway force makes the fork stick and "
        "slip in every one of them, and the slips' rate and peak speed at several "
        "duties fix its size and Stribeck speed"
    )

    def extra_friction(self, plant, z, sig: Signals):
        v = sig.v
        return self.dFs * jnp.exp(-((v / self.v_s) ** 2)) * jnp.tanh(v / plant.v_eps)

    @classmethod
    def starts_from_logs(
        cls,
        logs: Sequence[Log],
        params: Mapping[str, float],
        simulate: Callable[[Mapping[str, float]], Sequence[Solution] | None],
    ) -> list[dict[str, float]]:
        """Up to two starts from searches on the logs' slip statistics (two readings
        of the logs: :func:`slip_feature_search`), each a grid over ``dFs`` x
        ``v_s`` (Coulomb friction and damping at their nominal values, the rest at
        ``params``), then Nelder--Mead over :data:`SEARCHED`, both on the squared
        relative errors of the features (:func:`slip_features`) of every section of
        constant duty of at least :data:`MIN_SECTION_S` (what each asks for:
        :func:`section_kinds`). None when no log has a speed column, or no section of
        any log slips."""
        return slip_feature_search(logs, params, simulate)

    @classmethod
    def more_starts_from_logs(
        cls,
        logs: Sequence[Log],
        params: Mapping[str, float],
        simulate: Callable[[Mapping[str, float]], Sequence[Solution] | None],
    ) -> list[dict[str, float]]:
        """The rungs of the ridge of equal slip features through the search's first
        start (:func:`ridge_starts`): where one section slips, its features fix only a
        line in (``dFs``, ``v_s``), and a refit reaches the optimum only from a start
        within a few per cent of it (studies/DETECTION.md, twenty-eighth sitting)."""
        found = slip_feature_search(logs, params, simulate)
        return ridge_starts(logs, simulate, found[0]) if found else []

    @classmethod
    def revealed_in(cls, logs: Sequence[Log]) -> str | None:
        """The revealing run is there when the logs hold sections of constant duty of
        at least :data:`REVEALING_SECTION_S` that stick and slip (:func:`section_kinds`:
        slips by the count, and the fork stuck in between) at two or more different
        duties."""
        found = []  # (log name, duty, slips per second)
        for lg in logs:
            if lg.speed_mps is None:
                continue
            speed, pwm = np.asarray(lg.speed_mps), np.asarray(lg.pwm)
            secs = constant_duty_sections(pwm, lg.sample_period, REVEALING_SECTION_S)
            for (a, b), kind in zip(secs, section_kinds(speed, lg.sample_period, secs)):
                if kind == "slips":
                    rate = slip_features(speed[a:b], lg.sample_period)[0]
                    found.append((lg.name, float(pwm[a]), rate))
        if len({duty for _, duty, _ in found}) < 2:
            return None
        return f"{len(found)} sections that stick and slip: " + ", ".join(
            f"{name} at duty {duty:.3g} ({rate:.2g} slips/s)" for name, duty, rate in found
        )


def slip_features(speed: np.ndarray, dt: float, threshold: float = SLIP_SPEED) -> np.ndarray:
    """(slips per second [1/s], median peak speed [m/s], median duration [s]) of the
    slips in one section's speed [m/s] sampled every ``dt`` [s]; peak and duration 0
    with fewer than :data:`MIN_SLIPS` slips. A slip: a run of samples above
    ``threshold``, the speed smoothed over 3 samples.

    A lift near ``threshold`` reads as slipping without stick-slip: at ~11 mm/s its
    noisy speed crosses it again and again, and at ~17 mm/s the oscillations after a
    start from rest can cross it often enough (measured, tests/test_slip_starts.py; at
    24 mm/s and above, never). The second search therefore uses a section's slips only
    where the fork also stops (:func:`section_kinds`). Asking each slip to start from a
    stuck fork (below 5 mm/s) was tried first: it moved the log's features (noisy) away
    from the model's (noise-free) and the search into the wrong basin (measured on the
    slow test's logs: 423 N at 4.2 mm/s instead of 150 N at 11 mm/s)."""
    v = np.convolve(speed, np.ones(3) / 3, mode="same")
    up = v > threshold
    starts = np.nonzero(up[1:] & ~up[:-1])[0] + 1
    rate = starts.size / (speed.size * dt)
    if starts.size < MIN_SLIPS:
        return np.array([rate, 0.0, 0.0])
    ends = [s + int(np.argmin(up[s:])) if not up[s:].all() else up.size for s in starts]
    peaks = [v[s:e].max() for s, e in zip(starts, ends)]
    durations = [(e - s) * dt for s, e in zip(starts, ends)]
    return np.array([rate, np.median(peaks), np.median(durations)])


def stuck_share(speed: np.ndarray) -> float:
    """The share of the samples of a section's speed [m/s] at which the fork is stuck:
    the speed, smoothed over 3 samples as in :func:`slip_features`, below
    :data:`STUCK_SPEED`."""
    v = np.convolve(speed, np.ones(3) / 3, mode="same")
    return float(np.mean(v < STUCK_SPEED))


def section_kinds(speed: np.ndarray, dt: float, sections) -> list[str]:
    """What each section ``(a, b)`` of a log's speed [m/s] asks of the model in the
    search: ``"slips"`` (match its features: at least :data:`MIN_SLIPS` slips in
    :data:`MIN_SECTION_S`, and the fork stuck in at least :data:`MIN_STUCK_SHARE` of
    it), ``"still"`` (fewer than :data:`MIN_SLIPS` slips in all: the model should not
    slip either), ``"ignored"`` (slips by the count, but the fork never stops: a lift
    at the edge between sliding and stick-slip, or moving at around :data:`SLIP_SPEED`
    with its noisy speed crossing it again and again) or ``"few"`` (at least
    :data:`MIN_SLIPS` slips, but fewer in :data:`MIN_SECTION_S`). The first reading of
    :func:`slip_feature_search` matches the last two as slips, the second leaves them
    out.

    Why ``"few"``: such a section may be a slow stick-slip or a lift at about 20 mm/s
    whose noisy speed dips below :data:`SLIP_SPEED` now and then (measured on the
    studies' fitted logs: such sections in 79 of 154 cases, 73 of them without
    stick-slip), so it is read as uncertain, like ``"ignored"``. Read as ``"still"``, as
    before, it charged a slow stick-slip's truth for its own slips (measured, coverage
    set 18's case_015: 279 N at 28.6 mm/s; an 18 s section with 9 slips peaking at
    50 mm/s cost the truth 24 of its 28.7, and ``jaxlift fit`` from nominal values
    ended at chi2/N 5.57 and 3.74; read as uncertain, 0.986 and 0.997).
    """
    kinds = []
    for a, b in sections:
        rate, peak, _ = slip_features(speed[a:b], dt)
        if rate * MIN_SECTION_S < MIN_SLIPS:
            kinds.append("few" if peak > 0 else "still")
        else:
            kinds.append("slips" if stuck_share(speed[a:b]) >= MIN_STUCK_SHARE else "ignored")
    return kinds


def section_cost(measured: np.ndarray, simulated: np.ndarray, slips: bool) -> float:
    """The search's cost of one section: the squared relative errors of the
    simulated features against the measured ones (:data:`FEATURE_REL`) where the log
    slips, else the simulated slip rate against :data:`NO_SLIP_RATE`."""
    if slips:
        return float(np.sum(((simulated - measured) / (FEATURE_REL * measured)) ** 2))
    return float((simulated[0] / NO_SLIP_RATE) ** 2)


def constant_duty_sections(pwm: np.ndarray, dt: float, min_s: float = MIN_SECTION_S):
    """Sample ranges ``(a, b)`` of the sections of constant, positive duty of at least
    ``min_s`` [s]."""
    out, i = [], 0
    while i < len(pwm):
        rest = pwm[i:] != pwm[i]
        j = i + int(np.argmax(rest)) if rest.any() else len(pwm)
        if pwm[i] > 0 and (j - i) * dt >= min_s:
            out.append((i, j))
        i = j
    return out


def features_objective(
    logs: Sequence[Log],
    simulate: Callable[[Mapping[str, float]], Sequence[Solution] | None],
) -> tuple[Callable[[Mapping[str, float], Mapping[int, Sequence[str]]], float], dict]:
    """The slip-feature search's objective (:func:`slip_feature_search`; for studies).

    Returns ``(cost, kinds)``: ``kinds`` maps the index of each log with a speed column
    to the :func:`section_kinds` of its constant-duty sections; ``cost(values,
    reading)`` simulates ``values`` and sums :func:`section_cost` over the sections,
    each taken as ``reading`` says (``kinds`` mapped through one of :data:`READINGS`;
    ``"ignored"`` sections are left out); inf if the simulation fails."""
    used = [k for k, lg in enumerate(logs) if lg.speed_mps is not None]
    secs = {k: constant_duty_sections(np.asarray(logs[k].pwm), logs[k].sample_period) for k in used}
    measured = {
        k: [slip_features(np.asarray(logs[k].speed_mps)[a:b], logs[k].sample_period) for a, b in ss]
        for k, ss in secs.items()
    }
    kinds = {
        k: section_kinds(np.asarray(logs[k].speed_mps), logs[k].sample_period, ss)
        for k, ss in secs.items()
    }

    def cost(values: Mapping[str, float], reading: Mapping[int, Sequence[str]]) -> float:
        sols = simulate(values)
        if sols is None:
            return math.inf
        c = 0.0
        for k in used:
            v, dt = np.asarray(sols[k].speed), logs[k].sample_period
            for (a, b), f, kind in zip(secs[k], measured[k], reading[k]):
                if kind == "ignored":
                    continue
                c += section_cost(f, slip_features(v[a:b], dt), kind == "slips")
        return c

    return cost, kinds


def slip_feature_search(
    logs: Sequence[Log],
    params: Mapping[str, float],
    simulate: Callable[[Mapping[str, float]], Sequence[Solution] | None],
) -> list[dict[str, float]]:
    """:meth:`StickSlip.starts_from_logs` (a function, for studies). Logs without a
    speed column are left out (their solutions too).

    None unless some section slips by the count (``"slips"`` or ``"ignored"`` by
    :func:`section_kinds`; ``"few"`` alone may be noise). Up to two starts, from the two
    readings of the logs in :data:`READINGS`: every section with slips matched (the
    ``"few"`` too); then, if some of them are ``"ignored"`` or ``"few"`` and others are
    not, only the latter. Why both: where the fork never stops, the lift is at the edge
    between sliding and stick-slip, and the slips' features there depend on every detail
    of the model. A model that is exact matches them, and they then tell the breakaway
    force from the Stribeck speed (tests/test_slip_starts.py: 150 N at 11 mm/s is found
    only with them); against logs of another simulator at the true parameters they
    missed by a cost of up to 8 744 and led the search into another basin (detection
    case_089: 897 N read as 197 N, found only without them; studies/DETECTION.md,
    fifteenth sitting). The least-squares refits from both decide."""
    objective, kinds = features_objective(logs, simulate)
    readings = []
    # a section with slips by the count is needed: "few" alone may be noise (see
    # section_kinds; half the studies' cases have a "few" section, most without
    # stick-slip)
    by_count = {"slips", "ignored"} & set(itertools.chain(*kinds.values()))
    for read in READINGS if by_count else ():
        reading = {k: [read.get(x, x) for x in ks] for k, ks in kinds.items()}
        if reading not in readings and "slips" in itertools.chain(*reading.values()):
            readings.append(reading)
    start = {
        "cf_con": PLANT_PARAMS["cf_con"].nominal,
        "d": PLANT_PARAMS["d"].nominal,
        "beta": float(params["beta"]),
    }

    def cost(values: Mapping[str, float], reading) -> float:
        return objective({**start, **values}, reading)

    starts: list[dict[str, float]] = []
    for reading in readings:
        grid = min(
            (cost({"dFs": dfs, "v_s": vs}, reading), dfs, vs)
            for dfs, vs in itertools.product(DFS_GRID, VS_GRID)
        )
        if not math.isfinite(grid[0]):
            continue
        x0 = np.log([grid[1], grid[2], *(start[k] for k in SEARCHED[2:])])
        simplex = np.vstack([x0, x0 + 0.15 * np.eye(len(SEARCHED))])
        res = so.minimize(
            lambda x, r=reading: cost(dict(zip(SEARCHED, np.exp(x))), r), x0, method="Nelder-Mead",
            options=dict(maxfev=MAX_EVALS, initial_simplex=simplex, xatol=0.01, fatol=0.5),
        )  # fmt: skip
        best = res.x if math.isfinite(res.fun) and res.fun <= grid[0] else x0
        guess = {k: float(v) for k, v in zip(SEARCHED, np.exp(best))}
        if guess not in starts:
            starts.append(guess)
    return starts


def ridge_starts(
    logs: Sequence[Log],
    simulate: Callable[[Mapping[str, float]], Sequence[Solution] | None],
    start: Mapping[str, float],
) -> list[dict[str, float]]:
    """Points along the ridge of equal slip features through ``start`` (a start of
    :func:`slip_feature_search`), by Stribeck speed.

    For each Stribeck speed of :data:`RIDGE_VS`, outwards from ``start``'s both ways,
    the breakaway force that matches the features best in the search's first reading
    (bounded Brent on its log, within :data:`RIDGE_FACTOR` of the neighbour's, the
    other parameters at ``start``'s); the walk stops where a rung
    matches them worse than ``start`` by more than :data:`RIDGE_TOL`. Measured on
    detection case_093 (601 N at 8.3 mm/s): the search's start refits to chi2/N 1.81,
    the rung at 7.75 mm/s to 1.002 (studies/stick_slip_ridge.py)."""
    objective, kinds = features_objective(logs, simulate)
    reading = {k: [READINGS[0].get(x, x) for x in ks] for k, ks in kinds.items()}

    def cost(values: Mapping[str, float]) -> float:
        return objective(values, reading)  # ``simulate`` updates ``params`` by them

    at_start, out = cost(start), []
    half = math.sqrt(RIDGE_VS[1] / RIDGE_VS[0])
    up = [v for v in RIDGE_VS if v > start["v_s"] * half]
    down = [v for v in RIDGE_VS[::-1] if v < start["v_s"] / half]
    for way in (up, down):
        log_dfs = math.log(start["dFs"])
        for vs in way:
            res = so.minimize_scalar(
                lambda lf, vs=vs: cost({**start, "v_s": vs, "dFs": math.exp(lf)}),
                bounds=(log_dfs - math.log(RIDGE_FACTOR), log_dfs + math.log(RIDGE_FACTOR)),
                method="bounded", options=dict(xatol=0.005, maxiter=RIDGE_EVALS),
            )  # fmt: skip
            if not (math.isfinite(res.fun) and res.fun <= at_start + RIDGE_TOL):
                break
            log_dfs = float(res.x)
            out.append({**start, "v_s": float(vs), "dFs": math.exp(log_dfs)})
    return sorted(out, key=lambda st: st["v_s"])
