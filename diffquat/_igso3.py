"""The isotropic Gaussian on SO(3), IGSO(3), written once over an array namespace ``xp``.

Definition (docs/igso3.md): the density with respect to the normalised Haar measure of a rotation
whose angle to the mean is ``omega`` is the heat kernel on SO(3) at time ``sigma^2``,

    f(omega; sigma) = sum_{l >= 0} (2l + 1) exp(-l (l + 1) eps) sin((l + 1/2) omega) / sin(omega / 2),

with ``eps = sigma^2 / 2``, so that for small ``sigma`` the rotation vector is close to N(0, sigma^2 I_3).
Two exact forms of the same function are evaluated, each where it needs few terms:

- ``eps > 1/2``: the series itself, ``f = 1 + sum_{l=1}^{9} ...``: its terms fall as ``exp(-l (l + 1)
  eps)``, so at ``l = 10`` the next one is below ``21^2 exp(-55) ~ 5e-22`` relative;
- ``eps <= 1/2``: its Poisson dual (Poisson summation over the half-integers ``l + 1/2``),

      f = sqrt(pi) eps^(-3/2) e^(eps / 4) / (2 sin(omega / 2))
          * sum_k (-1)^k (omega + 2 pi k) e^(-(omega + 2 pi k)^2 / (4 eps)),

  taken in log space: the ``k = 0`` term's ``-omega^2 / (4 eps)`` and the prefactor are added as logs,
  and the other terms relative to it, whose pairs ``k = +-m`` fall as ``(4 pi^2 m^2 / eps) exp(-pi^2
  m^2 / eps)``, through a ``logaddexp``: ``m = 2`` is below 1e-32 at ``eps = 1/2``, so one pair counts.

So the log density is finite and accurate far into the tail (``f`` itself underflows there: ``log f``
is about ``-5e8`` at ``omega = pi, sigma = 1e-4``), with no truncated series and no ``+1e-6`` guard.
"""

from __future__ import annotations

import functools
import math
from collections.abc import Callable
from typing import Any, NamedTuple

import numpy as np

from ._algebra import _canonical_components, match_rank, series_threshold
from ._core import (
    NONFINITE_BY_ARITHMETIC,
    Conversion,
    cancelling_factor,
    constants,
    matrix_to_quaternion,
    op,
    small_matmul,
    unit_quaternion_to_matrix,
)
from ._fisher import _constant
from ._statistics import repeat

# eps = sigma^2 / 2 where the two forms trade (module docstring): both are exact to rounding there,
# and the graph is small (each pair or term is ~15 operations; compilers inline them all).
_SWITCH = 0.5
_TERMS = 9  # series terms l = 1 ... 9
# the series' constants over its trailing axis j (or l) = 1 ... 9 (see _series_tails, _score_series)
_HARMONICS = tuple(float(j) for j in range(1, _TERMS + 1))
_SIZES = tuple(2.0 * j + 1.0 for j in _HARMONICS)  # 2 l + 1
_RATES = tuple(-j * (j + 1.0) for j in _HARMONICS)  # -l (l + 1)
_UPPER = tuple(tuple(1.0 if row >= col else 0.0 for col in range(_TERMS)) for row in range(_TERMS))
_ODD = tuple((-1.0) ** (j + 1) for j in range(1, _TERMS + 1))  # (-1)^(j + 1)
_EVEN = tuple(-v for v in _ODD)  # (-1)^j
_SQUARES = tuple(j * j for j in _HARMONICS)  # j^2
# the weights' sum and twice their tails, (S, 2 W_1, ..., 2 W_9): w times [1 | 2 [l >= j]]
_DOUBLED = tuple((1.0, *(2.0 * v for v in row)) for row in _UPPER)


# pi in parts: a head of 8 bits, a middle (float64: one part of 24 bits; float32: three of 8) and a
# tail, so that pi - omega near omega = pi, and an angle less a multiple of 2 pi, lose no digits to the
# rounding of pi: each part but the tail times the number of turns (or the odd multiple of pi nearest
# the angle) is exact, their differences with the angle are exact (Sterbenz), and the tail adds pi's
# remaining bits (~80 in all). Exact while the odd multiple has at most 53 - 24 = 29 bits in float64
# and 24 - 8 = 16 in float32: |angle| < _EXACT (2^30 and 2^17 rad, 1.7e8 and 2.1e4 turns), beyond
# which a reduction to the angle's last bit needs up to ~1100 bits of pi (Payne-Hanek), and the log
# density is NaN. Near pi at small sigma log f curves as (pi / (2 eps))^2: at sigma = 1e-4, float32's
# rounding of pi (8.7e-8) alone would move its derivative by 1e10, and float64's two-part split (61
# bits) by 1e-5.
_PI_HEAD = 3.140625
_PI_MID = 9.676535846665502e-4
_PI_MID_BYTES = (0.000965118408203125, 2.5331974029541016e-06, 1.979060471057892e-09)  # sum: _PI_MID
_PI_TAIL = 5.126688303189038e-12
_EXACT = {"float64": 2.0**30, "float32": 2.0**17}


def _pi_parts(xp: Any, dtype: Any) -> tuple[float, ...]:
    """pi's parts for ``dtype`` (float32 or float64): see ``_PI_HEAD``."""
    if float(xp.finfo(dtype).eps) > 1e-10:
        return (_PI_HEAD, *_PI_MID_BYTES, _PI_TAIL)
    return (_PI_HEAD, _PI_MID, _PI_TAIL)


def _exact_range(xp: Any, dtype: Any) -> float:
    """The largest ``|angle|`` (excluded) that :func:`_fold` reduces exactly in ``dtype``."""
    return _EXACT["float32" if float(xp.finfo(dtype).eps) > 1e-10 else "float64"]


def _fold(xp: Any, angle: Any, bounded: bool = False) -> tuple[Any, Any, Any]:
    """The angle reduced to [-pi, pi], ``pi`` less its size (signed: an angle within a rounding of pi
    may reduce to just past it), both to the last bit of the angle, and its size (by a selection of
    its sign: the size's derivative at 0 is 1, ``abs``'s 0); NaN from ``|angle| >= _exact_range`` on
    (see ``_PI_HEAD``).

    f is even and 2 pi-periodic in omega, so any real angle has the density of its reduction. The
    reduction is signed, not its absolute value: the forms below are even in it, and an ``abs`` would
    make every derivative of even order vanish at ``omega = 0`` (the identity). The gap to pi is taken
    from the angle itself, not from the reduction (whose rounding, 2e-16 near pi, is 2.5e-9 of a gap
    of 8.7e-8, and the derivative of log f near pi changes by ``(pi / (2 eps))^2`` times the gap)."""
    if bounded:
        # the sampler's angles, in [0, pi] (float32's pi at most): turns is 0 or 1 and the odd multiple
        # 1, so that the three parts are exact in float32 too, and no angle is beyond the range
        parts: tuple[float, ...] = (_PI_HEAD, _PI_MID, _PI_TAIL)
    else:
        parts = _pi_parts(xp, angle.dtype)
        # beyond the exact range, NaN (the angle is a branch, so that numpy keeps its dtype)
        angle = xp.where(xp.abs(angle) < _exact_range(xp, angle.dtype), angle, _number(xp, math.nan, angle))
    turns = xp.round(angle * (0.5 / math.pi))
    omega = angle
    for part in parts[:-1]:
        omega = _less_multiple(xp, omega, turns, 2.0 * part)
    omega = omega - (2.0 * parts[-1]) * turns
    # pi - |omega| = +-(odd pi - angle), with odd = 2 turns +- 1 the odd multiple of pi nearest the
    # angle on omega's side: sign (+-1) times a sum, both exact
    sign = _signs(xp, omega < 0, omega)
    odd = 2.0 * turns + sign
    size = odd * parts[0] - angle
    for part in parts[1:-1]:
        size = _less_multiple(xp, size, odd, -part)
    size = size + odd * parts[-1]
    gap = sign * size
    # Within a rounding of an odd multiple of pi the reduction may land just past pi (float32's pi is
    # pi + 8.7e-8): the gap is then negative, and the dual form below takes it so (its k = -1 term then
    # leads, in log space). No reflection of omega: inductor inlines the reduction at each of its many
    # uses, and a selection on it made compiling the log density take minutes.
    return omega, gap, sign * omega


