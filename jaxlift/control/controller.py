"""The lift controller of docs/control.md: a filtered PID with back-calculation anti-windup,
plain or gain-scheduled by stage and load mass.

The law (docs/control.md, thesis 2.17 and figure 2.12), for the error ``e = v_ref - v_meas``
[m/s] and the controller states ``q_I`` (integral term, duty) and ``eta`` (derivative
filter, m/s)::

    d eta/dt = N (e - eta)
    u_raw    = P e + q_I + D N (e - eta)
    u        = clip(u_raw, 0, 1)
    d q_I/dt = I e + K_aw (u - u_raw)

Stops: where ``v_ref == 0`` the valve is closed (``u = 0``) and the states are held.

Units of the gains (duty per ...): ``P`` [s/m] (duty per m/s of error), ``I`` [1/m]
(duty per m of integrated error), ``D`` [s^2/m] (duty per m/s^2), ``N`` [1/s] (filter
bandwidth), ``K_aw`` [1/s] (back-calculation gain; 0 = no anti-windup).

Gain scheduling (thesis 2.18--2.20): one PID per stage, each gain linear in the load
mass ``m_load`` [kg], ``G_i(m) = G_b,i + G_m,i m`` for ``G`` in ``P, I, D`` and stage
``i = 1, 2, 3``; the three are blended with the plant's stage switches ``s_j(x)``.
In files the 18 numbers are named ``P_b1, P_m1, I_b1, I_m1, D_b1, D_m1, ..., D_m3``
(``G_b,i`` -> ``G_bi``, ``G_m,i`` -> ``G_mi``); ``N`` and ``K_aw`` are shared.
A scheduled gain that becomes negative at some load is clipped at 0 in the law.
"""

from __future__ import annotations

import abc
import json
import math
import os
from collections.abc import Mapping
from typing import ClassVar

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, ArrayLike, Float

from ..model.constants import SAMPLE_PERIOD_S
from ..model.params import (
    ParameterError,
    get_params,
    load_params_json,
    param,
    param_infos,
    replace_params,
)
from ..model.plant import Plant

Scalar = Float[Array, ""]

#: Default controller clock of the sampled form [s] (docs/control.md).
DEFAULT_TC = SAMPLE_PERIOD_S
#: Loads at which a scheduled PID's gains are tuned and between which they are
#: interpolated (thesis 2.4.2) [kg].
SCHEDULE_MASSES = (500.0, 1500.0)


class ControlOutput(eqx.Module):
    """The controller's output and state derivatives at one instant.

    Attributes:
        u: duty cycle sent to the plant, in [0, 1] (0 while stopped).
        u_raw: unsaturated law ``P e + q_I + D N (e - eta)`` [-].
        dq_I: derivative of the integral state [1/s] (0 while stopped).
        deta: derivative of the filter state [m/s^2] (0 while stopped).
    """

    u: Scalar
    u_raw: Scalar
    dq_I: Scalar
    deta: Scalar


