"""What binds the core math to one backend: validation, dtype handling and error messages, written once.

Each backend module builds one :class:`Backend` and calls core functions through it. Everything here
reads only static information (types, dtypes, shapes), so it traces cleanly under ``torch.compile``
and ``jax.jit``; value-level edge cases are the core's business and never raise.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from typing import Any, TypeVar

from . import _core
from ._core import SHAPES

F = TypeVar("F", bound=Callable[..., Any])


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


def shape_tuple(shape: int | tuple[int, ...] | list[int]) -> tuple[int, ...]:
    """A batch shape given as an int or a sequence of ints, as a tuple."""
    return (int(shape),) if isinstance(shape, int) else tuple(int(n) for n in shape)


def documented(core_fn: Callable[..., Any]) -> Callable[[F], F]:
    """Give a backend wrapper the docstring of the core function it binds (written once, there)."""

    def attach(wrapper: F) -> F:
        wrapper.__doc__ = core_fn.__doc__
        return wrapper

    return attach


@dataclass(frozen=True)
class Backend:
    """One backend's primitives that the array namespace does not share.

    Attributes:
        xp: the array namespace the core runs on (``numpy``, ``torch`` or ``jax.numpy``).
        convert: turns a user argument into the backend's array, or raises ``TypeError``.
        is_floating: whether a dtype is a floating-point dtype the library accepts.
        astype: casts an array to a dtype.
        float32: the backend's float32 dtype, the compute dtype of half-precision input.
    """

    xp: Any
    convert: Callable[[str, str, Any], Any]
    is_floating: Callable[[Any], bool]
    astype: Callable[[Any, Any], Any]
    float32: Any

    def compute_dtype(self, dtype: Any) -> Any:
        # float16 and bfloat16 (and anything narrower) are computed in float32: the epsilons and
        # products of the core would flush to zero or overflow in 16 bits.
        return self.float32 if dtype.itemsize < 4 else dtype

    def validate(self, fname: str, *arrays: Any) -> list[Any]:
        """Convert and check every array argument of core function ``fname`` against ``SHAPES``.
        An optional array argument passed as ``None`` stays ``None``."""
        checked: list[Any] = []
        for (argname, trailing), raw in zip(SHAPES[fname].items(), arrays, strict=True):
            if raw is None:
                checked.append(None)
                continue
            x = self.convert(fname, argname, raw)
            if not self.is_floating(x.dtype):
                raise TypeError(f"{fname}: expected {argname} with a floating-point dtype, got {x.dtype}")
            shape = tuple(x.shape)
            if not matches(shape, trailing):
                raise ValueError(
                    f"{fname}: expected {argname} of shape {format_shape(trailing)}, got shape {shape}"
                )
            checked.append(x)
        dtypes = {x.dtype for x in checked if x is not None}
        if len(dtypes) > 1:
            pairs = zip(SHAPES[fname], checked, strict=True)
            names = ", ".join(f"{a}: {x.dtype}" for a, x in pairs if x is not None)
            raise TypeError(f"{fname}: expected all arrays to have one dtype, got {names}")
        return checked

    def __call__(self, core_fn: Callable[..., Any], *arrays: Any, **options: Any) -> Any:
        """Validate ``arrays``, run ``core_fn`` in the compute dtype, return in the input dtype."""
        checked = self.validate(core_fn.__name__, *arrays)
        dtype = checked[0].dtype
        compute = self.compute_dtype(dtype)
        if compute == dtype:
            return core_fn(self.xp, *checked, **options)
        out = core_fn(self.xp, *(x if x is None else self.astype(x, compute) for x in checked), **options)
        if isinstance(out, tuple):
            return tuple(self.astype(o, dtype) for o in out)
        if core_fn.__name__ in _core.CANONICAL:
            return self.cast_canonical(out, dtype, options.get("scalar_first", True))
        return self.astype(out, dtype)

    def cast_canonical(self, q: Any, dtype: Any, scalar_first: bool) -> Any:
        """Cast a canonical quaternion to ``dtype``, keeping it canonical: narrowing can round a tiny
        positive w to 0 (see ``_core.CANONICAL``), so a narrowed result is standardised again."""
        if dtype.itemsize >= q.dtype.itemsize:
            return self.astype(q, dtype)
        return _core.standardize_quaternion(self.xp, self.astype(q, dtype), scalar_first=scalar_first)
