"""ATen operations per eager torch call: every public function of ``diffquat.torch`` beside the peers
that do the same job, forward and forward + backward. ``python -m benchmarks.ops [--out DIR]`` writes
``ops.json`` and ``OPS.md`` (default: next to this file); ``tests/test_ops.py`` pins diffquat's counts
at ``ops.json``'s, so regenerate the table with that command after a change that adds or removes
operations.

Eager torch pays for each ATen operation on its own (a dispatch on the CPU, a kernel launch on a GPU),
so their number per call is the eager cost that does not shrink with the batch (issue 46). Counted
with a ``TorchDispatchMode`` that sees every operation dispatched, ``aten.detach.default`` excepted
(autograd's bookkeeping, the rule of the project's ``before-stop`` hook), in one call made after one
warm-up call of the same kind:

- forward: ``f(*xs)`` on float32 inputs that do not require grad;
- forward + backward: ``f(*xs)`` on fresh float32 leaves that require grad, then
  the sum of ``o.sum()`` over the floating outputs, ``.backward()`` (the loss's operations are
  counted too, alike for every method: a ``sum`` per output, the additions, and their backward).

The inputs are those of the rows of ``tests/cases.py`` (``OPS``) at N = 8 random rotations (seed 0):
one row per public function and keyword variant, plus the public functions the table has no row for
(the samplers, with a fixed generator, and ``se3_to_rotation_translation``). diffquat's counts depend
on the code, the shapes, the device and the torch version (recorded), not on the values (no Python
branch reads an array value) or the machine: they are exact, and pinned.

Each peer takes its own layout (scalar-last quaternions, pypose's ``(t, q)`` poses, torchlie's 3x4
poses, roma's ``Rigid``, a 6D as two columns), converted outside the counted region; its output is
converted back outside it too and compared with diffquat's float64 result on the same inputs, in
float64. A peer that disagrees there (another job, or another branch of the result) is left out of
the budget (reported). Then every peer is run at the named edge cases of the suite (``EDGE_CASES``:
the identity, the exact and near half-turns, near the identity, the exact quaternions of
{0, +-1/2, +-1} (w = 0 exactly among them), extreme norms, the zero quaternion, each where the row
applies), in float64: a peer is wrong at an edge where diffquat's value or gradient is finite and
the peer's is not, or where the two values differ by more than ``EDGE_TOL`` (relative to the size of
the result, up to sign where the result is defined up to sign, modulo 2 pi for angles).

Budgets (issue 46, point 2): at most the count of every peer that is right at every edge, and at most
1.5x that of one that is wrong at an edge (the edge named); ``quaternion_to_matrix`` at most 12 / 30,
``matrix_to_quaternion`` at most 25 / 60; a function no peer has, at most half of its count at commit
``BEFORE_COMMIT`` (``BEFORE``).
"""

from __future__ import annotations

import argparse
import collections
import functools
import json
import math
import operator
import platform
import sys
import warnings
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import torch

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT / "tests"))

import cases  # noqa: E402  (the suite's table of operations: its rows' inputs are counted here)

import diffquat.torch as dq  # noqa: E402

N = 8
SEED = 0
COMMAND = "python -m benchmarks.ops"
# The named cases at which each peer is checked (float64), where the row applies.
EDGE_CASES = ("identity", "half_turns", "near_half_turns", "near_identity", "gimbal_lock", "norms", "zero")
EDGE_TOL = 1e-6
AGREE_TOL = 1e-9  # float64, on the N = 8 random inputs

# The counts of the tree before issue 46's work (commit BEFORE_COMMIT), measured by this module's own
# rules (forward, forward + backward; None: no output has a gradient). Fixed: the baseline that the
# budgets of the functions no peer has are set from. They equal the figures of the first count of
# that tree (issue 46's sketch) row for row, except where the sketch also counted the table's join of
# a pair (cases.Op.join: fit_similarity_transform's s T, the B-splines' packed outputs; 2-3 more), and
# less one in forward + backward: that first count's loss was Python's sum, whose 0 + tensor added one.
BEFORE_COMMIT = "266ec9f"
BEFORE: dict[str, tuple[int, int | None]] = {
    "quaternion_to_matrix": (71, 201),
    "matrix_to_quaternion": (95, 208),
    "standardize_quaternion": (29, 40),
    "normalize_quaternion": (35, 90),
    "wxyz_to_xyzw": (14, 30),
    "xyzw_to_wxyz": (14, 30),
    "rotation_6d_to_matrix": (88, 206),
    "matrix_to_rotation_6d": (12, 22),
    "rotation_6d_to_matrix[rows]": (88, 206),
    "matrix_to_rotation_6d[rows]": (12, 22),
    "special_procrustes": (37, 146),
    "special_procrustes-reflection": (37, 146),
    "special_procrustes-rank2": (37, 146),
    "symmetric_matrix_to_quaternion": (63, 306),
    "fit_rotation": (57, 180),
    "fit_rotation-unweighted": (50, 169),
    "axis_angle_to_quaternion": (34, 100),
    "quaternion_to_axis_angle": (84, 203),
    "axis_angle_to_matrix": (64, 197),
    "matrix_to_axis_angle": (170, 397),
    "euler_angles_to_matrix[XYZ]": (152, 391),
    "matrix_to_euler_angles[ZXZ]": (92, 210),
    "euler_angles_to_quaternion[zyx]": (81, 193),
    "quaternion_to_euler_angles[xzx]": (87, 218),
    "quaternion_multiply": (52, 137),
    "quaternion_conjugate": (17, 36),
    "quaternion_invert": (58, 175),
    "quaternion_apply": (72, 193),
    "quaternion_slerp": (251, 647),
    "quaternion_geodesic_distance": (100, 229),
    "matrix_geodesic_distance": (186, 436),
    "so3_hat": (18, 44),
    "so3_vee": (26, 55),
    "so3_exp": (64, 197),
    "so3_log": (170, 397),
    "so3_left_jacobian": (65, 219),
    "so3_right_jacobian": (66, 221),
    "so3_left_jacobian_inverse": (53, 176),
    "so3_right_jacobian_inverse": (53, 176),
    "so3_plus[left]": (120, 323),
    "so3_minus[left]": (180, 419),
    "quaternion_plus[left]": (60, 160),
    "quaternion_minus[left]": (133, 323),
    "se3_from_rotation_translation": (25, 41),
    "se3_compose": (21, 41),
    "se3_inverse": (20, 42),
    "se3_apply": (19, 36),
    "se3_hat": (25, 60),
    "se3_vee": (31, 67),
    "se3_exp": (134, 388),
    "se3_log": (222, 540),
    "se3_adjoint": (32, 78),
    "se3_ad": (33, 91),
    "se3_left_jacobian": (226, 692),
    "se3_right_jacobian": (227, 694),
    "se3_left_jacobian_inverse": (227, 678),
    "se3_right_jacobian_inverse": (228, 680),
    "se3_plus[left]": (149, 418),
    "se3_minus[left]": (266, 620),
    "pose_to_matrix[xyz_xyzw]": (90, 230),
    "matrix_to_pose[xyzw_xyz]": (109, 241),
    "se3_interpolate": (421, 1051),
    "matrix_fisher_log_normalizer": (185, 477),
    "matrix_fisher_nll": (195, 495),
    "matrix_fisher_mode": (37, 146),
    "bingham_nll": (251, 604),
    "rotation_mean[chordal]": (50, 166),
    "rotation_mean[geodesic]": (187, 821),
    "rotation_mean[geodesic_l1]": (187, 836),
    "quaternion_mean": (142, 508),
    "symmetric_geodesic_distance": (218, 514),
    "se3_mean": (74, 217),
    "fit_rigid_transform": (105, 301),
    "fit_similarity_transform": (128, 379),
    "rotation_between_vectors": (173, 424),
    "frame_from_three_points": (111, 247),
    "igso3_log_density": (146, 354),
    "igso3_angle_cdf": (101, 240),
    "igso3_score": (491, 1225),
    "angular_velocity": (102, 282),
    "quaternion_derivative[space]": (54, 131),
    "angular_acceleration": (201, 583),
    "integrate_angular_velocity[space]": (79, 187),
    "angular_velocity_from_quaternions": (151, 356),
    "quaternion_squad": (991, 2551),
    "so3_bspline": (585, 1473),
    "se3_bspline": (993, 2536),
    "se3_bspline[split]": (705, 1740),
    "se3_to_rotation_translation": (12, 24),
    "igso3_sample": (4781, 5071),
    "matrix_fisher_sample": (410, None),
}

