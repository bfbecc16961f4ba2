"""Rotations in time, over ``xp``: angular velocity and acceleration of a quaternion trajectory, the
quaternion derivative of a rate, exact integration of a rate, rates from samples, Shoemake's SQUAD,
and uniform cumulative B-splines on SO(3) and SE(3) with their exact body rates.

Conventions, written once (each docstring repeats the part its function needs):

- Hamilton quaternions, scalar first by default (``scalar_first=False``: (x, y, z, w)), as everywhere
  in diffquat; a rotation matrix acts on column vectors (``R(q) v = q v q*``).
- Body-frame angular velocity ``w_b = 2 vec(q^-1 q')`` (``hat(w_b) = R^T R'``, what a gyroscope
  strapped to the body reads; scipy's ``RotationSpline`` rates, basalt's and Sophus' splines), and
  space-frame ``w_s = 2 vec(q' q^-1) = R w_b`` (``hat(w_s) = R' R^T``). ``frame="body"`` is the
  default, ``frame="space"`` the other; their rates are related by ``w_s = R w_b`` and, since
  ``R' w_b = R (w_b x w_b) = 0``, also ``w_s' = R w_b'``.
- Twists of SE(3) are translation first, ``(v, w)``, as in ``diffquat._se3``: the body twist of a pose
  trajectory ``T(u)`` is ``vee(T^-1 dT/du)``, ``v = R^T dp/du`` and ``w = w_b``.
- Time: every function here takes times already made relative and normalised (a step ``dt``, a knot
  parameter ``t`` = knot index + fraction, a spline parameter ``u`` = segment index + fraction). Compute
  them from absolute timestamps in float64 or in integers (nanoseconds) *before* casting to the compute
  dtype: float32 cannot tell apart two instants 100 s apart at a Unix timestamp (its spacing there is
  128 s), and even in float64 the fraction of a knot interval loses the digits the timestamp holds.
  Rates with respect to a normalised spline parameter ``u = (t - t0) / h`` convert to physical time
  as ``w = w_u / h`` and ``w' = w_u' / h^2``.

Sign of quaternions: the logarithms taken here are shortest-arc (``quaternion_to_axis_angle``'s
canonical sign), so ``q`` and ``-q`` give the same rates from samples and the same splines. Consecutive
samples, knots and control points must be less than a half-turn apart (the shortest arc between them
is then unique); at exactly a half-turn the logarithm takes the canonical sign and jumps there, with a
finite gradient, as ``so3_log`` does.
"""

from __future__ import annotations

import functools
import math
import numbers
from collections.abc import Callable
from fractions import Fraction
from typing import Any

from ._algebra import (
    _hamilton_forms,
    axis_angle_to_matrix,
    axis_angle_to_matrix_eager,
    hamilton,
    match_rank,
    matrix_to_axis_angle,
    matrix_to_axis_angle_eager,
    quaternion_invert,
    quaternion_invert_eager,
    quaternion_slerp,
    quaternion_slerp_eager,
    series_threshold,
)
from ._core import (
    Conversion,
    cancelling_factor,
    constants,
    eager_form,
    join_quaternion,
    matrix_to_quaternion,
    normalize_quaternion,
    op,
    small_matmul,
    split_quaternion,
    unit_quaternion_to_matrix,
    wxyz_to_xyzw,
    xyzw_to_wxyz,
)
from ._lie import (
    _join,
    _outer,
    _plus_constants,
    _product,
    _unit,
    _unit_eager,
    quaternion_minus,
    quaternion_minus_eager,
    quaternion_plus,
    quaternion_plus_eager,
)
from ._se3 import (
    _bottom_row,
    _with_bottom,
    se3_compose,
    se3_compose_eager,
    se3_exp,
    se3_exp_eager,
    se3_minus,
    se3_minus_eager,
)

FRAMES = ("body", "space")


def check_frame(fname: str, frame: str) -> bool:
    """Whether ``frame`` is ``"body"``; ``ValueError`` naming ``fname`` unless it is ``"body"`` or
    ``"space"``. A Python check of a static option: it traces."""
    if frame not in FRAMES:
        raise ValueError(f"{fname}: expected frame to be 'body' or 'space', got {frame!r}")
    return frame == "body"


# ---------------------------------------------------------------------------------------------------
# Rates of a quaternion trajectory


def _relative(xp: Any, q: Any, p: Any, body: bool, scalar_first: bool) -> tuple[Any, Any, Any, Any]:
    """Components (w, x, y, z) of ``q^-1 p`` (body) or ``p q^-1`` (space), ``q^-1 = q* / |q|^2``
    (``quaternion_invert``: scaled by the largest component, the zero quaternion giving 0)."""
    inv = split_quaternion(quaternion_invert(xp, q, scalar_first=scalar_first), scalar_first)
    other = split_quaternion(p, scalar_first)
    return hamilton(inv, other) if body else hamilton(other, inv)


@op(q=(4,), q_dot=(4,))
def angular_velocity(xp: Any, q: Any, q_dot: Any, *, frame: str = "body", scalar_first: bool = True) -> Any:
    """The angular velocity of a quaternion trajectory from its derivative: ``w_b = 2 vec(q^-1 q')``
    (``frame="body"``, ``hat(w_b) = R^T R'``) or ``w_s = 2 vec(q' q^-1) = R w_b`` (``frame="space"``).

    Why ``q^-1 = q* / |q|^2`` and not ``q*``: the rotation of ``q`` is that of ``n = q / |q|``, and
    ``n* n' = q* q' / |q|^2 - (q . q') / |q|^2``, whose second term is real; so ``2 vec(q* q') / |q|^2``
    is exactly the angular velocity of the rotation ``R(q(t))`` for every non-zero norm, whatever the
    radial part of ``q'`` (which changes the norm, not the rotation). For a unit ``q`` it is the
    textbook ``2 vec(q* q')``.

    Args:
        q: quaternions, shape ``(..., 4)``, any non-zero norm; the zero quaternion gives the zero
            vector, with a finite gradient.
        q_dot: their time derivatives, shape ``(..., 4)``, any (the radial part is ignored); the batch
            shapes broadcast.
        frame: ``"body"`` (the default) or ``"space"``; anything else raises ``ValueError``.
        scalar_first: storage order of ``q`` and ``q_dot``.

    Returns:
        Shape ``(..., 3)``, in radians per unit of time of ``q_dot``. ``angular_velocity(q,
        quaternion_derivative(q, w))`` is ``w`` for every non-zero ``q``.
    """
    body = check_frame("angular_velocity", frame)
    q, q_dot = match_rank(xp, q, q_dot)
    _, x, y, z = _relative(xp, q, q_dot, body, scalar_first)
    return 2.0 * xp.stack([x, y, z], axis=-1)


@op(q=(4,), omega=(3,))
def quaternion_derivative(
    xp: Any, q: Any, omega: Any, *, frame: str = "body", scalar_first: bool = True
) -> Any:
    """The time derivative of a quaternion turning at an angular velocity: ``q' = q (0, w_b) / 2``
    (``frame="body"``) or ``q' = (0, w_s) q / 2`` (``frame="space"``).

    Args:
        q: quaternions, shape ``(..., 4)``, any norm; ``q`` is used as it is (not normalised), so the
            derivative is the one that keeps ``|q|`` constant (``q . q' = 0``) and turns ``R(q)`` at
            ``w``. The zero quaternion gives 0.
        omega: angular velocities, shape ``(..., 3)``; the batch shapes broadcast.
        frame: ``"body"`` (the default) or ``"space"``; anything else raises ``ValueError``.
        scalar_first: storage order of ``q`` and of the result.

    Returns:
        Shape ``(..., 4)``: the inverse of ``angular_velocity`` in its second argument for every
        non-zero ``q`` (up to the radial part, which this one leaves out).
    """
    body = check_frame("quaternion_derivative", frame)
    q, omega = match_rank(xp, q, omega)
    half = 0.5 * omega
    pure = (xp.zeros_like(half[..., 0]), half[..., 0], half[..., 1], half[..., 2])
    parts = split_quaternion(q, scalar_first)
    return join_quaternion(xp, *(hamilton(parts, pure) if body else hamilton(pure, parts)), scalar_first)


