"""SE(3): diffquat's pose functions against the peers that have them, timed side by side, with the float32
accuracy of every SE(3) Jacobian on an angle grid. ``python -m benchmarks.se3 [--quick] [--out DIR]
[--threads N]`` writes ``SE3.md`` and ``se3.json`` (default: next to this file).

Timing. Eight operations: ``se3_exp``, ``se3_log``, ``se3_compose``, ``se3_inverse``, ``se3_apply``,
``se3_right_jacobian``, ``se3_plus`` (right) and ``jlog``, the inverse right Jacobian at the log of a pose
(``se3_right_jacobian_inverse(se3_log(T))``, what jaxlie's ``SE3.jlog`` and torchlie's ``SE3.log(...,
jacobians=)`` give). Each is timed forward (torch: under ``no_grad``) and forward + backward (the
gradient of every input for a cotangent of ones on every output), in float32, over the N grid of
``benchmarks/run.py`` (``--quick``: N = 64 only), by ``run.time_all``: medians over interleaved blocks
whose order rotates from block to block, the first call (warm-up, and compilation for ``jax.jit`` and
``torch.compile``) apart. Four paths, each set against the peers on the same path:

- diffquat torch eager against pypose, torchlie (theseus' Lie library), kornia (``liegroup.Se3``) and
  roma (``Rigid``, ``RigidUnitQuat``), each called eagerly;
- diffquat under ``torch.compile`` (``fullgraph=True``) against the same peers under ``torch.compile``
  (``fullgraph=True``; where that fails, with graph breaks allowed, and the reason recorded; a peer
  that does not compile at all is left out of that cell, and the reason recorded);
- diffquat ``jax.jit`` against jaxlie under ``jax.jit``;
- diffquat numpy against scipy's ``RigidTransform``, both in float64, forward only.

Every method takes its own native layout, converted from the same poses outside the timed region (and
any wrapping object, ``pp.SE3(x)``, kornia's ``Se3``, roma's ``Rigid``, scipy's ``RigidTransform``,
built there too; under ``torch.compile`` and ``jax.jit`` the wrapping is inside the compiled function,
where it costs nothing): pypose ``(t, q_xyzw)``, jaxlie ``(q_wxyz, t)``, torchlie the top 3x4 rows,
kornia a scalar-first quaternion and a translation, roma a matrix (or an ``xyzw`` quaternion) and a
translation, scipy's exponential coordinates rotation first. Each returns its own layout too; a layout
check converts every method's output at N = 64 back and compares it with diffquat's float64 result.

Accuracy. On the angle grid ``THETAS`` with ``rho = (0.3, -0.7, 0.5)`` and ``phi = theta * axis``
(``AXIS``, unit), rounded to float32 (and, apart, in float64): every SE(3) Jacobian of diffquat and of
the peers that have one, against the series ``sum_n ad(xi)^n / (n + 1)!`` (60 terms, ``ad = [[phi^,
rho^], [0, phi^]]``, summed in ``numpy.longdouble`` and rounded to float64) evaluated at the rounded
input itself, its inverse where the peer's function is an inverse. Each peer's function is mapped onto
diffquat's convention (``MAPPING``; checked in float64 at theta = 1, where every mapped result agrees
with the series to ~1e-15). Errors in units of eps * |rho| of the dtype: the upper-right 3x3 block
(``Q`` of ``J_l``, ``Q(-rho, -phi)`` of ``J_r``, ``-J^-1 Q J^-1`` of the inverses) and the whole 6x6.
"""

from __future__ import annotations

import argparse
import itertools
import math
import os
import sys
import time
import traceback
import types
import warnings
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from .run import FULL_SIZES, _fmt_time, _sync, finish, time_all, unit_quaternions

QUICK_SIZES = (64,)
DEFAULT_REPEATS = {True: 2, False: 7}  # rotated blocks per cell, by --quick
OPS = (
    "se3_exp",
    "se3_log",
    "se3_compose",
    "se3_inverse",
    "se3_apply",
    "se3_right_jacobian",
    "se3_plus",
    "jlog",
)
# The canonical inputs of each operation (diffquat's convention: poses (N, 4, 4), twists (N, 6)
# translation first, points (N, 3)).
INPUTS = {
    "se3_exp": ("twist",),
    "se3_log": ("pose",),
    "se3_compose": ("pose", "pose"),
    "se3_inverse": ("pose",),
    "se3_apply": ("pose", "points"),
    "se3_right_jacobian": ("twist",),
    "se3_plus": ("pose", "twist"),
    "jlog": ("pose",),
}
DESCRIPTION = {
    "se3_exp": "exp: twist (N, 6) -> pose",
    "se3_log": "log: pose -> twist",
    "se3_compose": "T1 T2",
    "se3_inverse": "T^-1",
    "se3_apply": "R p + t for N poses and N points",
    "se3_right_jacobian": "J_r(xi), (N, 6, 6)",
    "se3_plus": "T exp(d) (side='right')",
    "jlog": "J_r^-1(log T), (N, 6, 6) (jaxlie's jlog)",
}

TORCH_PEERS = ("pypose", "torchlie", "kornia", "roma Rigid", "roma RigidUnitQuat")
COMPILED = " (torch.compile)"
JAXLIE, SCIPY = "jaxlie (jit)", "scipy"
DQ = {
    "torch eager": "diffquat torch eager",
    "torch.compile": "diffquat torch.compile",
    "jax.jit": "diffquat jax.jit",
    "numpy": "diffquat numpy",
}
PATHS: dict[str, tuple[str, ...]] = {
    "torch eager": TORCH_PEERS,
    "torch.compile": tuple(p + COMPILED for p in TORCH_PEERS),
    "jax.jit": (JAXLIE,),
    "numpy": (SCIPY,),
}
# Peers without the operation, and why.
GAPS: dict[str, dict[str, str]] = {
    "se3_exp": dict.fromkeys(("roma Rigid", "roma RigidUnitQuat"), "no SE(3) exp (rigid transforms only)"),
    "se3_log": dict.fromkeys(("roma Rigid", "roma RigidUnitQuat"), "no SE(3) log (rigid transforms only)"),
    "se3_right_jacobian": {
        "kornia": "Se3 has no Jacobian (only So3 has left and right Jacobians)",
        "roma Rigid": "no SE(3) Jacobian",
        "roma RigidUnitQuat": "no SE(3) Jacobian",
        JAXLIE: "SE3 has no Jacobian of exp, only jlog (the jlog row)",
        SCIPY: "RigidTransform has no Jacobian",
    },
    "se3_plus": dict.fromkeys(("roma Rigid", "roma RigidUnitQuat"), "no SE(3) exp (rigid transforms only)"),
    "jlog": {
        "pypose": "no right Jacobian of log: its SE3 Jinvp(X, p) gives J_l(log X)^-1 p, a vector",
        "kornia": "Se3 has no Jacobian",
        "roma Rigid": "no SE(3) Jacobian",
        "roma RigidUnitQuat": "no SE(3) Jacobian",
        SCIPY: "RigidTransform has no Jacobian",
    },
}


# ---------------------------------------------------------------------------------------------------
# Inputs and layouts


def canonical_inputs(op: str, n: int) -> tuple[np.ndarray, ...]:
    """float64 inputs in diffquat's convention: twists with uniformly random rotations (angles up to pi)
    and Gaussian translations, poses alike, Gaussian points."""
    import diffquat.numpy as dqn

    out = []
    for k, kind in enumerate(INPUTS[op]):
        rng = np.random.default_rng(10 * k + 1)
        rotvec = dqn.quaternion_to_axis_angle(unit_quaternions(n, seed=k))
        if kind == "twist":
            out.append(np.concatenate([rng.standard_normal((n, 3)), rotvec], axis=-1))
        elif kind == "pose":
            rotation = dqn.axis_angle_to_matrix(rotvec)
            out.append(dqn.se3_from_rotation_translation(rotation, rng.standard_normal((n, 3))))
        else:
            out.append(rng.standard_normal((n, 3)))
    return tuple(out)


