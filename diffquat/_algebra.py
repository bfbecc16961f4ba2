"""Quaternion algebra and the rotation vector (the exponential and logarithm of SO(3)), over ``xp``.

The rotation vector lives here beside the algebra because ``quaternion_slerp`` is written with it:
``slerp(p, q, t) = p exp(t log(p* q))``, so the series that make ``exp`` and ``log`` exact and smooth at
the identity also make slerp's gradient correct where ``p = +-q``.
"""

from __future__ import annotations

import functools
from collections.abc import Callable
from typing import Any

from ._core import (
    Conversion,
    _negative_canonical,
    _quadratic_forms,
    cancelling_factor,
    computed_once,
    constants,
    eager_form,
    join_quaternion,
    largest_magnitude,
    matrix_to_quaternion,
    nonfinite_by_arithmetic,
    op,
    split_quaternion,
    unit_quaternion_to_matrix,
    zero_or_nan,
)

Components = tuple[Any, Any, Any, Any]


def hamilton(p: Components, q: Components) -> Components:
    """Hamilton product of two quaternions given as components (w, x, y, z); i*i = j*j = k*k = ijk = -1.

    Grouped as ``pw qv + qw pv`` plus the cross product ``pv x qv``, each pair in one parenthesis, so
    that ``p* p`` has an exactly zero vector part in floating point (the distance of a rotation to itself
    is then exactly 0)."""
    pw, px, py, pz = p
    qw, qx, qy, qz = q
    return (
        pw * qw - (px * qx + py * qy + pz * qz),
        (pw * qx + px * qw) + (py * qz - pz * qy),
        (pw * qy + py * qw) + (pz * qx - px * qz),
        (pw * qz + pz * qw) + (px * qy - py * qx),
    )


def match_rank(xp: Any, *arrays: Any) -> list[Any]:
    """Prepend unit axes so that every array has the same rank; broadcasting is then elementwise.
    Explicit, because jax (with rank promotion set to "raise") refuses to broadcast across ranks."""
    rank = max(a.ndim for a in arrays)
    # an array of the full rank as it is: a reshape to its own shape is an operation in eager torch
    return [a if a.ndim == rank else xp.reshape(a, (1,) * (rank - a.ndim) + tuple(a.shape)) for a in arrays]


def nonzero_or_identity(xp: Any, w: Any, x: Any, y: Any, z: Any) -> Components:
    """The quaternion itself, or the identity where it is zero (squared norm below the smallest normal
    number), the library's documented meaning of the zero quaternion. A selection, so it is exact and
    its gradient is the identity map (or zero at the zero quaternion)."""
    n2 = w * w + x * x + y * y + z * z
    zero = n2 < xp.finfo(n2.dtype).tiny
    return xp.where(zero, 1.0, w), xp.where(zero, 0.0, x), xp.where(zero, 0.0, y), xp.where(zero, 0.0, z)


def safe_norm(xp: Any, n2: Any) -> Any:
    """``sqrt(n2)`` with a zero (not infinite) derivative at ``n2 = 0``: the discarded branch sees 1."""
    positive = n2 > 0
    return xp.where(positive, xp.sqrt(xp.where(positive, n2, 1.0)), 0.0)


def series_threshold(xp: Any, dtype: Any) -> float:
    """Below this value of a squared small quantity, a three-term Taylor series in it is exact to the
    precision of ``dtype`` (its first dropped term is ~ threshold^3 = eps^1.5), and above it the closed
    form's cancellation costs at most a relative sqrt(eps) in the derivative."""
    return float(xp.finfo(dtype).eps) ** 0.5


# ---------------------------------------------------------------------------------------------------
# Quaternion algebra.


@op(p=(4,), q=(4,))
def quaternion_multiply(xp: Any, p: Any, q: Any, *, scalar_first: bool = True) -> Any:
    """Hamilton product ``p q`` (i*i = j*j = k*k = ijk = -1), no sign standardisation.

    Args:
        p: the left factor, quaternions of shape ``(..., 4)``, any norm (the product's norm is
            ``|p| |q|``).
        q: the right factor, shape ``(..., 4)``; its batch dimensions broadcast against ``p``'s.
        scalar_first: storage order of ``p``, ``q`` and of the result.

    Returns:
        Shape ``(..., 4)``. As rotations, ``quaternion_to_matrix(p q) == quaternion_to_matrix(p) @
        quaternion_to_matrix(q)``: first ``q``, then ``p``.
    """
    p, q = match_rank(xp, p, q)
    out = hamilton(split_quaternion(p, scalar_first), split_quaternion(q, scalar_first))
    return join_quaternion(xp, *out, scalar_first)


def _hamilton_forms() -> tuple[list[Any], ...]:
    """(16, 4): row ``4 i + j`` holds the coefficients of ``p_i q_j`` (scalar first) in the Hamilton
    product (:func:`hamilton`)."""
    c = [[0.0] * 4 for _ in range(16)]
    terms = (
        ((0, 0, 1), (1, 1, -1), (2, 2, -1), (3, 3, -1)),
        ((0, 1, 1), (1, 0, 1), (2, 3, 1), (3, 2, -1)),
        ((0, 2, 1), (2, 0, 1), (3, 1, 1), (1, 3, -1)),
        ((0, 3, 1), (3, 0, 1), (1, 2, 1), (2, 1, -1)),
    )
    for k, row in enumerate(terms):
        for i, j, v in row:
            c[4 * i + j][k] = float(v)
    return (c,)


@eager_form(of=quaternion_multiply)
def quaternion_multiply_eager(xp: Any, p: Any, q: Any, *, scalar_first: bool = True) -> Any:
    """:func:`quaternion_multiply`, eager form: the outer product ``p q^T`` contracted with the constant
    (16, 4) coefficients of the Hamilton product, one ``matmul`` (five operations in all for a batch of
    one dimension). Scalar-last storage is reordered in and out (``roll``), so that both orders sum the
    same products in the same order, bit for bit."""
    if not scalar_first:
        p, q = xp.roll(p, 1, -1), xp.roll(q, 1, -1)
    (c,) = constants(xp, p, _hamilton_forms)
    out = xp.matmul((p[..., :, None] * q[..., None, :]).flatten(-2), c)
    return out if scalar_first else xp.roll(out, -1, -1)


