"""esther_jax.detect: detector adapters, left/right assignment, `esther detect` clip folders.

The clip-folder path is tested with a ground-truth detector (the synthetic engine's
exact joints, projected): sides must come out right although its labels are wrong on
purpose, fisheye keypoints must map back to the original camera exactly, and an
interrupted run must resume without redoing frames. MediaPipe is tested on real pixels
(`../shared/data/mediapipe_oracle/`) when it is installed and the data is present.
"""

import dataclasses
import importlib
import importlib.util
import json
import pathlib
import shutil
from types import SimpleNamespace

import cv2
import jax
import jax.numpy as jnp
import numpy as np
import pytest

from esther_jax import cameras, cli, clips, crops
from esther_jax.data import motion, synth
from esther_jax.detect import Candidates, HandDetection, assign_hands, chirality, detect_clip
from esther_jax.detect.base import keypoint_box, merge_mirror_pass, same_hand, unmirror
from esther_jax.files import exclusive_lock

from .helpers import mixed_rig

FRAMES = 8
ORACLE = pathlib.Path(__file__).resolve().parents[2] / "shared" / "data" / "mediapipe_oracle"


def _mediapipe_unavailable() -> str | None:
    """Why the MediaPipe detector cannot be imported (None when it can): the tests skip only
    then. A package that is installed but cannot be imported (a run-time import missing
    from the detect extra) is also test_dependencies.py's failure, naming the module."""
    from esther_jax.detect.mediapipe import DetectorUnavailable, bundled_model_path

    try:
        importlib.import_module("mediapipe.tasks.python.vision")
        bundled_model_path()
    except (ImportError, DetectorUnavailable) as err:
        return f"the MediaPipe detector cannot be imported ({err})"
    return None


MEDIAPIPE_UNAVAILABLE = _mediapipe_unavailable()
HAVE_MEDIAPIPE = MEDIAPIPE_UNAVAILABLE is None
needs_mediapipe = pytest.mark.skipif(not HAVE_MEDIAPIPE, reason=MEDIAPIPE_UNAVAILABLE or "")
needs_oracle = pytest.mark.skipif(not ORACLE.is_dir(), reason="../shared/data/mediapipe_oracle is absent")
HAVE_ONNX = importlib.util.find_spec("onnx") is not None and importlib.util.find_spec("onnxruntime") is not None
needs_onnx = pytest.mark.skipif(not HAVE_ONNX, reason="onnx and onnxruntime (the test and detect extras) are not installed")


@pytest.fixture(scope="module")
def two_hands():
    cfg = synth.SynthConfig(
        num_frames=FRAMES, detector_preset="clean", motion_config=motion.MotionConfig(two_hands_probability=1.0, leave_view_probability=0.0)
    )
    clip = synth.make_clip(5, 0, cfg)
    assert set(clip.gt) == {"right", "left"}
    return {side: clip.gt[side]["joints"].astype(np.float64) for side in clip.gt}


class GroundTruthDetector:
    """Detects the synthetic hands exactly (projected joints), in the image it is given:
    the view's own pixels, or the rectified wide pinhole's for a fisheye view (as
    `detect_clip` gives it; `rectified=False`: the fisheye's own pixels). Its labels
    are wrong on purpose and it has no 3D, so only stereo geometry can tell the sides."""

    name = "truth"

    def __init__(self, joints: dict, rig: cameras.StereoRig, view: int, calls: list, fail_after: int | None = None, rectified: bool = True):
        self.joints, self.rig, self.view, self.calls, self.fail_after = joints, rig, view, calls, fail_after
        camera = rig.left if view == 0 else rig.right
        self.camera = camera if isinstance(camera, cameras.PinholeCamera) or not rectified else crops.wide_pinhole(camera, 120.0)
        self.frame = 0

    def detect(self, image, timestamp_s):
        if self.fail_after is not None and len(self.calls) >= self.fail_after:
            raise KeyboardInterrupt
        self.calls.append((self.view, timestamp_s))
        t = int(round(timestamp_s * 30))
        hands = []
        for side, joints in self.joints.items():
            uv = np.asarray(self.camera.project(self.rig.to_views(jnp.asarray(joints[t]))[self.view]), np.float64)
            conf = np.ones(21)
            hands.append(HandDetection(uv, conf, keypoint_box(uv, conf), 0.9, label=-1 if side == "right" else 1, label_score=0.9))
        return hands

    def close(self):
        pass


