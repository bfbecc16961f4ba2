"""Custom derivatives for torch: a map whose library derivative is unstable (SVD, eigh) or slow (the
conversions) with its own rules, in both modes. The formulas live in the core, over ``xp``; this only
registers them, and :func:`form` is the one place that decides which form a call takes.

Two forms of one map, because eager torch and graph capture each honour a different part of an
``autograd.Function``:

- Eager: a Function with ``forward``, ``backward``, ``jvp`` and ``generate_vmap_rule``. Autograd,
  ``torch.func`` (``grad``, ``jacrev``, ``jvp``, ``jacfwd``, ``hessian``, ``vmap``) and dual tensors
  (``torch.autograd.forward_ad``) call the rules, exact to every order. An eager call of which no
  derivative can be asked (inference) takes the Function's forward alone.
- Captured (``torch.compile``, ``torch.jit.trace``): no Function at all. Dynamo refuses one that
  defines ``jvp`` ("Unsupported custom jvp", an error under ``fullgraph=True``), fails to vmap one
  under ``hessian``, and without ``jvp`` differentiates its forward's operations under ``torch.func``
  (``torch.func.jvp`` of the SVD at M = I: NaN); ``torch.jit.trace`` records one as a Python call that
  TorchScript cannot save. So the map is written as plain operations whose autodiff *is* the custom
  rule, to second order (:func:`_linearised`), or, where autodiff of the formula is exact and fast
  once compiled (the conversions: inductor fuses it with the surrounding code), as the formula itself.

Both forms compute the forward by the same formula, so a differentiated call returns, bit for bit,
the value of a plain call, and the eager and captured forms agree to rounding.

An iterative map (the geodesic means: a fixed number of Newton steps, then a derivative by the
implicit function theorem) may also make its forward one opaque operator (``result_shape``, see
:func:`_opaque`): no capture then traces its iterations, whose derivative is never taken anyway.
"""

from __future__ import annotations

import contextlib
import sys
from collections.abc import Callable, Iterator
from typing import Any, Literal

import torch
from torch import Tensor
from torch.autograd import forward_ad
from torch.autograd.forward_ad import _set_fwd_grad_enabled
from torch.jit._trace import is_tracing

from .._core import EAGER_FORMS

Formula = Callable[[Any, Tensor, Tensor, Tensor], Tensor]


Form = Literal["captured", "rule", "formula"]


def form(x: Tensor) -> Form:
    """Which form a call of a map on ``x`` takes, decided here and nowhere else:

    - ``"captured"``: a graph capture records it (``torch.compile``, ``torch.export`` and the dynamo
      ONNX exporter through Dynamo; ``torch.jit.trace`` and the TorchScript ONNX exporter): the plain
      form (the formula, its linearisation or the map's own captured form).
    - ``"rule"``: eager, and a derivative of it can be asked for: autograd records it (``x`` requires
      grad in grad mode; ``torch.func.grad`` and ``jacrev`` wrap ``x`` so), or a forward-mode level
      is open (dual tensors; ``torch.func.jvp``, ``jacfwd`` and ``hessian`` open one): the
      ``autograd.Function`` with the core's rules.
    - ``"formula"``: eager, and no derivative can be asked (inference, ``torch.no_grad``, ``vmap``
      alone): the Function's forward alone, the same formula and so the same value bit for bit,
      without its bookkeeping (binding its signature, the copy of ``x`` its ``jvp`` reads: a pass over
      the input at large N)."""
    if _FORCED or torch.compiler.is_compiling() or is_tracing():  # type: ignore[no-untyped-call]
        return "captured"
    # forward_ad's level counter is the one record of an open dual level (there is no public accessor).
    if (x.requires_grad and torch.is_grad_enabled()) or forward_ad._current_level >= 0:
        return "rule"
    return "formula"


# Tests run the table through the componentwise forms in eager mode too (``componentwise()``).
_FORCED: list[Form] = []


