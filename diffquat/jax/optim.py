"""Riemannian optimisers on SO(3) for JAX, as optax ``GradientTransformation`` s, with the retraction
that applies their updates.

    import optax
    import diffquat.jax as dq
    from diffquat.jax import optim as dqo

    params = {"R": dq.quaternion_to_matrix(dq.random_quaternions((1000,), key=key))}  # (1000, 3, 3)
    optimizer = dqo.riemannian_adam(1e-2)
    state = optimizer.init(params)

    @jax.jit
    def step(params, state):
        grads = jax.grad(loss)(params)
        updates, state = optimizer.update(grads, state, params)  # tangent vectors (..., 3)
        return dqo.apply_updates(params, updates), state  # R <- R exp(update): still rotations

**Leaves.** Every leaf the transformations see is an array of rotations, told apart by its trailing
shape: a shape ending in ``(3, 3)`` holds rotation matrices, any other shape ending in ``4`` holds unit
quaternions (``scalar_first`` order, ``True`` by default: w, x, y, z); any other shape raises
``ValueError`` naming the leaf. For a pytree of rotations and ordinary arrays, label the leaves and
use ``optax.multi_transform``::

    optimizer = optax.multi_transform(
        {"so3": dqo.riemannian_adam(1e-2), "euclidean": optax.adam(1e-3)},
        {"R": "so3", "net": "euclidean"},  # or a function of the params giving such a tree
    )

and apply the updates with ``apply_updates``, which tells the leaves apart by the update's shape:
a tangent update ``(..., 3)`` of a ``(..., 3, 3)`` or ``(..., 4)`` leaf is a step along the manifold,
an update of the leaf's own shape is added (``optax.apply_updates``).

**The math** (derived in ``diffquat._optim``, the same as ``diffquat.torch.optim``'s, so that the
torch and jax optimisers take the same steps). Updates are body-frame rotation vectors ``w`` ``(...,
3)``, the direction of ``R exp(w)``, whose length is an angle in radians. ``project_to_tangent``
takes the Euclidean gradient ``G`` to the derivative of ``w -> f(R exp(w))`` at 0: ``vee(R^T G - G^T R)``
for matrices, ``vec(q* G) / 2`` for quaternions. ``scale_by_riemannian_adam`` keeps Adam's moments
as tangent vectors, the second moment one number per rotation (``|g|^2`` averaged), so that its
direction is along the first moment and the moments' body coordinates are their own parallel
transport. ``riemannian_momentum`` keeps a momentum buffer and transports it along each step
(``v -> exp(-d / 2) v``). ``apply_updates`` retracts with the exponential map, ``R exp(d)`` /
``q exp(d)``, through the quaternion, so parameters stay orthonormal (unit) to a few ulps.

Everything works under ``jit`` and ``vmap``, on any pytree, with learning-rate schedules (optax's
``ScalarOrSchedule``).
"""

from __future__ import annotations

from typing import Any, NamedTuple

import jax
import jax.numpy as jnp
import optax
from jax import Array

import diffquat.jax as _dq

from .. import _optim
from .._public import public_dir as _public_dir

__all__ = [
    "RiemannianMomentumState",
    "ScaleByRiemannianAdamState",
    "apply_updates",
    "project_to_tangent",
    "riemannian_adam",
    "riemannian_momentum",
    "riemannian_sgd",
    "scale_by_riemannian_adam",
]
# dir() lists the public API only (see diffquat._public).
__dir__ = _public_dir(globals())


class ScaleByRiemannianAdamState(NamedTuple):
    """State of ``scale_by_riemannian_adam``: the step count, and per rotation leaf the first
    moment ``(..., 3)``, the second ``(..., 1)`` and (amsgrad) its maximum ``(..., 1)``, else None."""

    # ``count``, as in optax's own states, where tools look the step count up by that name (it shadows
    # tuple.count, as there).
    count: Array  # type: ignore[assignment]
    mu: optax.Updates
    nu: optax.Updates
    nu_max: optax.Updates


class RiemannianMomentumState(NamedTuple):
    """State of ``riemannian_momentum``: the step count, and per rotation leaf the momentum buffer
    ``(..., 3)`` at the current rotation (None without momentum)."""

    count: Array  # type: ignore[assignment]  # optax's name (see ScaleByRiemannianAdamState)
    trace: optax.Updates


