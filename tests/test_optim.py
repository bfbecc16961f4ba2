"""Riemannian optimisers on SO(3): ``diffquat.torch.optim`` and ``diffquat.jax.optim``.

The tangent-space formulas (``diffquat._optim``) are checked against independent float64 references:
the tangent gradient against central differences of ``f(R exp(w))`` at ``w = 0``, the parallel
transport against the Levi-Civita transport of the embedded manifold (tangent vectors projected step
by step along the geodesic, a scheme that knows nothing of the Lie algebra). The optimisers are then
checked end to end: one torch step against the finite-difference gradient, torch and jax taking the
same steps in float64, convergence to a closed-form optimum, parameters staying rotations for 1e4
float32 steps, state dicts, parameter groups, the refusals, and optax's multi_transform.
"""

from __future__ import annotations

import io
import math
from collections.abc import Callable
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np
import optax
import pytest
import torch

import diffquat.jax as dqj
import diffquat.numpy as dqn
import diffquat.torch as dqt
from diffquat import _optim
from diffquat.jax import optim as jo
from diffquat.torch.optim import RiemannianAdam, RiemannianSGD


def rotations(n: int, seed: int = 0) -> np.ndarray:
    """``n`` random rotation matrices, the identity and a half-turn among them (float64)."""
    rng = np.random.default_rng(seed)
    out = dqn.quaternion_to_matrix(dqn.random_quaternions((n,), rng=rng))
    out[0] = np.eye(3)
    out[1] = np.diag([1.0, -1.0, -1.0])
    return out


def unit_quaternions(n: int, seed: int = 1) -> np.ndarray:
    rng = np.random.default_rng(seed)
    out = dqn.random_quaternions((n,), rng=rng)
    out[0] = [1.0, 0.0, 0.0, 0.0]
    out[1] = [0.0, 1.0, 0.0, 0.0]
    return out


def central_differences(f: Callable[[np.ndarray], np.ndarray], n: int, h: float = 1e-6) -> np.ndarray:
    """``d f(w) / dw`` at 0 for ``f`` of rotation vectors ``(n, 3)`` giving ``(n,)``, row by row."""
    out = np.zeros((n, 3))
    for k in range(3):
        step = np.zeros((n, 3))
        step[:, k] = h
        out[:, k] = (f(step) - f(-step)) / (2 * h)
    return out


# ---------------------------------------------------------------------------------------------------
# The formulas


def test_matrix_tangent_gradient_is_the_derivative_along_the_retraction() -> None:
    rng = np.random.default_rng(2)
    R = rotations(6)
    a, b = rng.normal(size=(6, 3, 3)), rng.normal(size=(6, 3, 3))

    def f(m: np.ndarray) -> np.ndarray:  # any smooth function of the entries, one per rotation
        return np.sum(a * m, axis=(-1, -2)) + np.sum((b * m) ** 2, axis=(-1, -2))

    euclidean = a + 2 * b * b * R  # df/dR
    expected = central_differences(lambda w: f(dqn.so3_plus(R, w)), 6)
    np.testing.assert_allclose(_optim.matrix_tangent_gradient(np, R, euclidean), expected, atol=1e-8)


@pytest.mark.parametrize("scalar_first", [True, False])
def test_quaternion_tangent_gradient_is_the_derivative_along_the_retraction(scalar_first: bool) -> None:
    rng = np.random.default_rng(3)
    q = unit_quaternions(6)
    q = q if scalar_first else dqn.wxyz_to_xyzw(q)
    a, b = rng.normal(size=(6, 4)), rng.normal(size=(6, 4))

    def f(x: np.ndarray) -> np.ndarray:  # not a function of the rotation only: exact at unit q
        return np.sum(a * x, axis=-1) + np.sum((b * x) ** 3, axis=-1)

    def plus(w: np.ndarray) -> np.ndarray:
        return dqn.quaternion_plus(q, w, scalar_first=scalar_first)

    euclidean = a + 3 * b**3 * q**2
    got = _optim.quaternion_tangent_gradient(np, q, euclidean, scalar_first)
    np.testing.assert_allclose(got, central_differences(lambda w: f(plus(w)), 6), atol=1e-8)

    # A loss of the rotation only (through quaternion_to_matrix) is exact at any norm: the gradient
    # at 3q is a third of the one at q, which the formula's q* multiplies back.
    target = rotations(6, seed=4)

    def g(x: np.ndarray) -> np.ndarray:
        return np.sum((dqn.quaternion_to_matrix(x, scalar_first=scalar_first) - target) ** 2, axis=(-1, -2))

    h = 1e-6
    euclidean = np.stack([(g(3 * q + h * e) - g(3 * q - h * e)) / (2 * h) for e in np.eye(4)], axis=-1)
    got = _optim.quaternion_tangent_gradient(np, 3 * q, euclidean, scalar_first)
    np.testing.assert_allclose(got, central_differences(lambda w: g(plus(w)), 6), atol=1e-7)


def projection_transport(R: np.ndarray, delta: np.ndarray, v: np.ndarray, substeps: int) -> np.ndarray:
    """The Levi-Civita transport of SO(3) as a submanifold of the 3x3 matrices (Frobenius metric, the
    bi-invariant one): the ambient vector ``R hat(v)`` projected onto the tangent space at each of
    ``substeps`` points of the geodesic ``R exp(t delta)`` (first order in the substep), read back in
    body coordinates at the end. Nothing of the Lie algebra's connection is used."""
    V = R @ dqn.so3_hat(v)
    for k in range(1, substeps + 1):
        P = dqn.so3_plus(R, delta * (k / substeps))
        A = np.swapaxes(P, -1, -2) @ V
        V = P @ (0.5 * (A - np.swapaxes(A, -1, -2)))
    return dqn.so3_vee(np.swapaxes(P, -1, -2) @ V)


def test_transport_is_the_parallel_transport_of_the_embedded_manifold() -> None:
    rng = np.random.default_rng(5)
    R = rotations(8)
    delta = rng.normal(size=(8, 3))
    delta[0] = 0.0
    delta[1] *= 2.5 / np.linalg.norm(delta[1])  # a long step, towards pi
    v = rng.normal(size=(8, 3))
    # Richardson extrapolation of the first-order scheme: error O(|delta|^4 / substeps^2), measured
    # 4e-6 for the long step (it quarters as the substeps double), 2e-7 for the others.
    reference = 2 * projection_transport(R, delta, v, 1600) - projection_transport(R, delta, v, 800)
    got = _optim.transport(np, delta, v)
    np.testing.assert_allclose(got, reference, atol=1e-5)
    # The test can fail: keeping the body coordinates (no transport) is far from it.
    assert np.abs(v - reference)[2:].max() > 0.1
    # A rotation of the vector: lengths kept; the step itself is carried to itself.
    np.testing.assert_allclose(np.linalg.norm(got, axis=-1), np.linalg.norm(v, axis=-1), rtol=1e-14)
    np.testing.assert_allclose(_optim.transport(np, delta, delta), delta, rtol=1e-14, atol=1e-15)