def _pose(layout: str) -> Callable[[np.ndarray], np.ndarray]:
    import diffquat.numpy as dqn

    return lambda m: dqn.matrix_to_pose(m, layout=layout)


def _from_pose(layout: str) -> Callable[[np.ndarray], np.ndarray]:
    import diffquat.numpy as dqn

    return lambda p: dqn.pose_to_matrix(np.asarray(p, dtype=np.float64), layout=layout)


def _top(m: np.ndarray) -> np.ndarray:
    return np.ascontiguousarray(m[..., :3, :])


def _from_top(top: np.ndarray) -> np.ndarray:
    bottom = np.broadcast_to(np.array([0.0, 0.0, 0.0, 1.0]), (*top.shape[:-2], 1, 4))
    return np.concatenate([top, bottom], axis=-2)


def _q_wxyz(m: np.ndarray) -> np.ndarray:
    import diffquat.numpy as dqn

    return dqn.matrix_to_quaternion(m[..., :3, :3])


def _rotation_first(xi: np.ndarray) -> np.ndarray:
    """diffquat's twist (rho, phi) as scipy's exponential coordinates (phi, rho), and back."""
    return np.ascontiguousarray(np.concatenate([xi[..., 3:], xi[..., :3]], axis=-1))


def _qt_to_matrix(q_wxyz: np.ndarray, t: np.ndarray) -> np.ndarray:
    import diffquat.numpy as dqn

    return dqn.pose_to_matrix(np.concatenate([q_wxyz, t], axis=-1), layout="wxyz_xyz")


def _rt_to_matrix(r: np.ndarray, t: np.ndarray) -> np.ndarray:
    import diffquat.numpy as dqn

    return dqn.se3_from_rotation_translation(r, t)


def _numpy(x: Any) -> Any:
    """A method's output as float64 numpy (tuples stay tuples; other objects as they are)."""
    if isinstance(x, (tuple, list)):
        return tuple(_numpy(v) for v in x)
    if hasattr(x, "detach"):
        import torch

        return torch.Tensor.as_subclass(x, torch.Tensor).detach().cpu().double().numpy()
    if hasattr(x, "block_until_ready"):
        return np.asarray(x, dtype=np.float64)
    return x


# ---------------------------------------------------------------------------------------------------
# Methods


@dataclass
class Method:
    """One implementation of one operation. ``prep`` maps the canonical float64 inputs to the method's
    native arrays; ``wrap`` maps those (as tensors, leaves for the backward) to the arguments of ``fn``
    (the peer's objects), outside the timed region in eager mode; ``post`` maps the output (as numpy)
    back to diffquat's convention, for the layout check."""

    label: str
    path: str
    call: str  # what the timed region runs, for the report
    fn: Callable[..., Any]
    prep: Callable[[tuple[np.ndarray, ...]], tuple[np.ndarray, ...]] = lambda x: x
    wrap: Callable[..., tuple[Any, ...]] | None = None
    post: Callable[[Any], np.ndarray] = lambda y: y
    compiled: bool = False
    raw: Callable[..., Any] | None = None  # jax and compiled torch: the function before jit / compile
    notes: list[str] = field(default_factory=list)
    broken: str | None = None  # a compiled peer that does not compile at all: why
    worked: bool = False  # a call has succeeded
    fell_back: bool = False  # a compiled peer recompiled with graph breaks allowed
    no_graph_breaks: str | None = None  # why a compiled peer is not retried with graph breaks


def _diffquat(op: str, module: Any) -> Callable[..., Any]:
    if op == "jlog":
        return lambda m: module.se3_right_jacobian_inverse(module.se3_log(m))
    return getattr(module, op)


DQ_CALLS = {
    "se3_exp": "se3_exp(xi)",
    "se3_log": "se3_log(T)",
    "se3_compose": "se3_compose(T1, T2)",
    "se3_inverse": "se3_inverse(T)",
    "se3_apply": "se3_apply(T, p)",
    "se3_right_jacobian": "se3_right_jacobian(xi)",
    "se3_plus": "se3_plus(T, d)",
    "jlog": "se3_right_jacobian_inverse(se3_log(T))",
}


def pypose_method(op: str) -> Method:
    import pypose as pp
    from pypose.lietensor.operation import se3_Jl

    pose, back = _pose("xyz_xyzw"), _from_pose("xyz_xyzw")
    layout = "SE3 as (t, q_xyzw) (N, 7)"
    table: dict[str, tuple[Any, ...]] = {
        "se3_exp": (
            lambda x: x.Exp(), lambda x: (pp.se3(x),), lambda a: a, back,
            "X = pp.se3(xi) outside; X.Exp()",
        ),
        "se3_log": (
            lambda x: x.Log(), lambda x: (pp.SE3(x),), lambda a: (pose(a[0]),), lambda y: y,
            f"X = pp.SE3(x) outside, {layout}; X.Log()",
        ),
        "se3_compose": (
            lambda a, b: a * b, lambda a, b: (pp.SE3(a), pp.SE3(b)), lambda a: tuple(map(pose, a)), back,
            "X * Y (pp.SE3 of (N, 7) each, built outside)",
        ),
        "se3_inverse": (
            lambda x: x.Inv(), lambda x: (pp.SE3(x),), lambda a: (pose(a[0]),), back, "X.Inv()",
        ),
        "se3_apply": (
            lambda x, p: x.Act(p), lambda x, p: (pp.SE3(x), p), lambda a: (pose(a[0]), a[1]), lambda y: y,
            "X.Act(p)",
        ),
        "se3_right_jacobian": (
            se3_Jl, None, lambda a: (-a[0],), lambda y: y,
            "pypose.lietensor.operation.se3_Jl(-xi) (= J_l(-xi) = J_r(xi); -xi formed outside; pypose's "
            "se3 LieTensor has no Jr, only so3's)",
        ),
        "se3_plus": (
            lambda x, d: x * d.Exp(), lambda x, d: (pp.SE3(x), pp.se3(d)), lambda a: (pose(a[0]), a[1]),
            back, "X * D.Exp() (D = pp.se3(d) built outside)",
        ),
    }  # fmt: skip
    fn, wrap, prep, post, call = table[op]
    method = Method("pypose", "torch eager", call, fn, prep, wrap, post)
    if op != "se3_right_jacobian":  # every other call goes through pypose's LieTensor
        method.no_graph_breaks = PYPOSE_NO_GRAPH_BREAKS
    return method


def torchlie_method(op: str) -> Method:
    import torchlie.functional as tf

    def right_jacobian(x: Any) -> Any:
        jacobians: list[Any] = []
        tf.SE3.exp(x, jacobians=jacobians)
        return jacobians[0]

    def jlog(g: Any) -> Any:
        jacobians: list[Any] = []
        tf.SE3.log(g, jacobians=jacobians)
        return jacobians[0]

    top = lambda a: tuple(_top(m) if m.shape[-2:] == (4, 4) else m for m in a)  # noqa: E731
    table: dict[str, tuple[Any, ...]] = {
        "se3_exp": (tf.SE3.exp, _from_top, "SE3.exp(xi) -> (N, 3, 4)"),
        "se3_log": (tf.SE3.log, lambda y: y, "SE3.log(g), g (N, 3, 4)"),
        "se3_compose": (tf.SE3.compose, _from_top, "SE3.compose(g1, g2)"),
        "se3_inverse": (tf.SE3.inv, _from_top, "SE3.inv(g)"),
        "se3_apply": (tf.SE3.transform, lambda y: y, "SE3.transform(g, p)"),
        "se3_right_jacobian": (
            right_jacobian,
            lambda y: y,
            "SE3.exp(xi, jacobians=J), J = J_r(xi) (the exp is computed as well; SE3.jexp itself raises "
            "AttributeError in torchlie 0.1.0: 'module ... has no attribute name')",
        ),
        "se3_plus": (lambda g, d: tf.SE3.compose(g, tf.SE3.exp(d)), _from_top, "SE3.compose(g, SE3.exp(d))"),
        "jlog": (
            jlog,
            lambda y: y,
            "SE3.log(g, jacobians=J), J = J_r^-1(log g) (the log is computed as well; SE3.jlog raises as "
            "jexp)",
        ),
    }
    fn, post, call = table[op]
    return Method("torchlie", "torch eager", call, fn, top, None, post)


