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

The same maps exist as pure functions for JAX in :mod:`diffquat.jax.nn`.
"""

from __future__ import annotations

import torch
from torch import Tensor, nn

import diffquat.torch as _dq

from .. import _heads
from . import _dispatch

__all__ = [
    "REPRESENTATIONS",
    "RotationHead",
    "representation_size",
    "representation_to_fisher",
    "representation_to_matrix",
]

REPRESENTATIONS: tuple[str, ...] = tuple(_heads.REPRESENTATIONS)


def representation_size(representation: str) -> int:
    """Number of raw outputs a head of ``representation`` needs (e.g. 6 for ``"6d"``)."""
    return _heads.representation_size(representation)


def representation_to_matrix(raw: Tensor, representation: str) -> Tensor:
    """Rotation matrices ``(..., 3, 3)`` from raw outputs ``(..., n)``, ``n = representation_size(...)``.

    Differentiable everywhere the representation is; any raw output gives a rotation (for example a
    zero quaternion gives the identity). The ``"9d"``, ``"10d"`` and ``"fisher"`` maps (SVD and eigh)
    cannot be exported to ONNX, which has no such operator: exporting them raises
    ``NotImplementedError``.
    """
    if representation in ("9d", "10d", "fisher"):
        _dispatch.refuse_onnx("representation_to_matrix", f"the {representation!r} representation")
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
        bias, device, dtype: as for ``torch.nn.Linear``.

    Shapes: ``(..., in_features)`` in, rotation matrices ``(..., 3, 3)`` out (column-vector convention).
    For ``representation="fisher"`` the rotation is the mode of a matrix Fisher distribution whose
    parameter F ``(..., 3, 3)`` :meth:`fisher` returns.
    """

    def __init__(
        self,
        in_features: int,
        representation: str = "6d",
        *,
        bias: bool = True,
        device: torch.device | str | None = None,
        dtype: torch.dtype | None = None,
    ) -> None:
        super().__init__()
        self.representation = representation
        self.linear = nn.Linear(
            in_features, representation_size(representation), bias=bias, device=device, dtype=dtype
        )

    def forward(self, features: Tensor) -> Tensor:
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

    def extra_repr(self) -> str:
        return f"representation={self.representation!r}"
