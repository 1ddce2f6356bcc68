"""Named physical parameters: names, units, bounds and nominal values in one place.

Every physical parameter of the plant and of the effects is a field of an
``eqx.Module`` declared with :func:`param`. The field's metadata carries a
:class:`ParamInfo` (name as in docs/model.md and in parameter files, unit, nominal value,
bounds, description). Everything else -- parameter files, optimiser transforms,
reports -- reads this metadata, so a parameter is described exactly once.

Optimisers never see physical values: they work on unconstrained coordinates
(:func:`to_unconstrained` / :func:`from_unconstrained`): a scaled logit where both
bounds are finite, a log of the distance to the one finite bound otherwise.
"""

from __future__ import annotations

import dataclasses
import json
import math
import os
from collections.abc import Iterable, Mapping

import equinox as eqx
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, ArrayLike, Float


class ParameterError(ValueError):
    """A parameter name, value or file that is not acceptable."""


@dataclasses.dataclass(frozen=True)
class ParamInfo:
    """Description of one physical parameter.

    Attributes:
        name: name in parameter files and reports (docs/model.md's first column).
        unit: SI unit, as text.
        nominal: nominal value (initial guess), in ``unit``.
        lower, upper: physical bounds (may be ``-inf``/``inf``), in ``unit``.
        description: what it is.
        nesting: for an effect parameter, the value at which the effect vanishes
            (``None`` for plant parameters).
        scale: a typical physical magnitude (for effect parameters whose nominal is
            the nesting value 0: where multi-start fits begin looking), in ``unit``.
        transform: unconstrained coordinate for optimisers: ``"log"`` (``log(x - lower)``;
            the upper bound is then only checked, not enforced), ``"logit"`` (scaled to
            ``(lower, upper)``) or ``"identity"``. Default: ``"log"`` where ``lower`` is
            finite and ``>= 0``, else ``"logit"`` where both bounds are finite.
        spread: multi-start fits draw starting points within a factor ``spread`` of the
            current estimate (log-uniform).
        typical: ``(low, high)``: the sizes a real vehicle can have (an effect's
            parameters), in ``unit``; the diagnosis's confirmation refits start from a
            grid over it. ``None`` where no such range is declared.
        typical_why: where the range comes from.
        stage: for an effect parameter, the stage of a staged fit (``fit(staged=True)``)
            that fits it beside the base model's set of that name: ``"motor"``
            (k1...z3) or ``"dynamic"`` (beta ... d); ``None`` (default): only the last
            stage, with everything else. A parameter that changes what the motor
            stage fits (the motor's speed) belongs there: fitted without it, that stage
            ends far from the truth and the later stages follow it (docs/statistics.md).
    """

    name: str
    unit: str
    nominal: float
    lower: float
    upper: float
    description: str
    nesting: float | None = None
    scale: float | None = None
    transform: str = ""
    spread: float = 1.5
    typical: tuple[float, float] | None = None
    typical_why: str = ""
    stage: str | None = None

    def __post_init__(self):
        if not self.transform:
            fin_lo, fin_hi = math.isfinite(self.lower), math.isfinite(self.upper)
            t = (
                "log"
                if fin_lo and self.lower >= 0
                else "logit"
                if fin_lo and fin_hi
                else "identity"
            )
            object.__setattr__(self, "transform", t)
        if self.transform not in ("log", "logit", "identity"):
            raise ParameterError(f"parameter {self.name!r}: unknown transform {self.transform!r}")
        if self.typical is not None and not (
            self.lower <= self.typical[0] < self.typical[1] <= self.upper
        ):
            raise ParameterError(
                f"parameter {self.name!r}: typical range {self.typical} not inside its "
                f"bounds [{self.lower}, {self.upper}]"
            )
        if self.stage not in (None, "motor", "dynamic"):
            raise ParameterError(
                f"parameter {self.name!r}: stage must be 'motor', 'dynamic' or None,"
                f" got {self.stage!r}"
            )
        if not self.lower <= self.nominal <= self.upper:
            raise ParameterError(
                f"parameter {self.name!r}: nominal value {self.nominal} outside its bounds "
                f"[{self.lower}, {self.upper}]"
            )

    def check(self, value: float, *, source: str = "") -> None:
        """Raise :class:`ParameterError` if ``value`` is not finite or out of bounds."""
        where = f"{source}: " if source else ""
        if not isinstance(value, (int, float)) or isinstance(value, bool):
            raise ParameterError(
                f"{where}parameter {self.name!r}: expected a number in {self.unit}, got {value!r}"
            )
        if not math.isfinite(value):
            raise ParameterError(f"{where}parameter {self.name!r}: expected a finite number")
        if not self.lower <= value <= self.upper:
            raise ParameterError(
                f"{where}parameter {self.name!r} = {value} {self.unit} is outside its "
                f"bounds [{self.lower}, {self.upper}] {self.unit}"
            )


def param(
    nominal: float,
    unit: str,
    lower: float,
    upper: float,
    description: str,
    *,
    nesting: float | None = None,
    scale: float | None = None,
    transform: str = "",
    spread: float = 1.5,
    name: str | None = None,
    typical: tuple[float, float] | None = None,
    typical_why: str = "",
    stage: str | None = None,
):
    """Declare a physical-parameter field of an ``eqx.Module``.

    The field holds a float64 scalar array (converted on construction) and defaults
    to ``nominal``. ``name`` defaults to the field's attribute name.
    """
    info = dict(nominal=nominal, unit=unit, lower=lower, upper=upper)
    info.update(description=description, nesting=nesting, scale=scale, name=name)
    info.update(transform=transform, spread=spread, typical=typical, typical_why=typical_why)
    info.update(stage=stage)
    return eqx.field(default=nominal, converter=_as_float64, metadata={"jaxlift_param": info})


