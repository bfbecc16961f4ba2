"""``quaternion_to_matrix`` and ``matrix_to_quaternion`` on CUDA as Triton kernels: one kernel
forward, one backward, each, in either component order.

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

Memory access: a block is read and written as whole tiles, ``(BLOCK, 4)`` for quaternions and
``(BLOCK, 16)`` masked to 9 columns for matrices, and split into (or joined from) one register per
component. One strided load or store per component instead, the obvious form, touches every 32-byte
sector of the block once per component: measured on an H100, the forward of
``quaternion_to_matrix`` then moved 17% of the device-to-device copy bandwidth, and with tiles 85%
(``benchmarks/RESULTS.md``). The kernels take no type annotations: Triton resolves them as globals at
compile time and refuses ``Any``.
"""

from __future__ import annotations

from typing import Any

import torch
import triton
import triton.language as tl
from torch import Tensor

from .. import _core

# Rows per program and warps per program: the fastest of 128-1024 rows x 4 or 8 warps at N = 16M on
# an H100 for all four kernels (84-96% of the copy bandwidth; 1024 rows with 4 warps fell to 44%).
BLOCK = 256
NUM_WARPS = 8


@triton.jit
def _rows(block: tl.constexpr, WIDE: tl.constexpr):
    """This program's rows, in int64 where element offsets (9 per row) would pass 2^31 in int32."""
    first = tl.program_id(0)
    if WIDE:
        first = first.to(tl.int64)
    return first * block + tl.arange(0, block)


@triton.jit
def _load_quaternion(ptr, rows, n, FIRST: tl.constexpr):
    """Components (w, x, y, z) of rows ``rows`` of an (n, 4) array in either order; 0 past ``n``."""
    t = tl.load(ptr + rows[:, None] * 4 + tl.arange(0, 4)[None, :], mask=rows[:, None] < n, other=0.0)
    even, odd = tl.split(tl.reshape(t, (rows.shape[0], 2, 2)))  # (c0, c2) and (c1, c3)
    c0, c2 = tl.split(even)
    c1, c3 = tl.split(odd)
    if FIRST:
        return c0, c1, c2, c3
    else:
        return c3, c0, c1, c2


@triton.jit
def _store_quaternion(ptr, rows, n, w, x, y, z, FIRST: tl.constexpr):
    # join appends an axis: join(join(a, c), join(b, d)) reshaped row-major is (a, b, c, d)
    if FIRST:  # noqa: SIM108  (a compile-time branch, as in _load_quaternion)
        t = tl.join(tl.join(w, y), tl.join(x, z))
    else:
        t = tl.join(tl.join(x, z), tl.join(y, w))
    t = tl.reshape(t, (rows.shape[0], 4))
    tl.store(ptr + rows[:, None] * 4 + tl.arange(0, 4)[None, :], t, mask=rows[:, None] < n)


@triton.jit
def _load_matrix(ptr, rows, n):
    """Entries m00 .. m22 of rows ``rows`` of an (n, 9) array; 0 past ``n`` (every value stays finite
    there: the zero matrix picks the w candidate, of norm 1)."""
    cols = tl.arange(0, 16)
    mask = (rows[:, None] < n) & (cols[None, :] < 9)
    t = tl.load(ptr + rows[:, None] * 9 + cols[None, :], mask=mask, other=0.0)
    # column 8 a + 4 b + 2 c + d of the tile is t[:, a, b, c, d]; split takes the last axis first
    e, o = tl.split(tl.reshape(t, (rows.shape[0], 2, 2, 2, 2)))  # columns 2k, 2k + 1
    e0, e1 = tl.split(e)  # 4k, 4k + 2
    o0, o1 = tl.split(o)  # 4k + 1, 4k + 3
    e00, e01 = tl.split(e0)  # 8k, 8k + 4
    e10, e11 = tl.split(e1)  # 8k + 2, 8k + 6
    o00, o01 = tl.split(o0)  # 8k + 1, 8k + 5
    o10, o11 = tl.split(o1)  # 8k + 3, 8k + 7
    m0, m8 = tl.split(e00)
    m4, _ = tl.split(e01)
    m2, _ = tl.split(e10)
    m6, _ = tl.split(e11)
    m1, _ = tl.split(o00)
    m5, _ = tl.split(o01)
    m3, _ = tl.split(o10)
    m7, _ = tl.split(o11)
    return m0, m1, m2, m3, m4, m5, m6, m7, m8


