"""Multiple rotation averaging on a synthetic pose graph, solved four ways: Adam on raw quaternions,
Riemannian Adam on SO(3), Levenberg-Marquardt with the analytic Jacobians, and the peers where they
are installed (geoopt's Riemannian Adam, pypose's Levenberg-Marquardt).

The problem: ``n`` unknown rotations ``R_i`` and, on the edges of a random graph, relative
measurements ``R_ij = R_i^T R_j exp(noise)``, a tenth of them outliers (uniformly random rotations).
The estimate minimises a robust (Cauchy) loss of the geodesic residual of every edge,

    cost = 1/2 sum_ij rho(|r_ij|^2),  r_ij = log((R_i R_ij)^T R_j),  rho(s) = c^2 log(1 + s / c^2),

which an outlier's huge residual barely moves. Every method starts from the same spectral
initialisation (the top eigenvectors of the measurement matrix, as in Martinec and Pajdla) and is
scored by its mean angle to the truth after the best global rotation (the gauge: ``R_i -> G R_i``
leaves every ``R_i^T R_j`` as it is).

Run:  python notebooks/orientation_on_manifold.py    (DIFFQUAT_SMALL=1: the small test-suite size)
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
# The problem


@dataclass(frozen=True)
class Problem:
    """A pose graph: ``n`` rotations, ``m`` edges ``(i, j)`` with measurements ``R_ij ~ R_i^T R_j``."""

    truth: np.ndarray  # (n, 3, 3)
    edges: np.ndarray  # (m, 2) int64: i, j
    measured: np.ndarray  # (m, 3, 3)
    outlier: np.ndarray  # (m,) bool: which measurements are random
    scale: float  # c of the Cauchy loss, radians
    start: np.ndarray = field(repr=False)  # (n, 3, 3): the spectral initialisation

    @property
    def n(self) -> int:
        return len(self.truth)


def make_problem(
    n: int = 1000,
    degree: int = 10,
    noise_deg: float = 3.0,
    outliers: float = 0.1,
    scale_deg: float = 6.0,
    seed: int = 0,
) -> Problem:
    """A random connected graph (a ring plus random chords, ``degree`` edges per node on average),
    measurements with isotropic Gaussian noise of ``noise_deg`` degrees per axis, a fraction
    ``outliers`` of them replaced by uniformly random rotations; Cauchy scale ``scale_deg``."""
    rng = np.random.default_rng(seed)
    truth = dqn.quaternion_to_matrix(dqn.random_quaternions((n,), rng=rng))
    ring = np.stack([np.arange(n), (np.arange(n) + 1) % n], axis=-1)
    chords = rng.integers(0, n, size=(n * degree // 2 - n, 2))
    edges = np.concatenate([ring, chords[chords[:, 0] != chords[:, 1]]])
    i, j = edges[:, 0], edges[:, 1]
    noise = np.deg2rad(noise_deg) * rng.normal(size=(len(edges), 3))
    measured = dqn.so3_plus(np.swapaxes(truth[i], -1, -2) @ truth[j], noise)
    outlier = rng.random(len(edges)) < outliers
    measured[outlier] = dqn.quaternion_to_matrix(dqn.random_quaternions((int(outlier.sum()),), rng=rng))
    start = spectral_initialisation(n, edges, measured)
    return Problem(truth, edges, measured, outlier, float(np.deg2rad(scale_deg)), start)


def spectral_initialisation(n: int, edges: np.ndarray, measured: np.ndarray) -> np.ndarray:
    """Rotations from the top three eigenvectors of the symmetric ``3n x 3n`` matrix whose block
    ``(i, j)`` is ``R_ij`` (and ``(j, i)`` its transpose): with ``X`` the stacked ``R_i^T``, that
    matrix is ``X X^T`` on the edges, so the eigenvectors span ``X``'s columns up to a 3x3 mixing
    that the gauge absorbs. Each block is projected onto SO(3) (``special_procrustes``)."""
    from scipy.sparse import coo_matrix
    from scipy.sparse.linalg import eigsh

    i, j = edges[:, 0], edges[:, 1]
    a, b = np.meshgrid(np.arange(3), np.arange(3), indexing="ij")
    rows = np.concatenate([(3 * i[:, None, None] + a).ravel(), (3 * j[:, None, None] + a).ravel()])
    cols = np.concatenate([(3 * j[:, None, None] + b).ravel(), (3 * i[:, None, None] + b).ravel()])
    values = np.concatenate([measured.ravel(), np.swapaxes(measured, -1, -2).ravel()])
    matrix = coo_matrix((values, (rows, cols)), shape=(3 * n, 3 * n)).tocsr()
    _, vectors = eigsh(matrix, k=3, which="LA", v0=np.ones(3 * n))
    blocks = vectors.reshape(n, 3, 3)  # block i ~ R_i^T Q
    if np.sum(np.linalg.det(blocks)) < 0:  # the eigenvectors' own sign: one column flipped
        blocks[..., 2] *= -1
    return np.swapaxes(dqn.special_procrustes(blocks), -1, -2)


def residuals(problem: Problem, rotations: np.ndarray) -> np.ndarray:
    """``r_ij = log((R_i R_ij)^T R_j)`` ``(m, 3)``: zero when the measurement holds exactly."""
    i, j = problem.edges[:, 0], problem.edges[:, 1]
    return dqn.so3_minus(rotations[j], rotations[i] @ problem.measured)


def cauchy(squared: Any, scale: float) -> Any:
    """``rho(s) = c^2 log(1 + s / c^2)`` (any backend's arrays: ``log1p`` is a method of none, so the
    caller's namespace is found through the array's type)."""
    c2 = scale * scale
    return c2 * _namespace(squared).log1p(squared / c2)


def _namespace(x: Any) -> Any:
    module = type(x).__module__
    if module.startswith("torch"):
        import torch

        return torch
    if module.startswith("jax"):
        import jax.numpy as jnp

        return jnp
    return np


def cost(problem: Problem, rotations: np.ndarray) -> float:
    """``1/2 sum rho(|r_ij|^2)``, the objective every method minimises."""
    r = residuals(problem, rotations)
    return 0.5 * float(np.sum(cauchy(np.sum(r * r, axis=-1), problem.scale)))


def align(problem: Problem, rotations: np.ndarray) -> np.ndarray:
    """The estimate moved by the gauge rotation ``G`` that brings it closest to the truth:
    ``G = argmin sum |G R_i - T_i|^2 = special_procrustes(sum T_i R_i^T)``."""
    g = dqn.special_procrustes(np.sum(problem.truth @ np.swapaxes(rotations, -1, -2), axis=0))
    return g @ rotations


def error_deg(problem: Problem, rotations: np.ndarray) -> float:
    """Mean angle (degrees) between the aligned estimate and the truth."""
    aligned = align(problem, rotations)
    return float(np.rad2deg(np.mean(dqn.matrix_geodesic_distance(aligned, problem.truth))))


# ---------------------------------------------------------------------------------------------------
# Gradient methods in torch: the loss, the optimisers, the loop


@dataclass
class Trace:
    """Error to the truth (degrees) and the cost after each step, and the time spent in the steps
    (seconds, cumulative: the evaluation of the error is not counted)."""

    label: str
    error: list[float] = field(default_factory=list)
    cost: list[float] = field(default_factory=list)
    seconds: list[float] = field(default_factory=list)
    skipped: str | None = None
    final: np.ndarray | None = None  # (n, 3, 3): the last estimate

    def record(self, problem: Problem, rotations: np.ndarray, elapsed: float) -> None:
        self.error.append(error_deg(problem, rotations))
        self.cost.append(cost(problem, rotations))
        self.seconds.append(elapsed)
        self.final = np.array(rotations)  # a copy: a torch parameter's numpy() is a view

    def first_within(self, optimum: float, fraction: float) -> int | None:
        """The first step whose error is within ``fraction`` of the optimum's (None: none is)."""
        return next((k for k, e in enumerate(self.error) if abs(e - optimum) <= fraction * optimum), None)

    def time_to(self, optimum: float, fraction: float) -> float | None:
        """Seconds of steps until the error is first within ``fraction`` of the optimum's (None:
        never)."""
        k = self.first_within(optimum, fraction)
        return None if k is None else self.seconds[k]


