"""Euler angles in all 12 axis sequences, intrinsic and extrinsic, over ``xp``: scipy's rules exactly.

A convention is three letters from x, y, z with no letter twice in a row: upper case (``"XYZ"``) is
intrinsic (rotations about the axes of the rotating frame, ``R = R_X(a) R_Y(b) R_Z(c)``), lower case
(``"xyz"``) extrinsic (about the fixed axes, ``R = R_z(c) R_y(b) R_x(a)``), as in
``scipy.spatial.transform.Rotation.from_euler``.

Angles from a rotation follow Bernardes and Viollet, "Quaternion to Euler angles conversion: a direct,
general and computationally efficient method", PLoS ONE 17(11), 2022 (the method scipy uses): every angle
is an ``atan2``, so there is no ``asin``/``acos`` of a clamped value and no loss of digits near the
poles.
"""

from __future__ import annotations

import math
from typing import Any

from ._algebra import hamilton, nonzero_or_identity, safe_norm
from ._core import (
    Conversion,
    cancelling_factor,
    computed_once,
    constants,
    eager_form,
    join_quaternion,
    largest_magnitude,
    nonfinite_by_arithmetic,
    op,
    quaternion_to_matrix,
    split_quaternion,
)

# scipy's threshold: a middle angle within this many radians of its singular value (0 or pi) is a
# gimbal lock. The rotation then depends on one combination of the other two angles only, and the
# third angle is set to 0 (scipy warns; diffquat documents it instead, since values never raise or warn).
GIMBAL_LOCK_TOL = 1e-7


def parse_convention(fname: str, convention: str) -> tuple[list[int], bool]:
    """Axis indices (x = 0, y = 1, z = 2) of a convention, and whether it is extrinsic; ``ValueError``
    naming ``fname`` for anything that is not three axis letters of one case, none twice in a row."""
    if (
        not isinstance(convention, str)
        or len(convention) != 3
        or not (set(convention) <= set("XYZ") or set(convention) <= set("xyz"))
        or convention[0] == convention[1]
        or convention[1] == convention[2]
    ):
        raise ValueError(
            f"{fname}: expected convention to be 3 letters from 'XYZ' (intrinsic) or from 'xyz' "
            f"(extrinsic), no letter twice in a row, e.g. 'XYZ', 'zyx' or 'ZXZ'; got {convention!r}"
        )
    return ["xyz".index(c) for c in convention.lower()], convention.islower()


@op(angles=(3,))
def euler_angles_to_quaternion(
    xp: Any, angles: Any, convention: str, *, degrees: bool = False, scalar_first: bool = True
) -> Any:
    """Unit quaternion of Euler angles.

    Args:
        angles: the three angles, shape ``(..., 3)``, in the order of the letters of ``convention``.
        convention: three letters from ``"XYZ"`` (intrinsic) or ``"xyz"`` (extrinsic), none twice in a
            row: all 12 axis sequences, scipy's rule (``"XYZ"`` gives ``R_X(a) R_Y(b) R_Z(c)``, ``"xyz"``
            gives ``R_z(c) R_y(b) R_x(a)``). Anything else raises ``ValueError``.
        degrees: whether ``angles`` are in degrees (default radians).
        scalar_first: storage order of the result.

    Returns:
        Unit quaternions, shape ``(..., 4)``: the product of the three elementary quaternions, sign not
        standardised (so that the map is smooth), as scipy's ``from_euler(...).as_quat()``.
    """
    axes, extrinsic = parse_convention("euler_angles_to_quaternion", convention)
    if degrees:
        angles = angles * (math.pi / 180.0)
    factors = []
    for n, axis in enumerate(axes):
        half = 0.5 * angles[..., n]
        zero = xp.zeros_like(half)
        vector = [xp.sin(half) if k == axis else zero for k in range(3)]
        factors.append((xp.cos(half), *vector))
    first, second, third = factors[::-1] if extrinsic else factors
    return join_quaternion(xp, *hamilton(hamilton(first, second), third), scalar_first)


@op(angles=(3,))
def euler_angles_to_matrix(
    xp: Any,
    angles: Any,
    convention: str,
    *,
    degrees: bool = False,
    to_matrix: Conversion = quaternion_to_matrix,
) -> Any:
    """Rotation matrix of Euler angles: shape ``(..., 3)`` to ``(..., 3, 3)``.

    ``convention`` and ``degrees`` as in ``euler_angles_to_quaternion`` (scipy's rule: upper case
    intrinsic, lower case extrinsic, all 12 axis sequences)."""
    parse_convention("euler_angles_to_matrix", convention)
    # The quaternion (behind cos and sin) is computed once, not again in each of the nine entries.
    q = computed_once(xp, euler_angles_to_quaternion(xp, angles, convention, degrees=degrees))
    return to_matrix(xp, q)


# ---------------------------------------------------------------------------------------------------
# Eager forms (_core.EAGER_FORMS: eager torch outside graph capture). The quaternion of three
# elementary rotations is trilinear in the three pairs (cos, sin) of the half angles: their outer
# product times a constant (8, 4) coefficient matrix for the convention, a dozen operations in all.
# The matrix takes the registered conversion of that quaternion (the test of the composites' paths).


