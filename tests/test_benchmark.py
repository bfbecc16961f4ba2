"""The benchmark runs (``--quick``) and writes its table, its accuracy table and its plot. No time is
asserted: the numbers depend on the machine."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path
from typing import Any

import numpy as np
import pytest

ROOT = Path(__file__).resolve().parent.parent


# The two conversions (the autograd.Function and custom_jvp paths, the roofline, the compiled methods,
# the N = 1 overhead table), and of the Lie functions one of each kind of input (a vector, with a
# float64 reference of its own; a packed pair, with a peer that reorders it): every path of the report,
# in a fraction of the time of all of them.
QUICK_OPS = (
    "quaternion_to_matrix",
    "matrix_to_quaternion",
    "so3_left_jacobian_inverse",
    "quaternion_plus",
)


def run_benchmark(module: str, out: Path, *args: str) -> None:
    """``python -m benchmarks.<module> --quick <args> --out <out>`` from the repository root."""
    env = {**os.environ, "PYTHONPATH": os.pathsep.join([str(ROOT), os.environ.get("PYTHONPATH", "")])}
    command = [sys.executable, "-m", f"benchmarks.{module}", "--quick", *args, "--out", str(out)]
    subprocess.run(command, cwd=ROOT, env=env, check=True, capture_output=True, timeout=600)


def test_quick_benchmark_writes_results(tmp_path: Path) -> None:
    pytest.importorskip("matplotlib")
    # four blocks, not --quick's three: the report names the count it was run with
    run_benchmark("run", tmp_path, "--ops", ",".join(QUICK_OPS), "--repeats", "4")
    text = (tmp_path / "RESULTS.md").read_text()
    assert "--repeats 4`" in text and "Medians over 4 interleaved blocks" in text
    assert json.loads((tmp_path / "results.json").read_text())["repeats"] == 4
    for heading in (*(f"## {name}\n" for name in QUICK_OPS), "### forward + backward"):
        assert heading in text
    for row in ("| diffquat torch eager |", "| diffquat jax.jit |", "| roofline (copy of the same bytes) |"):
        assert row in text
    assert "### Accuracy on the shared test cases" in text
    assert "### Cells below 1.0x" in text
    assert "## Per-call overhead at N = 1 (validation and dispatch)" in text
    for backend in ("torch eager, forward", "jax eager, forward", "jax.jit, forward", "numpy, forward"):
        assert f"| quaternion_to_matrix | {backend} |" in text
    assert "cpu_kernels" not in text and "C kernels" not in text
    assert (tmp_path / "results.png").stat().st_size > 0


def test_quick_averaging_benchmark_writes_results(tmp_path: Path) -> None:
    """The rotation-averaging benchmark (``benchmarks.averaging --quick``): every diffquat method has a
    row in the end-to-end table and in the optimiser-step table; peers that are not installed are
    named as skipped."""
    run_benchmark("averaging", tmp_path)
    text = (tmp_path / "AVERAGING.md").read_text()
    for heading in ("## End to end:", "## pypose (dense Jacobian) beside diffquat:", "## One optimiser step"):
        assert heading in text
    for row in (
        "| Adam, raw quaternions |",
        "| RiemannianAdam (diffquat) |",
        "| RiemannianAdam (diffquat, jax) |",
        "| Levenberg-Marquardt (diffquat Jacobians) |",
        "| diffquat RiemannianAdam, matrices (torch) |",
        "| diffquat riemannian_adam, matrices (jax.jit) |",
    ):
        assert row in text
    for peer in ("| geoopt RiemannianAdam |", "| pypose LM (dense) |"):
        assert peer in text  # a row either way: timed, or "skipped: ... is not installed"

    results = json.loads((tmp_path / "averaging.json").read_text())
    lm = results["end_to_end"]["methods"]["Levenberg-Marquardt (diffquat Jacobians)"]
    assert lm["seconds_to_1%"] is not None  # the reference reaches its own optimum


def test_quick_means_benchmark_writes_results(tmp_path: Path) -> None:
    """The means' benchmark (``benchmarks.means --quick``: one size, 8 sets of 16 rotations) runs and
    writes a table per function and mode, with scipy's ``Rotation.mean`` beside the chordal means."""
    import math

    run_benchmark("means", tmp_path)
    text = (tmp_path / "MEANS.md").read_text()
    for function in ("rotation_mean[chordal]", "rotation_mean[geodesic]", "rotation_mean[geodesic_l1]"):
        for mode in ("forward", "forward + backward"):
            assert f"## {function}, {mode}" in text
    assert "## quaternion_mean, forward" in text
    assert "| scipy Rotation.mean |" in text
    results = json.loads((tmp_path / "means.json").read_text())
    for per_mode in results["functions"].values():
        for per_size in per_mode.values():
            for timings in per_size.values():
                assert all(math.isfinite(t["median_s"]) and t["median_s"] > 0 for t in timings.values())


