"""The array namespace the core runs on in the jax backend."""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

import jax
import jax.numpy as jnp

from .._core import sum_of_products


def _repeat(count: int, step: Callable[[Any], Any], state: Any) -> Any:
    return jax.lax.fori_loop(0, count, lambda _, s: step(s), state)


@jax.custom_jvp
def _small_matmul(a: Any, b: Any) -> Any:
    return sum_of_products(a, b)


@_small_matmul.defjvp
def _small_matmul_jvp(primals: tuple[Any, Any], tangents: tuple[Any, Any]) -> tuple[Any, Any]:
    # The value as the broadcast products (XLA:CPU fuses them; a batched dot of 3x3 blocks is a slower
    # loop of its own), the tangent da b + a db as matmuls, whose transposes are matmuls too: reverse
    # mode of the broadcast products reduces over trailing axes of 3 and 4, which XLA:CPU runs slowly
    # (docs/performance.md, Formula shapes, SE(3)).
    (a, b), (da, db) = primals, tangents
    return sum_of_products(a, b), jnp.matmul(da, b) + jnp.matmul(a, db)


class _Namespace:
    """``jax.numpy``, with XLA's ``optimization_barrier``, which :func:`diffquat._core.computed_once`
    uses to keep a value that many outputs share from being recomputed in each of them,
    ``stop_gradient`` (:func:`diffquat._core.cancelling_factor`),
    ``diffquat_repeat`` (a fixed number of steps as one loop, see :func:`diffquat._statistics.repeat`),
    ``erf`` (which ``jax.numpy`` does not have; ``torch.erf`` is torch's) and
    ``diffquat_small_matmul`` (:func:`diffquat._core.small_matmul`)."""

    optimization_barrier = staticmethod(jax.lax.optimization_barrier)
    stop_gradient = staticmethod(jax.lax.stop_gradient)
    diffquat_repeat = staticmethod(_repeat)
    erf = staticmethod(jax.lax.erf)
    diffquat_small_matmul = staticmethod(_small_matmul)

    def __getattr__(self, name: str) -> Any:
        return getattr(jnp, name)


XP: Any = _Namespace()
