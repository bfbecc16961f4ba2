"""Fit an orientation by gradient descent through ``quaternion_to_matrix``, in PyTorch and in JAX.

Wahba's problem: given 3D points and their rotated, noisy images, find the rotation. The unknown is an
unconstrained 4-vector (no normalisation, no projection): ``quaternion_to_matrix`` is scale invariant,
so plain Adam on the raw vector works. Both backends fit the same data from the same start (torch with
``torch.optim.Adam``, JAX with ``optax.adam``), and both end where the closed form (``fit_rotation``)
and scipy's ``align_vectors`` put the optimum. Every function here is batched: a batch of independent
problems is fitted at once, exactly as if each were fitted alone (Adam's update is elementwise, and
the loss is a sum of one term per problem).

Run:  python notebooks/fit_orientation.py [--steps N]    (DIFFQUAT_SMALL=1: the small test-suite size)
"""

from __future__ import annotations

import argparse
import os
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
from _sizes import figure_dir, small_mode

import diffquat.numpy as dqn


@dataclass(frozen=True)
class Problem:
    """One problem, or a batch of independent ones (leading dimensions ``...``)."""

    points: np.ndarray  # (..., n, 3) in the local frame
    targets: np.ndarray  # (..., n, 3): true_rotation @ points + noise, in the global frame
    true_quaternion: np.ndarray  # (..., 4) w, x, y, z
    start: np.ndarray  # (..., 4) the initial guess, not normalised


def make_problem(
    n_points: int = 500,
    noise: float = 0.01,
    seed: int = 0,
    start_angle_deg: float | None = None,
    batch: tuple[int, ...] = (),
) -> Problem:
    """Random points, a random true rotation, noisy rotated images, and a starting guess: the
    identity, or a rotation ``start_angle_deg`` away from the truth (about a random axis)."""
    rng = np.random.default_rng(seed)
    truth = dqn.random_quaternions(batch, rng=rng)
    points = rng.normal(size=(*batch, n_points, 3))
    rotation = dqn.quaternion_to_matrix(truth)
    targets = np.einsum("...ij,...pj->...pi", rotation, points) + noise * rng.normal(size=points.shape)
    if start_angle_deg is None:
        start = np.broadcast_to([1.0, 0.0, 0.0, 0.0], truth.shape).copy()
    else:  # the truth composed with a rotation of the requested angle about a random axis
        axis = rng.normal(size=(*batch, 3))
        axis /= np.linalg.norm(axis, axis=-1, keepdims=True)
        half = np.deg2rad(start_angle_deg) / 2
        offset = np.concatenate([np.full((*batch, 1), np.cos(half)), np.sin(half) * axis], axis=-1)
        start = dqn.matrix_to_quaternion(dqn.quaternion_to_matrix(offset) @ rotation)
    return Problem(points, targets, truth, start)


def angle_error_deg(q: np.ndarray, truth: np.ndarray) -> np.ndarray:
    """Rotation angle between two orientations, in degrees (blind to the sign and norm of q)."""
    return np.rad2deg(dqn.quaternion_geodesic_distance(q, truth))


def closed_form(problem: Problem) -> np.ndarray:
    """The optimum in closed form: diffquat's ``fit_rotation`` (Kabsch/Davenport), ``(..., 3, 3)``."""
    return dqn.fit_rotation(problem.points, problem.targets)


def scipy_align_vectors(problem: Problem) -> np.ndarray:
    """The optimum by scipy, one problem at a time. ``align_vectors(a, b)`` returns the rotation C that
    minimises sum |a - C b|^2, so ``a`` is the targets and ``b`` the points."""
    from scipy.spatial.transform import Rotation

    batch = problem.points.shape[:-2]
    points = problem.points.reshape(-1, *problem.points.shape[-2:])
    targets = problem.targets.reshape(points.shape)
    out = [Rotation.align_vectors(t, p)[0].as_matrix() for p, t in zip(points, targets, strict=True)]
    return np.asarray(out).reshape(*batch, 3, 3)


def angle_to_matrix_deg(q: np.ndarray, rotation: np.ndarray) -> np.ndarray:
    """Angle (degrees) between the rotation of quaternion ``q`` and a rotation matrix."""
    return np.rad2deg(dqn.matrix_geodesic_distance(dqn.quaternion_to_matrix(q), rotation))


# A callback sees the step, the loss of each problem before that step, and the current estimate.
Callback = Callable[[int, np.ndarray, np.ndarray], None]


