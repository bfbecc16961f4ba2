"""The C kernels of ``quaternion_to_matrix``, ``matrix_to_quaternion``, the SO(3) Jacobians and
``quaternion_plus`` (diffquat/_kernels.c, bound for torch in diffquat/torch/_cpu.py and, all but the
first, for jax in diffquat/jax/_xla.py): what the shared matrix, tests/test_paths.py,
tests/test_lie.py and the jax tests do not already check through them.

The shared matrix runs every case, dtype, gradient and transform through the public torch functions,
which take the kernels for eager CPU tensors; tests/test_paths.py checks each evaluation against a
float64 reference and the derivatives' independence of the path. Here: that the extension is built at
all (a silent fallback would hide it), the strided inputs that the kernels read in place, batch
shapes, the split over threads, which calls take them, the portable (non-SIMD) build, and that the XLA
handlers declare XLA's FFI structures as jaxlib's header does.

CI runs these kernel tests twice: as built (on x86-64 with an AVX2 clone of every kernel, chosen at
load time), and once more, in a subprocess, with a portable build of the same source that the
compiler may not vectorise (``test_portable_build``): the suite must pass on any machine, and both
builds must give the same numbers, bit for bit, since both perform the same IEEE operations in the
same order (FMA contraction is off in both).
"""

from __future__ import annotations

import math
import shutil
import subprocess
import sysconfig
from pathlib import Path

import numpy as np
import pytest
import torch
from cases import CASES_BY_NAME, oracle_quaternion_to_matrix
from torch.autograd import forward_ad

import diffquat
import diffquat.torch as dq
from diffquat import _core, _lie
from diffquat.torch import _cpu, _dispatch


def test_the_extension_is_built() -> None:
    """pip builds the kernels wherever a C compiler is (pyproject.toml); on such a machine (CI's) a
    failed build must fail here, not fall back silently to the slower formula."""
    from diffquat import _kernels

    assert _dispatch._cpu is _cpu
    assert callable(_kernels.q2m_forward)
    assert _dispatch.quaternion_to_matrix(torch.zeros(4)) is _cpu.quaternion_to_matrix
    assert _dispatch.matrix_to_quaternion(torch.zeros(3, 3)) is _cpu.matrix_to_quaternion
    for name in _cpu.JACOBIAN_KINDS:
        assert getattr(_dispatch, name)(torch.zeros(3)) is getattr(_cpu, name)
    assert _dispatch.quaternion_plus(torch.zeros(4), torch.zeros(3)) is _cpu.quaternion_plus


def _quaternions(dtype: torch.dtype) -> torch.Tensor:
    """Every named quaternion case, the zero quaternion and norms from 1e-15 to 1e15 among them."""
    names = ("random", "identity", "half_turns", "near_half_turns", "near_identity", "norms", "zero")
    qs = [CASES_BY_NAME[name].quaternions("float64").reshape(-1, 4) for name in names]
    return torch.tensor(np.vstack(qs)).to(dtype)


def _matrices(dtype: torch.dtype) -> torch.Tensor:
    """Rotations of every unit case (half-turns with pivot ties among them), the same off SO(3), and
    arbitrary matrices."""
    names = ("random", "identity", "half_turns", "near_half_turns", "near_identity")
    q = np.vstack([CASES_BY_NAME[name].quaternions("float64").reshape(-1, 4) for name in names])
    rot = torch.tensor(oracle_quaternion_to_matrix(q))
    noise = torch.randn(rot.shape, generator=torch.Generator().manual_seed(5), dtype=torch.float64)
    arbitrary = torch.randn(9, 3, 3, generator=torch.Generator().manual_seed(6), dtype=torch.float64)
    return torch.cat([rot, rot + 0.05 * noise, arbitrary]).to(dtype)


def _rotation_vectors(dtype: torch.dtype) -> torch.Tensor:
    """Rotation vectors at every scale of the angle: 0, the series (below 1) down to 1e-12, both sides
    of its threshold, pi, past it up to 30, random ones, and non-finite ones."""
    angles = torch.tensor([0.0, 1e-12, 1e-6, 1e-3, 0.3, 1 - 1e-7, 1.0, 1 + 1e-7, 2.0, math.pi, 5.0, 30.0])
    axes = torch.randn(len(angles), 3, generator=torch.Generator().manual_seed(15), dtype=torch.float64)
    w = axes / axes.norm(dim=-1, keepdim=True) * angles[:, None]
    random = torch.randn(40, 3, generator=torch.Generator().manual_seed(16), dtype=torch.float64)
    bad = torch.tensor([[math.nan, 0.0, 0.0], [0.0, math.inf, 0.0], [-math.inf, 1.0, 2.0]])
    return torch.cat([w, random, bad]).to(dtype)


