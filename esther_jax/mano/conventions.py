"""Conversions between hand conventions: mirroring, smplx's translation, frame changes.

Our `ManoParams.transl` is the wrist joint's position, so a rigid change of frame is
`(R_c R, R_c transl + t_c)`. smplx's `transl` is instead an offset added after
skinning while the root rotates about the shape-dependent rest wrist J0(beta):
`wrist = J0(beta) + transl_smplx` (the pitfall of facebookresearch/hot3d#37).
"""

import jax.numpy as jnp
from jaxtyping import Array, Float

from .._math import apply3, matmul3
from ..rotations import axis_angle_to_matrix, matrix_to_axis_angle
from .kinematics import rest_joints
from .model import ManoModel, ManoParams

_AXIS_ANGLE_MIRROR = (1.0, -1.0, -1.0)
_POINT_MIRROR = (-1.0, 1.0, 1.0)


def _along_last_axis(signs: tuple[float, float, float], x: Array) -> Array:
    return jnp.asarray(signs, x.dtype).reshape((1,) * (x.ndim - 1) + (3,))


def mirror_points(points: Float[Array, "*batch 3"]) -> Float[Array, "*batch 3"]:
    """Reflect points x -> -x (the left/right mirror of the rig or model frame)."""
    return points * _along_last_axis(_POINT_MIRROR, points)


def mirror_hand_pose(hand_pose: Float[Array, "*batch 3"]) -> Float[Array, "*batch 3"]:
    """The mirror image of rotation vectors: (x, y, z) -> (x, -y, -z) (a right hand's
    joint rotations become the left model's, and back)."""
    return hand_pose * _along_last_axis(_AXIS_ANGLE_MIRROR, hand_pose)


def mirror_params(params: ManoParams) -> ManoParams:
    """The mirror-image hand: rotation vectors (x, y, z) -> (x, -y, -z), wrist x -> -x.

    A right hand's parameters become the left model's (and back); mirroring twice is
    the identity. Any leading batch axes are kept.
    """
    return ManoParams(
        global_orient=mirror_hand_pose(params.global_orient),
        hand_pose=mirror_hand_pose(params.hand_pose),
        betas=params.betas,
        transl=mirror_points(params.transl),
    )


def to_smplx(model: ManoModel, params: ManoParams) -> tuple[Float[Array, "3"], Float[Array, "3"]]:
    """`(global_orient, transl_smplx)` that make smplx's MANO layer place this hand."""
    wrist_rest = rest_joints(model, params.betas)[0]
    return params.global_orient, params.transl - wrist_rest


def from_smplx(
    model: ManoModel,
    global_orient: Float[Array, "3"],
    transl_smplx: Float[Array, "3"],
    hand_pose: Float[Array, "15 3"],
    betas: Float[Array, "betas"],
) -> ManoParams:
    """Our parameters from smplx's `(global_orient, transl)` (e.g. HOT3D's wrist_xform).

    `hand_pose` must be absolute (smplx with `flat_hand_mean=True`, or with
    `hands_mean` already added).
    """
    wrist_rest = rest_joints(model, betas)[0]
    return ManoParams(global_orient=global_orient, hand_pose=hand_pose, betas=betas, transl=transl_smplx + wrist_rest)


def transform_params(T_b_a: Float[Array, "4 4"], params: ManoParams) -> ManoParams:
    """Express a hand given in frame a in frame b (`X_b = T_b_a @ X_a`)."""
    R_c = T_b_a[:3, :3]
    R = matmul3(R_c, axis_angle_to_matrix(params.global_orient))
    return ManoParams(
        global_orient=matrix_to_axis_angle(R),
        hand_pose=params.hand_pose,
        betas=params.betas,
        transl=apply3(R_c, params.transl) + T_b_a[:3, 3],
    )
