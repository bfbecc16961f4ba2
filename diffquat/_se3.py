"""SE(3), rigid transforms, over ``xp``: building and splitting poses, composing, inverting and applying
them, hat and vee, exp and log, the adjoints, the four Jacobians, the perturbations plus and minus, and
interpolation.

Conventions, written once (each docstring repeats the part its function needs):

- A pose is a ``(..., 4, 4)`` homogeneous matrix ``T = [[R, t], [0, 1]]`` acting on column vectors,
  ``p' = R p + t``. Only the top three rows are read (the bottom row is taken to be ``(0, 0, 0, 1)``),
  and every pose returned has that bottom row exactly.
- A tangent vector (a twist) is ``(..., 6)``, **translation first**: ``xi = (rho, phi)``, and
  ``hat(xi) = [[hat(phi), rho], [0, 0]]``. This is Barfoot's, jaxlie's, pypose's, lietorch's, Sophus'
  and manif's order; scipy's ``RigidTransform.from_exp_coords`` takes ``(phi, rho)``.
- ``exp(xi) = [[exp(phi), J_l(phi) rho], [0, 1]]`` (the matrix exponential of ``hat(xi)``), ``log`` its
  inverse with ``|phi|`` in [0, pi].
- ``Ad(T) = [[R, hat(t) R], [0, R]]``, so that ``T exp(xi) T^-1 = exp(Ad(T) xi)``;
  ``ad(xi) = [[hat(phi), hat(rho)], [0, hat(phi)]]``.
- Jacobians: ``exp(xi + d) = exp(J_l(xi) d) exp(xi) = exp(xi) exp(J_r(xi) d)`` to first order,
  ``J_l(xi) = sum_n ad(xi)^n / (n + 1)! = [[J_l(phi), Q(rho, phi)], [0, J_l(phi)]]`` and
  ``J_r(xi) = J_l(-xi)``; ``J_l(xi) = Ad(exp(xi)) J_r(xi)``.
- Perturbations: ``plus(T, d) = T exp(d)`` (``side="right"``, the default) or ``exp(d) T``
  (``side="left"``); ``minus(T1, T2) = log(T2^-1 T1)`` or ``log(T1 T2^-1)``, so that
  ``plus(T2, minus(T1, T2, side=s), side=s) = T1``.

Numerics: ``Q`` (Barfoot, "State Estimation for Robotics", 2017, eq. 7.86) is
``Q = rho^/2 + c1 (phi^ rho^ + rho^ phi^ + phi^ rho^ phi^) + c2 (phi^^ rho^ + rho^ phi^^ - 3 phi^ rho^ phi^)
+ c3 (phi^ rho^ phi^^ + phi^^ rho^ phi^)`` with ``c1 = (t - sin t) / t^3``,
``c2 = (t^2 + 2 cos t - 2) / (2 t^4)``, ``c3 = (2 t - 3 sin t + t cos t) / (2 t^5)``. The products of
skew matrices reduce to outer products of ``phi``, ``rho`` and ``phi x rho`` (see :func:`_q_block`):
no 3x3 matrix products, and the three coefficients are Taylor series in ``u = t^2`` below ``t = 2``,
where their closed forms cancel (:data:`Q_SERIES_BELOW`).
"""

from __future__ import annotations

import math
from collections.abc import Callable
from typing import Any

from ._algebra import axis_angle_to_matrix, match_rank, matrix_to_axis_angle
from ._core import (
    NONFINITE_BY_ARITHMETIC,
    Conversion,
    _quadratic_forms,
    cancelling_factor,
    computed_once,
    constants,
    eager_form,
    matrix_to_quaternion,
    nonfinite_by_arithmetic,
    op,
    quaternion_to_matrix,
    range_divisor,
    small_matmul,
    stack_matrix,
    unit_quaternion_to_matrix,
)
from ._lie import (
    _B_SERIES,
    _assemble,
    _assemble_eager,
    _components,
    _inverse_coefficients,
    _inverse_coefficients_eager,
    _jacobian_coefficients,
    _jacobian_coefficients_eager,
    _jacobian_forms,
    _series,
    _series_eager,
    _series_tables,
    check_side,
    so3_hat,
    so3_vee,
)
from ._representations import rotation_6d_to_matrix

INTERPOLATION_MODES = ("screw", "decoupled")
# The 7-vector layouts of the peers, as (quaternion first, scalar first): jaxlie and kornia store
# (w, x, y, z, tx, ty, tz); ROS geometry_msgs/Pose, pypose, lietorch and manif (tx, ty, tz, x, y, z, w);
# Sophus' parameters (x, y, z, w, tx, ty, tz); theseus (tx, ty, tz, w, x, y, z).
POSE_LAYOUTS = {
    "wxyz_xyz": (True, True),
    "xyz_xyzw": (False, False),
    "xyzw_xyz": (True, False),
    "xyz_wxyz": (False, True),
}


# ---------------------------------------------------------------------------------------------------
# Building blocks


def _with_bottom(xp: Any, top: Any) -> Any:
    """``(..., 3, 4)`` top rows with the exact bottom row ``(0, 0, 0, 1)`` appended: ``(..., 4, 4)``.
    The constants are made from the input (``zeros_like``): on its device, with no derivative."""
    corner = top[..., :1, 3:]
    zero = xp.zeros_like(corner)
    return xp.concat([top, xp.concat([zero, zero, zero, xp.ones_like(corner)], axis=-1)], axis=-2)


def _blocks(xp: Any, a: Any, b: Any, c: Any) -> Any:
    """The ``(..., 6, 6)`` block upper-triangular matrix ``[[a, b], [0, c]]`` of 3x3 blocks."""
    top = xp.concat([a, b], axis=-1)
    return xp.concat([top, xp.concat([xp.zeros_like(a), c], axis=-1)], axis=-2)


def _split(xi: Any) -> tuple[Any, Any]:
    """``(rho, phi)`` of twists ``(..., 6)``, translation first."""
    return xi[..., :3], xi[..., 3:]


def _column(x: Any) -> Any:
    return x[..., None]


def _cross(xp: Any, a: Any, b: Any) -> Any:
    return xp.linalg.cross(a, b)


def _dot(xp: Any, a: Any, b: Any) -> Any:
    return xp.sum(a * b, axis=-1, keepdims=True)


# ---------------------------------------------------------------------------------------------------
# Poses as matrices


@op(rotation=(3, 3), translation=(3,))
def se3_from_rotation_translation(xp: Any, rotation: Any, translation: Any) -> Any:
    """The pose ``[[R, t], [0, 1]]`` of a rotation matrix and a translation.

    Args:
        rotation: rotation matrices ``R``, shape ``(..., 3, 3)`` (used as they are, not projected).
        translation: translations ``t``, shape ``(..., 3)``; the batch shapes broadcast.

    Returns:
        Poses, shape ``(..., 4, 4)``, with the bottom row ``(0, 0, 0, 1)`` exactly; they map a point
        ``p`` (column vector) to ``R p + t``.
    """
    r, t = match_rank(xp, rotation, _column(translation))
    batch = tuple(xp.broadcast_shapes(tuple(r.shape[:-2]), tuple(t.shape[:-2])))
    r, t = xp.broadcast_to(r, (*batch, 3, 3)), xp.broadcast_to(t, (*batch, 3, 1))
    return _with_bottom(xp, xp.concat([r, t], axis=-1))


@nonfinite_by_arithmetic
@eager_form(of=se3_from_rotation_translation)
def se3_from_rotation_translation_eager(xp: Any, rotation: Any, translation: Any) -> Any:
    """:func:`se3_from_rotation_translation`, eager form: ``[R | t]`` (one ``cat``), padded with a zero
    bottom row, plus the bias ``e4 e4^T`` and the non-finite term ``[R | t] - [R | t]`` summed (0, or
    NaN in every entry of a row with a non-finite input)."""
    _, corner, *_ = constants(xp, rotation, _pose_masks)
    t = translation[..., None]
    if rotation.shape[:-2] != t.shape[:-2]:
        batch = tuple(xp.broadcast_shapes(tuple(rotation.shape[:-2]), tuple(t.shape[:-2])))
        rotation, t = xp.broadcast_to(rotation, (*batch, 3, 3)), xp.broadcast_to(t, (*batch, 3, 1))
    top = xp.cat([rotation, t], -1)
    term = cancelling_factor(xp, (top - top).sum((-2, -1), keepdim=True))
    return xp.nn.functional.pad(top, (0, 0, 0, 1)) + (corner + term)


@op(matrix=(4, 4))
def se3_to_rotation_translation(xp: Any, matrix: Any) -> Any:
    """The rotation and the translation of poses: ``(R, t)`` of ``T = [[R, t], [0, 1]]``.

    Args:
        matrix: poses, shape ``(..., 4, 4)`` (the bottom row is not read).

    Returns:
        ``(rotation, translation)``, shapes ``(..., 3, 3)`` and ``(..., 3)``: ``T``'s entries. A NaN or
        an infinity anywhere in a pose makes both NaN.
    """
    # The core gives R (row-major) and t as one array [R_00, ..., R_22, t_0, t_1, t_2], (..., 12), so
    # that the backends' rule for non-finite rows applies to both parts at once; each backend's wrapper
    # splits it (one split and one reshape in eager torch, where the rows [R | t] took a slice and a
    # select after the slice of the top rows).
    top = matrix[..., :3, :]
    return xp.concat([xp.reshape(top[..., :3], (*top.shape[:-2], 9)), top[..., 3]], axis=-1)


def _rotation_translation_selection() -> tuple[Any, ...]:
    """(16, 12): the coefficients of a pose's entries (row-major) in ``[R (row-major) | t]``, one 1 in
    each column and the other entries 0; (16, 1): zeros."""
    c = [[0.0] * 12 for _ in range(16)]
    for i in range(3):
        for j in range(3):
            c[4 * i + j][3 * i + j] = 1.0
        c[4 * i + 3][9 + i] = 1.0
    return c, [[0.0]] * 16


@nonfinite_by_arithmetic
@eager_form(of=se3_to_rotation_translation)
def se3_to_rotation_translation_eager(xp: Any, matrix: Any) -> Any:
    """:func:`se3_to_rotation_translation`, eager form: the flattened poses times a constant (16, 12)
    selection, plus the term of non-finite rows, the flattened poses times a zero column (three
    operations, the flattening a view; the slice and the backend's rule for non-finite rows took four).

    The term is the sum of ``0 * x`` over the pose (``_core.zero_or_nan``, as one matrix product): 0
    for a finite pose, NaN for one with a NaN or an infinity anywhere, its bottom row included (``0 *
    inf`` and ``0 * NaN`` are NaN in a matrix product), a constant of differentiation. Each entry of
    the selection is one entry of the pose plus fifteen products by 0, and the term is 0: exact for
    finite poses, whatever order BLAS sums in (``x + 0 = x``; a ``-0`` may come out ``+0``, as after
    the backend's rule). The selection alone would leave an infinite entry infinite in the column
    that selects it; with the term, every entry of a non-finite pose is NaN (NONFINITE_BY_ARITHMETIC).
    The derivative is the selection's transpose, the identity on ``R`` and ``t``, 0 on the bottom
    row, as the componentwise form's."""
    c, zero = constants(xp, matrix, _rotation_translation_selection)
    flat = matrix.reshape(-1, 16)  # addmm takes matrices: one batch axis
    out = xp.addmm(cancelling_factor(xp, flat) @ zero, flat, c)
    return out if matrix.ndim == 3 else out.reshape(*matrix.shape[:-2], 12)


