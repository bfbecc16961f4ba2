"""Eager fast paths of ``quaternion_to_matrix`` and ``matrix_to_quaternion`` on torch, and the
dispatch between every path (:func:`q2m_path`, :func:`m2q_path`).

On the CPU the eager default is the C kernels of :mod:`._cpu` (one pass each way). The Functions here
are what runs where those do not: under ``torch.func`` transforms (the ``setup_context`` Functions,
which have vmap rules), and where the extension was not built (no C compiler at install time).

Small batches: a ``torch.autograd.Function`` for each whose linear part is one small matrix product
with the constant forms of :mod:`diffquat._fused`: seven operations forward and eight backward for
``quaternion_to_matrix``, instead of autograd recording and replaying the core's ~40 elementwise
operations plus their derivatives, each a few microseconds of dispatch at small N. The backward is
analytic and keeps only small tensors beside the input (1 / |q|^2, or the selected candidate).

Large batches: the "columns" Functions, the core formula forward and its analytic derivative
(``_core.quaternion_to_matrix_cotangent``, ``_core.matrix_to_quaternion_cotangent``) backward, both on
whole columns, with a vectorised selection in place of ``torch.where`` (see ``_EagerTorch``), and
evaluated by blocks of rows (see ``BLOCK_ROWS``).

Every backward is made of differentiable torch operations, so double backward (``gradgradcheck``,
Hessians) differentiates it; ``jvp`` gives forward mode; ``generate_vmap_rule`` gives
``torch.func.vmap`` (and with it ``jacrev``/``jacfwd``).

The functions here compute in scalar-first order; :mod:`diffquat.torch` reorders scalar-last arrays
around them, and calls them only in eager mode: under ``torch.compile`` it traces the plain core
formula instead, so that inductor fuses it with the user's surrounding code.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from typing import Any

import torch
from torch import Tensor

from .. import _core, _fused

# The C kernels, where the extension was built (pyproject.toml builds it wherever a C compiler is).
_cpu: Any
try:
    from .. import _kernels  # noqa: F401
except ImportError:
    _cpu = None
else:
    from . import _cpu


def _padded(rows: list[list[float]], width: int = 16) -> list[list[float]]:
    return [row + [0.0] * (width - len(row)) for row in rows]


def _expansion(index: Callable[[int, int], int]) -> list[list[float]]:
    """(4, 16): column ``4 i + j`` picks component ``index(i, j)`` of a 4-vector."""
    return [[float(index(i, j) == k) for i in range(4) for j in range(4)] for k in range(4)]


_TABLES: dict[str, Any] = {
    "q2m_forms": _fused.Q2M_FORMS,
    "q2m_forms9": [row[:9] for row in _fused.Q2M_FORMS],
    "q2m_forms_sym": _fused.Q2M_FORMS_SYM,
    "q2m_base": _fused.Q2M_BASE,
    "m2q_forms": _fused.M2Q_FORMS,
    "m2q_forms_t": [list(row) for row in zip(*_fused.M2Q_FORMS, strict=True)],
    "m2q_base": _fused.M2Q_BASE,
    "sign_weights": _fused.SIGN_WEIGHTS,
    "components": [0.0, 1.0, 2.0, 3.0],
    "expand_rows": _expansion(lambda i, j: i),
    "expand_cols": _expansion(lambda i, j: j),
}
# MKL's sgemm is ~2.5x faster when the output has 16 columns than 9 or 10 (measured at N = 4096:
# (N, 16) @ (16, 10) 52 us, @ (16, 16) 20 us), so the matmul path uses the forms zero-padded to 16.
for _name in ("q2m_forms", "q2m_forms9", "m2q_forms_t"):
    _TABLES[_name + "/16"] = _padded(_TABLES[_name])
_cache: dict[tuple[str, torch.dtype, torch.device], Tensor] = {}


def _table(name: str, like: Tensor) -> Tensor:
    """A table of :mod:`diffquat._fused` as a tensor of ``like``'s dtype and device, built once per
    dtype and device."""
    key = (name, like.dtype, like.device)
    value = _cache.get(key)
    if value is None:
        value = torch.tensor(_TABLES[name], dtype=like.dtype, device=like.device)
        _cache[key] = value
    return value


def _split(x: Tensor, rows: int, cols: int) -> Tensor:
    """The last dimension of ``x`` as ``(rows, cols)``."""
    return x.reshape(*x.shape[:-1], rows, cols)


# Below this many rows the small contractions with the constant forms are a multiply and a sum, not a
# BLAS matmul: MKL runs even a (64, 16) @ (16, 10) product on its thread pool, whose threads then
# spin-wait, a whole core busy for a while after every call, slowing whatever else runs on the machine
# (a 2-core test run took 4x longer). From ~200 rows on, the multiply's (N, 16, 10) intermediate
# passes ATen's 32768-element grain and goes parallel itself, so the (faster) matmul takes over.
_BLAS_ROWS = 256


def _blas(x: Tensor) -> bool:
    return x.numel() >= _BLAS_ROWS * x.shape[-1]


def _contract(x: Tensor, name: str) -> Tensor:
    """``x @ forms`` for ``x`` (..., k) and the constant table ``name`` (k, m)."""
    forms = _table(name, x)
    if not _blas(x):
        return torch.sum(x[..., :, None] * forms, dim=-2)
    if forms.shape[-1] == 16:
        return x @ forms
    return (x @ _table(name + "/16", x))[..., : forms.shape[-1]]


def _products(a: Tensor, b: Tensor) -> Tensor:
    """The 16 products ``a_i b_j`` (flat, row-major), shape (..., 16). From ``_BLAS_ROWS`` rows on,
    as two matrix products that repeat the components (exact: each output is one component times 1
    plus zeros) and one contiguous multiply: the broadcast multiply's inner loops of 4 are not
    vectorised (78 us at N = 4096, against 22 us)."""
    if _blas(a):
        return (a @ _table("expand_rows", a)) * (b @ _table("expand_cols", b))
    return torch.flatten(a[..., :, None] * b[..., None, :], -2)


def _inverse_square_norm(n2: Tensor) -> Tensor:
    """``1 / |q|^2`` from ``|q|^2`` (..., 1), and 0 (the zero quaternion gives the identity, with a
    zero gradient) below the smallest normal number. The clamp keeps the discarded value and every
    derivative of it finite at ``q = 0`` (double backward differentiates this too)."""
    tiny = torch.finfo(n2.dtype).tiny
    return torch.reciprocal(torch.clamp_min(n2, tiny)).masked_fill(n2 < tiny, 0.0)


def _q2m(q: Tensor) -> tuple[Tensor, Tensor]:
    """``R`` (..., 3, 3) and ``1 / |q|^2`` (..., 1): one outer product, one matrix product with the
    constant forms, one fused multiply-add."""
    forms = _contract(_products(q, q), "q2m_forms")
    s = _inverse_square_norm(forms[..., 9:])
    return _split(torch.addcmul(_table("q2m_base", q), forms[..., :9], s), 3, 3), s


def q2m_backward(q: Tensor, grad: Tensor, s: Tensor | None = None) -> Tensor:
    """``dL/dq`` (scalar first) from ``dL/dR``, in differentiable torch operations; ``s = 1 / |q|^2``
    as :func:`_q2m` returns it, recomputed (differentiably) when not given.

    ``R = I + s A(q)`` with ``A`` quadratic, ``h = H q`` the gradient of ``G . A`` (``H`` from
    ``Q2M_FORMS_SYM``), ``G . A = (q . h) / 2`` and ``ds/dq = -2 s^2 q``, so
    ``dL/dq = s (h - s (q . h) q)``; ``s (q . h)`` is formed first, since for ``|q|`` near 1e15 or
    1e-15 in float32 the dot product alone is at the range limit."""
    if s is None:
        s = _inverse_square_norm(torch.sum(q * q, dim=-1, keepdim=True))
    h = _split(_contract(torch.flatten(grad, -2), "q2m_forms_sym"), 4, 4)
    hq = torch.sum(h * q[..., None, :], dim=-1)
    return s * torch.addcmul(hq, s * torch.sum(q * hq, dim=-1, keepdim=True), q, value=-1.0)


def q2m_jvp(q: Tensor, tangent: Tensor) -> Tensor:
    """``dR`` for ``dq``: ``s (u q^T + q u^T) . F`` with ``u = dq - s (q . dq) q`` (the radial part of
    ``dq``, along ``q``, leaves ``R`` unchanged)."""
    s = _inverse_square_norm(torch.sum(q * q, dim=-1, keepdim=True))
    u = torch.addcmul(tangent, s * torch.sum(q * tangent, dim=-1, keepdim=True), q, value=-1.0)
    d_forms = _contract(_products(u, q) + _products(q, u), "q2m_forms9")
    return _split(s * d_forms, 3, 3)


def select(matrix: Tensor) -> tuple[Tensor, Tensor, Tensor]:
    """The candidate of the largest pivot, its signed inverse norm, and the pivot (..., 1).

    ``argmax`` returns the first maximum, so ties go to the lower index, as in the core. The canonical
    sign is that of the first non-zero component in (w, x, y, z) order, which is the sign of
    ``8 sign(w) + 4 sign(x) + 2 sign(y) + sign(z)`` (each weight exceeds the sum of those after it);
    the pivot's own component (>= 1) guarantees that this is not 0."""
    k = _split(_contract(torch.flatten(matrix, -2), "m2q_forms") + _table("m2q_base", matrix), 4, 4)
    pivot = torch.argmax(torch.diagonal(k, dim1=-2, dim2=-1), dim=-1, keepdim=True)
    c = torch.gather(k, -2, pivot[..., None].expand(*pivot.shape, 4))[..., 0, :]
    leading = torch.sum(torch.sign(c) * _table("sign_weights", matrix), dim=-1)
    norm = torch.rsqrt(torch.sum(c * c, dim=-1, keepdim=True))
    return c, torch.copysign(norm, leading[..., None]), pivot


