"""Execute notebooks top to bottom, headless, and write their outputs in place (or only check them).

    python notebooks/execute.py                       # every notebook, full size, outputs saved
    DIFFQUAT_SMALL=1 python notebooks/execute.py --check   # small size, nothing written

The committed notebooks hold the outputs of a full-size run made this way. The test suite executes each
notebook at the small size with ``execute`` below.
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

import nbformat
from nbclient import NotebookClient

HERE = Path(__file__).resolve().parent
NOTEBOOKS = (
    "fit_orientation",
    "pose_regression",
    "robot_orientation",
    "orientation_on_manifold",
    "probabilistic_pose",
    "rotation_diffusion",
    "pose_refinement",
    "trajectory",
)


def execute(name: str, timeout: int = 900) -> nbformat.NotebookNode:
    """Run ``notebooks/<name>.ipynb`` in a fresh kernel (working directory ``notebooks/``, environment
    inherited: ``DIFFQUAT_SMALL``, ``DIFFQUAT_FIGURES``); raises ``CellExecutionError`` on any error."""
    book = nbformat.read(HERE / f"{name}.ipynb", as_version=4)
    client = NotebookClient(
        book,
        timeout=timeout,
        kernel_name="python3",
        resources={"metadata": {"path": str(HERE)}},
        # One stream output per cell, with progress-bar redraws (carriage returns) collapsed.
        coalesce_streams=True,
    )
    client.execute()
    return book


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("names", nargs="*", default=list(NOTEBOOKS))
    parser.add_argument("--check", action="store_true", help="execute only; do not write the outputs")
    args = parser.parse_args()
    for name in args.names:
        start = time.perf_counter()
        book = execute(name)
        if not args.check:
            nbformat.write(book, HERE / f"{name}.ipynb")
        print(f"{name}: executed in {time.perf_counter() - start:.0f} s")


if __name__ == "__main__":
    main()
