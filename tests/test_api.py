"""The public API: one set of names and signatures on every backend, light imports, clear errors."""

from __future__ import annotations

import importlib
import inspect
import itertools
import subprocess
import sys
import typing
from pathlib import Path
from types import ModuleType

import numpy as np
import pytest
from cases import CASES_BY_NAME, NOT_IN_TABLE, OPS, OPS_BY_NAME, Op, only, uniform_quaternions
from conftest import BACKENDS, Backend

import diffquat.numpy as dqn  # importing a backend registers every op's shapes
from diffquat import _types
from diffquat._backend import format_shape
from diffquat._core import SHAPES
from diffquat._public import public_modules

N_POINTS = 5  # the size given to a "-1" (any size, e.g. N points) in a registered trailing shape


def concrete(trailing: tuple[int, ...]) -> tuple[int, ...]:
    return tuple(N_POINTS if n == -1 else n for n in trailing)


# The one place where the backends' signatures may differ: the random source is the framework's own,
# and so are the dtype and device keywords of the functions that make their result from nothing but a
# shape or a name.
RANDOM_SOURCE = {"numpy": {"rng"}, "torch": {"generator"}, "jax": {"key"}}
FACTORY_KEYWORDS = {"numpy": {"dtype"}, "torch": {"dtype", "device"}, "jax": {"dtype"}}
OWN_KEYWORDS = {
    "random_quaternions": (RANDOM_SOURCE, FACTORY_KEYWORDS),
    "matrix_fisher_sample": (RANDOM_SOURCE,),
    "igso3_sample": (RANDOM_SOURCE,),
    "symmetry_group": (FACTORY_KEYWORDS,),
}


def public(name: str) -> dict[str, inspect.Signature]:
    """The rotation functions of a backend: its ``__all__`` but its own switches."""
    module = importlib.import_module(f"diffquat.{name}")
    return {n: inspect.signature(getattr(module, n)) for n in module.__all__}


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
        for keywords in OWN_KEYWORDS.get(fn, ()):
            params = {k: v for k, v in params.items() if k not in keywords["numpy"]}
            theirs = {k: v for k, v in theirs.items() if k not in keywords[name]}
        assert [(p.name, p.kind, p.default) for p in params.values()] == [
            (p.name, p.kind, p.default) for p in theirs.values()
        ], fn


def test_every_public_function_is_in_the_test_table() -> None:
    exported = set(public("numpy"))
    assert exported == {op.name for op in OPS} | set(NOT_IN_TABLE)
    # a variant names its base row: a row of the same function, or of the function whose map it is
    # under another name (on inputs mapped by ``variant_inputs``), which then gives the same values
    variants = [op for op in OPS if op.variant_of]
    assert variants
    for op in variants:
        base = OPS_BY_NAME[op.variant_of]
        if base.name != op.name:
            xs = op.inputs(CASES_BY_NAME["random"].quaternions("float64"))
            np.testing.assert_array_equal(
                getattr(dqn, op.name)(*xs, **op.kwargs),
                getattr(dqn, base.name)(*op.variant_inputs(*xs), **op.kwargs),
            )


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


def typed(backend: Backend, x: np.ndarray, dtype: str) -> object:
    """``x`` as the backend's array of a NumPy dtype name the table has no entry for (integers,
    complex numbers)."""
    x = np.asarray(x).astype(dtype)
    if backend.name == "torch":
        import torch

        return torch.from_numpy(x)
    if backend.name == "jax":
        import jax.numpy as jnp

        return jnp.asarray(x)
    return x


def table_inputs(op: Op) -> list[np.ndarray]:
    return list(op.inputs(uniform_quaternions(3, seed=0)))


