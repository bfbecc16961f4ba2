"""What the table cannot express for the network-output representations: the documented results and
bounded gradients at the singular inputs (where no derivative exists, so there is nothing to compare
with finite differences), and fit_rotation's broadcasting and shape errors."""

from __future__ import annotations

from typing import Any

import jax
import jax.numpy as jnp
import numpy as np
import pytest
import torch
from cases import oracle_fit_rotation, oracle_special_procrustes, uniform_quaternions
from conftest import BACKENDS
from scipy.spatial.transform import Rotation

import diffquat.numpy as dn

SQRT_EPS = float(np.finfo(np.float64).eps) ** 0.5


def gradients(name: str, fn: Any, x: np.ndarray, cot: np.ndarray) -> np.ndarray:
    if name == "torch":
        t = torch.tensor(x, requires_grad=True)
        (g,) = torch.autograd.grad(fn(t), t, torch.tensor(cot))
        return g.numpy()
    _, pullback = jax.vjp(fn, jnp.asarray(x))
    return np.asarray(pullback(jnp.asarray(cot))[0])


# Matrices whose nearest rotation is not unique: rank 1, zero, and det < 0 with s_2 = s_3.
SINGULAR_MATRICES = np.stack([np.diag([2.0, 0.0, 0.0]), np.zeros((3, 3)), np.diag([2.0, 1.0, -1.0])])


@pytest.mark.parametrize("name", ["torch", "jax"])
def test_procrustes_gradient_is_finite_and_bounded_where_no_derivative_exists(name: str) -> None:
    module = BACKENDS[name].module
    cot = np.random.default_rng(0).normal(size=SINGULAR_MATRICES.shape)
    g = gradients(name, module.special_procrustes, SINGULAR_MATRICES, cot)
    s1 = np.maximum(np.linalg.svd(SINGULAR_MATRICES, compute_uv=False)[:, 0], SQRT_EPS)  # M = 0: delta = 1
    bound = 2 * np.linalg.norm(cot, axis=(-1, -2)) / (SQRT_EPS * s1)
    assert np.all(np.isfinite(g))
    assert np.all(np.linalg.norm(g, axis=(-1, -2)) <= bound)
    out = BACKENDS[name].to_numpy(
        module.special_procrustes(BACKENDS[name].array(SINGULAR_MATRICES, "float64"))
    )
    np.testing.assert_allclose(out, oracle_special_procrustes(SINGULAR_MATRICES), atol=1e-15)


def test_procrustes_gradient_at_the_identity_is_the_skew_projection() -> None:
    """At M = I (three equal singular values, where torch.linalg.svd's backward divides by zero),
    dR = (dM - dM^T)/2: the gradient is the skew part of the cotangent, exactly."""
    cot = np.random.default_rng(1).normal(size=(3, 3))
    for name in ("torch", "jax"):
        g = gradients(name, BACKENDS[name].module.special_procrustes, np.eye(3), cot)
        np.testing.assert_allclose(g, 0.5 * (cot - cot.T), atol=1e-7)  # delta's relative 1e-8 bias


@pytest.mark.parametrize("name", ["numpy", "torch", "jax"])
def test_rotation_6d_degenerate_inputs_give_the_documented_rotations(name: str) -> None:
    backend = BACKENDS[name]
    d6 = np.array(
        [
            [0.0, 0.0, 0.0, 0.0, 0.0, 0.0],  # zero: the identity
            [0.0, 0.0, 3.0, 0.0, 0.0, 0.0],  # a2 = 0: b2 from e_x (least aligned with b1 = e_z)
            [1.0, 2.0, 2.0, -2.0, -4.0, -4.0],  # a2 parallel to a1: b2 from e_x
            [0.0, 0.0, 0.0, 0.0, 5.0, 0.0],  # a1 = 0: b1 = e_x, then a2 = e_y
        ]
    )
    out = backend.to_numpy(backend.module.rotation_6d_to_matrix(backend.array(d6, "float64")))
    b1 = np.array([1.0, 2.0, 2.0]) / 3
    b2 = np.array([1.0, 0.0, 0.0]) - b1[0] * b1
    b2 /= np.linalg.norm(b2)
    expected = np.stack(
        [
            np.eye(3),
            np.stack([[0.0, 0, 1], [1.0, 0, 0], [0.0, 1, 0]], axis=-1),
            np.stack([b1, b2, np.cross(b1, b2)], axis=-1),
            np.eye(3),
        ]
    )
    np.testing.assert_allclose(out, expected, atol=1e-15)
    if backend.differentiable:
        cot = np.random.default_rng(2).normal(size=out.shape)
        assert np.all(np.isfinite(gradients(name, backend.module.rotation_6d_to_matrix, d6, cot)))