def _as_float64(x):
    return jnp.asarray(x, dtype=jnp.float64)


def param_infos(module: eqx.Module | type) -> dict[str, ParamInfo]:
    """The :class:`ParamInfo` of every parameter field of ``module`` (class or instance)."""
    cls = module if isinstance(module, type) else type(module)
    out = {}
    for f in dataclasses.fields(cls):
        meta = f.metadata.get("jaxlift_param")
        if meta is None:
            continue
        name = meta["name"] or f.name
        out[name] = ParamInfo(
            name=name,
            unit=meta["unit"],
            nominal=meta["nominal"],
            lower=meta["lower"],
            upper=meta["upper"],
            description=meta["description"],
            nesting=meta["nesting"],
            scale=meta["scale"],
            transform=meta["transform"],
            spread=meta["spread"],
            typical=meta["typical"],
            typical_why=meta["typical_why"],
            stage=meta["stage"],
        )
    return out


def _field_of(cls: type, name: str) -> str:
    for f in dataclasses.fields(cls):
        meta = f.metadata.get("jaxlift_param")
        if meta is not None and (meta["name"] or f.name) == name:
            return f.name
    raise KeyError(name)


def get_params(module: eqx.Module) -> dict[str, Array]:
    """Parameter values of ``module`` as ``{name: value}`` (physical units)."""
    return {name: getattr(module, _field_of(type(module), name)) for name in param_infos(module)}


def replace_params(module: eqx.Module, values: Mapping[str, ArrayLike]) -> eqx.Module:
    """A copy of ``module`` with the named parameters replaced (physical units).

    Works under ``jit``/``vmap``/``grad`` (values may be tracers). Unknown names raise
    :class:`ParameterError`.
    """
    infos = param_infos(module)
    unknown = sorted(set(values) - set(infos))
    if unknown:
        raise ParameterError(
            f"{type(module).__name__} has no parameter(s) {unknown}; known: {sorted(infos)}"
        )
    if not values:
        return module
    names = list(values)
    fields = [_field_of(type(module), n) for n in names]
    return eqx.tree_at(
        lambda m: [getattr(m, f) for f in fields],
        module,
        [jnp.asarray(values[n], dtype=jnp.float64) for n in names],
    )


# ---------------------------------------------------------------- transforms
def to_unconstrained(info: ParamInfo, value: Float[ArrayLike, "..."]) -> Float[Array, "..."]:
    """Map a physical value to the unconstrained coordinate of ``info.transform``."""
    value = jnp.asarray(value, dtype=jnp.float64)
    lo, hi = info.lower, info.upper
    if info.transform == "logit":
        s = (value - lo) / (hi - lo)
        return jnp.log(s) - jnp.log1p(-s)
    if info.transform == "log":
        return jnp.log(value - lo)
    return value


def from_unconstrained(info: ParamInfo, theta: Float[ArrayLike, "..."]) -> Float[Array, "..."]:
    """Inverse of :func:`to_unconstrained`."""
    theta = jnp.asarray(theta, dtype=jnp.float64)
    lo, hi = info.lower, info.upper
    if info.transform == "logit":
        return lo + (hi - lo) * jax_sigmoid(theta)
    if info.transform == "log":
        return lo + jnp.exp(theta)
    return theta


def jax_sigmoid(x):
    return 0.5 * (1.0 + jnp.tanh(0.5 * x))


# ---------------------------------------------------------------- files
def load_params_json(path: str | os.PathLike, known: Mapping[str, ParamInfo]) -> dict[str, float]:
    """Read a parameter file: a JSON object ``{name: value}`` with docs/model.md's names.

    Values are in the units of :class:`ParamInfo`; every name must be in ``known``
    and every value finite and inside its bounds. A key ``"_comment"`` (or any key
    starting with ``_``) is ignored, so files can carry notes.
    """
    path = os.fspath(path)
    try:
        with open(path, encoding="utf-8") as fh:
            data = json.load(fh)
    except FileNotFoundError:
        raise ParameterError(f"{path}: parameter file not found") from None
    except (json.JSONDecodeError, UnicodeDecodeError) as err:
        raise ParameterError(f"{path}: not a valid JSON parameter file ({err})") from None
    if not isinstance(data, dict):
        raise ParameterError(f"{path}: expected a JSON object {{name: value}}")
    out = {}
    for name, value in data.items():
        if name.startswith("_"):
            continue
        if name not in known:
            raise ParameterError(
                f"{path}: unknown parameter {name!r}; known parameters: {sorted(known)}"
            )
        known[name].check(value, source=path)
        out[name] = float(value)
    return out


def save_params_json(
    path: str | os.PathLike, values: Mapping[str, ArrayLike], comment: str | None = None
) -> None:
    """Write ``{name: value}`` as JSON (physical units), keys in the given order."""
    data: dict[str, object] = {}
    if comment:
        data["_comment"] = comment
    for k, v in values.items():
        data[k] = float(np.asarray(v))
    with open(os.fspath(path), "w", encoding="utf-8") as fh:
        json.dump(data, fh, indent=2)
        fh.write("\n")


def nominal_values(infos: Iterable[ParamInfo]) -> dict[str, float]:
    return {i.name: i.nominal for i in infos}
