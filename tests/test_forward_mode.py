"""Forward mode, for every op of the table at every named edge case, and for every rotation head.

``torch.func.jvp`` / ``jacfwd`` (eager and under ``torch.compile(fullgraph=True)``), torch's dual tensors
(``torch.autograd.forward_ad``) and ``jax.jvp`` / ``jax.jacfwd``, against reverse mode (the adjoint
identity ``<J t, w> = <t, J^T w>`` and the full Jacobians) and against central finite differences.
float64. All edge cases of one op run as one batch, so that each op compiles once.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np
import pytest
import torch
import torch.autograd.forward_ad as fwAD
from cases import CASES_BY_NAME, EDGE_CASES, Op, base_rows, gradients, torch_only
from conftest import Backend

import diffquat.jax.nn as jnn
import diffquat.torch.nn as tnn

pytestmark = [
    # torch.func.jvp's first call registers torch's own forward-mode decompositions with torch.jit.script
    pytest.mark.filterwarnings("ignore:`torch.jit.script` is deprecated:DeprecationWarning"),
    # inductor's lowering of aten.diagonal (in the forward-mode graphs of the SVD and eigh maps) calls
    # a deprecated helper of torch's own
    pytest.mark.filterwarnings("ignore:`torch._prims_common.check` is deprecated:FutureWarning"),
]

FD_STEP = 1e-6

# The compiled checks run Dynamo and AOTAutograd (``aot_eager``), where it is decided which rule a
# derivative takes (a Function's own, or autodiff of its operations) and where torch's forward-mode
# failures arise; inductor's code generation of these graphs (the SVD maps' second derivatives are
# thousands of nodes) took minutes per op and changes no rule. tests/test_transforms.py runs the ops
# through inductor, forward and backward.
COMPILE_BACKEND = "aot_eager"


def edge_batch(op: Op) -> tuple[list[np.ndarray], np.ndarray, list[int]]:
    """Every edge case the op applies to, flattened and concatenated into one batch: the inputs
    ``(N, *trailing)``, which rows are at a case where the op is smooth, and the row of the first
    element of each case (the sample for the dense Jacobians of compiled jacfwd)."""
    parts, smooth, firsts = [], [], []
    for case in (CASES_BY_NAME[name] for name in EDGE_CASES):
        if not op.applies(case):
            continue
        q = case.quaternions("float64")
        batch = q.shape[:-1]
        n = int(np.prod(batch))
        firsts.append(sum(len(s) for s in smooth))
        parts.append([x.reshape(n, *x.shape[len(batch) :]) for x in op.gradient_inputs(q)])
        smooth.append(np.full(n, op.smooth_at(case)))
    xs = [np.concatenate(p) for p in zip(*parts, strict=True)]
    return xs, np.concatenate(smooth), firsts


def directions(xs: list[np.ndarray], seed: int) -> list[np.ndarray]:
    """Random tangents, each element's scaled to its input's norm (the ops see 1e-8 ... 1e1 inputs
    and some are scale-invariant), 1 where the input is zero."""
    rng = np.random.default_rng(seed)
    out = []
    for x in xs:
        norm = np.linalg.norm(x.reshape(len(x), -1), axis=-1)
        scale = np.where(norm > 0, norm, 1.0).reshape(-1, *([1] * (x.ndim - 1)))
        out.append(rng.normal(size=x.shape) * scale)
    return out


def rows(a: Any) -> np.ndarray:
    """(N, ...) -> (N, everything else), float64 numpy."""
    a = a.detach().numpy() if isinstance(a, torch.Tensor) else np.asarray(a)
    return a.reshape(len(a), -1)


def assert_rows_close(got: Any, want: Any, rtol: float, where: np.ndarray | None = None) -> None:
    """Per row, ``|got - want| <= rtol * max(1, max |want|)``, on the rows ``where`` (default all)."""
    got, want = rows(got), rows(want)
    if where is not None:
        got, want = got[where], want[where]
    tol = rtol * np.maximum(1.0, np.abs(want).max(axis=-1, keepdims=True, initial=0.0))
    err = np.abs(got - want)
    assert np.all(err <= tol), f"max error / tolerance: {float(np.max(err / tol))}"


def check_tangent(
    tangent: Any,
    evaluate: Callable[[list[np.ndarray]], np.ndarray],
    pullback: Callable[[np.ndarray], list[np.ndarray]],
    xs: list[np.ndarray],
    ts: list[np.ndarray],
    smooth: np.ndarray,
    w: np.ndarray | None = None,
) -> None:
    """``tangent`` = J t: finite everywhere; where smooth, equal to central differences along t and
    adjoint to reverse mode: ``<J t, w>_row = sum_i <t_i, (J^T w)_i>_row`` for a random w (or the
    ``w`` given, which ``pullback`` may have pulled back already)."""
    dy = rows(tangent)
    assert np.all(np.isfinite(dy))
    plus = evaluate([x + FD_STEP * t for x, t in zip(xs, ts, strict=True)])
    minus = evaluate([x - FD_STEP * t for x, t in zip(xs, ts, strict=True)])
    # central differences: error O(h^2 f''') plus rounding O(eps / h), both ~1e-10 here
    assert_rows_close(dy, rows(plus - minus) / (2 * FD_STEP), 1e-6, smooth)
    if w is None:
        w = np.random.default_rng(7).normal(size=np.shape(tangent))
    forward = np.sum(dy * rows(w), axis=-1)
    reverse = sum(np.sum(rows(g) * rows(t), axis=-1) for g, t in zip(pullback(w), ts, strict=True))
    assert_rows_close(forward[:, None], np.asarray(reverse)[:, None], 1e-10, smooth)


# ---------------------------------------------------------------------------------------------------
# torch


@torch_only
@gradients
def test_torch_forward_mode_matches_reverse_mode_and_finite_differences(
    op: Op, backend: Backend, dtype: str
) -> None:
    """``torch.func.jvp``, dual tensors and ``vmap(jacfwd)`` in eager mode."""
    fn = op.gradient_function(backend.module)
    xs, smooth, _ = edge_batch(op)
    ts = directions(xs, seed=1)
    tx, tt = tuple(map(torch.tensor, xs)), tuple(map(torch.tensor, ts))
    _, tangent = torch.func.jvp(fn, tx, tt)

    def evaluate(moved: list[np.ndarray]) -> np.ndarray:
        return fn(*map(torch.tensor, moved)).numpy()

    def pullback(w: np.ndarray) -> list[np.ndarray]:
        return [g.numpy() for g in torch.func.vjp(fn, *tx)[1](torch.tensor(w))]

    check_tangent(tangent, evaluate, pullback, xs, ts, smooth)
    with fwAD.dual_level():
        dual = fwAD.unpack_dual(fn(*(fwAD.make_dual(x, t) for x, t in zip(tx, tt, strict=True)))).tangent
    assert dual is not None
    assert_rows_close(dual, tangent, 1e-12)
    # per-element Jacobians, forward against reverse
    argnums = tuple(range(len(tx)))
    fwd = torch.func.vmap(torch.func.jacfwd(fn, argnums=argnums))(*tx)
    rev = torch.func.vmap(torch.func.jacrev(fn, argnums=argnums))(*tx)
    for a, b in zip(fwd, rev, strict=True):
        assert bool(torch.all(torch.isfinite(a)))
        assert_rows_close(a, b, 1e-10, smooth)


def basis_tangents(xs: tuple[torch.Tensor, ...]) -> tuple[torch.Tensor, ...]:
    """For each input component j (of all inputs together, K of them), the tangent that is 1 at that
    component in every row and 0 elsewhere: (K, *x.shape) per input. The rows being independent,
    ``jvp`` along the k-th is the k-th column of every row's own Jacobian."""
    sizes = [x[0].numel() for x in xs]
    out = []
    for i, x in enumerate(xs):
        basis = torch.zeros(sum(sizes), len(x), sizes[i], dtype=x.dtype)
        basis[sum(sizes[:i]) + torch.arange(sizes[i]), :, torch.arange(sizes[i])] = 1
        out.append(basis.reshape(sum(sizes), *x.shape))
    return tuple(out)


