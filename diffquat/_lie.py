"""SO(3) as a Lie group, over ``xp``: hat and vee, exp and log, the left and right Jacobians and their
inverses, and the perturbations plus and minus on either side (matrices and quaternions).

Conventions, written once (the docstrings below repeat the part each function needs):

- ``hat(w) v = w x v``: ``hat(w) = [[0, -w_z, w_y], [w_z, 0, -w_x], [-w_y, w_x, 0]]``, and ``vee`` is its
  inverse on skew matrices (of any matrix it takes the skew part ``(M - M^T) / 2``).
- ``exp(w)`` is the rotation by ``|w|`` radians about ``w / |w|`` (``axis_angle_to_matrix``), and
  ``log(R)`` its inverse with angle in [0, pi] (``matrix_to_axis_angle``).
- Jacobians (Barfoot's, Sola's and Sophus' convention): to first order in ``d``,
  ``exp(w + d) = exp(J_l(w) d) exp(w) = exp(w) exp(J_r(w) d)``. They are
  ``J_l(w) = sum_k hat(w)^k / (k + 1)!`` and ``J_r(w) = J_l(-w) = J_l(w)^T``, related by
  ``J_l(w) = exp(w) J_r(w)``. With ``t = |w|`` and ``W = hat(w)``::

      J_l(w)      = I + (1 - cos t) / t^2 W + (t - sin t) / t^3 W^2
      J_l(w)^-1   = I - W / 2 + (1 / t^2 - cot(t / 2) / (2 t)) W^2

  and ``J_r`` and ``J_r^-1`` the same with ``-W``. The inverses are the derivatives of log: for a
  rotation ``R`` with ``r = log(R)``, ``log(exp(d) R) = r + J_l(r)^-1 d`` and ``log(R exp(d)) = r +
  J_r(r)^-1 d`` to first order. ``J_l`` is defined and smooth for every ``w``; its inverse has poles
  at ``|w| = 2 pi k`` (k >= 1), where ``J_l`` is singular: its entries grow like
  ``1 / (2 pi - |w|)``, and so does their relative error (the angle's own rounding is amplified as
  much). Rotation vectors from ``log`` have ``|w| <= pi``, where the inverses are bounded.
- Perturbations: ``plus(R, d) = R exp(d)`` on the right (``side="right"``, the default: ``d`` in the
  body frame, jaxlie's, Sophus' and GTSAM's retraction) or ``exp(d) R`` on the left (``side="left"``:
  ``d`` in the world frame, lietorch's). ``minus(R1, R2) = log(R2^T R1)`` on the right and
  ``log(R1 R2^T)`` on the left, so that ``plus(R2, minus(R1, R2, side=s), side=s) = R1`` on either
  side. Quaternions: ``plus(q, d) = q exp(d)`` or ``exp(d) q``, ``minus(q1, q2) = log(q2* q1)`` or
  ``log(q1 q2*)``.

Numerics: each Jacobian is ``p I + q W + r w w^T`` (``W^2 = w w^T - t^2 I``) with coefficients that are
functions of ``u = t^2`` (see :func:`_jacobian_coefficients`): a Taylor series in ``u`` below ``u = 1``,
the closed form in half angles above, so that the coefficients themselves, not only the entries, are
accurate to a few ulps, and the first and second derivatives with them.
"""

from __future__ import annotations

import math
from typing import Any

from ._algebra import (
    _exp_eager,
    _hamilton_forms,
    _log_eager,
    _nonzero_or_identity_eager,
    axis_angle_to_matrix,
    axis_angle_to_matrix_eager,
    axis_angle_to_quaternion,
    exp_factors,
    match_rank,
    matrix_to_axis_angle,
    matrix_to_axis_angle_eager,
    quaternion_to_axis_angle,
)
from ._core import (
    Conversion,
    cancelling_factor,
    computed_once,
    constants,
    eager_form,
    matrix_to_quaternion,
    nonfinite_by_arithmetic,
    op,
    quaternion_to_matrix,
    small_matmul,
    stack_matrix,
    unit_quaternion_to_matrix,
    xyzw_to_wxyz,
    zero_or_nan,
)

SIDES = ("right", "left")


def check_side(fname: str, side: str) -> bool:
    """Whether ``side`` is ``"right"``; ``ValueError`` naming ``fname`` unless it is ``"right"`` or
    ``"left"``. A Python check of a static option: it traces."""
    if side not in SIDES:
        raise ValueError(f"{fname}: expected side to be 'right' or 'left', got {side!r}")
    return side == "right"


# ---------------------------------------------------------------------------------------------------
# hat and vee


@op(omega=(3,))
def so3_hat(xp: Any, omega: Any) -> Any:
    """The skew matrix of a vector: ``hat(w) v = w x v`` (the cross product).

    Args:
        omega: vectors, shape ``(..., 3)``.

    Returns:
        Skew-symmetric matrices ``[[0, -w_z, w_y], [w_z, 0, -w_x], [-w_y, w_x, 0]]``, shape
        ``(..., 3, 3)``; ``so3_vee`` is its inverse.
    """
    x, y, z = _components(xp, omega)
    zero = xp.zeros_like(x)
    return stack_matrix(xp, [zero, -z, y, z, zero, -x, -y, x, zero])


def _hat_forms() -> tuple[Any, ...]:
    """(3, 9): the coefficients of ``(w_x, w_y, w_z)`` in the nine entries of ``hat(w)`` (row-major);
    (9, 3): those of the entries ``M_ij`` in ``vee(M)``, halves."""
    hat = [[0.0] * 9 for _ in range(3)]
    vee = [[0.0] * 3 for _ in range(9)]
    for k, (i, j) in enumerate(((2, 1), (0, 2), (1, 0))):  # w_k sits at (i, j) and -w_k at (j, i)
        hat[k][3 * i + j], hat[k][3 * j + i] = 1.0, -1.0
        vee[3 * i + j][k], vee[3 * j + i][k] = 0.5, -0.5
    return hat, vee


