"""Air in the oil: the gas volume fraction implied by a calibrated bulk modulus at the
mean working pressure (``phi = p (1/beta_eff - 1/beta_oil)``), and the bleed / don't-bleed
statement.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np
from jaxtyping import ArrayLike, Float

from ..model.constants import BETA_OIL, P_ATM
from ..model.simulate import simulate
from .predictive import hdi
from .problem import PosteriorProblem

#: Bulk modulus of ideal (air-free) oil [Pa] (docs/model.md).
#: Gas volume fraction at the mean working pressure above which bleeding the hydraulic
#: system is indicated (0.1 % by volume at working pressure, i.e. ~10 % free gas at
#: atmospheric pressure at 10 MPa: visibly foamy oil).
AIR_THRESHOLD = 1e-3


# ------------------------------------------------------------------ air content
def air_content(
    beta_eff: Float[ArrayLike, "..."], p_mean: float, beta_oil: float = BETA_OIL
) -> Float[np.ndarray, "..."]:
    """Gas volume fraction at pressure ``p_mean`` that explains ``beta_eff`` (docs/model.md).

    ``phi = p_mean * (1 / beta_eff - 1 / beta_oil)``: isothermal free gas, whose
    compliance per volume is ``phi / p``, added to that of ideal oil. ``p_mean`` is the
    absolute pressure [Pa] (the gas law), ``beta_eff`` and ``beta_oil`` in Pa; the result
    is a volume fraction (0.01 = 1 %), negative when the oil is stiffer than
    ``beta_oil``."""
    return p_mean * (1.0 / np.asarray(beta_eff, dtype=float) - 1.0 / beta_oil)


def mean_working_pressure(problem: PosteriorProblem) -> float:
    """Mean absolute pressure [Pa] over the moving parts of the logs (samples with
    ``pwm > 0``), simulated with the calibrated model: gauge line pressure + 1 atm."""
    return mean_pressure(
        problem.model.plant, problem.model.effects, [e.inputs for e in problem.experiments],
        [e.name for e in problem.experiments],
    )  # fmt: skip


def mean_pressure(plant, effects, inputs: Sequence, names: Sequence[str]) -> float:
    """Mean absolute pressure [Pa] over the samples with ``pwm > 0`` of runs with these
    ``inputs`` (named ``names`` in errors), simulated with ``plant`` and ``effects``."""
    tot, n = 0.0, 0
    for inp, name in zip(inputs, names, strict=True):
        sol = simulate(plant, effects, inp).check(f"simulating {name}")
        moving = np.asarray(inp.pwm) > 0
        p = np.asarray(sol.pressure)[moving]
        tot += float(np.sum(p))
        n += int(p.size)
    return tot / max(n, 1) + P_ATM


def air_verdict(phi_samples: np.ndarray, p_mean: float, has_hose: bool,
                threshold: float = AIR_THRESHOLD, prob: float = 0.9) -> dict:  # fmt: skip
    """The air-content statement for a service engineer: 90 % HDI of the gas fraction
    at the mean working pressure, and whether bleeding is indicated (whole HDI above
    ``threshold``), not indicated (whole HDI below) or undecided."""
    lo, hi = hdi(phi_samples, prob)
    mean = float(np.mean(phi_samples))
    alpha0_hi = hi * p_mean / P_ATM
    p_mpa = p_mean / 1e6
    if lo > threshold:
        verdict, action = "indicated", "bleeding the system is indicated"
    elif hi < threshold:
        verdict, action = "not indicated", "bleeding the system is not indicated"
    else:
        verdict, action = (
            "undecided",
            (
                "the data cannot decide whether bleeding is needed (the interval straddles "
                f"the {threshold:.1%} threshold)"
            ),
        )
    text = (
        f"Between {max(lo, 0) * 100:.3g} and {max(hi, 0) * 100:.3g} % gas by volume at "
        f"{p_mpa:.1f} MPa (90 % credible interval, attributing all softening to air); "
        f"{action}."
    )
    if lo < 0 < hi or hi <= 0:
        text += " Oil as stiff as ideal oil is within the interval."
    if alpha0_hi > 0.2 and lo > 0:
        text += (
            f" At atmospheric pressure that much gas would be {lo * p_mean / P_ATM:.0%}–"
            f"{alpha0_hi:.0%} of the oil volume — implausible as free air alone; a soft "
            "hose or seal compliance is the likelier cause of most of the softening."
        )
    if has_hose:
        text += (
            " The model includes hose compliance (`C_h`): `beta` is then the oil's own "
            "bulk modulus and the hoses' share of the softening is not counted as air."
        )
    else:
        text += (
            " Hose and seal compliance (not in this model) would soften the system in the "
            "same way; `jaxlift diagnose` distinguishes the two (hose compliance makes the "
            "oscillation frequency vary less with height), and `--effects hose_compliance` "
            "separates them here."
        )
    return {
        "phi_mean": mean,
        "phi_hdi90": [lo, hi],
        "p_mean_pa_abs": p_mean,
        "threshold": threshold,
        "verdict": verdict,
        "text": text,
    }
