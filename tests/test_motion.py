"""Rotations in time (diffquat._motion), on the core functions directly (``xp = numpy``; torch float64
for derivatives, jax under ``jit`` for its transforms): the properties here hold of the formulas, which
every backend binds unchanged (the shared table, tests/cases.py, checks the bound functions' values,
derivatives and paths against independent references):

- conventions against independent oracles: scipy's ``RotationSpline`` rates (body frame: a C2 spline
  cubic in rotation vectors, not a B-spline, so what is compared is the *definition* of the rates:
  ``angular_velocity`` and ``angular_acceleration`` of the spline's own quaternions and their
  derivatives, taken by 7-point stencils within a segment, against the spline's analytic rates);
  scipy's composition for rates from samples, and ``Slerp`` for SQUAD on a geodesic;
- exact cases: a constant-rate trajectory ``q0 exp(t w)`` and a B-spline whose control points lie
  equally spaced on one geodesic (rate ``w``, acceleration 0); a non-unit, time-varying norm;
- the B-splines' rates against central differences in time of their own rotation and rate, the
  space frame (``w_s' = R w_b'``), C^(k-2) continuity across segments (left and right limits
  computed exactly), invariance under a constant left rotation, batching, clamping;
- SQUAD through its knots, C1 at them, its sign consistency, slerp on a geodesic;
- rates from samples: sign flips between samples change nothing, round trip with the integrator;
- derivatives against central finite differences in float64 (torch ``gradcheck``), at random control
  points and at a static trajectory (zero increments), and jax's ``jacfwd == jacrev``.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np
import pytest
import torch
from conftest import Backend
from scipy.spatial.transform import Rotation, RotationSpline, Slerp

from diffquat import _motion as m
from diffquat._lie import so3_exp, so3_vee
from diffquat._se3 import se3_exp, se3_inverse, se3_vee
from diffquat.jax._namespace import XP as JXP

RNG_SEED = 20240533


def _rng(salt: int = 0) -> np.random.Generator:
    return np.random.default_rng(RNG_SEED + salt)


def _unit(q: np.ndarray) -> np.ndarray:
    return q / np.linalg.norm(q, axis=-1, keepdims=True)


def _qmul(p: np.ndarray, q: np.ndarray) -> np.ndarray:
    """Hamilton product, scalar first, written out here as the tests' own reference."""
    pw, pv = p[..., :1], p[..., 1:]
    qw, qv = q[..., :1], q[..., 1:]
    return np.concatenate(
        [pw * qw - np.sum(pv * qv, -1, keepdims=True), pw * qv + qw * pv + np.cross(pv, qv)], -1
    )


def _qexp(v: np.ndarray) -> np.ndarray:
    return Rotation.from_rotvec(v.reshape(-1, 3)).as_quat(scalar_first=True).reshape(*v.shape[:-1], 4)


def _matrix(q: np.ndarray) -> np.ndarray:
    return Rotation.from_quat(q.reshape(-1, 4), scalar_first=True).as_matrix().reshape(*q.shape[:-1], 3, 3)


def _same_rotation(p: np.ndarray, q: np.ndarray) -> np.ndarray:
    """| |<p, q>| - 1 | of unit quaternions: 0 where they are one rotation."""
    return np.abs(np.abs(np.sum(_unit(p) * _unit(q), axis=-1)) - 1.0)


def _vee_rate(r: np.ndarray, dr: np.ndarray) -> np.ndarray:
    return so3_vee(np, np.swapaxes(r, -1, -2) @ dr)


def _random_control(n: int, salt: int, scale: float = 0.6) -> np.ndarray:
    """n rotation matrices, consecutive ones well below a half-turn apart."""
    steps = _rng(salt).normal(size=(n, 3)) * scale
    return so3_exp(np, np.cumsum(steps, axis=0))


def _random_poses(n: int, salt: int) -> np.ndarray:
    return se3_exp(np, np.cumsum(_rng(salt).normal(size=(n, 6)) * 0.6, axis=0))


def _interior(u: np.ndarray, margin: float) -> np.ndarray:
    """The parameters at least ``margin`` from every integer (segment boundary)."""
    return u[np.abs(u - np.round(u)) > margin]


SPLINES = {"so3": (m.so3_bspline, _random_control), "se3": (m.se3_bspline, _random_poses)}


