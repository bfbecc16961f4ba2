"""The torch fast paths (diffquat/torch/_fused.py, and the C kernels' Functions of _cpu.py) against the
core formula they replace. The eager CPU default is the kernels (tests/test_kernels.py checks what is
particular to them); the pure-torch Functions are the fallback where the extension is not built, and
the ``setup_context`` ones run under ``torch.func``.

The shared matrix already runs every case through the public functions, which take the small-batch
Functions for small eager batches (the old-style Function eagerly, the ``setup_context`` one under
``torch.func``); this checks what it does not: every fused path and the core side by
side (values and reverse-mode gradients, both storage orders, every edge case), forward mode (``jvp``,
which ``gradcheck`` checks against finite differences), double backward and ``torch.func`` for the
columns Functions (the shared matrix's batches are too small to reach them), their evaluation by
blocks of rows, and the dispatch on batch size."""

from __future__ import annotations

import numpy as np
import pytest
import torch
from cases import AT_HALF_TURNS, CASES_BY_NAME, EDGE_CASES, oracle_quaternion_to_matrix, outer

import diffquat.torch as dq
from diffquat import _algebra, _core, _euler
from diffquat.torch import _cpu, _fused

PAIRS = [
    (_cpu.quaternion_to_matrix, _core.quaternion_to_matrix, lambda q: q),
    (_cpu.matrix_to_quaternion, _core.matrix_to_quaternion, oracle_quaternion_to_matrix),
    (_fused.quaternion_to_matrix, _core.quaternion_to_matrix, lambda q: q),
    (_fused.matrix_to_quaternion, _core.matrix_to_quaternion, oracle_quaternion_to_matrix),
    (_fused.matrix_to_quaternion_columns, _core.matrix_to_quaternion, oracle_quaternion_to_matrix),
    (_fused.quaternion_to_matrix_columns, _core.quaternion_to_matrix, lambda q: q),
]
PAIR_IDS = [
    "quaternion_to_matrix_kernel",
    "matrix_to_quaternion_kernel",
    "quaternion_to_matrix",
    "matrix_to_quaternion",
    "matrix_to_quaternion_columns",
    "quaternion_to_matrix_columns",
]
QUATERNION_INPUT = (
    _cpu.quaternion_to_matrix,
    _fused.quaternion_to_matrix,
    _fused.quaternion_to_matrix_columns,
)


def _off_so3(n: int) -> torch.Tensor:
    """Float64 rotation matrices plus noise: off SO(3), where the derivatives of the normalisation and
    of every candidate entry matter."""
    q = torch.tensor(CASES_BY_NAME["random"].quaternions("float64")[:n])
    m = torch.tensor(oracle_quaternion_to_matrix(q.numpy()))
    return m + 0.1 * torch.tensor(np.random.default_rng(0).normal(size=m.shape))


@pytest.mark.parametrize("scalar_first", [True, False])
@pytest.mark.parametrize("pair", range(len(PAIRS)), ids=PAIR_IDS)
@pytest.mark.parametrize("case", [*EDGE_CASES, "norms", "zero", "sign_flip"])
def test_fused_equals_core(pair: int, case: str, scalar_first: bool) -> None:
    fused, core, make = PAIRS[pair]
    x = torch.tensor(make(CASES_BY_NAME[case].quaternions("float64")))
    if not scalar_first and fused in QUATERNION_INPUT:
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
    m = _off_so3(6).requires_grad_(True)
    for fn, x in (
        (_cpu.quaternion_to_matrix, q),
        (_cpu.matrix_to_quaternion, m),
        (_fused.quaternion_to_matrix, q),
        (_fused.quaternion_to_matrix_columns, q),
        (_fused.matrix_to_quaternion, m),
        (_fused.matrix_to_quaternion_columns, m),
    ):
        assert torch.autograd.gradcheck(
            lambda t, fn=fn: fn(torch, t, scalar_first=scalar_first), x, check_forward_ad=True
        )