# The explicit budgets of issue 46 (forward, forward + backward).
FIXED_BUDGETS: dict[str, tuple[int, int]] = {
    "quaternion_to_matrix": (12, 30),
    "matrix_to_quaternion": (25, 60),
}


# ---------------------------------------------------------------------------------------------------
# Counting


def _counter_mode() -> Any:
    from torch.utils._python_dispatch import TorchDispatchMode

    class OpCounter(TorchDispatchMode):
        """Counts every ATen operation dispatched inside it, ``aten.detach.default`` excepted."""

        def __init__(self) -> None:
            super().__init__()
            self.ops: collections.Counter[str] = collections.Counter()

        def __torch_dispatch__(self, func: Any, types: Any, args: Any = (), kwargs: Any = None) -> Any:
            if func is not torch.ops.aten.detach.default:
                self.ops[str(func)] += 1
            return func(*args, **(kwargs or {}))

    return OpCounter()


def _outputs(out: Any) -> list[Any]:
    outs = out if isinstance(out, (tuple, list)) else (out,)
    return [o for o in outs if o.dtype.is_floating_point]


def _loss(out: Any) -> Any:
    # reduce, not sum(): Python's sum starts from 0, and 0 + tensor is an operation of its own
    return functools.reduce(operator.add, (o.sum() for o in _outputs(out)))


def _leaves(xs: Sequence[Any]) -> list[Any]:
    return [x.detach().clone().requires_grad_() if x.is_floating_point() else x for x in xs]


def count_forward(fn: Callable[..., Any], xs: Sequence[Any]) -> collections.Counter[str]:
    """The operations of ``fn(*xs)``, after one warm-up call: a Counter of operation names."""
    fn(*xs)
    with _counter_mode() as mode:
        fn(*xs)
    return mode.ops


def count_backward(fn: Callable[..., Any], xs: Sequence[Any]) -> collections.Counter[str] | None:
    """The operations of ``fn(*leaves)`` and the backward of the sum of its floating outputs, on fresh
    leaves that require grad, after one warm-up call of the same; None when no output has a gradient."""
    out = fn(*_leaves(xs))
    loss = _loss(out)
    if not getattr(loss, "requires_grad", False):
        return None
    loss.backward()
    leaves = _leaves(xs)
    with _counter_mode() as mode:
        _loss(fn(*leaves)).backward()
    return mode.ops


def count(fn: Callable[..., Any], xs: Sequence[Any]) -> tuple[int, int | None]:
    """(forward, forward + backward) operation counts of ``fn`` on ``xs``."""
    backward = count_backward(fn, xs)
    return sum(count_forward(fn, xs).values()), None if backward is None else sum(backward.values())


# ---------------------------------------------------------------------------------------------------
# diffquat's rows


@dataclass
class Row:
    """One public function (and keyword variant) of diffquat.torch with its inputs."""

    id: str
    name: str
    kwargs: dict[str, Any]
    # case quaternions (float64) -> float64 input arrays
    inputs: Callable[[np.ndarray], tuple[np.ndarray, ...]]
    op: Any = None  # the cases.Op row, where the table has one
    # for the public functions outside the table: how they are called (a generator for the samplers)
    call: Callable[..., Any] | None = None

    def function(self) -> Callable[..., Any]:
        if self.call is not None:
            return self.call
        f = getattr(dq, self.name)
        return lambda *xs: f(*xs, **self.kwargs)

    def tensors(self, q: np.ndarray, dtype: Any) -> list[Any]:
        return [torch.tensor(np.asarray(x), dtype=dtype) for x in self.inputs(q)]


def _sampler(name: str) -> Callable[..., Any]:
    def call(x: Any) -> Any:
        # a fixed seed per call: the same draw, the same operations
        return getattr(dq, name)(x, generator=torch.Generator().manual_seed(0))

    return call


def rows() -> list[Row]:
    """Every row of ``cases.OPS``, then the public functions that take tensors and have no row."""
    out = [Row(op.id, op.name, dict(op.kwargs), op.inputs, op) for op in cases.OPS]
    extra = [
        Row("se3_to_rotation_translation", "se3_to_rotation_translation", {}, lambda q: (_poses(q),)),
        Row(
            "igso3_sample",
            "igso3_sample",
            {},
            lambda q: (np.full(len(q), 0.5),),
            call=_sampler("igso3_sample"),
        ),
        Row(
            "matrix_fisher_sample",
            "matrix_fisher_sample",
            {},
            lambda q: (3.0 * cases.oracle_quaternion_to_matrix(q),),
            call=_sampler("matrix_fisher_sample"),
        ),
    ]
    covered = {r.name for r in out} | {r.name for r in extra}
    # the functions that take no tensor (a shape or a name): nothing of the caller's to count
    no_tensor = {"random_quaternions", "symmetry_group"}
    # the objects: each method is one function's call, with the very operations of its row
    # (tests/test_objects.py::test_methods_dispatch_the_functions_operations)
    objects = {"SO3", "SE3"}
    missing = set(dq.__all__) - covered - no_tensor - objects
    if missing:
        raise RuntimeError(f"public functions without a row in benchmarks/ops.py: {sorted(missing)}")
    return out + extra


