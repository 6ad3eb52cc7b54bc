"""The fitting objectives of appendix A as one per-frame residual function, in the form
least-squares solvers take: `frame_residuals(y, (problem, data, track, round))`.

Every robust term is a Huber-transformed residual (`priors.huber_*`), so the sum of
squares equals the paper's Huber loss. Units are chosen for conditioning: pixels for
reprojection, centimetres for the translation unknown (an offset from its anchor).

One function serves every stage, so the solver compiles once (`Round` holds the traced
switches that tell the stages apart):
- shape lock (`Round.free_betas = 1`): lambda_2d Huber 2D in the views that see the
  hand + pose prior + lambda_b |beta - beta_0| + lambda_t |t - t_0| (the soft wrist
  anchor to the triangulated wrist);
- per-frame fits (`free_betas = 0`: the betas are the locked ones): the same terms;
- motion refit (`Round.motion = 1`, with a `Track`): Huber 2D + the Huber depth anchor
  lambda_z rho(t_z - z_tri) along the viewing direction + one-sided Huber on the wrist's
  angular speed above omega_max and linear speed above v_max (to both neighbours) + a
  pull towards the motion prior's smoothed 16-frame-window trajectory.

A monocular frame has reprojection terms in one view and no wrist anchor (it was not
triangulated): its depth comes from the locked hand size, the priors and, in the motion
refit, from its neighbours.
"""

import math

import equinox as eqx
import jax.numpy as jnp
from jaxtyping import Array, Float

from esther_jax import mano
from esther_jax.cameras import StereoRig
from esther_jax.rotations import axis_angle_to_matrix, geodesic_angle

from .priors import MotionPrior, huber_residual, huber_vector


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
    """Unknowns of one frame: orientation, pose, wrist offset (cm) and a shape offset."""

    global_orient: Float[Array, "*batch 3"]
    hand_pose: Float[Array, "*batch 15 3"]
    transl_cm: Float[Array, "*batch 3"]
    """Wrist offset from `FrameData.anchor`, centimetres."""
    betas: Float[Array, "*batch 10"]
    """Shape offset from `Problem.betas`; it acts only while `Round.free_betas` is 1."""


class FrameData(eqx.Module):
    """Observations and anchors of one frame."""

    uv: Float[Array, "*batch 2 21 2"]
    weight: Float[Array, "*batch 2 21"]
    anchor: Float[Array, "*batch 3"]
    """Initial wrist (triangulated, monocular or interpolated), rig frame, metres."""
    anchor_weight: Float[Array, "*batch"]
    """1 where the wrist was triangulated in this frame, less where it was estimated."""
    depth_axis: Float[Array, "*batch 3"]
    """Unit viewing direction from the cameras' midpoint to the anchor (the 'depth' of
    the depth anchor; the camera z on a parallel rig)."""


class Problem(eqx.Module):
    """What every objective needs besides the unknowns (all traced: one compiled solver
    serves every rig of the same camera models, every hand model and every fps)."""

    model: mano.ManoModel
    rig: StereoRig
    pose_prior: mano.PosePrior
    motion_prior: MotionPrior
    weights: FitWeights
    betas: Float[Array, "10"]
    """The locked shape (the shape lock's starting shape beta_0 = 0 before it)."""
    fps: Float[Array, ""]


class Track(eqx.Module):
    """Temporal context of one frame for the motion refit (zero weights before it)."""

    pose_target: Float[Array, "*batch 16 3"]
    """The windowed motion prior's smoothed rotations of this frame (root first)."""
    transl_target: Float[Array, "*batch 3"]
    """The smoothed wrist position (m)."""
    weight: Float[Array, "*batch"]
    """Pull towards the smoothed trajectory (0 outside the motion refit)."""
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


class Round(eqx.Module):
    """The traced switches of one solver round (shared by all frames)."""

    free_betas: Float[Array, ""]
    """1 in the shape lock (betas are unknowns), 0 afterwards."""
    pose_scale: Float[Array, ""]
    """Multiplies lambda_pose (a stiff first phase settles the wrist first)."""
    motion: Float[Array, ""]
    """1 in the motion refit: the depth anchor replaces the wrist anchor."""

    @classmethod
    def make(cls, free_betas: float, pose_scale: float, motion: float, dtype) -> "Round":
        return cls(*(jnp.asarray(x, dtype) for x in (free_betas, pose_scale, motion)))


def frame_params(y: FrameUnknowns, data: FrameData, problem: Problem, round: Round) -> mano.ManoParams:
    """The MANO parameters (rig frame) the unknowns stand for."""
    betas = problem.betas + round.free_betas * y.betas
    return mano.ManoParams(y.global_orient, y.hand_pose, betas, data.anchor + 0.01 * y.transl_cm)


def reprojection(problem: Problem, params: mano.ManoParams, data: FrameData) -> Float[Array, "84"]:
    """lambda_2d * Huber 2D residuals of the 21 joints in both views, weighted by confidence."""
    joints = mano.forward_joints(problem.model, params, check_finite=False, analytic_jvp=True)
    uv = problem.rig.project(joints)  # (2, 21, 2)
    e = huber_vector(uv - data.uv, problem.weights.huber_px) * jnp.sqrt(data.weight)[..., None]
    return problem.weights.lambda_2d * e.reshape(84)


def frame_residuals(y: FrameUnknowns, args: tuple[Problem, FrameData, Track, Round]) -> tuple[Array, ...]:
    """All terms of one frame's objective (see the module docstring)."""
    problem, data, track, round = args
    w = problem.weights
    params = frame_params(y, data, problem, round)
    terms = [
        reprojection(problem, params, data),
        round.pose_scale * w.lambda_pose * problem.pose_prior(y.hand_pose),
        w.lambda_betas * y.betas,
        (1.0 - round.motion) * w.lambda_wrist * data.anchor_weight * y.transl_cm,
    ]
    dz_cm = jnp.dot(params.transl - data.anchor, data.depth_axis) * 100.0
    terms.append(round.motion * w.lambda_depth * data.anchor_weight * huber_residual(dz_cm, w.depth_huber_cm)[None])
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
