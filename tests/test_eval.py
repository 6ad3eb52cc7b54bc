import json

import cv2
import jax
import jax.numpy as jnp
import numpy as np
import pytest

from esther_jax import cli, clips, eval as ev, metrics
from esther_jax.eval import hot3d, protocols, reports
from esther_jax.mano import KEYPOINT_NAMES


def test_frame_drop_is_exact_and_deterministic():
    for n in protocols.FRAME_DROP_COUNTS:
        kept = protocols.frame_drop_mask(jax.random.key(3), 16, n)
        assert int(jnp.sum(~kept)) == n
        assert np.array_equal(np.asarray(kept), np.asarray(protocols.frame_drop_mask(jax.random.key(3), 16, n)))
    assert not np.array_equal(
        np.asarray(protocols.frame_drop_mask(jax.random.key(1), 16, 8)), np.asarray(protocols.frame_drop_mask(jax.random.key(2), 16, 8))
    )
    with pytest.raises(ValueError, match="cannot drop"):
        protocols.frame_drop_mask(jax.random.key(0), 16, 17)
    kept = protocols.frame_drop_mask(jax.random.key(0), 16, 4)
    conf = jnp.ones((16, 2, 21))
    dropped = protocols.drop_frames_keypoints(conf, kept)
    assert float(dropped.sum()) == 12 * 42
    images = jnp.ones((16, 2, 8, 8, 3), jnp.uint8)
    assert int(protocols.drop_frames_images(images, kept).sum()) == 12 * 2 * 8 * 8 * 3


def test_view_drop():
    conf = jnp.ones((5, 2, 21))
    out = protocols.drop_view_keypoints(conf, view=1)
    assert float(out[:, 1].sum()) == 0 and float(out[:, 0].sum()) == 5 * 21
    images, present = protocols.drop_view_images(jnp.ones((4, 2, 6, 6), jnp.float32), view=0)
    assert float(images[:, 0].sum()) == 0 and bool(present[:, 1].all()) and not bool(present[:, 0].any())


def test_corruptions_have_the_exact_parameters():
    flat = np.full((32, 32, 3), 100, np.uint8)
    assert protocols.corrupt(flat, "over_exposure")[0, 0, 0] == 160
    assert protocols.corrupt(np.full((4, 4), 200, np.uint8), "over_exposure")[0, 0] == 255  # clipped
    assert protocols.corrupt(flat, "low_light")[0, 0, 0] == 50
    assert protocols.corrupt(np.full((4, 4), 128, np.uint8), "gamma")[0, 0] == round(255 * (128 / 255) ** 2.2)
    impulse = np.zeros((31, 41), np.uint8)
    impulse[15, 20] = 150
    blurred = protocols.corrupt(impulse, "motion_blur")
    assert np.count_nonzero(blurred) == 15 and np.all(blurred[15, 13:28] == 10)
    noisy = protocols.corrupt(np.full((200, 200), 128, np.uint8), "sensor_noise", seed=1).astype(float)
    assert abs(noisy.std() - 25.0) < 0.5
    assert np.array_equal(noisy, protocols.corrupt(np.full((200, 200), 128, np.uint8), "sensor_noise", seed=1))
    skin = np.zeros((8, 8, 3), np.uint8)
    skin[:] = (200, 120, 90)
    hue = lambda img: cv2.cvtColor(img.astype(np.float32) / 255, cv2.COLOR_RGB2HSV)[0, 0]  # noqa: E731
    assert abs(hue(protocols.corrupt(skin, "hue_shift"))[0] - hue(skin)[0] - 25.0) < 1.0
    assert abs(hue(protocols.corrupt(skin, "desaturate"))[1] - 0.4 * hue(skin)[1]) < 0.01
    gray = np.full((8, 8), 90, np.uint8)
    assert np.array_equal(protocols.corrupt(gray, "hue_shift"), gray) and np.array_equal(protocols.corrupt(gray, "desaturate"), gray)
    with pytest.raises(ValueError, match="unknown corruption"):
        protocols.corrupt(flat, "fog")
    clip = np.full((3, 2, 16, 16, 3), 100, np.uint8)
    assert protocols.corrupt_clip(clip, "low_light").max() == 50


