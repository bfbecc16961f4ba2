"""The core of the rotation math, written once over an array namespace ``xp``. It holds:

- the operation registry the backends validate and wrap against: :func:`op` and ``SHAPES`` (the
  trailing shape of every array argument), and the markers :func:`canonical` (``CANONICAL``) and
  :func:`nonfinite_by_arithmetic` (``NONFINITE_BY_ARITHMETIC``);
- the quaternion <-> matrix conversions (:func:`quaternion_to_matrix`, :func:`matrix_to_quaternion`,
  :func:`unit_quaternion_to_matrix`), their written-out tangent and cotangent rules
  (:func:`derivative_rules`), and :func:`registered_conversions`, through which every backend binds
  its public conversions and the conversion step of every composite;
- the quaternion operations the backends expose directly (standardise, normalise, reorder, the
  uniform sampler) and the helpers the other core modules (``_algebra``, ``_lie``, ``_euler``,
  ``_representations``, ``_statistics``, ``_fisher``) build on: splitting and joining components,
  :func:`stack_matrix`, :func:`zero_or_nan`, :func:`computed_once`, :func:`small_matmul`,
  :func:`cancelling_factor`.

``xp`` is the ``numpy`` or ``torch`` module itself, or ``jax.numpy`` with a few additions
(:mod:`diffquat.jax._namespace`): the functions here use only what the three share (indexing with
``...``, arithmetic, comparisons, ``stack``/``reshape`` with ``axis``, ``where``, ``sqrt``,
``finfo``). They do no validation and no dtype juggling: the backend modules do that once, in
:mod:`diffquat._backend`, and then call into here in a floating dtype of at least 32 bits.

Numerical rules every function here follows, so that it is differentiable everywhere and traceable by
``torch.compile(fullgraph=True)``, ``torch.func`` and ``jax.jit``:

- no Python ``if`` on array values and no reductions across the batch;
- every branch of a ``where`` is finite for every input (the unused branch is fed a safe value), or
  the selection happens before the singular operation, so reverse mode never multiplies 0 by inf.
"""

from __future__ import annotations

import functools
from collections.abc import Callable
from typing import Any, TypeVar

F = TypeVar("F", bound=Callable[..., Any])

# The conversion step inside a composite (axis-angle or Euler angles to matrix through the quaternion,
# and back), as ``conversion(xp, x)``: the core formula by default. Every backend passes the same
# thing, its registration of the conversion with its written-out derivative (:func:`derivative_rules`;
# numpy: the formula itself), so that a composite differentiates its conversion step as the public
# conversion does. Not part of the public signatures: the backend wrappers do not take it.
Conversion = Callable[..., Any]

# Trailing shape of every array argument of every public core function, by argument name. The backend
# modules validate against this table, so the error message and the docstring cannot drift apart.
SHAPES: dict[str, dict[str, tuple[int, ...]]] = {}


def op(**trailing: tuple[int, ...]) -> Callable[[F], F]:
    """Register the trailing shape of each array argument of a core function."""

    def register(fn: F) -> F:
        SHAPES[fn.__name__] = trailing
        return fn

    return register


# Core functions whose result is a quaternion in canonical sign. The backends re-standardise such a
# result after casting it back to a 16-bit dtype: a w that is tiny but positive in float32 can round
# to 0 there, and then the sign of x decides.
CANONICAL: set[str] = set()


# Core functions whose arithmetic already makes every entry of a non-finite row NaN (the backends'
# rule, ``_backend.nonfinite_rows``), so that no selection is added after them: each output entry
# reads a scale taken over the whole row (a NaN or an infinity in it makes the scale NaN). Skipping
# the selection keeps the compiled program the core's own (tests/test_xla.py), and the rule itself is
# tested for every op on every backend (tests/test_values.py).
NONFINITE_BY_ARITHMETIC: set[str] = {"quaternion_to_matrix"}


def nonfinite_by_arithmetic(fn: F) -> F:
    """Mark a core function whose arithmetic makes every entry of a non-finite row NaN (see
    ``NONFINITE_BY_ARITHMETIC``): the backends then add no selection after it."""
    NONFINITE_BY_ARITHMETIC.add(fn.__name__)
    return fn


def canonical(fn: F) -> F:
    """Mark a core function whose result is a quaternion in canonical sign (see ``CANONICAL``)."""
    CANONICAL.add(fn.__name__)
    return fn


def split_quaternion(q: Any, scalar_first: bool) -> tuple[Any, Any, Any, Any]:
    """Components (w, x, y, z) of ``q`` in either storage order."""
    if scalar_first:
        return q[..., 0], q[..., 1], q[..., 2], q[..., 3]
    return q[..., 3], q[..., 0], q[..., 1], q[..., 2]


def unstack_quaternion(xp: Any, q: Any, scalar_first: bool) -> tuple[Any, Any, Any, Any]:
    """:func:`split_quaternion` for a formula that jax differentiates: read with the namespace's
    ``unstack`` where it has one (jax; numpy >= 2.1 reads the same values). Reverse mode transposes
    four slices into four zero-padded copies of the ``(..., 4)`` cotangent summed, and one ``unstack``
    into one ``stack`` (docs/performance.md, Formula shapes)."""
    unstack = getattr(xp, "unstack", None)
    if unstack is None:
        return split_quaternion(q, scalar_first)
    a, b, c, d = unstack(q, axis=-1)
    return (a, b, c, d) if scalar_first else (d, a, b, c)


def join_quaternion(xp: Any, w: Any, x: Any, y: Any, z: Any, scalar_first: bool) -> Any:
    """Stack components (w, x, y, z) into ``(..., 4)`` in the requested storage order."""
    return xp.stack([w, x, y, z] if scalar_first else [x, y, z, w], axis=-1)


def stack_matrix(xp: Any, entries: list[Any]) -> Any:
    """Nine row-major entries of shape ``batch`` into one ``(*batch, 3, 3)`` array."""
    flat = xp.stack(entries, axis=-1)
    return xp.reshape(flat, (*flat.shape[:-1], 3, 3))


def computed_once(xp: Any, x: Any) -> Any:
    """``x`` itself, computed once where a compiler would otherwise recompute it in every output.

    XLA fuses by recomputation: a value behind a transcendental (cos, sin) that feeds the nine entries
    of a matrix is evaluated nine times per rotation, in each entry's loop (docs/performance.md,
    Formula shapes). A namespace that has ``optimization_barrier`` (the jax backend's) keeps such a
    value as one array instead; for the others this is the identity, and it changes no value or
    derivative anywhere."""
    barrier = getattr(xp, "optimization_barrier", None)
    return x if barrier is None else barrier(x)


def small_matmul(xp: Any, a: Any, b: Any) -> Any:
    """``a @ b`` of small matrices, ``(..., n, k)`` times ``(..., k, m)`` (k static), batch shapes
    broadcast: one ``matmul`` call in eager torch and NumPy. Where a compiler writes the loops, the
    value is the sum of k broadcast products, which fuses into the loop of the operation around it:
    under ``torch.compile`` and ``torch.export`` (``compiler.is_compiling()``), where inductor leaves a
    batched product of 3x3 blocks on the CPU to a library ``bmm`` outside its fused loop, and on XLA
    (the namespace's ``diffquat_small_matmul``: the products in value, matmuls in derivative, whose
    transposes XLA:CPU runs faster than the products' reductions). Eager, the products are slower
    than one call (docs/performance.md, Formula shapes, SE(3))."""
    # torch first: a missing attribute of the torch module costs 0.8 us (its module __getattr__), a
    # found one 0.1 us, on every product of an eager call
    compiler = getattr(xp, "compiler", None)
    if compiler is not None:
        return sum_of_products(a, b) if compiler.is_compiling() else xp.matmul(a, b)
    fused = getattr(xp, "diffquat_small_matmul", None)
    return xp.matmul(a, b) if fused is None else fused(a, b)


