"""Which array ``SO3`` and ``SE3`` store: the candidates timed and counted on the same data.
``python -m benchmarks.objects [--n N ...] [--repeat R]`` prints a Markdown table (docs/performance.md,
Objects, holds one run).

For each of the three operations the issue names (compose, apply to points, as_matrix), float32:

- ``SO3``: a stored matrix ``(..., 3, 3)`` (``R1 @ R2``, ``R @ p``, the array itself) against a stored
  unit quaternion ``(..., 4)`` (jaxlie's choice: ``quaternion_multiply``, ``quaternion_apply``,
  ``quaternion_to_matrix``);
- ``SE3``: a stored matrix ``(..., 4, 4)`` (``se3_compose``, ``se3_apply``, the array) against a
  quaternion and a translation (jaxlie's: ``q1 q2`` and ``q1 t2 + t1``, ``q p + t``,
  ``se3_from_rotation_translation(quaternion_to_matrix(q), t)``);
- and the object method against the functional call on its stored array (the object's own cost:
  Python only, the ATen operations are the same, tests/test_objects.py counts them).

Eager torch: the ATen operations one call dispatches (``TorchDispatchMode``, forward) and the median
time of one call; ``jax.jit``: the median time of the compiled call. Medians of ``--repeat`` blocks,
the candidates interleaved within each block.
"""

from __future__ import annotations

import argparse
import statistics
import time
from collections.abc import Callable
from typing import Any

import jax
import jax.numpy as jnp
import torch
from torch.utils._python_dispatch import TorchDispatchMode

import diffquat.jax as dj
import diffquat.torch as dt


class _Count(TorchDispatchMode):
    def __init__(self) -> None:
        super().__init__()
        self.n = 0

    def __torch_dispatch__(self, func: Any, types: Any, args: Any = (), kwargs: Any = None) -> Any:
        self.n += 1
        return func(*args, **(kwargs or {}))


def count(fn: Callable[[], Any]) -> int:
    with torch.no_grad(), _Count() as c:
        fn()
    return c.n


def median_us(fns: dict[str, Callable[[], Any]], repeat: int, block_s: float = 0.02) -> dict[str, float]:
    """Median microseconds per call of each function, over ``repeat`` interleaved blocks."""
    times: dict[str, list[float]] = {k: [] for k in fns}
    loops = {}
    for k, f in fns.items():
        f()
        t0, n = time.perf_counter(), 0
        while time.perf_counter() - t0 < block_s:
            f()
            n += 1
        loops[k] = max(n, 1)
    for r in range(repeat):
        keys = list(fns)
        keys = keys[r % len(keys) :] + keys[: r % len(keys)]
        for k in keys:
            f, n = fns[k], loops[k]
            t0 = time.perf_counter()
            for _ in range(n):
                f()
            times[k].append((time.perf_counter() - t0) / n * 1e6)
    return {k: statistics.median(v) for k, v in times.items()}


def torch_cases(n: int) -> dict[str, dict[str, Callable[[], Any]]]:
    g = torch.Generator().manual_seed(0)
    q1, q2 = dt.random_quaternions(n, generator=g), dt.random_quaternions(n, generator=g)
    t1, t2, p = torch.randn(n, 3, generator=g), torch.randn(n, 3, generator=g), torch.randn(n, 3, generator=g)
    r1, r2 = dt.quaternion_to_matrix(q1), dt.quaternion_to_matrix(q2)
    m1, m2 = dt.se3_from_rotation_translation(r1, t1), dt.se3_from_rotation_translation(r2, t2)
    a, b, c, d = dt.SO3(r1), dt.SO3(r2), dt.SE3(m1), dt.SE3(m2)
    return {
        "SO3 compose": {
            "matrix: R1 @ R2": lambda: r1 @ r2,
            "matrix: SO3 @ SO3": lambda: a @ b,
            "quaternion: quaternion_multiply": lambda: dt.quaternion_multiply(q1, q2),
        },
        "SO3 apply": {
            "matrix: (R @ p[..., None])[..., 0]": lambda: (r1 @ p[..., None])[..., 0],
            "matrix: SO3 @ p": lambda: a @ p,
            "quaternion: quaternion_apply": lambda: dt.quaternion_apply(q1, p),
        },
        "SO3 as_matrix": {
            "matrix: SO3.as_matrix()": lambda: a.as_matrix(),
            "quaternion: quaternion_to_matrix": lambda: dt.quaternion_to_matrix(q1),
        },
        "SE3 compose": {
            "matrix: se3_compose": lambda: dt.se3_compose(m1, m2),
            "matrix: SE3 @ SE3": lambda: c @ d,
            "quaternion + translation": lambda: (
                dt.quaternion_multiply(q1, q2),
                dt.quaternion_apply(q1, t2) + t1,
            ),
        },
        "SE3 apply": {
            "matrix: se3_apply": lambda: dt.se3_apply(m1, p),
            "matrix: SE3 @ p": lambda: c @ p,
            "quaternion + translation": lambda: dt.quaternion_apply(q1, p) + t1,
        },
        "SE3 as_matrix": {
            "matrix: SE3.as_matrix()": lambda: c.as_matrix(),
            "quaternion + translation": lambda: dt.se3_from_rotation_translation(
                dt.quaternion_to_matrix(q1), t1
            ),
        },
    }