def _qmul(p: list[float], q: list[float]) -> list[float]:
    """The Hamilton product of two scalar-first quaternions (Python numbers)."""
    pw, px, py, pz = p
    qw, qx, qy, qz = q
    return [
        pw * qw - px * qx - py * qy - pz * qz,
        pw * qx + px * qw + py * qz - pz * qy,
        pw * qy + py * qw + pz * qx - px * qz,
        pw * qz + pz * qw + px * qy - py * qx,
    ]


_EULER_MAKERS: dict[tuple[str, bool], Any] = {}


def _euler_forms(convention: str, scalar_first: bool) -> Any:
    """The maker (for ``_core.constants``, one function object per convention and order) of the
    convention's (8, 4) coefficients: row ``4 i + 2 j + k`` the quaternion (in ``scalar_first``'s order)
    of the product of ``(cos, sin)[i]`` of the first half angle, ``[j]`` of the second, ``[k]`` of the
    third, multiplied in the convention's order."""
    key = (convention, scalar_first)
    if key in _EULER_MAKERS:
        return _EULER_MAKERS[key]
    axes, extrinsic = parse_convention("euler_angles", convention)
    order = [2, 1, 0] if extrinsic else [0, 1, 2]  # the angles in the order of the factors

    def make() -> tuple[list[Any], ...]:
        halves = []
        for a in axes:
            unit = [0.0, 0.0, 0.0, 0.0]
            unit[a + 1] = 1.0
            halves.append(([1.0, 0.0, 0.0, 0.0], unit))
        rows = []
        for i, j, k in ((i, j, k) for i in range(2) for j in range(2) for k in range(2)):
            pick = (i, j, k)
            q = halves[order[0]][pick[order[0]]]
            for n in order[1:]:
                q = _qmul(q, halves[n][pick[n]])
            rows.append(q if scalar_first else q[1:] + q[:1])
        return (rows,)

    _EULER_MAKERS[key] = make
    return make


def _trilinear(xp: Any, pairs: Any) -> Any:
    """The products ``a_i b_j c_k`` of the rows ``a, b, c`` of ``pairs`` ``(..., 3, n)``:
    ``(..., n^3)``, index ``n^2 i + n j + k``."""
    a, b, c = pairs.unbind(-2)
    return ((a[..., :, None] * b[..., None, :]).flatten(-2)[..., :, None] * c[..., None, :]).flatten(-2)


@nonfinite_by_arithmetic
@eager_form(of=euler_angles_to_quaternion)
def euler_angles_to_quaternion_eager(
    xp: Any, angles: Any, convention: str, *, degrees: bool = False, scalar_first: bool = True
) -> Any:
    """:func:`euler_angles_to_quaternion`, eager form: the products of ``(cos, sin)`` of the three
    half angles times the convention's constant (8, 4) coefficients (the same Hamilton products,
    expanded). A non-finite angle makes every component NaN (its cosine and sine reach every column of
    the product: ``NaN * 0``)."""
    (forms,) = constants(xp, angles, _euler_forms(convention, bool(scalar_first)))
    half = angles * (math.pi / 360.0 if degrees else 0.5)
    return xp.matmul(_trilinear(xp, xp.stack([xp.cos(half), xp.sin(half)], -1)), forms)


@nonfinite_by_arithmetic
@eager_form(of=euler_angles_to_matrix)
def euler_angles_to_matrix_eager(
    xp: Any,
    angles: Any,
    convention: str,
    *,
    degrees: bool = False,
    to_matrix: Conversion = quaternion_to_matrix,
) -> Any:
    """:func:`euler_angles_to_matrix`, eager form: :func:`euler_angles_to_quaternion_eager`, then the
    registered conversion ``to_matrix`` (the public ``quaternion_to_matrix``'s eager form), as the
    componentwise composite takes it. A non-finite angle makes every component of the quaternion NaN,
    and the conversion carries that to every entry."""
    parse_convention("euler_angles_to_matrix", convention)
    return to_matrix(xp, euler_angles_to_quaternion_eager(xp, angles, convention, degrees=degrees))