def _less_multiple(xp: Any, a: Any, b: Any, c: float) -> Any:
    """``a - c b``, for a product ``c b`` that is exact (so that one rounding is taken either way): in
    eager torch one operation (``sub`` with ``alpha``), else two."""
    if _eager(xp, a):
        return xp.sub(a, b, alpha=c)
    return a - c * b


def _signs(xp: Any, negative: Any, like: Any) -> Any:
    """-1 where ``negative``, else 1, in ``like``'s dtype (a ``where`` of two Python numbers would be
    float64 on NumPy)."""
    if _eager(xp, like):
        return xp.where(negative, _kept(xp, -1.0, like), _kept(xp, 1.0, like))
    one = xp.ones_like(like)
    return xp.where(negative, -one, one)


def _smallest_eps(xp: Any, dtype: Any) -> float:
    """The smallest ``eps`` the dual form is evaluated at: ``sqrt(1e3 / max)``, so that its largest
    first derivatives, ``omega^2 / (4 eps^2)`` and the like with numerators below 1e3, stay finite
    (float32: sigma >= 1.85e-9; float64: sigma >= 6.9e-77). Below it the density is that of this
    ``eps``, and its derivative in sigma is 0 (docs/igso3.md)."""
    return math.sqrt(1e3 / float(xp.finfo(dtype).max))


# Taylor coefficients of (1 - e^(-x)) / x, (-1)^n / (n + 1)!, n = 0 ... 4, used below x = 1e-3 (the next
# term is below 2e-18 there). Not -expm1(-x) / x there, because the quotient's derivative, (x e^(-x) -
# (1 - e^(-x))) / x^2, cancels to a relative 1e-16 / x^2; from 1e-3 on that is 1e-10 of a term whose
# weight in log f is at most 2e-7 (eps <= 1/2): below an ulp.
_ONE_MINUS_EXP_OVER = [(-1.0) ** n / math.factorial(n + 1) for n in range(5)]
# ... and of log(h / sin h), 2^(2n - 1) |B_2n| / (n (2n)!), n = 1 ... 6 (Abramowitz & Stegun 4.3.71),
# used below h = 0.1 (the next term is below 2e-18 of the value). The direct form is used above, where
# its derivative, 1/h - cot h, loses at most an ulp of 1/h (10 ulps of the derivative's size, 1).
_LOG_H_OVER_SIN_H = [
    0.16666666666666666,
    0.005555555555555556,
    0.0003527336860670194,
    2.6455026455026456e-05,
    2.1377799155576935e-06,
    1.803670234005331e-07,
]


# What the score needs, each divided by its argument analytically (see _score_dual): the series of
# psi2(x) = (phi + 2 phi') / x = sum_{n>=1} (-1)^(n+1) n x^(n-1) / (n+2)!, phi(x) = (1 - e^(-x)) / x, used
# below x = 0.01 (the next term is below 2e-14 of the value, in a part of weight below 3e-6); of
# (d/dh log(h / sin h)) / (4 h) = sum_n (n c_n / 2) h^(2n - 2), below h = 0.1; of sin(t) / t, 1 - t^2 / 6
# + t^4 / 120, below t = 0.01 (next term below 2e-16).
_PSI2 = [(-1.0) ** (n + 1) * n / math.factorial(n + 2) for n in range(1, 6)]
_LOG_H_OVER_SIN_H_SLOPE = [0.5 * n * c for n, c in enumerate(_LOG_H_OVER_SIN_H, start=1)]
_SINC = [1.0, -1.0 / 6.0, 1.0 / 120.0]


def _eager(xp: Any, like: Any) -> bool:
    """Whether ``like`` is a plain tensor of an eager torch call: there a constant made on every call is
    an operation of its own (``lift_fresh``, and ``scalar_tensor`` for a Python number in a ``where``),
    so the constants below are made once per dtype and device and kept. Not under capture (a tracer's
    tensor must not be kept for later calls), nor on jax and NumPy, where a constant costs nothing."""
    tensor = getattr(xp, "Tensor", None)
    return type(like) is tensor and not (xp.compiler.is_compiling() or xp.jit.is_tracing())


@functools.cache
def _maker(values: Any) -> Callable[[], tuple[Any, ...]]:
    """The maker, for ``_core.constants``, of the constant ``values`` (nested tuples of numbers; a
    number: a 0-d array), as floats: one per distinct ``values``, so each is made once per dtype and
    device and kept where ``constants`` keeps its own (not inside a ``torch.func`` transform)."""

    def floats(v: Any) -> Any:
        return [floats(u) for u in v] if isinstance(v, tuple) else float(v)

    return lambda: (floats(values),)


def _kept(xp: Any, values: Any, like: Any) -> Any:
    """The constant ``values`` in ``like``'s dtype and device, made once (``_core.constants``)."""
    return constants(xp, like, _maker(values))[0]


def _number(xp: Any, value: float, like: Any) -> Any:
    """``value`` as the branch of a ``where`` beside ``like``: a kept 0-d tensor in eager torch (see
    :func:`_eager`), else the number itself."""
    return _kept(xp, value, like) if _eager(xp, like) else value


def _fill(xp: Any, where: Any, value: float, x: Any) -> Any:
    """``value`` where ``where``, else ``x`` (``where`` broadcasting to ``x``'s shape): in eager torch
    ``masked_fill``, whose backward is one operation (``where``'s makes a zero of its own first: a
    ``scalar_tensor`` per differentiated call), else a ``where``."""
    if _eager(xp, x):
        return x.masked_fill(where, value)
    return xp.where(where, _number(xp, value, x), x)


def _row(xp: Any, values: tuple[float, ...], like: Any, rank: int) -> Any:
    """A constant 1-D array of ``like``'s dtype and device over a trailing axis of an array of rank
    ``rank``: kept in eager torch (which broadcasts it over the leading axes), else ``_constant``."""
    if _eager(xp, like):
        return _kept(xp, values, like)
    return _constant(xp, list(values), like, rank)


def _polynomial(xp: Any, coefficients: list[float], z: Any) -> Any:
    """``sum_n coefficients[n] z^n`` by Horner's rule: in eager torch one ``addcmul`` a step (the same
    two roundings as a product and a sum)."""
    if _eager(xp, z):
        out = _kept(xp, coefficients[-1], z)
        for c in reversed(coefficients[:-1]):
            out = xp.addcmul(_kept(xp, c, z), out, z)
        return out
    out = coefficients[-1]
    for c in reversed(coefficients[:-1]):
        out = out * z + c
    return out


def _log_h_over_sin_h(xp: Any, h: Any) -> Any:
    """``log(h / sin h)`` for ``|h| <= pi / 2`` (its series below 0.1, see ``_LOG_H_OVER_SIN_H``)."""
    h2 = h * h
    small = h2 < 0.01  # |h| < 0.1, on the square the series takes (one operation fewer than abs)
    hs = _fill(xp, small, 1.0, h)
    return xp.where(small, h2 * _polynomial(xp, _LOG_H_OVER_SIN_H, h2), xp.log(hs / xp.sin(hs)))


