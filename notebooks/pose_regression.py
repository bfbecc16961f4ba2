"""Regress an orientation with a small network, and compare the rotation heads of diffquat.

The task (synthetic, nothing downloaded): a fixed cloud of 3D points is rotated by a uniformly random
rotation and slightly perturbed; the network sees the rotated points, flattened, and must output the
rotation. One MLP body, one head per representation (``diffquat.torch.nn.RotationHead``), the same
budget (steps, batch, learning rate, seed) and the same geodesic loss for every head. The test set is
fixed; errors are reported as angles in degrees.

The training step is a plain function of (model, optimizer, batch) in torch and of (params, optimizer
state, batch) in JAX: it runs unchanged under DistributedDataParallel and under jax sharding.

Run:  python notebooks/pose_regression.py        (DIFFQUAT_SMALL=1 for a quick small-size run)
"""

from __future__ import annotations

import argparse
import os
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
from _sizes import figure_dir, small_mode

import diffquat.numpy as dqn

HEADS = ("quaternion", "axis_angle", "euler", "6d", "9d", "10d")


@dataclass(frozen=True)
class Config:
    n_points: int = 24  # points in the cloud; the input has 3 * n_points features
    noise: float = 0.01  # std of the perturbation of each rotated point
    hidden: int = 256
    steps: int = 3000
    batch: int = 128
    lr: float = 1e-3
    n_test: int = 10000
    seed: int = 0


FULL = Config()
SMALL = Config(hidden=32, steps=60, batch=32, n_test=256)


def config_from_env() -> Config:
    """The full-size run, or with ``DIFFQUAT_SMALL=1`` the small one the test suite executes."""
    return SMALL if small_mode() else FULL


def point_cloud(config: Config) -> np.ndarray:
    """The fixed object: ``n_points`` points, seeded, in the unit ball, with no symmetry."""
    rng = np.random.default_rng(1234)
    return rng.uniform(-1.0, 1.0, size=(config.n_points, 3))


