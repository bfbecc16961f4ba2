"""Side-by-side benchmark of diffquat against its peers, with a memory-bandwidth roofline and an
accuracy table from the same run. ``python -m benchmarks.run [--quick] [--out DIR]``.

Every method is timed in float32 on the same rotations, forward and forward + backward, at each batch
size N. Times are medians over interleaved blocks (block b of every method runs before block b + 1 of
any, in an order that rotates from block to block), so slow drifts of a shared machine, and what one
method leaves behind for the next, hit all methods alike; the first call (warm-up, and for
``torch.compile``/``jax.jit`` the compilation) is reported apart. The roofline row is a tensor copy that
moves the same bytes as the conversion (input read + output written; forward + backward adds the
input and the cotangent read and the input gradient written): each time is also a fraction of it.
The peers are benchmark-only dependencies (the ``bench`` extra); a missing one is left out and named.
Every diffquat row evaluates the library's one formula (torch's two conversions as
``autograd.Function``s with their derivatives written out in eager mode, jax's ``matrix_to_quaternion``
as a ``custom_jvp``); each path (torch eager, ``torch.compile``, ``jax.jit``, numpy) is set against the
fastest peer on that path, and every cell below 1.0x is listed in the report.

The per-call cost of validation and dispatch is measured apart at N = 1 (:func:`overhead`): each
backend's public conversion beside the same conversion called without the argument checks and beside
the bare core formula, side by side in rotated blocks.

The Lie functions (``so3_*``, ``quaternion_plus``) are timed against the peers that have them: jaxlie,
kornia, pypose and theseus' Lie library torchlie (``theseus-ai`` itself builds C++ extensions against
the installed torch at install time; its SO(3) is torchlie's). The two-argument ``so3_plus`` and
``quaternion_plus`` take one packed input per call, ``(N, 12)`` (the matrix row-major, then the
rotation vector) or ``(N, 7)`` (the quaternion, then the rotation vector), split by every method alike.

The further conversions (``rotation_6d_to_matrix``, whose input is the two columns, and the Euler
angles in one convention, ``EULER``) and the quaternion operations (``quaternion_multiply``,
``quaternion_apply``, ``quaternion_slerp``, ``quaternion_geodesic_distance``,
``matrix_geodesic_distance``) are timed the same way; the two-argument ones take one packed input too
(``PACKED``), whose second rotation is the first times the case's, so that the accuracy table's edge
cases (0, 1e-10, near and at pi) are the relative rotation. Where a peer lacks the operation, or
computes it wrongly for this benchmark, ``GAPS`` says why.
"""

from __future__ import annotations

import argparse
import functools
import json
import os
import platform
import statistics
import sys
import time
import warnings
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
from scipy.spatial.transform import Rotation

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT / "tests"))

import cases  # noqa: E402  (the test suite's named cases: the accuracy table runs on them)

FULL_SIZES = (1, 64, 4096, 262144, 4194304)
QUICK_SIZES = (1, 64)
# Floats per rotation of each representation.
WIDTH = {
    "quaternion": 4,
    "matrix": 9,
    "rotvec": 3,
    "jacobian": 9,
    "matrix+rotvec": 12,
    "quaternion+rotvec": 7,
    "rotation_6d": 6,
    "euler": 3,
    "vector": 3,
    "angle": 1,
    "quaternion+quaternion": 8,
    "quaternion+vector": 7,
    "quaternion+quaternion+t": 9,
    "matrix+matrix": 18,
}
# The Euler angles' convention of the Euler rows (scipy's rule: lower case extrinsic): roll, pitch, yaw
# about the fixed x, y, z axes. Every peer has it: jaxlie's rpy, roma's "xyz", pytorch-kinematics'
# intrinsic "ZYX" with the angles reversed (it has intrinsic sequences only), scipy's "xyz".
EULER = "xyz"


# An expected output, or a tuple of outputs that are all right (the accuracy table takes the nearest).
Reference = np.ndarray | tuple[np.ndarray, ...]


@dataclass
class Method:
    """One implementation of one operation. ``prep`` turns float32 NumPy input (diffquat's convention:
    scalar-first quaternions) into the library's native input; ``post`` turns its output back."""

    label: str
    family: str  # "torch", "jax" or "numpy" (forward only)
    fn: Callable[[Any], Any]
    prep: Callable[[np.ndarray], np.ndarray] = lambda x: x
    post: Callable[[np.ndarray], np.ndarray] = lambda y: y
    compiled: bool = False


@dataclass
class OpSpec:
    name: str
    source: str  # input representation
    target: str  # output representation
    methods: list[Method]
    skipped: list[str]
    # float64 input -> the expected float64 output, for the accuracy table (default: the rotation of the
    # case, in the target representation)
    reference: Callable[[np.ndarray], Reference] | None = None
    notes: list[str] = field(default_factory=list)


def _xyzw(q: np.ndarray) -> np.ndarray:
    return np.ascontiguousarray(q[..., [1, 2, 3, 0]])


def _wxyz(q: np.ndarray) -> np.ndarray:
    return np.ascontiguousarray(q[..., [3, 0, 1, 2]])


def _try(skipped: list[str], label: str, build: Callable[[], Method | list[Method]]) -> list[Method]:
    try:
        built = build()
    except (ImportError, AttributeError) as error:  # a peer not installed, or without this operation
        skipped.append(f"{label} ({type(error).__name__}: {error})")
        return []
    return built if isinstance(built, list) else [built]


def seed_quaternion_to_matrix(xp: Any, q: Any) -> Any:
    """The baseline of issue 46: the textbook matrix of ``q * rsqrt(|q|^2)`` (no guard of any kind:
    the zero quaternion is NaN, norms beyond ~1e19 overflow in float32), in any array namespace."""
    u = q / xp.sqrt(xp.sum(q * q, axis=-1, keepdims=True))
    w, x, y, z = u[..., 0], u[..., 1], u[..., 2], u[..., 3]
    rows = [
        1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y),
        2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x),
        2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y),
    ]  # fmt: skip
    return xp.stack(rows, axis=-1).reshape(*q.shape[:-1], 3, 3)


def shepperd_matrix_to_quaternion(xp: Any, m: Any) -> Any:
    """The baseline of issue 46: Shepperd's method as commonly written, the largest of the four pivots
    under a square root, the candidate of each pivot built and the largest selected (``where``), no
    range scaling and no canonical sign (w >= 0 where the trace pivot wins)."""
    m00, m01, m02 = m[..., 0, 0], m[..., 0, 1], m[..., 0, 2]
    m10, m11, m12 = m[..., 1, 0], m[..., 1, 1], m[..., 1, 2]
    m20, m21, m22 = m[..., 2, 0], m[..., 2, 1], m[..., 2, 2]
    t = [1 + m00 + m11 + m22, 1 + m00 - m11 - m22, 1 - m00 + m11 - m22, 1 - m00 - m11 + m22]
    # 4 |q_k|; the pivots not chosen may be negative (their candidates are discarded)
    s = [2 * xp.sqrt(xp.abs(x)) for x in t]
    candidates = [
        (s[0] / 4, (m21 - m12) / s[0], (m02 - m20) / s[0], (m10 - m01) / s[0]),
        ((m21 - m12) / s[1], s[1] / 4, (m01 + m10) / s[1], (m02 + m20) / s[1]),
        ((m02 - m20) / s[2], (m01 + m10) / s[2], s[2] / 4, (m12 + m21) / s[2]),
        ((m10 - m01) / s[3], (m02 + m20) / s[3], (m12 + m21) / s[3], s[3] / 4),
    ]
    use01 = xp.maximum(t[0], t[1]) >= xp.maximum(t[2], t[3])
    use0, use2 = t[0] >= t[1], t[2] >= t[3]
    c0, c1, c2, c3 = candidates
    out = [xp.where(use01, xp.where(use0, c0[i], c1[i]), xp.where(use2, c2[i], c3[i])) for i in range(4)]
    return xp.stack(out, axis=-1)


# The formulas issue 46 sets the conversions against on every path (eager, compiled the same way as
# diffquat, jax.jit): label and formula(xp, x).
BASELINES: dict[str, tuple[str, Callable[[Any, Any], Any]]] = {
    "quaternion_to_matrix": ("seed formula on q rsqrt(|q|^2)", seed_quaternion_to_matrix),
    "matrix_to_quaternion": ("plain Shepperd formula", shepperd_matrix_to_quaternion),
}


