import dataclasses
import json

import jax.numpy as jnp
import numpy as np
import pytest

from esther_jax import cameras, cli, clips, mano, metrics
from esther_jax.crops import HAND_CROP_PADDING, crop_camera, crop_poses, rectified_crop
from esther_jax.data import flow, motion, render, synth
from esther_jax.rotations import axis_angle_to_matrix


@pytest.fixture(scope="module")
def clean_clip():
    return synth.make_clip(7, 1, synth.SynthConfig(num_frames=24, detector_preset="clean", vertices=True))


def test_clean_detections_equal_projected_joints(clean_clip):
    rig = clean_clip.rig
    for side, kp in clean_clip.keypoints.items():
        joints = clean_clip.gt[side]["joints"].astype(np.float64)
        uv_true = np.moveaxis(np.asarray(rig.project(jnp.asarray(joints, jnp.result_type(float))), np.float64), 0, 1)  # (T, 2, 21, 2)
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
    uv_true = np.moveaxis(np.asarray(clip.rig.project(jnp.asarray(gt["joints"], jnp.result_type(float))), np.float64), 0, 1)
    err = np.linalg.norm(kp["uv"] - uv_true[None], axis=-1)
    observed = kp["conf"] > 0
    assert 0.5 < np.median(err[observed]) < 15.0
    high, low = kp["conf"] > 0.8, (kp["conf"] > 0) & (kp["conf"] < 0.4)
    assert np.median(err[high]) < np.median(err[low])
    del rng


def test_visibility_agrees_with_the_renderers_depth_buffer():
    """Ground-truth visibility (a splatted depth test of hands, forearms and the held box)
    against the depth buffer of the rendered scene with everything in it, under the same
    rule: hidden when a surface lies more than the joint's own depth below the skin in front."""
    rng = synth.clip_rng(7, 1)
    rig = cameras.rig_preset("esther")
    m = motion.sample_clip(rng, rig, 24)
    scene = render.sample_scene(np.random.default_rng(0))
    vertices = {side: np.asarray(track.vertices, np.float64) for side, track in m.hands.items()}
    agree, total = 0, 0
    for t in (0, 8, 16):
        _, depth = render.render_view(scene, rig.left, np.eye(4), synth._meshes_in(vertices, m, scene, t, np.eye(4)))
        for side, track in m.hands.items():
            joints = np.asarray(track.joints[t], np.float64)
            uv = np.rint(np.asarray(rig.left.project(jnp.asarray(joints, jnp.float32)))).astype(int)
            for j in range(21):
                u, v = uv[j]
                if not (0 <= u < rig.left.width and 0 <= v < rig.left.height) or joints[j, 2] <= 0:
                    continue
                hidden_by_render = depth[v, u] < joints[j, 2] - motion.JOINT_DEPTH_BELOW_SKIN_M[j]
                agree += m.visibility[side][t, 0, j] != hidden_by_render
                total += 1
    assert total > 20 and agree / total > 0.85


def test_hand_skin_paints_nails_creases_and_pale_palms_where_they_belong():
    h = render._hand_rest()
    dark = render.SKIN_TONES[-1]
    albedo, nail = render.hand_skin_albedo(h["vertices"], h["normals"], dark)
    assert albedo.shape == h["vertices"].shape and np.all((albedo >= 0) & (albedo <= 1))
    model = mano.load_builtin("right")
    tips = h["tips"]
    near_tip = np.linalg.norm(h["vertices"][:, None] - tips[None], axis=-1).min(axis=1) < 0.02
    dorsal = h["normals"][:, 1] > 0.5  # MANO frame: the back of the hand is +y
    palmar = h["normals"][:, 1] < -0.5
    assert np.all(nail[~near_tip] < 0.05), "nails only on the distal phalanges"
    assert np.all(nail[palmar] < 0.05), "no nail on the palmar side"
    for f in range(5):  # every finger has a nail on its back
        own = np.linalg.norm(h["vertices"] - tips[f], axis=1) < 0.012
        assert nail[own & dorsal].max() > 0.9, f
    lum = albedo @ np.array([0.299, 0.587, 0.114])
    palm = palmar & (h["vertices"][:, 0] > float(model.joint_template[4, 0]))  # between the wrist and the knuckles
    back = dorsal & (h["vertices"][:, 0] > float(model.joint_template[4, 0]))
    assert np.median(lum[palm]) > 1.3 * np.median(lum[back]), "dark skin has paler palms"
    # a flexion crease darkens the palmar skin right at a finger joint, not between joints
    pip, dip = np.asarray(model.joint_template[5], np.float64), np.asarray(model.joint_template[6], np.float64)  # middle finger
    along = (dip - pip) / np.linalg.norm(dip - pip)
    up = np.array([0.0, 1.0, 0.0])
    t = np.linspace(-0.008, 0.008, 161)
    points = pip + t[:, None] * along - 0.008 * up  # a line on the palmar skin across the PIP joint
    line, _ = render.hand_skin_albedo(points, np.tile(-up, (len(t), 1)), dark)
    line_lum = line @ np.array([0.299, 0.587, 0.114])
    assert line_lum[np.abs(t) < 0.001].min() < 0.85 * np.median(line_lum[np.abs(t) > 0.005])