def _grad(fn: object, x: torch.Tensor, cot: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    x = x.detach().requires_grad_(True)
    out = fn(x)  # type: ignore[operator]
    (g,) = torch.autograd.grad(out, x, cot)
    return out.detach(), g


@pytest.mark.parametrize("dtype", [torch.float64, torch.float32], ids=str)
def test_strided_inputs_are_read_in_place(dtype: torch.dtype) -> None:
    """Inputs the kernels read through their strides without a copy (a slice, every other row, a
    transposed matrix, an expanded cotangent, scalar-last storage) give what contiguous copies give,
    values and gradients."""
    gen = torch.Generator().manual_seed(8)
    wide = torch.randn(40, 8, generator=gen, dtype=dtype)
    q = wide[::2, 2:6]  # rows 16 elements apart, components contiguous
    assert not q.is_contiguous()
    cot = torch.randn(20, 3, 3, generator=gen, dtype=dtype)
    for scalar_first in (True, False):
        strided = _grad(lambda t, s=scalar_first: dq.quaternion_to_matrix(t, scalar_first=s), q, cot)
        dense = _grad(
            lambda t, s=scalar_first: dq.quaternion_to_matrix(t, scalar_first=s), q.contiguous(), cot
        )
        for a, b in zip(strided, dense, strict=True):
            assert torch.equal(a, b)
    m = dq.quaternion_to_matrix(torch.randn(20, 4, generator=gen, dtype=dtype)) + 0.1
    cot4 = torch.randn(20, 4, generator=gen, dtype=dtype)
    wider = torch.randn(20, 3, 5, generator=gen, dtype=dtype)
    batch_last = torch.randn(3, 3, 20, generator=gen, dtype=dtype)
    for matrix in (m.mT, wider[:, :, 1:4], batch_last.permute(2, 0, 1)):
        assert not matrix.is_contiguous()
        strided = _grad(dq.matrix_to_quaternion, matrix, cot4)
        dense = _grad(dq.matrix_to_quaternion, matrix.contiguous(), cot4)
        for a, b in zip(strided, dense, strict=True):
            assert torch.equal(a, b)
    w_wide, w_batch_last = (
        torch.randn(40, 8, generator=gen, dtype=dtype),
        torch.randn(3, 20, generator=gen, dtype=dtype),
    )
    for w in (w_wide[::2, 3:6], w_batch_last.mT):
        assert not w.is_contiguous()
        for name in _cpu.JACOBIAN_KINDS:
            strided = _grad(getattr(dq, name), w, cot)
            dense = _grad(getattr(dq, name), w.contiguous(), cot)
            for a, b in zip(strided, dense, strict=True):
                assert torch.equal(a, b)
    # an expanded cotangent (stride 0, what .sum().backward() hands the Function)
    for fn, x in (
        (dq.quaternion_to_matrix, q),
        (dq.matrix_to_quaternion, m),
        (dq.so3_left_jacobian_inverse, w),
    ):
        a, b = x.detach().clone().requires_grad_(True), x.detach().clone().requires_grad_(True)
        fn(a).sum().backward()
        (fn(b) * 1.0).backward(torch.ones(fn(b).shape, dtype=dtype))
        assert a.grad is not None and b.grad is not None
        assert torch.equal(a.grad, b.grad)


# The Jacobian kernels against the formula in float64, in ulps of each row's scale: measured at most
# 1.2 (values) and 2.0 (gradients) in both dtypes. The forward evaluates the core's coefficients
# operation by operation (sin and cos from libm instead of torch's), the backward is their derivative
# written out, not autograd's sequence of operations: a few ulps, not bits.
JACOBIAN_ULPS = {"values": 4.0, "gradients": 6.0}


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64], ids=str)
@pytest.mark.parametrize("name", list(_cpu.JACOBIAN_KINDS))
def test_jacobian_kernels_against_a_float64_reference(name: str, dtype: torch.dtype) -> None:
    """Each Jacobian through its kernels (the public function's eager path, forward and backward) at
    every scale of the angle, against the formula in float64 on the same inputs differentiated by
    autograd: values within a few ulps of each row's largest entry, gradients within a few ulps of
    that times the cotangent's largest entry; non-finite rows NaN, value and gradient, and only they.
    (tests/test_lie.py checks the values against mpmath, and the float64 gradients against finite
    differences, through the same public functions.)"""
    w = _rotation_vectors(dtype)
    cot = torch.randn(len(w), 3, 3, generator=torch.Generator().manual_seed(17), dtype=torch.float64)
    wd = w.double().requires_grad_(True)
    ref = getattr(_lie, name)(torch, wd)
    (ref_grad,) = torch.autograd.grad(ref, wd, cot)
    out, grad = _grad(getattr(dq, name), w, cot.to(dtype))
    finite = torch.isfinite(w).all(dim=-1)
    assert out[~finite].isnan().all() and grad[~finite].isnan().all()
    assert out[finite].isfinite().all() and grad[finite].isfinite().all()
    eps = torch.finfo(dtype).eps
    scale = ref.detach()[finite].abs().amax(dim=(-1, -2))
    value_ulps = (out[finite].double() - ref.detach()[finite]).abs().amax(dim=(-1, -2)) / (eps * scale)
    grad_scale = cot[finite].abs().amax(dim=(-1, -2)) * scale
    grad_ulps = (grad[finite].double() - ref_grad[finite]).abs().amax(dim=-1) / (eps * grad_scale)
    assert value_ulps.max() <= JACOBIAN_ULPS["values"], float(value_ulps.max())
    assert grad_ulps.max() <= JACOBIAN_ULPS["gradients"], float(grad_ulps.max())


