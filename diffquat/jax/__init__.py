"""diffquat on JAX. Same names and semantics as :mod:`diffquat.numpy` and :mod:`diffquat.torch`;
see :mod:`diffquat` for the conventions. Every function is traceable by ``jit``, ``vmap``, ``grad``
and ``jacfwd``/``jacrev``."""

from __future__ import annotations

from typing import Any

import jax
import jax.numpy as jnp
from jax import Array
from jax.typing import ArrayLike

from .. import _core
from .._backend import Backend, documented, shape_tuple

__all__ = [
    "matrix_to_quaternion",
    "normalize_quaternion",
    "quaternion_to_matrix",
    "random_quaternions",
    "standardize_quaternion",
    "wxyz_to_xyzw",
    "xyzw_to_wxyz",
]


def _convert(fname: str, argname: str, x: Any) -> Array:
    return jnp.asarray(x)


_B = Backend(
    xp=jnp,
    convert=_convert,
    is_floating=lambda dtype: bool(jnp.issubdtype(dtype, jnp.floating)),
    astype=lambda x, dtype: x.astype(dtype),
    float32=jnp.dtype(jnp.float32),
)


@documented(_core.quaternion_to_matrix)
def quaternion_to_matrix(q: ArrayLike, *, scalar_first: bool = True) -> Array:
    return _B(_core.quaternion_to_matrix, q, scalar_first=scalar_first)


@documented(_core.matrix_to_quaternion)
def matrix_to_quaternion(matrix: ArrayLike, *, scalar_first: bool = True) -> Array:
    return _B(_core.matrix_to_quaternion, matrix, scalar_first=scalar_first)


@documented(_core.standardize_quaternion)
def standardize_quaternion(q: ArrayLike, *, scalar_first: bool = True) -> Array:
    return _B(_core.standardize_quaternion, q, scalar_first=scalar_first)


@documented(_core.normalize_quaternion)
def normalize_quaternion(q: ArrayLike, *, scalar_first: bool = True) -> Array:
    return _B(_core.normalize_quaternion, q, scalar_first=scalar_first)


@documented(_core.wxyz_to_xyzw)
def wxyz_to_xyzw(q: ArrayLike) -> Array:
    return _B(_core.wxyz_to_xyzw, q)


@documented(_core.xyzw_to_wxyz)
def xyzw_to_wxyz(q: ArrayLike) -> Array:
    return _B(_core.xyzw_to_wxyz, q)


def random_quaternions(
    shape: int | tuple[int, ...] = (),
    *,
    key: Array,
    dtype: Any = None,
    scalar_first: bool = True,
) -> Array:
    """Unit quaternions uniformly distributed over rotations (Shoemake's method), in canonical sign.

    Args:
        shape: batch shape; the result has shape ``(*shape, 4)``.
        key: a ``jax.random`` key (required: JAX has no global random state).
        dtype: floating dtype of the result (default: float64 if x64 is enabled, else float32).
        scalar_first: storage order of the result.
    """
    dtype = jnp.dtype(jax.dtypes.canonicalize_dtype(jnp.float64) if dtype is None else dtype)
    uniform = jax.random.uniform(key, (*shape_tuple(shape), 3), dtype=_B.compute_dtype(dtype))
    return _B(_core.quaternions_from_uniform, uniform, scalar_first=scalar_first).astype(dtype)
