"""Stereo prefilter (appendix A) and initialisation of the fit, on any rig geometry.

Prefilter: every fused joint is triangulated with its confidences (the core's
`triangulate_batch`); joints whose depth along the axis of a camera that observes them
is outside 0.1-1.0 m are rejected (on a divergent rig the rig frame's z says little:
a hand 0.42 m from the headset can sit at z = 0.05 m in the left camera), and so are
isolated matches: joints all of whose triangulated bones deviate by more than 40 % from
the model's template bone lengths. The survivors' 2D keypoints are the observation set.
A joint seen by one view only cannot be triangulated and is kept as a monocular
observation.

Initialisation, per frame:
- wrist: the triangulated wrist; within 8 frames of a triangulated wrist the
  interpolation between them (held at the ends); otherwise, when one view sees
  the palm, the wrist's ray in that view at the distance the hand's known size implies
  (the palm's template edge lengths over their angles between rays, least foreshortened
  edges, clipped to the 0.1-1.0 m range, median-filtered over +-3 frames); frames with none of these are interpolated over time (held at the ends).
- orientation: a weighted Kabsch fit of the palm (wrist, thumb CMC and the four finger
  MCPs, which MANO moves rigidly with the wrist) to its triangulation, or in a
  monocular frame to the palm lifted along its rays at the estimated distance; the
  thumb CMC sits off the palm plane, which fixes the mirror ambiguity of a flat palm.
  Frames without a palm copy the nearest frame that has one; a clip without any takes
  an egocentric default (fingers forward, back of the hand up).

Everything is JAX (jit / vmap-able); nothing goes to the host.
"""

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Bool, Float

from esther_jax import mano
from esther_jax.cameras import StereoRig, apply_transform
from esther_jax.mano import KEYPOINT_PARENTS, PALM_KEYPOINTS
from esther_jax.rotations import axis_angle_to_matrix, matrix_to_axis_angle
from esther_jax.triangulation import triangulate_batch

from .fusion import Fused

DEPTH_RANGE_M = (0.1, 1.0)
BONE_TOLERANCE = 0.4
MEDIAN_HALF_WINDOW = 3
"""Monocular wrist estimates are median-filtered over +-3 frames (outlying keypoints)."""
MAX_INTERPOLATED_GAP = 8
"""Frames at most this far from a triangulated wrist interpolate (or hold) it rather than
estimate it from the hand's size (more reliable over a quarter of a second)."""
PALM_EDGES = ((0, 5), (0, 9), (0, 13), (0, 17), (5, 17), (1, 5))
"""Keypoint pairs rigid with the wrist whose template lengths give a monocular distance."""


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


def template_bones(model: mano.ManoModel, betas: Float[Array, "10"] | None = None) -> Float[Array, "21"]:
    """Bone length (m) of each keypoint to its parent at `betas` (default: mean shape; 0 for the wrist)."""
    params = mano.ManoParams.zeros()
    if betas is not None:
        params = mano.ManoParams(params.global_orient, params.hand_pose, betas, params.transl)
    joints = mano.forward_joints(model, params, check_finite=False)
    parents = jnp.asarray([max(p, 0) for p in KEYPOINT_PARENTS])
    return jnp.linalg.norm(joints - joints[parents], axis=-1)


def prefilter(rig: StereoRig, fused: Fused, bones: Float[Array, "21"]) -> Evidence:
    """Appendix A's coarse filter: per-camera depth range, then isolated bone lengths."""
    tri = triangulate_batch(rig.cameras, rig.T_rig_cams, jnp.swapaxes(fused.uv, 1, 2), jnp.swapaxes(fused.conf, 1, 2))
    X, valid = tri.point, tri.valid  # (T, 21, 3), (T, 21)
    depth = jnp.moveaxis(rig.depths(X), 0, 1)  # (T, 2, 21) along each camera's axis
    seen = fused.conf > 0
    in_range = (depth >= DEPTH_RANGE_M[0]) & (depth <= DEPTH_RANGE_M[1])
    depth_ok = jnp.all(in_range | ~seen, axis=1)
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


class Initial(eqx.Module):
    """Initial per-frame wrist and orientation, and where they came from."""

    transl: Float[Array, "frames 3"]
    """Initial wrist (rig frame, m)."""
    global_orient: Float[Array, "frames 3"]
    wrist_triangulated: Bool[Array, "frames"]
    """The wrist was triangulated in this frame (the soft anchor applies)."""
    wrist_monocular: Bool[Array, "frames"]
    """The wrist came from the hand's size along its ray in one view."""
    palm_seen: Bool[Array, "frames"]