def _folders(tmp_path: pathlib.Path, rig: cameras.StereoRig) -> tuple[pathlib.Path, pathlib.Path]:
    out = []
    for view, camera in (("left", rig.left), ("right", rig.right)):
        folder = tmp_path / f"frames_{view}"
        folder.mkdir()
        for t in range(FRAMES):
            cv2.imwrite(str(folder / f"{t:05d}.png"), np.full((camera.height, camera.width), 40 + t, np.uint8))
        out.append(folder)
    return out[0], out[1]


def _factory(joints, rig, calls, fail_after=None):
    views = iter(range(100))
    return lambda: GroundTruthDetector(joints, rig, next(views) % 2, calls, fail_after)


def test_chirality_is_positive_for_right_hands_and_flips_with_mirroring(two_hands):
    right, left = two_hands["right"], two_hands["left"]
    assert np.mean(chirality(right) > 0) > 0.8 and np.mean(chirality(left) < 0) > 0.8
    mirror = np.array([-1.0, 1.0, 1.0])
    np.testing.assert_allclose(chirality(right * mirror), -chirality(right), atol=1e-12)
    assert chirality(np.full((21, 3), np.nan)) == 0.0


def test_the_mirror_pass_adds_only_the_hands_the_direct_look_missed():
    rng = np.random.default_rng(0)
    height, width = 48, 80

    def hand(centre, score, size=20.0, wrist=None):
        uv = centre + size * rng.uniform(-0.5, 0.5, (21, 2))
        uv[0] = uv[0] if wrist is None else wrist
        return HandDetection(uv, np.ones(21), keypoint_box(uv, np.ones(21)), score, chirality=0.4, label=1, label_score=score)

    # A pixel at column c is at column W - 1 - c of the mirrored image (np.flip), and back.
    image = np.zeros((height, width), np.uint8)
    image[30, 17] = 255
    row, column = np.argwhere(np.flip(image, axis=1) == 255)[0]
    seen = hand(np.array([column, row], float), 0.8, wrist=(column, row))  # its wrist on the marker
    back = unmirror(seen, width)
    np.testing.assert_allclose(back.uv[0], [17, 30])
    np.testing.assert_allclose(back.uv[:, 1], seen.uv[:, 1])
    assert back.box[0] < back.box[2] and np.all(back.uv.min(0) >= back.box[:2]) and np.all(back.uv.max(0) <= back.box[2:])
    assert (back.chirality, back.label, back.label_score) == (-0.4, -1, seen.label_score)
    np.testing.assert_allclose(unmirror(back, width).uv, seen.uv)
    np.testing.assert_allclose(unmirror(back, width).box, seen.box)

    a, b = hand(np.array([20.0, 24.0]), 0.7), hand(np.array([60.0, 24.0]), 0.9)
    a_again = dataclasses.replace(a, uv=a.uv + 1.0, score=0.95)  # the same hand, seen again in the mirror
    a_neighbour = dataclasses.replace(a, uv=a.uv + [8.0, 0.0])  # another hand, 8 px away (the hand spans ~19 px)
    assert same_hand(a.uv, a_again.uv) and not same_hand(a.uv, a_neighbour.uv)
    merged = merge_mirror_pass([a], [a_again, b], max_hands=2)
    assert merged[0] is a and merged[1] is b  # the direct look's hand kept as found, the missed one added
    assert merge_mirror_pass([a], [a_again, b], max_hands=1) == [a]  # a mirror-only hand never displaces a direct one
    assert merge_mirror_pass([a], [a_neighbour], max_hands=2) == [a, a_neighbour]
    assert merge_mirror_pass([], [a, b], max_hands=1) == [b] and merge_mirror_pass([a], [], max_hands=2) == [a]
    with_nan = dataclasses.replace(a_again, uv=np.where(np.arange(21)[:, None] < 5, np.nan, a_again.uv))
    assert same_hand(a.uv, with_nan.uv) and not same_hand(a.uv, np.full((21, 2), np.nan))


@pytest.mark.parametrize("rig_name", ["esther", "mixed"])
def test_assign_hands_uses_geometry_over_wrong_labels(two_hands, rig_name):
    rig = mixed_rig() if rig_name == "mixed" else cameras.rig_preset(rig_name)  # mixed: a pinhole and a fisheye
    calls: list = []
    c = Candidates.empty(FRAMES, 2)
    for view in (0, 1):
        detector = GroundTruthDetector(two_hands, rig, view, calls, rectified=False)
        for t in range(FRAMES):
            c.put(t, view, detector.detect(None, t / 30))
    hands, report = assign_hands(c, rig)
    assert set(hands) == {"right", "left"}
    for side in hands:
        expected = np.asarray(rig.project(jnp.asarray(two_hands[side])))  # (2, T, 21, 2)
        np.testing.assert_allclose(hands[side]["uv"], expected.transpose(1, 0, 2, 3), atol=1e-3)  # float32 fisheye rounding
    assert all(t["stereo_observations"] == FRAMES for t in report["tracks"])
    assert {t["evidence_side"] for t in report["tracks"]} == {"right", "left"}


