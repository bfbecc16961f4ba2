"""``quaternion_to_matrix`` and ``matrix_to_quaternion`` on CUDA as Triton kernels: one kernel
forward, one backward, each.

Each program reads a block of quaternions (16 bytes each) and writes their matrices (36 bytes), or the
other way round: the whole conversion is one pass over memory, as is the backward (reads the input, the
saved output where needed and the output's cotangent, writes the input's). The math is the core's:
``quaternion_to_matrix`` scales by ``s = 2 / |q|^2`` (the zero-quaternion rule of the torch fused
path) and its backward is ``s ((H + H^T) q - s (q^T H q) q)`` with ``H + H^T`` written out entry by
entry; ``matrix_to_quaternion`` is the core's candidate selection and canonical sign, and its backward
is ``_core.matrix_to_quaternion_cotangent`` written out. Only imported where Triton is; used only for
CUDA tensors in eager mode (tests run it on the CPU under ``TRITON_INTERPRET=1``). The backward kernels
are not differentiable again: when a double backward is being recorded (``create_graph=True``), the
backward runs the differentiable torch formula instead.
"""

from __future__ import annotations

from typing import Any

import torch
import triton
import triton.language as tl
from torch import Tensor

from .. import _core
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


@triton.jit  # type: ignore[untyped-decorator]
def _load_matrix(m_ptr: Any, i: Any, mask: Any) -> Any:
    m = m_ptr + 9 * i
    m00 = tl.load(m, mask=mask, other=1.0)  # masked lanes see the identity: every value stays finite
    m01 = tl.load(m + 1, mask=mask, other=0.0)
    m02 = tl.load(m + 2, mask=mask, other=0.0)
    m10 = tl.load(m + 3, mask=mask, other=0.0)
    m11 = tl.load(m + 4, mask=mask, other=1.0)
    m12 = tl.load(m + 5, mask=mask, other=0.0)
    m20 = tl.load(m + 6, mask=mask, other=0.0)
    m21 = tl.load(m + 7, mask=mask, other=0.0)
    m22 = tl.load(m + 8, mask=mask, other=1.0)
    return m00, m01, m02, m10, m11, m12, m20, m21, m22


@triton.jit  # type: ignore[untyped-decorator]
def _pivots(m00: Any, m11: Any, m22: Any) -> Any:
    t0 = 1.0 + m00 + m11 + m22
    t1 = 1.0 + m00 - m11 - m22
    t2 = 1.0 - m00 + m11 - m22
    t3 = 1.0 - m00 - m11 + m22
    high01, high23 = tl.maximum(t0, t1), tl.maximum(t2, t3)
    # the core's choice: the larger pair, then the larger of it, ties to the lower index
    return t0, t1, t2, t3, high01 >= high23, t0 >= t1, t2 >= t3, tl.maximum(high01, high23)


@triton.jit  # type: ignore[untyped-decorator]
def _pick(use01: Any, use0: Any, use2: Any, a: Any, b: Any, c: Any, d: Any) -> Any:
    return tl.where(use01, tl.where(use0, a, b), tl.where(use2, c, d))


@triton.jit  # type: ignore[untyped-decorator]
def _m2q_forward_kernel(m_ptr: Any, out_ptr: Any, n: Any, block: tl.constexpr) -> None:
    i = tl.program_id(0) * block + tl.arange(0, block)
    mask = i < n
    m00, m01, m02, m10, m11, m12, m20, m21, m22 = _load_matrix(m_ptr, i, mask)
    t0, t1, t2, t3, use01, use0, use2, _ = _pivots(m00, m11, m22)
    wx, wy, wz = m21 - m12, m02 - m20, m10 - m01
    xy, xz, yz = m01 + m10, m02 + m20, m12 + m21
    w = _pick(use01, use0, use2, t0, wx, wy, wz)
    x = _pick(use01, use0, use2, wx, t1, xy, xz)
    y = _pick(use01, use0, use2, wy, xy, t2, yz)
    z = _pick(use01, use0, use2, wz, xz, yz, t3)
    inv = 1.0 / tl.sqrt(w * w + x * x + y * y + z * z)
    negative = (w < 0) | ((w == 0) & ((x < 0) | ((x == 0) & ((y < 0) | ((y == 0) & (z < 0))))))
    inv = tl.where(negative, -inv, inv)
    o = out_ptr + 4 * i
    tl.store(o, w * inv, mask=mask)
    tl.store(o + 1, x * inv, mask=mask)
    tl.store(o + 2, y * inv, mask=mask)
    tl.store(o + 3, z * inv, mask=mask)