def _kind(fname: str, path: Any, shape: tuple[int, ...]) -> str:
    kind = _optim.rotation_kind(shape)
    if kind is None:
        raise ValueError(
            f"{fname}: leaf {jax.tree_util.keystr(path)} has shape {shape}; expected rotation matrices "
            "(..., 3, 3) or quaternions (..., 4), told apart by the trailing shape (for a pytree with "
            "other arrays, give those another transformation with optax.multi_transform)"
        )
    return kind


def _tangent_zeros(fname: str, params: optax.Params, last: int) -> optax.Updates:
    """Zeros ``(*batch, last)`` of each rotation leaf's dtype (``last`` 3 for moments, 1 for second
    moments)."""

    def zeros(path: Any, p: Array) -> Array:
        shape = tuple(p.shape)
        batch = _optim.tangent_shape(shape, _kind(fname, path, shape))[:-1]
        return jnp.zeros((*batch, last), p.dtype)

    return jax.tree_util.tree_map_with_path(zeros, params)


def _check_tangent(fname: str, updates: optax.Updates, moments: optax.Updates | None) -> None:
    """Tangent vectors ``(..., 3)``, of the moments' shapes where there are moments (the shapes that
    ``init`` gave them from the rotation leaves)."""
    shapes = None if moments is None else [tuple(m.shape) for m in jax.tree.leaves(moments)]
    for k, (path, u) in enumerate(jax.tree_util.tree_leaves_with_path(updates)):
        expected = "(..., 3)" if shapes is None or k >= len(shapes) else str(shapes[k])
        if u.ndim == 0 or u.shape[-1] != 3 or (shapes is not None and tuple(u.shape) != shapes[k]):
            raise ValueError(
                f"{fname}: update {jax.tree_util.keystr(path)} has shape {tuple(u.shape)}; expected tangent "
                f"vectors {expected} (put project_to_tangent() before it)"
            )


def project_to_tangent(*, scalar_first: bool = True) -> optax.GradientTransformation:
    """Euclidean gradients of rotation leaves to tangent vectors ``(..., 3)``, the gradient of
    ``w -> f(R exp(w))`` (``f(q exp(w))``) at ``w = 0``: ``vee(R^T G - G^T R)`` for matrices ``(..., 3,
    3)``, ``vec(q* G) / 2`` for quaternions ``(..., 4)`` (exact for unit ``q``, and for any ``q`` under a
    loss of the rotation only). Needs ``params`` in ``update``. Stateless.

    Args:
        scalar_first: storage order of quaternion leaves.
    """

    def update(
        updates: optax.Updates, state: optax.EmptyState, params: optax.Params | None = None
    ) -> tuple[optax.Updates, optax.EmptyState]:
        if params is None:
            raise ValueError("project_to_tangent: needs the params: optimizer.update(grads, state, params)")

        def one(path: Any, g: Array, p: Array) -> Array:
            kind = _kind("project_to_tangent", path, tuple(p.shape))
            return _optim.tangent_gradient(jnp, p, g, kind, scalar_first)

        return jax.tree_util.tree_map_with_path(one, updates, params), state

    return optax.GradientTransformation(lambda params: optax.EmptyState(), update)


