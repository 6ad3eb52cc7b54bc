"""Import HOT3D (Banerjee et al., CVPR 2025) into clip folders: `esther import-hot3d`.

Two inputs, one output:

- a per-sequence export (HOT3D's VRS-derived files): `metadata.json` (`"headset"`: Aria or
  Quest3), `mano_hand_pose_trajectory.jsonl`, `headset_trajectory.csv`, `box2d_hands.csv`,
  and the calibration: Quest 3 `camera_models.json` (16 Fisheye624 parameters, fx == fy) or
  Aria `online_calibration*.jsonl` (15 parameters; the first record is used);
- a HOT3D-Clips tar (150 frames): per frame `<id>.cameras.json`, `<id>.hands.json` and the
  images `<id>.image_<stream>.jpg`, plus `__hand_shapes.json__` (the clip's MANO betas).

The stereo pair is the two SLAM cameras (`camera-slam-left` / `-right`, streams 1201-1 /
1201-2 on both headsets). The rig frame is the left SLAM camera's (our convention), so the
head moves the rig: `trajectory.npz` holds `T_world_rig [T, 4, 4]` per frame, and every
ground-truth quantity is written in the rig frame of its frame.

Ground truth (`hands/<side>/gt.npz`) needs the user's own MANO files (`--mano DIR`; never
shipped or downloaded): HOT3D's MANO convention is smplx's layer with 15 PCA components and
`flat_hand_mean=False` (pose = hands_mean + PCA), the left model's shapedirs sign fixed
(`mano.load_mano_pkl` does), and `wrist_xform` = smplx `(global_orient, transl)`, which
`mano.from_smplx` turns into our wrist translation. Frames without a hand carry the nearest
annotated frame's parameters with `onscreen` False; `onscreen` otherwise follows
appendix L (`metrics.onscreen`: at least half the joints inside a view). HOT3D's 2D boxes
go to `hands/<side>/boxes.npz` (`box [T, 2, 4]` x0, y0, x1, y1 px, NaN where absent;
`visibility [T, 2]`). Without MANO files everything else is written and `meta.json`
says what was not.
"""

import csv
import dataclasses
import json
import pathlib
import tarfile

import cv2
import jax
import jax.numpy as jnp
import numpy as np

from .. import clips, mano, metrics
from ..cameras import Fisheye624Camera, StereoRig, invert_transform
from ..files import read_json
from ..rotations import matrix_to_axis_angle, quaternion_to_matrix

LEFT_STREAM, RIGHT_STREAM = "1201-1", "1201-2"
CAMERA_LABELS = ("camera-slam-left", "camera-slam-right")
HAND_INDEX = {"0": "left", "1": "right"}
ARIA_SLAM_SIZE = (640, 480)
"""Aria SLAM image size; the online calibration does not record it."""
ARIA_SLAM_MAX_ANGLE = 1.4
"""The field-of-view limit projectaria-tools' MPS reader gives Aria's SLAM cameras (rad)."""
FPS = 30.0


class Hot3dFormatError(clips.ClipFormatError):
    """A HOT3D file is missing or does not follow HOT3D's layout."""


@dataclasses.dataclass
class Hot3dSequence:
    """A HOT3D recording (or clip) in memory, before it becomes a clip folder."""

    name: str
    device: str
    rig: StereoRig
    timestamps_ns: np.ndarray  # (T,) int64
    T_world_rig: np.ndarray  # (T, 4, 4): pose of the left SLAM camera in HOT3D's world frame
    mano: dict  # side -> {"pca" (T, 15), "global_orient" (T, 3), "transl_smplx" (T, 3), "betas" (10,), "present" (T,)}
    boxes: dict  # side -> {"box" (T, 2, 4), "visibility" (T, 2)}
    images: dict | None = None  # view -> list of encoded images (HOT3D-Clips)

    @property
    def rig_name(self) -> str:
        """The display name its clip's `rig.json` records: `hot3d_<device>_<name>`."""
        return f"hot3d_{self.device.lower()}_{self.name}"


