"""`esther detect`: stereo videos (or image folders) + `rig.json` -> a clip folder.

    detect_clip(left, right, rig, out)  ->  out/rig.json, out/meta.json,
                                            out/hands/<side>/keypoints.npz  (D = one per detector),
                                            out/video/left.mp4, right.mp4    (linked, copied or encoded)

Then `esther label out` works unchanged. Into an existing clip folder (an imported HOT3D
clip, say), the keypoints and the detection record are added and the rest is kept. Per detector, every frame of both views is
detected (one detector instance per view: trackers keep state); fisheye views are first
undistorted to the axis-aligned wide pinhole of the offbb strategies (appendix F / M:
detectors are trained on perspective images), and the keypoints and boxes are mapped
back to the original camera exactly (`camera.project(wide.unproject(uv))`). Left and
right hands are assigned by `handedness.assign_hands`.

Long runs are safe: every `checkpoint_every` frames are saved once, as a chunk of `out/.detect/`
(atomic writes) and a rerun continues from there; a lock stops a second `esther detect`
writing the same clip; the clip's files appear only once complete.

Many recordings: `detect_recordings(recordings, out_dir)` (`esther detect REC... --out DIR`,
one Ray task per recording with `--ray`) runs `detect_clip` on each recording folder
(`recording_views`: `rig.json` beside the left and right views) into `out_dir/<recording>`,
reporting a failing recording and going on, and skipping finished ones with `resume`.
"""

import dataclasses
import os
import pathlib
import shutil

import cv2
import jax
import jax.numpy as jnp
import numpy as np
from tqdm import tqdm

from .. import clips
from ..cameras import AbstractCamera, PinholeCamera, StereoRig, rig_name
from ..crops import RECTIFICATION_STRATEGIES, Crop, box_outline, rectification_map, wide_pinhole
from ..files import check_out_dir, exclusive_lock, named_folders
from .base import Candidates, HandDetection, KeypointDetector
from .handedness import assign_hands

IMAGE_SUFFIXES = (".png", ".jpg", ".jpeg", ".bmp", ".tif", ".tiff", ".webp")
VIDEO_SUFFIXES = (".mp4", ".avi", ".mov", ".mkv")
"""A recording's view as one video file: `left.mp4`, `right.mov`, ... (`recording_views`)."""


class FrameSource:
    """The frames of one view: a video file or a folder of images (sorted by name).
    Iterating yields (H, W, 3) RGB or (H, W) grey uint8 frames."""

    def __init__(self, path: str | pathlib.Path):
        self.path = pathlib.Path(path)
        if self.path.is_dir():
            self.images = sorted(p for p in self.path.iterdir() if p.suffix.lower() in IMAGE_SUFFIXES)
            if not self.images:
                raise clips.ClipFormatError(f"{self.path} holds no images ({', '.join(IMAGE_SUFFIXES)})")
        elif self.path.is_file():
            self.images = None
        else:
            raise clips.ClipFormatError(f"{self.path} does not exist (give a video file or a folder of images)")

    @property
    def is_video(self) -> bool:
        return self.images is None

    def fps(self) -> float | None:
        """The video's frame rate (None for image folders)."""
        if not self.is_video:
            return None
        capture = cv2.VideoCapture(str(self.path))
        fps = capture.get(cv2.CAP_PROP_FPS)
        capture.release()
        return float(fps) if fps and np.isfinite(fps) and fps > 0 else None

    def estimated_length(self) -> int | None:
        if not self.is_video:
            return len(self.images)
        capture = cv2.VideoCapture(str(self.path))
        count = int(capture.get(cv2.CAP_PROP_FRAME_COUNT))
        capture.release()
        return count if count > 0 else None

    def __iter__(self):
        if self.is_video:
            yield from clips.iter_video(self.path)
            return
        for path in self.images:
            image = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
            if image is None:
                raise clips.ClipFormatError(f"{path} cannot be read as an image")
            if image.dtype != np.uint8:
                raise clips.ClipFormatError(f"{path}: images must be 8-bit, got {image.dtype}")
            if image.ndim == 3 and image.shape[2] == 4:
                image = image[..., :3]
            yield np.ascontiguousarray(image[..., ::-1]) if image.ndim == 3 else image