# ---------------------------------------------------------------------------------------------------
# Rates of a quaternion trajectory


def test_rates_match_scipy_rotation_spline_body_frame() -> None:
    times = np.array([0.0, 0.7, 1.5, 2.0, 3.1, 4.0])
    spline = RotationSpline(times, Rotation.from_rotvec(_rng(1).normal(size=(6, 3))))
    h = 5e-3
    t = np.linspace(0.05, 3.95, 60)
    t = t[np.min(np.abs(t[:, None] - times[None]), axis=1) > 4 * h]  # stencils within one segment
    q0 = spline(t).as_quat(scalar_first=True)

    def sample(k: int) -> np.ndarray:
        q = spline(t + k * h).as_quat(scalar_first=True)
        return q * np.sign(np.sum(q * q0, axis=-1))[:, None]  # scipy's sign is canonical, not smooth

    f = {k: sample(k) for k in range(-3, 4)}
    q_dot = (-f[-3] + 9 * f[-2] - 45 * f[-1] + 45 * f[1] - 9 * f[2] + f[3]) / (60 * h)
    q_ddot = (2 * f[-3] - 27 * f[-2] + 270 * f[-1] - 490 * f[0] + 270 * f[1] - 27 * f[2] + 2 * f[3]) / (
        180 * h * h
    )
    omega = m.angular_velocity(np, q0, q_dot)
    np.testing.assert_allclose(omega, spline(t, 1), rtol=0, atol=1e-9)
    np.testing.assert_allclose(m.angular_acceleration(np, q0, q_dot, q_ddot), spline(t, 2), rtol=0, atol=1e-9)
    # the space frame is not scipy's: it differs by R
    space = m.angular_velocity(np, q0, q_dot, frame="space")
    np.testing.assert_allclose(space, np.einsum("...ij,...j->...i", _matrix(q0), spline(t, 1)), atol=1e-9)
    assert np.abs(space - spline(t, 1)).max() > 0.1


def _constant_rate(t: np.ndarray, w: np.ndarray, q0: np.ndarray) -> tuple[np.ndarray, ...]:
    """q0 exp(t w) and its exact first and second derivatives."""
    q = _qmul(q0, _qexp(t[:, None] * w))
    pure = np.concatenate([[0.0], w])
    q_dot = 0.5 * _qmul(q, pure)
    q_ddot = 0.5 * _qmul(q_dot, pure)
    return q, q_dot, q_ddot


def test_constant_rate_trajectory_has_its_rate_and_no_acceleration() -> None:
    w, q0 = np.array([0.4, -1.3, 2.2]), _unit(_rng(2).normal(size=4))
    t = np.linspace(-3.0, 3.0, 25)
    q, q_dot, q_ddot = _constant_rate(t, w, q0)
    np.testing.assert_allclose(m.angular_velocity(np, q, q_dot), np.broadcast_to(w, (25, 3)), atol=1e-14)
    np.testing.assert_allclose(m.angular_acceleration(np, q, q_dot, q_ddot), 0.0, atol=1e-14)
    # space frame: w_s = R w, constant only as R turns about w itself; its rate R w' = 0
    ws = m.angular_velocity(np, q, q_dot, frame="space")
    np.testing.assert_allclose(ws, _matrix(q) @ w, atol=1e-14)
    np.testing.assert_allclose(m.angular_acceleration(np, q, q_dot, q_ddot, frame="space"), 0.0, atol=1e-14)
    # scalar last: the same numbers reordered
    last = [np.roll(x, -1, axis=-1) for x in (q, q_dot, q_ddot)]
    np.testing.assert_allclose(
        m.angular_velocity(np, *last[:2], scalar_first=False), m.angular_velocity(np, q, q_dot)
    )


