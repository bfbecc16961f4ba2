"""The evaluations of a torch call, and the one place that decides between them
(``diffquat/torch/_custom.py``, ``form``): in eager mode, and under ``torch.func`` transforms,
the conversions are ``autograd.Function``s whose rules are the core's written-out tangent and
cotangent, or, where no derivative can be asked of the call, their forward alone; under every
graph capture (``torch.compile``, ``torch.export``, ``torch.jit.trace``, the ONNX exporters) the
plain core formula, which the compiler differentiates and fuses. Both compute the value by the same
formula: a differentiated call returns the plain call's value bit for bit, on
every backend (tests/test_grads.py checks that for every row), and the derivatives do not depend on
the path (here, at tied pivots and tiny norms)."""

from __future__ import annotations

import math
from collections.abc import Callable
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np
import pytest
import torch
from cases import CASES_BY_NAME, oracle_quaternion_to_matrix, uniform_quaternions

import diffquat.jax as dj
import diffquat.torch as dq
from diffquat import _algebra, _backend, _core, _euler, _lie
from diffquat.torch._custom import componentwise, form

Q2M, M2Q = "_quaternion_to_matrix_eager", "_matrix_to_quaternion_eager"  # the Functions
# the eager forms' Functions (few vectorised operations, no copy: _custom._lean)
Q2M_LEAN, M2Q_LEAN = "_quaternion_to_matrix_lean", "_matrix_to_quaternion_lean"


def test_eager_calls_take_the_function_and_captures_the_formula() -> None:
    """Eager: the eager form's Function in the graph, and under forward mode (an open dual level) the
    componentwise Function with its copy of the input, exact to every order. Traced
    (``torch.jit.trace``) and compiled: the core's operations, no Function (Dynamo refuses one with a
    ``jvp``; a trace cannot save one)."""
    q = torch.randn(5, 4, dtype=torch.float64, requires_grad=True)
    assert Q2M_LEAN + "Backward" in _function_nodes(dq.quaternion_to_matrix(q))
    m = dq.quaternion_to_matrix(q.detach()).requires_grad_(True)
    assert M2Q_LEAN + "Backward" in _function_nodes(dq.matrix_to_quaternion(m))
    with torch.autograd.forward_ad.dual_level():
        assert Q2M + "Backward" in _function_nodes(dq.quaternion_to_matrix(q))
        assert M2Q + "Backward" in _function_nodes(dq.matrix_to_quaternion(m))
    with pytest.warns(DeprecationWarning):  # torch.jit.trace is deprecated in torch 2.13
        traced = torch.jit.trace(dq.matrix_to_quaternion, m.detach())
    assert "PythonOp" not in str(traced.graph)
    other = dq.quaternion_to_matrix(torch.randn(5, 4, dtype=torch.float64))
    with componentwise():  # the trace recorded the componentwise form: the same numbers
        torch.testing.assert_close(traced(other), dq.matrix_to_quaternion(other), rtol=0, atol=0)
    # and the eager form's to rounding
    torch.testing.assert_close(traced(other), dq.matrix_to_quaternion(other), rtol=0, atol=4e-16)
    ops = _traced_ops(dq.matrix_to_quaternion, m.detach())
    assert not any("Function" in op or "autograd" in op for op in ops), ops


@pytest.mark.filterwarnings("ignore:`torch.jit.script` is deprecated:DeprecationWarning")  # make_dual
@pytest.mark.parametrize("layout", ["columns", "rows"])
def test_an_eager_form_with_a_rule_is_for_reverse_mode_only(layout: str) -> None:
    """A map the Backend calls whose eager form has its own reverse rule (``rotation_6d_to_matrix``,
    ``_custom.eager_form_with_rule``): its lean Function under autograd; in forward mode the
    componentwise form, after which the Backend's non-finite rule still makes a NaN row whole (the
    eager form carries it by its arithmetic, the componentwise one does not)."""
    d6 = torch.randn(3, 6, dtype=torch.float64)
    d6[0, 4] = math.nan  # a2's NaN: b1 alone does not read it
    leaf = d6.clone().requires_grad_(True)
    out = dq.rotation_6d_to_matrix(leaf, layout=layout)
    assert "_rotation_6d_to_matrix_leanBackward" in _function_nodes(out)
    value, tangent = torch.func.jvp(lambda x: dq.rotation_6d_to_matrix(x, layout=layout), (d6,), (d6,))
    assert torch.isnan(value[0]).all() and torch.isnan(out[0]).all()
    torch.testing.assert_close(value[1:], out[1:].detach(), rtol=0, atol=1e-15)
    assert torch.isfinite(tangent[1:]).all()