def m2q_backward(matrix: Tensor, grad: Tensor, c: Tensor, inv: Tensor, pivot: Tensor) -> Tensor:
    """``dL/dmatrix`` from ``dL/dq``: only the selected row of ``K`` receives the cotangent, and
    ``K``'s forms send it back to the matrix entries."""
    grad_c = _fused.normalize_vjp(torch, c * inv, inv, grad)
    rows = (_table("components", matrix) == pivot).to(grad_c.dtype)
    grad_k = _products(rows, grad_c)
    return _split(_contract(grad_k, "m2q_forms_t"), 3, 3)


def m2q_jvp(matrix: Tensor, tangent: Tensor) -> Tensor:
    c, inv, pivot = select(matrix)
    tangent_k = _split(_contract(torch.flatten(tangent, -2), "m2q_forms"), 4, 4)
    tangent_c = torch.gather(tangent_k, -2, pivot[..., None].expand(*pivot.shape, 4))[..., 0, :]
    return _fused.normalize_vjp(torch, c * inv, inv, tangent_c)


# Two Functions for each conversion, with the same formulas. In eager mode (no torch.func transform
# active) the old-style ``forward(ctx, ...)`` one: ``Function.apply`` binds the arguments of a
# ``setup_context`` Function through ``inspect.signature`` on every call, about 20 us, a fifth of the
# whole forward + backward at N = 64. It also keeps what backward needs (small: (..., 1) and (..., 4))
# instead of recomputing it, except under double backward, which needs it as a function of the input.
# Under torch.func the ``setup_context`` one, which ``generate_vmap_rule`` requires.


