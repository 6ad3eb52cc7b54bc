"""Hand keypoint models in ONNX that the user owns (nothing is downloaded), run with
onnxruntime, as `KeypointDetector`s: the paper's two detectors (appendix A).

`OnnxPoseDetector`, a one-stage YOLO-pose style model (the paper's YOLO11-pose). What we
assume of it, which is what Ultralytics' pose export produces for a one-class hand model
with 21 keypoints (its hand-keypoints data set uses MediaPipe's order, which is ours):

- one input, float32 NCHW RGB in [0, 1], square (its side is read from the model; a
  dynamic side is taken as 640), the image letterboxed into it (scaled to fit, centred,
  padded with grey 114);
- one output of shape (1, 5 + 21 * 3, N): box centre x, y, width, height (input pixels),
  hand score, then x, y, confidence per keypoint (input pixels, confidence in [0, 1]).

Candidates above `score_threshold` go through non-maximum suppression (IoU
`iou_threshold`) and are mapped back to the image's pixels (pixel-centre convention:
the letterbox maps u -> (u + 0.5) s + pad - 0.5). The model gives no handedness: left
and right come from stereo geometry and time (`handedness.assign_hands`).

`OnnxTopDownPose`, a top-down heatmap model (the paper's ViTPose; HRNet and the like
export the same way from MMPose): it refines the hands another detector found (its box
source), one crop per box. What we assume of it, MMPose's top-down export:

- one input, float32 NCHW, (N or 1, 3, H, W) with a fixed H x W (e.g. 256 x 192 or
  256 x 256), RGB normalised with ImageNet's mean (123.675, 116.28, 103.53) and standard
  deviation (58.395, 57.12, 57.375) on the 0-255 scale;
- one output of heatmaps (N, 21, h, w), one per keypoint in our order, peaking near 1
  at the keypoint (the Gaussian targets of MSE training);
- MMPose's unbiased data processing (UDP, which ViTPose's configurations use): the box,
  widened to the input's aspect ratio and scaled by `box_padding` (1.25, MMPose's
  default), maps its centre to the input's centre pixel ((W - 1) / 2, (H - 1) / 2), its
  width to W - 1 input pixels and its height to H - 1; heatmap cell (x, y) sits at input
  pixel (x (W - 1) / (w - 1), y (H - 1) / (h - 1)).

Each heatmap's maximum is refined to sub-cell precision by DARK (a Newton step on the
logarithm of the Gaussian-blurred heatmap, `refine_peak`); the peak value is the
keypoint's confidence. The hand's box, score and handedness evidence are the box
source's.
"""

import pathlib

import cv2
import numpy as np
from jaxtyping import Float

from .base import NUM_KEYPOINTS, HandDetection, KeypointDetector, as_rgb

_PAD_VALUE = 114
_DYNAMIC_SIDE = 640
IMAGENET_MEAN = np.array([123.675, 116.28, 103.53], np.float32)
IMAGENET_STD = np.array([58.395, 57.12, 57.375], np.float32)


def _session(model_path: str | pathlib.Path):
    """An onnxruntime CPU session of a model file with one image input (clear errors for a
    missing runtime, a missing file, an unreadable model)."""
    from .mediapipe import DetectorUnavailable

    try:
        import onnxruntime
    except ImportError as err:
        raise DetectorUnavailable(f"onnxruntime is not installed ({err}): python -m pip install -e '.[detect]'") from err
    path = pathlib.Path(model_path)
    if not path.is_file():
        raise FileNotFoundError(f"ONNX model {path} does not exist")
    try:
        session = onnxruntime.InferenceSession(str(path), providers=["CPUExecutionProvider"])
    except Exception as err:  # onnxruntime raises its own exception types for unreadable models
        raise ValueError(f"{path} is not a loadable ONNX model ({type(err).__name__}: {err})") from err
    inputs, outputs = session.get_inputs(), session.get_outputs()
    if len(inputs) != 1 or len(outputs) < 1:
        raise ValueError(f"{path}: expected one image input and at least one output, got {len(inputs)} inputs, {len(outputs)} outputs")
    return session