@triton.jit
def _store_matrix(ptr, rows, n, m0, m1, m2, m3, m4, m5, m6, m7, m8):
    # The inverse of _load_matrix's splits: the first join makes the most significant bit of the
    # column (8), the last the least (1). Columns 9-15 are masked off.
    zero = tl.zeros_like(m0)
    a0, a1, a2, a3 = tl.join(m0, m8), tl.join(m1, zero), tl.join(m2, zero), tl.join(m3, zero)
    a4, a5, a6, a7 = tl.join(m4, zero), tl.join(m5, zero), tl.join(m6, zero), tl.join(m7, zero)
    b0, b1, b2, b3 = tl.join(a0, a4), tl.join(a1, a5), tl.join(a2, a6), tl.join(a3, a7)
    c0, c1 = tl.join(b0, b2), tl.join(b1, b3)
    t = tl.reshape(tl.join(c0, c1), (rows.shape[0], 16))
    cols = tl.arange(0, 16)
    mask = (rows[:, None] < n) & (cols[None, :] < 9)
    tl.store(ptr + rows[:, None] * 9 + cols[None, :], t, mask=mask)


@triton.jit
def _scale(w, x, y, z, TINY: tl.constexpr):
    n2 = w * w + x * x + y * y + z * z
    return tl.where(n2 >= TINY, 2.0 / tl.maximum(n2, TINY), 0.0)


@triton.jit
def _q2m_forward_kernel(
    q_ptr, out_ptr, n, TINY: tl.constexpr, FIRST: tl.constexpr, WIDE: tl.constexpr, block: tl.constexpr
):
    rows = _rows(block, WIDE)
    w, x, y, z = _load_quaternion(q_ptr, rows, n, FIRST)
    s = _scale(w, x, y, z, TINY)
    sx, sy, sz = s * x, s * y, s * z
    xx, yy, zz = sx * x, sy * y, sz * z
    xy, xz, yz = sx * y, sx * z, sy * z
    wx, wy, wz = sx * w, sy * w, sz * w
    # a non-finite component makes the whole row NaN (diffquat._backend.nonfinite_rows): a value
    # times 0 is 0 when finite, NaN otherwise
    ok = w * 0.0 + x * 0.0 + y * 0.0 + z * 0.0 == 0.0
    _store_matrix(
        out_ptr, rows, n,
        _ok(ok, 1.0 - (yy + zz)), _ok(ok, xy - wz), _ok(ok, xz + wy),
        _ok(ok, xy + wz), _ok(ok, 1.0 - (xx + zz)), _ok(ok, yz - wx),
        _ok(ok, xz - wy), _ok(ok, yz + wx), _ok(ok, 1.0 - (xx + yy)),
    )  # fmt: skip


@triton.jit
def _ok(ok, value):
    return tl.where(ok, value, float("nan"))


@triton.jit
def _q2m_backward_kernel(
    q_ptr, g_ptr, out_ptr, n, TINY: tl.constexpr, FIRST: tl.constexpr, WIDE: tl.constexpr, block: tl.constexpr
):
    rows = _rows(block, WIDE)
    w, x, y, z = _load_quaternion(q_ptr, rows, n, FIRST)
    g00, g01, g02, g10, g11, g12, g20, g21, g22 = _load_matrix(g_ptr, rows, n)
    s = _scale(w, x, y, z, TINY)
    # B = H + H^T, H = dL/dP for P = (s q) q^T (B_ww = 0).
    bxx, byy, bzz = -2.0 * (g11 + g22), -2.0 * (g00 + g22), -2.0 * (g00 + g11)
    bxy, bxz, byz = g01 + g10, g02 + g20, g12 + g21
    bwx, bwy, bwz = g21 - g12, g02 - g20, g10 - g01
    hw = bwx * x + bwy * y + bwz * z
    hx = bwx * w + bxx * x + bxy * y + bxz * z
    hy = bwy * w + bxy * x + byy * y + byz * z
    hz = bwz * w + bxz * x + byz * y + bzz * z
    half = 0.5 * s * (w * hw + x * hx + y * hy + z * hz)
    gw, gx, gy, gz = s * (hw - half * w), s * (hx - half * x), s * (hy - half * y), s * (hz - half * z)
    _store_quaternion(out_ptr, rows, n, gw, gx, gy, gz, FIRST)


