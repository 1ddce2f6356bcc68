"""A law for an estimated signal: sparse regression over a small library of physically
meaningful terms (in the spirit of SINDy), and the one-state dependence of the signal
(partial-dependence curves). NumPy only.

Selection rule (stated, and the same everywhere): among the library's terms, the best
subset of each size k = 1 .. ``max_terms`` is found by exhaustive weighted least squares;
the law keeps the smallest k after which one more term adds less than ``min_gain``
(default 0.02, i.e. 2 %) to the weighted R². A constant (an offset, e.g. a weight the
model has wrong) is in every subset and not counted in k. The leading term is the
non-constant one whose contribution (coefficient times the term) has the largest
standard deviation, among the terms the model does not already have where there are
any (:data:`MODEL_TERMS`: those are shifts of the model's own parameters, which
absorbed part of the missing law in the fit). Terms the data cannot tell from the
leading one are named with it (``Law.alternatives``; rule at :data:`ALIAS_CORR`).
"""

from __future__ import annotations

import dataclasses
import itertools
from collections.abc import Callable, Mapping

import numpy as np

V_EPS = 1e-3  # m/s, the smoothing of sign(v) (as the plant's Coulomb friction)
#: A term that, in the leading term's place, explains at least ALIAS_CORR² (0.9) of
#: what the leading term adds to the law's other terms is reported as one the data
#: cannot tell from it (``Law.alternatives``): for a law of one term, the share one
#: column explains of another at this correlation.
ALIAS_CORR = 0.95

#: The library: name -> (function of the states, unit of the term). States: ``t`` [s],
#: ``x`` [m], ``v`` [m/s], ``p`` [Pa], ``a`` [m/s^2], ``u`` [-].
LIBRARY: dict[str, tuple[Callable[[Mapping[str, np.ndarray]], np.ndarray], str]] = {
    "1": (lambda s: np.ones_like(s["v"]), ""),
    "sign(v)": (lambda s: np.tanh(s["v"] / V_EPS), ""),
    "v": (lambda s: s["v"], "m/s"),
    "v|v|": (lambda s: s["v"] * np.abs(s["v"]), "m^2/s^2"),
    "v^3": (lambda s: s["v"] ** 3, "m^3/s^3"),
    "v^5": (lambda s: s["v"] ** 5, "m^5/s^5"),
    "p": (lambda s: s["p"], "Pa"),
    "p sign(v)": (lambda s: s["p"] * np.tanh(s["v"] / V_EPS), "Pa"),
    "sqrt(p)": (lambda s: np.sqrt(np.maximum(s["p"], 0.0)), "Pa^0.5"),
    "x": (lambda s: s["x"], "m"),
    "x sign(v)": (lambda s: s["x"] * np.tanh(s["v"] / V_EPS), "m"),
    "u": (lambda s: s["u"], ""),
    "a": (lambda s: s["a"], "m/s^2"),
    "t": (lambda s: s["t"], "s"),
}

#: The terms tried for each signal: those with a physical reading for it. A force: an
#: offset (a weight), Coulomb and viscous friction and their growth (``v|v|``: a
#: turbulent loss felt on the fork; ``v^3``, ``v^5``), a hydraulic area error (``p``),
#: seal friction that grows with pressure or with extension (``p sign(v)``,
#: ``x sign(v)``), a height-dependent force (``x``), an inertia error (``a``), a drift
#: (``t``), the input (``u``). A flow: an offset, leaks (``p``: laminar, ``sqrt(p)``:
#: orifice), a speed-dependent loss (``v``, ``v|v|``), a height-dependent one (``x``),
#: the input (``u``: a pump or drive nonlinearity) and a drift (``t``).
LIBRARIES: dict[str, tuple[str, ...]] = {
    "force": (
        "1",
        "sign(v)",
        "v",
        "v|v|",
        "v^3",
        "v^5",
        "p",
        "p sign(v)",
        "x",
        "x sign(v)",
        "u",
        "a",
        "t",
    ),  # fmt: skip
    "flow": ("1", "sign(v)", "v", "v|v|", "p", "sqrt(p)", "x", "u", "t"),
}

#: Terms the baseline model already carries, per signal: a coefficient on one of these
#: is a shift of that parameter (it absorbed part of the missing law), not a new law.
MODEL_TERMS: dict[str, dict[str, str]] = {
    "force": {
        "sign(v)": "cf_con (Coulomb friction)",
        "v": "d (viscous damping)",
        "v^5": "cf_out * cf_in^5 (friction growth)",
    },  # fmt: skip
    "flow": {},
}


