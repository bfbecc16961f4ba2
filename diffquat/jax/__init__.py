"""diffquat on JAX. Same names and semantics as ``diffquat.numpy`` and ``diffquat.torch``; the
conventions are on the documentation's Conventions page. Every function is traceable by ``jit``,
``vmap``, ``grad`` and ``jacfwd``/``jacrev``, runs under ``shard_map``, ``pmap`` and sharded ``jit``,
and exports with ``jax.export`` (the exported program is plain StableHLO: it runs where diffquat is
not installed)."""

from __future__ import annotations

import functools
import sys
from typing import Any

import jax
import jax.numpy as jnp
from jax import Array
from jax.typing import ArrayLike

from .. import _algebra, _core, _euler, _igso3, _lie, _motion, _objects, _se3
from .. import _fisher as _fi
from .. import _representations as _rep
from .. import _statistics as _stats
from .._backend import Backend, documented, shape_tuple
from .._public import public_dir as _public_dir
from .._types import (
    EulerConvention,
    Frame,
    MeanMethod,
    PoseLayout,
    Rotation6DLayout,
    SE3Interpolation,
    Side,
    SplineMode,
)
from ._custom import custom_derivative
from ._namespace import XP

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
    # A Python number for a scalar argument stays one, weakly typed in jax's promotion.
    if scalar and isinstance(x, int | float) and not isinstance(x, bool):
        return x
    # Strings, bytes and other objects that are no numbers: jax's own error names no diffquat function
    # (and numpy parses a numeric string where jax refuses it), so the refusal is diffquat's.
    if isinstance(x, str | bytes):
        raise TypeError(f"{fname}: expected {argname} to be an array, got {type(x).__name__}")
    try:
        return jnp.asarray(x)
    except (TypeError, ValueError) as error:
        raise TypeError(
            f"{fname}: expected {argname} to be an array, got {type(x).__name__}: {error}"
        ) from error


_B = Backend(
    xp=XP,
    convert=_convert,
    is_floating=lambda dtype: bool(jnp.issubdtype(dtype, jnp.floating)),
    is_integral=lambda dtype: bool(jnp.issubdtype(dtype, jnp.integer) or jnp.issubdtype(dtype, jnp.bool_)),
    result_type=lambda xs: jnp.result_type(*xs),
    # float64 where x64 is enabled, float32 otherwise: what jnp.sin makes of an integer array
    default_float=lambda: jnp.dtype(jax.dtypes.canonicalize_dtype(jnp.float64)),
    astype=lambda x, dtype: x.astype(dtype),
    scalar=lambda value, dtype, like: jnp.asarray(value, dtype=dtype),
    float32=jnp.dtype(jnp.float32),
)


# The conversions as every backend binds them (diffquat._core.registered_conversions): matrix_to_quaternion
# with its tangent rule, a custom_jvp (XLA's own derivative of the formula carries all four candidates
# through the selection, about twice the work forward + backward), quaternion_to_matrix as its formula,
# whose autodiff XLA compiles as well as the rule's transpose.
_CONVERSIONS = _core.registered_conversions(
    lambda name, rule, _: custom_derivative(rule[0], rule[1]) if name == "matrix_to_quaternion" else rule[0]
)
_Q2M, _M2Q = _CONVERSIONS["quaternion_to_matrix"], _CONVERSIONS["matrix_to_quaternion"]


@documented(_core.quaternion_to_matrix)
def quaternion_to_matrix(q: ArrayLike, *, scalar_first: bool = True) -> Array:
    return _B(_Q2M, q, scalar_first=scalar_first)


@documented(_core.matrix_to_quaternion)
def matrix_to_quaternion(matrix: ArrayLike, *, scalar_first: bool = True) -> Array:
    return _B(_M2Q, matrix, scalar_first=scalar_first)


@documented(_core.standardize_quaternion)
def standardize_quaternion(q: ArrayLike, *, scalar_first: bool = True) -> Array:
    return _B(_core.standardize_quaternion, q, scalar_first=scalar_first)


