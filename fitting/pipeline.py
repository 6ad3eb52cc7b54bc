"""The teacher pipeline for one hand of one clip (paper section 3.1, appendix A).

fuse -> stereo prefilter -> initialise -> stage 1 shape lock (64 most confident frames,
joint fit, betas averaged) -> stage 2 per-frame pose + wrist (betas fixed) -> motion
stage: the motion prior smooths 16-frame windows (stride 8, blended with triangular
weights so overlaps have no seams), then every frame is refitted (optimistix LM) to its
2D evidence with the depth anchor, the velocity limits and a pull towards the smoothed
trajectory; twice -> reprojection filter -> labels + quality.

Every stage is jitted once per clip-length bucket (frames are padded to a multiple of
32 with unobserved frames), so labelling many clips compiles a handful of times.
"""

import dataclasses
import time

import jax
import jax.numpy as jnp
import numpy as np

from esther_jax import mano
from esther_jax.cameras import StereoRig
from esther_jax.rotations import axis_angle_to_matrix, matrix_to_axis_angle, matrix_to_rotation_6d, rotation_6d_to_matrix

from . import fusion, initialise, objectives, quality, solve
from .objectives import FitWeights, FrameData, FrameUnknowns, Problem
from .priors import MotionPrior, PosePrior

BUCKET = 32


@dataclasses.dataclass(frozen=True)
class LabelConfig:
    weights: FitWeights = FitWeights()
    stage1_frames: int = 64
    stage1_steps: int = 15
    stage2_steps: int = 6
    """Steps of each stage-2 phase and of the motion refit (one compiled solve serves all)."""
    orient_first_pose_weight: float = 25.0
    """Stage 2 first solves with the pose prior this many times stiffer (in effect wrist
    orientation and position first, as EasyMocap stages its fits), then with the normal
    weights: from the same starts this reaches lower objectives than scipy's TRF."""
    window: int = 16
    stride: int = 8
    motion_sweeps: int = 1
    reject_px: float = quality.REJECT_PX
    min_joints_per_view: int = 4
    """A view 'observes' the hand in a frame with at least this many fused joints."""


def _pad(x: np.ndarray, length: int) -> np.ndarray:
    pad = [(0, length - x.shape[0])] + [(0, 0)] * (x.ndim - 1)
    return np.pad(x, pad)


def _frame_data(evidence, init, frames) -> FrameData:
    return FrameData(
        uv=evidence.uv[frames],
        weight=evidence.weight[frames],
        anchor=init.transl[frames],
        anchor_weight=init.wrist_triangulated[frames].astype(evidence.weight.dtype),
    )


def _solve(residuals, problem, y0, per_item, steps):
    return _jitted_solve(residuals, steps)(problem, y0, per_item)


_SOLVE_CACHE: dict = {}


def _jitted_solve(residuals, steps):
    key = (residuals, steps)
    if key not in _SOLVE_CACHE:
        _SOLVE_CACHE[key] = jax.jit(lambda problem, y0, per_item: solve.solve_batch(residuals, y0, problem, per_item, max_steps=steps))
    return _SOLVE_CACHE[key]


@jax.jit
def _fuse_and_filter(rig, uv, conf, box, box_score, bones):
    fused = fusion.fuse(uv, conf, box, box_score)
    return fused, initialise.prefilter(rig, fused, bones)


@jax.jit
def _project_both(rig: StereoRig, joints):
    T = rig.T_left_right
    in_right = (joints - T[None, None, :3, 3]) @ T[:3, :3]
    return jnp.stack([rig.left.project(joints), rig.right.project(in_right)], axis=1)


@jax.jit
def _forward_all(model, params):
    return jax.vmap(lambda p: mano.forward_joints(model, p))(params)


