"""The interface every candidate effect implements.

An effect is an ``eqx.Module`` whose fields are its parameters (declared with
:func:`jaxlift.param`, each with its nesting value). The plant's right-hand side
(:mod:`jaxlift.model.simulate`) evaluates the chain of docs/model.md in a fixed order and asks
every active effect for its contribution at each point of the chain:

1. ``delay``            -- the plant sees the input at ``t - delay`` (s);
2. ``motor_offset``     -- added to ``k U + z`` before the clip at 0 (rad/s);
3. ``motor_speed``      -- replaces the static motor speed (e.g. by a state);
4. ``extra_flow``       -- added to the numerator of ``dp/dt`` (m^3/s);
5. ``extra_capacitance``-- added to ``C = V/beta`` (m^3/Pa);
6. ``extra_friction``   -- added to the friction force opposing motion (N);
7. ``acceleration``     -- replaces the rigid fork-and-load law (at most one effect);
8. ``state_derivative`` -- time derivative of the effect's own states.

Besides the physics, an effect may say where a refit with it should start
(``starts_from_logs``, read from the logs; none by default).

Design note: the hooks have neutral defaults here (zero contribution / pass-through)
and a concrete effect overrides only those it uses. This is a deliberate departure
from equinox's strict "abstract or final" rule: requiring all eight hooks in every
effect would make adding a hook touch every effect. The abstract parts an effect
*must* fill in are its ``name``, its ``state_names`` and its ``initial_state``.
"""

from __future__ import annotations

import abc
from collections.abc import Callable, Mapping, Sequence
from typing import ClassVar, NamedTuple

import equinox as eqx
import jax.numpy as jnp
from jaxtyping import Array, Float

from ..constants import G
from ..log import Log
from ..params import ParamInfo, param_infos
from ..plant import Plant
from ..solution import Solution

Scalar = Float[Array, ""]
Vector = Float[Array, " n"]


class Signals(NamedTuple):
    """Quantities at one instant, filled in along the chain (SI units).

    ``omega_ss`` (rad/s, static motor speed incl. the valve logic) and ``a`` (m/s^2,
    carriage acceleration) are only meaningful once the chain has reached them.
    """

    t: Scalar
    x: Scalar
    v: Scalar
    p: Scalar
    u: Scalar
    m_load: Scalar
    omega_ss: Scalar
    a: Scalar
    forces: Scalar  # A p / r - friction - d v  [N], forces on the carriage w/o gravity


class AbstractEffect(eqx.Module):
    """Base of all candidate effects. See the module docstring for the hooks."""

    name: eqx.AbstractClassVar[str]
    state_names: eqx.AbstractClassVar[tuple[str, ...]]
    state_scales: eqx.AbstractClassVar[tuple[float, ...]]  # absolute-tolerance scales
    #: a test run that shows the effect plainly, in a sentence a service engineer can
    #: act on: the diagnosis suggests it when the effect removed a real part of the
    #: error but was not kept (``unexplained``). Empty: no such run known.
    revealing_run: ClassVar[str] = ""

    @abc.abstractmethod
    def initial_state(self, plant: Plant, sig: Signals) -> Vector:
        """The effect's own states at the start, the plant being at rest (``sig``)."""

    @classmethod
    def param_infos(cls) -> dict[str, ParamInfo]:
        return param_infos(cls)

    @property
    def n_states(self) -> int:
        return len(self.state_names)

    # ------------------------------------------------------------- hooks
    def delay(self) -> Scalar:
        return jnp.zeros(())

    def motor_offset(self, plant: Plant, z: Vector, sig: Signals) -> Scalar:
        return jnp.zeros(())

    def motor_speed(self, plant: Plant, z: Vector, sig: Signals) -> Scalar:
        return sig.omega_ss

    def extra_flow(self, plant: Plant, z: Vector, sig: Signals) -> Scalar:
        return jnp.zeros(())

    def extra_capacitance(self, plant: Plant, z: Vector, sig: Signals, volume: Scalar) -> Scalar:
        return jnp.zeros(())

    def extra_friction(self, plant: Plant, z: Vector, sig: Signals) -> Scalar:
        return jnp.zeros(())

    overrides_acceleration: eqx.AbstractClassVar[bool]

    def acceleration(self, plant: Plant, z: Vector, sig: Signals) -> Scalar:
        """Carriage acceleration [m/s^2]; only called if ``overrides_acceleration``."""
        raise NotImplementedError  # abstract: only for effects that override it

    def state_derivative(self, plant: Plant, z: Vector, sig: Signals) -> Vector:
        return jnp.zeros((0,))

    # ------------------------------------------------------------- calibration
    @classmethod
    def starts_from_logs(
        cls,
        logs: Sequence[Log],
        params: Mapping[str, float],
        simulate: Callable[[Mapping[str, float]], Sequence[Solution] | None],
    ) -> list[dict[str, float]]:
        """Starting values of a confirmation refit with this effect, read from the logs.

        Args:
            logs: the fitted logs.
            params: the fitted model without this effect (physical units).
            simulate: ``simulate(values)`` runs the model with this effect, its
                parameters ``params`` updated by ``values``, on each log: the
                solutions, or None if one fails.

        Returns:
            Starts (any parameters, this effect's or the baseline's), best first. The
            diagnosis refits from the first, besides the grid over the effect's typical
            range (:func:`jaxlift.calibrate.diagnose.refit_starts`). For effects whose
            least-squares surface is too rough for a grid of starts (stick-slip);
            none by default.
        """
        return []

    @classmethod
    def more_starts_from_logs(
        cls,
        logs: Sequence[Log],
        params: Mapping[str, float],
        simulate: Callable[[Mapping[str, float]], Sequence[Solution] | None],
    ) -> list[dict[str, float]]:
        """Further starts for a second look at this effect, read from the logs
        (arguments as :meth:`starts_from_logs`): where the diagnosis would end
        ``unexplained`` and this effect came closest but failed the held-out check, it
        refits from these too before it cross-validates
        (:func:`jaxlift.calibrate.diagnose.cross_validate`). None by default."""
        return []

    @classmethod
    def revealed_in(cls, logs: Sequence[Log]) -> str | None:
        """Where ``logs`` already hold the test run of :attr:`revealing_run`: a short
        description of what shows it (which logs, which sections), or None when they do
        not, or when the effect cannot tell (the default). The diagnosis then does not
        ask for a run the user has already made."""
        return None


def rigid_acceleration(plant: Plant, sig: Signals) -> Scalar:
    """Baseline fork-and-load law: ``M a = F - M g`` with ``M = m_load + m_st(x)``."""
    mass = sig.m_load + plant.stage_mass(sig.x)
    return sig.forces / mass - G


class AbstractStatelessEffect(AbstractEffect):
    """An effect without states of its own that keeps the rigid fork-and-load law
    (most effects): fills in the state-related parts of :class:`AbstractEffect`."""

    state_names: ClassVar[tuple[str, ...]] = ()
    state_scales: ClassVar[tuple[float, ...]] = ()
    overrides_acceleration: ClassVar[bool] = False

    def initial_state(self, plant: Plant, sig: Signals) -> Vector:
        return jnp.zeros((0,))
