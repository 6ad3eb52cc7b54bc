"""HOT3D in: `esther import-hot3d` (per-sequence exports and HOT3D-Clips tars) and
`esther evaluate --preset hot3d`.

The real HOT3D sample (`../shared/data/hot3d_sample/`, skipped when absent) checks the
calibration and head-motion chain against ground-truth landmarks that projectaria-tools
projected into the real Quest 3 cameras; the built-in hand, written as a MANO-format
pickle, stands in for the user's MANO files. A tiny clip tar in the documented layout
checks the tar reader and the MANO conventions (PCA with the hand mean, smplx transl).
"""

import io
import json
import pathlib
import tarfile

import cv2
import jax.numpy as jnp
import numpy as np
import pytest

from esther_jax import cameras, clips, mano
from esther_jax.cli import main
from esther_jax.data import hot3d

SAMPLE = pathlib.Path(__file__).resolve().parents[2] / "shared" / "data"
needs_sample = pytest.mark.skipif(not (SAMPLE / "hot3d_sample").is_dir(), reason="../shared/data/hot3d_sample is absent")


@pytest.fixture(scope="module")
def mano_dir(tmp_path_factory):
    folder = tmp_path_factory.mktemp("mano")
    for side in ("right", "left"):
        mano.save_mano_pkl(mano.load_builtin(side), folder / f"MANO_{side.upper()}.pkl")
    return folder


@needs_sample
def test_real_quest3_calibration_and_head_motion_reproduce_projectaria_pixels():
    seq = hot3d.read_sequence(SAMPLE / "hot3d_sample" / "Quest3_P0002_273c2819")
    data = json.loads((SAMPLE / "hot3d_quest3_landmarks_projected.json").read_text())["devices"]["quest3"]
    assert abs(float(seq.rig.baseline) - 0.064) < 0.002 and len(seq.timestamps_ns) == 15
    errors = []
    for frame in data["frames"]:
        t = int(np.flatnonzero(seq.timestamps_ns == frame["timestamp_ns"])[0])
        T_rig_world = np.linalg.inv(seq.T_world_rig[t])
        for hand in frame["hands"].values():
            X = np.asarray(hand["landmarks_world"]) @ T_rig_world[:3, :3].T + T_rig_world[:3, 3]
            uv = np.asarray(seq.rig.project(jnp.asarray(X)))
            for view, name in enumerate(hot3d.CAMERA_LABELS):
                errors.append(np.abs(uv[view] - np.asarray(hand["pixels"][name])).max())
    assert len(errors) == 60 and max(errors) < 0.05  # float32 geometry; projectaria-tools in float64


@needs_sample
@pytest.mark.parametrize("sequence", ["Quest3_P0002_273c2819", "Aria_P0003_c701bd11"])
def test_import_real_sequence_with_and_without_mano(tmp_path, mano_dir, sequence, capsys):
    source = SAMPLE / "hot3d_sample" / sequence
    assert main(["import-hot3d", str(source), "--out", str(tmp_path / "bare")]) == 0
    assert "not written: hands/right/gt.npz" in capsys.readouterr().out
    clip = tmp_path / "bare" / source.name.split("_", 1)[1]
    meta = clips.read_meta(clip)
    assert meta["fps"] == 30.0 and {m["file"] for m in meta["hot3d"]["not_written"]} >= {"hands/right/gt.npz", "hands/left/gt.npz"}
    rig = cameras.StereoRig.from_json(clip / "rig.json")
    assert abs(float(rig.baseline) - (0.064 if "Quest3" in sequence else 0.139)) < 0.002
    assert hot3d.read_trajectory(clip).shape == (meta["num_frames"], 4, 4)

    assert main(["import-hot3d", str(source), "--out", str(tmp_path / "gt"), "--mano", str(mano_dir)]) == 0
    clip = tmp_path / "gt" / clip.name
    for side in ("right", "left"):
        gt = clips.load_npz(clips.hand_file(clip, side, "gt"), "gt")
        with np.load(clip / "hands" / side / "boxes.npz") as boxes:
            box = boxes["box"]
        wrist = np.asarray(rig.project(jnp.asarray(gt["joints"][:, 0])))  # (2, T, 2)
        boxed = np.isfinite(box[..., 0]).T  # (2, T)
        margin = 20.0  # the built-in hand's wrist is not MANO's to the millimetre
        inside = (wrist[..., 0] >= box.transpose(1, 0, 2)[..., 0] - margin) & (wrist[..., 0] <= box.transpose(1, 0, 2)[..., 2] + margin) \
            & (wrist[..., 1] >= box.transpose(1, 0, 2)[..., 1] - margin) & (wrist[..., 1] <= box.transpose(1, 0, 2)[..., 3] + margin)  # fmt: skip
        assert boxed.sum() > 10 and inside[boxed].mean() > 0.95
        depth = np.asarray(rig.distances(jnp.asarray(gt["joints"][:, 0])))
        assert np.all((depth > 0.15) & (depth < 0.9))  # HOT3D hands are 0.3-0.5 m from the headset