def _log_density_dual(xp: Any, omega: Any, gap: Any, size: Any, at: _Concentration) -> Any:
    """``log f`` by the Poisson dual, for ``|omega| <= pi`` (``gap = pi - |omega|``, signed) and ``0 <
    eps <= 1/2``, where the pair ``k = +-1`` is the only one that counts.

    Relative to the ``k = 0`` term, ``1 + `` that pair is ``T = (1 - e^(-c)) + e^(-b) A`` with ``w =
    |omega|``, ``b = pi gap / eps``, ``c = pi (pi + w) / eps``, ``x = 2 pi w / eps`` and ``A = (4 pi^2 /
    eps) (1 - e^(-x)) / x - 1 >= 1`` (``(2 pi / w)(e^(-b) - e^(-c)) = (4 pi^2 / eps) e^(-b) (1 - e^(-x)) /
    x``: no 0 / 0 at the identity). ``log T`` is the ``logaddexp`` of ``log(1 - e^(-c))`` and ``-b + log
    A``, with ``log A`` from ``log((4 pi^2 / eps) (1 - e^(-x)) / x)``: no overflow for any ``eps``, and
    just past pi (``b < 0``), where the ``k = -1`` term leads, its exponent is exact. ``w`` is taken by a
    selection, whose derivative at 0 is 1 (``abs``'s is 0): ``T`` is even in ``w``, so every derivative
    at the identity is exact."""
    _, _, log_t = _dual_pair(xp, size, gap, at)
    return (at.head - omega * omega / at.four_eps) + _log_h_over_sin_h(xp, 0.5 * omega) + log_t


def _dual_pair(xp: Any, w: Any, gap: Any, at: _Concentration) -> tuple[Any, Any, Any]:
    """``x``, ``log((1 - e^(-x)) / x)`` and ``log T`` of :func:`_log_density_dual`, at ``w = |omega|``
    (see :func:`_fold`)."""
    eps = at.eps
    x = (2.0 * math.pi) * w / eps
    near = x < 1e-3
    xs = _fill(xp, near, 1.0, x)
    log_ratio = xp.where(
        near,
        xp.log(_polynomial(xp, _ONE_MINUS_EXP_OVER, xp.where(near, x, _number(xp, 0.0, x)))),
        xp.log(-xp.expm1(-xs)) - xp.log(xs),
    )
    log_ka = at.log_k + log_ratio  # log((4 pi^2 / eps) (1 - e^-x) / x)
    log_a = log_ka + xp.log1p(-xp.exp(-log_ka))
    minus_c = -math.pi * (math.pi + w) / eps  # -c itself (the negated constant is exact)
    return x, log_ratio, xp.logaddexp(xp.log1p(-xp.exp(minus_c)), log_a - math.pi * gap / eps)


def _series_tails(xp: Any, eps: Any) -> tuple[Any, Any, Any]:
    """The series' harmonics and weights over a trailing axis ``j = 1 ... 9``, of ``eps`` alone: ``j``,
    the weights' sum ``S = sum_l w_l``, ``w_l = (2l + 1) e^(-l (l + 1) eps)``, and their tails ``W_j =
    sum_{l >= j} w_l`` (a product with the constant 0/1 matrix ``[l >= j]``: each tail summed directly, not as
    ``S`` less a partial sum, which near pi, where f is small, would cost ~10 ulps). With the kernel
    ``sin((l + 1/2) omega) / sin(omega / 2) = 1 + 2 sum_{j <= l} cos(j omega)``, ``sum_l w_l kernel_l
    = S + 2 sum_j W_j cos(j omega)``: one ``cos`` and one ``exp`` of a (..., 9) array (a smaller graph
    for the compilers)."""
    return _row(xp, _HARMONICS, eps, eps.ndim + 1), *_tails(xp, _series_weights(xp, eps))


def _series_weights(xp: Any, eps: Any) -> Any:
    """The series' weights ``w_l = (2l + 1) e^(-l (l + 1) eps)``, ``l = 1 ... 9``, over a trailing axis."""
    return _row(xp, _SIZES, eps, eps.ndim + 1) * xp.exp(_row(xp, _RATES, eps, eps.ndim + 1) * eps[..., None])


def _tails(xp: Any, w: Any) -> tuple[Any, Any]:
    """The weights' sum and tails (see :func:`_series_tails`)."""
    eps = w
    if _eager(xp, eps):
        upper = _kept(xp, _UPPER, eps)
    else:
        upper = xp.reshape(_constant(xp, [v for r in _UPPER for v in r], eps, 1), (_TERMS, _TERMS))
    tails = xp.matmul(w, upper)
    return tails[..., 0], tails


def _log_density_series(xp: Any, omega: Any, at: _Concentration) -> Any:
    """``log f`` by the series, for ``eps >= 1/2``: ``log1p`` of its terms ``l >= 1`` (see
    :func:`_series_tails`; finite at 0)."""
    # sum_j T_j cos(j omega), j = 0 ... 9: T_0 = S, T_j = 2 W_j (_concentration)
    return xp.log1p(xp.sum(at.tails * xp.cos(at.ell * omega[..., None]), axis=-1))


def _score_dual(xp: Any, omega: Any, gap: Any, at: _Concentration) -> Any:
    """``(d log f / d omega) / omega`` by the dual form, each part divided by omega analytically.

    Of ``log T``: with ``T = (1 - e^(-c)) + e^(-b) A`` (see :func:`_log_density_dual`), ``T' = (pi / eps)
    e^(-b) (e^(-x) - 1 + (4 pi^2 / eps)(phi + 2 phi'))`` for ``phi(x) = (1 - e^(-x)) / x``, and ``e^(-x) -
    1 = -x phi``, ``phi + 2 phi' = x psi2(x)``, so ``T' / (w T) = (2 pi^2 / eps^2) ((4 pi^2 / eps) psi2 -
    phi) e^(-b) / T``, the last factor as ``exp(-b - log T)``. Of the rest: ``-1 / (2 eps)``, and
    ``(1 / h - cot h) / (4 h)`` with ``h = omega / 2``."""
    eps = at.eps
    x, log_ratio, log_t = _dual_pair(xp, omega, gap, at)  # omega >= 0 here
    near = x < 0.01
    xs = _fill(xp, near, 1.0, x)
    minus = -xs
    psi2 = xp.where(
        near,
        _polynomial(xp, _PSI2, xp.where(near, x, _number(xp, 0.0, x))),
        (xs * (1.0 + xp.exp(minus)) + 2.0 * xp.expm1(minus)) / (xs * xs * xs),
    )
    # 2 pi^2 / eps^2 as a product, not inside the exp: an exponent of size ~40 would carry ~40 ulps
    # into a term that near pi cancels against -omega / (2 eps) (both ~pi / sigma^2)
    weight = (2.0 * math.pi**2) / (eps * eps) * xp.exp(-math.pi * gap / eps - log_t)
    pair = weight * ((4.0 * math.pi**2) * psi2 / eps - xp.exp(log_ratio))
    h = 0.5 * omega
    h2 = h * h
    small = h2 < 0.01  # |h| < 0.1, as in _log_h_over_sin_h
    hs = _fill(xp, small, 1.0, h)
    sine = xp.where(
        small,
        _polynomial(xp, _LOG_H_OVER_SIN_H_SLOPE, h2),
        (1.0 / hs - xp.cos(hs) / xp.sin(hs)) / (4.0 * hs),
    )
    # Beyond pi / 2 the form about pi: here -1 / (2 eps) and the pair cancel to the score's size,
    # ~gap (pi / sigma^2)^2, which near pi is far below theirs, ~1 / sigma^2
    far = -0.5 / eps + sine + pair
    near = gap < omega
    return xp.where(near, _score_dual_near_pi(xp, near, omega, gap, eps), far)