def _nearest_known(known: Bool[Array, "frames"]) -> jax.Array:
    """Index of the nearest frame where `known` holds (ties: the earlier); 0 when none."""
    T = known.shape[0]
    t = jnp.arange(T)
    last = jax.lax.cummax(jnp.where(known, t, -1))
    nxt = jax.lax.cummin(jnp.where(known, t, T), reverse=True)
    use_next = (last < 0) | ((nxt < T) & (nxt - t < t - last))
    return jnp.clip(jnp.where(use_next, nxt, last), 0, T - 1)


def _running_median(values: Float[Array, "frames k"], known: Bool[Array, "frames"], half: int) -> Float[Array, "frames k"]:
    """Per-coordinate median of the known values within +-`half` frames (robust to a
    single-frame outlier); unknown frames keep their values."""
    T = values.shape[0]
    idx = jnp.clip(jnp.arange(T)[:, None] + jnp.arange(-half, half + 1)[None], 0, T - 1)
    ok = known[idx] & (jnp.abs(idx - jnp.arange(T)[:, None]) <= half)
    near = jnp.where(ok[..., None], values[idx], jnp.nan)  # (T, 2h+1, k)
    med = jnp.nanmedian(near, axis=1)
    return jnp.where(known[:, None] & jnp.all(jnp.isfinite(med), axis=1, keepdims=True), med, values)


def _interpolate(values: Float[Array, "frames k"], known: Bool[Array, "frames"]) -> Float[Array, "frames k"]:
    """Linear interpolation over time where `known` is False (held at the ends)."""
    T = known.shape[0]
    t = jnp.arange(T)
    last = jax.lax.cummax(jnp.where(known, t, -1))
    nxt = jax.lax.cummin(jnp.where(known, t, T), reverse=True)
    lo = jnp.clip(jnp.where(last < 0, nxt, last), 0, T - 1)
    hi = jnp.clip(jnp.where(nxt >= T, last, nxt), 0, T - 1)
    span = jnp.maximum(hi - lo, 1).astype(values.dtype)
    a = jnp.clip((t - lo).astype(values.dtype) / span, 0.0, 1.0)
    return (1.0 - a)[:, None] * values[lo] + a[:, None] * values[hi]


def kabsch(
    P: Float[Array, "n 3"], Q: Float[Array, "n 3"], w: Float[Array, "n"]
) -> Float[Array, "3 3"]:
    """The proper rotation R minimising sum_i w_i |R p_i - q_i|^2 (p, q already centred
    on the wrist)."""
    H = jnp.einsum("n,ni,nj->ij", w, P, Q)
    U, _, Vt = jnp.linalg.svd(H)
    d = jnp.sign(jnp.linalg.det(Vt.T @ U.T))
    D = jnp.diag(jnp.stack([jnp.ones_like(d), jnp.ones_like(d), jnp.where(d == 0, 1.0, d)]))
    return Vt.T @ D @ U.T


def _egocentric_default(is_right: Bool[Array, ""], dtype) -> Float[Array, "3 3"]:
    R = jnp.asarray([[0.0, 0.0, -1.0], [0.0, -1.0, 0.0], [-1.0, 0.0, 0.0]], dtype)
    M = jnp.diag(jnp.stack([jnp.where(is_right, 1.0, -1.0), jnp.ones((), dtype), jnp.ones((), dtype)]).astype(dtype))
    return M @ R @ M


def monocular_wrist(
    rig: StereoRig, uv: Float[Array, "2 21 2"], weight: Float[Array, "2 21"], rest: Float[Array, "21 3"]
) -> tuple[Float[Array, "3"], Float[Array, "21 3"], Bool[Array, ""]]:
    """Wrist and lifted palm of one frame from one view and the hand's known size.

    In the view with the most observed palm keypoints, the wrist lies on its ray at the
    distance D = template length / angle between the two rays of a palm edge:
    foreshortening only shortens an edge, so the least foreshortened edges give the
    distance (the second smallest estimate when three or more edges are seen, which
    ignores one outlying keypoint). The palm's keypoints are lifted along their rays to
    D (a weak-perspective palm).

    Returns:
        wrist (rig frame, m), the 21 lifted keypoints (rig frame; only palm ones
        meaningful), and whether an estimate exists (the wrist and two palm edges seen).
    """
    palm_w = weight[:, np.asarray(PALM_KEYPOINTS)]
    view = jnp.argmax(2 * jnp.sum(palm_w > 0, axis=1) + (weight[:, 0] > 0).astype(jnp.int32))  # most palm, then the wrist
    cams = rig.cameras
    rays = jax.vmap(lambda cam, p: cam.unproject_with_validity(p))(cams, uv)  # ((2, 21, 3), (2, 21))
    d = rays[0][view]
    ok = (weight[view] > 0) & rays[1][view]
    d_unit = d / jnp.linalg.norm(d, axis=-1, keepdims=True)
    estimates = []
    for a, b in PALM_EDGES:
        chord = jnp.linalg.norm(d_unit[a] - d_unit[b])
        angle = 2.0 * jnp.arcsin(jnp.clip(0.5 * chord, 0.0, 1.0))
        length = jnp.linalg.norm(rest[a] - rest[b])
        good = ok[a] & ok[b] & (angle > 1e-4)
        estimates.append(jnp.where(good, length / jnp.where(good, angle, 1.0), jnp.inf))
    est = jnp.sort(jnp.stack(estimates))
    usable = jnp.sum(jnp.isfinite(est))
    # the least foreshortened edges; the second smallest ignores one outlier keypoint
    distance = jnp.where(usable >= 3, est[1], est[0])
    has = (usable >= 2) & ok[0]
    distance = jnp.clip(distance, *DEPTH_RANGE_M)
    distance = jnp.where(has, distance, 0.4)
    lifted_cam = d_unit * distance
    T_rig_cam = rig.T_rig_cams[view]
    lifted = apply_transform(T_rig_cam, lifted_cam)
    return lifted[0], lifted, has


