"""The array namespace the core runs on in the jax backend."""

from __future__ import annotations

from typing import Any

import jax
import jax.numpy as jnp


class _Namespace:
    """``jax.numpy``, with XLA's ``optimization_barrier``, which :func:`diffquat._core.computed_once`
    uses to keep a value that many outputs share from being recomputed in each of them."""

    optimization_barrier = staticmethod(jax.lax.optimization_barrier)

    def __getattr__(self, name: str) -> Any:
        return getattr(jnp, name)


XP: Any = _Namespace()