# Composing, inverting and applying make non-finite rows NaN by their arithmetic (the backends add
# no selection after them, see _core.NONFINITE_BY_ARITHMETIC): a term that is 0 for a pose whose
# entries (its bottom row's too) are all finite and NaN otherwise, ``x - x`` summed, is added to every
# entry of the result, and the bottom row is (0, 0, 0, 1) plus that term. It is a constant of
# differentiation (``cancelling_factor``): its derivative is 0 wherever it is finite.


def _same_rank(xp: Any, *arrays: Any) -> Any:
    """The arrays with unit axes prepended to the same rank (``match_rank``), reshaped only where the
    ranks differ: each reshape is an operation of its own in eager torch."""
    return arrays if len({x.ndim for x in arrays}) == 1 else match_rank(xp, *arrays)


def _nonfinite_term(xp: Any, zero: Any, trailing: int) -> Any:
    """The sum of ``zero`` (0 or NaN entries, such as ``x - x``: an exact 0 for every finite entry, so
    that no sum overflows) over its last ``trailing`` axes, kept as unit axes: 0, or NaN where any entry
    is NaN, whatever the order of the additions. One ``sum`` (one operation in eager torch and NumPy),
    except on the namespace that compiles through XLA (the one with ``optimization_barrier``, as in
    ``_core.computed_once``): there the slices are unstacked and added, which XLA:CPU fuses into the
    loop that uses the term, where a reduction was a slower loop of its own (docs/performance.md,
    SE(3))."""
    if getattr(xp, "optimization_barrier", None) is None:
        return xp.sum(zero, axis=tuple(range(-trailing, 0)), keepdims=True)
    for _ in range(trailing):
        first, *rest = xp.unstack(zero, axis=-1)
        zero = first
        for part in rest:
            zero = zero + part
    return xp.reshape(zero, (*zero.shape, *(1,) * trailing))


def _bottom_row(xp: Any, term: Any) -> Any:
    """``(0, 0, 0, 1) + term`` for a term of shape ``(..., 1, 1)``: ``(..., 1, 4)``."""
    return xp.concat([term, term, term, term + xp.ones_like(term)], axis=-1)


def _compose(xp: Any, a: Any, b: Any, term: Any) -> Any:
    """``T1 T2`` of poses ``a``, ``b`` of one rank, with ``term`` ``(..., 1, 1)`` (0 or NaN, of the
    broadcast batch shape) in every entry: ``R1 [R2 | t2] + t1 (term, term, term, 1 + term)`` over the
    bottom row ``(0, 0, 0, 1) + term``."""
    row = _bottom_row(xp, term)
    # One matrix product, contracting over 3: R1 [R2 | t2]. XLA:CPU compiles the same product
    # contracting over 4 ([R1 | t1] times a 4x4 matrix) into a far slower dot; eager torch runs either
    # as one call (docs/performance.md, SE(3)).
    top = small_matmul(xp, a[..., :3, :3], b[..., :3, :]) + a[..., :3, 3:] * row
    return xp.concat([top, row], axis=-2)


@nonfinite_by_arithmetic
@op(matrix1=(4, 4), matrix2=(4, 4))
def se3_compose(xp: Any, matrix1: Any, matrix2: Any) -> Any:
    """The composition ``T1 T2`` of poses: ``[[R1 R2, R1 t2 + t1], [0, 1]]`` (apply ``T2``, then ``T1``).

    Args:
        matrix1: poses ``T1``, shape ``(..., 4, 4)``.
        matrix2: poses ``T2``, shape ``(..., 4, 4)``; the batch shapes broadcast. The bottom rows are
            not read.

    Returns:
        Shape ``(..., 4, 4)``, the bottom row exactly ``(0, 0, 0, 1)``.
    """
    a, b = _same_rank(xp, matrix1, matrix2)
    # one term for both poses: (a - a) b is 0, or NaN where an entry of either is not finite
    return _compose(xp, a, b, cancelling_factor(xp, _nonfinite_term(xp, (a - a) * b, 2)))


@nonfinite_by_arithmetic
@op(matrix=(4, 4))
def se3_inverse(xp: Any, matrix: Any) -> Any:
    """The inverse of poses in closed form: ``[[R^T, -R^T t], [0, 1]]`` (not a general matrix inverse).

    Args:
        matrix: poses ``T``, shape ``(..., 4, 4)``, with rotation matrices ``R`` (``R^T`` is used as the
            inverse of ``R``); the bottom row is not read.

    Returns:
        Shape ``(..., 4, 4)``, the bottom row exactly ``(0, 0, 0, 1)``.
    """
    term = cancelling_factor(xp, _nonfinite_term(xp, matrix - matrix, 2))
    r_t = xp.swapaxes(matrix[..., :3, :3], -1, -2)
    # R^T t as a matrix-vector product: XLA writes it as a multiply and a sum, eager torch as one call
    top = xp.concat([r_t + term, term - small_matmul(xp, r_t, matrix[..., :3, 3:])], axis=-1)
    return xp.concat([top, _bottom_row(xp, term)], axis=-2)


@nonfinite_by_arithmetic
@op(matrix=(4, 4), points=(3,))
def se3_apply(xp: Any, matrix: Any, points: Any) -> Any:
    """Poses applied to points: ``R p + t``.

    Args:
        matrix: poses ``T = [[R, t], [0, 1]]``, shape ``(..., 4, 4)``.
        points: points ``p``, shape ``(..., 3)``; the batch shapes broadcast (a pose of shape ``(4, 4)``
            and points of shape ``(N, 3)`` give ``(N, 3)``).

    Returns:
        Shape ``(..., 3)``.
    """
    m, p = _same_rank(xp, matrix, _column(points))
    term = cancelling_factor(xp, _nonfinite_term(xp, m - m, 2) + _nonfinite_term(xp, p - p, 2))
    # [R | t] times (p + term, 1 + term): the term reaches every component through the product, and
    # no elementwise pass follows it, which inductor would run as a loop over the trailing 3
    return small_matmul(xp, m[..., :3, :], xp.concat([p + term, term + xp.ones_like(term)], axis=-2))[..., 0]


# Eager forms (_core.EAGER_FORMS: eager torch outside graph capture) of composing, inverting and
# applying: one batched product of 4x4 matrices whose bottom rows are set by a constant mask and bias
# (one ``addcmul`` each), and the non-finite term of the componentwise forms, from the inputs (so that
# a finite pose whose result overflows keeps the componentwise result), added once.


def _pose_masks() -> tuple[list[Any], ...]:
    """(4, 4) constants: the mask of the top rows, the bias ``e4 e4^T`` (the bottom row (0, 0, 0, 1)),
    the mask of the top-left 3x3 block, the negated translation column, the identity."""
    top = [[1.0] * 4 if i < 3 else [0.0] * 4 for i in range(4)]
    corner = [[1.0 if i == j == 3 else 0.0 for j in range(4)] for i in range(4)]
    block = [[1.0 if i < 3 and j < 3 else 0.0 for j in range(4)] for i in range(4)]
    column = [[-1.0 if i < 3 and j == 3 else 0.0 for j in range(4)] for i in range(4)]
    eye = [[1.0 if i == j else 0.0 for j in range(4)] for i in range(4)]
    return top, corner, block, column, eye


def _product(xp: Any, a: Any, b: Any) -> Any:
    """``a @ b`` of ``(..., n, k)`` and ``(..., k, m)``: ``bmm`` (one operation) where both are
    ``(B, n, k)`` with one ``B``, else ``matmul``, which broadcasts (a few views more)."""
    if a.ndim == b.ndim == 3 and a.shape[0] == b.shape[0]:
        return xp.bmm(a, b)
    return xp.matmul(a, b)


@eager_form(of=se3_compose)
def se3_compose_eager(xp: Any, matrix1: Any, matrix2: Any) -> Any:
    """:func:`se3_compose`, eager form: ``P1 P2`` with ``P = T``'s top rows over ``(0, 0, 0, 1)``: the
    second one ``T2`` with its bottom row replaced by ``(0, 0, 0, 1)``; the first ``T1`` with its bottom
    row replaced by ``term`` (0, or NaN for a pose with a non-finite entry in either input: ``(T1 - T1)
    T2`` summed), which also reaches every entry of a bad pose, its bias added by the product
    (``baddbmm``). The bottom row is ``term P2 + (0, 0, 0, 1) = (0, 0, 0, 1)`` exactly.

    Each replacement is a ``lerp`` from the bias to ``T`` with the top rows' 0/1 mask as the weight:
    ``bias + 1 (T - bias)`` is ``T`` exactly there (torch evaluates a weight of 1 as ``T - (T - bias)
    0``), and ``bias + 0 (T - bias)`` the bias. Its derivative in ``T`` is one product (the mask),
    where ``addcmul``'s is two (``mask * value``, then the product). Six operations for one batch
    dimension, as a bare ``matmul`` of poses (which gives neither the bottom row nor the non-finite
    rows); six for the backward pass, where the bare product's takes seven."""
    top, corner, *_ = constants(xp, matrix1, _pose_masks)
    term = cancelling_factor(xp, ((matrix1 - matrix1) * matrix2).sum((-2, -1), keepdim=True))
    a, b = xp.lerp(term, matrix1, top), xp.lerp(corner, matrix2, top)
    if a.ndim == b.ndim == 3 and a.shape[0] == b.shape[0]:
        return xp.baddbmm(corner, a, b)
    return xp.matmul(a, b) + corner


@eager_form(of=se3_inverse)
def se3_inverse_eager(xp: Any, matrix: Any) -> Any:
    """:func:`se3_inverse`, eager form: ``[[R^T, 0], [0, 1]] [[I, -t], [0, 1]]``, each factor one
    ``addcmul`` of ``T`` (transposed, for the first) with a constant mask and bias; the non-finite term
    ``T - T`` summed rides on the first factor's bias. Six operations for one batch dimension."""
    _, corner, block, column, eye = constants(xp, matrix, _pose_masks)
    term = cancelling_factor(xp, (matrix - matrix).sum((-2, -1), keepdim=True))
    return _product(xp, xp.addcmul(corner + term, matrix.mT, block), xp.addcmul(eye, matrix, column))


