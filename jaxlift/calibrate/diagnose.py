"""Which physical effect is missing? Score screens, confirmation refits, a verdict.

For every candidate effect of docs/model.md that is not yet in the model:

1. **Screen** (no refit): the score (Lagrange-multiplier) test. At the fitted model,
   the sensitivity ``g`` of the scaled residuals to the effect's switch parameter at its
   nesting value is computed by a secant through the simulation (the effect switched
   on at a small fraction of its typical size: exact for effects linear in their
   parameter at nesting, and well defined for ``motor_inertia``, ``mast_compliance``
   and ``input_delay`` whose nesting value sits on a branch switch); ``g`` is projected
   against the Jacobian of the fitted parameters (what the model can already explain).
   One-sided, since every switch parameter is bounded below by its nesting value:
   ``z = -g'r / sqrt(s^2 * infl * |g_perp|^2)``, where ``s^2`` is the residual variance and
   ``infl = (1 + rho1) / (1 - rho1)`` accounts for the residuals' autocorrelation (an
   AR(1) effective sample size) -- thousands of correlated samples are not thousands of
   independent ones. The predicted chi2 drop is ``(g'r)^2 / |g_perp|^2``.
2. **Confirm** the best-screened candidates by refitting the model with the effect
   (warm start at the current optimum; the effect's parameters from a small grid of
   physically sized values, and from the starts the effect reads from the logs, where
   it reads any: :meth:`~jaxlift.AbstractEffect.starts_from_logs`, stick-slip's
   search on its slips' statistics), and compare the information criterion
   ``BIC = chi2 / infl + k ln(n / infl)`` and the error on held-out logs.
3. **Verdict**: the confirmed effect with the largest BIC drop, if that drop is larger
   than ``bic_threshold`` (default 10: "very strong" on Kass & Raftery's scale) and,
   where held-out logs are given, their chi2 falls by more than the same threshold
   (in effective samples; each held-out log's initial height is estimated under each
   model, a nuisance as in the fit); else ``"none"``. When the best two candidates
   that pass are within ``bic_threshold`` of each other the data cannot tell them
   apart: the verdict is ``"undecided"``, between those two, with the evidence for each
   and an experiment that would separate them (:data:`SEPARATING_EXPERIMENTS`).

No candidate ends the diagnosis by failing: a screen whose simulation fails, or a
refit that fails, is recorded on that candidate (:attr:`EffectScreen.failure`, why and
where) and the others go on. If the baseline fit itself failed, the verdict is
``"undecided"`` with that reason.

:func:`diagnose_iteratively` adds the winner and diagnoses again until ``none``,
checking after each addition whether an effect added earlier has become redundant.
"""

from __future__ import annotations

import dataclasses
import html
import math
from collections.abc import Callable, Mapping, Sequence

import numpy as np
import pandas as pd

from ..analysis.regimes import stage_of
from ..model.build import model_params
from ..model.effects import EFFECTS
from ..model.log import Log
from .experiment import make_experiments
from .fit import (
    READ_SYNC_GAINS,
    fit,
    fit_problem,
    heldout_residuals,
    log_simulator,
    offsets_and_chi2n,
)
from .parallel import thread_map
from .problem import Problem
from .result import FitResult, pooled_rho1


#: The parameter whose nesting value switches each effect off (first with a nesting).
def switch_parameter(effect_name: str) -> str:
    infos = EFFECTS[effect_name].param_infos()
    return next(n for n, i in infos.items() if i.nesting is not None)


@dataclasses.dataclass
class EffectScreen:
    """Score-test result of one candidate effect (see module docstring)."""

    effect: str
    parameter: str
    z: float  # one-sided score statistic (standard normal under "not missing")
    p_value: float
    predicted_chi2_drop: float  # before the autocorrelation correction
    predicted_value: float  # Gauss-Newton estimate of the switch parameter
    confirmed_chi2: float | None = None
    delta_bic: float | None = None  # negative = better with the effect
    heldout_chi2_before: float | None = None
    heldout_chi2_after: float | None = None
    fitted_params: dict[str, float] | None = None
    fitted_stderr: dict[str, float] | None = None  # standard errors of fitted_params
    failure: str | None = None  # why this candidate could not be screened or refitted
    #: the share of the fitted logs' error above the noise (chi2 - N) the refit removed
    explained_share: float | None = None
    #: why a candidate that passed the BIC was not kept (one of the other two tests
    #: failed): such a candidate may be one of two missing effects (Diagnosis.partial)
    not_kept: str | None = None

    def as_dict(self) -> dict:
        return {k: v for k, v in dataclasses.asdict(self).items()}


@dataclasses.dataclass
class Diagnosis:
    verdict: str
    ranking: list[EffectScreen]
    base_effects: list[str]
    base_chi2: float
    n_residuals: int
    inflation: float
    base_fit: FitResult
    winner_fit: FitResult | None
    #: effects removed again after the winner was added (backward check of
    #: :func:`diagnose_iteratively`): name -> BIC change when removed (< threshold)
    dropped: dict[str, float] = dataclasses.field(default_factory=dict)
    #: with verdict "undecided": the candidates the data cannot tell apart (best first)
    undecided_between: list[str] = dataclasses.field(default_factory=list)
    #: with verdict "undecided": why, and the experiment that would separate them;
    #: with "unexplained": how much error remains
    reasons: list[str] = dataclasses.field(default_factory=list)
    #: held-out logs left out of the held-out check, and why (:func:`usable_heldout`)
    heldout_excluded: dict[str, str] = dataclasses.field(default_factory=dict)
    #: the error left by the final model (set on the last step of
    #: :func:`diagnose_iteratively`): see :func:`remaining_misfit`
    misfit: RemainingMisfit | None = None
    #: candidates that passed the BIC but failed exactly one of the other two tests,
    #: with their refits (best first): those that removed less than :data:`MIN_SHARE`
    #: of a significant error (the smaller of two missing effects looks like this), and
    #: those that removed most of it but did not predict the held-out logs better (the
    #: larger of two does, when the held-out error comes from the other one). Each
    #: says why in :attr:`EffectScreen.not_kept`; see :func:`diagnose_iteratively`
    partial: list[tuple[EffectScreen, FitResult]] = dataclasses.field(default_factory=list)
    #: what the lookahead of :func:`diagnose_iteratively` tried and why it was not kept
    lookahead: list[str] = dataclasses.field(default_factory=list)
    #: what the cross-validation of :func:`diagnose_iteratively` (:func:`cross_validate`)
    #: found: why it kept the candidate, or why not
    cross_validation: list[str] = dataclasses.field(default_factory=list)
    #: with verdict "undecided": the refits with each of ``undecided_between`` (same
    #: order), to judge what the model with either would leave
    undecided_fits: list[FitResult] = dataclasses.field(default_factory=list)

    def explained_share(self) -> float | None:
        """The share of the model error (chi2/N above the noise floor of 1) that the
        named effect removed on the fitted logs; None without a named effect."""
        if self.winner_fit is None:
            return None
        before = self.base_chi2 / self.n_residuals - 1.0
        after = self.winner_fit.chi2 / self.winner_fit.n_residuals - 1.0
        return (before - after) / before if before > 0 else None

    def table(self):
        """The candidates as a :class:`pandas.DataFrame` indexed by effect, in the
        ranking's order: score ``z`` and ``p`` of the screen, the refit's ``delta_bic``
        (negative = better with the effect), held-out chi2/N before and after, the
        fitted sizes with their standard errors, and why a candidate failed."""
        rows = []
        for r in self.ranking:
            sizes = ", ".join(
                f"{k} = {v:.4g} ± {(r.fitted_stderr or {}).get(k, math.nan):.2g}"
                for k, v in (r.fitted_params or {}).items()
            )
            rows.append(
                {"effect": r.effect, "z": r.z, "p": r.p_value, "delta_bic": r.delta_bic,
                 "heldout_chi2_before": r.heldout_chi2_before,
                 "heldout_chi2_after": r.heldout_chi2_after, "fitted": sizes,
                 "failure": r.failure or ""}
            )  # fmt: skip
        return pd.DataFrame(rows).set_index("effect")

    def _repr_html_(self) -> str:
        model = "baseline" + "".join(f" + {e}" for e in self.base_effects)
        head = f"<p><b>Diagnosis</b> of the {model}: verdict <b>{self.verdict}</b>"
        if self.undecided_between:
            head += f" (between {' and '.join(self.undecided_between)})"
        head += "</p>" + "".join(f"<p>{html.escape(r)}</p>" for r in self.reasons)
        return head + self.table().to_html(float_format=lambda x: f"{x:.4g}", na_rep="")

    def as_dict(self) -> dict:
        return {
            "verdict": self.verdict,
            "explained_share": self.explained_share(),
            "undecided_between": self.undecided_between,
            "reasons": self.reasons,
            "heldout_excluded": self.heldout_excluded,
            "remaining_misfit": None if self.misfit is None else self.misfit.as_dict(),
            "ranking": [r.as_dict() for r in self.ranking],
            "base_effects": self.base_effects,
            "base_chi2": self.base_chi2,
            "n_residuals": self.n_residuals,
            "autocorrelation_inflation": self.inflation,
            "dropped_after_adding": self.dropped,
            "partial": [s.effect for s, _ in self.partial],
            "lookahead": self.lookahead,
            "cross_validation": self.cross_validation,
        }