@op(q=(4,))
def quaternion_conjugate(xp: Any, q: Any, *, scalar_first: bool = True) -> Any:
    """Conjugate ``(w, -x, -y, -z)``; shape ``(..., 4)``. For a unit quaternion, its inverse."""
    w, x, y, z = split_quaternion(q, scalar_first)
    return join_quaternion(xp, w, -x, -y, -z, scalar_first)


def _conjugate_signs() -> tuple[Any, ...]:
    return [1.0, -1.0, -1.0, -1.0], [-1.0, -1.0, -1.0, 1.0]


@eager_form(of=quaternion_conjugate)
def quaternion_conjugate_eager(xp: Any, q: Any, *, scalar_first: bool = True) -> Any:
    """:func:`quaternion_conjugate`, eager form: one product with the constant signs (negation is exact,
    so the two forms agree bit for bit)."""
    first, last = constants(xp, q, _conjugate_signs)
    return q * (first if scalar_first else last)


@nonfinite_by_arithmetic
@op(q=(4,))
def quaternion_invert(xp: Any, q: Any, *, scalar_first: bool = True) -> Any:
    """Multiplicative inverse ``conj(q) / |q|^2`` of a quaternion of any non-zero norm.

    Args:
        q: quaternions, shape ``(..., 4)``. The zero quaternion (squared norm below the smallest normal
            number of the compute dtype) gives the zero quaternion, with a finite (zero) gradient; as a
            rotation that is the identity, the inverse of the identity.
        scalar_first: storage order of ``q`` and of the result.

    Returns:
        Shape ``(..., 4)``, norm ``1 / |q|``.
    """
    w, x, y, z = split_quaternion(q, scalar_first)
    # "below", not ">=" (false for NaN): a NaN row counts as non-zero, so that its NaN reaches every
    # component through m (a NaN-propagating maximum) and n2, as an infinity does (inf * 0 in
    # w * inv_m), and the backends add no selection after it (NONFINITE_BY_ARITHMETIC)
    zero = w * w + x * x + y * y + z * z < xp.finfo(q.dtype).tiny
    # Scaled by m = max |q_i| first: the result grows as 1/|q|, so on a chain through n2 = |q|^2 the
    # derivative reaches |q|^-3 (1e45 at |q| = 1e-15, past float32). With p = q / m, |p|^2 lies in
    # [1, 4] and the largest intermediate derivative is 1/m^2. conj(q) / |q|^2 = conj(p) / (m |p|^2).
    # Double wheres: the discarded branch divides by 1, so everything stays finite at q = 0.
    m = xp.maximum(xp.maximum(xp.abs(w), xp.abs(x)), xp.maximum(xp.abs(y), xp.abs(z)))
    inv_m = xp.where(zero, 0.0, 1.0 / xp.where(zero, 1.0, m))
    w, x, y, z = w * inv_m, x * inv_m, y * inv_m, z * inv_m
    n2 = w * w + x * x + y * y + z * z
    s = xp.where(zero, 0.0, inv_m / xp.where(zero, 1.0, n2))
    return join_quaternion(xp, w * s, -x * s, -y * s, -z * s, scalar_first)


def _invert_constants() -> tuple[Any, ...]:
    # the conjugate's signs and inf
    return [1.0, -1.0, -1.0, -1.0], float("inf")


@nonfinite_by_arithmetic
@eager_form(of=quaternion_invert)
def quaternion_invert_eager(xp: Any, q: Any, *, scalar_first: bool = True) -> Any:
    """:func:`quaternion_invert`, eager form, in ten operations: ``conj(q) / |q|^2 = conj(u) / (|u| |q|)``
    with ``u = q / m``, ``m = max |q_i|`` a constant of differentiation (the same function of ``q`` for
    every fixed ``m``, so the derivative is exact), and ``|q| = m |u|``.

    ``|u|`` lies in [1, 2], so the norm neither overflows nor underflows for any finite quaternion
    (``linalg.vector_norm`` of ``q`` itself is inf from ``|q| ~ 1.8e19`` on in float32), and the divisor
    is of size ``|q|``, not ``|q|^2``: reverse mode through ``1 / |q|^2`` meets ``|q|^-3`` (1e45 at
    |q| = 1e-15, past float32); this way every intermediate derivative is of size ``1 / |q|^2`` at
    most. A NaN or an infinity makes ``q / m`` NaN
    (``inf / inf``), then ``|q|`` and every component of the row (NONFINITE_BY_ARITHMETIC). The zero
    quaternion (``|q| < sqrt(tiny)``: squared norm below the smallest normal number) is divided by inf
    instead: the zero quaternion, with a zero gradient."""
    if not scalar_first:  # one order of summation in the norm, so both orders agree bit for bit
        q = xp.roll(q, 1, -1)
    signs, inf = constants(xp, q, _invert_constants)
    tiny = float(xp.finfo(q.dtype).tiny)
    m = largest_magnitude(xp, cancelling_factor(xp, q)).clamp_min(tiny)
    u = q / m
    n = xp.linalg.vector_norm(u, 2, -1, True)
    norm = n * m
    out = u * signs / xp.where(norm < tiny**0.5, inf, n * norm)
    return out if scalar_first else xp.roll(out, -1, -1)