@contextlib.contextmanager
def componentwise() -> Iterator[None]:
    """Run every map in its componentwise form (the captured one) while the context is open, eager:
    how the test table checks both forms of a map on every row."""
    _FORCED.append("captured")
    try:
        yield
    finally:
        _FORCED.pop()


# The eager forms contract with constant coefficient matrices (matmul, addmm). Where a user lowers the
# precision of float32 products (torch.set_float32_matmul_precision("high"), common on GPUs: TF32 or
# bf16 keeps 10 or 7 bits of each operand), those would lose about 3 digits: such calls take the
# componentwise form, whose elementwise arithmetic no such setting touches. Read through torch's
# getter (a quarter of the public attribute's cost, per call), by device: cuBLAS on CUDA, oneDNN on CPU.
_PRECISION = getattr(torch._C, "_get_fp32_precision_getter", None)
_MATMUL_BACKEND = {"cuda": "cuda", "cpu": "mkldnn"}


def exact_products(x: Tensor) -> bool:
    """Whether float32 matrix products on ``x``'s device are exact IEEE products (the default), or
    ``x`` is not float32. Unknown devices and torch builds without the setting count as exact."""
    if x.dtype != torch.float32 or _PRECISION is None:
        return True
    # ``is_cpu`` first: reading ``device`` makes a device object, a third of this function's cost
    backend = "mkldnn" if x.is_cpu else _MATMUL_BACKEND.get(x.device.type)
    return backend is None or _PRECISION(backend, "matmul") in ("none", "ieee")


# On the CPU, the eager forms that contract an outer product with a constant matrix write an (N, 16)
# product and read it back: from a few thousand rows on, bytes and not dispatches are their cost, and
# the componentwise form, elementwise over the columns, is faster (crossover between 2048 and 4096
# rows: docs/performance.md). On other devices launches stay the cost: the eager form at every size.
# Both forms give the same values to a few ulps and take the same choices.
COMPONENTWISE_FROM_ROWS = 4096
_MEMORY_BOUND = {"quaternion_to_matrix", "quaternion_multiply", "axis_angle_to_matrix", "so3_exp"}


def few_rows(name: str, x: Tensor) -> bool:
    """Whether the eager form of the map ``name`` pays on ``x`` (rows: ``x``'s batch elements), as
    above: the maps in ``_MEMORY_BOUND`` on the CPU below :data:`COMPONENTWISE_FROM_ROWS`, every other
    map and device always. Reads static sizes only."""
    if name not in _MEMORY_BOUND or not x.is_cpu:
        return True
    return x.numel() < COMPONENTWISE_FROM_ROWS * x.shape[-1]


def choose(core_fn: Callable[..., Any], x: Tensor) -> Callable[..., Any]:
    """The function a call of the core function ``core_fn`` on ``x`` runs: its eager form where it has
    one (``_core.EAGER_FORMS``) and the call is eager (everywhere but under graph capture,
    :func:`form`, and where float32 matrix products are exact IEEE products, :func:`exact_products`),
    else ``core_fn`` itself; and ``core_fn`` in forward mode (an open dual level) where the eager form
    has a rule of its own (:func:`eager_form_with_rule`), which is for reverse mode only: the
    componentwise form's autodiff is exact to every order. The cheap refusals come first: this runs
    on every call, and a capture decides here without reading the table of eager forms (no guard on
    it in a compiled graph)."""
    if _FORCED or torch.compiler.is_compiling() or is_tracing():  # type: ignore[no-untyped-call]
        return core_fn
    name = core_fn.__name__
    fast = EAGER_FORMS.get(name)
    if fast is None or (name in _WITH_RULE and forward_ad._current_level >= 0):
        return core_fn
    return fast if exact_products(x) and few_rows(name, x) else core_fn


# The core functions whose eager form has its own reverse rule (eager_form_with_rule).
_WITH_RULE: set[str] = set()


