"""The string options of the public API as ``Literal`` types, written once.

A type checker then catches a misspelt representation or Euler convention where the call is written
(and an editor offers the choices); at run time a wrong string still raises ``ValueError`` naming the
function. The public aliases are exported by ``diffquat`` (which imports neither torch nor jax).
A new string option of a public function gets its alias here, and the test that compares each alias
with the values the code accepts (``tests/test_api.py``).
"""

from __future__ import annotations

from typing import Literal, TypeAlias

EulerConvention: TypeAlias = Literal[
    "XYZ", "XZY", "YXZ", "YZX", "ZXY", "ZYX",
    "XYX", "XZX", "YXY", "YZY", "ZXZ", "ZYZ",
    "xyz", "xzy", "yxz", "yzx", "zxy", "zyx",
    "xyx", "xzx", "yxy", "yzy", "zxz", "zyz",
]  # fmt: skip
"""The 24 Euler conventions, scipy's rule: upper case is intrinsic (rotations about the axes of the
rotating frame, ``"XYZ"``: ``R = R_X(a) R_Y(b) R_Z(c)``), lower case extrinsic (about the fixed axes,
``"xyz"``: ``R = R_z(c) R_y(b) R_x(a)``); in each case the 6 Tait-Bryan sequences (three different
axes) and the 6 proper ones (first axis = third)."""

Representation: TypeAlias = Literal["quaternion", "axis_angle", "euler", "6d", "9d", "10d", "fisher"]
"""What a rotation head regresses (``diffquat.torch.nn``, ``diffquat.jax.nn``), with 4, 3, 3, 6, 9, 10
and 9 raw outputs (``"fisher"``: the parameter F of a matrix Fisher distribution, whose mode is the
rotation)."""

Rotation6DLayout: TypeAlias = Literal["columns", "rows"]
"""How a 6D vector holds its two 3-vectors: ``"columns"`` (Zhou et al.'s paper, diffquat's default),
the first two columns of the matrix; ``"rows"`` (pytorch3d's layout), its first two rows, which is
the transpose: weights trained with pytorch3d's 6D need ``layout="rows"``."""

Side: TypeAlias = Literal["left", "right"]
"""On which side a tangent vector perturbs a rotation (the Lie-group plus and minus, and the left and
right Jacobians): ``"right"`` is ``R exp(delta)``, ``"left"`` is ``exp(delta) R``."""

MeanMethod: TypeAlias = Literal["chordal", "geodesic", "geodesic_l1"]
"""How a rotation average is taken: ``"chordal"`` (the rotation nearest to the arithmetic mean of the
matrices, scipy's ``Rotation.mean``), ``"geodesic"`` (the Karcher mean), ``"geodesic_l1"`` (the
geodesic median)."""

SE3Interpolation: TypeAlias = Literal["screw", "decoupled"]
"""How ``se3_interpolate`` moves between two poses: ``"screw"``, the constant twist
``T1 exp(t log(T1^-1 T2))`` (scipy's ``RigidTransform`` power), or ``"decoupled"``, slerp of the
rotations and a straight line of the translations."""

PoseLayout: TypeAlias = Literal["wxyz_xyz", "xyz_xyzw", "xyzw_xyz", "xyz_wxyz"]
"""The order of a 7-vector pose, a quaternion and a translation: ``"wxyz_xyz"`` (jaxlie, kornia),
``"xyz_xyzw"`` (ROS ``geometry_msgs/Pose``, pypose, lietorch, manif), ``"xyzw_xyz"`` (Sophus),
``"xyz_wxyz"`` (theseus)."""

Frame: TypeAlias = Literal["body", "space"]
"""In which frame an angular velocity or acceleration is expressed: ``"body"`` (the rotating frame's
axes, ``hat(w_b) = R^T R'``: what a gyroscope strapped to the body reads, scipy's ``RotationSpline``
rates), or ``"space"`` (the fixed axes, ``w_s = R w_b``)."""

SplineMode: TypeAlias = Literal["se3", "split"]
"""On which group ``se3_bspline`` interpolates: ``"se3"``, increments of SE(3) (rotation and
translation along screws), or ``"split"``, R^3 x SO(3) (the rotations' ``so3_bspline`` and a B-spline of
the translations in the world)."""
