"""Rotation averaging end to end, and one optimiser step alone: diffquat's Riemannian Adam (torch and
jax), Adam on raw quaternions, Levenberg-Marquardt with diffquat's Jacobians, and the peers where they
are installed (geoopt's RiemannianAdam, pypose's Levenberg-Marquardt).
``python -m benchmarks.averaging [--quick] [--out DIR]`` writes ``AVERAGING.md`` and ``averaging.json``.

The problem and the solvers are those of ``notebooks/orientation_on_manifold.py`` (imported from
there): a pose graph of ``n`` rotations, 10 measurements per rotation, a tenth of them outliers, a
Cauchy loss of the geodesic residual, every method from the same spectral initialisation. A method's
time to a given error is the time its steps took (the evaluation of the error is not counted) until
the mean angle to the truth first comes within 1% (0.1%) of the optimum's (Levenberg-Marquardt run
to convergence apart); each method runs ``repeats`` times, interleaved (run r of every method before
run r + 1 of any), and the table gives the medians. One CPU thread, float64 (the optimiser-step table:
float32). pypose's Levenberg-Marquardt forms a dense Jacobian (3 minutes and 13 GB per iteration at
n = 1000 here), so it runs on a smaller problem beside diffquat's.
"""

from __future__ import annotations

import argparse
import os
import statistics
import sys
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT / "notebooks"))

import orientation_on_manifold as om  # noqa: E402  (the problem and the solvers)

from benchmarks.run import Timing, finish, time_all  # noqa: E402

TARGETS = (("1%", 0.01), ("0.1%", 0.001))
FULL = {"n": 1000, "steps": 200, "lm_iterations": 12, "repeats": 3, "pypose_n": 200, "pypose_iterations": 8}
QUICK = {"n": 40, "steps": 30, "lm_iterations": 5, "repeats": 1, "pypose_n": 20, "pypose_iterations": 2}
STEP_SIZES_FULL = (1, 1000, 100_000)
STEP_SIZES_QUICK = (1, 1000)


def settings(config: dict[str, int]) -> om.Settings:
    return om.Settings(
        n=config["n"],
        steps=config["steps"],
        lm_iterations=config["lm_iterations"],
        pypose_n=config["pypose_n"],
        pypose_iterations=config["pypose_iterations"],
    )


def end_to_end(
    problem: om.Problem, methods: dict[str, Callable[[om.Problem], om.Trace]], repeats: int
) -> dict[str, Any]:
    """Each method ``repeats`` times, interleaved; per method the median time and the steps to each
    target, the median time per step, and the final error and cost."""
    runs: dict[str, list[om.Trace]] = {label: [] for label in methods}
    for _ in range(repeats):
        for label, solve in methods.items():
            traces = om.solve_all(problem, {label: solve}, say=lambda *a, **k: None)
            runs[label].append(traces[label])
            print(f"n={problem.n} {label} done", file=sys.stderr, flush=True)
    reference = om.optimum(problem).error[-1]
    out: dict[str, Any] = {"optimum_error_deg": reference, "methods": {}}
    for label, traces in runs.items():
        if traces[0].skipped:
            out["methods"][label] = {"skipped": traces[0].skipped}
            continue
        entry: dict[str, Any] = {
            "steps": len(traces[0].error) - 1,
            "final_error_deg": traces[0].error[-1],
            "final_cost": traces[0].cost[-1],
            "seconds_per_step": statistics.median(t.seconds[-1] / (len(t.error) - 1) for t in traces),
        }
        for name, fraction in TARGETS:
            times = [t.time_to(reference, fraction) for t in traces]
            reached = [x for x in times if x is not None]
            entry[f"seconds_to_{name}"] = statistics.median(reached) if len(reached) == len(times) else None
            entry[f"steps_to_{name}"] = traces[0].first_within(reference, fraction)
        out["methods"][label] = entry
    return out


