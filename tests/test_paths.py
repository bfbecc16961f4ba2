"""Every evaluation of ``quaternion_to_matrix`` and ``matrix_to_quaternion`` on torch, and the one place
that chooses between them (``diffquat/torch/_dispatch.py``): the core formula, the C kernels
(``_cpu.py``) and the Triton kernels (``_triton.py``, run under Triton's interpreter in
tests/test_triton.py).

The shared matrix runs every case through the public functions, which in eager CPU mode take the C
kernels, and under compilation and transforms the formula. This file checks what it cannot see from
outside: which evaluation each kind of call takes (every graph capture and transform takes the
formula), that each evaluation is accurate against a float64 reference at a bound derived from its
arithmetic (never one float32 evaluation against another: two correct float32 evaluations differ by a
few ulps from one instruction set to another), and that the derivatives do not depend on the path:
one choice of pivot, first and second order, forward and reverse.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from typing import Any

import numpy as np
import pytest
import torch
from cases import (
    CASES_BY_NAME,
    VALUE_TOL,
    oracle_quaternion_to_matrix,
)
from torch.utils._python_dispatch import TorchDispatchMode

import diffquat.torch as dq
from diffquat import _algebra, _backend, _core, _euler, _lie
from diffquat.torch import _cpu, _dispatch

# ---------------------------------------------------------------------------------------------------
# Which evaluation each call takes.


# The functions with more than one evaluation: (the chooser, the public function, an input, the module
# of the formula each capture must take).
CHOSEN: dict[
    str, tuple[Callable[[torch.Tensor], Any], Callable[[torch.Tensor], torch.Tensor], tuple[int, ...], str]
] = {
    "quaternion_to_matrix": (_dispatch.quaternion_to_matrix, dq.quaternion_to_matrix, (5, 4), "_dispatch"),
    "so3_left_jacobian_inverse": (
        _dispatch.so3_left_jacobian_inverse,
        dq.so3_left_jacobian_inverse,
        (5, 3),
        "_lie",
    ),
    # two arguments: the quaternion and the rotation vector as slices of one (5, 7) input
    "quaternion_plus": (
        lambda t: _dispatch.quaternion_plus(t[..., :4], t[..., 4:]),
        lambda t: dq.quaternion_plus(t[..., :4], t[..., 4:]),
        (5, 7),
        "_lie",
    ),
}


def _decisions(
    run: Callable[[Callable[[torch.Tensor], torch.Tensor]], Any], function: str = "quaternion_to_matrix"
) -> set[str]:
    """The evaluations ``function`` chose inside ``run(probe)`` for the tensors it saw."""
    choose, public, _, _ = CHOSEN[function]
    seen: set[str] = set()

    def probe(t: torch.Tensor) -> torch.Tensor:
        seen.add(choose(t).__module__.rsplit(".", 1)[-1])
        return public(t)

    run(probe)
    return seen


class _Logging(TorchDispatchMode):
    """A dispatch mode as debugging and capture tools install them (it sees every aten call)."""

    def __torch_dispatch__(self, func: Any, types: Any, args: Any = (), kwargs: Any = None) -> Any:
        return func(*args, **(kwargs or {}))


class _Subclass(torch.Tensor):
    pass


EAGER_CALLS: dict[str, Callable[[Any, torch.Tensor], Any]] = {
    "plain": lambda f, x: f(x),
    "requires_grad": lambda f, x: f(x.requires_grad_(True)),
    "parameter": lambda f, x: f(torch.nn.Parameter(x)),
    "no_grad": lambda f, x: torch.no_grad()(f)(x),
}


def _in_device_context(f: Any, x: torch.Tensor) -> Any:
    with torch.device("cpu"):
        return f(x)


EAGER_CALLS["device_context"] = _in_device_context


def _export(f: Any, x: torch.Tensor) -> Any:
    class Module(torch.nn.Module):
        def forward(self, t: torch.Tensor) -> torch.Tensor:
            return f(t)  # type: ignore[no-any-return]

    return torch.export.export(Module(), (x,))


def _dispatch_mode(f: Any, x: torch.Tensor) -> Any:
    with _Logging():
        return f(x)


def _fake(f: Any, x: torch.Tensor) -> Any:
    from torch._subclasses.fake_tensor import FakeTensorMode

    with FakeTensorMode() as mode:
        return f(mode.from_tensor(x))


CAPTURES: dict[str, Callable[[Any, torch.Tensor], Any]] = {
    "jit_trace": lambda f, x: torch.jit.trace(f, (x,), check_trace=False),  # (the check reruns it eagerly)
    "compile": lambda f, x: torch.compile(f, backend="eager", fullgraph=True)(x),
    "export": _export,
    "make_fx_real": lambda f, x: torch.fx.experimental.proxy_tensor.make_fx(f)(x),
    "make_fx_fake": lambda f, x: torch.fx.experimental.proxy_tensor.make_fx(f, tracing_mode="fake")(x),
    "make_fx_symbolic": lambda f, x: torch.fx.experimental.proxy_tensor.make_fx(f, tracing_mode="symbolic")(
        x
    ),
    "vmap": lambda f, x: torch.func.vmap(f)(x),
    "grad": lambda f, x: torch.func.grad(lambda t: f(t).sum())(x),
    "jvp": lambda f, x: torch.func.jvp(f, (x,), (x,)),
    "jacrev": lambda f, x: torch.func.jacrev(f)(x),
    "fake_tensor_mode": _fake,
    "dispatch_mode": _dispatch_mode,
    "subclass": lambda f, x: f(x.as_subclass(_Subclass)),
    "negated_view": lambda f, x: f(torch._neg_view(x)),
}


@pytest.mark.parametrize("function", list(CHOSEN))
@pytest.mark.parametrize("call", list(EAGER_CALLS))
def test_eager_cpu_calls_take_the_kernels(call: str, function: str) -> None:
    """Plain CPU tensors and parameters, recorded or not, in a ``torch.device`` context (a function mode
    that records nothing) or not: the C kernels."""
    shape = CHOSEN[function][2]
    assert _decisions(lambda f: EAGER_CALLS[call](f, torch.randn(shape)), function) == {"_cpu"}


@pytest.mark.filterwarnings("ignore:`torch.jit.trace` is deprecated:DeprecationWarning")
# torch.func.jvp goes through a torch module that still uses torch.jit.script.
@pytest.mark.filterwarnings("ignore:`torch.jit.script` is deprecated:DeprecationWarning")
@pytest.mark.parametrize("function", list(CHOSEN))
@pytest.mark.parametrize("capture", list(CAPTURES))
def test_captures_and_transforms_take_the_formula(capture: str, function: str) -> None:
    """Every graph capture, transform, dispatch mode and tensor subclass: the formula, which the
    capture records (the kernels write through raw pointers it would not see)."""
    torch._dynamo.reset()
    _, _, shape, formula = CHOSEN[function]
    x = torch.randn(shape)
    assert _decisions(lambda f: CAPTURES[capture](f, x), function) == {formula}


def test_without_the_extension_everything_takes_the_formula(monkeypatch: pytest.MonkeyPatch) -> None:
    """Where the extension was not built (no C compiler at install time), the CPU takes the formula."""
    monkeypatch.setattr(_dispatch, "_cpu", None)
    x = torch.randn(5, 4)
    assert _dispatch.quaternion_to_matrix(x) is _dispatch._formula_q2m
    assert _dispatch.matrix_to_quaternion(dq.quaternion_to_matrix(x)) is _core.matrix_to_quaternion
    assert _dispatch.so3_left_jacobian(x[:, 1:]) is _lie.so3_left_jacobian


def test_the_kernel_modules_do_not_import_the_dispatch() -> None:
    """The dispatch imports the kernel modules, never the other way round (no import cycle)."""
    import diffquat.torch._triton as triton_module

    for module in (_cpu, triton_module):
        assert "_dispatch" not in vars(module)


# ---------------------------------------------------------------------------------------------------
# Accuracy of each evaluation against a float64 reference.


def _quaternions() -> np.ndarray:
    """Every named quaternion case, the zero quaternion and norms from 1e-15 to 1e15 among them."""
    names = ("random", "identity", "half_turns", "near_half_turns", "near_identity", "norms", "zero")
    return np.vstack([CASES_BY_NAME[name].quaternions("float32").reshape(-1, 4) for name in names])


def _matrices() -> np.ndarray:
    """Rotations of every unit case (half-turns with pivot ties among them), the same off SO(3), and
    arbitrary matrices."""
    names = ("random", "identity", "half_turns", "near_half_turns", "near_identity")
    rot = oracle_quaternion_to_matrix(np.vstack([CASES_BY_NAME[n].quaternions("float64") for n in names]))
    rng = np.random.default_rng(5)
    return np.concatenate([rot, rot + 0.05 * rng.normal(size=rot.shape), rng.normal(size=(9, 3, 3))])


def _formula(name: str) -> Callable[..., torch.Tensor]:
    return {
        "quaternion_to_matrix": _dispatch._formula_q2m,
        "matrix_to_quaternion": _core.matrix_to_quaternion,
    }[name]


EVALUATIONS = {
    "kernels": lambda name: getattr(_cpu, name),
    "formula": _formula,
}


# The bound, in float32, for both maps: the first-order error analysis of the formula's ~10 roundings
# of unit roundoff u = 2^-24 gives at most 25 u = 1.5e-6 per entry (quaternion_to_matrix: the norm 4u,
# its inverse square root 4u, each unit component 5u, each product of two 11u, summed over terms whose
# magnitudes add up to at most 2, then subtracted from 1), within the table's 2e-6 (VALUE_TOL, against
# which the public functions are also checked); float64 likewise within 1e-12.
@pytest.mark.parametrize("dtype", [torch.float32, torch.float64], ids=str)
@pytest.mark.parametrize("scalar_first", [True, False], ids=["wxyz", "xyzw"])
@pytest.mark.parametrize("evaluation", list(EVALUATIONS))
def test_each_evaluation_against_a_float64_reference(
    evaluation: str, scalar_first: bool, dtype: torch.dtype
) -> None:
    """Values against a reference on the very values each evaluation received: scipy in float64 for
    ``quaternion_to_matrix``; for ``matrix_to_quaternion``, whose map off SO(3) is diffquat's own (the
    candidate of the largest pivot, normalised; scipy projects onto SO(3) first), the core formula in
    NumPy's extended precision. Signs up to rounding where the true w is 0. Gradients against the
    float64 core formula's (relative to the largest gradient entry: ~40 roundings of a sum of
    products, 1e-5 covers them in float32)."""
    tol = VALUE_TOL[str(dtype).removeprefix("torch.")]
    order = [0, 1, 2, 3] if scalar_first else [1, 2, 3, 0]
    q = torch.tensor(_quaternions()).to(dtype)
    m = torch.tensor(_matrices()).to(dtype)

    def extended(m: np.ndarray) -> np.ndarray:
        return _core.matrix_to_quaternion(np, m.astype(np.longdouble)).astype(np.float64)

    for name, x, oracle, stored in (
        ("quaternion_to_matrix", q[..., order], oracle_quaternion_to_matrix, None),
        ("matrix_to_quaternion", m, extended, order),
    ):
        fn = EVALUATIONS[evaluation](name)
        a = x.clone().requires_grad_(True)
        out = fn(torch, a, scalar_first=scalar_first)
        reference_input = x.double().numpy()
        if name == "quaternion_to_matrix":
            expected = oracle(reference_input[..., np.argsort(order)])
        else:
            expected = oracle(reference_input)[..., stored]
        got = out.detach().double().numpy()
        err = np.abs(got - expected).reshape(len(x), -1).max(axis=-1)
        if name == "matrix_to_quaternion":  # at a half-turn (w = 0) rounding decides the sign
            err = np.minimum(err, np.abs(got + expected).reshape(len(x), -1).max(axis=-1))
        assert err.max() <= tol, err.max()
        # gradients, away from the zero quaternion and the extreme norms (whose derivatives are 1e15
        # times larger or smaller than the rest, and checked in float64 by the shared matrix)
        unit = slice(0, len(x) - len(CASES_BY_NAME["norms"].quaternions("float64").reshape(-1, 4)) - 1)
        rows = unit if name == "quaternion_to_matrix" else slice(None)
        b = x.double()[rows].clone().requires_grad_(True)
        cot = torch.randn(out[rows].shape, generator=torch.Generator().manual_seed(7), dtype=torch.float64)
        (g,) = torch.autograd.grad(out[rows], a, cot.to(dtype))
        reference = _formula(name)(torch, b, scalar_first=scalar_first)
        (g_ref,) = torch.autograd.grad(reference, b, cot)
        scale = float(g_ref.abs().max())
        np.testing.assert_allclose(g[rows].double().numpy(), g_ref.numpy(), rtol=0, atol=1e-5 * scale)


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
    """At tied pivots: a plain backward (the backward kernel), a backward recorded for a double
    backward (the core's cotangent), forward mode (the core's tangent, transposed), ``torch.func``
    (the formula, differentiated by autograd) and ``torch.compile`` give one Jacobian."""
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
    """Second derivatives through the kernels' Function (its backward recorded, which is the core's
    cotangent) are finite at every norm of the documented range and equal the core formula's own,
    scaled: R(c q) = R(q), so the Hessian at c q is the Hessian at q over c^2 (once the fused backward
    divided by |q|^2 and overflowed to inf from |q| <= 1e-10 in float32)."""
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


@pytest.mark.filterwarnings("ignore:`torch.jit.script` is deprecated:DeprecationWarning")
@pytest.mark.parametrize("scalar_first", [True, False], ids=["wxyz", "xyzw"])
def test_kernel_functions_pass_gradcheck_both_modes(scalar_first: bool) -> None:
    """The kernels' Functions against finite differences: reverse mode (the backward kernels), forward
    mode (the core's tangents), and second order (the core's cotangents, differentiated)."""
    q = torch.tensor(CASES_BY_NAME["random"].quaternions("float64")[:6], requires_grad=True)
    m = (
        dq.quaternion_to_matrix(q.detach()) + 0.1 * torch.randn(6, 3, 3, dtype=torch.float64)
    ).requires_grad_(True)
    for fn, x in ((_cpu.quaternion_to_matrix, q), (_cpu.matrix_to_quaternion, m)):
        f = lambda t, fn=fn: fn(torch, t, scalar_first=scalar_first)  # noqa: E731
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
    (dq.axis_angle_to_matrix, _algebra.axis_angle_to_matrix, "QuaternionToMatrixKernel"),
    (dq.matrix_to_axis_angle, _algebra.matrix_to_axis_angle, "MatrixToQuaternionKernel"),
    (
        lambda a: dq.euler_angles_to_matrix(a, "ZXZ"),
        lambda xp, a: _euler.euler_angles_to_matrix(xp, a, "ZXZ"),
        "QuaternionToMatrixKernel",
    ),
    (dq.so3_exp, _lie.so3_exp, "QuaternionToMatrixKernel"),
    (dq.so3_log, _lie.so3_log, "MatrixToQuaternionKernel"),
    # plus and minus, the second argument fixed (a rotation about (1, 2, 3) by 0.7 rad)
    (
        lambda d: dq.so3_plus(_FIXED, d, side="left"),
        lambda xp, d: _lie.so3_plus(xp, _FIXED, d, side="left"),
        "QuaternionToMatrixKernel",
    ),
    (
        lambda m: dq.so3_minus(m, _FIXED),
        lambda xp, m: _lie.so3_minus(xp, m, _FIXED),
        "MatrixToQuaternionKernel",
    ),
]


@pytest.mark.parametrize(
    ("public", "composite", "function"),
    COMPOSITES,
    ids=[
        "axis_angle_to_matrix",
        "matrix_to_axis_angle",
        "euler_angles_to_matrix",
        "so3_exp",
        "so3_log",
        "so3_plus",
        "so3_minus",
    ],
)
def test_composites_take_the_kernels_for_their_conversion(public: Any, composite: Any, function: str) -> None:
    """Axis-angle and Euler conversions, and the Lie maps built on them (exp, log, plus, minus), go
    through the evaluation the quaternion conversion inside them would take (eager CPU: the kernels),
    with the core composite's values and gradients."""
    special = [[0.0, 0.0, 0.0], [np.pi, 0.0, 0.0], [0.0, 0.0, np.pi - 1e-9], [0.0, 3.2, 0.0]]
    rest = torch.randn(12, 3, generator=torch.Generator().manual_seed(3), dtype=torch.float64)
    x = torch.cat([torch.tensor(special, dtype=torch.float64), rest])
    if function.startswith("MatrixToQuaternion"):
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
            # quaternion_to_matrix: stacked by rows when compiled, and NaN rows by its own arithmetic
            namespace = _dispatch._COMPILED if core is _core.quaternion_to_matrix else torch
            out = core(namespace, t, scalar_first=scalar_first)
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