# quaternion_plus through its kernels against the formula in float64, in ulps of the scale of each row
# (values: 1; gradients: the cotangent's largest entry, over |q| for dL/dq): measured at most 3.1
# (values, float32), 3.3 (dL/dq) and 1.7 (dL/dd), the float32 formula's own errors being the same.
PLUS_ULPS = 6.0


def _plus_inputs(dtype: torch.dtype) -> tuple[torch.Tensor, torch.Tensor]:
    """Quaternions of every case (the zero quaternion and norms from 1e-15 to 1e15 among them), paired
    with rotation vectors at every scale of the angle (the series below sqrt(eps) in |d|^2 and the
    closed form above, up to 30 radians), a NaN and an infinity in each."""
    q = _quaternions(torch.float64)
    w = _rotation_vectors(torch.float64)
    n = max(len(q), len(w))
    q, w = q.repeat(n // len(q) + 1, 1)[:n], w.repeat(n // len(w) + 1, 1)[:n]
    q[-1, 2], q[-2, 0] = math.nan, math.inf
    return q.to(dtype), w.to(dtype)


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64], ids=str)
@pytest.mark.parametrize("side", ["right", "left"])
@pytest.mark.parametrize("scalar_first", [True, False], ids=["wxyz", "xyzw"])
def test_quaternion_plus_kernels_against_a_float64_reference(
    side: str, scalar_first: bool, dtype: torch.dtype
) -> None:
    """``quaternion_plus`` through its kernels (the public function's eager path), forward and backward,
    against the formula in float64 on the same inputs differentiated by autograd; NaN rows for a
    non-finite q or d, value and both gradients, and only there; the zero quaternion the identity with
    a zero gradient."""
    q, w = _plus_inputs(dtype)
    cot = torch.randn(len(q), 4, generator=torch.Generator().manual_seed(18), dtype=torch.float64)
    qd, wd = q.double().requires_grad_(True), w.double().requires_grad_(True)
    ref = _lie.quaternion_plus(torch, qd, wd, side=side, scalar_first=scalar_first)
    ref_q, ref_w = torch.autograd.grad(ref, (qd, wd), cot)
    qk, wk = q.clone().requires_grad_(True), w.clone().requires_grad_(True)
    out = dq.quaternion_plus(qk, wk, side=side, scalar_first=scalar_first)
    assert type(out.grad_fn).__name__ == "QuaternionPlusKernelBackward"
    gq, gw = torch.autograd.grad(out, (qk, wk), cot.to(dtype))
    bad = ~(torch.isfinite(q).all(-1) & torch.isfinite(w).all(-1))
    for x in (out, gq, gw):
        assert x[bad].isnan().all() and x[~bad].isfinite().all()
    eps = torch.finfo(dtype).eps
    # the zero quaternion underflows differently in the two dtypes: compared where both read it alike
    zero = (q.double() * q.double()).sum(-1) < torch.finfo(dtype).tiny
    good = ~bad & (zero == ((qd * qd).sum(-1) < torch.finfo(torch.float64).tiny))
    c = cot.abs().amax(-1)
    value = (out.detach().double() - ref.detach()).abs().amax(-1)[good] / eps
    grad_q = ((gq.double() - ref_q).abs().amax(-1) * qd.detach().norm(dim=-1) / c)[good & ~zero] / eps
    grad_w = ((gw.double() - ref_w).abs().amax(-1) / c)[good] / eps
    assert value.max() <= PLUS_ULPS, float(value.max())
    assert grad_q.max() <= PLUS_ULPS, float(grad_q.max())
    assert grad_w.max() <= PLUS_ULPS, float(grad_w.max())
    assert torch.equal(gq[zero & ~bad], torch.zeros_like(gq[zero & ~bad]))


