"""The benchmark runs (``--quick``) and writes its table, its accuracy table and its plot. No time is
asserted: the numbers depend on the machine."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parent.parent


def test_quick_benchmark_writes_results(tmp_path: Path) -> None:
    pytest.importorskip("matplotlib")
    env = {**os.environ, "PYTHONPATH": os.pathsep.join([str(ROOT), os.environ.get("PYTHONPATH", "")])}
    subprocess.run(
        [sys.executable, "-m", "benchmarks.run", "--quick", "--out", str(tmp_path)],
        cwd=ROOT, env=env, check=True, capture_output=True, timeout=600,
    )  # fmt: skip
    text = (tmp_path / "RESULTS.md").read_text()
    for heading in ("## quaternion_to_matrix", "## matrix_to_quaternion", "### forward + backward"):
        assert heading in text
    for row in ("| diffquat torch eager |", "| diffquat jax.jit |", "| roofline (copy of the same bytes) |"):
        assert row in text
    assert "### Accuracy on the shared test cases" in text
    assert (tmp_path / "results.png").stat().st_size > 0