def _score_dual_near_pi(xp: Any, near: Any, omega: Any, gap: Any, eps: Any) -> Any:
    """``(d log f / d omega) / omega`` by the dual form about pi, where ``near`` (``omega > pi / 2``;
    elsewhere a finite stand-in). The dual's terms pair up as reflections about pi, ``k`` with ``-1 -
    k``: with ``g = pi - omega`` (the gap), ``m = 2k + 1`` and ``a = pi g / (2 eps)``, each pair is ``2
    (-1)^k e^(-(m^2 pi^2 + g^2) / (4 eps)) (m pi cosh(m a) - g sinh(m a))``, even in ``g``. The pairs
    ``m = 1, 3`` count (``m = 5`` is below ``e^(-4 pi^2 / eps)``, 1e-34, of the first); relative to the
    first the second is ``rho (3 pi - g tanh 3a)`` with ``rho = e^(-2 pi^2 / eps) cosh(3a) / cosh(a) =
    e^(-pi (2 pi - g) / eps) (1 + e^(-6a)) / (1 + e^(-2a))`` (below 1.4e-13 for ``g <= pi / 2``, no
    overflow for any eps). Differentiating in ``g``,

        d log f / d omega = g / (2 eps) - N / D - tan(g / 2) / 2,
        N = ((pi^2 / (2 eps) - 1) tanh(a) - a) - rho ((9 pi^2 / (2 eps) - 1) tanh(3a) - 3a),
        D = (pi - g tanh(a)) - rho (3 pi - g tanh(3a)),

    every term odd in ``g`` and computed to its last bits from the gap (taken from the quaternion): the
    score is 0 at pi exactly, and near it accurate relative to its own size, ``~g (pi / sigma^2)^2``,
    where the form about the identity cancels to it from terms of size ``1 / sigma^2``. What cancels
    here is bounded by ``g < omega``: ``g / (2 eps) - N / D`` to ``-omega / (2 eps)`` (a factor ``pi /
    omega < 2``) and, as ``g -> 0``, ``N`` to ``a (pi^2 / (2 eps) - 2)`` and then ``g / (2 eps) - N /
    D`` to ``(g / (2 eps)) (3 - pi^2 / (2 eps))`` (factors below 1.3 and 1.5 for ``eps <= 1/2``)."""
    g = xp.where(near, gap, _number(xp, 0.0, gap))
    w = xp.where(near, omega, _number(xp, math.pi, omega))
    a = (0.5 * math.pi) * g / eps
    t1, t3 = xp.tanh(a), xp.tanh(3.0 * a)
    rho = xp.exp(-math.pi * (2.0 * math.pi - g) / eps) * (1.0 + xp.exp(-6.0 * a)) / (1.0 + xp.exp(-2.0 * a))
    n = ((0.5 * math.pi**2) / eps - 1.0) * t1 - a - rho * (((4.5 * math.pi**2) / eps - 1.0) * t3 - 3.0 * a)
    d = (math.pi - g * t1) - rho * (3.0 * math.pi - g * t3)
    return (0.5 * g / eps - n / d - 0.5 * xp.tan(0.5 * g)) / w


def _score_series(xp: Any, omega: Any, gap: Any, at: _Concentration) -> Any:
    """``(d log f / d omega) / omega`` by the series: the kernel's derivative over omega is ``-2 sum_j
    j^2 sin(j omega) / (j omega)`` (:func:`_series_tails`), ``sin(t) / t`` by its series below 0.01.
    Beyond pi / 2 the harmonics are taken from the gap ``g = pi - omega``: ``sin(j omega) = (-1)^(j + 1)
    sin(j g)`` and ``cos(j omega) = (-1)^j cos(j g)``. Near pi the score is ``~g``, and ``sin(j omega)``
    of a rounded omega would be off by its rounding (float32's 2.4e-7 at pi: 10% of a gap of 1e-6)."""
    ell, total, tails = at.ell, at.total, at.tails
    reflect = (gap < omega)[..., None]
    theta = xp.where(reflect, gap[..., None], omega[..., None])
    one = _number(xp, 1.0, omega)
    odd = _row(xp, _ODD, omega, omega.ndim + 1)
    even = _row(xp, _EVEN, omega, omega.ndim + 1)
    sines = xp.where(reflect, odd, one) * xp.sin(ell * theta)
    cosines = xp.where(reflect, even, one) * xp.cos(ell * theta)
    t = ell * omega[..., None]
    t2 = t * t
    small = t2 < 1e-4  # |t| < 0.01, on the square the series takes
    ts = _fill(xp, small, 1.0, t)
    sinc = xp.where(small, _polynomial(xp, _SINC, t2), sines / ts)
    slope = -2.0 * xp.sum(tails * _row(xp, _SQUARES, omega, omega.ndim + 1) * sinc, axis=-1)
    return slope / (1.0 + total + 2.0 * xp.sum(tails * cosines, axis=-1))


def _forms(xp: Any, sigma: Any) -> tuple[Any, Any, Any]:
    """Whether the dual form applies at ``sigma``, and ``eps = sigma^2 / 2`` as the dual (at least
    :func:`_smallest_eps`) and the series take it, each the switch where the other applies.
    Selections, not clip: a clip's derivative at its bound is 1/2 in jax (a tie of min or max)."""
    eps = 0.5 * (sigma * sigma)
    narrow = eps <= _SWITCH
    smallest = _smallest_eps(xp, eps.dtype)
    switch = _number(xp, _SWITCH, eps)
    return (
        narrow,
        xp.where(narrow, _fill(xp, eps < smallest, smallest, eps), switch),
        _fill(xp, narrow, _SWITCH, eps),
    )


class _Concentration(NamedTuple):
    """What the log density and the score take of ``sigma`` alone, made once per sigma
    (:func:`_concentration`; the sampler's steps share it): the two forms' ``eps`` and their terms
    in ``eps`` alone."""

    narrow: Any  # where the dual form applies
    eps: Any  # the dual form's eps (see _forms)
    log_k: Any  # log(4 pi^2 / eps), of the dual's pair
    head: Any  # 0.5 log(pi) - 1.5 log(eps) + eps / 4, the dual's terms in eps (None for the score)
    four_eps: Any  # 4 eps (None for the score)
    # the series' harmonics, weights' sum and tails (_series_tails); for the log density the
    # harmonics j = 0 ... 9 and the sum and twice the tails as one array, (S, 2 W_1, ..., 2 W_9)
    ell: Any
    total: Any
    tails: Any


def _concentration(xp: Any, sigma: Any, density: bool = True, forms: Any = None) -> _Concentration:
    """:class:`_Concentration` at ``sigma``; ``density``: with the log density's terms; ``forms``:
    :func:`_forms` of sigma, where made already."""
    narrow, eps, eps_series = _forms(xp, sigma) if forms is None else forms
    log_eps = xp.log(eps)
    head = four_eps = None
    if density:
        # 0.5 log(pi) - 1.5 log(eps) + eps / 4, the same roundings in one operation fewer in eager torch
        head = _less_multiple(xp, -1.5 * log_eps + 0.5 * math.log(math.pi), eps, -0.25)
        four_eps = 4.0 * eps
    log_k = math.log(4.0 * math.pi * math.pi) - log_eps
    if not density:
        return _Concentration(narrow, eps, log_k, head, four_eps, *_series_tails(xp, eps_series))
    w = _series_weights(xp, eps_series)
    if _eager(xp, w):
        doubled = _kept(xp, _DOUBLED, w)
    else:
        doubled = xp.reshape(_constant(xp, [v for r in _DOUBLED for v in r], w, 1), (_TERMS, _TERMS + 1))
    ell = _row(xp, (0.0, *_HARMONICS), eps, eps.ndim + 1)
    return _Concentration(narrow, eps, log_k, head, four_eps, ell, None, xp.matmul(w, doubled))