@eager_form(of=so3_hat)
def so3_hat_eager(xp: Any, omega: Any) -> Any:
    """:func:`so3_hat`, eager form: one product with constant coefficients (``w_k * 1 + 0 * ...``, the
    same numbers)."""
    hat, _ = constants(xp, omega, _hat_forms)
    return xp.matmul(omega, hat).unflatten(-1, (3, 3))


@op(matrix=(3, 3))
def so3_vee(xp: Any, matrix: Any) -> Any:
    """The vector of the skew part of a matrix: ``vee((M - M^T) / 2)``, the inverse of ``so3_hat``.

    Args:
        matrix: any matrices, shape ``(..., 3, 3)``.

    Returns:
        ``((M_21 - M_12) / 2, (M_02 - M_20) / 2, (M_10 - M_01) / 2)``, shape ``(..., 3)``: ``w`` for
        ``M = hat(w)``, exactly, and ``sin(t) axis`` for a rotation by ``t`` about ``axis``.
    """
    return 0.5 * xp.stack(
        [
            matrix[..., 2, 1] - matrix[..., 1, 2],
            matrix[..., 0, 2] - matrix[..., 2, 0],
            matrix[..., 1, 0] - matrix[..., 0, 1],
        ],
        axis=-1,
    )


@eager_form(of=so3_vee)
def so3_vee_eager(xp: Any, matrix: Any) -> Any:
    """:func:`so3_vee`, eager form: the entries times constant halves, one product (``0.5 a - 0.5 b`` is
    ``0.5 (a - b)`` to the last bit: halving is exact)."""
    _, vee = constants(xp, matrix, _hat_forms)
    return xp.matmul(matrix.flatten(-2), vee)


# ---------------------------------------------------------------------------------------------------
# exp and log: the maps of axis_angle_to_matrix and matrix_to_axis_angle, under the names Lie users
# look for. One implementation: these call those, with the same conversion step.


# NaN or inf reaches every component of the quaternion through the angle, and every entry from there.
@nonfinite_by_arithmetic
@op(omega=(3,))
def so3_exp(xp: Any, omega: Any, *, to_matrix: Conversion = unit_quaternion_to_matrix) -> Any:
    """The exponential map of SO(3): the rotation matrix of a rotation vector, ``(..., 3)`` to
    ``(..., 3, 3)``; the map of ``axis_angle_to_matrix``.

    ``exp(w)`` rotates by ``|w|`` radians about ``w / |w|``; ``exp(0) = I``. Exact and smooth at 0,
    gradient included (through the unit quaternion, in half angles), for every ``w``."""
    return axis_angle_to_matrix(xp, omega, to_matrix=to_matrix)


# As matrix_to_axis_angle: NaN rows by arithmetic.
@nonfinite_by_arithmetic
@op(matrix=(3, 3))
def so3_log(xp: Any, matrix: Any, *, to_quaternion: Conversion = matrix_to_quaternion) -> Any:
    """The logarithm of SO(3): the rotation vector ``axis * angle`` of a rotation matrix, angle in
    [0, pi], ``(..., 3, 3)`` to ``(..., 3)``; the map of ``matrix_to_axis_angle``.

    Accurate near 0 and pi (largest pivot, then atan2). At exactly pi the vector takes the sign of the
    canonical quaternion: log jumps to the antipode there, as every logarithm must; its gradient stays
    finite."""
    return matrix_to_axis_angle(xp, matrix, to_quaternion=to_quaternion)


@eager_form(of=so3_exp)
def so3_exp_eager(xp: Any, omega: Any, *, to_matrix: Conversion = unit_quaternion_to_matrix) -> Any:
    """:func:`so3_exp`, eager form: ``axis_angle_to_matrix``'s."""
    return axis_angle_to_matrix_eager(xp, omega)


@eager_form(of=so3_log)
def so3_log_eager(xp: Any, matrix: Any, *, to_quaternion: Conversion = matrix_to_quaternion) -> Any:
    """:func:`so3_log`, eager form: ``matrix_to_axis_angle``'s."""
    return matrix_to_axis_angle_eager(xp, matrix, to_quaternion=to_quaternion)


# ---------------------------------------------------------------------------------------------------
# Jacobians


# Why u = t^2 < 1 (t = 1 radian), and why for every dtype: the closed forms of the outer coefficients
# subtract nearly equal numbers, t - sin t ~ t^3 / 6 and 1 - (t/2) cot(t/2) ~ t^2 / 12, so their
# rounding errors are amplified by ~6 / t^2 and ~12 / t^2 in relative terms: the same number of ulps
# whatever the dtype. Measured against mpmath from t = 1 on: within 3 ulps (t - sin t) and 10 ulps
# (1/t^2 - cot(t/2) / (2 t)), in float32 and float64 alike; from t = 0.5 on already 10 and 50 ulps; at
# t = 0.02 (eps^(1/4) in float32, the usual switch) 2e3 to 2e4 ulps. The derivative of a closed form
# loses the same factor again (autodiff of t - sin t computes 1 - cos t), so from t = 1 on the first
# and second derivatives are accurate too (float32: within 2 and 20 ulps of a float64 evaluation).
# Below, the Taylor series in u, as long as the dtype needs (see _truncated): what depends on the
# dtype is the length of the series, not where it is used.
SERIES_BELOW = 1.0

# |B_2|, |B_4|, ..., |B_24| (Bernoulli numbers): (t/2) cot(t/2) = 1 - sum_n |B_2n| t^2n / (2n)!.
_BERNOULLI = (
    1 / 6, 1 / 30, 1 / 42, 1 / 30, 5 / 66, 691 / 2730, 7 / 6, 3617 / 510, 43867 / 798, 174611 / 330,
    854513 / 138, 236364091 / 2730,
)  # fmt: skip
# Taylor coefficients in u = t^2 of each coefficient function.
# (1 - cos t) / t^2 = 1/2 - u/24 + u^2/720 - ...
_A_SERIES = tuple((-1) ** k / math.factorial(2 * k + 2) for k in range(12))
# (t - sin t) / t^3 = 1/6 - u/120 + u^2/5040 - ...
_B_SERIES = tuple((-1) ** k / math.factorial(2 * k + 3) for k in range(12))
# 1/t^2 - cot(t/2) / (2 t) = (1 - (t/2) cot(t/2)) / t^2 = 1/12 + u/720 + u^2/30240 + ... (converging for
# t < 2 pi, where its pole is: the terms shrink by about u / (4 pi^2) each, 1/40 at u = 1)
_C_SERIES = tuple(b / math.factorial(2 * k + 2) for k, b in enumerate(_BERNOULLI))