def _poses(q: np.ndarray) -> np.ndarray:
    pose = np.zeros((*q.shape[:-1], 4, 4))
    pose[..., :3, :3] = cases.oracle_quaternion_to_matrix(q)
    pose[..., :3, 3] = q[..., 1:] * 2.0 - q[..., :1]
    pose[..., 3, 3] = 1.0
    return pose


# ---------------------------------------------------------------------------------------------------
# Peers


@dataclass
class Peer:
    """One peer's spelling of a row's job. ``prep`` maps diffquat's inputs (torch tensors, diffquat's
    layout) to the peer's, ``post`` the peer's output back to diffquat's; both run outside the counted
    region. ``up_to_sign``: the result is defined up to sign (an axis-angle at pi, a quaternion)."""

    label: str
    fn: Callable[..., Any]
    prep: Callable[..., tuple[Any, ...]] = lambda *xs: xs
    post: Callable[[Any], Any] = lambda y: y
    up_to_sign: bool = False
    note: str = ""


def _xyzw(q: Any) -> Any:
    return q[..., [1, 2, 3, 0]].contiguous()


def _wxyz(q: Any) -> Any:
    return q[..., [3, 0, 1, 2]].contiguous()


def _pad34(t: Any) -> Any:
    """A 3x4 pose (torchlie's) as 4x4."""
    bottom = torch.zeros_like(t[..., :1, :])
    bottom[..., 0, 3] = 1
    return torch.cat([t, bottom], dim=-2)


def _homogeneous(r: Any, t: Any) -> Any:
    return _pad34(torch.cat([r, t[..., None]], dim=-1))


def _pose7(m: Any) -> Any:
    """A 4x4 pose as pypose's (t, q_xyzw)."""
    return dq.matrix_to_pose(m, layout="xyz_xyzw")


def _from_pose7(x: Any) -> Any:
    return dq.pose_to_matrix(x, layout="xyz_xyzw")


def _canonical_pose(x: Any) -> Any:
    """pypose's (t, q_xyzw) as diffquat's "xyzw_xyz" layout, the quaternion in canonical sign."""
    return torch.cat([dq.standardize_quaternion(x[..., 3:], scalar_first=False), x[..., :3]], dim=-1)


def _attribute(module: Any, dotted: str) -> Any:
    for part in dotted.split("."):
        module = getattr(module, part)
    return module


def _d6_columns(d6: Any) -> Any:
    """diffquat's 6D (two columns, concatenated) as roma's (..., 3, 2)."""
    return d6.reshape(*d6.shape[:-1], 2, 3).transpose(-1, -2).contiguous()


