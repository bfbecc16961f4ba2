"""diffquat: differentiable 3D rotations, one semantics on NumPy, PyTorch and JAX.

Import the backend you use; ``import diffquat`` itself imports neither torch nor jax::

    import diffquat.torch as dq   # or diffquat.jax, diffquat.numpy

Conventions, identical on every backend:

- Quaternions have shape ``(..., 4)``. ``scalar_first=True`` (the default) reads (w, x, y, z);
  ``scalar_first=False`` reads (x, y, z, w), the order of ROS, scipy and Isaac. Every function that
  takes or returns a quaternion has this keyword.
- Rotation matrices have shape ``(..., 3, 3)`` and act on column vectors: ``R @ v`` rotates ``v`` from
  the local frame into the global frame (active rotation), as in Kuipers, *Quaternions and Rotation
  Sequences*, section 5.14.
- Quaternions are returned in canonical sign: w > 0, and where w = 0 the first non-zero of (x, y, z)
  is positive (scipy's ``as_quat(canonical=True)``).
- Quaternions going in may have any non-zero norm; the result does not depend on it. The zero
  quaternion gives the identity (matrix or quaternion), with a finite gradient.
- Any leading batch shape, ``()`` and empty batches included. Dtype and device are preserved;
  float16 and bfloat16 are computed in float32 and returned in the input dtype.
- A non-floating input raises ``TypeError``; a wrong trailing shape raises ``ValueError`` naming the
  function, the expected shape and the shape received. Values never raise (that is impossible under
  ``jit``): edge cases have one documented result instead.
"""

from ._types import EulerConvention as EulerConvention
from ._types import Representation as Representation
from ._types import Rotation6DLayout as Rotation6DLayout

__version__ = "0.1.0"

__all__ = ["EulerConvention", "Representation", "Rotation6DLayout", "__version__"]
