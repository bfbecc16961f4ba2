"""Which evaluation a torch call of ``quaternion_to_matrix``, ``matrix_to_quaternion``, one of the four
SO(3) Jacobians or ``quaternion_plus`` takes, decided in one place: the functions of those names below.

Each conversion has three evaluations of the one map written in :mod:`diffquat._core`:

- the **formula**: the core formula over torch, differentiated by autograd (or by whatever transform
  or compiler traces it);
- the **C kernels** of :mod:`._cpu` (CPU, eager): one pass over memory forward and one backward;
- the **Triton kernels** of :mod:`._triton` (CUDA, eager): the same, one kernel each way.

The Jacobians (``so3_left_jacobian`` and its right and inverse siblings) and ``quaternion_plus`` have the
formula and the C kernels, and forward-mode AD takes their formula (no ``jvp``: see
:func:`_cpu_kernel_or_formula`).

The kernels write their output through a raw pointer (C) or launch on a buffer (Triton), which no
graph capture records: a ``torch.jit.trace`` of a kernel call is a constant tensor, an export has no
input. So the decision reads the capture state first, then the device:

1. a graph is being captured or a transform is active (``torch.compile``, ``torch.export`` and the
   dynamo ONNX exporter, ``torch.jit.trace`` and the TorchScript ONNX exporter, ``torch.func``
   transforms, ``make_fx`` and every other dispatch or function mode, tensor subclasses): the formula;
2. a plain CPU tensor, where the extension was built (``pyproject.toml`` builds it wherever a C
   compiler is): the C kernels;
3. a plain CUDA tensor, where Triton imports: the Triton kernels;
4. anything else (no compiler at install time, MPS and other devices): the formula.

The kernel modules do not import this one. Every evaluation gives the same values to rounding and the
same derivatives, first and second, forward and reverse: one choice of pivot (the core's), one rule
for non-finite rows (``diffquat._backend.nonfinite_rows``); the tests compare each with a float64
reference.
"""

from __future__ import annotations

import sys
from collections.abc import Callable
from typing import Any

import torch
from torch import Tensor
from torch.autograd import forward_ad
from torch.jit._trace import is_tracing
from torch.overrides import _get_current_function_mode_stack
from torch.utils._device import DeviceContext

from .. import _core, _lie

Evaluation = Callable[..., Tensor]

# The C kernels, where the extension was built.
_cpu: Any
try:
    from .. import _kernels  # noqa: F401
except ImportError:
    _cpu = None
else:
    from . import _cpu


def capturing(x: Tensor) -> bool:
    """Whether a graph capture or a transform may be recording this call (see the module docstring).
    Only ``torch.device`` contexts and ``torch.set_default_device`` (a function mode that sets the
    device of factory functions, and records nothing) do not count."""
    return (
        torch.compiler.is_compiling()  # Dynamo: torch.compile, torch.export, the dynamo ONNX exporter
        or is_tracing()  # type: ignore[no-untyped-call]  # torch.jit.trace, the TorchScript-based ONNX exporter
        or torch._C._are_functorch_transforms_active()  # vmap, grad, jacrev, jvp
        or torch._C._len_torch_dispatch_stack() > 0  # make_fx, non-strict export, FakeTensorMode
        or any(
            not isinstance(mode, DeviceContext)
            for mode in _get_current_function_mode_stack()  # type: ignore[no-untyped-call]
        )
        or type(x) not in (Tensor, torch.nn.Parameter)  # subclasses dispatch themselves
    )


def _kernel_input(x: Tensor) -> bool:
    """A dense tensor whose buffer holds its values: not a lazily negated or conjugated view (its buffer
    holds the values before the sign change), nor a ZeroTensor (no buffer at all: a null pointer)."""
    return x.layout == torch.strided and not x.is_neg() and not x.is_conj() and not x._is_zerotensor()