@pytest.mark.parametrize("scalar_first", [True, False], ids=["wxyz", "xyzw"])
def test_compiled_quaternion_to_matrix_stacks_rows_with_the_same_values(scalar_first: bool) -> None:
    """Under torch.compile, ``quaternion_to_matrix`` takes the core formula over
    ``_dispatch._COMPILED``, which stacks the matrix by rows of three: inductor lowers a concatenation
    of more than eight inputs as one strided copy per input, and torch cannot compile reverse over
    forward mode through a view of one. The values are those of the single stack, bit for bit, and
    the compiled graph of the public function holds no stack of more than eight."""
    q = torch.randn(50, 4, dtype=torch.float64)
    rows = _core.quaternion_to_matrix(_dispatch._COMPILED, q, scalar_first=scalar_first)
    assert torch.equal(rows, _core.quaternion_to_matrix(torch, q, scalar_first=scalar_first))
    graphs: list[torch.fx.GraphModule] = []

    def capture(gm: torch.fx.GraphModule, example_inputs: object) -> object:
        graphs.append(gm)
        return gm.forward

    torch._dynamo.reset()
    fn = lambda t: dq.quaternion_to_matrix(t, scalar_first=scalar_first)  # noqa: E731
    assert torch.equal(torch.compile(fn, backend=capture, fullgraph=True, dynamic=False)(q), rows)
    (graph,) = graphs
    stacks = [len(node.args[0]) for node in graph.graph.nodes if node.target is torch.stack]
    assert stacks == [3, 3, 3, 3]