def build_ops(quick: bool, dynamic: bool | None = None) -> list[OpSpec]:
    """Every operation with its methods. ``dynamic`` is ``torch.compile``'s (None: a static graph
    first, then a dynamic one once a second batch size comes)."""
    import jax
    import jax.numpy as jnp
    import torch

    import diffquat.jax as dqj
    import diffquat.numpy as dqn
    import diffquat.torch as dqt
    from diffquat import _core

    # Several batch sizes and modes: one static graph, then a dynamic-shape one (torch defaults).
    torch._dynamo.config.recompile_limit = 64
    torch._dynamo.config.accumulated_recompile_limit = 1024

    def compiled(fn: Callable[[Any], Any]) -> Callable[[Any], Any]:
        return torch.compile(fn, fullgraph=True, dynamic=dynamic)

    ops: list[OpSpec] = []
    # (name, source, target, peer builders). Axis-angle rows appear once diffquat has those functions.
    table: list[tuple[str, str, str, dict[str, Callable[[], Method | list[Method]]]]] = []

    def roma_q2m() -> Method:
        import roma

        # the normalising path (diffquat's takes any norm): quat_normalize, then the unit conversion
        return Method("roma", "torch", lambda q: roma.unitquat_to_rotmat(roma.quat_normalize(q)), prep=_xyzw)

    def roma_m2q() -> Method:
        import roma

        return Method("roma", "torch", roma.rotmat_to_unitquat, post=_wxyz)

    def kornia_q2m() -> Method:
        from kornia.geometry import conversions as kc

        return Method("kornia", "torch", kc.quaternion_to_rotation_matrix)

    def kornia_m2q() -> Method:
        from kornia.geometry import conversions as kc

        return Method("kornia", "torch", kc.rotation_matrix_to_quaternion)

    def pk_fn(name: str) -> Callable[[], Method]:
        def build() -> Method:
            import pytorch_kinematics as pk

            return Method("pytorch-kinematics", "torch", getattr(pk, name))

        return build

    def jaxlie_q2m() -> Method:
        import jaxlie

        # on q / |q|: jaxlie's SO3 assumes a unit quaternion
        return Method(
            "jaxlie (jit)", "jax", jax.jit(jax.vmap(lambda q: jaxlie.SO3(q / jnp.linalg.norm(q)).as_matrix()))
        )

    def jaxlie_m2q() -> Method:
        import jaxlie

        return Method("jaxlie (jit)", "jax", jax.jit(jax.vmap(lambda m: jaxlie.SO3.from_matrix(m).wxyz)))

    def jaxlie_aa2m() -> Method:
        import jaxlie

        return Method("jaxlie (jit)", "jax", jax.jit(jax.vmap(lambda v: jaxlie.SO3.exp(v).as_matrix())))

    def jaxlie_m2aa() -> Method:
        import jaxlie

        return Method("jaxlie (jit)", "jax", jax.jit(jax.vmap(lambda m: jaxlie.SO3.from_matrix(m).log())))

    def roma_fn(name: str) -> Callable[[], Method]:
        def build() -> Method:
            import roma

            return Method("roma", "torch", getattr(roma, name))

        return build

    def kornia_fn(name: str) -> Callable[[], Method]:
        def build() -> Method:
            from kornia.geometry import conversions as kc

            return Method("kornia", "torch", getattr(kc, name))

        return build

    def scipy_fn(kind: str) -> Callable[[], Method]:
        def build() -> Method:
            fns = {
                "q2m": lambda q: Rotation.from_quat(q).as_matrix(),
                "m2q": lambda m: Rotation.from_matrix(m).as_quat(canonical=True),
                "aa2m": lambda v: Rotation.from_rotvec(v).as_matrix(),
                "m2aa": lambda m: Rotation.from_matrix(m).as_rotvec(),
            }
            pre = _xyzw if kind == "q2m" else (lambda x: x)
            post = _wxyz if kind == "m2q" else (lambda y: y)
            return Method("scipy", "numpy", fns[kind], prep=pre, post=post)

        return build

    table.append(
        (
            "quaternion_to_matrix",
            "quaternion",
            "matrix",
            {"roma": roma_q2m, "kornia": kornia_q2m, "pytorch-kinematics": pk_fn("quaternion_to_matrix"),
             "jaxlie": jaxlie_q2m, "scipy": scipy_fn("q2m")},
        )
    )  # fmt: skip
    table.append(
        (
            "matrix_to_quaternion",
            "matrix",
            "quaternion",
            {"roma": roma_m2q, "kornia": kornia_m2q, "pytorch-kinematics": pk_fn("matrix_to_quaternion"),
             "jaxlie": jaxlie_m2q, "scipy": scipy_fn("m2q")},
        )
    )  # fmt: skip
    table.append(
        (
            "axis_angle_to_matrix",
            "rotvec",
            "matrix",
            {"roma": roma_fn("rotvec_to_rotmat"), "kornia": kornia_fn("axis_angle_to_rotation_matrix"),
             "pytorch-kinematics": pk_fn("axis_angle_to_matrix"), "jaxlie": jaxlie_aa2m,
             "scipy": scipy_fn("aa2m")},
        )
    )  # fmt: skip
    table.append(
        (
            "matrix_to_axis_angle",
            "matrix",
            "rotvec",
            {"roma": roma_fn("rotmat_to_rotvec"), "kornia": kornia_fn("rotation_matrix_to_axis_angle"),
             "pytorch-kinematics": pk_fn("matrix_to_axis_angle"), "jaxlie": jaxlie_m2aa,
             "scipy": scipy_fn("m2aa")},
        )
    )  # fmt: skip

    # Further conversions and the quaternion operations (issue 46). The two-argument rows take one
    # packed input, as so3_plus does (PACKED below); every method splits it alike. Each peer's output
    # agreed with diffquat's to 1e-14 in float64 on random inputs (the layout of each noted where it
    # differs); jaxlie has no slerp and no distance: they are composed from its group operations, as
    # its users would write them.
    def roma_6d() -> Method:
        import roma

        # the (N, 3, 2) matrix whose columns are a1 and a2
        return Method("roma", "torch", roma.special_gramschmidt, prep=_columns_6d)

    def pk_6d() -> Method:
        import pytorch_kinematics as pk

        # pytorch3d's layout: a1 and a2 become the rows of its result, the transpose of diffquat's
        # default (its "rows" layout); the same Gram-Schmidt, transposed back outside the timing
        return Method("pytorch-kinematics", "torch", pk.rotation_6d_to_matrix, post=_transpose)

    def euler(library: str, to_matrix: bool) -> Callable[[], Method]:
        def build() -> Method:
            if library == "roma":
                import roma

                if to_matrix:
                    return Method("roma", "torch", functools.partial(roma.euler_to_rotmat, EULER))
                return Method("roma", "torch", functools.partial(roma.rotmat_to_euler, EULER))
            if library == "pytorch-kinematics":
                import pytorch_kinematics as pk

                # intrinsic sequences only: extrinsic "xyz" is intrinsic "ZYX" with the angles reversed
                if to_matrix:
                    return Method(
                        library, "torch", lambda a: pk.euler_angles_to_matrix(a, "ZYX"), prep=_reversed
                    )
                return Method(library, "torch", lambda m: pk.matrix_to_euler_angles(m, "ZYX"), post=_reversed)
            if library == "jaxlie":
                import jax.numpy as jnp
                import jaxlie

                # roll, pitch, yaw about the fixed x, y, z axes: extrinsic "xyz"
                if to_matrix:
                    fn = jax.vmap(lambda a: jaxlie.SO3.from_rpy_radians(a[0], a[1], a[2]).as_matrix())
                else:
                    fn = jax.vmap(lambda m: jnp.stack(jaxlie.SO3.from_matrix(m).as_rpy_radians()))
                return Method("jaxlie (jit)", "jax", jax.jit(fn), compiled=True)
            if to_matrix:
                return Method("scipy", "numpy", lambda a: Rotation.from_euler(EULER, a).as_matrix())
            return Method("scipy", "numpy", lambda m: Rotation.from_matrix(m).as_euler(EULER))

        return build

    def quaternion_op(library: str, kind: str) -> Callable[[], Method]:
        """``kind``: "mul" (p q), "apply" (R(q) v), "slerp" (p, q, t) or "dist" (the angle of p* q),
        on PACKED's input of that operation."""

        def build() -> Method:
            if library == "roma":
                import roma

                fns: dict[str, Callable[[Any], Any]] = {
                    "mul": lambda x: roma.quat_product(*_split_pair(x)),
                    "apply": lambda x: roma.quat_action(*_split_quaternion(x)),
                    "dist": lambda x: roma.unitquat_geodesic_distance(*_split_pair(x)),
                }
                return Method("roma", "torch", fns[kind], prep=_xyzw_leading(kind), post=_wxyz_out(kind))
            if library == "pytorch-kinematics":
                import pytorch_kinematics as pk

                fns = {
                    # pk.quaternion_multiply also flips the product to w >= 0, a step diffquat's
                    # product does not take: its raw product is the same job
                    "mul": lambda x: pk.quaternion_raw_multiply(*_split_pair(x)),
                    "apply": lambda x: pk.quaternion_apply(*_split_quaternion(x)),
                }
                return Method(library, "torch", fns[kind])
            if library == "kornia":
                from kornia.geometry.liegroup import So3
                from kornia.geometry.quaternion import Quaternion

                fns = {
                    "mul": lambda x: (Quaternion(x[..., :4]) * Quaternion(x[..., 4:])).data,
                    "apply": lambda x: So3(Quaternion(x[..., :4])) * x[..., 4:],
                    "slerp": lambda x: Quaternion(x[..., :4]).slerp(Quaternion(x[..., 4:8]), x[..., 8]).data,
                }
                return Method("kornia", "torch", fns[kind])
            if library == "jaxlie":
                import jax.numpy as jnp
                import jaxlie

                def relative(x: Any) -> Any:  # p^-1 q
                    return jaxlie.SO3(x[:4]).inverse() @ jaxlie.SO3(x[4:8])

                fns = {
                    "mul": lambda x: (jaxlie.SO3(x[:4]) @ jaxlie.SO3(x[4:])).wxyz,
                    "apply": lambda x: jaxlie.SO3(x[:4]).apply(x[4:]),
                    "slerp": lambda x: (jaxlie.SO3(x[:4]) @ jaxlie.SO3.exp(x[8] * relative(x).log())).wxyz,
                    "dist": lambda x: jnp.linalg.norm(relative(x).log()),
                }
                return Method("jaxlie (jit)", "jax", jax.jit(jax.vmap(fns[kind])), compiled=True)
            if library == "pypose":
                import pypose as pp

                fns = {
                    "mul": lambda x: (pp.SO3(x[..., :4]) * pp.SO3(x[..., 4:])).tensor(),
                    "apply": lambda x: pp.SO3(x[..., :4]).Act(x[..., 4:]),
                }
                return Method("pypose", "torch", fns[kind], prep=_xyzw_leading(kind), post=_wxyz_out(kind))
            numpy_fns: dict[str, Callable[[Any], Any]] = {
                "mul": lambda x: (Rotation.from_quat(x[..., :4]) * Rotation.from_quat(x[..., 4:])).as_quat(),
                "apply": lambda x: Rotation.from_quat(x[..., :4]).apply(x[..., 4:]),
                "dist": lambda x: (
                    Rotation.from_quat(x[..., :4]).inv() * Rotation.from_quat(x[..., 4:])
                ).magnitude(),
            }
            return Method("scipy", "numpy", numpy_fns[kind], prep=_xyzw_leading(kind), post=_wxyz_out(kind))

        return build

    def matrix_distance(library: str) -> Callable[[], Method]:
        def build() -> Method:
            if library == "roma":
                import roma

                return Method("roma", "torch", lambda x: roma.rotmat_geodesic_distance(*_split_matrices(x)))
            if library == "pytorch-kinematics":
                import pytorch_kinematics as pk

                return Method(library, "torch", lambda x: pk.so3_relative_angle(*_split_matrices(x)))
            if library == "jaxlie":
                import jax.numpy as jnp
                import jaxlie

                def distance(x: Any) -> Any:
                    a, b = _split_matrices(x)
                    return jnp.linalg.norm(jaxlie.SO3.from_matrix(a.T @ b).log())

                return Method("jaxlie (jit)", "jax", jax.jit(jax.vmap(distance)), compiled=True)

            def scipy_distance(x: np.ndarray) -> np.ndarray:
                a, b = _split_matrices(x)
                return (Rotation.from_matrix(a).inv() * Rotation.from_matrix(b)).magnitude()

            return Method("scipy", "numpy", scipy_distance)

        return build

    table.append(
        ("rotation_6d_to_matrix", "rotation_6d", "matrix", {"roma": roma_6d, "pytorch-kinematics": pk_6d})
    )
    for name, source, target, to_matrix in (
        ("euler_angles_to_matrix", "euler", "matrix", True),
        ("matrix_to_euler_angles", "matrix", "euler", False),
    ):
        libraries = ("roma", "pytorch-kinematics", "jaxlie", "scipy")
        table.append((name, source, target, {lib: euler(lib, to_matrix) for lib in libraries}))
    for name, kind, libraries in (
        ("quaternion_multiply", "mul", ("roma", "pytorch-kinematics", "kornia", "jaxlie", "pypose", "scipy")),
        ("quaternion_apply", "apply", ("roma", "pytorch-kinematics", "kornia", "jaxlie", "pypose", "scipy")),
        ("quaternion_slerp", "slerp", ("kornia", "jaxlie")),
        ("quaternion_geodesic_distance", "dist", ("roma", "jaxlie", "scipy")),
    ):
        source, target = PACKED[name]
        table.append((name, source, target, {lib: quaternion_op(lib, kind) for lib in libraries}))
    libraries = ("roma", "pytorch-kinematics", "jaxlie", "scipy")
    table.append(
        ("matrix_geodesic_distance", *PACKED["matrix_geodesic_distance"],
         {lib: matrix_distance(lib) for lib in libraries})
    )  # fmt: skip

    # SO(3) as a Lie group. Each peer's own spelling of the operation; where a peer lacks one, the
    # reason is recorded (GAPS).
    def jaxlie_lie(kind: str) -> Callable[[], Method]:
        def build() -> Method:
            import jax.numpy as jnp
            import jaxlie
            from jaxlie._so3 import _SO3_jac_left, _SO3_jac_left_inv

            fns: dict[str, Callable[[Any], Any]] = {
                "exp": lambda v: jaxlie.SO3.exp(v).as_matrix(),
                "log": lambda m: jaxlie.SO3.from_matrix(m).log(),
                # private: what jaxlie's SE3 exp uses. Its second argument is returned as J_l below
                # theta^2 = 1e-5 (jaxlie passes exp(w)); given I here, so that the time is the
                # Jacobian's alone, as for every other method.
                "jl": lambda v: _SO3_jac_left(v, jnp.eye(3, dtype=v.dtype)),
                "jl_inv": _SO3_jac_left_inv,  # private: what jaxlie's SE3 log uses
                "plus": lambda x: (
                    jaxlie.SO3.from_matrix(x[:9].reshape(3, 3)) @ jaxlie.SO3.exp(x[9:])
                ).as_matrix(),
                "qplus": lambda x: jaxlie.manifold.rplus(jaxlie.SO3(x[:4]), x[4:]).wxyz,
            }
            return Method("jaxlie (jit)", "jax", jax.jit(jax.vmap(fns[kind])), compiled=True)

        return build

    def kornia_lie(kind: str) -> Callable[[], Method]:
        def build() -> Method:
            from kornia.geometry.liegroup import So3
            from kornia.geometry.quaternion import Quaternion

            fns: dict[str, Callable[[Any], Any]] = {
                "exp": lambda v: So3.exp(v).matrix(),
                "log": lambda m: So3.from_matrix(m).log(),
                "jl": So3.left_jacobian,
                "plus": lambda x: (So3.from_matrix(_split_matrix(x)[0]) * So3.exp(x[..., 9:])).matrix(),
                "qplus": lambda x: (So3(Quaternion(x[..., :4])) * So3.exp(x[..., 4:])).q.data,
            }
            return Method("kornia", "torch", fns[kind])

        return build

    def pypose_lie(kind: str) -> Callable[[], Method]:
        def build() -> Method:
            import pypose as pp
            from pypose.lietensor.operation import so3_Jl, so3_Jl_inv

            def from_matrix(m: Any) -> Any:
                return pp.mat2SO3(m, check=False)

            fns: dict[str, Callable[[Any], Any]] = {
                "exp": lambda v: pp.so3(v).Exp().matrix(),
                "log": lambda m: from_matrix(m).Log().tensor(),
                "jl": so3_Jl,
                "jl_inv": so3_Jl_inv,
                "plus": lambda x: (from_matrix(_split_matrix(x)[0]) * pp.so3(x[..., 9:]).Exp()).matrix(),
                # pypose's quaternions are scalar last
                "qplus": lambda x: (pp.SO3(x[..., :4]) * pp.so3(x[..., 4:]).Exp()).tensor(),
            }
            if kind == "qplus":
                return Method(
                    "pypose",
                    "torch",
                    fns[kind],
                    prep=lambda x: np.concatenate([_xyzw(x[..., :4]), x[..., 4:]], axis=-1),
                    post=_wxyz,
                )
            return Method("pypose", "torch", fns[kind])

        return build

    def torchlie_lie(kind: str) -> Callable[[], Method]:
        def build() -> Method:
            import torchlie.functional as tf

            fns: dict[str, Callable[[Any], Any]] = {
                "exp": tf.SO3.exp,
                "log": tf.SO3.log,
                "plus": lambda x: tf.SO3.compose(_split_matrix(x)[0], tf.SO3.exp(x[..., 9:])),
            }
            return Method(THESEUS, "torch", fns[kind])

        return build

    lie = {
        "so3_exp": ("rotvec", "matrix", "exp"),
        "so3_log": ("matrix", "rotvec", "log"),
        "so3_left_jacobian": ("rotvec", "jacobian", "jl"),
        "so3_left_jacobian_inverse": ("rotvec", "jacobian", "jl_inv"),
        "so3_plus": ("matrix+rotvec", "matrix", "plus"),
        "quaternion_plus": ("quaternion+rotvec", "quaternion", "qplus"),
    }
    builders = {"jaxlie": jaxlie_lie, "kornia": kornia_lie, "pypose": pypose_lie, THESEUS: torchlie_lie}
    for name, (source, target, kind) in lie.items():
        gaps = GAPS.get(name, {})
        table.append(
            (
                name,
                source,
                target,
                {peer: build(kind) for peer, build in builders.items() if peer not in gaps},
            )
        )

    for name, source, target, peers in table:
        if not hasattr(dqt, name):
            continue
        skipped: list[str] = [f"{peer} ({why})" for peer, why in GAPS.get(name, {}).items()]
        if name in LIE_REFERENCES:
            skipped.append(THESEUS_AI)
        adapt = ADAPTERS.get(name, lambda fn: fn)
        methods = [Method("diffquat torch eager", "torch", adapt(getattr(dqt, name)))]
        if not quick:
            methods.append(
                Method("diffquat torch.compile", "torch", compiled(adapt(getattr(dqt, name))), compiled=True)
            )
            if hasattr(_core, name):
                core_fn = getattr(_core, name)
                methods.append(
                    Method(
                        "hand-written formula, torch.compile",
                        "torch",
                        compiled(lambda x, f=core_fn: f(torch, x)),
                        compiled=True,
                    )
                )
        baseline = BASELINES.get(name)
        if baseline is not None:
            label, formula = baseline
            methods.append(Method(f"{label}, torch eager", "torch", functools.partial(formula, torch)))
            if not quick:
                methods.append(
                    Method(
                        f"{label}, torch.compile",
                        "torch",
                        compiled(functools.partial(formula, torch)),
                        compiled=True,
                    )
                )
            methods.append(
                Method(f"{label}, jax.jit", "jax", jax.jit(functools.partial(formula, jnp)), compiled=True)
            )
        methods.append(Method("diffquat jax.jit", "jax", jax.jit(adapt(getattr(dqj, name))), compiled=True))
        methods.append(Method("diffquat numpy", "numpy", adapt(getattr(dqn, name))))
        for label, build in peers.items():
            methods += _try(skipped, label, build)
        for m in methods:
            if m.label == "jaxlie (jit)":
                m.compiled = True
        ops.append(OpSpec(name, source, target, methods, skipped, REFERENCES.get(name)))
    return ops