def _clip_tar(path: pathlib.Path, frames: int, rng: np.random.Generator) -> dict:
    """A HOT3D-Clips tar in the documented layout; returns what went in."""
    rig = cameras.rig_preset("hot3d_quest3")
    cams = {}
    for stream, label, camera, T_device in (("1201-1", "camera-slam-left", rig.left, np.eye(4)),
                                            ("1201-2", "camera-slam-right", rig.right, np.asarray(rig.T_left_right, np.float64))):  # fmt: skip
        params = np.asarray(camera.params, np.float64)
        q = np.asarray(mano_quaternion(T_device[:3, :3]))
        cams[stream] = {"label": label, "stream_id": stream, "image_width": camera.width, "image_height": camera.height,
                        "projection_model_type": "CameraModelType.FISHEYE624", "projection_params": params.tolist(),
                        "T_device_from_camera": {"translation_xyz": T_device[:3, 3].tolist(), "quaternion_wxyz": q.tolist()},
                        "max_solid_angle": 1.4}  # fmt: skip
    truth = {"T_world_rig": [], "thetas": rng.normal(scale=0.5, size=(frames, 15)), "aa": rng.normal(scale=0.4, size=(frames, 3)),
             "t": rng.normal(scale=0.05, size=(frames, 3)) + [0.0, 0.0, 0.4], "betas": rng.normal(size=10), "rig": rig}  # fmt: skip
    with tarfile.open(path, "w") as tar:

        def add(name: str, data: bytes):
            info = tarfile.TarInfo(name)
            info.size = len(data)
            tar.addfile(info, io.BytesIO(data))

        add("__hand_shapes.json__", json.dumps({"mano": truth["betas"].tolist()}).encode())
        for f in range(frames):
            yaw = 0.1 * f
            T_world_rig = np.eye(4)
            T_world_rig[:3, :3] = [[np.cos(yaw), 0, np.sin(yaw)], [0, 1, 0], [-np.sin(yaw), 0, np.cos(yaw)]]
            T_world_rig[:3, 3] = [0.1 * f, 1.5, -0.2]
            truth["T_world_rig"].append(T_world_rig)
            cameras_json = {}
            for stream, c in cams.items():
                T_device = np.eye(4)
                T_device[:3, :3] = np.asarray(quaternion_matrix(c["T_device_from_camera"]["quaternion_wxyz"]))
                T_device[:3, 3] = c["T_device_from_camera"]["translation_xyz"]
                T_world_camera = T_world_rig @ T_device  # the device frame is the left camera's here
                cameras_json[stream] = {"calibration": c, "T_world_from_camera": {"translation_xyz": T_world_camera[:3, 3].tolist(),
                                        "quaternion_wxyz": np.asarray(mano_quaternion(T_world_camera[:3, :3])).tolist()}}  # fmt: skip
            hand = {"mano_pose": {"thetas": truth["thetas"][f].tolist(), "wrist_xform": np.concatenate([truth["aa"][f], truth["t"][f]]).tolist()},
                    "boxes_amodal": {"1201-1": [10.0, 20.0, 300.0, 400.0]}, "visibilities_modeled": {"1201-1": 0.9}}  # fmt: skip
            frame = f"{f:06d}"
            add(f"{frame}.cameras.json", json.dumps(cameras_json).encode())
            add(f"{frame}.hands.json", json.dumps({"right": hand}).encode())
            for stream, c in cams.items():
                ok, jpg = cv2.imencode(".jpg", np.full((c["image_height"], c["image_width"]), (30 * f) % 256, np.uint8))
                add(f"{frame}.image_{stream}.jpg", jpg.tobytes())
    return truth


def mano_quaternion(R):
    from esther_jax.rotations import matrix_to_quaternion

    return matrix_to_quaternion(jnp.asarray(R))


def quaternion_matrix(q):
    from esther_jax.rotations import quaternion_to_matrix

    return quaternion_to_matrix(jnp.asarray(q))