def _truncated(coefficients: tuple[float, ...], eps: float, below: float = SERIES_BELOW) -> tuple[float, ...]:
    """The shortest head of a Taylor series in u whose first omitted term at ``u = below`` (where the
    series stops being used) is below a quarter of an ulp (``eps / 4``) of its leading term: float32
    takes 5 terms of each series here, float64 8 (t - sin t), 9 (1 - cos t) and 11 (the inverse's).
    Not cached: a dozen comparisons of Python numbers, and Dynamo warns of ``functools.cache``."""
    for n in range(2, len(coefficients)):
        if abs(coefficients[n]) * below**n <= 0.25 * eps * abs(coefficients[0]):
            return coefficients[:n]
    raise AssertionError("the series tables are too short for this dtype")  # pragma: no cover


def _series(xp: Any, u: Any, coefficients: tuple[float, ...], below: float = SERIES_BELOW) -> Any:
    """Horner's evaluation of the series at ``u < below``, truncated for ``u``'s dtype
    (:func:`_truncated`)."""
    terms = _truncated(coefficients, float(xp.finfo(u.dtype).eps), below)
    out = terms[-1] * u + terms[-2]
    for c in terms[-3::-1]:
        out = out * u + c
    return out


def _angle(xp: Any, omega: Any) -> tuple[Any, Any, Any, Any]:
    """Whether the series is used (``u = |w|^2 < SERIES_BELOW``); ``u`` for the series (0 where it is
    not used: no overflow of its powers there); ``u`` and ``t = |w|`` for the closed forms (1 where
    they are not used: double where, so that neither sqrt at 0 nor a division by t meets the
    cotangent of a discarded branch)."""
    u = xp.sum(omega * omega, axis=-1)
    small = u < SERIES_BELOW
    closed = xp.where(small, SERIES_BELOW, u)
    return small, xp.where(small, u, 0.0), closed, xp.sqrt(closed)


def _jacobian_coefficients(xp: Any, omega: Any) -> tuple[Any, Any, Any]:
    """``(p, q, r)`` with ``J_l(w) = p I + q W + r w w^T``: ``p = sin t / t``, ``q = (1 - cos t) / t^2``,
    ``r = (t - sin t) / t^3`` (from ``W^2 = w w^T - t^2 I``: ``p = 1 - t^2 r``).

    Closed forms: ``1 - cos t`` as ``2 sin^2(t/2)`` (no cancellation at small t), and ``t - sin t``
    with ``sin t`` itself (exact subtraction, Sterbenz); series below ``SERIES_BELOW``, where ``p`` is
    ``1 - u r`` (no cancellation: ``u r <= 1/6`` there)."""
    small, us, uc, t = _angle(xp, omega)
    r_series = _series(xp, us, _B_SERIES)
    sin_t, sin_half = xp.sin(t), xp.sin(0.5 * t)
    p = xp.where(small, 1.0 - us * r_series, sin_t / t)
    q = xp.where(small, _series(xp, us, _A_SERIES), 2.0 * (sin_half * sin_half) / uc)
    r = xp.where(small, r_series, (t - sin_t) / (t * uc))
    return p, q, r


def _inverse_coefficients(xp: Any, omega: Any) -> tuple[Any, Any]:
    """``(p, r)`` with ``J_l(w)^-1 = p I - W / 2 + r w w^T``: ``p = (t/2) cot(t/2)`` and
    ``r = (1 - p) / t^2 = 1/t^2 - cot(t/2) / (2 t)``.

    ``p`` is ``cos(t/2) / sin(t/2)`` times ``t/2``, in half angles: the usual ``(1 + cos t) / sin t``
    loses every digit near pi, where ``1 + cos t`` cancels (here ``cos(t/2)`` is accurate to its last
    bit); near ``t = 2 pi`` ``sin(t/2)`` vanishes: the pole of ``J^-1``. Series below
    ``SERIES_BELOW``, where ``1 - p`` cancels."""
    small, us, uc, t = _angle(xp, omega)
    r_series = _series(xp, us, _C_SERIES)
    half = 0.5 * t
    p_closed = half * xp.cos(half) / xp.sin(half)
    p = xp.where(small, 1.0 - us * r_series, p_closed)
    r = xp.where(small, r_series, (1.0 - p_closed) / uc)
    return p, r


def _components(xp: Any, v: Any) -> tuple[Any, Any, Any]:
    """The three components of ``(..., 3)`` vectors, read with the namespace's ``unstack`` where it
    has one (jax; see ``_core.unstack_quaternion``): jax transposes three slices into three
    zero-padded copies of the cotangent summed, and one ``unstack`` into one ``stack``."""
    unstack = getattr(xp, "unstack", None)
    if unstack is None:
        return v[..., 0], v[..., 1], v[..., 2]
    x, y, z = unstack(v, axis=-1)
    return x, y, z


def _assemble(xp: Any, omega: Any, p: Any, q: Any, r: Any) -> Any:
    """``p I + q hat(w) + r w w^T``, shape ``(..., 3, 3)``; ``q`` an array or a number.

    Entry by entry, not as a broadcast outer product ``(r w)[..., :, None] * w[..., None, :]``: jax's
    reverse mode of that is a reduction over a broadcast axis, which XLA:CPU runs far slower than the
    transposed stack of nine entries. The callers pass coefficients marked ``computed_once``: XLA would
    otherwise fuse them (sines, series) into each of the nine entries and their cotangents,
    recomputing them there (docs/performance.md, Formula shapes)."""
    x, y, z = _components(xp, omega)
    rx, ry = r * x, r * y
    # each product of the symmetric part once: torch's eager time at small N is its number of operations
    rxy, rxz, ryz = rx * y, rx * z, ry * z
    qx, qy, qz = q * x, q * y, q * z
    return stack_matrix(
        xp,
        [
            p + rx * x, rxy - qz, rxz + qy,
            rxy + qz, p + ry * y, ryz - qx,
            rxz - qy, ryz + qx, p + (r * z) * z,
        ],
    )  # fmt: skip


