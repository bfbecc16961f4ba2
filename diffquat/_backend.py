"""What binds the core math to one backend: validation, dtype handling and error messages, written once.

Each backend module builds one :class:`Backend` and calls core functions through it. Everything here
reads only static information (types, dtypes, shapes), so it traces cleanly under ``torch.compile``,
``torch.jit.trace``, ``torch.export`` and ``jax.jit``; value-level edge cases are the core's business
and never raise.

The rules, the same on every backend:

- Arguments are converted as the framework converts them (NumPy and JAX accept array-likes, integer
  ones included; torch asks for tensors, as torch's own functions do, except for the scalar arguments
  that a Python number may stand for, such as ``quaternion_slerp``'s ``t``).
- The result dtype is the framework's own promotion of the floating arguments (``np.result_type``,
  ``jnp.result_type``, torch's type promotion, Python numbers weak); integer and boolean arguments
  alone give the framework's default floating dtype, as ``sin`` does. Complex and non-numeric
  arguments raise ``TypeError`` naming the function and the argument.
- Half precision (float16, bfloat16) is computed in float32 and returned in its dtype.
- A wrong trailing shape, or batch shapes that do not broadcast, raise ``ValueError`` naming the
  function, the arguments and their shapes, from static shapes only.
- A non-finite row: any NaN or infinite entry in the input rows of one batch element makes every
  entry of that element's output NaN; the other elements are unaffected (see :func:`nonfinite_rows`).
"""

from __future__ import annotations

import contextlib
from collections.abc import Callable, Hashable
from dataclasses import dataclass, field
from typing import Any, TypeVar

from . import _core
from ._core import SHAPES

F = TypeVar("F", bound=Callable[..., Any])

# How many passing signatures a Backend remembers (Backend.validate) before it forgets them all: a
# bound for programs whose batch shapes never repeat.
_REMEMBERED = 4096


def format_shape(trailing: tuple[int, ...]) -> str:
    """``(..., 3, 3)``; a -1 in the registry (any size, e.g. a number of points) prints as ``N``."""
    return "(..., " + ", ".join("N" if n == -1 else str(n) for n in trailing) + ")"


def matches(shape: tuple[int, ...], trailing: tuple[int, ...]) -> bool:
    """Whether ``shape`` ends in ``trailing`` (where -1 matches any size)."""
    if len(shape) < len(trailing):
        return False
    tail = shape[len(shape) - len(trailing) :]
    # ``s == t``, not ``t in (-1, s)``: under torch.compile(dynamic=True) every size is symbolic, and
    # Dynamo traced the ``in`` as False, so that every valid input raised the shape error.
    return all(t == -1 or s == t for s, t in zip(tail, trailing, strict=True))


def broadcasts(shapes: list[tuple[int, ...]]) -> bool:
    """Whether batch shapes broadcast against each other (NumPy's rule, from the right)."""
    # Plain loops: Dynamo (torch.compile fullgraph) cannot trace ``max`` over a generator.
    rank = 0
    for s in shapes:
        rank = max(rank, len(s))
    for k in range(1, rank + 1):
        # ``== 1`` and ``==`` only (see ``matches``): symbolic sizes under torch.compile compare so.
        big = [s[-k] for s in shapes if len(s) >= k and not s[-k] == 1]  # noqa: SIM201
        for n in big[1:]:
            if not n == big[0]:  # noqa: SIM201
                return False
    return True


def shape_tuple(shape: int | tuple[int, ...] | list[int]) -> tuple[int, ...]:
    """A batch shape given as an int or a sequence of ints, as a tuple."""
    return (int(shape),) if isinstance(shape, int) else tuple(int(n) for n in shape)


def documented(core_fn: Callable[..., Any]) -> Callable[[F], F]:
    """Give a backend wrapper the docstring of the core function it binds (written once, there)."""

    def attach(wrapper: F) -> F:
        wrapper.__doc__ = core_fn.__doc__
        return wrapper

    return attach


def _match_rank(xp: Any, a: Any, rank: int) -> Any:
    # jax (with rank promotion set to "raise") refuses to broadcast across ranks: unit axes first.
    return xp.reshape(a, (1,) * (rank - a.ndim) + tuple(a.shape)) if a.ndim < rank else a