@pytest.mark.filterwarnings("ignore:`torch.jit.script` is deprecated:DeprecationWarning")  # make_dual
@pytest.mark.parametrize("name", ["integrate_angular_velocity", "angular_velocity_from_quaternions"])
def test_an_eager_step_with_a_rule_is_for_reverse_mode_only(name: str) -> None:
    """An eager form one of whose steps has its own reverse rule (``_custom.lean_step``: the rates'
    exponential and logarithm): that step's lean Function under autograd, the forward alone without a
    derivative (the same value, bit for bit, in float32), and in forward mode the componentwise form;
    a non-finite row NaN in each (the eager form by its arithmetic, the componentwise one by the
    Backend's rule)."""
    gen = torch.Generator().manual_seed(46)
    if name == "integrate_angular_velocity":
        xs = (
            torch.randn(3, 4, generator=gen),
            torch.randn(3, 3, generator=gen),
            torch.rand(3, generator=gen),
        )
        xs[1][0, 1] = math.nan
    else:
        xs = (torch.randn(3, 5, 4, generator=gen), torch.rand(3, generator=gen) + 0.1)
        xs[0][0, 2, 1] = math.nan
    fn = getattr(dq, name)
    leaves = [x.clone().requires_grad_(True) for x in xs]
    out = fn(*leaves)
    assert f"_{name}_leanBackward" in _function_nodes(out)
    torch.testing.assert_close(out.detach(), fn(*xs), rtol=0, atol=0, equal_nan=True)
    doubled = tuple(x.double() for x in xs)
    value, tangent = torch.func.jvp(fn, doubled, doubled)
    assert torch.isnan(value[0]).all() and torch.isnan(out[0]).all()
    torch.testing.assert_close(value[1:], fn(*doubled)[1:], rtol=0, atol=1e-14)
    assert torch.isfinite(tangent[1:]).all()


@pytest.mark.filterwarnings("ignore:`torch.jit.script` is deprecated:DeprecationWarning")  # make_dual
def test_the_form_of_a_call_in_each_context() -> None:
    """The one decision (``_custom.form``), in every context a user calls from: the rule wherever a
    derivative can be asked (autograd, dual tensors, each ``torch.func`` derivative transform, also
    nested), the formula alone where none can (inference, ``no_grad``, ``vmap`` alone), the captured
    form under ``torch.compile`` and ``torch.jit.trace``."""
    seen: list[str] = []

    def record(x: torch.Tensor) -> torch.Tensor:
        seen.append(form(x))
        return x * 2

    def forms(call: Callable[[], Any]) -> list[str]:
        seen.clear()
        call()
        return list(seen)

    x = torch.randn(3, dtype=torch.float64)
    leaf = x.clone().requires_grad_(True)
    assert forms(lambda: record(x)) == ["formula"]
    assert forms(lambda: record(leaf)) == ["rule"]
    with torch.no_grad():
        assert forms(lambda: record(leaf)) == ["formula"]
    with torch.autograd.forward_ad.dual_level():
        assert forms(lambda: record(torch.autograd.forward_ad.make_dual(x, x))) == ["rule"]
        assert forms(lambda: record(x)) == ["rule"]  # a dual level is open: x may meet a dual
    assert forms(lambda: torch.func.vmap(record)(x[None])) == ["formula"]
    for transform in (torch.func.grad, torch.func.jacrev, torch.func.jacfwd, torch.func.hessian):
        assert set(forms(lambda t=transform: t(lambda y: record(y).sum())(x))) == {"rule"}, transform
    assert forms(lambda: torch.func.jvp(record, (x,), (x,))) == ["rule"]
    assert forms(lambda: torch.func.vmap(torch.func.grad(lambda y: record(y).sum()))(x[None])) == ["rule"]
    with pytest.warns(DeprecationWarning):  # torch.jit.trace is deprecated in torch 2.13
        assert forms(lambda: torch.jit.trace(record, x, check_trace=False)) == ["captured"]
    torch._dynamo.reset()
    assert forms(lambda: torch.compile(record, fullgraph=True, backend="eager")(x)) == ["captured"]


