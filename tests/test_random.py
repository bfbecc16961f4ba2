"""random_quaternions: uniform over rotations, canonical, unit, reproducible, on every backend."""

from __future__ import annotations

from typing import Any

import numpy as np
import pytest
from cases import VALUE_TOL
from conftest import Backend
from scipy import stats


def draw(backend: Backend, shape: Any, seed: int, dtype: str = "float64", **kw: Any) -> Any:
    dq, native = backend.module, backend.dtypes[dtype]
    if backend.name == "numpy":
        return dq.random_quaternions(shape, rng=seed, dtype=native, **kw)
    if backend.name == "torch":
        import torch

        return dq.random_quaternions(shape, generator=torch.Generator().manual_seed(seed), dtype=native, **kw)
    import jax

    return dq.random_quaternions(shape, key=jax.random.key(seed), dtype=native, **kw)


@pytest.mark.parametrize("shape", [(), 5, (3, 0), (2, 3)], ids=["scalar", "int", "empty", "2d"])
def test_shape_dtype_unit_and_canonical(backend: Backend, dtype: str, shape: Any) -> None:
    q = draw(backend, shape, seed=0, dtype=dtype)
    expected = (shape,) if isinstance(shape, int) else shape
    assert tuple(q.shape) == (*expected, 4)
    assert q.dtype == backend.dtypes[dtype] or str(q.dtype) == dtype
    values = backend.to_numpy(q)
    assert np.all(np.abs(np.linalg.norm(values, axis=-1) - 1) <= 2 * VALUE_TOL[dtype])
    assert np.all(values[..., 0] >= 0)


def test_same_seed_same_draw_other_seed_other_draw(backend: Backend) -> None:
    a, b, c = (backend.to_numpy(draw(backend, 8, seed)) for seed in (1, 1, 2))
    np.testing.assert_array_equal(a, b)
    assert not np.allclose(a, c)


def test_scalar_last_is_the_reordered_scalar_first(backend: Backend) -> None:
    first = backend.to_numpy(draw(backend, 8, seed=3))
    last = backend.to_numpy(draw(backend, 8, seed=3, scalar_first=False))
    np.testing.assert_array_equal(last[..., [3, 0, 1, 2]], first)


def test_uniform_over_rotations(backend: Backend) -> None:
    """The rotation angle of a uniform rotation has density (1 - cos a) / pi on [0, pi], and the
    rotated x axis is uniform on the sphere (its z coordinate uniform on [-1, 1]). A fixed seed makes
    the Kolmogorov-Smirnov p-values deterministic; a wrong sampler gives p ~ 0 at this size."""
    q = backend.to_numpy(draw(backend, 20000, seed=4))
    angle = 2 * np.arctan2(np.linalg.norm(q[:, 1:], axis=-1), np.abs(q[:, 0]))
    assert stats.kstest(angle, lambda a: (a - np.sin(a)) / np.pi).pvalue > 1e-3
    w, x, y, z = q.T
    rotated_x_z = 2 * (x * z - w * y)
    assert stats.kstest(rotated_x_z, stats.uniform(loc=-1, scale=2).cdf).pvalue > 1e-3
