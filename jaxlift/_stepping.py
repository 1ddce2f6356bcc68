"""Step-size control that steps onto the input's jump times at O(log J) cost per step.

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

:class:`JumpStepSizeController` does the same thing with two binary searches per step
(``jnp.searchsorted``) and keeps the jump times on the controller (a loop constant),
not in its state, which is just the wrapped controller's.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

import diffrax
import equinox as eqx
import equinox.internal as eqxi
import jax.numpy as jnp
from jaxtyping import Array, ArrayLike, Float

__all__ = ["JumpStepSizeController"]

#: ``jnp.searchsorted`` method. "scan_unrolled" (a fixed log2(J) compare-and-halve
#: chain, no inner loop) was the fastest on CPU inside the solver's while loop.
_SEARCH_METHOD = "scan_unrolled"


def _t_at(i, ts: Array):
    """``ts[i]``, but ``inf`` for ``i == len(ts)`` (``i`` in ``0 .. len(ts)``)."""
    n = ts.shape[0]
    if n == 0:
        return jnp.asarray(jnp.inf, dtype=ts.dtype)
    return jnp.where(i >= n, jnp.inf, ts[jnp.minimum(i, n - 1)])


def _first_after(ts: Array, t) -> Array:
    """Index of the first element of the sorted ``ts`` strictly greater than ``t``."""
    if ts.shape[0] == 0:
        return jnp.zeros((), dtype=jnp.int32)
    return jnp.searchsorted(ts, t, side="right", method=_SEARCH_METHOD)


def _clip_before_next_jump(t_end, t_start, ts: Array):
    """Clip ``t_end`` to the float just before the first jump time after ``t_start``."""
    return jnp.minimum(eqxi.prevbefore(_t_at(_first_after(ts, t_start), ts)), t_end)


class JumpStepSizeController(diffrax.AbstractAdaptiveStepSizeController):
    """Wrap an adaptive controller (e.g. ``diffrax.PIDController``) so that the solver
    steps onto the discontinuities of the vector field at ``jump_ts``.

    Semantics are those of ``diffrax.ClipStepSizeController(controller,
    jump_ts=jump_ts)`` (diffrax 0.7.2): each proposed step is clipped to end at
    ``prevbefore(jump)`` for the first jump time after its start; a step that ended at
    ``prevbefore(jump)`` (or at the jump) is followed by one starting at
    ``nextafter(jump)`` (resp. just after it), so the jump itself is never evaluated;
    and ``made_jump`` is reported so that FSAL solvers (``Tsit5``) re-evaluate the
    vector field after the jump. Jump times never reached cost nothing.

    The per-step cost is two binary searches (O(log J)) instead of
    ``ClipStepSizeController``'s two full passes over ``jump_ts``, and the jump times
    are not part of the controller state (the solver loop's carry).

    ``jump_ts`` may be traced and differentiated (e.g. shifted by a fitted delay): the
    clipped step ends are differentiable in the jump times, as with diffrax's own.

    Attributes:
        controller: the wrapped adaptive controller.
        jump_ts: jump times, sorted on construction, floating point, 1-D.
    """

    controller: diffrax.AbstractAdaptiveStepSizeController
    jump_ts: Float[Array, " J"]

    def __init__(
        self,
        controller: diffrax.AbstractAdaptiveStepSizeController,
        jump_ts: Float[ArrayLike, " J"],
    ):
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
        self.jump_ts = jnp.sort(jump_ts)

    @property
    def rtol(self):
        return self.controller.rtol

    @property
    def atol(self):
        return self.controller.atol

    @property
    def norm(self):  # pyright: ignore[reportIncompatibleMethodOverride]
        return self.controller.norm

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
    ) -> tuple[Any, Any]:
        t1, inner_state = self.controller.init(terms, t0, t1, y0, dt0, args, func, error_order)
        ts = self._ts(jnp.result_type(t0))
        return _clip_before_next_jump(t1, t0, ts), inner_state

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
        keep_step, next_t0, next_t1, made_jump, inner_state, result = (
            self.controller.adapt_step_size(
                t0, t1, y0, y1_candidate, args, y_error, error_order, controller_state
            )
        )
        ts = self._ts(jnp.result_type(next_t0))
        n = ts.shape[0]
        if n == 0:
            return keep_step, next_t0, next_t1, made_jump, inner_state, result

        # Did the step end just before a jump (``nextafter(next_t0)`` is one) or on one
        # (``next_t0`` is one)? ts[k - 1] <= next_t0 < ts[k], so these are the only
        # candidates: the equivalent of ClipStepSizeController's two ``jnp.any``.
        k = _first_after(ts, next_t0)
        after = eqxi.nextafter(next_t0)
        before_jump = _t_at(k, ts) == after
        on_jump = (k > 0) & (ts[jnp.maximum(k - 1, 0)] == next_t0)
        # skip the jump time itself (left- or right-discontinuity alike)
        next_t0 = jnp.where(before_jump, eqxi.nextafter(after), next_t0)
        next_t0 = jnp.where(on_jump, after, next_t0)
        made_jump = made_jump | before_jump | on_jump
        # never a zero-length (or negative) next step (diffrax issue #713)
        next_t1 = jnp.maximum(eqxi.nextafter(next_t0), next_t1)
        # end the next step just before the first jump after its start
        next_t1 = _clip_before_next_jump(next_t1, next_t0, ts)
        return keep_step, next_t0, next_t1, made_jump, inner_state, result
