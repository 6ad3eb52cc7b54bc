"""Keypoint fusion of two detectors (paper appendix A, exactly) and input sanitising.

Per joint and view, the valid set is V_j = {d : c_j^d >= tau} with tau = 0.3. Two valid
detections within eps = 0.1 of the hand-box side of each other are averaged with
confidence weights; otherwise the more confident one wins (near ties, |c1 - c2| <
0.05, are broken by the detectors' box scores); a joint with no valid detection is
dropped (confidence 0). The fused confidence is the larger of the two.
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
    """Fused keypoints (pixels); 0 where dropped."""
    conf: Float[Array, "frames 2 21"]
    """Fused confidence; 0 = not observed."""
    box_side: Float[Array, "frames 2"]
    """Hand-box side w_b (pixels) per view (0 when no detector boxed the hand)."""
    num_invalid: Float[Array, ""]
    """Detections discarded because their pixels or confidences were NaN or infinite."""


def sanitise(uv: Array, conf: Array) -> tuple[Array, Array, Array]:
    """NaN / infinite keypoints or confidences become 'not observed' (conf 0); returns the count."""
    bad = ~(jnp.all(jnp.isfinite(uv), axis=-1) & jnp.isfinite(conf))
    return jnp.where(bad[..., None], 0.0, uv), jnp.where(bad, 0.0, jnp.clip(conf, 0.0, 1.0)), jnp.sum(bad)


def fuse(
    uv: Float[Array, "2 frames 2 21 2"],
    conf: Float[Array, "2 frames 2 21"],
    box: Float[Array, "2 frames 2 4"],
    box_score: Float[Array, "2 frames 2"],
) -> Fused:
    """Fuse the two detectors of a keypoints.npz (leading axis D = 2)."""
    if uv.shape[0] != 2:
        raise ValueError(f"fusion takes exactly two detectors; got D = {uv.shape[0]}")
    uv, conf, num_invalid = sanitise(uv, conf)
    box = jnp.where(jnp.isfinite(box), box, 0.0)
    box_score = jnp.where(jnp.isfinite(box_score), box_score, 0.0)
    sides = jnp.maximum(box[..., 2] - box[..., 0], box[..., 3] - box[..., 1])  # (2, T, 2)
    has_box = box_score > 0
    count = jnp.sum(has_box.astype(sides.dtype), axis=0)
    w_b = jnp.sum(jnp.where(has_box, sides, 0.0), axis=0) / jnp.maximum(count, 1.0)  # (T, 2)
    c1, c2 = conf[0], conf[1]
    v1, v2 = c1 >= TAU, c2 >= TAU
    distance = jnp.linalg.norm(uv[0] - uv[1], axis=-1)
    agree = v1 & v2 & (distance <= EPS * w_b[..., None])
    averaged = (c1[..., None] * uv[0] + c2[..., None] * uv[1]) / jnp.maximum(c1 + c2, 1e-9)[..., None]
    tie = jnp.abs(c1 - c2) < NEAR_TIE
    first_wins = jnp.where(tie, box_score[0][..., None] >= box_score[1][..., None], c1 >= c2)
    pick_first = v1 & (~v2 | first_wins)
    single = jnp.where(pick_first[..., None], uv[0], uv[1])
    single_conf = jnp.where(pick_first, c1, c2)
    fused_uv = jnp.where(agree[..., None], averaged, single)
    fused_conf = jnp.where(agree, jnp.maximum(c1, c2), jnp.where(v1 | v2, single_conf, 0.0))
    fused_uv = jnp.where((fused_conf > 0)[..., None], fused_uv, 0.0)
    return Fused(uv=fused_uv, conf=fused_conf, box_side=w_b, num_invalid=num_invalid.astype(fused_conf.dtype))


def observed(conf: Float[Array, "*batch"]) -> Bool[Array, "*batch"]:
    return conf >= TAU
