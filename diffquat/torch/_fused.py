"""Eager fast paths of ``quaternion_to_matrix`` and ``matrix_to_quaternion`` on torch.

Small batches: a ``torch.autograd.Function`` for each, over the index tables of
:mod:`diffquat._fused` (the "gather" Functions): about a dozen whole-tensor operations forward and
twenty backward, instead of autograd recording and replaying the core's ~30 elementwise operations
(each a pass over memory) plus their derivatives. No BLAS matmul: with a small contraction it would be
slower than the gathers, and its thread pool competes with ATen's on a loaded machine. Each saves
only its input and recomputes what it needs, so the memory kept for backward is the input's.

Large batches of ``matrix_to_quaternion``: the "columns" Function, the core formula forward and its
analytic derivative (``_core.matrix_to_quaternion_cotangent``) backward, both on whole columns, with a
vectorised selection in place of ``torch.where`` (see ``_EagerTorch``).

Every backward is made of differentiable torch operations, so double backward (``gradgradcheck``,
Hessians) differentiates it; ``jvp`` gives forward mode; ``generate_vmap_rule`` gives
``torch.func.vmap`` (and with it ``jacrev``/``jacfwd``).

The functions here compute in scalar-first order; :mod:`diffquat.torch` reorders scalar-last arrays
around them, and calls them only in eager mode: under ``torch.compile`` it traces the plain core
formula instead, so that inductor fuses it with the user's surrounding code.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

import torch
from torch import Tensor

from .. import _core, _fused

_TABLES = {
    "q2m_index": (_fused.Q2M_INDEX, torch.long),
    "q2m_sign": (_fused.Q2M_SIGN, None),
    "q2m_entry": (_fused.Q2M_ENTRY, torch.long),
    "q2m_base": (_fused.Q2M_BASE, None),
    "m2q_index": (_fused.M2Q_INDEX, torch.long),
    "m2q_sign": (_fused.M2Q_SIGN, None),
    "m2q_entry": (_fused.M2Q_ENTRY, torch.long),
    "m2q_base": (_fused.M2Q_BASE, None),
    "priority": (_fused.SIGN_PRIORITY, None),
    "components": (list(range(4)), torch.long),
}
_cache: dict[tuple[str, torch.dtype, torch.device], Tensor] = {}


def _table(name: str, like: Tensor) -> Tensor:
    """A table of :mod:`diffquat._fused` as a tensor on ``like``'s device (floating tables in its
    dtype), built once per dtype and device."""
    key = (name, like.dtype, like.device)
    value = _cache.get(key)
    if value is None:
        values, dtype = _TABLES[name]
        value = torch.tensor(values, dtype=dtype or like.dtype, device=like.device)
        _cache[key] = value
    return value


def _split(x: Tensor, rows: int, cols: int) -> Tensor:
    """The last dimension of ``x`` as ``(rows, cols)``."""
    return x.reshape(*x.shape[:-1], rows, cols)


def _q2m_terms(products: Tensor) -> Tensor:
    """The 9 entries of ``R - I`` (flat) from the 16 products ``P`` (flat): two signed terms each."""
    terms = torch.index_select(products, -1, _table("q2m_index", products)) * _table("q2m_sign", products)
    return torch.sum(_split(terms, 9, 2), dim=-1)


def _q2m(q: Tensor) -> Tensor:
    s = _fused.q2m_scale(torch, q)
    products = torch.flatten((s * q)[..., :, None] * q[..., None, :], -2)
    flat = _q2m_terms(products) + _table("q2m_base", q)
    return _split(flat, 3, 3)


def q2m_backward(q: Tensor, grad: Tensor) -> Tensor:
    """``dL/dq`` (scalar first) from ``dL/dR``, in differentiable torch operations."""
    # dL/dP: each of the 18 terms sends its entry's cotangent, signed, to its product.
    entries = torch.index_select(torch.flatten(grad, -2), -1, _table("q2m_entry", q))
    terms = entries * _table("q2m_sign", q)
    forms = torch.zeros((*terms.shape[:-1], 16), dtype=terms.dtype, device=terms.device)
    forms = torch.index_add(forms, -1, _table("q2m_index", q), terms)
    return _fused.q2m_gradient(torch, q, _fused.q2m_scale(torch, q), _split(forms, 4, 4))


class _SavesInput(torch.autograd.Function):
    """A Function of one tensor that keeps only that tensor for backward and forward mode."""

    generate_vmap_rule = True

    @staticmethod
    def setup_context(ctx: Any, inputs: tuple[Tensor], output: Tensor) -> None:
        ctx.save_for_backward(inputs[0])
        ctx.save_for_forward(inputs[0])


class QuaternionToMatrix(_SavesInput):
    @staticmethod
    def forward(q: Tensor) -> Tensor:
        return _q2m(q)

    @staticmethod
    def backward(ctx: Any, grad: Tensor) -> Tensor:
        (q,) = ctx.saved_tensors
        return q2m_backward(q, grad)

    @staticmethod
    def jvp(ctx: Any, tangent: Tensor) -> Tensor:
        (q,) = ctx.saved_tensors
        s = _fused.q2m_scale(torch, q)
        # d(s q) = s (dq - s (q . dq) q), since ds = -s^2 (q . dq)
        du = s * (tangent - (s * torch.sum(q * tangent, dim=-1, keepdim=True)) * q)
        d_products = du[..., :, None] * q[..., None, :] + (s * q)[..., :, None] * tangent[..., None, :]
        return _split(_q2m_terms(torch.flatten(d_products, -2)), 3, 3)


def _candidates(matrix: Tensor) -> Tensor:
    """``K`` flat (..., 16): entry (a, b) is ``4 q_a q_b`` of the core, three signed entries each."""
    padded = torch.nn.functional.pad(torch.flatten(matrix, -2), (0, 1))
    terms = torch.index_select(padded, -1, _table("m2q_index", matrix)) * _table("m2q_sign", matrix)
    return torch.sum(_split(terms, 16, 3), dim=-1)


def _select(matrix: Tensor) -> tuple[Tensor, Tensor, Tensor]:
    """The candidate of the largest pivot, its signed inverse norm, and the pivot (..., 1).

    ``argmax`` returns the first maximum, so ties go to the lower index, as in the core. The canonical
    sign is that of the first non-zero component in (w, x, y, z) order: the argmax of ``c != 0``
    weighted by priority finds it, and the pivot's own component (>= 1) guarantees there is one."""
    k = _split(_candidates(matrix) + _table("m2q_base", matrix), 4, 4)
    pivot = torch.argmax(torch.diagonal(k, dim1=-2, dim2=-1), dim=-1, keepdim=True)
    c = torch.gather(k, -2, pivot[..., None].expand(*pivot.shape, 4))[..., 0, :]
    leading = torch.argmax((c != 0) * _table("priority", matrix), dim=-1, keepdim=True)
    inv = torch.copysign(torch.rsqrt(torch.sum(c * c, dim=-1, keepdim=True)), torch.gather(c, -1, leading))
    return c, inv, pivot


