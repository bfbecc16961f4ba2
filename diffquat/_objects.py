"""``SO3`` and ``SE3``: rotations and rigid transforms as objects, written once over a backend module.

Each class is a thin immutable wrapper of one array, the matrix that diffquat's functions take:
``SO3`` holds rotation matrices ``(..., 3, 3)``, ``SE3`` holds poses ``(..., 4, 4)``
(``[[R, t], [0, 1]]``, column vectors), and the leading axes are the batch shape. Every method is one
call of a public function of the backend module (``diffquat.numpy``, ``diffquat.torch`` or
``diffquat.jax``) on the stored array, so the object path returns bit for bit what the function
returns and dispatches the same operations; where there is no function (``SO3``'s product and action)
it is the matrix product the migration pages write, ``R1 @ R2`` and ``R @ v``.

Why matrices, not quaternions (jaxlie's choice) or a quaternion and a translation: with a matrix, the
composition and the action are one matrix product and ``as_matrix`` is free; with a quaternion each is
a quaternion function of tens of eager operations, and every call of the matrix functions
(``so3_log``, ``so3_plus``, ``se3_*``, the optimisers) would convert first. Measured in
``benchmarks/objects.py`` (docs/performance.md, Objects).

Each backend module binds the classes to itself with :func:`bind`: ``diffquat.torch.SO3`` is a subclass
whose ``_dq`` is ``diffquat.torch``. Validation is the functions' own (``_backend.Backend.validate``):
the methods register their arguments' trailing shapes under their own names (``SO3.apply``), and an
error a function raises inside a method is raised again with the method's name in front.
"""

from __future__ import annotations

from collections.abc import Callable, Iterator, Sequence
from dataclasses import dataclass
from typing import Any, ClassVar, TypeVar

from ._backend import broadcasts
from ._core import SHAPES
from ._types import EulerConvention, MeanMethod, PoseLayout, Rotation6DLayout, SE3Interpolation, Side

G = TypeVar("G", bound="_Group")

# The methods that validate arguments themselves (no function of the backend does it for them): their
# arguments' trailing shapes, under the names their errors carry.
SHAPES["SO3"] = {"matrix": (3, 3)}
SHAPES["SE3"] = {"matrix": (4, 4)}
SHAPES["SO3.compose"] = {"matrix1": (3, 3), "matrix2": (3, 3)}
SHAPES["SO3.apply"] = {"matrix": (3, 3), "points": (3,)}


def _batch_axis(axis: int) -> int:
    # a negative batch axis counts from the end of the batch shape, before the two matrix axes
    return axis - 2 if axis < 0 else axis