_JACOBIAN_DOC = """

    Convention: ``exp(w + d) = exp(J_l(w) d) exp(w) = exp(w) exp(J_r(w) d)`` to first order in ``d``;
    ``J_r(w) = J_l(-w) = J_l(w)^T`` and ``J_l(w) = exp(w) J_r(w)``. With ``t = |w|``, ``W = hat(w)``:
    ``J_l = I + (1 - cos t) / t^2 W + (t - sin t) / t^3 W^2`` (``J_r``: ``-W``).
"""
_INVERSE_DOC = """

    With ``t = |w|``, ``W = hat(w)``: ``J_l^-1 = I - W / 2 + (1/t^2 - cot(t/2) / (2 t)) W^2`` (``J_r^-1``:
    ``+W / 2``), the derivative of log: ``log(exp(d) R) = log(R) + J_l(log R)^-1 d`` and
    ``log(R exp(d)) = log(R) + J_r(log R)^-1 d`` to first order. Pole at ``|w| = 2 pi`` (and every
    ``2 pi k``), where ``J`` is singular: finite but huge near it, the entries and their relative error
    growing like ``1 / (2 pi - |w|)``. Bounded for ``|w| <= pi``, the range of log.
"""
_ACCURACY_DOC = """
    Args:
        omega: rotation vectors, shape ``(..., 3)``, any length. A NaN or an infinity makes the whole
            matrix NaN (through ``|w|^2``, which every entry reads).

    Returns:
        Shape ``(..., 3, 3)``. The coefficients are Taylor series below ``|w| = 1`` and closed forms in
        half angles above: exact at 0 and accurate to a few ulps everywhere (tested against mpmath),
        first and second derivatives included.
"""


@nonfinite_by_arithmetic
@op(omega=(3,))
def so3_left_jacobian(xp: Any, omega: Any) -> Any:
    p, q, r = computed_once(xp, _jacobian_coefficients(xp, omega))
    return _assemble(xp, omega, p, q, r)


@nonfinite_by_arithmetic
@op(omega=(3,))
def so3_right_jacobian(xp: Any, omega: Any) -> Any:
    p, q, r = computed_once(xp, _jacobian_coefficients(xp, omega))
    return _assemble(xp, omega, p, -q, r)


@nonfinite_by_arithmetic
@op(omega=(3,))
def so3_left_jacobian_inverse(xp: Any, omega: Any) -> Any:
    p, r = computed_once(xp, _inverse_coefficients(xp, omega))
    return _assemble(xp, omega, p, -0.5, r)


@nonfinite_by_arithmetic
@op(omega=(3,))
def so3_right_jacobian_inverse(xp: Any, omega: Any) -> Any:
    p, r = computed_once(xp, _inverse_coefficients(xp, omega))
    return _assemble(xp, omega, p, 0.5, r)


# ---------------------------------------------------------------------------------------------------
# Eager forms of the Jacobians (_core.EAGER_FORMS: eager torch outside graph capture). The same
# coefficients (series below SERIES_BELOW, the same closed forms above), each evaluated for all its
# columns at once over a trailing axis: Horner's scheme as one ``addcmul`` per term for the three
# series together, the closed forms as one ``sin`` of (t, t/2). The matrix ``p I + q W + r w w^T`` is
# then linear in the outer product of ``v = (1, w)``: ``(v v^T) * (coefficients @ E)`` contracted with
# a constant (16, 9) matrix (:func:`_jacobian_forms`). About 30 operations, where the componentwise
# formulas take 53-66.

# sin t / t = 1 - u/6 + u^2/120 - ...: p as its own series (no cancellation)
_P_SERIES = tuple((-1) ** k / math.factorial(2 * k + 1) for k in range(12))
# (t/2) cot(t/2) = 1 - u C(u): the inverse's p as its own series
_INVERSE_P_SERIES = (1.0, *(-c for c in _C_SERIES[:11]))


def _jacobian_forms() -> tuple[list[Any], ...]:
    """Constants of :func:`_assemble_eager`: ``A`` (16, 9), row ``4 a + b`` the entries that
    ``v_a v_b`` (``v = (1, w)``) feeds in ``I`` (a = b = 0), ``hat(w)`` (a = 0 < b) and ``w w^T``
    (a, b > 0); and the maps ``E`` of the coefficients to the 16 products: ``(p, q, r)`` (left),
    ``(p, -q, r)`` (right), ``(p, 4 r)`` with the bias ``-+1/2`` on ``hat(w)`` (left and right
    inverses: :func:`_inverse_coefficients_eager`'s pair)."""
    a = [[0.0] * 9 for _ in range(16)]
    for k in (0, 4, 8):
        a[0][k] = 1.0
    # hat(w) = [[0, -z, y], [z, 0, -x], [-y, x, 0]], row-major
    for b, entries in ((1, ((5, -1.0), (7, 1.0))), (2, ((2, 1.0), (6, -1.0))), (3, ((1, -1.0), (3, 1.0)))):
        for k, sign in entries:
            a[b][k] = sign
    for i in range(3):
        for j in range(3):
            a[4 * (i + 1) + j + 1][3 * i + j] = 1.0
    kind = [0] + [1] * 3 + [1 if b == 0 else 2 for a_ in range(1, 4) for b in range(4)]
    left = [[1.0 if kind[j] == c else 0.0 for j in range(16)] for c in range(3)]
    right = [[(-1.0 if c == 1 else 1.0) if kind[j] == c else 0.0 for j in range(16)] for c in range(3)]
    inverse = [left[0], [0.25 * x for x in left[2]]]
    bias_left = [-0.5 if kind[j] == 1 else 0.0 for j in range(16)]
    bias_right = [0.5 if kind[j] == 1 else 0.0 for j in range(16)]
    return a, left, right, inverse, bias_left, bias_right