def test_skin_tones_are_measured_skin_and_the_grain_is_fixed_to_the_surface():
    import cv2

    lab = cv2.cvtColor(render.SKIN_TONES[None].astype(np.float32), cv2.COLOR_RGB2Lab)[0]
    np.testing.assert_allclose(lab, render.SKIN_TONES_LAB, atol=0.5)  # the sRGB albedos are the CIELAB ones
    lightness, chroma = lab[:, 0], np.hypot(lab[:, 1], lab[:, 2])
    hue = np.degrees(np.arctan2(lab[:, 2], lab[:, 1]))
    assert np.all(np.diff(lightness) < 0) and lightness[0] > 70 and lightness[-1] < 30, "very light to very dark"
    assert np.all((chroma > 14) & (chroma < 27)) and np.all((hue > 35) & (hue < 55)), "pale red-orange, as skin is"
    points = np.random.default_rng(0).uniform(-0.05, 0.05, size=(4000, 3))
    grain = render._skin_grain(points)
    assert grain.min() >= 0.96 and grain.max() <= 1.04 and abs(grain.mean() - 1) < 0.003 and grain.std() > 0.015
    same_cell = np.floor(points / 0.0015) * 0.0015 + 0.0007
    np.testing.assert_array_equal(render._skin_grain(same_cell), grain)  # constant within a 1.5 mm cell


def test_forearms_leave_the_wrist_outward_and_are_mirror_images():
    rng = synth.clip_rng(5, 0)
    m = motion.sample_clip(rng, cameras.rig_preset("esther"), 4)
    faces = motion.forearm_faces()
    for side, track in m.hands.items():
        arm = m.forearms[side]
        joints = np.asarray(track.joints, np.float64)
        first_ring = arm[:, : motion.FOREARM_AROUND].mean(axis=1)
        assert np.all(np.linalg.norm(first_ring - joints[:, 0], axis=-1) < 0.01), "the tube starts at the wrist"
        last_ring = arm[:, -motion.FOREARM_AROUND :].mean(axis=1)
        assert np.all(np.abs(np.linalg.norm(last_ring - joints[:, 0], axis=-1) - motion.FOREARM_LENGTH_M) < 0.03)
        # outward faces: each face normal points away from the tube's local axis
        tri = arm[0][faces]
        normal = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
        ring = faces.min(axis=1) // motion.FOREARM_AROUND
        centres = arm[0].reshape(motion.FOREARM_RINGS, motion.FOREARM_AROUND, 3).mean(axis=1)
        assert np.all(np.einsum("fk,fk->f", normal, tri.mean(axis=1) - centres[ring]) > 0)
    # a mirrored hand gets the mirrored forearm (elbow mirrored with it)
    joints = np.asarray(next(iter(m.hands.values())).joints, np.float64)
    elbow = np.tile([0.2, 0.45, 0.08], (len(joints), 1))
    flip = np.array([-1.0, 1.0, 1.0])
    mirrored = motion.forearm_surface(joints * flip, elbow * flip).reshape(len(joints), motion.FOREARM_RINGS, motion.FOREARM_AROUND, 3)
    expected = (motion.forearm_surface(joints, elbow) * flip).reshape(mirrored.shape)
    around = -np.arange(motion.FOREARM_AROUND) % motion.FOREARM_AROUND  # the mirror runs round the ring the other way
    np.testing.assert_allclose(mirrored, expected[:, :, around], atol=1e-12)


def test_ambient_occlusion_darkens_what_lies_behind_a_nearer_surface():
    depth = np.full((60, 60), np.inf, np.float32)
    depth[10:50, 10:50] = 0.40  # a flat plane...
    flat = render.ambient_occlusion(depth, 4.0)
    assert np.allclose(flat, 1.0, atol=1e-6)
    depth[10:50, 10:28] = 0.37  # ...with a nearer finger over its left part
    ao = render.ambient_occlusion(depth, 4.0)
    assert ao[30, 29] < 0.75 and ao[30, 45] > 0.99 and ao[30, 20] > 0.99


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
    assert back.meta["num_frames"] == 8 and cameras.rig_name(folder / "rig.json") == back.meta["rig"] == "esther"
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


