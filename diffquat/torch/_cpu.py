"""``quaternion_to_matrix`` and ``matrix_to_quaternion`` on the CPU through the C kernels of
``_kernels.c``: one pass over memory forward, one backward, each.

An eager call then costs one kernel (and, where autograd records, one ``autograd.Function``)
instead of the core's ~40 elementwise operations forward and as many backward: at small N that is
the dispatch cost, and at large N the memory traffic of their temporaries. The kernels compute what
the core formulas compute, operation by operation (the tests compare them at every edge case), read
strided inputs in place (an expanded cotangent, scalar-last storage, a transposed matrix) and write
contiguous outputs.

The backward kernels are not differentiable again: where a double backward is being recorded
(``create_graph=True``), the backward evaluates the differentiable torch formula instead. Forward
mode (``jvp``) takes the torch formula of :mod:`._fused`. ``torch.func`` transforms take the
Functions of :mod:`._fused`, which have vmap rules; ``torch.compile`` takes the core formula (see
``_fused.q2m_path``).

Only imported where the extension was built (``pyproject.toml`` builds it wherever a C compiler is
found); without it the dispatch keeps the pure-torch paths of :mod:`._fused`.
"""

from __future__ import annotations

from typing import Any

import torch
from torch import Tensor
from torch.autograd import forward_ad

from .. import _kernels
from . import _fused

_DTYPE = {torch.float32: 0, torch.float64: 1}


def usable(x: Any) -> bool:
    """A dense CPU tensor whose buffer holds its values (a plain tensor or a parameter, not a subclass
    with its own dispatch such as the fake tensors of tracing, nor a lazily negated or conjugated
    view, whose buffer holds the values before the sign change), outside ``torch.func`` transforms
    (a kernel has no vmap rule). Half precision counts: the backend computes it in float32 before the
    kernel sees it."""
    return (
        type(x) in (Tensor, torch.nn.Parameter)
        and x.device.type == "cpu"
        and x.layout == torch.strided
        and not x.is_neg()
        and not x.is_conj()
        and not torch._C._are_functorch_transforms_active()
    )


def _records(x: Tensor) -> bool:
    """Whether a derivative of this call can be asked for: autograd records it, or forward-mode AD is
    active (a dual tensor carries its tangent even where ``requires_grad`` is False)."""
    return (torch.is_grad_enabled() and x.requires_grad) or forward_ad._current_level >= 0


def q2m_forward(q: Tensor, first: bool) -> Tensor:
    """(..., 4) in either storage order to (..., 3, 3), one kernel."""
    rows = q.reshape(-1, 4)  # a view wherever the batch dimensions allow one
    out = torch.empty((rows.shape[0], 3, 3), dtype=q.dtype, device=q.device)
    if rows.shape[0]:
        row, component = rows.stride()
        _kernels.q2m_forward(
            _DTYPE[q.dtype], torch.get_num_threads(), rows.shape[0], first,
            rows.data_ptr(), row, component, out.data_ptr(),
        )  # fmt: skip
    return out.reshape(*q.shape[:-1], 3, 3)


def q2m_backward(q: Tensor, grad: Tensor, first: bool) -> Tensor:
    """``dL/dq`` (in ``q``'s storage order) from ``dL/dR``, one kernel."""
    rows, g = q.reshape(-1, 4), grad.reshape(-1, 3, 3)
    out = torch.empty((rows.shape[0], 4), dtype=q.dtype, device=q.device)
    if rows.shape[0]:
        row, component = rows.stride()
        g_row, g_i, g_j = g.stride()
        _kernels.q2m_backward(
            _DTYPE[q.dtype], torch.get_num_threads(), rows.shape[0], first,
            rows.data_ptr(), row, component, g.data_ptr(), g_row, g_i, g_j, out.data_ptr(),
        )  # fmt: skip
    return out.reshape(q.shape)


def m2q_forward(matrix: Tensor, first: bool) -> Tensor:
    """(..., 3, 3) to canonical unit quaternions (..., 4) in either storage order, one kernel."""
    rows = matrix.reshape(-1, 3, 3)
    out = torch.empty((rows.shape[0], 4), dtype=matrix.dtype, device=matrix.device)
    if rows.shape[0]:
        row, i, j = rows.stride()
        _kernels.m2q_forward(
            _DTYPE[matrix.dtype], torch.get_num_threads(), rows.shape[0], first,
            rows.data_ptr(), row, i, j, out.data_ptr(),
        )  # fmt: skip
    return out.reshape(*matrix.shape[:-2], 4)


