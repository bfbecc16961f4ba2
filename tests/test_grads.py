"""Gradients: correct (against finite differences), not merely finite, at every named case; torch's
gradcheck/gradgradcheck, jax's second order as check_grads checks it, jit/vmap/grad/jacfwd/jacrev on
jax; and torch == jax. All in float64; finite, and equal to the plain call's value, in every dtype."""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np
import pytest
import torch
from cases import (
    CASES,
    EDGE_CASES,
    GRAD_DTYPE,
    Case,
    Op,
    concatenate_cases,
    edge_cases,
    gradients,
    jax_only,
    only,
    oracle_quaternion_to_matrix,
    outer,
    smooth,
    torch_only,
)
from conftest import BACKENDS, Backend, pad_rows, rows_by_case
from jax.test_util import check_grads
from test_forward_mode import assert_rows_close, directions
from test_transforms import close_values

Fn = Callable[..., Any]


def batch_shape(case: Case) -> tuple[int, ...]:
    return case.quaternions("float64").shape[:-1]


Batch = tuple[int, ...]


_REVERSE: dict[tuple[Fn, int], Fn] = {}


def _jax_reverse_rows(fn: Fn, nb: int) -> Fn:
    """``xs -> `` the pullbacks of every one-hot cotangent (one per output component, in every batch
    element at once), as one compiled program per function and batch rank: ``vmap`` of the pullback,
    where a pullback called eagerly per component compiled a transposed program beside the
    linearised one."""
    if (fn, nb) not in _REVERSE:

        def rows(*xs: Any) -> Any:
            out, pullback = jax.vjp(fn, *xs)
            n_out = int(np.prod(out.shape[nb:]))
            one_hot = jnp.eye(n_out, dtype=out.dtype).reshape(n_out, *([1] * nb), *out.shape[nb:])
            return jax.vmap(pullback)(jnp.broadcast_to(one_hot, (n_out, *out.shape)))

        _REVERSE[(fn, nb)] = jax.jit(rows)
    return _REVERSE[(fn, nb)]


def reverse_jacobians(backend: Backend, fn: Fn, xs: list[np.ndarray], batch: Batch) -> list[np.ndarray]:
    """Per batch element, the Jacobian of ``fn``'s output w.r.t. each input, by reverse mode: one
    backward pass per output component, cotangent one-hot in that component for every element.
    Returns, per input, shape ``(*batch, n_out, n_in)``."""
    nb = len(batch)
    if backend.name == "torch":
        ts = [torch.tensor(x, requires_grad=True) for x in xs]
        out = fn(*ts)
        flat = out.reshape(*batch, int(np.prod(out.shape[nb:])))
        rows = [torch.autograd.grad(flat[..., o].sum(), ts, retain_graph=True) for o in range(flat.shape[-1])]
        per_input = [[r[i].detach().numpy() for r in rows] for i in range(len(xs))]
    else:
        grads = _jax_reverse_rows(fn, nb)(*[jnp.asarray(x) for x in xs])
        per_input = [list(np.asarray(g)) for g in grads]
    return _stack_rows(per_input, xs, batch)


def _stack_rows(per_input: list[list[np.ndarray]], xs: list[np.ndarray], batch: Batch) -> list[np.ndarray]:
    """Per input, its gradients for each one-hot cotangent -> Jacobians ``(*batch, n_out, n_in)``."""
    n_in = [int(np.prod(x.shape[len(batch) :])) for x in xs]
    return [
        np.stack([g.reshape(*batch, n) for g in rows_i], axis=-2)
        for rows_i, n in zip(per_input, n_in, strict=True)
    ]


