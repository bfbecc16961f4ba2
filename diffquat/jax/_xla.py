"""``matrix_to_quaternion``, the SO(3) Jacobians and ``quaternion_plus`` on the CPU through the C
kernels of ``diffquat/_kernels.c``, called from XLA programs (jax's FFI): one pass over memory forward
and one backward, where XLA's own loops for the formula run at 13% of the copy bound forward
(``matrix_to_quaternion``) and its reverse mode takes several passes. At small N the gain is XLA's
dispatch: the formula's programs have 7 to 21 kernels, which from some 16 rotations on XLA's CPU
client runs on its thread pool (its cost model estimates 1000 floating-point operations or more),
where one custom call, to which the cost model assigns none, runs inline.

Each map has three primitives over any leading batch dimensions; for ``matrix_to_quaternion``:

- ``m2q(matrix) -> q``: the forward kernel.
- ``m2q_tangent(matrix, q, dm) -> dq``, linear in ``dm``: the core's forward-mode formula
  (:func:`diffquat._core.matrix_to_quaternion_tangent`), which XLA compiles; forward mode is no hot
  path, and it has no kernel. Its transpose is ``m2q_cotangent``.
- ``m2q_cotangent(matrix, q, g) -> dL/dR``, linear in ``g``: the backward kernel. Its transpose is
  ``m2q_tangent``.

So ``jvp`` is the kernel and the core tangent, and ``vjp``/``grad`` the two kernels. The tangent and
the cotangent differentiate in all their arguments as the core formulas that they evaluate, so every
higher order (``hessian``, ``check_grads`` at order 2) works through XLA's derivatives of those.
``vmap`` moves the batch axis to the front (the kernels loop over leading dimensions). The Jacobians
(``jac``, ``jac_tangent``, ``jac_cotangent``, the kind a parameter) and ``quaternion_plus``
(``qplus``, ``qplus_tangent``, ``qplus_cotangent``, which returns the cotangents of both arguments)
follow the same pattern, their tangents being jax's forward mode of the core formulas.

The kernels take float32 and float64 (the backend computes half precision in float32 before). Only
the CPU lowering calls them; every other platform lowers the core formulas, and
:mod:`diffquat.jax` only takes this path where ``jit`` lowers for the CPU (``platform_dependent``),
and only while :func:`diffquat.jax.cpu_kernels` is on (off by default). A program lowered for
``jax.export`` lowers the formulas on the CPU too: jax.export refuses custom calls that are not jax's
own, and an artefact that called them would run only where this module registered the handlers.

The abstract evaluations keep the input's type beyond shape and dtype: the sharding of the batch
dimensions (sharding in types: ``jit`` over explicitly sharded inputs) and the mesh axes the value
varies over inside ``shard_map`` (``check_vma``): dropping them gave the kernels' branch of
``platform_dependent`` another type than the formula's, which ``shard_map`` refuses. The handlers are
registered as batch partitionable, and each custom call says how many leading batch dimensions it
has, so that XLA's SPMD partitioner runs the kernel on each device's shard of a batch-sharded array
rather than gather the whole batch on every device.
"""

from __future__ import annotations

import functools
import itertools
from collections.abc import Callable
from typing import Any, cast

import jax
import numpy as np
from jax import Array
from jax.core import ShapedArray
from jax.extend.core import Primitive
from jax.interpreters import ad, batching, mlir
from jax.sharding import PartitionSpec

from .. import _algebra, _core, _kernels, _lie
from ._namespace import XP

_ORDER = {True: "wxyz", False: "xyzw"}

# jax's interpreter helpers carry no annotations; typed here once.
_instantiate: Callable[[Any], Array] = ad.instantiate_zeros
_undefined: Callable[[Any], bool] = ad.is_undefined_primal
_spec: Callable[..., PartitionSpec] = PartitionSpec


def _bind(prim: Primitive, *args: Any, **params: Any) -> Any:
    bind: Callable[..., Any] = prim.bind
    return bind(*args, **params)


def _register_targets() -> None:
    """Register each handler with XLA's CPU runtime once (the registry is global to the process), as
    batch partitionable: each kernel loops over the leading batch dimensions of every operand and
    result, so a shard of the batch is computed by the same call on the shard."""
    partitionable = getattr(jax.ffi, "register_ffi_target_as_batch_partitionable", None)  # newer jax
    for name, capsule in _kernels.xla_handlers().items():
        jax.ffi.register_ffi_target(f"diffquat_{name}", capsule, platform="cpu")
        if partitionable is not None:
            partitionable(f"diffquat_{name}")