def peers() -> tuple[dict[str, list[Peer]], list[str]]:
    """The peers of each row (by row id), each built only where its library imports; and the peers
    left out (their library not installed)."""
    table: dict[str, list[Peer]] = collections.defaultdict(list)
    missing: list[str] = []

    def add(ids: str | Sequence[str], build: Callable[[], Peer]) -> None:
        try:
            peer = build()
        except (ImportError, AttributeError) as error:
            missing.append(f"{error}")
            return
        for row_id in [ids] if isinstance(ids, str) else ids:
            table[row_id].append(peer)

    def roma_peers() -> None:
        import roma

        add(
            "quaternion_to_matrix",
            lambda: Peer(
                "roma (quat_normalize + unitquat_to_rotmat)",
                lambda q: roma.unitquat_to_rotmat(roma.quat_normalize(q)),
                prep=lambda q: (_xyzw(q),),
            ),
        )
        add(
            "matrix_to_quaternion",
            lambda: Peer("roma (rotmat_to_unitquat)", roma.rotmat_to_unitquat, post=_wxyz, up_to_sign=True),
        )
        add("normalize_quaternion", lambda: Peer("roma (quat_normalize)", roma.quat_normalize))
        add("wxyz_to_xyzw", lambda: Peer("roma (quat_wxyz_to_xyzw)", roma.quat_wxyz_to_xyzw))
        add("xyzw_to_wxyz", lambda: Peer("roma (quat_xyzw_to_wxyz)", roma.quat_xyzw_to_wxyz))
        add(
            "rotation_6d_to_matrix",
            lambda: Peer(
                "roma (special_gramschmidt)", roma.special_gramschmidt, prep=lambda d6: (_d6_columns(d6),)
            ),
        )
        add(
            "rotation_6d_to_matrix[rows]",
            lambda: Peer(
                "roma (special_gramschmidt)",
                roma.special_gramschmidt,
                prep=lambda d6: (_d6_columns(d6),),
                post=lambda m: m.transpose(-1, -2),
            ),
        )
        add(
            [
                "special_procrustes",
                "special_procrustes-reflection",
                "special_procrustes-rank2",
                "matrix_fisher_mode",
            ],
            lambda: Peer("roma (special_procrustes)", roma.special_procrustes),
        )
        add(
            "symmetric_matrix_to_quaternion",
            lambda: Peer(
                "roma (symmatrixvec_to_unitquat)",
                roma.symmatrixvec_to_unitquat,
                prep=lambda a: (torch.from_numpy(cases.a10_to_scalar_last(a.numpy())),),
                post=_wxyz,
                up_to_sign=True,
            ),
        )
        add(
            "fit_rotation",
            lambda: Peer(
                "roma (rigid_vectors_registration)", lambda x, y, w: roma.rigid_vectors_registration(x, y, w)
            ),
        )
        add(
            "fit_rotation-unweighted",
            lambda: Peer(
                "roma (rigid_vectors_registration)", lambda x, y: roma.rigid_vectors_registration(x, y)
            ),
        )
        add(
            "fit_rigid_transform",
            lambda: Peer(
                "roma (rigid_points_registration)",
                lambda x, y, w: roma.rigid_points_registration(x, y, w),
                post=lambda rt: _homogeneous(*rt),
            ),
        )
        add(
            "fit_similarity_transform",
            lambda: Peer(
                "roma (rigid_points_registration, compute_scaling)",
                lambda x, y, w: roma.rigid_points_registration(x, y, w, compute_scaling=True),
                post=lambda rts: (_homogeneous(rts[0], rts[1]), rts[2]),
            ),
        )
        add(
            "axis_angle_to_quaternion",
            lambda: Peer("roma (rotvec_to_unitquat)", roma.rotvec_to_unitquat, post=_wxyz),
        )
        add(
            "quaternion_to_axis_angle",
            lambda: Peer(
                "roma (unitquat_to_rotvec)",
                roma.unitquat_to_rotvec,
                prep=lambda q: (_xyzw(q),),
                up_to_sign=True,
            ),
        )
        add(
            ["axis_angle_to_matrix", "so3_exp"],
            lambda: Peer("roma (rotvec_to_rotmat)", roma.rotvec_to_rotmat),
        )
        add(
            ["matrix_to_axis_angle", "so3_log"],
            lambda: Peer("roma (rotmat_to_rotvec)", roma.rotmat_to_rotvec, up_to_sign=True),
        )
        add(
            "euler_angles_to_matrix[XYZ]",
            lambda: Peer("roma (euler_to_rotmat)", lambda a: roma.euler_to_rotmat("XYZ", a)),
        )
        add(
            "matrix_to_euler_angles[ZXZ]",
            lambda: Peer("roma (rotmat_to_euler)", lambda m: roma.rotmat_to_euler("ZXZ", m)),
        )
        add(
            "euler_angles_to_quaternion[zyx]",
            lambda: Peer(
                "roma (euler_to_unitquat)",
                lambda a: roma.euler_to_unitquat("zyx", a),
                post=_wxyz,
                up_to_sign=True,
            ),
        )
        add(
            "quaternion_to_euler_angles[xzx]",
            lambda: Peer(
                "roma (unitquat_to_euler)",
                lambda q: roma.unitquat_to_euler("xzx", q),
                prep=lambda q: (_xyzw(q),),
            ),
        )
        add(
            "quaternion_multiply",
            lambda: Peer(
                "roma (quat_product)", roma.quat_product, prep=lambda p, q: (_xyzw(p), _xyzw(q)), post=_wxyz
            ),
        )
        add(
            "quaternion_conjugate",
            lambda: Peer(
                "roma (quat_conjugation)", roma.quat_conjugation, prep=lambda q: (_xyzw(q),), post=_wxyz
            ),
        )
        add(
            "quaternion_invert",
            lambda: Peer("roma (quat_inverse)", roma.quat_inverse, prep=lambda q: (_xyzw(q),), post=_wxyz),
        )
        add(
            "quaternion_apply",
            lambda: Peer("roma (quat_action)", roma.quat_action, prep=lambda q, v: (_xyzw(q), v)),
        )
        # one t per rotation: roma interpolates every pair at every step (a (K, B, 4) result); the
        # diagonal is this row's job, taken outside the count (the count does not depend on K or B)
        add(
            "quaternion_slerp",
            lambda: Peer(
                "roma (unitquat_slerp)",
                roma.unitquat_slerp,
                prep=lambda p, q, t: (_xyzw(p), _xyzw(q), t),
                post=lambda y: _wxyz(y.diagonal(dim1=0, dim2=1).transpose(0, -1)),
                up_to_sign=True,
                note="evaluates every pair at every t; the diagonal is compared",
            ),
        )
        add(
            "quaternion_geodesic_distance",
            lambda: Peer(
                "roma (unitquat_geodesic_distance)",
                roma.unitquat_geodesic_distance,
                prep=lambda p, q: (_xyzw(p), _xyzw(q)),
            ),
        )
        add(
            "matrix_geodesic_distance",
            lambda: Peer("roma (rotmat_geodesic_distance)", roma.rotmat_geodesic_distance),
        )
        add(
            "so3_plus[left]",
            lambda: Peer("roma (rotvec_to_rotmat, matmul)", lambda m, d: roma.rotvec_to_rotmat(d) @ m),
        )
        add(
            "so3_minus[left]",
            lambda: Peer(
                "roma (rotmat_to_rotvec of R1 R2^T)",
                lambda a, b: roma.rotmat_to_rotvec(a @ b.transpose(-1, -2)),
                up_to_sign=True,
            ),
        )
        add(
            "quaternion_plus[left]",
            lambda: Peer(
                "roma (rotvec_to_unitquat, quat_product)",
                lambda q, d: roma.quat_product(roma.rotvec_to_unitquat(d), q),
                prep=lambda q, d: (_xyzw(q), d),
                post=_wxyz,
            ),
        )
        add(
            "quaternion_minus[left]",
            lambda: Peer(
                "roma (unitquat_to_rotvec of q1 q2*)",
                lambda a, b: roma.unitquat_to_rotvec(roma.quat_product(a, roma.quat_conjugation(b))),
                prep=lambda a, b: (_xyzw(a), _xyzw(b)),
                up_to_sign=True,
            ),
        )
        add(
            "se3_from_rotation_translation",
            lambda: Peer("roma (Rigid.to_homogeneous)", lambda r, t: roma.Rigid(r, t).to_homogeneous()),
        )
        add(
            "se3_compose",
            lambda: Peer(
                "roma (Rigid.compose)",
                lambda r1, t1, r2, t2: roma.Rigid(r1, t1).compose(roma.Rigid(r2, t2)).as_tuple(),
                prep=lambda a, b: (a[..., :3, :3], a[..., :3, 3], b[..., :3, :3], b[..., :3, 3]),
                post=lambda rt: _homogeneous(*rt),
            ),
        )
        add(
            "se3_inverse",
            lambda: Peer(
                "roma (Rigid.inverse)",
                lambda r, t: roma.Rigid(r, t).inverse().as_tuple(),
                prep=lambda a: (a[..., :3, :3], a[..., :3, 3]),
                post=lambda rt: _homogeneous(*rt),
            ),
        )
        add(
            "se3_apply",
            lambda: Peer(
                "roma (Rigid.apply)",
                lambda r, t, p: roma.Rigid(r, t).apply(p),
                prep=lambda a, p: (a[..., :3, :3], a[..., :3, 3], p),
            ),
        )
        add(
            "se3_to_rotation_translation",
            lambda: Peer(
                "roma (Rigid.from_homogeneous)", lambda a: roma.Rigid.from_homogeneous(a).as_tuple()
            ),
        )
        add(
            "pose_to_matrix[xyz_xyzw]",
            lambda: Peer(
                "roma (RigidUnitQuat.to_homogeneous)",
                lambda q, t: roma.RigidUnitQuat(q, t).to_homogeneous(),
                prep=lambda x: (x[..., 3:], x[..., :3]),
            ),
        )

    def torch_matmul() -> None:
        add("se3_compose", lambda: Peer("a 4x4 matmul (torch.matmul)", lambda a, b: a @ b))

    def kornia_peers() -> None:
        from kornia.geometry import conversions as kc

        add(
            "quaternion_to_matrix",
            lambda: Peer("kornia (quaternion_to_rotation_matrix)", kc.quaternion_to_rotation_matrix),
        )
        add(
            "matrix_to_quaternion",
            lambda: Peer(
                "kornia (rotation_matrix_to_quaternion)", kc.rotation_matrix_to_quaternion, up_to_sign=True
            ),
        )
        add("normalize_quaternion", lambda: Peer("kornia (normalize_quaternion)", kc.normalize_quaternion))
        add(
            "axis_angle_to_quaternion",
            lambda: Peer("kornia (axis_angle_to_quaternion)", kc.axis_angle_to_quaternion),
        )
        add(
            "quaternion_to_axis_angle",
            lambda: Peer("kornia (quaternion_to_axis_angle)", kc.quaternion_to_axis_angle, up_to_sign=True),
        )
        add(
            ["axis_angle_to_matrix", "so3_exp"],
            lambda: Peer("kornia (axis_angle_to_rotation_matrix)", kc.axis_angle_to_rotation_matrix),
        )
        add(
            ["matrix_to_axis_angle", "so3_log"],
            lambda: Peer(
                "kornia (rotation_matrix_to_axis_angle)", kc.rotation_matrix_to_axis_angle, up_to_sign=True
            ),
        )

    def pk_peers() -> None:
        import pytorch_kinematics as pk

        label = "pytorch-kinematics ({})".format
        for row, name in [
            ("quaternion_to_matrix", "quaternion_to_matrix"),
            ("standardize_quaternion", "standardize_quaternion"),
            ("wxyz_to_xyzw", "wxyz_to_xyzw"),
            ("xyzw_to_wxyz", "xyzw_to_wxyz"),
            ("axis_angle_to_quaternion", "axis_angle_to_quaternion"),
            ("axis_angle_to_matrix", "so3_exp_map"),
            ("so3_exp", "so3_exp_map"),
            ("quaternion_invert", "quaternion_invert"),
            ("quaternion_apply", "quaternion_apply"),
            ("quaternion_multiply", "quaternion_raw_multiply"),
            ("quaternion_geodesic_distance", "quaternion_angular_distance"),
            ("matrix_geodesic_distance", "so3_relative_angle"),
            ("so3_hat", "so3.hat"),
        ]:
            add(row, lambda name=name: Peer(label(name), _attribute(pk, name)))
        for row, name in [
            ("matrix_to_quaternion", "matrix_to_quaternion"),
            ("quaternion_to_axis_angle", "quaternion_to_axis_angle"),
            ("matrix_to_axis_angle", "matrix_to_axis_angle"),
            ("so3_log", "matrix_to_axis_angle"),
            ("matrix_to_axis_angle", "so3_log_map"),
            ("so3_log", "so3_log_map"),
        ]:
            add(row, lambda name=name: Peer(label(name), getattr(pk, name), up_to_sign=True))
        add("quaternion_slerp", lambda: Peer(label("quaternion_slerp"), pk.quaternion_slerp, up_to_sign=True))
        add(
            "rotation_6d_to_matrix",
            lambda: Peer(
                label("rotation_6d_to_matrix"), pk.rotation_6d_to_matrix, post=lambda m: m.transpose(-1, -2)
            ),
        )
        add(
            "rotation_6d_to_matrix[rows]",
            lambda: Peer(label("rotation_6d_to_matrix"), pk.rotation_6d_to_matrix),
        )
        add(
            "matrix_to_rotation_6d",
            lambda: Peer(
                label("matrix_to_rotation_6d"),
                pk.matrix_to_rotation_6d,
                prep=lambda m: (m.transpose(-1, -2),),
            ),
        )
        add(
            "matrix_to_rotation_6d[rows]",
            lambda: Peer(label("matrix_to_rotation_6d"), pk.matrix_to_rotation_6d),
        )
        add(
            "euler_angles_to_matrix[XYZ]",
            lambda: Peer(label("euler_angles_to_matrix"), lambda a: pk.euler_angles_to_matrix(a, "XYZ")),
        )
        add(
            "matrix_to_euler_angles[ZXZ]",
            lambda: Peer(label("matrix_to_euler_angles"), lambda m: pk.matrix_to_euler_angles(m, "ZXZ")),
        )

    def pypose_peers() -> None:
        import pypose as pp
        from pypose.lietensor.operation import so3_Jl, so3_Jl_inv

        def so3(m: Any) -> Any:
            return pp.mat2SO3(m, check=False)

        add(
            "quaternion_to_matrix",
            lambda: Peer("pypose (SO3.matrix)", lambda q: pp.SO3(q).matrix(), prep=lambda q: (_xyzw(q),)),
        )
        add(
            "matrix_to_quaternion",
            lambda: Peer("pypose (mat2SO3)", lambda m: so3(m).tensor(), post=_wxyz, up_to_sign=True),
        )
        add(
            ["axis_angle_to_matrix", "so3_exp"],
            lambda: Peer("pypose (so3.Exp.matrix)", lambda v: pp.so3(v).Exp().matrix()),
        )
        add(
            ["matrix_to_axis_angle", "so3_log"],
            lambda: Peer("pypose (mat2SO3.Log)", lambda m: so3(m).Log().tensor(), up_to_sign=True),
        )
        add("so3_hat", lambda: Peer("pypose (vec2skew)", pp.vec2skew))
        add("so3_left_jacobian", lambda: Peer("pypose (so3_Jl)", so3_Jl))
        add("so3_left_jacobian_inverse", lambda: Peer("pypose (so3_Jl_inv)", so3_Jl_inv))
        add("so3_right_jacobian", lambda: Peer("pypose (so3.Jr)", lambda v: pp.so3(v).Jr()))
        add(
            "quaternion_apply",
            lambda: Peer("pypose (SO3.Act)", lambda q, v: pp.SO3(q).Act(v), prep=lambda q, v: (_xyzw(q), v)),
        )
        add(
            "quaternion_multiply",
            lambda: Peer(
                "pypose (SO3 *)",
                lambda p, q: (pp.SO3(p) * pp.SO3(q)).tensor(),
                prep=lambda p, q: (_xyzw(p), _xyzw(q)),
                post=_wxyz,
            ),
        )
        add(
            "quaternion_invert",
            lambda: Peer(
                "pypose (SO3.Inv)", lambda q: pp.SO3(q).Inv().tensor(), prep=lambda q: (_xyzw(q),), post=_wxyz
            ),
        )
        add(
            "so3_plus[left]",
            lambda: Peer("pypose (so3.Exp * SO3)", lambda m, d: (pp.so3(d).Exp() * so3(m)).matrix()),
        )
        add(
            "so3_minus[left]",
            lambda: Peer(
                "pypose ((SO3 * SO3.Inv).Log)",
                lambda a, b: (so3(a) * so3(b).Inv()).Log().tensor(),
                up_to_sign=True,
            ),
        )
        add(
            "quaternion_plus[left]",
            lambda: Peer(
                "pypose (so3.Exp * SO3)",
                lambda q, d: (pp.so3(d).Exp() * pp.SO3(q)).tensor(),
                prep=lambda q, d: (_xyzw(q), d),
                post=_wxyz,
                up_to_sign=True,
            ),
        )
        add(
            "quaternion_minus[left]",
            lambda: Peer(
                "pypose ((SO3 * SO3.Inv).Log)",
                lambda a, b: (pp.SO3(a) * pp.SO3(b).Inv()).Log().tensor(),
                prep=lambda a, b: (_xyzw(a), _xyzw(b)),
                up_to_sign=True,
            ),
        )
        # poses: pypose's (t, q_xyzw), built from the matrix outside the count
        add(
            "se3_compose",
            lambda: Peer(
                "pypose (SE3 *)",
                lambda a, b: (pp.SE3(a) * pp.SE3(b)).tensor(),
                prep=lambda a, b: (_pose7(a), _pose7(b)),
                post=_from_pose7,
            ),
        )
        add(
            "se3_inverse",
            lambda: Peer(
                "pypose (SE3.Inv)",
                lambda a: pp.SE3(a).Inv().tensor(),
                prep=lambda a: (_pose7(a),),
                post=_from_pose7,
            ),
        )
        add(
            "se3_apply",
            lambda: Peer("pypose (SE3.Act)", lambda a, p: pp.SE3(a).Act(p), prep=lambda a, p: (_pose7(a), p)),
        )
        add("se3_exp", lambda: Peer("pypose (se3.Exp)", lambda x: pp.se3(x).Exp().tensor(), post=_from_pose7))
        add(
            "se3_log",
            lambda: Peer(
                "pypose (SE3.Log)",
                lambda a: pp.SE3(a).Log().tensor(),
                prep=lambda a: (_pose7(a),),
                up_to_sign=True,
            ),
        )
        add(
            "se3_plus[left]",
            lambda: Peer(
                "pypose (se3.Exp * SE3)",
                lambda a, d: (pp.se3(d).Exp() * pp.SE3(a)).tensor(),
                prep=lambda a, d: (_pose7(a), d),
                post=_from_pose7,
            ),
        )
        add(
            "se3_minus[left]",
            lambda: Peer(
                "pypose ((SE3 * SE3.Inv).Log)",
                lambda a, b: (pp.SE3(a) * pp.SE3(b).Inv()).Log().tensor(),
                prep=lambda a, b: (_pose7(a), _pose7(b)),
                up_to_sign=True,
            ),
        )
        add("pose_to_matrix[xyz_xyzw]", lambda: Peer("pypose (SE3.matrix)", lambda x: pp.SE3(x).matrix()))
        add(
            "matrix_to_pose[xyzw_xyz]",
            lambda: Peer(
                "pypose (mat2SE3)",
                lambda m: pp.mat2SE3(m, check=False).tensor(),
                post=_canonical_pose,
            ),
        )

    def torchlie_peers() -> None:
        import torchlie.functional as tf

        label = "torchlie ({})".format
        add(
            "quaternion_to_matrix",
            lambda: Peer(label("SO3.quaternion_to_rotation"), tf.SO3.quaternion_to_rotation),
        )
        add(["axis_angle_to_matrix", "so3_exp"], lambda: Peer(label("SO3.exp"), tf.SO3.exp))
        add(["matrix_to_axis_angle", "so3_log"], lambda: Peer(label("SO3.log"), tf.SO3.log, up_to_sign=True))
        add("so3_hat", lambda: Peer(label("SO3.hat"), tf.SO3.hat))
        add("so3_vee", lambda: Peer(label("SO3.vee"), tf.SO3.vee))
        add(
            "so3_plus[left]",
            lambda: Peer(label("SO3.compose, SO3.exp"), lambda m, d: tf.SO3.compose(tf.SO3.exp(d), m)),
        )
        add(
            "so3_minus[left]",
            lambda: Peer(
                label("SO3.log, compose, inv"),
                lambda a, b: tf.SO3.log(tf.SO3.compose(a, tf.SO3.inv(b))),
                up_to_sign=True,
            ),
        )
        top = lambda *ms: tuple(m[..., :3, :] for m in ms)  # noqa: E731  (torchlie's 3x4 poses)
        add("se3_compose", lambda: Peer(label("SE3.compose"), tf.SE3.compose, prep=top, post=_pad34))
        add("se3_inverse", lambda: Peer(label("SE3.inv"), tf.SE3.inv, prep=top, post=_pad34))
        add(
            "se3_apply",
            lambda: Peer(label("SE3.transform"), tf.SE3.transform, prep=lambda a, p: (a[..., :3, :], p)),
        )
        add("se3_exp", lambda: Peer(label("SE3.exp"), tf.SE3.exp, post=_pad34))
        add("se3_log", lambda: Peer(label("SE3.log"), tf.SE3.log, prep=top, up_to_sign=True))
        add("se3_hat", lambda: Peer(label("SE3.hat"), tf.SE3.hat))
        add("se3_vee", lambda: Peer(label("SE3.vee"), tf.SE3.vee))
        add("se3_adjoint", lambda: Peer(label("SE3.adj"), tf.SE3.adj, prep=top))
        add(
            "se3_plus[left]",
            lambda: Peer(
                label("SE3.compose, SE3.exp"),
                lambda a, d: tf.SE3.compose(tf.SE3.exp(d), a),
                prep=lambda a, d: (a[..., :3, :], d),
                post=_pad34,
            ),
        )
        add(
            "se3_minus[left]",
            lambda: Peer(
                label("SE3.log, compose, inv"),
                lambda a, b: tf.SE3.log(tf.SE3.compose(a, tf.SE3.inv(b))),
                prep=top,
                up_to_sign=True,
            ),
        )

    for group in (roma_peers, torch_matmul, kornia_peers, pk_peers, pypose_peers, torchlie_peers):
        try:
            group()
        except ImportError as error:
            missing.append(f"{group.__name__}: {error}")
    return dict(table), missing