class AbstractController(eqx.Module):
    """A filtered PID with back-calculation anti-windup whose gains ``P, I, D`` may
    depend on the height [m] and the load mass [kg] (:meth:`gains`).

    Concrete controllers provide the gains; the law itself (:meth:`output`) and its
    sampled form (:meth:`sampled_update`) are shared and final.
    """

    N: eqx.AbstractVar[Scalar]
    K_aw: eqx.AbstractVar[Scalar]

    kind: eqx.AbstractClassVar[str]

    @abc.abstractmethod
    def gains(self, plant: Plant, x: Scalar, m_load: Scalar) -> tuple[Scalar, Scalar, Scalar]:
        """``(P [s/m], I [1/m], D [s^2/m])`` at height ``x`` [m] with load ``m_load`` [kg]."""

    def _raw(self, plant, x, m_load, e, q_I, eta):
        """``(I, u_raw)``: the integral gain and ``P e + q_I + D N (e - eta)``."""
        P, I, D = self.gains(plant, x, m_load)  # noqa: E741
        return I, P * e + q_I + D * self.N * (e - eta)

    def output(
        self,
        plant: Plant,
        x: Scalar,
        m_load: Scalar,
        e: Scalar,
        q_I: Scalar,
        eta: Scalar,
        moving: ArrayLike,
        sat_gain: ArrayLike | None = None,
    ) -> ControlOutput:
        """The continuous-time law at one instant.

        Args:
            plant: for the stage switches of a scheduled controller.
            x: (measured) height [m]; m_load: load [kg].
            e: error ``v_ref - v_meas`` [m/s]; q_I: integral state [-]; eta: filter [m/s].
            moving: False where ``v_ref == 0`` (valve shut, states held).
            sat_gain: None for the saturation ``clip(u_raw, 0, 1)``; a number ``g``
                keeps the value ``clip(u_raw)`` but gives ``du/du_raw = g`` to autodiff
                (the describing-gain linearisation of :mod:`jaxlift.control.tune`).
        """
        I, u_raw = self._raw(plant, x, m_load, e, q_I, eta)  # noqa: E741
        u = jnp.clip(u_raw, 0.0, 1.0)
        if sat_gain is not None:  # value clip(u_raw), derivative sat_gain
            u = jax.lax.stop_gradient(u) + sat_gain * (u_raw - jax.lax.stop_gradient(u_raw))
        dq = I * e + self.K_aw * (u - u_raw)
        deta = self.N * (e - eta)
        zero = jnp.zeros_like(u_raw)
        return ControlOutput(
            u=jnp.where(moving, u, zero),
            u_raw=u_raw,
            dq_I=jnp.where(moving, dq, zero),
            deta=jnp.where(moving, deta, zero),
        )

    def sampled_update(
        self,
        plant: Plant,
        x: Scalar,
        m_load: Scalar,
        e: Scalar,
        q_I: Scalar,
        eta: Scalar,
        moving: ArrayLike,
        T_c: float,
    ) -> tuple[Scalar, Scalar, Scalar, Scalar]:
        """One step of the sampled law (clock ``T_c`` [s], docs/control.md): the filter
        discretised exactly, the integral by forward Euler.

        Returns ``(u, u_raw, q_I_next, eta_next)``; ``u`` is held for one period."""
        I, u_raw = self._raw(plant, x, m_load, e, q_I, eta)  # noqa: E741
        u = jnp.clip(u_raw, 0.0, 1.0)
        q_next = q_I + T_c * (I * e + self.K_aw * (u - u_raw))
        eta_next = eta + (1.0 - jnp.exp(-self.N * T_c)) * (e - eta)
        return (
            jnp.where(moving, u, 0.0),
            u_raw,
            jnp.where(moving, q_next, q_I),
            jnp.where(moving, eta_next, eta),
        )

    def with_gains(self, values: Mapping[str, ArrayLike]) -> AbstractController:
        """A copy with the named gains replaced (names as in gains files; jit-safe)."""
        return replace_params(self, values)

    def gain_values(self) -> dict[str, float]:
        """The gains as ``{name: value}`` (floats, file units)."""
        return {k: float(np.asarray(v)) for k, v in get_params(self).items()}


_P = dict(unit="s/m", lower=0.0, upper=1e4, description="proportional gain (duty per m/s)")
_I = dict(unit="1/m", lower=0.0, upper=1e5, description="integral gain (duty per m)")
_D = dict(unit="s^2/m", lower=0.0, upper=1e3, description="derivative gain (duty per m/s^2)")
_N = dict(unit="1/s", lower=0.0, upper=1e6, description="derivative filter bandwidth")
_K = dict(unit="1/s", lower=0.0, upper=1e5, description="back-calculation anti-windup gain")


def _p(nominal, spec, **kw):
    return param(nominal, spec["unit"], spec["lower"], spec["upper"], spec["description"], **kw)


class PID(AbstractController):
    """The plain filtered PID of docs/control.md (thesis gains by default: ``P=20, I=300,
    D=2, N=100``, no anti-windup)."""

    P: Scalar = _p(20.0, _P)
    I: Scalar = _p(300.0, _I)  # noqa: E741
    D: Scalar = _p(2.0, _D)
    N: Scalar = _p(100.0, _N)
    K_aw: Scalar = _p(0.0, _K)

    kind: ClassVar[str] = "PID"

    def gains(self, plant, x, m_load):
        return self.P, self.I, self.D


