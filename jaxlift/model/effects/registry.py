"""The registry of candidate effects, and effects that users bring.

The eight effects of docs/model.md are registered by ``jaxlift.model.effects``. A user
adds a ninth without touching jaxlift: a subclass of :class:`AbstractEffect` in their
own file or package, registered

- in Python: :func:`register_effect` (usable as a class decorator);
- on the command line: ``--effect-file PATH`` on every command
  (:func:`load_effect_file` registers every effect class the file defines);
- from an installed package: an entry point in the group ``jaxlift.effects``
  (:func:`load_entry_point_effects`; the CLI loads them at its start, a library user
  calls it).

A registered effect is simulated, fitted, screened and confirmed by the diagnosis
exactly like the built-in ones: everything iterates over :data:`EFFECTS`. Registration
checks what the rest of jaxlift relies on (see :func:`register_effect`) and says what is
wrong, naming the class and the parameter.
"""

from __future__ import annotations

import importlib.util
import inspect
import math
import pathlib
import sys
from importlib.metadata import entry_points

from ..params import ParameterError
from ..plant import PLANT_PARAMS
from .base import AbstractEffect

#: The registry: effect name -> class. Order = the order in which effects are applied
#: and in which their states are stacked (the eight of docs/model.md first, in its
#: table's order; user effects after them, in the order they were registered).
EFFECTS: dict[str, type[AbstractEffect]] = {}

#: The names of the effects jaxlift itself defines (they cannot be replaced or removed).
BUILTIN: set[str] = set()

ENTRY_POINT_GROUP = "jaxlift.effects"


def register_effect(cls: type[AbstractEffect], *, builtin: bool = False):
    """Add an effect class to :data:`EFFECTS`; returns the class (a decorator).

    Checks, each failure a :class:`~jaxlift.ParameterError` naming the class:

    - it is a concrete subclass of :class:`AbstractEffect` (every abstract part filled
      in: ``name``, ``state_names``, ``state_scales`` (one per state),
      ``overrides_acceleration``, ``initial_state``);
    - its ``name`` is an identifier not taken by another registered effect (the same
      class registered twice is fine: a file loaded again);
    - at least one parameter has a nesting value (the first is the switch the
      diagnosis screens: at it the effect must vanish), and the switch parameter's
      nominal value is its nesting value (a model built with the effect's defaults is
      the model without it);
    - its parameter names are not those of the plant or of another registered effect
      (parameter files and fits name parameters in one flat namespace);
    - every parameter with a nesting value declares ``typical`` (the sizes a real
      vehicle can have, inside its bounds): the confirmation refits start from a
      grid over that range.
    """
    if not (isinstance(cls, type) and issubclass(cls, AbstractEffect)):
        raise ParameterError(f"{cls!r} is not a subclass of jaxlift.AbstractEffect")
    label = f"effect class {cls.__module__}.{cls.__qualname__}"
    # checked on the class, not by building one: no JAX work at registration (the
    # built-in eight register on import, before a program has chosen float64)
    if inspect.isabstract(cls):
        raise ParameterError(
            f"{label} is abstract: it must fill in initial_state (and name, state_names, "
            f"state_scales, overrides_acceleration); missing: {sorted(cls.__abstractmethods__)}"
        )
    missing = [
        a for a in ("name", "state_names", "state_scales", "overrides_acceleration")
        if not hasattr(cls, a)
    ]  # fmt: skip
    if missing:
        raise ParameterError(f"{label}: class attribute(s) {missing} not set (ClassVar)")
    if len(cls.state_names) != len(cls.state_scales):
        raise ParameterError(
            f"{label}: state_names {cls.state_names} and state_scales {cls.state_scales} "
            "must have the same length (one absolute-tolerance scale per state)"
        )
    name = getattr(cls, "name", None)
    if not (isinstance(name, str) and name.isidentifier()):
        raise ParameterError(f"{label}: name must be an identifier string, not {name!r}")
    if name in EFFECTS:
        if EFFECTS[name] is cls or _same_definition(EFFECTS[name], cls):
            return cls
        owner = EFFECTS[name]
        raise ParameterError(
            f"{label}: the effect name {name!r} is taken by "
            f"{owner.__module__}.{owner.__qualname__}; choose another name"
        )
    infos = cls.param_infos()
    switches = [n for n, i in infos.items() if i.nesting is not None]
    if not switches:
        raise ParameterError(
            f"{label}: no parameter has a nesting value (the value at which the effect "
            "vanishes); declare one with jaxlift.param(..., nesting=...)"
        )
    taken = {**{n: "the plant" for n in PLANT_PARAMS}}
    for other in EFFECTS.values():
        taken.update({n: f"effect {other.name!r}" for n in other.param_infos()})
    for pname, info in infos.items():
        if pname in taken:
            raise ParameterError(
                f"{label}: parameter {pname!r} is already a parameter of {taken[pname]}; "
                "parameter names are one namespace (parameter files, fits): rename it"
            )
        if info.nesting is None:
            continue
        if info.typical is None:
            raise ParameterError(
                f"{label}: parameter {pname!r} has a nesting value but no typical range; "
                "declare typical=(low, high), the sizes a real vehicle can have, in "
                f"{info.unit} (the diagnosis searches that range)"
            )
        lo, hi = info.typical
        if not (info.lower <= lo < hi <= info.upper) or not all(map(math.isfinite, (lo, hi))):
            raise ParameterError(
                f"{label}: parameter {pname!r}: typical range ({lo:g}, {hi:g}) must be "
                f"finite, increasing and inside its bounds [{info.lower:g}, {info.upper:g}]"
            )
    first = infos[switches[0]]
    if first.nominal != first.nesting:
        raise ParameterError(
            f"{label}: the switch parameter {first.name!r} has nominal {first.nominal:g} "
            f"but nesting value {first.nesting:g}: an effect's defaults must switch it off"
        )
    EFFECTS[name] = cls
    if builtin:
        BUILTIN.add(name)
    return cls


