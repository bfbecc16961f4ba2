"""The GPU half of the benchmark: ``python -m benchmarks.gpu [--quick] [--out DIR]`` on a CUDA machine.

The same methods as :mod:`benchmarks.run` (diffquat's torch eager path, which on CUDA as on the CPU is
torch's operations of the formula, the two conversions as ``autograd.Function``s with their derivatives
written out; torch.compile; jax.jit on the GPU; and the peers), timed the same way (medians over
interleaved blocks, each block synchronised with the device at its end), for ``quaternion_to_matrix``
and ``matrix_to_quaternion`` up to N = 16 777 216, against a device-to-device copy of the same bytes.
It also counts the kernels that one diffquat call launches, forward and backward, with torch's
profiler. It writes ``gpu.json`` and ``gpu.png`` into the output folder and renders them into its
``RESULTS.md`` beside the CPU run's tables (``results.json``), where that is present.

``--device cpu`` runs the same program on the CPU, so that the test suite can prove that it works on
machines without a GPU (its times then say nothing about a GPU).
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import sys
import time
import warnings
from collections.abc import Callable
from pathlib import Path
from typing import Any

# jax takes 75% of the GPU's memory on its first use unless told otherwise; torch's methods run beside it.
os.environ.setdefault("XLA_PYTHON_CLIENT_PREALLOCATE", "false")

import numpy as np

from benchmarks import run

OPS = ("quaternion_to_matrix", "matrix_to_quaternion")
FULL_SIZES = (64, 4096, 262144, 4194304, 16777216)
QUICK_SIZES = (64,)
ROOFLINE = "roofline (copy of the same bytes)"
TARGET_N = 16777216


def copy_bandwidth(device: str, numel: int) -> float:
    """Bytes per second of a device-to-device copy of ``numel`` float32 (bytes read + bytes written),
    median of 20 timed copies after warm-up."""
    import torch

    src = torch.rand(numel, device=device)
    dst = torch.empty_like(src)
    timing = run.time_all({"copy": lambda: dst.copy_(src)}, repeats=20, block_s=0.01)["copy"]
    return 2 * 4 * numel / timing.median_s


def kernels(fn: Callable[[], Any], device: str) -> list[str]:
    """The names of the device kernels (on the CPU: the ATen operations) that one call of ``fn`` runs."""
    import torch
    from torch.profiler import ProfilerActivity, profile

    cuda = device != "cpu"
    fn()
    run._sync(torch.empty(0, device=device))
    with profile(activities=[ProfilerActivity.CUDA if cuda else ProfilerActivity.CPU]) as prof:
        fn()
        run._sync(torch.empty(0, device=device))
    if cuda:
        return [e.name for e in prof.events() if e.device_type.name == "CUDA"]
    # top-level ATen operations only (an operation's own sub-operations are not separate passes)
    return [e.name for e in prof.events() if e.name.startswith("aten::") and e.cpu_parent is None]


def count_kernels(name: str, device: str, n: int) -> dict[str, Any]:
    """Kernels of one diffquat torch eager call, forward (no gradient recorded) and backward alone,
    in each component order."""
    import torch

    import diffquat.torch as dqt

    fn = getattr(dqt, name)
    q = torch.nn.functional.normalize(torch.randn(n, 4, device=device), dim=-1)
    x = q if name == "quaternion_to_matrix" else dqt.quaternion_to_matrix(q)
    counts: dict[str, Any] = {}
    for scalar_first in (True, False):
        leaf = x.clone().requires_grad_(True)
        with torch.no_grad():
            forward = kernels(lambda first=scalar_first: fn(x, scalar_first=first), device)
        out = fn(leaf, scalar_first=scalar_first)
        cot = torch.randn_like(out)
        backward = kernels(
            lambda out=out, cot=cot, leaf=leaf: torch.autograd.grad(out, leaf, cot, retain_graph=True), device
        )
        counts["scalar-first" if scalar_first else "scalar-last"] = {"forward": forward, "backward": backward}
    return counts


def machine(device: str) -> dict[str, str]:
    import jax
    import torch

    info = run.machine()
    info["device"] = torch.cuda.get_device_name() if device != "cpu" else "cpu (no GPU: a smoke run)"
    if device != "cpu":
        props = torch.cuda.get_device_properties(0)
        info["multiprocessors"] = str(props.multi_processor_count)
        info["GPU memory"] = f"{props.total_memory / 2**30:.0f} GiB"
        info["CUDA (torch)"] = str(torch.version.cuda)
    try:
        import triton

        info["triton"] = triton.__version__
    except ImportError:
        info["triton"] = "not installed"
    info["jax devices"] = ", ".join(str(d) for d in jax.devices())
    info["python"] = platform.python_version()
    return info


def run_gpu(quick: bool, out_dir: Path, device: str) -> dict[str, Any]:
    sizes = QUICK_SIZES if quick else FULL_SIZES
    repeats, block_s = (3, 0.002) if quick else (9, 0.02)
    # One dynamic graph per function from the first call: a recompilation per batch size is minutes.
    ops = [op for op in run.build_ops(quick, dynamic=True) if op.name in OPS]
    started = time.time()
    # What diffquat's eager torch path was when this ran (a gpu.json without it: the former Triton kernels).
    results: dict[str, Any] = {
        "quick": quick,
        "sizes": list(sizes),
        "device": device,
        "eager_path": "formula (autograd.Function for the conversions)",
        "ops": {},
    }
    # 128 B per rotation is about the largest traffic timed here (matrix_to_quaternion forward + backward)
    results["copy_bandwidth"] = copy_bandwidth(device, 32 * sizes[-1])
    for op in ops:
        traffic = run.WIDTH[op.source] + run.WIDTH[op.target]
        entry: dict[str, Any] = {"skipped": op.skipped, "timings": {}}
        methods = [m for m in op.methods if m.family != "numpy"]
        for mode, backward in (("forward", False), ("forward + backward", True)):
            per_n: dict[str, dict[str, Any]] = {}
            for n in sizes:
                x32 = run.make_input(op.source, run.unit_quaternions(n)).astype(np.float32)
                calls = {}
                for m in methods:
                    call = run.make_call(m, x32, backward, device)
                    if call is not None:
                        calls[m.label] = call
                floats = traffic + (traffic + run.WIDTH[op.source] if backward else 0)
                calls[ROOFLINE] = run.roofline_call(floats, n, device)
                with warnings.catch_warnings():
                    warnings.simplefilter("ignore")
                    timings = run.time_all(calls, repeats, block_s)
                per_n[str(n)] = {label: t.__dict__ for label, t in timings.items()}
                del calls
                print(f"{op.name} {mode} N={n} done", file=sys.stderr, flush=True)
            entry["timings"][mode] = per_n
        entry["kernels"] = count_kernels(op.name, device, 4096)
        results["ops"][op.name] = entry
    results["seconds"] = time.time() - started
    results["machine"] = machine(device)
    out_dir.mkdir(parents=True, exist_ok=True)
    (out_dir / "gpu.json").write_text(json.dumps(results, indent=1))
    plot(results, out_dir / "gpu.png")
    rerender(out_dir)
    return results


def rerender(out_dir: Path) -> None:
    """``RESULTS.md`` again from the CPU run's ``results.json`` and this ``gpu.json``."""
    cpu = out_dir / "results.json"
    if cpu.exists():
        (out_dir / "RESULTS.md").write_text(run.render(json.loads(cpu.read_text()), load_gpu(out_dir)))


