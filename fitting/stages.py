"""The teacher's optimisation stages (paper section 3.1, appendix A) as typed functions.

    shape_lock   -> the 64 most confident frames fix one shape per hand
    fit_frames   -> per-frame pose and wrist with the shape locked (stiff, then normal)
    refine_motion-> 16-frame sliding windows (stride 8) of the motion prior, blended
                    with triangular weights, then a per-frame refit with the depth
                    anchor, the velocity limits and a pull towards the smoothed
                    trajectory; the labels are the final smoothed trajectory

Every solve is a *round* of the one per-frame objective (`objectives.frame_residuals`)
over all frames of the clip, differing only in traced switches (`objectives.Round`), so
the solver compiles once for all stages (`solve_round` is jitted on its own; the stages
around it are small jitted steps). Frames are independent in every round, so the shape
lock's result depends only on its chosen frames; the other frames' solutions are warm
starts for `fit_frames`.
"""

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Bool, Float

from esther_jax import mano
from esther_jax.compilation import CPU_LIGHT_OPTIMISATION, CPU_QUICK_COMPILE, persistent_jit
from esther_jax.rotations import axis_angle_to_matrix, matrix_to_axis_angle, matrix_to_rotation_6d, rotation_6d_to_matrix

from . import solve
from .evidence import Evidence, Initial
from .objectives import FLAT_BETAS, FrameData, FrameUnknowns, Problem, Round, Track, frame_normal_equations, frame_residuals


class Fits(eqx.Module):
    """Per-frame fits of one hand (what every stage returns)."""

    global_orient: Float[Array, "frames 3"]
    hand_pose: Float[Array, "frames 15 3"]
    transl: Float[Array, "frames 3"]
    """Wrist, rig frame, metres."""
    betas: Float[Array, "frames 10"]
    converged: Bool[Array, "frames"]

    def params(self) -> mano.ManoParams:
        """Batched `ManoParams` (vmap `mano.forward` over them)."""
        return mano.ManoParams(self.global_orient, self.hand_pose, self.betas, self.transl)


class ShapeLock(eqx.Module):
    betas: Float[Array, "10"]
    """The locked shape: the chosen frames' shapes pooled by their information (`pooled_betas`)."""
    chosen: Bool[Array, "frames"]
    """The frames that set it (the most confident stereo frames; without any, the
    monocular frames whose fits warm-start `fit_frames`, the shape staying the mean)."""
    from_monocular: Bool[Array, ""]
    """True when no frame was stereo: the shape rests on monocular evidence and the prior."""
    fits: Fits
    """Every frame's solution of the shape-lock rounds (warm starts for `fit_frames`)."""


def frame_data(evidence: Evidence, initial: Initial, problem: Problem, untriangulated_anchor: float = 0.3) -> FrameData:
    """The per-frame observations and anchors of the objectives: a triangulated wrist
    anchors with weight 1, an estimated one (monocular size, interpolation) with
    `untriangulated_anchor`, so that a frame with thin 2D evidence cannot run away along
    its rays while a well-observed monocular frame's 2D overrides its start."""
    midpoint = 0.5 * problem.rig.T_left_right[:3, 3]
    axis = initial.transl - midpoint[None]
    axis = axis / jnp.maximum(jnp.linalg.norm(axis, axis=-1, keepdims=True), 1e-6)
    return FrameData(
        uv=evidence.uv,
        weight=evidence.weight,
        anchor=initial.transl,
        anchor_weight=jnp.where(initial.wrist_triangulated, 1.0, untriangulated_anchor).astype(evidence.weight.dtype),
        depth_axis=axis,
    )


def solve_round(
    problem: Problem, y0: FrameUnknowns, data: FrameData, track: Track, round: Round, *, steps: int, solver: str
) -> solve.Solution:
    """One round of `steps` per-frame solver steps (vmapped over frames), compiled once
    per shape: with "lm" the step count is traced, so the stages' different counts share
    one program; optimistix's solvers compile once per count (their maximum)."""
    if solver == "lm":
        return _solve_round(problem, y0, data, track, round, jnp.asarray(steps, jnp.int32), solver=solver, max_steps=None)
    return _solve_round(problem, y0, data, track, round, None, solver=solver, max_steps=steps)