def test_reduced_precision_products_take_the_componentwise_form() -> None:
    """The eager forms contract with constant matrices; where a user lowers float32 products to TF32
    or bf16 (``torch.set_float32_matmul_precision("high")``), float32 calls take the componentwise
    form (no product dispatched: three digits kept), at the oracle's accuracy; float64 calls keep the
    eager form."""
    from torch.utils._python_dispatch import TorchDispatchMode

    class Ops(TorchDispatchMode):
        def __init__(self) -> None:
            super().__init__()
            self.ops: set[str] = set()

        def __torch_dispatch__(self, func: Any, types: Any, args: Any = (), kwargs: Any = None) -> Any:
            self.ops.add(str(func))
            return func(*args, **(kwargs or {}))

    q = torch.tensor(uniform_quaternions(64, 0))
    expected = torch.tensor(oracle_quaternion_to_matrix(q.numpy()))
    before = torch.get_float32_matmul_precision()
    try:
        torch.set_float32_matmul_precision("high")
        for dtype, eager in ((torch.float32, False), (torch.float64, True)):
            with Ops() as mode:
                r = dq.quaternion_to_matrix(q.to(dtype).requires_grad_(True))
                dq.matrix_to_quaternion(r)
                dq.quaternion_multiply(q.to(dtype), q.to(dtype))
            products = {name for name in mode.ops if name.split(".")[1] in ("mm", "addmm", "matmul", "bmm")}
            assert bool(products) == eager, (dtype, products)
            torch.testing.assert_close(r.detach().double(), expected, rtol=0, atol=4 * torch.finfo(dtype).eps)
    finally:
        torch.set_float32_matmul_precision(before)


@pytest.mark.parametrize(
    "name, arguments",
    [
        ("quaternion_to_matrix", lambda q: (q,)),
        ("quaternion_multiply", lambda q: (q, q[:, [2, 0, 3, 1]])),
        ("axis_angle_to_matrix", lambda q: (q[:, 1:] * 3.0,)),
        ("so3_exp", lambda q: (q[:, 1:] * 3.0,)),
    ],
)
def test_memory_bound_maps_take_the_componentwise_form_from_many_rows_on_the_cpu(
    name: str, arguments: Any
) -> None:
    """On the CPU the outer-product eager forms lose to the componentwise form from a few thousand rows
    (``_custom.COMPONENTWISE_FROM_ROWS``, docs/performance.md): a call just below the limit dispatches
    the eager form's product, one at the limit none, and both give the oracle's values (the matrices)
    or the other form's to a few ulps; a differentiated call returns the plain call's value bit for
    bit on either side."""
    from torch.utils._python_dispatch import TorchDispatchMode

    from diffquat.torch import _custom

    class Ops(TorchDispatchMode):
        def __init__(self) -> None:
            super().__init__()
            self.ops: set[str] = set()

        def __torch_dispatch__(self, func: Any, types: Any, args: Any = (), kwargs: Any = None) -> Any:
            self.ops.add(str(func).split(".")[1])
            return func(*args, **(kwargs or {}))

    fn = getattr(dq, name)
    limit = _custom.COMPONENTWISE_FROM_ROWS
    q = torch.tensor(uniform_quaternions(limit, 5), dtype=torch.float32)
    outs = []
    for rows, eager in ((limit - 1, True), (limit, False)):
        xs = arguments(q[:rows])
        with Ops() as mode:
            plain = fn(*xs)
        assert bool(mode.ops & {"mm", "addmm", "matmul", "bmm"}) == eager, (rows, sorted(mode.ops))
        differentiated = fn(*(x.clone().requires_grad_(True) for x in xs))
        assert torch.equal(differentiated.detach(), plain), rows
        differentiated.sum().backward()
        outs.append(plain)
    eps = torch.finfo(torch.float32).eps
    torch.testing.assert_close(outs[1][: limit - 1], outs[0], rtol=0, atol=8 * eps)
    if name == "quaternion_to_matrix":
        expected = torch.tensor(oracle_quaternion_to_matrix(q.double().numpy()), dtype=torch.float32)
        # entries of size <= 1, each a few rounded products and a normalisation: 8 ulps of 1
        torch.testing.assert_close(outs[1], expected, rtol=0, atol=8 * eps)