@op(q=(4,), v=(3,))
def quaternion_apply(xp: Any, q: Any, v: Any, *, scalar_first: bool = True) -> Any:
    """Rotate 3-vectors by quaternions: ``q v q*`` for unit ``q``, ``R(q) @ v`` for any ``q``.

    Args:
        q: quaternions, shape ``(..., 4)``, any non-zero norm (as ``quaternion_to_matrix``); the zero
            quaternion is the identity (``v`` is returned), with a finite gradient.
        v: vectors, shape ``(..., 3)``; the batch dimensions of ``q`` and ``v`` broadcast.
        scalar_first: storage order of ``q``.

    Returns:
        Rotated vectors, shape ``(..., 3)``.
    """
    q, v = match_rank(xp, q, v)
    w, x, y, z = split_quaternion(q, scalar_first)
    vx, vy, vz = v[..., 0], v[..., 1], v[..., 2]
    n2 = w * w + x * x + y * y + z * z
    nonzero = n2 >= xp.finfo(n2.dtype).tiny
    # Normalise first (see quaternion_to_matrix: 2 / n2 overflows float32 gradients at small |q|);
    # the zero quaternion gets inv = 0, so v comes back unchanged.
    inv = xp.where(nonzero, 1.0 / xp.sqrt(xp.where(nonzero, n2, 1.0)), 0.0)
    w, x, y, z = w * inv, x * inv, y * inv, z * inv
    s = 2.0
    # v' = v + 2 (w (u x v) + u x (u x v)), (w, u) the unit quaternion: no matrix is formed.
    cx, cy, cz = y * vz - z * vy, z * vx - x * vz, x * vy - y * vx
    tx, ty, tz = w * cx + (y * cz - z * cy), w * cy + (z * cx - x * cz), w * cz + (x * cy - y * cx)
    return xp.stack([vx + s * tx, vy + s * ty, vz + s * tz], axis=-1)


def _unit_constants() -> tuple[Any, ...]:
    # 1 and 0 as arrays: a Python number in a ``where`` is an operation of its own (``scalar_tensor``)
    # in eager torch; and the identity quaternion (scalar first)
    return 1.0, 0.0, [1.0, 0.0, 0.0, 0.0]


def _inverse_norm(xp: Any, q: Any) -> Any:
    """``1 / |q|`` over the last axis, kept as a unit axis, 0 where the squared norm is below the
    smallest normal number (the componentwise forms' zero quaternion); the double where keeps the
    reciprocal square root and its derivative finite in the branch that is thrown away."""
    one, zero, _ = constants(xp, q, _unit_constants)
    n2 = (q * q).sum(-1, keepdim=True)
    nonzero = n2 >= xp.finfo(q.dtype).tiny
    # 1 / sqrt, not rsqrt: rsqrt's derivative is formed as its value cubed, |q|^-3, which overflows
    # float32 from |q| ~ 1e-13 on, where 1 / sqrt's chain stays near |q|^-2
    return xp.where(nonzero, 1.0 / xp.sqrt(xp.where(nonzero, n2, one)), zero)


@eager_form(of=quaternion_apply)
@nonfinite_by_arithmetic
def quaternion_apply_eager(xp: Any, q: Any, v: Any, *, scalar_first: bool = True) -> Any:
    """:func:`quaternion_apply`, eager form: the same normalisation and the same formula
    ``v + 2 (w (u x v) + u x (u x v))``, its cross products as ``linalg.cross`` over the last axis
    (sixteen operations where the componentwise form takes sixty).

    A NaN or an infinity in a row makes every component NaN by the arithmetic, so the backends add no
    selection after it (three operations where their rule for two arguments takes six): in ``q``, the
    squared norm is NaN or inf, the scale ``1 / |q|`` is 0, and ``u = q / |q|`` holds a NaN (``inf *
    0``) where ``q`` held it; ``v``'s rows add ``(v - v)`` summed (0, or NaN) to the scale, a constant
    of differentiation, which makes all of ``u`` NaN. A NaN in ``w`` reaches every component through
    ``w (u x v)``; one in ``u`` reaches two components of ``u x v`` (a product with each other axis,
    ``0 * NaN`` included) and from there all three of ``u x (u x v)``. (An infinity in ``v`` alone
    would not: ``inf - inf`` is NaN, ``inf + inf`` is not.)"""
    q, v = match_rank(xp, q, v)  # linalg.cross broadcasts only arrays of one rank
    if not scalar_first:
        q = xp.roll(q, 1, -1)
    term = cancelling_factor(xp, (v - v).sum(-1, keepdim=True))
    u = q * (_inverse_norm(xp, q) + term)
    w, axis = u[..., :1], u[..., 1:]
    c = xp.linalg.cross(axis, v, dim=-1)
    return xp.add(v, w * c + xp.linalg.cross(axis, c, dim=-1), alpha=2.0)


# ---------------------------------------------------------------------------------------------------
# The rotation vector.


# NaN or inf reaches every component through the squared angle (cos and sin of inf are NaN), so the
# backends add no selection after it (a pass over the output per operation in eager torch).
@nonfinite_by_arithmetic
@op(axis_angle=(3,))
def axis_angle_to_quaternion(xp: Any, axis_angle: Any, *, scalar_first: bool = True) -> Any:
    """Unit quaternion of a rotation vector (the exponential map).

    Args:
        axis_angle: rotation vectors ``axis * angle`` (angle in radians), shape ``(..., 3)``.
        scalar_first: storage order of the result.

    Returns:
        Unit quaternions ``(cos(angle / 2), sin(angle / 2) axis)``, shape ``(..., 4)``; w >= 0 for
        angles up to pi. The sign is not standardised beyond pi, so that the map stays smooth on all
        of R^3. Gradients are exact at the zero vector (a series, not ``sin(x) / x``).
    """
    vx, vy, vz = axis_angle[..., 0], axis_angle[..., 1], axis_angle[..., 2]
    w, k = exp_factors(xp, vx * vx + vy * vy + vz * vz)  # angle^2: smooth at 0, unlike the angle
    # k v as a broadcast product, not three products stacked with w: XLA would recompute the square
    # root, the sine and the division behind k in each of the four parts of the stack; a broadcast
    # reuses k, which XLA keeps as one array (docs/performance.md, Formula shapes). The same products,
    # the same values.
    v = k[..., None] * axis_angle
    return xp.concat([w[..., None], v] if scalar_first else [v, w[..., None]], axis=-1)


# The Taylor series in u = t^2 of exp_factors: cos(t/2) = 1 - u/8 + u^2/384 - ... and
# sin(t/2)/t = 1/2 - u/48 + u^2/3840 - ..., three terms each (exact below series_threshold).
EXP_SERIES = ((1.0, -1 / 8, 1 / 384), (0.5, -1 / 48, 1 / 3840))