def label_hand(
    model: mano.ManoModel, rig: StereoRig, keypoints: dict, fps: float, config: LabelConfig = LabelConfig(),
    monocular: dict | None = None,
) -> tuple[dict, dict]:  # fmt: skip
    """Label one hand of one clip.

    Args:
        model: the hand model of this side (`load_builtin(side)` or the user's MANO).
        rig: the clip's stereo rig.
        keypoints: the keypoints.npz arrays (uv [D,T,2,21,2], conf, box, box_score).
        fps: frame rate (the velocity limits are per second).
        monocular: optional per-view monocular MANO estimates (monocular.npz arrays);
            where present they initialise the wrist orientation and the pose.
    Returns:
        (labels, quality): the labels.npz arrays and the quality.json content.
    """
    timings = {}
    t0 = time.perf_counter()
    T = keypoints["uv"].shape[1]
    length = max(BUCKET, -(-T // BUCKET) * BUCKET)
    dtype = jnp.result_type(float)
    padded = {k: jnp.asarray(_pad(np.moveaxis(np.asarray(v), 1, 0), length).swapaxes(0, 1), dtype) for k, v in keypoints.items()}
    bones = initialise.template_bones(model)
    fused, evidence = _fuse_and_filter(rig, padded["uv"], padded["conf"], padded["box"], padded["box_score"], bones)
    timings["fuse_filter_s"] = time.perf_counter() - t0
    weight = np.asarray(evidence.weight)
    per_view = (weight > 0).sum(axis=2)  # (L, 2)
    observed = per_view.max(axis=1) >= config.min_joints_per_view
    stereo = per_view.min(axis=1) >= config.min_joints_per_view
    observed[T:] = False
    stereo[T:] = False
    notes = []
    if int(fused.num_invalid):
        notes.append(f"{int(fused.num_invalid)} detections had NaN or infinite values and were treated as missing")
    if not stereo.any():
        labels = _empty_labels(T, model)
        notes.append("the hand is never detected in both views: no metric label (all frames invalid)")
        return labels, {"notes": notes, "share_passing": 0.0, "hand_frames": T}

    t1 = time.perf_counter()
    init = initialise.initialise(model, evidence, jnp.zeros(model.num_betas, dtype))
    mono_pose = None
    if monocular is not None:
        orient, mono_pose_T, has = initialise.monocular_average(rig, monocular)
        has = np.concatenate([has, np.zeros(length - T, bool)])
        orient = np.concatenate([orient, np.zeros((length - T, 3))])
        mono_pose = np.concatenate([mono_pose_T, np.zeros((length - T, 15, 3))])
        mono_pose = np.where(has[:, None, None], mono_pose, np.asarray(model.hands_mean).reshape(15, 3))
        init = initialise.Initial(
            transl=init.transl,
            global_orient=jnp.where(jnp.asarray(has)[:, None], jnp.asarray(orient, dtype), init.global_orient),
            wrist_triangulated=init.wrist_triangulated,
            palm_seen=init.palm_seen,
        )
        notes.append(f"initialised from monocular estimates in {int(has.sum())} frames")
    problem = Problem(
        model=model,
        rig=rig,
        pose_prior=PosePrior.from_model(model),
        motion_prior=MotionPrior(),
        weights=config.weights,
        betas=jnp.zeros(model.num_betas, dtype),
        fps=float(fps),
    )
    # stage 1: shape lock on the most confident stereo frames
    score = np.where(stereo, weight.sum(axis=(1, 2)), -1.0)
    chosen = np.argsort(-score, kind="stable")[: config.stage1_frames]
    chosen = np.sort(chosen)
    used = stereo[chosen]
    start_pose = np.broadcast_to(np.asarray(model.hands_mean).reshape(15, 3), (length, 15, 3)) if mono_pose is None else mono_pose
    mean_pose = jnp.asarray(start_pose[chosen], dtype)
    y0 = FrameUnknowns(init.global_orient[chosen], mean_pose, jnp.zeros((len(chosen), 3), dtype), jnp.zeros((len(chosen), model.num_betas), dtype))
    s1 = _solve(objectives.stage1_residuals, problem, y0, (_frame_data(evidence, init, chosen),), config.stage1_steps)
    w = used.astype(np.float64) * score[chosen].clip(0)
    betas = jnp.asarray((np.asarray(s1.value.betas) * w[:, None]).sum(0) / max(w.sum(), 1e-9), dtype)
    timings["stage1_s"] = time.perf_counter() - t1

    # stage 2: per-frame pose and wrist with the betas locked
    t2 = time.perf_counter()
    orient_start = init.global_orient
    init = initialise.initialise(model, evidence, betas)
    if mono_pose is not None:
        init = initialise.Initial(init.transl, orient_start, init.wrist_triangulated, init.palm_seen)
    problem = Problem(
        model=model, rig=rig, pose_prior=PosePrior.from_model(model, betas), motion_prior=MotionPrior(),
        weights=config.weights, betas=betas, fps=float(fps),
    )  # fmt: skip
    frames = np.arange(length)
    pose0 = np.array(start_pose, copy=True)
    pose0[chosen] = np.asarray(s1.value.hand_pose)
    orient0 = np.asarray(init.global_orient).copy()
    orient0[chosen] = np.asarray(s1.value.global_orient)
    y0 = FrameUnknowns(jnp.asarray(orient0, dtype), jnp.asarray(pose0, dtype), jnp.zeros((length, 3), dtype))
    data = _frame_data(evidence, init, frames)
    s2 = solve_frames_staged(problem, y0, data, config)
    timings["stage2_s"] = time.perf_counter() - t2

    # motion stage: the motion prior smooths 16-frame windows (stride 8, blended), then
    # every frame is refitted to its 2D evidence pulled towards the smoothed trajectory
    t3 = time.perf_counter()
    estimate = s2.value
    converged = np.asarray(s2.converged)
    coverage = (weight > 0).sum(axis=(1, 2)) / 42.0
    confidence = jnp.asarray(np.where(observed, 0.25 + coverage, 0.0), dtype)
    starts = _window_starts(T, config.window, config.stride)
    for _ in range(config.motion_sweeps):
        track = _smoothed_track(problem, init, estimate, confidence, starts, config, observed)
        s3 = _solve(objectives.frame_residuals, problem, estimate, (data, track), config.stage2_steps)
        estimate = s3.value
        converged = converged & np.asarray(s3.converged)
    if config.motion_sweeps:  # the labels are the motion prior's final smoothed trajectory
        track = _smoothed_track(problem, init, estimate, confidence, starts, config, observed)
        estimate = FrameUnknowns(
            track.pose_target[:, 0], track.pose_target[:, 1:], 100.0 * (track.transl_target - init.transl)
        )
    timings["motion_s"] = time.perf_counter() - t3

    # labels and quality
    t4 = time.perf_counter()
    transl = init.transl + 0.01 * estimate.transl_cm
    params = mano.ManoParams(
        estimate.global_orient, estimate.hand_pose, jnp.broadcast_to(betas, (length, model.num_betas)), transl
    )
    joints = _forward_all(model, params)
    uv_label = np.asarray(_project_both(rig, joints))
    residual = quality.reprojection_residual(uv_label, np.asarray(fused.uv), np.asarray(fused.conf))
    finite = np.all(np.isfinite(np.asarray(joints)), axis=(1, 2))
    passing = stereo & finite & (residual <= config.reject_px)
    sl = slice(0, T)
    labels = {
        "global_orient": np.asarray(estimate.global_orient)[sl],
        "hand_pose": np.asarray(estimate.hand_pose)[sl],
        "betas": np.asarray(betas),
        "transl": np.asarray(transl)[sl],
        "joints": np.asarray(joints)[sl],
        "onscreen": observed[sl],
        "valid": passing[sl],
        "residual_px": residual[sl].astype(np.float32),  # NaN where the hand is not observed
        "stereo": stereo[sl],
        "converged": converged[sl],
    }
    report = quality.quality_table(residual[sl], np.asarray(transl)[sl, 2], passing[sl], rig)
    mono = observed[sl] & ~stereo[sl]
    if mono.any():
        notes.append(f"{int(mono.sum())} frames see the hand in one view only: labelled, flagged (stereo = False, valid = False)")
    timings["labels_s"] = time.perf_counter() - t4
    report.update(
        notes=notes,
        hand_frames=T,
        stereo_frames=int(stereo[sl].sum()),
        converged_share=float(converged[sl][stereo[sl]].mean()) if stereo[sl].any() else 0.0,
        rejected_joints_depth=int(evidence.rejected_depth),
        rejected_joints_bones=int(evidence.rejected_bones),
        stage1_frames=int(used.sum()),
        betas=np.asarray(betas).tolist(),
        timings=timings,
        solver_steps={"stage1_median": float(np.median(np.asarray(s1.num_steps))), "stage2_median": float(np.median(np.asarray(s2.num_steps)))},
    )
    return labels, report


def solve_frames_staged(problem: Problem, y0: FrameUnknowns, data: FrameData, config: LabelConfig) -> "solve.Solution":
    """Per-frame fits in two phases of the same compiled solve: a stiff pose prior first
    (the wrist's orientation and position settle), then the normal weights."""
    frames = y0.global_orient.shape[0]
    track = objectives.Track.none(frames, y0.global_orient.dtype)
    stiff = dataclasses.replace(problem, weights=dataclasses.replace(problem.weights, lambda_pose=problem.weights.lambda_pose * config.orient_first_pose_weight))
    first = _solve(objectives.frame_residuals, stiff, y0, (data, track), config.stage2_steps)
    second = _solve(objectives.frame_residuals, problem, first.value, (data, track), config.stage2_steps)
    return solve.Solution(second.value, second.converged, first.num_steps + second.num_steps)


def _window_starts(T: int, window: int, stride: int) -> np.ndarray:
    if T <= window:
        return np.zeros(1, int)
    starts = list(range(0, T - window + 1, stride))
    if starts[-1] + window < T:
        starts.append(T - window)
    return np.asarray(starts)


def _trajectory(init, estimate) -> jax.Array:
    """(L, 57) features the motion prior smooths: wrist rotation as 6D, the 15 joints'
    rotation vectors, the wrist in centimetres."""
    R = axis_angle_to_matrix(estimate.global_orient)
    transl_cm = 100.0 * init.transl + estimate.transl_cm
    return jnp.concatenate([matrix_to_rotation_6d(R), estimate.hand_pose.reshape(-1, 45), transl_cm], axis=1)


@jax.jit
def _smooth_windows(prior, features, confidence, idx, blend_weights):
    windows = jax.vmap(prior.smooth)(features[idx], confidence[idx])  # (n, W, 57)
    flat = idx.reshape(-1)
    summed = jnp.zeros_like(features).at[flat].add(windows.reshape(-1, features.shape[1]) * blend_weights[:, None])
    return summed


def _smoothed_track(problem, init, estimate, confidence, starts, config, observed) -> objectives.Track:
    """Run the motion prior over every window in parallel, blend overlaps with triangular
    weights (no seams), and package targets and neighbours for the refit."""
    length = estimate.global_orient.shape[0]
    W = min(config.window, length)
    idx = (starts[:, None] + np.arange(W)[None]).clip(0, length - 1)
    ramp = np.minimum(np.arange(W) + 1, W - np.arange(W)).astype(np.float64)
    total = np.zeros(length)
    np.add.at(total, idx.reshape(-1), np.tile(ramp, len(starts)))
    blend = np.tile(ramp, len(starts)) / np.maximum(total[idx.reshape(-1)], 1e-9)
    dtype = confidence.dtype
    features = _trajectory(init, estimate)
    smooth = _smooth_windows(problem.motion_prior, features, confidence, jnp.asarray(idx), jnp.asarray(blend, dtype))
    covered = jnp.asarray(total > 0)[:, None]
    smooth = jnp.where(covered, smooth, features)
    R = rotation_6d_to_matrix(smooth[:, :6])
    orient = matrix_to_axis_angle(R)
    pose = jnp.concatenate([orient[:, None], smooth[:, 6:51].reshape(-1, 15, 3)], axis=1)
    transl = smooth[:, 51:54] / 100.0
    prev = np.maximum(np.arange(length) - 1, 0)
    nxt = np.minimum(np.arange(length) + 1, length - 1)
    valid = jnp.asarray(observed, dtype)
    return objectives.Track(
        pose_target=pose,
        transl_target=transl,
        weight=problem.weights.lambda_track * valid,
        orient_previous=orient[prev],
        orient_next=orient[nxt],
        transl_previous=transl[prev],
        transl_next=transl[nxt],
        has_previous=jnp.asarray((np.arange(length) > 0) & observed[prev], dtype) * valid,
        has_next=jnp.asarray((np.arange(length) < length - 1) & observed[nxt], dtype) * valid,
    )


def _empty_labels(T: int, model: mano.ManoModel) -> dict:
    z = np.zeros
    return {
        "global_orient": z((T, 3), np.float32), "hand_pose": z((T, 15, 3), np.float32), "betas": z(model.num_betas, np.float32),
        "transl": z((T, 3), np.float32), "joints": z((T, 21, 3), np.float32), "onscreen": z(T, bool), "valid": z(T, bool),
        "residual_px": np.full(T, np.nan, np.float32), "stereo": z(T, bool), "converged": z(T, bool),
    }  # fmt: skip
