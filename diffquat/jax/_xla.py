"""``matrix_to_quaternion`` on the CPU through the C kernels of ``diffquat/_kernels.c``, called from
XLA programs (jax's FFI): one pass over memory forward and one backward, where XLA's own loops for
the formula run at 13% of the copy bound forward and its reverse mode takes several passes.

Three primitives, each over any leading batch dimensions:

- ``m2q(matrix) -> q``: the forward kernel.
- ``m2q_tangent(matrix, q, dm) -> dq``, linear in ``dm``: the core's forward-mode formula
  (:func:`diffquat._core.matrix_to_quaternion_tangent`), which XLA compiles; forward mode is no hot
  path, and it has no kernel. Its transpose is ``m2q_cotangent``.
- ``m2q_cotangent(matrix, q, g) -> dL/dR``, linear in ``g``: the backward kernel. Its transpose is
  ``m2q_tangent``.

So ``jvp`` is the kernel and the core tangent, and ``vjp``/``grad`` the two kernels. The tangent and
the cotangent differentiate in all their arguments as the core formulas that they evaluate, so every
higher order (``hessian``, ``check_grads`` at order 2) works through XLA's derivatives of those.
``vmap`` moves the batch axis to the front (the kernels loop over leading dimensions).

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
from jax import Array
from jax.core import ShapedArray
from jax.extend.core import Primitive
from jax.interpreters import ad, batching, mlir
from jax.sharding import PartitionSpec

from .. import _core, _kernels
from ._namespace import XP

_ORDER = {True: "wxyz", False: "xyzw"}

# jax's interpreter helpers carry no annotations; typed here once.
_instantiate: Callable[[Any], Array] = ad.instantiate_zeros
_undefined: Callable[[Any], bool] = ad.is_undefined_primal
_spec: Callable[..., PartitionSpec] = PartitionSpec


def _bind(prim: Primitive, *args: Any, scalar_first: bool) -> Array:
    bind: Callable[..., Array] = prim.bind
    return bind(*args, scalar_first=scalar_first)


def _register_targets() -> None:
    """Register each handler with XLA's CPU runtime once (the registry is global to the process), as
    batch partitionable: each kernel loops over the leading batch dimensions of every operand and
    result, so a shard of the batch is computed by the same call on the shard."""
    partitionable = getattr(jax.ffi, "register_ffi_target_as_batch_partitionable", None)  # newer jax
    for name, capsule in _kernels.xla_handlers().items():
        jax.ffi.register_ffi_target(f"diffquat_{name}", capsule, platform="cpu")
        if partitionable is not None:
            partitionable(f"diffquat_{name}")


_register_targets()


def _primitive(name: str, abstract: Callable[..., ShapedArray], formula: Callable[..., Array]) -> Primitive:
    """A primitive evaluated eagerly by ``jit`` of itself, lowered as ``formula`` (the core) on every
    platform; the CPU lowering of a kernel is registered beside it."""
    prim: Any = Primitive(f"diffquat_{name}")  # untyped in jax

    @functools.cache
    def compiled(**params: Any) -> Callable[..., Array]:
        return jax.jit(functools.partial(prim.bind, **params))

    prim.def_impl(lambda *args, **params: compiled(**params)(*args))
    prim.def_abstract_eval(abstract)
    mlir.register_lowering(prim, mlir.lower_fun(formula, multiple_results=False))
    batching.primitive_batchers[prim] = functools.partial(_batched, prim)
    return cast(Primitive, prim)


def _batched(prim: Primitive, args: tuple[Array, ...], dims: tuple[int | None, ...], **params: Any) -> Any:
    """``vmap``: the batch axis moved to the front of every argument (broadcast where unbatched)."""
    size = next(arg.shape[dim] for arg, dim in zip(args, dims, strict=True) if dim is not None)
    moved = [
        jax.numpy.broadcast_to(arg, (size, *arg.shape)) if dim is None else jax.numpy.moveaxis(arg, dim, 0)
        for arg, dim in zip(args, dims, strict=True)
    ]
    return _bind(prim, *moved, **params), 0


def _batch_partitioning(ctx: Any) -> dict[str, Any]:
    """The attributes that let XLA's SPMD partitioners split a kernel's custom call along the leading
    batch dimensions that all its operands and its result share (those of the matrix, its first
    operand). GSPMD reads the number of batch dimensions of a target registered as batch partitionable
    (``_register_targets``); Shardy, jax's default partitioner, reads a sharding rule: one factor per
    batch dimension, shared by every operand and the result, and one per other dimension, each its
    own (never split). Without them, ``jit`` over a batch-sharded array gathers the whole batch on
    every device and runs the kernel on all of it there (``shard_map`` needs neither: each device
    lowers its own shard)."""
    if not all(isinstance(n, int) for aval in (*ctx.avals_in, *ctx.avals_out) for n in aval.shape):
        return {}  # symbolic sizes (shape polymorphism): no rule to state, XLA keeps the call whole
    batch = ctx.avals_in[0].ndim - 2
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


def _kernel_lowering(prim: Primitive, kernel: str, formula: Callable[..., Array]) -> None:
    """The CPU lowering of ``prim``: a custom call of the handler for its storage order, for the
    dtypes the kernels have (the handlers read float64 or else float32); any other dtype is
    ``formula``, and so is a program lowered for ``jax.export`` (the artefact must run without
    diffquat's handlers, and jax.export refuses custom calls that are not jax's own)."""
    fallback = mlir.lower_fun(formula, multiple_results=False)

    def lower(ctx: Any, *args: Any, scalar_first: bool) -> Any:
        if ctx.avals_in[0].dtype not in (jax.numpy.float32, jax.numpy.float64) or _for_export(ctx):
            return fallback(ctx, *args, scalar_first=scalar_first)
        # The order is in the target's name: the handlers take no attributes.
        rule = jax.ffi.ffi_lowering(
            f"diffquat_{kernel}_{_ORDER[scalar_first]}", extra_attributes=_batch_partitioning(ctx)
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
    the same axes, as jax's own primitives require (a tangent or cotangent varies with its matrix)."""
    mat = getattr(arg, "mat", None)  # jax before varying-axes types has none
    if any(getattr(other, "mat", None) != mat for other in others):
        raise ValueError(f"diffquat: arguments that vary over different mesh axes: {(arg, *others)}")
    batch = arg.ndim - core
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
_kernel_lowering(m2q_p, "m2q_forward", _forward_formula)
_kernel_lowering(m2q_cotangent_p, "m2q_backward", _cotangent_formula)