_EPS = (1.1920928955078125e-07, 2.220446049250313e-16)  # float32's and float64's (the compute dtypes)


def _series_tables(*series: tuple[float, ...], below: float = SERIES_BELOW) -> tuple[list[Any], ...]:
    """For float32, then float64: the constant terms, the powers ``1, ..., n - 1`` and the
    ``(n - 1, m)`` table of the next terms of ``m`` series, ``n`` the most any of them needs in that
    dtype (:func:`_truncated`: a quarter of an ulp at ``below``; more terms only round closer)."""
    out: list[list[Any]] = []
    for eps in _EPS:
        n = max(len(_truncated(s, eps, below)) for s in series)
        out += [
            [s[0] for s in series],
            [float(k) for k in range(1, n)],
            [[s[k] for s in series] for k in range(1, n)],
        ]
    return tuple(out)


def _jacobian_constants() -> tuple[list[Any], ...]:
    """``(1, 1/2)`` (the angles whose sines the closed forms read), ``(1, 0)`` and ``(0, 2)`` (the
    numerators ``sin t`` and ``2 sin^2(t/2)``), and the series tables of ``(p, q, r)``."""
    return [1.0, 0.5], [1.0, 0.0], [0.0, 2.0], *_series_tables(_P_SERIES, _A_SERIES, _B_SERIES)


def _inverse_constants() -> tuple[list[Any], ...]:
    """``(0, 1)`` (``(-p, 1 - p)`` from ``p``), and the series tables of the inverse's ``(p, 4 r)``
    (:func:`_inverse_coefficients_eager`)."""
    return [0.0, 1.0], *_series_tables(_INVERSE_P_SERIES, tuple(4.0 * c for c in _C_SERIES))


def _series_eager(xp: Any, u: Any, tables: tuple[Any, ...], closed: Any = None, small: Any = None) -> Any:
    """The series of :func:`_series_tables` at ``u`` ``(..., 1)``: ``(..., m)``, the powers ``u^k``
    (one ``pow``) times the table plus the constant terms (one ``addmm``), where Horner's scheme takes
    two operations a term, forward and backward. Below ``SERIES_BELOW`` (``u < 1``) the terms fall,
    so the sum of the products is as accurate as Horner's. No power 0: ``pow``'s derivative in the
    base at ``u = 0`` is 0 by a selection, whose discarded branch ``0 * u^-1`` is NaN in the second
    derivative.

    ``closed``, where given, is the value where ``small`` is false, selected into the constant terms:
    there ``u`` is 0 (the caller's ``u * small``), its powers are 0, and the sum is ``closed + 0``,
    exactly ``closed``. So the selection has one cotangent to route, the constant terms needing none:
    one ``where`` backward, where a selection after the sum routes two."""
    first, powers, table = tables[:3] if u.dtype.itemsize <= 4 else tables[3:]
    if closed is not None:
        first = xp.where(small, first, closed)
    if u.ndim == 2:
        return xp.addmm(first, u**powers, table)
    return xp.matmul(u**powers, table) + first


def _angle_eager(xp: Any, omega: Any) -> tuple[Any, Any, Any, Any]:
    """:func:`_angle` with a trailing unit axis: ``(small, u for the series, u and t for the closed
    forms)``, each ``(..., 1)``."""
    u = (omega * omega).sum(-1, keepdim=True)
    small = u < SERIES_BELOW
    # Double where by arithmetic with the mask, not wheres with a number (a scalar tensor made per
    # call) nor clamps (three operations each backward): the series reads 0 where the closed form is
    # chosen, the closed forms u + SERIES_BELOW (in [1, 2), finite sines) where the series is.
    closed = xp.add(u, small, alpha=SERIES_BELOW)
    return small, u * small, closed, xp.sqrt(closed)


def _jacobian_coefficients_eager(xp: Any, omega: Any) -> Any:
    """:func:`_jacobian_coefficients` as one ``(..., 3)`` array ``(p, q, r)``."""
    ang, num_a, num_b, *tables = constants(xp, omega, _jacobian_constants)
    small, us, uc, t = _angle_eager(xp, omega)
    s = xp.sin(t * ang)
    # (sin t, 2 sin^2(t/2)) / (t, t^2), and (t - sin t) / t^3 with sin t itself (Sterbenz)
    pq = s * xp.addcmul(num_a, s, num_b) / xp.cat([t, uc], -1)
    closed = xp.cat([pq, (t - s[..., :1]) / (t * uc)], -1)
    return _series_eager(xp, us, tuple(tables), closed, small)


def _inverse_coefficients_eager(xp: Any, omega: Any) -> Any:
    """:func:`_inverse_coefficients` as one ``(..., 2)`` array ``(p, 4 r)`` (the forms ``inverse`` of
    :func:`_jacobian_forms` take ``r`` back by a quarter, exactly: a power of 2)."""
    zero_one, *tables = constants(xp, omega, _inverse_constants)
    u = (omega * omega).sum(-1, keepdim=True)
    small = u < SERIES_BELOW
    # The closed forms read (t/2)^2 = u / 4 directly (exact), so that t/2 is one square root, and the
    # double where by arithmetic with the mask (as _angle_eager): 1 + u / 4 in [1, 1.25) where the
    # series is chosen, which reads 0 where the closed forms are.
    quarter = xp.add(small, u, alpha=0.25)
    half = xp.sqrt(quarter)
    # cos / sin, not 1 / tan: at a half-turn (t/2 = pi/2) tan's derivatives are of size 1e16 and the
    # second derivative of (t/2) / tan(t/2) cancels them to O(1), losing every digit (measured)
    p = half * xp.cos(half) / xp.sin(half)
    # (p, 4 r) = (0 - p, 1 - p) / (-1, (t/2)^2): one division of two columns, whose backward takes
    # fewer operations than a division, a subtraction and a concatenation (0 - p, -p / -1 exact)
    pair = (zero_one - p) / xp.nn.functional.pad(quarter, (1, 0), value=-1.0)
    return _series_eager(xp, u * small, tuple(tables), pair, small)