def _progress(steps: int, desc: str, progress: bool) -> Any:
    from tqdm import tqdm

    return tqdm(total=steps, desc=desc, disable=not progress, mininterval=1.0)


def fit_torch(
    problem: Problem,
    steps: int = 300,
    lr: float = 0.05,
    callback: Callback | None = None,
    progress: bool = False,
) -> np.ndarray:
    """Adam on the raw 4-vector(s); returns the final estimate ``(..., 4)`` (not normalised)."""
    import torch

    import diffquat.torch as dq

    points = torch.tensor(problem.points)
    targets = torch.tensor(problem.targets)
    q = torch.tensor(problem.start, requires_grad=True)
    optimizer = torch.optim.Adam([q], lr=lr)
    with _progress(steps, "torch", progress) as bar:
        for step in range(steps + 1):
            optimizer.zero_grad()
            residual = points @ dq.quaternion_to_matrix(q).transpose(-1, -2) - targets
            per_problem = (residual**2).sum(-1).mean(-1)
            if callback is not None:
                callback(step, per_problem.detach().numpy().copy(), q.detach().numpy().copy())
            if step == steps:
                break
            per_problem.sum().backward()
            optimizer.step()
            bar.update()
    return q.detach().numpy()


def fit_jax(
    problem: Problem,
    steps: int = 300,
    lr: float = 0.05,
    callback: Callback | None = None,
    progress: bool = False,
) -> np.ndarray:
    """The same fit with ``optax.adam`` (the same update rule and defaults as ``torch.optim.Adam``)."""
    import jax
    import jax.numpy as jnp
    import optax

    import diffquat.jax as dq

    points, targets = jnp.asarray(problem.points), jnp.asarray(problem.targets)

    def per_problem(q: jax.Array) -> jax.Array:
        residual = points @ jnp.swapaxes(dq.quaternion_to_matrix(q), -1, -2) - targets
        return jnp.mean(jnp.sum(residual**2, axis=-1), axis=-1)

    optimizer = optax.adam(lr)

    @jax.jit
    def step_fn(q: jax.Array, state: optax.OptState) -> tuple[jax.Array, optax.OptState, jax.Array]:
        losses, pullback = jax.vjp(per_problem, q)
        (g,) = pullback(jnp.ones_like(losses))  # the gradient of the sum over problems
        # optax raises an int32 step count to float powers: fine in jax's standard promotion, refused
        # by the strict promotion the test suite sets (and diffquat itself obeys).
        with jax.numpy_dtype_promotion("standard"):
            updates, state = optimizer.update(g, state, q)
        return optax.apply_updates(q, updates), state, losses

    q = jnp.asarray(problem.start)
    state = optimizer.init(q)
    with _progress(steps, "jax", progress) as bar:
        for step in range(steps):
            new_q, state, losses = step_fn(q, state)
            if callback is not None:
                callback(step, np.asarray(losses), np.asarray(q))
            q = new_q
            bar.update()
    if callback is not None:
        callback(steps, np.asarray(per_problem(q)), np.asarray(q))
    return np.asarray(q)


@dataclass
class History:
    """Loss and angle error to the closed-form optimum (degrees) at every step, per problem."""

    loss: list[np.ndarray]
    error_deg: list[np.ndarray]


def fit_with_history(
    fit: Callable[..., np.ndarray], problem: Problem, steps: int, progress: bool = True
) -> tuple[np.ndarray, History]:
    optimum = closed_form(problem)
    history = History([], [])

    def record(step: int, loss: np.ndarray, q: np.ndarray) -> None:
        history.loss.append(loss)
        history.error_deg.append(angle_to_matrix_deg(q, optimum))

    q = fit(problem, steps=steps, callback=record, progress=progress)
    return q, history


