"""What the table of operations cannot say in one row: all 24 Euler conventions against scipy, the
algebra's properties, broadcasting between two inputs, and the promises at pi and at equal rotations."""

from __future__ import annotations

import functools
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
from conftest import Backend, case_rows
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

    def inputs(c: Case) -> list[np.ndarray]:
        q = c.quaternions(dtype)
        p = uniform_quaternions(int(np.prod(q.shape[:-1])) or 1, seed=30)[: int(np.prod(q.shape[:-1]))]
        return [p.reshape(q.shape), q]

    lhs, rp, rq = case_rows(
        backend,
        dtype,
        case,
        "product",
        inputs,
        lambda p, q: (
            dq.quaternion_to_matrix(dq.quaternion_multiply(p, q)),
            dq.quaternion_to_matrix(p),
            dq.quaternion_to_matrix(q),
        ),
    )
    rhs = rp @ rq
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


# ---------------------------------------------------------------------------------------------------
# matrix_to_euler_angles: as accurate as the direct formula (float32) and as scipy (float64), round
# trips, the gimbal-lock rule, matrices off SO(3), non-finite entries, derivatives in every convention.


# matrix_to_euler_angles has one code path per structure, intrinsic or extrinsic, Tait-Bryan or proper;
# the convention otherwise only permutes entries and flips signs (exact operations). Values are checked
# in all 24 conventions; the costlier checks (derivatives, non-finite entries, scaling) take one
# convention of each structure, two of either parity.
STRUCTURES = ["YXZ", "XZX", "zyx", "yzy"]


def _intrinsic_frame(convention: str) -> tuple[list[int], list[int], bool, bool]:
    """The right-handed frame (e_a, e_b, s e_c) of a convention read intrinsically as R_a R_b R_c (the
    letters reversed for an extrinsic one; for a proper sequence c is the axis not in it): axis indices,
    signs, whether proper, whether extrinsic."""
    letters = ["xyz".index(ch) for ch in convention.lower()]
    a, b, c = letters[::-1] if convention.islower() else letters
    proper = a == c
    if proper:
        c = 3 - a - b
    sign = round(float(np.linalg.det(np.eye(3)[[a, b, c]])))
    return [a, b, c], [1, 1, sign], proper, convention.islower()


def direct_euler(m: Any, convention: str, atan2: Any, hypot: Any) -> list[Any]:
    """The textbook formulas for XYZ and XYX, each angle one atan2 of its own two entries of ``m``, in
    m's own array type and dtype: written for this test, not taken from diffquat. In the frame of
    ``_intrinsic_frame`` the matrix is R_x(first) R_y(middle) R_z(s third) (Tait-Bryan) or
    R_x(first) R_y(middle) R_x(third) (proper). The three angles in the order of the convention."""
    idx, sg, proper, extrinsic = _intrinsic_frame(convention)

    def r(u: int, v: int) -> Any:
        return sg[u] * sg[v] * m[..., idx[u], idx[v]]

    if proper:
        out = [atan2(r(1, 0), -r(2, 0)), atan2(hypot(r(0, 1), r(0, 2)), r(0, 0)), atan2(r(0, 1), r(0, 2))]
    else:
        third = atan2(-r(0, 1), r(0, 0))
        out = [atan2(-r(1, 2), r(2, 2)), atan2(r(0, 2), hypot(r(0, 0), r(0, 1))), sg[2] * third]
    return out[::-1] if extrinsic else out


def _atan2_and_hypot(backend: Backend) -> tuple[Any, Any]:
    """The backend's own atan2 and hypot: the direct formula is evaluated as the backend evaluates ours
    (torch's float32 atan2 is more accurate than numpy's, XLA's is on a par with it)."""
    if backend.name == "torch":
        import torch

        return torch.atan2, torch.hypot
    if backend.name == "jax":
        import jax.numpy as jnp

        return jnp.arctan2, jnp.hypot
    return np.arctan2, np.hypot


def _lock_distance_angles(convention: str, distance: np.ndarray, seed: int) -> np.ndarray:
    """Angles whose middle one is ``distance`` away from one of its singular values (either one, at
    random), the first and third uniform in [-pi, pi)."""
    rng = np.random.default_rng(seed)
    n = len(distance)
    first, third = rng.uniform(-np.pi, np.pi, (2, n))
    upper = rng.uniform(size=n) < 0.5
    if convention[0].lower() == convention[2].lower():
        middle = np.where(upper, np.pi - distance, distance)
    else:
        middle = np.where(upper, np.pi / 2 - distance, distance - np.pi / 2)
    return np.stack([first, middle, third], axis=-1)


