"""Stereo prefilter (appendix A) and initialisation of the fit, on any rig geometry.

Prefilter: every fused joint is triangulated with its confidences (the core's
`triangulate_rig`); joints whose depth along the axis of a camera that observes them
is outside 0.1-1.0 m are rejected (on a divergent rig the rig frame's z says little:
a hand 0.42 m from the headset can sit at z = 0.05 m in the left camera), and so are
isolated matches: joints all of whose triangulated bones deviate by more than 40 % from
the model's template bone lengths. The survivors' 2D keypoints are the observation set.
A joint seen by one view only cannot be triangulated and is kept as a monocular
observation.

Initialisation, per frame (`initialise`):
- the palm's pose (`palm_pose`): the wrist, thumb CMC and four finger MCPs move rigidly
  with the wrist in MANO, so their template at the clip's shape, seen along the observed
  rays of one or both views, fixes the orientation and, through the hand's known size,
  the distance (perspective-n-point on any camera model, from the triangulated palm's
  Kabsch fit and 24 cube orientations; the lowest cost wins, which also resolves the
  mirror ambiguity of a nearly flat palm: the thumb CMC sits off its plane). With the
  locked shape the pose is refined from the first one rather than searched again.
- wrist: the triangulated wrist where there is one; else the palm pose's wrist
  (median-filtered over +-3 frames) when at least 4 palm keypoints are seen and their rms
  ray angle is below 0.05 rad; frames with neither are interpolated over time (held at
  the ends).
- orientation: the palm pose's; frames without one copy the nearest frame that has one;
  a clip without any takes an egocentric default (fingers forward, back of the hand up).

Everything is JAX (jit / vmap-able); nothing goes to the host.
"""

import functools

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Bool, Float

from esther_jax import mano, safe_norm, safe_normalize
from esther_jax.cameras import StereoRig, apply_transform
from esther_jax.mano import KEYPOINT_PARENTS, PALM_KEYPOINTS
from esther_jax.rotations import axis_angle_left_jacobian, axis_angle_to_matrix, matrix_to_axis_angle, skew
from esther_jax.triangulation import triangulate_rig

from .fusion import Fused
from .priors import huber_vector, huber_vector_with_jacobian
from .solve import gauss_newton, levenberg_marquardt

DEPTH_RANGE_M = (0.1, 1.0)
BONE_TOLERANCE = 0.4
MEDIAN_HALF_WINDOW = 3
"""Wrists from the palm's pose are median-filtered over +-3 frames (outlying keypoints)."""
MIN_PALM_POINTS = 4
"""A palm pose needs at least 4 of the 6 palm keypoints (8 constraints for 6 unknowns)."""
MAX_PALM_RESIDUAL_RAD = 0.05
"""A palm pose whose rms ray angle exceeds this (about 12 px at 241 px focal length) is
not trusted: the keypoints do not look like a palm."""


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
    tri = triangulate_rig(rig, jnp.swapaxes(fused.uv, 1, 2), jnp.swapaxes(fused.conf, 1, 2))
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


def _cube_rotations() -> np.ndarray:
    """The 24 proper rotations of the cube (signed permutation matrices with det +1):
    starting orientations of the palm's pose that are at most 62.8 degrees from any rotation."""
    out = []
    for perm in ((0, 1, 2), (0, 2, 1), (1, 0, 2), (1, 2, 0), (2, 0, 1), (2, 1, 0)):
        for signs in np.ndindex(2, 2, 2):
            R = np.zeros((3, 3))
            R[np.arange(3), perm] = np.where(np.asarray(signs) == 1, -1.0, 1.0)
            if np.linalg.det(R) > 0:
                out.append(R)
    return np.stack(out)


PNP_START_DEPTHS_M = (0.45,)
"""Distances along the palm's mean ray at which the palm pose search starts (with each of
the 24 cube orientations)."""
PNP_STEPS = 12
PNP_HUBER_RAD = 0.01
"""Huber threshold of the palm pose's angular residuals (about 2.5 px at Aria's 241 px
focal length, 6 px at 623 px): an outlying keypoint bends the pose little."""