# ---------------------------------------------------------------------------------------------------
# Derivatives that do not depend on the path.


def _tied_pivots() -> torch.Tensor:
    """Half-turns about axes between coordinate axes, where two or three pivots tie exactly, and the
    same matrices moved off SO(3) by 1e-9: the choice of candidate then decides the derivative off
    SO(3), so every path must make the core's choice."""
    axes = np.array([[1.0, 0, 1], [1, 1, 0], [0, 1, 1], [1, 1, 1], [1, -1, 0], [1, 0, -1]])
    axes /= np.linalg.norm(axes, axis=1, keepdims=True)
    half_turns = np.concatenate([np.zeros((len(axes), 1)), axes], axis=1)
    m = oracle_quaternion_to_matrix(half_turns)
    wiggle = 1e-9 * np.random.default_rng(3).normal(size=m.shape)
    return torch.tensor(np.concatenate([m, m + wiggle]))


@pytest.mark.filterwarnings("ignore:`torch.jit.script` is deprecated:DeprecationWarning")
def test_matrix_to_quaternion_derivatives_do_not_depend_on_the_path() -> None:
    """At tied pivots: a plain backward and a backward recorded for a double backward (the core's
    cotangent), forward mode (the core's tangent), ``torch.func`` (the Function's rules under its
    transforms) and ``torch.compile`` (the formula, differentiated by autograd) give one Jacobian."""
    m = _tied_pivots()
    rng = np.random.default_rng(4)
    cot = torch.tensor(rng.normal(size=(len(m), 4)))
    tangent = torch.tensor(rng.normal(size=m.shape))

    def vjp(create_graph: bool) -> torch.Tensor:
        x = m.clone().requires_grad_(True)
        (g,) = torch.autograd.grad(dq.matrix_to_quaternion(x), x, cot, create_graph=create_graph)
        return g.detach()

    plain, recorded = vjp(False), vjp(True)
    functional = torch.func.vjp(dq.matrix_to_quaternion, m)[1](cot)[0]
    torch._dynamo.reset()
    compiled_fn = torch.compile(lambda x: (dq.matrix_to_quaternion(x) * cot).sum(), fullgraph=True)
    x = m.clone().requires_grad_(True)
    (compiled,) = torch.autograd.grad(compiled_fn(x), x)
    for other in (recorded, functional, compiled):
        torch.testing.assert_close(other, plain, rtol=1e-12, atol=1e-12)
    # forward mode against the reverse mode's Jacobian: <cot, J t> both ways
    forward = torch.func.jvp(dq.matrix_to_quaternion, (m,), (tangent,))[1]
    with torch.autograd.forward_ad.dual_level():
        dual = torch.autograd.forward_ad.make_dual(m, tangent)
        kernel_forward = torch.autograd.forward_ad.unpack_dual(dq.matrix_to_quaternion(dual)).tangent
    for dq_ in (forward, kernel_forward):
        torch.testing.assert_close(
            (dq_ * cot).sum(-1), (plain * tangent).sum((-1, -2)), rtol=1e-12, atol=1e-12
        )


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64], ids=str)
def test_quaternion_to_matrix_second_derivatives_at_small_norms(dtype: torch.dtype) -> None:
    """Second derivatives through the Function (its backward recorded, which is the core's cotangent)
    are finite at every norm of the documented range and equal the core formula's own,
    scaled: R(c q) = R(q), so the Hessian at c q is the Hessian at q over c^2 (a backward that divides
    by |q|^2 overflows to inf from |q| <= 1e-10 in float32)."""
    q = torch.tensor(CASES_BY_NAME["random"].quaternions("float64")[:8]).to(dtype)
    cot = torch.randn(8, 3, 3, generator=torch.Generator().manual_seed(1), dtype=dtype)
    direction = torch.randn(8, 4, generator=torch.Generator().manual_seed(2), dtype=dtype)

    def hessian_vector(x: torch.Tensor) -> torch.Tensor:
        x = x.clone().requires_grad_(True)
        (g,) = torch.autograd.grad(dq.quaternion_to_matrix(x), x, cot, create_graph=True)
        return torch.autograd.grad(g, x, direction)[0]

    unit = hessian_vector(q)
    smallest = {torch.float32: 1e-15, torch.float64: 1e-150}[dtype]
    for c in (1e-5, 1e-10, smallest, 1e5):
        scaled = hessian_vector(q * c)
        assert torch.all(torch.isfinite(scaled))
        tol = 1e-4 if dtype == torch.float32 else 1e-10
        torch.testing.assert_close((scaled * (c * c)).double(), unit.double(), rtol=tol, atol=tol)