def test_quaternion_plus_kernels_read_strided_and_broadcast_inputs() -> None:
    """Slices of one packed array, a rotation vector shared by the whole batch (an expanded view, stride
    0), and batch shapes that broadcast: the values and gradients of contiguous, materialised copies."""
    gen = torch.Generator().manual_seed(19)
    x = torch.randn(12, 7, generator=gen, dtype=torch.float64)
    shared = torch.randn(3, generator=gen, dtype=torch.float64)
    cot = torch.randn(12, 4, generator=gen, dtype=torch.float64)
    q2 = torch.randn(2, 1, 4, generator=gen, dtype=torch.float64)
    w2 = torch.randn(3, 3, generator=gen, dtype=torch.float64)
    cot2 = torch.randn(2, 3, 4, generator=gen, dtype=torch.float64)
    for (q, w, c), (qc, wc) in (
        ((x[:, :4], x[:, 4:], cot), (x[:, :4].contiguous(), x[:, 4:].contiguous())),
        ((x[:, :4], shared, cot), (x[:, :4].contiguous(), shared.expand(12, 3).contiguous())),
        ((q2, w2, cot2), (q2.expand(2, 3, 4).contiguous(), w2.expand(2, 3, 3).contiguous())),
    ):
        a = [t.detach().clone().requires_grad_(True) for t in (q, w)]
        b = [t.detach().clone().requires_grad_(True) for t in (qc, wc)]
        out_a, out_b = dq.quaternion_plus(*a), dq.quaternion_plus(*b)
        assert torch.equal(out_a, out_b)
        grads_a = torch.autograd.grad(out_a, a, c)
        grads_b = torch.autograd.grad(out_b, b, c)
        for ga, gb, t in zip(grads_a, grads_b, (q, w), strict=True):
            assert ga.shape == t.shape
            torch.testing.assert_close(ga, gb.sum_to_size(t.shape), rtol=1e-14, atol=1e-14)


@pytest.mark.parametrize("shape", [(), (0,), (2, 0, 3), (3, 1, 2), (7,)], ids=str)
def test_batch_shapes(shape: tuple[int, ...]) -> None:
    """Any leading shape, scalar and empty batches included, and batch dimensions that do not
    flatten into one without a copy."""
    gen = torch.Generator().manual_seed(9)
    q = torch.randn(*shape, 4, generator=gen, dtype=torch.float64)
    r = dq.quaternion_to_matrix(q)
    assert r.shape == (*shape, 3, 3)
    torch.testing.assert_close(r, _core.quaternion_to_matrix(torch, q), rtol=0, atol=1e-15)
    back = dq.matrix_to_quaternion(r)
    assert back.shape == (*shape, 4)
    torch.testing.assert_close(back, _core.matrix_to_quaternion(torch, r), rtol=0, atol=1e-15)
    w = torch.randn(*shape, 3, generator=gen, dtype=torch.float64)
    for name in _cpu.JACOBIAN_KINDS:
        j = getattr(dq, name)(w)
        assert j.shape == (*shape, 3, 3)
        torch.testing.assert_close(j, getattr(_lie, name)(torch, w), rtol=0, atol=1e-14)
    if len(shape) == 3:  # (3, 1, 2) batch, permuted: its rows are no longer evenly spaced
        permuted = q.permute(2, 1, 0, 3)
        torch.testing.assert_close(
            dq.quaternion_to_matrix(permuted), _core.quaternion_to_matrix(torch, permuted), rtol=0, atol=1e-15
        )


