"""Pose refinement on SE(3) by gradient descent, from noisy 3D-3D and 2D-3D correspondences:
``diffquat.torch.optim.RiemannianAdam`` on ``(B, 4, 4)`` poses (``manifold="se3"``) against
``torch.optim.Adam`` on raw parameters, against the closed form (``fit_rigid_transform``), its robust
iteration, and Gauss-Newton.

Two synthetic problems (float64, nothing downloaded), each a batch of independent poses:

- **Registration (3D-3D).** ``B`` objects, each ``N`` model points ``s_i`` in a 20 cm box, seen at
  ``o_i = T s_i + e_i`` with per-point noise ``e_i ~ N(0, sigma_i^2 I)``, ``sigma_i`` log-uniform in
  1-5 mm (heteroscedastic, as a depth sensor's), weights ``w_i = 1 / sigma_i^2``. The cost is
  ``1/2 sum_i rho(w_i |T s_i - o_i|^2)`` with ``rho(s) = s`` (weighted least squares, whose minimiser
  is ``fit_rigid_transform``'s closed form) or the Cauchy loss ``rho(s) = c^2 log(1 + s / c^2)`` for
  data where a fifth of the correspondences are wrong matches (``o_i`` is another model point's).
- **Camera resection (2D-3D, PnP).** ``B`` cameras (pinhole, f = 500 px, 640 x 480), each seeing
  ``N`` landmarks 2-6 m away, with 1 px Gaussian noise on the pixels. The parameter is the camera's
  pose in the world ``T_wc`` (its right perturbation turns the camera about its own centre), the cost
  ``1/2 sum_i |pi(T_wc^-1 X_i) - u_i|^2 / sigma^2``. No closed form: Gauss-Newton with the analytic
  Jacobian of the reprojection error gives the optimum.

Every method starts from the truth perturbed by a random twist (5-45 degrees and 2-10 cm for
registration, 2-10 degrees and 10-30 cm for cameras) and is scored by the rotation angle (degrees) and
the translation (mm) between its poses and the truth, and between its poses and the optimum.

Run:  python notebooks/pose_refinement.py    (DIFFQUAT_SMALL=1: the small test-suite size)
"""

from __future__ import annotations

import argparse
import os
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
from _sizes import figure_dir, small_mode

import diffquat.numpy as dqn

# ---------------------------------------------------------------------------------------------------
# Settings


RIEMANNIAN = "RiemannianAdam, se3 (torch)"
RIEMANNIAN_JAX = "riemannian_adam, se3 (jax)"
ADAM = "Adam, raw quaternion + translation"
ADAM_MATRIX = "Adam, raw 3x4 matrix (scored projected)"
ADAM_PROJECTED = "Adam, raw 3x4, projected every step"
CLOSED_FORM = "fit_rigid_transform (closed form)"
IRLS = "IRLS: fit_rigid_transform reweighted"
GAUSS_NEWTON = "Gauss-Newton (analytic Jacobian)"


@dataclass(frozen=True)
class Settings:
    """Sizes, steps, and each Adam's learning rate per problem. The learning rate decays exponentially
    to ``lr_decay`` times its start over ``steps`` (one schedule for every gradient method). Each rate
    is that method's best on the full-size problem, by the steps its worst pose took to come within
    1e-3 degrees of the optimum, over 0.01, 0.02, 0.05, 0.1 and 0.2 (metres and radians per step for
    RiemannianAdam: the scenes are metre-sized), with a tenth and a hundredth as the decay:

    - least squares: RiemannianAdam 0.2 (196 steps; 0.05-0.1: 197-201), Adam 0.05 (196; the others
      202-209); the raw 3x4 block 0.05 (at its own optimum, the affine fit, from step ~100; 0.02-0.2
      alike), projected after every step 0.1 (stops 0.19 degrees from the optimum; 0.22-0.30 at the
      other rates);
    - Cauchy: RiemannianAdam 0.05 (182), Adam 0.02 (179); at 0.1 they need 269 and 342 steps, and at
      0.2 neither is within 1e-3 degrees after 400;
    - cameras: RiemannianAdam 0.2 (177), Adam 0.05 (not within 1e-3 degrees in 400 steps at any rate
      of the grid: 9e-3 at best; at 0.2, 220 of the 256 cameras are still 0.01-16 degrees away).

    A decay to a hundredth was 4-7 steps faster on the registrations, and worse on the cameras
    (RiemannianAdam at 0.2: 4e-3 degrees from the optimum after 400 steps, against 177 steps to 1e-3)."""

    objects: int  # registration problems (poses)
    points: int  # correspondences per object
    cameras: int  # resection problems (camera poses)
    landmarks: int  # 2D-3D correspondences per camera
    steps: int
    irls_iterations: int = 30
    gauss_newton_iterations: int = 10
    outliers: float = 0.2  # the fraction of wrong matches in the robust registration
    cauchy: float = 3.0  # c of the Cauchy loss, in units of each point's sigma
    lr: dict[str, dict[str, float]] = field(
        default_factory=lambda: {
            "least_squares": {RIEMANNIAN: 0.2, ADAM: 0.05, ADAM_MATRIX: 0.05, ADAM_PROJECTED: 0.1},
            "robust": {RIEMANNIAN: 0.05, ADAM: 0.02},
            "cameras": {RIEMANNIAN: 0.2, ADAM: 0.05},
        }
    )
    lr_decay: float = 0.1
    seed: int = 0


FULL = Settings(objects=256, points=100, cameras=256, landmarks=50, steps=400)
SMALL = Settings(objects=8, points=30, cameras=8, landmarks=20, steps=60, irls_iterations=10)


# ---------------------------------------------------------------------------------------------------
# The problems (numpy, float64)