def load_gpu(out_dir: Path) -> dict[str, Any] | None:
    path = out_dir / "gpu.json"
    return json.loads(path.read_text()) if path.exists() else None


def _frac(per_n: dict[str, Any], label: str) -> float:
    return float(per_n[ROOFLINE]["median_s"] / per_n[label]["median_s"])


def _kernel_cell(names: list[str]) -> str:
    short = sorted({name.split("(")[0][:40] for name in names})
    return f"{len(names)}: " + ", ".join(f"`{s}`" for s in short) if names else "0"


def render(results: dict[str, Any]) -> str:
    """The GPU section of ``RESULTS.md``."""
    info = results["machine"]
    sizes = results["sizes"]
    gbps = results["copy_bandwidth"] / 1e9
    out = [
        f"## GPU: {info['device']}",
        "",
        "Written by `python -m benchmarks.gpu" + (" --quick" if results["quick"] else "") + "` "
        f"({results['seconds']:.0f} s), do not edit by hand. float32. Each cell: median time per call "
        "over interleaved blocks, each block synchronised with the device at its end, and in "
        "parentheses the fraction of the memory bound: the roofline row (a device-to-device copy "
        "moving the same bytes) over this row's time. A large copy on this device moved "
        f"{gbps:.0f} GB/s (bytes read + written).",
        "",
        "| | |",
        "|---|---|",
        *[f"| {k} | {v} |" for k, v in info.items() if k not in ("torch threads",)],
        "",
        *(
            [
                "Measured with diffquat's former Triton kernels as its eager torch path on CUDA; they "
                "have been removed (the eager path is now torch's operations of the formula): to be "
                "re-measured.",
                "",
            ]
            if results.get("eager_path") is None
            else []
        ),
        "![ns per rotation against N, GPU](gpu.png)",
        "",
        f"### Targets at N = {TARGET_N} (issue 4)",
        "",
        "| op | mode | diffquat eager / copy bound | fastest torch peer / diffquat eager "
        "| jaxlie / diffquat jax |",
        "|---|---|---|---|---|",
    ]
    for name, entry in results["ops"].items():
        for mode, per_n in entry["timings"].items():
            t = per_n.get(str(TARGET_N)) or per_n[str(sizes[-1])]
            med = {label: v["median_s"] for label, v in t.items()}
            peers = [med[p] for p in run.TORCH_PEERS if p in med]
            eager = med.get("diffquat torch eager")
            cells = [
                f"{_frac(t, 'diffquat torch eager'):.0%}" if eager else "—",
                f"{min(peers) / eager:.1f}x" if peers and eager else "—",
                f"{med['jaxlie (jit)'] / med['diffquat jax.jit']:.2f}x"
                if "jaxlie (jit)" in med and "diffquat jax.jit" in med
                else "—",
            ]
            out.append(f"| {name} | {mode} | " + " | ".join(cells) + " |")
    out += [
        "",
        "### Kernels per diffquat torch eager call",
        "",
        "Counted with torch's profiler: the forward with no gradient recorded, and the backward "
        "(`torch.autograd.grad` with a given cotangent) alone.",
        "",
        "| op | order | forward | backward |",
        "|---|---|---|---|",
    ]
    for name, entry in results["ops"].items():
        for order, k in entry["kernels"].items():
            out.append(f"| {name} | {order} | {_kernel_cell(k['forward'])} | {_kernel_cell(k['backward'])} |")
    for name, entry in results["ops"].items():
        out += ["", f"### {name} on the GPU", ""]
        if entry["skipped"]:
            out += ["Left out: " + "; ".join(entry["skipped"]), ""]
        for mode, per_n in entry["timings"].items():
            labels = list(per_n[str(sizes[0])])
            out += [f"#### {mode}", "", "| method | " + " | ".join(f"N = {n}" for n in sizes) + " |"]
            out += ["|---" * (len(sizes) + 1) + "|"]
            for label in labels:
                cells = [
                    run._fmt_time(per_n[str(n)][label]["median_s"]) + f" ({_frac(per_n[str(n)], label):.0%})"
                    for n in sizes
                ]
                out.append(f"| {label} | " + " | ".join(cells) + " |")
            first = [
                f"{label}: {run._fmt_time(per_n[str(sizes[0])][label]['first_s'])}"
                for label in labels
                if "compile" in label or "jit" in label
            ]
            spreads = [v["spread"] for ts in per_n.values() for v in ts.values()]
            out += [
                "",
                f"First call at N = {sizes[0]} (compilation included): " + "; ".join(first) + ". "
                f"Largest (max - min) / median over blocks in this table: {max(spreads):.0%}.",
                "",
            ]
    return "\n".join(out) + "\n"


def plot(results: dict[str, Any], path: Path) -> None:
    run.plot(results, path, f" ({results['machine']['device']})")


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--quick", action="store_true", help="one small N, few repeats")
    parser.add_argument("--out", type=Path, default=Path(__file__).resolve().parent)
    parser.add_argument("--device", default="cuda", help="torch device (default cuda; cpu: a smoke run)")
    parser.add_argument("--render", action="store_true", help="only render RESULTS.md from the json files")
    args = parser.parse_args(argv)
    if args.render:
        rerender(args.out)
        return
    if args.device != "cpu":
        import torch

        if not torch.cuda.is_available():
            parser.error("no CUDA device: run on a GPU machine, or pass --device cpu for a smoke run")
    run_gpu(args.quick, args.out, args.device)


if __name__ == "__main__":
    main()