def kornia_method(op: str) -> Method:
    from kornia.geometry.liegroup import Se3, So3
    from kornia.geometry.quaternion import Quaternion

    def se3(q: Any, t: Any) -> Any:
        return Se3(So3(Quaternion(q)), t)

    def qt(s: Any) -> tuple[Any, Any]:
        return s.r.q.data, s.t

    def pose_prep(a: tuple[np.ndarray, ...]) -> tuple[np.ndarray, ...]:
        out: list[np.ndarray] = []
        for m in a:
            out += [_q_wxyz(m), np.ascontiguousarray(m[..., :3, 3])] if m.shape[-2:] == (4, 4) else [m]
        return tuple(out)

    back = lambda y: _qt_to_matrix(*y)  # noqa: E731
    table: dict[str, tuple[Any, ...]] = {
        "se3_exp": (lambda x: qt(Se3.exp(x)), None, back, "Se3.exp(xi), returning (q_wxyz, t)"),
        "se3_log": (lambda s: s.log(), lambda q, t: (se3(q, t),), lambda y: y, "S.log()"),
        "se3_compose": (
            lambda a, b: qt(a * b), lambda q1, t1, q2, t2: (se3(q1, t1), se3(q2, t2)), back, "S1 * S2",
        ),
        "se3_inverse": (lambda s: qt(s.inverse()), lambda q, t: (se3(q, t),), back, "S.inverse()"),
        "se3_apply": (lambda s, p: s * p, lambda q, t, p: (se3(q, t), p), lambda y: y, "S * p"),
        "se3_plus": (lambda s, d: qt(s * Se3.exp(d)), lambda q, t, d: (se3(q, t), d), back, "S * Se3.exp(d)"),
    }  # fmt: skip
    fn, wrap, post, call = table[op]
    call += " (S = Se3(So3(Quaternion(q_wxyz)), t) built outside)" if wrap else ""
    return Method("kornia", "torch eager", call, fn, pose_prep, wrap, post)


def roma_method(op: str, unit_quaternion: bool) -> Method:
    import roma

    cls = roma.RigidUnitQuat if unit_quaternion else roma.Rigid

    def prep(a: tuple[np.ndarray, ...]) -> tuple[np.ndarray, ...]:
        out: list[np.ndarray] = []
        for m in a:
            if m.shape[-2:] == (4, 4):
                linear = _q_wxyz(m)[..., [1, 2, 3, 0]] if unit_quaternion else m[..., :3, :3]
                out += [np.ascontiguousarray(linear), np.ascontiguousarray(m[..., :3, 3])]
            else:
                out.append(m)
        return tuple(out)

    def back(y: tuple[np.ndarray, np.ndarray]) -> np.ndarray:
        linear, t = y
        if unit_quaternion:
            return _qt_to_matrix(linear[..., [3, 0, 1, 2]], t)
        return _rt_to_matrix(linear, t)

    def lt(r: Any) -> tuple[Any, Any]:
        return r.linear, r.translation

    table: dict[str, tuple[Any, ...]] = {
        "se3_compose": (
            lambda a, b: lt(a.compose(b)), lambda l1, t1, l2, t2: (cls(l1, t1), cls(l2, t2)), back,
            "A.compose(B)",
        ),
        "se3_inverse": (lambda a: lt(a.inverse()), lambda lin, t: (cls(lin, t),), back, "A.inverse()"),
        "se3_apply": (lambda a, p: a.apply(p), lambda lin, t, p: (cls(lin, t), p), lambda y: y, "A.apply(p)"),
    }  # fmt: skip
    fn, wrap, post, call = table[op]
    name = "RigidUnitQuat(q_xyzw, t)" if unit_quaternion else "Rigid(R, t)"
    label = "roma RigidUnitQuat" if unit_quaternion else "roma Rigid"
    return Method(label, "torch eager", f"{call} (A = roma.{name} built outside)", fn, prep, wrap, post)


def jaxlie_method(op: str) -> Method:
    import jax
    import jaxlie
    from jaxlie import SE3

    pose, back = _pose("wxyz_xyz"), _from_pose("wxyz_xyz")
    fns: dict[str, tuple[Any, ...]] = {
        "se3_exp": (lambda x: SE3.exp(x).wxyz_xyz, lambda a: a, back, "SE3.exp(xi).wxyz_xyz"),
        "se3_log": (lambda x: SE3(x).log(), lambda a: (pose(a[0]),), lambda y: y, "SE3(x).log()"),
        "se3_compose": (
            lambda a, b: (SE3(a) @ SE3(b)).wxyz_xyz, lambda a: tuple(map(pose, a)), back,
            "(SE3(a) @ SE3(b)).wxyz_xyz",
        ),
        "se3_inverse": (
            lambda x: SE3(x).inverse().wxyz_xyz, lambda a: (pose(a[0]),), back, "SE3(x).inverse()",
        ),
        "se3_apply": (
            lambda x, p: SE3(x).apply(p), lambda a: (pose(a[0]), a[1]), lambda y: y, "SE3(x).apply(p)",
        ),
        "se3_plus": (
            lambda x, d: jaxlie.manifold.rplus(SE3(x), d).wxyz_xyz, lambda a: (pose(a[0]), a[1]), back,
            "jaxlie.manifold.rplus(SE3(x), d) (= SE3(x) @ SE3.exp(d))",
        ),
        "jlog": (
            lambda x: SE3(x).jlog(), lambda a: (pose(a[0]),), lambda y: y, "SE3(x).jlog() = J_r^-1(log T)",
        ),
    }  # fmt: skip
    fn, prep, post, call = fns[op]
    call = f"jax.jit of {call}, x (N, 7) wxyz_xyz"
    return Method(JAXLIE, "jax.jit", call, jax.jit(fn), prep, None, post, raw=fn)


def scipy_method(op: str) -> Method:
    from scipy.spatial.transform import RigidTransform

    def poses(*a: np.ndarray) -> tuple[Any, ...]:
        return tuple(
            RigidTransform.from_matrix(m) if m.ndim == 3 and m.shape[-2:] == (4, 4) else m for m in a
        )

    as_matrix = lambda y: y.as_matrix()  # noqa: E731
    table: dict[str, tuple[Any, ...]] = {
        "se3_exp": (
            RigidTransform.from_exp_coords, lambda a: (_rotation_first(a[0]),), None, as_matrix,
            "RigidTransform.from_exp_coords(x), x = (phi, rho) reordered outside",
        ),
        "se3_log": (lambda a: a.as_exp_coords(), lambda a: a, poses, _rotation_first, "A.as_exp_coords()"),
        "se3_compose": (lambda a, b: a * b, lambda a: a, poses, as_matrix, "A * B"),
        "se3_inverse": (lambda a: a.inv(), lambda a: a, poses, as_matrix, "A.inv()"),
        "se3_apply": (lambda a, p: a.apply(p), lambda a: a, poses, lambda y: y, "A.apply(p)"),
        "se3_plus": (
            lambda a, d: a * RigidTransform.from_exp_coords(d), lambda a: (a[0], _rotation_first(a[1])),
            poses, as_matrix, "A * RigidTransform.from_exp_coords(d), d reordered outside",
        ),
    }  # fmt: skip
    fn, prep, wrap, post, call = table[op]
    call += " (A = RigidTransform.from_matrix(T) built outside)" if wrap else ""
    return Method(SCIPY, "numpy", call, fn, prep, wrap, post)