@functools.cache
def away_from_lock(convention: str, n: int) -> np.ndarray:
    """Rotation matrices (float64) whose middle angle is at least 0.04 rad from a gimbal lock: half of
    them within 0.2 rad of one (where the quaternion route lost most), half up to pi/2 away."""
    rng = np.random.default_rng(CONVENTIONS.index(convention))
    distance = np.where(rng.uniform(size=n) < 0.5, rng.uniform(0.04, 0.2, n), rng.uniform(0.04, np.pi / 2, n))
    angles = _lock_distance_angles(convention, distance, seed=100 + CONVENTIONS.index(convention))
    return Rotation.from_euler(convention, angles).as_matrix()


def angle_error(angles: np.ndarray, truth: np.ndarray) -> np.ndarray:
    """|angles - truth| modulo 2 pi (an angle of pi may come back as -pi), per angle, float64."""
    d = angles.astype(np.float64) - truth
    return np.abs(d - 2 * np.pi * np.round(d / (2 * np.pi)))


@pytest.mark.parametrize("convention", CONVENTIONS)
def test_float32_matrix_to_euler_angles_as_accurate_as_the_direct_formula(
    backend: Backend, convention: str
) -> None:
    """20000 float32 rotation matrices at least 0.04 rad from a lock, half of them within 0.2 rad. Each
    angle's largest error against float64 on the same float32 matrices is at most the direct formula's
    (each angle one atan2 of its own two entries, by the same backend's atan2, against itself in
    float64), plus (1 + sqrt 2) 2^-24 rad.

    That margin is the rounding of what ours computes before its atan2 where the direct formula reads
    entries (u = 2^-24): the first angle is atan2(y, x) with y = y0 zx + y1 zy (x alike), entries
    |(y0, y1)| <= 1 and (zx, zy) of norm n = |(y, x)|; each product and the sum round, so |dy| <=
    u n + u |y| (Cauchy-Schwarz), and the angle moves by at most |(dy, dx)| / n <= (sqrt 2 + 1) u. The
    middle angle's sqrt(a^2 + b^2 + tiny) against hypot: at most 2u relative, which moves it by u.
    Measured (numpy): ours 1.2-1.3 ulp of pi (2.6e-7 to 3.1e-7 rad), direct 1.0-1.05 ulp; the route
    through the quaternion (before) erred by up to 4.7e-6 here (proper sequences 6.3e-7), which fails
    the bound by far in all 24 conventions."""
    m32 = away_from_lock(convention, 20_000).astype(np.float32)
    dq = backend.module
    x32, x64 = backend.array(m32, "float32"), backend.array(m32, "float64")
    out = dq.matrix_to_euler_angles(x32, convention)
    assert out.dtype == backend.dtypes["float32"]
    error = angle_error(backend.to_numpy(out), backend.to_numpy(dq.matrix_to_euler_angles(x64, convention)))
    atan2, hypot = _atan2_and_hypot(backend)
    direct32 = np.stack([backend.to_numpy(a) for a in direct_euler(x32, convention, atan2, hypot)], axis=-1)
    direct64 = np.stack([backend.to_numpy(a) for a in direct_euler(x64, convention, atan2, hypot)], axis=-1)
    direct_error = angle_error(direct32, direct64).max(axis=0)
    margin = (1 + np.sqrt(2)) * 2.0**-24
    assert np.all(error.max(axis=0) <= direct_error + margin), (error.max(axis=0), direct_error)


def _exact_matrices(convention: str, angles: np.ndarray) -> np.ndarray:
    """The rotation matrices of float64 ``angles``, computed in mpmath (40 digits) and correctly rounded
    to float64: off SO(3) by the rounding of each entry only, relative to the entry."""
    import mpmath

    with mpmath.workdps(40):
        theta = np.frompyfunc(mpmath.mpf, 1, 1)(angles)
        cos, sin = np.frompyfunc(mpmath.cos, 1, 1)(theta), np.frompyfunc(mpmath.sin, 1, 1)(theta)
        factors = []
        for n, letter in enumerate(convention.lower()):
            axis = "xyz".index(letter)
            u, v = [k for k in range(3) if k != axis]
            r = np.zeros((len(angles), 3, 3), dtype=object)
            r[:, axis, axis], r[:, u, u], r[:, v, v] = 1, cos[:, n], cos[:, n]
            s = sin[:, n] if (v - u) % 3 == 1 else -sin[:, n]
            r[:, v, u], r[:, u, v] = s, -s
            factors.append(r)
        first, second, third = factors[::-1] if convention.islower() else factors
        return (first @ second @ third).astype(np.float64)


