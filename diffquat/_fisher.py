"""The matrix Fisher distribution on SO(3) and the Bingham distribution on S^3, over ``xp``.

**One normaliser for both.** For a unit quaternion q and any 3x3 F, ``tr(F^T R(q)) = q^T K(F) q`` with
Davenport's symmetric 4x4 ``K(F)`` (``davenport``, linear and traceless), and the Haar probability
measure on SO(3) is the image of the uniform one on S^3. So the matrix Fisher normaliser is a Bingham
one, ``c(F) = E_q[exp(q^T K(F) q)]``, and every quantity below comes from the eigenvalues
``b_0 <= ... <= b_3`` of a symmetric 4x4 matrix X and its eigenvectors V. In the eigenbasis the Bingham
distribution has independent sign flips, so every moment the derivatives need is a moment of the
squares ``q_a^2``: ``m_a = E[q_a^2] = d log c / d b_a`` and ``E[q_a^2 q_c^2]``, second derivatives of
``c`` in the eigenvalues. The Hessian of ``log c`` in X (the covariance of ``q q^T``) is written with
those, so no ``1 / (b_a - b_c)`` appears: the derivatives are exact at repeated eigenvalues (F = 0,
F a multiple of a rotation) as well.

K(F)'s eigenvalues are ``(s1 + s2 + s3, s1 - s2 - s3, -s1 + s2 - s3, -s1 - s2 + s3)`` for the proper
singular values of F (``F = U diag(s) V^T`` with U, V rotations, ``s1 >= s2 >= |s3|``, s3 < 0 where
det F < 0), and conversely ``s_i = (b_3 + b_{3-i}) / 2`` for a traceless X.

**The normaliser** ``log c(X) - tr(X)/4`` (the part that does not follow from ``c(X + tI) = e^t c(X)``):

- Small eigenvalues (``max_a |b_a - mean(b)| <= SERIES_RADIUS``): the power series of ``c``, i.e.
  ``1F1(1/2; 2; X)``: ``c = sum_K H_K / (K+1)!`` with ``prod_a (1 - b_a x)^(-1/2) = sum_K H_K x^K``
  for the centred eigenvalues (the Dirichlet(1/2, 1/2, 1/2, 1/2) moments of ``q_a^2``). The terms
  K = 0, 1 are 1 and ``sum(b)/4 = 0`` exactly, so ``c - 1`` and with it ``log c`` (``|b|^2 / 24`` at
  small b) keep their relative precision down to F = 0, where ``e^{b_3} J`` below would cancel.
- Otherwise, a Laplace inversion. ``integral_{R^4} exp(-t|g|^2 - g^T L g) dg`` in polar coordinates
  shows that ``rho J(rho L)`` has the Laplace transform ``prod_a (t + l_a)^(-1/2)``, where
  ``J(L) = E_q[exp(-q^T L q)]``. With ``l_a = b_3 - b_a >= 0`` (so that the peak ``e^{b_3}`` is
  factored out), ``log c = b_3 + log J`` and ``J`` is the inverse transform at ``rho = 1``, a contour
  integral around the branch cut on ``[-l_max, 0]``, evaluated on Talbot's contour in Weideman's
  optimised form (J. A. C. Weideman, "Optimizing Talbot's contours for the inversion of the Laplace
  transform", SIAM J. Numer. Anal. 44, 2006) with a fixed number of nodes. The singularities are on the
  negative real axis wherever the eigenvalues lie, so one rule serves every scale (1e-3 to 1e5 and
  beyond, every gap), the peak at large S included; all complex arithmetic is written with moduli and
  arguments in logarithmic form, so nothing under- or overflows. The moments are the same integral
  with an extra ``-1 / (2 (t + l_a))`` (first order) or ``1 / (4 (t + l_a)(t + l_c))`` per factor.

The classical one-dimensional form of the same normaliser (Wood 1993; T. Lee, "Bayesian attitude
estimation with the matrix Fisher distribution on SO(3)", IEEE TAC 2018; Mohlin et al., NeurIPS 2020)
is ``c = integral_{-1}^{1} 1/2 I0((s_i - s_j)(1 - u)/2) I0((s_i + s_j)(1 + u)/2) exp(s_k u) du``. The
tests evaluate it with mpmath as the reference; its integrand concentrates at ``u = 1`` on a scale
``1 / s``, which is why fixed-node rules over ``u`` (the widely copied 512-point trapezoid) fail at
large S and the Laplace inversion is used here instead.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from typing import Any

from ._core import (
    _TINY32,
    NONFINITE_BY_ARITHMETIC,
    _unit_components,
    constants,
    eager_form,
    join_quaternion,
    op,
    quaternion_to_matrix_eager,
    split_quaternion,
    stack_matrix,
    unit_scale,
)
from ._representations import (
    _INDEX,
    _UPPER,
    _XYZW,
    _finite_or_zero,
    _symmetric,
    _transpose,
    special_procrustes,
)

# Where the series is used (max |b_a - mean b|) and how many terms it takes, per compute dtype (its
# itemsize). The value, ~|b|^2 / 24, is computed by the Laplace inversion as b_3 + log J, a difference
# that loses (b_3 / log c) ~ 18 / |b| ulps of the operands: at |b| = 2 about 9 ulps, i.e. 1e-15 in float64
# and 1e-6 in float32. Below, the series: its terms are bounded by |b|^K / K!, so at |b| <= 2 the first
# omitted term is below 2^25 / 25! = 2e-18 (float64, 24 terms) and 2^17 / 17! = 4e-10 (float32, 16).
SERIES_RADIUS = 2.0
SERIES_TERMS = {8: 24, 4: 16}
# Talbot nodes per compute dtype (its itemsize), for the value and for the moments: Weideman's rule
# converges as ~e^{-1.36 N}, while rounding is amplified by ~e^{0.17 N} (the largest e^t on the contour).
# Measured against mpmath over s in [1e-3, 1e5]^3 with both signs of s3, the value's relative error is
# below 1e-12 with N = 24 (12 evaluations, by symmetry) in float64 and 3e-6 with N = 16 in float32.
# The moments converge more slowly where several l_a are 0 (F a multiple of a rotation: t^(-7/2) at
# the origin): N = 32 holds them to 2e-13 (N = 24: 1e-11, which finite differences of the gradient
# over a step of 1e-6 would see as 1e-5) and N = 20 to 5e-8 in float32.
TALBOT_NODES = {(8, False): 24, (8, True): 32, (4, False): 16, (4, True): 20}
_SIGMA, _MU, _ALPHA, _NU = 0.6122, 0.5017, 0.6407, 0.2645  # Weideman's optimised parameters


def _talbot_nodes(n: int) -> list[list[float]]:
    """Nodes of the Talbot rule with ``n`` points, the upper half (the integrand is conjugate-symmetric):
    rows ``x``, ``y`` (z = x + iy), ``log|w|`` and ``arg w`` of the weight ``w = z'(theta) h / pi``, so
    that ``f(1) = sum_k Im(e^{z_k} F(z_k) w_k)``. Contour ``z = n (-sigma + mu theta cot(alpha theta) + i nu
    theta)``, midpoints ``theta_k = (k + 1/2) 2 pi / n``."""
    h = 2.0 * math.pi / n
    rows: list[list[float]] = [[], [], [], []]
    for k in range(n // 2):
        th = (k + 0.5) * h
        cot = 1.0 / math.tan(_ALPHA * th)
        dx = n * _MU * (cot - _ALPHA * th / math.sin(_ALPHA * th) ** 2)
        dy = n * _NU
        for row, value in zip(
            rows,
            (
                n * (-_SIGMA + _MU * th * cot),
                n * _NU * th,
                math.log(math.hypot(dx, dy) * h / math.pi),
                math.atan2(dy, dx),
            ),
            strict=True,
        ):
            row.append(value)
    return rows


_NODES = {key: _talbot_nodes(n) for key, n in TALBOT_NODES.items()}


def _constant(xp: Any, values: list[float], like: Any, rank: int) -> Any:
    """A constant 1-D array of ``like``'s dtype and device, with ``rank - 1`` leading unit axes (jax may
    be set to refuse implicit rank promotion). jax's traced arrays have no device (jax places constants
    itself): None there."""
    out = xp.asarray(values, dtype=like.dtype, device=getattr(like, "device", None))
    return xp.reshape(out, (1,) * (rank - 1) + (len(values),))


# ---------------------------------------------------------------------------------------------------
# The normaliser and the moments from the eigenvalues


def _talbot(xp: Any, lam: Any, order: int) -> tuple[Any, Any, Any]:
    """``log J`` for ``l = lam`` (..., 4), all >= 0 and ``lam[..., 3] = 0``; with ``order >= 1`` the
    moments ``m_a`` of the Bingham distribution ``exp(-sum l_a q_a^2)``, with ``order >= 2`` its
    ``E[q_a^2 q_c^2]`` (..., 4, 4). ``m_3`` (the mode's axis, near 1 when concentrated) is taken as
    ``1 - sum_{a<3} m_a`` and the covariances in its row from ``sum_c q_c^2 = 1``: the direct sums would
    hold them only to an absolute 1e-13, their sizes being ~1/l."""
    x, y, log_w, arg_w = _NODES[(lam.dtype.itemsize, order > 0)]
    rank = lam.ndim + 1  # (..., node, a)
    cx = xp.reshape(_constant(xp, x, lam, rank - 1), (*(1,) * (rank - 2), len(x), 1))
    cy = xp.reshape(_constant(xp, y, lam, rank - 1), (*(1,) * (rank - 2), len(x), 1))
    re = cx + lam[..., None, :]  # t + l_a at every node, real and imaginary parts
    im = xp.broadcast_to(cy, re.shape)
    log_mod = xp.log(xp.hypot(re, im))
    arg = xp.atan2(im, re)  # in (-pi, pi): the principal branch, continuous off the cut
    # e^t prod_a (t + l_a)^(-1/2) w, as modulus exp(e) and argument phase; the largest modulus factored
    # out (at l ~ 1e30 the modulus is ~1e-45, below float32's range)
    e = cx[..., 0] + _constant(xp, log_w, lam, rank - 1) - 0.5 * xp.sum(log_mod, axis=-1)
    phase = cy[..., 0] + _constant(xp, arg_w, lam, rank - 1) - 0.5 * xp.sum(arg, axis=-1)
    top = xp.amax(e, axis=-1, keepdims=True)
    size = xp.exp(e - top)
    j = xp.sum(size * xp.sin(phase), axis=-1)
    log_j = top[..., 0] + xp.log(j)
    if order == 0:
        return log_j, None, None
    # dJ/dl_a = -1/2 sum Im(T / (t + l_a)): the modulus divided by |t + l_a|, the argument less arg_a
    inv = xp.exp(-log_mod)
    weight = size[..., None] * inv
    m = 0.5 * xp.sum(weight * xp.sin(phase[..., None] - arg), axis=-2) / j[..., None]
    m = xp.concat([m[..., :3], 1.0 - xp.sum(m[..., :3], axis=-1, keepdims=True)], axis=-1)
    if order == 1:
        return log_j, m, None
    # d2J/dl_a dl_c = 1/4 sum Im(T / ((t + l_a)(t + l_c))) for a != c, 3/4 sum Im(T / (t + l_a)^2)
    pair = weight[..., :, None] * inv[..., None, :]
    angle = phase[..., None, None] - arg[..., :, None] - arg[..., None, :]
    moment = xp.sum(pair * xp.sin(angle), axis=-3) / j[..., None, None]
    factor = [0.75 if a == c else 0.25 for a in range(4) for c in range(4)]
    moment = moment * xp.reshape(_constant(xp, factor, lam, 1), (*(1,) * (lam.ndim - 1), 4, 4))
    # The mode's row: E[q_a^2 q_3^2] = m_a - sum_{c<3} E[q_a^2 q_c^2], E[q_3^4] = m_3 - sum_{a<3} that.
    block = moment[..., :3, :3]
    side = m[..., :3] - xp.sum(block, axis=-1)
    corner = m[..., 3] - xp.sum(side, axis=-1)
    rows = xp.concat([block, side[..., :, None]], axis=-1)
    last = xp.concat([side, corner[..., None]], axis=-1)
    return log_j, m, xp.concat([rows, last[..., None, :]], axis=-2)


def _placement(xp: Any, like: Any) -> Any:
    """The 0/1 tensor ``[K - k == d]`` (n, n * n) of :func:`_lower_toeplitz` for ``n = like.shape[-1]``,
    built from ``arange`` (a gather by a constant index, or a constant from a Python list of n^3 numbers,
    costs more in torch eager than the product itself: docs/performance.md, Formula shapes); made once
    per series, for all its products."""
    n = like.shape[-1]
    i = xp.arange(n, dtype=like.dtype, device=getattr(like, "device", None))
    gap = xp.reshape(i, (1, n, 1)) - xp.reshape(i, (1, 1, n)) - xp.reshape(i, (n, 1, 1))
    return xp.reshape(xp.where(gap == 0.0, xp.ones_like(gap), xp.zeros_like(gap)), (n, n * n))


def _lower_toeplitz(xp: Any, u: Any, placement: Any) -> Any:
    """``(..., n) -> (..., n, n)``: the matrix of the truncated product of power series by ``u``,
    ``T[K, k] = u[K - k]`` for ``K >= k`` and 0 above the diagonal, as one matrix product with
    ``placement`` (:func:`_placement`)."""
    n = u.shape[-1]
    flat = xp.matmul(xp.reshape(u, (-1, n)), placement)
    return xp.reshape(flat, (*u.shape, n))


def _times(xp: Any, t: Any, u: Any) -> Any:
    """The product of the series of matrix ``t`` (..., n, n) and vector ``u`` (..., n)."""
    return xp.matmul(t, u[..., None])[..., 0]


def _series(xp: Any, b: Any, order: int) -> tuple[Any, Any, Any]:
    """For centred eigenvalues ``b`` (..., 4) (sum 0): ``log c(b)``; with ``order >= 1`` the deviations
    ``m_a - 1/4`` (relative precision, so that E[R] = K^*(...) keeps it at small F); with ``order >= 2``
    ``E[q_a^2 q_c^2]``. The coefficients of ``E(x) = prod_a (1 - b_a x)^(-1/2)``, of ``dE/db_a = x/2
    (1 - b_a x)^(-1) E`` and of ``d2E/db_a db_c = x^2/4 (1 - b_a x)^(-1)(1 - b_c x)^(-1) E`` (3/4 for
    a = c) are truncated products of power series, each a matrix product (a fixed, small number of
    array operations for any number of terms); ``c`` and its derivatives are their sums weighted by
    ``1 / (K+1)!``."""
    n = SERIES_TERMS[b.dtype.itemsize] + 1
    rank = b.ndim + 1
    ones = xp.ones_like(b)[..., None]
    powers = xp.cumprod(xp.concat([ones, xp.broadcast_to(b[..., None], (*b.shape, n - 1))], axis=-1), axis=-1)
    # (1 - b x)^(-1/2) = sum_k binom(2k, k) / 4^k b^k x^k
    binomial = _constant(xp, [math.comb(2 * k, k) / 4.0**k for k in range(n)], b, rank)
    factors = powers * binomial  # (..., 4, n)
    e = factors[..., 3, :]
    placement = _placement(xp, e)
    for a in (2, 1, 0):
        e = _times(xp, _lower_toeplitz(xp, factors[..., a, :], placement), e)
    # weights 1/(K+1)!, and the same without K = 0, 1: those terms are 1 and sum(b)/4 = 0 (b is centred,
    # and dropping the rounding of its sum keeps c - 1 ~ |b|^2/24 to its relative precision)
    full = [1.0 / math.factorial(k + 1) for k in range(n)]
    weight = _constant(xp, [0.0, 0.0, *full[2:]], b, rank - 1)
    excess = xp.sum(e * weight, axis=-1)  # c - 1
    log_c = xp.log1p(excess)
    if order == 0:
        return log_c, None, None
    # x (1 - b_a x)^(-1) = sum_{k>=1} b_a^(k-1) x^k
    geometric = xp.concat([xp.zeros_like(ones), powers[..., :-1]], axis=-1)  # (..., 4, n)
    shift = _lower_toeplitz(xp, geometric, placement)  # (..., 4, n, n)
    g = _times(xp, shift, e[..., None, :])  # (..., 4, n): coefficients of x (1 - b_a x)^(-1) E
    # dc/db_a - c/4 = sum_K (g_{a,K}/2 - e_K/4) / (K+1)!, whose K = 0, 1 terms cancel exactly
    dev = xp.sum((0.5 * g - 0.25 * e[..., None, :]) * weight[..., None, :], axis=-1)
    dev = dev / (1.0 + excess)[..., None]
    if order == 1:
        return log_c, dev, None
    gg = _times(xp, shift[..., None, :, :, :], g[..., :, None, :])  # (..., a, c, n)
    second = xp.sum(gg * _constant(xp, full, b, rank + 1), axis=-1)
    eye = [0.75 if a == c else 0.25 for a in range(4) for c in range(4)]
    factor = xp.reshape(_constant(xp, eye, b, 1), (*(1,) * (b.ndim - 1), 4, 4))
    return log_c, dev, second * factor / (1.0 + excess)[..., None, None]


def _moments(xp: Any, b: Any, order: int) -> tuple[Any, Any, Any]:
    """``log c(b) - mean(b)``, ``m - 1/4`` and ``E[q_a^2 q_c^2]`` for ascending eigenvalues ``b`` (..., 4),
    from the series or the Laplace inversion (see the module docstring), both evaluated and one
    selected (no control flow on values); each is fed values for which it is finite."""
    centred = b - xp.mean(b, axis=-1, keepdims=True)
    small = xp.amax(xp.abs(centred), axis=-1) <= SERIES_RADIUS
    inside = xp.where(small[..., None], centred, 0.0)  # the series overflows far outside its radius
    lam = b[..., 3:4] - b
    log_j, m, second = _talbot(xp, lam, order)
    log_s, dev_s, second_s = _series(xp, inside, order)
    value = xp.where(small, log_s, centred[..., 3] + log_j)
    if order == 0:
        return value, None, None
    dev = xp.where(small[..., None], dev_s, m - 0.25)
    if order == 1:
        return value, dev, None
    return value, dev, xp.where(small[..., None, None], second_s, second)


# ---------------------------------------------------------------------------------------------------
# The eager form of the normaliser and its gradient (torch): the same two evaluations, each a few
# vectorised operations over (batch, node, eigenvalue) or (batch, pair, term) axes (docs/design.md, "Two
# forms of a map"); the moment rule's nodes serve the value too, so that one contour evaluation gives
# both (as the captured form's expansion does).


def _eager_tables(itemsize: int) -> Callable[[], tuple[Any, ...]]:
    """The constants of :func:`_eager_moments` for a compute dtype (its itemsize), as a ``make`` for
    ``_core.constants``:

    - ``nodes`` (n, 1) and ``offsets`` (n,), complex: the Talbot nodes ``z_k`` and ``z_k + log w_k``, of
      the value's rule and of the moments' (``TALBOT_NODES``);
    - ``powers`` (m,): 0 .. m - 1, and ``slopes`` (m,), ``scales`` (m,): ``max(k - 1, 0)`` and ``2 k``
      (the derivative of ``b^k`` is ``k b^(k-1)``; the 2 is that of ``excess``'s two halves below);
    - ``pair`` (m^2, m) and its transpose: ``c_i c_j [i + j = K]``, the coefficients ``c_k = binom(2k,
      k) / 4^k`` of ``(1 - b x)^(-1/2)`` folded in, so that one product of the outer product of two
      eigenvalues' powers gives the series of the product of their two factors (truncated at m - 1);
    - ``swap`` (2m, 2m): ``[[0, W], [W, 0]]`` with ``W[K, L] = 1 / (K + L + 1)! / 2`` for ``2 <= K + L <
      m`` (0 else: the terms K = 0, 1 are 1 and ``sum(b) / 4 = 0``), so that ``p . (p swap)`` over the
      two pairs' series ``p`` is ``c - 1`` (each pair's product with the other's, halved, twice);
    - ``mix`` (3, 4), ``shift`` (4,): ``m_3 = 1 - m_0 - m_1 - m_2`` and the deviations ``m - 1/4`` of
      the Laplace inversion's three sums (halved, its ``1/2``)."""
    m = SERIES_TERMS[itemsize] + 1

    def make() -> tuple[Any, ...]:
        rules: list[list[Any]] = []
        for moments in (False, True):
            x, y, log_w, arg_w = _NODES[(itemsize, moments)]
            rules.append([[complex(a, b)] for a, b in zip(x, y, strict=True)])
            rules.append([complex(a + c, b + d) for a, b, c, d in zip(x, y, log_w, arg_w, strict=True)])
        c = [math.comb(2 * k, k) / 4.0**k for k in range(m)]
        pair = [[c[i] * c[j] if i + j == k else 0.0 for k in range(m)] for i in range(m) for j in range(m)]
        pair_t = [list(row) for row in zip(*pair, strict=True)]
        w = [0.5 / math.factorial(k + 1) if 2 <= k < m else 0.0 for k in range(2 * m)]
        half = [[w[i + j] for j in range(m)] for i in range(m)]
        zero = [0.0] * m
        swap = [zero + row for row in half] + [row + zero for row in half]
        mix = [[0.5 if a == c else -0.5 if c == 3 else 0.0 for c in range(4)] for a in range(3)]
        return (
            *rules,
            [float(k) for k in range(m)],
            [float(max(k - 1, 0)) for k in range(m)],
            [2.0 * k for k in range(m)],
            pair,
            pair_t,
            swap,
            mix,
            [-0.25, -0.25, -0.25, 0.75],
        )

    return make


_EAGER_TABLES = {itemsize: _eager_tables(itemsize) for itemsize in SERIES_TERMS}


def _eager_moments(xp: Any, x: Any, order: int) -> tuple[Any, Any]:
    """``reduced_log_normalizer`` of symmetric ``x`` (B, 4, 4), torch, and with ``order = 1`` its
    gradient ``E[q q^T] - I/4`` (B, 4, 4): :func:`_moments`' two evaluations, selected alike.

    - The Laplace inversion in complex arithmetic: ``log(z_k + l_a)`` over a (node, eigenvalue) axis
      is the modulus and argument of each factor at once; the integrand's logarithm is one sum and one
      addition, and ``Im`` of its exponentials' sum (the largest modulus factored out) is J. The
      moments are the same terms over one factor more.
    - The series as two products of pairs: the outer product of two eigenvalues' powers, contracted
      with ``pair``, is the series of the product of their two factors; ``c - 1`` is the two pairs'
      series contracted by the constant ``swap``. Its derivative in ``b_a`` is the power series of
      ``k b_a^(k-1)`` against the contraction of everything else (``swap`` and ``pair`` again).

    The value's operations are the same whatever ``order``, so that a differentiated call returns the
    plain one's value bit for bit. Non-finite entries are replaced by 0 before the eigensolver (the
    backend then makes their rows NaN)."""
    b, v = xp.linalg.eigh(xp.nan_to_num(x, nan=0.0, posinf=0.0, neginf=0.0))
    nodes, offsets, nodes_m, offsets_m, powers, slopes, scales, pair, pair_t, swap, mix, shift = constants(
        xp, b, _EAGER_TABLES[b.dtype.itemsize]
    )
    m = powers.shape[0]
    centred = b - xp.mean(b, -1, keepdim=True)
    small = xp.amax(xp.abs(centred), -1) <= SERIES_RADIUS
    # the Laplace inversion, l = b_3 - b >= 0
    lam = (b[:, 3:] - b)[:, None, :]
    log_z = xp.log(lam + nodes)  # (B, node, a)
    e = xp.add(offsets, xp.sum(log_z, -1), alpha=-0.5)
    top = xp.amax(xp.view_as_real(e)[..., 0], -1, keepdim=True)
    j = xp.view_as_real(xp.sum(xp.exp(e - top), -1))[..., 1]
    inversion = centred[:, 3] + (top[:, 0] + xp.log(j))
    # the series; far outside its radius its powers overflow, in rows the selection drops (a matrix
    # product sums within a row)
    u = centred[:, :, None] ** powers  # (B, a, k)
    halves = u.view(-1, 2, 2, m)
    outer = halves[:, :, 0, :, None] * halves[:, :, 1, None, :]  # (B, pair, i, j)
    p = xp.mm(outer.view(-1, m * m), pair).view(-1, 2 * m)  # (B, pair * K)
    q = xp.mm(p, swap)
    excess = xp.sum(p * q, -1)  # c - 1
    value = xp.where(small, xp.log1p(excess), inversion)
    if order == 0:
        return value, None
    # Laplace, on the moments' nodes (their terms scaled by the value's largest, the same to a factor
    # e^{O(n)}): m_a = 1/2 sum_k Im(T_k / (z_k + l_a)) / J for a < 3; m_3 = 1 - their sum (mix, shift)
    log_z = xp.log(lam + nodes_m)
    shifted = xp.add(offsets_m, xp.sum(log_z, -1), alpha=-0.5) - top
    j = xp.view_as_real(xp.sum(xp.exp(shifted), -1))[..., 1]
    terms = xp.exp(shifted[:, :, None] - log_z[:, :, :3])
    sums = xp.view_as_real(xp.sum(terms, -2))[..., 1] / j[:, None]
    dev_inversion = xp.addmm(shift, sums, mix)
    # series: d(c - 1)/db_a, then m_a - 1/4 = (dc/db_a - c/4) / c, the K = 0, 1 terms cancelled exactly
    slope = scales * centred[:, :, None] ** slopes  # (B, a, k): 2 k b_a^(k-1)
    other = xp.mm(q.view(-1, m), pair_t).view(-1, 2, 1, m, m)  # c_i c_j W p_other[i + j], per pair
    adjoint = xp.sum(other * halves.flip(2)[:, :, :, None, :], -1)  # (B, pair, member, i)
    d_excess = xp.sum(slope * adjoint.view(-1, 4, m), -1)
    dev_series = xp.sub(d_excess, excess[:, None], alpha=0.25) / (1.0 + excess)[:, None]
    dev = xp.where(small[:, None], dev_series, dev_inversion)
    return value, xp.matmul(v * dev[:, None, :], v.transpose(-1, -2))


# ---------------------------------------------------------------------------------------------------
# The Bingham normaliser of a symmetric 4x4 matrix, its gradient and Hessian (registered per backend as
# custom derivatives, like the SVD and eigh maps of _representations.py)


def _eigh(xp: Any, x: Any) -> tuple[Any, Any]:
    return xp.linalg.eigh(_finite_or_zero(xp, x, 2))


def reduced_log_normalizer(xp: Any, x: Any) -> Any:
    """``log E_q[exp(q^T X q)] - tr(X) / 4`` for symmetric X (..., 4, 4), q uniform on S^3: the Bingham
    log normaliser less its trivial part (it depends on X only through ``X - tr(X)/4 I``). Gradient:
    ``reduced_second_moment``."""
    value, _, _ = _moments(xp, xp.linalg.eigvalsh(_finite_or_zero(xp, x, 2)), 0)
    return value


def reduced_second_moment(xp: Any, x: Any) -> Any:
    """``E[q q^T] - I / 4`` under ``exp(q^T X q)``: the gradient of ``reduced_log_normalizer``,
    ``V diag(m - 1/4) V^T`` in X's eigenbasis (unique even where eigenvalues repeat: so are the m_a)."""
    b, v = _eigh(xp, x)
    _, dev, _ = _moments(xp, b, 1)
    return xp.matmul(v * dev[..., None, :], _transpose(xp, v))


def _hessian(xp: Any, v: Any, dev: Any, second: Any, dx: Any) -> Any:
    """``Cov(q q^T, q^T dX q)`` from the eigenvectors V, ``m - 1/4`` and ``E[q_a^2 q_c^2]``: in X's
    eigenbasis, with ``D = V^T sym(dX) V``, the independent sign flips of the Bingham distribution leave
    ``2 E[q_a^2 q_c^2] D_ac`` off the diagonal and ``sum_c Cov(q_a^2, q_c^2) D_cc`` on it: moments only,
    no division by eigenvalue gaps, so exact where eigenvalues repeat."""
    m = dev + 0.25
    vt = _transpose(xp, v)
    d = xp.matmul(vt, xp.matmul(0.5 * (dx + _transpose(xp, dx)), v))
    diag = xp.stack([d[..., a, a] for a in range(4)], axis=-1)
    cov = second - m[..., :, None] * m[..., None, :]
    on = xp.sum(cov * diag[..., None, :], axis=-1)
    off = 2.0 * second * d
    eye = [1.0 if a == c else 0.0 for a in range(4) for c in range(4)]
    eye = xp.reshape(_constant(xp, eye, v, 1), (*(1,) * (v.ndim - 2), 4, 4))
    inner = off * (1.0 - eye) + on[..., :, None] * eye
    return xp.matmul(v, xp.matmul(inner, vt))


def reduced_second_moment_tangent(xp: Any, x: Any, moment: Any, dx: Any) -> Any:
    """The derivative of ``reduced_second_moment`` along ``dx`` (self-adjoint: also its reverse mode),
    i.e. the Hessian of the log normaliser, ``Cov(q q^T, q^T dX q)`` (see ``_hessian``)."""
    del moment
    b, v = _eigh(xp, x)
    _, dev, second = _moments(xp, b, 2)
    return _hessian(xp, v, dev, second, dx)


def _expansion(xp: Any, x0: Any) -> tuple[Any, Any, Any, Any, Any]:
    b, v = _eigh(xp, x0)
    value, dev, second = _moments(xp, b, 2)
    return value, xp.matmul(v * dev[..., None, :], _transpose(xp, v)), v, dev, second


def reduced_log_normalizer_eager_rules() -> tuple[Callable[..., Any], ...]:
    """The eager form of ``reduced_log_normalizer`` (torch), as ``_custom.custom_derivative`` takes it:
    ``(prepare, forward, cotangent, finish, plain)``. The forward (``_eager_moments``) gives the value
    with the gradient ``E[q q^T] - I/4`` as an output, so that the reverse rule is one product
    (``grad * moment``), with no second eigendecomposition; a derivative of that product reaches the
    moment, whose cotangent is taken back by the Hessian rule (``reduced_second_moment_tangent``,
    self-adjoint). ``plain``: the value alone, the same operations, for calls of which no derivative
    can be asked."""

    def prepare(xp: Any, x: Any) -> Any:
        return xp.reshape(x, (-1, 4, 4))

    def forward(xp: Any, u: Any) -> tuple[Any, Any]:
        return _eager_moments(xp, u, 1)

    def plain(xp: Any, u: Any) -> tuple[Any]:
        return (_eager_moments(xp, u, 0)[0],)

    def cotangent(xp: Any, u: Any, value: Any, moment: Any, grad: Any, grad_moment: Any) -> Any:
        del value
        out = None if grad is None else grad[:, None, None] * moment
        if grad_moment is not None:
            hessian = reduced_second_moment_tangent(xp, u, None, grad_moment)
            out = hessian if out is None else out + hessian
        return out

    def finish(xp: Any, x: Any, value: Any) -> Any:
        return xp.reshape(value, tuple(x.shape[:-2]))

    return prepare, forward, cotangent, finish, plain


def reduced_second_moment_eager_rules() -> tuple[Callable[..., Any], ...]:
    """The eager form of ``reduced_second_moment`` (torch), ``(prepare, forward, cotangent, finish)``:
    the moments of ``_eager_moments``, the same numbers as the normaliser's eager gradient, with the
    Hessian rule (self-adjoint) as its reverse rule."""
    prepare, _, _, _, _ = reduced_log_normalizer_eager_rules()

    def forward(xp: Any, u: Any) -> tuple[Any]:
        return (_eager_moments(xp, u, 1)[1],)

    def cotangent(xp: Any, u: Any, moment: Any, grad: Any) -> Any:
        del moment
        return None if grad is None else reduced_second_moment_tangent(xp, u, None, grad)

    def finish(xp: Any, x: Any, moment: Any) -> Any:
        return xp.reshape(moment, tuple(x.shape))

    return prepare, forward, cotangent, finish


def reduced_log_normalizer_taylor(xp: Any, x0: Any, dx: Any) -> Any:
    """``reduced_log_normalizer`` at ``x0 + dx`` to second order in ``dx``, from one
    eigendecomposition of ``x0``: for graph capture with ``dx = x - x0`` zero in value and ``x0`` a
    constant, its value and first and second derivatives in x are the map's at x (third ones are 0)."""
    value, grad, v, dev, second = _expansion(xp, x0)
    quadratic = grad + 0.5 * _hessian(xp, v, dev, second, dx)
    return value + xp.sum(quadratic * dx, axis=(-2, -1))


def reduced_second_moment_taylor(xp: Any, x0: Any, dx: Any) -> Any:
    """``reduced_second_moment`` at ``x0 + dx`` to first order (as above: its derivative at x)."""
    _, grad, v, dev, second = _expansion(xp, x0)
    return grad + _hessian(xp, v, dev, second, dx)


def reduced_log_normalizer_tangent(
    xp: Any, x: Any, value: Any, dx: Any, *, moment: Callable[[Any, Any], Any] = reduced_second_moment
) -> Any:
    """Forward-mode derivative of ``reduced_log_normalizer``: ``<E[q q^T] - I/4, dX>``."""
    del value
    return xp.sum(moment(xp, x) * dx, axis=(-2, -1))


def reduced_log_normalizer_cotangent(
    xp: Any, x: Any, value: Any, grad: Any, *, moment: Callable[[Any, Any], Any] = reduced_second_moment
) -> Any:
    """Reverse-mode derivative of ``reduced_log_normalizer``: ``grad (E[q q^T] - I/4)``."""
    del value
    return grad[..., None, None] * moment(xp, x)


# ---------------------------------------------------------------------------------------------------
# Matrix Fisher


def davenport(xp: Any, matrix: Any) -> Any:
    """Davenport's K(F) (..., 4, 4), scalar-first quaternion order: ``tr(F^T R(q)) = q^T K q`` for unit q."""
    f = [[matrix[..., i, j] for j in range(3)] for i in range(3)]
    ww = f[0][0] + f[1][1] + f[2][2]
    xx = f[0][0] - f[1][1] - f[2][2]
    yy = f[1][1] - f[0][0] - f[2][2]
    zz = f[2][2] - f[0][0] - f[1][1]
    wx, wy, wz = f[2][1] - f[1][2], f[0][2] - f[2][0], f[1][0] - f[0][1]
    xy, xz, yz = f[0][1] + f[1][0], f[0][2] + f[2][0], f[1][2] + f[2][1]
    flat = xp.stack([ww, wx, wy, wz, wx, xx, xy, xz, wy, xy, yy, yz, wz, xz, yz, zz], axis=-1)
    return xp.reshape(flat, (*flat.shape[:-1], 4, 4))


def davenport_adjoint(xp: Any, p: Any) -> Any:
    """The adjoint of ``davenport``: the 3x3 matrix of ``<K(.), P>`` for symmetric P (..., 4, 4), i.e.
    ``R(q)`` with each product ``q_a q_c`` replaced by ``P_ac`` (``E[R]`` for ``P = E[q q^T]``)."""
    (ww, wx, wy, wz), (_, xx, xy, xz), (_, _, yy, yz), (_, _, _, zz) = (
        [p[..., a, c] for c in range(4)] for a in range(4)
    )
    return stack_matrix(
        xp,
        [
            ww + xx - yy - zz, 2.0 * (xy - wz), 2.0 * (xz + wy),
            2.0 * (xy + wz), ww - xx + yy - zz, 2.0 * (yz - wx),
            2.0 * (xz - wy), 2.0 * (yz + wx), ww - xx - yy + zz,
        ],
    )  # fmt: skip


Normalizer = Callable[[Any, Any], Any]


@op(F=(3, 3))
def matrix_fisher_log_normalizer(xp: Any, F: Any, *, normalizer: Normalizer = reduced_log_normalizer) -> Any:
    """Log normaliser of the matrix Fisher distribution on SO(3), ``log c(F)``.

    The density is ``p(R) = exp(tr(F^T R)) / c(F)`` against the Haar probability measure (uniform
    rotations have density 1), so ``c(F) = E_R[exp(tr(F^T R))]`` over uniform R, ``c(0) = 1``.

    Args:
        F: any real matrices, shape ``(..., 3, 3)``.

    Returns:
        Shape ``(...)``. Depends only on the proper singular values of F (``F = U diag(s) V^T`` with
        U, V rotations), ``log c ~ |s|^2 / 6`` near 0 and ``s1 + s2 + s3 - log(...)/2`` at large s.
        Within 1e-12 relative in float64 and 3e-6 in float32 of a high-precision reference for singular
        values from 1e-3 to 1e5, every sign pattern (see ``diffquat._fisher`` for the method).

    Gradients (torch and jax): ``d log c / dF = E[R]`` (the mean rotation matrix, ``U diag(d log c / ds)
    V^T``), in closed form from the moments of the equivalent Bingham distribution; ``E[R] = 0`` at F = 0.
    Second derivatives are the covariance of R, also in closed form: both are exact wherever F's
    singular values repeat (F = 0, F a multiple of a rotation). Third and higher derivatives
    differentiate the eigendecomposition inside that rule: exact where the eigenvalues of K(F) are
    distinct, not finite where they repeat. Under torch graph capture (``torch.compile``,
    ``torch.jit.trace``, ``torch.export``) the map is its second-order Taylor polynomial about the
    input, whose third derivatives are 0.
    """
    return normalizer(xp, davenport(xp, F))


@op(F=(3, 3))
def matrix_fisher_mean(xp: Any, F: Any, *, moment: Callable[[Any, Any], Any] = reduced_second_moment) -> Any:
    """``E[R]`` under the matrix Fisher distribution (the gradient of its log normaliser), shape
    ``(..., 3, 3)``: ``K^*(E[q q^T] - I/4)`` (``K^*`` annihilates I, and the deviation keeps its relative
    precision down to F = 0, where ``E[R] ~ F/3``)."""
    return davenport_adjoint(xp, moment(xp, davenport(xp, F)))


@op(F=(3, 3), matrix=(3, 3))
def matrix_fisher_nll(
    xp: Any, F: Any, matrix: Any, *, normalizer: Normalizer = reduced_log_normalizer
) -> Any:
    """Negative log-likelihood of rotations under the matrix Fisher distribution.

    Args:
        F: the parameter, shape ``(..., 3, 3)``.
        matrix: rotation matrices, shape ``(..., 3, 3)`` (not checked: any matrix is evaluated by the
            same formula); the batch shapes broadcast.

    Returns:
        Shape ``(...)``: ``log c(F) - tr(F^T R)``, the negative log density against the Haar probability
        measure (uniform rotations: 0 for F = 0). Derivatives as ``matrix_fisher_log_normalizer``'s.
    """
    # the normaliser on F's own batch (a batch of rotations for one F needs it once), then broadcast
    batch = tuple(xp.broadcast_shapes(F.shape[:-2], matrix.shape[:-2]))
    log_c = _lead(xp, normalizer(xp, davenport(xp, F)), len(batch))
    energy = xp.broadcast_to(F, (*batch, 3, 3)) * xp.broadcast_to(matrix, (*batch, 3, 3))
    return log_c - xp.sum(energy, axis=(-2, -1))


def _davenport_table() -> tuple[Any, ...]:
    """(9, 16): ``davenport`` of each of the nine unit matrices, so that ``K(F)`` is one product of F's
    entries with it (each entry a sum of two or three of them with coefficients +-1)."""
    import numpy as np

    return (davenport(np, np.eye(9).reshape(9, 3, 3)).reshape(9, 16).tolist(),)


def _davenport_eager(xp: Any, F: Any) -> Any:
    """``davenport`` of F (..., 3, 3) as (B, 4, 4), B the flattened batch: one product."""
    (table,) = constants(xp, F, _davenport_table)
    return xp.mm(xp.reshape(F, (-1, 9)), table).view(-1, 4, 4)


@eager_form(of=matrix_fisher_log_normalizer)
def matrix_fisher_log_normalizer_eager(
    xp: Any, F: Any, *, normalizer: Normalizer = reduced_log_normalizer
) -> Any:
    """:func:`matrix_fisher_log_normalizer`, eager form: ``K(F)`` as one product."""
    return xp.reshape(normalizer(xp, _davenport_eager(xp, F)), tuple(F.shape[:-2]))


@eager_form(of=matrix_fisher_nll)
def matrix_fisher_nll_eager(
    xp: Any, F: Any, matrix: Any, *, normalizer: Normalizer = reduced_log_normalizer
) -> Any:
    """:func:`matrix_fisher_nll`, eager form: the normaliser on F's batch, the energy by broadcasting."""
    log_c = xp.reshape(normalizer(xp, _davenport_eager(xp, F)), tuple(F.shape[:-2]))
    return log_c - xp.sum(F * matrix, (-2, -1))


@op(F=(3, 3))
def matrix_fisher_mode(xp: Any, F: Any, *, procrustes: Callable[[Any, Any], Any] = special_procrustes) -> Any:
    """The mode of the matrix Fisher distribution: the rotation nearest to F.

    Args:
        F: shape ``(..., 3, 3)``.

    Returns:
        Shape ``(..., 3, 3)``: ``special_procrustes`` of F, ``U diag(1, 1, det(U V^T)) V^T`` (the
        rotation maximising ``tr(F^T R)``, so the density's maximum), with its derivatives.
    """
    return procrustes(xp, F)


# ---------------------------------------------------------------------------------------------------
# Sampling: Kent, Ganeiber and Mardia's rejection sampler for the Bingham distribution (an angular
# central Gaussian envelope), "A new unified approach for the simulation of a wide class of directional
# distributions", J. Comput. Graph. Stat. 27, 2018. For f(x) = exp(-x^T L x) on S^3 (L >= 0 diagonal in
# the eigenbasis) and the ACG density (x^T W x)^(-2), W = I + 2L/beta, f/g <= M = e^{-(4 - beta)/2}
# (4/beta)^2 for every beta in (0, 4] (the maximum of e^{-t}(1 + 2t/beta)^2 over t >= 0); beta solving
# sum_a 1/(beta + 2 l_a) = 1 maximises the acceptance. Over every L the acceptance is at least 0.4469
# (its infimum, reached as L grows without bound), so that 64 proposals all fail with probability at
# most 0.5531^64 < 4e-17 per sample.
SAMPLE_ROUNDS = 4
SAMPLE_PROPOSALS = 16  # per round: 64 proposals
_NEWTON_STEPS = 10  # from beta = 1 (left of the root: the function is convex and decreasing), 7 suffice


def _acg_beta(xp: Any, lam: Any) -> Any:
    beta = xp.ones_like(lam[..., 0])
    for _ in range(_NEWTON_STEPS):
        inv = 1.0 / (beta[..., None] + 2.0 * lam)
        beta = beta + (xp.sum(inv, axis=-1) - 1.0) / xp.sum(inv * inv, axis=-1)
    return beta


Draw = Callable[[int | None], tuple[Any, Any]]


def _lead(xp: Any, a: Any, rank: int) -> Any:
    """``a`` with unit axes in front, to ``rank`` (jax may be set to refuse implicit rank promotion)."""
    return xp.reshape(a, (1,) * (rank - a.ndim) + tuple(a.shape))


# The sampler makes the rows of a non-finite F NaN itself (its sample axes come first, the backend's
# rule appends axes): see the end of matrix_fisher_sample.
NONFINITE_BY_ARITHMETIC.add("matrix_fisher_sample")


@op(F=(3, 3))
def matrix_fisher_sample(xp: Any, F: Any, *, draw: Draw) -> Any:
    """Rotations distributed by the matrix Fisher distribution of F, from the backend's random numbers.

    ``draw(k)``, for the rounds ``k = 0 .. SAMPLE_ROUNDS - 1``, returns standard normal numbers of shape
    ``(*sample, *batch, SAMPLE_PROPOSALS, 4)`` and uniform ones in [0, 1) of shape ``(*sample, *batch,
    SAMPLE_PROPOSALS)``, in F's compute dtype (torch's eager form asks ``draw(None)`` for all rounds'
    numbers at once, ``SAMPLE_ROUNDS * SAMPLE_PROPOSALS`` proposals, round by round). Each sample is
    the first accepted proposal (see the comment above), or where all 64 are rejected (probability <
    4e-17) the mode. Returns ``(*sample, *batch, 3, 3)``."""
    bad = ~xp.all(xp.isfinite(xp.reshape(F, (*F.shape[:-2], 9))), axis=-1)
    b, v = _eigh(xp, davenport(xp, F))
    lam = b[..., 3:4] - b  # >= 0, lam_3 = 0: exp(q^T K q) = e^{b_3} exp(-sum l_a x_a^2), x = V^T q
    beta = _acg_beta(xp, lam)
    log_bound = -0.5 * (4.0 - beta) + 2.0 * xp.log(4.0 / beta)
    scale = 1.0 / xp.sqrt(1.0 + 2.0 * lam / beta[..., None])  # W^(-1/2)
    chosen: Any = None
    done: Any = None
    for k in range(SAMPLE_ROUNDS):
        normal, uniform = draw(k)
        rank = normal.ndim  # (*sample, *batch, proposal, 4): F's arrays get the sample axes as unit axes
        y = normal * _lead(xp, scale[..., None, :], rank)
        x = y / xp.sqrt(xp.sum(y * y, axis=-1, keepdims=True))
        t = xp.sum(_lead(xp, lam[..., None, :], rank) * x * x, axis=-1)
        # log(1 - u) with u in [0, 1): log of a uniform in (0, 1], never -inf
        ratio = -t + 2.0 * xp.log1p(2.0 * t / _lead(xp, beta[..., None], rank - 1))
        accept = xp.log1p(-uniform) < ratio - _lead(xp, log_bound[..., None], rank - 1)
        # the first accepted of this round: where the running count of acceptances first reaches 1
        one, zero = xp.ones_like(t), xp.zeros_like(t)  # (a where of two Python floats is float64 in NumPy)
        count = xp.cumsum(xp.where(accept, one, zero), axis=-1)
        one_hot = xp.where(accept & (count == 1.0), one, zero)
        pick = xp.sum(x * one_hot[..., None], axis=-2)
        hit = count[..., -1] > 0.0
        if chosen is None:
            mode = xp.zeros_like(pick) + _constant(xp, [0.0, 0.0, 0.0, 1.0], pick, pick.ndim)
            chosen, done = xp.where(hit[..., None], pick, mode), hit
        else:
            chosen, done = xp.where(done[..., None], chosen, pick), done | hit
    q = xp.sum(_lead(xp, v, chosen.ndim + 1) * chosen[..., None, :], axis=-1)  # V x: (w, x, y, z)
    # Normalised again: V is orthonormal only to the eigensolver's accuracy (cuSOLVER's float64
    # eigenvectors left | |q|^2 - 1 | ~ 2e-15 on an H200, and R(q) below assumes |q| = 1), so that every
    # sample is a rotation to a few ulps on every device.
    q = q / xp.sqrt(xp.sum(q * q, axis=-1, keepdims=True))
    # the backend's rule for non-finite rows, here: the sample axes lead, where the rule appends axes
    bad = xp.reshape(bad, (*(1,) * (q.ndim - 1 - bad.ndim), *bad.shape, 1))
    q = xp.where(bad, xp.nan, q)
    w, qx, qy, qz = q[..., 0], q[..., 1], q[..., 2], q[..., 3]
    return stack_matrix(
        xp,
        [
            1.0 - 2.0 * (qy * qy + qz * qz), 2.0 * (qx * qy - w * qz), 2.0 * (qx * qz + w * qy),
            2.0 * (qx * qy + w * qz), 1.0 - 2.0 * (qx * qx + qz * qz), 2.0 * (qy * qz - w * qx),
            2.0 * (qx * qz - w * qy), 2.0 * (qy * qz + w * qx), 1.0 - 2.0 * (qx * qx + qy * qy),
        ],
    )  # fmt: skip


def _mode_axis() -> tuple[Any, ...]:
    return ([0.0, 0.0, 0.0, 1.0],)


@eager_form(of=matrix_fisher_sample)
def matrix_fisher_sample_eager(xp: Any, F: Any, *, draw: Draw) -> Any:
    """:func:`matrix_fisher_sample`, eager form (torch): the four rounds as one, over all
    ``SAMPLE_ROUNDS * SAMPLE_PROPOSALS`` proposals (``draw(None)``: the rounds' numbers side by side,
    which ``draw(k)`` slices), F's batch flattened. The first accepted proposal over the rounds in
    order is the first accepted one of their concatenation, so the rule is the same; the per-F
    quantities keep unit axes (B, 1, .) that broadcast against the proposals (S, B, P, .). The
    rotation is :func:`_core.quaternion_to_matrix_eager`'s, and a non-finite F makes its rows NaN by
    the arithmetic (a NaN added to q)."""
    (mode,) = constants(xp, F, _mode_axis)
    batch = tuple(F.shape[:-2])
    b, v = xp.linalg.eigh(xp.nan_to_num(_davenport_eager(xp, F), nan=0.0, posinf=0.0, neginf=0.0))
    lam = (b[:, 3:] - b)[:, None, :]  # (B, 1, 4)
    twice = lam + lam
    beta: Any = 1.0  # Newton's steps of _acg_beta, on (B, 1, 1)
    for _ in range(_NEWTON_STEPS):
        inv = xp.reciprocal(beta + twice)
        beta = beta + (xp.sum(inv, -1, keepdim=True) - 1.0) / xp.sum(inv * inv, -1, keepdim=True)
    log_bound = -0.5 * (4.0 - beta) + 2.0 * xp.log(4.0 / beta)
    scale = xp.rsqrt(1.0 + twice / beta)
    normal, uniform = draw(None)
    rows = math.prod(batch)
    samples = normal.shape[: normal.ndim - 2 - len(batch)]
    y = normal.view(math.prod(samples), rows, normal.shape[-2], 4) * scale  # (S, B, P, 4)
    squares = y * y
    t = xp.sum(squares * lam, -1, keepdim=True) / xp.sum(squares, -1, keepdim=True)
    ratio = -t + 2.0 * xp.log1p(t * (2.0 / beta))
    accept = xp.log1p(-uniform.view(*y.shape[:-1], 1)) < ratio - log_bound
    first = accept & (xp.cumsum(accept, -2) == 1)
    pick = xp.where(xp.any(accept, -2), xp.sum(y * first, -2), mode)  # (S, B, 4)
    pick = pick / xp.linalg.vector_norm(pick, dim=-1, keepdim=True)
    bad = xp.sum(F * 0.0, (-2, -1)).view(1, rows, 1)  # 0, or NaN for a non-finite F
    q = xp.sum(v * pick[..., None, :], -1) + bad  # V x: (w, x, y, z)
    r9, _ = quaternion_to_matrix_eager(xp, q.view(-1, 4))
    return r9.view(*samples, *batch, 3, 3)


# ---------------------------------------------------------------------------------------------------
# Bingham NLL for the 10D head


@op(a=(10,), q=(4,))
def bingham_nll(
    xp: Any, a: Any, q: Any, *, scalar_first: bool = True, normalizer: Normalizer = reduced_log_normalizer
) -> Any:
    """Negative log-likelihood of quaternions under the Bingham distribution of the 10D head.

    Args:
        a: shape ``(..., 10)``: the upper triangle of a symmetric 4x4 matrix A, row by row, indexed in
            the storage order of q (as ``symmetric_matrix_to_quaternion`` reads it).
        q: quaternions of any non-zero norm, shape ``(..., 4)`` (the zero quaternion is the identity);
            the batch shapes broadcast.
        scalar_first: storage order of q and of A's indices.

    Returns:
        Shape ``(...)``: ``q^T A q / |q|^2 + log c_B(A)`` for the density ``exp(-q^T A q) / c_B(A)``
        against the uniform probability measure on S^3 (equivalently, on SO(3)). The sign makes the
        head's point estimate, the eigenvector of A's *smallest* eigenvalue
        (``symmetric_matrix_to_quaternion``), the mode. The distribution is the matrix Fisher one
        of the F with ``K(F) = tr(A)/4 I - A`` (``exp(-q^T A q) = e^{-tr(A)/4} exp(tr(F^T R(q)))``; the
        proper singular values of F are ``tr(A)/4 - (a_0 + a_i)/2`` for A's ascending eigenvalues
        a_0..a_3): ``bingham_nll(a, q) = matrix_fisher_nll(F, R(q))``, ``log c_B(A) = log c(F) -
        tr(A)/4``, computed by the same normaliser with the same derivatives.
    """
    if not scalar_first:  # re-index to (w, x, y, z) first, so that both orders compute the same
        a = xp.stack([a[..., _INDEX[(_XYZW[i], _XYZW[j])]] for i, j in _UPPER], axis=-1)
        q = join_quaternion(xp, *split_quaternion(q, False), True)
    batch = tuple(xp.broadcast_shapes(a.shape[:-1], q.shape[:-1]))
    mat = _symmetric(xp, a)
    trace = mat[..., 0, 0] + mat[..., 1, 1] + mat[..., 2, 2] + mat[..., 3, 3]
    log_c = _lead(xp, normalizer(xp, -mat) - 0.25 * trace, len(batch))  # on a's own batch, once
    w, x, y, z, inv = _unit_components(xp, xp.broadcast_to(q, (*batch, 4)), True)
    w = xp.where(inv == 0.0, 1.0, w)  # the zero quaternion is the identity
    u = xp.stack([w, x, y, z], axis=-1)
    full = xp.broadcast_to(_lead(xp, mat, len(batch) + 2), (*batch, 4, 4))
    energy = xp.sum(u * xp.matmul(full, u[..., None])[..., 0], axis=-1)
    return energy + log_c


def _bingham_tables() -> tuple[Any, ...]:
    """The constants of :func:`bingham_nll_eager`, in scalar-first order:

    - (10, 16): ``K = tr(A)/4 I - A`` from the ten entries;
    - (16, 11): from the products ``u_i u_j`` (row-major), the coefficient of each of the ten entries in
      ``u^T A u - tr(A) |u|^2 / 4`` and, last, ``|u|^2``;
    - (11,): the bias: those of ``u = e_w`` times ``tiny``, so that the zero quaternion gives exactly the
      identity's energy (``tiny * c / tiny``), and every other one (``|u|^2 >= 1``) an energy changed
      by at most ``tiny``, below its rounding;
    - (10,): the position in scalar-last storage of each scalar-first entry."""
    import numpy as np

    mats = _symmetric(np, np.eye(10))
    trace = np.trace(mats, axis1=-2, axis2=-1)
    to_k = trace[:, None, None] / 4.0 * np.eye(4) - mats
    forms = np.zeros((4, 4, 11))
    for k, (i, j) in enumerate(_UPPER):
        forms[i, j, k] += 1.0
        if i != j:
            forms[j, i, k] += 1.0
        else:
            forms[range(4), range(4), k] -= 0.25
    forms[range(4), range(4), 10] = 1.0
    bias = _TINY32 * forms[0, 0]
    positions = [_INDEX[(_XYZW[i], _XYZW[j])] for i, j in _UPPER]
    return to_k.reshape(10, 16).tolist(), forms.reshape(16, 11).tolist(), bias.tolist(), positions


@eager_form(of=bingham_nll)
def bingham_nll_eager(
    xp: Any, a: Any, q: Any, *, scalar_first: bool = True, normalizer: Normalizer = reduced_log_normalizer
) -> Any:
    """:func:`bingham_nll`, eager form. With ``A_0 = A - tr(A)/4 I``, ``q^T A q / |q|^2 - tr(A)/4 = u^T A_0
    u / |u|^2`` and the normaliser depends on ``A_0`` alone: the normaliser of ``-A_0`` (one product of
    the ten entries) plus the energy ``a . f(u) / |u|^2``, where ``f(u)`` and ``|u|^2`` are one product
    of ``u u^T`` (``u`` = :func:`_core.unit_scale` of q). Scalar-last storage is reordered first (an
    index and a roll), so that both orders compute the same numbers."""
    to_k, forms, bias, positions = constants(xp, a, _bingham_tables)
    if not scalar_first:
        a, q = xp.index_select(a, -1, positions), xp.roll(q, 1, -1)
    k = xp.mm(xp.reshape(a, (-1, 10)), to_k).view(-1, 4, 4)  # -A_0
    log_c = xp.reshape(normalizer(xp, k), tuple(a.shape[:-1]))
    u = unit_scale(xp, q)
    p = xp.addmm(bias, (u[..., :, None] * u[..., None, :]).reshape(-1, 16), forms)
    f, n = p.split([10, 1], 1)
    energy = xp.sum((f / n).view(*q.shape[:-1], 10) * a, -1)
    return energy + log_c