def random_twists(
    rng: np.random.Generator, n: int, degrees: tuple[float, float], metres: tuple[float, float]
) -> np.ndarray:
    """``(n, 6)`` twists ``(rho, phi)``: random directions, angles and lengths uniform in the ranges."""

    def vectors(lo: float, hi: float) -> np.ndarray:
        v = rng.normal(size=(n, 3))
        return v / np.linalg.norm(v, axis=-1, keepdims=True) * rng.uniform(lo, hi, size=(n, 1))

    return np.concatenate([vectors(*metres), vectors(*np.deg2rad(degrees))], axis=-1)


@dataclass(frozen=True)
class Registration:
    """3D-3D correspondences of ``B`` objects: ``observed_i ~ T model_i`` (``B, N, 3``)."""

    model: np.ndarray  # (B, N, 3) points in the object frame, metres
    observed: np.ndarray  # (B, N, 3) the same points measured in the sensor frame
    sigma: np.ndarray  # (B, N) each measurement's noise (standard deviation per axis, metres)
    outlier: np.ndarray  # (B, N) bool: a wrong match (observed is another model point's)
    truth: np.ndarray  # (B, 4, 4)
    start: np.ndarray  # (B, 4, 4)

    @property
    def weights(self) -> np.ndarray:
        return 1.0 / self.sigma**2


def make_registration(objects: int, points: int, outliers: float = 0.0, seed: int = 0) -> Registration:
    """Model points uniform in a 20 cm box about the object's origin; poses uniform in rotation, 0.6-1.4 m
    in front of the sensor; noise 1-5 mm (log-uniform) per point; a fraction ``outliers`` of the
    correspondences wrong (each observed point is a different, random model point's); the start is
    the truth moved by a random body twist of 5-45 degrees and 2-10 cm."""
    rng = np.random.default_rng(seed)
    model = rng.uniform(-0.1, 0.1, size=(objects, points, 3))
    rotation = dqn.SO3.random(objects, rng=rng)
    translation = np.array([0.0, 0.0, 1.0]) + rng.uniform(-0.4, 0.4, size=(objects, 3))
    truth = dqn.SE3.from_rotation_translation(rotation, translation)  # (B,) poses, object to sensor
    sigma = np.exp(rng.uniform(np.log(1e-3), np.log(5e-3), size=(objects, points)))
    outlier = rng.random((objects, points)) < outliers
    shift = rng.integers(1, points, size=(objects, points))  # a wrong match: another point, never itself
    matched = np.where(outlier, (np.arange(points) + shift) % points, np.arange(points))
    source = np.take_along_axis(model, matched[..., None], axis=1)
    observed = truth[:, None] @ source + sigma[..., None] * rng.normal(size=source.shape)
    start = truth.plus(random_twists(rng, objects, (5.0, 45.0), (0.02, 0.10)))  # T exp(delta)
    return Registration(model, observed, sigma, outlier, truth.matrix, start.matrix)


@dataclass(frozen=True)
class Cameras:
    """2D-3D correspondences of ``B`` cameras: ``pixels_i ~ pi(T_wc^-1 landmarks_i)``."""

    landmarks: np.ndarray  # (B, N, 3) world points, metres
    pixels: np.ndarray  # (B, N, 2) their measured projections
    sigma: float  # pixel noise, standard deviation per axis
    focal: float
    centre: tuple[float, float]
    truth: np.ndarray  # (B, 4, 4): T_wc, the camera's pose in the world (camera to world)
    start: np.ndarray  # (B, 4, 4)


def make_cameras(cameras: int, landmarks: int, sigma: float = 1.0, seed: int = 1) -> Cameras:
    """Camera poses uniform in rotation, centres within 2 m of the origin; landmarks uniform in the
    image (640 x 480, f = 500 px) at depths 2-6 m; 1 px noise; the start is the truth moved by a random
    body twist of 2-10 degrees (about the optical centre) and 10-30 cm."""
    rng = np.random.default_rng(seed)
    focal, centre, size = 500.0, (320.0, 240.0), (640.0, 480.0)
    rotation = dqn.SO3.random(cameras, rng=rng)
    truth = dqn.SE3.from_rotation_translation(rotation, rng.normal(scale=2.0 / np.sqrt(3), size=(cameras, 3)))
    u = rng.uniform(0.0, size[0], size=(cameras, landmarks))
    v = rng.uniform(0.0, size[1], size=(cameras, landmarks))
    depth = rng.uniform(2.0, 6.0, size=(cameras, landmarks))
    in_camera = np.stack([(u - centre[0]) / focal * depth, (v - centre[1]) / focal * depth, depth], axis=-1)
    world = truth[:, None] @ in_camera  # camera to world, each camera's landmarks
    pixels = np.stack([u, v], axis=-1) + sigma * rng.normal(size=(cameras, landmarks, 2))
    start = truth.plus(random_twists(rng, cameras, (2.0, 10.0), (0.10, 0.30)))
    return Cameras(world, pixels, sigma, focal, centre, truth.matrix, start.matrix)


# ---------------------------------------------------------------------------------------------------
# Errors, costs, traces


