"""Crops of recorded clips (`esther crops`, `data.video_crops`): cut from a clip's
videos, they must be the crops the synthetic engine renders directly (same crop camera,
same pixels up to resampling), on a fisheye rig."""

import dataclasses
import json
import shutil

import jax
import numpy as np
import pytest

from esther_jax import cli, clips
from esther_jax.cameras import StereoRig
from esther_jax.crops import hand_box
from esther_jax.data import motion, synth
from esther_jax.data import video_crops as vc
from esther_jax.train import data as train_data
from esther_jax.train.features import feature_file

SIZE = 64


@pytest.fixture(scope="module")
def rendered(tmp_path_factory):
    """A fisheye (hot3d_aria) clip of 6 frames with its full views and its directly
    rendered crops, in memory and as a clip folder."""
    cfg = synth.SynthConfig(num_frames=6, rig="hot3d_aria", render=True, crop_size=SIZE, motion_config=motion.MotionConfig(two_hands_probability=1.0))
    clip = synth.make_clip(0, 5, cfg)
    return clip, synth.write_clip(clip, tmp_path_factory.mktemp("video_crops") / "clip")


def _rgb(frames):
    return np.repeat(np.asarray(frames)[..., None], 3, axis=-1) if np.asarray(frames).ndim == 3 else np.asarray(frames)


def test_crops_cut_from_the_views_are_the_rendered_crops(rendered):
    """Given the engine's crop windows, the crops cut from its full views have its crop
    cameras exactly and its pixels up to resampling (the renderer draws crops directly);
    both hands are cut in one pass over the frames (a one-pass iterator)."""
    clip, _ = rendered
    frames = zip(_rgb(clip.videos["left"]), _rgb(clip.videos["right"]))
    both = vc.render_crops(frames, clip.rig, {side: ref["box"].astype(np.float64) for side, ref in clip.crops.items()}, vc.CropConfig(size=SIZE))
    assert len(clip.crops) == 2 and set(both) == set(clip.crops)
    for side, ref in clip.crops.items():
        cut = both[side]
        np.testing.assert_allclose(cut["K"], ref["K"], rtol=1e-5, atol=1e-4)
        np.testing.assert_allclose(cut["R_cam_crop"], ref["R_cam_crop"], atol=1e-6)
        for t, v in np.ndindex(6, 2):
            inside = cut["images"][t, v, ..., 0] > 0
            assert inside.all() or np.mean(ref["images"][t, v][~inside] < 8) > 0.95  # beyond the source image: black in both
            if inside.mean() > 0.5:
                a, b = ref["images"][t, v][inside].astype(float), cut["images"][t, v, ..., 0][inside].astype(float)
                assert np.corrcoef(a, b)[0, 1] > 0.9, (side, t, v)
        assert np.abs(cut["flow"] - ref["flow"]).max() < 0.1