@pytest.mark.parametrize("scalar_first", [True, False], ids=["wxyz", "xyzw"])
def test_conversion_functions_pass_gradcheck_both_modes(scalar_first: bool) -> None:
    """The conversions' Functions against finite differences: reverse mode (the core's cotangent),
    forward mode (the core's tangent), and second order (the cotangent, differentiated)."""
    q = torch.tensor(CASES_BY_NAME["random"].quaternions("float64")[:6], requires_grad=True)
    m = (
        dq.quaternion_to_matrix(q.detach()) + 0.1 * torch.randn(6, 3, 3, dtype=torch.float64)
    ).requires_grad_(True)
    for fn, x in ((dq.quaternion_to_matrix, q), (dq.matrix_to_quaternion, m)):
        f = lambda t, fn=fn: fn(t, scalar_first=scalar_first)  # noqa: E731
        assert torch.autograd.gradcheck(f, x, check_forward_ad=True)
        assert torch.autograd.gradgradcheck(f, x)


# ---------------------------------------------------------------------------------------------------
# Composites and compiled graphs.


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


_FIXED = _algebra.axis_angle_to_matrix(
    torch, torch.tensor([1.0, 2.0, 3.0], dtype=torch.float64) * 0.7 / 14**0.5
)
COMPOSITES = [
    (dq.matrix_to_axis_angle, _algebra.matrix_to_axis_angle, M2Q_LEAN),
    (
        lambda a: dq.euler_angles_to_matrix(a, "ZXZ"),
        lambda xp, a: _euler.euler_angles_to_matrix(xp, a, "ZXZ"),
        Q2M_LEAN,
    ),
    (dq.so3_log, _lie.so3_log, M2Q_LEAN),
    # plus and minus, the second argument fixed (a rotation about (1, 2, 3) by 0.7 rad)
    (
        lambda d: dq.so3_plus(_FIXED, d, side="left"),
        lambda xp, d: _lie.so3_plus(xp, _FIXED, d, side="left"),
        Q2M_LEAN,
    ),
    (
        lambda m: dq.so3_minus(m, _FIXED),
        lambda xp, m: _lie.so3_minus(xp, m, _FIXED),
        M2Q_LEAN,
    ),
]


@pytest.mark.parametrize(
    ("public", "composite", "function"),
    COMPOSITES,
    ids=[
        "matrix_to_axis_angle",
        "euler_angles_to_matrix",
        "so3_log",
        "so3_plus",
        "so3_minus",
    ],
)
def test_composites_take_the_registered_conversion(public: Any, composite: Any, function: str) -> None:
    """The composites whose conversion step is a general quaternion or matrix (log, minus, Euler to
    matrix, plus) take it as the public conversion does (eager: its eager form's Function and
    written-out derivative), with the core composite's values and gradients (autodiff of the formula)."""
    special = [[0.0, 0.0, 0.0], [np.pi, 0.0, 0.0], [0.0, 0.0, np.pi - 1e-9], [0.0, 3.2, 0.0]]
    rest = torch.randn(12, 3, generator=torch.Generator().manual_seed(3), dtype=torch.float64)
    x = torch.cat([torch.tensor(special, dtype=torch.float64), rest])
    if function == M2Q_LEAN:
        x = _algebra.axis_angle_to_matrix(torch, x)
    x.requires_grad_(True)
    ours = public(x)
    assert function + "Backward" in _function_nodes(ours)
    core = composite(torch, x)
    torch.testing.assert_close(ours, core, rtol=1e-12, atol=1e-12)
    weights = torch.randn(ours.shape, generator=torch.Generator().manual_seed(4), dtype=torch.float64)
    (g_ours,) = torch.autograd.grad(ours, x, weights)
    (g_core,) = torch.autograd.grad(core, x, weights)
    torch.testing.assert_close(g_ours, g_core, rtol=1e-9, atol=1e-9)