@pytest.mark.parametrize("name", ["torch", "jax"])
def test_10d_gradient_is_finite_and_bounded_at_a_repeated_smallest_eigenvalue(name: str) -> None:
    module = BACKENDS[name].module
    a = np.array([[0.0] * 10, [1.0, 0, 0, 0, 1.0, 0, 0, 2.0, 0, 3.0]])  # A = 0; diag(1, 1, 2, 3)
    cot = np.random.default_rng(3).normal(size=(2, 4))
    g = gradients(name, module.symmetric_matrix_to_quaternion, a, cot)
    size = np.maximum(np.abs(a).sum(-1), SQRT_EPS)  # A = 0: delta = 1
    assert np.all(np.isfinite(g))
    assert np.all(np.linalg.norm(g, axis=-1) <= 4 * np.linalg.norm(cot, axis=-1) / (SQRT_EPS * size))


def test_6d_round_trip_and_pytorch3d_convention() -> None:
    """Columns, not rows: the 6D of R is (R[:, 0], R[:, 1]), and back gives R."""
    r = dn.quaternion_to_matrix(uniform_quaternions(8, seed=5))
    d6 = dn.matrix_to_rotation_6d(r)
    np.testing.assert_array_equal(d6[:, :3], r[:, :, 0])
    np.testing.assert_allclose(dn.rotation_6d_to_matrix(d6), r, atol=1e-15)


@pytest.mark.parametrize("name", ["numpy", "torch", "jax"])
def test_pytorch3d_6d_layout_round_trips_with_layout_rows(name: str) -> None:
    """pytorch3d's 6D is the first two rows of R, flattened (its matrix_to_rotation_6d drops the last
    row; its rotation_6d_to_matrix stacks b1, b2, b3 as rows). Written here from that definition, not
    from pytorch3d (not installed): ``layout="rows"`` reads and writes it exactly, and the default
    layout reads the same numbers as the inverse rotation, the trap of a ported checkpoint."""
    module, backend = BACKENDS[name].module, BACKENDS[name]
    r = Rotation.random(16, random_state=7).as_matrix()
    pytorch3d_d6 = r[:, :2, :].reshape(16, 6)
    d6 = backend.array(pytorch3d_d6, "float64")
    np.testing.assert_allclose(
        backend.to_numpy(module.rotation_6d_to_matrix(d6, layout="rows")), r, atol=1e-15
    )
    np.testing.assert_allclose(
        backend.to_numpy(module.matrix_to_rotation_6d(backend.array(r, "float64"), layout="rows")),
        pytorch3d_d6,
        atol=0,
    )
    inverse = backend.to_numpy(module.rotation_6d_to_matrix(d6))
    np.testing.assert_allclose(inverse, np.swapaxes(r, -1, -2), atol=1e-15)
    for fn, x in [("rotation_6d_to_matrix", d6), ("matrix_to_rotation_6d", backend.array(r, "float64"))]:
        with pytest.raises(ValueError, match=f"{fn}: expected layout 'columns' or 'rows', got 'row'"):
            getattr(module, fn)(x, layout="row")


@pytest.mark.parametrize("name", ["numpy", "torch", "jax"])
def test_fit_rotation_broadcasts_and_checks_the_number_of_points(name: str) -> None:
    backend = BACKENDS[name]
    rng = np.random.default_rng(4)
    source, target, weights = rng.normal(size=(6, 3)), rng.normal(size=(2, 6, 3)), rng.random(6)
    out = backend.module.fit_rotation(*(backend.array(x, "float64") for x in (source, target, weights)))
    expected = oracle_fit_rotation(
        np.broadcast_to(source, (2, 6, 3)), target, np.broadcast_to(weights, (2, 6))
    )
    np.testing.assert_allclose(backend.to_numpy(out), expected, atol=1e-12)
    with pytest.raises(ValueError, match="fit_rotation: expected the same number of points N"):
        backend.module.fit_rotation(*(backend.array(x, "float64") for x in (source, target[:, :5])))