class _Group:
    """What ``SO3`` and ``SE3`` share: the stored matrix and its batch shape."""

    __slots__ = ("_matrix",)
    _dq: ClassVar[Any]  # the backend module whose functions the methods call
    _native: ClassVar[Any]  # its few primitives that are no diffquat function (see bind)
    _size: ClassVar[int]  # 3 (SO3) or 4 (SE3): the matrix is (..., size, size)
    _matrix: Any

    def __init__(self, matrix: Any) -> None:
        """Wrap matrices of shape ``(..., n, n)`` as they are (no projection: ``special_procrustes``
        makes a rotation of a nearby matrix); wrong trailing shapes and dtypes raise as the functions'
        arguments do."""
        (checked,), _ = self._dq._B.validate(type(self).__name__, matrix)
        object.__setattr__(self, "_matrix", checked)

    @classmethod
    def _wrap(cls: type[G], matrix: Any) -> G:
        # A function's result, already valid: no check (and pytrees unflatten tracers and placeholders)
        out = object.__new__(cls)
        object.__setattr__(out, "_matrix", matrix)
        return out

    def __setattr__(self, name: str, value: Any) -> None:
        raise AttributeError(
            f"{type(self).__name__} is immutable: make a new one instead of setting {name!r}"
        )

    def __reduce__(self) -> tuple[Any, tuple[Any]]:
        # pickle and copy.deepcopy rebuild through _wrap (the default would set the slot, which
        # __setattr__ refuses)
        return type(self)._wrap, (self._matrix,)

    @classmethod
    def _call(cls, name: str, fn: Callable[..., Any], /, *args: Any, **kwargs: Any) -> Any:
        """``fn(*args, **kwargs)``, with the name of the method in front of an argument error."""
        try:
            return fn(*args, **kwargs)
        except (TypeError, ValueError) as error:
            raise type(error)(f"{cls.__name__}.{name}: {error}") from None

    def _same(self: G, method: str, other: Any) -> G:
        if not isinstance(other, type(self)):
            raise TypeError(
                f"{type(self).__name__}.{method}: expected another {type(self).__name__} of the same "
                f"backend, got {type(other).__module__}.{type(other).__name__}"
            )
        return other

    def _product(self, a: Any, b: Any) -> Any:
        # float16 and bfloat16 multiplied in float32, as the functions compute them, and rounded once
        compute = self._dq._B.compute_dtype(a.dtype)
        if compute == a.dtype:
            return self._native.matmul(a, b)
        astype = self._native.astype
        return astype(self._native.matmul(astype(a, compute), astype(b, compute)), a.dtype)

    # --- the stored array ---

    @property
    def matrix(self) -> Any:
        """The stored matrices, shape ``(*shape, n, n)``: the array to hand to an optimiser or a
        function (no copy)."""
        return self._matrix

    def as_matrix(self) -> Any:
        """The matrices, shape ``(*shape, n, n)`` (the stored array, no copy)."""
        return self._matrix

    @property
    def shape(self) -> tuple[int, ...]:
        """The batch shape: the stored array's shape without its two matrix axes."""
        return tuple(self._matrix.shape[:-2])

    @property
    def ndim(self) -> int:
        """The number of batch axes."""
        return len(self.shape)

    @property
    def dtype(self) -> Any:
        """The stored array's dtype."""
        return self._matrix.dtype

    @property
    def device(self) -> Any:
        """The device of the stored array (``"cpu"`` on NumPy; ``None`` for an abstract jax value)."""
        return self._native.device(self._matrix)

    def __len__(self) -> int:
        if not self.shape:
            raise TypeError(f"len() of an unbatched {type(self).__name__}")
        return self.shape[0]

    def __iter__(self: G) -> Iterator[G]:
        # explicit: jax clamps an index out of range instead of raising IndexError
        for i in range(len(self)):
            yield self[i]

    def __getitem__(self: G, index: Any) -> G:
        """Index or slice the batch axes as an array is indexed (``T[0]``, ``T[:, 1:]``, ``T[..., None]``,
        a boolean mask); the matrix axes are never indexed."""
        index = index if isinstance(index, tuple) else (index,)
        return self._wrap(self._matrix[(*index, slice(None), slice(None))])

    def reshape(self: G, *shape: Any) -> G:
        """The same matrices with batch shape ``shape`` (``reshape(2, -1)`` or ``reshape((2, -1))``)."""
        batch = tuple(shape[0]) if len(shape) == 1 and not isinstance(shape[0], int) else tuple(shape)
        return self._wrap(self._matrix.reshape((*batch, self._size, self._size)))

    def broadcast_to(self: G, shape: Sequence[int]) -> G:
        """The matrices broadcast to batch shape ``shape`` (a view where the backend has views)."""
        return self._wrap(self._native.broadcast_to(self._matrix, (*shape, self._size, self._size)))

    @classmethod
    def concatenate(cls: type[G], items: Sequence[G], axis: int = 0) -> G:
        """Join objects along an existing batch axis (their other batch axes equal)."""
        for item in items:
            if not isinstance(item, cls):
                raise TypeError(
                    f"{cls.__name__}.concatenate: expected {cls.__name__}s, got {type(item).__name__}"
                )
        return cls._wrap(cls._native.concatenate([i._matrix for i in items], _batch_axis(axis)))

    @classmethod
    def stack(cls: type[G], items: Sequence[G], axis: int = 0) -> G:
        """Join objects of one batch shape along a new batch axis."""
        for item in items:
            if not isinstance(item, cls):
                raise TypeError(f"{cls.__name__}.stack: expected {cls.__name__}s, got {type(item).__name__}")
        return cls._wrap(cls._native.stack([i._matrix for i in items], _batch_axis(axis)))

    def astype(self: G, dtype: Any) -> G:
        """The matrices cast to ``dtype``."""
        return self._wrap(self._native.astype(self._matrix, dtype))

    def to(self: G, *args: Any, **kwargs: Any) -> G:
        """torch: ``Tensor.to`` of the stored tensor (a device, a dtype, or both); NumPy and jax have
        no ``to`` (use ``astype``, or ``jax.device_put`` on the object: it is a pytree)."""
        return self._wrap(self._matrix.to(*args, **kwargs))

    def detach(self: G) -> G:
        """torch: the object on ``Tensor.detach()`` of the stored tensor (jax: ``jax.lax.stop_gradient``
        of the object, a pytree)."""
        return self._wrap(self._matrix.detach())

    def allclose(self, other: Any, *, rtol: float = 1e-5, atol: float = 1e-8) -> bool:
        """Whether the stored matrices are close entrywise (the backend's ``allclose``, batch shapes
        broadcast), for tests: two rotations that are equal are equal matrices."""
        other = self._same("allclose", other)
        return bool(self._native.allclose(self._matrix, other._matrix, rtol, atol))

    def __repr__(self) -> str:
        device = self.device
        where = "" if device is None else f", device={device}"
        return f"{type(self).__name__}(shape={self.shape}, dtype={self.dtype}{where})"

    def __eq__(self, other: object) -> bool:
        # Identity, not entrywise: arrays compare entrywise to arrays, not to one bool (use allclose).
        return self is other

    __hash__ = object.__hash__