def sum_of_products(a: Any, b: Any) -> Any:
    """``a @ b`` as the sum over the contracted axis of broadcast products ``a[:, j] b[j, :]``."""
    out = a[..., :, :1] * b[..., :1, :]
    for j in range(1, a.shape[-1]):
        out = out + a[..., :, j : j + 1] * b[..., j : j + 1, :]
    return out


def zero_or_nan(xp: Any, x: Any, trailing: int) -> Any:
    """0 for each element of ``x``'s batch (all but the last ``trailing`` axes) whose entries are all
    finite, NaN for one that holds a NaN or an infinity: the sum of ``0 * x`` over those axes. IEEE
    gives ``0 * x = +-0`` for finite ``x`` and NaN for NaN and +-inf, and a sum of zeros is 0 (where a
    sum of ``x`` itself could overflow). One product and one sum; no compiler folds ``0 * x`` to 0 for
    floats (that would be wrong for inf and NaN; tests/test_paths.py checks inductor's code). Read by
    ``_backend.nonfinite_rows`` and by functions that make non-finite rows NaN by their arithmetic."""
    z = x * 0.0
    return xp.sum(z, axis=tuple(range(-trailing, 0))) if trailing else z


def cancelling_factor(xp: Any, x: Any) -> Any:
    """``x`` itself, as a constant of differentiation: only for a factor that cancels out of the
    result, such as the scale a vector is divided by before its norm is taken (``v / s / |v / s|`` is
    ``v / |v|`` for every ``s > 0``). Its derivative terms cancel exactly in theory and to rounding in
    practice; dropping them saves the backward of the scale: the maximum, the absolute values and a
    division of the cotangent (docs/performance.md, Formula shapes). ``stop_gradient`` on the jax
    backend's namespace, ``torch.detach`` on torch, the identity on NumPy."""
    # torch's name first: a missing attribute of the torch module costs 0.8 us (its module __getattr__),
    # a found one 0.1 us, on every eager call (see small_matmul); neither jax's namespace nor NumPy has
    # a ``detach``
    drop = getattr(xp, "detach", None) or getattr(xp, "stop_gradient", None)
    return x if drop is None else drop(x)


def range_divisor(xp: Any, largest: Any) -> Any:
    """What to divide arrays by whose largest absolute entry is ``largest`` (keepdims) before their
    squares are taken, for maps blind to that scale: ``largest / 16`` (1 where that is 0), a constant
    of differentiation (``cancelling_factor``). The largest entry becomes 16, so no square over- or
    underflows. 16, not 1: XLA divides by a broadcast divisor as a product with its reciprocal, which
    is subnormal and flushed to zero for divisors beyond 2^126 in float32 (2^1022 in float64)."""
    divisor = largest * 0.0625
    return cancelling_factor(xp, xp.where(divisor > 0, divisor, 1.0))


def _negative_canonical(w: Any, x: Any, y: Any, z: Any) -> Any:
    """True where the quaternion is not in canonical sign: w < 0, or w = 0 and the first non-zero of
    (x, y, z) is negative. This is scipy's ``as_quat(canonical=True)`` rule."""
    return (w < 0) | ((w == 0) & ((x < 0) | ((x == 0) & ((y < 0) | ((y == 0) & (z < 0))))))


@op(q=(4,))
def quaternion_to_matrix(xp: Any, q: Any, *, scalar_first: bool = True) -> Any:
    """Rotation matrix of a quaternion of any non-zero norm.

    Args:
        q: quaternions, shape ``(..., 4)``: (w, x, y, z) if ``scalar_first`` else (x, y, z, w).
            They need not be unit: ``q`` and ``c * q`` (c != 0) give the same matrix, so a network can
            feed its raw 4-vector output, of any size down to the smallest subnormal number. The zero
            quaternion (all four components zero) gives the identity, with a zero gradient.
        scalar_first: storage order of ``q``; the default is scalar first (w, x, y, z).

    Returns:
        Rotation matrices, shape ``(..., 3, 3)``, acting on column vectors: ``R @ v`` rotates ``v`` from
        the local frame into the global frame (active rotation). Same dtype as ``q``.
    """
    # Normalise first, then use the unit formula (s = 2). Dividing by |q|^2 instead (s = 2 / n2) has
    # the same value but puts d(1/n2)/dn2 = -1/n2^2 on the reverse-mode chain, which overflows float32
    # for |q| below ~3e-10; through 1/sqrt(n2) every intermediate derivative stays near 1/n2.
    w, x, y, z, _ = _unit_components(xp, q, scalar_first)
    return _matrix_of_unit(xp, w, x, y, z)


def unit_quaternion_to_matrix(xp: Any, q: Any) -> Any:
    """:func:`quaternion_to_matrix` of a scalar-first quaternion that is unit by construction (to
    rounding), without normalising it: the conversion step of ``axis_angle_to_matrix``, whose
    ``(cos(t/2), sin(t/2) axis)`` has norm 1 within an ulp or two. On a unit quaternion the
    normalisation changes the entries by rounding only, and ``w -> R(w / |w|)`` and ``w -> R(w)`` are
    one map on the sphere, so every derivative along it is the same; skipping it saves the largest
    component, the norm and four divisions per rotation (docs/performance.md, Formula shapes), for one
    more rounding of the norm in the entries (float32 max error on the shared test cases 3.9e-7 ->
    4.4e-7)."""
    return _matrix_of_unit(xp, *unstack_quaternion(xp, q, True))


def _matrix_of_unit(xp: Any, w: Any, x: Any, y: Any, z: Any) -> Any:
    """Kuipers' matrix of the unit quaternion (w, x, y, z), ``(..., 3, 3)``."""
    x2, y2, z2 = 2.0 * x, 2.0 * y, 2.0 * z
    xx, yy, zz = x2 * x, y2 * y, z2 * z
    xy, xz, yz = x2 * y, x2 * z, y2 * z
    wx, wy, wz = x2 * w, y2 * w, z2 * w
    return stack_matrix(
        xp,
        [
            1.0 - (yy + zz), xy - wz, xz + wy,
            xy + wz, 1.0 - (xx + zz), yz - wx,
            xz - wy, yz + wx, 1.0 - (xx + yy),
        ],
    )  # fmt: skip


def _unit_components(xp: Any, q: Any, scalar_first: bool) -> tuple[Any, Any, Any, Any, Any]:
    """``q / |q|`` as components (w, x, y, z), and ``1 / |q|``.

    The quaternion is divided by its largest component first, and that is normalised: its squared norm
    lies in [1, 4]. Through ``1 / sqrt(|q|^2)`` instead, every derivative meets powers of ``1 / |q|^2``:
    the second derivative overflowed float32 from |q| <= 1e-13 and float64 from 1e-150 on, though it is
    only of size ``1 / |q|^2``, and ``|q|^2`` itself overflows float32 from |q| ~ 1.8e19. This way the
    largest intermediate derivative of second order is ``1 / max|q_i|^2``, and every finite non-zero
    quaternion works, subnormal ones included. The zero quaternion takes ``1 / |q| = 0``, so all
    components are 0 (the identity rotation, with a zero gradient); the double wheres keep the divisions
    and their derivatives finite in the branch that is thrown away."""
    w, x, y, z = unstack_quaternion(xp, q, scalar_first)
    big, nonzero = _unit_scale(xp, w, x, y, z)
    # big cancels out of both results (q / big / |q / big| and |q / big|^-1 / big), so it is a
    # constant of differentiation: with it held fixed both are the same functions of q, every
    # derivative included, and the backward pass skips the maximum and the divisions' derivatives
    # in big, which XLA would fuse into each component of the cotangent (docs/performance.md,
    # Formula shapes).
    big = cancelling_factor(xp, big)
    # Divisions, not a product with 1 / big: that reciprocal is subnormal past ~8.5e37 in float32.
    w, x, y, z = w / big, x / big, y / big, z / big
    inv = _inverse_norm(xp, nonzero, w * w + x * x + y * y + z * z)
    return w * inv, x * inv, y * inv, z * inv, inv / big


