"""Values against the scipy oracle, and the properties every user relies on, for every op, backend,
dtype and case in the table."""

from __future__ import annotations

import contextlib
import itertools
import os
import subprocess
import sys
from pathlib import Path
from typing import Any

import numpy as np
from cases import (
    CASES,
    DTYPES,
    HOST_DTYPES,
    OPS,
    ROUND_TRIP_TOL,
    VALUE_TOL,
    Case,
    Op,
    hamilton,
    host_cast,
    only,
    oracle_normalize,
    oracle_quaternion_to_matrix,
    table_error,
    uniform_quaternions,
    value_batches,
)
from conftest import COMPILE_SPEED_FLAGS, Backend, case_rows, pad_rows

WXYZ_TO_XYZW = [1, 2, 3, 0]
XYZW_TO_WXYZ = [3, 0, 1, 2]


def run(
    op: Op, backend: Backend, dtype: str, case: Case, scalar_last: bool = False
) -> tuple[list[np.ndarray], np.ndarray]:
    """Run ``op`` on the case's inputs cast to ``dtype`` (with ``scalar_last``: its quaternion arguments
    reordered, and ``scalar_first=False``); return the float64 values the backend received and its
    output. On jax, from one call over the op's value cases (``conftest.case_rows``)."""

    def inputs(c: Case) -> list[np.ndarray]:
        xs = op.inputs(c.quaternions(dtype))
        return [
            op.to_scalar_last(x) if scalar_last and i in op.quaternion_args else x for i, x in enumerate(xs)
        ]

    def apply(*xs: Any) -> Any:
        return op(backend.module, *xs, **({"scalar_first": False} if scalar_last else {}))

    if backend.name == "jax" and case.name.startswith("batch_"):
        # The batch_* cases are about the batch shape, which jit traces as eager jax runs it; eager
        # jax compiles every primitive anew for each new shape (2-3 s per op and case for SQUAD,
        # against 0.4 s for the whole program), and the eager values are checked at every other case.
        import jax

        apply = jax.jit(apply)

    def call(*xs: Any) -> tuple[Any, ...]:
        received = [backend.to_numpy(x) for x in xs]
        out = apply(*xs)
        assert out.dtype == xs[0].dtype, "dtype not preserved"
        assert type(out) is type(xs[0]), "array type not preserved"
        for x, before in zip(xs, received, strict=True):
            np.testing.assert_array_equal(backend.to_numpy(x), before, err_msg="the op wrote into its input")
        return (*xs, out)

    *received, out = case_rows(backend, dtype, case, f"run {op.id} {scalar_last}", inputs, call)
    return received, out


def tol(op: Op, dtype: str) -> float:
    return VALUE_TOL[dtype] * op.tol_scale


def max_error(actual: np.ndarray, expected: np.ndarray, up_to_sign: bool = False) -> float:
    if actual.size == 0:
        return 0.0
    err = np.abs(actual - expected).max(axis=-1)
    if up_to_sign:
        err = np.minimum(err, np.abs(actual + expected).max(axis=-1))
    return float(err.max())


FULL_DTYPES = ("float64", "float32")
HALF_DTYPES = ("float16", "bfloat16")


@only(dtype=lambda d: d in FULL_DTYPES)
def test_values(op: Op, backend: Backend, dtype: str, case: Case) -> None:
    """The oracle's values within the op's tolerance, and, from the same call, what a user relies on
    besides: a matrix is a rotation, a quaternion is unit and in canonical sign, and scalar-last
    storage gives the reordered scalar-first result bit for bit."""
    received, out = run(op, backend, dtype, case)
    check_values(op, dtype, received, out)
    check_properties(op, dtype, out)
    if op.scalar_first:
        _, last = run(op, backend, dtype, case, scalar_last=True)
        np.testing.assert_array_equal(from_scalar_last(op, last), out)


@only(backend=lambda name: name == "torch", dtype=lambda d: d in FULL_DTYPES)
def test_values_componentwise(op: Op, backend: Backend, dtype: str) -> None:
    """Eager torch runs a map's eager form (few vectorised operations, ``_core.EAGER_FORMS``) and the
    compilers its componentwise form: both forms of every row against the oracle and its properties,
    the componentwise one here run eagerly (``torch._custom.componentwise``) at every case, where the
    compiled tests reach it at a few. One test per row and dtype (a test per case cost minutes of
    pytest's own time); every failing case is named."""
    from diffquat.torch._custom import componentwise

    failures = []
    for case in CASES:
        if not op.applies(case):
            continue
        with componentwise():
            received, out = run(op, backend, dtype, case)
        try:
            check_values(op, dtype, received, out)
            check_properties(op, dtype, out)
        except AssertionError as error:
            failures.append(f"{case.name}: {error}")
    assert not failures, "\n".join(failures)


