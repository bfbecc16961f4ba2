"""Riemannian optimisers on SO(3) and SE(3) for PyTorch: drop-in ``torch.optim.Optimizer`` s whose
parameters are rotations or rigid transforms, which stay rotations and rigid transforms.

    import diffquat.torch as dq
    from diffquat.torch.optim import RiemannianAdam

    R = torch.nn.Parameter(dq.quaternion_to_matrix(dq.random_quaternions(1000)))  # (1000, 3, 3)
    optimizer = RiemannianAdam([R], lr=1e-2)
    for _ in range(100):
        optimizer.zero_grad()
        loss(R).backward()
        optimizer.step()  # R <- R exp(d), d in the body frame: R stays in SO(3)

**Which parameters.** A parameter group's ``manifold`` says what its tensors are:

- ``"so3"`` (the default): rotations, told apart by their trailing shape: a shape ending in
  ``(3, 3)`` holds rotation matrices ``(..., 3, 3)``, any other shape ending in ``4`` holds unit
  quaternions ``(..., 4)`` (in the group's ``scalar_first`` order, ``True`` by default: w, x, y, z).
  Any other shape raises ``ValueError``, and so does a tensor that is not a rotation when the group
  is added (``|R^T R - I| > 1e-3`` or ``det R < 0``, ``| |q| - 1 | > 1e-3``; 1e-2 for 16-bit
  dtypes): the optimiser never guesses, so that a network's ``(4,)`` bias passed by mistake is refused
  instead of being turned into a rotation.
- ``"se3"``: rigid transforms ``(..., 4, 4)`` (``[[R, t], [0, 1]]``, column vectors), checked likewise
  when the group is added (``R`` a rotation to 1e-3, bottom row ``(0, 0, 0, 1)`` to 1e-3). Their
  tangent vectors are body twists ``(rho, phi)`` ``(..., 6)``, translation first, and the step is
  ``T <- se3_plus(T, d) = T exp(d)``. A ``(..., 4, 4)`` tensor in a ``"so3"`` group is read as
  quaternions, so poses need their own group: a ``"so3"`` group refuses a tensor of rigid transforms.
- ``"euclidean"``: ordinary tensors of any shape, updated as ``torch.optim.Adam`` / ``torch.optim.SGD``
  update them (weight decay included), so that one optimiser can hold a network and its rotations::

      RiemannianAdam([{"params": [R]}, {"params": net.parameters(), "manifold": "euclidean"}], lr=1e-3)

**The update of a rotation** (the derivations are in ``diffquat._optim``). Tangent vectors are body-frame
rotation vectors ``w`` ``(..., 3)``, the direction of ``R exp(w)``, and ``|w|`` is an angle in radians
(the bi-invariant metric). The Euclidean gradient ``G = p.grad`` is taken to the tangent space as the
derivative of ``w -> f(R exp(w))`` at 0, ``vee(R^T G - G^T R)`` for matrices and ``vec(q* G) / 2`` for
quaternions (the conjugate, then the Hamilton product's vector part); the moments are tangent vectors
at the current rotation, carried to the next by parallel transport (``v -> exp(-d / 2) v`` for a step
``d``); and the step is the exponential map, ``R exp(d)`` / ``q exp(d)`` (the values of ``so3_plus``
and ``quaternion_plus``), computed through the quaternion and normalised, so a parameter stays
orthonormal to a few ulps, however many steps it takes (float32: ``|R^T R - I| <= 1e-5`` after 1e4
steps, tested; 1e-6 measured, where ``R @ exp(d)`` alone drifted to 2e-5) and a quaternion unit. A
quaternion's sign is whatever the product gives (both signs are the same rotation).

**The update of a pose** (``"se3"``): the metric is that of ``R^3 x SO(3)``, ``|rho / s|^2 + |phi|^2``
with ``s`` the group's ``length_scale`` (1 by default: the translation that counts as one radian),
and the tangent gradient of ``G = p.grad`` is ``(R^T G_t, vee(R^T G_R - G_R^T R))`` (its blocks).
The moments keep their translation part in the world frame, where its parallel transport is the
identity, and their rotation part as on SO(3); Adam's second moment is one number per part, so a step
moves the translation by about ``s lr`` (in its units) and turns the rotation by about ``lr`` radians
while the gradient is steady. The step ``T exp(d)`` is ``se3_plus``' value, its rotation computed
through the quaternion: the bottom row stays exact and ``R`` orthonormal (``|R^T R - I| <= 1e-5``
after 1e4 float32 steps, tested).

**Weight decay** (an L2 penalty on the entries) means nothing on a rotation: ``|R|_F^2 = 3`` and
``|q| = 1`` are constant on the manifold, so its gradient has no tangent part (on a pose, it would pull
the translation towards a world origin that the metric does not single out). A ``"so3"`` or ``"se3"``
group with ``weight_decay != 0`` raises ``ValueError``; to pull rotations towards a reference, add
``dq.matrix_geodesic_distance(R, reference) ** 2`` (or another penalty) to the loss.

The optimisers support per-group options (``lr`` and the rest, ``manifold``, ``scalar_first``),
learning-rate schedulers, closures, ``state_dict`` / ``load_state_dict``, and parameters of any batch
shape, dtype and device; not sparse gradients, nor ``foreach``/``fused``/``capturable``.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Iterable
from typing import Any

import torch
from torch import Tensor

import diffquat.torch as _dq

from .. import _optim
from .._public import public_dir as _public_dir

__all__ = ["MANIFOLDS", "RiemannianAdam", "RiemannianSGD"]
# dir() lists the public API only (see diffquat._public).
__dir__ = _public_dir(globals())

MANIFOLDS = ("so3", "se3", "euclidean")
"""The manifolds of a param group's ``manifold``: rotations, rigid transforms, ordinary tensors."""

