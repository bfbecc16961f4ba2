"""Where a jax model goes after training: every function of the table exports with ``jax.export`` (by
default, with a static and with a symbolic batch size) and the serialized artefact runs in a process
that never imported diffquat; every function runs under ``shard_map`` (with its default checks),
``pmap`` and ``jit`` over a batch-sharded array on the two host CPU devices of ``conftest.py``, with
the C kernels off (the default) and on; and the switch ``diffquat.jax.cpu_kernels`` changes the CPU
program, not the values, never lets a compiled program outlive a flip, and never reaches an export.

One generic case (the "random" rotations of the table): the shapes, types and programs are under test
here, not the branches, which the shared matrix covers. float64 results are compared with eager ones
tightly; float32 artefacts with the table's oracle at the table's bound. Every program here is
compiled once (XLA's compile time is what this file costs), each eager reference computed once.
"""

from __future__ import annotations

import json
import os
import re
import subprocess
import sys
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from functools import cache
from pathlib import Path
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from cases import CASES_BY_NAME, JAX_KERNELS, OPS, OPS_BY_NAME, VALUE_TOL, Op, table_error
from jax.sharding import AxisType, NamedSharding
from jax.sharding import PartitionSpec as P

import diffquat.jax as dq

# The rows whose CPU program the switch changes (cases.JAX_KERNELS);
# test_the_switch_decides_the_cpu_program checks the table against every row.
KERNEL_OPS = frozenset(JAX_KERNELS)
CASE = CASES_BY_NAME["random"]  # 64 rotations
SYMBOLIC_CALL = 7  # the batch size a symbolic artefact is called at: one that no export saw
AXIS = "batch"

needs_kernels = pytest.mark.skipif(dq._xla is None, reason="the C extension is not built (no C compiler)")


def inputs(op: Op, dtype: str, batch: int | None = None) -> list[np.ndarray]:
    return [np.asarray(x[:batch], dtype) for x in op.inputs(CASE.quaternions("float64"))]


def function(op: Op) -> Callable[..., Any]:
    return lambda *xs: op(dq, *xs)


def kernel_calls(program: str) -> list[str]:
    """The diffquat custom-call targets in a StableHLO or compiled HLO text (not the primitives' names
    in the locations and metadata)."""
    return sorted(
        set(re.findall(r'(?:custom_call_target="|stablehlo\.custom_call @)(diffquat_\w+)', program))
    )


def close(actual: Any, expected: Any) -> None:
    np.testing.assert_allclose(np.asarray(actual), np.asarray(expected), rtol=1e-12, atol=1e-12)


def eager(op: Op, mode: str = "forward") -> np.ndarray:
    """The float64 values of ``op`` on the case, eager, or of its ``vjp`` (the formula's reverse mode,
    under ``jit``: eager reverse mode compiles each of its many operations on its own, seconds per
    op); each computed once, with the kernels off."""
    return _reference(op.id, mode)


@cache
def _reference(op_id: str, mode: str) -> np.ndarray:
    op = OPS_BY_NAME[op_id]
    fn = function(op) if mode == "forward" else jax.jit(vjp(function(op)))
    with dq.cpu_kernels(False):
        return np.asarray(fn(*(jnp.asarray(x) for x in inputs(op, "float64"))))


@pytest.fixture(autouse=True)
def _kernels_off() -> Iterator[None]:
    """Each test starts with the switch in its default state and leaves it there."""
    with dq.cpu_kernels(False):
        yield


# ---------------------------------------------------------------------------------------------------
# jax.export: every artefact exported here, all run in one child process that never imports diffquat.