@only(dtype=lambda d: d in HALF_DTYPES)
def test_values_in_half_precision(op: Op, backend: Backend, dtype: str) -> None:
    """float16 and bfloat16 (computed in float32, returned in their dtype): what test_values checks,
    at every value case, in one call over the cases concatenated (rows are independent), each case's
    rows checked on their own."""
    xs, parts = value_batches(op, dtype)
    outs = {}
    for scalar_last in (False, True) if op.scalar_first else (False,):
        inputs = [
            op.to_scalar_last(x) if scalar_last and i in op.quaternion_args else x for i, x in enumerate(xs)
        ]
        # jax at conftest.JAX_ROWS rows: its float32 primitives those of the other tests' calls
        arrays = [backend.array(x, dtype) for x in (pad_rows(inputs) if backend.name == "jax" else inputs)]
        out = op(backend.module, *arrays, **({"scalar_first": False} if scalar_last else {}))
        assert out.dtype == arrays[0].dtype, "dtype not preserved"
        outs[scalar_last] = backend.to_numpy(out)[: len(xs[0])]
    failures = []
    for case, rows, batch in parts:
        received = [x[rows].reshape(*batch, *x.shape[1:]) for x in xs]
        out = outs[False][rows].reshape(*batch, *outs[False].shape[1:])
        try:
            check_values(op, dtype, received, out)
            check_properties(op, dtype, out)
            if op.scalar_first:
                last = outs[True][rows].reshape(*batch, *outs[True].shape[1:])
                np.testing.assert_array_equal(from_scalar_last(op, last), out)
        except AssertionError as error:
            failures.append(f"{case.name}: {error}")
    assert not failures, "\n".join(failures)


def from_scalar_last(op: Op, out: np.ndarray) -> np.ndarray:
    """A scalar-last call's output in scalar-first order (a quaternion output is reordered)."""
    return out[..., XYZW_TO_WXYZ] if op.output == "quaternion" else out


def check_values(op: Op, dtype: str, received: list[np.ndarray], out: np.ndarray) -> None:
    """``out`` (float64), what the op gave for the float64 values ``received`` in ``dtype``, is the
    oracle's within the op's tolerance."""
    assert np.all(np.isfinite(out))
    assert table_error(op, received, out) <= tol(op, dtype)


def check_properties(op: Op, dtype: str, out: np.ndarray) -> None:
    """A matrix output is a rotation (orthonormal, det 1); a quaternion output is unit (``op.unit``)
    and in canonical sign (``op.canonical``), within the op's tolerance."""
    if op.output == "matrix":
        gram = np.swapaxes(out, -1, -2) @ out
        assert max_error(gram, np.broadcast_to(np.eye(3), gram.shape)) <= 2 * tol(op, dtype)
        det = np.linalg.det(out) if out.size else np.ones(0)
        assert np.all(np.abs(det - 1) <= 3 * tol(op, dtype))
    if op.unit:
        norm = np.linalg.norm(out, axis=-1)
        assert np.all(np.abs(norm - 1) <= 2 * tol(op, dtype))
    if op.canonical:
        w, x, y, z = np.moveaxis(out, -1, 0)
        negative = (w < 0) | ((w == 0) & ((x < 0) | ((x == 0) & ((y < 0) | ((y == 0) & (z < 0))))))
        assert not np.any(negative)


# What test_jax_values_hold_under_xlas_default_flags runs in its subprocess: every op at every
# value case, one call per op and dtype, saved as float64.
_DEFAULT_EMITTERS = """
import sys
import jax
import jax.numpy as jnp
import numpy as np
jax.config.update("jax_enable_x64", True)
import diffquat.jax as dq
from cases import DTYPES, OPS, value_batches
out = {}
for op in OPS:
    for dtype in DTYPES:
        xs, _ = value_batches(op, dtype)
        y = op(dq, *(jnp.asarray(x, dtype=jnp.dtype(dtype)) for x in xs))
        out[op.id + "|" + dtype] = np.asarray(y).astype(np.float64)
np.savez(sys.argv[1], **out)
"""