def test_esther_crops_on_a_clip_folder(rendered, tmp_path, capsys):
    """The command cuts the crops around the projected ground truth, records how, skips a
    clip already done, keeps esther synth's crops unless told, and the training loader
    reads what it wrote."""
    clip, folder = rendered
    work = shutil.copytree(folder, tmp_path / "clip")
    assert cli.main(["crops", str(work), "--size", str(SIZE)]) == 1  # esther synth's crops are kept
    assert cli.main(["crops", str(work), "--size", str(SIZE), "--overwrite"]) == 0
    meta = json.loads((work / "meta.json").read_text())
    record = meta["crops"]
    assert "crop_strategy" not in meta  # esther synth's record of the crops replaced
    assert record["settings"]["size"] == SIZE and record["settings"]["strategy"] == "offbb120"
    assert sorted(record["hands"]) == sorted(clip.crops)
    for side, counts in record["hands"].items():
        gt = clips.load_npz(clips.hand_file(work, side, "gt"), "gt")
        rig = StereoRig.from_json(work / "rig.json")
        cams = np.asarray(rig.to_views(gt["joints"]))  # (2, T, 21, 3)
        seen = np.asarray(rig.is_visible(gt["joints"])).any(axis=-1)  # (2, T): the view sees some joint
        ahead = (cams[..., 2] > 1e-2).all(axis=-1) & gt["onscreen"] & seen  # the frame-views the projected hand frames
        assert counts["joints"] == int(ahead.sum()) > 0 and sum(counts.values()) == 12
        cut = dict(np.load(work / "crops" / f"{side}.npz"))
        assert cut["images"].shape == (6, 2, SIZE, SIZE, 3) and cut["flow"].shape == (6, 192)
        # every ground-truth joint the view sees projects inside its crop (the window follows
        # the hand), boxes reaching past the image and the fisheye's field included
        rays = np.einsum("tvji,vtnj->tvni", cut["R_cam_crop"], cams)  # R_cam_crop^T x: the crop camera's frame
        uv = np.einsum("tvij,tvnj->tvni", cut["K"], rays / rays[..., 2:3])[..., :2]
        visible = np.asarray(rig.is_visible(gt["joints"])).transpose(1, 0, 2) & ahead.T[..., None]  # (T, 2, 21)
        past_edge = ~((cut["box"][..., :2] >= 0).all(axis=-1) & (cut["box"][..., 2:] < [640, 480]).all(axis=-1))
        assert visible.any() and np.all((uv[visible] > -1) & (uv[visible] < SIZE))
        if side == "right":
            assert (past_edge & ahead.T).any()  # the case at hand: this clip's right hand leaves the right view
    stamp = (work / "crops" / "right.npz").stat().st_mtime_ns
    capsys.readouterr()
    assert cli.main(["crops", str(work), "--size", str(SIZE)]) == 0  # done: skipped
    assert (work / "crops" / "right.npz").stat().st_mtime_ns == stamp
    assert "cropped 0 hands of 0 clips (64 px, offbb120), 1 already done" in capsys.readouterr().out
    assert cli.main(["crops", str(work), "--size", "32"]) == 1  # other settings: kept unless --overwrite
    assert "esther crops --overwrite" in capsys.readouterr().err
    windows = train_data.build_index([work], train_data.DataConfig(frames=4, stride=2, crop_size=SIZE))
    example, targets = train_data.load_example(windows[0], train_data.DataConfig(frames=4, stride=2, crop_size=SIZE))
    assert example.images.shape == (4, 2, 3, SIZE, SIZE) and np.all(np.isfinite(np.asarray(example.K)))


def test_crops_of_a_detected_clip_follow_its_keypoints(rendered, tmp_path):
    """Without a 3D hand (a clip of esther detect), the windows come from the detections;
    the crops then frame the hand about as the ground truth's projection would."""
    _, folder = rendered
    work = shutil.copytree(folder, tmp_path / "clip")
    for side in clips.SIDES:
        clips.hand_file(work, side, "gt").unlink()
    record = vc.crop_clip(work, vc.CropConfig(size=SIZE), overwrite=True)
    for side, counts in record["hands"].items():
        assert counts["joints"] == 0 and counts["keypoints"] > 0
        detected = clips.load_crops(clips.crops_file(work, side))["box"]
        projected, _ = vc.hand_crop_boxes(folder, side, StereoRig.from_json(folder / "rig.json"), vc.CropConfig(size=SIZE))
        both = np.isfinite(detected).all(axis=-1) & np.isfinite(projected).all(axis=-1)
        centres = lambda b: (b[both][:, :2] + b[both][:, 2:]) / 2  # noqa: E731
        assert both.any() and np.median(np.abs(centres(detected) - centres(projected))) < 10  # px of 640 x 480