# ---------------------------------------------------------------------------------------------------
# Checks: the same job on random inputs, and right at the edges


def _as_list(out: Any) -> list[np.ndarray]:
    outs = out if isinstance(out, (tuple, list)) else (out,)
    return [np.asarray(o.detach().to(dtype=torch.float64).numpy()) for o in outs]


def _distance(
    a: np.ndarray, b: np.ndarray, other: Callable[[np.ndarray], np.ndarray] | None, periodic: bool
) -> float:
    """Largest error of ``a`` against ``b`` (or, row by row, against ``other(b)``, the other branch of a
    result defined up to a choice), relative to the size of ``b``'s entries (at least 1)."""
    if a.shape != b.shape:
        return math.inf
    if a.size == 0:
        return 0.0

    def rowwise(ref: np.ndarray) -> np.ndarray:
        diff = a - ref
        if periodic:
            diff = (diff + np.pi) % (2 * np.pi) - np.pi
        return np.abs(diff).reshape(len(a), -1).max(axis=-1) if a.ndim else np.abs(diff)

    err = rowwise(b)
    if other is not None:
        err = np.fmin(err, rowwise(other(b)))
    scale = max(1.0, float(np.nanmax(np.abs(b)))) if np.isfinite(b).any() else 1.0
    return float(np.max(np.where(np.isnan(err), np.inf, err))) / scale


