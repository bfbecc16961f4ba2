"""The isotropic Gaussian on SO(3), IGSO(3), written once over an array namespace ``xp``.

Definition (docs/igso3.md): the density with respect to the normalised Haar measure of a rotation
whose angle to the mean is ``omega`` is the heat kernel on SO(3) at time ``sigma^2``,

    f(omega; sigma) = sum_{l >= 0} (2l + 1) exp(-l (l + 1) eps) sin((l + 1/2) omega) / sin(omega / 2),

with ``eps = sigma^2 / 2``, so that for small ``sigma`` the rotation vector is close to N(0, sigma^2 I_3).
Two exact forms of the same function are evaluated, each where it needs few terms:

- ``eps > 2``: the series itself, ``f = 1 + sum_{l=1}^{5} ...``: its terms fall as ``exp(-l (l + 1) eps)``,
  so at ``l = 6`` the next one is below ``(13)^2 exp(-84) ~ 5e-35`` relative;
- ``eps <= 2``: its Poisson dual (Poisson summation over the half-integers ``l + 1/2``),

      f = sqrt(pi) eps^(-3/2) e^(eps / 4) / (2 sin(omega / 2))
          * sum_k (-1)^k (omega + 2 pi k) e^(-(omega + 2 pi k)^2 / (4 eps)),

  taken in log space: the ``k = 0`` term's ``-omega^2 / (4 eps)`` and the prefactor are added as logs,
  and the other terms enter as ``log1p`` of their sum relative to it, whose terms ``k = +-m`` fall as
  ``(4 pi^2 m^2 / eps) exp(-pi^2 m^2 / eps)``: below 1e-17 from ``m = 4`` on at ``eps = 2`` (3 pairs).

So the log density is finite and accurate far into the tail (``f`` itself underflows there: ``log f``
is about ``-5e8`` at ``omega = pi, sigma = 1e-4``), with no truncated series and no ``+1e-6`` guard.
"""

from __future__ import annotations

import math
from typing import Any

from ._algebra import match_rank
from ._core import op

# eps = sigma^2 / 2 where the two forms trade (module docstring): both are exact to rounding there.
_SWITCH = 2.0
_PAIRS = 3  # dual terms k = +-1 ... +-3
_TERMS = 5  # series terms l = 1 ... 5


# pi in three parts: a head of 8 bits, a middle of 24 (both exact in float32 and float64) and a tail,
# so that pi - omega near omega = pi, and an angle less a multiple of 2 pi, lose no digits to the
# rounding of pi: the head times a small integer and its difference with a nearby angle are exact
# (Sterbenz), and the other parts add pi's remaining bits (~80 in all, ~56 in float32). Near pi at
# small sigma log f curves as (pi / (2 eps))^2: at sigma = 1e-4, float32's rounding of pi (8.7e-8)
# alone would move its derivative by 1e10, and float64's two-part split (61 bits) by 1e-5.
_PI_HEAD = 3.140625
_PI_MID = 9.676535846665502e-4
_PI_TAIL = 5.126688303189038e-12


def _fold(xp: Any, angle: Any) -> tuple[Any, Any]:
    """The angle reduced to [-pi, pi], and ``pi`` less its size, both to the last bit of the angle.

    f is even and 2 pi-periodic in omega, so any real angle has the density of its reduction. The
    reduction is signed, not its absolute value: the forms below are even in it, and an ``abs`` would
    make every derivative of even order vanish at ``omega = 0`` (the identity). The gap to pi is taken
    from the angle itself, not from the reduction (whose rounding, 2e-16 near pi, is 2.5e-9 of a gap
    of 8.7e-8, and the derivative of log f near pi changes by ``(pi / (2 eps))^2`` times the gap)."""
    turns = xp.round(angle * (0.5 / math.pi))
    omega = ((angle - (2.0 * _PI_HEAD) * turns) - (2.0 * _PI_MID) * turns) - (2.0 * _PI_TAIL) * turns
    above = 2.0 * turns + 1.0  # pi - omega = above pi - angle where omega >= 0
    below = 2.0 * turns - 1.0  # pi + omega = angle - below pi where omega < 0
    gap = xp.where(
        omega >= 0,
        ((above * _PI_HEAD - angle) + above * _PI_MID) + above * _PI_TAIL,
        ((angle - below * _PI_HEAD) - below * _PI_MID) - below * _PI_TAIL,
    )
    # Within a rounding of an odd multiple of pi, the reduction may land just past pi (gap < 0; e.g.
    # float32's pi is pi + 8.7e-8): the angle is then reflected to pi - |gap|, the same density.
    past = gap < 0
    gap = xp.abs(gap)
    inside = ((_PI_HEAD - gap) + _PI_MID) + _PI_TAIL
    return xp.where(past, xp.where(omega < 0, -inside, inside), omega), gap