def test_non_unit_quaternions_give_the_rates_of_their_rotation() -> None:
    """q~(t) = c(t) q(t): the same rotation, so the same rates, whatever c, c' and c''."""
    rng = _rng(3)
    q = _unit(rng.normal(size=(50, 4)))
    q_dot, q_ddot = rng.normal(size=(50, 4)), rng.normal(size=(50, 4))
    q_dot -= np.sum(q_dot * q, -1, keepdims=True) * q  # a unit trajectory: q . q' = 0
    q_ddot -= (np.sum(q_ddot * q, -1, keepdims=True) + np.sum(q_dot * q_dot, -1, keepdims=True)) * q
    c, c1, c2 = (rng.uniform(0.1, 10.0, size=(50, 1)), rng.normal(size=(50, 1)), rng.normal(size=(50, 1)))
    scaled = (c * q, c1 * q + c * q_dot, c2 * q + 2 * c1 * q_dot + c * q_ddot)
    for frame in ("body", "space"):
        w = m.angular_velocity(np, q, q_dot, frame=frame)
        a = m.angular_acceleration(np, q, q_dot, q_ddot, frame=frame)
        np.testing.assert_allclose(m.angular_velocity(np, *scaled[:2], frame=frame), w, atol=1e-12)
        np.testing.assert_allclose(m.angular_acceleration(np, *scaled, frame=frame), a, atol=1e-11)
    # for unit q the textbook 2 vec(q* q'') (body)
    np.testing.assert_allclose(
        m.angular_acceleration(np, q, q_dot, q_ddot),
        2 * _qmul(q * [1, -1, -1, -1], q_ddot)[:, 1:],
        atol=1e-13,
    )
    # the zero quaternion reads as the identity's zero rate
    zero = np.zeros(4)
    assert np.all(m.angular_velocity(np, zero, q_dot[0]) == 0)
    assert np.all(m.angular_acceleration(np, zero, q_dot[0], q_ddot[0]) == 0)


@pytest.mark.parametrize("frame", ["body", "space"])
def test_quaternion_derivative_inverts_angular_velocity(frame: str) -> None:
    rng = _rng(4)
    q = rng.normal(size=(40, 4)) * rng.uniform(0.01, 100.0, size=(40, 1))
    w = rng.normal(size=(40, 3))
    q_dot = m.quaternion_derivative(np, q, w, frame=frame)
    np.testing.assert_allclose(np.sum(q * q_dot, -1), 0.0, atol=1e-10)  # keeps the norm
    np.testing.assert_allclose(m.angular_velocity(np, q, q_dot, frame=frame), w, atol=1e-12)
    # it is the time derivative of the exact integrator at dt = 0 (unit q)
    qu = _unit(q)
    h = 1e-6
    fd = (
        m.integrate_angular_velocity(np, qu, w, np.asarray(h), frame=frame)
        - m.integrate_angular_velocity(np, qu, w, np.asarray(-h), frame=frame)
    ) / (2 * h)
    np.testing.assert_allclose(fd, m.quaternion_derivative(np, qu, w, frame=frame), atol=1e-8)


def test_space_rates_are_the_body_rates_rotated() -> None:
    """w_s = R w_b and w_s' = R w_b', for any q (any norm), q' and q''."""
    rng = _rng(5)
    q, q_dot, q_ddot = rng.normal(size=(3, 30, 4))
    r = _matrix(_unit(q))
    for fn, args in ((m.angular_velocity, (q, q_dot)), (m.angular_acceleration, (q, q_dot, q_ddot))):
        body, space = fn(np, *args), fn(np, *args, frame="space")
        np.testing.assert_allclose(space, np.einsum("nij,nj->ni", r, body), atol=1e-12)


def test_frame_must_be_body_or_space() -> None:
    q = np.array([1.0, 0, 0, 0])
    for call in (
        lambda: m.angular_velocity(np, q, q, frame="world"),
        lambda: m.quaternion_derivative(np, q, q[1:], frame="world"),
        lambda: m.angular_acceleration(np, q, q, q, frame="world"),
        lambda: m.integrate_angular_velocity(np, q, q[1:], np.asarray(1.0), frame="world"),
        lambda: m.angular_velocity_from_quaternions(np, q[None], np.asarray(1.0), frame="world"),
    ):
        with pytest.raises(ValueError, match="expected frame to be 'body' or 'space', got 'world'"):
            call()


# ---------------------------------------------------------------------------------------------------
# Integration and rates from samples


