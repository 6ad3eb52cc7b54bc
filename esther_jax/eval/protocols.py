"""The robustness protocols of the paper's tables: view drop (table 2), frame drop
(table 3) and the seven photometric corruptions of appendix K (table 6).

They apply to keypoint clips (the teacher's input: confidences set to 0 is "not
observed") and to image clips (the network's input: pixels blanked plus a mask the
model reads). Everything is deterministic from an explicit key or seed.

Corruptions act on uint8 images (H, W, 3) RGB or (H, W) grayscale, on the 0-255 scale:

| name           | parameter | what it does                                                   |
|----------------|-----------|----------------------------------------------------------------|
| over_exposure  | x1.6      | intensities times 1.6, clipped                                 |
| low_light      | x0.5      | intensities times 0.5                                         |
| gamma          | 2.2       | I = 255 (I / 255)^2.2 (darker mid-tones, lighting non-linearity) |
| motion_blur    | k = 15    | horizontal box line of 15 px (camera panning)                  |
| sensor_noise   | sigma=25  | additive Gaussian noise, sigma 25 grey levels, clipped         |
| hue_shift      | +25       | hue rotated by +25 degrees (HSV; skin-tone shift); RGB only    |
| desaturate     | x0.4      | HSV saturation times 0.4; RGB only                             |

Hue and saturation are undefined for grayscale images (the HOT3D rigs), so those two
leave grayscale images unchanged.
"""

import cv2
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Bool, Float, PRNGKeyArray

FRAME_DROP_COUNTS = (0, 2, 4, 6, 8)
"""N of 16 frames dropped in table 3."""

CORRUPTIONS: dict[str, float] = {
    "over_exposure": 1.6,
    "low_light": 0.5,
    "gamma": 2.2,
    "motion_blur": 15,
    "sensor_noise": 25.0,
    "hue_shift": 25.0,
    "desaturate": 0.4,
}
"""Appendix K corruptions and their exact parameters."""


# ----------------------------------------------------------------------------- views and frames


def drop_view_keypoints(conf: Float[Array, "*batch views joints"], view: int) -> Float[Array, "*batch views joints"]:
    """Mark every joint of one view (0 left, 1 right) unobserved (confidence 0)."""
    keep = (jnp.arange(conf.shape[-2]) != view).astype(conf.dtype)
    return conf * keep.reshape((1,) * (conf.ndim - 2) + (conf.shape[-2], 1))


def drop_view_images(images: Float[Array, "frames views *pixels"], view: int) -> tuple[Array, Bool[Array, "frames views"]]:
    """Blank one view of an image clip; returns the images and the view mask (True = present)."""
    present = jnp.broadcast_to(jnp.arange(images.shape[1]) != view, images.shape[:2])
    blank = present.reshape(present.shape + (1,) * (images.ndim - 2))
    return jnp.where(blank, images, jnp.zeros((), images.dtype)), present


def frame_drop_mask(key: PRNGKeyArray, num_frames: int, num_dropped: int) -> Bool[Array, "frames"]:
    """True for kept frames: exactly `num_dropped` frames chosen uniformly at random."""
    if not 0 <= num_dropped <= num_frames:
        raise ValueError(f"cannot drop {num_dropped} of {num_frames} frames")
    order = jax.random.permutation(key, num_frames)
    return jnp.zeros(num_frames, bool).at[order[num_dropped:]].set(True)


def drop_frames_keypoints(conf: Float[Array, "frames *rest"], kept: Bool[Array, "frames"]) -> Float[Array, "frames *rest"]:
    """Confidences of dropped frames set to 0 (for (T, ...) or (D, T, ...) leading axes use vmap)."""
    return conf * kept.reshape(kept.shape + (1,) * (conf.ndim - 1)).astype(conf.dtype)


def drop_frames_images(images: Array, kept: Bool[Array, "frames"]) -> Array:
    """Dropped frames blanked (all zeros); pair with `kept` as the frame mask."""
    return jnp.where(kept.reshape(kept.shape + (1,) * (images.ndim - 1)), images, jnp.zeros((), images.dtype))


# ----------------------------------------------------------------------------- photometric corruptions


def _as_uint8(x: np.ndarray) -> np.ndarray:
    return np.clip(np.rint(x), 0, 255).astype(np.uint8)


def _hsv_edit(image: np.ndarray, hue_deg: float = 0.0, saturation: float = 1.0) -> np.ndarray:
    if image.ndim == 2 or image.shape[-1] == 1:
        return image
    hsv = cv2.cvtColor(image.astype(np.float32) / 255.0, cv2.COLOR_RGB2HSV)  # H in [0, 360)
    hsv[..., 0] = np.mod(hsv[..., 0] + hue_deg, 360.0)
    hsv[..., 1] = np.clip(hsv[..., 1] * saturation, 0.0, 1.0)
    return _as_uint8(cv2.cvtColor(hsv, cv2.COLOR_HSV2RGB) * 255.0)


def corrupt(image: np.ndarray, name: str, seed: int = 0) -> np.ndarray:
    """Apply one appendix-K corruption to a uint8 image (RGB or grayscale)."""
    if image.dtype != np.uint8:
        raise ValueError(f"corruptions take uint8 images, got {image.dtype}")
    p = CORRUPTIONS.get(name)
    if p is None:
        raise ValueError(f"unknown corruption {name!r}; choose one of {sorted(CORRUPTIONS)}")
    x = image.astype(np.float32)
    if name in ("over_exposure", "low_light"):
        return _as_uint8(x * p)
    if name == "gamma":
        return _as_uint8(255.0 * (x / 255.0) ** p)
    if name == "motion_blur":
        k = int(p)
        kernel = np.zeros((k, k), np.float32)
        kernel[k // 2, :] = 1.0 / k
        return cv2.filter2D(image, -1, kernel, borderType=cv2.BORDER_REFLECT)
    if name == "sensor_noise":
        return _as_uint8(x + np.random.default_rng(seed).normal(scale=p, size=image.shape))
    if name == "hue_shift":
        return _hsv_edit(image, hue_deg=p)
    return _hsv_edit(image, saturation=p)  # desaturate


def corrupt_clip(images: np.ndarray, name: str, seed: int = 0) -> np.ndarray:
    """Corrupt every image of a (frames, views, H, W[, C]) uint8 clip (noise seeded per image)."""
    out = np.empty_like(images)
    for t in range(images.shape[0]):
        for v in range(images.shape[1]):
            out[t, v] = corrupt(images[t, v], name, seed=seed * 1_000_003 + t * 7 + v)
    return out
