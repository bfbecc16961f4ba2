"""Network output -> rotation matrix, for every representation a rotation head can regress; written once.

A rotation head is a linear layer whose ``n`` raw outputs are mapped to a rotation matrix. The mapping
per representation is written here once, over the array namespace ``xp`` and the backend's public
module ``dq`` (``diffquat.torch`` or ``diffquat.jax``), whose functions have the same names and
semantics on every backend. Going through ``dq`` rather than the private core keeps each backend's
own fast paths and custom backward passes (the SVD of ``special_procrustes``, the eigendecomposition
of ``symmetric_matrix_to_quaternion``) in the head as well.
"""

from __future__ import annotations

from typing import Any

# Raw outputs per representation, and what they mean (the keys are the public spelling).
REPRESENTATIONS: dict[str, int] = {
    "quaternion": 4,  # (w, x, y, z), any non-zero norm: quaternion_to_matrix is scale invariant
    "axis_angle": 3,  # rotation vector, axis times angle (the exponential map)
    "euler": 3,  # intrinsic Euler angles in radians, EULER_CONVENTION
    "6d": 6,  # the first two columns, Gram-Schmidt (Zhou et al., CVPR 2019)
    "9d": 9,  # any 3x3 matrix, row-major, projected by SVD onto SO(3) (Levinson et al., NeurIPS 2020)
    "10d": 10,  # upper triangle of a symmetric 4x4 matrix (Peretroukhin et al., RSS 2020)
    # the parameter F of a matrix Fisher distribution, row-major (Mohlin et al., NeurIPS 2020): the
    # head's rotation is its mode (the 9D map), and representation_to_fisher gives F for the NLL
    "fisher": 9,
}
EULER_CONVENTION = "XYZ"


def representation_size(representation: str) -> int:
    """Number of raw outputs a head of this representation needs."""
    try:
        return REPRESENTATIONS[representation]
    except KeyError:
        known = ", ".join(repr(r) for r in REPRESENTATIONS)
        raise ValueError(
            f"unknown rotation representation {representation!r}; expected one of {known}"
        ) from None


def representation_to_matrix(xp: Any, dq: Any, raw: Any, representation: str) -> Any:
    """Rotation matrices ``(..., 3, 3)`` from raw head outputs ``(..., n)``, ``n`` as in REPRESENTATIONS.

    Only static information (the representation, the trailing shape) is inspected in Python, so this
    traces under ``torch.compile(fullgraph=True)`` and ``jax.jit``.
    """
    n = representation_size(representation)
    shape = tuple(raw.shape)
    if len(shape) < 1 or shape[-1] != n:
        raise ValueError(
            f"representation_to_matrix: expected raw of shape (..., {n}) for representation "
            f"{representation!r}, got shape {shape}"
        )
    if representation == "quaternion":
        return dq.quaternion_to_matrix(raw)
    if representation == "axis_angle":
        return dq.axis_angle_to_matrix(raw)
    if representation == "euler":
        return dq.euler_angles_to_matrix(raw, EULER_CONVENTION)
    if representation == "6d":
        return dq.rotation_6d_to_matrix(raw)
    if representation == "9d":
        return dq.special_procrustes(xp.reshape(raw, (*shape[:-1], 3, 3)))
    if representation == "fisher":
        return dq.matrix_fisher_mode(representation_to_fisher(xp, raw))
    return dq.quaternion_to_matrix(dq.symmetric_matrix_to_quaternion(raw))


def representation_to_fisher(xp: Any, raw: Any) -> Any:
    """The matrix Fisher parameter F ``(..., 3, 3)`` of a ``"fisher"`` head's raw outputs ``(..., 9)``
    (row-major): the density ``exp(tr(F^T R)) / c(F)``, whose mode is the head's rotation."""
    shape = tuple(raw.shape)
    if len(shape) < 1 or shape[-1] != REPRESENTATIONS["fisher"]:
        raise ValueError(f"representation_to_fisher: expected raw of shape (..., 9), got shape {shape}")
    return xp.reshape(raw, (*shape[:-1], 3, 3))
