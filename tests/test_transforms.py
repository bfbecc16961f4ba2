"""Every op under the function transforms users apply to it, agreeing with eager execution:
``torch.compile(fullgraph=True)`` forward and backward, and ``torch.func.vmap/grad/jacrev``;
``jax.jit/vmap/grad``, with ``jvp`` and ``jacfwd``/``jacrev`` under ``vmap``, in one compiled program
per op in tests/test_forward_mode.py. float64, so agreement is checked tightly."""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

import numpy as np
import torch
from cases import CASES_BY_NAME, Op, base_rows, gradients, torch_only
from conftest import Backend

# Two cases, a generic batch and the exact half-turns (the branchiest inputs for every op), as one
# batch: each transform compiles once per op (compilation, not the batch, is what these tests cost).
TRANSFORM_CASES = ("random", "half_turns")


def setup(op: Op) -> tuple[list[np.ndarray], np.ndarray, np.ndarray]:
    """The cases' inputs, flattened and concatenated; which rows are at a case where the op is smooth;
    a weight per row."""
    parts, smooth = [], []
    for case in (CASES_BY_NAME[name] for name in TRANSFORM_CASES):
        if op.applies(case):
            q = case.quaternions("float64")
            batch = q.shape[:-1]
            n = int(np.prod(batch))
            parts.append([x.reshape(n, *x.shape[len(batch) :]) for x in op.gradient_inputs(q)])
            smooth.append(np.full(n, op.smooth_at(case)))
    xs = [np.concatenate(p) for p in zip(*parts, strict=True)]
    return xs, np.concatenate(smooth), np.random.default_rng(1).normal(size=(len(xs[0]),))


def scalar_loss(fn: Callable[..., Any], weights: Any) -> Callable[..., Any]:
    """A scalar of every output entry, weighted per batch element, for grad-style transforms."""

    def loss(*xs: Any) -> Any:
        out = fn(*xs)
        flat = out.reshape(out.shape[0], -1)
        return ((flat * flat.sum(-1, keepdims=True)).sum(-1) * weights).sum()

    return loss


def close(a: Any, b: Any) -> None:
    np.testing.assert_allclose(np.asarray(a), np.asarray(b), rtol=1e-12, atol=1e-12)


def close_values(op: Op, a: Any, b: Any, smooth: np.ndarray) -> None:
    """Values under a compiler equal eager ones, except where the op jumps between two results that
    both stand for the rotation (``op.up_to_sign``: a rotation vector at exactly pi, whose sign
    follows a rounding error of the size of 1e-17 that a compiler's reordering may flip): there, up to
    sign."""
    a, b = np.asarray(a), np.asarray(b)
    if not op.up_to_sign:
        close(a, b)
        return
    close(a[smooth], b[smooth])
    rest = ~smooth
    shape = (int(rest.sum()), int(np.prod(a.shape[1:])))  # (0, -1) would not reshape an empty array
    a, b = a[rest].reshape(shape), b[rest].reshape(shape)
    same = np.isclose(a, b, rtol=1e-12, atol=1e-12).all(-1)
    other = -b if op.other_branch is None else op.other_branch(b).reshape(shape)
    flipped = np.isclose(a, other, rtol=1e-12, atol=1e-12).all(-1)
    assert np.all(same | flipped)


def close_derivatives(a: Any, b: Any, smooth: np.ndarray) -> None:
    """Derivatives under a transform equal eager ones on the rows where the op is differentiable
    (``smooth``). At a kink (a distance between antipodal rotations, |w| at w = 0) the derivative
    follows the sign or the direction of a rounding error, which a compiler's reordering of the same
    arithmetic may change: there, both must only be finite."""
    a, b = np.asarray(a), np.asarray(b)
    close(a[smooth], b[smooth])
    assert np.all(np.isfinite(a)) and np.all(np.isfinite(b))


@torch_only
@gradients
@base_rows
def test_torch_compile_fullgraph_forward_and_backward(op: Op, backend: Backend, dtype: str) -> None:
    fn = op.gradient_function(backend.module)
    xs, smooth, _ = setup(op)
    # Every op's test function is the same lambda code object (Op.gradient_function), and dynamo
    # caches compiled frames per code object: without a reset, the ninth op compiled in one worker
    # hits dynamo's recompile limit, which fullgraph=True turns into an error.
    torch._dynamo.reset()
    compiled = torch.compile(fn, fullgraph=True, dynamic=False)
    eager_in = [torch.tensor(x, requires_grad=True) for x in xs]
    comp_in = [torch.tensor(x, requires_grad=True) for x in xs]
    eager, comp = fn(*eager_in), compiled(*comp_in)
    close_values(op, comp.detach(), eager.detach(), smooth)
    cot = torch.tensor(np.random.default_rng(2).normal(size=tuple(eager.shape)))
    for a, b in zip(
        torch.autograd.grad(comp, comp_in, cot), torch.autograd.grad(eager, eager_in, cot), strict=True
    ):
        close_derivatives(a, b, smooth)


@torch_only
@gradients
@base_rows
def test_torch_compile_dynamic_shapes(op: Op, backend: Backend, dtype: str) -> None:
    """Under ``torch.compile(dynamic=True)`` every size is symbolic, the trailing (3, 3) or (4,) too:
    the argument checks must still pass (they once compared sizes in a way Dynamo could not resolve,
    and raised the shape error for a valid input). Two batch sizes through one compiled graph.

    Dynamo and AOTAutograd (``aot_eager``) are where shapes are symbolic and the checks run; inductor's
    code generation, which took 8 s per op here, is tested with static shapes above. The table's
    keyword variants (``variant_of``) run the same argument checks as their base rows, as above."""
    fn = op.gradient_function(backend.module)
    xs, _, _ = setup(op)
    torch._dynamo.reset()
    compiled = torch.compile(fn, backend="aot_eager", fullgraph=True, dynamic=True)
    for rows in (len(xs[0]), len(xs[0]) - 1):
        ts = [torch.tensor(x[:rows]) for x in xs]
        close(compiled(*ts), fn(*ts))


@torch_only
@gradients
def test_torch_func_vmap_grad_jacrev(op: Op, backend: Backend, dtype: str) -> None:
    fn = op.gradient_function(backend.module)
    xs, smooth, w = setup(op)
    ts = [torch.tensor(x) for x in xs]
    close(torch.func.vmap(fn)(*ts), fn(*ts))
    # grad of a weighted scalar equals autograd's
    loss = scalar_loss(fn, torch.tensor(w))
    leaves = [t.clone().requires_grad_(True) for t in ts]
    expected = torch.autograd.grad(loss(*leaves), leaves)
    got = torch.func.grad(loss, argnums=tuple(range(len(ts))))(*ts)
    for a, b in zip(got, expected, strict=True):
        close_derivatives(a, b, smooth)
    # per-element Jacobians: jacrev under vmap equals jacrev of one element
    jac = torch.func.vmap(torch.func.jacrev(fn))(*ts)
    one = torch.func.jacrev(fn)(*(t[0] for t in ts))
    close_derivatives(jac[:1], one[None], smooth[:1])
    assert torch.all(torch.isfinite(jac))