# ---------------------------------------------------------------------------------------------------
# Inputs


def unit_quaternions(n: int, seed: int = 0) -> np.ndarray:
    return cases.uniform_quaternions(n, seed=seed)


def make_input(representation: str, q: np.ndarray) -> np.ndarray:
    """float64 input of the given representation for scalar-first unit quaternions ``q``. A packed
    "<group>+rotvec" input is a random rotation beside the rotation vector of ``q`` (so the accuracy
    table's edge cases are the perturbations: 0, 1e-10, near and at pi)."""
    rotation = Rotation.from_quat(_xyzw(q))
    if representation.endswith("+rotvec"):
        base = make_input(representation.split("+")[0], cases.uniform_quaternions(len(q), seed=21))
        return np.concatenate([base.reshape(len(q), -1), rotation.as_rotvec()], axis=-1)
    if representation in PAIRS:
        # a random rotation p, then p times the rotation of q: the relative rotation p^-1 (p q) is the
        # case's (0, 1e-10, near and at pi for the distances and slerp)
        p = Rotation.from_quat(_xyzw(cases.uniform_quaternions(len(q), seed=21)))
        if representation == "matrix+matrix":
            return np.concatenate(
                [p.as_matrix().reshape(-1, 9), (p * rotation).as_matrix().reshape(-1, 9)], -1
            )
        pair = [_wxyz(p.as_quat()), _wxyz((p * rotation).as_quat())]
        if representation == "quaternion+quaternion+t":
            pair.append(np.random.default_rng(23).uniform(size=(len(q), 1)))
        return np.concatenate(pair, axis=-1)
    if representation == "quaternion+vector":
        return np.concatenate([q, np.random.default_rng(22).normal(size=(len(q), 3))], axis=-1)
    if representation == "rotation_6d":  # the first two columns (diffquat's default layout)
        matrix = rotation.as_matrix()
        return np.concatenate([matrix[:, :, 0], matrix[:, :, 1]], axis=-1)
    if representation == "euler":
        return rotation.as_euler(EULER)
    if representation == "quaternion":
        return q
    if representation == "matrix":
        return rotation.as_matrix()
    return rotation.as_rotvec()


