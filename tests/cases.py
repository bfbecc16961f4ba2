"""The named cases and the one table of operations that drive the whole suite.

Adding an operation to diffquat means adding one ``Op`` row to ``OPS``: values against the oracle,
properties, gradients, transforms, dtypes and bad-input errors then run for it on every backend.
Everything here is plain NumPy float64; the oracle is scipy's ``Rotation``, an independent
implementation, wherever scipy has the operation.
"""

from __future__ import annotations

import functools
import sys
import warnings
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field, replace
from typing import Any

import ml_dtypes
import mpmath
import numpy as np
import scipy.linalg
from scipy import integrate, special
from scipy.spatial.transform import Rotation, Slerp

DTYPES = ("float64", "float32", "float16", "bfloat16")

# Tolerances, the one place they are written down. VALUE_TOL: max abs error of an op's output against
# the float64 oracle evaluated on the very values the backend received (so input rounding is not
# counted, only the computation and the rounding of the output). For 16-bit types this is a few units
# in the last place of numbers of magnitude 1: the computation itself runs in float32.
VALUE_TOL = {"float64": 1e-12, "float32": 2e-6, "float16": 2e-3, "bfloat16": 1.6e-2}
# R -> q -> R, max abs error over all cases (the issue's accuracy targets for float32 and float64).
ROUND_TRIP_TOL = {"float64": 2e-15, "float32": 5e-7, "float16": 4e-3, "bfloat16": 3e-2}
# The norms a quaternion may have, per dtype (documented in the README): beyond these the squares of
# its components leave the normal range of the compute dtype (float32 for the 16-bit types), and XLA
# and GPUs flush subnormals to zero. float16 inputs are bounded by float16's own range.
NORM_RANGE = {
    "float64": (1e-20, 1e20),
    "float32": (1e-15, 1e15),
    "float16": (1e-4, 1e4),
    "bfloat16": (1e-15, 1e15),
}
# Gradient checks run in float64 only.
GRAD_DTYPE = "float64"


# ---------------------------------------------------------------------------------------------------
# Cases: batches of quaternions (w, x, y, z), float64, not necessarily unit.


def axis_angle_quaternions(axes: np.ndarray, angles: np.ndarray) -> np.ndarray:
    axes = axes / np.linalg.norm(axes, axis=-1, keepdims=True)
    half = 0.5 * angles[..., None]
    return np.concatenate([np.cos(half), np.sin(half) * axes], axis=-1)


def uniform_quaternions(n: int | tuple[int, ...], seed: int) -> np.ndarray:
    # scipy's sampler, not ours: the cases must not depend on the code under test.
    shape = (n,) if isinstance(n, int) else n
    flat = Rotation.random(int(np.prod(shape)), random_state=seed).as_quat(scalar_first=True)
    return flat.reshape((*shape, 4))


def _half_turns() -> np.ndarray:
    grid = np.array([(a, b, c) for a in (-1, 0, 1) for b in (-1, 0, 1) for c in (-1, 0, 1)], float)
    axes = grid[np.abs(grid).sum(axis=1) > 0]  # the 26 axes of {-1, 0, 1}^3
    return axis_angle_quaternions(axes, np.full(len(axes), np.pi))


def _tilted_axes(tilts: np.ndarray) -> np.ndarray:
    """Axes tilted by each angle in ``tilts`` away from x, y and z (towards a fixed oblique direction)."""
    out = []
    for k in range(3):
        base = np.eye(3)[k]
        away = np.array([0.3, 0.5, 0.8])
        away -= away.dot(base) * base
        away /= np.linalg.norm(away)
        out += [np.cos(t) * base + np.sin(t) * away for t in tilts]
    return np.array(out)


def _near_half_turns() -> np.ndarray:
    # 36 axes tilted by 1e-3 ... 1e-8, and their negatives: then w is tiny and positive while x, y or z
    # is negative, the combination where a rounding of w to 0 would break the canonical sign.
    axes = _tilted_axes(10.0 ** -np.arange(3, 9))
    axes = np.concatenate([axes, -axes])
    angles = np.pi - 10.0 ** -np.arange(1, 9)  # pi - 1e-1 ... pi - 1e-8
    return axis_angle_quaternions(np.repeat(axes, len(angles), axis=0), np.tile(angles, len(axes)))


def _near_identity() -> np.ndarray:
    axes = np.vstack([np.eye(3), [[1.0, 1.0, 1.0]], [[0.3, -0.5, 0.8]]])
    angles = 10.0 ** -np.arange(4, 11)  # 1e-4 ... 1e-10
    return axis_angle_quaternions(np.repeat(axes, len(angles), axis=0), np.tile(angles, len(axes)))


def _norms(dtype: str) -> np.ndarray:
    lo, hi = NORM_RANGE[dtype]
    scales = np.logspace(np.log10(lo), np.log10(hi), 9)
    return (uniform_quaternions(8, seed=3)[None, :, :] * scales[:, None, None]).reshape(-1, 4)


def _gimbal_locks() -> np.ndarray:
    """The 24 quaternions with entries in {0, +-1/2, +-1}: the identity, the half-turns about x, y, z and
    the third-turns about the cube's diagonals, each with both signs. Every Euler convention has exact
    gimbal locks among them (proper sequences: the identity and the half-turns; Tait-Bryan sequences:
    the third-turns that take the third axis onto the first), the others are far from any lock, and the
    entries are exact in every dtype, so the lock is exact on every backend."""
    units = np.vstack([np.eye(4), -np.eye(4)])
    halves = np.array([(a, b, c, d) for a in (-1, 1) for b in (-1, 1) for c in (-1, 1) for d in (-1, 1)])
    return np.vstack([units, 0.5 * halves])


@dataclass(frozen=True)
class Case:
    name: str
    make: Callable[[str], np.ndarray]  # dtype name -> quaternions, shape (..., 4)
    differentiable: bool = True  # False where the op is not differentiable (the zero quaternion)

    def quaternions(self, dtype: str) -> np.ndarray:
        return self.make(dtype)


def _fixed(q: np.ndarray) -> Callable[[str], np.ndarray]:
    return lambda dtype: q


CASES = [
    Case("random", _fixed(uniform_quaternions(64, seed=0))),
    Case("identity", _fixed(np.array([[1.0, 0, 0, 0], [-1.0, 0, 0, 0]]))),
    Case("half_turns", _fixed(_half_turns())),
    Case("near_half_turns", _fixed(_near_half_turns())),
    Case("near_identity", _fixed(_near_identity())),
    Case("norms", _norms),
    Case("sign_flip", _fixed(np.stack([uniform_quaternions(8, 1), -uniform_quaternions(8, 1)]))),
    Case("gimbal_lock", _fixed(_gimbal_locks())),
    Case("zero", _fixed(np.zeros((1, 4))), differentiable=False),
    Case("batch_scalar", _fixed(uniform_quaternions(1, seed=4)[0])),
    Case("batch_1", _fixed(uniform_quaternions(1, seed=5))),
    Case("batch_3x1x2", _fixed(uniform_quaternions((3, 1, 2), seed=6))),
    Case("batch_empty", _fixed(np.zeros((0, 4)))),
]
CASES_BY_NAME = {c.name: c for c in CASES}
# Cases for the expensive checks (gradcheck, jax's second order, compile): the named edge cases.
EDGE_CASES = ("random", "identity", "half_turns", "near_half_turns", "near_identity", "batch_3x1x2")


# ---------------------------------------------------------------------------------------------------
# Oracles (float64 NumPy; scipy where scipy has the operation).


def _flat(x: np.ndarray, trailing: int) -> tuple[np.ndarray, tuple[int, ...]]:
    x = np.array(x)  # a writable copy: scipy's Cython refuses read-only views of jax arrays
    batch = x.shape[: x.ndim - trailing]
    return x.reshape(-1, *x.shape[x.ndim - trailing :]), batch


def oracle_quaternion_to_matrix(q: np.ndarray) -> np.ndarray:
    flat, batch = _flat(q, 1)
    zero = np.all(flat == 0, axis=-1)  # documented: the zero quaternion gives the identity
    safe = np.where(zero[:, None], [1.0, 0.0, 0.0, 0.0], flat)
    out = Rotation.from_quat(safe, scalar_first=True).as_matrix() if len(flat) else np.zeros((0, 3, 3))
    return out.reshape((*batch, 3, 3))


def oracle_matrix_to_quaternion(matrix: np.ndarray) -> np.ndarray:
    flat, batch = _flat(matrix, 2)
    out = Rotation.from_matrix(flat).as_quat(canonical=True, scalar_first=True) if len(flat) else flat[:, 0]
    return out.reshape((*batch, 4))


def oracle_standardize(q: np.ndarray) -> np.ndarray:
    flat, _ = _flat(q, 1)
    out = flat.copy()
    for row in out:  # the rule as written: the first non-zero of (w, x, y, z) must be positive
        nonzero = row[row != 0]
        if len(nonzero) and nonzero[0] < 0:
            row *= -1
    return out.reshape(q.shape)


def oracle_normalize(q: np.ndarray) -> np.ndarray:
    norm = np.linalg.norm(q, axis=-1, keepdims=True)
    return np.where(norm > 0, q / np.where(norm > 0, norm, 1.0), [1.0, 0.0, 0.0, 0.0])


def outer(q: Any) -> Any:
    """q q^T: a smooth function of q that is blind to its sign, for gradient checks of ops whose
    output sign is canonicalised (and so jumps where w crosses 0, exactly at half-turns)."""
    return q[..., :, None] * q[..., None, :]


# ---------------------------------------------------------------------------------------------------
# The table of operations.


# ---------------------------------------------------------------------------------------------------
# Degenerate configurations: where the geometry degenerates (parallel vectors, collinear points, a
# scale at the ends of the dtype's range), each op's inputs and an error measure in ulps of the dtype
# against a reference at the inputs as rounded: mpmath at 40 digits where the map is written out
# here, else the row's float64 oracle at the inputs brought back to unit scale.


@dataclass(frozen=True)
class Degenerate:
    """One degenerate configuration of an op.

    name: what degenerates (tests/README.md lists them per op).
    make: dtype name -> the op's float64 inputs (they are rounded to the dtype, as received).
    error: (float64 inputs as received, the op's float64 output, the dtype's name) -> the worst
        error over the rows, in ulps (units of the dtype's eps).
    ulps: the bound on that error (say why in the row).
    """

    name: str
    make: Callable[[str], tuple[np.ndarray, ...]]
    error: Callable[[list[np.ndarray], np.ndarray, str], float]
    ulps: float


_MP_ZERO = mpmath.mpf(0)


def _at_40_digits(fn: Callable[..., float]) -> Callable[..., float]:
    """``fn`` evaluated with mpmath at 40 significant digits (the module's precision is left alone)."""

    @functools.wraps(fn)
    def wrapped(*args: Any) -> float:
        with mpmath.workdps(40):
            return fn(*args)

    return wrapped


def _mp_vector(v: np.ndarray) -> list[Any]:
    return [mpmath.mpf(float(x)) for x in v]


def _mp_unit(v: list[Any]) -> list[Any]:
    norm = mpmath.sqrt(sum(x * x for x in v))
    return [x / norm for x in v] if norm > 0 else list(v)


def _mp_dot(a: list[Any], b: list[Any]) -> Any:
    return sum((x * y for x, y in zip(a, b, strict=True)), _MP_ZERO)


def _mp_cross(a: list[Any], b: list[Any]) -> list[Any]:
    return [a[1] * b[2] - a[2] * b[1], a[2] * b[0] - a[0] * b[2], a[0] * b[1] - a[1] * b[0]]


def _orthogonality_ulps(r: np.ndarray, eps: float) -> float:
    """max |R^T R - I| and |det R - 1| over the rows of ``r`` ``(n, 3, 3)``, in mpmath, in ulps."""
    worst = 0.0
    for m in r.reshape(-1, 3, 3):
        mm = mpmath.matrix(m.tolist())
        gram = mm.T * mm - mpmath.eye(3)
        worst = max(worst, float(max(abs(gram[i, j]) for i in range(3) for j in range(3))))
        worst = max(worst, float(abs(mpmath.det(mm) - 1)))
    return worst / eps


@_at_40_digits
def between_error(received: list[np.ndarray], out: np.ndarray, dtype: str) -> float:
    """``rotation_between_vectors``: max over rows of |R a/|a| - b/|b|| (the map it promises, well
    conditioned at every angle, unlike R itself near antiparallel vectors) and half of R's distance
    from a rotation (bound 32 ulp where the map's is 16); a zero vector must give the identity."""
    eps = float(np.finfo(dtype).eps)
    a, b = (x.reshape(-1, 3) for x in received)
    r = out.reshape(-1, 3, 3)
    worst = 0.0
    for k in range(len(a)):
        ua, ub = _mp_unit(_mp_vector(a[k])), _mp_unit(_mp_vector(b[k]))
        if not any(ua) or not any(ub):
            worst = max(worst, float(np.abs(r[k] - np.eye(3)).max()) / eps)
            continue
        moved = mpmath.matrix(r[k].tolist()) * mpmath.matrix(ua)
        worst = max(worst, max(float(abs(moved[i] - ub[i])) for i in range(3)) / eps)
    return max(worst, _orthogonality_ulps(r, eps) / 2)


# rotation_6d_to_matrix's fallback: the part of a2 orthogonal to b1 at most 8 eps |a2| (one
# Gram-Schmidt pass's rounding is up to ~4 eps |a2|: between 2 and 16 eps either branch is right).
_PARALLEL_BELOW, _EITHER_BRANCH = 8.0, (2.0, 16.0)


def _mp_gram_schmidt(a1: list[Any], a2: list[Any], fallback: bool) -> tuple[Any, Any]:
    """rotation_6d_to_matrix in mpmath: the matrix and the sine of the angle between b1 and a2 (the
    conditioning of b2); ``fallback``: b2 from the coordinate axis least aligned with b1."""
    b1 = _mp_unit(a1) if any(a1) else [mpmath.mpf(1), _MP_ZERO, _MP_ZERO]
    if fallback:
        k = min(range(3), key=lambda i: (abs(b1[i]), i))
        a2 = [mpmath.mpf(i == k) for i in range(3)]
    c = _mp_dot(b1, a2)
    u2 = [x - c * y for x, y in zip(a2, b1, strict=True)]
    n2 = mpmath.sqrt(_mp_dot(a2, a2))
    sine = mpmath.sqrt(_mp_dot(u2, u2)) / n2 if n2 > 0 else _MP_ZERO
    b2 = _mp_unit(u2)
    return mpmath.matrix([b1, b2, _mp_cross(b1, b2)]).T, sine


def _six_d_row_error(a1: list[Any], a2: list[Any], r: np.ndarray, eps: float) -> float:
    """One row of ``six_d_error``: the mpmath columns ``a1``, ``a2`` and the op's matrix ``r``."""
    _, sine = _mp_gram_schmidt(a1, a2, fallback=False)
    lo, hi = _EITHER_BRANCH
    branches = [bool(sine <= _PARALLEL_BELOW * eps)] if not lo * eps < sine < hi * eps else [False, True]
    errors = []
    for fallback in branches:
        ref, _ = _mp_gram_schmidt(a1, a2, fallback)
        # b2 and b3 carry the rounding of a2's remainder, eps |a2| / |u2|: weighed by the sine
        weight = mpmath.mpf(1) if fallback else min(mpmath.mpf(1), sine)
        b1 = max(abs(mpmath.mpf(float(r[i, 0])) - ref[i, 0]) for i in range(3))
        rest = max(abs(mpmath.mpf(float(r[i, j])) - ref[i, j]) for i in range(3) for j in (1, 2))
        errors.append(float(max(b1, rest * weight)) / eps)
    return min(errors)


@_at_40_digits
def six_d_error(received: list[np.ndarray], out: np.ndarray, dtype: str) -> float:
    """``rotation_6d_to_matrix`` (columns) against Gram-Schmidt in mpmath with the documented fallback
    at 8 eps of the dtype (either branch where the remainder is within 2-16 eps: rounding decides),
    the errors of b2 and b3 weighed by their conditioning (the sine between a1 and a2), and half of
    R's distance from a rotation."""
    eps = float(np.finfo(dtype).eps)
    d6, r = received[0].reshape(-1, 6), out.reshape(-1, 3, 3)
    worst = max(
        (_six_d_row_error(_mp_vector(d6[k, :3]), _mp_vector(d6[k, 3:]), r[k], eps) for k in range(len(d6))),
        default=0.0,
    )
    return max(worst, _orthogonality_ulps(r, eps) / 2)


@_at_40_digits
def frame_error(received: list[np.ndarray], out: np.ndarray, dtype: str) -> float:
    """``frame_from_three_points``: the 6D map's error (``six_d_error``) at (x3 - x2, x1 - x2) taken
    in mpmath, and the origin exactly x2."""
    eps = float(np.finfo(dtype).eps)
    shape = np.broadcast_shapes(*(x.shape for x in received))
    x1, x2, x3 = (np.broadcast_to(x, shape).reshape(-1, 3) for x in received)
    frames = out.reshape(-1, 4, 4)
    worst = 0.0
    for k in range(len(x1)):
        p1, p2, p3 = _mp_vector(x1[k]), _mp_vector(x2[k]), _mp_vector(x3[k])
        a1 = [u - v for u, v in zip(p3, p2, strict=True)]
        a2 = [u - v for u, v in zip(p1, p2, strict=True)]
        worst = max(worst, _six_d_row_error(a1, a2, frames[k, :3, :3], eps))
    if np.any(frames[:, :3, 3] != x2):
        return np.inf
    return max(worst, _orthogonality_ulps(frames[:, :3, :3], eps) / 2)


def _extreme_scale(dtype: str, sign: int) -> float:
    return 10.0 ** (sign * (30 if dtype == "float32" else 300))


def at_unit_scale(op_name: str, sign: int) -> Callable[[list[np.ndarray], np.ndarray, str], float]:
    """The fits of point sets scaled by 1e30 / 1e-30 (float32) or 1e300 / 1e-300 (float64): the row's
    float64 oracle at the inputs brought back to unit scale (the maps are scale-free; the
    translation scales with the points), errors relative to the largest expected entry, in ulps."""

    def error(received: list[np.ndarray], out: np.ndarray, dtype: str) -> float:
        scale = _extreme_scale(dtype, sign)
        source, target, *rest = received
        expected = OPS_BY_NAME[op_name].oracle(source / scale, target / scale, *rest)
        actual = np.array(out, np.float64)
        actual[..., :3, 3] /= scale
        largest = np.abs(expected).max(axis=(-1, -2), keepdims=True)
        return float((np.abs(actual - expected) / largest).max()) / float(np.finfo(dtype).eps)

    return error


def _antiparallel_pairs(dtype: str) -> tuple[np.ndarray, ...]:
    a = np.array(
        [
            [1e-3, 2.0, -1e-3],
            [1.0, 0.0, 0.0],
            [0.0, 0.0, 3.0],
            [0.0, -2.0, 0.0],
            [1.0, 1.0, 1.0],
            [0.3, -0.5, 0.8],
            [-0.6, 0.0, 0.8],
            [2e20, 1e17, -3e19],
        ]
    )
    a = host_cast(a, HOST_DTYPES[dtype]).astype(np.float64)
    return np.concatenate([a, a]), np.concatenate([-a, -2.5 * a])


def _parallel_pairs(dtype: str) -> tuple[np.ndarray, ...]:
    a, b = _antiparallel_pairs(dtype)
    return a, -b


def _generic_directions(n: int, seed: int) -> tuple[np.ndarray, np.ndarray]:
    """``n`` unit vectors a and unit vectors p orthogonal to them."""
    rng = np.random.default_rng(seed)
    a = rng.normal(size=(n, 3))
    a /= np.linalg.norm(a, axis=-1, keepdims=True)
    p = rng.normal(size=(n, 3))
    p -= np.sum(p * a, axis=-1, keepdims=True) * a
    return a, p / np.linalg.norm(p, axis=-1, keepdims=True)


def _near_antiparallel(dtype: str) -> tuple[np.ndarray, ...]:
    """b a half-turn minus delta from a, delta = 1e-4 ... 1e-12, lengths 0.1 to 10."""
    gaps = 10.0 ** -np.arange(4, 13)
    a, p = _generic_directions(4 * len(gaps), seed=31)
    gap = np.repeat(gaps, 4)[:, None]
    return 0.1 * a, 10.0 * (np.cos(np.pi - gap) * a + np.sin(np.pi - gap) * p)


def _every_angle(dtype: str) -> tuple[np.ndarray, ...]:
    """Angles 0, pi/32, ..., pi (the last one pi as rounded in float64: 1.2e-16 from antiparallel)."""
    angles = np.linspace(0.0, np.pi, 33)[:, None]
    a, p = _generic_directions(len(angles), seed=32)
    return a, np.cos(angles) * a + np.sin(angles) * p


