"""Rotations in time: diffquat's splines with their rates against pypose's SE(3) B-spline and scipy's
``RotationSpline``, per evaluated point. ``python -m benchmarks.motion [--quick] [--out DIR]
[--threads N] [--render-only]`` writes ``MOTION.md`` and ``motion.json`` (default: next to this file;
``--render-only`` rewrites the report from the JSON without timing anything).

What is timed (float32; numpy and scipy float64), forward (torch: under ``no_grad``) and forward +
backward (the gradient with respect to the control points for a cotangent of ones on every output),
by ``run.time_all``: medians over blocks whose order rotates from block to block, the first call
(warm-up, and compilation for ``jax.jit`` and ``torch.compile``) apart. The metric is the median time of
a call divided by the number of points it evaluates.

Sizes: ``S`` segments of ``M`` points each, ``K = S + 3`` control points (cubic, order 4), and the
points ``u = i + m / M`` (``i < S``, ``m < M``) plus the end point ``u = S``: ``N = S M + 1``. That is
exactly the set of points ``pp.bspline(X, interval=1 / M)`` evaluates (``M`` a power of two, so that
pypose's ``torch.arange(0, 1, interval)`` has ``M`` entries in float32). Forward: N = 65, 4097 and
262 145 (S = 16, 128, 1024; M = 4, 32, 256); forward + backward: N = 65, 4097 and 65 537 (S = M = 256),
not 262 145 (``FULL_BACKWARD_CASES``: an earlier ``_motion._gather``, torch's ``take_along_dim``, had a
derivative of N K entries and ran out of memory there; the flat index that replaced it was not timed there).

- ``se3_bspline``: diffquat's ``se3_bspline(control (K, 4, 4), u (N,))`` -> pose (N, 4, 4), body twist
  (N, 6) and its derivative (N, 6), ``mode="se3"`` (and ``"split"``, diffquat only), on torch eager,
  ``torch.compile`` (``fullgraph=True``; only at the sizes in ``COMPILE_N``: one compilation took 76 s
  forward and 96 s forward + backward on the 2-core machine), ``jax.jit`` and numpy; against pypose's
  ``pp.bspline(X, interval=1 / M)`` with ``X = pp.SE3(x)``, ``x (K, 7)`` ``(t, q_xyzw)`` built outside
  the timed region: poses only, (N, 7), no rates. pypose's spline is the same curve: its segment ``i``
  is diffquat's ``u`` in [i, i + 1) on control points i .. i + 3, its end pose diffquat's ``u = S``;
  the check below compares the two pose by pose.
- ``so3_bspline``: diffquat's ``so3_bspline(control (K, 3, 3), u (N,))`` -> rotation (N, 3, 3), body
  angular velocity (N, 3) and acceleration (N, 3); against scipy's ``RotationSpline`` through the same
  K rotations as knots at times 0 .. K - 1, evaluated at N points evenly on [0, K - 1]: ``s =
  RotationSpline(times, rotations)`` then ``s(t)``, ``s(t, 1)``, ``s(t, 2)`` (a ``Rotation``, the
  angular rate and acceleration; ``rotations = Rotation.from_matrix(R)`` built outside). It is an
  interpolating cubic in rotation vectors (C2 through its knots; the construction solves for the rates
  at the knots), not a B-spline: the curves differ, the work per point is what is compared. Timed
  twice: construction and evaluation together (what diffquat's call does: its increments are computed
  in every call), and evaluation alone (the spline built outside). Forward only (numpy).
- ``quaternion_squad(q (K, 4), t (N,))``: diffquat only (no peer has SQUAD), on the K control
  rotations as knots at N points evenly on [0, K - 1].

``--quick`` (the test suite's smoke run, seconds): N = 65 only, two blocks, without ``jax.jit`` (its
six compilations took 36 s of a 54 s quick run).
"""

from __future__ import annotations

import argparse
import functools
import json
import os
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np

from .run import _fmt_time, _sync, finish, time_all