def test_complex_and_string_input_raise_type_error(op: Op, backend: Backend) -> None:
    """A complex array, a string or an object that is no array: a TypeError naming the function and
    the argument, on every backend (not the framework's own error, which names neither)."""
    for i, argname in enumerate(list(SHAPES[op.name])[: len(table_inputs(op))]):
        args: list[object] = [backend.array(x, "float64") for x in table_inputs(op)]
        args[i] = typed(backend, table_inputs(op)[i], "complex64")
        with pytest.raises(TypeError, match=rf"{op.name}: expected {argname} with a real floating-point"):
            op(backend.module, *args)
        for bad in ("1.0", object()):
            args[i] = bad
            with pytest.raises(TypeError, match=rf"^{op.name}: expected {argname} "):
                op(backend.module, *args)


DEFAULT_FLOAT = {"numpy": "float64", "torch": "float32", "jax": "float64"}  # jax: x64 is on (conftest)


def test_integer_input_computes_in_the_default_float_dtype(op: Op, backend: Backend) -> None:
    """Integer arguments are read as the framework's default floating dtype, as its ``sin`` reads them:
    the result is that of the same numbers given as floats (NumPy and JAX also take them as nested
    lists; torch, like its own functions, asks for tensors)."""
    numbers = [np.round(3 * x) for x in table_inputs(op)]
    default = DEFAULT_FLOAT[backend.name]
    expected = op(backend.module, *(backend.array(x, default) for x in numbers))
    out = op(backend.module, *(typed(backend, x, "int32") for x in numbers))
    assert str(out.dtype).endswith(default)
    # Equal to the last bits only: LAPACK's SVD and eigh (special_procrustes, fit_rotation, the 10D
    # map) round differently depending on how their buffer is aligned in memory.
    tol = {"float64": 1e-13, "float32": 1e-6}[default]
    np.testing.assert_allclose(backend.to_numpy(out), backend.to_numpy(expected), rtol=0, atol=tol)
    if backend.name != "torch":
        lists = op(backend.module, *(x.astype(int).tolist() for x in numbers))
        np.testing.assert_allclose(backend.to_numpy(lists), backend.to_numpy(expected), rtol=0, atol=tol)


several_arrays = only(op=lambda op: len(SHAPES[op.name]) > 1)


@several_arrays
def test_mixed_float_dtypes_follow_the_framework_promotion(op: Op, backend: Backend) -> None:
    """float32 beside float64 gives what the framework's own promotion gives (float64 on every backend;
    jax's strict promotion mode, which the suite sets, refuses the pair: a TypeError naming the
    function), computed in that dtype."""
    inputs = table_inputs(op)
    for i in range(len(inputs)):
        mixed = [backend.array(x, "float32" if j == i else "float64") for j, x in enumerate(inputs)]
        if backend.name == "jax":
            import jax

            with pytest.raises(TypeError, match=rf"{op.name}: the arguments' dtypes do not promote"):
                op(backend.module, *mixed)
            with jax.numpy_dtype_promotion("standard"):
                out = op(backend.module, *mixed)
        else:
            out = op(backend.module, *mixed)
        assert str(out.dtype).endswith("float64")
        promoted = [backend.to_numpy(x) for x in mixed]  # the float32 values, exactly, in float64
        again = op(backend.module, *(backend.array(x, "float64") for x in promoted))
        # to the last bits: LAPACK's results depend on the alignment of its buffers
        np.testing.assert_allclose(backend.to_numpy(out), backend.to_numpy(again), rtol=0, atol=1e-13)


@several_arrays
def test_batch_shapes_that_do_not_broadcast_raise_naming_the_arguments(op: Op, backend: Backend) -> None:
    """One ValueError on every backend, from the static shapes, naming the function, every argument
    and its shape (not whatever the arithmetic inside would raise)."""
    trailing = SHAPES[op.name]
    for i in range(len(trailing)):
        shapes = [((3 if j == i else 2), *concrete(t)) for j, t in enumerate(trailing.values())]
        args = [backend.array(np.ones(s), "float64") for s in shapes]
        with pytest.raises(ValueError, match=rf"{op.name}: expected batch shapes that broadcast") as err:
            op(backend.module, *args)
        for argname, shape in zip(trailing, shapes, strict=True):
            assert f"{argname}: shape {shape}" in str(err.value)