def _perturbed(
    xs: list[np.ndarray], batch: Batch
) -> tuple[list[np.ndarray], Callable[[np.ndarray], list[np.ndarray]]]:
    """Central finite differences, laid out for one call: every input moved by +h and -h along each of
    its components, stacked on a new leading axis (the ops are batched over any leading dimensions), and
    the function that turns the outputs of that call, ``(P, *batch, *out)``, into the Jacobians."""
    nb = len(batch)
    moved: list[list[np.ndarray]] = [[] for _ in xs]
    steps = []
    for i, x in enumerate(xs):
        flat = x.reshape(*batch, int(np.prod(x.shape[nb:])))
        # Relative to the input's norm (scale-invariant ops see 1e-20 ... 1e20), absolute where the input
        # is exactly zero (a zero rotation vector or Euler angles are ordinary, smooth inputs).
        norm = np.linalg.norm(flat, axis=-1)
        h = 1e-6 * np.where(norm > 0, norm, 1.0)
        steps.append((flat.shape[-1], h))
        for j in range(flat.shape[-1]):
            step = np.zeros_like(flat)
            step[..., j] = h
            for sign in (1.0, -1.0):
                for k, other in enumerate(xs):
                    moved[k].append((flat + sign * step).reshape(x.shape) if k == i else other)

    def assemble(values: np.ndarray) -> list[np.ndarray]:
        out, p = [], 0
        n_out = int(np.prod(values.shape[1 + nb :]))
        for n_in, h in steps:
            cols = []
            for _ in range(n_in):
                plus, minus = values[p].reshape(*batch, n_out), values[p + 1].reshape(*batch, n_out)
                cols.append((plus - minus) / (2 * h[..., None]))
                p += 2
            out.append(np.stack(cols, axis=-1))
        return out

    return [np.stack(m) for m in moved], assemble


def fd_jacobians(backend: Backend, fn: Fn, xs: list[np.ndarray], batch: Batch) -> list[np.ndarray]:
    """The same Jacobians by central finite differences, the step scaled to each element's input, all
    the moved inputs evaluated in one call."""
    stacked, assemble = _perturbed(xs, batch)
    return assemble(backend.to_numpy(fn(*(backend.array(m, "float64") for m in stacked))))


def jacobians(backend: Backend, fn: Fn, xs: list[np.ndarray], batch: Batch) -> list[np.ndarray]:
    """:func:`reverse_jacobians` and then :func:`fd_jacobians` of every input."""
    return [*reverse_jacobians(backend, fn, xs, batch), *fd_jacobians(backend, fn, xs, batch)]


def by_case(
    test: str, op: Op, backend: Backend, case: Case, compute: Callable[[Fn, list[np.ndarray], Batch], Any]
) -> list[np.ndarray]:
    """``compute(fn, xs, batch)`` on the op's float64 gradient inputs at ``case``: from one call over
    every case the op applies to (``conftest.rows_by_case``: the op and its pullback compile for one
    shape, and the finite differences take one evaluation per input component for all cases, not one
    per case), the batch_* cases at their own shapes. (jax: ``test_jax_derivatives``.)"""
    fn = op.gradient_function(backend.module)
    return rows_by_case(
        (test, op.id, backend.name),
        case,
        batch_shape,
        lambda c: list(op.gradient_inputs(c.quaternions("float64"))),
        lambda xs, batch: [*xs, *compute(fn, xs, batch)],
        applies=op.applies,
    )


@torch_only
@gradients
def test_gradient_matches_finite_differences(op: Op, backend: Backend, dtype: str, case: Case) -> None:
    n = len(op.gradient_inputs(case.quaternions("float64")))
    arrays = by_case(
        "finite differences",
        op,
        backend,
        case,
        lambda fn, xs, batch: jacobians(backend, fn, xs, batch),
    )
    _assert_jacobians_match(op, case, arrays[:n], arrays[n : 2 * n], arrays[2 * n :], batch_shape(case))


def small(op: Op, case: Case) -> list[np.ndarray]:
    """At most 24 elements of a case (every 4th of a larger one), batch flattened to one dimension,
    to keep the numerical Jacobians of gradcheck small. Every input of an op gets the
    same."""
    xs, batch = op.gradient_inputs(case.quaternions("float64")), batch_shape(case)
    flat = [x.reshape(-1, *x.shape[len(batch) :]) for x in xs]
    return [x if len(x) <= 24 else x[::4][:24] for x in flat]


