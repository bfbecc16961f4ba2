"""diffquat: differentiable 3D rotations, one semantics on NumPy, PyTorch and JAX.

Import the backend you use; ``import diffquat`` itself imports neither torch nor jax::

    import diffquat.torch as dq   # or diffquat.jax, diffquat.numpy

The conventions, identical on every backend, are spelled out in full on the documentation's
Conventions page (``docs/conventions.md``). In short: quaternions ``(..., 4)`` scalar first (w, x, y, z)
unless ``scalar_first=False``; matrices ``(..., 3, 3)`` act on column vectors (active rotations);
returned quaternions have w > 0; any input norm, the zero quaternion being the identity; any batch
shape; float16 and bfloat16 computed in float32; wrong shapes and dtypes raise, values never do.
"""

from ._types import EulerConvention as EulerConvention
from ._types import Frame as Frame
from ._types import MeanMethod as MeanMethod
from ._types import PoseLayout as PoseLayout
from ._types import Representation as Representation
from ._types import Rotation6DLayout as Rotation6DLayout
from ._types import SE3Interpolation as SE3Interpolation
from ._types import Side as Side
from ._types import SplineMode as SplineMode

__version__ = "0.1.0"

__all__ = [
    "EulerConvention",
    "Frame",
    "MeanMethod",
    "PoseLayout",
    "Representation",
    "Rotation6DLayout",
    "SE3Interpolation",
    "Side",
    "SplineMode",
    "__version__",
]
