"""Riemannian optimisation on SO(3), written once: the tangent-space formulas that the torch optimisers
(:mod:`diffquat.torch.optim`) and the optax transformations (:mod:`diffquat.jax.optim`) share.

Conventions (derived here once; the public docstrings repeat what each needs):

- **Parameters and their trailing shape.** A rotation parameter is an array of rotation matrices
  ``(..., 3, 3)`` or of unit quaternions ``(..., 4)``; the trailing shape tells them apart
  (:func:`rotation_kind`): a shape ending in ``(3, 3)`` holds matrices, any other shape ending in
  ``4`` holds quaternions, and any other shape is not a rotation.
- **Tangent vectors, right-trivialised.** A tangent vector at ``R`` is a rotation vector ``w``
  ``(..., 3)`` in the body frame: the curve ``t -> R exp(t w)`` (``so3_plus(R, t w)``,
  ``quaternion_plus(q, t w)``). Its length ``|w|`` is the angle turned per unit ``t``: the metric is
  the bi-invariant one whose geodesic distance is the rotation angle
  (``matrix_geodesic_distance``).
- **Gradient.** For a loss ``f`` and its Euclidean gradient ``G = df/dR`` (the ``.grad`` of the
  ``(..., 3, 3)`` parameter), the derivative of ``w -> f(R exp(w))`` at ``w = 0`` is, entry ``k``,
  ``<G, R hat(e_k)> = <R^T G, hat(e_k)>``; only the skew part of ``R^T G`` pairs with a skew matrix,
  and ``<hat(a), hat(b)> = 2 a.b``, so the tangent gradient is
  ``g = 2 vee(skew(R^T G)) = vee(R^T G - G^T R)`` (:func:`matrix_tangent_gradient`). For a quaternion
  ``q`` and ``G = df/dq``: ``d/dw (q exp(w))`` at 0 is ``q (0, e_k) / 2`` (``exp(w) = (cos |w|/2,
  sin(|w|/2) w/|w|)``), and left multiplication by ``q`` has the adjoint left multiplication by its
  conjugate, so ``g = vec(q* G) / 2``, the vector part of a Hamilton product
  (:func:`quaternion_tangent_gradient`). Both are exact derivatives of ``f`` along the retraction at
  ``w = 0`` for a unit ``q`` (and for any ``q`` when ``f`` depends on the rotation only, as every loss
  through ``quaternion_to_matrix`` does: ``G`` then scales as ``1/|q|``, which ``q*`` cancels).
- **Parallel transport.** For the bi-invariant metric the Levi-Civita connection of left-invariant
  fields is ``nabla_X Y = [X, Y] / 2``. Along ``R exp(t d)`` a field with body coordinates ``v(t)`` is
  parallel iff ``v' + (d x v) / 2 = 0`` (``[hat a, hat b] = hat(a x b)``), so the transport to
  ``R exp(d)`` is ``v -> exp(-d / 2) v``: the body coordinates turn back by half the step
  (:func:`transport`). The velocity ``d`` itself is carried to itself (geodesics are the curves
  ``R exp(t d)``), and every transport is a rotation, so it keeps lengths and inner products.
- **Retraction.** ``R exp(d)`` and ``q exp(d)`` (``so3_plus``'s and ``quaternion_plus``' values): the
  exponential map, exact (:func:`retract`).

Poses (manifold ``"se3"``): rigid transforms ``T = [[R, t], [0, 1]]`` ``(..., 4, 4)``.

- **Tangent vectors** are body twists ``(rho, phi)`` ``(..., 6)``, translation first, the direction of
  ``T exp(t delta)`` (``se3_plus(T, t delta)``). The metric is that of ``R^3 x SO(3)``:
  ``|delta|^2 = |rho|^2 + |phi|^2``, since along ``T exp(t delta)`` the translation moves at
  ``R rho`` (whose length is ``|rho|``) and the rotation turns at ``phi`` in its body frame. Left
  invariant (a change of world frame keeps every length), in metres and radians: the two parts get
  their own second moments in Adam (below), as their units differ.
- **Gradient.** ``d/dw f(T exp(w))`` at 0 pairs ``G`` (``df/dT``, ``(..., 4, 4)``) with
  ``T hat(w) = [[R hat(phi), R rho], [0, 0]]``: ``<G_t, R rho> + <R^T G_R, hat(phi)>``, so the tangent
  gradient is ``(R^T G_t, vee(R^T G_R - G_R^T R))`` with ``G_R``, ``G_t`` the blocks of ``G``
  (:func:`pose_tangent_gradient`); the bottom row of ``G`` pairs with nothing.
- **Parallel transport** in ``R^3 x SO(3)``: the rotation part as on SO(3), ``exp(-d_phi / 2) v``; the
  translation part is a vector of ``R^3``, parallel when constant in the world frame, where its body
  coordinates turn with the frame. So the optimisers keep the translation part of their moments in
  the world frame, ``R rho`` (:func:`translation_to_world`), where the transport is the identity, and
  take the step back to the body frame with the rotation of the current pose: exact whatever
  transformation follows (a learning rate, a schedule), with nothing stored but the moments.
- **Retraction** ``T exp(d)`` (``se3_plus``' value), the rotation through its quaternion as above:
  ``[[R exp(d_phi), t + R J_l(d_phi) d_rho], [0, 1]]``, bottom row exact (:func:`retract`).
"""