def _quaternion_to_euler(
    xp: Any, fname: str, q: Any, convention: str, degrees: bool, scalar_first: bool
) -> Any:
    axes, extrinsic = parse_convention(fname, convention)
    w, *v = nonzero_or_identity(xp, *split_quaternion(q, scalar_first))
    # Bernardes and Viollet: permute (and for Tait-Bryan sequences, rotate by pi/4 in two planes) the
    # quaternion so that every sequence reads like the proper sequence (i, j, i).
    i, j, k = axes if extrinsic else axes[::-1]
    proper = i == k
    if proper:
        k = 3 - i - j
    sign = (i - j) * (j - k) * (k - i) // 2  # +1 for an even permutation of (x, y, z), -1 for odd
    if proper:
        a, b, c, d = w, v[i], v[j], v[k] * sign
    else:
        a, b, c, d = w - v[j], v[i] + v[k] * sign, v[j] + w, v[k] * sign - v[i]
    ab2, cd2 = a * a + b * b, c * c + d * d
    # safe_norm: the middle angle has a kink at the lock (like |x| at 0); its gradient there is 0.
    middle = 2.0 * xp.atan2(safe_norm(xp, cd2), safe_norm(xp, ab2))
    lock_zero = middle <= GIMBAL_LOCK_TOL
    lock_pi = middle >= math.pi - GIMBAL_LOCK_TOL
    free = ~(lock_zero | lock_pi)
    # atan2(0, 0) has a NaN derivative: each half angle sees (1, 0) where its pair vanishes (there it
    # is not used: at a lock only the other one is).
    tiny = xp.finfo(ab2.dtype).tiny
    ab_ok, cd_ok = ab2 >= tiny, cd2 >= tiny
    half_sum = xp.atan2(xp.where(ab_ok, b, 0.0), xp.where(ab_ok, a, 1.0))
    half_diff = xp.atan2(xp.where(cd_ok, d, 0.0), xp.where(cd_ok, c, 1.0))
    # At a lock the whole rotation about the (aligned) first and third axes goes into the first angle,
    # and the third is 0 (scipy's choice).
    locked = xp.where(lock_zero, 2.0 * half_sum, (-2.0 if extrinsic else 2.0) * half_diff)
    zero = xp.zeros_like(half_sum)
    first_slot = xp.where(free, half_sum - half_diff, locked if extrinsic else zero)
    third_slot = xp.where(free, half_sum + half_diff, zero if extrinsic else locked)
    if not proper:
        third_slot = third_slot * sign
        middle = middle - 0.5 * math.pi
    # Into [-pi, pi): the sums above reach +-2 pi. A shift by a constant, so the gradient is untouched.
    # The middle angle is in its documented range already (a half-turn's pi is not -pi).
    first_slot, third_slot = (
        xp.where(x >= math.pi, x - 2.0 * math.pi, xp.where(x < -math.pi, x + 2.0 * math.pi, x))
        for x in (first_slot, third_slot)
    )
    out = [first_slot, middle, third_slot] if extrinsic else [third_slot, middle, first_slot]
    result = xp.stack(out, axis=-1)
    return result * (180.0 / math.pi) if degrees else result


@op(q=(4,))
def quaternion_to_euler_angles(
    xp: Any, q: Any, convention: str, *, degrees: bool = False, scalar_first: bool = True
) -> Any:
    """Euler angles of a quaternion of any non-zero norm (the zero quaternion is the identity).

    Args:
        q: quaternions, shape ``(..., 4)``; ``q`` and ``-q`` give the same angles.
        convention: as in ``euler_angles_to_quaternion`` (scipy's rule, all 12 axis sequences).
        degrees: whether to return degrees (default radians).
        scalar_first: storage order of ``q``.

    Returns:
        Angles, shape ``(..., 3)``, in the order of the letters of ``convention``, each in [-pi, pi);
        the middle angle is in [0, pi] for proper sequences (e.g. ``"ZXZ"``) and in [-pi/2, pi/2] for
        Tait-Bryan ones (e.g. ``"XYZ"``). At a gimbal lock (middle angle within 1e-7 rad of 0 or pi,
        resp. of +-pi/2) the third angle is 0 and the first carries the rotation about the aligned axes,
        as scipy; no warning, no error, and finite gradients (the angles jump there, as they must).
    """
    return _quaternion_to_euler(xp, "quaternion_to_euler_angles", q, convention, degrees, scalar_first)


_Q2E_MAKERS: dict[tuple[str, bool], Any] = {}


def _q2e_forms(convention: str, scalar_first: bool) -> Any:
    """The maker (one function object per convention and order, for ``_core.constants``) of the
    constants of :func:`quaternion_to_euler_angles_eager`: the identity quaternion in the storage
    order; the (4, 4) map of the components to Bernardes and Viollet's ``(a, c, b, d)``; the (4, 2) sums
    ``(a^2 + b^2, c^2 + d^2)``; the (2, 2) map of the half angles to ``(sum - diff, sum + diff)``; the
    lock's factors ``(2, -+2)``; the slots' signs; the (3, 3) placement of ``(first slot, third slot,
    middle)`` and its bias (``-pi/2`` on the middle angle of a Tait-Bryan sequence); 0 and 1."""
    key = (convention, scalar_first)
    if key in _Q2E_MAKERS:
        return _Q2E_MAKERS[key]
    axes, extrinsic = parse_convention("quaternion_to_euler_angles", convention)
    i, j, k = axes if extrinsic else axes[::-1]
    proper = i == k
    if proper:
        k = 3 - i - j
    sign = (i - j) * (j - k) * (k - i) // 2
    w_at, v_at = (0, [1, 2, 3]) if scalar_first else (3, [0, 1, 2])

    def make() -> tuple[list[Any], ...]:
        identity = [0.0] * 4
        identity[w_at] = 1.0
        terms: list[dict[int, float]]  # a, c, b, d as linear forms in the stored components
        if proper:
            terms = [{w_at: 1.0}, {v_at[j]: 1.0}, {v_at[i]: 1.0}, {v_at[k]: float(sign)}]
        else:
            terms = [
                {w_at: 1.0, v_at[j]: -1.0},
                {v_at[j]: 1.0, w_at: 1.0},
                {v_at[i]: 1.0, v_at[k]: float(sign)},
                {v_at[k]: float(sign), v_at[i]: -1.0},
            ]
        forms = [[terms[col].get(row, 0.0) for col in range(4)] for row in range(4)]
        pairs = [[1.0, 0.0], [0.0, 1.0], [1.0, 0.0], [0.0, 1.0]]  # (a, c, b, d)^2 -> (ab2, cd2)
        sums = [[1.0, 1.0], [-1.0, 1.0]]  # (half_sum, half_diff) -> (sum - diff, sum + diff)
        lock = [2.0, -2.0 if extrinsic else 2.0]
        slot_sign = [1.0, 1.0 if proper else float(sign)]
        # (first slot, third slot, middle) -> the angles in the convention's order
        where_to = [0, 2, 1] if extrinsic else [2, 0, 1]
        place = [[1.0 if where_to[r] == c else 0.0 for c in range(3)] for r in range(3)]
        bias = [0.0, 0.0 if proper else -0.5 * math.pi, 0.0]
        return identity, forms, pairs, sums, lock, slot_sign, place, bias, [0.0], [1.0]

    _Q2E_MAKERS[key] = make
    return make