@smooth
@edge_cases
@torch_only
@gradients
def test_torch_gradcheck_and_gradgradcheck(op: Op, backend: Backend, dtype: str, case: Case) -> None:
    fn = op.gradient_function(backend.module)
    ts = tuple(torch.tensor(x, requires_grad=True) for x in small(op, case))
    # Fast mode: u^T J v against its central difference for random u and v, where the slow mode builds
    # the whole numerical Jacobian (216 columns for 24 matrices), and its transpose for the second order;
    # a wrong entry moves u^T J v unless the error is orthogonal to a random vector (probability 0).
    # The whole Jacobian of every element is compared with finite differences above.
    assert torch.autograd.gradcheck(fn, ts, eps=1e-6, atol=1e-6, rtol=1e-5, fast_mode=True)
    assert torch.autograd.gradgradcheck(fn, ts, eps=1e-6, atol=1e-5, rtol=1e-4, fast_mode=True)


# ---------------------------------------------------------------------------------------------------
# jax: every derivative check of an op from one compiled program


SECOND_ORDER_TOL = 1e-5  # jax's check_grads tolerance for float64, with its step, 1e-6 (relative here)


def _rowwise(a: Any, n: int) -> np.ndarray:
    return np.asarray(a).reshape(n, -1)


def _row_sums(pairs: list[tuple[Any, Any]], n: int) -> np.ndarray:
    """Per row, the sum over the pairs of the inner product of their entries."""
    return sum((_rowwise(a, n) * _rowwise(b, n)).sum(-1) for a, b in pairs)  # type: ignore[return-value]


def _jax_program(op: Op, second_order: bool, ranks: list[int], apart: bool) -> Fn:
    """One jitted program with everything the jax derivative checks of ``op`` compare: per group of
    inputs (every case but the batch_* ones concatenated on one batch axis, then each batch_* case at
    its own shape), the reverse-mode Jacobians and the function at the inputs moved for central
    differences; for the concatenated group ``vmap(jacrev)``, and, on the table's base rows, what users
    compile: ``jit`` and ``vmap`` of the op, ``grad`` of a scalar loss, ``vmap(jacfwd)``, and the second
    order that jax's ``check_grads`` checks (``jvp`` of ``jvp``, ``vjp`` of ``vjp``, in the op's
    ``second_order_modes``) beside the first-order derivatives at inputs moved along a direction.

    ``apart``: each of those steps as a program of its own, run one after another. For the ops whose
    derivatives call LAPACK (eigh, SVD, LU): jaxlib 0.10's LAPACK kernels split a large batch over
    XLA's CPU thread pool and block a pool thread until the pieces finish, so a program that runs as
    many of them at once as the pool has threads deadlocks, every thread waiting (the one program of
    symmetric_matrix_to_quaternion hung in half of the runs on two cores; jaxlib 0.11 compiles that
    path out)."""
    fn = op.gradient_function(BACKENDS["jax"].module)

    def program(flat: Any, groups: Any, extra: Any, step: Callable[..., Any]) -> dict[str, Any]:
        argnums = tuple(range(len(flat["xs"])))
        out: dict[str, Any] = {
            "jacrev": step(jax.vmap(jax.jacrev(fn, argnums)), *flat["xs"]),
            "moved": step(fn, *flat["moved"]),
            "groups": [
                (step(_jax_reverse_rows(fn, nb), *g["xs"]), step(fn, *g["moved"]))
                for g, nb in zip(groups, ranks, strict=True)
            ],
        }
        if not second_order:
            return out
        xs, t1, t2 = flat["xs"], extra["t1"], extra["t2"]
        out["value"] = step(fn, *xs)
        out["vmap"] = step(jax.vmap(fn), *xs)

        def loss(*xs: Any) -> Any:
            value = fn(*xs)
            return (extra["weights"] * value.reshape(len(xs[0]), -1).sum(-1) ** 2).sum(), value

        # the value the gradient's own forward computed beside it (has_aux): the cotangent is built
        # from it, and a compiler may round it otherwise in a program of its own
        out["grad"], out["grad_value"] = step(jax.grad(loss, argnums, has_aux=True), *xs)
        out["jacfwd"] = step(jax.vmap(jax.jacfwd(fn, argnums)), *xs)
        # x +- h t2 for every row, stacked on a leading axis (the ops are batched over leading axes)
        moved = [jnp.stack([x + extra["h"] * t, x - extra["h"] * t]) for x, t in zip(xs, t2, strict=True)]
        if "fwd" in op.second_order_modes:

            def tangent(xs: Any, ts: Any) -> Any:
                return jax.jvp(fn, tuple(xs), tuple(ts))[1]

            out["jvp_jvp"] = step(lambda *xs: jax.jvp(lambda *xs: tangent(xs, t1), xs, tuple(t2))[1], *xs)
            out["jvp_moved"] = step(lambda *m: tangent(m, [jnp.stack([t, t]) for t in t1]), *moved)
        if "rev" in op.second_order_modes:

            def pullback(xs: Any, w: Any) -> Any:
                return jax.vjp(fn, *xs)[1](w)

            out["vjp_vjp"] = step(
                lambda *xs: jax.vjp(lambda *xs: pullback(xs, extra["w"]), *xs)[1](tuple(extra["v"])), *xs
            )
            out["vjp_moved"] = step(lambda *m: pullback(m, jnp.stack([extra["w"], extra["w"]])), *moved)
        return out

    if not apart:
        return jax.jit(lambda flat, groups, extra: program(flat, groups, extra, lambda f, *xs: f(*xs)))

    def run(flat: Any, groups: Any, extra: Any) -> dict[str, Any]:
        return program(flat, groups, extra, lambda f, *xs: jax.block_until_ready(jax.jit(f)(*xs)))

    return run