@eager_form(of=se3_apply)
def se3_apply_eager(xp: Any, matrix: Any, points: Any) -> Any:
    """:func:`se3_apply`, eager form: ``T (p, 1)`` as a product summed over the last axis (it
    broadcasts any batch shapes), plus the non-finite term: ``(T - T) (p, 1)`` summed over all four
    rows, so that a non-finite entry of either input, the bottom row's included, makes the whole
    result NaN. Ten operations for one batch dimension."""
    ph = xp.nn.functional.pad(points, (0, 1), value=1.0)[..., None, :]
    term = cancelling_factor(xp, ((matrix - matrix) * ph).sum((-2, -1)))
    return (matrix * ph).sum(-1)[..., :3] + term[..., None]


# ---------------------------------------------------------------------------------------------------
# hat and vee, exp and log


@op(xi=(6,))
def se3_hat(xp: Any, xi: Any) -> Any:
    """The ``(..., 4, 4)`` matrix of twists ``xi = (rho, phi)`` (translation first):
    ``[[hat(phi), rho], [0, 0]]``; ``se3_vee`` is its inverse.

    Args:
        xi: twists, shape ``(..., 6)``, translation ``rho`` first, then rotation ``phi``.

    Returns:
        Shape ``(..., 4, 4)``, with ``hat(phi) v = phi x v`` and a zero bottom row.
    """
    rho, phi = _split(xi)
    top = xp.concat([so3_hat(xp, phi), _column(rho)], axis=-1)
    return xp.concat([top, xp.zeros_like(top[..., :1, :])], axis=-2)


@op(matrix=(4, 4))
def se3_vee(xp: Any, matrix: Any) -> Any:
    """The twist ``(rho, phi)`` of a ``(..., 4, 4)`` matrix, the inverse of ``se3_hat``: ``rho`` is the
    top of the last column, ``phi`` the vector of the skew part of the top-left block.

    Args:
        matrix: any matrices, shape ``(..., 4, 4)`` (the bottom row is not read).

    Returns:
        Shape ``(..., 6)``, translation first.
    """
    return xp.concat([matrix[..., :3, 3], so3_vee(xp, matrix[..., :3, :3])], axis=-1)


# Eager forms of the linear maps: one product of the flattened input with a constant matrix (two
# operations). The backends' rule makes non-finite rows NaN after them: through the product an
# infinity stays infinite in the entries it feeds.


def _linear_forms() -> tuple[list[Any], ...]:
    """(6, 16) ``se3_hat``, (16, 6) ``se3_vee``, (6, 36) ``se3_ad``: the coefficient of each input
    entry in each output entry (row-major)."""
    skew = {0: ((2, 1, 1.0), (1, 2, -1.0)), 1: ((0, 2, 1.0), (2, 0, -1.0)), 2: ((1, 0, 1.0), (0, 1, -1.0))}
    hat = [[0.0] * 16 for _ in range(6)]
    vee = [[0.0] * 6 for _ in range(16)]
    ad = [[0.0] * 36 for _ in range(6)]
    for k in range(3):
        hat[k][4 * k + 3] = 1.0
        vee[4 * k + 3][k] = 1.0
        for row, col, sign in skew[k]:
            hat[3 + k][4 * row + col] = sign
            vee[4 * row + col][3 + k] = 0.5 * sign
            for r0, c0, source in ((0, 0, 3 + k), (0, 3, k), (3, 3, 3 + k)):
                ad[source][6 * (r0 + row) + c0 + col] = sign
    return hat, vee, ad


@eager_form(of=se3_hat)
def se3_hat_eager(xp: Any, xi: Any) -> Any:
    """:func:`se3_hat`, eager form: ``xi`` times a constant (6, 16) matrix."""
    hat, _, _ = constants(xp, xi, _linear_forms)
    return xp.matmul(xi, hat).unflatten(-1, (4, 4))


@eager_form(of=se3_vee)
def se3_vee_eager(xp: Any, matrix: Any) -> Any:
    """:func:`se3_vee`, eager form: the 16 entries times a constant (16, 6) matrix (``0.5 m_21 - 0.5
    m_12``: halving is exact, the same numbers as ``0.5 (m_21 - m_12)``)."""
    _, vee, _ = constants(xp, matrix, _linear_forms)
    return xp.matmul(matrix.flatten(-2), vee)


def _left_jacobian_times(xp: Any, phi: Any, v: Any) -> Any:
    """``J_l(phi) v = p v + q phi x v + r phi (phi . v)`` for vectors ``v`` ``(..., 3)``."""
    p, q, r = computed_once(xp, _jacobian_coefficients(xp, phi))
    return _column(p) * v + _column(q) * _cross(xp, phi, v) + _column(r) * phi * _dot(xp, phi, v)


@op(xi=(6,))
def se3_exp(xp: Any, xi: Any, *, to_matrix: Conversion = unit_quaternion_to_matrix) -> Any:
    """The exponential map of SE(3): the pose of a twist, ``(..., 6)`` to ``(..., 4, 4)``.

    ``exp((rho, phi)) = [[exp(phi), J_l(phi) rho], [0, 1]]``, the matrix exponential of
    ``se3_hat(xi)``: the rotation is ``so3_exp(phi)`` and the translation ``J_l(phi) rho`` (``rho``
    itself where ``phi`` is parallel to it, a pure screw along the axis).

    Args:
        xi: twists, shape ``(..., 6)``, translation ``rho`` first; any length.

    Returns:
        Poses, shape ``(..., 4, 4)``, bottom row exact. Exact at 0 and accurate to a few ulps of
        ``|rho|`` for every angle (``J_l``'s coefficients are series below ``|phi| = 1``), derivatives
        included.
    """
    rho, phi = _split(xi)
    rotation = axis_angle_to_matrix(xp, phi, to_matrix=to_matrix)
    translation = _left_jacobian_times(xp, phi, rho)
    return _with_bottom(xp, xp.concat([rotation, _column(translation)], axis=-1))


def _exp_forms() -> tuple[list[Any], ...]:
    """Constants of :func:`se3_exp_eager`: ``E`` (3, 64), the coefficient (of ``p, q, r``) of each
    product ``v_a v_b y_c`` (``v = (1, phi)``, ``y = (1, rho)``, index ``16 a + 4 b + c``); ``A``
    (64, 16), the entries of the pose (row-major) each product feeds; the bias, the identity.

    ``R = I + p hat(phi) + q hat(phi)^2`` with ``hat(phi)^2 = phi phi^T - |phi|^2 I``, and
    ``t = J_l(phi) rho = p rho + q phi x rho + r phi (phi . rho)``: every entry is linear in these
    products, with one of ``p, q, r`` for each."""
    e = [[0.0] * 64 for _ in range(3)]
    a = [[0.0] * 16 for _ in range(64)]
    # hat(w) = [[0, -z, y], [z, 0, -x], [-y, x, 0]]: (row, column, sign) per component of w
    hat = {0: ((1, 2, -1.0), (2, 1, 1.0)), 1: ((0, 2, 1.0), (2, 0, -1.0)), 2: ((0, 1, -1.0), (1, 0, 1.0))}
    for i, j in ((i, j) for i in range(4) for j in range(4)):
        rot, trans = 16 * i + 4 * j, [16 * i + 4 * j + c for c in range(1, 4)]
        if i == 0 and j > 0:  # hat(phi) in R (p), phi x rho in t (q)
            e[0][rot] = 1.0
            for row, col, sign in hat[j - 1]:
                a[rot][4 * row + col] = sign
            for c, f in enumerate(trans):
                e[1][f] = 1.0
                for row, col, sign in hat[j - 1]:
                    if col == c:  # (phi x rho)_row = sum hat(phi)[row, col] rho_col
                        a[f][4 * row + 3] = sign
        elif i > 0 and j > 0:  # phi phi^T - |phi|^2 I in R (q), phi (phi . rho) in t (r)
            e[1][rot] = 1.0
            a[rot][4 * (i - 1) + j - 1] += 1.0
            if i == j:
                for k in range(3):
                    a[rot][5 * k] -= 1.0
            e[2][trans[j - 1]] = 1.0
            a[trans[j - 1]][4 * (i - 1) + 3] = 1.0
        elif i == 0 and j == 0:  # rho in t (p)
            for c, f in enumerate(trans):
                e[0][f] = 1.0
                a[f][4 * c + 3] = 1.0
    bias = [1.0 if k in (0, 5, 10, 15) else 0.0 for k in range(16)]
    return e, a, bias


@nonfinite_by_arithmetic
@eager_form(of=se3_exp)
def se3_exp_eager(xp: Any, xi: Any, *, to_matrix: Conversion = unit_quaternion_to_matrix) -> Any:
    """:func:`se3_exp`, eager form: the coefficients ``(p, q, r)`` of ``J_l(phi)``
    (``_lie._jacobian_coefficients_eager``: the same series and closed forms) and the products of
    ``(1, phi)``, ``(1, phi)`` and ``(1, rho)``, contracted with constant forms (:func:`_exp_forms`)
    into the 16 entries at once, the bottom row ``(0, 0, 0, 1)`` by the bias alone. Rodrigues' formula
    for the rotation (the componentwise form goes through the unit quaternion; both are accurate to a
    few ulps of 1). A non-finite twist makes every entry NaN: the coefficients or the products carry
    it to every column of the contraction (``NaN * 0``)."""
    e, a, bias = constants(xp, xi, _exp_forms)
    phi = xi[..., 3:]
    v = xp.nn.functional.pad(phi, (1, 0), value=1.0)
    y = xp.nn.functional.pad(xi, (1, 0), value=1.0)[..., :4]
    f = ((v[..., :, None] * v[..., None, :]).flatten(-2)[..., :, None] * y[..., None, :]).flatten(-2)
    fg = f * xp.matmul(_jacobian_coefficients_eager(xp, phi), e)
    out = xp.addmm(bias, fg, a) if fg.ndim == 2 else xp.matmul(fg, a) + bias
    return out.unflatten(-1, (4, 4))


def _log(xp: Any, matrix: Any, to_quaternion: Conversion) -> Any:
    phi = matrix_to_axis_angle(xp, matrix[..., :3, :3], to_quaternion=to_quaternion)
    t = matrix[..., :3, 3]
    # J_l(phi)^-1 t = p t - phi x t / 2 + r phi (phi . t): bounded for |phi| <= pi (its pole is at 2 pi)
    p, r = computed_once(xp, _inverse_coefficients(xp, phi))
    rho = _column(p) * t - 0.5 * _cross(xp, phi, t) + _column(r) * phi * _dot(xp, phi, t)
    return xp.concat([rho, phi], axis=-1)


@op(matrix=(4, 4))
def se3_log(xp: Any, matrix: Any, *, to_quaternion: Conversion = matrix_to_quaternion) -> Any:
    """The logarithm of SE(3): the twist ``(rho, phi)`` of a pose, ``(..., 4, 4)`` to ``(..., 6)``,
    translation first, ``|phi|`` in [0, pi].

    ``phi = so3_log(R)`` and ``rho = J_l(phi)^-1 t``, so that ``se3_exp(se3_log(T)) = T``.

    Args:
        matrix: poses ``[[R, t], [0, 1]]``, shape ``(..., 4, 4)``; the bottom row is not read.

    Returns:
        Shape ``(..., 6)``. As ``so3_log``: at a rotation of exactly pi, ``phi`` takes the sign of the
        canonical quaternion and jumps there (with ``rho``, which depends on ``phi``'s sign through
        ``phi x t``); the gradient stays finite.
    """
    return _log(xp, matrix, to_quaternion)