from __future__ import annotations

import math
from typing import Any

from . import _algebra

MATRIX = "matrix"
QUATERNION = "quaternion"
POSE = "pose"


def rotation_kind(shape: tuple[int, ...]) -> str | None:
    """``"matrix"`` for a shape ending in ``(3, 3)``, ``"quaternion"`` for any other shape ending in
    ``4``, ``None`` otherwise (not a rotation). Static: it reads the shape only."""
    if len(shape) >= 2 and shape[-1] == 3 and shape[-2] == 3:
        return MATRIX
    if len(shape) >= 1 and shape[-1] == 4:
        return QUATERNION
    return None


def parameter_kind(shape: tuple[int, ...], manifold: str) -> str | None:
    """The kind of a parameter on ``manifold`` (``"so3"``: :func:`rotation_kind`; ``"se3"``:
    ``"pose"`` for a shape ending in ``(4, 4)``), ``None`` if the shape cannot be one. Static."""
    if manifold == "se3":
        return POSE if len(shape) >= 2 and shape[-2:] == (4, 4) else None
    return rotation_kind(shape)


def tangent_shape(shape: tuple[int, ...], kind: str) -> tuple[int, ...]:
    """Shape of the tangent vectors of a parameter: its batch shape, then 3 (6 for poses)."""
    batch = shape[:-1] if kind == QUATERNION else shape[:-2]
    return (*batch, 6 if kind == POSE else 3)


def second_moment_size(kind: str) -> int:
    """Adam's second moments per rotation (1) or pose (2: translation, rotation)."""
    return 2 if kind == POSE else 1


def matrix_tangent_gradient(xp: Any, matrix: Any, grad: Any) -> Any:
    """``vee(R^T G - G^T R)``, shape ``(..., 3)``: the gradient of ``w -> f(R exp(w))`` at ``w = 0``
    from the Euclidean gradient ``G = df/dR`` ``(..., 3, 3)`` (exact for any ``R``).

    Entry x is ``(R^T G)_21 - (R^T G)_12 = sum_k (G_k1 R_k2 - G_k2 R_k1)``, and so on: the sum over
    the rows ``k`` of ``G_k x R_k``, the cross product of the two matrices' rows. Two whole-array
    operations, where a batched matrix product of 3x3 matrices is slow in eager torch (one small
    product per matrix; docs/performance.md, Formula shapes)."""
    return xp.sum(xp.linalg.cross(grad, matrix), axis=-2)


def quaternion_tangent_gradient(xp: Any, q: Any, grad: Any, scalar_first: bool) -> Any:
    """``vec(q* G) / 2``, shape ``(..., 3)``: the gradient of ``w -> f(q exp(w))`` at ``w = 0`` from
    the Euclidean gradient ``G = df/dq`` ``(..., 4)`` (exact for any ``q``; the retraction normalises
    ``q``, so along it this is exact for unit ``q`` or a loss of the rotation only). With
    ``q = (w, u)`` and ``G = (g_w, g_u)``, the vector part of ``(w, -u) (g_w, g_u)`` is
    ``w g_u - g_w u - u x g_u``."""
    w, u = _parts(q, scalar_first)
    gw, gu = _parts(grad, scalar_first)
    return 0.5 * ((w * gu - gw * u) - xp.linalg.cross(u, gu))


def _parts(q: Any, scalar_first: bool) -> tuple[Any, Any]:
    """The scalar part ``(..., 1)`` and the vector part ``(..., 3)`` of quaternions in either order."""
    return (q[..., :1], q[..., 1:]) if scalar_first else (q[..., 3:], q[..., :3])


