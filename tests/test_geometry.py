"""What the table of operations cannot say in one row: all 24 Euler conventions against scipy, the
algebra's properties, broadcasting between two inputs, and the promises at pi and at equal rotations."""

from __future__ import annotations

from typing import Any

import numpy as np
import pytest
from cases import (
    CASES_BY_NAME,
    Case,
    only,
    oracle_normalize,
    oracle_quaternion_to_matrix,
    uniform_quaternions,
)
from conftest import Backend
from scipy.spatial.transform import Rotation

SEQUENCES = [a + b + c for a in "xyz" for b in "xyz" for c in "xyz" if a != b and b != c]
CONVENTIONS = SEQUENCES + [s.upper() for s in SEQUENCES]


def wrapped(angles: np.ndarray) -> np.ndarray:
    return np.mod(angles + np.pi, 2 * np.pi) - np.pi


@pytest.mark.parametrize("convention", CONVENTIONS)
def test_euler_angles_agree_with_scipy_in_every_convention(backend: Backend, convention: str) -> None:
    """float64, random rotations and exact gimbal locks, both directions, radians and degrees."""
    dq = backend.module
    q = np.concatenate(
        [uniform_quaternions(32, seed=20), CASES_BY_NAME["gimbal_lock"].quaternions("float64")]
    )
    rot = Rotation.from_quat(q, scalar_first=True)
    angles = rot.as_euler(convention, suppress_warnings=True)
    assert np.any(np.all(angles == angles * [1, 1, 0], axis=-1)), "no gimbal lock among the inputs"

    def arr(x: np.ndarray) -> Any:
        return backend.array(x, "float64")

    out = {
        "to_matrix": dq.euler_angles_to_matrix(arr(angles), convention),
        "to_quaternion": dq.euler_angles_to_quaternion(arr(angles), convention),
        "from_matrix": dq.matrix_to_euler_angles(arr(rot.as_matrix()), convention),
        "from_quaternion": dq.quaternion_to_euler_angles(arr(q), convention),
        "degrees": dq.quaternion_to_euler_angles(arr(q), convention, degrees=True),
        "from_degrees": dq.euler_angles_to_matrix(arr(np.degrees(angles)), convention, degrees=True),
    }
    out = {k: backend.to_numpy(v) for k, v in out.items()}
    expected_matrix = Rotation.from_euler(convention, angles).as_matrix()
    np.testing.assert_allclose(out["to_matrix"], expected_matrix, atol=1e-12)
    np.testing.assert_allclose(out["from_degrees"], expected_matrix, atol=1e-12)
    np.testing.assert_allclose(
        out["to_quaternion"], Rotation.from_euler(convention, angles).as_quat(scalar_first=True), atol=1e-12
    )
    for key in ("from_matrix", "from_quaternion"):
        np.testing.assert_allclose(wrapped(out[key] - angles), 0, atol=1e-12, err_msg=key)
    np.testing.assert_allclose(wrapped(np.radians(out["degrees"]) - angles), 0, atol=1e-12)


@pytest.mark.parametrize("name", ["numpy"])
def test_bad_euler_convention_raises_naming_the_function(name: str) -> None:
    import diffquat.numpy as dq

    angles, q, m = np.zeros(3), np.array([1.0, 0, 0, 0]), np.eye(3)
    calls = {
        "euler_angles_to_matrix": lambda c: dq.euler_angles_to_matrix(angles, c),
        "euler_angles_to_quaternion": lambda c: dq.euler_angles_to_quaternion(angles, c),
        "matrix_to_euler_angles": lambda c: dq.matrix_to_euler_angles(m, c),
        "quaternion_to_euler_angles": lambda c: dq.quaternion_to_euler_angles(q, c),
    }
    for fname, call in calls.items():
        for bad in ("XXY", "XYz", "xy", "xyzx", "abc", "XYY"):
            with pytest.raises(ValueError, match=f"{fname}: expected convention"):
                call(bad)