@pytest.mark.parametrize("dtype", [np.float32, np.float64])
def test_retraction_is_so3_plus_and_quaternion_plus(dtype: type) -> None:
    """The optimisers' retraction gives the values of so3_plus and quaternion_plus, float64
    references, within a few ulps: steps of 0 and around the series' threshold, small, large, and
    beyond pi."""
    rng = np.random.default_rng(10)
    # around t = eps^(1/4), the switch to the series: 1.2e-4 in float64, 1.9e-2 in float32
    lengths = np.array([0, 1e-9, 1e-4, 1.2e-4, 1.3e-4, 1e-3, 0.018, 0.019, 0.5, 2, np.pi - 1e-6, 4, 7, 30])
    axes = rng.normal(size=(len(lengths), 3))
    delta = (axes / np.linalg.norm(axes, axis=-1, keepdims=True)) * lengths[:, None]
    R, q = rotations(len(lengths)), unit_quaternions(len(lengths))
    eps = float(np.finfo(dtype).eps)
    for scalar_first in (True, False):
        stored = q if scalar_first else dqn.wxyz_to_xyzw(q)
        got = _optim.retract(dqn, np, stored.astype(dtype), delta.astype(dtype), "quaternion", scalar_first)
        assert got.dtype == dtype
        expected = dqn.quaternion_plus(stored, delta, scalar_first=scalar_first)
        np.testing.assert_allclose(got, expected, rtol=0, atol=8 * eps)
    got = _optim.retract(dqn, np, R.astype(dtype), delta.astype(dtype), "matrix", True)
    np.testing.assert_allclose(got, dqn.so3_plus(R, delta), rtol=0, atol=16 * eps)


def test_adam_step_is_along_its_first_moment() -> None:
    """Why RiemannianAdam keeps its moments' body coordinates as they are: the step is along the first
    moment, and the transport along it is then the identity."""
    rng = np.random.default_rng(6)
    g, m, v = rng.normal(size=(5, 3)), rng.normal(size=(5, 3)), rng.random((5, 1))
    direction, m, v, _ = _optim.adam(np, g, m, v, None, 3, (0.9, 0.999), 1e-8, False, True)
    np.testing.assert_allclose(np.cross(direction, m), 0.0, atol=1e-15)
    np.testing.assert_allclose(_optim.transport(np, -0.3 * direction, m), m, rtol=1e-14)


# ---------------------------------------------------------------------------------------------------
# torch: one step against finite differences, convergence, long runs, state, groups, refusals


def wahba(points: np.ndarray, rotation: np.ndarray) -> np.ndarray:
    return points @ np.swapaxes(rotation, -1, -2)


@pytest.mark.parametrize("kind", ["matrix", "quaternion"])
def test_torch_sgd_step_is_the_exponential_of_the_finite_difference_gradient(kind: str) -> None:
    rng = np.random.default_rng(7)
    R0 = rotations(4)
    a = rng.normal(size=(4, 3, 3))
    q0 = dqn.matrix_to_quaternion(R0)

    def loss(m: Any) -> Any:
        return ((torch.tensor(a) * m) ** 2).sum()

    start = R0 if kind == "matrix" else q0
    p = torch.nn.Parameter(torch.tensor(start))
    optimizer = RiemannianSGD([p], lr=0.1)
    loss(dqt.quaternion_to_matrix(p) if kind == "quaternion" else p).backward()
    optimizer.step()

    def along(w: np.ndarray) -> np.ndarray:
        return np.sum((a * dqn.so3_plus(R0, w)) ** 2, axis=(-1, -2))

    gradient = central_differences(along, 4)
    expected = dqn.so3_plus(R0, -0.1 * gradient)
    got = p.detach().numpy() if kind == "matrix" else dqn.quaternion_to_matrix(p.detach().numpy())
    np.testing.assert_allclose(got, expected, atol=1e-8)