# (segments S, points per segment M): K = S + 3 control points, N = S M + 1 points.
FULL_CASES = ((16, 4), (128, 32), (1024, 256))
# Forward + backward stops at N = 65 537: at 262 145 the first full run was killed by the kernel's
# out-of-memory killer at 18.5 GB resident (the 2-core machine has 23 GB, shared; at N = 8193 one
# forward + backward of se3_bspline raised the peak by 131 MB in torch eager, 354 MB with jax.jit,
# 54 MB for pypose).
FULL_BACKWARD_CASES = ((16, 4), (128, 32), (256, 256))
QUICK_CASES = ((16, 4),)
COMPILE_N = (4097,)  # the sizes at which diffquat's torch.compile is timed (full run)
DEFAULT_REPEATS = {True: 2, False: 5}
MODES = (("forward", False), ("forward + backward", True))
STEP = 0.4  # rad: the standard deviation of each component of a control rotation's increment

TORCH, COMPILED, JAX, NUMPY = (
    "diffquat torch eager",
    "diffquat torch.compile",
    "diffquat jax.jit",
    "diffquat numpy",
)
SPLIT = " (mode='split')"
PYPOSE, SCIPY, SCIPY_EVAL = "pypose bspline", "scipy RotationSpline", "scipy RotationSpline, evaluation only"
GROUPS = ("se3_bspline", "so3_bspline", "quaternion_squad")
# Per group: (peer, the diffquat method it is set against, the mode it has).
PAIRS: dict[str, tuple[tuple[str, str, tuple[str, ...]], ...]] = {
    "se3_bspline": (
        (PYPOSE, TORCH, ("forward", "forward + backward")),
        (PYPOSE, COMPILED, ("forward", "forward + backward")),
    ),
    "so3_bspline": ((SCIPY, NUMPY, ("forward",)), (SCIPY_EVAL, NUMPY, ("forward",))),
    "quaternion_squad": (),
}
CALLS = {
    TORCH: "se3_bspline(control, u) / so3_bspline(control, u) / quaternion_squad(q, t)",
    TORCH + SPLIT: "se3_bspline(control, u, mode='split')",
    COMPILED: "torch.compile(fullgraph=True) of se3_bspline(control, u)",
    JAX: "jax.jit of the same; forward + backward: jax.jit of jax.vjp with respect to the control points",
    JAX + SPLIT: "jax.jit of se3_bspline(control, u, mode='split')",
    NUMPY: "the same, float64",
    PYPOSE: "pp.bspline(X, interval=1 / M), X = pp.SE3(x) built outside, x (K, 7) (t, q_xyzw): poses only",
    SCIPY: "s = RotationSpline(times, rotations); (s(t), s(t, 1), s(t, 2)): construction and evaluation",
    SCIPY_EVAL: "(s(t), s(t, 1), s(t, 2)), s built outside",
}


# ---------------------------------------------------------------------------------------------------
# Inputs


def control_poses(count: int, seed: int = 0) -> np.ndarray:
    """``count`` control poses (count, 4, 4), float64: a random walk of rotations (each increment a
    rotation vector with Gaussian components of standard deviation ``STEP``, well under a half-turn)
    and of translations (unit Gaussian steps)."""
    import diffquat.numpy as dqn

    rng = np.random.default_rng(seed)
    rotvec_steps = rng.normal(scale=STEP, size=(count, 3))
    rotation = dqn.axis_angle_to_matrix(rotvec_steps[:1])
    rotations = [rotation[0]]
    for step in dqn.axis_angle_to_matrix(rotvec_steps[1:]):
        rotations.append(rotations[-1] @ step)
    translation = np.cumsum(rng.standard_normal((count, 3)), axis=0)
    return dqn.se3_from_rotation_translation(np.stack(rotations), translation)


def spline_points(segments: int, per_segment: int) -> np.ndarray:
    """``u = i + m / M`` for ``i < S``, ``m < M``, then ``S``: pypose's points."""
    return np.concatenate([np.arange(segments * per_segment) / per_segment, [float(segments)]])