class QuaternionToMatrix(torch.autograd.Function):
    @staticmethod
    def forward(ctx: Any, q: Tensor) -> Tensor:
        r, s = _q2m(q)
        ctx.save_for_backward(q, s)
        ctx.save_for_forward(q)
        return r

    @staticmethod
    def backward(ctx: Any, grad: Tensor) -> Tensor:
        q, s = ctx.saved_tensors
        return q2m_backward(q, grad, None if torch.is_grad_enabled() else s)

    @staticmethod
    def jvp(ctx: Any, tangent: Tensor) -> Tensor:
        (q,) = ctx.saved_tensors
        return q2m_jvp(q, tangent)


class _SavesInput(torch.autograd.Function):
    """A Function of one tensor that keeps only that tensor for backward and forward mode."""

    generate_vmap_rule = True

    @staticmethod
    def setup_context(ctx: Any, inputs: tuple[Tensor], output: Tensor) -> None:
        ctx.save_for_backward(inputs[0])
        ctx.save_for_forward(inputs[0])


class QuaternionToMatrixTransformable(_SavesInput):
    @staticmethod
    def forward(q: Tensor) -> Tensor:
        return _q2m(q)[0]

    @staticmethod
    def backward(ctx: Any, grad: Tensor) -> Tensor:
        (q,) = ctx.saved_tensors
        return q2m_backward(q, grad)

    @staticmethod
    def jvp(ctx: Any, tangent: Tensor) -> Tensor:
        (q,) = ctx.saved_tensors
        return q2m_jvp(q, tangent)