def _traced_ops(fn: Any, x: torch.Tensor) -> list[str]:
    """The operations dynamo records for ``fn(x)`` (one graph: fullgraph=True fails on a break)."""
    graphs: list[torch.fx.GraphModule] = []

    def capture(gm: torch.fx.GraphModule, example_inputs: object) -> object:
        graphs.append(gm)
        return gm.forward

    torch._dynamo.reset()
    torch.compile(fn, backend=capture, fullgraph=True, dynamic=False)(x)
    (graph,) = graphs
    return [str(node.target) for node in graph.graph.nodes if node.op in ("call_function", "call_method")]


def test_products_of_small_blocks_fuse_under_torch_compile() -> None:
    """Products of 3x3 blocks (``_core.small_matmul``): one ``matmul`` eager, and under
    ``torch.compile`` broadcast products that inductor fuses into the operation's loop, where it would
    leave a ``matmul`` of small blocks to ATen's ``bmm`` outside it (docs/performance.md, Formula
    shapes): the compiled SE(3) compose and ``so3_plus`` record no matrix product, and compute what
    the eager ones do. On jax the same products in value and matmuls in the derivative rule."""
    rng = np.random.default_rng(3)
    poses = dq.se3_exp(torch.tensor(rng.normal(size=(2, 8, 6))))
    matrices, delta = poses[0, :, :3, :3].contiguous(), torch.tensor(rng.normal(size=(8, 3)))
    for fn, x in (
        (lambda p: dq.se3_compose(p[0], p[1]), poses),
        (lambda m: dq.so3_plus(m, delta), matrices),
        (lambda m: dq.so3_minus(m, m.flip(0)), matrices),
    ):
        ops = _traced_ops(fn, x)
        assert not any("matmul" in op or "bmm" in op for op in ops), ops
        torch._dynamo.reset()
        compiled = torch.compile(fn, fullgraph=True, dynamic=False, backend="aot_eager")(x)
        np.testing.assert_allclose(compiled.numpy(), fn(x).numpy(), rtol=1e-12, atol=1e-12)
    eager = torch.rand(4, 3, 3, dtype=torch.float64), torch.rand(4, 3, 4, dtype=torch.float64)
    assert torch.equal(_core.small_matmul(torch, *eager), torch.matmul(*eager))
    # jax: the products in value (no dot in the forward program), matmuls in the derivative rule
    a, b = (jnp.asarray(p.numpy()) for p in poses)
    assert "dot_general" not in str(jax.make_jaxpr(dj.se3_compose)(a, b))
    vjp = jax.make_jaxpr(lambda x, y: jax.vjp(dj.se3_compose, x, y)[1](x))(a, b)
    assert "dot_general" in str(vjp)
    np.testing.assert_allclose(np.asarray(dj.se3_compose(a, b)), np.matmul(a, b), rtol=1e-12, atol=1e-12)


@pytest.mark.parametrize("scalar_first", [True, False], ids=["wxyz", "xyzw"])
@pytest.mark.parametrize("dtype", [torch.float32, torch.bfloat16], ids=str)
def test_compiled_public_function_traces_to_the_core_formula(scalar_first: bool, dtype: torch.dtype) -> None:
    """Under torch.compile the public functions hand inductor exactly the core formula followed by the
    non-finite row rule (where the formula's arithmetic does not already apply it): validation and
    dispatch add nothing to the graph and break nothing, so a user's compiled code fuses with
    diffquat's as with a hand-written copy. In 16 bits the graph also holds the float32 upcast and
    the cast back and, for a canonical-sign output, its re-standardisation after the narrowing cast."""
    q = torch.randn(64, 4, dtype=dtype)
    m = dq.quaternion_to_matrix(q.float()).to(dtype)
    for public, core, x, trailing in (
        (dq.quaternion_to_matrix, _core.quaternion_to_matrix, q, (4,)),
        (dq.matrix_to_quaternion, _core.matrix_to_quaternion, m, (3, 3)),
    ):

        def reference(t: torch.Tensor, core: Any = core, trailing: Any = trailing) -> torch.Tensor:
            out = core(torch, t, scalar_first=scalar_first)
            if core.__name__ in _core.NONFINITE_BY_ARITHMETIC:
                return out  # type: ignore[no-any-return]
            return _backend.nonfinite_rows(torch, out, [(t, trailing)])  # type: ignore[no-any-return]

        ours = _traced_ops(lambda t, f=public: f(t, scalar_first=scalar_first), x)
        theirs = _traced_ops(reference, x.float())
        if dtype == torch.float32:
            assert ours == theirs
            continue
        # 16 bits: the upcast, the formula, the cast back, then the re-standardisation if canonical
        assert ours[0] == "to" and ours[1 : len(theirs) + 1] == theirs and ours[len(theirs) + 1] == "to"
        assert (len(ours) > len(theirs) + 2) == (core.__name__ in _core.CANONICAL)