Params = Iterable[Tensor] | Iterable[dict[str, Any]]


def _is_rotation(param: Tensor, kind: str) -> bool:
    """Whether every rotation (pose) of ``param`` is one, to 1e-3 (1e-2 in 16-bit dtypes):
    ``|R^T R - I|`` and ``det R > 0`` (and a pose's bottom row ``(0, 0, 0, 1)``), or ``| |q| - 1 |``.
    Checked once, when the parameter is added (eager)."""
    x = param.detach()
    tolerance = 1e-2 if x.dtype.itemsize < 4 else 1e-3
    x = x.float() if x.dtype.itemsize < 4 else x
    if x.numel() == 0:
        return True
    if kind == _optim.POSE:
        bottom = torch.tensor([0.0, 0.0, 0.0, 1.0], dtype=x.dtype, device=x.device)
        rigid = (x[..., 3, :] - bottom).abs().amax() <= tolerance
        return bool(rigid) and _is_rotation(x[..., :3, :3], _optim.MATRIX)
    if kind == _optim.MATRIX:
        eye = torch.eye(3, dtype=x.dtype, device=x.device)
        gram = x.transpose(-1, -2) @ x
        ok = (gram - eye).abs().amax() <= tolerance
        return bool(ok & (torch.linalg.det(x) > 0).all())
    return bool(((torch.linalg.vector_norm(x, dim=-1) - 1).abs() <= tolerance).all())


