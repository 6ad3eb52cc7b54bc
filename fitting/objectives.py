"""Residual functions of the fitting objectives (appendix A), in the form optimistix
least-squares solvers take: `residuals(y, args)` with `y` a Module of unknowns.

Every robust term is a Huber-transformed residual (`priors.huber_*`), so the sum of
squares equals the paper's Huber loss. Units are chosen for conditioning: pixels for
reprojection, centimetres for the translation unknown (offset from its anchor).

- Stage 1 (`stage1_residuals`): lambda_2d Huber 2D in both views + pose prior +
  lambda_b |beta - beta_0| + lambda_t |t - t_0| (the soft wrist anchor to the triangulation).
- Stage 2 (`frame_residuals`): the same with the betas fixed.
- Motion stage (`frame_residuals` with a `Track`): per frame, Huber 2D + Huber depth
  anchor lambda_z rho(t_z - z_tri) + one-sided Huber on the wrist's angular speed
  above omega_max and linear speed above v_max (to both neighbours) + a pull towards
  the motion prior's smoothed 16-frame-window trajectory (`priors.MotionPrior`).
"""

import math

import equinox as eqx
import jax.numpy as jnp
from jaxtyping import Array, Float

from esther_jax import mano
from esther_jax.cameras import StereoRig
from esther_jax.rotations import axis_angle_to_matrix, geodesic_angle

from .priors import MotionPrior, PosePrior, huber_residual, huber_vector


class FitWeights(eqx.Module):
    """Weights and thresholds of the objectives (traced floats: retuning does not recompile)."""

    huber_px: float = 4.0
    """Huber threshold of the 2D terms (pixels)."""
    lambda_2d: float = 1.0
    lambda_pose: float = 1.2
    """Weight of the pose prior (per standardised PCA coefficient)."""
    lambda_betas: float = 1.5
    lambda_wrist: float = 0.3
    """Soft wrist anchor to the triangulated wrist, per centimetre (small: 2D can override)."""
    lambda_depth: float = 0.3
    """Huber depth anchor of the motion stage, per centimetre."""
    depth_huber_cm: float = 1.0
    lambda_angular: float = 3.0
    """One-sided penalty on wrist angular speed above omega_max, per rad/s (heavier than linear)."""
    lambda_linear: float = 1.0
    """One-sided penalty on wrist speed above v_max, per m/s."""
    omega_max: float = math.radians(300.0)
    """Wrist angular speed limit (rad/s) at 30 fps; scales with fps through the frame time."""
    v_max: float = 1.5
    """Wrist speed limit (m/s)."""
    lambda_track: float = 60.0
    """Pull of each frame towards the motion prior's smoothed trajectory (per radian, per cm)."""


class FrameUnknowns(eqx.Module):
    """Unknowns of one frame: orientation, pose, wrist offset in cm (and betas in stage 1)."""

    global_orient: Float[Array, "*batch 3"]
    hand_pose: Float[Array, "*batch 15 3"]
    transl_cm: Float[Array, "*batch 3"]
    betas: Float[Array, "*batch 10"] | None = None


class FrameData(eqx.Module):
    """Observations and anchors of one frame."""

    uv: Float[Array, "*batch 2 21 2"]
    weight: Float[Array, "*batch 2 21"]
    anchor: Float[Array, "*batch 3"]
    """Triangulated (or interpolated) wrist, rig frame, metres."""
    anchor_weight: Float[Array, "*batch"]
    """1 where the wrist was triangulated in this frame, else 0."""


class Problem(eqx.Module):
    """What every objective needs besides the unknowns."""

    model: mano.ManoModel
    rig: StereoRig
    pose_prior: PosePrior
    motion_prior: MotionPrior
    weights: FitWeights
    betas: Float[Array, "10"]
    fps: float