@documented(_core.normalize_quaternion)
def normalize_quaternion(q: ArrayLike, *, scalar_first: bool = True) -> Array:
    return _B(_core.normalize_quaternion, q, scalar_first=scalar_first)


@documented(_core.wxyz_to_xyzw)
def wxyz_to_xyzw(q: ArrayLike) -> Array:
    return _B(_core.wxyz_to_xyzw, q)


@documented(_core.xyzw_to_wxyz)
def xyzw_to_wxyz(q: ArrayLike) -> Array:
    return _B(_core.xyzw_to_wxyz, q)


def _compiled(core_fn: Any, *static: str) -> Any:
    """``core_fn`` compiled as one XLA computation: run eagerly, jax would compile each of its many
    small operations separately for every new shape (seconds per call); under an outer ``jit`` this
    inlines. ``xp`` and the keyword options are static."""
    return jax.jit(core_fn, static_argnums=0, static_argnames=static)


# The SVD and eigh maps with their closed-form derivatives (see diffquat._representations).
_special_procrustes = _compiled(
    custom_derivative(_rep.special_procrustes, _rep.procrustes_tangent, _rep.procrustes_cotangent)
)
_smallest_eigenvector = custom_derivative(
    _rep.smallest_eigenvector, _rep.eigenvector_tangent, _rep.eigenvector_cotangent
)
_rotation_6d_to_matrix = _compiled(_rep.rotation_6d_to_matrix, "layout")
_symmetric_matrix_to_quaternion = _compiled(
    _rep.symmetric_matrix_to_quaternion, "scalar_first", "eigenvector"
)
_fit_rotation = _compiled(_rep.fit_rotation, "procrustes")


@documented(_rep.rotation_6d_to_matrix)
def rotation_6d_to_matrix(d6: ArrayLike, *, layout: Rotation6DLayout = "columns") -> Array:
    return _B(_rotation_6d_to_matrix, d6, layout=layout)


@documented(_rep.matrix_to_rotation_6d)
def matrix_to_rotation_6d(matrix: ArrayLike, *, layout: Rotation6DLayout = "columns") -> Array:
    return _B(_rep.matrix_to_rotation_6d, matrix, layout=layout)


@documented(_rep.special_procrustes)
def special_procrustes(matrix: ArrayLike) -> Array:
    return _B(_special_procrustes, matrix)


@documented(_rep.symmetric_matrix_to_quaternion)
def symmetric_matrix_to_quaternion(a: ArrayLike, *, scalar_first: bool = True) -> Array:
    return _B(
        _symmetric_matrix_to_quaternion, a, scalar_first=scalar_first, eigenvector=_smallest_eigenvector
    )


@documented(_rep.fit_rotation)
def fit_rotation(source: ArrayLike, target: ArrayLike, weights: ArrayLike | None = None) -> Array:
    return _B(_fit_rotation, source, target, weights, procrustes=_special_procrustes)


# Rotation vector, Euler angles, quaternion algebra, interpolation and distances.


@documented(_algebra.axis_angle_to_quaternion)
def axis_angle_to_quaternion(axis_angle: ArrayLike, *, scalar_first: bool = True) -> Array:
    return _B(_algebra.axis_angle_to_quaternion, axis_angle, scalar_first=scalar_first)


@documented(_algebra.quaternion_to_axis_angle)
def quaternion_to_axis_angle(q: ArrayLike, *, scalar_first: bool = True) -> Array:
    return _B(_algebra.quaternion_to_axis_angle, q, scalar_first=scalar_first)


@documented(_algebra.axis_angle_to_matrix)
def axis_angle_to_matrix(axis_angle: ArrayLike) -> Array:
    return _B(_algebra.axis_angle_to_matrix, axis_angle)


@documented(_algebra.matrix_to_axis_angle)
def matrix_to_axis_angle(matrix: ArrayLike) -> Array:
    return _B(_algebra.matrix_to_axis_angle, matrix, to_quaternion=_M2Q)