def _unit_scale(xp: Any, w: Any, x: Any, y: Any, z: Any) -> tuple[Any, Any]:
    """The largest component of a quaternion (1 for the zero quaternion) and whether it is not the zero
    quaternion: the divisor and the mask of :func:`_unit_components`."""
    big = xp.maximum(xp.maximum(xp.abs(w), xp.abs(x)), xp.maximum(xp.abs(y), xp.abs(z)))
    # "not zero", not "> 0": a NaN row must count as non-zero, so that the NaN reaches the scale and
    # with it every entry of the row (NONFINITE_BY_ARITHMETIC), not only those that read it. Every
    # other quaternion, subnormal components included, is divided to a largest component of 1, the
    # eager form's test too (quaternion_to_matrix_eager): one rule on every path.
    nonzero = ~(big == 0)
    return xp.where(nonzero, big, 1.0), nonzero


def _inverse_norm(xp: Any, nonzero: Any, s2: Any) -> Any:
    """``1 / sqrt(s2)``, and 0 for the zero quaternion; the discarded branch sees 1, so that neither
    the value nor its derivative is infinite there."""
    return xp.where(nonzero, 1.0 / xp.sqrt(xp.where(nonzero, s2, 1.0)), 0.0)


def quaternion_to_matrix_cotangent(xp: Any, q: Any, grad: Any, *, scalar_first: bool = True) -> Any:
    """Reverse-mode derivative of :func:`quaternion_to_matrix`: ``dL/dq`` (..., 4) for ``dL/dR``
    (..., 3, 3), both quaternions in the storage order ``scalar_first``; analytic, for eager backends
    that would otherwise record and replay the formula's ~40 operations.

    With ``u = q / |q|``, ``R = I + 2 A(u)`` for the quadratic form ``A`` of :func:`quaternion_to_matrix`,
    so ``G . R = tr G + 2 u^T M u`` with ``M`` the symmetric 4 x 4 matrix linear in ``G`` below, and
    ``g = 2 M u`` is its gradient in ``u``. The normalisation projects out the radial part:
    ``dL/dq = (2 / |q|) (g - (u . g) u)``, 0 for the zero quaternion (``1 / |q|`` taken as 0)."""
    w, x, y, z, inv = _unit_components(xp, q, scalar_first)
    g00, g01, g02 = grad[..., 0, 0], grad[..., 0, 1], grad[..., 0, 2]
    g10, g11, g12 = grad[..., 1, 0], grad[..., 1, 1], grad[..., 1, 2]
    g20, g21, g22 = grad[..., 2, 0], grad[..., 2, 1], grad[..., 2, 2]
    # The entries of 2 M: each off-diagonal product of u (wx, ..., yz) appears in two entries of R, with
    # signs as in the formula; each square in the two diagonal entries that it is subtracted from.
    wx, wy, wz = g21 - g12, g02 - g20, g10 - g01
    xy, xz, yz = g01 + g10, g02 + g20, g12 + g21
    trace = g00 + g11 + g22
    gw = wx * x + wy * y + wz * z
    gx = wx * w + xy * y + xz * z + 2.0 * (g00 - trace) * x
    gy = wy * w + xy * x + yz * z + 2.0 * (g11 - trace) * y
    gz = wz * w + xz * x + yz * y + 2.0 * (g22 - trace) * z
    radial = w * gw + x * gx + y * gy + z * gz
    s = 2.0 * inv
    return join_quaternion(
        xp,
        s * (gw - radial * w),
        s * (gx - radial * x),
        s * (gy - radial * y),
        s * (gz - radial * z),
        scalar_first,
    )


def quaternion_to_matrix_tangent(xp: Any, q: Any, tangent: Any, *, scalar_first: bool = True) -> Any:
    """Forward-mode derivative of :func:`quaternion_to_matrix`: ``dR`` (..., 3, 3) for ``dq`` (..., 4),
    both quaternions in the storage order ``scalar_first``; the transpose of
    :func:`quaternion_to_matrix_cotangent`.

    With ``u = q / |q|``, ``du = (dq - u (u . dq)) / |q|`` (the radial part of ``dq`` leaves the
    rotation unchanged), and each entry ``2 u_a u_b`` of the formula changes by ``2 (du_a u_b + u_a
    du_b)``. The zero quaternion takes ``1 / |q| = 0``, so its tangent is 0, as its gradient is."""
    w, x, y, z, inv = _unit_components(xp, q, scalar_first)
    dw, dx, dy, dz = split_quaternion(tangent, scalar_first)
    radial = w * dw + x * dx + y * dy + z * dz
    dw, dx, dy, dz = (inv * (d - radial * u) for d, u in ((dw, w), (dx, x), (dy, y), (dz, z)))

    def d(a: Any, da: Any, b: Any, db: Any) -> Any:  # the change of 2 a b
        return 2.0 * (da * b + a * db)

    xx, yy, zz = d(x, dx, x, dx), d(y, dy, y, dy), d(z, dz, z, dz)
    xy, xz, yz = d(x, dx, y, dy), d(x, dx, z, dz), d(y, dy, z, dz)
    wx, wy, wz = d(x, dx, w, dw), d(y, dy, w, dw), d(z, dz, w, dw)
    return stack_matrix(
        xp,
        [
            -(yy + zz), xy - wz, xz + wy,
            xy + wz, -(xx + zz), yz - wx,
            xz - wy, yz + wx, -(xx + yy),
        ],
    )  # fmt: skip


# NaN or inf anywhere in the matrix reaches every component: each of the four candidates reads all nine
# entries, and the largest component it is divided by (a NaN-propagating maximum) or its norm is then
# NaN. So the backends add no selection after it (tests/test_values.py checks the rule on every backend).
@nonfinite_by_arithmetic
@canonical
@op(matrix=(3, 3))
def matrix_to_quaternion(xp: Any, matrix: Any, *, scalar_first: bool = True) -> Any:
    """Unit quaternion of a rotation matrix, in canonical sign.

    Args:
        matrix: rotation matrices, shape ``(..., 3, 3)``, column-vector convention. A matrix slightly
            off SO(3) still gives a unit quaternion; any finite 3x3 matrix gives a finite result.
        scalar_first: storage order of the result.

    Returns:
        Unit quaternions, shape ``(..., 4)``, in canonical sign: w > 0, and where w = 0 the first
        non-zero of (x, y, z) is positive (scipy's ``as_quat(canonical=True)``).

    Method: the four "pivots" ``t_k = 4 q_k^2`` are read off the diagonal, and the candidate
    ``c_k = 4 q_k q`` is built from sums and differences of entries for the largest pivot only; the
    result is ``c_k / |c_k|``. The pivots sum to 4 for *every* 3x3 matrix, so the largest is at least 1
    and the normalisation never divides by a small number; there is no square root of a pivot at all,
    so half-turns (where three pivots vanish) are as accurate and as smooth as any other rotation.
    Every finite matrix gives a finite unit quaternion: the candidate is built from a quarter of the
    matrix (sums of four quarters cannot overflow) and divided by its largest component before its
    norm is taken (squares of components above ~1.8e19 overflow float32).
    """
    pivots, candidates = _m2q_candidates(_quarter(xp, matrix), 0.25)
    return join_quaternion(xp, *_m2q_unit(xp, *_m2q_select(xp, pivots, candidates)), scalar_first)


def _quarter(xp: Any, matrix: Any) -> Any:
    """A quarter of the matrix, exactly (a power of two), so that the pivots and candidates built from
    it (sums of at most four quarters, ``c_k / 4``) cannot overflow for any finite matrix. The choice of
    pivot is unchanged (the same comparisons of exactly scaled numbers), and so is ``c / |c|``."""
    return matrix * 0.25