class _Riemannian(torch.optim.Optimizer):
    """What both optimisers share: the checks of a parameter group, and the loop over parameters."""

    def add_param_group(self, param_group: dict[str, Any]) -> None:
        super().add_param_group(param_group)
        try:
            self._check_group(self.param_groups[-1], len(self.param_groups) - 1)
        except Exception:
            self.param_groups.pop()
            raise

    def _check_group(self, group: dict[str, Any], index: int) -> None:
        name = type(self).__name__
        manifold = group["manifold"]
        if manifold not in MANIFOLDS:
            raise ValueError(
                f"{name}: param group {index} has manifold={manifold!r}; expected 'so3' (rotations), 'se3' "
                "(rigid transforms) or 'euclidean' (ordinary tensors)"
            )
        for k, p in enumerate(group["params"]):
            if not p.dtype.is_floating_point:
                raise TypeError(f"{name}: parameter {k} of param group {index} has dtype {p.dtype}; "
                                "expected a real floating-point dtype")  # fmt: skip
        if manifold == "euclidean":
            return
        if group.get("weight_decay", 0.0) != 0.0:
            why = (
                "an L2 penalty on the entries of a rotation is constant on SO(3) (|R|_F^2 = 3, |q| = 1) and "
                "has no effect there"
                if manifold == "so3"
                else "on a rigid transform an L2 penalty on the entries pulls the translation towards the "
                "world origin, which the metric does not single out, and does nothing to the rotation"
            )
            raise ValueError(
                f"{name}: param group {index} (manifold {manifold!r}) has weight_decay="
                f"{group['weight_decay']}: {why}; add a penalty on the rotation or pose to the loss instead "
                "(e.g. matrix_geodesic_distance(R, reference) ** 2), or use weight_decay in a 'euclidean' "
                "group"
            )
        scale = group.get("length_scale", 1.0)
        if not (scale > 0.0 and math.isfinite(scale)) or (manifold != "se3" and scale != 1.0):
            raise ValueError(
                f"{name}: param group {index} (manifold {manifold!r}) has length_scale={scale}; expected a "
                "positive finite length, on a group with manifold 'se3' only (the translation that counts as "
                "one radian)"
            )
        for k, p in enumerate(group["params"]):
            kind = _optim.parameter_kind(tuple(p.shape), manifold)
            if kind is None and manifold == "se3":
                raise ValueError(
                    f"{name}: parameter {k} of param group {index} has shape {tuple(p.shape)}; a param group "
                    "with manifold 'se3' holds rigid transforms (..., 4, 4); put rotations in a group with "
                    "manifold='so3', other tensors in one with manifold='euclidean'"
                )
            if kind is None:
                raise ValueError(
                    f"{name}: parameter {k} of param group {index} has shape {tuple(p.shape)}; a param group "
                    "with manifold 'so3' holds rotation matrices (..., 3, 3) or quaternions (..., 4), told "
                    "apart by the trailing shape; put other tensors in a group with manifold='euclidean'"
                )
            pose = _optim.parameter_kind(tuple(p.shape), "se3") == _optim.POSE
            if manifold == "so3" and pose and _is_rotation(p, _optim.POSE):
                raise ValueError(
                    f"{name}: parameter {k} of param group {index} (shape {tuple(p.shape)}) holds rigid "
                    "transforms, which a group with manifold 'so3' would read as quaternions (..., 4); put "
                    "them in a group with manifold='se3'"
                )
            if not _is_rotation(p, kind):
                what = {
                    _optim.MATRIX: "rotation matrices (R^T R = I, det R = 1)",
                    _optim.QUATERNION: "unit quaternions",
                    _optim.POSE: "rigid transforms (R^T R = I, det R = 1, bottom row 0, 0, 0, 1)",
                }[kind]
                raise ValueError(
                    f"{name}: parameter {k} of param group {index} (shape {tuple(p.shape)}) does not hold "
                    f"{what} to 1e-3; start from rotations (e.g. normalize_quaternion), or put ordinary "
                    "tensors in a group with manifold='euclidean'"
                )

    @torch.no_grad()
    def step(self, closure: Callable[[], Any] | None = None) -> Any:
        """One step for every parameter with a gradient; ``closure`` (optional) re-evaluates the loss,
        which is returned."""
        loss = None
        if closure is not None:
            with torch.enable_grad():
                loss = closure()
        for group in self.param_groups:
            for p in group["params"]:
                if p.grad is None:
                    continue
                if p.grad.is_sparse:
                    raise RuntimeError(f"{type(self).__name__} does not support sparse gradients")
                if group["manifold"] == "euclidean":
                    kind = None
                    grad = p.grad if group["weight_decay"] == 0 else p.grad + group["weight_decay"] * p
                else:
                    kind = _optim.parameter_kind(tuple(p.shape), group["manifold"])
                    assert kind is not None  # checked when the group was added
                    grad = _optim.tangent_gradient(torch, p, p.grad, kind, group["scalar_first"])
                update = self._update(grad, self.state[p], group, kind, p)
                if kind is None:
                    p.add_(update)
                else:
                    p.copy_(_optim.retract(_dq, torch, p, update, kind, group["scalar_first"]))
        return loss

    def _update(
        self, grad: Tensor, state: dict[str, Any], group: dict[str, Any], kind: str | None, param: Tensor
    ) -> Tensor:
        """The update of ``param`` (``kind`` as ``_optim.parameter_kind``'s, None for a Euclidean
        tensor) from its (tangent) gradient; a body twist for a pose."""
        raise NotImplementedError  # pragma: no cover


