"""Keypoint fusion of D >= 1 detectors (paper appendix A) and input sanitising.

Per joint and view, the valid set is V_j = {d : c_j^d >= tau} with tau = 0.3, and
d* = argmax_{d in V_j} c_j^d, near ties (confidence within 0.05 of the best) broken by
the detectors' box scores s^d. The fused keypoint is the confidence-weighted mean of
the valid detections that agree with d*, i.e. lie within eps = 0.1 of the hand-box side
w_b of it; its confidence is the largest of theirs; a joint with V_j empty is dropped (confidence 0).

- D = 2 is appendix A exactly: two agreeing detections are averaged with confidence
  weights, otherwise the more confident one (near ties: the higher box score) wins.
- D = 1: that detector's joints with c >= tau, unchanged.
- D > 2: the same rule. The most confident detection anchors the joint and every valid
  detection that agrees with it joins the weighted mean, so a lone outlier is ignored
  and a consensus is averaged; with two detectors this is the paper's case analysis.
"""

import equinox as eqx
import jax.numpy as jnp
from jaxtyping import Array, Bool, Float

TAU = 0.3
EPS = 0.1
NEAR_TIE = 0.05


class Fused(eqx.Module):
    """Fused 2D evidence of one hand over a clip."""

    uv: Float[Array, "frames 2 21 2"]
    """Fused keypoints (pixels, each view's image); 0 where dropped."""
    conf: Float[Array, "frames 2 21"]
    """Fused confidence; 0 = not observed."""
    box_side: Float[Array, "frames 2"]
    """Hand-box side w_b (pixels) per view (0 when no detector boxed the hand)."""
    num_invalid: Float[Array, ""]
    """Keypoints discarded because their pixels or confidences were NaN or infinite while
    their confidence said they were detected (`sanitise`)."""


def sanitise(
    uv: Float[Array, "*batch 2"], conf: Float[Array, "*batch"]
) -> tuple[Float[Array, "*batch 2"], Float[Array, "*batch"], Float[Array, ""]]:
    """NaN / infinite keypoints or confidences become 'not observed' (conf 0); returns the
    count of the contradictory ones: a non-finite confidence, or a non-finite keypoint with
    a confidence above 0 (a NaN keypoint of confidence 0 is the clip format's "not
    detected", not counted)."""
    bad = ~(jnp.all(jnp.isfinite(uv), axis=-1) & jnp.isfinite(conf))
    count = jnp.sum(bad & (conf != 0)).astype(conf.dtype)
    return jnp.where(bad[..., None], 0.0, uv), jnp.where(bad, 0.0, jnp.clip(conf, 0.0, 1.0)), count


def fuse(
    uv: Float[Array, "detectors frames 2 21 2"],
    conf: Float[Array, "detectors frames 2 21"],
    box: Float[Array, "detectors frames 2 4"],
    box_score: Float[Array, "detectors frames 2"],
) -> Fused:
    """Fuse the D detectors of a keypoints.npz (leading axis D >= 1)."""
    if uv.shape[0] < 1:
        raise ValueError("fusion needs at least one detector (keypoints.npz has D = 0)")
    uv, conf, num_invalid = sanitise(uv, conf)
    box = jnp.where(jnp.isfinite(box), box, 0.0)
    box_score = jnp.where(jnp.isfinite(box_score), box_score, 0.0)
    sides = jnp.maximum(box[..., 2] - box[..., 0], box[..., 3] - box[..., 1])  # (D, T, 2)
    has_box = box_score > 0
    count = jnp.sum(has_box.astype(sides.dtype), axis=0)
    w_b = jnp.sum(jnp.where(has_box, sides, 0.0), axis=0) / jnp.maximum(count, 1.0)  # (T, 2)

    valid = conf >= TAU  # (D, T, 2, 21)
    best = jnp.max(jnp.where(valid, conf, -1.0), axis=0)
    # d*: among valid detections within NEAR_TIE of the best, the highest box score
    # (then the lowest index, as argmax does)
    contender = valid & (conf > best[None] - NEAR_TIE)
    score = jnp.broadcast_to(box_score[..., None], conf.shape)
    star = jnp.argmax(jnp.where(contender, score, -jnp.inf), axis=0)  # (T, 2, 21)
    uv_star = jnp.take_along_axis(uv, star[None, ..., None], axis=0)[0]
    distance = jnp.linalg.norm(uv - uv_star[None], axis=-1)
    agree = valid & (distance <= EPS * w_b[None, ..., None])
    agree = agree | (jnp.arange(uv.shape[0])[:, None, None, None] == star[None])  # d* agrees with itself
    w = jnp.where(agree & valid, conf, 0.0)
    averaged = jnp.sum(w[..., None] * uv, axis=0) / jnp.maximum(jnp.sum(w, axis=0), 1e-9)[..., None]
    observed = jnp.any(valid, axis=0)
    fused_uv = jnp.where(observed[..., None], averaged, 0.0)
    fused_conf = jnp.where(observed, jnp.max(w, axis=0), 0.0)
    return Fused(uv=fused_uv, conf=fused_conf, box_side=w_b, num_invalid=num_invalid)


def observed(conf: Float[Array, "*batch"]) -> Bool[Array, "*batch"]:
    """Whether a fused confidence counts as an observation (>= tau)."""
    return conf >= TAU