def _norm_sf(z: float) -> float:
    return 0.5 * math.erfc(z / math.sqrt(2.0))


def screen_effects(
    base: FitResult,
    logs: Sequence[Log],
    candidates: Sequence[str] | None = None,
    *,
    secant_fraction: float = 0.2,
    workers: int | None = None,
    free: str = "all",
) -> list[EffectScreen]:
    """Score screens of the candidate effects at the fitted model ``base``; sorted by
    ``z``, most likely missing first. The candidates' simulations run on ``workers``
    threads (default one per CPU core). ``free``: the diagnosis's free parameters; each
    candidate is simulated through the residual function of its confirmation refit
    (:func:`refit_free`), compiled here once for both."""
    experiments = make_experiments(logs)
    candidates = [c for c in (candidates or EFFECTS) if c not in base.effects]
    plant, base_effs = base.model.plant, base.model.effects
    infos = base.model.param_infos()
    problem = Problem(
        plant, base_effs, tuple(experiments), tuple(base.free), tuple(infos[n] for n in base.free)
    )
    x0_mm = [1e3 * base.x0_offsets[e.name] for e in experiments]
    theta = problem.to_theta(base.params, x0_mm)
    r, J = problem.jacobian_at(theta)
    n, p = J.shape
    s2 = float(r @ r) / max(n - p, 1)
    infl = base.inflation

    def secant(name: str) -> tuple[str, float, np.ndarray]:
        par = switch_parameter(name)
        info = EFFECTS[name].param_infos()[par]
        step = secant_fraction * (info.scale or 1.0)
        # the model with the effect switched on, parametrised as the candidate's refit
        # is (its free parameters, in its order): the residual function compiled for
        # the screen is the one the refit calls, not a second compilation of the same
        # model (~4 s each on 2 cores; measured on the shipped logs, 2026-11-29)
        prob_e = fit_problem(experiments, [*base.effects, name], refit_free(free),
                             {**base.params, par: step})  # fmt: skip
        at = {k: float(v) for k, v in model_params(prob_e.plant, prob_e.effects).items()}
        try:
            return par, step, prob_e.residuals_at(prob_e.to_theta(at, x0_mm)), None
        except Exception as err:  # noqa: BLE001 -- one candidate's failure, reported
            return par, step, None, f"{type(err).__name__}: {err}"

    out = []
    # one thread per core: each candidate is its own compiled simulation (_parallel.py)
    nan = float("nan")
    for name, (par, step, rs, err) in zip(candidates, thread_map(secant, candidates, workers)):
        if err is None and not np.all(np.isfinite(rs)):
            err = "the simulation failed on at least one log (solver failure)"
        if err is not None:
            why = f"screen with {par} = {step:g}: {err}"
            out.append(EffectScreen(name, par, nan, nan, nan, nan, failure=why))
            continue
        g = (rs - r) / step
        coef, *_ = np.linalg.lstsq(J, g, rcond=None)
        g_perp = g - J @ coef
        gg = float(g_perp @ g_perp)
        # g_perp'r, not g'r: equal at an exact optimum (J'r = 0), but the optimiser stops
        # at a tolerance, and what the fitted parameters could still explain is not
        # evidence for the effect
        score = -float(g_perp @ r)
        if gg <= 0 or not np.isfinite(gg) or not np.isfinite(score):
            z, drop, psi = 0.0, 0.0, 0.0
        else:
            z = score / math.sqrt(s2 * infl * gg)
            drop = max(score, 0.0) ** 2 / gg
            psi = max(score, 0.0) / gg  # one Gauss-Newton step from the nesting value
        out.append(EffectScreen(name, par, z, _norm_sf(z), drop, psi))
    return sorted(out, key=lambda s: -s.z if math.isfinite(s.z) else math.inf)


def refit_free(free: str) -> str:
    """The free parameters of a candidate's confirmation refit, given the diagnosis's
    ``free``: those and every effect's (the screen simulates the candidate through the
    same parametrisation, so that both share one compiled residual function)."""
    return f"{free},effects"


def _bic(chi2: float, k: int, n: int, infl: float) -> float:
    n_eff = n / infl
    return chi2 / infl + k * math.log(n_eff)