@documented(_euler.euler_angles_to_matrix)
def euler_angles_to_matrix(angles: ArrayLike, convention: EulerConvention, *, degrees: bool = False) -> Array:
    return _B(_euler.euler_angles_to_matrix, angles, convention=convention, degrees=degrees, to_matrix=_Q2M)


@documented(_euler.matrix_to_euler_angles)
def matrix_to_euler_angles(matrix: ArrayLike, convention: EulerConvention, *, degrees: bool = False) -> Array:
    return _B(_euler.matrix_to_euler_angles, matrix, convention=convention, degrees=degrees)


@documented(_euler.euler_angles_to_quaternion)
def euler_angles_to_quaternion(
    angles: ArrayLike, convention: EulerConvention, *, degrees: bool = False, scalar_first: bool = True
) -> Array:
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
) -> Array:
    return _B(
        _euler.quaternion_to_euler_angles,
        q,
        convention=convention,
        degrees=degrees,
        scalar_first=scalar_first,
    )


@documented(_algebra.quaternion_multiply)
def quaternion_multiply(p: ArrayLike, q: ArrayLike, *, scalar_first: bool = True) -> Array:
    return _B(_algebra.quaternion_multiply, p, q, scalar_first=scalar_first)


@documented(_algebra.quaternion_conjugate)
def quaternion_conjugate(q: ArrayLike, *, scalar_first: bool = True) -> Array:
    return _B(_algebra.quaternion_conjugate, q, scalar_first=scalar_first)


@documented(_algebra.quaternion_invert)
def quaternion_invert(q: ArrayLike, *, scalar_first: bool = True) -> Array:
    return _B(_algebra.quaternion_invert, q, scalar_first=scalar_first)


@documented(_algebra.quaternion_apply)
def quaternion_apply(q: ArrayLike, v: ArrayLike, *, scalar_first: bool = True) -> Array:
    return _B(_algebra.quaternion_apply, q, v, scalar_first=scalar_first)


@documented(_algebra.quaternion_slerp)
def quaternion_slerp(p: ArrayLike, q: ArrayLike, t: ArrayLike, *, scalar_first: bool = True) -> Array:
    return _B(_algebra.quaternion_slerp, p, q, t, scalar_first=scalar_first)


@documented(_algebra.quaternion_geodesic_distance)
def quaternion_geodesic_distance(p: ArrayLike, q: ArrayLike, *, scalar_first: bool = True) -> Array:
    return _B(_algebra.quaternion_geodesic_distance, p, q, scalar_first=scalar_first)


@documented(_algebra.matrix_geodesic_distance)
def matrix_geodesic_distance(matrix1: ArrayLike, matrix2: ArrayLike) -> Array:
    return _B(_algebra.matrix_geodesic_distance, matrix1, matrix2)


# SO(3) as a Lie group: hat and vee, exp and log, Jacobians, plus and minus (diffquat._lie).


@documented(_lie.so3_hat)
def so3_hat(omega: ArrayLike) -> Array:
    return _B(_lie.so3_hat, omega)


@documented(_lie.so3_left_jacobian)
def so3_left_jacobian(omega: ArrayLike) -> Array:
    return _B(_lie.so3_left_jacobian, omega)


@documented(_lie.so3_right_jacobian)
def so3_right_jacobian(omega: ArrayLike) -> Array:
    return _B(_lie.so3_right_jacobian, omega)


@documented(_lie.so3_left_jacobian_inverse)
def so3_left_jacobian_inverse(omega: ArrayLike) -> Array:
    return _B(_lie.so3_left_jacobian_inverse, omega)


@documented(_lie.so3_right_jacobian_inverse)
def so3_right_jacobian_inverse(omega: ArrayLike) -> Array:
    return _B(_lie.so3_right_jacobian_inverse, omega)


@documented(_lie.so3_vee)
def so3_vee(matrix: ArrayLike) -> Array:
    return _B(_lie.so3_vee, matrix)


@documented(_lie.so3_exp)
def so3_exp(omega: ArrayLike) -> Array:
    return _B(_lie.so3_exp, omega)