@eager_form(of=quaternion_to_euler_angles)
def quaternion_to_euler_angles_eager(
    xp: Any, q: Any, convention: str, *, degrees: bool = False, scalar_first: bool = True
) -> Any:
    """:func:`quaternion_to_euler_angles`, eager form: the same method and selections, each step over
    a trailing axis of two (the pairs ``(a, b)`` and ``(c, d)``, the two half angles, the two free
    slots) with constant maps for the convention's permutation (:func:`_q2e_forms`)."""
    identity, forms, pairs, sums, lock_factors, slot_sign, place, bias, zero, one = constants(
        xp, q, _q2e_forms(convention, bool(scalar_first))
    )
    tiny = xp.finfo(q.dtype).tiny
    n2 = (q * q).sum(-1, keepdim=True)
    acbd = xp.matmul(xp.where(n2 < tiny, identity, q), forms)
    norms2 = xp.matmul(acbd * acbd, pairs)  # (a^2 + b^2, c^2 + d^2)
    positive = norms2 > 0
    norms = xp.where(positive, xp.sqrt(xp.where(positive, norms2, one)), zero)  # _algebra.safe_norm
    ab, cd = norms.unbind(-1)
    middle = 2.0 * xp.atan2(cd, ab)
    lock_zero = middle <= GIMBAL_LOCK_TOL
    free = ~(lock_zero | (middle >= math.pi - GIMBAL_LOCK_TOL))
    ok = norms2 >= tiny
    halves = xp.atan2(xp.where(ok, acbd[..., 2:], zero), xp.where(ok, acbd[..., :2], one))
    twice = halves * lock_factors
    locked = xp.where(lock_zero, twice[..., 0], twice[..., 1])[..., None]
    alternative = xp.nn.functional.pad(locked, (0, 1) if convention.islower() else (1, 0))
    slots = xp.where(free[..., None], xp.matmul(halves, sums), alternative) * slot_sign
    # into [-pi, pi), as the componentwise form (a shift by a constant: the gradient is untouched)
    wrapped = xp.where(slots < -math.pi, slots + 2.0 * math.pi, slots)
    slots = xp.where(slots >= math.pi, slots - 2.0 * math.pi, wrapped)
    result = xp.matmul(xp.cat([slots, middle[..., None]], -1), place) + bias
    return result * (180.0 / math.pi) if degrees else result


def _degenerate(xp: Any, y: Any, x: Any) -> Any:
    """Where ``atan2(y, x)`` has no finite derivative: ``x^2 + y^2`` below the smallest normal number
    (its derivative divides by that). For a rotation matrix no pair of entries read below gets there
    where it is used; a matrix far off SO(3) (a zero column) can."""
    return y * y + x * x < xp.finfo(x.dtype).tiny


def _wrap(xp: Any, x: Any) -> Any:
    """An angle from ``atan2`` (in [-pi, pi]) into [-pi, pi): +pi (and, in float32, values that round to
    it) become -pi. A shift by a constant, so the derivative is untouched."""
    return xp.where(x >= math.pi, x - 2.0 * math.pi, x)


def _entries(xp: Any, matrix: Any) -> tuple[list[Any], Any]:
    """The nine entries of ``(..., 3, 3)`` matrices, row-major, each of shape ``(...)``, scaled by
    :func:`_power_of_two`, and whether all nine are finite.

    Where the namespace has ``unstack`` (jax; numpy >= 2.1), rows and then entries are unstacked, as
    in ``_core._Unstacked``: reverse mode transposes that into stacks, where nine indexed entries
    become nine zero-padded copies of the matrix, and XLA does not see through the copy below. torch's
    entries would be views with a stride of 9, slow for its elementwise operations (atan2 the most):
    one stack copies them into contiguous rows, taken apart by iteration (``unbind``), whose reverse
    mode is again one stack (docs/performance.md, Formula shapes)."""
    unstack = getattr(xp, "unstack", None)
    if unstack is not None:
        largest = xp.amax(xp.abs(matrix), axis=(-2, -1))
        matrix = matrix * _power_of_two(xp, largest)[..., None, None]
        entries = [e for row in unstack(matrix, axis=-2) for e in unstack(row, axis=-1)]
    else:
        # Indexing, not moveaxis: torch.func.vmap has no batching rule for the moveaxis alias.
        flat = xp.reshape(matrix, (*matrix.shape[:-2], 9))
        rows = xp.stack([flat[..., i] for i in range(9)], axis=0)
        largest = xp.amax(xp.abs(rows), axis=0)
        entries = list(rows * _power_of_two(xp, largest))
    # max |entry| is infinite or NaN exactly where an entry is; isfinite raises no warning in numpy.
    return entries, xp.isfinite(largest)