def scale_by_riemannian_adam(
    b1: float = 0.9, b2: float = 0.999, eps: float = 1e-8, *, amsgrad: bool = False
) -> optax.GradientTransformation:
    """Adam's direction ``m_hat / (sqrt(v_hat) + eps)`` from tangent gradients ``(..., 3)`` (after
    ``project_to_tangent``), the step of ``diffquat.torch.optim.RiemannianAdam``.

    The first moment is a tangent vector, the second one number per rotation (``|g|^2`` averaged): a
    rotation of the body frame leaves it unchanged, and the direction is along the first moment, so
    the parallel transport of the moment along the step (``exp(-d / 2) m``, ``d`` along ``m``) leaves
    its body coordinates as they are: kept as they are, they are transported. (Followed by a
    transformation that turns the direction, they are still carried by a rotation-invariant
    transport, that of the body frame.)

    Args:
        b1: decay rate of the first moment.
        b2: decay rate of the second moment.
        eps: added to the square root of the second moment.
        amsgrad: keep the maximum of the second moment.
    """

    def init(params: optax.Params) -> ScaleByRiemannianAdamState:
        name = "scale_by_riemannian_adam"
        nu = _tangent_zeros(name, params, 1)
        return ScaleByRiemannianAdamState(
            jnp.zeros([], jnp.int32), _tangent_zeros(name, params, 3), nu, nu if amsgrad else None
        )

    def update(
        updates: optax.Updates, state: ScaleByRiemannianAdamState, params: optax.Params | None = None
    ) -> tuple[optax.Updates, ScaleByRiemannianAdamState]:
        del params
        _check_tangent("scale_by_riemannian_adam", updates, state.mu)
        count = optax.safe_increment(state.count)
        # The moments have the structure of the updates (one leaf per rotation leaf, in order).
        leaves, tree = jax.tree.flatten(updates)
        mus, nus = jax.tree.leaves(state.mu), jax.tree.leaves(state.nu)
        maxima = jax.tree.leaves(state.nu_max) if amsgrad else [None] * len(leaves)
        out = [
            _optim.adam(jnp, g, m, v, vm, count.astype(g.dtype), (b1, b2), eps, amsgrad, True)
            for g, m, v, vm in zip(leaves, mus, nus, maxima, strict=True)
        ]
        direction, mu, nu, nu_max = ([o[k] for o in out] for k in range(4))
        new = ScaleByRiemannianAdamState(
            count,
            jax.tree.unflatten(tree, mu),
            jax.tree.unflatten(tree, nu),
            jax.tree.unflatten(tree, nu_max) if amsgrad else None,
        )
        return jax.tree.unflatten(tree, direction), new

    return optax.GradientTransformation(init, update)


def riemannian_momentum(
    learning_rate: optax.ScalarOrSchedule,
    momentum: float = 0.0,
    *,
    dampening: float = 0.0,
    nesterov: bool = False,
) -> optax.GradientTransformation:
    """SGD's update ``-lr * buffer`` (``torch.optim.SGD``'s momentum rule) from tangent gradients
    ``(..., 3)``, with the buffer carried to the new rotation by parallel transport along the update
    (``exp(-d / 2) buffer``). It includes the learning rate because the transport depends on the
    step's length; its output is the final update, for ``apply_updates``.

    Args:
        learning_rate: a number or a schedule of the step count.
        momentum: momentum factor (0: the update is ``-lr * g``, no state).
        dampening: dampening of the momentum (from the second step on, as torch).
        nesterov: Nesterov momentum (needs ``momentum > 0`` and ``dampening == 0``).
    """
    if nesterov and (momentum <= 0 or dampening != 0):
        raise ValueError("riemannian_momentum: Nesterov momentum requires a momentum and zero dampening")

    def init(params: optax.Params) -> RiemannianMomentumState:
        trace = _tangent_zeros("riemannian_momentum", params, 3) if momentum else None
        return RiemannianMomentumState(jnp.zeros([], jnp.int32), trace)

    def update(
        updates: optax.Updates, state: RiemannianMomentumState, params: optax.Params | None = None
    ) -> tuple[optax.Updates, RiemannianMomentumState]:
        del params
        _check_tangent("riemannian_momentum", updates, state.trace)
        lr = learning_rate(state.count) if callable(learning_rate) else learning_rate
        count = optax.safe_increment(state.count)
        if not momentum:
            return jax.tree.map(lambda g: -lr * g, updates), RiemannianMomentumState(count, None)
        leaves, tree = jax.tree.flatten(updates)
        out = [
            _optim.momentum(jnp, g, b, state.count == 0, lr, momentum, dampening, nesterov, True)
            for g, b in zip(leaves, jax.tree.leaves(state.trace), strict=True)
        ]
        steps, trace = ([o[k] for o in out] for k in range(2))
        new = RiemannianMomentumState(count, jax.tree.unflatten(tree, trace))
        return jax.tree.unflatten(tree, steps), new

    return optax.GradientTransformation(init, update)


