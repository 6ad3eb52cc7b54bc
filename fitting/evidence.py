"""Stereo prefilter (appendix A) and initialisation of the fit.

Prefilter: every fused joint is triangulated with its confidences (the core's
`triangulate_batch`); joints whose triangulated depth is outside 0.1-1.0 m are
rejected, and so are isolated matches: joints all of whose triangulated bones deviate
by more than 40 % from the model's template bone lengths. The survivors' 2D keypoints
are the observation set.

Initialisation: the wrist translation is the triangulated wrist (linearly interpolated
over frames where it is missing); the wrist orientation is a weighted Kabsch fit of the
palm (wrist, thumb CMC and the four finger MCPs, which MANO moves rigidly with the wrist)
to its triangulation. The thumb CMC sits off the palm plane, which fixes the
mirror/180-degree ambiguity of a flat palm; frames where the palm is not seen copy the
nearest frame that sees it.
"""

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Bool, Float

from esther_jax import mano
from esther_jax.cameras import StereoRig
from esther_jax.rotations import matrix_to_axis_angle
from esther_jax.triangulation import triangulate_batch

from .fusion import Fused

KEYPOINT_PARENTS = (-1, 0, 1, 2, 3, 0, 5, 6, 7, 0, 9, 10, 11, 0, 13, 14, 15, 0, 17, 18, 19)
"""Parent of each of the 21 keypoints (bones of the 21-keypoint skeleton)."""
PALM_KEYPOINTS = (0, 1, 5, 9, 13, 17)
"""Wrist, thumb CMC, index/middle/ring/pinky MCP: rigid with the wrist in MANO."""
DEPTH_RANGE_M = (0.1, 1.0)
BONE_TOLERANCE = 0.4


class Evidence(eqx.Module):
    """The observation set after the stereo prefilter, and the triangulation."""

    uv: Float[Array, "frames 2 21 2"]
    weight: Float[Array, "frames 2 21"]
    """Fused confidence of kept observations (0 = not observed or rejected)."""
    joints3d: Float[Array, "frames 21 3"]
    """Triangulated joints in the rig frame (metres)."""
    joints3d_valid: Bool[Array, "frames 21"]
    rejected_depth: Float[Array, ""]
    rejected_bones: Float[Array, ""]


def template_bones(model: mano.ManoModel) -> Float[Array, "21"]:
    """Bone length (m) of each keypoint to its parent at the mean shape (0 for the wrist)."""
    joints = mano.forward_joints(model, mano.ManoParams.zeros())
    parents = jnp.asarray([max(p, 0) for p in KEYPOINT_PARENTS])
    return jnp.linalg.norm(joints - joints[parents], axis=-1)


@jax.jit
def prefilter(rig: StereoRig, fused: Fused, bones: Float[Array, "21"]) -> Evidence:
    tri = triangulate_batch(rig.cameras, rig.T_rig_cams, jnp.swapaxes(fused.uv, 1, 2), jnp.swapaxes(fused.conf, 1, 2))
    X, valid = tri.point, tri.valid  # (T, 21, 3), (T, 21)
    depth_ok = (X[..., 2] >= DEPTH_RANGE_M[0]) & (X[..., 2] <= DEPTH_RANGE_M[1])
    bad_depth = valid & ~depth_ok
    valid = valid & depth_ok
    parents = jnp.asarray([max(p, 0) for p in KEYPOINT_PARENTS])
    children = [[c for c, p in enumerate(KEYPOINT_PARENTS) if p == j] for j in range(21)]
    length = jnp.linalg.norm(X - X[:, parents], axis=-1)  # bone to the parent, (T, 21)
    bone_valid = valid & valid[:, parents] & (jnp.arange(21) > 0)[None]
    bone_bad = bone_valid & (jnp.abs(length / jnp.maximum(bones, 1e-6)[None] - 1.0) > BONE_TOLERANCE)
    checked, bad = [], []
    for j in range(21):  # each joint's bones: to its parent and to its children
        own = [(bone_valid[:, j], bone_bad[:, j])] if j > 0 else []
        own += [(bone_valid[:, c], bone_bad[:, c]) for c in children[j]]
        checked.append(sum(v.astype(jnp.int32) for v, _ in own))
        bad.append(sum((v & b).astype(jnp.int32) for v, b in own))
    checked, bad = jnp.stack(checked, 1), jnp.stack(bad, 1)
    isolated = valid & (checked > 0) & (bad == checked)
    reject = bad_depth | isolated
    weight = jnp.where(reject[:, None, :], 0.0, fused.conf)
    return Evidence(
        uv=fused.uv,
        weight=weight,
        joints3d=X,
        joints3d_valid=valid & ~isolated,
        rejected_depth=jnp.sum(bad_depth).astype(weight.dtype),
        rejected_bones=jnp.sum(isolated).astype(weight.dtype),
    )


def _interpolate(values: np.ndarray, known: np.ndarray) -> np.ndarray:
    """Linear interpolation over time of (T, k) values where `known` (T,) is False (held at the ends)."""
    t = np.arange(len(values))
    if not known.any():
        return values
    return np.stack([np.interp(t, t[known], values[known, k]) for k in range(values.shape[1])], axis=1)


