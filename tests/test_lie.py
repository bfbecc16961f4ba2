"""SO(3) as a Lie group (diffquat._lie), beyond the shared table (tests/cases.py, where every function
has its row: values against scipy, derivatives, transforms, dtypes, shapes, errors):

- the Jacobians and their inverses against mpmath (60 digits) on the very float32 and float64 values
  given, at every scale of the angle from 0 to 30 radians (the inverses up to their pole at 2 pi), and
  the coefficients that cancel, each to a few ulps of itself;
- the identities that define them (derivatives of the perturbed exponential and of log,
  ``J_l = R J_r``, ``J_l J_l^-1 = I``), and plus and minus inverting each other on both sides, for
  matrices and quaternions, up to ``|d| = pi - 1e-6``;
- first and second derivatives where the table's cases do not reach (the series threshold at
  ``|w| = 1``, angles beyond pi) and on the right side (the table's rows perturb on the left), and
  float32 derivatives as accurate as the values.
"""

from __future__ import annotations

import functools
from collections.abc import Callable
from typing import Any

import jax
import jax.numpy as jnp
import mpmath
import numpy as np
import pytest
import torch
from cases import (
    CASES,
    EDGE_CASES,
    OPS_BY_NAME,
    hamilton,
    hat,
    oracle_normalize,
    oracle_quaternion_to_matrix,
    uniform_quaternions,
)
from conftest import BACKENDS, Backend
from jax.test_util import check_grads

from diffquat import _lie

# torch.func.jacfwd's first call registers torch's forward-mode decompositions with torch.jit.script
pytestmark = pytest.mark.filterwarnings("ignore:`torch.jit.script` is deprecated:DeprecationWarning")

TWO_PI = 2 * np.pi
# Angles (radians) at every scale: 0, the series (|w| < 1) down to 1e-12, both sides of its threshold,
# near pi, then towards and past 2 pi, where J_l is singular (its inverse's pole) but J_l itself is not.
THETAS = np.array(
    [0.0, 1e-12, 1e-10, 1e-8, 1e-6, 1e-4, 1e-3, 1e-2, 0.05, 0.1, 0.3, 0.5, 0.9, 0.999, 1.0, 1.001, 1.2, 1.5,
     2.0, 2.5, 3.0, np.pi - 1e-2, np.pi - 1e-3, np.pi, 3.5, 4.0, 5.0, 5.5, 6.0, TWO_PI - 0.1, TWO_PI - 1e-2,
     TWO_PI - 1e-3, TWO_PI, 7.0, 10.0, 30.0]
)  # fmt: skip
AXES = np.array([[1.0, 0.0, 0.0], [1.0, 1.0, 1.0], [0.3, -0.5, 0.8]])
AXES /= np.linalg.norm(AXES, axis=-1, keepdims=True)
OMEGA = (THETAS[:, None, None] * AXES[None]).reshape(-1, 3)
ANGLE = np.repeat(THETAS, len(AXES))

JACOBIANS = {
    "so3_left_jacobian": ("jacobian", 1.0),
    "so3_right_jacobian": ("jacobian", -1.0),
    "so3_left_jacobian_inverse": ("inverse", -0.5),
    "so3_right_jacobian_inverse": ("inverse", 0.5),
}
NAMESPACES: dict[str, Any] = {"numpy": np, "torch": torch, "jax": jnp}
PRECISIONS = ("float32", "float64")
# Entries within this many ulps of the largest entry (float32: "a few"; float64: the issue allows a
# few tens). Measured: at most 1.9 (float32) and 1.7 (float64) ulps on every backend; the inverses
# grow near their pole (below).
ENTRY_ULPS = {"float32": 6.0, "float64": 8.0}
# The cancelling coefficients, (t - sin t) / t^3 and 1/t^2 - cot(t/2) / (2 t), relative to themselves:
# measured at most 5.6 ulps (float32) and 4.4 (float64), both at the series threshold t = 1.
COEFFICIENT_ULPS = 8.0


def _exact(x: np.ndarray) -> list[mpmath.mpf]:
    return [mpmath.mpf(float(c)) for c in x]


