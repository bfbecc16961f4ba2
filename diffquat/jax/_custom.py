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


def custom_derivative(
    forward: Callable[[Any, Array], Array], tangent: Formula, cotangent: Formula | None = None
) -> Callable[[Any, Array], Array]:
    """``forward(xp, x) -> y`` with the forward-mode derivative ``tangent(xp, x, y, dx) -> dy``, bound
    as ``(xp, x)`` like the core functions.

    A ``custom_jvp`` (not ``custom_vjp``): jax transposes the linear tangent rule for reverse mode,
    so ``jvp``, ``vjp``, ``jacfwd``, ``jacrev`` and every higher order all work, and the tangent rule
    differentiates through the primal (this function again). The rule's primal is the function
    itself, so a differentiated call returns the value of a plain call. ``cotangent`` is therefore
    not needed here; where given, it is the same formula, used by the torch backend."""
    del cotangent

    @jax.custom_jvp
    def fn(x: Array) -> Array:
        return forward(XP, x)

    @fn.defjvp
    def fn_jvp(primals: tuple[Array], tangents: tuple[Array]) -> tuple[Array, Array]:
        (x,), (dx,) = primals, tangents
        y = fn(x)
        return y, tangent(XP, x, y, dx)

    def bound(xp: Any, x: Array) -> Array:
        return fn(x)

    bound.__name__ = forward.__name__  # the Backend validates arguments by this name
    return bound
