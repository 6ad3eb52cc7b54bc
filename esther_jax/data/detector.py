"""Simulated 2D hand keypoint detectors (the teacher's input without a real detector).

Two detectors with different error models stand in for the paper's YOLO11-pose and
ViTPose ensemble. What we assume, and why (from how such detectors behave on
egocentric video, and from the real detector `esther_jax.detect.MediaPipeHands`, whose
errors on real hand photos are a few pixels median and ~15-20 px worst case on 700 px
images; see README, "Your own data"):

- *Pixel noise scales with the apparent hand size* (keypoint heatmaps live on a crop
  resized to a fixed size): sigma = `noise` x the hand's 2D bounding-box diagonal for a
  visible joint (about 1-2 %, i.e. 2-4 px for a 200 px hand), 2.5x that when the joint
  is hidden by the hand or an object (the detector guesses from context).
- *Heavy tails*: Student-t noise (3 degrees of freedom) plus gross outliers with
  probability `outlier_rate` per joint, displaced by up to 25 % of the hand size.
- *Confidence correlates with error*: a logistic function of the normalised error,
  lower for hidden joints, with calibration noise.
- *Finger swaps*: with probability `swap_rate` per frame, the keypoints of two adjacent
  fingers are exchanged (a classic failure on curled fingers).
- *Out of frame*: joints outside the image get confidence 0 (or, with probability 0.3,
  a low-confidence guess clamped to the border).
- *Misses*: whole frames (`frame_miss_rate`) and whole views (`view_miss_rate`) without
  detection: confidence 0, box score 0.
- *Boxes*: the keypoints' bounding box padded by 15 % with 3 % jitter; box score tracks
  the mean confidence.

Presets: `clean` (no error at all: detections equal the projected joints, for tests),
`easy`, `default` (as hard as real detectors on egocentric video, we assume: a few
pixels median, a few percent outliers, occasional swaps and misses) and `hard`.
"""

import dataclasses

import jax.numpy as jnp
import numpy as np

from ..cameras import StereoRig
from ..mano import KEYPOINT_FINGERS

_FINGER_NAMES = tuple(KEYPOINT_FINGERS)
"""Thumb to pinky: adjacent entries are neighbouring fingers."""


@dataclasses.dataclass(frozen=True)
class DetectorModel:
    """Error model of one simulated detector."""

    noise: float = 0.012
    """Pixel noise (std) as a fraction of the hand's 2D box diagonal, for visible joints."""
    hidden_noise_factor: float = 2.5
    outlier_rate: float = 0.02
    swap_rate: float = 0.01
    frame_miss_rate: float = 0.02
    view_miss_rate: float = 0.02
    confidence_slope: float = 1.6
    """How fast confidence falls with the normalised error."""
    confidence_noise: float = 0.08


PRESETS: dict[str, tuple[DetectorModel, DetectorModel]] = {
    "clean": (
        DetectorModel(0.0, 1.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0),
        DetectorModel(0.0, 1.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0),
    ),
    "easy": (DetectorModel(0.006, 2.0, 0.005, 0.0, 0.0, 0.0), DetectorModel(0.008, 2.0, 0.005, 0.0, 0.0, 0.0)),
    "default": (
        DetectorModel(noise=0.011, outlier_rate=0.02, swap_rate=0.01, frame_miss_rate=0.03, view_miss_rate=0.03),
        DetectorModel(noise=0.014, outlier_rate=0.03, swap_rate=0.015, frame_miss_rate=0.02, view_miss_rate=0.02),
    ),
    "hard": (
        DetectorModel(noise=0.02, outlier_rate=0.06, swap_rate=0.04, frame_miss_rate=0.08, view_miss_rate=0.08),
        DetectorModel(noise=0.025, outlier_rate=0.08, swap_rate=0.05, frame_miss_rate=0.06, view_miss_rate=0.06),
    ),
}