# ----------------------------------------------------------------------------- crop strategies, hand size and depth knobs

_STRATEGY_MOTION = motion.MotionConfig(two_hands_probability=0.0, leave_view_probability=0.0)


@pytest.fixture(scope="module")
def strategy_clips():
    """rig -> strategy -> a 4-frame clip with 32 px crops (same seed and index); the
    focal of offbbF on the fisheye rig only (fisheye crops are the slow ones)."""
    strategies = {"esther": ("offbb120", "hc"), "hot3d_aria": ("offbb120", "offbb90", "hc")}
    return {
        rig: {
            s: synth.make_clip(4, 0, synth.SynthConfig(num_frames=4, rig=rig, crops=True, crop_size=32, crop_strategy=s, motion_config=_STRATEGY_MOTION))
            for s in chosen
        }
        for rig, chosen in strategies.items()
    }  # fmt: skip


def test_default_crop_strategy_is_offbb120_and_recorded(strategy_clips):
    assert synth.SynthConfig().crop_strategy == "offbb120"
    implicit = synth.make_clip(4, 0, synth.SynthConfig(num_frames=4, crops=True, crop_size=32, motion_config=_STRATEGY_MOTION))
    explicit = strategy_clips["esther"]["offbb120"]
    for side in implicit.crops:
        for k, v in implicit.crops[side].items():
            np.testing.assert_array_equal(v, explicit.crops[side][k])
    assert implicit.meta["crop_strategy"] == "offbb120" and strategy_clips["esther"]["hc"].meta["crop_strategy"] == "hc"
    assert "crop_strategy" not in synth.make_clip(4, 0, synth.SynthConfig(num_frames=4, motion_config=_STRATEGY_MOTION)).meta
    # on a pinhole rig the default is the axis-aligned crop around the stored box
    pinhole = strategy_clips["esther"]["offbb120"]
    side = next(iter(pinhole.crops))
    crops = pinhole.crops[side]
    for t, v in ((0, 0), (3, 1)):
        expected = crop_camera(pinhole.rig.left if v == 0 else pinhole.rig.right, jnp.asarray(crops["box"][t, v]), 32, HAND_CROP_PADDING)
        np.testing.assert_allclose(crops["K"][t, v], np.asarray(expected.camera.K), rtol=1e-6)
        np.testing.assert_array_equal(crops["R_cam_crop"][t, v], np.eye(3))
    with pytest.raises(ValueError, match="unknown crop_strategy 'offbb100'"):
        synth.SynthConfig(crop_strategy="offbb100")


@pytest.mark.parametrize("rig", ["esther", "hot3d_aria"])
def test_crop_strategies_change_only_the_crops_and_stay_consistent(strategy_clips, rig):
    by_strategy = strategy_clips[rig]
    reference = by_strategy["offbb120"]
    side = next(iter(reference.crops))
    S = 32
    for strategy, clip in by_strategy.items():
        for part in ("keypoints", "gt"):  # same motion, detections and ground truth
            for k, v in getattr(reference, part)[side].items():
                np.testing.assert_array_equal(getattr(clip, part)[side][k], v)
        crops = clip.crops[side]
        np.testing.assert_array_equal(crops["box"], reference.crops[side]["box"])  # same crop window in the source image
        if strategy == "hc":  # ray-aligned: a turned crop camera, other pixels
            assert np.abs(crops["R_cam_crop"] - np.eye(3)).max() > 1e-3
            assert np.abs(crops["K"] - reference.crops[side]["K"]).max() > 1.0
            assert np.mean(crops["images"] != reference.crops[side]["images"]) > 0.2
        else:  # offbbF: the crop camera does not depend on F (documented in SynthConfig.crop_strategy)
            np.testing.assert_allclose(crops["K"], reference.crops[side]["K"], rtol=1e-4, atol=1e-3)
            np.testing.assert_array_equal(crops["R_cam_crop"], reference.crops[side]["R_cam_crop"])
        # the stored crop camera (K, and its pose from R_cam_crop) projects the ground truth
        # onto the hand: every joint inside the crop, their box centred in it
        joints = clip.gt[side]["joints"].astype(np.float64)  # (T, 21, 3) rig frame
        in_image = np.asarray(clip.rig.is_visible(jnp.asarray(joints, jnp.float32))).all(axis=-1)  # (2, T)
        T_rig_crop = np.asarray(crop_poses(jnp.asarray(crops["R_cam_crop"]), clip.rig.T_rig_cams.astype(jnp.float32)), np.float64)
        checked = 0
        for t in range(4):
            for v in range(2):
                if not in_image[v, t]:
                    continue
                X = (joints[t] - T_rig_crop[t, v, :3, 3]) @ T_rig_crop[t, v, :3, :3]  # rig -> crop frame
                uv = X @ crops["K"][t, v].astype(np.float64).T
                uv = uv[:, :2] / uv[:, 2:]
                assert np.all(X[:, 2] > 0) and np.all((uv > -0.5) & (uv < S - 0.5)), (strategy, t, v)
                centre = 0.5 * (uv.min(axis=0) + uv.max(axis=0))
                assert np.all(np.abs(centre - (S - 1) / 2) < 0.2 * S), (strategy, t, v, centre)
                checked += 1
        assert checked >= 4