def _split_matrix(x: Any) -> tuple[Any, Any]:
    """A packed (..., 12) input: the (..., 3, 3) matrix and the (..., 3) rotation vector."""
    return x[..., :9].reshape(*x.shape[:-1], 3, 3), x[..., 9:]


def _split_quaternion(x: Any) -> tuple[Any, Any]:
    """A packed (..., 7) input: the (..., 4) quaternion and the (..., 3) rotation vector."""
    return x[..., :4], x[..., 4:]


# The packed input and the output of each two-argument operation (one input per call, split by every
# method alike, as so3_plus's): two scalar-first quaternions (N, 8); a quaternion and a vector (N, 7);
# two quaternions and t (N, 9); two matrices row-major (N, 18).
PACKED: dict[str, tuple[str, str]] = {
    "quaternion_multiply": ("quaternion+quaternion", "quaternion"),
    "quaternion_apply": ("quaternion+vector", "vector"),
    "quaternion_slerp": ("quaternion+quaternion+t", "quaternion"),
    "quaternion_geodesic_distance": ("quaternion+quaternion", "angle"),
    "matrix_geodesic_distance": ("matrix+matrix", "angle"),
}
PAIRS = ("quaternion+quaternion", "quaternion+quaternion+t", "matrix+matrix")


def _split_pair(x: Any) -> tuple[Any, Any]:
    """A packed (..., 8) input: the two (..., 4) quaternions."""
    return x[..., :4], x[..., 4:]


def _split_slerp(x: Any) -> tuple[Any, Any, Any]:
    """A packed (..., 9) input: the (..., 4) start and end quaternions and the (...) parameter t."""
    return x[..., :4], x[..., 4:8], x[..., 8]


def _split_matrices(x: Any) -> tuple[Any, Any]:
    """A packed (..., 18) input: the two (..., 3, 3) matrices."""
    shape = (*x.shape[:-1], 3, 3)
    return x[..., :9].reshape(shape), x[..., 9:].reshape(shape)


def _xyzw_leading(kind: str) -> Callable[[np.ndarray], np.ndarray]:
    """``prep`` of a scalar-last peer: the packed input's quaternions (two, or one for "apply")
    scalar last, the rest as it is."""
    count = 1 if kind == "apply" else 2
    return lambda x: np.concatenate(
        [*(_xyzw(x[..., 4 * i : 4 * i + 4]) for i in range(count)), x[..., 4 * count :]], -1
    )


def _wxyz_out(kind: str) -> Callable[[np.ndarray], np.ndarray]:
    """``post`` of a scalar-last peer: its quaternion output scalar first (vectors and angles as they are)."""
    return _wxyz if kind in ("mul", "slerp") else (lambda y: y)


def _columns_6d(x: np.ndarray) -> np.ndarray:
    """(..., 6) = (a1, a2) as the (..., 3, 2) matrix of the two columns (roma's input)."""
    return x.reshape(*x.shape[:-1], 2, 3).swapaxes(-1, -2)


def _transpose(m: np.ndarray) -> np.ndarray:
    return np.swapaxes(m, -1, -2)


def _reversed(a: np.ndarray) -> np.ndarray:
    return np.ascontiguousarray(a[..., ::-1])


def _reference_multiply(x: np.ndarray) -> np.ndarray:
    p, q = _split_pair(x)
    return _wxyz((Rotation.from_quat(_xyzw(p)) * Rotation.from_quat(_xyzw(q))).as_quat())


def _reference_apply(x: np.ndarray) -> np.ndarray:
    q, v = _split_quaternion(x)
    return Rotation.from_quat(_xyzw(q)).apply(v)


def _relative(x: np.ndarray) -> tuple[Rotation, Rotation]:
    """The first rotation of a packed pair of quaternions or matrices, and the relative one p^-1 q."""
    if x.shape[-1] == 18:
        a, b = (Rotation.from_matrix(m) for m in _split_matrices(x))
    else:
        a, b = (Rotation.from_quat(_xyzw(x[..., i : i + 4])) for i in (0, 4))
    return a, a.inv() * b


def _reference_distance(x: np.ndarray) -> np.ndarray:
    return _relative(x)[1].magnitude()