def _smallest_eps(xp: Any, dtype: Any) -> float:
    """The smallest ``eps`` the dual form is evaluated at: ``sqrt(1e3 / max)``, so that its largest
    first derivatives, ``omega^2 / (4 eps^2)`` and the like with numerators below 1e3, stay finite
    (float32: sigma >= 1.8e-9; float64: sigma >= 2.2e-76). Below it the density is that of this
    ``eps``, and its derivative in sigma is 0 (docs/igso3.md)."""
    return math.sqrt(1e3 / float(xp.finfo(dtype).max))


# Taylor coefficients in y^2 of sinh(y) / y, 1 / (2n + 1)!, n = 0 ... 8: for |y| <= 1/2 the next term
# is below 3e-23. A polynomial, not sinh(y) / y, because the quotient's derivative, (y cosh y -
# sinh y) / y^2, cancels to a relative 1e-16 / y^2 (1e-10 at y = 1e-3).
_SINH_OVER = [1.0 / math.factorial(2 * n + 1) for n in range(9)]
# ... and of log(h / sin h), 2^(2n - 1) |B_2n| / (n (2n)!), n = 1 ... 11 (Abramowitz & Stegun 4.3.71):
# for |h| < 1/2 the next term is below 6e-21 (1.4e-19 of the value). The direct form is used above 1/2,
# where its derivative, 1/h - cot h, loses at most an ulp of 1/h.
_LOG_H_OVER_SIN_H = [
    0.16666666666666666,
    0.005555555555555556,
    0.0003527336860670194,
    2.6455026455026456e-05,
    2.1377799155576935e-06,
    1.803670234005331e-07,
    1.5661391322766983e-08,
    1.3884130493737299e-09,
    1.2504359176004997e-10,
    1.1402575602296091e-11,
    1.0502923908637557e-12,
]


def _polynomial(coefficients: list[float], z: Any) -> Any:
    """``sum_n coefficients[n] z^n`` by Horner's rule."""
    out = coefficients[-1]
    for c in reversed(coefficients[:-1]):
        out = out * z + c
    return out


def _log_h_over_sin_h(xp: Any, h: Any) -> Any:
    """``log(h / sin h)`` for ``|h| <= pi / 2`` (its series below 1/2, see ``_LOG_H_OVER_SIN_H``)."""
    small = xp.abs(h) < 0.5
    hs = xp.where(small, 1.0, h)
    h2 = h * h
    return xp.where(small, h2 * _polynomial(_LOG_H_OVER_SIN_H, h2), xp.log(hs / xp.sin(hs)))