def _power_of_two(xp: Any, largest: Any) -> Any:
    """A power of two that brings the largest entry of a matrix, ``largest``, into [2^-h, 2^h], with
    h = log2(1 / tiny) / 4 rounded down (31 in float32, 255 in float64); 1 where it is there already.

    The angles are read off ratios of entries, so a positive factor changes none of them, but squares
    of entries (the middle angle's norm, the lock rule, atan2's own derivative) overflow above about
    2^63 (float32: 1.8e19), and the lock rule, which compares a square with 1e-14 (2^-46.5) times a
    square, loses its digits below about 2^-40; a matrix whose largest entry is in [2^-h, 2^h] has
    room for both. A power of two is exact, and it is built from comparisons and constants only, so
    it carries no derivative: the angles' derivative is the one of the scaled matrix, times the
    factor, which is exactly the derivative of the unscaled one. Five ranges: 2^(+-2h) and 2^(+-4h)
    cover every finite value, the smallest subnormal included. A NaN or an infinity gives NaN angles
    anyway."""
    h = int(-math.log2(float(xp.finfo(largest.dtype).tiny))) // 4
    factor = xp.ones_like(largest)
    factor = xp.where(largest < 2.0**-h, 2.0 ** (2 * h), factor)
    factor = xp.where(largest < 2.0 ** (-3 * h), 2.0 ** (4 * h), factor)
    factor = xp.where(largest > 2.0**h, 2.0 ** (-2 * h), factor)
    factor = xp.where(largest > 2.0 ** (3 * h), 2.0 ** (-4 * h), factor)
    # The zero matrix has nothing to scale, and its derivatives (of angles read off zeros) must not be
    # multiplied by 2^(4h).
    return xp.where(largest > 0.0, factor, 1.0)


def _signed(sign: int, x: Any) -> Any:
    return x if sign > 0 else -x