def _pose(q_wxyz, t_xyz) -> np.ndarray:
    T = np.eye(4)
    q = np.asarray(q_wxyz, np.float64)
    T[:3, :3] = _orthonormal(np.asarray(quaternion_to_matrix(jnp.asarray(q / np.linalg.norm(q))), np.float64))
    T[:3, 3] = np.asarray(t_xyz, np.float64)
    return T


def _orthonormal(R: np.ndarray) -> np.ndarray:
    u, _, vt = np.linalg.svd(R)
    return u @ vt


def _rig(cams: dict, where: str) -> StereoRig:
    """`cams`: label -> (Fisheye624Camera, T_device_camera); `where` names the source in errors."""
    missing = [label for label in CAMERA_LABELS if label not in cams]
    if missing:
        raise Hot3dFormatError(f"{where}: cameras {missing} are missing (found {sorted(cams)})")
    (left, T_device_left), (right, T_device_right) = cams[CAMERA_LABELS[0]], cams[CAMERA_LABELS[1]]
    T_left_right = invert_transform(jnp.asarray(T_device_left)) @ jnp.asarray(T_device_right)
    return StereoRig(left, right, T_left_right)


def _quest3_cameras(path: pathlib.Path) -> dict:
    try:
        entries = json.loads(path.read_text())
        return {
            e["label"]: (
                Fisheye624Camera.from_params(e["projectionParams"], e["imageWidth"], e["imageHeight"], e.get("maxSolidAngle", 1.4)),
                _pose(e["T_Device_Camera"]["quaternion_wxyz"], e["T_Device_Camera"]["translation_xyz"]),
            )
            for e in entries
        }
    except (OSError, json.JSONDecodeError, KeyError, TypeError, ValueError) as err:
        raise Hot3dFormatError(f"{path}: not a HOT3D camera_models.json ({type(err).__name__}: {err})") from err


def _aria_cameras(path: pathlib.Path) -> dict:
    try:
        record = json.loads(path.read_text().splitlines()[0])
        out = {}
        for c in record["CameraCalibrations"]:
            if c["Label"] not in CAMERA_LABELS:
                continue
            q = c["T_Device_Camera"]["UnitQuaternion"]
            camera = Fisheye624Camera.from_params(c["Projection"]["Params"], *ARIA_SLAM_SIZE, ARIA_SLAM_MAX_ANGLE)
            out[c["Label"]] = (camera, _pose([q[0], *q[1]], c["T_Device_Camera"]["Translation"]))
        return out
    except (OSError, IndexError, json.JSONDecodeError, KeyError, TypeError, ValueError) as err:
        raise Hot3dFormatError(f"{path}: not an Aria online calibration ({type(err).__name__}: {err})") from err


def _csv_rows(path: pathlib.Path) -> list[dict]:
    try:
        with open(path, newline="") as f:
            return list(csv.DictReader(f))
    except OSError as err:
        raise Hot3dFormatError(f"cannot read {path}: {err.strerror or err}") from err


def _mano_fields(pose15, global_orient, transl, betas, present: bool) -> dict:
    return {"pca": np.asarray(pose15, np.float64), "global_orient": np.asarray(global_orient, np.float64),
            "transl_smplx": np.asarray(transl, np.float64), "betas": np.asarray(betas, np.float64), "present": present}  # fmt: skip


def _stack_hands(per_frame: list[dict], T: int) -> dict:
    """side -> arrays over frames; absent frames take the nearest present frame's values."""
    out = {}
    for side in clips.SIDES:
        present = np.array([side in f for f in per_frame])
        if not present.any():
            continue
        idx = np.flatnonzero(present)
        nearest = idx[np.abs(np.arange(T)[:, None] - idx[None]).argmin(axis=1)]
        rows = [per_frame[i][side] for i in nearest]
        out[side] = {k: np.stack([r[k] for r in rows]) for k in ("pca", "global_orient", "transl_smplx")}
        out[side]["betas"] = rows[0]["betas"]
        out[side]["present"] = present
    return out