def _triton() -> Any:
    """:mod:`._triton`, or None where Triton does not import (imported on first use: it is slow)."""
    try:
        from . import _triton
    except ImportError:
        return None
    return _triton


class _Compiled:
    """``torch`` as the core's namespace for ``quaternion_to_matrix`` under ``torch.compile``: the
    matrix is stacked by rows (``_core.stack_matrix``), which inductor writes as one kernel of whole
    rows (forward 4.2x faster on an H100 than the flat stack of nine, 1.8x on the CPU at N = 262144),
    and which torch 2.13 compiles under reverse-over-forward mode, where the view of a nine-way stack
    fails (``jacrev(jacfwd(f))``: "ViewBackward0 returned an invalid gradient ... expected device cpu
    but got meta"). The other maps keep ``torch``: rows measured 1.17x slower for
    ``axis_angle_to_matrix`` on the CPU. The same formula, only stacked differently: the same values."""

    stack_rows = True

    def __getattr__(self, name: str) -> Any:
        return getattr(torch, name)


_COMPILED = _Compiled()


def _formula_q2m(xp: Any, q: Tensor, *, scalar_first: bool = True) -> Tensor:
    """The core formula, stacked by rows where it is compiled (see :class:`_Compiled`)."""
    namespace = _COMPILED if torch.compiler.is_compiling() else xp
    r: Tensor = _core.quaternion_to_matrix(namespace, q, scalar_first=scalar_first)
    return r


def quaternion_to_matrix(q: Tensor) -> Evaluation:
    """The evaluation of ``quaternion_to_matrix`` for this call, given its (validated) input."""
    if capturing(q) or not _kernel_input(q):
        return _formula_q2m
    if q.device.type == "cpu" and _cpu is not None:
        return _cpu.quaternion_to_matrix
    if q.is_cuda and (triton := _triton()) is not None:
        return triton.quaternion_to_matrix
    return _formula_q2m


def matrix_to_quaternion(matrix: Tensor) -> Evaluation:
    """The evaluation of ``matrix_to_quaternion`` for this call, given its (validated) input."""
    if capturing(matrix) or not _kernel_input(matrix):
        return _core.matrix_to_quaternion
    if matrix.device.type == "cpu" and _cpu is not None:
        return _cpu.matrix_to_quaternion
    if matrix.is_cuda and (triton := _triton()) is not None:
        return triton.matrix_to_quaternion
    return _core.matrix_to_quaternion


def _cpu_kernel_or_formula(name: str, formula: Evaluation) -> Callable[..., Evaluation]:
    """The chooser of a function whose only fast path is the C kernels (the SO(3) Jacobians,
    ``quaternion_plus``): the kernels ``_cpu.<name>`` where every argument is a plain eager CPU tensor,
    otherwise the formula. Forward-mode AD takes the formula too: those kernels' Functions have no
    ``jvp``, and the formula's tangent is what one would compute."""

    def choose(*xs: Tensor) -> Evaluation:
        if forward_ad._current_level >= 0 or any(capturing(x) or not _kernel_input(x) for x in xs):
            return formula
        if _cpu is not None and all(x.device.type == "cpu" for x in xs):
            evaluation: Evaluation = getattr(_cpu, name)
            return evaluation
        return formula

    choose.__name__ = choose.__qualname__ = name
    return choose


so3_left_jacobian = _cpu_kernel_or_formula("so3_left_jacobian", _lie.so3_left_jacobian)
so3_right_jacobian = _cpu_kernel_or_formula("so3_right_jacobian", _lie.so3_right_jacobian)
so3_left_jacobian_inverse = _cpu_kernel_or_formula(
    "so3_left_jacobian_inverse", _lie.so3_left_jacobian_inverse
)
so3_right_jacobian_inverse = _cpu_kernel_or_formula(
    "so3_right_jacobian_inverse", _lie.so3_right_jacobian_inverse
)
quaternion_plus = _cpu_kernel_or_formula("quaternion_plus", _lie.quaternion_plus)


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
