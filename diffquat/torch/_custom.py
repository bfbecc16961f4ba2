"""Custom derivatives for torch: one map whose library derivative is unstable (SVD, eigh) with its
own rules, in both modes. The formulas live in the core, over ``xp``; this only registers them.

Two ``autograd.Function`` classes per map, because eager torch and torch 2.13's Dynamo each honour
a different part of one:

- Eager: ``forward``, ``backward``, ``jvp`` and ``generate_vmap_rule``. Autograd, ``torch.func``
  (``grad``, ``jacrev``, ``jvp``, ``jacfwd``, ``hessian``, ``vmap``) and dual tensors
  (``torch.autograd.forward_ad``) call the rules.
- Compiled (``torch.compiler.is_compiling()``): Dynamo refuses a Function that defines ``jvp``
  ("Unsupported custom jvp", an error under ``fullgraph=True``). Without one, it calls ``backward``
  where an input requires grad, but under a ``torch.func`` transform it inlines ``forward`` and
  differentiates its operations (``torch.func.jvp`` of the SVD at M = I: NaN). So that Function's
  forward is written so that autodiff of its operations *is* the custom rule (:func:`_linearised`).
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

import torch
from torch import Tensor
from torch.autograd.forward_ad import _set_fwd_grad_enabled

Formula = Callable[[Any, Tensor, Tensor, Tensor], Tensor]

# Under compilation the forward is exact to this order of differentiation (see _linearised): 2 covers
# hessian and every other pair of jacfwd/jacrev/jvp/grad. Each order costs one more tangent (a 3x3 or
# 4x4 solve) per call of the compiled function, inference included.
_COMPILED_ORDER = 2


def _linearised(forward: Callable[[Any, Tensor], Tensor], tangent: Formula, x: Tensor) -> Tensor:
    """``forward(x)`` in value, with ``tangent`` as its derivative under autodiff of the operations.

    With ``x0 = x.detach()``, ``y0 = forward(x0)`` and ``dx = x - x0`` (zero in value, the identity
    in derivative): ``g_0 = y0`` and ``g_(k+1) = y0 + tangent(x, g_k, dx)``. As ``tangent`` is linear
    in its last argument, every other term of the derivative of ``g_(k+1)`` is multiplied by
    ``dx = 0``: ``g_(k+1)'(x) = tangent(x, g_k(x), .)``, exact to order k + 1 when ``g_k`` is exact to
    order k. The value stays ``y0``: ``tangent(x, g, 0) = 0`` (a linear solve of zero)."""
    x0 = x.detach()
    dx = x - x0
    y0 = forward(torch, x0)
    # g_0 carries a zero tangent rather than none: torch 2.13's compiled vmap(jvp) fails on a matmul
    # of a batched tensor without a tangent by one with ("Tensor device mismatch"). 0 * sum(dx) is
    # exactly 0 and broadcasts against y0 ((..., 3, 1) for a matrix, (..., 1) for a vector).
    y = y0 + 0 * dx.sum(-1, keepdim=True)
    for _ in range(_COMPILED_ORDER):
        y = y0 + tangent(torch, x, y, dx)
    return y


def custom_derivative(
    forward: Callable[[Any, Tensor], Tensor], tangent: Formula, cotangent: Formula
) -> Callable[[Any, Tensor], Tensor]:
    """``forward(xp, x) -> y`` with the derivatives ``tangent(xp, x, y, dx) -> dy`` (forward mode)
    and ``cotangent(xp, x, y, gy) -> gx`` (reverse mode). Both formulas are written with
    differentiable torch operations on ``x`` and on the *output* ``y`` (whose own derivative is this
    map again), so every higher order is exact in eager mode, in either order of the two modes.
    ``generate_vmap_rule``: the forward and the formulas are batched torch code, so
    ``torch.func.vmap`` runs them as they are."""

    class Eager(torch.autograd.Function):
        """Returns ``(y, copy of x)``. The copy is what ``jvp`` reads x from: autograd calls ``jvp``
        with forward grad mode off, which hides the tangents of an outer forward level, so that
        jacfwd(jacfwd(f)) would silently drop the second-order terms (pytorch/pytorch#197867). With
        the mode back on, the saved *input* would carry this level's own tangent (an error: "a
        forward grad that itself has a forward gradient at the same level"); an *output* has none
        yet, and carries every outer level's, like ``y``. Its tangent is ``dx``, its cotangent
        adds to x's."""

        generate_vmap_rule = True

        @staticmethod
        def forward(x: Tensor) -> tuple[Tensor, Tensor]:
            # contiguous: a strided view (eigh's column) as the output of a Function trips dual
            # tensors (forward_ad wants its tangent to be a view of the same layout).
            return forward(torch, x).contiguous(), x.clone()

        @staticmethod
        def setup_context(ctx: Any, inputs: tuple[Tensor], output: tuple[Tensor, Tensor]) -> None:
            y, x = output
            ctx.save_for_backward(inputs[0], y)
            ctx.save_for_forward(x, y)

        @staticmethod
        def backward(ctx: Any, grad: Tensor, grad_x: Tensor) -> Tensor:
            x, y = ctx.saved_tensors
            return cotangent(torch, x, y, grad) + grad_x

        @staticmethod
        def jvp(ctx: Any, dx: Tensor) -> tuple[Tensor, Tensor]:
            x, y = ctx.saved_tensors
            with _set_fwd_grad_enabled(True):
                return tangent(torch, x, y, dx), dx

    class Compiled(torch.autograd.Function):
        generate_vmap_rule = True

        @staticmethod
        def forward(x: Tensor) -> Tensor:
            return _linearised(forward, tangent, x)

        @staticmethod
        def setup_context(ctx: Any, inputs: tuple[Tensor], output: Tensor) -> None:
            ctx.save_for_backward(inputs[0], output)

        @staticmethod
        def backward(ctx: Any, grad: Tensor) -> Tensor:
            x, y = ctx.saved_tensors
            return cotangent(torch, x, y, grad)

    Eager.__name__ = Eager.__qualname__ = f"_{forward.__name__}_eager"
    Compiled.__name__ = Compiled.__qualname__ = f"_{forward.__name__}_compiled"

    def bound(xp: Any, x: Tensor) -> Tensor:
        if torch.compiler.is_compiling():
            return Compiled.apply(x)  # type: ignore[no-untyped-call]
        return Eager.apply(x)[0]  # type: ignore[no-untyped-call]

    bound.__name__ = forward.__name__  # the Backend validates arguments by this name
    return bound