@op(angle=(), sigma=())
def igso3_log_density(xp: Any, angle: Any, sigma: Any) -> Any:
    """Log density of IGSO(3) at rotations whose angle to the mean is ``angle``, with respect to the
    normalised Haar measure (docs/igso3.md).

    Args:
        angle: rotation angles ``omega`` in radians, shape ``(...)``; an angle is reduced to [-pi,
            pi] exactly (the density is even and 2 pi-periodic in it) below ``2^30`` rad in float64
            and ``2^17`` in float32; from there on the result is NaN (an exact reduction would need
            up to ~1100 bits of pi).
        sigma: the concentration, shape ``(...)``, broadcasting against ``angle``: the heat kernel at
            time ``sigma^2``, so that for small ``sigma`` the rotation vector is close to
            ``N(0, sigma^2 I_3)`` (papers that write ``exp(-l (l + 1) sigma^2)`` use ``sigma / sqrt(2)``
            of this one). It enters as ``sigma^2``: ``-sigma`` gives the same density. Below
            ``sqrt(2 sqrt(1e3 / finfo.max))`` (float32 1.85e-9, float64 6.9e-77) it is taken as that.

    Returns:
        ``log f(omega; sigma)``, shape the broadcast of both: finite for every finite sigma and
        every angle in the exact range, accurate to a few ulps of the sizes of its terms in float32
        and float64 from ``sigma = 1e-4`` to 10 and beyond, far into the tail where ``f``
        underflows. Its integral against the angle's Haar
        marginal ``(1 - cos omega) / pi`` over [0, pi] is 1."""
    return _log_density(xp, angle, sigma)


def _log_density(xp: Any, angle: Any, sigma: Any, bounded: bool = False) -> Any:
    """:func:`igso3_log_density`; ``bounded``: for angles known to be in [0, pi] (the sampler's),
    with fewer operations (see :func:`_fold`)."""
    angle, sigma = match_rank(xp, angle, sigma)
    return _log_density_at(xp, angle, _concentration(xp, sigma), bounded)


def _log_density_at(xp: Any, angle: Any, at: _Concentration, bounded: bool = False) -> Any:
    """:func:`_log_density` at a concentration made beforehand (``angle`` of its rank)."""
    omega, gap, size = _fold(xp, angle, bounded)
    return xp.where(
        at.narrow, _log_density_dual(xp, omega, gap, size, at), _log_density_series(xp, omega, at)
    )


@op(matrix=(3, 3), sigma=(), mean=(3, 3))
def igso3_score(
    xp: Any, matrix: Any, sigma: Any, mean: Any = None, *, to_quaternion: Conversion = matrix_to_quaternion
) -> Any:
    """The score of IGSO(3), the gradient of its log density at rotation matrices, as body-frame
    tangent vectors (docs/igso3.md).

    Args:
        matrix: rotation matrices ``R``, shape ``(..., 3, 3)`` (column vectors, active).
        sigma: the concentration, shape ``(...)``, as in :func:`igso3_log_density`, broadcasting against
            the batch of ``matrix``.
        mean: the distribution's mean rotation, ``(..., 3, 3)``, or None for the identity.

    Returns:
        ``(..., 3)``: with ``phi = log(mean^T R)`` (the rotation vector, angle ``omega = |phi|`` in [0,
        pi]), ``(d log f / d omega) phi / omega``, the derivative of ``delta -> log p(R exp(delta))``
        at 0 (``phi`` is fixed by the Jacobians of log, so none appears); the space-frame gradient, of
        ``exp(delta) R``, is ``R @ score``. The factor ``(d log f / d omega) / omega`` is written out
        with each part divided by omega analytically: exact at the identity, where the score is 0 and
        its derivative is ``(d^2 log f / d omega^2)(0)`` times the identity; beyond pi / 2 it is
        written in the gap to pi (taken from the quaternion, not as pi less a rounded angle), odd in
        it: 0 exactly at a half-turn, and near it accurate relative to its own size, ~``gap (pi /
        sigma^2)^2``, in float32 as in float64."""
    relative = matrix
    if mean is not None:
        mean, matrix = match_rank(xp, mean, matrix)
        relative = small_matmul(xp, xp.swapaxes(mean, -1, -2), matrix)
    # From the relative rotation's quaternion (w >= 0): the angle 2 atan2(s, w) and its gap to pi,
    # 2 atan2(w, s), each without cancellation (pi - omega from a rounded omega would be off by pi's
    # rounding, 1.2e-16, which near pi moves the score by (pi / sigma^2)^2 times as much).
    w, x, y, z = _canonical(xp, to_quaternion(xp, relative))
    squared = x * x + y * y + z * z
    positive = squared > 0
    # |xyz| with a zero derivative at 0: the factor is even in omega, so its derivative there is 0
    one, zero = _number(xp, 1.0, squared), _number(xp, 0.0, squared)
    s = xp.where(positive, xp.sqrt(xp.where(positive, squared, one)), zero)
    omega = 2.0 * xp.atan2(s, w)
    gap = 2.0 * xp.atan2(w, s)
    # phi = k xyz, k = omega / s, as quaternion_to_axis_angle takes it (the same values): its series
    # in r^2 = s^2 / w^2 near the identity (there w >= |q| / sqrt(2) > 0), else omega itself over s
    small = squared < series_threshold(xp, squared.dtype) * (w * w)
    r2 = xp.where(small, squared / xp.where(small, w * w, one), zero)
    series = (2.0 / xp.where(small, w, one)) * _polynomial(xp, [1.0, -1.0 / 3.0, 0.2], r2)
    k = xp.where(small, series, omega / _fill(xp, small, 1.0, s))
    omega, gap, sigma = match_rank(xp, omega, gap, sigma)
    at = _concentration(xp, sigma, density=False)
    factor = xp.where(at.narrow, _score_dual(xp, omega, gap, at), _score_series(xp, omega, gap, at))
    phi = k[..., None] * xp.stack([x, y, z], axis=-1)
    factor, phi = match_rank(xp, factor[..., None], phi)
    return factor * phi


def _canonical(xp: Any, q: Any) -> tuple[Any, Any, Any, Any]:
    """:func:`_algebra._canonical_components` of scalar-first ``q`` (zero -> identity, then the sign that
    makes the first non-zero component positive), the same values; in eager torch over the
    ``(..., 4)`` axis: the first non-zero component's sign is that of ``sign(q) . (8, 4, 2, 1)``, a sum
    of small integers and so exact in any order (no choice rides on a rounding)."""
    if not _eager(xp, q):
        return _canonical_components(xp, q, True)
    squares = xp.unbind(q * q, dim=-1)
    n2 = squares[0] + squares[1] + squares[2] + squares[3]  # nonzero_or_identity's order
    q = xp.where((n2 < xp.finfo(q.dtype).tiny)[..., None], _kept(xp, (1.0, 0.0, 0.0, 0.0), q), q)
    flip = xp.matmul(xp.sign(q), _kept(xp, (8.0, 4.0, 2.0, 1.0), q)) < 0
    w, x, y, z = xp.unbind(xp.where(flip[..., None], -q, q), dim=-1)
    return w, x, y, z


