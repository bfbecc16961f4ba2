"""diffquat on PyTorch. Same names and semantics as :mod:`diffquat.numpy` and :mod:`diffquat.jax`;
see :mod:`diffquat` for the conventions. Dtype and device of the input are preserved."""

from __future__ import annotations

from typing import Any

import torch
from torch import Tensor

from .. import _algebra, _core, _euler
from .. import _representations as _rep
from .._backend import Backend, documented, shape_tuple
from . import _fused
from ._custom import custom_derivative

__all__ = [
    "axis_angle_to_matrix",
    "axis_angle_to_quaternion",
    "euler_angles_to_matrix",
    "euler_angles_to_quaternion",
    "fit_rotation",
    "matrix_geodesic_distance",
    "matrix_to_axis_angle",
    "matrix_to_euler_angles",
    "matrix_to_quaternion",
    "matrix_to_rotation_6d",
    "normalize_quaternion",
    "quaternion_apply",
    "quaternion_conjugate",
    "quaternion_geodesic_distance",
    "quaternion_invert",
    "quaternion_multiply",
    "quaternion_slerp",
    "quaternion_to_axis_angle",
    "quaternion_to_euler_angles",
    "quaternion_to_matrix",
    "random_quaternions",
    "rotation_6d_to_matrix",
    "special_procrustes",
    "standardize_quaternion",
    "symmetric_matrix_to_quaternion",
    "wxyz_to_xyzw",
    "xyzw_to_wxyz",
]


def _convert(fname: str, argname: str, x: Any) -> Tensor:
    # No silent conversion from lists or numpy arrays: it would pick a device and a dtype for the user.
    if not isinstance(x, Tensor):
        raise TypeError(f"{fname}: expected {argname} to be a torch.Tensor, got {type(x).__name__}")
    return x


_B = Backend(
    xp=torch,
    convert=_convert,
    is_floating=lambda dtype: dtype.is_floating_point,
    astype=lambda x, dtype: x.to(dtype),
    float32=torch.float32,
)


@documented(_core.quaternion_to_matrix)
def quaternion_to_matrix(q: Tensor, *, scalar_first: bool = True) -> Tensor:
    # The fused Function, the Triton kernels or the core formula: see _fused.q2m_path.
    return _B(_fused.q2m_path(q), q, scalar_first=scalar_first)


@documented(_core.matrix_to_quaternion)
def matrix_to_quaternion(matrix: Tensor, *, scalar_first: bool = True) -> Tensor:
    return _B(_fused.m2q_path(matrix), matrix, scalar_first=scalar_first)


def _quaternion_to_matrix(xp: Any, q: Tensor, *, scalar_first: bool = True) -> Tensor:
    """The conversion step of the composites (see ``_core.Conversion``), by the same path as
    :func:`quaternion_to_matrix` for this call."""
    return _fused.q2m_path(q)(xp, q, scalar_first=scalar_first)


def _matrix_to_quaternion(xp: Any, matrix: Tensor, *, scalar_first: bool = True) -> Tensor:
    """The conversion step of the composites, by the same path as :func:`matrix_to_quaternion`."""
    return _fused.m2q_path(matrix)(xp, matrix, scalar_first=scalar_first)


@documented(_core.standardize_quaternion)
def standardize_quaternion(q: Tensor, *, scalar_first: bool = True) -> Tensor:
    return _B(_core.standardize_quaternion, q, scalar_first=scalar_first)


@documented(_core.normalize_quaternion)
def normalize_quaternion(q: Tensor, *, scalar_first: bool = True) -> Tensor:
    return _B(_core.normalize_quaternion, q, scalar_first=scalar_first)


@documented(_core.wxyz_to_xyzw)
def wxyz_to_xyzw(q: Tensor) -> Tensor:
    return _B(_core.wxyz_to_xyzw, q)


@documented(_core.xyzw_to_wxyz)
def xyzw_to_wxyz(q: Tensor) -> Tensor:
    return _B(_core.xyzw_to_wxyz, q)


# The SVD and eigh maps with their closed-form derivatives (see diffquat._representations).
_special_procrustes = custom_derivative(
    _rep.special_procrustes, _rep.procrustes_tangent, _rep.procrustes_cotangent
)
_smallest_eigenvector = custom_derivative(
    _rep.smallest_eigenvector, _rep.eigenvector_tangent, _rep.eigenvector_cotangent
)


@documented(_rep.rotation_6d_to_matrix)
def rotation_6d_to_matrix(d6: Tensor) -> Tensor:
    return _B(_rep.rotation_6d_to_matrix, d6)


@documented(_rep.matrix_to_rotation_6d)
def matrix_to_rotation_6d(matrix: Tensor) -> Tensor:
    return _B(_rep.matrix_to_rotation_6d, matrix)


@documented(_rep.special_procrustes)
def special_procrustes(matrix: Tensor) -> Tensor:
    return _B(_special_procrustes, matrix)


@documented(_rep.symmetric_matrix_to_quaternion)
def symmetric_matrix_to_quaternion(a: Tensor, *, scalar_first: bool = True) -> Tensor:
    return _B(
        _rep.symmetric_matrix_to_quaternion, a, scalar_first=scalar_first, eigenvector=_smallest_eigenvector
    )