def pose_errors(estimate: np.ndarray, reference: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Rotation angle (degrees) and translation distance (mm) between poses ``(B, 4, 4)``, per pose."""
    angle, distance = dqn.SE3(estimate).distance(dqn.SE3(reference))
    return np.rad2deg(angle), 1e3 * distance


def rigid(poses: np.ndarray) -> np.ndarray:
    """The nearest rigid transforms to ``(B, 4, 4)`` affine maps: the 3x3 block projected onto SO(3)
    (``special_procrustes``), the translation kept."""
    return dqn.se3_from_rotation_translation(dqn.special_procrustes(poses[..., :3, :3]), poses[..., :3, 3])


def orthogonality_defect(poses: np.ndarray) -> float:
    """``max |R^T R - I|`` over the batch: 0 for rotations (to rounding)."""
    r = poses[..., :3, :3]
    return float(np.abs(np.swapaxes(r, -1, -2) @ r - np.eye(3)).max())


def registration_cost(problem: Registration, poses: Any, cauchy: float | None) -> Any:
    """``1/2 sum_i rho(w_i |T s_i - o_i|^2)`` per pose ``(B,)``, for numpy, torch or jax poses
    ``(B, 4, 4)`` (any 3x4 top block, rigid or not): ``rho(s) = s``, or with ``cauchy = c`` the Cauchy
    loss ``c^2 log(1 + s / c^2)``."""
    xp = _namespace(poses)
    model, observed, weights = (xp.asarray(a) for a in (problem.model, problem.observed, problem.weights))
    mapped = xp.matmul(model, xp.swapaxes(poses[..., :3, :3], -1, -2)) + poses[..., None, :3, 3]
    s = weights * xp.sum((mapped - observed) ** 2, axis=-1)
    if cauchy is not None:
        s = cauchy**2 * xp.log1p(s / cauchy**2)
    return 0.5 * xp.sum(s, axis=-1)


def project(problem: Cameras, poses: Any) -> Any:
    """Pixels ``(B, N, 2)`` of the landmarks seen from camera poses ``T_wc`` ``(B, 4, 4)``: the world
    points in the camera frame, ``R^T (X - t)``, then the pinhole. Depths are clamped at 1 cm (every
    start keeps the landmarks well in front; the clamp only keeps a wild step finite)."""
    xp = _namespace(poses)
    x = xp.matmul(xp.asarray(problem.landmarks) - poses[..., None, :3, 3], poses[..., :3, :3])
    z = xp.clip(x[..., 2:], 1e-2, None)
    centre = xp.asarray(problem.centre, dtype=x.dtype)
    return problem.focal * x[..., :2] / z + centre


def reprojection_cost(problem: Cameras, poses: Any) -> Any:
    """``1/2 sum_i |pi(T_wc^-1 X_i) - u_i|^2 / sigma^2`` per camera ``(B,)``."""
    xp = _namespace(poses)
    r = (project(problem, poses) - xp.asarray(problem.pixels)) / problem.sigma
    return 0.5 * xp.sum(r * r, axis=(-1, -2))


def rms_reprojection(problem: Cameras, poses: np.ndarray) -> np.ndarray:
    """Root-mean-square reprojection error per camera (pixels, ``(B,)``)."""
    r = project(problem, poses) - problem.pixels
    return np.sqrt(np.mean(np.sum(r * r, axis=-1), axis=-1))


def _namespace(x: Any) -> Any:
    """The array namespace of ``x``: numpy, torch, or jax.numpy (found through the array's type,
    so that this module imports neither framework)."""
    module = type(x).__module__
    if module.startswith("torch"):
        import torch

        return torch
    if module.startswith("jax"):
        import jax.numpy as jnp

        return jnp
    return np


@dataclass
class Trace:
    """Per step (the start first): each pose's rotation (degrees) and translation (mm) error against
    the truth and against the reference (the optimum, where there is one), the mean cost per pose,
    the orthogonality defect of the raw parameters, and the cumulative time in the steps (seconds)."""

    label: str
    rotation: list[np.ndarray] = field(default_factory=list)
    translation: list[np.ndarray] = field(default_factory=list)
    rotation_to_reference: list[np.ndarray] = field(default_factory=list)
    translation_to_reference: list[np.ndarray] = field(default_factory=list)
    cost: list[float] = field(default_factory=list)
    defect: list[float] = field(default_factory=list)
    seconds: list[float] = field(default_factory=list)
    final: np.ndarray | None = None
    poses: list[np.ndarray] | None = None  # every step's poses, where asked for (``keep=True``)

    def record(
        self,
        poses: np.ndarray,
        truth: np.ndarray,
        reference: np.ndarray | None,
        cost: float,
        elapsed: float,
    ) -> None:
        poses = np.array(poses)  # a copy: a torch parameter's numpy() is a view
        scored = rigid(poses)
        r, t = pose_errors(scored, truth)
        self.rotation.append(r)
        self.translation.append(t)
        if reference is not None:
            r, t = pose_errors(scored, reference)
            self.rotation_to_reference.append(r)
            self.translation_to_reference.append(t)
        self.cost.append(cost)
        self.defect.append(orthogonality_defect(poses))
        self.seconds.append(elapsed)
        self.final = poses
        if self.poses is not None:
            self.poses.append(poses)

    def rescore(self, reference: np.ndarray) -> None:
        """The errors against ``reference`` from the kept poses (for a reference known only at the end)."""
        assert self.poses is not None
        errors = [pose_errors(rigid(p), reference) for p in self.poses]
        self.rotation_to_reference = [r for r, _ in errors]
        self.translation_to_reference = [t for _, t in errors]

    def curve(self, which: str, statistic: Callable[..., Any] = np.median) -> np.ndarray:
        """A statistic over the poses of ``which`` (an attribute holding per-pose errors), per step."""
        return np.array([statistic(x) for x in getattr(self, which)])


# ---------------------------------------------------------------------------------------------------
# Gradient methods in torch


Make = Callable[[Any], tuple[Any, Callable[[], Any]]]  # start poses -> (optimizer, current poses)


def run_torch(
    label: str,
    make: Make,
    cost: Callable[[Any], Any],
    start: np.ndarray,
    truth: np.ndarray,
    reference: np.ndarray | None,
    steps: int,
    lr_decay: float,
    keep: bool = False,
) -> Trace:
    """A gradient loop on the summed cost of every pose: ``make(start)`` gives ``(optimizer,
    to_poses)``; the learning rate decays exponentially to ``lr_decay`` times its start over ``steps``
    steps. ``keep``: store every step's poses as well."""
    import torch

    optimizer, to_poses = make(torch.from_numpy(start.copy()))
    schedule = torch.optim.lr_scheduler.ExponentialLR(optimizer, gamma=lr_decay ** (1.0 / steps))
    trace = Trace(label, poses=[] if keep else None)
    with torch.no_grad():
        trace.record(to_poses().numpy(), truth, reference, float(cost(to_poses()).mean()), 0.0)
    elapsed = 0.0
    for _ in range(steps):
        begin = time.perf_counter()
        optimizer.zero_grad()
        cost(to_poses()).sum().backward()
        optimizer.step()
        schedule.step()
        elapsed += time.perf_counter() - begin
        with torch.no_grad():
            poses = to_poses()
            trace.record(poses.numpy(), truth, reference, float(cost(poses).mean()), elapsed)
    return trace


def riemannian_adam(lr: float) -> Make:
    """``diffquat.torch.optim.RiemannianAdam`` on the poses themselves, ``(B, 4, 4)``, with
    ``manifold="se3"``: each step is ``T <- T exp(d)``, a body twist ``d = (rho, phi)``."""
    import torch

    from diffquat.torch.optim import RiemannianAdam

    def make(start: Any) -> tuple[Any, Callable[[], Any]]:
        poses = torch.nn.Parameter(start)
        return RiemannianAdam([poses], lr=lr, manifold="se3"), lambda: poses

    return make


def adam_quaternion_translation(lr: float) -> Make:
    """``torch.optim.Adam`` on a raw 4-vector and a translation ``(B, 4)``, ``(B, 3)``: the pose is
    ``[[quaternion_to_matrix(q), t], [0, 1]]``, and ``quaternion_to_matrix`` normalises ``q`` (any
    non-zero norm is the same rotation), so every iterate is rigid; Adam itself knows nothing of the
    group (each of the 7 coordinates gets its own step size)."""
    import torch

    import diffquat.torch as dq

    def make(start: Any) -> tuple[Any, Callable[[], Any]]:
        q = torch.nn.Parameter(dq.matrix_to_quaternion(start[..., :3, :3]))
        t = torch.nn.Parameter(start[..., :3, 3].clone())
        optimizer = torch.optim.Adam([q, t], lr=lr)
        return optimizer, lambda: dq.se3_from_rotation_translation(dq.quaternion_to_matrix(q), t)

    return make


def adam_matrix(lr: float, project: bool = False) -> Make:
    """``torch.optim.Adam`` on the raw top 3x4 block ``(B, 3, 4)``, unconstrained: the iterates are
    affine maps, which the least-squares cost pulls off SE(3) (towards the affine fit, whose cost is
    lower than any rigid transform's); they are scored after projection onto SE(3) (:func:`rigid`).
    ``project``: the 3x3 block is projected onto SO(3) (``special_procrustes``) after every step
    instead, so that the iterates are rigid (projected gradient descent; Adam's moments then refer to
    entries that the projection has moved)."""
    import torch

    import diffquat.torch as dq

    class ProjectedAdam(torch.optim.Adam):
        @torch.no_grad()
        def step(self, closure: Any = None) -> Any:
            loss = super().step(closure)
            for group in self.param_groups:
                for block in group["params"]:
                    block[..., :3] = dq.special_procrustes(block[..., :3])
            return loss

    def make(start: Any) -> tuple[Any, Callable[[], Any]]:
        block = torch.nn.Parameter(start[..., :3, :].clone())
        bottom = start[..., 3:, :]
        optimizer = (ProjectedAdam if project else torch.optim.Adam)([block], lr=lr)
        return optimizer, lambda: torch.cat([block, bottom], dim=-2)

    return make


def riemannian_sgd_step_check(problem: Registration, step: float = 0.01) -> dict[str, float]:
    """What the optimiser's step is, checked on the least-squares registration: the tangent gradient
    ``g`` is the derivative of ``delta -> f(T exp(delta))`` at ``delta = 0`` (autograd through
    ``se3_plus``), and one step of ``RiemannianSGD(lr, manifold="se3")`` is ``se3_plus(T, -lr g)``.
    Returns the largest difference between the two poses, the size of the step (for scale), and how
    far the stepped parameters' bottom rows are from ``(0, 0, 0, 1)``."""
    import torch

    import diffquat.torch as dq
    from diffquat.torch.optim import RiemannianSGD

    start = torch.from_numpy(problem.start.copy())
    delta = torch.zeros(start.shape[0], 6, requires_grad=True)
    (g,) = torch.autograd.grad(registration_cost(problem, dq.se3_plus(start, delta), None).sum(), delta)
    lr = step / float(g.norm(dim=-1).max())
    by_hand = dq.se3_plus(start, -lr * g)

    poses = torch.nn.Parameter(start.clone())
    optimizer = RiemannianSGD([poses], lr=lr, manifold="se3")
    registration_cost(problem, poses, None).sum().backward()
    optimizer.step()
    stepped = poses.detach()
    return {
        "lr": lr,
        "max |optimiser's step - se3_plus(T, -lr g)|": float((stepped - by_hand).abs().max()),
        "max |optimiser's step - T|": float((stepped - start).abs().max()),
        "max |bottom row - (0, 0, 0, 1)|": float(
            (stepped[..., 3, :] - torch.tensor([0.0, 0.0, 0.0, 1.0])).abs().max()
        ),
    }


# ---------------------------------------------------------------------------------------------------
# Closed forms and second-order references (numpy)


def closed_form(problem: Registration, weights: np.ndarray | None = None) -> np.ndarray:
    """``fit_rigid_transform`` with the problem's weights ``1 / sigma_i^2`` (or ``weights``): the exact
    minimiser of the weighted least-squares cost."""
    return dqn.fit_rigid_transform(
        problem.model, problem.observed, problem.weights if weights is None else weights
    )


def affine_fit(problem: Registration) -> np.ndarray:
    """The affine map ``[[A, b], [0, 1]]`` ``(B, 4, 4)`` minimising the weighted least-squares cost: the
    optimum of the raw 3x4 parametrisation, by weighted linear least squares (the normal equations of
    ``[s_i, 1] X = o_i``)."""
    x = np.concatenate([problem.model, np.ones_like(problem.model[..., :1])], axis=-1)  # (B, N, 4)
    xt = np.swapaxes(x, -1, -2)
    w = problem.weights[..., None]
    solution = np.linalg.solve(xt @ (w * x), xt @ (w * problem.observed))  # (B, 4, 3)
    bottom = np.broadcast_to(np.array([0.0, 0.0, 0.0, 1.0]), (*solution.shape[:-2], 1, 4))
    return np.concatenate([np.swapaxes(solution, -1, -2), bottom], axis=-2)


def irls(problem: Registration, iterations: int, cauchy: float, reference: np.ndarray | None = None) -> Trace:
    """The Cauchy cost minimised by iteratively reweighted closed forms: each iteration is
    ``fit_rigid_transform`` with the weights ``w_i rho'(s_i) = w_i / (1 + s_i / c^2)`` at the current
    pose (a majorise-minimise step: the Cauchy cost never rises). From the same start as the
    gradient methods."""
    c = cauchy
    trace = Trace(IRLS)
    poses = problem.start
    trace.record(poses, problem.truth, reference, float(registration_cost(problem, poses, c).mean()), 0.0)
    elapsed = 0.0
    for _ in range(iterations):
        begin = time.perf_counter()
        mapped = dqn.SE3(poses)[:, None] @ problem.model
        s = problem.weights * np.sum((mapped - problem.observed) ** 2, axis=-1)
        poses = closed_form(problem, problem.weights / (1.0 + s / c**2))
        elapsed += time.perf_counter() - begin
        trace.record(
            poses, problem.truth, reference, float(registration_cost(problem, poses, c).mean()), elapsed
        )
    return trace


def reprojection_jacobian(problem: Cameras, poses: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Whitened residuals ``(B, 2N)`` and their Jacobian ``(B, 2N, 6)`` with respect to a right
    perturbation of the camera pose, ``T_wc exp(delta)``: the point in the camera frame moves as
    ``x -> exp(-delta) x ~ x - rho - phi x x``, so ``dx/d rho = -I`` and ``dx/d phi = hat(x)``,
    and the pinhole's ``du/dx = f [[1/z, 0, -x/z^2], [0, 1/z, -y/z^2]]``."""
    x = np.einsum("bij,bni->bnj", poses[..., :3, :3], problem.landmarks - poses[..., None, :3, 3])
    z = x[..., 2]
    pinhole = np.zeros((*x.shape[:-1], 2, 3))
    pinhole[..., 0, 0] = pinhole[..., 1, 1] = problem.focal / z
    pinhole[..., :, 2] = -problem.focal * x[..., :2] / z[..., None] ** 2
    hat = dqn.so3_hat(x)
    dx = np.concatenate([np.broadcast_to(-np.eye(3), hat.shape), hat], axis=-1)  # (B, N, 3, 6)
    jacobian = pinhole @ dx / problem.sigma
    residual = (project(problem, poses) - problem.pixels) / problem.sigma
    b = poses.shape[0]
    return residual.reshape(b, -1), jacobian.reshape(b, -1, 6)


def registration_jacobian(problem: Registration) -> np.ndarray:
    """The Jacobian ``(B, 3N, 6)`` of the whitened residuals ``sqrt(w_i) (T s_i - o_i)`` with respect to
    a right perturbation ``T exp(delta)``, in the body frame (``R^T`` times the residual, which
    leaves ``J^T J`` as it is): ``T exp(delta) s ~ T (s + rho + phi x s)``, so ``d/d rho = I`` and
    ``d/d phi = -hat(s)``, times ``sqrt(w_i)``. It does not depend on the pose."""
    hat = dqn.so3_hat(problem.model)
    jacobian = np.concatenate([np.broadcast_to(np.eye(3), hat.shape), -hat], axis=-1)
    jacobian = jacobian * np.sqrt(problem.weights)[..., None, None]
    return jacobian.reshape(jacobian.shape[0], -1, 6)


def conditioning(problem: Registration | Cameras, poses: np.ndarray | None = None) -> dict[str, float]:
    """How hard the problem is for a first-order method, from the Gauss-Newton matrix ``H = J^T J``
    per pose (at ``poses``, the truth by default; in metres and radians): the median condition
    number of ``H``; the median condition number of ``D^-1/2 H D^-1/2`` with ``D`` its diagonal, the
    part that no per-coordinate step size (Adam's, RiemannianAdam's per-part one) can undo; and the
    median correlation between the translation along x and the rotation about y (for a camera: the
    image shifts sideways either way)."""
    if isinstance(problem, Registration):
        jacobian = registration_jacobian(problem)
    else:
        _, jacobian = reprojection_jacobian(problem, problem.truth if poses is None else poses)
    h = np.swapaxes(jacobian, -1, -2) @ jacobian
    d = np.sqrt(np.diagonal(h, axis1=-2, axis2=-1))
    correlation = h / d[..., :, None] / d[..., None, :]

    def condition(m: np.ndarray) -> float:
        e = np.linalg.eigvalsh(m)
        return float(np.median(e[..., -1] / e[..., 0]))

    return {
        "condition number of J^T J": condition(h),
        "after scaling to a unit diagonal": condition(correlation),
        "|correlation| of rho_x and phi_y": float(np.median(np.abs(correlation[..., 0, 4]))),
    }


def gauss_newton(problem: Cameras, iterations: int) -> Trace:
    """Gauss-Newton on the reprojection cost: ``T_wc <- T_wc exp(-(J^T J)^-1 J^T r)`` with the analytic
    Jacobian (:func:`reprojection_jacobian`), each camera's 6x6 system solved apart. From the same
    start as the gradient methods; it converges in a few iterations from these starts, and its last
    iterate is the optimum the gradient methods are measured against."""
    trace = Trace(GAUSS_NEWTON, poses=[])
    poses = problem.start
    trace.record(poses, problem.truth, None, float(reprojection_cost(problem, poses).mean()), 0.0)
    elapsed = 0.0
    for _ in range(iterations):
        begin = time.perf_counter()
        r, j = reprojection_jacobian(problem, poses)
        jt = np.swapaxes(j, -1, -2)
        step = np.linalg.solve(jt @ j, -(jt @ r[..., None]))[..., 0]
        poses = dqn.se3_plus(poses, step)
        elapsed += time.perf_counter() - begin
        trace.record(poses, problem.truth, None, float(reprojection_cost(problem, poses).mean()), elapsed)
    return trace


# ---------------------------------------------------------------------------------------------------
# The same Riemannian Adam in JAX (optax)


def jax_riemannian_adam(
    cost: Callable[[Any], Any],
    start: np.ndarray,
    truth: np.ndarray,
    reference: np.ndarray | None,
    steps: int,
    lr: float,
    lr_decay: float,
    keep: bool = False,
) -> Trace:
    """``diffquat.jax.optim.riemannian_adam(schedule, manifold="se3")`` with ``apply_updates`` (a
    ``(B, 6)`` update of the ``(B, 4, 4)`` leaf is ``se3_plus``), the step jitted, the schedule
    torch's (``lr * decay^(k / steps)``): the same steps as the torch optimiser, up to rounding."""
    import jax
    import jax.numpy as jnp

    from diffquat.jax import optim as dqo

    jax.config.update("jax_enable_x64", True)

    def schedule(count: jax.Array) -> jax.Array:
        return lr * lr_decay ** (count.astype(jnp.float64) / steps)

    optimizer = dqo.riemannian_adam(schedule, manifold="se3")

    @jax.jit
    def step(poses: jax.Array, state: Any) -> tuple[jax.Array, Any]:
        updates, state = optimizer.update(jax.grad(lambda p: cost(p).sum())(poses), state, poses)
        return dqo.apply_updates(poses, updates), state

    poses = jnp.asarray(start)
    state = optimizer.init(poses)
    jax.block_until_ready(step(poses, state))  # compile first: the trace times the steps only
    trace = Trace(RIEMANNIAN_JAX, poses=[] if keep else None)
    trace.record(np.asarray(poses), truth, reference, float(cost(poses).mean()), 0.0)
    elapsed = 0.0
    for _ in range(steps):
        begin = time.perf_counter()
        poses, state = jax.block_until_ready(step(poses, state))
        elapsed += time.perf_counter() - begin
        trace.record(np.asarray(poses), truth, reference, float(cost(poses).mean()), elapsed)
    return trace


# ---------------------------------------------------------------------------------------------------
# The three experiments


def setup() -> None:
    """float64 throughout, one thread (the problems are small: more threads cost more than they give)."""
    import torch

    torch.set_default_dtype(torch.float64)
    torch.set_num_threads(1)


@dataclass
class Experiment:
    """One problem solved every way: the traces by label, the optimum the gradient methods are
    measured against, and reference poses drawn as lines (the closed forms, the optimum)."""

    name: str
    title: str  # the figure's: the problem and its optimum
    problem: Registration | Cameras
    optimum: np.ndarray
    optimum_label: str
    traces: dict[str, Trace]
    references: dict[str, np.ndarray]
    lr: dict[str, float]
    cost: Callable[[Any], Any] = field(repr=False)


def least_squares(settings: Settings, with_jax: bool = True) -> Experiment:
    """Weighted least-squares registration (no outliers): the closed form is the optimum; every
    gradient method's poses are compared with it and with the truth. RiemannianAdam runs in torch and,
    with ``with_jax``, in JAX, each step's poses kept to compare the two."""
    s, lr = settings, settings.lr["least_squares"]
    problem = make_registration(s.objects, s.points, 0.0, s.seed)
    optimum = closed_form(problem)

    def cost(poses: Any) -> Any:
        return registration_cost(problem, poses, None)

    def run(label: str, make: Make, keep: bool = False) -> Trace:
        return run_torch(label, make, cost, problem.start, problem.truth, optimum, s.steps, s.lr_decay, keep)

    traces = {RIEMANNIAN: run(RIEMANNIAN, riemannian_adam(lr[RIEMANNIAN]), keep=with_jax)}
    if with_jax:
        traces[RIEMANNIAN_JAX] = jax_riemannian_adam(
            cost, problem.start, problem.truth, optimum, s.steps, lr[RIEMANNIAN], s.lr_decay, keep=True
        )
    traces[ADAM] = run(ADAM, adam_quaternion_translation(lr[ADAM]))
    traces[ADAM_MATRIX] = run(ADAM_MATRIX, adam_matrix(lr[ADAM_MATRIX]))
    traces[ADAM_PROJECTED] = run(ADAM_PROJECTED, adam_matrix(lr[ADAM_PROJECTED], project=True))
    references = {CLOSED_FORM: optimum}
    return Experiment(
        "least squares",
        "3D-3D, least squares (optimum: closed form)",
        problem,
        optimum,
        CLOSED_FORM,
        traces,
        references,
        lr,
        cost,
    )


def robust(settings: Settings) -> Experiment:
    """Registration with wrong matches under the Cauchy loss: the least-squares closed form is dragged
    by them; the gradient methods and IRLS minimise the Cauchy cost, whose optimum (IRLS run to
    convergence, 200 iterations) they are compared with, as well as with the truth and with the closed
    form on the inliers alone (an oracle: it knows which matches are wrong)."""
    s, lr = settings, settings.lr["robust"]
    problem = make_registration(s.objects, s.points, s.outliers, s.seed + 2)
    optimum = irls(problem, 200, s.cauchy).final
    assert optimum is not None

    def cost(poses: Any) -> Any:
        return registration_cost(problem, poses, s.cauchy)

    def run(label: str, make: Make) -> Trace:
        return run_torch(label, make, cost, problem.start, problem.truth, optimum, s.steps, s.lr_decay)

    traces = {
        RIEMANNIAN: run(RIEMANNIAN, riemannian_adam(lr[RIEMANNIAN])),
        ADAM: run(ADAM, adam_quaternion_translation(lr[ADAM])),
        IRLS: irls(problem, s.irls_iterations, s.cauchy, optimum),
    }
    references = {
        "least-squares closed form (all matches)": closed_form(problem),
        "closed form on the inliers (oracle)": closed_form(problem, problem.weights * ~problem.outlier),
        "Cauchy optimum (IRLS, 200 iterations)": optimum,
    }
    return Experiment(
        "Cauchy",
        f"3D-3D, {s.outliers:.0%} wrong matches, Cauchy (optimum: IRLS)",
        problem,
        optimum,
        "the Cauchy optimum",
        traces,
        references,
        lr,
        cost,
    )


def cameras(settings: Settings) -> Experiment:
    """Camera poses from 2D-3D correspondences: the gradient methods against Gauss-Newton, whose last
    iterate is the optimum (the maximum-likelihood pose for Gaussian pixel noise)."""
    s, lr = settings, settings.lr["cameras"]
    problem = make_cameras(s.cameras, s.landmarks, seed=s.seed + 1)
    newton = gauss_newton(problem, s.gauss_newton_iterations)
    optimum = newton.final
    assert optimum is not None
    newton.rescore(optimum)

    def cost(poses: Any) -> Any:
        return reprojection_cost(problem, poses)

    def run(label: str, make: Make) -> Trace:
        return run_torch(label, make, cost, problem.start, problem.truth, optimum, s.steps, s.lr_decay)

    traces = {
        RIEMANNIAN: run(RIEMANNIAN, riemannian_adam(lr[RIEMANNIAN])),
        ADAM: run(ADAM, adam_quaternion_translation(lr[ADAM])),
        GAUSS_NEWTON: newton,
    }
    references = {"maximum likelihood (Gauss-Newton)": optimum}
    return Experiment(
        "cameras",
        "2D-3D cameras (optimum: Gauss-Newton)",
        problem,
        optimum,
        "Gauss-Newton's optimum",
        traces,
        references,
        lr,
        cost,
    )


def describe(experiment: Experiment) -> str:
    """The problem in a line: sizes, the start's errors, the optimum's errors and cost."""
    p = experiment.problem
    b, n = p.truth.shape[0], (p.model if isinstance(p, Registration) else p.landmarks).shape[1]
    r0, t0 = pose_errors(p.start, p.truth)
    r1, t1 = pose_errors(experiment.optimum, p.truth)
    cost = float(experiment.cost(experiment.optimum).mean())
    line = (
        f"{experiment.name}: {b} poses x {n} correspondences; start {np.median(r0):.1f} deg / "
        f"{np.median(t0):.0f} mm from the truth (median; max {r0.max():.1f} deg / {t0.max():.0f} mm); "
        f"{experiment.optimum_label}: {np.median(r1):.3f} deg / {np.median(t1):.2f} mm (median), "
        f"cost {cost:.2f}"
    )
    if isinstance(p, Registration) and p.outlier.any():
        line += f"; {p.outlier.mean():.0%} wrong matches"
    if isinstance(p, Cameras):
        floor = p.sigma * np.sqrt(2.0 * (1.0 - 3.0 / n))
        rms = np.median(rms_reprojection(p, experiment.optimum))
        line += (
            f"; RMS reprojection error at the optimum {rms:.3f} px "
            f"(median; the noise floor sigma sqrt(2 (1 - 3/N)) = {floor:.3f} px), at the start "
            f"{np.median(rms_reprojection(p, p.start)):.1f} px"
        )
    return line


TOLERANCE = 1e-3  # degrees: "converged" means every pose's rotation is within this of the optimum's


def table(experiment: Experiment) -> list[dict[str, Any]]:
    """Per method: its learning rate, the step at which every pose first came within ``TOLERANCE``
    degrees of the optimum (None: never), the final errors against the truth (median and max over
    the poses) and against the optimum (max), the mean cost, the largest orthogonality defect of the
    parameters over the run, the time per step; then the reference poses' errors and costs."""
    truth, rows = experiment.problem.truth, []
    for label, trace in experiment.traces.items():
        to_optimum = trace.curve("rotation_to_reference", np.max)
        reached = np.nonzero(to_optimum <= TOLERANCE)[0]
        steps = len(trace.rotation) - 1
        rows.append(
            {
                "method": label,
                "lr": experiment.lr.get(RIEMANNIAN if label == RIEMANNIAN_JAX else label),
                "steps": steps,
                f"steps to {TOLERANCE:g} deg": int(reached[0]) if len(reached) else None,
                "rotation (deg)": (float(np.median(trace.rotation[-1])), float(np.max(trace.rotation[-1]))),
                "translation (mm)": (
                    float(np.median(trace.translation[-1])),
                    float(np.max(trace.translation[-1])),
                ),
                "to the optimum (deg, mm)": (
                    float(to_optimum[-1]),
                    float(np.max(trace.translation_to_reference[-1])),
                ),
                "cost": trace.cost[-1],
                "max |R^T R - I|": max(trace.defect),
                "ms per step": 1e3 * trace.seconds[-1] / max(steps, 1),
            }
        )
    for label, poses in experiment.references.items():
        r, t = pose_errors(poses, truth)
        rows.append(
            {
                "method": label,
                "rotation (deg)": (float(np.median(r)), float(np.max(r))),
                "translation (mm)": (float(np.median(t)), float(np.max(t))),
                "cost": float(experiment.cost(poses).mean()),
            }
        )
    return rows


COLUMNS = (
    "method",
    "lr",
    "steps",
    f"steps to {TOLERANCE:g} deg",
    "rotation (deg)",
    "translation (mm)",
    "to the optimum (deg, mm)",
    "cost",
    "max |R^T R - I|",
    "ms per step",
)


def render(rows: list[dict[str, Any]]) -> str:
    """The table as Markdown: errors against the truth as median / max over the poses, against the
    optimum as the max over the poses; a dash where a column does not apply or a target was not
    reached."""

    def cell(x: Any) -> str:
        if x is None:
            return "-"
        if isinstance(x, tuple):
            return " / ".join(cell(v) for v in x)
        if isinstance(x, float):
            return f"{x:.3g}" if 1e-2 <= abs(x) < 1e4 or x == 0 else f"{x:.1e}"
        return str(x)

    head = [c.replace("|", "\\|") for c in COLUMNS]
    head[4], head[5] = "rotation to truth (deg, median / max)", "translation to truth (mm, median / max)"
    lines = ["| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
    lines += ["| " + " | ".join(cell(row.get(c)) for c in COLUMNS) + " |" for row in rows]
    return "\n".join(lines)


# ---------------------------------------------------------------------------------------------------
# The figure


STYLE: dict[str, dict[str, Any]] = {
    RIEMANNIAN: {"color": "C1", "lw": 3.0},
    RIEMANNIAN_JAX: {"color": "k", "ls": "--", "lw": 1.0},
    ADAM: {"color": "C0"},
    ADAM_MATRIX: {"color": "C3", "ls": ":"},
    ADAM_PROJECTED: {"color": "C4", "ls": "-."},
    IRLS: {"color": "C2", "marker": "o", "ms": 3},
    GAUSS_NEWTON: {"color": "C2", "marker": "o", "ms": 3},
}
REFERENCE_STYLE: tuple[dict[str, Any], ...] = (
    {"color": "k", "ls": ":"},
    {"color": "grey", "ls": "--"},
    {"color": "k", "ls": "-", "lw": 0.8},
)


def plot(experiments: list[Experiment], path: Path) -> Path:
    """One column per experiment. Top: the worst pose's rotation error to the optimum (degrees),
    against the step (the iteration for IRLS and Gauss-Newton), the tolerance dotted. Bottom: the
    median rotation error to the truth, the reference poses' as horizontal lines. Both axes
    logarithmic (the start drawn at step 1). Saved as a small PNG."""
    from matplotlib.figure import Figure

    fig = Figure(figsize=(13, 7), dpi=72, layout="constrained")
    axes = fig.subplots(2, len(experiments), squeeze=False)
    for column, experiment in enumerate(experiments):
        top, bottom = axes[0, column], axes[1, column]
        for label, trace in experiment.traces.items():
            style = STYLE.get(label, {})
            steps = np.maximum(np.arange(len(trace.rotation)), 1)
            lr = experiment.lr.get(RIEMANNIAN if label == RIEMANNIAN_JAX else label)
            name = label if lr is None else f"{label}, lr {lr:g}"
            worst = np.maximum(trace.curve("rotation_to_reference", np.max), 1e-12)
            top.plot(steps, worst, label=name, **style)
            bottom.plot(steps, trace.curve("rotation"), **style)
        top.axhline(TOLERANCE, color="grey", lw=0.8, ls=":")
        for (label, poses), style in zip(experiment.references.items(), REFERENCE_STYLE, strict=False):
            median = float(np.median(pose_errors(poses, experiment.problem.truth)[0]))
            bottom.axhline(median, label=f"{label}: {median:.3g} deg", **style)
        top.set_title(f"{experiment.title}: {experiment.problem.truth.shape[0]} poses", fontsize=10)
        top.set(xscale="log", yscale="log", ylim=(1e-9, 3e2))
        bottom.set(xscale="log", yscale="log", xlabel="step (iteration for IRLS, Gauss-Newton)")
        top.legend(fontsize=7, loc="lower left")
        bottom.legend(fontsize=7, loc="upper right")
    axes[0, 0].set_ylabel("worst pose: rotation to the optimum (deg)")
    axes[1, 0].set_ylabel("median rotation error to the truth (deg)")
    fig.savefig(path, pil_kwargs={"optimize": True})
    return path


# ---------------------------------------------------------------------------------------------------
# Everything


def run(settings: Settings | None = None, verbose: bool = True) -> dict[str, Any]:
    """The three experiments, their tables, the figure. Returns the experiments by name and the
    figure's path."""
    settings = settings or (SMALL if small_mode() else FULL)
    say = print if verbose else (lambda *a, **k: None)
    setup()
    experiments = [least_squares(settings), robust(settings), cameras(settings)]
    for experiment in experiments:
        say(describe(experiment))
        say(render(table(experiment)) + "\n")
    path = plot(experiments, figure_dir() / "pose_refinement.png")
    say(f"figure saved to {os.path.relpath(path)}")
    return {"experiments": {e.name: e for e in experiments}, "figure": path}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.parse_args()
    print(f"size: {'small' if small_mode() else 'full'}")
    run()


if __name__ == "__main__":
    main()
