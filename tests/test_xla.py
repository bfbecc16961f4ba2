"""What the jax backend hands XLA: conversions through a quaternion evaluate each cosine and sine once
per rotation, not once per matrix entry (XLA fuses by recomputation; see ``_core.computed_once``)."""

from __future__ import annotations

import re
from collections.abc import Callable
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from cases import CASES_BY_NAME, JAX_KERNELS, OPS, Op, both_sides

import diffquat.jax as dq

CASES: dict[str, tuple[Callable[[Any], Any], int]] = {
    # (function of (N, 3) float32, angles per rotation: the cosines and sines the formula has)
    "axis_angle_to_matrix": (dq.axis_angle_to_matrix, 1),
    "euler_angles_to_matrix-ZYX": (lambda v: dq.euler_angles_to_matrix(v, "ZYX"), 3),
    "euler_angles_to_matrix-xyx": (lambda v: dq.euler_angles_to_matrix(v, "xyx"), 3),
}


@pytest.mark.parametrize("name", list(CASES))
def test_each_cosine_and_sine_is_evaluated_once(name: str) -> None:
    fn, angles = CASES[name]
    hlo = jax.jit(fn).lower(jnp.ones((1024, 3), jnp.float32)).compile().as_text()
    assert hlo is not None
    assert len(re.findall(r" cosine\(", hlo)) == angles
    assert len(re.findall(r" sine\(", hlo)) == angles


@pytest.mark.parametrize("scalar_first", [True, False], ids=["wxyz", "xyzw"])
def test_matrix_to_quaternion_cotangent_is_one_stack(scalar_first: bool) -> None:
    """The reverse-mode program of matrix_to_quaternion assembles the (..., 3, 3) cotangent in one
    stack of the nine entries, not as nine zero-padded copies of the matrix summed (see
    ``_core._tangent_entries``), and the scalar-last result is built in its order, not reindexed.
    That is the formula every platform compiles by default (``cpu_kernels`` on, the CPU calls the C
    kernels: below)."""
    from diffquat.jax._namespace import XP

    def loss(m: Any) -> Any:
        weights = jnp.arange(4.0, dtype=jnp.float32)[None]
        return (dq._M2Q[scalar_first](XP, m) * weights).sum()

    hlo = jax.jit(jax.grad(loss)).lower(jnp.ones((1024, 3, 3), jnp.float32)).compile().as_text()
    assert hlo is not None
    assert not re.findall(r" pad\(", hlo)


# The rows whose whole map is one kernel (cases.JAX_KERNELS; matrix_to_axis_angle and so3_log call
# one for their quaternion step only: below), in each storage order they take.
WHOLE = [
    (row, first)
    for op in OPS
    if op.id in JAX_KERNELS and op.name not in ("matrix_to_axis_angle", "so3_log")
    for row in both_sides(op)
    for first in ((True, False) if op.scalar_first else (True,))
]


@pytest.mark.parametrize(
    ("op", "scalar_first"), WHOLE, ids=[f"{op.id}-{'wxyz' if f else 'xyzw'}" for op, f in WHOLE]
)
def test_the_kernels_are_the_whole_cpu_program(op: Op, scalar_first: bool) -> None:
    """With ``cpu_kernels`` on, these functions on the CPU are the C kernels as custom calls
    (``diffquat/jax/_xla.py``): the forward program is the forward kernel alone, and the reverse
    program calls the backward kernel (and the forward one where the cotangent reads the result),
    with nothing of the formula (no square root, no sine) compiled beside them; the vmap of a gradient
    still calls them. The storage order and the side are in the kernels' names."""
    if dq._xla is None:
        pytest.skip("the C extension is not built (no C compiler at install)")
    forward = "diffquat_" + JAX_KERNELS[op.id].replace("wxyz", "wxyz" if scalar_first else "xyzw")
    backward = forward.replace("_forward_", "_backward_")
    xs = [jnp.asarray(x, jnp.float32) for x in op.inputs(CASES_BY_NAME["random"].quaternions("float64"))]
    keyword = {"scalar_first": scalar_first} if op.scalar_first else {}

    def f(*args: Any) -> Any:
        return op(dq, *args, **keyword)

    def loss(*args: Any) -> Any:
        out = f(*args)
        return (out * jnp.linspace(0.5, 1.5, out.size, dtype=out.dtype).reshape(out.shape)).sum()

    def calls(fn: Callable[..., Any], *args: Any) -> set[str]:
        text = jax.jit(fn).lower(*args).compile().as_text()
        assert text is not None
        assert "sqrt(" not in text and "sine(" not in text
        return set(re.findall(r'custom_call_target="([^"]+)"', text))

    argnums = tuple(range(len(xs)))
    with dq.cpu_kernels():
        assert calls(f, *xs) == {forward}
        assert backward in calls(jax.grad(loss, argnums), *xs) <= {forward, backward}
        pairs = [x.reshape(8, -1, *x.shape[1:]) for x in xs]
        assert backward in calls(jax.vmap(jax.grad(loss, argnums)), *pairs) <= {forward, backward}