@pytest.mark.parametrize("threads", [1, 2, 3])
def test_rows_split_over_threads(threads: int) -> None:
    """Batches large enough to be split over threads (in uneven shares for 3) give the core's values
    and gradients in every row, the last ones included."""
    n = 3 * 32768 + 5
    gen = torch.Generator().manual_seed(10)
    q = torch.randn(n, 4, generator=gen, dtype=torch.float64)
    q[-1] = 0.0
    cot9 = torch.randn(n, 3, 3, generator=gen, dtype=torch.float64)
    before = torch.get_num_threads()
    torch.set_num_threads(threads)
    try:
        r, g = _grad(dq.quaternion_to_matrix, q, cot9)
        m = r + 0.01 * cot9
        qm, gm = _grad(dq.matrix_to_quaternion, m, q)
    finally:
        torch.set_num_threads(before)
    r_core, g_core = _grad(lambda t: _core.quaternion_to_matrix(torch, t), q, cot9)
    torch.testing.assert_close(r, r_core, rtol=0, atol=4e-15)
    torch.testing.assert_close(g, g_core, rtol=1e-12, atol=1e-12)
    qm_core, gm_core = _grad(lambda t: _core.matrix_to_quaternion(torch, t), m, q)
    torch.testing.assert_close(qm, qm_core, rtol=0, atol=4e-15)
    torch.testing.assert_close(gm, gm_core, rtol=1e-12, atol=1e-12)
    # the Jacobians: the split changes nothing, bit for bit, against one thread
    w = q[:, 1:]
    torch.set_num_threads(threads)
    try:
        split = _grad(dq.so3_right_jacobian_inverse, w, cot9)
    finally:
        torch.set_num_threads(1)
    try:
        whole = _grad(dq.so3_right_jacobian_inverse, w, cot9)
    finally:
        torch.set_num_threads(before)
    for a, b in zip(split, whole, strict=True):
        assert torch.equal(a, b)

    # quaternion_plus likewise, values and both gradients
    def plus(t: torch.Tensor) -> torch.Tensor:
        return dq.quaternion_plus(t[:, :4], t[:, 4:], side="left")

    x = torch.cat([q, w], dim=-1)
    torch.set_num_threads(threads)
    try:
        split = _grad(plus, x, q.flip(0))
    finally:
        torch.set_num_threads(1)
    try:
        whole = _grad(plus, x, q.flip(0))
    finally:
        torch.set_num_threads(before)
    for a, b in zip(split, whole, strict=True):
        assert torch.equal(a, b)


def test_which_calls_take_the_kernels() -> None:
    """Plain tensors and parameters take the kernels: through the Function where a derivative can be
    asked for (``requires_grad`` or a forward-mode dual tensor), directly where none can (see
    tests/test_paths.py for the calls that take the formula)."""
    q = torch.randn(5, 4, dtype=torch.float64)
    assert dq.quaternion_to_matrix(q).grad_fn is None
    param = torch.nn.Parameter(q.clone())
    assert type(dq.quaternion_to_matrix(param).grad_fn).__name__ == "QuaternionToMatrixKernelBackward"
    with torch.no_grad():
        assert dq.quaternion_to_matrix(param).grad_fn is None
    m = dq.quaternion_to_matrix(q).requires_grad_(True)
    assert type(dq.matrix_to_quaternion(m).grad_fn).__name__ == "MatrixToQuaternionKernelBackward"
    w = torch.randn(5, 3, dtype=torch.float64)
    for name in _cpu.JACOBIAN_KINDS:
        assert getattr(dq, name)(w).grad_fn is None
        assert type(getattr(dq, name)(w.requires_grad_(True)).grad_fn).__name__ == "JacobianKernelBackward"
        w = w.detach()
    assert dq.quaternion_plus(q, w).grad_fn is None
    for a, b in ((param, w), (q, w.requires_grad_(True))):
        assert type(dq.quaternion_plus(a, b).grad_fn).__name__ == "QuaternionPlusKernelBackward"


# Forward-mode AD goes through a torch module that still uses torch.jit.script.
@pytest.mark.filterwarnings("ignore:`torch.jit.script` is deprecated:DeprecationWarning")
def test_forward_mode_without_requires_grad() -> None:
    """A dual tensor that does not require grad still gets its tangent through (the kernels' direct
    call would drop it): the jvp equals the core's."""
    gen = torch.Generator().manual_seed(11)
    q = torch.randn(6, 4, generator=gen, dtype=torch.float64)
    dq_ = torch.randn(6, 4, generator=gen, dtype=torch.float64)
    m = dq.quaternion_to_matrix(q) + 0.05 * torch.randn(6, 3, 3, generator=gen, dtype=torch.float64)
    dm = torch.randn(6, 3, 3, generator=gen, dtype=torch.float64)
    for public, core, x, t in (
        (dq.quaternion_to_matrix, _core.quaternion_to_matrix, q, dq_),
        (dq.matrix_to_quaternion, _core.matrix_to_quaternion, m, dm),
    ):
        with forward_ad.dual_level():
            ours = forward_ad.unpack_dual(public(forward_ad.make_dual(x, t))).tangent
            theirs = forward_ad.unpack_dual(core(torch, forward_ad.make_dual(x, t))).tangent
        assert ours is not None and theirs is not None
        torch.testing.assert_close(ours, theirs, rtol=1e-12, atol=1e-12)
    # The Jacobians' kernels have no jvp: forward mode takes their formula, whose tangent is exact.
    w, dw = q[:, 1:], dq_[:, 1:]
    for name in _cpu.JACOBIAN_KINDS:
        with forward_ad.dual_level():
            assert getattr(_dispatch, name)(w) is getattr(_lie, name)
            ours = forward_ad.unpack_dual(getattr(dq, name)(forward_ad.make_dual(w, dw))).tangent
        theirs = torch.func.jvp(lambda t, n=name: getattr(_lie, n)(torch, t), (w,), (dw,))[1]
        assert ours is not None
        torch.testing.assert_close(ours, theirs, rtol=1e-12, atol=1e-12)
    with forward_ad.dual_level():
        assert _dispatch.quaternion_plus(q, w) is _lie.quaternion_plus
        ours = forward_ad.unpack_dual(dq.quaternion_plus(forward_ad.make_dual(q, dq_), w)).tangent
    theirs = torch.func.jvp(lambda t: _lie.quaternion_plus(torch, t, w), (q,), (dq_,))[1]
    assert ours is not None
    torch.testing.assert_close(ours, theirs, rtol=1e-12, atol=1e-12)


