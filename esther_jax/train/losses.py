"""The training losses of appendix B, term by term.

Every term is a masked mean over its valid entries: `clip_loss_terms` returns, per clip,
each term's sum and the number of entries it summed (`Term`), and `combine` divides the
batch's sums by the batch's counts, so a term's scale depends neither on the batch size
nor on how the batch is split over devices (the sums are reduced over the sharded batch
axis like any other array). A term with no valid entry in the batch is 0.

Stage 1 (image encoder), `L_img = 0.5 L_2d + 1.0 L_hm + 1.0 L_tri`, plus the visibility
and depth-bin terms the paper supervises without giving a weight (1.0 here):

- `two_d`: Huber on pixel-normalised 2D keypoints ((u, v) / S), isotropic on the 2D
  error with delta `LossWeights.huber_delta`, per view and joint where the joint projects
  inside the crop of a present view (a blanked view contributes nothing).
- `heatmap`: cross-entropy of the heatmap logits against Gaussian soft targets on the
  patch grid (sigma `LossWeights.heatmap_sigma_cells` cells), same entries.
- `triangulation`: L1 (metres, summed over x, y, z) between the encoder's triangulation
  and the 3D joints, per joint visible in both views.
- `visibility`: binary cross-entropy of the visibility logits against in-frame
  projection validity, per joint of every present view.
- `depth`: cross-entropy over the log-spaced depth bins, target the bin nearest (in log
  depth) to the joint's depth in the crop camera, per visible joint inside the range.

Stage 2 (joint training) adds `L_FK`, `L_mot` and `L_on`; stage 1's terms stay on:

- `joints` (1.0): L1 (metres) of rig-frame keypoints; `canonical` (1.0): of wrist-relative
  keypoints; `vertices` (0.5): of mesh vertices; per keypoint / vertex of target frames.
- `rotation` (1.0): geodesic angle (radians) of the 16 local joint rotations (the root is
  the global orientation); `six_d` (0.2): L1 between the decoder's raw 6D output and the
  6D form (first two columns) of the target rotations, which keeps the 6D parameters
  consistent with the rotations they decode to; per joint of target frames.
- `betas` (0.01): L1 of the shape; `transl` (2.0): L1 (metres) of the wrist position.
- Priors on the prediction, every frame: `pose_prior` (0.1): the mean squared
  standardised PCA coefficient of the hand pose (`mano.PosePrior`, the teacher's pose
  prior); `limit_prior` (0.05): the mean squared excess (radians) over the anatomical
  joint limits; `shape_prior` (0.02): the mean squared beta.
- `motion` (0.5): the motion encoder at the masked positions: canonical joints (L1, per
  masked joint), MANO pose (per masked frame, i.e. a frame with a masked joint: the L1
  of each of the 16 local rotations in 6D, averaged over the rotations, the same scale
  as `six_d`; summed over the 96 numbers it was 48 at initialisation, three quarters of
  the whole loss) and root velocity (L1 on the target's frame differences,
  per masked frame and its successor); the three masked means are summed.
- `onscreen` (0.5): binary cross-entropy of the on-screen logits against "the hand is
  visible in at least one present view" (a blanked frame is a negative).

The table-5 switches turn terms off: `guidance_2d` (`two_d`, `heatmap`),
`guidance_triangulation` (`triangulation`); `motion_masking` acts through the mask (no
masked position, no `motion` term).

All terms are computed in float32 whatever the network's compute precision.
"""

import dataclasses

import equinox as eqx
import jax
import jax.numpy as jnp
import optax
from jaxtyping import Array, Bool, Float

from .. import mano
from .._math import safe_norm
from ..crops import patch_centres
from ..model.config import ModelConfig
from ..model.esther import ClipInput, ESTHEROutput, crop_projections
from ..model.stereo_encoder import depth_bin_centres
from ..rotations import axis_angle_to_matrix, geodesic_angle, matrix_to_rotation_6d

STAGES = ("image", "joint")


@dataclasses.dataclass(frozen=True)
class LossWeights:
    """Appendix B's weights (and the few choices it leaves open, documented here)."""

    two_d: float = 0.5
    heatmap: float = 1.0
    triangulation: float = 1.0
    visibility: float = 1.0
    """Unweighted in the paper: 1.0."""
    depth: float = 1.0
    """Unweighted in the paper: 1.0."""
    joints: float = 1.0
    canonical: float = 1.0
    vertices: float = 0.5
    rotation: float = 1.0
    six_d: float = 0.2
    betas: float = 0.01
    transl: float = 2.0
    pose_prior: float = 0.1
    limit_prior: float = 0.05
    shape_prior: float = 0.02
    motion: float = 0.5
    onscreen: float = 0.5
    huber_delta: float = 0.02
    """Of the 2D Huber, in crop-normalised units (0.02 of a 224 px crop: 4.5 px)."""
    heatmap_sigma_cells: float = 1.0
    """Standard deviation of the heatmap's Gaussian targets, in patch cells."""