def pose_tangent_gradient(xp: Any, pose: Any, grad: Any) -> Any:
    """``(R^T G_t, vee(R^T G_R - G_R^T R))``, shape ``(..., 6)``: the gradient of
    ``w -> f(T exp(w))`` at ``w = 0`` from the Euclidean gradient ``G = df/dT`` ``(..., 4, 4)``
    (see the module)."""
    rotation = pose[..., :3, :3]
    rho = translation_to_body(xp, rotation, grad[..., :3, 3])
    phi = matrix_tangent_gradient(xp, rotation, grad[..., :3, :3])
    return xp.concat([rho, phi], axis=-1)


def translation_to_world(xp: Any, rotation: Any, rho: Any) -> Any:
    """``R rho`` ``(..., 3)``: body coordinates of a translation to world coordinates (sums of
    products, no batched 3x3 product)."""
    return xp.sum(rotation * rho[..., None, :], axis=-1)


def translation_to_body(xp: Any, rotation: Any, v: Any) -> Any:
    """``R^T v`` ``(..., 3)``: world coordinates of a translation to body coordinates."""
    return xp.sum(rotation * v[..., :, None], axis=-2)


def pose_to_world(xp: Any, pose: Any, twist: Any, scale: float = 1.0) -> Any:
    """A body twist ``(rho, phi)`` ``(..., 6)`` with its translation part in world coordinates and
    times ``scale``, ``(scale R rho, phi)``: the form in which the optimisers keep the moments of a pose
    (see the module; ``scale`` is the ``length_scale`` of a gradient, below)."""
    rho = translation_to_world(
        xp, pose[..., :3, :3], twist[..., :3] if scale == 1.0 else scale * twist[..., :3]
    )
    return xp.concat([rho, twist[..., 3:]], axis=-1)


def pose_to_body(xp: Any, pose: Any, twist: Any, scale: float = 1.0) -> Any:
    """The inverse of :func:`pose_to_world` for ``1 / scale``: ``(scale R^T v, phi)``."""
    rho = translation_to_body(xp, pose[..., :3, :3], twist[..., :3])
    return xp.concat([rho if scale == 1.0 else scale * rho, twist[..., 3:]], axis=-1)


def tangent_gradient(xp: Any, param: Any, grad: Any, kind: str, scalar_first: bool) -> Any:
    """The tangent gradient ``(..., 3)`` (poses ``(..., 6)``) of a parameter of any kind (see the
    module)."""
    if kind == MATRIX:
        return matrix_tangent_gradient(xp, param, grad)
    if kind == POSE:
        return pose_tangent_gradient(xp, param, grad)
    return quaternion_tangent_gradient(xp, param, grad, scalar_first)


# The exponential of a rotation vector on (..., 1) scalar and (..., 3) vector parts, for the transport
# of the optimisers' moments: a few whole-array operations, run eagerly on every parameter each step.


def exp_quaternion(xp: Any, delta: Any) -> tuple[Any, Any]:
    """``exp(delta)`` as a unit quaternion ``(cos(t/2), sin(t/2) delta / t)``, ``t = |delta|``: the
    scalar part ``(..., 1)`` and the vector part ``(..., 3)``.

    ``sin(t/2) / t`` is ``sinc(t / (2 pi)) / 2`` (``sinc(x) = sin(pi x) / (pi x)``, 1 at 0), accurate
    to its last bits at every ``t`` (a quotient of a sine and its small argument, no cancellation),
    in fewer operations than a series below a threshold. ``t`` is ``safe_norm``'s: its derivative is 0
    at ``delta = 0``, where the square root's is infinite, so the derivative of the whole, for whoever
    differentiates through an update, is the exact ``(0, I / 2)`` there."""
    t = _algebra.safe_norm(xp, xp.sum(delta * delta, axis=-1, keepdims=True))
    return xp.cos(0.5 * t), (0.5 * xp.sinc(t * (0.5 / math.pi))) * delta


def transport(xp: Any, delta: Any, vector: Any) -> Any:
    """Parallel transport of body-frame tangent vectors from ``R`` to ``R exp(delta)``:
    ``exp(-delta / 2) vector``, shapes ``(..., 3)`` (see the module for the derivation). A rotation of
    ``vector`` (``v + 2 w (u x v) + 2 u x (u x v)`` with ``(w, u)`` the unit quaternion of
    ``-delta / 2``), so lengths are kept; the identity at ``delta = 0``."""
    w, u = exp_quaternion(xp, -0.5 * delta)
    c = xp.linalg.cross(u, vector)
    return vector + 2.0 * (w * c + xp.linalg.cross(u, c))


