"""Fused formulations of quaternion <-> matrix and their derivatives: index tables and shared steps.

The core (:mod:`diffquat._core`) writes each conversion as ~30 scalar expressions; evaluated eagerly,
every one is a pass over memory, forward and again backward. The fused paths of the backends evaluate
the same maps as a few whole-array steps driven by the constant index tables here:

- ``quaternion_to_matrix``: every entry of ``R`` is ``base + sign_1 P[a_1, b_1] + sign_2 P[a_2, b_2]``
  with ``P = (s q) q^T`` and ``s = 2 / |q|^2``: one outer product, one gather of 18 products, one sum.
  The values agree with the core's to rounding (the core normalises ``q`` first, for float32
  gradients at extreme norms; the fused backward is analytic and needs no such care).
- ``matrix_to_quaternion``: the four candidates ``c_k = 4 q_k q`` of the core are the rows of one
  symmetric 4 x 4 matrix ``K``, each entry ``base + up to three signed entries of the matrix``.

Tables are in scalar-first order (w, x, y, z); the backends reorder scalar-last arrays around them, so
that both orders give bitwise the same numbers.
"""

from __future__ import annotations

from typing import Any

_W, _X, _Y, _Z = 0, 1, 2, 3

# Entry (i, j) of R, row-major: two terms (a, b, sign) of P[a, b] = (s q_a) q_b, and the constant.
_Q2M_TERMS = [
    ((_Y, _Y, -1.0), (_Z, _Z, -1.0)), ((_X, _Y, 1.0), (_Z, _W, -1.0)), ((_X, _Z, 1.0), (_Y, _W, 1.0)),
    ((_X, _Y, 1.0), (_Z, _W, 1.0)), ((_X, _X, -1.0), (_Z, _Z, -1.0)), ((_Y, _Z, 1.0), (_X, _W, -1.0)),
    ((_X, _Z, 1.0), (_Y, _W, -1.0)), ((_Y, _Z, 1.0), (_X, _W, 1.0)), ((_X, _X, -1.0), (_Y, _Y, -1.0)),
]  # fmt: skip

#: Flat index into P (4 a + b) of each of the 18 terms, entry by entry, and their signs.
Q2M_INDEX = [4 * a + b for terms in _Q2M_TERMS for a, b, _ in terms]
Q2M_SIGN = [sign for terms in _Q2M_TERMS for _, _, sign in terms]
#: Entry of R that each of the 18 terms belongs to (for the backward pass).
Q2M_ENTRY = [entry for entry in range(9) for _ in range(2)]
#: The constant part of R (the identity), flat.
Q2M_BASE = [1.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0]

# K[a, b] = 4 q_a q_b, rows and columns in (w, x, y, z) order, from (row-major matrix index, sign)
# terms; index 9 is a zero pad so that every entry has three terms.
_PAD = (9, 0.0)
_K_TERMS = {
    (_W, _W): ((0, 1.0), (4, 1.0), (8, 1.0)),
    (_X, _X): ((0, 1.0), (4, -1.0), (8, -1.0)),
    (_Y, _Y): ((0, -1.0), (4, 1.0), (8, -1.0)),
    (_Z, _Z): ((0, -1.0), (4, -1.0), (8, 1.0)),
    (_W, _X): ((7, 1.0), (5, -1.0), _PAD),
    (_W, _Y): ((2, 1.0), (6, -1.0), _PAD),
    (_W, _Z): ((3, 1.0), (1, -1.0), _PAD),
    (_X, _Y): ((1, 1.0), (3, 1.0), _PAD),
    (_X, _Z): ((2, 1.0), (6, 1.0), _PAD),
    (_Y, _Z): ((5, 1.0), (7, 1.0), _PAD),
}


def _k_terms(a: int, b: int) -> tuple[tuple[int, float], ...]:
    return _K_TERMS[(a, b)] if (a, b) in _K_TERMS else _K_TERMS[(b, a)]


#: Index into the padded flat matrix (10 entries) of the 3 terms of each of the 16 entries of K.
M2Q_INDEX = [i for a in range(4) for b in range(4) for i, _ in _k_terms(a, b)]
M2Q_SIGN = [s for a in range(4) for b in range(4) for _, s in _k_terms(a, b)]
#: Entry of K (flat) that each of the 48 terms belongs to (for the backward pass).
M2Q_ENTRY = [entry for entry in range(16) for _ in range(3)]
#: The constant part of K: 1 on the diagonal (the pivots are 1 +- m00 +- m11 +- m22).
M2Q_BASE = [1.0 if a == b else 0.0 for a in range(4) for b in range(4)]
#: Priority of each component in the canonical-sign rule: the first non-zero of (w, x, y, z) decides.
SIGN_PRIORITY = [4.0, 3.0, 2.0, 1.0]


def q2m_scale(xp: Any, q: Any) -> Any:
    """``s = 2 / |q|^2``, shape ``(..., 1)``, and 0 (the identity, zero derivative) where ``|q|^2`` is
    below the smallest normal number. The clip keeps the discarded branch and every derivative of it
    finite at ``q = 0`` (double backward differentiates this too)."""
    n2 = xp.sum(q * q, axis=-1, keepdims=True)
    tiny = xp.finfo(n2.dtype).tiny
    return xp.where(n2 >= tiny, 2.0 / xp.clip(n2, tiny, None), 0.0)


def q2m_gradient(xp: Any, q: Any, s: Any, forms: Any) -> Any:
    """``dL/dq`` of ``R = I + terms of P = (s q) q^T`` given ``H = dL/dP`` (..., 4, 4):
    ``s ((H + H^T) q - s (q^T H q) q)`` (``ds/dq = -s^2 q``). The product ``s (q . Hq)`` is formed
    first: for ``|q|`` near 1e15 or 1e-15 in float32 the dot product alone is at the range limit."""
    h = forms + xp.swapaxes(forms, -1, -2)
    hq = xp.sum(h * q[..., None, :], axis=-1)
    half = 0.5 * s * xp.sum(q * hq, axis=-1, keepdims=True)
    return s * (hq - half * q)


def normalize_vjp(xp: Any, q: Any, inv: Any, grad: Any) -> Any:
    """Cotangent of ``c`` for ``q = c * inv``, ``inv = +-1 / |c|``: ``inv (g - q (q . g))``. The same
    linear map takes a tangent ``dc`` to ``dq`` (it is symmetric)."""
    return inv * (grad - q * xp.sum(q * grad, axis=-1, keepdims=True))
