import dataclasses

import jax.numpy as jnp
import numpy as np
import pytest

from esther_jax import cameras, cli, clips, metrics
from esther_jax.crops import crop_camera
from esther_jax.data import detector, flow, motion, render, synth
from esther_jax.rotations import axis_angle_to_matrix


@pytest.fixture(scope="module")
def clean_clip():
    return synth.make_clip(7, 1, synth.SynthConfig(num_frames=24, detector_preset="clean", vertices=True))


def test_clean_detections_equal_projected_joints(clean_clip):
    rig = clean_clip.rig
    for side, kp in clean_clip.keypoints.items():
        joints = clean_clip.gt[side]["joints"].astype(np.float64)
        uv_true = detector.project_views(rig, joints)
        visible = clean_clip.gt[side]["visibility"]
        for d in range(2):
            np.testing.assert_allclose(kp["uv"][d][visible], uv_true[visible], atol=1e-3)
            assert np.all(kp["conf"][d][visible] == 1.0)
        assert kp["uv"].shape == (2, 24, 2, 21, 2) and kp["box_score"].shape == (2, 24, 2)


def test_default_detector_is_noisy_and_confidence_tracks_error():
    rng = np.random.default_rng(0)
    clip = synth.make_clip(3, 2, synth.SynthConfig(num_frames=64))
    side = next(iter(clip.keypoints))
    kp, gt = clip.keypoints[side], clip.gt[side]
    uv_true = detector.project_views(clip.rig, gt["joints"].astype(np.float64))
    err = np.linalg.norm(kp["uv"] - uv_true[None], axis=-1)
    observed = kp["conf"] > 0
    assert 0.5 < np.median(err[observed]) < 15.0
    high, low = kp["conf"] > 0.8, (kp["conf"] > 0) & (kp["conf"] < 0.4)
    assert np.median(err[high]) < np.median(err[low])
    del rng


def test_visibility_agrees_with_the_renderers_depth_buffer(clean_clip):
    rig = clean_clip.rig
    scene = render.sample_scene(np.random.default_rng(0))
    agree, total = 0, 0
    for t in (0, 8, 16):
        meshes = [(clean_clip.gt[s]["vertices"][t].astype(np.float64), synth._faces(s), scene.skin) for s in clean_clip.gt]
        _, depth = render.render_view(scene, rig.left, np.eye(4), meshes)
        for side, gt in clean_clip.gt.items():
            joints = gt["joints"][t].astype(np.float64)
            uv = np.rint(np.asarray(rig.left.project(jnp.asarray(joints, jnp.float32)))).astype(int)
            for j in range(21):
                u, v = uv[j]
                if not (0 <= u < rig.left.width and 0 <= v < rig.left.height) or joints[j, 2] <= 0:
                    continue
                hidden_by_render = depth[v, u] < joints[j, 2] - 0.03
                visible = gt["visibility"][t, 0, j]
                agree += visible != hidden_by_render
                total += 1
    assert total > 20 and agree / total > 0.85


def test_onscreen_flags_follow_the_rule(clean_clip):
    for gt in clean_clip.gt.values():
        expected = [bool(metrics.onscreen(jnp.asarray(j), clean_clip.rig)) for j in gt["joints"]]
        assert list(gt["onscreen"]) == expected


def test_clips_are_deterministic_per_seed_and_differ_across_seeds():
    a = synth.make_clip(11, 4, synth.SynthConfig(num_frames=16))
    b = synth.make_clip(11, 4, synth.SynthConfig(num_frames=16))
    c = synth.make_clip(12, 4, synth.SynthConfig(num_frames=16))
    for side in a.keypoints:
        for k in a.keypoints[side]:
            np.testing.assert_array_equal(a.keypoints[side][k], b.keypoints[side][k])
        np.testing.assert_array_equal(a.gt[side]["joints"], b.gt[side]["joints"])
    side = next(iter(c.gt))
    assert side not in a.gt or not np.allclose(a.gt[side]["joints"], c.gt[side]["joints"])


def test_motion_is_egocentric_and_within_human_speeds():
    rig = cameras.rig_preset("esther")
    depths, speeds = [], []
    for i in range(6):
        m = motion.sample_clip(np.random.default_rng([5, i]), rig, 64)
        for track in m.hands.values():
            wrist = np.asarray(track.joints)[:, 0]
            depths.append(wrist[:, 2])
            speeds.append(np.linalg.norm(np.diff(wrist, axis=0), axis=1) * 30.0)
    depths, speeds = np.concatenate(depths), np.concatenate(speeds)
    assert depths.min() >= 0.1 and depths.max() <= 0.85 and 0.25 <= np.median(depths) <= 0.5
    assert np.percentile(speeds, 99) < 3.0  # m/s, relative to the moving head


def _static_scene_view(camera, T_world_cam, box):
    scene = render.sample_scene(np.random.default_rng(1))
    crop = crop_camera(camera, jnp.asarray(box, jnp.float32))
    T_crop = T_world_cam
    image, _ = render.render_view(scene, crop.camera, T_crop, [])
    return image, np.asarray(crop.camera.K, np.float64)


