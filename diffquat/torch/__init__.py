"""diffquat on PyTorch. Same names and semantics as ``diffquat.numpy`` and ``diffquat.jax``;
the conventions are on the documentation's Conventions page. Dtype and device of the input are preserved."""

from __future__ import annotations

import contextlib
import functools
import sys
import warnings
from typing import Any

import torch
from torch import Tensor
from torch.jit._trace import TracerWarning, is_tracing

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
from ._custom import choose, custom_derivative, eager_form_with_rule, lean_step, refuse_onnx

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
    # No silent conversion from lists or numpy arrays: it would pick a device and a dtype for the user
    # (torch's own functions ask for tensors too). A Python number may stand for a scalar argument
    # (slerp's ``t``), weak in the promotion as in torch's own binary operations.
    if isinstance(x, Tensor):
        return x
    if scalar and isinstance(x, int | float) and not isinstance(x, bool):
        return x
    allowed = "a torch.Tensor or a Python number" if scalar else "a torch.Tensor"
    raise TypeError(f"{fname}: expected {argname} to be {allowed}, got {type(x).__name__}")


def _result_type(xs: list[Any]) -> torch.dtype:
    """torch's promotion of floating arguments: tensors with dimensions decide over 0-dimensional ones,
    and those over Python numbers (``torch.result_type``'s rule, over any number of arguments);
    integer and boolean tensors, lower in the category order, decide nothing."""
    floats = [x for x in xs if isinstance(x, Tensor) and x.dtype.is_floating_point]
    pool = [x.dtype for x in floats if x.ndim > 0] or [x.dtype for x in floats]
    return functools.reduce(_promote, pool) if pool else torch.get_default_dtype()


# torch.promote_types is an ATen operation (a dispatch per call); validation dispatches none, so the
# pairs met are remembered (a handful of dtypes).
_PROMOTED: dict[tuple[torch.dtype, torch.dtype], torch.dtype] = {}


def _promote(a: torch.dtype, b: torch.dtype) -> torch.dtype:
    if a == b:
        return a
    promoted = _PROMOTED.get((a, b))
    if promoted is None:
        promoted = _PROMOTED[(a, b)] = torch.promote_types(a, b)
    return promoted


# Whether autocast is on for any device (a private accessor, one call; torch builds without it: assumed
# on, and the device's own flag read). Dynamo does not trace it: a capture reads the device's flag.
_ANY_AUTOCAST = getattr(torch._C, "_is_any_autocast_enabled", lambda: True)


def _without_autocast(x: Tensor) -> contextlib.AbstractContextManager[Any] | None:
    """Autocast off around the core: under ``torch.autocast`` its matrix products and solves would run
    in the autocast dtype (bfloat16 for a float32 input), and the backward of a float32 result would
    then meet bfloat16 tensors. The Backend has already chosen the compute dtype. None (no context)
    outside autocast, told in eager calls by one look at every device's flag."""
    if not (torch.compiler.is_compiling() or _ANY_AUTOCAST()):
        return None
    device = x.device.type
    if torch.is_autocast_enabled(device):
        return torch.autocast(device, enabled=False)
    return None


class _QuietTracer(warnings.catch_warnings):
    """Under ``torch.jit.trace`` sizes are traced tensors, and comparing one in a shape check warns that
    the result is read as a constant, which for a static check is what is meant (see _backend)."""

    def __enter__(self) -> None:
        super().__enter__()
        warnings.simplefilter("ignore", TracerWarning)


def _static_shapes() -> contextlib.AbstractContextManager[Any]:
    tracing = is_tracing()  # type: ignore[no-untyped-call]
    return _QuietTracer() if tracing else contextlib.nullcontext()