def test_slerp_takes_a_python_number_for_t(backend: Backend) -> None:
    """``t`` may be a Python number on every backend (a scalar, weak in the promotion: a float32 pair
    stays float32), or an array whose shape broadcasts against the batch shapes of ``p`` and ``q``."""
    p, q = uniform_quaternions(4, seed=1), uniform_quaternions(4, seed=2)
    for dtype in ("float32", "float64"):
        a, b = backend.array(p, dtype), backend.array(q, dtype)
        out = backend.module.quaternion_slerp(a, b, 0.25)
        assert str(out.dtype).endswith(dtype)
        as_array = backend.module.quaternion_slerp(a, b, backend.array(np.full(4, 0.25), dtype))
        np.testing.assert_array_equal(backend.to_numpy(out), backend.to_numpy(as_array))
    # t of shape (2, 1) against p and q of batch shape (4,): a (2, 4) batch
    t = backend.array(np.array([[0.25], [0.75]]), "float64")
    out = backend.module.quaternion_slerp(backend.array(p, "float64"), backend.array(q, "float64"), t)
    assert tuple(out.shape) == (2, 4, 4)


def test_torch_backend_rejects_non_tensors() -> None:
    import diffquat.torch as dq

    with pytest.raises(
        TypeError, match=r"quaternion_to_matrix: expected q to be a torch\.Tensor, got ndarray"
    ):
        dq.quaternion_to_matrix(uniform_quaternions(2, seed=0))


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


def test_the_public_modules_are_found() -> None:
    found = {m.__name__ for m in public_modules()}
    expected = {"diffquat", "diffquat.numpy", "diffquat.torch", "diffquat.torch.nn", "diffquat.jax"}
    assert expected | {"diffquat.jax.nn"} <= found


def test_public_modules_list_only_their_public_api() -> None:
    """``dir()`` of a public module lists its ``__all__`` and its public submodules, nothing it only
    imports (``torch``, ``Tensor``, ``Any``, the private machinery that binds the core)."""
    for module in public_modules():
        submodules = {
            k
            for k, v in vars(module).items()
            if isinstance(v, ModuleType) and v.__name__.startswith(module.__name__ + ".")
        }
        listed = {n for n in dir(module) if not n.startswith("_")}
        assert listed <= set(module.__all__) | submodules, (module.__name__, listed - set(module.__all__))
        assert all(hasattr(module, n) for n in module.__all__), module.__name__


# Each string option of the public API, by parameter name, and its Literal alias (diffquat/_types.py).
OPTION_TYPES = {
    "convention": _types.EulerConvention,
    "representation": _types.Representation,
    "layout": _types.Rotation6DLayout,
    "side": _types.Side,
    "method": _types.MeanMethod,
    "mode": _types.SE3Interpolation,
    "frame": _types.Frame,
}
# Where one parameter name carries another option: the 7-vector pose layouts.
OWN_OPTION_TYPES = {
    ("pose_to_matrix", "layout"): _types.PoseLayout,
    ("matrix_to_pose", "layout"): _types.PoseLayout,
    ("se3_bspline", "mode"): _types.SplineMode,
}


def test_string_options_are_typed_by_their_literal_alias() -> None:
    """Wherever a public function or class takes one of the string options, its annotation is the
    option's alias, so that a type checker sees the allowed values."""
    checked = 0
    for module in public_modules():
        for name in module.__all__:
            obj = getattr(module, name)
            fn = obj.__init__ if isinstance(obj, type) else obj
            if not callable(fn) or (isinstance(obj, type) and fn is object.__init__):
                continue
            params = inspect.signature(fn).parameters
            if not set(params) & set(OPTION_TYPES):
                continue
            hints = typing.get_type_hints(fn)
            for p in set(params) & set(OPTION_TYPES):
                expected = OWN_OPTION_TYPES.get((name, p), OPTION_TYPES[p])
                assert hints[p] == expected, (module.__name__, name, p)
                checked += 1
    assert checked >= 3 * 6 + 2 * 3  # the Euler and 6D functions of three backends, and the heads


