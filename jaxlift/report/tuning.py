"""The tuning report: responses of controllers along the reference, the distributions
of the figures of "good" over parameter draws, and the robustness section.
"""

from __future__ import annotations

import os
from collections.abc import Mapping, Sequence

import jax
import numpy as np

from ..control.closed_loop import (
    ClosedLoopSolution,
)
from ..control.controller import AbstractController
from ..control.cost import FAILED_COST, OSC_FREE_MPS, tuning_runs
from ..control.draws import DrawSet, batch_models, evaluate_draws
from ..control.performance import (
    CostWeights,
    Figures,
)
from ..control.reference import Reference
from ..control.stability import stability_table
from ..model.effects import AbstractEffect
from ..model.plant import Plant
from ..model.vector_field import (
    canonical_effects,
)
from .document import Report
from .figures import new_figure


# ------------------------------------------------------------------ figures and reports
def plot_response(
    runs: Sequence[tuple[str, ClosedLoopSolution]], path: str | os.PathLike, title: str = ""
) -> str:
    """Height, speed against the reference, and duty of closed-loop runs (PNG)."""

    fig, ax = new_figure(3, 1, figsize=(11, 7.5), sharex=True)
    ref = runs[0][1]
    ax[0].plot(ref.ts, ref.reference.height(), "k--", lw=0.8, label="reference")
    ax[1].plot(ref.ts, ref.v_ref, "k--", lw=0.8, label="reference")
    for i, (label, sol) in enumerate(runs):
        ax[0].plot(sol.ts, sol.height, color=f"C{i}", lw=0.9, label=label)
        ax[1].plot(sol.ts, sol.speed, color=f"C{i}", lw=0.7, label=label)
        ax[2].plot(sol.ts, sol.u, color=f"C{i}", lw=0.5, label=label)
    ax[0].set_ylabel("height [m]")
    ax[1].set_ylabel("fork speed [m/s]")
    ax[2].set_ylabel("duty u [-]")
    ax[2].set_xlabel("time [s]")
    for a in ax:
        a.grid(alpha=0.3)
    ax[1].legend(loc="upper right", fontsize=8)
    fig.suptitle(title)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    return os.fspath(path)


def plot_distributions(
    table: Mapping[str, Mapping[str, np.ndarray]], keys: Sequence[str], path: str | os.PathLike
) -> str:
    """Box plots of figures (``table[gain set][key]`` arrays over draws) (PNG)."""

    fig, ax = new_figure(1, len(keys), figsize=(3.2 * len(keys), 3.6))
    for a, k in zip(np.atleast_1d(ax), keys):
        data = [np.asarray(v[k])[np.isfinite(v[k])] for v in table.values()]
        a.boxplot(data, tick_labels=list(table), whis=(0, 100))
        a.set_title(k, fontsize=9)
        a.tick_params(axis="x", labelrotation=30, labelsize=8)
        a.grid(alpha=0.3)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    return os.fspath(path)


def _finite(fn, a) -> float:
    """``fn`` over the finite entries of ``a``; NaN if there are none (no warning)."""
    a = np.asarray(a, dtype=float).ravel()
    a = a[np.isfinite(a)]
    return float(fn(a)) if a.size else float("nan")


def _fig_arrays(fig: Figures) -> dict[str, np.ndarray]:
    b = fig.tracking_rms.shape[0]
    rows = [jax.tree.map(lambda a, i=i: a[i], fig).as_dict() for i in range(b)]
    return {k: np.asarray([r[k] for r in rows]) for k in rows[0]}