def _extreme_lengths(dtype: str) -> tuple[np.ndarray, ...]:
    """Lengths 1e-30 ... 1e30 (float32) or 1e-300 ... 1e300 (float64), generic and 1e-6 from
    antiparallel, each vector at its own length."""
    top = 30 if dtype == "float32" else 300
    lengths = 10.0 ** np.linspace(-top, top, 7)
    a, p = _generic_directions(14, seed=33)
    gap = np.array([1.0, 1e-6]).repeat(7)[:, None]
    b = np.cos(np.pi - gap) * a + np.sin(np.pi - gap) * p
    return a * np.tile(lengths, 2)[:, None], b * np.tile(lengths[::-1], 2)[:, None]


def _zero_vectors(dtype: str) -> tuple[np.ndarray, ...]:
    return np.array([[0.0, 0.0, 0.0], [1.0, 2.0, 3.0], [0.0, 0.0, 0.0]]), np.array(
        [[1.0, 0.0, 0.0], [0.0, 0.0, 0.0], [0.0, 0.0, 0.0]]
    )


BETWEEN_DEGENERATE = (
    Degenerate("parallel", _parallel_pairs, between_error, 16),
    Degenerate("antiparallel", _antiparallel_pairs, between_error, 16),
    Degenerate("near_antiparallel", _near_antiparallel, between_error, 16),
    Degenerate("every_angle", _every_angle, between_error, 16),
    Degenerate("extreme_lengths", _extreme_lengths, between_error, 16),
    Degenerate("zero_vector", _zero_vectors, between_error, 0),
)


def _parallel_columns(dtype: str) -> tuple[np.ndarray, ...]:
    """a2 = k a1 exactly (k a power of 2, or 1, or 0), and the review's row (parallel once rounded to
    float32: 0.6 = 2 x 0.3 there)."""
    a1 = np.random.default_rng(34).normal(size=(6, 3))
    rows = [np.concatenate([a1, k * a1], axis=-1) for k in (2.0, -0.5, 1.0, 0.0)]
    return (np.concatenate([*rows, [[0.3, -0.5, 0.8, 0.6, -1.0, 1.6], [0.0] * 6]]),)


def _near_parallel_columns(dtype: str) -> tuple[np.ndarray, ...]:
    """a2 within 1e-3 ... 1e-9 of a1's direction (some below the fallback's threshold in float32)."""
    a1, p = _generic_directions(14, seed=35)
    gap = np.tile(10.0 ** -np.arange(3, 10), 2)[:, None]
    return (np.concatenate([3.0 * a1, 0.5 * (np.cos(gap) * a1 + np.sin(gap) * p)], axis=-1),)


def _scaled_columns(dtype: str) -> tuple[np.ndarray, ...]:
    top = 30 if dtype == "float32" else 300
    g = np.random.default_rng(36).normal(size=(8, 6))
    scale = np.array([10.0**top, 10.0**-top, 10.0**top, 10.0**-top])
    return (np.concatenate([g[:4, :3] * scale[:, None], g[:4, 3:] * scale[::-1, None]], axis=-1),)


SIX_D_DEGENERATE = (
    Degenerate("parallel_columns", _parallel_columns, six_d_error, 16),
    Degenerate("near_parallel_columns", _near_parallel_columns, six_d_error, 16),
    Degenerate("extreme_scales", _scaled_columns, six_d_error, 16),
)


def _collinear_points(dtype: str) -> tuple[np.ndarray, ...]:
    """x1 on the line of x2 and x3 exactly (small integers), the review's triple (on it before
    rounding), and coincident points (x3 = x2, x1 = x2, all three)."""
    x2 = np.array([1.0, 1.0, 1.0])
    x3 = np.array([[2.0, 1.0, 1.0], [1.0, 3.0, -2.0], [4.0, 5.0, 6.0], [1.1, 1.2, 1.3], [1.0, 1.0, 1.0]])
    x1 = np.array([[3.0, 1.0, 1.0], [1.0, -3.0, 7.0], [-2.0, -3.0, -4.0], [1.2, 1.4, 1.6], [0.0, 2.0, 1.0]])
    x1 = np.concatenate([x1, [[1.0, 1.0, 1.0], [1.0, 1.0, 1.0]]])
    x3 = np.concatenate([x3, [[2.0, 0.0, 1.0], [1.0, 1.0, 1.0]]])
    return x1, np.broadcast_to(x2, x1.shape).copy(), x3


def _scaled_points(dtype: str) -> tuple[np.ndarray, ...]:
    top = 30 if dtype == "float32" else 300
    x1, x2, x3 = (np.random.default_rng(37 + k).normal(size=(4, 3)) for k in range(3))
    scale = np.array([10.0**top, 10.0**-top, 10.0**top, 10.0**-top])[:, None]
    return x1 * scale, x2 * scale, x3 * scale


FRAME_DEGENERATE = (
    Degenerate("collinear_and_coincident", _collinear_points, frame_error, 16),
    Degenerate("extreme_scales", _scaled_points, frame_error, 16),
)


def _scaled_point_sets(sign: int) -> Callable[[str], tuple[np.ndarray, ...]]:
    def make(dtype: str) -> tuple[np.ndarray, ...]:
        source, target, weights = _fit_pose_inputs(uniform_quaternions(6, seed=38))
        scale = _extreme_scale(dtype, sign)
        return source * scale, target * scale, weights

    return make


def fit_degenerate(name: str) -> tuple[Degenerate, ...]:
    # 32 ulp: the SVD's error relative to the largest entry (4.3 ulp measured in float32)
    return tuple(
        Degenerate(f"scale_{label}", _scaled_point_sets(sign), at_unit_scale(name, sign), 32)
        for label, sign in (("huge", 1), ("tiny", -1))
    )


def against_the_oracle(op_id: str) -> Callable[[list[np.ndarray], np.ndarray, str], float]:
    """The row's own float64 oracle at the inputs as received, measured as the table measures it
    (``table_error``: relative, up to the sign, ...), in ulps of the dtype."""

    def error(received: list[np.ndarray], out: np.ndarray, dtype: str) -> float:
        op = OPS_BY_NAME[op_id]
        return table_error(op, received, out, op.expected(*received)) / float(np.finfo(dtype).eps)

    return error


def _without_translation(x: np.ndarray) -> np.ndarray:
    """A pose ``(..., 4, 4)`` with its translation zeroed, or a twist ``(..., 6)`` with its rho."""
    x = np.array(x)
    if x.shape[-2:] == (4, 4):
        x[..., :3, 3] = 0.0
    else:
        x[..., :3] = 0.0
    return x


def zero_translation(
    op_id: str, inputs: Callable[[np.ndarray], tuple[np.ndarray, ...]], ulps: float
) -> tuple[Degenerate, ...]:
    """An SE(3) row at pure rotations (zero translation, zero rho) of the identity, the 26 exact
    half-turns and rotations 1e-1 ... 1e-8 short of a half-turn, where the rotation part degenerates,
    against the row's float64 oracle."""
    quaternions = np.concatenate([[[1.0, 0.0, 0.0, 0.0]], _half_turns(), _near_half_turns()[::7]])
    return (
        Degenerate(
            "zero_translation",
            lambda dtype: tuple(_without_translation(x) for x in inputs(quaternions)),
            against_the_oracle(op_id),
            ulps,
        ),
    )


_EXPECTED: dict[tuple[Any, ...], np.ndarray] = {}


@dataclass(frozen=True)
class Op:
    """One public function of diffquat and everything the suite needs to test it.

    name: its name in every backend module.
    inputs: case quaternions (float64, (..., 4)) -> the op's float64 input arrays.
    oracle: float64 inputs (as the backend received them) -> the expected float64 output.
    quaternion_args: which positional inputs are quaternions (reordered for ``scalar_first=False``).
    output: "matrix", "quaternion" or "other"; matrices are checked to be rotations.
    scalar_first: whether the op takes the ``scalar_first`` keyword.
    canonical: the output quaternion is in canonical sign (checked as a property), which makes the op
        jump where w crosses 0: gradients are checked through ``outer``.
    unit: the output quaternion has unit norm.
    up_to_sign: compare with the oracle up to the sign of q: when the true w is 0 (half-turns),
        rounding legitimately decides the canonical sign.
    grad_inputs / grad_fn: what gradients are checked on; by default the op itself on its inputs.
        ``grad_fn(module, *xs)`` must be differentiable at every case (see ``outer``).
    kwargs: keyword arguments the op is called with (e.g. an Euler convention).
    label: the name in test ids when one function has several rows (default: ``name``).
    tol_scale: this op's tolerances are ``tol_scale`` times the table's (say why where it is not 1).
    applies: the cases this op is run on at all (default: all).
    finite_gradient: (case, dtype) -> whether the gradient is representable there, and so must be
        finite (default: everywhere; the exception is a true derivative beyond the dtype's range).
    smooth_at: the cases where the op is differentiable, so that gradients must match finite
        differences; elsewhere they must only be finite (default: ``case.differentiable``).
    to_scalar_last: maps one quaternion argument (see ``quaternion_args``) to its scalar-last form
        (default: reorder the last axis; the 10D representation permutes its matrix instead).
    relative: errors are measured relative to the largest entry of each expected output element (for
        ops whose output scales with the norm of the input, e.g. ``quaternion_invert`` at 1e20).
    error_scale: float64 inputs -> the size, per batch element, that errors are measured against
        (for scalar outputs whose size follows the input's, e.g. a log normaliser at |F| = 1e20).
    periodic: the outputs are angles, compared modulo 2 pi (an angle of pi may come back as -pi).
    join: for a function that returns a pair, the one array the table checks, made from the pair
        with operators every backend's arrays share (``fit_similarity_transform``: ``s T``).
    other_branch: with ``up_to_sign``, the other of the two results at a jump, from one of them
        (default: its negation; an SE(3) log's other twist at a half-turn has -phi and another rho).
    variant_of: the label of the row this one is a variant of, whose code path it shares: a keyword
        variant (the 6D layout: the axis the result is stacked on, a static choice), or another name
        of the same map (``so3_exp`` is ``axis_angle_to_matrix``, ``matrix_fisher_mode`` is
        ``special_procrustes``: one core function; tests/test_api.py checks that the two names give
        the same values). Values, properties, errors, per-case gradients against finite differences,
        captures and exports run on it; the compile-heavy checks of the derivatives (jax's second
        order, ``torch.compile``, compiled forward mode, jit/vmap/grad: tens of seconds per row) run
        on the base row only (``base_rows``, ``Op.variant_of`` in test_grads.test_jax_derivatives),
        where the same map is checked. ``variant_inputs`` maps the variant's inputs to the base's
        where the map is the base's at other arguments (``J_r(xi) = J_l(-xi)``, computed as that).
    degenerate: the op's degenerate configurations (``Degenerate``: parallel and antiparallel vectors,
        collinear points, extreme scales, ...), each checked against a high-precision reference at
        the inputs as rounded, in float32 and float64 (test_values.test_degenerate_inputs; the list
        per op is in tests/README.md).
    second_order_modes: the modes in which jax's second order is checked as ``check_grads`` checks
        it (``jvp`` of ``jvp``, ``vjp`` of ``vjp``; the first order is checked in both): the iterative
        means check it in reverse mode, where XLA compiles each
        transformed program of their loops for 5-10 s and forward-over-forward added 30 s a row.
    """

    name: str
    inputs: Callable[[np.ndarray], tuple[np.ndarray, ...]]
    oracle: Callable[..., np.ndarray]
    quaternion_args: tuple[int, ...] = (0,)
    output: str = "quaternion"
    scalar_first: bool = True
    canonical: bool = False
    unit: bool = False
    up_to_sign: bool = False
    grad_inputs: Callable[[np.ndarray], tuple[np.ndarray, ...]] | None = None
    grad_fn: Callable[..., Any] | None = None
    kwargs: Mapping[str, Any] = field(default_factory=dict)
    label: str = ""
    tol_scale: float = 1.0
    applies: Callable[[Case], bool] = lambda case: True
    smooth_at: Callable[[Case], bool] = lambda case: case.differentiable
    finite_gradient: Callable[[Case, str], bool] = lambda case, dtype: True
    to_scalar_last: Callable[[np.ndarray], np.ndarray] = lambda x: x[..., [1, 2, 3, 0]]
    relative: bool = False
    error_scale: Callable[..., np.ndarray] | None = None
    periodic: bool = False
    variant_of: str = ""
    second_order_modes: tuple[str, ...] = ("fwd", "rev")
    other_branch: Callable[[np.ndarray], np.ndarray] | None = None
    join: Callable[[Any], Any] | None = None
    variant_inputs: Callable[..., tuple[Any, ...]] = lambda *xs: xs
    degenerate: tuple[Degenerate, ...] = ()

    @property
    def id(self) -> str:
        return self.label or self.name

    def __call__(self, module: Any, *xs: Any, **kw: Any) -> Any:
        out = getattr(module, self.name)(*xs, **self.kwargs, **kw)
        return out if self.join is None else self.join(out)

    def expected(self, *xs: np.ndarray) -> np.ndarray:
        """The oracle's output on float64 inputs, computed once per distinct input: the backends
        receive the same values in a dtype (the suite casts on the host), and some oracles (scipy's
        matrix exponential, a loop of ``align_vectors``) take seconds over a whole table."""
        key = (self.id, *((x.shape, x.tobytes()) for x in (np.ascontiguousarray(x, np.float64) for x in xs)))
        if key not in _EXPECTED:
            _EXPECTED[key] = self.oracle(*xs)
        return _EXPECTED[key]

    def gradient_inputs(self, q: np.ndarray) -> tuple[np.ndarray, ...]:
        return (self.grad_inputs or self.inputs)(q)

    def gradient_function(self, module: Any) -> Callable[..., Any]:
        if self.grad_fn is not None:
            return lambda *xs: self.grad_fn(module, *xs)  # type: ignore[misc]
        if self.canonical:
            return lambda *xs: outer(self(module, *xs))
        return lambda *xs: self(module, *xs)


def _q(q: np.ndarray) -> tuple[np.ndarray, ...]:
    return (q,)


def _unit(q: np.ndarray) -> tuple[np.ndarray, ...]:
    return (oracle_normalize(q),)


def _matrix(q: np.ndarray) -> tuple[np.ndarray, ...]:
    return (oracle_quaternion_to_matrix(q),)


# ---------------------------------------------------------------------------------------------------
# Representations for network outputs (6D, 9D, 10D) and fitting. Inputs are built from the case
# quaternion q so that every named case (half-turns, near identity, norms, batch shapes) reaches them:
# its rotation R(q), scaled by |q| (so the "norms" case spans the dtype's range and "zero" gives the
# degenerate all-zero input).


def _scale(q: np.ndarray) -> np.ndarray:
    return np.linalg.norm(q, axis=-1)


def _d6(q: np.ndarray) -> tuple[np.ndarray, ...]:
    """Unnormalised, non-orthogonal columns whose Gram-Schmidt is R(q): (2 c0, c1 + 0.5 c0) * |q|."""
    r = oracle_quaternion_to_matrix(q)
    c0, c1 = r[..., :, 0], r[..., :, 1]
    return (np.concatenate([2.0 * c0, c1 + 0.5 * c0], axis=-1) * _scale(q)[..., None],)


def _d6_rows(q: np.ndarray) -> tuple[np.ndarray, ...]:
    """The same from the rows of R(q), pytorch3d's layout: (2 r0, r1 + 0.5 r0) * |q|."""
    r = oracle_quaternion_to_matrix(q)
    r0, r1 = r[..., 0, :], r[..., 1, :]
    return (np.concatenate([2.0 * r0, r1 + 0.5 * r0], axis=-1) * _scale(q)[..., None],)


LAYOUT_CASES = ("random", "half_turns", "norms", "zero", "batch_scalar", "batch_3x1x2")


def oracle_rotation_6d_to_matrix(d6: np.ndarray) -> np.ndarray:
    """Gram-Schmidt by numpy's QR (Householder: an independent algorithm), signs fixed so that the
    diagonal of the triangular factor is positive; the documented fallbacks for degenerate input."""
    flat, batch = _flat(d6, 1)
    out = np.zeros((len(flat), 3, 3))
    for k, row in enumerate(flat):
        a1, a2 = row[:3], row[3:]
        if a1 @ a1 < np.finfo(np.float64).tiny:
            a1 = np.array([1.0, 0.0, 0.0])
        b1 = a1 / np.linalg.norm(a1)
        resid = a2 - (b1 @ a2) * b1
        if resid @ resid <= (8 * np.finfo(np.float64).eps) ** 2 * (a2 @ a2) + np.finfo(np.float64).tiny:
            a2 = np.eye(3)[int(np.argmin(np.abs(b1)))]  # argmin: the first on ties
        qm, rm = np.linalg.qr(np.stack([a1, a2], axis=-1))
        qm = qm * np.sign(np.diag(rm))
        out[k] = np.stack([qm[:, 0], qm[:, 1], np.cross(qm[:, 0], qm[:, 1])], axis=-1)
    return out.reshape((*batch, 3, 3))


# Fixed matrices right-multiplying R(q): generic singular values, one with det < 0 (the determinant
# fix), one of rank 2 (s_3 = 0; still differentiable: the denominators are s_i + s_3 > 0).
_REFLECTION = np.array([[1.8, 0.3, -0.2], [0.1, 1.1, 0.4], [0.3, -0.2, -0.5]])
_GENERIC = np.array([[1.5, 0.2], [-0.3, 0.9], [0.4, 0.1]])
_RANK2 = np.concatenate([_GENERIC, _GENERIC @ [[1.0], [0.2]]], axis=1)  # column 2 = column 0 + 0.2 column 1


def _procrustes_inputs(factor: np.ndarray) -> Callable[[np.ndarray], tuple[np.ndarray, ...]]:
    return lambda q: (_scale(q)[..., None, None] * (oracle_quaternion_to_matrix(q) @ factor),)


def oracle_special_procrustes(matrix: np.ndarray) -> np.ndarray:
    """float64 NumPy SVD with the determinant fixed (scipy's Rotation has no Procrustes of a matrix)."""
    u, _, vh = np.linalg.svd(matrix)
    d = np.sign(np.linalg.det(u @ vh))
    return (u * np.stack([np.ones_like(d), np.ones_like(d), d], axis=-1)[..., None, :]) @ vh


_UPPER = [(0, 0), (0, 1), (0, 2), (0, 3), (1, 1), (1, 2), (1, 3), (2, 2), (2, 3), (3, 3)]


def _sym4(a: np.ndarray) -> np.ndarray:
    m = np.zeros((*a.shape[:-1], 4, 4))
    for k, (i, j) in enumerate(_UPPER):
        m[..., i, j] = m[..., j, i] = a[..., k]
    return m


def _upper10(m: np.ndarray) -> np.ndarray:
    return np.stack([m[..., i, j] for i, j in _UPPER], axis=-1)


def _a10(q: np.ndarray) -> tuple[np.ndarray, ...]:
    """|q| L diag(0, 1, 2, 3) L^T with L the (orthogonal) left-multiplication matrix of q/|q|, whose
    first column is q/|q|: the eigenvector of the smallest eigenvalue is q/|q|, with gap |q|."""
    w, x, y, z = np.moveaxis(oracle_normalize(q), -1, 0)
    left = np.stack(
        [
            np.stack([w, -x, -y, -z], axis=-1),
            np.stack([x, w, -z, y], axis=-1),
            np.stack([y, z, w, -x], axis=-1),
            np.stack([z, -y, x, w], axis=-1),
        ],
        axis=-2,
    )
    m = (left * np.array([0.0, 1.0, 2.0, 3.0])) @ np.swapaxes(left, -1, -2)
    return (_upper10(m * _scale(q)[..., None, None]),)


def oracle_symmetric_matrix_to_quaternion(a: np.ndarray) -> np.ndarray:
    """NumPy's float64 eigh (LAPACK), canonical sign."""
    return oracle_standardize(np.linalg.eigh(_sym4(a))[1][..., :, 0])


def a10_to_scalar_last(a: np.ndarray) -> np.ndarray:
    """The same matrix with its rows and columns in (x, y, z, w) order."""
    return _upper10(_sym4(a)[..., [1, 2, 3, 0], :][..., :, [1, 2, 3, 0]])


# Points for fit_rotation: 5 generic points, target = |q| R(q) source + noise, positive weights.
_POINTS = np.random.default_rng(11).normal(size=(5, 3))
_NOISE = 0.05 * np.random.default_rng(12).normal(size=(5, 3))
_WEIGHTS = np.array([1.0, 0.5, 2.0, 0.25, 1.5])


def _fit_inputs(q: np.ndarray) -> tuple[np.ndarray, ...]:
    batch = q.shape[:-1]
    source = np.broadcast_to(_POINTS, (*batch, 5, 3)).copy()
    target = _scale(q)[..., None, None] * (
        source @ np.swapaxes(oracle_quaternion_to_matrix(q), -1, -2) + _NOISE
    )
    return source, target, np.broadcast_to(_WEIGHTS, (*batch, 5)).copy()


