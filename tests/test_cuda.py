"""On a CUDA device (skipped without one; run on a GPU machine by hand, CI has none): the conversions
(eager, their Functions) and every capture of them compute what the float64 reference does, and
the Lie calculus, the means, the symmetric distance, the heads and the optimisers run on the device
and agree with the CPU. Every float32 result is compared with a float64 reference at a bound stated
in ulps, never with another float32 evaluation."""

from __future__ import annotations

import numpy as np
import pytest
import torch
from scipy.spatial.transform import Rotation

import diffquat.torch as dq
from diffquat.torch.nn import RotationHead
from diffquat.torch.optim import RiemannianAdam

pytestmark = [
    pytest.mark.skipif(not torch.cuda.is_available(), reason="no CUDA device"),
    pytest.mark.filterwarnings(r"ignore:`torch\.jit\.\w+` is deprecated:DeprecationWarning"),
    pytest.mark.filterwarnings("ignore::torch.jit.TracerWarning"),
]

# float32 results of conversions whose entries are at most 1 in size: a few roundings of the
# formula's ~10 operations, 8 ulps of 1 (1.2e-7 each) is a generous bound that still catches a wrong
# sign, a wrong pivot or a stale constant (errors of order 1).
F32 = 8 * float(np.finfo(np.float32).eps)


def _quaternions(n: int, seed: int) -> np.ndarray:
    q = Rotation.random(n, random_state=seed).as_quat(scalar_first=True)
    q[0] = [0.0, 1.0, 0.0, 0.0]  # an exact half-turn
    q[1] = [1.0, 0.0, 0.0, 0.0]  # the identity
    return q * np.random.default_rng(seed).uniform(0.5, 2.0, (n, 1))  # any norm


def _cuda(x: np.ndarray, dtype: torch.dtype = torch.float32) -> torch.Tensor:
    return torch.tensor(x, dtype=dtype, device="cuda")


def _expected_matrices(q: np.ndarray) -> np.ndarray:
    return Rotation.from_quat(q, scalar_first=True).as_matrix()