def robustness_report(
    controllers: Mapping[str, AbstractController],
    plant: Plant,
    effects: Sequence[AbstractEffect],
    draws: DrawSet,
    reference: Reference | Sequence[Reference],
    out_dir: str | os.PathLike,
    *,
    noise_seed: int | None = 0,
    sampled: bool = False,
    T_c: float = 0.01,
    weights: CostWeights | None = None,
    report=None,
) -> tuple[object, dict]:
    """Evaluate each gain set over the draws (the figures as distributions, worst
    case, share of oscillation-free draws, failures), with and without the model's
    effects, with and without noise (every draw with a noise realisation of its own,
    seeds from ``noise_seed``), at every reference (load) given, plus the stability
    tables on the nominal model (first load). Adds sections to ``report`` (a
    :class:`~jaxlift.report.document.Report`, made if None) and writes figures under
    ``out_dir/figures``. Returns ``(report, summary)``; ``summary["cases"]`` is keyed
    ``"<case> @ <load> kg"``."""
    references = [reference] if isinstance(reference, Reference) else list(reference)
    reference = references[0]

    out = os.fspath(out_dir)
    figdir = os.path.join(out, "figures")
    os.makedirs(figdir, exist_ok=True)
    rep = Report("Robustness of the lift controller") if report is None else report
    effects = canonical_effects(effects)
    sim = dict(sampled=sampled, T_c=T_c)
    rep.heading("Robustness over parameter draws")
    rep.text(
        f"{len(draws.draws)} held-out draws of the plant parameters; source: {draws.source}. "
        "Reference: the thesis-like sequence at "
        f"{', '.join(format(float(r.m_load), 'g') for r in references)} kg, "
        f"{'sampled controller, T_c = ' + format(T_c, 'g') + ' s' if sampled else 'continuous controller'}. "  # noqa: E501
        f"Oscillation-free: sustained oscillation RMS below {OSC_FREE_MPS * 1e3:g} mm/s. "
        f"A failed run (solver failure or fork out of range) costs {FAILED_COST:g} and is counted."
    )
    summary: dict = {"source": draws.source, "n_draws": len(draws.draws), "cases": {}}
    cases = [("with effects" if effects else "model", effects, None)]
    if effects:
        cases.append(("without effects", (), None))
    if noise_seed is not None:
        cases.append((f"{cases[0][0]}, with noise", effects, noise_seed))
    batched = {name: batch_models(plant, effs, draws.draws) for name, effs, _ in cases}
    for (case_name, _, seed), ref in ((c, r) for c in cases for r in references):
        case = f"{case_name} @ {float(ref.m_load):g} kg"
        plants, effs_b = batched[case_name]
        noise = None if seed is None else tuning_runs([ref], [seed], len(draws.draws))[1]
        table, rows = {}, []
        for name, ctrl in controllers.items():
            c, ok, fig = evaluate_draws(
                ctrl, plants, effs_b, ref, weights=weights, noise_seeds=noise, **sim
            )
            arr = _fig_arrays(fig)
            arr["cost"] = np.where(ok, c, np.nan)
            table[name] = arr
            osc_free = ok & (arr["osc_sustained_mmps"] < OSC_FREE_MPS * 1e3)
            rows.append(
                dict(
                    gains=name,
                    cost_median=float(np.median(c)),
                    cost_worst=float(np.max(c)),
                    tracking_p50_mmps=_finite(np.median, arr["tracking_rms_mmps"]),
                    tracking_max_mmps=_finite(np.max, arr["tracking_rms_mmps"]),
                    osc_p50_mmps=_finite(np.median, arr["osc_rms_mmps"]),
                    osc_max_mmps=_finite(np.max, arr["osc_rms_mmps"]),
                    osc_sust_p50_mmps=_finite(np.median, arr["osc_sustained_mmps"]),
                    osc_sust_max_mmps=_finite(np.max, arr["osc_sustained_mmps"]),
                    offset_max_mmps=_finite(
                        np.max, np.abs([arr["shift1_offset_mmps"], arr["shift2_offset_mmps"]])
                    ),
                    effort_p50=_finite(np.median, arr["effort_per_s"]),
                    shut_p50_pct=_finite(np.median, arr["shut_share_pct"]),
                    osc_free_pct=100.0 * float(np.mean(osc_free)),
                    failed=int(np.sum(~ok)),
                )
            )
        summary["cases"][case] = rows
        rep.heading(f"Figures over the draws: {case}", 3)
        rep.table(rows, floatfmt=".3g", caption=f"{case}: distribution over the draws")
        slug = case.replace(" @ ", "_").replace(" ", "_").replace(",", "")
        png = plot_distributions(
            table,
            ["cost", "tracking_rms_mmps", "osc_sustained_mmps", "effort_per_s"],
            os.path.join(figdir, f"draws_{slug}.png"),
        )
        rep.figure(png, f"{case}: figures over the draws (box: quartiles, whiskers: range)")
    rep.heading("Closed-loop stability (nominal model)")
    rep.text(
        "Max real part of the eigenvalues of the closed loop linearised with `jax.jacfwd` "
        "at steady motion (height frozen) along the lift, slow and fast reference speed, "
        f"in continuous time and as deployed: sampled every {1e3 * T_c:g} ms with the duty "
        "held (the multipliers lambda of one period, given as log(lambda) / T_c so that "
        "the columns read alike; stable when |lambda| < 1: `max_abs_multiplier`). "
        "With noise: the saturation's slope replaced by its describing gain under the "
        "sensor noise (the probability that the noisy duty stays inside (0, 1)); "
        "a gain below 1 weakens the loop."
    )
    m = float(reference.m_load)
    for name, ctrl in controllers.items():
        rows = []
        for form_sampled in (False, True):
            for noisy in (False, True):
                for r in stability_table(
                    plant, effects, ctrl, m, noise=noisy, sampled=form_sampled, T_c=T_c
                ):
                    rows.append(dict(noise=noisy, **r))
        summary.setdefault("stability", {})[name] = rows
        n_unstable = sum(not r["stable"] for r in rows)
        rep.heading(f"Stability: {name} ({n_unstable} of {len(rows)} points unstable)", 3)
        rep.table(
            rows,
            columns=["form", "noise", "point", "x_m", "v_ref_mps", "u", "sat_gain",
                     "max_real_per_s", "freq_hz", "max_abs_multiplier", "stable"],
            floatfmt=".3g",
            collapsed=f"every point: {len(rows)} rows (click to open)",
        )  # fmt: skip
    return rep, summary