def test_flow_token_cancels_a_turning_crop_window():
    """hc crops turn with the hand: the token's homography of K R^T cancels that turn
    (synth._render_crops), K alone would not."""
    cam = cameras.rig_preset("esther").left
    scene = render.sample_scene(np.random.default_rng(1))
    views = []
    for box in ([700, 450, 900, 650], [740, 470, 940, 670]):  # a static scene, the window moves
        crop = rectified_crop(cam, jnp.asarray(box, jnp.float32), "hc", 224, HAND_CROP_PADDING)
        R = np.asarray(crop.R_cam_crop, np.float64)
        T_world_crop = np.eye(4)
        T_world_crop[:3, :3] = R
        image, _ = render.render_view(scene, crop.camera, T_world_crop, [])
        views.append((image, np.asarray(crop.camera.K, np.float64), R))
    (a, Ka, Ra), (b, Kb, Rb) = views
    assert np.degrees(np.arccos(np.clip((np.trace(Ra.T @ Rb) - 1) / 2, -1, 1))) > 1.0  # the window turned
    turned = flow.flow_token(a, b, Ka @ Ra.T, Kb @ Rb.T)
    plain = flow.flow_token(a, b, Ka, Kb)
    flags = turned[128:].reshape(8, 8).astype(bool)
    assert flags.mean() > 0.5
    assert np.median(np.abs(turned[:128].reshape(8, 8, 2)[flags])) * 224 < 0.3  # px
    assert np.median(np.abs(plain[:128].reshape(8, 8, 2)[plain[128:].reshape(8, 8).astype(bool)])) * 224 > 3.0


def _betas_draw(seed: int, two_hands_probability: float) -> np.ndarray:
    """The clip's betas as sampled before shape_sd existed (motion.sample_clip's draws)."""
    rng = np.random.default_rng(seed)
    if rng.uniform() >= two_hands_probability:
        rng.choice(["right", "left"])
    return rng.normal(size=10)


def test_shape_sd_scales_the_betas_of_the_same_draw():
    rig = cameras.rig_preset("esther")
    one = motion.sample_clip(np.random.default_rng(9), rig, 4, motion.MotionConfig())
    two = motion.sample_clip(np.random.default_rng(9), rig, 4, motion.MotionConfig(shape_sd=2.0))
    np.testing.assert_array_equal(one.betas, _betas_draw(9, motion.MotionConfig().two_hands_probability))  # shape_sd=1: as before
    np.testing.assert_array_equal(two.betas, 2.0 * one.betas)
    np.testing.assert_array_equal(two.T_world_rig, one.T_world_rig)  # every other draw is the same
    assert sorted(two.hands) == sorted(one.hands)
    side = next(iter(one.hands))
    np.testing.assert_array_equal(np.asarray(two.hands[side].params.hand_pose), np.asarray(one.hands[side].params.hand_pose))
    with pytest.raises(ValueError, match="shape_sd"):
        motion.MotionConfig(shape_sd=-1.0)


def test_depth_range_and_uniform_sampling_reach_past_the_training_depths():
    def depths(cfg):
        return np.concatenate([motion.wrist_path(np.random.default_rng([2, i]), 300, cfg, 0.09, False)[:, 2] for i in range(12)])

    training = depths(motion.MotionConfig())
    assert 0.2 < training.min() and training.max() < 0.72
    np.testing.assert_array_equal(depths(motion.MotionConfig(depth_range_m=(0.1, 1.1))), training)  # egocentric: the range only limits
    held_out = depths(motion.MotionConfig(depth_range_m=(0.1, 1.1), depth_sampling="uniform"))
    assert 0.1 <= held_out.min() < 0.2 and 0.95 < held_out.max() <= 1.1 and np.mean(held_out > 0.8) > 0.15
    with pytest.raises(ValueError, match="depth_range_m"):
        motion.MotionConfig(depth_range_m=(0.5, 0.2))
    with pytest.raises(ValueError, match="depth_sampling"):
        motion.MotionConfig(depth_sampling="log")