CHILD = """
import json, sys
import jax
import numpy as np

jax.config.update("jax_enable_x64", True)
folder = sys.argv[1]
manifest = json.load(open(f"{folder}/manifest.json"))
outputs, errors = {}, {}
for key, count in manifest.items():
    try:
        exported = jax.export.deserialize(bytearray(open(f"{folder}/{key}.bin", "rb").read()))
        args = np.load(f"{folder}/{key}.npz")
        outputs[key] = np.asarray(exported.call(*(args[f"x{i}"] for i in range(count))))
    except Exception as error:  # reported per artefact by the test that reads it
        errors[key] = f"{type(error).__name__}: {error}"
assert "diffquat" not in sys.modules, sorted(m for m in sys.modules if "diffquat" in m)
np.savez(f"{folder}/outputs.npz", **outputs)
json.dump(errors, open(f"{folder}/errors.json", "w"))
"""


@dataclass(frozen=True)
class Artefact:
    fn: Callable[..., Any]
    args: list[np.ndarray]  # what the exported function is called with in the child
    symbolic: bool


# (dtype, batch size) of the artefacts of every function: float64 exported at the case's static
# shape, float32 with a symbolic batch size.
VARIANTS = [("float64", "static"), ("float32", "symbolic")]


def _artefacts() -> dict[str, Artefact]:
    out = {}
    for op in OPS:
        for dtype, shape in VARIANTS:
            batch = SYMBOLIC_CALL if shape == "symbolic" else None
            out[f"{op.id}-{dtype}-{shape}"] = Artefact(
                function(op), inputs(op, dtype, batch), shape == "symbolic"
            )
    for op in OPS:
        if op.id in KERNEL_OPS:  # exported with the switch on: forward, and reverse mode (a vjp)
            out[f"{op.id}-kernels-forward"] = Artefact(function(op), inputs(op, "float64"), symbolic=False)
            out[f"{op.id}-kernels-vjp"] = Artefact(vjp(function(op)), inputs(op, "float64"), symbolic=False)
    return out


def vjp(fn: Callable[..., Any]) -> Callable[..., Any]:
    """The gradient of a fixed weighting of every output entry (the weights depend on nothing)."""

    def loss(*xs: Any) -> Any:
        out = fn(*xs)
        weights = jnp.linspace(0.5, 1.5, out.shape[-1], dtype=out.dtype)
        return (out * jnp.broadcast_to(weights, out.shape)).sum()

    return jax.grad(loss)


@dataclass(frozen=True)
class Exported:
    programs: dict[str, str]  # key -> StableHLO text, or the export's error
    outputs: dict[str, np.ndarray]
    errors: dict[str, str]  # key -> the export's or the child's error


@pytest.fixture(scope="module")
def exported(tmp_path_factory: pytest.TempPathFactory) -> Exported:
    folder: Path = tmp_path_factory.mktemp("exported")
    programs, errors, manifest = {}, {}, {}
    for key, art in _artefacts().items():
        shapes: list[Any] = list(art.args)
        if art.symbolic:
            (batch,) = jax.export.symbolic_shape("b")
            shapes = [jax.ShapeDtypeStruct((batch, *x.shape[1:]), x.dtype) for x in art.args]
        try:
            with dq.cpu_kernels("kernels" in key):
                artefact = jax.export.export(jax.jit(art.fn))(*shapes)
        except Exception as error:
            errors[key] = f"export: {type(error).__name__}: {error}"
            continue
        programs[key] = artefact.mlir_module()
        (folder / f"{key}.bin").write_bytes(artefact.serialize())
        np.savez(folder / f"{key}.npz", **{f"x{i}": x for i, x in enumerate(art.args)})
        manifest[key] = len(art.args)
    (folder / "manifest.json").write_text(json.dumps(manifest))
    child = subprocess.run(
        [sys.executable, "-c", CHILD, str(folder)], capture_output=True, text=True, timeout=600
    )
    assert child.returncode == 0, child.stderr[-4000:]
    errors.update(json.loads((folder / "errors.json").read_text()))
    with np.load(folder / "outputs.npz") as outputs:
        return Exported(programs, {k: outputs[k] for k in outputs.files}, errors)