class OnnxPoseDetector:
    name = "onnx"

    def __init__(self, model_path: str | pathlib.Path, *, score_threshold: float = 0.25, iou_threshold: float = 0.45, max_hands: int = 2):
        self._session = _session(model_path)
        image_input = self._session.get_inputs()[0]
        side = image_input.shape[-1] if isinstance(image_input.shape[-1], int) else _DYNAMIC_SIDE
        self._input, self.side = image_input.name, int(side)
        self.name = f"onnx:{pathlib.Path(model_path).name}"
        self.score_threshold, self.iou_threshold, self.max_hands = score_threshold, iou_threshold, max_hands

    def _letterbox(self, rgb: np.ndarray) -> tuple[np.ndarray, float, np.ndarray]:
        h, w = rgb.shape[:2]
        scale = self.side / max(h, w)
        nw, nh = int(round(w * scale)), int(round(h * scale))
        pad = np.array([(self.side - nw) / 2, (self.side - nh) / 2])
        canvas = np.full((self.side, self.side, 3), _PAD_VALUE, np.uint8)
        x0, y0 = int(np.floor(pad[0])), int(np.floor(pad[1]))
        canvas[y0 : y0 + nh, x0 : x0 + nw] = cv2.resize(rgb, (nw, nh), interpolation=cv2.INTER_LINEAR)
        return canvas, scale, np.array([x0, y0], np.float64)

    def detect(self, image: np.ndarray, timestamp_s: float = 0.0) -> list[HandDetection]:
        rgb = as_rgb(image)
        canvas, scale, pad = self._letterbox(rgb)
        blob = (canvas.astype(np.float32) / 255.0).transpose(2, 0, 1)[None]
        raw = np.asarray(self._session.run(None, {self._input: blob})[0])
        if raw.ndim != 3 or raw.shape[1] != 5 + 3 * NUM_KEYPOINTS:
            raise ValueError(f"{self.name}: expected an output of shape (1, {5 + 3 * NUM_KEYPOINTS}, N), got {raw.shape}")
        rows = raw[0].T  # (N, 68)
        rows = rows[rows[:, 4] >= self.score_threshold]
        if len(rows) == 0:
            return []
        boxes_xywh = np.concatenate([rows[:, :2] - rows[:, 2:4] / 2, rows[:, 2:4]], axis=1)
        keep = cv2.dnn.NMSBoxes(boxes_xywh.tolist(), rows[:, 4].tolist(), self.score_threshold, self.iou_threshold)
        keep = np.asarray(keep, int).reshape(-1)[: self.max_hands]
        back = lambda p: (p - pad) / scale  # noqa: E731  (input pixel -> image pixel; pixel-centre convention)
        hands = []
        for row in rows[keep]:
            kp = row[5:].reshape(NUM_KEYPOINTS, 3)
            box = np.concatenate([back(row[:2] - row[2:4] / 2 + 0.5) - 0.5, back(row[:2] + row[2:4] / 2 + 0.5) - 0.5])
            hands.append(HandDetection(uv=back(kp[:, :2] + 0.5) - 0.5, conf=kp[:, 2], box=box, score=float(np.clip(row[4], 0, 1))))
        return hands

    def close(self) -> None:
        self._session = None


def refine_peak(heatmap: Float[np.ndarray, "h w"], blur_kernel: int = 11) -> tuple[Float[np.ndarray, "2"], float]:
    """The maximum of one (h, w) heatmap to sub-cell precision (DARK, Zhang et al. 2020):
    the heatmap is blurred with a Gaussian of `blur_kernel` cells (odd; MMPose's value
    for 64 x 48 heatmaps), and one Newton step on its logarithm from the best cell moves
    to the peak of the locally fitted Gaussian. Returns ((2,) x, y in cells, the raw
    maximum). The step is skipped on the border and where the log is not concave."""
    y, x = np.unravel_index(int(np.argmax(heatmap)), heatmap.shape)
    peak = float(heatmap[y, x])
    h, w = heatmap.shape
    if not (0 < x < w - 1 and 0 < y < h - 1):
        return np.array([x, y], np.float64), peak
    blurred = cv2.GaussianBlur(heatmap.astype(np.float64), (blur_kernel, blur_kernel), 0)
    L = np.log(np.maximum(blurred[y - 1 : y + 2, x - 1 : x + 2], 1e-3))
    gradient = 0.5 * np.array([L[1, 2] - L[1, 0], L[2, 1] - L[0, 1]])
    dxy = 0.25 * (L[2, 2] - L[2, 0] - L[0, 2] + L[0, 0])
    hessian = np.array([[L[1, 2] - 2 * L[1, 1] + L[1, 0], dxy], [dxy, L[2, 1] - 2 * L[1, 1] + L[0, 1]]])
    if np.linalg.det(hessian) <= 1e-12 or hessian[0, 0] >= 0:  # not a maximum of a concave log
        return np.array([x, y], np.float64), peak
    step = np.clip(-np.linalg.solve(hessian, gradient), -1.0, 1.0)
    return np.array([x, y], np.float64) + step, peak