# ---------------------------------------------------------------------------------------------------
# Methods


def _torch_call(fn: Callable[..., Any], control: Any, backward: bool) -> Callable[[], Any]:
    import torch

    if not backward:

        def forward() -> Any:
            with torch.no_grad():
                return fn(control)

        return forward
    leaf = control.clone().requires_grad_(True)

    def forward_backward() -> Any:
        out = fn(leaf)
        outs = tuple(out) if isinstance(out, (tuple, list)) else (out,)
        plain = tuple(torch.Tensor.as_subclass(o, torch.Tensor) for o in outs)
        return torch.autograd.grad(plain, leaf, [torch.ones(o.shape, dtype=o.dtype) for o in plain])

    return forward_backward


def _jax_call(fn: Callable[..., Any], control: Any, backward: bool) -> Callable[[], Any]:
    import jax
    import jax.numpy as jnp

    if not backward:
        jitted = jax.jit(fn)
        return lambda: _sync(jitted(control))
    cotangent = jax.tree.map(jnp.ones_like, jax.eval_shape(fn, control))
    vjp = jax.jit(lambda c, cot: jax.vjp(fn, c)[1](cot))
    return lambda: _sync(vjp(control, cotangent))


def calls(
    group: str, segments: int, per_segment: int, backward: bool, compiled: bool, jit: bool = True
) -> dict[str, Callable[[], Any]]:
    """Every method of one group at one size and direction, as zero-argument callables on inputs
    built here (outside the timed region); ``jit=False`` leaves out ``jax.jit``."""
    import jax.numpy as jnp
    import torch
    from scipy.spatial.transform import Rotation, RotationSpline

    import diffquat.jax as dqj
    import diffquat.numpy as dqn
    import diffquat.torch as dqt

    count = segments + 3
    poses = control_poses(count)
    u = spline_points(segments, per_segment)
    n = len(u)
    f32 = np.float32
    out: dict[str, Callable[[], Any]] = {}
    if group == "se3_bspline":
        control = poses
        ut, uj = torch.from_numpy(u.astype(f32)), jnp.asarray(u.astype(f32))
        ct, cj = torch.from_numpy(control.astype(f32)), jnp.asarray(control.astype(f32))
        out[TORCH] = _torch_call(lambda c: dqt.se3_bspline(c, ut), ct, backward)
        out[TORCH + SPLIT] = _torch_call(lambda c: dqt.se3_bspline(c, ut, mode="split"), ct, backward)
        if compiled:
            fn = torch.compile(lambda c, u: dqt.se3_bspline(c, u), fullgraph=True)
            out[COMPILED] = _torch_call(lambda c: fn(c, ut), ct, backward)
        if jit:
            out[JAX] = _jax_call(lambda c: dqj.se3_bspline(c, uj), cj, backward)
            out[JAX + SPLIT] = _jax_call(lambda c: dqj.se3_bspline(c, uj, mode="split"), cj, backward)
        if not backward:
            out[NUMPY] = functools.partial(dqn.se3_bspline, control, u)
        try:
            import pypose as pp
        except ImportError:
            return out
        x = torch.from_numpy(dqn.matrix_to_pose(control, layout="xyz_xyzw").astype(f32))
        if backward:
            leaf = x.clone().requires_grad_(True)
            lie = pp.SE3(leaf)

            def pypose_backward() -> Any:
                y = torch.Tensor.as_subclass(pp.bspline(lie, interval=1 / per_segment), torch.Tensor)
                return torch.autograd.grad(y, leaf, torch.ones(y.shape))

            out[PYPOSE] = pypose_backward
        else:
            lie = pp.SE3(x)

            def pypose_forward() -> Any:
                with torch.no_grad():
                    return pp.bspline(lie, interval=1 / per_segment)

            out[PYPOSE] = pypose_forward
        return out
    rotations = poses[:, :3, :3]
    fn_t: Callable[..., Any]
    fn_j: Callable[..., Any]
    fn_n: Callable[..., Any]
    if group == "so3_bspline":
        control, points, fn_t, fn_j, fn_n = rotations, u, dqt.so3_bspline, dqj.so3_bspline, dqn.so3_bspline
    else:
        control, points = dqn.matrix_to_quaternion(rotations), np.linspace(0.0, count - 1.0, n)
        fn_t, fn_j, fn_n = dqt.quaternion_squad, dqj.quaternion_squad, dqn.quaternion_squad
    ct, cj = torch.from_numpy(control.astype(f32)), jnp.asarray(control.astype(f32))
    pt, pj = torch.from_numpy(points.astype(f32)), jnp.asarray(points.astype(f32))
    out[TORCH] = _torch_call(lambda c: fn_t(c, pt), ct, backward)
    if jit:
        out[JAX] = _jax_call(lambda c: fn_j(c, pj), cj, backward)
    if not backward:
        out[NUMPY] = functools.partial(fn_n, control, points)
    if group == "so3_bspline" and not backward:
        times = np.arange(count, dtype=np.float64)
        knots = Rotation.from_matrix(rotations)
        at = np.linspace(0.0, count - 1.0, n)
        built = RotationSpline(times, knots)

        def scipy_all() -> Any:
            spline = RotationSpline(times, knots)
            return spline(at), spline(at, 1), spline(at, 2)

        out[SCIPY] = scipy_all
        out[SCIPY_EVAL] = lambda: (built(at), built(at, 1), built(at, 2))
    return out