def diagnose(
    logs: Sequence[Log],
    validate_logs: Sequence[Log] = (),
    *,
    base_effects: Sequence[str] = (),
    base: FitResult | None = None,
    free: str = "all",
    init: Mapping[str, float] | None = None,
    n_confirm: int | None = None,
    z_threshold: float = 3.0,
    bic_threshold: float = 10.0,
    n_starts: int = 2,
    seed: int = 0,
    workers: int | None = None,
    progress: Callable[[str], None] | None = None,
) -> Diagnosis:
    """Fit the model (baseline + ``base_effects``, from ``init`` or nominal values)
    unless ``base`` is given, screen every other candidate effect, confirm by refits
    the screened ones whose ``z`` exceeds ``z_threshold`` (all of them, or the best
    ``n_confirm``), and give the verdict.

    Confirming every significant candidate, not only the top of the screen: once one
    effect is in the model the remaining misfit is small and every candidate's score
    is significant (measured on the shipped data: z 7-14 for all seven, the hidden
    one last), so only the refits can tell them apart.

    The refits run on ``workers`` threads (default: one per CPU core); the result does
    not depend on it."""
    say = progress or (lambda _s: None)
    validate_logs, excluded = usable_heldout(logs, validate_logs)
    for name, why in excluded.items():
        say(f"held-out log {name} not used: {why}")
    if base is None:
        say(f"fitting the model (effects: {', '.join(base_effects) or 'none'})")
        base = fit(logs, effects=base_effects, free=free, init=init, staged=True,
                   n_starts=n_starts, seed=seed, workers=workers, progress=progress)  # fmt: skip
    if not math.isfinite(base.chi2):
        why = f"the fit of the model ({', '.join(base.effects) or 'baseline'}) failed: "
        why += "; ".join(st.message for st in base.stages)
        say(f"undecided: {why}")
        return Diagnosis("undecided", [], list(base.effects), base.chi2, base.n_residuals,
                         base.inflation, base, None, reasons=[why],
                         heldout_excluded=excluded)  # fmt: skip
    ranking = screen_effects(base, logs, workers=workers, free=free)
    say("score screens: " + ", ".join(f"{s.effect} z={s.z:.1f}" for s in ranking))
    n_held = sum(e.n_residuals for e in make_experiments(validate_logs))
    bic0 = _bic(base.chi2, len(base.free), base.n_residuals, base.inflation)
    misfit = remaining_misfit(base)
    excess = base.chi2 - base.n_residuals  # the error above the sensor-noise floor
    to_confirm = [s for s in ranking if s.z > z_threshold][:n_confirm]  # None: all
    held_before: list = []  # the current model's held-out error, computed once
    partial: list[tuple[EffectScreen, FitResult]] = []  # one test short (below)

    def confirm(to_confirm: list[EffectScreen]) -> list[tuple[EffectScreen, FitResult]]:
        """Refit each candidate from its starts; the ones that pass both tests."""
        guesses = {s.effect: refit_starts(s.effect, s.predicted_value) for s in to_confirm}
        # every candidate's first start before any second one: two threads on the two
        # starts of one candidate would wait on the same compilation
        most = max((len(g) for g in guesses.values()), default=0)
        jobs = [
            (s, guesses[s.effect][k])
            for k in range(most)
            for s in to_confirm
            if len(guesses[s.effect]) > k
        ]
        # and the starts an effect reads from the logs (AbstractEffect.starts_from_logs;
        # None here: found in the refit's thread), after every candidate's first start
        jobs[len(to_confirm) : len(to_confirm)] = [(s, None) for s in to_confirm]

        def best_refit(
            effect: str, starts: Sequence[Mapping[str, float]], synchronise: Sequence[float] = ()
        ) -> FitResult:
            """The best of one refit from each start, the base's parameters elsewhere;
            ``synchronise``: after fits pulled towards the data (:func:`fit`)."""
            best = None
            for start in starts:
                one = fit(logs, effects=[*base.effects, effect], free=refit_free(free),
                          init={**base.params, **start}, staged=False, n_starts=1,
                          seed=seed, workers=1, synchronise=synchronise)  # fmt: skip
                if best is None or one.chi2 < best.chi2:
                    best = one
            return best

        def refit(job) -> tuple[FitResult | None, float | None, str | None]:
            if job is None:  # the current model's held-out error
                if held_before:
                    return None, held_before[0], None
                return None, _heldout_chi2(base.params, base.effects, validate_logs), None
            s, guess = job
            where = (
                "the logs" if guess is None else ", ".join(f"{k} = {v:g}" for k, v in guess.items())
            )
            try:
                if guess is None:
                    run = log_simulator(base.params, [*base.effects, s.effect], logs)
                    found = EFFECTS[s.effect].starts_from_logs(logs, base.params, run)
                    if not found:
                        return None, None, None  # the effect reads none from these logs
                else:
                    found = [guess]
                # from the base's parameters, the initial-height offsets from 0 (starting
                # them at the base's was measured: no fewer trials, other local minima;
                # docs/statistics.md, "Confirm: refits")
                # the best refit from the start(s): stick-slip reads up to two
                res = best_refit(s.effect, found)
                if guess is None:
                    where = "the logs: " + "; ".join(
                        ", ".join(f"{k} = {v:.4g}" for k, v in start.items()) for start in found
                    )
                    if not res.chi2 <= base.chi2:
                        # every read start ended above the model without the effect,
                        # which the model with it contains: local minima. Fit them again
                        # after fits pulled towards the data, as jaxlift fit does when its
                        # read starts end above the noise floor (READ_SYNC_GAINS).
                        # Detection case_010 (1.7 kN breakaway): the read starts refitted
                        # to chi2/N 15.7 and 19.6 against the baseline's 9.14; pulled,
                        # the first reached 2.10 (docs/statistics.md, "Confirm: refits")
                        say(
                            f"confirm {s.effect}: its starts read from the logs ended above "
                            "the model without it; fitting them again after fits pulled "
                            "towards the data"
                        )
                        pulled = best_refit(s.effect, found, READ_SYNC_GAINS)
                        where += " (fitted again after fits pulled towards the data)"
                        if pulled.chi2 < res.chi2 or not math.isfinite(res.chi2):
                            res = pulled
                if not math.isfinite(res.chi2):
                    return None, None, f"refit from {where}: every start failed"
                # held-out error of this refit here, in the same thread: its compilation (a
                # new model structure) then overlaps the other refits
                return res, _heldout_chi2(res.params, res.effects, validate_logs), None
            except Exception as err:  # noqa: BLE001 -- one candidate's failure, reported
                return None, None, f"refit from {where}: {type(err).__name__}: {err}"

        # the refits are independent: one thread per core (_parallel.py)
        say(f"confirming {len(to_confirm)} candidates by {len(jobs)} refits")
        bests: dict[str, tuple[FitResult, float | None]] = {}
        failures: dict[str, list[str]] = {}
        results = thread_map(refit, [None, *jobs], workers)
        _, heldout_before, _ = next(results)
        held_before[:] = [heldout_before]
        for (s, _), (res, held, err) in zip(jobs, results):
            if err is not None:
                failures.setdefault(s.effect, []).append(err)
            elif res is None:  # no start read from the logs
                continue
            elif s.effect not in bests or res.chi2 < bests[s.effect][0].chi2:
                bests[s.effect] = (res, held)
        passing = []
        for s in to_confirm:
            infos = EFFECTS[s.effect].param_infos()
            if s.effect not in bests:
                s.failure = "; ".join(failures.get(s.effect, ["no refit"]))
                say(f"confirm {s.effect}: failed ({s.failure})")
                continue
            best, heldout_after = bests[s.effect]
            bic1 = _bic(best.chi2, len(best.free), best.n_residuals, base.inflation)
            s.confirmed_chi2 = best.chi2
            s.delta_bic = bic1 - bic0
            s.fitted_params = {k: best.params[k] for k in infos}
            s.fitted_stderr = {k: best.stderr[k] for k in infos if k in best.stderr}
            if best.chi2 > base.chi2:
                # the model with the effect contains the one without (at the nesting
                # value), so every refit ended in a local minimum: say so, and give no
                # standard errors of a point that is not an optimum (measured: 1e-72)
                s.fitted_stderr = None
                s.failure = (
                    f"every refit ended above the model without it (chi2/N "
                    f"{best.chi2 / best.n_residuals:.4g} > {base.chi2 / base.n_residuals:.4g}):"
                    " local minima, not the optimum"
                )
            s.heldout_chi2_before = heldout_before
            s.heldout_chi2_after = heldout_after
            say(
                f"confirm {s.effect}: chi2/N {base.chi2 / base.n_residuals:.3g} -> "
                f"{best.chi2 / best.n_residuals:.3g}, dBIC {s.delta_bic:.1f}"
            )
            # the held-out logs must be predicted better, by more than their noise: the
            # chi2 drop over the held-out samples, counted as effective samples like the BIC,
            # beyond the same threshold (a spurious extra effect moves it by a few units, a
            # real one by hundreds to thousands; measured on the test matrix)
            held_ok = (
                s.heldout_chi2_after is None
                or s.heldout_chi2_before is None
                or _held_out_change(s, n_held, base.inflation) < -bic_threshold
            )
            s.explained_share = (base.chi2 - best.chi2) / excess if excess > 0 else None
            # material: when the error is far above the noise, a candidate must remove a
            # real part of it. Over tens of thousands of samples, any extra parameter
            # passes the BIC by bending the model a little towards a law that is none of
            # the candidates (measured: a seal friction growing with pressure, chi2/N
            # 2.88, "confirmed" stick_slip at 2.86, dBIC -150): that is a stand-in, not
            # the missing effect. A real one, alone or the larger of two, removes most
            # (MIN_SHARE).
            material = not misfit.significant or (
                s.explained_share is not None and s.explained_share >= MIN_SHARE
            )
            if s.delta_bic < -bic_threshold and held_ok != material:
                # one test short: possibly one of two missing effects (the lookahead of
                # diagnose_iteratively). Measured (detection study, case_014: hose
                # compliance beside a 13 ms input delay): hose compliance removed 95 %
                # of the fitted error, dBIC -9253, but the held-out log's error came
                # from the delay (chi2/N 19.3 -> 19.5 with hose compliance alone)
                if held_ok:
                    s.not_kept = (
                        f"removes only {s.explained_share or 0:.1%} of the error above the "
                        f"noise (needs {MIN_SHARE:.0%})"
                    )
                else:
                    s.not_kept = (
                        f"removes {s.explained_share or 0:.0%} of the error but predicts the "
                        f"held-out logs no better (chi2/N {s.heldout_chi2_before:.4g} -> "
                        f"{s.heldout_chi2_after:.4g})"
                    )
                say(f"confirm {s.effect}: {s.not_kept}: not kept")
                partial.append((s, best))
            if s.delta_bic < -bic_threshold and held_ok and material:
                passing.append((s, best))
        return passing

    passing = confirm(to_confirm)
    rest = [s for s in ranking if s not in to_confirm and math.isfinite(s.z)]
    if not passing and misfit.significant and rest and n_confirm is None:
        # the screen is local (a secant near the nesting value, against s^2 that holds
        # the model error): with an error this far above the noise it can miss an
        # effect that is large (measured: breakaway friction of 1.7 kN scored z = -1.9,
        # the error chi2/N 9.1; a stick-slip with a mast mode, chi2/N 3.5, every z < 3).
        # When no screened candidate passes, the others are refitted from their grids
        # too, and the refits' BIC and held-out checks decide as always
        say(
            f"nothing passed, but the error is far above the noise ({misfit.describe()}): "
            f"confirming the other {len(rest)} candidates by refits, whatever their score"
        )
        passing = confirm(rest)
    winner, between, reasons = decide(
        [s for s, _ in passing], bic_threshold, n_held, base.inflation
    )
    winner_fit = next((f for s, f in passing if s.effect == winner), None)
    undecided_fits = [f for name in between for s, f in passing if s.effect == name]
    if winner == "undecided":
        say("undecided: " + "; ".join(reasons))
    elif reasons:  # a winner the held-out logs decided
        say(reasons[0])
    confirmed = [s for s in ranking if s.delta_bic is not None]
    rest = [s for s in ranking if s.delta_bic is None]
    ranking = sorted(confirmed, key=lambda s: s.delta_bic) + rest
    return Diagnosis(
        verdict=winner,
        ranking=ranking,
        base_effects=list(base.effects),
        base_chi2=base.chi2,
        n_residuals=base.n_residuals,
        inflation=base.inflation,
        base_fit=base,
        winner_fit=winner_fit,
        undecided_between=between,
        reasons=reasons,
        heldout_excluded=excluded,
        partial=sorted(partial, key=lambda sb: sb[0].delta_bic),
        undecided_fits=undecided_fits,
    )