@pytest.mark.parametrize(("dtype", "shape"), VARIANTS, ids=[f"{d}-{s}" for d, s in VARIANTS])
@pytest.mark.parametrize("op", OPS, ids=lambda op: op.id)
def test_exports_by_default_and_runs_without_diffquat(
    op: Op, dtype: str, shape: str, exported: Exported
) -> None:
    """By default no function calls diffquat's kernels, so each exports (jax.export refuses custom
    calls without a compatibility guarantee), with a symbolic batch size too, and the artefact runs
    in a process that never imported diffquat: in float64 it gives the eager values, in float32 the
    oracle's at the table's bound. The symbolic artefact is called at a batch size no export saw."""
    key = f"{op.id}-{dtype}-{shape}"
    assert key not in exported.errors, exported.errors.get(key)
    assert kernel_calls(exported.programs[key]) == []
    actual = exported.outputs[key]
    received = inputs(op, dtype, SYMBOLIC_CALL if shape == "symbolic" else None)
    assert actual.dtype == received[0].dtype
    if dtype == "float64":
        close(actual, eager(op))
    else:
        assert (
            table_error(op, [x.astype(np.float64) for x in received], actual)
            <= VALUE_TOL[dtype] * op.tol_scale
        )


@needs_kernels
@pytest.mark.parametrize("mode", ["forward", "vjp"])
@pytest.mark.parametrize("op", [op for op in OPS if op.id in KERNEL_OPS], ids=lambda op: op.id)
def test_export_with_the_kernels_on_takes_the_formula(op: Op, mode: str, exported: Exported) -> None:
    """With the switch on, a program lowered for ``jax.export`` takes the formula on the CPU too (as
    ``cpu_kernels`` documents): it exports, forward and reverse mode, and runs without diffquat."""
    key = f"{op.id}-kernels-{mode}"
    assert key not in exported.errors, exported.errors.get(key)
    assert kernel_calls(exported.programs[key]) == []
    close(exported.outputs[key], eager(op, mode))


# ---------------------------------------------------------------------------------------------------
# Two host devices: shard_map, pmap, jit over a batch-sharded array.


@pytest.fixture(scope="module")
def mesh() -> jax.sharding.Mesh:
    assert jax.device_count() >= 2, "conftest.py asks jax for two host CPU devices"
    return jax.make_mesh((2,), (AXIS,))


def distributed(transform: str, fn: Callable[..., Any], xs: list[Any], mesh: Any) -> tuple[Any, str]:
    """``fn`` of ``xs`` (which share their leading batch dimension) split over the two devices by
    ``transform``, compiled once; with the compiled program's text."""
    split = [jax.device_put(x, NamedSharding(mesh, P(AXIS))) for x in xs]
    if transform == "pmap":
        stacked = [x.reshape(2, -1, *x.shape[1:]) for x in xs]
        compiled = jax.pmap(fn).lower(*stacked).compile()
        out = compiled(*stacked)
        return out.reshape(-1, *out.shape[2:]), compiled.as_text()
    if transform == "shard_map":
        fn = jax.shard_map(fn, mesh=mesh, in_specs=P(AXIS), out_specs=P(AXIS))
    compiled = jax.jit(fn).lower(*split).compile()
    out = compiled(*split)
    assert out.sharding.spec[:1] == (AXIS,), f"the result is not split as the batch: {out.sharding}"
    return out, compiled.as_text()


TRANSFORMS = ["shard_map", "pmap", "sharded_jit"]


@pytest.mark.parametrize("transform", TRANSFORMS)
@pytest.mark.parametrize("op", OPS, ids=lambda op: op.id)
def test_every_function_runs_on_two_devices(op: Op, transform: str, mesh: Any) -> None:
    """Each function of the table (the formula: the default) gives its eager values under
    ``shard_map`` (with its default checks), ``pmap`` and ``jit`` of batch-sharded arrays, whose
    result stays split as the batch."""
    out, _ = distributed(transform, function(op), [jnp.asarray(x) for x in inputs(op, "float64")], mesh)
    close(out, eager(op))