def _mp_coefficients(w: np.ndarray) -> dict[str, Any]:
    """The coefficients at the exact value of ``w`` (float64 numbers), in 60-digit arithmetic: with
    ``J = p I + q W + r w w^T``, (p, q, r) of J_l, and (p, r) of J_l^-1 (whose q is -1/2)."""
    x, y, z = _exact(w)
    u = x * x + y * y + z * z
    if u == 0:
        one = mpmath.mpf(1)
        return {"jacobian": (one, one / 2, one / 6), "inverse": (one, one / 12)}
    t = mpmath.sqrt(u)
    p = (t / 2) * mpmath.cot(t / 2)
    return {
        "jacobian": (mpmath.sin(t) / t, (1 - mpmath.cos(t)) / u, (t - mpmath.sin(t)) / (t * u)),
        "inverse": (p, (1 - p) / u),
    }


def _mp_matrix(w: np.ndarray, p: Any, q: Any, r: Any) -> np.ndarray:
    x, y, z = v = _exact(w)
    skew = [[0, -z, y], [z, 0, -x], [-y, x, 0]]
    return np.array(
        [[float((p if i == j else 0) + q * skew[i][j] + r * v[i] * v[j]) for j in range(3)] for i in range(3)]
    )


@functools.cache
def reference(precision: str) -> dict[str, Any]:
    """Once per session and precision: the rotation vectors as that dtype holds them (exactly, in
    float64), each Jacobian in 60 digits rounded to float64, and the cancelling coefficients."""
    with mpmath.workdps(60):
        omega = OMEGA.astype(precision).astype(np.float64)
        coefficients = [_mp_coefficients(w) for w in omega]
        out: dict[str, Any] = {"omega": omega}
        for name, (kind, sign) in JACOBIANS.items():
            if kind == "jacobian":
                out[name] = np.array(
                    [
                        _mp_matrix(w, c[kind][0], sign * c[kind][1], c[kind][2])
                        for w, c in zip(omega, coefficients, strict=True)
                    ]
                )
            else:
                out[name] = np.array(
                    [
                        _mp_matrix(w, c[kind][0], sign, c[kind][1])
                        for w, c in zip(omega, coefficients, strict=True)
                    ]
                )
        out["sine_cancelling"] = np.array([float(c["jacobian"][2]) for c in coefficients])
        out["cotangent_cancelling"] = np.array([float(c["inverse"][1]) for c in coefficients])
        return out


def _eps(precision: str) -> float:
    return float(np.finfo(precision).eps)


@pytest.mark.parametrize("name", list(JACOBIANS))
@pytest.mark.parametrize("precision", PRECISIONS)
def test_jacobians_against_mpmath(backend: Backend, precision: str, name: str) -> None:
    """Every entry within a few ulps of the largest, on the very float values given, from 0 to 30
    radians; the inverses up to 2 pi - 1e-3, their error growing as documented, like 1 / (2 pi - t)
    (measured: 14, 175 and 1218 ulps at 0.1, 1e-2 and 1e-3 from the pole), the pole itself left out."""
    ref = reference(precision)
    keep = np.ones(len(OMEGA), bool) if "inverse" not in name else ANGLE < TWO_PI - 1e-4
    omega = ref["omega"][keep]
    expected = ref[name][keep]
    out = backend.to_numpy(getattr(backend.module, name)(backend.array(omega, precision)))
    scale = np.abs(expected).max(axis=(-1, -2))
    ulps = np.abs(out - expected).max(axis=(-1, -2)) / (scale * _eps(precision))
    bound = ENTRY_ULPS[precision] * np.ones(len(omega))
    if "inverse" in name:
        bound = bound * np.maximum(1.0, 1.0 / np.abs(TWO_PI - ANGLE[keep]))
    worst = int(np.argmax(ulps / bound))
    assert np.all(ulps <= bound), f"{ulps[worst]:.1f} ulps at |w| = {ANGLE[keep][worst]}"