@functools.cache
def float64_sample(convention: str) -> tuple[np.ndarray, np.ndarray, float]:
    """200 float64 angles at least 0.04 rad from a lock (half within 0.2 rad), their matrices correctly
    rounded (mpmath), and scipy's largest error against the angles."""
    rng = np.random.default_rng(CONVENTIONS.index(convention))
    distance = np.where(
        rng.uniform(size=200) < 0.5, rng.uniform(0.04, 0.2, 200), rng.uniform(0.04, np.pi / 2, 200)
    )
    angles = _lock_distance_angles(convention, distance, seed=600 + CONVENTIONS.index(convention))
    m = _exact_matrices(convention, angles)
    scipy_error = float(angle_error(Rotation.from_matrix(m).as_euler(convention), angles).max())
    return m, angles, scipy_error


@pytest.mark.parametrize("convention", CONVENTIONS)
def test_float64_matrix_to_euler_angles_at_least_as_accurate_as_scipy(
    backend: Backend, convention: str
) -> None:
    """float64 matrices at least 0.04 rad from a lock, correctly rounded from the exact rotations of
    known angles (mpmath): our largest error against those angles is at most scipy's
    ``from_matrix(m).as_euler`` (through the quaternion, up to 5e-15 here), and within 2 ulp of pi.

    The truth is the exact rotation's angles rather than a formula evaluated exactly on the rounded
    matrix: such a matrix is off SO(3) by its rounding, and two readings of it (ours, where the first
    angle follows the third, and reading each angle off its own entries) differ by that rounding
    divided by the distance to the lock, which is not an error of either."""
    m, angles, scipy_error = float64_sample(convention)
    ours = backend.to_numpy(backend.module.matrix_to_euler_angles(backend.array(m, "float64"), convention))
    error = float(angle_error(ours, angles).max())
    assert error <= scipy_error, (error, scipy_error)
    assert error <= 2 * np.spacing(np.pi), error


def _float32_product(convention: str, angles: np.ndarray) -> np.ndarray:
    """The rotation of ``angles`` as the float32 product of its three elementary rotations, each from
    float32 cos and sin: entries near 0 carry absolute rounding errors (the matrix is a few ulps off
    SO(3) in every entry), as a float32 pipeline's matrices do."""
    a = angles.astype(np.float32)
    letters = ["xyz".index(ch) for ch in convention.lower()]
    factors = []
    for n, axis in enumerate(letters):
        c, s = np.cos(a[:, n]), np.sin(a[:, n])
        r = np.zeros((len(a), 3, 3), np.float32)
        u, v = [k for k in range(3) if k != axis]
        r[:, axis, axis], r[:, u, u], r[:, v, v] = 1, c, c
        r[:, v, u], r[:, u, v] = (s, -s) if (v - u) % 3 == 1 else (-s, s)
        factors.append(r)
    first, second, third = factors[::-1] if convention.islower() else factors
    return first @ second @ third


@functools.cache
def round_trip_matrices(convention: str) -> np.ndarray:
    """float32 rotation matrices: the exact gimbal locks; middle angles from 1e-8 to pi/2 rad away from
    a lock (log-uniform, so that every scale near the lock is there), rounded from float64; and the
    same rotations as float32 products (``_float32_product``). 20024 in all."""
    rng = np.random.default_rng(200 + CONVENTIONS.index(convention))
    distance = 10.0 ** rng.uniform(-8, np.log10(np.pi / 2), 10_000)
    angles = _lock_distance_angles(convention, distance, seed=300 + CONVENTIONS.index(convention))
    locks = oracle_quaternion_to_matrix(CASES_BY_NAME["gimbal_lock"].quaternions("float64"))
    rounded = np.concatenate([locks, Rotation.from_euler(convention, angles).as_matrix()]).astype(np.float32)
    return np.concatenate([rounded, _float32_product(convention, angles)])