def _assemble_eager(xp: Any, omega: Any, coefficients: Any, forms: Any, bias: Any = None) -> Any:
    """``p I + q hat(w) + r w w^T`` of :func:`_assemble`, from ``coefficients @ forms (+ bias)``, the
    coefficient of each product ``v_a v_b`` of ``v = (1, w)`` (:func:`_jacobian_forms`)."""
    (a, *_) = constants(xp, omega, _jacobian_forms)
    v = xp.nn.functional.pad(omega, (1, 0), value=1.0)
    if bias is None:
        g = xp.matmul(coefficients, forms)
    else:
        g = (
            xp.addmm(bias, coefficients, forms)
            if coefficients.ndim == 2
            else xp.matmul(coefficients, forms) + bias
        )
    return xp.matmul((v[..., :, None] * v[..., None, :]).flatten(-2) * g, a).unflatten(-1, (3, 3))


@eager_form(of=so3_left_jacobian)
def so3_left_jacobian_eager(xp: Any, omega: Any) -> Any:
    """:func:`so3_left_jacobian`, eager form (see above)."""
    _, left, *_ = constants(xp, omega, _jacobian_forms)
    return _assemble_eager(xp, omega, _jacobian_coefficients_eager(xp, omega), left)


@eager_form(of=so3_right_jacobian)
def so3_right_jacobian_eager(xp: Any, omega: Any) -> Any:
    """:func:`so3_right_jacobian`, eager form (see above)."""
    _, _, right, *_ = constants(xp, omega, _jacobian_forms)
    return _assemble_eager(xp, omega, _jacobian_coefficients_eager(xp, omega), right)


@eager_form(of=so3_left_jacobian_inverse)
def so3_left_jacobian_inverse_eager(xp: Any, omega: Any) -> Any:
    """:func:`so3_left_jacobian_inverse`, eager form (see above)."""
    _, _, _, inverse, bias, _ = constants(xp, omega, _jacobian_forms)
    return _assemble_eager(xp, omega, _inverse_coefficients_eager(xp, omega), inverse, bias)


@eager_form(of=so3_right_jacobian_inverse)
def so3_right_jacobian_inverse_eager(xp: Any, omega: Any) -> Any:
    """:func:`so3_right_jacobian_inverse`, eager form (see above)."""
    _, _, _, inverse, _, bias = constants(xp, omega, _jacobian_forms)
    return _assemble_eager(xp, omega, _inverse_coefficients_eager(xp, omega), inverse, bias)


so3_left_jacobian.__doc__ = "The left Jacobian ``J_l(w)`` of SO(3)." + _JACOBIAN_DOC + _ACCURACY_DOC
so3_right_jacobian.__doc__ = (
    "The right Jacobian ``J_r(w) = J_l(-w)`` of SO(3)." + _JACOBIAN_DOC + _ACCURACY_DOC
)
so3_left_jacobian_inverse.__doc__ = (
    "The inverse ``J_l(w)^-1`` of the left Jacobian of SO(3)." + _JACOBIAN_DOC.rstrip() + _INVERSE_DOC
    + _ACCURACY_DOC
)  # fmt: skip
so3_right_jacobian_inverse.__doc__ = (
    "The inverse ``J_r(w)^-1 = J_l(-w)^-1`` of the right Jacobian of SO(3)." + _JACOBIAN_DOC.rstrip()
    + _INVERSE_DOC + _ACCURACY_DOC
)  # fmt: skip


# ---------------------------------------------------------------------------------------------------
# plus and minus


@nonfinite_by_arithmetic
@op(matrix=(3, 3), delta=(3,))
def so3_plus(
    xp: Any,
    matrix: Any,
    delta: Any,
    *,
    side: str = "right",
    # the normalising conversion, not exp's unit one: with that, XLA:CPU fuses the nine entries into
    # the product (docs/performance.md, Formula shapes)
    to_matrix: Conversion = quaternion_to_matrix,
) -> Any:
    """A rotation matrix perturbed by a rotation vector: ``R exp(d)`` (``side="right"``) or
    ``exp(d) R`` (``side="left"``).

    Args:
        matrix: rotation matrices ``R``, shape ``(..., 3, 3)`` (multiplied as they are, not projected
            onto SO(3)).
        delta: rotation vectors ``d``, shape ``(..., 3)``, any length; the batch shapes of ``matrix``
            and ``delta`` broadcast.
        side: ``"right"`` (``d`` in the body frame, the default) or ``"left"`` (``d`` in the world
            frame); anything else raises ``ValueError``.

    Returns:
        Shape ``(..., 3, 3)``. ``so3_plus(R2, so3_minus(R1, R2, side=s), side=s) == R1`` on either side.
    """
    right = check_side("so3_plus", side)
    # Non-finite rows by arithmetic: a NaN or an infinity in delta makes the step's whole quaternion NaN
    # (through the angle), but one in R reaches only a row (or a column) of the product, so
    # zero_or_nan of R (0 where R is finite, NaN where it is not) is added to the quaternion, a
    # constant of differentiation: cheaper than the selection after the product (a pass over the
    # inputs and one over the output), and than adding it to R (an extra pass over R before the
    # product; docs/performance.md, Formula shapes). On the quaternion, a delta shared by a batch of
    # R is exponentiated once per R (the same values to rounding).
    poison = cancelling_factor(xp, zero_or_nan(xp, matrix, 2))
    q, poison = match_rank(xp, axis_angle_to_quaternion(xp, delta), poison[..., None])
    step = to_matrix(xp, computed_once(xp, q + poison))
    matrix, step = match_rank(xp, matrix, step)
    return small_matmul(xp, matrix, step) if right else small_matmul(xp, step, matrix)