class PalmPose(eqx.Module):
    """The rigid pose of the palm (wrist, thumb CMC, four MCPs) in one frame."""

    rotation: Float[Array, "3 3"]
    """Hand frame -> rig frame (the MANO global orientation)."""
    wrist: Float[Array, "3"]
    """Wrist position, rig frame, metres."""
    residual_rad: Float[Array, ""]
    """Confidence-weighted root-mean-square angle between the observed rays and the posed
    palm's rays (radians; Huber-transformed, so an outlier counts about linearly)."""
    points: Float[Array, ""]
    """How many palm keypoints at least one view observes."""


def _palm_rays(rig: StereoRig, uv: Float[Array, "2 21 2"], weight: Float[Array, "2 21"]):
    rays, valid = rig.unproject_with_validity(uv)
    palm = np.asarray(PALM_KEYPOINTS)
    rays = rays[:, palm] / jnp.linalg.norm(rays[:, palm], axis=-1, keepdims=True)
    return rays, jnp.where(valid[:, palm], weight[:, palm], 0.0)


class PalmUnknowns(eqx.Module):
    """Unknowns of the palm pose, relative to a start `(R0, t0)`."""

    rotation: Float[Array, "3"]
    """Rotation vector applied to the start's orientation (rig frame)."""
    wrist_cm: Float[Array, "3"]
    """Wrist offset from the start's, centimetres (conditioning)."""

    def pose(self, R0: Float[Array, "3 3"], t0: Float[Array, "3"]) -> tuple[Float[Array, "3 3"], Float[Array, "3"]]:
        return axis_angle_to_matrix(self.rotation) @ R0, t0 + 0.01 * self.wrist_cm


def palm_residuals(y: PalmUnknowns, args) -> tuple[Float[Array, "36"]]:
    """Huber angular residuals of the posed palm in both views (the palm pose's objective)."""
    rig, rays, w, P, R0, t0 = args
    R, t = y.pose(R0, t0)
    X = (P @ R.T) + t[None]
    X_views = rig.to_views(X)  # (2, 6, 3)
    direction = safe_normalize(X_views)
    e = huber_vector(direction - rays, PNP_HUBER_RAD) * jnp.sqrt(w)[..., None]
    return (e.reshape(-1),)


def palm_residuals_and_jacobian(y: PalmUnknowns, args) -> tuple[Float[Array, "36"], Float[Array, "36 6"]]:
    """`palm_residuals` and its Jacobian in (rotation, wrist_cm), in closed form.

    A change `dw` of the rotation vector turns the posed palm about the world axis
    `J_l(w) dw` (`axis_angle_left_jacobian`), moving point Q by `-[Q]x J_l dw`; each view
    rotates that motion into its camera; the unit ray's derivative is the motion's part
    across the ray over the distance; then the Huber scale's derivative."""
    rig, rays, w, P, R0, t0 = args
    R, t = y.pose(R0, t0)
    Q = P @ R.T
    turn = -skew(Q) @ axis_angle_left_jacobian(y.rotation)  # (6, 3, 3)
    X_views = rig.to_views(Q + t[None])  # (2, 6, 3)
    R_views = rig.T_cams_rig[:, :3, :3]
    dX_views = jnp.concatenate([  # (2, 6, 3, 6): turning, then moving the wrist
        jnp.einsum("vab,ibu->viau", R_views, turn), jnp.broadcast_to(0.01 * R_views[:, None], (2, 6, 3, 3))], axis=-1)  # fmt: skip
    n = safe_norm(X_views)[..., None]
    direction = safe_normalize(X_views)
    along = jnp.einsum("via,viau->viu", direction, dX_views)[..., None, :]  # (2, 6, 1, 6)
    d_direction = (dX_views - direction[..., None] * along) / jnp.where(n > 0.0, n, 1.0)[..., None]
    e, d_e = huber_vector_with_jacobian(direction - rays, d_direction, PNP_HUBER_RAD)
    root_w = jnp.sqrt(w)[..., None]
    return (e * root_w).reshape(36), (d_e * root_w[..., None]).reshape(36, 6)