def test_crops_are_cut_again_when_their_evidence_changes(rendered, tmp_path):
    """Crops cut before a hand's labels existed (windows from gt.npz) are cut again from
    the labels once they arrive, without --overwrite (same settings, other evidence)."""
    _, folder = rendered
    work = shutil.copytree(folder, tmp_path / "clip")
    labels = tmp_path / "labels"
    labels.mkdir()
    first = vc.crop_clip(work, vc.CropConfig(size=SIZE), labels=labels, overwrite=True)
    before = clips.load_crops(clips.crops_file(work, "right"))["box"]
    assert vc.crop_clip(work, vc.CropConfig(size=SIZE), labels=labels) == first  # nothing changed: skipped
    gt = clips.load_npz(clips.hand_file(work, "right", "gt"), "gt")
    moved = gt["joints"] + np.array([0.03, 0.0, 0.0])  # the labelled hand 3 cm to the side of the ground truth's
    clips.hand_file(labels / work.name, "right", "labels").parent.mkdir(parents=True)
    clips.save_npz(clips.hand_file(labels / work.name, "right", "labels"), **{**gt, "joints": moved, "valid": gt["onscreen"],
                                                                             "residual_px": np.zeros(len(moved))})  # fmt: skip
    again = vc.crop_clip(work, vc.CropConfig(size=SIZE), labels=labels)
    assert again["evidence"]["right"].keys() == {"labels", "gt", "keypoints"} and again["evidence"]["left"] == first["evidence"]["left"]
    after = clips.load_crops(clips.crops_file(work, "right"))["box"]
    shown = np.isfinite(before).all(axis=-1) & np.isfinite(after).all(axis=-1)
    assert shown.any() and np.all(np.abs(after[shown] - before[shown]).max(axis=-1) > 1.0)  # the windows follow the labels


def test_esther_crops_says_what_is_missing(rendered, tmp_path, capsys):
    _, folder = rendered
    work = shutil.copytree(folder, tmp_path / "clip")
    (work / "video" / "left.mp4").unlink()
    assert cli.main(["crops", str(work), "--size", str(SIZE), "--overwrite"]) == 1
    assert "no video/left.mp4" in capsys.readouterr().err
    short = shutil.copytree(folder, tmp_path / "short")
    gt = clips.load_npz(clips.hand_file(short, "right", "gt"), "gt")
    clips.save_npz(clips.hand_file(short, "right", "gt"), **{k: v if k == "betas" else v[:3] for k, v in gt.items()})
    assert cli.main(["crops", str(short), "--size", str(SIZE), "--overwrite"]) == 1
    assert "gt.npz has 3 frames; the clip has 6" in capsys.readouterr().err
    assert cli.main(["crops", str(tmp_path / "nowhere")]) == 2
    assert cli.main(["crops", str(short), "--labels", str(tmp_path / "no_labels")]) == 2
    assert "no_labels does not exist" in capsys.readouterr().err
    assert cli.main(["crops", str(short), "--size", "8"]) == 2


def test_keypoint_boxes_gaps_and_absent_views():
    """Boxes from detections: the median over the detectors that are confident, none with
    too few joints; short gaps bridged, long ones not; a view without a box is black with
    a NaN box and finite crop geometry."""
    rng = np.random.default_rng(0)
    T = 12
    hand = 300 + rng.uniform(-40, 40, size=(T, 2, 21, 2))
    uv = np.stack([hand, hand + 1.0, hand + 500.0])  # (D=3, T, 2, 21, 2): the third detector is wrong...
    conf = np.ones((3, T, 2, 21))
    conf[2] = 0.1  # ...and unconfident
    conf[:, 3, 1] = 0.0  # frame 3: nobody sees the right view
    conf[:, 5:, 1, :17] = 0.0  # frames 5+: 4 joints only in the right view
    boxes = vc.keypoint_boxes({"uv": uv, "conf": conf}, vc.CropConfig(min_joints=5))
    np.testing.assert_allclose(boxes[0, 0], hand_box(hand[0, 0] + 0.5), atol=1e-9)  # the median of the two confident detectors
    assert np.isnan(boxes[3, 1]).all() and np.isnan(boxes[5:, 1]).all() and np.isfinite(boxes[:, 0]).all()
    filled = vc.fill_gaps(boxes[:, 1], max_gap=1)
    assert np.isfinite(filled[3]).all() and np.isnan(filled[5:]).all()
    np.testing.assert_allclose(filled[3], (boxes[2, 1] + boxes[4, 1]) / 2)
    assert np.isnan(vc.fill_gaps(boxes[:, 1], max_gap=0)[3]).all()

    rig = synth.make_clip(0, 5, synth.SynthConfig(num_frames=2, rig="hot3d_aria")).rig
    frame = np.full((rig.left.height, rig.left.width, 3), 200, np.uint8)
    box = np.array([[[250.0, 200, 330, 280], [np.nan] * 4]] * 2)
    cut = vc.render_crops([(frame, frame)] * 2, rig, {"right": box}, vc.CropConfig(size=32))["right"]
    assert cut["images"][:, 1].max() == 0 and np.isnan(cut["box"][:, 1]).all() and np.isfinite(cut["K"]).all()
    assert cut["images"][:, 0].max() == 200
    with pytest.raises(clips.ClipFormatError, match="1 frames; the clip has 2"):
        vc.render_crops([(frame, frame)], rig, {"right": box}, vc.CropConfig(size=32))
    with pytest.raises(clips.ClipFormatError, match="the rig's camera is 640 x 480"):
        vc.render_crops([(frame[:100], frame)] * 2, rig, {"right": box}, vc.CropConfig(size=32))
    with pytest.raises(ValueError, match="different numbers of frames"):
        vc.render_crops([(frame, frame)] * 2, rig, {"right": box, "left": box[:1]}, vc.CropConfig(size=32))


