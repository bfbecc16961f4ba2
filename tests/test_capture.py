"""Graph capture on torch: a model traced or exported with one input computes, on another input, what
eager computes (eager takes the conversions' autograd.Functions, every capture the core formula:
diffquat/torch/_custom.py, ``form``).

Every row of the table (every public function, each keyword variant) and every ``RotationHead`` is
captured by ``torch.jit.trace`` (and that trace scripted into a module, saved and loaded, the way
TorchScript deploys), ``torch.export``, ``make_fx`` and ``torch.fx.symbolic_trace``, with one input,
then called on another. The four conversions and the heads whose maps have ONNX operators export with
both ONNX exporters and run in onnxruntime; the 9D and 10D heads refuse with a message that names them.

Inputs are float64 so that the capture and eager agree to a few ulps of float64 whatever the machine
(a compiler may fuse and round differently); 1e-12 is about 5000 ulps of the outputs (all of size
<= ~10) and a wrong capture is off by O(1).
"""

from __future__ import annotations

import copy
import io
import warnings
from collections.abc import Callable
from typing import Any

import numpy as np
import pytest
import torch
from cases import OPS, Op, uniform_quaternions
from torch import nn

import diffquat.torch as dq
from diffquat.torch.nn import REPRESENTATIONS, RotationHead

ATOL = 1e-12

pytestmark = [
    # TorchScript is deprecated in torch 2.13, and still how many models deploy: it is tested.
    pytest.mark.filterwarnings(r"ignore:`torch\.jit\.\w+` is deprecated:DeprecationWarning"),
    # jit.trace warns of every Python value it records; diffquat's are shapes, which are checked.
    pytest.mark.filterwarnings("ignore::torch.jit.TracerWarning"),
]


class _Call(nn.Module):
    """One row of the table as a module with fixed positional arguments (FX and TorchScript need a
    signature without ``*args``)."""

    def __init__(self, op: Op) -> None:
        super().__init__()
        self.op = op

    def forward(
        self, x0: torch.Tensor, x1: torch.Tensor | None = None, x2: torch.Tensor | None = None
    ) -> Any:
        xs = [x for x in (x0, x1, x2) if x is not None]
        return self.op(dq, *xs)


def _inputs(op: Op, seed: int) -> tuple[torch.Tensor, ...]:
    # Five rotations: different values and, from the second seed on, a different batch size too, so a
    # capture that baked in a shape or a value fails.
    q = uniform_quaternions(5, seed)
    return tuple(torch.from_numpy(np.ascontiguousarray(x)) for x in op.inputs(q))


def _script(module: nn.Module, args: tuple[torch.Tensor, ...]) -> Callable[..., Any]:
    traced = torch.jit.trace(module, args, check_trace=False)
    buffer = io.BytesIO()
    torch.jit.save(torch.jit.script(traced), buffer)
    buffer.seek(0)
    return torch.jit.load(buffer)  # type: ignore[no-any-return]


def _export(module: nn.Module, args: tuple[torch.Tensor, ...]) -> Callable[..., Any]:
    batch = torch.export.Dim("batch")
    shapes = tuple({0: batch} for _ in args)
    return torch.export.export(module, args, dynamic_shapes=shapes).module()  # type: ignore[no-any-return]


def _make_fx(module: nn.Module, args: tuple[torch.Tensor, ...]) -> Callable[..., Any]:
    from torch.fx.experimental.proxy_tensor import make_fx

    # symbolic sizes: the default ("real") bakes the batch size into every view
    # (the parameters of a head are real tensors, read as constants of the graph)
    capture = make_fx(module, tracing_mode="symbolic", _allow_non_fake_inputs=True)
    return capture(*args)  # type: ignore[no-any-return]


def _fx(module: nn.Module, args: tuple[torch.Tensor, ...]) -> Callable[..., Any]:
    # The unused optional arguments of ``_Call`` are given as the constants they are (FX would
    # otherwise trace them as inputs, which are never None).
    unused = {f"x{i}": None for i in range(len(args), 3)} if isinstance(module, _Call) else None
    return torch.fx.symbolic_trace(module, concrete_args=unused)


CAPTURES: dict[str, Callable[[nn.Module, tuple[torch.Tensor, ...]], Callable[..., Any]]] = {
    "jit.trace": lambda module, args: torch.jit.trace(module, args, check_trace=False),
    "jit.script": _script,
    "export": _export,
    "make_fx": _make_fx,
    "fx": _fx,
}

_ROWS = {op.id: op for op in OPS}


def _same(a: Any, b: Any) -> None:
    torch.testing.assert_close(a, b, rtol=0, atol=ATOL, equal_nan=True)


@pytest.mark.parametrize("capture", list(CAPTURES))
@pytest.mark.parametrize("row", list(_ROWS))
def test_captured_function_computes_what_eager_does(row: str, capture: str) -> None:
    op = _ROWS[row]
    module = _Call(op)
    first, second = _inputs(op, 1), _inputs(op, 2)
    captured = CAPTURES[capture](module, first)
    _same(captured(*second), module(*second))
    _same(captured(*first), module(*first))