@pytest.mark.parametrize("frame", ["body", "space"])
def test_rates_from_samples_are_exact_and_blind_to_sign_flips(frame: str) -> None:
    rng = _rng(6)
    q0 = _unit(rng.normal(size=(3, 4)))
    w = rng.normal(size=(3, 3))
    dt = rng.uniform(0.05, 0.4, size=(3, 11))
    # integrate a piecewise-constant rate (one rate per sequence, per-interval steps)
    samples = [q0]
    for k in range(11):
        samples.append(m.integrate_angular_velocity(np, samples[-1], w, dt[:, k], frame=frame))
    q = np.stack(samples, axis=-2)  # (3, 12, 4)
    rates = m.angular_velocity_from_quaternions(np, q, dt, frame=frame)
    assert rates.shape == (3, 11, 3)
    np.testing.assert_allclose(rates, np.broadcast_to(w[:, None], rates.shape), atol=1e-12)
    # random sign flips and norms between samples change nothing
    flips = rng.choice([-1.0, 1.0], size=(3, 12, 1)) * rng.uniform(0.1, 10.0, size=(3, 12, 1))
    np.testing.assert_allclose(
        m.angular_velocity_from_quaternions(np, q * flips, dt, frame=frame), rates, atol=1e-12
    )
    # the round trip: integrating each rate over its step lands on the next sample
    again = m.integrate_angular_velocity(np, q[:, :-1], rates, dt, frame=frame)
    assert _same_rotation(again, q[:, 1:]).max() < 1e-14


def test_rates_from_samples_against_scipy_and_shared_step() -> None:
    rng = _rng(7)
    rots = Rotation.from_rotvec(np.cumsum(rng.normal(size=(9, 3)) * 0.5, axis=0))
    q = rots.as_quat(scalar_first=False)
    expected = (rots[:-1].inv() * rots[1:]).as_rotvec() / 0.1
    got = m.angular_velocity_from_quaternions(np, q, np.asarray(0.1), scalar_first=False)
    np.testing.assert_allclose(got, expected, atol=1e-12)
    space = (rots[1:] * rots[:-1].inv()).as_rotvec() / 0.1
    np.testing.assert_allclose(
        m.angular_velocity_from_quaternions(np, q, np.asarray(0.1), frame="space", scalar_first=False),
        space,
        atol=1e-12,
    )
    assert m.angular_velocity_from_quaternions(np, q[:1], np.asarray(0.1)).shape == (0, 3)


# ---------------------------------------------------------------------------------------------------
# SQUAD


def _knots(n: int, salt: int) -> np.ndarray:
    """Random knots with random signs and norms, consecutive ones well below a half-turn apart."""
    rng = _rng(salt)
    q = _qexp(np.cumsum(rng.normal(size=(n, 3)) * 0.7, axis=0))
    return q * rng.choice([-1.0, 1.0], size=(n, 1)) * rng.uniform(0.5, 2.0, size=(n, 1))


def test_squad_passes_through_its_knots_with_consistent_signs() -> None:
    q = _knots(6, 8)
    out = m.quaternion_squad(np, q, np.arange(6.0))
    assert _same_rotation(out, q).max() < 1e-14
    np.testing.assert_allclose(np.linalg.norm(out, axis=-1), 1.0, atol=1e-15)
    assert np.all(np.sum(out[1:] * out[:-1], axis=-1) > 0)  # each in the hemisphere of the one before
    np.testing.assert_allclose(out[0], _unit(q[0]), atol=1e-15)
    # continuous as a quaternion across each knot, not only as a rotation
    e = 1e-9
    t = np.arange(1.0, 5.0)
    np.testing.assert_allclose(m.quaternion_squad(np, q, t - e), m.quaternion_squad(np, q, t + e), atol=1e-8)
    # scalar last
    np.testing.assert_allclose(
        m.quaternion_squad(np, np.roll(q, -1, axis=-1), np.array([0.3, 2.5]), scalar_first=False),
        np.roll(m.quaternion_squad(np, q, np.array([0.3, 2.5])), -1, axis=-1),
        atol=1e-15,
    )


def test_squad_is_c1_at_its_knots() -> None:
    q = _knots(5, 9)
    h = 1e-6
    for k in (1.0, 2.0, 3.0):
        at = m.quaternion_squad(np, q, np.asarray(k))
        left = m.angular_velocity(np, at, (at - m.quaternion_squad(np, q, np.asarray(k - h))) / h)
        right = m.angular_velocity(np, at, (m.quaternion_squad(np, q, np.asarray(k + h)) - at) / h)
        np.testing.assert_allclose(left, right, atol=1e-5)


