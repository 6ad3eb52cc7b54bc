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

The solver does not differentiate `frame_residuals` as a whole: `frame_normal_equations`
gives it J^T r and J^T J from the terms' structure (the reprojection's Jacobian in closed
form, the pose prior's in its own unknowns, the per-unknown priors as diagonals), equal
to those of the full Jacobian at a fifth of the cost.
"""

import math

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jax.flatten_util import ravel_pytree
from jaxtyping import Array, Float

from esther_jax import mano
from esther_jax.cameras import StereoRig
from esther_jax.rotations import axis_angle_to_matrix, geodesic_angle

from .priors import MotionPrior, huber_residual, huber_vector, huber_vector_with_jacobian
from .solve import gauss_newton


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


FLAT_ORIENT, FLAT_POSE, FLAT_TRANSL, FLAT_BETAS = np.r_[0:3], np.r_[3:48], np.r_[48:51], np.r_[51:61]
"""Where each field of one frame's `FrameUnknowns` sits in `ravel_pytree`'s flat vector
(the fields' order): the layout of `frame_normal_equations` and of the solver's steps."""


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
    serves every rig of the same camera models and image sizes, every hand model and every
    fps)."""

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
    joints = mano.forward_joints(problem.model, params, check_finite=False)
    uv = problem.rig.project(joints)  # (2, 21, 2)
    e = huber_vector(uv - data.uv, problem.weights.huber_px) * jnp.sqrt(data.weight)[..., None]
    return problem.weights.lambda_2d * e.reshape(84)


def reprojection_with_jacobian(y: FrameUnknowns, args: tuple[Problem, FrameData, Track, Round]) -> tuple[Float[Array, "84"], Float[Array, "84 61"]]:
    """`reprojection` at the unknowns and its Jacobian in them (flat, `ravel_pytree(y)`'s
    order), in closed form: the keypoints' (`mano.forward_joints_with_jacobian`), each
    view's projection of each keypoint (forward mode in its 3 coordinates), then the Huber
    scale's (`huber_vector_with_jacobian`)."""
    problem, data, _, round = args
    params = frame_params(y, data, problem, round)
    joints, jac = mano.forward_joints_with_jacobian(problem.model, params, check_finite=False)
    # d joints / d (global_orient, hand_pose, transl_cm, betas): FLAT_ORIENT, FLAT_POSE, FLAT_TRANSL, FLAT_BETAS
    d_joints = jnp.concatenate([jac.pose.reshape(21, 3, 48), 0.01 * jac.transl, round.free_betas * jac.betas], axis=-1)
    project = lambda X: (problem.rig.project(X), problem.rig.project(X))  # noqa: E731 - the value rides along as jacfwd's aux
    d_uv, uv = jax.vmap(jax.jacfwd(project, has_aux=True))(joints)  # (21, 2, 2, 3), (21, 2, 2)
    d_uv = jnp.einsum("kvab,kbn->vkan", d_uv, d_joints)
    e, d_e = huber_vector_with_jacobian(jnp.swapaxes(uv, 0, 1) - data.uv, d_uv, problem.weights.huber_px)
    scale = problem.weights.lambda_2d * jnp.sqrt(data.weight)[..., None]
    return (scale * e).reshape(84), (scale[..., None] * d_e).reshape(84, -1)


def coupled_terms(y: FrameUnknowns, args: tuple[Problem, FrameData, Track, Round]) -> tuple[Array, ...]:
    """The terms that couple several unknowns besides the 2D reprojection: the motion
    stage's depth anchor (1 residual) and the wrist's speed limits (4)."""
    problem, data, track, round = args
    w = problem.weights
    params = frame_params(y, data, problem, round)
    dz_cm = jnp.dot(params.transl - data.anchor, data.depth_axis) * 100.0
    terms = [round.motion * w.lambda_depth * data.anchor_weight * huber_residual(dz_cm, w.depth_huber_cm)[None]]
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


def pose_prior_weight(args: tuple[Problem, FrameData, Track, Round]) -> Float[Array, ""]:
    """What the pose prior's residuals are multiplied by in this round."""
    problem, _, _, round = args
    return round.pose_scale * problem.weights.lambda_pose


def per_unknown_terms(y: FrameUnknowns, args: tuple[Problem, FrameData, Track, Round]) -> tuple[FrameUnknowns, ...]:
    """The terms each residual of which depends on the one unknown it is stored at (so
    their Jacobians are diagonal): the shape prior, the wrist anchor and the pull towards
    the smoothed track (rotations, then the wrist in the second term)."""
    problem, data, track, round = args
    w = problem.weights
    pull = jnp.sqrt(track.weight)
    zero = jax.tree.map(jnp.zeros_like, y)
    anchors = FrameUnknowns(
        pull * (y.global_orient - track.pose_target[0]),
        pull * (y.hand_pose - track.pose_target[1:]),
        (1.0 - round.motion) * w.lambda_wrist * data.anchor_weight * y.transl_cm,
        w.lambda_betas * y.betas,
    )
    transl = data.anchor + 0.01 * y.transl_cm
    track_wrist = eqx.tree_at(lambda u: u.transl_cm, zero, pull * 100.0 * (transl - track.transl_target))
    return anchors, track_wrist


def frame_residuals(y: FrameUnknowns, args: tuple[Problem, FrameData, Track, Round]) -> tuple[Array, ...]:
    """All terms of one frame's objective (see the module docstring)."""
    problem, data, _, round = args
    return (
        reprojection(problem, frame_params(y, data, problem, round), data),
        *coupled_terms(y, args),
        pose_prior_weight(args) * problem.pose_prior(y.hand_pose),
        *(ravel_pytree(term)[0] for term in per_unknown_terms(y, args)),
    )


def frame_normal_equations(y: FrameUnknowns, args: tuple[Problem, FrameData, Track, Round]) -> tuple[Float[Array, "61"], Float[Array, "61 61"]]:
    """`frame_residuals`' Gauss-Newton gradient J^T r and matrix J^T J (flat, in
    `ravel_pytree(y)`'s order), assembled from the objective's structure instead of its
    whole Jacobian: the 2D reprojection's Jacobian in closed form
    (`reprojection_with_jacobian`), the other coupled terms' by forward-mode autodiff
    in the wrist's 6 unknowns, the pose prior's in closed form in the 45 pose unknowns
    (`PosePrior.normal_equations`), the per-unknown terms' as diagonals.
    Equal to `solve.gauss_newton` of the full Jacobian (tested), with about a third of
    its rows in the dense product."""
    problem = args[0]
    g, H = gauss_newton(*reprojection_with_jacobian(y, args))
    # the depth anchor and speed limits, in the wrist's orientation and position only
    def coupled(orient, transl_cm):
        r = jnp.concatenate([t.reshape(-1) for t in coupled_terms(FrameUnknowns(orient, y.hand_pose, transl_cm, y.betas), args)])
        return r, r  # jacfwd's auxiliary output: the residuals themselves

    (J_orient, J_transl), r = jax.jacfwd(coupled, argnums=(0, 1), has_aux=True)(y.global_orient, y.transl_cm)
    g_wrist, H_wrist = gauss_newton(r, jnp.concatenate([J_orient, J_transl], axis=1))
    wrist = np.r_[FLAT_ORIENT, FLAT_TRANSL]
    g, H = g.at[wrist].add(g_wrist), H.at[np.ix_(wrist, wrist)].add(H_wrist)
    # the pose prior, in the 45 pose unknowns
    g_pose, H_pose = problem.pose_prior.normal_equations(y.hand_pose)
    weight2 = pose_prior_weight(args) ** 2
    g, H = g.at[FLAT_POSE].add(weight2 * g_pose), H.at[np.ix_(FLAT_POSE, FLAT_POSE)].add(weight2 * H_pose)
    # the per-unknown terms: a diagonal Jacobian is its product with a vector of ones
    terms, diagonals = jax.jvp(lambda u: per_unknown_terms(u, args), (y,), (jax.tree.map(jnp.ones_like, y),))
    flat_terms = [(ravel_pytree(term)[0], ravel_pytree(diagonal)[0]) for term, diagonal in zip(terms, diagonals)]
    g = g + sum(d * r for r, d in flat_terms)
    return g, H + jnp.diag(sum(d * d for _, d in flat_terms))
