"""The matrix Fisher distribution on SO(3) and the Bingham NLL of the 10D head, beyond the shared table
(tests/cases.py has their rows): the normaliser against a high-precision reference over the whole
range of singular values, its gradient E[R] and Hessian Cov(R) where singular values repeat, the
density's total mass, the sampler's moments, the torch Distribution and the Bingham relation.

Statistical tests use fixed seeds (so they are deterministic) and bounds of 5 standard errors, each
estimated from the same draws: a correct implementation exceeds one with probability ~6e-7 per
compared number (normal tails; the sample sizes make the means close to normal), a wrong one (an
error of a few standard errors or more) fails.
"""

from __future__ import annotations

import itertools
import math
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np
import pytest
import torch
from cases import oracle_log_c, proper_singular_values, reference_log_c
from conftest import BACKENDS, Backend
from scipy.spatial.transform import Rotation

import diffquat.jax as djax
import diffquat.numpy as dnp
import diffquat.torch as dtorch
from diffquat.torch.distributions import MatrixFisher, special_orthogonal

# torch.func.hessian's first call registers torch's forward-mode decompositions with torch.jit.script
pytestmark = pytest.mark.filterwarnings("ignore:`torch.jit.script` is deprecated:DeprecationWarning")

SIGMAS = 5.0


# Magnitudes of the singular values, from 1e-3 to 1e5: equal, distinct, and mixed scales (the widths of
# the integrand's features then differ by up to 1e8).
MAGNITUDES = [
    (1e-3, 1e-3, 1e-3),
    (0.5, 0.2, 1e-3),
    (1.0, 1.0, 1.0),
    (3.0, 2.0, 1.0),
    (10.0, 1e-3, 1e-3),
    (100.0, 100.0, 100.0),
    (1e3, 10.0, 1e-3),
    (1e4, 100.0, 1.0),
    (1e5, 1e5, 1e5),
    (1e5, 1e-3, 1e-3),
    (1e5, 1e4, 1e3),
]
# Every sign pattern of a diagonal F: det F < 0 (an odd number of minus signs) makes s3 negative.
SIGNS = list(itertools.product((1.0, -1.0), repeat=3))


def matrices_and_references() -> tuple[np.ndarray, np.ndarray]:
    """``F = U diag(signs * magnitudes) V^T`` for random rotations U, V (scipy's), every magnitude and
    every sign pattern, and the reference log c of each (two distinct ones per magnitude: s3 > 0, < 0)."""
    rotations = Rotation.random(2 * len(MAGNITUDES) * len(SIGNS), random_state=7).as_matrix()
    out, refs = [], []
    for k, (m, signs) in enumerate(itertools.product(MAGNITUDES, SIGNS)):
        u, v = rotations[2 * k], rotations[2 * k + 1]
        out.append(u @ np.diag(np.array(signs) * np.array(m)) @ v.T)
        s3 = m[2] * math.prod(signs)
        refs.append(reference_log_c(m[0], m[1], s3))
    return np.array(out), np.array(refs)


TOLERANCE = {"float64": 1e-10, "float32": 2e-5}  # relative, the accuracy target


@pytest.mark.parametrize("precision", list(TOLERANCE))
def test_log_normalizer_matches_the_mpmath_reference(backend: Backend, precision: str) -> None:
    """log c(F) within 1e-10 relative (float64) and 2e-5 (float32) of mpmath, for proper singular
    values from 1e-3 to 1e5, every sign pattern. In float32 the reference is that of the float64 F:
    rounding F to float32 moves log c by at most ``|E[R]| |dF| <= 3 * 6e-8 |F|``, i.e. 2e-7 relative
    (log c ~ s1 at large s, ~|s|^2/6 with E[R] ~ F/3 at small s), a hundredth of the bound."""
    matrices, refs = matrices_and_references()
    x = backend.array(matrices, precision)
    out = backend.to_numpy(backend.module.matrix_fisher_log_normalizer(x))
    error = np.abs(out - refs) / np.abs(refs)
    assert error.max() <= TOLERANCE[precision], (error.max(), matrices[np.argmax(error)])