def _evaluate(fn: Callable[..., Any], xs: Sequence[Any]) -> tuple[list[np.ndarray], bool]:
    """float64 outputs of ``fn(*xs)`` and whether the gradient of the loss is finite."""
    leaves = _leaves(xs)
    out = fn(*leaves)
    loss = _loss(out)
    finite = True
    if getattr(loss, "requires_grad", False):
        grads = torch.autograd.grad(loss, leaves, allow_unused=True)
        finite = all(g is None or bool(g.isfinite().all()) for g in grads)
    return _as_list(out), finite


def _same(
    ref: list[np.ndarray],
    got: list[np.ndarray],
    other: Callable[[np.ndarray], np.ndarray] | None,
    periodic: bool,
) -> float:
    if len(ref) != len(got):
        return math.inf
    return max(_distance(g, r, other, periodic) for r, g in zip(ref, got, strict=True))


def check_peer(row: Row, peer: Peer) -> dict[str, Any]:
    """The peer's agreement with diffquat on the N random inputs, and the edge cases where it is wrong
    (None where it is right at every one)."""
    periodic = bool(row.op is not None and row.op.periodic)
    other = None  # the other branch of a result defined up to a choice: -x, or the row's own rule
    if peer.up_to_sign or (row.op is not None and row.op.up_to_sign):
        other = (row.op.other_branch if row.op is not None else None) or np.negative
    dq_fn = row.function()
    peer_fn = lambda *xs: peer.post(peer.fn(*xs))  # noqa: E731

    def compare(q: np.ndarray) -> tuple[float, bool, bool, bool, bool]:
        xs = row.tensors(q, torch.float64)
        ref, ref_finite_grad = _evaluate(dq_fn, xs)
        got, finite_grad = _evaluate(peer_fn, peer.prep(*xs))
        ref_finite = all(np.isfinite(r).all() for r in ref)
        got_finite = all(np.isfinite(g).all() for g in got)
        return _same(ref, got, other, periodic), ref_finite, got_finite, ref_finite_grad, finite_grad

    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        try:
            error = compare(cases.uniform_quaternions(N, SEED))[0]
        except Exception as exc:  # a peer that cannot run these inputs does another job
            return {"agrees": False, "error": f"{type(exc).__name__}: {str(exc)[:120]}", "edge": None}
        if not error <= AGREE_TOL:
            return {"agrees": False, "error": f"max relative difference {error:.1e}", "edge": None}
        wrong = []
        for name in EDGE_CASES:
            case = cases.CASES_BY_NAME[name]
            if row.op is not None and not row.op.applies(case):
                continue
            try:
                err, ref_finite, got_finite, ref_grad, got_grad = compare(case.quaternions("float64"))
            except Exception as exc:
                wrong.append(f"{name} (raises {type(exc).__name__})")
                continue
            if ref_finite and not got_finite:
                wrong.append(f"{name} (non-finite value)")
            elif ref_grad and not got_grad:
                wrong.append(f"{name} (non-finite gradient)")
            elif ref_finite and not err <= EDGE_TOL:
                wrong.append(f"{name} (value off by {err:.1e})")
    return {"agrees": True, "edge": ", ".join(wrong) or None, "edge_cases": [w.split(" ")[0] for w in wrong]}