def test_a_hand_glimpsed_in_one_frame_is_not_a_hand(two_hands):
    """A one-frame detection in one view (a spurious hand, far from both real ones) makes a
    track of its own; it is dropped, not given the free side of a one-handed clip."""
    rig = cameras.rig_preset("esther")
    c = Candidates.empty(FRAMES, 2)
    for view in (0, 1):
        detector = GroundTruthDetector({"right": two_hands["right"]}, rig, view, [], rectified=False)
        for t in range(FRAMES):
            found = detector.detect(None, t / 30)
            if view == 0 and t == 3:
                uv = np.stack([np.linspace(30, 90, 21), np.linspace(40, 120, 21)], -1)
                found.append(HandDetection(uv, np.ones(21), keypoint_box(uv, np.ones(21)), 0.8, label=1, label_score=0.9))
            c.put(t, view, found)
    hands, report = assign_hands(c, rig)
    assert set(hands) == {"right"}
    glimpse = next(t for t in report["tracks"] if t["observations"] == 1)
    assert glimpse["side"] == "dropped" and glimpse["dropped"] == "fewer than 3 frames"
    assert set(assign_hands(c, rig, min_observations=1)[0]) == {"right", "left"}  # kept, it would be the 'left' hand


@pytest.mark.parametrize("rig_name", ["esther", "hot3d_quest3", "mixed"])
def test_detect_clip_writes_a_clip_the_teacher_reads(tmp_path, two_hands, rig_name):
    rig = mixed_rig() if rig_name == "mixed" else cameras.rig_preset(rig_name)
    left, right = _folders(tmp_path, rig)
    calls: list = []
    report = detect_clip(left, right, rig, tmp_path / "clip", detectors=("truth",), fps=30.0, progress=False,
                         factories={"truth": _factory(two_hands, rig, calls)})  # fmt: skip
    clip = tmp_path / "clip"
    meta = clips.read_meta(clip)
    assert meta["num_frames"] == FRAMES and meta["detect"]["sides"] == ["right", "left"]
    assert report["rectification"] == (None if rig_name == "esther" else "offbb120")
    for side in ("right", "left"):
        kp = clips.load_npz(clips.hand_file(clip, side, "keypoints"), "keypoints")
        assert kp["uv"].shape == (1, FRAMES, 2, 21, 2)
        expected = np.asarray(rig.project(jnp.asarray(two_hands[side]))).transpose(1, 0, 2, 3)
        visible = np.asarray(rig.is_visible(jnp.asarray(two_hands[side]))).transpose(1, 0, 2)
        np.testing.assert_allclose(kp["uv"][0][visible], expected[visible], atol=2e-3)  # mapped back exactly (float32 file)
        assert np.all(kp["conf"][0][~visible] == 0)
    assert (clip / "video" / "left.mp4").is_file() and clips.read_video(clip / "video" / "left.mp4").shape[0] == FRAMES
    written = cameras.StereoRig.from_json(clip / "rig.json")  # an in-memory rig has no name: "rig"
    assert jax.tree.structure(written) == jax.tree.structure(rig) and cameras.rig_name(clip / "rig.json") == "rig"
    assert not (clip / ".detect").exists()


def test_detect_clip_resumes_without_redoing_frames(tmp_path, two_hands):
    rig = cameras.rig_preset("esther")
    left, right = _folders(tmp_path, rig)
    first: list = []
    with pytest.raises(KeyboardInterrupt):
        detect_clip(left, right, rig, tmp_path / "clip", detectors=("truth",), fps=30.0, progress=False, checkpoint_every=3,
                    factories={"truth": _factory(two_hands, rig, first, fail_after=2 * 5)})  # fmt: skip
    assert not (tmp_path / "clip" / "meta.json").exists()  # nothing half-written appears as a clip
    second: list = []
    detect_clip(left, right, rig, tmp_path / "clip", detectors=("truth",), fps=30.0, progress=False, checkpoint_every=3,
                factories={"truth": _factory(two_hands, rig, second)})  # fmt: skip
    assert sorted({t for _, t in second}) == [t / 30 for t in range(3, FRAMES)]  # frames 0-2 were saved, 3-4 lost
    fresh: list = []
    named = rig.to_json(tmp_path / "rig.json", "esther")  # from a rig.json: the clip's keeps its name
    detect_clip(left, right, named, tmp_path / "fresh", detectors=("truth",), fps=30.0, progress=False,
                factories={"truth": _factory(two_hands, rig, fresh)})  # fmt: skip
    assert cameras.rig_name(tmp_path / "fresh" / "rig.json") == "esther"
    for side in ("right", "left"):
        a = clips.load_npz(clips.hand_file(tmp_path / "clip", side, "keypoints"), "keypoints")
        b = clips.load_npz(clips.hand_file(tmp_path / "fresh", side, "keypoints"), "keypoints")
        for key in a:
            np.testing.assert_array_equal(a[key], b[key])