def _log_density_dual(xp: Any, omega: Any, gap: Any, eps: Any) -> Any:
    """``log f`` by the Poisson dual, for ``|omega| <= pi`` (``gap = pi - |omega|``) and ``0 < eps <= 2``.

    Relative to the ``k = 0`` term, the pair ``k = +-m`` contributes ``(-1)^m`` times

        e^(-c) + e^(-b) - (2 pi m / w) (e^(-b) - e^(-c)),   b = pi m (pi m - w) / eps,
                                                             c = pi m (pi m + w) / eps,

    with ``w = |omega|``. Where ``x = c - b = 2 pi m w / eps >= 1`` it is evaluated so, the last part as
    ``exp(log(2 pi m / w) - b) (1 - e^(-x))``: the large factor enters through the exponent, so that a
    tiny ``eps`` meets no overflow times zero. Below, where ``omega -> 0`` would divide 0 by 0, it is the
    same function written even in ``omega``, ``2 e^(-a) cosh(y) - (4 pi^2 m^2 / eps) e^(-a) sinh(y) / y``
    with ``a = pi^2 m^2 / eps`` and ``y = pi m omega / eps`` (``|y| < 1/2``), so that every derivative at
    the identity is that of an even function."""
    log_eps = xp.log(eps)
    w = xp.abs(omega)
    total = 0.0
    for m in range(1, _PAIRS + 1):
        pm = math.pi * m
        a = pm * pm / eps
        x = (2.0 * pm) * w / eps
        wide = x >= 1.0
        # |x| >= 1: w > 0, and both exponents b, c >= 0
        ww = xp.where(wide, w, 1.0)
        b = pm * ((m - 1) * math.pi + gap) / eps
        c = pm * (pm + ww) / eps
        far = xp.exp(-c) + xp.exp(-b) - xp.exp(math.log(2.0 * pm) - xp.log(ww) - b) * -xp.expm1(-(c - b))
        # |x| < 1: even in omega
        y = xp.where(wide, 0.0, pm * omega / eps)
        near = 2.0 * xp.exp(-a) * xp.cosh(y) - xp.exp(math.log(4.0 * pm * pm) - log_eps - a) * _polynomial(
            _SINH_OVER, y * y
        )
        term = xp.where(wide, far, near)
        total = total - term if m % 2 else total + term
    return (
        (0.5 * math.log(math.pi) - 1.5 * log_eps + 0.25 * eps - omega * omega / (4.0 * eps))
        + _log_h_over_sin_h(xp, 0.5 * omega)
        + xp.log1p(total)
    )


def _log_density_series(xp: Any, omega: Any, eps: Any) -> Any:
    """``log f`` by the series, for ``eps >= 2``: ``log1p`` of its terms ``l >= 1``, with
    ``sin((l + 1/2) omega) / sin(omega / 2) = 1 + 2 sum_{j=1}^{l} cos(j omega)`` (finite at 0)."""
    total = 0.0
    kernel = 1.0
    for ell in range(1, _TERMS + 1):
        kernel = kernel + 2.0 * xp.cos(ell * omega)
        total = total + (2 * ell + 1) * xp.exp(-(ell * (ell + 1)) * eps) * kernel
    return xp.log1p(total)


@op(angle=(), sigma=())
def igso3_log_density(xp: Any, angle: Any, sigma: Any) -> Any:
    """Log density of IGSO(3) at rotations whose angle to the mean is ``angle``, with respect to the
    normalised Haar measure (docs/igso3.md).

    Args:
        angle: rotation angles ``omega`` in radians, shape ``(...)``; any real angle is reduced to
            [-pi, pi] (the density is even and 2 pi-periodic in it).
        sigma: the concentration, shape ``(...)``, broadcasting against ``angle``: the heat kernel at
            time ``sigma^2``, so that for small ``sigma`` the rotation vector is close to
            ``N(0, sigma^2 I_3)`` (papers that write ``exp(-l (l + 1) sigma^2)`` use ``sigma / sqrt(2)``
            of this one). It enters as ``sigma^2``: ``-sigma`` gives the same density. Below
            ``sqrt(2 sqrt(1e3 / finfo.max))`` (float32 1.8e-9, float64 2.2e-76) it is taken as that.

    Returns:
        ``log f(omega; sigma)``, shape the broadcast of both: finite for every finite input, accurate
        to a few ulps of the sizes of its terms in float32 and float64 from ``sigma = 1e-4`` to 10 and
        beyond, far into the tail where ``f`` underflows. Its integral against the angle's Haar
        marginal ``(1 - cos omega) / pi`` over [0, pi] is 1."""
    angle, sigma = match_rank(xp, angle, sigma)
    omega, gap = _fold(xp, angle)
    eps = 0.5 * (sigma * sigma)
    # Selections, not clip: a clip's derivative at its bound is 1/2 in jax (a tie of min or max).
    narrow = eps <= _SWITCH
    smallest = _smallest_eps(xp, eps.dtype)
    dual = _log_density_dual(
        xp, omega, gap, xp.where(narrow, xp.where(eps < smallest, smallest, eps), _SWITCH)
    )
    series = _log_density_series(xp, omega, xp.where(narrow, _SWITCH, eps))
    return xp.where(narrow, dual, series)