def _cases_of(bad: np.ndarray, parts: list[tuple[Case, slice, Batch]]) -> list[str]:
    return [case.name for case, rows, _ in parts if np.any(bad[rows])]


def _assert_jacobians_match(
    op: Op, case: Case, xs: list[np.ndarray], ad: list[np.ndarray], fd: list[np.ndarray], batch: Batch
) -> None:
    """Reverse-mode Jacobians ``(*batch, n_out, n_in)`` finite at ``case``, and where the op is smooth
    there equal to central differences to 1e-6 of the largest entry (or of 1/|x|, for a Jacobian that
    is zero at a scale-invariant op)."""
    assert all(np.all(np.isfinite(j)) for j in ad), f"case {case.name}: non-finite derivative"
    if not op.smooth_at(case):
        return  # e.g. the zero quaternion: no derivative exists, finiteness is the promise
    for x, j_ad, j_fd in zip(xs, ad, fd, strict=True):
        norm = np.linalg.norm(x.reshape(*batch, j_ad.shape[-1]), axis=-1)[..., None, None]
        scale = np.where(norm > 0, norm, 1.0)
        tol = 1e-6 * np.maximum(np.abs(j_fd).max(axis=(-1, -2), keepdims=True), 1 / scale)
        err = np.abs(j_ad - j_fd)
        assert np.all(err <= tol), f"case {case.name}: error / tolerance {float(np.max(err / tol))}"