class MatrixToQuaternion(torch.autograd.Function):
    @staticmethod
    def forward(ctx: Any, matrix: Tensor) -> Tensor:
        c, inv, pivot = select(matrix)
        ctx.save_for_backward(matrix, c, inv, pivot)
        ctx.save_for_forward(matrix)
        return c * inv

    @staticmethod
    def backward(ctx: Any, grad: Tensor) -> Tensor:
        matrix, c, inv, pivot = ctx.saved_tensors
        if torch.is_grad_enabled():  # double backward: c and inv as functions of the matrix
            c, inv, pivot = select(matrix)
        return m2q_backward(matrix, grad, c, inv, pivot)

    @staticmethod
    def jvp(ctx: Any, tangent: Tensor) -> Tensor:
        (matrix,) = ctx.saved_tensors
        return m2q_jvp(matrix, tangent)


class MatrixToQuaternionTransformable(_SavesInput):
    @staticmethod
    def forward(matrix: Tensor) -> Tensor:
        c, inv, _ = select(matrix)
        return c * inv

    @staticmethod
    def backward(ctx: Any, grad: Tensor) -> Tensor:
        (matrix,) = ctx.saved_tensors
        return m2q_backward(matrix, grad, *select(matrix))

    @staticmethod
    def jvp(ctx: Any, tangent: Tensor) -> Tensor:
        (matrix,) = ctx.saved_tensors
        return m2q_jvp(matrix, tangent)


class _EagerTorch:
    """``torch`` as the core's array namespace, with a ``where`` that is fast in eager mode, for one
    evaluation of a core formula (make one per call: it keeps the masks it has seen).

    ``torch.where`` on the CPU runs about 25x slower than a multiply (it is not vectorised; measured
    on float32 at N = 262144), and the core selects with it in every conversion. Every ``where`` of
    the core chooses between finite branches (its numerical rule), and for finite ``a``, ``b``,
    ``lerp(b, a, 1) = a`` and ``lerp(b, a, 0) = b`` exactly (up to the sign of a zero), so ``lerp``
    with the condition as its weight is the same selection in one vectorised pass. It is
    differentiable in ``a`` and ``b`` (the weight is a constant), so double backward goes through it.
    The core selects with the same few masks many times (matrix_to_quaternion: 4 masks, ~50 selections
    forward and backward), so each mask's 0/1 weight is converted once and kept."""

    def __init__(self) -> None:
        self._weights: dict[int, tuple[Tensor, Tensor]] = {}

    def __getattr__(self, name: str) -> Any:
        return getattr(torch, name)

    def _weight(self, condition: Tensor, dtype: torch.dtype) -> Tensor:
        # Keyed by identity; the entry keeps the mask alive, so its id is not reused meanwhile.
        kept = self._weights.get(id(condition))
        if kept is None or kept[0] is not condition or kept[1].dtype != dtype:
            kept = (condition, condition.to(dtype))
            self._weights[id(condition)] = kept
        return kept[1]

    def where(self, condition: Tensor, a: Tensor | float, b: Tensor | float) -> Tensor:
        like = a if isinstance(a, Tensor) else b
        assert isinstance(like, Tensor)
        weight = self._weight(condition, like.dtype)
        if isinstance(b, float) and b == 0.0:
            return like * weight  # a * 1 = a and a * 0 = 0 for finite a: one pass
        start = b if isinstance(b, Tensor) else torch.tensor(b, dtype=like.dtype, device=like.device)
        end = a if isinstance(a, Tensor) else torch.tensor(a, dtype=like.dtype, device=like.device)
        return torch.lerp(start, end, weight)


