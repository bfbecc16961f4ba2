"""Representations for neural-network outputs (6D, 9D, 10D) and point-set fitting, over ``xp``.

The 9D and 10D maps go through an SVD or an eigendecomposition, whose library backward passes divide
by differences of singular values or eigenvalues and blow up exactly where these maps are smooth
(the identity has three equal singular values). Their derivatives are therefore written here, once,
in closed forms that only divide where the map itself is singular, and the backends register them as
custom derivatives (``_procrustes_tangent``/``_cotangent``, ``_eigenvector_tangent``/``_cotangent``).
The formulas are written in terms of the *output* and the input with differentiable operations
only, so differentiating the backward again (double backward, ``jacfwd`` of ``grad``) is exact too.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

from ._core import (
    NONFINITE_BY_ARITHMETIC,
    cancelling_factor,
    canonical,
    constants,
    eager_form,
    join_quaternion,
    largest_magnitude,
    nonfinite_by_arithmetic,
    op,
    range_divisor,
    split_quaternion,
    stack_matrix,
    standardize_quaternion,
    zero_or_nan,
)

# ---------------------------------------------------------------------------------------------------
# 6D (Zhou et al., CVPR 2019)


def _dot(xp: Any, a: Any, b: Any) -> Any:
    return xp.sum(a * b, axis=-1, keepdims=True)


def _cross(xp: Any, a: Any, b: Any) -> Any:
    a0, a1, a2 = a[..., 0], a[..., 1], a[..., 2]
    b0, b1, b2 = b[..., 0], b[..., 1], b[..., 2]
    return xp.stack([a1 * b2 - a2 * b1, a2 * b0 - a0 * b2, a0 * b1 - a1 * b0], axis=-1)


def _normalize_or(xp: Any, v: Any, n2: Any, degenerate: Any, fallback: Any) -> Any:
    """``v / sqrt(n2)``, or ``fallback`` where ``degenerate``; finite gradients in both branches."""
    safe = xp.where(degenerate, 1.0, n2)  # the discarded branch never sees 1/sqrt(0)
    return xp.where(degenerate[..., None], fallback, v / xp.sqrt(safe)[..., None])


def _layout_axis(fname: str, layout: str) -> int:
    """The matrix axis that stacks the 6D vectors: -1 (they are columns) or -2 (rows); ``ValueError``
    naming ``fname`` for any other layout."""
    if layout == "columns":
        return -1
    if layout == "rows":
        return -2
    raise ValueError(f"{fname}: expected layout 'columns' or 'rows', got {layout!r}")


_PARALLEL_BELOW = 8.0


@op(d6=(6,))
def rotation_6d_to_matrix(xp: Any, d6: Any, *, layout: str = "columns") -> Any:
    """Rotation matrix from the 6D representation of Zhou et al. (CVPR 2019), by Gram-Schmidt.

    Args:
        d6: shape ``(..., 6)``: two 3-vectors ``(a1, a2)``, unnormalised.
        layout: ``"columns"`` (the default, as in the paper): ``a1`` and ``a2`` are the first two
            **columns** of the matrix. ``"rows"``: they are its first two **rows**, the layout of
            pytorch3d's ``rotation_6d_to_matrix`` (the transpose: weights trained with pytorch3d
            need ``layout="rows"``, or every rotation comes out inverted).

    Returns:
        Rotation matrices, shape ``(..., 3, 3)``, whose columns (rows for ``layout="rows"``) are
        ``b1 = a1/|a1|``, ``b2`` = the normalised part of ``a2`` orthogonal to ``b1``, ``b3 = b1 x b2``.

    Every finite input gives a rotation (orthonormal, det 1, to a few ulps: Gram-Schmidt twice), at
    every scale of ``a1`` and ``a2`` in the dtype's range (each is first divided by its largest
    component). Degenerate input never raises and has finite gradients: where ``a1`` is zero,
    ``b1 = (1, 0, 0)``; where the part of ``a2`` orthogonal to ``b1`` is at most 8 times machine
    epsilon times ``|a2|`` (``a2`` zero or parallel to ``a1`` up to the rounding of one Gram-Schmidt
    pass), ``b2`` is the unit vector orthogonal to ``b1`` in the plane of ``b1`` and the coordinate
    axis least aligned with ``b1`` (the first such axis on ties). So the zero vector gives the
    identity.
    """
    axis = _layout_axis("rotation_6d_to_matrix", layout)
    # a1 and a2 each brought to a largest component of 16 (range_divisor): the map is blind to their
    # positive scales, and no square over- or underflows, up to the largest finite number.
    pair = xp.reshape(d6, (*d6.shape[:-1], 2, 3))
    pair = pair / range_divisor(xp, xp.amax(xp.abs(pair), axis=-1, keepdims=True))
    a1, a2 = pair[..., 0, :], pair[..., 1, :]
    info = xp.finfo(d6.dtype)
    n1 = xp.sum(a1 * a1, axis=-1)
    zero1 = n1 < info.tiny
    ex = xp.stack([xp.ones_like(n1), xp.zeros_like(n1), xp.zeros_like(n1)], axis=-1)
    b1 = _normalize_or(xp, a1, n1, zero1, ex)
    # Gram-Schmidt twice ("twice is enough", Giraud et al., Numer. Math. 101, 2005): one pass leaves
    # a component along b1 of the rounding's size, eps |a2|, which is not small beside a small
    # remainder (columns near parallel: det 0.015 once); the second removes it to eps |u2|, so b2 is
    # orthogonal to b1 to a few ulps for every input.
    u2 = a2 - _dot(xp, b1, a2) * b1
    u2 = u2 - _dot(xp, b1, u2) * b1
    n_u2, n_a2 = xp.sum(u2 * u2, axis=-1), xp.sum(a2 * a2, axis=-1)
    # Below 8 eps |a2| the remainder is the first pass's rounding (at most ~4 eps |a2|), whose
    # direction is the arithmetic's choice: the documented fallback instead, the same on every backend.
    parallel = n_u2 <= (_PARALLEL_BELOW * info.eps) ** 2 * n_a2 + info.tiny
    # Fallback for b2: Gram-Schmidt of the axis e_k with the smallest |b1_k| (<= 1/sqrt(3), so the
    # residual has norm >= sqrt(2/3) and this branch never divides by a small number).
    m = xp.abs(b1)
    k0 = (m[..., 0] <= m[..., 1]) & (m[..., 0] <= m[..., 2])
    k1 = (~k0) & (m[..., 1] <= m[..., 2])
    one, nil = xp.ones_like(n1), xp.zeros_like(n1)
    e = xp.stack([xp.where(k0, one, nil), xp.where(k1, one, nil), xp.where(k0 | k1, nil, one)], axis=-1)
    f = e - _dot(xp, b1, e) * b1
    f = f / xp.sqrt(xp.sum(f * f, axis=-1, keepdims=True))
    b2 = _normalize_or(xp, u2, n_u2, parallel, f)
    b3 = _cross(xp, b1, b2)
    return xp.stack([b1, b2, b3], axis=axis)


def _six_d_constants() -> tuple[Any, ...]:
    # the rows a zero a1 and a zero a2 take (b1 = e_x; a2 stays zero, so that its sine is 0), the axes
    return [[1.0, 0.0, 0.0], [0.0, 0.0, 0.0]], [[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]]


# The eager form's own name: its arithmetic makes every entry of a non-finite row NaN (the Backend
# reads the name of the function it runs), where the componentwise form leaves that to the backend.
NONFINITE_BY_ARITHMETIC.add("rotation_6d_to_matrix_eager")


def rotation_6d_to_matrix_eager(xp: Any, d6: Any, axis: int) -> tuple[Any, Any]:
    """:func:`rotation_6d_to_matrix`, eager form, with the 6D vectors stacked along ``axis`` (-1:
    columns, -2: rows): ``(R, parallel)``, ``parallel`` (``(..., 1)``, bool) where ``b2`` is the
    fallback's. Twenty operations in float32 on the CPU and CUDA, twenty-two otherwise
    (``linalg.cross`` and ``linalg.vector_norm`` are one each).

    The same map by cross products (``b1``, ``a2`` unit here): ``|b1 x a2|`` is the sine between
    them, and ``v = (b1 x w) x b1 = w - (b1 . w) b1`` is Gram-Schmidt's remainder of ``w`` (``a2``, or
    the fallback's axis ``e_k``). ``b1 x w`` has the remainder's rounding error (``eps / sin`` of its
    size, as one Gram-Schmidt pass), but ``v``, a cross product with ``b1``, is orthogonal to ``b1``
    to a few ulps of ``|v|`` whatever that error (what the componentwise form's second pass buys). So
    ``b2 = v / |v|`` and ``b3 = b1 x b2`` are orthonormal to a few ulps, and ``b2`` has the
    componentwise form's conditioning, ``eps / sin``.

    Each vector is normalised at every scale of the dtype's range (1e30 and 1e-30 columns): in float32
    (half precision included) on the CPU and CUDA by its norm accumulated in float64, where no square
    of a float32 over- or underflows, divided there and rounded once to float32 (as fast as the
    scaling below at 262144 rows on the CPU, and more accurate); otherwise (float64, or a device
    without float64) first divided by its largest component (each its own), then by the norm. A zero
    ``a1`` takes ``e_x`` and a zero ``a2`` stays zero (sine 0: the fallback), by one selection of the
    two rows, whose other branch (``0 / 0``) is never read: the rule below differentiates the map
    itself, not these operations. ``parallel``: the sine at most 8 eps, as
    the componentwise form's remainder at most 8 eps ``|a2|``; the fallback's axis is the first of
    the smallest ``|b1_k|`` (``argmin``; a tie of ``|a1|`` components is a tie of ``|b1|``'s).

    A NaN or an infinity makes its vector's row NaN (the norm or the largest component, or ``inf /
    inf`` in one entry, which the cross products spread), and with it ``c``, ``b2`` and ``b3`` (a NaN
    sine is no fallback); ``b1`` adds ``0 * sine``, so that ``a2``'s reaches it too
    (NONFINITE_BY_ARITHMETIC)."""
    zero_rows, axes = constants(xp, d6, _six_d_constants)
    pair = d6.reshape(*d6.shape[:-1], 2, 3)
    if d6.dtype == xp.float32 and d6.device.type in ("cpu", "cuda"):  # devices with float64 (not MPS)
        # The norms accumulated in float64, where no square of a float32 over- or underflows, and the
        # division there, rounded once to float32: no range scaling (two operations fewer).
        norm = xp.linalg.vector_norm(pair, 2, -1, True, dtype=xp.float64)
        unit = xp.where(norm == 0, zero_rows, pair / norm).to(d6.dtype)
    else:
        big = largest_magnitude(xp, pair)
        scaled = pair / big
        unit = xp.where(big == 0, zero_rows, scaled / xp.linalg.vector_norm(scaled, 2, -1, True))
    b1, a2 = unit.unbind(-2)
    sine = xp.linalg.vector_norm(xp.linalg.cross(b1, a2), 2, -1, True)
    parallel = sine <= _PARALLEL_BELOW * xp.finfo(d6.dtype).eps
    w = xp.where(parallel, axes[b1.abs().argmin(-1)], a2)
    v = xp.linalg.cross(xp.linalg.cross(b1, w), b1)
    b2 = v / xp.linalg.vector_norm(v, 2, -1, True)
    return xp.stack([xp.add(b1, sine, alpha=0.0), b2, xp.linalg.cross(b1, b2)], axis), parallel


def rotation_6d_to_matrix_eager_cotangent(
    xp: Any, d6: Any, r: Any, parallel: Any, g: Any | None, gparallel: Any, axis: int
) -> Any:
    """Reverse mode of :func:`rotation_6d_to_matrix_eager`: ``dL/d6`` ``(..., 6)`` for ``g = dL/dR``.

    With ``b1, b2, b3`` the rows of ``B`` (``R`` or its transpose) and ``W = B G^T - G B^T`` (``G``
    likewise), ``W_ij = b_i . g_j - b_j . g_i``, only the rotation's tangent is read:

    - ``dL/da2 = W_32 b3 / (b2 . a2)``: ``a2`` turns ``b2`` towards ``b3`` at the rate ``1 / |u2|``,
      ``|u2| = b2 . a2`` the length of its part orthogonal to ``b1``; 0 where ``b2`` is the
      fallback's (it does not read ``a2``);
    - ``dL/da1 = (W_21 b2 + W_31 b3 - t W_32 b3) / |a1|`` with ``t = (b1 . w) / (b2 . w)`` the
      cotangent of the angle between ``a1`` and ``w`` (``a2``, or the fallback's axis); 0 where
      ``a1`` is zero (``b1 = e_x`` is constant).

    Both read the scaled vectors (``|a1| = |s1| m1`` with ``m1`` the largest component), and a zero
    denominator is taken as infinite, so that each factor is finite in every branch, its derivative
    too: the rule is written in ``d6`` and in the output, so its own autodiff is the second
    derivative."""
    if g is None:
        return None
    _, axes = constants(xp, d6, _six_d_constants)
    basis, gb = (r, g) if axis == -2 else (r.mT, g.mT)
    a = basis @ gb.mT
    w21, w31, w32 = (a - a.mT).flatten(-2)[..., [3, 6, 7]].unsqueeze(-1).unbind(-2)
    b1, b2, b3 = basis.unbind(-2)
    pair = d6.reshape(*d6.shape[:-1], 2, 3)
    big = largest_magnitude(xp, cancelling_factor(xp, pair))
    big = xp.where(big > 0, big, 1.0)
    s1, s2 = (pair / big).unbind(-2)
    m1, m2 = big.unbind(-2)
    w = xp.where(parallel, axes[b1.abs().argmin(-1)], s2)
    t = (b1 * w).sum(-1, keepdim=True) / (b2 * w).sum(-1, keepdim=True)
    n1 = xp.linalg.vector_norm(s1, 2, -1, True) * m1
    d1 = xp.where(n1 > 0, n1, float("inf"))
    d2 = xp.where(parallel, float("inf"), (b2 * s2).sum(-1, keepdim=True) * m2)
    g1 = (w21 * b2 + (w31 - t * w32) * b3) / d1
    g2 = w32 * b3 / d2
    return xp.stack([g1, g2], -2).reshape(d6.shape)


def six_d_eager_rules() -> dict[int, tuple[Callable[..., Any], Callable[..., Any]]]:
    """:func:`rotation_6d_to_matrix_eager` and its rule for each stacking axis (-1: columns, -2: rows),
    ``(forward(xp, d6) -> (R, parallel), cotangent(xp, d6, R, parallel, gR, gparallel))``: what the
    torch backend registers as ``rotation_6d_to_matrix``'s eager form."""

    def rules(axis: int) -> tuple[Callable[..., Any], Callable[..., Any]]:
        def forward(xp: Any, d6: Any) -> tuple[Any, Any]:
            return rotation_6d_to_matrix_eager(xp, d6, axis)

        def cotangent(xp: Any, d6: Any, r: Any, parallel: Any, g: Any, gparallel: Any) -> Any:
            return rotation_6d_to_matrix_eager_cotangent(xp, d6, r, parallel, g, gparallel, axis)

        return forward, cotangent

    return {axis: rules(axis) for axis in (-1, -2)}


def six_d_axis(*, layout: str = "columns") -> int:
    """The key of :func:`six_d_eager_rules` for a call's options: the stacking axis of ``layout``."""
    return _layout_axis("rotation_6d_to_matrix", layout)


@nonfinite_by_arithmetic
@op(matrix=(3, 3))
def matrix_to_rotation_6d(xp: Any, matrix: Any, *, layout: str = "columns") -> Any:
    """The 6D representation of Zhou et al. (CVPR 2019): the first two columns (or rows) of the matrix.

    Args:
        matrix: shape ``(..., 3, 3)``.
        layout: ``"columns"`` (the default, as in the paper) or ``"rows"`` (pytorch3d's layout), as
            in ``rotation_6d_to_matrix``.

    Returns:
        Shape ``(..., 6)``: ``(R[:, 0], R[:, 1])``, i.e. ``(R00, R10, R20, R01, R11, R21)``; with
        ``layout="rows"``, ``(R[0, :], R[1, :])``, i.e. ``(R00, R01, R02, R10, R11, R12)``. For a
        rotation matrix, ``rotation_6d_to_matrix`` of the result in the same layout gives it back.
    """
    if _layout_axis("matrix_to_rotation_6d", layout) == -1:
        out = xp.concat([matrix[..., :, 0], matrix[..., :, 1]], axis=-1)
    else:
        out = xp.concat([matrix[..., 0, :], matrix[..., 1, :]], axis=-1)
    # The non-finite rows (NONFINITE_BY_ARITHMETIC): _backend.nonfinite_rows' sum of 0 * matrix (the
    # third column or row is not read), written here so that the eager form shares its flattening.
    return out + zero_or_nan(xp, cancelling_factor(xp, matrix), 2)[..., None]


def _6d_constants() -> tuple[Any, ...]:
    # the positions of the first two columns in the row-major entries, and a (9, 6) matrix of zeros
    return [0, 3, 6, 1, 4, 7], [[0.0] * 6 for _ in range(9)]


@eager_form(of=matrix_to_rotation_6d)
def matrix_to_rotation_6d_eager(xp: Any, matrix: Any, *, layout: str = "columns") -> Any:
    """:func:`matrix_to_rotation_6d`, eager form, in three operations for a batch of one dimension (a
    view of the flattened entries, the gather of six, one ``addmm``; a view back for any other): the
    non-finite rows as the product of all nine entries with a (9, 6) matrix of zeros added to the six
    (``0 * x`` is +-0 for a finite ``x``, NaN for NaN and +-inf, and a sum of zeros is 0: the very
    numbers), where a sum of ``0 * entries`` and its addition took two more. The product reads the
    entries as a constant of differentiation (its derivative is 0), so the backward pass is that of
    the gather alone."""
    columns, zeros = constants(xp, matrix, _6d_constants)
    flat = matrix.reshape(-1, 9)
    picked = flat[:, columns] if _layout_axis("matrix_to_rotation_6d", layout) == -1 else flat[:, :6]
    out = xp.addmm(picked, cancelling_factor(xp, flat), zeros)
    # a batch of one dimension is already in its shape (a view to it would be one more operation)
    return out if matrix.ndim == 3 else out.view(*matrix.shape[:-2], 6)


# ---------------------------------------------------------------------------------------------------
# 9D (Levinson et al., NeurIPS 2020): the special orthogonal Procrustes problem


def _finite_or_zero(xp: Any, a: Any, trailing: int) -> Any:
    """``a`` with every batch element that holds a NaN or an infinity replaced by zeros, before an SVD
    or an eigendecomposition: LAPACK raises on such input (torch, NumPy) or iterates for minutes, for
    the whole batch. Those elements' results are set to NaN afterwards (the backend's rule for
    non-finite rows), so the zeros are never seen."""
    finite = xp.isfinite(a)
    for _ in range(trailing):
        finite = xp.all(finite, axis=-1)
    return xp.where(xp.reshape(finite, tuple(finite.shape) + (1,) * trailing), a, 0.0)


def _transpose(xp: Any, m: Any) -> Any:
    return xp.swapaxes(m, -1, -2)


def _hat(xp: Any, z: Any) -> Any:
    z0, z1, z2 = z[..., 0], z[..., 1], z[..., 2]
    nil = xp.zeros_like(z0)
    return stack_matrix(xp, [nil, -z2, z1, z2, nil, -z0, -z1, z0, nil])


def _vee_antisymmetric(m: Any) -> Any:
    """vee(m - m^T) as a 3-vector (stacked by the caller)."""
    return m[..., 2, 1] - m[..., 1, 2], m[..., 0, 2] - m[..., 2, 0], m[..., 1, 0] - m[..., 0, 1]


def _solve(xp: Any, a: Any, b: Any) -> Any:
    """``a^{-1} b`` for a small well-conditioned ``a`` (..., n, n) and ``b`` (..., n), by the inverse.

    Not ``linalg.solve``: the derivative formulas are differentiated again (second derivatives, and
    the torch binding's compiled path differentiates them as its forward), and torch 2.13's forward
    rule of ``linalg.solve`` is not itself differentiable (its A^{-1} is a constant LU: jacfwd(jacfwd)
    misses terms, pytorch/pytorch#196695) and is wrong under ``vmap`` (``vmap(hessian)`` of a solve
    differs from the loop by up to 5e6 on rows after the first). ``inv``'s rule, ``-X dA X`` from its
    own output X, differentiates to every order. An inverse is as accurate as a solve where ``a`` is
    well conditioned, which is why the resolvent lifts its null direction (see ``_resolvent``)."""
    return xp.matmul(xp.linalg.inv(a), b[..., None])[..., 0]


def _procrustes_solve(xp: Any, rotation: Any, matrix: Any, x: Any) -> Any:
    """``R hat(z)`` with ``z = (tr(P) I - P + delta I)^{-1} vee(R^T X - X^T R)``, ``P = sym(R^T M)``.

    This is the derivative of the Procrustes map in both directions (X = dM gives dR; X = the
    cotangent of R gives the cotangent of M). Why: R^T M = P is symmetric, so R^T dM - dM^T R =
    Omega P + P Omega with dR = R Omega, Omega = hat(w), and Omega P + P Omega = hat((tr(P) I - P) w)
    for symmetric P. In the basis of M's right singular vectors, tr(P) I - P is diagonal with entries
    s_i + s_j (i != j; the smallest singular value carries the sign of the determinant fix): the
    usual 1/(s_i + s_j) terms, and no 1/(s_i - s_j), so equal singular values are harmless.

    Epsilon: ``delta = sqrt(eps) * tr(P)`` (1 where tr(P) < sqrt(tiny): M = 0) is added to every
    s_i + s_j. It changes the derivative by a relative ``sqrt(eps) * s_1 / (s_i + s_j)`` (1e-8 in
    float64 where M is well conditioned) and bounds its norm by about ``2 |X| / delta``, i.e.
    ``2 |X| / (sqrt(eps) s_1)``, where s_i + s_j vanishes: M of rank <= 1, or det(M) < 0 with
    s_2 = s_3, where the nearest rotation is not unique and no derivative exists.
    """
    info = xp.finfo(matrix.dtype)
    rt = _transpose(xp, rotation)
    p = xp.matmul(rt, matrix)
    p = 0.5 * (p + _transpose(xp, p))
    trace = p[..., 0, 0] + p[..., 1, 1] + p[..., 2, 2]
    floor = info.tiny**0.5
    # The zero matrix (no direction defined at all) gets delta = 1: a bounded, not a huge, gradient.
    delta = xp.where(trace > floor, info.eps**0.5 * trace, 1.0)
    b = stack_matrix(
        xp,
        [
            trace - p[..., 0, 0] + delta, -p[..., 0, 1], -p[..., 0, 2],
            -p[..., 1, 0], trace - p[..., 1, 1] + delta, -p[..., 1, 2],
            -p[..., 2, 0], -p[..., 2, 1], trace - p[..., 2, 2] + delta,
        ],
    )  # fmt: skip
    rhs = xp.stack(_vee_antisymmetric(xp.matmul(rt, x)), axis=-1)
    z = _solve(xp, b, rhs)
    return xp.matmul(rotation, _hat(xp, z))


def procrustes_tangent(xp: Any, matrix: Any, rotation: Any, tangent: Any) -> Any:
    """Forward-mode derivative of ``special_procrustes``: dR for dM = ``tangent``."""
    return _procrustes_solve(xp, rotation, matrix, tangent)


def procrustes_cotangent(xp: Any, matrix: Any, rotation: Any, cotangent: Any) -> Any:
    """Reverse-mode derivative of ``special_procrustes``: dL/dM for dL/dR = ``cotangent``.

    The linear map dM -> dR is self-adjoint up to the map dM -> R^T dM, so the same solve serves
    (see :func:`_procrustes_solve`)."""
    return _procrustes_solve(xp, rotation, matrix, cotangent)


@op(matrix=(3, 3))
def special_procrustes(xp: Any, matrix: Any) -> Any:
    """The rotation nearest to a 3x3 matrix (special orthogonal Procrustes; the 9D representation of
    Levinson et al., NeurIPS 2020).

    Args:
        matrix: any real matrices, shape ``(..., 3, 3)``.

    Returns:
        Shape ``(..., 3, 3)``: ``U diag(1, 1, det(U V^T)) V^T`` for ``M = U diag(s) V^T``, the rotation R
        that minimises ``|R - M|_F`` (equivalently maximises ``tr(R^T M)``). The zero matrix gives the
        identity (the SVD of zero is the identity in LAPACK, cuSOLVER and XLA).

    Gradients (torch and jax) use a closed-form derivative with the usual ``1/(s_i + s_j)`` terms,
    never ``1/(s_i - s_j)``: finite, and correct, at repeated singular values (the identity) and at
    rank 2. Where the nearest rotation is not unique (rank <= 1, or det(M) < 0 with the two smallest
    singular values equal) the derivative is regularised by ``sqrt(eps) * tr(R^T M)`` added to each
    denominator: finite and bounded by about ``2 |dL/dR| / (sqrt(eps) s_1)`` (by ``|dL/dR|`` for M = 0).
    """
    u, _, vh = xp.linalg.svd(_finite_or_zero(xp, matrix, 2))
    # det(U V^T) = +-1; only its sign matters, and the product of the determinants is exact enough.
    flip = xp.linalg.det(u) * xp.linalg.det(vh) < 0
    last = xp.where(flip[..., None, None], -u[..., :, 2:3], u[..., :, 2:3])
    return xp.matmul(xp.concat([u[..., :, 0:2], last], axis=-1), vh)


def _procrustes_forms() -> tuple[Any, ...]:
    """The constants of :func:`procrustes_eager`: ``(1, 1, 0)`` and ``(0, 0, 1)`` as columns (the rows
    of V^T kept and the one that takes the determinant's sign), (3, 9) the coefficients of ``z`` in the nine
    entries of ``hat(z)`` (row-major), (9, 3) those of ``M_ij`` in ``vee(M - M^T)`` (+-1: each entry
    of the result is one rounding of two terms), and the identity."""
    hat = [[0.0] * 9 for _ in range(3)]
    vee = [[0.0] * 3 for _ in range(9)]
    for k, (i, j) in enumerate(((2, 1), (0, 2), (1, 0))):  # z_k sits at (i, j) and -z_k at (j, i)
        hat[k][3 * i + j], hat[k][3 * j + i] = 1.0, -1.0
        vee[3 * i + j][k], vee[3 * j + i][k] = 1.0, -1.0
    eye = [[1.0 if i == j else 0.0 for j in range(3)] for i in range(3)]
    return [[1.0], [1.0], [0.0]], [[0.0], [0.0], [1.0]], hat, vee, eye


def procrustes_eager(xp: Any, matrix: Any) -> tuple[Any]:
    """:func:`special_procrustes`, eager form (torch), ``(R,)``: the same SVD and the same sign test,
    in fewer operations. Non-finite entries are zeroed by one ``nan_to_num`` before the SVD (LAPACK
    raises on them, see :func:`_finite_or_zero`; the backend's rule sets those batch elements to NaN
    after, so which finite matrix they hold is never seen); the determinant's sign scales the last row
    of V^T by +-1 (an exact product, as the componentwise form's negated column of U)."""
    keep, last, *_ = constants(xp, matrix, _procrustes_forms)
    u, _, vh = xp.linalg.svd(matrix.nan_to_num(0.0, 0.0, 0.0))
    # det(U V^T) = +-1, never 0: its sign is the componentwise form's `< 0` test, exactly
    sign = (xp.linalg.det(u) * xp.linalg.det(vh)).sign()
    # U diag(f) V^T as a sum of three products, elementwise: a batched matmul of 3x3 blocks is six
    # operations in eager torch (its expands and views), this four (no choice rides on the sum)
    vf = vh * xp.addcmul(keep, sign.reshape(*sign.shape, 1, 1), last)
    return ((u[..., :, :, None] * vf[..., None, :, :]).sum(-2),)


def procrustes_eager_cotangent(xp: Any, matrix: Any, rotation: Any, cotangent: Any | None) -> Any:
    """:func:`procrustes_cotangent` in vectorised operations (torch): ``B = (tr P + delta) I - P`` as
    one ``addcmul``, ``vee`` and ``hat`` as products with +-1 coefficient tables, the same solve by the
    inverse (differentiable to every order, see :func:`_solve`). None for no cotangent (autograd gives
    none where the rotation's is not asked for)."""
    if cotangent is None:
        return None
    *_, hat, vee, eye = constants(xp, matrix, _procrustes_forms)
    info = xp.finfo(matrix.dtype)
    rt = _transpose(xp, rotation)
    p = xp.matmul(rt, matrix)
    p = 0.5 * (p + _transpose(xp, p))
    trace = p.diagonal(0, -2, -1).sum(-1, keepdim=True)
    # as procrustes_cotangent: the zero matrix gets delta = 1
    delta = xp.where(trace > info.tiny**0.5, info.eps**0.5 * trace, 1.0)
    b = xp.addcmul(-p, (trace + delta)[..., None], eye)
    rhs = xp.matmul(xp.matmul(rt, cotangent).flatten(-2), vee)
    z = xp.matmul(xp.linalg.inv(b), rhs[..., None])[..., 0]
    return xp.matmul(rotation, xp.matmul(z, hat).unflatten(-1, (3, 3)))


def procrustes_eager_rules() -> tuple[Callable[..., Any], ...]:
    """``special_procrustes``'s eager form as ``custom_derivative`` takes it: (prepare, forward,
    cotangent, finish), the input and the result as they are."""

    def identity(xp: Any, x: Any) -> Any:
        return x

    def finish(xp: Any, x: Any, y: Any) -> Any:
        return y

    return identity, procrustes_eager, procrustes_eager_cotangent, finish


# ---------------------------------------------------------------------------------------------------
# 10D (Peretroukhin et al., RSS 2020)

_UPPER = ((0, 0), (0, 1), (0, 2), (0, 3), (1, 1), (1, 2), (1, 3), (2, 2), (2, 3), (3, 3))
_XYZW = (3, 0, 1, 2)  # the position of w, x, y, z in scalar-last storage
_INDEX = {ij: k for k, ij in enumerate(_UPPER)} | {(j, i): k for k, (i, j) in enumerate(_UPPER)}


def _symmetric(xp: Any, a: Any) -> Any:
    """The symmetric 4x4 matrix of a ``(..., 10)`` upper triangle (row by row)."""
    flat = xp.stack([a[..., _INDEX[(i, j)]] for i in range(4) for j in range(4)], axis=-1)
    return xp.reshape(flat, (*flat.shape[:-1], 4, 4))


def _upper(xp: Any, g: Any) -> Any:
    """Adjoint of :func:`_symmetric`: the gradient of the 10 entries from that of the 4x4 matrix."""
    return xp.stack([g[..., i, j] + g[..., j, i] if i != j else g[..., i, i] for i, j in _UPPER], axis=-1)


def _resolvent(xp: Any, a: Any, q: Any, v: Any) -> Any:
    """``-Pi (A - l0 I + delta I)^{-1} Pi v`` with ``Pi = I - q q^T``, ``l0 = q^T A q``: minus the
    pseudo-inverse of ``A - l0 I`` (eigenvalues l_j - l0 off q), regularised.

    Epsilon: ``delta = sqrt(eps) * sum|a|`` (1 where sum|a| < sqrt(tiny): A = 0) is added to every
    gap l_j - l0. It changes the derivative by a relative ``delta / (l_j - l0)`` and bounds it by
    ``|v| / delta`` where the smallest eigenvalue is repeated (and the eigenvector, so the
    derivative, is not defined)."""
    info = xp.finfo(a.dtype)
    mat = _symmetric(xp, a)
    l0 = _dot(xp, q, xp.matmul(mat, q[..., None])[..., 0])
    size = xp.sum(xp.abs(a), axis=-1, keepdims=True)
    floor = size > info.tiny**0.5
    # A = 0 (no eigenvector defined at all) gets delta = 1: a bounded, not a huge, gradient.
    delta = xp.where(floor, info.eps**0.5 * size, 1.0)
    # C = A + (delta - l0) I + kappa q q^T, built entrywise (no eye: jax's strict rank promotion). On
    # q's complement C is A - l0 I + delta I; kappa q q^T lifts C's eigenvalue along q from delta to
    # about |A| (kappa = sum|a|, 1 for A = 0), so C is as well conditioned as the gaps themselves, not
    # 1/sqrt(eps). As q stays an eigenvector of A along any path, C^{-1} Pi v (orthogonal to q) does
    # not depend on kappa, nor do its derivatives. Gaps l_j - l0 are at most 4 sum|a| (|A|_2 <= 2 sum|a|).
    kappa = xp.where(floor, size, 1.0)[..., 0]
    shift = (delta - l0)[..., 0]
    flat = xp.stack(
        [
            (mat[..., i, j] + shift if i == j else mat[..., i, j]) + kappa * q[..., i] * q[..., j]
            for i in range(4)
            for j in range(4)
        ],
        axis=-1,
    )
    c = xp.reshape(flat, (*flat.shape[:-1], 4, 4))
    pv = v - _dot(xp, q, v) * q
    w = _solve(xp, c, pv)
    return -(w - _dot(xp, q, w) * q)


def eigenvector_tangent(xp: Any, a: Any, q: Any, tangent: Any) -> Any:
    """dq for da = ``tangent``: ``dq = -(A - l0 I)^+ dA q`` (first-order perturbation theory)."""
    da = _symmetric(xp, tangent)
    return _resolvent(xp, a, q, xp.matmul(da, q[..., None])[..., 0])


def eigenvector_cotangent(xp: Any, a: Any, q: Any, cotangent: Any) -> Any:
    """dL/da for dL/dq = ``cotangent``: ``dL/dA = -((A - l0 I)^+ g) q^T``, folded onto the 10 entries."""
    k = _resolvent(xp, a, q, cotangent)
    return _upper(xp, k[..., :, None] * q[..., None, :])


def _symmetric_positions() -> tuple[Any, ...]:
    """The constants of the eigenvector's eager form: (16,) the position among the 10 upper entries of
    each entry of the 4x4 matrix (row-major), (10,) the position among the 16 of each upper entry,
    the (4, 4) mask of the upper triangle and the identity."""
    upper = [[1.0 if i <= j else 0.0 for j in range(4)] for i in range(4)]
    eye = [[1.0 if i == j else 0.0 for j in range(4)] for i in range(4)]
    return [_INDEX[(i, j)] for i in range(4) for j in range(4)], [4 * i + j for i, j in _UPPER], upper, eye


def upper_entries(xp: Any, m: Any) -> Any:
    """The ``(..., 10)`` upper triangle (row by row) of ``(..., 4, 4)`` matrices, by one gather (torch):
    the eager forms' :func:`_symmetric` in reverse."""
    _, positions, *_ = constants(xp, m, _symmetric_positions)
    return m.flatten(-2).index_select(-1, positions)


def _eigenvector_prepare(xp: Any, a: Any) -> Any:
    """The symmetric matrix of ``a`` (..., 10), by one gather (torch): its derivative, the gather's
    (a scatter-add), folds the 4x4 cotangent onto the 10 entries as :func:`_upper` does."""
    positions, *_ = constants(xp, a, _symmetric_positions)
    return a.index_select(-1, positions).unflatten(-1, (4, 4))


def _eigenvector_eager(xp: Any, m: Any) -> tuple[Any]:
    """:func:`smallest_eigenvector` of the symmetric matrix ``m`` (..., 4, 4), eager form (torch): the
    same ``eigh`` of the same entries. Non-finite entries are zeroed by one ``nan_to_num`` (LAPACK
    raises on them); the backend's rule sets those batch elements to NaN after."""
    return (xp.linalg.eigh(m.nan_to_num(0.0, 0.0, 0.0))[1][..., :, 0],)


def _eigenvector_eager_cotangent(xp: Any, m: Any, q: Any, cotangent: Any | None) -> Any:
    """:func:`eigenvector_cotangent` in vectorised operations (torch), as a cotangent of the 4x4 matrix
    ``m`` (the gather of :func:`_eigenvector_prepare` folds it): ``k q^T`` with ``k`` the resolvent
    of :func:`_resolvent`, whose ``C`` is one ``addcmul``. None for no cotangent."""
    if cotangent is None:
        return None
    *_, upper, eye = constants(xp, m, _symmetric_positions)
    info = xp.finfo(m.dtype)
    l0 = (q * xp.matmul(m, q[..., None])[..., 0]).sum(-1, keepdim=True)
    size = (m.abs() * upper).sum((-2, -1))[..., None]  # sum |a| over the 10 entries
    floor = size > info.tiny**0.5
    delta = xp.where(floor, info.eps**0.5 * size, 1.0)
    kappa = xp.where(floor, size, 1.0)
    c = xp.addcmul(m, (delta - l0)[..., None], eye) + (kappa * q)[..., :, None] * q[..., None, :]
    pv = cotangent - (q * cotangent).sum(-1, keepdim=True) * q
    w = xp.matmul(xp.linalg.inv(c), pv[..., None])[..., 0]
    k = (q * w).sum(-1, keepdim=True) * q - w
    return k[..., :, None] * q[..., None, :]


def eigenvector_eager_rules() -> tuple[Callable[..., Any], ...]:
    """``smallest_eigenvector``'s eager form as ``custom_derivative`` takes it: (prepare, forward,
    cotangent, finish)."""

    def finish(xp: Any, a: Any, q: Any) -> Any:
        return q

    return _eigenvector_prepare, _eigenvector_eager, _eigenvector_eager_cotangent, finish


def smallest_eigenvector(xp: Any, a: Any) -> Any:
    """Unit eigenvector of the smallest eigenvalue of the symmetric matrix of ``a`` (sign: eigh's)."""
    _, vectors = xp.linalg.eigh(_symmetric(xp, _finite_or_zero(xp, a, 1)))
    return vectors[..., :, 0]


@canonical
@op(a=(10,))
def symmetric_matrix_to_quaternion(
    xp: Any,
    a: Any,
    *,
    scalar_first: bool = True,
    eigenvector: Callable[[Any, Any], Any] = smallest_eigenvector,
) -> Any:
    """Unit quaternion from the 10D representation of Peretroukhin et al. (RSS 2020).

    Args:
        a: shape ``(..., 10)``: the upper triangle of a symmetric 4x4 matrix A, row by row
            ``(a00, a01, a02, a03, a11, a12, a13, a22, a23, a33)``. A's rows and columns are indexed
            in the storage order of the quaternion (w, x, y, z if ``scalar_first``, else x, y, z, w),
            so the result minimises ``q^T A q`` over unit q in the order you store q.
        scalar_first: storage order of the result (and of A's indices).

    Returns:
        Unit quaternions, shape ``(..., 4)``: the eigenvector of A's smallest eigenvalue, in
        canonical sign. Where that eigenvalue is repeated (e.g. A = 0) the eigenvector is whichever
        the backend's ``eigh`` returns (for A = 0: the identity quaternion).

    Gradients (torch and jax) use first-order perturbation theory, ``dq = -(A - l0 I)^+ dA q``,
    which divides only by the gaps ``l_j - l0`` to the smallest eigenvalue (never by the gaps
    between the other eigenvalues): each gap is regularised by adding ``sqrt(eps) * sum|a|`` (1 for
    A = 0), which bounds the gradient where the smallest eigenvalue is repeated.
    """
    if not scalar_first:
        # Re-index A from (x, y, z, w) to (w, x, y, z) (a gather, exact), so that both orders run the
        # very same computation and give bit-identical results.
        a = xp.stack([a[..., _INDEX[(_XYZW[i], _XYZW[j])]] for i, j in _UPPER], axis=-1)
    w, x, y, z = split_quaternion(eigenvector(xp, a), True)
    return standardize_quaternion(
        xp, join_quaternion(xp, w, x, y, z, scalar_first), scalar_first=scalar_first
    )


# ---------------------------------------------------------------------------------------------------
# Fitting (Wahba's problem)


@op(source=(-1, 3), target=(-1, 3), weights=(-1,))
def fit_rotation(
    xp: Any,
    source: Any,
    target: Any,
    weights: Any = None,
    *,
    procrustes: Callable[[Any, Any], Any] = special_procrustes,
) -> Any:
    """The rotation that best maps the points ``source`` onto ``target`` (Wahba's problem, Kabsch).

    Args:
        source: points, shape ``(..., N, 3)``.
        target: the points they should map onto, shape ``(..., N, 3)``; leading dimensions broadcast
            against ``source``'s.
        weights: shape ``(..., N)``, non-negative, or ``None`` for all ones.

    Returns:
        Shape ``(..., 3, 3)``: the rotation R that minimises ``sum_i w_i |R s_i - t_i|^2``, i.e.
        ``special_procrustes`` of ``sum_i w_i t_i s_i^T`` (determinant fixed: never a reflection).
        scipy's equivalent is ``Rotation.align_vectors(target, source, weights)`` (note the order).
        Its gradients are those of ``special_procrustes``.
    """
    # The backend has checked that N is the same in every argument (diffquat._backend).
    n = source.shape[-2]
    shapes = [source.shape[:-2], target.shape[:-2]] + ([] if weights is None else [weights.shape[:-1]])
    batch = tuple(xp.broadcast_shapes(*shapes))
    source = xp.broadcast_to(source, (*batch, n, 3))
    target = xp.broadcast_to(target, (*batch, n, 3))
    if weights is not None:
        target = target * xp.broadcast_to(weights, (*batch, n))[..., None]
    return procrustes(xp, xp.matmul(_transpose(xp, target), source))