def palm_normal_equations(y: PalmUnknowns, args) -> tuple[Float[Array, "6"], Float[Array, "6 6"]]:
    """The palm objective's Gauss-Newton gradient and matrix from the closed-form Jacobian."""
    return gauss_newton(*palm_residuals_and_jacobian(y, args))


def palm_pose(
    rig: StereoRig, uv: Float[Array, "2 21 2"], weight: Float[Array, "2 21"], rest: Float[Array, "21 3"],
    start_rotation: Float[Array, "3 3"], start_wrist: Float[Array, "3"], has_start: Bool[Array, ""],
    *, search: bool = True,
) -> PalmPose:  # fmt: skip
    """The palm's rigid pose from its keypoints in one or both views (perspective-n-point
    on any camera model, rays from `unproject_with_validity`).

    The palm keypoints move rigidly with the wrist in MANO, so their template (`rest`,
    the hand model at the clip's shape) seen along the observed rays fixes the
    orientation and, through the hand's known size, the distance: in a monocular frame
    this is the metric depth cue; in a stereo frame both views constrain it. The
    objective (Huber on the angle between observed and posed rays, confidence-weighted)
    is solved by Levenberg-Marquardt from 24 cube orientations placed on the palm's mean
    ray (at each of `PNP_START_DEPTHS_M`), plus the given start (the triangulated palm's
    Kabsch fit) where `has_start`; the lowest cost wins, which resolves the two
    mirror-image poses a nearly planar palm admits (the thumb CMC sits off the palm
    plane). Every start is solved to the end: screening them after a few steps and
    finishing only the cheapest (even of distinct orientations) saved a tenth of the
    teacher's time but changed the labels of clips with one view blanked for a while.
    With `search=False` only the given start is refined (a pose already found, e.g.
    with another shape).
    """
    rays, w = _palm_rays(rig, uv, weight)
    P = rest[np.asarray(PALM_KEYPOINTS)] - rest[0][None]
    dtype = rays.dtype
    # the starting ray: the weighted mean palm ray of the view that sees the palm best
    view = jnp.argmax(jnp.sum(w > 0, axis=1))
    mean_ray = jnp.sum(rays[view] * w[view][:, None], axis=0)
    mean_ray = mean_ray / jnp.maximum(jnp.linalg.norm(mean_ray), 1e-9)
    mean_ray = jnp.where(jnp.sum(w[view]) > 0, mean_ray, jnp.asarray([0.0, 0.0, 1.0], dtype))
    R_starts, t_starts = start_rotation[None], start_wrist[None]
    if search:
        cube = jnp.asarray(_cube_rotations(), dtype)
        depths = jnp.asarray(PNP_START_DEPTHS_M, dtype)
        along = apply_transform(rig.T_rig_cams[view], mean_ray[None] * depths[:, None])  # palm centre, rig frame
        t_cube = along[:, None] - jnp.einsum("sij,j->si", cube, jnp.mean(P, axis=0))[None]  # wrist of each start
        R_starts = jnp.concatenate([R_starts, jnp.tile(cube, (len(PNP_START_DEPTHS_M), 1, 1))])
        t_starts = jnp.concatenate([t_starts, t_cube.reshape(-1, 3)])

    def solve_from(R0, t0):
        y0 = PalmUnknowns(jnp.zeros(3, dtype), jnp.zeros(3, dtype))
        y, _, _ = levenberg_marquardt(palm_residuals, y0, (rig, rays, w, P, R0, t0), steps=PNP_STEPS, normal_equations=palm_normal_equations)
        (res,) = palm_residuals(y, (rig, rays, w, P, R0, t0))
        return *y.pose(R0, t0), jnp.sum(res * res)

    R, t, cost = jax.vmap(solve_from)(R_starts, t_starts)
    if search:
        cost = jnp.where(jnp.arange(cost.shape[0]) == 0, jnp.where(has_start, cost, jnp.inf), cost)
    cost = jnp.where(jnp.isfinite(cost), cost, jnp.inf)
    best = jnp.argmin(cost)
    total_w = jnp.maximum(jnp.sum(w), 1e-9)
    rms = jnp.sqrt(jnp.minimum(cost[best], 1e6) / total_w)
    return PalmPose(R[best], t[best], rms, jnp.sum(jnp.any(w > 0, axis=0)).astype(dtype))


