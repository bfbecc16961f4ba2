"""Benchmark of the rotation means against scipy's ``Rotation.mean``: ``python -m benchmarks.means
[--quick] [--out DIR]`` writes ``means.json`` and ``MEANS.md`` in DIR (default: benchmarks/).

Workload: B sets of N rotations each (clusters of up to 0.5 rad around random centres, random positive
weights), float32, one mean per set. Functions: ``rotation_mean`` with each method (``"chordal"``,
``"geodesic"``, ``"geodesic_l1"``) from matrices, and ``quaternion_mean`` from quaternions. Methods:
diffquat torch eager, diffquat ``jax.jit``, diffquat numpy and, for the chordal means (the only mean
scipy has), scipy's ``Rotation.mean`` over the same sets (``axis=-1``: vectorised over B). Forward, and
forward + backward (the gradient of a weighted sum of the mean's entries with respect to the samples
and the weights) for torch and jax. Times are medians over interleaved blocks (``run.time_all``); the
first call (jax compiles there) is reported apart.
"""

from __future__ import annotations

import argparse
import os
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np
from scipy.spatial.transform import Rotation

from .run import _fmt_time, _sync, finish, machine, time_all

FULL_SIZES = ((1, 16), (1, 1024), (64, 16), (1024, 16), (16384, 8))
QUICK_SIZES = ((8, 16),)  # one size: each jax function compiles once per size and mode
FUNCTIONS = (
    "rotation_mean[chordal]",
    "rotation_mean[geodesic]",
    "rotation_mean[geodesic_l1]",
    "quaternion_mean",
)


