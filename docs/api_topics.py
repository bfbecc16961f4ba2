"""The topics of the API reference: every public name of every public module in exactly one topic.

The API pages are generated from each module's ``__all__`` (docs/hooks.py), so a new public function
appears without editing a page; where it appears is decided here. Adding a public name to any public
module (or a new public module) makes ``mkdocs build`` and ``tests/test_docs.py`` fail until the name
is placed in one topic below: that is the intended workflow. A new topic is one more entry (the
order here is the order on the pages); a name that two modules share (``representation_to_matrix``
in ``diffquat.torch.nn`` and ``diffquat.jax.nn``) is placed once.
"""

from __future__ import annotations

from diffquat._public import public_modules

TOPICS: dict[str, list[str]] = {
    "Objects: SO3 and SE3": ["SO3", "SE3"],
    "Quaternions and rotation matrices": [
        "quaternion_to_matrix",
        "matrix_to_quaternion",
        "standardize_quaternion",
        "normalize_quaternion",
        "wxyz_to_xyzw",
        "xyzw_to_wxyz",
        "random_quaternions",
    ],
    "Rotation vectors (axis-angle)": [
        "axis_angle_to_quaternion",
        "quaternion_to_axis_angle",
        "axis_angle_to_matrix",
        "matrix_to_axis_angle",
    ],
    "Euler angles": [
        "euler_angles_to_matrix",
        "matrix_to_euler_angles",
        "euler_angles_to_quaternion",
        "quaternion_to_euler_angles",
    ],
    "Quaternion algebra and interpolation": [
        "quaternion_multiply",
        "quaternion_conjugate",
        "quaternion_invert",
        "quaternion_apply",
        "quaternion_slerp",
    ],
    "Distances": ["quaternion_geodesic_distance", "matrix_geodesic_distance"],
    "Representations for networks (6D, 9D, 10D)": [
        "rotation_6d_to_matrix",
        "matrix_to_rotation_6d",
        "special_procrustes",
        "symmetric_matrix_to_quaternion",
    ],
    "Fitting": ["fit_rotation"],
    "Lie calculus on SO(3)": [
        "so3_hat",
        "so3_vee",
        "so3_exp",
        "so3_log",
        "so3_left_jacobian",
        "so3_right_jacobian",
        "so3_left_jacobian_inverse",
        "so3_right_jacobian_inverse",
        "so3_plus",
        "so3_minus",
        "quaternion_plus",
        "quaternion_minus",
    ],
    "Poses: SE(3)": [
        "se3_from_rotation_translation",
        "se3_to_rotation_translation",
        "se3_compose",
        "se3_inverse",
        "se3_apply",
        "se3_hat",
        "se3_vee",
        "se3_exp",
        "se3_log",
        "se3_adjoint",
        "se3_ad",
        "se3_left_jacobian",
        "se3_right_jacobian",
        "se3_left_jacobian_inverse",
        "se3_right_jacobian_inverse",
        "se3_plus",
        "se3_minus",
        "se3_interpolate",
        "pose_to_matrix",
        "matrix_to_pose",
        "se3_mean",
        "fit_rigid_transform",
        "fit_similarity_transform",
        "rotation_between_vectors",
        "frame_from_three_points",
    ],
    "Rotations in time": [
        "angular_velocity",
        "quaternion_derivative",
        "angular_acceleration",
        "integrate_angular_velocity",
        "angular_velocity_from_quaternions",
        "quaternion_squad",
        "so3_bspline",
        "se3_bspline",
    ],
    "Rotation averaging and symmetric objects": [
        "rotation_mean",
        "quaternion_mean",
        "symmetry_group",
        "symmetric_geodesic_distance",
    ],
    "The matrix Fisher distribution": [
        "matrix_fisher_log_normalizer",
        "matrix_fisher_nll",
        "matrix_fisher_mode",
        "matrix_fisher_sample",
        "bingham_nll",
        "MatrixFisher",
        "special_orthogonal",
    ],
    "The isotropic Gaussian on SO(3), IGSO(3)": [
        "igso3_log_density",
        "igso3_score",
        "igso3_angle_cdf",
        "igso3_sample",
    ],
    "Rotation heads": [
        "RotationHead",
        "representation_to_matrix",
        "representation_to_fisher",
        "representation_size",
        "REPRESENTATIONS",
        "init_rotation_head",
        "rotation_head",
    ],
    "Optimisers on SO(3) and SE(3)": [
        "RiemannianAdam",
        "RiemannianSGD",
        "MANIFOLDS",
        "riemannian_adam",
        "riemannian_sgd",
        "scale_by_riemannian_adam",
        "riemannian_momentum",
        "project_to_tangent",
        "apply_updates",
        "ScaleByRiemannianAdamState",
        "RiemannianMomentumState",
    ],
    "Types": [
        "EulerConvention",
        "Frame",
        "MeanMethod",
        "PoseLayout",
        "Representation",
        "Rotation6DLayout",
        "SE3Interpolation",
        "Side",
        "SplineMode",
    ],
    "Version": ["__version__"],
}


def topic_of() -> dict[str, str]:
    """Each name's topic; ``ValueError`` for a name placed twice."""
    placed: dict[str, str] = {}
    for topic, names in TOPICS.items():
        for name in names:
            if name in placed:
                raise ValueError(
                    f"docs/api_topics.py: {name!r} is in two topics, {placed[name]!r} and {topic!r}"
                )
            placed[name] = topic
    return placed


def problems() -> list[str]:
    """What stops the topic map from covering the public API exactly: public names in no topic, and
    names in a topic that no public module exports. Empty when the map is complete."""
    placed = topic_of()
    exported = {(m.__name__, n) for m in public_modules() for n in m.__all__}
    out = [
        f"{module}.{name} is in no topic of docs/api_topics.py: add it to one"
        for module, name in sorted(exported)
        if name not in placed
    ]
    names = {n for _, n in exported}
    out += [
        f"docs/api_topics.py lists {n!r}, which no public module exports" for n in placed if n not in names
    ]
    return out