@dataclasses.dataclass
class Law:
    """A fitted law ``signal ~ sum(coef * term)``.

    ``coefs``: by term name, in the signal's unit per the term's unit. ``r2``: weighted
    R² of the law; ``path``: the best R² for each number of terms tried. ``leading``: the
    term with the largest contribution; ``model_terms``: the chosen terms the model
    already has (with the parameter they shift); ``alternatives``: library terms that
    the data cannot tell from the leading one: in its place, free to shift one more of
    the model's own parameters (:data:`MODEL_TERMS`), the term explains at least
    ``ALIAS_CORR²`` of the weighted R² the leading term adds to the law's other terms
    (e.g. ``p`` and ``p sign(v)`` on logs that only lift, or whose pressure at rest is
    that of lifting: ``p sign(v)`` with a shift of ``cf_con`` is then ``p`` plus a
    constant)."""

    signal: str
    unit: str
    coefs: dict[str, float]
    r2: float
    path: list[tuple[list[str], float]]
    leading: str
    model_terms: dict[str, str]
    min_gain: float
    alternatives: list[str] = dataclasses.field(default_factory=list)

    def describe(self) -> str:
        parts = []
        for name, c in sorted(self.coefs.items(), key=lambda kv: kv[0] != self.leading):
            tu = LIBRARY[name][1]
            unit = f"{self.unit}/({tu})" if tu else self.unit
            parts.append(f"{c:+.3g} {unit} * {name}")
        text = f"missing {self.signal} ~ " + " ".join(parts) + f"  (R² {self.r2:.2f})"
        if self.model_terms:
            text += "; " + ", ".join(f"{t}: a shift of {p}" for t, p in self.model_terms.items())
        if self.alternatives:
            text += f"; on these data {self.leading} cannot be told from " + " or ".join(
                self.alternatives
            )
        return text

    def predict(self, states: Mapping[str, np.ndarray]) -> np.ndarray:
        return sum(c * LIBRARY[n][0](states) for n, c in self.coefs.items())

    def as_dict(self) -> dict:
        return {
            "signal": self.signal, "unit": self.unit, "coefs": self.coefs, "r2": self.r2,
            "leading": self.leading, "alternatives": self.alternatives,
            "model_terms": self.model_terms,
            "path": [{"terms": t, "r2": r} for t, r in self.path],
            "min_gain": self.min_gain, "law": self.describe(),
        }  # fmt: skip


def _wls(X: np.ndarray, y: np.ndarray, w: np.ndarray) -> tuple[np.ndarray, float]:
    sw = np.sqrt(w)
    coef, *_ = np.linalg.lstsq(X * sw[:, None], y * sw, rcond=None)
    r = y - X @ coef
    ybar = np.sum(w * y) / np.sum(w)
    ss_tot = np.sum(w * (y - ybar) ** 2)
    return coef, float(1.0 - np.sum(w * r**2) / ss_tot) if ss_tot > 0 else 0.0