def test_jax_values_hold_under_xlas_default_flags(tmp_path: Path) -> None:
    """The suite runs jax with XLA's classic CPU emitters and LLVM at -O0, which compile faster
    (tests/conftest.py); users run XLA's defaults. Every op at every value case, in
    every dtype, evaluated by a jax that runs the defaults, is the oracle's within the tolerance of
    test_values, so what test_values asserts holds on the default emitters too."""
    # (a blank XLA_FLAGS is read as the name of a file of flags: the rest are joined, or none)
    flags = " ".join(f for f in os.environ.get("XLA_FLAGS", "").split() if f not in COMPILE_SPEED_FLAGS)
    path = tmp_path / "values.npz"
    subprocess.run(
        [sys.executable, "-c", _DEFAULT_EMITTERS, str(path)],
        cwd=Path(__file__).parent,
        env={**os.environ, "XLA_FLAGS": flags},
        check=True,
        timeout=900,
    )
    values, failures = np.load(path), []
    for op in OPS:
        for dtype in DTYPES:
            xs, parts = value_batches(op, dtype)
            out = values[f"{op.id}|{dtype}"]
            for case, rows, batch in parts:
                received = [x[rows].reshape(*batch, *x.shape[1:]) for x in xs]
                try:
                    check_values(op, dtype, received, out[rows].reshape(*batch, *out.shape[1:]))
                except AssertionError as error:
                    failures.append(f"{op.id} {dtype} {case.name}: {error}")
    assert not failures, "\n".join(failures)


def test_round_trip_matrix_quaternion_matrix(backend: Backend, dtype: str, case: Case) -> None:
    """R -> q -> R reproduces R (the accuracy target of the core issue, exact half-turns included)."""
    dq = backend.module
    matrix, back = case_rows(
        backend,
        dtype,
        case,
        "round trip R q R",
        lambda c: [oracle_quaternion_to_matrix(c.quaternions(dtype))],
        lambda m: (m, dq.quaternion_to_matrix(dq.matrix_to_quaternion(m))),
    )
    assert max_error(back, matrix) <= ROUND_TRIP_TOL[dtype]


def test_round_trip_quaternion_matrix_quaternion(backend: Backend, dtype: str, case: Case) -> None:
    """q -> R -> q gives back q/|q| up to the canonical sign (the zero quaternion gives the identity)."""
    dq = backend.module
    q, back = case_rows(
        backend,
        dtype,
        case,
        "round trip q R q",
        lambda c: [c.quaternions(dtype)],
        lambda q: (q, dq.matrix_to_quaternion(dq.quaternion_to_matrix(q))),
    )
    assert max_error(back, oracle_normalize(q), up_to_sign=True) <= 2 * VALUE_TOL[dtype]


def unit_quaternion_matrices(backend: Backend, dtype: str, case: Case) -> list[np.ndarray]:
    """The case's quaternions normalised (as the backend received them, float64) and their matrices."""
    return case_rows(
        backend,
        dtype,
        case,
        "unit quaternion matrices",
        lambda c: [oracle_normalize(c.quaternions(dtype))],
        lambda q: (q, backend.module.quaternion_to_matrix(q)),
    )


def test_matrix_equals_the_quaternion_sandwich(backend: Backend, dtype: str, case: Case) -> None:
    """R(q) v == q v q* for unit q: the matrix is the active rotation that q stands for."""
    q_in, matrix = unit_quaternion_matrices(backend, dtype, case)
    v = np.random.default_rng(0).normal(size=(*q_in.shape[:-1], 3))
    rotated = (matrix @ v[..., None])[..., 0]
    pure = np.concatenate([np.zeros((*v.shape[:-1], 1)), v], axis=-1)
    conj = q_in * np.array([1.0, -1.0, -1.0, -1.0])
    sandwich = hamilton(hamilton(q_in, pure), conj)[..., 1:] / np.sum(q_in**2, axis=-1, keepdims=True)
    assert max_error(rotated, sandwich) <= 4 * VALUE_TOL[dtype] * max(1.0, float(np.abs(v).max(initial=0)))