def _set_tables() -> None:
    """Hand the kernels the tables that the torch binding passes with each call: the Jacobians'
    series (:func:`diffquat._lie.series_table`) and ``exp_factors``' threshold and series
    (:func:`diffquat._algebra.exp_series_table`), for float32 and float64 (copied by the C side,
    before any handler is registered)."""
    for f64, dtype in ((0, np.float32), (1, np.float64)):
        flat, terms = _lie.series_table(float(np.finfo(dtype).eps))
        series = np.asarray(flat, np.float64)
        exp = np.asarray(_algebra.exp_series_table(np, dtype), np.float64)
        _kernels.xla_set_tables(f64, series.ctypes.data, len(series), *terms, exp.ctypes.data)


_set_tables()
_register_targets()


def _primitive(
    name: str, abstract: Callable[..., Any], formula: Callable[..., Any], multiple_results: bool = False
) -> Primitive:
    """A primitive evaluated eagerly by ``jit`` of itself, lowered as ``formula`` (the core) on every
    platform; the CPU lowering of a kernel is registered beside it. ``multiple_results``: ``abstract``
    and ``formula`` return a list (quaternion_plus's cotangent in both arguments)."""
    prim: Any = Primitive(f"diffquat_{name}")  # untyped in jax
    prim.multiple_results = multiple_results

    @functools.cache
    def compiled(**params: Any) -> Callable[..., Array]:
        return jax.jit(functools.partial(prim.bind, **params))

    prim.def_impl(lambda *args, **params: compiled(**params)(*args))
    prim.def_abstract_eval(abstract)
    mlir.register_lowering(prim, mlir.lower_fun(formula, multiple_results=multiple_results))
    batching.primitive_batchers[prim] = functools.partial(_batched, prim)
    return cast(Primitive, prim)


def _batched(prim: Primitive, args: tuple[Array, ...], dims: tuple[int | None, ...], **params: Any) -> Any:
    """``vmap``: the batch axis moved to the front of every argument (broadcast where unbatched)."""
    size = next(arg.shape[dim] for arg, dim in zip(args, dims, strict=True) if dim is not None)
    moved = [
        jax.numpy.broadcast_to(arg, (size, *arg.shape)) if dim is None else jax.numpy.moveaxis(arg, dim, 0)
        for arg, dim in zip(args, dims, strict=True)
    ]
    out = _bind(prim, *moved, **params)
    return out, [0] * len(out) if prim.multiple_results else 0


def _batch_partitioning(ctx: Any, core: int) -> dict[str, Any]:
    """The attributes that let XLA's SPMD partitioners split a kernel's custom call along the leading
    batch dimensions that all its operands and its results share (those of its first operand, which
    has ``core`` more: the matrix's two, the quaternion's or the rotation vector's one). GSPMD reads
    the number of batch dimensions of a target registered as batch partitionable
    (``_register_targets``); Shardy, jax's default partitioner, reads a sharding rule: one factor per
    batch dimension, shared by every operand and every result, and one per other dimension, each its
    own (never split). Without them, ``jit`` over a batch-sharded array gathers the whole batch on
    every device and runs the kernel on all of it there (``shard_map`` needs neither: each device
    lowers its own shard)."""
    if not all(isinstance(n, int) for aval in (*ctx.avals_in, *ctx.avals_out) for n in aval.shape):
        return {}  # symbolic sizes (shape polymorphism): no rule to state, XLA keeps the call whole
    batch = ctx.avals_in[0].ndim - core
    attributes: dict[str, Any] = {
        "mhlo.frontend_attributes": mlir.ir_attribute({"num_batch_dims": str(batch)})
    }
    if getattr(jax.config, "jax_use_shardy_partitioner", False):
        # Shardy names factors i, j, ..., z, z_1, z_2, ... in the order of their first use.
        names = (chr(ord("i") + k) if k < 18 else f"z_{k - 17}" for k in itertools.count())
        sizes: list[tuple[str, int]] = [(next(names), int(n)) for n in ctx.avals_in[0].shape[:batch]]
        batch_names = [name for name, _ in sizes]

        def mapping(aval: Any) -> str:
            own = [(next(names), int(n)) for n in aval.shape[batch:]]
            sizes.extend(own)
            return "[" + ", ".join(batch_names + [name for name, _ in own]) + "]"

        operands = ", ".join(mapping(aval) for aval in ctx.avals_in)
        results = ", ".join(mapping(aval) for aval in ctx.avals_out)
        factors = ", ".join(f"{name}={n}" for name, n in sizes)
        rule = f"#sdy.op_sharding_rule<({operands})->({results}) {{{factors}}}>"
        attributes["sdy.sharding_rule"] = mlir.ir.Attribute.parse(rule)
    return attributes