STAGE_TERMS = {
    "image": ("two_d", "heatmap", "triangulation", "visibility", "depth"),
    "joint": ("two_d", "heatmap", "triangulation", "visibility", "depth", "joints", "canonical", "vertices", "rotation",
              "six_d", "betas", "transl", "pose_prior", "limit_prior", "shape_prior", "motion", "onscreen"),
}  # fmt: skip


class Targets(eqx.Module):
    """What one clip is supervised with (right-hand frame: left hands arrive mirrored),
    rig frame, metres: ground truth (`gt.npz`) or the teacher's labels (`labels.npz`)."""

    global_orient: Float[Array, "*batch T 3"]
    hand_pose: Float[Array, "*batch T 15 3"]
    betas: Float[Array, "*batch 10"]
    transl: Float[Array, "*batch T 3"]
    """Wrist position."""
    joints: Float[Array, "*batch T 21 3"]
    valid: Bool[Array, "*batch T"]
    """Frames with a 3D target (on screen in the ground truth; the teacher's `valid`)."""


class Term(eqx.Module):
    """A loss term's sum over its valid entries and their number (per clip or batch)."""

    total: Float[Array, "*batch"]
    count: Float[Array, "*batch"]


def _term(values: Array, mask: Array) -> Term:
    mask = jnp.broadcast_to(mask, values.shape).astype(jnp.float32)
    return Term(jnp.sum(jnp.where(mask > 0, values, 0.0)), jnp.sum(mask))


def _bce_with_logits(logits: Array, labels: Array) -> Array:
    """Binary cross-entropy of `sigmoid(logits)` against boolean labels (optax's stable form)."""
    return optax.sigmoid_binary_cross_entropy(logits, labels.astype(logits.dtype))


def _masked_mean(values: Array, mask: Array) -> Array:
    t = _term(values, mask)
    return t.total / jnp.maximum(t.count, 1.0)


def onscreen_label(targets: Targets, visible: Bool[Array, "T 2 21"]) -> Bool[Array, "T"]:
    """The hand is on screen in a frame when it has a target and some joint projects into
    the crop of a present view."""
    return targets.valid & jnp.any(visible, axis=(1, 2))