def test_the_nonfinite_row_rule_holds_under_inductor_and_xla() -> None:
    """The non-finite row rule finds the bad rows as sums of ``0 * x`` (NaN exactly where a NaN or an
    infinity is). Compiled, as a user's compiled model runs it (inductor, and XLA under ``jax.jit``),
    the rule still makes those rows NaN and leaves the others as they are, a row of huge finite
    entries (whose plain sum would overflow) included: no compiler folds ``0 * x`` to 0."""
    import jax

    from diffquat.jax._namespace import XP

    x = np.random.default_rng(0).normal(size=(7, 3, 3))
    x[0] = 1e308
    x[1, 0, 2], x[3, 2, 2], x[4, 1, 1] = math.inf, -math.inf, math.nan
    v = np.random.default_rng(1).normal(size=(7, 3))
    v[5, 0] = math.nan
    v[6, 2] = -math.inf
    out = np.random.default_rng(2).normal(size=(7, 3, 3))

    def rule(xp: Any) -> Callable[..., Any]:
        return lambda out, x, v: _backend.nonfinite_rows(xp, out, [(x, (3, 3)), (v, (3,))])

    torch._dynamo.reset()
    paths = {
        "torch": (rule(torch), torch.tensor),
        "inductor": (torch.compile(rule(torch), fullgraph=True, dynamic=False), torch.tensor),
        "jax.jit": (jax.jit(rule(XP)), jax.numpy.asarray),
    }
    for name, (fn, array) in paths.items():
        got = np.asarray(fn(array(out), array(x), array(v)))
        assert np.isnan(got[[1, 3, 4, 5, 6]]).all(), name
        np.testing.assert_array_equal(got[[0, 2]], out[[0, 2]], err_msg=name)


_SIGMA = torch.tensor([0.05, 0.3, 1.0, 2.0, 30.0], dtype=torch.float64)


@pytest.mark.parametrize(
    "name, size",
    [
        ("symmetric_matrix_to_quaternion", 10),
        ("matrix_to_quaternion", (3, 3)),
        ("rotation_6d_to_matrix", 6),
        ("matrix_fisher_log_normalizer", (3, 3)),
        ("igso3_log_density", ()),
        ("igso3_angle_cdf", ()),
    ],
)
def test_constants_made_inside_a_transform_do_not_escape_it(name: str, size: Any) -> None:
    """The eager forms keep their constant tensors (``_core.constants``); one first made inside a
    ``torch.func`` transform (a rule's cotangent under ``jacrev(jacrev)``) is a tensor of that
    transform's level, and kept, it broke every later call outside it (an internal assert in
    functorch, met by the 10D head's test run alone). Made there, it is not kept. The IGSO(3) rows
    (angles, at fixed sigma) keep theirs through the same cache."""
    from torch._C._functorch import is_functorch_wrapped_tensor

    from diffquat import _core

    public = getattr(dq, name)
    fn = (lambda y: public(y, _SIGMA)) if name.startswith("igso3") else public
    shape = (5, *size) if isinstance(size, tuple) else (5, size)
    x = torch.tensor(np.random.default_rng(7).normal(size=shape))
    if name.startswith("igso3"):
        x = x.abs()
    _core._CONSTANTS.clear()
    torch.func.jacrev(torch.func.jacrev(lambda y: fn(y).sum()))(x)
    assert not any(is_functorch_wrapped_tensor(c) for v in _core._CONSTANTS.values() for c in v)
    out, pullback = torch.func.vjp(fn, x)
    (grad,) = pullback(torch.ones_like(out))
    assert torch.isfinite(grad).all()