def torch_cost(problem: Problem) -> Callable[[Any], Any]:
    """The cost of rotation matrices ``(n, 3, 3)`` as a differentiable torch function: the residual's
    norm is the geodesic distance between ``R_i R_ij`` and ``R_j`` (``matrix_geodesic_distance``,
    exact and with a finite gradient at 0)."""
    import torch

    import diffquat.torch as dq

    i, j = torch.from_numpy(problem.edges[:, 0]), torch.from_numpy(problem.edges[:, 1])
    measured = torch.from_numpy(problem.measured)

    def f(rotations: Any) -> Any:
        angle = dq.matrix_geodesic_distance(rotations[i] @ measured, rotations[j])
        return 0.5 * cauchy(angle * angle, problem.scale).sum()

    return f


Make = Callable[[Any], tuple[Any, Any, Callable[[], Any]]]  # start -> (parameter, optimizer, matrices)


def run_torch(
    problem: Problem,
    label: str,
    make: Make,
    steps: int,
    lr_decay: float,
) -> Trace:
    """A gradient loop: ``make(start)`` gives ``(parameter, optimizer, to_matrices)``; the learning
    rate decays exponentially to ``lr_decay`` times its start over ``steps`` steps (a schedule that
    every gradient method here shares)."""
    import torch

    f = torch_cost(problem)
    _, optimizer, to_matrices = make(torch.from_numpy(problem.start.copy()))
    schedule = torch.optim.lr_scheduler.ExponentialLR(optimizer, gamma=lr_decay ** (1.0 / steps))
    trace = Trace(label)
    trace.record(problem, problem.start, 0.0)
    elapsed = 0.0
    for _ in range(steps):
        start = time.perf_counter()
        optimizer.zero_grad()
        f(to_matrices()).backward()
        optimizer.step()
        schedule.step()
        elapsed += time.perf_counter() - start
        with torch.no_grad():
            trace.record(problem, to_matrices().numpy(), elapsed)
    return trace