def _m2q_unit(xp: Any, w: Any, x: Any, y: Any, z: Any) -> tuple[Any, Any, Any, Any]:
    """``+-c / |c|`` in canonical sign for the selected candidate ``c``, its components divided by the
    largest of them first: their squares would overflow (float32 from ~1.8e19 on, float64 from
    ~1.3e154) and ``1 / |c|`` become 0. The largest component is at least the chosen pivot (a quarter
    of one at least), so the divisions are safe, and the scaled norm lies in [1, 2]. Divisions, not a
    multiplication by ``1 / big``: for a component near the largest finite number that reciprocal is
    subnormal, which XLA and GPUs flush to zero."""
    big = xp.maximum(xp.maximum(xp.abs(w), xp.abs(x)), xp.maximum(xp.abs(y), xp.abs(z)))
    w, x, y, z = w / big, x / big, y / big, z / big
    inv = _m2q_scale(xp, w, x, y, z)
    return w * inv, x * inv, y * inv, z * inv


def _m2q_pivots(matrix: Any, one: Any) -> tuple[Any, Any, Any, Any]:
    """The pivots ``t_k = 4 q_k^2`` of a matrix, from its diagonal. ``one`` is their constant: 1 for a
    matrix, 0 for a tangent (the map is affine)."""
    m00, m11, m22 = matrix[..., 0, 0], matrix[..., 1, 1], matrix[..., 2, 2]
    return (
        one + m00 + m11 + m22,
        one + m00 - m11 - m22,
        one - m00 + m11 - m22,
        one - m00 - m11 + m22,
    )


def _m2q_candidates(matrix: Any, one: Any) -> tuple[tuple[Any, ...], list[tuple[Any, Any, Any, Any]]]:
    """The pivots ``t_k = 4 q_k^2`` and the candidates ``c_k = 4 q_k q`` (w, x, y, z) of a matrix.

    ``one`` is the constant of the pivots: 1 for a matrix, 0 for a tangent (the map is affine)."""
    m01, m02 = matrix[..., 0, 1], matrix[..., 0, 2]
    m10, m12 = matrix[..., 1, 0], matrix[..., 1, 2]
    m20, m21 = matrix[..., 2, 0], matrix[..., 2, 1]
    t0, t1, t2, t3 = _m2q_pivots(matrix, one)
    # 4 q_i q_j for i != j, each from two entries.
    wx, wy, wz = m21 - m12, m02 - m20, m10 - m01
    xy, xz, yz = m01 + m10, m02 + m20, m12 + m21
    candidates = [(t0, wx, wy, wz), (wx, t1, xy, xz), (wy, xy, t2, yz), (wz, xz, yz, t3)]
    return (t0, t1, t2, t3), candidates


def _m2q_choice(xp: Any, pivots: tuple[Any, ...]) -> tuple[Any, Any, Any]:
    """The largest pivot as a two-level choice: between pivots (0, 1) and (2, 3), then within the
    pair; ties go to the lower index. The eager form (:func:`matrix_to_quaternion_eager`) sums the
    same pivots elementwise in the same order and takes their ``argmax``: the same choice, to the bit,
    at every tie."""
    t0, t1, t2, t3 = pivots
    return xp.maximum(t0, t1) >= xp.maximum(t2, t3), t0 >= t1, t2 >= t3


def _m2q_select(
    xp: Any, pivots: tuple[Any, ...], candidates: list[tuple[Any, Any, Any, Any]]
) -> tuple[Any, Any, Any, Any]:
    """Components (w, x, y, z) of the candidate of the largest pivot. Every candidate is finite, so
    the selection is safe for reverse mode, and it happens before the one division."""
    use01, use0, use2 = _m2q_choice(xp, pivots)

    def pick(i: int) -> Any:
        return _m2q_pick(xp, use01, use0, use2, *(candidate[i] for candidate in candidates))

    return pick(0), pick(1), pick(2), pick(3)


def _m2q_pick(xp: Any, use01: Any, use0: Any, use2: Any, v0: Any, v1: Any, v2: Any, v3: Any) -> Any:
    """``v_k`` for the pivot ``k`` chosen by :func:`_m2q_choice` (whose results these are)."""
    return xp.where(use01, xp.where(use0, v0, v1), xp.where(use2, v2, v3))


def _m2q_scale(xp: Any, w: Any, x: Any, y: Any, z: Any) -> Any:
    """``+-1 / |c|`` for a candidate ``c`` already divided by its largest component (so ``|c|`` lies in
    [1, 2] and the division is safe), the sign folded in to make ``c / |c|`` canonical."""
    inv = 1.0 / xp.sqrt(w * w + x * x + y * y + z * z)
    return xp.where(_negative_canonical(w, x, y, z), -inv, inv)


def _m2q_recover_scale(xp: Any, matrix: Any, q: Any) -> tuple[Any, Any, Any, Any]:
    """The choice of :func:`_m2q_choice` and the scale ``+-1 / |c|`` of :func:`_m2q_scale`, read back
    from the result ``q`` (scalar first) instead of rebuilding and renormalising the candidates:
    component k of candidate k is the pivot ``t_k`` itself, so ``q_k = t_k (+-1 / |c|)``. The pivot is
    selected before the division, and the largest pivot is at least 1. It is the chosen pivot, picked
    as the components are, not the maximum of the four: the derivative of a maximum splits between
    tied pivots (half-turns about a diagonal tie three), which made the second derivative wrong there."""
    pivots = _m2q_pivots(matrix, 1.0)
    use01, use0, use2 = _m2q_choice(xp, pivots)
    chosen = functools.partial(_m2q_pick, xp, use01, use0, use2)
    return use01, use0, use2, chosen(*split_quaternion(q, True)) / chosen(*pivots)


class _Unstacked:
    """The nine entries of a ``(..., 3, 3)`` array, taken apart with the array API's ``unstack`` (into
    rows, then each row into entries) and indexed as the array is (``m[..., a, b]``)."""

    def __init__(self, xp: Any, matrix: Any) -> None:
        self._rows = [xp.unstack(row, axis=-1) for row in xp.unstack(matrix, axis=-2)]

    def __getitem__(self, index: tuple[Any, int, int]) -> Any:
        _, a, b = index
        return self._rows[a][b]


def _tangent_entries(xp: Any, tangent: Any) -> Any:
    """A tangent matrix as a forward-mode rule reads it (``t[..., a, b]``), for jax to transpose.

    The transpose of reading one entry (a slice) is a zero-padded copy of the whole ``(..., 3, 3)``
    cotangent, so nine entries read become nine padded copies summed, which XLA:CPU evaluates entry by
    entry, all nine expressions for each of the nine outputs. The transpose of an ``unstack`` is a
    ``stack``; rows of three, then three rows, because XLA:CPU fuses a stack of at most eight operands
    into the loop that computes them, and nine flat entries would become nine loops and a copy
    (docs/performance.md, Formula shapes). Only where the namespace has ``unstack`` (jax; numpy >= 2.1
    reads the same values); the torch rule is never transposed, and the primal matrix is read by
    indexing, which is faster forward."""
    return _Unstacked(xp, tangent) if hasattr(xp, "unstack") else tangent


def matrix_to_quaternion_tangent(
    xp: Any, matrix: Any, q: Any, tangent: Any, *, scalar_first: bool = True
) -> Any:
    """Forward-mode derivative of :func:`matrix_to_quaternion`: ``dq`` for ``dR``, with ``q`` (the
    result) and ``dq`` in the storage order ``scalar_first``; the transpose of
    :func:`matrix_to_quaternion_cotangent`, and like it, it reads the choice and the scale back from
    ``q`` (:func:`_m2q_recover_scale`).

    ``q = +-c / |c|`` for the selected candidate ``c``, which is affine in the matrix, so
    ``dq = +-(dc - q (q . dc)) / |c|`` with ``dc`` the same candidate of the tangent: only the selected
    candidate is differentiated, where autodiff of the formula carries all four through the selection."""
    first = q if scalar_first else xyzw_to_wxyz(xp, q)
    use01, use0, use2, inv = _m2q_recover_scale(xp, matrix, first)
    _, tangents = _m2q_candidates(_tangent_entries(xp, tangent), 0.0)
    pick = functools.partial(_m2q_pick, xp, use01, use0, use2)
    w, x, y, z = (pick(*(t[i] for t in tangents)) for i in range(4))
    dc = join_quaternion(xp, w, x, y, z, scalar_first)
    return inv[..., None] * (dc - q * xp.sum(q * dc, axis=-1, keepdims=True))