@op(matrix=(3, 3))
def matrix_to_euler_angles(xp: Any, matrix: Any, convention: str, *, degrees: bool = False) -> Any:
    """Euler angles of a rotation matrix: shape ``(..., 3, 3)`` to ``(..., 3)``.

    Args:
        matrix: rotation matrices, shape ``(..., 3, 3)``, column-vector convention.
        convention: as in ``euler_angles_to_quaternion`` (scipy's rule, all 12 axis sequences).
        degrees: whether to return degrees (default radians).

    Returns:
        Angles, shape ``(..., 3)``, in the order of the letters of ``convention``: the first and third
        in [-pi, pi), the middle one in [0, pi] for proper sequences (e.g. ``"ZXZ"``) and in
        [-pi/2, pi/2] for Tait-Bryan ones (e.g. ``"XYZ"``). At a gimbal lock (middle angle within
        1e-7 rad of 0 or pi, resp. of +-pi/2) the third angle is 0 and the first carries the rotation
        about the aligned axes, as scipy; no warning, no error, and finite gradients (the angles jump
        there, as they must). For a rotation matrix, the angles of
        ``quaternion_to_euler_angles(matrix_to_quaternion(matrix))``, to rounding (which the route
        through the quaternion amplifies near a lock).

    Method: the angles are read off the entries (no quaternion in between), one ``atan2`` each. Write
    the convention intrinsically, ``R = R_p(u) R_q(v) R_r(w)`` (an extrinsic convention is the
    intrinsic one of its letters reversed, its angles reversed: ``w`` is its first angle). The middle
    angle ``v`` is read off row ``p``. Of ``u`` and ``w``, the one that is 0 at a lock (the
    convention's third angle) is read off directly: ``w`` off row ``p``, resp. ``u`` off column ``r``
    (column ``p`` for proper sequences). The other is read off what is left once that rotation is
    undone: column ``q`` of ``matrix @ R_r(-w)``, resp. row ``q`` of ``R_p(-u) @ matrix``, entries
    of size 1. In float32, 0.04 rad and more from a lock, the angles are within 1.3 ulp of pi
    (3.1e-7 rad) of those of the same matrix in float64; the textbook formula, each angle off its own
    two entries, is within 1.05 ulp (its atan2 alone), and the route through the quaternion erred by
    up to 20 ulp (4.7e-6 rad). The undoing costs at most (1 + sqrt 2) 2^-24 rad of rounding (sums of
    two products), and is what lets a matrix near a lock round-trip (below).

    Matrices off SO(3) get the angles of that reading. So any positive multiple of a rotation gives the
    rotation's angles (a matrix whose largest entry is far from 1, beyond 2^+-31 in float32, is first
    scaled by a power of two, exactly), and the angles of a matrix that is off SO(3) by rounding
    errors rebuild it to within a few of those errors, at and near a gimbal lock too: the two angles
    read off entries of the size of the distance to the lock are each uncertain by rounding / distance
    there, but the second one follows the first (reading both directly, a float32 product of rotations
    1e-6 rad from a lock came back up to 2 away). Any finite matrix gives finite angles (an angle read
    off two entries that are both 0 is 0) and finite gradients, of size 1 / (largest entry), wherever
    that is a finite number; a NaN or an infinite entry gives NaN angles.
    """
    axes, extrinsic = parse_convention("matrix_to_euler_angles", convention)
    # Intrinsically R = R_i(u) R_j(v) R_k(w); extrinsic angles are (w, v, u) of the reversed letters.
    i, j, k = axes[::-1] if extrinsic else axes
    proper = i == k
    if proper:
        k = 3 - i - j  # the axis not in the sequence
    sign = (i - j) * (j - k) * (k - i) // 2  # +1 for an even permutation of (x, y, z), -1 for odd
    entries, finite = _entries(xp, matrix)

    def m(row: int, col: int) -> Any:
        return entries[3 * row + col]

    # Row i of R is row i of R_j(v) R_k(w): it fixes v and w. The (sin w, cos w) pair in it, (m_ij, m_ik)
    # for proper sequences and (m_ii, m_ij) for Tait-Bryan ones, is scaled by n = |sin v|, resp.
    # |cos v|, the distance from the lock; the row's third entry is cos v, resp. sin v. Column k
    # (proper: i) of R_i(u) R_j(v) holds (sin u, cos u) scaled by n likewise.
    if proper:
        w_pair, axis_entry = (m(i, j), _signed(sign, m(i, k))), m(i, i)
        u_pair = (m(j, i), _signed(-sign, m(k, i)))
    else:
        w_pair, axis_entry = (_signed(-sign, m(i, j)), m(i, i)), _signed(sign, m(i, k))
        u_pair = (_signed(-sign, m(j, k)), m(k, k))
    n2 = w_pair[0] * w_pair[0] + w_pair[1] * w_pair[1]
    tiny = xp.finfo(n2.dtype).tiny
    # The middle angle has a kink at the lock, like |x| at 0. n = sqrt(n2 + tiny) keeps the derivative
    # finite at n2 = 0, where it is 0 (dn/dm = m / n, m = 0 there), and all higher ones, with no where
    # (which costs torch 20x a multiplication); it is sqrt(n2) to rounding for n2 > tiny / eps (1e-31
    # in float32), deep inside the lock. sqrt(tiny) (2^-63, 2^-511) is taken off again, so that the
    # middle angle of the identity is exactly 0 (proper), resp. +-pi/2 at an exact lock (Tait-Bryan).
    n = xp.sqrt(n2 + tiny) - math.sqrt(tiny)
    # A zero row (a matrix far off SO(3)) is read as (0, 1): atan2(0, 0) has no derivative.
    if proper:
        middle = xp.atan2(n, xp.where(_degenerate(xp, n, axis_entry), 1.0, axis_entry))
    else:
        middle = xp.atan2(axis_entry, xp.where(_degenerate(xp, axis_entry, n), 1.0, n))
    # scipy's rule on the angle from the lock, atan2(n, |axis_entry|) <= tol, without evaluating it:
    # n^2 - tan(tol)^2 axis_entry^2 <= tiny. Exact where that atan2 would round; "tiny" also counts as
    # locked a row whose pair is too small to take an atan2 of (a matrix far off SO(3)). A difference
    # of two terms compared with a constant: the eager form computes it bit for bit (one rounding).
    lock = n2 - math.tan(GIMBAL_LOCK_TOL) ** 2 * (axis_entry * axis_entry) <= tiny
    # The angle that is 0 at a lock (scipy's rule: the convention's third), read off directly: w off row
    # i, or extrinsically u off its column. Selected before the atan2: at an exact lock the pair is
    # (0, 0), where atan2 has no derivative; at a lock it is (0, 1), angle 0 with a zero gradient.
    if extrinsic:
        zeroed_pair, zero = u_pair, lock | _degenerate(xp, *u_pair)
    else:
        zeroed_pair, zero = w_pair, lock  # w_pair is not degenerate off the lock
    zy, zx = xp.where(zero, 0.0, zeroed_pair[0]), xp.where(zero, 1.0, zeroed_pair[1])
    zeroed = xp.atan2(zy, zx)
    # The other angle, from the entries of size 1 left once the zeroed rotation is undone, so that it
    # absorbs the uncertainty of the zeroed one near a lock (see the docstring), and at a lock (zeroed
    # = 0) carries the rotation about the aligned axes. Intrinsically u, off column j of
    # M R_k(-w) = R_i(u) R_j(v): R_i(u) e_j = (cos u) e_j + sign (sin u) e_k. Extrinsically w, off row j
    # of R_i(-u) M = R_j(v) R_k(w): e_j^T R_k(w), which is (cos w, -sign sin w) at (j, k) for proper
    # sequences (k = i), (sign sin w, cos w) at (i, j) for Tait-Bryan ones. Each as y0 cz + y1 sz over
    # x0 cz + x1 sz:
    if extrinsic and proper:
        y0, y1, x0, x1 = _signed(-sign, m(j, k)), -m(k, k), m(j, j), _signed(sign, m(k, j))
    elif extrinsic:
        y0, y1, x0, x1 = _signed(sign, m(j, i)), m(k, i), m(j, j), _signed(sign, m(k, j))
    elif proper:
        y0, y1, x0, x1 = _signed(sign, m(k, j)), -m(k, k), m(j, j), _signed(-sign, m(j, k))
    else:
        y0, y1, x0, x1 = _signed(sign, m(k, j)), m(k, i), m(j, j), _signed(sign, m(j, i))
    y, x = y0 * zx + y1 * zy, x0 * zx + x1 * zy
    carried = xp.atan2(y, xp.where(_degenerate(xp, y, x), 1.0, x))
    first, third = _wrap(xp, carried), _wrap(xp, zeroed)  # the middle angle needs no wrapping
    result = xp.stack([first, middle, third], axis=-1)
    # The angles read eight of the nine entries, and atan2 of an infinite one is finite: a matrix with a
    # NaN or an infinity anywhere gives NaN angles, decided here (a selection: the derivative of a
    # finite matrix is unchanged).
    result = xp.where(finite[..., None], result, math.nan)
    return result * (180.0 / math.pi) if degrees else result