def exp_factors(xp: Any, t2: Any) -> tuple[Any, Any]:
    """``(cos(t / 2), sin(t / 2) / t)`` of ``t2 = t^2``: the quaternion of a rotation vector ``v`` with
    ``|v|^2 = t2`` is ``(w, k v)``. Written once for :func:`axis_angle_to_quaternion` and
    ``quaternion_plus`` (which keeps ``v`` as one array)."""
    small = t2 < series_threshold(xp, t2.dtype)
    # Double where: the closed forms see a safe angle in the branch that is thrown away, so that the
    # derivative of sqrt at 0 (inf) never meets a zero cotangent.
    angle = xp.sqrt(xp.where(small, 1.0, t2))
    half = 0.5 * angle
    # the series (EXP_SERIES) sees 0 where it is not used, so that t2^2 cannot overflow there
    u = xp.where(small, t2, 0.0)
    (w0, w1, w2), (k0, k1, k2) = EXP_SERIES
    w = xp.where(small, w0 + w1 * u + w2 * (u * u), xp.cos(half))
    k = xp.where(small, k0 + k1 * u + k2 * (u * u), xp.sin(half) / angle)
    return w, k


def _exp_constants() -> tuple[Any, ...]:
    # EXP_SERIES' coefficients as arrays (torch.add/addcmul take an array for the constant term), 1, 0,
    # and the coefficients of the nine entries of R(u) = P(u) for a unit u (_core._quadratic_forms)
    (w0, w1, _), (k0, k1, _) = EXP_SERIES
    return w0, w1, k0, k1, 1.0, 0.0, [row[:9] for row in _quadratic_forms()]


def _exp_eager(xp: Any, v: Any) -> Any:
    """:func:`axis_angle_to_quaternion` of ``(..., 3)`` rotation vectors, scalar first, in eighteen
    operations: :func:`exp_factors` with its two factors' series in Horner's form and ``k v`` as one
    broadcast product."""
    w0, w1, k0, k1, one, zero, _ = constants(xp, v, _exp_constants)
    (_, _, w2), (_, _, k2) = EXP_SERIES
    t2 = (v * v).sum(-1, keepdim=True)
    small = t2 < series_threshold(xp, t2.dtype)
    # double where: the closed forms see a safe angle in the branch thrown away (sin(0) / 0 there
    # would make the derivative NaN though the where discards its value)
    angle = xp.sqrt(xp.where(small, one, t2))
    half = 0.5 * angle
    # the series sees 0 where it is not used (no overflow of t2^2); Horner's form
    u = xp.where(small, t2, zero)
    w = xp.where(small, xp.addcmul(w0, u, xp.add(w1, u, alpha=w2)), xp.cos(half))
    k = xp.where(small, xp.addcmul(k0, u, xp.add(k1, u, alpha=k2)), xp.sin(half) / angle)
    return xp.cat([w, k * v], -1)


@eager_form(of=axis_angle_to_quaternion)
def axis_angle_to_quaternion_eager(xp: Any, axis_angle: Any, *, scalar_first: bool = True) -> Any:
    """:func:`axis_angle_to_quaternion`, eager form (:func:`_exp_eager`). A NaN or an infinity reaches
    every component through the angle and the sum of squares, as in the componentwise form."""
    q = _exp_eager(xp, axis_angle)
    return q if scalar_first else xp.roll(q, -1, -1)


def _canonical_components(xp: Any, q: Any, scalar_first: bool) -> Components:
    """Components of ``q`` (zero -> identity) in canonical sign (w > 0; where w = 0 the first non-zero
    of x, y, z positive), so that the angle ``2 atan2(|xyz|, w)`` is in [0, pi] and ``q``, ``-q`` agree."""
    w, x, y, z = nonzero_or_identity(xp, *split_quaternion(q, scalar_first))
    flip = _negative_canonical(w, x, y, z)
    return xp.where(flip, -w, w), xp.where(flip, -x, x), xp.where(flip, -y, y), xp.where(flip, -z, z)


@op(q=(4,))
def quaternion_to_axis_angle(xp: Any, q: Any, *, scalar_first: bool = True) -> Any:
    """Rotation vector of a quaternion (the logarithm map), angle in [0, pi].

    Args:
        q: quaternions, shape ``(..., 4)``, any non-zero norm; ``q`` and ``-q`` give the same vector.
            The zero quaternion is the identity and gives the zero vector.
        scalar_first: storage order of ``q``.

    Returns:
        ``axis * angle``, shape ``(..., 3)``, with ``angle = 2 atan2(|xyz|, |w|)`` in [0, pi] (atan2, not
        acos: accurate near 0 and near pi). At exactly pi (w = 0) the vector takes the sign of the
        canonical quaternion (first non-zero of x, y, z positive): the vector jumps to its antipode
        there, so the function is discontinuous at pi; its gradient stays finite. At the identity it is
        smooth and its gradient exact (a series in ``|xyz|^2 / w^2``).
    """
    w, x, y, z = _canonical_components(xp, q, scalar_first)
    s2 = x * x + y * y + z * z
    # 2 atan2(s, w) / s = (2 / w) atan(r) / r with r = s / w: series in r^2 near the identity. There
    # w >= 1/sqrt(2) |q| > 0, so 1 / w is safe in the branch that is kept.
    small = s2 < series_threshold(xp, s2.dtype) * (w * w)
    # The series only ever sees small arguments (0 elsewhere): no overflow in the branch thrown away.
    r2 = xp.where(small, s2 / xp.where(small, w * w, 1.0), 0.0)
    series = (2.0 / xp.where(small, w, 1.0)) * (1.0 - r2 / 3.0 + r2 * r2 / 5.0)
    s = xp.sqrt(xp.where(small, 1.0, s2))
    closed = 2.0 * xp.atan2(s, w) / s
    k = xp.where(small, series, closed)
    # A broadcast product, not a stack of three: XLA fuses a cheap consumer into its producers by
    # recomputing them, and into each part of a stack it would recompute the atan2 (three per
    # rotation); a broadcast reuses the factor, which XLA then keeps as one array (docs/performance.md,
    # Formula shapes). The same products, the same values.
    return k[..., None] * xp.stack([x, y, z], axis=-1)


def _log_constants() -> tuple[Any, ...]:
    # the identity quaternion; the weights of the canonical sign (the first non-zero component
    # decides: 8, 4, 2, 1 from w to z, as _core.matrix_to_quaternion_eager); 1, 0; the series' 1/6
    return [1.0, 0.0, 0.0, 0.0], [[8.0], [4.0], [2.0], [1.0]], 1.0, 0.0, 1 / 6