# ---------------------------------------------------------------------------------------------------
# Adjoints


# atan2(s, w) / s as a series in x = s^2 / w^2 below x ~ 1e-4 (w > 0.99 there): (1/w) (1 - x/3 + x^2/5
# - ...); the first term left out, x^5 / 11 < 1e-21, is below float64's rounding. Above, the closed
# form (a quotient, no cancellation); the series keeps its derivatives finite at s = 0.
_LOG_SERIES_BELOW = 1e-4


def _log_constants() -> tuple[list[Any], ...]:
    """2 (the constant term of 2 atan2(s, w) / s, times w), the powers 1-4 and their terms."""
    return [2.0], [1.0, 2.0, 3.0, 4.0], [[2.0 * (-1) ** k / (2 * k + 1)] for k in range(1, 5)]


@eager_form(of=se3_log)
def se3_log_eager(xp: Any, matrix: Any, *, to_quaternion: Conversion = matrix_to_quaternion) -> Any:
    """:func:`se3_log`, eager form: ``phi = 2 atan2(|v|, w) v / |v|`` of the unit quaternion
    ``(w, v)`` (``w >= 0``) of ``R`` (the conversion the componentwise form reads too), and
    ``rho = J_l(phi)^-1 t`` from ``_lie``'s eager inverse: ``(p, r)`` in one array, the matrix from
    constant forms, one product with ``t``."""
    return _log_eager(xp, matrix, to_quaternion)


def _log_eager(xp: Any, matrix: Any, to_quaternion: Conversion) -> Any:
    """:func:`se3_log_eager`'s twist, for the eager forms that take a logarithm."""
    first, powers, table = constants(xp, matrix, _log_constants)
    q = to_quaternion(xp, matrix[..., :3, :3])
    w, v = q[..., :1], q[..., 1:]
    n2 = (v * v).sum(-1, keepdim=True)
    # double where by clamps: each branch reads a finite value where the other one is chosen
    ws, s = w.clamp_min(0.5), xp.sqrt(n2.clamp_min(_LOG_SERIES_BELOW))
    x = n2.clamp_max(_LOG_SERIES_BELOW) / (ws * ws)
    series = (xp.matmul(x**powers, table) + first) / ws
    phi = xp.where(n2 < _LOG_SERIES_BELOW, series, 2.0 * xp.atan2(s, w) / s) * v
    _, _, _, inverse, bias, _ = constants(xp, phi, _jacobian_forms)
    j_inv = _assemble_eager(xp, phi, _inverse_coefficients_eager(xp, phi), inverse, bias)
    return xp.cat([(j_inv * matrix[..., None, :3, 3]).sum(-1), phi], -1)


@op(matrix=(4, 4))
def se3_adjoint(xp: Any, matrix: Any) -> Any:
    """The adjoint ``Ad(T) = [[R, hat(t) R], [0, R]]`` of poses, acting on twists ``(rho, phi)``:
    ``T exp(xi) T^-1 = exp(Ad(T) xi)``, and ``Ad(T1 T2) = Ad(T1) Ad(T2)``.

    Args:
        matrix: poses ``T = [[R, t], [0, 1]]``, shape ``(..., 4, 4)``.

    Returns:
        Shape ``(..., 6, 6)``.
    """
    r = matrix[..., :3, :3]
    return _blocks(xp, r, small_matmul(xp, so3_hat(xp, matrix[..., :3, 3]), r), r)


@op(xi=(6,))
def se3_ad(xp: Any, xi: Any) -> Any:
    """The adjoint of the Lie algebra, ``ad(xi) = [[hat(phi), hat(rho)], [0, hat(phi)]]`` for twists
    ``xi = (rho, phi)``: ``ad(xi) eta = vee([hat(xi), hat(eta)])``, the derivative of ``Ad(exp(t xi))``
    at ``t = 0``.

    Args:
        xi: twists, shape ``(..., 6)``, translation first.

    Returns:
        Shape ``(..., 6, 6)``.
    """
    rho, phi = _split(xi)
    w = so3_hat(xp, phi)
    return _blocks(xp, w, so3_hat(xp, rho), w)


@eager_form(of=se3_ad)
def se3_ad_eager(xp: Any, xi: Any) -> Any:
    """:func:`se3_ad`, eager form: ``xi`` times a constant (6, 36) matrix."""
    _, _, ad = constants(xp, xi, _linear_forms)
    return xp.matmul(xi, ad).unflatten(-1, (6, 6))


# ---------------------------------------------------------------------------------------------------
# Jacobians


# Why the series of Q's coefficients run up to t = 2 (u = 4), and not to 1 as J_l's: their closed forms
# cancel harder, t^2 + 2 cos t - 2 ~ t^4 / 12 and 2 t - 3 sin t + t cos t ~ t^5 / 60, so that at t = 1
# they still lose ~100 ulps in float32 (measured against mpmath), and ~10 at t = 2; from t = 2 on the
# cancelled fraction is at most ~3/4 and ~9/10. The series are entire (alternating, terms ~ 4^n/(2n)!
# at t = 2): float64 takes 11 or 12 terms there, float32 6.
Q_SERIES_BELOW = 4.0

# Taylor coefficients in u = t^2: (t^2 + 2 cos t - 2) / (2 t^4) = sum_n (-1)^n u^n / (2n + 4)!, and
# (2 t - 3 sin t + t cos t) / (2 t^5) = sum_n (-1)^n (n + 1) u^n / (2n + 5)!
_C2_SERIES = tuple((-1) ** n / math.factorial(2 * n + 4) for n in range(16))
_C3_SERIES = tuple((-1) ** n * (n + 1) / math.factorial(2 * n + 5) for n in range(16))
_C1_SERIES = tuple((-1) ** n / math.factorial(2 * n + 3) for n in range(16))  # (t - sin t) / t^3
assert _C1_SERIES[: len(_B_SERIES)] == _B_SERIES


def _q_coefficients(xp: Any, u: Any) -> tuple[Any, Any, Any]:
    """``(c1, c2, c3)`` of Q at ``u = |phi|^2`` (``(...,)``): Taylor series below ``Q_SERIES_BELOW``,
    closed forms above (with ``2 - 2 cos t = 4 sin^2(t/2)``). Double where: the closed forms see
    ``u >= Q_SERIES_BELOW`` only, so neither ``sqrt`` at 0 nor a division by ``t`` meets a discarded
    branch's cotangent."""
    small = u < Q_SERIES_BELOW
    us = xp.where(small, u, 0.0)
    uc = xp.where(small, Q_SERIES_BELOW, u)
    t = xp.sqrt(uc)
    sin_t, cos_t, sin_half = xp.sin(t), xp.cos(t), xp.sin(0.5 * t)
    c1 = (t - sin_t) / (t * uc)
    c2 = (uc - 4.0 * (sin_half * sin_half)) / (2.0 * uc * uc)
    c3 = (2.0 * t - 3.0 * sin_t + t * cos_t) / (2.0 * t * uc * uc)
    return (
        xp.where(small, _series(xp, us, _C1_SERIES, Q_SERIES_BELOW), c1),
        xp.where(small, _series(xp, us, _C2_SERIES, Q_SERIES_BELOW), c2),
        xp.where(small, _series(xp, us, _C3_SERIES, Q_SERIES_BELOW), c3),
    )


def _q_block(xp: Any, rho: Any, phi: Any) -> Any:
    """Barfoot's ``Q(rho, phi)``, the upper-right block of SE(3)'s left Jacobian, ``(..., 3, 3)``.

    With ``a = phi``, ``b = rho``, ``c = a x b``, ``d = a . b``, ``u = |a|^2`` the skew products reduce
    (``a^ b^ = b a^T - d I``, ``a^ a^ = a a^T - u I``, ``a^T a^ = 0``, so ``a^ b^ a^ = -d a^``) to
    ``Q = hat(beta b + gamma a) + delta I + v a^T + a w^T`` with ``beta = 1/2 - 2 u c2``,
    ``gamma = d (3 c2 - c1)``, ``delta = 2 d (u c3 - c1)``, ``v = c1 b - c2 c - 2 d c3 a`` and
    ``w = c1 b + c2 c``: each term is its size
    (``|b| u^k``) times an accurate coefficient, so the entries are accurate to a few ulps of
    ``|rho|``."""
    u = xp.sum(phi * phi, axis=-1)
    c1, c2, c3 = computed_once(xp, _q_coefficients(xp, u))
    d = xp.sum(phi * rho, axis=-1)
    c = _cross(xp, phi, rho)
    col = _column
    h = col(0.5 - 2.0 * u * c2) * rho + col(d * (3.0 * c2 - c1)) * phi
    delta = 2.0 * d * (u * c3 - c1)
    v = col(c1) * rho - col(c2) * c - col(2.0 * d * c3) * phi
    w = col(c1) * rho + col(c2) * c
    x, y, z = _components(xp, phi)
    vx, vy, vz = _components(xp, v)
    wx, wy, wz = _components(xp, w)
    hx, hy, hz = _components(xp, h)
    return stack_matrix(
        xp,
        [
            delta + vx * x + x * wx, vx * y + x * wy - hz, vx * z + x * wz + hy,
            vy * x + y * wx + hz, delta + vy * y + y * wy, vy * z + y * wz - hx,
            vz * x + z * wx - hy, vz * y + z * wy + hx, delta + vz * z + z * wz,
        ],
    )  # fmt: skip


def _left_jacobian(xp: Any, xi: Any) -> Any:
    rho, phi = _split(xi)
    p, q, r = computed_once(xp, _jacobian_coefficients(xp, phi))
    j = _assemble(xp, phi, p, q, r)
    return _blocks(xp, j, _q_block(xp, rho, phi), j)


def _left_jacobian_inverse(xp: Any, xi: Any) -> Any:
    # [[J, Q], [0, J]]^-1 = [[J^-1, -J^-1 Q J^-1], [0, J^-1]]
    rho, phi = _split(xi)
    p, r = computed_once(xp, _inverse_coefficients(xp, phi))
    j_inv = _assemble(xp, phi, p, -0.5, r)
    block = -small_matmul(xp, small_matmul(xp, j_inv, _q_block(xp, rho, phi)), j_inv)
    return _blocks(xp, j_inv, block, j_inv)