#: Samples [-] a log must spend lifting (duty > 0) in a stage for the stage's motor
#: parameters to be determined by it: 1 s at 100 Hz.
MIN_LIFT_SAMPLES_PER_STAGE = 100


def lifted_stages(log: Log) -> set[int]:
    """The mast stages (1, 2, 3) through which ``log`` lifts for at least
    :data:`MIN_LIFT_SAMPLES_PER_STAGE` samples (duty > 0)."""
    stages = np.asarray(stage_of(log.height_m))[np.asarray(log.pwm) > 0]
    counts = {k: np.count_nonzero(stages == k) for k in (1, 2, 3)}
    return {k for k, c in counts.items() if c >= MIN_LIFT_SAMPLES_PER_STAGE}


def usable_heldout(
    logs: Sequence[Log], validate_logs: Sequence[Log]
) -> tuple[list[Log], dict[str, str]]:
    """The held-out logs that can judge a model fitted on ``logs``, and why the others
    cannot: a held-out log that lifts through a mast stage no fitted log lifts through
    is predicted with that stage's motor parameters (``k``, ``z`` of the stage) left
    at whatever the fit made of them -- undetermined -- so its error says nothing about
    the effects (measured: a null case fitted on two mid-mast logs had held-out chi2/N
    6 449 on a log from the bottom stop; a true effect's refit moved it at random)."""
    seen = set().union(*(lifted_stages(lg) for lg in logs)) if logs else set()
    keep, excluded = [], {}
    for lg in validate_logs:
        new = sorted(lifted_stages(lg) - seen)
        if new:
            excluded[lg.name] = (
                f"it lifts through stage(s) {', '.join(map(str, new))}, which no fitted log "
                "lifts through (that stage's motor parameters are not determined by the fit)"
            )
        else:
            keep.append(lg)
    return keep, excluded


#: Model error, as a share of the sensor-noise variance, below which what remains is
#: not worth a name: chi2/N - 1 < 0.2, an RMS model error below 45 % of the noise.
MIN_EXCESS = 0.2


#: The share of the error above the noise a candidate must remove to be kept, when that
#: error is significant (:func:`remaining_misfit`); see ``diagnose``. Measured stand-ins
#: for laws outside the eight removed 1 % (stick_slip for a pressure-dependent seal
#: friction), 5 % (a mast mode) and 21 % (hose compliance for a quadratic drag); a
#: hidden candidate alone removes nearly all, the larger of two about half or more.
MIN_SHARE = 0.25


@dataclasses.dataclass
class RemainingMisfit:
    """The error a model leaves, against the sensor-noise floor (chi2/N = 1 for a
    model that is right: residuals are scaled by the sensor noise).

    ``z`` is the excess ``chi2/N - 1`` in standard errors, ``sqrt(2 infl / N)``: a sum
    of N squared standard normals, counted in effective samples (``infl`` the AR(1)
    inflation of the residuals, as for the BIC). ``significant``: the excess is at
    least :data:`MIN_EXCESS` and ``z`` at least ``z_threshold``, on the fitted logs
    and (where there are usable held-out logs) on the held-out ones."""

    chi2n: float
    n: int
    inflation: float
    z: float
    heldout_chi2n: float | None
    heldout_n: int
    heldout_inflation: float | None
    heldout_z: float | None
    significant: bool

    def as_dict(self) -> dict:
        return dataclasses.asdict(self)

    def describe(self) -> str:
        held = ""
        if self.heldout_chi2n is not None:
            held = f"; held-out chi2/N {self.heldout_chi2n:.3g} (z = {self.heldout_z:.1f})"
        return (
            f"fitted chi2/N {self.chi2n:.3g} (noise floor 1; z = {self.z:.1f} with "
            f"{self.n / self.inflation:.0f} effective samples){held}"
        )


def _excess_z(chi2n: float, n: int, infl: float) -> float:
    return (chi2n - 1.0) / math.sqrt(2.0 * infl / max(n, 1))


def remaining_misfit(
    model: FitResult,
    validate_logs: Sequence[Log] = (),
    *,
    min_excess: float = MIN_EXCESS,
    z_threshold: float = 3.0,
) -> RemainingMisfit:
    """Is the error that ``model`` leaves more than the sensor noise? (see
    :class:`RemainingMisfit`). Held-out logs are predicted at their own
    initial-height offsets, estimated under the model."""
    n = model.n_residuals
    chi2n = model.chi2 / n
    z = _excess_z(chi2n, n, model.inflation)
    sig = chi2n - 1.0 >= min_excess and z >= z_threshold
    h_chi2n = h_infl = h_z = None
    h_n = 0
    if validate_logs:
        r, sizes, experiments = heldout_residuals(model.params, model.effects, validate_logs)
        if r is None:
            h_chi2n, h_z, h_infl = math.inf, math.inf, 1.0
        else:
            rho = pooled_rho1(r, sizes, experiments)
            h_n, h_infl = r.size, (1 + rho) / max(1 - rho, 1e-3)
            h_chi2n = float(r @ r) / r.size
            h_z = _excess_z(h_chi2n, h_n, h_infl)
        sig = sig and h_chi2n - 1.0 >= min_excess and h_z >= z_threshold
    return RemainingMisfit(chi2n, n, model.inflation, z, h_chi2n, h_n, h_infl, h_z, bool(sig))


