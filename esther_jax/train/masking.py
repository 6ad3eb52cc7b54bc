"""Appendix C: token masking of the motion encoder's input and image augmentation.

Every draw is a pure function of a key; `example_key(seed, step, index)` derives the
key of one example of one step, so a batch's masks and augmentations are reproducible
per (seed, step, example) and a resumed run draws exactly what the uninterrupted run
would have.

Token masking (the motion encoder's input F, `ESTHER(..., motion_mask=...)`):

- per joint, each (frame, joint) slot with probability 0.20;
- whole frames, each with probability 0.10;
- a contiguous span of 3 frames, with probability 0.10 per clip (random start);
- anchor frames, every T/4 (frames 0, T/4, 2T/4, 3T/4), are never masked;
- a whole view, with probability 0.05 per clip and view: the view is absent for the
  whole clip (`view_present` False), so its tokens are replaced by the view-mask token.

These three masks go through the motion mask token, the last through the view-mask
token; both replace the token itself, so a masked observation also loses its ray (the
Plucker embedding is part of the token), as appendix C requires.

Image augmentation, per frame and view: Gaussian noise with a standard deviation drawn
in [0, 0.08] (images in [0, 1]); random erasing with probability 0.5, two rectangles
whose sides each cover 10-40 % of the crop's side, filled with uniform noise; whole-view
blanking with probability 0.12 and whole-frame blanking (both views) with probability
0.08: a blanked view is absent (`view_present` False, its pixels zero), and a frame
with no present view is an on-screen negative (`losses.onscreen_label`).
"""

import dataclasses

import jax
import jax.numpy as jnp
from jaxtyping import Array, Bool, Float, PRNGKeyArray

from ..model.config import ModelConfig
from ..model.esther import ClipInput


@dataclasses.dataclass(frozen=True)
class MaskingRates:
    joint: float = 0.20
    frame: float = 0.10
    span: float = 0.10
    span_length: int = 3
    view: float = 0.05
    anchors: int = 4
    """Anchor frames per clip (every T / anchors frames), never masked."""


@dataclasses.dataclass(frozen=True)
class AugmentRates:
    noise_sigma_max: float = 0.08
    erase: float = 0.5
    erase_rectangles: int = 2
    erase_side: tuple[float, float] = (0.1, 0.4)
    view_blank: float = 0.12
    frame_blank: float = 0.08


def example_key(seed: int | Array, step: int | Array, index: int | Array) -> PRNGKeyArray:
    """The key of example `index` of training step `step` of a run seeded with `seed`."""
    return jax.random.fold_in(jax.random.fold_in(jax.random.key(seed), step), index)