@op(q=(4,), q_dot=(4,), q_ddot=(4,))
def angular_acceleration(
    xp: Any, q: Any, q_dot: Any, q_ddot: Any, *, frame: str = "body", scalar_first: bool = True
) -> Any:
    """The angular acceleration of a quaternion trajectory from its first two derivatives: the time
    derivative of ``angular_velocity(q, q_dot)`` in the same frame.

    Derivation (body): with ``a = q^-1 q'``, ``w_b = 2 vec(a)`` and ``a' = -(q^-1 q' q^-1) q' +
    q^-1 q'' = q^-1 q'' - a a``, whose vector part is ``vec(q^-1 q'') - 2 a_w vec(a)``, so
    ``w_b' = 2 vec(q^-1 q'') - 4 a_w vec(a)``, ``a_w = (q . q') / |q|^2``. For a unit ``q`` (so
    ``q . q' = 0``) this is ``2 vec(q* q'')``: the term ``2 vec(q'* q')`` of the product rule is real.
    Space: the same with ``b = q' q^-1`` (``b_w = a_w``), ``w_s' = 2 vec(q'' q^-1) - 4 b_w vec(b)``,
    which equals ``R w_b'`` (``d/dt (R w_b) = R (w_b x w_b) + R w_b'``).

    Args:
        q: quaternions, shape ``(..., 4)``, any non-zero norm (the rates are those of ``R(q(t))``, as in
            ``angular_velocity``); the zero quaternion gives 0.
        q_dot: first time derivatives, shape ``(..., 4)``.
        q_ddot: second time derivatives, shape ``(..., 4)``; the batch shapes broadcast.
        frame: ``"body"`` (the default) or ``"space"``; anything else raises ``ValueError``.
        scalar_first: storage order of the three.

    Returns:
        Shape ``(..., 3)``, in radians per unit of time squared.
    """
    body = check_frame("angular_acceleration", frame)
    q, q_dot, q_ddot = match_rank(xp, q, q_dot, q_ddot)
    aw, ax, ay, az = _relative(xp, q, q_dot, body, scalar_first)
    _, cx, cy, cz = _relative(xp, q, q_ddot, body, scalar_first)
    k = 4.0 * aw
    return xp.stack([2.0 * cx - k * ax, 2.0 * cy - k * ay, 2.0 * cz - k * az], axis=-1)


# ---------------------------------------------------------------------------------------------------
# Integration, and rates from samples


@op(q=(4,), omega=(3,), dt=())
def integrate_angular_velocity(
    xp: Any, q: Any, omega: Any, dt: Any, *, frame: str = "body", scalar_first: bool = True
) -> Any:
    """One step of an orientation turning at a constant angular velocity: ``q exp(w_b dt)``
    (``frame="body"``) or ``exp(w_s dt) q`` (``frame="space"``), ``exp`` the unit quaternion of a
    rotation vector (``quaternion_plus``). Exact for a rate constant over the step (no Euler or
    Runge-Kutta error, no drift off the unit sphere), for every step length.

    Args:
        q: quaternions, shape ``(..., 4)``, any non-zero norm (normalised first; the zero quaternion is
            the identity).
        omega: angular velocities, shape ``(..., 3)``.
        dt: time steps, shape ``(...)`` (one per rotation; a 0-dimensional array for all); the batch
            shapes of the three broadcast.
        frame: ``"body"`` (the default) or ``"space"``; anything else raises ``ValueError``.
        scalar_first: storage order of ``q`` and of the result.

    Returns:
        Unit quaternions, shape ``(..., 4)``, the sign the product's (continuous in ``w dt``; not
        standardised). ``angular_velocity_from_quaternions`` of ``q`` and this step gives ``w`` back
        while ``|w dt| < pi``. Finite and unit for every finite ``w dt``: a rotation vector whose
        squared length would overflow (|w dt| beyond ~4.6e18 rad in float32, 3.3e153 in float64) is
        first reduced modulo 4 pi along its axis; at such angles the rounding of ``w dt`` has long
        lost every turn (beyond 1 / eps rad), so only the axis is meaningful.
    """
    body = check_frame("integrate_angular_velocity", frame)
    omega, step = match_rank(xp, omega, dt[..., None])
    side = "right" if body else "left"
    return quaternion_plus(xp, q, _within_range(xp, omega * step), side=side, scalar_first=scalar_first)