class _ViewGeometry:
    """How a view's frames reach the detector and its keypoints come back."""

    def __init__(self, camera: AbstractCamera, strategy: str):
        self.camera = camera
        self.rectified = not isinstance(camera, PinholeCamera)
        if self.rectified:
            if not strategy.startswith("offbb"):
                raise ValueError(f"detection rectifies whole frames: use an offbb strategy, not {strategy!r}")
            self.wide = wide_pinhole(camera, float(strategy[len("offbb"):]))
            table = np.asarray(rectification_map(camera, Crop(self.wide, jnp.eye(3, dtype=self.wide.fx.dtype))), np.float32)
            self.map_x, self.map_y = np.ascontiguousarray(table[..., 0]), np.ascontiguousarray(table[..., 1])
            self._back = jax.jit(lambda uv, box: camera.project(self.wide.unproject(jnp.concatenate([uv, box_outline(box)]))))

    def image(self, frame: np.ndarray) -> np.ndarray:
        if (frame.shape[1], frame.shape[0]) != (self.camera.width, self.camera.height):
            raise ValueError(
                f"a frame is {frame.shape[1]}x{frame.shape[0]} px but the rig's camera is {self.camera.width}x{self.camera.height}"
            )
        if not self.rectified:
            return frame
        return cv2.remap(frame, self.map_x, self.map_y, cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT)

    def back(self, hand: HandDetection) -> HandDetection:
        """A detection on the rectified image, in the original camera's pixels."""
        if not self.rectified:
            return hand
        mapped = np.asarray(self._back(jnp.asarray(hand.uv), jnp.asarray(hand.box)), np.float64)
        uv, box_points = mapped[: len(hand.uv)], mapped[len(hand.uv) :]
        w, h = self.camera.width, self.camera.height
        inside = (uv[:, 0] >= -0.5) & (uv[:, 0] < w - 0.5) & (uv[:, 1] >= -0.5) & (uv[:, 1] < h - 0.5)
        box = np.concatenate([box_points.min(axis=0), box_points.max(axis=0)])
        return HandDetection(uv, hand.conf * inside, box, hand.score, hand.chirality, hand.label, hand.label_score)


def make_detector(name: str) -> KeypointDetector:
    """A detector by name: `mediapipe` (with its mirror pass, `MediaPipeHands`);
    `mediapipe:direct` (without it: half the time); `onnx:PATH` (a YOLO-pose style ONNX model);
    `vitpose:PATH` (a top-down heatmap ONNX model, ViTPose and the like) on MediaPipe's
    boxes, or `vitpose:PATH@BOXES` on the boxes of the detector named BOXES (e.g.
    `vitpose:vitpose_hand.onnx@onnx:yolo11_hand.onnx`, the paper's pair)."""
    if name == "mediapipe":
        from .mediapipe import MediaPipeHands

        return MediaPipeHands(video=True)
    if name == "mediapipe:direct":
        from .mediapipe import MediaPipeHands

        return MediaPipeHands(video=True, mirror_pass=False)
    if name.startswith("onnx:"):
        from .onnx import OnnxPoseDetector

        return OnnxPoseDetector(name[len("onnx:") :])
    if name.startswith("vitpose:"):
        from .onnx import OnnxTopDownPose

        model, _, boxes = name[len("vitpose:") :].partition("@")
        if boxes.startswith("vitpose:"):
            raise ValueError(f"{name!r}: the box source of a top-down model must find hands itself (mediapipe, mediapipe:direct or onnx:PATH)")
        box_source = make_detector(boxes or "mediapipe")
        try:
            return OnnxTopDownPose(model, box_source)
        except Exception:
            box_source.close()
            raise
    raise ValueError(
        f"unknown detector {name!r}; use 'mediapipe', 'mediapipe:direct', 'onnx:MODEL.onnx' or 'vitpose:MODEL.onnx[@BOX_DETECTOR]'"
    )


def _state_dir(out: pathlib.Path, index: int) -> pathlib.Path:
    return out / ".detect" / f"detector{index}"