def refit_starts(effect: str, screen_estimate: float) -> list[dict[str, float]]:
    """Starting values of the confirmation refits of ``effect`` (its parameters only):
    the screen's Gauss--Newton estimate of the switch parameter, kept inside the
    effect's typical range (:attr:`~jaxlift.ParamInfo.typical`: the sizes a real
    vehicle can have), then a log-spaced grid over that range (low end, geometric
    middle, high end), each grid point paired with the same position in the range of
    the effect's second parameter where it has one (``v_s``, ``c_s``; those effects
    also start from the range's quartiles with the second parameter nominal). A grid point
    within a factor 2 of an earlier start is left out. The score says where the optimum
    is near the nesting value; the grid lets a refit reach it from anywhere in the
    range, whatever the true size."""
    infos = EFFECTS[effect].param_infos()
    par = switch_parameter(effect)
    info = infos[par]
    scale = info.scale or 1.0
    lo, hi = info.typical or (0.1 * scale, 10.0 * scale)
    est = screen_estimate if math.isfinite(screen_estimate) else math.sqrt(lo * hi)
    starts = [{par: min(max(est, lo), hi)}]
    seconds = [(n, i.typical) for n, i in infos.items() if n != par and i.typical]
    for q in (0.0, 0.5, 1.0):
        v = _log_between(lo, hi, q)
        if any(abs(math.log(v / st[par])) < math.log(2.0) for st in starts):
            continue
        starts.append({par: v, **{n: _log_between(a, b, q) for n, (a, b) in seconds}})
    if seconds:
        # two-parameter effects: also the quartiles of the range with the second
        # parameter at its nominal value. Their chi2 surface is rough (stick-slip:
        # on the shipped logs the refits from 20 N/2 mm/s, 200 N/7.7 mm/s and
        # 2 kN/30 mm/s all stalled at chi2/N 3.8-9.9, the one from 63 N/10 mm/s
        # reached 1.2), so a grid of three paired points is too coarse.
        for q in (0.25, 0.75):
            v = _log_between(lo, hi, q)
            if not any(abs(math.log(v / st[par])) < math.log(2.0) for st in starts):
                starts.append({par: v})
    return starts


def _log_between(lo: float, hi: float, q: float) -> float:
    """The point a fraction ``q`` of the way from ``lo`` to ``hi`` on a log scale."""
    return math.exp(math.log(lo) + q * (math.log(hi) - math.log(lo)))


def decide(
    passing: Sequence[EffectScreen],
    bic_threshold: float = 10.0,
    n_held: int = 0,
    inflation: float = 1.0,
) -> tuple[str, list[str], list[str]]:
    """The verdict from the candidates that passed both tests (BIC drop beyond
    ``bic_threshold`` and the held-out check): ``(verdict, undecided_between, reasons)``.

    ``"none"`` if none passed; the best one if it beats the runner-up by at least
    ``bic_threshold``; else ``"undecided"`` between the two, with the evidence for each
    and an experiment that would separate them.

    When the fitted logs leave the best two within the threshold, the held-out logs
    (``n_held`` residuals, at the fit's autocorrelation ``inflation``) add their
    evidence: each candidate's held-out chi2 change, counted as effective samples like
    the BIC (:func:`held_out_evidence`). That is the second factor of the evidence of
    all the logs, p(fitted, held-out) = p(fitted) p(held-out | fitted), so the sum
    ranks the candidates on everything measured; if it separates them by the
    threshold, the better one is the verdict and the reasons say that the held-out
    logs decided. (Measured, detection study case_014: after hose compliance, a 13 ms
    input delay and a 13 ms motor lag 1.4 apart in BIC on the fitted logs; the held-out
    log, 22 776 residuals, preferred the delay, the truth, by 185: 186.7 in all.) A
    decision the fitted logs make alone is never overturned: they are what the refits
    minimised."""
    ranked = sorted(passing, key=lambda s: s.delta_bic)
    if not ranked:
        return "none", [], []
    if len(ranked) == 1 or ranked[1].delta_bic - ranked[0].delta_bic >= bic_threshold:
        return ranked[0].effect, [], []
    close = [s for s in ranked if s.delta_bic - ranked[0].delta_bic < bic_threshold]
    held = [held_out_evidence(s, n_held, inflation) for s in close]
    if len(close) >= 2 and all(h is not None for h in held):
        total = sorted(zip(close, held), key=lambda sh: sh[0].delta_bic + sh[1])
        (a, ha), (b, hb) = total[:2]
        margin = (b.delta_bic + hb) - (a.delta_bic + ha)
        if margin >= bic_threshold:
            return (
                a.effect,
                [],
                [
                    f"{a.effect} decided by the held-out logs: on the fitted logs {a.effect} and "
                    f"{b.effect} were {abs(b.delta_bic - a.delta_bic):.1f} apart in BIC (a "
                    f"decision needs {bic_threshold:g}); the held-out logs' evidence "
                    f"({ha:.1f} and {hb:.1f}) puts {a.effect} ahead by {margin:.1f} in all",
                    *(_evidence(s) for s in (a, b)),
                ],
            )
    a, b = ranked[:2]
    reasons = [
        f"{a.effect} and {b.effect} explain the data almost equally well: dBIC "
        f"{a.delta_bic:.1f} and {b.delta_bic:.1f}, {b.delta_bic - a.delta_bic:.1f} apart "
        f"(a decision needs {bic_threshold:g})",
        *(_evidence(s) for s in (a, b)),
        "to separate them: " + separating_experiment(a.effect, b.effect),
    ]
    return "undecided", [a.effect, b.effect], reasons


def held_out_evidence(s: EffectScreen, n_held: int, inflation: float) -> float | None:
    """The held-out logs' evidence for candidate ``s`` [chi2 units, negative = for it]:
    the change of their chi2 with the effect, ``(after - before) * n_held``, over the
    autocorrelation ``inflation`` (effective samples, as in the BIC and the held-out
    check); None without held-out logs or a held-out error."""
    if n_held <= 0 or s.heldout_chi2_before is None or s.heldout_chi2_after is None:
        return None
    if not (math.isfinite(s.heldout_chi2_before) and math.isfinite(s.heldout_chi2_after)):
        return None
    return _held_out_change(s, n_held, inflation)


def _held_out_change(s: EffectScreen, n_held: int, inflation: float) -> float:
    """``(after - before) * n_held / inflation`` of the held-out chi2 per sample, in
    effective samples. A failed held-out simulation is an infinite chi2: with the effect,
    +inf or NaN, so the held-out check fails; without it only, -inf."""
    return (s.heldout_chi2_after - s.heldout_chi2_before) * n_held / inflation


def _evidence(s: EffectScreen) -> str:
    held = ""
    if s.heldout_chi2_before is not None and s.heldout_chi2_after is not None:
        held = f", held-out chi2/N {s.heldout_chi2_before:.3g} -> {s.heldout_chi2_after:.3g}"
    sizes = ", ".join(
        f"{k} = {v:.3g}"
        + (f" ± {s.fitted_stderr[k]:.2g}" if s.fitted_stderr and k in s.fitted_stderr else "")
        for k, v in (s.fitted_params or {}).items()
    )
    return f"{s.effect}: dBIC {s.delta_bic:.1f}{held}; fitted {sizes}"


#: Experiments that separate two candidate effects the data cannot tell apart.
SEPARATING_EXPERIMENTS: dict[frozenset[str], str] = {
    frozenset({"hose_compliance", "entrained_air"}): (
        "slow runs at two loads (a light and a heavy one) and at two heights: air softens "
        "the oil mostly at low pressure, hose compliance does not depend on pressure"
    ),
    frozenset({"motor_inertia", "input_delay"}): (
        "steps of the duty from rest, of several sizes: a delay shifts the response by a "
        "fixed time, a motor lag rounds it with a time constant"
    ),
    frozenset({"leakage", "motor_droop"}): (
        "a long hold with the valve shut at a heavy load: only leakage lets the fork sink"
    ),
    frozenset({"mast_compliance", "hose_compliance"}): (
        "the same slow run with a light and a heavy load: the mast's spring frequency falls "
        "with the load mass, the hydraulic one with the oil volume (height)"
    ),
    frozenset({"mast_compliance", "entrained_air"}): (
        "the same slow run with a light and a heavy load at two heights: the mast's spring "
        "depends on the load mass, air on the pressure"
    ),
}


