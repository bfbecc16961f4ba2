"""The notebooks run top to bottom, headless, at the small size (``DIFFQUAT_SMALL=1``); the committed
notebooks hold the outputs and figures of a full-size run."""

from __future__ import annotations

import sys
from pathlib import Path

import nbformat
import pytest

NOTEBOOK_DIR = Path(__file__).resolve().parents[1] / "notebooks"
sys.path.insert(0, str(NOTEBOOK_DIR))

from execute import NOTEBOOKS, execute  # noqa: E402


def text_outputs(book: nbformat.NotebookNode) -> str:
    return "\n".join(
        out.get("text", "") + str(out.get("data", {}).get("text/plain", ""))
        for cell in book.cells
        if cell.cell_type == "code"
        for out in cell.outputs
    )


@pytest.mark.parametrize("name", NOTEBOOKS)
def test_notebook_runs_top_to_bottom_at_the_small_size(
    name: str, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    monkeypatch.setenv("DIFFQUAT_SMALL", "1")
    monkeypatch.setenv("DIFFQUAT_FIGURES", str(tmp_path))  # not over the committed figures
    book = execute(name, timeout=600)
    assert "size: small" in text_outputs(book)
    assert [p.name for p in tmp_path.glob("*.png")] == [f"{name}.png"]


@pytest.mark.parametrize("name", NOTEBOOKS)
def test_committed_notebook_holds_the_outputs_of_a_full_size_run(name: str) -> None:
    book = nbformat.read(NOTEBOOK_DIR / f"{name}.ipynb", as_version=4)
    code = [cell for cell in book.cells if cell.cell_type == "code"]
    # Executed top to bottom in one kernel session: execution counts 1, 2, 3, ... in order.
    assert [cell.execution_count for cell in code] == list(range(1, len(code) + 1))
    outputs = [out for cell in code for out in cell.outputs]
    assert not [out for out in outputs if out.output_type == "error"]
    assert "size: full" in text_outputs(book)
    assert any("image/png" in out.get("data", {}) for out in outputs)
    figure = NOTEBOOK_DIR / "figures" / f"{name}.png"
    assert figure.stat().st_size < 150_000, "keep committed figures small"


def test_readme_links_every_notebook_and_its_figure() -> None:
    readme = (NOTEBOOK_DIR.parent / "README.md").read_text()
    for name in NOTEBOOKS:
        assert f"(notebooks/{name}.ipynb)" in readme
        assert f"(notebooks/figures/{name}.png)" in readme