_JACOBIAN_DOC = """

    Convention: ``exp(xi + d) = exp(J_l(xi) d) exp(xi) = exp(xi) exp(J_r(xi) d)`` to first order in
    ``d``, twists translation first; ``J_l(xi) = sum_n ad(xi)^n / (n + 1)! = [[J_l(phi), Q(rho, phi)],
    [0, J_l(phi)]]``, ``J_r(xi) = J_l(-xi)`` and ``J_l(xi) = Ad(exp(xi)) J_r(xi)``. The inverses are
    the derivatives of log: ``log(exp(d) T) = log(T) + J_l(log T)^-1 d`` and
    ``log(T exp(d)) = log(T) + J_r(log T)^-1 d`` to first order; they have poles at
    ``|phi| = 2 pi k`` (k >= 1), and are bounded for ``|phi| <= pi``, the range of log.

    Args:
        xi: twists ``(rho, phi)``, shape ``(..., 6)``.

    Returns:
        Shape ``(..., 6, 6)``. ``J_l(phi)``'s coefficients are series below ``|phi| = 1`` and ``Q``'s
        below ``|phi| = 2``, closed forms above: exact at 0 and accurate to a few ulps of ``|rho|``
        at every angle (tested against the series of ``ad`` at 40 digits), derivatives included. A NaN
        or an infinity makes the whole matrix NaN.
"""


@op(xi=(6,))
def se3_left_jacobian(xp: Any, xi: Any) -> Any:
    return _left_jacobian(xp, xi)


@op(xi=(6,))
def se3_right_jacobian(xp: Any, xi: Any) -> Any:
    return _left_jacobian(xp, -xi)


@op(xi=(6,))
def se3_left_jacobian_inverse(xp: Any, xi: Any) -> Any:
    return _left_jacobian_inverse(xp, xi)


@op(xi=(6,))
def se3_right_jacobian_inverse(xp: Any, xi: Any) -> Any:
    return _left_jacobian_inverse(xp, -xi)


# Eager forms of the Jacobians (_core.EAGER_FORMS): J_l(phi) and its inverse from _lie's eager forms;
# Q's coefficients (c1, c2, c3) as one (..., 3) array (series below Q_SERIES_BELOW, the same closed
# forms above); the matrix of _q_block's (h, v, w) over (rho, phi, phi x rho), its entries and delta
# from the products of (1, u, d, d u) and (1, c1, c2, c3) and a constant (16, 10) matrix; Q =
# hat(h) + delta I + [v, phi] [phi, w]^T.


def _q_constants() -> tuple[list[Any], ...]:
    """Constants of :func:`_q_block_eager`: ``(1, 1/2)``; the numerators' forms (7, 3) in ``(t, sin t,
    sin(t/2), sin^2 t, sin^2(t/2), t cos t, u)`` and the denominators' factors ``(1, 2, 2)``; the
    coefficient matrix (16, 10) of :func:`_q_block_eager`; ``(hat(h), delta I)`` (4, 9); then the
    series tables of ``(c1, c2, c3)``."""
    numerators = [[0.0] * 3 for _ in range(7)]
    for row, col, value in (
        (0, 0, 1.0),
        (1, 0, -1.0),
        (6, 1, 1.0),
        (4, 1, -4.0),
        (0, 2, 2.0),
        (1, 2, -3.0),
        (5, 2, 1.0),
    ):
        numerators[row][col] = value
    k = [[0.0] * 10 for _ in range(16)]
    one, u, d, du, c1, c2, c3 = 0, 1, 2, 3, 1, 2, 3
    # rows of K: h, v, w; columns: rho, phi, phi x rho; then delta
    entries = [
        (0, 0, one, 0, 0.5), (0, 0, u, c2, -2.0), (0, 1, d, c2, 3.0), (0, 1, d, c1, -1.0),
        (1, 0, one, c1, 1.0), (1, 1, d, c3, -2.0), (1, 2, one, c2, -1.0),
        (2, 0, one, c1, 1.0), (2, 2, one, c2, 1.0),
    ]  # fmt: skip
    for row, col, i, j, value in entries:
        k[4 * i + j][3 * row + col] += value
    k[4 * du + c3][9] += 2.0
    k[4 * d + c1][9] -= 2.0
    hat_delta = [[0.0] * 9 for _ in range(4)]
    for comp, cells in ((0, ((7, 1.0), (5, -1.0))), (1, ((2, 1.0), (6, -1.0))), (2, ((3, 1.0), (1, -1.0)))):
        for cell, sign in cells:
            hat_delta[comp][cell] = sign
    for cell in (0, 4, 8):
        hat_delta[3][cell] = 1.0
    tables = _series_tables(_C1_SERIES, _C2_SERIES, _C3_SERIES, below=Q_SERIES_BELOW)
    return [1.0, 0.5], numerators, [1.0, 2.0, 2.0], k, hat_delta, *tables


def _q_block_eager(xp: Any, rho: Any, phi: Any) -> Any:
    """:func:`_q_block`, eager form: ``(..., 3, 3)``."""
    ang, numerators, factors, k, hat_delta, *tables = constants(xp, rho, _q_constants)
    u = (phi * phi).sum(-1, keepdim=True)
    small = u < Q_SERIES_BELOW
    # the double where by the mask, as _lie._angle_eager: the closed forms read u + 4 where unused
    uc = xp.add(u, small, alpha=Q_SERIES_BELOW)
    t = xp.sqrt(uc)
    s = xp.sin(t * ang)
    tu = t * uc
    z = xp.cat([t, s, s * s, t * xp.cos(t), uc], -1)
    closed = xp.matmul(z, numerators) / (xp.cat([t, uc, tu], -1) * factors * uc)
    series = _series_eager(xp, u * small, tuple(tables))
    c = xp.where(small, series, closed)
    d = (phi * rho).sum(-1, keepdim=True)
    left = xp.nn.functional.pad(xp.cat([u, d, d * u], -1), (1, 0), value=1.0)
    right = xp.nn.functional.pad(c, (1, 0), value=1.0)
    kd = xp.matmul((left[..., :, None] * right[..., None, :]).flatten(-2), k)
    basis = xp.stack([rho, phi, xp.linalg.cross(phi, rho)], -2)
    h, v, w = _product(xp, kd[..., :9].unflatten(-1, (3, 3)), basis).unbind(-2)
    outer = _product(xp, xp.stack([v, phi], -1), xp.stack([phi, w], -2))
    return outer + xp.matmul(xp.cat([h, kd[..., 9:]], -1), hat_delta).unflatten(-1, (3, 3))


def _left_jacobian_eager(xp: Any, xi: Any) -> Any:
    rho, phi = xi[..., :3], xi[..., 3:]
    _, left, *_ = constants(xp, xi, _jacobian_forms)
    j = _assemble_eager(xp, phi, _jacobian_coefficients_eager(xp, phi), left)
    return _blocks_eager(xp, j, _q_block_eager(xp, rho, phi))


def _left_jacobian_inverse_eager(xp: Any, xi: Any) -> Any:
    rho, phi = xi[..., :3], xi[..., 3:]
    _, _, _, inverse, bias, _ = constants(xp, xi, _jacobian_forms)
    j_inv = _assemble_eager(xp, phi, _inverse_coefficients_eager(xp, phi), inverse, bias)
    block = -_product(xp, _product(xp, j_inv, _q_block_eager(xp, rho, phi)), j_inv)
    return _blocks_eager(xp, j_inv, block)


def _blocks_eager(xp: Any, j: Any, q: Any) -> Any:
    """``[[j, q], [0, j]]``: one ``cat`` of the top, the bottom ``j`` padded with zeros, one ``cat``."""
    return xp.cat([xp.cat([j, q], -1), xp.nn.functional.pad(j, (3, 0))], -2)


@eager_form(of=se3_left_jacobian)
def se3_left_jacobian_eager(xp: Any, xi: Any) -> Any:
    """:func:`se3_left_jacobian`, eager form (see above)."""
    return _left_jacobian_eager(xp, xi)


@eager_form(of=se3_right_jacobian)
def se3_right_jacobian_eager(xp: Any, xi: Any) -> Any:
    """:func:`se3_right_jacobian`, eager form (see above)."""
    return _left_jacobian_eager(xp, -xi)


@eager_form(of=se3_left_jacobian_inverse)
def se3_left_jacobian_inverse_eager(xp: Any, xi: Any) -> Any:
    """:func:`se3_left_jacobian_inverse`, eager form (see above)."""
    return _left_jacobian_inverse_eager(xp, xi)


@eager_form(of=se3_right_jacobian_inverse)
def se3_right_jacobian_inverse_eager(xp: Any, xi: Any) -> Any:
    """:func:`se3_right_jacobian_inverse`, eager form (see above)."""
    return _left_jacobian_inverse_eager(xp, -xi)


se3_left_jacobian.__doc__ = "The left Jacobian ``J_l(xi)`` of SE(3)." + _JACOBIAN_DOC
se3_right_jacobian.__doc__ = "The right Jacobian ``J_r(xi) = J_l(-xi)`` of SE(3)." + _JACOBIAN_DOC
se3_left_jacobian_inverse.__doc__ = "The inverse ``J_l(xi)^-1`` of SE(3)'s left Jacobian." + _JACOBIAN_DOC
se3_right_jacobian_inverse.__doc__ = (
    "The inverse ``J_r(xi)^-1 = J_l(-xi)^-1`` of SE(3)'s right Jacobian." + _JACOBIAN_DOC
)


# ---------------------------------------------------------------------------------------------------
# plus, minus, interpolation


@nonfinite_by_arithmetic
@op(matrix=(4, 4), delta=(6,))
def se3_plus(
    xp: Any,
    matrix: Any,
    delta: Any,
    *,
    side: str = "right",
    to_matrix: Conversion = unit_quaternion_to_matrix,
) -> Any:
    """A pose perturbed by a twist: ``T exp(d)`` (``side="right"``) or ``exp(d) T`` (``side="left"``).

    Args:
        matrix: poses ``T``, shape ``(..., 4, 4)``.
        delta: twists ``d = (rho, phi)``, shape ``(..., 6)``, translation first; the batch shapes
            broadcast.
        side: ``"right"`` (``d`` in the body frame, the default) or ``"left"`` (``d`` in the world
            frame); anything else raises ``ValueError``.

    Returns:
        Shape ``(..., 4, 4)``, bottom row exact. ``se3_plus(T2, se3_minus(T1, T2, side=s), side=s)``
        is ``T1`` on either side.
    """
    right = check_side("se3_plus", side)
    a, step = _same_rank(xp, matrix, se3_exp(xp, delta, to_matrix=to_matrix))
    # the term of the inputs (delta's six entries, not the step's sixteen)
    terms = _same_rank(
        xp, _nonfinite_term(xp, matrix - matrix, 2), _nonfinite_term(xp, delta - delta, 1)[..., None]
    )
    term = cancelling_factor(xp, terms[0] + terms[1])
    return _compose(xp, a, step, term) if right else _compose(xp, step, a, term)


