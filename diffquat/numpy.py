"""diffquat on NumPy: the reference backend (no autograd). Same names and semantics as
``diffquat.torch`` and ``diffquat.jax``; the conventions are on the documentation's Conventions page."""

from __future__ import annotations

import sys
from typing import Any

import numpy as np
from numpy.typing import ArrayLike, NDArray

from . import _algebra, _core, _euler, _igso3, _lie, _motion, _objects, _se3
from . import _fisher as _fi
from . import _representations as _rep
from . import _statistics as _stats
from ._backend import Backend, documented, shape_tuple
from ._public import public_dir as _public_dir
from ._types import (
    EulerConvention,
    Frame,
    MeanMethod,
    PoseLayout,
    Rotation6DLayout,
    SE3Interpolation,
    Side,
    SplineMode,
)

__all__ = [
    "SE3",
    "SO3",
    "angular_acceleration",
    "angular_velocity",
    "angular_velocity_from_quaternions",
    "axis_angle_to_matrix",
    "axis_angle_to_quaternion",
    "bingham_nll",
    "euler_angles_to_matrix",
    "euler_angles_to_quaternion",
    "fit_rigid_transform",
    "fit_rotation",
    "fit_similarity_transform",
    "frame_from_three_points",
    "igso3_angle_cdf",
    "igso3_log_density",
    "igso3_sample",
    "igso3_score",
    "integrate_angular_velocity",
    "matrix_fisher_log_normalizer",
    "matrix_fisher_mode",
    "matrix_fisher_nll",
    "matrix_fisher_sample",
    "matrix_geodesic_distance",
    "matrix_to_axis_angle",
    "matrix_to_euler_angles",
    "matrix_to_pose",
    "matrix_to_quaternion",
    "matrix_to_rotation_6d",
    "normalize_quaternion",
    "pose_to_matrix",
    "quaternion_apply",
    "quaternion_conjugate",
    "quaternion_derivative",
    "quaternion_geodesic_distance",
    "quaternion_invert",
    "quaternion_mean",
    "quaternion_minus",
    "quaternion_multiply",
    "quaternion_plus",
    "quaternion_slerp",
    "quaternion_squad",
    "quaternion_to_axis_angle",
    "quaternion_to_euler_angles",
    "quaternion_to_matrix",
    "random_quaternions",
    "rotation_6d_to_matrix",
    "rotation_between_vectors",
    "rotation_mean",
    "se3_ad",
    "se3_adjoint",
    "se3_apply",
    "se3_bspline",
    "se3_compose",
    "se3_exp",
    "se3_from_rotation_translation",
    "se3_hat",
    "se3_interpolate",
    "se3_inverse",
    "se3_left_jacobian",
    "se3_left_jacobian_inverse",
    "se3_log",
    "se3_mean",
    "se3_minus",
    "se3_plus",
    "se3_right_jacobian",
    "se3_right_jacobian_inverse",
    "se3_to_rotation_translation",
    "se3_vee",
    "so3_bspline",
    "so3_exp",
    "so3_hat",
    "so3_left_jacobian",
    "so3_left_jacobian_inverse",
    "so3_log",
    "so3_minus",
    "so3_plus",
    "so3_right_jacobian",
    "so3_right_jacobian_inverse",
    "so3_vee",
    "special_procrustes",
    "standardize_quaternion",
    "symmetric_geodesic_distance",
    "symmetric_matrix_to_quaternion",
    "symmetry_group",
    "wxyz_to_xyzw",
    "xyzw_to_wxyz",
]
# dir() lists the public API only (see diffquat._public).
__dir__ = _public_dir(globals())


def _convert(fname: str, argname: str, x: Any, scalar: bool) -> Any:
    # A Python number for a scalar argument stays one: NumPy promotes it weakly (NEP 50), so a float32
    # pair with ``t=0.5`` stays float32, which ``np.asarray(0.5)`` (a float64 array) would not.
    if scalar and isinstance(x, int | float) and not isinstance(x, bool):
        return x
    return np.asarray(x)