# A non-finite entry of either matrix makes a row or column of the relative rotation non-finite, which
# every candidate of matrix_to_quaternion reads: NaN rows by arithmetic.
@nonfinite_by_arithmetic
@op(matrix1=(3, 3), matrix2=(3, 3))
def so3_minus(
    xp: Any,
    matrix1: Any,
    matrix2: Any,
    *,
    side: str = "right",
    to_quaternion: Conversion = matrix_to_quaternion,
) -> Any:
    """The rotation vector from one rotation matrix to another: ``log(R2^T R1)`` (``side="right"``) or
    ``log(R1 R2^T)`` (``side="left"``), angle in [0, pi].

    Args:
        matrix1: rotation matrices ``R1``, shape ``(..., 3, 3)``.
        matrix2: rotation matrices ``R2``, shape ``(..., 3, 3)``; the batch shapes broadcast.
        side: ``"right"`` (the default) or ``"left"``, as in ``so3_plus``; anything else raises
            ``ValueError``.

    Returns:
        Shape ``(..., 3)``, the inverse of ``so3_plus`` on the same side:
        ``so3_plus(R2, so3_minus(R1, R2, side=s), side=s) == R1``. Where ``R1`` and ``R2`` are a
        half-turn apart the vector takes the sign of the canonical quaternion (``so3_log``'s rule):
        it jumps there, with a finite gradient.
    """
    relative = _relative_matrix(xp, matrix1, matrix2, check_side("so3_minus", side))
    return matrix_to_axis_angle(xp, relative, to_quaternion=to_quaternion)


def _relative_matrix(xp: Any, matrix1: Any, matrix2: Any, right: bool) -> Any:
    """``R2^T R1`` (right) or ``R1 R2^T`` (left), batch shapes broadcast: both forms of ``so3_minus``
    compute it alike, so that a half-turn takes the same sign in each."""
    a, b = match_rank(xp, matrix1, matrix2)
    b_t = xp.swapaxes(b, -1, -2)
    return small_matmul(xp, b_t, a) if right else small_matmul(xp, a, b_t)


def _unit(xp: Any, q: Any, scalar_first: bool, one: Any = 1.0, zero: Any = 0.0) -> tuple[Any, Any]:
    """``q / |q|`` as its scalar part ``(..., 1)`` and vector part ``(..., 3)``, the zero quaternion
    (squared norm below the smallest normal number, as ``nonzero_or_identity``) read as the identity.

    Divided by the largest component before the norm is taken (as ``_core._unit_components`` does),
    so that no derivative meets a power of ``1 / |q|^2``, which overflows float32 at small norms; that
    scale cancels out of the result, so it is not differentiated (``cancelling_factor``). The zero
    quaternion gets the factor 0 and then w = 1: a selection, with a zero derivative. On the
    ``(..., 4)`` array, not component by component: a quarter of the operations, which is what torch's
    eager time at small N is made of. Scalar-last input is reordered first, so that the sums over the
    last axis add in one order and both storage orders give the very same numbers. ``one`` and
    ``zero`` are the selected constants: an eager caller's constant tensors (``_core.constants``)
    select the same numbers without making a tensor of a Python number per ``where``."""
    if not scalar_first:
        q = xyzw_to_wxyz(xp, q)
    is_zero = xp.sum(q * q, axis=-1, keepdims=True) < xp.finfo(q.dtype).tiny
    big = cancelling_factor(xp, xp.amax(xp.abs(q), axis=-1, keepdims=True))
    scaled = q / xp.where(is_zero, one, big)
    s2 = xp.sum(scaled * scaled, axis=-1, keepdims=True)
    # 1 <= s2 <= 4 where it is used (the largest component is 1); the discarded branch sees 1.
    unit = scaled * xp.where(is_zero, zero, 1.0 / xp.sqrt(xp.where(is_zero, one, s2)))
    return xp.where(is_zero, one, unit[..., :1]), unit[..., 1:]


def _product(p: tuple[Any, Any], q: tuple[Any, Any], xp: Any) -> tuple[Any, Any]:
    """The Hamilton product of quaternions given as (scalar ``(..., 1)``, vector ``(..., 3)``):
    ``(pw qw - pv . qv, pw qv + qw pv + pv x qv)``. On the vectors as arrays, a cross product and a
    sum, not sixteen products of components: fewer operations for torch eager, and XLA fuses it
    better than ``hamilton``'s components (docs/performance.md, Formula shapes). As in
    ``hamilton``, ``pw qv + qw pv`` is one parenthesis, so that ``p* p`` has an exactly zero vector
    part."""
    pw, pv = p
    qw, qv = q
    scalar = pw * qw - xp.sum(pv * qv, axis=-1, keepdims=True)
    return scalar, (pw * qv + qw * pv) + xp.linalg.cross(pv, qv)


def _join(xp: Any, w: Any, v: Any, scalar_first: bool) -> Any:
    return xp.concat([w, v] if scalar_first else [v, w], axis=-1)


# NaN or inf in q reaches every component through the norm, and in delta through the angle.
@nonfinite_by_arithmetic
@op(q=(4,), delta=(3,))
def quaternion_plus(xp: Any, q: Any, delta: Any, *, side: str = "right", scalar_first: bool = True) -> Any:
    """A quaternion perturbed by a rotation vector: ``q exp(d)`` (``side="right"``) or ``exp(d) q``
    (``side="left"``), as a unit quaternion; the rotation of ``so3_plus``.

    Args:
        q: quaternions, shape ``(..., 4)``, any non-zero norm (normalised first; the zero quaternion
            is the identity).
        delta: rotation vectors ``d``, shape ``(..., 3)``, any length; batch shapes broadcast.
        side: ``"right"`` (the default) or ``"left"``; anything else raises ``ValueError``.
        scalar_first: storage order of ``q`` and of the result.

    Returns:
        Unit quaternions, shape ``(..., 4)``. The sign is the product's, not standardised: the map is
        smooth in ``q`` and ``d`` (a canonical sign would jump where w crosses 0), and ``-q`` gives the
        negated result, the same rotation. ``standardize_quaternion`` gives the canonical sign.
    """
    right = check_side("quaternion_plus", side)
    q, delta = match_rank(xp, q, delta)
    unit = _unit(xp, q, scalar_first)
    w, k = exp_factors(xp, xp.sum(delta * delta, axis=-1, keepdims=True))
    step = (w, k * delta)
    return _join(xp, *(_product(unit, step, xp) if right else _product(step, unit, xp)), scalar_first)