@triton.jit
def _pivots(m00, m11, m22, one):
    t0 = one + m00 + m11 + m22
    t1 = one + m00 - m11 - m22
    t2 = one - m00 + m11 - m22
    t3 = one - m00 - m11 + m22
    high01, high23 = tl.maximum(t0, t1), tl.maximum(t2, t3)
    # the core's choice: the larger pair, then the larger of it, ties to the lower index
    return t0, t1, t2, t3, high01 >= high23, t0 >= t1, t2 >= t3, tl.maximum(high01, high23)


@triton.jit
def _pick(use01, use0, use2, a, b, c, d):
    return tl.where(use01, tl.where(use0, a, b), tl.where(use2, c, d))


@triton.jit
def _m2q_forward_kernel(m_ptr, out_ptr, n, FIRST: tl.constexpr, WIDE: tl.constexpr, block: tl.constexpr):
    rows = _rows(block, WIDE)
    m00, m01, m02, m10, m11, m12, m20, m21, m22 = _load_matrix(m_ptr, rows, n)
    ok = (
        m00 * 0.0
        + m01 * 0.0
        + m02 * 0.0
        + m10 * 0.0
        + m11 * 0.0
        + m12 * 0.0
        + m20 * 0.0
        + m21 * 0.0
        + m22 * 0.0
    ) == 0.0
    # a quarter of the matrix (exact): sums of four quarters cannot overflow (_core._quarter)
    m00, m01, m02, m10, m11, m12 = 0.25 * m00, 0.25 * m01, 0.25 * m02, 0.25 * m10, 0.25 * m11, 0.25 * m12
    m20, m21, m22 = 0.25 * m20, 0.25 * m21, 0.25 * m22
    t0, t1, t2, t3, use01, use0, use2, _ = _pivots(m00, m11, m22, 0.25)
    wx, wy, wz = m21 - m12, m02 - m20, m10 - m01
    xy, xz, yz = m01 + m10, m02 + m20, m12 + m21
    w = _pick(use01, use0, use2, t0, wx, wy, wz)
    x = _pick(use01, use0, use2, wx, t1, xy, xz)
    y = _pick(use01, use0, use2, wy, xy, t2, yz)
    z = _pick(use01, use0, use2, wz, xz, yz, t3)
    # divided by the largest component first (_core._m2q_unit): the squares cannot overflow
    big = tl.maximum(tl.maximum(tl.abs(w), tl.abs(x)), tl.maximum(tl.abs(y), tl.abs(z)))
    w, x, y, z = w / big, x / big, y / big, z / big
    inv = 1.0 / tl.sqrt(w * w + x * x + y * y + z * z)
    negative = (w < 0) | ((w == 0) & ((x < 0) | ((x == 0) & ((y < 0) | ((y == 0) & (z < 0))))))
    inv = tl.where(negative, -inv, inv)
    inv = tl.where(ok, inv, float("nan"))  # a non-finite entry makes the whole row NaN
    _store_quaternion(out_ptr, rows, n, w * inv, x * inv, y * inv, z * inv, FIRST)