def matrix_to_quaternion_cotangent(
    xp: Any, matrix: Any, q: Any, grad: Any, *, scalar_first: bool = True
) -> Any:
    """Reverse-mode derivative of :func:`matrix_to_quaternion`: ``dL/dR`` (..., 3, 3) for ``dL/dq``
    (..., 4), with ``q`` (the result) and ``dL/dq`` in the storage order ``scalar_first``; the
    transpose of :func:`matrix_to_quaternion_tangent`.

    The cotangent of the selected candidate, ``+-(g - q (q . g)) / |c|``, goes to that candidate only;
    each of its components is a pivot or one of the six sums and differences of off-diagonal entries,
    and those send it on to the matrix entries they are made of."""
    if not scalar_first:
        q, grad = xyzw_to_wxyz(xp, q), xyzw_to_wxyz(xp, grad)
    use01, use0, use2, inv = _m2q_recover_scale(xp, matrix, q)
    gc = inv[..., None] * (grad - q * xp.sum(q * grad, axis=-1, keepdims=True))
    gw, gx, gy, gz = split_quaternion(gc, True)
    chosen = (use01 & use0, use01 & ~use0, ~use01 & use2, ~use01 & ~use2)

    def to(k: int, g: Any) -> Any:
        return xp.where(chosen[k], g, 0.0)

    # Candidate k is (c_k0, ..., c_k3) = row k of the symmetric K (see _m2q_candidates): entry (a, b)
    # of K receives the cotangent where row a or row b was chosen.
    tw, tx, ty, tz = to(0, gw), to(1, gx), to(2, gy), to(3, gz)
    wx, wy, wz = to(0, gx) + to(1, gw), to(0, gy) + to(2, gw), to(0, gz) + to(3, gw)
    xy, xz, yz = to(1, gy) + to(2, gx), to(1, gz) + to(3, gx), to(2, gz) + to(3, gy)
    return stack_matrix(
        xp,
        [
            tw + tx - ty - tz, xy - wz, wy + xz,
            wz + xy, tw - tx + ty - tz, yz - wx,
            xz - wy, wx + yz, tw - tx - ty + tz,
        ],
    )  # fmt: skip


@op(q=(4,))
def standardize_quaternion(xp: Any, q: Any, *, scalar_first: bool = True) -> Any:
    """The same rotation in canonical sign: ``q`` or ``-q``, whichever has w > 0, and where w = 0, the
    one whose first non-zero of (x, y, z) is positive (scipy's ``as_quat(canonical=True)``).

    Args:
        q: quaternions, shape ``(..., 4)``, any norm (the norm is kept).
        scalar_first: storage order of ``q`` and of the result.

    Returns:
        Shape ``(..., 4)``. The gradient is +1 or -1 times the identity, by the sign chosen.
    """
    w, x, y, z = split_quaternion(q, scalar_first)
    flip = _negative_canonical(w, x, y, z)
    return xp.where(flip[..., None], -q, q)


@op(q=(4,))
def normalize_quaternion(xp: Any, q: Any, *, scalar_first: bool = True) -> Any:
    """``q / |q|``; the zero quaternion gives the identity quaternion.

    Args:
        q: quaternions, shape ``(..., 4)``. A quaternion whose squared norm is below the smallest
            normal number of the compute dtype counts as zero and gives the identity, with a finite
            (zero) gradient.
        scalar_first: storage order of ``q`` and of the result.

    Returns:
        Unit quaternions, shape ``(..., 4)``, the sign of ``q`` kept.
    """
    w, x, y, z = split_quaternion(q, scalar_first)
    n2 = w * w + x * x + y * y + z * z
    nonzero = n2 >= xp.finfo(n2.dtype).tiny
    # Double where: the discarded branch sees n2 = 1, so 1/sqrt and its derivative stay finite at 0.
    inv = xp.where(nonzero, 1.0 / xp.sqrt(xp.where(nonzero, n2, 1.0)), 0.0)
    return join_quaternion(xp, xp.where(nonzero, w * inv, 1.0), x * inv, y * inv, z * inv, scalar_first)


@op(q=(4,))
def wxyz_to_xyzw(xp: Any, q: Any) -> Any:
    """Reorder scalar-first quaternions (w, x, y, z) to scalar-last (x, y, z, w); shape ``(..., 4)``."""
    return xp.stack([q[..., 1], q[..., 2], q[..., 3], q[..., 0]], axis=-1)


@op(q=(4,))
def xyzw_to_wxyz(xp: Any, q: Any) -> Any:
    """Reorder scalar-last quaternions (x, y, z, w) to scalar-first (w, x, y, z); shape ``(..., 4)``."""
    return xp.stack([q[..., 3], q[..., 0], q[..., 1], q[..., 2]], axis=-1)


# Eager forms of the reorderings, standardisation and normalisation (see "Eager forms" below): the
# same values bit for bit (a roll moves the very numbers; a product with +-1 is exact).


def wxyz_to_xyzw_eager(xp: Any, q: Any) -> Any:
    """:func:`wxyz_to_xyzw`, eager form: one ``roll``."""
    return xp.roll(q, -1, -1)


def xyzw_to_wxyz_eager(xp: Any, q: Any) -> Any:
    """:func:`xyzw_to_wxyz`, eager form: one ``roll``."""
    return xp.roll(q, 1, -1)


def _sign_weights() -> tuple[Any, ...]:
    # the first non-zero component decides the canonical sign: weights 8, 4, 2, 1 from w to z (each
    # exceeds the sum of those after it), in either storage order; 1; and the zero column of the
    # non-finite rows
    return [[8.0], [4.0], [2.0], [1.0]], [[4.0], [2.0], [1.0], [8.0]], 1.0, [[0.0], [0.0], [0.0], [0.0]]


def standardize_quaternion_eager(xp: Any, q: Any, *, scalar_first: bool = True) -> Any:
    """:func:`standardize_quaternion`, eager form, in five operations: ``q`` times the sign of ``sgn(q) .
    (8, 4, 2, 1)`` (``copysign(1, .)``: +1 for the zero quaternion, whose sum is +0, as the componentwise
    form keeps it), a constant of differentiation, so the gradient is +-1 times the identity as there.
    The sums are of small integers, exact in any order. The non-finite rows by arithmetic
    (NONFINITE_BY_ARITHMETIC, registered under this form's name): ``q . 0`` is 0 for a finite row and
    NaN for one with a NaN or an infinity (``0 * inf``, ``0 * NaN`` in the matrix product), added to the
    result by the same ``addcmul`` that multiplies by the sign (a zero component comes out +0 where the
    componentwise form may give -0: equal values)."""
    first, last, one, zeros = constants(xp, q, _sign_weights)
    fixed = cancelling_factor(xp, q)
    signs = xp.sgn(fixed) @ (first if scalar_first else last)
    return xp.addcmul(fixed @ zeros, q, xp.copysign(one, signs))


def _normalize_constants() -> tuple[Any, ...]:
    return [1.0, 0.0, 0.0, 0.0], 0.0, float("inf")