def _is_floating(dtype: Any) -> bool:
    # ml_dtypes' bfloat16 (shipped with jax) is not a np.floating subtype but is accepted all the same.
    return bool(np.issubdtype(dtype, np.floating)) or np.dtype(dtype).name == "bfloat16"


def _is_integral(dtype: Any) -> bool:
    return bool(np.issubdtype(dtype, np.integer)) or np.dtype(dtype) == np.bool_


_B = Backend(
    xp=np,
    convert=_convert,
    is_floating=_is_floating,
    is_integral=_is_integral,
    result_type=lambda xs: np.result_type(*xs),
    default_float=lambda: np.dtype(np.float64),
    astype=lambda x, dtype: x.astype(dtype),
    scalar=lambda value, dtype, like: np.asarray(value, dtype=dtype),
    float32=np.dtype(np.float32),
    # Values never raise or warn: the arithmetic of a non-finite row (inf * 0), of an overflowing
    # intermediate that a rule then discards, or of the branch a ``where`` throws away is defined by the
    # documented results, on NumPy as under jit.
    guard=lambda x: np.errstate(all="ignore"),
)


# The conversions as every backend binds them (diffquat._core.registered_conversions); NumPy has no
# derivatives to register, so each is its formula.
_CONVERSIONS = _core.registered_conversions(lambda name, rule, _: rule[0])
_Q2M, _M2Q = _CONVERSIONS["quaternion_to_matrix"], _CONVERSIONS["matrix_to_quaternion"]


@documented(_core.quaternion_to_matrix)
def quaternion_to_matrix(q: ArrayLike, *, scalar_first: bool = True) -> NDArray[Any]:
    return _B(_Q2M, q, scalar_first=scalar_first)


@documented(_core.matrix_to_quaternion)
def matrix_to_quaternion(matrix: ArrayLike, *, scalar_first: bool = True) -> NDArray[Any]:
    return _B(_M2Q, matrix, scalar_first=scalar_first)


@documented(_core.standardize_quaternion)
def standardize_quaternion(q: ArrayLike, *, scalar_first: bool = True) -> NDArray[Any]:
    return _B(_core.standardize_quaternion, q, scalar_first=scalar_first)


@documented(_core.normalize_quaternion)
def normalize_quaternion(q: ArrayLike, *, scalar_first: bool = True) -> NDArray[Any]:
    return _B(_core.normalize_quaternion, q, scalar_first=scalar_first)


@documented(_core.wxyz_to_xyzw)
def wxyz_to_xyzw(q: ArrayLike) -> NDArray[Any]:
    return _B(_core.wxyz_to_xyzw, q)


@documented(_core.xyzw_to_wxyz)
def xyzw_to_wxyz(q: ArrayLike) -> NDArray[Any]:
    return _B(_core.xyzw_to_wxyz, q)


@documented(_rep.rotation_6d_to_matrix)
def rotation_6d_to_matrix(d6: ArrayLike, *, layout: Rotation6DLayout = "columns") -> NDArray[Any]:
    return _B(_rep.rotation_6d_to_matrix, d6, layout=layout)


@documented(_rep.matrix_to_rotation_6d)
def matrix_to_rotation_6d(matrix: ArrayLike, *, layout: Rotation6DLayout = "columns") -> NDArray[Any]:
    return _B(_rep.matrix_to_rotation_6d, matrix, layout=layout)


@documented(_rep.special_procrustes)
def special_procrustes(matrix: ArrayLike) -> NDArray[Any]:
    return _B(_rep.special_procrustes, matrix)


@documented(_rep.symmetric_matrix_to_quaternion)
def symmetric_matrix_to_quaternion(a: ArrayLike, *, scalar_first: bool = True) -> NDArray[Any]:
    return _B(_rep.symmetric_matrix_to_quaternion, a, scalar_first=scalar_first)


@documented(_rep.fit_rotation)
def fit_rotation(source: ArrayLike, target: ArrayLike, weights: ArrayLike | None = None) -> NDArray[Any]:
    return _B(_rep.fit_rotation, source, target, weights)