def read_sequence(folder: str | pathlib.Path) -> Hot3dSequence:
    """A per-sequence HOT3D export (module docstring); frames = the MANO annotations."""
    folder = pathlib.Path(folder)
    meta = read_json(folder / "metadata.json", Hot3dFormatError)
    device = meta.get("headset")
    if device == "Quest3":
        cams = _quest3_cameras(folder / "camera_models.json")
    elif device == "Aria":
        found = sorted(folder.glob("online_calibration*.jsonl")) + sorted(folder.glob("mps/slam/online_calibration*.jsonl"))
        if not found:
            raise Hot3dFormatError(f"{folder}: an Aria sequence needs online_calibration*.jsonl (or mps/slam/online_calibration.jsonl)")
        cams = _aria_cameras(found[0])
    else:
        raise Hot3dFormatError(f"{folder / 'metadata.json'}: 'headset' must be 'Aria' or 'Quest3', got {device!r}")
    name = meta.get("recording_name", folder.name)
    rig = _rig(cams, f"hot3d_{device.lower()}_{name}")
    path = folder / "mano_hand_pose_trajectory.jsonl"
    try:
        records = [json.loads(line) for line in path.read_text().splitlines() if line.strip()]
    except (OSError, json.JSONDecodeError) as err:
        raise Hot3dFormatError(f"cannot read {path}: {err}") from err
    if not records:
        raise Hot3dFormatError(f"{path} holds no frames")
    timestamps = np.array([r["timestamp_ns"] for r in records], np.int64)
    per_frame = []
    for r in records:
        hands = {}
        for index, h in r.get("hand_poses", {}).items():
            if index not in HAND_INDEX:
                continue
            R = _pose(h["wrist_xform"]["q_wxyz"], [0, 0, 0])[:3, :3]
            hands[HAND_INDEX[index]] = _mano_fields(h["pose"], _rotvec(R), h["wrist_xform"]["t_xyz"], h["betas"], True)
        per_frame.append(hands)
    head = {int(row["timestamp[ns]"]): row for row in _csv_rows(folder / "headset_trajectory.csv")}
    T_world_device = []
    for t in timestamps:
        row = head.get(int(t))
        if row is None:
            raise Hot3dFormatError(f"{folder / 'headset_trajectory.csv'} has no headset pose at {t} ns (a MANO frame)")
        q = [float(row[k]) for k in ("q_wo_w", "q_wo_x", "q_wo_y", "q_wo_z")]
        T_world_device.append(_pose(q, [float(row[k]) for k in ("t_wo_x[m]", "t_wo_y[m]", "t_wo_z[m]")]))
    T_world_rig = np.stack(T_world_device) @ cams[CAMERA_LABELS[0]][1]
    frame_of = {int(t): i for i, t in enumerate(timestamps)}
    boxes = {side: {"box": np.full((len(timestamps), 2, 4), np.nan), "visibility": np.zeros((len(timestamps), 2))} for side in clips.SIDES}
    box_path = folder / "box2d_hands.csv"
    if box_path.is_file():
        for row in _csv_rows(box_path):
            view = {LEFT_STREAM: 0, RIGHT_STREAM: 1}.get(row["stream_id"])
            t = frame_of.get(int(row["timestamp[ns]"]))
            if view is None or t is None or row["hand_index"] not in HAND_INDEX or not row["x_min[pixel]"]:
                continue  # another stream, frame or hand, or a hand HOT3D saw outside this view (empty fields)
            side = HAND_INDEX[row["hand_index"]]
            x0, x1, y0, y1 = (float(row[k]) for k in ("x_min[pixel]", "x_max[pixel]", "y_min[pixel]", "y_max[pixel]"))
            boxes[side]["box"][t, view] = [x0, y0, x1, y1]
            boxes[side]["visibility"][t, view] = float(row["visibility_ratio[%]"])
    return Hot3dSequence(name, device, rig, timestamps, T_world_rig, _stack_hands(per_frame, len(timestamps)), boxes)


def _rotvec(R: np.ndarray) -> np.ndarray:
    return np.asarray(matrix_to_axis_angle(jnp.asarray(R)), np.float64)