def _kabsch(P: np.ndarray, Q: np.ndarray, w: np.ndarray) -> np.ndarray:
    """Rotations R (T, 3, 3) minimising sum w |R p - q|^2 (proper, det +1)."""
    H = np.einsum("tn,tni,tnj->tij", w, P, Q)
    U, _, Vt = np.linalg.svd(H)
    d = np.sign(np.linalg.det(np.einsum("tji,tkj->tik", Vt, U)))
    D = np.ones((len(P), 3))
    D[:, 2] = np.where(d == 0, 1.0, d)
    return np.einsum("tji,tj,tkj->tik", Vt, D, U)


class Initial(eqx.Module):
    """Initial per-frame wrist and orientation, and where they came from."""

    transl: Float[Array, "frames 3"]
    global_orient: Float[Array, "frames 3"]
    wrist_triangulated: Bool[Array, "frames"]
    palm_seen: Bool[Array, "frames"]


def initialise(model: mano.ManoModel, evidence: Evidence, betas: Float[Array, "10"]) -> Initial:
    """Wrist translation and orientation per frame from the triangulation (numpy on host)."""
    X = np.asarray(evidence.joints3d, np.float64)
    valid = np.asarray(evidence.joints3d_valid)
    T = len(X)
    wrist_ok = valid[:, 0]
    rest = np.asarray(mano.forward_joints(model, mano.ManoParams(jnp.zeros(3), jnp.zeros((15, 3)), betas, jnp.zeros(3))), np.float64)
    palm = list(PALM_KEYPOINTS)
    any_ok = valid.any(axis=1)
    if wrist_ok.any():
        transl = _interpolate(X[:, 0], wrist_ok)
    elif any_ok.any():  # no wrist anywhere: start at the centroid of what is triangulated (a few cm off)
        centroid = np.where(any_ok[:, None], (X * valid[..., None]).sum(1) / np.maximum(valid.sum(1), 1)[:, None], 0.0)
        transl = _interpolate(centroid, any_ok)
    else:
        transl = np.tile([0.0, 0.0, 0.4], (T, 1))
    weights = valid[:, palm].astype(np.float64)
    Q = X[:, palm] - transl[:, None]
    P = np.broadcast_to(rest[palm] - rest[0], Q.shape)
    seen = weights.sum(axis=1) >= 3
    R = _kabsch(P, Q, weights)
    if seen.any():
        seen_at = np.flatnonzero(seen)
        nearest = seen_at[np.argmin(np.abs(seen_at[None, :] - np.arange(T)[:, None]), axis=1)]
        R = R[nearest]
    else:  # the palm is never triangulated: an egocentric default (fingers forward, back of the hand up)
        R_ego = np.array([[0.0, 0.0, -1.0], [0.0, -1.0, 0.0], [-1.0, 0.0, 0.0]])
        if not bool(model.is_right):
            M = np.diag([-1.0, 1.0, 1.0])
            R_ego = M @ R_ego @ M
        R = np.tile(R_ego, (T, 1, 1))
    dtype = jnp.result_type(float)
    return Initial(
        transl=jnp.asarray(transl, dtype),
        global_orient=matrix_to_axis_angle(jnp.asarray(R, dtype)),
        wrist_triangulated=jnp.asarray(wrist_ok),
        palm_seen=jnp.asarray(seen),
    )


def monocular_average(rig: StereoRig, monocular: dict) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Fuse per-view monocular MANO estimates in the rig frame, as the paper does with
    WiLoR: both views' estimates are moved into the rig (left) frame and averaged
    (rotations by the chordal mean, poses and wrists arithmetically).

    Args:
        monocular: monocular.npz arrays (per view, in that camera's frame).
    Returns:
        global_orient (T, 3), hand_pose (T, 15, 3) in the rig frame, and which frames have one (T,).
    """
    from esther_jax.rotations import axis_angle_to_matrix

    R_views = np.asarray(axis_angle_to_matrix(jnp.asarray(monocular["global_orient"], jnp.result_type(float))), np.float64)
    R_left_right = np.asarray(rig.T_left_right, np.float64)[:3, :3]
    R_views[:, 1] = np.einsum("ij,tjk->tik", R_left_right, R_views[:, 1])  # right camera -> rig frame
    valid = np.asarray(monocular["valid"], bool)
    w = valid.astype(np.float64)
    summed = np.einsum("tv,tvij->tij", w, R_views)
    U, _, Vt = np.linalg.svd(summed)
    d = np.sign(np.linalg.det(U @ Vt))
    U[:, :, 2] *= np.where(d == 0, 1.0, d)[:, None]
    R = U @ Vt
    any_view = valid.any(axis=1)
    pose = np.einsum("tv,tvjc->tjc", w, np.asarray(monocular["hand_pose"], np.float64)) / np.maximum(w.sum(1), 1)[:, None, None]
    orient = np.asarray(matrix_to_axis_angle(jnp.asarray(R, jnp.result_type(float))), np.float64)
    return orient, pose, any_view
