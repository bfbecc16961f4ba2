"""``quaternion_to_matrix``, ``matrix_to_quaternion``, the four SO(3) Jacobians and ``quaternion_plus`` on
the CPU through the C kernels of ``_kernels.c``: one pass over memory forward, one backward, each.

An eager call then costs one kernel (and, where autograd records, one ``autograd.Function``)
instead of the core's ~40 elementwise operations forward and as many backward: at small N that is
the dispatch cost, and at large N the memory traffic of their temporaries. The kernels compute what
the core formulas compute, operation by operation; the tests compare both with a float64 reference.
They read strided inputs in place (an expanded cotangent, scalar-last storage, a transposed matrix)
and write contiguous outputs, and apply the non-finite row rule themselves (``handles_nonfinite``).

Every other derivative is the core's formula in differentiable torch operations: forward mode
(``jvp``) the core's tangents, and where a double backward is being recorded (``create_graph=True``)
the core's cotangents, which then differentiate again. So every order of derivative is the core's,
with the core's choice of pivot. :mod:`._dispatch` calls this module only in plain eager mode.

The backward kernels of the Jacobians and of ``quaternion_plus`` are their derivatives written out
(``_kernels.c`` says how), within a few ulps of autograd's derivative of the formula; their double
backward differentiates the formula, and forward mode takes the formula from the start (their
Functions have no ``jvp``).
"""

from __future__ import annotations

import functools
from typing import Any

import torch
from torch import Tensor
from torch.autograd import forward_ad

from .. import _algebra, _core, _kernels, _lie

_DTYPE = {torch.float32: 0, torch.float64: 1}


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
    """Whether a cotangent can go to a kernel: a dense plain tensor of ``like``'s dtype on the CPU
    (autograd hands the output's; anything else takes the torch formula, never a raw pointer)."""
    return (
        type(grad) is Tensor
        and grad.device.type == "cpu"
        and grad.dtype == like.dtype
        and grad.layout == torch.strided
        and not grad.is_neg()
        and not grad.is_conj()
        and not grad._is_zerotensor()  # autograd hands these for some zero cotangents: no buffer
    )


def _first(q: Tensor, first: bool) -> Tensor:
    """A quaternion in storage order ``first`` as scalar first (the core's derivative formulas read
    that order)."""
    return q if first else _core.xyzw_to_wxyz(torch, q)


def _stored(q: Tensor, first: bool) -> Tensor:
    """A scalar-first quaternion in storage order ``first``."""
    return q if first else _core.wxyz_to_xyzw(torch, q)


# Old-style Functions (``forward(ctx, ...)``): ``Function.apply`` binds the arguments of a
# ``setup_context`` Function through ``inspect.signature`` on every call, about 20 us, a fifth of the
# whole forward + backward at N = 64. Used in eager mode only (see _dispatch.py): torch.func
# transforms and compilers take the formula, which they differentiate themselves.


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
        if torch.is_grad_enabled() or not _plain(grad, q):  # recorded for a double backward
            cotangent = _core.quaternion_to_matrix_cotangent(torch, _first(q, ctx.first), grad)
            return _stored(cotangent, ctx.first), None
        return q2m_backward(q, grad, ctx.first), None

    @staticmethod
    def jvp(ctx: Any, tangent: Tensor, _: None) -> Tensor:
        (q,) = ctx.saved_tensors
        r: Tensor = _core.quaternion_to_matrix_tangent(torch, q, tangent, scalar_first=ctx.first)
        return r


