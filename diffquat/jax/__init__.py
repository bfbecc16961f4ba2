"""diffquat on JAX. Same names and semantics as ``diffquat.numpy`` and ``diffquat.torch``; the
conventions are on the documentation's Conventions page. Every function is traceable by ``jit``,
``vmap``, ``grad`` and ``jacfwd``/``jacrev``, runs under ``shard_map``, ``pmap`` and sharded ``jit``,
and exports with ``jax.export`` (the exported program is plain StableHLO: it runs where diffquat is
not installed).

One switch of its own, ``cpu_kernels`` (off by default): ``matrix_to_quaternion``,
``matrix_to_axis_angle`` and ``so3_log``, the four SO(3) Jacobians and ``quaternion_plus`` on the CPU
through diffquat's C kernels, called as XLA custom calls."""

from __future__ import annotations

import functools
import importlib
import os
import warnings
from collections.abc import Callable
from types import TracebackType
from typing import Any

import jax
import jax.numpy as jnp
from jax import Array
from jax.typing import ArrayLike

from .. import _algebra, _core, _euler, _lie
from .. import _fisher as _fi
from .. import _representations as _rep
from .. import _statistics as _stats
from .._backend import Backend, documented, shape_tuple
from .._public import public_dir as _public_dir
from .._types import EulerConvention, MeanMethod, Rotation6DLayout, Side
from ._custom import custom_derivative, custom_jvp_rule
from ._namespace import XP