def _erf(xp: Any, x: Any) -> Any:
    """``erf`` of the namespace (``torch.erf``, ``jax.lax.erf``); on NumPy, which has none, Python's
    ``math.erf`` element by element in float64 (within an ulp), in the input's dtype."""
    erf = getattr(xp, "erf", None)
    if erf is not None:
        return erf(x)
    return np.vectorize(math.erf, otypes=[np.float64])(x).astype(x.dtype)


# Gauss-Legendre nodes and weights on [0, 1] for the integral in _cdf_dual_part: its integrand
# exp(d^2 t^2) sin(a t) is entire, with a <= 3 pi / 2 and d^2 <= 1/8, and 16 nodes integrate it to
# below 1e-17 (the rule is exact to degree 31; the Taylor terms of degree 32 and beyond are below
# (3 pi / 2)^32 / 32! ~ 1e-14 and the rule's error on them a further ~2^-32 of that).
_GL_NODES, _GL_WEIGHTS = (
    tuple(float(v) for v in 0.5 * (part + 1.0)) if i == 0 else tuple(float(v) for v in 0.5 * part)
    for i, part in enumerate(np.polynomial.legendre.leggauss(16))
)
# half the weights: the bracket of _cdf_dual takes sqrt(eps) / 2 times the integral (a power of two, so
# the same values to the bit as halving the product), in one operation fewer
_GL_HALF_WEIGHTS = tuple(0.5 * w for w in _GL_WEIGHTS)
_CDF_HARMONICS = tuple(float(k) for k in range(1, _TERMS + 2))  # sin(k omega), k = 1 ... 10
# (t / 2)^2 at the nodes t, so that the integrand's e^(d^2 t^2) is e^(eps (t / 2)^2)
_GL_QUARTER_SQUARES = tuple(0.25 * t * t for t in _GL_NODES)
# The series' CDF, sum_l w_l (sin(l omega) / l - sin((l + 1) omega) / (l + 1)) - sin(omega), regrouped by
# harmonic: sin(k omega) has (w_k - w_(k-1)) / k, with w_10 = 0 and w_0 = 1 (the -sin(omega)): the
# coefficients are w times the (9, 10) matrix of +-1 / k, plus -1 at k = 1.
_CDF_DIFFERENCES = tuple(
    tuple((1.0 if k == ell else -1.0 if k == ell + 1 else 0.0) / k for k in range(1, _TERMS + 2))
    for ell in range(1, _TERMS + 1)
)
_CDF_FIRST = (-1.0,) + (0.0,) * _TERMS


class _CdfConcentration(NamedTuple):
    """What the angle's CDF takes of ``sigma`` alone (:func:`_cdf_concentration`), made once per
    sigma (the sampler's steps share it); ``(..., 1)`` arrays over the trailing axis of the dual form's
    three parts, the series' coefficients over its harmonics."""

    narrow: Any  # where the dual form applies (see _forms)
    root: Any  # sqrt(eps)
    quarter: Any  # e^(eps / 4)
    weights: Any  # half the quadrature's weights times e^(eps t^2 / 4) at its nodes t, (..., 1, 16)
    ell: Any  # the series' harmonics l = 1 ... 10 and their coefficients (see _cdf_series)
    coefficients: Any
    # for the density beside the CDF (_cdf_and_density; else None): 2 e^(eps / 4) / (sqrt(pi) eps),
    # (..., 1), and the series' weights' sum and tails (_series_tails), the latter with a tenth of 0
    scale: Any
    total: Any
    tails: Any


def _cdf_concentration(xp: Any, sigma: Any, forms: Any = None, density: bool = False) -> _CdfConcentration:
    """:class:`_CdfConcentration` at ``sigma`` (``forms``: as in :func:`_concentration`; ``density``:
    with what :func:`_cdf_and_density` needs)."""
    narrow, eps, eps_series = _forms(xp, sigma) if forms is None else forms
    e = eps[..., None]
    root = xp.sqrt(e)
    growth = xp.exp(e[..., None] * _row(xp, _GL_QUARTER_SQUARES, e, e.ndim + 1))
    weights = _row(xp, _GL_HALF_WEIGHTS, e, e.ndim + 1) * growth
    ell = _row(xp, _CDF_HARMONICS, eps, eps.ndim + 1)
    w = _series_weights(xp, eps_series)
    if _eager(xp, w) and w.ndim == 2:
        coefficients = xp.addmm(_kept(xp, _CDF_FIRST, w), w, _kept(xp, _CDF_DIFFERENCES, w))
    else:
        differences = xp.reshape(
            _constant(xp, [v for r in _CDF_DIFFERENCES for v in r], w, 1), (_TERMS, _TERMS + 1)
        )
        coefficients = xp.matmul(w, differences) + _row(xp, _CDF_FIRST, w, w.ndim)
    quarter = xp.exp(0.25 * e)
    scale = total = tails = None
    if density:
        # not eps^(-3/2): each operation's derivative stays finite down to the smallest eps (forward
        # mode multiplies a zero tangent by it: the sampler's sigma below the smallest)
        scale = quarter / ((0.5 * math.sqrt(math.pi)) * e)
        total, tails = _tails(xp, w)
        tails = xp.concat([tails, xp.zeros_like(w[..., :1])], axis=-1)
    return _CdfConcentration(narrow, root, quarter, weights, ell, coefficients, scale, total, tails)


def _cdf_dual(xp: Any, omega: Any, at: _CdfConcentration) -> tuple[Any, Any, Any, Any]:
    """``F(omega)`` for ``omega`` in [0, pi], ``0 < eps <= 1/2``: the wrapped sum ``sum_k P(omega + 2 pi
    k) - P(2 pi k)`` of the odd ``P``, of which ``k = 0, +-1`` count (the pair ``k = +-2`` differs from 0
    by ``erfc(3 pi / (2 sqrt(eps)))``, below 1e-20): ``(P(omega) - P(2 pi - omega)) + P(2 pi +
    omega)``, ordered so that ``F(0) = 0`` and ``F(pi) = P(3 pi) = 1`` exactly.

    ``P(u)``, the antiderivative from 0 of ``u sin(u / 2) exp(-u^2 / (4 eps))`` times ``eps^(-3/2) e^(eps
    / 4) / sqrt(pi)`` (docs/igso3.md), of the three ``u`` over a trailing axis, is

        Re erf(x - i d) - (2 / sqrt(pi)) e^(eps / 4) sin(u / 2) e^(-x^2) / sqrt(eps),

    ``x = u / (2 sqrt(eps))``, ``d = sqrt(eps) / 2``, with ``Re erf(x + i d) = erf(x) + (2 / sqrt(pi))
    e^(-x^2) d int_0^1 e^(d^2 t^2) sin((u / 2) t) dt`` (the derivative of erf along the imaginary axis,
    integrated), the integral by Gauss-Legendre (``_GL_NODES``) over a further trailing axis: one
    ``sin`` of a (..., 3, 16) array, not 48 (``e^(d^2 t^2)`` is of sigma alone). No complex
    arithmetic, and ``e^(-x^2)`` multiplies only bounded factors (it underflows to 0 in the tail).

    Returns ``F``, and for :func:`_cdf_and_density` the three ``x``, ``sin(u / 2)`` and ``e^(-x^2)``."""
    # a = u / 2 of omega, 2 pi - omega, 2 pi + omega: each one rounding, as their sums and differences
    a = omega[..., None] * _row(xp, (0.5, -0.5, 0.5), omega, omega.ndim + 1) + _row(
        xp, (0.0, math.pi, math.pi), omega, omega.ndim + 1
    )
    x = a / at.root
    nodes = _row(xp, _GL_NODES, a, a.ndim + 1)
    integral = xp.sum(at.weights * xp.sin(a[..., None] * nodes), axis=-1)
    # (e^(eps / 4) sin(a)) / sqrt(eps) in this order: its derivative at u = 0 then cancels that of erf
    # exactly (both ~1 / sqrt(eps)), and F's derivative at the identity is 0
    sines = xp.sin(a)
    bracket = at.root * integral - at.quarter * sines / at.root
    gauss = xp.exp(-(x * x))
    p = _erf(xp, x) + (2.0 / math.sqrt(math.pi)) * gauss * bracket
    p0, p1, p2 = _parts(xp, p)
    return (p0 - p1) + p2, x, sines, gauss