def _log_eager(xp: Any, q: Any, unit_canonical: bool = False) -> tuple[Any, Any]:
    """:func:`quaternion_to_axis_angle` of ``(..., 4)`` scalar-first quaternions, vectorised, and their
    norms (``(..., 1)``, for the non-finite rows). Unless ``unit_canonical`` (``matrix_to_quaternion``'s
    result is unit and in canonical sign already): the zero quaternion is the identity, ``q`` is
    divided by its norm, and its sign made canonical, ``sgn(sgn(q) . (8, 4, 2, 1))`` (the first
    non-zero component's: each weight exceeds the sum of those after it).

    On the unit sphere ``2 atan2(s, w) / s`` (``s = |xyz|``) is ``2 asin(s) / s``, whose Taylor series
    in ``u = s^2``, ``2 (1 + u / 6 + 3 u^2 / 40)`` (first term dropped ``5 u^3 / 112``), is used below
    :func:`series_threshold`, as the componentwise form's series in ``s^2 / w^2``: one variable, no
    division."""
    identity, weights, one, zero, sixth = constants(xp, q, _log_constants)
    norm = None
    if not unit_canonical:
        q, norm, zero = _nonzero_or_identity_eager(xp, q, identity)
        q = q / xp.where(zero, one, norm)
        # the sign is piecewise constant: a constant of differentiation (its zero derivative would
        # otherwise cost a backward pass through the product with the weights)
        q = q * xp.sgn(xp.sgn(cancelling_factor(xp, q)) @ weights)
    w, v = q[..., :1], q[..., 1:]
    u = (v * v).sum(-1, keepdim=True)
    small = u < series_threshold(xp, u.dtype)
    # double wheres: the series sees u = 0 where it is not used, atan2 / s sees s = 1
    us = xp.where(small, u, zero)
    series = xp.addcmul(one, us, xp.add(sixth, us, alpha=3 / 40))
    s = xp.sqrt(xp.where(small, one, u))
    return 2.0 * (xp.where(small, series, xp.atan2(s, w) / s) * v), norm


@eager_form(of=quaternion_to_axis_angle)
def quaternion_to_axis_angle_eager(xp: Any, q: Any, *, scalar_first: bool = True) -> Any:
    """:func:`quaternion_to_axis_angle`, eager form (:func:`_log_eager`). The backend's rule makes the
    non-finite rows NaN (``_backend.nonfinite_rows``), as after the componentwise form, which the
    composites (slerp, the splines, IGSO(3)) call without it."""
    return _log_eager(xp, q if scalar_first else xp.roll(q, 1, -1))[0]


# As so3_exp, the same map: every entry reads a component of the quaternion, NaN in a non-finite row.
@nonfinite_by_arithmetic
@op(axis_angle=(3,))
def axis_angle_to_matrix(
    xp: Any, axis_angle: Any, *, to_matrix: Conversion = unit_quaternion_to_matrix
) -> Any:
    """Rotation matrix of a rotation vector ``axis * angle``: shape ``(..., 3)`` to ``(..., 3, 3)``.

    Through the unit quaternion (Rodrigues' formula in half angles), so it is exact and smooth at the
    zero vector, gradient included, and accurate at every angle."""
    # The quaternion (behind cos and sin) is computed once, not again in each of the nine entries.
    return to_matrix(xp, computed_once(xp, axis_angle_to_quaternion(xp, axis_angle)))


# NaN rows by arithmetic, as matrix_to_quaternion's: every component of a NaN quaternion is NaN here.
@nonfinite_by_arithmetic
@op(matrix=(3, 3))
def matrix_to_axis_angle(xp: Any, matrix: Any, *, to_quaternion: Conversion = matrix_to_quaternion) -> Any:
    """Rotation vector ``axis * angle`` of a rotation matrix, angle in [0, pi]: ``(..., 3, 3)`` to
    ``(..., 3)``.

    Through ``matrix_to_quaternion`` (largest pivot, no square root of a pivot) and the atan2 form of
    ``quaternion_to_axis_angle``: accurate near 0 and pi, where ``acos((trace - 1) / 2)`` loses half the
    digits. At exactly pi the vector's sign is that of the canonical quaternion (discontinuous there,
    as every rotation vector must be; the gradient stays finite)."""
    return quaternion_to_axis_angle(xp, to_quaternion(xp, matrix))


def _matrix_of_unit_eager(xp: Any, q: Any) -> Any:
    """The rotation matrix ``(..., 3, 3)`` of scalar-first unit quaternions: the outer product ``q q^T``
    contracted with the constant coefficients of the nine entries (``_core._quadratic_forms``), which
    for ``|q| = 1`` are the entries of ``R(q)`` (as :func:`unit_quaternion_to_matrix`)."""
    *_, forms = constants(xp, q, _exp_constants)
    r = xp.matmul((q[..., :, None] * q[..., None, :]).flatten(-2), forms)
    return r.unflatten(-1, (3, 3))


@eager_form(of=axis_angle_to_matrix)
def axis_angle_to_matrix_eager(
    xp: Any, axis_angle: Any, *, to_matrix: Conversion = unit_quaternion_to_matrix
) -> Any:
    """:func:`axis_angle_to_matrix`, eager form: :func:`_exp_eager`, then :func:`_matrix_of_unit_eager`;
    every entry reads every component of the quaternion, NaN in a non-finite row."""
    return _matrix_of_unit_eager(xp, _exp_eager(xp, axis_angle))


@eager_form(of=matrix_to_axis_angle)
def matrix_to_axis_angle_eager(
    xp: Any, matrix: Any, *, to_quaternion: Conversion = matrix_to_quaternion
) -> Any:
    """:func:`matrix_to_axis_angle`, eager form: the registered conversion (its own eager form), then
    :func:`_log_eager`; a non-finite row's quaternion is NaN throughout, and so is its vector."""
    return _log_eager(xp, to_quaternion(xp, matrix), unit_canonical=True)[0]


# ---------------------------------------------------------------------------------------------------
# Interpolation and distances.