def _step_calls(n: int) -> dict[str, Callable[[], Any]]:
    """One optimiser step of each method on ``n`` rotations, as zero-argument callables."""
    import jax
    import jax.numpy as jnp
    import torch

    import diffquat.jax as dqj
    import diffquat.torch as dqt
    from diffquat.jax import optim as dqo
    from diffquat.torch.optim import RiemannianAdam

    generator = torch.Generator().manual_seed(0)
    start = dqt.quaternion_to_matrix(dqt.random_quaternions(n, generator=generator))
    grad = torch.randn(n, 3, 3, generator=generator)
    q_start = dqt.random_quaternions(n, generator=generator)
    q_grad = torch.randn(n, 4, generator=generator)

    def torch_step(param: torch.Tensor, gradient: torch.Tensor, optimizer: Any) -> Callable[[], Any]:
        param.grad = gradient
        return lambda: optimizer.step()

    calls: dict[str, Callable[[], Any]] = {}
    R = torch.nn.Parameter(start.clone())
    calls["diffquat RiemannianAdam, matrices (torch)"] = torch_step(R, grad, RiemannianAdam([R], lr=1e-3))
    q = torch.nn.Parameter(q_start.clone())
    calls["diffquat RiemannianAdam, quaternions (torch)"] = torch_step(
        q, q_grad, RiemannianAdam([q], lr=1e-3)
    )
    raw = torch.nn.Parameter(q_start.clone())
    calls["torch.optim.Adam, raw quaternions"] = torch_step(raw, q_grad, torch.optim.Adam([raw], lr=1e-3))

    transformation = dqo.riemannian_adam(1e-3)

    @jax.jit
    def jax_step(params: jax.Array, state: Any, g: jax.Array) -> tuple[jax.Array, Any]:
        updates, state = transformation.update(g, state, params)
        return dqo.apply_updates(params, updates), state

    params = dqj.quaternion_to_matrix(jnp.asarray(q_start.numpy()))
    box = [params, transformation.init(params)]
    g_jax = jnp.asarray(grad.numpy())

    def run_jax() -> Any:
        box[0], box[1] = jax_step(box[0], box[1], g_jax)
        return box[0]

    calls["diffquat riemannian_adam, matrices (jax.jit)"] = run_jax
    try:
        import geoopt
    except ImportError:
        return calls
    G = geoopt.ManifoldParameter(start.clone(), manifold=geoopt.Stiefel())
    calls["geoopt RiemannianAdam, Stiefel"] = torch_step(G, grad, geoopt.optim.RiemannianAdam([G], lr=1e-3))
    return calls


def optimizer_steps(sizes: tuple[int, ...], repeats: int, block_s: float) -> dict[str, dict[str, Timing]]:
    """One optimiser step, given a gradient (no loss), float32, per batch size N: the cost that an
    optimiser adds to every step of a training loop."""
    out: dict[str, dict[str, Timing]] = {}
    for n in sizes:
        out[str(n)] = time_all(_step_calls(n), repeats, block_s)
        print(f"optimizer step N={n} done", file=sys.stderr, flush=True)
    return out


def run(quick: bool, out_dir: Path) -> dict[str, Any]:
    import torch

    config = QUICK if quick else FULL
    s = settings(config)
    om.setup()
    load_before = os.getloadavg()
    started = time.time()
    results: dict[str, Any] = {"quick": quick, "config": config}
    problem = om.make_problem(n=s.n, degree=s.degree)
    results["problem"] = om.describe(problem)
    results["end_to_end"] = end_to_end(problem, om.solvers(s), config["repeats"])
    small = om.make_problem(n=s.pypose_n, degree=s.degree)
    results["pypose_problem"] = om.describe(small)
    methods = {
        om.LM: lambda p: om.levenberg_marquardt(p, s.pypose_iterations),
        om.PYPOSE: lambda p: om.pypose_lm(p, s.pypose_iterations),
    }
    results["pypose"] = end_to_end(small, methods, config["repeats"])
    torch.set_default_dtype(torch.float32)
    sizes = STEP_SIZES_QUICK if quick else STEP_SIZES_FULL
    steps = optimizer_steps(sizes, 3 if quick else 7, 0.002 if quick else 0.05)
    results["optimizer_step"] = {n: {label: t.__dict__ for label, t in ts.items()} for n, ts in steps.items()}
    return finish(
        results, started, load_before, out_dir, "averaging", render, peers=("geoopt", "pypose", "optax")
    )