@jax_only
@gradients
def test_jax_derivatives(op: Op, backend: Backend, dtype: str) -> None:
    """Every derivative check of an op on jax, from one program compiled for it (``_jax_program``: what
    the checks cost is compiling, and one program of all of them compiles in less than a third of the
    time the programs of each check took apart):

    - at every case, the reverse-mode Jacobian of each batch element finite, and where the op is smooth
      equal to central differences; the batch_* cases at their own shapes;
    - on the base rows (``Op.variant_of``), at the edge cases: ``jit`` and ``vmap`` equal to eager,
      ``vmap(jacfwd)`` equal to ``vmap(jacrev)`` (the adjoint identity, element by element), ``grad`` of
      a scalar loss equal to the Jacobians' contraction, the second order as jax's ``check_grads``
      checks it (``jvp`` of ``jvp`` against central differences of ``jvp``; ``<v, d(J^T w)[t]>`` by
      central differences against ``<t, vjp of vjp>``), and torch's pullback of a random cotangent
      equal to jax's."""
    fn = op.gradient_function(backend.module)
    base = not op.variant_of

    def inputs(case: Case) -> list[np.ndarray]:
        return list(op.gradient_inputs(case.quaternions("float64")))

    flat_cases = [c for c in CASES if not c.name.startswith("batch_") and op.applies(c)]
    xs, parts = concatenate_cases(flat_cases, batch_shape, inputs)
    n = len(xs[0])
    moved, assemble = _perturbed(xs, (n,))
    groups = [(c, inputs(c), batch_shape(c)) for c in CASES if c.name.startswith("batch_") and op.applies(c)]
    group_moved = [_perturbed(gx, b) for _, gx, b in groups]
    t1, t2 = directions(xs, seed=1), directions(xs, seed=2)
    rng = np.random.default_rng(3)
    out_shape = jax.eval_shape(fn, *map(jnp.asarray, xs)).shape
    extra = {
        "t1": t1,
        "t2": t2,
        "h": 1e-6,
        "w": rng.normal(size=out_shape),
        "v": [rng.normal(size=x.shape) for x in xs],
        "weights": rng.normal(size=n),
    }
    lapack = "lapack" in jax.jit(jax.vmap(jax.jacrev(fn, tuple(range(len(xs)))))).lower(*xs).as_text()
    program = _jax_program(op, base, [len(b) for _, _, b in groups], apart=lapack)
    got = program(
        {"xs": xs, "moved": moved},
        [{"xs": gx, "moved": m} for (_, gx, _), (m, _) in zip(groups, group_moved, strict=True)],
        extra,
    )
    got = jax.tree.map(np.asarray, got)

    # first order, reverse mode, against central differences at every case
    n_out = int(np.prod(out_shape[1:]))
    rev = [j.reshape(n, n_out, -1) for j in got["jacrev"]]
    fd = assemble(got["moved"])
    for case, rows, _ in parts:
        _assert_jacobians_match(
            op,
            case,
            [x[rows] for x in xs],
            [j[rows] for j in rev],
            [j[rows] for j in fd],
            (len(xs[0][rows]),),
        )
    group_rev = []
    for (case, gx, batch), (_, g_assemble), (g_rows, g_moved) in zip(
        groups, group_moved, got["groups"], strict=True
    ):
        group_rev.append(_stack_rows([list(r) for r in g_rows], gx, batch))
        _assert_jacobians_match(op, case, gx, group_rev[-1], g_assemble(g_moved), batch)
    # torch's pullback of a random cotangent equals jax's, at the edge cases where the op is smooth (at a
    # kink the gradient follows a rounding error's direction, which two correct implementations may
    # take differently; it is finite everywhere, above)
    fn_torch = op.gradient_function(BACKENDS["torch"].module)
    rng = np.random.default_rng(4)
    for case, gx, batch, jac in [
        *((c, [x[rows] for x in xs], b, [j[rows] for j in rev]) for c, rows, b in parts),
        *((c, gx, b, g) for (c, gx, b), g in zip(groups, group_rev, strict=True)),
    ]:
        if case.name not in EDGE_CASES or not op.smooth_at(case):
            continue
        cot = rng.normal(size=(*batch, jac[0].shape[-2]))
        ts = [torch.tensor(x, requires_grad=True) for x in gx]
        out = fn_torch(*ts)
        g_torch = torch.autograd.grad(out, ts, torch.tensor(cot.reshape(out.shape)))
        for a, j in zip(g_torch, jac, strict=True):
            b = np.einsum("...oi,...o->...i", j, cot).reshape(a.shape)
            np.testing.assert_allclose(
                a.numpy(), b, rtol=1e-10, atol=1e-10 * max(1.0, float(np.abs(b).max(initial=0)))
            )
    if not base:
        return

    # the base row: transforms and the second order at the edge cases where the op is smooth
    edge = np.zeros(n, bool)
    smooth = np.zeros(n, bool)
    for case, rows, _ in parts:
        edge[rows] = case.name in EDGE_CASES
        smooth[rows] = case.name in EDGE_CASES and op.smooth_at(case)
    eager = np.asarray(fn(*map(jnp.asarray, xs)))
    close_values(op, got["value"][edge], eager[edge], smooth[edge])
    close_values(op, got["vmap"][edge], eager[edge], smooth[edge])
    fwd = [j.reshape(n, n_out, -1) for j in got["jacfwd"]]
    for a, b in zip(fwd, rev, strict=True):
        assert np.all(np.isfinite(a[edge])), _cases_of(~np.isfinite(a).reshape(n, -1).all(-1) & edge, parts)
        assert_rows_close(a, b, 1e-10, smooth)
    # grad of sum_n weights_n (sum_o f_no)^2: J^T (2 weights_n S_n) per row, with S from the value the
    # gradient's forward computed (where an op is ill-conditioned, as the IGSO(3) score just short of
    # pi, two compiled evaluations differ by its conditioning, and this check is of the pullback, not
    # the value)
    s = got["grad_value"].reshape(n, -1).sum(-1)
    for g, j in zip(got["grad"], rev, strict=True):
        want = np.einsum("noi,n->ni", j, 2 * extra["weights"] * s)
        assert np.all(np.isfinite(g[edge]))
        assert_rows_close(g, want, 1e-10, smooth)
    h = extra["h"]
    if "fwd" in op.second_order_modes:
        central = (got["jvp_moved"][0] - got["jvp_moved"][1]) / (2 * h)
        assert np.all(np.isfinite(_rowwise(got["jvp_jvp"], n)[smooth]))
        assert_rows_close(got["jvp_jvp"], central, SECOND_ORDER_TOL, smooth)
    if "rev" in op.second_order_modes:
        central = [(g[0] - g[1]) / (2 * h) for g in got["vjp_moved"]]
        lhs = _row_sums(list(zip(extra["v"], central, strict=True)), n)
        rhs = _row_sums(list(zip(t2, got["vjp_vjp"], strict=True)), n)
        scale = np.maximum(
            1.0, _row_sums([(np.abs(v), np.abs(c)) for v, c in zip(extra["v"], central, strict=True)], n)
        )
        assert np.all(np.isfinite(rhs[smooth]))
        bad = smooth & ~(np.abs(lhs - rhs) <= SECOND_ORDER_TOL * scale)
        assert not bad.any(), f"second order (vjp of vjp) off in cases {_cases_of(bad, parts)}"