# ---------------------------------------------------------------------------------------------------
# The run


def budget(entry: dict[str, Any]) -> tuple[int | None, int | None, str]:
    """Issue 46's budget of one row (forward, forward + backward) and where it comes from."""
    candidates: list[tuple[float, float, str]] = []
    fixed = FIXED_BUDGETS.get(entry["id"])
    if fixed is not None:
        candidates.append((fixed[0], fixed[1], f"issue 46's {fixed[0]} / {fixed[1]}"))
    for label, peer in entry["peers"].items():
        if not peer["agrees"] or peer["backward"] is None:
            continue
        factor = 1.0 if peer["edge"] is None else 1.5
        why = label if peer["edge"] is None else f"1.5x {label}, wrong at {_edges(peer)}"
        candidates.append((factor * peer["forward"], factor * peer["backward"], why))
    if candidates:
        fwd = min(candidates, key=lambda c: c[0])
        bwd = min(candidates, key=lambda c: c[1])
        source = fwd[2] if fwd[2] == bwd[2] else f"{fwd[2]} / {bwd[2]}"
        return math.floor(fwd[0]), math.floor(bwd[1]), source
    before = BEFORE.get(entry["id"])
    if before is None:
        return None, None, f"no peer, no count at {BEFORE_COMMIT}"
    return before[0] // 2, None if before[1] is None else before[1] // 2, f"no peer: half of {BEFORE_COMMIT}"


def count_rows(ids: Sequence[str] | None = None) -> dict[str, tuple[int, int | None]]:
    """diffquat's (forward, forward + backward) counts of every row (or of ``ids``) at N float32
    inputs: what ``ops.json`` records and ``tests/test_ops.py`` pins."""
    q = cases.uniform_quaternions(N, SEED)
    out = {}
    for row in rows():
        if ids is None or row.id in ids:
            out[row.id] = count(row.function(), row.tensors(q, torch.float32))
    return out


def run(out_dir: Path, with_peers: bool = True) -> dict[str, Any]:
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # the peers' own (deprecations, tracer hints)
        return _run(out_dir, with_peers)


def _run(out_dir: Path, with_peers: bool) -> dict[str, Any]:
    q = cases.uniform_quaternions(N, SEED)
    table, missing = peers() if with_peers else ({}, [])
    entries = []
    for row in rows():
        xs = row.tensors(q, torch.float32)
        fwd, bwd = count(row.function(), xs)
        entry: dict[str, Any] = {"id": row.id, "name": row.name, "forward": fwd, "backward": bwd, "peers": {}}
        for peer in table.get(row.id, []):
            try:
                pf, pb = count(peer.fn, peer.prep(*xs))
            except Exception as exc:
                entry["peers"][peer.label] = {
                    "agrees": False, "error": f"{type(exc).__name__}: {str(exc)[:120]}",
                    "forward": None, "backward": None, "edge": None,
                }  # fmt: skip
                continue
            entry["peers"][peer.label] = {"forward": pf, "backward": pb, **check_peer(row, peer)}
            if peer.note:
                entry["peers"][peer.label]["note"] = peer.note
        before = BEFORE.get(row.id)
        entry["before"] = list(before) if before else None
        fb, bb, source = budget(entry)
        entry["budget"] = {"forward": fb, "backward": bb, "source": source}
        entry["met"] = None if fb is None else bool(fwd <= fb and (bwd is None or bb is None or bwd <= bb))
        entries.append(entry)
    results = {
        "n": N,
        "dtype": "float32",
        "torch": torch.__version__,
        "before_commit": BEFORE_COMMIT,
        "versions": _versions(),
        "missing_peers": missing,
        "rows": entries,
    }
    out_dir.mkdir(parents=True, exist_ok=True)
    (out_dir / "ops.json").write_text(json.dumps(results, indent=1) + "\n")
    (out_dir / "OPS.md").write_text(render(results))
    return results