class RiemannianAdam(_Riemannian):
    """Adam on SO(3) (and on ordinary tensors in ``"euclidean"`` groups); see the module for the
    conventions and the rules for parameters.

    Args:
        params: parameters or parameter groups (dicts), as for ``torch.optim.Adam``.
        lr: learning rate; on a rotation the step turns it by about ``lr`` radians while the gradient is
            steady (the second moment is one number per rotation, below).
        betas: decay rates of the first and second moments.
        eps: added to the square root of the second moment.
        weight_decay: L2 penalty, ``"euclidean"`` groups only (``ValueError`` on the others).
        amsgrad: keep the maximum of the second moment (Reddi et al.).
        manifold: ``"so3"`` (default), ``"se3"`` or ``"euclidean"``, the default of every group.
        scalar_first: storage order of quaternion parameters.
        length_scale: on a pose (``"se3"`` groups), the translation that counts as one radian, in the
            translation's units (the metric ``|rho / s|^2 + |phi|^2``): Adam's step then moves the
            translation by about ``length_scale * lr``; changing the units of length and
            ``length_scale`` with them leaves every step the same.

    On a rotation the first moment is a tangent vector ``(..., 3)`` and the second moment one number
    per rotation, ``|g|^2`` averaged ``(..., 1)``: it does not depend on the body frame, and the step
    ``-lr m_hat / (sqrt(v_hat) + eps)`` is then parallel to ``m``, so the parallel transport of ``m``
    along it leaves its body coordinates unchanged (``exp(-d / 2) m = m`` for ``d`` along ``m``). State
    per parameter: ``step`` (an int), ``exp_avg``, ``exp_avg_sq``, and ``max_exp_avg_sq`` with amsgrad.
    On a pose the first moment is a twist ``(..., 6)`` whose translation part is kept in the world
    frame, and the second moment two numbers ``(..., 2)``, translation and rotation.
    """

    def __init__(
        self,
        params: Params,
        lr: float = 1e-3,
        betas: tuple[float, float] = (0.9, 0.999),
        eps: float = 1e-8,
        weight_decay: float = 0.0,
        amsgrad: bool = False,
        *,
        manifold: str = "so3",
        scalar_first: bool = True,
        length_scale: float = 1.0,
    ) -> None:
        if not lr >= 0.0:
            raise ValueError(f"RiemannianAdam: invalid learning rate {lr}")
        if not eps >= 0.0:
            raise ValueError(f"RiemannianAdam: invalid eps {eps}")
        if not (0.0 <= betas[0] < 1.0 and 0.0 <= betas[1] < 1.0):
            raise ValueError(f"RiemannianAdam: invalid betas {betas}")
        if not weight_decay >= 0.0:
            raise ValueError(f"RiemannianAdam: invalid weight_decay {weight_decay}")
        defaults = {
            "lr": lr,
            "betas": betas,
            "eps": eps,
            "weight_decay": weight_decay,
            "amsgrad": amsgrad,
            "manifold": manifold,
            "scalar_first": scalar_first,
            "length_scale": length_scale,
        }
        super().__init__(params, defaults)

    def _update(
        self, grad: Tensor, state: dict[str, Any], group: dict[str, Any], kind: str | None, param: Tensor
    ) -> Tensor:
        if not state:
            state["step"] = 0
            state["exp_avg"] = torch.zeros_like(grad)
            square = grad if kind is None else grad[..., : _optim.second_moment_size(kind)]
            state["exp_avg_sq"] = torch.zeros_like(square)
            if group["amsgrad"]:
                state["max_exp_avg_sq"] = torch.zeros_like(square)
        state["step"] += 1
        options = (state["step"], group["betas"], group["eps"], group["amsgrad"])
        moments = (state["exp_avg"], state["exp_avg_sq"], state.get("max_exp_avg_sq"))
        if kind == _optim.POSE:
            out = _optim.pose_adam(torch, param, grad, *moments, *options, group["length_scale"])
        else:
            out = _optim.adam(torch, grad, *moments, *options, kind is not None)
        direction, state["exp_avg"], state["exp_avg_sq"], maximum = out
        if group["amsgrad"]:
            state["max_exp_avg_sq"] = maximum
        return -group["lr"] * direction