def initialise(
    model: mano.ManoModel, rig: StereoRig, evidence: Evidence, betas: Float[Array, "10"], previous: "Initial | None" = None,
    *, triangulated_start: bool = False,
) -> Initial:  # fmt: skip
    """Wrist translation and orientation per frame (see the module docstring).

    `previous` (an initialisation with another shape, e.g. before the shape lock) is
    refined instead of searched again: the palm pose starts from its orientation and
    wrist only; with `triangulated_start` also from the triangulated palm's rigid fit
    where a frame has one, the lower cost winning (a network's prediction as `previous`:
    its palm may sit on the wrong one of the two mirror-image poses a nearly planar palm
    admits, which refining it alone cannot leave)."""
    X = evidence.joints3d
    valid = evidence.joints3d_valid
    dtype = X.dtype
    rest = mano.forward_joints(model, mano.ManoParams(jnp.zeros(3, dtype), jnp.zeros((15, 3), dtype), betas, jnp.zeros(3, dtype)), check_finite=False)
    palm = np.asarray(PALM_KEYPOINTS)
    P = rest[palm] - rest[0][None]
    # the triangulated palm's rigid fit: the pose search's first start
    tri_w = valid[:, palm].astype(dtype)
    tri_seen = jnp.sum(tri_w, axis=1) >= 3
    centre_P = jnp.sum(P[None] * tri_w[..., None], axis=1) / jnp.maximum(jnp.sum(tri_w, axis=1), 1.0)[:, None]
    centre_Q = jnp.sum(X[:, palm] * tri_w[..., None], axis=1) / jnp.maximum(jnp.sum(tri_w, axis=1), 1.0)[:, None]
    R_tri = jax.vmap(kabsch)(P[None] - centre_P[:, None], X[:, palm] - centre_Q[:, None], tri_w)
    wrist_tri = centre_Q - jnp.einsum("tij,tj->ti", R_tri, centre_P)
    if previous is None:
        search = jax.vmap(functools.partial(palm_pose, search=True), in_axes=(None, 0, 0, None, 0, 0, 0))
        pose = search(rig, evidence.uv, evidence.weight, rest, R_tri, wrist_tri, tri_seen)
    else:
        refine = jax.vmap(functools.partial(palm_pose, search=False), in_axes=(None, 0, 0, None, 0, 0, 0))
        R_prev = axis_angle_to_matrix(previous.global_orient)
        pose = refine(rig, evidence.uv, evidence.weight, rest, R_prev, previous.transl, jnp.ones_like(tri_seen))
        if triangulated_start:
            other = refine(rig, evidence.uv, evidence.weight, rest, R_tri, wrist_tri, tri_seen)
            better = tri_seen & (other.residual_rad < pose.residual_rad)
            pose = jax.tree.map(lambda a, b: jnp.where(better.reshape(better.shape + (1,) * (a.ndim - 1)), b, a), pose, other)
    pose_ok = (pose.points >= MIN_PALM_POINTS) & (pose.residual_rad <= MAX_PALM_RESIDUAL_RAD)
    tri_ok = valid[:, 0]
    mono_ok = pose_ok & ~tri_ok
    mono_wrist = _running_median(pose.wrist, mono_ok, MEDIAN_HALF_WINDOW)
    wrist = jnp.where(tri_ok[:, None], X[:, 0], mono_wrist)
    known = tri_ok | mono_ok
    # nothing to start from anywhere: 0.4 m ahead of the cameras' midpoint
    midpoint = 0.5 * rig.T_left_right[:3, 3]
    default = jnp.broadcast_to(midpoint + jnp.asarray([0.0, 0.0, 0.4], dtype), wrist.shape)
    transl = jnp.where(jnp.any(known), _interpolate(wrist, known), default)

    R = pose.rotation[_nearest_known(pose_ok)]
    R = jnp.where(jnp.any(pose_ok), R, _egocentric_default(model.is_right, dtype)[None])
    return Initial(
        transl=transl,
        global_orient=matrix_to_axis_angle(R),
        wrist_triangulated=tri_ok,
        wrist_monocular=mono_ok,
        palm_seen=pose_ok,
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