@documented(_rep.fit_rotation)
def fit_rotation(source: Tensor, target: Tensor, weights: Tensor | None = None) -> Tensor:
    return _B(_rep.fit_rotation, source, target, weights, procrustes=_special_procrustes)


# Rotation vector, Euler angles, quaternion algebra, interpolation and distances.


@documented(_algebra.axis_angle_to_quaternion)
def axis_angle_to_quaternion(axis_angle: Tensor, *, scalar_first: bool = True) -> Tensor:
    return _B(_algebra.axis_angle_to_quaternion, axis_angle, scalar_first=scalar_first)


@documented(_algebra.quaternion_to_axis_angle)
def quaternion_to_axis_angle(q: Tensor, *, scalar_first: bool = True) -> Tensor:
    return _B(_algebra.quaternion_to_axis_angle, q, scalar_first=scalar_first)


@documented(_algebra.axis_angle_to_matrix)
def axis_angle_to_matrix(axis_angle: Tensor) -> Tensor:
    return _B(_algebra.axis_angle_to_matrix, axis_angle, to_matrix=_quaternion_to_matrix)


@documented(_algebra.matrix_to_axis_angle)
def matrix_to_axis_angle(matrix: Tensor) -> Tensor:
    return _B(_algebra.matrix_to_axis_angle, matrix, to_quaternion=_matrix_to_quaternion)


@documented(_euler.euler_angles_to_matrix)
def euler_angles_to_matrix(angles: Tensor, convention: str, *, degrees: bool = False) -> Tensor:
    return _B(
        _euler.euler_angles_to_matrix,
        angles,
        convention=convention,
        degrees=degrees,
        to_matrix=_quaternion_to_matrix,
    )


@documented(_euler.matrix_to_euler_angles)
def matrix_to_euler_angles(matrix: Tensor, convention: str, *, degrees: bool = False) -> Tensor:
    return _B(_euler.matrix_to_euler_angles, matrix, convention=convention, degrees=degrees)


@documented(_euler.euler_angles_to_quaternion)
def euler_angles_to_quaternion(
    angles: Tensor, convention: str, *, degrees: bool = False, scalar_first: bool = True
) -> Tensor:
    return _B(
        _euler.euler_angles_to_quaternion,
        angles,
        convention=convention,
        degrees=degrees,
        scalar_first=scalar_first,
    )


@documented(_euler.quaternion_to_euler_angles)
def quaternion_to_euler_angles(
    q: Tensor, convention: str, *, degrees: bool = False, scalar_first: bool = True
) -> Tensor:
    return _B(
        _euler.quaternion_to_euler_angles,
        q,
        convention=convention,
        degrees=degrees,
        scalar_first=scalar_first,
    )


@documented(_algebra.quaternion_multiply)
def quaternion_multiply(p: Tensor, q: Tensor, *, scalar_first: bool = True) -> Tensor:
    return _B(_algebra.quaternion_multiply, p, q, scalar_first=scalar_first)


@documented(_algebra.quaternion_conjugate)
def quaternion_conjugate(q: Tensor, *, scalar_first: bool = True) -> Tensor:
    return _B(_algebra.quaternion_conjugate, q, scalar_first=scalar_first)


@documented(_algebra.quaternion_invert)
def quaternion_invert(q: Tensor, *, scalar_first: bool = True) -> Tensor:
    return _B(_algebra.quaternion_invert, q, scalar_first=scalar_first)


@documented(_algebra.quaternion_apply)
def quaternion_apply(q: Tensor, v: Tensor, *, scalar_first: bool = True) -> Tensor:
    return _B(_algebra.quaternion_apply, q, v, scalar_first=scalar_first)


@documented(_algebra.quaternion_slerp)
def quaternion_slerp(p: Tensor, q: Tensor, t: Tensor, *, scalar_first: bool = True) -> Tensor:
    return _B(_algebra.quaternion_slerp, p, q, t, scalar_first=scalar_first)


@documented(_algebra.quaternion_geodesic_distance)
def quaternion_geodesic_distance(p: Tensor, q: Tensor, *, scalar_first: bool = True) -> Tensor:
    return _B(_algebra.quaternion_geodesic_distance, p, q, scalar_first=scalar_first)


@documented(_algebra.matrix_geodesic_distance)
def matrix_geodesic_distance(matrix1: Tensor, matrix2: Tensor) -> Tensor:
    return _B(_algebra.matrix_geodesic_distance, matrix1, matrix2)


def random_quaternions(
    shape: int | tuple[int, ...] = (),
    *,
    generator: torch.Generator | None = None,
    dtype: torch.dtype | None = None,
    device: torch.device | str | None = None,
    scalar_first: bool = True,
) -> Tensor:
    """Unit quaternions uniformly distributed over rotations (Shoemake's method), in canonical sign.

    Args:
        shape: batch shape; the result has shape ``(*shape, 4)``.
        generator: a ``torch.Generator`` to draw from (default: the global one).
        dtype: floating dtype of the result (default ``torch.get_default_dtype()``).
        device: device of the result (default: the current default device).
        scalar_first: storage order of the result.
    """
    dtype = torch.get_default_dtype() if dtype is None else dtype
    uniform = torch.rand(
        (*shape_tuple(shape), 3), generator=generator, dtype=_B.compute_dtype(dtype), device=device
    )
    q = _B(_core.quaternions_from_uniform, uniform, scalar_first=scalar_first)
    return _B.cast_canonical(q, dtype, scalar_first)