# Rotation vector, Euler angles, quaternion algebra, interpolation and distances.


@documented(_algebra.axis_angle_to_quaternion)
def axis_angle_to_quaternion(axis_angle: ArrayLike, *, scalar_first: bool = True) -> NDArray[Any]:
    return _B(_algebra.axis_angle_to_quaternion, axis_angle, scalar_first=scalar_first)


@documented(_algebra.quaternion_to_axis_angle)
def quaternion_to_axis_angle(q: ArrayLike, *, scalar_first: bool = True) -> NDArray[Any]:
    return _B(_algebra.quaternion_to_axis_angle, q, scalar_first=scalar_first)


@documented(_algebra.axis_angle_to_matrix)
def axis_angle_to_matrix(axis_angle: ArrayLike) -> NDArray[Any]:
    return _B(_algebra.axis_angle_to_matrix, axis_angle)


@documented(_algebra.matrix_to_axis_angle)
def matrix_to_axis_angle(matrix: ArrayLike) -> NDArray[Any]:
    return _B(_algebra.matrix_to_axis_angle, matrix, to_quaternion=_M2Q)


@documented(_euler.euler_angles_to_matrix)
def euler_angles_to_matrix(
    angles: ArrayLike, convention: EulerConvention, *, degrees: bool = False
) -> NDArray[Any]:
    return _B(_euler.euler_angles_to_matrix, angles, convention=convention, degrees=degrees, to_matrix=_Q2M)


@documented(_euler.matrix_to_euler_angles)
def matrix_to_euler_angles(
    matrix: ArrayLike, convention: EulerConvention, *, degrees: bool = False
) -> NDArray[Any]:
    # A NaN or an infinite entry gives NaN angles by design: no floating-point warnings on the way there.
    with np.errstate(invalid="ignore", divide="ignore", over="ignore"):
        return _B(_euler.matrix_to_euler_angles, matrix, convention=convention, degrees=degrees)


@documented(_euler.euler_angles_to_quaternion)
def euler_angles_to_quaternion(
    angles: ArrayLike, convention: EulerConvention, *, degrees: bool = False, scalar_first: bool = True
) -> NDArray[Any]:
    return _B(
        _euler.euler_angles_to_quaternion,
        angles,
        convention=convention,
        degrees=degrees,
        scalar_first=scalar_first,
    )


@documented(_euler.quaternion_to_euler_angles)
def quaternion_to_euler_angles(
    q: ArrayLike, convention: EulerConvention, *, degrees: bool = False, scalar_first: bool = True
) -> NDArray[Any]:
    return _B(
        _euler.quaternion_to_euler_angles,
        q,
        convention=convention,
        degrees=degrees,
        scalar_first=scalar_first,
    )


@documented(_algebra.quaternion_multiply)
def quaternion_multiply(p: ArrayLike, q: ArrayLike, *, scalar_first: bool = True) -> NDArray[Any]:
    return _B(_algebra.quaternion_multiply, p, q, scalar_first=scalar_first)


@documented(_algebra.quaternion_conjugate)
def quaternion_conjugate(q: ArrayLike, *, scalar_first: bool = True) -> NDArray[Any]:
    return _B(_algebra.quaternion_conjugate, q, scalar_first=scalar_first)


@documented(_algebra.quaternion_invert)
def quaternion_invert(q: ArrayLike, *, scalar_first: bool = True) -> NDArray[Any]:
    return _B(_algebra.quaternion_invert, q, scalar_first=scalar_first)


@documented(_algebra.quaternion_apply)
def quaternion_apply(q: ArrayLike, v: ArrayLike, *, scalar_first: bool = True) -> NDArray[Any]:
    return _B(_algebra.quaternion_apply, q, v, scalar_first=scalar_first)


@documented(_algebra.quaternion_slerp)
def quaternion_slerp(p: ArrayLike, q: ArrayLike, t: ArrayLike, *, scalar_first: bool = True) -> NDArray[Any]:
    return _B(_algebra.quaternion_slerp, p, q, t, scalar_first=scalar_first)


