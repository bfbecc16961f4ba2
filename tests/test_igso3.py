"""IGSO(3) beyond the shared table (tests/cases.py has its row, sigma from 0.3 to 10): values and
derivatives from sigma = 1e-4 on, against the 50-digit reference and its own derivatives
(``mpmath.diff``), far into the tail (f = 1e-300 and far below); the score in float64 and float32,
relative to its size and its inputs' rounding (``score_reference``), near pi too; the limits sigma ->
infinity (Haar) and sigma -> 0 (the Gaussian); the two forms of the reference against each other; the
total mass; the documented edge cases (negative, zero and tiny sigma, large sigma, angles beyond pi).

Errors are measured against the size of log f's terms (``cases.igso3_scale``): where log f crosses 0
its terms cancel, and a relative error there would measure the cancellation, not the computation.
The bounds are in units of the dtype's epsilon times that size: log f is a sum of five terms, each
computed to an ulp or two of its own size, so a correct evaluation stays within a few.
"""

from __future__ import annotations

import functools
import math
from collections.abc import Callable
from typing import Any

import jax
import mpmath
import numpy as np
import pytest
import torch
from cases import (
    igso3_cdf_reference,
    igso3_log_density_dual,
    igso3_log_density_series,
    igso3_reference,
    igso3_reference_slope,
    igso3_scale,
    reference_igso3_angle_cdf,
    reference_igso3_log_density,
)
from conftest import Backend
from scipy import integrate, stats
from scipy.spatial.transform import Rotation

import diffquat.jax as djax
import diffquat.numpy as dnp
import diffquat.torch as dtorch
from diffquat import _igso3

# From the concentrations of protein-diffusion schedules (1e-4 ... 5e-4) to nearly uniform, both sides
# of the switch between the two forms (sigma = 1, eps = 1/2), and angles from the identity (the dual's
# 0/0) to pi and past it (reduced to [-pi, pi]).
SIGMAS = [1e-4, 5e-4, 2e-3, 0.02, 0.1, 0.3, 0.99, 1.0, 1.01, 2.0, 3.0, 10.0, 30.0]
ANGLES = [0.0, 1e-9, 1e-5, 1e-3, 0.1, 1.0, 2.0, 3.0, math.pi - 1e-6, math.pi, 4.0, -1.0, 7.0]
ULPS = {"float64": 4, "float32": 4}


def grid() -> tuple[np.ndarray, np.ndarray]:
    angle, sigma = np.meshgrid(ANGLES, SIGMAS)
    return angle.ravel(), sigma.ravel()


@pytest.mark.parametrize("precision", list(ULPS))
def test_log_density_matches_the_reference_far_into_the_tail(backend: Backend, precision: str) -> None:
    """Within 4 ulps of the size of the terms, against the reference at the values the backend
    received (float32 inputs are rounded first; the reference is taken at the rounded values), for
    sigma from 1e-4 to 30 (at omega = pi and sigma = 1e-4, log f = -4.9e8: f itself underflows)."""
    angle, sigma = grid()
    a, s = backend.array(angle, precision), backend.array(sigma, precision)
    got = backend.to_numpy(backend.module.igso3_log_density(a, s))
    ra, rs = backend.to_numpy(a), backend.to_numpy(s)
    expected = np.array([reference_igso3_log_density(x, y) for x, y in zip(ra, rs, strict=True)])
    error = np.abs(got - expected) / igso3_scale(ra, rs) / np.finfo(precision).eps
    worst = int(np.argmax(error))
    assert error[worst] <= ULPS[precision], (
        f"{error[worst]:.2f} ulps at angle {ra[worst]}, sigma {rs[worst]}: {got[worst]} vs {expected[worst]}"
    )


EXACT_RANGE = {"float64": 2.0**30, "float32": 2.0**17}


@pytest.mark.parametrize("precision", list(ULPS))
def test_large_angles_are_reduced_exactly_up_to_the_documented_range(
    backend: Backend, precision: str
) -> None:
    """Angles up to the exact range of the reduction (2^30 rad in float64, 2^17 in float32, where the
    odd multiple of pi nearest the angle times each part of pi but its tail is exact) have the density
    of their exact reduction, within the 4 ulps of the size of the terms of the test above: random
    angles in every decade, the float nearest the range, and the floats nearest large odd multiples of
    pi and large multiples of 2 pi (the cancelling cases), at sigma = 0.01, 0.3, 2 (both forms). From the
    range on, and for -angle too, NaN (before: wrong from 1e15 rad in float64 and 1e5 in float32, by
    up to 260 in log f, then NaN from 1e17 and 1e9 with no documented bound)."""
    limit = EXACT_RANGE[precision]
    rng = np.random.default_rng(5)
    turns = np.array([limit / (2 * math.pi) - 1, limit / (4 * math.pi) + 7, 12345.0])
    angle = np.concatenate(
        [
            10.0 ** rng.uniform(1, math.log10(limit), 12),
            [np.nextafter(np.float32(limit), 0) if precision == "float32" else np.nextafter(limit, 0)],
            2 * math.pi * turns,
            (2 * turns + 1) * math.pi,
        ]
    )
    angle = np.concatenate([angle, -angle]).astype(precision).astype(np.float64)
    assert np.all(np.abs(angle) < limit)
    for sigma in [0.01, 0.3, 2.0]:
        s = np.full_like(angle, sigma).astype(precision).astype(np.float64)
        got = backend.to_numpy(
            backend.module.igso3_log_density(backend.array(angle, precision), backend.array(s, precision))
        )
        with mpmath.workdps(60):
            expected = np.array(
                [float(igso3_reference(mpmath.mpf(x), mpmath.mpf(y))) for x, y in zip(angle, s, strict=True)]
            )
        # the size of the terms at the reduced angle (the reference's own reduction)
        reduced = np.abs(np.remainder(angle + math.pi, 2 * math.pi) - math.pi)
        error = np.abs(got - expected) / igso3_scale(reduced, s) / np.finfo(precision).eps
        worst = int(np.argmax(error))
        assert error[worst] <= ULPS[precision], (
            sigma,
            angle[worst],
            got[worst],
            expected[worst],
            error[worst],
        )
    beyond = np.array([limit, -limit, 2 * limit, float(np.finfo(precision).max)])
    out = backend.to_numpy(
        backend.module.igso3_log_density(
            backend.array(beyond, precision), backend.array(np.full(4, 0.3), precision)
        )
    )
    assert np.all(np.isnan(out)), out


