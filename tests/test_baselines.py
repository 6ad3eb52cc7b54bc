"""The triangulation baseline of the missing-view study (table 2) on a synthetic clip with
noise-free detections: stereo recovers the truth, one view places joints on its rays at
the prior depth, unobserved joints and frames are filled as documented, the output is in
the targets' (mirrored) frame, and the network's scoring path scores it."""

import shutil

import jax.numpy as jnp
import numpy as np
import pytest

from esther_jax import clips, train
from esther_jax.cameras import StereoRig
from esther_jax.studies.baselines import mean_joint_depth, triangulation_baseline
from esther_jax.train.validation import score_predictions

FRAMES, CROP = 16, 64
DATA = train.DataConfig(frames=FRAMES, stride=FRAMES, crop_size=CROP)
PRIOR_M = 0.45


@pytest.fixture(scope="module")
def clip(tmp_path_factory):
    """Both hands, 16 frames, 64 px crops, detections equal to the projected joints."""
    from esther_jax.data import motion, synth

    cfg = synth.SynthConfig(num_frames=FRAMES, crops=True, crop_size=CROP, detector_preset="clean",
                            motion_config=motion.MotionConfig(two_hands_probability=1.0))  # fmt: skip
    return synth.write_clip(synth.make_clip(0, 0, cfg), tmp_path_factory.mktemp("baselines") / "clip_00000")


def _windows(clip):
    windows = train.build_index([clip], DATA)
    assert [w.side for w in windows] == ["right", "left"]
    return windows


def _visible(clip, side) -> np.ndarray:
    """(2, T, 21): each ground-truth joint inside each original view (what the clean detector reports)."""
    gt = clips.load_npz(clips.hand_file(clip, side, "gt"), "gt")["joints"][:FRAMES]
    return np.asarray(StereoRig.from_json(clip / "rig.json").is_visible(jnp.asarray(gt)))


def test_stereo_triangulation_recovers_the_truth_in_the_targets_frame(clip):
    windows = _windows(clip)
    joints, emitted = triangulation_baseline(windows, DATA, prior_depth_m=PRIOR_M)
    assert joints.shape == (2, FRAMES, 21, 3) and emitted.shape == (2, FRAMES) and bool(emitted.all())
    for window, predicted in zip(windows, np.asarray(joints)):
        targets = train.load_example(window, DATA)[1]
        both = _visible(clip, window.side).all(axis=0)
        assert both.mean() > 0.5
        error = np.linalg.norm(predicted - np.asarray(targets.joints), axis=-1)
        assert error[both].max() < 1e-3, window.side
    # the left hand comes mirrored, as its targets: not in the clip's own frame
    left_gt = clips.load_npz(clips.hand_file(clip, "left", "gt"), "gt")["joints"][:FRAMES]
    assert np.linalg.norm(np.asarray(joints[1]) - left_gt, axis=-1).mean() > 0.02


@pytest.mark.parametrize("view_dropped", [0, 1])
def test_a_dropped_view_puts_joints_on_the_kept_rays_at_the_prior_depth(clip, view_dropped):
    """In the window's frame (a left hand's mirrored clip has its views swapped), the
    kept view's camera sees each joint where the truth is, at the prior depth."""
    windows = _windows(clip)
    joints, emitted = triangulation_baseline(windows, DATA, prior_depth_m=PRIOR_M, view_dropped=view_dropped)
    kept = 1 - view_dropped
    for window, predicted, shown in zip(windows, np.asarray(joints), np.asarray(emitted)):
        example, targets = train.load_example(window, DATA)
        T_cam_rig = np.linalg.inv(np.asarray(example.T_rig_cams[kept]))
        ours, truth = (x @ T_cam_rig[:3, :3].T + T_cam_rig[:3, 3] for x in (predicted, np.asarray(targets.joints)))
        seen = _visible(clip, window.side)[kept if window.side == "right" else 1 - kept]
        assert seen.mean() > 0.5 and np.array_equal(shown, seen.any(axis=1))
        np.testing.assert_allclose(ours[..., 2][seen], PRIOR_M, rtol=1e-5)
        np.testing.assert_allclose((ours[..., :2] / ours[..., 2:])[seen], (truth[..., :2] / truth[..., 2:])[seen], atol=1e-5)


