"""The string options of the public API as ``Literal`` types, written once.

A type checker then catches a misspelt representation or Euler convention where the call is written
(and an editor offers the choices); at run time a wrong string still raises ``ValueError`` naming the
function. The public aliases are exported by :mod:`diffquat` (which imports neither torch nor jax).
A new string option of a public function gets its alias here, and the test that compares each alias
with the values the code accepts (``tests/test_api.py``).
"""

from __future__ import annotations

from typing import Literal, TypeAlias

# The 24 Euler conventions, scipy's rule: upper case intrinsic (rotations about the axes of the
# rotating frame), lower case extrinsic (about the fixed axes); the 6 Tait-Bryan sequences (three
# different axes) and the 6 proper ones (first axis = third) in each case.
EulerConvention: TypeAlias = Literal[
    "XYZ", "XZY", "YXZ", "YZX", "ZXY", "ZYX",
    "XYX", "XZX", "YXY", "YZY", "ZXZ", "ZYZ",
    "xyz", "xzy", "yxz", "yzx", "zxy", "zyx",
    "xyx", "xzx", "yxy", "yzy", "zxz", "zyz",
]  # fmt: skip

# What a rotation head regresses (diffquat.torch.nn, diffquat.jax.nn), by its number of raw outputs:
# 4, 3, 3, 6, 9 and 10.
Representation: TypeAlias = Literal["quaternion", "axis_angle", "euler", "6d", "9d", "10d"]

# How the 6D representation stores the first two columns of a rotation matrix: "columns" (Zhou et
# al.'s paper, diffquat's default) stacks the first two columns, "rows" the first two rows (pytorch3d's
# layout, which is the transpose: a checkpoint trained with pytorch3d reads its 6D outputs so).
Rotation6DLayout: TypeAlias = Literal["columns", "rows"]

# On which side a tangent vector perturbs a rotation (the Lie-group plus and minus, and the left and
# right Jacobians): "right" is R exp(delta), "left" is exp(delta) R.
Side: TypeAlias = Literal["left", "right"]

# The rotation averages: "chordal" (the projection of the arithmetic mean of the matrices, scipy's
# Rotation.mean), "geodesic" (the Karcher mean), "geodesic_l1" (the geodesic median).
MeanMethod: TypeAlias = Literal["chordal", "geodesic", "geodesic_l1"]