@torch_only
@gradients
@base_rows
def test_torch_compiled_forward_mode_equals_eager(op: Op, backend: Backend, dtype: str) -> None:
    """Under ``torch.compile(fullgraph=True)``: ``vmap`` over ``jvp`` along each input component at
    once, so every row's whole Jacobian in forward mode (forward-mode rules and the batching rules
    over them) at all the edge cases, in one compiled function, equal to eager ``vmap(jacfwd)`` (which
    the first test proves right), and its contraction with a random tangent equal to eager ``jvp``.

    (One transform, not ``jvp`` and ``jacfwd`` compiled apart: those took twice as long to trace, and
    ``vmap(jacfwd)`` fails to compile in torch 2.13 even for ``sin``, pytorch/pytorch#160508.)"""
    fn = op.gradient_function(backend.module)
    xs, smooth, _ = edge_batch(op)
    tx = tuple(map(torch.tensor, xs))
    ts = directions(xs, seed=1)
    basis = basis_tangents(tx)

    def columns(xs: tuple[torch.Tensor, ...], basis: tuple[torch.Tensor, ...]) -> torch.Tensor:
        return torch.func.vmap(lambda *t: torch.func.jvp(fn, xs, t)[1])(*basis)

    torch._dynamo.reset()  # as in test_transforms: one code object for every op's test function
    compiled = torch.compile(columns, backend=COMPILE_BACKEND, fullgraph=True, dynamic=False)
    got = compiled(tx, basis)  # (K, N, *out)
    assert bool(torch.all(torch.isfinite(got)))
    n = len(xs[0])
    jac = got.reshape(len(got), n, -1).permute(1, 2, 0)  # (N, n_out, K)
    argnums = tuple(range(len(tx)))
    eager = torch.func.vmap(torch.func.jacfwd(fn, argnums=argnums))(*tx)
    eager_jac = torch.cat([j.reshape(n, jac.shape[1], -1) for j in eager], dim=-1)
    assert_rows_close(jac, eager_jac, 1e-12, smooth)
    flat_t = torch.tensor(np.concatenate([t.reshape(n, -1) for t in ts], axis=-1))
    tangent = torch.func.jvp(fn, tx, tuple(map(torch.tensor, ts)))[1]
    assert_rows_close(torch.einsum("nok,nk->no", jac, flat_t), tangent.reshape(n, -1), 1e-12, smooth)