def _linearised(forward: Callable[[Any, Tensor], Tensor], tangent: Formula, x: Tensor) -> Tensor:
    """``forward(x)`` in value, whose first and second derivatives under autodiff of its operations
    are those of the rules: the form for graph capture (compiled, traced), where a Function's own
    rules are not all honoured.

    With ``x0 = x.detach()``, ``y0 = forward(x0)``, ``e = x - x0`` (zero in value, the identity in
    derivative) and ``T(x, y, e)`` the tangent, linear in ``e`` and exact on solutions (``T(x, y(x),
    .) = y'(x)``), the midpoint rule ``y(x0 + e) = y0 + y'(x0 + e / 2) e + O(e^3)``:

    - ``m = x0 + e / 2`` and ``g = y0 + T(m, y0, e / 2)``: ``y(m)`` to first order.
    - ``h = y0 + T(m, g, e)``: its Taylor polynomial in ``e`` is ``y0 + T(x0, y0, e) + S(e / 2, e)``
      with ``S(d, e) = T_x(x0, y0, e)[d] + T_y(x0, y0, e)[y' d] = y''[d, e]`` (the derivative of
      ``T(x, y(x), e) = y'(x) e``), i.e. ``y0 + y' e + y''[e, e] / 2``: exact to second order; the
      error of ``g`` (second order) is multiplied by ``e`` again.

    Two evaluations of the tangent (a third, for the same order, doubled the compile time of the
    geodesic means). The value stays ``y0``, bit for bit: ``e = 0``, ``m = x0`` and ``T(x, y, 0) = 0``
    (a linear solve of zero). The first derivative is ``T(x0, y0, .)``, the rule itself; third
    derivatives are not those of the map, the eager Function is exact to every order."""
    x0 = x.detach()
    dx = x - x0
    y0 = forward(torch, x0)
    # y0 carries a zero tangent rather than none: torch 2.13's compiled vmap(jvp) fails on a matmul of
    # a batched tensor without a tangent by one with ("Tensor device mismatch"). 0 * sum(dx) is
    # exactly 0 and broadcasts against y0 ((..., 3, 1) for a matrix, (..., 1) for a vector): dx's axes
    # past y0's leading ones are summed (a mean of samples (..., N, 5) -> (..., 4) sums N too).
    y0 = y0 + 0 * dx.flatten(y0.ndim - 1).sum(-1, keepdim=True)
    m = x0 + 0.5 * dx
    g = y0 + tangent(torch, m, y0, 0.5 * dx)
    return y0 + tangent(torch, m, g, dx)


def _opaque(
    forward: Callable[[Any, Tensor], Tensor], result_shape: Callable[[tuple[int, ...]], tuple[int, ...]]
) -> Callable[[Any, Tensor], Tensor]:
    """``forward`` as one operator (``torch.library.custom_op`` ``diffquat::<name>``): captures record
    one call (``torch.compile`` and ``torch.export`` through its fake implementation, of shape
    ``result_shape(x.shape)``; ``torch.jit.trace``, TorchScript and ``make_fx`` as the operator),
    and inductor calls the eager function. Why: the geodesic median's forward is 12 iterations of a
    few hundred operations, ~10^4 nodes unrolled, which inductor compiled for minutes and export
    traced for one; its derivative never looks inside (it is the implicit function theorem's). Its
    vmap rule moves the batched dimension to the front: the forward is batched over leading
    dimensions. Not differentiable itself: it is only ever called where no derivative is taken."""

    @torch.library.custom_op(f"diffquat::{forward.__name__}", mutates_args=())
    def operator(x: Tensor) -> Tensor:
        return forward(torch, x).contiguous()

    @operator.register_fake
    def _(x: Tensor) -> Tensor:
        return x.new_empty(result_shape(tuple(x.shape)))

    def batched(info: Any, in_dims: tuple[int | None], x: Tensor) -> tuple[Tensor, int | None]:
        (dim,) = in_dims
        return operator(x if dim is None else x.movedim(dim, 0)), (None if dim is None else 0)

    operator.register_vmap(batched)

    def bound(xp: Any, x: Tensor) -> Tensor:
        return operator(x)

    bound.__name__ = forward.__name__
    return bound