def _m2q_jvp(primals: tuple[Array], tangents: tuple[Any], *, scalar_first: bool) -> tuple[Array, Array]:
    (matrix,), (dm,) = primals, tangents
    q = _bind(m2q_p, matrix, scalar_first=scalar_first)
    return q, _bind(m2q_tangent_p, matrix, q, _instantiate(dm), scalar_first=scalar_first)


def _formula_jvp(formula: Callable[..., Array]) -> Callable[..., tuple[Array, Array]]:
    """The JVP of a tangent or cotangent primitive in all its arguments: that of the core formula it
    evaluates, differentiated by jax (second and higher orders only)."""

    def jvp(
        primals: tuple[Array, ...], tangents: tuple[Any, ...], *, scalar_first: bool
    ) -> tuple[Array, Array]:
        fn = functools.partial(formula, scalar_first=scalar_first)
        out: tuple[Array, Array] = jax.jvp(fn, primals, tuple(_instantiate(t) for t in tangents))
        return out

    return jvp


def _transpose(to: Primitive) -> Callable[..., list[Any]]:
    """Transpose of a tangent or cotangent primitive in its linear (last) argument: the other one,
    at the same matrix and result."""

    def transpose(ct: Any, matrix: Any, q: Any, linear: Any, *, scalar_first: bool) -> list[Any]:
        assert not _undefined(matrix) and not _undefined(q)
        if type(ct) is ad.Zero:
            return [None, None, ad.Zero(linear.aval)]
        return [None, None, _bind(to, matrix, q, ct, scalar_first=scalar_first)]

    return transpose


ad.primitive_jvps[m2q_p] = _m2q_jvp
ad.primitive_jvps[m2q_tangent_p] = _formula_jvp(_tangent_formula)
ad.primitive_jvps[m2q_cotangent_p] = _formula_jvp(_cotangent_formula)
ad.primitive_transposes[m2q_tangent_p] = _transpose(m2q_cotangent_p)
ad.primitive_transposes[m2q_cotangent_p] = _transpose(m2q_tangent_p)


def matrix_to_quaternion(matrix: Array, scalar_first: bool) -> Array:
    """:func:`diffquat._core.matrix_to_quaternion` of a float32 or float64 ``(..., 3, 3)`` array."""
    return _bind(m2q_p, matrix, scalar_first=bool(scalar_first))