def read_clip_tar(path: str | pathlib.Path) -> Hot3dSequence:
    """A HOT3D-Clips tar (module docstring; layout of facebookresearch/hot3d's clips README)."""
    path = pathlib.Path(path)
    try:
        tar = tarfile.open(path)
    except (OSError, tarfile.TarError) as err:
        raise Hot3dFormatError(f"{path} is not a readable tar ({err})") from err
    with tar:
        members = {m.name: m for m in tar.getmembers() if m.isfile()}

        def read(name: str) -> bytes:
            return tar.extractfile(members[name]).read()

        frames = sorted({name.split(".")[0] for name in members if name.endswith(".cameras.json")})
        if not frames:
            raise Hot3dFormatError(f"{path}: no <frame>.cameras.json inside (not a HOT3D-Clips tar?)")
        try:
            shapes = json.loads(read("__hand_shapes.json__")) if "__hand_shapes.json__" in members else {}
            betas = np.asarray(shapes.get("mano", np.zeros(10)), np.float64)
            cams, T_world_rig, per_frame, images = None, [], [], {0: [], 1: []}
            boxes = {side: {"box": np.full((len(frames), 2, 4), np.nan), "visibility": np.zeros((len(frames), 2))} for side in clips.SIDES}
            for t, frame in enumerate(frames):
                cameras = json.loads(read(f"{frame}.cameras.json"))
                streams = {}
                for stream, entry in cameras.items():
                    c = entry["calibration"]
                    streams[c.get("label", stream)] = (stream, entry)
                if cams is None:
                    cams = {}
                    for label in CAMERA_LABELS:
                        if label in streams:
                            c = streams[label][1]["calibration"]
                            camera = Fisheye624Camera.from_params(c["projection_params"], c["image_width"], c["image_height"], c.get("max_solid_angle", 1.4))
                            cams[label] = (camera, _pose(c["T_device_from_camera"]["quaternion_wxyz"], c["T_device_from_camera"]["translation_xyz"]))
                    rig = _rig(cams, f"hot3d_clip_{path.stem}")
                left = streams[CAMERA_LABELS[0]][1]["T_world_from_camera"]
                T_world_rig.append(_pose(left["quaternion_wxyz"], left["translation_xyz"]))
                hands_json = json.loads(read(f"{frame}.hands.json")) if f"{frame}.hands.json" in members else {}
                hands = {}
                for side in clips.SIDES:
                    h = hands_json.get(side)
                    if not h or "mano_pose" not in h:
                        continue
                    wrist = np.asarray(h["mano_pose"]["wrist_xform"], np.float64)
                    hands[side] = _mano_fields(h["mano_pose"]["thetas"], wrist[:3], wrist[3:], betas, True)
                    for view, label in enumerate(CAMERA_LABELS):
                        stream = streams[label][0]
                        if stream in h.get("boxes_amodal", {}):
                            boxes[side]["box"][t, view] = np.asarray(h["boxes_amodal"][stream], np.float64)
                            boxes[side]["visibility"][t, view] = float(h.get("visibilities_modeled", {}).get(stream, np.nan))
                per_frame.append(hands)
                for view, label in enumerate(CAMERA_LABELS):
                    name = f"{frame}.image_{streams[label][0]}.jpg"
                    if name in members:
                        images[view].append(read(name))
        except (KeyError, TypeError, ValueError, json.JSONDecodeError) as err:
            raise Hot3dFormatError(f"{path}: does not follow the HOT3D-Clips layout ({type(err).__name__}: {err})") from err
    timestamps = np.arange(len(frames), dtype=np.int64) * int(round(1e9 / FPS))
    complete = all(len(images[v]) == len(frames) for v in (0, 1))
    return Hot3dSequence(path.stem, "clip", rig, timestamps, np.stack(T_world_rig), _stack_hands(per_frame, len(frames)), boxes,
                         {"left": images[0], "right": images[1]} if complete else None)  # fmt: skip