def _for_export(ctx: Any) -> bool:
    """Whether ``ctx`` lowers a program for ``jax.export``. jax has no public way to ask; its lowering
    parameters say so (``for_export``, which ``jax.export`` sets). Read defensively: where a jax has
    no such field, the kernels are lowered and ``jax.export`` refuses them with its own error."""
    params = getattr(getattr(ctx, "module_context", None), "lowering_parameters", None)
    return bool(getattr(params, "for_export", False))


def _kernel_lowering(
    prim: Primitive, target: Callable[..., str], formula: Callable[..., Any], core: int
) -> None:
    """The CPU lowering of ``prim``: a custom call of the handler ``target(**params)`` (the storage
    order, the side, the Jacobian are in the handler's name: the handlers take no attributes), for
    operands of one of the dtypes the kernels have (the handlers read float64 or else float32); any
    other dtype is ``formula``, and so is a program lowered for ``jax.export`` (the artefact must run
    without diffquat's handlers, and jax.export refuses custom calls that are not jax's own). ``core``:
    the trailing dimensions of the first operand beyond the batch."""
    fallback = mlir.lower_fun(formula, multiple_results=prim.multiple_results)

    def lower(ctx: Any, *args: Any, **params: Any) -> Any:
        dtypes = {aval.dtype for aval in ctx.avals_in}
        if len(dtypes) != 1 or dtypes.pop() not in (jax.numpy.float32, jax.numpy.float64) or _for_export(ctx):
            return fallback(ctx, *args, **params)
        rule = jax.ffi.ffi_lowering(
            f"diffquat_{target(**params)}", extra_attributes=_batch_partitioning(ctx, core)
        )
        return rule(ctx, *args)

    mlir.register_lowering(prim, lower, platform="cpu")


def _forward_formula(matrix: Array, *, scalar_first: bool) -> Array:
    return _core.matrix_to_quaternion(XP, matrix, scalar_first=scalar_first)


def _tangent_formula(matrix: Array, q: Array, dm: Array, *, scalar_first: bool) -> Array:
    return _core.matrix_to_quaternion_tangent(XP, matrix, q, dm, scalar_first=scalar_first)


def _cotangent_formula(matrix: Array, q: Array, g: Array, *, scalar_first: bool) -> Array:
    if not scalar_first:  # the core's cotangent reads scalar-first quaternions
        q, g = _core.xyzw_to_wxyz(XP, q), _core.xyzw_to_wxyz(XP, g)
    return _core.matrix_to_quaternion_cotangent(XP, matrix, q, g)


def _result_type(arg: Any, core: int, trailing: tuple[int, ...], *others: Any) -> ShapedArray:
    """The abstract value of a result with the batch dimensions of ``arg`` (all but its last
    ``core``) followed by ``trailing``: the dtype of ``arg``, not weak, and the rest of its type, which
    ``update`` keeps: the sharding of the batch dimensions (sharding in types; the trailing ones
    unsharded) and the mesh axes it varies over inside ``shard_map``. Every argument must vary over
    the same axes: a kernel's primitive takes one type for all its operands (a tangent or cotangent
    varies with its matrix, and ``quaternion_plus`` gives two inputs of two types to the formula)."""
    mat = getattr(arg, "mat", None)  # jax before varying-axes types has none
    if any(getattr(other, "mat", None) != mat for other in others):
        raise ValueError(f"diffquat: arguments that vary over different mesh axes: {(arg, *others)}")
    batch = arg.ndim - core
    # The kernels read as many rows of every operand as the first has: one batch shape for all (the
    # public functions broadcast first; a primitive bound directly on others is refused here).
    if any(other.shape[:batch] != arg.shape[:batch] or other.ndim - batch not in (1, 2) for other in others):
        raise ValueError(f"diffquat: operands of different batch shapes: {(arg, *others)}")
    shape = (*arg.shape[:batch], *trailing)
    sharding = getattr(arg, "sharding", None)  # jax before sharding in types has none
    if sharding is None:
        return cast(ShapedArray, arg.update(shape=shape, weak_type=False))
    spec = (*sharding.spec, *(None,) * (arg.ndim - len(sharding.spec)))
    sharding = sharding.update(spec=_spec(*spec[:batch], *(None,) * len(trailing)))
    return cast(ShapedArray, arg.update(shape=shape, weak_type=False, sharding=sharding))