def test_detect_clip_refuses_a_second_writer_and_bad_input(tmp_path, two_hands):
    rig = cameras.rig_preset("esther")
    left, right = _folders(tmp_path, rig)
    kwargs = dict(detectors=("truth",), fps=30.0, progress=False, factories={"truth": _factory(two_hands, rig, [])})
    out = tmp_path / "clip"
    out.mkdir()
    with exclusive_lock(out / ".detect.lock"):
        with pytest.raises(RuntimeError, match="another esther detect"):
            detect_clip(left, right, rig, out, **kwargs)
    with pytest.raises(ValueError, match="--fps is needed"):
        detect_clip(left, right, rig, tmp_path / "x", detectors=("truth",), progress=False)
    (right / f"{FRAMES - 1:05d}.png").unlink()
    with pytest.raises(clips.ClipFormatError, match="different numbers of frames"):
        detect_clip(left, right, rig, tmp_path / "y", **kwargs)
    with pytest.raises(clips.ClipFormatError, match="does not exist"):
        detect_clip(tmp_path / "nothing", right, rig, tmp_path / "z", **kwargs)
    small = tmp_path / "small"
    small.mkdir()
    cv2.imwrite(str(small / "0.png"), np.zeros((10, 10), np.uint8))
    with pytest.raises(ValueError, match="rig's camera is 1920x1200"):
        detect_clip(small, small, rig, tmp_path / "w", **kwargs)


def _recording(folder: pathlib.Path, rig: cameras.StereoRig) -> pathlib.Path:
    """A recording folder: rig.json beside left/ and right/ image folders."""
    folder.mkdir(parents=True)
    left, right = _folders(folder, rig)
    left.rename(folder / "left")
    right.rename(folder / "right")
    rig.to_json(folder / "rig.json", "esther")
    return folder


def test_detect_recordings_detects_each_reports_failures_and_resumes(tmp_path, two_hands):
    from esther_jax.detect import detect_recordings, recording_views

    rig = cameras.rig_preset("esther")
    good = [_recording(tmp_path / "recordings" / name, rig) for name in ("rec_a", "rec_b")]
    broken = _recording(tmp_path / "recordings" / "rec_c", rig)
    shutil.rmtree(broken / "right")
    calls: list = []
    kwargs = dict(detectors=("truth",), fps=30.0, progress=False, factories={"truth": _factory(two_hands, rig, calls)})
    result = detect_recordings([*good, broken], tmp_path / "clips", **kwargs)
    assert [c["clip"] for c in result["detected"]] == ["rec_a", "rec_b"] and result["skipped"] == []
    assert result["failed"] == [{"clip": "rec_c", "error": f"ClipFormatError: {broken} has no right view: a folder right/ of images or a video "
                                                            "right.mp4 (.mp4, .avi, .mov, .mkv)"}]  # fmt: skip
    assert all(c["sides"] == ["right", "left"] and c["frames"] == FRAMES for c in result["detected"])
    single = detect_clip(*recording_views(good[0]), tmp_path / "single", **kwargs)  # the one-clip path gives the same keypoints
    assert single["sides"] == ["right", "left"]
    for side in ("right", "left"):
        a, b = (clips.load_npz(clips.hand_file(root, side, "keypoints"), "keypoints") for root in (tmp_path / "clips" / "rec_a", tmp_path / "single"))
        for key in a:
            np.testing.assert_array_equal(a[key], b[key])
    calls.clear()
    again = detect_recordings([*good, broken], tmp_path / "clips", resume=True, **kwargs)
    assert again["skipped"] == ["rec_a", "rec_b"] and not again["detected"] and not calls and len(again["failed"]) == 1
    (tmp_path / "clips" / "rec_a" / ".detect").mkdir()  # a re-detection interrupted: not finished
    (tmp_path / "clips" / "rec_b" / "meta.json").write_text("{not json")  # unreadable: reported, the others go on
    third = detect_recordings([*good, broken], tmp_path / "clips", resume=True, **kwargs)
    assert [c["clip"] for c in third["detected"]] == ["rec_a"] and [f["clip"] for f in third["failed"]] == ["rec_b", "rec_c"]
    (good[1] / "left.mp4").write_bytes(b"")  # a second left view: which one is meant?
    with pytest.raises(clips.ClipFormatError, match="ambiguous"):
        recording_views(good[1])
    with pytest.raises(ValueError, match="share the name"):
        detect_recordings([good[0], _recording(tmp_path / "elsewhere" / "rec_a", rig)], tmp_path / "other", **kwargs)