def _derivatives(backend: Backend, angle: np.ndarray, sigma: np.ndarray, precision: str) -> tuple[Any, Any]:
    """d log f / d angle and d log f / d sigma, elementwise, by the backend's reverse mode."""
    fn = backend.module.igso3_log_density
    a, s = backend.array(angle, precision), backend.array(sigma, precision)
    if backend.name == "torch":
        a, s = a.requires_grad_(True), s.requires_grad_(True)
        out = fn(a, s)
        grads = torch.autograd.grad(out, (a, s), torch.ones_like(out))
    else:
        grads = jax.grad(lambda a, s: fn(a, s).sum(), argnums=(0, 1))(a, s)
    return backend.to_numpy(grads[0]), backend.to_numpy(grads[1])


@pytest.fixture(scope="module")
def reference_derivatives() -> tuple[np.ndarray, np.ndarray]:
    """The reference's derivatives on the grid, by mpmath.diff at 50 digits (on the float32 grid,
    which is also a float64 grid)."""
    angle, sigma = grid()
    angle, sigma = angle.astype(np.float32).astype(np.float64), sigma.astype(np.float32).astype(np.float64)
    d_angle, d_sigma = [], []
    with mpmath.workdps(50):
        for x, y in zip(angle, sigma, strict=True):
            xm, ym = mpmath.mpf(x), mpmath.mpf(y)
            d_angle.append(float(mpmath.diff(lambda t, y=ym: igso3_reference(t, y), xm)))
            d_sigma.append(float(mpmath.diff(lambda t, x=xm: igso3_reference(x, t), ym)))
    return np.array(d_angle), np.array(d_sigma)