m2q_p = _primitive("m2q", lambda matrix, *, scalar_first: _result_type(matrix, 2, (4,)), _forward_formula)
m2q_tangent_p = _primitive(
    "m2q_tangent",
    lambda matrix, q, dm, *, scalar_first: _result_type(q, 1, (4,), matrix, dm),
    _tangent_formula,
)
m2q_cotangent_p = _primitive(
    "m2q_cotangent",
    lambda matrix, q, g, *, scalar_first: _result_type(matrix, 2, (3, 3), q, g),
    _cotangent_formula,
)
_kernel_lowering(m2q_p, lambda scalar_first: f"m2q_forward_{_ORDER[scalar_first]}", _forward_formula, 2)
_kernel_lowering(
    m2q_cotangent_p, lambda scalar_first: f"m2q_backward_{_ORDER[scalar_first]}", _cotangent_formula, 2
)


def _m2q_jvp(primals: tuple[Array], tangents: tuple[Any], *, scalar_first: bool) -> tuple[Array, Array]:
    (matrix,), (dm,) = primals, tangents
    q = _bind(m2q_p, matrix, scalar_first=scalar_first)
    return q, _bind(m2q_tangent_p, matrix, q, _instantiate(dm), scalar_first=scalar_first)


def _formula_jvp(formula: Callable[..., Any]) -> Callable[..., tuple[Any, Any]]:
    """The JVP of a tangent or cotangent primitive in all its arguments: that of the core formula it
    evaluates, differentiated by jax (second and higher orders only)."""

    def jvp(primals: tuple[Array, ...], tangents: tuple[Any, ...], **params: Any) -> tuple[Any, Any]:
        fn = functools.partial(formula, **params)
        out: tuple[Any, Any] = jax.jvp(fn, primals, tuple(_instantiate(t) for t in tangents))
        return out

    return jvp


def _transpose(to: Primitive) -> Callable[..., list[Any]]:
    """Transpose of a tangent or cotangent primitive in its linear (last) argument: the other one,
    at the same other arguments (the matrix and its quaternion; the rotation vector)."""

    def transpose(ct: Any, *args: Any, **params: Any) -> list[Any]:
        *fixed, linear = args
        assert not any(_undefined(arg) for arg in fixed)
        if type(ct) is ad.Zero:
            return [*(None for _ in fixed), ad.Zero(linear.aval)]
        return [*(None for _ in fixed), _bind(to, *fixed, ct, **params)]

    return transpose


def _differentiate(
    prim: Primitive,
    jvp: Callable[..., tuple[Any, Any]],
    tangent: tuple[Primitive, Callable[..., Any]],
    cotangent: tuple[Primitive, Callable[..., Any]],
    transposes: tuple[Callable[..., list[Any]], Callable[..., list[Any]]] | None = None,
) -> None:
    """Register the derivative rules of a map's three primitives: ``jvp`` for the forward kernel, the
    formulas' JVPs for the tangent and the cotangent primitive (each given with its formula), and
    their transposes, by default :func:`_transpose` of each other."""
    (tangent_p, tangent_formula), (cotangent_p, cotangent_formula) = tangent, cotangent
    ad.primitive_jvps[prim] = jvp
    ad.primitive_jvps[tangent_p] = _formula_jvp(tangent_formula)
    ad.primitive_jvps[cotangent_p] = _formula_jvp(cotangent_formula)
    of_tangent, of_cotangent = transposes or (_transpose(cotangent_p), _transpose(tangent_p))
    ad.primitive_transposes[tangent_p] = of_tangent
    ad.primitive_transposes[cotangent_p] = of_cotangent


_differentiate(m2q_p, _m2q_jvp, (m2q_tangent_p, _tangent_formula), (m2q_cotangent_p, _cotangent_formula))


def matrix_to_quaternion(matrix: Array, scalar_first: bool) -> Array:
    """:func:`diffquat._core.matrix_to_quaternion` of a float32 or float64 ``(..., 3, 3)`` array."""
    return _bind(m2q_p, matrix, scalar_first=bool(scalar_first))