@only(case=lambda c: c.name != "zero")  # zero times p is zero, the identity: not R(p)
def test_product_of_quaternions_is_product_of_matrices(backend: Backend, dtype: str, case: Case) -> None:
    dq = backend.module
    q = case.quaternions(dtype)
    p = uniform_quaternions(int(np.prod(q.shape[:-1])) or 1, seed=30)[: int(np.prod(q.shape[:-1]))]
    p = p.reshape(q.shape)
    pb, qb = backend.array(p, dtype), backend.array(q, dtype)
    lhs = backend.to_numpy(dq.quaternion_to_matrix(dq.quaternion_multiply(pb, qb)))
    rhs = backend.to_numpy(dq.quaternion_to_matrix(pb)) @ backend.to_numpy(dq.quaternion_to_matrix(qb))
    tol = {"float64": 1e-12, "float32": 4e-6, "float16": 8e-3, "bfloat16": 6e-2}[dtype]
    np.testing.assert_allclose(lhs, rhs, atol=tol)


def test_two_inputs_broadcast_their_batch_dimensions(backend: Backend) -> None:
    dq = backend.module
    p = uniform_quaternions((5, 1), seed=31)
    q = uniform_quaternions((3,), seed=32)
    v = np.random.default_rng(33).normal(size=(2, 1, 1, 3))
    t = np.linspace(0.1, 0.9, 3)
    full_p, full_q = np.broadcast_to(p, (5, 3, 4)).copy(), np.broadcast_to(q, (5, 3, 4)).copy()

    def run(fn: Any, *xs: np.ndarray) -> np.ndarray:
        return backend.to_numpy(fn(*(backend.array(x, "float64") for x in xs)))

    for fn in (dq.quaternion_multiply, dq.quaternion_geodesic_distance):
        np.testing.assert_allclose(run(fn, p, q), run(fn, full_p, full_q), atol=1e-15)
    np.testing.assert_allclose(
        run(dq.quaternion_slerp, p, q, t),
        run(dq.quaternion_slerp, full_p, full_q, t * np.ones((5, 3))),
        atol=1e-15,
    )
    assert run(dq.quaternion_apply, q, v).shape == (2, 1, 3, 3)
    assert run(
        dq.matrix_geodesic_distance, oracle_quaternion_to_matrix(p), oracle_quaternion_to_matrix(q)
    ).shape == (5, 3)


def test_float32_matrix_axis_angle_matrix_round_trip(backend: Backend, case: Case) -> None:
    """Within 1e-6 of the input matrix for every case, pi - 1e-8 about tilted axes included."""
    dq = backend.module
    matrix = backend.array(oracle_quaternion_to_matrix(case.quaternions("float32")), "float32")
    vector = dq.matrix_to_axis_angle(matrix)
    back = backend.to_numpy(dq.axis_angle_to_matrix(vector))
    assert np.all(np.linalg.norm(backend.to_numpy(vector), axis=-1) <= np.pi + 1e-6)
    np.testing.assert_allclose(back, backend.to_numpy(matrix), atol=1e-6)


def differentiate(backend: Backend, fn: Any, *xs: np.ndarray) -> tuple[np.ndarray, list[np.ndarray]]:
    """Value and gradient of ``fn(*xs).sum()`` on a differentiable backend, in float64."""
    if backend.name == "torch":
        import torch

        ts = [torch.tensor(x, requires_grad=True) for x in xs]
        out = fn(*ts)
        grads = torch.autograd.grad(out.sum(), ts)
        return out.detach().numpy(), [g.numpy() for g in grads]
    import jax

    out, pullback = jax.vjp(fn, *xs)
    return np.asarray(out), [np.asarray(g) for g in pullback(np.ones(out.shape))]