def plot(runs: dict[str, History], batch_errors: np.ndarray, path: Path, title_batch: str = "batch") -> Path:
    """Loss and angle error against step for every run (torch solid, jax dashed, one colour per
    start), and the final errors of the batch of independent problems. Saved as a small PNG."""
    from matplotlib.figure import Figure

    fig = Figure(figsize=(12, 3.6), dpi=80, layout="constrained")
    ax_loss, ax_err, ax_batch = fig.subplots(1, 3)
    colours: dict[str, str] = {}
    for label, history in runs.items():
        start, backend = label.rsplit(" ", 1)
        colour = colours.setdefault(start, f"C{len(colours)}")
        # torch wide and pale, jax thin and dashed on top: where they agree, both stay visible.
        style = {"lw": 3.0, "alpha": 0.45} if backend == "torch" else {"lw": 1.0, "ls": "--"}
        steps = np.arange(len(history.loss))
        ax_loss.plot(steps, [float(np.mean(x)) for x in history.loss], color=colour, label=label, **style)
        # A floor of 1e-9 degrees: an exact 0 has no place on a log axis.
        errors = [max(float(np.max(x)), 1e-9) for x in history.error_deg]
        ax_err.plot(steps, errors, color=colour, label=label, **style)
    ax_loss.set(xlabel="step", ylabel="loss (mean squared residual)", yscale="log", title="loss")
    ax_err.axhline(0.01, color="grey", lw=0.8, ls=":")
    ax_err.set(xlabel="step", ylabel="angle to the closed form (deg)", yscale="log")
    ax_err.set_title("angle error to the optimum (dotted: 0.01 deg)")
    ax_err.legend(fontsize=8)
    ax_batch.hist(np.log10(np.maximum(batch_errors.ravel(), 1e-12)), bins=30, color="C2")
    ax_batch.set(xlabel="log10 final angle to the closed form (deg)", ylabel="problems", title=title_batch)
    fig.savefig(path)
    return path


def run(
    steps: int = 300, batch: int = 1000, progress: bool = True, verbose: bool = True
) -> dict[str, object]:
    """The whole example: identity start and 179-degree start, on torch and jax, then a batch of
    independent problems. Returns the numbers the notebook shows; raises if a fit misses the optimum."""
    import jax

    jax.config.update("jax_enable_x64", True)  # the same float64 arithmetic as the torch run
    say = print if verbose else (lambda *a, **k: None)
    problems = {
        "identity start": make_problem(),
        "179 deg start": make_problem(seed=1, start_angle_deg=179.0),
    }
    runs: dict[str, History] = {}
    finals: dict[str, np.ndarray] = {}
    for start, problem in problems.items():
        start_error = float(angle_error_deg(problem.start, problem.true_quaternion))
        say(f"{start}: {start_error:.2f} deg from the truth")
        for backend, fit in (("torch", fit_torch), ("jax", fit_jax)):
            finals[f"{start} {backend}"], runs[f"{start} {backend}"] = fit_with_history(
                fit, problem, steps, progress
            )
    summary: dict[str, object] = {"runs": runs}
    rows = []
    for label, q in finals.items():
        problem = problems[label.rsplit(" ", 1)[0]]
        rows.append(
            (
                label,
                float(angle_error_deg(q, problem.true_quaternion)),
                float(angle_to_matrix_deg(q, closed_form(problem))),
                float(angle_to_matrix_deg(q, scipy_align_vectors(problem))),
            )
        )
    summary["final"] = rows
    say(f"\n{'run':<22s} {'to truth (deg)':>15s} {'to fit_rotation':>16s} {'to align_vectors':>17s}")
    for label, truth, closed, scipy in rows:
        say(f"{label:<22s} {truth:15.6f} {closed:16.2e} {scipy:17.2e}")

    batched = make_problem(n_points=100, seed=2, start_angle_deg=179.0, batch=(batch,))
    q_batch = fit_torch(batched, steps=steps, progress=progress)
    batch_errors = angle_to_matrix_deg(q_batch, closed_form(batched))
    summary["batch_errors"] = batch_errors
    say(
        f"\nbatch of {batch} independent problems, each started 179 deg away, fitted at once (torch): "
        f"angle to fit_rotation max {batch_errors.max():.2e} deg, median {np.median(batch_errors):.2e} deg"
    )
    path = plot(runs, batch_errors, figure_dir() / "fit_orientation.png", f"{batch} problems fitted at once")
    summary["figure"] = path
    say(f"\nfigure saved to {os.path.relpath(path)}")
    worst = max(max(r[2] for r in rows), float(batch_errors.max()))
    if worst > 0.01:
        raise SystemExit(f"gradient descent ended {worst:.3g} deg from the closed form (more than 0.01 deg)")
    return summary


def main() -> None:
    import torch

    # The tensors here are tiny: more threads cost more in synchronisation than they give.
    torch.set_num_threads(1)
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--steps", type=int, default=300)
    parser.add_argument("--batch", type=int, default=16 if small_mode() else 1000)
    args = parser.parse_args()
    run(steps=args.steps, batch=args.batch)


if __name__ == "__main__":
    main()