def perturbed_rotations(n: int, seed: int) -> np.ndarray:
    rng = np.random.default_rng(seed)
    q = rng.normal(size=(n, 4))
    return oracle_quaternion_to_matrix(q) + 1e-2 * rng.normal(size=(n, 3, 3))


@pytest.mark.parametrize("name", ["torch", "jax"])
def test_matrix_to_quaternion_gradient_off_rotation_matrices(name: str) -> None:
    """Full 9-dimensional directions, not only along SO(3): matrices perturbed by 1e-2, as a network
    would produce them. Checked through outer(q) since the sign of q is canonicalised."""
    backend = BACKENDS[name]
    matrices = perturbed_rotations(16, seed=9)

    def fn(m: Any) -> Any:
        return outer(backend.module.matrix_to_quaternion(m))

    ad = reverse_jacobians(backend, fn, [matrices], (16,))[0]
    fd = fd_jacobians(backend, fn, [matrices], (16,))[0]
    np.testing.assert_allclose(ad, fd, atol=1e-7)
    if name == "torch":
        assert torch.autograd.gradcheck(fn, (torch.tensor(matrices, requires_grad=True),))
        assert torch.autograd.gradgradcheck(fn, (torch.tensor(matrices, requires_grad=True),))
    else:
        check_grads(fn, (jnp.asarray(matrices),), order=2, modes=("fwd", "rev"), eps=1e-6)


@pytest.mark.parametrize("name", ["torch", "jax"])
def test_matrix_to_quaternion_scalar_last_gradient(name: str) -> None:
    """jax builds the scalar-last conversion with a derivative rule of its own (in that order; see
    diffquat.jax): its pullback of a cotangent is the scalar-first pullback of the same cotangent
    reordered, on every backend, and jax's rule is right to second order in both modes."""
    backend = BACKENDS[name]
    matrices = perturbed_rotations(16, seed=10)
    cot = np.random.default_rng(1).normal(size=(16, 4))  # (x, y, z, w)

    def pullback(scalar_first: bool, g: np.ndarray) -> np.ndarray:
        def fn(m: Any) -> Any:
            return backend.module.matrix_to_quaternion(m, scalar_first=scalar_first)

        if name == "torch":
            m = torch.tensor(matrices, requires_grad=True)
            return torch.autograd.grad(fn(m), m, torch.tensor(g))[0].numpy()
        return np.asarray(jax.vjp(fn, jnp.asarray(matrices))[1](jnp.asarray(g))[0])

    reordered = cot[:, [3, 0, 1, 2]]  # (w, x, y, z)
    np.testing.assert_allclose(pullback(False, cot), pullback(True, reordered), rtol=1e-12, atol=1e-12)
    if name == "jax":
        check_grads(
            lambda m: backend.module.matrix_to_quaternion(m, scalar_first=False),
            (jnp.asarray(matrices),),
            order=2,
            modes=("fwd", "rev"),
            eps=1e-6,
        )