def clip_loss_terms(
    out: ESTHEROutput,
    clip: ClipInput,
    targets: Targets,
    motion_mask: Bool[Array, "T 21"],
    hand_model: mano.ManoModel,
    cfg: ModelConfig,
    weights: LossWeights = LossWeights(),
    *,
    crop_size: int,
) -> dict[str, Term]:
    """Every appendix-B term of one clip (right hand, rig frame) as `Term`s (sum, count).

    Args:
        out: the network's output on `clip` (with `motion_mask` applied).
        clip: the clip as the network saw it (after augmentation: blanked views and
            frames are in `view_present`).
        targets: the clip's 3D supervision.
        motion_mask: True where the motion encoder's input was masked.
        crop_size: S, the crops' side in pixels (the config's `crop_size`).
    """
    f32 = lambda x: jnp.asarray(x, jnp.float32)  # noqa: E731  (losses in float32)
    T = targets.joints.shape[0]
    valid = targets.valid
    present = clip.view_present
    terms: dict[str, Term] = {}

    # --- stage 1: the image encoder's guidance
    uv, depth, inside = crop_projections(clip, f32(targets.joints), crop_size)
    visible = inside & present[..., None] & valid[:, None, None]  # (T, 2, 21)
    S = float(crop_size)
    err = (f32(out.image.keypoints_2d) - uv) / S
    norm = safe_norm(err)
    delta = weights.huber_delta
    huber = jnp.where(norm <= delta, 0.5 * norm**2, delta * (norm - 0.5 * delta))
    terms["two_d"] = _term(huber, visible)

    G = cfg.grid
    centres = f32(patch_centres(crop_size, G)).reshape(G * G, 2)
    sigma = weights.heatmap_sigma_cells * S / G
    d2 = jnp.sum((centres[None, None, None] - uv[..., None, :]) ** 2, axis=-1)  # (T, 2, 21, G*G)
    soft = jax.nn.softmax(-d2 / (2.0 * sigma**2), axis=-1)
    log_p = jax.nn.log_softmax(f32(out.image.heatmap_logits).reshape(T, 2, 21, G * G), axis=-1)
    terms["heatmap"] = _term(-jnp.sum(soft * log_p, axis=-1), visible)

    both = jnp.all(visible, axis=1)  # (T, 21)
    terms["triangulation"] = _term(jnp.sum(jnp.abs(f32(out.image.triangulated) - f32(targets.joints)), axis=-1), both)

    vis_logits = f32(out.image.visibility_logits)
    bce = _bce_with_logits(vis_logits, inside)
    terms["visibility"] = _term(bce, present[..., None] & valid[:, None, None])

    centres_z = f32(depth_bin_centres(cfg))
    lo, hi = cfg.depth_range_m
    log_depth = jnp.log(jnp.clip(depth, lo, hi))
    nearest = jnp.argmin(jnp.abs(log_depth[..., None] - jnp.log(centres_z)[None, None, None]), axis=-1)
    log_q = jax.nn.log_softmax(f32(out.image.depth_logits), axis=-1)
    ce = -jnp.take_along_axis(log_q, nearest[..., None], axis=-1)[..., 0]
    terms["depth"] = _term(ce, visible & (depth >= lo) & (depth <= hi))

    # --- stage 2: forward kinematics, priors, motion, on-screen
    target_local = axis_angle_to_matrix(jnp.concatenate([f32(targets.global_orient)[:, None], f32(targets.hand_pose)], axis=1))
    joints_pred = f32(out.joints)
    frames = valid[:, None]
    terms["joints"] = _term(jnp.sum(jnp.abs(joints_pred - f32(targets.joints)), axis=-1), frames)
    canon_pred = joints_pred - joints_pred[:, :1]
    canon_gt = f32(targets.joints) - f32(targets.joints)[:, :1]
    terms["canonical"] = _term(jnp.sum(jnp.abs(canon_pred - canon_gt), axis=-1), frames)
    target_vertices = jax.vmap(
        lambda R, t: mano.forward_rotations(hand_model, R, f32(targets.betas), t).vertices
    )(target_local, f32(targets.transl))  # fmt: skip
    terms["vertices"] = _term(jnp.sum(jnp.abs(f32(out.vertices) - target_vertices), axis=-1), frames)
    terms["rotation"] = _term(geodesic_angle(f32(out.decoded.rotations), target_local), frames)
    terms["six_d"] = _term(jnp.sum(jnp.abs(f32(out.decoded.pose_6d) - matrix_to_rotation_6d(target_local)), axis=-1), frames)
    terms["betas"] = _term(jnp.sum(jnp.abs(f32(out.decoded.betas) - f32(targets.betas))), jnp.any(valid))
    terms["transl"] = _term(jnp.sum(jnp.abs(f32(out.params.transl) - f32(targets.transl)), axis=-1), valid)

    prior = mano.PosePrior.from_model(hand_model)
    residuals = jax.vmap(prior)(f32(out.params.hand_pose))  # (T, 90): 45 PCA coefficients, 45 weighted excesses
    every = jnp.ones((T,), bool)
    terms["pose_prior"] = _term(jnp.mean(residuals[:, :45] ** 2, axis=-1), every)
    terms["limit_prior"] = _term(jnp.mean((residuals[:, 45:] / prior.limit_weight) ** 2, axis=-1), every)
    terms["shape_prior"] = _term(jnp.mean(f32(out.decoded.betas) ** 2), jnp.ones((), bool))

    masked_joint = motion_mask & frames
    masked_frame = jnp.any(motion_mask, axis=1) & valid
    canon_mot = jnp.sum(jnp.abs(f32(out.motion.canonical_joints) - canon_gt), axis=-1)
    pose_mot = jnp.mean(jnp.sum(jnp.abs(f32(out.motion.pose_6d) - matrix_to_rotation_6d(target_local)), axis=-1), axis=-1)
    velocity_gt = f32(targets.transl)[1:] - f32(targets.transl)[:-1]
    velocity_ok = masked_frame[:-1] & valid[1:]
    velocity = jnp.sum(jnp.abs(f32(out.motion.root_velocity)[:-1] - velocity_gt), axis=-1)
    motion = _masked_mean(canon_mot, masked_joint) + _masked_mean(pose_mot, masked_frame) + _masked_mean(velocity, velocity_ok)
    any_masked = jnp.any(masked_joint)
    terms["motion"] = Term(jnp.where(any_masked, motion, 0.0), any_masked.astype(jnp.float32))

    label = onscreen_label(targets, visible)
    logits = f32(out.motion.onscreen_logits)
    on_bce = _bce_with_logits(logits, label)
    terms["onscreen"] = _term(on_bce, every)
    return terms


def combine(terms: dict[str, Term], cfg: ModelConfig, stage: str, weights: LossWeights = LossWeights()) -> tuple[Array, dict[str, Array]]:
    """The batch's loss: each term's masked mean (batch sums over batch counts), weighted
    and summed over the terms of `stage` ('image' or 'joint') that the config's switches
    keep. Returns (loss, {term: masked mean}) with the mean of every term of the stage
    (switched off or not), for the logs; stage 'image' computes nothing of the motion
    encoder, the decoder or the forward kinematics once compiled."""
    if stage not in STAGES:
        raise ValueError(f"stage must be one of {STAGES}, got {stage!r}")
    off = set()
    if not cfg.guidance_2d:
        off |= {"two_d", "heatmap"}
    if not cfg.guidance_triangulation:
        off.add("triangulation")
    means = {name: jnp.sum(terms[name].total) / jnp.maximum(jnp.sum(terms[name].count), 1.0) for name in STAGE_TERMS[stage]}
    loss = sum(getattr(weights, name) * means[name] for name in STAGE_TERMS[stage] if name not in off)
    return loss, means


__all__ = ["LossWeights", "STAGES", "STAGE_TERMS", "Targets", "Term", "clip_loss_terms", "combine", "onscreen_label"]