def test_unobserved_joints_are_filled_and_empty_frames_not_emitted(clip, tmp_path):
    """Detections removed from a copy of the clip: a frame without any (not emitted,
    interpolated), a joint missing for three frames (interpolated), a joint seen by the
    left view only (its ray at the prior depth), a joint never seen (the centroid)."""
    copy = tmp_path / clip.name
    shutil.copytree(clip, copy)
    path = clips.hand_file(copy, "right", "keypoints")
    keypoints = clips.load_npz(path, "keypoints")
    conf = keypoints["conf"]
    conf[:, 10] = 0.0
    conf[:, 3:6, :, 8] = 0.0
    conf[:, 7, 1, 4] = 0.0
    conf[:, :, :, 20] = 0.0
    clips.save_npz(path, **keypoints)
    window = _windows(copy)[0]
    stereo = np.asarray(triangulation_baseline([_windows(clip)[0]], DATA, prior_depth_m=PRIOR_M)[0][0])
    joints, emitted = (np.asarray(x[0]) for x in triangulation_baseline([window], DATA, prior_depth_m=PRIOR_M))
    assert window.side == "right" and not emitted[10] and emitted.sum() == FRAMES - 1
    np.testing.assert_allclose(joints[10, :20], (stereo[9, :20] + stereo[11, :20]) / 2, atol=1e-6)
    for t in (3, 4, 5):
        np.testing.assert_allclose(joints[t, 8], stereo[2, 8] + (t - 2) / 4 * (stereo[6, 8] - stereo[2, 8]), atol=1e-6)
    assert joints[7, 4, 2] == pytest.approx(PRIOR_M, rel=1e-5)  # the rig frame is the left camera's
    np.testing.assert_allclose(joints[7, 4, :2] / PRIOR_M, stereo[7, 4, :2] / stereo[7, 4, 2], atol=1e-5)
    np.testing.assert_allclose(joints[:, 20], joints[:, :20].mean(axis=1), atol=1e-6)
    keep = np.ones((FRAMES, 21), bool)
    keep[10] = keep[3:6, 8] = keep[7, 4] = keep[:, 20] = False
    np.testing.assert_allclose(joints[keep], stereo[keep], atol=1e-6)


def test_the_networks_scoring_scores_the_baseline(clip):
    """score_predictions of the targets: no error; of the baseline: stereo exact, the
    wrist collapsing with a view dropped; predictions of the wrong shape are refused."""
    windows = _windows(clip)
    targets = [train.load_example(w, DATA)[1] for w in windows]
    truth = jnp.stack([t.joints for t in targets])
    perfect = score_predictions(truth, jnp.stack([t.valid for t in targets]), windows, DATA, intervals=True, resamples=200)
    assert perfect["p_mpjpe_mm"] == perfect["pa_mpjpe_mm"] == perfect["wrist_mm"] == 0.0
    assert perfect["keypoints_2d_px"] is None and perfect["intervals"]["keypoints_2d_px"] is None
    assert perfect["jitter"] == pytest.approx(perfect["gt_jitter"]) and perfect["onscreen_recall"] == 1.0 and perfect["windows"] == 2
    prior = mean_joint_depth(windows, DATA)
    assert 0.1 < prior < 1.0
    stereo = score_predictions(*triangulation_baseline(windows, DATA, prior_depth_m=prior), windows, DATA)
    mono = score_predictions(*triangulation_baseline(windows, DATA, prior_depth_m=prior, view_dropped=1), windows, DATA, view_dropped=1)
    assert stereo["wrist_mm"] < 1.0 and stereo["p_mpjpe_mm"] < 1.0 and mono["wrist_mm"] > 10.0
    with pytest.raises(ValueError, match="one row per window"):
        score_predictions(truth[:1], jnp.ones((1, FRAMES), bool), windows, DATA)