def custom_derivative(
    forward: Callable[[Any, Tensor], Tensor],
    tangent: Formula,
    cotangent: Formula,
    *,
    captured: Callable[[Any, Tensor, Tensor], Tensor] | None = None,
    result_shape: Callable[[tuple[int, ...]], tuple[int, ...]] | None = None,
    formula_when_captured: bool = False,
    eager: tuple[Callable[..., Any], ...] | None = None,
) -> Callable[[Any, Tensor], Tensor]:
    """``forward(xp, x) -> y`` with the derivatives ``tangent(xp, x, y, dx) -> dy`` (forward mode)
    and ``cotangent(xp, x, y, gy) -> gx`` (reverse mode). Both formulas are written with
    differentiable torch operations on ``x`` and on the *output* ``y`` (whose own derivative is this
    map again), so every higher order is exact in eager mode, in either order of the two modes.
    ``generate_vmap_rule``: the forward and the formulas are batched torch code, so
    ``torch.func.vmap`` runs them as they are.

    ``captured(xp, x0, dx)``: the map's own form for graph capture, in place of :func:`_linearised`,
    given ``x0 = x.detach()`` and ``dx = x - x0`` (zero in value, the identity in derivative), whose
    autodiff gives the map's derivatives at x (the Bingham maps of ``diffquat._fisher``: their Taylor
    polynomials in dx, whose coefficients all come from one eigendecomposition of x0, where
    linearising their rules would trace the eigendecomposition and the moments seven times, and
    differentiate ``eigh``, which is NaN where eigenvalues repeat even for a zero cotangent).

    With ``result_shape`` (the shape of ``y`` for that of ``x``), the forward is an opaque operator
    (:func:`_opaque`). With ``formula_when_captured``, a capture records the forward's own operations,
    whose autodiff is the map's exact derivative to every order.

    With ``eager`` (``_core.eager_rules``: prepare, forward, cotangent, finish; a forward None: the
    map's own, as the opaque geodesic means keep theirs; optionally a fifth, the forward without
    the auxiliary outputs, for the calls that take no rule), an eager
    call outside forward mode takes the map's eager form (few vectorised operations) with its own
    rules, registered by :func:`_lean` (:func:`form` decides, as above); forward mode (an open dual
    level: ``jvp``, ``jacfwd``, ``hessian``) keeps the Function below, exact to every order through
    its copy of ``x``."""
    if result_shape is not None:
        forward = _opaque(forward, result_shape)

    # An eager rule whose forward is None reuses the map's own (the geodesic means: their opaque
    # operator, whose iterations no rule looks into); its cotangent is the lean one.
    def own_forward(xp: Any, u: Tensor) -> tuple[Tensor]:
        return (forward(xp, u).contiguous(),)

    eager_forward: Callable[..., tuple[Tensor, ...]] = own_forward
    if eager is not None and eager[1] is not None:
        eager_forward = eager[1]
    lean = None if eager is None else _lean(eager_forward, eager[2], forward.__name__)
    # a fifth entry: the eager forward without the outputs only its rule reads (the Fisher normaliser's
    # gradient), for calls of which no derivative can be asked
    plain = eager[4] if eager is not None and len(eager) > 4 else eager_forward

    class Eager(torch.autograd.Function):
        """Returns ``(y, copy of x)``. The copy is what ``jvp`` reads x from: autograd calls ``jvp``
        with forward grad mode off, which hides the tangents of an outer forward level, so that
        jacfwd(jacfwd(f)) would silently drop the second-order terms (pytorch/pytorch#197867). With
        the mode back on, the saved *input* would carry this level's own tangent (an error: "a
        forward grad that itself has a forward gradient at the same level"); an *output* has none
        yet, and carries every outer level's, like ``y``. Its tangent is ``dx``, its cotangent
        adds to x's."""

        generate_vmap_rule = True

        @staticmethod
        def forward(x: Tensor) -> tuple[Tensor, Tensor]:
            # contiguous: a strided view (eigh's column) as the output of a Function trips dual
            # tensors (forward_ad wants its tangent to be a view of the same layout).
            return forward(torch, x).contiguous(), x.clone()

        @staticmethod
        def setup_context(ctx: Any, inputs: tuple[Tensor], output: tuple[Tensor, Tensor]) -> None:
            y, x = output
            ctx.save_for_backward(inputs[0], y)
            ctx.save_for_forward(x, y)

        @staticmethod
        def backward(ctx: Any, grad: Tensor, grad_x: Tensor) -> Tensor:
            x, y = ctx.saved_tensors
            return cotangent(torch, x, y, grad) + grad_x

        @staticmethod
        def jvp(ctx: Any, dx: Tensor) -> tuple[Tensor, Tensor]:
            x, y = ctx.saved_tensors
            with _set_fwd_grad_enabled(True):
                return tangent(torch, x, y, dx), dx

    # A subclass of the map's name: autograd names the backward node after the class when it is made
    # (``_quaternion_to_matrix_eagerBackward`` in a graph, not one ``EagerBackward`` for every map).
    Eager = type(f"_{forward.__name__}_eager", (Eager,), {"__doc__": Eager.__doc__})  # type: ignore[assignment,misc]

    def bound(xp: Any, x: Tensor) -> Tensor:
        chosen = form(x)
        if (
            eager is not None
            and lean is not None
            and chosen != "captured"
            and forward_ad._current_level < 0
            and exact_products(x)
            and few_rows(forward.__name__, x)
        ):
            prepare, finish = eager[0], eager[3]
            u = prepare(torch, x)
            return finish(torch, x, (lean(u) if chosen == "rule" else plain(torch, u))[0])
        if chosen == "rule":
            return Eager.apply(x)[0]  # type: ignore[no-untyped-call]
        if chosen == "formula":
            return forward(torch, x).contiguous()  # laid out as the Function returns it
        if formula_when_captured:
            return forward(torch, x)
        if captured is not None:
            x0 = x.detach()
            return captured(torch, x0, x - x0)
        return _linearised(forward, tangent, x)

    bound.__name__ = forward.__name__  # the Backend validates arguments by this name
    return bound