class OnnxTopDownPose:
    """A top-down heatmap hand model in ONNX (ViTPose and the like) on the boxes of a box
    source (module docstring for the model contract). `boxes` is any `KeypointDetector`
    (MediaPipe, a YOLO-pose model); its hands are re-estimated, one crop per box."""

    def __init__(self, model_path: str | pathlib.Path, boxes: KeypointDetector, *, box_padding: float = 1.25, blur_kernel: int = 11):
        if box_padding <= 0 or blur_kernel % 2 == 0:
            raise ValueError(f"box_padding must be > 0 and blur_kernel odd; got {box_padding}, {blur_kernel}")
        self._session = _session(model_path)
        image_input = self._session.get_inputs()[0]
        shape = image_input.shape
        fixed_channels = isinstance(shape[1], int) if len(shape) == 4 else False
        if len(shape) != 4 or not all(isinstance(d, int) for d in shape[2:]) or (fixed_channels and shape[1] != 3):
            raise ValueError(f"{model_path}: expected an input (N, 3, H, W) with a fixed H x W, got {shape}")
        self._input, self.input_hw = image_input.name, (int(shape[2]), int(shape[3]))
        self._batched = not isinstance(shape[0], int) or shape[0] > 1
        self.boxes, self.box_padding, self.blur_kernel = boxes, box_padding, blur_kernel
        self.name = f"vitpose:{pathlib.Path(model_path).name}@{boxes.name}"

    def crop_affine(self, box: Float[np.ndarray, "4"]) -> Float[np.ndarray, "2 3"]:
        """(2, 3) the affine map image px -> model input px of a hand box (x0, y0, x1, y1 px;
        UDP convention, module docstring)."""
        H, W = self.input_hw
        centre = 0.5 * (box[:2] + box[2:])
        size = np.maximum(box[2:] - box[:2], 1.0)
        if size[0] * H > size[1] * W:  # widen the box to the input's aspect ratio
            size = np.array([size[0], size[0] * H / W])
        else:
            size = np.array([size[1] * W / H, size[1]])
        scale = np.array([W - 1, H - 1]) / (size * self.box_padding)
        return np.concatenate([np.diag(scale), ((np.array([W, H]) - 1) / 2 - scale * centre)[:, None]], axis=1)

    def _heatmaps(self, blob: np.ndarray) -> np.ndarray:
        if self._batched:
            out = np.asarray(self._session.run(None, {self._input: blob})[0])
        else:
            out = np.concatenate([np.asarray(self._session.run(None, {self._input: b[None]})[0]) for b in blob])
        if out.ndim != 4 or out.shape[:2] != (len(blob), NUM_KEYPOINTS) or min(out.shape[2:]) < 2:
            raise ValueError(f"{self.name}: expected heatmaps of shape ({len(blob)}, {NUM_KEYPOINTS}, h, w), got {out.shape}")
        return out

    def detect(self, image: np.ndarray, timestamp_s: float = 0.0) -> list[HandDetection]:
        rgb = as_rgb(image)
        found = [h for h in self.boxes.detect(image, timestamp_s) if np.all(np.isfinite(h.box))]
        if not found:
            return []
        H, W = self.input_hw
        affines = [self.crop_affine(h.box) for h in found]
        crops = [cv2.warpAffine(rgb, M, (W, H), flags=cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT) for M in affines]
        blob = ((np.stack(crops).astype(np.float32) - IMAGENET_MEAN) / IMAGENET_STD).transpose(0, 3, 1, 2)
        heatmaps = self._heatmaps(np.ascontiguousarray(blob))
        h, w = heatmaps.shape[2:]
        cells_to_input = np.array([(W - 1) / (w - 1), (H - 1) / (h - 1)])
        hands = []
        for source, M, maps in zip(found, affines, heatmaps):
            peaks = [refine_peak(m, self.blur_kernel) for m in maps]
            uv_input = np.stack([p for p, _ in peaks]) * cells_to_input
            uv = (uv_input - M[:, 2]) / np.diag(M)
            conf = np.clip([c for _, c in peaks], 0.0, 1.0)
            hands.append(HandDetection(uv, conf, source.box, source.score, source.chirality, source.label, source.label_score))
        return hands

    def close(self) -> None:
        self.boxes.close()
        self._session = None
