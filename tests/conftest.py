"""One ``backend`` fixture, and the parametrisation that turns the table in ``cases.py`` into tests.

A test asks for any of ``op``, ``backend``, ``dtype`` and ``case``; it gets every combination, with
an id that names them in that order: ``test_values[quaternion_to_matrix-torch-float32-half_turns]``.
``cases.only`` narrows a test to some ops, backends, dtypes or cases.
"""

from __future__ import annotations

import gc
import importlib
import importlib.util
import itertools
import os
import re
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import jax
import numpy as np
import pytest
import torch
from cases import CASES, DTYPES, HOST_DTYPES, OPS, concatenate_cases, host_cast

# Switched once, here: float64 for the gradient checks, and strict promotion so the core cannot lean
# on an implicit cast or a rank broadcast that numpy or torch would not do the same way. Two host CPU
# devices for the sharding tests (shard_map, pmap, sharded jit: tests/test_jax_deploy.py); it must be
# set before anything starts jax's backend, and single-device programs still run on the first.
jax.config.update("jax_num_cpu_devices", 2)
# XLA compiles the suite's programs for speed of compiling, not of running: its classic CPU emitters,
# not its default fusion emitters (about half the compile time: a jax-heavy third of the suite 366 s
# -> 250 s), LLVM at -O0 (a third off again: jax's check_grads of three ops 55 s -> 36 s), and one
# LLVM module, not 32 split apart for parallel code generation, which the two workers' cores do not
# have to spare (cloning the parts was 11% of the largest derivative program's run: SQUAD's compiled
# in 36 s, not 45 s). None of them changes what IEEE arithmetic computes, and test_values.py checks
# every op at every value case under XLA's defaults too, in a subprocess, against the same oracles.
# Read when jax starts its CPU backend (at first use, below); a flag the caller set is kept.
COMPILE_SPEED_FLAGS = (
    "--xla_cpu_use_fusion_emitters=false",
    "--xla_backend_optimization_level=0",
    "--xla_cpu_parallel_codegen_split_count=1",
)
for _flag in COMPILE_SPEED_FLAGS:
    if _flag.split("=")[0] not in os.environ.get("XLA_FLAGS", ""):
        os.environ["XLA_FLAGS"] = f"{os.environ.get('XLA_FLAGS', '')} {_flag}".strip()
jax.config.update("jax_enable_x64", True)
jax.config.update("jax_numpy_dtype_promotion", "strict")
jax.config.update("jax_numpy_rank_promotion", "raise")
torch.set_default_dtype(torch.float32)

import jax.numpy as jnp  # noqa: E402

# Every executable XLA compiles for the CPU keeps about 40 memory mappings (its code and data) for as
# long as jax's in-memory caches hold it, and a worker of this suite compiles about 8000 programs
# (eager jax compiles each operation per shape and dtype; the derivative checks many shapes). Past the
# kernel's limit on mappings per process (vm.max_map_count, 65530 by default) the next mapping fails
# and XLA crashes in its compiler: a segfault, the worker lost, the run failed (the jax tests of
# test_grads.py alone, in one process, crashed after ~850 tests at 65531 mappings). So the caches are
# cleared when a worker's mappings pass a third of the limit; the count is read (a scan of
# /proc/self/maps, a few ms at these sizes) only after every _COMPILES_PER_CHECK compilations, which
# map far fewer than the margin. No persistent compilation cache (jax's default): it did not pay here.
_COMPILES_PER_CHECK = 50
_compiles = [0, 0]  # compilations so far, and at the last check


def _count_compiles(event: str, duration: float, **_: Any) -> None:
    if event == "/jax/core/compile/backend_compile_duration":
        _compiles[0] += 1


jax.monitoring.register_event_duration_secs_listener(_count_compiles)


def _map_limit() -> int:
    try:
        with open("/proc/sys/vm/max_map_count") as f:
            return int(f.read())
    except (OSError, ValueError):  # not Linux: no such limit to keep under
        return 0


_MAP_LIMIT = _map_limit()


def pytest_runtest_teardown(item: pytest.Item) -> None:
    if not _MAP_LIMIT or _compiles[0] - _compiles[1] < _COMPILES_PER_CHECK:
        return
    _compiles[1] = _compiles[0]
    with open("/proc/self/maps") as f:
        mappings = sum(1 for _ in f)
    if mappings > _MAP_LIMIT // 3:
        jax.clear_caches()
        gc.collect()