class RiemannianSGD(_Riemannian):
    """SGD on SO(3), with momentum, dampening and Nesterov momentum as in ``torch.optim.SGD`` (and on
    ordinary tensors in ``"euclidean"`` groups); see the module for the conventions.

    Args:
        params: parameters or parameter groups (dicts), as for ``torch.optim.SGD``.
        lr: learning rate: a step turns a rotation by ``lr |g|`` radians (``g`` the tangent gradient).
        momentum: momentum factor (0: plain Riemannian gradient descent).
        dampening: dampening of the momentum.
        weight_decay: L2 penalty, ``"euclidean"`` groups only (``ValueError`` on the others).
        nesterov: Nesterov momentum (needs ``momentum > 0`` and ``dampening == 0``).
        manifold: ``"so3"`` (default), ``"se3"`` or ``"euclidean"``, the default of every group.
        scalar_first: storage order of quaternion parameters.
        length_scale: on a pose (``"se3"`` groups), the translation that counts as one radian, in the
            translation's units (the metric ``|rho / s|^2 + |phi|^2``): the gradient's translation part
            is then ``s^2 g_rho``; changing the units of length and ``length_scale`` with them (and
            the loss's scale) leaves every step the same.

    The momentum buffer of a rotation is a tangent vector ``(..., 3)``, carried to the new rotation by
    parallel transport after each step (``exp(-d / 2) buffer`` for the step ``d``: the identity without
    Nesterov, whose step is along the buffer); that of a pose is a twist ``(..., 6)`` whose
    translation part is kept in the world frame (transported by the identity). State per parameter:
    ``momentum_buffer``.
    """

    def __init__(
        self,
        params: Params,
        lr: float = 1e-3,
        momentum: float = 0.0,
        dampening: float = 0.0,
        weight_decay: float = 0.0,
        nesterov: bool = False,
        *,
        manifold: str = "so3",
        scalar_first: bool = True,
        length_scale: float = 1.0,
    ) -> None:
        if not lr >= 0.0:
            raise ValueError(f"RiemannianSGD: invalid learning rate {lr}")
        if not momentum >= 0.0:
            raise ValueError(f"RiemannianSGD: invalid momentum {momentum}")
        if not weight_decay >= 0.0:
            raise ValueError(f"RiemannianSGD: invalid weight_decay {weight_decay}")
        if nesterov and (momentum <= 0 or dampening != 0):
            raise ValueError("RiemannianSGD: Nesterov momentum requires a momentum and zero dampening")
        defaults = {
            "lr": lr,
            "momentum": momentum,
            "dampening": dampening,
            "weight_decay": weight_decay,
            "nesterov": nesterov,
            "manifold": manifold,
            "scalar_first": scalar_first,
            "length_scale": length_scale,
        }
        super().__init__(params, defaults)

    def _update(
        self, grad: Tensor, state: dict[str, Any], group: dict[str, Any], kind: str | None, param: Tensor
    ) -> Tensor:
        if group["momentum"] == 0:
            if kind == _optim.POSE:
                return -group["lr"] * _optim.scale_translation(torch, grad, group["length_scale"] ** 2)
            return -group["lr"] * grad
        buffer = state.get("momentum_buffer")
        options = (group["lr"], group["momentum"], group["dampening"], group["nesterov"])
        start = (grad if buffer is None else buffer, buffer is None)
        if kind == _optim.POSE:
            update, state["momentum_buffer"] = _optim.pose_momentum(
                torch, param, grad, *start, *options, group["length_scale"]
            )
        else:
            update, state["momentum_buffer"] = _optim.momentum(
                torch, grad, *start, *options, kind is not None
            )
        return update