def _parts(xp: Any, v: Any) -> tuple[Any, ...]:
    """The entries of a short trailing axis: one ``unbind`` in eager torch, else slices."""
    if _eager(xp, v):
        return tuple(xp.unbind(v, dim=-1))
    return tuple(v[..., k] for k in range(v.shape[-1]))


def _cdf_series(xp: Any, omega: Any, at: _CdfConcentration) -> tuple[Any, Any]:
    """``F(omega)`` by the series, for ``eps >= 1/2``: the integral of each term of ``f (1 - cos omega)
    / pi``, ``[(omega - sin omega) + sum_l (2l + 1) e^(-l (l + 1) eps) (sin(l omega) / l - sin((l + 1)
    omega) / (l + 1))] / pi`` (nine terms, as the density), as ``omega`` and a sum over the harmonics
    ``sin(k omega)``, ``k = 1 ... 10`` (their coefficients are of sigma alone: :func:`_cdf_concentration`).
    Returns ``F`` and the harmonics' arguments ``k omega``."""
    t = at.ell * omega[..., None]
    # times 1 / pi, not / pi: jax divides by a Python number differently under differentiation (its
    # float32 quotient then differs in the last bit from the plain call's)
    return (omega + xp.sum(at.coefficients * xp.sin(t), axis=-1)) * (1.0 / math.pi), t


def _cdf_and_density(xp: Any, omega: Any, at: _CdfConcentration) -> tuple[Any, Any]:
    """``F(omega)`` and the angle's density ``dF / d omega`` for ``omega`` in [0, pi] (the sampler's), at
    a concentration made with ``density=True``; the density from the CDF's own pieces, each form's
    derivative written out:

    - dual: ``P'(omega) + P'(2 pi - omega) + P'(2 pi + omega)``, ``P'(u) = eps^(-3/2) e^(eps / 4) u
      sin(u / 2) e^(-x^2) / sqrt(pi) = (2 e^(eps / 4) / (sqrt(pi) eps)) x sin(u / 2) e^(-x^2)``, a sum
      whose first two terms (the only ones that count) are positive;
    - series: ``f (1 - cos omega) / pi`` with ``f = 1 + S + 2 sum_j W_j cos(j omega)``
      (:func:`_series_tails`) and ``1 - cos omega = 2 sin^2(omega / 2)`` (no cancellation at small
      angles, where the density is ~omega^2)."""
    cdf_dual, x, sines, gauss = _cdf_dual(xp, omega, at)
    cdf_series, t = _cdf_series(xp, omega, at)
    density_dual = xp.sum(at.scale * x * sines * gauss, axis=-1)
    half = _parts(xp, sines)[0]  # sin(omega / 2): the dual's first u is omega itself
    f = 1.0 + (at.total + 2.0 * xp.sum(at.tails * xp.cos(t), axis=-1))
    density_series = f * (2.0 / math.pi) * (half * half)
    cdf = xp.where(at.narrow, cdf_dual, cdf_series)
    # 1 exactly from pi on, as igso3_angle_cdf
    cdf = _fill(xp, omega >= math.pi, 1.0, cdf)
    return cdf, xp.where(at.narrow, density_dual, density_series)


@op(angle=(), sigma=())
def igso3_angle_cdf(xp: Any, angle: Any, sigma: Any) -> Any:
    """The cumulative distribution function of the rotation angle of IGSO(3) (docs/igso3.md).

    Args:
        angle: angles ``omega`` in radians, shape ``(...)``; below 0 the CDF is 0, above pi it is 1
            (the angle of a rotation is in [0, pi]).
        sigma: the concentration, shape ``(...)``, broadcasting against ``angle``, as in
            :func:`igso3_log_density`.

    Returns:
        ``F(omega; sigma) = int_0^omega f(w; sigma) (1 - cos w) / pi dw``, shape the broadcast of both:
        ``F(0) = 0`` and ``F(pi) = 1`` exactly, accurate to an absolute 1e-15 (float64) from ``sigma =
        1e-4`` on; its derivative in the angle is the angle's density, in sigma what the implicit
        reparameterisation of :func:`igso3_sample` uses. Closed forms both: the series integrated term
        by term (large sigma) and the Poisson dual integrated in ``erf`` (small sigma)."""
    angle, sigma = match_rank(xp, angle, sigma)
    return _angle_cdf_at(xp, angle, _cdf_concentration(xp, sigma))


def _angle_cdf_at(xp: Any, angle: Any, at: _CdfConcentration) -> Any:
    """:func:`igso3_angle_cdf` at a concentration made beforehand (``angle`` of its rank)."""
    # selections, so that the derivative is 0 outside [0, pi] (and F exact at the ends)
    # (pi itself from pi on: F is 1 there, below)
    top = angle >= math.pi
    omega = _fill(xp, angle < 0.0, 0.0, _fill(xp, top, math.pi, angle))
    cdf = xp.where(at.narrow, _cdf_dual(xp, omega, at)[0], _cdf_series(xp, omega, at)[0])
    # 1 exactly from pi as the dtype rounds it (float32's is pi + 8.7e-8, where the forms give 1 - ulp)
    return _fill(xp, top, 1.0, cdf)


# Steps of the angle's inversion (see _angle_quantile): from its start, 12 bring every (sigma, u) of a
# random grid (sigma log-uniform from 1e-4 to 30, u uniform and down to 1e-12 from either end) to
# |F(omega) - u| within F's own accuracy (tests/test_igso3.py checks the residual after these 16).
SAMPLE_STEPS = 16


def _angle_density(xp: Any, omega: Any, at: _Concentration) -> Any:
    """The angle's density on [0, pi], ``f(omega) (1 - cos omega) / pi``, with ``1 - cos omega`` as ``2
    sin^2(omega / 2)`` (no cancellation at small angles)."""
    half = xp.sin(0.5 * omega)
    return xp.exp(_log_density_at(xp, omega, at, True)) * (2.0 / math.pi) * (half * half)