# ---------------------------------------------------------------------------------------------------
# jax


# ---------------------------------------------------------------------------------------------------
# Rotation heads: first and second derivatives in forward mode


def _flat_3x3(m: np.ndarray) -> np.ndarray:
    return np.asarray(m, dtype=np.float64).reshape(9)


# Raw outputs where a head is degenerate or borderline: the 9D head at M = I (equal singular values:
# where a library SVD derivative divides by zero), at rank 2 and at det < 0 (all smooth), and at
# M = 0; the 10D head at a = 0 (A = 0: no eigenvector defined); the zero quaternion. At M = 0, a = 0
# and the zero quaternion no derivative exists: the derivative must only be finite (documented bound).
_EDGE_RAW: dict[str, list[tuple[np.ndarray, bool]]] = {
    "quaternion": [(np.zeros(4), False)],
    "axis_angle": [(np.zeros(3), True)],
    "euler": [(np.zeros(3), True)],
    "6d": [(np.array([1.0, 0, 0, 0, 1, 0]), True)],
    "9d": [
        (_flat_3x3(np.eye(3)), True),
        (_flat_3x3([[1.5, 0.2, 1.54], [-0.3, 0.9, -0.12], [0.4, 0.1, 0.42]]), True),  # rank 2
        (_flat_3x3([[1.8, 0.3, -0.2], [0.1, 1.1, 0.4], [0.3, -0.2, -0.5]]), True),  # det < 0
        (np.zeros(9), False),
    ],
    "10d": [(np.array([0.0, 0, 0, 0, 1, 0, 0, 2, 0, 3]), True), (np.zeros(10), False)],
}


def head_inputs(representation: str) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Raw outputs (B, n): 4 Gaussian ones and the edge ones; which rows are smooth; loss weights."""
    n = tnn.representation_size(representation)
    edge = _EDGE_RAW[representation]
    raw = np.concatenate([np.random.default_rng(5).normal(size=(4, n)), [r for r, _ in edge]])
    smooth = np.array([True] * 4 + [s for _, s in edge])
    return raw, smooth, np.random.default_rng(6).normal(size=(len(raw), 3, 3))


def block_diagonal(h: Any, b: int, n: int) -> Any:
    """(B, n, B, n) Hessian of a sum over the batch -> each element's own (B, n, n) block."""
    idx = torch.arange(b) if isinstance(h, torch.Tensor) else jnp.arange(b)
    return h.reshape(b, n, b, n)[idx, :, idx]