@documented(_lie.so3_log)
def so3_log(matrix: ArrayLike) -> Array:
    return _B(_lie.so3_log, matrix, to_quaternion=_M2Q)


@documented(_lie.so3_plus)
def so3_plus(matrix: ArrayLike, delta: ArrayLike, *, side: Side = "right") -> Array:
    return _B(_lie.so3_plus, matrix, delta, side=side, to_matrix=_Q2M)


@documented(_lie.so3_minus)
def so3_minus(matrix1: ArrayLike, matrix2: ArrayLike, *, side: Side = "right") -> Array:
    return _B(_lie.so3_minus, matrix1, matrix2, side=side, to_quaternion=_M2Q)


@documented(_lie.quaternion_plus)
def quaternion_plus(
    q: ArrayLike, delta: ArrayLike, *, side: Side = "right", scalar_first: bool = True
) -> Array:
    return _B(_lie.quaternion_plus, q, delta, side=side, scalar_first=scalar_first)


@documented(_lie.quaternion_minus)
def quaternion_minus(
    q1: ArrayLike, q2: ArrayLike, *, side: Side = "right", scalar_first: bool = True
) -> Array:
    return _B(_lie.quaternion_minus, q1, q2, side=side, scalar_first=scalar_first)


def random_quaternions(
    shape: int | tuple[int, ...] = (),
    *,
    key: Array,
    dtype: Any = None,
    scalar_first: bool = True,
) -> Array:
    """Unit quaternions uniformly distributed over rotations (Shoemake's method), in canonical sign.

    Args:
        shape: batch shape; the result has shape ``(*shape, 4)``.
        key: a ``jax.random`` key (required: JAX has no global random state).
        dtype: floating dtype of the result (default: float64 if x64 is enabled, else float32).
        scalar_first: storage order of the result.
    """
    dtype = jnp.dtype(jax.dtypes.canonicalize_dtype(jnp.float64) if dtype is None else dtype)
    uniform = jax.random.uniform(key, (*shape_tuple(shape), 3), dtype=_B.compute_dtype(dtype))
    q = _B(_core.quaternions_from_uniform, uniform, scalar_first=scalar_first)
    return _B.cast_canonical(q, dtype, scalar_first)


# The matrix Fisher distribution on SO(3) and the Bingham NLL of the 10D head (diffquat._fisher): the
# Bingham log normaliser of a symmetric 4x4 matrix with its gradient (the second moment) and Hessian
# (the rule of the second moment) in closed form, exact where eigenvalues repeat.
_reduced_second_moment = custom_derivative(_fi.reduced_second_moment, _fi.reduced_second_moment_tangent)
_reduced_log_normalizer = custom_derivative(
    _fi.reduced_log_normalizer,
    functools.partial(_fi.reduced_log_normalizer_tangent, moment=_reduced_second_moment),
)
_matrix_fisher_log_normalizer = _compiled(_fi.matrix_fisher_log_normalizer, "normalizer")
_matrix_fisher_nll = _compiled(_fi.matrix_fisher_nll, "normalizer")
_matrix_fisher_mode = _compiled(_fi.matrix_fisher_mode, "procrustes")
_bingham_nll = _compiled(_fi.bingham_nll, "scalar_first", "normalizer")


@documented(_igso3.igso3_angle_cdf)
def igso3_angle_cdf(angle: ArrayLike, sigma: ArrayLike) -> Array:
    return _B(_igso3.igso3_angle_cdf, angle, sigma)


@documented(_igso3.igso3_log_density)
def igso3_log_density(angle: ArrayLike, sigma: ArrayLike) -> Array:
    return _B(_igso3.igso3_log_density, angle, sigma)


def igso3_sample(sigma: ArrayLike, shape: int | tuple[int, ...] = (), *, key: Array) -> Array:
    (checked,), dtype = _B.validate("igso3_sample", sigma)
    compute = _B.compute_dtype(dtype)
    size = (*shape_tuple(shape), *checked.shape)
    k_uniform, k_normal = jax.random.split(key)
    uniform = jax.random.uniform(k_uniform, size, dtype=compute)
    normal = jax.random.normal(k_normal, (*size, 3), dtype=compute)
    return _B(_igso3.igso3_sample, checked, uniform=uniform, normal=normal)