@needs_kernels
@pytest.mark.parametrize("transform", TRANSFORMS)
@pytest.mark.parametrize("op", [op for op in OPS if op.id in KERNEL_OPS], ids=lambda op: op.id)
def test_the_kernels_run_on_two_devices(op: Op, transform: str, mesh: Any) -> None:
    """With the switch on, the kernels' primitives keep their input's type (its sharding, and the
    mesh axes it varies over inside ``shard_map``), so the three transforms trace them, forward and
    reverse mode (the tangent and the cotangent primitives); each device runs the kernels on its own
    shard, without gathering the batch (the custom calls are batch partitionable for XLA's
    partitioners, with an automatic mesh too); the values are the eager formula's."""
    xs = [jnp.asarray(x) for x in inputs(op, "float64")]
    meshes = [mesh, jax.make_mesh((2,), (AXIS,), axis_types=(AxisType.Auto,))]
    for mode, fn in (("forward", function(op)), ("vjp", vjp(function(op)))):
        for where in meshes if transform == "sharded_jit" else meshes[:1]:
            with dq.cpu_kernels():
                out, program = distributed(transform, fn, xs, where)
            assert kernel_calls(program), "the kernels were not called"
            assert "all-gather" not in program
            close(out, eager(op, mode))


@needs_kernels
@pytest.mark.parametrize("transform", ["shard_map", "sharded_jit"])
def test_quaternion_plus_of_two_mesh_types(transform: str, mesh: Any) -> None:
    """``quaternion_plus`` of a batch-split ``q`` and a ``delta`` replicated on both devices (inside
    ``shard_map``: one varies over the mesh axis, the other not; under ``jit``: two shardings), as
    jax's own operations take them: with the switch on, its value and its gradient in both are the
    formula's (the kernels' primitives take one type for both operands, so this pair takes the
    formula)."""
    op = OPS_BY_NAME["quaternion_plus[left]"]
    q, delta = (jnp.asarray(x) for x in inputs(op, "float64"))
    delta = delta[:1]  # one step for the whole batch
    plus = function(op)
    if transform == "shard_map":
        plus = jax.shard_map(plus, mesh=mesh, in_specs=(P(AXIS), P()), out_specs=P(AXIS))

    def fn(q: Any, d: Any) -> Any:
        return plus(q, d), jax.grad(lambda q, d: (plus(q, d) ** 2).sum(), (0, 1))(q, d)

    q_split = jax.device_put(q, NamedSharding(mesh, P(AXIS)))
    d_whole = jax.device_put(delta, NamedSharding(mesh, P()))
    with dq.cpu_kernels():
        by_kernels = jax.jit(fn)(q_split, d_whole)
    with dq.cpu_kernels(False):
        by_formula = jax.jit(fn)(q_split, d_whole)
    for a, b in zip(jax.tree.leaves(by_kernels), jax.tree.leaves(by_formula), strict=True):
        close(a, b)
    with dq.cpu_kernels(False):
        close(by_kernels[0], function(op)(q, delta))  # and the unsplit call's


# ---------------------------------------------------------------------------------------------------
# The switch.


@needs_kernels
@pytest.mark.parametrize("op", OPS, ids=lambda op: op.id)
def test_the_switch_decides_the_cpu_program(op: Op) -> None:
    """On, exactly the functions of KERNEL_OPS call the kernels on the CPU, with the formula's values
    (off, none does: test_exports_by_default_and_runs_without_diffquat reads every exported program)."""
    xs = [jnp.asarray(x) for x in inputs(op, "float64")]
    fn = jax.jit(function(op))
    with dq.cpu_kernels():
        program = fn.lower(*xs).as_text()
        if op.id in KERNEL_OPS:
            close(fn(*xs), eager(op))
    assert kernel_calls(program) == ([f"diffquat_{JAX_KERNELS[op.id]}"] if op.id in KERNEL_OPS else [])