def test_reference_matches_monte_carlo() -> None:
    """The Bessel integral (the reference) against the definition, E_R[exp(tr(S R))] over uniform R
    (scipy's sampler), within 5 standard errors; and against the table's scipy-quadrature oracle."""
    rotations = Rotation.random(400_000, random_state=3).as_matrix()
    for s in [(1.0, 0.5, 0.2), (2.0, 1.0, -0.5), (3.0, 3.0, 3.0)]:
        values = np.exp(np.einsum("i,nii->n", np.array(s), rotations))
        mean, se = values.mean(), values.std() / math.sqrt(len(values))
        assert abs(math.exp(reference_log_c(*s)) - mean) <= SIGMAS * se
        assert abs(oracle_log_c(*s) - reference_log_c(*s)) <= 1e-13 * abs(reference_log_c(*s))


def test_large_singular_values_follow_the_laplace_asymptote(backend: Backend) -> None:
    """Far beyond the reference's range (s up to 1e30 in float32, 1e150 in float64) log c is finite and
    equals the leading term of Laplace's method, ``s1 + s2 + s3 - log(pi l1 l2 l3)/2`` with
    ``l_i = 2 (s_j + s_k)``, whose relative error O(1/l) is below 1e-6 there."""
    rotations = Rotation.random(2, random_state=5).as_matrix()
    for dtype, scale in (("float32", 1e30), ("float64", 1e150), ("float64", 1e8)):
        s = np.array([3.0, 2.0, -1.0]) * scale
        matrix = rotations[0] @ np.diag(s) @ rotations[1].T
        x = backend.array(matrix, dtype)
        out = float(backend.to_numpy(backend.module.matrix_fisher_log_normalizer(x)))
        lam = 2 * np.array([s[1] + s[2], s[0] + s[2], s[0] + s[1]])
        asymptote = s.sum() - 0.5 * (math.log(math.pi) + np.log(lam).sum())
        assert abs(out - asymptote) <= 1e-6 * abs(asymptote)


# ---------------------------------------------------------------------------------------------------
# Derivatives: E[R] and Cov(R), where the singular values repeat


def derivative_points() -> np.ndarray:
    """F = 0, multiples of a rotation (all singular values equal: small, in the series' range, and large),
    two equal ones (s2 = s3, s2 = -s3), rank 1, a generic F and a concentrated one."""
    u, v = Rotation.random(2, random_state=11).as_matrix()
    diag = [(0, 0, 0), (1e-3, 1e-3, 1e-3), (0.7, 0.7, 0.7), (5, 5, 5), (3, 1, 1), (3, 1, -1), (2, 0, 0)]
    diag += [(1.5, 0.7, -0.2), (40, 30, 20)]
    return np.array([u @ np.diag(d) @ v.T for d in diag], dtype=np.float64)


def _log_c(backend: Backend, x: Any) -> Any:
    return backend.module.matrix_fisher_log_normalizer(x)