def _load_chunks(folder: pathlib.Path, name: str, max_hands: int) -> list[Candidates]:
    """The saved chunks of a detector, in frame order (each written once, atomically);
    none when they were made by another detector or setting (that detector starts again)."""
    parts = []
    for path in sorted(folder.glob("frames_*.npz")):
        with np.load(path, allow_pickle=False) as data:
            if str(data["detector"]) != name or data["score"].shape[2] != max_hands:
                return []
            parts.append(Candidates(**{f.name: data[f.name] for f in dataclasses.fields(Candidates)}))
    return parts


def _save_chunk(folder: pathlib.Path, name: str, start: int, chunk: Candidates) -> None:
    clips.save_npz(folder / f"frames_{start:08d}.npz", detector=np.asarray(name), **chunk.arrays())


def _concatenate(parts: list[Candidates]) -> Candidates:
    return Candidates(**{k: np.concatenate([p.arrays()[k] for p in parts]) for k in parts[0].arrays()})


def _run_detector(
    index: int, name: str, factory, sources: tuple[FrameSource, FrameSource], views: tuple[_ViewGeometry, _ViewGeometry],
    fps: float, out: pathlib.Path, max_hands: int, checkpoint_every: int, progress: bool,
) -> Candidates:  # fmt: skip
    state = _state_dir(out, index)
    parts = _load_chunks(state, name, max_hands)
    start = sum(p.num_frames for p in parts)
    chunk = Candidates.empty(checkpoint_every, max_hands)
    filled = 0
    detectors = [factory()]  # one per view (video mode tracks each view's hands)
    try:
        detectors.append(factory())
    except BaseException:
        detectors[0].close()
        raise
    bar = tqdm(total=sources[0].estimated_length(), initial=start, desc=f"detect {name}", unit="frame", disable=not progress)
    try:
        for frame_index, frames in enumerate(zip(*sources, strict=True)):
            if frame_index < start:
                continue
            for v, (detector, view, frame) in enumerate(zip(detectors, views, frames)):
                hands = detector.detect(view.image(frame), frame_index / fps)
                chunk.put(filled, v, [view.back(h) for h in hands])
            filled += 1
            bar.update(1)
            if filled == checkpoint_every:
                _save_chunk(state, name, frame_index + 1 - filled, chunk)
                parts.append(chunk)
                chunk, filled = Candidates.empty(checkpoint_every, max_hands), 0
    except ValueError as err:
        if "zip()" in str(err):
            raise clips.ClipFormatError(f"{sources[0].path} and {sources[1].path} hold different numbers of frames") from err
        raise
    finally:
        bar.close()
        for detector in detectors:
            detector.close()
    if filled:  # the tail is saved too: a rerun after a later failure detects nothing again
        tail = Candidates(**{k: v[:filled] for k, v in chunk.arrays().items()})
        _save_chunk(state, name, sum(p.num_frames for p in parts), tail)
        parts.append(tail)
    if not parts:
        raise clips.ClipFormatError(f"{sources[0].path} holds no frames")
    return _concatenate(parts)