class MatrixToQuaternion(_SavesInput):
    @staticmethod
    def forward(matrix: Tensor) -> Tensor:
        c, inv, _ = _select(matrix)
        return c * inv

    @staticmethod
    def backward(ctx: Any, grad: Tensor) -> Tensor:
        (matrix,) = ctx.saved_tensors
        c, inv, pivot = _select(matrix)
        grad_c = _fused.normalize_vjp(torch, c * inv, inv, grad)
        # Only the selected row of K receives the cotangent; each of K's 48 terms sends it back,
        # signed, to its matrix entry (the pad entry 9 is dropped).
        rows = _table("components", matrix) == pivot
        grad_k = torch.flatten(rows[..., :, None] * grad_c[..., None, :], -2)
        terms = torch.index_select(grad_k, -1, _table("m2q_entry", matrix)) * _table("m2q_sign", matrix)
        padded = torch.zeros((*terms.shape[:-1], 10), dtype=terms.dtype, device=terms.device)
        padded = torch.index_add(padded, -1, _table("m2q_index", matrix), terms)
        return _split(padded[..., :9], 3, 3)

    @staticmethod
    def jvp(ctx: Any, tangent: Tensor) -> Tensor:
        (matrix,) = ctx.saved_tensors
        c, inv, pivot = _select(matrix)
        tangent_k = _split(_candidates(tangent), 4, 4)
        tangent_c = torch.gather(tangent_k, -2, pivot[..., None].expand(*pivot.shape, 4))[..., 0, :]
        return _fused.normalize_vjp(torch, c * inv, inv, tangent_c)


class _EagerTorch:
    """``torch`` as the core's array namespace, with a ``where`` that is fast in eager mode.

    ``torch.where`` on the CPU runs about 25x slower than a multiply (it is not vectorised; measured
    on float32 at N = 262144), and the core selects with it in every conversion. Every ``where`` of
    the core chooses between finite branches (its numerical rule), and for finite ``a``, ``b``,
    ``lerp(b, a, 1) = a`` and ``lerp(b, a, 0) = b`` exactly (up to the sign of a zero), so ``lerp``
    with the condition as its weight is the same selection in one vectorised pass. It is
    differentiable in ``a`` and ``b`` (the weight is a constant), so double backward goes through it."""

    def __getattr__(self, name: str) -> Any:
        return getattr(torch, name)

    @staticmethod
    def where(condition: Tensor, a: Tensor | float, b: Tensor | float) -> Tensor:
        like = a if isinstance(a, Tensor) else b
        assert isinstance(like, Tensor)
        if isinstance(b, float) and b == 0.0:
            return like * condition.to(like.dtype)  # a * 1 = a and a * 0 = 0 for finite a: one pass
        start = b if isinstance(b, Tensor) else torch.tensor(b, dtype=like.dtype, device=like.device)
        end = a if isinstance(a, Tensor) else torch.tensor(a, dtype=like.dtype, device=like.device)
        return torch.lerp(start, end, condition.to(like.dtype))