@documented(_algebra.quaternion_geodesic_distance)
def quaternion_geodesic_distance(p: ArrayLike, q: ArrayLike, *, scalar_first: bool = True) -> NDArray[Any]:
    # np.asarray: a 0-d result must stay an array, not become a NumPy scalar.
    return np.asarray(_B(_algebra.quaternion_geodesic_distance, p, q, scalar_first=scalar_first))


@documented(_algebra.matrix_geodesic_distance)
def matrix_geodesic_distance(matrix1: ArrayLike, matrix2: ArrayLike) -> NDArray[Any]:
    # np.asarray: a 0-d result must stay an array, not become a NumPy scalar.
    return np.asarray(_B(_algebra.matrix_geodesic_distance, matrix1, matrix2))


# SO(3) as a Lie group: hat and vee, exp and log, Jacobians, plus and minus (diffquat._lie).


@documented(_lie.so3_hat)
def so3_hat(omega: ArrayLike) -> NDArray[Any]:
    return _B(_lie.so3_hat, omega)


@documented(_lie.so3_left_jacobian)
def so3_left_jacobian(omega: ArrayLike) -> NDArray[Any]:
    return _B(_lie.so3_left_jacobian, omega)


@documented(_lie.so3_right_jacobian)
def so3_right_jacobian(omega: ArrayLike) -> NDArray[Any]:
    return _B(_lie.so3_right_jacobian, omega)


@documented(_lie.so3_left_jacobian_inverse)
def so3_left_jacobian_inverse(omega: ArrayLike) -> NDArray[Any]:
    return _B(_lie.so3_left_jacobian_inverse, omega)


@documented(_lie.so3_right_jacobian_inverse)
def so3_right_jacobian_inverse(omega: ArrayLike) -> NDArray[Any]:
    return _B(_lie.so3_right_jacobian_inverse, omega)


@documented(_lie.so3_vee)
def so3_vee(matrix: ArrayLike) -> NDArray[Any]:
    return _B(_lie.so3_vee, matrix)


@documented(_lie.so3_exp)
def so3_exp(omega: ArrayLike) -> NDArray[Any]:
    return _B(_lie.so3_exp, omega)


@documented(_lie.so3_log)
def so3_log(matrix: ArrayLike) -> NDArray[Any]:
    return _B(_lie.so3_log, matrix, to_quaternion=_M2Q)


@documented(_lie.so3_plus)
def so3_plus(matrix: ArrayLike, delta: ArrayLike, *, side: Side = "right") -> NDArray[Any]:
    return _B(_lie.so3_plus, matrix, delta, side=side, to_matrix=_Q2M)


@documented(_lie.so3_minus)
def so3_minus(matrix1: ArrayLike, matrix2: ArrayLike, *, side: Side = "right") -> NDArray[Any]:
    return _B(_lie.so3_minus, matrix1, matrix2, side=side, to_quaternion=_M2Q)


@documented(_lie.quaternion_plus)
def quaternion_plus(
    q: ArrayLike, delta: ArrayLike, *, side: Side = "right", scalar_first: bool = True
) -> NDArray[Any]:
    return _B(_lie.quaternion_plus, q, delta, side=side, scalar_first=scalar_first)


@documented(_lie.quaternion_minus)
def quaternion_minus(
    q1: ArrayLike, q2: ArrayLike, *, side: Side = "right", scalar_first: bool = True
) -> NDArray[Any]:
    return _B(_lie.quaternion_minus, q1, q2, side=side, scalar_first=scalar_first)


