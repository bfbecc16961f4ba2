"""Quaternion algebra and the rotation vector (the exponential and logarithm of SO(3)), over ``xp``.

The rotation vector lives here beside the algebra because ``quaternion_slerp`` is written with it:
``slerp(p, q, t) = p exp(t log(p* q))``, so the series that make ``exp`` and ``log`` exact and smooth at
the identity also make slerp's gradient correct where ``p = +-q``.
"""

from __future__ import annotations

from typing import Any

from ._core import (
    Conversion,
    _negative_canonical,
    computed_once,
    constants,
    eager_form,
    join_quaternion,
    matrix_to_quaternion,
    nonfinite_by_arithmetic,
    op,
    split_quaternion,
    unit_quaternion_to_matrix,
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
    return [xp.reshape(a, (1,) * (rank - a.ndim) + tuple(a.shape)) for a in arrays]


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
    nonzero = w * w + x * x + y * y + z * z >= xp.finfo(q.dtype).tiny
    # Scaled by m = max |q_i| first: the result grows as 1/|q|, so on a chain through n2 = |q|^2 the
    # derivative reaches |q|^-3 (1e45 at |q| = 1e-15, past float32). With p = q / m, |p|^2 lies in
    # [1, 4] and the largest intermediate derivative is 1/m^2. conj(q) / |q|^2 = conj(p) / (m |p|^2).
    # Double wheres: the discarded branch divides by 1, so everything stays finite at q = 0.
    m = xp.maximum(xp.maximum(xp.abs(w), xp.abs(x)), xp.maximum(xp.abs(y), xp.abs(z)))
    inv_m = xp.where(nonzero, 1.0 / xp.where(nonzero, m, 1.0), 0.0)
    w, x, y, z = w * inv_m, x * inv_m, y * inv_m, z * inv_m
    n2 = w * w + x * x + y * y + z * z
    s = xp.where(nonzero, inv_m / xp.where(nonzero, n2, 1.0), 0.0)
    return join_quaternion(xp, w * s, -x * s, -y * s, -z * s, scalar_first)
    n2 = w * w + x * x + y * y + z * z
    nonzero = n2 >= xp.finfo(n2.dtype).tiny
    # Through 1/|q| twice, not 1/|q|^2 once: d(1/n2)/dn2 = -1/n2^2 on the reverse chain overflows
    # float32 for |q| below ~3e-10 (see quaternion_to_matrix). Double where: the discarded branch
    # sees n2 = 1, so 1/sqrt and its derivative stay finite at 0.
    inv = xp.where(nonzero, 1.0 / xp.sqrt(xp.where(nonzero, n2, 1.0)), 0.0)
    return join_quaternion(
        xp, (w * inv) * inv, -(x * inv) * inv, -(y * inv) * inv, -(z * inv) * inv, scalar_first
    )


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


# ---------------------------------------------------------------------------------------------------
# Interpolation and distances.


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
    return 2.0 * xp.atan2(safe_norm(xp, rx * rx + ry * ry + rz * rz), xp.abs(rw))


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

    cos2 = m(0, 0) + m(1, 1) + m(2, 2) - 1.0  # 2 cos(angle)
    sx, sy, sz = m(2, 1) - m(1, 2), m(0, 2) - m(2, 0), m(1, 0) - m(0, 1)  # 2 sin(angle) axis
    return xp.atan2(safe_norm(xp, sx * sx + sy * sy + sz * sz), cos2)