def detect_clip(
    left: str | pathlib.Path,
    right: str | pathlib.Path,
    rig: StereoRig | str | pathlib.Path,
    out: str | pathlib.Path,
    *,
    detectors: tuple[str, ...] = ("mediapipe",),
    fps: float | None = None,
    strategy: str = "offbb120",
    max_hands: int = 2,
    videos: str = "link",
    checkpoint_every: int = 100,
    progress: bool = True,
    factories: dict | None = None,
) -> dict:
    """Detect hands in a stereo sequence and write the clip folder `out` (module docstring).

    Args:
        left, right: each view's video file or image folder (same number of frames).
        rig: the rig, or its `rig.json` (whose "name" the clip's `rig.json` keeps).
        detectors: detector names (`make_detector`); each is one entry of the D axis.
        fps: frame rate; read from the videos when omitted (required for image folders).
        strategy: offbb120 / offbb90 / offbb150, the rectification of fisheye views.
        videos: `link` (symlink the videos), `copy`, or `encode` (write mp4s; image folders
            are always encoded).
        factories: optional {name: callable returning a KeypointDetector}, for detectors
            that `make_detector` does not know (e.g. your own adapter).
    Returns:
        the report written into `meta.json` under `"detect"`.
    """
    if strategy not in RECTIFICATION_STRATEGIES or not strategy.startswith("offbb"):
        raise ValueError(f"strategy must be offbb120, offbb90 or offbb150, got {strategy!r}")
    if videos not in ("link", "copy", "encode"):
        raise ValueError(f"videos must be 'link', 'copy' or 'encode', got {videos!r}")
    if not detectors:
        raise ValueError("give at least one detector")
    display_name = "rig" if isinstance(rig, StereoRig) else rig_name(rig)
    rig = rig if isinstance(rig, StereoRig) else StereoRig.from_json(rig)
    sources = (FrameSource(left), FrameSource(right))
    if fps is None:
        fps = sources[0].fps()
        if fps is None:
            raise ValueError("--fps is needed: image folders (and some videos) do not say their frame rate")
    out = check_out_dir(out)
    with exclusive_lock(out / ".detect.lock", wait=False) as held:
        if not held:
            raise RuntimeError(f"another esther detect is writing {out}; wait for it or choose another --out")
        views = (_ViewGeometry(rig.left, strategy), _ViewGeometry(rig.right, strategy))
        factories = {**{name: (lambda name=name: make_detector(name)) for name in detectors}, **(factories or {})}
        results = [
            _run_detector(i, name, factories[name], sources, views, fps, out, max_hands, checkpoint_every, progress)
            for i, name in enumerate(detectors)
        ]
        T = results[0].num_frames
        assigned = [assign_hands(c, rig) for c in results]
        sides = [s for s in clips.SIDES if any(s in hands for hands, _ in assigned)]
        for side in sides:
            per_detector = [hands.get(side) for hands, _ in assigned]
            template = next(h for h in per_detector if h is not None)
            empty = {"uv": np.full_like(template["uv"], np.nan), "conf": np.zeros_like(template["conf"]),
                     "box": np.full_like(template["box"], np.nan), "box_score": np.zeros_like(template["box_score"])}  # fmt: skip
            stacked = {k: np.stack([(h if h is not None else empty)[k] for h in per_detector]).astype(np.float32) for k in empty}
            clips.save_npz(clips.hand_file(out, side, "keypoints"), **stacked)
        for side in clips.SIDES:
            if side not in sides:
                clips.hand_file(out, side, "keypoints").unlink(missing_ok=True)
        _write_videos(sources, out, fps, videos)
        rig.to_json(out / "rig.json", display_name)
        report = {
            "detectors": list(detectors),
            "rectification": strategy if any(v.rectified for v in views) else None,
            "sides": sides,
            "frames_with_hands": {name: int(np.sum(c.score.max(axis=(1, 2)) > 0)) for name, c in zip(detectors, results)},
            "handedness": {name: r for name, (_, r) in zip(detectors, assigned)},
        }
        previous = clips.read_meta(out) if (out / "meta.json").is_file() else {}  # e.g. an imported HOT3D clip's record
        if previous and previous["num_frames"] != T:
            raise clips.ClipFormatError(f"{out} holds a clip of {previous['num_frames']} frames; the videos have {T}")
        clips.write_meta(out, **{**previous, "fps": float(fps), "num_frames": int(T), "detect": report,
                                 "frames": {"left": str(sources[0].path), "right": str(sources[1].path)}})  # fmt: skip
        shutil.rmtree(out / ".detect", ignore_errors=True)
    return report


def _write_videos(sources: tuple[FrameSource, FrameSource], out: pathlib.Path, fps: float, mode: str) -> None:
    for view, source in zip(("left", "right"), sources):
        target = out / "video" / f"{view}.mp4"
        target.parent.mkdir(parents=True, exist_ok=True)
        if target.exists() and target.resolve() == source.path.resolve():
            continue  # detecting the clip's own videos
        if source.is_video and source.path.suffix.lower() == ".mp4" and mode in ("link", "copy"):
            tmp = target.with_name(f".{view}.partial.mp4")
            tmp.unlink(missing_ok=True)
            if mode == "link":
                os.symlink(source.path.resolve(), tmp)
            else:
                shutil.copyfile(source.path, tmp)
            os.replace(tmp, target)
        else:
            clips.write_video(target, iter(source), fps)