def _sched(g: str, kind: str, stage: int, nominal: float):
    base = {"P": _P, "I": _I, "D": _D}[g]
    unit = base["unit"] if kind == "b" else f"{base['unit']}/kg"
    what = "at zero load" if kind == "b" else "per kg of load"
    return param(
        nominal,
        unit,
        -math.inf,
        math.inf,
        f"{g} gain of stage {stage}, {what} (G_{kind},{stage})",
        transform="identity",
    )


class ScheduledPID(AbstractController):
    """The gain-scheduled PID of thesis 2.4.2: ``G_i(m) = G_b,i + G_m,i m`` per stage
    ``i`` and gain ``G`` in ``P, I, D``, blended by the plant's stage switches. The
    defaults reproduce the plain thesis PID (``G_b = 20, 300, 2``; ``G_m = 0``)."""

    P_b1: Scalar = _sched("P", "b", 1, 20.0)
    P_m1: Scalar = _sched("P", "m", 1, 0.0)
    I_b1: Scalar = _sched("I", "b", 1, 300.0)
    I_m1: Scalar = _sched("I", "m", 1, 0.0)
    D_b1: Scalar = _sched("D", "b", 1, 2.0)
    D_m1: Scalar = _sched("D", "m", 1, 0.0)
    P_b2: Scalar = _sched("P", "b", 2, 20.0)
    P_m2: Scalar = _sched("P", "m", 2, 0.0)
    I_b2: Scalar = _sched("I", "b", 2, 300.0)
    I_m2: Scalar = _sched("I", "m", 2, 0.0)
    D_b2: Scalar = _sched("D", "b", 2, 2.0)
    D_m2: Scalar = _sched("D", "m", 2, 0.0)
    P_b3: Scalar = _sched("P", "b", 3, 20.0)
    P_m3: Scalar = _sched("P", "m", 3, 0.0)
    I_b3: Scalar = _sched("I", "b", 3, 300.0)
    I_m3: Scalar = _sched("I", "m", 3, 0.0)
    D_b3: Scalar = _sched("D", "b", 3, 2.0)
    D_m3: Scalar = _sched("D", "m", 3, 0.0)
    N: Scalar = _p(100.0, _N)
    K_aw: Scalar = _p(0.0, _K)

    kind: ClassVar[str] = "ScheduledPID"

    def stage_gains(self, m_load: ArrayLike) -> Float[Array, "3 3"]:
        """Gains per stage (rows 1..3) and kind (columns P, I, D) at ``m_load`` [kg],
        clipped at 0."""
        g = [
            [getattr(self, f"{k}_b{i}") + getattr(self, f"{k}_m{i}") * m_load for k in "PID"]
            for i in (1, 2, 3)
        ]
        return jnp.maximum(jnp.asarray(g), 0.0)

    def gains(self, plant, x, m_load):
        g = self.stage_gains(m_load)
        return tuple(plant.staged(x, g[0, j], g[1, j], g[2, j]) for j in range(3))

    @classmethod
    def from_pid(cls, pid: PID) -> ScheduledPID:
        """The scheduled PID equal to ``pid`` at every stage and load."""
        values = {f"{k}_b{i}": getattr(pid, k) for k in "PID" for i in (1, 2, 3)}
        values.update({f"{k}_m{i}": 0.0 for k in "PID" for i in (1, 2, 3)})
        values.update(N=pid.N, K_aw=pid.K_aw)
        return replace_params(cls(), values)

    @classmethod
    def from_stage_gains(
        cls,
        g_lo: ArrayLike,
        g_hi: ArrayLike,
        N: ArrayLike,
        K_aw: ArrayLike,
        masses: tuple[float, float] = SCHEDULE_MASSES,
    ) -> ScheduledPID:
        """From the gains at two loads (thesis 2.4.2): ``g_lo``, ``g_hi`` of shape (3, 3)
        (stage x [P, I, D]) at ``masses`` [kg]; linear in between (jit-safe)."""
        m0, m1 = masses
        g_lo, g_hi = jnp.asarray(g_lo), jnp.asarray(g_hi)
        slope = (g_hi - g_lo) / (m1 - m0)
        base = g_lo - slope * m0
        values = {}
        for i in range(3):
            for j, k in enumerate("PID"):
                values[f"{k}_b{i + 1}"] = base[i, j]
                values[f"{k}_m{i + 1}"] = slope[i, j]
        values.update(N=N, K_aw=K_aw)
        return replace_params(cls(), values)


