"""The public API: one set of names and signatures on every backend, light imports, clear errors."""

from __future__ import annotations

import importlib
import inspect
import subprocess
import sys

import numpy as np
import pytest
from cases import NOT_IN_TABLE, OPS, Op, uniform_quaternions
from conftest import BACKENDS, Backend

from diffquat._backend import format_shape
from diffquat._core import SHAPES

N_POINTS = 5  # the size given to a "-1" (any size, e.g. N points) in a registered trailing shape


def concrete(trailing: tuple[int, ...]) -> tuple[int, ...]:
    return tuple(N_POINTS if n == -1 else n for n in trailing)


# The one place where the backends' signatures may differ: the random source is the framework's own.
RANDOM_SOURCE = {"numpy": {"rng"}, "torch": {"generator", "device"}, "jax": {"key"}}
# A backend's own switches, public but no rotation function: jax's C-kernel switch (tests/test_jax_deploy.py).
SWITCHES = {"numpy": set(), "torch": set(), "jax": {"cpu_kernels"}}


def public(name: str) -> dict[str, inspect.Signature]:
    """The rotation functions of a backend: its ``__all__`` but its own switches."""
    module = importlib.import_module(f"diffquat.{name}")
    return {n: inspect.signature(getattr(module, n)) for n in module.__all__ if n not in SWITCHES[name]}


def test_import_diffquat_imports_neither_torch_nor_jax() -> None:
    code = "import sys, diffquat; print(sorted(m for m in ('torch', 'jax') if m in sys.modules))"
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True).stdout
    assert out.strip() == "[]"


@pytest.mark.parametrize("name", ["torch", "jax"])
def test_backend_exports_the_same_names_and_signatures_as_numpy(name: str) -> None:
    reference, other = public("numpy"), public(name)
    assert sorted(other) == sorted(reference)
    for fn, sig in reference.items():
        params, theirs = dict(sig.parameters), dict(other[fn].parameters)
        if fn == "random_quaternions":
            params = {k: v for k, v in params.items() if k not in RANDOM_SOURCE["numpy"] | {"dtype"}}
            theirs = {k: v for k, v in theirs.items() if k not in RANDOM_SOURCE[name] | {"dtype"}}
        assert [(p.name, p.kind, p.default) for p in params.values()] == [
            (p.name, p.kind, p.default) for p in theirs.values()
        ], fn


def test_every_public_function_is_in_the_test_table() -> None:
    exported = set(public("numpy"))
    assert exported == {op.name for op in OPS} | set(NOT_IN_TABLE)


def test_every_public_function_is_documented_with_its_shapes(backend: Backend) -> None:
    for name in backend.module.__all__:
        doc = getattr(backend.module, name).__doc__ or ""
        assert "(..., " in doc or "shape" in doc, name


def wrong_shapes(trailing: tuple[int, ...]) -> list[tuple[int, ...]]:
    """Shapes a caller gets wrong: the last dimension off by one (unless it may be any size), and too
    few dimensions. An argument with no trailing dimensions (e.g. slerp's ``t``) accepts every shape:
    there is nothing to get wrong."""
    if not trailing:
        return []
    size = concrete(trailing)
    too_few = size[1:] or ((size[0] + 1,) if trailing[0] != -1 else ())
    return ([(2, *size[:-1], size[-1] + 1)] if trailing[-1] != -1 else []) + [too_few]


def test_bad_shape_raises_naming_the_function_and_the_shapes(op: Op, backend: Backend) -> None:
    trailing = list(SHAPES[op.name].values())
    for i, t in enumerate(trailing):
        for wrong in wrong_shapes(t):
            args = [backend.array(np.zeros((2, *concrete(s))), "float64") for s in trailing]
            args[i] = backend.array(np.zeros(wrong), "float64")
            with pytest.raises(ValueError) as err:
                op(backend.module, *args)
            for fragment in (f"{op.name}:", format_shape(t), f"got shape {wrong}"):
                assert fragment in str(err.value)


def integer_array(backend: Backend, shape: tuple[int, ...]) -> object:
    x = np.zeros(shape, dtype=np.int32)
    if backend.name == "torch":
        import torch

        return torch.from_numpy(x)
    if backend.name == "jax":
        import jax.numpy as jnp

        return jnp.asarray(x)
    return x


def test_non_floating_input_raises_type_error(op: Op, backend: Backend) -> None:
    trailing = list(SHAPES[op.name].values())
    for i, t in enumerate(trailing):
        args = [backend.array(np.zeros((2, *concrete(s))), "float64") for s in trailing]
        args[i] = integer_array(backend, (2, *concrete(t)))
        with pytest.raises(TypeError, match=f"{op.name}.*floating"):
            op(backend.module, *args)


def test_torch_backend_rejects_non_tensors() -> None:
    import diffquat.torch as dq

    with pytest.raises(
        TypeError, match=r"quaternion_to_matrix: expected q to be a torch\.Tensor, got ndarray"
    ):
        dq.quaternion_to_matrix(uniform_quaternions(2, seed=0))


def test_numpy_backend_accepts_lists_of_floats() -> None:
    import diffquat.numpy as dq

    np.testing.assert_allclose(dq.quaternion_to_matrix([1.0, 0.0, 0.0, 0.0]), np.eye(3))


@pytest.mark.parametrize("name", list(BACKENDS))
def test_backend_modules_declare_every_public_function_in_all(name: str) -> None:
    module = importlib.import_module(f"diffquat.{name}")
    defined = {
        n
        for n, v in vars(module).items()
        if callable(v) and getattr(v, "__module__", None) == module.__name__ and not n.startswith("_")
    }
    assert defined == set(module.__all__)


def test_ci_runs_the_readme_test_command() -> None:
    from pathlib import Path

    root = Path(__file__).resolve().parents[1]
    readme = (root / "README.md").read_text()
    blocks = [b.split("```", 1)[0].strip() for b in readme.split("```bash\n")[1:]]
    assert len(blocks) == 2, "the README holds exactly two set-up commands"
    test_command = blocks[1]
    assert "pytest" in test_command and "ruff" in test_command and "mypy" in test_command
    assert test_command in (root / ".ci" / "run").read_text().splitlines()