PEER_BUILDERS: dict[str, Callable[[str], Method]] = {
    "pypose": pypose_method,
    "torchlie": torchlie_method,
    "kornia": kornia_method,
    "roma Rigid": lambda op: roma_method(op, unit_quaternion=False),
    "roma RigidUnitQuat": lambda op: roma_method(op, unit_quaternion=True),
    JAXLIE: jaxlie_method,
    SCIPY: scipy_method,
}


_FRESH = itertools.count()


def _fresh(fn: Callable[..., Any]) -> Callable[..., Any]:
    """``fn`` with a code object of its own. dynamo keeps its compiled code, and counts recompilations
    against ``recompile_limit``, per code object: every compiled peer wrapped by one shared closure
    filled that one cache within a few operations, after which calls ran uncompiled (an earlier run of
    this benchmark: "found no compiled frames", ``FailOnRecompileLimitHit``)."""
    code = fn.__code__.replace(co_name=f"{fn.__code__.co_name}_{next(_FRESH)}")
    copy = types.FunctionType(code, fn.__globals__, code.co_name, fn.__defaults__, fn.__closure__)
    copy.__kwdefaults__ = fn.__kwdefaults__
    return copy


def compiled_peer(method: Method) -> Method:
    """The peer under ``torch.compile``: its wrapping and its call in one compiled function of the
    native tensors. ``fullgraph=True`` first (see :func:`_trial`)."""
    import torch

    fn, wrap = method.fn, method.wrap

    def whole(*tensors: Any) -> Any:
        return fn(*(wrap(*tensors) if wrap else tensors))

    whole = _fresh(whole)
    return Method(
        method.label + COMPILED,
        "torch.compile",
        "torch.compile of: " + method.call,
        torch.compile(whole, fullgraph=True),
        method.prep,
        None,
        method.post,
        compiled=True,
        raw=whole,
        no_graph_breaks=method.no_graph_breaks,
    )


def build_methods(op: str, quick: bool) -> tuple[list[Method], list[str]]:
    """Every method of one operation, and the peers left out with the reason."""
    import jax
    import torch

    import diffquat.jax as dqj
    import diffquat.numpy as dqn
    import diffquat.torch as dqt

    call = DQ_CALLS[op]
    methods = [Method(DQ["torch eager"], "torch eager", call, _diffquat(op, dqt))]
    if not quick:
        m = Method(
            DQ["torch.compile"],
            "torch.compile",
            f"torch.compile(fullgraph=True) of {call}",
            torch.compile(_fresh(_diffquat(op, dqt)), fullgraph=True),
            compiled=True,
        )
        methods.append(m)
    jm = Method(
        DQ["jax.jit"], "jax.jit", f"jax.jit of {call}", jax.jit(_diffquat(op, dqj)), raw=_diffquat(op, dqj)
    )
    methods += [jm, Method(DQ["numpy"], "numpy", f"{call}, float64", _diffquat(op, dqn))]
    skipped = []
    gaps = GAPS.get(op, {})
    for peer, build in PEER_BUILDERS.items():
        if peer in gaps:
            skipped.append(f"{peer}: {gaps[peer]}")
            continue
        try:
            method = build(op)
        except (ImportError, AttributeError) as error:
            skipped.append(f"{peer}: {type(error).__name__}: {error}")
            continue
        methods.append(method)
        if method.path == "torch eager" and not quick:
            methods.append(compiled_peer(method))
    return methods, skipped


# ---------------------------------------------------------------------------------------------------
# Timing


def _tensors(out: Any) -> tuple[Any, ...]:
    return tuple(out) if isinstance(out, (tuple, list)) else (out,)


def make_call(method: Method, inputs: tuple[np.ndarray, ...], backward: bool) -> Callable[[], Any] | None:
    """A zero-argument callable running the method once on its native inputs (float32; numpy float64),
    forward or forward + backward; None where the method has no backward (numpy)."""
    native = method.prep(inputs)
    if method.path == "numpy":
        if backward:
            return None
        args = method.wrap(*native) if method.wrap else native
        return lambda: method.fn(*args)
    native = tuple(np.ascontiguousarray(a, dtype=np.float32) for a in native)
    if method.path == "jax.jit":
        import jax
        import jax.numpy as jnp

        xs = tuple(jnp.asarray(a) for a in native)
        if not backward:
            return lambda: _sync(method.fn(*xs))
        raw = method.raw
        assert raw is not None
        cot = jax.tree.map(jnp.ones_like, method.fn(*xs))
        vjp = jax.jit(lambda xs, c: jax.vjp(raw, *xs)[1](c))
        return lambda: _sync(vjp(xs, cot))
    import torch

    ts = tuple(torch.from_numpy(a) for a in native)
    if backward:
        ts = tuple(t.clone().requires_grad_(True) for t in ts)
    args = method.wrap(*ts) if method.wrap and not method.compiled else ts
    if not backward:

        def forward() -> Any:
            with torch.no_grad():
                return method.fn(*args)

        return forward

    def forward_backward() -> Any:
        outs = _tensors(method.fn(*args))
        return torch.autograd.grad(outs, ts, [torch.ones_like(o) for o in outs])

    return forward_backward


def _reason(error: BaseException) -> str:
    text = f"{type(error).__name__}: {error}".strip().splitlines()
    return text[0][:300] if text else type(error).__name__


# Why a compiled peer is not retried with graph breaks (Method.no_graph_breaks).
PYPOSE_NO_GRAPH_BREAKS = (
    "not retried with graph breaks allowed: there, dynamo re-entered pypose's LieTensor.__torch_function__ "
    "until RecursionError in this benchmark's trial runs, and one run ended in it without a Python error"
)


class LeftOut(Exception):
    """A compiled peer that compiles neither with ``fullgraph=True`` nor with graph breaks: left out of
    every cell (the reason is in its notes)."""


def _trial(
    method: Method, inputs: tuple[np.ndarray, ...], backward: bool, where: str
) -> tuple[Callable[[], Any], float]:
    """The method's call, run once (its first call: compilation, warm-up), and how long that took.

    A compiled peer whose ``fullgraph=True`` compilation fails (in the cell ``where``) is recompiled
    with graph breaks allowed, for this cell and every later one, and that is noted; one that has never
    compiled and fails then too is left out of every cell (:class:`LeftOut`). Any other failure raises,
    for that cell alone."""
    import torch

    if method.broken:
        raise LeftOut(method.broken)
    call = make_call(method, inputs, backward)
    assert call is not None
    start = time.perf_counter()
    try:
        _sync(call())
    except Exception as error:
        peer = method.compiled and method.raw is not None and method.label != DQ["torch.compile"]
        if not peer or method.fell_back:
            raise
        reason = _reason(error)
        no_fallback = method.no_graph_breaks
        if no_fallback:
            if method.worked:
                raise
            method.broken = f"does not compile: fullgraph=True failed ({reason}); {no_fallback}; left out"
            method.notes.append(method.broken)
            raise LeftOut(method.broken) from error
        method.fell_back = True
        method.fn = torch.compile(_fresh(method.raw))
        call = make_call(method, inputs, backward)
        assert call is not None
        start = time.perf_counter()
        try:
            _sync(call())
        except Exception as again:
            if method.worked:
                method.notes.append(
                    f"fullgraph=True failed from {where} on ({reason}), and with graph breaks"
                )
                raise
            method.broken = (
                f"does not compile: fullgraph=True failed ({reason}), and with graph breaks allowed "
                f"({_reason(again)}); left out of every cell"
            )
            method.notes.append(method.broken)
            raise LeftOut(method.broken) from again
        first = "" if not method.worked else f" from {where} on (the cells before: fullgraph=True)"
        method.notes.append(f"fullgraph=True failed{first} ({reason}); timed with graph breaks allowed")
    method.worked = True
    return call, time.perf_counter() - start