def test_hot3d_landmark_mapping():
    names = [KEYPOINT_NAMES[k] for k in hot3d.HOT3D_LANDMARKS_FROM_KEYPOINTS]
    assert names[:6] == ["thumb_tip", "index_tip", "middle_tip", "ring_tip", "pinky_tip", "wrist"]
    assert names[6:8] == ["thumb_mcp", "thumb_ip"] and names[8:11] == ["index_mcp", "index_pip", "index_dip"]
    assert names[17:] == ["pinky_mcp", "pinky_pip", "pinky_dip"] and "thumb_cmc" not in names
    assert len(hot3d.LANDMARKS_TO_EVAL) == 19 and 5 not in hot3d.LANDMARKS_TO_EVAL


def test_hot3d_metrics_are_absolute_every_tenth_frame():
    rng = np.random.default_rng(0)
    gt = rng.normal(scale=0.05, size=(40, 21, 3))
    pred = gt + np.array([0.01, 0.0, 0.0])  # 10 mm everywhere, including the ignored wrist
    pred[:, 1] += 1.0  # the thumb CMC is not a HOT3D landmark
    pred[5] += 1.0  # frame 5 is never evaluated (stride 10)
    m = hot3d.hot3d_sequence_metrics(jnp.asarray(pred), jnp.asarray(gt))
    assert m["num_frames"] == 4 and m["mpjpe_mm"] == pytest.approx(10.0)
    assert m["pck_auc"] == pytest.approx(100 * (1 - 10 / 50), abs=1.0)
    gt_nan = gt.copy()
    gt_nan[0, 8] = np.nan  # NaN landmarks are masked
    assert hot3d.hot3d_sequence_metrics(jnp.asarray(pred), jnp.asarray(gt_nan))["mpjpe_mm"] == pytest.approx(10.0)
    total = hot3d.hot3d_dataset_metrics([m, dict(m, mpjpe_mm=30.0, num_frames=12)])
    assert total["mpjpe_mm"] == pytest.approx((10 * 4 + 30 * 12) / 16)


def _write_clip(root, name, rng, T=24, fps=30.0, noise=0.0, drift=0.0):
    clip = root / name
    t = np.arange(T)[:, None, None] / fps
    joints = rng.normal(scale=0.04, size=(1, 21, 3)) + np.array([0.0, 0.0, 0.4]) + 0.2 * t * np.array([1.0, 0.0, 0.0])
    onscreen = np.ones(T, bool)
    onscreen[5] = False
    arrays = dict(
        global_orient=np.zeros((T, 3)), hand_pose=np.zeros((T, 15, 3)), betas=np.zeros(10), transl=joints[:, 0],
        joints=joints, onscreen=onscreen,
    )  # fmt: skip
    clips.save_npz(clips.hand_file(clip, "right", "gt"), **arrays)
    clips.write_meta(clip, fps=fps, num_frames=T, source="test")
    pred = dict(arrays)
    pred["joints"] = joints + rng.normal(scale=noise, size=joints.shape) + drift
    pred["valid"] = np.ones(T, bool)
    pred["residual_px"] = np.zeros(T)
    return pred


def test_evaluate_folders_end_to_end(tmp_path, capsys):
    rng = np.random.default_rng(1)
    gt_root, pred_root = tmp_path / "gt", tmp_path / "pred"
    for i in range(6):
        pred = _write_clip(gt_root, f"clip{i:02d}", rng, noise=0.002, drift=0.01)
        clips.save_npz(clips.hand_file(pred_root / f"clip{i:02d}", "right", "labels"), **pred)
    _write_clip(gt_root, "unlabelled", rng)
    assert cli.main(["evaluate", "--pred", str(pred_root), "--gt", str(gt_root), "--out", str(tmp_path / "out"), "--method", "test"]) == 0
    result = json.loads((tmp_path / "out" / "metrics.json").read_text())
    assert result["num_hands"] == 6 and result["missing_predictions"] == ["unlabelled/right"]
    assert result["metrics"]["wrist"]["value"] == pytest.approx(np.sqrt(3) * 10, abs=1.5)  # mm
    assert result["metrics"]["pa_mpjpe"]["value"] < result["metrics"]["mpjpe"]["value"]
    assert result["metrics"]["wrist"]["ci_low"] <= result["metrics"]["wrist"]["value"] <= result["metrics"]["wrist"]["ci_high"]
    # coverage counts every ground-truth hand: the unlabelled clip's 23 on-screen frames too
    assert result["coverage"] == pytest.approx(6 / 7) and result["depth_scatter"]["count"] == 6 * 23
    assert "6 hands scored, 1 ground-truth hands with no prediction (unlabelled/right); coverage 85.7%" in capsys.readouterr().out
    for name in ("table.md", "table.csv", "depth_scatter.png", "pck.png"):
        assert (tmp_path / "out" / name).stat().st_size > 100
    assert "P-MPJPE" in (tmp_path / "out" / "table.md").read_text()
    with pytest.raises(ValueError, match="predictions folder .*nowhere does not exist"):
        ev.evaluate_folders(tmp_path / "nowhere", gt_root, tmp_path / "out2")
    clips.hand_file(gt_root / "unlabelled", "right", "gt").unlink()
    with pytest.raises(ValueError, match="holds ground truth"):  # clips of esther detect: nothing to score against
        ev.evaluate_folders(pred_root, gt_root / "unlabelled", tmp_path / "out2")


