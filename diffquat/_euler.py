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
    computed_once,
    join_quaternion,
    matrix_to_quaternion,
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
    out = [first_slot, middle, third_slot] if extrinsic else [third_slot, middle, first_slot]
    # Into [-pi, pi): the sums above reach +-2 pi. A shift by a constant, so the gradient is untouched.
    angles = [
        xp.where(x >= math.pi, x - 2.0 * math.pi, xp.where(x < -math.pi, x + 2.0 * math.pi, x)) for x in out
    ]
    result = xp.stack(angles, axis=-1)
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


@op(matrix=(3, 3))
def matrix_to_euler_angles(
    xp: Any,
    matrix: Any,
    convention: str,
    *,
    degrees: bool = False,
    to_quaternion: Conversion = matrix_to_quaternion,
) -> Any:
    """Euler angles of a rotation matrix: shape ``(..., 3, 3)`` to ``(..., 3)``.

    Through ``matrix_to_quaternion``, then exactly as ``quaternion_to_euler_angles`` (scipy's rule, all
    12 axis sequences; third angle 0 at a gimbal lock, no warning, finite gradients)."""
    parse_convention("matrix_to_euler_angles", convention)
    q = to_quaternion(xp, matrix)
    return _quaternion_to_euler(xp, "matrix_to_euler_angles", q, convention, degrees, True)