def test_matches_the_kuipers_formula(backend: Backend, dtype: str, case: Case) -> None:
    """Kuipers, Quaternions and Rotation Sequences, section 5.14, on unit quaternions."""
    q_in, out = unit_quaternion_matrices(backend, dtype, case)
    q = oracle_normalize(q_in)  # unit in float64, as the formula assumes
    q0, q1, q2, q3 = np.moveaxis(q, -1, 0)
    kuipers = np.stack(
        [
            np.stack([2 * (q0**2 + q1**2) - 1, 2 * (q1 * q2 - q0 * q3), 2 * (q1 * q3 + q0 * q2)], -1),
            np.stack([2 * (q1 * q2 + q0 * q3), 2 * (q0**2 + q2**2) - 1, 2 * (q2 * q3 - q0 * q1)], -1),
            np.stack([2 * (q1 * q3 - q0 * q2), 2 * (q2 * q3 + q0 * q1), 2 * (q0**2 + q3**2) - 1], -1),
        ],
        -2,
    )
    assert max_error(out, kuipers) <= VALUE_TOL[dtype]


def test_quaternion_and_its_negative_and_multiples_give_one_matrix(backend: Backend, dtype: str) -> None:
    q = uniform_quaternions(16, seed=7)
    scales = np.array([1.0, -1.0, 3.0, -0.25])[:, None, None]
    out = backend.to_numpy(backend.module.quaternion_to_matrix(backend.array(q[None] * scales, dtype)))
    assert max_error(out, np.broadcast_to(out[0], out.shape)) <= VALUE_TOL[dtype]


def test_cases_cover_the_named_edge_cases() -> None:
    """The suite's promise depends on these cases existing: guard the table against shrinking."""
    names = {c.name for c in CASES}
    assert {"random", "identity", "half_turns", "near_half_turns", "near_identity", "norms", "zero"} <= names
    shapes = {c.quaternions("float64").shape[:-1] for c in CASES}
    assert {(), (1,), (3, 1, 2), (0,)} <= shapes
    assert CASES[[c.name for c in CASES].index("half_turns")].quaternions("float64").shape == (26, 4)


def poisoned_batch(op: Op) -> tuple[list[np.ndarray], list[np.ndarray], list[int]]:
    """The op's inputs for a batch of generic rotations, clean and with non-finite entries: for each
    argument, one row with a NaN and one with an infinity (of either sign) in one of its entries,
    each in a row of its own; the last two rows stay finite everywhere. Returns (clean, poisoned,
    the poisoned rows)."""
    n_args = len(op.inputs(uniform_quaternions(1, seed=0)))
    n = 2 * n_args + 2
    clean = [np.array(x) for x in op.inputs(uniform_quaternions(n, seed=3))]
    poisoned = [x.copy() for x in clean]
    for i, x in enumerate(poisoned):
        rows = x.reshape(n, -1)  # a view of the (contiguous) copy, one row per batch element
        rows[2 * i, -1] = np.nan
        rows[2 * i + 1, 0] = np.inf if i % 2 == 0 else -np.inf
    return clean, poisoned, list(range(2 * n_args))


def test_nonfinite_rows_give_nan_rows_and_leave_the_others(op: Op, backend: Backend, dtype: str) -> None:
    """A NaN or an infinity anywhere in an input row makes that row's whole output NaN, and only that
    row's (the documented rule, the same on every backend and path: diffquat._backend.nonfinite_rows);
    the finite rows give what they give without their neighbours."""
    clean, poisoned, bad = poisoned_batch(op)
    n = len(clean[0])
    if backend.name == "jax":  # at conftest.JAX_ROWS rows, the other rows dropped
        clean, poisoned = pad_rows(clean), pad_rows(poisoned)
    out = backend.to_numpy(op(backend.module, *(backend.array(x, dtype) for x in poisoned)))[:n]
    expected = backend.to_numpy(op(backend.module, *(backend.array(x, dtype) for x in clean)))[:n]
    # Equal up to the rounding of the last bits: LAPACK (the SVD and eigh maps) rounds differently
    # depending on how its buffer is aligned; every other op gives the very same numbers.
    eps = float(np.finfo(np.float32 if dtype != "float64" else np.float64).eps)
    assert_nan_rows(out, expected, bad, atol=4 * eps)


def assert_nan_rows(out: np.ndarray, expected: np.ndarray, bad: list[int], atol: float) -> None:
    """The ``bad`` rows of ``out`` are NaN throughout, and the others equal ``expected`` within ``atol``
    (relative to entries of size 1 or more)."""
    assert np.all(np.isnan(out[bad]))
    good = [k for k in range(len(out)) if k not in bad]
    scale = np.maximum(np.abs(expected[good]), 1.0)
    np.testing.assert_allclose(out[good] / scale, expected[good] / scale, rtol=0, atol=atol)