def oracle_fit_rotation(
    source: np.ndarray, target: np.ndarray, weights: np.ndarray | None = None
) -> np.ndarray:
    """scipy's ``align_vectors(a, b)`` finds R with a ~ R b: here a = target, b = source."""
    batch = source.shape[:-2]
    s, t = source.reshape(-1, *source.shape[-2:]), target.reshape(-1, *target.shape[-2:])
    w = None if weights is None else weights.reshape(-1, weights.shape[-1])
    out = np.zeros((len(s), 3, 3))
    for k in range(len(s)):
        with warnings.catch_warnings():  # scipy warns that the zero input has no unique rotation
            warnings.simplefilter("ignore")
            out[k] = Rotation.align_vectors(t[k], s[k], None if w is None else w[k])[0].as_matrix()
    return out.reshape((*batch, 3, 3))


OPS = [
    Op("quaternion_to_matrix", _q, oracle_quaternion_to_matrix, output="matrix"),
    Op(
        "matrix_to_quaternion",
        _matrix,
        oracle_matrix_to_quaternion,
        quaternion_args=(),
        canonical=True,
        unit=True,
        up_to_sign=True,
        # Checked on SO(3): u -> m2q(q2m(u)). Off SO(3) at a pivot tie (half-turns about tilted axes)
        # the two candidate branches differ to first order, so only on-manifold directions have one
        # derivative there. Arbitrary directions off SO(3) are checked at random matrices (test_grads).
        grad_inputs=_unit,
        grad_fn=lambda m, u: outer(m.matrix_to_quaternion(m.quaternion_to_matrix(u))),
    ),
    Op("standardize_quaternion", _q, oracle_standardize, canonical=True),
    Op("normalize_quaternion", _q, oracle_normalize, unit=True),
    Op("wxyz_to_xyzw", _q, lambda q: q[..., [1, 2, 3, 0]], quaternion_args=(), scalar_first=False),
    Op("xyzw_to_wxyz", _q, lambda q: q[..., [3, 0, 1, 2]], quaternion_args=(), scalar_first=False),
    Op(
        "rotation_6d_to_matrix",
        _d6,
        oracle_rotation_6d_to_matrix,
        quaternion_args=(),
        output="matrix",
        scalar_first=False,
        degenerate=SIX_D_DEGENERATE,
    ),
    Op(
        "matrix_to_rotation_6d",
        _matrix,
        lambda m: np.concatenate([m[..., :, 0], m[..., :, 1]], axis=-1),
        quaternion_args=(),
        output="other",
        scalar_first=False,
    ),
    # pytorch3d's layout (the first two rows): the same Gram-Schmidt, stacked the other way. On a few
    # cases only, the transpose being the one difference: the generic and degenerate (zero) inputs,
    # half-turns, the dtype range and a batch shape.
    Op(
        "rotation_6d_to_matrix",
        _d6_rows,
        lambda d6: np.swapaxes(oracle_rotation_6d_to_matrix(d6), -1, -2),
        quaternion_args=(),
        output="matrix",
        scalar_first=False,
        kwargs={"layout": "rows"},
        label="rotation_6d_to_matrix[rows]",
        applies=lambda case: case.name in LAYOUT_CASES,
        variant_of="rotation_6d_to_matrix",
    ),
    Op(
        "matrix_to_rotation_6d",
        _matrix,
        lambda m: np.concatenate([m[..., 0, :], m[..., 1, :]], axis=-1),
        quaternion_args=(),
        output="other",
        scalar_first=False,
        kwargs={"layout": "rows"},
        label="matrix_to_rotation_6d[rows]",
        applies=lambda case: case.name in LAYOUT_CASES,
        variant_of="matrix_to_rotation_6d",
    ),
    # Three rows: all singular values equal (|q| R: where a library SVD backward divides by zero),
    # det < 0, and rank 2. Each is smooth, so gradients must match finite differences there too.
    *(
        Op(
            "special_procrustes",
            _procrustes_inputs(factor),
            oracle_special_procrustes,
            quaternion_args=(),
            output="matrix",
            scalar_first=False,
            label=label,
        )
        for label, factor in [
            ("special_procrustes", np.eye(3)),
            ("special_procrustes-reflection", _REFLECTION),
            ("special_procrustes-rank2", _RANK2),
        ]
    ),
    Op(
        "symmetric_matrix_to_quaternion",
        _a10,
        oracle_symmetric_matrix_to_quaternion,
        canonical=True,
        unit=True,
        up_to_sign=True,
        to_scalar_last=a10_to_scalar_last,
    ),
    Op(
        "fit_rotation",
        _fit_inputs,
        oracle_fit_rotation,
        quaternion_args=(),
        output="matrix",
        scalar_first=False,
    ),
    Op(
        "fit_rotation",
        lambda q: _fit_inputs(q)[:2],
        oracle_fit_rotation,
        quaternion_args=(),
        output="matrix",
        scalar_first=False,
        label="fit_rotation-unweighted",
    ),
]

# ---------------------------------------------------------------------------------------------------
# Rotation vector, Euler angles, quaternion algebra, interpolation and distances.


def _rotation(q: np.ndarray) -> tuple[Rotation, tuple[int, ...]]:
    """scipy rotations of float64 quaternions (w, x, y, z) of any shape, the zero quaternion being the
    identity (diffquat's documented meaning); with the batch shape to restore."""
    flat, batch = _flat(q, 1)
    zero = np.all(flat == 0, axis=-1)
    safe = np.where(zero[:, None], [1.0, 0.0, 0.0, 0.0], flat)
    return Rotation.from_quat(safe if len(flat) else [1.0, 0, 0, 0], scalar_first=True), batch


def _batched(fn: Callable[[Rotation], np.ndarray], q: np.ndarray, trailing: tuple[int, ...]) -> np.ndarray:
    rot, batch = _rotation(q)
    n = int(np.prod(batch))
    out = fn(rot) if n else np.zeros((0, *trailing))
    return np.asarray(out).reshape((*batch, *trailing))


def _companion(q: np.ndarray, seed: int) -> np.ndarray:
    """Uniform unit quaternions (scipy's sampler) with the batch shape of ``q``."""
    batch = q.shape[:-1]
    n = int(np.prod(batch))
    return uniform_quaternions(n, seed).reshape(q.shape) if n else np.zeros(q.shape)


def _rotvec(q: np.ndarray) -> tuple[np.ndarray, ...]:
    return (_batched(lambda r: r.as_rotvec(), oracle_standardize(q), (3,)),)


def oracle_quaternion_to_axis_angle(q: np.ndarray) -> np.ndarray:
    # scipy flips where w < 0; diffquat's documented rule is the canonical sign (which also decides
    # w = 0, where scipy keeps the input's sign): the vector of the canonical quaternion.
    return _rotvec(q)[0]


def oracle_axis_angle_to_quaternion(v: np.ndarray) -> np.ndarray:
    flat, batch = _flat(v, 1)
    out = Rotation.from_rotvec(flat).as_quat(scalar_first=True) if len(flat) else np.zeros((0, 4))
    return out.reshape((*batch, 4))


def oracle_axis_angle_to_matrix(v: np.ndarray) -> np.ndarray:
    return oracle_quaternion_to_matrix(oracle_axis_angle_to_quaternion(v))


def oracle_matrix_to_axis_angle(matrix: np.ndarray) -> np.ndarray:
    return _rotvec(oracle_matrix_to_quaternion(matrix))[0]


def _euler(convention: str) -> Callable[[np.ndarray], tuple[np.ndarray, ...]]:
    def angles(q: np.ndarray) -> tuple[np.ndarray, ...]:
        return (oracle_quaternion_to_euler(q, convention),)

    return angles


def oracle_quaternion_to_euler(q: np.ndarray, convention: str) -> np.ndarray:
    return _batched(lambda r: r.as_euler(convention, suppress_warnings=True), q, (3,))


def oracle_euler_to_quaternion(angles: np.ndarray, convention: str) -> np.ndarray:
    flat, batch = _flat(angles, 1)
    out = Rotation.from_euler(convention, flat).as_quat(scalar_first=True) if len(flat) else np.zeros((0, 4))
    return out.reshape((*batch, 4))


def _norm(q: np.ndarray) -> np.ndarray:
    return np.linalg.norm(q, axis=-1, keepdims=True)


def oracle_multiply(p: np.ndarray, q: np.ndarray) -> np.ndarray:
    # scipy composes unit quaternions (R(p) * R(q), sign as the Hamilton product); the norms multiply.
    rp, rq = _rotation(p)[0], _rotation(q)[0]
    unit = (rp * rq).as_quat(scalar_first=True) if p.size else np.zeros((0, 4))
    return unit.reshape(p.shape) * _norm(p) * _norm(q)


def oracle_conjugate(q: np.ndarray) -> np.ndarray:
    return _batched(lambda r: r.inv().as_quat(scalar_first=True), q, (4,)) * _norm(q)


def oracle_invert(q: np.ndarray) -> np.ndarray:
    norm = _norm(q)  # documented: zero -> zero
    return _batched(lambda r: r.inv().as_quat(scalar_first=True), q, (4,)) / np.where(norm > 0, norm, np.inf)


def _vectors(q: np.ndarray) -> np.ndarray:
    return np.random.default_rng(12).normal(size=(*q.shape[:-1], 3))


def oracle_apply(q: np.ndarray, v: np.ndarray) -> np.ndarray:
    rot = _rotation(q)[0]
    return rot.apply(np.array(v).reshape(-1, 3)).reshape(v.shape) if v.size else np.zeros(v.shape)