# ---------------------------------------------------------------------------------------------------
# The SO(3) Jacobians and quaternion_plus: the kernels of the torch binding (_kernels.c), the same
# arrangement as above. Each map has three primitives: the forward kernel; its tangent, the forward
# mode of the core formula (jax.jvp of it, which XLA compiles); its cotangent, the backward kernel,
# whose formula is jax.vjp of the core. Tangent and cotangent are each other's transpose.


# The Jacobian of each kind (the kernels' Args.first: 0 J_l, 1 J_r, 2 J_l^-1, 3 J_r^-1), by the
# name of its handlers.
JACOBIANS: dict[str, Callable[[Any, Array], Array]] = {
    "jl": _lie.so3_left_jacobian,
    "jr": _lie.so3_right_jacobian,
    "jl_inv": _lie.so3_left_jacobian_inverse,
    "jr_inv": _lie.so3_right_jacobian_inverse,
}


def _forward_mode(formula: Callable[..., Array], inputs: int) -> Callable[..., Array]:
    """The tangent formula of ``formula`` of ``inputs`` arrays: ``(*x, *dx) -> dy``, jax's forward mode."""

    def tangent(*args: Array, **params: Any) -> Array:
        out: Array = jax.jvp(functools.partial(formula, **params), args[:inputs], args[inputs:])[1]
        return out

    return tangent


def _reverse_mode(formula: Callable[..., Array], inputs: int) -> Callable[..., Any]:
    """The cotangent formula of ``formula`` of ``inputs`` arrays: ``(*x, g) -> dL/dx`` (a list where
    ``inputs`` > 1, as a primitive of multiple results returns), jax's reverse mode."""

    def cotangent(*args: Array, **params: Any) -> Any:
        _, pullback = jax.vjp(functools.partial(formula, **params), *args[:inputs])
        out = pullback(args[inputs])
        return list(out) if inputs > 1 else out[0]

    return cotangent


def _jac_formula(omega: Array, *, kind: str) -> Array:
    return JACOBIANS[kind](XP, omega)


_jac_tangent_formula = _forward_mode(_jac_formula, 1)
_jac_cotangent_formula = _reverse_mode(_jac_formula, 1)


jac_p = _primitive("jac", lambda omega, *, kind: _result_type(omega, 1, (3, 3)), _jac_formula)
jac_tangent_p = _primitive(
    "jac_tangent", lambda omega, domega, *, kind: _result_type(omega, 1, (3, 3), domega), _jac_tangent_formula
)
jac_cotangent_p = _primitive(
    "jac_cotangent", lambda omega, g, *, kind: _result_type(omega, 1, (3,), g), _jac_cotangent_formula
)
_kernel_lowering(jac_p, lambda kind: f"jac_forward_{kind}", _jac_formula, 1)
_kernel_lowering(jac_cotangent_p, lambda kind: f"jac_backward_{kind}", _jac_cotangent_formula, 1)


def _jac_jvp(primals: tuple[Array], tangents: tuple[Any], *, kind: str) -> tuple[Array, Array]:
    (omega,), (domega,) = primals, tangents
    return _bind(jac_p, omega, kind=kind), _bind(jac_tangent_p, omega, _instantiate(domega), kind=kind)


_differentiate(
    jac_p, _jac_jvp, (jac_tangent_p, _jac_tangent_formula), (jac_cotangent_p, _jac_cotangent_formula)
)


def jacobian(omega: Array, kind: str) -> Array:
    """The Jacobian ``kind`` (a key of :data:`JACOBIANS`) of a float32 or float64 ``(..., 3)`` array."""
    return cast(Array, _bind(jac_p, omega, kind=kind))


def _qplus_formula(q: Array, d: Array, *, scalar_first: bool, right: bool) -> Array:
    side = "right" if right else "left"
    return _lie.quaternion_plus(XP, q, d, side=side, scalar_first=scalar_first)


_qplus_tangent_formula = _forward_mode(_qplus_formula, 2)
_qplus_cotangent_formula = _reverse_mode(_qplus_formula, 2)


def _qplus_target(kind: str) -> Callable[..., str]:
    return lambda scalar_first, right: f"qplus_{kind}_{_ORDER[scalar_first]}_{'right' if right else 'left'}"