def separating_experiment(a: str, b: str) -> str:
    """A test run that would tell effect ``a`` from effect ``b``."""
    if "stick_slip" in (a, b):  # slow runs show a breakaway force, whatever the other is
        return EFFECTS["stick_slip"].revealing_run
    return SEPARATING_EXPERIMENTS.get(
        frozenset({a, b}),
        "a run in the regime where the two fitted models' predictions differ most (compare "
        "their simulated speed on the logs, e.g. with `jaxlift fit --effects`)",
    )


def _heldout_chi2(params: Mapping[str, float], effects, validate_logs) -> float | None:
    """Mean chi2/N over the held-out logs, each at its own initial-height offset
    estimated under this model (``_fit.offsets_and_chi2n``); None without held-out
    logs, inf if the model cannot be simulated on them."""
    if not validate_logs:
        return None
    _, chi2n = offsets_and_chi2n(params, effects, validate_logs)
    return float(np.mean(list(chi2n.values()))) if chi2n else math.inf


#: :func:`diagnose_iteratively`: how many steps may be repeated because their newcomer
#: was dropped again (it only completed the fit of the model without it)
MAX_REPEATS = 2


def diagnose_iteratively(
    logs: Sequence[Log],
    validate_logs: Sequence[Log] = (),
    *,
    max_effects: int = 3,
    bic_threshold: float = 10.0,
    base: FitResult | None = None,
    progress: Callable[[str], None] | None = None,
    lookahead: bool = True,
    cross_validation: bool = True,
    **kwargs,
) -> list[Diagnosis]:
    """Diagnose, add the winner, diagnose again, until the verdict is ``none`` (or
    ``undecided``: then the last step says between which effects, and why). When it
    ends on ``none`` and the final model still leaves an error well above the sensor
    noise (:func:`remaining_misfit`, on fitted and held-out logs), the last verdict is
    ``unexplained``: something none of the candidates describes is missing.

    After each addition the effects added earlier are checked backwards: each is
    removed in turn and the model refitted; if the BIC grows by less than
    ``bic_threshold`` without it, the newcomer explains its part of the data and it is
    dropped (recorded in :attr:`Diagnosis.dropped`). Forward selection alone keeps an
    effect that was chosen early because it mimicked the real one (a pure delay for a
    motor lag). Then the newcomer itself is checked the same way: if the model without
    it, refitted from its refit's values, fits as well (BIC change below
    ``bic_threshold``), the step's base fit had not reached its optimum and the
    newcomer only completed it; it is dropped (also in :attr:`Diagnosis.dropped`, of
    the step that named it) and the step is repeated from that better fit.

    ``base``: a fit of the first step's model (its effects are the starting model),
    instead of fitting it here.

    ``lookahead``: when the iteration would end ``unexplained`` and a candidate passed
    the BIC but failed one of the other two tests (:attr:`Diagnosis.partial`: it removed
    too small a share of the error -- the smaller of two missing effects looks like this
    while the larger is not in the model -- or it did not predict the held-out logs
    better, where their error comes from the other missing effect), the one with the
    largest BIC drop is added provisionally and the iteration goes on from there. It
    is kept only if the iteration then ends at the sensor-noise floor (``none`` with
    no significant misfit, or ``undecided`` between two candidates the better of which
    leaves no significant misfit); otherwise the first ending stands and the attempt is
    recorded in :attr:`Diagnosis.lookahead`. A stand-in for a law outside the eight
    does not reach the noise floor with any second candidate, so it is still not
    named.

    ``cross_validation``: when it would still end ``unexplained`` and a candidate
    removed most of the error but failed the held-out check, that candidate gets a
    second look (:func:`cross_validate`): refits from the further starts it reads from
    the logs, then, if one of them removes nearly all of the fitted logs' error, a
    cross-validation with the held-out logs among the fitted ones. If the candidate
    predicts every left-out log far better than the model without it, it is named (its
    values are not determined by the fitted logs alone), and the iteration ends there:
    the held-out logs, now needed to fix its values, cannot judge a further candidate.
    The final verdict still says ``unexplained`` where the error left on the held-out
    logs is significant."""
    say = progress or (lambda _s: None)
    steps: list[Diagnosis] = []
    effects: list[str] = [] if base is None else list(base.effects)
    repeated = 0  # steps repeated after their newcomer was dropped again (below)

    def drop_one(d: Diagnosis, candidates: list[str]) -> str | None:
        """Refit without each of ``candidates`` (:func:`backward_check`); where the
        best of them changes the BIC by less than ``bic_threshold``, drop it from
        ``effects`` and the step ``d``'s record, move ``base`` to the reduced fit and
        return its name (else None)."""
        nonlocal effects, base
        drop = backward_check(base, logs, candidates, kwargs.get("free", "all"),
                              kwargs.get("seed", 0), kwargs.get("workers"))  # fmt: skip
        if drop is None or drop[1] >= bic_threshold:
            return None
        name, dbic, base = drop
        d.dropped[name] = dbic
        effects = [e for e in effects if e != name]
        return name

    while len(steps) < max_effects + 1 + repeated:
        d = diagnose(logs, validate_logs, base_effects=effects, base=base, progress=progress,
                     bic_threshold=bic_threshold, **kwargs)  # fmt: skip
        steps.append(d)
        if d.verdict in NOT_AN_EFFECT:  # nothing (more) to add
            break
        effects = [*effects, d.verdict]
        base = d.winner_fit

        while len(effects) > 1 and (name := drop_one(d, effects[:-1])) is not None:
            say(f"backward check: without {name} BIC changes by {d.dropped[name]:+.1f}: dropped")
        # and the newcomer itself, after the earlier ones (so that it is not dropped in
        # favour of one that only mimicked it): refitted without it from its refit's
        # values, does the model fit as well? Then the step's base fit had not reached
        # its own optimum, and the newcomer's refit only completed that fit, which the
        # BIC and the held-out logs credited to the effect. Measured (detection study,
        # case_092, motor droop and leakage hidden, library 992621e): the model with
        # both ended at chi2/N 1.0064 and 0.9998 (held-out 1.0136) where another
        # library's fit of the same logs reached 1.0058 and 0.9990 (held-out 0.9983);
        # the next step's input_delay and motor_inertia both took it there ("chi2/N
        # 1 -> 1", dBIC -23.8 and -23.0) and the held-out logs named input_delay. The
        # step is then repeated from the better fit; it does not count against
        # max_effects. Each repeat starts from a fit whose BIC is lower than the base's
        # before (within the threshold of the newcomer's, which was below that by more),
        # and at most MAX_REPEATS are made: after them a newcomer is kept as before.
        if repeated < MAX_REPEATS and (name := drop_one(d, [d.verdict])) is not None:
            say(
                f"backward check: refitted without {name} from its values, BIC changes by "
                f"{d.dropped[name]:+.1f}: the model without it had not reached its "
                f"optimum; {name} dropped, the step repeated from the better fit"
            )
            repeated += 1
    last = steps[-1]
    # (an effect dropped again by the backward check counts, as it always has; a
    # newcomer dropped again does not: its step was repeated)
    room = max_effects - len(found_effects(steps)) + repeated
    misfit0 = None  # the final model's misfit when it ends on none (computed once)
    if lookahead and last.verdict == "none" and last.partial and room >= 2:
        usable, _ = usable_heldout(logs, validate_logs)
        misfit0 = remaining_misfit(last.base_fit, usable)
        if misfit0.significant:
            s0, fit0 = last.partial[0]
            say(f"lookahead: {s0.effect} {s0.not_kept}; adding it provisionally")
            more = diagnose_iteratively(
                logs, validate_logs, max_effects=room - 1, bic_threshold=bic_threshold,
                base=fit0, progress=progress, lookahead=False, cross_validation=False,
                **kwargs,
            )  # fmt: skip
            ends = final_verdict(more)
            after = [
                e for d in more if (e := d.verdict) not in NOT_AN_EFFECT and e not in d.dropped
            ]
            if ends == "undecided" and more[-1].undecided_fits:
                # the second effect is there, only which of two candidates it is cannot
                # be told (measured, case_014: after hose compliance, a 13 ms input delay
                # and a 13 ms motor lag 1.4 apart in BIC, both taking the held-out
                # chi2/N from 19.5 to 1.0): judged by what the better of the two leaves
                reached = not remaining_misfit(more[-1].undecided_fits[0], usable).significant
                after = [*after, " or ".join(more[-1].undecided_between) + " (undecided which)"]
            else:
                reached = ends == "none" and bool(after)
            if reached:
                last.verdict, last.winner_fit = s0.effect, fit0
                later = ", ".join(after)
                alone = f"{s0.effect} alone {s0.not_kept}"
                if any(s0.effect in m.dropped for m in more):
                    # a stepping stone: with it the larger effect was found, which then
                    # explained its part too (the backward check of the later step)
                    why = (
                        f"{alone}; added provisionally, with it {later} was "
                        f"found, which then made {s0.effect} unnecessary (dropped)"
                    )
                else:
                    why = (
                        f"{alone}; kept because with it {later} was found and "
                        "the error reached the sensor-noise floor"
                    )
                last.reasons = [why]
                say("lookahead: " + last.reasons[0])
                return [*steps, *more]
            why = (
                f"{s0.effect} ({s0.not_kept}) was added provisionally; the iteration then ended "
                f"{ends} after {', '.join(after) or 'nothing'}"
                ", not at the noise floor: not kept"
            )
            last.lookahead.append(why)
            say("lookahead: " + why)
    if cross_validation and last.verdict == "none" and last.partial and room >= 1:
        # about to end unexplained, with a candidate that removed most of the fitted
        # logs' error but failed the held-out check: are its values merely not fixed by
        # the fitted logs? (detection case_093 by hand: one slipping section; case_087,
        # mast compliance, named by it in the study)
        usable, _ = usable_heldout(logs, validate_logs)
        if usable:
            if misfit0 is None:
                misfit0 = remaining_misfit(last.base_fit, usable)
            if misfit0.significant:
                found = cross_validate(
                    last, logs, usable, bic_threshold=bic_threshold,
                    free=kwargs.get("free", "all"), seed=kwargs.get("seed", 0),
                    workers=kwargs.get("workers"), progress=progress,
                )  # fmt: skip
                if found is not None:
                    s0, fit0 = found
                    last.verdict, last.winner_fit = s0.effect, fit0
                    last.reasons = list(last.cross_validation)
                    misfit0 = None
    named = last.verdict not in NOT_AN_EFFECT  # the loop ran out of steps on a name
    if last.verdict == "none" or named:
        usable, _ = usable_heldout(logs, validate_logs)
        final_model = last.winner_fit if named else last.base_fit
        last.misfit = (
            misfit0 if misfit0 is not None and not named else remaining_misfit(final_model, usable)
        )
        if last.misfit.significant:
            if not named:
                last.verdict = "unexplained"
            last.reasons = [
                "none of the candidate effects explains what remains: "
                + last.misfit.describe()
                + "; see where it remains (report) and docs/effects.md to add your own"
            ]
            partial = [
                f"{d.verdict} ({100 * d.explained_share():.0f} % of the model error)"
                for d in (steps if named else steps[:-1])
                if d.explained_share() is not None
            ]
            if partial:
                last.reasons.append(
                    "the effects added on the way, " + ", ".join(partial) + ", lower the "
                    "error but leave it well above the sensor noise: they may stand in "
                    "for what is missing rather than be it"
                )
            last.reasons.extend(last.lookahead)
            last.reasons.extend(last.cross_validation)
            # the candidate that came closest (one test short, the largest BIC drop) may
            # still be there, hidden by what is missing beside it or by logs that barely
            # show it (detection study case_093: a 601 N breakaway force removed 49 % of
            # the error, but one slipping section could not place it, and the held-out
            # log got worse): say which run would show it plainly. Only that one: for a
            # law outside the eight most candidates are one test short (measured,
            # tests/test_unexplained.py's drag: six of seven, 3-24 % each)
            closest = None if named or not last.partial else last.partial[0][0]
            if closest is not None and (run := EFFECTS[closest.effect].revealing_run):
                # unless the logs already hold that run: then asking for it again sends
                # the user in a circle (measured, studies/DETECTION.md: case_093 with
                # three slow sections that stick and slip added to its fitted logs ended
                # unexplained again, the refits from nominal values out of the optimum's
                # reach)
                seen = EFFECTS[closest.effect].revealed_in(logs)
                said = f"the candidate that came closest, {closest.effect}, {closest.not_kept}; "
                if seen is None:
                    last.reasons.append(said + f"a run that would show whether it is there: {run}")
                else:
                    last.reasons.append(
                        said + "the fitted logs already hold the run that "
                        f"shows it ({seen}), so it may be there but out of reach of the "
                        "refits from nominal values (a rough least-squares surface: their "
                        "best fit is not the optimum); compare the model with the "
                        "measurement on those sections, or fit the model with it "
                        f"(`jaxlift fit --effects {closest.effect}`) from starting values "
                        "of your own (`--params`)"
                    )
            for line in last.reasons:
                say("unexplained: " + line)
    return steps