def workload(sets: int, n: int, seed: int = 0) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Matrices (sets, n, 3, 3), scalar-first quaternions (sets, n, 4) and weights (sets, n), float32."""
    rng = np.random.default_rng(seed)
    centres = Rotation.random(sets, random_state=seed).as_quat()
    v = rng.normal(size=(sets, n, 3))
    v *= rng.uniform(0.0, 0.5, size=(sets, n, 1)) / np.linalg.norm(v, axis=-1, keepdims=True)
    samples = Rotation.from_quat(np.repeat(centres[:, None], n, 1)) * Rotation.from_rotvec(v)
    weights = rng.uniform(0.2, 2.0, size=(sets, n))
    f32 = np.float32
    return (
        samples.as_matrix().astype(f32),
        samples.as_quat(scalar_first=True).astype(f32),
        weights.astype(f32),
    )


def _methods(function: str) -> dict[str, tuple[str, Callable[..., Any]]]:
    """label -> (family, fn(samples, weights)) for one function."""
    import jax

    import diffquat.jax as dqj
    import diffquat.numpy as dqn
    import diffquat.torch as dqt

    if function == "quaternion_mean":
        out: dict[str, tuple[str, Callable[..., Any]]] = {
            "diffquat torch eager": ("torch", dqt.quaternion_mean),
            "diffquat jax.jit": ("jax", jax.jit(dqj.quaternion_mean)),
            "diffquat numpy": ("numpy", dqn.quaternion_mean),
        }
        out["scipy Rotation.mean"] = (
            "numpy",
            lambda q, w: Rotation.from_quat(q, scalar_first=True).mean(weights=w, axis=-1).as_quat(),
        )
        return out
    method = function.split("[")[1][:-1]

    def bind(module: Any) -> Callable[..., Any]:
        return lambda m, w: module.rotation_mean(m, w, method=method)

    out = {
        "diffquat torch eager": ("torch", bind(dqt)),
        "diffquat jax.jit": ("jax", jax.jit(bind(dqj))),
        "diffquat numpy": ("numpy", bind(dqn)),
    }
    if method == "chordal":
        out["scipy Rotation.mean"] = (
            "numpy",
            lambda m, w: Rotation.from_matrix(m).mean(weights=w, axis=-1).as_matrix(),
        )
    return out


def _call(family: str, fn: Callable[..., Any], x: np.ndarray, w: np.ndarray, backward: bool) -> Any:
    """A zero-argument callable: the forward, or the forward and the gradient of ``sum(out * c)``."""
    if family == "numpy":
        return None if backward else (lambda: fn(x, w))
    if family == "torch":
        import torch

        xt, wt = torch.from_numpy(x), torch.from_numpy(w)
        if not backward:

            def forward() -> Any:
                with torch.no_grad():
                    return fn(xt, wt)

            return forward
        leaves = (xt.clone().requires_grad_(True), wt.clone().requires_grad_(True))
        cot = torch.ones_like(fn(xt, wt))
        return lambda: torch.autograd.grad(fn(*leaves), leaves, cot)
    import jax
    import jax.numpy as jnp

    xj, wj = jnp.asarray(x), jnp.asarray(w)
    if not backward:
        return lambda: _sync(fn(xj, wj))
    cot = jnp.ones_like(fn(xj, wj))
    vjp = jax.jit(lambda a, b, c: jax.vjp(fn, a, b)[1](c))
    return lambda: _sync(vjp(xj, wj, cot))


def run(quick: bool, out_dir: Path) -> dict[str, Any]:
    sizes = QUICK_SIZES if quick else FULL_SIZES
    repeats, block_s = (3, 0.02) if quick else (7, 0.2)
    started = time.time()
    load_before = os.getloadavg()
    results: dict[str, Any] = {"machine": machine(), "quick": quick, "functions": {}}
    for function in FUNCTIONS:
        methods = _methods(function)
        per_mode: dict[str, Any] = {}
        for mode in ("forward", "forward + backward"):
            per_size: dict[str, Any] = {}
            for sets, n in sizes:
                matrices, quaternions, weights = workload(sets, n)
                x = quaternions if function == "quaternion_mean" else matrices
                calls = {
                    label: call
                    for label, (family, fn) in methods.items()
                    if (call := _call(family, fn, x, weights, mode != "forward")) is not None
                }
                timings = time_all(calls, repeats, block_s)
                per_size[f"{sets}x{n}"] = {
                    label: {"median_s": t.median_s, "first_s": t.first_s, "spread": t.spread}
                    for label, t in timings.items()
                }
            per_mode[mode] = per_size
        results["functions"][function] = per_mode
    return finish(results, started, load_before, out_dir, "means", render)


def ratios(results: dict[str, Any]) -> list[str]:
    """Table rows: scipy / diffquat (forward) for the chordal means, per size and backend."""
    rows = []
    for function in ("rotation_mean[chordal]", "quaternion_mean"):
        for size, timings in results["functions"][function]["forward"].items():
            scipy = timings["scipy Rotation.mean"]["median_s"]
            parts = [
                f"{label.removeprefix('diffquat ')} {scipy / t['median_s']:.2f}x"
                for label, t in timings.items()
                if label.startswith("diffquat")
            ]
            rows.append(f"| {function} | {size} | {'; '.join(parts)} |")
    return rows


def render(results: dict[str, Any]) -> str:
    load = results["load"]
    lines = [
        "# Rotation means: benchmark",
        "",
        "Written by `python -m benchmarks.means`; do not edit by hand. float32, CPU, one mean per set of "
        "N rotations (B sets of N: `BxN`), clusters of up to 0.5 rad. Each cell: median time per call "
        "(forward + backward: the gradient with respect to the samples and the weights).",
        "",
        f"Run time {results['seconds']:.0f} s{' (--quick)' if results['quick'] else ''}; load average "
        f"before {tuple(round(v, 2) for v in load['before'])}, after "
        f"{tuple(round(v, 2) for v in load['after'])}: other jobs shared the machine, absolute times are "
        "noisy.",
        "",
        "## Machine and versions",
        "",
        "| | |",
        "|---|---|",
        *(f"| {k} | {v} |" for k, v in results["machine"].items()),
        "",
        "## scipy / diffquat, forward (chordal means: the only mean scipy has)",
        "",
        "| function | BxN | scipy `Rotation.mean` time / diffquat time |",
        "|---|---|---|",
        *ratios(results),
    ]
    for function, per_mode in results["functions"].items():
        for mode, per_size in per_mode.items():
            sizes = list(per_size)
            labels = list(per_size[sizes[0]])
            lines += ["", f"## {function}, {mode}", "", "| method | " + " | ".join(sizes) + " |"]
            lines.append("|---" * (len(sizes) + 1) + "|")
            for label in labels:
                cells = [_fmt_time(per_size[s][label]["median_s"]) for s in sizes]
                lines.append(f"| {label} | " + " | ".join(cells) + " |")
            firsts = [_fmt_time(per_size[s]["diffquat jax.jit"]["first_s"]) for s in sizes]
            lines.append("| (diffquat jax.jit, first call: compilation) | " + " | ".join(firsts) + " |")
    return "\n".join(lines) + "\n"


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--quick", action="store_true", help="one small size, few repeats")
    parser.add_argument("--out", type=Path, default=Path(__file__).resolve().parent)
    args = parser.parse_args(argv)
    run(args.quick, args.out)


if __name__ == "__main__":
    main()