def check_second_order(
    hessians: dict[str, Any], grad: Callable[[np.ndarray], np.ndarray], raw: np.ndarray, smooth: np.ndarray
) -> None:
    """Every order of the two modes gives the reverse-over-reverse Hessian (which gradgradcheck
    proves right for the maps), and it matches central differences of the gradient along t."""
    b, n = raw.shape
    blocks = {k: block_diagonal(h, b, n) for k, h in hessians.items()}
    reference = blocks.pop("jacrev(jacrev)")
    for name, h in blocks.items():
        assert bool(np.all(np.isfinite(np.asarray(h)))), name
        assert_rows_close(h, reference, 1e-10)
    t = directions([raw], seed=8)[0]
    fd = (grad(raw + FD_STEP * t) - grad(raw - FD_STEP * t)) / (2 * FD_STEP)
    assert_rows_close(np.einsum("bij,bj->bi", np.asarray(reference), t), fd, 1e-6, smooth)


# The "fisher" head's map is the "9d" one (its rotation is matrix_fisher_mode = special_procrustes of
# the same raw output): its transforms are those of the 9d head, tested here once.
HEADS = [r for r in tnn.REPRESENTATIONS if r != "fisher"]


def _torch_head(representation: str) -> tuple[np.ndarray, Any, Any, Any, torch.Tensor, torch.Tensor]:
    """The head's raw inputs, its smooth rows, the head, a weighted loss of it, and x and t as tensors."""
    raw, smooth, weights = head_inputs(representation)
    w = torch.tensor(weights)

    def head(r: torch.Tensor) -> torch.Tensor:
        return tnn.representation_to_matrix(r, representation)

    def loss(r: torch.Tensor) -> torch.Tensor:
        return (head(r) * w).sum()

    return raw, smooth, head, loss, torch.tensor(raw), torch.tensor(directions([raw], seed=1)[0])


def _torch_head_transforms(head: Any, loss: Any, x: torch.Tensor, t: torch.Tensor) -> dict[str, Any]:
    """Eager forward mode and the Hessian: what the compiled transforms are compared with."""
    tf = torch.func
    return {
        "jvp": tf.jvp(head, (x,), (t,))[1],
        "jacfwd": tf.jacfwd(head)(x),
        "hessian": tf.hessian(loss)(x),  # jacfwd(jacrev)
    }


@pytest.mark.parametrize("representation", HEADS)
def test_torch_heads_under_jvp_jacfwd_and_hessian(representation: str) -> None:
    """Eager: every row's Jacobian in forward mode, and the Hessian in every order of the two modes.
    (Compiled: the test below.)"""
    raw, smooth, head, loss, x, t = _torch_head(representation)
    tf = torch.func
    eager = _torch_head_transforms(head, loss, x, t)
    # Eager only: torch 2.13 cannot compile forward over forward mode at all (for
    # ``(torch.sin(x) * 1e-3).sum()`` too: "InferenceMode::is_enabled() && self.is_inference()
    # INTERNAL ASSERT FAILED" in Dynamo's fake-tensor pass). The two reverse-mode second
    # orders eager only too: compiled, they are the graphs test_transforms.py and
    # test_capture.py compile already, differentiated once more, and tracing them doubled
    # the cost of this test (the 10D head's took 60 s).
    eager["jacfwd(jacfwd)"] = tf.jacfwd(tf.jacfwd(loss))(x)
    eager["jacrev(jacfwd)"] = tf.jacrev(tf.jacfwd(loss))(x)
    eager["jacrev(jacrev)"] = tf.jacrev(tf.jacrev(loss))(x)
    check_tangent(
        eager["jvp"],
        lambda moved: head(torch.tensor(moved[0])).numpy(),
        lambda g: [torch.func.vjp(head, x)[1](torch.tensor(g))[0].numpy()],
        [raw],
        [t.numpy()],
        smooth,
    )
    b, n = raw.shape
    diag = torch.arange(b)
    jac = eager["jacfwd"].reshape(b, 9, b, n)[diag, :, diag]
    assert_rows_close(jac, torch.func.vmap(torch.func.jacrev(head))(x), 1e-10, smooth)
    check_second_order(
        {k: v for k, v in eager.items() if k not in ("jvp", "jacfwd")},
        lambda r: torch.func.grad(loss)(torch.tensor(r)).numpy(),
        raw,
        smooth,
    )


