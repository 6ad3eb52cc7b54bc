"""Where the stereo encoder's cross-view attention goes: the hand or the rest of the crop.

The probe of the paper's size-depth binding study (section 5.4, figure 7): across the
stereo blocks L1..Ln, the share of the cross-attention into the kept view that lands
on the hand's patches, for a stereo model (both views), the view-mask model with one
view dropped (the dropped view's tokens are the view-mask placeholder, whose queries
attend into the kept view) and the pure-monocular model (config ablation
`monocular`). For one clip with its target keypoints `joints` (rig frame), the left
view kept (the view-mask model's clip has its right view dropped, e.g. with
`train.validation.drop_view(clip, 1)`):

    attention = esther_jax.model.cross_view_attention(net, clip)  # [layers T 2 heads P P]
    mask = hand_patch_mask(clip, joints, crop_size=net.config.crop_size, grid=net.config.grid)
    result = attention_on_hand(attention, mask, kept_view=0)      # .share [layers], .chance

Hand patches are the patches whose centre lies within `radius` patch sides (default
one) of the hand's skeleton projected into the crop: the 20 bones, each the 2D segment
between a keypoint and its parent (`mano.KEYPOINT_PARENTS`). A patch holding a
keypoint or a bone point is always a hand patch (its centre is at most half a diagonal,
0.71 patch sides, away), and one side of margin covers the palm between the metacarpal
bones and the fingers' thickness, without the bounding box's corners of background.
"""

import math

import equinox as eqx
import jax.numpy as jnp
from jaxtyping import Array, Bool, Float, Int

from ..crops import patch_centres
from ..mano import KEYPOINT_PARENTS
from ..model import ClipInput, crop_projections

_BONES = tuple((child, parent) for child, parent in enumerate(KEYPOINT_PARENTS) if parent >= 0)
_MIN_DEPTH_M = 0.01
"""A keypoint nearer than 1 cm to (or behind) a crop camera has no usable pixel: its bones are left out."""


def hand_patch_mask(
    clip: ClipInput, joints: Float[Array, "T 21 3"], *, crop_size: int, grid: int, radius: float = 1.0
) -> Bool[Array, "T 2 grid grid"]:
    """The patches of each view's crop that hold the hand (rows = v, as the heatmaps).

    Args:
        clip: one clip (no batch axis); its crop cameras (`K`, `R_cam_crop`,
            `T_rig_cams`) project the joints, and a view it marks absent
            (`view_present` False) has no hand patches (the network saw no pixels).
        joints: the 21 target keypoints per frame in the rig frame (metres); a frame
            whose keypoints are NaN has no hand patches.
        crop_size: side S of the crops (pixels), the network config's `crop_size`.
        grid: patches per crop side, the network config's `grid`.
        radius: how far (in patch sides, S / grid pixels) a patch centre may lie from
            the projected skeleton; bones with a keypoint within 1 cm of (or behind) the
            crop camera are left out.

    Returns:
        True for hand patches, per frame and view, over the grid x grid patch tiling
        (`crops.patch_centres`; flattened row-major, the patch order of the tokens).
    """
    if radius <= 0:
        raise ValueError(f"radius is in patch sides and must be positive; got {radius}")
    uv, depth, _ = crop_projections(clip, joints, crop_size)  # (T, 2, 21, 2) crop pixels, (T, 2, 21) metres
    child, parent = (jnp.asarray(index) for index in zip(*_BONES))
    start, end = uv[..., parent, :], uv[..., child, :]  # (T, 2, bones, 2)
    usable = (depth[..., parent] > _MIN_DEPTH_M) & (depth[..., child] > _MIN_DEPTH_M) & clip.view_present[..., None]
    centres = patch_centres(crop_size, grid).reshape(1, 1, grid * grid, 1, 2).astype(uv.dtype)
    # distance of every patch centre to every bone segment: the nearest point of the
    # segment is start + s (end - start), s the projection clipped to [0, 1]
    bone = (end - start)[:, :, None]  # (T, 2, 1, bones, 2)
    offset = centres - start[:, :, None]  # (T, 2, P, bones, 2)
    length_sq = jnp.sum(bone * bone, axis=-1)
    degenerate = length_sq <= 0.0  # a bone seen end-on projects to a point
    s = jnp.clip(jnp.sum(offset * bone, axis=-1) / jnp.where(degenerate, 1.0, length_sq), 0.0, 1.0)
    gap = offset - s[..., None] * bone
    near = jnp.sum(gap * gap, axis=-1) <= (radius * crop_size / grid) ** 2  # (T, 2, P, bones)
    hand = jnp.any(near & usable[:, :, None, :], axis=-1)
    return hand.reshape(hand.shape[:2] + (grid, grid))