# Evaluation by blocks of rows, for very large batches. Over a whole batch, the core formulas' ~40 to
# ~100 column temporaries pile up to many times the input's size (1.6 GB for matrix_to_quaternion's
# forward + backward at N = 4194304), and malloc serves such a peak with fresh pages, a page fault per
# 4 KB, on every call (glibc gives memory back to the system once more than twice its largest freed
# block is free). By blocks, the temporaries are those of one block, reused by the next from cache.
# Measured on a 2-core CPU (float32, several processes, outputs kept alive across calls as a training
# loop does): at N = 4194304, 3-6x faster forward and 2-3x forward + backward; at N = 262144 level or
# slower (the fault pattern then depends on the process's earlier allocations more than on blocks), so
# batches up to BLOCKS_FROM rows run whole. Each elementwise operation on a block of 65536 rows still
# spans ATen's grain and runs on all threads; 32768 and 131072 measured about the same.
BLOCK_ROWS = 65536
BLOCKS_FROM = 4 * BLOCK_ROWS


def _by_blocks(
    fn: Callable[..., Tensor], batch: torch.Size, tail: tuple[int, ...], *arrays: Tensor
) -> Tensor:
    """``fn(*arrays)``, a function of rows, evaluated by blocks of ``BLOCK_ROWS`` rows into one result
    where the batch has more than ``BLOCKS_FROM`` rows.

    Every array has the leading dimensions ``batch``; each row of the result has the shape ``tail``.
    In one call for smaller batches, under ``torch.func`` transforms (the result buffer would not be
    batched) and where autograd records (double backward differentiates ``fn`` whole)."""
    rows = math.prod(batch)
    if rows <= BLOCKS_FROM or torch.is_grad_enabled() or torch._C._are_functorch_transforms_active():
        return fn(*arrays)
    flat = [a.reshape(rows, *a.shape[len(batch) :]) for a in arrays]
    out = torch.empty((rows, *tail), dtype=arrays[0].dtype, device=arrays[0].device)
    for start in range(0, rows, BLOCK_ROWS):
        out[start : start + BLOCK_ROWS] = fn(*(a[start : start + BLOCK_ROWS] for a in flat))
    return out.reshape(*batch, *tail)


def _q2m_columns(q: Tensor) -> Tensor:
    return _core.quaternion_to_matrix(_EagerTorch(), q)


def _q2m_cotangent(q: Tensor, grad: Tensor) -> Tensor:
    return _core.quaternion_to_matrix_cotangent(_EagerTorch(), q, grad)


def _m2q_columns(matrix: Tensor) -> Tensor:
    return _core.matrix_to_quaternion(_EagerTorch(), matrix)


def _m2q_cotangent(matrix: Tensor, q: Tensor, grad: Tensor) -> Tensor:
    return _core.matrix_to_quaternion_cotangent(_EagerTorch(), matrix, q, grad)


class QuaternionToMatrixColumns(torch.autograd.Function):
    """The core formula forward and its analytic derivative backward
    (``_core.quaternion_to_matrix_cotangent``), by blocks of rows. Keeps only the input."""

    generate_vmap_rule = True

    @staticmethod
    def forward(q: Tensor) -> Tensor:
        return _by_blocks(_q2m_columns, q.shape[:-1], (3, 3), q)

    @staticmethod
    def setup_context(ctx: Any, inputs: tuple[Tensor], output: Tensor) -> None:
        ctx.save_for_backward(inputs[0])
        ctx.save_for_forward(inputs[0])

    @staticmethod
    def backward(ctx: Any, grad: Tensor) -> Tensor:
        (q,) = ctx.saved_tensors
        return _by_blocks(_q2m_cotangent, q.shape[:-1], (4,), q, grad)

    @staticmethod
    def jvp(ctx: Any, tangent: Tensor) -> Tensor:
        (q,) = ctx.saved_tensors
        return q2m_jvp(q, tangent)


class MatrixToQuaternionColumns(torch.autograd.Function):
    """The core formula forward and its analytic derivatives (``_core.matrix_to_quaternion_cotangent``
    and ``_tangent``), by blocks of rows: only the selected candidate is differentiated. Keeps the
    input and the output (both derivatives use the quaternion; recomputing it would cost a forward
    pass)."""

    generate_vmap_rule = True

    @staticmethod
    def forward(matrix: Tensor) -> Tensor:
        return _by_blocks(_m2q_columns, matrix.shape[:-2], (4,), matrix)

    @staticmethod
    def setup_context(ctx: Any, inputs: tuple[Tensor], output: Tensor) -> None:
        ctx.save_for_backward(inputs[0], output)
        ctx.save_for_forward(inputs[0], output)

    @staticmethod
    def backward(ctx: Any, grad: Tensor) -> Tensor:
        matrix, q = ctx.saved_tensors
        return _by_blocks(_m2q_cotangent, matrix.shape[:-2], (3, 3), matrix, q, grad)

    @staticmethod
    def jvp(ctx: Any, tangent: Tensor) -> Tensor:
        matrix, q = ctx.saved_tensors
        return _core.matrix_to_quaternion_tangent(_EagerTorch(), matrix, q, tangent)


