"""The torch fast paths (diffquat/torch/_fused.py) against the core formula they replace.

The shared matrix already runs every case through the public functions, which take the fused path for
small eager batches; this checks what it does not: the fused and core paths side by side (values and
reverse-mode gradients, both storage orders), forward mode (``jvp``, which ``gradcheck`` checks
against finite differences), and the dispatch on batch size."""

from __future__ import annotations

import numpy as np
import pytest
import torch
from cases import CASES_BY_NAME, EDGE_CASES, oracle_quaternion_to_matrix

import diffquat.torch as dq
from diffquat import _core
from diffquat.torch import _fused

PAIRS = [
    (_fused.quaternion_to_matrix, _core.quaternion_to_matrix, lambda q: q),
    (_fused.matrix_to_quaternion, _core.matrix_to_quaternion, oracle_quaternion_to_matrix),
]


@pytest.mark.parametrize("scalar_first", [True, False])
@pytest.mark.parametrize("pair", range(len(PAIRS)), ids=["quaternion_to_matrix", "matrix_to_quaternion"])
@pytest.mark.parametrize("case", [*EDGE_CASES, "norms", "zero", "sign_flip"])
def test_fused_equals_core(pair: int, case: str, scalar_first: bool) -> None:
    fused, core, make = PAIRS[pair]
    x = torch.tensor(make(CASES_BY_NAME[case].quaternions("float64")))
    if not scalar_first and fused is _fused.quaternion_to_matrix:
        x = x[..., [1, 2, 3, 0]]
    a, b = x.clone().requires_grad_(True), x.clone().requires_grad_(True)
    out_fused = fused(torch, a, scalar_first=scalar_first)
    out_core = core(torch, b, scalar_first=scalar_first)
    np.testing.assert_allclose(out_fused.detach().numpy(), out_core.detach().numpy(), rtol=0, atol=1e-15)
    cot = torch.tensor(np.random.default_rng(0).normal(size=tuple(out_core.shape)))
    (g_fused,) = torch.autograd.grad(out_fused, a, cot)
    (g_core,) = torch.autograd.grad(out_core, b, cot)
    np.testing.assert_allclose(g_fused.numpy(), g_core.numpy(), rtol=1e-9, atol=1e-9)


# gradcheck's forward-mode check goes through a torch module that still uses torch.jit.script.
@pytest.mark.filterwarnings("ignore:`torch.jit.script` is deprecated:DeprecationWarning")
@pytest.mark.parametrize("scalar_first", [True, False])
def test_fused_forward_mode(scalar_first: bool) -> None:
    q = torch.tensor(CASES_BY_NAME["random"].quaternions("float64")[:6], requires_grad=True)
    m = torch.tensor(oracle_quaternion_to_matrix(q.detach().numpy()))
    m = (m + 0.1 * torch.tensor(np.random.default_rng(0).normal(size=m.shape))).requires_grad_(True)
    for fn, x in ((_fused.quaternion_to_matrix, q), (_fused.matrix_to_quaternion, m)):
        assert torch.autograd.gradcheck(
            lambda t, fn=fn: fn(torch, t, scalar_first=scalar_first), x, check_forward_ad=True
        )


def test_batch_size_dispatch() -> None:
    """Small eager batches take the fused Function, large ones the core formula."""
    small = torch.randn(_fused.MAX_FUSED_BATCH, 4, requires_grad=True)
    large = torch.randn(_fused.MAX_FUSED_BATCH + 1, 4, requires_grad=True)
    assert "QuaternionToMatrix" in type(dq.quaternion_to_matrix(small).grad_fn).__name__
    assert "QuaternionToMatrix" not in type(dq.quaternion_to_matrix(large).grad_fn).__name__
    matrices = dq.quaternion_to_matrix(large.detach()).requires_grad_(True)
    assert "MatrixToQuaternion" in type(dq.matrix_to_quaternion(matrices[:10]).grad_fn).__name__
    assert "MatrixToQuaternion" not in type(dq.matrix_to_quaternion(matrices).grad_fn).__name__


def _traced_ops(fn: object, x: torch.Tensor) -> list[str]:
    """The operations dynamo records for ``fn(x)`` (one graph: fullgraph=True fails on a break)."""
    graphs: list[torch.fx.GraphModule] = []

    def capture(gm: torch.fx.GraphModule, example_inputs: object) -> object:
        graphs.append(gm)
        return gm.forward

    torch._dynamo.reset()
    torch.compile(fn, backend=capture, fullgraph=True, dynamic=False)(x)  # type: ignore[call-overload]
    (graph,) = graphs
    return [str(node.target) for node in graph.graph.nodes if node.op in ("call_function", "call_method")]


@pytest.mark.parametrize("scalar_first", [True, False])
@pytest.mark.parametrize("dtype", [torch.float32, torch.bfloat16], ids=str)
def test_compiled_public_function_traces_to_the_core_formula(scalar_first: bool, dtype: torch.dtype) -> None:
    """Under torch.compile, the public functions hand inductor exactly the core formula: validation,
    dispatch (the fused Function is eager-only) and the wrapper add no operation to the graph and
    break nothing, so a user's compiled code fuses with diffquat's as with a hand-written copy. In 16
    bits the graph holds the float32 upcast and the cast back and, for a canonical-sign output, its
    re-standardisation after the narrowing cast."""
    q = torch.randn(64, 4, dtype=dtype)
    m = dq.quaternion_to_matrix(q.float()).to(dtype)
    for public, core, x in (
        (dq.quaternion_to_matrix, _core.quaternion_to_matrix, q),
        (dq.matrix_to_quaternion, _core.matrix_to_quaternion, m),
    ):
        ours = _traced_ops(lambda t, f=public: f(t, scalar_first=scalar_first), x)  # type: ignore[misc]
        theirs = _traced_ops(lambda t, f=core: f(torch, t, scalar_first=scalar_first), x.float())  # type: ignore[misc]
        if dtype == torch.float32:
            assert ours == theirs
            continue
        # 16 bits: the upcast, the formula, the cast back, then the re-standardisation if canonical
        assert ours[0] == "to" and ours[1 : len(theirs) + 1] == theirs and ours[len(theirs) + 1] == "to"
        assert (len(ours) > len(theirs) + 2) == (core.__name__ in _core.CANONICAL)
