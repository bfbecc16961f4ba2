"""Gradients: correct (against finite differences), not merely finite, at every named case; torch's
gradcheck/gradgradcheck and jax's check_grads; and torch == jax. All in float64."""

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
    base_rows,
    edge_cases,
    gradients,
    jax_only,
    only,
    oracle_quaternion_to_matrix,
    outer,
    smooth,
    torch_only,
)
from conftest import BACKENDS, Backend, rows_by_case
from jax.test_util import check_grads

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


_PULLBACK: dict[Fn, Fn] = {}


def _jax_pullback(fn: Fn) -> Fn:
    """``(xs, cotangent) ->`` the pullback of ``cotangent`` through ``fn`` at ``xs``, jitted once per
    function."""
    if fn not in _PULLBACK:
        _PULLBACK[fn] = jax.jit(lambda xs, cot: jax.vjp(fn, *xs)[1](cot))
    return _PULLBACK[fn]


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


_BOTH: dict[tuple[Fn, int], Fn] = {}


def jacobians(backend: Backend, fn: Fn, xs: list[np.ndarray], batch: Batch) -> list[np.ndarray]:
    """:func:`reverse_jacobians` and then :func:`fd_jacobians` of every input; on jax from one compiled
    program (the pullbacks and the moved evaluations together: the programs compiled per op and shape
    are what the jax half of the finite-difference test costs)."""
    if backend.name == "torch":
        return [*reverse_jacobians(backend, fn, xs, batch), *fd_jacobians(backend, fn, xs, batch)]
    nb = len(batch)
    if (fn, nb) not in _BOTH:
        rows = _jax_reverse_rows(fn, nb)
        _BOTH[(fn, nb)] = jax.jit(lambda xs, moved: (rows(*xs), fn(*moved)))
    stacked, assemble = _perturbed(xs, batch)
    grads, values = _BOTH[(fn, nb)]([jnp.asarray(x) for x in xs], [jnp.asarray(m) for m in stacked])
    reverse = _stack_rows([list(np.asarray(g)) for g in grads], xs, batch)
    return [*reverse, *assemble(np.asarray(values))]


_JITTED: dict[str, Fn] = {}


def gradient_function(op: Op, backend: Backend) -> Fn:
    """The op's gradient function on ``backend``; on jax under ``jax.jit``, as users run it: one per
    op for the session, since jax caches a compiled program (and those of its ``vjp``) per function
    and input shape."""
    if backend.name == "torch":
        return op.gradient_function(backend.module)
    if op.id not in _JITTED:
        _JITTED[op.id] = jax.jit(op.gradient_function(backend.module))
    return _JITTED[op.id]


def by_case(
    test: str, op: Op, backend: Backend, case: Case, compute: Callable[[Fn, list[np.ndarray], Batch], Any]
) -> list[np.ndarray]:
    """``compute(fn, xs, batch)`` on the op's float64 gradient inputs at ``case``: from one call over
    every case the op applies to (``conftest.rows_by_case``: the op and its pullback compile for one
    shape, and the finite differences take one evaluation per input component for all cases, not one
    per case), the batch_* cases at their own shapes."""
    fn = gradient_function(op, backend)
    return rows_by_case(
        (test, op.id, backend.name),
        case,
        batch_shape,
        lambda c: list(op.gradient_inputs(c.quaternions("float64"))),
        lambda xs, batch: [*xs, *compute(fn, xs, batch)],
        applies=op.applies,
    )


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
    xs, ad, fd = arrays[:n], arrays[n : 2 * n], arrays[2 * n :]
    batch = batch_shape(case)
    assert all(np.all(np.isfinite(j)) for j in ad)
    if not op.smooth_at(case):
        return  # e.g. the zero quaternion: no derivative exists, finiteness is the promise
    for x, j_ad, j_fd in zip(xs, ad, fd, strict=True):
        norm = np.linalg.norm(x.reshape(*batch, j_ad.shape[-1]), axis=-1)[..., None, None]
        scale = np.where(norm > 0, norm, 1.0)
        tol = 1e-6 * np.maximum(np.abs(j_fd).max(axis=(-1, -2), keepdims=True), 1 / scale)
        assert np.all(np.abs(j_ad - j_fd) <= tol), float(np.max(np.abs(j_ad - j_fd) / tol))