#: :func:`cross_validate`: the share of the fitted logs' error above the noise that the
#: candidate's best refit must remove before it is cross-validated ("nearly all": a
#: hidden candidate alone removes nearly all, stand-ins for laws outside the eight
#: 1-21 %, :data:`MIN_SHARE`), and the share of the model's error on each left-out log
#: (chi2/N above 1) its prediction must remove. Measured on detection case_093 (601 N
#: breakaway, one slipping section, by hand): 100 % on the fitted logs; 97 % and 86 % of
#: the left-out logs'; case_087 (mast compliance, in the study's call): 99 %; 99.8 % and
#: 99 % (studies/DETECTION.md, twenty-eighth and twenty-ninth sittings).
CV_SHARE = 0.9
CV_PREDICT_SHARE = 0.5


def left_out_predictions(
    predictions: Sequence[tuple[str, float | None, float | None, int]],
    inflation: float,
    bic_threshold: float = 10.0,
) -> tuple[bool, list[str]]:
    """The decision of :func:`cross_validate` on its predictions: ``(name, before,
    after, n)`` per left-out log, its chi2/N predicted by the model without and with
    the candidate (None: that fit failed) over ``n`` residuals. Passes if every log is
    predicted better by more than ``bic_threshold`` in effective samples (``n /
    inflation``) and the candidate removes at least :data:`CV_PREDICT_SHARE` of the
    error above the noise floor (chi2/N 1). Returns ``(passed, one line per log)``."""
    ok, parts = bool(predictions), []
    for name, before, after, n in predictions:
        if before is None or after is None or not (math.isfinite(before) and math.isfinite(after)):
            ok = False
            parts.append(f"{name}: a fit failed")
            continue
        change = (after - before) * n / inflation
        removed = (before - after) / (before - 1.0) if before > 1.0 else 0.0
        ok = ok and change < -bic_threshold and removed >= CV_PREDICT_SHARE
        parts.append(f"{name} predicted at chi2/N {before:.3g} -> {after:.3g}")
    return ok, parts