_M2E_MAKERS: dict[tuple[str, float], Any] = {}


def _m2e_forms(convention: str, tiny: float) -> Any:
    """The maker (one function object per convention and dtype's ``tiny``, for ``_core.constants``)
    of the constants of :func:`matrix_to_euler_angles_eager`:

    - ``pick`` (9, K): the signed entries ``E`` of :func:`matrix_to_euler_angles` as columns: the pair
      of the angle that is 0 at a lock, ``(zy, zx)`` (``w_pair``, or extrinsically ``u_pair``); the
      carried angle's ``(y1, y0, x1, x0)``; the axis entry; extrinsically ``w_pair`` again;
    - ``squares`` (K, 2 or 3): the squares of those to ``(n2, tan(tol)^2 axis^2)`` (and ``|u_pair|^2``);
    - ``spread`` (2 or 3, 3 or 5) and its ``bias``: those to ``(d, d, n2 + tiny)``, ``d = n2 -
      tan(tol)^2 axis^2`` (extrinsically ``(d, d, u2, u2, n2 + tiny)``);
    - the zeroed pair at a lock ``(0, 1)``; the wrap's limits ``(pi, inf, pi)``; ``2 pi``; 1;
      ``sqrt(tiny)``.

    Every column of ``pick``, ``squares`` and ``spread`` has at most two non-zero coefficients, +-1
    where there are two (or one coefficient and the bias): each entry of the products rounds once, in
    any order of summation, as the componentwise form's operations do (BLAS sums in an order that
    depends on the batch's layout)."""
    key = (convention, tiny)
    if key in _M2E_MAKERS:
        return _M2E_MAKERS[key]
    axes, extrinsic = parse_convention("matrix_to_euler_angles", convention)
    i, j, k = axes[::-1] if extrinsic else axes
    proper = i == k
    if proper:
        k = 3 - i - j
    sign = (i - j) * (j - k) * (k - i) // 2
    # (row, column, sign) of each entry, as in matrix_to_euler_angles
    if proper:
        w_pair, axis = [(i, j, 1), (i, k, sign)], (i, i, 1)
        u_pair = [(j, i, 1), (k, i, -sign)]
    else:
        w_pair, axis = [(i, j, -sign), (i, i, 1)], (i, k, sign)
        u_pair = [(j, k, -sign), (k, k, 1)]
    if extrinsic and proper:
        y0, y1, x0, x1 = (j, k, -sign), (k, k, -1), (j, j, 1), (k, j, sign)
    elif extrinsic:
        y0, y1, x0, x1 = (j, i, sign), (k, i, 1), (j, j, 1), (k, j, sign)
    elif proper:
        y0, y1, x0, x1 = (k, j, sign), (k, k, -1), (j, j, 1), (j, k, -sign)
    else:
        y0, y1, x0, x1 = (k, j, sign), (k, i, 1), (j, j, 1), (j, i, sign)
    columns = [*(u_pair if extrinsic else w_pair), y1, y0, x1, x0, axis, *(w_pair if extrinsic else [])]

    def make() -> tuple[Any, ...]:
        pick = [[0.0] * len(columns) for _ in range(9)]
        for col, (r, c, s) in enumerate(columns):
            pick[3 * r + c][col] = float(s)
        squares = [[0.0] * (3 if extrinsic else 2) for _ in columns]
        for a in [7, 8] if extrinsic else [0, 1]:
            squares[a][0] = 1.0
        squares[6][1] = math.tan(GIMBAL_LOCK_TOL) ** 2
        if extrinsic:
            squares[0][2] = squares[1][2] = 1.0
        if extrinsic:
            spread = [[1.0, 1.0, 0.0, 0.0, 1.0], [-1.0, -1.0, 0.0, 0.0, 0.0], [0.0, 0.0, 1.0, 1.0, 0.0]]
        else:
            spread = [[1.0, 1.0, 1.0], [-1.0, -1.0, 0.0]]
        bias = [0.0] * (len(spread[0]) - 1) + [tiny]
        limits = [math.pi, math.inf, math.pi]
        return pick, squares, spread, bias, [0.0, 1.0], limits, 2.0 * math.pi, 1.0, math.sqrt(tiny)

    _M2E_MAKERS[key] = make
    return make