def test_detect_command_takes_recordings_or_one_clip(tmp_path, capsys):
    assert cli.main(["detect", "--out", str(tmp_path / "x")]) == 2
    assert "RECORDING folders, or one recording's --left" in capsys.readouterr().err
    assert cli.main(["detect", str(tmp_path), "--left", "a", "--out", str(tmp_path / "x")]) == 2
    assert "not both" in capsys.readouterr().err
    assert cli.main(["detect", "--left", "a", "--right", "b", "--rig", "c", "--resume", "--out", str(tmp_path / "x")]) == 2
    assert "for RECORDING folders" in capsys.readouterr().err


def test_opencv_check_names_the_fix(monkeypatch):
    import importlib.metadata

    from esther_jax.detect import DetectorUnavailable, check_opencv

    versions = {"opencv-python-headless": "5.0.0", "opencv-contrib-python": "5.0.0"}

    def version(name):
        if name in versions:
            return versions[name]
        raise importlib.metadata.PackageNotFoundError(name)

    monkeypatch.setattr(importlib.metadata, "version", version)
    with pytest.raises(DetectorUnavailable, match="uninstall -y opencv-contrib-python && .*--force-reinstall opencv-python-headless"):
        check_opencv()
    versions.pop("opencv-contrib-python")
    assert check_opencv() == "opencv-python-headless"


# ----------------------------------------------------------------------------- ONNX adapters
# Tiny ONNX models with the exported models' input and output contracts stand in for the
# user's YOLO-pose and ViTPose files: the adapters' geometry, decoding and plumbing are
# what is tested, against positions known exactly.


def _save_model(path: pathlib.Path, nodes, inputs, outputs, initializers=()) -> str:
    import onnx
    from onnx import helper

    graph = helper.make_graph(nodes, "toy", inputs, outputs, list(initializers))
    model = helper.make_model(graph, opset_imports=[helper.make_opsetid("", 17)])
    model.ir_version = 8
    onnx.checker.check_model(model)
    onnx.save(model, str(path))
    return str(path)


def _yolo_toy(path: pathlib.Path, rows: np.ndarray) -> str:
    """A YOLO-pose export that always outputs `rows` ((N, 68): box cx, cy, w, h, score,
    then x, y, conf per keypoint, in input pixels), whatever the 640 x 640 image."""
    from onnx import TensorProto, helper, numpy_helper

    constant = numpy_helper.from_array(rows.T[None].astype(np.float32), "rows")
    nodes = [
        helper.make_node("ReduceSum", ["image"], ["total"], keepdims=0),
        helper.make_node("Mul", ["total", "zero"], ["nothing"]),
        helper.make_node("Add", ["rows", "nothing"], ["output0"]),
    ]
    image = helper.make_tensor_value_info("image", TensorProto.FLOAT, [1, 3, 640, 640])
    out = helper.make_tensor_value_info("output0", TensorProto.FLOAT, [1, 68, len(rows)])
    return _save_model(path, nodes, [image], [out], [constant, numpy_helper.from_array(np.zeros((), np.float32), "zero")])