igso3_sample.__doc__ = _igso3.SAMPLE_DOC.format(
    random="key: a ``jax.random`` key (required: JAX has no global random state)."
)


@documented(_igso3.igso3_score)
def igso3_score(matrix: ArrayLike, sigma: ArrayLike, mean: ArrayLike | None = None) -> Array:
    return _B(_igso3.igso3_score, matrix, sigma, mean, to_quaternion=_M2Q)


@documented(_fi.matrix_fisher_log_normalizer)
def matrix_fisher_log_normalizer(F: ArrayLike) -> Array:
    return _B(_matrix_fisher_log_normalizer, F, normalizer=_reduced_log_normalizer)


@documented(_fi.matrix_fisher_nll)
def matrix_fisher_nll(F: ArrayLike, matrix: ArrayLike) -> Array:
    return _B(_matrix_fisher_nll, F, matrix, normalizer=_reduced_log_normalizer)


@documented(_fi.matrix_fisher_mode)
def matrix_fisher_mode(F: ArrayLike) -> Array:
    return _B(_matrix_fisher_mode, F, procrustes=_special_procrustes)


@documented(_fi.bingham_nll)
def bingham_nll(a: ArrayLike, q: ArrayLike, *, scalar_first: bool = True) -> Array:
    return _B(_bingham_nll, a, q, scalar_first=scalar_first, normalizer=_reduced_log_normalizer)


def _sample_from(xp: Any, F: Array, *, normal: Array, uniform: Array) -> Array:
    """The sampler on random numbers drawn for all rounds at once, ``(rounds, ...)``."""
    return _fi.matrix_fisher_sample(xp, F, draw=lambda k: (normal[k], uniform[k]))


_sample_from.__name__ = "matrix_fisher_sample"  # the Backend validates by this name
_sample = _compiled(_sample_from)


def matrix_fisher_sample(F: ArrayLike, shape: int | tuple[int, ...] = (), *, key: Array) -> Array:
    """Rotations drawn from the matrix Fisher distribution ``exp(tr(F^T R)) / c(F)``.

    Args:
        F: the parameter, shape ``(..., 3, 3)``.
        shape: sample shape; the result has shape ``(*shape, ..., 3, 3)``, in F's dtype.
        key: a ``jax.random`` key (required: JAX has no global random state).

    Exact: Kent et al.'s rejection sampler for the equivalent Bingham distribution on S^3 (an angular
    central Gaussian envelope, acceptance at least 0.447 for every F), with a fixed number of 64
    proposals per sample, the first accepted taken; all 64 fail with probability below 4e-17, and then
    the sample is the mode. Traceable by ``jit`` and ``vmap``. Not differentiable (a rejection sampler
    has no reparameterisation): F enters through ``stop_gradient``.
    """
    (checked,), dtype = _B.validate("matrix_fisher_sample", F)
    compute = _B.compute_dtype(dtype)
    size = (_fi.SAMPLE_ROUNDS, *shape_tuple(shape), *checked.shape[:-2], _fi.SAMPLE_PROPOSALS)
    k_normal, k_uniform = jax.random.split(key)
    normal = jax.random.normal(k_normal, (*size, 4), dtype=compute)
    uniform = jax.random.uniform(k_uniform, size, dtype=compute)
    return _B(_sample, jax.lax.stop_gradient(checked), normal=normal, uniform=uniform)


# Rotation averaging and symmetric objects. The geodesic means with their implicit derivatives (see
# diffquat._statistics): jax transposes the tangent rule for reverse mode.
_karcher_mean = custom_derivative(_stats.karcher_mean, _stats.karcher_tangent)
_geodesic_median = custom_derivative(_stats.geodesic_median, _stats.median_tangent)
_rotation_mean = _compiled(
    _stats.rotation_mean, "method", "procrustes", "karcher", "median", "to_quaternion", "to_matrix"
)
_quaternion_mean = _compiled(_stats.quaternion_mean, "scalar_first", "eigenvector")
_symmetric_geodesic_distance = _compiled(_stats.symmetric_geodesic_distance)