def test_literal_aliases_list_exactly_what_the_functions_accept() -> None:
    from diffquat import _heads
    from diffquat._euler import parse_convention
    from diffquat._representations import _layout_axis

    accepted = set()
    for letters in itertools.product("XYZxyz", repeat=3):
        try:
            parse_convention("f", "".join(letters))
            accepted.add("".join(letters))
        except ValueError:
            pass
    assert set(typing.get_args(_types.EulerConvention)) == accepted and len(accepted) == 24
    assert typing.get_args(_types.Representation) == tuple(_heads.REPRESENTATIONS)
    for layout in typing.get_args(_types.Rotation6DLayout):
        _layout_axis("f", layout)
    from diffquat._se3 import INTERPOLATION_MODES, POSE_LAYOUTS

    assert typing.get_args(_types.PoseLayout) == tuple(POSE_LAYOUTS)
    assert typing.get_args(_types.SE3Interpolation) == INTERPOLATION_MODES
    from diffquat._motion import FRAMES, SPLINE_MODES

    assert typing.get_args(_types.Frame) == FRAMES
    assert typing.get_args(_types.SplineMode) == SPLINE_MODES
    import diffquat

    assert diffquat.EulerConvention is _types.EulerConvention


def test_the_design_pages_layout_is_the_tree() -> None:
    """docs/design.md's "Layout of the code" lists every module of the package, and every path it
    lists exists: a reader finds each map's one place from there."""
    root = Path(__file__).resolve().parents[1]
    text = (root / "docs" / "design.md").read_text()
    block = text.split("## Layout of the code", 1)[1].split("```", 2)[1]
    listed = {line.split()[0] for line in block.splitlines() if line.strip()}
    for path in listed:
        assert (root / path).exists(), f"docs/design.md lists {path}, which is not in the tree"
    modules = {str(p.relative_to(root)) for p in (root / "diffquat").rglob("*.py")}
    assert modules <= listed, f"missing from docs/design.md's layout: {sorted(modules - listed)}"


def test_a_remembered_signature_leaves_every_other_call_checked() -> None:
    """Eager torch calls skip the checks of an argument signature (shapes, dtypes) that passed before
    (``Backend.validate``): a bad call after good ones of the same function still raises its error,
    and integer arguments alone follow torch's default dtype at the time of the call."""
    torch = pytest.importorskip("torch")
    import diffquat.torch as dqt

    q = torch.ones(2, 4)
    for _ in range(2):
        assert dqt.quaternion_multiply(q, q).shape == (2, 4)
    with pytest.raises(ValueError, match=r"quaternion_multiply: expected batch shapes that broadcast"):
        dqt.quaternion_multiply(q, torch.ones(3, 4))
    with pytest.raises(ValueError, match=r"quaternion_multiply: expected q of shape \(\.\.\., 4\)"):
        dqt.quaternion_multiply(q, torch.ones(2, 3))
    with pytest.raises(TypeError, match=r"quaternion_multiply: expected q to be a torch\.Tensor"):
        dqt.quaternion_multiply(q, q.numpy())
    with pytest.raises(TypeError, match="real floating-point"):
        dqt.quaternion_multiply(q, q.to(torch.complex64))
    ints = torch.ones(2, 4, dtype=torch.int64)
    default = torch.get_default_dtype()
    try:
        for dtype in (torch.float64, torch.float32):
            torch.set_default_dtype(dtype)
            assert dqt.quaternion_multiply(ints, ints).dtype == dtype
    finally:
        torch.set_default_dtype(default)