def _seconds(x: float | None) -> str:
    if x is None:
        return "not reached"
    return f"{x * 1e3:.3g} ms" if x < 1 else f"{x:.3g} s"


def _table(block: dict[str, Any]) -> list[str]:
    lines = [
        "| method | steps | to 1%: steps | to 1%: time | to 0.1%: steps | to 0.1%: time | time per step "
        "| final error (deg) | final cost |",
        "|---|---|---|---|---|---|---|---|---|",
    ]
    for label, m in block["methods"].items():
        if "skipped" in m:
            lines.append(f"| {label} | skipped: {m['skipped']} |" + " |" * 7)
            continue
        cells = [str(m["steps"])]
        for name, _ in TARGETS:
            steps = m[f"steps_to_{name}"]
            cells += ["—" if steps is None else str(steps), _seconds(m[f"seconds_to_{name}"])]
        cells += [_seconds(m["seconds_per_step"]), f"{m['final_error_deg']:.4f}", f"{m['final_cost']:.6g}"]
        lines.append(f"| {label} | " + " | ".join(cells) + " |")
    return lines


def render(results: dict[str, Any]) -> str:
    config = results["config"]
    lines = [
        "# Rotation averaging: end to end, and one optimiser step",
        "",
        f"Written by `python -m benchmarks.averaging{' --quick' if results['quick'] else ''}`; do not "
        "edit by hand. The problem, the methods and the rules of the timing are in the module's docstring "
        "(`benchmarks/averaging.py`) and in `notebooks/orientation_on_manifold.ipynb`.",
        "",
        f"Run time {results['seconds']:.0f} s; load average (1, 5, 15 min) before "
        f"{tuple(round(x, 2) for x in results['load']['before'])}, after "
        f"{tuple(round(x, 2) for x in results['load']['after'])}: other jobs shared the machine, so "
        "absolute times are noisy.",
        "",
        f"## End to end: {results['problem']}",
        "",
        f"Time to come within 1% and 0.1% of the optimum's mean error "
        f"({results['end_to_end']['optimum_error_deg']:.4f} deg), median of {config['repeats']} runs; "
        "steps counted from the start (iterations for Levenberg-Marquardt). Adam learning rates: the "
        "best of 0.005-0.16 for each (see `notebooks/orientation_on_manifold.py`).",
        "",
        *_table(results["end_to_end"]),
        "",
        f"## pypose (dense Jacobian) beside diffquat: {results['pypose_problem']}",
        "",
        *_table(results["pypose"]),
        "",
        "## One optimiser step, given a gradient (float32, one thread)",
        "",
    ]
    sizes = list(results["optimizer_step"])
    labels = list(results["optimizer_step"][sizes[0]])
    lines.append("| method | " + " | ".join(f"N = {n}" for n in sizes) + " |")
    lines.append("|---|" + "---|" * len(sizes))
    for label in labels:
        cells = []
        for n in sizes:
            t = results["optimizer_step"][n].get(label)
            cells.append("—" if t is None else _seconds(t["median_s"]))
        lines.append(f"| {label} | " + " | ".join(cells) + " |")
    lines += ["", "## Machine and versions", "", "| | |", "|---|---|"]
    lines += [f"| {k} | {v} |" for k, v in results["machine"].items()]
    return "\n".join(lines) + "\n"


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--quick", action="store_true", help="a small problem, one run each: seconds")
    parser.add_argument("--out", type=Path, default=Path(__file__).resolve().parent)
    args = parser.parse_args(argv)
    run(args.quick, args.out)


if __name__ == "__main__":
    main()
