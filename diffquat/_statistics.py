"""Rotation averaging and symmetric objects, over ``xp``: means of rotations (chordal, geodesic L2 and
geodesic L1), Markley's quaternion mean, the rotation groups of symmetric objects, and the distance
between two orientations of a symmetric object.

The geodesic means are the solutions of a stationarity equation, found by a fixed number of iterations
(no data-dependent loop, so they trace under every compiler and transform) and differentiated by the
implicit function theorem, not through the iterations: :func:`karcher_mean` and :func:`geodesic_median`
are the maps that the backends register with their derivative rules (``karcher_tangent`` /
``karcher_cotangent``, ``median_tangent`` / ``median_cotangent``, in the form of
``diffquat/torch/_custom.py`` and ``diffquat/jax/_custom.py``).

Everything is computed on unit quaternions, scalar first. The derivative formulas take the logarithm
of SO(3) with ``quaternion_to_axis_angle``'s series at the identity (:func:`_logs`: smooth to every
order below a half-turn) and the inverse Jacobians of SO(3), both written here, privately
(:func:`_jacobian_inverse`; the library's Lie functions have the same maps under their own names).
The forward iterations, which are never differentiated, take leaner forms of the logarithm and the
exponential (:func:`_forward_logs`, :func:`_exp_right`): fewer operations for the compilers that
trace them.

Conventions of the derivations: a rotation ``q`` moves as ``q exp(e)`` (a right perturbation, ``e``
in the body frame), and ``log(exp(v) exp(d)) = v + Jr^-1(v) d``, ``log(exp(-e) exp(v)) = v - Jl^-1(v) e``
to first order, with ``Jr^-1(v) = I + hat(v) / 2 + c(|v|) hat(v)^2``, ``Jl^-1(v) = Jr^-1(v)^T = Jr^-1(-v)``
and ``c(t) = (1 - (t / 2) cot(t / 2)) / t^2``.
"""

from __future__ import annotations

import functools
import re
from collections.abc import Callable
from typing import Any, NamedTuple

import numpy as np

from ._algebra import (
    hamilton,
    match_rank,
    quaternion_conjugate_eager,
    quaternion_multiply_eager,
    series_threshold,
)
from ._algebra import matrix_geodesic_distance as _matrix_geodesic_distance
from ._core import (
    canonical,
    constants,
    eager_form,
    join_quaternion,
    matrix_to_quaternion,
    normalize_quaternion,
    normalize_quaternion_eager,
    op,
    quaternion_to_matrix,
    split_quaternion,
    stack_matrix,
    standardize_quaternion,
    standardize_quaternion_eager,
    wxyz_to_xyzw,
)
from ._representations import (
    _transpose,
    smallest_eigenvector,
    special_procrustes,
    symmetric_matrix_to_quaternion,
    upper_entries,
)
from ._types import MeanMethod

METHODS: tuple[str, ...] = ("chordal", "geodesic", "geodesic_l1")

# Newton steps of the Karcher mean, from the chordal mean. Measured (float64, 2 to 12 samples skewed
# to one side, weights from uniform(0, 1)^4, up to 1e-3 ... 1.55 rad from their centre, 10^4 sets per
# radius): the largest entry of the residual sum_i w_i log(q* q_i) (weights summing to 1) is at most
# 0.5 at the chordal mean, then at most 8e-4, 8e-9 and 5e-16 after one, two and three steps (1.55
# rad): quadratic, e_{k+1} <= C e_k^2 with C <= 0.02. Three steps reach rounding; the fourth is
# margin. Plain Riemannian gradient steps contract linearly, by up to 0.35 per step there (a dozen
# steps for 1e-12).
KARCHER_STEPS = 4
# Iterations of the geodesic median (each a Newton step, a vertex step and Weiszfeld's step, the best
# kept; see geodesic_median). Measured with the distance to the median that Newton's step estimates
# (|B^-1 G|, 0 at a sample that is the median), relative to the cluster's radius: float64, 3 to 30
# samples up to 1e-3, 0.3 or 1.5 rad from their centre, 6000 sets per line: equal weights, weights
# from uniform(0.1, 1), and equal weights with a quarter of outliers 0.5-2.5 rad away end at rounding
# (1e-16 to 1e-15 of the radius, 2e-13 of a radius of 1e-3 rad: 2e-16 rad) on 99.9% of the sets and
# within 1e-7 of the radius on 99.99% (the outliers around a tight cluster need the 12: 2e-4 after
# 10). Weights of very different sizes (uniform(0.1, 1)^3) leave about one set in 3000 short, by up to
# 4% of the radius: two heavy samples close to the median make its objective a double cone, where
# Newton's step fails and Weiszfeld's crawls. Near a sample the residual |sum_i w_i n_i| itself is
# ill-conditioned (the unit vector towards a sample 1e-8 rad away): it is not the measure.
MEDIAN_STEPS = 12


# ---------------------------------------------------------------------------------------------------
# Small helpers.


def _dot(xp: Any, a: Any, b: Any) -> Any:
    return xp.sum(a * b, axis=-1)


def _cross(xp: Any, a: Any, b: Any) -> Any:
    a0, a1, a2 = a[..., 0], a[..., 1], a[..., 2]
    b0, b1, b2 = b[..., 0], b[..., 1], b[..., 2]
    return xp.stack([a1 * b2 - a2 * b1, a2 * b0 - a0 * b2, a0 * b1 - a1 * b0], axis=-1)


def _solve3(xp: Any, a: Any, b: Any) -> Any:
    """``a^-1 b`` for ``a`` (..., 3, 3) and ``b`` (..., 3), by the adjugate (Cramer's rule): elementwise
    arithmetic, no LAPACK call (torch's ``linalg.inv`` raises on a singular batch element; the callers
    bound ``a`` away from singular, see :func:`_floored`), and differentiable to every order."""
    c0, c1, c2 = a[..., :, 0], a[..., :, 1], a[..., :, 2]
    k0, k1, k2 = _cross(xp, c1, c2), _cross(xp, c2, c0), _cross(xp, c0, c1)
    det = _dot(xp, c0, k0)
    return xp.stack([_dot(xp, k0, b), _dot(xp, k1, b), _dot(xp, k2, b)], axis=-1) / det[..., None]


def _solve3_transposed(xp: Any, a: Any, b: Any) -> Any:
    """``a^-T b`` (see :func:`_solve3`)."""
    return _solve3(xp, _transpose(xp, a), b)


def _diagonal(xp: Any, a: Any, lam: Any) -> Any:
    """``a + lam I`` for ``a`` (..., 3, 3) and ``lam`` (...)."""
    e = [a[..., i, j] + lam if i == j else a[..., i, j] for i in range(3) for j in range(3)]
    return stack_matrix(xp, e)