def normalize_quaternion_eager(xp: Any, q: Any, *, scalar_first: bool = True) -> Any:
    """:func:`normalize_quaternion`, eager form, in six operations: ``q / |q|`` with the norm from
    ``linalg.vector_norm``; the zero quaternion (``|q| < sqrt(tiny)``, i.e. squared norm below the
    smallest normal number: the square root of a power of 4 is exact) the identity, and divided by inf
    in the branch thrown away (to 0: finite, with a zero gradient). The non-finite rows by arithmetic
    (NONFINITE_BY_ARITHMETIC, registered under this form's name): the divisor is ``|q| + 0 |q|`` (the
    second term a constant of differentiation), NaN where ``|q|`` is inf or NaN, so every component of
    such a row is NaN (``q / |q|`` alone leaves 0 in the finite components beside an infinity); so is
    a row whose norm overflows (``|q| > ~1.8e19`` in float32), which the componentwise form returns as 0.
    Composites call the componentwise form, and the backend's rule after it (see
    :func:`normalize_quaternion`)."""
    if not scalar_first:  # one order of summation in the norm, so both orders agree bit for bit
        q = xp.roll(q, 1, -1)
    identity, zero, inf = constants(xp, q, _normalize_constants)
    norm = xp.linalg.vector_norm(q, 2, -1, True)
    small = norm < float(xp.finfo(q.dtype).tiny) ** 0.5
    divisor = xp.where(small, inf, xp.addcmul(norm, cancelling_factor(xp, norm), zero))
    out = xp.where(small, identity, q / divisor)
    return out if scalar_first else xp.roll(out, -1, -1)


@canonical
@op(uniform=(3,))
def quaternions_from_uniform(xp: Any, uniform: Any, *, scalar_first: bool = True) -> Any:
    """Shoemake's map from three uniform [0, 1) numbers to a uniformly distributed unit quaternion, in
    canonical sign. Shape ``(..., 3)`` to ``(..., 4)``. The random draw itself is the backend's."""
    u1, u2, u3 = uniform[..., 0], uniform[..., 1], uniform[..., 2]
    r1, r2 = xp.sqrt(1.0 - u1), xp.sqrt(u1)
    a, b = 2.0 * xp.pi * u2, 2.0 * xp.pi * u3
    w, x, y, z = r2 * xp.cos(b), r1 * xp.sin(a), r1 * xp.cos(a), r2 * xp.sin(b)
    q = join_quaternion(xp, w, x, y, z, scalar_first)
    return standardize_quaternion(xp, q, scalar_first=scalar_first)


Rule = tuple[Callable[..., Any], Callable[..., Any], Callable[..., Any]]
# (prepare, forward, tangent, cotangent, finish): see :func:`eager_rules`
EagerRule = tuple[Callable[..., Any], ...]


def registered_conversions(
    register: Callable[[str, Rule, EagerRule | None], Conversion],
) -> dict[str, Conversion]:
    """``quaternion_to_matrix`` and ``matrix_to_quaternion`` as a backend evaluates them, by name, each
    ``(xp, x, *, scalar_first=True)``: ``register(name, rule, eager)`` turns one storage order's
    :func:`derivative_rules` (and its :func:`eager_rules`, where the map has an eager form, else None)
    into a function ``(xp, x)`` (torch: an ``autograd.Function``, jax: a ``custom_jvp``, numpy: the
    forward itself). Every backend binds its public conversions and the
    conversion step of every composite to these, so all of them reach a conversion the same way."""
    rules = {order: derivative_rules(order) for order in (True, False)}
    eager = {order: eager_rules(order) for order in (True, False)}
    out: dict[str, Conversion] = {}
    for name in ("quaternion_to_matrix", "matrix_to_quaternion"):
        by_order = {order: register(name, rules[order][name], eager[order].get(name)) for order in rules}

        def conversion(xp: Any, x: Any, *, scalar_first: bool = True, _by_order: Any = by_order) -> Any:
            return _by_order[bool(scalar_first)](xp, x)

        conversion.__name__ = name  # the backends validate arguments by the core function's name
        out[name] = conversion
    return out


def derivative_rules(scalar_first: bool) -> dict[str, Rule]:
    """The two conversions with their derivatives written out, in one storage order, as each backend
    registers them (torch: an ``autograd.Function``; jax: a ``custom_jvp``): ``forward(xp, x)``,
    ``tangent(xp, x, y, dx)`` and ``cotangent(xp, x, y, gy)``, ``y`` being the forward's result.

    Why the rules: autodiff of :func:`matrix_to_quaternion` carries all four candidates through the
    selection, twice the work of differentiating the chosen one, and eager torch records and replays
    :func:`quaternion_to_matrix`'s ~40 operations where its cotangent is ~25 (docs/performance.md)."""

    def q2m(xp: Any, q: Any) -> Any:
        return quaternion_to_matrix(xp, q, scalar_first=scalar_first)

    def q2m_tangent(xp: Any, q: Any, r: Any, dq: Any) -> Any:
        return quaternion_to_matrix_tangent(xp, q, dq, scalar_first=scalar_first)

    def q2m_cotangent(xp: Any, q: Any, r: Any, grad: Any) -> Any:
        return quaternion_to_matrix_cotangent(xp, q, grad, scalar_first=scalar_first)

    def m2q(xp: Any, matrix: Any) -> Any:
        return matrix_to_quaternion(xp, matrix, scalar_first=scalar_first)

    def m2q_tangent(xp: Any, matrix: Any, q: Any, dm: Any) -> Any:
        return matrix_to_quaternion_tangent(xp, matrix, q, dm, scalar_first=scalar_first)

    def m2q_cotangent(xp: Any, matrix: Any, q: Any, grad: Any) -> Any:
        return matrix_to_quaternion_cotangent(xp, matrix, q, grad, scalar_first=scalar_first)

    # the backends validate arguments by the core function's name
    q2m.__name__, m2q.__name__ = "quaternion_to_matrix", "matrix_to_quaternion"
    return {
        "quaternion_to_matrix": (q2m, q2m_tangent, q2m_cotangent),
        "matrix_to_quaternion": (m2q, m2q_tangent, m2q_cotangent),
    }


# ---------------------------------------------------------------------------------------------------
# Eager forms. Eager torch pays per ATen operation (a dispatch on the CPU, a kernel launch on a GPU),
# not per flop: the forms below compute the same maps as the componentwise formulas above in a handful
# of vectorised operations over the (..., 4) and (..., 3, 3) axes (products with constant coefficient
# matrices, one reduction, one division). They take torch's signatures (``torch.linalg.vector_norm``,
# ``addmm``, ``clamp_min``); the compilers (inductor, XLA) and NumPy keep the componentwise formulas,
# which fuse. ``diffquat.torch._custom`` chooses between the two, in the one place that decides eager
# against capture; the test table runs every row through both.
# ---------------------------------------------------------------------------------------------------

# Eager forms of maps whose derivative autodiff takes (no written-out rule), by the name of the
# componentwise core function they stand beside: ``eager_form(of=...)`` registers one, and the torch
# backend's Backend calls it in place of the componentwise function outside graph capture
# (``diffquat.torch._custom.chosen``).
EAGER_FORMS: dict[str, Callable[..., Any]] = {}


def eager_form(of: Callable[..., Any]) -> Callable[[F], F]:
    """Register the decorated function as the eager form of the core function ``of``: the same
    signature, the same map to rounding, few vectorised operations."""

    def register(fn: F) -> F:
        EAGER_FORMS[of.__name__] = fn
        return fn

    return register


# the eager forms written beside their componentwise functions, above this registry
for _of, _form in (
    (wxyz_to_xyzw, wxyz_to_xyzw_eager),
    (xyzw_to_wxyz, xyzw_to_wxyz_eager),
    (standardize_quaternion, standardize_quaternion_eager),
    (normalize_quaternion, normalize_quaternion_eager),
):
    eager_form(of=_of)(_form)
# the two whose arithmetic makes non-finite rows NaN (by the eager form's name: the backend checks the
# function it ran; their componentwise forms keep the backend's rule)
nonfinite_by_arithmetic(standardize_quaternion_eager)
nonfinite_by_arithmetic(normalize_quaternion_eager)