MODES = (("forward", False), ("forward + backward", True))


def timings(
    ops: tuple[str, ...], sizes: tuple[int, ...], repeats: int, block_s: float, quick: bool
) -> dict[str, Any]:
    """op -> {"timings": mode -> N -> label -> Timing, "skipped", "failed", "calls", "notes"}."""
    import torch

    torch._dynamo.config.recompile_limit = 64
    torch._dynamo.config.accumulated_recompile_limit = 1024
    out: dict[str, Any] = {}
    for op in ops:
        methods, skipped = build_methods(op, quick)
        entry: dict[str, Any] = {"skipped": skipped, "failed": {}, "timings": {}}
        for mode, backward in MODES:
            per_n: dict[str, Any] = {}
            for n in sizes:
                inputs = canonical_inputs(op, n)
                calls: dict[str, Callable[[], Any]] = {}
                first: dict[str, float] = {}
                for m in methods:
                    if backward and m.path == "numpy":
                        continue
                    try:
                        with warnings.catch_warnings():
                            warnings.simplefilter("ignore")
                            calls[m.label], first[m.label] = _trial(m, inputs, backward, f"{mode}, N = {n}")
                    except LeftOut:
                        pass
                    except Exception as error:
                        entry["failed"].setdefault(m.label, []).append(f"{mode}, N = {n}: {_reason(error)}")
                with warnings.catch_warnings():
                    warnings.simplefilter("ignore")
                    timed = time_all(calls, repeats, block_s)
                for label, t in timed.items():
                    t.first_s = first[label]
                per_n[str(n)] = {label: t.__dict__ for label, t in timed.items()}
                del calls, inputs
                print(f"{op} {mode} N={n} done", file=sys.stderr, flush=True)
            entry["timings"][mode] = per_n
        entry["calls"] = {m.label: m.call for m in methods}
        entry["notes"] = {m.label: m.notes for m in methods if m.notes}
        entry["layout_check"] = layout_check(op, methods)
        out[op] = entry
    return out


def layout_check(op: str, methods: list[Method], n: int = 64) -> dict[str, float]:
    """Every method's forward output at N = 64 mapped back to diffquat's convention, against diffquat
    numpy in float64: the max abs difference (float32 rounding, ~1e-6, where the layouts are right)."""
    import diffquat.numpy as dqn

    inputs = canonical_inputs(op, n)
    expected = _diffquat(op, dqn)(*inputs)
    out = {}
    for m in methods:
        if m.compiled or m.broken:
            continue
        try:
            call = make_call(m, inputs, backward=False)
            assert call is not None
            with warnings.catch_warnings():
                warnings.simplefilter("ignore")
                got = m.post(_numpy(call()))
            out[m.label] = float(np.max(np.abs(np.asarray(got, dtype=np.float64) - expected)))
        except Exception as error:
            print(f"layout check {op} {m.label}: {_reason(error)}", file=sys.stderr)
            out[m.label] = float("nan")
    return out


def path_ratios(timed: dict[str, Any]) -> list[dict[str, Any]]:
    """Every cell: each peer's median time over diffquat's on the same path (above 1: diffquat is
    faster)."""
    cells = []
    for op, entry in timed.items():
        for mode, per_n in entry["timings"].items():
            for n, ts in per_n.items():
                for path, peers in PATHS.items():
                    ours = ts.get(DQ[path])
                    if ours is None:
                        continue
                    for peer in peers:
                        if peer in ts:
                            ratio = ts[peer]["median_s"] / ours["median_s"]
                            cell = {"op": op, "mode": mode, "n": int(n), "path": path, "peer": peer}
                            cell.update(ratio=ratio, peer_s=ts[peer]["median_s"], diffquat_s=ours["median_s"])
                            cells.append(cell)
    return cells


# ---------------------------------------------------------------------------------------------------
# Accuracy of the Jacobians


THETAS = (0.0, 1e-10, 1e-8, 1e-6, 1e-4, 3e-3, 1e-2, 0.3, 1.0, 1.5, 2.0, 3.0, math.pi - 1e-6)
RHO = (0.3, -0.7, 0.5)
AXIS = (0.48, 0.6, 0.64)  # unit: 0.48^2 + 0.6^2 + 0.64^2 = 1
SERIES_TERMS = 60
CHECK_THETA = 1.0
CHECK_TOLERANCE = 1e-12
DQ_BOUND = 8.0  # the test's bound on diffquat's float32 Q error, eps * |rho|


def twists(dtype: Any) -> np.ndarray:
    """The grid's twists ``(rho, theta * axis)``, rounded to ``dtype``: (len(THETAS), 6)."""
    phi = np.asarray(THETAS)[:, None] * np.asarray(AXIS)
    return np.concatenate([np.broadcast_to(np.asarray(RHO), phi.shape), phi], axis=-1).astype(dtype)


def _hat(v: np.ndarray) -> np.ndarray:
    x, y, z = v[..., 0], v[..., 1], v[..., 2]
    o = np.zeros_like(x)
    return np.stack([np.stack([o, -z, y], -1), np.stack([z, o, -x], -1), np.stack([-y, x, o], -1)], -2)


def _series_ld(xi: np.ndarray) -> np.ndarray:
    """``sum_n ad(xi)^n / (n + 1)!`` in numpy.longdouble, (K, 6, 6)."""
    xi = np.asarray(xi, dtype=np.longdouble)
    ad = np.zeros((*xi.shape[:-1], 6, 6), dtype=np.longdouble)
    ad[..., :3, :3] = ad[..., 3:, 3:] = _hat(xi[..., 3:])
    ad[..., :3, 3:] = _hat(xi[..., :3])
    total = np.zeros_like(ad)
    power = np.broadcast_to(np.eye(6, dtype=np.longdouble), ad.shape).copy()
    factorial = np.longdouble(1)
    for k in range(SERIES_TERMS):
        factorial *= k + 1
        total += power / factorial
        power = np.matmul(power, ad)
    return total


def _inverse_ld(j: np.ndarray) -> np.ndarray:
    """The inverse of block upper-triangular ``[[A, B], [0, A]]``: ``[[A^-1, -A^-1 B A^-1], [0, A^-1]]``,
    A^-1 by cofactors, in longdouble."""
    a, b = j[..., :3, :3], j[..., :3, 3:]
    r0, r1, r2 = a[..., 0, :], a[..., 1, :], a[..., 2, :]
    cof = np.stack([np.cross(r1, r2), np.cross(r2, r0), np.cross(r0, r1)], axis=-1)
    det = np.sum(r0 * np.cross(r1, r2), axis=-1)[..., None, None]
    inv = cof / det
    out = np.zeros_like(j)
    out[..., :3, :3] = out[..., 3:, 3:] = inv
    out[..., :3, 3:] = -np.matmul(np.matmul(inv, b), inv)
    return out