def test_evaluate_a_prediction_that_emits_nothing(tmp_path, capsys):
    """An untrained network's gate may emit no frame: the evaluation says so (coverage 0,
    no data) instead of failing inside a plot."""
    pred = _write_clip(tmp_path / "gt", "clip", np.random.default_rng(3))
    clips.save_npz(clips.hand_file(tmp_path / "pred" / "clip", "right", "labels"), **{**pred, "valid": np.zeros_like(pred["valid"])})
    assert cli.main(["evaluate", "--pred", str(tmp_path / "pred"), "--gt", str(tmp_path / "gt"), "--out", str(tmp_path / "o")]) == 0
    result = json.loads((tmp_path / "o" / "metrics.json").read_text())
    assert result["coverage"] == 0.0 and result["metrics"]["wrist"]["value"] is None
    assert "no data" in capsys.readouterr().out and (tmp_path / "o" / "depth_scatter.png").is_file()


def test_evaluate_reports_bad_inputs(tmp_path, capsys):
    rng = np.random.default_rng(2)
    pred = _write_clip(tmp_path / "gt", "clip", rng)
    clips.save_npz(clips.hand_file(tmp_path / "pred" / "clip", "right", "labels"), **{k: v for k, v in pred.items() if k != "joints"})
    assert cli.main(["evaluate", "--pred", str(tmp_path / "pred"), "--gt", str(tmp_path / "gt"), "--out", str(tmp_path / "o")]) == 2
    assert "joints" in capsys.readouterr().err
    assert cli.main(["evaluate", "--pred", str(tmp_path / "nothing"), "--gt", str(tmp_path / "gt"), "--out", str(tmp_path / "o")]) == 2


def test_clip_files_say_what_is_wrong(tmp_path):
    rng = np.random.default_rng(3)
    _write_clip(tmp_path, "c", rng)
    path = clips.hand_file(tmp_path / "c", "right", "gt")
    good = path.read_bytes()
    path.write_bytes(good[: len(good) // 2])
    with pytest.raises(clips.ClipFormatError, match="truncated"):
        clips.load_npz(path, "gt")
    with pytest.raises(clips.ClipFormatError, match="does not exist"):
        clips.load_npz(tmp_path / "absent.npz", "gt")
    clips.save_npz(path, joints=np.zeros((4, 20, 3)), **{k: np.zeros(s) for k, s in
                     dict(global_orient=(4, 3), hand_pose=(4, 15, 3), betas=(10,), transl=(4, 3), onscreen=(4,)).items()})  # fmt: skip
    with pytest.raises(clips.ClipFormatError, match="joints has shape"):
        clips.load_npz(path, "gt")
    clips.save_npz(path, joints=np.zeros((5, 21, 3)), **{k: np.zeros(s) for k, s in
                     dict(global_orient=(4, 3), hand_pose=(4, 15, 3), betas=(10,), transl=(4, 3), onscreen=(4,)).items()})  # fmt: skip
    with pytest.raises(clips.ClipFormatError, match="T is 4 elsewhere"):
        clips.load_npz(path, "gt")


def test_reports_table_and_figure(tmp_path):
    b = metrics.bootstrap(np.random.default_rng(0).normal(0.0177, 0.004, size=60), jax.random.key(0))
    rows = [reports.Record.from_bootstrap("ESTHER", f"drop {n}", "p_mpjpe", b, 1000.0) for n in (0, 2, 4)]
    rows.append(reports.Record.from_bootstrap("ESTHER", "drop 0", "jitter", None))
    text = reports.markdown_table(rows, condition="drop 0")
    assert f"| ESTHER | {b.mean * 1000:.2f} ± {b.std * 1000:.2f} |" in text and "no data" in text
    path = reports.plot_metric_vs_condition(rows, "p_mpjpe", ["drop 0", "drop 2", "drop 4"], tmp_path / "drop.png")
    assert path.stat().st_size > 1000
    assert ev.Record is reports.Record