def simulate(
    rng: np.random.Generator,
    uv_true: np.ndarray,
    visible: np.ndarray,
    in_image: np.ndarray,
    image_size: tuple[int, int],
    model: DetectorModel,
) -> dict[str, np.ndarray]:
    """One detector on one hand: uv [T,2,21,2], conf [T,2,21], box [T,2,4], box_score [T,2].

    Args:
        uv_true: projected ground-truth joints (T, 2 views, 21, 2).
        visible: joint not hidden and inside the image (T, 2, 21).
        in_image: joint projects inside the image, hidden or not (T, 2, 21).
        image_size: (width, height).
    """
    T = uv_true.shape[0]
    width, height = image_size
    lo = np.where(in_image[..., None], uv_true, np.inf).min(axis=2)
    hi = np.where(in_image[..., None], uv_true, -np.inf).max(axis=2)
    size = np.linalg.norm(np.where(np.isfinite(hi - lo), hi - lo, 0.0), axis=-1)  # (T, 2)
    size = np.maximum(size, 10.0)[..., None]
    sigma = model.noise * size * np.where(visible, 1.0, model.hidden_noise_factor)
    noise = rng.standard_t(3, size=uv_true.shape) / np.sqrt(3.0) * sigma[..., None]
    outlier = rng.uniform(size=visible.shape) < model.outlier_rate
    noise += outlier[..., None] * rng.uniform(-0.25, 0.25, size=uv_true.shape) * size[..., None]
    uv = uv_true + noise
    swap = rng.uniform(size=(T, 2)) < model.swap_rate
    for t, v in zip(*np.nonzero(swap)):
        f = rng.integers(1, 4)  # index/middle, middle/ring or ring/pinky
        a, b = (list(KEYPOINT_FINGERS[name]) for name in _FINGER_NAMES[f : f + 2])
        uv[t, v, a + b] = uv[t, v, b + a]
    error = np.linalg.norm(uv - uv_true, axis=-1) / np.maximum(model.noise * size, 1e-6)
    conf = 0.5 * (1.0 - np.tanh(0.5 * model.confidence_slope * (error - 2.5)))  # logistic, overflow-free
    conf = conf * np.where(visible, 1.0, 0.55) + rng.normal(scale=model.confidence_noise, size=conf.shape)
    conf = np.clip(conf, 0.02, 1.0)
    if model.noise == 0.0:
        conf = np.where(visible, 1.0, np.where(in_image, 0.5, 0.0))
    guessed = rng.uniform(size=conf.shape) < 0.3
    out = ~in_image
    uv = np.where(out[..., None] & guessed[..., None], np.clip(uv, [0, 0], [width - 1, height - 1]), uv)
    conf = np.where(out, np.where(guessed & (model.noise > 0), 0.1 * conf, 0.0), conf)
    missed = (rng.uniform(size=(T, 1)) < model.frame_miss_rate) | (rng.uniform(size=(T, 2)) < model.view_miss_rate)
    missed |= in_image.sum(axis=-1) < 3  # nothing to detect
    conf = np.where(missed[..., None], 0.0, conf)
    detected = conf > 0
    box_lo = np.where(detected[..., None], uv, np.inf).min(axis=2)
    box_hi = np.where(detected[..., None], uv, -np.inf).max(axis=2)
    ok = np.all(np.isfinite(box_lo), axis=-1) & ~missed
    span = np.where(ok[..., None], box_hi - box_lo, 0.0)
    pad = 0.15 * span + rng.normal(scale=0.03, size=span.shape) * span
    box = np.where(ok[..., None], np.concatenate([box_lo - pad, box_hi + pad], axis=-1), 0.0)
    mean_conf = np.where(detected, conf, 0.0).sum(-1) / np.maximum(detected.sum(-1), 1)
    box_score = np.where(ok, np.clip(mean_conf + rng.normal(scale=0.05, size=mean_conf.shape), 0.05, 1.0), 0.0)
    uv = np.where(conf[..., None] > 0, uv, 0.0)
    return {"uv": uv, "conf": conf, "box": box, "box_score": box_score}


def simulate_detectors(
    rng: np.random.Generator, rig: StereoRig, joints_rig: np.ndarray, visibility: np.ndarray, preset: str = "default"
) -> dict[str, np.ndarray]:
    """Both detectors on one hand, stacked on a leading detector axis (the keypoints.npz layout)."""
    if preset not in PRESETS:
        raise ValueError(f"unknown detector preset {preset!r}; choose one of {sorted(PRESETS)}")
    X_rig = jnp.asarray(joints_rig, jnp.result_type(float))
    uv_true = np.moveaxis(np.asarray(rig.project(X_rig), np.float64), 0, 1)  # (T, 2, 21, 2)
    in_image = np.moveaxis(np.asarray(rig.is_visible(X_rig)), 0, 1)  # (T, 2, 21)
    runs = [simulate(rng, uv_true, visibility, in_image, (rig.left.width, rig.left.height), m) for m in PRESETS[preset]]
    return {k: np.stack([r[k] for r in runs]).astype(np.float32) for k in runs[0]}