@persistent_jit(static_argnames=("solver", "max_steps"), compiler_options=CPU_LIGHT_OPTIMISATION)
def _solve_round(problem, y0, data, track, round, steps, *, solver: str, max_steps: int | None) -> solve.Solution:
    steps = steps if max_steps is None else max_steps
    return solve.solve_batch(frame_residuals, y0, (problem, round), (data, track), steps=steps, solver=solver, normal_equations=frame_normal_equations)


def _unknowns(fits: Fits, data: FrameData, betas0: Float[Array, "10"]) -> FrameUnknowns:
    return FrameUnknowns(fits.global_orient, fits.hand_pose, 100.0 * (fits.transl - data.anchor), fits.betas - betas0[None])


@persistent_jit(compiler_options=CPU_QUICK_COMPILE)
def _to_fits(y: FrameUnknowns, data: FrameData, betas: Float[Array, "10"], free: Float[Array, ""], converged) -> Fits:
    T = y.global_orient.shape[0]
    return Fits(y.global_orient, y.hand_pose, data.anchor + 0.01 * y.transl_cm, jnp.broadcast_to(betas, (T, 10)) + free * y.betas, converged)


def start_fits(initial: Initial, pose: Float[Array, "frames 15 3"], betas: Float[Array, "10"]) -> Fits:
    """Fits at the initialisation (the stages' starting point)."""
    T = initial.transl.shape[0]
    return Fits(initial.global_orient, pose, initial.transl, jnp.broadcast_to(betas, (T, 10)), jnp.zeros(T, bool))


def _rounds(problem, fits, data, track, rounds, steps, solver) -> Fits:
    y = _unknowns(fits, data, problem.betas)
    converged = jnp.ones(fits.converged.shape, bool)
    for r in rounds:
        sol = solve_round(problem, y, data, track, r, steps=steps, solver=solver)
        y, converged = sol.value, sol.converged
    return _to_fits(y, data, problem.betas, rounds[-1].free_betas, converged)


@persistent_jit(static_argnames=("frames",), compiler_options=CPU_QUICK_COMPILE)
def _choose(weight: Float[Array, "T 2 21"], stereo: Bool[Array, "T"], observed: Bool[Array, "T"], frames: int):
    # the hand's size is seen through the joints both views observe (triangulation fixes
    # their depth); a monocular frame's shape only through its proportions
    both = jnp.sum(jnp.min(weight, axis=1), axis=1)
    score = jnp.where(jnp.any(stereo), both, jnp.sum(weight, axis=(1, 2)))
    pool = jnp.where(jnp.any(stereo), stereo, observed)
    ranked = jnp.where(pool, score, -1.0)
    k = min(frames, score.shape[0])
    _, idx = jax.lax.top_k(ranked, k)
    chosen = jnp.zeros(score.shape, bool).at[idx].set(True) & pool
    return chosen, ~jnp.any(stereo)


@persistent_jit(compiler_options=CPU_QUICK_COMPILE)
def pooled_betas(problem: Problem, y: FrameUnknowns, data: FrameData, track: Track, round: Round, chosen: Bool[Array, "frames"]) -> Float[Array, "10"]:
    """One shape from the chosen frames' shape-lock solutions, each weighted by the
    information its data carry about the shape.

    Frame f's solution beta_f minimises its objective with the shape prior
    lambda_b |beta - beta_0|^2 counted in every frame; its Gauss-Newton information about
    the shape is the Schur complement S_f of its Hessian (pose and wrist eliminated),
    S_f = D_f + lambda_b^2 I with D_f the data's share. The shape that minimises the
    frames' linearised objectives together, with the prior counted once, is

        beta = beta_0 + (sum_f D_f + lambda_b^2 I)^-1 sum_f S_f (beta_f - beta_0),

    so a frame whose 2D evidence fixes the size (both views see many joints) counts
    fully, one that leaves the size free (a monocular frame: size and depth trade off)
    adds almost nothing, and the per-frame shrinkage towards beta_0 is undone. A frame
    whose solve stopped short of its minimum adds its remaining (Schur-reduced) gradient
    g_f to the right-hand side: one Gauss-Newton step of the joint problem."""
    lam2 = problem.weights.lambda_betas**2

    def information(y1: FrameUnknowns, d1: FrameData, t1: Track):
        g, H = frame_normal_equations(y1, (problem, d1, t1, round))
        k = int(FLAT_BETAS[0])  # the betas are the last unknowns
        H_oo = H[:k, :k] + 1e-6 * (jnp.trace(H[:k, :k]) / k + 1.0) * jnp.eye(k, dtype=H.dtype)
        eliminate = jnp.linalg.solve(H_oo, jnp.concatenate([H[:k, k:], g[:k, None]], axis=1))
        S = H[k:, k:] - H[k:, :k] @ eliminate[:, :10]
        g_shape = g[k:] - H[k:, :k] @ eliminate[:, 10]
        return S, g_shape

    S, g = jax.vmap(information)(y, data, track)  # (T, 10, 10), (T, 10)
    S = jnp.where(chosen[:, None, None], S, 0.0)
    g = jnp.where(chosen[:, None], g, 0.0)
    eye = jnp.eye(10, dtype=S.dtype)
    n = jnp.sum(chosen).astype(S.dtype)
    A = jnp.sum(S, axis=0) - jnp.maximum(n - 1.0, 0.0) * lam2 * eye
    b = jnp.einsum("tij,tj->i", S, y.betas) - jnp.sum(g, axis=0)
    return problem.betas + jnp.linalg.solve(A, b)