def series_jacobian(xi: np.ndarray, kind: str) -> np.ndarray:
    """The float64 reference at float64 twists: ``kind`` in J_l, J_r, J_l^-1, J_r^-1."""
    xi = np.asarray(xi, dtype=np.float64)
    j = _series_ld(-xi if kind.startswith("J_r") else xi)
    return (_inverse_ld(j) if kind.endswith("^-1") else j).astype(np.float64)


@dataclass
class AccuracyMethod:
    label: str  # library and backend
    function: str  # the call, in the peer's terms
    compared: str  # what it is compared with, in diffquat's terms
    group: str  # "J(xi)", "J^-1(xi)", "J_r^-1(log T)"
    evaluate: Callable[[Any], tuple[np.ndarray, np.ndarray]]  # dtype -> (result (K,6,6), reference)


def _torch_eval(fn: Callable[[Any], Any], x: np.ndarray) -> np.ndarray:
    import torch

    with torch.no_grad():
        return _numpy(fn(torch.from_numpy(np.ascontiguousarray(x))))


def _jax_eval(fn: Callable[[Any], Any], x: np.ndarray) -> np.ndarray:
    import jax
    import jax.numpy as jnp

    return np.asarray(jax.jit(fn)(jnp.asarray(x)), dtype=np.float64)


JACOBIANS = (
    ("se3_left_jacobian", "J_l"),
    ("se3_right_jacobian", "J_r"),
    ("se3_left_jacobian_inverse", "J_l^-1"),
    ("se3_right_jacobian_inverse", "J_r^-1"),
)
_JAX_RESULTS: dict[str, dict[str, np.ndarray]] = {}


def _dq_jax(name: str, x: np.ndarray) -> np.ndarray:
    """diffquat jax's Jacobians (and the jlog composite) on the grid, all in one ``jax.jit`` per dtype
    (one compilation instead of five: the quick run's accuracy table took 23 s, most of it compiling)."""
    import jax
    import jax.numpy as jnp

    import diffquat.jax as dqj

    key = x.dtype.name
    if key not in _JAX_RESULTS:

        def every(xi: Any, pose: Any) -> dict[str, Any]:
            out = {n: getattr(dqj, n)(xi) for n, _ in JACOBIANS}
            out["jlog"] = dqj.se3_right_jacobian_inverse(dqj.se3_log(pose))
            return out

        got = jax.jit(every)(jnp.asarray(twists(x.dtype)), jnp.asarray(_log_input(x.dtype)))
        _JAX_RESULTS[key] = {n: np.asarray(v, dtype=np.float64) for n, v in got.items()}
    expected = twists(x.dtype) if name != "jlog" else _log_input(x.dtype)
    assert np.array_equal(x, expected), "the grid's own inputs only"
    return _JAX_RESULTS[key][name]


def _dq_backends() -> list[tuple[str, Callable[[str, np.ndarray], np.ndarray]]]:
    """(label, evaluate(name, x)): each backend's evaluation of a diffquat function by name."""
    import diffquat.numpy as dqn
    import diffquat.torch as dqt

    def composite(module: Any) -> Callable[[Any], Any]:
        return lambda m: module.se3_right_jacobian_inverse(module.se3_log(m))

    def named(module: Any, name: str) -> Callable[[Any], Any]:
        return composite(module) if name == "jlog" else getattr(module, name)

    return [
        ("diffquat numpy", lambda name, x: np.asarray(named(dqn, name)(x), dtype=np.float64)),
        ("diffquat torch", lambda name, x: _torch_eval(named(dqt, name), x)),
        ("diffquat jax.jit", _dq_jax),
    ]


def _log_input(dtype: Any) -> np.ndarray:
    """The grid's poses ``exp(xi)`` computed in float64 and rounded to ``dtype``: (K, 4, 4)."""
    import diffquat.numpy as dqn

    return dqn.se3_exp(twists(np.float64)).astype(dtype)


def _log_reference(pose64: np.ndarray) -> np.ndarray:
    """``J_r^-1(log T)`` at the given float64 poses (the float32 input itself, widened), with the log in
    float64 (diffquat numpy)."""
    import diffquat.numpy as dqn

    return series_jacobian(dqn.se3_log(pose64), "J_r^-1")


def accuracy_methods() -> list[AccuracyMethod]:
    """Every SE(3) Jacobian compared, with its mapping onto diffquat's convention."""
    methods: list[AccuracyMethod] = []

    def at_xi(kind: str, run: Callable[[np.ndarray], np.ndarray]) -> Callable[[Any], Any]:
        def evaluate(dtype: Any) -> tuple[np.ndarray, np.ndarray]:
            x = twists(dtype)
            return run(x), series_jacobian(x.astype(np.float64), kind)

        return evaluate

    def at_log(run: Callable[[np.ndarray], np.ndarray], to_native: Callable[[np.ndarray], np.ndarray],
               from_native: Callable[[np.ndarray], np.ndarray]) -> Callable[[Any], Any]:  # fmt: skip
        def evaluate(dtype: Any) -> tuple[np.ndarray, np.ndarray]:
            native = to_native(_log_input(np.float64)).astype(dtype)  # rounded in the peer's layout
            return run(native), _log_reference(from_native(native.astype(np.float64)))

        return evaluate

    same = lambda x: x  # noqa: E731
    for label, evaluate in _dq_backends():
        for name, kind in JACOBIANS:
            group = "J^-1(xi)" if kind.endswith("^-1") else "J(xi)"
            run = lambda x, n=name, e=evaluate: e(n, x)  # noqa: E731
            methods.append(AccuracyMethod(label, f"{name}(xi)", f"{kind}(xi)", group, at_xi(kind, run)))
        run = lambda x, e=evaluate: e("jlog", x)  # noqa: E731
        methods.append(
            AccuracyMethod(
                label,
                "se3_right_jacobian_inverse(se3_log(T))",
                "J_r^-1(log T)",
                "J_r^-1(log T)",
                at_log(run, same, same),
            )
        )
    try:
        from pypose.lietensor.operation import se3_Jl, se3_Jl_inv

        methods.append(
            AccuracyMethod(
                "pypose",
                "pypose.lietensor.operation.se3_Jl(xi) (its SE3 backward's Jacobian)",
                "J_l(xi)",
                "J(xi)",
                at_xi("J_l", lambda x: _torch_eval(se3_Jl, x)),
            )
        )
        methods.append(
            AccuracyMethod(
                "pypose",
                "pypose.lietensor.operation.se3_Jl_inv(xi) (inside SE3.Jinvp)",
                "J_l^-1(xi)",
                "J^-1(xi)",
                at_xi("J_l^-1", lambda x: _torch_eval(se3_Jl_inv, x)),
            )
        )
    except ImportError:
        pass
    try:
        import torchlie.functional as tf

        def torchlie_jr(x: Any) -> Any:
            jacobians: list[Any] = []
            tf.SE3.exp(x, jacobians=jacobians)
            return jacobians[0]

        def torchlie_jlog(g: Any) -> Any:
            jacobians: list[Any] = []
            tf.SE3.log(g, jacobians=jacobians)
            return jacobians[0]

        methods.append(
            AccuracyMethod(
                "torchlie",
                "SE3.exp(xi, jacobians=J): J",
                "J_r(xi)",
                "J(xi)",
                at_xi("J_r", lambda x: _torch_eval(torchlie_jr, x)),
            )
        )
        methods.append(
            AccuracyMethod(
                "torchlie",
                "SE3.log(g, jacobians=J): J, g = the top 3x4 rows of T",
                "J_r^-1(log T)",
                "J_r^-1(log T)",
                at_log(lambda g: _torch_eval(torchlie_jlog, g), _top, _from_top),
            )
        )
    except ImportError:
        pass
    try:
        from jaxlie import SE3

        methods.append(
            AccuracyMethod(
                "jaxlie (jit)",
                "SE3(wxyz_xyz).jlog()",
                "J_r^-1(log T)",
                "J_r^-1(log T)",
                at_log(
                    lambda x: _jax_eval(lambda v: SE3(v).jlog(), x), _pose("wxyz_xyz"), _from_pose("wxyz_xyz")
                ),
            )
        )
    except ImportError:
        pass
    return methods


