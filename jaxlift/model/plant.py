"""The baseline lift plant of docs/model.md: every component as its own small function.

Chain: voltage unit -> DC motor (static map per stage) -> pump -> check valve ->
cylinder with compressible oil (capacitance ``C = V/beta``) -> friction -> fork and
load. Stage-dependent quantities are blended smoothly with ``s_j(x)`` (docs/model.md).

Units: SI throughout (m, m/s, Pa, kg, N, s, rad/s, m^3).
"""

from __future__ import annotations

import math

import equinox as eqx
import jax.numpy as jnp
from jaxtyping import Array, ArrayLike, Float

from .constants import END_STOP_OMEGA, END_STOP_ZETA, MAST_HEIGHT_M, X_S1, X_S2, G
from .params import param, param_infos

_INF = math.inf

Scalar = Float[Array, ""]


class Plant(eqx.Module):
    """Parameters and component laws of the baseline lift (docs/model.md, nominal values).

    Fields declared with :func:`~jaxlift.param` are physical parameters (names as in
    docs/model.md and in parameter files). The geometry constants below them are static.
    """

    u_batt: Scalar = param(24.0, "V", 1.0, 100.0, "battery voltage of the voltage unit")
    k1: Scalar = param(1.9, "rad/(s V)", 0.05, 20.0, "motor map gain, stage 1", spread=1.1)
    k2: Scalar = param(1.8, "rad/(s V)", 0.05, 20.0, "motor map gain, stage 2", spread=1.1)
    k3: Scalar = param(1.7, "rad/(s V)", 0.05, 20.0, "motor map gain, stage 3", spread=1.1)
    z1: Scalar = param(-3.0, "rad/s", -40.0, 20.0, "motor map offset, stage 1", spread=1.3)
    z2: Scalar = param(-3.5, "rad/s", -40.0, 20.0, "motor map offset, stage 2", spread=1.3)
    z3: Scalar = param(-4.0, "rad/s", -40.0, 20.0, "motor map offset, stage 3", spread=1.3)
    disp: Scalar = param(43e-6, "m^3/rev", 1e-7, 1e-3, "pump displacement")
    eta_v: Scalar = param(0.95, "-", 0.3, 1.0, "pump volumetric efficiency", transform="logit")
    A1: Scalar = param(28.27e-4, "m^2", 1e-5, 0.1, "piston area, stage 1")
    A2: Scalar = param(22.68e-4, "m^2", 1e-5, 0.1, "piston area, stage 2 (both cylinders)")
    A3: Scalar = param(22.68e-4, "m^2", 1e-5, 0.1, "piston area, stage 3 (both cylinders)")
    ratio: Scalar = param(2.0, "-", 0.5, 10.0, "fork speed / piston speed (chain)")
    m_st1: Scalar = param(100.0, "kg", 0.0, 5000.0, "mass moved in stage 1 (carriage)")
    m_st2: Scalar = param(145.0, "kg", 0.0, 5000.0, "mass added in stage 2 (inner mast)")
    m_st3: Scalar = param(140.0, "kg", 0.0, 5000.0, "mass added in stage 3 (middle mast)")
    V0: Scalar = param(2.0e-3, "m^3", 1e-5, 0.1, "oil volume under pressure at x = 0")
    beta: Scalar = param(1.4e9, "Pa", 1e7, 1e10, "effective bulk modulus of the oil", spread=4.0)
    cf_con: Scalar = param(10.0, "N", 0.0, 1e4, "Coulomb friction", spread=3.0)
    cf_in: Scalar = param(16.0, "s/m", 0.0, 200.0, "friction speed scale (inner)")
    cf_out: Scalar = param(545.0, "N", 0.0, 1e6, "friction fifth-power coefficient", spread=3.0)
    d: Scalar = param(300.0, "N s/m", 0.0, 1e5, "viscous damping", spread=3.0)

    x_s1: float = eqx.field(static=True, default=X_S1)  # m, stage boundary 1 -> 2
    x_s2: float = eqx.field(static=True, default=X_S2)  # m, stage boundary 2 -> 3
    x_max: float = eqx.field(static=True, default=MAST_HEIGHT_M)  # m, full height
    w_blend: float = eqx.field(static=True, default=5e-3)  # m, blending width
    v_eps: float = eqx.field(static=True, default=1e-3)  # m/s, Coulomb smoothing
    omega_es: float = eqx.field(static=True, default=END_STOP_OMEGA)  # rad/s, bottom stop
    zeta_es: float = eqx.field(static=True, default=END_STOP_ZETA)  # -, bottom stop damping

    # -------------------------------------------------------------- stages
    def blend(self, x: Scalar) -> tuple[Scalar, Scalar]:
        """Stage switches ``s_1(x), s_2(x)`` in [0, 1] (docs/model.md)."""
        s1 = 0.5 * (1.0 + jnp.tanh((x - self.x_s1) / self.w_blend))
        s2 = 0.5 * (1.0 + jnp.tanh((x - self.x_s2) / self.w_blend))
        return s1, s2

    def staged(self, x: Scalar, q1: ArrayLike, q2: ArrayLike, q3: ArrayLike) -> Scalar:
        """``q(x) = q1 + (q2 - q1) s1(x) + (q3 - q2) s2(x)``."""
        s1, s2 = self.blend(x)
        return q1 + (q2 - q1) * s1 + (q3 - q2) * s2

    def area(self, x: Scalar) -> Scalar:
        """Active piston area ``A(x)`` [m^2]."""
        return self.staged(x, self.A1, self.A2, self.A3)

    def stage_mass(self, x: Scalar) -> Scalar:
        """Cumulative moving structure mass ``m_st(x)`` [kg]."""
        return self.staged(
            x, self.m_st1, self.m_st1 + self.m_st2, self.m_st1 + self.m_st2 + self.m_st3
        )

    def volume(self, x: Scalar) -> Scalar:
        """Oil volume under pressure ``V(x)`` [m^3], continuous in ``x``."""
        stroke = (
            self.A1 * jnp.clip(x, 0.0, self.x_s1)
            + self.A2 * jnp.clip(x - self.x_s1, 0.0, self.x_s2 - self.x_s1)
            + self.A3 * jnp.maximum(x - self.x_s2, 0.0)
        )
        return self.V0 + stroke / self.ratio

    # -------------------------------------------------------------- components
    def voltage(self, u: Scalar) -> Scalar:
        """Voltage unit: ``U = u U_batt`` [V]."""
        return u * self.u_batt

    def motor_map(self, x: Scalar, voltage: Scalar) -> Scalar:
        """Unclipped static motor map ``k(x) U + z(x)`` [rad/s]."""
        k = self.staged(x, self.k1, self.k2, self.k3)
        z = self.staged(x, self.z1, self.z2, self.z3)
        return k * voltage + z

    def pump_flow(self, omega: Scalar) -> Scalar:
        """Pump: ``Q = eta_v D omega / (2 pi)`` [m^3/s]."""
        return self.eta_v * self.disp * omega / (2.0 * jnp.pi)

    def friction(self, v: Scalar) -> Scalar:
        """Baseline friction force opposing motion [N] (docs/model.md item 6)."""
        return self.cf_con * jnp.tanh(v / self.v_eps) + self.cf_out * (self.cf_in * v) ** 5

    def end_stop_force(self, x: Scalar, v: Scalar, m_load: Scalar) -> Scalar:
        """Force of the bottom end stop on the carriage [N], upward: a stiff one-sided
        contact below ``x = 0``, nothing above. With the depth ``delta = -x > 0``:

            F = max(0, k delta (1 + lambda delta')),   k = M w^2,   lambda = 2 zeta w / g

        a Hunt--Crossley contact (damping grows with the depth, so the force starts at 0
        on touching instead of jumping with the impact speed) whose stiffness scales with
        the moving mass ``M = m_load + m_st(x)``. At rest on the stop the depth is
        ``g / w^2`` (0.11 mm) and the damping there ``2 zeta M w`` (critical). See
        :data:`jaxlift.model.constants.END_STOP_OMEGA` for why this differs from the
        specification's fixed spring-damper. The top of the mast has no stop: a run that
        reaches it is reported as out of range."""
        mass = m_load + self.stage_mass(x)
        w = self.omega_es
        # jnp.where, not jnp.maximum: at a tie (a fork resting exactly at x = 0, as a
        # log that starts on the stop does until the pressure lifts it) maximum's
        # derivative is 1/2, which hands the forward-mode tangent half the contact
        # stiffness while the primal feels none; the explicit solver, stepping for the
        # primal, then lets the tangent blow up (measured: d r / d x0-offset 1.6e19
        # where finite differences give 175, and every fit on such a log stalled)
        depth = jnp.where(x < 0.0, -x, 0.0)
        push = mass * w * w * depth * (1.0 - 2.0 * self.zeta_es * w * v / G)
        return jnp.where(push > 0.0, push, 0.0)

    def static_pressure(self, x: Scalar, m_load: Scalar) -> Scalar:
        """Pressure holding the fork at rest, ``M(x) g r / A(x)`` [Pa]."""
        return (m_load + self.stage_mass(x)) * G * self.ratio / self.area(x)


PLANT_PARAMS = param_infos(Plant)