def ground_truth(seq: Hot3dSequence, side: str, model: mano.ManoModel) -> dict[str, np.ndarray]:
    """The gt.npz arrays of one hand, in the rig frame of each frame."""
    h = seq.mano[side]
    dtype = jnp.result_type(float)
    betas = jnp.asarray(h["betas"], dtype)
    T_rig_world = invert_transform(jnp.asarray(seq.T_world_rig, dtype))

    def one(pca, global_orient, transl, T):
        hand_pose = mano.pca_to_hand_pose(model, pca, flat_hand_mean=False)
        world = mano.from_smplx(model, global_orient, transl, hand_pose, betas)
        params = mano.transform_params(T, world)
        out = mano.forward(model, params, check_finite=False)
        return params, out.joints

    params, joints = jax.jit(jax.vmap(one))(
        jnp.asarray(h["pca"], dtype), jnp.asarray(h["global_orient"], dtype), jnp.asarray(h["transl_smplx"], dtype), T_rig_world
    )
    onscreen = np.asarray(jax.vmap(lambda j: metrics.onscreen(j, seq.rig))(joints)) & h["present"]
    return {
        "global_orient": np.asarray(params.global_orient, np.float32), "hand_pose": np.asarray(params.hand_pose, np.float32),
        "betas": np.asarray(betas, np.float32), "transl": np.asarray(params.transl, np.float32),
        "joints": np.asarray(joints, np.float32), "onscreen": onscreen,
    }  # fmt: skip


def write_sequence(seq: Hot3dSequence, out: str | pathlib.Path, models: dict | None = None, model_sources: dict | None = None) -> dict:
    """Write `seq` as a clip folder; returns what was written and what was not (and why)."""
    out = pathlib.Path(out)
    out.mkdir(parents=True, exist_ok=True)
    written, not_written = ["rig.json", "trajectory.npz"], []
    seq.rig.to_json(out / "rig.json", seq.rig_name)
    clips.save_npz(out / "trajectory.npz", T_world_rig=seq.T_world_rig.astype(np.float64), timestamps_ns=seq.timestamps_ns)
    for side in clips.SIDES:
        if np.isfinite(seq.boxes[side]["box"]).any():
            clips.save_npz(out / "hands" / side / "boxes.npz", **seq.boxes[side])
            written.append(f"hands/{side}/boxes.npz")
        if side not in seq.mano:
            continue
        if models is None:
            not_written.append({"file": f"hands/{side}/gt.npz", "why": "needs your MANO files (--mano DIR): HOT3D's ground truth is MANO parameters"})
            continue
        clips.save_npz(clips.hand_file(out, side, "gt"), **ground_truth(seq, side, models[side]))
        written.append(f"hands/{side}/gt.npz")
    if seq.images is not None:
        for view, encoded in seq.images.items():
            frames = (cv2.imdecode(np.frombuffer(b, np.uint8), cv2.IMREAD_GRAYSCALE) for b in encoded)
            clips.write_video(out / "video" / f"{view}.mp4", frames, FPS)
            written.append(f"video/{view}.mp4")
    else:
        not_written.append({"file": "video/*.mp4", "why": "a per-sequence export has no images (they are in HOT3D's VRS files)"})
    hot3d = {"device": seq.device, "recording": seq.name, "timestamps_ns": seq.timestamps_ns.tolist(), "written": written, "not_written": not_written}
    if models is not None:
        hot3d["mano_model"] = {side: {"id": mano.model_id(models[side]), "source": (model_sources or {}).get(side)} for side in models}
    clips.write_meta(out, fps=FPS, num_frames=int(len(seq.timestamps_ns)), source=f"HOT3D {seq.device} {seq.name}", hot3d=hot3d)
    return hot3d


def import_hot3d(sources: list[str | pathlib.Path], out: str | pathlib.Path, models: dict | None = None, model_sources: dict | None = None) -> list[dict]:
    """Each source (a per-sequence folder or a HOT3D-Clips tar) -> `out/<name>/`."""
    reports = []
    for source in sources:
        source = pathlib.Path(source)
        seq = read_clip_tar(source) if source.is_file() else read_sequence(source)
        report = write_sequence(seq, pathlib.Path(out) / seq.name, models, model_sources)
        reports.append({"source": str(source), "clip": str(pathlib.Path(out) / seq.name), **report})
    return reports


def read_trajectory(clip_dir: str | pathlib.Path) -> np.ndarray:
    """`T_world_rig [T, 4, 4]` of an imported clip."""
    path = pathlib.Path(clip_dir) / "trajectory.npz"
    try:
        with np.load(path) as data:
            return data["T_world_rig"]
    except (OSError, KeyError, ValueError) as err:
        raise clips.ClipFormatError(f"cannot read {path}: {err}") from err