def _heatmap_toy(path: pathlib.Path, batch: int | str = "N", height: int = 256, width: int = 192) -> str:
    """A top-down heatmap export whose 21 heatmaps are the crop's red (keypoints 0-6),
    green (7-13) and blue (14-20) intensity in [0, 1], sampled at the heatmap cells' UDP
    positions: each keypoint lands on the centre of a coloured blob."""
    from onnx import TensorProto, helper, numpy_helper

    from esther_jax.detect.onnx import IMAGENET_MEAN, IMAGENET_STD

    weight = np.zeros((21, 3, 1, 1), np.float32)
    bias = np.zeros(21, np.float32)
    for j in range(21):  # undo the ImageNet normalisation of channel j // 7
        weight[j, j // 7] = IMAGENET_STD[j // 7] / 255.0
        bias[j] = IMAGENET_MEAN[j // 7] / 255.0
    nodes = [
        helper.make_node("Conv", ["input", "w", "b"], ["intensity"]),
        helper.make_node("Resize", ["intensity", "", "scales"], ["heatmaps"], mode="linear", coordinate_transformation_mode="align_corners"),
    ]
    inits = [
        numpy_helper.from_array(weight, "w"),
        numpy_helper.from_array(bias, "b"),
        numpy_helper.from_array(np.array([1, 1, 0.25, 0.25], np.float32), "scales"),
    ]
    image = helper.make_tensor_value_info("input", TensorProto.FLOAT, [batch, 3, height, width])
    out = helper.make_tensor_value_info("heatmaps", TensorProto.FLOAT, [batch, 21, height // 4, width // 4])
    return _save_model(path, nodes, [image], [out], inits)


def _blobs(shape: tuple[int, int], centres: np.ndarray, sigma: float = 4.0) -> np.ndarray:
    """An RGB image, black, with a Gaussian blob of red, green and blue at `centres` (3, 2) px."""
    v, u = np.mgrid[: shape[0], : shape[1]]
    image = np.zeros((*shape, 3))
    for c, (x, y) in enumerate(centres):
        image[..., c] = 255 * np.exp(-((u - x) ** 2 + (v - y) ** 2) / (2 * sigma**2))
    return np.round(image).astype(np.uint8)


class BoxSource:
    name = "boxes"

    def __init__(self, boxes):
        self.hands = [HandDetection(np.zeros((21, 2)), np.zeros(21), np.asarray(b, np.float64), 0.7, 0.3, 1, 0.8) for b in boxes]
        self.closed = False

    def detect(self, image, timestamp_s=0.0):
        return self.hands

    def close(self):
        self.closed = True


@needs_onnx
@pytest.mark.parametrize("batch", ["N", 1])
def test_top_down_model_finds_keypoints_in_each_box(tmp_path, batch):
    from esther_jax.detect import OnnxTopDownPose

    first = np.array([[301.3, 242.6], [352.8, 270.1], [318.4, 318.9]])  # red, green, blue blob centres (px)
    second = first + np.array([-210.55, 61.2])
    image = np.maximum(_blobs((480, 640), first), _blobs((480, 640), second))
    # boxes of other shapes than the input's 3:4 (widened to it), one partly outside the image
    source = BoxSource([[280.0, 225.0, 380.0, 340.0], [40.0, 290.0, 200.0, 390.0]])
    detector = OnnxTopDownPose(_heatmap_toy(tmp_path / "vitpose.onnx", batch), source)
    hands = detector.detect(image, 0.0)
    assert len(hands) == 2
    for hand, centres in zip(hands, (first, second)):
        expected = np.repeat(centres, 7, axis=0)
        assert np.abs(hand.uv - expected).max() < 0.35, np.abs(hand.uv - expected).max(axis=1)
        assert np.all(hand.conf > 0.8)
        assert (hand.score, hand.chirality, hand.label, hand.label_score) == (0.7, 0.3, 1, 0.8)
    # the UDP crop: the box centre lands on the input's centre pixel; the box (100 x 115 px,
    # wider than 3:4) is heightened to 100 x 133.3, padded by 1.25, onto W - 1 and H - 1 px
    M = detector.crop_affine(np.array([280.0, 225.0, 380.0, 340.0]))
    assert np.allclose(M @ [330.0, 282.5, 1.0], [95.5, 127.5])
    assert np.isclose(M[0, 0] * 100 * 1.25, 191) and np.isclose(M[1, 1] * 100 * 4 / 3 * 1.25, 255)
    detector.close()
    assert source.closed


@needs_onnx
def test_onnx_pose_detector_letterboxes_thresholds_and_suppresses(tmp_path):
    from esther_jax.detect import OnnxPoseDetector

    rng = np.random.default_rng(0)
    rows = np.zeros((3, 68))
    rows[0, :5] = [300.0, 330.0, 100.0, 120.0, 0.9]
    rows[0, 5:] = np.concatenate([rng.uniform([250, 270], [350, 390], size=(21, 2)), rng.uniform(0.2, 1.0, size=(21, 1))], axis=1).ravel()
    rows[1] = rows[0] + np.r_[5.0, 0.0, 0.0, 0.0, -0.1, np.zeros(63)]  # overlaps the first: suppressed
    rows[2, :5] = [100.0, 200.0, 50.0, 50.0, 0.1]  # under the score threshold
    detector = OnnxPoseDetector(_yolo_toy(tmp_path / "yolo.onnx", rows))
    image = np.zeros((720, 1280, 3), np.uint8)  # letterboxed at scale 0.5, 140 px of padding above and below
    hands = detector.detect(image)
    assert len(hands) == 1 and hands[0].score == pytest.approx(0.9)
    keypoints = rows[0, 5:].reshape(21, 3)
    # cv2.resize's pixel-centre convention: input u = (u_image + 0.5) * 0.5 - 0.5 + pad
    image_uv = (keypoints[:, :2] - [0.0, 140.0] + 0.5) / 0.5 - 0.5
    assert np.allclose(hands[0].uv, image_uv) and np.allclose(hands[0].conf, keypoints[:, 2])
    assert np.allclose(hands[0].box, (np.r_[250.0, 270.0, 350.0, 390.0] - [0, 140, 0, 140] + 0.5) / 0.5 - 0.5)
    with pytest.raises(ValueError, match="not a loadable ONNX model"):
        (tmp_path / "broken.onnx").write_bytes(b"not a model")
        OnnxPoseDetector(tmp_path / "broken.onnx")


@needs_onnx
def test_the_papers_detector_pair_by_name(tmp_path):
    """`vitpose:MODEL@onnx:YOLO`: the top-down model re-estimates the YOLO model's hand."""
    from esther_jax.detect import make_detector

    centres = np.array([[610.0, 560.0], [640.0, 600.0], [590.0, 625.0]])  # image px of 720 x 1280
    rows = np.zeros((1, 68))
    box_in = (np.r_[560.0, 500.0, 700.0, 680.0] + 0.5) * 0.5 - 0.5 + [0, 140, 0, 140]  # the YOLO box, input px
    rows[0, :5] = [*(box_in[:2] + box_in[2:]) / 2, *(box_in[2:] - box_in[:2]), 0.95]
    rows[0, 5:] = np.tile([320.0, 430.0, 0.5], 21)
    yolo = _yolo_toy(tmp_path / "yolo.onnx", rows)
    detector = make_detector(f"vitpose:{_heatmap_toy(tmp_path / 'vitpose.onnx')}@onnx:{yolo}")
    assert detector.name == "vitpose:vitpose.onnx@onnx:yolo.onnx"
    hands = detector.detect(_blobs((720, 1280), centres), 0.0)
    assert len(hands) == 1 and hands[0].score == pytest.approx(0.95)
    assert np.abs(hands[0].uv - np.repeat(centres, 7, axis=0)).max() < 0.35
    detector.close()
    with pytest.raises(ValueError, match="must find hands itself"):
        make_detector(f"vitpose:{tmp_path / 'vitpose.onnx'}@vitpose:{tmp_path / 'vitpose.onnx'}")
    with pytest.raises(FileNotFoundError, match="does not exist"):
        make_detector(f"vitpose:{tmp_path / 'missing.onnx'}@onnx:{yolo}")


# ----------------------------------------------------------------------------- real pixels


@pytest.fixture(scope="module")
def oracle():
    return json.loads((ORACLE / "mediapipe_tasks_outputs.json").read_text())


@needs_mediapipe
@needs_oracle
def test_mediapipe_on_a_real_photo_matches_the_reference(oracle):
    from esther_jax.detect import MediaPipeHands

    expected = np.asarray(oracle["tfjs_expected_hands_jpg"]["keypoints_px"], np.float64)  # corner convention, 20 px tolerance
    image = cv2.imread(str(ORACLE / "hands.jpg"))[..., ::-1]
    with MediaPipeHands(video=False) as detector:
        hands = detector.detect(image)
        mirrored = detector.detect(np.ascontiguousarray(image[:, ::-1]))
    with MediaPipeHands(video=False, mirror_pass=False) as detector:
        one_look = detector.detect(image)
    assert len(hands) == 2
    for reference in expected:
        errors = [np.abs(h.uv + 0.5 - reference).max() for h in hands]
        assert min(errors) <= 20.0
    for h in hands:
        assert h.conf.shape == (21,) and np.all((h.conf >= 0) & (h.conf <= 1)) and h.score >= 0.5
        assert np.all(h.uv.min(0) >= h.box[:2]) and np.all(h.uv.max(0) <= h.box[2:])
    # Both hands of hands.jpg are left hands (backs towards the camera, thumbs on the right
    # when the fingers point up): geometry says so, and says "right" on the mirrored image.
    assert all(h.chirality < 0 for h in hands) and len(mirrored) == 2 and all(h.chirality > 0 for h in mirrored)
    # Both hands found in one look: the mirror pass adds nothing and changes nothing; and the
    # hands found in the mirrored photo are the photo's hands, mirrored.
    assert len(one_look) == 2 and all(any(np.array_equal(h.uv, o.uv) for o in one_look) for h in hands)
    assert all(any(same_hand(unmirror(m, image.shape[1]).uv, h.uv) for h in hands) for m in mirrored)


class FakeLandmarker:
    """Stands in for MediaPipe's HandLandmarker: records what it is given, and finds one
    right hand with its wrist on the image's one white pixel (none when `blind`)."""

    def __init__(self, world: np.ndarray, offsets: np.ndarray, blind: bool):
        self.world, self.offsets, self.blind = world, offsets, blind
        self.calls, self.closed = [], False

    def detect_for_video(self, frame, ms):
        image = frame.numpy_view().copy()
        self.calls.append((image, ms))
        if self.blind:
            return SimpleNamespace(hand_landmarks=[], hand_world_landmarks=[], handedness=[])
        height, width = image.shape[:2]
        v, u = np.argwhere(image[..., 0] == 255)[0]
        uv = np.array([u, v]) + self.offsets
        return SimpleNamespace(
            hand_landmarks=[[SimpleNamespace(x=(a + 0.5) / width, y=(b + 0.5) / height, z=0.0) for a, b in uv]],
            hand_world_landmarks=[[SimpleNamespace(x=x, y=y, z=z) for x, y, z in self.world]],
            handedness=[[SimpleNamespace(score=0.9, category_name="Right")]],
        )

    def close(self):
        self.closed = True


@needs_mediapipe
def test_mediapipe_mirror_pass_runs_a_second_landmarker_on_the_mirror(monkeypatch, two_hands):
    from mediapipe.tasks.python import vision

    from esther_jax.detect import MediaPipeHands

    world = two_hands["right"][0]
    offsets = np.random.default_rng(1).uniform(-6.0, 6.0, (21, 2))
    offsets[0] = 0.0
    made = []

    def create(options, fail_second=False):
        if fail_second and made:
            raise RuntimeError("no second landmarker")
        made.append(FakeLandmarker(world, offsets, blind=not made))  # the direct look misses the hand
        return made[-1]

    monkeypatch.setattr(vision.HandLandmarker, "create_from_options", create)
    image = np.zeros((48, 80, 3), np.uint8)  # not square: W and H are not interchangeable
    image[30, 17] = 255
    with MediaPipeHands(video=True) as detector:
        assert detector.name == "mediapipe" and len(made) == 2
        hands = detector.detect(image, 0.5)
    direct, mirror = made
    assert [ms for _, ms in direct.calls] == [ms for _, ms in mirror.calls] == [500]
    np.testing.assert_array_equal(direct.calls[0][0], image)
    np.testing.assert_array_equal(mirror.calls[0][0], image[:, ::-1])
    assert len(hands) == 1
    np.testing.assert_allclose(hands[0].uv[0], [17, 30], atol=1e-9)  # back on the marker
    np.testing.assert_allclose(hands[0].uv - hands[0].uv[0], offsets * [-1, 1], atol=1e-9)
    assert chirality(world) > 0 and hands[0].chirality == pytest.approx(-chirality(world)) and hands[0].label == -1
    assert direct.closed and mirror.closed

    made.clear()
    monkeypatch.setattr(vision.HandLandmarker, "create_from_options", lambda options: create(options, fail_second=True))
    with pytest.raises(RuntimeError, match="no second landmarker"):
        MediaPipeHands(video=True)
    assert len(made) == 1 and made[0].closed  # the first one is not left open

    made.clear()
    with MediaPipeHands(video=True, mirror_pass=False) as detector:
        assert detector.name == "mediapipe:direct" and len(made) == 1 and detector.detect(image, 0.0) == []


@needs_mediapipe
@needs_oracle
def test_mediapipe_tracks_the_real_video_frame_by_frame():
    from esther_jax.detect import MediaPipeHands

    reference = np.asarray(json.loads((ORACLE / "asl_hand.full.json").read_text()), np.float64)[..., :2]
    errors = []
    with MediaPipeHands(video=True) as detector:
        for t, frame in enumerate(clips.iter_video(ORACLE / "asl_hand.25fps.mp4")):
            hands = detector.detect(frame, t / 25.0)
            assert len(hands) >= 1, f"frame {t}: no hand"
            errors.append(min(np.abs(h.uv + 0.5 - reference[t]).max() for h in hands))
        with pytest.raises(ValueError, match="strictly increasing"):
            detector.detect(frame, 0.0)
    assert len(errors) == len(reference) == 325
    assert max(errors) <= 26.0 and np.median(errors) < 2.0