def cross_validate(
    step: Diagnosis,
    logs: Sequence[Log],
    validate_logs: Sequence[Log],
    *,
    bic_threshold: float = 10.0,
    free: str = "all",
    seed: int = 0,
    workers: int | None = None,
    progress: Callable[[str], None] | None = None,
) -> tuple[EffectScreen, FitResult] | None:
    """A second look at the candidate of ``step`` that came closest but failed the
    held-out check (the first such one of :attr:`Diagnosis.partial`): is it absent,
    or are its values only not determined by the fitted logs?

    1. Refit it from the further starts it reads from the logs
       (:meth:`~jaxlift.AbstractEffect.more_starts_from_logs`: the ridge of equal slip
       features for stick-slip), one start each; the best refit, this one or the
       step's, goes on if it removes at least :data:`CV_SHARE` of the fitted logs'
       error above the noise.
    2. Leave each fitted log out in turn, fit the model without and with the candidate
       (from their fits: ``step.base_fit`` and the best refit) on the other fitted logs
       together with ``validate_logs``, and predict the left-out log (at its own
       initial-height offset, as the held-out check does). The candidate passes if, for
       every left-out log the rest can judge (:func:`usable_heldout`), it predicts it
       better by more than ``bic_threshold`` (effective samples) and removes at least
       :data:`CV_PREDICT_SHARE` of the model's error on it.

    Returns the candidate and its best refit on ``logs`` if it passes, else None; what
    was found either way is appended to ``step.cross_validation``. A failed refit ends
    the check (recorded), not the diagnosis."""
    say = progress or (lambda _s: None)
    base = step.base_fit
    n_held = sum(e.n_residuals for e in make_experiments(validate_logs))
    s, best = next(
        (
            (s, f)
            for s, f in step.partial
            if (h := held_out_evidence(s, n_held, base.inflation)) is not None
            and h >= -bic_threshold
        ),
        (None, None),
    )
    if s is None:
        return None
    effects = [*base.effects, s.effect]

    def note(line: str) -> None:  # what was found, kept in the step and reported
        step.cross_validation.append(line)
        say("cross-validation: " + line)

    try:
        run = log_simulator(base.params, effects, logs)
        starts = EFFECTS[s.effect].more_starts_from_logs(logs, base.params, run)
        say(f"cross-validation: {s.effect}: refitting from {len(starts)} further starts")

        def refit(start: Mapping[str, float]) -> FitResult:
            return fit(logs, effects=effects, free=refit_free(free), init={**base.params, **start},
                       staged=False, n_starts=1, seed=seed, workers=1)  # fmt: skip

        for res in thread_map(refit, starts, workers):
            if math.isfinite(res.chi2) and res.chi2 < best.chi2:
                best = res
        excess = base.chi2 - base.n_residuals
        share = (base.chi2 - best.chi2) / excess if excess > 0 else 0.0
        if share < CV_SHARE:
            note(
                f"{s.effect}: its best refit removes {share:.0%} of the fitted logs' error "
                f"(cross-validated from {CV_SHARE:.0%}): not cross-validated"
            )
            return None
        jobs = []
        for i, out in enumerate(logs):
            train = [*logs[:i], *logs[i + 1 :], *validate_logs]
            if usable_heldout(train, [out])[0]:
                jobs += [(train, out, base), (train, out, best)]
        if not jobs:
            note(f"{s.effect}: no fitted log can be predicted from the others: not cross-validated")
            return None

        def predict(job) -> float | None:
            train, out, model = job
            free_ = refit_free(free) if model.effects else free
            res = fit(train, effects=list(model.effects), free=free_, init=model.params,
                      staged=False, n_starts=1, seed=seed, workers=1)  # fmt: skip
            if not math.isfinite(res.chi2):
                return None
            return _heldout_chi2(res.params, res.effects, [out])

        say(f"cross-validation: {s.effect}: {len(jobs)} fits, each fitted log left out in turn")
        predicted = list(thread_map(predict, jobs, workers))
    except Exception as err:  # noqa: BLE001 -- the check fails, the diagnosis goes on
        note(f"{s.effect}: the cross-validation failed ({type(err).__name__}: {err})")
        return None
    outs = [jobs[k][1] for k in range(0, len(jobs), 2)]
    ok, parts = left_out_predictions(
        [
            (out.name, predicted[2 * i], predicted[2 * i + 1],
             sum(e.n_residuals for e in make_experiments([out])))
            for i, out in enumerate(outs)
        ],
        base.inflation,
        bic_threshold,
    )  # fmt: skip
    summary = (
        f"{s.effect} removes {share:.0%} of the fitted logs' error (chi2/N "
        f"{base.chi2 / base.n_residuals:.3g} -> {best.chi2 / best.n_residuals:.3g}) but "
        f"predicts the held-out logs no better; fitted with them, each fitted log left out: "
        + "; ".join(parts)
    )
    if not ok:
        note(summary + f": not kept (needs {CV_PREDICT_SHARE:.0%} of each left-out log's error)")
        return None
    note(
        summary + ": kept, its values are not determined by the fitted logs alone (fit the "
        "model with it on every log to fix them)"
    )
    infos = EFFECTS[s.effect].param_infos()
    s.confirmed_chi2 = best.chi2
    s.delta_bic = _bic(best.chi2, len(best.free), best.n_residuals, base.inflation) - _bic(
        base.chi2, len(base.free), base.n_residuals, base.inflation
    )
    s.explained_share = share
    s.fitted_params = {k: best.params[k] for k in infos}
    s.fitted_stderr = {k: best.stderr[k] for k in infos if k in best.stderr}
    s.heldout_chi2_after = _heldout_chi2(best.params, best.effects, validate_logs)
    return s, best


#: Verdicts that name no effect: nothing missing, cannot tell which, none of the
#: candidates.
NOT_AN_EFFECT = ("none", "undecided", "unexplained")


def final_verdict(steps: Sequence[Diagnosis]) -> str:
    """How an iterative diagnosis ended: ``none`` (nothing more is missing),
    ``undecided`` (which of two), or ``unexplained`` (the final model still leaves an
    error well above the noise, also when the iteration ran out of steps on a name)."""
    last = steps[-1]
    if last.misfit is not None and last.misfit.significant:
        return "unexplained"
    return last.verdict if last.verdict in NOT_AN_EFFECT else "none"


def found_effects(steps: Sequence[Diagnosis]) -> list[str]:
    """The effects an iterative diagnosis added, in order (including those the
    backward check dropped again: see :attr:`Diagnosis.dropped`)."""
    return [d.verdict for d in steps if d.verdict not in NOT_AN_EFFECT]


def kept_effects(steps: Sequence[Diagnosis]) -> list[str]:
    """The effects an iterative diagnosis kept, in the order they were added: each
    step's verdict added, then what that step's backward check dropped (an earlier
    effect, or the newcomer itself) removed, so that an effect dropped in one step and
    named again later counts."""
    kept: list[str] = []
    for d in steps:
        if d.verdict not in NOT_AN_EFFECT:
            kept.append(d.verdict)
        kept = [e for e in kept if e not in d.dropped]
    return kept


def backward_check(
    model: FitResult,
    logs: Sequence[Log],
    candidates: Sequence[str],
    free: str,
    seed: int,
    workers: int | None = None,
) -> tuple[str, float, FitResult] | None:
    """Refit ``model`` without each of ``candidates`` (warm start from its parameters,
    offsets from 0; one thread per core);
    the one whose removal raises the BIC least: (name, BIC change, reduced fit)."""
    bic = _bic(model.chi2, len(model.free), model.n_residuals, model.inflation)

    def refit(name: str) -> FitResult:
        rest = [e for e in model.effects if e != name]
        own = set(EFFECTS[name].param_infos())
        init = {k: v for k, v in model.params.items() if k not in own}
        return fit(logs, effects=rest, free=f"{free},effects" if rest else free, init=init,
                   staged=False, n_starts=1, seed=seed, workers=1)  # fmt: skip

    best = None
    for name, res in zip(candidates, thread_map(refit, candidates, workers)):
        dbic = _bic(res.chi2, len(res.free), res.n_residuals, model.inflation) - bic
        if best is None or dbic < best[1]:
            best = (name, dbic, res)
    return best