# Half-turns about an axis between two coordinate axes tie two pivots: off SO(3) the two candidates
# have different first derivatives, so there is no second derivative for finite differences to match.
@pytest.mark.parametrize("case", [*(c for c in EDGE_CASES if c not in AT_HALF_TURNS), "off_so3"])
def test_columns_double_backward(case: str) -> None:
    """The columns Function's backward is made of differentiable operations (the lerp selection
    included), so second derivatives are exact: gradgradcheck against finite differences, through
    ``q q^T`` since the canonical sign jumps at half-turns."""
    if case == "off_so3":
        m = _off_so3(6)
    else:
        m = torch.tensor(oracle_quaternion_to_matrix(CASES_BY_NAME[case].quaternions("float64")))
    fn = lambda t: outer(_fused.matrix_to_quaternion_columns(torch, t))  # noqa: E731
    assert torch.autograd.gradgradcheck(fn, m.reshape(-1, 3, 3)[:6].clone().requires_grad_(True))


@pytest.mark.parametrize("case", [*EDGE_CASES, "norms", "zero"])
def test_quaternion_columns_double_backward(case: str) -> None:
    """The backward of quaternion_to_matrix's columns Function (the core's analytic cotangent) is made
    of differentiable operations: second derivatives against finite differences at every edge case; at
    norms from 1e-15 to 1e15, where finite differences of step 1e-6 mean nothing, equal to those of
    autograd through the core formula; at the zero quaternion (no derivative there), 0."""
    q = torch.tensor(CASES_BY_NAME[case].quaternions("float64")).reshape(-1, 4)[:6].clone()

    def fn(t: torch.Tensor) -> torch.Tensor:
        return _fused.quaternion_to_matrix_columns(torch, t)

    if case not in ("norms", "zero"):
        assert torch.autograd.gradgradcheck(fn, q.requires_grad_(True))
        return
    rng = np.random.default_rng(2)
    cot, direction = torch.tensor(rng.normal(size=(len(q), 3, 3))), torch.tensor(rng.normal(size=q.shape))
    second = []
    for f in (fn, lambda t: _core.quaternion_to_matrix(torch, t)):
        x = q.clone().requires_grad_(True)
        (g,) = torch.autograd.grad(f(x), x, cot, create_graph=True)
        second.append(torch.autograd.grad(g, x, direction)[0])
    torch.testing.assert_close(second[0], second[1], rtol=1e-9, atol=0)
    if case == "zero":
        assert torch.equal(second[0], torch.zeros_like(q))


COLUMNS = [
    (_fused.matrix_to_quaternion_columns, _core.matrix_to_quaternion, (3, 3), (4,)),
    (_fused.quaternion_to_matrix_columns, _core.quaternion_to_matrix, (4,), (3, 3)),
]


# jacfwd goes through a torch module that still uses torch.jit.script (see test_fused_forward_mode).
@pytest.mark.filterwarnings("ignore:`torch.jit.script` is deprecated:DeprecationWarning")
@pytest.mark.parametrize("pair", range(len(COLUMNS)), ids=["matrix_to_quaternion", "quaternion_to_matrix"])
def test_columns_under_torch_func(pair: int) -> None:
    """``vmap`` (through ``generate_vmap_rule``), ``jacrev`` and ``jacfwd`` of each columns Function
    equal those of the core formula."""
    columns, core, input_shape, output_shape = COLUMNS[pair]
    if input_shape == (3, 3):
        x = _off_so3(5)
    else:
        x = torch.tensor(CASES_BY_NAME["random"].quaternions("float64")[:5]) * torch.arange(1.0, 6.0)[:, None]

    def ours_fn(t: torch.Tensor) -> torch.Tensor:
        return columns(torch, t)

    def core_fn(t: torch.Tensor) -> torch.Tensor:
        return core(torch, t)

    for transform in (torch.func.jacrev, torch.func.jacfwd):
        ours = torch.func.vmap(transform(ours_fn))(x)
        theirs = torch.func.vmap(transform(core_fn))(x)
        assert ours.shape == (5, *output_shape, *input_shape)
        torch.testing.assert_close(ours, theirs, rtol=1e-10, atol=1e-10)


