"""Rotation heads for JAX networks, as pure functions of parameters and arrays.

They fit inside any JAX framework: in flax or equinox, let a ``Dense``/``Linear`` layer produce
``representation_size(representation)`` outputs and call ``representation_to_matrix`` on them; or use
``init_rotation_head`` / ``rotation_head``, a linear head whose parameters are a plain dict (a pytree
that optax, ``jax.jit``, ``vmap`` and sharding take as it is)::

    import diffquat.jax as dq
    from diffquat.jax import nn as dqnn

    params = dqnn.init_rotation_head(jax.random.key(0), 128, "6d")
    R = dqnn.rotation_head(params, features, "6d")  # (..., 3, 3)
    loss = dq.matrix_geodesic_distance(R, R_true).mean()

The representations and maps are those of ``diffquat.torch.nn`` (written once, in the core). A
``"fisher"`` head's rotation is the mode of a matrix Fisher distribution; ``representation_to_fisher``
gives its parameter F for the negative log-likelihood::

    raw = features @ params["w"] + params["b"]  # (..., 9)
    loss = dq.matrix_fisher_nll(dqnn.representation_to_fisher(raw), R_true).mean()
"""

from __future__ import annotations

import math
from typing import Any

import jax
import jax.numpy as jnp
from jax import Array
from jax.typing import ArrayLike

import diffquat.jax as _dq

from .. import _heads
from .._public import public_dir as _public_dir
from .._types import Representation

__all__ = [
    "REPRESENTATIONS",
    "init_rotation_head",
    "representation_size",
    "representation_to_fisher",
    "representation_to_matrix",
    "rotation_head",
]
# dir() lists the public API only (see diffquat._public).
__dir__ = _public_dir(globals())

REPRESENTATIONS: tuple[str, ...] = tuple(_heads.REPRESENTATIONS)


def representation_size(representation: Representation) -> int:
    """Number of raw outputs a head of ``representation`` needs (e.g. 6 for ``"6d"``)."""
    return _heads.representation_size(representation)


def representation_to_matrix(raw: ArrayLike, representation: Representation) -> Array:
    """Rotation matrices ``(..., 3, 3)`` from raw outputs ``(..., n)``, ``n = representation_size(...)``.

    Differentiable everywhere the representation is; any raw output gives a rotation (for example a
    zero quaternion gives the identity). Traceable by ``jit``, ``vmap`` and ``grad``.
    """
    return _heads.representation_to_matrix(jnp, _dq, jnp.asarray(raw), representation)


def representation_to_fisher(raw: ArrayLike) -> Array:
    """The matrix Fisher parameter F ``(..., 3, 3)`` of a ``"fisher"`` head's raw outputs ``(..., 9)``,
    row-major: the density ``exp(tr(F^T R)) / c(F)``, whose mode ``matrix_fisher_mode(F)`` is
    ``representation_to_matrix(raw, "fisher")``."""
    return _heads.representation_to_fisher(jnp, jnp.asarray(raw))


def init_rotation_head(
    key: Array, in_features: int, representation: Representation, *, dtype: Any = None
) -> dict[str, Array]:
    """Parameters ``{"w": (in_features, n), "b": (n,)}`` of a linear rotation head, initialised as
    ``torch.nn.Linear`` is (uniform in +-1/sqrt(in_features)), so both backends start alike."""
    dtype = jnp.dtype(jax.dtypes.canonicalize_dtype(jnp.float64) if dtype is None else dtype)
    n = representation_size(representation)
    bound = 1.0 / math.sqrt(in_features)
    kw, kb = jax.random.split(key)
    return {
        "w": jax.random.uniform(kw, (in_features, n), dtype, -bound, bound),
        "b": jax.random.uniform(kb, (n,), dtype, -bound, bound),
    }


def rotation_head(params: dict[str, Array], features: ArrayLike, representation: Representation) -> Array:
    """``representation_to_matrix(features @ w + b)``: features ``(..., in_features)`` to ``(..., 3, 3)``."""
    x = jnp.asarray(features)
    # The bias is broadcast explicitly: diffquat works under jax_numpy_rank_promotion="raise".
    bias = jnp.reshape(params["b"], (1,) * (x.ndim - 1) + params["b"].shape)
    return representation_to_matrix(x @ params["w"] + bias, representation)
