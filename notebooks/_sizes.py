"""What every notebook script shares: which size to run, and where its figure goes."""

from __future__ import annotations

import os
from pathlib import Path


def small_mode() -> bool:
    """``DIFFQUAT_SMALL=1``: the sizes the test suite runs the notebooks with (seconds, not minutes)."""
    return os.environ.get("DIFFQUAT_SMALL") == "1"


def figure_dir() -> Path:
    """Where figures go: ``$DIFFQUAT_FIGURES``, or ``notebooks/figures`` next to this file."""
    out = Path(os.environ.get("DIFFQUAT_FIGURES", Path(__file__).resolve().parent / "figures"))
    out.mkdir(parents=True, exist_ok=True)
    return out