@op(matrix1=(4, 4), matrix2=(4, 4))
def se3_minus(
    xp: Any,
    matrix1: Any,
    matrix2: Any,
    *,
    side: str = "right",
    to_quaternion: Conversion = matrix_to_quaternion,
) -> Any:
    """The twist from one pose to another: ``log(T2^-1 T1)`` (``side="right"``) or ``log(T1 T2^-1)``
    (``side="left"``), ``|phi|`` in [0, pi].

    Args:
        matrix1: poses ``T1``, shape ``(..., 4, 4)``.
        matrix2: poses ``T2``, shape ``(..., 4, 4)``; the batch shapes broadcast.
        side: ``"right"`` (the default) or ``"left"``, as in ``se3_plus``; anything else raises
            ``ValueError``.

    Returns:
        Shape ``(..., 6)``, translation first, the inverse of ``se3_plus`` on the same side. Where the
        rotations are a half-turn apart ``phi`` takes ``so3_log``'s sign and jumps there.
    """
    right = check_side("se3_minus", side)
    inverse = se3_inverse(xp, matrix2)
    relative = se3_compose(xp, inverse, matrix1) if right else se3_compose(xp, matrix1, inverse)
    return _log(xp, relative, to_quaternion)


@op(matrix1=(4, 4), matrix2=(4, 4), t=())
def se3_interpolate(
    xp: Any,
    matrix1: Any,
    matrix2: Any,
    t: Any,
    *,
    mode: str = "screw",
    to_matrix: Conversion = unit_quaternion_to_matrix,
    to_quaternion: Conversion = matrix_to_quaternion,
) -> Any:
    """Poses between two poses at parameters ``t`` (0 gives ``T1``, 1 gives ``T2``).

    - ``mode="screw"`` (the default): ``T1 exp(t log(T1^-1 T2))``, the constant-twist motion (scipy's
      ``T1 * (T1.inv() * T2) ** t``): the rotation and the translation move together along a screw.
    - ``mode="decoupled"``: the rotation by slerp, ``R1 exp(t log(R1^T R2))``, and the translation on
      the straight line ``(1 - t) t1 + t t2``.

    Args:
        matrix1: poses ``T1``, shape ``(..., 4, 4)``.
        matrix2: poses ``T2``, shape ``(..., 4, 4)``.
        t: parameters, any shape that broadcasts with the batch shapes (as ``quaternion_slerp``'s
            ``t``; a Python number where the backend takes one); extrapolates outside [0, 1].
        mode: ``"screw"`` or ``"decoupled"``; anything else raises ``ValueError``.

    Returns:
        Shape ``(..., 4, 4)``, bottom row exact. Where the rotations are a half-turn apart the path is
        the one of ``so3_log``'s sign.
    """
    if mode not in INTERPOLATION_MODES:
        raise ValueError(f"se3_interpolate: expected mode to be 'screw' or 'decoupled', got {mode!r}")
    a, b, s = match_rank(xp, matrix1, matrix2, _column(_column(t)))
    if mode == "screw":
        xi = _log(xp, se3_compose(xp, se3_inverse(xp, a), b), to_quaternion)
        return se3_compose(xp, a, se3_exp(xp, s[..., 0] * xi, to_matrix=to_matrix))
    r1, r2 = a[..., :3, :3], b[..., :3, :3]
    phi = matrix_to_axis_angle(xp, small_matmul(xp, xp.swapaxes(r1, -1, -2), r2), to_quaternion=to_quaternion)
    rotation = small_matmul(xp, r1, axis_angle_to_matrix(xp, s[..., 0] * phi, to_matrix=to_matrix))
    translation = a[..., :3, 3:] + s * (b[..., :3, 3:] - a[..., :3, 3:])
    rotation, translation = match_rank(xp, rotation, translation)
    batch = tuple(xp.broadcast_shapes(tuple(rotation.shape[:-2]), tuple(translation.shape[:-2])))
    rotation = xp.broadcast_to(rotation, (*batch, 3, 3))
    translation = xp.broadcast_to(translation, (*batch, 3, 1))
    return _with_bottom(xp, xp.concat([rotation, translation], axis=-1))


# Eager forms of the perturbations and the screw interpolation: the same steps through the eager forms
# of exp, log, compose and inverse.


@nonfinite_by_arithmetic
@eager_form(of=se3_plus)
def se3_plus_eager(
    xp: Any,
    matrix: Any,
    delta: Any,
    *,
    side: str = "right",
    to_matrix: Conversion = unit_quaternion_to_matrix,
) -> Any:
    """:func:`se3_plus`, eager form: :func:`se3_compose_eager` of the pose and :func:`se3_exp_eager`
    of the twist (NaN in every entry for a non-finite twist, so compose's term covers both inputs)."""
    right = check_side("se3_plus", side)
    step = se3_exp_eager(xp, delta)
    return se3_compose_eager(xp, matrix, step) if right else se3_compose_eager(xp, step, matrix)


@eager_form(of=se3_minus)
def se3_minus_eager(
    xp: Any,
    matrix1: Any,
    matrix2: Any,
    *,
    side: str = "right",
    to_quaternion: Conversion = matrix_to_quaternion,
) -> Any:
    """:func:`se3_minus`, eager form: :func:`se3_log_eager` of the relative pose, which
    :func:`se3_inverse_eager` and :func:`se3_compose_eager` make."""
    right = check_side("se3_minus", side)
    inverse = se3_inverse_eager(xp, matrix2)
    relative = se3_compose_eager(xp, inverse, matrix1) if right else se3_compose_eager(xp, matrix1, inverse)
    return _log_eager(xp, relative, to_quaternion)


@eager_form(of=se3_interpolate)
def se3_interpolate_eager(
    xp: Any,
    matrix1: Any,
    matrix2: Any,
    t: Any,
    *,
    mode: str = "screw",
    to_matrix: Conversion = unit_quaternion_to_matrix,
    to_quaternion: Conversion = matrix_to_quaternion,
) -> Any:
    """:func:`se3_interpolate`, eager form: the screw through the eager forms of inverse, compose, log
    and exp; the decoupled mode is the componentwise function's."""
    if mode != "screw":
        return se3_interpolate(
            xp, matrix1, matrix2, t, mode=mode, to_matrix=to_matrix, to_quaternion=to_quaternion
        )
    a, b, s = match_rank(xp, matrix1, matrix2, _column(_column(t)))
    xi = _log_eager(xp, se3_compose_eager(xp, se3_inverse_eager(xp, a), b), to_quaternion)
    return se3_compose_eager(xp, a, se3_exp_eager(xp, s[..., 0] * xi))


# ---------------------------------------------------------------------------------------------------
# 7-vector poses: a quaternion and a translation, in each peer's order


def _pose_layout(fname: str, layout: str) -> tuple[bool, bool]:
    """(quaternion first, scalar first) of a layout; ``ValueError`` naming ``fname`` otherwise."""
    if layout not in POSE_LAYOUTS:
        names = ", ".join(repr(k) for k in POSE_LAYOUTS)
        raise ValueError(f"{fname}: expected layout to be one of {names}, got {layout!r}")
    return POSE_LAYOUTS[layout]


_LAYOUT_DOC = """``"wxyz_xyz"`` (jaxlie, kornia),
            ``"xyz_xyzw"`` (ROS ``geometry_msgs/Pose``, pypose, lietorch, manif), ``"xyzw_xyz"`` (Sophus)
            or ``"xyz_wxyz"`` (theseus): the order of the quaternion's and the translation's
            components; anything else raises ``ValueError``."""


@op(pose=(7,))
def pose_to_matrix(xp: Any, pose: Any, *, layout: str, to_matrix: Conversion = quaternion_to_matrix) -> Any:
    """The ``(..., 4, 4)`` pose matrix of a 7-vector pose (a quaternion and a translation).

    Args:
        pose: poses, shape ``(..., 7)``. The quaternion may have any non-zero norm (it is normalised;
            the zero quaternion is the identity, as in ``quaternion_to_matrix``).
        layout: LAYOUT

    Returns:
        ``[[R(q), t], [0, 1]]``, shape ``(..., 4, 4)``, bottom row exact.
    """
    quaternion_first, scalar_first = _pose_layout("pose_to_matrix", layout)
    q, t = (pose[..., :4], pose[..., 4:]) if quaternion_first else (pose[..., 3:], pose[..., :3])
    rotation = to_matrix(xp, q, scalar_first=scalar_first)
    return _with_bottom(xp, xp.concat([rotation, _column(t)], axis=-1))


@op(matrix=(4, 4))
def matrix_to_pose(
    xp: Any, matrix: Any, *, layout: str, to_quaternion: Conversion = matrix_to_quaternion
) -> Any:
    """The 7-vector pose (a quaternion and a translation) of a ``(..., 4, 4)`` pose matrix.

    Args:
        matrix: poses ``[[R, t], [0, 1]]``, shape ``(..., 4, 4)``; the bottom row is not read.
        layout: LAYOUT

    Returns:
        Shape ``(..., 7)``: ``matrix_to_quaternion(R)`` (unit, canonical sign: w > 0) and ``t``, in the
        layout's order. ``pose_to_matrix(matrix_to_pose(T, layout=l), layout=l)`` is ``T``.
    """
    quaternion_first, scalar_first = _pose_layout("matrix_to_pose", layout)
    q = to_quaternion(xp, matrix[..., :3, :3], scalar_first=scalar_first)
    t = matrix[..., :3, 3]
    return xp.concat([q, t] if quaternion_first else [t, q], axis=-1)


for _fn in (pose_to_matrix, matrix_to_pose):
    _fn.__doc__ = (_fn.__doc__ or "").replace("LAYOUT", _LAYOUT_DOC)


# ---------------------------------------------------------------------------------------------------
# Means and fits of point sets


def _weights_and_total(xp: Any, weights: Any, like: Any) -> tuple[Any, Any, Any]:
    """Weights ``(..., N)`` (ones where ``None``) broadcast to ``like``'s ``(..., N)``, their sum
    ``(..., 1)`` with 1 where it is not positive (no weight at all: the means are then 0, not NaN),
    and whether it is positive."""
    w = xp.ones_like(like) if weights is None else xp.broadcast_to(weights, tuple(like.shape))
    total = xp.sum(w, axis=-1, keepdims=True)
    positive = total > 0
    return w, xp.where(positive, total, 1.0), positive


@op(matrices=(-1, 4, 4), weights=(-1,))
def se3_mean(xp: Any, matrices: Any, weights: Any = None, *, rotation_mean: Any, procrustes: Any) -> Any:
    """The mean of poses: the chordal mean of the rotations (``rotation_mean``'s default, scipy's
    ``Rotation.mean``) and the weighted mean of the translations (scipy's ``RigidTransform.mean``).

    Args:
        matrices: poses, shape ``(..., N, 4, 4)``.
        weights: non-negative weights, shape ``(..., N)``, or ``None`` for equal weights; batch
            dimensions broadcast against the poses'. Weights summing to zero (and ``N = 0``) give the
            identity.

    Returns:
        Shape ``(..., 4, 4)``, bottom row exact; the rotation's gradients are ``rotation_mean``'s.
    """
    n = matrices.shape[-3]
    shapes = [matrices.shape[:-3]] + ([] if weights is None else [weights.shape[:-1]])
    batch = tuple(xp.broadcast_shapes(*shapes))
    matrices = xp.broadcast_to(matrices, (*batch, n, 4, 4))
    w, total, _ = _weights_and_total(xp, weights, matrices[..., 0, 0])
    rotation = rotation_mean(xp, matrices[..., :3, :3], w, procrustes=procrustes)
    translation = xp.sum(w[..., None] * matrices[..., :3, 3], axis=-2) / total
    return _with_bottom(xp, xp.concat([rotation, _column(translation)], axis=-1))