def adam_raw_quaternions(lr: float) -> Make:
    """(a) ``torch.optim.Adam`` on unconstrained 4-vectors, mapped by ``quaternion_to_matrix``."""
    import torch

    import diffquat.torch as dq

    def make(start: Any) -> tuple[Any, Any, Callable[[], Any]]:
        q = torch.nn.Parameter(dq.matrix_to_quaternion(start))
        return q, torch.optim.Adam([q], lr=lr), lambda: dq.quaternion_to_matrix(q)

    return make


def riemannian_adam(lr: float, quaternions: bool = False) -> Make:
    """(b) ``diffquat.torch.optim.RiemannianAdam`` on rotation matrices ``(n, 3, 3)`` (or unit
    quaternions ``(n, 4)`` mapped by ``quaternion_to_matrix``)."""
    import torch

    import diffquat.torch as dq
    from diffquat.torch.optim import RiemannianAdam

    def make(start: Any) -> tuple[Any, Any, Callable[[], Any]]:
        if quaternions:
            q = torch.nn.Parameter(dq.matrix_to_quaternion(start))
            return q, RiemannianAdam([q], lr=lr), lambda: dq.quaternion_to_matrix(q)
        rotations = torch.nn.Parameter(start)
        return rotations, RiemannianAdam([rotations], lr=lr), lambda: rotations

    return make


def geoopt_adam(lr: float) -> Make:
    """geoopt's ``RiemannianAdam`` on its canonical Stiefel manifold of 3x3 matrices (square: the
    orthogonal group, whose component of the start is SO(3)); its metric is ours (the canonical
    inner product of ``R hat(w)`` is ``|w|^2``), its retraction the Cayley transform."""
    import geoopt

    def make(start: Any) -> tuple[Any, Any, Callable[[], Any]]:
        rotations = geoopt.ManifoldParameter(start, manifold=geoopt.Stiefel())
        return rotations, geoopt.optim.RiemannianAdam([rotations], lr=lr), lambda: rotations

    return make