def _lean(
    forward: Callable[..., tuple[Tensor, ...]], cotangent: Callable[..., Tensor | None], name: str
) -> Callable[[Tensor], tuple[Tensor, ...]]:
    """An eager form ``forward(xp, u) -> (y, *aux)`` with its rule ``cotangent(xp, u, y, *aux, gy,
    *gaux)`` (a cotangent None where none is given) as an ``autograd.Function`` that adds no operation
    of its own: no copy of the input (forward mode needs one, and forward mode takes the componentwise
    Function), no zero cotangent materialised for an output that is not used. ``aux`` is what the
    rule reuses from the forward pass (a norm, the chosen candidate's positions): outputs, so that a
    floating one's dependence on ``u`` is recorded (its cotangent, given in a second derivative, is
    the rule's to take back to ``u``); an integer one has none."""

    class Lean(torch.autograd.Function):
        generate_vmap_rule = True

        @staticmethod
        def forward(u: Tensor) -> tuple[Tensor, ...]:
            return forward(torch, u)

        @staticmethod
        def setup_context(ctx: Any, inputs: tuple[Tensor], output: tuple[Tensor, ...]) -> None:
            ctx.set_materialize_grads(False)
            ctx.save_for_backward(inputs[0], *output)

        @staticmethod
        def backward(ctx: Any, *grads: Tensor | None) -> Tensor | None:
            return cotangent(torch, *ctx.saved_tensors, *grads)

    Lean = type(f"_{name}_lean", (Lean,), {"__doc__": Lean.__doc__})  # type: ignore[assignment,misc]

    def apply(u: Tensor) -> tuple[Tensor, ...]:
        return Lean.apply(u)  # type: ignore[no-untyped-call]

    return apply