@nonfinite_by_arithmetic
@op(p=(4,), q=(4,), t=())
def quaternion_slerp(xp: Any, p: Any, q: Any, t: Any, *, scalar_first: bool = True) -> Any:
    """Spherical linear interpolation from ``p`` (t = 0) to ``q`` (t = 1) along the shortest arc.

    Args:
        p: the start, quaternions of shape ``(..., 4)``, any non-zero norm (the zero quaternion is the
            identity).
        q: the end, the same.
        t: interpolation parameters, shape ``(...)`` (no trailing axis: one ``t`` per rotation), or a
            Python number (weak in the promotion: a float32 pair stays float32); the batch shapes of
            ``p``, ``q`` and ``t`` broadcast against each other.
        scalar_first: storage order of ``p``, ``q`` and of the result.

    Returns:
        Unit quaternions, shape ``(..., 4)``: ``p exp(t log(p* q))`` with ``p`` normalised and the sign
        of ``q`` chosen so that the arc is the shortest (at most pi). At ``t = 1`` this is ``+-q/|q|``.
        Gradients are exact where ``p = +-q`` (series at the identity); where ``p`` and ``q`` are a
        half-turn apart the shortest arc is not unique, and the gradient is finite.
    """
    p, q, t = match_rank(xp, p, q, t[..., None])
    t = t[..., 0]
    pc = nonzero_or_identity(xp, *split_quaternion(p, scalar_first))
    qc = nonzero_or_identity(xp, *split_quaternion(q, scalar_first))
    pw, px, py, pz = pc
    inv = 1.0 / xp.sqrt(pw * pw + px * px + py * py + pz * pz)
    p_unit = (pw * inv, px * inv, py * inv, pz * inv)
    relative = hamilton((pw, -px, -py, -pz), qc)  # p* q: log() is scale invariant, no division needed
    log = quaternion_to_axis_angle(xp, join_quaternion(xp, *relative, True))  # canonical: shortest arc
    step = axis_angle_to_quaternion(xp, log * t[..., None])
    return join_quaternion(xp, *hamilton(p_unit, split_quaternion(step, True)), scalar_first)


def _slerp_constants() -> tuple[Any, ...]:
    # the coefficients of p* q (_conjugate_hamilton_forms), the identity quaternion, 1 and 0
    c, identity, zero = _conjugate_hamilton_forms()
    return c, identity, 1.0, zero


@eager_form(of=quaternion_slerp)
def quaternion_slerp_eager(xp: Any, p: Any, q: Any, t: Any, *, scalar_first: bool = True) -> Any:
    """:func:`quaternion_slerp`, eager form: the same map, ``p exp(t log(p* q))``, written as Shoemake's
    ``(cos(t phi) - k cos(phi)) p + k q'`` with ``k = sin(t phi) / sin(phi)`` (Shoemake 1985, "Animating
    rotation with quaternion curves", SIGGRAPH), where ``p``, ``q'`` are the unit quaternions, ``q'``
    signed so that ``r = p* q'`` has ``w >= 0`` (the shorter arc) and ``phi = atan2(|r_xyz|, r_w)``:
    ``p (0, r_xyz) = q' - r_w p``, so the second product of the componentwise form is not formed.

    Near ``p = +-q`` (``u = sin(phi)^2`` below :func:`series_threshold`) both factors are series in
    ``u``, so that the value and its derivatives of every order are exact there: ``cos(t phi) = 1 -
    (t^2 / 2) u + O(u^2)`` and ``k = t (1 - (t^2 - 1) u / 6 + O(u^2))``. Two terms: the first term
    dropped is ``t^2 (t^2 - 4) u^2 / 24`` and ``t (t^2 - 1) (t^2 - 9) u^2 / 120``, below ``0.1 eps`` at
    the threshold ``u = sqrt(eps)`` for ``t`` in [0, 1]. The zero quaternion is the identity (squared
    norm below the smallest normal number, as the componentwise form). A NaN or an infinity in ``p``,
    ``q`` or ``t`` reaches every component: each component of ``r`` reads all of ``p`` and ``q``, and
    ``t`` enters both factors (NONFINITE_BY_ARITHMETIC)."""
    if not scalar_first:
        p, q = xp.roll(p, 1, -1), xp.roll(q, 1, -1)
    c, identity, one, zero = constants(xp, p, _slerp_constants)
    p, norm, zero = _nonzero_or_identity_eager(xp, p, identity)
    p = p / xp.where(zero, one, norm)
    q, norm, zero = _nonzero_or_identity_eager(xp, q, identity)
    q = q / xp.where(zero, one, norm)
    r = xp.matmul((p[..., :, None] * q[..., None, :]).flatten(-2), c)
    # the shorter arc: q' = sign(r_w) q, a constant of differentiation (piecewise constant)
    sign = xp.copysign(one, cancelling_factor(xp, r[..., :1]))
    r = r * sign
    cos_phi, axis = r[..., :1], r[..., 1:]
    u = (axis * axis).sum(-1, keepdim=True)
    small = u < series_threshold(xp, u.dtype)
    # double where: the closed forms see sin(phi) = 1 in the branch thrown away, the series u = 0
    sin_phi = xp.sqrt(xp.where(small, one, u))
    t = t[..., None]
    t_phi = t * xp.atan2(sin_phi, cos_phi)
    u = xp.where(small, u, zero)
    t2 = t * t
    k = xp.where(small, t * xp.addcmul(one, t2 - 1.0, u, value=-1 / 6), xp.sin(t_phi) / sin_phi)
    cos_t_phi = xp.where(small, xp.addcmul(one, t2, u, value=-0.5), xp.cos(t_phi))
    out = xp.addcmul(xp.addcmul(cos_t_phi, k, cos_phi, value=-1.0) * p, k * sign, q)
    return out if scalar_first else xp.roll(out, -1, -1)