def nonfinite_rows(xp: Any, out: Any, arrays: list[tuple[Any, tuple[int, ...]]]) -> Any:
    """``out`` with every batch element whose input rows hold a NaN or an infinity set to NaN.

    ``arrays`` are the inputs with their registered trailing shapes; their batch shapes broadcast to
    ``out``'s batch shape, and the rest of ``out``'s dimensions are one element's output. Why a rule
    of its own: left to the arithmetic, a NaN reaches some entries of a row and not others (a matrix
    entry the selected candidate does not read), and ``inf`` turns into NaN or 0 depending on the
    path, so each path would document its own result.

    The rule is arithmetic, not a selection: ``out + sum(0 * x)`` over each input's row, which adds 0
    to a finite row (``-0`` becomes ``+0``, equal) and NaN to every entry of a bad one, nothing across
    rows. ``x`` enters as a constant of differentiation (``_core.cancelling_factor``), so the rule
    adds no operation to a backward pass and the derivative is the formula's own: the identity on the
    good rows, NaN or 0 on the bad ones. Two or three operations per input in eager torch (a product,
    a sum, the addition; a view where the trailing ranks differ), where a selection took nine
    (``isfinite``'s four, the NaN constant, the mask's view, the ``where``)."""
    batch_rank = 0
    for x, trailing in arrays:
        batch_rank = max(batch_rank, x.ndim - len(trailing))
    out_trailing = out.ndim - batch_rank
    acc = None
    for x, trailing in arrays:
        # _core.zero_or_nan, its sum kept as unit axes where the trailing ranks agree
        z = _core.cancelling_factor(xp, x) * 0.0
        if trailing:
            z = xp.sum(z, axis=tuple(range(-len(trailing), 0)), keepdims=len(trailing) == out_trailing)
        if len(trailing) != out_trailing:
            z = xp.reshape(z, tuple(z.shape) + (1,) * out_trailing)
        if acc is None:
            acc = z
        else:
            rank = max(acc.ndim, z.ndim)
            acc = _match_rank(xp, acc, rank) + _match_rank(xp, z, rank)
    assert acc is not None
    return out + _match_rank(xp, acc, out.ndim)


