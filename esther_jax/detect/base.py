"""What a real 2D hand keypoint detector returns, and the interface every adapter follows.

A detector looks at one image at a time and returns the hands it found, each as 21
keypoints in our order (docs/architecture.md, "Conventions"; MediaPipe's order) in the
pixel-centre convention of `esther_jax.cameras` (the image spans -0.5 <= u < W - 0.5),
a per-keypoint confidence in [0, 1], a box and a hand score. It does not decide which
hand is the left one: that is `handedness.assign_hands`, from stereo geometry and
time, with the detector's own left/right guess as weak evidence only.

Adapters: `MediaPipeHands` (embedded, offline), and ONNX models the user owns:
`OnnxPoseDetector` (YOLO-pose style) and `OnnxTopDownPose` (ViTPose style, on another
detector's boxes). Anything with `name`, `detect(image, timestamp_s)`
and `close()` plugs into `detect_clip` (one instance per view, as trackers keep state).
"""

import dataclasses
from typing import Protocol, runtime_checkable

import numpy as np

NUM_KEYPOINTS = 21


@dataclasses.dataclass(frozen=True)
class HandDetection:
    """One hand found in one image (pixels of the image given to the detector)."""

    uv: np.ndarray
    """(21, 2) keypoints (px, pixel-centre convention), our keypoint order."""
    conf: np.ndarray
    """(21,) per-keypoint confidence in [0, 1] (0: not located)."""
    box: np.ndarray
    """(4,) hand box x0, y0, x1, y1 (px)."""
    score: float
    """Hand score in [0, 1]."""
    chirality: float = 0.0
    """Geometric handedness evidence from the detector's own 3D estimate (`handedness.chirality`
    of its 3D keypoints): > 0 a right hand, < 0 a left hand, 0 none; the magnitude is the
    signed finger curl relative to the palm normal (unitless, ~0.3 for a relaxed hand)."""
    label: int = 0
    """The detector's own left/right claim: +1 right, -1 left, 0 none."""
    label_score: float = 0.0
    """The detector's confidence in `label`, in [0, 1]."""

    def __post_init__(self):
        uv, conf, box = np.asarray(self.uv, np.float64), np.asarray(self.conf, np.float64), np.asarray(self.box, np.float64)
        if uv.shape != (NUM_KEYPOINTS, 2) or conf.shape != (NUM_KEYPOINTS,) or box.shape != (4,):
            raise ValueError(f"a HandDetection holds uv (21, 2), conf (21,), box (4,); got {uv.shape}, {conf.shape}, {box.shape}")
        object.__setattr__(self, "uv", uv)
        object.__setattr__(self, "conf", np.clip(conf, 0.0, 1.0))
        object.__setattr__(self, "box", box)


@runtime_checkable
class KeypointDetector(Protocol):
    """A 2D hand keypoint detector. One instance per video stream (trackers keep state
    between calls; timestamps must increase)."""

    name: str

    def detect(self, image: np.ndarray, timestamp_s: float) -> list[HandDetection]:
        """Hands in `image`, (H, W, 3) RGB or (H, W) grey uint8, taken at `timestamp_s` (s)."""
        ...

    def close(self) -> None:
        """Release the detector's resources."""
        ...


def keypoint_box(uv: np.ndarray, conf: np.ndarray, padding: float = 0.15) -> np.ndarray:
    """The box of the located keypoints (conf > 0), widened by `padding` of its size on
    each side (x0, y0, x1, y1 px); NaN when no keypoint is located."""
    located = uv[np.asarray(conf) > 0]
    if located.size == 0:
        return np.full(4, np.nan)
    lo, hi = located.min(axis=0), located.max(axis=0)
    pad = padding * (hi - lo)
    return np.concatenate([lo - pad, hi + pad])


def unmirror(hand: HandDetection, width: int) -> HandDetection:
    """A hand found in the left-right mirror of a `width` px wide image, in the image
    itself: u -> W - 1 - u (pixel centres), the box's sides swapped, and the handedness
    evidence negated (a mirrored right hand looks like a left one)."""
    uv = hand.uv * np.array([-1.0, 1.0]) + np.array([width - 1.0, 0.0])
    x0, y0, x1, y1 = hand.box
    return dataclasses.replace(
        hand, uv=uv, box=np.array([width - 1.0 - x1, y0, width - 1.0 - x0, y1]), chirality=-hand.chirality, label=-hand.label
    )