@documented(_stats.rotation_mean)
def rotation_mean(
    matrices: ArrayLike, weights: ArrayLike | None = None, *, method: MeanMethod = "chordal"
) -> Array:
    _stats.check_method("rotation_mean", method)  # before jit, whose static arguments must hash
    return _B(
        _rotation_mean,
        matrices,
        weights,
        method=method,
        procrustes=_special_procrustes,
        karcher=_karcher_mean,
        median=_geodesic_median,
        to_quaternion=_M2Q,
        to_matrix=_Q2M,
    )


@documented(_stats.quaternion_mean)
def quaternion_mean(q: ArrayLike, weights: ArrayLike | None = None, *, scalar_first: bool = True) -> Array:
    return _B(_quaternion_mean, q, weights, scalar_first=scalar_first, eigenvector=_smallest_eigenvector)


@documented(_stats.symmetric_geodesic_distance)
def symmetric_geodesic_distance(matrix1: ArrayLike, matrix2: ArrayLike, group: ArrayLike) -> Array:
    return _B(_symmetric_geodesic_distance, matrix1, matrix2, group)


def symmetry_group(name: str, *, dtype: Any = None) -> Array:
    dtype = jnp.dtype(jax.dtypes.canonicalize_dtype(jnp.float64) if dtype is None else dtype)
    return jnp.asarray(_stats.symmetry_group_matrices(name), dtype=dtype)


symmetry_group.__doc__ = _stats.SYMMETRY_GROUP_DOC.format(
    keywords="        dtype: floating dtype of the result (default float64 where x64 is on, else float32).\n"
)


# SE(3): poses as 4x4 matrices, their Lie calculus and interpolation (diffquat._se3).


@documented(_se3.se3_from_rotation_translation)
def se3_from_rotation_translation(rotation: ArrayLike, translation: ArrayLike) -> Array:
    return _B(_se3.se3_from_rotation_translation, rotation, translation)


@documented(_se3.se3_to_rotation_translation)
def se3_to_rotation_translation(matrix: ArrayLike) -> tuple[Array, Array]:
    flat = _B(_se3.se3_to_rotation_translation, matrix)
    return flat[..., :9].reshape(*flat.shape[:-1], 3, 3), flat[..., 9:]


@documented(_se3.se3_compose)
def se3_compose(matrix1: ArrayLike, matrix2: ArrayLike) -> Array:
    return _B(_se3.se3_compose, matrix1, matrix2)


@documented(_se3.se3_inverse)
def se3_inverse(matrix: ArrayLike) -> Array:
    return _B(_se3.se3_inverse, matrix)


@documented(_se3.se3_apply)
def se3_apply(matrix: ArrayLike, points: ArrayLike) -> Array:
    return _B(_se3.se3_apply, matrix, points)


@documented(_se3.se3_hat)
def se3_hat(xi: ArrayLike) -> Array:
    return _B(_se3.se3_hat, xi)


@documented(_se3.se3_vee)
def se3_vee(matrix: ArrayLike) -> Array:
    return _B(_se3.se3_vee, matrix)


@documented(_se3.se3_exp)
def se3_exp(xi: ArrayLike) -> Array:
    return _B(_se3.se3_exp, xi)


@documented(_se3.se3_log)
def se3_log(matrix: ArrayLike) -> Array:
    return _B(_se3.se3_log, matrix, to_quaternion=_M2Q)


@documented(_se3.se3_adjoint)
def se3_adjoint(matrix: ArrayLike) -> Array:
    return _B(_se3.se3_adjoint, matrix)


@documented(_se3.se3_ad)
def se3_ad(xi: ArrayLike) -> Array:
    return _B(_se3.se3_ad, xi)


@documented(_se3.se3_left_jacobian)
def se3_left_jacobian(xi: ArrayLike) -> Array:
    return _B(_se3.se3_left_jacobian, xi)