def _signature(fname: str, arrays: tuple[Any, ...]) -> tuple[Any, ...] | None:
    """What decides the validation of an eager call (``Backend.validate`` remembers the passing ones):
    the function's name and each argument's shape and dtype (None, or a Python number's type). None
    under graph capture, where Dynamo traces the checks themselves and sizes may be symbolic or traced
    tensors, and for any other argument (the checks then say what is wrong with it). A device is not
    part of it: no check reads one."""
    if torch.compiler.is_compiling() or is_tracing():  # type: ignore[no-untyped-call]
        return None
    if len(arrays) == 1:
        (x,) = arrays
        return (fname, x.shape, x.dtype) if isinstance(x, Tensor) else None
    key: list[Any] = [fname]
    for x in arrays:
        if isinstance(x, Tensor):
            key.append((x.shape, x.dtype))
        elif x is None or type(x) is float or type(x) is int:  # not bool, which the checks refuse
            key.append(x if x is None else type(x))
        else:
            return None
    return tuple(key)


_B = Backend(
    xp=torch,
    convert=_convert,
    is_floating=lambda dtype: dtype.is_floating_point,
    is_integral=lambda dtype: not (dtype.is_floating_point or dtype.is_complex),
    result_type=_result_type,
    default_float=torch.get_default_dtype,
    astype=lambda x, dtype: x.to(dtype),
    scalar=lambda value, dtype, like: torch.tensor(value, dtype=dtype, device=like.device),
    float32=torch.float32,
    guard=_without_autocast,
    static=_static_shapes,
    choose=choose,
    signature=_signature,
)


# The conversions with their derivatives written out (diffquat._core.derivative_rules): an
# autograd.Function in eager mode, the formula under capture (see _custom.form). The public
# functions and every composite's conversion step call these.
_CONVERSIONS = _core.registered_conversions(
    lambda name, rule, eager: custom_derivative(*rule, formula_when_captured=True, eager=eager)
)
_Q2M, _M2Q = _CONVERSIONS["quaternion_to_matrix"], _CONVERSIONS["matrix_to_quaternion"]


@documented(_core.quaternion_to_matrix)
def quaternion_to_matrix(q: Tensor, *, scalar_first: bool = True) -> Tensor:
    return _B(_Q2M, q, scalar_first=scalar_first)


@documented(_core.matrix_to_quaternion)
def matrix_to_quaternion(matrix: Tensor, *, scalar_first: bool = True) -> Tensor:
    return _B(_M2Q, matrix, scalar_first=scalar_first)


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
    _rep.special_procrustes,
    _rep.procrustes_tangent,
    _rep.procrustes_cotangent,
    eager=_rep.procrustes_eager_rules(),
)
_smallest_eigenvector = custom_derivative(
    _rep.smallest_eigenvector,
    _rep.eigenvector_tangent,
    _rep.eigenvector_cotangent,
    eager=_rep.eigenvector_eager_rules(),
)


# The 6D map's eager form with its own reverse rule (diffquat._representations): autodiff of its
# selections would read the 0 / 0 of the branches it throws away.
_core.eager_form(of=_rep.rotation_6d_to_matrix)(
    eager_form_with_rule(_rep.rotation_6d_to_matrix, _rep.six_d_eager_rules(), _rep.six_d_axis)
)


@documented(_rep.rotation_6d_to_matrix)
def rotation_6d_to_matrix(d6: Tensor, *, layout: Rotation6DLayout = "columns") -> Tensor:
    return _B(_rep.rotation_6d_to_matrix, d6, layout=layout)


@documented(_rep.matrix_to_rotation_6d)
def matrix_to_rotation_6d(matrix: Tensor, *, layout: Rotation6DLayout = "columns") -> Tensor:
    return _B(_rep.matrix_to_rotation_6d, matrix, layout=layout)


@documented(_rep.special_procrustes)
def special_procrustes(matrix: Tensor) -> Tensor:
    refuse_onnx("special_procrustes", "the projection onto SO(3)")
    return _B(_special_procrustes, matrix)


@documented(_rep.symmetric_matrix_to_quaternion)
def symmetric_matrix_to_quaternion(a: Tensor, *, scalar_first: bool = True) -> Tensor:
    refuse_onnx("symmetric_matrix_to_quaternion", "the smallest eigenvector")
    return _B(
        _rep.symmetric_matrix_to_quaternion, a, scalar_first=scalar_first, eigenvector=_smallest_eigenvector
    )