@pytest.mark.parametrize("precision", PRECISIONS)
def test_cancelling_coefficients_against_mpmath(backend: Backend, precision: str) -> None:
    """(t - sin t) / t^3 and 1/t^2 - cot(t/2) / (2 t) themselves to a few ulps (not only the entries,
    where t^2 hides their errors: a coefficient 1e-3 off at t = 0.02 changes no float32 entry, but
    every derivative), on both sides of the series threshold; the second up to pi (its pole is at
    2 pi)."""
    ref = reference(precision)
    xp = NAMESPACES[backend.name]
    omega = backend.array(ref["omega"], precision)
    _, _, sine = _lie._jacobian_coefficients(xp, omega)
    _, cotangent = _lie._inverse_coefficients(xp, omega)
    for got, expected, where in (
        (sine, ref["sine_cancelling"], np.ones(len(ANGLE), bool)),
        (cotangent, ref["cotangent_cancelling"], np.less_equal(ANGLE, np.pi)),
    ):
        ulps = np.abs(backend.to_numpy(got) - expected) / (np.abs(expected) * _eps(precision))
        assert np.all(ulps[where] <= COEFFICIENT_ULPS), float(ulps[where].max())


# ---------------------------------------------------------------------------------------------------
# Identities (float64)


def _vectors(angles: np.ndarray, seed: int) -> np.ndarray:
    """Rotation vectors of the given lengths about random axes."""
    axes = np.random.default_rng(seed).normal(size=(len(angles), 3))
    return axes / np.linalg.norm(axes, axis=-1, keepdims=True) * angles[:, None]


# |w| across the range of J_l (to 2 pi - 0.1, short of the inverse's pole) and both sides of t = 1.
IDENTITY_ANGLES = np.array(
    [0.0, 1e-9, 1e-4, 0.3, 0.999, 1.0, 1.001, 2.0, np.pi - 1e-6, np.pi, 4.0, 6.0, TWO_PI - 0.1]
)


def _float64(backend: Backend, *xs: np.ndarray) -> list[Any]:
    return [backend.array(x, "float64") for x in xs]


