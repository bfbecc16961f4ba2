"""The Triton kernels of ``quaternion_to_matrix`` and ``matrix_to_quaternion``
(diffquat/torch/_triton.py), run on the CPU by Triton's interpreter against the core formula: values,
the backward kernels, and the differentiable fallback that a double backward records. In a
subprocess, because ``TRITON_INTERPRET`` must be set before the kernels are defined. On CUDA the same
kernels are compiled; timing them is the benchmark's."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parent.parent

SCRIPT = r"""
import torch
from diffquat import _core
from diffquat.torch import _triton

torch.manual_seed(0)
for dtype in (torch.float32, torch.float64):
    q = torch.randn(300, 4, dtype=dtype)
    q[0] = 0.0
    q[1] = torch.tensor([0.0, 1.0, 0.0, 0.0])
    q[2] *= 1e-15
    q[3] *= 1e15
    # forward against the core (which normalises first; the kernel scales by 2/|q|^2 instead, so
    # the two agree to rounding, not bitwise)
    tol = 1e-6 if dtype == torch.float32 else 1e-14
    torch.testing.assert_close(
        _triton.q2m_forward(q), _core.quaternion_to_matrix(torch, q), rtol=tol, atol=tol
    )
    # backward kernel against autograd through the core, away from the float32 range limits
    # (where the core's own float32 gradient overflows)
    ok = q[4:]
    a, b = ok.clone().requires_grad_(True), ok.clone().requires_grad_(True)
    cot = torch.randn(len(ok), 3, 3, dtype=dtype)
    (ga,) = torch.autograd.grad(_triton.QuaternionToMatrix.apply(a, True), a, cot)
    (gb,) = torch.autograd.grad(_core.quaternion_to_matrix(torch, b), b, cot)
    tol = 1e-5 if dtype == torch.float32 else 1e-12
    torch.testing.assert_close(ga, gb, rtol=tol, atol=tol)
    # zero quaternion: identity with zero gradient
    z = torch.zeros(1, 4, dtype=dtype, requires_grad=True)
    (gz,) = torch.autograd.grad(_triton.QuaternionToMatrix.apply(z, True).sum(), z)
    assert torch.equal(gz, torch.zeros_like(gz))
    assert torch.equal(_triton.q2m_forward(z.detach())[0], torch.eye(3, dtype=dtype))
    # scalar-last in the kernels themselves (no reordering copy): forward and backward kernels
    last = q[:, [1, 2, 3, 0]].contiguous()
    tol = 1e-6 if dtype == torch.float32 else 1e-14
    torch.testing.assert_close(
        _triton.q2m_forward(last, scalar_first=False), _triton.q2m_forward(q), rtol=tol, atol=tol
    )
    torch.testing.assert_close(
        _triton.q2m_backward(last[4:], cot, scalar_first=False),
        _triton.q2m_backward(q[4:], cot)[:, [1, 2, 3, 0]],
        rtol=tol, atol=tol,
    )
# scalar-last through the dispatcher's entry point, and double backward (the recorded fallback)
q = torch.randn(5, 4, dtype=torch.float64, requires_grad=True)
fn = lambda x: _triton.quaternion_to_matrix(torch, x, scalar_first=False)
torch.testing.assert_close(
    fn(q.detach()), _core.quaternion_to_matrix(torch, q.detach(), scalar_first=False), rtol=1e-14, atol=1e-14
)
assert torch.autograd.gradcheck(fn, q)
assert torch.autograd.gradgradcheck(fn, q)
# matrix_to_quaternion: rotations (half-turns, with ties between pivots, and the identity among
# them), the same off SO(3), an arbitrary matrix; a batch that is not a multiple of the block
import numpy as np
from cases import CASES_BY_NAME, oracle_quaternion_to_matrix
for dtype in (torch.float32, torch.float64):
    qs = [CASES_BY_NAME[name].quaternions("float64").reshape(-1, 4) for name in
          ("random", "identity", "half_turns", "near_half_turns", "near_identity")]
    rot = torch.tensor(oracle_quaternion_to_matrix(np.vstack(qs)))
    m = torch.cat([rot, rot + 0.05 * torch.randn_like(rot), torch.randn(7, 3, 3, dtype=rot.dtype)]).to(dtype)
    tol = 1e-6 if dtype == torch.float32 else 1e-14
    # same selection and canonical sign as the core: equal to rounding, never sign-flipped
    ours, core = _triton.m2q_forward(m), _core.matrix_to_quaternion(torch, m)
    torch.testing.assert_close(ours, core, rtol=tol, atol=tol)
    a, b = m.clone().requires_grad_(True), m.clone().requires_grad_(True)
    cot = torch.randn(len(m), 4, dtype=dtype)
    (ga,) = torch.autograd.grad(_triton.MatrixToQuaternion.apply(a, True), a, cot)
    (gb,) = torch.autograd.grad(_core.matrix_to_quaternion(torch, b), b, cot)
    tol = 1e-5 if dtype == torch.float32 else 1e-12
    torch.testing.assert_close(ga, gb, rtol=tol, atol=tol)
    # scalar-last kernels: the same quaternion reordered, and the same matrix gradient
    q_last = _triton.m2q_forward(m, scalar_first=False)
    torch.testing.assert_close(q_last, ours[:, [1, 2, 3, 0]], rtol=0, atol=0)
    torch.testing.assert_close(
        _triton.m2q_backward(m, q_last, cot[:, [1, 2, 3, 0]], scalar_first=False),
        _triton.m2q_backward(m, ours, cot), rtol=tol, atol=tol,
    )