_CONSTANTS: dict[tuple[Any, ...], Any] = {}


def constants(xp: Any, like: Any, make: Callable[[], tuple[Any, ...]]) -> tuple[Any, ...]:
    """The constant arrays ``make()`` (nested lists, or numbers: 0-d arrays) in ``like``'s dtype and
    device, made once per map, dtype and device: making one on every call is an operation (a
    host-to-device copy on a GPU), and a map's forward makes all of them, those its rules read
    included, so that no backward pass makes one either."""
    key = (make, like.dtype, like.device)
    # only for a plain tensor: a tracer's (make_fx's FakeTensor, a FunctionalTensor) would be cached
    # and handed to later eager calls, which then return fake tensors
    if type(like) is not getattr(xp, "Tensor", type(like)):
        return tuple(xp.tensor(rows, dtype=_dtype(xp, rows, like), device=like.device) for rows in make())
    value = _CONSTANTS.get(key)
    if value is None:
        value = tuple(xp.tensor(rows, dtype=_dtype(xp, rows, like), device=like.device) for rows in make())
        # Not kept when made inside a torch.func transform (grad, vjp, jacrev: a rule's second
        # derivative): there torch.tensor returns a tensor wrapped at the transform's level, which a
        # later call would meet outside it ("level <= current_level INTERNAL ASSERT FAILED").
        if not _wrapped(xp, value[0]):
            _CONSTANTS[key] = value
    return value


def _wrapped(xp: Any, x: Any) -> bool:
    """Whether ``x`` is a tensor of a torch.func transform's level (torch only)."""
    functorch = getattr(getattr(xp, "_C", None), "_functorch", None)
    return functorch is not None and bool(functorch.is_functorch_wrapped_tensor(x))


def _dtype(xp: Any, rows: Any, like: Any) -> Any:
    """A constant's dtype by its first entry: Python ints make an index table (int64), complex numbers
    ``like``'s complex counterpart (the Fisher normaliser's contour nodes), floats ``like``'s dtype."""
    first = rows
    while isinstance(first, list):
        first = first[0]
    if isinstance(first, int):
        return xp.int64
    if isinstance(first, complex):
        return like.dtype.to_complex()
    return like.dtype


def _quadratic_forms() -> list[list[float]]:
    """(16, 10): row ``4 i + j`` holds the coefficients of ``u_i u_j`` (symmetrised; u scalar first) in
    the nine entries of ``P(u) = |u|^2 R(u / |u|)`` (row-major, Kuipers' matrix) and, in the tenth
    column, ``|u|^2``."""
    w, x, y, z = 0, 1, 2, 3
    entries = [
        [(w, w, 1), (x, x, 1), (y, y, -1), (z, z, -1)], [(x, y, 2), (w, z, -2)], [(x, z, 2), (w, y, 2)],
        [(x, y, 2), (w, z, 2)], [(w, w, 1), (x, x, -1), (y, y, 1), (z, z, -1)], [(y, z, 2), (w, x, -2)],
        [(x, z, 2), (w, y, -2)], [(y, z, 2), (w, x, 2)], [(w, w, 1), (x, x, -1), (y, y, -1), (z, z, 1)],
        [(w, w, 1), (x, x, 1), (y, y, 1), (z, z, 1)],
    ]  # fmt: skip
    c = [[0.0] * 10 for _ in range(16)]
    for k, terms in enumerate(entries):
        for i, j, v in terms:
            c[4 * i + j][k] += v / 2
            c[4 * j + i][k] += v / 2
    return c


def largest_magnitude(xp: Any, x: Any) -> Any:
    """``max_i |x_i|`` over the last axis (keepdims), eager torch: ``abs`` and ``amax``, two operations
    where ``vector_norm(x, inf)`` is one, because that kernel reduces a short last axis without
    vectorising it: 17 ms against 0.6 ms for ``abs().amax()`` at (262144, 4) on the 2-core CPU, slower
    from N = 64 on (docs/performance.md). NaN propagates (``amax`` does), as it did."""
    return x.abs().amax(-1, keepdim=True)


def unit_scale(xp: Any, q: Any) -> Any:
    """``q / max(max_i |q_i|, tiny)``: components in [-1, 1], the largest of magnitude 1, so the squared
    norm lies in [1, 4] (the zero quaternion stays 0). The scale is a constant of differentiation: the
    maps it feeds are invariant to it (:func:`cancelling_factor`). Four operations eager."""
    big = largest_magnitude(xp, cancelling_factor(xp, q)).clamp_min(xp.finfo(q.dtype).tiny)
    return q / big


def quaternion_to_matrix_eager(xp: Any, u: Any) -> tuple[Any, Any]:
    """:func:`quaternion_to_matrix` of ``u`` = :func:`unit_scale` of q, eager form: ``(R9, n)``, the nine
    entries ``(B, 9)`` (``B`` the flattened batch) and ``n = |u|^2`` ``(B, 1)``.

    ``R = P(u) / |u|^2`` with ``P`` the quadratic forms of :func:`_quadratic_forms`: the outer product
    ``u u^T`` contracted with the constant (16, 10) matrix, whose tenth column is ``|u|^2`` itself, and a
    bias of ``tiny`` on the diagonal and the norm, so that the zero quaternion gives ``tiny I / tiny =
    I`` exactly (the documented identity). For every other ``u``, ``|u|^2 >= 1``: the bias changes an
    entry by at most ``tiny`` (1.2e-38 in float32), below the rounding of any entry of size 1. A NaN or
    an infinity in ``q`` makes ``n`` NaN, and with it every entry (NONFINITE_BY_ARITHMETIC). Seven
    operations: two views, the product, a view, ``addmm``, one split, the division."""
    c, _, bias = constants(xp, u, _q2m_constants)
    p = xp.addmm(bias, (u[..., :, None] * u[..., None, :]).reshape(-1, 16), c)
    r, n = p.split([9, 1], 1)  # one operation for both views, where two slices are two
    return r / n, n


def quaternion_to_matrix_eager_cotangent(
    xp: Any, u: Any, r: Any, n: Any, g: Any | None, gn: Any | None
) -> Any:
    """Reverse mode of :func:`quaternion_to_matrix_eager`: ``dL/du`` for ``g = dL/dR9`` ``(B, 9)`` and
    ``gn = dL/dn`` (None where not asked for; a second derivative asks for it).

    ``R_k = P_k(u) / n`` with ``P_k = u^T C_k u`` and ``n = u^T u``:
    ``dL/du = (2 / n) (sum_k g_k C_k - (g . R) I) u``, the bracket one product of ``[g, g . R]`` with
    the transposed coefficients (the norm's column negated, the factor 2 folded in), then one
    contraction with ``u``. It is orthogonal to ``u`` (the map is scale invariant). ``n``'s own
    cotangent adds ``2 gn u``.

    The zero quaternion (``n`` the bias alone, every other ``n`` at least ~1e-14) takes a zero
    cotangent by a selection, not by its arithmetic (``M 0 / tiny``): so its derivative is zero too,
    where ``M / tiny`` met the scale's ``1 / tiny`` and gave a second derivative of inf * 0."""
    radial = None if gn is None else 2.0 * u * gn.view(*u.shape[:-1], 1)
    if g is None:
        return radial
    _, ct, _ = constants(xp, u, _q2m_constants)
    m = xp.cat([g, (g * r).sum(-1, keepdim=True)], -1) @ ct
    n = n.view(*u.shape[:-1], 1)
    gu = xp.where(n > _TINY32, (m.view(*u.shape, 4) * u[..., None, :]).sum(-1) / n, 0.0)
    return gu if radial is None else gu + radial


def _cotangent_forms() -> list[list[float]]:
    """(10, 16): the transpose of :func:`_quadratic_forms`, times 2, its norm row negated."""
    c = _quadratic_forms()
    return [[(-2.0 if k == 9 else 2.0) * c[i][k] for i in range(16)] for k in range(10)]