@pytest.mark.parametrize("scalar_first", [True, False])
def test_evaluation_by_blocks(monkeypatch: pytest.MonkeyPatch, scalar_first: bool) -> None:
    """Very large batches are evaluated by blocks of rows (``BLOCK_ROWS``, shrunk here to 4 so that a
    small batch spans several blocks and a partial last one): values and gradients equal the core
    formula's over several leading dimensions, forward and backward, with and without a gradient."""
    monkeypatch.setattr(_fused, "BLOCK_ROWS", 4)
    monkeypatch.setattr(_fused, "BLOCKS_FROM", 8)
    rng = np.random.default_rng(1)
    q = torch.tensor(rng.normal(size=(3, 5, 4)))
    q[1, 2] = 0.0  # the zero quaternion, in a middle block
    m = torch.tensor(oracle_quaternion_to_matrix(rng.normal(size=(3, 5, 4)))) + 0.1  # off SO(3)
    order, every = ([0, 1, 2, 3] if scalar_first else [1, 2, 3, 0]), slice(None)
    for columns, core, x, x_in, out_order, grad_order in (
        (_fused.quaternion_to_matrix_columns, _core.quaternion_to_matrix, q, q[..., order], every, order),
        (_fused.matrix_to_quaternion_columns, _core.matrix_to_quaternion, m, m, order, every),
    ):
        a, b = x_in.clone().requires_grad_(True), x.clone().requires_grad_(True)
        out = columns(torch, a, scalar_first=scalar_first)
        expected = core(torch, b)[..., out_order]
        torch.testing.assert_close(out, expected, rtol=0, atol=1e-15)
        cot = torch.tensor(rng.normal(size=tuple(out.shape)))
        (g_ours,) = torch.autograd.grad(out, a, cot)
        (g_core,) = torch.autograd.grad(expected, b, cot)
        torch.testing.assert_close(g_ours, g_core[..., grad_order], rtol=1e-12, atol=1e-12)
    with torch.no_grad():
        blocks = _fused.quaternion_to_matrix_blocks(torch, q[..., order], scalar_first=scalar_first)
    torch.testing.assert_close(blocks, _core.quaternion_to_matrix(torch, q), rtol=0, atol=1e-15)


@pytest.fixture
def without_kernels(monkeypatch: pytest.MonkeyPatch) -> None:
    """The dispatch as where the C extension is not built (no C compiler at install)."""
    monkeypatch.setattr(_fused, "_cpu", None)


@pytest.mark.usefixtures("without_kernels")
def test_batch_size_dispatch() -> None:
    """Without the kernels, small eager batches take the small-batch Functions, large ones the
    columns Functions."""
    limit = _fused.MAX_FUSED_BATCH["quaternion_to_matrix"]
    small = torch.randn(limit, 4, requires_grad=True)
    large = torch.randn(limit + 1, 4, requires_grad=True)
    assert type(dq.quaternion_to_matrix(small).grad_fn).__name__ == "QuaternionToMatrixBackward"
    assert type(dq.quaternion_to_matrix(large).grad_fn).__name__ == "QuaternionToMatrixColumnsBackward"
    limit = _fused.MAX_FUSED_BATCH["matrix_to_quaternion"]
    matrices = dq.quaternion_to_matrix(torch.randn(limit + 1, 4)).requires_grad_(True)
    assert type(dq.matrix_to_quaternion(matrices[:limit]).grad_fn).__name__ == "MatrixToQuaternionBackward"
    large_fn = type(dq.matrix_to_quaternion(matrices).grad_fn).__name__
    assert large_fn == "MatrixToQuaternionColumnsBackward"


def _rotation_vectors(n: int) -> torch.Tensor:
    """Float64 rotation vectors with the named edge cases first: zero, a half-turn, and angles just
    below and past pi."""
    special = [[0.0, 0.0, 0.0], [np.pi, 0.0, 0.0], [0.0, 0.0, np.pi - 1e-9], [0.0, 3.2, 0.0]]
    rest = torch.randn(n - len(special), 3, generator=torch.Generator().manual_seed(3), dtype=torch.float64)
    return torch.cat([torch.tensor(special, dtype=torch.float64), rest])


def _function_nodes(out: torch.Tensor) -> set[str]:
    """The names of every node of ``out``'s autograd graph."""
    names, stack, seen = set(), [out.grad_fn], set()
    while stack:
        node = stack.pop()
        if node is None or node in seen:
            continue
        seen.add(node)
        names.add(type(node).__name__)
        stack += [child for child, _ in node.next_functions]
    return names


COMPOSITES = [
    (dq.axis_angle_to_matrix, _algebra.axis_angle_to_matrix, "QuaternionToMatrix", "quaternion_to_matrix"),
    (dq.matrix_to_axis_angle, _algebra.matrix_to_axis_angle, "MatrixToQuaternion", "matrix_to_quaternion"),
    (
        lambda a: dq.euler_angles_to_matrix(a, "ZXZ"),
        lambda xp, a: _euler.euler_angles_to_matrix(xp, a, "ZXZ"),
        "QuaternionToMatrix",
        "quaternion_to_matrix",
    ),
]