# Largest batch (number of rotations) that takes the small-batch Functions above, by operation.
# Measured on a 2-core CPU (float32, forward + backward, medians of interleaved runs): their cost is
# the number of operations, ~2.5x fewer than autograd over the core formula at N = 64, but their
# (N, 16) intermediates move more memory than the core's (N,) column passes. quaternion_to_matrix:
# 1.6x faster than autograd over the core at N = 4096, level with it at 16384, so the core takes over
# above 8192. matrix_to_quaternion: 1.6x faster than the columns Function at 1024, 1.4x slower at 4096.
MAX_FUSED_BATCH = {"quaternion_to_matrix": 4096, "matrix_to_quaternion": 2048}
# Without a gradient to build, quaternion_to_matrix's Function pays for a backward it never runs: its
# (N, 16) products move 4x the memory of the core's columns. Forward only (same machine and method) it
# is 1.3x faster than the core at N = 1024, level at 2048 and 2x slower at 4096, so above 1024 a call
# that needs no gradient takes the core formula. (matrix_to_quaternion's columns Function already is
# the core formula forward.)
MAX_FUSED_BATCH_NO_GRAD = {"quaternion_to_matrix": 1024}

# Scalar-last (x, y, z, w) <-> scalar-first (w, x, y, z) positions.
TO_FIRST = [3, 0, 1, 2]
TO_LAST = [1, 2, 3, 0]


def to_first(q: Tensor, scalar_first: bool) -> Tensor:
    """``q`` stored in ``scalar_first`` order, as scalar-first."""
    return q if scalar_first else q[..., TO_FIRST]


def from_first(q: Tensor, scalar_first: bool) -> Tensor:
    """A scalar-first ``q`` in ``scalar_first`` storage order (the inverse of :func:`to_first`)."""
    return q if scalar_first else q[..., TO_LAST]


def quaternion_to_matrix(xp: Any, q: Tensor, *, scalar_first: bool = True) -> Tensor:
    """Fused :func:`diffquat._core.quaternion_to_matrix` (same name: the backend validates by it)."""
    fn = (
        QuaternionToMatrixTransformable if torch._C._are_functorch_transforms_active() else QuaternionToMatrix
    )
    r: Tensor = fn.apply(to_first(q, scalar_first))  # type: ignore[no-untyped-call]
    return r


def matrix_to_quaternion(xp: Any, matrix: Tensor, *, scalar_first: bool = True) -> Tensor:
    """Fused :func:`diffquat._core.matrix_to_quaternion` (same name: the backend validates by it)."""
    fn = (
        MatrixToQuaternionTransformable if torch._C._are_functorch_transforms_active() else MatrixToQuaternion
    )
    q: Tensor = fn.apply(matrix)  # type: ignore[no-untyped-call]
    return from_first(q, scalar_first)


def quaternion_to_matrix_columns(xp: Any, q: Tensor, *, scalar_first: bool = True) -> Tensor:
    """:class:`QuaternionToMatrixColumns` in either storage order."""
    r: Tensor = QuaternionToMatrixColumns.apply(to_first(q, scalar_first))  # type: ignore[no-untyped-call]
    return r


def quaternion_to_matrix_blocks(xp: Any, q: Tensor, *, scalar_first: bool = True) -> Tensor:
    """The core formula (by blocks of rows where the batch is very large), for a call that records no
    gradient. Over plain ``torch``: with only two selections, the lerp namespace measured no faster
    forward (and 5% slower at N = 4096)."""

    def rows(t: Tensor) -> Tensor:
        return _core.quaternion_to_matrix(xp, t, scalar_first=scalar_first)

    with torch.no_grad():  # q2m_path takes this only where no gradient is recorded
        return _by_blocks(rows, q.shape[:-1], (3, 3), q)


def matrix_to_quaternion_columns(xp: Any, matrix: Tensor, *, scalar_first: bool = True) -> Tensor:
    """:class:`MatrixToQuaternionColumns` in either storage order."""
    q: Tensor = MatrixToQuaternionColumns.apply(matrix)  # type: ignore[no-untyped-call]
    return from_first(q, scalar_first)