@dataclass(frozen=True)
class Backend:
    """One backend's primitives that the array namespace does not share.

    Attributes:
        xp: the array namespace the core runs on (``numpy``, ``torch`` or ``jax.numpy``).
        convert: ``(fname, argname, x, scalar)`` -> the backend's array for a user argument (a Python
            number stays as it is where ``scalar`` says it may stand for the argument), or raises
            ``TypeError``.
        is_floating: whether a dtype is a real floating-point dtype.
        is_integral: whether a dtype is an integer or boolean dtype (converted to a floating one).
        result_type: the framework's promotion of the converted arguments (arrays and Python numbers).
        default_float: the framework's default floating dtype (of an integer argument).
        astype: casts an array to a dtype.
        scalar: ``(value, dtype, like)`` -> a 0-dimensional array of a Python number, on the device of
            the array ``like`` (or None).
        float32: the backend's float32 dtype, the compute dtype of half-precision input.
        guard: a context manager around every computation (torch: autocast off, so that the core
            computes in the dtype chosen here, not in the autocast dtype), or None where the call
            needs none (torch outside autocast: no context entered, per call).
        static: a context manager around the checks of shapes (torch: under ``torch.jit.trace``
            sizes are traced tensors, and each comparison of one warns that it is read as a constant,
            which for these checks is what is meant).
        choose: ``(core_fn, first input) -> the function to run``: torch runs a map's eager form
            (``_core.EAGER_FORMS``) outside graph capture; the others run the core function.
        signature: ``(fname, arguments)`` -> what decides the outcome of their validation (each
            argument's type, shape and dtype), or None where it is not to be remembered (torch: under
            graph capture, whose sizes may be symbolic and whose Python is traced, and for any
            argument that is not a tensor, None or a Python number). See :meth:`validate`.
    """

    xp: Any
    convert: Callable[[str, str, Any, bool], Any]
    is_floating: Callable[[Any], bool]
    is_integral: Callable[[Any], bool]
    result_type: Callable[[list[Any]], Any]
    default_float: Callable[[], Any]
    astype: Callable[[Any, Any], Any]
    scalar: Callable[[float, Any, Any], Any]
    float32: Any
    guard: Callable[[Any], contextlib.AbstractContextManager[Any] | None] = lambda x: None
    static: Callable[[], contextlib.AbstractContextManager[Any]] = contextlib.nullcontext
    choose: Callable[[Callable[..., Any], Any], Callable[..., Any]] = lambda fn, x: fn
    signature: Callable[[str, tuple[Any, ...]], Hashable | None] = lambda fname, arrays: None
    # signature -> the promoted dtype, of the calls that passed validation (see validate)
    _passed: dict[Hashable, Any] = field(default_factory=dict, compare=False, repr=False)

    def compute_dtype(self, dtype: Any) -> Any:
        # float16 and bfloat16 (and anything narrower) are computed in float32: the epsilons and
        # products of the core would flush to zero or overflow in 16 bits.
        return self.float32 if dtype.itemsize < 4 else dtype

    def validate(self, fname: str, *arrays: Any) -> tuple[list[Any], Any]:
        """Convert and check every array argument of core function ``fname`` against ``SHAPES``, and
        cast them to their promoted dtype, which is returned beside them. An optional array argument
        passed as ``None`` stays ``None``.

        The outcome of the checks is a function of the arguments' :attr:`signature` (types, shapes,
        dtypes): a signature that passed once passes again with the same promoted dtype, so an eager
        call whose signature has passed before skips them (a dictionary look-up in place of ~10 µs of
        Python per call at small N). Only passing signatures are remembered, so every bad argument
        still meets the checks and raises their error; and only those with a floating array, whose
        promotion reads no global state (integer arguments alone promote to torch's default dtype,
        which the user may change)."""
        key = self.signature(fname, arrays)
        if key is not None:
            try:
                dtype = self._passed.get(key)
            except TypeError:  # a symbolic size (torch.fx, non-strict export) has no hash
                dtype = key = None
            if dtype is not None:
                if len(arrays) == 1:  # the common case: one array, already a floating one
                    (x,) = arrays
                    return [x if x.dtype == dtype else self.astype(x, dtype)], dtype
                present = [x for x in arrays if x is not None]
                return [None if x is None else self.array_of(x, dtype, like=present) for x in arrays], dtype
        with self.static():
            checked, dtype = self._validate(fname, arrays)
        if key is not None and any(
            x is not None and not isinstance(x, int | float) and self.is_floating(x.dtype) for x in arrays
        ):
            if len(self._passed) >= _REMEMBERED:  # many shapes (varying batches): start again
                self._passed.clear()
            self._passed[key] = dtype
        return checked, dtype

    def _validate(self, fname: str, arrays: tuple[Any, ...]) -> tuple[list[Any], Any]:
        registry = SHAPES[fname]
        converted: list[Any] = []
        for (argname, trailing), raw in zip(registry.items(), arrays, strict=True):
            if raw is None:
                converted.append(None)
                continue
            x = self.convert(fname, argname, raw, trailing == ())
            if isinstance(x, int | float) and not isinstance(x, bool):
                converted.append(x)  # a Python number for a scalar argument: weak in the promotion
                continue
            if not (self.is_floating(x.dtype) or self.is_integral(x.dtype)):
                raise TypeError(
                    f"{fname}: expected {argname} with a real floating-point (or integer) dtype, "
                    f"got {x.dtype}"
                )
            shape = tuple(x.shape)
            if not matches(shape, trailing):
                raise ValueError(
                    f"{fname}: expected {argname} of shape {format_shape(trailing)}, got shape {shape}"
                )
            converted.append(x)
        present = [x for x in converted if x is not None]
        try:
            dtype = self.result_type(present)
        except Exception as error:  # e.g. jax's strict promotion refusing float32 with float64
            names = ", ".join(f"{a}: {_dtype_of(x)}" for a, x in zip(registry, converted, strict=True))
            raise TypeError(f"{fname}: the arguments' dtypes do not promote ({names}): {error}") from error
        if not self.is_floating(dtype):
            dtype = self.default_float()
        checked = [None if x is None else self.array_of(x, dtype, like=present) for x in converted]
        named = [(a, t, x) for (a, t), x in zip(registry.items(), checked, strict=True) if x is not None]
        # Every -1 of a registered shape is one size N (a number of points), the same in every argument.
        sizes = [(a, tuple(x.shape)[x.ndim - len(t) + t.index(-1)]) for a, t, x in named if -1 in t]
        if any(not n == sizes[0][1] for _, n in sizes[1:]):  # noqa: SIM201
            names = ", ".join(f"{a}: shape {tuple(x.shape)}" for a, _, x in named)
            raise ValueError(f"{fname}: expected the same number of points N in every argument, got {names}")
        if len(named) > 1:
            batches = [tuple(x.shape)[: x.ndim - len(t)] for _, t, x in named]
            if not broadcasts(batches):
                names = ", ".join(f"{a}: shape {tuple(x.shape)}" for a, _, x in named)
                raise ValueError(f"{fname}: expected batch shapes that broadcast, got {names}")
        return checked, dtype

    def array_of(self, x: Any, dtype: Any, like: list[Any]) -> Any:
        """``x`` as an array of ``dtype`` (a Python number on the device of the arrays in ``like``)."""
        if isinstance(x, int | float):
            return self.scalar(x, dtype, next((a for a in like if not isinstance(a, int | float)), None))
        return x if x.dtype == dtype else self.astype(x, dtype)

    def __call__(self, core_fn: Callable[..., Any], *arrays: Any, **options: Any) -> Any:
        """Validate ``arrays``, run ``core_fn`` in the compute dtype, return in the promoted dtype,
        with :func:`nonfinite_rows`'s rule applied, except after the core functions named in
        ``_core.NONFINITE_BY_ARITHMETIC``, which make non-finite rows NaN by their arithmetic."""
        fname = core_fn.__name__
        checked, dtype = self.validate(fname, *arrays)
        compute = self.compute_dtype(dtype)
        # every checked array is of the promoted dtype: all of them or none are cast
        inputs = checked
        if compute != dtype:
            inputs = [None if x is None else self.astype(x, compute) for x in checked]
        guard = self.guard(inputs[0])
        if guard is None:
            return self._run(core_fn, fname, inputs, dtype, compute, options)
        with guard:
            return self._run(core_fn, fname, inputs, dtype, compute, options)

    def _run(
        self,
        core_fn: Callable[..., Any],
        fname: str,
        inputs: list[Any],
        dtype: Any,
        compute: Any,
        options: dict[str, Any],
    ) -> Any:
        chosen = self.choose(core_fn, inputs[0])
        out = chosen(self.xp, *inputs, **options)
        # an eager form may make non-finite rows NaN by its arithmetic where the core function
        # does not (registered by its own name)
        by_arithmetic = _core.NONFINITE_BY_ARITHMETIC
        if fname not in by_arithmetic and chosen.__name__ not in by_arithmetic:
            if len(inputs) == 1:
                rows = [(inputs[0], next(iter(SHAPES[fname].values())))]
            else:
                rows = [(x, t) for x, t in zip(inputs, SHAPES[fname].values(), strict=True) if x is not None]
            out = nonfinite_rows(self.xp, out, rows)
        if compute == dtype:
            return out
        if fname in _core.CANONICAL:
            return self.cast_canonical(out, dtype, options.get("scalar_first", True))
        return self.astype(out, dtype)

    def cast_canonical(self, q: Any, dtype: Any, scalar_first: bool) -> Any:
        """Cast a canonical quaternion to ``dtype``, keeping it canonical: narrowing can round a tiny
        positive w to 0 (see ``_core.CANONICAL``), so a narrowed result is standardised again."""
        if dtype.itemsize >= q.dtype.itemsize:
            return self.astype(q, dtype)
        return _core.standardize_quaternion(self.xp, self.astype(q, dtype), scalar_first=scalar_first)


def _dtype_of(x: Any) -> str:
    return "None" if x is None else type(x).__name__ if isinstance(x, int | float) else str(x.dtype)