def gradient_and_hessian(backend: Backend, matrices: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Per element, d log c / dF (3, 3) and the 9x9 Hessian, by each framework's autodiff."""
    if backend.name == "torch":
        x = torch.tensor(matrices)
        grad = torch.func.vmap(torch.func.grad(dtorch.matrix_fisher_log_normalizer))(x)
        hess = torch.func.vmap(torch.func.hessian(dtorch.matrix_fisher_log_normalizer))(x)
        return grad.numpy(), hess.reshape(-1, 9, 9).numpy()
    grad, hess = _jax_derivatives(jnp.asarray(matrices))
    return np.asarray(grad), np.asarray(hess).reshape(-1, 9, 9)


@jax.jit
def _jax_derivatives(x: Any) -> tuple[Any, Any]:
    """Compiled: eagerly, jax dispatches the Hessian rule's operations one by one (seconds)."""
    grad = jax.vmap(jax.grad(djax.matrix_fisher_log_normalizer))(x)
    return grad, jax.vmap(jax.hessian(djax.matrix_fisher_log_normalizer))(x)


@pytest.mark.parametrize("name", ["torch", "jax"])
def test_gradient_and_hessian_match_finite_differences_where_singular_values_repeat(name: str) -> None:
    """The gradient E[R] against central differences of log c, and the Hessian against central
    differences of the gradient, at F = 0, at multiples of rotations and at pairs of equal singular
    values (where an SVD's derivative divides by zero); E[R] = 0 and the Hessian is I/3 at F = 0 (the
    covariance of a uniform rotation's entries: E[R_ij R_kl] = delta_ik delta_jl / 3)."""
    backend = BACKENDS[name]
    matrices = derivative_points()
    grad, hess = gradient_and_hessian(backend, matrices)
    assert np.all(np.isfinite(grad)) and np.all(np.isfinite(hess))
    np.testing.assert_array_equal(grad[0], np.zeros((3, 3)))
    np.testing.assert_allclose(hess[0], np.eye(9) / 3, rtol=0, atol=1e-14)
    step = 1e-5
    steps = step * np.eye(9).reshape(9, 1, 3, 3)
    plus = backend.array((matrices[None] + steps).reshape(-1, 3, 3), "float64")
    minus = backend.array((matrices[None] - steps).reshape(-1, 3, 3), "float64")
    values = [backend.to_numpy(_log_c(backend, x)).reshape(9, -1) for x in (plus, minus)]
    fd_grad = ((values[0] - values[1]) / (2 * step)).T.reshape(-1, 3, 3)
    # central differences: O(step^2 |f'''|) ~ 1e-10, rounding O(eps |f| / step) ~ 1e-10
    np.testing.assert_allclose(grad, fd_grad, rtol=0, atol=1e-8)
    grads = [gradient_and_hessian(backend, backend.to_numpy(x))[0].reshape(9, -1, 9) for x in (plus, minus)]
    fd_hess = np.moveaxis((grads[0] - grads[1]) / (2 * step), 0, -1)
    np.testing.assert_allclose(hess, fd_hess, rtol=0, atol=1e-7)
    np.testing.assert_allclose(hess, np.swapaxes(hess, -1, -2), rtol=0, atol=1e-14)


def test_gradient_keeps_its_relative_precision_at_small_f() -> None:
    """At small F, E[R] ~ F/3 keeps its relative precision (it is computed as the deviation from 1/4 of
    the Bingham second moments, never as a difference of near-equal numbers): torch's gradient in
    float32 at |F| = 1e-8 ... 1e-20 equals the float64 one of the same (rounded) F to 1e-6 of its size,
    and that is F/3 (E[R] = F/3 + O(|F|^2)) to the same precision."""
    grad = torch.func.vmap(torch.func.grad(dtorch.matrix_fisher_log_normalizer))
    for scale in (1e-8, 1e-14, 1e-20):
        x32 = torch.tensor(scale * derivative_points()[1:4], dtype=torch.float32)
        single, double = grad(x32).double().numpy(), grad(x32.double()).numpy()
        size = np.abs(double).max(axis=(-2, -1), keepdims=True)
        assert np.all(np.abs(single - double) <= 1e-6 * size)
        assert np.all(np.abs(double - x32.double().numpy() / 3) <= 1e-6 * size)


# ---------------------------------------------------------------------------------------------------
# The density, the sampler and the moments


def test_density_integrates_to_one(backend: Backend) -> None:
    """E_R[exp(-nll(F, R))] = 1 over uniform rotations (scipy's sampler), within 5 standard errors of
    the Monte Carlo mean (400 000 rotations; the density's variance c(2F)/c(F)^2 - 1 is ~10 here)."""
    rotations = Rotation.random(400_000, random_state=4).as_matrix()
    u, v = Rotation.random(2, random_state=9).as_matrix()
    for s in [(2.0, 1.0, -0.5), (1.0, 1.0, 1.0)]:
        matrix = u @ np.diag(s) @ v.T
        f, r = backend.array(matrix, "float64"), backend.array(rotations, "float64")
        nll = backend.module.matrix_fisher_nll(f, r)
        density = np.exp(-backend.to_numpy(nll))
        assert abs(density.mean() - 1.0) <= SIGMAS * density.std() / math.sqrt(len(density))


def draw(backend: Backend, matrix: np.ndarray, shape: Any, seed: int, dtype: str = "float64") -> Any:
    x = backend.array(matrix, dtype)
    if backend.name == "numpy":
        return dnp.matrix_fisher_sample(x, shape, rng=seed)
    if backend.name == "torch":
        return dtorch.matrix_fisher_sample(x, shape, generator=torch.Generator().manual_seed(seed))
    return djax.matrix_fisher_sample(x, shape, key=jax.random.key(seed))


def sampling_points() -> np.ndarray:
    """Uniform (F = 0), moderate, concentrated, and concentrated about one axis only."""
    u, v = Rotation.random(2, random_state=13).as_matrix()
    diag = [(0, 0, 0), (2, 1, -0.5), (30, 20, 10), (1e4, 1e-3, -1e-3)]
    return np.array([u @ np.diag(d) @ v.T for d in diag])


def test_sample_moments_equal_the_mean_and_covariance(backend: Backend) -> None:
    """The sample mean of R equals E[R] (the gradient of log c, torch's autodiff) and the sample
    covariance of its entries equals the Hessian of log c, entry by entry within 5 standard errors
    (each estimated from the draws, 20 000 per F). Samples are rotations."""
    matrices = sampling_points()
    samples = backend.to_numpy(draw(backend, matrices, 20_000, seed=1))
    assert samples.shape == (20_000, len(matrices), 3, 3)
    gram = np.swapaxes(samples, -1, -2) @ samples
    np.testing.assert_allclose(gram, np.broadcast_to(np.eye(3), gram.shape), rtol=0, atol=1e-12)
    np.testing.assert_allclose(np.linalg.det(samples), 1.0, rtol=0, atol=1e-12)
    grad, hess = gradient_and_hessian(BACKENDS["torch"], matrices)
    flat = samples.reshape(len(samples), len(matrices), 9)
    n = len(flat)
    mean = flat.mean(axis=0)
    se = flat.std(axis=0) / math.sqrt(n)
    assert np.all(np.abs(mean - grad.reshape(-1, 9)) <= SIGMAS * se + 1e-12)
    centred = flat - mean
    products = centred[..., :, None] * centred[..., None, :]
    cov, cov_se = products.mean(axis=0), products.std(axis=0) / math.sqrt(n)
    assert np.all(np.abs(cov - hess) <= SIGMAS * cov_se + 1e-12)


@pytest.mark.parametrize("precision", ["float32", "float16", "bfloat16"])
def test_samples_are_rotations_in_every_dtype(backend: Backend, precision: str) -> None:
    samples = draw(backend, sampling_points(), (3, 2), seed=2, dtype=precision)
    assert samples.dtype == backend.dtypes[precision] or str(samples.dtype) == precision
    assert tuple(samples.shape) == (3, 2, 4, 3, 3)
    r = backend.to_numpy(samples)
    tol = {"float32": 1e-5, "float16": 4e-3, "bfloat16": 3e-2}[precision]
    gram = np.swapaxes(r, -1, -2) @ r
    np.testing.assert_allclose(gram, np.broadcast_to(np.eye(3), gram.shape), rtol=0, atol=tol)


def test_sampling_is_reproducible_and_shaped(backend: Backend) -> None:
    """The same seed gives the same draws, another seed others; a NaN F gives NaN samples in its rows
    only; scalar and empty batches. (The shapes of the other sampling tests: jax compiles per shape.)"""
    matrices = sampling_points()
    matrices[3] = np.nan
    a, b, c = (backend.to_numpy(draw(backend, matrices, (3, 2), seed)) for seed in (1, 1, 2))
    np.testing.assert_array_equal(a, b)
    assert not np.allclose(a[..., :3, :, :], c[..., :3, :, :])
    assert np.all(np.isnan(a[..., 3, :, :])) and np.all(np.isfinite(a[..., :3, :, :]))
    assert backend.to_numpy(draw(backend, matrices[1], (), seed=1)).shape == (3, 3)
    assert backend.to_numpy(draw(backend, np.zeros((0, 3, 3)), 4, seed=1)).shape == (4, 0, 3, 3)


def test_jax_sampling_traces_under_jit_and_vmap() -> None:
    matrices = jnp.asarray(sampling_points())
    key = jax.random.key(3)
    eager = djax.matrix_fisher_sample(matrices, (3, 2), key=key)
    jitted = jax.jit(lambda f, k: djax.matrix_fisher_sample(f, (3, 2), key=k))(matrices, key)
    np.testing.assert_allclose(np.asarray(jitted), np.asarray(eager), rtol=0, atol=1e-12)
    keys = jax.random.split(key, len(matrices))
    mapped = jax.vmap(lambda f, k: djax.matrix_fisher_sample(f, 2, key=k))(matrices, keys)
    assert mapped.shape == (len(matrices), 2, 3, 3)


def test_torch_sampling_compiles_and_does_not_require_grad() -> None:
    matrix = torch.tensor(sampling_points(), requires_grad=True)
    out = dtorch.matrix_fisher_sample(matrix, 3)
    assert not out.requires_grad
    torch._dynamo.reset()
    compiled = torch.compile(lambda f: dtorch.matrix_fisher_sample(f, 3), fullgraph=True, backend="aot_eager")
    r = compiled(matrix.detach()).numpy()
    np.testing.assert_allclose(np.swapaxes(r, -1, -2) @ r, np.broadcast_to(np.eye(3), r.shape), atol=1e-12)


# ---------------------------------------------------------------------------------------------------
# torch.distributions.MatrixFisher


def test_torch_distribution_api() -> None:
    matrices = torch.tensor(sampling_points())
    dist = MatrixFisher(matrices)
    assert dist.batch_shape == (4,) and dist.event_shape == (3, 3) and not dist.has_rsample
    draws = dist.sample((7,))
    assert draws.shape == (7, 4, 3, 3) and bool(dist.support.check(draws).all())
    np.testing.assert_allclose(
        dist.log_prob(draws).numpy(), -dtorch.matrix_fisher_nll(matrices, draws).numpy(), rtol=0, atol=0
    )
    torch.testing.assert_close(dist.mode, dtorch.matrix_fisher_mode(matrices))
    grad, _ = gradient_and_hessian(BACKENDS["torch"], sampling_points())
    np.testing.assert_allclose(dist.mean.numpy(), grad, rtol=0, atol=1e-14)
    log_c = dtorch.matrix_fisher_log_normalizer(matrices)
    np.testing.assert_allclose(dist.log_normalizer.numpy(), log_c.numpy())
    expanded = dist.expand((2, 4))
    assert expanded.batch_shape == (2, 4) and expanded.sample().shape == (2, 4, 3, 3)
    # validation: the parameter's shape and values, and the support of log_prob's argument
    with pytest.raises(ValueError, match=r"MatrixFisher: expected F"):
        MatrixFisher(torch.zeros(3, 4))
    with pytest.raises(ValueError):
        MatrixFisher(torch.full((3, 3), float("nan")), validate_args=True)
    with pytest.raises(ValueError):
        MatrixFisher(matrices, validate_args=True).log_prob(2 * draws)
    assert not bool(special_orthogonal.check(-torch.eye(3, dtype=torch.float64)))


def test_torch_distribution_entropy() -> None:
    """The entropy ``log c - tr(F^T E[R])`` (relative to the Haar probability measure: 0 for F = 0)
    equals the Monte Carlo estimate ``-E[log p(R)]`` over its own samples, within 5 standard errors,
    and is differentiable (its gradient ``-Hess(F) F`` matches finite differences)."""
    matrices = torch.tensor(sampling_points()[:3])
    dist = MatrixFisher(matrices)
    entropy = dist.entropy()
    assert float(entropy[0]) == 0.0
    torch.manual_seed(0)
    log_p = dist.log_prob(dist.sample((20_000,)))
    estimate, se = -log_p.mean(0), log_p.std(0) / math.sqrt(len(log_p))
    assert bool(torch.all((entropy - estimate).abs() <= SIGMAS * se + 1e-12))
    x = matrices[1:2].clone().requires_grad_(True)
    assert torch.autograd.gradcheck(lambda f: MatrixFisher(f).entropy(), (x,))


# ---------------------------------------------------------------------------------------------------
# The Bingham NLL of the 10D head: the same family


def davenport_inverse(m: np.ndarray) -> np.ndarray:
    """The F with K(F) = M for a traceless symmetric 4x4 M (scalar-first): ww + xx = 2 F00, etc."""
    f = np.empty((*m.shape[:-2], 3, 3))
    ww = m[..., 0, 0]
    for i, a in enumerate((1, 2, 3)):
        f[..., i, i] = (ww + m[..., a, a]) / 2
    wx, wy, wz = m[..., 0, 1], m[..., 0, 2], m[..., 0, 3]
    xy, xz, yz = m[..., 1, 2], m[..., 1, 3], m[..., 2, 3]
    f[..., 0, 1], f[..., 1, 0] = (xy - wz) / 2, (xy + wz) / 2
    f[..., 0, 2], f[..., 2, 0] = (xz + wy) / 2, (xz - wy) / 2
    f[..., 1, 2], f[..., 2, 1] = (yz - wx) / 2, (yz + wx) / 2
    return f


UPPER = [(0, 0), (0, 1), (0, 2), (0, 3), (1, 1), (1, 2), (1, 3), (2, 2), (2, 3), (3, 3)]


def symmetric(a: np.ndarray) -> np.ndarray:
    m = np.zeros((*a.shape[:-1], 4, 4))
    for k, (i, j) in enumerate(UPPER):
        m[..., i, j] = m[..., j, i] = a[..., k]
    return m


def test_bingham_nll_is_the_matrix_fisher_nll(backend: Backend) -> None:
    """For the 10D head's A, ``exp(-q^T A q) = e^{-tr(A)/4} exp(tr(F^T R(q)))`` for the F with
    ``K(F) = tr(A)/4 I - A``, so the normalised densities are one: ``bingham_nll(a, q) =
    matrix_fisher_nll(F, R(q))``; F's proper singular values are ``tr(A)/4 - (a_0 + a_i)/2`` for A's ascending
    eigenvalues; the head's rotation (A's smallest eigenvector) is the matrix Fisher mode and the
    minimum of the NLL; and ``exp(-bingham_nll)`` integrates to 1 over uniform quaternions."""
    rng = np.random.default_rng(21)
    a = rng.normal(size=(6, 10)) * np.array([[0.01], [0.3], [1.0], [3.0], [30.0], [1000.0]])
    mat = symmetric(a)
    trace = np.trace(mat, axis1=-2, axis2=-1)
    f = davenport_inverse(trace[:, None, None] / 4 * np.eye(4) - mat)
    eig = np.linalg.eigvalsh(mat)
    np.testing.assert_allclose(
        proper_singular_values(f), trace[:, None] / 4 - (eig[:, :1] + eig[:, 1:]) / 2, rtol=1e-12, atol=1e-12
    )
    q = rng.normal(size=(6, 4))
    rotation = Rotation.from_quat(q, scalar_first=True).as_matrix()
    dq = backend.module
    arr = lambda x: backend.array(x, "float64")  # noqa: E731
    bingham = backend.to_numpy(dq.bingham_nll(arr(a), arr(q)))
    fisher = backend.to_numpy(dq.matrix_fisher_nll(arr(f), arr(rotation)))
    np.testing.assert_allclose(bingham, fisher, rtol=1e-12, atol=1e-12 * np.abs(a).sum())
    head = backend.to_numpy(dq.symmetric_matrix_to_quaternion(arr(a)))
    mode = backend.to_numpy(dq.matrix_fisher_mode(arr(f)))
    np.testing.assert_allclose(Rotation.from_quat(head, scalar_first=True).as_matrix(), mode, atol=1e-8)
    at_mode = backend.to_numpy(dq.bingham_nll(arr(a), arr(head)))
    others = backend.to_numpy(dq.bingham_nll(arr(a[:, None]), arr(rng.normal(size=(6, 100, 4)))))
    assert np.all(at_mode[:, None] <= others + 1e-12)
    uniform = Rotation.random(400_000, random_state=8).as_quat(scalar_first=True)
    density = np.exp(-backend.to_numpy(dq.bingham_nll(arr(a[1]), arr(uniform))))
    assert abs(density.mean() - 1) <= SIGMAS * density.std() / math.sqrt(len(density))


@pytest.mark.skipif(not torch.cuda.is_available(), reason="no CUDA device")
def test_cuda_matches_the_cpu() -> None:
    """On a GPU (cuSOLVER's eigh, the constants placed on the device): the normaliser, its gradient and
    the Bingham NLL equal the CPU's to rounding, and the sampler draws rotations on the device."""
    f = torch.tensor(derivative_points())
    for dtype, tol in ((torch.float64, 1e-10), (torch.float32, 1e-3)):
        cpu = f.to(dtype).requires_grad_(True)
        gpu = f.to(dtype).cuda().requires_grad_(True)
        values = [dtorch.matrix_fisher_log_normalizer(x) for x in (cpu, gpu)]
        grads = [torch.autograd.grad(v.sum(), x)[0] for v, x in zip(values, (cpu, gpu), strict=True)]
        torch.testing.assert_close(values[1].cpu(), values[0], rtol=tol, atol=tol)
        torch.testing.assert_close(grads[1].cpu(), grads[0], rtol=tol, atol=tol)
        a, q = torch.randn(8, 10, dtype=dtype), torch.randn(8, 4, dtype=dtype)
        torch.testing.assert_close(dtorch.bingham_nll(a.cuda(), q.cuda()).cpu(), dtorch.bingham_nll(a, q))
        r = dtorch.matrix_fisher_sample(gpu.detach(), 3)
        assert r.device == gpu.device and r.dtype == dtype
        eye = torch.eye(3, dtype=dtype, device=r.device)
        assert float((r.mT @ r - eye).abs().max()) < 10 * torch.finfo(dtype).eps