@triton.jit
def _m2q_backward_kernel(
    m_ptr, q_ptr, g_ptr, out_ptr, n, FIRST: tl.constexpr, WIDE: tl.constexpr, block: tl.constexpr
):
    rows = _rows(block, WIDE)
    mask = rows < n
    # the choice needs only the diagonal (masked lanes see the identity); three strided loads: the
    # whole matrix is read in the same sectors anyway (measured 96% of the copy bandwidth)
    m00 = tl.load(m_ptr + 9 * rows, mask=mask, other=1.0)
    m11 = tl.load(m_ptr + 9 * rows + 4, mask=mask, other=1.0)
    m22 = tl.load(m_ptr + 9 * rows + 8, mask=mask, other=1.0)
    _, _, _, _, use01, use0, use2, largest = _pivots(m00, m11, m22, 1.0)
    w, x, y, z = _load_quaternion(q_ptr, rows, n, FIRST)
    gw, gx, gy, gz = _load_quaternion(g_ptr, rows, n, FIRST)
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
    _store_matrix(
        out_ptr, rows, n,
        tw + tx - ty - tz, cxy - cwz, cwy + cxz,
        cwz + cxy, tw - tx + ty - tz, cyz - cwx,
        cxz - cwy, cwx + cyz, tw - tx - ty + tz,
    )  # fmt: skip


def _grid(n: int) -> tuple[int]:
    return (triton.cdiv(n, BLOCK),)


# Batches from this many rotations index their elements in int64: 9 n element offsets reach 2^31
# there (about 238 million matrices, 8.6 GB in float32), where int32 offsets wrap to other memory.
WIDE_FROM = 2**31 // 9


def _wide(n: int) -> bool:
    return n >= WIDE_FROM


def _tiny(dtype: torch.dtype) -> float:
    """The smallest normal number of ``dtype``, passed as a constexpr: a float kernel argument is
    float32, where float64's (2^-1022) would be 0, and the zero quaternion would give NaN."""
    return torch.finfo(dtype).tiny


def q2m_forward(q: Tensor, scalar_first: bool = True) -> Tensor:
    """``q`` (..., 4) in either order to (..., 3, 3) in one kernel."""
    flat = q.reshape(-1, 4).contiguous()
    out = torch.empty((flat.shape[0], 9), dtype=q.dtype, device=q.device)
    n = flat.shape[0]
    _q2m_forward_kernel[_grid(n)](
        flat, out, n, TINY=_tiny(q.dtype), FIRST=scalar_first, WIDE=_wide(n), block=BLOCK, num_warps=NUM_WARPS
    )
    return out.reshape(*q.shape[:-1], 3, 3)


def q2m_backward(q: Tensor, grad: Tensor, scalar_first: bool = True) -> Tensor:
    """``dL/dq`` from ``q`` (..., 4) and ``dL/dR`` (..., 3, 3) in one kernel."""
    flat = q.reshape(-1, 4).contiguous()
    g = grad.reshape(-1, 9).contiguous()
    out = torch.empty_like(flat)
    n = flat.shape[0]
    _q2m_backward_kernel[_grid(n)](
        flat,
        g,
        out,
        n,
        TINY=_tiny(q.dtype),
        FIRST=scalar_first,
        WIDE=_wide(n),
        block=BLOCK,
        num_warps=NUM_WARPS,
    )
    return out.reshape(q.shape)


class QuaternionToMatrix(torch.autograd.Function):
    @staticmethod
    def forward(q: Tensor, scalar_first: bool) -> Tensor:
        return q2m_forward(q, scalar_first)

    @staticmethod
    def setup_context(ctx: Any, inputs: tuple[Tensor, bool], output: Tensor) -> None:
        ctx.save_for_backward(inputs[0])
        ctx.save_for_forward(inputs[0])
        ctx.scalar_first = inputs[1]

    @staticmethod
    def backward(ctx: Any, grad: Tensor) -> tuple[Tensor, None]:
        (q,) = ctx.saved_tensors
        first = ctx.scalar_first
        if torch.is_grad_enabled() and (q.requires_grad or grad.requires_grad):
            # recorded for a double backward: the core's cotangent, which differentiates again
            q1 = q if first else _core.xyzw_to_wxyz(torch, q)
            cotangent = _core.quaternion_to_matrix_cotangent(torch, q1, grad)
            return (cotangent if first else _core.wxyz_to_xyzw(torch, cotangent)), None
        return q2m_backward(q, grad, first), None

    @staticmethod
    def jvp(ctx: Any, tangent: Tensor, _: None) -> Tensor:
        (q,) = ctx.saved_tensors
        r: Tensor = _core.quaternion_to_matrix_tangent(torch, q, tangent, scalar_first=ctx.scalar_first)
        return r