def small(op: Op, case: Case) -> list[np.ndarray]:
    """At most 24 elements of a case (every 4th of a larger one), batch flattened to one dimension,
    to keep the numerical Jacobians of gradcheck and check_grads small. Every input of an op gets the
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


@jax_only
@gradients
@base_rows
def test_jax_check_grads(op: Op, backend: Backend, dtype: str) -> None:
    """``check_grads`` to second order, forward and reverse (the second order in
    ``op.second_order_modes``), at every edge case where the op is smooth, all in one batch (each
    element is checked on its own: the ops are row by row, and check_grads compares the directional
    derivatives element by element), of the op under ``jax.jit`` as users run it: each derivative
    program compiles once for the batch (eagerly, jax compiled each of their many operations one by
    one: 31 s against 17 s for four ops). A failure is traced back to the case it is in."""
    cases = [c for c in CASES if c.name in EDGE_CASES and op.applies(c) and op.smooth_at(c)]
    parts = [small(op, case) for case in cases]
    fn = jax.jit(op.gradient_function(backend.module))

    def check(xs: list[np.ndarray]) -> None:
        args = tuple(jnp.asarray(x) for x in xs)
        check_grads(fn, args, order=2, modes=op.second_order_modes, eps=1e-6)
        first_only = tuple(m for m in ("fwd", "rev") if m not in op.second_order_modes)
        if first_only:
            check_grads(fn, args, order=1, modes=first_only, eps=1e-6)

    try:
        check([np.concatenate(p) for p in zip(*parts, strict=True)])
    except AssertionError:
        for case, xs in zip(cases, parts, strict=True):
            try:
                check(xs)
            except AssertionError as error:
                raise AssertionError(f"case {case.name}: {error}") from None
        raise


@smooth
@edge_cases
@jax_only
@gradients
def test_torch_and_jax_gradients_agree(op: Op, backend: Backend, dtype: str, case: Case) -> None:
    """The same cotangent pulled back through jax and through torch gives the same gradient to 1e-10.

    Where the op is differentiable (``smooth``). At a kink, such as a distance at 0 or at pi, the
    gradient points along a vector that is pure rounding (the axis of a rotation by 1e-16), so two
    correct implementations legitimately differ there; that it is finite is tested at every case
    (test_gradient_matches_finite_differences, test_gradient_is_finite_in_every_dtype)."""
    fn_torch = gradient_function(op, BACKENDS["torch"])

    def pullbacks(fn_jax: Fn, xs: list[np.ndarray], batch: Batch) -> list[np.ndarray]:
        arrays = [jnp.asarray(x) for x in xs]
        cot = np.random.default_rng(0).normal(size=jax.eval_shape(fn_jax, *arrays).shape)
        # the pullback under jit: one program, where an eager vjp of the jitted function compiled its
        # linearisation and its transpose apart
        g_jax = [np.asarray(g) for g in _jax_pullback(fn_jax)(arrays, jnp.asarray(cot))]
        ts = [torch.tensor(x, requires_grad=True) for x in xs]
        g_torch = [g.numpy() for g in torch.autograd.grad(fn_torch(*ts), ts, torch.tensor(cot))]
        return [*g_torch, *g_jax]

    n = len(op.gradient_inputs(case.quaternions("float64")))
    grads = by_case("torch and jax", op, backend, case, pullbacks)[n:]
    for a, b in zip(grads[:n], grads[n:], strict=True):
        np.testing.assert_allclose(a, b, rtol=1e-10, atol=1e-10 * max(1.0, float(np.abs(b).max(initial=0))))


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
    xs = [backend.array(np.concatenate(parts), dtype) for parts in zip(*batches, strict=True)]
    fn = op.gradient_function(backend.module)
    if backend.name == "torch":
        leaves = [x.clone().requires_grad_(True) for x in xs]
        out = fn(*leaves)
        grads = [backend.to_numpy(g) for g in torch.autograd.grad(out, leaves, torch.ones_like(out))]
    else:
        out, pullback = jax.vjp(fn, *xs)
        grads = [backend.to_numpy(g) for g in pullback(jnp.ones_like(out))]
    if dtype == "float32":  # the dtype users train in; 16-bit inputs are computed in float32 too
        plain = backend.to_numpy(fn(*xs))
        if backend.name == "jax" and op.name in JAX_COMPILED:
            eps = float(np.finfo(np.float32).eps)
            np.testing.assert_allclose(backend.to_numpy(out), plain, rtol=8 * eps, atol=8 * eps)
        else:
            np.testing.assert_array_equal(backend.to_numpy(out), plain)
    finite = np.all([np.all(np.isfinite(g.reshape(len(g), -1)), axis=-1) for g in grads], axis=0)
    bad = {cases[i].name for i in np.searchsorted(np.cumsum(sizes), np.flatnonzero(~finite), side="right")}
    assert not bad, f"non-finite gradients in cases {sorted(bad)}"