def explain(
    signal: np.ndarray,
    states: Mapping[str, np.ndarray],
    *,
    name: str = "force",
    unit: str = "N",
    weights: np.ndarray | None = None,
    library: Mapping[str, tuple[Callable, str]] | None = None,
    max_terms: int = 4,
    min_gain: float = 0.02,
) -> Law:
    """Sparse regression of ``signal`` on the library's terms (module docstring).

    Args:
        signal: the estimated signal at the samples [``unit``].
        states: the states at the same samples (``t, x, v, p, a, u``; SI units).
        name: ``"force"`` or ``"flow"`` (which model terms to flag as shifts).
        weights: per-sample weights (e.g. 1 / the estimate's variance); default 1.
        library: terms to use (default: those of :data:`LIBRARIES` for ``name``, all
            of :data:`LIBRARY` for another name).
        max_terms: the largest subset tried.
        min_gain: the R² a further term must add to be kept.
    """
    if library is None:
        library = {k: LIBRARY[k] for k in LIBRARIES.get(name, tuple(LIBRARY))}
    lib = dict(library)
    y = np.asarray(signal, float)
    w = np.ones_like(y) if weights is None else np.asarray(weights, float)
    if y.ndim != 1 or w.shape != y.shape:
        raise ValueError(
            f"signal and weights must be 1-D of the same length, got {y.shape}, {w.shape}"
        )
    ok = np.isfinite(y) & np.isfinite(w) & (w > 0)
    cols = {}
    for term, (fn, _) in lib.items():
        c = np.asarray(fn(states), float)
        if c.shape != y.shape:
            raise ValueError(f"library term {term!r} has shape {c.shape}, the signal {y.shape}")
        ok &= np.isfinite(c)
        cols[term] = c
    names = [n for n in cols if np.ptp(cols[n][ok]) > 0 or n == "1"]
    X = np.stack([cols[n][ok] for n in names], axis=1)
    yk, wk = y[ok], w[ok]
    # scale the columns (conditioning only; coefficients are returned in physical units)
    scale = np.sqrt(np.mean(X**2, axis=0))
    scale[scale == 0] = 1.0
    Xs = X / scale
    # the constant ("1", an offset: e.g. a weight the model has wrong) is in every
    # subset and not counted among the k terms
    const = [names.index("1")] if "1" in names else []
    others = [i for i in range(len(names)) if i not in const]
    path: list[tuple[list[str], float, np.ndarray]] = []
    for k in range(1, min(max_terms, len(others)) + 1):
        best = None
        for subset in itertools.combinations(others, k):
            cols_k = [*const, *subset]
            coef, r2 = _wls(Xs[:, cols_k], yk, wk)
            if best is None or r2 > best[1]:
                best = (cols_k, r2, coef)
        path.append(([names[i] for i in best[0]], best[1], best[2] / scale[best[0]]))
    chosen = 0
    while chosen + 1 < len(path) and path[chosen + 1][1] - path[chosen][1] >= min_gain:
        chosen += 1
    terms, r2, coef = path[chosen]
    coefs = {t: float(c) for t, c in zip(terms, coef)}
    model = MODEL_TERMS.get(name, {})
    contrib = {t: float(np.std(coefs[t] * cols[t][ok])) for t in terms if t != "1"}
    new = {t: c for t, c in contrib.items() if t not in model}
    contrib = new or contrib
    leading = max(contrib, key=contrib.get) if contrib else "1"
    alternatives = []
    if leading != "1":
        rest = [names.index(t) for t in terms if t != leading]
        shifts = [names.index(t) for t in model if t in names and t not in terms]
        # R² of the law's other terms, alone and with each shift (computed once)
        r2_without = {m: _wls(Xs[:, [*rest, *([] if m is None else [m])]], yk, wk)[1]
                      for m in (None, *shifts)}  # fmt: skip
        for n in names:
            if n in ("1", leading) or n in terms:
                continue
            j = names.index(n)
            # in the leading term's place, free to shift one more of the model's own
            # parameters, n explains as much of the data beyond the law's other terms
            # (at least ALIAS_CORR², the share one column explains of another at that
            # correlation): e.g. p sign(v) + sign(v) against p + 1 on logs whose
            # pressure at rest is that of lifting
            r2_alt = max(
                _wls(Xs[:, [*rest, j, *([] if m is None else [m])]], yk, wk)[1] - r2_without[m]
                for m in (None, *shifts) if m != j
            )  # fmt: skip
            if r2_alt >= ALIAS_CORR**2 * (r2 - r2_without[None]):
                alternatives.append(n)
    return Law(
        signal=name, unit=unit, coefs=coefs, r2=r2,
        path=[(t, float(r)) for t, r, _ in path], leading=leading,
        model_terms={t: model[t] for t in terms if t in model}, min_gain=min_gain,
        alternatives=alternatives,
    )  # fmt: skip


def dependence(
    signal: np.ndarray,
    states: Mapping[str, np.ndarray],
    *,
    weights: np.ndarray | None = None,
    bins: int = 20,
) -> dict[str, dict]:
    """The signal's mean in quantile bins of each state (a one-state partial-dependence
    curve), and the share of the signal's variance that curve explains (``r2``).
    Returns ``{state: {"centers", "mean", "r2"}}``."""
    y = np.asarray(signal, float)
    w = np.ones_like(y) if weights is None else np.asarray(weights, float)
    ybar = np.sum(w * y) / np.sum(w)
    ss = np.sum(w * (y - ybar) ** 2)
    out = {}
    for key, s in states.items():
        s = np.asarray(s, float)
        edges = np.unique(np.quantile(s, np.linspace(0, 1, bins + 1)))
        if edges.size < 3:
            continue
        idx = np.clip(np.searchsorted(edges, s, side="right") - 1, 0, edges.size - 2)
        means = np.array([
            np.sum(w[idx == b] * y[idx == b]) / max(np.sum(w[idx == b]), 1e-300)
            for b in range(edges.size - 1)
        ])  # fmt: skip
        centers = 0.5 * (edges[1:] + edges[:-1])
        fitted = means[idx]
        r2 = float(1.0 - np.sum(w * (y - fitted) ** 2) / ss) if ss > 0 else 0.0
        out[key] = {"centers": centers, "mean": means, "r2": r2}
    return out