@pytest.mark.parametrize("size", ["kernel", "small", "large"])
@pytest.mark.parametrize(
    ("public", "composite", "function", "conversion"),
    COMPOSITES,
    ids=["axis_angle_to_matrix", "matrix_to_axis_angle", "euler_angles_to_matrix"],
)
def test_composites_take_the_fused_conversion(
    public: object,
    composite: object,
    function: str,
    conversion: str,
    size: str,
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    """Axis-angle conversions to and from matrices and Euler angles to matrices (matrix_to_euler_angles
    reads the matrix entries directly, with no quaternion step) go through the same fast path as the
    quaternion conversion inside them (the kernels' Function; without them the small-batch or columns
    Function, by batch size), and give the core composite's values and gradients, edge cases
    included."""
    if size != "kernel":
        monkeypatch.setattr(_fused, "_cpu", None)
    n = _fused.MAX_FUSED_BATCH[conversion] + 1 if size == "large" else 16
    x = _rotation_vectors(n)
    if conversion == "matrix_to_quaternion":
        x = _algebra.axis_angle_to_matrix(torch, x)
    x.requires_grad_(True)
    ours = public(x)  # type: ignore[operator]
    expected = function + {"kernel": "Kernel", "small": "", "large": "Columns"}[size]
    assert expected + "Backward" in _function_nodes(ours)
    core = composite(torch, x)  # type: ignore[operator]
    torch.testing.assert_close(ours, core, rtol=1e-12, atol=1e-12)
    weights = torch.randn(ours.shape, generator=torch.Generator().manual_seed(4), dtype=torch.float64)
    (g_ours,) = torch.autograd.grad(ours, x, weights)
    (g_core,) = torch.autograd.grad(core, x, weights)
    torch.testing.assert_close(g_ours, g_core, rtol=1e-9, atol=1e-9)


@pytest.mark.usefixtures("without_kernels")
def test_batch_size_dispatch_without_gradient() -> None:
    """Without the kernels, quaternion_to_matrix takes the core formula (by blocks) from a smaller
    batch on where no gradient is recorded (the Function's products cost more memory than its saved
    backward is worth there), and gives the same values either way."""
    limit = _fused.MAX_FUSED_BATCH_NO_GRAD["quaternion_to_matrix"]
    assert limit < _fused.MAX_FUSED_BATCH["quaternion_to_matrix"]
    small, large = torch.randn(limit, 4), torch.randn(limit + 1, 4)
    assert _fused.q2m_path(small) is _fused.quaternion_to_matrix
    assert _fused.q2m_path(large) is _fused.quaternion_to_matrix_blocks
    assert _fused.q2m_path(large.requires_grad_(True)) is _fused.quaternion_to_matrix
    with torch.no_grad():
        assert _fused.q2m_path(large) is _fused.quaternion_to_matrix_blocks
        fast = dq.quaternion_to_matrix(large)
    torch.testing.assert_close(fast, dq.quaternion_to_matrix(large).detach(), rtol=1e-6, atol=1e-6)


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


@pytest.mark.parametrize("scalar_first", [True, False])
def test_compiled_cuda_namespace_stacks_rows_with_the_same_values(scalar_first: bool) -> None:
    """Under torch.compile, CUDA tensors take the core formula over ``_fused._CompiledCuda``, which
    stacks the matrix by rows of three: inductor lowers a concatenation of more than eight inputs as
    one strided copy per input, and one of at most eight as a single kernel. The values are those of
    the single stack, bit for bit, and the traced graph holds no stack of more than eight."""
    q = torch.randn(50, 4, dtype=torch.float64)
    rows = _fused.compiled_quaternion_to_matrix(torch, q, scalar_first=scalar_first)
    assert torch.equal(rows, _core.quaternion_to_matrix(torch, q, scalar_first=scalar_first))
    graphs: list[torch.fx.GraphModule] = []

    def capture(gm: torch.fx.GraphModule, example_inputs: object) -> object:
        graphs.append(gm)
        return gm.forward

    torch._dynamo.reset()
    fn = lambda t: _fused.compiled_quaternion_to_matrix(torch, t, scalar_first=scalar_first)  # noqa: E731
    torch.compile(fn, backend=capture, fullgraph=True, dynamic=False)(q)  # type: ignore[call-overload]
    (graph,) = graphs
    stacks = [len(node.args[0]) for node in graph.graph.nodes if node.target is torch.stack]
    assert stacks == [3, 3, 3, 3]