def test_merge_lists_only_the_runs_whose_tables_it_shows(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """Merging reports: a later run of an operation replaces an earlier one, and the run list, the run
    time and the load come only from the runs whose tables the report still shows."""

    monkeypatch.syspath_prepend(str(ROOT))
    from benchmarks.run import merge

    def report(name: str, ops: list[str], seconds: float, load: float) -> Path:
        path = tmp_path / f"{name}.json"
        data = {
            "ops": dict.fromkeys(ops, name),
            "seconds": seconds,
            "load": {"before": [load] * 3, "after": [load] * 3},
        }
        path.write_text(json.dumps(data))
        return path

    first = merge([report("a", ["q2m", "m2q"], 100.0, 3.0), report("b", ["m2q"], 50.0, 0.5)])
    (tmp_path / "first.json").write_text(json.dumps(first))
    merged = merge([tmp_path / "first.json", report("c", ["q2m"], 60.0, 0.2)])
    assert merged["ops"] == {"q2m": "c", "m2q": "b"}
    assert [run["ops"] for run in merged["runs"]] == [["m2q"], ["q2m"]]
    assert merged["seconds"] == 60.0
    assert merged["load"]["before"][0] == 0.5  # run "a" (load 3) no longer shows a table


def test_gpu_benchmark_runs_and_renders_into_results(tmp_path: Path) -> None:
    """The GPU half (``benchmarks.gpu``) on the CPU (``--device cpu``, a smoke run: this machine may
    have no GPU): it times every method beside the copy, counts the operations of one diffquat call,
    and its section joins RESULTS.md, which also names it in place of "still to be measured"."""
    pytest.importorskip("matplotlib")

    cpu = json.loads((ROOT / "benchmarks" / "results.json").read_text())
    (tmp_path / "results.json").write_text(json.dumps(cpu))
    run_benchmark("gpu", tmp_path, "--device", "cpu")
    gpu = json.loads((tmp_path / "gpu.json").read_text())
    for name in ("quaternion_to_matrix", "matrix_to_quaternion"):
        timings = gpu["ops"][name]["timings"]["forward + backward"]["64"]
        assert {"diffquat torch eager", "diffquat jax.jit", "roofline (copy of the same bytes)"} <= set(
            timings
        )
        assert all(t["median_s"] > 0 for t in timings.values())
        for order in ("scalar-first", "scalar-last"):
            # the operations (on a GPU: the launched kernels) of one diffquat torch eager call
            assert gpu["ops"][name]["kernels"][order]["forward"], "no operation counted"
    assert gpu["copy_bandwidth"] > 0
    text = (tmp_path / "RESULTS.md").read_text()
    assert "## GPU: cpu (no GPU: a smoke run)" in text
    assert "### Kernels per diffquat torch eager call" in text
    assert "still to be measured" not in text
    assert (tmp_path / "gpu.png").stat().st_size > 0


def test_quick_fisher_benchmark_writes_results(tmp_path: Path) -> None:
    """``benchmarks.fisher --quick`` writes its accuracy and timing tables; the accuracy rows are
    deterministic: the 512-node trapezoid baseline is off by ~0.05 nats at S = 100 I (the issue's
    figure), diffquat within 1e-9."""

    run_benchmark("fisher", tmp_path)
    text = (tmp_path / "FISHER.md").read_text()
    for fragment in ("## Accuracy", "## Time per call", "| value + gradient: diffquat torch eager |"):
        assert fragment in text
    results = json.loads((tmp_path / "fisher.json").read_text())
    row = next(r for r in results["accuracy"] if r["pattern"] == "(s, s, s)" and r["s"] == 100.0)
    assert 0.04 < row["trapezoid float64"] < 0.06
    assert row["diffquat float64"] < 1e-9


def test_quick_igso3_benchmark_writes_results(tmp_path: Path) -> None:
    """``benchmarks.igso3 --quick`` writes its ratio, timing, accuracy and median tables against the
    lookup table of diffusion codes; the accuracy rows are deterministic: the 1000-term series is off
    by ~31% at sigma = 0.002 (docs/igso3.md's figure), the table's left cumulative sum puts the median
    angle at sigma = 0.02 about half a grid step (5%) low, and on the grid the table's log density is
    within the interpolation's 5e-3 nats in the bulk (1.8e-3 at sigma = 0.1)."""
    import math

    run_benchmark("igso3", tmp_path)
    text = (tmp_path / "IGSO3.md").read_text()
    for fragment in (
        "## Time per call: table / diffquat",
        "### log density",
        "### score",
        "### sample",
        "## Accuracy against diffquat float64",
        "## The sampled angle's median",
        "| diffquat jax.jit (float32) |",
        "| table from rotation vectors (np.interp) |",
    ):
        assert fragment in text
    results = json.loads((tmp_path / "igso3.json").read_text())
    assert all(math.isfinite(c["ratio"]) and c["ratio"] > 0 for c in results["ratios"])
    rows = {(r["row"], r["sigma"]): r for r in results["accuracy"]}
    below = rows[("below the grid: a row built at sigma", 0.002)]
    assert 0.25 < below["series_alone"] < 0.4
    on_grid = next(r for (label, _), r in rows.items() if label == "on the grid")
    assert on_grid["log_density_bulk"] < 5e-3 and on_grid["diffquat_float32_log_density_bulk"] < 1e-5
    median = next(
        m for m in results["medians"] if m["sigma"] == 0.02 and m["table_row"] == "a row built at sigma"
    )
    assert -0.07 < median["table_relative_error"] < -0.03


def test_quick_se3_benchmark_writes_results(tmp_path: Path) -> None:
    """``benchmarks.se3 --quick`` writes its ratio tables (peer time / diffquat time on each path), its
    timing tables and the accuracy table of the SE(3) Jacobians. Every method's output, mapped back to
    diffquat's layout, matches diffquat's (the peers' layouts are converted right); every Jacobian
    compared maps onto diffquat's convention (float64, theta = 1: within 1e-12 of the series); and
    diffquat's float32 Q block (J_l's, and J_r's, on all three backends) is within 8 float32 eps * |rho|
    of the series at every angle of the grid, 0 to pi - 1e-6."""
    import importlib.util
    import math

    run_benchmark("se3", tmp_path)
    text = (tmp_path / "SE3.md").read_text()
    for fragment in (
        "## Ratios: peer time / diffquat time",
        "### torch eager",
        "### jax.jit",
        "### numpy",
        "### Every cell where a peer is faster",
        "## What is timed",
        "### se3_exp, forward + backward",
        "## Accuracy of the SE(3) Jacobians",
        "### The mapping onto diffquat's convention, checked in float64 at theta = 1",
        "### float32: error of the upper-right 3x3 block, in float32 eps * |rho|",
        "### float64: error of the upper-right 3x3 block, in float64 eps * |rho|",
    ):
        assert fragment in text
    results = json.loads((tmp_path / "se3.json").read_text())
    assert all(math.isfinite(c["ratio"]) and c["ratio"] > 0 for c in results["ratios"])
    assert {c["path"] for c in results["ratios"]} == {"torch eager", "jax.jit", "numpy"}
    # every op has a ratio against some peer; the right Jacobian's peers (pypose, torchlie) are in the
    # bench extra only, which the test command does not install
    jacobian_peers = any(importlib.util.find_spec(m) is not None for m in ("pypose", "torchlie"))
    expected_ops = {op for op in results["ops"] if jacobian_peers or op != "se3_right_jacobian"}
    assert {c["op"] for c in results["ratios"]} == expected_ops
    for entry in results["ops"].values():
        assert entry["layout_check"] and all(e < 1e-4 for e in entry["layout_check"].values())
    accuracy = results["accuracy"]
    assert accuracy["check"] and all(c["ok"] for c in accuracy["check"])
    peers = {r["label"] for r in accuracy["rows"]}
    for module, label in (("pypose", "pypose"), ("torchlie", "torchlie"), ("jaxlie", "jaxlie (jit)")):
        assert label in peers or importlib.util.find_spec(module) is None
    ours = [
        r
        for r in accuracy["rows"]
        if r["label"].startswith("diffquat") and r["compared"] in ("J_l(xi)", "J_r(xi)")
    ]
    assert len(ours) == 6  # J_l and J_r on numpy, torch and jax
    for row in ours:
        q = row["float32"]["q"]
        assert len(q) == len(accuracy["thetas"]) == 13 and max(q) <= 8, (row["label"], row["function"], q)


def test_quick_motion_benchmark_writes_results(tmp_path: Path) -> None:
    """``benchmarks.motion --quick`` (N = 65, without ``jax.jit``) writes its ratio, timing and check
    tables: every timing is positive, scipy's ``RotationSpline`` is set against diffquat numpy's
    ``so3_bspline``, scipy's rate is the body rate (what ``so3_bspline`` returns), and where pypose is
    installed its ``bspline`` poses are diffquat's ``se3_bspline`` poses at the same points (float64
    rounding), with a ratio against diffquat torch eager forward and forward + backward."""
    import importlib.util
    import math

    run_benchmark("motion", tmp_path)
    text = (tmp_path / "MOTION.md").read_text()
    for fragment in (
        "## Ratios: peer time / diffquat time",
        "### Every cell where a peer is faster",
        "## Time per evaluated point",
        "### se3_bspline, forward + backward",
        "### so3_bspline, forward",
        "### quaternion_squad, forward + backward",
        "| diffquat torch eager (mode='split') |",
        "| scipy RotationSpline, evaluation only |",
        "## Checks",
    ):
        assert fragment in text
    results = json.loads((tmp_path / "motion.json").read_text())
    for per_mode in results["timings"].values():
        for per_n in per_mode.values():
            for timings in per_n.values():
                assert all(math.isfinite(t["median_s"]) and t["median_s"] > 0 for t in timings.values())
    cells = results["ratios"]
    assert all(math.isfinite(c["ratio"]) and c["ratio"] > 0 for c in cells)
    assert {(c["peer"], c["diffquat"]) for c in cells if c["group"] == "so3_bspline"} == {
        ("scipy RotationSpline", "diffquat numpy"),
        ("scipy RotationSpline, evaluation only", "diffquat numpy"),
    }
    assert results["scipy_rate_frame"]["body"] < 1e-6 < results["scipy_rate_frame"]["space"]
    if importlib.util.find_spec("pypose") is not None:
        pypose_modes = {c["mode"] for c in cells if c["peer"] == "pypose bspline"}
        assert pypose_modes == {"forward", "forward + backward"}
        agreement = results["pypose_agreement"]
        assert agreement and all(r["float64"] < 1e-12 and r["float32"] < 1e-4 for r in agreement)


@pytest.mark.filterwarnings("ignore")
def test_every_method_computes_diffquats_job(monkeypatch: pytest.MonkeyPatch) -> None:
    """The layout check of ``benchmarks.run``: every method of every operation (``build_ops``), on 16
    random float32 inputs through its own ``prep`` and ``post``, agrees with diffquat numpy in float64
    to 1e-4. A peer timed with another layout (rows for columns, scalar last), another Euler convention
    or another sign rule fails here. Every disagreement is listed, not only the first."""
    monkeypatch.syspath_prepend(str(ROOT))
    import jax
    from scipy.spatial.transform import Rotation

    import diffquat.numpy as dqn
    from benchmarks import run

    # the peers as the benchmark runs them: jaxlie needs jax's standard promotion rules, not the
    # strict ones of this suite
    with jax.numpy_dtype_promotion("standard"), jax.numpy_rank_promotion("allow"):
        wrong = _layout_disagreements(run, dqn, Rotation)
    assert not wrong, wrong


def _layout_disagreements(run: Any, dqn: Any, Rotation: Any) -> list[str]:
    """Each method that differs from diffquat numpy in float64, and by how much."""

    def as_rotation(y: Any, target: str) -> Any:
        if target == "euler":
            return Rotation.from_euler(run.EULER, y.reshape(-1, 3)).as_matrix()
        return Rotation.from_rotvec(y.reshape(-1, 3)).as_matrix()

    wrong = []
    for op in run.build_ops(quick=True):
        x64 = run.make_input(op.source, run.unit_quaternions(16, seed=5))
        expected = np.asarray(run.ADAPTERS.get(op.name, lambda fn: fn)(getattr(dqn, op.name))(x64))
        for method in op.methods:
            call = run.make_call(method, x64.astype(np.float32), backward=False)
            assert call is not None
            got = np.asarray(method.post(np.asarray(call(), dtype=np.float64)))
            if op.target in ("rotvec", "euler"):  # the same rotation (angles wrap, +-pi alike)
                err = np.abs(as_rotation(got, op.target) - as_rotation(expected, op.target)).max()
            elif op.target == "quaternion":  # up to sign, row by row
                err = np.minimum(np.abs(got - expected).max(-1), np.abs(got + expected).max(-1)).max()
            else:
                err = np.abs(got - expected).max()
            if not err <= 1e-4:
                wrong.append(f"{op.name}: {method.label} differs by {err:.1e}")
    return wrong