def same_hand(a: np.ndarray, b: np.ndarray) -> bool:
    """Whether keypoints `a` and `b` (21, 2) px are one hand: over the keypoints located
    (finite) in both, the median distance is under a quarter of the longer side of the
    larger of the two keypoint extents. False when none is located in both."""
    both = np.all(np.isfinite(a), axis=-1) & np.all(np.isfinite(b), axis=-1)
    if not both.any():
        return False
    a, b = a[both], b[both]
    size = max(np.ptp(a, axis=0).max(), np.ptp(b, axis=0).max())
    return bool(np.median(np.linalg.norm(a - b, axis=-1)) < 0.25 * size)


def merge_mirror_pass(direct: list[HandDetection], mirrored: list[HandDetection], max_hands: int) -> list[HandDetection]:
    """One list of hands from a detector's two looks at an image: `direct`, and `mirrored`
    (found in the image's mirror, already `unmirror`ed). The direct look is the answer: its
    hands are kept as found (its `max_hands` highest scores), and the mirrored look's hands
    that are `same_hand` as none of them fill the slots left, highest scores first.

    Why a second look: a detector need not be mirror-symmetric (MediaPipe is not:
    `mediapipe`'s module docstring, "Two looks"). Where both looks find a hand its keypoints
    are not averaged: on the real video of the detector tests (hands ~280 px tall) the direct
    look reproduces MediaPipe's reference output (0.35 px at the median frame, largest
    coordinate error) and the mirror look is 10.7 px from it; no real ground truth here says
    which look is nearer the hand."""
    kept = sorted(direct, key=lambda h: -h.score)[:max_hands]
    added = sorted((m for m in mirrored if not any(same_hand(m.uv, d.uv) for d in direct)), key=lambda h: -h.score)
    return kept + added[: max_hands - len(kept)]


def as_rgb(image: np.ndarray) -> np.ndarray:
    """(H, W, 3) contiguous uint8 RGB from an RGB or grey image (clear error otherwise)."""
    image = np.asarray(image)
    if image.dtype != np.uint8:
        raise ValueError(f"detectors take uint8 images, got dtype {image.dtype}")
    if image.ndim == 2:
        image = np.repeat(image[..., None], 3, axis=-1)
    if image.ndim != 3 or image.shape[-1] != 3:
        raise ValueError(f"detectors take (H, W, 3) RGB or (H, W) grey images, got shape {image.shape}")
    return np.ascontiguousarray(image)


@dataclasses.dataclass
class Candidates:
    """Every hand one detector found in a stereo clip, before left/right assignment:
    up to H hands per frame and view, in the order the detector returned them.

    Arrays: uv [T, 2, H, 21, 2] px (NaN in empty slots), conf [T, 2, H, 21], box
    [T, 2, H, 4] (NaN in empty slots), score [T, 2, H] (0: empty slot), chirality [T, 2, H],
    label [T, 2, H] (+1 right, -1 left, 0 none), label_score [T, 2, H]; views left, right.
    """

    uv: np.ndarray
    conf: np.ndarray
    box: np.ndarray
    score: np.ndarray
    chirality: np.ndarray
    label: np.ndarray
    label_score: np.ndarray

    @classmethod
    def empty(cls, num_frames: int, max_hands: int) -> "Candidates":
        T, H = num_frames, max_hands
        return cls(
            uv=np.full((T, 2, H, NUM_KEYPOINTS, 2), np.nan), conf=np.zeros((T, 2, H, NUM_KEYPOINTS)),
            box=np.full((T, 2, H, 4), np.nan), score=np.zeros((T, 2, H)), chirality=np.zeros((T, 2, H)),
            label=np.zeros((T, 2, H), np.int8), label_score=np.zeros((T, 2, H)),
        )  # fmt: skip

    def put(self, frame: int, view: int, hands: list[HandDetection]) -> None:
        """Store the hands of one frame and view (the H highest-scoring ones)."""
        for slot, hand in enumerate(sorted(hands, key=lambda h: -h.score)[: self.max_hands]):
            self.uv[frame, view, slot] = hand.uv
            self.conf[frame, view, slot] = hand.conf
            self.box[frame, view, slot] = hand.box
            self.score[frame, view, slot] = max(hand.score, 1e-6)  # a found hand is never an empty slot
            self.chirality[frame, view, slot] = hand.chirality
            self.label[frame, view, slot] = hand.label
            self.label_score[frame, view, slot] = hand.label_score

    @property
    def num_frames(self) -> int:
        return self.score.shape[0]

    @property
    def max_hands(self) -> int:
        return self.score.shape[2]

    def arrays(self) -> dict[str, np.ndarray]:
        return {f.name: getattr(self, f.name) for f in dataclasses.fields(self)}