# float32's smallest normal number, representable in every compute dtype (float32, float64)
_TINY32 = 1.1754943508222875e-38


def _q2m_constants() -> tuple[list[Any], ...]:
    # the bias: tiny on the diagonal and the norm (the zero quaternion's identity)
    tiny = _TINY32
    bias = [tiny, 0.0, 0.0, 0.0, tiny, 0.0, 0.0, 0.0, tiny, tiny]
    return _quadratic_forms(), _cotangent_forms(), bias


def _batch_matrix(xp: Any, q: Any, r9: Any) -> Any:
    """The eager form's ``(B, 9)`` entries as ``(..., 3, 3)`` in the batch shape of ``q``."""
    return r9.view(*q.shape[:-1], 3, 3)


# columns of matrix_to_quaternion_eager's product: the pivots, then the six off-diagonal sums; and the
# columns of the candidate (w, x, y, z) of pivot k: row k of the symmetric K
_OFF = range(4, 10)
_K_ROWS = ((0, 4, 5, 6), (4, 1, 7, 8), (5, 7, 2, 9), (6, 8, 9, 3))


def _m2q_forms() -> tuple[Any, ...]:
    """The constants of :func:`matrix_to_quaternion_eager`: ``(A, bias, pivot_signs, rows, signs,
    At)``. ``A`` (9, 10) maps the row-major entries to a quarter of the pivots (with ``bias``) and of
    the off-diagonal sums of :func:`_m2q_candidates`; ``pivot_signs`` (4, 3) are the signed quarters of
    the diagonal in each pivot (:func:`_m2q_pivots`); ``rows`` (4, 4) the columns of the candidate of each
    pivot (w, x, y, z); ``signs`` weighs the candidate's signs so that the first non-zero component
    decides the canonical sign (8, 4, 2, 1); ``At`` (10, 9) is the transpose of ``A``."""
    a = [[0.0] * 10 for _ in range(9)]
    diagonal = (0, 4, 8)
    pivot_signs = [[0.25, 0.25, 0.25], [0.25, -0.25, -0.25], [-0.25, 0.25, -0.25], [-0.25, -0.25, 0.25]]
    for k, signs in enumerate(pivot_signs):
        for entry, sign in zip(diagonal, signs, strict=True):
            a[entry][k] = sign
    # wx = m21 - m12, wy = m02 - m20, wz = m10 - m01, xy = m01 + m10, xz = m02 + m20, yz = m12 + m21
    for column, (i, j, sign) in zip(
        _OFF, ((7, 5, -1), (2, 6, -1), (3, 1, -1), (1, 3, 1), (2, 6, 1), (5, 7, 1)), strict=True
    ):
        a[i][column], a[j][column] = 0.25, 0.25 * sign
    transposed = [[a[i][j] for i in range(9)] for j in range(10)]
    bias = [0.25] * 4 + [0.0] * 6
    rows = [list(row) for row in _K_ROWS]
    return a, bias, pivot_signs, rows, [[8.0], [4.0], [2.0], [1.0]], transposed


def matrix_to_quaternion_eager(xp: Any, m: Any) -> tuple[Any, Any, Any]:
    """:func:`matrix_to_quaternion` of the row-major entries ``m`` ``(B, 9)``, eager form: ``(q, cols,
    den)``, the quaternions ``(B, 4)`` scalar first (scalar-last storage is reordered after, so that
    both orders give the same numbers bit for bit), the columns of the chosen candidate and
    ``+-|c|`` ``(B, 1)``, which the rule reuses.

    The pivot is the componentwise form's choice to the bit: its four pivots summed elementwise in its
    order (``((1 +- d0) +- d1) +- d2``), and ``argmax``, which takes the first of tied maxima as the
    two-level choice of :func:`_m2q_choice` does. Not from a matrix product: BLAS sums in an order that
    depends on the batch's layout, so a pivot read from one differed between ``vmap`` and a plain call
    at exact ties. One ``addmm`` gives a quarter of the pivots and of the six off-diagonal sums (the
    candidates' entries, as :func:`_m2q_candidates`); the chosen candidate's columns are gathered; it is
    divided by its largest entry before its norm (no square overflows), and by the norm carrying the
    canonical sign: the sign of the candidate's signs weighed 8, 4, 2, 1, so that the first non-zero
    component decides (never 0: the chosen pivot is positive). A NaN or an infinity in the matrix
    makes every column of the product NaN (``0 * x``), and with them the quaternion."""
    a, bias, pivot_signs, rows, signs, _ = constants(xp, m, _m2q_forms)
    # (B, 4, 3): each pivot's signed diagonal entries, quartered as the componentwise form's (exactly)
    e = m[:, ::4, None].mT * pivot_signs
    cols = rows[(((0.25 + e[..., 0]) + e[..., 1]) + e[..., 2]).argmax(-1)]
    c = xp.addmm(bias, m, a).gather(1, cols)
    big = largest_magnitude(xp, c)
    norm = xp.linalg.vector_norm(c / cancelling_factor(xp, big), 2, -1, True)
    den = norm.copysign(c.sign() @ signs) * big
    return c / den, cols, den


def matrix_to_quaternion_eager_cotangent(
    xp: Any, m: Any, q: Any, cols: Any, den: Any, g: Any | None, gcols: Any, gden: Any | None
) -> Any:
    """Reverse mode of :func:`matrix_to_quaternion_eager`: ``dL/dm`` ``(B, 9)`` for ``g = dL/dq`` and
    ``gden = dL/dden`` (None where not asked for; a second derivative asks for it).

    ``q = c / den`` with ``den = +-|c|``: ``dL/dc = (g - q (q . g)) / den + gden q``, which goes to the
    chosen candidate's columns of the product (a scatter) and through its transposed coefficients to
    the entries."""
    gc = None if g is None else (g - q * (q * g).sum(-1, keepdim=True)) / den
    if gden is not None:
        gc = gden * q if gc is None else gc + gden * q
    if gc is None:
        return None
    *_, transposed = constants(xp, m, _m2q_forms)
    return q.new_zeros(q.shape[0], 10).scatter(1, cols, gc) @ transposed


def eager_rules(scalar_first: bool) -> dict[str, EagerRule]:
    """The eager forms of the conversions in one storage order, as torch registers them beside
    :func:`derivative_rules`: ``(prepare, forward, cotangent, finish)`` with ``u = prepare(xp, x)``
    (plain operations: a range scaling; scalar-last storage reordered, so that the forms compute in
    one order and the two storage orders give the same numbers bit for bit), ``forward(xp, u) -> (y,
    *aux)``, ``cotangent(xp, u, y, *aux, gy, *gaux)`` and the result ``finish(xp, x, y)`` (a view).

    ``matrix_to_quaternion``'s input is the nine entries ``(B, 9)``; its form computes scalar first,
    and scalar-last storage is reordered after (``roll``). Its pivots are summed elementwise, in the
    componentwise order, so every path and every layout of a batch chooses alike at every tie."""

    def q2m_prepare(xp: Any, q: Any) -> Any:
        return unit_scale(xp, q if scalar_first else xp.roll(q, 1, -1))

    def m2q_prepare(xp: Any, matrix: Any) -> Any:
        return matrix.reshape(-1, 9)

    def m2q(xp: Any, m: Any) -> tuple[Any, Any, Any]:
        return matrix_to_quaternion_eager(xp, m)

    def m2q_finish(xp: Any, matrix: Any, q: Any) -> Any:
        return (q if scalar_first else xp.roll(q, -1, -1)).view(*matrix.shape[:-2], 4)

    return {
        "quaternion_to_matrix": (
            q2m_prepare,
            quaternion_to_matrix_eager,
            quaternion_to_matrix_eager_cotangent,
            _batch_matrix,
        ),
        "matrix_to_quaternion": (m2q_prepare, m2q, matrix_to_quaternion_eager_cotangent, m2q_finish),
    }
