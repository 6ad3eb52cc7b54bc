"""Anatomical joint frames and the joint-limit table (flexion, abduction, twist).

MANO's `hand_pose[j]` is a rotation vector in the rest-pose (model) axes. Each joint
also has an anatomical frame computed from the model's rest joints, so that limits
and priors are stated once, in anatomical terms, for any MANO-format model (our
built-in hand or a user's official file) and for both sides:

- twist axis `d`: from the joint to its child (the tip for the distal joints);
- abduction axis `s * u`, with `u` the dorsal direction orthogonalised against `d`
  (for the thumb, the thumbnail direction: the dorsal normal turned 40 degrees to
  the radial side);
- flexion axis `u x d` (positive flexion curls towards the palm).

`s` is +1 for a right hand and -1 for a left hand, which makes the three angles
mirror-invariant: a right pose and its mirror (`mirror_params`) have the same
anatomical angles, with positive abduction towards the thumb on both sides.
"""

import math

import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Bool, Float

from .._math import cross, safe_normalize
from .constants import FINGER_CHAINS, FINGER_ORDER

THUMBNAIL_TURN_RAD = math.radians(40.0)
"""Angle from the dorsal normal towards the radial side that defines the thumb's 'dorsal'."""

# Limits in degrees as (low, high) for (flexion, abduction, twist), per joint class.
# Typical adult active ranges of motion (clinical goniometry norms: MCP flexion ~90,
# PIP ~100-110, DIP ~80-90, thumb CMC/MCP/IP smaller), widened by a few degrees for
# passive motion; thumb CMC twist +-45 as in lixiny/manotorch's anatomy defaults.
_LIMITS_DEG = {
    "mcp": ((-30.0, 90.0), (-25.0, 25.0), (-15.0, 15.0)),
    "pip": ((-5.0, 115.0), (-8.0, 8.0), (-8.0, 8.0)),
    "dip": ((-15.0, 90.0), (-8.0, 8.0), (-8.0, 8.0)),
    "thumb_cmc": ((-25.0, 55.0), (-35.0, 50.0), (-45.0, 45.0)),
    "thumb_mcp": ((-15.0, 70.0), (-12.0, 12.0), (-20.0, 20.0)),
    "thumb_ip": ((-20.0, 90.0), (-8.0, 8.0), (-8.0, 8.0)),
}


def _joint_class(joint: int) -> str:
    for finger, chain in FINGER_CHAINS.items():
        if joint in chain:
            level = chain.index(joint)
            if finger == "thumb":
                return ("thumb_cmc", "thumb_mcp", "thumb_ip")[level]
            return ("mcp", "pip", "dip")[level]
    raise ValueError(f"joint {joint} is not a finger joint (1..15)")


JOINT_LIMITS: np.ndarray = np.deg2rad(
    np.asarray([_LIMITS_DEG[_joint_class(j)] for j in range(1, 16)], dtype=np.float64)
)
"""(15, 3, 2) radians: per MANO joint 1..15, (flexion, abduction, twist) x (low, high)."""


def anatomical_frames(
    joints_rest: Float[Array, "16 3"],
    tips_rest: Float[Array, "5 3"],
    is_right: Bool[Array, ""] | bool,
) -> Float[Array, "15 3 3"]:
    """Per finger joint 1..15, a rotation whose columns are the (flexion, abduction,
    twist) axes in the model frame.

    Args:
        joints_rest: the 16 rest joints (MANO order) of the model at the betas of interest.
        tips_rest: rest fingertip vertices in FINGER_ORDER (thumb, index, middle, ring, pinky).
        is_right: handedness; flips the sign of the abduction and twist axes.
    """
    side = jnp.where(jnp.asarray(is_right), 1.0, -1.0).astype(joints_rest.dtype)
    wrist = joints_rest[0]
    index_mcp, middle_mcp, pinky_mcp = joints_rest[1], joints_rest[4], joints_rest[7]
    # dorsal normal of the palm: for a right hand (pinky - wrist) x (index - wrist)
    dorsal = safe_normalize(side * cross(pinky_mcp - wrist, index_mcp - wrist))
    radial = index_mcp - pinky_mcp
    radial = safe_normalize(radial - jnp.sum(radial * dorsal) * dorsal)
    thumbnail = math.cos(THUMBNAIL_TURN_RAD) * dorsal + math.sin(THUMBNAIL_TURN_RAD) * radial
    del middle_mcp

    # child of each joint: the next joint in its chain, or the fingertip
    child = list(range(16))
    tip_of = {}  # last joint of a chain -> its slot in FINGER_ORDER
    for finger_index, finger in enumerate(FINGER_ORDER):
        chain = FINGER_CHAINS[finger]
        for a, b in zip(chain[:-1], chain[1:]):
            child[a] = b
        tip_of[chain[-1]] = finger_index
    frames = []
    for j in range(1, 16):
        end = tips_rest[tip_of[j]] if j in tip_of else joints_rest[child[j]]
        d = safe_normalize(end - joints_rest[j])
        up = thumbnail if j in FINGER_CHAINS["thumb"] else dorsal
        u = safe_normalize(up - jnp.sum(up * d) * d)
        flex = cross(u, d)
        frames.append(jnp.stack([flex, side * u, side * d], axis=-1))
    return jnp.stack(frames)


def hand_pose_to_anatomical(
    hand_pose: Float[Array, "15 3"], frames: Float[Array, "15 3 3"]
) -> Float[Array, "15 3"]:
    """(flexion, abduction, twist) of each joint: its rotation vector in the anatomical
    frame (radians). Exact for single-axis motions; a smooth swing-twist proxy otherwise."""
    return jnp.einsum("jai,ja->ji", frames, hand_pose)


def anatomical_to_hand_pose(
    angles: Float[Array, "15 3"], frames: Float[Array, "15 3 3"]
) -> Float[Array, "15 3"]:
    """Inverse of `hand_pose_to_anatomical`: rotation vectors in model axes."""
    return jnp.einsum("jai,ji->ja", frames, angles)

