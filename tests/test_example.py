"""The training example of the README's main job fits the known rotation, identically on both backends."""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "notebooks"))

from fit_orientation import angle_error_deg, fit_jax, fit_torch, make_problem


def test_gradient_descent_recovers_the_rotation_on_torch_and_jax() -> None:
    problem = make_problem(n_points=200, seed=1)
    start_error = angle_error_deg(problem.start, problem.true_quaternion)
    q_torch = fit_torch(problem, steps=200)
    q_jax = fit_jax(problem, steps=200)
    assert start_error > 10
    assert angle_error_deg(q_torch, problem.true_quaternion) < 0.5
    np.testing.assert_allclose(q_jax, q_torch, rtol=1e-9, atol=1e-9)


def test_gradient_descent_from_179_degrees_away() -> None:
    problem = make_problem(n_points=200, seed=2, start_angle_deg=179.0)
    assert abs(angle_error_deg(problem.start, problem.true_quaternion) - 179.0) < 1e-6
    assert angle_error_deg(fit_torch(problem, steps=300), problem.true_quaternion) < 0.5