qplus_p = _primitive(
    "qplus", lambda q, d, *, scalar_first, right: _result_type(q, 1, (4,), d), _qplus_formula
)
qplus_tangent_p = _primitive(
    "qplus_tangent",
    lambda q, d, dq, dd, *, scalar_first, right: _result_type(q, 1, (4,), d, dq, dd),
    _qplus_tangent_formula,
)
qplus_cotangent_p = _primitive(
    "qplus_cotangent",
    lambda q, d, g, *, scalar_first, right: [_result_type(q, 1, (4,), d, g), _result_type(d, 1, (3,), q, g)],
    _qplus_cotangent_formula,
    multiple_results=True,
)
_kernel_lowering(qplus_p, _qplus_target("forward"), _qplus_formula, 1)
_kernel_lowering(qplus_cotangent_p, _qplus_target("backward"), _qplus_cotangent_formula, 1)


def _qplus_jvp(
    primals: tuple[Array, Array], tangents: tuple[Any, Any], *, scalar_first: bool, right: bool
) -> tuple[Array, Array]:
    (q, d), (dq, dd) = primals, tangents
    params = {"scalar_first": scalar_first, "right": right}
    out = _bind(qplus_p, q, d, **params)
    return out, _bind(qplus_tangent_p, q, d, _instantiate(dq), _instantiate(dd), **params)


def _qplus_tangent_transpose(ct: Any, q: Any, d: Any, dq: Any, dd: Any, **params: Any) -> list[Any]:
    """The tangent is linear in (dq, dd): its transpose is the cotangent, in both at once."""
    assert not _undefined(q) and not _undefined(d)
    if type(ct) is ad.Zero:
        return [None, None, ad.Zero(dq.aval), ad.Zero(dd.aval)]
    gq, gd = _bind(qplus_cotangent_p, q, d, ct, **params)
    return [None, None, gq, gd]


def _qplus_cotangent_transpose(cts: list[Any], q: Any, d: Any, g: Any, **params: Any) -> list[Any]:
    """The cotangent is linear in g: its transpose is the tangent, at the cotangents of both results."""
    assert not _undefined(q) and not _undefined(d)
    if all(type(ct) is ad.Zero for ct in cts):
        return [None, None, ad.Zero(g.aval)]
    cq, cd = (_instantiate(ct) for ct in cts)
    return [None, None, _bind(qplus_tangent_p, q, d, cq, cd, **params)]


_differentiate(
    qplus_p,
    _qplus_jvp,
    (qplus_tangent_p, _qplus_tangent_formula),
    (qplus_cotangent_p, _qplus_cotangent_formula),
    (_qplus_tangent_transpose, _qplus_cotangent_transpose),
)


def quaternion_plus(q: Array, delta: Array, side: str, scalar_first: bool) -> Array:
    """:func:`diffquat._lie.quaternion_plus` of float32 or float64 ``q`` (..., 4) and ``delta``
    (..., 3) of one dtype. The batch shapes are broadcast first (the kernels read one row of each per
    result row; jax sums the gradient of a broadcast input back)."""
    right = _lie.check_side("quaternion_plus", side)
    batch = jax.numpy.broadcast_shapes(q.shape[:-1], delta.shape[:-1])
    q = jax.numpy.broadcast_to(q, (*batch, 4))
    delta = jax.numpy.broadcast_to(delta, (*batch, 3))
    if not _one_type(q, delta):
        return _qplus_formula(q, delta, scalar_first=bool(scalar_first), right=right)
    return cast(Array, _bind(qplus_p, q, delta, scalar_first=bool(scalar_first), right=right))


def _one_type(a: Array, b: Array) -> bool:
    """Whether two arrays of one batch shape have one type beyond shape and dtype: they vary over the
    same mesh axes (inside ``shard_map``) and their batch dimensions are sharded alike. jax's own
    binary operations reconcile two such types (a ``pcast``, a resharding), which the formula
    inherits; a kernel's primitive takes one type for all its operands, so other pairs (``q``
    varying over an axis and ``delta`` replicated, say) take the formula."""
    ta, tb = jax.typeof(a), jax.typeof(b)
    if getattr(ta, "mat", None) != getattr(tb, "mat", None):
        return False
    sa, sb = getattr(ta, "sharding", None), getattr(tb, "sharding", None)
    if sa is None or sb is None:
        return sa is sb
    batch = a.ndim - 1
    return _padded(sa.spec, a.ndim)[:batch] == _padded(sb.spec, b.ndim)[:batch]


def _padded(spec: Any, ndim: int) -> tuple[Any, ...]:
    return (*spec, *(None,) * (ndim - len(spec)))
