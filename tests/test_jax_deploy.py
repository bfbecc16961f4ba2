"""Where a jax model goes after training: every function of the table exports with ``jax.export`` (with
a static and with a symbolic batch size), the serialized artefact runs in a process that never
imported diffquat, and every function runs under ``shard_map`` (with its default checks), ``pmap`` and
``jit`` over a batch-sharded array on the two host CPU devices of ``conftest.py``.

One generic case (the "random" rotations of the table): the shapes, types and programs are under test
here, not the branches, which the shared matrix covers. float64 results are compared with eager ones
tightly; float32 artefacts with the table's oracle at the table's bound. XLA's compile time is what
this file costs, so every function of the table is one output of a single program per variant (one
export per dtype and batch kind, one program per transform), and each test reads its op's output:
a new row of the table adds an output, not a compilation.
"""

from __future__ import annotations

import json
import subprocess
import sys
from collections.abc import Callable
from dataclasses import dataclass
from functools import cache
from pathlib import Path
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from cases import CASES_BY_NAME, OPS, OPS_BY_NAME, VALUE_TOL, Op, table_error
from jax.sharding import NamedSharding
from jax.sharding import PartitionSpec as P

import diffquat.jax as dq

CASE = CASES_BY_NAME["random"]  # 64 rotations
SYMBOLIC_CALL = 7  # the batch size a symbolic artefact is called at: one that no export saw
AXIS = "batch"


def inputs(op: Op, dtype: str, batch: int | None = None) -> list[np.ndarray]:
    return [np.asarray(x[:batch], dtype) for x in op.inputs(CASE.quaternions("float64"))]


def function(op: Op) -> Callable[..., Any]:
    return lambda *xs: op(dq, *xs)


def close(actual: Any, expected: Any) -> None:
    np.testing.assert_allclose(np.asarray(actual), np.asarray(expected), rtol=1e-12, atol=1e-12)


def eager(op: Op, mode: str = "forward") -> np.ndarray:
    """The float64 values of ``op`` on the case, eager; each computed once."""
    return _reference(op.id, mode)


@cache
def _reference(op_id: str, mode: str) -> np.ndarray:
    op = OPS_BY_NAME[op_id]
    assert mode == "forward"
    return np.asarray(function(op)(*(jnp.asarray(x) for x in inputs(op, "float64"))))


def all_inputs(dtype: str, batch: int | None = None) -> list[np.ndarray]:
    return [x for op in OPS for x in inputs(op, dtype, batch)]


def all_outputs(*xs: Any) -> tuple[Any, ...]:
    """Every op of the table at its slice of ``xs`` (:func:`all_inputs`): one program for the table."""
    out, start = [], 0
    for op in OPS:
        count = len(op.inputs(CASE.quaternions("float64")))
        out.append(function(op)(*xs[start : start + count]))
        start += count
    return tuple(out)


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
        for i, out in enumerate(exported.call(*(args[f"x{i}"] for i in range(count)))):
            outputs[f"{key}.{i}"] = np.asarray(out)
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
    return {
        f"{dtype}-{shape}": Artefact(
            all_outputs,
            all_inputs(dtype, SYMBOLIC_CALL if shape == "symbolic" else None),
            shape == "symbolic",
        )
        for dtype, shape in VARIANTS
    }


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
def test_exports_and_runs_without_diffquat(op: Op, dtype: str, shape: str, exported: Exported) -> None:
    """Each function exports, with a symbolic batch size too, and the artefact runs in a process that
    never imported diffquat: in float64 it gives the eager values, in float32 the oracle's at the
    table's bound. The symbolic artefact is called at a batch size no export saw."""
    key = f"{dtype}-{shape}"
    assert key not in exported.errors, exported.errors.get(key)
    actual = exported.outputs[f"{key}.{OPS.index(op)}"]
    received = inputs(op, dtype, SYMBOLIC_CALL if shape == "symbolic" else None)
    assert actual.dtype == received[0].dtype
    if dtype == "float64":
        close(actual, eager(op))
    else:
        assert (
            table_error(op, [x.astype(np.float64) for x in received], actual)
            <= VALUE_TOL[dtype] * op.tol_scale
        )


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
        return jax.tree.map(lambda o: o.reshape(-1, *o.shape[2:]), out), compiled.as_text()
    if transform == "shard_map":
        fn = jax.shard_map(fn, mesh=mesh, in_specs=P(AXIS), out_specs=P(AXIS))
    compiled = jax.jit(fn).lower(*split).compile()
    out = compiled(*split)
    for o in jax.tree.leaves(out):
        assert o.sharding.spec[:1] == (AXIS,), f"the result is not split as the batch: {o.sharding}"
    return out, compiled.as_text()


TRANSFORMS = ["shard_map", "pmap", "sharded_jit"]


_DISTRIBUTED: dict[str, tuple[Any, ...]] = {}


@pytest.mark.parametrize("transform", TRANSFORMS)
@pytest.mark.parametrize("op", OPS, ids=lambda op: op.id)
def test_every_function_runs_on_two_devices(op: Op, transform: str, mesh: Any) -> None:
    """Each function of the table gives its eager values under ``shard_map`` (with its default
    checks), ``pmap`` and ``jit`` of batch-sharded arrays, whose result stays split as the batch; one
    program per transform holds every function (:func:`all_outputs`)."""
    if transform not in _DISTRIBUTED:
        xs = [jnp.asarray(x) for x in all_inputs("float64")]
        _DISTRIBUTED[transform] = distributed(transform, all_outputs, xs, mesh)[0]
    close(_DISTRIBUTED[transform][OPS.index(op)], eager(op))