def riemannian_adam(
    learning_rate: optax.ScalarOrSchedule,
    b1: float = 0.9,
    b2: float = 0.999,
    eps: float = 1e-8,
    *,
    amsgrad: bool = False,
    scalar_first: bool = True,
) -> optax.GradientTransformation:
    """Adam on SO(3): ``optax.chain(project_to_tangent(), scale_by_riemannian_adam(...),
    optax.scale_by_learning_rate(learning_rate))``; the same steps as
    ``diffquat.torch.optim.RiemannianAdam``. A step turns a rotation by about ``learning_rate``
    radians while the gradient is steady. Apply the updates with ``apply_updates``.

    Args:
        learning_rate: a number or a schedule of the step count.
        b1: decay rate of the first moment.
        b2: decay rate of the second moment.
        eps: added to the square root of the second moment.
        amsgrad: keep the maximum of the second moment.
        scalar_first: storage order of quaternion leaves.
    """
    return optax.chain(
        project_to_tangent(scalar_first=scalar_first),
        scale_by_riemannian_adam(b1, b2, eps, amsgrad=amsgrad),
        optax.scale_by_learning_rate(learning_rate),
    )


def riemannian_sgd(
    learning_rate: optax.ScalarOrSchedule,
    momentum: float = 0.0,
    *,
    dampening: float = 0.0,
    nesterov: bool = False,
    scalar_first: bool = True,
) -> optax.GradientTransformation:
    """SGD on SO(3) with momentum: ``optax.chain(project_to_tangent(), riemannian_momentum(...))``;
    the same steps as ``diffquat.torch.optim.RiemannianSGD``. Apply the updates with
    ``apply_updates``.

    Args:
        learning_rate: a number or a schedule of the step count.
        momentum: the momentum factor (0: plain gradient steps).
        dampening: dampening of the gradient's share in the momentum.
        nesterov: Nesterov momentum.
        scalar_first: storage order of quaternion leaves.
    """
    return optax.chain(
        project_to_tangent(scalar_first=scalar_first),
        riemannian_momentum(learning_rate, momentum, dampening=dampening, nesterov=nesterov),
    )


def apply_updates(params: optax.Params, updates: optax.Updates, *, scalar_first: bool = True) -> optax.Params:
    """Apply updates to a pytree of rotations (and ordinary arrays), leaf by leaf, by the update's shape.

    - an update ``(..., 3)`` of a leaf ``(..., 3, 3)`` (the same batch shape): ``R exp(d)``, the
      value of ``so3_plus`` (computed through the quaternion, so the result is orthonormal to a few
      ulps whatever rounding ``R`` carries: parameters do not drift off SO(3));
    - an update ``(..., 3)`` of a leaf ``(..., 4)``: ``quaternion_plus(q, d)``, a unit quaternion;
    - an update of the leaf's own shape: ``p + u`` (``optax.apply_updates``), for ordinary arrays;
    - a None update leaves the leaf as it is; any other pair of shapes raises ``ValueError``.

    The shapes cannot be mistaken for one another: a tangent update never has its rotation leaf's
    shape. Results keep the leaves' dtypes.

    Args:
        params: the pytree of parameters.
        updates: the pytree of updates (the output of an optimizer's ``update``), the same structure.
        scalar_first: storage order of quaternion leaves.
    """

    def one(path: Any, p: Any, u: Any) -> Any:
        if u is None:
            return p
        p, u = jnp.asarray(p), jnp.asarray(u)
        shape = tuple(p.shape)
        if tuple(u.shape) == shape:
            return (p + u).astype(p.dtype)
        kind = _optim.rotation_kind(shape)
        if kind is None or tuple(u.shape) != _optim.tangent_shape(shape, kind):
            raise ValueError(
                f"apply_updates: leaf {jax.tree_util.keystr(path)} of shape {shape} has an update of shape "
                f"{tuple(u.shape)}; expected the leaf's shape, or tangent vectors (..., 3) of rotation "
                "matrices (..., 3, 3) or quaternions (..., 4) of the same batch shape"
            )
        return _optim.retract(_dq, jnp, p, u, kind, scalar_first).astype(p.dtype)

    return jax.tree_util.tree_map_with_path(one, params, updates)