@nonfinite_by_arithmetic
@op(p=(4,), q=(4,))
def quaternion_geodesic_distance(xp: Any, p: Any, q: Any, *, scalar_first: bool = True) -> Any:
    """Angle of the rotation between ``p`` and ``q``, in [0, pi], blind to the sign of either.

    Args:
        p: quaternions, shape ``(..., 4)``, any non-zero norm; the zero quaternion is the identity.
        q: the same; its batch dimensions broadcast against ``p``'s.
        scalar_first: storage order of ``p`` and ``q``.

    Returns:
        Shape ``(...)``: ``2 atan2(|r_xyz|, |r_w|)`` with ``r = p* q``. Exactly 0 for ``q = +-p``, where
        the gradient is finite (zero: the distance has a kink there, like a norm), and finite at pi.
    """
    p, q = match_rank(xp, p, q)
    pw, px, py, pz = nonzero_or_identity(xp, *split_quaternion(p, scalar_first))
    rw, rx, ry, rz = hamilton(
        (pw, -px, -py, -pz), nonzero_or_identity(xp, *split_quaternion(q, scalar_first))
    )
    angle = 2.0 * xp.atan2(safe_norm(xp, rx * rx + ry * ry + rz * rz), xp.abs(rw))
    # The non-finite rows (NONFINITE_BY_ARITHMETIC): NaN where p or q holds a NaN or an infinity, the
    # sum of 0 * p (_backend.nonfinite_rows' arithmetic, written here so that the eager form can
    # take it from the norms it computes anyway).
    bad = zero_or_nan(xp, cancelling_factor(xp, p), 1) + zero_or_nan(xp, cancelling_factor(xp, q), 1)
    return angle + bad