def timings(repeats: int, block_s: float, quick: bool) -> dict[str, Any]:
    """group -> mode -> N -> label -> Timing (as dicts)."""
    out: dict[str, Any] = {}
    for group in GROUPS:
        out[group] = {}
        for mode, backward in MODES:
            out[group][mode] = {}
            for segments, per_segment in _cases(quick, backward):
                n = segments * per_segment + 1
                compiled = not quick and n in COMPILE_N and group == "se3_bspline"
                methods = calls(group, segments, per_segment, backward, compiled, jit=not quick)
                timed = time_all(methods, repeats, block_s)
                out[group][mode][str(n)] = {label: t.__dict__ for label, t in timed.items()}
                print(f"{group} {mode} N={n}: done", flush=True)
    return out


def _cases(quick: bool, backward: bool) -> tuple[tuple[int, int], ...]:
    return QUICK_CASES if quick else FULL_BACKWARD_CASES if backward else FULL_CASES


def ratios(timed: dict[str, Any]) -> list[dict[str, Any]]:
    """Every cell: the peer's time over diffquat's (above 1: diffquat is faster)."""
    cells = []
    for group, pairs in PAIRS.items():
        for peer, ours, modes in pairs:
            for mode in modes:
                for n, ts in timed[group][mode].items():
                    if peer in ts and ours in ts:
                        cells.append(
                            {
                                "group": group,
                                "mode": mode,
                                "n": int(n),
                                "peer": peer,
                                "diffquat": ours,
                                "ratio": ts[peer]["median_s"] / ts[ours]["median_s"],
                                "peer_s": ts[peer]["median_s"],
                                "diffquat_s": ts[ours]["median_s"],
                            }
                        )
    return cells


# ---------------------------------------------------------------------------------------------------
# Checks


def pypose_agreement(quick: bool) -> list[dict[str, Any]]:
    """pypose's poses against diffquat's ``se3_bspline`` at the same points, converted to matrices: max
    absolute difference, float64 and float32 (both against diffquat float64)."""
    try:
        import pypose as pp
    except ImportError:
        return []
    import torch

    import diffquat.numpy as dqn

    rows = []
    for segments, per_segment in ((4, 16), (16, 4), (128, 32))[: 2 if quick else 3]:
        poses = control_poses(segments + 3, seed=1)
        reference, _, _ = dqn.se3_bspline(poses, spline_points(segments, per_segment))
        x = dqn.matrix_to_pose(poses, layout="xyz_xyzw")
        row: dict[str, Any] = {"segments": segments, "per_segment": per_segment}
        for dtype in ("float64", "float32"):
            with torch.no_grad():
                y = pp.bspline(pp.SE3(torch.from_numpy(x.astype(dtype))), interval=1 / per_segment)
            y64 = torch.Tensor.as_subclass(y, torch.Tensor).double().numpy()
            row["points"] = len(y64)
            row[dtype] = float(np.abs(dqn.pose_to_matrix(y64, layout="xyz_xyzw") - reference).max())
        rows.append(row)
    return rows


