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


@pytest.mark.parametrize("scalar_first", [True, False], ids=["wxyz", "xyzw"])
def test_matrix_to_quaternion_cotangent_is_one_stack(scalar_first: bool) -> None:
    """The reverse-mode program of matrix_to_quaternion assembles the (..., 3, 3) cotangent in one
    stack of the nine entries, not as nine zero-padded copies of the matrix summed (see
    ``_core._tangent_entries``), and the scalar-last result is built in its order, not reindexed."""
    from diffquat.jax._namespace import XP

    def loss(m: Any) -> Any:
        weights = jnp.arange(4.0, dtype=jnp.float32)[None]
        return (dq._M2Q(XP, m, scalar_first=scalar_first) * weights).sum()

    hlo = jax.jit(jax.grad(loss)).lower(jnp.ones((1024, 3, 3), jnp.float32)).compile().as_text()
    assert hlo is not None
    assert not re.findall(r" pad\(", hlo)


@pytest.mark.parametrize("scalar_first", [True, False], ids=["wxyz", "xyzw"])
def test_quaternion_to_matrix_cotangent_is_one_stack(scalar_first: bool) -> None:
    """The reverse-mode program of quaternion_to_matrix assembles the (..., 4) cotangent in one stack
    of the four components, not as four zero-padded copies of the quaternion summed (see
    ``_core.unstack_quaternion``)."""

    def loss(q: Any) -> Any:
        weights = jnp.arange(9.0, dtype=jnp.float32).reshape(1, 3, 3)
        return (dq.quaternion_to_matrix(q, scalar_first=scalar_first) * weights).sum()

    hlo = jax.jit(jax.grad(loss)).lower(jnp.ones((1024, 4), jnp.float32)).compile().as_text()
    assert hlo is not None
    assert not re.findall(r" pad\(", hlo)
