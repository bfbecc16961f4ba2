"""The matrix Fisher normaliser (value, value + gradient) and sampler, against the research normaliser
that pose-estimation code copies. ``python -m benchmarks.fisher [--quick] [--out DIR]`` writes
``FISHER.md`` and ``fisher.json`` (default: next to this file).

The baseline, written here from its published description (Mohlin et al., "Probabilistic orientation
estimation with matrix Fisher distributions", NeurIPS 2020, and its public code): the proper singular
values from ``torch.linalg.svd``, then ``log c = s1 + s2 + s3 + log c_bar`` with ``c_bar`` the
trapezoid rule with 512 nodes on [-1, 1] of the exponentially scaled Bessel integrand
``1/2 I0e((s2 - s3)(1 - u)/2) I0e((s2 + s3)(1 + u)/2) exp((s3 + s1)(u - 1))``, the Bessel function from
the polynomial approximations of Abramowitz & Stegun (9.8.1, 9.8.2), and an ``autograd.Function``
whose backward takes three more trapezoid rules (``d log c / ds_k``, by cyclic shifts of s).

Accuracy: both against the mpmath evaluation of the Bessel integral the tests use
(``tests/cases.py::reference_log_c``), in nats (absolute error of log c), float64 and float32.
Timing: float32, torch eager on ``--device`` (default cpu; ``cuda`` on a GPU machine) and ``jax.jit``
on jax's default backend, medians of repeated calls after a warm-up (torch calls synchronised); the
baseline gets an F and does its own SVD, as diffquat does its own eigendecomposition.
"""

from __future__ import annotations

import argparse
import functools
import json
import platform
import statistics
import sys
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np
import torch
from scipy.spatial.transform import Rotation

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT / "tests"))

import cases  # noqa: E402  (the mpmath reference of the normaliser)

import diffquat.torch as dq  # noqa: E402

# ---------------------------------------------------------------------------------------------------
# The baseline: the 512-node trapezoid normaliser, from its description

NODES = 512
# Abramowitz & Stegun 9.8.1 (|x| <= 3.75, in t^2 = (x/3.75)^2) and 9.8.2 (x >= 3.75, in 3.75/x: the
# polynomial is sqrt(x) e^{-x} I0(x)); |error| < 1.6e-7 and 1.9e-7 relative.
_AS_SMALL = (1.0, 3.5156229, 3.0899424, 1.2067492, 0.2659732, 0.0360768, 0.0045813)
_AS_LARGE = (0.39894228, 0.01328592, 0.00225319, -0.00157565, 0.00916281, -0.02057706, 0.02635537,
             -0.01647633, 0.00392377)  # fmt: skip


def _polynomial(coefficients: tuple[float, ...], x: torch.Tensor) -> torch.Tensor:
    out = torch.full_like(x, coefficients[-1])
    for c in reversed(coefficients[:-1]):
        out = out * x + c
    return out


def _i0e_polynomial(x: torch.Tensor) -> torch.Tensor:
    """exp(-|x|) I0(x) by A&S's polynomials, as the baseline evaluates it."""
    a = x.abs()
    small = _polynomial(_AS_SMALL, (a / 3.75) ** 2) * torch.exp(-a)
    large = _polynomial(_AS_LARGE, 3.75 / a.clamp(min=3.75)) / a.clamp(min=3.75).sqrt()
    return torch.where(a <= 3.75, small, large)


def _trapezoid(values: torch.Tensor) -> torch.Tensor:
    """The trapezoid rule over ``NODES`` equispaced nodes on [-1, 1], along the last axis."""
    h = 2.0 / (NODES - 1)
    return h * (values.sum(-1) - 0.5 * (values[..., 0] + values[..., -1]))


def _integrand(s: torch.Tensor, u: torch.Tensor, k: int) -> torch.Tensor:
    """The scaled integrand with s_k in the exponential and the other two as (i, j), i >= j."""
    others = [s[..., (k + 1) % 3], s[..., (k + 2) % 3]]
    si, sj = torch.maximum(*others)[..., None], torch.minimum(*others)[..., None]
    sk = s[..., k, None]
    return (
        0.5
        * _i0e_polynomial((si - sj) * 0.5 * (1 - u))
        * _i0e_polynomial((si + sj) * 0.5 * (1 + u))
        * torch.exp((sj + sk) * (u - 1))
    )


class _ResearchLogC(torch.autograd.Function):
    @staticmethod
    def forward(ctx: Any, s: torch.Tensor) -> torch.Tensor:
        u = torch.linspace(-1.0, 1.0, NODES, dtype=s.dtype, device=s.device)
        c_bar = _trapezoid(_integrand(s, u, 0))
        ctx.save_for_backward(s, c_bar)
        return torch.log(c_bar) + s.sum(-1)

    @staticmethod
    def backward(ctx: Any, grad: torch.Tensor) -> torch.Tensor:
        s, c_bar = ctx.saved_tensors
        u = torch.linspace(-1.0, 1.0, NODES, dtype=s.dtype, device=s.device)
        # d log c / ds_k = (1/c_bar) int 1/2 ... u du with s_k in the exponential
        ds = torch.stack([_trapezoid(_integrand(s, u, k) * u) for k in range(3)], dim=-1)
        return grad[..., None] * ds / c_bar[..., None]