def scipy_rate_frame() -> dict[str, float]:
    """The frame of scipy's ``RotationSpline`` rate, by central differences of its rotations
    (float64): the max difference of ``s(t, 1)`` from the body rate ``vee(R^T R')`` and from the space
    rate ``vee(R' R^T)``."""
    from scipy.spatial.transform import Rotation, RotationSpline

    poses = control_poses(8, seed=2)
    spline = RotationSpline(np.arange(8.0), Rotation.from_matrix(poses[:, :3, :3]))
    t, h = np.linspace(0.3, 6.7, 17), 1e-5
    r = spline(t).as_matrix()
    dr = (spline(t + h).as_matrix() - spline(t - h).as_matrix()) / (2 * h)

    def vee(m: np.ndarray) -> np.ndarray:
        return np.stack([m[..., 2, 1], m[..., 0, 2], m[..., 1, 0]], axis=-1)

    body = vee(np.swapaxes(r, -1, -2) @ dr)
    space = vee(dr @ np.swapaxes(r, -1, -2))
    rate = spline(t, 1)
    return {"body": float(np.abs(rate - body).max()), "space": float(np.abs(rate - space).max())}


# ---------------------------------------------------------------------------------------------------
# Report

# Why a peer is faster, per (group, peer, diffquat method): quoted under every such cell.
CAUSES = {
    (PYPOSE, TORCH): (
        "the rates: pypose returns poses only, diffquat the body twist and its rate too (per point the "
        "transports Ad(A_j^-1) and brackets ad(V_j) beyond the three exponentials and compositions both "
        "do), and its backward runs through them"
    ),
    (PYPOSE, COMPILED): (
        "as against torch eager: the rates and their backward; pypose's own call is eager (its LieTensor "
        "stops torch.compile with fullgraph=True, benchmarks/se3.py)"
    ),
    (SCIPY, NUMPY): (
        "scipy evaluates each point in compiled loops (a cubic in the rotation vector, its rate through "
        "the rotation vector's Jacobian); diffquat numpy runs its recursion one array operation at a "
        "time, and computes its K - 1 increments in every call"
    ),
    (SCIPY_EVAL, NUMPY): (
        "per-call cost at small N: scipy's three evaluations of a spline built beforehand run in compiled "
        "loops; diffquat numpy's call validates its inputs, computes its K - 1 increments (logarithms) "
        "and runs its recursion one array operation at a time. From N = 4097 on diffquat is faster"
    ),
}


def _ratio(r: float) -> str:
    return f"{r:.2f}x" if r >= 0.1 else f"{r:.2g}x"


def _per_point(seconds: float, n: int) -> str:
    return _fmt_time(seconds / n)