def _reference_slerp(x: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """p exp(t log(p^-1 q)) along the shorter arc, and along the other one: both are right at a
    half-turn (the accuracy table takes the nearer, row by row)."""
    p, relative = _relative(x)
    t = x[..., 8:9]
    v = relative.as_rotvec()
    angle = np.linalg.norm(v, axis=-1, keepdims=True)
    other = v - 2 * np.pi * v / np.where(angle > 0, angle, 1)
    return tuple(_wxyz((p * Rotation.from_rotvec(t * w)).as_quat()) for w in (v, other))


def _reference_plus(x: np.ndarray) -> np.ndarray:
    matrix, delta = _split_matrix(x)
    return matrix @ Rotation.from_rotvec(delta).as_matrix()


def _reference_quaternion_plus(x: np.ndarray) -> np.ndarray:
    q, delta = _split_quaternion(x)
    return _wxyz((Rotation.from_quat(_xyzw(q)) * Rotation.from_rotvec(delta)).as_quat())


THESEUS = "theseus (torchlie)"
THESEUS_AI = (
    "theseus-ai itself (its sdist needs torch at build time, which pip's build isolation does not "
    "provide, and SuiteSparse for scikit-sparse; its SO(3) is torchlie's, timed here)"
)
# Peers without the operation, and why (recorded in RESULTS.md under "Left out").
GAPS: dict[str, dict[str, str]] = {
    "so3_left_jacobian": {THESEUS: "no left Jacobian of its own, only inside jexp, with exp"},
    "so3_left_jacobian_inverse": {
        "kornia": "no inverse Jacobian",
        THESEUS: "no inverse Jacobian of its own, only inside jlog, with log",
    },
    "quaternion_plus": {THESEUS: "its rotations are matrices only"},
    "rotation_6d_to_matrix": {"jaxlie": "no 6D representation", "scipy": "no 6D representation"},
    "euler_angles_to_matrix": {"kornia": "Euler angles to and from quaternions only"},
    "matrix_to_euler_angles": {"kornia": "Euler angles to and from quaternions only"},
    "quaternion_slerp": {
        "roma": "unitquat_slerp takes one grid of steps for the whole batch (steps x batch outputs), "
        "not a t per pair",
        "scipy": "Slerp interpolates one sequence of key rotations, not a batch of pairs",
        "pytorch-kinematics": "quaternion_slerp negates rows of its q and of their dot products in place "
        "after using them: its backward raises (a variable needed for the gradient was modified by an "
        "inplace operation), and it writes into the caller's q",
    },
}


# The expected float64 output of each Lie function (the table's oracles: the defining series, compositions).
LIE_REFERENCES: dict[str, Callable[[np.ndarray], Reference] | None] = {
    "so3_exp": None,
    "so3_log": None,
    "so3_left_jacobian": cases.oracle_left_jacobian,
    "so3_left_jacobian_inverse": cases.oracle_left_jacobian_inverse,
    "so3_plus": _reference_plus,
    "quaternion_plus": _reference_quaternion_plus,
}
# Every operation's expected float64 output where it is not the rotation of the case itself.
REFERENCES: dict[str, Callable[[np.ndarray], Reference] | None] = {
    **LIE_REFERENCES,
    "quaternion_multiply": _reference_multiply,
    "quaternion_apply": _reference_apply,
    "quaternion_slerp": _reference_slerp,
    "quaternion_geodesic_distance": _reference_distance,
    "matrix_geodesic_distance": _reference_distance,
}


# The one-input form of each two-argument diffquat function (see the module docstring).
ADAPTERS: dict[str, Callable[[Callable[..., Any]], Callable[[Any], Any]]] = {
    "so3_plus": lambda fn: lambda x: fn(*_split_matrix(x)),
    "quaternion_plus": lambda fn: lambda x: fn(*_split_quaternion(x)),
    "quaternion_multiply": lambda fn: lambda x: fn(*_split_pair(x)),
    "quaternion_apply": lambda fn: lambda x: fn(*_split_quaternion(x)),
    "quaternion_slerp": lambda fn: lambda x: fn(*_split_slerp(x)),
    "quaternion_geodesic_distance": lambda fn: lambda x: fn(*_split_pair(x)),
    "matrix_geodesic_distance": lambda fn: lambda x: fn(*_split_matrices(x)),
    "euler_angles_to_matrix": lambda fn: lambda x: fn(x, EULER),
    "matrix_to_euler_angles": lambda fn: lambda x: fn(x, EULER),
}


# ---------------------------------------------------------------------------------------------------
# Timing


def _sync(out: Any) -> Any:
    if hasattr(out, "block_until_ready"):
        out.block_until_ready()
    elif isinstance(out, (tuple, list)):
        for o in out:
            _sync(o)
    elif getattr(out, "is_cuda", False):  # a torch tensor on a GPU: wait for the kernels queued so far
        import torch

        torch.cuda.synchronize(out.device)
    return out


def make_call(
    method: Method, x32: np.ndarray, backward: bool, device: str = "cpu"
) -> Callable[[], Any] | None:
    """A zero-argument callable running the method once (forward, or forward + backward). ``device``
    places torch's input; jax's goes to jax's default device."""
    native = np.ascontiguousarray(method.prep(x32), dtype=np.float32)
    if method.family == "numpy":
        if backward:
            return None
        return lambda: method.fn(native)
    if method.family == "torch":
        import torch

        xt = torch.from_numpy(native).to(device)
        if not backward:

            def forward() -> Any:
                with torch.no_grad():
                    return method.fn(xt)

            return forward
        leaf = xt.clone().requires_grad_(True)
        cot = torch.ones_like(method.fn(leaf.detach()))
        return lambda: torch.autograd.grad(method.fn(leaf), leaf, cot)
    import jax
    import jax.numpy as jnp

    xj = jnp.asarray(native)
    if not backward:
        return lambda: _sync(method.fn(xj))
    cot = jnp.ones_like(method.fn(xj))
    vjp = jax.jit(lambda x, c: jax.vjp(method.fn, x)[1](c))
    return lambda: _sync(vjp(xj, cot))


def roofline_call(floats_per_rotation: int, n: int, device: str = "cpu") -> Callable[[], Any]:
    """A tensor copy moving ``floats_per_rotation`` float32 per rotation in total (half read, half
    written): the memory-bandwidth bound of an operation with that traffic."""
    import torch

    numel = max(1, (floats_per_rotation * n + 1) // 2)
    src = torch.ones(numel, dtype=torch.float32, device=device)
    dst = torch.empty_like(src)
    return lambda: dst.copy_(src)


@dataclass
class Timing:
    median_s: float = float("nan")
    spread: float = float("nan")  # (max - min) / median over blocks
    first_s: float = float("nan")  # the first call: warm-up, and compilation for compiled methods


def time_all(calls: dict[str, Callable[[], Any]], repeats: int, block_s: float) -> dict[str, Timing]:
    timings = {label: Timing() for label in calls}
    per_block: dict[str, int] = {}
    for label, call in calls.items():
        start = time.perf_counter()
        _sync(call())
        timings[label].first_s = time.perf_counter() - start
        start = time.perf_counter()
        _sync(call())
        once = max(time.perf_counter() - start, 1e-7)
        per_block[label] = max(1, int(block_s / once))
    samples: dict[str, list[float]] = {label: [] for label in calls}
    labels = list(calls)
    for block in range(repeats):
        # The order rotates from block to block, so that each method follows each other one equally
        # often. On these 2-core virtual machines a method's time depends on what ran just before it:
        # jax forward + backward of so3_left_jacobian at N = 4096 ran 4x faster after a 15 ms block of
        # single-threaded numpy, or of sleep, than after its own or torch.compile's calls (jaxlie
        # alike), so a fixed order favoured whichever method came after numpy.
        shift = block % len(labels)
        for label in labels[shift:] + labels[:shift]:
            call = calls[label]
            k = per_block[label]
            start = time.perf_counter()
            for _ in range(k):
                out = call()
            _sync(out)
            samples[label].append((time.perf_counter() - start) / k)
    for label, s in samples.items():
        med = statistics.median(s)
        timings[label].median_s = med
        timings[label].spread = (max(s) - min(s)) / med
    return timings


# ---------------------------------------------------------------------------------------------------
# Accuracy on the test suite's named cases


ACCURACY_CASES = ("random", "identity", "half_turns", "near_half_turns", "near_identity", "sign_flip")


def _matrix_error(a: np.ndarray, b: np.ndarray) -> float:
    return float(np.max(np.abs(a - b))) if a.size else 0.0


def accuracy(op: OpSpec, method: Method) -> tuple[float, bool | None]:
    """Max float32 error against scipy float64 over the shared cases, and whether the gradient of a
    random weighted sum of the output is finite at every one of them (None: not differentiable). The
    cases run as one batch: one compilation per jitted method, not one per case (the quick run's
    accuracy table took 51 s of its 76 compiling)."""
    q = np.concatenate(
        [
            cases.oracle_normalize(cases.CASES_BY_NAME[name].quaternions("float64").reshape(-1, 4))
            for name in ACCURACY_CASES
        ]
    )
    x64 = make_input(op.source, q)
    rotation = Rotation.from_quat(_xyzw(q))
    native = np.ascontiguousarray(method.prep(x64.astype(np.float32)))
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        out, grad_finite = _run_with_grad(method, native)
    got = np.asarray(method.post(np.asarray(out, dtype=np.float64)))
    if op.reference is not None:
        # the reference, or a tuple of outputs that are all right (slerp at a half-turn): the nearest,
        # row by row; quaternions up to sign
        expected = op.reference(x64)
        candidates = list(expected) if isinstance(expected, tuple) else [expected]
        if op.target == "quaternion":
            candidates += [-c for c in candidates]
        rows = [np.abs(got - c).reshape(len(q), -1).max(-1) for c in candidates]
        err = float(np.max(np.min(rows, axis=0)))
    elif op.target == "euler":  # compared as the rotation the angles represent (gimbal lock included)
        err = _matrix_error(Rotation.from_euler(EULER, got).as_matrix(), rotation.as_matrix())
    elif op.target == "matrix":
        err = _matrix_error(got, rotation.as_matrix())
    elif op.target == "quaternion":
        # up to sign, row by row: at half-turns w = 0 and rounding legitimately picks the sign
        expected = _wxyz(rotation.as_quat(canonical=True))
        err = float(np.max(np.minimum(np.abs(got - expected).max(-1), np.abs(got + expected).max(-1))))
    else:  # a rotation vector: compared as the rotation it represents (+-pi are the same)
        err = _matrix_error(Rotation.from_rotvec(got).as_matrix(), rotation.as_matrix())
    return (err if np.isfinite(err) else float("inf")), grad_finite


def _run_with_grad(method: Method, native: np.ndarray) -> tuple[np.ndarray, bool | None]:
    weights = np.random.default_rng(0).normal(size=(native.shape[0],))
    if method.family == "numpy":
        return np.asarray(method.fn(native)), None
    if method.family == "torch":
        import torch

        leaf = torch.from_numpy(native).requires_grad_(True)
        out = method.fn(leaf)
        w = torch.from_numpy(weights.astype(np.float32)).reshape(-1, *([1] * (out.dim() - 1)))
        (grad,) = torch.autograd.grad((out * w).sum(), leaf)
        return out.detach().numpy(), bool(torch.isfinite(grad).all())
    import jax
    import jax.numpy as jnp

    xj = jnp.asarray(native)
    out = method.fn(xj)
    w = jnp.asarray(weights.astype(np.float32)).reshape(-1, *([1] * (out.ndim - 1)))
    grad = jax.grad(lambda x: (method.fn(x) * w).sum())(xj)
    return np.asarray(out), bool(jnp.isfinite(grad).all())


# ---------------------------------------------------------------------------------------------------
# Report


def machine() -> dict[str, str]:
    import jax
    import torch

    info = {
        "python": platform.python_version(),
        "platform": platform.platform(),
        "processor": platform.processor() or platform.machine(),
        "cpus": str(os.cpu_count()),
        "torch threads": str(torch.get_num_threads()),
        "numpy": np.__version__,
        "torch": torch.__version__,
        "jax": jax.__version__,
        "jax devices": ", ".join(str(d) for d in jax.devices()),
    }
    try:
        with open("/proc/cpuinfo") as f:
            names = [line.split(":", 1)[1].strip() for line in f if line.startswith("model name")]
        if names:
            info["processor"] = names[0]
    except OSError:
        pass
    for peer in ("scipy", "roma", "kornia", "pytorch_kinematics", "jaxlie", "pypose", "torchlie"):
        try:
            module = __import__(peer)
            info[peer] = str(getattr(module, "__version__", "installed"))
        except ImportError:
            info[peer] = "not installed"
    return info


def finish(
    results: dict[str, Any],
    started: float,
    load_before: tuple[float, ...],
    out_dir: Path,
    name: str,
    render: Callable[[dict[str, Any]], str],
    peers: tuple[str, ...] = (),
) -> dict[str, Any]:
    """Completes a benchmark module's results (its length, the load before and after it, the machine
    and the versions of ``peers`` beside ``machine``'s) and writes ``<name>.json`` and the rendered
    ``<NAME>.md`` in ``out_dir``."""
    results["seconds"] = time.time() - started
    results["load"] = {"before": list(load_before), "after": list(os.getloadavg())}
    info = machine()
    for peer in peers:
        try:
            info[peer] = str(getattr(__import__(peer), "__version__", "installed"))
        except ImportError:
            info[peer] = "not installed"
    results["machine"] = info
    out_dir.mkdir(parents=True, exist_ok=True)
    (out_dir / f"{name}.json").write_text(json.dumps(results, indent=1))
    (out_dir / f"{name.upper()}.md").write_text(render(results))
    return results


def _fmt_time(seconds: float) -> str:
    if not np.isfinite(seconds):
        return "—"
    us = seconds * 1e6
    if us >= 1e6:
        return f"{us / 1e6:.3g} s"
    return f"{us:.3g} µs" if us < 1000 else f"{us / 1000:.3g} ms"


def _fmt_overhead(first: float, median: float) -> str:
    """First call minus median; a first call that was faster than the median (noise larger than the
    warm-up) reads as no measurable overhead, not as a negative time."""
    return "≈ 0 (below noise)" if first <= median else _fmt_time(first - median)


# Interleaved blocks per cell, by --quick.
DEFAULT_REPEATS = {True: 3, False: 7}


def run(
    quick: bool,
    out_dir: Path,
    only: list[str] | None = None,
    sizes: tuple[int, ...] | None = None,
    repeats: int | None = None,
) -> dict[str, Any]:
    import torch

    if sizes is None:
        sizes = QUICK_SIZES if quick else FULL_SIZES
    # Medians over 7 blocks of >= 30 ms: a 2-core shared machine is noisy (spreads of 100% and more
    # between 3 blocks of 10 ms). More blocks (--repeats) for ratios near 1: two runs of 7 moved a
    # ratio of microsecond calls (N = 1) by up to 0.3.
    repeats, block_s = repeats or DEFAULT_REPEATS[quick], 0.002 if quick else 0.03
    ops = [op for op in build_ops(quick) if only is None or op.name in only]
    load_before = os.getloadavg()
    started = time.time()
    results: dict[str, Any] = {"quick": quick, "sizes": list(sizes), "repeats": repeats, "ops": {}}
    for op in ops:
        traffic = WIDTH[op.source] + WIDTH[op.target]
        entry: dict[str, Any] = {"skipped": op.skipped, "timings": {}, "accuracy": {}}
        for mode, backward in (("forward", False), ("forward + backward", True)):
            per_n: dict[str, dict[str, Timing]] = {}
            for n in sizes:
                x32 = make_input(op.source, unit_quaternions(n)).astype(np.float32)
                calls = {}
                for m in op.methods:
                    call = make_call(m, x32, backward)
                    if call is not None:
                        calls[m.label] = call
                # forward + backward moves the input and output twice plus the input gradient
                floats = traffic + (traffic + WIDTH[op.source] if backward else 0)
                calls["roofline (copy of the same bytes)"] = roofline_call(floats, n)
                with warnings.catch_warnings():
                    warnings.simplefilter("ignore")
                    per_n[str(n)] = time_all(calls, repeats, block_s)
                print(f"{op.name} {mode} N={n} done", file=sys.stderr, flush=True)
            entry["timings"][mode] = {
                n: {label: t.__dict__ for label, t in ts.items()} for n, ts in per_n.items()
            }
        for m in op.methods:
            err, finite = accuracy(op, m)
            entry["accuracy"][m.label] = {"max_error": err, "grad_finite": finite}
        results["ops"][op.name] = entry
    if only is None or set(OVERHEAD_OPS) & set(only):  # the Lie run (LIE.md) leaves it to the conversions'
        results["overhead"] = overhead(repeats, block_s)
    results["seconds"] = time.time() - started
    results["load"] = {"before": load_before, "after": os.getloadavg()}
    results["machine"] = machine()
    results["torch_threads"] = torch.get_num_threads()
    write(results, out_dir)
    return results


def write(results: dict[str, Any], out_dir: Path) -> None:
    out_dir.mkdir(parents=True, exist_ok=True)
    (out_dir / "results.json").write_text(json.dumps(results, indent=1))
    from benchmarks import gpu

    (out_dir / "RESULTS.md").write_text(render(results, gpu.load_gpu(out_dir)))
    plot(results, out_dir / "results.png")


def merge(paths: list[Path]) -> dict[str, Any]:
    """One report from runs of different operations (``--ops``) made side by side on one machine.

    A later run of an operation replaces an earlier one; a report that is itself merged contributes
    the runs it lists. The report lists, and takes its run time and load from, only the runs whose
    tables it still shows, each with the operations it shows from it."""
    reports = [json.loads(p.read_text()) for p in paths]
    runs = [
        dict(run)
        for r in reports
        for run in r.get("runs", [{"ops": list(r["ops"]), "seconds": r["seconds"], "load": r["load"]}])
    ]
    ops: dict[str, Any] = {}
    for r in reports:
        ops.update(r["ops"])
    # The last run of each operation is the one its tables come from.
    source = {op: i for i, run in enumerate(runs) for op in run["ops"]}
    for i, run in enumerate(runs):
        run["ops"] = [op for op in run["ops"] if source[op] == i]
    runs = [run for run in runs if run["ops"]]
    merged = {**reports[0], "ops": ops, "runs": runs, "seconds": max(r["seconds"] for r in runs)}
    merged["load"] = {
        "before": max((r["load"]["before"] for r in runs), key=lambda x: x[0]),
        "after": max((r["load"]["after"] for r in runs), key=lambda x: x[0]),
    }
    return merged


TORCH_PEERS = ("roma", "kornia", "pytorch-kinematics", "pypose", THESEUS)
HAND = "hand-written formula, torch.compile"
# Each diffquat path, its row, and the peers on that path. The torch peers are called as their users
# call them, eagerly: the torch.compile row is set against the same eager peers.
PATHS: dict[str, tuple[str, tuple[str, ...]]] = {
    "torch eager": ("diffquat torch eager", TORCH_PEERS),
    "torch.compile": ("diffquat torch.compile", TORCH_PEERS),
    "jax.jit": ("diffquat jax.jit", ("jaxlie (jit)",)),
    "numpy": ("diffquat numpy", ("scipy",)),
}


def path_ratios(results: dict[str, Any]) -> list[dict[str, Any]]:
    """Every cell of every path: the fastest peer's median time over diffquat's (above 1: diffquat is
    faster), with the peer's name."""
    cells = []
    for name, entry in results["ops"].items():
        for mode, per_n in entry["timings"].items():
            for n, ts in per_n.items():
                t = {label: v["median_s"] for label, v in ts.items()}
                for path, (row, peers) in PATHS.items():
                    timed = [(t[p], p) for p in peers if p in t and np.isfinite(t[p])]
                    if row not in t or not timed or not np.isfinite(t[row]):
                        continue
                    fastest, peer = min(timed)
                    ratio = fastest / t[row]
                    cell = {"op": name, "mode": mode, "n": int(n), "path": path, "ratio": ratio, "peer": peer}
                    cells.append(cell)
    return cells


def ratios(results: dict[str, Any]) -> list[str]:
    """One row per operation, mode and N: the fastest peer / diffquat on each path (below 1 in bold),
    and diffquat compiled over the formula hand-written and compiled."""
    by_cell: dict[tuple[str, str, int], dict[str, str]] = {}
    for c in path_ratios(results):
        text = f"{c['ratio']:.2f}x ({c['peer']})"
        by_cell.setdefault((c["op"], c["mode"], c["n"]), {})[c["path"]] = (
            f"**{text}**" if c["ratio"] < 1.0 else text
        )
    lines = []
    for name, entry in results["ops"].items():
        for mode, per_n in entry["timings"].items():
            for n, ts in per_n.items():
                cells = by_cell.get((name, mode, int(n)), {})
                t = {label: v["median_s"] for label, v in ts.items()}
                compiled = t.get("diffquat torch.compile")
                hand = f"{compiled / t[HAND]:.2f}" if HAND in t and compiled else "—"
                row = " | ".join(cells.get(path, "—") for path in PATHS)
                lines.append(f"| {name} | {mode} | {n} | {row} | {hand} |")
    return lines


def below_one(results: dict[str, Any]) -> list[str]:
    """The rows of the table of cells below 1.0x, slowest first."""
    cells = sorted((c for c in path_ratios(results) if c["ratio"] < 1.0), key=lambda c: c["ratio"])
    return [
        f"| {c['op']} | {c['path']} | {c['n']} | {c['mode']} | {c['ratio']:.2f}x | {c['peer']} |"
        for c in cells
    ]


def path_summary(results: dict[str, Any]) -> list[str]:
    """Per path: the range of the ratios and how many cells fall below 1.0x and 0.9x."""
    lines = []
    cells = path_ratios(results)
    for path in PATHS:
        rs = [c["ratio"] for c in cells if c["path"] == path]
        if rs:
            lines.append(
                f"| {path} | {len(rs)} | {min(rs):.2f}-{max(rs):.2f}x | {sum(r < 1.0 for r in rs)} "
                f"| {sum(r < 0.9 for r in rs)} |"
            )
    return lines


# ---------------------------------------------------------------------------------------------------
# Per-call overhead at N = 1


OVERHEAD_OPS = ("quaternion_to_matrix", "matrix_to_quaternion")
PUBLIC, UNCHECKED, CORE = "public function", "conversion, no validation", "core formula"


def overhead(repeats: int, block_s: float) -> dict[str, Any]:
    """The per-call cost of validation and dispatch at N = 1, per backend: the public conversion, the
    same conversion without the argument checks (``_CONVERSIONS``: torch's ``autograd.Function``,
    jax's ``custom_jvp`` or formula, numpy's formula) and the bare core formula
    (``diffquat._core.<op>(xp, x)``), float32, side by side in rotated blocks. public - unchecked is
    the validation (conversion, shape and dtype checks, the non-finite-row rule); unchecked - core
    is the dispatch (torch: the ``autograd.Function``; jax: the ``custom_jvp``). Under ``jax.jit`` the
    checks run once at trace time: what remains is the program's own difference."""

    out: dict[str, Any] = {}
    for name in OVERHEAD_OPS:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            timed = time_all(_overhead_calls(name), repeats, block_s)
        entry: dict[str, dict[str, Any]] = {}
        for key, t in timed.items():
            backend, label = key.split("|")
            entry.setdefault(backend, {})[label] = t.__dict__
        out[name] = entry
        print(f"overhead {name} done", file=sys.stderr, flush=True)
    return out


def _overhead_calls(name: str) -> dict[str, Callable[[], Any]]:
    """The calls that :func:`overhead` times for one conversion, keyed ``"<backend>|<form>"``."""
    import jax
    import torch

    import diffquat.jax as dqj
    import diffquat.numpy as dqn
    import diffquat.torch as dqt
    from diffquat import _core

    x = make_input("quaternion" if name == "quaternion_to_matrix" else "matrix", unit_quaternions(1))
    x = x.astype(np.float32)
    xt, xj = torch.from_numpy(x), jax.numpy.asarray(x)
    leaf = xt.clone().requires_grad_(True)
    core = getattr(_core, name)

    def forms(module: Any, xp: Any) -> dict[str, Callable[[Any], Any]]:
        conversion = module._CONVERSIONS[name]
        return {
            PUBLIC: getattr(module, name),
            UNCHECKED: lambda v: conversion(xp, v),
            CORE: lambda v: core(xp, v),
        }

    def backward(fn: Callable[[Any], Any]) -> Callable[[], Any]:
        cot = torch.ones_like(fn(xt))
        return lambda: torch.autograd.grad(fn(leaf), leaf, cot)

    def jitted(fn: Callable[[Any], Any]) -> Callable[[], Any]:
        compiled = jax.jit(fn)
        return lambda: _sync(compiled(xj))

    calls: dict[str, Callable[[], Any]] = {}
    for label, fn in forms(dqt, torch).items():
        calls[f"torch eager, forward|{label}"] = functools.partial(_no_grad, fn, xt)
        calls[f"torch eager, forward + backward|{label}"] = backward(fn)
    for label, fn in forms(dqj, dqj._B.xp).items():
        calls[f"jax eager, forward|{label}"] = functools.partial(lambda f, v: _sync(f(v)), fn, xj)
        calls[f"jax.jit, forward|{label}"] = jitted(fn)
    for label, fn in forms(dqn, np).items():
        calls[f"numpy, forward|{label}"] = functools.partial(fn, x)
    return calls


def _no_grad(fn: Callable[[Any], Any], x: Any) -> Any:
    import torch

    with torch.no_grad():
        return fn(x)


def _us(seconds: float) -> str:
    return f"{seconds * 1e6:.2f}"


def render_overhead(results: dict[str, Any]) -> list[str]:
    """The N = 1 overhead section of ``RESULTS.md`` (empty where the run did not measure it)."""
    data = results.get("overhead")
    if not data:
        return []
    out = [
        "",
        "## Per-call overhead at N = 1 (validation and dispatch)",
        "",
        "float32, one rotation, medians over the same rotated blocks as the tables below (all rows of "
        "one operation side by side). *public*: the function users call; *no validation*: the same "
        "conversion called without the argument checks (torch: the `autograd.Function`, jax: the "
        "`custom_jvp` or the formula, numpy: the formula); *core*: the bare formula "
        "`diffquat._core.<op>(xp, x)`. Validation = public - no validation; dispatch = no validation "
        "- core. Under `jax.jit` the checks run once, at trace time. Times in µs.",
        "",
        "| op | backend | public | no validation | core | validation | dispatch | public - core |",
        "|---|---|---|---|---|---|---|---|",
    ]
    for name, entry in data.items():
        for backend, rows in entry.items():
            pub, unc, core = (rows[k]["median_s"] for k in (PUBLIC, UNCHECKED, CORE))
            out.append(
                f"| {name} | {backend} | {_us(pub)} | {_us(unc)} | {_us(core)} | {_us(pub - unc)} "
                f"| {_us(unc - core)} | {_us(pub - core)} |"
            )
        ts = results["ops"].get(name, {}).get("timings", {})
        for mode, per_n in ts.items():
            one = per_n.get("1", {})
            if "diffquat torch.compile" in one and HAND in one:
                pub, core = one["diffquat torch.compile"]["median_s"], one[HAND]["median_s"]
                out.append(
                    f"| {name} | torch.compile, {mode} (from the table below) | {_us(pub)} | — | {_us(core)} "
                    f"| — | — | {_us(pub - core)} |"
                )
    return out


def render(results: dict[str, Any], gpu_results: dict[str, Any] | None = None) -> str:
    """``RESULTS.md``: the CPU run's tables, and the GPU run's section (``benchmarks.gpu``) where
    given."""
    out = [
        "# Benchmark results",
        "",
        "Written by `python -m benchmarks.run"
        + (" --quick" if results["quick"] else "")
        + (
            " --sizes " + ",".join(str(n) for n in results["sizes"])
            if tuple(results["sizes"]) not in (FULL_SIZES, QUICK_SIZES)
            else ""
        )
        + (
            f" --repeats {results['repeats']}"
            if results.get("repeats", DEFAULT_REPEATS[results["quick"]]) != DEFAULT_REPEATS[results["quick"]]
            else ""
        )
        + "`; "
        "do not edit by hand. float32, CPU. Each cell: median time per call, and in parentheses the "
        "fraction of the memory-bandwidth bound (the roofline row's time over this one's) where N >= 4096. "
        f"Medians over {results.get('repeats', 'several')} interleaved blocks; the first call (warm-up, "
        "compilation) is in its own table.",
        "",
        f"Run time {results['seconds']:.0f} s; load average (1, 5, 15 min) before "
        f"{tuple(round(x, 2) for x in results['load']['before'])}, after "
        f"{tuple(round(x, 2) for x in results['load']['after'])}: other jobs shared the machine, so "
        "absolute times are noisy; ratios between rows of one table were taken side by side.",
        "",
        *(
            [
                f"**Warning: the load average exceeded the {results['machine']['cpus']} cores during "
                "this run; blocks of one method differ by up to the spreads given under each table, "
                "and the ratios below are not reliable. Rerun on a quiet machine.**",
                "",
            ]
            if max(results["load"]["before"][0], results["load"]["after"][0])
            > float(results["machine"]["cpus"])
            else []
        ),
        *(
            [
                "Merged from separate runs on this machine (`--merge`; a later run of an operation "
                "replaces an earlier one); every table was taken side by side within one run:",
                "",
                *(
                    f"- run {i + 1}: {', '.join(r['ops'])}; {r['seconds']:.0f} s; load average before "
                    f"{tuple(round(x, 2) for x in r['load']['before'])}"
                    for i, r in enumerate(results["runs"])
                ),
                "",
            ]
            if "runs" in results
            else []
        ),
        (
            "GPU figures: still to be measured; this run had no GPU."
            if gpu_results is None
            else f"GPU figures: the last section ({gpu_results['machine']['device']}, a separate run"
            + (
                "; measured with diffquat's former Triton kernels, since removed: to be re-measured)."
                if gpu_results.get("eager_path") is None
                else ")."
            )
        ),
        "",
        "## Machine and versions",
        "",
        "| | |",
        "|---|---|",
        *[f"| {k} | {v} |" for k, v in results["machine"].items()],
        "",
        "![ns per rotation against N](results.png)",
        "",
        "## Key ratios: the fastest peer on each path / diffquat",
        "",
        "Above 1: diffquat is faster. Paths: diffquat torch eager and `torch.compile` against the torch "
        "peers (roma, kornia, pytorch-kinematics, pypose, torchlie; called eagerly, as their users call "
        "them), `jax.jit` against jaxlie (jit), numpy against scipy (forward only). The last column is "
        "diffquat under `torch.compile` over the core formula hand-written and compiled. Below 1.0x in bold.",
        "",
        "| path | cells | range | below 1.0x | below 0.9x |",
        "|---|---|---|---|---|",
        *path_summary(results),
        "",
        "| op | mode | N | " + " | ".join(PATHS) + " | compiled / hand-written |",
        "|---" * (len(PATHS) + 4) + "|",
        *ratios(results),
        "",
        "### Cells below 1.0x",
        "",
        "| op | path | N | mode | fastest peer / diffquat | fastest peer |",
        "|---|---|---|---|---|---|",
        *(below_one(results) or ["| none | | | | | |"]),
        *render_overhead(results),
    ]
    sizes = results["sizes"]
    for name, entry in results["ops"].items():
        out += ["", f"## {name}", ""]
        if entry["skipped"]:
            out += ["Left out: " + "; ".join(entry["skipped"]), ""]
        for mode, per_n in entry["timings"].items():
            labels = list(next(iter(per_n.values())).keys())
            out += [f"### {mode}", "", "| method | " + " | ".join(f"N = {n}" for n in sizes) + " |"]
            out += ["|---" * (len(sizes) + 1) + "|"]
            for label in labels:
                cells = []
                for n in sizes:
                    t = per_n[str(n)][label]["median_s"]
                    roof = per_n[str(n)]["roofline (copy of the same bytes)"]["median_s"]
                    frac = f" ({roof / t:.0%})" if n >= 4096 else ""
                    cells.append(_fmt_time(t) + frac)
                out.append(f"| {label} | " + " | ".join(cells) + " |")
            out += ["", f"First call minus median ({mode}): warm-up, and compilation where compiled.", ""]
            out += [
                "| method | " + " | ".join(f"N = {n}" for n in sizes) + " |",
                "|---" * (len(sizes) + 1) + "|",
            ]
            for label in labels:
                cells = [
                    _fmt_overhead(per_n[str(n)][label]["first_s"], per_n[str(n)][label]["median_s"])
                    for n in sizes
                ]
                out.append(f"| {label} | " + " | ".join(cells) + " |")
            spreads = [v["spread"] for ts in per_n.values() for v in ts.values()]
            out += ["", f"Largest (max - min) / median over blocks in this table: {max(spreads):.0%}.", ""]
        out += ["### Accuracy on the shared test cases", "",
                "Max float32 error against scipy in float64 over the cases " + ", ".join(ACCURACY_CASES)
                + " of `tests/cases.py` (unit inputs; exact half-turns included), and whether the gradient "
                "of a weighted sum of the output is finite at every one.", "",
                "| method | max error | finite gradients |", "|---|---|---|"]  # fmt: skip
        for label, acc in entry["accuracy"].items():
            finite = {None: "n/a (forward only)", True: "yes", False: "**no**"}[acc["grad_finite"]]
            out.append(f"| {label} | {acc['max_error']:.2e} | {finite} |")
    if gpu_results is not None:
        from benchmarks import gpu

        out += ["", gpu.render(gpu_results).rstrip("\n")]
    return "\n".join(out) + "\n"


def plot(results: dict[str, Any], path: Path, where: str = "") -> None:
    """ns per rotation against N, log-log, one line per method; one panel per operation and mode
    (``where`` is added to each panel's title)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    ops = list(results["ops"])
    fig, axes = plt.subplots(len(ops), 2, figsize=(12, 4.2 * len(ops)), squeeze=False)
    sizes = results["sizes"]
    for row, name in enumerate(ops):
        for col, (mode, per_n) in enumerate(results["ops"][name]["timings"].items()):
            ax = axes[row][col]
            for label in per_n[str(sizes[0])]:
                ns = [per_n[str(n)][label]["median_s"] * 1e9 / n for n in sizes]
                style = "k--" if label.startswith("roofline") else ("-o" if "diffquat" in label else "-.x")
                ax.loglog(sizes, ns, style, label=label, linewidth=2 if "diffquat" in label else 1)
            ax.set_title(f"{name}, {mode}{where}")
            ax.set_xlabel("N (rotations per call)")
            ax.set_ylabel("ns per rotation")
            ax.grid(True, which="both", alpha=0.3)
            ax.legend(fontsize=7)
    fig.tight_layout()
    fig.savefig(path, dpi=90)
    plt.close(fig)


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--quick", action="store_true", help="small N, few repeats: seconds")
    parser.add_argument("--out", type=Path, default=Path(__file__).resolve().parent)
    parser.add_argument("--ops", help="comma-separated operation names (default: all)")
    parser.add_argument("--merge", type=Path, nargs="+", help="render one report from these results.json")
    parser.add_argument("--sizes", help="comma-separated batch sizes N (default: the full or the quick grid)")
    parser.add_argument("--repeats", type=int, help="interleaved blocks per cell (default: 7; --quick: 3)")
    args = parser.parse_args(argv)
    if args.merge:
        write(merge(args.merge), args.out)
        return
    sizes = tuple(int(n) for n in args.sizes.split(",")) if args.sizes else None
    run(args.quick, args.out, args.ops.split(",") if args.ops else None, sizes, args.repeats)


if __name__ == "__main__":
    main()