@needs_kernels
def test_a_flip_retraces_and_never_reuses_the_other_program() -> None:
    """The switch is part of jit's cache key: a function compiled in one state is traced again in the
    other, and each state finds its own program again; the call form and the block restore as
    documented, and a function that enters the block inside its trace takes the kernels."""
    m = jnp.asarray(inputs(OPS_BY_NAME["matrix_to_quaternion"], "float32")[0])
    traces: list[bool] = []

    @jax.jit
    def f(x: Any) -> Any:
        traces.append(dq._kernels_on())
        return dq.matrix_to_quaternion(x)

    def calls() -> list[str]:
        return kernel_calls(f.lower(m).compile().as_text())

    formula = f(m)
    assert traces == [False] and calls() == []
    with dq.cpu_kernels():
        kernels = f(m)
        assert traces == [False, True] and calls() == ["diffquat_m2q_forward_wxyz"]
        with dq.cpu_kernels(False):
            f(m)
            assert dq._kernels_on() is False
        assert dq._kernels_on() is True
    f(m)
    assert dq._kernels_on() is False
    dq.cpu_kernels(True)  # the call form: on until switched off
    f(m)
    assert dq._kernels_on() is True
    dq.cpu_kernels(False)
    assert traces == [False, True]  # each state found its program again: no third trace
    assert calls() == []
    # both, in float32, against the float64 formula on the same matrices
    reference = np.asarray(dq.matrix_to_quaternion(m.astype(jnp.float64)))
    for out in (formula, kernels):
        assert np.abs(np.asarray(out, np.float64) - reference).max() <= VALUE_TOL["float32"]

    @jax.jit
    def inside(x: Any) -> Any:
        with dq.cpu_kernels():
            return dq.matrix_to_quaternion(x)

    assert kernel_calls(inside.lower(m).compile().as_text()) == ["diffquat_m2q_forward_wxyz"]
    assert dq._kernels_on() is False


def test_the_switch_from_the_environment(monkeypatch: pytest.MonkeyPatch) -> None:
    """DIFFQUAT_JAX_CPU_KERNELS gives the switch its state at import: off unless set to 1 (or true,
    on, yes); anything else is an error, not a silent default."""
    for value, state in [("", False), ("0", False), ("off", False), ("1", True), ("True", True)]:
        monkeypatch.setenv("DIFFQUAT_JAX_CPU_KERNELS", value)
        assert dq._from_environment() is state
    monkeypatch.delenv("DIFFQUAT_JAX_CPU_KERNELS")
    assert dq._from_environment() is False
    monkeypatch.setenv("DIFFQUAT_JAX_CPU_KERNELS", "fast")
    with pytest.raises(ValueError, match="DIFFQUAT_JAX_CPU_KERNELS"):
        dq._from_environment()


@needs_kernels
def test_the_environment_turns_the_kernels_on_at_import() -> None:
    code = (
        "import jax, jax.numpy as jnp, diffquat.jax as dq\n"
        "text = jax.jit(dq.matrix_to_quaternion).lower(jnp.ones((4, 3, 3))).as_text()\n"
        "assert 'diffquat_m2q_forward_wxyz' in text, text\n"
    )
    env = {**os.environ, "DIFFQUAT_JAX_CPU_KERNELS": "1"}
    done = subprocess.run([sys.executable, "-c", code], env=env, capture_output=True, text=True, timeout=300)
    assert done.returncode == 0, done.stderr[-4000:]


def test_switch_without_the_kernels(monkeypatch: pytest.MonkeyPatch) -> None:
    """Where the extension was not built, turning the switch on warns and keeps the formula."""
    monkeypatch.setattr(dq, "_KERNELS_ON", None)
    with pytest.warns(RuntimeWarning, match="no effect"):
        dq.cpu_kernels(True)
    assert dq._kernels_on() is False
    m = jnp.ones((4, 3, 3))
    assert kernel_calls(jax.jit(dq.matrix_to_quaternion).lower(m).as_text()) == []