def anchor_frames(frames: int, anchors: int = MaskingRates.anchors) -> Bool[Array, "T"]:
    """Frames kept fully observed: every `frames // anchors` frames from frame 0."""
    every = max(frames // anchors, 1)
    return jnp.arange(frames) % every == 0


def motion_mask(key: PRNGKeyArray, frames: int, rates: MaskingRates = MaskingRates()) -> Bool[Array, "T 21"]:
    """Which (frame, joint) slots of F the motion encoder sees as the mask token."""
    k_joint, k_frame, k_span, k_start = jax.random.split(key, 4)
    joint = jax.random.bernoulli(k_joint, rates.joint, (frames, 21))
    frame = jax.random.bernoulli(k_frame, rates.frame, (frames,))
    start = jax.random.randint(k_start, (), 0, max(frames - rates.span_length + 1, 1))
    t = jnp.arange(frames)
    span = jax.random.bernoulli(k_span, rates.span) & (t >= start) & (t < start + rates.span_length)
    masked = joint | (frame | span)[:, None]
    return masked & ~anchor_frames(frames, rates.anchors)[:, None]


def dropped_views(key: PRNGKeyArray, rates: MaskingRates = MaskingRates()) -> Bool[Array, "2"]:
    """Views dropped for the whole clip (token masking's whole-view drop)."""
    return jax.random.bernoulli(key, rates.view, (2,))


def _augment_keys(key: PRNGKeyArray) -> tuple[PRNGKeyArray, PRNGKeyArray]:
    """(pixel-level key, blanking key) of one example's augmentation: crops and
    precomputed features get the same blanking from the same key."""
    k_pixels, k_blank = jax.random.split(key)
    return k_pixels, k_blank


def kept_views(key: PRNGKeyArray, frames: int, rates: AugmentRates = AugmentRates()) -> Bool[Array, "T 2"]:
    """Which views stay present after whole-view (per frame and view) and whole-frame
    blanking."""
    k_view, k_frame = jax.random.split(key)
    return ~jax.random.bernoulli(k_view, rates.view_blank, (frames, 2)) & ~jax.random.bernoulli(k_frame, rates.frame_blank, (frames, 1))


def augment_images(
    key: PRNGKeyArray, images: Float[Array, "T 2 3 S S"], rates: AugmentRates = AugmentRates()
) -> tuple[Float[Array, "T 2 3 S S"], Bool[Array, "T 2"]]:
    """Noise, random erasing and blanking of one clip's crops (values in [0, 1]).
    Returns the images and which views stay present (False: blanked)."""
    T, _, _, S, _ = images.shape
    k_pixels, k_blank = _augment_keys(key)
    k_sigma, k_noise, k_erase, k_rect, k_fill = jax.random.split(k_pixels, 5)
    dtype = images.dtype
    sigma = jax.random.uniform(k_sigma, (T, 2, 1, 1, 1), dtype, 0.0, rates.noise_sigma_max)
    out = images + sigma * jax.random.normal(k_noise, images.shape, dtype)

    lo, hi = rates.erase_side
    R = rates.erase_rectangles
    sides = jax.random.uniform(k_rect, (4, T, 2, R), dtype, lo, hi) * S  # width, height, then the corner draws
    width, height = sides[0], sides[1]
    x0 = jax.random.uniform(jax.random.fold_in(k_rect, 1), (T, 2, R), dtype) * (S - width)
    y0 = jax.random.uniform(jax.random.fold_in(k_rect, 2), (T, 2, R), dtype) * (S - height)
    pixel = jnp.arange(S, dtype=dtype)[None, None, None]
    in_x = (pixel >= x0[..., None]) & (pixel < (x0 + width)[..., None])  # (T, 2, R, S)
    in_y = (pixel >= y0[..., None]) & (pixel < (y0 + height)[..., None])
    rect = jnp.any(in_y[..., :, None] & in_x[..., None, :], axis=2)  # (T, 2, S rows, S cols)
    erase = jax.random.bernoulli(k_erase, rates.erase, (T, 2))[..., None, None] & rect
    fill = jax.random.uniform(k_fill, images.shape, dtype)
    out = jnp.where(erase[:, :, None], fill, out)

    present = kept_views(k_blank, T, rates)
    out = jnp.where(present[..., None, None, None], jnp.clip(out, 0.0, 1.0), 0.0)
    return out, present


def corrupt(
    key: PRNGKeyArray,
    clip: ClipInput,
    cfg: ModelConfig,
    masking: MaskingRates = MaskingRates(),
    augment: AugmentRates = AugmentRates(),
) -> tuple[ClipInput, Bool[Array, "T 21"]]:
    """One training example's corruption: the clip as the network sees it and the motion
    mask. `cfg.motion_masking` off: no token masking and no whole-view drop;
    `cfg.image_augmentation` off: the crops as they are. Views already absent stay
    absent. Precomputed features get the blanking but no pixel-level augmentation."""
    T = clip.flow.shape[0]
    k_mask, k_view, k_aug = jax.random.split(key, 3)
    present = clip.view_present
    mask = jnp.zeros((T, 21), bool)
    if cfg.motion_masking:
        mask = motion_mask(k_mask, T, masking)
        present = present & ~dropped_views(k_view, masking)[None, :]
    images = clip.images
    if cfg.image_augmentation:
        if images is not None:
            images, kept = augment_images(k_aug, images, augment)
        else:  # the same blanking draws as with crops
            kept = kept_views(_augment_keys(k_aug)[1], T, augment)
        present = present & kept
    if images is not None:
        images = jnp.where(present[..., None, None, None], images, 0.0)
    return dataclasses.replace(clip, images=images, view_present=present), mask


__all__ = ["AugmentRates", "MaskingRates", "anchor_frames", "augment_images", "corrupt", "dropped_views", "example_key", "kept_views", "motion_mask"]