@eager_form(of=matrix_to_euler_angles)
@nonfinite_by_arithmetic
def matrix_to_euler_angles_eager(xp: Any, matrix: Any, convention: str, *, degrees: bool = False) -> Any:
    """:func:`matrix_to_euler_angles`, eager form: the same reading, entries, selections and roundings,
    each step over a trailing axis, with constant maps for the convention (:func:`_m2e_forms`):
    32 operations for one batch dimension where the componentwise form takes 87.

    - The matrix is divided by the power of two above its largest entry, a constant of
      differentiation (``_core.cancelling_factor``): the angles do not depend on it, and their
      derivative is the scaled matrix's divided by it, exactly. A power of two, like the componentwise
      form's scale (which is 1 for largest entries in [2^-31, 2^31]), so that every product, sum,
      comparison and ``atan2`` below scales exactly: the values and the lock and other selections are
      the componentwise form's (but for quantities within a few ``tiny`` of a threshold, deep inside a
      lock or far off SO(3)). Where a degenerate pair is read as ``(0, 1)`` (a matrix far off SO(3):
      a zero row or column), the gradient is the componentwise form's times the ratio of the two
      scales. Dividing by the largest entry itself would save two operations, but rounds each entry:
      the angles moved by up to 1 ulp, and the lock's threshold with them.
    - ``E``, the signed entries read, are one product with a constant matrix, which also carries a
      NaN or an infinity anywhere in the matrix (``NaN * 0``) to every entry: the non-finite rule is
      the arithmetic's. Their squares give ``n2`` and ``tan(tol)^2 axis^2``, and those the lock's
      difference and ``n2 + tiny`` (two more products).
    - The zeroed angle's pair is selected at the lock, the carried angle's pair is its product with the
      entries, and the three pairs ``(y, x)`` (first, middle, third angle) take one degenerate rule,
      one ``atan2`` (on contiguous rows: torch's vectorised kernel) and one wrap.

    The lock and every other selection read the componentwise form's roundings: each column of the
    constant products has one non-zero coefficient, or two of +-1, so it rounds once in any order of
    summation (BLAS sums in an order that depends on the batch's layout); the carried pair and the
    degenerate rule's squares are elementwise products summed over two."""
    axes, extrinsic = parse_convention("matrix_to_euler_angles", convention)
    proper = axes[0] == axes[2]
    tiny = float(xp.finfo(matrix.dtype).tiny)
    pick, squares, spread, bias, locked, limits, two_pi, one, root_tiny = constants(
        xp, matrix, _m2e_forms(convention, tiny)
    )
    flat = matrix.reshape(-1, 9)
    big = largest_magnitude(xp, cancelling_factor(xp, flat))
    # big / mantissa: the power of two above big, exactly (frexp: big = mantissa 2^exponent, mantissa
    # in [1/2, 1)), subnormal ones included. 0 / 0 for the zero matrix, whose scale is 1 (its gradient
    # is not to be multiplied by 1 / tiny), and for a NaN or an infinity, which the product below
    # carries to every entry anyway; the largest finite numbers' 2^128 (2^1024) overflows to the
    # largest finite number, a scale that rounds.
    mantissa, _ = xp.frexp(big)
    e = xp.mm(flat / xp.nan_to_num(big / mantissa, nan=1.0), pick)
    sums = xp.addmm(bias, xp.mm(e * e, squares), spread)
    if extrinsic:
        lock, u2, n2 = sums.split([2, 2, 1], -1)
        zero = (lock <= tiny) | (u2 < tiny)
    else:
        lock, n2 = sums.split([2, 1], -1)
        zero = lock <= tiny
    n = n2.sqrt() - root_tiny
    raw, entries, axis, *_ = e.split([2, 4, 1, e.shape[-1] - 7], -1)
    z = xp.where(zero, locked, raw)
    carried = (entries.view(-1, 2, 2) * z[:, None, :]).sum(-1)
    middle = xp.cat([n, axis] if proper else [axis, n], -1)
    pairs = xp.stack([carried, middle, z], -1)
    degenerate = (pairs * pairs).sum(1) < tiny
    # contiguous: torch's atan2 takes its vectorised kernel (within 1.4e-7 in float32) only there; on
    # rows of three with a stride it takes the scalar one (within 2.3e-7)
    y, x = pairs.unbind(1)
    y, x = y.contiguous(), x.contiguous()
    angles = xp.atan2(y, xp.where(degenerate, one, x))
    angles = xp.addcmul(angles, angles >= limits, two_pi, value=-1.0)
    if matrix.ndim != 3:
        angles = angles.view(*matrix.shape[:-2], 3)
    return angles * (180.0 / math.pi) if degrees else angles