class MatrixToQuaternionKernel(torch.autograd.Function):
    @staticmethod
    def forward(ctx: Any, matrix: Tensor, first: bool) -> Tensor:
        q = m2q_forward(matrix, first)
        ctx.first = first
        ctx.save_for_backward(matrix, q)
        ctx.save_for_forward(matrix, q)
        return q

    @staticmethod
    def backward(ctx: Any, grad: Tensor) -> tuple[Tensor, None]:
        matrix, q = ctx.saved_tensors
        # A double backward differentiates this through the saved result q, whose own derivative is
        # this Function again.
        if torch.is_grad_enabled() or not _plain(grad, matrix):
            first = ctx.first
            return _core.matrix_to_quaternion_cotangent(
                torch, matrix, _first(q, first), _first(grad, first)
            ), None
        return m2q_backward(matrix, q, grad, ctx.first), None

    @staticmethod
    def jvp(ctx: Any, tangent: Tensor, _: None) -> Tensor:
        matrix, q = ctx.saved_tensors
        dq: Tensor = _core.matrix_to_quaternion_tangent(torch, matrix, q, tangent, scalar_first=ctx.first)
        return dq


def quaternion_to_matrix(xp: Any, q: Tensor, *, scalar_first: bool = True) -> Tensor:
    """:func:`diffquat._core.quaternion_to_matrix` through the C kernels; without the Function where no
    derivative can be asked for."""
    if _records(q):
        r: Tensor = QuaternionToMatrixKernel.apply(q, scalar_first)  # type: ignore[no-untyped-call]
        return r
    return q2m_forward(q, scalar_first)


def matrix_to_quaternion(xp: Any, matrix: Tensor, *, scalar_first: bool = True) -> Tensor:
    """:func:`diffquat._core.matrix_to_quaternion` through the C kernels."""
    if _records(matrix):
        q: Tensor = MatrixToQuaternionKernel.apply(matrix, scalar_first)  # type: ignore[no-untyped-call]
        return q
    return m2q_forward(matrix, scalar_first)


# The kernels write NaN rows for non-finite input themselves (diffquat._backend.nonfinite_rows).
quaternion_to_matrix.handles_nonfinite = True  # type: ignore[attr-defined]
matrix_to_quaternion.handles_nonfinite = True  # type: ignore[attr-defined]


def _formula_cotangents(formula: Any, inputs: tuple[Tensor, ...], grad: Tensor) -> list[Tensor | None]:
    """The formula's own cotangents of ``inputs`` (None for those that need none), for a backward being
    recorded (a double backward: differentiable in the inputs and in ``grad``) or given a cotangent
    that is no plain buffer: ``formula()`` recomputes the output from ``inputs`` under autograd."""
    wanted = [x for x in inputs if x.requires_grad]
    with torch.enable_grad():
        out = formula()
    grads = iter(torch.autograd.grad(out, wanted, grad, create_graph=torch.is_grad_enabled()))
    return [next(grads) if x.requires_grad else None for x in inputs]


# ---------------------------------------------------------------------------------------------------
# The SO(3) Jacobians and their inverses (diffquat._lie): one kernel each way for the four of them.

# The kernels' ``kind`` of each function (see _kernels.c).
JACOBIAN_KINDS = {
    "so3_left_jacobian": 0,
    "so3_right_jacobian": 1,
    "so3_left_jacobian_inverse": 2,
    "so3_right_jacobian_inverse": 3,
}
_JACOBIAN_FORMULAS = {kind: getattr(_lie, name) for name, kind in JACOBIAN_KINDS.items()}


@functools.cache  # eager only (never traced): a dict lookup per call
def _series(dtype: torch.dtype) -> tuple[Tensor, tuple[int, int, int]]:
    """The core's series for ``dtype`` (:func:`diffquat._lie.series_table`, float64 numbers that the
    kernel rounds to the dtype as the core's Python numbers are rounded), kept alive for the kernels'
    pointer; built once per dtype."""
    flat, terms = _lie.series_table(float(torch.finfo(dtype).eps))
    # the kernels hold up to 16 coefficients per series and differentiate at least 3
    assert all(3 <= n <= 16 for n in terms), terms
    return torch.tensor(flat, dtype=torch.float64), terms


def jac_forward(omega: Tensor, kind: int) -> Tensor:
    """(..., 3) rotation vectors to (..., 3, 3) Jacobians of the given kind, one kernel."""
    rows = omega.reshape(-1, 3)
    out = torch.empty((rows.shape[0], 3, 3), dtype=omega.dtype, device=omega.device)
    if rows.shape[0]:
        row, component = rows.stride()
        series, terms = _series(omega.dtype)
        _kernels.jac_forward(
            _DTYPE[omega.dtype], torch.get_num_threads(), rows.shape[0], kind,
            rows.data_ptr(), row, component, series.data_ptr(), *terms, out.data_ptr(),
        )  # fmt: skip
    return out.reshape(*omega.shape[:-1], 3, 3)