def _pair(q: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(p, p q): the rotation between the two is the case's own quaternion, so the identity case gives
    q = +-p, the half-turns antipodal rotations, and so on."""
    p = _companion(q, seed=11)
    return p, hamilton(p, q)


def hamilton(p: np.ndarray, q: np.ndarray) -> np.ndarray:
    """Hamilton product, written out (i*i = -1), float64."""
    pw, px, py, pz = np.moveaxis(p, -1, 0)
    qw, qx, qy, qz = np.moveaxis(q, -1, 0)
    return np.stack(
        [
            pw * qw - px * qx - py * qy - pz * qz,
            pw * qx + px * qw + py * qz - pz * qy,
            pw * qy - px * qz + py * qw + pz * qx,
            pw * qz + px * qy - py * qx + pz * qw,
        ],
        axis=-1,
    )


def _slerp_inputs(q: np.ndarray) -> tuple[np.ndarray, ...]:
    t = np.random.default_rng(13).uniform(0.1, 0.9, size=q.shape[:-1])
    return (*_pair(q), t)


def oracle_slerp(p: np.ndarray, q: np.ndarray, t: np.ndarray) -> np.ndarray:
    rp, rq = _rotation(p)[0], _rotation(q)[0]
    n = int(np.prod(t.shape))
    out = [Slerp([0.0, 1.0], Rotation.concatenate([rp[i], rq[i]]))(t.reshape(-1)[i]) for i in range(n)]
    quats = np.array([r.as_quat(scalar_first=True) for r in out]).reshape((*t.shape, 4))
    return quats


def oracle_quaternion_distance(p: np.ndarray, q: np.ndarray) -> np.ndarray:
    rp, rq = _rotation(p)[0], _rotation(q)[0]
    return (rp.inv() * rq).magnitude().reshape(p.shape[:-1]) if p.size else np.zeros(p.shape[:-1])


def oracle_matrix_distance(m1: np.ndarray, m2: np.ndarray) -> np.ndarray:
    return oracle_quaternion_distance(oracle_matrix_to_quaternion(m1), oracle_matrix_to_quaternion(m2))


def _except(*names: str) -> Callable[[Case], bool]:
    return lambda case: case.differentiable and case.name not in names


# The rotation vector jumps to its antipode where the angle crosses pi (w = 0), so log-type maps are
# differentiable everywhere except there: finite differences must agree everywhere else, and the
# gradient must be finite at the jump. Near half-turns (w down to 5e-9) the finite-difference step
# (1e-6) itself crosses the jump, so those are checked for finiteness only too; gimbal_lock holds exact
# half-turns. The same holds for slerp between antipodal rotations (two shortest arcs).
AT_HALF_TURNS = ("half_turns", "near_half_turns", "gimbal_lock")
# A distance has a kink where it is 0 (like a norm) and where it is pi: cases whose two rotations are
# equal, antipodal or within the finite-difference step of either are checked for finiteness only.
AT_DISTANCE_KINKS = ("identity", "near_identity", *AT_HALF_TURNS)
# Euler angles are ill-conditioned near a gimbal lock: a rotation 1e-8 away from one moves the first
# and third angles by O(1), so comparing them with scipy across dtypes is meaningless there. Angle
# outputs are checked on generic rotations and at exact locks (gimbal_lock), whose round trip through
# every convention is tested separately (tests/test_geometry.py) on every case.
EULER_ILL_CONDITIONED = ("half_turns", "near_half_turns", "near_identity")
# One row per function, together covering intrinsic and extrinsic, Tait-Bryan and proper sequences
# (all 24 conventions are compared with scipy in tests/test_geometry.py).
EULER_ROWS = {
    "euler_angles_to_matrix": "XYZ",
    "matrix_to_euler_angles": "ZXZ",
    "euler_angles_to_quaternion": "zyx",
    "quaternion_to_euler_angles": "xzx",
}


def _euler_ops() -> list[Op]:
    def smooth_at(conv: str) -> Callable[[Case], bool]:
        # The angles jump at a lock; for proper sequences (e.g. ZXZ) the identity is one.
        return _except("gimbal_lock", "identity") if conv[0] == conv[2] else _except("gimbal_lock")

    def well_conditioned(case: Case) -> bool:
        return case.name not in EULER_ILL_CONDITIONED

    def row(name: str, inputs: Callable[..., Any], oracle: Callable[..., np.ndarray], **kw: Any) -> Op:
        conv = EULER_ROWS[name]
        return Op(name, inputs, oracle, kwargs={"convention": conv}, label=f"{name}[{conv}]", **kw)

    to_matrix, from_matrix = EULER_ROWS["euler_angles_to_matrix"], EULER_ROWS["matrix_to_euler_angles"]
    to_q, from_q = EULER_ROWS["euler_angles_to_quaternion"], EULER_ROWS["quaternion_to_euler_angles"]
    return [
        row(
            "euler_angles_to_matrix",
            _euler(to_matrix),
            lambda a: oracle_quaternion_to_matrix(oracle_euler_to_quaternion(a, to_matrix)),
            quaternion_args=(),
            output="matrix",
            scalar_first=False,
        ),
        row(
            "matrix_to_euler_angles",
            _matrix,
            lambda m: oracle_quaternion_to_euler(oracle_matrix_to_quaternion(m), from_matrix),
            quaternion_args=(),
            output="other",
            scalar_first=False,
            applies=well_conditioned,
            smooth_at=smooth_at(from_matrix),
            periodic=True,
        ),
        row(
            "euler_angles_to_quaternion",
            _euler(to_q),
            lambda a: oracle_euler_to_quaternion(a, to_q),
            quaternion_args=(),
            unit=True,
        ),
        row(
            "quaternion_to_euler_angles",
            _q,
            lambda q: oracle_quaternion_to_euler(q, from_q),
            output="other",
            applies=well_conditioned,
            smooth_at=smooth_at(from_q),
            periodic=True,
        ),
    ]


OPS += [
    Op("axis_angle_to_quaternion", _rotvec, oracle_axis_angle_to_quaternion, quaternion_args=(), unit=True),
    Op(
        "quaternion_to_axis_angle",
        _q,
        oracle_quaternion_to_axis_angle,
        output="other",
        smooth_at=_except(*AT_HALF_TURNS),
    ),
    Op(
        "axis_angle_to_matrix",
        _rotvec,
        oracle_axis_angle_to_matrix,
        quaternion_args=(),
        output="matrix",
        scalar_first=False,
    ),
    Op(
        "matrix_to_axis_angle",
        _matrix,
        oracle_matrix_to_axis_angle,
        quaternion_args=(),
        output="other",
        scalar_first=False,
        # At exact half-turns rounding legitimately decides the canonical sign, so v or -v (the same
        # rotation there); elsewhere -v is another rotation, which the round trip R -> v -> R rules out.
        up_to_sign=True,
        smooth_at=_except(*AT_HALF_TURNS),
    ),
    *_euler_ops(),
    Op(
        "quaternion_multiply",
        lambda q: (_companion(q, seed=11), q),
        oracle_multiply,
        quaternion_args=(0, 1),
        relative=True,
    ),
    Op("quaternion_conjugate", _q, oracle_conjugate, relative=True),
    Op(
        "quaternion_invert",
        _q,
        oracle_invert,
        relative=True,
        # d(conj(q)/|q|^2)/dq is of size 1/|q|^2: 1e8 at the float16 norm 1e-4, beyond float16's 65504.
        finite_gradient=lambda case, dtype: not (case.name == "norms" and dtype == "float16"),
    ),
    Op("quaternion_apply", lambda q: (q, _vectors(q)), oracle_apply, output="other"),
    Op(
        "quaternion_slerp",
        _slerp_inputs,
        oracle_slerp,
        quaternion_args=(0, 1),
        unit=True,
        up_to_sign=True,  # scipy's Slerp returns the rotation, not a particular sign of its quaternion
        # Between rotations a half-turn apart there are two shortest arcs and rounding picks one: that
        # is checked on its own (tests/test_geometry.py), with its gradient's finiteness.
        applies=lambda case: case.name not in AT_HALF_TURNS,
    ),
    Op(
        "quaternion_geodesic_distance",
        _pair,
        oracle_quaternion_distance,
        quaternion_args=(0, 1),
        output="other",
        smooth_at=_except(*AT_DISTANCE_KINKS),
    ),
    Op(
        "matrix_geodesic_distance",
        lambda q: tuple(oracle_quaternion_to_matrix(x) for x in _pair(q)),
        oracle_matrix_distance,
        quaternion_args=(),
        output="other",
        scalar_first=False,
        smooth_at=_except(*AT_DISTANCE_KINKS),
    ),
]

# ---------------------------------------------------------------------------------------------------
# SO(3) as a Lie group (diffquat._lie). Rotation vectors come from the case quaternion (``_rotvec``), so
# that every row reaches 0, 1e-4 ... 1e-10, pi - 1e-1 ... pi - 1e-8 and exactly pi about the 26 axes.
# Each function with a ``side`` has one row, on the left (the keyword given); the right side, the
# default, is checked in tests/test_lie.py (values, identities and derivatives).


def hat(v: np.ndarray) -> np.ndarray:
    """The skew matrix of each vector, written out: hat(v) u = v x u."""
    x, y, z = np.moveaxis(np.asarray(v, dtype=np.float64), -1, 0)
    zero = np.zeros_like(x)
    rows = [np.stack(r, axis=-1) for r in ([zero, -z, y], [z, zero, -x], [-y, x, zero])]
    return np.stack(rows, axis=-2)


def oracle_so3_vee(m: np.ndarray) -> np.ndarray:
    skew = 0.5 * (m - np.swapaxes(m, -1, -2))
    return np.stack([skew[..., 2, 1], skew[..., 0, 2], skew[..., 1, 0]], axis=-1)


def oracle_left_jacobian(v: np.ndarray) -> np.ndarray:
    """J_l(v) = sum_k hat(v)^k / (k + 1)!, the definition, summed in float64 matrix powers: independent
    of the closed form and of its series in |v|^2. 40 terms: the table's rotation vectors have
    |v| <= pi, where the terms fall below pi^40 / 41! ~ 1e-30, and the positive sum of their sizes,
    (e^pi - 1) / pi ~ 7, bounds the rounding by ~1e-15 (scipy's expm of the block matrix
    [[hat(v), I], [0, 0]] agrees; it took seconds a call, a Pade step per matrix)."""
    flat, batch = _flat(v, 1)
    return phi_series(hat(flat), 40).reshape((*batch, 3, 3))


def phi_series(a: np.ndarray, terms: int) -> np.ndarray:
    """sum_{n <= terms} a^n / (n + 1)! of square matrices ``a`` (..., k, k), in float64 powers: the
    Jacobian of the exponential of the Lie algebra element whose adjoint (or hat) is ``a``."""
    power = np.broadcast_to(np.eye(a.shape[-1]), a.shape).copy()
    out = power.copy()
    for k in range(1, terms + 1):
        power = power @ a / (k + 1)
        out = out + power
    return out


def oracle_right_jacobian(v: np.ndarray) -> np.ndarray:
    return oracle_left_jacobian(-v)


def oracle_left_jacobian_inverse(v: np.ndarray) -> np.ndarray:
    # J_l is well conditioned for |v| <= pi (singular values 1 and 2 sin(t/2) / t >= 2 / pi)
    return np.linalg.inv(oracle_left_jacobian(v))


def oracle_right_jacobian_inverse(v: np.ndarray) -> np.ndarray:
    return np.linalg.inv(oracle_right_jacobian(v))


def _companion_matrix(q: np.ndarray) -> np.ndarray:
    return oracle_quaternion_to_matrix(_companion(q, seed=11))


def _so3_plus_inputs(q: np.ndarray) -> tuple[np.ndarray, ...]:
    return _companion_matrix(q), _rotvec(q)[0]


def oracle_so3_plus_left(m: np.ndarray, v: np.ndarray) -> np.ndarray:
    return oracle_axis_angle_to_matrix(v) @ m


def _so3_minus_left_inputs(q: np.ndarray) -> tuple[np.ndarray, ...]:
    """(R(q p), R(p)): R1 R2^T is R(q), the case's own rotation (half-turns apart, equal, ...)."""
    p = _companion(q, seed=11)
    return oracle_quaternion_to_matrix(hamilton(q, p)), oracle_quaternion_to_matrix(p)


def oracle_so3_minus_left(m1: np.ndarray, m2: np.ndarray) -> np.ndarray:
    return oracle_matrix_to_axis_angle(m1 @ np.swapaxes(m2, -1, -2))


def _quaternion_plus_inputs(q: np.ndarray) -> tuple[np.ndarray, ...]:
    """(|q| p, rotation vector of q): the norms case reaches the quaternion argument, the zero case
    gives the zero quaternion (the identity)."""
    return _companion(q, seed=11) * _norm(q), _rotvec(q)[0]


def oracle_quaternion_plus_left(p: np.ndarray, v: np.ndarray) -> np.ndarray:
    # scipy's exponential (w = cos(t/2) >= 0 for t <= pi, as diffquat's), its normalisation of p (the
    # zero quaternion as the identity: _rotation), and the Hamilton product written out: the sign of
    # the product, which diffquat keeps.
    unit = _batched(lambda r: r.as_quat(scalar_first=True), p, (4,))
    return hamilton(oracle_axis_angle_to_quaternion(v), unit)


def _quaternion_minus_left_inputs(q: np.ndarray) -> tuple[np.ndarray, ...]:
    p = _companion(q, seed=11)
    return hamilton(q, p), p


def oracle_quaternion_minus_left(q1: np.ndarray, q2: np.ndarray) -> np.ndarray:
    r1, r2 = _rotation(q1)[0], _rotation(q2)[0]
    relative = (r1 * r2.inv()).as_quat(scalar_first=True) if q1.size else np.zeros(q1.shape)
    return oracle_quaternion_to_axis_angle(relative.reshape(q1.shape))


def _lie_ops() -> list[Op]:
    def vectors(name: str, inputs: Callable[..., Any], oracle: Callable[..., np.ndarray], **kw: Any) -> Op:
        return Op(name, inputs, oracle, quaternion_args=(), output="other", scalar_first=False, **kw)

    left = {"side": "left"}
    return [
        vectors("so3_hat", lambda q: (_rotvec(q)[0] * _norm(q),), hat, relative=True),
        # Absolute errors: near half-turns the skew part (sin t) is tiny beside the matrix entries.
        vectors("so3_vee", _matrix, oracle_so3_vee),
        Op(
            "so3_exp",
            _rotvec,
            oracle_axis_angle_to_matrix,
            quaternion_args=(),
            output="matrix",
            scalar_first=False,
            variant_of="axis_angle_to_matrix",  # the same core function
        ),
        # As matrix_to_axis_angle: v or -v at exact half-turns, where log jumps.
        vectors(
            "so3_log",
            _matrix,
            oracle_matrix_to_axis_angle,
            up_to_sign=True,
            smooth_at=_except(*AT_HALF_TURNS),
            variant_of="matrix_to_axis_angle",  # the same core function
        ),
        vectors("so3_left_jacobian", _rotvec, oracle_left_jacobian),
        vectors("so3_right_jacobian", _rotvec, oracle_right_jacobian),
        vectors("so3_left_jacobian_inverse", _rotvec, oracle_left_jacobian_inverse),
        vectors("so3_right_jacobian_inverse", _rotvec, oracle_right_jacobian_inverse),
        Op(
            "so3_plus",
            _so3_plus_inputs,
            oracle_so3_plus_left,
            quaternion_args=(),
            output="matrix",
            scalar_first=False,
            kwargs=left,
            label="so3_plus[left]",
        ),
        vectors(
            "so3_minus",
            _so3_minus_left_inputs,
            oracle_so3_minus_left,
            kwargs=left,
            label="so3_minus[left]",
            up_to_sign=True,
            smooth_at=_except(*AT_HALF_TURNS),
        ),
        Op(
            "quaternion_plus",
            _quaternion_plus_inputs,
            oracle_quaternion_plus_left,
            unit=True,
            kwargs=left,
            label="quaternion_plus[left]",
        ),
        Op(
            "quaternion_minus",
            _quaternion_minus_left_inputs,
            oracle_quaternion_minus_left,
            quaternion_args=(0, 1),
            output="other",
            kwargs=left,
            label="quaternion_minus[left]",
            up_to_sign=True,
            smooth_at=_except(*AT_HALF_TURNS),
        ),
    ]


OPS += _lie_ops()


# ---------------------------------------------------------------------------------------------------
# SE(3). Twists come from the cases' rotation vectors (|phi| from 0 to pi, the half-turns about 26
# axes, near 0 down to 1e-9) with a translation part of size ~1 beside them (the issue's rho =
# (0.3, -0.7, 0.5) plus a companion's); poses from the cases' rotations with translations of size ~2.
# The oracles are the definitions in float64: the matrix exponential (scipy's expm of the 4x4 twist),
# the series sum_n ad(xi)^n / (n + 1)!, general matrix products and inverses.

_RHO = np.array([0.3, -0.7, 0.5])


def _translation(q: np.ndarray, seed: int, size: float = 2.0) -> np.ndarray:
    return size * _companion(q, seed)[..., 1:]


def _twist(q: np.ndarray) -> np.ndarray:
    return np.concatenate([_RHO + _translation(q, 21, 1.0), _rotvec(q)[0]], axis=-1)


def se3_matrix(rotation: np.ndarray, translation: np.ndarray) -> np.ndarray:
    """[[R, t], [0, 1]], written out (float64)."""
    rotation, translation = np.asarray(rotation, np.float64), np.asarray(translation, np.float64)
    batch = np.broadcast_shapes(rotation.shape[:-2], translation.shape[:-1])
    out = np.zeros((*batch, 4, 4))
    out[..., :3, :3] = rotation
    out[..., :3, 3] = translation
    out[..., 3, 3] = 1.0
    return out


def _pose(q: np.ndarray, seed: int = 22) -> np.ndarray:
    return se3_matrix(oracle_quaternion_to_matrix(q), _translation(q, seed))


def _xyz_xyzw(t: np.ndarray, q: np.ndarray) -> tuple[np.ndarray]:
    return (np.concatenate([t, q[..., 1:], q[..., :1]], axis=-1),)


def wxyz_to_xyzw_of(q: np.ndarray) -> np.ndarray:
    return np.concatenate([q[..., 1:], q[..., :1]], axis=-1)


def se3_hat_of(xi: np.ndarray) -> np.ndarray:
    out = np.zeros((*xi.shape[:-1], 4, 4))
    out[..., :3, :3] = hat(xi[..., 3:])
    out[..., :3, 3] = xi[..., :3]
    return out


def oracle_se3_exp(xi: np.ndarray) -> np.ndarray:
    flat, batch = _flat(xi, 1)
    out = scipy.linalg.expm(se3_hat_of(flat)) if len(flat) else np.zeros((0, 4, 4))
    return out.reshape((*batch, 4, 4))


def se3_ad_of(xi: np.ndarray) -> np.ndarray:
    out = np.zeros((*xi.shape[:-1], 6, 6))
    out[..., :3, :3] = out[..., 3:, 3:] = hat(xi[..., 3:])
    out[..., :3, 3:] = hat(xi[..., :3])
    return out


def oracle_se3_left_jacobian(xi: np.ndarray) -> np.ndarray:
    """sum_n ad(xi)^n / (n + 1)!, the definition, in float64 matrix powers (60 terms: |ad| <= |phi| +
    |rho| < 6 here, where the terms fall below 6^60 / 61! ~ 1e-37 and their sizes sum to < e^6 / 6,
    which bounds the rounding by ~1e-14)."""
    flat, batch = _flat(xi, 1)
    return phi_series(se3_ad_of(flat), 60).reshape((*batch, 6, 6))


def oracle_se3_log(matrix: np.ndarray) -> np.ndarray:
    """(J_l(phi)^-1 t, phi), phi = log(R) with diffquat's sign rule at pi (the canonical quaternion's),
    J_l by its series: the inverse of the definition of exp, not its closed form."""
    phi = oracle_matrix_to_axis_angle(matrix[..., :3, :3])
    rho = np.linalg.solve(oracle_left_jacobian(phi), matrix[..., :3, 3:])[..., 0]
    return np.concatenate([rho, phi], axis=-1)


def se3_log_other_branch(xi: np.ndarray) -> np.ndarray:
    """The other twist of the same pose at a rotation of pi: (J_l(-phi)^-1 J_l(phi) rho, -phi)."""
    rho, phi = xi[..., :3], xi[..., 3:]
    t = np.einsum("...ij,...j->...i", oracle_left_jacobian(phi), rho)
    return np.concatenate([np.linalg.solve(oracle_left_jacobian(-phi), t[..., None])[..., 0], -phi], axis=-1)


def oracle_se3_adjoint(m: np.ndarray) -> np.ndarray:
    """[[R, hat(t) R], [0, R]], written out."""
    r = m[..., :3, :3]
    out = np.zeros((*m.shape[:-2], 6, 6))
    out[..., :3, :3] = out[..., 3:, 3:] = r
    out[..., :3, 3:] = hat(m[..., :3, 3]) @ r
    return out


def _se3_pair(q: np.ndarray) -> tuple[np.ndarray, ...]:
    """(E T2, T2) with E the case's rotation and a translation, T2 a companion pose: the relative pose
    T1 T2^-1 (the left side's) is E, so the cases' angles (0, pi, near both) reach the log."""
    return _pose(q, 23) @ _pose(_companion(q, seed=11), 24), _pose(_companion(q, seed=11), 24)


def _se3_interpolate_inputs(q: np.ndarray) -> tuple[np.ndarray, ...]:
    """(T1, T1 E, t): the relative pose T1^-1 T2 (the screw's) is the case's E."""
    t1 = _pose(_companion(q, seed=11), 24)
    t = np.random.default_rng(13).uniform(-0.2, 1.2, size=q.shape[:-1])
    return t1, t1 @ _pose(q, 23), t


def oracle_se3_interpolate(t1: np.ndarray, t2: np.ndarray, t: np.ndarray) -> np.ndarray:
    return t1 @ oracle_se3_exp(t[..., None] * oracle_se3_log(np.linalg.inv(t1) @ t2))


# The SE(3) rows at zero translation: the table's tolerance for them (VALUE_TOL: 2e-6 in float32, 17
# ulp; 1e-12 in float64, where the float64 oracles (scipy's expm, a solve) round too), in ulps.
ZERO_TRANSLATION_ULPS = 16.0


def _se3_ops() -> list[Op]:
    # Errors relative to each element's largest entry: translations (~2, up to ~10 applied to points)
    # sit beside rotation entries <= 1, and a rounding error is an ulp of the largest.
    def poses(name: str, inputs: Callable[..., Any], oracle: Callable[..., np.ndarray], **kw: Any) -> Op:
        if inputs in (twist, pose):  # one pose or twist: its pure rotations are degenerate
            label = kw.get("label", name)
            kw = {"degenerate": zero_translation(label, inputs, ZERO_TRANSLATION_ULPS), **kw}
        return Op(
            name, inputs, oracle, quaternion_args=(), output="other", scalar_first=False, relative=True, **kw
        )

    twist = lambda q: (_twist(q),)  # noqa: E731
    pose = lambda q: (_pose(q),)  # noqa: E731
    left = {"side": "left"}
    # log jumps between two twists of one pose at a half-turn (phi's sign), differentiable elsewhere
    log_like = {
        "up_to_sign": True,
        "other_branch": se3_log_other_branch,
        "smooth_at": _except(*AT_HALF_TURNS),
    }
    return [
        poses(
            "se3_from_rotation_translation",
            lambda q: (oracle_quaternion_to_matrix(q), _translation(q, 22)),
            se3_matrix,
        ),
        poses("se3_compose", lambda q: (_pose(q), _pose(_companion(q, seed=11), 24)), lambda a, b: a @ b),
        poses("se3_inverse", pose, np.linalg.inv),
        poses(
            "se3_apply",
            lambda q: (_pose(q), 3.0 * _vectors(q)),
            lambda m, p: np.einsum("...ij,...j->...i", m[..., :3, :3], p) + m[..., :3, 3],
        ),
        poses("se3_hat", twist, se3_hat_of),
        poses("se3_vee", pose, lambda m: np.concatenate([m[..., :3, 3], oracle_so3_vee(m[..., :3, :3])], -1)),
        poses("se3_exp", twist, oracle_se3_exp),
        poses("se3_log", pose, oracle_se3_log, **log_like),
        poses("se3_adjoint", pose, oracle_se3_adjoint),
        poses("se3_ad", twist, se3_ad_of),
        poses("se3_left_jacobian", twist, oracle_se3_left_jacobian),
        # J_r(xi) is computed as J_l(-xi): the compile-heavy checks run on the left rows
        poses(
            "se3_right_jacobian",
            twist,
            lambda xi: oracle_se3_left_jacobian(-xi),
            variant_of="se3_left_jacobian",
            variant_inputs=lambda xi: (-xi,),
        ),
        poses("se3_left_jacobian_inverse", twist, lambda xi: np.linalg.inv(oracle_se3_left_jacobian(xi))),
        poses(
            "se3_right_jacobian_inverse",
            twist,
            lambda xi: np.linalg.inv(oracle_se3_left_jacobian(-xi)),
            variant_of="se3_left_jacobian_inverse",
            variant_inputs=lambda xi: (-xi,),
        ),
        poses(
            "se3_plus",
            lambda q: (_pose(_companion(q, seed=11), 24), _twist(q)),
            lambda m, d: oracle_se3_exp(d) @ m,
            kwargs=left,
            label="se3_plus[left]",
        ),
        poses(
            "se3_minus",
            _se3_pair,
            lambda a, b: oracle_se3_log(a @ np.linalg.inv(b)),
            kwargs=left,
            label="se3_minus[left]",
            **log_like,
        ),
        # One non-default layout per direction (the rows' keyword); every layout's round trip and the
        # orders themselves are checked in tests/test_se3.py.
        poses(
            "pose_to_matrix",
            lambda q: _xyz_xyzw(_translation(q, 22), q),
            lambda pose: se3_matrix(
                oracle_quaternion_to_matrix(np.concatenate([pose[..., 6:], pose[..., 3:6]], -1)),
                pose[..., :3],
            ),
            kwargs={"layout": "xyz_xyzw"},
            label="pose_to_matrix[xyz_xyzw]",
            # derivatives at unit norm: at the norms case's 1e-30 they scale as 1 / |q|, beyond what
            # finite differences resolve beside the translation (the values cover every norm)
            grad_inputs=lambda q: _xyz_xyzw(_translation(q, 22), oracle_normalize(q)),
        ),
        poses(
            "matrix_to_pose",
            pose,
            lambda m: np.concatenate(
                [wxyz_to_xyzw_of(oracle_matrix_to_quaternion(m[..., :3, :3])), m[..., :3, 3]], axis=-1
            ),
            kwargs={"layout": "xyzw_xyz"},
            label="matrix_to_pose[xyzw_xyz]",
            # the quaternion's canonical sign is rounding's choice at w = 0 (half-turns)
            up_to_sign=True,
            other_branch=lambda out: np.concatenate([-out[..., :4], out[..., 4:]], axis=-1),
            smooth_at=_except(*AT_HALF_TURNS),
        ),
        # Between poses a half-turn apart there are two screws, and rounding picks one (within 5e-9 of
        # pi, as near_half_turns are, already float32's rounding of the matrix): checked on its own
        # (tests/test_se3.py).
        poses(
            "se3_interpolate",
            _se3_interpolate_inputs,
            oracle_se3_interpolate,
            applies=lambda case: case.name not in AT_HALF_TURNS,
        ),
    ]


OPS += _se3_ops()


# ---------------------------------------------------------------------------------------------------
# The matrix Fisher distribution and the Bingham NLL of the 10D head. The oracle of the normaliser is
# the one-dimensional Bessel integral (T. Lee, "Bayesian attitude estimation with the matrix Fisher
# distribution on SO(3)", IEEE TAC 2018; Mohlin et al., NeurIPS 2020) by scipy's adaptive quadrature,
# with the peak exp(s1 + s2 + s3) factored out and break points at the widths of the integrand's
# features (1/l near each end); where the singular values are small, so that log c ~ |s|^2 / 6 would
# cancel in float64, mpmath at 30 digits. Against mpmath over [1e-3, 1e5]^3 (tests/test_fisher.py)
# the quadrature is within 1e-13. diffquat computes it another way (Laplace inversion, power series).


def proper_singular_values(matrix: np.ndarray) -> np.ndarray:
    """``(..., 3)``: ``s1 >= s2 >= |s3|`` with ``F = U diag(s) V^T``, U and V rotations (s3 < 0 where
    det F < 0)."""
    u, s, vh = np.linalg.svd(matrix)
    s = s.copy()
    s[..., 2] *= np.where(np.linalg.det(u) * np.linalg.det(vh) < 0, -1.0, 1.0)
    return s


@functools.cache
def oracle_log_c(s1: float, s2: float, s3: float) -> float:
    """log c for proper singular values s1 >= s2 >= |s3|, float64 (see above)."""
    if abs(s1) + abs(s2) + abs(s3) < 0.05:
        with mpmath.workdps(30):
            a, b, c = (mpmath.mpf(x) for x in (s1, s2, s3))

            def excess(u: Any) -> Any:  # the integrand less its value 1/2 at S = 0
                i1 = mpmath.besseli(0, (a - b) * (1 - u) / 2)
                return i1 * mpmath.besseli(0, (a + b) * (1 + u) / 2) * mpmath.exp(c * u) / 2 - 0.5

            return float(mpmath.log1p(mpmath.quad(excess, [-1, 1])))
    # c = e^{s1+s2+s3} J with J = int_0^1 e^{-l2 v} I0e(l1 (1 - v)/2) I0e((l3 - l2) v/2) dv, where
    # l1 = 2 (s2 + s3) <= l2 = 2 (s1 + s3) <= l3 = 2 (s1 + s2) (the substitution v = (1 - u)/2 in the
    # form with k = 1; I0e(x) = e^{-x} I0(x))
    l1, l2, l3 = 2 * (s2 + s3), 2 * (s1 + s3), 2 * (s1 + s2)

    def integrand(v: float) -> float:
        return float(np.exp(-l2 * v) * special.i0e(l1 * (1 - v) / 2) * special.i0e((l3 - l2) * v / 2))

    points = {k / w for w in (l2, l3 - l2) for k in (1.0, 10.0, 100.0) if w > 0 and 1e-300 < k / w < 1}
    points |= {1 - k / l1 for k in (1.0, 10.0, 100.0) if l1 > 0 and 1e-15 < k / l1 < 1}
    with warnings.catch_warnings():  # at 1e20 the last digits are rounding: quad says so, harmlessly
        warnings.simplefilter("ignore", integrate.IntegrationWarning)
        j = integrate.quad(integrand, 0, 1, points=sorted(points) or None, epsabs=0, epsrel=1e-13, limit=500)
    return float(s1 + s2 + s3 + np.log(j[0]))


@functools.cache
def reference_log_c(s1: float, s2: float, s3: float) -> float:
    """log c for proper singular values ``s1 >= s2 >= |s3|`` by mpmath (20 digits) from the 1D Bessel
    integral (T. Lee, IEEE TAC 2018, eq. (21); Mohlin et al., NeurIPS 2020, eq. (8))

        c = int_{-1}^{1} 1/2 I0((s1 - s2)(1 - u)/2) I0((s1 + s2)(1 + u)/2) exp(s3 u) du,

    with the peak exp(s1 + s2 + s3) taken out and v = 1 - u: the integrand is then
    ``1/2 I0e(a (2 - v)) I0e(b v) exp(-(s2 + s3) v)`` for ``a = (s1 + s2)/2``, ``b = (s1 - s2)/2``, whose
    features near v = 0 have widths 1/(s2 + s3) and 1/b and near v = 2 the width 1/a: mpmath's
    tanh-sinh rule is given break points there. (Derivation: with t = w^2 + z^2, uniform on [0, 1] for
    a uniform unit quaternion, and the angles in the (w, z) and (x, y) planes uniform,
    ``tr(S R) = s3 (2t - 1) + t (s1 + s2) cos 2 phi + (1 - t)(s1 - s2) cos 2 psi``; the angle averages
    are I0. test_reference_matches_monte_carlo checks the formula itself.)"""
    with mpmath.workdps(20):
        s1m, s2m, s3m = (mpmath.mpf(x) for x in (s1, s2, s3))
        a, b, r = (s1m + s2m) / 2, (s1m - s2m) / 2, s2m + s3m

        def integrand(v: Any) -> Any:
            x1, x2 = a * (2 - v), b * v
            return mpmath.besseli(0, x1) * mpmath.besseli(0, x2) * mpmath.exp(-x1 - x2 - r * v) / 2

        points = {mpmath.mpf(0), mpmath.mpf(1), mpmath.mpf(2)}
        for width, end in ((r, 0), (b, 0), (a, 2)):
            for k in (1, 10, 100):
                if width > 0 and k / width < 1:
                    points.add(abs(end - k / width))
        j = mpmath.quad(integrand, sorted(points))
        # log c = s1 + s2 + s3 + log J, summed in 20 digits: at small s the two nearly cancel
        return float(s1m + s2m + s3m + mpmath.log(j))


def _each(values: np.ndarray, fn: Callable[..., float]) -> np.ndarray:
    flat = values.reshape(-1, values.shape[-1])
    return np.array([fn(*(float(x) for x in row)) for row in flat]).reshape(values.shape[:-1])


def oracle_matrix_fisher_log_normalizer(matrix: np.ndarray) -> np.ndarray:
    return _each(proper_singular_values(matrix), oracle_log_c)


def oracle_matrix_fisher_nll(matrix: np.ndarray, rotation: np.ndarray) -> np.ndarray:
    return oracle_matrix_fisher_log_normalizer(matrix) - np.sum(matrix * rotation, axis=(-2, -1))


def bingham_log_normalizer_by_matrix_fisher(a: np.ndarray) -> np.ndarray:
    """log E_q[exp(-q^T A q)] through the matrix Fisher normaliser: with b = eig(-A) descending and
    b_bar their mean, ``log c_B = b_bar + log c(s)``, ``s_i = (b_0 + b_i)/2 - b_bar`` (the proper singular
    values of the F with K(F) = b_bar I - A)."""
    b = -np.linalg.eigvalsh(_sym4(a))  # descending: eigvalsh is ascending
    mean = b.mean(axis=-1, keepdims=True)
    s = (b[..., :1] + b[..., 1:]) / 2 - mean
    return mean[..., 0] + _each(s, oracle_log_c)


def oracle_bingham_nll(a: np.ndarray, q: np.ndarray) -> np.ndarray:
    batch = np.broadcast_shapes(a.shape[:-1], q.shape[:-1])
    a, q = np.broadcast_to(a, (*batch, 10)), np.broadcast_to(q, (*batch, 4))
    norm = np.linalg.norm(q, axis=-1, keepdims=True)
    u = np.where(norm > 0, q / np.where(norm > 0, norm, 1.0), [1.0, 0.0, 0.0, 0.0])
    energy = np.einsum("...a,...ab,...b->...", u, _sym4(a), u)
    return energy + bingham_log_normalizer_by_matrix_fisher(a)


# F = |q| R(q) for the log normaliser: all three singular values equal (where a library SVD derivative
# divides by zero, and the zero case gives F = 0, where E[R] = 0); for the NLL, |q| R(q) diag(2, 1, -0.5):
# distinct singular values and det < 0. Both smooth everywhere: finite differences must agree at every
# case, the zero matrix included. Errors are measured against the size of the terms (at least 1).
_FISHER_FACTOR = np.diag([2.0, 1.0, -0.5])


def _fisher_scale(matrix: np.ndarray, *rest: np.ndarray) -> np.ndarray:
    return np.maximum(2.0 * np.abs(np.linalg.svd(matrix, compute_uv=False)).sum(axis=-1), 1.0)


OPS += [
    Op(
        "matrix_fisher_log_normalizer",
        lambda q: (_scale(q)[..., None, None] * oracle_quaternion_to_matrix(q),),
        oracle_matrix_fisher_log_normalizer,
        quaternion_args=(),
        output="other",
        scalar_first=False,
        smooth_at=lambda case: True,
        error_scale=_fisher_scale,
    ),
    Op(
        "matrix_fisher_nll",
        lambda q: (
            _scale(q)[..., None, None] * (oracle_quaternion_to_matrix(q) @ _FISHER_FACTOR),
            oracle_quaternion_to_matrix(_companion(q, seed=11)),
        ),
        oracle_matrix_fisher_nll,
        quaternion_args=(),
        output="other",
        scalar_first=False,
        smooth_at=lambda case: True,
        error_scale=_fisher_scale,
    ),
    Op(
        "matrix_fisher_mode",
        _procrustes_inputs(_FISHER_FACTOR),
        oracle_special_procrustes,
        quaternion_args=(),
        output="matrix",
        scalar_first=False,
        # special_procrustes itself (one core function): the compile-heavy checks run on its rows
        variant_of="special_procrustes",
    ),
    Op(
        "bingham_nll",
        lambda q: (*_a10(q), _companion(q, seed=11)),
        oracle_bingham_nll,
        quaternion_args=(0, 1),
        output="other",
        smooth_at=lambda case: True,
        to_scalar_last=lambda x: a10_to_scalar_last(x) if x.shape[-1] == 10 else x[..., [1, 2, 3, 0]],
        error_scale=lambda a, q: np.maximum(2.0 * np.abs(a).sum(axis=-1), 1.0),
    ),
]


# ---------------------------------------------------------------------------------------------------
# Rotation averaging and symmetric objects. Each case quaternion q becomes a cluster of N = 5 samples
# R(q) P_i around its rotation (P_i fixed, 0.46-0.64 rad from the identity in five directions, so that
# no sample is the median and the geodesic means are far from the chordal one), weighted |q| w_i:
# every named case reaches the means (half-turns, near the identity, the batch shapes), "norms" spans
# the dtype's range in the weights (only their ratios matter), and "zero" gives weights that sum to
# zero, whose documented mean is the identity. The means are equivariant, mean(R P_i) = R mean(P_i),
# so every case has the same, generic, configuration.
CLUSTER = np.array(
    [[0.4, -0.1, 0.2], [-0.3, 0.5, 0.1], [0.1, 0.2, -0.6], [-0.2, -0.4, -0.1], [0.3, 0.25, 0.35]]
)
CLUSTER_WEIGHTS = np.array([1.0, 0.5, 2.0, 0.25, 1.5])
_CLUSTER_QUATERNIONS = Rotation.from_rotvec(CLUSTER).as_quat(scalar_first=True)
_CLUSTER_SIGNS = np.array([1.0, -1.0, 1.0, -1.0, 1.0])[:, None]  # quaternion_mean is sign blind


# The cases that only rotate the cluster again (equivariance: the same configuration relative to its
# samples, so the same iterations): near_half_turns and near_identity are 323 of the 528 rows of the
# concatenated cases and most of the iterative means' eager time in the suite, while half_turns and
# identity already put the mean at those rotations. The iterative means skip them; their own edge
# cases (tight and wide clusters, the median at a sample, non-unique means) are in
# tests/test_statistics.py.
ROTATED_ONLY = ("near_half_turns", "near_identity", "gimbal_lock")


def _mean_inputs(q: np.ndarray) -> tuple[np.ndarray, ...]:
    r = oracle_quaternion_to_matrix(q)[..., None, :, :] @ Rotation.from_rotvec(CLUSTER).as_matrix()
    return r, _scale(q)[..., None] * CLUSTER_WEIGHTS


def _quaternion_mean_inputs(q: np.ndarray) -> tuple[np.ndarray, ...]:
    """The samples q p_i (norm |q|, alternating signs), with the fixed weights: "zero" gives zero
    quaternions, which are the identity."""
    samples = hamilton(q[..., None, :], _CLUSTER_QUATERNIONS) * _CLUSTER_SIGNS
    return samples, np.broadcast_to(CLUSTER_WEIGHTS, samples.shape[:-1]).copy()


def _identity_where_weightless(out: np.ndarray, weights: np.ndarray, identity: np.ndarray) -> np.ndarray:
    positive = (weights.sum(-1) > 0).reshape(-1, *([1] * identity.ndim))
    return np.where(positive, out, identity)


def _sample_rotations(matrices: np.ndarray) -> tuple[Rotation, np.ndarray, tuple[int, ...]]:
    """scipy rotations (B, N) of matrices (..., N, 3, 3) (projected onto SO(3) by scipy, for the
    rounded input of 16-bit dtypes), their flattened float64 array and the batch shape."""
    flat, batch = _flat(matrices, 3)
    quats = Rotation.from_matrix(flat.reshape(-1, 3, 3)).as_quat() if flat.size else np.zeros((0, 4))
    return Rotation.from_quat(quats.reshape(*flat.shape[:2], 4)), flat, batch


def oracle_chordal_mean(matrices: np.ndarray, weights: np.ndarray) -> np.ndarray:
    """scipy's ``Rotation.mean`` (the chordal L2 mean)."""
    rotations, flat, batch = _sample_rotations(matrices)
    if not len(flat):
        return np.zeros((*batch, 3, 3))
    w = weights.reshape(len(flat), -1)
    out = rotations.mean(weights=np.where(w.sum(-1, keepdims=True) > 0, w, 1.0), axis=-1).as_matrix()
    return _identity_where_weightless(out, w, np.eye(3)).reshape(*batch, 3, 3)


_GEODESIC_ORACLE: dict[tuple[bytes, bytes, tuple[int, ...], bool], np.ndarray] = {}


def oracle_geodesic_mean(matrices: np.ndarray, weights: np.ndarray, l1: bool = False) -> np.ndarray:
    """The Karcher mean (``l1``: the geodesic median) by the textbook iterations in float64, with
    scipy's exponential and logarithm: the Riemannian gradient step ``R <- R exp(sum_i w_i v_i /
    sum_i w_i)`` (``v_i = log(R^T R_i)``), or Weiszfeld's ``R <- R exp(sum_i (w_i / t_i) v_i /
    sum_i (w_i / t_i))`` (``t_i = |v_i|``; the cluster's median is no sample), until the step is below
    1e-15 rad (the error left is at most a few times that: both contract by 0.5 or better per step
    here). Independent of diffquat's Newton iterations; checked to be stationary to 1e-13.
    Memoised: every backend and dtype asks for the same float64 inputs' mean several times."""
    arrays = (np.ascontiguousarray(matrices).tobytes(), np.ascontiguousarray(weights).tobytes())
    key = (*arrays, matrices.shape, l1)
    if key not in _GEODESIC_ORACLE:
        _GEODESIC_ORACLE[key] = _iterated_mean(matrices, weights, l1)
    return _GEODESIC_ORACLE[key].copy()


def _iterated_mean(matrices: np.ndarray, weights: np.ndarray, l1: bool) -> np.ndarray:
    rotations, flat, batch = _sample_rotations(matrices)
    if not len(flat):
        return np.zeros((*batch, 3, 3))
    w = weights.reshape(len(flat), -1)
    safe = np.where(w.sum(-1, keepdims=True) > 0, w, 1.0)
    mean = rotations.mean(weights=safe, axis=-1)
    for _ in range(1000):
        v = (Rotation.from_quat(mean.as_quat()[:, None, :]).inv() * rotations).as_rotvec()
        a = safe / np.linalg.norm(v, axis=-1) if l1 else safe
        step = np.sum(a[..., None] * v, axis=-2) / a.sum(-1, keepdims=True)
        mean = mean * Rotation.from_rotvec(step)
        if np.abs(step).max() < 1e-15:
            break
    v = (Rotation.from_quat(mean.as_quat()[:, None, :]).inv() * rotations).as_rotvec()
    t = np.linalg.norm(v, axis=-1, keepdims=True)
    residual = v / t if l1 else v
    # the unit vector of a log of length t is known to ~eps / t (tight clusters)
    bound = 1e-13 + (1e-15 / t.min() if l1 else 0.0)
    assert np.abs(np.sum(safe[..., None] * residual, axis=-2) / safe.sum(-1, keepdims=True)).max() < bound
    return _identity_where_weightless(mean.as_matrix(), w, np.eye(3)).reshape(*batch, 3, 3)


def oracle_quaternion_mean(q: np.ndarray, weights: np.ndarray) -> np.ndarray:
    """scipy's ``Rotation.mean`` of the normalised quaternions (zero: the identity): for unit
    quaternions the chordal mean is Markley's, as ``|R(p) - R(q)|_F^2 = 8 (1 - (p . q)^2)``."""
    flat, batch = _flat(q, 2)
    if not len(flat):
        return np.zeros((*batch, 4))
    w = weights.reshape(len(flat), -1)
    unit = np.where(np.all(flat == 0, axis=-1, keepdims=True), [1.0, 0.0, 0.0, 0.0], flat)
    rotations = Rotation.from_quat(unit, scalar_first=True)
    out = rotations.mean(weights=np.where(w.sum(-1, keepdims=True) > 0, w, 1.0), axis=-1)
    out = out.as_quat(canonical=True, scalar_first=True)
    return _identity_where_weightless(out, w, np.array([1.0, 0.0, 0.0, 0.0])).reshape(*batch, 4)


# The symmetric distance's row: a pair as matrix_geodesic_distance's, and scipy's group D3 (a 3-fold
# axis, z, and three 2-fold axes) given to every element of the batch.
SYMMETRY_ROW_GROUP = Rotation.create_group("D3").as_matrix()


def _symmetric_inputs(q: np.ndarray) -> tuple[np.ndarray, ...]:
    m1, m2 = (oracle_quaternion_to_matrix(x) for x in _pair(q))
    return m1, m2, np.broadcast_to(SYMMETRY_ROW_GROUP, (*q.shape[:-1], *SYMMETRY_ROW_GROUP.shape)).copy()


def oracle_symmetric_distance(m1: np.ndarray, m2: np.ndarray, group: np.ndarray) -> np.ndarray:
    """The minimum over the group's elements, by brute force with scipy's distance."""
    distances = [oracle_matrix_distance(m1, m2 @ group[..., k, :, :]) for k in range(group.shape[-3])]
    return np.min(distances, axis=0) if distances else np.zeros(m1.shape[:-2])


OPS += [
    *(
        Op(
            "rotation_mean",
            _mean_inputs,
            oracle,
            quaternion_args=(),
            output="matrix",
            scalar_first=False,
            kwargs={"method": method},
            label=f"rotation_mean[{method}]",
            applies=(lambda case: True) if method == "chordal" else _except(*ROTATED_ONLY),
            second_order_modes=("fwd", "rev") if method == "chordal" else ("rev",),
        )
        for method, oracle in [
            ("chordal", oracle_chordal_mean),
            ("geodesic", oracle_geodesic_mean),
            ("geodesic_l1", lambda m, w: oracle_geodesic_mean(m, w, l1=True)),
        ]
    ),
    Op(
        "quaternion_mean",
        _quaternion_mean_inputs,
        oracle_quaternion_mean,
        canonical=True,
        unit=True,
        up_to_sign=True,
    ),
    Op(
        "symmetric_geodesic_distance",
        _symmetric_inputs,
        oracle_symmetric_distance,
        quaternion_args=(),
        output="other",
        scalar_first=False,
        smooth_at=_except(*AT_DISTANCE_KINKS),
    ),
]


# ---------------------------------------------------------------------------------------------------
# SE(3) means and fits of point sets (the rest of SE(3) is above). Oracles: scipy's Rotation.mean and
# align_vectors for the rotations, and Umeyama's SVD for the similarity, in float64.


def _se3_mean_inputs(q: np.ndarray) -> tuple[np.ndarray, ...]:
    r, w = _mean_inputs(q)
    t = 2.0 * np.random.default_rng(25).normal(size=(*r.shape[:-2], 3))
    return se3_matrix(r, t), w


def oracle_se3_mean(matrices: np.ndarray, weights: np.ndarray) -> np.ndarray:
    """scipy's chordal mean of the rotations and the weighted mean of the translations (scipy's
    ``RigidTransform.mean``); weights summing to zero give the identity."""
    total = weights.sum(-1)[..., None]
    translation = (weights[..., None] * matrices[..., :3, 3]).sum(-2) / np.where(total > 0, total, 1.0)
    return se3_matrix(oracle_chordal_mean(matrices[..., :3, :3], weights), translation)


_SHIFT = np.array([0.7, -1.2, 2.1])


def _fit_pose_inputs(q: np.ndarray) -> tuple[np.ndarray, ...]:
    """fit_rotation's points and weights, the target moved by a translation and at the unit scale
    (a tiny scale beside the translation would be lost to rounding), except for the zero quaternion:
    then every target point is the same (no rotation is determined)."""
    source, target, weights = _fit_inputs(q)
    scale = _scale(q)[..., None, None]
    return source, target / np.where(scale > 0, scale, 1.0) + _SHIFT, weights


def _centroids(source: np.ndarray, target: np.ndarray, weights: np.ndarray) -> tuple[np.ndarray, ...]:
    total = weights.sum(-1)[..., None]
    total = np.where(total > 0, total, 1.0)
    return (weights[..., None] * source).sum(-2) / total, (weights[..., None] * target).sum(-2) / total


def oracle_fit_rigid_transform(source: np.ndarray, target: np.ndarray, weights: np.ndarray) -> np.ndarray:
    """scipy's align_vectors of the centred points, and t = ct - R cs."""
    cs, ct = _centroids(source, target, weights)
    rotation = oracle_fit_rotation(source - cs[..., None, :], target - ct[..., None, :], weights)
    # target points all equal: no rotation is determined, and special_procrustes(0) is the identity
    equal = np.all(target == target[..., :1, :], axis=(-1, -2))[..., None, None]
    rotation = np.where(equal, np.eye(3), rotation)
    return se3_matrix(rotation, ct - np.einsum("...ij,...j->...i", rotation, cs))


def oracle_fit_similarity_transform(
    source: np.ndarray, target: np.ndarray, weights: np.ndarray
) -> np.ndarray:
    """Umeyama (1991) by the SVD of the weighted covariance: s T, the table's join of (T, s)."""
    cs, ct = _centroids(source, target, weights)
    a, b = source - cs[..., None, :], target - ct[..., None, :]
    b = np.where(np.all(target == target[..., :1, :], axis=(-1, -2))[..., None, None], 0.0, b)  # no spread
    covariance = np.einsum("...n,...ni,...nj->...ij", weights, b, a)
    u, d, vt = np.linalg.svd(covariance)
    sign = np.sign(np.linalg.det(u) * np.linalg.det(vt))
    sign = np.where(sign == 0, 1.0, sign)
    flip = np.stack([np.ones_like(sign), np.ones_like(sign), sign], axis=-1)
    rotation = u @ (flip[..., :, None] * vt)
    spread = np.einsum("...n,...ni,...ni->...", weights, a, a)
    scale = np.where(spread > 0, (d * flip).sum(-1) / np.where(spread > 0, spread, 1.0), 1.0)
    translation = ct - scale[..., None] * np.einsum("...ij,...j->...i", rotation, cs)
    return scale[..., None, None] * se3_matrix(rotation, translation)


def _between_inputs(q: np.ndarray) -> tuple[np.ndarray, ...]:
    """(a, b) with b along R(q) a: the case's rotation is the one between them (b is a's direction
    rotated: the identity case gives parallel vectors); lengths 3 and 2 (the result is blind to them)."""
    a = 3.0 * _vectors(q)
    return a, 2.0 * np.einsum("...ij,...j->...i", oracle_quaternion_to_matrix(q), a)


def _sine_between(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    an = a / np.linalg.norm(a, axis=-1, keepdims=True)
    bn = b / np.linalg.norm(b, axis=-1, keepdims=True)
    return np.linalg.norm(np.cross(an, bn), axis=-1)


def oracle_rotation_between_vectors(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """scipy's align_vectors of one pair: the shortest-arc rotation R with b ~ R a."""
    fa, batch = _flat(a, 1)
    fb, _ = _flat(b, 1)
    out = np.zeros((len(fa), 3, 3))
    for k in range(len(fa)):
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            out[k] = Rotation.align_vectors(fb[k : k + 1], fa[k : k + 1])[0].as_matrix()
    return out.reshape((*batch, 3, 3))


def _frame_inputs(q: np.ndarray) -> tuple[np.ndarray, ...]:
    """(x1, x2, x3) of the frame [R(q), x2]: x3 along its first axis, x1 in the plane of its first two
    (on the side of the second), as a protein backbone's N, CA, C."""
    r = oracle_quaternion_to_matrix(q)
    x2 = _translation(q, 26)
    x3 = x2 + 1.5 * r[..., :, 0]
    x1 = x2 + 1.46 * (np.cos(2.0) * r[..., :, 0] + np.sin(2.0) * r[..., :, 1])
    return x1, x2, x3


def oracle_frame_from_three_points(x1: np.ndarray, x2: np.ndarray, x3: np.ndarray) -> np.ndarray:
    """Gram-Schmidt, written out."""
    e1 = (x3 - x2) / np.linalg.norm(x3 - x2, axis=-1, keepdims=True)
    v = x1 - x2
    u = v - np.sum(v * e1, axis=-1, keepdims=True) * e1
    e2 = u / np.linalg.norm(u, axis=-1, keepdims=True)
    return se3_matrix(np.stack([e1, e2, np.cross(e1, e2)], axis=-1), x2)


OPS += [
    Op(
        "se3_mean",
        _se3_mean_inputs,
        oracle_se3_mean,
        quaternion_args=(),
        output="other",
        scalar_first=False,
        relative=True,
    ),
    Op(
        "fit_rigid_transform",
        _fit_pose_inputs,
        oracle_fit_rigid_transform,
        quaternion_args=(),
        output="other",
        scalar_first=False,
        relative=True,
        degenerate=fit_degenerate("fit_rigid_transform"),
    ),
    Op(
        "fit_similarity_transform",
        _fit_pose_inputs,
        oracle_fit_similarity_transform,
        quaternion_args=(),
        output="other",
        scalar_first=False,
        relative=True,
        join=lambda out: out[0] * out[1][..., None, None],
        degenerate=fit_degenerate("fit_similarity_transform"),
    ),
    Op(
        "rotation_between_vectors",
        _between_inputs,
        oracle_rotation_between_vectors,
        quaternion_args=(),
        output="matrix",
        scalar_first=False,
        # The shortest arc's axis, a x b / |a x b|, has condition number 1 / sin(angle): the cross
        # product's rounding (eps |a| |b|) moves it by eps / sin(angle) near antiparallel vectors (the
        # half-turns' rows come within 3e-3 of it). Errors are measured in units of that conditioning.
        error_scale=lambda a, b: 1.0 / np.clip(_sine_between(a, b), 1e-300, 1.0),
        degenerate=BETWEEN_DEGENERATE,
    ),
    Op(
        "frame_from_three_points",
        _frame_inputs,
        oracle_frame_from_three_points,
        quaternion_args=(),
        output="other",
        scalar_first=False,
        relative=True,
        degenerate=FRAME_DEGENERATE,
    ),
]


# ---------------------------------------------------------------------------------------------------
# IGSO(3). The reference is mpmath at 50 digits: the defining series in l where it converges within
# a few hundred terms (eps = sigma^2 / 2 >= 0.05), its Poisson dual summed over |k| <= 30 below (the
# series would need ~1e5 terms at sigma = 1e-4, in ~300-digit arithmetic in the tail);
# tests/test_igso3.py checks that the two agree where both are summed. Each case quaternion gives the
# angle of its rotation (0 to pi: half-turns, near them, near the identity, the zero quaternion's 0)
# and a sigma from 0.3 to 10, log-uniform in the first vector component x of its unit quaternion
# (0.3 (10 / 0.3)^((x + 1) / 2)): both forms of the density, and both of its branches at the identity,
# are reached.
# Not below 0.3: the table's derivative checks take central differences with a step of 1e-6 relative,
# whose error grows as the curvature of log f about pi, (pi / sigma^2)^2, does; tests/test_igso3.py
# checks values and derivatives from sigma = 1e-4 against the reference's own derivatives.


def igso3_log_density_series(omega: Any, eps: Any) -> Any:
    """log f by its defining series in l, in mpmath (the working precision's), to a relative 1e-60."""
    total, ell = mpmath.mpf(0), 0
    while True:
        weight = (2 * ell + 1) * mpmath.exp(-ell * (ell + 1) * eps)
        kernel = mpmath.sin((ell + mpmath.mpf(0.5)) * omega) / mpmath.sin(omega / 2) if omega else 2 * ell + 1
        total += weight * kernel
        if ell > 2 and weight * (2 * ell + 1) < mpmath.mpf(10) ** -60:
            return mpmath.log(total)
        ell += 1


def igso3_log_density_dual(omega: Any, eps: Any) -> Any:
    """log f by the Poisson dual summed over |k| <= 30, in mpmath, for 0 < omega <= pi (the sum is
    taken relative to its k = 0 term, whose exponent is added as a log)."""
    total = mpmath.fsum(
        (-1) ** k
        * (omega + 2 * mpmath.pi * k)
        * mpmath.exp(-((omega + 2 * mpmath.pi * k) ** 2 - omega**2) / (4 * eps))
        for k in range(-30, 31)
    )
    log_f = mpmath.log(mpmath.sqrt(mpmath.pi) * total / (2 * mpmath.sin(omega / 2)))
    return log_f - 1.5 * mpmath.log(eps) + eps / 4 - omega**2 / (4 * eps)


def igso3_reference(omega: Any, sigma: Any) -> Any:
    """log f(omega; sigma) as an mpmath number at the working precision (see above), omega reduced to
    [0, pi]; differentiable by ``mpmath.diff`` in both arguments."""
    w = abs(omega - 2 * mpmath.pi * mpmath.nint(omega / (2 * mpmath.pi)))
    eps = sigma**2 / 2
    if eps >= mpmath.mpf("0.05"):
        return igso3_log_density_series(w, eps)
    # the dual's 0/0 at omega = 0: f is even in omega, so within 1e-60 of f(1e-30)
    return igso3_log_density_dual(max(w, mpmath.mpf(10) ** -30), eps)


@functools.cache
def reference_igso3_log_density(angle: float, sigma: float) -> float:
    """log f(omega; sigma) by mpmath at 50 digits (see above)."""
    with mpmath.workdps(50):
        return float(igso3_reference(mpmath.mpf(angle), mpmath.mpf(sigma)))


def igso3_reference_slope(omega: Any, sigma: Any) -> Any:
    """d log f / d omega at omega in (0, pi] as an mpmath number, from the derivative of each form
    (of the dual's sum F, ``F' = sum_k (-1)^k (1 - u_k^2 / (2 eps)) e^(-u_k^2 / (4 eps))``, less
    ``cot(omega / 2) / 2``; of the series term by term)."""
    eps = sigma**2 / 2
    half = omega / 2
    if eps >= mpmath.mpf("0.05"):
        total, slope, ell = mpmath.mpf(0), mpmath.mpf(0), 0
        while True:
            weight = (2 * ell + 1) * mpmath.exp(-ell * (ell + 1) * eps)
            lw = (ell + mpmath.mpf(0.5)) * omega
            total += weight * mpmath.sin(lw) / mpmath.sin(half)
            slope += weight * (
                (ell + 0.5) * mpmath.cos(lw) * mpmath.sin(half) - 0.5 * mpmath.sin(lw) * mpmath.cos(half)
            )
            if ell > 2 and weight * (2 * ell + 1) ** 2 < mpmath.mpf(10) ** -60:
                return slope / mpmath.sin(half) ** 2 / total
            ell += 1
    us = [omega + 2 * mpmath.pi * k for k in range(-30, 31)]
    # each term relative to the k = 0 one, exp(-omega^2 / (4 eps)), which cancels from F' / F
    rel = [
        mpmath.exp(-(u**2 - omega**2) / (4 * eps)) * (-1) ** k
        for k, u in zip(range(-30, 31), us, strict=True)
    ]
    f = mpmath.fsum(r * u for r, u in zip(rel, us, strict=True))
    df = mpmath.fsum(r * (1 - u**2 / (2 * eps)) for r, u in zip(rel, us, strict=True))
    return df / f - mpmath.cot(half) / 2


def oracle_igso3_score(matrix: np.ndarray, sigma: np.ndarray, mean: np.ndarray) -> np.ndarray:
    """(d log f / d omega) phi / omega with phi = log(mean^T R) (scipy's rotation vector), 0 at the
    identity; the derivative by mpmath at 50 digits (``igso3_reference_slope``)."""
    relative = np.swapaxes(mean, -1, -2) @ matrix
    batch = np.broadcast_shapes(relative.shape[:-2], np.shape(sigma))
    flat = relative.reshape(-1, 3, 3)
    phi = Rotation.from_matrix(flat).as_rotvec() if len(flat) else np.zeros((0, 3))
    phi = np.broadcast_to(phi.reshape((*relative.shape[:-2], 3)), (*batch, 3))
    angle = np.linalg.norm(phi, axis=-1)
    s = np.broadcast_to(sigma, batch)
    factor = np.array([_igso3_factor(float(w), float(y)) for w, y in zip(angle.flat, s.flat, strict=True)])
    return factor.reshape(batch)[..., None] * phi


@functools.cache
def _igso3_factor(angle: float, sigma: float) -> float:
    if angle == 0.0:
        return 0.0  # the score at the identity is 0; the factor's value does not matter there
    with mpmath.workdps(50):
        return float(igso3_reference_slope(mpmath.mpf(angle), mpmath.mpf(sigma)) / angle)


def igso3_cdf_reference(omega: Any, sigma: Any) -> Any:
    """F(omega; sigma) for omega in [0, pi] as an mpmath number: the series integrated term by term for
    eps >= 0.05 (to terms below 1e-60), else the integral of the dual form's angle density
    (``mpmath.quad``, split at a few sigma, where the mass is)."""
    eps = sigma**2 / 2
    if eps >= mpmath.mpf("0.05"):
        total, ell = omega - mpmath.sin(omega), 1
        while True:
            weight = (2 * ell + 1) * mpmath.exp(-ell * (ell + 1) * eps)
            total += weight * (mpmath.sin(ell * omega) / ell - mpmath.sin((ell + 1) * omega) / (ell + 1))
            if ell > 2 and weight < mpmath.mpf(10) ** -60:
                return total / mpmath.pi
            ell += 1

    def density(t: Any) -> Any:
        # f (1 - cos t) / pi with f's dual sum: 2 sin^2(t / 2) / pi * f
        terms = [
            (-1) ** k * (t + 2 * mpmath.pi * k) * mpmath.exp(-((t + 2 * mpmath.pi * k) ** 2) / (4 * eps))
            for k in range(-4, 5)
        ]
        return (
            mpmath.sqrt(mpmath.pi)
            * eps**-1.5
            * mpmath.exp(eps / 4)
            * mpmath.sin(t / 2)
            * mpmath.fsum(terms)
            / mpmath.pi
        )

    points = [mpmath.mpf(0)] + [p for p in (sigma, 3 * sigma, 8 * sigma) if p < omega] + [omega]
    return mpmath.quad(density, points)


@functools.cache
def reference_igso3_angle_cdf(angle: float, sigma: float) -> float:
    """F(omega; sigma) by mpmath at 30 digits (twice float64's: its quadrature at 50 cost minutes),
    omega clamped to [0, pi]."""
    with mpmath.workdps(30):
        w = min(max(mpmath.mpf(angle), mpmath.mpf(0)), mpmath.pi)
        return float(igso3_cdf_reference(w, mpmath.mpf(sigma))) if w > 0 else 0.0


def oracle_igso3_angle_cdf(angle: np.ndarray, sigma: np.ndarray) -> np.ndarray:
    a, s = np.broadcast_arrays(angle, sigma)
    return np.array(
        [reference_igso3_angle_cdf(float(x), float(y)) for x, y in zip(a.flat, s.flat, strict=True)]
    ).reshape(a.shape)


def oracle_igso3_log_density(angle: np.ndarray, sigma: np.ndarray) -> np.ndarray:
    a, s = np.broadcast_arrays(angle, sigma)
    return np.array(
        [reference_igso3_log_density(float(x), float(y)) for x, y in zip(a.flat, s.flat, strict=True)]
    ).reshape(a.shape)


def igso3_scale(angle: np.ndarray, sigma: np.ndarray) -> np.ndarray:
    """The size of log f's terms, which its error is measured against: 1 + |1.5 log eps| + omega^2 / (4
    eps) (where log f crosses 0, the terms cancel and a relative error would be meaningless)."""
    eps = np.maximum(0.5 * np.asarray(sigma, np.float64) ** 2, 1e-300)
    return 1.0 + np.abs(1.5 * np.log(eps)) + np.asarray(angle, np.float64) ** 2 / (4.0 * eps)


def _igso3_inputs(q: np.ndarray) -> tuple[np.ndarray, ...]:
    u = oracle_normalize(q)
    angle = 2.0 * np.arctan2(np.linalg.norm(u[..., 1:], axis=-1), np.abs(u[..., 0]))
    return angle, 0.3 * (10.0 / 0.3) ** (0.5 * (u[..., 1] + 1.0))


def _igso3_score_inputs(q: np.ndarray) -> tuple[np.ndarray, ...]:
    """mean R(q) for a uniform mean, so that the rotation relative to the mean is the case's R(q)."""
    mean = _companion_matrix(q)
    return mean @ oracle_quaternion_to_matrix(q), _igso3_inputs(q)[1], mean


def _igso3_score_gradient_inputs(q: np.ndarray) -> tuple[np.ndarray, ...]:
    return q, _igso3_inputs(q)[1], _companion(q, seed=11)


OPS += [
    Op(
        "igso3_log_density",
        _igso3_inputs,
        oracle_igso3_log_density,
        quaternion_args=(),
        output="other",
        scalar_first=False,
        smooth_at=lambda case: True,
        error_scale=igso3_scale,
    ),
    Op(
        "igso3_angle_cdf",
        _igso3_inputs,
        oracle_igso3_angle_cdf,
        quaternion_args=(),
        output="other",
        scalar_first=False,
        # F is the CDF of an angle in [0, pi]: constant 1 beyond pi, so it has a kink there (its slope
        # from the left is the density at pi), which half-turns reach
        smooth_at=lambda case: case.name not in ("half_turns", "near_half_turns", "gimbal_lock"),
        # a probability: its error is absolute (error_scale 1)
    ),
    Op(
        "igso3_score",
        _igso3_score_inputs,
        oracle_igso3_score,
        quaternion_args=(),
        output="other",
        scalar_first=False,
        # through quaternions, as matrix_to_quaternion's gradient: on the manifold (the score is the
        # gradient of a smooth function there, at half-turns too), not along the nine entries, where
        # the conversion's pivot choice makes the extension off SO(3) kink
        grad_inputs=_igso3_score_gradient_inputs,
        grad_fn=lambda m, q, sigma, mean: m.igso3_score(
            m.quaternion_to_matrix(mean) @ m.quaternion_to_matrix(q), sigma, m.quaternion_to_matrix(mean)
        ),
        smooth_at=lambda case: True,
        # d score / dq is up to (2 / |q|) (pi / sigma^2)^2: 2e4 * 1.2e3 at the float16 norm 1e-4 and
        # sigma = 0.3, beyond float16's 65504
        finite_gradient=lambda case, dtype: not (case.name == "norms" and dtype == "float16"),
        # The score's size, 1 + pi / sigma^2, and its sensitivity to the rotation: near pi an error of
        # the angle moves it by up to (pi / sigma^2)^2 times as much, and a float32 matrix's angle is
        # defined only to an ulp (its projection onto SO(3) decides it).
        error_scale=lambda matrix, sigma, mean: (
            1.0 + np.pi / np.asarray(sigma) ** 2 + (np.pi / np.asarray(sigma) ** 2) ** 2
        ),
    ),
]


# ---------------------------------------------------------------------------------------------------
# Rotations in time. References, independent of the formulas: the rates of R(q(t)) from scipy's
# matrices (the quadratic numerator M(q) = |q|^2 R(q) differentiated by exact polarisation, not by
# quaternion algebra), scipy's composition and rotation vectors for integration and rates from
# samples, Shoemake's construction from scipy's slerps for SQUAD, and for the B-splines the product
# rule over scipy's exponentials (the first and second derivatives of the cumulative product, not
# Sommer et al.'s recursion) with the cubic basis written out. The case's rotation is the increment
# between samples, knots or control points: the identity and the zero quaternion give static
# trajectories (zero increments), near_identity tiny ones. Increments of exactly a half-turn have two
# shortest arcs and rounding picks one (tests/test_motion.py checks them), so the rows where the
# increment's arc is ambiguous are left out as for se3_interpolate.

_GENERIC_STEP = Rotation.from_rotvec([0.4, -0.3, 0.5])


def _numerator(x: np.ndarray) -> np.ndarray:
    """M(x) = |x|^2 R(x): quadratic in x, 0 at x = 0 (scipy's matrix of the normalised x)."""
    flat, batch = _flat(x, 1)
    n2 = np.sum(flat * flat, axis=-1)
    safe = np.where(n2[:, None] > 0, flat, [1.0, 0.0, 0.0, 0.0])
    out = Rotation.from_quat(safe, scalar_first=True).as_matrix() if len(flat) else np.zeros((0, 3, 3))
    return (n2[:, None, None] * out).reshape((*batch, 3, 3))


def _polar(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """The bilinear form of M: (M(a + b) - M(a - b)) / 4."""
    return 0.25 * (_numerator(a + b) - _numerator(a - b))


def _skew_vee(a: np.ndarray) -> np.ndarray:
    return 0.5 * np.stack(
        [a[..., 2, 1] - a[..., 1, 2], a[..., 0, 2] - a[..., 2, 0], a[..., 1, 0] - a[..., 0, 1]], -1
    )


def _rotation_rates(q: np.ndarray, qd: np.ndarray, qdd: np.ndarray) -> tuple[np.ndarray, ...]:
    """(R, R', R'') of R(q(t)) = M(q) / |q|^2 at q(t) = q + t q' + t^2 q'' / 2; the zero q gives 0."""
    n2 = np.sum(q * q, axis=-1)[..., None, None]
    d1 = 2.0 * np.sum(q * qd, axis=-1)[..., None, None]
    d2 = 2.0 * (np.sum(qd * qd, axis=-1) + np.sum(q * qdd, axis=-1))[..., None, None]
    m0, m1, m2 = _numerator(q), 2.0 * _polar(q, qd), 2.0 * (_numerator(qd) + _polar(q, qdd))
    inv = 1.0 / np.where(n2 > 0, n2, np.inf)
    r = m0 * inv
    r1 = (m1 - r * d1) * inv
    r2 = (m2 - 2.0 * r1 * d1 - r * d2) * inv
    return r, r1, r2


def _rate_inputs(q: np.ndarray) -> tuple[np.ndarray, ...]:
    """(q, q', q''): derivatives of the size of |q| in random directions (the radial parts included)."""
    size = _scale(q)[..., None]
    return q, 0.7 * size * _companion(q, seed=31), 0.9 * size * _companion(q, seed=32)


def oracle_angular_velocity(q: np.ndarray, qd: np.ndarray) -> np.ndarray:
    r, r1, _ = _rotation_rates(q, qd, np.zeros_like(q))
    return _skew_vee(np.swapaxes(r, -1, -2) @ r1)


def oracle_angular_acceleration(q: np.ndarray, qd: np.ndarray, qdd: np.ndarray) -> np.ndarray:
    # d/dt (R^T R') = R'^T R' + R^T R'', whose first term is symmetric
    r, _, r2 = _rotation_rates(q, qd, qdd)
    return _skew_vee(np.swapaxes(r, -1, -2) @ r2)


def oracle_quaternion_derivative_space(q: np.ndarray, omega: np.ndarray) -> np.ndarray:
    pure = np.concatenate([np.zeros_like(omega[..., :1]), omega], axis=-1)
    return 0.5 * hamilton(pure, q)


def _integrate_inputs(q: np.ndarray) -> tuple[np.ndarray, ...]:
    """(p, w, dt) with w dt the case's rotation vector: p any norm (the case's), the step the case."""
    dt = np.random.default_rng(33).uniform(0.2, 1.5, size=q.shape[:-1])
    return _companion(q, seed=11) * _scale(q)[..., None], _rotvec(q)[0] / dt[..., None], dt


def oracle_integrate_space(p: np.ndarray, omega: np.ndarray, dt: np.ndarray) -> np.ndarray:
    flat, _ = _flat(omega * dt[..., None], 1)
    step = Rotation.from_rotvec(flat) if len(flat) else None
    return _batched(lambda r: (step * r).as_quat(scalar_first=True), p, (4,))


def _sequence(q: np.ndarray) -> np.ndarray:
    """(..., 4, 4): unit samples p, p q, p q g, p q g q (g a generic step): the case's increment twice."""
    p = oracle_normalize(_companion(q, seed=11))
    g = np.broadcast_to(_GENERIC_STEP.as_quat(scalar_first=True), q.shape)
    u = oracle_normalize(np.where(_scale(q)[..., None] > 0, q, [1.0, 0.0, 0.0, 0.0]))
    s1 = hamilton(p, u)
    s2 = hamilton(s1, g)
    return np.stack([p, s1, s2, hamilton(s2, u)], axis=-2)


def _from_quaternions_inputs(q: np.ndarray) -> tuple[np.ndarray, ...]:
    dt = np.random.default_rng(34).uniform(0.05, 2.0, size=q.shape[:-1])
    return _sequence(q) * np.array([1.0, -1.0, 2.0, 0.5])[:, None], dt  # sign flip and norms: ignored


def oracle_angular_velocity_from_quaternions(q: np.ndarray, dt: np.ndarray) -> np.ndarray:
    a, b = q[..., :-1, :], q[..., 1:, :]
    # r_k^-1 r_k+1 as a quaternion, its shortest-arc (canonical) rotation vector
    return _rotvec(hamilton(oracle_invert(a), b))[0] / dt[..., None, None]


OPS += [
    Op(
        "angular_velocity",
        lambda q: _rate_inputs(q)[:2],
        oracle_angular_velocity,
        quaternion_args=(0, 1),
        output="other",
    ),
    Op(
        "quaternion_derivative",
        lambda q: (q, 1.5 * _companion(q, seed=31)[..., 1:]),
        oracle_quaternion_derivative_space,
        kwargs={"frame": "space"},
        label="quaternion_derivative[space]",
        relative=True,  # q' scales with |q|
    ),
    Op(
        "angular_acceleration",
        _rate_inputs,
        oracle_angular_acceleration,
        quaternion_args=(0, 1, 2),
        output="other",
    ),
    Op(
        "integrate_angular_velocity",
        _integrate_inputs,
        oracle_integrate_space,
        kwargs={"frame": "space"},
        label="integrate_angular_velocity[space]",
        unit=True,
    ),
    Op(
        "angular_velocity_from_quaternions",
        _from_quaternions_inputs,
        oracle_angular_velocity_from_quaternions,
        output="other",
        # a rotation vector's error is absolute (an ulp of the samples): divided by dt, as the rates
        error_scale=lambda q, dt: 1.0 / dt,
        applies=lambda case: case.name not in AT_HALF_TURNS,
    ),
]


# SQUAD and the B-splines: six samples (the case's increment, a generic step, the case's, the generic,
# the case's: three segments of a cubic B-spline, five of SQUAD), parameters drawn inside the segments
# (not at a joint, where SQUAD's acceleration jumps) and away from the clamped ends.


def _six(q: np.ndarray) -> np.ndarray:
    """(..., 6, 4) unit samples: ``_sequence``'s four, then the generic step and the case's again."""
    seq = _sequence(q)
    g = np.broadcast_to(_GENERIC_STEP.as_quat(scalar_first=True), q.shape)
    u = oracle_normalize(np.where(_scale(q)[..., None] > 0, q, [1.0, 0.0, 0.0, 0.0]))
    fifth = hamilton(seq[..., -1, :], g)
    return np.concatenate([seq, fifth[..., None, :], hamilton(fifth, u)[..., None, :]], axis=-2)


def _parameters(q: np.ndarray, seed: int, top: float) -> np.ndarray:
    """A parameter per batch element in (0.05, top - 0.05), not within 0.05 of an integer."""
    u = np.random.default_rng(seed).uniform(0.05, 0.95, size=q.shape[:-1])
    return u + np.random.default_rng(seed + 1).integers(0, int(top), size=q.shape[:-1])


def _squad_inputs(q: np.ndarray) -> tuple[np.ndarray, ...]:
    return _six(q) * np.array([1.0, -1.0, 2.0, 1.0, -0.5, 1.0])[:, None], _parameters(q, 35, 5.0)


def _slerp_rotations(a: Rotation, b: Rotation, h: np.ndarray) -> Rotation:
    """scipy's shortest arc from a to b at h: a exp(h log(a^-1 b))."""
    return a * Rotation.from_rotvec(h[:, None] * (a.inv() * b).as_rotvec())


def oracle_quaternion_squad(q: np.ndarray, t: np.ndarray) -> np.ndarray:
    """Shoemake's construction from scipy's rotations: inner controls s_i = q_i exp((d_i-1 - d_i)/4)
    with d_i = log(q_i^-1 q_i+1) (ends their own), slerps of slerps; the sign of the knots made
    consistent (each in the hemisphere of the one before), the result's sign that of the knots'
    normalised linear blend."""
    flat, batch = _flat(q, 2)
    tf = np.broadcast_to(t, batch).reshape(-1)
    n, count = flat.shape[0], flat.shape[1]
    if n == 0:
        return np.zeros((*batch, 4))
    unit = flat / np.linalg.norm(flat, axis=-1, keepdims=True)
    for k in range(1, count):
        flip = np.sum(unit[:, k] * unit[:, k - 1], axis=-1) < 0
        unit[flip, k] *= -1.0
    rots = [Rotation.from_quat(unit[:, k], scalar_first=True) for k in range(count)]
    d = [(rots[k].inv() * rots[k + 1]).as_rotvec() for k in range(count - 1)]
    inner = [rots[0]] + [rots[k] * Rotation.from_rotvec((d[k - 1] - d[k]) / 4) for k in range(1, count - 1)]
    inner.append(rots[-1])
    tc = np.clip(tf, 0.0, count - 1.0)
    i = np.minimum(np.floor(tc), count - 2).astype(int)
    h = tc - i
    out = np.zeros((n, 4))
    blend = np.zeros((n, 4))
    for k in range(count - 1):
        sel = i == k
        if not np.any(sel):
            continue
        hk = h[sel]
        outer = _slerp_rotations(rots[k][sel], rots[k + 1][sel], hk)
        mid = _slerp_rotations(inner[k][sel], inner[k + 1][sel], hk)
        out[sel] = _slerp_rotations(outer, mid, 2.0 * hk * (1.0 - hk)).as_quat(scalar_first=True)
        blend[sel] = (1.0 - hk)[:, None] * unit[sel, k] + hk[:, None] * unit[sel, k + 1]
    out *= np.where(np.sum(out * blend, axis=-1) < 0, -1.0, 1.0)[:, None]
    return out.reshape((*batch, 4))


# The cubic's cumulative basis in powers s^0 .. s^3 (Kim, Kim and Shin 1995), rows j = 1, 2, 3.
_CUBIC = np.array([[5.0, 3.0, -3.0, 1.0], [1.0, 3.0, 3.0, -2.0], [0.0, 0.0, 0.0, 1.0]]) / 6.0


def _cubic_basis(s: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(lambda, lambda', lambda''), each (n, 3), of the cubic at fractions s (n,)."""
    powers = np.stack([np.ones_like(s), s, s * s, s**3], axis=-1)
    first = np.stack([np.zeros_like(s), np.ones_like(s), 2 * s, 3 * s * s], axis=-1)
    second = np.stack([np.zeros_like(s), np.zeros_like(s), 2 * np.ones_like(s), 6 * s], axis=-1)
    return powers @ _CUBIC.T, first @ _CUBIC.T, second @ _CUBIC.T


def _product_rule(first: np.ndarray, factors: list[tuple[np.ndarray, ...]]) -> tuple[np.ndarray, ...]:
    """(X, X', X'') of X = first A_1 ... A_m from each factor's (A, A', A'') (n, d, d)."""
    value, d1, d2 = first, np.zeros_like(first), np.zeros_like(first)
    for a, a1, a2 in factors:
        value, d1, d2 = value @ a, d1 @ a + value @ a1, d2 @ a + 2.0 * d1 @ a1 + value @ a2
    return value, d1, d2


def _segments(u: np.ndarray, count: int) -> tuple[np.ndarray, np.ndarray]:
    uc = np.clip(u, 0.0, count - 3.0)
    i = np.minimum(np.floor(uc), count - 4).astype(int)
    return i, uc - i


def _twists(value: np.ndarray, d1: np.ndarray, d2: np.ndarray) -> np.ndarray:
    """(..., 24): [T]_top (12), the body twist vee(T^-1 T') and its derivative
    vee(T^-1 T'' - (T^-1 T')^2), of 4x4 pose curves."""
    inv = np.linalg.inv(value)
    x = inv @ d1
    x1 = inv @ d2 - x @ x

    def vee(m: np.ndarray) -> np.ndarray:
        return np.concatenate([m[:, :3, 3], _skew_vee(m[:, :3, :3])], axis=-1)

    return np.concatenate([value[:, :3, :].reshape(-1, 12), vee(x), vee(x1)], axis=-1)


def _so3_factors(d: np.ndarray, lam: tuple[np.ndarray, ...]) -> list[tuple[np.ndarray, ...]]:
    """Each exp(lambda_j d_j) and its first two derivatives in s, (n, 3, 3), from scipy's exponential:
    A' = A hat(lambda' d), A'' = A (hat(lambda' d)^2 + hat(lambda'' d))."""
    out = []
    for j in range(3):
        dj = d[:, j]
        a = Rotation.from_rotvec(lam[0][:, j, None] * dj).as_matrix()
        w1, w2 = hat(lam[1][:, j, None] * dj), hat(lam[2][:, j, None] * dj)
        out.append((a, a @ w1, a @ (w1 @ w1 + w2)))
    return out


def _controls(q: np.ndarray) -> np.ndarray:
    """(..., 6, 3, 3): the rotations of ``_six``."""
    return (
        _batched(lambda r: r.as_matrix(), _six(q), (3, 3)) if q.size else np.zeros((*q.shape[:-1], 6, 3, 3))
    )


def _bspline_inputs(q: np.ndarray) -> tuple[np.ndarray, ...]:
    return _controls(q), _parameters(q, 36, 3.0)


def _poses(q: np.ndarray) -> np.ndarray:
    rot = _controls(q)
    t = np.random.default_rng(37).normal(size=(*rot.shape[:-2], 3))
    top = np.concatenate([rot, t[..., None]], axis=-1)
    bottom = np.broadcast_to([0.0, 0.0, 0.0, 1.0], (*rot.shape[:-2], 1, 4))
    return np.concatenate([top, bottom], axis=-2)


def _se3_bspline_inputs(q: np.ndarray) -> tuple[np.ndarray, ...]:
    return _poses(q), _parameters(q, 38, 3.0)


def _so3_curve(control: np.ndarray, u: np.ndarray) -> tuple[np.ndarray, ...]:
    """(R, R', R'') (n, 3, 3) of the cubic B-spline by the product rule over scipy's exponentials,
    increments from scipy's logarithm of the control rotations (read as scipy reads a matrix)."""
    n, count = control.shape[0], control.shape[1]
    rots = [Rotation.from_matrix(control[:, k]) for k in range(count)]
    inc = np.stack([(rots[k].inv() * rots[k + 1]).as_rotvec() for k in range(count - 1)], axis=1)
    i, s = _segments(u, count)
    rows = np.arange(n)
    d = np.stack([inc[rows, i + j] for j in range(3)], axis=1)
    first = np.stack([rots[k].as_matrix() for k in range(count)], axis=1)[rows, i]
    return _product_rule(first, _so3_factors(d, _cubic_basis(s)))


def _flat_pair(control: np.ndarray, u: np.ndarray, trailing: int) -> tuple[np.ndarray, np.ndarray, tuple]:
    batch = np.broadcast_shapes(control.shape[: -1 - trailing], u.shape)
    c = np.broadcast_to(control, (*batch, *control.shape[-1 - trailing :])).reshape(
        -1, *control.shape[-1 - trailing :]
    )
    return c, np.broadcast_to(u, batch).reshape(-1), batch


def oracle_so3_bspline(control: np.ndarray, u: np.ndarray) -> np.ndarray:
    c, uf, batch = _flat_pair(control, u, 2)
    if c.shape[0] == 0:
        return np.zeros((*batch, 15))
    r, r1, r2 = _so3_curve(c, uf)
    rt = np.swapaxes(r, -1, -2)
    # d/du (R^T R') = R'^T R' + R^T R'', whose first term is symmetric
    out = np.concatenate([r.reshape(-1, 9), _skew_vee(rt @ r1), _skew_vee(rt @ r2)], axis=-1)
    return out.reshape((*batch, 15))


def _se3_hat(xi: np.ndarray) -> np.ndarray:
    out = np.zeros((xi.shape[0], 4, 4))
    out[:, :3, :3], out[:, :3, 3] = hat(xi[:, 3:]), xi[:, :3]
    return out


def oracle_se3_bspline(control: np.ndarray, u: np.ndarray) -> np.ndarray:
    """The SE(3) cubic by the product rule over scipy's matrix exponential of twists, increments from
    scipy's matrix logarithm of the relative poses; the first control pose of a segment as it is."""
    c, uf, batch = _flat_pair(control, u, 2)
    n, count = c.shape[0], c.shape[1] if c.ndim == 4 else 0
    if n == 0:
        return np.zeros((*batch, 24))
    # the control rotations read as scipy reads a matrix (the nearest rotation: inputs rounded to a
    # half-precision dtype are off SO(3) by their rounding), the relative poses of those exactly
    exact = c.copy()
    exact[..., :3, :3] = (
        Rotation.from_matrix(c[..., :3, :3].reshape(-1, 3, 3)).as_matrix().reshape(n, count, 3, 3)
    )
    rel = np.linalg.inv(exact[:, :-1]) @ exact[:, 1:]
    logs = np.array([[np.real(scipy.linalg.logm(m)) for m in row] for row in rel])  # (n, K - 1, 4, 4)
    inc = np.concatenate([logs[..., :3, 3], _skew_vee(logs[..., :3, :3])], axis=-1)
    i, s = _segments(uf, count)
    rows = np.arange(n)
    lam = _cubic_basis(s)
    factors = []
    for j in range(3):
        dj = inc[rows, i + j]
        a = np.array([scipy.linalg.expm(m) for m in _se3_hat(lam[0][:, j, None] * dj)])
        w1, w2 = _se3_hat(lam[1][:, j, None] * dj), _se3_hat(lam[2][:, j, None] * dj)
        factors.append((a, a @ w1, a @ (w1 @ w1 + w2)))
    return _twists(*_product_rule(c[rows, i], factors)).reshape((*batch, 24))


def oracle_se3_bspline_split(control: np.ndarray, u: np.ndarray) -> np.ndarray:
    """R^3 x SO(3): the rotations' cubic (as oracle_so3_bspline) and the translations' cubic blend."""
    c, uf, batch = _flat_pair(control, u, 2)
    n, count = c.shape[0], c.shape[1] if c.ndim == 4 else 0
    if n == 0:
        return np.zeros((*batch, 24))
    r, r1, r2 = _so3_curve(np.ascontiguousarray(c[..., :3, :3]), uf)
    i, s = _segments(uf, count)
    rows = np.arange(n)
    steps = np.stack([c[rows, i + j + 1, :3, 3] - c[rows, i + j, :3, 3] for j in range(3)], axis=1)
    lam = _cubic_basis(s)
    curve = [np.zeros((n, 4, 4)) for _ in range(3)]
    for k, (rk, pk) in enumerate(
        [(r, c[rows, i, :3, 3] + np.einsum("nj,njc->nc", lam[0], steps))]
        + [(rd, np.einsum("nj,njc->nc", lam[m], steps)) for m, rd in ((1, r1), (2, r2))]
    ):
        curve[k][:, :3, :3], curve[k][:, :3, 3] = rk, pk
    curve[0][:, 3, 3] = 1.0
    return _twists(*curve).reshape((*batch, 24))


def pack_outputs(out: Any) -> Any:
    """The table's one array of a function returning (value, rate, rate of the rate): the value's top
    three rows (a rotation's 9 entries, a pose's 12) flattened, then the rates, concatenated along the
    last axis by the arrays' own framework (torch's also under FX, whose proxies are not tensors)."""
    value, rate, accel = out
    top = value[..., :3, :]
    torch = sys.modules.get("torch")
    if torch is not None and isinstance(value, torch.Tensor | torch.fx.Proxy):
        return torch.cat([top.flatten(-2), rate, accel], dim=-1)
    flat = top.reshape(*top.shape[:-2], top.shape[-2] * top.shape[-1])
    if isinstance(value, np.ndarray):
        return np.concatenate([flat, rate, accel], axis=-1)
    return sys.modules["jax.numpy"].concatenate([flat, rate, accel], axis=-1)


OPS += [
    Op(
        "quaternion_squad",
        _squad_inputs,
        oracle_quaternion_squad,
        unit=True,
        applies=lambda case: case.name not in AT_HALF_TURNS,
    ),
    Op(
        "so3_bspline",
        _bspline_inputs,
        oracle_so3_bspline,
        quaternion_args=(),
        output="other",
        scalar_first=False,
        join=pack_outputs,
        applies=lambda case: case.name not in AT_HALF_TURNS,
    ),
    Op(
        "se3_bspline",
        _se3_bspline_inputs,
        oracle_se3_bspline,
        quaternion_args=(),
        output="other",
        relative=True,  # twists and their rates scale with the translations (entries up to ~10)
        scalar_first=False,
        join=pack_outputs,
        applies=lambda case: case.name not in AT_HALF_TURNS,
    ),
    Op(
        "se3_bspline",
        _se3_bspline_inputs,
        oracle_se3_bspline_split,
        quaternion_args=(),
        output="other",
        relative=True,
        scalar_first=False,
        join=pack_outputs,
        kwargs={"mode": "split"},
        label="se3_bspline[split]",
        applies=lambda case: case.name not in AT_HALF_TURNS,
    ),
]


# Every row without configurations of its own is named at the rotations where rotation maps
# degenerate, through the row's own inputs (its pairs give coincident rotations at the identity and
# antipodal ones at the half-turns; its SE(3) rows pure rotations with their translation; its means
# clusters about them): the identity, the 26 exact half-turns (about the axes, the face and the cube
# diagonals), rotations 1e-1 ... 1e-8 short of a half-turn and 1e-4 ... 1e-10 from the identity, and
# the 24 exact gimbal locks of ``_gimbal_locks``, against the row's float64 oracle as the table
# measures it (accurate to a few float64 ulps there: float64's bound allows for it).
_IDENTITIES = np.array([[1.0, 0.0, 0.0, 0.0], [-1.0, 0.0, 0.0, 0.0]])


def _near_half_turns_for(dtype: str, relative: bool) -> np.ndarray:
    """``_near_half_turns`` (every 7th), and for a row of a relative rotation (``relative``) in float32
    only those 1e-1 ... 1e-3 short: a pair's relative rotation 1e-4 or less short of a half-turn is, once
    rounded to float32, within float32's rounding of the tie where the shortest path changes sides
    (there the answer is either branch's, and the reference at the rounded inputs cannot say which)."""
    q = _near_half_turns()[::7]
    if relative and dtype != "float64":
        angle = 2.0 * np.arctan2(np.linalg.norm(q[:, 1:], axis=-1), np.abs(q[:, 0]))
        q = q[np.pi - angle > 5e-4]
    return q


def euler_rotation_error(convention: str) -> Callable[[list[np.ndarray], np.ndarray, str], float]:
    """Angles at a gimbal lock are not unique: the rotation they make (scipy, float64) against the
    input's rotation, entrywise, in ulps of the dtype. Within 1e-7 rad of a lock the documented rule
    (the third angle 0, as scipy) moves the rotation by up to that distance: allowed, as documented."""
    proper = convention[0].lower() == convention[2].lower()

    def error(received: list[np.ndarray], out: np.ndarray, dtype: str) -> float:
        x = received[0]
        expected = oracle_quaternion_to_matrix(oracle_normalize(x)) if x.shape[-1] == 4 else x
        made = oracle_quaternion_to_matrix(oracle_euler_to_quaternion(out, convention))
        middle = out[..., 1]
        to_lock = np.minimum(middle, np.pi - middle) if proper else 0.5 * np.pi - np.abs(middle)
        allowed = np.where(to_lock <= 1.0001e-7, 2.0 * np.abs(to_lock), 0.0)
        excess = np.maximum(np.abs(made - expected).max(axis=(-2, -1)) - allowed, 0.0)
        return float(excess.max(initial=0.0)) / float(np.finfo(dtype).eps)

    return error


def at_rotations(
    op: Op, ulps: float, skip: tuple[str, ...] = (), relative: bool = False, error: Any = None
) -> tuple[Degenerate, ...]:
    sets: dict[str, Callable[[str], np.ndarray]] = {
        "identity": lambda dtype: _IDENTITIES,
        "half_turns": lambda dtype: _half_turns(),
        "near_half_turns": lambda dtype: _near_half_turns_for(dtype, relative),
        "near_identity": lambda dtype: _near_identity(),
        "gimbal_lock": lambda dtype: _gimbal_locks(),
    }
    return tuple(
        Degenerate(name, lambda dtype, q=q: op.inputs(q(dtype)), error or against_the_oracle(op.id), ulps)
        for name, q in sets.items()
        if name not in skip
    )


def _endpoint_inputs(
    inputs: Callable[[np.ndarray], tuple[np.ndarray, ...]],
) -> Callable[[str], tuple[np.ndarray, ...]]:
    """An interpolation's inputs at t = 0 and t = 1 exactly, at coincident, generic and nearly
    antipodal pairs (1e-1 ... 1e-3 short of a half-turn, away from the tie of the shortest path)."""

    def make(dtype: str) -> tuple[np.ndarray, ...]:
        q = np.concatenate(
            [_IDENTITIES, uniform_quaternions(8, seed=41), _near_half_turns_for("float32", True)]
        )
        *pair, _ = inputs(np.concatenate([q, q]))
        return (*pair, np.repeat([0.0, 1.0], len(q)))

    return make


def endpoint_error(received: list[np.ndarray], out: np.ndarray, dtype: str) -> float:
    """An interpolation at t = 0 and 1 against its ends as received (exact): relative to the largest
    entry of each, up to the sign for quaternions (slerp takes the shortest path)."""
    start, end, t = received
    expected = np.where(np.reshape(t, t.shape + (1,) * (start.ndim - t.ndim)) == 0.0, start, end)
    if expected.shape[-1] == 4 and expected.ndim == 2:
        expected = oracle_normalize(expected)
        error = np.minimum(np.abs(out - expected).max(axis=-1), np.abs(out + expected).max(axis=-1))
    else:
        error = (np.abs(out - expected) / np.abs(expected).max(axis=(-2, -1), keepdims=True)).max(
            axis=(-2, -1)
        )
    return float(error.max()) / float(np.finfo(dtype).eps)


def reference_matrix_fisher_log_normalizer(matrix: np.ndarray) -> np.ndarray:
    """log c(F) by mpmath (``reference_log_c``, 20 digits) at the proper singular values: the float64
    oracle's quadrature stops at a relative 1e-13 (~60 float64 ulps measured)."""
    return _each(proper_singular_values(matrix), reference_log_c)


def _fisher_reference(op_id: str) -> Callable[[list[np.ndarray], np.ndarray, str], float]:
    def error(received: list[np.ndarray], out: np.ndarray, dtype: str) -> float:
        reference = reference_matrix_fisher_log_normalizer(received[0])
        if len(received) > 1:  # the NLL: log c(F) - tr(F^T R)
            reference = reference - np.sum(received[0] * received[1], axis=(-2, -1))
        return table_error(OPS_BY_NAME[op_id], received, out, reference) / float(np.finfo(dtype).eps)

    return error


def _concentrations(op: Op) -> Callable[[str], tuple[np.ndarray, ...]]:
    """The Fisher rows' F = k R D at concentrations k = 0, 1e-12, 1e-6, 1e-2, 1e2, 1e4 (zero, vanishing,
    large), with D = I (equal singular values), diag(2, 1, -0.5), diag(1, 0, 0) and diag(1, 1, 0)
    (rank 1 and 2), R the identity, a half-turn and two generic rotations."""

    def make(dtype: str) -> tuple[np.ndarray, ...]:
        q = np.concatenate([_IDENTITIES[:1], _half_turns()[12:13], uniform_quaternions(2, seed=42)])
        xs = op.inputs(oracle_normalize(np.repeat(q, 24, axis=0)))
        k = np.tile(np.repeat([0.0, 1e-12, 1e-6, 1e-2, 1e2, 1e4], 4), len(q))
        diagonals = ([1.0, 1.0, 1.0], [2.0, 1.0, -0.5], [1.0, 0.0, 0.0], [1.0, 1.0, 0.0])
        d = np.tile(np.array([np.diag(v) for v in diagonals]), (6 * len(q), 1, 1))
        rotation = oracle_quaternion_to_matrix(oracle_normalize(np.repeat(q, 24, axis=0)))
        return (k[:, None, None] * rotation @ d, *xs[1:])

    return make


def _spline_inputs_at(op: Op, top: int, constant: bool) -> Callable[[str], tuple[np.ndarray, ...]]:
    """A spline row's inputs at every knot 0, 1, ..., ``top`` (segment boundaries and both ends of the
    parameter range) for generic controls, or (``constant``) at its usual parameters with every
    control rotation the first one (an SE(3) spline keeps its translations: a pure translation)."""

    def make(dtype: str) -> tuple[np.ndarray, ...]:
        q = uniform_quaternions(4 * (top + 1), seed=43)
        control, u = op.inputs(q)
        if constant:
            control = control.copy()
            if control.shape[-1] == 4 and control.ndim == 3:  # squad: keep the signs and norms
                norms = np.linalg.norm(control, axis=-1, keepdims=True)
                signs = np.sign(control[..., :1] * control[..., :1, :1])
                control = control[..., :1, :] * norms / norms[..., :1, :] * np.where(signs == 0, 1.0, signs)
            else:
                control[..., :3, :3] = control[..., :1, :3, :3]
            return control, u
        return control, np.tile(np.arange(top + 1.0), 4)

    return make


_SPLINE_TOPS = {"quaternion_squad": 5, "so3_bspline": 3, "se3_bspline": 3, "se3_bspline[split]": 3}
# se3_bspline's float64 oracle (scipy's 4x4 expm and logm) is itself ~10-20 ulp off (18.5 at the knots)
_SPLINE_ULPS = {"se3_bspline": 32.0}


_IGSO3_ANGLES = np.array([0.0, 1e-8, 1e-3, 0.5, 2.0, np.pi - 1e-6, np.pi])
_IGSO3_SIGMAS = np.array([1e-6, 1e-3, 1e-2, 0.1, 3.0, 30.0, 1e3, 1e5])


def _igso3_sigma_ends(op: Op) -> Callable[[str], tuple[np.ndarray, ...]]:
    """IGSO(3) at sigma's ends (1e-6 ... 1e-2: a point mass at the identity; 30 ... 1e5: the uniform law)
    and in between, at the angles 0, 1e-8, 1e-3, 0.5, 2, pi - 1e-6 and pi."""

    def make(dtype: str) -> tuple[np.ndarray, ...]:
        angle = np.tile(_IGSO3_ANGLES, len(_IGSO3_SIGMAS))
        sigma = np.repeat(_IGSO3_SIGMAS, len(_IGSO3_ANGLES))
        if op.id != "igso3_score":
            return angle, sigma
        q = axis_angle_quaternions(np.tile([[0.3, -0.5, 0.8]], (len(angle), 1)), angle)
        matrix, _, mean = op.inputs(q)
        return matrix, sigma, mean

    return make


def _fit_points(op: Op, kind: str) -> Callable[[str], tuple[np.ndarray, ...]]:
    """A fit's inputs with coplanar source points (z = 0: the cross-covariance has rank 2, the
    rotation is still unique) or with two source points and their targets repeated (coincident),
    at generic rotations and the half-turns."""

    def make(dtype: str) -> tuple[np.ndarray, ...]:
        q = np.concatenate([uniform_quaternions(8, seed=44), _half_turns()[::3]])
        source, target, *rest = (x.copy() for x in op.inputs(q))
        if kind == "coplanar":
            source[..., 2] = 0.0
        else:
            source[..., 1, :], target[..., 1, :] = source[..., 0, :], target[..., 0, :]
        return (source, target, *rest)

    return make


_FITS = ("fit_rotation", "fit_rotation-unweighted", "fit_rigid_transform", "fit_similarity_transform")


def _all_equal(op: Op) -> Callable[[str], tuple[np.ndarray, ...]]:
    """A mean's samples all one element (the first; quaternions keep their signs, which the mean
    ignores), at the identity, the half-turns, near them and generic rotations: the mean is that
    element."""

    def make(dtype: str) -> tuple[np.ndarray, ...]:
        q = np.concatenate(
            [_IDENTITIES, _half_turns()[::2], _near_half_turns()[::15], uniform_quaternions(4, seed=45)]
        )
        samples, weights = op.inputs(q)
        if samples.shape[-1] == 4 and samples.ndim == 3:  # quaternions (..., n, 4)
            signs = np.sign(np.sum(samples * samples[..., :1, :], axis=-1, keepdims=True))
            return samples[..., :1, :] * np.where(signs == 0, 1.0, signs), weights
        return np.broadcast_to(samples[..., :1, :, :], samples.shape).copy(), weights

    return make


def _all_equal_error(op_id: str) -> Callable[[list[np.ndarray], np.ndarray, str], float]:
    """Against the row's oracle; the L1 median's (Weiszfeld's, which divides by each distance) against
    the L2 geodesic mean's oracle: both are the common element."""
    if op_id != "rotation_mean[geodesic_l1]":
        return against_the_oracle(op_id)

    def error(received: list[np.ndarray], out: np.ndarray, dtype: str) -> float:
        expected = OPS_BY_NAME["rotation_mean[geodesic]"].expected(*received)
        return table_error(OPS_BY_NAME[op_id], received, out, expected) / float(np.finfo(dtype).eps)

    return error


_MEANS = (
    "rotation_mean[chordal]",
    "rotation_mean[geodesic]",
    "rotation_mean[geodesic_l1]",
    "quaternion_mean",
    "se3_mean",
)


def _at_rest(op: Op) -> Callable[[str], tuple[np.ndarray, ...]]:
    """A rate row at rest: its rates (q', q'', w) zero at the identity, the half-turns and generic
    rotations (the step dt as the row has it); a sequence of samples all the first (signs kept)."""

    def make(dtype: str) -> tuple[np.ndarray, ...]:
        q = np.concatenate([_IDENTITIES, _half_turns()[::2], uniform_quaternions(4, seed=46)])
        xs = [x.copy() for x in op.inputs(q)]
        if op.id == "angular_velocity_from_quaternions":
            samples = xs[0]
            signs = np.sign(np.sum(samples * samples[..., :1, :], axis=-1, keepdims=True))
            norms = np.linalg.norm(samples, axis=-1, keepdims=True)  # norms are ignored too: kept
            first = samples[..., :1, :] / norms[..., :1, :]
            return first * norms * np.where(signs == 0, 1.0, signs), xs[1]
        last = len(xs) - 1 if op.id.startswith("integrate_angular_velocity") else len(xs)
        for i in range(1, last):
            xs[i][...] = 0.0
        return tuple(xs)

    return make


_RATES = (
    "angular_velocity",
    "quaternion_derivative[space]",
    "angular_acceleration",
    "integrate_angular_velocity[space]",
    "angular_velocity_from_quaternions",
)


@functools.cache
def _mp_expm_times(t1: bytes, xi: bytes) -> bytes:
    """``T1 expm(hat(xi))`` by mpmath's expm at 40 digits (float64 bytes in and out)."""
    with mpmath.workdps(40):
        e = mpmath.expm(mpmath.matrix(se3_hat_of(np.frombuffer(xi)[None])[0].tolist()))
        out = mpmath.matrix(np.frombuffer(t1).reshape(4, 4).tolist()) * e
        return np.array(out.tolist(), dtype=np.float64).tobytes()


def se3_interpolate_error(received: list[np.ndarray], out: np.ndarray, dtype: str) -> float:
    """``T1 exp(t log(T1^-1 T2))`` with the log by the float64 oracle (the axis-angle closed form and a
    solve, a few ulps) and the exponential by mpmath at 40 digits: scipy's expm, the row's oracle, is
    itself up to 62 float64 ulps off near a half-turn (diffquat 4.5 from this reference)."""
    t1, t2, t = received
    xi = t[:, None] * oracle_se3_log(np.linalg.inv(t1) @ t2)
    expected = np.array(
        [
            np.frombuffer(_mp_expm_times(a.tobytes(), x.tobytes())).reshape(4, 4)
            for a, x in zip(t1, xi, strict=True)
        ]
    )
    return table_error(OPS_BY_NAME["se3_interpolate"], received, out, expected) / float(np.finfo(dtype).eps)


# Rows whose rotation configurations need more than the default (16 ulp, as ZERO_TRANSLATION_ULPS):
# the relative rotations of a pair or sequence at an exact half-turn (and at the locks, which hold
# half-turns) have two shortest paths (skipped),
# and near one in float32 only to 1e-3 (see _near_half_turns_for); Euler angles at a lock are measured
# by the rotation they make; the float64 bound of rows whose float64 oracle is itself a few ulps off.
_RELATIVE = {"skip": ("half_turns", "gimbal_lock"), "relative": True}
ROTATION_DEGENERATE: dict[str, dict[str, Any]] = {
    "quaternion_slerp": _RELATIVE,
    # against mpmath's expm of the oracle's log: scipy's expm is up to 62 float64 ulps off there
    "se3_interpolate": {**_RELATIVE, "error": se3_interpolate_error},
    "angular_velocity_from_quaternions": _RELATIVE,
    "quaternion_squad": _RELATIVE,
    "so3_bspline": _RELATIVE,
    # the float64 oracle takes scipy's logm of the relative poses, which loses ~1/delta near a
    # half-turn (1.9e8 ulp): no reference there, as the row's `applies` says
    # and at generic controls scipy's 4x4 expm / logm are themselves ~10-20 float64 ulp off (its
    # expm at t = 1 is 12 ulp from T2 in se3_interpolate): 32 ulp
    "se3_bspline": {"skip": ("half_turns", "gimbal_lock", "near_half_turns"), "ulps": 32.0},
    "se3_bspline[split]": _RELATIVE,
    # F = R: singular values (1, 1, 1), where the 24-node Talbot rule is 59 float64 ulps (of the
    # error scale 6) from mpmath's 20 digits (float32: 1.1): a limit of the rule, reported (issue 48)
    "matrix_fisher_log_normalizer": {
        "error": _fisher_reference("matrix_fisher_log_normalizer"),
        "ulps": 64.0,
    },
    "matrix_fisher_nll": {"error": _fisher_reference("matrix_fisher_nll")},
    "matrix_to_euler_angles[ZXZ]": {"error": euler_rotation_error(EULER_ROWS["matrix_to_euler_angles"])},
    "quaternion_to_euler_angles[xzx]": {
        "error": euler_rotation_error(EULER_ROWS["quaternion_to_euler_angles"])
    },
}
OPS = [
    op
    if op.degenerate
    else replace(op, degenerate=at_rotations(op, **{"ulps": 16.0, **ROTATION_DEGENERATE.get(op.id, {})}))
    for op in OPS
]
OPS = [
    replace(
        op,
        degenerate=(
            *op.degenerate,
            Degenerate("endpoints", _endpoint_inputs(op.inputs), endpoint_error, 16.0),
        ),
    )
    if op.id in ("quaternion_slerp", "se3_interpolate")
    else op
    for op in OPS
]
OPS = [
    replace(
        op,
        degenerate=(
            *op.degenerate,
            Degenerate("concentrations", _concentrations(op), _fisher_reference(op.id), 16.0),
        ),
    )
    if op.id in ("matrix_fisher_log_normalizer", "matrix_fisher_nll")
    else op
    for op in OPS
]
OPS = [
    replace(
        op,
        degenerate=(
            *op.degenerate,
            Degenerate(
                "knots",
                _spline_inputs_at(op, _SPLINE_TOPS[op.id], False),
                against_the_oracle(op.id),
                _SPLINE_ULPS.get(op.id, 16.0),
            ),
            Degenerate(
                "constant_rotation",
                _spline_inputs_at(op, _SPLINE_TOPS[op.id], True),
                against_the_oracle(op.id),
                _SPLINE_ULPS.get(op.id, 16.0),
            ),
        ),
    )
    if op.id in _SPLINE_TOPS
    else op
    for op in OPS
]
OPS = [
    replace(
        op,
        degenerate=(
            *op.degenerate,
            Degenerate("sigma_ends", _igso3_sigma_ends(op), against_the_oracle(op.id), 16.0),
        ),
    )
    if op.id in ("igso3_log_density", "igso3_angle_cdf", "igso3_score")
    else op
    for op in OPS
]
OPS = [
    replace(
        op,
        degenerate=(
            *op.degenerate,
            *(
                Degenerate(kind, _fit_points(op, kind), against_the_oracle(op.id), 16.0)
                for kind in ("coplanar", "coincident")
            ),
        ),
    )
    if op.id in _FITS
    else op
    for op in OPS
]
OPS = [
    replace(
        op,
        degenerate=(*op.degenerate, Degenerate("all_equal", _all_equal(op), _all_equal_error(op.id), 16.0)),
    )
    if op.id in _MEANS
    else op
    for op in OPS
]
OPS = [
    replace(
        op, degenerate=(*op.degenerate, Degenerate("at_rest", _at_rest(op), against_the_oracle(op.id), 16.0))
    )
    if op.id in _RATES
    else op
    for op in OPS
]
OPS_BY_NAME = {op.id: op for op in OPS}


def table_error(
    op: Op, received: Sequence[np.ndarray], actual: np.ndarray, expected: np.ndarray | None = None
) -> float:
    """Max abs error of ``actual`` (float64), what ``op`` gave for the float64 values ``received``,
    against ``expected`` (by default the oracle on ``received``), measured as the table measures it:
    angles modulo 2 pi (``periodic``), relative to the largest expected entry (``relative``) or to the
    size the op declares (``error_scale``), up to the sign where the sign is rounding's choice
    (``up_to_sign``)."""
    if expected is None:
        expected = op.expected(*received)
    actual = np.asarray(actual, np.float64)
    assert actual.shape == expected.shape
    if actual.size == 0:
        return 0.0
    if op.periodic:  # angles: pi and -pi are one angle
        actual = expected + (np.mod(actual - expected + np.pi, 2 * np.pi) - np.pi)
    # the other result at a jump, taken before any scaling (it is a function of the result itself)
    other = -actual if op.other_branch is None else op.other_branch(actual)
    scale = np.ones((*expected.shape[:-1], 1))
    if op.relative:  # per element, relative to the largest expected entry
        largest = np.abs(expected).max(axis=-1, keepdims=True)
        scale = np.where(largest > 0, largest, 1.0)
    if op.error_scale is not None:  # per element, relative to the size the op declares
        declared = op.error_scale(*received)
        scale = scale * np.reshape(declared, declared.shape + (1,) * (expected.ndim - declared.ndim))
    error = (np.abs(actual - expected) / scale).max(axis=-1)
    if op.up_to_sign:
        error = np.minimum(error, (np.abs(other - expected) / scale).max(axis=-1))
    return float(error.max())


def both_sides(op: Op) -> list[Op]:
    """``op`` and, for a row of a function with a ``side`` keyword, the same row on the other side
    (where a test compares two evaluations of one function, not the row's oracle, which is one
    side's)."""
    side = op.kwargs.get("side")
    if side is None:
        return [op]
    other = "right" if side == "left" else "left"
    return [op, replace(op, kwargs={**op.kwargs, "side": other}, label=op.id.replace(side, other))]


# Public names that are not rows of the table, with the test that covers each.
NOT_IN_TABLE = {
    "random_quaternions": "tests/test_random.py",
    "matrix_fisher_sample": "tests/test_fisher.py",
    "igso3_sample": "tests/test_igso3.py",
    "symmetry_group": "tests/test_statistics.py",
    "se3_to_rotation_translation": "tests/test_se3.py",
    # the objects: every method against its function over the table's cases
    "SO3": "tests/test_objects.py",
    "SE3": "tests/test_objects.py",
}


# ---------------------------------------------------------------------------------------------------
# Narrowing a table-driven test (read by conftest.pytest_generate_tests).


def only(
    op: Callable[[Op], bool] | None = None,
    backend: Callable[[str], bool] | None = None,
    dtype: Callable[[str], bool] | None = None,
    case: Callable[[Case], bool] | None = None,
    pair: Callable[[Op, Case], bool] | None = None,
) -> Callable[[Callable[..., Any]], Callable[..., Any]]:
    """Decorator: run a table-driven test only on the ops, backends, dtypes and cases that pass, and
    (``pair``) only on the (op, case) combinations that pass. Stacked decorators combine: every filter
    must pass."""
    axes = {"op": op, "backend": backend, "dtype": dtype, "case": case, "pair": pair}
    new = {k: v for k, v in axes.items() if v}

    def mark(fn: Callable[..., Any]) -> Callable[..., Any]:
        filters = dict(getattr(fn, "diffquat_filters", {}))
        for axis, keep in new.items():
            before = filters.get(axis)
            filters[axis] = keep if before is None else (lambda *v, a=before, b=keep: a(*v) and b(*v))
        fn.diffquat_filters = filters  # type: ignore[attr-defined]
        return fn

    return mark


gradients = only(backend=lambda b: b in ("torch", "jax"), dtype=lambda d: d == GRAD_DTYPE)
torch_only = only(backend=lambda b: b == "torch")
jax_only = only(backend=lambda b: b == "jax")
edge_cases = only(case=lambda c: c.name in EDGE_CASES)
# The compile-heavy derivative checks: on every row but the keyword variants (see Op.variant_of).
base_rows = only(op=lambda op: not op.variant_of)
# Where the op is differentiable (e.g. not where a rotation vector jumps at pi): for the numerical
# derivative checks (gradcheck, check_grads), which cannot pass across a jump.
smooth = only(pair=lambda op, case: op.smooth_at(case))


# The backends' dtypes as NumPy dtypes, and the cast every test makes on the host.
HOST_DTYPES = {
    "float64": np.float64,
    "float32": np.float32,
    "float16": np.float16,
    "bfloat16": ml_dtypes.bfloat16,
}


def host_cast(x: np.ndarray, dtype: Any) -> np.ndarray:
    with np.errstate(over="ignore"):  # beyond the dtype's range: inf, as every backend's cast gives
        return x.astype(np.dtype(dtype))


def concatenate_cases(
    cases: list[Case], batch_of: Callable[[Case], tuple[int, ...]], inputs: Callable[[Case], list[np.ndarray]]
) -> tuple[list[np.ndarray], list[tuple[Case, slice, tuple[int, ...]]]]:
    """The ``inputs`` of every case, flattened to one batch dimension and concatenated (rows are
    independent, so one call evaluates an op at every case), with each case's rows and batch shape."""
    parts, rows, start = [], [], 0
    for case in cases:
        batch = batch_of(case)
        parts.append([x.reshape(-1, *x.shape[len(batch) :]) for x in inputs(case)])
        rows.append((case, slice(start, start + int(np.prod(batch))), batch))
        start = rows[-1][1].stop
    return [np.concatenate(p) for p in zip(*parts, strict=True)], rows


def value_batches(op: Op, dtype: str) -> tuple[list[np.ndarray], list[tuple[Case, slice, tuple[int, ...]]]]:
    """:func:`concatenate_cases` of the op's float64 inputs at every value case but the batch_* ones
    (whose point is their shape), cast to ``dtype`` and back."""
    return concatenate_cases(
        [c for c in CASES if not c.name.startswith("batch_") and op.applies(c)],
        lambda c: c.quaternions(dtype).shape[:-1],
        lambda c: [
            host_cast(x, HOST_DTYPES[dtype]).astype(np.float64) for x in op.inputs(c.quaternions(dtype))
        ],
    )
