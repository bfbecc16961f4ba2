"""What the jax backend hands XLA: conversions through a quaternion evaluate each cosine and sine once
per rotation, not once per matrix entry (XLA fuses by recomputation; see ``_core.computed_once``)."""

from __future__ import annotations

import re
from collections.abc import Callable
from typing import Any

import jax
import jax.numpy as jnp
import pytest

import diffquat.jax as dq

CASES: dict[str, tuple[Callable[[Any], Any], int]] = {
    # (function of (N, 3) float32, angles per rotation: the cosines and sines the formula has)
    "axis_angle_to_matrix": (dq.axis_angle_to_matrix, 1),
    "euler_angles_to_matrix-ZYX": (lambda v: dq.euler_angles_to_matrix(v, "ZYX"), 3),
    "euler_angles_to_matrix-xyx": (lambda v: dq.euler_angles_to_matrix(v, "xyx"), 3),
}


@pytest.mark.parametrize("name", list(CASES))
def test_each_cosine_and_sine_is_evaluated_once(name: str) -> None:
    fn, angles = CASES[name]
    hlo = jax.jit(fn).lower(jnp.ones((1024, 3), jnp.float32)).compile().as_text()
    assert hlo is not None
    assert len(re.findall(r" cosine\(", hlo)) == angles
    assert len(re.findall(r" sine\(", hlo)) == angles