def attention_map(attention: Float[Array, "*batch layers T 2 heads P P"], kept_view: int) -> Float[Array, "*batch layers T grid grid"]:
    """The cross-attention into the kept view as a map over its crop: per block and
    frame, the attention that the other view's queries (the placeholder's when that view
    is dropped) give to each patch of the kept view, averaged over heads and queries.

    Args:
        attention: `esther_jax.model.cross_view_attention` of a clip (any leading
            axes, e.g. clips from a vmap).
        kept_view: 0 (left) or 1 (right), the view attended into.

    Returns:
        Per block and frame, a grid x grid map (rows = v, crop pixels of
        `crops.patch_centres`) that sums to 1.
    """
    if kept_view not in (0, 1):
        raise ValueError(f"kept_view must be 0 (left) or 1 (right); got {kept_view!r}")
    P = attention.shape[-1]
    grid = math.isqrt(P)
    if grid * grid != P:
        raise ValueError(f"attention has {P} keys per query, not the patches of a square grid; pass esther_jax.model.cross_view_attention's output")
    mean = jnp.mean(attention[..., 1 - kept_view, :, :, :], axis=(-3, -2))  # queries of the other view: (*batch, layers, T, P)
    return mean.reshape(mean.shape[:-1] + (grid, grid))


class HandAttention(eqx.Module):
    """How much of the cross-attention into the kept view lands on the hand."""

    share: Float[Array, "layers"]
    """Per stereo block, the share (in [0, 1]) of the other view's attention into the
    kept view that falls on the kept view's hand patches, averaged over heads, queries
    and the counted frames; NaN when no frame counts."""
    chance: Float[Array, ""]
    """The share uniform attention would give: the mean fraction of the kept view's
    patches that are hand patches, over the same frames (NaN when none counts)."""
    frames: Int[Array, ""]
    """Frames counted: those in which the kept view has hand patches."""


def attention_on_hand(
    attention: Float[Array, "*batch layers T 2 heads P P"], hand_mask: Bool[Array, "*batch T 2 grid grid"], kept_view: int
) -> HandAttention:
    """The share of the cross-attention into the kept view that lands on the hand.

    For the queries of the other view (the view-mask placeholder when that view is
    dropped or removed), the attention mass on the kept view's hand patches, averaged
    over heads, queries and frames. Only frames where the kept view has hand patches
    count (`hand_patch_mask` gives none where the kept view is absent or the hand does
    not project). Leading axes (clips, from a vmap) are pooled with the frames.

    Args:
        attention: `esther_jax.model.cross_view_attention` of the clip(s).
        hand_mask: `hand_patch_mask` of the same clip(s).
        kept_view: 0 (left) or 1 (right), the view attended into.

    Returns:
        The per-block shares, the uniform-attention share over the same frames (a share
        above it means attention concentrates on the hand) and the frames counted.
    """
    maps = attention_map(attention, kept_view)  # (*batch, layers, T, grid, grid)
    expected = maps.shape[:-4] + (maps.shape[-3], 2) + maps.shape[-2:]  # (*batch, T, 2, grid, grid)
    if hand_mask.shape != expected:
        raise ValueError(f"hand_mask {hand_mask.shape} does not match attention {attention.shape}: expected {expected}, "
                         "hand_patch_mask of the same clip(s) and the network's grid")  # fmt: skip
    dtype = maps.dtype
    mask = hand_mask[..., kept_view, :, :]  # (*batch, T, grid, grid)
    counted = jnp.any(mask, axis=(-2, -1))  # (*batch, T)
    on_hand = jnp.sum(jnp.where(mask[..., None, :, :, :], maps, 0.0), axis=(-2, -1))  # (*batch, layers, T)
    layers = on_hand.shape[-2]
    share_sum = jnp.sum(jnp.where(counted[..., None, :], on_hand, 0.0), axis=-1).reshape(-1, layers).sum(axis=0)
    fraction = jnp.mean(mask.astype(dtype), axis=(-2, -1))  # the uniform share per frame
    chance_sum = jnp.sum(jnp.where(counted, fraction, 0.0))
    frames = jnp.sum(counted)
    denominator = jnp.maximum(frames, 1).astype(dtype)
    nan = jnp.asarray(jnp.nan, dtype)
    return HandAttention(
        share=jnp.where(frames > 0, share_sum / denominator, nan),
        chance=jnp.where(frames > 0, chance_sum / denominator, nan),
        frames=frames,
    )