# The backend validates arguments by the core function's name.
matrix_to_quaternion_columns.__name__ = "matrix_to_quaternion"
quaternion_to_matrix_columns.__name__ = "quaternion_to_matrix"
quaternion_to_matrix_blocks.__name__ = "quaternion_to_matrix"


class _CompiledCuda:
    """``torch`` as the core's namespace under ``torch.compile`` for CUDA tensors: the core's matrices
    are stacked by rows (``_core.stack_matrix``), which inductor's CUDA code generation writes as one
    kernel of whole rows. On the CPU inductor lowers every concatenation as copies, and rows measured
    mixed there (``quaternion_to_matrix`` forward 1.8x faster, ``axis_angle_to_matrix`` 1.17x slower,
    at N = 262144), so the plain ``torch`` namespace stays there."""

    stack_rows = True

    def __getattr__(self, name: str) -> Any:
        return getattr(torch, name)


_COMPILED_CUDA = _CompiledCuda()


def compiled_quaternion_to_matrix(xp: Any, q: Tensor, *, scalar_first: bool = True) -> Tensor:
    """The core formula over :class:`_CompiledCuda` (``xp`` is the caller's ``torch``)."""
    r: Tensor = _core.quaternion_to_matrix(_COMPILED_CUDA, q, scalar_first=scalar_first)
    return r


compiled_quaternion_to_matrix.__name__ = "quaternion_to_matrix"


def _triton_usable(x: Tensor) -> bool:
    """CUDA tensor, Triton importable, and no torch.func transform active (a kernel has no vmap rule)."""
    if not x.is_cuda or torch._C._are_functorch_transforms_active():
        return False
    try:
        from . import _triton  # noqa: F401
    except ImportError:
        return False
    return True


def q2m_path(q: Any) -> Callable[..., Tensor]:
    """The implementation of ``quaternion_to_matrix`` for this call: the core formula under
    ``torch.compile`` (inductor fuses it with the user's code; for CUDA tensors over
    :class:`_CompiledCuda`, which stacks the matrix by rows); the Triton kernels on CUDA; the C
    kernels of :mod:`._cpu` on the CPU. Without those (no C compiler at install, a ``torch.func``
    transform, another device): for eager batches, the fused Function for small ones, the columns
    Function for large ones, and where no gradient is recorded, the core formula by blocks from a
    smaller batch size on."""
    if not isinstance(q, Tensor) or torch.compiler.is_compiling():
        return (
            compiled_quaternion_to_matrix
            if isinstance(q, Tensor) and q.is_cuda
            else _core.quaternion_to_matrix
        )
    if _triton_usable(q):
        from . import _triton

        return _triton.quaternion_to_matrix
    if _cpu is not None and _cpu.usable(q):
        return _cpu.quaternion_to_matrix
    if _builds_gradient(q):
        small = q.numel() <= 4 * MAX_FUSED_BATCH["quaternion_to_matrix"]
        return quaternion_to_matrix if small else quaternion_to_matrix_columns
    small = q.numel() <= 4 * MAX_FUSED_BATCH_NO_GRAD["quaternion_to_matrix"]
    return quaternion_to_matrix if small else quaternion_to_matrix_blocks


def _builds_gradient(x: Tensor) -> bool:
    """Whether autograd records this call (or a ``torch.func`` transform may differentiate it)."""
    return torch._C._are_functorch_transforms_active() or (torch.is_grad_enabled() and x.requires_grad)


def m2q_path(matrix: Any) -> Callable[..., Tensor]:
    """The implementation of ``matrix_to_quaternion`` for this call: the core formula under
    ``torch.compile``; the Triton kernels on CUDA; the C kernels on the CPU; otherwise the small-batch
    Function for small eager batches, the columns Function for large ones."""
    if not isinstance(matrix, Tensor) or torch.compiler.is_compiling():
        return _core.matrix_to_quaternion
    if _triton_usable(matrix):
        from . import _triton

        return _triton.matrix_to_quaternion
    if _cpu is not None and _cpu.usable(matrix):
        return _cpu.matrix_to_quaternion
    small = matrix.numel() <= 9 * MAX_FUSED_BATCH["matrix_to_quaternion"]
    return matrix_to_quaternion if small else matrix_to_quaternion_columns