class SO3(_Group):
    """Rotations ``(...)``: rotation matrices ``(..., 3, 3)``, active, acting on column vectors.

    ``a @ b`` composes (apply ``b`` first, then ``a``: the matrix ``a.matrix @ b.matrix``), ``a @ points``
    rotates points ``(..., 3)``. scipy's ``Rotation`` writes the product ``a * b``; jaxlie's ``SO3``
    stores a quaternion, diffquat the matrix (see ``diffquat._objects``). Build one with
    ``from_quaternion``, ``from_matrix``, ``from_axis_angle``, ``from_euler_angles``,
    ``from_rotation_6d``, ``exp``, ``identity`` or ``random``.
    """

    __slots__ = ()
    _size = 3

    # --- construction ---

    @classmethod
    def from_matrix(cls: type[G], matrix: Any) -> G:
        """From rotation matrices ``(..., 3, 3)``, stored as they are (scipy's ``from_matrix``
        orthonormalises: pass ``special_procrustes(m)`` for that)."""
        return cls(matrix)

    @classmethod
    def from_quaternion(cls: type[G], q: Any, *, scalar_first: bool = True) -> G:
        """From quaternions ``(..., 4)`` of any norm (``quaternion_to_matrix``); scipy's ``from_quat``
        is scalar last by default, jaxlie's ``SO3(wxyz)`` scalar first."""
        return cls._wrap(
            cls._call("from_quaternion", cls._dq.quaternion_to_matrix, q, scalar_first=scalar_first)
        )

    @classmethod
    def from_axis_angle(cls: type[G], axis_angle: Any) -> G:
        """From rotation vectors ``(..., 3)``, angle in radians (scipy's ``from_rotvec``,
        ``axis_angle_to_matrix``)."""
        return cls._wrap(cls._call("from_axis_angle", cls._dq.axis_angle_to_matrix, axis_angle))

    @classmethod
    def from_euler_angles(
        cls: type[G], angles: Any, convention: EulerConvention, *, degrees: bool = False
    ) -> G:
        """From Euler angles ``(..., 3)`` in a convention (scipy's ``from_euler(seq, angles)``; jaxlie's
        ``from_rpy_radians(roll, pitch, yaw)`` is ``convention="xyz"`` with ``angles = (roll, pitch,
        yaw)``)."""
        fn = cls._dq.euler_angles_to_matrix
        return cls._wrap(cls._call("from_euler_angles", fn, angles, convention, degrees=degrees))

    @classmethod
    def from_rotation_6d(cls: type[G], d6: Any, *, layout: Rotation6DLayout = "columns") -> G:
        """From 6D vectors ``(..., 6)`` (Gram-Schmidt, ``rotation_6d_to_matrix``)."""
        return cls._wrap(cls._call("from_rotation_6d", cls._dq.rotation_6d_to_matrix, d6, layout=layout))

    @classmethod
    def exp(cls: type[G], omega: Any) -> G:
        """The exponential of rotation vectors ``(..., 3)`` (``so3_exp``; jaxlie's ``SO3.exp``)."""
        return cls._wrap(cls._call("exp", cls._dq.so3_exp, omega))

    @classmethod
    def identity(cls: type[G], shape: int | Sequence[int] = (), **factory: Any) -> G:
        """Identity rotations of batch shape ``shape``; ``dtype=`` (and ``device=`` on torch) as the
        backend's ``random_quaternions`` takes them."""
        return cls._wrap(cls._native.identity(3, shape, **factory))

    @classmethod
    def random(cls: type[G], shape: int | Sequence[int] = (), **source: Any) -> G:
        """Rotations uniform over SO(3), batch shape ``shape``, from the backend's own random source
        (``rng=`` on NumPy, ``generator=`` on torch, ``key=`` on jax, required there) and factory
        keywords (``dtype=``, ``device=`` on torch), as ``random_quaternions`` takes them (scipy's
        ``Rotation.random``, jaxlie's ``SO3.sample_uniform``)."""
        q = cls._call("random", cls._dq.random_quaternions, shape, **source)
        return cls._wrap(cls._dq.quaternion_to_matrix(q))

    # --- conversion ---

    def as_quaternion(self, *, scalar_first: bool = True) -> Any:
        """Unit quaternions ``(..., 4)``, canonical sign (``matrix_to_quaternion``; scipy's ``as_quat``,
        scalar last by default; jaxlie's ``wxyz``)."""
        return self._dq.matrix_to_quaternion(self._matrix, scalar_first=scalar_first)

    def as_axis_angle(self) -> Any:
        """Rotation vectors ``(..., 3)``, angle in [0, pi] (``matrix_to_axis_angle``; scipy's
        ``as_rotvec``)."""
        return self._dq.matrix_to_axis_angle(self._matrix)

    def as_euler_angles(self, convention: EulerConvention, *, degrees: bool = False) -> Any:
        """Euler angles ``(..., 3)`` (``matrix_to_euler_angles``; scipy's ``as_euler``)."""
        return self._call(
            "as_euler_angles", self._dq.matrix_to_euler_angles, self._matrix, convention, degrees=degrees
        )

    def as_rotation_6d(self, *, layout: Rotation6DLayout = "columns") -> Any:
        """6D vectors ``(..., 6)`` (``matrix_to_rotation_6d``)."""
        return self._call("as_rotation_6d", self._dq.matrix_to_rotation_6d, self._matrix, layout=layout)

    def log(self) -> Any:
        """Rotation vectors ``(..., 3)`` (``so3_log``; jaxlie's ``log``)."""
        return self._dq.so3_log(self._matrix)

    # --- the group ---

    def compose(self: G, other: Any) -> G:
        """``self @ other``: the product ``R_self R_other`` (apply ``other`` first), batch shapes
        broadcast (scipy's ``self * other``, jaxlie's ``self @ other``); float16 and bfloat16 are
        multiplied in float32."""
        if not isinstance(other, type(self)):
            raise TypeError(
                f"SO3.compose: expected an SO3 of the same backend, got {type(other).__module__}."
                f"{type(other).__name__} (an SE3 takes a rotation as SE3.from_rotation_translation(R, t))"
            )
        a, b = self._matrix, other._matrix
        if not (a.dtype == b.dtype and broadcasts([a.shape[:-2], b.shape[:-2]])):
            # the functions' checks and promotion (their errors, named SO3.compose); same dtypes and
            # broadcasting batches, the common case, skip them: torch's promote_types is an operation
            (a, b), _ = self._dq._B.validate("SO3.compose", a, b)
        return self._wrap(self._product(a, b))

    def apply(self, points: Any) -> Any:
        """Rotated points ``R p``, shape ``(..., 3)``; the batch shapes broadcast (``R @ p[..., None]``,
        scipy's and jaxlie's ``apply``)."""
        r, p = self._matrix, points
        if not (
            isinstance(p, self._native.array)
            and p.dtype == r.dtype
            and p.shape[-1:] == (3,)
            and broadcasts([r.shape[:-2], p.shape[:-1]])
        ):
            (r, p), _ = self._dq._B.validate("SO3.apply", r, p)  # as in compose
        return self._product(r, p[..., None])[..., 0]

    def __matmul__(self, other: Any) -> Any:
        """``a @ b`` composes two ``SO3``; ``a @ points`` rotates points ``(..., 3)``."""
        if isinstance(other, _Group):
            return self.compose(other)
        return self.apply(other)

    def inverse(self: G) -> G:
        """The inverse rotations: the transposes ``R^T`` (scipy's ``inv``)."""
        return self._wrap(self._matrix.swapaxes(-1, -2))

    def adjoint(self) -> Any:
        """The adjoint ``(..., 3, 3)``, which on SO(3) is ``R`` itself (jaxlie's ``adjoint``)."""
        return self._matrix

    def plus(self: G, delta: Any, *, side: Side = "right") -> G:
        """``R exp(delta)`` (``side="right"``) or ``exp(delta) R`` (``"left"``), rotation vectors
        ``delta`` ``(..., 3)`` (``so3_plus``; jaxlie's ``manifold.rplus``)."""
        return self._wrap(self._call("plus", self._dq.so3_plus, self._matrix, delta, side=side))

    def minus(self, other: Any, *, side: Side = "right") -> Any:
        """The rotation vector ``(..., 3)`` from ``other`` to ``self``: ``log(R_other^T R_self)``
        (``side="right"``) or ``log(R_self R_other^T)`` (``"left"``), so that
        ``other.plus(self.minus(other)) == self`` (``so3_minus``; jaxlie's ``manifold.rminus(other,
        self)``)."""
        other = self._same("minus", other)
        return self._call("minus", self._dq.so3_minus, self._matrix, other._matrix, side=side)

    def interpolate(self: G, other: G, t: Any) -> G:
        """The geodesic ``R_self exp(t log(R_self^T R_other))`` at parameters ``t`` (a number or an
        array broadcasting against the batch shape; 0 gives ``self``, 1 ``other``): slerp of the
        rotations, as ``so3_plus(R, t * so3_minus(R_other, R))`` (scipy's ``Slerp``)."""
        other = self._same("interpolate", other)
        delta = self._call("interpolate", self._dq.so3_minus, other._matrix, self._matrix)
        return self._wrap(
            self._call("interpolate", self._dq.so3_plus, self._matrix, self._native.scale(t, delta))
        )

    def mean(self: G, weights: Any = None, *, method: MeanMethod = "chordal") -> G:
        """The mean over the last batch axis, batch shape ``shape[:-1]`` (``rotation_mean``; scipy's
        ``mean`` of a 1-D stack)."""
        return self._wrap(self._call("mean", self._dq.rotation_mean, self._matrix, weights, method=method))

    def distance(self, other: Any) -> Any:
        """The geodesic distance to ``other``, the rotation angle of ``R_self^T R_other`` in [0, pi],
        shape ``(...)`` (``matrix_geodesic_distance``; scipy's ``(a.inv() * b).magnitude()``)."""
        other = self._same("distance", other)
        return self._call("distance", self._dq.matrix_geodesic_distance, self._matrix, other._matrix)


