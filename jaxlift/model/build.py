"""A model = a plant plus effects; parameters addressed by their flat file names.

docs/model.md's parameter names are unique across the plant and the effects, so one flat
``{name: value}`` mapping describes a whole model (that is what parameter files hold).
"""

from __future__ import annotations

import os
from collections.abc import Mapping, Sequence

import equinox as eqx
from jaxtyping import ArrayLike

from .effects import EFFECTS, AbstractEffect
from .params import ParameterError, ParamInfo, get_params, load_params_json, replace_params
from .plant import PLANT_PARAMS, Plant


def make_effects(
    names: Sequence[str] | str | None, values: dict[str, float] | None = None
) -> tuple[AbstractEffect, ...]:
    """Effects by name (comma-separated string or sequence), in registry order, with
    their parameters taken from ``values`` where given (else their defaults)."""

    if names is None:
        names = []
    if isinstance(names, str):
        names = [n.strip() for n in names.split(",") if n.strip()]
    unknown = [n for n in names if n not in EFFECTS]
    if unknown:
        raise ValueError(f"unknown effect(s) {unknown}; known effects: {list(EFFECTS)}")
    values = dict(values or {})
    chosen = [EFFECTS[n] for n in names]
    stray = sorted(k for k in values if not any(k in c.param_infos() for c in chosen))
    if stray:
        raise ValueError(
            f"parameter(s) {stray} belong to none of the effects {list(names)}; their "
            f"parameters are {sorted(k for c in chosen for k in c.param_infos())}"
        )
    out = []
    for name, cls in EFFECTS.items():
        if name in names:
            eff = cls()
            own = {k: v for k, v in values.items() if k in cls.param_infos()}
            out.append(replace_params(eff, own))
    return tuple(out)


def all_param_infos(effects: Sequence[AbstractEffect | str] = ()) -> dict[str, ParamInfo]:
    """Parameter descriptions of the plant and the given effects (all effects if
    ``effects == "all"``), by file name."""
    out = dict(_plant_infos())
    if effects == "all":
        names = list(EFFECTS)
    else:
        names = [e if isinstance(e, str) else e.name for e in effects]
    for n in names:
        out.update(EFFECTS[n].param_infos())
    return out


def _plant_infos():

    return PLANT_PARAMS


def model_params(plant: Plant, effects: Sequence[AbstractEffect] = ()) -> dict[str, ArrayLike]:
    """All parameter values of a model as one flat ``{name: value}`` dict."""
    out = dict(get_params(plant))
    for e in effects:
        out.update(get_params(e))
    return out


def with_params(
    plant: Plant, effects: Sequence[AbstractEffect], values: Mapping[str, ArrayLike]
) -> tuple[Plant, tuple[AbstractEffect, ...]]:
    """Plant and effects with the named parameters replaced (jit/vmap/grad-safe)."""
    plant_names = _plant_infos()
    rest = dict(values)
    plant = replace_params(plant, {k: rest.pop(k) for k in list(rest) if k in plant_names})
    new_effects = []
    for e in effects:
        own = e.param_infos()
        new_effects.append(replace_params(e, {k: rest.pop(k) for k in list(rest) if k in own}))
    if rest:
        raise ParameterError(
            f"parameter(s) {sorted(rest)} belong to no part of this model (plant + "
            f"{[e.name for e in effects]}); known: {sorted(all_param_infos(effects))}"
        )
    return plant, tuple(new_effects)


def load_model(
    params_path: str | os.PathLike | None = None, effects: Sequence[str] | str | None = None
) -> tuple[Plant, tuple[AbstractEffect, ...]]:
    """Plant and effects from a parameter file (docs/model.md names) and effect names.

    With ``effects=None`` the effects are those whose parameters appear in the file.
    Parameters missing from the file keep their nominal values.
    """
    values = {}
    if params_path is not None:
        values = load_params_json(params_path, all_param_infos("all"))
    if effects is None:
        effects = [n for n, cls in EFFECTS.items() if set(cls.param_infos()) & set(values)]
    effs = make_effects(effects)
    names = [e.name for e in effs]
    stray = sorted(set(values) - set(all_param_infos(effs)))
    if stray:
        raise ParameterError(
            f"{params_path}: parameter(s) {stray} belong to effects that are not switched on "
            f"({names}); add them with --effects or remove them from the file"
        )
    return with_params(Plant(), effs, values)


class Model(eqx.Module):
    """A whole lift model, built once and handed down: the plant and the switched-on
    effects (registry order), each carrying its parameters.

    Build it from effect names and a flat ``{name: value}`` mapping (docs/model.md
    names, SI units) with :meth:`build`, then derive what a job needs from it
    (:meth:`values`, :meth:`param_infos`, :meth:`with_values`, :meth:`with_effect`)
    instead of turning names into modules again.
    """

    plant: Plant
    effects: tuple[AbstractEffect, ...]

    @classmethod
    def build(
        cls,
        effects: Sequence[str] | str | None = (),
        values: Mapping[str, ArrayLike] | None = None,
    ) -> Model:
        """The nominal plant with ``effects`` switched on and ``values`` set."""
        plant, effs = with_params(Plant(), make_effects(effects), dict(values or {}))
        return cls(plant, effs)

    @property
    def effect_names(self) -> tuple[str, ...]:
        """Names of the switched-on effects (registry order)."""
        return tuple(e.name for e in self.effects)

    def values(self) -> dict[str, ArrayLike]:
        """Every parameter value, plant and effects, as one flat dict."""
        return model_params(self.plant, self.effects)

    def param_infos(self) -> dict[str, ParamInfo]:
        """Descriptions (unit, bounds, nominal) of every parameter of this model."""
        return all_param_infos(self.effects)

    def with_values(self, values: Mapping[str, ArrayLike]) -> Model:
        """This model with the named parameters replaced (jit/vmap/grad-safe)."""
        return Model(*with_params(self.plant, self.effects, values))

    def with_effect(self, name: str, values: Mapping[str, ArrayLike] | None = None) -> Model:
        """This model with effect ``name`` switched on as well (its parameters from
        ``values``, else their defaults); everything else keeps its value."""
        effs = make_effects([*self.effect_names, name], dict(values or {}))
        own = {k: v for k, v in self.values().items() if k not in PLANT_PARAMS}
        _, effs = with_params(self.plant, effs, own)
        return Model(self.plant, effs)