def render(results: dict[str, Any]) -> str:
    load = results["load"]
    cells = results["ratios"]
    sizes = [s * m + 1 for s, m in results["cases"]]
    shape = {s * m + 1: (s, m) for s, m in results["cases"]}
    command = "python -m benchmarks.motion" + (" --quick" if results["quick"] else "")
    lines = [
        "# Rotations in time: diffquat's splines against pypose and scipy",
        "",
        f"Written by `{command}`; do not edit by hand. What each call computes, the layouts and the "
        "points are in the module's docstring (`benchmarks/motion.py`) and below. float32 (numpy and "
        f"scipy: float64), CPU, torch with {results['torch_threads']} thread(s).",
        "",
        f"Run time {results['seconds']:.0f} s; load average (1, 5, 15 min) before "
        f"{tuple(round(x, 2) for x in load['before'])}, after {tuple(round(x, 2) for x in load['after'])}: "
        "other jobs shared the machine, so absolute times are noisy; ratios were taken side by side "
        f"(medians over {results['repeats']} rotated blocks).",
        "",
        "Sizes: S segments of M points, K = S + 3 control points, N = S M + 1 evaluated points (pypose's "
        "points for `interval = 1 / M`: M per segment and the end pose; forward + backward up to N = "
        f"{max(s * m + 1 for s, m in results['backward_cases'])}, not above: an earlier gather's "
        "derivative ran out of memory there): "
        + ", ".join(f"N = {n} (S = {s}, M = {m}, K = {s + 3})" for n, (s, m) in shape.items())
        + ".",
        "",
        "## Ratios: peer time / diffquat time (above 1: diffquat is faster)",
        "",
        "pypose's `bspline` against diffquat's `se3_bspline` (mode 'se3', the same curve) on torch; "
        "scipy's `RotationSpline` against diffquat numpy's `so3_bspline` (both float64, forward only). "
        "pypose computes poses only, diffquat poses, body twists and their rates; scipy rotations, "
        "rates and accelerations of an interpolating spline.",
        "",
        "| function | peer | against | mode | " + " | ".join(f"N = {n}" for n in sizes) + " |",
        "|---|---|---|---|" + "---|" * len(sizes),
    ]
    for group, pairs in PAIRS.items():
        for peer, ours, modes in pairs:
            for mode in modes:
                row = {
                    c["n"]: c["ratio"]
                    for c in cells
                    if (c["group"], c["peer"], c["diffquat"], c["mode"]) == (group, peer, ours, mode)
                }
                if not row:
                    continue
                parts = [
                    "—" if n not in row else (f"**{_ratio(row[n])}**" if row[n] < 1 else _ratio(row[n]))
                    for n in sizes
                ]
                lines.append(f"| {group} | {peer} | {ours} | {mode} | " + " | ".join(parts) + " |")
    faster = sorted((c for c in cells if c["ratio"] < 1), key=lambda c: c["ratio"])
    lines += [
        "",
        f"### Every cell where a peer is faster ({len(faster)} of {len(cells)})",
        "",
    ]
    if faster:
        lines += [
            "| function | peer | against | mode | N | peer / diffquat | peer, per point "
            "| diffquat, per point | cause |",
            "|---|---|---|---|---|---|---|---|---|",
        ]
        for c in faster:
            lines.append(
                f"| {c['group']} | {c['peer']} | {c['diffquat']} | {c['mode']} | {c['n']} "
                f"| {_ratio(c['ratio'])} "
                f"| {_per_point(c['peer_s'], c['n'])} | {_per_point(c['diffquat_s'], c['n'])} "
                f"| {CAUSES[(c['peer'], c['diffquat'])]} |"
            )
    else:
        lines.append("None.")
    lines += ["", "## What is timed", "", "| method | call |", "|---|---|"]
    lines += [f"| {label} | {call} |" for label, call in CALLS.items()]
    lines += [
        "",
        "Forward + backward: the gradient with respect to the control points (torch: `autograd.grad`; "
        "pypose: of its (K, 7) tensor, through `pp.SE3`), for a cotangent of ones on every output "
        "(diffquat: pose, twist and its rate; pypose: its poses). The spline parameters are constants.",
        "",
        "## Time per evaluated point",
        "",
        "Median time of a call divided by N. *first call*: warm-up, and compilation for `jax.jit` and "
        "`torch.compile` (the whole call; `torch.compile`'s with whatever inductor's on-disk cache held: "
        "cold, on the 2-core machine, 76 s forward and 96 s forward + backward at N = 4097).",
        "",
    ]
    for group in GROUPS:
        for mode, _ in MODES:
            per_n = results["timings"][group][mode]
            labels: list[str] = []
            for ts in per_n.values():
                labels += [label for label in ts if label not in labels]
            lines += [
                f"### {group}, {mode}",
                "",
                "| method | " + " | ".join(f"N = {n}" for n in sizes) + " |",
            ]
            lines.append("|---" * (len(sizes) + 1) + "|")
            for label in labels:
                parts = [
                    _per_point(per_n[str(n)][label]["median_s"], n) if label in per_n.get(str(n), {}) else "—"
                    for n in sizes
                ]
                lines.append(f"| {label} | " + " | ".join(parts) + " |")
            for label in (JAX, COMPILED):
                if label in labels:
                    firsts = [
                        _fmt_time(per_n[str(n)][label]["first_s"]) if label in per_n.get(str(n), {}) else "—"
                        for n in sizes
                    ]
                    lines.append(f"| ({label}, first call) | " + " | ".join(firsts) + " |")
            spread = max(t["spread"] for ts in per_n.values() for t in ts.values())
            lines += ["", f"Largest (max - min) / median over blocks: {spread:.0%}.", ""]
    lines += [
        "## Checks",
        "",
        "### pypose's poses against diffquat's `se3_bspline`",
        "",
        "The same control poses (diffquat 4x4 matrices; pypose `(t, q_xyzw)`), pypose at `interval = 1 / "
        "M`, diffquat at `u = i + m / M` and `u = S`; pypose's poses converted to matrices, max absolute "
        "difference from diffquat numpy float64 over every entry.",
        "",
        "| S | M | points | pypose float64 | pypose float32 |",
        "|---|---|---|---|---|",
    ]
    for r in results["pypose_agreement"]:
        lines.append(
            f"| {r['segments']} | {r['per_segment']} | {r['points']} | {r['float64']:.1e} "
            f"| {r['float32']:.1e} |"
        )
    frame = results["scipy_rate_frame"]
    lines += [
        "",
        "### scipy's `RotationSpline` rate",
        "",
        "`s(t, 1)` against the body rate vee(R^T R') and the space rate vee(R' R^T) of its own rotations "
        f"(central differences, step 1e-5, float64): {frame['body']:.1e} from the body rate, "
        f"{frame['space']:.1e} from the space rate. diffquat's `so3_bspline` returns the body rate.",
        "",
        "## Machine and versions",
        "",
        "| | |",
        "|---|---|",
    ]
    lines += [f"| {k} | {v} |" for k, v in results["machine"].items()]
    return "\n".join(lines) + "\n"