class SE3(_Group):
    """Rigid transforms (poses) ``(...)``: matrices ``[[R, t], [0, 1]]`` ``(..., 4, 4)``, column vectors.

    ``a @ b`` composes (``se3_compose``: apply ``b`` first), ``a @ points`` transforms points ``(..., 3)``
    (``se3_apply``: ``R p + t``). scipy's ``RigidTransform`` writes the product ``a * b``; jaxlie's
    ``SE3`` stores a quaternion and a translation, diffquat the matrix that the ``se3_*`` functions
    take (see ``diffquat._objects``). Tangent vectors are twists ``(rho, phi)`` ``(..., 6)``,
    translation first (jaxlie's order). Build one with ``from_matrix``, ``from_rotation_translation``,
    ``from_pose``, ``exp``, ``identity`` or ``random``.
    """

    __slots__ = ()
    _size = 4

    # --- construction ---

    @classmethod
    def from_matrix(cls: type[G], matrix: Any) -> G:
        """From poses ``(..., 4, 4)``, stored as they are (the functions never read the bottom row)."""
        return cls(matrix)

    @classmethod
    def from_rotation_translation(cls: type[G], rotation: Any, translation: Any) -> G:
        """From rotations (an ``SO3`` or matrices ``(..., 3, 3)``) and translations ``(..., 3)``, batch
        shapes broadcast (``se3_from_rotation_translation``; jaxlie's ``from_rotation_and_translation``,
        scipy's ``from_components``)."""
        if isinstance(rotation, SE3):
            raise TypeError("SE3.from_rotation_translation: expected an SO3 or rotation matrices, got an SE3")
        r = rotation.matrix if isinstance(rotation, SO3) else rotation
        fn = cls._dq.se3_from_rotation_translation
        return cls._wrap(cls._call("from_rotation_translation", fn, r, translation))

    @classmethod
    def from_pose(cls: type[G], pose: Any, *, layout: PoseLayout) -> G:
        """From 7-vectors ``(..., 7)``, a quaternion and a translation in ``layout`` (``pose_to_matrix``;
        jaxlie's ``SE3(wxyz_xyz)`` is ``layout="wxyz_xyz"``)."""
        return cls._wrap(cls._call("from_pose", cls._dq.pose_to_matrix, pose, layout=layout))

    @classmethod
    def exp(cls: type[G], xi: Any) -> G:
        """The exponential of twists ``(rho, phi)`` ``(..., 6)`` (``se3_exp``; jaxlie's ``SE3.exp``)."""
        return cls._wrap(cls._call("exp", cls._dq.se3_exp, xi))

    @classmethod
    def identity(cls: type[G], shape: int | Sequence[int] = (), **factory: Any) -> G:
        """Identity poses of batch shape ``shape``; ``dtype=`` (and ``device=`` on torch)."""
        return cls._wrap(cls._native.identity(4, shape, **factory))

    @classmethod
    def random(cls: type[G], shape: int | Sequence[int] = (), **source: Any) -> G:
        """Poses with rotations uniform over SO(3) and translations standard normal, batch shape
        ``shape``, from the backend's own random source (``rng=`` on NumPy, ``generator=`` on torch,
        ``key=`` on jax) and factory keywords (``dtype=``, ``device=`` on torch). jaxlie's
        ``sample_uniform`` draws the translation uniform in [-1, 1]^3."""
        q, t = cls._native.draw(cls._dq, shape, **source)
        r = cls._dq.quaternion_to_matrix(q)
        return cls._wrap(cls._dq.se3_from_rotation_translation(r, t))

    # --- conversion ---

    def as_pose(self, *, layout: PoseLayout) -> Any:
        """7-vectors ``(..., 7)`` in ``layout`` (``matrix_to_pose``; jaxlie's ``parameters()`` is
        ``layout="wxyz_xyz"``)."""
        return self._call("as_pose", self._dq.matrix_to_pose, self._matrix, layout=layout)

    def as_rotation_translation(self) -> tuple[SO3, Any]:
        """The rotation (an ``SO3``) and the translation ``(..., 3)`` (``se3_to_rotation_translation``;
        scipy's ``as_components``)."""
        r, t = self._dq.se3_to_rotation_translation(self._matrix)
        return self._dq.SO3._wrap(r), t

    def rotation(self) -> SO3:
        """The rotation part, an ``SO3`` (jaxlie's ``rotation()``, scipy's ``rotation``)."""
        return self.as_rotation_translation()[0]

    def translation(self) -> Any:
        """The translation part ``(..., 3)`` (jaxlie's ``translation()``, scipy's ``translation``)."""
        return self.as_rotation_translation()[1]

    def log(self) -> Any:
        """Twists ``(rho, phi)`` ``(..., 6)`` (``se3_log``; jaxlie's ``log``)."""
        return self._dq.se3_log(self._matrix)

    # --- the group ---

    def compose(self: G, other: Any) -> G:
        """``self @ other``: ``T_self T_other`` (apply ``other`` first), batch shapes broadcast
        (``se3_compose``; scipy's ``self * other``, jaxlie's ``self @ other``)."""
        if not isinstance(other, type(self)):
            raise TypeError(
                f"SE3.compose: expected an SE3 of the same backend, got {type(other).__module__}."
                f"{type(other).__name__} (make a pose of a rotation with SE3.from_rotation_translation(R, t))"
            )
        return self._wrap(self._call("compose", self._dq.se3_compose, self._matrix, other._matrix))

    def apply(self, points: Any) -> Any:
        """Transformed points ``R p + t``, shape ``(..., 3)``; the batch shapes broadcast (a pose and
        points ``(N, 3)`` give ``(N, 3)``; poses ``(B,)`` and clouds ``(B, N, 3)``: ``T[:, None] @ p``)
        (``se3_apply``; scipy's and jaxlie's ``apply``)."""
        return self._call("apply", self._dq.se3_apply, self._matrix, points)

    def __matmul__(self, other: Any) -> Any:
        """``a @ b`` composes two ``SE3``; ``a @ points`` transforms points ``(..., 3)``."""
        if isinstance(other, _Group):
            return self.compose(other)
        return self.apply(other)

    def inverse(self: G) -> G:
        """The inverse poses ``[[R^T, -R^T t], [0, 1]]`` (``se3_inverse``; scipy's ``inv``)."""
        return self._wrap(self._dq.se3_inverse(self._matrix))

    def adjoint(self) -> Any:
        """The adjoint ``(..., 6, 6)`` acting on twists ``(rho, phi)`` (``se3_adjoint``; jaxlie's
        ``adjoint``)."""
        return self._dq.se3_adjoint(self._matrix)

    def plus(self: G, delta: Any, *, side: Side = "right") -> G:
        """``T exp(delta)`` (``side="right"``) or ``exp(delta) T`` (``"left"``), twists ``(..., 6)``
        (``se3_plus``; jaxlie's ``manifold.rplus``)."""
        return self._wrap(self._call("plus", self._dq.se3_plus, self._matrix, delta, side=side))

    def minus(self, other: Any, *, side: Side = "right") -> Any:
        """The twist ``(..., 6)`` from ``other`` to ``self``, ``log(T_other^-1 T_self)``
        (``side="right"``) or ``log(T_self T_other^-1)`` (``"left"``): ``other.plus(self.minus(other))
        == self`` (``se3_minus``; jaxlie's ``manifold.rminus(other, self)``)."""
        other = self._same("minus", other)
        return self._call("minus", self._dq.se3_minus, self._matrix, other._matrix, side=side)

    def interpolate(self: G, other: G, t: Any, *, mode: SE3Interpolation = "screw") -> G:
        """Poses between ``self`` (``t = 0``) and ``other`` (``t = 1``), ``t`` a number or an array
        broadcasting against the batch shape (``se3_interpolate``: ``"screw"`` is scipy's
        ``T1 * (T1.inv() * T2) ** t``, ``"decoupled"`` slerp and a straight line)."""
        other = self._same("interpolate", other)
        fn = self._dq.se3_interpolate
        return self._wrap(self._call("interpolate", fn, self._matrix, other._matrix, t, mode=mode))

    def mean(self: G, weights: Any = None) -> G:
        """The mean over the last batch axis, batch shape ``shape[:-1]`` (``se3_mean``; scipy's
        ``RigidTransform`` has none)."""
        return self._wrap(self._call("mean", self._dq.se3_mean, self._matrix, weights))

    def distance(self, other: Any) -> tuple[Any, Any]:
        """The rotation angle ``(...)`` between the two rotations, in [0, pi], and the distance
        ``(...)`` between the two translations (``matrix_geodesic_distance`` and the norm of the
        difference): two numbers of two units, not one made-up metric."""
        other = self._same("distance", other)
        r1, t1 = self._dq.se3_to_rotation_translation(self._matrix)
        r2, t2 = self._dq.se3_to_rotation_translation(other._matrix)
        angle = self._call("distance", self._dq.matrix_geodesic_distance, r1, r2)
        return angle, self._native.norm(t1 - t2)