# The jax functions compiled as one program inside diffquat.jax (its ``_compiled``: the SVD, eigh and
# iterative maps, whose many small operations jax would otherwise compile one by one).
JAX_COMPILED = {
    "special_procrustes",
    "rotation_6d_to_matrix",
    "symmetric_matrix_to_quaternion",
    "fit_rotation",
    "matrix_fisher_log_normalizer",
    "matrix_fisher_nll",
    "matrix_fisher_mode",
    "bingham_nll",
    "rotation_mean",
    "quaternion_mean",
    "symmetric_geodesic_distance",
}


@only(backend=lambda b: b in ("torch", "jax"), dtype=lambda d: d != GRAD_DTYPE)
def test_gradient_is_finite_in_every_dtype(op: Op, backend: Backend, dtype: str) -> None:
    """The float64 checks above prove gradients right, and finite at every case (the finite-difference
    test asserts it before comparing); this proves them finite where users train, in float32 and half
    precision: at norms near the ends of the dtype's range the intermediate derivatives of a careless
    formula overflow (d(1/n2)/dn2 = -1/n2^2 does at |q| ~ 1e-10 in float32). Every case the op applies
    to, in one batch (one compilation per op and dtype for jax).

    And in float32 the differentiated call returns, bit for bit, the value of a plain call (NaN rows
    included):
    one formula computes both, whatever derivative rule is registered beside it. Except where the jax
    backend compiles the whole map as one XLA program (``JAX_COMPILED``): XLA compiles the primal of a
    differentiated program anew, and its float32 rounding may differ by a few ulps there."""
    cases = [c for c in CASES if op.applies(c) and op.finite_gradient(c, dtype) and c.quaternions(dtype).size]
    sizes, batches = [], []
    for case in cases:
        batch = case.quaternions(dtype).shape[:-1]
        sizes.append(int(np.prod(batch)))
        # each input flattened to (elements, *trailing), so that the cases concatenate
        batches.append(
            [
                x.reshape(sizes[-1], *x.shape[len(batch) :])
                for x in op.gradient_inputs(case.quaternions(dtype))
            ]
        )
    columns = [np.concatenate(parts) for parts in zip(*batches, strict=True)]
    n = len(columns[0])
    if backend.name == "jax":  # at conftest.JAX_ROWS rows, as every dtype's and op's eager call
        columns = pad_rows(columns)
    xs = [backend.array(x, dtype) for x in columns]
    fn = op.gradient_function(backend.module)
    if backend.name == "torch":
        leaves = [x.clone().requires_grad_(True) for x in xs]
        out = fn(*leaves)
        grads = [backend.to_numpy(g) for g in torch.autograd.grad(out, leaves, torch.ones_like(out))]
    else:
        out, pullback = jax.vjp(fn, *xs)
        grads = [backend.to_numpy(g)[:n] for g in pullback(jnp.ones_like(out))]
    if dtype == "float32":  # the dtype users train in; 16-bit inputs are computed in float32 too
        plain = backend.to_numpy(fn(*xs))[:n]
        if backend.name == "jax" and op.name in JAX_COMPILED:
            eps = float(np.finfo(np.float32).eps)
            np.testing.assert_allclose(backend.to_numpy(out)[:n], plain, rtol=8 * eps, atol=8 * eps)
        else:
            np.testing.assert_array_equal(backend.to_numpy(out)[:n], plain)
    finite = np.all([np.all(np.isfinite(g.reshape(len(g), -1)), axis=-1) for g in grads], axis=0)
    bad = {cases[i].name for i in np.searchsorted(np.cumsum(sizes), np.flatnonzero(~finite), side="right")}
    assert not bad, f"non-finite gradients in cases {sorted(bad)}"