def _nan_rows_by_arithmetic(op: Op) -> bool:
    import diffquat.numpy  # noqa: F401  (imports every core module, which mark their functions)
    from diffquat import _core

    return op.name in _core.NONFINITE_BY_ARITHMETIC and not op.variant_of


@only(op=_nan_rows_by_arithmetic, backend=lambda name: name != "numpy")
def test_nonfinite_rows_by_arithmetic_hold_compiled(op: Op, backend: Backend) -> None:
    """The functions that add no selection for non-finite rows (``_core.NONFINITE_BY_ARITHMETIC``:
    every output entry of a bad row is NaN by the arithmetic itself, a NaN-propagating maximum among
    it) keep that rule compiled, where the compiler may rewrite the arithmetic: under
    ``torch.compile(fullgraph=True)`` (inductor, the formula path) and ``jax.jit`` (XLA). The other
    rows are the eager float64 call's within the table's float32 tolerance (a reference, not another
    float32 evaluation)."""
    import jax
    import torch

    clean, poisoned, bad = poisoned_batch(op)
    xs = [backend.array(x, "float32") for x in poisoned]
    module = backend.module
    if backend.name == "torch":
        torch._dynamo.reset()
        compiled = torch.compile(lambda *a: op(module, *a), fullgraph=True, dynamic=False)
    else:
        compiled = jax.jit(lambda *a: op(module, *a))
    out = backend.to_numpy(compiled(*xs))
    expected = backend.to_numpy(op(module, *(backend.array(x, "float64") for x in clean)))
    assert_nan_rows(out, expected, bad, atol=tol(op, "float32"))


@only(op=_nan_rows_by_arithmetic, backend=lambda name: name == "torch")
def test_nonfinite_rows_by_arithmetic_hold_for_every_entry_on_both_forms(op: Op, backend: Backend) -> None:
    """``_core.NONFINITE_BY_ARITHMETIC`` promises a NaN row for a non-finite entry anywhere, and two
    forms compute each map in eager torch (the eager form, and the componentwise one, also the
    compilers'), whose arithmetic differs: every entry of every argument in turn, NaN, +inf and -inf,
    in every row of a batch of generic rotations, the identity and its negative (where products with
    zero components are exact zeros), gives all-NaN rows in both forms."""
    import torch

    from diffquat.torch._custom import componentwise

    q = np.concatenate([uniform_quaternions(6, seed=7), np.eye(4)[:1], -np.eye(4)[:1]])
    clean = [np.asarray(x, dtype=np.float64) for x in op.inputs(q)]
    for i, x in enumerate(clean):
        for j in range(x.reshape(len(q), -1).shape[1]):
            for value in (np.nan, np.inf, -np.inf):
                poisoned = [y.copy() for y in clean]
                poisoned[i].reshape(len(q), -1)[:, j] = value
                for forced in (False, True):
                    with componentwise() if forced else contextlib.nullcontext():
                        out = op(backend.module, *(torch.tensor(y) for y in poisoned)).numpy()
                    assert np.isnan(out).all(), f"argument {i}, entry {j}, {value}, componentwise={forced}"


@only(op=lambda op: op.name in ("matrix_to_quaternion", "matrix_to_axis_angle", "matrix_to_euler_angles"))
def test_huge_finite_matrices_give_finite_results(op: Op, backend: Backend, dtype: str) -> None:
    """Any finite matrix gives a finite unit quaternion, up to the largest finite number of the dtype
    (once the squares of the candidate's components overflowed from ~1.8e19 in float32 and 1.3e154 in
    float64, and (0, 0, 0, 0) came back, which later functions read as the identity), equal to the same
    map evaluated in extended precision (NumPy's longdouble: nothing overflows there); and so the
    conversions through it are finite."""
    from diffquat import _core

    largest = float(np.finfo(np.float16 if dtype == "float16" else np.float32).max)
    largest = {"float64": 1e308, "bfloat16": 3.3e38}.get(dtype, largest)
    rng = np.random.default_rng(4)
    rotations = oracle_quaternion_to_matrix(uniform_quaternions(8, seed=4))
    for factor in (1e10, 1e20, 1e160, largest / 1.01):
        if factor > largest:
            continue
        with np.errstate(over="ignore"):  # entries past the largest finite number are clipped to it
            matrices = np.concatenate([rotations, rng.normal(size=(4, 3, 3)), -np.eye(3)[None]]) * factor
        matrices = np.clip(matrices, -largest, largest)
        received = backend.to_numpy(backend.array(matrices, dtype))
        out = backend.to_numpy(op(backend.module, backend.array(matrices, dtype)))
        assert np.all(np.isfinite(out))
        if op.name != "matrix_to_quaternion":
            continue
        np.testing.assert_allclose(np.linalg.norm(out, axis=-1), 1.0, rtol=0, atol=2 * VALUE_TOL[dtype])
        with np.errstate(all="raise"):  # nothing may overflow in the reference
            expected = _core.matrix_to_quaternion(np, received.astype(np.longdouble)).astype(np.float64)
        assert max_error(out, expected, up_to_sign=True) <= VALUE_TOL[dtype]