@eager_form(of=se3_mean)
def se3_mean_eager(
    xp: Any, matrices: Any, weights: Any = None, *, rotation_mean: Any, procrustes: Any
) -> Any:
    """:func:`se3_mean`, eager form: one weighted sum of the whole poses ``S = sum_i w_i T_i`` holds
    both sums, the rotations' (top-left block: what ``rotation_mean``'s chordal form projects, the same
    products and sums) and the translations' (top-right column); ``S / total`` gives the translation,
    and the result is ``pad(R) + S / total`` masked to its column ``+ e4 e4^T`` (exact bottom row)."""
    _, corner, _, column, _ = constants(xp, matrices, _pose_masks)
    n = matrices.shape[-3]
    shapes = [matrices.shape[:-3]] + ([] if weights is None else [weights.shape[:-1]])
    batch = tuple(xp.broadcast_shapes(*shapes))
    if tuple(matrices.shape) != (*batch, n, 4, 4):
        matrices = xp.broadcast_to(matrices, (*batch, n, 4, 4))
    if weights is None:  # equal weights: the sums themselves (products by 1 are exact)
        total = xp.full((*batch, 1, 1), float(n), dtype=matrices.dtype, device=matrices.device)
        summed = xp.sum(matrices, axis=-3)
    else:
        w = weights if tuple(weights.shape) == (*batch, n) else xp.broadcast_to(weights, (*batch, n))
        total = xp.sum(w, axis=-1).reshape(*batch, 1, 1)
        summed = xp.sum(xp.reshape(w, (*batch, n, 1, 1)) * matrices, axis=-3)
    rotation = procrustes(xp, summed[..., :3, :3])
    total = xp.where(total > 0, total, 1.0)
    # corner + (S / total) masked to the translation column (its -1s, negated again), plus R padded
    top = xp.addcmul(corner, summed / total, column, value=-1.0)
    return top + xp.nn.functional.pad(rotation, (0, 1, 0, 1))


def _centred(xp: Any, source: Any, target: Any, weights: Any) -> tuple[Any, ...]:
    """Broadcast ``source``, ``target`` ``(..., N, 3)`` and weights ``(..., N)``; their weighted
    centroids ``(..., 3)``, the weighted cross-covariance ``sum_i w_i (t_i - ct) (s_i - cs)^T`` and the
    source's weighted spread ``sum_i w_i |s_i - cs|^2`` ``(...)``, both of the centred points divided
    by the largest coordinate of their set, and the ratio of those divisors (target's over source's).
    Centred before the products: the covariance of points far from the origin would otherwise cancel."""
    n = source.shape[-2]
    shapes = [source.shape[:-2], target.shape[:-2]] + ([] if weights is None else [weights.shape[:-1]])
    batch = tuple(xp.broadcast_shapes(*shapes))
    source = xp.broadcast_to(source, (*batch, n, 3))
    target = xp.broadcast_to(target, (*batch, n, 3))
    w, total, positive = _weights_and_total(xp, weights, source[..., 0])

    def centre(x: Any) -> tuple[Any, Any]:
        # relative to the first point (0 for N = 0) first: points that are all equal give exactly
        # zero, so a set with no spread has an exactly zero covariance (its documented rotation).
        # With no weight the centroids are 0, so that the fits are the identity transform.
        first = xp.where(positive, xp.sum(x[..., :1, :], axis=-2), 0.0)
        d = x - first[..., None, :]
        shift = xp.sum(w[..., None] * d, axis=-2) / total
        return first + shift, d - shift[..., None, :]

    (cs, s), (ct, t) = centre(source), centre(target)
    # Each centred set divided by its largest coordinate: the rotation is blind to both scales, and
    # no product over- or underflows (points at 1e30 or 1e-30 in float32 once gave non-finite or
    # identity rotations). Constants of differentiation: the similarity's scale multiplies their
    # ratio back.
    ks, kt = range_divisor(xp, _largest(xp, s)), range_divisor(xp, _largest(xp, t))
    s, t = s / ks, t / kt
    covariance = xp.matmul(xp.swapaxes(w[..., None] * t, -1, -2), s)
    spread = xp.sum(w * xp.sum(s * s, axis=-1), axis=-1)
    return cs, ct, covariance, spread, (kt / ks)[..., 0, 0]


def _largest(xp: Any, x: Any) -> Any:
    """The largest absolute coordinate of points ``(..., N, 3)``, shape ``(..., 1, 1)``."""
    return xp.amax(xp.abs(x), axis=(-2, -1), keepdims=True)


@op(source=(-1, 3), target=(-1, 3), weights=(-1,))
def fit_rigid_transform(xp: Any, source: Any, target: Any, weights: Any = None, *, procrustes: Any) -> Any:
    """The pose that best maps the points ``source`` onto ``target``: ``T`` minimising
    ``sum_i w_i |R s_i + t - t_i|^2`` (weighted Kabsch).

    Args:
        source: points, shape ``(..., N, 3)``.
        target: the points they should map onto, shape ``(..., N, 3)``; leading dimensions broadcast.
        weights: non-negative weights, shape ``(..., N)``, or ``None`` for all ones.

    Returns:
        Shape ``(..., 4, 4)``: ``R = special_procrustes(sum_i w_i (t_i - ct)(s_i - cs)^T)`` of the
        centred points (never a reflection) and ``t = ct - R cs``, with ``cs``, ``ct`` the weighted
        centroids. Degenerate sets have ``fit_rotation``'s rotation: coplanar points still determine
        it; collinear points and points all equal leave it undetermined, and it is then
        ``special_procrustes``' choice for the rank-1 or zero covariance (the identity for zero), with
        a finite gradient; weights summing to zero (or to less) give the identity transform (rotation
        and translation: no point counts), with zero gradients in the points. Scale-free: the centred
        points are divided by their largest coordinate before any product, so points anywhere in
        the dtype's range (1e-30 to 1e30 in float32) give the rotation of the same points at unit
        scale. Gradients are ``special_procrustes``' (exact wherever the rotation is unique).
    """
    cs, ct, covariance, _, _ = _centred(xp, source, target, weights)
    rotation = procrustes(xp, covariance)
    translation = ct - xp.matmul(rotation, _column(cs))[..., 0]
    return _with_bottom(xp, xp.concat([rotation, _column(translation)], axis=-1))


@op(source=(-1, 3), target=(-1, 3), weights=(-1,))
def fit_similarity_transform(
    xp: Any, source: Any, target: Any, weights: Any = None, *, procrustes: Any
) -> Any:
    """The similarity that best maps the points ``source`` onto ``target``: ``(T, s)`` minimising
    ``sum_i w_i |s R s_i + t - t_i|^2`` (weighted Umeyama).

    Args:
        source: points, shape ``(..., N, 3)``.
        target: the points they should map onto, shape ``(..., N, 3)``; leading dimensions broadcast.
        weights: non-negative weights, shape ``(..., N)``, or ``None`` for all ones.

    Returns:
        ``(matrix, scale)``: the pose ``[[R, t], [0, 1]]``, shape ``(..., 4, 4)``, and the scale ``s``,
        shape ``(...)``, with target ~ ``s R source + t``. ``R`` is ``fit_rigid_transform``'s rotation,
        ``s = tr(R^T C) / sum_i w_i |s_i - cs|^2`` (``C`` the weighted cross-covariance of the centred
        points; negative only if the target is mirrored beyond what a rotation can undo) and
        ``t = ct - s R cs``. Where the source has no spread (all points equal, or no weight) the scale
        is 1; weights summing to zero (or to less) give the identity transform and scale 1.
        Scale-free as ``fit_rigid_transform``: the rotation and ``s`` are exact for points anywhere
        in the dtype's range (``s`` itself must be representable).
    """
    # The core returns the pose with the scale in its bottom-right entry; each backend's wrapper
    # splits it off and restores the exact bottom row (so that the non-finite rule covers both).
    cs, ct, covariance, spread, ratio = _centred(xp, source, target, weights)
    rotation = procrustes(xp, covariance)
    spread_ok = spread > 0
    fit = xp.sum(rotation * covariance, axis=(-1, -2)) / xp.where(spread_ok, spread, 1.0)
    scale = xp.where(spread_ok, fit * ratio, 1.0)
    translation = ct - scale[..., None] * xp.matmul(rotation, _column(cs))[..., 0]
    top = xp.concat([rotation, _column(translation)], axis=-1)
    zero = xp.zeros_like(top[..., :1, :3])
    return xp.concat([top, xp.concat([zero, scale[..., None, None]], axis=-1)], axis=-2)


def split_similarity(xp: Any, packed: Any) -> tuple[Any, Any]:
    """``(matrix, scale)`` of ``fit_similarity_transform``'s core result: the scale sits in the
    bottom-right entry; the pose gets its bottom row back, NaN where the row is NaN (the rule for
    non-finite rows), exact elsewhere."""
    # corner - corner + 1: 1, or NaN; with no Python float, which promotes NumPy's bfloat16
    corner = packed[..., 3:, 3:]
    bottom = xp.concat([packed[..., 3:, :3], corner - corner + xp.ones_like(corner)], axis=-1)
    return xp.concat([packed[..., :3, :], bottom], axis=-2), packed[..., 3, 3]


# ---------------------------------------------------------------------------------------------------
# Frames from vectors and points

# atan2(s, d) / s as a series in x = (s / d)^2 where s / d < 0.01 (d > 0): 1/d (1 - x/3 + x^2/5 - ...);
# the first omitted term, x^5 / 11 < 1e-21, is below float64's rounding. Above, the closed form, which
# has no cancellation (a quotient); the series only keeps its derivative in s^2 finite at s = 0 (the
# closed form's autodiff there divides by s^3).
_ATAN_SERIES = (1.0, -1.0 / 3.0, 1.0 / 5.0, -1.0 / 7.0, 1.0 / 9.0)
_ATAN_SERIES_BELOW = 1e-4


def _perpendicular(xp: Any, a: Any) -> Any:
    """The unit vector orthogonal to ``a`` (non-zero) in the plane of ``a`` and the coordinate axis
    least aligned with it (the first on ties), as ``rotation_6d_to_matrix``'s fallback."""
    m = xp.abs(a)
    k0 = (m[..., 0] <= m[..., 1]) & (m[..., 0] <= m[..., 2])
    k1 = (~k0) & (m[..., 1] <= m[..., 2])
    one, nil = xp.ones_like(m[..., 0]), xp.zeros_like(m[..., 0])
    e = xp.stack([xp.where(k0, one, nil), xp.where(k1, one, nil), xp.where(k0 | k1, nil, one)], axis=-1)
    f = e * _dot(xp, a, a) - _dot(xp, a, e) * a
    return f / xp.sqrt(xp.sum(f * f, axis=-1, keepdims=True))