@nonfinite_by_arithmetic  # through the norms of q1 and q2 (see quaternion_plus), then the angle
@op(q1=(4,), q2=(4,))
def quaternion_minus(xp: Any, q1: Any, q2: Any, *, side: str = "right", scalar_first: bool = True) -> Any:
    """The rotation vector from one quaternion to another: ``log(q2* q1)`` (``side="right"``) or
    ``log(q1 q2*)`` (``side="left"``), angle in [0, pi]; the value of ``so3_minus`` on the rotations.

    Args:
        q1: quaternions, shape ``(..., 4)``, any non-zero norm; the zero quaternion is the identity.
            Blind to the sign: ``q`` and ``-q`` are one rotation.
        q2: quaternions, shape ``(..., 4)``, as ``q1``; the batch shapes broadcast.
        side: ``"right"`` (the default) or ``"left"``; anything else raises ``ValueError``.
        scalar_first: storage order of ``q1`` and ``q2``.

    Returns:
        Shape ``(..., 3)``: ``quaternion_plus(q2, quaternion_minus(q1, q2, side=s), side=s)`` is ``q1``
        up to sign and norm. Where the two are a half-turn apart the vector takes the sign of the
        canonical quaternion (``quaternion_to_axis_angle``'s rule): it jumps there, with a finite
        gradient.
    """
    relative = _relative_quaternion(xp, q1, q2, check_side("quaternion_minus", side), scalar_first)
    return quaternion_to_axis_angle(xp, relative)


def _relative_quaternion(xp: Any, q1: Any, q2: Any, right: bool, scalar_first: bool) -> Any:
    """``q2* q1`` (right) or ``q1 q2*`` (left) of the unit quaternions, scalar first: both forms of
    ``quaternion_minus`` compute it alike (``_product``'s grouping makes ``q* q``'s vector part exactly
    zero, and gives a half-turn one sign)."""
    a, b = match_rank(xp, q1, q2)
    p1 = _unit(xp, a, scalar_first)
    w, v = _unit(xp, b, scalar_first)
    inverse = (w, -v)
    relative = _product(inverse, p1, xp) if right else _product(p1, inverse, xp)
    return _join(xp, *relative, True)


def _plus_constants() -> tuple[Any, ...]:
    """The coefficients of ``p_i q_j`` (row ``4 i + j``) in ``p q``, ``p* q`` and ``p q*`` (scalar
    first), and the identity quaternion and 1."""
    (c,) = _hamilton_forms()
    first = [[-x if i // 4 else x for x in row] for i, row in enumerate(c)]
    second = [[-x if i % 4 else x for x in row] for i, row in enumerate(c)]
    return c, first, second, [1.0, 0.0, 0.0, 0.0], 1.0


def _unit_eager(xp: Any, q: Any, identity: Any, one: Any) -> Any:
    """``(..., 4)`` scalar-first quaternions over their norm, the zero quaternion (``|q| < sqrt(tiny)``:
    squared norm below the smallest normal number, as :func:`_unit`) the identity."""
    q, norm, zero = _nonzero_or_identity_eager(xp, q, identity)
    return q / xp.where(zero, one, norm)


def _outer(xp: Any, p: Any, q: Any, forms: Any) -> Any:
    """A bilinear map of two ``(..., 4)`` arrays: their outer product contracted with ``forms``."""
    return xp.matmul((p[..., :, None] * q[..., None, :]).flatten(-2), forms)


@eager_form(of=quaternion_plus)
def quaternion_plus_eager(
    xp: Any, q: Any, delta: Any, *, side: str = "right", scalar_first: bool = True
) -> Any:
    """:func:`quaternion_plus`, eager form: the unit quaternion (:func:`_unit_eager`), the step's
    (``axis_angle_to_quaternion``'s eager form) and their product by constant coefficients. A NaN or
    an infinity in ``q`` makes its norm, and with it the whole unit quaternion, NaN, or one component
    of it, which every component of the product reads; one in ``delta`` makes the whole step NaN."""
    right = check_side("quaternion_plus", side)
    if not scalar_first:
        q = xp.roll(q, 1, -1)
    c, _, _, identity, one = constants(xp, q, _plus_constants)
    unit = _unit_eager(xp, q, identity, one)
    step = _exp_eager(xp, delta)
    out = _outer(xp, unit, step, c) if right else _outer(xp, step, unit, c)
    return out if scalar_first else xp.roll(out, -1, -1)


@eager_form(of=so3_minus)
def so3_minus_eager(
    xp: Any,
    matrix1: Any,
    matrix2: Any,
    *,
    side: str = "right",
    to_quaternion: Conversion = matrix_to_quaternion,
) -> Any:
    """:func:`so3_minus`, eager form: the same relative rotation (one ``matmul``, as the componentwise
    form computes it in eager torch), then ``matrix_to_axis_angle``'s eager form."""
    relative = _relative_matrix(xp, matrix1, matrix2, check_side("so3_minus", side))
    return matrix_to_axis_angle_eager(xp, relative, to_quaternion=to_quaternion)


@eager_form(of=quaternion_minus)
def quaternion_minus_eager(
    xp: Any, q1: Any, q2: Any, *, side: str = "right", scalar_first: bool = True
) -> Any:
    """:func:`quaternion_minus`, eager form: the same unit quaternions and relative rotation (their
    grouping makes ``q* q``'s vector part exactly zero, and a half-turn's sign the componentwise
    form's), then ``quaternion_to_axis_angle``'s eager form (:func:`_log_eager`)."""
    relative = _relative_quaternion(xp, q1, q2, check_side("quaternion_minus", side), scalar_first)
    return _log_eager(xp, relative)[0]