def random_quaternions(
    shape: int | tuple[int, ...] = (),
    *,
    rng: np.random.Generator | int | None = None,
    dtype: Any = np.float64,
    scalar_first: bool = True,
) -> NDArray[Any]:
    """Unit quaternions uniformly distributed over rotations (Shoemake's method), in canonical sign.

    Args:
        shape: batch shape; the result has shape ``(*shape, 4)``.
        rng: a ``numpy.random.Generator``, or a seed for ``numpy.random.default_rng``.
        dtype: floating dtype of the result (default float64).
        scalar_first: storage order of the result.
    """
    uniform = np.random.default_rng(rng).random((*shape_tuple(shape), 3))
    q = _B(_core.quaternions_from_uniform, uniform, scalar_first=scalar_first)
    return _B.cast_canonical(np.asarray(q), np.dtype(dtype), scalar_first)


# The matrix Fisher distribution on SO(3) and the Bingham NLL of the 10D head (diffquat._fisher).


@documented(_igso3.igso3_angle_cdf)
def igso3_angle_cdf(angle: ArrayLike, sigma: ArrayLike) -> NDArray[Any]:
    return np.asarray(_B(_igso3.igso3_angle_cdf, angle, sigma))


@documented(_igso3.igso3_log_density)
def igso3_log_density(angle: ArrayLike, sigma: ArrayLike) -> NDArray[Any]:
    return np.asarray(_B(_igso3.igso3_log_density, angle, sigma))


def igso3_sample(
    sigma: ArrayLike, shape: int | tuple[int, ...] = (), *, rng: np.random.Generator | int | None = None
) -> NDArray[Any]:
    (checked,), dtype = _B.validate("igso3_sample", sigma)
    compute = _B.compute_dtype(dtype)
    generator = np.random.default_rng(rng)
    size = (*shape_tuple(shape), *checked.shape)
    uniform = generator.random(size, dtype=compute)
    normal = generator.standard_normal((*size, 3), dtype=compute)
    return np.asarray(_B(_igso3.igso3_sample, checked, uniform=uniform, normal=normal))


igso3_sample.__doc__ = _igso3.SAMPLE_DOC.format(
    random="rng: a ``numpy.random.Generator``, or a seed for ``numpy.random.default_rng``."
)


@documented(_igso3.igso3_score)
def igso3_score(matrix: ArrayLike, sigma: ArrayLike, mean: ArrayLike | None = None) -> NDArray[Any]:
    return np.asarray(_B(_igso3.igso3_score, matrix, sigma, mean, to_quaternion=_M2Q))


@documented(_fi.matrix_fisher_log_normalizer)
def matrix_fisher_log_normalizer(F: ArrayLike) -> NDArray[Any]:
    return np.asarray(_B(_fi.matrix_fisher_log_normalizer, F))


@documented(_fi.matrix_fisher_nll)
def matrix_fisher_nll(F: ArrayLike, matrix: ArrayLike) -> NDArray[Any]:
    return np.asarray(_B(_fi.matrix_fisher_nll, F, matrix))


@documented(_fi.matrix_fisher_mode)
def matrix_fisher_mode(F: ArrayLike) -> NDArray[Any]:
    return _B(_fi.matrix_fisher_mode, F)


@documented(_fi.bingham_nll)
def bingham_nll(a: ArrayLike, q: ArrayLike, *, scalar_first: bool = True) -> NDArray[Any]:
    return np.asarray(_B(_fi.bingham_nll, a, q, scalar_first=scalar_first))


def matrix_fisher_sample(
    F: ArrayLike, shape: int | tuple[int, ...] = (), *, rng: np.random.Generator | int | None = None
) -> NDArray[Any]:
    """Rotations drawn from the matrix Fisher distribution ``exp(tr(F^T R)) / c(F)``.

    Args:
        F: the parameter, shape ``(..., 3, 3)``.
        shape: sample shape; the result has shape ``(*shape, ..., 3, 3)``, one draw per element of F's
            batch for every sample index.
        rng: a ``numpy.random.Generator``, or a seed for ``numpy.random.default_rng``.

    Exact: Kent et al.'s rejection sampler for the equivalent Bingham distribution on S^3 (an angular
    central Gaussian envelope, acceptance at least 0.447 for every F), with a fixed number of 64
    proposals per sample, the first accepted taken; all 64 fail with probability below 4e-17, and then
    the sample is the mode. Not differentiable (a rejection sampler has no reparameterisation).
    """
    (checked,), dtype = _B.validate("matrix_fisher_sample", F)
    compute = _B.compute_dtype(dtype)
    generator = np.random.default_rng(rng)
    size = (*shape_tuple(shape), *checked.shape[:-2], _fi.SAMPLE_PROPOSALS)

    def draw(k: int) -> tuple[NDArray[Any], NDArray[Any]]:
        return (
            generator.standard_normal((*size, 4), dtype=compute),
            generator.random(size, dtype=compute),
        )

    return _B(_fi.matrix_fisher_sample, checked, draw=draw)