@dataclass(frozen=True)
class Native:
    """One backend's array primitives that are no diffquat function.

    Attributes:
        xp: the array namespace (``numpy``, ``torch``, ``jax.numpy``).
        array: the backend's array type.
        identity: ``(n, shape, **factory)`` -> identity matrices ``(*shape, n, n)``.
        draw: ``(module, shape, **source)`` -> unit quaternions ``(*shape, 4)`` and standard normal
            translations ``(*shape, 3)`` from the backend's random source.
        device: the device of an array (``None`` where it has none to tell).
        astype: casts an array to a dtype.
        match_rank: whether broadcasting needs equal ranks (jax, whose rank promotion may be set to
            raise): unit axes are then put in front of the lower-rank operand, as the functions do.
    """

    xp: Any
    array: type
    identity: Callable[..., Any]
    draw: Callable[..., tuple[Any, Any]]
    device: Callable[[Any], Any]
    astype: Callable[[Any, Any], Any]
    match_rank: bool = False

    def _ranked(self, a: Any, b: Any) -> tuple[Any, Any]:
        if not self.match_rank or a.ndim == b.ndim:
            return a, b
        rank = max(a.ndim, b.ndim)
        return tuple(self.xp.reshape(x, (1,) * (rank - x.ndim) + tuple(x.shape)) for x in (a, b))

    def matmul(self, a: Any, b: Any) -> Any:
        return self.xp.matmul(*self._ranked(a, b))

    def scale(self, t: Any, v: Any) -> Any:
        if isinstance(t, int | float) and not isinstance(t, bool):
            return t * v
        t = self.xp.asarray(t) if not hasattr(t, "ndim") else t
        a, b = self._ranked(t[..., None], v)
        return a * b

    def broadcast_to(self, x: Any, shape: tuple[int, ...]) -> Any:
        return self.xp.broadcast_to(x, shape)

    def concatenate(self, xs: list[Any], axis: int) -> Any:
        return self.xp.concatenate(xs, axis=axis)

    def stack(self, xs: list[Any], axis: int) -> Any:
        return self.xp.stack(xs, axis)

    def allclose(self, a: Any, b: Any, rtol: float, atol: float) -> Any:
        return self.xp.allclose(*self._ranked(a, b), rtol=rtol, atol=atol)

    def norm(self, x: Any) -> Any:
        return (
            self.xp.linalg.vector_norm(x, axis=-1)
            if self.xp.__name__ != "torch"
            else self.xp.linalg.vector_norm(x, dim=-1)
        )


def bind(module: Any, native: Native) -> tuple[type[SO3], type[SE3]]:
    """``SO3`` and ``SE3`` bound to a backend module (its functions and its ``_B``), named as that
    module's classes.

    ``native`` holds the few array primitives that are no diffquat function (:class:`Native`).
    """
    classes = []
    for base in (SO3, SE3):
        cls = type(
            base.__name__,
            (base,),
            {
                "__slots__": (),
                "__module__": module.__name__,
                "__doc__": base.__doc__,
                "_dq": module,
                "_native": native,
            },
        )
        cls.__qualname__ = base.__name__
        classes.append(cls)
    return classes[0], classes[1]