def derivative_scales(angle: np.ndarray, sigma: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The sizes of the terms of each derivative: ``d/d omega`` of ``-omega^2 / (4 eps)`` is
    ``|omega| / (2 eps)``, ``d/d sigma`` of it and of ``-1.5 log eps`` are ``omega^2 / sigma^3`` and
    ``3 / sigma``."""
    eps = 0.5 * sigma**2
    return 1.0 + np.abs(angle) / (2.0 * eps), 1.0 + 3.0 / sigma + angle**2 / sigma**3


DERIVATIVE_ULPS = {"float64": 64, "float32": 16}


@pytest.mark.parametrize("precision", list(DERIVATIVE_ULPS))
def test_derivatives_match_the_reference(
    backend: Backend, precision: str, reference_derivatives: tuple[np.ndarray, np.ndarray]
) -> None:
    """d log f / d omega (the score's size) and d log f / d sigma within 64 ulps (float64; 16 in
    float32) of the size of their terms, from sigma = 1e-4, at the identity (where the derivative in
    omega is 0 and the dual's terms divide 0 by 0) and at pi (0 again, by symmetry). A chain of ~100
    operations, each an ulp, bounds the float64 error well below 64; float32 has fewer bits to lose
    relative to the same chain."""
    if not backend.differentiable:
        pytest.skip("numpy has no derivatives")
    angle, sigma = grid()
    angle, sigma = angle.astype(np.float32).astype(np.float64), sigma.astype(np.float32).astype(np.float64)
    got_angle, got_sigma = _derivatives(backend, angle, sigma, precision)
    scale_angle, scale_sigma = derivative_scales(angle, sigma)
    eps = np.finfo(precision).eps
    for name, got, expected, scale in [
        ("angle", got_angle, reference_derivatives[0], scale_angle),
        ("sigma", got_sigma, reference_derivatives[1], scale_sigma),
    ]:
        error = np.abs(got - expected) / scale / eps
        worst = int(np.argmax(error))
        assert error[worst] <= DERIVATIVE_ULPS[precision], (
            f"d/d{name}: {error[worst]:.1f} ulps at angle {angle[worst]}, sigma {sigma[worst]}: "
            f"{got[worst]} vs {expected[worst]}"
        )


@pytest.mark.parametrize(("omega", "eps"), [(0.3, 0.05), (2.0, 0.5), (3.1, 2.0), (1e-3, 1.0), (math.pi, 0.2)])
def test_the_two_forms_of_the_reference_agree(omega: float, eps: float) -> None:
    """The defining series and its Poisson dual (the reference's form below eps = 0.05, and the
    library's below eps = 1/2) agree to 40 digits where both converge: the dual, its (-1)^k included,
    is the series."""
    with mpmath.workdps(60):
        w, e = mpmath.mpf(omega), mpmath.mpf(eps)
        assert abs(igso3_log_density_series(w, e) - igso3_log_density_dual(w, e)) < mpmath.mpf(10) ** -40


@pytest.mark.parametrize("sigma", [1e-3, 0.05, 0.5, 2.0, 5.0])
def test_density_integrates_to_one(sigma: float) -> None:
    """The angle's density f(omega) (1 - cos omega) / pi has total mass 1 on [0, pi] (f is the density
    with respect to the normalised Haar measure), to 1e-11, by adaptive quadrature: on [0, 40 sigma]
    with break points at multiples of sigma, where the mass is when sigma is small, and beyond."""

    def density(w: float) -> float:
        return math.exp(float(dnp.igso3_log_density(w, sigma))) * (1.0 - math.cos(w)) / math.pi

    edge = min(40.0 * sigma, math.pi)
    points = [k * sigma for k in (0.5, 1.0, 2.0, 4.0, 8.0, 16.0) if k * sigma < edge]
    mass = integrate.quad(density, 0.0, edge, points=points or None, epsabs=1e-15, epsrel=1e-12, limit=200)[0]
    if edge < math.pi:
        mass += integrate.quad(density, edge, math.pi, epsabs=1e-15, limit=200)[0]
    assert abs(mass - 1.0) < 1e-11


def _values(backend: Backend, angle: Any, sigma: Any, precision: str = "float64") -> np.ndarray:
    fn: Callable[..., Any] = backend.module.igso3_log_density
    return backend.to_numpy(fn(backend.array(angle, precision), backend.array(sigma, precision)))


@pytest.mark.parametrize("precision", ["float64", "float32"])
def test_documented_edge_cases(backend: Backend, precision: str) -> None:
    """sigma enters as sigma^2 (-sigma is sigma); below the smallest sigma the dtype can carry the
    derivatives of (``sqrt(2 sqrt(1e3 / max))``), sigma = 0 included, the density is that sigma's,
    finite; at sigma = 30 it is uniform (log f = 0 to rounding); an angle is reduced to [-pi, pi]
    (2 pi + w is w, -w is w)."""
    angle = np.array([0.5, 2.0, 0.0, math.pi])
    same = _values(backend, angle, np.full(4, 0.7), precision)
    np.testing.assert_array_equal(_values(backend, angle, np.full(4, -0.7), precision), same)
    smallest = math.sqrt(2.0 * math.sqrt(1e3 / float(np.finfo(precision).max)))
    floor = _values(backend, angle, np.full(4, smallest), precision)
    assert np.all(np.isfinite(floor))
    np.testing.assert_array_equal(_values(backend, angle, np.zeros(4), precision), floor)
    np.testing.assert_array_equal(_values(backend, angle, np.full(4, smallest / 10), precision), floor)
    assert np.all(np.abs(_values(backend, angle, np.full(4, 30.0), precision)) <= np.finfo(precision).eps)
    shifted = _values(backend, np.array([0.5 + 2 * math.pi, -2.0, -0.5, 2.0 - 4 * math.pi]), np.full(4, 0.7))
    np.testing.assert_allclose(
        shifted, _values(backend, np.array([0.5, 2.0, 0.5, 2.0]), np.full(4, 0.7)), rtol=1e-13
    )


# ---------------------------------------------------------------------------------------------------
# The score.


def _run(backend: Backend, fn: Callable[..., Any], *args: Any) -> np.ndarray:
    """``fn(*args)`` as float64 NumPy; on jax under ``jit``: one compilation of the whole function
    instead of one per operation for each new shape (eager), ~1 s against ~3 s here."""
    return backend.to_numpy(jax.jit(fn)(*args) if backend.name == "jax" else fn(*args))


def _about_x(angle: np.ndarray, precision: str = "float64") -> np.ndarray:
    """Rotations about x by each angle, their entries rounded to the precision."""
    c, s = np.cos(angle).astype(precision), np.sin(angle).astype(precision)
    one, zero = np.ones_like(c), np.zeros_like(c)
    return np.stack([one, zero, zero, zero, c, -s, zero, s, c], axis=-1).reshape(*angle.shape, 3, 3)


@functools.cache
def score_reference(
    angles: tuple[float, ...], sigmas: tuple[float, ...], precision: str
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Rotations about x by each angle, each with its sigma (both rounded to the precision), the reference's
    score along x at them, ``s = d log f / d omega`` at 50 digits, and the size it is measured
    against, ``|s| + |sin(omega) ds/d omega| + |sigma ds/d sigma|``.

    The reference is taken at the input exactly as the backend receives it: at the angle of the
    rounded matrix, ``atan2`` of its entries (the angle of its nearest rotation), and at the rounded
    sigma. The size is the score's own plus what the dtype's rounding of its inputs moves it by, its
    condition: an ulp of each entry (``cos omega``, ``sin omega``: a rotation about a coordinate axis,
    whose entries carry the gap to pi to their last bit) moves the angle by up to an ulp of ``sin
    omega`` (so near pi an ulp of the gap, whose size the score has there: the measure stays relative
    to it, not the ``(pi / sigma^2)^2`` per radian of an ulp of the angle itself), and an ulp of
    ``sigma^2`` (which the computation rounds) moves it by half an ulp of ``sigma ds/d sigma``; only
    their sizes matter, so the derivatives are taken by ``mpmath.diff`` at 20 digits."""
    matrices = _about_x(np.array(angles), precision)
    sigma = np.array(sigmas).astype(precision)
    expected, size = [], []
    with mpmath.workdps(50):
        for m, y in zip(matrices, sigma, strict=True):
            w = mpmath.atan2(mpmath.mpf(float(m[2, 1])), mpmath.mpf(float(m[1, 1])))
            ym = mpmath.mpf(float(y))
            if w == 0:  # the identity: the score is 0
                expected.append(0.0)
                size.append(0.0)
                continue
            value = igso3_reference_slope(w, ym)
            with mpmath.workdps(20):
                d_angle = mpmath.diff(lambda t, ym=ym: igso3_reference_slope(t, ym), w)
                d_sigma = mpmath.diff(lambda t, w=w: igso3_reference_slope(w, t), ym)
            expected.append(float(value))
            size.append(float(abs(value) + abs(mpmath.sin(w) * d_angle) + abs(ym * d_sigma)))
    return matrices, sigma, np.array(expected), np.array(size)


def score_errors(backend: Backend, angles: np.ndarray, sigmas: np.ndarray, precision: str) -> np.ndarray:
    """The backend's score on ``score_reference``'s rotations, its error along x in ulps of the
    reference's size, or of the dtype's smallest normal where that is larger (the score is below it at
    sigma = 10 in float32: ~1e-43, which XLA's CPU code flushes to 0 with the subnormals), after checking
    that the other two components are 0."""
    matrices, sigma, expected, size = score_reference(tuple(angles), tuple(sigmas), precision)
    m, s = backend.array(matrices, precision), backend.array(sigma, precision)
    got = _run(backend, backend.module.igso3_score, m, s)
    assert np.all(got[:, 1:] == 0)
    info = np.finfo(precision)
    return np.abs(got[:, 0] - expected) / np.maximum(info.eps * size, float(info.tiny))


# The grid's angles in [0, pi] and more near pi, where the score is ~ the gap to pi and would be
# lost to the cancellation of terms ~1 / sigma^2 (so the forms about pi), and sigma just above the
# switch (eps = 1/2), where the series alternates most near pi.
SCORE_ANGLES = [a for a in ANGLES if 0 <= a <= math.pi] + [3.1, 3.14, math.pi - 1e-9]
SCORE_SIGMAS = [*SIGMAS, 1.05, 1.1]
# The score is a quotient of two sums of ~10 terms (or a difference of three terms about pi), each
# within an ulp or two of the sizes above, with the angle and its gap to pi each within an ulp or
# two from the quaternion: a correct evaluation stays within a few ulps. Measured: 4.0 (float64) and
# 6.1 (float32), both at sigma = 1.01 near pi. In float64 8 ulps is 1.8e-15, far within the 1e-12.
SCORE_ULPS = {"float64": 8, "float32": 8}


@pytest.mark.parametrize("precision", list(SCORE_ULPS))
def test_score_matches_the_reference(backend: Backend, precision: str) -> None:
    """Rotations about x by each angle (0 to pi) at each sigma from 1e-4 (5e-4 among them) to 30: the
    score is ``(d log f / d omega)`` along x, within 8 ulps of the size of the reference's and of what
    the rounding of its inputs moves it by (``score_reference``), in float64 and float32; relative
    to its own size near pi too, where it goes to 0 with the gap; the other two components are 0."""
    angle, sigma = (x.ravel() for x in np.meshgrid(SCORE_ANGLES, SCORE_SIGMAS))
    error = score_errors(backend, angle, sigma, precision)
    worst = int(np.argmax(error))
    assert error[worst] <= SCORE_ULPS[precision], (
        f"{error[worst]:.1f} ulps at angle {angle[worst]}, sigma {sigma[worst]}"
    )


# (angle, sigma) where log f is about -690, f about 1e-300 (float64's smallest normal is 2.2e-308):
# the Gaussian's tail at the sigmas of protein-diffusion schedules (1e-4, 5e-4) and on to 0.084,
# where it reaches pi (at larger sigma f(pi) is above 1e-300). Angles from the 50-digit reference's
# root of log f = -690, rounded.
TAIL = [
    (0.0037927, 1e-4),
    (0.0189, 5e-4),
    (0.075379, 2e-3),
    (0.37562, 0.01),
    (0.75013, 0.02),
    (1.87183, 0.05),
    (2.61896, 0.07),
    (2.99246, 0.08),
    (math.pi, 0.0839512),
]
# log f there is -690 to a few ulps of the size of its largest term, omega^2 / (4 eps) ~ 700, so
# within a few ulps relative: 4 (measured: 1.5 in float64, 0.7 in float32), 9e-16 relative in
# float64, far within the 1e-12.
TAIL_ULPS = 4


@pytest.mark.parametrize("precision", ["float64", "float32"])
def test_log_density_and_score_far_in_the_tail(backend: Backend, precision: str) -> None:
    """Where f is about 1e-300: log f within 4 ulps relative of the reference at the values the backend
    received, and the score within SCORE_ULPS of its size (``score_reference``); in float32 too, where
    f itself underflows to 0 (log f does not)."""
    angle, sigma = (np.array(x) for x in zip(*TAIL, strict=True))
    a, s = backend.array(angle, precision), backend.array(sigma, precision)
    got = _run(backend, backend.module.igso3_log_density, a, s)
    ra, rs = backend.to_numpy(a), backend.to_numpy(s)
    expected = np.array([reference_igso3_log_density(x, y) for x, y in zip(ra, rs, strict=True)])
    assert np.all((expected > -691) & (expected < -689))
    error = np.abs(got - expected) / np.abs(expected) / np.finfo(precision).eps
    worst = int(np.argmax(error))
    assert error[worst] <= TAIL_ULPS, (
        f"log f: {error[worst]:.2f} ulps at angle {ra[worst]}, sigma {rs[worst]}"
    )
    score = score_errors(backend, angle, sigma, precision)
    worst = int(np.argmax(score))
    assert score[worst] <= SCORE_ULPS[precision], (
        f"score: {score[worst]:.2f} ulps at angle {angle[worst]}, sigma {sigma[worst]}"
    )


@pytest.mark.parametrize("sigma", [0.05, 0.5, 3.0])
def test_score_is_the_derivative_of_the_log_density_along_a_tangent(sigma: float) -> None:
    """<score(R), delta> equals the central difference of log p(R exp(h delta)) in h, log p(R) =
    log f(|log(mean^T R)|), for random rotations, means and tangents (float64, h = 1e-5: the difference
    is accurate to ~1e-9 of the curvature's scale, the bound 1e-7 of the score's)."""
    rng = np.random.default_rng(5)
    rotations = Rotation.random(20, random_state=6).as_matrix()
    means = Rotation.random(20, random_state=7).as_matrix()
    delta = rng.normal(size=(20, 3))
    score = dnp.igso3_score(rotations, sigma, means)

    def log_p(r: np.ndarray) -> np.ndarray:
        return dnp.igso3_log_density(
            np.linalg.norm(dnp.so3_log(np.swapaxes(means, -1, -2) @ r), axis=-1), sigma
        )

    h = 1e-5
    moved = [rotations @ dnp.so3_exp(sign * h * delta) for sign in (1.0, -1.0)]
    fd = (log_p(moved[0]) - log_p(moved[1])) / (2 * h)
    np.testing.assert_allclose(
        np.sum(score * delta, axis=-1), fd, rtol=0, atol=1e-7 * (1.0 + math.pi / sigma**2)
    )


@pytest.mark.parametrize("sigma", [0.01, 0.5, 3.0])
def test_score_at_the_identity_and_at_pi(backend: Backend, sigma: float) -> None:
    """At the identity the score is 0 and its derivative in the body frame is (d^2 log f / d omega^2)(0)
    times the identity (torch and jax; the reference's second derivative at 0); at a half-turn it is
    0 exactly; ``mean=None`` is the identity mean."""
    module = backend.module
    eye = np.eye(3)
    assert np.all(backend.to_numpy(module.igso3_score(backend.array(eye, "float64"), sigma)) == 0)
    # an exact half-turn (cos pi = -1, sin pi = 0 exactly): the angle's gap to pi is taken from the
    # quaternion, 0 here, and the forms about pi are odd in it, so the score is 0 exactly
    half = backend.to_numpy(module.igso3_score(backend.array(np.diag([1.0, -1.0, -1.0]), "float64"), sigma))
    assert np.all(half == 0)
    rotations = backend.array(Rotation.random(4, random_state=8).as_matrix(), "float64")
    np.testing.assert_array_equal(
        backend.to_numpy(module.igso3_score(rotations, sigma)),
        backend.to_numpy(module.igso3_score(rotations, sigma, backend.array(eye, "float64"))),
    )
    if not backend.differentiable:
        return
    with mpmath.workdps(50):
        s = mpmath.mpf(sigma)
        # (d log f / d omega)(t) / t at t = 1e-12: the curvature at 0 plus O(t^2) (the series form
        # cancels to t^3 of its terms: 36 of the 50 digits)
        tiny = mpmath.mpf(10) ** -12
        curvature = float(igso3_reference_slope(tiny, s) / tiny)

    def score_of(d: Any) -> Any:
        return module.igso3_score(module.so3_exp(d), sigma)

    if backend.name == "torch":
        jac = torch.func.jacrev(score_of)(torch.zeros(3, dtype=torch.float64))
    else:
        jac = jax.jacrev(score_of)(jax.numpy.zeros(3, dtype="float64"))
    np.testing.assert_allclose(
        backend.to_numpy(jac), curvature * eye, rtol=1e-13, atol=1e-13 * abs(curvature)
    )


# ---------------------------------------------------------------------------------------------------
# The angle's CDF

CDF_ABSOLUTE = {"float64": 1e-15, "float32": 8 * float(np.finfo(np.float32).eps)}


@pytest.mark.parametrize("precision", list(CDF_ABSOLUTE))
def test_angle_cdf_matches_the_reference(backend: Backend, precision: str) -> None:
    """F within an absolute 1e-15 (float64; 8 ulps of 1 in float32) of the 50-digit reference at the
    values the backend received, from sigma = 1e-4 to 30, angles in [0, pi] and beyond (clamped); F(0)
    = 0 and F(pi) = 1 exactly, and F does not decrease along the angle (to rounding)."""
    angle, sigma = grid()
    a, s = backend.array(angle, precision), backend.array(sigma, precision)
    got = backend.to_numpy(backend.module.igso3_angle_cdf(a, s))
    ra, rs = backend.to_numpy(a), backend.to_numpy(s)
    expected = np.array([reference_igso3_angle_cdf(float(x), float(y)) for x, y in zip(ra, rs, strict=True)])
    error = np.abs(got - expected)
    worst = int(np.argmax(error))
    assert error[worst] <= CDF_ABSOLUTE[precision], (
        f"{error[worst]:.2e} at angle {ra[worst]}, sigma {rs[worst]}: {got[worst]} vs {expected[worst]}"
    )
    ends = backend.to_numpy(
        backend.module.igso3_angle_cdf(
            backend.array(np.array([[0.0], [math.pi]]), precision), backend.array(np.array(SIGMAS), precision)
        )
    )
    assert np.all(ends[0] == 0) and np.all(ends[1] == 1)
    sweep = np.linspace(0.0, math.pi, 2001)[:, None]
    values = backend.to_numpy(
        backend.module.igso3_angle_cdf(
            backend.array(sweep, precision), backend.array(np.array(SIGMAS), precision)
        )
    )
    # non-decreasing to its accuracy: within CDF_ABSOLUTE of a non-decreasing F, it steps back by at
    # most twice that where F rises by less (near 1, float32's erf carries a few ulps)
    assert np.all(np.diff(values, axis=0) >= -2 * CDF_ABSOLUTE[precision])


def test_angle_cdf_derivative_is_the_angle_density(backend: Backend) -> None:
    """dF/d omega, by the backend's reverse mode, equals f (1 - cos omega) / pi from the log density to
    within 1e-13 of the density's peak (float64), for sigma from 1e-4 to 30 (inside (0, pi))."""
    if not backend.differentiable:
        pytest.skip("numpy has no derivatives")
    omega = np.concatenate([np.linspace(1e-3, math.pi - 1e-3, 40), [1e-5, 3e-4, 1e-3]])
    angle, sigma = (x.ravel() for x in np.meshgrid(omega, SIGMAS))
    fn = backend.module.igso3_angle_cdf
    if backend.name == "torch":
        a = torch.tensor(angle, requires_grad=True)
        got = torch.autograd.grad(fn(a, torch.tensor(sigma)).sum(), a)[0].numpy()
    else:
        got = np.asarray(jax.grad(lambda a: fn(a, sigma).sum())(jax.numpy.asarray(angle)))
    # 1 - cos omega as 2 sin^2(omega / 2): no cancellation at small angles
    density = np.exp(dnp.igso3_log_density(angle, sigma)) * 2.0 * np.sin(0.5 * angle) ** 2 / math.pi
    # the density's peak is about sqrt(2 / pi) * 2 / sigma (the Maxwell peak) for small sigma
    peak = 1.0 + 2.0 / sigma
    np.testing.assert_array_less(np.abs(got - density) / peak, 1e-13)


# ---------------------------------------------------------------------------------------------------
# The limits: sigma -> infinity (Haar) and sigma -> 0 (the Gaussian)

LIMIT_ANGLES = [0.0, 0.5, 1.0, 2.0, 3.0, math.pi]
# From 10 on; 1e30's sigma^2 overflows float32 (eps = inf: every term's weight is 0).
LARGE_SIGMAS = [10.0, 30.0, 100.0, 1e4, 1e30]


def _limit_values(backend: Backend, angle: np.ndarray, sigma: np.ndarray, precision: str) -> tuple[Any, ...]:
    """log f, the score along x of the rotation about x by each angle (and its other components), and
    F, all in float64, with the angles and sigmas the backend received (a matrix's angle from its
    entries)."""
    a, s = backend.array(angle, precision), backend.array(sigma, precision)
    m = _about_x(angle, precision)
    module = backend.module
    log_f = _run(backend, module.igso3_log_density, a, s)
    score = _run(backend, module.igso3_score, backend.array(m, precision), s)
    cdf = _run(backend, module.igso3_angle_cdf, a, s)
    matrix_angle = np.arctan2(m[:, 2, 1].astype(np.float64), m[:, 1, 1].astype(np.float64))
    return backend.to_numpy(a), backend.to_numpy(s), matrix_angle, log_f, score, cdf


@pytest.mark.parametrize("precision", ["float64", "float32"])
def test_large_sigma_is_the_haar_measure(backend: Backend, precision: str) -> None:
    """sigma -> infinity: f -> 1 (the uniform distribution), the score -> 0 and F -> (omega - sin
    omega) / pi, the angle's law under Haar. From sigma = 10 on only the series' l = 1 term is left:
    log f = 3 e^(-sigma^2) (1 + 2 cos omega) and d log f / d omega = -6 e^(-sigma^2) sin omega (the l = 2
    term is e^(-2 sigma^2) = e^(-200) of it, log1p's square e^(-100)), held within 4 ulps of the size
    9 e^(-sigma^2) and 6 e^(-sigma^2) (or of the smallest normal, above them at sigma = 10 in float32:
    ~1e-43, which XLA flushes to 0), and F within CDF_ABSOLUTE of Haar's. From sigma = 30 the term
    underflows: log f and the score are 0 exactly (docs/igso3.md: the uniform density)."""
    angle, sigma = (x.ravel() for x in np.meshgrid(LIMIT_ANGLES, LARGE_SIGMAS))
    ra, rs, w, log_f, score, cdf = _limit_values(backend, angle, sigma, precision)
    info = np.finfo(precision)
    with np.errstate(under="ignore"):
        weight = np.exp(-(rs**2))
    for name, got, expected, size in [
        ("log f", log_f, 3.0 * weight * (1.0 + 2.0 * np.cos(ra)), 9.0 * weight),
        ("score", score[:, 0], -6.0 * weight * np.sin(w), 6.0 * weight),
    ]:
        error = np.abs(got - expected) / np.maximum(info.eps * size, float(info.tiny))
        worst = int(np.argmax(error))
        assert error[worst] <= 4, f"{name}: {error[worst]:.1f} ulps at angle {ra[worst]}, sigma {rs[worst]}"
        assert np.all(got[rs >= 30] == 0)
    assert np.all(score[:, 1:] == 0)
    np.testing.assert_allclose(cdf, (ra - np.sin(ra)) / math.pi, rtol=0, atol=CDF_ABSOLUTE[precision])


SMALL_SIGMAS = [1e-4, 5e-4, 1e-3, 1e-2]
STANDARD = [0.0, 0.5, 1.0, 2.0, 4.0, 8.0]  # angles in units of sigma


@pytest.mark.parametrize("precision", ["float64", "float32"])
def test_small_sigma_is_the_gaussian(backend: Backend, precision: str) -> None:
    """sigma -> 0: the rotation vector is N(0, sigma^2 I_3) (docs/igso3.md), to O(sigma^2). Against the
    normalised Haar measure, whose density in the rotation vector is (1 - cos omega) / (4 pi^2 omega^2),
    that Gaussian has log g = log(2 sqrt(2 pi) / sigma^3) - omega^2 / (2 sigma^2) + 2 log(h / sin h), h =
    omega / 2, and from the dual form (its k = 0 term; the others are e^(-pi^2 / eps) of it)

        log f - log g = sigma^2 / 8 - log(h / sin h) = sigma^2 / 8 - omega^2 / 24 + O(omega^4),
        score = -phi / sigma^2 + phi / 12 + O(omega^3)  (the Gaussian's is -phi / sigma^2),
        F(k sigma) = M(k) + (sigma^2 / 8) (M(k) - C5(k)) + O(sigma^4),

    with M the Maxwell distribution's CDF, that of chi^2 with 3 degrees of freedom at k^2, and C5
    that with 5 (the integral of the relative correction sigma^2 / 8 - omega^2 / 24 against Maxwell's
    density). Checked for angles up to 8 sigma and sigma from 1e-4 to 1e-2, to the next order (its
    coefficients: omega^4 / 2880, omega^3 / 720, ~1e-3 sigma^4 measured) plus the rounding of each (8
    ulps of its terms' size; the CDF's absolute accuracy): in float64 the O(sigma^2) terms are resolved
    (sigma^2 / 8 is 1e-9 at sigma = 1e-4), in float32 the leading order is, to its rounding. And F is 1
    exactly from 12 sigma on at sigma = 1e-6."""
    angle, sigma = (x.ravel() for x in np.meshgrid(STANDARD, SMALL_SIGMAS))
    angle = angle * sigma
    ra, rs, w, log_f, score, cdf = _limit_values(backend, angle, sigma, precision)
    eps = float(np.finfo(precision).eps)
    h = 0.5 * ra
    ratio = np.where(h > 0, h / np.sin(np.where(h > 0, h, 1.0)), 1.0)
    log_g = np.log(2.0 * math.sqrt(2.0 * math.pi) / rs**3) - ra**2 / (2.0 * rs**2) + 2.0 * np.log(ratio)
    np.testing.assert_array_less(
        np.abs(log_f - (log_g + rs**2 / 8.0 - ra**2 / 24.0)), ra**4 / 2000.0 + 8.0 * eps * igso3_scale(ra, rs)
    )
    np.testing.assert_array_less(
        np.abs(score[:, 0] - (-w / rs**2 + w / 12.0)), w**3 / 500.0 + 8.0 * eps * (1.0 + w / rs**2) + 1e-300
    )
    assert np.all(score[:, 1:] == 0)
    k2 = (ra / rs) ** 2
    maxwell = stats.chi2.cdf(k2, 3)
    np.testing.assert_array_less(
        np.abs(cdf - (maxwell + rs**2 / 8.0 * (maxwell - stats.chi2.cdf(k2, 5)))),
        rs**4 / 100.0 + CDF_ABSOLUTE[precision],
    )
    far = np.linspace(12e-6, math.pi, 50)
    tiny = backend.array(np.full(50, 1e-6), precision)
    assert np.all(_run(backend, backend.module.igso3_angle_cdf, backend.array(far, precision), tiny) == 1)


# ---------------------------------------------------------------------------------------------------
# The sampler


def _sample(backend: Backend, sigma: Any, n: int, seed: int, precision: str = "float64") -> np.ndarray:
    """n draws per element of sigma from the backend's sampler, with a fixed seed."""
    s = backend.array(np.asarray(sigma, np.float64), precision)
    if backend.name == "numpy":
        out = dnp.igso3_sample(s, n, rng=seed)
    elif backend.name == "torch":
        out = backend.module.igso3_sample(s, n, generator=torch.Generator().manual_seed(seed))
    else:
        out = backend.module.igso3_sample(s, n, key=jax.random.key(seed))
    return backend.to_numpy(out)


def _angles(matrices: np.ndarray) -> np.ndarray:
    return np.linalg.norm(Rotation.from_matrix(matrices.reshape(-1, 3, 3)).as_rotvec(), axis=-1).reshape(
        matrices.shape[:-2]
    )


KS_SIGMAS = [1e-3, 0.1, 0.5, 1.0, 2.0, 5.0]


def test_sampled_angles_follow_the_cdf(backend: Backend) -> None:
    """Kolmogorov-Smirnov of 4000 sampled angles per sigma against F (fixed seeds: p > 0.01 at each of
    six sigmas, from 1e-3 to 5), and the axes are uniform (their mean within 4 standard errors of 0)."""
    samples = _sample(backend, KS_SIGMAS, 4000, seed=11)
    angles = _angles(samples)
    for k, sigma in enumerate(KS_SIGMAS):
        result = stats.kstest(angles[:, k], lambda w, sigma=sigma: dnp.igso3_angle_cdf(w, sigma))
        assert result.pvalue > 0.01, (sigma, result)
    axes = Rotation.from_matrix(samples[:, 3].reshape(-1, 3, 3)).as_rotvec()
    axes = axes / np.linalg.norm(axes, axis=-1, keepdims=True)
    assert np.all(np.abs(axes.mean(axis=0)) < 4.0 / math.sqrt(3.0 * len(axes)))


def test_the_exponential_of_a_gaussian_is_not_igso3() -> None:
    """exp(N(0, sigma^2 I)) at sigma = 1, the easy mistake, fails the same test (p < 1e-6 with 20000
    draws), while diffquat's sampler passes it with as many."""
    rng = np.random.default_rng(3)
    wrong = np.linalg.norm(Rotation.from_rotvec(rng.normal(size=(20000, 3))).as_rotvec(), axis=-1)

    def cdf(w: np.ndarray) -> np.ndarray:
        return dnp.igso3_angle_cdf(w, 1.0)

    assert stats.kstest(wrong, cdf).pvalue < 1e-6
    assert stats.kstest(_angles(dnp.igso3_sample(1.0, 20000, rng=4)), cdf).pvalue > 0.01


def test_composed_samples_are_igso3_at_the_summed_time() -> None:
    """The semigroup: R1 R2 with R1 ~ IGSO(3)(0.3), R2 ~ IGSO(3)(0.4) is IGSO(3)(0.5), by KS (p > 0.01)."""
    composed = dnp.igso3_sample(0.3, 4000, rng=5) @ dnp.igso3_sample(0.4, 4000, rng=6)
    assert stats.kstest(_angles(composed), lambda w: dnp.igso3_angle_cdf(w, 0.5)).pvalue > 0.01


def test_the_inversion_reaches_the_cdf_within_its_accuracy() -> None:
    """After SAMPLE_STEPS steps, |F(omega) - u| is within F's own accuracy (4 ulps of 1) for sigma
    log-uniform from 1e-4 to 30 and u uniform and within 1e-12 of either end."""
    rng = np.random.default_rng(1)
    sigma = np.exp(rng.uniform(math.log(1e-4), math.log(30.0), 4000))
    u = np.concatenate(
        [rng.uniform(size=3000), 10.0 ** -rng.uniform(0, 12, 500), 1.0 - 10.0 ** -rng.uniform(0, 12, 500)]
    )
    with np.errstate(all="ignore"):
        omega = _igso3._angle_quantile(np, u, sigma)
    assert np.all((omega >= 0) & (omega <= math.pi))
    assert np.max(np.abs(dnp.igso3_angle_cdf(omega, sigma) - u)) <= 4 * np.finfo(np.float64).eps


@pytest.mark.parametrize("sigma", [1e-3, 0.3, 2.0])
def test_reparameterised_angles_have_the_implicit_derivative(backend: Backend, sigma: float) -> None:
    """At fixed random numbers, each sample's angle has ``d omega / d sigma = -(dF/d sigma) / p``, the
    implicit derivative at its own u, within 1e-9 of the reference's (mpmath, 30 digits); central
    differences of samples drawn with the same seed at sigma +- h agree (h = 1e-6 sigma); and the
    sample median's derivative is that of the reference median within 2% (40001 draws: its standard
    error is ~0.35% there)."""
    if not backend.differentiable:
        pytest.skip("numpy has no derivatives")
    n = 40001
    if backend.name == "torch":
        s = torch.tensor(sigma, dtype=torch.float64, requires_grad=True)
        angles = torch.linalg.vector_norm(
            backend.module.matrix_to_axis_angle(
                backend.module.igso3_sample(s, n, generator=torch.Generator().manual_seed(7))
            ),
            dim=-1,
        )
        first = angles[:5].detach().numpy()
        grads = np.stack([torch.autograd.grad(a, s, retain_graph=True)[0].numpy() for a in angles[:5]])
        median_grad = float(torch.autograd.grad(torch.median(angles), s)[0])
    else:

        def angle_of(s: Any) -> Any:
            m = backend.module.igso3_sample(s, n, key=jax.random.key(7))
            return jax.numpy.linalg.norm(backend.module.matrix_to_axis_angle(m), axis=-1)

        def five_and_median(s: Any) -> Any:
            angles = angle_of(s)
            return jax.numpy.concatenate([angles[:5], jax.numpy.median(angles)[None]])

        # one eager evaluation of the 40001 draws and one pullback of the six outputs (reverse mode
        # as jacrev and grad take it), where a call each for the values, jacrev and grad drew them
        # three times
        out, pullback = jax.vjp(five_and_median, jax.numpy.float64(sigma))
        (rows,) = jax.vmap(pullback)(jax.numpy.eye(6, dtype=out.dtype))
        first, grads, median_grad = np.asarray(out[:5]), np.asarray(rows[:5]), float(rows[5])
    h = 1e-6 * sigma
    moved = [_angles(_sample(backend, sigma + d, 5, seed=7))[:5] for d in (h, -h)]
    if backend.name == "torch":  # the same seed draws the same first numbers for any n (jax: split keys)
        np.testing.assert_allclose(grads, (moved[0] - moved[1]) / (2 * h), rtol=1e-5, atol=1e-6)
    with mpmath.workdps(30):
        sm = mpmath.mpf(sigma)
        for w, g in zip(first, grads, strict=True):
            wm = mpmath.mpf(float(w))
            d_sigma = mpmath.diff(lambda t, wm=wm: igso3_cdf_reference(wm, t), sm)
            p = mpmath.diff(lambda t: igso3_cdf_reference(t, sm), wm)
            assert abs(g - float(-d_sigma / p)) <= 1e-9 * (1.0 + abs(float(-d_sigma / p))), (w, g)

    def reference_median(s: float) -> float:
        with mpmath.workdps(30):
            sm = mpmath.mpf(s)
            start = min(1.54 * s, 2.3)
            bracket = (mpmath.mpf(0.5 * start), mpmath.mpf(min(2.0 * start, math.pi)))
            return float(
                mpmath.findroot(
                    lambda w: igso3_cdf_reference(w, sm) - mpmath.mpf(0.5), bracket, solver="anderson"
                )
            )

    d = 1e-4 * sigma
    expected = (reference_median(sigma + d) - reference_median(sigma - d)) / (2 * d)
    assert abs(median_grad - expected) <= 0.02 * abs(expected), (median_grad, expected)


@pytest.mark.parametrize("precision", ["float32", "float16"])
def test_samples_are_rotations_in_every_dtype(backend: Backend, precision: str) -> None:
    """Samples in the input's dtype are rotations to a few ulps of it (computed in float32 for float16);
    a NaN sigma gives NaN samples in its own column only."""
    sigma = np.array([1e-3, 0.5, 3.0, np.nan])
    s = backend.array(sigma, precision)
    if backend.name == "numpy":
        out = dnp.igso3_sample(s, 50, rng=2)
    elif backend.name == "torch":
        out = backend.module.igso3_sample(s, 50, generator=torch.Generator().manual_seed(2))
    else:
        out = backend.module.igso3_sample(s, 50, key=jax.random.key(2))
    assert str(out.dtype).endswith(precision)
    r = backend.to_numpy(out).astype(np.float64)
    assert np.all(np.isnan(r[:, 3]))
    good = r[:, :3]
    eps = float(np.finfo(precision).eps)
    assert np.abs(good @ np.swapaxes(good, -1, -2) - np.eye(3)).max() <= 8 * eps
    assert np.all(np.abs(np.linalg.det(good) - 1.0) <= 8 * eps)


@pytest.mark.parametrize("sigma", [0.05, 0.5, 1.5])
def test_score_has_zero_mean_under_the_distribution(sigma: float) -> None:
    """E_p[score] = 0 (the integral of a gradient of p over a compact group): the mean score of 20000
    samples (fixed seed), each component within 4 standard errors of 0."""
    rotations = dnp.igso3_sample(sigma, 20000, rng=9)
    score = dnp.igso3_score(rotations, sigma)
    mean, error = score.mean(axis=0), score.std(axis=0) / math.sqrt(len(score))
    assert np.all(np.abs(mean) <= 4 * error), (mean, error)


def test_sampler_traces_under_jit_vmap_and_torch_compile() -> None:
    """No data-dependent control flow: ``torch.compile(fullgraph=True)`` (Dynamo and AOTAutograd,
    ``aot_eager``) draws what eager draws from the same seed, bit for bit; ``jax.jit`` matches eager
    within 4 float32 ulps of 1 (XLA fuses the arithmetic); ``jax.vmap`` over sigma and keys gives each
    element its own draws."""
    sigma = [0.1, 1.0]
    compiled = torch.compile(lambda s: dtorch.igso3_sample(s, 4), backend="aot_eager", fullgraph=True)
    torch.manual_seed(0)
    a = compiled(torch.tensor(sigma))
    torch.manual_seed(0)
    assert torch.equal(a, dtorch.igso3_sample(torch.tensor(sigma), 4))
    dj, key = djax, jax.random.key(0)
    jitted = jax.jit(lambda s: dj.igso3_sample(s, 4, key=key))(jax.numpy.array(sigma))
    eager = dj.igso3_sample(jax.numpy.array(sigma), 4, key=key)
    np.testing.assert_allclose(
        np.asarray(jitted), np.asarray(eager), rtol=0, atol=4 * np.finfo(np.float32).eps
    )
    keys = jax.random.split(key, 2)
    mapped = jax.vmap(lambda s, k: dj.igso3_sample(s, 3, key=k))(jax.numpy.array(sigma), keys)
    for i in range(2):
        np.testing.assert_array_equal(
            np.asarray(mapped[i]), np.asarray(dj.igso3_sample(sigma[i], 3, key=keys[i]))
        )


@pytest.mark.parametrize("precision", ["float32", "float64"])
def test_below_the_smallest_sigma_samples_scale_the_gaussian(backend: Backend, precision: str) -> None:
    """Below the smallest sigma the density is taken at (``sqrt(2 sqrt(1e3 / max))``, float32 1.9e-9,
    float64 6.9e-77) a sample's angle is sigma times the Maxwell quantile of its uniform number, the law
    of the rotation vector N(0, sigma^2 I), on every backend: at fixed random numbers angle / sigma is
    scipy's ``maxwell.ppf(u)`` within F's accuracy over the density (16 ulps of 1 over the Maxwell
    density, plus 8 ulps of the quantile for the angle's rounding), sigma = 0 gives the identity
    exactly, and the derivative of the rotation vector in sigma (torch, jax) is the axis times that
    quantile, at sigma = 0 as beyond. Before, float32 sigma = 1e-12 gave NaN and half-turns, and sigma =
    0 angles of pi / 2^16 on one backend but not another."""
    rng = np.random.default_rng(4)
    n = 64
    u = np.concatenate([[1e-6, 0.5, 1.0 - 2.0**-20], rng.uniform(size=n - 3)]).astype(precision)
    normal = rng.normal(size=(n, 3)).astype(precision)
    axis = normal.astype(np.float64) / np.linalg.norm(normal.astype(np.float64), axis=-1, keepdims=True)
    quantile = stats.maxwell.ppf(u.astype(np.float64))
    eps = float(np.finfo(precision).eps)
    bound = 16 * eps / stats.maxwell.pdf(quantile) + 8 * eps * quantile
    smallest = math.sqrt(2.0 * math.sqrt(1e3 / float(np.finfo(precision).max)))
    sigmas = [1e-20, 1e-12, 0.5 * smallest] if precision == "float32" else [1e-300, 1e-100, 0.5 * smallest]
    B = backend.module._B

    def sample(sigma: Any) -> Any:
        return B(
            _igso3.igso3_sample,
            sigma,
            uniform=backend.array(u, precision),
            normal=backend.array(normal, precision),
        )

    if backend.name == "jax":  # one compilation of the inversion's 16 steps, not each step's ops eagerly
        sample = jax.jit(sample)

    for s in [0.0, *sigmas]:
        sigma = backend.array(np.full(n, s), precision)
        r = backend.to_numpy(sample(sigma))
        assert np.all(np.isfinite(r)), s
        if s == 0.0:
            np.testing.assert_array_equal(r, np.broadcast_to(np.eye(3), r.shape))
            continue
        s_rounded = float(np.asarray(s, precision))
        # the rotation vector from the skew part (sin omega = omega to below an ulp), scaled first
        vector = np.stack([r[:, 2, 1] - r[:, 1, 2], r[:, 0, 2] - r[:, 2, 0], r[:, 1, 0] - r[:, 0, 1]], -1)
        scaled = (vector / s_rounded) / 2.0
        assert np.all(np.abs(np.linalg.norm(scaled, axis=-1) - quantile) <= bound), s
        np.testing.assert_allclose(
            scaled / np.linalg.norm(scaled, axis=-1, keepdims=True), axis, atol=8 * eps
        )
    if not backend.differentiable:
        return
    for s in [0.0, sigmas[0]]:
        if backend.name == "torch":
            sigma = backend.array(np.full(n, s), precision).requires_grad_(True)
            r = sample(sigma)
            grads = [
                torch.autograd.grad(r[:, i, j].sum(), sigma, retain_graph=True)[0]
                for i, j in ((2, 1), (0, 2), (1, 0))
            ]
            slope = np.stack([backend.to_numpy(g) for g in grads], -1)
        else:
            # forward mode, one pass: each sample depends on its own sigma only
            t = backend.array(np.full(n, s), precision)
            r_dot = np.asarray(jax.jvp(sample, (t,), (jax.numpy.ones_like(t),))[1]).astype(np.float64)
            slope = np.stack([r_dot[:, 2, 1], r_dot[:, 0, 2], r_dot[:, 1, 0]], -1)
        assert np.all(np.abs(slope - quantile[:, None] * axis) <= (bound + 8 * eps * quantile)[:, None]), s


def test_sampler_exports_with_a_dynamic_batch() -> None:
    """``torch.export`` of ``igso3_sample`` with a dynamic batch of sigma (it failed with torch's
    "SymIntArrayRef expected to contain only concrete integers" while a static batch exported: the
    wrapper passed ``generator=None`` to ``torch.rand``; it draws by ``uniform_``/``normal_`` now, which
    export with a generator or without): the exported program, run at another batch
    size from the same global seed, draws what eager draws, bit for bit."""

    class Sample(torch.nn.Module):
        def forward(self, sigma: torch.Tensor) -> torch.Tensor:
            return dtorch.igso3_sample(sigma, 3)

    batch = torch.export.Dim("batch")
    exported = torch.export.export(Sample(), (torch.tensor([0.1, 0.5]),), dynamic_shapes=({0: batch},))
    sigma = torch.tensor([1e-3, 0.2, 1.0, 3.0, 0.0])
    torch.manual_seed(3)
    got = exported.module()(sigma)
    torch.manual_seed(3)
    assert torch.equal(got, dtorch.igso3_sample(sigma, 3))
