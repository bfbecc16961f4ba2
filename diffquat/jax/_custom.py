"""Custom derivatives for jax: one ``custom_jvp`` per core map whose library derivative is unstable
(SVD, eigh) or slow (matrix_to_quaternion). The formulas live in the core, over ``xp``; this only
registers them."""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

import jax
from jax import Array

from ._namespace import XP

Formula = Callable[[Any, Array, Array, Array], Array]


Rule = Callable[[Callable[[Array], Array], Array, Array], tuple[Array, Array]]


def _registered(forward: Callable[[Any, Array], Array], rule: Rule) -> Callable[[Any, Array], Array]:
    """``forward(xp, x)`` as a ``custom_jvp`` whose rule is ``rule(fn, x, dx) -> (y, dy)`` (``fn`` the
    registered function itself), bound as ``(xp, x)`` like the core functions."""

    @jax.custom_jvp
    def fn(x: Array) -> Array:
        return forward(XP, x)

    @fn.defjvp
    def fn_jvp(primals: tuple[Array], tangents: tuple[Array]) -> tuple[Array, Array]:
        (x,), (dx,) = primals, tangents
        return rule(fn, x, dx)

    def bound(xp: Any, x: Array) -> Array:
        return fn(x)

    bound.__name__ = forward.__name__  # the Backend validates arguments by this name
    return bound


def custom_derivative(
    forward: Callable[[Any, Array], Array], tangent: Formula, cotangent: Formula | None = None
) -> Callable[[Any, Array], Array]:
    """``forward(xp, x) -> y`` with the forward-mode derivative ``tangent(xp, x, y, dx) -> dy``.

    A ``custom_jvp`` (not ``custom_vjp``): jax transposes the linear tangent rule for reverse mode,
    so ``jvp``, ``vjp``, ``jacfwd``, ``jacrev`` and every higher order all work, and the tangent rule
    differentiates through the primal (this function again). ``cotangent`` is therefore not needed
    here; where given, it is the same formula, used by the torch backend."""
    del cotangent

    def rule(fn: Callable[[Array], Array], x: Array, dx: Array) -> tuple[Array, Array]:
        y = fn(x)
        return y, tangent(XP, x, y, dx)

    return _registered(forward, rule)


def custom_jvp_rule(
    forward: Callable[[Any, Array], Array], jvp: Callable[[Any, Array, Array], tuple[Array, Array]]
) -> Callable[[Any, Array], Array]:
    """``forward(xp, x) -> y`` with a forward-mode rule ``jvp(xp, x, dx) -> (y, dy)`` that computes the
    primal itself, where it shares work with the tangent that XLA then does once. The primal of the
    rule is differentiated as written (autodiff), so every higher order works as above."""
    return _registered(forward, lambda fn, x, dx: jvp(XP, x, dx))