def _range(dtype_max: float) -> tuple[float, float]:
    """``(top, c)`` for a dtype whose largest finite number is ``dtype_max``: a rotation vector ``v``
    with ``|v|^2 > top = max / 16`` (``|v| > sqrt(max) / 4``: 4.6e18 rad in float32) is reduced
    (its square may overflow), after being scaled by the power of two ``c`` (exact). Scaled, not
    divided by its largest component: XLA multiplies by the reciprocal of a broadcast divisor, which
    flushes to zero beyond 2^126 in float32. Where reduced ``|v c|`` is then in [2^-8, 2^(maxexp / 2 -
    5)]: the squares neither over- nor underflow."""
    return dtype_max / 16, 2.0 ** -(math.frexp(dtype_max)[1] // 2 + 6)


def _within_range(xp: Any, v: Any) -> Any:
    """The rotation vectors ``v`` ``(..., 3)``, those whose angle's square would overflow (``|v|`` beyond
    sqrt(max) / 4: 4.6e18 rad in float32, :func:`_range`) reduced modulo 4 pi along their axis: the
    same rotation and the same quaternion (exp is 4 pi periodic along a fixed axis), finite. The others
    are ``v`` itself, bit for bit. The reduced angle is exact for the rounded angle, which has lost
    every turn to rounding long before (beyond 1 / eps rad): the axis alone is meaningful there. The
    eager form (:func:`exp_in_range`) reduces the same rows."""
    top, c = _range(float(xp.finfo(v.dtype).max))
    # |v|^2 itself (inf where it overflows), not the largest component: NaN stays NaN (not big) on
    # every backend, and the eager form reads the same sum of squares
    big = xp.sum(v * v, axis=-1, keepdims=True) > top
    w = v * c
    angle = xp.sqrt(xp.where(big, xp.sum(w * w, axis=-1, keepdims=True), 1.0))
    # 2 fmod(|v| / 2, 2 pi) = |v| mod 4 pi, without |v| overflowing near the largest finite number
    reduced = 2.0 * xp.fmod(angle * (0.5 / c), 2.0 * math.pi)
    return xp.where(big, w * (reduced / angle), v)


def angular_velocity_from_quaternions(
    xp: Any, q: Any, dt: Any, *, frame: str = "body", scalar_first: bool = True
) -> Any:
    """The constant angular velocity between consecutive samples of an orientation:
    ``log(q_k^-1 q_k+1) / dt_k`` (``frame="body"``) or ``log(q_k+1 q_k^-1) / dt_k`` (``frame="space"``),
    along the sequence axis -2.

    Exact for a rate constant over each interval with ``|w dt| < pi`` (the inverse of
    ``integrate_angular_velocity``); a central difference of quaternions is biased by a relative
    ``(|w| dt)^2 / 24`` and breaks where the samples change sign. The logarithm is the shortest arc
    (``quaternion_minus``): ``q_k`` and ``-q_k`` give the same rates, so sign flips between samples
    change nothing.

    Args:
        q: samples, shape ``(..., T, 4)``, any non-zero norms (the zero quaternion is the identity).
        dt: the time steps, a 0-dimensional array (one step for all) or shape ``(..., T - 1)`` (one per
            interval), broadcasting against ``q``'s batch. Differences of timestamps: take them in
            float64 or integers before casting (see the module's note on time).
        frame: ``"body"`` (the default) or ``"space"``; anything else raises ``ValueError``.
        scalar_first: storage order of ``q``.

    Returns:
        Shape ``(..., T - 1, 3)`` (empty for ``T <= 1``). Where two samples are exactly a half-turn
        apart the rate takes ``quaternion_minus``'s sign and jumps there.
    """
    # Not registered with ``op``: ``dt``'s trailing shape is ``(T - 1,)`` against ``q``'s ``(T, 4)``,
    # which the registry's one size N per function cannot state; the binding validates it.
    body = check_frame("angular_velocity_from_quaternions", frame)
    side = "right" if body else "left"
    log = quaternion_minus(xp, q[..., 1:, :], q[..., :-1, :], side=side, scalar_first=scalar_first)
    log, step = match_rank(xp, log, dt[..., None])
    return log / step


# ---------------------------------------------------------------------------------------------------
# Segments and gathers


def _segment(xp: Any, u: Any, segments: int) -> tuple[Any, Any]:
    """The segment index ``i`` (as a float, in [0, segments - 1]) and the fraction ``s`` in [0, 1] of
    parameters ``u`` clamped to [0, segments]: ``u = i + s``, with the end ``u = segments`` in the last
    segment at ``s = 1``. The index is a selection (a zero derivative), the fraction carries ``u``'s.

    The clamp is two selections, not a clip, so that at the ends ``u = 0`` and ``u = segments`` the
    derivative in ``u`` is the one-sided one from inside on every backend (jax's clip halves it there:
    a tie of min or max splits the derivative; torch's clamp passes it whole); outside, it is 0.

    A NaN parameter takes segment 0 (an index must be in range on every backend: numpy and torch
    raise on one that is not) and keeps its NaN in the fraction, so the values at it are NaN."""
    uc = xp.where(u < 0.0, 0.0, xp.where(u > float(segments), float(segments), u))
    # uc >= 0 is False only where uc is NaN (the selections have put every number in range)
    i = xp.clip(xp.floor(xp.where(uc >= 0.0, uc, 0.0)), 0.0, float(segments - 1))
    return i, uc - i


def _gather(xp: Any, x: Any, index: Any, trailing: int) -> Any:
    """``x[..., index[..., j], *rest]``: the entries of ``x`` ``(B..., K, *rest)`` (``trailing`` axes
    in ``rest``) at integer-valued float positions ``index`` ``(S..., J)`` along its axis of size K,
    batch shapes broadcast: ``(N..., J, *rest)``.

    Its derivative adds the cotangents into an array of the size of ``x``: gathering along an axis
    of ``x`` broadcast to every point (``take_along_axis``) has a derivative of N K entries, which
    ran out of memory at 262 144 points (docs/performance.md, Rotations in time). So one spline
    (``B`` all ones, a static check) is indexed directly, ``x`` ``(K, *rest)`` at the integers; a
    batch of splines in torch by one index into ``x`` flattened to ``(prod(B) K, *rest)`` (batch
    position times K plus the index; torch's ``take_along_dim`` also made a dynamic batch a constant
    under ``torch.export``), and in numpy and jax by ``take_along_axis``, whose batch axes stay
    aligned (jax shards them; a flat index would mix the shards)."""
    count = x.shape[-1 - trailing]
    rest = tuple(x.shape[x.ndim - trailing :])
    batch = tuple(x.shape[: x.ndim - 1 - trailing])
    size = math.prod(batch)
    astype = getattr(xp, "astype", None)
    # torch wants int64 (it has no namespace astype); numpy and jax int32 (K < 2^31; jax has int64
    # only with x64)
    ints = index.long() if astype is None else astype(index, xp.int32)
    if size == 1:
        return xp.reshape(x, (count, *rest))[ints]
    if astype is not None:
        ints, x = match_rank(xp, xp.reshape(ints, (*ints.shape, *(1,) * trailing)), x)
        return xp.take_along_axis(x, ints, axis=-1 - trailing)
    offsets = xp.reshape(xp.arange(size, device=x.device) * count, (*batch, 1))
    offsets, ints = match_rank(xp, offsets, ints)
    return xp.reshape(x, (size * count, *rest))[offsets + ints]


def _consecutive(xp: Any, i: Any, count: int) -> Any:
    """``(i, i + 1, ..., i + count - 1)`` along a new last axis: ``(S..., count)``."""
    return xp.stack([i + float(j) for j in range(count)], axis=-1)


# ---------------------------------------------------------------------------------------------------
# SQUAD


@op(q=(-1, 4), t=())
def quaternion_squad(xp: Any, q: Any, t: Any, *, scalar_first: bool = True) -> Any:
    """Shoemake's spherical quadrangle interpolation (SQUAD, 1987) through knots ``q_0 ... q_K-1`` at
    parameters ``t`` = knot index + fraction.

    On segment ``i`` (``t = i + h``, ``h`` in [0, 1]):
    ``squad = slerp(slerp(q_i, q_i+1, h), slerp(s_i, s_i+1, h), 2 h (1 - h))`` with the inner control
    points ``s_i = q_i exp(-(log(q_i^-1 q_i+1) + log(q_i^-1 q_i-1)) / 4)`` (``exp``, ``log`` of rotation
    vectors; ``log(q_i^-1 q_i-1) = -log(q_i-1^-1 q_i)``, shortest arcs), and the end knots their own
    controls (``s_0 = q_0``, ``s_K-1 = q_K-1``). It passes through every knot, its tangent is continuous
    at the inner knots (C1, not C2: a B-spline is C2, see ``so3_bspline``), and where the knots lie
    equally spaced on one geodesic every ``s_i = q_i`` and it is the constant-speed slerp along it.

    Knot signs: the knots are normalised, then each is flipped into the hemisphere of the one before
    (a cumulative product of the signs of consecutive dot products, no loop over the knots), so the
    returned quaternion is continuous in ``t`` across knots, not only its rotation.

    Args:
        q: knots, shape ``(..., K, 4)``, K >= 2 (fewer raises ``ValueError``), any non-zero norms (the
            zero quaternion is the identity). Consecutive knots less than a half-turn apart.
        t: parameters, shape ``(...)``, broadcasting against the knots' batch shape (knots ``(B, K, 4)``
            at ``t`` of shape ``(N, 1)`` give ``(N, B, 4)``). Clamped to [0, K - 1]: outside, the end
            knots. A knot index plus a fraction: compute it from timestamps in float64 or integers
            before casting (see the module's note on time).
        scalar_first: storage order of ``q`` and of the result.

    Returns:
        Unit quaternions, shape ``(..., 4)``; at ``t = k`` the knot ``q_k``, normalised, with the sign
        made consistent with ``q_0``.
    """
    return _squad(xp, q, t, scalar_first, eager=False)


def _squad(xp: Any, q: Any, t: Any, scalar_first: bool, *, eager: bool) -> Any:
    """``quaternion_squad``, its pieces (``quaternion_minus``, ``quaternion_plus``, ``quaternion_slerp``)
    componentwise or, ``eager``, their eager forms (the same values and choices)."""
    minus, plus, slerp = (
        (quaternion_minus_eager, quaternion_plus_eager, quaternion_slerp_eager)
        if eager
        else (quaternion_minus, quaternion_plus, quaternion_slerp)
    )
    count = q.shape[-2]
    if count < 2:
        raise ValueError(f"quaternion_squad: expected at least 2 knots, got q of shape {tuple(q.shape)}")
    if not scalar_first:
        q = xyzw_to_wxyz(xp, q)
    q = normalize_quaternion(xp, q)
    dots = xp.sum(q[..., :-1, :] * q[..., 1:, :], axis=-1)
    one = xp.ones_like(dots)
    parity = xp.cumprod(xp.where(dots < 0.0, -one, one), axis=-1)  # constants: no derivative
    q = q * xp.concat([one[..., :1], parity], axis=-1)[..., None]
    # d_k = log(q_k^-1 q_k+1), k = 0 .. K-2; inner control k: q_k exp((d_k-1 - d_k) / 4)
    d = minus(xp, q[..., 1:, :], q[..., :-1, :])
    zero = xp.zeros_like(d[..., :1, :])
    correction = xp.concat([zero, 0.25 * (d[..., :-1, :] - d[..., 1:, :]), zero], axis=-2)
    s = plus(xp, q, correction)
    i, h = _segment(xp, t, count - 1)
    pair = _consecutive(xp, i, 2)
    knots, controls = _gather(xp, q, pair, 1), _gather(xp, s, pair, 1)
    # the outer (knots) and inner (controls) slerps at h as one call on the pairs stacked: the same
    # elementwise arithmetic on each, in a graph of two slerps, not three
    ends = xp.stack([knots, controls], axis=-3)  # (..., outer / inner, start / end, 4)
    both = slerp(xp, ends[..., 0, :], ends[..., 1, :], h[..., None])
    out = slerp(xp, both[..., 0, :], both[..., 1, :], 2.0 * h * (1.0 - h))
    return out if scalar_first else wxyz_to_xyzw(xp, out)


# ---------------------------------------------------------------------------------------------------
# Cumulative B-splines


def _cumulative_basis(order: int) -> list[list[Fraction]]:
    """The cumulative basis matrix of the uniform B-spline of ``order`` (degree ``order - 1``), exactly:
    row ``j`` holds the coefficients of ``B~_j(s) = sum_{l >= j} B_l(s)`` in powers ``s^0 ... s^(k-1)``,
    ``B_l`` the blending function of control point ``i + l`` on segment ``i``.

    The blending matrix is Qin's closed form ("General matrix representations for B-splines", 2000):
    ``m_{n, l} = C(k-1, n) / (k-1)! sum_{m=l}^{k-1} (-1)^(m-l) C(k, m-l) (k-1-m)^(k-1-n)`` (power ``n``,
    control ``l``; ``0^0 = 1``), so for order 4 ``B~ = [[6, 0, 0, 0], [5, 3, -3, 1], [1, 3, 3, -2],
    [0, 0, 0, 1]] / 6``. Row 0 is ``(1, 0, ..., 0)``: the basis is a partition of unity. Python
    fractions of the static order, a few dozen operations per call."""
    k = order
    blend = [
        [
            Fraction(math.comb(k - 1, n), math.factorial(k - 1))
            * sum(
                (-1) ** (m - col) * math.comb(k, m - col) * (k - 1 - m) ** (k - 1 - n) for m in range(col, k)
            )
            for n in range(k)
        ]
        for col in range(k)
    ]
    return [[sum((blend[l][n] for l in range(j, k)), Fraction(0)) for n in range(k)] for j in range(k)]


def _polynomial(s: Any, coefficients: list[Fraction]) -> Any:
    """Horner's evaluation of ``sum_n c_n s^n`` (``c`` in increasing powers, at least one)."""
    out = float(coefficients[-1]) + 0.0 * s
    for c in coefficients[-2::-1]:
        out = out * s + float(c)
    return out


def _basis(xp: Any, s: Any, order: int) -> list[tuple[Any, Any, Any]]:
    """``(lambda_j, lambda_j', lambda_j'')`` for ``j = 1 .. order - 1``: the cumulative basis functions
    at the fractions ``s`` and their first and second derivatives in ``s``."""
    out = []
    for row in _cumulative_basis(order)[1:]:
        first = [n * c for n, c in enumerate(row)][1:]
        second = [n * c for n, c in enumerate(first)][1:] or [Fraction(0)]
        out.append((_polynomial(s, row), _polynomial(s, first), _polynomial(s, second)))
    return out


def _check_spline(fname: str, shape: tuple[int, ...], trailing: int, order: int) -> int:
    """The number of control points; ``TypeError`` for an order that is not an integer (a bool, a
    float such as 4.0, an array: the order is static), ``ValueError`` for one below 2 or fewer points
    than it."""
    if isinstance(order, bool) or not isinstance(order, numbers.Integral):
        raise TypeError(
            f"{fname}: expected order to be an int (static), got {order!r} of type {type(order).__name__}"
        )
    if order < 2:
        raise ValueError(f"{fname}: expected order >= 2, got {order}")
    count = shape[-1 - trailing]
    if count < order:
        raise ValueError(
            f"{fname}: expected at least order = {order} control points, got control of shape {shape}"
        )
    return count


def _scaled(xp: Any, factor: Any, v: Any) -> Any:
    """``factor[..., None] * v`` with ``factor`` ``(S...)`` and ``v`` ``(N..., n)``."""
    f, v = match_rank(xp, factor[..., None], v)
    return f * v


def _recursion(
    xp: Any,
    first: Any,
    d: Any,
    basis: list[tuple[Any, Any, Any]],
    *,
    exp: Callable[[Any], Any],
    compose: Callable[[Any, Any], Any],
    transport: Callable[[Any, Any], Any],
    bracket: Callable[[Any, Any], Any],
) -> tuple[Any, Any, Any]:
    """Sommer et al.'s recursion on one group: the value ``first exp(lambda_1 d_1) ...`` and its body
    rate ``V`` and acceleration ``V'``, from the first control point of the segment ``first``
    ``(N..., n, n)``, the increments ``d`` ``(N..., order - 1, m)`` and the basis at the fractions
    (``_basis``, each ``(S...)``).

    ``exp`` maps a tangent to the group, ``compose`` multiplies, ``transport(A, v)`` is ``Ad(A^-1) v``
    and ``bracket(a, b)`` is ``ad(a) b``. Each step ``j`` appends ``A_j = exp(lambda_j d_j)``:
    ``V_j = Ad(A_j^-1) V_j-1 + lambda_j' d_j`` (the body rate of a product) and, differentiating it
    with ``d/ds Ad(A_j^-1) = -ad(lambda_j' d_j) Ad(A_j^-1)``,
    ``V_j' = Ad(A_j^-1) V_j-1' + lambda_j'' d_j + ad(V_j) (lambda_j' d_j)``. At ``j = 1`` (``V_0 = 0``)
    the bracket is ``ad(V_1) V_1 = 0``, and the step starts the rates."""
    value, rate, accel = first, None, None
    # One exponential of the steps stacked on d's axis, not one per step: the same elementwise
    # arithmetic on each, in a graph a third the size (the compilers' cost is the graph's size).
    steps = exp(_scaled(xp, xp.stack([lam for lam, _, _ in basis], axis=-1), d))
    for j, (_, lam_dot, lam_ddot) in enumerate(basis):
        dj = d[..., j, :]
        step = steps[..., j, :, :]
        value = compose(value, step)
        step_rate, step_accel = _scaled(xp, lam_dot, dj), _scaled(xp, lam_ddot, dj)
        if j == 0:
            rate, accel = step_rate, step_accel
        else:
            rate = transport(step, rate) + step_rate
            accel = transport(step, accel) + step_accel + bracket(rate, step_rate)
    return value, rate, accel


@functools.cache
def _basis_forms(order: int) -> Callable[[], tuple[Any, ...]]:
    """The maker (for ``_core.constants``, one per order) of the coefficients of the cumulative basis
    and of its two derivatives, ``(order, 3 (order - 1))``: row ``n`` the coefficients of ``s^n`` of
    ``lambda_1 .. lambda_k-1``, then of their first and of their second derivatives."""
    polys = []
    for part in range(3):
        for row in _cumulative_basis(order)[1:]:
            for _ in range(part):
                row = [n * c for n, c in enumerate(row)][1:]
            polys.append([float(c) for c in row] + [0.0] * (order - len(row)))

    def make() -> tuple[Any, ...]:
        return tuple([p[n] for p in polys] for n in range(order))

    return make


def _basis_eager(xp: Any, s: Any, order: int) -> Any:
    """:func:`_basis`, eager form: ``lambda_1 .. lambda_k-1``, their first and their second derivatives
    at the fractions ``s`` ``(S...)``, side by side ``(S..., 3 (order - 1))``, by one Horner evaluation
    of all of them (the same operations on each polynomial as :func:`_polynomial`; the lower degrees'
    zero leading coefficients add exact zeros)."""
    forms = constants(xp, s, _basis_forms(order))
    x = s[..., None]
    out = x * forms[-1] + forms[-2]
    for c in forms[-3::-1]:
        out = out * x + c
    return out


def _recursion_eager(
    xp: Any,
    first: Any,
    d: Any,
    basis: Any,
    *,
    exp: Callable[[Any], Any],
    compose: Callable[[Any, Any], Any],
    transport: Callable[[Any, Any], Any],
    bracket: Callable[[Any, Any], Any],
) -> tuple[Any, Any, Any]:
    """:func:`_recursion`, eager form, with the basis of :func:`_basis_eager` ``(S..., 3 (order - 1))``:
    the same steps, with every ``lambda_j d_j`` and its derivatives' terms formed by one product and
    every exponential by one call (the steps stacked on the axis of ``d``)."""
    count = d.shape[-2]
    lam, dj = match_rank(xp, basis.unflatten(-1, (3, count))[..., None], d[..., None, :, :])
    terms = (lam * dj).unbind(-3)  # each (N..., order - 1, m)
    steps = exp(terms[0]).unbind(-3)
    rates, accels = terms[1].unbind(-2), terms[2].unbind(-2)
    value, rate, accel = compose(first, steps[0]), rates[0], accels[0]
    for j in range(1, count):
        value = compose(value, steps[j])
        rate = transport(steps[j], rate) + rates[j]
        accel = transport(steps[j], accel) + accels[j] + bracket(rate, rates[j])
    return value, rate, accel


_SPLINE_DOC = """
    The spline (Kim, Kim and Shin, "A general construction scheme for unit quaternion curves with
    simple high order derivatives", SIGGRAPH 1995; Sommer, Usenko, Schubert, Demmel and Cremers,
    "Efficient Derivative Computation for Cumulative B-Splines on Lie Groups", CVPR 2020): on segment
    ``i`` (``u = i + s``, ``s`` in [0, 1]) of order ``k``,
    ``{X}(u) = {X}_i exp(lambda_1(s) d_1) ... exp(lambda_k-1(s) d_k-1)`` with the increments
    ``d_j = log({X}_i+j-1^-1 {X}_i+j)`` and ``lambda_j`` the cumulative basis of the uniform B-spline
    (:func:`_cumulative_basis`). The rates follow Sommer et al.'s recursion for the body velocity
    and acceleration (as basalt's ``so3_spline.h``), exact, no finite differences
    (:func:`_recursion`): with ``A_j = exp(lambda_j d_j)``,
    ``V_j = {Ad} V_j-1 + lambda_j' d_j`` and ``V_j' = {Ad} V_j-1' + lambda_j'' d_j + {ad}``, from
    ``V_0 = V_0' = 0``; the rate of the spline is ``V_k-1``.
    The spline is C^(k-2) in ``u``: order 4 (cubic) has its rate and acceleration continuous across
    segments. It does not pass through its control points (a B-spline approximates them), but a
    control polygon on one geodesic with equal steps gives the constant-rate motion along it.

    Time: ``u`` is segment index + fraction, segment ``i`` spanning ``u`` in [i, i + 1] and reading
    control points ``i .. i + k - 1``; ``u`` is clamped to [0, K - k + 1], and outside that range the
    value and both rates are those at the nearest end (held, not extrapolated). The rates are with
    respect to ``u``: for knots ``h`` seconds apart, ``w / h`` and ``w' / h^2``. Compute ``u`` from
    timestamps in float64 or integers before casting (see the module's note on time).

    Increments are shortest-arc logarithms: consecutive control rotations less than a half-turn apart
    (at exactly a half-turn the logarithm takes ``so3_log``'s sign). Where they coincide (a static
    trajectory) everything is finite and exact, derivatives included (the exponential and logarithm
    are series there). Gradients with respect to the control points and ``u`` are those of the
    formula.
"""


@op(control=(-1, 3, 3), u=())
def so3_bspline(
    xp: Any,
    control: Any,
    u: Any,
    *,
    order: int = 4,
    to_matrix: Conversion = unit_quaternion_to_matrix,
    to_quaternion: Conversion = matrix_to_quaternion,
) -> tuple[Any, Any, Any]:
    """A uniform cumulative B-spline of rotation matrices, with its exact body angular velocity and
    acceleration.

    Args:
        control: control rotations, shape ``(..., K, 3, 3)``, K >= order (fewer raises
            ``ValueError``). The first of a segment is multiplied as it is; the increments are taken
            through ``matrix_to_quaternion`` (a matrix slightly off SO(3) reads as a nearby rotation).
        u: spline parameters, shape ``(...)``, broadcasting against the control points' batch shape
            (control ``(B, K, 3, 3)`` at ``u`` of shape ``(N, 1)`` gives ``(N, B, ...)``).
        order: the spline's order ``k`` >= 2 (degree ``k - 1``; 4 is cubic, C2); static.

    Returns:
        ``(rotation, omega, omega_dot)``: rotation matrices ``R(u)``, shape ``(..., 3, 3)``; the body
        angular velocity ``w_b = vee(R^T dR/du)``, shape ``(..., 3)``; and its derivative
        ``dw_b/du``, shape ``(..., 3)``. The space-frame rates are ``R w_b`` and ``R w_b'``.
    """
    count = _check_spline("so3_bspline", tuple(control.shape), 2, order)
    i, s = _segment(xp, u, count - order + 1)
    return _so3_bspline_at(xp, control, i, s, order, to_matrix, to_quaternion, eager=False)


def _so3_bspline_at(
    xp: Any,
    control: Any,
    i: Any,
    s: Any,
    order: int,
    to_matrix: Conversion,
    to_quaternion: Conversion,
    *,
    eager: bool,
) -> tuple[Any, Any, Any]:
    """``so3_bspline`` on the segments ``i`` at the fractions ``s`` (``_segment``), which the split
    SE(3) spline shares; ``eager``: with the eager forms of the logarithm and the exponential and
    :func:`_recursion_eager` (the same values, to rounding, and the same choices)."""
    log, exp = (
        (matrix_to_axis_angle_eager, axis_angle_to_matrix_eager)
        if eager
        else (matrix_to_axis_angle, axis_angle_to_matrix)
    )
    relative = small_matmul(xp, xp.swapaxes(control[..., :-1, :, :], -1, -2), control[..., 1:, :, :])
    increments = log(xp, relative, to_quaternion=to_quaternion)  # (B..., K - 1, 3)
    rotation = _gather(xp, control, i[..., None], 2)[..., 0, :, :]
    d = _gather(xp, increments, _consecutive(xp, i, order - 1), 1)

    def transport(step: Any, v: Any) -> Any:  # Ad(A^-1) on SO(3): A^T
        return xp.matmul(xp.swapaxes(step, -1, -2), v[..., None])[..., 0]

    recursion = _recursion_eager if eager else _recursion
    return recursion(
        xp,
        rotation,
        d,
        _basis_eager(xp, s, order) if eager else _basis(xp, s, order),
        exp=lambda v: exp(xp, v, to_matrix=to_matrix),
        compose=lambda a, b: small_matmul(xp, *match_rank(xp, a, b)),
        transport=transport,
        bracket=xp.linalg.cross,
    )


SPLINE_MODES = ("se3", "split")


@op(control=(-1, 4, 4), u=())
def se3_bspline(
    xp: Any,
    control: Any,
    u: Any,
    *,
    order: int = 4,
    mode: str = "se3",
    to_matrix: Conversion = unit_quaternion_to_matrix,
    to_quaternion: Conversion = matrix_to_quaternion,
) -> tuple[Any, Any, Any]:
    """A uniform cumulative B-spline of poses, on SE(3) or on R^3 x SO(3), with its exact body twist
    and its rate.

    ``mode="se3"`` (the default): the increments are twists of SE(3) (``se3_minus``), so rotation and
    translation move together along screws; the poses' rotation is not the ``so3_bspline`` of their
    rotations (it is where the translations are all equal). ``mode="split"``: the rotation is the
    ``so3_bspline`` of the control rotations and the position the cumulative B-spline of the control
    translations in R^3 (basalt's split spline; a straight line in the world for collinear control
    translations, whatever the rotations do). Both return the same quantities, the body twist of the
    curve they draw.

    Args:
        control: control poses ``[[R, t], [0, 1]]``, shape ``(..., K, 4, 4)``, K >= order (fewer raises
            ``ValueError``); the bottom rows are not read.
        u: spline parameters, shape ``(...)``, broadcasting against the control points' batch shape.
        order: the spline's order ``k`` >= 2 (4 is cubic, C2); static.
        mode: ``"se3"`` or ``"split"`` (anything else raises ``ValueError``); static.

    Returns:
        ``(pose, twist, twist_dot)``: poses ``T(u)``, shape ``(..., 4, 4)``, bottom row exact; the body
        twist ``vee(T^-1 dT/du)``, shape ``(..., 6)``, translation first (``(R^T dp/du, w_b)``); and
        its derivative in ``u``, shape ``(..., 6)``. The position's derivative in the world is
        ``R v``; in the split form its second derivative is ``R (v' + w_b x v)``.
    """
    return _se3_bspline(xp, control, u, order, mode, to_matrix, to_quaternion, eager=False)


def _se3_bspline(
    xp: Any,
    control: Any,
    u: Any,
    order: int,
    mode: str,
    to_matrix: Conversion,
    to_quaternion: Conversion,
    *,
    eager: bool,
) -> tuple[Any, Any, Any]:
    """``se3_bspline``; ``eager``: with the eager forms of its pieces (``se3_minus``, ``se3_exp``,
    ``se3_compose``, the split form's ``so3_bspline`` pieces), the same values and choices."""
    if mode not in SPLINE_MODES:
        raise ValueError(f"se3_bspline: expected mode to be 'se3' or 'split', got {mode!r}")
    count = _check_spline("se3_bspline", tuple(control.shape), 2, order)
    if mode == "split":
        return _split_bspline(xp, control, u, order, count, to_matrix, to_quaternion, eager=eager)
    minus, exp, compose = (
        (se3_minus_eager, se3_exp_eager, se3_compose_eager) if eager else (se3_minus, se3_exp, se3_compose)
    )
    increments = minus(xp, control[..., 1:, :, :], control[..., :-1, :, :], to_quaternion=to_quaternion)
    i, s = _segment(xp, u, count - order + 1)
    pose = _gather(xp, control, i[..., None], 2)[..., 0, :, :]
    d = _gather(xp, increments, _consecutive(xp, i, order - 1), 1)

    cross = xp.linalg.cross

    def rotate_back(step: Any, v: Any) -> Any:  # R^T v
        return xp.matmul(xp.swapaxes(step[..., :3, :3], -1, -2), v[..., None])[..., 0]

    # Ad(A^-1) (rho, phi) = (R^T (rho - t x phi), R^T phi) for A = [R, t], and ad(a) b =
    # (phi_a x rho_b + rho_a x phi_b, phi_a x phi_b): the products written out, no 6x6 matrices
    def transport(step: Any, v: Any) -> Any:
        rho, phi = v[..., :3], v[..., 3:]
        moved = rho - cross(*match_rank(xp, step[..., :3, 3], phi))
        return xp.concat([rotate_back(step, moved), rotate_back(step, phi)], axis=-1)

    def bracket(a: Any, b: Any) -> Any:
        rho_a, phi_a, rho_b, phi_b = a[..., :3], a[..., 3:], b[..., :3], b[..., 3:]
        return xp.concat([cross(phi_a, rho_b) + cross(rho_a, phi_b), cross(phi_a, phi_b)], axis=-1)

    recursion = _recursion_eager if eager else _recursion
    return recursion(
        xp,
        pose,
        d,
        _basis_eager(xp, s, order) if eager else _basis(xp, s, order),
        exp=lambda v: exp(xp, v, to_matrix=to_matrix),
        compose=lambda a, b: compose(xp, a, b),
        transport=transport,
        bracket=bracket,
    )


def _sum_terms(terms: list[Any]) -> Any:
    """The sum of a non-empty list of arrays, in order."""
    out = terms[0]
    for t in terms[1:]:
        out = out + t
    return out


def _split_bspline(
    xp: Any,
    control: Any,
    u: Any,
    order: int,
    count: int,
    to_matrix: Conversion,
    to_quaternion: Conversion,
    *,
    eager: bool,
) -> tuple[Any, Any, Any]:
    """``se3_bspline``'s ``mode="split"``: the rotation, ``w_b`` and ``w_b'`` of ``so3_bspline``, and
    the position ``p = p_i + sum_j lambda_j (p_i+j - p_i+j-1)`` with its derivatives in ``u``, as the
    body twist ``(R^T p', w_b)`` and its derivative ``(R^T p'' - w_b x R^T p', w_b')`` (``R'^T = -hat(w_b)
    R^T``)."""
    i, s = _segment(xp, u, count - order + 1)
    rotation, omega, omega_dot = _so3_bspline_at(
        xp, control[..., :3, :3], i, s, order, to_matrix, to_quaternion, eager=eager
    )
    points = control[..., :3, 3]  # (B..., K, 3)
    first = _gather(xp, points, i[..., None], 1)[..., 0, :]
    steps = _gather(xp, points[..., 1:, :] - points[..., :-1, :], _consecutive(xp, i, order - 1), 1)
    if eager:
        # the three sums of lambda_j (and its derivatives) times the steps as one product (S..., 3,
        # order - 1) @ (N..., order - 1, 3): values only, no choice rides on its rounding
        lam = _basis_eager(xp, s, order).unflatten(-1, (3, order - 1))
        sums = xp.matmul(*match_rank(xp, lam, steps))
        position, velocity, accel = first + sums[..., 0, :], sums[..., 1, :], sums[..., 2, :]
    else:
        terms = [[_scaled(xp, f, steps[..., j, :]) for f in fs] for j, fs in enumerate(_basis(xp, s, order))]
        position = first + _sum_terms([t[0] for t in terms])
        velocity, accel = _sum_terms([t[1] for t in terms]), _sum_terms([t[2] for t in terms])
    r_t = xp.swapaxes(rotation, -1, -2)
    v = xp.matmul(r_t, velocity[..., None])[..., 0]
    v_dot = xp.matmul(r_t, accel[..., None])[..., 0] - xp.linalg.cross(omega, v)
    pose = _with_bottom(xp, xp.concat([rotation, position[..., None]], axis=-1))
    return pose, xp.concat([v, omega], axis=-1), xp.concat([v_dot, omega_dot], axis=-1)


so3_bspline.__doc__ = (so3_bspline.__doc__ or "") + _SPLINE_DOC.format(
    X="R", Ad="A_j^T", ad="V_j x (lambda_j' d_j)"
)
se3_bspline.__doc__ = (se3_bspline.__doc__ or "") + _SPLINE_DOC.format(
    X="T", Ad="Ad(A_j^-1)", ad="ad(V_j) (lambda_j' d_j)"
)


# ---------------------------------------------------------------------------------------------------
# What the backends bind. The public functions validate their arguments against the registered shapes
# (``_backend.Backend``) and apply the rule for non-finite rows to one array; this adapts the function
# whose public form is not the core's (one step per sequence).


def _bound(name: str, **trailing: tuple[int, ...]) -> Callable[[Callable[..., Any]], Callable[..., Any]]:
    """Register ``fn`` under the public name ``name`` (validation and errors name it)."""

    def register(fn: Callable[..., Any]) -> Callable[..., Any]:
        fn.__name__ = name
        return op(**trailing)(fn)

    return register


@_bound("angular_velocity_from_quaternions", q=(-1, 4), dt=())
def bound_angular_velocity_from_quaternions(
    xp: Any, q: Any, dt: Any, *, frame: str = "body", scalar_first: bool = True
) -> Any:
    # one step per sequence, dt (...): the core's step per interval is dt[..., None]
    return angular_velocity_from_quaternions(xp, q, dt[..., None], frame=frame, scalar_first=scalar_first)


bound_angular_velocity_from_quaternions.__doc__ = """The constant angular velocity between consecutive
    samples of an orientation: ``log(q_k^-1 q_k+1) / dt`` (``frame="body"``) or ``log(q_k+1 q_k^-1) /
    dt`` (``frame="space"``), along the sequence axis -2.

    Exact for a rate constant over each interval with ``|w dt| < pi`` (the inverse of
    ``integrate_angular_velocity``); a central difference of quaternions is biased by a relative
    ``(|w| dt)^2 / 24`` and breaks where the samples change sign. The logarithm is the shortest arc
    (``quaternion_minus``): ``q_k`` and ``-q_k`` give the same rates, so sign flips between samples
    change nothing.

    Args:
        q: samples, shape ``(..., T, 4)``, any non-zero norms (the zero quaternion is the identity).
        dt: the time step between samples, shape ``(...)`` (one per sequence, broadcasting against
            ``q``'s batch shape; a Python number for all). For irregular samples pass ``dt=1`` and
            divide the result by the steps ``(..., T - 1, 1)``. Differences of timestamps: take them in
            float64 or integers before casting (see the documentation's note on time).
        frame: ``"body"`` (the default) or ``"space"``; anything else raises ``ValueError``.
        scalar_first: storage order of ``q``.

    Returns:
        Shape ``(..., T - 1, 3)`` (empty for ``T <= 1``). Where two samples are exactly a half-turn
        apart the rate takes ``quaternion_minus``'s sign and jumps there. A NaN or an infinity in a
        sequence makes all of its rates NaN (the sequence is one row).
    """


# The B-splines return three arrays; the backends run one core and split its packed result (one
# array, so that validation, dtypes and the rule for non-finite rows apply as to every function).


def _pack(xp: Any, *parts: Any) -> Any:
    """The parts ``(..., *trailing)`` flattened and concatenated along one last axis."""
    flat = [xp.reshape(p, (*p.shape[: p.ndim - t], math.prod(p.shape[p.ndim - t :]))) for p, t in parts]
    return xp.concat(flat, axis=-1)


@_bound("so3_bspline", control=(-1, 3, 3), u=())
def bound_so3_bspline(xp: Any, control: Any, u: Any, **options: Any) -> Any:
    rotation, omega, omega_dot = so3_bspline(xp, control, u, **options)
    return _pack(xp, (rotation, 2), (omega, 1), (omega_dot, 1))


@_bound("se3_bspline", control=(-1, 4, 4), u=())
def bound_se3_bspline(xp: Any, control: Any, u: Any, **options: Any) -> Any:
    pose, twist, twist_dot = se3_bspline(xp, control, u, **options)
    return _pack(xp, (pose[..., :3, :], 2), (twist, 1), (twist_dot, 1))


def split_so3_bspline(xp: Any, packed: Any) -> tuple[Any, Any, Any]:
    """``(rotation, omega, omega_dot)`` from ``bound_so3_bspline``'s ``(..., 15)``."""
    return xp.reshape(packed[..., :9], (*packed.shape[:-1], 3, 3)), packed[..., 9:12], packed[..., 12:]


def split_se3_bspline(xp: Any, packed: Any) -> tuple[Any, Any, Any]:
    """``(pose, twist, twist_dot)`` from ``bound_se3_bspline``'s ``(..., 24)``: the pose's bottom row
    ``(0, 0, 0, 1)``, NaN where the row is NaN (the rule for non-finite rows)."""
    top = xp.reshape(packed[..., :12], (*packed.shape[:-1], 3, 4))
    corner = top[..., :1, :1]
    return xp.concat([top, _bottom_row(xp, corner - corner)], axis=-2), packed[..., 12:18], packed[..., 18:]


# ---------------------------------------------------------------------------------------------------
# Eager forms of the rates (see ``_core``'s note on eager forms): the same products of quaternions as
# above, each one outer product contracted with constant Hamilton coefficients (one ``matmul``), the
# inverse by ``quaternion_invert``'s eager form. No selection or sign rides on the contractions.


def _rate_forms() -> tuple[Any, ...]:
    """The Hamilton coefficients (16, 4) (:func:`_algebra._hamilton_forms`), their vector part times 2
    (the rate ``2 vec(.)``: a power of two, exact), and the (12, 4) coefficients of ``q (0, v) / 2``
    (row ``3 i + j``: ``q_i v_j``) and of ``(0, v) q / 2`` (row ``3 i + j``: ``v_j q_i``)."""
    (c,) = _hamilton_forms()
    twice = [[2.0 * v for v in row[1:]] for row in c]
    body = [[0.5 * v for v in c[4 * i + j + 1]] for i in range(4) for j in range(3)]
    space = [[0.5 * v for v in c[4 * (j + 1) + i]] for i in range(4) for j in range(3)]
    return c, twice, body, space


def _bilinear(xp: Any, p: Any, q: Any, forms: Any) -> Any:
    """A bilinear map of ``p`` ``(..., m)`` and ``q`` ``(..., n)``: their outer product, flattened
    (row ``n i + j``: ``p_i q_j``), contracted with ``forms`` ``(m n, k)``."""
    return xp.matmul((p[..., :, None] * q[..., None, :]).flatten(-2), forms)


@eager_form(of=angular_velocity)
def angular_velocity_eager(
    xp: Any, q: Any, q_dot: Any, *, frame: str = "body", scalar_first: bool = True
) -> Any:
    """:func:`angular_velocity`, eager form: ``quaternion_invert``'s eager form, then the vector part of
    its product with ``q'`` times 2, one contraction."""
    body = check_frame("angular_velocity", frame)
    q, q_dot = match_rank(xp, q, q_dot)
    if not scalar_first:
        q, q_dot = xp.roll(q, 1, -1), xp.roll(q_dot, 1, -1)
    _, twice, _, _ = constants(xp, q, _rate_forms)
    inv = quaternion_invert_eager(xp, q)
    return _bilinear(xp, inv, q_dot, twice) if body else _bilinear(xp, q_dot, inv, twice)


@eager_form(of=quaternion_derivative)
def quaternion_derivative_eager(
    xp: Any, q: Any, omega: Any, *, frame: str = "body", scalar_first: bool = True
) -> Any:
    """:func:`quaternion_derivative`, eager form: ``q (0, w) / 2`` or ``(0, w) q / 2`` as one
    contraction of the outer product ``q w^T`` with constant coefficients."""
    body = check_frame("quaternion_derivative", frame)
    q, omega = match_rank(xp, q, omega)
    if not scalar_first:
        q = xp.roll(q, 1, -1)
    _, _, right, left = constants(xp, q, _rate_forms)
    out = _bilinear(xp, q, omega, right if body else left)
    return out if scalar_first else xp.roll(out, -1, -1)


@eager_form(of=angular_acceleration)
def angular_acceleration_eager(
    xp: Any, q: Any, q_dot: Any, q_ddot: Any, *, frame: str = "body", scalar_first: bool = True
) -> Any:
    """:func:`angular_acceleration`, eager form: ``a = q^-1 q'`` (or ``q' q^-1``) and ``2 vec(q^-1
    q'')`` as two contractions with the one inverse, then ``2 vec(q^-1 q'') - 4 a_w vec(a)``."""
    body = check_frame("angular_acceleration", frame)
    q, q_dot, q_ddot = match_rank(xp, q, q_dot, q_ddot)
    if not scalar_first:
        q, q_dot, q_ddot = xp.roll(q, 1, -1), xp.roll(q_dot, 1, -1), xp.roll(q_ddot, 1, -1)
    c, twice, _, _ = constants(xp, q, _rate_forms)
    inv = quaternion_invert_eager(xp, q)
    a = _bilinear(xp, inv, q_dot, c) if body else _bilinear(xp, q_dot, inv, c)
    cv = _bilinear(xp, inv, q_ddot, twice) if body else _bilinear(xp, q_ddot, inv, twice)
    return cv - (4.0 * a[..., :1]) * a[..., 1:]


def _exp_in_range_constants() -> tuple[Any, ...]:
    # 1, 0, and the first term of twice c2's series (see exp_in_range_cotangent)
    return 1.0, 0.0, -1 / 12


def exp_in_range(xp: Any, v: Any) -> tuple[Any, ...]:
    """The unit quaternion ``exp(v) = (cos(t / 2), sin(t / 2) v / t)`` (``t = |v|``, scalar first) of the
    rotation vectors ``v`` ``(..., 3)`` of :func:`integrate_angular_velocity`, eager form: the range
    reduction of :func:`_within_range` and the exponential in twenty-one operations, for a rule of
    its own (:func:`exp_in_range_cotangent`), so with no guard for autodiff's sake.

    Where not reduced, the values are ``quaternion_plus``'s eager exponential's (``_algebra._exp_eager``)
    bit for bit, except below its series' threshold, where ``cos`` and ``sin(t / 2) / t`` are as
    accurate (at ``t = 0``, ``0 / 0`` is read as its limit 1/2). Where reduced (``|v|^2 > max / 16``),
    the half-angle is ``fmod(|v c| / (2 c), 2 pi)`` and the direction that of ``v c`` (``c`` a power of
    two, :func:`_range`): the componentwise form's reduction, the same sum of squares to the bit.

    Returns ``(e, u, k, d2, small, big)``: ``e`` ``(..., 4)``, ``e = (cos h, k u)`` with ``u`` the vector
    ``v`` (``v c`` where reduced; ``(..., 3)``), ``d2 = |u|^2``, ``k = sin(h) / |u|``, and the masks
    ``small`` (below the series' threshold) and ``big`` (reduced), ``(..., 1)``: what the rule reads."""
    top, c = _range(float(xp.finfo(v.dtype).max))
    t2 = (v * v).sum(-1, keepdim=True)
    big = t2 > top
    small = t2 < series_threshold(xp, t2.dtype)
    angle = xp.sqrt(t2)
    scaled = v * c
    # the componentwise form's sum, to the bit: an ulp of |v| / 2 moves its remainder by any amount
    norm = xp.sqrt((scaled * scaled).sum(-1, keepdim=True))
    # 2 fmod(|v| / 2, 2 pi) = |v| mod 4 pi, as _within_range
    half = xp.where(big, xp.fmod(norm * (0.5 / c), 2.0 * math.pi), 0.5 * angle)
    d = xp.where(big, norm, angle)
    u = xp.where(big, scaled, v)
    # sin(0) / 0 = NaN only at v = 0, where u = 0 (k is read by the rule alone there): its limit 1/2.
    # A NaN row stays NaN: cos(NaN) in e's first entry, which every entry of the product reads.
    k = xp.nan_to_num(xp.sin(half) / d, nan=0.5)
    return xp.cat([xp.cos(half), k * u], -1), u, k, d * d, small, big


def exp_in_range_cotangent(
    xp: Any, v: Any, e: Any, u: Any, k: Any, d2: Any, small: Any, big: Any, ge: Any, *gaux: Any
) -> Any:
    """The cotangent of :func:`exp_in_range`'s input ``v`` from those of its outputs (None where not
    given: ``gu``, ``gk``, ``gd2`` only in the pass of a second derivative, which differentiates this).

    With ``u = s v`` (``s`` 1, or ``c`` where reduced), ``d = |u|`` and ``e = (w, vec)``: ``dw = -(k / 2)
    (u . dv)``, ``d vec = kt dv + c2 (u . dv) u``, ``dk = c2 (u . dv)``, ``d(d2) = 2 s (u . dv)``, ``du =
    s dv``, where ``kt = sin(h) / |v| = s k`` (below 2^-62 where reduced: 0 to rounding) and ``c2 =
    (w / 2 - kt) / d2``, whose series ``-1/24 + d2 / 960`` (next term ``d2^2 / 107520``) is taken below
    the threshold. So ``gv = kt gvec + u (c2 (u . gvec + gk) - (k / 2) gw + 2 s gd2) + s gu``: ten
    operations in a first derivative."""
    gu, gk, gd2, *_ = gaux
    one, zero, series = constants(xp, v, _exp_in_range_constants)
    kt = xp.where(big, zero, k)
    # 2 c2; the closed form divides by 1 where the series is taken (no 0 / 0 for a second derivative)
    closed = xp.add(e[..., :1], kt, alpha=-2) / xp.where(small, one, d2)
    c2 = xp.where(small, xp.add(series, d2, alpha=1 / 480), closed)
    # minus twice u's factor, and the rest
    minus, grad = 0.0, 0.0
    if ge is not None:
        gvec = ge[..., 1:]
        dot = (u * gvec).sum(-1, keepdim=True)
        minus = xp.addcmul(k * ge[..., :1], c2, dot if gk is None else dot + gk, value=-1)
        grad = kt * gvec
    elif gk is not None:
        minus = -c2 * gk
    if gd2 is not None or gu is not None:
        s = xp.where(big, _range(float(xp.finfo(v.dtype).max))[1] * one, one)
        if gd2 is not None:
            minus = minus - 4.0 * s * gd2
        if gu is not None:
            grad = grad + s * gu
    return xp.addcmul(grad, minus, u, value=-0.5) if ge is not None else grad - 0.5 * minus * u


def integrate_eager_with(exp: Callable[[Any], tuple[Any, ...]]) -> Callable[..., Any]:
    """:func:`integrate_angular_velocity`'s eager form with ``exp`` (``v -> (e, ...)``, torch's
    :func:`exp_in_range` with its rule, or without where no derivative is asked): ``omega dt``, its
    exponential, then ``quaternion_plus``'s unit quaternion and product (``_lie._unit_eager``,
    ``_lie._outer``), so below the range reduction and the series' threshold the result is
    ``quaternion_plus``'s eager one of ``omega dt`` bit for bit. A NaN or an infinity in ``q`` makes
    the whole unit quaternion NaN or one of its components, which every entry of the product reads; one
    in ``omega`` or ``dt`` makes ``cos(h)``, read by every entry, NaN: no rule for non-finite rows is
    needed after it."""

    def integrate_angular_velocity_eager(
        xp: Any, q: Any, omega: Any, dt: Any, *, frame: str = "body", scalar_first: bool = True
    ) -> Any:
        body = check_frame("integrate_angular_velocity", frame)
        omega, step = match_rank(xp, omega, dt[..., None])
        if not scalar_first:
            q = xp.roll(q, 1, -1)
        c, _, _, identity, one = constants(xp, q, _plus_constants)
        unit = _unit_eager(xp, q, identity, one)
        e = exp(omega * step)[0]
        out = _outer(xp, unit, e, c) if body else _outer(xp, e, unit, c)
        return out if scalar_first else xp.roll(out, -1, -1)

    return integrate_angular_velocity_eager


def _unit_constants() -> tuple[Any, ...]:
    return 1.0, 0.0


def _log_of_relative_constants() -> tuple[Any, ...]:
    # the weights of the canonical sign (_algebra._log_eager's), 1, the series' 1/6 and 4/3
    return [[8.0], [4.0], [2.0], [1.0]], 1.0, 1 / 6, 4 / 3


def log_of_relative(xp: Any, r: Any) -> tuple[Any, ...]:
    """The rotation vector (``quaternion_to_axis_angle``) of the relative rotations ``r`` ``(..., 4)``
    (scalar first) of :func:`angular_velocity_from_quaternions`, eager form, for a rule of its own
    (:func:`log_of_relative_cotangent`): ``_algebra._log_eager``'s canonical sign and factor ``g =
    2 atan2(s, w) / s`` (its series ``2 (1 + u / 6 + 3 u^2 / 40)`` in ``u = s^2`` below the threshold),
    with no guard for autodiff's sake, and no zero rule or division by the norm: ``r`` is a product of
    two unit quaternions (its norm 1 to rounding, which changes the vector by as much).

    Returns ``(phi, w, v, g, u, small, sign)``: ``phi = g v`` ``(..., 3)``, the canonical ``sign r =
    (w, v)``, ``g``, ``u = |v|^2``, ``u`` below the threshold, and ``sign`` (``(..., 1)`` each): what
    the rule reads."""
    weights, one, sixth, _ = constants(xp, r, _log_of_relative_constants)
    # the first non-zero component's sign (each weight exceeds the sum of those after it): exact
    sign = xp.sgn(xp.sgn(r) @ weights)
    canonical = r * sign
    w, v = canonical[..., :1], canonical[..., 1:]
    u = (v * v).sum(-1, keepdim=True)
    small = u < series_threshold(xp, u.dtype)
    series = xp.addcmul(one, u, xp.add(sixth, u, alpha=3 / 40))
    s = xp.sqrt(u)
    g = 2.0 * xp.where(small, series, xp.atan2(s, w) / s)
    return g * v, w, v, g, u, small, sign


def log_of_relative_cotangent(
    xp: Any, r: Any, phi: Any, w: Any, v: Any, g: Any, u: Any, small: Any, sign: Any, gphi: Any, *gaux: Any
) -> Any:
    """The cotangent of :func:`log_of_relative`'s input ``r`` from those of its outputs (None where not
    given: ``gw``, ``gv``, ``gg`` and ``gu`` only in the pass of a second derivative, which
    differentiates this).

    For ``|r| = 1``: ``phi = g v``, ``dg = sign (-2 dr_w + c v . dr_v)`` up to a multiple of ``r . dr``
    (``phi`` is blind to ``|r|``, and the unit quaternions ``r`` is made of see no such component) with
    ``c = (2 w - g) / u``, whose series is ``-4/3 - 2 u / 5`` (next term ``-3 u^2 / 14``) below the
    threshold; ``(dw, dv) = sign dr``, ``du = 2 sign v . dr_v``. So ``gr = sign (-2 a - 2 gg + gw, g
    gphi + (c a + c gg + 2 gu) v + gv)`` with ``a = v . gphi``: fourteen operations in a first
    derivative."""
    gw, gv, gg, gu, *_ = gaux
    _, one, _, four_thirds = constants(xp, r, _log_of_relative_constants)
    # -c; the closed form divides by 1 where the series is taken (no 0 / 0 for a second derivative)
    minus_c = xp.where(
        small, xp.add(four_thirds, u, alpha=0.4), xp.add(g, w, alpha=-2) / xp.where(small, one, u)
    )
    a = 0.0 if gphi is None else (v * gphi).sum(-1, keepdim=True)
    if gg is not None:
        a = a + gg
    # the scalar part's cotangent, and minus the factor of v (both before the sign)
    scalar = -2.0 * a
    factor = minus_c * a
    if gu is not None:
        factor = factor - 2.0 * gu
    if gw is not None:
        scalar = scalar + gw
    vector = -factor * v if gphi is None else xp.addcmul(g * gphi, factor, v, value=-1)
    if gv is not None:
        vector = vector + gv
    return xp.cat([scalar * sign, vector * sign], -1)


def angular_velocity_eager_with(log: Callable[[Any], tuple[Any, ...]]) -> Callable[..., Any]:
    """:func:`bound_angular_velocity_from_quaternions`'s eager form with ``log`` (``r -> (phi, ...)``,
    torch's :func:`log_of_relative` with its rule, or without where no derivative is asked): the
    componentwise form's unit quaternions and relative rotations (``_lie._unit``, ``_lie._product``:
    the same half-turn signs), each sample made unit once (the componentwise form makes the inner ones
    unit twice, to the same bits: the map is row by row), their logarithms divided by the step.

    The rule for non-finite rows by arithmetic (the sequence is one row): 0 times the sum of the
    samples' scalar parts (NaN where a sample holds a NaN or an infinity, which reaches its whole unit
    quaternion) and the step, added to every rate; a constant of differentiation, as
    ``_backend.nonfinite_rows``' sum, in four operations where that took six."""

    def angular_velocity_from_quaternions_eager(
        xp: Any, q: Any, dt: Any, *, frame: str = "body", scalar_first: bool = True
    ) -> Any:
        body = check_frame("angular_velocity_from_quaternions", frame)
        if not scalar_first:
            q = xp.roll(q, 1, -1)  # the very numbers _unit's reordering gives
        one, zero = constants(xp, q, _unit_constants)
        w, v = _unit(xp, q, True, one, zero)
        later = (w[..., 1:, :], v[..., 1:, :])
        inverse = (w[..., :-1, :], -v[..., :-1, :])
        relative = _product(inverse, later, xp) if body else _product(later, inverse, xp)
        rates, step = match_rank(xp, log(_join(xp, *relative, True))[0], dt[..., None, None])
        bad = (cancelling_factor(xp, w).sum(-2, keepdim=True) + cancelling_factor(xp, step)) * 0.0
        return rates / step + bad

    return angular_velocity_from_quaternions_eager


# ---------------------------------------------------------------------------------------------------
# Eager forms of SQUAD and the splines: the same compositions with the eager forms of their pieces
# (each gives its componentwise form's values and discrete choices: the knots' signs, the shortest
# arcs, the pivots of the logarithms), so the composites keep them too.


@eager_form(of=quaternion_squad)
def quaternion_squad_eager(xp: Any, q: Any, t: Any, *, scalar_first: bool = True) -> Any:
    """:func:`quaternion_squad`, eager form: the same knot signs (from the same dot products), then the
    eager forms of ``quaternion_minus``, ``quaternion_plus`` and ``quaternion_slerp``."""
    return _squad(xp, q, t, scalar_first, eager=True)


@eager_form(of=bound_so3_bspline)
def bound_so3_bspline_eager(
    xp: Any,
    control: Any,
    u: Any,
    *,
    order: int = 4,
    to_matrix: Conversion = unit_quaternion_to_matrix,
    to_quaternion: Conversion = matrix_to_quaternion,
) -> Any:
    """:func:`bound_so3_bspline`, eager form: the same increments and recursion, with the eager forms
    of ``matrix_to_axis_angle`` and ``axis_angle_to_matrix``."""
    count = _check_spline("so3_bspline", tuple(control.shape), 2, order)
    i, s = _segment(xp, u, count - order + 1)
    rotation, omega, omega_dot = _so3_bspline_at(
        xp, control, i, s, order, to_matrix, to_quaternion, eager=True
    )
    return _pack(xp, (rotation, 2), (omega, 1), (omega_dot, 1))


@eager_form(of=bound_se3_bspline)
def bound_se3_bspline_eager(
    xp: Any,
    control: Any,
    u: Any,
    *,
    order: int = 4,
    mode: str = "se3",
    to_matrix: Conversion = unit_quaternion_to_matrix,
    to_quaternion: Conversion = matrix_to_quaternion,
) -> Any:
    """:func:`bound_se3_bspline`, eager form: the same increments and recursion, with the eager forms
    of ``se3_minus``, ``se3_exp`` and ``se3_compose`` (``mode="split"``: of ``so3_bspline``'s
    pieces)."""
    pose, twist, twist_dot = _se3_bspline(xp, control, u, order, mode, to_matrix, to_quaternion, eager=True)
    return _pack(xp, (pose[..., :3, :], 2), (twist, 1), (twist_dot, 1))