# Rotation averaging and symmetric objects.


@documented(_stats.rotation_mean)
def rotation_mean(
    matrices: ArrayLike, weights: ArrayLike | None = None, *, method: MeanMethod = "chordal"
) -> NDArray[Any]:
    return _B(_stats.rotation_mean, matrices, weights, method=method, to_quaternion=_M2Q, to_matrix=_Q2M)


@documented(_stats.quaternion_mean)
def quaternion_mean(
    q: ArrayLike, weights: ArrayLike | None = None, *, scalar_first: bool = True
) -> NDArray[Any]:
    return _B(_stats.quaternion_mean, q, weights, scalar_first=scalar_first)


@documented(_stats.symmetric_geodesic_distance)
def symmetric_geodesic_distance(matrix1: ArrayLike, matrix2: ArrayLike, group: ArrayLike) -> NDArray[Any]:
    # np.asarray: a 0-d result must stay an array, not become a NumPy scalar.
    return np.asarray(_B(_stats.symmetric_geodesic_distance, matrix1, matrix2, group))


def symmetry_group(name: str, *, dtype: Any = np.float64) -> NDArray[Any]:
    return _stats.symmetry_group_matrices(name).astype(dtype)


symmetry_group.__doc__ = _stats.SYMMETRY_GROUP_DOC.format(
    keywords="        dtype: floating dtype of the result (default float64).\n"
)


# SE(3): poses as 4x4 matrices, their Lie calculus and interpolation (diffquat._se3).


@documented(_se3.se3_from_rotation_translation)
def se3_from_rotation_translation(rotation: ArrayLike, translation: ArrayLike) -> NDArray[Any]:
    return _B(_se3.se3_from_rotation_translation, rotation, translation)


@documented(_se3.se3_to_rotation_translation)
def se3_to_rotation_translation(matrix: ArrayLike) -> tuple[NDArray[Any], NDArray[Any]]:
    flat = _B(_se3.se3_to_rotation_translation, matrix)
    return flat[..., :9].reshape(*flat.shape[:-1], 3, 3), flat[..., 9:]


@documented(_se3.se3_compose)
def se3_compose(matrix1: ArrayLike, matrix2: ArrayLike) -> NDArray[Any]:
    return _B(_se3.se3_compose, matrix1, matrix2)


@documented(_se3.se3_inverse)
def se3_inverse(matrix: ArrayLike) -> NDArray[Any]:
    return _B(_se3.se3_inverse, matrix)


@documented(_se3.se3_apply)
def se3_apply(matrix: ArrayLike, points: ArrayLike) -> NDArray[Any]:
    return _B(_se3.se3_apply, matrix, points)


@documented(_se3.se3_hat)
def se3_hat(xi: ArrayLike) -> NDArray[Any]:
    return _B(_se3.se3_hat, xi)


@documented(_se3.se3_vee)
def se3_vee(matrix: ArrayLike) -> NDArray[Any]:
    return _B(_se3.se3_vee, matrix)


@documented(_se3.se3_exp)
def se3_exp(xi: ArrayLike) -> NDArray[Any]:
    return _B(_se3.se3_exp, xi)


@documented(_se3.se3_log)
def se3_log(matrix: ArrayLike) -> NDArray[Any]:
    return _B(_se3.se3_log, matrix, to_quaternion=_M2Q)