m = (torch.tensor(oracle_quaternion_to_matrix(CASES_BY_NAME["random"].quaternions("float64")[:5]))
     + 0.05 * torch.randn(5, 3, 3, dtype=torch.float64)).requires_grad_(True)
fn = lambda x: _triton.matrix_to_quaternion(torch, x, scalar_first=False)
torch.testing.assert_close(
    fn(m.detach()), _core.matrix_to_quaternion(torch, m.detach(), scalar_first=False), rtol=1e-14, atol=1e-14
)
assert torch.autograd.gradcheck(fn, m)
assert torch.autograd.gradgradcheck(fn, m)
# int64 element offsets (taken from ~238 million rotations on): the same results on a small batch
q, cot9 = torch.randn(300, 4), torch.randn(300, 3, 3)
m, cot4 = _triton.q2m_forward(q), torch.randn(300, 4)
narrow = [_triton.q2m_forward(q), _triton.q2m_backward(q, cot9), _triton.m2q_forward(m)]
narrow.append(_triton.m2q_backward(m, narrow[2], cot4))
_triton.WIDE_FROM = 0
wide = [_triton.q2m_forward(q), _triton.q2m_backward(q, cot9), _triton.m2q_forward(m)]
wide.append(_triton.m2q_backward(m, wide[2], cot4))
for a, b in zip(narrow, wide):
    assert torch.equal(a, b)
print("ok")
"""


def test_triton_kernels_under_the_interpreter() -> None:
    pytest.importorskip("triton", reason="triton is not installed (pip install -e '.[triton]')")
    env = {
        **os.environ,
        "TRITON_INTERPRET": "1",
        "PYTHONPATH": os.pathsep.join([str(ROOT), str(ROOT / "tests"), os.environ.get("PYTHONPATH", "")]),
    }
    done = subprocess.run(
        [sys.executable, "-c", SCRIPT], cwd=ROOT, env=env, capture_output=True, text=True, timeout=600
    )
    assert done.returncode == 0, done.stderr[-3000:]
    assert done.stdout.strip().endswith("ok")


COMPILE = r"""
import re
import triton
from triton.backends.compiler import GPUTarget
from triton.compiler import ASTSource
from diffquat.torch import _triton as K

F32_TINY, F64_TINY = 2.0**-126, 2.0**-1022
KERNELS = {
    K._q2m_forward_kernel: (("q_ptr", "out_ptr"), True),
    K._q2m_backward_kernel: (("q_ptr", "g_ptr", "out_ptr"), True),
    K._m2q_forward_kernel: (("m_ptr", "out_ptr"), False),
    K._m2q_backward_kernel: (("m_ptr", "q_ptr", "g_ptr", "out_ptr"), False),
}
for kernel, (pointers, has_tiny) in KERNELS.items():
    for dtype, tiny in (("fp32", F32_TINY), ("fp64", F64_TINY)):
        for first, wide in ((True, False), (False, False), (True, True)):
            signature = {p: "*" + dtype for p in pointers} | {"n": "i64" if wide else "i32"}
            constexprs = {"FIRST": first, "WIDE": wide, "block": K.BLOCK}
            constexprs |= {"TINY": tiny} if has_tiny else {}
            signature |= dict.fromkeys(constexprs, "constexpr")
            # as the launcher specialises them for torch's allocations: 16-byte aligned pointers
            attrs = {(i,): [["tt.divisibility", 16]] for i in range(len(pointers))}
            source = ASTSource(fn=kernel, signature=signature, constexprs=constexprs, attrs=attrs)
            compiled = triton.compile(
                source, target=GPUTarget("cuda", 90, 32), options={"num_warps": K.NUM_WARPS}
            )
            ptx = compiled.asm["ptx"]
            if dtype == "fp32" and kernel in (K._q2m_backward_kernel, K._m2q_forward_kernel):
                # the quaternion tile is written 16 bytes per store, not 4 strided ones
                assert "st.global.v4.b32" in ptx, kernel.__name__
            # the program's first row: widened to 64 bits straight from the block index, or not
            (block_id,) = re.findall(r"mov\.u32\s+(%r\d+), %ctaid\.x;", ptx)
            widened = re.search(rf"(mul\.wide\.[su]32|cvt\.[su]64\.[su]32)\s+%rd\d+, {block_id}\b", ptx)
            assert bool(widened) == wide, (kernel.__name__, wide)
            print(kernel.__name__, dtype, first, wide, len(compiled.asm["cubin"]))
print("ok")
"""


def test_triton_kernels_compile_for_cuda() -> None:
    """Every kernel compiles to a Hopper (sm_90) binary, in both dtypes and both orders, on a machine
    without a GPU: the interpreter runs kernels as Python and accepts what the compiler refuses (type
    annotations resolved as globals, once). And the quaternion tiles are written by 16-byte stores."""
    pytest.importorskip("triton", reason="triton is not installed (pip install -e '.[triton]')")
    env = {k: v for k, v in os.environ.items() if k != "TRITON_INTERPRET"}
    env["PYTHONPATH"] = os.pathsep.join([str(ROOT), os.environ.get("PYTHONPATH", "")])
    env["TRITON_DEFAULT_FP_FUSION"] = "1"  # Triton's default, stated (else it warns that it will change)
    done = subprocess.run(
        [sys.executable, "-c", COMPILE], cwd=ROOT, env=env, capture_output=True, text=True, timeout=600
    )
    assert done.returncode == 0, done.stderr[-3000:]
    assert done.stdout.strip().endswith("ok")
