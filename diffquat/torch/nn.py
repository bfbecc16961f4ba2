"""Rotation heads for PyTorch networks: raw network outputs -> rotation matrices.

``RotationHead`` is a linear layer followed by the map of one representation onto SO(3); put it on top
of any feature extractor and train with a geodesic loss::

    import diffquat.torch as dq
    from diffquat.torch.nn import RotationHead

    head = RotationHead(128, representation="6d")
    R = head(features)  # (..., 3, 3)
    loss = dq.matrix_geodesic_distance(R, R_true).mean()

Representations (the number of raw outputs in brackets): ``"quaternion"`` (4), ``"axis_angle"`` (3),
``"euler"`` (3, intrinsic ``"XYZ"``, radians), ``"6d"`` (6, Zhou et al. 2019, first two *columns*),
``"9d"`` (9, SVD projection, Levinson et al. 2020), ``"10d"`` (10, Peretroukhin et al. 2020) and
``"fisher"`` (9, the parameter F of a matrix Fisher distribution, Mohlin et al. 2020). Every head
returns rotations; a ``"fisher"`` head returns the distribution's mode, and its ``fisher`` method the
parameter F, for the negative log-likelihood::

    head = RotationHead(128, representation="fisher")
    F = head.fisher(features)  # (..., 3, 3)
    loss = dq.matrix_fisher_nll(F, R_true).mean()  # or -MatrixFisher(F).log_prob(R_true)
    R = dq.matrix_fisher_mode(F)  # = head(features)

The same maps exist as pure functions for JAX in ``diffquat.jax.nn``.
"""

from __future__ import annotations

from typing import TYPE_CHECKING, Any

import torch
from torch import Tensor, nn

import diffquat.torch as _dq

from .. import _heads
from .._public import public_dir as _public_dir
from .._types import Representation
from . import _custom

__all__ = [
    "REPRESENTATIONS",
    "RotationHead",
    "representation_size",
    "representation_to_fisher",
    "representation_to_matrix",
]
# dir() lists the public API only (see diffquat._public).
__dir__ = _public_dir(globals())

REPRESENTATIONS: tuple[str, ...] = tuple(_heads.REPRESENTATIONS)


def representation_size(representation: Representation) -> int:
    """Number of raw outputs a head of ``representation`` needs (e.g. 6 for ``"6d"``)."""
    return _heads.representation_size(representation)


def representation_to_matrix(raw: Tensor, representation: Representation) -> Tensor:
    """Rotation matrices ``(..., 3, 3)`` from raw outputs ``(..., n)``, ``n = representation_size(...)``.

    Differentiable everywhere the representation is; any raw output gives a rotation (for example a
    zero quaternion gives the identity). The ``"9d"``, ``"10d"`` and ``"fisher"`` maps (SVD and eigh)
    cannot be exported to ONNX, which has no such operator: exporting them raises
    ``NotImplementedError``.
    """
    if representation in ("9d", "10d", "fisher"):
        _custom.refuse_onnx("representation_to_matrix", f"the {representation!r} representation")
    return _heads.representation_to_matrix(torch, _dq, raw, representation)


def representation_to_fisher(raw: Tensor) -> Tensor:
    """The matrix Fisher parameter F ``(..., 3, 3)`` of a ``"fisher"`` head's raw outputs ``(..., 9)``,
    row-major: the density ``exp(tr(F^T R)) / c(F)``, whose mode ``matrix_fisher_mode(F)`` is
    ``representation_to_matrix(raw, "fisher")``."""
    return _heads.representation_to_fisher(torch, raw)


# Leaves of torch.fx.symbolic_trace, as the functions of diffquat.torch (see there).
torch.fx.wrap("representation_to_matrix")
torch.fx.wrap("representation_to_fisher")