def test_flow_token_cancels_pure_crop_window_motion():
    cam = cameras.rig_preset("esther").left
    a, Ka = _static_scene_view(cam, np.eye(4), [800, 500, 1000, 700])
    b, Kb = _static_scene_view(cam, np.eye(4), [830, 515, 1050, 735])  # moved and zoomed window, same scene
    token = flow.flow_token(a, b, Ka, Kb)
    assert token.shape == (192,)
    flags = token[128:].reshape(8, 8).astype(bool)
    assert flags.mean() > 0.5  # cells the previous window did not cover are flagged out
    assert np.abs(token[:128].reshape(8, 8, 2)[flags]).max() * 224 < 0.6  # px


def test_flow_token_of_a_known_camera_rotation_is_analytic():
    cam = cameras.rig_preset("esther").left
    box = [820, 520, 1020, 720]
    R = np.asarray(axis_angle_to_matrix(jnp.asarray([0.004, -0.012, 0.003])), np.float64)  # camera turns between frames
    T1 = np.eye(4)
    T1[:3, :3] = R
    a, K = _static_scene_view(cam, np.eye(4), box)
    b, _ = _static_scene_view(cam, T1, box)
    token = flow.flow_token(a, b, K, K)
    # pure rotation: a pixel u of frame t moves to K R^T K^-1 u (X_cam1 = R^T X_cam0)
    H = K @ R.T @ np.linalg.inv(K)
    cell = 224 // 8
    centres = (np.arange(8) + 0.5) * cell - 0.5
    u, v = np.meshgrid(centres, centres)
    p = np.stack([u, v, np.ones_like(u)], -1) @ H.T
    analytic = p[..., :2] / p[..., 2:] - np.stack([u, v], -1)
    measured = token[:128].reshape(8, 8, 2) * 224
    flags = token[128:].reshape(8, 8).astype(bool)
    assert np.abs(analytic).max() > 3.0  # a real motion of several pixels
    assert np.median(np.abs(measured - analytic)[flags]) < 0.25


def test_written_clips_load_back_identically(tmp_path):
    clip = synth.make_clip(2, 0, synth.SynthConfig(num_frames=8, crops=True, crop_size=64))
    folder = synth.write_clip(clip, tmp_path / "clip")
    back = synth.load_clip(folder)
    assert back.meta["num_frames"] == 8 and back.rig.name == "esther"
    for side in clip.keypoints:
        for k, v in clip.keypoints[side].items():
            np.testing.assert_array_equal(back.keypoints[side][k], v)
        for k in ("joints", "hand_pose", "onscreen"):
            np.testing.assert_array_equal(back.gt[side][k], clip.gt[side][k])
        for k, v in clip.crops[side].items():
            np.testing.assert_array_equal(back.crops[side][k], v)
    assert back.crops[side]["images"].shape[2:4] == (64, 64) and back.crops[side]["flow"].shape == (8, 192)
    kp_path = clips.hand_file(folder, side, "keypoints")
    kp_path.write_bytes(kp_path.read_bytes()[:100])
    with pytest.raises(clips.ClipFormatError, match="truncated"):
        synth.load_clip(folder)
    kp_path.unlink()
    (folder / "rig.json").unlink()
    with pytest.raises(clips.ClipFormatError, match="rig.json"):
        synth.load_clip(folder)


@pytest.mark.slow
def test_rendered_videos_round_trip(tmp_path):
    cfg = synth.SynthConfig(num_frames=3, rig="hot3d_aria", render=True, crop_size=64)
    clip = synth.make_clip(0, 5, cfg)
    assert clip.videos["left"].shape == (3, 480, 640)  # grayscale rig
    folder = synth.write_clip(clip, tmp_path / "clip")
    back = synth.load_clip(folder, videos=True)
    assert back.videos["left"].shape[:3] == (3, 480, 640)
    assert np.abs(back.videos["left"][..., 0].astype(float) - clip.videos["left"]).mean() < 8.0  # lossy mp4
    (folder / "video" / "right.mp4").write_bytes(b"not a video")
    with pytest.raises(clips.ClipFormatError, match="right.mp4"):
        synth.load_clip(folder, videos=True)


def test_synth_cli_resumes_without_redoing_clips(tmp_path):
    out = tmp_path / "clips"
    assert cli.main(["synth", "--out", str(out), "--clips", "2", "--frames", "8", "--seed", "3"]) == 0
    first = (out / "clip_00000" / "hands").stat().st_mtime_ns
    (out / ".clip_00002.partial").mkdir()  # a run interrupted while writing clip 2
    assert cli.main(["synth", "--out", str(out), "--clips", "3", "--frames", "8", "--seed", "3"]) == 0
    assert (out / "clip_00000" / "hands").stat().st_mtime_ns == first
    assert sorted(p.name for p in out.iterdir() if p.is_dir()) == ["clip_00000", "clip_00001", "clip_00002"]
    reference = synth.make_clip(3, 2, synth.SynthConfig(num_frames=8))
    loaded = synth.load_clip(out / "clip_00002")
    side = next(iter(reference.keypoints))
    np.testing.assert_array_equal(loaded.keypoints[side]["uv"], reference.keypoints[side]["uv"])
    assert dataclasses.asdict(synth.SynthConfig())["crop_size"] == 224
