"""``quaternion_to_matrix`` on CUDA as Triton kernels: one kernel forward, one backward.

Each program reads a block of quaternions (16 bytes each) and writes their matrices (36 bytes): the
whole conversion is one pass over memory, as is the backward (reads q and dL/dR, writes dL/dq). The
math is that of :mod:`diffquat._fused` (same products, same zero-quaternion rule); the backward is its
``s ((H + H^T) q - s (q^T H q) q)`` with ``H + H^T`` written out entry by entry. Only imported where
Triton is; used only for CUDA tensors in eager mode (tests run it on the CPU under ``TRITON_INTERPRET=1``).
The backward kernel is not differentiable again: when a double backward is being recorded
(``create_graph=True``), the backward runs the differentiable formula of the torch fused path instead.
"""

from __future__ import annotations

from typing import Any

import torch
import triton
import triton.language as tl
from torch import Tensor

from . import _fused

BLOCK = 256


@triton.jit  # type: ignore[untyped-decorator]
def _scale(w: Any, x: Any, y: Any, z: Any, tiny: Any) -> Any:
    n2 = w * w + x * x + y * y + z * z
    return tl.where(n2 >= tiny, 2.0 / tl.maximum(n2, tiny), 0.0)


@triton.jit  # type: ignore[untyped-decorator]
def _load_quaternion(q_ptr: Any, i: Any, mask: Any) -> Any:
    w = tl.load(q_ptr + 4 * i, mask=mask, other=0.0)
    x = tl.load(q_ptr + 4 * i + 1, mask=mask, other=0.0)
    y = tl.load(q_ptr + 4 * i + 2, mask=mask, other=0.0)
    z = tl.load(q_ptr + 4 * i + 3, mask=mask, other=0.0)
    return w, x, y, z


@triton.jit  # type: ignore[untyped-decorator]
def _q2m_forward_kernel(q_ptr: Any, out_ptr: Any, n: Any, tiny: Any, block: tl.constexpr) -> None:
    i = tl.program_id(0) * block + tl.arange(0, block)
    mask = i < n
    w, x, y, z = _load_quaternion(q_ptr, i, mask)
    s = _scale(w, x, y, z, tiny)
    sx, sy, sz = s * x, s * y, s * z
    xx, yy, zz = sx * x, sy * y, sz * z
    xy, xz, yz = sx * y, sx * z, sy * z
    wx, wy, wz = sx * w, sy * w, sz * w
    o = out_ptr + 9 * i
    tl.store(o, 1.0 - (yy + zz), mask=mask)
    tl.store(o + 1, xy - wz, mask=mask)
    tl.store(o + 2, xz + wy, mask=mask)
    tl.store(o + 3, xy + wz, mask=mask)
    tl.store(o + 4, 1.0 - (xx + zz), mask=mask)
    tl.store(o + 5, yz - wx, mask=mask)
    tl.store(o + 6, xz - wy, mask=mask)
    tl.store(o + 7, yz + wx, mask=mask)
    tl.store(o + 8, 1.0 - (xx + yy), mask=mask)


@triton.jit  # type: ignore[untyped-decorator]
def _q2m_backward_kernel(
    q_ptr: Any, g_ptr: Any, out_ptr: Any, n: Any, tiny: Any, block: tl.constexpr
) -> None:
    i = tl.program_id(0) * block + tl.arange(0, block)
    mask = i < n
    w, x, y, z = _load_quaternion(q_ptr, i, mask)
    g = g_ptr + 9 * i
    g00 = tl.load(g, mask=mask, other=0.0)
    g01 = tl.load(g + 1, mask=mask, other=0.0)
    g02 = tl.load(g + 2, mask=mask, other=0.0)
    g10 = tl.load(g + 3, mask=mask, other=0.0)
    g11 = tl.load(g + 4, mask=mask, other=0.0)
    g12 = tl.load(g + 5, mask=mask, other=0.0)
    g20 = tl.load(g + 6, mask=mask, other=0.0)
    g21 = tl.load(g + 7, mask=mask, other=0.0)
    g22 = tl.load(g + 8, mask=mask, other=0.0)
    s = _scale(w, x, y, z, tiny)
    # B = H + H^T, H = dL/dP for P = (s q) q^T (B_ww = 0).
    bxx, byy, bzz = -2.0 * (g11 + g22), -2.0 * (g00 + g22), -2.0 * (g00 + g11)
    bxy, bxz, byz = g01 + g10, g02 + g20, g12 + g21
    bwx, bwy, bwz = g21 - g12, g02 - g20, g10 - g01
    hw = bwx * x + bwy * y + bwz * z
    hx = bwx * w + bxx * x + bxy * y + bxz * z
    hy = bwy * w + bxy * x + byy * y + byz * z
    hz = bwz * w + bxz * x + byz * y + bzz * z
    half = 0.5 * s * (w * hw + x * hx + y * hy + z * hz)
    o = out_ptr + 4 * i
    tl.store(o, s * (hw - half * w), mask=mask)
    tl.store(o + 1, s * (hx - half * x), mask=mask)
    tl.store(o + 2, s * (hy - half * y), mask=mask)
    tl.store(o + 3, s * (hz - half * z), mask=mask)


def _grid(n: int) -> tuple[int]:
    return (triton.cdiv(n, BLOCK),)


def q2m_forward(q: Tensor) -> Tensor:
    """Scalar-first ``q`` (..., 4) to (..., 3, 3) in one kernel."""
    flat = q.reshape(-1, 4).contiguous()
    out = torch.empty((flat.shape[0], 9), dtype=q.dtype, device=q.device)
    n = flat.shape[0]
    _q2m_forward_kernel[_grid(n)](flat, out, n, torch.finfo(q.dtype).tiny, block=BLOCK)
    return out.reshape(*q.shape[:-1], 3, 3)


def q2m_backward(q: Tensor, grad: Tensor) -> Tensor:
    """``dL/dq`` from ``q`` (..., 4) and ``dL/dR`` (..., 3, 3) in one kernel."""
    flat = q.reshape(-1, 4).contiguous()
    g = grad.reshape(-1, 9).contiguous()
    out = torch.empty_like(flat)
    n = flat.shape[0]
    _q2m_backward_kernel[_grid(n)](flat, g, out, n, torch.finfo(q.dtype).tiny, block=BLOCK)
    return out.reshape(q.shape)


class QuaternionToMatrix(torch.autograd.Function):
    @staticmethod
    def forward(q: Tensor) -> Tensor:
        return q2m_forward(q)

    @staticmethod
    def setup_context(ctx: Any, inputs: tuple[Tensor], output: Tensor) -> None:
        ctx.save_for_backward(inputs[0])

    @staticmethod
    def backward(ctx: Any, grad: Tensor) -> Tensor:
        (q,) = ctx.saved_tensors
        if torch.is_grad_enabled() and (q.requires_grad or grad.requires_grad):
            return _fused.q2m_backward(q, grad)  # recorded for a double backward
        return q2m_backward(q, grad)


def quaternion_to_matrix(xp: Any, q: Tensor, *, scalar_first: bool = True) -> Tensor:
    """:func:`diffquat._core.quaternion_to_matrix` as Triton kernels (same name: the backend validates
    by it)."""
    q_first = q if scalar_first else q[..., _fused.TO_FIRST]
    return QuaternionToMatrix.apply(q_first)  # type: ignore[no-untyped-call]