@documented(_rep.fit_rotation)
def fit_rotation(source: Tensor, target: Tensor, weights: Tensor | None = None) -> Tensor:
    refuse_onnx("fit_rotation", "the least-squares rotation")
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
    return _B(_algebra.axis_angle_to_matrix, axis_angle)


@documented(_algebra.matrix_to_axis_angle)
def matrix_to_axis_angle(matrix: Tensor) -> Tensor:
    return _B(_algebra.matrix_to_axis_angle, matrix, to_quaternion=_M2Q)


@documented(_euler.euler_angles_to_matrix)
def euler_angles_to_matrix(angles: Tensor, convention: EulerConvention, *, degrees: bool = False) -> Tensor:
    return _B(
        _euler.euler_angles_to_matrix,
        angles,
        convention=convention,
        degrees=degrees,
        to_matrix=_Q2M,
    )


@documented(_euler.matrix_to_euler_angles)
def matrix_to_euler_angles(matrix: Tensor, convention: EulerConvention, *, degrees: bool = False) -> Tensor:
    return _B(_euler.matrix_to_euler_angles, matrix, convention=convention, degrees=degrees)


@documented(_euler.euler_angles_to_quaternion)
def euler_angles_to_quaternion(
    angles: Tensor, convention: EulerConvention, *, degrees: bool = False, scalar_first: bool = True
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
    q: Tensor, convention: EulerConvention, *, degrees: bool = False, scalar_first: bool = True
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


# SO(3) as a Lie group: hat and vee, exp and log, Jacobians, plus and minus (diffquat._lie).


@documented(_lie.so3_hat)
def so3_hat(omega: Tensor) -> Tensor:
    return _B(_lie.so3_hat, omega)


@documented(_lie.so3_left_jacobian)
def so3_left_jacobian(omega: Tensor) -> Tensor:
    return _B(_lie.so3_left_jacobian, omega)


@documented(_lie.so3_right_jacobian)
def so3_right_jacobian(omega: Tensor) -> Tensor:
    return _B(_lie.so3_right_jacobian, omega)


@documented(_lie.so3_left_jacobian_inverse)
def so3_left_jacobian_inverse(omega: Tensor) -> Tensor:
    return _B(_lie.so3_left_jacobian_inverse, omega)


@documented(_lie.so3_right_jacobian_inverse)
def so3_right_jacobian_inverse(omega: Tensor) -> Tensor:
    return _B(_lie.so3_right_jacobian_inverse, omega)


@documented(_lie.so3_vee)
def so3_vee(matrix: Tensor) -> Tensor:
    return _B(_lie.so3_vee, matrix)


@documented(_lie.so3_exp)
def so3_exp(omega: Tensor) -> Tensor:
    return _B(_lie.so3_exp, omega)


@documented(_lie.so3_log)
def so3_log(matrix: Tensor) -> Tensor:
    return _B(_lie.so3_log, matrix, to_quaternion=_M2Q)


@documented(_lie.so3_plus)
def so3_plus(matrix: Tensor, delta: Tensor, *, side: Side = "right") -> Tensor:
    return _B(_lie.so3_plus, matrix, delta, side=side, to_matrix=_Q2M)


@documented(_lie.so3_minus)
def so3_minus(matrix1: Tensor, matrix2: Tensor, *, side: Side = "right") -> Tensor:
    return _B(_lie.so3_minus, matrix1, matrix2, side=side, to_quaternion=_M2Q)


@documented(_lie.quaternion_plus)
def quaternion_plus(q: Tensor, delta: Tensor, *, side: Side = "right", scalar_first: bool = True) -> Tensor:
    return _B(_lie.quaternion_plus, q, delta, side=side, scalar_first=scalar_first)


@documented(_lie.quaternion_minus)
def quaternion_minus(q1: Tensor, q2: Tensor, *, side: Side = "right", scalar_first: bool = True) -> Tensor:
    return _B(_lie.quaternion_minus, q1, q2, side=side, scalar_first=scalar_first)


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


# The matrix Fisher distribution on SO(3) and the Bingham NLL of the 10D head (diffquat._fisher): the
# Bingham log normaliser of a symmetric 4x4 matrix with its gradient (the second moment) and Hessian
# (the rule of the second moment) in closed form, exact where eigenvalues repeat.
_reduced_second_moment = custom_derivative(
    _fi.reduced_second_moment,
    _fi.reduced_second_moment_tangent,
    _fi.reduced_second_moment_tangent,
    captured=_fi.reduced_second_moment_taylor,
    eager=_fi.reduced_second_moment_eager_rules(),
)
_reduced_log_normalizer = custom_derivative(
    _fi.reduced_log_normalizer,
    functools.partial(_fi.reduced_log_normalizer_tangent, moment=_reduced_second_moment),
    functools.partial(_fi.reduced_log_normalizer_cotangent, moment=_reduced_second_moment),
    captured=_fi.reduced_log_normalizer_taylor,
    eager=_fi.reduced_log_normalizer_eager_rules(),
)


@documented(_igso3.igso3_angle_cdf)
def igso3_angle_cdf(angle: Tensor | float, sigma: Tensor | float) -> Tensor:
    return _B(_igso3.igso3_angle_cdf, angle, sigma)


@documented(_igso3.igso3_log_density)
def igso3_log_density(angle: Tensor | float, sigma: Tensor | float) -> Tensor:
    return _B(_igso3.igso3_log_density, angle, sigma)


def igso3_sample(
    sigma: Tensor | float, shape: int | tuple[int, ...] = (), *, generator: torch.Generator | None = None
) -> Tensor:
    (checked,), dtype = _B.validate("igso3_sample", sigma)
    compute = _B.compute_dtype(dtype)
    size = (*shape_tuple(shape), *checked.shape)
    options: dict[str, Any] = {"dtype": compute, "device": checked.device}
    # In-place draws into empty tensors, the numbers torch.rand/randn draw: torch.export of those with
    # a generator argument (None included) and a dynamic batch fails ("SymIntArrayRef expected to
    # contain only concrete integers"); uniform_/normal_ export with or without a generator.
    uniform = torch.empty(size, **options).uniform_(generator=generator)
    normal = torch.empty((*size, 3), **options).normal_(generator=generator)
    return _B(_igso3.igso3_sample, checked, uniform=uniform, normal=normal)


igso3_sample.__doc__ = _igso3.SAMPLE_DOC.format(
    random="generator: a ``torch.Generator`` to draw from (default: the global one)."
)


@documented(_igso3.igso3_score)
def igso3_score(matrix: Tensor, sigma: Tensor | float, mean: Tensor | None = None) -> Tensor:
    return _B(_igso3.igso3_score, matrix, sigma, mean, to_quaternion=_M2Q)


@documented(_fi.matrix_fisher_log_normalizer)
def matrix_fisher_log_normalizer(F: Tensor) -> Tensor:
    refuse_onnx("matrix_fisher_log_normalizer", "the matrix Fisher normaliser")
    return _B(_fi.matrix_fisher_log_normalizer, F, normalizer=_reduced_log_normalizer)


@documented(_fi.matrix_fisher_nll)
def matrix_fisher_nll(F: Tensor, matrix: Tensor) -> Tensor:
    refuse_onnx("matrix_fisher_nll", "the matrix Fisher normaliser")
    return _B(_fi.matrix_fisher_nll, F, matrix, normalizer=_reduced_log_normalizer)


@documented(_fi.matrix_fisher_mode)
def matrix_fisher_mode(F: Tensor) -> Tensor:
    refuse_onnx("matrix_fisher_mode", "the projection onto SO(3)")
    return _B(_fi.matrix_fisher_mode, F, procrustes=_special_procrustes)


@documented(_fi.bingham_nll)
def bingham_nll(a: Tensor, q: Tensor, *, scalar_first: bool = True) -> Tensor:
    refuse_onnx("bingham_nll", "the Bingham normaliser")
    return _B(_fi.bingham_nll, a, q, scalar_first=scalar_first, normalizer=_reduced_log_normalizer)


def _matrix_fisher_mean(F: Tensor) -> Tensor:
    """``E[R]`` (..., 3, 3), differentiable (MatrixFisher.mean; not public: jax.grad / torch.func.grad
    of matrix_fisher_log_normalizer give it on every backend)."""
    return _B(_fi.matrix_fisher_mean, F, moment=_reduced_second_moment)


def matrix_fisher_sample(
    F: Tensor, shape: int | tuple[int, ...] = (), *, generator: torch.Generator | None = None
) -> Tensor:
    """Rotations drawn from the matrix Fisher distribution ``exp(tr(F^T R)) / c(F)``.

    Args:
        F: the parameter, shape ``(..., 3, 3)``.
        shape: sample shape; the result has shape ``(*shape, ..., 3, 3)``, on F's device, in F's dtype.
        generator: a ``torch.Generator`` to draw from (default: the global one).

    Exact: Kent et al.'s rejection sampler for the equivalent Bingham distribution on S^3 (an angular
    central Gaussian envelope, acceptance at least 0.447 for every F), with a fixed number of 64
    proposals per sample, the first accepted taken; all 64 fail with probability below 4e-17, and then
    the sample is the mode. Not differentiable (a rejection sampler has no reparameterisation): the
    result does not require grad.
    """
    (checked,), dtype = _B.validate("matrix_fisher_sample", F)
    checked = checked.detach()
    compute = _B.compute_dtype(dtype)
    # all rounds' numbers drawn at once (two operations), each round a slice of them, so that the eager
    # form (all rounds as one: draw(None)) and the componentwise one draw the same numbers
    size = (*shape_tuple(shape), *checked.shape[:-2], _fi.SAMPLE_ROUNDS * _fi.SAMPLE_PROPOSALS)
    options: dict[str, Any] = {"generator": generator, "dtype": compute, "device": checked.device}
    numbers = torch.randn((*size, 4), **options), torch.rand(size, **options)

    def draw(k: int | None) -> tuple[Tensor, Tensor]:
        if k is None:
            return numbers
        part = slice(k * _fi.SAMPLE_PROPOSALS, (k + 1) * _fi.SAMPLE_PROPOSALS)
        return numbers[0][..., part, :], numbers[1][..., part]

    return _B(_fi.matrix_fisher_sample, checked, draw=draw)


# Rotation averaging and symmetric objects. The geodesic means with their implicit derivatives (see
# diffquat._statistics), registered as the SVD and eigh maps are.
# Their forwards are opaque operators: captures record one call, not the iterations (see _custom).
_karcher_mean = custom_derivative(
    _stats.karcher_mean,
    _stats.karcher_tangent,
    _stats.karcher_cotangent,
    result_shape=_stats.mean_shape,
    eager=_stats.karcher_eager_rules(),
)
_geodesic_median = custom_derivative(
    _stats.geodesic_median,
    _stats.median_tangent,
    _stats.median_cotangent,
    result_shape=_stats.mean_shape,
    eager=_stats.median_eager_rules(),
)


@documented(_stats.rotation_mean)
def rotation_mean(
    matrices: Tensor, weights: Tensor | None = None, *, method: MeanMethod = "chordal"
) -> Tensor:
    refuse_onnx("rotation_mean", "a mean of rotations")
    return _B(
        _stats.rotation_mean,
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
def quaternion_mean(q: Tensor, weights: Tensor | None = None, *, scalar_first: bool = True) -> Tensor:
    refuse_onnx("quaternion_mean", "the largest eigenvector")
    return _B(
        _stats.quaternion_mean, q, weights, scalar_first=scalar_first, eigenvector=_smallest_eigenvector
    )


@documented(_stats.symmetric_geodesic_distance)
def symmetric_geodesic_distance(matrix1: Tensor, matrix2: Tensor, group: Tensor) -> Tensor:
    return _B(_stats.symmetric_geodesic_distance, matrix1, matrix2, group)


def symmetry_group(
    name: str, *, dtype: torch.dtype | None = None, device: torch.device | str | None = None
) -> Tensor:
    matrices = _stats.symmetry_group_matrices(name)
    return torch.tensor(matrices.copy(), dtype=dtype or torch.get_default_dtype(), device=device)


symmetry_group.__doc__ = _stats.SYMMETRY_GROUP_DOC.format(
    keywords="        dtype: floating dtype of the result (default ``torch.get_default_dtype()``).\n"
    "        device: device of the result (default: the current default device).\n"
)


# torch.fx.symbolic_trace runs Python on Proxy objects, which have no shape or dtype to validate: it
# records each public function as one call instead (a leaf), which runs it when the graph runs.
for _name in __all__:
    torch.fx.wrap(_name)


# SE(3): poses as 4x4 matrices, their Lie calculus and interpolation (diffquat._se3).


@documented(_se3.se3_from_rotation_translation)
def se3_from_rotation_translation(rotation: Tensor, translation: Tensor) -> Tensor:
    return _B(_se3.se3_from_rotation_translation, rotation, translation)


@documented(_se3.se3_to_rotation_translation)
def se3_to_rotation_translation(matrix: Tensor) -> tuple[Tensor, Tensor]:
    rotation, translation = _B(_se3.se3_to_rotation_translation, matrix).split([9, 3], -1)
    return rotation.unflatten(-1, (3, 3)), translation


@documented(_se3.se3_compose)
def se3_compose(matrix1: Tensor, matrix2: Tensor) -> Tensor:
    return _B(_se3.se3_compose, matrix1, matrix2)


@documented(_se3.se3_inverse)
def se3_inverse(matrix: Tensor) -> Tensor:
    return _B(_se3.se3_inverse, matrix)


@documented(_se3.se3_apply)
def se3_apply(matrix: Tensor, points: Tensor) -> Tensor:
    return _B(_se3.se3_apply, matrix, points)


@documented(_se3.se3_hat)
def se3_hat(xi: Tensor) -> Tensor:
    return _B(_se3.se3_hat, xi)


@documented(_se3.se3_vee)
def se3_vee(matrix: Tensor) -> Tensor:
    return _B(_se3.se3_vee, matrix)


@documented(_se3.se3_exp)
def se3_exp(xi: Tensor) -> Tensor:
    return _B(_se3.se3_exp, xi)


@documented(_se3.se3_log)
def se3_log(matrix: Tensor) -> Tensor:
    return _B(_se3.se3_log, matrix, to_quaternion=_M2Q)


@documented(_se3.se3_adjoint)
def se3_adjoint(matrix: Tensor) -> Tensor:
    return _B(_se3.se3_adjoint, matrix)


@documented(_se3.se3_ad)
def se3_ad(xi: Tensor) -> Tensor:
    return _B(_se3.se3_ad, xi)


@documented(_se3.se3_left_jacobian)
def se3_left_jacobian(xi: Tensor) -> Tensor:
    return _B(_se3.se3_left_jacobian, xi)


@documented(_se3.se3_right_jacobian)
def se3_right_jacobian(xi: Tensor) -> Tensor:
    return _B(_se3.se3_right_jacobian, xi)


@documented(_se3.se3_left_jacobian_inverse)
def se3_left_jacobian_inverse(xi: Tensor) -> Tensor:
    return _B(_se3.se3_left_jacobian_inverse, xi)


@documented(_se3.se3_right_jacobian_inverse)
def se3_right_jacobian_inverse(xi: Tensor) -> Tensor:
    return _B(_se3.se3_right_jacobian_inverse, xi)


@documented(_se3.se3_plus)
def se3_plus(matrix: Tensor, delta: Tensor, *, side: Side = "right") -> Tensor:
    return _B(_se3.se3_plus, matrix, delta, side=side)


@documented(_se3.se3_minus)
def se3_minus(matrix1: Tensor, matrix2: Tensor, *, side: Side = "right") -> Tensor:
    return _B(_se3.se3_minus, matrix1, matrix2, side=side, to_quaternion=_M2Q)


@documented(_se3.se3_interpolate)
def se3_interpolate(
    matrix1: Tensor, matrix2: Tensor, t: Tensor | float, *, mode: SE3Interpolation = "screw"
) -> Tensor:
    return _B(_se3.se3_interpolate, matrix1, matrix2, t, mode=mode, to_quaternion=_M2Q)


@documented(_se3.pose_to_matrix)
def pose_to_matrix(pose: Tensor, *, layout: PoseLayout) -> Tensor:
    return _B(_se3.pose_to_matrix, pose, layout=layout, to_matrix=_Q2M)


@documented(_se3.matrix_to_pose)
def matrix_to_pose(matrix: Tensor, *, layout: PoseLayout) -> Tensor:
    return _B(_se3.matrix_to_pose, matrix, layout=layout, to_quaternion=_M2Q)


@documented(_se3.se3_mean)
def se3_mean(matrices: Tensor, weights: Tensor | None = None) -> Tensor:
    refuse_onnx("se3_mean", "a mean of poses")
    return _B(
        _se3.se3_mean, matrices, weights, rotation_mean=_stats.rotation_mean, procrustes=_special_procrustes
    )


@documented(_se3.fit_rigid_transform)
def fit_rigid_transform(source: Tensor, target: Tensor, weights: Tensor | None = None) -> Tensor:
    refuse_onnx("fit_rigid_transform", "the least-squares pose")
    return _B(_se3.fit_rigid_transform, source, target, weights, procrustes=_special_procrustes)


@documented(_se3.fit_similarity_transform)
def fit_similarity_transform(
    source: Tensor, target: Tensor, weights: Tensor | None = None
) -> tuple[Tensor, Tensor]:
    refuse_onnx("fit_similarity_transform", "the least-squares similarity")
    packed = _B(_se3.fit_similarity_transform, source, target, weights, procrustes=_special_procrustes)
    return _se3.split_similarity(_B.xp, packed)


@documented(_se3.rotation_between_vectors)
def rotation_between_vectors(a: Tensor, b: Tensor) -> Tensor:
    return _B(_se3.rotation_between_vectors, a, b)


@documented(_se3.frame_from_three_points)
def frame_from_three_points(x1: Tensor, x2: Tensor, x3: Tensor) -> Tensor:
    return _B(_se3.frame_from_three_points, x1, x2, x3, to_rotation=_six_d)


def _six_d(xp: Any, d6: Tensor) -> Tensor:
    """The 6D map as the public one computes it (its eager form and rule in eager mode, the core
    formula under capture and in forward mode: ``choose``), for the composites built on it."""
    return choose(_rep.rotation_6d_to_matrix, d6)(xp, d6)


# Rotations in time: angular velocity and acceleration, integration, SQUAD and B-splines (diffquat._motion).


@documented(_motion.angular_velocity)
def angular_velocity(q: Tensor, q_dot: Tensor, *, frame: Frame = "body", scalar_first: bool = True) -> Tensor:
    return _B(_motion.angular_velocity, q, q_dot, frame=frame, scalar_first=scalar_first)


@documented(_motion.quaternion_derivative)
def quaternion_derivative(
    q: Tensor, omega: Tensor, *, frame: Frame = "body", scalar_first: bool = True
) -> Tensor:
    return _B(_motion.quaternion_derivative, q, omega, frame=frame, scalar_first=scalar_first)


@documented(_motion.angular_acceleration)
def angular_acceleration(
    q: Tensor, q_dot: Tensor, q_ddot: Tensor, *, frame: Frame = "body", scalar_first: bool = True
) -> Tensor:
    return _B(_motion.angular_acceleration, q, q_dot, q_ddot, frame=frame, scalar_first=scalar_first)


# integrate_angular_velocity's eager form: its exponential (with the range reduction) one Function with
# a written cotangent (diffquat._motion.exp_in_range), where autodiff of its guards was most of the
# backward pass; NaN rows by its arithmetic.
_core.eager_form(of=_motion.integrate_angular_velocity)(
    _core.nonfinite_by_arithmetic(
        _motion.integrate_eager_with(
            lean_step(_motion.exp_in_range, _motion.exp_in_range_cotangent, "integrate_angular_velocity")
        )
    )
)


# angular_velocity_from_quaternions' eager form: the logarithm of the relative rotations one Function
# with a written cotangent (diffquat._motion.log_of_relative), where autodiff of its series, sign and
# guards was half of the backward pass; NaN sequences by its arithmetic.
_core.eager_form(of=_motion.bound_angular_velocity_from_quaternions)(
    _core.nonfinite_by_arithmetic(
        _motion.angular_velocity_eager_with(
            lean_step(
                _motion.log_of_relative,
                _motion.log_of_relative_cotangent,
                "angular_velocity_from_quaternions",
            )
        )
    )
)


@documented(_motion.integrate_angular_velocity)
def integrate_angular_velocity(
    q: Tensor, omega: Tensor, dt: Tensor | float, *, frame: Frame = "body", scalar_first: bool = True
) -> Tensor:
    return _B(_motion.integrate_angular_velocity, q, omega, dt, frame=frame, scalar_first=scalar_first)


@documented(_motion.bound_angular_velocity_from_quaternions)
def angular_velocity_from_quaternions(
    q: Tensor, dt: Tensor | float, *, frame: Frame = "body", scalar_first: bool = True
) -> Tensor:
    return _B(_motion.bound_angular_velocity_from_quaternions, q, dt, frame=frame, scalar_first=scalar_first)


@documented(_motion.quaternion_squad)
def quaternion_squad(q: Tensor, t: Tensor | float, *, scalar_first: bool = True) -> Tensor:
    return _B(_motion.quaternion_squad, q, t, scalar_first=scalar_first)


@documented(_motion.so3_bspline)
def so3_bspline(control: Tensor, u: Tensor | float, *, order: int = 4) -> tuple[Tensor, Tensor, Tensor]:
    packed = _B(_motion.bound_so3_bspline, control, u, order=order, to_quaternion=_M2Q)
    return _motion.split_so3_bspline(_B.xp, packed)


@documented(_motion.se3_bspline)
def se3_bspline(
    control: Tensor, u: Tensor | float, *, order: int = 4, mode: SplineMode = "se3"
) -> tuple[Tensor, Tensor, Tensor]:
    packed = _B(_motion.bound_se3_bspline, control, u, order=order, mode=mode, to_quaternion=_M2Q)
    return _motion.split_se3_bspline(_B.xp, packed)


# SO3 and SE3 objects over the functions above (diffquat._objects, written once).


def _identity(
    n: int,
    shape: int | tuple[int, ...] = (),
    *,
    dtype: torch.dtype | None = None,
    device: torch.device | str | None = None,
) -> Tensor:
    eye = torch.eye(n, dtype=dtype or torch.get_default_dtype(), device=device)
    return eye.expand(*shape_tuple(shape), n, n).clone()


def _draw(
    module: Any,
    shape: int | tuple[int, ...] = (),
    *,
    generator: torch.Generator | None = None,
    dtype: torch.dtype | None = None,
    device: torch.device | str | None = None,
) -> tuple[Tensor, Tensor]:
    q = random_quaternions(shape, generator=generator, dtype=dtype, device=device)
    t = torch.randn((*shape_tuple(shape), 3), generator=generator, dtype=q.dtype, device=q.device)
    return q, t


SO3, SE3 = _objects.bind(
    sys.modules[__name__],
    _objects.Native(
        xp=torch, array=Tensor, identity=_identity, draw=_draw, device=lambda x: x.device, astype=_B.astype
    ),
)
# torch's pytrees (torch.func's vmap and grad, torch.compile's inputs and outputs, torch.export): one
# leaf, the stored tensor.
for _cls in (SO3, SE3):
    torch.utils._pytree.register_pytree_node(
        _cls,
        lambda obj: ([obj.matrix], None),
        functools.partial(lambda cls, leaves, context: cls._wrap(leaves[0]), _cls),
        serialized_type_name=f"diffquat.torch.{_cls.__name__}",
    )
