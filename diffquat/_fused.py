"""Fused formulations of quaternion <-> matrix: constant matrices of quadratic and linear forms.

The core (:mod:`diffquat._core`) writes each conversion as ~30 scalar expressions; evaluated eagerly,
every one is a pass over memory, forward and again backward (and for small batches, each costs a fixed
few microseconds of dispatch whatever its size). The fused paths of the backends evaluate the same
maps as a few whole-array steps, each conversion's linear part one small matrix product with a
constant matrix built here from the formula's terms:

- ``quaternion_to_matrix``: every entry of ``|q|^2 (R - I)`` is a quadratic form in ``q``, a linear
  map of the 16 products ``P = q q^T``, and so is ``|q|^2``: ``P @ Q2M_FORMS`` gives all ten at once.
  The values agree with the core's to rounding (the core normalises ``q`` first, for float32
  gradients at extreme norms; the fused backward is analytic and needs no such care).
- ``matrix_to_quaternion``: the four candidates ``c_k = 4 q_k q`` of the core are the rows of one
  symmetric 4 x 4 matrix ``K``, an affine map of the matrix: ``matrix @ M2Q_FORMS + M2Q_BASE``.

Everything is in scalar-first order (w, x, y, z); the backends reorder scalar-last arrays around it,
so that both orders give bitwise the same numbers.
"""

from __future__ import annotations

from typing import Any

_W, _X, _Y, _Z = 0, 1, 2, 3

# Entry (i, j) of R - I, row-major, for a unit q: 2 (sign_1 q_a1 q_b1 + sign_2 q_a2 q_b2), as the two
# terms (a, b, sign) (Kuipers' formula with q0^2 + q1^2 + q2^2 + q3^2 = 1 used on the diagonal).
_Q2M_TERMS = [
    ((_Y, _Y, -1.0), (_Z, _Z, -1.0)), ((_X, _Y, 1.0), (_Z, _W, -1.0)), ((_X, _Z, 1.0), (_Y, _W, 1.0)),
    ((_X, _Y, 1.0), (_Z, _W, 1.0)), ((_X, _X, -1.0), (_Z, _Z, -1.0)), ((_Y, _Z, 1.0), (_X, _W, -1.0)),
    ((_X, _Z, 1.0), (_Y, _W, -1.0)), ((_Y, _Z, 1.0), (_X, _W, 1.0)), ((_X, _X, -1.0), (_Y, _Y, -1.0)),
]  # fmt: skip


def _q2m_forms() -> list[list[float]]:
    forms = [[0.0] * 10 for _ in range(16)]
    for entry, terms in enumerate(_Q2M_TERMS):
        for a, b, sign in terms:
            forms[4 * a + b][entry] += 2.0 * sign
    for a in range(4):
        forms[5 * a][9] = 1.0  # the squared norm: the trace of P
    return forms


#: (16, 10): for the products ``P = q q^T`` (flat), ``P @ Q2M_FORMS`` holds the 9 entries of
#: ``|q|^2 (R - I)`` (row-major), then ``|q|^2``; so ``R = I + (P @ F)[:9] / (P @ F)[9]``.
Q2M_FORMS = _q2m_forms()
#: (9, 16): row ``e`` is ``F_e + F_e^T`` (flat) for column ``e`` of ``Q2M_FORMS`` seen as a 4 x 4
#: matrix ``F_e``. For a cotangent ``G`` of ``R`` (flat), ``H = G @ Q2M_FORMS_SYM`` (as 4 x 4) is the
#: symmetric matrix with ``grad_q (G . (P @ F)[:9]) = H q`` (the backward pass).
Q2M_FORMS_SYM = [
    [Q2M_FORMS[4 * a + b][e] + Q2M_FORMS[4 * b + a][e] for a in range(4) for b in range(4)] for e in range(9)
]
#: The constant part of R (the identity), flat.
Q2M_BASE = [1.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0]

# K[a, b] = 4 q_a q_b (rows and columns in (w, x, y, z) order) as (row-major matrix index, sign) terms;
# the diagonal, the pivots, also has the constant 1 (M2Q_BASE).
_K_TERMS = {
    (_W, _W): ((0, 1.0), (4, 1.0), (8, 1.0)),
    (_X, _X): ((0, 1.0), (4, -1.0), (8, -1.0)),
    (_Y, _Y): ((0, -1.0), (4, 1.0), (8, -1.0)),
    (_Z, _Z): ((0, -1.0), (4, -1.0), (8, 1.0)),
    (_W, _X): ((7, 1.0), (5, -1.0)),
    (_W, _Y): ((2, 1.0), (6, -1.0)),
    (_W, _Z): ((3, 1.0), (1, -1.0)),
    (_X, _Y): ((1, 1.0), (3, 1.0)),
    (_X, _Z): ((2, 1.0), (6, 1.0)),
    (_Y, _Z): ((5, 1.0), (7, 1.0)),
}


def _m2q_forms() -> list[list[float]]:
    forms = [[0.0] * 16 for _ in range(9)]
    for a in range(4):
        for b in range(4):
            for i, sign in _K_TERMS[(min(a, b), max(a, b))]:
                forms[i][4 * a + b] += sign
    return forms


#: (9, 16): ``matrix (flat) @ M2Q_FORMS + M2Q_BASE`` is ``K`` (flat), whose row k is candidate ``c_k``;
#: for the backward pass, ``dL/dmatrix = dL/dK @ M2Q_FORMS^T``.
M2Q_FORMS = _m2q_forms()
#: The constant part of K: 1 on the diagonal (the pivots are 1 +- m00 +- m11 +- m22).
M2Q_BASE = [1.0 if a == b else 0.0 for a in range(4) for b in range(4)]
#: Weights of the component signs in the canonical-sign rule (the first non-zero of (w, x, y, z)
#: decides): each exceeds the sum of those after it, so ``sign(q) . SIGN_WEIGHTS`` has that sign.
SIGN_WEIGHTS = [8.0, 4.0, 2.0, 1.0]


def normalize_vjp(xp: Any, q: Any, inv: Any, grad: Any) -> Any:
    """Cotangent of ``c`` for ``q = c * inv``, ``inv = +-1 / |c|``: ``inv (g - q (q . g))``. The same
    linear map takes a tangent ``dc`` to ``dq`` (it is symmetric)."""
    return inv * (grad - q * xp.sum(q * grad, axis=-1, keepdims=True))