def research_log_normalizer(matrix: torch.Tensor) -> torch.Tensor:
    """The baseline from an F: SVD, proper singular values (det sign on the last), trapezoid."""
    u, s, vh = torch.linalg.svd(matrix)
    with torch.no_grad():
        sign = torch.sign(torch.linalg.det(u) * torch.linalg.det(vh))
    proper = torch.cat([s[..., :2], s[..., 2:] * sign[..., None]], dim=-1)
    return _ResearchLogC.apply(proper)  # type: ignore[no-any-return]


def research_log_c_of_s(s: np.ndarray, dtype: torch.dtype) -> np.ndarray:
    return _ResearchLogC.apply(torch.tensor(s, dtype=dtype)).double().numpy()  # type: ignore[no-any-return]


# ---------------------------------------------------------------------------------------------------
# Accuracy

PATTERNS = {"(s, s, s)": (1.0, 1.0, 1.0), "(s, s/2, -s/4)": (1.0, 0.5, -0.25), "(s, 1e-3, 1e-3)": None}


def _singular_values(pattern: str, s: float) -> tuple[float, float, float]:
    factors = PATTERNS[pattern]
    if factors is None:
        return (s, 1e-3, 1e-3)
    return (s * factors[0], s * factors[1], s * factors[2])


def accuracy(magnitudes: list[float]) -> list[dict[str, Any]]:
    """|log c - reference| in nats, per method, pattern and magnitude (diffquat through F = R1 S R2^T)."""
    rows = []
    r1, r2 = Rotation.random(2, random_state=0).as_matrix()
    for pattern in PATTERNS:
        for m in magnitudes:
            s = _singular_values(pattern, m)
            ref = cases.reference_log_c(*s)
            f = r1 @ np.diag(s) @ r2.T
            row: dict[str, Any] = {"pattern": pattern, "s": m, "log_c": ref}
            for name, dtype in (("float64", torch.float64), ("float32", torch.float32)):
                x = torch.tensor(f, dtype=dtype)
                ours = float(dq.matrix_fisher_log_normalizer(x))
                # the reference of the F as rounded to the dtype, so that only the computation counts
                proper = cases.proper_singular_values(x.double().numpy())
                exact = cases.reference_log_c(*proper) if dtype == torch.float32 else ref
                row[f"diffquat {name}"] = abs(ours - exact)
                research = float(research_log_c_of_s(np.array(s), dtype)[()])
                row[f"trapezoid {name}"] = abs(research - ref)
            rows.append(row)
    return rows


# ---------------------------------------------------------------------------------------------------
# Timing


def _time(call: Callable[[], Any], repeats: int, min_s: float) -> float:
    call()  # warm-up (and compilation)
    sync = torch.cuda.synchronize if torch.cuda.is_available() else (lambda: None)
    samples = []
    for _ in range(repeats):
        n, start = 0, time.perf_counter()
        while True:
            call()
            sync()
            n += 1
            elapsed = time.perf_counter() - start
            if elapsed >= min_s:
                break
        samples.append(elapsed / n)
    return statistics.median(samples)


def _inputs(n: int) -> np.ndarray:
    rng = np.random.default_rng(1)
    rotations = Rotation.random(2 * n, random_state=2).as_matrix()
    s = np.sort(rng.uniform(0.0, 50.0, size=(n, 3)), axis=-1)[:, ::-1]
    return np.einsum("nij,nj,nkj->nik", rotations[:n], s, rotations[n:]).astype(np.float32)