def eager_form_with_rule(
    core_fn: Callable[..., Any],
    rules: dict[Any, tuple[Callable[..., Any], Callable[..., Any]]],
    key: Callable[..., Any],
) -> Callable[..., Any]:
    """The eager form of the core function ``core_fn``, a map that the Backend calls (``choose``), with
    its own reverse rule: ``rules[key(**options)] = (forward, cotangent)``, ``forward(xp, x) -> (y,
    aux)`` and ``cotangent(xp, x, y, aux, gy, gaux)`` as for :func:`_lean` (one pair per value of the
    options that shape the result, as the conversions take one per storage order; ``key`` raises for
    an invalid one). A call of which a derivative can be asked (:func:`form`'s ``"rule"``) takes the
    rule's Function, any other eager call the forward alone (the same value, bit for bit); in forward
    mode (an open dual level: ``jvp``, ``jacfwd``, ``hessian``) :func:`choose` takes ``core_fn``
    itself, whose autodiff is exact to every order (and the Backend then applies its non-finite rule
    as after ``core_fn``). Named ``<core_fn>_eager``, the name the Backend reads."""
    steps = {k: lean_step(forward, cotangent, core_fn.__name__) for k, (forward, cotangent) in rules.items()}

    def eager_form(xp: Any, x: Tensor, **options: Any) -> Tensor:
        return steps[key(**options)](x)[0]

    eager_form.__name__ = f"{core_fn.__name__}_eager"
    return eager_form


def lean_step(
    forward: Callable[..., tuple[Tensor, ...]], cotangent: Callable[..., Tensor | None], name: str
) -> Callable[[Tensor], tuple[Tensor, ...]]:
    """One step ``forward(xp, x) -> (y, *aux)`` of the eager form of the core function named ``name``,
    with its reverse rule ``cotangent`` (as for :func:`_lean`): the rule's Function where a derivative
    can be asked (:func:`form`'s ``"rule"``), the forward alone in any other eager call (the same
    value, bit for bit). The eager form is then for reverse mode only, as :func:`eager_form_with_rule`'s
    (:func:`choose` takes the componentwise form in forward mode)."""
    lean = _lean(forward, cotangent, name)
    _WITH_RULE.add(name)

    def step(x: Tensor) -> tuple[Tensor, ...]:
        return lean(x) if form(x) == "rule" else forward(torch, x)

    return step


def exporting_to_onnx() -> bool:
    """Whether an ONNX exporter is tracing this call. ``torch.onnx.is_in_onnx_export`` says so for the
    TorchScript exporter and the dynamo exporter's non-strict pass; Dynamo (the strict pass, which the
    exporter falls back to) folds that function to False, so the exporter's own flag is read as well
    (a module attribute, which Dynamo reads and guards on). Neither module is imported here: where
    ``torch.onnx`` was never imported, nothing is exporting."""
    onnx = sys.modules.get("torch.onnx")
    if onnx is None:
        return False
    flags = sys.modules.get("torch.onnx._internal.exporter._flags")
    return bool(onnx.is_in_onnx_export() or getattr(flags, "_is_onnx_exporting", False))


def refuse_onnx(fname: str, what: str) -> None:
    """Raise ``NotImplementedError`` naming ``fname`` (and ``what`` it is) if an ONNX export traces this
    call: ONNX has no SVD or symmetric eigensolver operator, so the map cannot be exported, and without
    this the exporters fail later with a message about ``aten::linalg_svd`` that names no diffquat
    function."""
    if exporting_to_onnx():
        raise NotImplementedError(
            f"{fname}: {what} cannot be exported to ONNX: it takes an SVD or a symmetric eigendecomposition, "
            "and ONNX has no such operator. Export a '6d' or 'quaternion' head (both export), or deploy "
            "with torch.export or TorchScript, which run it."
        )