def _hat_plus(xp: Any, s: Any, z: Any, outer: Any) -> Any:
    """``s I + hat(z) + outer`` for ``s`` (...), ``z`` (..., 3) and ``outer`` (..., 3, 3)."""
    z0, z1, z2 = z[..., 0], z[..., 1], z[..., 2]
    hat = [s, -z2, z1, z2, s, -z0, -z1, z0, s]  # hat(z), with s on the diagonal
    return stack_matrix(xp, [outer[..., k // 3, k % 3] + h for k, h in enumerate(hat)])


def _floored(xp: Any, a: Any) -> Any:
    """``a + lam I``, ``lam >= 0`` raising the smallest eigenvalue of ``a``'s symmetric part ``s`` to at
    least ``sqrt(eps) tr(s)`` where it may be below: a linear system whose solution is a derivative
    stays bounded where the median is not unique, and is exact everywhere else.

    The matrices here have a positive semidefinite symmetric part (a weighted sum of projections), so
    ``4 det(s) / tr(s)^2 <= l_min(s)`` (with ``l1 <= l2 <= l3``: ``l1 l2 l3 / (l1 + l2 + l3)^2 <=
    l1 l2 l3 / (4 l2 l3)``) bounds the smallest eigenvalue from below without an eigendecomposition;
    ``lam = max(0, sqrt(eps) tr(s) - 4 det(s) / tr(s)^2)`` is 0 unless ``s`` is within ``sqrt(eps)`` of
    singular, and it is continuous. The skew part only helps: ``x^T a x = x^T s x``. Where ``tr(s)`` is
    0 (all weights 0), ``lam = 1``."""
    info = xp.finfo(a.dtype)
    s = 0.5 * (a + _transpose(xp, a))
    trace = s[..., 0, 0] + s[..., 1, 1] + s[..., 2, 2]
    det = _det3(xp, s)
    positive = trace > info.tiny**0.5
    safe = xp.where(positive, trace, 1.0)
    lam = info.eps**0.5 * trace - 4.0 * det / (safe * safe)
    lam = xp.where(lam > 0, lam, 0.0)
    return _diagonal(xp, a, xp.where(positive, lam, 1.0))


def _det3(xp: Any, a: Any) -> Any:
    return _dot(xp, a[..., :, 0], _cross(xp, a[..., :, 1], a[..., :, 2]))


def _first(xp: Any, chosen: Any) -> Any:
    """The first True of ``chosen`` along the last axis, as a boolean mask (all False where none)."""
    count = xp.cumsum(xp.where(chosen, 1, 0), -1)
    return chosen & (count == 1)


def _first_minimum(xp: Any, values: Any, ulps: float = 0.0) -> Any:
    """Mask (..., N) of the first entry within ``ulps`` units in the last place of ``max(1, minimum)``
    of the minimum along the last axis."""
    smallest = xp.amin(values, axis=-1, keepdims=True)
    tolerance = ulps * float(xp.finfo(values.dtype).eps) * xp.where(smallest > 1, smallest, 1.0)
    return _first(xp, values <= smallest + tolerance)


def _pick(xp: Any, mask: Any, x: Any) -> Any:
    """The row of ``x`` (..., N, k) where the one-hot ``mask`` (..., N) is True: (..., k)."""
    return xp.sum(xp.where(mask[..., None], x, 0.0), axis=-2)


def repeat(xp: Any, count: int, step: Callable[[Any], Any], state: Any) -> Any:
    """``step`` applied ``count`` times (a number fixed in advance, never read from the data) to
    ``state``. A Python loop, except where the namespace has ``diffquat_repeat`` (jax's runs
    ``lax.fori_loop``): XLA then compiles the step once instead of ``count`` unrolled copies
    (docs/performance.md, Formula shapes)."""
    loop = getattr(xp, "diffquat_repeat", None)
    if loop is not None:
        return loop(count, step, state)
    for _ in range(count):
        state = step(state)
    return state


def _unit(xp: Any, q: Any) -> Any:
    return q / xp.sqrt(xp.sum(q * q, axis=-1, keepdims=True))


def _identity_quaternion(xp: Any, like: Any) -> Any:
    """The identity quaternion (scalar first) with the batch shape of ``like`` (..., k)."""
    one = xp.ones_like(like[..., 0])
    nil = xp.zeros_like(one)
    return xp.stack([one, nil, nil, nil], axis=-1)


# ---------------------------------------------------------------------------------------------------
# The quantities of a rotation q relative to samples q_i, written for the forward iterations.


def _relative(xp: Any, y: Any, u: Any) -> tuple[Any, Any, Any]:
    """For a unit quaternion ``y`` (..., 4) and quaternions ``u`` (..., N, 4) of any non-zero norm
    (scalar first): ``r = y* u_i`` as ``(cos, sin, axis)`` of the half angle, the sign of ``r`` chosen so
    that ``cos >= 0`` (the shortest rotation, angle in [0, pi]): ``cos`` and ``sin`` (..., N) scaled by
    ``|u_i|``, ``axis`` (..., N, 3) = ``sin * unit axis`` (0 at the identity)."""
    yw, yx, yy, yz = split_quaternion(y[..., None, :], True)
    rw, rx, ry, rz = hamilton((yw, -yx, -yy, -yz), split_quaternion(u, True))
    axis = xp.stack([rx, ry, rz], axis=-1)
    axis = xp.where((rw < 0)[..., None], -axis, axis)
    return xp.abs(rw), xp.sqrt(rx * rx + ry * ry + rz * rz), axis


def _forward_logs(xp: Any, y: Any, u: Any) -> tuple[Any, Any]:
    """``log(y* u_i)`` (..., N, 3) and its angle (..., N) in [0, pi], for the forward iterations, whose
    derivative is never taken (the implicit derivatives replace it): ``axis * angle / sin``, and
    ``2 axis / cos`` at the identity (a limit, exact there)."""
    cos, sin, axis = _relative(xp, y, u)
    angle = 2.0 * xp.atan2(sin, cos)
    positive = sin > 0
    k = xp.where(positive, angle / xp.where(positive, sin, 1.0), 2.0 / xp.where(cos > 0, cos, 1.0))
    return axis * k[..., None], angle


def _exp_right(xp: Any, y: Any, e: Any) -> Any:
    """``y exp(e)``: the rotation ``y`` (..., 4) moved by ``e`` (..., 3) in its own frame, renormalised
    (for the forward iterations: no series, ``sin(t / 2) / t`` has no cancellation)."""
    t = xp.sqrt(_dot(xp, e, e))
    half = 0.5 * t
    positive = t > 0
    k = xp.where(positive, xp.sin(half) / xp.where(positive, t, 1.0), 0.5)
    step = (xp.cos(half), k * e[..., 0], k * e[..., 1], k * e[..., 2])
    return _unit(xp, join_quaternion(xp, *hamilton(split_quaternion(y, True), step), True))


def _chordal_quaternion(xp: Any, u: Any, w: Any, eigenvector: Callable[[Any, Any], Any]) -> Any:
    """Markley's mean (scalar first): the eigenvector of the largest eigenvalue of ``sum_i w_i u_i u_i^T``
    for unit ``u_i`` (..., N, 4), i.e. of the smallest of its negative, which is what
    :func:`diffquat._representations.symmetric_matrix_to_quaternion` computes (with its derivative,
    where ``eigenvector`` is the backend's). Equal to the chordal mean of the rotations:
    ``|R(p) - R(q)|_F^2 = 8 (1 - (p . q)^2)``. Weights summing to zero give the identity."""
    k = xp.matmul(_transpose(xp, u * w[..., None]), u)  # (..., 4, 4): one product, not ten sums
    a = xp.stack([-k[..., i, j] for i in range(4) for j in range(i, 4)], axis=-1)
    q: Any = symmetric_matrix_to_quaternion(xp, a, scalar_first=True, eigenvector=eigenvector)
    return q


def _weights(xp: Any, x: Any) -> tuple[Any, Any, Any]:
    """Quaternions ``u`` (..., N, 4), weights normalised to sum 1 (..., N), and whether the total is
    positive (...), from the packed input ``x`` (..., N, 5) of the geodesic means."""
    u, omega = x[..., :4], x[..., 4]
    total = xp.sum(omega, axis=-1, keepdims=True)
    positive = total > xp.finfo(x.dtype).tiny
    w = omega / xp.where(positive, total, 1.0)
    return u, w, positive[..., 0]


def _finish(xp: Any, y: Any, positive: Any) -> Any:
    """The documented result where the weights sum to zero (the identity), in canonical sign."""
    y = xp.where(positive[..., None], y, _identity_quaternion(xp, y))
    return standardize_quaternion(xp, y, scalar_first=True)


# ---------------------------------------------------------------------------------------------------
# The inverse Jacobians of SO(3).


def _c_series_threshold(xp: Any, dtype: Any) -> float:
    """Below this ``t^2``, :func:`_c` takes its series. The closed form ``(1 - (t / 2) cot(t / 2)) / t^2``
    loses ``12 eps / t^2`` relative to cancellation, the series through ``t^6`` has a relative error of
    ``12 t^8 / 47900160``; they meet at ``t^2 = (2e8 eps)^(1/5)``: 0.034 in float64 (both errors ~3e-13,
    on a term of size ``c t^2 ~ t^2 / 12``: ~1e-15 absolute) and 1.9 in float32 (~3e-6, ~5e-7 absolute)."""
    return float((2e8 * float(xp.finfo(dtype).eps)) ** 0.2)


def _c(xp: Any, t2: Any) -> Any:
    """``c(t) = (1 - (t / 2) cot(t / 2)) / t^2`` as a function of ``t^2`` (smooth at 0), for ``t`` in
    [0, pi]: the coefficient of ``hat(v)^2`` in the inverse Jacobians. Series
    ``1/12 + t^2/720 + t^4/30240 + t^6/1209600`` below :func:`_c_series_threshold`; each branch sees a
    safe argument where it is discarded."""
    small = t2 < _c_series_threshold(xp, t2.dtype)
    s = xp.where(small, t2, 0.0)
    series = 1.0 / 12.0 + s * (1.0 / 720.0 + s * (1.0 / 30240.0 + s / 1209600.0))
    big = xp.where(small, 1.0, t2)
    half = 0.5 * xp.sqrt(big)
    closed = (1.0 - half * xp.cos(half) / xp.sin(half)) / big
    return xp.where(small, series, closed)


def _weighted_left_inverse(xp: Any, w: Any, v: Any, c: Any, t2: Any) -> tuple[Any, Any]:
    """``sum_i w_i Jl^-1(v_i)`` (..., 3, 3) for weights (..., N), ``v`` (..., N, 3), ``c = c(|v|)`` and
    ``t2 = |v|^2`` (..., N), by ``hat(v)^2 = v v^T - |v|^2 I``: ``(sum w - sum w c |v|^2) I -
    hat(sum w v) / 2 + sum w c v v^T``; and that diagonal term ``sum_i w_i (1 - c_i t_i^2)`` (...)."""
    wc = w * c
    diagonal = xp.sum(w - wc * t2, axis=-1)
    outer = xp.matmul(_transpose(xp, v * wc[..., None]), v)
    return _hat_plus(xp, diagonal, -0.5 * xp.sum(w[..., None] * v, axis=-2), outer), diagonal


def _jacobian_inverse(xp: Any, v: Any, c: Any, x: Any, right: bool) -> Any:
    """``Jr^-1(v) x`` (``right``) or ``Jl^-1(v) x`` for ``v``, ``x`` (..., 3) and ``c = c(|v|)`` (...):
    ``x +- hat(v) x / 2 + c hat(v)^2 x``, without forming the matrix."""
    vx = _cross(xp, v, x)
    return x + (0.5 if right else -0.5) * vx + c[..., None] * _cross(xp, v, vx)


# ---------------------------------------------------------------------------------------------------
# The Karcher (geodesic L2) mean.


def _logs(xp: Any, y: Any, u: Any) -> Any:
    """``log(y* u_i)`` (..., N, 3) for the derivative formulas, angle in [0, pi] (the sign of ``y* u_i``
    with ``w >= 0``: blind to the signs): ``2 atan2(s, w) / s`` times the vector part, with
    ``quaternion_to_axis_angle``'s series in ``s^2 / w^2`` at the identity, so that it is smooth (to
    every order) wherever the angle is below pi. Without that function's zero-quaternion and
    ``w = 0`` rules, which products of unit quaternions never need: a third fewer operations to
    trace and compile."""
    yw, yx, yy, yz = split_quaternion(y[..., None, :], True)
    rw, rx, ry, rz = hamilton((yw, -yx, -yy, -yz), split_quaternion(u, True))
    flip = rw < 0
    w = xp.where(flip, -rw, rw)
    vector = xp.stack([rx, ry, rz], axis=-1)
    s2 = rx * rx + ry * ry + rz * rz
    small = s2 < series_threshold(xp, s2.dtype) * (w * w)
    r2 = xp.where(small, s2 / xp.where(small, w * w, 1.0), 0.0)
    series = (2.0 / xp.where(small, w, 1.0)) * (1.0 - r2 / 3.0 + r2 * r2 / 5.0)
    s = xp.sqrt(xp.where(small, 1.0, s2))
    k = xp.where(small, series, 2.0 * xp.atan2(s, w) / s)
    return xp.where(flip[..., None], -vector, vector) * k[..., None]


def mean_shape(shape: tuple[int, ...]) -> tuple[int, ...]:
    """The shape of :func:`karcher_mean`'s and :func:`geodesic_median`'s result for an input of
    shape ``(..., N, 5)``: ``(..., 4)``."""
    return (*shape[:-2], 4)


def karcher_mean(xp: Any, x: Any, *, eigenvector: Callable[[Any, Any], Any] = smallest_eigenvector) -> Any:
    """The Karcher mean (scalar first, canonical) of quaternions ``x[..., :4]`` (..., N, 4, any
    non-zero norm) with weights ``x[..., 4]`` (..., N): the rotation ``q`` where ``sum_i w_i log(q* q_i)
    = 0``. :data:`KARCHER_STEPS` Newton steps ``q <- q exp(A^-1 sum_i w_i v_i)``, ``v_i = log(q* q_i)``,
    ``A = sum_i w_i Jl^-1(v_i)`` (the derivative of the residual), from Markley's mean."""
    u, w, positive = _weights(xp, x)
    # A + lift I: the identity where the weights sum to zero (A = 0), and bounded steps where A is
    # singular (samples a half-turn from q). A lift changes the step, never the fixed point (g = 0).
    one = xp.ones_like(w[..., 0])  # an array: a NumPy where of two Python numbers would be float64
    lift = xp.where(positive, float(xp.finfo(x.dtype).eps) ** 0.5 * one, one)

    def newton(y: Any) -> Any:
        v, angle = _forward_logs(xp, y, u)
        g = xp.sum(w[..., None] * v, axis=-2)
        t2 = angle * angle
        a, _ = _weighted_left_inverse(xp, w, v, _c(xp, t2), t2)
        return _exp_right(xp, y, _solve3(xp, _diagonal(xp, a, lift), g))

    y = repeat(xp, KARCHER_STEPS, newton, _chordal_quaternion(xp, _unit(xp, u), w, eigenvector))
    return _finish(xp, y, positive)


def _right_perturbations(xp: Any, u: Any, du: Any) -> Any:
    """``d_i = 2 vec(u_i* du_i) / |u_i|^2`` (..., N, 3): the tangent ``du_i`` of a quaternion as the
    rotation vector of ``u_i^-1 (u_i + du_i)`` to first order (its radial part changes no rotation)."""
    uw, ux, uy, uz = split_quaternion(u, True)
    _, dx, dy, dz = hamilton((uw, -ux, -uy, -uz), split_quaternion(du, True))
    scale = 2.0 / xp.sum(u * u, axis=-1, keepdims=True)
    return xp.stack([dx, dy, dz], axis=-1) * scale


def _right_perturbations_transposed(xp: Any, u: Any, g: Any) -> Any:
    """The adjoint of :func:`_right_perturbations`: ``dL/du_i = 2 u_i (0, g_i) / |u_i|^2``."""
    nil = xp.zeros_like(g[..., 0])
    pure = (nil, g[..., 0], g[..., 1], g[..., 2])
    out = join_quaternion(xp, *hamilton(split_quaternion(u, True), pure), True)
    return out * (2.0 / xp.sum(u * u, axis=-1, keepdims=True))


def _tangent_of_rotation(xp: Any, y: Any, e: Any) -> Any:
    """``dy = y (0, e / 2)`` for the unit quaternion ``y``: the tangent of ``y exp(e)`` at ``e = 0``."""
    nil = xp.zeros_like(e[..., 0])
    return join_quaternion(
        xp, *hamilton(split_quaternion(y, True), (nil, *(0.5 * e[..., k] for k in range(3)))), True
    )


def _rotation_of_cotangent(xp: Any, y: Any, gy: Any) -> Any:
    """The adjoint of :func:`_tangent_of_rotation`: ``dL/de = vec(y* gy) / 2``."""
    yw, yx, yy, yz = split_quaternion(y, True)
    _, gx, gy_, gz = hamilton((yw, -yx, -yy, -yz), split_quaternion(gy, True))
    return 0.5 * xp.stack([gx, gy_, gz], axis=-1)


def _karcher_system(xp: Any, x: Any, y: Any) -> tuple[Any, Any, Any, Any, Any, Any]:
    """The pieces of the implicit derivative of the Karcher mean at its solution ``y``: quaternions,
    normalised weights, logs ``v_i``, ``c(|v_i|)``, the total weight (1 where it is zero) and
    ``A = sum_i w_i Jl^-1(v_i)``, lifted where it is near singular.

    The lift: ``Jl^-1(v)``'s symmetric part has eigenvalues 1 (along ``v``) and ``k = (t / 2) cot(t /
    2) = 1 - c t^2`` (across), so ``m = sum_i w_i k_i`` (which A's diagonal term already is) bounds
    the smallest eigenvalue of A's from below; ``A + max(0, sqrt(eps) - m) I`` is A itself unless
    ``m < sqrt(eps)`` (samples within ~sqrt(eps) of a half-turn from the mean, where it is not
    unique), and there bounds the derivative. Weights summing to zero: ``A + I``."""
    u, omega = x[..., :4], x[..., 4]
    total = xp.sum(omega, axis=-1, keepdims=True)
    positive = total > xp.finfo(x.dtype).tiny
    total = xp.where(positive, total, 1.0)
    w = omega / total
    v = _logs(xp, y, u)
    t2 = _dot(xp, v, v)
    c = _c(xp, t2)
    a, diagonal = _weighted_left_inverse(xp, w, v, c, t2)
    floor = float(xp.finfo(x.dtype).eps) ** 0.5
    lift = xp.where(positive[..., 0], xp.where(diagonal < floor, floor - diagonal, 0.0), 1.0)
    return u, w, v, c, total, _diagonal(xp, a, lift)


def karcher_tangent(xp: Any, x: Any, y: Any, dx: Any) -> Any:
    """Forward-mode derivative of :func:`karcher_mean` by the implicit function theorem.

    With ``q_i -> q_i exp(d_i)`` and ``q -> q exp(e)``, ``v_i = log(q* q_i)`` moves by
    ``Jr^-1(v_i) d_i - Jl^-1(v_i) e``; keeping ``sum_i w_i v_i = 0`` (``w_i = omega_i / sum omega``):
    ``A e = sum_i w_i Jr^-1(v_i) d_i + sum_i d(omega_i) v_i / sum omega`` (the term in ``d(sum omega)``
    multiplies ``sum_i w_i v_i = 0``). Exact on the solutions, so differentiating this formula again
    (through ``y``, whose derivative is this map) gives the second derivative."""
    u, w, v, c, total, a = _karcher_system(xp, x, y)
    d = _right_perturbations(xp, u, dx[..., :4])
    b = xp.sum(w[..., None] * _jacobian_inverse(xp, v, c, d, right=True), axis=-2)
    b = b + xp.sum(dx[..., 4:5] * v, axis=-2) / total
    return _tangent_of_rotation(xp, y, _solve3(xp, a, b))


class _Pieces(NamedTuple):
    """The products the means' reverse rules are made of: componentwise (``_COMPONENTWISE``, for the
    compilers and jax) or vectorised (``_EAGER``, eager torch); every selection is read from the same
    componentwise quantities either way."""

    cross: Callable[..., Any]
    rotation_of_cotangent: Callable[..., Any]
    right_perturbations_transposed: Callable[..., Any]
    jacobian_inverse: Callable[..., Any]
    solve3_transposed: Callable[..., Any]


def karcher_cotangent(xp: Any, x: Any, y: Any, gy: Any, pieces: _Pieces | None = None) -> Any:
    """Reverse-mode derivative of :func:`karcher_mean`: the transpose of :func:`karcher_tangent`
    (``Jr^-1(v)^T = Jl^-1(v)``)."""
    p = pieces or _COMPONENTWISE
    u, w, v, c, total, a = _karcher_system(xp, x, y)
    gb = p.solve3_transposed(xp, a, p.rotation_of_cotangent(xp, y, gy))[..., None, :]
    gd = w[..., None] * p.jacobian_inverse(xp, v, c, xp.broadcast_to(gb, v.shape), right=False)
    gomega = xp.sum(v * gb, axis=-1, keepdims=True) / total[..., None]
    return xp.concat([p.right_perturbations_transposed(xp, u, gd), gomega], axis=-1)


# ---------------------------------------------------------------------------------------------------
# The geodesic median (L1), by Weiszfeld's, Newton's and vertex steps.


def _coincident(xp: Any, dtype: Any) -> float:
    """Samples within this angle of the current rotation count as at it: 64 ulps of 1, a few times
    the rounding of an angle computed from a product of unit quaternions (an exact duplicate gives 0)."""
    return 64.0 * float(xp.finfo(dtype).eps)


class _Sweep:
    """The median's objective and its derivatives at a unit quaternion ``y`` (..., 4), for samples
    ``u`` (..., N, 4) and weights ``w`` (..., N) summing to 1 (forward iterations only). Samples within
    :func:`_coincident` of ``y`` are at ``y``: their total weight is ``eta``; the others give the
    gradient ``g = sum_i w_i n_i`` (``n_i`` the unit vector of ``log(y* q_i)``, ``t_i`` its length) and
    ``a_i = w_i cot(t_i / 2)``."""

    def __init__(self, xp: Any, y: Any, u: Any, w: Any) -> None:
        cos, sin, axis = _relative(xp, y, u)
        self.xp = xp
        self.angle = 2.0 * xp.atan2(sin, cos)
        at = self.angle <= _coincident(xp, y.dtype)
        safe = xp.where(at, 1.0, sin)
        self.n = axis / safe[..., None]
        self.wr = xp.where(at, 0.0, w)
        self.a = self.wr * (cos / safe)
        self.f = xp.sum(w * self.angle, axis=-1)
        self.eta = xp.sum(xp.where(at, w, 0.0), axis=-1)
        self.g = xp.sum(self.wr[..., None] * self.n, axis=-2)
        self.r = xp.sqrt(_dot(xp, self.g, self.g))
        self.safe_angle = xp.where(at, 1.0, self.angle)

    @property
    def dominant(self) -> Any:
        """Whether ``y`` is the median: the samples at it outweigh the pull of the others."""
        return self.r <= self.eta

    def newton_step(self) -> Any:
        """``B^-1 g`` with ``B = sum_i a_i (I - n_i n_i^T) / 2 - hat(g) / 2``, the derivative of the
        residual ``sum_i w_i n_i`` (see :func:`median_tangent`), lifted by ``sqrt(eps) (tr B + 1)``:
        where the samples lie on one geodesic through ``y``, ``B`` is singular, and the objective's
        comparison rejects the step anyway."""
        xp = self.xp
        total = xp.sum(self.a, axis=-1)
        outer = xp.matmul(_transpose(xp, self.n * self.a[..., None]), self.n)
        b = _hat_plus(xp, 0.5 * total, -0.5 * self.g, -0.5 * outer)
        lift = float(xp.finfo(b.dtype).eps) ** 0.5 * (total + 1.0)
        return _solve3(xp, _diagonal(xp, b, lift), self.g)

    def weiszfeld_step(self) -> Any:
        """Weiszfeld's step ``g / sum_i (w_i / t_i)``, shortened by Vardi and Zhang's ``max(0, 1 - eta /
        |g|)`` so that it also leaves a sample that is not the median."""
        xp = self.xp
        inverse = xp.sum(self.wr / self.safe_angle, axis=-1)
        shrink = xp.where(self.r > self.eta, 1.0 - self.eta / xp.where(self.r > 0, self.r, 1.0), 0.0)
        return self.g * (shrink / xp.where(inverse > 0, inverse, 1.0))[..., None]

    def curvature(self, d: Any) -> Any:
        """``d^T B d = sum_i a_i (1 - (n_i . d)^2) / 2`` for a unit vector ``d``."""
        nd = _dot(self.xp, self.n, d[..., None, :])
        return 0.5 * self.xp.sum(self.a * (1.0 - nd * nd), axis=-1)


def _objective(xp: Any, y: Any, u: Any, w: Any) -> Any:
    cos, sin, _ = _relative(xp, y, u)
    return xp.sum(w * 2.0 * xp.atan2(sin, cos), axis=-1)


def _vertex_step(xp: Any, vertex: Any, u: Any, w: Any) -> Any:
    """From a sample ``vertex``: itself if it is the median, else the minimum of the objective's model
    along the direction of steepest descent, ``t = (|G| - eta) / (g^T B g)`` (the cone of the samples at
    the vertex is linear along a ray, the rest quadratic): where the median is close to a sample,
    Newton's step from elsewhere overshoots the cone and Weiszfeld's crawls, and this lands near it."""
    s = _Sweep(xp, vertex, u, w)
    direction = s.g / xp.where(s.r > 0, s.r, 1.0)[..., None]
    curvature = s.curvature(direction)
    t = xp.where(s.dominant | ~(curvature > 0), 0.0, (s.r - s.eta) / xp.where(curvature > 0, curvature, 1.0))
    return _exp_right(xp, vertex, direction * t[..., None])


def geodesic_median(xp: Any, x: Any, *, eigenvector: Callable[[Any, Any], Any] = smallest_eigenvector) -> Any:
    """The geodesic median (scalar first, canonical) of quaternions ``x[..., :4]`` (..., N, 4, any
    non-zero norm) with weights ``x[..., 4]`` (..., N): the rotation minimising ``sum_i w_i
    |log(q* q_i)|``.

    From Markley's mean, :data:`MEDIAN_STEPS` iterations, each keeping the better of a Newton step on
    the residual ``sum_i w_i n_i = 0`` and a vertex step (:func:`_vertex_step`) if it does not raise
    the objective (beyond its rounding, ``8 eps``), else Weiszfeld's step (a descent step, in Vardi and
    Zhang's form). The vertex step starts from the heaviest sample in the first iteration and from
    the sample nearest to the current rotation in the others; where that sample is the median (its
    weight at least the pull of the others: the optimality condition at the tip of a cone of the
    objective) it is that sample, exactly. All steps are fixed: the objective is compared, never
    looped on."""
    u, w, positive = _weights(xp, x)
    heaviest = _pick(xp, _first_minimum(xp, -w), u)

    def step(state: tuple[Any, Any]) -> tuple[Any, Any]:
        # Constants inside the step: a Python float from outside is a symbolic input of torch's
        # while_loop under dynamic shapes, which it refuses.
        atol = 8.0 * float(xp.finfo(x.dtype).eps)
        y, first = state
        s = _Sweep(xp, y, u, w)
        sample = xp.where(first[..., None], heaviest, _pick(xp, _first_minimum(xp, s.angle), u))
        vertex = _vertex_step(xp, _unit(xp, sample), u, w)
        newton = _exp_right(xp, y, s.newton_step())
        fn, fv = _objective(xp, newton, u, w), _objective(xp, vertex, u, w)
        fn = xp.where(xp.isfinite(fn), fn, xp.inf)
        best = xp.where((fv < fn)[..., None], vertex, newton)
        accept = xp.minimum(fn, fv) <= s.f + atol
        return xp.where(accept[..., None], best, _exp_right(xp, y, s.weiszfeld_step())), xp.zeros_like(first)

    y = _chordal_quaternion(xp, _unit(xp, u), w, eigenvector)
    y, _ = repeat(xp, MEDIAN_STEPS, step, (y, positive | ~positive))
    return _finish(xp, y, positive)


def _median_system(xp: Any, x: Any, y: Any) -> tuple[Any, Any, Any, Any, Any, Any, Any, Any, Any]:
    """The pieces of the derivative of the median at its solution ``y``: quaternions, normalised
    weights, total weight (1 where zero), which samples are at ``y`` (weight > 0, within
    :func:`_coincident`), whether any is, their total weight (1 where none), the unit vectors ``n_i``,
    ``cot(t_i / 2)`` (both with safe values at coincident samples) and ``B`` (floored)."""
    u, omega = x[..., :4], x[..., 4]
    total = xp.sum(omega, axis=-1, keepdims=True)
    total = xp.where(total > xp.finfo(x.dtype).tiny, total, 1.0)
    w = omega / total
    cos, sin, axis = _relative(xp, y, u)
    near = 2.0 * xp.atan2(sin, cos) <= _coincident(xp, x.dtype)
    at = near & (w > 0)
    snapped = xp.any(at, axis=-1)
    weight_at = xp.sum(xp.where(at, w, 0.0), axis=-1)
    weight_at = xp.where(snapped, weight_at, 1.0)
    safe = xp.where(near, 1.0, sin)
    n = xp.where(near[..., None], 0.0, axis / safe[..., None])
    cot = xp.where(near, 0.0, cos / safe)
    wr = xp.where(near, 0.0, w)
    a = wr * cot
    outer = xp.matmul(_transpose(xp, n * a[..., None]), n)
    g = xp.sum(wr[..., None] * n, axis=-2)
    b = _floored(xp, _hat_plus(xp, 0.5 * xp.sum(a, axis=-1), -0.5 * g, -0.5 * outer))
    return u, w, total, at, snapped, weight_at, n, cot, b


def median_tangent(xp: Any, x: Any, y: Any, dx: Any) -> Any:
    """Forward-mode derivative of :func:`geodesic_median` by the implicit function theorem.

    Away from the samples, the residual ``sum_i w_i n_i`` stays 0: with ``dn_i = (I - n_i n_i^T)
    dv_i / t_i`` and ``dv_i`` as for the Karcher mean, ``B e = sum_i w_i (cot(t_i / 2) (I - n_i n_i^T)
    + hat(n_i)) d_i / 2 + sum_i d(omega_i) n_i / sum omega`` (``(I - n n^T) Jr^-1(v) / t`` is that
    bracket). Where the median is a sample (snapped to it: the sample outweighs the pull of the
    others, strictly so in all but a set of measure zero), it moves with that sample: ``e = d_j``
    (with several coincident samples, their weighted mean) and not with the weights."""
    u, w, total, at, snapped, weight_at, n, cot, b = _median_system(xp, x, y)
    d = _right_perturbations(xp, u, dx[..., :4])
    off = xp.where(at, 0.0, w)[..., None]
    along = d - n * _dot(xp, n, d)[..., None]
    rhs = xp.sum(off * 0.5 * (cot[..., None] * along + _cross(xp, n, d)), axis=-2)
    rhs = rhs + xp.sum(dx[..., 4:5] * n, axis=-2) / total
    follow = xp.sum(xp.where(at, w, 0.0)[..., None] * d, axis=-2) / weight_at[..., None]
    e = xp.where(snapped[..., None], follow, _solve3(xp, b, rhs))
    return _tangent_of_rotation(xp, y, e)


def median_cotangent(xp: Any, x: Any, y: Any, gy: Any, pieces: _Pieces | None = None) -> Any:
    """Reverse-mode derivative of :func:`geodesic_median`: the transpose of :func:`median_tangent`."""
    p = pieces or _COMPONENTWISE
    u, w, total, at, snapped, weight_at, n, cot, b = _median_system(xp, x, y)
    ge = p.rotation_of_cotangent(xp, y, gy)
    free = xp.where(snapped[..., None], 0.0, p.solve3_transposed(xp, b, ge))[..., None, :]
    gfollow = xp.where(snapped[..., None], ge / weight_at[..., None], 0.0)[..., None, :]
    off = xp.where(at, 0.0, w)[..., None]
    # adjoint of d -> (cot (d - n (n . d)) + n x d) / 2 is g -> (cot (g - n (n . g)) - n x g) / 2
    free = xp.broadcast_to(free, n.shape)
    along = free - n * _dot(xp, n, free)[..., None]
    gd = off * 0.5 * (cot[..., None] * along - p.cross(xp, n, free))
    gd = gd + xp.where(at, w, 0.0)[..., None] * gfollow
    gomega = xp.sum(n * free, axis=-1, keepdims=True) / total[..., None]
    return xp.concat([p.right_perturbations_transposed(xp, u, gd), gomega], axis=-1)


_COMPONENTWISE = _Pieces(
    _cross, _rotation_of_cotangent, _right_perturbations_transposed, _jacobian_inverse, _solve3_transposed
)


# ---------------------------------------------------------------------------------------------------
# The geodesic means' reverse rules in vectorised operations (torch, eager): the same formulas as
# karcher_cotangent and median_cotangent, with their products of quaternions as one product with the
# Hamilton coefficients (quaternion_multiply_eager) and cross products as linalg.cross. Every selection
# (the sign of y* q_i, the series switches, the coincident samples) is the componentwise one, read from
# the same componentwise quantities: only values that no choice reads are computed otherwise.


def _cross_eager(xp: Any, a: Any, b: Any) -> Any:
    return xp.linalg.cross(a, b)


def _rotation_of_cotangent_eager(xp: Any, y: Any, gy: Any) -> Any:
    """:func:`_rotation_of_cotangent`: ``vec(y* gy) / 2``."""
    return 0.5 * quaternion_multiply_eager(xp, quaternion_conjugate_eager(xp, y), gy)[..., 1:]


def _right_perturbations_transposed_eager(xp: Any, u: Any, g: Any) -> Any:
    """:func:`_right_perturbations_transposed`: ``2 u_i (0, g_i) / |u_i|^2``."""
    pure = xp.nn.functional.pad(g, (1, 0))
    return quaternion_multiply_eager(xp, u, pure) * (2.0 / xp.sum(u * u, axis=-1, keepdims=True))


def _jacobian_inverse_eager(xp: Any, v: Any, c: Any, x: Any, right: bool) -> Any:
    """:func:`_jacobian_inverse` with ``linalg.cross``."""
    vx = _cross_eager(xp, v, x)
    return x + (0.5 if right else -0.5) * vx + c[..., None] * _cross_eager(xp, v, vx)


def _solve3_transposed_eager(xp: Any, a: Any, b: Any) -> Any:
    """:func:`_solve3_transposed`, ``a^-T b`` by the adjugate: ``a``'s columns are the rows of ``a^T``,
    whose cofactor rows are the cross products of ``a``'s rows, as :func:`_solve3` forms them."""
    r0, r1, r2 = a.unbind(-2)
    k = xp.stack([_cross_eager(xp, r1, r2), _cross_eager(xp, r2, r0), _cross_eager(xp, r0, r1)], axis=-2)
    det = _dot(xp, r0, k[..., 0, :])
    return xp.matmul(k, b[..., None])[..., 0] / det[..., None]


_EAGER = _Pieces(
    _cross_eager,
    _rotation_of_cotangent_eager,
    _right_perturbations_transposed_eager,
    _jacobian_inverse_eager,
    _solve3_transposed_eager,
)


def karcher_eager_cotangent(xp: Any, x: Any, y: Any, gy: Any | None) -> Any:
    """:func:`karcher_cotangent`, eager form (torch). None for no cotangent."""
    return None if gy is None else karcher_cotangent(xp, x, y, gy, _EAGER)


def median_eager_cotangent(xp: Any, x: Any, y: Any, gy: Any | None) -> Any:
    """:func:`median_cotangent`, eager form (torch). None for no cotangent."""
    return None if gy is None else median_cotangent(xp, x, y, gy, _EAGER)


def _same(xp: Any, x: Any) -> Any:
    return x


def _result(xp: Any, x: Any, y: Any) -> Any:
    return y


def karcher_eager_rules() -> tuple[Any, ...]:
    """The Karcher mean's eager rule as ``custom_derivative`` takes it: (prepare, forward, cotangent,
    finish), the forward None: the map's own (opaque) forward."""
    return _same, None, karcher_eager_cotangent, _result


def median_eager_rules() -> tuple[Any, ...]:
    """The geodesic median's eager rule, as :func:`karcher_eager_rules`."""
    return _same, None, median_eager_cotangent, _result


# ---------------------------------------------------------------------------------------------------
# Public functions.


def _broadcast_samples(xp: Any, x: Any, weights: Any, trailing: int) -> tuple[Any, Any]:
    """``x`` (..., N, *k) and ``weights`` (..., N) (all ones where None), broadcast to one batch shape."""
    n = x.shape[-trailing - 1]
    shapes = [x.shape[: x.ndim - trailing - 1]] + ([] if weights is None else [weights.shape[:-1]])
    batch = tuple(xp.broadcast_shapes(*shapes))
    # broadcast only where a shape differs (static shapes): an expand is an operation in eager torch
    shape = (*batch, n, *x.shape[x.ndim - trailing :])
    x = x if tuple(x.shape) == shape else xp.broadcast_to(x, shape)
    if weights is None:
        return x, xp.ones_like(x[(..., *([0] * trailing))])
    return x, weights if tuple(weights.shape) == (*batch, n) else xp.broadcast_to(weights, (*batch, n))


def check_method(fname: str, method: str) -> None:
    if method not in METHODS:
        raise ValueError(f"{fname}: method must be one of {', '.join(map(repr, METHODS))}, got {method!r}")


@op(matrices=(-1, 3, 3), weights=(-1,))
def rotation_mean(
    xp: Any,
    matrices: Any,
    weights: Any = None,
    *,
    method: MeanMethod = "chordal",
    procrustes: Callable[[Any, Any], Any] = special_procrustes,
    karcher: Callable[[Any, Any], Any] = karcher_mean,
    median: Callable[[Any, Any], Any] = geodesic_median,
    to_quaternion: Callable[..., Any] = matrix_to_quaternion,
    to_matrix: Callable[..., Any] = quaternion_to_matrix,
) -> Any:
    """Mean of rotation matrices: ``(..., N, 3, 3)`` and weights ``(..., N)`` to ``(..., 3, 3)``.

    Args:
        matrices: rotation matrices, shape ``(..., N, 3, 3)``; batch dimensions broadcast against those
            of ``weights``.
        weights: non-negative weights, shape ``(..., N)``, or ``None`` for equal weights. Only their
            ratios matter; weights summing to zero (and ``N = 0``) give the identity.
        method: ``"chordal"`` (default): the rotation nearest to ``sum_i w_i R_i``,
            ``special_procrustes`` of it, which minimises ``sum_i w_i |R - R_i|_F^2``: scipy's
            ``Rotation.mean``, and Markley's quaternion mean (``quaternion_mean``). ``"geodesic"``: the
            Karcher mean, minimising ``sum_i w_i angle(R, R_i)^2``: ``sum_i w_i log(R^T R_i) = 0``,
            converged to rounding (residual below 1e-15 in float64, weights summing to 1) in 4
            Newton steps from the chordal mean, for samples up to 1.55 rad from their centre (the
            mean is unique within pi/2). ``"geodesic_l1"``: the geodesic median, minimising
            ``sum_i w_i angle(R, R_i)`` (robust to outliers), in 12 fixed iterations: on 99.9% of
            the sets measured (equal, uniform and outlier-laden weights; clusters of 1e-3 to 1.5
            rad) within rounding of the median (1e-15 of the cluster's radius), on 99.99% within
            1e-7 of it; weights of very different sizes leave about one set in 3000 short (see
            ``MEDIAN_STEPS`` in ``diffquat/_statistics.py``). Where a sample outweighs the pull of
            the others (``w_j >= |sum_{i != j} w_i n_i|``, ``n_i`` the unit vectors towards them,
            e.g. more than half of the total weight) the median is that sample, returned exactly.

    Returns:
        Rotation matrices, shape ``(..., 3, 3)``. The geodesic methods read each matrix as the rotation
        of ``matrix_to_quaternion`` (the matrix itself on SO(3)).

    Gradients (torch and jax): ``"chordal"`` through ``special_procrustes``; the geodesic methods by
    the implicit function theorem at the solution, not through the iterations (first and second order,
    forward and reverse). The median moves with the sample it is at (and not with the weights) where
    it is one. Where the solution is not unique (the linear system of the implicit derivative has a
    symmetric part within ``sqrt(eps)`` of singular) that system is regularised: bounded.
    """
    check_method("rotation_mean", method)
    matrices, w = _broadcast_samples(xp, matrices, weights, 2)
    if matrices.shape[-3] == 0:  # no samples (a static shape): the documented identity
        return to_matrix(xp, _identity_quaternion(xp, xp.sum(matrices, axis=-3)[..., 0, :]))
    if method == "chordal":
        # equal weights: the sum itself (products by 1 are exact, so the same numbers in fewer operations)
        total = xp.sum(matrices if weights is None else xp.reshape(w, (*w.shape, 1, 1)) * matrices, axis=-3)
        return procrustes(xp, total)
    q = to_quaternion(xp, matrices)
    x = xp.concat([q, w[..., None]], axis=-1)
    y = (karcher if method == "geodesic" else median)(xp, x)
    return to_matrix(xp, y)


@canonical
@op(q=(-1, 4), weights=(-1,))
def quaternion_mean(
    xp: Any,
    q: Any,
    weights: Any = None,
    *,
    scalar_first: bool = True,
    eigenvector: Callable[[Any, Any], Any] = smallest_eigenvector,
) -> Any:
    """Markley's mean of quaternions: ``(..., N, 4)`` and weights ``(..., N)`` to ``(..., 4)``.

    Args:
        q: quaternions, shape ``(..., N, 4)``, any non-zero norm (each is normalised; the zero
            quaternion is the identity); the sign of each is irrelevant (``q`` and ``-q`` are one
            rotation). Batch dimensions broadcast against those of ``weights``.
        weights: non-negative weights, shape ``(..., N)``, or ``None`` for equal weights; weights
            summing to zero (and ``N = 0``) give the identity.
        scalar_first: storage order of ``q`` and of the result.

    Returns:
        Unit quaternions in canonical sign, shape ``(..., 4)``: the eigenvector of the largest
        eigenvalue of ``sum_i w_i q_i q_i^T`` (Markley et al., 2007), the rotation minimising
        ``sum_i w_i |R - R_i|_F^2`` (the chordal mean, as ``rotation_mean``'s default and scipy's
        ``Rotation.mean``). Where that eigenvalue is repeated the mean is not unique and the result
        is whichever eigenvector the backend's ``eigh`` returns.

    Gradients (torch and jax) are those of ``symmetric_matrix_to_quaternion`` (the largest eigenvector
    of ``K`` is the smallest of ``-K``): they divide only by the gaps to the largest eigenvalue.
    """
    q, w = _broadcast_samples(xp, q, weights, 1)
    u = normalize_quaternion(xp, q, scalar_first=scalar_first)
    u = join_quaternion(xp, *split_quaternion(u, scalar_first), True)
    mean = _chordal_quaternion(xp, u, w, eigenvector)
    return mean if scalar_first else wxyz_to_xyzw(xp, mean)


@eager_form(of=quaternion_mean)
def quaternion_mean_eager(
    xp: Any,
    q: Any,
    weights: Any = None,
    *,
    scalar_first: bool = True,
    eigenvector: Callable[[Any, Any], Any] = smallest_eigenvector,
) -> Any:
    """:func:`quaternion_mean`, eager form (torch): the same products and the same ``eigh``, with the
    eager forms of the normalisation and the canonical sign, scalar-last storage reordered by ``roll``
    (exact), and the upper triangle of ``-K`` read by one gather."""
    q, w = _broadcast_samples(xp, q, weights, 1)
    u = normalize_quaternion_eager(xp, q, scalar_first=scalar_first)
    u = u if scalar_first else xp.roll(u, 1, -1)
    k = xp.matmul(_transpose(xp, u * w[..., None]), u)
    mean = standardize_quaternion_eager(xp, eigenvector(xp, -upper_entries(xp, k)), scalar_first=True)
    return mean if scalar_first else xp.roll(mean, -1, -1)


# ---------------------------------------------------------------------------------------------------
# Symmetric objects.


@op(matrix1=(3, 3), matrix2=(3, 3), group=(-1, 3, 3))
def symmetric_geodesic_distance(xp: Any, matrix1: Any, matrix2: Any, group: Any) -> Any:
    """Angle between two orientations of a symmetric object: ``min_g angle(matrix1^T matrix2 g)``.

    Args:
        matrix1: a rotation matrix, shape ``(..., 3, 3)``.
        matrix2: a rotation matrix, shape ``(..., 3, 3)``.
        group: the object's symmetries, shape ``(..., G, 3, 3)`` with ``G >= 1`` (e.g.
            ``symmetry_group("D4")``): rotations ``g`` in the object's own frame, so that ``R`` and
            ``R g`` are the same pose. Batch dimensions of the three arguments broadcast.

    Returns:
        Shape ``(...)``, in [0, pi]: ``min_g matrix_geodesic_distance(matrix1, matrix2 @ g)``. Ties
        (distances within 4 ulps of ``max(1, minimum)`` of the minimum, the rounding of one distance):
        the first such ``g`` in the group's order, on every backend and path; the value and the
        gradient are those of the distance to this ``g``, finite everywhere (0 where the distance is
        0, as for ``matrix_geodesic_distance``).
    """
    if group.shape[-3] == 0:
        raise ValueError(
            "symmetric_geodesic_distance: expected a group of at least one rotation, "
            f"got shape {tuple(group.shape)}"
        )
    a, b = match_rank(xp, matrix1, matrix2)
    # angle(R1^T (R2 g)) = angle((R2^T R1)^T g): one product per pair, then the core distance per g.
    m = xp.matmul(_transpose(xp, b), a)[..., None, :, :]
    m, g = match_rank(xp, m, group)
    d = _matrix_geodesic_distance(xp, m, g)
    return _nearest(xp, d)


def _nearest(xp: Any, d: Any) -> Any:
    """The distance ``(...)`` to the chosen symmetry of the distances ``d`` ``(..., G)``."""
    # Ties within 4 ulps (the rounding of one distance: exact ties come out so) go to the first g, so
    # that one choice holds on every backend and path, whichever order its arithmetic rounds in.
    return xp.sum(xp.where(_first_minimum(xp, d, 4.0), d, 0.0), axis=-1)


def _one_zero() -> tuple[Any, ...]:
    # 1 and 0 as arrays: a Python number in a ``where`` is an operation of its own in eager torch
    return 1.0, 0.0


@eager_form(of=symmetric_geodesic_distance)
def symmetric_geodesic_distance_eager(xp: Any, matrix1: Any, matrix2: Any, group: Any) -> Any:
    """:func:`symmetric_geodesic_distance`, eager form: the same relative rotation, then the distance
    to every ``g`` in a few vectorised operations and the same choice of ``g``.

    The distances decide the choice, so they are formed as the componentwise form forms them, without
    a BLAS product: ``M = m^T g`` entry by entry as three products summed over ``k`` in order (a
    reduction, not a ``matmul``, whose blocking differs between layouts), the axial part as
    differences of two entries (exactly 0 for a symmetric ``M``), the trace as the sum of the
    diagonal, then ``atan2(|axial|, trace - 1)`` with the componentwise form's double ``where`` on the
    norm (a zero gradient at the zero axial part)."""
    if group.shape[-3] == 0:
        raise ValueError(
            "symmetric_geodesic_distance: expected a group of at least one rotation, "
            f"got shape {tuple(group.shape)}"
        )
    one, zero = constants(xp, matrix1, _one_zero)
    a, b = match_rank(xp, matrix1, matrix2)
    m = xp.matmul(_transpose(xp, b), a)[..., None, :, :]
    m, g = match_rank(xp, m, group)
    full = (m[..., :, :, None] * g[..., :, None, :]).sum(-3)
    # the entries (2, 1), (0, 2), (1, 0) of M - M^T (row-major 7, 2, 3), in the componentwise order
    flat = (full - full.mT).flatten(-2)
    skew = xp.cat([flat[..., 7:8], flat[..., 2:4]], -1)
    s2 = (skew * skew).sum(-1)
    cos2 = full.diagonal(0, -2, -1).sum(-1) - 1.0
    positive = s2 > 0
    d = xp.atan2(xp.where(positive, xp.sqrt(xp.where(positive, s2, one)), zero), cos2)
    return _nearest(xp, d)


_NAME = re.compile(r"^(?:([CD])([1-9][0-9]*)|([TOI]))$")
_GOLDEN = (1.0 + 5.0**0.5) / 2.0


def _tetrahedral() -> list[tuple[float, float, float, float]]:
    """The 12 rotations of the tetrahedron (scalar first): the identity, the half-turns about x, y and
    z, and the third-turns about the 4 diagonals (+-1, +-1, +-1) (with w = 1/2 > 0, both senses)."""
    units = [(1.0, 0.0, 0.0, 0.0), (0.0, 1.0, 0.0, 0.0), (0.0, 0.0, 1.0, 0.0), (0.0, 0.0, 0.0, 1.0)]
    thirds = [(0.5, 0.5 * a, 0.5 * b, 0.5 * c) for a in (1, -1) for b in (1, -1) for c in (1, -1)]
    return units + thirds


def _octahedral() -> list[tuple[float, float, float, float]]:
    """The 24 rotations of the cube: the tetrahedral ones, the quarter-turns about x, y and z (both
    senses), and the half-turns about the 6 face diagonals ``(1, +-1, 0)``, ``(1, 0, +-1)``,
    ``(0, 1, +-1)``."""
    h = 0.5**0.5
    quarters = [(h, h, 0.0, 0.0), (h, -h, 0.0, 0.0), (h, 0.0, h, 0.0), (h, 0.0, -h, 0.0)]
    quarters += [(h, 0.0, 0.0, h), (h, 0.0, 0.0, -h)]
    diagonals = [(0.0, h, h, 0.0), (0.0, h, -h, 0.0), (0.0, h, 0.0, h), (0.0, h, 0.0, -h)]
    diagonals += [(0.0, 0.0, h, h), (0.0, 0.0, h, -h)]
    return _tetrahedral() + quarters + diagonals


def _icosahedral() -> list[tuple[float, float, float, float]]:
    """The 60 rotations of the icosahedron whose 2-fold axes include x, y and z and whose 5-fold axes
    lie along ``(0, +-1, +-phi)`` and its cyclic permutations (phi the golden ratio): the tetrahedral
    ones and the 48 quaternions ``(x, y, z, w)`` = the even permutations of ``(1, 1/phi, phi, 0) / 2``
    with every sign of the three non-zero entries (one of each pair +-q)."""
    base = (0.5, 0.5 / _GOLDEN, 0.5 * _GOLDEN, 0.0)
    even = [
        (0, 1, 2, 3), (0, 2, 3, 1), (0, 3, 1, 2), (1, 0, 3, 2), (1, 2, 0, 3), (1, 3, 2, 0),
        (2, 0, 1, 3), (2, 1, 3, 0), (2, 3, 0, 1), (3, 0, 2, 1), (3, 1, 0, 2), (3, 2, 1, 0),
    ]  # fmt: skip
    out = []
    for perm in even:
        xyzw = [base[p] for p in perm]
        nonzero = [k for k in range(4) if xyzw[k] != 0.0]
        for signs in ((1, 1, 1), (1, 1, -1), (1, -1, 1), (1, -1, -1)):
            entry = list(xyzw)
            for k, s in zip(nonzero, signs, strict=True):
                entry[k] *= s
            out.append((entry[3], entry[0], entry[1], entry[2]))
    return _tetrahedral() + out


SYMMETRY_GROUP_DOC = """The rotations of a symmetric object, the proper point group ``name``: ``(G, 3, 3)``.

    The same set as scipy's ``Rotation.create_group(name)`` (its default axis, z), in this order (the
    order decides ties in ``symmetric_geodesic_distance``; the identity is always first):

    - ``"C<n>"`` (n >= 1, cyclic, G = n): the rotations by ``2 pi k / n`` about z, k = 0 ... n - 1.
    - ``"D<n>"`` (dihedral, G = 2n): ``"C<n>"``, then the half-turns about the n axes of the xy-plane
      at angles ``pi k / n`` from x, k = 0 ... n - 1 (``"D1"``: the identity and the half-turn about x).
    - ``"T"`` (tetrahedral, G = 12): the identity, the half-turns about x, y and z, and the turns by
      120 degrees about the diagonals (+-1, +-1, +-1).
    - ``"O"`` (octahedral, the cube's, G = 24): ``"T"``, the quarter-turns about x, y and z, and the
      half-turns about the face diagonals ``(1, +-1, 0)``, ``(1, 0, +-1)``, ``(0, 1, +-1)``.
    - ``"I"`` (icosahedral, G = 60): ``"T"`` and the 48 rotations whose quaternions ``(x, y, z, w)``
      are the even permutations of ``(1, 1/phi, phi, 0) / 2`` with signs (phi the golden ratio): the
      2-fold axes include x, y and z, the 5-fold axes lie along ``(0, +-1, +-phi)`` and its cyclic
      permutations.

    Entries that are 0, +-1/2 or +-1 are exact. An unknown name (or n < 1) raises ``ValueError``.

    Args:
        name: ``"C<n>"``, ``"D<n>"``, ``"T"``, ``"O"`` or ``"I"``.
{keywords}
    Returns:
        Rotation matrices, shape ``(G, 3, 3)``.
    """


@functools.cache
def symmetry_group_matrices(name: str) -> Any:
    """The rotation matrices ``(G, 3, 3)`` (float64 NumPy, read-only) of the named group, built from
    their quaternions (see :data:`SYMMETRY_GROUP_DOC`)."""
    match = _NAME.match(name) if isinstance(name, str) else None
    if match is None:
        raise ValueError(f"symmetry_group: expected 'C<n>' or 'D<n>' (n >= 1), 'T', 'O' or 'I', got {name!r}")
    kind, order, solid = match.groups()
    if solid is not None:
        quaternions = {"T": _tetrahedral, "O": _octahedral, "I": _icosahedral}[solid]()
    else:
        n = int(order)
        quaternions = [
            (float(np.cos(np.pi * k / n)), 0.0, 0.0, float(np.sin(np.pi * k / n))) for k in range(n)
        ]
        if kind == "D":
            quaternions += [
                (0.0, float(np.cos(np.pi * k / n)), float(np.sin(np.pi * k / n)), 0.0) for k in range(n)
            ]
    q = np.array(quaternions, dtype=np.float64)
    m = quaternion_to_matrix(np, q)
    # Entries within a few ulps of 0, +-1/2 or +-1 are exactly that (cos(pi/2) is 6e-17 in floating
    # point): the groups then map the axes onto each other exactly.
    halves = np.round(2.0 * m) / 2.0
    m = np.where(np.abs(m - halves) <= 4.0 * np.finfo(np.float64).eps, halves, m)
    m.setflags(write=False)
    return m