def test_clip_tar_import_follows_hot3d_mano_conventions(tmp_path, mano_dir):
    truth = _clip_tar(tmp_path / "clip-000123.tar", 3, np.random.default_rng(0))
    assert main(["import-hot3d", str(tmp_path / "clip-000123.tar"), "--out", str(tmp_path / "out"), "--mano", str(mano_dir)]) == 0
    clip = tmp_path / "out" / "clip-000123"
    gt = clips.load_npz(clips.hand_file(clip, "right", "gt"), "gt")
    model = mano.load_builtin("right")
    for f in range(3):
        hand_pose = np.asarray(mano.pca_to_hand_pose(model, jnp.asarray(truth["thetas"][f]), flat_hand_mean=False))
        np.testing.assert_allclose(gt["hand_pose"][f], hand_pose, atol=1e-5)  # pose = hands_mean + PCA
        world = mano.forward(model, mano.ManoParams(jnp.asarray(truth["aa"][f]), jnp.asarray(hand_pose), jnp.asarray(truth["betas"]),
                                                    jnp.asarray(truth["t"][f]) + mano.rest_joints(model, jnp.asarray(truth["betas"]))[0]))  # fmt: skip
        T_rig_world = np.linalg.inv(truth["T_world_rig"][f])
        expected = np.asarray(world.joints) @ T_rig_world[:3, :3].T + T_rig_world[:3, 3]
        np.testing.assert_allclose(gt["joints"][f], expected, atol=2e-5)
    np.testing.assert_allclose(hot3d.read_trajectory(clip), np.stack(truth["T_world_rig"]), atol=1e-5)
    assert clips.read_video(clip / "video" / "left.mp4").shape[:3] == (3, 1024, 1280)
    with np.load(clip / "hands" / "right" / "boxes.npz") as boxes:
        np.testing.assert_array_equal(boxes["box"][:, 0], [[10.0, 20.0, 300.0, 400.0]] * 3)
        assert np.all(np.isnan(boxes["box"][:, 1]))
    assert not clips.hand_file(clip, "left", "gt").exists()
    assert cameras.rig_name(clip / "rig.json") == "hot3d_clip_clip-000123"  # the display name beside the calibration


def test_broken_hot3d_inputs_are_named(tmp_path):
    (tmp_path / "seq").mkdir()
    (tmp_path / "seq" / "metadata.json").write_text(json.dumps({"headset": "Vive"}))
    with pytest.raises(hot3d.Hot3dFormatError, match="'Aria' or 'Quest3'"):
        hot3d.read_sequence(tmp_path / "seq")
    (tmp_path / "bad.tar").write_bytes(b"not a tar")
    with pytest.raises(hot3d.Hot3dFormatError, match="not a readable tar"):
        hot3d.read_clip_tar(tmp_path / "bad.tar")


def test_evaluate_preset_hot3d_scores_labels_with_the_ground_truth_shape(tmp_path, mano_dir):
    _clip_tar(tmp_path / "clip-000007.tar", 21, np.random.default_rng(1))
    assert main(["import-hot3d", str(tmp_path / "clip-000007.tar"), "--out", str(tmp_path / "gt"), "--mano", str(mano_dir)]) == 0
    gt = clips.load_npz(clips.hand_file(tmp_path / "gt" / "clip-000007", "right", "gt"), "gt")
    labels = {k: v for k, v in gt.items() if k != "onscreen"}
    labels["betas"] = np.zeros(10, np.float32)  # a wrong shape: the preset substitutes the ground truth's
    labels["transl"] = gt["transl"] + np.float32([0.01, 0.0, 0.0])  # 1 cm off: every joint moves 10 mm
    labels.update(onscreen=gt["onscreen"], valid=np.ones(21, bool), residual_px=np.zeros(21, np.float32))
    pred = tmp_path / "pred" / "clip-000007"
    clips.save_npz(clips.hand_file(pred, "right", "labels"), **labels)
    clips.write_meta(pred, fps=30.0, num_frames=21, mano_model={"right": {"id": mano.model_id(mano.load_builtin("right"))}})
    assert main(["evaluate", "--preset", "hot3d", "--pred", str(tmp_path / "pred"), "--gt", str(tmp_path / "gt"), "--out", str(tmp_path / "ev")]) == 0
    result = json.loads((tmp_path / "ev" / "metrics.json").read_text())
    assert result["dataset"]["num_frames"] == 3  # frames 0, 10, 20
    assert abs(result["dataset"]["mpjpe_mm"] - 10.0) < 0.01