@pytest.mark.parametrize("convention", CONVENTIONS)
def test_float32_matrix_euler_matrix_round_trip(backend: Backend, convention: str) -> None:
    """euler_angles_to_matrix(matrix_to_euler_angles(R)) in float32 is within rtol 1e-5 of R, plus an
    absolute 1e-6, on every row, at and near gimbal locks too, for float32 products as well (reading
    the first and third angles each directly off its own entries, those came back up to 2 away near a
    lock). The absolute term is needed: entries near 0 cannot meet any rtol, since rebuilding R in
    float32 from the correctly rounded angles of R itself misses it by up to 7.8e-7 (6.5 ulp of 1) on
    such samples (it fails rtol 1e-5 alone on 4.7% of rows)."""
    dq = backend.module
    m32 = round_trip_matrices(convention)
    x = backend.array(m32, "float32")
    back = backend.to_numpy(dq.euler_angles_to_matrix(dq.matrix_to_euler_angles(x, convention), convention))
    excess = np.abs(back - m32) - (1e-5 * np.abs(m32) + 1e-6)
    assert np.all(excess <= 0), float(excess.max())


@pytest.mark.parametrize("convention", CONVENTIONS)
def test_gimbal_lock_is_scipy_rule_within_1e_7(backend: Backend, convention: str) -> None:
    """float64 rotations whose middle angle is 0.5e-7 and 0.9e-7 rad from each singular value are
    locked: the third angle is exactly 0, and the rotation is reproduced to the distance from the
    lock (the angles describe the rotation at the lock); at 1.1e-7 and 2e-7 rad they are not, and the
    angles are scipy's. The lock angle is the one scipy gives."""
    dq = backend.module
    distance = np.repeat([0.5e-7, 0.9e-7, 1.1e-7, 2e-7], 16)
    angles = _lock_distance_angles(convention, distance, seed=400 + CONVENTIONS.index(convention))
    angles[:, 2] = np.where(np.abs(angles[:, 2]) < 0.1, 0.5, angles[:, 2])  # a third angle far from 0
    m = Rotation.from_euler(convention, angles).as_matrix()
    ours = backend.to_numpy(dq.matrix_to_euler_angles(backend.array(m, "float64"), convention))
    expected = Rotation.from_matrix(m).as_euler(convention, suppress_warnings=True)
    locked = distance < 1e-7
    assert np.all((ours[:, 2] == 0) == locked)
    np.testing.assert_array_less(angle_error(ours, expected)[locked], 1e-6)
    np.testing.assert_array_less(angle_error(ours, expected)[~locked], 1e-7)
    back = Rotation.from_euler(convention, ours).as_matrix()
    np.testing.assert_array_less(np.abs(back - m)[locked], 4e-7)
    np.testing.assert_array_less(np.abs(back - m)[~locked], 1e-12)


def _elementary(axis: int, angle: np.ndarray) -> np.ndarray:
    return Rotation.from_rotvec(angle[:, None] * np.eye(3)[axis]).as_matrix()


def _parallel(u: np.ndarray, v: np.ndarray, drop: int) -> None:
    """Rows of u and v, their component ``drop`` removed, point the same way (float64)."""
    keep = [k for k in range(3) if k != drop]
    u, v = u[:, keep], v[:, keep]
    u = u / np.linalg.norm(u, axis=-1, keepdims=True)
    v = v / np.linalg.norm(v, axis=-1, keepdims=True)
    np.testing.assert_allclose(u, v, atol=1e-12)