def _batched_args(op: Op, batch: tuple[int, ...]) -> tuple[list[np.ndarray], list[int]]:
    """The op's float64 inputs at generic rotations of batch shape ``batch``, and the arguments that
    carry that batch shape (the others, such as a time step shared by the batch, are left out)."""
    xs = [np.asarray(x, np.float64) for x in op.inputs(uniform_quaternions(batch, seed=11))]
    return xs, [i for i, x in enumerate(xs) if x.shape[: len(batch)] == batch]


def _multi_argument(op: Op) -> bool:
    return len(_batched_args(op, (5, 3))[1]) > 1


@only(op=_multi_argument)
def test_arguments_broadcast_pairwise(op: Op, backend: Backend) -> None:
    """Every pair of batched arguments broadcasts as the conventions page promises: one of batch
    shape (5, 1) and the other (3,) (the rest (1, 1)) give the result at the arguments broadcast
    explicitly to (5, 3), to the last few bits (the same numbers, maybe summed in another order)."""
    xs, batched = _batched_args(op, (5, 3))
    apply: Any = lambda *args: op(backend.module, *args)  # noqa: E731
    if backend.name == "jax":
        # Jitted: the broadcasting is decided from the static shapes, which jit traces as eager jax
        # runs them, and eager jax compiles every primitive anew for each of the pairs' shapes (a
        # large op's ~150 compilations per call, against one program).
        import jax

        apply = jax.jit(apply)
    failures = []
    for i, j in itertools.combinations(batched, 2):
        # the others of batch shape (1, 1): the pair alone decides the result's batch shape
        args = [x[:1, :1] if k in batched else x for k, x in enumerate(xs)]
        args[i], args[j] = xs[i][:, :1], xs[j][0]
        explicit = [np.array(np.broadcast_to(x, xs[k].shape)) for k, x in enumerate(args)]
        try:
            out = backend.to_numpy(apply(*(backend.array(x, "float64") for x in args)))
        except Exception as error:  # the report names every pair that fails
            failures.append(f"arguments {i} (5, 1) and {j} (3,): {type(error).__name__}: {error}"[:300])
            continue
        expected = backend.to_numpy(apply(*(backend.array(x, "float64") for x in explicit)))
        if out.shape != expected.shape or not np.allclose(out, expected, rtol=1e-13, atol=1e-13):
            failures.append(f"arguments {i} and {j}: shape {out.shape}, expected {expected.shape}")
    assert not failures, "\n".join(failures)


@only(op=lambda op: bool(op.degenerate), dtype=lambda d: d in FULL_DTYPES)
def test_degenerate_inputs(op: Op, backend: Backend, dtype: str) -> None:
    """Each of the op's degenerate configurations (``Op.degenerate``: parallel and antiparallel
    vectors, collinear points, extreme scales, zero translation, ...) within its bound in ulps of a
    high-precision reference at the inputs as rounded to ``dtype``. One eager call for all of them
    (each configuration is a batch of rows along one axis; rows are independent)."""
    received = [
        [host_cast(x, HOST_DTYPES[dtype]).astype(np.float64) for x in config.make(dtype)]
        for config in op.degenerate
    ]
    together = [np.concatenate(xs) for xs in zip(*received, strict=True)]
    n = len(together[0])
    if backend.name == "jax":  # at conftest.JAX_ROWS rows, the other rows dropped
        together = pad_rows(together)
    out = backend.to_numpy(op(backend.module, *(backend.array(x, dtype) for x in together)))[:n]
    failures, start = [], 0
    for config, xs in zip(op.degenerate, received, strict=True):
        rows = slice(start, start + len(xs[0]))
        start = rows.stop
        error = config.error(xs, out[rows], dtype) if np.all(np.isfinite(out[rows])) else np.inf
        if not error <= config.ulps:
            failures.append(f"{config.name}: {error:.3g} ulp > {config.ulps}")
    assert not failures, "\n".join(failures)
