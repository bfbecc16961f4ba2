"""The array namespace the core runs on in the jax backend."""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

import jax
import jax.numpy as jnp


def _repeat(count: int, step: Callable[[Any], Any], state: Any) -> Any:
    return jax.lax.fori_loop(0, count, lambda _, s: step(s), state)


class _Namespace:
    """``jax.numpy``, with XLA's ``optimization_barrier``, which :func:`diffquat._core.computed_once`
    uses to keep a value that many outputs share from being recomputed in each of them,
    ``stop_gradient`` (:func:`diffquat._core.cancelling_factor`), and
    ``diffquat_repeat`` (a fixed number of steps as one loop, see :func:`diffquat._statistics.repeat`),
    and ``erf`` (which ``jax.numpy`` does not have; ``torch.erf`` is torch's)."""

    optimization_barrier = staticmethod(jax.lax.optimization_barrier)
    stop_gradient = staticmethod(jax.lax.stop_gradient)
    diffquat_repeat = staticmethod(_repeat)
    erf = staticmethod(jax.lax.erf)

    def __getattr__(self, name: str) -> Any:
        return getattr(jnp, name)


XP: Any = _Namespace()