_EAGER = _EagerTorch()


class MatrixToQuaternionColumns(torch.autograd.Function):
    """The core formula forward and its analytic derivatives (``_core.matrix_to_quaternion_cotangent``
    and ``_tangent``): only the selected candidate is differentiated. Keeps the input and the output
    (both formulas use the quaternion; recomputing it would cost a forward pass)."""

    generate_vmap_rule = True

    @staticmethod
    def forward(matrix: Tensor) -> Tensor:
        return _core.matrix_to_quaternion(_EAGER, matrix)

    @staticmethod
    def setup_context(ctx: Any, inputs: tuple[Tensor], output: Tensor) -> None:
        ctx.save_for_backward(inputs[0], output)
        ctx.save_for_forward(inputs[0], output)

    @staticmethod
    def backward(ctx: Any, grad: Tensor) -> Tensor:
        matrix, q = ctx.saved_tensors
        return _core.matrix_to_quaternion_cotangent(_EAGER, matrix, q, grad)

    @staticmethod
    def jvp(ctx: Any, tangent: Tensor) -> Tensor:
        matrix, q = ctx.saved_tensors
        return _core.matrix_to_quaternion_tangent(_EAGER, matrix, q, tangent)


# Largest batch (number of rotations) that takes the gather Functions above, by operation. Measured
# on a 2-core CPU (float32, forward + backward, median of interleaved runs): their cost is the number
# of operations, so at N = 64 they are ~2x faster than autograd over the core formula, but their
# gathers and index_add over (N, 16) and (N, 18) intermediates move more memory than the core's (N,)
# column passes, so at N = 4096 they are ~2x slower. Above it, quaternion_to_matrix takes autograd
# over the core formula and matrix_to_quaternion the columns Function (below N = 512 the gather one is
# faster, above 1024 the columns one).
MAX_FUSED_BATCH = {"quaternion_to_matrix": 1024, "matrix_to_quaternion": 512}

# Scalar-last (x, y, z, w) <-> scalar-first (w, x, y, z) positions.
TO_FIRST = [3, 0, 1, 2]
TO_LAST = [1, 2, 3, 0]


def quaternion_to_matrix(xp: Any, q: Tensor, *, scalar_first: bool = True) -> Tensor:
    """Fused :func:`diffquat._core.quaternion_to_matrix` (same name: the backend validates by it)."""
    return QuaternionToMatrix.apply(q if scalar_first else q[..., TO_FIRST])  # type: ignore[no-untyped-call]


def matrix_to_quaternion(xp: Any, matrix: Tensor, *, scalar_first: bool = True) -> Tensor:
    """Fused :func:`diffquat._core.matrix_to_quaternion` (same name: the backend validates by it)."""
    q: Tensor = MatrixToQuaternion.apply(matrix)  # type: ignore[no-untyped-call]
    return q if scalar_first else q[..., TO_LAST]


def matrix_to_quaternion_columns(xp: Any, matrix: Tensor, *, scalar_first: bool = True) -> Tensor:
    """:class:`MatrixToQuaternionColumns` in either storage order."""
    q: Tensor = MatrixToQuaternionColumns.apply(matrix)  # type: ignore[no-untyped-call]
    return q if scalar_first else q[..., TO_LAST]


# The backend validates arguments by the core function's name.
matrix_to_quaternion_columns.__name__ = "matrix_to_quaternion"


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
    ``torch.compile`` (inductor fuses it with the user's code) and for large CPU batches; the Triton
    kernels on CUDA; the fused Function for small eager batches."""
    if not isinstance(q, Tensor) or torch.compiler.is_compiling():
        return _core.quaternion_to_matrix
    if _triton_usable(q):
        from . import _triton

        return _triton.quaternion_to_matrix
    small = q.numel() <= 4 * MAX_FUSED_BATCH["quaternion_to_matrix"]
    return quaternion_to_matrix if small else _core.quaternion_to_matrix


def m2q_path(matrix: Any) -> Callable[..., Tensor]:
    """The implementation of ``matrix_to_quaternion`` for this call: the core formula under
    ``torch.compile``, the gather Function for small eager batches, the columns Function for large
    ones (no Triton kernel yet)."""
    if not isinstance(matrix, Tensor) or torch.compiler.is_compiling():
        return _core.matrix_to_quaternion
    small = matrix.numel() <= 9 * MAX_FUSED_BATCH["matrix_to_quaternion"]
    return matrix_to_quaternion if small else matrix_to_quaternion_columns