def make_batch(
    config: Config, n: int, rng: np.random.Generator, cloud: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """``n`` samples: features ``(n, 3 * n_points)`` (float32) and true rotations ``(n, 3, 3)``."""
    rotations = dqn.quaternion_to_matrix(dqn.random_quaternions(n, rng=rng))
    seen = np.einsum("nij,pj->npi", rotations, cloud) + config.noise * rng.normal(size=(n, len(cloud), 3))
    return seen.reshape(n, -1).astype(np.float32), rotations.astype(np.float32)


def rotation_angle_deg(rotations: np.ndarray) -> np.ndarray:
    """Angle of each rotation from the identity, in degrees."""
    eye = np.broadcast_to(np.eye(3), rotations.shape)
    return np.rad2deg(dqn.matrix_geodesic_distance(eye, rotations.astype(np.float64)))


# --------------------------------------------------------------------------------------------------
# PyTorch


def torch_model(config: Config, representation: str) -> Any:
    """MLP body and a ``RotationHead``, initialised from ``config.seed``."""
    import torch
    from torch import nn

    from diffquat.torch.nn import RotationHead

    torch.manual_seed(config.seed)
    return nn.Sequential(
        nn.Linear(3 * config.n_points, config.hidden),
        nn.ReLU(),
        nn.Linear(config.hidden, config.hidden),
        nn.ReLU(),
        RotationHead(config.hidden, representation),
    )


def torch_loss(model: Any, features: Any, rotations: Any) -> Any:
    """Mean geodesic distance (radians) between predicted and true rotations."""
    import diffquat.torch as dq

    return dq.matrix_geodesic_distance(model(features), rotations).mean()


def torch_train_step(model: Any, optimizer: Any, features: Any, rotations: Any) -> Any:
    """One optimisation step; returns the loss before the step (a detached tensor). ``model`` may be
    a ``DistributedDataParallel`` wrapper: DDP averages the gradients over processes."""
    optimizer.zero_grad()
    loss = torch_loss(model, features, rotations)
    loss.backward()
    optimizer.step()
    return loss.detach()


def train_torch(config: Config, representation: str, progress: bool = True) -> tuple[Any, list[float]]:
    """Train one head; returns the model and the loss per step (radians)."""
    import torch
    from tqdm import tqdm

    model = torch_model(config, representation)
    optimizer = torch.optim.Adam(model.parameters(), lr=config.lr)
    scheduler = torch.optim.lr_scheduler.CosineAnnealingLR(optimizer, T_max=config.steps)
    rng, cloud = np.random.default_rng(config.seed), point_cloud(config)
    losses = []
    bar = tqdm(range(config.steps), desc=f"{representation:>10s}", disable=not progress, mininterval=2.0)
    for _ in bar:
        features, rotations = make_batch(config, config.batch, rng, cloud)
        losses.append(
            float(torch_train_step(model, optimizer, torch.from_numpy(features), torch.from_numpy(rotations)))
        )
        scheduler.step()
        bar.set_postfix(loss=f"{np.rad2deg(losses[-1]):7.2f} deg", refresh=False)
    return model, losses


def evaluate_torch(config: Config, model: Any) -> tuple[np.ndarray, np.ndarray]:
    """Angle error (degrees) on the fixed test set, and the true rotation angle of each test sample."""
    import torch

    import diffquat.torch as dq

    features, rotations = make_batch(
        config, config.n_test, np.random.default_rng(10_000), point_cloud(config)
    )
    with torch.no_grad():
        predicted = model(torch.from_numpy(features))
        errors = dq.matrix_geodesic_distance(predicted.double(), torch.from_numpy(rotations).double())
    return np.rad2deg(errors.numpy()), rotation_angle_deg(rotations)


# --------------------------------------------------------------------------------------------------
# JAX: the same network as pure functions of a parameter pytree


def jax_init(config: Config, representation: str, key: Any) -> dict[str, Any]:
    import jax
    import jax.numpy as jnp

    from diffquat.jax import nn as dqnn

    k1, k2, k3 = jax.random.split(key, 3)

    def dense(k: Any, n_in: int, n_out: int) -> dict[str, Any]:
        bound = 1.0 / np.sqrt(n_in)
        kw, kb = jax.random.split(k)
        return {
            "w": jax.random.uniform(kw, (n_in, n_out), jnp.float32, -bound, bound),
            "b": jax.random.uniform(kb, (n_out,), jnp.float32, -bound, bound),
        }

    return {
        "l1": dense(k1, 3 * config.n_points, config.hidden),
        "l2": dense(k2, config.hidden, config.hidden),
        "head": dqnn.init_rotation_head(k3, config.hidden, representation, dtype=jnp.float32),
    }


def jax_forward(params: dict[str, Any], features: Any, representation: str) -> Any:
    import jax

    from diffquat.jax import nn as dqnn

    h = features
    for layer in ("l1", "l2"):
        h = jax.nn.relu(h @ params[layer]["w"] + params[layer]["b"][None, :])
    return dqnn.rotation_head(params["head"], h, representation)


def jax_loss(params: dict[str, Any], features: Any, rotations: Any, representation: str) -> Any:
    import diffquat.jax as dq

    return dq.matrix_geodesic_distance(jax_forward(params, features, representation), rotations).mean()


def make_jax_train_step(representation: str, optimizer: Any) -> Any:
    """``step(params, opt_state, features, rotations) -> (params, opt_state, loss)``, jitted. Under
    sharding, jit partitions it by the shardings of its arguments; the code does not change."""
    import jax
    import optax

    @jax.jit
    def step(params: Any, opt_state: Any, features: Any, rotations: Any) -> tuple[Any, Any, Any]:
        loss, grads = jax.value_and_grad(jax_loss)(params, features, rotations, representation)
        # optax raises an int32 step count to float powers: fine in jax's standard promotion, refused
        # by the strict promotion the test suite sets (and diffquat itself obeys).
        with jax.numpy_dtype_promotion("standard"):
            updates, opt_state = optimizer.update(grads, opt_state, params)
        return optax.apply_updates(params, updates), opt_state, loss

    return step


def train_jax(config: Config, representation: str, progress: bool = True) -> tuple[Any, list[float]]:
    import jax
    import optax
    from tqdm import tqdm

    optimizer = optax.adam(optax.cosine_decay_schedule(config.lr, config.steps))
    params = jax_init(config, representation, jax.random.key(config.seed))
    opt_state = optimizer.init(params)
    step = make_jax_train_step(representation, optimizer)
    rng, cloud = np.random.default_rng(config.seed), point_cloud(config)
    losses = []
    bar = tqdm(range(config.steps), desc=f"jax {representation:>6s}", disable=not progress, mininterval=2.0)
    for _ in bar:
        features, rotations = make_batch(config, config.batch, rng, cloud)
        params, opt_state, loss = step(params, opt_state, features, rotations)
        losses.append(float(loss))
    return params, losses


def evaluate_jax(config: Config, params: Any, representation: str) -> tuple[np.ndarray, np.ndarray]:
    import diffquat.jax as dq

    features, rotations = make_batch(
        config, config.n_test, np.random.default_rng(10_000), point_cloud(config)
    )
    predicted = np.asarray(jax_forward(params, features, representation), dtype=np.float64)
    errors = dq.matrix_geodesic_distance(predicted, rotations.astype(np.float64))
    return np.rad2deg(np.asarray(errors)), rotation_angle_deg(rotations)


# --------------------------------------------------------------------------------------------------
# The comparison


@dataclass
class Result:
    representation: str
    errors: np.ndarray  # degrees, per test sample
    true_angles: np.ndarray  # degrees, per test sample
    losses: list[float]  # radians, per step
    seconds: float


def compare_heads(config: Config, heads: tuple[str, ...] = HEADS, progress: bool = True) -> list[Result]:
    results = []
    for representation in heads:
        start = time.perf_counter()
        model, losses = train_torch(config, representation, progress)
        seconds = time.perf_counter() - start
        errors, angles = evaluate_torch(config, model)
        results.append(Result(representation, errors, angles, losses, seconds))
    return results


def table(results: list[Result]) -> str:
    """Markdown table of test angle errors per head, best mean first."""
    lines = [
        "| head | mean (deg) | median (deg) | p99 (deg) | max (deg) | train time (s) |",
        "|---|---:|---:|---:|---:|---:|",
    ]
    for r in sorted(results, key=lambda r: float(np.mean(r.errors))):
        e = r.errors
        lines.append(
            f"| {r.representation} | {np.mean(e):.2f} | {np.median(e):.2f} | {np.percentile(e, 99):.2f} "
            f"| {np.max(e):.2f} | {r.seconds:.1f} |"
        )
    return "\n".join(lines)


def plot(results: list[Result], path: Path) -> Path:
    """Left: test error against the true rotation angle (mean per 10-degree bin). Right: training loss."""
    from matplotlib.figure import Figure

    fig = Figure(figsize=(10, 3.8), dpi=80, layout="constrained")
    ax_err, ax_loss = fig.subplots(1, 2)
    edges = np.linspace(0.0, 180.0, 19)
    centres = 0.5 * (edges[1:] + edges[:-1])
    for r in results:
        which = np.clip(np.digitize(r.true_angles, edges) - 1, 0, len(centres) - 1)
        means = [r.errors[which == b].mean() if np.any(which == b) else np.nan for b in range(len(centres))]
        ax_err.plot(centres, means, marker="o", ms=3, label=r.representation)
        window = max(1, len(r.losses) // 50)
        smooth = np.convolve(np.rad2deg(r.losses), np.ones(window) / window, mode="valid")
        ax_loss.plot(np.arange(len(smooth)) + window, smooth, label=r.representation)
    ax_err.set(xlabel="true rotation angle (deg)", ylabel="mean test error (deg)", yscale="log")
    ax_err.set_title("test error against the true angle")
    ax_loss.set(xlabel="step", ylabel="training loss (deg, moving mean)", yscale="log")
    ax_loss.set_title("geodesic training loss")
    ax_err.legend(fontsize=8, ncols=2)
    fig.savefig(path)
    return path


def main() -> None:
    import torch

    # The tensors here are tiny: more threads cost more in synchronisation than they give.
    torch.set_num_threads(1)
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.parse_args()
    config = config_from_env()
    results = compare_heads(config)
    print(table(results))
    print(f"figure saved to {os.path.relpath(plot(results, figure_dir() / 'pose_regression.png'))}")


if __name__ == "__main__":
    main()
