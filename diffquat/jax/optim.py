"""Riemannian optimisers on SO(3) and SE(3) for JAX, as optax ``GradientTransformation`` s, with the
retraction that applies their updates.

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

**Leaves.** With ``manifold="so3"`` (the default) every leaf the transformations see is an array of
rotations, told apart by its trailing shape: a shape ending in ``(3, 3)`` holds rotation matrices, any
other shape ending in ``4`` holds unit quaternions, in the order given as ``scalar_first`` (``True``: w,
x, y, z; ``False``: x, y, z, w), to the transformation and to ``apply_updates`` alike, with no default: a
quaternion leaf without it raises ``ValueError`` (a default in one of the two let them disagree
silently); any other shape raises ``ValueError`` naming the leaf. With ``manifold="se3"`` every leaf is
an array of rigid transforms ``(..., 4, 4)`` (``[[R, t], [0, 1]]``), whose updates are body twists
``(rho, phi)`` ``(..., 6)``, translation first: a ``(..., 4, 4)`` leaf is quaternions under ``"so3"``, so
the manifold is never guessed from the shape. For a pytree of rotations, poses and ordinary arrays, label
the leaves and use ``optax.multi_transform``::

    optimizer = optax.multi_transform(
        {"so3": dqo.riemannian_adam(1e-2), "se3": dqo.riemannian_adam(1e-2, manifold="se3"),
         "euclidean": optax.adam(1e-3)},
        {"R": "so3", "T": "se3", "net": "euclidean"},  # or a function of the params giving such a tree
    )

and apply the updates with ``apply_updates``, which tells the leaves apart by the update's shape:
a tangent update ``(..., 3)`` of a ``(..., 3, 3)`` or ``(..., 4)`` leaf, or ``(..., 6)`` of a ``(..., 4,
4)`` leaf, is a step along the manifold, an update of the leaf's own shape is added
(``optax.apply_updates``).

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

Poses (``manifold="se3"``) take the steps of ``diffquat.torch.optim``'s ``"se3"`` groups: the tangent
gradient ``(R^T G_t, vee(R^T G_R - G_R^T R))``, moments whose translation part is kept in the world
frame (its parallel transport in ``R^3 x SO(3)`` is then the identity; this needs the params in
``update``, as ``project_to_tangent`` does), Adam's second moment one number per part (translation,
rotation), and the retraction ``T exp(d)`` (``se3_plus``' value, bottom row exact).

Everything works under ``jit`` and ``vmap``, on any pytree, with learning-rate schedules (optax's
``ScalarOrSchedule``). The updates are tangent vectors, not of the params' shapes: optax wrappers
that map updates to updates of their own shape compose (``MultiSteps``, ``clip_by_global_norm``,
``masked``, ...); ``optax.apply_if_finite`` composes around the tangent part (``chain(project_to_tangent(),
apply_if_finite(chain(scale_by_riemannian_adam(), scale_by_learning_rate(lr)), k))``), not around
``riemannian_adam`` itself (its rejected step has the gradients' shapes); docs/optimisation.md lists them.
"""

from __future__ import annotations

import math
from typing import Any, NamedTuple

import jax
import jax.numpy as jnp
import optax
from jax import Array

import diffquat.jax as _dq

from .. import _optim
from .._public import public_dir as _public_dir