def test_synth_record_without_new_fields_counts_as_defaults(tmp_path):
    out = tmp_path / "clips"
    cfg = synth.SynthConfig(num_frames=8)
    synth.synthesize(out, 0, cfg, seed=3, progress=False)
    record = json.loads((out / "synth.json").read_text())
    del record["config"]["crop_strategy"], record["config"]["motion_config"]["shape_sd"], record["config"]["motion_config"]["depth_sampling"]
    (out / "synth.json").write_text(json.dumps(record))  # as written before these fields existed
    synth.synthesize(out, 0, cfg, seed=3, progress=False)  # made with the defaults: accepted
    assert json.loads((out / "synth.json").read_text())["config"]["crop_strategy"] == "offbb120"  # and rewritten whole
    (out / "synth.json").write_text(json.dumps(record))
    with pytest.raises(ValueError, match=r"config.crop_strategy differ; e.g. config.crop_strategy was 'offbb120', now 'hc'"):
        synth.synthesize(out, 0, dataclasses.replace(cfg, crop_strategy="hc"), seed=3, progress=False)
    with pytest.raises(ValueError, match=r"config.motion_config differ"):
        synth.synthesize(out, 0, dataclasses.replace(cfg, motion_config=motion.MotionConfig(shape_sd=2.0)), seed=3, progress=False)
    with pytest.raises(ValueError, match=r"config.num_frames differ"):
        synth.synthesize(out, 0, synth.SynthConfig(num_frames=9), seed=3, progress=False)
    del record["config"]["num_frames"]  # an old field missing counts as its default too (64)
    (out / "synth.json").write_text(json.dumps(record))
    with pytest.raises(ValueError, match=r"config.num_frames was 64, now 8"):
        synth.synthesize(out, 0, cfg, seed=3, progress=False)


def test_synth_folder_of_another_engine_revision_is_never_added_to(tmp_path):
    out = tmp_path / "clips"
    cfg = synth.SynthConfig(num_frames=4)
    synth.synthesize(out, 1, cfg, seed=3, progress=False)
    record = json.loads((out / "synth.json").read_text())
    assert record["engine_revision"] == synth.ENGINE_REVISION
    del record["engine_revision"]  # as written before the revision was recorded: revision 1
    (out / "synth.json").write_text(json.dumps(record))
    with pytest.warns(UserWarning, match="made by synth engine revision 1"):
        summary = synth.synthesize(out, 1, cfg, seed=3, progress=False)  # complete: used as it is
    assert summary["made"] == 0 and "engine_revision" not in json.loads((out / "synth.json").read_text())
    with pytest.raises(ValueError, match=f"revision 1, and this is revision {synth.ENGINE_REVISION}.*would mix"):
        synth.synthesize(out, 2, cfg, seed=3, progress=False)
    assert not (out / "clip_00001").exists()


def test_synth_cli_crop_strategy_and_motion_knobs(tmp_path, capsys):
    out = tmp_path / "held_out"
    knobs = ["--crop-strategy", "hc", "--shape-sd", "2", "--depth-range", "0.1", "1.1", "--depth-sampling", "uniform"]
    assert cli.main(["synth", "--out", str(out), "--clips", "1", "--frames", "4", "--crops", "--crop-size", "32", "--seed", "6", *knobs]) == 0
    cfg = synth.SynthConfig(num_frames=4, crops=True, crop_size=32, crop_strategy="hc",
                            motion_config=motion.MotionConfig(shape_sd=2.0, depth_range_m=(0.1, 1.1), depth_sampling="uniform"))  # fmt: skip
    assert json.loads((out / "synth.json").read_text())["config"] == json.loads(json.dumps(synth._config_dict(cfg)))
    loaded = synth.load_clip(out / "clip_00000")
    reference = synth.make_clip(6, 0, cfg)
    assert loaded.meta["crop_strategy"] == "hc"
    for side in reference.crops:
        np.testing.assert_array_equal(loaded.gt[side]["betas"], reference.gt[side]["betas"])
        np.testing.assert_array_equal(loaded.crops[side]["R_cam_crop"], reference.crops[side]["R_cam_crop"])
    assert cli.main(["synth", "--out", str(tmp_path / "bad"), "--clips", "1", "--frames", "3", "--depth-range", "0.8", "0.2"]) == 2
    assert "depth_range_m must be 0 < near < far" in capsys.readouterr().err