def retract(dq: Any, xp: Any, param: Any, delta: Any, kind: str, scalar_first: bool) -> Any:
    """``R exp(delta)``, ``q exp(delta)`` or ``T exp(delta)``, with the backend module ``dq`` and its
    namespace ``xp``.

    Matrices go through their quaternion: ``quaternion_to_matrix(q exp(delta))`` with
    ``q = matrix_to_quaternion(R)`` is ``so3_plus(R, delta)`` for a rotation ``R``, and is orthonormal
    to a few ulps whatever rounding ``R`` carries, where ``R @ exp(delta)`` keeps the rounding of every
    earlier step: in float32 its ``|R^T R - I|`` grew to 2e-5 in 1e4 steps (measured), this one stays
    at the first step's few ulps. Quaternions are normalised after each product likewise. A pose's
    rotation goes the same way, and its translation moves by ``R J_l(phi) rho``, the translation of
    ``T exp(delta)`` (``se3_exp``'s): ``se3_plus``' value, bottom row exact."""
    if kind == MATRIX:
        return dq.quaternion_to_matrix(dq.quaternion_plus(dq.matrix_to_quaternion(param), delta))
    if kind == POSE:
        rotation, translation = param[..., :3, :3], param[..., :3, 3]
        rotated = retract(dq, xp, rotation, delta[..., 3:], MATRIX, scalar_first)
        step = translation_to_world(xp, rotation, dq.se3_exp(delta)[..., :3, 3])
        return dq.se3_from_rotation_translation(rotated, translation + step)
    return dq.quaternion_plus(param, delta, scalar_first=scalar_first)


def adam(
    xp: Any,
    grad: Any,
    exp_avg: Any,
    exp_avg_sq: Any,
    max_exp_avg_sq: Any,
    step: Any,
    betas: tuple[float, float],
    eps: float,
    amsgrad: bool,
    tangent: bool,
) -> tuple[Any, Any, Any, Any]:
    """One Adam step: ``(direction, exp_avg, exp_avg_sq, max_exp_avg_sq)``, the update being
    ``-lr * direction`` (the caller multiplies, as ``optax.scale_by_learning_rate`` does).

    ``tangent``: ``grad`` is tangent vectors ``(..., 3)``, and the second moment is one number per
    rotation, ``|g|^2`` averaged, shape ``(..., 1)``: a rotation of the body frame leaves it unchanged
    (an entrywise moment would depend on the frame, and could not be transported), and the update
    ``-lr m_hat / (sqrt(v_hat) + eps)`` is parallel to the first moment ``m``, so that the transport
    of ``m`` along it, ``exp(-update / 2) m``, is ``m`` itself (a rotation about ``m``'s own axis):
    the body coordinates of the moments are their parallel transport, with no arithmetic. The step
    turns each rotation by about ``lr`` radians while the gradient is steady. Otherwise ``grad`` is
    Euclidean and the second moment entrywise (``torch.optim.Adam``, ``optax.adam``).

    ``step`` is the number of this step (1 for the first), a Python int or an array of the moments'
    dtype; ``max_exp_avg_sq`` is ignored (and returned) unless ``amsgrad``."""
    beta1, beta2 = betas
    exp_avg = beta1 * exp_avg + (1.0 - beta1) * grad
    square = xp.sum(grad * grad, axis=-1, keepdims=True) if tangent else grad * grad
    exp_avg_sq = beta2 * exp_avg_sq + (1.0 - beta2) * square
    second = exp_avg_sq
    if amsgrad:
        max_exp_avg_sq = xp.maximum(max_exp_avg_sq, exp_avg_sq)
        second = max_exp_avg_sq
    correction1 = 1.0 - beta1**step
    correction2 = 1.0 - beta2**step
    direction = (exp_avg / correction1) / (xp.sqrt(second / correction2) + eps)
    return direction, exp_avg, exp_avg_sq, max_exp_avg_sq


def momentum(
    xp: Any,
    grad: Any,
    buffer: Any,
    first: Any,
    lr: Any,
    momentum: float,
    dampening: float,
    nesterov: bool,
    tangent: bool,
) -> tuple[Any, Any]:
    """One step of SGD with momentum (``torch.optim.SGD``'s rule): ``(update, buffer)``.

    The buffer is ``grad`` on the first step (``first``: a Python bool or a boolean array), then
    ``momentum * buffer + (1 - dampening) * grad``; the update is ``-lr`` times the buffer, or with
    ``nesterov`` ``-lr (grad + momentum * buffer)``. ``tangent``: the buffer is tangent vectors
    ``(..., 3)``, carried to the new point by :func:`transport` along the update (the identity, up to
    rounding, unless ``nesterov``: the update is then not parallel to the buffer)."""
    mixed = momentum * buffer + (1.0 - dampening) * grad
    # A Python bool (torch's state) selects in Python; an array (jax's count) selects in the program.
    buffer = (grad if first else mixed) if isinstance(first, bool) else xp.where(first, grad, mixed)
    update = -lr * (grad + momentum * buffer if nesterov else buffer)
    if tangent:
        buffer = transport(xp, update, buffer)
    return update, buffer


