"""Fit an orientation by gradient descent through ``quaternion_to_matrix``, in PyTorch and in JAX.

Wahba's problem: given 3D points and their rotated, noisy images, find the rotation. The unknown is an
unconstrained 4-vector (no normalisation, no projection): ``quaternion_to_matrix`` is scale invariant,
so plain Adam on the raw vector works. Both backends fit the same data from the same start.

Run:  python notebooks/fit_orientation.py [--steps N]
"""

from __future__ import annotations

import argparse
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

import diffquat.numpy as dqn


@dataclass(frozen=True)
class Problem:
    points: np.ndarray  # (n, 3) in the local frame
    targets: np.ndarray  # (n, 3): true_rotation @ points + noise, in the global frame
    true_quaternion: np.ndarray  # (4,) w, x, y, z
    start: np.ndarray  # (4,) the initial guess, not normalised


def make_problem(
    n_points: int = 500, noise: float = 0.01, seed: int = 0, start_angle_deg: float | None = None
) -> Problem:
    """Random points, a random true rotation, noisy rotated images, and a starting guess: the
    identity, or a rotation ``start_angle_deg`` away from the truth."""
    rng = np.random.default_rng(seed)
    truth = dqn.random_quaternions(rng=rng)
    points = rng.normal(size=(n_points, 3))
    targets = points @ dqn.quaternion_to_matrix(truth).T + noise * rng.normal(size=(n_points, 3))
    if start_angle_deg is None:
        start = np.array([1.0, 0.0, 0.0, 0.0])
    else:  # the truth composed with a rotation of the requested angle about a random axis
        axis = rng.normal(size=3)
        axis /= np.linalg.norm(axis)
        half = np.deg2rad(start_angle_deg) / 2
        offset = dqn.quaternion_to_matrix(np.concatenate([[np.cos(half)], np.sin(half) * axis]))
        start = dqn.matrix_to_quaternion(offset @ dqn.quaternion_to_matrix(truth))
    return Problem(points, targets, truth, start)


def angle_error_deg(q: np.ndarray, truth: np.ndarray) -> float:
    """Rotation angle between two orientations, in degrees (blind to the sign of q)."""
    rel = dqn.matrix_to_quaternion(dqn.quaternion_to_matrix(q).T @ dqn.quaternion_to_matrix(truth))
    return float(np.rad2deg(2 * np.arctan2(np.linalg.norm(rel[..., 1:], axis=-1), np.abs(rel[..., 0]))))


Callback = Callable[[int, float, np.ndarray], None]


def fit_torch(
    problem: Problem, steps: int = 300, lr: float = 0.05, callback: Callback | None = None
) -> np.ndarray:
    import torch

    import diffquat.torch as dq

    points = torch.tensor(problem.points)
    targets = torch.tensor(problem.targets)
    q = torch.tensor(problem.start, requires_grad=True)
    optimizer = torch.optim.Adam([q], lr=lr)
    for step in range(steps + 1):
        optimizer.zero_grad()
        loss = ((points @ dq.quaternion_to_matrix(q).T - targets) ** 2).sum(-1).mean()
        if callback is not None:
            callback(step, float(loss.detach()), q.detach().numpy().copy())
        if step == steps:
            break
        loss.backward()
        optimizer.step()
    return q.detach().numpy()


def fit_jax(
    problem: Problem, steps: int = 300, lr: float = 0.05, callback: Callback | None = None
) -> np.ndarray:
    import jax
    import jax.numpy as jnp

    import diffquat.jax as dq

    points, targets = jnp.asarray(problem.points), jnp.asarray(problem.targets)

    def loss_fn(q: jax.Array) -> jax.Array:
        return jnp.mean(jnp.sum((points @ dq.quaternion_to_matrix(q).T - targets) ** 2, axis=-1))

    # Adam, written out (the same update rule and defaults as torch.optim.Adam).
    b1, b2, eps = 0.9, 0.999, 1e-8

    @jax.jit
    def step_fn(q: jax.Array, m: jax.Array, v: jax.Array, t: jax.Array) -> tuple[jax.Array, ...]:
        loss, g = jax.value_and_grad(loss_fn)(q)
        m = b1 * m + (1 - b1) * g
        v = b2 * v + (1 - b2) * g * g
        m_hat, v_hat = m / (1 - b1**t), v / (1 - b2**t)
        return q - lr * m_hat / (jnp.sqrt(v_hat) + eps), m, v, loss

    q = jnp.asarray(problem.start)
    m, v = jnp.zeros_like(q), jnp.zeros_like(q)
    for step in range(steps + 1):
        if step == steps:
            if callback is not None:
                callback(step, float(loss_fn(q)), np.asarray(q))
            break
        new_q, m, v, loss = step_fn(q, m, v, jnp.asarray(step + 1, dtype=q.dtype))
        if callback is not None:
            callback(step, float(loss), np.asarray(q))
        q = new_q
    return np.asarray(q)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--steps", type=int, default=300)
    parser.add_argument("--print-every", type=int, default=50)
    args = parser.parse_args()

    import jax

    jax.config.update("jax_enable_x64", True)  # the same float64 arithmetic as the torch run

    problem = make_problem()
    print(f"true rotation (w, x, y, z): {np.round(problem.true_quaternion, 4)}")
    print(
        f"start: identity, {angle_error_deg(problem.start, problem.true_quaternion):.2f} deg from the truth\n"
    )
    finals = {}
    for name, fit in (("torch", fit_torch), ("jax", fit_jax)):

        def report(step: int, loss: float, q: np.ndarray, name: str = name) -> None:
            if step % args.print_every == 0 or step == args.steps:
                err = angle_error_deg(q, problem.true_quaternion)
                print(f"[{name:5s}] step {step:4d}  loss {loss:.6f}  angle error {err:8.4f} deg")

        q = fit(problem, steps=args.steps, callback=report)
        finals[name] = angle_error_deg(q, problem.true_quaternion)
        print()
    for name, err in finals.items():
        print(f"final angle error ({name}): {err:.4f} deg against the known rotation")
    worst = max(finals.values())
    if worst > 1.0:
        raise SystemExit(f"the fit did not converge: {worst:.3f} deg error")


if __name__ == "__main__":
    main()
