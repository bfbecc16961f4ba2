"""Custom derivatives for torch: one ``autograd.Function`` per core map whose library backward is
unstable (SVD, eigh). The formulas live in the core, over ``xp``; this only registers them."""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

import torch
from torch import Tensor

Formula = Callable[[Any, Tensor, Tensor, Tensor], Tensor]


def custom_derivative(
    forward: Callable[[Any, Tensor], Tensor], tangent: Formula, cotangent: Formula
) -> Callable[[Any, Tensor], Tensor]:
    """``forward(xp, x) -> y`` with the derivatives ``tangent(xp, x, y, dx) -> dy`` (forward mode)
    and ``cotangent(xp, x, y, gy) -> gx`` (reverse mode). Both formulas are written with
    differentiable torch operations on ``x`` and on the saved *output* ``y`` (whose own gradient is
    this Function again), so double backward is exact. ``generate_vmap_rule``: the forward and the
    formulas are batched torch code, so ``torch.func.vmap`` can run them as they are.

    No ``jvp`` (forward mode): torch 2.13's Dynamo refuses to trace a Function that defines one
    (``Unsupported custom jvp``), and ``torch.compile(fullgraph=True)`` matters more. ``tangent`` is
    kept in the signature for symmetry with the jax binding, which uses it."""
    del tangent

    class Function(torch.autograd.Function):
        generate_vmap_rule = True

        @staticmethod
        def forward(x: Tensor) -> Tensor:
            return forward(torch, x)

        @staticmethod
        def setup_context(ctx: Any, inputs: tuple[Tensor], output: Tensor) -> None:
            ctx.save_for_backward(inputs[0], output)

        @staticmethod
        def backward(ctx: Any, grad: Tensor) -> Tensor:
            x, y = ctx.saved_tensors
            return cotangent(torch, x, y, grad)

    Function.__name__ = Function.__qualname__ = f"_{forward.__name__}_function"

    def bound(xp: Any, x: Tensor) -> Tensor:
        return Function.apply(x)  # type: ignore[no-untyped-call]

    bound.__name__ = forward.__name__  # the Backend validates arguments by this name
    return bound
