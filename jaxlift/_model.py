"""A model = a plant plus effects; parameters addressed by their flat file names.

MODEL.md's parameter names are unique across the plant and the effects, so one flat
``{name: value}`` mapping describes a whole model (that is what parameter files hold).
"""

from __future__ import annotations

import os
from collections.abc import Mapping, Sequence

from jaxtyping import ArrayLike

from ._effects import EFFECTS, AbstractEffect
from ._params import ParameterError, ParamInfo, get_params, load_params_json, replace_params
from ._plant import Plant
from ._simulate import make_effects

__all__ = ["all_param_infos", "model_params", "with_params", "load_model"]


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
    from ._plant import PLANT_PARAMS

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
    """Plant and effects from a parameter file (MODEL.md names) and effect names.

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