@triton.jit  # type: ignore[untyped-decorator]
def _m2q_backward_kernel(
    m_ptr: Any, q_ptr: Any, g_ptr: Any, out_ptr: Any, n: Any, block: tl.constexpr
) -> None:
    i = tl.program_id(0) * block + tl.arange(0, block)
    mask = i < n
    # the choice needs only the diagonal (masked lanes see the identity)
    m00 = tl.load(m_ptr + 9 * i, mask=mask, other=1.0)
    m11 = tl.load(m_ptr + 9 * i + 4, mask=mask, other=1.0)
    m22 = tl.load(m_ptr + 9 * i + 8, mask=mask, other=1.0)
    _, _, _, _, use01, use0, use2, largest = _pivots(m00, m11, m22)
    w, x, y, z = _load_quaternion(q_ptr, i, mask)
    gw, gx, gy, gz = _load_quaternion(g_ptr, i, mask)
    # the scale +-1/|c| read back from q: component k of candidate k is the pivot t_k
    inv = _pick(use01, use0, use2, w, x, y, z) / largest
    dot = w * gw + x * gx + y * gy + z * gz
    gw, gx, gy, gz = inv * (gw - w * dot), inv * (gx - x * dot), inv * (gy - y * dot), inv * (gz - z * dot)
    k0, k1 = use01 & use0, use01 & ~use0
    k2, k3 = ~use01 & use2, ~use01 & ~use2
    tw, tx = tl.where(k0, gw, 0.0), tl.where(k1, gx, 0.0)
    ty, tz = tl.where(k2, gy, 0.0), tl.where(k3, gz, 0.0)
    cwx = tl.where(k0, gx, 0.0) + tl.where(k1, gw, 0.0)
    cwy = tl.where(k0, gy, 0.0) + tl.where(k2, gw, 0.0)
    cwz = tl.where(k0, gz, 0.0) + tl.where(k3, gw, 0.0)
    cxy = tl.where(k1, gy, 0.0) + tl.where(k2, gx, 0.0)
    cxz = tl.where(k1, gz, 0.0) + tl.where(k3, gx, 0.0)
    cyz = tl.where(k2, gz, 0.0) + tl.where(k3, gy, 0.0)
    o = out_ptr + 9 * i
    tl.store(o, tw + tx - ty - tz, mask=mask)
    tl.store(o + 1, cxy - cwz, mask=mask)
    tl.store(o + 2, cwy + cxz, mask=mask)
    tl.store(o + 3, cwz + cxy, mask=mask)
    tl.store(o + 4, tw - tx + ty - tz, mask=mask)
    tl.store(o + 5, cyz - cwx, mask=mask)
    tl.store(o + 6, cxz - cwy, mask=mask)
    tl.store(o + 7, cwx + cyz, mask=mask)
    tl.store(o + 8, tw - tx - ty + tz, mask=mask)


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


def m2q_forward(matrix: Tensor) -> Tensor:
    """(..., 3, 3) to scalar-first quaternions (..., 4) in one kernel."""
    flat = matrix.reshape(-1, 9).contiguous()
    out = torch.empty((flat.shape[0], 4), dtype=matrix.dtype, device=matrix.device)
    n = flat.shape[0]
    _m2q_forward_kernel[_grid(n)](flat, out, n, block=BLOCK)
    return out.reshape(*matrix.shape[:-2], 4)


def m2q_backward(matrix: Tensor, q: Tensor, grad: Tensor) -> Tensor:
    """``dL/dmatrix`` from the matrix, its quaternion ``q`` and ``dL/dq``, in one kernel."""
    flat = matrix.reshape(-1, 9).contiguous()
    out = torch.empty_like(flat)
    n = flat.shape[0]
    q_flat, g_flat = q.reshape(-1, 4).contiguous(), grad.reshape(-1, 4).contiguous()
    _m2q_backward_kernel[_grid(n)](flat, q_flat, g_flat, out, n, block=BLOCK)
    return out.reshape(matrix.shape)


class MatrixToQuaternion(torch.autograd.Function):
    @staticmethod
    def forward(matrix: Tensor) -> Tensor:
        return m2q_forward(matrix)

    @staticmethod
    def setup_context(ctx: Any, inputs: tuple[Tensor], output: Tensor) -> None:
        ctx.save_for_backward(inputs[0], output)

    @staticmethod
    def backward(ctx: Any, grad: Tensor) -> Tensor:
        matrix, q = ctx.saved_tensors
        if torch.is_grad_enabled() and (matrix.requires_grad or grad.requires_grad):
            return _core.matrix_to_quaternion_cotangent(torch, matrix, q, grad)  # recorded
        return m2q_backward(matrix, q, grad)


def matrix_to_quaternion(xp: Any, matrix: Tensor, *, scalar_first: bool = True) -> Tensor:
    """:func:`diffquat._core.matrix_to_quaternion` as Triton kernels (same name: the backend validates
    by it)."""
    q: Tensor = MatrixToQuaternion.apply(matrix)  # type: ignore[no-untyped-call]
    return q if scalar_first else q[..., _fused.TO_LAST]