def test_squad_on_a_geodesic_is_slerp() -> None:
    rng = _rng(10)
    q0, w = _unit(rng.normal(size=4)), np.array([0.5, -0.9, 0.3])
    knots = _qmul(q0, _qexp(np.arange(5.0)[:, None] * w))
    knots = knots * np.array([1.0, -1.0, -1.0, 1.0, -1.0])[:, None]
    t = np.linspace(0.0, 4.0, 33)
    out = m.quaternion_squad(np, knots, t)
    assert _same_rotation(out, _qmul(q0, _qexp(t[:, None] * w))).max() < 1e-14
    scipy = Slerp(np.arange(5.0), Rotation.from_quat(knots, scalar_first=True))(t).as_quat(scalar_first=True)
    assert _same_rotation(out, scipy).max() < 1e-14


def test_squad_clamps_broadcasts_and_is_left_invariant() -> None:
    q = np.stack([_knots(4, 11), _knots(4, 12)])  # (2, 4, 4)
    t = np.array([[-1.0], [0.4], [2.6], [3.0], [7.0]])  # (5, 1) against a batch of 2
    out = m.quaternion_squad(np, q, t)
    assert out.shape == (5, 2, 4)
    for b in range(2):
        np.testing.assert_allclose(out[:, b], m.quaternion_squad(np, q[b], t[:, 0]), atol=0)
    assert _same_rotation(out[0], q[:, 0]).max() < 1e-14 and _same_rotation(out[-1], q[:, -1]).max() < 1e-14
    g = _unit(_rng(13).normal(size=4))
    assert _same_rotation(m.quaternion_squad(np, _qmul(g, q), t), _qmul(g, out)).max() < 1e-14
    with pytest.raises(ValueError, match="at least 2 knots"):
        m.quaternion_squad(np, q[:, :1], t)
    assert np.all(np.isnan(m.quaternion_squad(np, q[0], np.array([np.nan]))))


# ---------------------------------------------------------------------------------------------------
# Cumulative B-splines


def test_cumulative_basis() -> None:
    np.testing.assert_array_equal(
        np.array(m._cumulative_basis(4), dtype=float) * 6,
        [[6, 0, 0, 0], [5, 3, -3, 1], [1, 3, 3, -2], [0, 0, 0, 1]],
    )
    for k in range(2, 8):
        basis = m._cumulative_basis(k)
        assert basis[0] == [1] + [0] * (k - 1)
        # B~_j(1) on a segment is B~_j-1(0) on the next: sum of the coefficients against the constant
        for j in range(1, k):
            assert sum(basis[j]) == basis[j - 1][0]


@pytest.mark.parametrize("order", [2, 3, 4, 5])
def test_bspline_on_a_geodesic_is_the_constant_rate_motion(order: int) -> None:
    r0, w = _random_control(1, 14)[0], np.array([0.3, 0.8, -0.5])
    control = r0 @ so3_exp(np, np.arange(8.0)[:, None] * w)
    u = np.linspace(0.0, 8 - order + 1, 29)
    rotation, omega, omega_dot = m.so3_bspline(np, control, u, order=order)
    # a B-spline of equally spaced points is the same motion, delayed by (order - 2) / 2 control steps
    expected = r0 @ so3_exp(np, (u + (order - 2) / 2)[:, None] * w)
    np.testing.assert_allclose(rotation, expected, atol=1e-14)
    np.testing.assert_allclose(omega, np.broadcast_to(w, omega.shape), atol=1e-14)
    np.testing.assert_allclose(omega_dot, 0.0, atol=1e-14)


@pytest.mark.parametrize("order", [3, 4, 5])
@pytest.mark.parametrize("group", ["so3", "se3"])
def test_bspline_rates_are_the_time_derivatives(group: str, order: int) -> None:
    fn, make = SPLINES[group]
    control = make(9, 15)
    u = _interior(np.linspace(0.0, 9 - order + 1, 61)[1:-1], 1e-3)
    h = 1e-5
    x, rate, accel = fn(np, control, u, order=order)
    xp_, rate_p, _ = fn(np, control, u + h, order=order)
    xm, rate_m, _ = fn(np, control, u - h, order=order)
    if group == "so3":
        fd = _vee_rate(x, (xp_ - xm) / (2 * h))
    else:
        fd = se3_vee(np, se3_inverse(np, x) @ ((xp_ - xm) / (2 * h)))
    np.testing.assert_allclose(rate, fd, atol=1e-9)
    np.testing.assert_allclose(accel, (rate_p - rate_m) / (2 * h), atol=1e-9)
    if group == "so3":
        # space frame: d/du (R w_b) = R w_b'
        space_p, space_m = xp_ @ rate_p[..., None], xm @ rate_m[..., None]
        np.testing.assert_allclose(
            (x @ accel[..., None])[..., 0], ((space_p - space_m) / (2 * h))[..., 0], atol=3e-9
        )
    else:
        np.testing.assert_allclose(x[..., 3, :], np.broadcast_to([0.0, 0, 0, 1], (len(u), 4)), atol=0)