@pytest.mark.parametrize("name", ["torch", "jax"])
def test_distances_are_exactly_zero_between_equal_rotations_with_finite_gradient(name: str) -> None:
    from conftest import BACKENDS

    backend = BACKENDS[name]
    dq = backend.module
    p = uniform_quaternions(64, seed=34) * np.random.default_rng(35).uniform(0.1, 10, size=(64, 1))
    m = oracle_quaternion_to_matrix(p)
    for q in (p, -p):
        value, grads = differentiate(backend, dq.quaternion_geodesic_distance, p, q)
        assert np.all(value == 0) and all(np.all(np.isfinite(g)) for g in grads)
    value, grads = differentiate(backend, dq.matrix_geodesic_distance, m, m.copy())
    assert np.all(value == 0) and all(np.all(np.isfinite(g)) for g in grads)
    # pi apart: finite gradients, the value pi
    half = CASES_BY_NAME["half_turns"].quaternions("float64")
    r = uniform_quaternions(len(half), seed=36)
    from cases import hamilton

    value, grads = differentiate(backend, dq.quaternion_geodesic_distance, r, hamilton(r, half))
    np.testing.assert_allclose(value, np.pi, atol=1e-7)
    assert all(np.all(np.isfinite(g)) for g in grads)
    value, grads = differentiate(
        backend,
        dq.matrix_geodesic_distance,
        oracle_quaternion_to_matrix(r),
        oracle_quaternion_to_matrix(hamilton(r, half)),
    )
    np.testing.assert_allclose(value, np.pi, atol=1e-7)
    assert all(np.all(np.isfinite(g)) for g in grads)


@pytest.mark.parametrize("name", ["torch", "jax"])
def test_slerp_between_antipodal_rotations_follows_one_shortest_arc(name: str) -> None:
    """A half-turn apart there are two shortest arcs; either is right, and the gradient is finite."""
    from cases import hamilton
    from conftest import BACKENDS

    backend = BACKENDS[name]
    dq = backend.module
    half = CASES_BY_NAME["half_turns"].quaternions("float64")
    p = uniform_quaternions(len(half), seed=37)
    q = hamilton(p, half)
    t = np.random.default_rng(38).uniform(0.1, 0.9, size=len(half))
    out, grads = differentiate(backend, dq.quaternion_slerp, p, q, t)
    assert all(np.all(np.isfinite(g)) for g in grads)
    dist_p = backend.to_numpy(
        dq.quaternion_geodesic_distance(backend.array(p, "float64"), backend.array(out, "float64"))
    )
    dist_q = backend.to_numpy(
        dq.quaternion_geodesic_distance(backend.array(q, "float64"), backend.array(out, "float64"))
    )
    np.testing.assert_allclose(dist_p, t * np.pi, atol=1e-7)
    np.testing.assert_allclose(dist_q, (1 - t) * np.pi, atol=1e-7)


@pytest.mark.parametrize("name", ["torch", "jax"])
def test_log_maps_give_correct_gradients_at_pi_on_the_rotation(name: str) -> None:
    """The rotation vector jumps to its antipode at pi, but the rotation it stands for does not:
    through ``axis_angle_to_matrix``, the gradients of both log maps match finite differences at and
    near half-turns (there the table only asks them to be finite)."""
    from conftest import BACKENDS
    from test_grads import fd_jacobians, reverse_jacobians

    backend = BACKENDS[name]
    dq = backend.module
    q = np.concatenate([CASES_BY_NAME[c].quaternions("float64") for c in ("half_turns", "near_half_turns")])
    q = oracle_normalize(q)[::3]
    for fn, x in (
        (lambda u: dq.axis_angle_to_matrix(dq.quaternion_to_axis_angle(u)), q),
        (lambda u: dq.axis_angle_to_matrix(dq.matrix_to_axis_angle(dq.quaternion_to_matrix(u))), q),
    ):
        ad = reverse_jacobians(backend, fn, [x], (len(x),))[0]
        fd = fd_jacobians(backend, fn, [x], (len(x),))[0]
        np.testing.assert_allclose(ad, fd, atol=2e-6)