@pytest.mark.parametrize("representation", HEADS)
def test_torch_heads_compiled_under_jvp_and_hessian(representation: str) -> None:
    """Compiled (``fullgraph=True``), every row's Jacobian in forward mode and the Hessian, equal to
    eager. (A test of its own, named for the compiler, so the quick tier leaves it out with the other
    compiled checks: conftest.SLOW_NAMES. Within the eager test it was most of the quick tier's
    largest torch item.)"""
    raw, _, head, loss, x, t = _torch_head(representation)
    (basis,) = basis_tangents((x,))
    eager = _torch_head_transforms(head, loss, x, t)
    b, n = raw.shape
    diag = torch.arange(b)
    jac = eager["jacfwd"].reshape(b, 9, b, n)[diag, :, diag]

    def transforms(x: torch.Tensor) -> dict[str, Any]:
        # forward mode as in test_torch_compiled_forward_mode_equals_eager: vmap over jvp along
        # each component, every row's Jacobian in one transform (jvp and jacfwd compiled apart:
        # 25 s for the 10D head, against 10 s)
        return {
            "columns": torch.func.vmap(lambda b: torch.func.jvp(head, (x,), (b,))[1])(basis),
            "hessian": torch.func.hessian(loss)(x),  # jacfwd(jacrev)
        }

    torch._dynamo.reset()
    compiled = torch.compile(transforms, backend=COMPILE_BACKEND, fullgraph=True, dynamic=False)(x)
    # each row's Jacobian (b, 9, n), from the columns (n, b, 3, 3); its contraction with t is the jvp
    columns = compiled.pop("columns").reshape(n, b, 9).permute(1, 2, 0)
    assert bool(torch.all(torch.isfinite(columns)))
    assert_rows_close(columns.reshape(b, -1), jac.reshape(b, -1), 1e-12)
    assert_rows_close(torch.einsum("bon,bn->bo", columns, t), eager["jvp"].reshape(b, 9), 1e-12)
    for name, value in compiled.items():
        assert bool(torch.all(torch.isfinite(value))), name
        # Compiled, the SVD/eigh maps differentiate a linearised forward (diffquat/torch/_custom.py):
        # its second derivative symmetrises the rules' mixed terms, where eager differentiates the
        # rules as they are. The rules hold a regularisation delta = sqrt(eps) |M| (the solves of
        # _representations.py), so the two second derivatives agree to O(sqrt(eps)) = 1.5e-8, not
        # to rounding (both are that close to finite differences of torch's SVD gradient).
        svd = representation in ("9d", "10d")
        assert_rows_close(value.reshape(b, -1), eager[name].reshape(b, -1), 1e-7 if svd else 1e-12)


@pytest.mark.parametrize("representation", HEADS)
def test_jax_heads_under_jvp_jacfwd_and_hessian(representation: str) -> None:
    raw, smooth, weights = head_inputs(representation)
    w = jnp.asarray(weights)

    def head(r: Any) -> Any:
        return jnn.representation_to_matrix(r, representation)

    def loss(r: Any) -> Any:
        return jnp.sum(head(r) * w)

    x = jnp.asarray(raw)
    t = directions([raw], seed=1)[0]

    @jax.jit
    def transforms(x: Any) -> dict[str, Any]:
        return {
            "jvp": jax.jvp(head, (x,), (jnp.asarray(t),))[1],
            "jacfwd": jax.vmap(jax.jacfwd(head))(x),
            "jacrev": jax.vmap(jax.jacrev(head))(x),
            "hessian": jax.hessian(loss)(x),  # jacfwd(jacrev)
            "jacfwd(jacfwd)": jax.jacfwd(jax.jacfwd(loss))(x),
            # (not reverse over forward: the costliest of the four to compile here, a third of this
            # test; the torch test above runs it, on the same map written once)
            "jacrev(jacrev)": jax.jacrev(jax.jacrev(loss))(x),
        }

    out = transforms(x)
    head_jit = jax.jit(head)
    check_tangent(
        out["jvp"],
        lambda moved: np.asarray(head_jit(jnp.asarray(moved[0]))),
        lambda g: [np.asarray(jax.vjp(head, x)[1](jnp.asarray(g))[0])],
        [raw],
        [t],
        smooth,
    )
    assert bool(jnp.all(jnp.isfinite(out["jacfwd"])))
    assert_rows_close(out["jacfwd"], out["jacrev"], 1e-10, smooth)
    grad = jax.jit(jax.grad(loss))
    check_second_order(
        {k: v for k, v in out.items() if k not in ("jvp", "jacfwd", "jacrev")},
        lambda r: np.asarray(grad(jnp.asarray(r))),
        raw,
        smooth,
    )
