"""Every public torch function dispatches exactly the ATen operations recorded in
``benchmarks/ops.json`` (forward, and forward + backward, at one eager call: issue 46's operation
budget), counted by ``benchmarks/ops.py`` itself. A change that adds or removes operations fails here
until the table is regenerated (``python -m benchmarks.ops``) and committed with it, so every change of
the eager cost is seen in review. Counts are exact for a given torch; on another version that test is
skipped. Eager calls only: a second or so."""

from __future__ import annotations

import sys
from pathlib import Path
from typing import Any

import pytest
import torch

# benchmarks/ is a folder of the repository, not of the installed package: importable from its root
sys.path.insert(0, str(Path(__file__).resolve().parent.parent))
from benchmarks import ops

RECORDED = ops.load()
BY_ID = {entry["id"]: entry for entry in RECORDED["rows"]}
REGENERATE = (
    f"regenerate the table with `{ops.COMMAND}` (it rewrites benchmarks/ops.json and benchmarks/OPS.md) "
    "and commit it with the change"
)

# the version, not the build (+cpu, +cu126): CPU tensors dispatch the same operations in every build
same_torch = pytest.mark.skipif(
    torch.__version__.split("+")[0] != RECORDED["torch"].split("+")[0],
    reason=f"operation counts are recorded for torch {RECORDED['torch']}, not {torch.__version__}",
)


def test_every_row_is_recorded() -> None:
    ids = [row.id for row in ops.rows()]
    assert ids == list(BY_ID), f"the rows of benchmarks/ops.py and ops.json differ: {REGENERATE}"


def test_the_report_is_the_recorded_table_rendered() -> None:
    """benchmarks/OPS.md is ops.json rendered: neither was edited by hand, nor one regenerated alone."""
    text = (ops.ROOT / "benchmarks" / "OPS.md").read_text()
    assert text == ops.render(RECORDED), f"benchmarks/OPS.md is not ops.json rendered: {REGENERATE}"


@same_torch
@pytest.mark.parametrize("row", ops.rows(), ids=lambda row: row.id)
def test_operation_counts_are_the_recorded_ones(row: ops.Row) -> None:
    entry = BY_ID.get(row.id)
    assert entry is not None, f"{row.id} is not in benchmarks/ops.json: {REGENERATE}"
    counted = ops.count_rows([row.id])[row.id]
    recorded = (entry["forward"], entry["backward"])
    assert counted == recorded, (
        f"{row.id}: {counted[0]} / {counted[1]} ATen operations (forward / forward + backward), "
        f"benchmarks/ops.json records {recorded[0]} / {recorded[1]}: {REGENERATE}"
    )


def test_argument_validation_dispatches_no_operation(monkeypatch: pytest.MonkeyPatch) -> None:
    """The checks of shapes and dtypes (``Backend.validate``, which every public function calls) read
    static shapes and dtypes: on inputs of the compute dtype they dispatch nothing, for every row, so
    the counts above are the formulas' alone."""
    from diffquat import _backend

    validate = _backend.Backend.validate
    seen: list[tuple[str, dict[str, int]]] = []

    def counting(self: Any, fname: str, *arrays: Any) -> Any:
        with ops._counter_mode() as mode:
            out = validate(self, fname, *arrays)
        seen.append((fname, dict(mode.ops)))
        return out

    monkeypatch.setattr(_backend.Backend, "validate", counting)
    q = ops.cases.uniform_quaternions(ops.N, ops.SEED)
    unvalidated = []
    for row in ops.rows():
        before = len(seen)
        row.function()(*row.tensors(q, torch.float32))
        if len(seen) == before:
            unvalidated.append(row.id)
    assert seen
    dispatched = {fname: counts for fname, counts in seen if counts}
    assert not dispatched, f"argument validation dispatched ATen operations: {dispatched}"
    assert not unvalidated, f"public functions that call no Backend.validate: {unvalidated}"


def test_the_count_sees_every_operation_but_detach() -> None:
    """The counter itself: ``a * b + 1`` is two operations, ``detach`` none; forward + backward counts
    the loss and the pullbacks to every floating input (each a leaf that requires grad)."""
    a, b = torch.ones(3), torch.ones(3)
    assert sum(ops.count_forward(lambda x, y: x * y + 1, [a, b]).values()) == 2
    assert sum(ops.count_forward(lambda x: x.detach(), [a]).values()) == 0
    backward = ops.count_backward(lambda x, y: x * y, [a, b])
    assert backward == {
        "aten.mul.Tensor": 3,  # x * y, and the cotangent times y and times x
        "aten.sum.default": 1,  # the loss: the sum of the output (no 0 + sum: one output, no addition)
        "aten.ones_like.default": 1,  # the loss's seed
        "aten.expand.default": 1,  # sum's pullback
    }