def test_kernel_primitives_lower_other_dtypes_as_the_formula() -> None:
    """The kernels read float32 or float64; the backend casts half precision to float32 before, but a
    primitive bound on another dtype (under some transform, or directly) lowers as the formula, in
    that dtype, rather than hand XLA's buffer to a kernel that would misread it."""
    if dq._xla is None:
        pytest.skip("the C extension is not built (no C compiler at install)")
    m = jnp.asarray(np.random.default_rng(0).normal(size=(8, 3, 3)), jnp.bfloat16)

    def f(x: Any) -> Any:
        return dq._xla.matrix_to_quaternion(x, True)

    text = jax.jit(f).lower(m).compile().as_text()
    assert text is not None and "custom_call" not in text
    np.testing.assert_allclose(
        np.asarray(jax.jit(f)(m), np.float32),
        np.asarray(dq.matrix_to_quaternion(m.astype(jnp.float32))),
        atol=2e-2,
    )


def test_matrix_to_axis_angle_takes_the_kernels_on_the_cpu() -> None:
    """With ``cpu_kernels`` on, jax's matrix_to_axis_angle takes the kernels for its quaternion step on
    the CPU (forward, and backward under differentiation); matrix_to_euler_angles keeps the core
    formula (benchmarks/)."""
    if dq._xla is None:
        pytest.skip("the C extension is not built (no C compiler at install)")
    m = jnp.ones((1024, 3, 3), jnp.float32)

    def targets(fn: Callable[..., Any]) -> list[str]:
        return sorted(re.findall(r'custom_call_target="([^"]+)"', jax.jit(fn).lower(m).compile().as_text()))

    with dq.cpu_kernels():
        assert targets(dq.matrix_to_axis_angle) == ["diffquat_m2q_forward_wxyz"]
        assert targets(jax.grad(lambda x: dq.matrix_to_axis_angle(x).sum())) == [
            "diffquat_m2q_backward_wxyz",
            "diffquat_m2q_forward_wxyz",
        ]
        assert targets(lambda x: dq.matrix_to_euler_angles(x, "ZYX")) == []


@pytest.mark.parametrize("scalar_first", [True, False], ids=["wxyz", "xyzw"])
def test_quaternion_to_matrix_cotangent_is_one_stack(scalar_first: bool) -> None:
    """The reverse-mode program of quaternion_to_matrix assembles the (..., 4) cotangent in one stack
    of the four components, not as four zero-padded copies of the quaternion summed (see
    ``_core.unstack_quaternion``)."""

    def loss(q: Any) -> Any:
        weights = jnp.arange(9.0, dtype=jnp.float32).reshape(1, 3, 3)
        return (dq.quaternion_to_matrix(q, scalar_first=scalar_first) * weights).sum()

    hlo = jax.jit(jax.grad(loss)).lower(jnp.ones((1024, 4), jnp.float32)).compile().as_text()
    assert hlo is not None
    assert not re.findall(r" pad\(", hlo)


@pytest.mark.parametrize("scalar_first", [True, False], ids=["wxyz", "xyzw"])
def test_quaternion_to_matrix_compiles_to_the_stack_on_the_cpu(scalar_first: bool) -> None:
    """``quaternion_to_matrix`` chooses its form by platform (``lax.platform_dependent``): on the CPU
    the compiled programs, forward, reverse and forward mode, are those of the core's stack of nine,
    instruction for instruction (the gathered form, for GPUs, is not even lowered)."""
    from diffquat import _core
    from diffquat.jax._namespace import XP

    def program(fn: Callable[..., Any], *args: Any) -> list[str]:
        text = jax.jit(fn).lower(*args).compile().as_text()
        lines = [line for line in text.splitlines() if " = " in line]
        # instruction names carry numbers, and metadata the source lines; neither is the program
        return [re.sub(r"\.\d+|, metadata=\{[^}]*\}|stack_frame_id=\d+", "", line) for line in lines]

    q, g = jnp.ones((1024, 4), jnp.float32), jnp.ones((1024, 3, 3), jnp.float32)
    ours = lambda x: dq.quaternion_to_matrix(x, scalar_first=scalar_first)  # noqa: E731
    core = lambda x: _core.quaternion_to_matrix(XP, x, scalar_first=scalar_first)  # noqa: E731
    for wrap, args in (
        (lambda f: f, (q,)),
        (lambda f: lambda x, c: jax.vjp(f, x)[1](c), (q, g)),
        (lambda f: lambda x, t: jax.jvp(f, (x,), (t,)), (q, q)),
    ):
        assert program(wrap(ours), *args) == program(wrap(core), *args)