def recording_views(recording: str | pathlib.Path) -> tuple[pathlib.Path, pathlib.Path, pathlib.Path]:
    """A recording folder's (left view, right view, rig.json): each view a folder of
    images (`left/`, `right/`) or one video file (`left.mp4`, ..., `VIDEO_SUFFIXES`),
    beside the rig's `rig.json`. `ClipFormatError` naming what is missing or ambiguous."""
    folder = pathlib.Path(recording)
    if not folder.is_dir():
        raise clips.ClipFormatError(f"{folder} is not a folder (a recording holds rig.json and its left and right views)")
    rig = folder / "rig.json"
    if not rig.is_file():
        raise clips.ClipFormatError(f"{folder} has no rig.json (the calibration of both views)")
    views = []
    for view in ("left", "right"):
        found = [p for p in (folder / view, *(folder / f"{view}{suffix}" for suffix in VIDEO_SUFFIXES)) if p.exists()]
        if not found:
            raise clips.ClipFormatError(f"{folder} has no {view} view: a folder {view}/ of images or a video {view}.mp4 ({', '.join(VIDEO_SUFFIXES)})")
        if len(found) > 1:
            raise clips.ClipFormatError(f"{folder}: its {view} view is ambiguous ({', '.join(p.name for p in found)}); keep one")
        views.append(found[0])
    return views[0], views[1], rig


def _detected_as(clip: pathlib.Path, detectors: tuple[str, ...], strategy: str, fps: float | None) -> bool:
    """True when `clip` holds a finished detection as this run would make it: by the same
    detectors, the same crop strategy where its views were rectified, the same frame
    rate where one is given, and no detection in progress (`.detect/`)."""
    if not (clip / "meta.json").is_file() or (clip / ".detect").exists():
        return False
    meta = clips.read_meta(clip)
    report = meta.get("detect", {})
    return (
        report.get("detectors") == list(detectors)
        and report.get("rectification") in (None, strategy)
        and (fps is None or meta.get("fps") == float(fps))
    )


def detect_recordings(
    recordings: list[str | pathlib.Path],
    out_dir: str | pathlib.Path,
    *,
    detectors: tuple[str, ...] = ("mediapipe",),
    fps: float | None = None,
    strategy: str = "offbb120",
    videos: str = "link",
    resume: bool = False,
    progress: bool = True,
    factories: dict | None = None,
) -> dict:
    """`detect_clip` on every recording folder (`recording_views`) into
    `out_dir/<recording name>`, the batch form of `esther detect` (and a Ray task per
    recording with `--ray`: `esther_jax.cluster.map_clips`).

    A recording that fails (a missing view, an unreadable video or rig.json, views of
    different lengths, another process writing its clip) is reported under "failed" and
    the others go on; a detector that is not installed (`DetectorUnavailable`) stops the
    run. With `resume`, a recording whose clip is complete (its `meta.json` records a
    detection by the same detectors, crop strategy and frame rate) is skipped; an
    interrupted one continues from its saved chunks either way. Recordings are keyed by
    folder name (`files.named_folders`). Other arguments: `detect_clip`'s.

    Returns:
        {"detected": [{"clip", "sides", "frames"}], "skipped": [names], "failed": [{"clip", "error"}], "out": str}.
    """
    from .mediapipe import DetectorUnavailable

    recordings = named_folders(recordings, "recordings")
    out_dir = check_out_dir(out_dir)
    result: dict = {"detected": [], "skipped": [], "failed": [], "out": str(out_dir)}
    for recording in tqdm(recordings, desc="detect", unit="recording", disable=not progress or len(recordings) < 2):
        clip = out_dir / recording.name
        try:
            if resume and _detected_as(clip, detectors, strategy, fps):
                result["skipped"].append(recording.name)
                continue
            left, right, rig = recording_views(recording)
            report = detect_clip(left, right, rig, clip, detectors=detectors, fps=fps, strategy=strategy, videos=videos,
                                 progress=progress and len(recordings) == 1, factories=factories)  # fmt: skip
        except DetectorUnavailable:
            raise
        except (clips.ClipFormatError, OSError, ValueError, RuntimeError) as err:
            result["failed"].append({"clip": recording.name, "error": f"{type(err).__name__}: {err}"})
            continue
        result["detected"].append({"clip": recording.name, "sides": report["sides"], "frames": clips.read_meta(clip)["num_frames"]})
    return result