def _quantile_start(xp: Any, u: Any, sigma: Any, at: _Concentration) -> Any:
    """Where the inversion starts: below the median the lower tail's own law, ``F ~ f(0) omega^3 / (6
    pi)`` (exact as u -> 0, for every sigma); above it ``sigma z``, with ``z`` the Maxwell distribution's
    upper quantile (the small-sigma limit: the rotation vector is ~ N(0, sigma^2 I)) from its tail
    ``1 - F ~ sqrt(2 / pi) (z + 1 / z) e^(-z^2 / 2)``, one fixed-point step from ``z^2 = -2 log(1 - u)``;
    neither beyond 2.31, the uniform distribution's median angle."""
    f0 = xp.exp(_log_density_at(xp, 0.0 * sigma, at, True))
    low = xp.exp((xp.log(6.0 * math.pi * u) - xp.log(f0)) / 3.0)
    top = -2.0 * xp.log1p(-_fill(xp, u < 0.5, 0.5, u))
    z0 = xp.sqrt(top)
    z = xp.sqrt(top + 2.0 * xp.log(math.sqrt(2.0 / math.pi) * (z0 + 1.0 / z0)))
    start = xp.where(u < 0.5, low, sigma * z)
    # 0 start + 2.31, not a number: a NaN sigma's start stays NaN (its samples are NaN by arithmetic)
    return xp.where(start < 2.31, start, 0.0 * start + 2.31)


class _Target(NamedTuple):
    """What the inversion's steps take of ``u`` and ``sigma`` alone, made once for all of them."""

    u: Any
    log_u: Any
    lower: Any  # u < 1/2: the step on log F against log omega
    at: _CdfConcentration  # with the density's terms


def _quantile_step(xp: Any, state: tuple[Any, Any, Any], target: _Target) -> tuple[Any, Any, Any]:
    """One safeguarded Newton step for ``F(omega) = u`` within the bracket ``[lo, hi]``: below the median
    on ``log F`` against ``log omega`` (exact where ``F ~ omega^3``, the lower tail at every sigma),
    above it on ``F``; a bisection of the bracket where the step leaves it (or stands still short of
    the root: where F has saturated to 1)."""
    omega, lo, hi = state
    u = target.u
    cdf, density = _cdf_and_density(xp, omega, target.at)
    below = cdf < u
    lo = xp.where(below, omega, lo)
    hi = xp.where(below, hi, omega)
    tiny = xp.finfo(cdf.dtype).tiny
    usable = density > 0.0
    p = xp.where(usable, density, _number(xp, 1.0, density))
    head = xp.where(cdf > tiny, cdf, _number(xp, tiny, cdf))
    w = xp.where(omega > 0.0, omega, _number(xp, 1.0, omega))
    lower = w * xp.exp(-(xp.log(head) - target.log_u) * head / (w * p))
    step = xp.where(target.lower, lower, omega - (cdf - u) / p)
    settled = (step == omega) & (xp.abs(cdf - u) <= 8.0 * xp.finfo(cdf.dtype).eps)
    inside = usable & (((step > lo) & (step < hi)) | settled)
    return xp.where(inside, step, 0.5 * (lo + hi)), lo, hi


def _angle_quantile(xp: Any, u: Any, sigma: Any) -> Any:
    """The angle ``omega`` with ``F(omega; sigma) = u``, for ``u`` in (0, 1): ``SAMPLE_STEPS``
    safeguarded Newton steps from ``_quantile_start``, in a bracket from [0, pi], with ``sigma`` held
    constant; then one Newton step in which it is not, so that the derivative in ``sigma`` is the
    implicit one, ``-(dF/dsigma) / p(omega)`` (the step itself is of the size of F's rounding)."""
    sigma, u = match_rank(xp, sigma, u)
    fixed = cancelling_factor(xp, sigma)
    forms = _forms(xp, fixed)
    target = _Target(u, xp.log(u), u < 0.5, _cdf_concentration(xp, fixed, forms, density=True))
    start = _quantile_start(xp, u, fixed, _concentration(xp, fixed, forms=forms))
    state = (start, 0.0 * start, 0.0 * start + math.pi)
    omega = repeat(xp, SAMPLE_STEPS, lambda s: _quantile_step(xp, s, target), state)[0]
    omega = cancelling_factor(xp, omega)
    cdf, density = _cdf_and_density(xp, omega, _cdf_concentration(xp, sigma, density=True))
    usable = density > 0.0
    correction = (cdf - u) / xp.where(usable, density, _number(xp, 1.0, density))
    return xp.where(usable, omega - correction, omega)


# The sampler's rows of a non-finite sigma are NaN by its arithmetic (its sample axes come first).
NONFINITE_BY_ARITHMETIC.add("igso3_sample")

SAMPLE_DOC = """Rotations drawn from IGSO(3) about the identity (docs/igso3.md).

    Args:
        sigma: the concentration, shape ``(...)``, as in ``igso3_log_density``.
        shape: sample shape; the result has shape ``(*shape, ..., 3, 3)``, one draw per element of
            sigma for every sample index, in sigma's dtype.
        {random}

    A uniform axis (a normalised Gaussian vector) and the angle by inverting the angle's CDF,
    ``igso3_angle_cdf``, with a fixed number of safeguarded Newton steps (no data-dependent control
    flow: it works under jit, vmap and torch.compile) to within the CDF's own accuracy. Differentiable
    in sigma by implicit reparameterisation, ``d omega / d sigma = -(dF / d sigma) / p(omega)``: the
    derivative of a sample's angle at fixed random numbers. Below the smallest sigma the density is
    taken at (float32 1.85e-9, float64 6.9e-77), sigma = 0 included, the angle is sigma / smallest
    times the one drawn there: the rotation vector is N(0, sigma^2 I) to below an ulp, sigma = 0
    gives the identity, and d omega / d sigma is the Maxwell quantile. For a mean M, ``M @ sample``; for a
    distribution at time sigma^2 after another at s^2, compose samples (IGSO(3) is a semigroup:
    ``sqrt(sigma^2 + s^2)``)."""


@op(sigma=())
def igso3_sample(xp: Any, sigma: Any, *, uniform: Any, normal: Any) -> Any:
    """Rotations drawn from IGSO(3) about the identity, from the backend's random numbers: ``uniform``
    in [0, 1) of shape ``(*sample, ...)`` for the angle (by inverting the angle's CDF) and ``normal`` of
    shape ``(*sample, ..., 3)`` for the axis (a normalised Gaussian: uniform on the sphere). Returns
    ``(*sample, ..., 3, 3)``, differentiable in ``sigma`` (implicit reparameterisation)."""
    sigma, uniform = match_rank(xp, sigma, uniform)
    tiny = xp.finfo(uniform.dtype).tiny
    u = xp.where(uniform > tiny, uniform, tiny)  # u = 0 would give log(0) in the lower-half step
    # Below the smallest sigma the density is evaluated at (_forms), the angle is sigma / smallest times
    # the one drawn at the smallest: there IGSO(3) is the Gaussian N(0, sigma^2 I) of the rotation
    # vector to below an ulp (its relative corrections are ~sigma^2 <= 1e-17), whose angle scales with
    # sigma; sigma = 0 gives the identity, and d omega / d sigma is the Maxwell quantile omega / sigma.
    # The inversion itself never sees such a sigma: its start and steps would underflow there.
    smallest = math.sqrt(2.0 * _smallest_eps(xp, uniform.dtype))
    below = 0.5 * (sigma * sigma) < _smallest_eps(xp, uniform.dtype)
    scale = xp.where(below, sigma * (1.0 / smallest), 1.0)
    omega = scale * _angle_quantile(xp, u, xp.where(below, smallest, sigma))
    norm2 = xp.sum(normal * normal, axis=-1, keepdims=True)
    ok = norm2 > 0.0
    axis = xp.where(
        ok,
        normal / xp.sqrt(xp.where(ok, norm2, 1.0)),
        0.0 * normal + _constant(xp, [1.0, 0.0, 0.0], normal, normal.ndim),
    )
    half = 0.5 * omega[..., None]
    q = xp.concat([xp.cos(half), xp.sin(half) * axis], axis=-1)
    return unit_quaternion_to_matrix(xp, q)