@documented(_se3.se3_right_jacobian)
def se3_right_jacobian(xi: ArrayLike) -> Array:
    return _B(_se3.se3_right_jacobian, xi)


@documented(_se3.se3_left_jacobian_inverse)
def se3_left_jacobian_inverse(xi: ArrayLike) -> Array:
    return _B(_se3.se3_left_jacobian_inverse, xi)


@documented(_se3.se3_right_jacobian_inverse)
def se3_right_jacobian_inverse(xi: ArrayLike) -> Array:
    return _B(_se3.se3_right_jacobian_inverse, xi)


@documented(_se3.se3_plus)
def se3_plus(matrix: ArrayLike, delta: ArrayLike, *, side: Side = "right") -> Array:
    return _B(_se3.se3_plus, matrix, delta, side=side)


@documented(_se3.se3_minus)
def se3_minus(matrix1: ArrayLike, matrix2: ArrayLike, *, side: Side = "right") -> Array:
    return _B(_se3.se3_minus, matrix1, matrix2, side=side, to_quaternion=_M2Q)


@documented(_se3.se3_interpolate)
def se3_interpolate(
    matrix1: ArrayLike, matrix2: ArrayLike, t: ArrayLike, *, mode: SE3Interpolation = "screw"
) -> Array:
    return _B(_se3.se3_interpolate, matrix1, matrix2, t, mode=mode, to_quaternion=_M2Q)


@documented(_se3.pose_to_matrix)
def pose_to_matrix(pose: ArrayLike, *, layout: PoseLayout) -> Array:
    return _B(_se3.pose_to_matrix, pose, layout=layout, to_matrix=_Q2M)


@documented(_se3.matrix_to_pose)
def matrix_to_pose(matrix: ArrayLike, *, layout: PoseLayout) -> Array:
    return _B(_se3.matrix_to_pose, matrix, layout=layout, to_quaternion=_M2Q)


@documented(_se3.se3_mean)
def se3_mean(matrices: ArrayLike, weights: ArrayLike | None = None) -> Array:
    return _B(_se3.se3_mean, matrices, weights, rotation_mean=_rotation_mean, procrustes=_special_procrustes)


@documented(_se3.fit_rigid_transform)
def fit_rigid_transform(source: ArrayLike, target: ArrayLike, weights: ArrayLike | None = None) -> Array:
    return _B(_se3.fit_rigid_transform, source, target, weights, procrustes=_special_procrustes)


@documented(_se3.fit_similarity_transform)
def fit_similarity_transform(
    source: ArrayLike, target: ArrayLike, weights: ArrayLike | None = None
) -> tuple[Array, Array]:
    packed = _B(_se3.fit_similarity_transform, source, target, weights, procrustes=_special_procrustes)
    return _se3.split_similarity(_B.xp, packed)


@documented(_se3.rotation_between_vectors)
def rotation_between_vectors(a: ArrayLike, b: ArrayLike) -> Array:
    return _B(_se3.rotation_between_vectors, a, b)


@documented(_se3.frame_from_three_points)
def frame_from_three_points(x1: ArrayLike, x2: ArrayLike, x3: ArrayLike) -> Array:
    return _B(_se3.frame_from_three_points, x1, x2, x3)


# Rotations in time: angular velocity and acceleration, integration, SQUAD and B-splines (diffquat._motion).


@documented(_motion.angular_velocity)
def angular_velocity(
    q: ArrayLike, q_dot: ArrayLike, *, frame: Frame = "body", scalar_first: bool = True
) -> Array:
    return _B(_motion.angular_velocity, q, q_dot, frame=frame, scalar_first=scalar_first)


@documented(_motion.quaternion_derivative)
def quaternion_derivative(
    q: ArrayLike, omega: ArrayLike, *, frame: Frame = "body", scalar_first: bool = True
) -> Array:
    return _B(_motion.quaternion_derivative, q, omega, frame=frame, scalar_first=scalar_first)