@pytest.mark.parametrize("convention", CONVENTIONS)
def test_matrix_to_euler_angles_off_rotation_matrices(backend: Backend, convention: str) -> None:
    """The documented reading of a matrix M off SO(3), intrinsically R_p(u) R_q(v) R_r(w), checked on
    the rotation R' of the angles: v is read off row p; the convention's third angle (w, resp. u when
    extrinsic) off row p (resp. column r, or p for proper sequences); the first off column q of
    M R_r(-w) (resp. row q of R_p(-u) M). So a positive multiple of a rotation gives its angles, and a
    matrix a few rounding errors off SO(3) is rebuilt to within those, also 1e-6 rad from a lock.
    Any finite matrix gives finite angles."""
    dq = backend.module

    def angles_of(m: np.ndarray, dtype: str = "float64") -> np.ndarray:
        return backend.to_numpy(dq.matrix_to_euler_angles(backend.array(m, dtype), convention))

    rng = np.random.default_rng(500 + CONVENTIONS.index(convention))
    rot = away_from_lock(convention, 64)
    m = rot * rng.uniform(0.5, 2, size=(64, 1, 1)) + 0.05 * rng.normal(size=(64, 3, 3))
    ours = angles_of(m)
    r = Rotation.from_euler(convention, ours).as_matrix()
    (p, q, rr), _, proper, extrinsic = _intrinsic_frame(convention)
    u, _v, w = (ours[:, 2], ours[:, 1], ours[:, 0]) if extrinsic else (ours[:, 0], ours[:, 1], ours[:, 2])
    axis = p if proper else rr  # the entry of row p that is cos v, resp. +-sin v
    np.testing.assert_allclose(r[:, p, axis], m[:, p, axis] / np.linalg.norm(m[:, p], axis=-1), atol=1e-12)
    if extrinsic:
        column = p if proper else rr
        _parallel(r[:, :, column], m[:, :, column], drop=p)
        undo = _elementary(p, -u)
        _parallel((undo @ r)[:, q], (undo @ m)[:, q], drop=p if proper else rr)
    else:
        np.testing.assert_allclose(
            r[:, p], m[:, p] / np.linalg.norm(m[:, p], axis=-1, keepdims=True), atol=1e-12
        )
        undo = _elementary(p if proper else rr, -w)
        _parallel((r @ undo)[:, :, q], (m @ undo)[:, :, q], drop=p)
    # One call for the rest: positive multiples of rotations, and rotations 1e-6 rad from a lock that
    # are 1e-12 off SO(3), whose angles rebuild them to a few times that.
    scales = np.array([1e-3, 0.5, 3.0, 1e3])[:, None, None, None]
    near_lock = _lock_distance_angles(convention, np.full(64, 1e-6), seed=7)
    noisy = Rotation.from_euler(convention, near_lock).as_matrix() + 1e-12 * rng.normal(size=(64, 3, 3))
    out = angles_of(np.concatenate([rot, (scales * rot).reshape(-1, 3, 3), noisy]))
    plain, scaled, rebuilt = out[:64], out[64:320].reshape(4, 64, 3), out[320:]
    np.testing.assert_allclose(angle_error(scaled, plain), 0, atol=1e-14)
    np.testing.assert_allclose(Rotation.from_euler(convention, rebuilt).as_matrix(), noisy, atol=1e-11)
    garbage = np.concatenate(
        [np.zeros((1, 3, 3)), np.ones((1, 3, 3)), np.eye(3)[None, [0, 0, 1]], 1e-30 * m[:4]]
    )
    for dtype in ("float32", "float64"):
        assert np.all(np.isfinite(angles_of(garbage, dtype)))


@pytest.mark.parametrize("convention", STRUCTURES)
def test_matrix_to_euler_angles_of_any_positive_multiple(backend: Backend, convention: str) -> None:
    """c R gives the angles of R for c from 1e-30 to 1e38 in float32 and from 1e-300 to 1e300 in
    float64, where squares of entries overflow (from ~1.8e19, resp. 1.3e154) or leave the lock rule
    no digits; and on torch and jax the gradient is that of R divided by c, finite, wherever that is
    a normal number (jax flushes subnormal ones, 1e-38 R's, to 0). Before the scaling, 1e20 R gave
    wrong angles and a NaN gradient, 1e-20 R zeros. The tolerances are the rounding of c R itself
    (a relative 2^-24, resp. 2^-53, per entry, 0.04 rad and more from the lock)."""
    dq = backend.module
    rot = away_from_lock(convention, 16)[8:]  # the half 0.04 to pi/2 rad from a lock
    for dtype, scales, tol in (
        ("float32", [1e-30, 1e-20, 1e20, 1e30, 1e38], 2e-6),
        ("float64", [1e-300, 1e-160, 1e160, 1e300], 1e-14),
    ):
        c = np.repeat([1.0, *scales], len(rot))
        m = backend.array(c[:, None, None] * np.tile(rot, (len(scales) + 1, 1, 1)), dtype)
        out = backend.to_numpy(dq.matrix_to_euler_angles(m, convention)).reshape(len(scales) + 1, -1, 3)
        np.testing.assert_allclose(angle_error(out[1:], out[0]), 0, atol=tol)
        if backend.differentiable:
            grad = _summed_gradient(backend, lambda x: dq.matrix_to_euler_angles(x, convention), m)
            grad = (grad * c[:, None, None]).reshape(len(scales) + 1, -1, 3, 3)
            normal = [k + 1 for k, s in enumerate(scales) if s < 1e-3 / np.finfo(dtype).tiny]
            expected = np.broadcast_to(grad[0], grad[normal].shape)
            np.testing.assert_allclose(grad[normal], expected, rtol=1e-4, atol=tol)