def table_batch(op_id: str, xs: tuple[np.ndarray, ...]) -> tuple[np.ndarray, ...]:
    """``xs`` repeated (``np.resize``) to one batch size per table row ``op_id`` (its smooth edge cases,
    at most 24 elements each): the tests of one function share it, and eager jax compiles each
    operation once per shape (at a new shape per test they took 25 s per function)."""
    op = OPS_BY_NAME[op_id]
    sizes = [int(np.prod(c.quaternions("float64").shape[:-1])) for c in CASES if c.name in EDGE_CASES]
    smooth = [op.applies(c) and op.smooth_at(c) for c in CASES if c.name in EDGE_CASES]
    n = sum(k if k <= 24 else min(24, -(-k // 4)) for k, keep in zip(sizes, smooth, strict=True) if keep)
    return tuple(np.resize(x, (n, *x.shape[1:])) for x in xs)


def test_jacobian_relations(backend: Backend) -> None:
    """J_r(w) = J_l(-w) = J_l(w)^T, J_l = exp(w) J_r, and each inverse is the inverse, over 0 ... 2 pi
    - 0.1 (J_l = exp(w) J_r also at 10 and 30)."""
    dq = backend.module
    omega = _vectors(np.concatenate([IDENTITY_ANGLES, [10.0, 30.0]]), seed=1)
    (w,) = _float64(backend, omega)
    left, right = backend.to_numpy(dq.so3_left_jacobian(w)), backend.to_numpy(dq.so3_right_jacobian(w))
    (minus_w,) = _float64(backend, -omega)
    np.testing.assert_array_equal(right, backend.to_numpy(dq.so3_left_jacobian(minus_w)))
    np.testing.assert_allclose(right, np.swapaxes(left, -1, -2), rtol=0, atol=1e-15)
    rotation = backend.to_numpy(dq.so3_exp(w))
    np.testing.assert_allclose(left, rotation @ right, rtol=0, atol=1e-14)
    bounded = np.abs(np.linalg.norm(omega, axis=-1)) < TWO_PI - 0.05
    for jacobian, inverse in ((left, dq.so3_left_jacobian_inverse), (right, dq.so3_right_jacobian_inverse)):
        product = jacobian @ backend.to_numpy(inverse(w))
        np.testing.assert_allclose(
            product[bounded], np.broadcast_to(np.eye(3), product[bounded].shape), atol=1e-13
        )


def test_jacobians_are_the_derivatives_of_exp_and_log() -> None:
    """At d = 0: the derivative of log(exp(w + d) exp(w)^T) is J_l(w), of log(exp(w)^T exp(w + d)) is
    J_r(w) (the convention: exp(w + d) = exp(J_l d) exp(w) = exp(w) exp(J_r d)); and the derivative of
    log(exp(d) R) is J_l(log R)^-1, of log(R exp(d)) is J_r(log R)^-1. Forward mode (torch.func)
    through diffquat's own exp and log, themselves tested against scipy in the table; the formulas are
    the same on every backend (their values are compared with mpmath above on each)."""
    dq = BACKENDS["torch"].module
    omega = _vectors(IDENTITY_ANGLES, seed=2)
    w, zero = torch.tensor(omega), torch.zeros(omega.shape, dtype=torch.float64)
    r = torch.tensor(oracle_quaternion_to_matrix(uniform_quaternions(len(omega), seed=3)))

    def perturbed(w: Any, d: Any, side: str) -> Any:
        moved, fixed = dq.so3_exp(w + d), dq.so3_exp(w)
        return dq.so3_log(moved @ fixed.mT if side == "left" else fixed.mT @ moved)

    def log_of(r: Any, d: Any, side: str) -> Any:
        return dq.so3_log(dq.so3_exp(d) @ r if side == "left" else r @ dq.so3_exp(d))

    def jacobian(f: Callable[..., Any], x: Any) -> np.ndarray:
        return torch.func.vmap(torch.func.jacfwd(f, argnums=1))(x, zero).numpy()

    for side, jac, inv in (
        ("left", dq.so3_left_jacobian, dq.so3_left_jacobian_inverse),
        ("right", dq.so3_right_jacobian, dq.so3_right_jacobian_inverse),
    ):
        derivative = jacobian(functools.partial(perturbed, side=side), w)
        np.testing.assert_allclose(derivative, jac(w).numpy(), rtol=0, atol=1e-12)
        derivative = jacobian(functools.partial(log_of, side=side), r)
        np.testing.assert_allclose(derivative, inv(dq.so3_log(r)).numpy(), rtol=0, atol=1e-11)


# Lengths of the perturbations in the round trips: up to pi - 1e-6 (at pi itself, minus returns the
# vector or its antipode, the same rotation: checked by the second round trip).
STEPS = np.array([0.0, 1e-12, 1e-9, 1e-6, 1e-3, 0.5, 1.0, 2.0, 3.0, np.pi - 1e-3, np.pi - 1e-6])
ROUND_TRIP_TOL = {"float64": 1e-12, "float32": 4e-6}


@pytest.mark.parametrize("side", ["right", "left"])
@pytest.mark.parametrize("precision", PRECISIONS)
def test_plus_and_minus_invert_each_other(backend: Backend, precision: str, side: str) -> None:
    """minus(plus(x, d), x) = d for |d| < pi, and plus(x2, minus(x1, x2)) = x1 for any pair (equal,
    a half-turn apart, generic), on matrices and on quaternions (those up to sign, and of any norm)."""
    dq = backend.module
    n = len(STEPS)
    delta = _vectors(STEPS, seed=4)
    q = uniform_quaternions(n, seed=5) * np.geomspace(1e-3, 1e3, n)[:, None]
    q1 = np.concatenate([uniform_quaternions(n - 2, seed=6), q[:2]])
    q1[1] = -q1[1]  # q and -q: the same rotation
    half_turn = np.concatenate([[0.0], _vectors(np.array([1.0]), seed=7)[0]])
    q1 = np.concatenate([q1, hamilton(q[-1:], half_turn[None])])  # a half-turn from q[-1] (right side)
    q2 = np.concatenate([q, q[-1:]])
    # at one batch size for the tests of so3_plus (shapes eager jax has compiled: see table_batch)
    delta, q = table_batch("so3_plus[left]", (delta, q))
    q1, q2 = table_batch("so3_plus[left]", (q1, q2))
    matrix = oracle_quaternion_to_matrix(q)
    m1, m2 = oracle_quaternion_to_matrix(q1), oracle_quaternion_to_matrix(q2)
    tol = ROUND_TRIP_TOL[precision]

    def run(fn: Callable[..., Any], *xs: np.ndarray) -> np.ndarray:
        return backend.to_numpy(fn(*(backend.array(x, precision) for x in xs), side=side))

    def received(x: np.ndarray) -> np.ndarray:
        return backend.to_numpy(backend.array(x, precision))

    # matrices
    moved = run(dq.so3_plus, matrix, delta)
    np.testing.assert_allclose(run(dq.so3_minus, moved, matrix), received(delta), rtol=0, atol=tol * np.pi)
    back = run(dq.so3_plus, m2, run(dq.so3_minus, m1, m2))
    np.testing.assert_allclose(back, received(m1), rtol=0, atol=4 * tol)
    # quaternions
    moved_q = run(dq.quaternion_plus, q, delta)
    np.testing.assert_allclose(np.linalg.norm(moved_q, axis=-1), 1.0, rtol=0, atol=tol)
    np.testing.assert_allclose(
        run(dq.quaternion_minus, moved_q, q), received(delta), rtol=0, atol=tol * np.pi
    )
    back_q = run(dq.quaternion_plus, q2, run(dq.quaternion_minus, q1, q2))
    expected = oracle_normalize(received(q1))
    sign = np.sign(np.sum(back_q * expected, axis=-1, keepdims=True))
    np.testing.assert_allclose(back_q * sign, expected, rtol=0, atol=4 * tol)


def test_hat_and_vee(backend: Backend) -> None:
    """hat(w) v = w x v; vee(hat(w)) = w exactly; hat(vee(M)) = (M - M^T) / 2 exactly, for any M."""
    dq = backend.module
    rng = np.random.default_rng(8)
    omega, v, m = rng.normal(size=(16, 3)), rng.normal(size=(16, 3)), rng.normal(size=(16, 3, 3))
    w, mm = _float64(backend, omega, m)
    skew = backend.to_numpy(dq.so3_hat(w))
    np.testing.assert_array_equal(skew, hat(omega))
    np.testing.assert_allclose((skew @ v[..., None])[..., 0], np.cross(omega, v), rtol=0, atol=1e-15)
    np.testing.assert_array_equal(backend.to_numpy(dq.so3_vee(dq.so3_hat(w))), omega)
    np.testing.assert_array_equal(
        backend.to_numpy(dq.so3_hat(dq.so3_vee(mm))), 0.5 * (m - np.swapaxes(m, -1, -2))
    )


def test_exp_and_log_are_the_axis_angle_maps(backend: Backend) -> None:
    """One implementation under two names: the same values, bit for bit (the same evaluation, on torch
    the same kernels), and errors that name the function called."""
    dq = backend.module
    omega = _vectors(IDENTITY_ANGLES, seed=9)
    w, m = _float64(backend, omega, oracle_quaternion_to_matrix(uniform_quaternions(16, seed=10)))
    np.testing.assert_array_equal(
        backend.to_numpy(dq.so3_exp(w)), backend.to_numpy(dq.axis_angle_to_matrix(w))
    )
    np.testing.assert_array_equal(
        backend.to_numpy(dq.so3_log(m)), backend.to_numpy(dq.matrix_to_axis_angle(m))
    )
    with pytest.raises(ValueError, match=r"so3_exp: expected omega of shape \(\.\.\., 3\)"):
        dq.so3_exp(backend.array(np.zeros((2, 4)), "float64"))
    with pytest.raises(ValueError, match=r"so3_log: expected matrix of shape \(\.\.\., 3, 3\)"):
        dq.so3_log(backend.array(np.zeros((2, 3)), "float64"))


SIDED = {
    "so3_plus": ((3, 3), (3,)),
    "so3_minus": ((3, 3), (3, 3)),
    "quaternion_plus": ((4,), (3,)),
    "quaternion_minus": ((4,), (4,)),
}


@pytest.mark.parametrize("name", list(SIDED))
def test_side_is_right_or_left(backend: Backend, name: str) -> None:
    """Anything but "right" and "left" raises a ValueError naming the function; "right" is the default."""
    fn = getattr(backend.module, name)
    shapes = SIDED[name]
    a, b = (backend.array(np.ones((2, *s)), "float64") for s in shapes)
    for bad in ("up", "Right", None):
        with pytest.raises(ValueError, match=rf"{name}: expected side to be 'right' or 'left', got {bad!r}"):
            fn(a, b, side=bad)
    np.testing.assert_array_equal(backend.to_numpy(fn(a, b)), backend.to_numpy(fn(a, b, side="right")))


@pytest.mark.parametrize("name", list(SIDED))
def test_plus_and_minus_broadcast_their_batch_shapes(backend: Backend, name: str) -> None:
    """Batch shapes broadcast as in the other two-argument functions: (2, 1) with (3,) gives (2, 3),
    each element the function of its own pair: within a few ulps of the call on the full arrays (XLA's
    CPU matrix product may round a broadcast batch differently from a full one, by an ulp)."""
    first, second = SIDED[name]
    q = uniform_quaternions(2, seed=11)[:, None]
    inputs = {
        (3, 3): lambda qs: oracle_quaternion_to_matrix(qs),
        (4,): lambda qs: qs,
        (3,): lambda qs: _vectors(np.full(qs.shape[0], 2.0), seed=12),
    }
    a = inputs[first](q)
    b = inputs[second](uniform_quaternions(3, seed=13))
    fn = getattr(backend.module, name)
    full = [np.broadcast_to(a, (2, 3, *first)).copy(), np.broadcast_to(b, (2, 3, *second)).copy()]
    for side in ("right", "left"):
        out = backend.to_numpy(fn(*_float64(backend, a, b), side=side))
        assert out.shape[:2] == (2, 3)
        expected = backend.to_numpy(fn(*_float64(backend, *full), side=side))
        np.testing.assert_allclose(out, expected, rtol=0, atol=4 * np.finfo(np.float64).eps)


# ---------------------------------------------------------------------------------------------------
# Derivatives the table's rows do not reach: the right side of plus and minus, and the Jacobians across
# their series threshold and beyond pi. float64.


def _sided_inputs(name: str) -> tuple[np.ndarray, ...]:
    """Generic pairs, equal pairs, pairs 1e-7 apart and pi - 1e-3 apart (not a half-turn: minus jumps
    there), perturbations of length 0, 1e-8, 1 and pi."""
    n = 8
    q = uniform_quaternions(n, seed=14)
    lengths = np.array([0.0, 1e-8, 0.3, 1.0, 1.0 + 1e-9, 2.0, np.pi - 1e-3, np.pi])
    delta = _vectors(lengths, seed=15)
    relative = np.concatenate(
        [np.cos(lengths / 2)[:, None], np.sin(lengths / 2)[:, None] * _vectors(np.ones(n), seed=16)], -1
    )
    relative[-1] = relative[-2]  # minus: pi - 1e-3 at most
    q1 = hamilton(q, relative)
    if name == "so3_plus":
        return oracle_quaternion_to_matrix(q), delta
    if name == "so3_minus":
        return oracle_quaternion_to_matrix(q1), oracle_quaternion_to_matrix(q)
    if name == "quaternion_plus":
        return q * 3.0, delta
    return q1 * 0.5, -q


@pytest.mark.parametrize("name", list(SIDED))
def test_right_side_first_and_second_derivatives(name: str) -> None:
    """gradcheck and gradgradcheck (torch), check_grads to second order forward and reverse (jax), of
    each function with side="right" (the table's rows are on the left)."""
    xs = table_batch(f"{name}[left]", _sided_inputs(name))
    torch_fn = functools.partial(getattr(BACKENDS["torch"].module, name), side="right")
    ts = tuple(torch.tensor(x, requires_grad=True) for x in xs)
    assert torch.autograd.gradcheck(torch_fn, ts, eps=1e-6, atol=1e-6, rtol=1e-5, fast_mode=True)
    assert torch.autograd.gradgradcheck(torch_fn, ts, eps=1e-6, atol=1e-5, rtol=1e-4, fast_mode=True)
    jax_fn = functools.partial(getattr(BACKENDS["jax"].module, name), side="right")
    # under jax.jit, as users run it: each derivative program compiles once, not each eager operation
    check_grads(jax.jit(jax_fn), tuple(jnp.asarray(x) for x in xs), order=2, modes=("fwd", "rev"), eps=1e-6)


# Both sides of the series threshold (|w| = 1), and beyond pi towards 2 pi (J_l only: its inverse's
# pole is there).
BEYOND_THE_TABLE = {
    "jacobian": np.array([0.5, 0.999999, 1.0, 1.000001, 2.0, 4.0, 5.5, TWO_PI, 7.0, 30.0]),
    "inverse": np.array([0.5, 0.999999, 1.0, 1.000001, 2.0, 3.5, 4.0, 5.0]),
}


@pytest.mark.parametrize("name", list(JACOBIANS))
def test_jacobian_derivatives_across_the_threshold_and_beyond_pi(name: str) -> None:
    """First and second derivatives of every Jacobian on both sides of the series threshold and at
    angles past pi, where the table's rotation vectors do not go: torch gradcheck/gradgradcheck and jax
    check_grads (order 2, forward and reverse)."""
    (omega,) = table_batch(name, (_vectors(BEYOND_THE_TABLE[JACOBIANS[name][0]], seed=17),))
    fn = getattr(BACKENDS["torch"].module, name)
    t = torch.tensor(omega, requires_grad=True)
    assert torch.autograd.gradcheck(fn, (t,), eps=1e-6, atol=1e-6, rtol=1e-5, fast_mode=True)
    assert torch.autograd.gradgradcheck(fn, (t,), eps=1e-6, atol=1e-5, rtol=1e-4, fast_mode=True)
    jax_fn = jax.jit(getattr(BACKENDS["jax"].module, name))
    check_grads(jax_fn, (jnp.asarray(omega),), order=2, modes=("fwd", "rev"), eps=1e-6)


# Angles for the float32 derivatives: every scale up to pi (and 6 for J_l), both sides of t = 1.
DERIVATIVE_ANGLES = np.array([0.0, 1e-12, 1e-8, 1e-4, 1e-3, 1e-2, 0.02, 0.05, 0.1, 0.3, 0.5, 0.9, 0.999, 1.0,
                              1.001, 1.2, 2.0, 3.0, np.pi - 1e-3])  # fmt: skip


def _eager_jacobian(fn: Callable[[Any], Any], omega: torch.Tensor) -> torch.Tensor:
    """d fn(w)[n, i, j] / d w[n], shape (N, 3, 3, 3), by eager reverse mode (one backward per entry;
    rows are independent): what a training loop's ``loss.backward()`` computes."""
    w = omega.clone().requires_grad_(True)
    out = fn(w)
    rows = [
        torch.autograd.grad(out[:, i, j].sum(), w, retain_graph=True)[0] for i in range(3) for j in range(3)
    ]
    return torch.stack(rows, dim=1).reshape(-1, 3, 3, 3)


@pytest.mark.parametrize("path", ["transforms", "eager"])
@pytest.mark.parametrize("name", ["so3_left_jacobian", "so3_left_jacobian_inverse"])
def test_float32_derivatives_are_as_accurate_as_the_values(name: str, path: str) -> None:
    """torch float32 Jacobians of the entries (reverse mode) within a few ulps of the largest, against
    the float64 evaluation of the same float32 inputs (itself checked against finite differences by
    the table), by torch.func and by eager autograd (``backward()``, one entry at a time): the series
    where the closed forms cancel keep the derivatives exact too (measured at most 2.1 ulps; 1e3 and
    more where the series stops at t ~ eps^(1/4) = 0.02, the usual choice)."""
    fn = getattr(BACKENDS["torch"].module, name)
    omega = torch.from_numpy(
        (DERIVATIVE_ANGLES[:, None, None] * AXES[None]).reshape(-1, 3).astype(np.float32)
    )
    if path == "transforms":
        jac32 = torch.func.vmap(torch.func.jacrev(fn))(omega).double().numpy()
    else:
        jac32 = _eager_jacobian(fn, omega).double().numpy()
    jac64 = torch.func.vmap(torch.func.jacrev(fn))(omega.double()).numpy()
    scale = np.abs(jac64).max(axis=(1, 2, 3))
    ulps = np.abs(jac32 - jac64).max(axis=(1, 2, 3)) / (scale * _eps("float32"))
    assert np.all(ulps <= 6.0), float(ulps.max())