@documented(_motion.angular_acceleration)
def angular_acceleration(
    q: ArrayLike, q_dot: ArrayLike, q_ddot: ArrayLike, *, frame: Frame = "body", scalar_first: bool = True
) -> Array:
    return _B(_motion.angular_acceleration, q, q_dot, q_ddot, frame=frame, scalar_first=scalar_first)


@documented(_motion.integrate_angular_velocity)
def integrate_angular_velocity(
    q: ArrayLike, omega: ArrayLike, dt: ArrayLike | float, *, frame: Frame = "body", scalar_first: bool = True
) -> Array:
    return _B(_motion.integrate_angular_velocity, q, omega, dt, frame=frame, scalar_first=scalar_first)


@documented(_motion.bound_angular_velocity_from_quaternions)
def angular_velocity_from_quaternions(
    q: ArrayLike, dt: ArrayLike | float, *, frame: Frame = "body", scalar_first: bool = True
) -> Array:
    return _B(_motion.bound_angular_velocity_from_quaternions, q, dt, frame=frame, scalar_first=scalar_first)


@documented(_motion.quaternion_squad)
def quaternion_squad(q: ArrayLike, t: ArrayLike | float, *, scalar_first: bool = True) -> Array:
    return _B(_motion.quaternion_squad, q, t, scalar_first=scalar_first)


@documented(_motion.so3_bspline)
def so3_bspline(control: ArrayLike, u: ArrayLike | float, *, order: int = 4) -> tuple[Array, Array, Array]:
    packed = _B(_motion.bound_so3_bspline, control, u, order=order, to_quaternion=_M2Q)
    return _motion.split_so3_bspline(_B.xp, packed)


@documented(_motion.se3_bspline)
def se3_bspline(
    control: ArrayLike, u: ArrayLike | float, *, order: int = 4, mode: SplineMode = "se3"
) -> tuple[Array, Array, Array]:
    packed = _B(_motion.bound_se3_bspline, control, u, order=order, mode=mode, to_quaternion=_M2Q)
    return _motion.split_se3_bspline(_B.xp, packed)


# SO3 and SE3 objects over the functions above (diffquat._objects, written once).


def _float(dtype: Any) -> Any:
    return jnp.dtype(jax.dtypes.canonicalize_dtype(jnp.float64) if dtype is None else dtype)


def _identity(n: int, shape: int | tuple[int, ...] = (), *, dtype: Any = None) -> Array:
    return jnp.broadcast_to(jnp.eye(n, dtype=_float(dtype)), (*shape_tuple(shape), n, n))


def _draw(
    module: Any, shape: int | tuple[int, ...] = (), *, key: Array, dtype: Any = None
) -> tuple[Array, Array]:
    rotation_key, translation_key = jax.random.split(key)
    q = random_quaternions(shape, key=rotation_key, dtype=_float(dtype))
    return q, jax.random.normal(translation_key, (*shape_tuple(shape), 3), dtype=_float(dtype))


def _device(x: Any) -> Any:
    # an abstract value (under jit, vmap, grad) has no device to tell
    return None if isinstance(x, jax.core.Tracer) else getattr(x, "device", None)


SO3, SE3 = _objects.bind(
    sys.modules[__name__],
    _objects.Native(
        xp=jnp,
        array=jax.Array,
        identity=_identity,
        draw=_draw,
        device=_device,
        astype=_B.astype,
        match_rank=True,
    ),
)
# Pytrees of one leaf, the stored array: through jit, vmap, grad, scan, optax and jax.export (whose
# serialisation names them).
for _cls in (SO3, SE3):
    jax.tree_util.register_pytree_node(
        _cls,
        lambda obj: ((obj.matrix,), None),
        functools.partial(lambda cls, aux, leaves: cls._wrap(leaves[0]), _cls),
    )
    jax.export.register_pytree_node_serialization(
        _cls,
        serialized_name=f"diffquat.jax.{_cls.__name__}",
        serialize_auxdata=lambda aux: b"",
        deserialize_auxdata=lambda data: None,
    )