def test_unusual_cotangent_takes_the_torch_formula(monkeypatch: pytest.MonkeyPatch) -> None:
    """A cotangent the kernels cannot read as a plain buffer (here a tensor subclass, as tracing tools
    pass) goes through the differentiable torch formula instead, with the same result; the backward
    kernels are not called."""

    class Wrapped(torch.Tensor):
        pass

    gen = torch.Generator().manual_seed(12)
    q = torch.randn(4, 4, generator=gen, dtype=torch.float64, requires_grad=True)
    w = q.detach()[:, 1:].requires_grad_(True)
    cot = torch.randn(4, 3, 3, generator=gen, dtype=torch.float64)
    cot4 = torch.randn(4, 4, generator=gen, dtype=torch.float64)
    calls = {
        "quaternion_to_matrix": (lambda: (dq.quaternion_to_matrix(q), q, cot)),
        "so3_left_jacobian": (lambda: (dq.so3_left_jacobian(w), w, cot)),
        "quaternion_plus": (lambda: (dq.quaternion_plus(q, w), q, cot4)),
    }
    plain = {}
    for name, call in calls.items():
        out, x, c = call()
        plain[name] = torch.autograd.grad(out, x, c)[0]

    def refuse(*args: object) -> None:
        raise AssertionError("a backward kernel ran on a subclass cotangent")

    for kernel in ("q2m_backward", "jac_backward", "qplus_backward"):
        monkeypatch.setattr(_cpu, kernel, refuse)
    for name, call in calls.items():
        out, x, c = call()
        (wrapped,) = torch.autograd.grad(out, x, c.as_subclass(Wrapped))
        torch.testing.assert_close(torch.Tensor(wrapped), plain[name], rtol=1e-12, atol=1e-12)


def test_zero_tensors_are_not_read_as_buffers() -> None:
    """A ZeroTensor (``torch._efficientzerotensor``, which autograd hands for some zero cotangents) has
    no buffer: as an input or a cotangent it takes the formula (a null pointer would crash the
    process), and the results are those of zeros."""
    w = torch.randn(4, 3, dtype=torch.float64, requires_grad=True)
    zero_cot = torch._efficientzerotensor((4, 3, 3), dtype=torch.float64)
    (g,) = torch.autograd.grad(dq.so3_left_jacobian(w), w, zero_cot)
    assert torch.equal(torch.Tensor(g), torch.zeros(4, 3, dtype=torch.float64))
    zero_w = torch._efficientzerotensor((4, 3), dtype=torch.float64)
    eye = torch.eye(3, dtype=torch.float64).expand(4, 3, 3)
    torch.testing.assert_close(dq.so3_left_jacobian(zero_w), eye, rtol=0, atol=0)
    q = torch.randn(4, 4, dtype=torch.float64, requires_grad=True)
    (gq,) = torch.autograd.grad(dq.quaternion_to_matrix(q), q, zero_cot)
    assert torch.equal(torch.Tensor(gq), torch.zeros(4, 4, dtype=torch.float64))


def test_lazily_negated_views() -> None:
    """A negated view (``torch._neg_view``: the buffer holds the values before the sign change) is
    not read as a raw buffer: both conversions give the values of the materialised tensor."""
    gen = torch.Generator().manual_seed(13)
    q = torch.randn(5, 4, generator=gen, dtype=torch.float64)
    m = dq.quaternion_to_matrix(q)
    assert torch._neg_view(m).is_neg()
    torch.testing.assert_close(dq.matrix_to_quaternion(torch._neg_view(m)), dq.matrix_to_quaternion(-m))
    torch.testing.assert_close(dq.quaternion_to_matrix(torch._neg_view(q)), dq.quaternion_to_matrix(-q))


def _compiler() -> str | None:
    return shutil.which(sysconfig.get_config_var("CC").split()[0]) or shutil.which("cc")