def _errors(got: np.ndarray, ref: np.ndarray, dtype: Any) -> dict[str, Any]:
    unit = float(np.finfo(dtype).eps) * float(np.linalg.norm(RHO))
    diff = np.abs(np.asarray(got, dtype=np.float64) - ref)
    q = diff[:, :3, 3:].reshape(len(THETAS), -1).max(-1) / unit
    whole = diff.reshape(len(THETAS), -1).max(-1) / unit
    return {"q": [float(v) for v in q], "whole": [float(v) for v in whole]}


def accuracy() -> dict[str, Any]:
    """float32 rows (jax at its default precision), then float64 rows (jax with x64 on, restored after),
    and the float64 mapping check at theta = 1."""
    import jax

    methods = accuracy_methods()
    out: dict[str, Any] = {"rows": [], "check": []}
    results: dict[str, dict[int, dict[str, Any]]] = {"float32": {}, "float64": {}}
    x64 = bool(jax.config.jax_enable_x64)
    for dtype in (np.float32, np.float64):
        name = np.dtype(dtype).name
        jax.config.update("jax_enable_x64", dtype == np.float64 or x64)
        for i, m in enumerate(methods):
            try:
                with warnings.catch_warnings():
                    warnings.simplefilter("ignore")
                    got, ref = m.evaluate(dtype)
                results[name][i] = {**_errors(got, ref, dtype), "raw": (got, ref)}
            except Exception as error:
                traceback.print_exc()
                results[name][i] = {"error": _reason(error)}
    jax.config.update("jax_enable_x64", x64)
    k = THETAS.index(CHECK_THETA)
    for i, m in enumerate(methods):
        row = {"label": m.label, "function": m.function, "compared": m.compared, "group": m.group}
        for name in ("float32", "float64"):
            r = results[name][i]
            row[name] = {key: v for key, v in r.items() if key != "raw"}
        out["rows"].append(row)
        r64 = results["float64"][i]
        if "raw" in r64:
            got, ref = r64["raw"]
            err = float(np.max(np.abs(got[k] - ref[k])))
            out["check"].append({**{key: row[key] for key in ("label", "function", "compared")}, "error": err,
                                 "ok": err < CHECK_TOLERANCE})  # fmt: skip
    out["thetas"] = list(THETAS)
    out["rho"] = list(RHO)
    out["axis"] = list(AXIS)
    out["series"] = {"terms": SERIES_TERMS, "longdouble_eps": float(np.finfo(np.longdouble).eps)}
    return out


# ---------------------------------------------------------------------------------------------------
# Report


def _ratio(r: float) -> str:
    return f"{r:.2f}x" if r >= 0.1 else f"{r:.2g}x"


def _units(x: float) -> str:
    if not np.isfinite(x):
        return "**nan**"
    return f"{x:.2g}" if x < 100 else f"{x:.2e}"


def _theta(t: float) -> str:
    return "pi - 1e-6" if abs(t - (math.pi - 1e-6)) < 1e-12 else f"{t:g}"


def command(results: dict[str, Any]) -> str:
    """The command line that wrote the results."""
    words = ["python -m benchmarks.se3"] + (["--quick"] if results["quick"] else [])
    if results["torch_threads"] != 1:
        words.append(f"--threads {results['torch_threads']}")
    if tuple(results["ops"]) != OPS:
        words.append("--ops " + ",".join(results["ops"]))
    if tuple(results["sizes"]) != (QUICK_SIZES if results["quick"] else FULL_SIZES):
        words.append("--sizes " + ",".join(str(n) for n in results["sizes"]))
    if results["repeats"] != DEFAULT_REPEATS[results["quick"]]:
        words.append(f"--repeats {results['repeats']}")
    return " ".join(words)


def render(results: dict[str, Any]) -> str:
    load = results["load"]
    sizes = results["sizes"]
    cells = results["ratios"]
    lines = [
        "# SE(3): diffquat against its peers",
        "",
        f"Written by `{command(results)}`; do not edit by hand. What is timed, the layouts and the "
        "accuracy reference are in the module's docstring (`benchmarks/se3.py`) and below. float32 (numpy "
        f"and scipy: float64), CPU, torch with {results['torch_threads']} thread(s)"
        + ("; `--quick` leaves out the `torch.compile` path." if results["quick"] else "."),
        "",
        f"Run time {results['seconds']:.0f} s; load average (1, 5, 15 min) before "
        f"{tuple(round(x, 2) for x in load['before'])}, after {tuple(round(x, 2) for x in load['after'])}: "
        "other jobs shared the machine, so absolute times are noisy; ratios were taken side by side "
        f"(medians over {results['repeats']} rotated blocks).",
        "",
        "## Ratios: peer time / diffquat time (above 1: diffquat is faster)",
        "",
        "Each path against the peers on it: diffquat torch eager against the torch peers called eagerly; "
        "diffquat under `torch.compile` against the same peers under `torch.compile`; `jax.jit` against "
        "jaxlie under `jax.jit`; numpy against scipy (float64, forward only). *fastest*: the fastest peer "
        "of the cell over diffquat.",
        "",
        "| path | cells (peer x op x mode x N) | peer / diffquat: range | fastest peer / diffquat: range "
        "| peer cells below 1.0x | below 0.9x |",
        "|---|---|---|---|---|---|",
    ]
    for path in PATHS:
        rs = [c["ratio"] for c in cells if c["path"] == path]
        if not rs:
            continue
        fastest = _fastest(cells, path)
        lines.append(
            f"| {path} | {len(rs)} | {_ratio(min(rs))}-{_ratio(max(rs))} | "
            f"{_ratio(min(fastest.values()))}-{_ratio(max(fastest.values()))} | "
            f"{sum(r < 1 for r in rs)} | {sum(r < 0.9 for r in rs)} |"
        )
    for path, peers in PATHS.items():
        present = [p for p in peers if any(c["peer"] == p for c in cells)]
        if not present:
            continue
        lines += ["", f"### {path}", "", "| op | mode | N | " + " | ".join(present) + " |"]
        lines.append("|---" * (len(present) + 3) + "|")
        for op in results["ops"]:
            for mode, _ in MODES:
                for n in sizes:
                    row = {c["peer"]: c["ratio"] for c in cells
                           if (c["path"], c["op"], c["mode"], c["n"]) == (path, op, mode, n)}  # fmt: skip
                    if not row:
                        continue
                    parts = [
                        "—" if p not in row else (f"**{_ratio(row[p])}**" if row[p] < 1 else _ratio(row[p]))
                        for p in present
                    ]
                    lines.append(f"| {op} | {mode} | {n} | " + " | ".join(parts) + " |")
    below = sorted((c for c in cells if c["ratio"] < 1), key=lambda c: c["ratio"])
    lines += [
        "",
        f"### Every cell where a peer is faster ({len(below)} of {len(cells)})",
        "",
        "| op | path | mode | N | peer | peer / diffquat | peer | diffquat |",
        "|---|---|---|---|---|---|---|---|",
    ]
    lines += [
        f"| {c['op']} | {c['path']} | {c['mode']} | {c['n']} | {c['peer']} | {_ratio(c['ratio'])} | "
        f"{_fmt_time(c['peer_s'])} | {_fmt_time(c['diffquat_s'])} |"
        for c in below
    ] or ["| none | | | | | | | |"]
    lines += ["", "## What is timed", "",
              "Inside the timed region, per library (the native inputs and any wrapping objects are built "
              "outside it; compiled functions take the native tensors and wrap them inside). *layout "
              "check*: the forward output at N = 64 converted back to diffquat's convention, max abs "
              "difference from diffquat numpy float64 (float32 rounding where the layouts are right).", "",
              "| op | method | call | layout check |", "|---|---|---|---|"]  # fmt: skip
    for op, entry in results["ops"].items():
        for label, call in entry["calls"].items():
            check = entry["layout_check"].get(label)
            lines.append(f"| {op} | {label} | {call} | {'—' if check is None else f'{check:.1e}'} |")
    notes = [
        f"- {op}, {label}: {'; '.join(n)}"
        for op, entry in results["ops"].items()
        for label, n in entry["notes"].items()
    ]
    failed = [
        f"- {op}, {label}: {'; '.join(f)}"
        for op, entry in results["ops"].items()
        for label, f in entry["failed"].items()
    ]
    skipped = [
        f"- {op}: " + "; ".join(entry["skipped"]) for op, entry in results["ops"].items() if entry["skipped"]
    ]
    lines += ["", "## Left out, and compilation", ""]
    lines += ["Peers without the operation:", "", *skipped, ""] if skipped else []
    if notes:
        lines += [
            "The peers under `torch.compile` (the others compiled with `fullgraph=True`):",
            "",
            *notes,
            "",
        ]
    elif not results["quick"]:
        lines += ["Every peer compiled with `fullgraph=True`.", ""]
    lines += (
        ["Cells not timed (the call failed; the first line of the error):", "", *failed, ""] if failed else []
    )
    lines += ["## Time per call", ""]
    for op, entry in results["ops"].items():
        for mode, per_n in entry["timings"].items():
            labels = list(dict.fromkeys(label for ts in per_n.values() for label in ts))
            lines += [f"### {op}, {mode}", "", "| method | " + " | ".join(f"N = {n}" for n in sizes) + " |"]
            lines.append("|---" * (len(sizes) + 1) + "|")
            for label in labels:
                row = [per_n[str(n)].get(label) for n in sizes]
                lines.append(
                    f"| {label} | "
                    + " | ".join("—" if t is None else _fmt_time(t["median_s"]) for t in row)
                    + " |"
                )
            for label in labels:
                if "jit" in label or "compile" in label:
                    row = [per_n[str(n)].get(label) for n in sizes]
                    lines.append(
                        f"| ({label}, first call: compilation) | "
                        + " | ".join("—" if t is None else _fmt_time(t["first_s"]) for t in row)
                        + " |"
                    )
            spread = max(t["spread"] for ts in per_n.values() for t in ts.values())
            lines += ["", f"Largest (max - min) / median over blocks: {spread:.0%}.", ""]
    lines += render_accuracy(results["accuracy"])
    lines += ["", "## Machine and versions", "", "| | |", "|---|---|"]
    lines += [f"| {k} | {v} |" for k, v in results["machine"].items()]
    return "\n".join(lines) + "\n"