@pytest.mark.parametrize("order", [3, 4, 5])
@pytest.mark.parametrize("group", ["so3", "se3"])
def test_bspline_is_continuous_across_segments(group: str, order: int) -> None:
    """Segment i - 1 at s = 1 (the end of the spline over the first i + order - 1 control points) against
    segment i at s = 0: the value and the rate agree for every order >= 3, the acceleration from order
    4 on (C^(k-2)), to rounding."""
    fn, make = SPLINES[group]
    control = make(9, 16)
    for i in range(1, 9 - order + 1):
        left = fn(np, control[: i + order - 1], np.asarray(float(i)), order=order)
        right = fn(np, control, np.asarray(float(i)), order=order)
        np.testing.assert_allclose(left[0], right[0], atol=1e-14)
        np.testing.assert_allclose(left[1], right[1], atol=1e-13)
        if order >= 4:
            np.testing.assert_allclose(left[2], right[2], atol=1e-13)
        else:
            assert np.abs(left[2] - right[2]).max() > 1e-3  # order 3 is C1 only


@pytest.mark.parametrize("group", ["so3", "se3"])
def test_bspline_is_invariant_under_a_left_transform(group: str) -> None:
    fn, make = SPLINES[group]
    control = make(7, 17)
    g = make(1, 18)[0] if group == "so3" else se3_exp(np, np.array([1.0, -2.0, 0.5, 0.9, -0.4, 2.1]))
    u = np.linspace(0.0, 4.0, 21)
    x, rate, accel = fn(np, control, u)
    gx, g_rate, g_accel = fn(np, g @ control, u)
    np.testing.assert_allclose(gx, g @ x, atol=1e-13)
    np.testing.assert_allclose(g_rate, rate, atol=1e-13)
    np.testing.assert_allclose(g_accel, accel, atol=1e-12)


@pytest.mark.parametrize("group", ["so3", "se3"])
def test_bspline_batches_clamps_and_checks(group: str) -> None:
    fn, make = SPLINES[group]
    control = np.stack([make(6, 19), make(6, 20)])  # (2, 6, n, n)
    u = np.array([[-2.0], [0.0], [1.7], [3.0], [9.0]])  # (5, 1): (5, 2) evaluations
    x, rate, accel = fn(np, control, u)
    assert x.shape == (5, 2, *control.shape[-2:]) and rate.shape == accel.shape == (5, 2, rate.shape[-1])
    for b in range(2):
        one = fn(np, control[b], u[:, 0])
        for got, want in zip((x, rate, accel), one, strict=True):
            np.testing.assert_array_equal(got[:, b], want)
    # outside [0, K - order + 1]: the value and the rates at the nearest end, held
    for got in (x, rate, accel):
        np.testing.assert_array_equal(got[0], got[1])
        np.testing.assert_array_equal(got[-1], got[-2])
    nan = fn(np, control[0], np.array([np.nan, 1.0]))
    # a NaN parameter: NaN values (the pose's top rows: its bottom row is exact), never an index error
    assert np.all(np.isnan(nan[0][0, :3])) and np.all(np.isnan(nan[1][0])) and np.all(np.isnan(nan[2][0]))
    assert all(np.all(np.isfinite(a[1])) for a in nan)
    with pytest.raises(ValueError, match="at least order = 4 control points"):
        fn(np, control[:, :3], u)
    with pytest.raises(ValueError, match="expected order >= 2"):
        fn(np, control, u, order=1)