def jac_backward(omega: Tensor, grad: Tensor, kind: int) -> Tensor:
    """``dL/dw`` from ``dL/dJ``, one kernel."""
    rows, g = omega.reshape(-1, 3), grad.reshape(-1, 3, 3)
    out = torch.empty((rows.shape[0], 3), dtype=omega.dtype, device=omega.device)
    if rows.shape[0]:
        row, component = rows.stride()
        g_row, g_i, g_j = g.stride()
        series, terms = _series(omega.dtype)
        _kernels.jac_backward(
            _DTYPE[omega.dtype], torch.get_num_threads(), rows.shape[0], kind,
            rows.data_ptr(), row, component, g.data_ptr(), g_row, g_i, g_j,
            series.data_ptr(), *terms, out.data_ptr(),
        )  # fmt: skip
    return out.reshape(omega.shape)


class JacobianKernel(torch.autograd.Function):
    """No ``jvp``: :mod:`._dispatch` gives forward-mode AD the formula."""

    @staticmethod
    def forward(ctx: Any, omega: Tensor, kind: int) -> Tensor:
        ctx.kind = kind
        ctx.save_for_backward(omega)
        return jac_forward(omega, kind)

    @staticmethod
    def backward(ctx: Any, grad: Tensor) -> tuple[Tensor | None, None]:
        (omega,) = ctx.saved_tensors
        if torch.is_grad_enabled() or not _plain(grad, omega):
            (cotangent,) = _formula_cotangents(
                lambda: _JACOBIAN_FORMULAS[ctx.kind](torch, omega), (omega,), grad
            )
            return cotangent, None
        return jac_backward(omega, grad, ctx.kind), None


def _jacobian(name: str) -> Any:
    kind = JACOBIAN_KINDS[name]

    def evaluation(xp: Any, omega: Tensor) -> Tensor:
        if torch.is_grad_enabled() and omega.requires_grad:
            j: Tensor = JacobianKernel.apply(omega, kind)  # type: ignore[no-untyped-call]
            return j
        return jac_forward(omega, kind)

    evaluation.__name__ = evaluation.__qualname__ = name
    evaluation.__doc__ = f":func:`diffquat._lie.{name}` through the C kernels."
    # Non-finite rows come out NaN by the same arithmetic as the core's (``|w|^2``, read by every entry).
    evaluation.handles_nonfinite = True  # type: ignore[attr-defined]
    return evaluation


so3_left_jacobian = _jacobian("so3_left_jacobian")
so3_right_jacobian = _jacobian("so3_right_jacobian")
so3_left_jacobian_inverse = _jacobian("so3_left_jacobian_inverse")
so3_right_jacobian_inverse = _jacobian("so3_right_jacobian_inverse")


# ---------------------------------------------------------------------------------------------------
# quaternion_plus (diffquat._lie): one kernel each way.


@functools.cache  # as _series
def _exp_table(dtype: torch.dtype) -> Tensor:
    """The core's ``exp_factors`` threshold and series for ``dtype``
    (:func:`diffquat._algebra.exp_series_table`), kept alive for the kernels' pointer."""
    return torch.tensor(_algebra.exp_series_table(torch, dtype), dtype=torch.float64)


def _rows(q: Tensor, delta: Tensor) -> tuple[torch.Size, Tensor, Tensor]:
    """The broadcast batch shape of ``q`` (..., 4) and ``delta`` (..., 3), and both as rows of it
    (expanded views where the batch shapes differ: the kernels read a stride of 0 in place)."""
    batch = q.shape[:-1]
    if delta.shape[:-1] != batch:
        batch = torch.broadcast_shapes(batch, delta.shape[:-1])  # type: ignore[no-untyped-call]
        q, delta = q.expand(*batch, 4), delta.expand(*batch, 3)
    return batch, q.reshape(-1, 4), delta.reshape(-1, 3)