# The quick tier for local work: ``pytest -m "not slow"`` leaves out the checks that compile, export or
# run whole programs (tests/README.md). They are marked here, by file and by name, not one by one, so a
# new test of that kind is marked by its name; CI runs everything (no -m). Compiled: torch.compile
# (inductor, aot_eager) and jax.jit programs (test_jax_derivatives jits every derivative check of a
# row, the suite's largest cost after inductor); exported: jit.trace/script, torch.export, fx, ONNX,
# jax.export, sharded programs; and the notebooks, the documentation site, the wheel and the benchmarks'
# quick runs, each a program of its own.
SLOW_FILES = {
    "test_benchmark.py",
    "test_capture.py",
    "test_docs.py",
    "test_export_roundtrip.py",
    "test_jax_deploy.py",
    "test_notebooks.py",
    "test_scale_out.py",
    "test_wheel.py",
    "test_xla.py",
}
# the checks in those files that only read sources or merge tables, kept in the quick tier
QUICK_IN_SLOW_FILES = {
    "test_every_public_name_is_in_exactly_one_topic",
    "test_readme_links_into_the_docs_resolve",
    "test_readme_links_every_notebook_and_its_figure",
    "test_merge_lists_only_the_runs_whose_tables_it_shows",
}
SLOW_NAMES = re.compile(r"compil|jit|onnx|trace|captur|inductor|xla")
# long runs, each a program of its own: the soak tests of 10^4 optimiser steps (2 to 8 minutes of one
# worker, the quick tier's largest item; the poses' 40 s, its jax loop compiled)
SLOW_RUNS = {
    "test_torch_parameters_stay_rotations_for_ten_thousand_float32_steps",
    "test_pose_parameters_stay_rigid_for_ten_thousand_float32_steps",
}


def pytest_collection_modifyitems(config: pytest.Config, items: list[pytest.Item]) -> None:
    slow = pytest.mark.slow
    for item in items:
        name = getattr(item, "originalname", item.name)
        in_slow_file = item.path.name in SLOW_FILES and name not in QUICK_IN_SLOW_FILES
        if in_slow_file or SLOW_NAMES.search(name) or name == "test_jax_derivatives" or name in SLOW_RUNS:
            item.add_marker(slow)


@dataclass(frozen=True)
class Backend:
    """How the suite talks to one backend: its module, its dtypes, and conversions from/to NumPy."""

    name: str
    dtypes: dict[str, Any]
    asarray: Callable[[np.ndarray, Any], Any]
    to_numpy: Callable[[Any], np.ndarray]
    differentiable: bool

    @property
    def module(self) -> Any:
        return importlib.import_module(f"diffquat.{self.name}")

    def array(self, x: np.ndarray, dtype: str) -> Any:
        return self.asarray(np.asarray(x, dtype=np.float64), self.dtypes[dtype])


BACKENDS = {
    "numpy": Backend(
        "numpy",
        HOST_DTYPES,
        lambda x, dt: x.astype(dt),
        lambda x: np.asarray(x).astype(np.float64),
        differentiable=False,
    ),
    "torch": Backend(
        "torch",
        {
            "float64": torch.float64,
            "float32": torch.float32,
            "float16": torch.float16,
            "bfloat16": torch.bfloat16,
        },
        lambda x, dt: torch.from_numpy(x).to(dt),
        lambda x: x.detach().to(torch.float64).numpy(),
        differentiable=True,
    ),
    "jax": Backend(
        "jax",
        {"float64": jnp.float64, "float32": jnp.float32, "float16": jnp.float16, "bfloat16": jnp.bfloat16},
        # Cast on the host: a jax cast is a compiled program per shape and dtype, which made up a
        # third of the compilations of the value tests (numpy's casts round the same way).
        lambda x, dt: jax.device_put(host_cast(x, dt)),
        lambda x: np.asarray(x).astype(np.float64),
        differentiable=True,
    ),
}


@pytest.fixture
def backend(request: pytest.FixtureRequest) -> Backend:
    return BACKENDS[request.param]


def pytest_generate_tests(metafunc: pytest.Metafunc) -> None:
    names = metafunc.fixturenames
    if "backend" not in names:
        return
    keep = getattr(metafunc.function, "diffquat_filters", {})
    axes: list[tuple[str, list[Any], Callable[[Any], str]]] = []
    if "op" in names:
        axes.append(("op", OPS, lambda op: op.id))
    axes.append(("backend", list(BACKENDS), str))
    if "dtype" in names:
        axes.append(("dtype", list(DTYPES), str))
    if "case" in names:
        axes.append(("case", CASES, lambda case: case.name))
    axes = [(a, [v for v in values if keep.get(a, lambda v: True)(v)], fmt) for a, values, fmt in axes]
    pair = keep.get("pair", lambda op, case: True)
    argnames = [a for a, _, _ in axes]
    combos = list(itertools.product(*(values for _, values, _ in axes)))
    if "op" in argnames and "case" in argnames:
        i, j = argnames.index("op"), argnames.index("case")
        combos = [c for c in combos if c[i].applies(c[j]) and pair(c[i], c[j])]
    ids = ["-".join(fmt(v) for (_, _, fmt), v in zip(axes, combo, strict=True)) for combo in combos]
    metafunc.parametrize(argnames, combos, ids=ids, indirect=["backend"])