def build_portable(directory: Path) -> Path:
    """``diffquat/_kernels.c`` built as the extension module ``_kernels`` with ``DIFFQUAT_PORTABLE``
    (no AVX2 clones, no SSE moves) and the compiler's vectorisers off: scalar code that any CPU the
    compiler targets runs. The other flags are pyproject.toml's (FMA contraction off, as the core)."""
    kernels = Path(diffquat.__file__).parent / "_kernels.c"
    target = directory / ("_kernels" + sysconfig.get_config_var("EXT_SUFFIX"))
    flags = ["-O2", "-fno-tree-vectorize", "-fno-tree-slp-vectorize", "-fno-math-errno", "-fno-trapping-math"]
    command = [
        _compiler() or "cc", "-shared", "-fPIC", *flags, "-ffp-contract=off", "-DDIFFQUAT_PORTABLE",
        f"-I{sysconfig.get_paths()['include']}", str(kernels), "-o", str(target), "-lpthread",
    ]  # fmt: skip
    subprocess.run(command, check=True, capture_output=True, text=True)
    return target


def _all_kernels(module: object, dtype: torch.dtype) -> list[torch.Tensor]:
    """Every kernel of ``module`` (an extension build) on every quaternion and matrix case, both
    storage orders, through the Python entry points of _cpu.py with that build swapped in."""
    q, m = _quaternions(dtype), _matrices(dtype)
    gen = torch.Generator().manual_seed(14)
    cot9 = torch.randn(len(q), 3, 3, generator=gen, dtype=torch.float64).to(dtype)
    cot4 = torch.randn(len(m), 4, generator=gen, dtype=torch.float64).to(dtype)
    outs = []
    before = _cpu._kernels
    _cpu._kernels = module  # type: ignore[assignment]
    try:
        for first in (True, False):
            qm = _cpu.m2q_forward(m, first)
            outs += [_cpu.q2m_forward(q, first), _cpu.q2m_backward(q, cot9, first), qm]
            outs.append(_cpu.m2q_backward(m, qm, cot4, first))
        w = _rotation_vectors(dtype)
        cot3 = torch.randn(len(w), 3, 3, generator=gen, dtype=torch.float64).to(dtype)
        for kind in _cpu.JACOBIAN_KINDS.values():
            outs += [_cpu.jac_forward(w, kind), _cpu.jac_backward(w, cot3, kind)]
        qs = q[: len(w)] if len(q) >= len(w) else q.repeat(len(w) // len(q) + 1, 1)[: len(w)]
        cotq = torch.randn(len(w), 4, generator=gen, dtype=torch.float64).to(dtype)
        for first in (True, False):
            for right in (True, False):
                outs += [
                    _cpu.qplus_forward(qs, w, first, right),
                    *_cpu.qplus_backward(qs, w, cotq, first, right),
                ]
    finally:
        _cpu._kernels = before
    return outs


def test_portable_build(tmp_path: Path) -> None:
    """The portable build gives the installed build's numbers bit for bit (the same IEEE operations in
    the same order, vectorised or not), and the kernel tests pass again in a process that loads it
    (tests/conftest.py swaps it in when DIFFQUAT_TEST_KERNELS names it)."""
    import importlib.util
    import os
    import sys

    if _compiler() is None:
        pytest.skip("no C compiler")
    path = build_portable(tmp_path)
    spec = importlib.util.spec_from_file_location("_kernels", path)
    assert spec is not None and spec.loader is not None
    portable = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(portable)
    assert portable.PORTABLE == 1
    for dtype in (torch.float32, torch.float64):
        for a, b in zip(_all_kernels(portable, dtype), _all_kernels(_cpu._kernels, dtype), strict=True):
            torch.testing.assert_close(a, b, rtol=0, atol=0, equal_nan=True)
    tests = Path(__file__).parent
    selection = [
        str(tests / "test_kernels.py"),
        "-k", "not portable_build and not xla_declarations",
        f"{tests / 'test_paths.py'}::test_each_evaluation_against_a_float64_reference",
        f"{tests / 'test_paths.py'}::test_kernel_functions_pass_gradcheck_both_modes",
        f"{tests / 'test_paths.py'}::test_quaternion_to_matrix_second_derivatives_at_small_norms",
        f"{tests / 'test_lie.py'}::test_jacobians_against_mpmath",
        f"{tests / 'test_lie.py'}::test_jacobian_derivatives_across_the_threshold_and_beyond_pi",
    ]  # fmt: skip
    env = {**os.environ, "DIFFQUAT_TEST_KERNELS": str(path)}
    done = subprocess.run(
        [sys.executable, "-m", "pytest", "-q", "-p", "no:cacheprovider", *selection],
        env=env, capture_output=True, text=True, timeout=600, cwd=tests.parent,
    )  # fmt: skip
    assert done.returncode == 0, done.stdout[-4000:] + done.stderr[-2000:]
    assert "passed" in done.stdout


# The fields of XLA's FFI structures that diffquat/_kernels.c reads or writes: its structure, the
# header's, and the fields ("its:the header's" where the names differ). Then the enumerators it uses.
_XLA_LAYOUT = [
    ("XlaExtension", "XLA_FFI_Extension_Base", "struct_size type next"),
    ("XlaApiVersion", "XLA_FFI_Api_Version", "extension_start major_version minor_version"),
    ("XlaMetadata", "XLA_FFI_Metadata", "struct_size api_version traits"),
    ("XlaMetadataExtension", "XLA_FFI_Metadata_Extension", "extension_base metadata"),
    ("XlaBuffer", "XLA_FFI_Buffer", "dtype data rank dims"),
    ("XlaList", "XLA_FFI_Args", "size types items:args"),
    ("XlaList", "XLA_FFI_Rets", "size types items:rets"),
    ("XlaCallFrame", "XLA_FFI_CallFrame", "extension_start api ctx stage args rets"),
]
_XLA_ENUMS = [
    ("XLA_EXTENSION_METADATA", "XLA_FFI_Extension_Metadata"),
    ("XLA_STAGE_EXECUTE", "XLA_FFI_ExecutionStage_EXECUTE"),
    ("XLA_F64", "XLA_FFI_DataType_F64"),
    ("XLA_API_MAJOR", "XLA_FFI_API_MAJOR"),
]


def test_xla_declarations_match_jaxlib_header(tmp_path: Path) -> None:
    """The XLA handlers declare the few FFI structures they use themselves (the extension builds
    without jax); compiled beside the installed jaxlib's ``xla/ffi/api/c_api.h``, every size, offset
    and enumerator they rely on equals the header's, and the API version they report is one that
    header describes (a mismatch is a compile error here, not a crash in a user's program)."""
    import jax.ffi

    compiler = shutil.which(sysconfig.get_config_var("CC").split()[0]) or shutil.which("cc")
    if compiler is None:
        pytest.skip("no C compiler")
    checks = []
    for ours, theirs, fields in _XLA_LAYOUT:
        checks.append(f'_Static_assert(sizeof({ours}) <= sizeof({theirs}), "{ours}");')
        for field in fields.split():
            mine, _, header = field.partition(":")
            header = header or mine
            for measure in ("offsetof({s}, {f})", "sizeof((({s} *)0)->{f})"):
                a, b = measure.format(s=ours, f=mine), measure.format(s=theirs, f=header)
                checks.append(f'_Static_assert({a} == {b}, "{ours}.{mine}");')
    checks += [f'_Static_assert((int){a} == (int){b}, "{a}");' for a, b in _XLA_ENUMS]
    checks.append('_Static_assert(XLA_API_MINOR <= XLA_FFI_API_MINOR, "minor version");')
    checks.append('_Static_assert(XLA_METADATA_WRITTEN == XLA_FFI_Metadata_STRUCT_SIZE, "metadata");')
    source = tmp_path / "layout.c"
    kernels = Path(diffquat.__file__).parent / "_kernels.c"
    source.write_text(
        "#include <stddef.h>\n"
        f'#include "{kernels}"\n'
        "#include <xla/ffi/api/c_api.h>\n" + "\n".join(checks) + "\n"
    )
    includes = [f"-I{jax.ffi.include_dir()}", f"-I{sysconfig.get_paths()['include']}"]
    result = subprocess.run(
        [compiler, "-fsyntax-only", "-std=gnu11", *includes, str(source)], capture_output=True, text=True
    )
    assert result.returncode == 0, result.stderr


@pytest.mark.parametrize(
    ("f64", "terms"),
    [(2, (3, 3, 3)), (0, (2, 3, 3)), (1, (3, 17, 3)), (0, (16, 16, 17))],
    ids=["dtype", "too-few-terms", "too-many-terms", "past-the-table"],
)
def test_xla_tables_refuse_what_the_kernels_cannot_read(f64: int, terms: tuple[int, int, int]) -> None:
    """The XLA handlers read their series tables from what diffquat/jax/_xla.py hands over at import;
    a table that the kernels cannot read (a dtype other than float32 and float64, fewer than the 3
    coefficients they differentiate, more than the 16 each series holds) is refused before anything
    is copied, so the handlers keep reading the tables set at import."""
    import diffquat.jax
    from diffquat import _kernels

    series = np.zeros(1 + sum(terms))
    table = np.zeros(7)
    try:
        with pytest.raises(ValueError, match="xla_set_tables"):
            _kernels.xla_set_tables(f64, series.ctypes.data, len(series), *terms, table.ctypes.data)
    finally:  # had the zeros been taken, the rest of this process's jax kernels would read them
        if diffquat.jax._xla is not None:
            diffquat.jax._xla._set_tables()