def jax_cases(n: int) -> dict[str, dict[str, Callable[[], Any]]]:
    k = jax.random.split(jax.random.key(0), 5)
    q1, q2 = (
        dj.random_quaternions(n, key=k[0], dtype=jnp.float32),
        dj.random_quaternions(n, key=k[1], dtype=jnp.float32),
    )
    t1, t2, p = (jax.random.normal(k[i], (n, 3), dtype=jnp.float32) for i in (2, 3, 4))
    r1, r2 = dj.quaternion_to_matrix(q1), dj.quaternion_to_matrix(q2)
    m1, m2 = dj.se3_from_rotation_translation(r1, t1), dj.se3_from_rotation_translation(r2, t2)
    a, b, c, d = dj.SO3(r1), dj.SO3(r2), dj.SE3(m1), dj.SE3(m2)

    def jit(f: Callable[..., Any], *xs: Any) -> Callable[[], Any]:
        compiled = jax.jit(f)
        return lambda: jax.block_until_ready(compiled(*xs))

    return {
        "SO3 compose": {
            "matrix: SO3 @ SO3": jit(lambda a, b: a @ b, a, b),
            "quaternion: quaternion_multiply": jit(dj.quaternion_multiply, q1, q2),
        },
        "SO3 apply": {
            "matrix: SO3 @ p": jit(lambda a, p: a @ p, a, p),
            "quaternion: quaternion_apply": jit(dj.quaternion_apply, q1, p),
        },
        "SO3 as_matrix": {
            "matrix: SO3.as_matrix()": jit(lambda a: a.as_matrix(), a),
            "quaternion: quaternion_to_matrix": jit(dj.quaternion_to_matrix, q1),
        },
        "SE3 compose": {
            "matrix: SE3 @ SE3": jit(lambda c, d: c @ d, c, d),
            "quaternion + translation": jit(
                lambda q1, q2, t1, t2: (dj.quaternion_multiply(q1, q2), dj.quaternion_apply(q1, t2) + t1),
                q1,
                q2,
                t1,
                t2,
            ),
        },
        "SE3 apply": {
            "matrix: SE3 @ p": jit(lambda c, p: c @ p, c, p),
            "quaternion + translation": jit(lambda q, t, p: dj.quaternion_apply(q, p) + t, q1, t1, p),
        },
        "SE3 as_matrix": {
            "matrix: SE3.as_matrix()": jit(lambda c: c.as_matrix(), c),
            "quaternion + translation": jit(
                lambda q, t: dj.se3_from_rotation_translation(dj.quaternion_to_matrix(q), t), q1, t1
            ),
        },
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--n", type=int, nargs="+", default=[64, 4096])
    parser.add_argument("--repeat", type=int, default=7)
    args = parser.parse_args()
    torch.set_num_threads(1)
    print(
        "| operation | stored | torch ops | "
        + " | ".join(f"torch us N={n} | jit us N={n}" for n in args.n)
        + " |"
    )
    print("|---|---|---|" + "---|---|" * len(args.n))
    rows: dict[tuple[str, str], list[str]] = {}
    for n in args.n:
        tc, jc = torch_cases(n), jax_cases(n)
        for op, fns in tc.items():
            t = median_us(fns, args.repeat)
            j = median_us(jc[op], args.repeat)
            for name, f in fns.items():
                row = rows.setdefault((op, name), [str(count(f))])
                row += [f"{t[name]:.1f}", f"{j[name]:.1f}" if name in j else "-"]
    for (op, name), cells in rows.items():
        print(f"| {op} | {name} | " + " | ".join(cells) + " |")


if __name__ == "__main__":
    main()
