"""``SO3`` and ``SE3`` (diffquat._objects), on every backend.

The objects add no math: each method is one function call on the stored matrix. So the tests check
that (every method against its function, bit for bit, over the shared table's cases; the same ATen
operations in eager torch), the grammar (construction, batch shape, indexing, joining, repr,
errors naming the method) and the paths users run (torch autograd, ``torch.func``,
``torch.compile(fullgraph=True)``, an optimiser step; jax's ``jit``, ``vmap``, ``grad``, ``scan``,
``jax.export``, an optax step). The values of the functions themselves are the table's business
(tests/test_values.py and the rest). Everything here runs in seconds: the cases are concatenated
into one batch (plus the batch_* shapes, whose point is their shape), and one small program is
compiled per path.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

import numpy as np
import pytest
from cases import CASES, CASES_BY_NAME, concatenate_cases, uniform_quaternions
from conftest import Backend

# The cases' quaternions in four batch shapes: every value case but the batch_* ones in one (N,) batch
# (rows are independent), and the scalar, (3, 1, 2) and empty batches.
_FLAT, _ = concatenate_cases(
    [c for c in CASES if not c.name.startswith("batch_")],
    lambda c: c.quaternions("float64").shape[:-1],
    lambda c: [c.quaternions("float64")],
)
BATCHES = {
    "cases": _FLAT[0],
    "batch_scalar": CASES_BY_NAME["batch_scalar"].quaternions("float64"),
    "batch_3x1x2": CASES_BY_NAME["batch_3x1x2"].quaternions("float64"),
    "batch_empty": CASES_BY_NAME["batch_empty"].quaternions("float64"),
}


def _inputs(q: np.ndarray) -> dict[str, np.ndarray]:
    """Float64 arguments of the batch shape of ``q``: two quaternions, points, rotation vectors,
    twists, parameters ``t``, 7-vector poses and 6D vectors."""
    batch = q.shape[:-1]
    rng = np.random.default_rng(int(np.prod(batch)) + len(batch))
    q2 = uniform_quaternions(batch or (1,), seed=7).reshape(*batch, 4)
    return {
        "q": q,
        "q2": q2,
        "points": rng.normal(size=(*batch, 3)),
        "omega": rng.normal(size=(*batch, 3)),
        "xi": rng.normal(size=(*batch, 6)),
        "t": rng.uniform(size=batch),
        "translation": rng.normal(size=(*batch, 3)),
        "pose": np.concatenate([q, rng.normal(size=(*batch, 3))], axis=-1),
        "d6": rng.normal(size=(*batch, 6)),
    }


def _same(out: Any, expected: Any, backend: Backend, what: str) -> None:
    if isinstance(expected, tuple):
        for o, e in zip(out, expected, strict=True):
            _same(o, e, backend, what)
        return
    if hasattr(expected, "matrix") and not isinstance(expected, np.ndarray):
        expected = expected.matrix
    if hasattr(out, "matrix") and not isinstance(out, np.ndarray):
        out = out.matrix
    assert tuple(out.shape) == tuple(expected.shape), what
    np.testing.assert_array_equal(backend.to_numpy(out), backend.to_numpy(expected), err_msg=what)


def _pairs(dq: Any, x: dict[str, Any]) -> list[tuple[str, Callable[[], Any], Callable[[], Any]]]:
    """(name, object path, functional call) for every method that calls a function."""
    SO3, SE3 = dq.SO3, dq.SE3
    r1, r2 = dq.quaternion_to_matrix(x["q"]), dq.quaternion_to_matrix(x["q2"])
    m1 = dq.se3_from_rotation_translation(r1, x["translation"])
    m2 = dq.se3_from_rotation_translation(r2, x["points"])
    a, b, c, d = SO3(r1), SO3(r2), SE3(m1), SE3(m2)
    p, t = x["points"], x["t"]
    return [
        ("SO3.from_quaternion", lambda: SO3.from_quaternion(x["q"]), lambda: dq.quaternion_to_matrix(x["q"])),
        (
            "SO3.from_quaternion xyzw",
            lambda: SO3.from_quaternion(x["q"][..., [1, 2, 3, 0]], scalar_first=False),
            lambda: dq.quaternion_to_matrix(x["q"][..., [1, 2, 3, 0]], scalar_first=False),
        ),
        (
            "SO3.from_axis_angle",
            lambda: SO3.from_axis_angle(x["omega"]),
            lambda: dq.axis_angle_to_matrix(x["omega"]),
        ),
        (
            "SO3.from_euler_angles",
            lambda: SO3.from_euler_angles(x["omega"], "ZYX", degrees=True),
            lambda: dq.euler_angles_to_matrix(x["omega"], "ZYX", degrees=True),
        ),
        (
            "SO3.from_rotation_6d",
            lambda: SO3.from_rotation_6d(x["d6"], layout="rows"),
            lambda: dq.rotation_6d_to_matrix(x["d6"], layout="rows"),
        ),
        ("SO3.exp", lambda: SO3.exp(x["omega"]), lambda: dq.so3_exp(x["omega"])),
        ("SO3.as_matrix", lambda: a.as_matrix(), lambda: r1),
        (
            "SO3.as_quaternion",
            lambda: a.as_quaternion(scalar_first=False),
            lambda: dq.matrix_to_quaternion(r1, scalar_first=False),
        ),
        ("SO3.as_axis_angle", lambda: a.as_axis_angle(), lambda: dq.matrix_to_axis_angle(r1)),
        (
            "SO3.as_euler_angles",
            lambda: a.as_euler_angles("xzx"),
            lambda: dq.matrix_to_euler_angles(r1, "xzx"),
        ),
        ("SO3.as_rotation_6d", lambda: a.as_rotation_6d(), lambda: dq.matrix_to_rotation_6d(r1)),
        ("SO3.log", lambda: a.log(), lambda: dq.so3_log(r1)),
        ("SO3 @ SO3", lambda: a @ b, lambda: r1 @ r2),
        ("SO3.compose", lambda: a.compose(b), lambda: r1 @ r2),
        ("SO3 @ points", lambda: a @ p, lambda: (r1 @ p[..., None])[..., 0]),
        ("SO3.inverse", lambda: a.inverse(), lambda: r1.swapaxes(-1, -2)),
        ("SO3.adjoint", lambda: a.adjoint(), lambda: r1),
        (
            "SO3.plus",
            lambda: a.plus(x["omega"], side="left"),
            lambda: dq.so3_plus(r1, x["omega"], side="left"),
        ),
        ("SO3.minus", lambda: a.minus(b), lambda: dq.so3_minus(r1, r2)),
        (
            "SO3.interpolate",
            lambda: a.interpolate(b, t),
            lambda: dq.so3_plus(r1, (lambda delta: t[..., None] * delta)(dq.so3_minus(r2, r1))),
        ),
        ("SO3.distance", lambda: a.distance(b), lambda: dq.matrix_geodesic_distance(r1, r2)),
        (
            "SE3.from_rotation_translation",
            lambda: SE3.from_rotation_translation(a, x["translation"]),
            lambda: dq.se3_from_rotation_translation(r1, x["translation"]),
        ),
        (
            "SE3.from_pose",
            lambda: SE3.from_pose(x["pose"], layout="wxyz_xyz"),
            lambda: dq.pose_to_matrix(x["pose"], layout="wxyz_xyz"),
        ),
        ("SE3.exp", lambda: SE3.exp(x["xi"]), lambda: dq.se3_exp(x["xi"])),
        (
            "SE3.as_pose",
            lambda: c.as_pose(layout="xyz_xyzw"),
            lambda: dq.matrix_to_pose(m1, layout="xyz_xyzw"),
        ),
        ("SE3.rotation", lambda: c.rotation(), lambda: dq.se3_to_rotation_translation(m1)[0]),
        ("SE3.translation", lambda: c.translation(), lambda: dq.se3_to_rotation_translation(m1)[1]),
        ("SE3.log", lambda: c.log(), lambda: dq.se3_log(m1)),
        ("SE3 @ SE3", lambda: c @ d, lambda: dq.se3_compose(m1, m2)),
        ("SE3 @ points", lambda: c @ p, lambda: dq.se3_apply(m1, p)),
        ("SE3.apply", lambda: c.apply(p), lambda: dq.se3_apply(m1, p)),
        ("SE3.inverse", lambda: c.inverse(), lambda: dq.se3_inverse(m1)),
        ("SE3.adjoint", lambda: c.adjoint(), lambda: dq.se3_adjoint(m1)),
        ("SE3.plus", lambda: c.plus(x["xi"]), lambda: dq.se3_plus(m1, x["xi"])),
        ("SE3.minus", lambda: c.minus(d, side="left"), lambda: dq.se3_minus(m1, m2, side="left")),
        (
            "SE3.interpolate",
            lambda: c.interpolate(d, t, mode="decoupled"),
            lambda: dq.se3_interpolate(m1, m2, t, mode="decoupled"),
        ),
    ]


def _backend_inputs(backend: Backend, q: np.ndarray, dtype: str = "float64") -> dict[str, Any]:
    return {k: backend.array(v, dtype) for k, v in _inputs(q).items()}


def test_every_method_is_its_function_bit_for_bit(backend: Backend) -> None:
    """Over the shared table's cases (the edge cases included: half-turns, the zero quaternion, norms
    from 1e-20 to 1e20), every method returns exactly what its function returns on the stored array.
    Eager jax compiles every primitive per shape (5-8 s a batch shape here), so it runs the cases
    only: the other batch shapes are the functions' business there (the methods' batch handling is
    the same code on every backend, run here on NumPy and torch)."""
    skip = ("batch_scalar", "batch_empty", "batch_3x1x2") if backend.name == "jax" else ()
    for batch, q in BATCHES.items():
        if batch in skip:
            continue
        x = _backend_inputs(backend, q)
        for name, method, function in _pairs(backend.module, x):
            _same(method(), function(), backend, f"{name} at {batch}")


def test_means_and_distance_of_poses_are_their_functions(backend: Backend) -> None:
    dq = backend.module
    x = _backend_inputs(backend, uniform_quaternions((2, 5), seed=3))
    r1 = dq.quaternion_to_matrix(x["q"])
    m1 = dq.se3_from_rotation_translation(r1, x["translation"])
    m2 = dq.se3_from_rotation_translation(dq.quaternion_to_matrix(x["q2"]), x["points"])
    w = x["t"]
    _same(
        dq.SO3(r1).mean(w, method="geodesic"), dq.rotation_mean(r1, w, method="geodesic"), backend, "SO3.mean"
    )
    _same(dq.SE3(m1).mean(), dq.se3_mean(m1), backend, "SE3.mean")
    angle, length = dq.SE3(m1).distance(dq.SE3(m2))
    _same(angle, dq.matrix_geodesic_distance(m1[..., :3, :3], m2[..., :3, :3]), backend, "SE3.distance")
    expected = np.linalg.norm(backend.to_numpy(m1)[..., :3, 3] - backend.to_numpy(m2)[..., :3, 3], axis=-1)
    np.testing.assert_allclose(backend.to_numpy(length), expected, rtol=1e-15)
    assert dq.SO3(r1).mean().shape == (2,) and dq.SE3(m1).mean().shape == (2,)


def test_methods_dispatch_the_functions_operations() -> None:
    """Eager torch: each method dispatches exactly the ATen operations of the call it stands for
    (validation reads static shapes and dtypes; the wrapper adds nothing)."""
    import torch
    from conftest import BACKENDS
    from torch.utils._python_dispatch import TorchDispatchMode

    import diffquat.torch as dq

    class Ops(TorchDispatchMode):
        def __init__(self) -> None:
            super().__init__()
            self.ops: list[str] = []

        def __torch_dispatch__(self, func: Any, types: Any, args: Any = (), kwargs: Any = None) -> Any:
            self.ops.append(str(func))
            return func(*args, **(kwargs or {}))

    def ops(fn: Callable[[], Any]) -> list[str]:
        with Ops() as mode:
            fn()
        return mode.ops

    for dtype in ("float32", "float64"):
        x = _backend_inputs(BACKENDS["torch"], uniform_quaternions(8, seed=2), dtype)
        for name, method, function in _pairs(dq, x):
            function()  # the first call makes the eager forms' constants (diffquat._core.constants)
            assert ops(method) == ops(function), name
        with torch.no_grad():
            for name, method, function in _pairs(dq, x)[:3]:
                assert ops(method) == ops(function), name
    # forward + backward: the same operations again (autograd records the same graph)
    x = {
        k: v.requires_grad_()
        for k, v in _backend_inputs(BACKENDS["torch"], uniform_quaternions(8, seed=2)).items()
    }

    def backward(fn: Callable[[], Any]) -> Callable[[], Any]:
        def run() -> None:
            for v in x.values():
                v.grad = None
            out = fn()
            for o in out if isinstance(out, tuple) else (out,):
                (o.matrix if isinstance(o, dq.SO3 | dq.SE3) else o).sum().backward(retain_graph=True)

        return run

    checked = 0
    for name, method, function in _pairs(dq, x):
        assert ops(backward(method)) == ops(backward(function)), name
        checked += 1
    assert checked == len(_pairs(dq, x))


def test_grammar(backend: Backend) -> None:
    dq = backend.module
    random = {"numpy": {"rng": 0}, "jax": {}, "torch": {}}[backend.name]
    if backend.name == "jax":
        import jax

        random = {"key": jax.random.key(0)}
    elif backend.name == "torch":
        import torch

        random = {"generator": torch.Generator().manual_seed(0)}
    R = dq.SO3.random((4, 3), **random)
    T = dq.SE3.random((4, 3), **dict(random))
    assert R.shape == T.shape == (4, 3) and R.ndim == 2 and len(R) == 4
    assert tuple(R.matrix.shape) == (4, 3, 3, 3) and tuple(T.matrix.shape) == (4, 3, 4, 4)
    assert R.as_matrix() is R.matrix
    assert str(R.dtype).endswith("float64" if backend.name != "torch" else "float32")
    assert repr(R).startswith("SO3(shape=(4, 3), dtype=") and "device=" in repr(T)
    assert type(R).__module__ == f"diffquat.{backend.name}" and isinstance(T.rotation(), dq.SO3)
    # indexing and slicing the batch, never the matrix axes
    assert R[0].shape == (3,) and R[1:, 0].shape == (3,) and R[..., None].shape == (4, 3, 1)
    assert R[..., 0].shape == (4,) and T[None].shape == (1, 4, 3)
    _same(R[2, 1], R.matrix[2, 1], backend, "index")
    assert [r.shape for r in R] == [(3,)] * 4
    assert (
        R.reshape(12).shape == (12,)
        and R.reshape((2, -1)).shape == (2, 6)
        and T.reshape(3, 4).shape == (3, 4)
    )
    assert R[:, :1].broadcast_to((2, 4, 3)).shape == (2, 4, 3)
    assert dq.SO3.concatenate([R, R[:1]]).shape == (5, 3) and dq.SE3.concatenate([T, T], axis=-1).shape == (
        4,
        6,
    )
    assert dq.SO3.stack([R, R]).shape == (2, 4, 3) and dq.SE3.stack([T, T], axis=-1).shape == (4, 3, 2)
    _same(dq.SO3.stack([R, R], axis=-1)[..., 1], R, backend, "stack")
    # broadcasting batch shapes, identities, inverses
    assert (R @ R[:1]).shape == (4, 3) and (T[:, :1] @ T[:1]).shape == (4, 3)
    assert (R @ R.inverse()).allclose(dq.SO3.identity((4, 3)), atol=1e-6)
    assert (T.inverse() @ T).allclose(dq.SE3.identity(3), atol=1e-6)
    assert dq.SO3.identity().shape == () and dq.SE3.identity(2).shape == (2,)
    assert not R.allclose(R.inverse())
    # a pose applied to a cloud: poses (4,) on clouds (4, N, 3) through a new axis
    cloud = backend.array(np.ones((4, 5, 3)), "float64").astype(R.dtype) if backend.name != "torch" else None
    if cloud is not None:
        assert tuple((T[:, 0][:, None] @ cloud).shape) == (4, 5, 3)
    # the order of the arguments: other.plus(self.minus(other)) is self; interpolation goes from self
    # (t = 0) to other (t = 1). The same code on every backend; eager jax would compile each
    # function for these shapes (about 1 s each), so it is checked on NumPy and torch.
    if backend.name != "jax":
        assert R[1].plus(R[0].minus(R[1])).allclose(R[0], atol=1e-5)
        assert R[1].plus(R[0].minus(R[1], side="left"), side="left").allclose(R[0], atol=1e-5)
        assert T[1].plus(T[0].minus(T[1])).allclose(T[0], atol=1e-5)
        assert R[0].interpolate(R[1], 0.0).allclose(R[0], atol=1e-6)
        assert R[0].interpolate(R[1], 1.0).allclose(R[1], atol=1e-5)
        assert T[0].interpolate(T[1], 1.0).allclose(T[1], atol=1e-5)
    # immutable, compared by identity (allclose compares values)
    with pytest.raises(AttributeError, match="SO3 is immutable"):
        R.matrix = R.matrix  # type: ignore[misc]
    assert R == R and R[...] != R
    # pickled and copied through their stored array
    import copy
    import pickle

    for obj in (R, T):
        for again in (pickle.loads(pickle.dumps(obj)), copy.deepcopy(obj), copy.copy(obj)):
            assert type(again) is type(obj) and again.allclose(obj, rtol=0, atol=0)
    # reproducible draws from the backend's own source; distinct draws differ
    if backend.name == "numpy":
        assert dq.SO3.random(2, rng=1).allclose(dq.SO3.random(2, rng=1), rtol=0, atol=0)
    assert not R[0].allclose(R[1])
    assert R.astype(backend.dtypes["float32"]).dtype == backend.dtypes["float32"]


def test_errors_name_the_method(backend: Backend) -> None:
    dq = backend.module
    R = dq.SO3(backend.array(np.tile(np.eye(3), (2, 1, 1)), "float64"))
    T = dq.SE3(backend.array(np.tile(np.eye(4), (2, 1, 1)), "float64"))
    with pytest.raises(
        ValueError, match=r"^SO3: expected matrix of shape \(\.\.\., 3, 3\), got shape \(4, 4\)"
    ):
        dq.SO3(backend.array(np.eye(4), "float64"))
    with pytest.raises(
        ValueError, match=r"^SE3: expected matrix of shape \(\.\.\., 4, 4\), got shape \(2, 3, 3\)"
    ):
        dq.SE3.from_matrix(R.matrix)
    with pytest.raises(
        ValueError, match=r"^SO3.apply: expected points of shape \(\.\.\., 3\), got shape \(2, 4\)"
    ):
        R @ backend.array(np.ones((2, 4)), "float64")
    with pytest.raises(ValueError, match=r"^SE3.apply: se3_apply: expected points of shape \(\.\.\., 3\)"):
        T @ backend.array(np.ones((2, 4)), "float64")
    with pytest.raises(ValueError, match=r"^SO3.from_quaternion: quaternion_to_matrix: expected q of shape"):
        dq.SO3.from_quaternion(backend.array(np.ones(3), "float64"))
    with pytest.raises(
        TypeError, match=r"^SO3.compose: expected an SO3 of the same backend, got diffquat\.\w+\.SE3"
    ):
        R @ T
    with pytest.raises(
        TypeError, match=r"^SE3.compose: expected an SE3 of the same backend, got diffquat\.\w+\.SO3"
    ):
        T @ R
    with pytest.raises(TypeError, match=r"^SO3.minus: expected another SO3"):
        R.minus(T)
    with pytest.raises(TypeError, match=r"^SE3.from_rotation_translation: expected an SO3"):
        dq.SE3.from_rotation_translation(T, backend.array(np.ones(3), "float64"))
    three = dq.SO3(backend.array(np.tile(np.eye(3), (3, 1, 1)), "float64"))
    with pytest.raises(
        ValueError,
        match=r"^SO3.compose: expected batch shapes that broadcast, got matrix1: shape \(2, 3, 3\), "
        r"matrix2: shape \(3, 3, 3\)",
    ):
        R @ three
    with pytest.raises(ValueError, match=r"^SO3.apply: expected batch shapes that broadcast"):
        R @ backend.array(np.ones((3, 3)), "float64")
    four = dq.SE3(backend.array(np.tile(np.eye(4), (3, 1, 1)), "float64"))
    with pytest.raises(ValueError, match=r"^SE3.compose: se3_compose: expected batch shapes that broadcast"):
        T @ four
    with pytest.raises(ValueError, match=r"^SE3.plus: se3_plus: expected"):
        T.plus(backend.array(np.ones((2, 3)), "float64"))
    with pytest.raises(
        ValueError, match=r"^SO3.as_euler_angles: matrix_to_euler_angles: expected convention"
    ):
        R.as_euler_angles("xyw")  # type: ignore[arg-type]
    complex_matrix = np.eye(3).astype("complex64")
    if backend.name == "torch":
        import torch

        complex_matrix = torch.from_numpy(complex_matrix)
    elif backend.name == "jax":
        import jax.numpy as jnp

        complex_matrix = jnp.asarray(complex_matrix)
    with pytest.raises(TypeError, match=r"^SO3: expected matrix with a real floating-point"):
        dq.SO3(complex_matrix)
    with pytest.raises(TypeError, match=r"^SO3: expected matrix "):
        dq.SO3("1.0")
    with pytest.raises(TypeError, match=r"^SO3.apply: expected points "):
        R @ "1.0"
    with pytest.raises(TypeError, match=r"^SE3.apply: se3_apply: expected points "):
        T.apply("1.0")
    with pytest.raises(TypeError, match=r"^SO3.from_axis_angle: axis_angle_to_matrix: expected axis_angle "):
        dq.SO3.from_axis_angle("1.0")
    with pytest.raises(TypeError, match="len\\(\\) of an unbatched SO3"):
        len(R[0])


def test_mixed_dtypes_promote_as_the_functions_do(backend: Backend) -> None:
    """float32 beside float64: float64, as the functions promote (jax's strict promotion, which the
    suite sets, refuses the pair: a TypeError naming the method, as the functions name theirs)."""
    dq = backend.module
    R = dq.SO3(backend.array(np.eye(3), "float32"))
    p = backend.array(np.ones(3), "float64")
    S = dq.SO3(backend.array(np.eye(3), "float64"))
    if backend.name == "jax":
        with pytest.raises(TypeError, match=r"^SO3.apply: the arguments' dtypes do not promote"):
            R @ p
        with pytest.raises(TypeError, match=r"^SO3.compose: the arguments' dtypes do not promote"):
            R @ S
        return
    assert str((R @ p).dtype).endswith("float64") and str((R @ S).dtype).endswith("float64")


@pytest.mark.parametrize("half", ["float16", "bfloat16"])
def test_half_precision_products_are_computed_in_float32(backend: Backend, half: str) -> None:
    """``SO3 @ SO3`` and ``SO3 @ p`` in float16 and bfloat16: the float32 product rounded once to the
    dtype, as the functions compute half precision (the SE3 methods are the functions themselves)."""
    dq = backend.module
    q = uniform_quaternions((3, 4), seed=5)
    r1 = backend.array(_oracle_matrix(q), half)
    r2 = backend.array(_oracle_matrix(uniform_quaternions((3, 4), seed=6)), half)
    p = backend.array(np.random.default_rng(0).normal(size=(3, 4, 3)), half)
    wide = [backend.to_numpy(x).astype(np.float32) for x in (r1, r2, p)]
    composed = (dq.SO3(r1) @ dq.SO3(r2)).matrix
    moved = dq.SO3(r1) @ p
    assert str(composed.dtype).endswith(half) and str(moved.dtype).endswith(half)
    np.testing.assert_array_equal(
        backend.to_numpy(composed), backend.to_numpy(backend.array(wide[0] @ wide[1], half))
    )
    np.testing.assert_array_equal(
        backend.to_numpy(moved),
        backend.to_numpy(backend.array((wide[0] @ wide[2][..., None])[..., 0], half)),
    )


def _oracle_matrix(q: np.ndarray) -> np.ndarray:
    from cases import oracle_quaternion_to_matrix

    return oracle_quaternion_to_matrix(q)


def test_torch_paths() -> None:
    """Autograd, torch.func (vmap, grad), torch.compile(fullgraph=True) without a graph break,
    ``.to``, ``.detach``, and an optimiser step on the stored tensor."""
    import torch

    import diffquat.torch as dq
    from diffquat.torch.optim import RiemannianAdam

    g = torch.Generator().manual_seed(0)
    T = dq.SE3.random(5, generator=g, dtype=torch.float64)
    R = dq.SO3.random(5, generator=g, dtype=torch.float64)
    p = torch.randn(5, 3, generator=g, dtype=torch.float64)

    def loss(T: Any, R: Any) -> Any:
        U = T.compose(dq.SE3.from_rotation_translation(R, p)).inverse()
        return (U.apply(p) ** 2).sum() + R.compose(R).distance(R).sum() + U.log().sum()

    # autograd through the object is autograd through the functions
    m, r = T.matrix.clone().requires_grad_(), R.matrix.clone().requires_grad_()
    loss(dq.SE3(m), dq.SO3(r)).backward()
    m2, r2 = T.matrix.clone().requires_grad_(), R.matrix.clone().requires_grad_()
    U = dq.se3_inverse(dq.se3_compose(m2, dq.se3_from_rotation_translation(r2, p)))
    expected = (
        (dq.se3_apply(U, p) ** 2).sum() + dq.matrix_geodesic_distance(r2 @ r2, r2).sum() + dq.se3_log(U).sum()
    )
    expected.backward()
    assert torch.equal(m.grad, m2.grad) and torch.equal(r.grad, r2.grad)
    # torch.func: objects in and out of vmap, gradients of a function of the stored tensor
    V = torch.func.vmap(lambda T, p: (T.inverse(), T @ p))(T, p)
    assert isinstance(V[0], dq.SE3) and torch.equal(V[0].matrix, T.inverse().matrix)
    assert torch.allclose(V[1], T @ p, rtol=0, atol=1e-15)
    grad = torch.func.grad(lambda m: loss(dq.SE3(m), R))(T.matrix)
    torch.testing.assert_close(grad, m.grad, rtol=1e-12, atol=1e-12)
    # torch.compile, fullgraph: objects in and out, the methods traced (Dynamo in torch 2.13 cannot
    # trace the @ operator of a Python class: compiled code calls compose/apply)
    compiled = torch.compile(
        lambda T, R: (T.compose(dq.SE3.from_rotation_translation(R, p)).inverse(), R.apply(p)), fullgraph=True
    )
    U, q = compiled(T, R)
    assert isinstance(U, dq.SE3)
    torch.testing.assert_close(
        U.matrix, (T @ dq.SE3.from_rotation_translation(R, p)).inverse().matrix, rtol=0, atol=1e-14
    )
    torch.testing.assert_close(q, R @ p, rtol=0, atol=1e-14)
    # .to and .detach
    assert T.to(torch.float32).dtype == torch.float32 and T.to("cpu").device == torch.device("cpu")
    assert not dq.SE3(m).detach().matrix.requires_grad
    # an optimiser step: the optimiser takes the stored tensor, with its manifold
    target = dq.SE3.random(generator=g, dtype=torch.float64)
    pose = dq.SE3(torch.nn.Parameter(dq.SE3.identity(dtype=torch.float64).matrix))
    optimizer = RiemannianAdam([pose.matrix], lr=0.1, manifold="se3")
    first = None
    for _ in range(20):
        optimizer.zero_grad()
        error = (pose.minus(target) ** 2).sum()
        first = float(error.detach()) if first is None else first
        error.backward()
        optimizer.step()
    assert float((pose.minus(target) ** 2).sum().detach()) < 0.5 * first
    rotation = pose.rotation().matrix.detach()
    torch.testing.assert_close(rotation.T @ rotation, torch.eye(3, dtype=torch.float64), rtol=0, atol=1e-12)


def test_jax_paths() -> None:
    """A registered pytree: jit, vmap, grad, scan, an optax step with diffquat's optimiser, and
    jax.export (serialised and called back)."""
    import jax
    import jax.numpy as jnp

    import diffquat.jax as dq
    from diffquat.jax import optim as dqo

    k1, k2, k3 = jax.random.split(jax.random.key(0), 3)
    T, target = dq.SE3.random(4, key=k1), dq.SE3.random(4, key=k2)
    p = jax.random.normal(k3, (4, 3))

    @jax.jit
    def step(T: Any, p: Any) -> Any:
        moved = jax.vmap(lambda T, p: T @ p)(T, p)
        grads = jax.grad(lambda T: ((T @ p - target @ p) ** 2).sum())(T)
        walk, _ = jax.lax.scan(lambda U, _: (U @ T, None), dq.SE3.identity(4), None, length=3)
        return moved, grads, walk

    moved, grads, walk = step(T, p)
    assert isinstance(grads, dq.SE3) and isinstance(walk, dq.SE3)
    # compiled against eager: equal to a few ulps (XLA fuses the compiled program's arithmetic)
    np.testing.assert_allclose(moved, dq.se3_apply(T.matrix, p), rtol=0, atol=1e-15)
    np.testing.assert_allclose(walk.matrix, (T @ T @ T).matrix, rtol=0, atol=1e-14)
    expected = jax.grad(lambda m: ((dq.se3_apply(m, p) - target @ p) ** 2).sum())(T.matrix)
    np.testing.assert_allclose(grads.matrix, expected, rtol=0, atol=1e-14)
    # optax: diffquat's transformation, the object a pytree of one pose leaf
    optimizer = dqo.riemannian_adam(0.1, manifold="se3")
    state = optimizer.init(T)
    loss = lambda T: (T.minus(target) ** 2).sum()  # noqa: E731

    @jax.jit
    def train(T: Any, state: Any) -> Any:
        def one(carry: Any, _: Any) -> Any:
            T, state = carry
            updates, state = optimizer.update(jax.grad(loss)(T), state, T)
            return (dqo.apply_updates(T, updates), state), None

        return jax.lax.scan(one, (T, state), None, length=20)[0][0]

    trained = train(T, state)
    assert isinstance(trained, dq.SE3) and loss(trained) < 0.5 * loss(T)
    # jax.export: objects in and out of the exported program, through serialisation
    exported = jax.export.export(jax.jit(lambda T, p: (T.inverse(), T @ p)))(T, p)
    inverse, points = jax.export.deserialize(exported.serialize()).call(T, p)
    assert isinstance(inverse, dq.SE3)
    np.testing.assert_allclose(inverse.matrix, T.inverse().matrix, rtol=0, atol=1e-15)
    np.testing.assert_allclose(points, T @ p, rtol=0, atol=1e-15)
    assert repr(jax.jit(lambda T: T)(T)).startswith("SE3(shape=(4,)")
    assert jnp.asarray(T.matrix).shape == (4, 4, 4)