__all__ = [
    "MANIFOLDS",
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
    moment ``(..., 3)``, the second ``(..., 1)`` and (amsgrad) its maximum ``(..., 1)``, else None
    (per pose leaf ``(..., 6)``, the translation part in the world frame, and ``(..., 2)``)."""

    # ``count``, as in optax's own states, where tools look the step count up by that name (it shadows
    # tuple.count, as there).
    count: Array  # type: ignore[assignment]
    mu: optax.Updates
    nu: optax.Updates
    nu_max: optax.Updates


class RiemannianMomentumState(NamedTuple):
    """State of ``riemannian_momentum``: the step count, and per rotation leaf the momentum buffer
    ``(..., 3)`` at the current rotation (per pose leaf ``(..., 6)``, the translation part in the world
    frame; None without momentum)."""

    count: Array  # type: ignore[assignment]  # optax's name (see ScaleByRiemannianAdamState)
    trace: optax.Updates


MANIFOLDS = ("so3", "se3")
"""The manifolds of the transformations' ``manifold`` argument: rotations, rigid transforms."""


def _check_manifold(fname: str, manifold: str, length_scale: float = 1.0) -> None:
    if not (length_scale > 0.0 and math.isfinite(length_scale)) or (
        manifold != "se3" and length_scale != 1.0
    ):
        raise ValueError(
            f"{fname}: length_scale={length_scale} with manifold={manifold!r}; expected a positive finite "
            "length, with manifold 'se3' only (the translation that counts as one radian)"
        )
    if manifold not in MANIFOLDS:
        raise ValueError(
            f"{fname}: manifold={manifold!r}; expected 'so3' (rotations) or 'se3' (rigid transforms); give "
            "ordinary arrays an optax transformation of their own with optax.multi_transform"
        )


def _kind(fname: str, path: Any, shape: tuple[int, ...], manifold: str) -> str:
    kind = _optim.parameter_kind(shape, manifold)
    if kind is None and manifold == "se3":
        raise ValueError(
            f"{fname}: leaf {jax.tree_util.keystr(path)} has shape {shape}; expected rigid transforms "
            "(..., 4, 4) (manifold 'se3'; for a pytree with other arrays, give those another "
            "transformation with optax.multi_transform)"
        )
    if kind is None:
        raise ValueError(
            f"{fname}: leaf {jax.tree_util.keystr(path)} has shape {shape}; expected rotation matrices "
            "(..., 3, 3) or quaternions (..., 4), told apart by the trailing shape (for a pytree with "
            "other arrays, give those another transformation with optax.multi_transform)"
        )
    return kind


def _order(fname: str, path: Any, scalar_first: bool | None) -> bool:
    """The storage order of a quaternion leaf: it has no default, so that the transformation's
    projection and ``apply_updates``' retraction are never left to disagree (one given, one not)."""
    if scalar_first is None:
        raise ValueError(
            f"{fname}: leaf {jax.tree_util.keystr(path)} holds quaternions (..., 4): give scalar_first= "
            "(True: w, x, y, z; False: x, y, z, w), the same to the transformation (riemannian_adam, "
            "riemannian_sgd, project_to_tangent) and to apply_updates; the order has no default there"
        )
    return scalar_first


def _tangent_zeros(fname: str, params: optax.Params, manifold: str, second: bool = False) -> optax.Updates:
    """Zeros of each leaf's dtype, the shape of its tangent vectors (``second``: of Adam's second
    moments, ``(*batch, 1)`` per rotation, ``(*batch, 2)`` per pose)."""

    def zeros(path: Any, p: Array) -> Array:
        shape = tuple(p.shape)
        kind = _kind(fname, path, shape, manifold)
        tangent = _optim.tangent_shape(shape, kind)
        return jnp.zeros((*tangent[:-1], _optim.second_moment_size(kind)) if second else tangent, p.dtype)

    return jax.tree_util.tree_map_with_path(zeros, params)


def _check_tangent(fname: str, updates: optax.Updates, moments: optax.Updates | None, manifold: str) -> None:
    """Tangent vectors ``(..., 3)`` (``(..., 6)`` on SE(3)), of the moments' shapes where there are
    moments (the shapes that ``init`` gave them from the leaves)."""
    size = 6 if manifold == "se3" else 3
    shapes = None if moments is None else [tuple(m.shape) for m in jax.tree.leaves(moments)]
    for k, (path, u) in enumerate(jax.tree_util.tree_leaves_with_path(updates)):
        expected = f"(..., {size})" if shapes is None or k >= len(shapes) else str(shapes[k])
        if u.ndim == 0 or u.shape[-1] != size or (shapes is not None and tuple(u.shape) != shapes[k]):
            raise ValueError(
                f"{fname}: update {jax.tree_util.keystr(path)} has shape {tuple(u.shape)}; expected tangent "
                f"vectors {expected} (put project_to_tangent() before it)"
            )


def _poses(fname: str, params: optax.Params | None, tree: Any, manifold: str) -> list[Array | None]:
    """Per leaf of the updates (of structure ``tree``), its pose on SE(3) (the params' leaf), else
    None: the pose's rotation takes its moments between the body and the world frame."""
    if manifold != "se3":
        return [None] * tree.num_leaves
    if params is None:
        raise ValueError(f"{fname}: needs the params on SE(3): optimizer.update(grads, state, params)")
    return [jnp.asarray(p) for p in tree.flatten_up_to(params)]


def project_to_tangent(
    *, scalar_first: bool | None = None, manifold: str = "so3"
) -> optax.GradientTransformation:
    """Euclidean gradients of rotation leaves to tangent vectors ``(..., 3)``, the gradient of
    ``w -> f(R exp(w))`` (``f(q exp(w))``) at ``w = 0``: ``vee(R^T G - G^T R)`` for matrices ``(..., 3,
    3)``, ``vec(q* G) / 2`` for quaternions ``(..., 4)`` (exact for unit ``q``, and for any ``q`` under a
    loss of the rotation only). With ``manifold="se3"``, of pose leaves ``(..., 4, 4)`` to body twists
    ``(..., 6)``, the gradient of ``w -> f(T exp(w))``: ``(R^T G_t, vee(R^T G_R - G_R^T R))``. Needs
    ``params`` in ``update``. Stateless.

    Args:
        scalar_first: storage order of quaternion leaves, required where there are any (the same as
            ``apply_updates``'); matrix and pose leaves need none.
        manifold: ``"so3"`` (rotations) or ``"se3"`` (rigid transforms).
    """
    return _project("project_to_tangent", scalar_first, manifold)


def _project(name: str, scalar_first: bool | None, manifold: str) -> optax.GradientTransformation:
    """``project_to_tangent``, its refusals naming ``name``."""
    _check_manifold(name, manifold)

    def update(
        updates: optax.Updates, state: optax.EmptyState, params: optax.Params | None = None
    ) -> tuple[optax.Updates, optax.EmptyState]:
        if params is None:
            raise ValueError(f"{name}: needs the params: optimizer.update(grads, state, params)")

        def one(path: Any, g: Array, p: Array) -> Array:
            kind = _kind(name, path, tuple(p.shape), manifold)
            order = _order(name, path, scalar_first) if kind == _optim.QUATERNION else True
            return _optim.tangent_gradient(jnp, p, g, kind, order)

        return jax.tree_util.tree_map_with_path(one, updates, params), state

    return optax.GradientTransformation(lambda params: optax.EmptyState(), update)


def scale_by_riemannian_adam(
    b1: float = 0.9,
    b2: float = 0.999,
    eps: float = 1e-8,
    *,
    amsgrad: bool = False,
    manifold: str = "so3",
    length_scale: float = 1.0,
) -> optax.GradientTransformation:
    """Adam's direction ``m_hat / (sqrt(v_hat) + eps)`` from tangent gradients ``(..., 3)`` (after
    ``project_to_tangent``), the step of ``diffquat.torch.optim.RiemannianAdam``.

    The first moment is a tangent vector, the second one number per rotation (``|g|^2`` averaged): a
    rotation of the body frame leaves it unchanged, and the direction is along the first moment, so
    the parallel transport of the moment along the step (``exp(-d / 2) m``, ``d`` along ``m``) leaves
    its body coordinates as they are: kept as they are, they are transported. (Followed by a
    transformation that turns the direction, they are still carried by a rotation-invariant
    transport, that of the body frame.)

    On SE(3) (``manifold="se3"``; twists ``(..., 6)`` of pose leaves ``(..., 4, 4)``) the first moment
    keeps its translation part in the world frame, where its transport is the identity, and the
    second moment is one number per part, translation and rotation; ``update`` then needs the params,
    to turn the direction back into the body frame.

    Args:
        b1: decay rate of the first moment.
        b2: decay rate of the second moment.
        eps: added to the square root of the second moment.
        amsgrad: keep the maximum of the second moment.
        manifold: ``"so3"`` (rotations) or ``"se3"`` (rigid transforms).
        length_scale: on SE(3), the translation that counts as one radian, in the translation's units (the
            metric ``|rho / s|^2 + |phi|^2``; Adam's step then moves a translation by about
            ``length_scale`` times the learning rate). Changing the units of length and ``length_scale``
            with them leaves every step the same.
    """
    name = "scale_by_riemannian_adam"
    _check_manifold(name, manifold, length_scale)

    def init(params: optax.Params) -> ScaleByRiemannianAdamState:
        nu = _tangent_zeros(name, params, manifold, second=True)
        return ScaleByRiemannianAdamState(
            jnp.zeros([], jnp.int32), _tangent_zeros(name, params, manifold), nu, nu if amsgrad else None
        )

    def update(
        updates: optax.Updates, state: ScaleByRiemannianAdamState, params: optax.Params | None = None
    ) -> tuple[optax.Updates, ScaleByRiemannianAdamState]:
        _check_tangent(name, updates, state.mu, manifold)
        count = optax.safe_increment(state.count)
        # The moments have the structure of the updates (one leaf per rotation leaf, in order).
        leaves, tree = jax.tree.flatten(updates)
        mus, nus = jax.tree.leaves(state.mu), jax.tree.leaves(state.nu)
        maxima = jax.tree.leaves(state.nu_max) if amsgrad else [None] * len(leaves)
        poses = _poses(name, params, tree, manifold)
        out = [
            _optim.adam(jnp, g, m, v, vm, count.astype(g.dtype), (b1, b2), eps, amsgrad, True)
            if pose is None
            else _optim.pose_adam(
                jnp, pose, g, m, v, vm, count.astype(g.dtype), (b1, b2), eps, amsgrad, length_scale
            )
            for g, m, v, vm, pose in zip(leaves, mus, nus, maxima, poses, strict=True)
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
    manifold: str = "so3",
    length_scale: float = 1.0,
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
        manifold: ``"so3"`` (rotations) or ``"se3"`` (rigid transforms: the buffer's translation part is
            kept in the world frame, transported by the identity; ``update`` then needs the params).
        length_scale: on SE(3), the translation that counts as one radian, in the translation's units (the
            metric ``|rho / s|^2 + |phi|^2``; the gradient's translation part is then ``s^2 g_rho``).
    """
    name = "riemannian_momentum"
    _check_manifold(name, manifold, length_scale)
    if nesterov and (momentum <= 0 or dampening != 0):
        raise ValueError("riemannian_momentum: Nesterov momentum requires a momentum and zero dampening")

    def init(params: optax.Params) -> RiemannianMomentumState:
        trace = _tangent_zeros(name, params, manifold) if momentum else None
        return RiemannianMomentumState(jnp.zeros([], jnp.int32), trace)

    def update(
        updates: optax.Updates, state: RiemannianMomentumState, params: optax.Params | None = None
    ) -> tuple[optax.Updates, RiemannianMomentumState]:
        _check_tangent(name, updates, state.trace, manifold)
        lr = learning_rate(state.count) if callable(learning_rate) else learning_rate
        count = optax.safe_increment(state.count)
        if not momentum:
            steps = jax.tree.map(lambda g: -lr * _optim.scale_translation(jnp, g, length_scale**2), updates)
            return steps, RiemannianMomentumState(count, None)
        leaves, tree = jax.tree.flatten(updates)
        first = state.count == 0
        options = (lr, momentum, dampening, nesterov)
        out = [
            _optim.momentum(jnp, g, b, first, *options, True)
            if pose is None
            else _optim.pose_momentum(jnp, pose, g, b, first, *options, length_scale)
            for g, b, pose in zip(
                leaves, jax.tree.leaves(state.trace), _poses(name, params, tree, manifold), strict=True
            )
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
    scalar_first: bool | None = None,
    manifold: str = "so3",
    length_scale: float = 1.0,
) -> optax.GradientTransformation:
    """Adam on SO(3) (or SE(3)): ``optax.chain(project_to_tangent(), scale_by_riemannian_adam(...),
    optax.scale_by_learning_rate(learning_rate))``; the same steps as
    ``diffquat.torch.optim.RiemannianAdam``. A step turns a rotation by about ``learning_rate``
    radians while the gradient is steady (and moves a pose's translation by about as much, in its
    units). Apply the updates with ``apply_updates``.

    Args:
        learning_rate: a number or a schedule of the step count.
        b1: decay rate of the first moment.
        b2: decay rate of the second moment.
        eps: added to the square root of the second moment.
        amsgrad: keep the maximum of the second moment.
        scalar_first: storage order of quaternion leaves, required where there are any (the same as
            ``apply_updates``'; a quaternion leaf without it raises ``ValueError`` at ``update``).
        manifold: ``"so3"`` (rotations) or ``"se3"`` (rigid transforms ``(..., 4, 4)``).
        length_scale: on SE(3), the translation that counts as one radian, in the translation's units (the
            metric ``|rho / s|^2 + |phi|^2``; Adam's step then moves a translation by about
            ``length_scale`` times the learning rate). Changing the units of length and ``length_scale``
            with them leaves every step the same.
    """
    _check_manifold("riemannian_adam", manifold, length_scale)
    return optax.chain(
        _project("riemannian_adam", scalar_first, manifold),
        scale_by_riemannian_adam(b1, b2, eps, amsgrad=amsgrad, manifold=manifold, length_scale=length_scale),
        optax.scale_by_learning_rate(learning_rate),
    )


def riemannian_sgd(
    learning_rate: optax.ScalarOrSchedule,
    momentum: float = 0.0,
    *,
    dampening: float = 0.0,
    nesterov: bool = False,
    scalar_first: bool | None = None,
    manifold: str = "so3",
    length_scale: float = 1.0,
) -> optax.GradientTransformation:
    """SGD on SO(3) (or SE(3)) with momentum: ``optax.chain(project_to_tangent(), riemannian_momentum(...))``;
    the same steps as ``diffquat.torch.optim.RiemannianSGD``. Apply the updates with
    ``apply_updates``.

    Args:
        learning_rate: a number or a schedule of the step count.
        momentum: the momentum factor (0: plain gradient steps).
        dampening: dampening of the gradient's share in the momentum.
        nesterov: Nesterov momentum.
        scalar_first: storage order of quaternion leaves, required where there are any (the same as
            ``apply_updates``'; a quaternion leaf without it raises ``ValueError`` at ``update``).
        manifold: ``"so3"`` (rotations) or ``"se3"`` (rigid transforms ``(..., 4, 4)``).
        length_scale: on SE(3), the translation that counts as one radian, in the translation's units (the
            metric ``|rho / s|^2 + |phi|^2``; the gradient's translation part is then ``s^2 g_rho``).
    """
    _check_manifold("riemannian_sgd", manifold, length_scale)
    return optax.chain(
        _project("riemannian_sgd", scalar_first, manifold),
        riemannian_momentum(
            learning_rate,
            momentum,
            dampening=dampening,
            nesterov=nesterov,
            manifold=manifold,
            length_scale=length_scale,
        ),
    )


def apply_updates(
    params: optax.Params, updates: optax.Updates, *, scalar_first: bool | None = None
) -> optax.Params:
    """Apply updates to a pytree of rotations (and ordinary arrays), leaf by leaf, by the update's shape.

    - an update ``(..., 3)`` of a leaf ``(..., 3, 3)`` (the same batch shape): ``R exp(d)``, the
      value of ``so3_plus`` (computed through the quaternion, so the result is orthonormal to a few
      ulps whatever rounding ``R`` carries: parameters do not drift off SO(3));
    - an update ``(..., 3)`` of a leaf ``(..., 4)``: ``quaternion_plus(q, d)``, a unit quaternion;
    - an update ``(..., 6)`` of a leaf ``(..., 4, 4)``: ``se3_plus(T, d)``, ``T exp(d)`` (its rotation
      through the quaternion likewise; bottom row exact);
    - an update of the leaf's own shape: ``p + u`` (``optax.apply_updates``), for ordinary arrays;
    - a None update leaves the leaf as it is; any other pair of shapes raises ``ValueError``.

    The shapes cannot be mistaken for one another: a tangent update never has its rotation leaf's
    shape. Results keep the leaves' dtypes.

    Args:
        params: the pytree of parameters.
        updates: the pytree of updates (the output of an optimizer's ``update``), the same structure.
        scalar_first: storage order of quaternion leaves, required where a quaternion leaf has a
            tangent update (the order given to the transformation: neither has a default, so that
            they cannot disagree silently); matrix, pose and ordinary leaves need none.
    """

    def one(path: Any, p: Any, u: Any) -> Any:
        if u is None:
            return p
        p, u = jnp.asarray(p), jnp.asarray(u)
        shape = tuple(p.shape)
        if tuple(u.shape) == shape:
            return (p + u).astype(p.dtype)
        # A (..., 4, 4) leaf is quaternions or poses; their tangent shapes, (..., 4, 3) and (..., 6), differ.
        kind = _optim.parameter_kind(shape, "se3" if u.ndim and u.shape[-1] == 6 else "so3")
        if kind is None or tuple(u.shape) != _optim.tangent_shape(shape, kind):
            raise ValueError(
                f"apply_updates: leaf {jax.tree_util.keystr(path)} of shape {shape} has an update of shape "
                f"{tuple(u.shape)}; expected the leaf's shape, or tangent vectors (..., 3) of rotation "
                "matrices (..., 3, 3) or quaternions (..., 4), or twists (..., 6) of rigid transforms (..., "
                "4, 4), of the same batch shape"
            )
        order = _order("apply_updates", path, scalar_first) if kind == _optim.QUATERNION else True
        return _optim.retract(_dq, jnp, p, u, kind, order).astype(p.dtype)

    return jax.tree_util.tree_map_with_path(one, params, updates)