def test_crops_files_are_validated(rendered, tmp_path):
    _, folder = rendered
    good = clips.load_crops(clips.crops_file(folder, "right"))
    assert set(good) == set(clips.CROP_KEYS)
    path = tmp_path / "crops.npz"
    for change, message in (
        ({"K": good["K"][:-1]}, r"K has shape \(5, 2, 3, 3\), expected \[6, 2, 3, 3\]"),
        ({"images": good["images"].astype(np.float32)}, "images must be"),
        ({"flow": np.full_like(good["flow"], np.nan)}, "flow contains NaN"),
    ):
        clips.save_npz(path, **{**good, **change})
        with pytest.raises(clips.ClipFormatError, match=message):
            clips.load_crops(path)
    clips.save_npz(path, **{k: v for k, v in good.items() if k != "box"})
    with pytest.raises(clips.ClipFormatError, match=r"keys \['box'\] are missing"):
        clips.load_crops(path)
    path.write_bytes(clips.crops_file(folder, "right").read_bytes()[:1000])
    with pytest.raises(clips.ClipFormatError, match="truncated"):
        clips.load_crops(path)


def test_stored_crops_are_memory_mapped_and_load_as_compressed_ones(rendered, tmp_path):
    """Crops files are written uncompressed and memory-mapped by the training loader (a
    window reads its frames only); compressed files of earlier versions load the same."""
    _, folder = rendered
    stored = clips.load_crops(clips.crops_file(folder, "right"), mmap=True)
    assert isinstance(stored["images"], np.memmap)
    old = shutil.copytree(folder, tmp_path / "compressed")
    clips.save_npz(clips.crops_file(old, "right"), **clips.load_crops(clips.crops_file(folder, "right")))
    assert not isinstance(clips.load_crops(clips.crops_file(old, "right"), mmap=True)["images"], np.memmap)
    cfg = train_data.DataConfig(frames=4, stride=2, crop_size=32)  # resized on the way (stored at 64)
    for a, b in zip(train_data.build_index([folder], cfg), train_data.build_index([old], cfg)):
        if a.side == "right":
            for x, y in zip(jax.tree.leaves(train_data.load_example(a, cfg)), jax.tree.leaves(train_data.load_example(b, cfg))):
                np.testing.assert_array_equal(np.asarray(x), np.asarray(y))
    # cached features (of the crops resized to 32 px) come with those crops' intrinsics
    cached = feature_file(tmp_path / "features", folder, "right")
    cached.parent.mkdir(parents=True)
    np.save(cached, np.zeros((6, 2, 4, 8), np.float16))
    window = next(w for w in train_data.build_index([folder], cfg) if w.side == "right")
    with_features = train_data.load_example(window, dataclasses.replace(cfg, features=str(tmp_path / "features")))[0]
    np.testing.assert_array_equal(np.asarray(with_features.K), np.asarray(train_data.load_example(window, cfg)[0].K))