@documented(_se3.se3_adjoint)
def se3_adjoint(matrix: ArrayLike) -> NDArray[Any]:
    return _B(_se3.se3_adjoint, matrix)


@documented(_se3.se3_ad)
def se3_ad(xi: ArrayLike) -> NDArray[Any]:
    return _B(_se3.se3_ad, xi)


@documented(_se3.se3_left_jacobian)
def se3_left_jacobian(xi: ArrayLike) -> NDArray[Any]:
    return _B(_se3.se3_left_jacobian, xi)


@documented(_se3.se3_right_jacobian)
def se3_right_jacobian(xi: ArrayLike) -> NDArray[Any]:
    return _B(_se3.se3_right_jacobian, xi)


@documented(_se3.se3_left_jacobian_inverse)
def se3_left_jacobian_inverse(xi: ArrayLike) -> NDArray[Any]:
    return _B(_se3.se3_left_jacobian_inverse, xi)


@documented(_se3.se3_right_jacobian_inverse)
def se3_right_jacobian_inverse(xi: ArrayLike) -> NDArray[Any]:
    return _B(_se3.se3_right_jacobian_inverse, xi)


@documented(_se3.se3_plus)
def se3_plus(matrix: ArrayLike, delta: ArrayLike, *, side: Side = "right") -> NDArray[Any]:
    return _B(_se3.se3_plus, matrix, delta, side=side)


@documented(_se3.se3_minus)
def se3_minus(matrix1: ArrayLike, matrix2: ArrayLike, *, side: Side = "right") -> NDArray[Any]:
    return _B(_se3.se3_minus, matrix1, matrix2, side=side, to_quaternion=_M2Q)


@documented(_se3.se3_interpolate)
def se3_interpolate(
    matrix1: ArrayLike, matrix2: ArrayLike, t: ArrayLike, *, mode: SE3Interpolation = "screw"
) -> NDArray[Any]:
    return _B(_se3.se3_interpolate, matrix1, matrix2, t, mode=mode, to_quaternion=_M2Q)


@documented(_se3.pose_to_matrix)
def pose_to_matrix(pose: ArrayLike, *, layout: PoseLayout) -> NDArray[Any]:
    return _B(_se3.pose_to_matrix, pose, layout=layout, to_matrix=_Q2M)


@documented(_se3.matrix_to_pose)
def matrix_to_pose(matrix: ArrayLike, *, layout: PoseLayout) -> NDArray[Any]:
    return _B(_se3.matrix_to_pose, matrix, layout=layout, to_quaternion=_M2Q)


@documented(_se3.se3_mean)
def se3_mean(matrices: ArrayLike, weights: ArrayLike | None = None) -> NDArray[Any]:
    return _B(
        _se3.se3_mean,
        matrices,
        weights,
        rotation_mean=_stats.rotation_mean,
        procrustes=_rep.special_procrustes,
    )


@documented(_se3.fit_rigid_transform)
def fit_rigid_transform(
    source: ArrayLike, target: ArrayLike, weights: ArrayLike | None = None
) -> NDArray[Any]:
    return _B(_se3.fit_rigid_transform, source, target, weights, procrustes=_rep.special_procrustes)


@documented(_se3.fit_similarity_transform)
def fit_similarity_transform(
    source: ArrayLike, target: ArrayLike, weights: ArrayLike | None = None
) -> tuple[NDArray[Any], NDArray[Any]]:
    packed = _B(_se3.fit_similarity_transform, source, target, weights, procrustes=_rep.special_procrustes)
    return _se3.split_similarity(_B.xp, packed)


@documented(_se3.rotation_between_vectors)
def rotation_between_vectors(a: ArrayLike, b: ArrayLike) -> NDArray[Any]:
    return _B(_se3.rotation_between_vectors, a, b)


@documented(_se3.frame_from_three_points)
def frame_from_three_points(x1: ArrayLike, x2: ArrayLike, x3: ArrayLike) -> NDArray[Any]:
    return _B(_se3.frame_from_three_points, x1, x2, x3)