def run(quick: bool, out_dir: Path, repeats: int | None = None) -> dict[str, Any]:
    import torch

    cases = sorted(set(_cases(quick, False)) | set(_cases(quick, True)), key=lambda c: c[0] * c[1])
    repeats = repeats or DEFAULT_REPEATS[quick]
    block_s = 0.002 if quick else 0.05
    started = time.time()
    load_before = os.getloadavg()
    timed = timings(repeats, block_s, quick)
    results: dict[str, Any] = {
        "quick": quick,
        "cases": [list(c) for c in cases],
        "backward_cases": [list(c) for c in _cases(quick, True)],
        "repeats": repeats,
        "torch_threads": torch.get_num_threads(),
        "timings": timed,
        "ratios": ratios(timed),
        "pypose_agreement": pypose_agreement(quick),
        "scipy_rate_frame": scipy_rate_frame(),
    }
    return finish(results, started, load_before, out_dir, "motion", render)


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=(__doc__ or "").split("\n")[0])
    parser.add_argument("--quick", action="store_true", help="one small size, few repeats: seconds")
    parser.add_argument("--out", type=Path, default=Path(__file__).resolve().parent)
    parser.add_argument("--threads", type=int, default=1, help="torch's CPU threads (default 1)")
    parser.add_argument("--repeats", type=int, default=None, help="rotated blocks per cell")
    parser.add_argument("--render-only", action="store_true", help="rewrite MOTION.md from motion.json")
    args = parser.parse_args(argv)
    if args.render_only:
        results = json.loads((args.out / "motion.json").read_text())
        (args.out / "MOTION.md").write_text(render(results))
        return
    import torch

    torch.set_num_threads(args.threads)
    run(args.quick, args.out, args.repeats)


if __name__ == "__main__":
    main()