class RotationHead(nn.Module):
    """A linear layer ``in_features -> representation_size(representation)`` then the map to SO(3).

    Args:
        in_features: size of the last dimension of the input features.
        representation: one of ``REPRESENTATIONS``.
        bias: whether the linear layer has a bias, as for ``torch.nn.Linear``.
        device: the device of the parameters, as for ``torch.nn.Linear``.
        dtype: the dtype of the parameters, as for ``torch.nn.Linear``.

    Shapes: ``(..., in_features)`` in, rotation matrices ``(..., 3, 3)`` out (column-vector convention).

    The representation is part of the module's ``state_dict``, as the buffer ``representation_code``
    (its name's bytes, zero-padded): loading weights saved by a head of another representation raises
    ``ValueError`` naming both, rather than loading them into a map they were not trained for (the
    axis-angle and Euler heads both have 3 raw outputs, so their weights would otherwise load without
    complaint). A buffer, not a non-tensor extra state: every exporter (TorchScript, ONNX,
    ``torch.export``) and ``DistributedDataParallel`` handle tensors in a state dict.

    For ``representation="fisher"`` the rotation is the mode of a matrix Fisher distribution whose
    parameter F ``(..., 3, 3)`` ``fisher`` returns.
    """

    representation_code: Tensor

    def __init__(
        self,
        in_features: int,
        representation: Representation = "6d",
        *,
        bias: bool = True,
        device: torch.device | str | None = None,
        dtype: torch.dtype | None = None,
    ) -> None:
        super().__init__()
        self.representation: Representation = representation
        self.linear = nn.Linear(
            in_features, representation_size(representation), bias=bias, device=device, dtype=dtype
        )
        self.register_buffer("representation_code", _encode(representation, device))
        self.register_load_state_dict_pre_hook(_check_representation)  # type: ignore[no-untyped-call]

    def forward(self, features: Tensor) -> Tensor:
        """Rotation matrices ``(..., 3, 3)`` of features ``(..., in_features)``: the linear layer, then
        ``representation_to_matrix`` of its raw outputs. Any features give a rotation; the map runs in
        float32 at least (under ``torch.autocast`` too) and returns the linear layer's dtype."""
        return representation_to_matrix(self.linear(features), self.representation)

    def fisher(self, features: Tensor) -> Tensor:
        """The matrix Fisher parameter F ``(..., 3, 3)`` of a ``"fisher"`` head (``ValueError`` for the
        other representations): train with ``matrix_fisher_nll(F, R_true)``; ``forward`` gives its
        mode."""
        if self.representation != "fisher":
            raise ValueError(
                f"RotationHead.fisher: the head's representation is {self.representation!r}; "
                "a matrix Fisher parameter comes from a 'fisher' head"
            )
        return representation_to_fisher(self.linear(features))

    if TYPE_CHECKING:
        # torch types ``Module.__call__`` as returning Any; a call runs ``forward``, so a user's type
        # checker sees tensor in, tensor out.
        def __call__(self, features: Tensor) -> Tensor: ...

    def extra_repr(self) -> str:
        return f"representation={self.representation!r}"


_CODE_BYTES = 16  # longer than every representation's name


def _encode(representation: str, device: torch.device | str | None) -> Tensor:
    code = representation.encode().ljust(_CODE_BYTES, b"\0")
    return torch.tensor(list(code), dtype=torch.uint8, device=device)


def _check_representation(module: nn.Module, state_dict: dict[str, Any], prefix: str, *args: Any) -> None:
    """Before a ``state_dict`` loads into a ``RotationHead``: the representation it was saved for must
    be the head's (a missing code is left to ``load_state_dict``'s missing-key rule)."""
    code = state_dict.get(prefix + "representation_code")
    if code is None:
        return
    saved = bytes(code.tolist()).rstrip(b"\0").decode(errors="replace")
    if saved != module.representation:
        raise ValueError(
            f"RotationHead: the weights being loaded were saved for representation {saved!r}, "
            f"this head's is {module.representation!r}; build the head with "
            f"representation={saved!r} to load them"
        )