def qplus_forward(q: Tensor, delta: Tensor, first: bool, right: bool) -> Tensor:
    """``q exp(d)`` or ``exp(d) q`` as unit quaternions in ``q``'s storage order, one kernel."""
    batch, rows, d = _rows(q, delta)
    out = torch.empty((rows.shape[0], 4), dtype=q.dtype, device=q.device)
    if rows.shape[0]:
        (row, component), (d_row, d_component) = rows.stride(), d.stride()
        _kernels.qplus_forward(
            _DTYPE[q.dtype], torch.get_num_threads(), rows.shape[0], first, right,
            rows.data_ptr(), row, component, d.data_ptr(), d_row, d_component,
            _exp_table(q.dtype).data_ptr(), out.data_ptr(),
        )  # fmt: skip
    return out.reshape(*batch, 4)


def qplus_backward(q: Tensor, delta: Tensor, grad: Tensor, first: bool, right: bool) -> tuple[Tensor, Tensor]:
    """``(dL/dq, dL/dd)`` from ``dL/dout``, one kernel, each summed over the batch dimensions its
    argument was broadcast along."""
    _, rows, d = _rows(q, delta)
    g = grad.reshape(-1, 4)
    out_q = torch.empty((rows.shape[0], 4), dtype=q.dtype, device=q.device)
    out_d = torch.empty((rows.shape[0], 3), dtype=q.dtype, device=q.device)
    if rows.shape[0]:
        (row, component), (d_row, d_component), (g_row, g_component) = rows.stride(), d.stride(), g.stride()
        _kernels.qplus_backward(
            _DTYPE[q.dtype], torch.get_num_threads(), rows.shape[0], first, right,
            rows.data_ptr(), row, component, d.data_ptr(), d_row, d_component,
            g.data_ptr(), g_row, g_component, _exp_table(q.dtype).data_ptr(),
            out_q.data_ptr(), out_d.data_ptr(),
        )  # fmt: skip
    batch = grad.shape[:-1]
    return out_q.reshape(*batch, 4).sum_to_size(q.shape), out_d.reshape(*batch, 3).sum_to_size(delta.shape)


class QuaternionPlusKernel(torch.autograd.Function):
    """No ``jvp``: :mod:`._dispatch` gives forward-mode AD the formula."""

    @staticmethod
    def forward(ctx: Any, q: Tensor, delta: Tensor, first: bool, right: bool) -> Tensor:
        ctx.first, ctx.right = first, right
        ctx.save_for_backward(q, delta)
        return qplus_forward(q, delta, first, right)

    @staticmethod
    def backward(ctx: Any, grad: Tensor) -> tuple[Tensor | None, Tensor | None, None, None]:
        q, delta = ctx.saved_tensors
        if torch.is_grad_enabled() or not _plain(grad, q):
            side = "right" if ctx.right else "left"
            dq, dd = _formula_cotangents(
                lambda: _lie.quaternion_plus(torch, q, delta, side=side, scalar_first=ctx.first),
                (q, delta),
                grad,
            )
            return dq, dd, None, None
        dq, dd = qplus_backward(q, delta, grad, ctx.first, ctx.right)
        return dq, dd, None, None


def quaternion_plus(
    xp: Any, q: Tensor, delta: Tensor, *, side: str = "right", scalar_first: bool = True
) -> Tensor:
    """:func:`diffquat._lie.quaternion_plus` through the C kernels."""
    right = _lie.check_side("quaternion_plus", side)
    if torch.is_grad_enabled() and (q.requires_grad or delta.requires_grad):
        out: Tensor = QuaternionPlusKernel.apply(q, delta, scalar_first, right)  # type: ignore[no-untyped-call]
        return out
    return qplus_forward(q, delta, scalar_first, right)


# Non-finite rows come out NaN by the core's arithmetic (the norm of q, the angle of d).
quaternion_plus.handles_nonfinite = True  # type: ignore[attr-defined]