def shape_lock(
    problem: Problem, data: FrameData, start: Fits, stereo: Bool[Array, "frames"], observed: Bool[Array, "frames"],
    *, frames: int = 64, rounds: int = 1, steps: int = 16, solver: str = "lm",
) -> ShapeLock:  # fmt: skip
    """Stage 1: shape, pose and wrist jointly on the `frames` most confident stereo frames
    (most joints seen by both views), the per-frame shapes pooled by their information
    into one locked shape (`pooled_betas`). A clip without a stereo frame keeps the mean
    shape `problem.betas` (beta_0): one view cannot separate size from distance."""
    dtype = data.uv.dtype
    chosen, from_mono = _choose(data.weight, stereo, observed, frames)
    track = Track.none(data.uv.shape[0], dtype)
    free = Round.make(1.0, 1.0, 0.0, dtype)
    fits = _rounds(problem, start, data, track, [free] * rounds, steps, solver)
    betas = pooled_betas(problem, _unknowns(fits, data, problem.betas), data, track, free, chosen)
    # one view alone cannot tell a large hand far away from a small one nearby: without a
    # stereo frame the size is the shape prior's mean (the least-risk guess)
    betas = jnp.where(from_mono, problem.betas, betas)
    return ShapeLock(betas, chosen, from_mono, fits)


def fit_frames(
    problem: Problem, data: FrameData, start: Fits, *, stiff_pose: float = 25.0, steps: int = 5, solver: str = "lm"
) -> Fits:
    """Stage 2: every frame's pose and wrist with the locked shape `problem.betas`, in
    two rounds: the pose prior `stiff_pose` times stiffer first (the wrist's orientation
    and position settle, as EasyMocap stages its fits), then the normal weights."""
    dtype = data.uv.dtype
    track = Track.none(data.uv.shape[0], dtype)
    rounds = [Round.make(0.0, stiff_pose, 0.0, dtype), Round.make(0.0, 1.0, 0.0, dtype)]
    start = Fits(start.global_orient, start.hand_pose, start.transl, jnp.broadcast_to(problem.betas, start.betas.shape), start.converged)
    return _rounds(problem, start, data, track, rounds, steps, solver)


def window_starts(length: int, window: int = 16, stride: int = 8) -> np.ndarray:
    """First frame of each sliding window covering `length` frames (static)."""
    if length <= window:
        return np.zeros(1, int)
    starts = list(range(0, length - window + 1, stride))
    if starts[-1] + window < length:
        starts.append(length - window)
    return np.asarray(starts)


def _trajectory(fits: Fits) -> Float[Array, "T 54"]:
    """Features the motion prior smooths: wrist rotation as 6D, the 15 joints' rotation
    vectors, the wrist in centimetres."""
    R = axis_angle_to_matrix(fits.global_orient)
    return jnp.concatenate([matrix_to_rotation_6d(R), fits.hand_pose.reshape(-1, 45), 100.0 * fits.transl], axis=1)