def _fastest(cells: list[dict[str, Any]], path: str) -> dict[tuple[str, str, int], float]:
    out: dict[tuple[str, str, int], float] = {}
    for c in cells:
        if c["path"] == path:
            key = (c["op"], c["mode"], c["n"])
            out[key] = min(out.get(key, math.inf), c["ratio"])
    return out


def render_accuracy(acc: dict[str, Any]) -> list[str]:
    rho = float(np.linalg.norm(RHO))
    lines = [
        "## Accuracy of the SE(3) Jacobians",
        "",
        f"rho = {tuple(acc['rho'])} (|rho| = {rho:.4f}), phi = theta * {tuple(acc['axis'])}, rounded to the "
        "dtype; every result against the series sum_n ad(xi)^n / (n + 1)! "
        f"({acc['series']['terms']} terms, summed in numpy.longdouble, eps "
        f"{acc['series']['longdouble_eps']:.1e}, rounded to float64) at the rounded input itself, inverted "
        "(blockwise, in longdouble) for the inverses. *J_r^-1(log T)* rows: the input is the pose "
        "exp(xi) computed in float64 and rounded to the dtype in the method's own layout (a quaternion "
        "for jaxlie, the 3x4 top rows for torchlie), and the reference is the series at the float64 log "
        "(diffquat numpy) of that rounded pose; the rounded rotation is not exactly orthogonal, which "
        "adds up to about one unit to these rows. jax runs under `jax.jit`, torch eagerly.",
        "",
        "### The mapping onto diffquat's convention, checked in float64 at theta = 1",
        "",
        "| library | function | compared with | max abs error, whole 6x6 | mapping |",
        "|---|---|---|---|---|",
    ]
    for c in acc["check"]:
        ok = "ok" if c["ok"] else "**not within 1e-12**"
        lines.append(f"| {c['label']} | {c['function']} | {c['compared']} | {c['error']:.1e} | {ok} |")
    header = "| library | function | compared with | " + " | ".join(_theta(t) for t in acc["thetas"])
    for dtype in ("float32", "float64"):
        lines += [
            "",
            f"### {dtype}: error of the upper-right 3x3 block, in {dtype} eps * |rho|",
            "",
            "(Q of J_l; Q(-rho, -phi) of J_r; -J^-1 Q J^-1 of the inverses.) Last column: the whole 6x6, "
            "the largest over theta.",
            "",
            header + " | whole, max |",
            "|---" * (len(acc["thetas"]) + 4) + "|",
        ]
        for r in acc["rows"]:
            e = r[dtype]
            if "error" in e:
                lines.append(f"| {r['label']} | {r['function']} | {r['compared']} | failed: {e['error']} |")
                continue
            lines.append(
                f"| {r['label']} | {r['function']} | {r['compared']} | "
                + " | ".join(_units(v) for v in e["q"])
                + f" | {_units(max(e['whole']))} |"
            )
    return lines


def run(
    quick: bool, out_dir: Path, ops: tuple[str, ...] = OPS, sizes: tuple[int, ...] | None = None,
    repeats: int | None = None,
) -> dict[str, Any]:  # fmt: skip
    import torch

    sizes = sizes or (QUICK_SIZES if quick else FULL_SIZES)
    repeats = repeats or DEFAULT_REPEATS[quick]
    block_s = 0.002 if quick else 0.03
    started = time.time()
    load_before = os.getloadavg()
    timed = timings(ops, sizes, repeats, block_s, quick)
    results: dict[str, Any] = {
        "quick": quick,
        "sizes": list(sizes),
        "repeats": repeats,
        "block_s": block_s,
        "torch_threads": torch.get_num_threads(),
        "ops": timed,
        "ratios": path_ratios(timed),
        "accuracy": accuracy(),
    }
    return finish(results, started, load_before, out_dir, "se3", render)


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--quick", action="store_true", help="N = 64, few repeats, no torch.compile: seconds")
    parser.add_argument("--out", type=Path, default=Path(__file__).resolve().parent)
    parser.add_argument("--threads", type=int, default=1, help="torch's CPU threads (default 1)")
    parser.add_argument("--ops", help="comma-separated operations (default: all)")
    parser.add_argument("--sizes", help="comma-separated batch sizes N (default: run.py's grid; --quick: 64)")
    parser.add_argument("--repeats", type=int, help="rotated blocks per cell (default: 7; --quick: 2)")
    args = parser.parse_args(argv)
    import torch

    torch.set_num_threads(args.threads)
    ops = tuple(args.ops.split(",")) if args.ops else OPS
    sizes = tuple(int(n) for n in args.sizes.split(",")) if args.sizes else None
    run(args.quick, args.out, ops, sizes, args.repeats)


if __name__ == "__main__":
    main()