# Rotations in time: angular velocity and acceleration, integration, SQUAD and B-splines (diffquat._motion).


@documented(_motion.angular_velocity)
def angular_velocity(
    q: ArrayLike, q_dot: ArrayLike, *, frame: Frame = "body", scalar_first: bool = True
) -> NDArray[Any]:
    return _B(_motion.angular_velocity, q, q_dot, frame=frame, scalar_first=scalar_first)


@documented(_motion.quaternion_derivative)
def quaternion_derivative(
    q: ArrayLike, omega: ArrayLike, *, frame: Frame = "body", scalar_first: bool = True
) -> NDArray[Any]:
    return _B(_motion.quaternion_derivative, q, omega, frame=frame, scalar_first=scalar_first)


@documented(_motion.angular_acceleration)
def angular_acceleration(
    q: ArrayLike, q_dot: ArrayLike, q_ddot: ArrayLike, *, frame: Frame = "body", scalar_first: bool = True
) -> NDArray[Any]:
    return _B(_motion.angular_acceleration, q, q_dot, q_ddot, frame=frame, scalar_first=scalar_first)


@documented(_motion.integrate_angular_velocity)
def integrate_angular_velocity(
    q: ArrayLike, omega: ArrayLike, dt: ArrayLike | float, *, frame: Frame = "body", scalar_first: bool = True
) -> NDArray[Any]:
    return _B(_motion.integrate_angular_velocity, q, omega, dt, frame=frame, scalar_first=scalar_first)


@documented(_motion.bound_angular_velocity_from_quaternions)
def angular_velocity_from_quaternions(
    q: ArrayLike, dt: ArrayLike | float, *, frame: Frame = "body", scalar_first: bool = True
) -> NDArray[Any]:
    return _B(_motion.bound_angular_velocity_from_quaternions, q, dt, frame=frame, scalar_first=scalar_first)


@documented(_motion.quaternion_squad)
def quaternion_squad(q: ArrayLike, t: ArrayLike | float, *, scalar_first: bool = True) -> NDArray[Any]:
    return _B(_motion.quaternion_squad, q, t, scalar_first=scalar_first)


@documented(_motion.so3_bspline)
def so3_bspline(
    control: ArrayLike, u: ArrayLike | float, *, order: int = 4
) -> tuple[NDArray[Any], NDArray[Any], NDArray[Any]]:
    packed = _B(_motion.bound_so3_bspline, control, u, order=order, to_quaternion=_M2Q)
    return _motion.split_so3_bspline(_B.xp, packed)


@documented(_motion.se3_bspline)
def se3_bspline(
    control: ArrayLike, u: ArrayLike | float, *, order: int = 4, mode: SplineMode = "se3"
) -> tuple[NDArray[Any], NDArray[Any], NDArray[Any]]:
    packed = _B(_motion.bound_se3_bspline, control, u, order=order, mode=mode, to_quaternion=_M2Q)
    return _motion.split_se3_bspline(_B.xp, packed)


# SO3 and SE3 objects over the functions above (diffquat._objects, written once).


def _identity(n: int, shape: int | tuple[int, ...] = (), *, dtype: Any = np.float64) -> NDArray[Any]:
    return np.broadcast_to(np.eye(n, dtype=dtype), (*shape_tuple(shape), n, n)).copy()


def _draw(
    module: Any,
    shape: int | tuple[int, ...] = (),
    *,
    rng: np.random.Generator | int | None = None,
    dtype: Any = np.float64,
) -> tuple[NDArray[Any], NDArray[Any]]:
    generator = np.random.default_rng(rng)
    q = random_quaternions(shape, rng=generator, dtype=dtype)
    return q, generator.standard_normal((*shape_tuple(shape), 3)).astype(dtype)


SO3, SE3 = _objects.bind(
    sys.modules[__name__],
    _objects.Native(
        xp=np, array=np.ndarray, identity=_identity, draw=_draw, device=lambda x: "cpu", astype=_B.astype
    ),
)