def test_conversions_and_their_captures_equal_the_float64_reference() -> None:
    """Eager (the Functions), ``torch.jit.trace``, ``torch.export`` and ``torch.compile`` on the
    device: each traced with one input and called with another, each within F32 of scipy in float64."""
    q0, q1 = _quaternions(1000, 0), _quaternions(1000, 1)
    m1 = _expected_matrices(q1)
    expected_q = Rotation.from_matrix(m1).as_quat(scalar_first=True, canonical=True)

    def both(q: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        m = dq.quaternion_to_matrix(q)
        return m, dq.matrix_to_quaternion(m)

    class Both(torch.nn.Module):
        def forward(self, q: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
            return both(q)

    paths = {
        "eager": both,
        "jit.trace": torch.jit.trace(both, (_cuda(q0),), check_trace=False),
        "export": torch.export.export(Both(), (_cuda(q0),)).module(),
        "compile": torch.compile(both, fullgraph=True),
    }
    for name, path in paths.items():
        m, q = (x.double().cpu().numpy() for x in path(_cuda(q1)))
        np.testing.assert_allclose(m, m1, atol=F32, rtol=0, err_msg=name)
        np.testing.assert_allclose(q, expected_q, atol=F32, rtol=0, err_msg=name)


def test_device_backward_equals_float64_autograd() -> None:
    """The conversions' cotangents on the device against float64 on the CPU: gradients of size ~1 per
    unit cotangent, within 32 ulps of 1."""
    q = _quaternions(512, 2)
    cot = np.random.default_rng(3).normal(size=(512, 3, 3))
    device = _cuda(q).requires_grad_(True)
    reference = torch.tensor(q, dtype=torch.float64, requires_grad=True)
    (g_device,) = torch.autograd.grad(dq.quaternion_to_matrix(device), device, _cuda(cot))
    (g_ref,) = torch.autograd.grad(dq.quaternion_to_matrix(reference), reference, torch.tensor(cot))
    scale = np.abs(g_ref.numpy()).max(axis=-1, keepdims=True) + 1.0
    assert np.all(np.abs(g_device.double().cpu().numpy() - g_ref.numpy()) <= 32 * F32 * scale)

    m = _expected_matrices(q)
    device_m = _cuda(m).requires_grad_(True)
    reference_m = torch.tensor(m, requires_grad=True)
    cot_q = np.random.default_rng(4).normal(size=(512, 4))
    (g_device,) = torch.autograd.grad(dq.matrix_to_quaternion(device_m), device_m, _cuda(cot_q))
    (g_ref,) = torch.autograd.grad(dq.matrix_to_quaternion(reference_m), reference_m, torch.tensor(cot_q))
    assert np.all(
        np.abs(g_device.double().cpu().numpy() - g_ref.numpy()) <= 32 * F32 * (1 + np.abs(g_ref.numpy()))
    )


def _float64_on_both(fn: object, *arrays: np.ndarray) -> None:
    """``fn`` and its gradient (a fixed cotangent) in float64 on the CPU and on CUDA: equal to 1e-9
    (cuSOLVER's and LAPACK's SVD/eigh round differently; the maps are well conditioned here)."""
    results = []
    for device in ("cpu", "cuda"):
        args = [torch.tensor(a, dtype=torch.float64, device=device, requires_grad=True) for a in arrays]
        out = fn(*args)  # type: ignore[operator]
        cot = torch.ones_like(out) + torch.arange(out.numel(), device=device).reshape(out.shape) % 3
        grads = torch.autograd.grad(out, args, cot)
        assert out.device.type == device
        results.append([out.detach().cpu().numpy(), *(g.cpu().numpy() for g in grads)])
    for cpu, cuda in zip(*results, strict=True):
        np.testing.assert_allclose(cuda, cpu, rtol=1e-9, atol=1e-9)


def test_lie_statistics_and_fisher_functions_on_the_device_equal_the_cpu() -> None:
    rng = np.random.default_rng(5)
    m = _expected_matrices(_quaternions(16, 6))
    v = rng.normal(size=(16, 3))
    cluster = (
        Rotation.from_matrix(m[:, None]) * Rotation.from_rotvec(0.3 * rng.normal(size=(16, 7, 3)))
    ).as_matrix()
    weights = rng.uniform(0.5, 2.0, (16, 7))
    _float64_on_both(lambda r, d: dq.so3_plus(r, d, side="left"), m, v)
    _float64_on_both(dq.so3_minus, m, m[::-1].copy())
    _float64_on_both(dq.so3_left_jacobian_inverse, v)
    _float64_on_both(dq.quaternion_plus, _quaternions(16, 7), v)
    for method in ("chordal", "geodesic", "geodesic_l1"):
        _float64_on_both(lambda r, w, method=method: dq.rotation_mean(r, w, method=method), cluster, weights)
    _float64_on_both(dq.quaternion_mean, Rotation.from_matrix(cluster).as_quat(), weights)
    group = dq.symmetry_group("D4", dtype=torch.float64, device="cuda")
    assert group.device.type == "cuda" and group.shape == (8, 3, 3)
    _float64_on_both(dq.symmetric_geodesic_distance, m, m[::-1].copy(), group.cpu().numpy())
    _float64_on_both(dq.matrix_fisher_nll, 5.0 * m + rng.normal(size=m.shape), m[::-1].copy())


def test_heads_and_optimisers_run_on_the_device() -> None:
    """A fisher head and a 6D head forward and backward on the device; RiemannianAdam fits 64 CUDA
    rotations to their targets, the parameters stay on the device and stay rotations."""
    torch.manual_seed(0)
    features = torch.randn(32, 16, device="cuda")
    for representation in ("6d", "fisher"):
        head = RotationHead(16, representation=representation).cuda()
        r = head(features)
        assert r.device.type == "cuda" and r.shape == (32, 3, 3)
        loss = dq.matrix_geodesic_distance(r, torch.eye(3, device="cuda")).mean()
        if representation == "fisher":
            loss = loss + dq.matrix_fisher_nll(head.fisher(features), torch.eye(3, device="cuda")).mean()
        loss.backward()
        assert all(torch.isfinite(p.grad).all() for p in head.parameters() if p.grad is not None)

    target = _cuda(_expected_matrices(_quaternions(64, 8)))
    rotation = torch.nn.Parameter(_cuda(_expected_matrices(_quaternions(64, 9))))
    optimizer = RiemannianAdam([rotation], lr=0.05)
    for _ in range(300):
        optimizer.zero_grad()
        dq.matrix_geodesic_distance(rotation, target).square().sum().backward()
        optimizer.step()
    rotation = rotation.detach()
    assert rotation.device.type == "cuda"
    eye = torch.eye(3, device="cuda")
    assert float((rotation.mT @ rotation - eye).abs().max()) <= 1e-5
    # Adam's last steps dither at about lr * (sign noise)
    assert float(dq.matrix_geodesic_distance(rotation, target).max()) <= 0.05