# Eager jax compiles every primitive anew for each (shape, dtype) it meets: a large op is ~150
# compilations, 2-3 s, at a new batch length (against ~0.4 s to jit the whole op once), and the
# suite's one-call-per-op batches had a length per op and test (528 and 190 rows for the values, 536
# and 198 for the finite gradients, 11 ... 225 for the degenerate configurations, 4 ... 8 for the
# non-finite rows). So those eager calls are padded to one length, JAX_ROWS (or a multiple): then an
# op's float32 primitives compiled for one test (or one dtype: half precision computes in float32)
# serve the next, and the elementwise ones (a product of (N, 4) arrays) serve every op. The padding
# repeats the batch's own rows; rows are independent (tests/test_values.py checks it), the extra
# rows' results are dropped, and no jax function chooses its path by the batch length.
JAX_ROWS = 576


def pad_rows(xs: list[np.ndarray], rows: int = JAX_ROWS) -> list[np.ndarray]:
    """Each of ``xs`` (arrays of one batch dimension ``n = len(xs[0])`` first) with its rows repeated
    cyclically to the least multiple of ``rows`` from ``n`` (an empty batch as it is); the caller keeps
    the first ``n`` rows of the result."""
    n = len(xs[0])
    if n == 0:
        return xs
    total = -(-n // rows) * rows
    return [np.take(x, np.arange(total) % n, axis=0) if np.ndim(x) and len(x) == n else x for x in xs]


_ROWS: dict[tuple[Any, ...], dict[str, list[np.ndarray]]] = {}


def rows_by_case(
    key: tuple[Any, ...],
    case: Any,
    batch_of: Callable[[Any], tuple[int, ...]],
    inputs: Callable[[Any], list[np.ndarray]],
    compute: Callable[[list[np.ndarray], tuple[int, ...]], list[np.ndarray]],
    applies: Callable[[Any], bool] = lambda case: True,
) -> list[np.ndarray]:
    """``compute(xs, batch)`` at ``case``: its outputs, arrays whose leading dimensions are ``batch``.

    Every case but the batch_* ones (and those ``applies`` rejects) is computed in one call, its
    inputs flattened to one batch dimension and concatenated, and the outputs are cached per ``key``
    and sliced per case. Rows are independent (a NaN row leaves the others alone:
    tests/test_values.py), so each row is the result at that row, while the compiled programs and
    the calls are one per op, not thirteen (eager jax compiles each primitive for every new shape, and
    the per-case calls made the per-case tests a compiler benchmark). The batch_* cases, whose point
    is the batch shape, are computed alone at their own shapes."""
    if case.name.startswith("batch_"):
        return compute(inputs(case), batch_of(case))
    if key not in _ROWS:
        cases = [c for c in CASES if not c.name.startswith("batch_") and applies(c)]
        concatenated, parts = concatenate_cases(cases, batch_of, inputs)
        outs = compute(concatenated, (len(concatenated[0]),))
        _ROWS[key] = {
            c.name: [o[rows].reshape(*batch, *o.shape[1:]) for o in outs] for c, rows, batch in parts
        }
    return _ROWS[key][case.name]


def case_rows(
    backend: Backend,
    dtype: str,
    case: Any,
    key: str,
    inputs: Callable[[Any], list[np.ndarray]],
    fn: Callable[..., Any],
) -> list[np.ndarray]:
    """``fn`` on the backend arrays of ``inputs(case)`` (float64 arrays of the case's batch shape, cast
    to ``dtype``): its outputs (an array or a tuple of arrays of the same batch shape) as float64.
    On jax from one call over all cases (:func:`rows_by_case`, ``key`` one per test), padded to
    :data:`JAX_ROWS` rows; numpy and torch, which compile nothing, evaluate each case as it is."""

    def call(xs: list[np.ndarray], batch: tuple[int, ...] | None = None) -> list[np.ndarray]:
        out = fn(*(backend.array(x, dtype) for x in xs))
        return [backend.to_numpy(o) for o in (out if isinstance(out, tuple) else (out,))]

    if backend.name != "jax":
        return call(inputs(case))

    def call_padded(xs: list[np.ndarray], batch: tuple[int, ...]) -> list[np.ndarray]:
        return [o[: len(xs[0])] for o in call(pad_rows(xs))]

    # the one call over the cases at JAX_ROWS rows; a batch_* case at its own shape
    return rows_by_case(
        (key, backend.name, dtype),
        case,
        lambda c: c.quaternions(dtype).shape[:-1],
        inputs,
        call if case.name.startswith("batch_") else call_padded,
    )