def test_se3_bspline_with_equal_translations_is_the_so3_bspline() -> None:
    rotations = _random_control(7, 21)
    poses = np.tile(np.eye(4), (7, 1, 1))
    poses[:, :3, :3] = rotations
    u = np.linspace(0.0, 4.0, 17)
    pose, twist, twist_dot = m.se3_bspline(np, poses, u)
    rotation, omega, omega_dot = m.so3_bspline(np, rotations, u)
    np.testing.assert_allclose(pose[:, :3, :3], rotation, atol=1e-14)
    np.testing.assert_allclose(pose[:, :3, 3], 0.0, atol=1e-14)
    np.testing.assert_allclose(twist, np.concatenate([0 * omega, omega], -1), atol=1e-14)
    np.testing.assert_allclose(twist_dot, np.concatenate([0 * omega, omega_dot], -1), atol=1e-13)


def test_bspline_near_half_turn_increments() -> None:
    """Increments up to 3.1 rad (below pi, as documented): finite, and the rates still the derivatives."""
    axis = np.array([0.48, -0.6, 0.64])
    control = so3_exp(np, np.cumsum(np.array([0.0, 3.1, 3.0, 3.1, 2.9, 3.1])[:, None] * axis, 0))
    control = control @ so3_exp(np, _rng(22).normal(size=(6, 3)) * 0.05)
    u = _interior(np.linspace(0.0, 3.0, 31), 1e-3)
    h = 1e-6
    rotation, omega, omega_dot = m.so3_bspline(np, control, u)
    assert np.all(np.isfinite(omega)) and np.all(np.isfinite(omega_dot))
    fd = _vee_rate(
        rotation, (m.so3_bspline(np, control, u + h)[0] - m.so3_bspline(np, control, u - h)[0]) / (2 * h)
    )
    np.testing.assert_allclose(omega, fd, atol=1e-7)


# ---------------------------------------------------------------------------------------------------
# Derivatives


def _gradcheck(fn: Callable[..., Any], *inputs: np.ndarray, fast: bool = False) -> None:
    """torch's ``gradcheck`` in float64: the Jacobian of ``fn`` against central differences (``fast``:
    its projection on random vectors, one backward pass instead of one per output entry)."""
    args = tuple(torch.tensor(x, dtype=torch.float64, requires_grad=True) for x in inputs)
    assert torch.autograd.gradcheck(fn, args, atol=1e-7, rtol=1e-6, fast_mode=fast)


# In the control points: the ends of the clamp and a segment boundary. In u: away from segment
# boundaries (the acceleration of a cubic is only C0 in u there: its u-derivative jumps) and from
# the clamp (a kink).
U_CONTROL = np.array([0.0, 0.3, 1.0, 2.999, 3.0])
U_TIME = np.array([0.3, 1.55, 2.4])


@pytest.mark.parametrize("static", [False, True], ids=["random", "static"])
@pytest.mark.parametrize("group", ["so3", "se3"])
def test_bspline_gradients_match_finite_differences(group: str, static: bool) -> None:
    """Control points as exp of tangent vectors (so that every perturbation stays on the group), at a
    random trajectory and at a static one (all increments zero: the logarithms' series)."""
    size = 3 if group == "so3" else 6
    tangents = np.zeros((6, size)) + 0.3 if static else _rng(23).normal(size=(6, size)) * 0.6
    exp = so3_exp if group == "so3" else se3_exp
    fn = SPLINES[group][0]

    def spline(v: torch.Tensor, u: torch.Tensor) -> tuple[torch.Tensor, ...]:
        out: tuple[torch.Tensor, ...] = fn(torch, exp(torch, v), u)
        return out

    fixed = torch.tensor(U_CONTROL, dtype=torch.float64)
    _gradcheck(lambda v: spline(v, fixed), tangents, fast=group == "se3" or static)
    _gradcheck(spline, tangents, U_TIME, fast=True)
    if static:  # the rates of a static trajectory are exactly zero
        _, rate, accel = spline(torch.tensor(tangents), fixed)
        assert torch.all(rate == 0) and torch.all(accel == 0)


def test_float32_gradients_are_finite_at_a_static_trajectory() -> None:
    control = torch.tensor(np.tile(np.eye(3), (5, 1, 1)), dtype=torch.float32, requires_grad=True)
    u = torch.tensor([0.0, 0.5, 1.0, 2.0], requires_grad=True)
    rotation, omega, omega_dot = m.so3_bspline(torch, control, u)
    (rotation.sum() + omega.sum() + omega_dot.sum()).backward()
    assert control.grad is not None and u.grad is not None
    assert torch.all(torch.isfinite(control.grad)) and torch.all(torch.isfinite(u.grad))