def _pairs(xp: Any, twist: Any) -> Any:
    """``(..., 6)`` as ``(..., 2, 3)``: a pose's translation and rotation parts."""
    return xp.reshape(twist, (*twist.shape[:-1], 2, 3))


def _joined(xp: Any, pairs: Any) -> Any:
    return xp.reshape(pairs, (*pairs.shape[:-2], 6))


def pose_adam(
    xp: Any,
    pose: Any,
    grad: Any,
    exp_avg: Any,
    exp_avg_sq: Any,
    max_exp_avg_sq: Any,
    step: Any,
    betas: tuple[float, float],
    eps: float,
    amsgrad: bool,
    length_scale: float = 1.0,
) -> tuple[Any, Any, Any, Any]:
    """:func:`adam` for a pose at ``pose`` ``(..., 4, 4)``, from its tangent gradient ``(..., 6)``:
    ``(direction, exp_avg, exp_avg_sq, max_exp_avg_sq)``, the direction a body twist ``(..., 6)``.

    The first moment ``(..., 6)`` keeps its translation part in the world frame (its parallel
    transport is then the identity; see the module), the second moment is one number per part,
    ``(..., 2)``: ``|g_rho|^2`` and ``|g_phi|^2`` averaged, each independent of the frame, and each
    part of the direction is along its part of the first moment (so the rotation part's transport is
    the identity, as on SO(3)). ``max_exp_avg_sq`` is ignored (and returned) unless ``amsgrad``.

    ``length_scale`` ``s``: the metric ``|rho / s|^2 + |phi|^2``, the translation ``s`` counting as one
    radian. Adam runs in the coordinates ``rho / s`` (its gradient is ``s g_rho``), and its step
    ``d`` there is ``s d`` in ``rho``: changing the units of length by a factor and ``s`` with them
    changes nothing else."""
    maximum = max_exp_avg_sq[..., None] if amsgrad else None
    direction, exp_avg, exp_avg_sq, maximum = adam(
        xp,
        _pairs(xp, pose_to_world(xp, pose, grad, length_scale)),
        _pairs(xp, exp_avg),
        exp_avg_sq[..., None],
        maximum,
        step,
        betas,
        eps,
        amsgrad,
        True,
    )
    direction = pose_to_body(xp, pose, _joined(xp, direction), length_scale)
    return direction, _joined(xp, exp_avg), exp_avg_sq[..., 0], maximum[..., 0] if amsgrad else max_exp_avg_sq


def pose_momentum(
    xp: Any,
    pose: Any,
    grad: Any,
    buffer: Any,
    first: Any,
    lr: Any,
    momentum_: float,
    dampening: float,
    nesterov: bool,
    length_scale: float = 1.0,
) -> tuple[Any, Any]:
    """:func:`momentum` for a pose at ``pose`` ``(..., 4, 4)``, from its tangent gradient ``(..., 6)``:
    ``(update, buffer)``, the update a body twist. The buffer keeps its translation part in the world
    frame (transported by the identity) and its rotation part in the body frame, transported along
    the step's rotation as on SO(3). ``length_scale`` as for :func:`pose_adam` (the gradient step in
    ``rho`` is then ``s^2`` times that of the unit metric)."""
    update, buffer = momentum(
        xp,
        pose_to_world(xp, pose, grad, length_scale),
        buffer,
        first,
        lr,
        momentum_,
        dampening,
        nesterov,
        False,
    )
    buffer = xp.concat([buffer[..., :3], transport(xp, update[..., 3:], buffer[..., 3:])], axis=-1)
    return pose_to_body(xp, pose, update, length_scale), buffer


def scale_translation(xp: Any, twist: Any, factor: float) -> Any:
    """``(factor rho, phi)`` for twists ``(..., 6)``: the plain gradient step of a pose under the
    metric of ``length_scale`` ``s`` is ``-lr (s^2 g_rho, g_phi)``."""
    if factor == 1.0:
        return twist
    return xp.concat([factor * twist[..., :3], twist[..., 3:]], axis=-1)