def timings(sizes: tuple[int, ...], repeats: int, min_s: float, device: str) -> dict[str, dict[str, float]]:
    """Seconds per call, float32, per method and N (rows: methods; N: columns)."""
    import jax
    import jax.numpy as jnp

    import diffquat.jax as djax

    out: dict[str, dict[str, float]] = {}

    def add(label: str, n: int, call: Callable[[], Any]) -> None:
        out.setdefault(label, {})[str(n)] = _time(call, repeats, min_s)

    value_jit = jax.jit(lambda f: djax.matrix_fisher_log_normalizer(f))
    grad_jit = jax.jit(jax.value_and_grad(lambda f: djax.matrix_fisher_log_normalizer(f).sum()))

    def torch_grad(fn: Callable[[torch.Tensor], torch.Tensor], t: torch.Tensor) -> Callable[[], Any]:
        def call() -> Any:
            x = t.clone().requires_grad_(True)
            return torch.autograd.grad(fn(x).sum(), x)

        return call

    def no_grad(fn: Callable[[torch.Tensor], torch.Tensor], t: torch.Tensor) -> Callable[[], Any]:
        def call() -> Any:
            with torch.no_grad():
                return fn(t)

        return call

    one = np.diag([30.0, 20.0, 10.0]).astype(np.float32)  # sampling: n draws from one concentrated F
    key = jax.random.key(0)
    for n in sizes:
        f = _inputs(n)
        t, j = torch.tensor(f, device=device), jnp.asarray(f)
        sample_jit = jax.jit(functools.partial(djax.matrix_fisher_sample, shape=n))
        calls = {
            "value: diffquat torch eager": no_grad(dq.matrix_fisher_log_normalizer, t),
            "value: trapezoid (512 nodes) torch eager": no_grad(research_log_normalizer, t),
            "value: diffquat jax.jit": functools.partial(lambda x: value_jit(x).block_until_ready(), j),
            "value + gradient: diffquat torch eager": torch_grad(dq.matrix_fisher_log_normalizer, t),
            "value + gradient: trapezoid (512 nodes) torch eager": torch_grad(research_log_normalizer, t),
            "value + gradient: diffquat jax.jit": functools.partial(
                lambda x: grad_jit(x)[1].block_until_ready(), j
            ),
            "sample n rotations: diffquat torch eager": functools.partial(
                dq.matrix_fisher_sample, torch.tensor(one, device=device), n
            ),
            "sample n rotations: diffquat jax.jit": functools.partial(
                lambda fn: fn(jnp.asarray(one), key=key).block_until_ready(), sample_jit
            ),
        }
        for label, call in calls.items():
            add(label, n, call)
    return out


# ---------------------------------------------------------------------------------------------------
# Report


def _fmt_time(seconds: float) -> str:
    for unit, scale in (("s", 1.0), ("ms", 1e-3), ("µs", 1e-6)):
        if seconds >= scale:
            return f"{seconds / scale:.3g} {unit}"
    return f"{seconds * 1e9:.3g} ns"


def render(results: dict[str, Any]) -> str:
    lines = [
        "# Matrix Fisher normaliser and sampler",
        "",
        f"`python -m benchmarks.fisher{' --quick' if results['quick'] else ''}` on {results['machine']}, "
        f"torch {results['torch']}, jax {results['jax']}.",
        "",
        "## Accuracy: |log c - reference| in nats",
        "",
        "The reference: mpmath (20 digits) on the one-dimensional Bessel integral "
        "(`tests/cases.py::reference_log_c`). The trapezoid rule is the baseline described in the module "
        "docstring (512 nodes, A&S Bessel polynomials).",
        "",
        "| singular values | s | log c | diffquat float64 | diffquat float32 | trapezoid float64 | "
        "trapezoid float32 |",
        "|---|---|---|---|---|---|---|",
    ]
    for row in results["accuracy"]:
        cells = [f"{row[k]:.1e}" for k in ("diffquat float64", "diffquat float32", "trapezoid float64",
                                           "trapezoid float32")]  # fmt: skip
        lines.append(f"| {row['pattern']} | {row['s']:g} | {row['log_c']:.6g} | " + " | ".join(cells) + " |")
    sizes = results["sizes"]
    lines += [
        "",
        f"## Time per call (float32; torch on {results['device']}, jax on {results['jax_backend']})",
        "",
        "| method | " + " | ".join(f"N = {n}" for n in sizes) + " |",
        "|---|" + "---|" * len(sizes),
    ]
    for label, row in results["timings"].items():
        lines.append(f"| {label} | " + " | ".join(_fmt_time(row[str(n)]) for n in sizes) + " |")
    lines.append("")
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--quick", action="store_true", help="few sizes and magnitudes: seconds")
    parser.add_argument("--out", type=Path, default=Path(__file__).resolve().parent)
    parser.add_argument("--device", default="cpu", help="torch device of the timings (cpu, cuda)")
    parser.add_argument("--threads", type=int, help="torch's CPU threads (default: torch's choice)")
    args = parser.parse_args(argv)
    if args.threads:
        torch.set_num_threads(args.threads)
    import jax

    magnitudes = [100.0] if args.quick else [1e-3, 1.0, 10.0, 100.0, 1e3, 1e4, 1e5]
    sizes = (64,) if args.quick else (1, 64, 4096, 65536)
    results = {
        "quick": args.quick,
        "machine": f"{platform.processor() or platform.machine()} ({platform.system()})",
        "torch": torch.__version__,
        "jax": jax.__version__,
        "sizes": list(sizes),
        "accuracy": accuracy(magnitudes),
        "device": torch.cuda.get_device_name()
        if args.device == "cuda"
        else f"cpu, {torch.get_num_threads()} threads",
        "jax_backend": jax.default_backend(),
        "timings": timings(
            sizes, repeats=2 if args.quick else 7, min_s=0.002 if args.quick else 0.2, device=args.device
        ),
    }
    args.out.mkdir(parents=True, exist_ok=True)
    (args.out / "fisher.json").write_text(json.dumps(results, indent=1))
    (args.out / "FISHER.md").write_text(render(results))
    print(render(results))


if __name__ == "__main__":
    main()