# ---------------------------------------------------------------------------------------------------
# Levenberg-Marquardt with the analytic Jacobians (numpy + scipy.sparse)


def jacobians(problem: Problem, rotations: np.ndarray, r: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``dr_ij / d delta_i`` and ``dr_ij / d delta_j`` ``(m, 3, 3)`` for right perturbations
    ``R_k -> R_k exp(delta_k)``. With ``E = (R_i R_ij)^T R_j`` and ``r = log E``:
    ``R_j exp(d)`` gives ``log(E exp(d)) = r + J_r^-1(r) d``, and ``R_i exp(d)`` gives
    ``log(exp(-R_ij^T d) E) = r - J_l^-1(r) R_ij^T d``, and ``J_l^-1(r) = J_r^-1(r) E^T``, so
    ``dr/d delta_i = -J_r^-1(r) R_j^T R_i``."""
    i, j = problem.edges[:, 0], problem.edges[:, 1]
    right_inverse = dqn.so3_right_jacobian_inverse(r)
    return -right_inverse @ np.swapaxes(rotations[j], -1, -2) @ rotations[i], right_inverse


def _block_indices(a: np.ndarray, b: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Row and column indices of the 3x3 blocks ``(a_k, b_k)`` of a ``3n x 3n`` matrix, ``(m, 3, 3)``."""
    rows = 3 * a[:, None, None] + np.arange(3)[None, :, None]
    cols = 3 * b[:, None, None] + np.arange(3)[None, None, :]
    return np.broadcast_to(rows, (len(a), 3, 3)), np.broadcast_to(cols, (len(a), 3, 3))


def levenberg_marquardt(
    problem: Problem, iterations: int = 30, damping: float = 1e-3, label: str = "Levenberg-Marquardt"
) -> Trace:
    """(c) Levenberg-Marquardt on the Cauchy cost by iteratively reweighted least squares: each
    iteration weighs edge ``e`` by ``rho'(|r_e|^2) = 1 / (1 + |r_e|^2 / c^2)``, solves the sparse
    normal equations ``(H + lambda diag(H)) delta = -b`` with ``H = sum w J^T J``, ``b = sum w J^T r``
    (rotation 0 held fixed: the gauge), and keeps the step ``R_k exp(delta_k)`` if the cost drops
    (``lambda / 3``), else retries with ``lambda * 10``.

    The normal equations are solved by conjugate gradients preconditioned with the inverses of the
    3x3 diagonal blocks, to a relative residual of 1e-10 (a few dozen products with the sparse ``H``,
    milliseconds): the graph is random, so a sparse Cholesky factor fills in (scipy's SuperLU took
    3 s per solve at n = 1000, a dense Cholesky as long)."""
    from scipy.sparse import coo_matrix
    from scipy.sparse.linalg import LinearOperator, cg

    n, i, j = problem.n, problem.edges[:, 0], problem.edges[:, 1]
    trace = Trace(label)
    rotations = problem.start.copy()
    trace.record(problem, rotations, 0.0)
    elapsed = 0.0
    start = time.perf_counter()
    r = residuals(problem, rotations)
    current = 0.5 * float(np.sum(cauchy(np.sum(r * r, axis=-1), problem.scale)))
    for _ in range(iterations):
        weight = 1.0 / (1.0 + np.sum(r * r, axis=-1) / problem.scale**2)
        ji, jj = jacobians(problem, rotations, r)
        wji, wjj = weight[:, None, None] * ji, weight[:, None, None] * jj
        jit, jjt = np.swapaxes(wji, -1, -2), np.swapaxes(wjj, -1, -2)
        hii, hjj = jit @ ji, jjt @ jj
        blocks = [(i, i, hii), (j, j, hjj), (i, j, jit @ jj), (j, i, jjt @ ji)]
        rows, cols, values = zip(*((*_block_indices(a, b), v) for a, b, v in blocks), strict=True)
        hessian = coo_matrix(
            (
                np.concatenate([v.ravel() for v in values]),
                (np.concatenate([x.ravel() for x in rows]), np.concatenate([x.ravel() for x in cols])),
            ),
            shape=(3 * n, 3 * n),
        ).tocsr()[3:, 3:]  # fmt: skip  (rotation 0 fixed)
        gradient = np.zeros((n, 3))
        np.add.at(gradient, i, (jit @ r[..., None])[..., 0])
        np.add.at(gradient, j, (jjt @ r[..., None])[..., 0])
        diagonal_blocks = np.zeros((n, 3, 3))
        np.add.at(diagonal_blocks, i, hii)
        np.add.at(diagonal_blocks, j, hjj)
        diagonal_blocks = diagonal_blocks[1:]
        diagonal = np.diagonal(diagonal_blocks, axis1=-2, axis2=-1).ravel()
        while True:
            scaled = damping * coo_matrix((diagonal, (np.arange(3 * n - 3),) * 2), shape=hessian.shape)
            system = hessian + scaled.tocsr()
            blocks = diagonal_blocks + damping * (diagonal.reshape(-1, 3)[:, :, None] * np.eye(3))
            inverse = np.linalg.inv(blocks)
            preconditioner = LinearOperator(
                system.shape, matvec=lambda v, inverse=inverse: (inverse @ v.reshape(-1, 3, 1)).ravel()
            )
            solution, _ = cg(system, -gradient.ravel()[3:], rtol=1e-10, M=preconditioner, maxiter=500)
            delta = np.concatenate([np.zeros(3), solution]).reshape(n, 3)
            candidate = dqn.so3_plus(rotations, delta)
            r_new = residuals(problem, candidate)
            new = 0.5 * float(np.sum(cauchy(np.sum(r_new * r_new, axis=-1), problem.scale)))
            if new <= current or damping > 1e8:
                break
            damping *= 10.0
        rotations, r, current, damping = candidate, r_new, new, max(damping / 3.0, 1e-9)
        elapsed += time.perf_counter() - start
        trace.record(problem, rotations, elapsed)
        start = time.perf_counter()
    return trace


# ---------------------------------------------------------------------------------------------------
# pypose (where installed): its Levenberg-Marquardt with its Cauchy kernel


def pypose_lm(problem: Problem, iterations: int = 10) -> Trace:
    """pypose's ``optim.LM`` on ``pp.SO3`` parameters, with its Cauchy kernel (``rho(s) = c^2 log(1 +
    s / c^2)``, the same) and a Cholesky solver. Its Jacobian is dense (``3m x 3n``, by autograd;
    pypose's sparse mode needs a backend that does not install here)."""
    import pypose as pp
    import torch

    import diffquat.torch as dq

    class Graph(torch.nn.Module):
        def __init__(self, start: torch.Tensor) -> None:
            super().__init__()
            xyzw = dq.matrix_to_quaternion(start, scalar_first=False)
            self.rotations = pp.Parameter(pp.SO3(xyzw))

        def forward(self, edges: torch.Tensor, measured: Any) -> torch.Tensor:
            i, j = edges[:, 0], edges[:, 1]
            return ((self.rotations[i] * measured).Inv() * self.rotations[j]).Log().tensor()

    edges = torch.from_numpy(problem.edges)
    measured = pp.SO3(dq.matrix_to_quaternion(torch.from_numpy(problem.measured), scalar_first=False))
    graph = Graph(torch.from_numpy(problem.start))
    kernel = pp.optim.kernel.Cauchy(delta=problem.scale)
    optimizer = pp.optim.LM(graph, solver=pp.optim.solver.Cholesky(), kernel=kernel)
    trace = Trace("pypose LM (dense)")
    trace.record(problem, problem.start, 0.0)
    elapsed = 0.0

    def matrices() -> np.ndarray:
        return dq.quaternion_to_matrix(graph.rotations.tensor().detach(), scalar_first=False).numpy()

    for _ in range(iterations):
        start = time.perf_counter()
        optimizer.step(input=(edges, measured))
        elapsed += time.perf_counter() - start
        trace.record(problem, matrices(), elapsed)
    return trace


# ---------------------------------------------------------------------------------------------------
# The same Riemannian Adam in JAX (optax)


def jax_riemannian_adam(problem: Problem, steps: int, lr: float, lr_decay: float) -> Trace:
    """(b) again with ``diffquat.jax.optim.riemannian_adam`` (optax) and the same schedule, the step
    jitted: the same updates as the torch optimiser (up to rounding)."""
    import jax
    import jax.numpy as jnp
    import optax

    import diffquat.jax as dq
    from diffquat.jax import optim as dqo

    jax.config.update("jax_enable_x64", True)
    i, j = jnp.asarray(problem.edges[:, 0]), jnp.asarray(problem.edges[:, 1])
    measured = jnp.asarray(problem.measured)

    def f(rotations: jax.Array) -> jax.Array:
        angle = dq.matrix_geodesic_distance(rotations[i] @ measured, rotations[j])
        return 0.5 * jnp.sum(cauchy(angle * angle, problem.scale))

    schedule = optax.exponential_decay(lr, transition_steps=steps, decay_rate=lr_decay)
    optimizer = dqo.riemannian_adam(schedule)

    @jax.jit
    def step(rotations: jax.Array, state: optax.OptState) -> tuple[jax.Array, optax.OptState]:
        # optax's schedule raises an int32 count to a float power: standard promotion for it.
        with jax.numpy_dtype_promotion("standard"):
            updates, state = optimizer.update(jax.grad(f)(rotations), state, rotations)
        return dqo.apply_updates(rotations, updates), state

    rotations = jnp.asarray(problem.start)
    state = optimizer.init(rotations)
    jax.block_until_ready(step(rotations, state))  # compile first: the trace times steps only
    trace = Trace("RiemannianAdam (diffquat, jax)")
    trace.record(problem, problem.start, 0.0)
    elapsed = 0.0
    for _ in range(steps):
        start = time.perf_counter()
        rotations, state = jax.block_until_ready(step(rotations, state))
        elapsed += time.perf_counter() - start
        trace.record(problem, np.asarray(rotations), elapsed)
    return trace


# ---------------------------------------------------------------------------------------------------
# Everything, and the figure


@dataclass(frozen=True)
class Settings:
    """Sizes and step counts, and the learning rate of each Adam, decayed exponentially to
    ``lr_decay`` times its start over ``steps``: each Adam's best, by the steps it took to come within
    0.1% of the optimum's error on the full problem, over 0.005, 0.01, 0.02, 0.03, 0.04, 0.06, 0.08
    and 0.16 (raw Adam: 0.02, 50 steps; RiemannianAdam: 0.03, 51 steps; the others 52 to 114 or not
    reached). geoopt's Cayley step turns a rotation by ``2 atan(lr |d|)``, about twice ours: at half
    our learning rate it takes our steps, and 0.015 was its best too (its 0.03: 52 steps)."""

    n: int
    steps: int
    lm_iterations: int
    pypose_n: int  # pypose's dense Levenberg-Marquardt runs on a problem of this size
    pypose_iterations: int
    degree: int = 10
    lr: dict[str, float] = field(default_factory=lambda: {"adam": 0.02, "riemannian": 0.03, "geoopt": 0.015})
    lr_decay: float = 0.01


FULL = Settings(n=1000, steps=200, lm_iterations=12, pypose_n=200, pypose_iterations=8)
SMALL = Settings(n=60, steps=40, lm_iterations=6, pypose_n=20, pypose_iterations=2)

ADAM = "Adam, raw quaternions"
RIEMANNIAN = "RiemannianAdam (diffquat)"
RIEMANNIAN_JAX = "RiemannianAdam (diffquat, jax)"
LM = "Levenberg-Marquardt (diffquat Jacobians)"
GEOOPT = "geoopt RiemannianAdam"
PYPOSE = "pypose LM (dense)"


def solvers(settings: Settings) -> dict[str, Callable[[Problem], Trace]]:
    """The methods of the main comparison, by label (pypose's has its own, smaller problem: see
    :func:`run_pypose`). A peer that is not installed raises ImportError; :func:`solve_all` records it
    as skipped."""
    s, lr = settings, settings.lr

    def gradient(label: str, make: Callable[[], Make]) -> Callable[[Problem], Trace]:
        return lambda p: run_torch(p, label, make(), s.steps, s.lr_decay)

    return {
        ADAM: gradient(ADAM, lambda: adam_raw_quaternions(lr["adam"])),
        RIEMANNIAN: gradient(RIEMANNIAN, lambda: riemannian_adam(lr["riemannian"])),
        RIEMANNIAN_JAX: lambda p: jax_riemannian_adam(p, s.steps, lr["riemannian"], s.lr_decay),
        LM: lambda p: levenberg_marquardt(p, s.lm_iterations),
        GEOOPT: gradient(GEOOPT, lambda: geoopt_adam(lr["geoopt"])),
    }


def solve_all(
    problem: Problem, methods: dict[str, Callable[[Problem], Trace]], say: Callable[..., None] = print
) -> dict[str, Trace]:
    """Run each method on the problem; a method whose library is missing is recorded as skipped."""
    traces: dict[str, Trace] = {}
    for label, solve in methods.items():
        try:
            traces[label] = solve(problem)
        except ImportError as error:
            traces[label] = Trace(label, skipped=f"{error.name} is not installed")
            say(f"{label}: skipped ({error.name} is not installed)")
    return traces


def setup() -> None:
    """One thread for every method (scipy's sparse solver uses one), float64 throughout."""
    import torch

    torch.set_default_dtype(torch.float64)
    torch.set_num_threads(1)


def describe(problem: Problem) -> str:
    return (
        f"{problem.n} rotations, {len(problem.edges)} measurements ({int(problem.outlier.sum())} outliers); "
        f"spectral start {error_deg(problem, problem.start):.3f} deg from the truth"
    )


def run(settings: Settings | None = None, verbose: bool = True) -> dict[str, Any]:
    """The main comparison: build the problem, run every method, print the table, save the figure.
    Returns the problem, the traces, the table's rows and the figure's path."""
    settings = settings or (SMALL if small_mode() else FULL)
    say = print if verbose else (lambda *a, **k: None)
    setup()
    problem = make_problem(n=settings.n, degree=settings.degree)
    say(describe(problem))
    best_error = optimum(problem).error[-1]
    say(f"the optimum (Levenberg-Marquardt, 40 iterations) is {best_error:.4f} deg from the truth")
    traces = solve_all(problem, solvers(settings), say)
    rows = table(traces, best_error)
    say(render(rows))
    path = plot(traces, best_error, figure_dir() / "orientation_on_manifold.png", problem)
    say(f"\nfigure saved to {os.path.relpath(path)}")
    return {"problem": problem, "traces": traces, "rows": rows, "figure": path, "optimum": best_error}


def run_pypose(settings: Settings | None = None, verbose: bool = True) -> dict[str, Any]:
    """pypose's Levenberg-Marquardt beside diffquat's on a smaller problem of the same kind
    (``settings.pypose_n`` rotations): pypose forms the dense ``3m x 3n`` Jacobian by autograd, which
    at n = 1000 took 178 s and 13 GB for one iteration here. Prints the table; returns the traces."""
    settings = settings or (SMALL if small_mode() else FULL)
    say = print if verbose else (lambda *a, **k: None)
    setup()
    problem = make_problem(n=settings.pypose_n, degree=settings.degree)
    say(describe(problem))
    methods = {
        LM: lambda p: levenberg_marquardt(p, settings.pypose_iterations),
        PYPOSE: lambda p: pypose_lm(p, settings.pypose_iterations),
    }
    best_error = optimum(problem).error[-1]
    traces = solve_all(problem, methods, say)
    rows = table(traces, best_error)
    say(render(rows))
    return {"problem": problem, "traces": traces, "rows": rows, "optimum": best_error}


def optimum(problem: Problem, iterations: int = 40) -> Trace:
    """The reference optimum: Levenberg-Marquardt run to convergence (40 iterations; it converges
    quadratically and stops moving after about 15). Its last error is the one every method is
    measured against."""
    return levenberg_marquardt(problem, iterations, label="optimum")


def table(traces: dict[str, Trace], best_error: float) -> list[dict[str, Any]]:
    """Per method: steps, final error and cost, time per step, and the time to come within 1% and
    0.1% of the optimum's error ``best_error``."""
    rows = []
    for label, trace in traces.items():
        if trace.skipped:
            rows.append({"method": label, "skipped": trace.skipped})
            continue
        steps = len(trace.error) - 1
        rows.append(
            {
                "method": label,
                "steps": steps,
                "final error (deg)": trace.error[-1],
                "final cost": trace.cost[-1],
                "ms per step": 1e3 * trace.seconds[-1] / max(steps, 1),
                "s to 1%": trace.time_to(best_error, 0.01),
                "s to 0.1%": trace.time_to(best_error, 0.001),
            }
        )
    return rows


def render(rows: list[dict[str, Any]]) -> str:
    """The table as Markdown (a skipped method says why; a target not reached is a dash)."""

    def cell(x: Any) -> str:
        if x is None:
            return "-"
        if isinstance(x, float):
            return f"{x:.4g}"
        return str(x)

    head = ["method", "steps", "final error (deg)", "final cost", "ms per step", "s to 1%", "s to 0.1%"]
    lines = ["| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
    for row in rows:
        if "skipped" in row:
            lines.append(f"| {row['method']} | skipped: {row['skipped']} |" + " |" * (len(head) - 2))
        else:
            lines.append("| " + " | ".join(cell(row[h]) for h in head) + " |")
    return "\n".join(lines)


STYLE = {
    ADAM: {"color": "C0"},
    RIEMANNIAN: {"color": "C1", "lw": 3.0, "alpha": 0.5},
    RIEMANNIAN_JAX: {"color": "C1", "ls": "--", "lw": 1.0},
    LM: {"color": "C2", "marker": "o", "ms": 3},
    GEOOPT: {"color": "C3", "ls": ":"},
    PYPOSE: {"color": "C4", "marker": "s", "ms": 3},
}


def plot(traces: dict[str, Trace], best_error: float, path: Path, problem: Problem) -> Path:
    """Each method's mean error to the truth minus the optimum's, against the step (left) and against
    time (right), the 1% and 0.1% targets dotted. The error axis is logarithmic down to 1e-4 degrees
    and linear below (``symlog``), so that an error that crosses the optimum's (it can: the optimum
    minimises the cost, not the error) crosses zero smoothly. Saved as a small PNG."""
    from matplotlib.figure import Figure

    fig = Figure(figsize=(12, 4), dpi=80, layout="constrained")
    by_step, by_time = fig.subplots(1, 2, sharey=True)
    for label, trace in traces.items():
        if trace.skipped:
            continue
        style = STYLE.get(label, {})
        excess = np.array(trace.error) - best_error
        # The start drawn at step 1 and at 1 ms: the step and time axes are logarithmic.
        by_step.plot(np.maximum(np.arange(len(excess)), 1), excess, label=label, **style)
        by_time.plot(np.maximum(trace.seconds, 1e-3), excess, label=label, **style)
    for ax in (by_step, by_time):
        for fraction in (0.01, 0.001):
            ax.axhline(fraction * best_error, color="grey", lw=0.8, ls=":")
        ax.axhline(0.0, color="grey", lw=0.8)
        ax.set(xscale="log", ylabel="mean error - the optimum's (deg)")
        ax.set_yscale("symlog", linthresh=1e-4)
        ax.set_ylim(-0.01 * best_error, None)  # below the optimum's error: to 1% of it
    by_step.set(xlabel="step (iteration for Levenberg-Marquardt; the start at 1)")
    by_time.set(xlabel="seconds in the steps (1 CPU thread; the start at 1 ms)")
    by_step.set_title(
        f"{problem.n} rotations, {len(problem.edges)} edges: the optimum's error {best_error:.3f} deg"
    )
    by_time.set_title("dotted: 1% and 0.1% of the optimum's error")
    by_time.legend(fontsize=8)
    fig.savefig(path)
    return path


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.parse_args()
    print(f"size: {'small' if small_mode() else 'full'}")
    run()
    run_pypose()


if __name__ == "__main__":
    main()