def _versions() -> dict[str, str]:
    from importlib import metadata

    out = {"python": platform.python_version()}
    for name in ("torch", "roma", "kornia", "pypose", "torchlie", "pytorch-kinematics"):
        try:
            out[name] = metadata.version(name)
        except metadata.PackageNotFoundError:
            out[name] = "not installed"
    # pytorch3d does not install here (pytorch-kinematics carries a copy of its rotation transforms)
    out["pytorch3d"] = "not installable in this environment"
    return out


def load(path: Path | None = None) -> dict[str, Any]:
    """The recorded table (``benchmarks/ops.json``)."""
    return json.loads((path or Path(__file__).resolve().parent / "ops.json").read_text())


def _edges(peer: dict[str, Any]) -> str:
    """The names of the edge cases where a peer is wrong (what, in the table of every peer)."""
    return ", ".join(peer.get("edge_cases", [])) or str(peer["edge"])


def _cell(fwd: int | None, bwd: int | None) -> str:
    return "—" if fwd is None else f"{fwd} / {'—' if bwd is None else bwd}"


def render(results: dict[str, Any]) -> str:
    rows_ = results["rows"]
    lines = [
        "# ATen operations per eager torch call",
        "",
        f"Written by `{COMMAND}`; do not edit by hand. How it counts, and the rules of the budgets, are "
        "in the module's docstring (`benchmarks/ops.py`); `tests/test_ops.py` pins diffquat's counts at "
        "`ops.json`'s.",
        "",
        f"One eager call at N = {results['n']}, {results['dtype']}, torch {results['torch']}, after one "
        "warm-up call: `forward / forward + backward`, every dispatched ATen operation counted but "
        "`aten.detach.default`; forward + backward is `f(*xs)` on leaves that require grad, then "
        "the sum of `o.sum()` over the floating outputs, `.backward()`, the loss included. "
        "Peers get their own layout and "
        "wrap their own objects (`pp.SE3(x)`, `roma.Rigid(R, t)`) inside the count; layout conversions "
        "are outside it. A peer counts only where it agrees with diffquat on random inputs (float64); "
        "one that is wrong at an edge diffquat guarantees (a non-finite value or gradient, or a value "
        f"off by more than {EDGE_TOL:g}, at the suite's named cases) sets a budget of 1.5x its count, "
        "the edge named. "
        f"`{results['before_commit']}`: the counts of the tree before issue 46's work, by the same rules.",
        "",
        "Peers: roma, kornia, pytorch-kinematics, pypose, torchlie (theseus' Lie groups) and, for "
        "`se3_compose`, a plain 4x4 matmul. pytorch3d is not installable in this environment; "
        "pytorch-kinematics' `transforms` are adapted from its rotation conversions and stand in for it.",
        "",
    ]
    met = [e for e in rows_ if e["met"] is True]
    missed = [e for e in rows_ if e["met"] is False]
    totals = _totals(rows_)
    lines += [
        "## Totals",
        "",
        "| | forward | forward + backward |",
        "|---|---|---|",
        f"| diffquat, all {len(rows_)} rows | {totals['all'][0]} | {totals['all'][1]} |",
        f"| diffquat, the {totals['n_before']} rows counted at `{results['before_commit']}` | "
        f"{totals['now'][0]} | {totals['now'][1]} |",
        f"| the same rows at `{results['before_commit']}` | {totals['before'][0]} | {totals['before'][1]} |",
        "",
        f"Budgets met: {len(met)} of {len(met) + len(missed)} rows with a budget.",
        "",
        "## Per function",
        "",
        f"| function | diffquat | fewest-op peer | its counts | `{results['before_commit']}` | budget | "
        "source of the budget | met |",
        "|---|---|---|---|---|---|---|---|",
    ]
    for e in rows_:
        good = [(p["backward"] or 0, p["forward"], label) for label, p in e["peers"].items() if p["agrees"]]
        if good:
            _, _, best = min(good)
            peer = e["peers"][best]
            best_cell = best + (f", wrong at {_edges(peer)}" if peer["edge"] else "")
            counts = _cell(peer["forward"], peer["backward"])
        else:
            best_cell, counts = "—", "—"
        b = e["budget"]
        met_cell = {True: "yes", False: "**no**", None: "—"}[e["met"]]
        before = e["before"] or [None, None]
        lines.append(
            f"| `{e['id']}` | {_cell(e['forward'], e['backward'])} | {best_cell} | {counts} | "
            f"{_cell(*before)} | {_cell(b['forward'], b['backward'])} | {b['source']} | {met_cell} |"
        )
    lines += ["", "## Every peer", "", "| function | peer | counts | same job | edge where it is wrong |",
              "|---|---|---|---|---|"]  # fmt: skip
    for e in rows_:
        for label, p in e["peers"].items():
            same = "yes" if p["agrees"] else f"no: {p.get('error', '')}"
            edge = p["edge"] or ("none found" if p["agrees"] else "—")
            note = f" ({p['note']})" if p.get("note") else ""
            lines.append(
                f"| `{e['id']}` | {label}{note} | {_cell(p['forward'], p['backward'])} | {same} | {edge} |"
            )
    lines += ["", "## Versions", "", "| | |", "|---|---|"]
    lines += [f"| {k} | {v} |" for k, v in results["versions"].items()]
    if results["missing_peers"]:
        lines += ["", "Peers left out: " + "; ".join(results["missing_peers"])]
    return "\n".join(lines) + "\n"


def _totals(rows_: list[dict[str, Any]]) -> dict[str, Any]:
    def total(pairs: list[tuple[int, int | None]]) -> tuple[int, int]:
        return sum(p[0] for p in pairs), sum(p[1] or 0 for p in pairs)

    counted = [e for e in rows_ if e["before"]]
    return {
        "all": total([(e["forward"], e["backward"]) for e in rows_]),
        "now": total([(e["forward"], e["backward"]) for e in counted]),
        "before": total([tuple(e["before"]) for e in counted]),
        "n_before": len(counted),
    }


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=(__doc__ or "").split("\n")[0])
    parser.add_argument("--out", type=Path, default=Path(__file__).resolve().parent)
    parser.add_argument("--render-only", action="store_true", help="rewrite OPS.md from ops.json")
    args = parser.parse_args(argv)
    if args.render_only:
        (args.out / "OPS.md").write_text(render(load(args.out / "ops.json")))
        return
    run(args.out)


if __name__ == "__main__":
    main()