def wahba_problem(batch: int, seed: int = 8) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Points, their rotated noisy images, and the closed-form optimum (``fit_rotation``)."""
    rng = np.random.default_rng(seed)
    truth = rotations(batch, seed)
    points = rng.normal(size=(batch, 20, 3))
    targets = wahba(points, truth) + 0.01 * rng.normal(size=points.shape)
    return points, targets, dqn.fit_rotation(points, targets)


def far_start(optimum: np.ndarray) -> np.ndarray:
    """Starts 170 degrees from the optimum, about random axes."""
    rng = np.random.default_rng(9)
    axis = rng.normal(size=(len(optimum), 3))
    axis *= np.deg2rad(170.0) / np.linalg.norm(axis, axis=-1, keepdims=True)
    return dqn.so3_plus(optimum, axis)


# Learning rates: Adam's step turns by about lr radians; SGD's by lr |g|, and |g| ~ 120 |w| here.
TORCH_OPTIMIZERS: dict[str, Callable[[list[Any]], torch.optim.Optimizer]] = {
    "adam": lambda ps: RiemannianAdam(ps, lr=0.1, betas=(0.9, 0.9)),
    "adam-amsgrad": lambda ps: RiemannianAdam(ps, lr=0.1, betas=(0.9, 0.9), amsgrad=True),
    "sgd-momentum": lambda ps: RiemannianSGD(ps, lr=0.005, momentum=0.9),
    "sgd-nesterov": lambda ps: RiemannianSGD(ps, lr=0.005, momentum=0.9, nesterov=True),
}
# The decay of the learning rate per step: AMSGrad's steps are lr |g| / max |g| near the optimum,
# gradient descent's own linear rate, which a decay would stop.
DECAY = {"adam": 0.98, "adam-amsgrad": 1.0, "sgd-momentum": 0.98, "sgd-nesterov": 0.98}


@pytest.mark.parametrize("name", list(TORCH_OPTIMIZERS))
def test_torch_optimizers_converge_to_the_closed_form(name: str) -> None:
    """A batch of Wahba problems, each started 170 degrees away, as matrices and as quaternions (in
    one optimizer), with a learning rate decaying to 3e-4 times its start (AMSGrad: constant): every
    one ends within 1e-3 degrees of the closed-form optimum. (Adam with beta2 = 0.999 remembers the
    large gradients far from the optimum for a thousand steps, and its steps near it are tiny: 0.4
    degrees away after 400 steps; beta2 = 0.9 forgets them.)"""
    points, targets, optimum = wahba_problem(8)
    start = far_start(optimum)
    R = torch.nn.Parameter(torch.tensor(start))
    q = torch.nn.Parameter(torch.tensor(dqn.wxyz_to_xyzw(dqn.matrix_to_quaternion(start))))
    optimizer = TORCH_OPTIMIZERS[name]([{"params": [R]}, {"params": [q], "scalar_first": False}])
    schedule = torch.optim.lr_scheduler.ExponentialLR(optimizer, DECAY[name])
    p_t, t_t = torch.tensor(points), torch.tensor(targets)
    for _ in range(400):
        optimizer.zero_grad()
        for m in (R, dqt.quaternion_to_matrix(q, scalar_first=False)):
            ((p_t @ m.transpose(-1, -2) - t_t) ** 2).sum().backward()
        optimizer.step()
        schedule.step()
    for m in (R.detach().numpy(), dqn.quaternion_to_matrix(q.detach().numpy(), scalar_first=False)):
        assert np.rad2deg(dqn.matrix_geodesic_distance(m, optimum)).max() < 1e-3


def test_torch_parameters_stay_rotations_for_ten_thousand_float32_steps() -> None:
    """1e4 float32 steps of 0.1 to 0.3 rad each, random gradients (the cheapest loss): matrices stay
    orthonormal to 1e-5 (R @ exp(d) itself drifts 2e-5 in as many steps) and quaternions unit."""
    generator = torch.Generator().manual_seed(0)
    R = torch.nn.Parameter(dqt.quaternion_to_matrix(dqt.random_quaternions(32, generator=generator)))
    q = torch.nn.Parameter(dqt.random_quaternions(32, generator=generator))
    optimizer = RiemannianSGD([R, q], lr=0.1)
    grads_R = torch.randn(64, 32, 3, 3, generator=generator)
    grads_q = torch.randn(64, 32, 4, generator=generator)
    for k in range(10_000):
        R.grad, q.grad = grads_R[k % 64], grads_q[k % 64]
        optimizer.step()
    eye = torch.eye(3)
    assert (R.detach().transpose(-1, -2) @ R.detach() - eye).abs().max() <= 1e-5
    assert torch.linalg.det(R.detach()).min() > 0
    assert (torch.linalg.vector_norm(q.detach(), dim=-1) - 1).abs().max() <= 1e-6


@pytest.mark.parametrize("name", ["adam-amsgrad", "sgd-nesterov"])
def test_torch_state_dict_round_trip(name: str) -> None:
    """Save after 5 steps, load into a fresh optimizer over copies of the parameters, take 5 more
    steps with both: the same parameters (the state carried every moment)."""
    points, targets, optimum = wahba_problem(4)
    p_t, t_t = torch.tensor(points), torch.tensor(targets)
    start = far_start(optimum)

    def params() -> list[torch.nn.Parameter]:
        return [
            torch.nn.Parameter(torch.tensor(start)),
            torch.nn.Parameter(torch.tensor(dqn.matrix_to_quaternion(start))),
        ]

    def steps(ps: list[torch.nn.Parameter], optimizer: torch.optim.Optimizer, n: int) -> None:
        for _ in range(n):
            optimizer.zero_grad()
            for m in (ps[0], dqt.quaternion_to_matrix(ps[1])):
                ((p_t @ m.transpose(-1, -2) - t_t) ** 2).sum().backward()
            optimizer.step()

    first = params()
    optimizer = TORCH_OPTIMIZERS[name](first)
    steps(first, optimizer, 5)
    buffer = io.BytesIO()
    torch.save(optimizer.state_dict(), buffer)
    second = [torch.nn.Parameter(p.detach().clone()) for p in first]
    restored = TORCH_OPTIMIZERS[name](second)
    buffer.seek(0)
    restored.load_state_dict(torch.load(buffer))
    steps(first, optimizer, 5)
    steps(second, restored, 5)
    for a, b in zip(first, second, strict=True):
        torch.testing.assert_close(a, b, rtol=0, atol=0)


def test_torch_param_groups_and_euclidean_groups() -> None:
    """Per-group learning rates (a group at lr 0 does not move), and a 'euclidean' group updated
    exactly as torch.optim.Adam updates it, weight decay included."""
    generator = torch.Generator().manual_seed(1)
    R = torch.nn.Parameter(
        dqt.quaternion_to_matrix(dqt.random_quaternions(3, generator=generator, dtype=torch.float64))
    )
    frozen = torch.nn.Parameter(R.detach().clone())
    w = torch.nn.Parameter(torch.randn(5, 4, generator=generator, dtype=torch.float64))
    w_ref = torch.nn.Parameter(w.detach().clone())
    optimizer = RiemannianAdam(
        [
            {"params": [R]},
            {"params": [frozen], "lr": 0.0},
            {"params": [w], "manifold": "euclidean", "weight_decay": 0.1},
        ],
        lr=0.05,
    )
    reference = torch.optim.Adam([w_ref], lr=0.05, weight_decay=0.1)
    for _ in range(20):
        for opt in (optimizer, reference):
            opt.zero_grad()
        (R.sum() + frozen.sum() + (w**3).sum()).backward()
        (w_ref**3).sum().backward()
        optimizer.step()
        reference.step()
    torch.testing.assert_close(w, w_ref, rtol=1e-12, atol=1e-12)
    torch.testing.assert_close(frozen, frozen.detach(), rtol=0, atol=0)
    assert (R - frozen).abs().max() > 0.1


def test_torch_sgd_euclidean_group_is_torch_sgd() -> None:
    generator = torch.Generator().manual_seed(2)
    w = torch.nn.Parameter(torch.randn(6, generator=generator, dtype=torch.float64))
    w_ref = torch.nn.Parameter(w.detach().clone())
    optimizer = RiemannianSGD(
        [w], lr=0.01, momentum=0.9, nesterov=True, weight_decay=0.2, manifold="euclidean"
    )
    reference = torch.optim.SGD([w_ref], lr=0.01, momentum=0.9, nesterov=True, weight_decay=0.2)
    for _ in range(10):
        for p, opt in ((w, optimizer), (w_ref, reference)):
            opt.zero_grad()
            (p**4).sum().backward()
            opt.step()
    torch.testing.assert_close(w, w_ref, rtol=1e-13, atol=1e-13)


def test_torch_refusals() -> None:
    R = torch.nn.Parameter(torch.eye(3))
    with pytest.raises(ValueError, match=r"RiemannianAdam: parameter 0 of param group 0 has shape \(5, 3\)"):
        RiemannianAdam([torch.nn.Parameter(torch.zeros(5, 3))])
    with pytest.raises(ValueError, match=r"does not hold unit quaternions"):
        RiemannianAdam([torch.nn.Parameter(torch.full((4,), 0.1))])  # a (4,) bias is no quaternion
    with pytest.raises(ValueError, match=r"does not hold rotation matrices"):
        RiemannianSGD([torch.nn.Parameter(-torch.eye(3))])  # a reflection
    with pytest.raises(ValueError, match=r"weight_decay=0.01: an L2 penalty"):
        RiemannianAdam([R], weight_decay=0.01)
    with pytest.raises(ValueError, match=r"manifold='sphere'"):
        RiemannianSGD([R], manifold="sphere")
    with pytest.raises(ValueError, match="Nesterov momentum requires"):
        RiemannianSGD([R], nesterov=True)
    with pytest.raises(TypeError, match="real floating-point dtype"):
        RiemannianSGD([torch.eye(3, dtype=torch.complex64)])
    optimizer = RiemannianAdam([R])
    with pytest.raises(ValueError, match="param group 1 has shape"):
        optimizer.add_param_group({"params": [torch.nn.Parameter(torch.zeros(2))]})
    assert len(optimizer.param_groups) == 1  # a refused group is not kept


def documented_example(heading: str) -> dict[str, Any]:
    """Runs the first code block after ``heading`` in docs/optimisation.md, as written there, and
    returns its variables."""
    from pathlib import Path

    text = (Path(__file__).resolve().parents[1] / "docs" / "optimisation.md").read_text()
    start = text.index("```python", text.index(heading))
    code = text[start + len("```python") : text.index("```", start + 1)]
    torch.manual_seed(0)
    scope: dict[str, Any] = {}
    exec(code, scope)  # the page's own code
    return scope


def test_documented_example_runs() -> None:
    """The documentation's block on the optimisers: every rotation ends at its target, and the
    parameters are rotations."""
    scope = documented_example("# Optimising rotations on the manifold")
    R = scope["R"].detach()
    assert dqt.matrix_geodesic_distance(R, scope["target"]).max() < 1e-3
    assert (R.transpose(-1, -2) @ R - torch.eye(3)).abs().max() < 1e-5


def test_documented_pose_example_runs() -> None:
    """The documentation's block on poses: every pose ends at the least-squares optimum
    (fit_rigid_transform) from the identity, and the parameters are rigid transforms."""
    scope = documented_example("## Poses: SE(3)")
    T = scope["T"].detach()
    optimum = dqt.fit_rigid_transform(scope["points"], scope["observed"])
    assert dqt.matrix_geodesic_distance(T[:, :3, :3], optimum[:, :3, :3]).max() < 1e-4
    assert (T[:, :3, 3] - optimum[:, :3, 3]).abs().max() < 1e-4
    assert (T[:, :3, :3].transpose(-1, -2) @ T[:, :3, :3] - torch.eye(3)).abs().max() < 1e-5
    assert torch.equal(T[:, 3], torch.tensor([0.0, 0.0, 0.0, 1.0]).expand(len(T), 4))


def test_modules_declare_their_public_names() -> None:
    import diffquat.jax.optim as jax_optim
    import diffquat.torch.optim as torch_optim

    for module in (torch_optim, jax_optim):
        defined = {
            n
            for n, v in vars(module).items()
            if callable(v) and getattr(v, "__module__", None) == module.__name__ and not n.startswith("_")
        }
        assert defined <= set(module.__all__)


# ---------------------------------------------------------------------------------------------------
# torch and jax take the same steps; jax on its own


CROSS: dict[
    str, tuple[Callable[[list[Any]], torch.optim.Optimizer], Callable[..., optax.GradientTransformation]]
] = {
    "adam": (
        lambda ps: RiemannianAdam(ps, lr=0.05, betas=(0.8, 0.99), eps=1e-6),
        lambda **kw: jo.riemannian_adam(0.05, 0.8, 0.99, 1e-6, **kw),
    ),
    "adam-amsgrad": (
        lambda ps: RiemannianAdam(ps, lr=0.05, amsgrad=True),
        lambda **kw: jo.riemannian_adam(0.05, amsgrad=True, **kw),
    ),
    "sgd-nesterov": (
        lambda ps: RiemannianSGD(ps, lr=0.005, momentum=0.9, nesterov=True),
        lambda **kw: jo.riemannian_sgd(0.005, 0.9, nesterov=True, **kw),
    ),
    "sgd-dampening": (
        lambda ps: RiemannianSGD(ps, lr=0.005, momentum=0.8, dampening=0.3),
        lambda **kw: jo.riemannian_sgd(0.005, 0.8, dampening=0.3, **kw),
    ),
}


@pytest.mark.parametrize("name", list(CROSS))
def test_torch_and_jax_take_the_same_steps_in_float64(name: str) -> None:
    points, targets, optimum = wahba_problem(4)
    start = far_start(optimum)
    q_start = dqn.matrix_to_quaternion(start)
    make_torch, make_jax = CROSS[name]
    R = torch.nn.Parameter(torch.tensor(start))
    q = torch.nn.Parameter(torch.tensor(q_start))
    optimizer = make_torch([R, q])
    p_t, t_t = torch.tensor(points), torch.tensor(targets)

    def loss_jax(params: dict[str, jax.Array]) -> jax.Array:
        total = jnp.zeros((), jnp.float64)
        for m in (params["R"], dqj.quaternion_to_matrix(params["q"])):
            total = total + jnp.sum((points @ jnp.swapaxes(m, -1, -2) - targets) ** 2)
        return total

    transformation = make_jax(scalar_first=True)

    @jax.jit
    def step(params: dict[str, jax.Array], state: Any) -> tuple[dict[str, jax.Array], Any]:
        updates, state = transformation.update(jax.grad(loss_jax)(params), state, params)
        return jo.apply_updates(params, updates, scalar_first=True), state

    params = {"R": jnp.asarray(start), "q": jnp.asarray(q_start)}
    state = transformation.init(params)
    for _ in range(30):
        optimizer.zero_grad()
        for m in (R, dqt.quaternion_to_matrix(q)):
            ((p_t @ m.transpose(-1, -2) - t_t) ** 2).sum().backward()
        optimizer.step()
        params, state = step(params, state)
    np.testing.assert_allclose(np.asarray(params["R"]), R.detach().numpy(), atol=1e-12)
    np.testing.assert_allclose(np.asarray(params["q"]), q.detach().numpy(), atol=1e-12)
    assert np.rad2deg(dqn.matrix_geodesic_distance(R.detach().numpy(), start)).min() > 1.0  # it moved


def test_jax_multi_transform_with_a_rotation_leaf_and_a_euclidean_leaf() -> None:
    """Under optax.multi_transform, the rotation leaf takes exactly riemannian_adam's steps and the
    Euclidean leaf exactly optax.adam's, and apply_updates tells them apart by the update's shape."""
    points, targets, optimum = wahba_problem(3)
    start = far_start(optimum)
    w0 = jnp.linspace(-1.0, 1.0, 4, dtype=jnp.float64)

    def loss(params: dict[str, jax.Array]) -> jax.Array:
        residual = points @ jnp.swapaxes(params["R"], -1, -2) - targets
        return jnp.sum(residual**2) + jnp.sum((params["w"] - 0.5) ** 4)

    mixed = optax.multi_transform(
        {"so3": jo.riemannian_adam(0.05), "euclidean": optax.adam(0.05)}, {"R": "so3", "w": "euclidean"}
    )

    def run(transformation: optax.GradientTransformation, params: Any, steps: int) -> Any:
        @jax.jit
        def step(params: Any, state: Any) -> Any:
            with jax.numpy_dtype_promotion("standard"):  # optax.adam's int32 count to a float power
                updates, state = transformation.update(jax.grad(loss)(params), state, params)
            return jo.apply_updates(params, updates), state

        state = transformation.init(params)
        for _ in range(steps):
            params, state = step(params, state)
        return params

    both = run(mixed, {"R": jnp.asarray(start), "w": w0}, 40)
    alone_R = run(
        optax.multi_transform(
            {"so3": jo.riemannian_adam(0.05), "none": optax.set_to_zero()}, {"R": "so3", "w": "none"}
        ),
        {"R": jnp.asarray(start), "w": w0},
        40,
    )["R"]
    np.testing.assert_allclose(np.asarray(both["R"]), np.asarray(alone_R), rtol=0, atol=1e-14)
    w = w0
    adam = optax.adam(0.05)
    state = adam.init(w)
    for _ in range(40):
        g = jax.grad(lambda w: loss({"R": both["R"], "w": w}))(w)
        with jax.numpy_dtype_promotion("standard"):
            updates, state = adam.update(g, state, w)
        w = optax.apply_updates(w, updates)
    np.testing.assert_allclose(np.asarray(both["w"]), np.asarray(w), rtol=1e-13)
    final = run(mixed, both, 360)
    assert np.rad2deg(dqn.matrix_geodesic_distance(np.asarray(final["R"]), optimum)).max() < 0.05


def test_jax_parameters_stay_rotations_for_ten_thousand_float32_steps() -> None:
    """The jax retraction, 1e4 float32 steps in one compiled loop: orthonormal to 1e-5, unit to 1e-6."""
    rng = np.random.default_rng(12)  # inputs made on the host: one compiled program in all
    params = {
        "R": jnp.asarray(rotations(32).astype(np.float32)),
        "q": jnp.asarray(unit_quaternions(32).astype(np.float32)),
    }
    transformation = jo.riemannian_sgd(0.1, scalar_first=True)
    grads = jnp.asarray(rng.normal(size=(64, 32, 4)).astype(np.float32))

    def body(k: jax.Array, carry: Any) -> Any:
        params, state = carry
        g = grads[k % 64]
        updates, state = transformation.update({"R": g[:, :3, None] * g[:, None, 1:], "q": g}, state, params)
        return jo.apply_updates(params, updates, scalar_first=True), state

    params, _ = jax.jit(lambda p: jax.lax.fori_loop(0, 10_000, body, (p, transformation.init(p))))(params)
    R, q = np.asarray(params["R"], np.float64), np.asarray(params["q"], np.float64)
    assert np.abs(np.swapaxes(R, -1, -2) @ R - np.eye(3)).max() <= 1e-5
    assert np.abs(np.linalg.norm(q, axis=-1) - 1).max() <= 1e-6


def test_jax_apply_updates_differentiates_to_the_tangent_gradient() -> None:
    """Differentiated through ``apply_updates`` (meta-learning does), the derivative of a loss in the
    update at 0 is the tangent gradient itself (``project_to_tangent`` of the loss's gradient), and
    it is finite at 0, where ``|delta|`` has no derivative."""
    rng = np.random.default_rng(11)
    params = {"R": jnp.asarray(rotations(4)), "q": jnp.asarray(unit_quaternions(4))}
    weights = {k: jnp.asarray(rng.normal(size=v.shape)) for k, v in params.items()}

    def loss(p: dict[str, jax.Array]) -> jax.Array:
        return sum(jnp.sum(weights[k] * p[k] ** 3) for k in p)

    zeros = {"R": jnp.zeros((4, 3), jnp.float64), "q": jnp.zeros((4, 3), jnp.float64)}
    # One compiled program each (eager jax compiles every primitive of the retraction apart).
    through = jax.jit(jax.grad(lambda u: loss(jo.apply_updates(params, u, scalar_first=True))))(zeros)
    project = jo.project_to_tangent(scalar_first=True).update
    projected, _ = jax.jit(lambda p: project(jax.grad(loss)(p), optax.EmptyState(), p))(params)
    for k in params:
        np.testing.assert_allclose(np.asarray(through[k]), np.asarray(projected[k]), rtol=1e-12, atol=1e-12)


def test_jax_quaternion_order_has_no_default_and_scalar_last_converges() -> None:
    """A quaternion leaf's order is stated to the transformation and to apply_updates, with no
    default in either: left out of one, ``ValueError`` naming that function and the leaf (before,
    ``riemannian_adam(scalar_first=False)`` with ``apply_updates`` left at its default retracted in
    the other order, silently, and the loss rose over 300 steps); stated in both, a scalar-last leaf
    takes the steps of the same leaf scalar first (float64, to 1e-13), and matrix leaves need none."""
    points, targets, optimum = wahba_problem(3)
    start = dqn.matrix_to_quaternion(far_start(optimum))

    def loss(params: dict[str, jax.Array], scalar_first: bool) -> jax.Array:
        m = dqj.quaternion_to_matrix(params["q"], scalar_first=scalar_first)
        return jnp.sum((points @ jnp.swapaxes(m, -1, -2) - targets) ** 2)

    def run(scalar_first: bool, make: Callable[..., optax.GradientTransformation]) -> np.ndarray:
        q = start if scalar_first else dqn.wxyz_to_xyzw(start)
        transformation = make(0.02, scalar_first=scalar_first)

        @jax.jit
        def step(params: Any, state: Any) -> Any:
            updates, state = transformation.update(jax.grad(loss)(params, scalar_first), state, params)
            return jo.apply_updates(params, updates, scalar_first=scalar_first), state

        params = {"q": jnp.asarray(q)}
        state = transformation.init(params)
        for _ in range(100):
            params, state = step(params, state)
        out = np.asarray(params["q"])
        return out if scalar_first else dqn.xyzw_to_wxyz(out)

    for make in (jo.riemannian_adam, jo.riemannian_sgd):
        first, last = run(True, make), run(False, make)
        np.testing.assert_allclose(last, first, rtol=0, atol=1e-13)
        assert np.rad2deg(
            dqn.quaternion_geodesic_distance(first, dqn.matrix_to_quaternion(optimum))
        ).max() < (
            np.rad2deg(dqn.quaternion_geodesic_distance(start, dqn.matrix_to_quaternion(optimum))).min()
        )
    params = {"q": jnp.asarray(start), "R": jnp.asarray(optimum)}
    grads = jax.tree.map(jnp.ones_like, params)
    for name, make in (("riemannian_adam", jo.riemannian_adam), ("riemannian_sgd", jo.riemannian_sgd)):
        transformation = make(0.1)
        with pytest.raises(ValueError, match=rf"^{name}: leaf \['q'\] holds quaternions.*scalar_first="):
            transformation.update(grads, transformation.init(params), params)
    with pytest.raises(ValueError, match=r"^project_to_tangent: leaf \['q'\] holds quaternions"):
        jo.project_to_tangent().update(grads, optax.EmptyState(), params)
    tangent = {"q": jnp.zeros((3, 3), jnp.float64), "R": jnp.zeros((3, 3), jnp.float64)}
    with pytest.raises(ValueError, match=r"^apply_updates: leaf \['q'\] holds quaternions"):
        jo.apply_updates(params, tangent)
    # matrix leaves alone need no order, anywhere
    matrices = {"R": params["R"]}
    transformation = jo.riemannian_adam(0.1)
    updates, _ = transformation.update({"R": grads["R"]}, transformation.init(matrices), matrices)
    assert np.all(np.isfinite(np.asarray(jo.apply_updates(matrices, updates)["R"])))


def test_jax_optax_wrappers_that_compose() -> None:
    """The transformations map gradients (the params' shapes) to tangent updates ``(..., 3)``. So
    ``optax.apply_if_finite(riemannian_adam(...))`` cannot compose (its rejected step is zeros of the
    gradients' shapes: jax's cond refuses two branch types; documented), but around the tangent part
    it does: ``chain(project_to_tangent(), apply_if_finite(chain(scale_by_riemannian_adam(),
    scale_by_learning_rate(lr)), k))`` takes riemannian_adam's steps exactly while the gradients are
    finite, and a non-finite gradient leaves the params and the moments as they were. Wrappers that
    map updates to updates of their shape compose around or after the whole optimiser
    (``optax.MultiSteps``, ``clip_by_global_norm``): the same steps as without them where they do
    nothing (a norm below the clip; one step per update)."""
    points, targets, optimum = wahba_problem(3)
    start = far_start(optimum)
    params = {"R": jnp.asarray(start)}

    def loss(p: dict[str, jax.Array]) -> jax.Array:
        return jnp.sum((points @ jnp.swapaxes(p["R"], -1, -2) - targets) ** 2)

    with pytest.raises(TypeError):
        wrapped = optax.apply_if_finite(jo.riemannian_adam(0.05), 3)
        wrapped.update(jax.grad(loss)(params), wrapped.init(params), params)
    guarded = optax.chain(
        jo.project_to_tangent(),
        optax.apply_if_finite(
            optax.chain(jo.scale_by_riemannian_adam(), optax.scale_by_learning_rate(0.05)), 3
        ),
    )
    transformations = {
        "adam": jo.riemannian_adam(0.05),
        "guarded": guarded,
        "multisteps": optax.MultiSteps(jo.riemannian_adam(0.05), 1).gradient_transformation(),
        "clipped": optax.chain(optax.clip_by_global_norm(1e6), jo.riemannian_adam(0.05)),
    }
    states = {k: t.init(params) for k, t in transformations.items()}
    current = dict.fromkeys(transformations, params)
    for k in range(6):
        for name, t in transformations.items():
            g = jax.grad(loss)(current[name])
            if name == "guarded" and k == 3:  # a non-finite gradient: the step is skipped
                before = current[name]
                updates, states[name] = t.update(jax.tree.map(lambda x: x * jnp.nan, g), states[name], before)
                current[name] = jo.apply_updates(before, updates)
                # a zero step: the retraction's own rounding (through the quaternion), 8 ulps
                np.testing.assert_allclose(
                    np.asarray(current[name]["R"]),
                    np.asarray(before["R"]),
                    rtol=0,
                    atol=8 * np.finfo(float).eps,
                )
                g = jax.grad(loss)(current[name])
            with jax.numpy_dtype_promotion("standard"):  # MultiSteps' float32 counters
                updates, states[name] = t.update(g, states[name], current[name])
            current[name] = jo.apply_updates(current[name], updates)
    for name in transformations:
        np.testing.assert_allclose(
            np.asarray(current[name]["R"]), np.asarray(current["adam"]["R"]), rtol=0, atol=1e-14, err_msg=name
        )


def test_jax_refusals() -> None:
    params = {"R": jnp.eye(3, dtype=jnp.float64), "b": jnp.zeros(5, jnp.float64)}
    with pytest.raises(ValueError, match=r"leaf \['b'\] has shape \(5,\).*multi_transform"):
        jo.riemannian_adam(0.1).init(params)
    with pytest.raises(ValueError, match=r"needs the params"):
        jo.project_to_tangent().update({"R": params["R"]}, optax.EmptyState())
    expected = r"update \['R'\] has shape \(3, 3\); expected tangent vectors \(3,\)"
    with pytest.raises(ValueError, match=expected):
        transformation = jo.scale_by_riemannian_adam()
        transformation.update({"R": params["R"]}, transformation.init({"R": params["R"]}))
    with pytest.raises(
        ValueError, match=r"apply_updates: leaf \['R'\] of shape \(3, 3\) has an update of shape \(4,\)"
    ):
        jo.apply_updates({"R": params["R"]}, {"R": jnp.zeros(4, jnp.float64)})
    with pytest.raises(ValueError, match="Nesterov momentum requires"):
        jo.riemannian_sgd(0.1, nesterov=True)


# ---------------------------------------------------------------------------------------------------
# SE(3): rigid transforms (manifold "se3")


def poses(n: int, seed: int = 20) -> np.ndarray:
    """``n`` random rigid transforms (float64), the identity and a half-turn among them."""
    rng = np.random.default_rng(seed)
    return dqn.se3_from_rotation_translation(rotations(n, seed), rng.normal(size=(n, 3)))


def central_differences_6(f: Callable[[np.ndarray], np.ndarray], n: int, h: float = 1e-6) -> np.ndarray:
    """``d f(w) / dw`` at 0 for ``f`` of twists ``(n, 6)`` giving ``(n,)``."""
    steps = np.eye(6)[:, None, :] * h
    return np.stack(
        [(f(np.broadcast_to(s, (n, 6))) - f(-np.broadcast_to(s, (n, 6)))) / (2 * h) for s in steps], -1
    )


def test_pose_tangent_gradient_is_the_derivative_along_the_retraction() -> None:
    """``(R^T G_t, vee(R^T G_R - G_R^T R))`` against central differences of ``f(se3_plus(T, w))``,
    for a function of every entry (the bottom row's gradient must not leak in)."""
    rng = np.random.default_rng(21)
    T = poses(6)
    a = rng.normal(size=(6, 4, 4))

    def f(m: np.ndarray) -> np.ndarray:
        return np.sum(a * m**3, axis=(-1, -2))

    expected = central_differences_6(lambda w: f(dqn.se3_plus(T, w)), 6)
    np.testing.assert_allclose(_optim.pose_tangent_gradient(np, T, 3 * a * T**2), expected, atol=1e-8)


@pytest.mark.parametrize("dtype", [np.float32, np.float64])
def test_pose_retraction_is_se3_plus(dtype: type) -> None:
    """The retraction gives se3_plus' values (float64 reference) within a few ulps of the entries'
    size, with the bottom row exact, for rotation steps of 0, across the series' thresholds (SO(3)'s
    at eps^(1/4), SE(3)'s Q below |phi| = 2), large, and beyond pi."""
    rng = np.random.default_rng(22)
    lengths = np.array([0, 1e-9, 1e-4, 1.3e-4, 0.019, 0.5, 1.99, 2.01, 3, np.pi - 1e-6, 4, 7])
    axes = rng.normal(size=(len(lengths), 3))
    delta = np.concatenate(
        [
            rng.normal(size=(len(lengths), 3)),
            axes / np.linalg.norm(axes, axis=-1, keepdims=True) * lengths[:, None],
        ],
        axis=-1,
    )
    T = poses(len(lengths))
    got = _optim.retract(dqn, np, T.astype(dtype), delta.astype(dtype), _optim.POSE, True)
    assert got.dtype == dtype
    expected = dqn.se3_plus(T, delta)
    scale = 1 + np.abs(expected).max(axis=(-1, -2), keepdims=True)
    assert np.max(np.abs(got - expected) / scale) <= 16 * float(np.finfo(dtype).eps)
    np.testing.assert_array_equal(got[..., 3, :], np.broadcast_to([0.0, 0.0, 0.0, 1.0], got[..., 3, :].shape))


def test_pose_momentum_is_the_parallel_transport_of_the_embedded_manifold() -> None:
    """A Nesterov step (not along its buffer) moves the buffer to the new pose as the Levi-Civita
    transport of R^3 x SO(3), embedded in R^3 x R^(3x3): the translation part constant in the ambient
    space (read in the new pose's body frame), the rotation part by projection (as on SO(3))."""
    rng = np.random.default_rng(23)
    T, grad = poses(8), rng.normal(size=(8, 6))
    grad[0] = 0.0
    update, buffer = _optim.pose_momentum(np, T, grad, np.zeros((8, 6)), True, 0.4, 0.9, 0.0, True)
    moved = _optim.retract(dqn, np, T, update, _optim.POSE, True)
    body = _optim.pose_to_body(np, moved, buffer)  # the buffer in the body frame of the new pose
    R, R_new = T[:, :3, :3], moved[:, :3, :3]
    expected_rho = np.einsum("nji,njk,nk->ni", R_new, R, grad[:, :3])
    phi = grad[:, 3:]
    expected_phi = 2 * projection_transport(R, update[:, 3:], phi, 1600) - projection_transport(
        R, update[:, 3:], phi, 800
    )
    np.testing.assert_allclose(body[:, :3], expected_rho, atol=1e-12)
    np.testing.assert_allclose(body[:, 3:], expected_phi, atol=1e-5)
    assert np.abs(body[:, :3] - grad[:, :3]).max() > 0.1  # the body coordinates do turn


def registration_problem(batch: int, seed: int = 24) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Points, their noisy images under random poses, the closed-form optimum (``fit_rigid_transform``)
    and a start 170 degrees and ~2 units away from it."""
    rng = np.random.default_rng(seed)
    points = rng.normal(size=(batch, 20, 3))
    targets = dqn.se3_apply(poses(batch, seed)[:, None], points) + 0.01 * rng.normal(size=points.shape)
    optimum = dqn.fit_rigid_transform(points, targets)
    axis = rng.normal(size=(batch, 3))
    axis *= np.deg2rad(170.0) / np.linalg.norm(axis, axis=-1, keepdims=True)
    start = dqn.se3_plus(optimum, np.concatenate([rng.normal(size=(batch, 3)), axis], axis=-1))
    return points, targets, optimum, start


@pytest.mark.parametrize("name", list(TORCH_OPTIMIZERS))
def test_torch_pose_optimizers_converge_to_the_closed_form(name: str) -> None:
    """A batch of point-set registrations, each started 170 degrees away: every pose ends within
    1e-3 degrees and 1e-5 units of fit_rigid_transform's optimum, a rigid transform."""
    points, targets, optimum, start = registration_problem(8)
    T = torch.nn.Parameter(torch.tensor(start))
    optimizer = TORCH_OPTIMIZERS[name]([{"params": [T], "manifold": "se3"}])
    schedule = torch.optim.lr_scheduler.ExponentialLR(optimizer, DECAY[name])
    p_t, t_t = torch.tensor(points), torch.tensor(targets)
    for _ in range(400):
        optimizer.zero_grad()
        ((dqt.se3_apply(T[:, None], p_t) - t_t) ** 2).sum().backward()
        optimizer.step()
        schedule.step()
    got = T.detach().numpy()
    assert np.rad2deg(dqn.matrix_geodesic_distance(got[:, :3, :3], optimum[:, :3, :3])).max() < 1e-3
    assert np.abs(got[:, :3, 3] - optimum[:, :3, 3]).max() < 1e-5
    np.testing.assert_array_equal(got[:, 3], np.broadcast_to([0.0, 0.0, 0.0, 1.0], (8, 4)))


def test_torch_pose_momentum_of_the_translation_keeps_its_world_direction() -> None:
    """A constant world-frame force on the translation while the rotation spins: the momentum buffer's
    translation part (kept in the world frame) is the geometric sum of the force, and the translation
    moves along it, where body-frame moments without transport would turn with the rotation."""
    T = torch.nn.Parameter(torch.eye(4, dtype=torch.float64))
    force = torch.tensor([0.3, -0.2, 0.5], dtype=torch.float64)
    spin = torch.tensor([0.0, 0.0, 1.0], dtype=torch.float64)
    optimizer = RiemannianSGD([T], lr=0.01, momentum=0.9, manifold="se3")
    turned = torch.zeros((), dtype=torch.float64)
    for k in range(1, 61):
        before = T.detach()[:3, 3].clone()
        optimizer.zero_grad()
        # d/dT of <force, t> + the turn about z: a constant tangent gradient (force, spin) at every pose
        R = T.detach()[:3, :3].clone()
        T.grad = torch.zeros(4, 4, dtype=torch.float64)
        T.grad[:3, 3] = force
        T.grad[:3, :3] = 0.5 * R @ dqt.so3_hat(spin)
        optimizer.step()
        buffer = optimizer.state[T]["momentum_buffer"]
        torch.testing.assert_close(buffer[:3], force * (1 - 0.9**k) / (1 - 0.9), rtol=1e-12, atol=0)
        step = T.detach()[:3, 3] - before
        cosine = -(step @ force) / (step.norm() * force.norm())
        # Down the force, to within the turn of J_l(d_phi) in the step R J_l(d_phi) d_rho: at most
        # |d_phi| / 2 = 0.05 rad here, while the frame turns by 0.1 rad a step, 5.9 rad in all.
        assert cosine > math.cos(0.051)
        turned = turned + dqt.matrix_geodesic_distance(T.detach()[:3, :3], R)
    assert turned > 4.0


def test_pose_parameters_stay_rigid_for_ten_thousand_float32_steps() -> None:
    """1e4 float32 steps of about 0.1 to 0.3 (rad and units), random gradients, in torch and in jax
    (one compiled loop): |R^T R - I| <= 1e-5, det R > 0, the bottom row exactly (0, 0, 0, 1)."""
    rng = np.random.default_rng(25)
    start = poses(32).astype(np.float32)
    grads = rng.normal(size=(64, 32, 4, 4)).astype(np.float32)
    T = torch.nn.Parameter(torch.tensor(start))
    optimizer = RiemannianSGD([T], lr=0.1, manifold="se3")
    grads_t = torch.tensor(grads)
    for k in range(10_000):
        T.grad = grads_t[k % 64]
        optimizer.step()
    transformation = jo.riemannian_sgd(0.1, manifold="se3")
    grads_j = jnp.asarray(grads)

    def body(k: jax.Array, carry: Any) -> Any:
        params, state = carry
        updates, state = transformation.update({"T": grads_j[k % 64]}, state, params)
        return jo.apply_updates(params, updates), state

    params = {"T": jnp.asarray(start)}
    params, _ = jax.jit(lambda p: jax.lax.fori_loop(0, 10_000, body, (p, transformation.init(p))))(params)
    for got in (T.detach().numpy(), np.asarray(params["T"])):
        R = got[:, :3, :3].astype(np.float64)
        assert np.abs(np.swapaxes(R, -1, -2) @ R - np.eye(3)).max() <= 1e-5
        assert np.linalg.det(R).min() > 0
        np.testing.assert_array_equal(got[:, 3], np.broadcast_to(np.float32([0, 0, 0, 1]), (32, 4)))


@pytest.mark.parametrize("name", list(CROSS))
def test_torch_and_jax_take_the_same_pose_steps_in_float64(name: str) -> None:
    points, targets, _, start = registration_problem(4)
    make_torch, make_jax = CROSS[name]
    T = torch.nn.Parameter(torch.tensor(start))
    optimizer = make_torch([{"params": [T], "manifold": "se3"}])
    transformation = make_jax(manifold="se3")

    def loss_jax(params: dict[str, jax.Array]) -> jax.Array:
        return jnp.sum((dqj.se3_apply(params["T"][:, None], points) - targets) ** 2)

    @jax.jit
    def step(params: dict[str, jax.Array], state: Any) -> tuple[dict[str, jax.Array], Any]:
        updates, state = transformation.update(jax.grad(loss_jax)(params), state, params)
        return jo.apply_updates(params, updates), state

    params = {"T": jnp.asarray(start)}
    state = transformation.init(params)
    p_t, t_t = torch.tensor(points), torch.tensor(targets)
    for _ in range(30):
        optimizer.zero_grad()
        ((dqt.se3_apply(T[:, None], p_t) - t_t) ** 2).sum().backward()
        optimizer.step()
        params, state = step(params, state)
    np.testing.assert_allclose(np.asarray(params["T"]), T.detach().numpy(), atol=1e-12)
    assert np.abs(T.detach().numpy() - start).max() > 0.1  # it moved


def test_jax_pose_leaves_under_multi_transform_and_through_apply_updates() -> None:
    """A pytree of a pose, a rotation and an ordinary array under optax.multi_transform, told apart
    by labels; differentiated through apply_updates at 0, a loss's derivative in the pose's update is
    its tangent gradient (project_to_tangent(manifold="se3"))."""
    rng = np.random.default_rng(26)
    params = {"T": jnp.asarray(poses(3)), "R": jnp.asarray(rotations(3)), "w": jnp.zeros(4, jnp.float64)}
    weights = {k: jnp.asarray(rng.normal(size=v.shape)) for k, v in params.items()}

    def loss(p: dict[str, jax.Array]) -> jax.Array:
        return sum(jnp.sum(weights[k] * p[k] ** 3) for k in p)

    mixed = optax.multi_transform(
        {
            "se3": jo.riemannian_adam(0.05, manifold="se3"),
            "so3": jo.riemannian_adam(0.05),
            "e": optax.sgd(0.1),
        },
        {"T": "se3", "R": "so3", "w": "e"},
    )

    @jax.jit
    def step(params: Any, state: Any) -> Any:
        updates, state = mixed.update(jax.grad(loss)(params), state, params)
        return jo.apply_updates(params, updates), state

    state = mixed.init(params)
    moved = params
    for _ in range(5):
        moved, state = step(moved, state)
    alone = jo.riemannian_adam(0.05, manifold="se3")
    T, alone_state = {"T": params["T"]}, alone.init({"T": params["T"]})
    for _ in range(5):
        g = jax.grad(lambda t: loss({**params, **moved, "T": t["T"]}))(T)
        updates, alone_state = alone.update(g, alone_state, T)
        T = jo.apply_updates(T, updates)
    np.testing.assert_allclose(np.asarray(moved["T"]), np.asarray(T["T"]), rtol=0, atol=1e-14)
    assert np.abs(np.asarray(moved["T"] - params["T"])).max() > 0.05

    pose = {"T": params["T"]}
    through = jax.jit(jax.grad(lambda u: loss({**params, **jo.apply_updates(pose, u)})))(
        {"T": jnp.zeros((3, 6), jnp.float64)}
    )
    project = jo.project_to_tangent(manifold="se3").update
    projected, _ = jax.jit(
        lambda p: project(jax.grad(lambda t: loss({**params, **t}))(p), optax.EmptyState(), p)
    )(pose)
    np.testing.assert_allclose(np.asarray(through["T"]), np.asarray(projected["T"]), rtol=1e-12, atol=1e-12)


SCALED: dict[
    str, tuple[Callable[..., torch.optim.Optimizer], Callable[..., optax.GradientTransformation]]
] = {
    "adam": (
        lambda ps, s: RiemannianAdam(ps, lr=0.05, betas=(0.9, 0.99), manifold="se3", length_scale=s),
        lambda s: jo.riemannian_adam(0.05, 0.9, 0.99, manifold="se3", length_scale=s),
    ),
    "sgd-nesterov": (
        lambda ps, s: RiemannianSGD(
            ps, lr=0.005, momentum=0.9, nesterov=True, manifold="se3", length_scale=s
        ),
        lambda s: jo.riemannian_sgd(0.005, 0.9, nesterov=True, manifold="se3", length_scale=s),
    ),
    "sgd": (
        lambda ps, s: RiemannianSGD(ps, lr=0.005, manifold="se3", length_scale=s),
        lambda s: jo.riemannian_sgd(0.005, manifold="se3", length_scale=s),
    ),
}


@pytest.mark.parametrize("name", list(SCALED))
def test_length_scale_makes_the_pose_steps_independent_of_the_units(name: str) -> None:
    """The same registration in metres (length_scale 1) and in millimetres (length_scale 1000, the
    loss in square metres): the same rotations and the same translations, in torch and in jax, at
    every step; and in millimetres without the scale, other steps."""
    points, targets, _, start = registration_problem(4)
    make_torch, make_jax = SCALED[name]

    def run(factor: float, scale: float) -> tuple[np.ndarray, np.ndarray]:
        begin = start.copy()
        begin[:, :3, 3] *= factor
        p, t = points * factor, targets * factor
        T = torch.nn.Parameter(torch.tensor(begin))
        optimizer = make_torch([T], scale)
        transformation = make_jax(scale)

        def loss_jax(params: dict[str, jax.Array]) -> jax.Array:
            return jnp.sum((dqj.se3_apply(params["T"][:, None], p) - t) ** 2) / factor**2

        @jax.jit
        def step(params: dict[str, jax.Array], state: Any) -> tuple[dict[str, jax.Array], Any]:
            updates, state = transformation.update(jax.grad(loss_jax)(params), state, params)
            return jo.apply_updates(params, updates), state

        params = {"T": jnp.asarray(begin)}
        state = transformation.init(params)
        p_t, t_t = torch.tensor(p), torch.tensor(t)
        for _ in range(20):
            optimizer.zero_grad()
            (((dqt.se3_apply(T[:, None], p_t) - t_t) ** 2).sum() / factor**2).backward()
            optimizer.step()
            params, state = step(params, state)
        out = T.detach().numpy().copy()
        np.testing.assert_allclose(np.asarray(params["T"]), out, rtol=1e-12, atol=1e-12 * factor)
        out[:, :3, 3] /= factor
        return out[:, :3, :3], out[:, :3, 3]

    metres = run(1.0, 1.0)
    millimetres = run(1000.0, 1000.0)
    np.testing.assert_allclose(millimetres[0], metres[0], rtol=0, atol=1e-11)
    np.testing.assert_allclose(millimetres[1], metres[1], rtol=0, atol=1e-11)
    assert np.abs(metres[1] - start[:, :3, 3]).max() > 0.05  # it moved
    unscaled = run(1000.0, 1.0)
    assert np.abs(unscaled[0] - metres[0]).max() > 1e-3


def test_pose_refusals() -> None:
    eye4 = torch.eye(4)
    with pytest.raises(
        ValueError,
        match=r"parameter 0 of param group 0 has shape \(3, 3\); a param group with manifold 'se3'",
    ):
        RiemannianAdam([torch.nn.Parameter(torch.eye(3))], manifold="se3")
    shear = eye4.clone()
    shear[3, 0] = 0.5
    with pytest.raises(ValueError, match=r"does not hold rigid transforms"):
        RiemannianSGD([torch.nn.Parameter(shear)], manifold="se3")
    with pytest.raises(
        ValueError,
        match=r"holds rigid transforms, which a group with manifold 'so3' would read as quaternions",
    ):
        RiemannianAdam([torch.nn.Parameter(eye4)])
    with pytest.raises(ValueError, match=r"manifold 'se3'\) has weight_decay=0.1"):
        RiemannianAdam([torch.nn.Parameter(eye4)], manifold="se3", weight_decay=0.1)
    params = {"R": jnp.eye(3, dtype=jnp.float64)}
    with pytest.raises(ValueError, match=r"leaf \['R'\] has shape \(3, 3\); expected rigid transforms"):
        jo.riemannian_adam(0.1, manifold="se3").init(params)
    with pytest.raises(ValueError, match=r"param group 0 \(manifold 'so3'\) has length_scale=2.0"):
        RiemannianAdam([torch.nn.Parameter(torch.eye(3))], length_scale=2.0)
    with pytest.raises(ValueError, match=r"has length_scale=-1.0; expected a positive finite length"):
        RiemannianSGD([torch.nn.Parameter(eye4)], manifold="se3", length_scale=-1.0)
    with pytest.raises(ValueError, match=r"riemannian_adam: length_scale=0.0 with manifold='se3'"):
        jo.riemannian_adam(0.1, manifold="se3", length_scale=0.0)
    with pytest.raises(ValueError, match=r"riemannian_sgd: manifold='sphere'"):
        jo.riemannian_sgd(0.1, manifold="sphere")
    pose = {"T": jnp.eye(4, dtype=jnp.float64)}
    transformation = jo.scale_by_riemannian_adam(manifold="se3")
    with pytest.raises(ValueError, match=r"needs the params on SE\(3\)"):
        transformation.update({"T": jnp.zeros(6, jnp.float64)}, transformation.init(pose))
    with pytest.raises(ValueError, match=r"update \['T'\] has shape \(3,\); expected tangent vectors \(6,\)"):
        transformation.update({"T": jnp.zeros(3, jnp.float64)}, transformation.init(pose), pose)
    with pytest.raises(ValueError, match=r"leaf \['T'\] of shape \(4, 4\) has an update of shape \(5,\)"):
        jo.apply_updates(pose, {"T": jnp.zeros(5, jnp.float64)})
