"""Rotation averaging and symmetric objects beyond the table rows (tests/cases.py): the means against
scipy and against the iterated references at 1e-12 in float64, the median's robustness and its
result at a sample, the implicit derivatives against finite differences on tight and wide clusters,
the weights' edge cases, the symmetry groups against scipy's, and the symmetric distance's invariance,
ties and gradient."""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np
import pytest
import torch
from cases import only, oracle_geodesic_mean, oracle_matrix_distance
from conftest import BACKENDS, Backend
from scipy.spatial.transform import Rotation

METHODS = ("chordal", "geodesic", "geodesic_l1")
GROUPS = ("C1", "C2", "C3", "C5", "C12", "D1", "D2", "D3", "D4", "D7", "T", "O", "I")
differentiable = only(backend=lambda b: b in ("torch", "jax"))


def cluster(
    sets: int, n: int, radius: float, seed: int, outliers: int = 0
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """``sets`` clusters of ``n`` rotation matrices (sets, n, 3, 3) around random centres, each sample
    a rotation by up to ``radius`` rad from its centre (the first ``outliers`` samples 1.5-2.5 rad
    away instead), positive weights (sets, n), and the centres (sets, 3, 3). scipy's sampler."""
    rng = np.random.default_rng(seed)
    centres = Rotation.random(sets, random_state=seed)
    v = rng.normal(size=(sets, n, 3))
    length = rng.uniform(0.2, 1.0, size=(sets, n, 1)) * radius
    length[:, :outliers] = rng.uniform(1.5, 2.5, size=(sets, outliers, 1))
    v *= length / np.linalg.norm(v, axis=-1, keepdims=True)
    samples = Rotation.from_quat(np.repeat(centres.as_quat()[:, None], n, 1)) * Rotation.from_rotvec(v)
    return samples.as_matrix(), rng.uniform(0.2, 2.0, size=(sets, n)), centres.as_matrix()


def logs(mean: np.ndarray, samples: np.ndarray) -> np.ndarray:
    """scipy's ``log(mean^T R_i)`` (sets, n, 3)."""
    n = samples.shape[1]
    base = Rotation.from_matrix(np.repeat(mean[:, None], n, 1).reshape(-1, 3, 3))
    return (base.inv() * Rotation.from_matrix(samples.reshape(-1, 3, 3))).as_rotvec().reshape(-1, n, 3)


def angle(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    return np.asarray(oracle_matrix_distance(a, b))


def call(backend: Backend, fn: Callable[..., Any], *xs: np.ndarray, **kw: Any) -> np.ndarray:
    return backend.to_numpy(fn(*(backend.array(x, "float64") for x in xs), **kw))


# ---------------------------------------------------------------------------------------------------
# The means


def test_chordal_mean_is_scipys_and_markleys(backend: Backend) -> None:
    """The chordal mean of matrices is scipy's ``Rotation.mean``, and Markley's mean of the quaternions
    (of any norm and sign) is the same rotation."""
    dq = backend.module
    matrices, weights, _ = cluster(16, 7, 1.2, seed=0)
    expected = Rotation.from_matrix(matrices).mean(weights=weights, axis=-1)
    chordal = call(backend, dq.rotation_mean, matrices, weights)
    np.testing.assert_allclose(chordal, expected.as_matrix(), rtol=0, atol=1e-13)
    signs = np.random.default_rng(1).choice([-3.0, 0.5, 2.0], size=(16, 7, 1))
    q = Rotation.from_matrix(matrices).as_quat(scalar_first=True) * signs
    markley = call(backend, dq.quaternion_mean, q, weights)
    np.testing.assert_allclose(
        markley, expected.as_quat(canonical=True, scalar_first=True), rtol=0, atol=1e-13
    )


@pytest.mark.parametrize("radius", [1e-3, 1.0, 1.5])
def test_karcher_mean_is_stationary_in_float64(backend: Backend, radius: float) -> None:
    """``sum_i w_i log(R^T R_i) = 0`` to 1e-12 (scipy's logarithm, weights summing to 1), for clusters
    up to 1.5 rad from their centre, and the same rotation as the textbook gradient iteration."""
    matrices, weights, _ = cluster(32, 9, radius, seed=2)
    mean = call(backend, backend.module.rotation_mean, matrices, weights, method="geodesic")
    residual = np.sum(weights[..., None] * logs(mean, matrices), axis=-2) / weights.sum(-1, keepdims=True)
    assert np.abs(residual).max() <= 1e-12 * radius
    np.testing.assert_allclose(mean, oracle_geodesic_mean(matrices, weights), rtol=0, atol=1e-12)


@pytest.mark.parametrize("radius", [1e-3, 1.0])
def test_median_is_stationary_in_float64(backend: Backend, radius: float) -> None:
    """The optimality condition of the median, ``|sum_i w_i n_i| <= (weight of the samples at it)`` (unit
    vectors ``n_i`` towards the other samples, weights summing to 1), to 1e-12 (1e-10 for a cluster of
    1e-3 rad, where the unit vector of a log ~1e-4 long is known to ~eps / 1e-4); and, where the median
    is no sample, the same rotation as Weiszfeld's iteration."""
    matrices, weights, _ = cluster(32, 9, radius, seed=3)
    median = call(backend, backend.module.rotation_mean, matrices, weights, method="geodesic_l1")
    w = weights / weights.sum(-1, keepdims=True)
    v = logs(median, matrices)
    t = np.linalg.norm(v, axis=-1)
    at = t < 1e-14
    pull = np.linalg.norm(np.sum(w[..., None] * v / np.where(at, 1.0, t)[..., None], axis=-2), axis=-1)
    assert np.all(pull - np.sum(np.where(at, w, 0.0), axis=-1) <= (1e-12 if radius > 0.1 else 1e-10))
    free = ~at.any(-1)
    assert free.sum() > 16
    expected = oracle_geodesic_mean(matrices[free], weights[free], l1=True)
    np.testing.assert_allclose(median[free], expected, rtol=0, atol=1e-12)


def test_median_resists_outliers(backend: Backend) -> None:
    """Three outliers 1.5-2.5 rad away among ten samples: the median stays within the inliers' radius
    (0.05 rad) of their centre, where the chordal and the Karcher means are pulled away by 0.1 rad and
    more."""
    dq = backend.module
    matrices, weights, centres = cluster(16, 10, 0.05, seed=4, outliers=3)
    weights = np.ones_like(weights)
    median = call(backend, dq.rotation_mean, matrices, weights, method="geodesic_l1")
    assert angle(median, centres).max() < 0.05
    for method in ("chordal", "geodesic"):
        assert angle(call(backend, dq.rotation_mean, matrices, weights, method=method), centres).min() > 0.1


def test_median_at_a_sample_is_that_sample(backend: Backend) -> None:
    """A sample holding more than half of the weight outweighs the pull of all the others: the median
    is that sample, exactly (to the rounding of matrix -> quaternion -> matrix)."""
    matrices, weights, _ = cluster(16, 6, 1.0, seed=5)
    weights[:, 2] = weights.sum(-1)  # more than half of the total
    median = call(backend, backend.module.rotation_mean, matrices, weights, method="geodesic_l1")
    np.testing.assert_allclose(median, matrices[:, 2], rtol=0, atol=2e-15)


@pytest.mark.parametrize("method", METHODS)
def test_equal_weights_are_no_weights(backend: Backend, method: str) -> None:
    dq = backend.module
    matrices, weights, _ = cluster(8, 5, 1.0, seed=6)
    ones = np.full(weights.shape, 0.7)
    np.testing.assert_allclose(
        call(backend, dq.rotation_mean, matrices, ones, method=method),
        call(backend, dq.rotation_mean, matrices, method=method),
        rtol=0,
        atol=2e-15,
    )
    q = Rotation.from_matrix(matrices).as_quat(scalar_first=True)
    np.testing.assert_allclose(
        call(backend, dq.quaternion_mean, q, ones), call(backend, dq.quaternion_mean, q), rtol=0, atol=2e-15
    )


def test_weights_summing_to_zero_and_no_samples_give_the_identity(backend: Backend) -> None:
    """The documented result where no mean is defined: the identity (as scipy's ``Rotation.mean`` with
    zero weights), for every method, and for zero samples; batch shapes broadcast."""
    dq = backend.module
    matrices = cluster(3, 4, 1.0, seed=7)[0]
    for method in METHODS:
        out = call(backend, dq.rotation_mean, matrices, np.zeros((2, 1, 4)), method=method)
        np.testing.assert_array_equal(out, np.broadcast_to(np.eye(3), (2, 3, 3, 3)))
        out = call(backend, dq.rotation_mean, np.zeros((3, 0, 3, 3)), method=method)
        np.testing.assert_array_equal(out, np.broadcast_to(np.eye(3), (3, 3, 3)))
    q = Rotation.from_matrix(matrices).as_quat(scalar_first=True)
    np.testing.assert_array_equal(
        call(backend, dq.quaternion_mean, q, np.zeros((3, 4))), [[1.0, 0, 0, 0]] * 3
    )
    np.testing.assert_array_equal(
        call(backend, dq.quaternion_mean, np.zeros((2, 0, 4))), [[1.0, 0, 0, 0]] * 2
    )


def test_unknown_method_raises_naming_the_function(backend: Backend) -> None:
    matrices, _, _ = cluster(1, 3, 1.0, seed=8)
    with pytest.raises(ValueError, match=r"rotation_mean: method must be one of 'chordal', 'geodesic'"):
        backend.module.rotation_mean(backend.array(matrices, "float64"), method="karcher")


# ---------------------------------------------------------------------------------------------------
# Implicit derivatives


def jacobians(backend: Backend, fn: Callable[..., Any], xs: list[np.ndarray]) -> list[np.ndarray]:
    """Per set, the Jacobian of ``fn``'s output (sets, *out) w.r.t. each input (sets, *in), reverse
    mode: (sets, n_out, n_in) per input (the sets are independent)."""
    sets = len(xs[0])
    if backend.name == "torch":
        full = torch.autograd.functional.jacobian(fn, tuple(torch.tensor(x) for x in xs))
        full = [j.numpy() for j in full]
    else:
        full = [np.asarray(j) for j in jax.jacrev(fn, argnums=tuple(range(len(xs))))(*map(jnp.asarray, xs))]
    out = []
    for j, x in zip(full, xs, strict=True):
        j = j.reshape(sets, -1, sets, x[0].size)
        out.append(j[np.arange(sets), :, np.arange(sets)])
    return out


def finite_differences(fn: Callable[..., Any], xs: list[np.ndarray], step: float) -> list[np.ndarray]:
    """The same Jacobians by central differences (every set moved at once: they are independent)."""
    sets = len(xs[0])
    out = []
    for i, x in enumerate(xs):
        flat = x.reshape(sets, -1)
        cols = []
        for k in range(flat.shape[1]):
            moved = [flat.copy(), flat.copy()]
            moved[0][:, k] += step
            moved[1][:, k] -= step
            values = [np.asarray(fn(*xs[:i], m.reshape(x.shape), *xs[i + 1 :])) for m in moved]
            cols.append((values[0] - values[1]).reshape(sets, -1) / (2 * step))
        out.append(np.stack(cols, axis=-1))
    return out


@differentiable
@pytest.mark.parametrize("radius", [1e-3, 1.0], ids=["tight", "wide"])
@pytest.mark.parametrize("method", METHODS)
def test_gradients_match_finite_differences(backend: Backend, method: str, radius: float) -> None:
    """The implicit derivatives (and the chordal mean's SVD derivative) are the derivatives of the
    computed means, in every direction of the 3x3 inputs and of the weights, on clusters of 1e-3 rad
    and of 1 rad. The derivative of a mean with respect to a sample stays of order 1 however tight the
    cluster; its second derivative grows as 1 / radius, so the step shrinks with it."""
    dq = backend.module
    matrices, weights, _ = cluster(4, 5, radius, seed=9)

    def fn(m: Any, w: Any) -> Any:
        return dq.rotation_mean(m, w, method=method)

    numpy_fn = lambda m, w: dq.rotation_mean(m, w, method=method)  # noqa: E731
    if backend.name == "torch":
        evaluate = lambda m, w: numpy_fn(torch.tensor(m), torch.tensor(w)).numpy()  # noqa: E731
    else:
        evaluate = jax.jit(numpy_fn)
    ad = jacobians(backend, fn, [matrices, weights])
    fd = finite_differences(evaluate, [matrices, weights], step=1e-6 * min(1.0, 10 * radius))
    for a, f in zip(ad, fd, strict=True):
        assert np.all(np.isfinite(a))
        np.testing.assert_allclose(a, f, rtol=0, atol=2e-6 * max(1.0, float(np.abs(f).max())))


@differentiable
def test_gradient_of_the_median_at_a_sample_follows_that_sample(backend: Backend) -> None:
    """Where the median is a sample (strictly outweighing the others' pull), it moves with that sample
    only: its Jacobian is that of R_j with respect to itself (the projection onto rotations of
    matrix_to_quaternion), and zero for the other samples and the weights."""
    dq = backend.module
    matrices, weights, _ = cluster(3, 5, 1.0, seed=10)
    weights[:, 1] = weights.sum(-1)
    median_jacobians = jacobians(
        backend, lambda m, w: dq.rotation_mean(m, w, method="geodesic_l1"), [matrices, weights]
    )
    sample_jacobian = jacobians(
        backend, lambda m: dq.quaternion_to_matrix(dq.matrix_to_quaternion(m)), [matrices[:, 1]]
    )[0]
    by_sample = median_jacobians[0].reshape(3, 9, 5, 9)
    np.testing.assert_allclose(by_sample[:, :, 1], sample_jacobian, rtol=0, atol=1e-12)
    assert np.all(by_sample[:, :, [0, 2, 3, 4]] == 0)
    assert np.all(median_jacobians[1] == 0)


@differentiable
def test_gradients_are_finite_where_the_mean_is_not_unique(backend: Backend) -> None:
    """Where no derivative exists, the gradients are finite (the regularised systems, documented), in
    one batch of sets of four samples: weights summing to zero (two sets); two rotations a half-turn
    apart (no unique Karcher mean or median); the median of two samples (any point between them);
    a median at two coincident samples. Samples of zero weight fill the pairs up to four."""
    dq = backend.module
    others, _, _ = cluster(5, 2, 1.0, seed=11)
    rz, rx = Rotation.from_rotvec([[0.0, 0.0, np.pi], [0.4, 0.0, 0.0]]).as_matrix()
    eye = np.eye(3)
    firsts = np.stack([others[0], others[1], np.stack([eye, rz]), np.stack([eye, rx]), np.stack([eye, eye])])
    matrices = np.concatenate([firsts, others], axis=1)  # (5, 4, 3, 3)
    weights = np.array([[0.0] * 4, [0.0] * 4, [1, 1, 0, 0], [1, 1, 0, 0], [1, 1, 0.5, 0.4]], dtype=float)
    for method in METHODS:
        if backend.name == "torch":
            m, w = torch.tensor(matrices, requires_grad=True), torch.tensor(weights, requires_grad=True)
            out = dq.rotation_mean(m, w, method=method)
            grads = [g.numpy() for g in torch.autograd.grad((out * out).sum(), (m, w))]
        else:

            def loss(m: Any, w: Any, method: str = method) -> Any:
                return (dq.rotation_mean(m, w, method=method) ** 2).sum()

            grads = [np.asarray(g) for g in jax.grad(loss, argnums=(0, 1))(matrices, weights)]
        assert all(np.all(np.isfinite(g)) for g in grads), method


# ---------------------------------------------------------------------------------------------------
# Symmetric objects


@pytest.mark.parametrize("name", GROUPS)
def test_symmetry_group_is_scipys(backend: Backend, name: str) -> None:
    """The same set of rotations as scipy's ``Rotation.create_group`` (its default axis z), identity
    first, in the backend's default floating dtype or the one asked for."""
    group = backend.module.symmetry_group(name)
    assert str(group.dtype).endswith({"numpy": "float64", "torch": "float32", "jax": "float64"}[backend.name])
    group = backend.to_numpy(backend.module.symmetry_group(name, dtype=backend.dtypes["float64"]))
    expected = Rotation.create_group(name).as_matrix()
    assert group.shape == expected.shape
    distance = np.abs(group[:, None] - expected[None]).max(axis=(-1, -2))
    assert np.all(distance.min(axis=1) < 4e-15) and np.all(distance.min(axis=0) < 4e-15)
    np.testing.assert_array_equal(group[0], np.eye(3))
    np.testing.assert_allclose(
        group @ np.swapaxes(group, -1, -2), np.broadcast_to(np.eye(3), group.shape), atol=1e-15
    )


def test_symmetry_group_on_a_device_and_errors() -> None:
    import diffquat.torch as dq

    group = dq.symmetry_group("O", dtype=torch.float64, device="meta")
    assert group.device.type == "meta" and group.dtype == torch.float64 and group.shape == (24, 3, 3)
    for backend in BACKENDS.values():
        for name in ("C0", "D", "X", "c4", "D-2", "T2", "", 4):
            with pytest.raises(ValueError, match=r"symmetry_group: expected 'C<n>' or 'D<n>'"):
                backend.module.symmetry_group(name)


@pytest.mark.parametrize("name", ["C4", "D3", "T", "O", "I"])
def test_symmetric_distance_is_invariant_under_the_group(backend: Backend, name: str) -> None:
    """``d(R1, R2 g) = d(R1, R2)`` for every g of the group, and both are the brute-force minimum over
    scipy's group of scipy's distance."""
    dq = backend.module
    group = Rotation.create_group(name).as_matrix()
    r1, r2 = (Rotation.random(16, random_state=s).as_matrix() for s in (12, 13))
    moved = r2[:, None] @ group[None]  # (16, G, 3, 3): R2 g for every g
    d = call(backend, dq.symmetric_geodesic_distance, r1[:, None], moved, group)
    expected = np.min([angle(r1, r2 @ g) for g in group], axis=0)
    np.testing.assert_allclose(d, np.broadcast_to(expected[:, None], d.shape), rtol=0, atol=1e-13)


@differentiable
def test_symmetric_distance_ties_take_the_first_element(backend: Backend) -> None:
    """R2 a quarter-turn about z from R1, and the group C2 about z: the identity and the half-turn give
    the same distance (pi / 2). The first element (the identity) is chosen, on every backend: the
    gradient is that of ``matrix_geodesic_distance(R1, R2)``, and it is finite."""
    dq = backend.module
    r1 = Rotation.random(4, random_state=14).as_matrix()
    r2 = r1 @ Rotation.from_rotvec([0.0, 0.0, np.pi / 2]).as_matrix()
    group = backend.module.symmetry_group("C2", dtype=backend.dtypes["float64"])
    if backend.name == "torch":
        a, b = torch.tensor(r1, requires_grad=True), torch.tensor(r2, requires_grad=True)
        tie = torch.autograd.grad(dq.symmetric_geodesic_distance(a, b, group).sum(), (a, b))
        plain = torch.autograd.grad(dq.matrix_geodesic_distance(a, b).sum(), (a, b))
    else:
        tie = jax.grad(lambda a, b: dq.symmetric_geodesic_distance(a, b, group).sum(), argnums=(0, 1))(r1, r2)
        plain = jax.grad(lambda a, b: dq.matrix_geodesic_distance(a, b).sum(), argnums=(0, 1))(r1, r2)
    for g, p in zip(tie, plain, strict=True):
        np.testing.assert_allclose(np.asarray(g), np.asarray(p), rtol=0, atol=1e-12)
    value = call(backend, dq.symmetric_geodesic_distance, r1, r2, np.asarray(group))
    np.testing.assert_allclose(value, np.pi / 2, rtol=0, atol=1e-14)


def test_symmetric_distance_needs_a_group(backend: Backend) -> None:
    r = backend.array(np.eye(3), "float64")
    with pytest.raises(ValueError, match=r"symmetric_geodesic_distance: expected a group of at least one"):
        backend.module.symmetric_geodesic_distance(r, r, backend.array(np.zeros((0, 3, 3)), "float64"))