def _same_definition(a: type, b: type) -> bool:
    """The same class defined again (a user file loaded a second time)."""
    return a.__qualname__ == b.__qualname__ and inspect.getsourcefile(a) == inspect.getsourcefile(b)


def unregister_effect(name: str) -> None:
    """Remove a user effect from :data:`EFFECTS` (the built-in eight stay)."""
    if name in BUILTIN:
        raise ParameterError(f"effect {name!r} is built in and cannot be removed")
    if name not in EFFECTS:
        raise ParameterError(f"no effect {name!r} is registered; registered: {list(EFFECTS)}")
    del EFFECTS[name]


def load_effect_file(path: str | pathlib.Path) -> list[str]:
    """Import a Python file and register every concrete effect class it defines (not
    those it imports); returns their names. Errors name the file: a missing file, one
    that fails to import (with the error and its line), one that defines no effect."""
    path = pathlib.Path(path)
    if not path.is_file():
        raise ParameterError(f"effect file {path}: no such file")
    module_name = f"jaxlift_user_effects.{path.stem}_{abs(hash(str(path.resolve())))}"
    spec = importlib.util.spec_from_file_location(module_name, path)
    if spec is None or spec.loader is None:
        raise ParameterError(f"effect file {path}: not a Python file")
    module = importlib.util.module_from_spec(spec)
    sys.modules[module_name] = module  # dataclasses (equinox) look their module up
    try:
        spec.loader.exec_module(module)
    except Exception as err:  # noqa: BLE001 -- the user's code: report where it failed
        del sys.modules[module_name]
        line = f", line {err.lineno}" if isinstance(err, SyntaxError) else ""
        tb = err.__traceback__
        while tb is not None:
            if pathlib.Path(tb.tb_frame.f_code.co_filename) == path:
                line = f", line {tb.tb_lineno}"
            tb = tb.tb_next
        raise ParameterError(
            f"effect file {path}{line}: importing it failed: {type(err).__name__}: {err}"
        ) from err
    found = _effect_classes_of(module)
    if not found:
        raise ParameterError(
            f"effect file {path}: defines no concrete subclass of jaxlift.AbstractEffect"
        )
    names = []
    for cls in found:
        try:
            register_effect(cls)
        except ParameterError as err:
            raise ParameterError(f"effect file {path}: {err}") from err
        names.append(cls.name)
    return names


def load_entry_point_effects() -> list[str]:
    """Register the effects installed packages declare in the entry-point group
    ``jaxlift.effects`` (each entry an effect class, or a module whose effect classes
    are all registered); returns their names. A broken entry point is an error naming
    it and its package."""
    names = []
    for ep in entry_points(group=ENTRY_POINT_GROUP):
        where = f"entry point {ep.name} = {ep.value} (group {ENTRY_POINT_GROUP}"
        where += f", package {ep.dist.name})" if ep.dist is not None else ")"
        try:
            obj = ep.load()
        except Exception as err:  # noqa: BLE001 -- a plugin's failure, reported
            raise ParameterError(f"{where}: loading failed: {type(err).__name__}: {err}") from err
        classes = [obj] if isinstance(obj, type) else _effect_classes_of(obj)
        if not classes:
            raise ParameterError(f"{where}: is neither an effect class nor defines one")
        for cls in classes:
            try:
                register_effect(cls)
            except ParameterError as err:
                raise ParameterError(f"{where}: {err}") from err
            names.append(cls.name)
    return names


def _effect_classes_of(module) -> list[type[AbstractEffect]]:
    """The effect classes a module defines (not those it imports), abstract ones left
    out (a class left without ``name`` is registered, and refused with the reason)."""
    mod_name = getattr(module, "__name__", None)
    return [
        obj
        for obj in vars(module).values()
        if isinstance(obj, type)
        and issubclass(obj, AbstractEffect)
        and obj.__module__ == mod_name
        and not inspect.isabstract(obj)
    ]


__all__ = [
    "EFFECTS",
    "BUILTIN",
    "ENTRY_POINT_GROUP",
    "register_effect",
    "unregister_effect",
    "load_effect_file",
    "load_entry_point_effects",
]