def _head(representation: str) -> RotationHead:
    torch.manual_seed(0)
    return RotationHead(8, representation=representation, dtype=torch.float64).eval()


def _features(seed: int, n: int) -> torch.Tensor:
    return torch.randn(n, 8, generator=torch.Generator().manual_seed(seed), dtype=torch.float64)


@pytest.mark.parametrize("capture", list(CAPTURES))
@pytest.mark.parametrize("representation", REPRESENTATIONS)
def test_captured_head_computes_what_eager_does(representation: str, capture: str) -> None:
    head = _head(representation)
    captured = CAPTURES[capture](head, (_features(1, 5),))
    with torch.no_grad():
        for features in (_features(2, 7), _features(3, 5)):
            _same(captured(features), head(features))


# ---------------------------------------------------------------------------------------------------
# ONNX: the exported graph, run by onnxruntime, against eager.
#
# In float32: onnxruntime has no float64 kernel for some operators the maps need (Atan, in the atan2
# of the axis-angle maps). The reference is eager float64 on the same (float32) inputs; the outputs
# are of size <= pi, the maps well conditioned at these generic rotations, so onnxruntime's float32
# result lies within a few tens of float32 ulps (1e-5 is ~80 ulps of pi); a wrong export is off by O(1).

ONNX_ATOL = 1e-5

# The maps with ONNX operators (the 9D/10D heads need an SVD/eigh, which ONNX lacks).
ONNX_ROWS = ["quaternion_to_matrix", "matrix_to_quaternion", "axis_angle_to_matrix", "matrix_to_axis_angle"]
ONNX_HEADS = ["quaternion", "6d", "axis_angle", "euler"]


def _onnx_run(module: nn.Module, args: tuple[torch.Tensor, ...], dynamo: bool) -> Callable[..., Any]:
    import onnxruntime

    names = [f"x{i}" for i in range(len(args))]
    buffer = io.BytesIO()
    with warnings.catch_warnings():
        # the exporters' own chatter (training-mode notes, deprecations inside torch.onnx)
        warnings.simplefilter("ignore")
        if dynamo:
            batch = torch.export.Dim("batch")
            program = torch.onnx.export(
                module,
                args,
                input_names=names,
                dynamic_shapes=tuple({0: batch} for _ in args),
                dynamo=True,
                verbose=False,
            )
            assert program is not None
            program.save(buffer)
        else:
            axes = {name: {0: "batch"} for name in names}
            torch.onnx.export(module, args, buffer, input_names=names, dynamic_axes=axes, dynamo=False)
    session = onnxruntime.InferenceSession(buffer.getvalue(), providers=["CPUExecutionProvider"])

    def run(*xs: torch.Tensor) -> torch.Tensor:
        outputs = session.run(None, {n: x.numpy() for n, x in zip(names, xs, strict=True)})
        return torch.from_numpy(outputs[0])

    return run


def _onnx_same(received: torch.Tensor, reference: torch.Tensor) -> None:
    assert received.dtype == torch.float32
    torch.testing.assert_close(received.double(), reference, rtol=0, atol=ONNX_ATOL)


@pytest.mark.parametrize("dynamo", [False, True], ids=["torchscript", "dynamo"])
@pytest.mark.parametrize("row", ONNX_ROWS)
def test_onnx_export_of_conversions_runs_in_onnxruntime(row: str, dynamo: bool) -> None:
    op = _ROWS[row]
    module = _Call(op)
    run = _onnx_run(module, tuple(x.float() for x in _inputs(op, 1)), dynamo)
    for seed in (2, 3):
        xs = tuple(x.float() for x in _inputs(op, seed))
        _onnx_same(run(*xs), module(*(x.double() for x in xs)))


@pytest.mark.parametrize("dynamo", [False, True], ids=["torchscript", "dynamo"])
@pytest.mark.parametrize("representation", ONNX_HEADS)
def test_onnx_export_of_heads_runs_in_onnxruntime(representation: str, dynamo: bool) -> None:
    reference = _head(representation)
    head = copy.deepcopy(reference).float()
    run = _onnx_run(head, (_features(1, 5).float(),), dynamo)
    with torch.no_grad():
        for features in (_features(2, 7).float(), _features(3, 5).float()):
            _onnx_same(run(features), reference(features.double()))


@pytest.mark.parametrize("dynamo", [False, True], ids=["torchscript", "dynamo"])
@pytest.mark.parametrize("representation", ["9d", "10d", "fisher"])
def test_onnx_export_of_svd_heads_names_the_representation(representation: str, dynamo: bool) -> None:
    head = _head(representation).float()
    # The dynamo exporter reports the exception of its first failed pass inside its own error.
    with pytest.raises(Exception, match=f"the '{representation}' representation cannot be exported to ONNX"):
        _onnx_run(head, (_features(1, 5).float(),), dynamo)
    assert head(_features(2, 3).float()).shape == (3, 3, 3)  # and eager is untouched
