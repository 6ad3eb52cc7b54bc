"""A YOLO-pose style hand keypoint model in ONNX (e.g. the paper's YOLO11-pose, exported by
its owner), run with onnxruntime, as a `KeypointDetector`.

The model file is the user's (nothing is downloaded). What we assume of it, which is
what Ultralytics' pose export produces for a one-class hand model with 21 keypoints
(its hand-keypoints data set uses MediaPipe's order, which is ours):

- one input, float32 NCHW RGB in [0, 1], square (its side is read from the model; a
  dynamic side is taken as 640), the image letterboxed into it (scaled to fit, centred,
  padded with grey 114);
- one output of shape (1, 5 + 21 * 3, N): box centre x, y, width, height (input pixels),
  hand score, then x, y, confidence per keypoint (input pixels, confidence in [0, 1]).

Candidates above `score_threshold` go through non-maximum suppression (IoU
`iou_threshold`) and are mapped back to the image's pixels (pixel-centre convention:
the letterbox maps u -> (u + 0.5) s + pad - 0.5). The model gives no handedness: left
and right come from stereo geometry and time (`handedness.assign_hands`).
"""

import pathlib

import cv2
import numpy as np

from .base import NUM_KEYPOINTS, HandDetection, as_rgb

_PAD_VALUE = 114
_DYNAMIC_SIDE = 640


class OnnxPoseDetector:
    name = "onnx"

    def __init__(self, model_path: str | pathlib.Path, *, score_threshold: float = 0.25, iou_threshold: float = 0.45, max_hands: int = 2):
        from .mediapipe import DetectorUnavailable

        try:
            import onnxruntime
        except ImportError as err:
            raise DetectorUnavailable(f"onnxruntime is not installed ({err}): python -m pip install -e '.[detect]'") from err
        path = pathlib.Path(model_path)
        if not path.is_file():
            raise FileNotFoundError(f"ONNX model {path} does not exist")
        try:
            self._session = onnxruntime.InferenceSession(str(path), providers=["CPUExecutionProvider"])
        except Exception as err:  # onnxruntime raises its own exception types for unreadable models
            raise ValueError(f"{path} is not a loadable ONNX model ({type(err).__name__}: {err})") from err
        inputs, outputs = self._session.get_inputs(), self._session.get_outputs()
        if len(inputs) != 1 or len(outputs) < 1:
            raise ValueError(f"{path}: expected one image input and a pose output, got {len(inputs)} inputs, {len(outputs)} outputs")
        shape = inputs[0].shape
        side = shape[-1] if isinstance(shape[-1], int) else _DYNAMIC_SIDE
        self._input, self.side = inputs[0].name, int(side)
        self.name = f"onnx:{path.name}"
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