@persistent_jit(static_argnames=("window", "stride"), compiler_options=CPU_QUICK_COMPILE)
def smooth_track(problem: Problem, fits: Fits, confidence: Float[Array, "T"], observed: Bool[Array, "T"], *, window: int = 16, stride: int = 8) -> Track:
    """The motion prior over every sliding window in parallel, overlaps blended with
    triangular weights (no seams), packaged as targets and neighbours for the refit."""
    length = fits.transl.shape[0]
    W = min(window, length)
    starts = window_starts(length, W, stride)
    idx = (starts[:, None] + np.arange(W)[None]).clip(0, length - 1)
    ramp = np.minimum(np.arange(W) + 1, W - np.arange(W)).astype(np.float64)
    total = np.zeros(length)
    np.add.at(total, idx.reshape(-1), np.tile(ramp, len(starts)))
    dtype = confidence.dtype
    blend = jnp.asarray(np.tile(ramp, len(starts)) / np.maximum(total[idx.reshape(-1)], 1e-9), dtype)
    features = _trajectory(fits)
    windows = jax.vmap(problem.motion_prior.smooth)(features[idx], confidence[idx])  # (n, W, 54)
    smooth = jnp.zeros_like(features).at[idx.reshape(-1)].add(windows.reshape(-1, features.shape[1]) * blend[:, None])
    smooth = jnp.where(jnp.asarray(total > 0)[:, None], smooth, features)
    orient = matrix_to_axis_angle(rotation_6d_to_matrix(smooth[:, :6]))
    pose = jnp.concatenate([orient[:, None], smooth[:, 6:51].reshape(-1, 15, 3)], axis=1)
    transl = smooth[:, 51:54] / 100.0
    prev = np.maximum(np.arange(length) - 1, 0)
    nxt = np.minimum(np.arange(length) + 1, length - 1)
    valid = observed.astype(dtype)
    return Track(
        pose_target=pose,
        transl_target=transl,
        weight=problem.weights.lambda_track * valid,
        orient_previous=orient[prev],
        orient_next=orient[nxt],
        transl_previous=transl[prev],
        transl_next=transl[nxt],
        has_previous=(jnp.asarray(np.arange(length) > 0) & observed[prev]).astype(dtype) * valid,
        has_next=(jnp.asarray(np.arange(length) < length - 1) & observed[nxt]).astype(dtype) * valid,
    )


@persistent_jit(compiler_options=CPU_QUICK_COMPILE)
def _track_fits(track: Track, fits: Fits) -> Fits:
    return Fits(track.pose_target[:, 0], track.pose_target[:, 1:], track.transl_target, fits.betas, fits.converged)


def motion_confidence(data: FrameData, observed: Bool[Array, "frames"]) -> Float[Array, "frames"]:
    """Per-frame confidence of the motion prior's data term: 0.25 + the share of the 42
    (view, joint) observations present, 0 when unobserved (thin evidence is smoothed more)."""
    coverage = jnp.sum(data.weight > 0, axis=(1, 2)).astype(data.weight.dtype) / 42.0
    return jnp.where(observed, 0.25 + coverage, 0.0)


def refine_motion(
    problem: Problem, data: FrameData, fits: Fits, observed: Bool[Array, "frames"],
    *, sweeps: int = 1, window: int = 16, stride: int = 8, steps: int = 5, solver: str = "lm",
) -> Fits:  # fmt: skip
    """Sliding-window motion optimisation: `sweeps` times (smooth the trajectory with the
    motion prior over 16-frame windows, refit every frame to its 2D evidence with the
    depth anchor, the velocity limits and the pull to the smoothed trajectory), then the
    final smoothed trajectory is the result."""
    confidence = motion_confidence(data, observed)
    motion = Round.make(0.0, 1.0, 1.0, data.uv.dtype)
    converged = fits.converged
    for _ in range(sweeps):
        track = smooth_track(problem, fits, confidence, observed, window=window, stride=stride)
        fits = _rounds(problem, fits, data, track, [motion], steps, solver)
        converged = converged & fits.converged
    track = smooth_track(problem, fits, confidence, observed, window=window, stride=stride)
    out = _track_fits(track, fits)
    return Fits(out.global_orient, out.hand_pose, out.transl, out.betas, converged)