def _summed_gradient(backend: Backend, fn: Any, x: Any) -> np.ndarray:
    """d(sum fn(x))/dx on torch or jax, as float64 numpy."""
    if backend.name == "torch":
        import torch

        x = x.detach().requires_grad_()
        return backend.to_numpy(torch.autograd.grad(fn(x).sum(), x)[0])
    import jax

    return backend.to_numpy(jax.grad(lambda y: fn(y).sum())(x))


@pytest.mark.parametrize("convention", STRUCTURES)
def test_matrix_to_euler_angles_of_non_finite_entries_is_nan(backend: Backend, convention: str) -> None:
    """A NaN or an infinity in any of the nine entries gives NaN angles in that row, whether or not the
    formula reads that entry; the other rows are unchanged (one call per dtype)."""
    dq = backend.module
    rot = away_from_lock(convention, 1)[0]
    bad = []
    for value in (np.nan, np.inf, -np.inf):
        for entry in range(9):
            m = rot.copy()
            m.reshape(9)[entry] = value
            bad.append(m)
    m = np.concatenate([np.array(bad), rot[None]])
    expected = Rotation.from_matrix(rot).as_euler(convention)
    for dtype, tol in (("float32", 1e-6), ("float64", 1e-12)):
        out = backend.to_numpy(dq.matrix_to_euler_angles(backend.array(m, dtype), convention))
        assert np.all(np.isnan(out[:-1]))
        np.testing.assert_allclose(angle_error(out[-1], expected), 0, atol=tol)


@pytest.mark.parametrize("convention", STRUCTURES)
@pytest.mark.parametrize("name", ["torch", "jax"])
def test_matrix_to_euler_angles_derivatives_in_each_structure(name: str, convention: str) -> None:
    """float64, one convention of each structure (the table checks ZXZ at every case): reverse mode
    equals finite differences on rotations 0.05 rad and more from a lock, and so do torch's second
    derivatives (gradgradcheck) and jax's forward mode. Gradients are finite at exact gimbal locks,
    half-turns, the identity and matrices far off SO(3) (zero, rank 1, a repeated row): float64 on
    both, float32 on torch (jax runs the same formula; each of its dtypes costs a compilation)."""
    import jax
    import torch
    from conftest import BACKENDS
    from test_grads import fd_jacobians, reverse_jacobians

    backend = BACKENDS[name]
    dq = backend.module

    def fn(m: Any) -> Any:
        return dq.matrix_to_euler_angles(m, convention)

    distance = np.random.default_rng(700 + CONVENTIONS.index(convention)).uniform(0.05, np.pi / 2, 12)
    m = Rotation.from_euler(convention, _lock_distance_angles(convention, distance, seed=8)).as_matrix()
    special = [CASES_BY_NAME[c].quaternions("float64") for c in ("gimbal_lock", "half_turns", "identity")]
    edge = np.concatenate(
        [
            oracle_quaternion_to_matrix(np.concatenate(special)),
            np.zeros((1, 3, 3)),
            np.ones((1, 3, 3)),
            np.eye(3)[None, [0, 0, 1]],
        ]
    )
    if name == "jax":
        # one compilation: reverse and forward mode, smooth rows and edge rows together
        both = jax.jit(jax.vmap(lambda x: (jax.jacrev(fn)(x), jax.jacfwd(fn)(x))))
        rev, fwd = (np.asarray(j).reshape(-1, 3, 9) for j in both(np.concatenate([m, edge])))
        ad, edge_grads = rev[: len(m)], rev[len(m) :]
        np.testing.assert_allclose(fwd[: len(m)], ad, atol=1e-12)
        fd = fd_jacobians(backend, jax.jit(fn), [m], (len(m),))[0]
    else:
        ad = reverse_jacobians(backend, fn, [m], (len(m),))[0]
        fd = fd_jacobians(backend, fn, [m], (len(m),))[0]
        x = torch.tensor(m[:3], requires_grad=True)
        assert torch.autograd.gradcheck(fn, (x,), eps=1e-6, atol=1e-6, rtol=1e-5)
        assert torch.autograd.gradgradcheck(fn, (x,), eps=1e-6, atol=1e-5, rtol=1e-4)
        edge_grads = []
        for dtype in (torch.float32, torch.float64):
            x = torch.tensor(edge, dtype=dtype, requires_grad=True)
            out = fn(x)
            edge_grads.append(torch.autograd.grad(out, x, torch.ones_like(out))[0].numpy())
    np.testing.assert_allclose(ad, fd, atol=1e-6 * np.abs(fd).max())
    assert all(np.all(np.isfinite(g)) for g in edge_grads)