def initialise(model: mano.ManoModel, rig: StereoRig, evidence: Evidence, betas: Float[Array, "10"]) -> Initial:
    """Wrist translation and orientation per frame (see the module docstring)."""
    X = evidence.joints3d
    valid = evidence.joints3d_valid
    dtype = X.dtype
    rest = mano.forward_joints(model, mano.ManoParams(jnp.zeros(3, dtype), jnp.zeros((15, 3), dtype), betas, jnp.zeros(3, dtype)), check_finite=False)
    mono_wrist, lifted, mono_ok = jax.vmap(monocular_wrist, in_axes=(None, 0, 0, None))(rig, evidence.uv, evidence.weight, rest)
    tri_ok = valid[:, 0]
    # a short gap between triangulated wrists is better interpolated than estimated from size
    t = jnp.arange(X.shape[0])
    last = jax.lax.cummax(jnp.where(tri_ok, t, -X.shape[0]))
    nxt = jax.lax.cummin(jnp.where(tri_ok, t, 2 * X.shape[0]), reverse=True)
    short_gap = jnp.minimum(t - last, nxt - t) <= MAX_INTERPOLATED_GAP
    mono_ok = mono_ok & ~tri_ok & ~short_gap
    mono_wrist = _running_median(mono_wrist, mono_ok, MEDIAN_HALF_WINDOW)
    wrist = jnp.where(tri_ok[:, None], X[:, 0], mono_wrist)
    known = tri_ok | mono_ok
    # nothing to start from anywhere: 0.4 m ahead of the cameras' midpoint
    midpoint = 0.5 * rig.T_left_right[:3, 3]
    default = jnp.broadcast_to(midpoint + jnp.asarray([0.0, 0.0, 0.4], dtype), wrist.shape)
    transl = jnp.where(jnp.any(known), _interpolate(wrist, known), default)

    palm = np.asarray(PALM_KEYPOINTS)
    P = rest[palm] - rest[0][None]
    tri_w = valid[:, palm].astype(dtype)
    tri_seen = jnp.sum(tri_w, axis=1) >= 3
    mono_w = (jnp.max(evidence.weight[:, :, palm], axis=1) > 0).astype(dtype)
    mono_seen = mono_ok & (jnp.sum(mono_w, axis=1) >= 3)
    Q = jnp.where(tri_seen[:, None, None], X[:, palm], lifted[:, palm]) - transl[:, None]
    w = jnp.where(tri_seen[:, None], tri_w, mono_w)
    R = jax.vmap(kabsch, in_axes=(None, 0, 0))(P, Q, w)
    seen = tri_seen | mono_seen
    R = R[_nearest_known(seen)]
    R = jnp.where(jnp.any(seen), R, _egocentric_default(model.is_right, dtype)[None])
    return Initial(
        transl=transl,
        global_orient=matrix_to_axis_angle(R),
        wrist_triangulated=tri_ok,
        wrist_monocular=mono_ok,
        palm_seen=seen,
    )


def monocular_average(rig: StereoRig, monocular: dict) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Fuse per-view monocular MANO estimates in the rig frame, as the paper does with
    WiLoR: both views' estimates are moved into the rig (left) frame and averaged
    (rotations by the chordal mean, poses arithmetically). Host-side: it reads an input file.

    Args:
        monocular: monocular.npz arrays (per view, in that camera's frame).
    Returns:
        global_orient (T, 3), hand_pose (T, 15, 3) in the rig frame, and which frames have one (T,).
    """
    dtype = jnp.result_type(float)
    R_views = np.asarray(axis_angle_to_matrix(jnp.asarray(monocular["global_orient"], dtype)), np.float64)
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
    orient = np.asarray(matrix_to_axis_angle(jnp.asarray(R, dtype)), np.float64)
    return orient, pose, any_view