@op(a=(3,), b=(3,))
def rotation_between_vectors(
    xp: Any, a: Any, b: Any, *, to_matrix: Conversion = unit_quaternion_to_matrix
) -> Any:
    """The shortest-arc rotation taking the direction of ``a`` to that of ``b``.

    Args:
        a: vectors, shape ``(..., 3)``, any non-zero length.
        b: vectors, shape ``(..., 3)``; the batch shapes broadcast.

    Returns:
        Rotation matrices ``R`` with ``R a / |a| = b / |b|``, shape ``(..., 3, 3)``: the rotation by
        ``atan2(|a x b|, a . b)`` about ``a x b`` (made orthogonal to ``a`` to the last bit), through
        the quaternion. No ``1 + a . b``: ``R`` maps ``a``'s direction onto ``b``'s to a few ulps
        (16 at most) and is a rotation to a few ulps, at every angle up to exactly pi and for
        vectors of any length in the dtype's range. Vectors antiparallel to within 4 ulps
        (``|a x b| <= 4 eps |a . b|``) have no shortest arc that rounding can tell apart: the
        half-turn about the unit vector orthogonal to ``a`` in the plane of ``a`` and the coordinate
        axis least aligned with ``a`` (the first such axis on ties), on every backend. A zero ``a``
        or ``b`` gives the identity. Gradients are finite everywhere but at (those 4 ulps of)
        antiparallel vectors, where the rotation jumps; near them they grow like the axis'
        conditioning, ``1 / sin(angle)``.
    """
    return axis_angle_to_matrix(xp, _rotation_vector_between(xp, a, b), to_matrix=to_matrix)


def _between_axis(xp: Any, a: Any, b: Any, one: Any) -> tuple[Any, ...]:
    """What both forms of :func:`rotation_between_vectors` read, computed alike, so that they choose
    the half-turn at the same inputs to the bit: ``(a, c, |a|^2, d, |c|^2, d^2, antiparallel)`` with
    ``a`` as scaled, ``c`` the axis and ``d = a . b``, the last five of shape ``(..., 1)``. ``one`` is 1: an
    array in eager torch, where a Python number in ``where`` is an operation of its own."""
    a, b = match_rank(xp, a, b)
    # each divided by its largest component / 16 (range_divisor's rule): the result is scale
    # invariant, and no product over- or underflows (a constant of differentiation: it cancels)
    a, b = (
        v / cancelling_factor(xp, xp.where(m > 0, m, one))
        for v, m in ((a, _sixteenth(xp, a)), (b, _sixteenth(xp, b)))
    )
    c = _cross(xp, a, b)
    # The axis must be orthogonal to a to the last bit: the rounding of a x b (eps |a| |b| in any
    # direction; an FMA leaves it along a even for exactly antiparallel input) would otherwise move a
    # by eps / sin(angle) near antiparallel vectors. a x b is orthogonal to a, so removing its
    # component along a changes neither the value nor the derivative; |a|^2 is 0 or in [256, 768].
    na = _dot(xp, a, a)
    c = c - (_dot(xp, c, a) / xp.where(na > 0, na, one)) * a
    d = _dot(xp, a, b)
    u = _dot(xp, c, c)
    # Antiparallel to within 4 ulp (tan(gap)^2 <= (4 eps)^2: the cross product is then rounding, and
    # its direction the arithmetic's choice): the documented half-turn, which maps a's direction onto
    # b's to within the gap, the same on every backend.
    dd = d * d
    antiparallel = (d < 0) & (u <= (16.0 * xp.finfo(d.dtype).eps ** 2) * dd)
    return a, c, na, d, u, dd, antiparallel


def _sixteenth(xp: Any, v: Any) -> Any:
    """``range_divisor``'s divisor of ``v`` ``(..., 3)`` before its fallback for 0: the largest
    absolute component / 16, shape ``(..., 1)``."""
    return xp.amax(xp.abs(v), axis=-1, keepdims=True) * 0.0625


def _rotation_vector_between(xp: Any, a: Any, b: Any) -> Any:
    """The rotation vector ``(..., 3)`` of :func:`rotation_between_vectors`, its conventions."""
    a, c, _, d, u, _, antiparallel = _between_axis(xp, a, b, 1.0)
    d, u, antiparallel = d[..., 0], u[..., 0], antiparallel[..., 0]
    # rotation vector = (atan2(s, d) / s) c with s = |c| (no sqrt at 0: double where)
    series = (d > 0) & (u < _ATAN_SERIES_BELOW * (d * d))
    d_s = xp.where(series, d, 1.0)
    x = xp.where(series, u, 0.0) / (d_s * d_s)
    f_series = x * _ATAN_SERIES[-1] + _ATAN_SERIES[-2]
    for k in _ATAN_SERIES[-3::-1]:
        f_series = f_series * x + k
    closed = ~series & ~antiparallel & (u > 0)
    s = xp.sqrt(xp.where(closed, u, 1.0))
    f_closed = xp.atan2(s, xp.where(closed, d, 0.0)) / s
    f = xp.where(series, f_series / d_s, xp.where(closed, f_closed, 0.0))
    rotvec = xp.where(
        antiparallel[..., None],
        math.pi * _perpendicular(xp, xp.where(antiparallel[..., None], a, 1.0)),
        f[..., None] * c,
    )
    return rotvec


def _between_constants() -> tuple[Any, ...]:
    # 1 (the divisors' fallback, the zero vectors' r), 0 (the half-turn's w), the axes' indices, and
    # the (16, 10) quadratic forms of the nine entries and the squared norm
    return 1.0, 0.0, [0, 1, 2], _quadratic_forms()


# The eager form's own name: its arithmetic makes every entry of a non-finite row NaN (the Backend
# reads the name of the function it runs), where the componentwise form leaves that to the backend.
NONFINITE_BY_ARITHMETIC.add("rotation_between_vectors_eager")


@eager_form(of=rotation_between_vectors)
def rotation_between_vectors_eager(
    xp: Any, a: Any, b: Any, *, to_matrix: Conversion = unit_quaternion_to_matrix
) -> Any:
    """:func:`rotation_between_vectors`, eager form: the same rotation, through its quaternion without
    an angle. With ``c`` the axis and ``d = a . b`` (the componentwise form's, bit for bit, so that
    the half-turn is chosen at the same inputs), ``s = |c|`` and ``r = sqrt(s^2 + d^2)`` (``|a| |b|``),
    the quaternion is ``(cos(t/2), sin(t/2) c / s)`` with ``tan(t/2) = s / (r + d) = (r - d) / s``, so
    proportional to ``(r + d, c)``, or to ``(s^2 / (r - d), c)``: the first for ``d >= 0`` and the
    second for ``d < 0`` add two numbers of one sign, nothing cancels at any angle. The matrix is the
    quadratic forms of that quaternion over its squared norm (one product with constant
    coefficients, the norm its tenth column), which is blind to its scale. Every operation is
    smooth where it is used (``r >= |d| > 0`` and ``s^2 > 0`` wherever a branch divides by them), so
    autodiff of it is the derivative, parallel vectors included, where the componentwise form needs
    a series. Zero vectors: ``r`` is taken as 1 and ``c`` as 0, the quaternion is ``(1, 0, 0, 0)``,
    the identity to the bit, with a zero gradient. A NaN or an infinity makes the whole row NaN
    through the scaling (``inf / inf``) and every product (NONFINITE_BY_ARITHMETIC)."""
    one, zero, indices, forms = constants(xp, a, _between_constants)
    a, c, na, d, u, dd, antiparallel = _between_axis(xp, a, b, one)
    rr = u + dd
    nonzero = rr > 0
    t = xp.sqrt(xp.where(nonzero, rr, one)) + d.abs()
    w = xp.where(antiparallel, zero, xp.where(d >= 0, t, u / t))
    # the documented half-turn: its quaternion (0, f), f the part of the least aligned axis e
    # orthogonal to a (unnormalised: the matrix is blind to the quaternion's scale); a zero vector's
    # c (0) selected, so that its gradient is zero as the componentwise form's (c = a x b reads b).
    # e as a mask (argmin: the first of tied minima), not an indexed row of the identity, which
    # vmap of forward mode (jacfwd) refuses as data-dependent.
    e = a.abs().argmin(-1, keepdim=True) == indices
    v = xp.where(antiparallel, e * na - _dot(xp, a, e) * a, xp.where(nonzero, c, zero))
    q = xp.cat([w, v], -1)
    p = (q[..., :, None] * q[..., None, :]).flatten(-2) @ forms
    m, n = p.split([9, 1], -1)
    return (m / n).unflatten(-1, (3, 3))


@op(x1=(3,), x2=(3,), x3=(3,))
def frame_from_three_points(
    xp: Any, x1: Any, x2: Any, x3: Any, *, to_rotation: Callable[..., Any] = rotation_6d_to_matrix
) -> Any:
    """The pose of the frame that three points define (protein models' backbone frames from N, CA, C):
    origin ``x2``, first axis towards ``x3``, second axis in the plane of ``x1`` (on its side).

    Args:
        x1: points, shape ``(..., 3)`` (N).
        x2: points, shape ``(..., 3)``, the origin (CA).
        x3: points, shape ``(..., 3)`` (C); the batch shapes broadcast.

    Returns:
        Poses ``[[R, x2], [0, 1]]``, shape ``(..., 4, 4)``, with ``R``'s columns
        ``e1 = (x3 - x2) / |x3 - x2|``, ``e2`` the normalised part of ``x1 - x2`` orthogonal to
        ``e1``, and ``e3 = e1 x e2`` (Gram-Schmidt: ``rotation_6d_to_matrix`` of ``(x3 - x2, x1 - x2)``).
        ``R`` is a rotation to a few ulps for all finite points, at every scale in the dtype's range.
        Degenerate points never raise and have finite gradients, as in ``rotation_6d_to_matrix``:
        ``x3 = x2`` gives ``e1 = (1, 0, 0)``, and ``x1`` on the line of the other two (to within 8
        ulps of ``|x1 - x2|``) gives the ``e2`` of the coordinate axis least aligned with ``e1``.
    """
    p1, p2, p3 = match_rank(xp, x1, x2, x3)
    along, toward = p3 - p2, p1 - p2
    batch = tuple(xp.broadcast_shapes(along.shape[:-1], toward.shape[:-1]))  # all three's
    d6 = xp.concat([xp.broadcast_to(along, (*batch, 3)), xp.broadcast_to(toward, (*batch, 3))], axis=-1)
    # the backend's 6D map (torch: its eager form and rule in eager mode), else the core's
    rotation = to_rotation(xp, d6)
    origin = xp.broadcast_to(p2, (*batch, 3))
    return _with_bottom(xp, xp.concat([rotation, _column(origin)], axis=-1))
