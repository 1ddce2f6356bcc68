"""Step-size control that steps onto the input's jump times at O(1)-O(log J) per step.

``diffrax.ClipStepSizeController(controller, jump_ts=...)`` (diffrax 0.7.2) does what
a zero-order-held input needs -- every step ends just before the next jump time and
the next one starts just after it, so no step straddles a discontinuity of the right-
hand side -- but each step costs O(J) in the number J of jump times, whether or not
they are ever reached:

- ``_bump_next_t0`` tests ``jnp.any(nextafter(t) == jump_ts)`` and
  ``jnp.any(t == jump_ts)``: two passes over all J jump times on every step;
- the jump array itself is part of the controller *state*, i.e. of the solver's
  while-loop carry, so it is copied into every checkpoint of the reverse-mode
  (``RecursiveCheckpointAdjoint``) solve and, in forward mode, its tangents (one
  J-vector per tangent direction) are pushed through every step.

No other way of using ``ClipStepSizeController`` avoids this: ``step_ts`` goes through
the same ``_bump_next_t0`` and the same state, and there is no option that changes it.

:class:`JumpStepSizeController` makes the same decisions from the one or two jump
times next to the step (the index of the next jump time is kept in the controller
state as a hint and checked; a binary search, ``jnp.searchsorted``, is the fallback
when the check fails), and keeps the jump times on the controller (a loop constant),
not in its state.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

import diffrax
import equinox as eqx
import equinox.internal as eqxi
import jax
import jax.numpy as jnp
from jaxtyping import Array, ArrayLike, Float, Int


def _t_at(i, ts: Array):
    """``ts[i]``, but ``inf`` for ``i == len(ts)`` (``i`` in ``0 .. len(ts)``)."""
    n = ts.shape[0]
    return jnp.where(i >= n, jnp.inf, ts[jnp.clip(i, 0, n - 1)])


def _first_after(ts: Array, t) -> Int[Array, ""]:
    """Index of the first element of the sorted ``ts`` strictly greater than ``t``
    (binary search, O(log J))."""
    return jnp.searchsorted(ts, t, side="right").astype(jnp.int32)


def _is_first_after(i, ts: Array, t):
    """Whether ``i`` is the index of the first element of ``ts`` greater than ``t``."""
    return (_t_at(i, ts) > t) & ((i == 0) | (ts[jnp.maximum(i - 1, 0)] <= t))


class AbstractWrappingController(diffrax.AbstractAdaptiveStepSizeController):
    """A step-size controller that wraps another adaptive one and takes its tolerances
    and error norm from it."""

    controller: eqx.AbstractVar[diffrax.AbstractAdaptiveStepSizeController]

    @property
    def rtol(self):
        return self.controller.rtol

    @property
    def atol(self):
        return self.controller.atol

    @property
    def norm(self):  # pyright: ignore[reportIncompatibleMethodOverride]
        return self.controller.norm


class JumpStepSizeController(AbstractWrappingController):
    """Wrap an adaptive controller (e.g. ``diffrax.PIDController``) so that the solver
    steps onto the discontinuities of the vector field at ``jump_ts``.

    The decisions are those of ``diffrax.ClipStepSizeController(controller,
    jump_ts=jump_ts)`` (diffrax 0.7.2), step for step: each proposed step is clipped to
    end at ``prevbefore(jump)`` for the first jump time after its start; a step that
    ended at ``prevbefore(jump)`` (or at the jump) is followed by one starting at
    ``nextafter(jump)`` (resp. just after it), so the jump itself is never evaluated;
    and ``made_jump`` is reported so that FSAL solvers (``Tsit5``) re-evaluate the
    vector field after the jump.

    The cost per step does not grow with the number of jump times: the index of the
    next jump time is carried in the controller state and checked with two
    comparisons; only when the check fails (a jump time listed twice, or a solve
    started elsewhere) does it fall back to a binary search (``jnp.searchsorted``,
    O(log J)). Under ``vmap`` the check and the search both run (``lax.cond`` becomes a
    select), which is still O(log J). The jump times are a constant of the solver's
    loop, not part of its carried state.

    ``jump_ts`` may be traced and differentiated (e.g. shifted by a fitted delay): the
    clipped step ends are differentiable in the jump times, as with diffrax's own.

    Attributes:
        controller: the wrapped adaptive controller.
        jump_ts: jump times, floating point, 1-D, sorted ascending (sorted on
            construction unless ``assume_sorted=True``).
    """

    controller: diffrax.AbstractAdaptiveStepSizeController
    jump_ts: Float[Array, " J"]

    def __init__(
        self,
        controller: diffrax.AbstractAdaptiveStepSizeController,
        jump_ts: Float[ArrayLike, " J"],
        *,
        assume_sorted: bool = False,
    ):
        """**Arguments:**

        - ``controller``: the adaptive controller to wrap.
        - ``jump_ts``: times at which the vector field jumps (1-D, floating point).
        - ``assume_sorted``: skip sorting ``jump_ts`` (an O(J log J) sort per solve);
          only for arrays known to be sorted ascending -- unsorted ones then give wrong
          step ends, silently.
        """
        if not isinstance(controller, diffrax.AbstractAdaptiveStepSizeController):
            raise ValueError(
                f"JumpStepSizeController wraps an adaptive step size controller, got {controller!r}"
            )
        jump_ts = jnp.asarray(jump_ts)
        if jump_ts.ndim != 1:
            raise ValueError(f"jump_ts must be 1-D, got shape {jump_ts.shape}")
        if not jnp.issubdtype(jump_ts.dtype, jnp.floating):
            raise ValueError(f"jump_ts must be floating point, not {jump_ts.dtype}")
        self.controller = controller
        self.jump_ts = jump_ts if assume_sorted else jnp.sort(jump_ts)

    def wrap(self, direction):
        # ``jump_ts`` is sorted ascending, so for direction -1 the negated times sorted
        # ascending are just the reversed negation: O(J), no sort.
        ts = self.jump_ts
        flipped = jnp.where(direction > 0, ts, -ts[::-1])
        return eqx.tree_at(
            lambda s: (s.controller, s.jump_ts),
            self,
            (self.controller.wrap(direction), flipped),
        )

    def _ts(self, t_dtype) -> Array:
        if self.jump_ts.dtype != t_dtype:
            return self.jump_ts.astype(jnp.result_type(self.jump_ts.dtype, t_dtype))
        return self.jump_ts

    def init(
        self,
        terms,
        t0,
        t1,
        y0,
        dt0,
        args,
        func: Callable,
        error_order,
    ) -> tuple[Any, tuple[Int[Array, ""], Any]]:
        t1, inner_state = self.controller.init(terms, t0, t1, y0, dt0, args, func, error_order)
        ts = self._ts(jnp.result_type(t0))
        if ts.shape[0] == 0:
            return t1, (jnp.zeros((), jnp.int32), inner_state)
        k = _first_after(ts, t0)
        # the first step ends just before the first jump time after t0
        return jnp.minimum(eqxi.prevbefore(_t_at(k, ts)), t1), (k, inner_state)

    def adapt_step_size(
        self,
        t0,
        t1,
        y0,
        y1_candidate,
        args,
        y_error,
        error_order,
        controller_state,
    ):
        hint, inner_state = controller_state
        keep_step, next_t0, next_t1, made_jump, inner_state, result = (
            self.controller.adapt_step_size(
                t0, t1, y0, y1_candidate, args, y_error, error_order, inner_state
            )
        )
        ts = self._ts(jnp.result_type(next_t0))
        if ts.shape[0] == 0:
            return keep_step, next_t0, next_t1, made_jump, (hint, inner_state), result

        # k: the first jump time after next_t0. ``hint`` is that for t0, and next_t0 is
        # t0 (rejected step) or t1 <= prevbefore(ts[hint]) (accepted), so it is
        # normally right; checked, with a binary search if not.
        k = jax.lax.cond(
            _is_first_after(hint, ts, next_t0),
            lambda: hint,
            lambda: _first_after(ts, next_t0),
        )
        # Did the step end just before a jump (``nextafter(next_t0)`` is one) or on one
        # (``next_t0`` is one)? With ts[k - 1] <= next_t0 < ts[k] these are the only
        # candidates: ClipStepSizeController's two ``jnp.any`` over all jump times.
        after = eqxi.nextafter(next_t0)
        before_jump = _t_at(k, ts) == after
        on_jump = (k > 0) & (ts[jnp.maximum(k - 1, 0)] == next_t0)
        # skip the jump time itself (left- or right-discontinuity alike)
        next_t0 = jnp.where(before_jump, eqxi.nextafter(after), next_t0)
        next_t0 = jnp.where(on_jump, after, next_t0)
        made_jump = made_jump | before_jump | on_jump
        # never a zero-length (or negative) next step (diffrax issue #713)
        next_t1 = jnp.maximum(eqxi.nextafter(next_t0), next_t1)
        # the first jump time after the (bumped) next_t0: k, or k + 1 after a jump
        # (ts[k - 1] <= next_t0 still holds); checked, binary search if not (a jump time
        # listed twice)
        k_next = k + (_t_at(k, ts) <= next_t0).astype(jnp.int32)
        k_next = jax.lax.cond(
            _t_at(k_next, ts) > next_t0,
            lambda: k_next,
            lambda: _first_after(ts, next_t0),
        )
        # end the next step just before it
        next_t1 = jnp.minimum(eqxi.prevbefore(_t_at(k_next, ts)), next_t1)
        return keep_step, next_t0, next_t1, made_jump, (k_next, inner_state), result


class StabilityLimitedController(AbstractWrappingController):
    """Wrap an adaptive controller and keep every step inside the explicit solver's
    region of absolute stability: ``dt <= limit / rho``, with ``rho`` the spectral radius
    of the vector field's Jacobian ``df/dy``, estimated by one power-iteration step
    (one Jacobian-vector product) per step, the iterate carried in the controller state.

    Why: error control alone keeps the *solution* accurate, but where the solution sits
    at an exact equilibrium (the forks held at rest: every error estimate is zero) it
    lets the step grow to ``dtmax`` although the linearisation is stiff there (the
    Coulomb friction's slope at zero speed over the carriage mass: ~200/s with mast
    compliance, 0.05 s steps, ``|lambda dt| ~ 11`` against Tsit5's ~3.5). The solution does
    not notice (nothing perturbs it), but its forward-mode sensitivities -- the same
    Runge--Kutta map, linearised, and forced by ``df/dtheta`` -- grow by ~10^3 per step:
    measured, a Jacobian column of 1e103 after two seconds of a hold, which stalled the
    Levenberg--Marquardt refits of the diagnosis.

    The power iteration works in coordinates scaled by ``scale`` (the absolute
    tolerances), where the states are of comparable size; the eigenvalues do not depend
    on that scaling. The bound is kept out of the derivatives (``stop_gradient``), like
    diffrax's own step-size factors.

    ``|J w|`` alone is not a bound on ``rho`` when the dominant eigenvalues are a complex
    pair: the iterate then turns in their plane instead of converging, and in scaled
    coordinates the matrix is far from normal, so ``|J w|`` swings below and above
    ``rho``. Measured on a mast-compliance log held at rest (eigenvalues -250 +- 309i,
    ``rho`` = 398/s): ``|J w|`` between 50 and 2 900/s, steps of up to 0.05 s
    (``|lambda dt|`` = 20), and a Jacobian column of 1.7e114, which gave the posterior's
    walkers a covariance of 1e-218, so emcee refused to start. Each step therefore takes
    two Arnoldi steps, ``J w`` and ``J (J w)`` (two Jacobian-vector products, at the same
    point), and the estimate is the larger of ``|J w|`` and the Ritz values' modulus on
    ``span{w, J w}``: exact for a pair whose plane the iterate has found. (Ritz values
    from the last two iterates, for one product per step, are not enough: in such
    scaled coordinates successive iterates are often nearly parallel, measured on a
    2-state oscillator, and the steps in between still explode.)

    Attributes:
        controller: the wrapped adaptive controller.
        vector_field: ``(t, y, args) -> dy/dt``.
        scale: per-state scale of ``y`` (e.g. the absolute tolerances).
        limit: ``|lambda dt|`` allowed (Tsit5's real stability interval is about
            [-3.5, 0]; 2.5 leaves a margin for complex eigenvalues).
    """

    controller: diffrax.AbstractAdaptiveStepSizeController
    vector_field: Callable = eqx.field(static=True)
    scale: Float[Array, " S"]
    limit: float = eqx.field(static=True, default=2.5)

    def wrap(self, direction):
        return eqx.tree_at(lambda s: s.controller, self, self.controller.wrap(direction))

    def _power_step(self, t, y, args, w):
        """One power-iteration step in scaled coordinates, with a two-step Arnoldi
        estimate: (new unit iterate, ``max(|J w|, Ritz radius on span{w, J w})``)."""
        t, y, w = jax.lax.stop_gradient((t, y, w))
        # linearised once: the two products share one evaluation of the vector field
        _, f_jvp = jax.linearize(lambda yy: self.vector_field(t, yy, args), y)

        def jvp(v):
            return jax.lax.stop_gradient(f_jvp(self.scale * v) / self.scale)

        jw = jvp(w)
        rho = jnp.sqrt(jnp.sum(jw**2))
        ok = jnp.isfinite(rho) & (rho > 0)
        w_new = jnp.where(ok, jw / jnp.where(ok, rho, 1.0), w)
        est = jnp.maximum(rho, _ritz_radius(w, jw, rho, jvp(w_new)))
        return w_new, jnp.where(ok & jnp.isfinite(est), est, 0.0)

    def _clip(self, t0, t1, rho):
        return jnp.where(rho > 0, jnp.minimum(t1, t0 + self.limit / jnp.maximum(rho, 1e-300)), t1)

    def init(self, terms, t0, t1, y0, dt0, args, func: Callable, error_order):
        t1, inner = self.controller.init(terms, t0, t1, y0, dt0, args, func, error_order)
        n = jnp.shape(y0)[0]
        # a start vector with a component along every state, then a few iterations
        w = jnp.ones(n, dtype=jnp.result_type(y0)) / jnp.sqrt(n) * (1.0 + jnp.arange(n) / n)
        w = w / jnp.sqrt(jnp.sum(w**2))
        rho = jnp.zeros((), jnp.result_type(y0))
        for _ in range(4):
            w, rho = self._power_step(t0, y0, args, w)
        return self._clip(t0, t1, rho), (w, inner)

    def adapt_step_size(
        self, t0, t1, y0, y1_candidate, args, y_error, error_order, controller_state
    ):
        w, inner = controller_state
        keep_step, next_t0, next_t1, made_jump, inner, result = self.controller.adapt_step_size(
            t0, t1, y0, y1_candidate, args, y_error, error_order, inner
        )
        t_at = jnp.where(keep_step, t1, t0)
        y_at = jnp.where(keep_step, y1_candidate, y0)
        w, rho = self._power_step(t_at, y_at, args, w)
        next_t1 = self._clip(next_t0, next_t1, rho)
        return keep_step, next_t0, next_t1, made_jump, (w, inner), result


#: Smallest ``|J w - (w . J w) w| / |J w|`` for which ``span{w, J w}`` gives a Ritz
#: value: below it ``w`` is an eigenvector to that accuracy and ``|J w|`` is right.
RITZ_MIN_SINE = 1e-8


def _ritz_radius(w, jw, rho, jjw_unit):
    """Largest modulus of the two Ritz values of ``J`` on ``span{w, J w}`` (Arnoldi),
    from the unit ``w``, ``jw = J w``, ``rho = |J w|`` and ``jjw_unit = J (J w / rho)``;
    0 where ``w`` is (to ``RITZ_MIN_SINE``) an eigenvector."""
    h11 = jnp.sum(w * jw)
    u = jw - h11 * w
    h21 = jnp.sqrt(jnp.sum(u**2))
    ok = (h21 > RITZ_MIN_SINE * rho) & jnp.isfinite(h21)
    h21_safe = jnp.where(ok, h21, 1.0)
    q2 = u / h21_safe
    jq2 = (rho * jjw_unit - h11 * jw) / h21_safe  # J q2 = (J J w - h11 J w) / h21
    h12, h22 = jnp.sum(w * jq2), jnp.sum(q2 * jq2)
    half_tr, det = 0.5 * (h11 + h22), h11 * h22 - h12 * h21
    disc = half_tr**2 - det
    real = jnp.abs(half_tr) + jnp.sqrt(jnp.maximum(disc, 0.0))  # two real Ritz values
    pair = jnp.sqrt(jnp.maximum(det, 0.0))  # a complex pair: |lambda|^2 = det
    radius = jnp.where(disc >= 0, real, pair)
    return jnp.where(ok & jnp.isfinite(radius), radius, 0.0)