def m2q_backward(matrix: Tensor, q: Tensor, grad: Tensor, first: bool) -> Tensor:
    """``dL/dmatrix`` from the matrix, its quaternion ``q`` and ``dL/dq`` (both in the storage order
    ``first``), one kernel."""
    rows, q_rows, g = matrix.reshape(-1, 3, 3), q.reshape(-1, 4), grad.reshape(-1, 4)
    out = torch.empty((rows.shape[0], 3, 3), dtype=matrix.dtype, device=matrix.device)
    if rows.shape[0]:
        row, i, j = rows.stride()
        (q_row, q_component), (g_row, g_component) = q_rows.stride(), g.stride()
        _kernels.m2q_backward(
            _DTYPE[matrix.dtype], torch.get_num_threads(), rows.shape[0], first,
            rows.data_ptr(), row, i, j, q_rows.data_ptr(), q_row, q_component,
            g.data_ptr(), g_row, g_component, out.data_ptr(),
        )  # fmt: skip
    return out.reshape(matrix.shape)


def _plain(grad: Tensor, like: Tensor) -> bool:
    """Whether a cotangent can go to a kernel: a dense tensor of ``like``'s dtype and device (autograd
    hands the output's; anything else takes the torch formula, never a raw pointer)."""
    return usable(grad) and grad.dtype == like.dtype


# Old-style Functions (``forward(ctx, ...)``): ``Function.apply`` binds the arguments of a
# ``setup_context`` Function through ``inspect.signature`` on every call (see _fused.py). Used in
# eager mode only; torch.func transforms take _fused's Functions, which have vmap rules.


class QuaternionToMatrixKernel(torch.autograd.Function):
    @staticmethod
    def forward(ctx: Any, q: Tensor, first: bool) -> Tensor:
        ctx.first = first
        ctx.save_for_backward(q)
        ctx.save_for_forward(q)
        return q2m_forward(q, first)

    @staticmethod
    def backward(ctx: Any, grad: Tensor) -> tuple[Tensor, None]:
        (q,) = ctx.saved_tensors
        # a double backward records this (or an unusual cotangent): the differentiable formula
        if torch.is_grad_enabled() or not _plain(grad, q):
            return _fused.from_first(
                _fused.q2m_backward(_fused.to_first(q, ctx.first), grad), ctx.first
            ), None
        return q2m_backward(q, grad, ctx.first), None

    @staticmethod
    def jvp(ctx: Any, tangent: Tensor, _: None) -> Tensor:
        (q,) = ctx.saved_tensors
        return _fused.q2m_jvp(_fused.to_first(q, ctx.first), _fused.to_first(tangent, ctx.first))


class MatrixToQuaternionKernel(torch.autograd.Function):
    @staticmethod
    def forward(ctx: Any, matrix: Tensor, first: bool) -> Tensor:
        q = m2q_forward(matrix, first)
        ctx.first = first
        ctx.save_for_backward(matrix, q)
        ctx.save_for_forward(matrix)
        return q

    @staticmethod
    def backward(ctx: Any, grad: Tensor) -> tuple[Tensor, None]:
        matrix, q = ctx.saved_tensors
        # double backward (or an unusual cotangent): the quaternion as a function of the matrix
        if torch.is_grad_enabled() or not _plain(grad, matrix):
            return _fused.m2q_backward(matrix, _fused.to_first(grad, ctx.first), *_fused.select(matrix)), None
        return m2q_backward(matrix, q, grad, ctx.first), None

    @staticmethod
    def jvp(ctx: Any, tangent: Tensor, _: None) -> Tensor:
        (matrix,) = ctx.saved_tensors
        return _fused.from_first(_fused.m2q_jvp(matrix, tangent), ctx.first)


def quaternion_to_matrix(xp: Any, q: Tensor, *, scalar_first: bool = True) -> Tensor:
    """:func:`diffquat._core.quaternion_to_matrix` through the C kernels (same name: the backend
    validates by it); without the Function where no derivative can be asked for."""
    if _records(q):
        r: Tensor = QuaternionToMatrixKernel.apply(q, scalar_first)  # type: ignore[no-untyped-call]
        return r
    return q2m_forward(q, scalar_first)


def matrix_to_quaternion(xp: Any, matrix: Tensor, *, scalar_first: bool = True) -> Tensor:
    """:func:`diffquat._core.matrix_to_quaternion` through the C kernels (same name: the backend
    validates by it)."""
    if _records(matrix):
        q: Tensor = MatrixToQuaternionKernel.apply(matrix, scalar_first)  # type: ignore[no-untyped-call]
        return q
    return m2q_forward(matrix, scalar_first)