def _reprojection(problem: Problem, params: mano.ManoParams, data: FrameData) -> Float[Array, "84"]:
    joints = mano.forward_joints(problem.model, params, check_finite=False)
    T = problem.rig.T_left_right
    # right camera: X_right = R^T (X_left - t)
    in_right = (joints - T[None, :3, 3]) @ T[:3, :3]
    uv = jnp.stack([problem.rig.left.project(joints), problem.rig.right.project(in_right)])
    e = huber_vector(uv - data.uv, problem.weights.huber_px) * jnp.sqrt(data.weight)[..., None]
    return problem.weights.lambda_2d * e.reshape(84)


def _params(y: FrameUnknowns, data: FrameData, betas) -> mano.ManoParams:
    return mano.ManoParams(y.global_orient, y.hand_pose, betas, data.anchor + 0.01 * y.transl_cm)


def stage1_residuals(y: FrameUnknowns, args: tuple[Problem, FrameData]):
    problem, data = args
    w = problem.weights
    return (
        _reprojection(problem, _params(y, data, y.betas), data),
        w.lambda_pose * problem.pose_prior(y.hand_pose),
        w.lambda_betas * y.betas,
        w.lambda_wrist * data.anchor_weight * y.transl_cm,
    )


class Track(eqx.Module):
    """Temporal context of one frame for the motion stage (zero weights in stage 2)."""

    pose_target: Float[Array, "*batch 16 3"]
    """The windowed motion prior's smoothed rotations of this frame (root first)."""
    transl_target: Float[Array, "*batch 3"]
    """The smoothed wrist position (m)."""
    weight: Float[Array, "*batch"]
    """Pull towards the smoothed trajectory (0 in stage 2)."""
    orient_previous: Float[Array, "*batch 3"]
    orient_next: Float[Array, "*batch 3"]
    transl_previous: Float[Array, "*batch 3"]
    transl_next: Float[Array, "*batch 3"]
    has_previous: Float[Array, "*batch"]
    has_next: Float[Array, "*batch"]

    @classmethod
    def none(cls, frames: int, dtype) -> "Track":
        z = lambda *s: jnp.zeros((frames,) + s, dtype)  # noqa: E731
        return cls(z(16, 3), z(3), z(), z(3), z(3), z(3), z(3), z(), z())


def frame_residuals(y: FrameUnknowns, args: tuple[Problem, FrameData, Track]):
    """Stage 2 and the motion stage's per-frame refit (one compiled function for both).

    Huber 2D + pose prior + soft wrist anchor; with a `Track`: the Huber depth anchor,
    the pull towards the motion prior's smoothed trajectory, and one-sided Huber
    penalties on the wrist's angular speed above omega_max and linear speed above v_max
    to both neighbours (angular weighted above linear)."""
    problem, data, track = args
    w = problem.weights
    params = _params(y, data, problem.betas)
    motion = (track.weight > 0).astype(params.transl.dtype)
    terms = [
        _reprojection(problem, params, data),
        w.lambda_pose * problem.pose_prior(y.hand_pose),
        (1.0 - motion) * w.lambda_wrist * data.anchor_weight * y.transl_cm,
    ]
    dz_cm = (params.transl[2] - data.anchor[2]) * 100.0
    terms.append(motion * w.lambda_depth * data.anchor_weight * huber_residual(dz_cm, w.depth_huber_cm)[None])
    pose = jnp.concatenate([y.global_orient[None], y.hand_pose])
    terms.append(jnp.sqrt(track.weight) * (pose - track.pose_target).reshape(48))
    terms.append(jnp.sqrt(track.weight) * 100.0 * (params.transl - track.transl_target))
    R = axis_angle_to_matrix(y.global_orient)
    for orient, t, present in (
        (track.orient_previous, track.transl_previous, track.has_previous),
        (track.orient_next, track.transl_next, track.has_next),
    ):
        omega = geodesic_angle(R, axis_angle_to_matrix(orient)) * problem.fps
        speed = jnp.sqrt(jnp.sum((params.transl - t) ** 2) + 1e-12) * problem.fps
        terms.append(present * w.lambda_angular * huber_residual(jnp.maximum(omega - w.omega_max, 0.0), 1.0)[None])
        terms.append(present * w.lambda_linear * huber_residual(jnp.maximum(speed - w.v_max, 0.0), 0.1)[None])
    return tuple(terms)