#: Thesis gains (docs/control.md): PI of figure 3.9, PID of 3.10, PID with noise of 3.14.
THESIS_PI = dict(P=20.0, I=120.0, D=0.0, N=100.0, K_aw=0.0)
THESIS_PID = dict(P=20.0, I=300.0, D=2.0, N=100.0, K_aw=0.0)
THESIS_PID_NOISE = dict(P=20.0, I=300.0, D=3.0, N=10000.0, K_aw=0.0)

_CONTROLLERS: dict[str, type[AbstractController]] = {"PID": PID, "ScheduledPID": ScheduledPID}


def controller_from_gains(values: Mapping[str, float], *, source: str = "") -> AbstractController:
    """A :class:`PID` or :class:`ScheduledPID` from ``{name: value}`` (file names).

    The class is the one that knows all the names (scheduled names such as ``P_b1``
    select :class:`ScheduledPID`). Unknown names, non-finite values, negative plain
    gains, and scheduled gains negative at a load in [0, 3000] kg raise
    :class:`~jaxlift.ParameterError` naming the gain."""
    where = f"{source}: " if source else ""
    values = {k: v for k, v in values.items() if not k.startswith("_")}
    sched_names = set(param_infos(ScheduledPID)) - {"N", "K_aw"}
    cls: type[AbstractController] = ScheduledPID if set(values) & sched_names else PID
    infos = param_infos(cls)
    unknown = sorted(set(values) - set(infos))
    if unknown:
        raise ParameterError(
            f"{where}unknown gain(s) {unknown} for a {cls.kind}; known gains: {list(infos)} "
            "(plain PID: P, I, D, N, K_aw; scheduled: P_b1, P_m1, ..., D_m3, N, K_aw)"
        )
    for name, value in values.items():
        infos[name].check(value, source=source)
    ctrl = replace_params(cls(), {k: float(v) for k, v in values.items()})
    if isinstance(ctrl, ScheduledPID):
        for i in (1, 2, 3):
            for k in "PID":
                b = float(getattr(ctrl, f"{k}_b{i}"))
                m = float(getattr(ctrl, f"{k}_m{i}"))
                for load in (0.0, 3000.0):
                    if b + m * load < 0:
                        raise ParameterError(
                            f"{where}gain {k}_b{i} + {k}_m{i} * m = {b + m * load:.4g} is "
                            f"negative at m = {load:g} kg; scheduled gains must stay >= 0 "
                            "for loads in [0, 3000] kg"
                        )
    return ctrl


def load_gains(path: str | os.PathLike) -> AbstractController:
    """Read a gains file (JSON ``{name: value}``, names from docs/control.md; keys starting
    with ``_`` are comments) into a controller (see :func:`controller_from_gains`)."""
    known = {**param_infos(PID), **param_infos(ScheduledPID)}
    return controller_from_gains(load_params_json(path, known), source=os.fspath(path))


def save_gains(
    path: str | os.PathLike, controller: AbstractController, comment: str | None = None
) -> None:
    """Write a controller's gains as JSON with their units (key ``_units``) and a
    comment; loadable with :func:`load_gains` and ``jaxlift control simulate``."""
    infos = param_infos(controller)
    data: dict[str, object] = {}
    if comment:
        data["_comment"] = comment
    data["_controller"] = controller.kind
    data["_units"] = {k: i.unit for k, i in infos.items()}
    data.update(controller.gain_values())
    with open(os.fspath(path), "w", encoding="utf-8") as fh:
        json.dump(data, fh, indent=2)
        fh.write("\n")