__all__ = [
    "axis_angle_to_matrix",
    "axis_angle_to_quaternion",
    "bingham_nll",
    "cpu_kernels",
    "euler_angles_to_matrix",
    "euler_angles_to_quaternion",
    "fit_rotation",
    "matrix_fisher_log_normalizer",
    "matrix_fisher_mode",
    "matrix_fisher_nll",
    "matrix_fisher_sample",
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
    "quaternion_mean",
    "quaternion_minus",
    "quaternion_multiply",
    "quaternion_plus",
    "quaternion_slerp",
    "quaternion_to_axis_angle",
    "quaternion_to_euler_angles",
    "quaternion_to_matrix",
    "random_quaternions",
    "rotation_6d_to_matrix",
    "rotation_mean",
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
    return jnp.asarray(x)


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


def _q2m_gathered(scalar_first: bool) -> Callable[[Any, Array], Array]:
    """:func:`diffquat._core.quaternion_to_matrix_gathered` in one order, differentiated as the core
    formula (a ``custom_jvp`` whose rule is the stack of nine's own ``jvp``, the same values): the
    gathered form's reverse mode is a scatter-add, 15x slower on an H100 than the stack's."""

    def forward(xp: Any, q: Array) -> Array:
        return _core.quaternion_to_matrix_gathered(xp, q, scalar_first=scalar_first)

    def jvp(xp: Any, q: Array, dq: Array) -> tuple[Array, Array]:
        return jax.jvp(lambda x: _core.quaternion_to_matrix(xp, x, scalar_first=scalar_first), (q,), (dq,))

    return custom_jvp_rule(forward, jvp)


_Q2M_GATHERED = {order: _q2m_gathered(order) for order in (True, False)}


def _quaternion_to_matrix(xp: Any, q: Array, *, scalar_first: bool = True) -> Array:
    """The core formula in the form that the platform compiles better, chosen when ``jit`` lowers for
    a platform (the other is not lowered): the stack of nine entries on the CPU, the gathered entries
    elsewhere (the same values). On an H100 the gathered forward is 1.2x faster, as fast as jaxlie's;
    derivatives are the stack's on every platform."""
    gathered = _Q2M_GATHERED[bool(scalar_first)]
    return jax.lax.platform_dependent(
        q,
        cpu=lambda x: _core.quaternion_to_matrix(xp, x, scalar_first=scalar_first),
        default=lambda x: gathered(xp, x),
    )


_quaternion_to_matrix.__name__ = "quaternion_to_matrix"  # the backend validates by the core's name


@documented(_core.quaternion_to_matrix)
def quaternion_to_matrix(q: ArrayLike, *, scalar_first: bool = True) -> Array:
    return _B(_quaternion_to_matrix, q, scalar_first=scalar_first)


# With its derivative written out (only the picked candidate is differentiated): XLA's own derivative
# of the formula carries all four candidates through the selection, about twice the work forward +
# backward (benchmarks/). The forward is the core formula in the order that XLA compiles best
# (whole-candidate selection; twice as fast forward, and 1.3x forward + backward, at N = 262144).
# One per storage order, each built in its order: a reindexing of the (..., 4) result after the
# custom derivative measured 5x slower forward at N = 262144 (XLA then materialises each of the four
# candidates as an array of its own before the reindexing). The rule computes the result with the
# tangent (_core.matrix_to_quaternion_jvp: the core formula's scale, shared), so a differentiated
# call's value may differ from a plain call's in the last bit.
def _m2q_in_order(scalar_first: bool) -> Any:
    def forward(xp: Any, matrix: Array) -> Array:
        return _core.matrix_to_quaternion_stacked(xp, matrix, scalar_first=scalar_first)

    def jvp(xp: Any, matrix: Array, dm: Array) -> tuple[Array, Array]:
        return _core.matrix_to_quaternion_jvp(xp, matrix, dm, scalar_first=scalar_first)

    return custom_jvp_rule(forward, jvp)


_M2Q = {order: _m2q_in_order(order) for order in (True, False)}


# The C kernels as XLA custom calls (_xla.py), where the extension was built (pyproject.toml builds it
# wherever a C compiler is found) and jax can key its caches on the switch (make_user_context).
def _load_kernels() -> Any:
    if not hasattr(jax, "make_user_context"):
        return None  # an older jax: a flip of the switch could not reach jit's caches
    try:
        return importlib.import_module("._xla", __name__)
    except ImportError:  # the extension was not built
        return None


_xla = _load_kernels()

_ENVIRONMENT = "DIFFQUAT_JAX_CPU_KERNELS"


def _from_environment() -> bool:
    value = os.environ.get(_ENVIRONMENT, "0").strip().lower()
    if value not in ("0", "1", "false", "true", "off", "on", "no", "yes", ""):
        raise ValueError(f"{_ENVIRONMENT} must be 1 (on) or 0 (off), got {value!r}")
    return value in ("1", "true", "on", "yes")


# The state of the switch: a jax user context, whose value is part of the key of jax's tracing,
# lowering and compilation caches (as jax's own options are): a function traced, or compiled, with
# the switch in one state is traced and compiled again when it is called in the other.
_KERNELS_ON: Any = None
if _xla is not None:
    _user_context: Callable[[bool], Any] = jax.make_user_context  # untyped in jax
    _KERNELS_ON = _user_context(_from_environment())


class _Restore:
    """What :func:`cpu_kernels` returns: a context manager that puts the previous setting back."""

    def __init__(self, previous: bool | None) -> None:
        self._previous = previous

    def __enter__(self) -> None:
        return None

    def __exit__(
        self, kind: type[BaseException] | None, error: BaseException | None, trace: TracebackType | None
    ) -> None:
        if _KERNELS_ON is not None and self._previous is not None:
            _KERNELS_ON.set_global(self._previous)


def cpu_kernels(enabled: bool = True) -> _Restore:
    """Turn the C kernels on the CPU on or off (off by default): ``cpu_kernels(True)`` for the rest of
    the process, or for a block::

        with diffquat.jax.cpu_kernels():          # or cpu_kernels(True) / cpu_kernels(False)
            q = jax.jit(diffquat.jax.matrix_to_quaternion)(matrices)   # (..., 3, 3) -> (..., 4)

    On, ``matrix_to_quaternion``, the four SO(3) Jacobians (``so3_left_jacobian``,
    ``so3_right_jacobian`` and their inverses) and ``quaternion_plus`` (forward and reverse mode), and
    the quaternion step of ``matrix_to_axis_angle`` and ``so3_log``, call diffquat's C kernels
    (``diffquat/_kernels.c``, the torch backend's) as XLA custom calls wherever ``jit`` lowers for the
    CPU: one pass over memory each way, where XLA runs the formula as 7 to 21 small loops (and, from
    some 16 rotations on, on its thread pool): 1.2-4.8x faster at N = 64, 1.0-5.3x at N = 4096
    (benchmarks/LIE.md and RESULTS.md). The values are the formula's (the same operations, to a few
    ulps); other platforms, and dtypes other than float32 and float64, keep the formula. Off, every
    platform runs the formula, and every compiled program is plain StableHLO.

    The switch is process-wide, like ``jax.config.update``: calling it sets it at once, and as a
    context manager it restores the previous setting when the block exits. It is read when a function
    is traced, and it is part of the key of jax's caches (``jax.make_user_context``): a function that
    ``jit`` traced or compiled in one state is traced and compiled again when it runs in the other,
    never reusing the other's program (so each flip recompiles every ``jit`` function at its next call;
    set it once, or around a block, not in a loop). Where a function is traced decides, not where it
    is called: ``jit`` of a function that enters the block itself traces with the kernels.

    Exported programs never call the kernels. ``jax.export`` refuses custom calls that have no
    compatibility guarantee, and an artefact that called them would run only in a process that
    imported diffquat.jax: a program lowered for ``jax.export`` takes the formula on the CPU too,
    whatever the switch says. Without the C extension (no C compiler at install) or on a jax without
    ``jax.make_user_context``, turning it on warns and changes nothing.

    The environment variable ``DIFFQUAT_JAX_CPU_KERNELS=1`` at import turns it on from the start.

    Args:
        enabled: whether the kernels are on (default ``True``).
    """
    if _KERNELS_ON is None:
        if enabled:
            warnings.warn(
                "diffquat.jax.cpu_kernels(True) has no effect: the C extension is not built, or this "
                "jax has no make_user_context; the formula runs on the CPU",
                RuntimeWarning,
                stacklevel=2,
            )
        return _Restore(None)
    previous = bool(_KERNELS_ON.get_global())
    _KERNELS_ON.set_global(bool(enabled))
    return _Restore(previous)


def _kernels_on() -> bool:
    return _KERNELS_ON is not None and bool(_KERNELS_ON.value)


def _on_the_cpu(kernel: Callable[..., Array], elsewhere: Callable[..., Array], *arrays: Array) -> Array:
    """``kernel`` (the C kernels, _xla.py) of ``arrays`` where ``jit`` lowers for the CPU and
    ``elsewhere`` on other platforms (the branch not chosen is not lowered), while :func:`cpu_kernels`
    is on; ``elsewhere`` on every platform while it is off (the default)."""
    if not _kernels_on():
        return elsewhere(*arrays)
    return jax.lax.platform_dependent(*arrays, cpu=kernel, default=elsewhere)


def _matrix_to_quaternion(xp: Any, matrix: Array, *, scalar_first: bool = True) -> Array:
    """The formula above; the kernels on the CPU, forward and backward, while :func:`cpu_kernels` is
    on. Side by side at N = 262144 the kernels measured 1.5x faster forward than the formula and 1.4x
    forward + backward, 2.4x both at N = 4096."""
    portable = _M2Q[bool(scalar_first)]
    kernel = lambda m: _xla.matrix_to_quaternion(m, scalar_first)  # noqa: E731
    return _on_the_cpu(kernel, lambda m: portable(xp, m), matrix)


_matrix_to_quaternion.__name__ = "matrix_to_quaternion"  # the Backend validates arguments by this name


@documented(_core.matrix_to_quaternion)
def matrix_to_quaternion(matrix: ArrayLike, *, scalar_first: bool = True) -> Array:
    return _B(_matrix_to_quaternion, matrix, scalar_first=scalar_first)


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


# matrix_to_axis_angle takes the kernels for its quaternion step on the CPU while cpu_kernels is on
# (see _core.Conversion): against the plain core step, which XLA fuses into what follows, they
# measured forward 1.1x faster at N = 262144 and forward + backward 1.2-1.8x from N = 64 on.
# matrix_to_euler_angles keeps the core's step, where the kernels measured mixed (0.95-1.24x). Without
# the kernels the composite takes the formula with its derivative written out (_M2Q), as
# matrix_to_quaternion does: against the plain core step, so3_log at N = 4096 measured 1.4x faster
# forward and 3x forward + backward (XLA's own derivative of the plain step carried all four
# candidates, and fused thirteen divisions into each of the nine entries of the cotangent).
def _m2q_step(xp: Any, matrix: Array) -> Array:
    return _on_the_cpu(lambda m: _xla.matrix_to_quaternion(m, True), lambda m: _M2Q[True](xp, m), matrix)


@documented(_algebra.matrix_to_axis_angle)
def matrix_to_axis_angle(matrix: ArrayLike) -> Array:
    return _B(_algebra.matrix_to_axis_angle, matrix, to_quaternion=_m2q_step)


@documented(_euler.euler_angles_to_matrix)
def euler_angles_to_matrix(angles: ArrayLike, convention: EulerConvention, *, degrees: bool = False) -> Array:
    return _B(_euler.euler_angles_to_matrix, angles, convention=convention, degrees=degrees)


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


def _kernels_or(core_fn: Callable[..., Array], kernel: Callable[..., Array]) -> Callable[..., Any]:
    """The Backend's ``choose`` for a function with C kernels: ``kernel(*arrays, **options)`` or
    ``core_fn`` as :func:`_on_the_cpu` decides. The kernels have the core's non-finite rows (the torch
    binding's tests)."""

    def evaluate(xp: Any, *arrays: Array, **options: Any) -> Array:
        return _on_the_cpu(
            lambda *xs: kernel(*xs, **options), lambda *xs: core_fn(xp, *xs, **options), *arrays
        )

    return lambda *arrays: evaluate


# The Jacobians and quaternion_plus take the kernels on the CPU while cpu_kernels is on: side by side
# with the formula (benchmarks/LIE.md) one custom call each way, where XLA's programs for the formula
# have 7 to 21 kernels; below N ~ 16 rotations those run inline, above they go to XLA's thread pool,
# and a custom call, which XLA's cost model counts as no work, keeps the whole call inline.
def _jacobian_choice(kind: str) -> Callable[..., Any]:
    return _kernels_or(_xla.JACOBIANS[kind], lambda omega: _xla.jacobian(omega, kind))


# by the kinds of _xla.JACOBIANS; empty, and None, (the formula) where the extension was not built
_JACOBIAN_CHOICE = {kind: _jacobian_choice(kind) for kind in _xla.JACOBIANS} if _xla is not None else {}
_QPLUS_CHOICE = _kernels_or(_lie.quaternion_plus, _xla.quaternion_plus) if _xla is not None else None


@documented(_lie.so3_left_jacobian)
def so3_left_jacobian(omega: ArrayLike) -> Array:
    return _B(_lie.so3_left_jacobian, omega, choose=_JACOBIAN_CHOICE.get("jl"))


@documented(_lie.so3_right_jacobian)
def so3_right_jacobian(omega: ArrayLike) -> Array:
    return _B(_lie.so3_right_jacobian, omega, choose=_JACOBIAN_CHOICE.get("jr"))


@documented(_lie.so3_left_jacobian_inverse)
def so3_left_jacobian_inverse(omega: ArrayLike) -> Array:
    return _B(_lie.so3_left_jacobian_inverse, omega, choose=_JACOBIAN_CHOICE.get("jl_inv"))


@documented(_lie.so3_right_jacobian_inverse)
def so3_right_jacobian_inverse(omega: ArrayLike) -> Array:
    return _B(_lie.so3_right_jacobian_inverse, omega, choose=_JACOBIAN_CHOICE.get("jr_inv"))


@documented(_lie.so3_vee)
def so3_vee(matrix: ArrayLike) -> Array:
    return _B(_lie.so3_vee, matrix)


@documented(_lie.so3_exp)
def so3_exp(omega: ArrayLike) -> Array:
    return _B(_lie.so3_exp, omega)


@documented(_lie.so3_log)
def so3_log(matrix: ArrayLike) -> Array:
    return _B(_lie.so3_log, matrix, to_quaternion=_m2q_step)


@documented(_lie.so3_plus)
def so3_plus(matrix: ArrayLike, delta: ArrayLike, *, side: Side = "right") -> Array:
    return _B(_lie.so3_plus, matrix, delta, side=side)


@documented(_lie.so3_minus)
def so3_minus(matrix1: ArrayLike, matrix2: ArrayLike, *, side: Side = "right") -> Array:
    return _B(_lie.so3_minus, matrix1, matrix2, side=side, to_quaternion=_M2Q[True])


@documented(_lie.quaternion_plus)
def quaternion_plus(
    q: ArrayLike, delta: ArrayLike, *, side: Side = "right", scalar_first: bool = True
) -> Array:
    return _B(_lie.quaternion_plus, q, delta, side=side, scalar_first=scalar_first, choose=_QPLUS_CHOICE)


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
_rotation_mean = _compiled(_stats.rotation_mean, "method", "procrustes", "karcher", "median")
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