def test_squad_and_rate_gradients_match_finite_differences() -> None:
    # t at a knot is fine (SQUAD is C1); not at the clamp's kink
    _gradcheck(lambda q, t: m.quaternion_squad(torch, q, t), _knots(5, 24), np.array([0.2, 1.0, 1.5, 3.7]))
    samples = _knots(5, 25)
    _gradcheck(lambda q, dt: m.angular_velocity_from_quaternions(torch, q, dt), samples, np.full(4, 0.1))
    rng = _rng(26)
    _gradcheck(
        lambda q, w, dt: m.integrate_angular_velocity(torch, q, w, dt, frame="space"),
        rng.normal(size=(2, 4)),
        rng.normal(size=(2, 3)),
        np.array([0.1, 2.0]),
    )
    _gradcheck(
        lambda q, a, b: m.angular_acceleration(torch, q, a, b, frame="space"), *rng.normal(size=(3, 4, 4))
    )


def test_jax_jit_and_reverse_mode() -> None:
    """Under ``jit`` (no Python branch on values; jax's gather), the values are numpy's and the
    reverse-mode Jacobian in the control points is the central difference of numpy's values."""
    tangents = _rng(27).normal(size=(6, 3)) * 0.6
    u = np.array([0.3, 1.0, 2.999])

    def spline(xp: Any, v: Any) -> Any:
        return xp.concatenate([p.reshape(-1) for p in m.so3_bspline(xp, so3_exp(xp, v), xp.asarray(u))])

    def with_values(v: jax.Array) -> tuple[jax.Array, jax.Array]:
        out = spline(JXP, v)
        return out, out

    jacobian, values = jax.jit(jax.jacrev(with_values, has_aux=True))(jnp.asarray(tangents))
    np.testing.assert_allclose(np.asarray(values), spline(np, tangents), atol=1e-14)
    jacobian = np.asarray(jacobian)
    h = 1e-6
    for k in range(tangents.size):
        e = np.zeros(tangents.size)
        e[k] = h
        fd = (spline(np, tangents + e.reshape(6, 3)) - spline(np, tangents - e.reshape(6, 3))) / (2 * h)
        np.testing.assert_allclose(jacobian[:, k // 3, k % 3], fd, atol=1e-8)


@pytest.mark.parametrize("precision", ["float32", "float64"])
def test_integrate_angular_velocity_at_huge_angles(backend: Backend, precision: str) -> None:
    """|w dt| from 1 to the largest finite number: a finite unit quaternion whose vector part lies
    along w (its sign the angle's choice), on every backend; once NaN from 1.8e19 rad in float32
    (the angle's square overflowed). Below sqrt(max) / 4 the result is quaternion_plus's of w dt bit
    for bit; beyond it only the axis is meaningful (the rounding of w dt has lost every turn), which
    is what is checked."""
    eps, top = float(np.finfo(precision).eps), float(np.finfo(precision).max)
    middle = (1e18, 1e19, 1e30) if precision == "float32" else (1e150, 1e160, 1e300)
    dts = np.array([1.0, *middle, 0.9 * top, top])
    w = np.array([0.3, -0.5, 1.0])  # largest component 1: w dt stays finite up to dt = max
    dq = backend.module
    q, omega, dt = (
        backend.array(x, precision)
        for x in (np.tile([1.0, 0.0, 0.0, 0.0], (len(dts), 1)), np.tile(w, (len(dts), 1)), dts)
    )
    out = backend.to_numpy(dq.integrate_angular_velocity(q, omega, dt))
    assert np.all(np.isfinite(out))
    np.testing.assert_allclose(np.linalg.norm(out, axis=-1), 1.0, rtol=0, atol=4 * eps)
    axis = w / np.linalg.norm(w)
    assert np.abs(np.cross(out[:, 1:], axis)).max() <= 8 * eps
    plain = backend.to_numpy(dq.quaternion_plus(q[:2], omega[:2] * dt[:2, None]))
    np.testing.assert_array_equal(out[:2], plain)