def _conjugate_hamilton_forms() -> tuple[Any, ...]:
    """(16, 4): the coefficients of ``p_i q_j`` in ``p* q`` (:func:`_hamilton_forms` with the rows of
    ``p``'s vector part negated), the identity quaternion and 0."""
    (c,) = _hamilton_forms()
    return [[-v if i // 4 else v for v in row] for i, row in enumerate(c)], [1.0, 0.0, 0.0, 0.0], 0.0


def _nonzero_or_identity_eager(xp: Any, q: Any, identity: Any) -> tuple[Any, Any, Any]:
    """:func:`nonzero_or_identity` of ``(..., 4)`` scalar-first quaternions in three operations, their
    norm and the mask of the zero ones (``|q| < 2^-63`` in float32 is ``|q|^2`` below the smallest
    normal number, 2^-126, the square root being exact at a power of 4)."""
    norm = xp.linalg.vector_norm(q, 2, -1, True)
    zero = norm < float(xp.finfo(q.dtype).tiny) ** 0.5
    return xp.where(zero, identity, q), norm, zero


@functools.cache
def _half_unit_constants(rank: int) -> Callable[[], tuple[Any, ...]]:
    """The constants of :func:`quaternion_geodesic_distance_eager` for a stack of rank ``rank``: half the
    identity quaternion (scalar first), 0, inf, and the signs (-1, +1) of ``p - q`` and
    ``p + q`` along the stack's first axis, shaped ``(2, 1, ..., 1)`` to broadcast against its rank."""

    def make() -> tuple[Any, ...]:
        signs: list[Any] = [-1.0, 1.0]
        for _ in range(rank - 1):
            signs = _nest(signs)
        return [0.5, 0.0, 0.0, 0.0], 0.0, float("inf"), signs

    return make


def _nest(values: list[Any]) -> list[Any]:
    """Each entry of ``values`` wrapped in one more list: ``[a, b]`` -> ``[[a], [b]]``."""
    return [_nest(v) if isinstance(v, list) else [v] for v in values]


@eager_form(of=quaternion_geodesic_distance)
def quaternion_geodesic_distance_eager(xp: Any, p: Any, q: Any, *, scalar_first: bool = True) -> Any:
    """:func:`quaternion_geodesic_distance`, eager form, in thirteen operations: both quaternions halved to
    norm 1/2 (``u``, ``v``; one stack, one norm, one ``addcdiv``), then ``4 asin(min(|u - v|, |u + v|))``.

    For unit ``p``, ``q`` at an angle ``phi`` in R^4, ``|p -+ q| / 2 = sin(phi / 2)``, ``cos(phi / 2)``, and
    the rotation between them turns by ``2 min(phi, pi - phi)``: four times the arcsine of the smaller
    half-norm, which is at most ``sin(pi / 4)`` (the arcsine's slope at most sqrt 2). The value agrees
    with the componentwise ``2 atan2(|r_xyz|, |r_w|)`` to rounding (the differences carry the same
    cancellation as its 2 x 2 minors near ``q = +-p``). Scalar-last storage is reordered first (``roll``),
    so that the norms sum in one order and the two storage orders agree bit for bit.

    Exactly 0 for ``q = +-p``: ``v = +-u`` bit for bit (the same norm and halving; negation is exact), and
    ``u -+ v`` is one rounding of two terms with coefficients +-1, exactly 0. The zero rule is the
    componentwise form's (``|q| < sqrt(tiny)``: squared norm below the smallest normal number, the square
    root of a power of 4 exact): such a quaternion is divided by inf (to 0) and half the identity added,
    two selections on one mask; every other one is divided by its norm and 0 added. Its gradient is 0,
    and finite for every input. A NaN or an infinity makes the norm NaN or inf and ``x / norm`` NaN
    (``inf / inf``), so every later value of the row is NaN (``min`` propagates NaN):
    NONFINITE_BY_ARITHMETIC. So does a norm that overflows (``|q| > ~1.8e19`` in float32, ``1.3e154``
    in float64: the divisor is ``|x| + 0 |x|``), where ``x / |x|`` would be 0 and the distance silently
    wrong; the componentwise form's squares overflow there too. ``linalg.vector_norm``'s derivative is
    0 at the zero vector (``q = +-p``), as :func:`safe_norm`'s."""
    if p.shape != q.shape:  # static shapes: stack wants one shape
        p, q = xp.broadcast_tensors(p, q)
    x = xp.stack([p, q])
    if not scalar_first:  # one order of summation in the norms, so both orders agree bit for bit
        x = xp.roll(x, 1, -1)
    identity, zero, inf, signs = constants(xp, x, _half_unit_constants(x.ndim))
    norm = xp.linalg.vector_norm(x, 2, -1, True)
    small = norm < float(xp.finfo(x.dtype).tiny) ** 0.5
    half = xp.where(small, identity, zero)
    # |x| + 0 |x|: NaN where the norm overflowed (|x| > ~1.8e19 in float32), where x / |x| would be 0
    divisor = xp.where(small, inf, xp.addcmul(norm, cancelling_factor(xp, norm), zero))
    u, v = xp.addcdiv(half, x, divisor, value=0.5).split(1, 0)
    lo, _ = xp.linalg.vector_norm(xp.addcmul(u, v, signs), 2, -1).min(0)
    return xp.asin(lo) * 4.0


@nonfinite_by_arithmetic
@op(matrix1=(3, 3), matrix2=(3, 3))
def matrix_geodesic_distance(xp: Any, matrix1: Any, matrix2: Any) -> Any:
    """Angle of the rotation ``matrix1^T matrix2`` between two rotation matrices, in [0, pi].

    Args:
        matrix1: rotation matrices, shape ``(..., 3, 3)``.
        matrix2: rotation matrices, shape ``(..., 3, 3)``; batch dimensions broadcast against
            ``matrix1``'s.

    Returns:
        Shape ``(...)``: ``atan2(|axial(M - M^T)| / 2, (trace(M) - 1) / 2)`` with ``M = matrix1^T matrix2``:
        the sine and cosine of the angle, so it is accurate near 0 and pi (``acos`` of the clamped trace
        is not). Exactly 0 for equal matrices, where the gradient is finite (zero), and finite at pi.
    """
    a, b = match_rank(xp, matrix1, matrix2)

    # Only the trace and the skew part of M = a^T b are needed: M_ij = sum_k a_ki b_kj.
    def m(i: int, j: int) -> Any:
        return a[..., 0, i] * b[..., 0, j] + a[..., 1, i] * b[..., 1, j] + a[..., 2, i] * b[..., 2, j]

    trace = m(0, 0) + m(1, 1) + m(2, 2)
    # 2 cos(angle). The trace sums the products of all 18 entries, so a NaN or an infinity in either
    # matrix makes it NaN or infinite, and 0 * trace (constant of differentiation) NaN: the whole row
    # is NaN by this arithmetic (NONFINITE_BY_ARITHMETIC), not by a selection after it.
    cos2 = trace - 1.0 + 0.0 * cancelling_factor(xp, trace)
    sx, sy, sz = m(2, 1) - m(1, 2), m(0, 2) - m(2, 0), m(1, 0) - m(0, 1)  # 2 sin(angle) axis
    return xp.atan2(safe_norm(xp, sx * sx + sy * sy + sz * sz), cos2)


def _skew_and_trace_forms() -> tuple[Any, ...]:
    """(9, 3): the coefficients of the entries of ``M`` (row-major) in ``axial(M - M^T)`` (``M_21 -
    M_12``, ``M_02 - M_20``, ``M_10 - M_01``: each two entries with +-1, the others 0); (9,): those of
    ``trace(M)``; and the bias -1 that makes it ``trace(M) - 1``."""
    c = [[0.0] * 3 for _ in range(9)]
    for i, j, column, sign in (
        (2, 1, 0, 1.0), (1, 2, 0, -1.0),
        (0, 2, 1, 1.0), (2, 0, 1, -1.0),
        (1, 0, 2, 1.0), (0, 1, 2, -1.0),
    ):  # fmt: skip
        c[3 * i + j][column] = sign
    return c, [1.0 if k in (0, 4, 8) else 0.0 for k in range(9)], -1.0


@eager_form(of=matrix_geodesic_distance)
def matrix_geodesic_distance_eager(xp: Any, matrix1: Any, matrix2: Any) -> Any:
    """:func:`matrix_geodesic_distance`, eager form, in nine operations: ``M = a^T b`` as the sum over
    ``k`` of the outer products of the rows ``a_k``, ``b_k`` (elementwise products, then one sum over
    ``k``), then ``axial(M - M^T)`` as one matrix product with constant coefficients, ``trace(M) - 1``
    as one ``addmv`` (a vector per matrix: no split of one product's columns, no reshape of the
    result), and ``atan2(|axial|, trace - 1)``, the componentwise form's formula.

    Why not ``a.mT @ b``: a rotation's distance to itself is exactly 0 only if ``M = a^T a`` comes out
    exactly symmetric, and a BLAS product sums its three terms in an order (and with fused
    multiply-adds) that may differ between entries; ``linalg.cross`` of the rows fuses ``a1 b2 - a2
    b1`` into one multiply-add on CPUs and GPUs that have one, which is not 0 for ``a = b``. Here every
    product is rounded on its own and ``M_ij``, ``M_ji`` are the same three products summed in the same
    order, so ``M`` is exactly symmetric; the product with the coefficients then takes each skew
    component as the difference of two entries (coefficients +-1, the others 0: one rounding, exact
    sign, exactly 0 for a symmetric ``M``), whatever order BLAS sums in. The trace is a sum of three
    entries and rides on no choice: BLAS's order changes it by rounding only.

    Non-finite rows: a NaN or an infinity in either matrix makes a row of ``M`` NaN or infinite, and
    the skew's product multiplies every entry of ``M`` by 0 in two or three of its columns (``0 *
    inf`` and ``0 * NaN`` are NaN in a matrix product), so ``|axial|`` and the result are NaN
    (NONFINITE_BY_ARITHMETIC). ``linalg.vector_norm``'s derivative is 0 at the zero vector (at equal
    rotations and exact half-turns), as :func:`safe_norm`'s."""
    skew_forms, trace_form, minus_one = constants(xp, matrix1, _skew_and_trace_forms)
    if 0 in matrix1.shape or 0 in matrix2.shape:
        # torch 2.13's backward of addmv fails on an empty batch ("outer: Expected 1-D argument")
        return matrix_geodesic_distance(xp, matrix1, matrix2)
    # keepdim: the sum's backward is then one expand, without an unsqueeze
    m = (matrix1[..., :, :, None] * matrix2[..., :, None, :]).sum(-3, keepdim=True)
    flat = m.reshape(-1, 9)
    cos2 = xp.addmv(minus_one, flat, trace_form)
    angle = xp.atan2(xp.linalg.vector_norm(flat @ skew_forms, 2, -1), cos2)
    return angle if m.ndim == 4 else angle.view(m.shape[:-3])