def quaternion_to_matrix(xp: Any, q: Tensor, *, scalar_first: bool = True) -> Tensor:
    """:func:`diffquat._core.quaternion_to_matrix` as Triton kernels (same name: the backend validates
    by it)."""
    return QuaternionToMatrix.apply(q, scalar_first)  # type: ignore[no-untyped-call]


def m2q_forward(matrix: Tensor, scalar_first: bool = True) -> Tensor:
    """(..., 3, 3) to quaternions (..., 4) in either order in one kernel."""
    flat = matrix.reshape(-1, 9).contiguous()
    out = torch.empty((flat.shape[0], 4), dtype=matrix.dtype, device=matrix.device)
    n = flat.shape[0]
    _m2q_forward_kernel[_grid(n)](
        flat, out, n, FIRST=scalar_first, WIDE=_wide(n), block=BLOCK, num_warps=NUM_WARPS
    )
    return out.reshape(*matrix.shape[:-2], 4)


def m2q_backward(matrix: Tensor, q: Tensor, grad: Tensor, scalar_first: bool = True) -> Tensor:
    """``dL/dmatrix`` from the matrix, its quaternion ``q`` and ``dL/dq``, in one kernel."""
    flat = matrix.reshape(-1, 9).contiguous()
    out = torch.empty_like(flat)
    n = flat.shape[0]
    q_flat, g_flat = q.reshape(-1, 4).contiguous(), grad.reshape(-1, 4).contiguous()
    _m2q_backward_kernel[_grid(n)](
        flat, q_flat, g_flat, out, n, FIRST=scalar_first, WIDE=_wide(n), block=BLOCK, num_warps=NUM_WARPS
    )
    return out.reshape(matrix.shape)


class MatrixToQuaternion(torch.autograd.Function):
    @staticmethod
    def forward(matrix: Tensor, scalar_first: bool) -> Tensor:
        return m2q_forward(matrix, scalar_first)

    @staticmethod
    def setup_context(ctx: Any, inputs: tuple[Tensor, bool], output: Tensor) -> None:
        ctx.save_for_backward(inputs[0], output)
        ctx.save_for_forward(inputs[0], output)
        ctx.scalar_first = inputs[1]

    @staticmethod
    def backward(ctx: Any, grad: Tensor) -> tuple[Tensor, None]:
        matrix, q = ctx.saved_tensors
        first = ctx.scalar_first
        if torch.is_grad_enabled() and (matrix.requires_grad or grad.requires_grad):
            # recorded for a double backward
            if not first:
                q, grad = _core.xyzw_to_wxyz(torch, q), _core.xyzw_to_wxyz(torch, grad)
            return _core.matrix_to_quaternion_cotangent(torch, matrix, q, grad), None
        return m2q_backward(matrix, q, grad, first), None

    @staticmethod
    def jvp(ctx: Any, tangent: Tensor, _: None) -> Tensor:
        matrix, q = ctx.saved_tensors
        dq: Tensor = _core.matrix_to_quaternion_tangent(
            torch, matrix, q, tangent, scalar_first=ctx.scalar_first
        )
        return dq


def matrix_to_quaternion(xp: Any, matrix: Tensor, *, scalar_first: bool = True) -> Tensor:
    """:func:`diffquat._core.matrix_to_quaternion` as Triton kernels (same name: the backend validates
    by it)."""
    return MatrixToQuaternion.apply(matrix, scalar_first)  # type: ignore[no-untyped-call]
