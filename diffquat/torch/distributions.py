"""Distributions over rotations, as ``torch.distributions`` objects.

``MatrixFisher(F)``: the matrix Fisher distribution on SO(3), density ``exp(tr(F^T R)) / c(F)``
against the Haar probability measure (uniform rotations have density 1)::

    import diffquat.torch as dq
    from diffquat.torch.distributions import MatrixFisher

    F = network(features).reshape(-1, 3, 3)  # or RotationHead(..., "fisher").fisher(features)
    dist = MatrixFisher(F)
    loss = -dist.log_prob(R_true).mean()  # = dq.matrix_fisher_nll(F, R_true).mean()
    R_hat, R_draws = dist.mode, dist.sample((16,))  # (B, 3, 3), (16, B, 3, 3)

Batch shape: ``F.shape[:-2]``; event shape ``(3, 3)``.
"""

from __future__ import annotations

from typing import Any

import torch
from torch import Tensor
from torch.distributions import Distribution, constraints
from torch.distributions.utils import lazy_property

import diffquat.torch as _dq

from .._public import public_dir as _public_dir

__all__ = ["MatrixFisher", "special_orthogonal"]
# dir() lists the public API only (see diffquat._public).
__dir__ = _public_dir(globals())


class _SpecialOrthogonal(constraints.Constraint):
    """Rotation matrices ``(..., 3, 3)``: ``R^T R = I`` and ``det R = 1``, each to within
    ``max(1e-5, 10 eps)`` of the dtype (a rotation rounded to float32 and cast to float64 passes)."""

    event_dim = 2

    def check(self, value: Tensor) -> Tensor:
        if value.shape[-2:] != (3, 3):
            return torch.zeros(value.shape[:-2], dtype=torch.bool, device=value.device)
        tol = max(1e-5, 10 * torch.finfo(value.dtype).eps)
        work = value if value.dtype.itemsize >= 4 else value.float()
        eye = torch.eye(3, dtype=work.dtype, device=work.device)
        gram = (work.mT @ work - eye).abs().amax(dim=(-2, -1))
        return (gram <= tol) & ((torch.linalg.det(work) - 1).abs() <= tol)

    def __repr__(self) -> str:
        return "SpecialOrthogonal()"


special_orthogonal = _SpecialOrthogonal()


class MatrixFisher(Distribution):
    """The matrix Fisher distribution on SO(3): ``p(R) = exp(tr(F^T R)) / c(F)`` against the Haar
    probability measure.

    Args:
        F: the parameter, shape ``(..., 3, 3)``, any real matrices (F = 0 is the uniform distribution;
            ``F = U diag(s) V^T`` concentrates around ``U V^T``-like rotations as s grows).
        validate_args: as for every ``torch.distributions.Distribution``.

    ``log_prob``, ``entropy`` and ``mean`` are differentiable in F (the normaliser's closed-form
    derivatives: ``diffquat.torch.matrix_fisher_log_normalizer``); ``sample`` is not (a rejection
    sampler: ``has_rsample`` is False). ``mode`` is the rotation nearest to F, ``mean`` is ``E[R]`` (a
    3x3 matrix inside the convex hull of SO(3), not a rotation), and ``entropy`` is relative to the Haar
    probability measure: 0 for the uniform distribution, negative otherwise.
    """

    arg_constraints = {"F": constraints.independent(constraints.real, 2)}  # type: ignore[no-untyped-call]  # noqa: RUF012
    support = special_orthogonal
    has_rsample = False

    def __init__(self, F: Tensor, validate_args: bool | None = None) -> None:
        if not isinstance(F, Tensor) or F.ndim < 2 or tuple(F.shape[-2:]) != (3, 3):
            shape = tuple(F.shape) if isinstance(F, Tensor) else type(F).__name__
            raise ValueError(f"MatrixFisher: expected F, a tensor of shape (..., 3, 3), got {shape}")
        self.F = F
        super().__init__(F.shape[:-2], torch.Size((3, 3)), validate_args=validate_args)

    def expand(self, batch_shape: Any, _instance: Any = None) -> MatrixFisher:
        new = self._get_checked_instance(MatrixFisher, _instance)  # type: ignore[no-untyped-call]
        batch_shape = torch.Size(batch_shape)
        new.F = self.F.expand((*batch_shape, 3, 3))
        super(MatrixFisher, new).__init__(batch_shape, self.event_shape, validate_args=False)
        new._validate_args = self._validate_args
        return new

    @lazy_property
    def log_normalizer(self) -> Tensor:
        """``log c(F)``, shape ``batch_shape``."""
        return _dq.matrix_fisher_log_normalizer(self.F)

    def log_prob(self, value: Tensor) -> Tensor:
        if self._validate_args:
            self._validate_sample(value)
        return -_dq.matrix_fisher_nll(self.F, value)

    @torch.no_grad()
    def sample(self, sample_shape: Any = torch.Size()) -> Tensor:  # noqa: B008
        """Exact draws (see ``diffquat.torch.matrix_fisher_sample``), shape
        ``sample_shape + batch_shape + (3, 3)``, from torch's global random generator."""
        return _dq.matrix_fisher_sample(self.F, tuple(torch.Size(sample_shape)))

    @property
    def mode(self) -> Tensor:
        return _dq.matrix_fisher_mode(self.F)

    @property
    def mean(self) -> Tensor:
        """``E[R]``, the gradient of ``log c(F)``: ``U diag(d log c / ds) V^T``."""
        return _dq._matrix_fisher_mean(self.F)

    def entropy(self) -> Tensor:
        """``log c(F) - tr(F^T E[R])``, relative to the Haar probability measure (<= 0)."""
        return self.log_normalizer - (self.F * self.mean).sum(dim=(-2, -1))
