"""The space the tuner works in: the controller's gains on a log scale, with floors
that keep them physical.
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import equinox as eqx
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Float

from ..model.params import ParameterError
from .controller import SCHEDULE_MASSES, AbstractController, ScheduledPID

_FLOORS = {"D": 0.05, "K_aw": None, "N": 10.0, "P": 1.0, "I": 10.0}


# ------------------------------------------------------------------ gain coordinates
class GainSpace(eqx.Module):
    """Log coordinates of the tuned gains of a controller (see the module docstring).

    Attributes:
        template: the controller whose untuned gains are kept.
        names: coordinate names (``P``, ``I``, ... for a PID; ``P1@500``, ``P1@1500``,
            ..., ``N``, ``K_aw`` for a scheduled PID).
    """

    template: AbstractController
    names: tuple[str, ...] = eqx.field(static=True)

    @classmethod
    def for_controller(
        cls, controller: AbstractController, names: Sequence[str] | None = None
    ) -> GainSpace:
        """Coordinates for ``controller``: ``names`` of the gains to tune (default: all
        of P, I, D, N, K_aw for a PID; the 18 stage gains, N and K_aw for a scheduled
        PID; give a subset to keep some fixed, e.g. without ``K_aw``)."""
        if isinstance(controller, ScheduledPID):
            stage = [f"{k}{i}@{m:g}" for i in (1, 2, 3) for k in "PID" for m in SCHEDULE_MASSES]
            allowed = stage + ["N", "K_aw"]
        else:
            allowed = ["P", "I", "D", "N", "K_aw"]
        names = tuple(allowed if names is None else names)
        bad = [n for n in names if n not in allowed]
        if bad:
            raise ParameterError(f"cannot tune {bad}; tunable gains: {allowed}")
        return cls(template=controller, names=names)

    def _values(self, ctrl: AbstractController) -> dict[str, Array]:
        out = {}
        if isinstance(ctrl, ScheduledPID):
            for m in SCHEDULE_MASSES:
                g = ctrl.stage_gains(m)
                for i in range(3):
                    for j, k in enumerate("PID"):
                        out[f"{k}{i + 1}@{m:g}"] = g[i, j]
            out["N"], out["K_aw"] = ctrl.N, ctrl.K_aw
        else:
            out = {k: getattr(ctrl, k) for k in ("P", "I", "D", "N", "K_aw")}
        return out

    def to_theta(self, ctrl: AbstractController) -> Float[np.ndarray, " n"]:
        """Log coordinates of ``ctrl``'s tuned gains (zeros raised to a floor)."""
        vals = {k: float(np.asarray(v)) for k, v in self._values(ctrl).items()}
        out = []
        for n in self.names:
            v = vals[n]
            if v <= 0:
                base = n.split("@")[0].rstrip("123")
                if base == "K_aw":
                    v = max(vals.get("I", 300.0) / max(vals.get("P", 20.0), 1e-3), 1.0)
                else:
                    v = _FLOORS[base]
            out.append(math.log(v))
        return np.asarray(out)

    def from_theta(self, theta: Float[Array, " n"]) -> AbstractController:
        """The controller with the tuned gains ``exp(theta)`` (jit/grad-safe)."""
        vals = dict(self._values(self.template))
        for i, n in enumerate(self.names):
            vals[n] = jnp.exp(theta[i])
        if isinstance(self.template, ScheduledPID):
            g = [
                jnp.asarray(
                    [[vals[f"{k}{i}@{m:g}"] for k in "PID"] for i in (1, 2, 3)], dtype=jnp.float64
                )
                for m in SCHEDULE_MASSES
            ]
            return ScheduledPID.from_stage_gains(g[0], g[1], vals["N"], vals["K_aw"])
        return self.template.with_gains({k: vals[k] for k in ("P", "I", "D", "N", "K_aw")})

    def local_values(self, theta: Float[Array, " n"], m_load) -> Float[Array, " 11"]:
        """Scheduled PID: what the loop at load ``m_load`` sees of ``theta`` -- the nine
        stage gains at that load, ``N`` and ``K_aw`` (11 numbers, linear units). A run
        at one load depends on the 18 + 2 coordinates only through these, so its
        Jacobian needs 11 forward-mode tangents instead of one per coordinate."""
        ctrl = self.from_theta(theta)
        f64 = lambda a: jnp.asarray(a, dtype=jnp.float64)  # noqa: E731
        return jnp.concatenate(
            [f64(ctrl.stage_gains(m_load)).ravel(), jnp.stack([f64(ctrl.N), f64(ctrl.K_aw)])]
        )

    @staticmethod
    def local_controller(values: Float[Array, " 11"]) -> ScheduledPID:
        """The scheduled PID with the gains ``values`` (:meth:`local_values`) at every
        load: the same loop as the full controller at that load."""
        g = values[:9].reshape(3, 3)
        return ScheduledPID.from_stage_gains(g, g, values[9], values[10])
