"""The synthetic egocentric stereo clip engine: motion -> detections -> (rendering, crops,
flow tokens) -> clip folders (docs/architecture.md format), deterministic from a seed.

`esther synth --out DIR --clips N --frames T --rig esther [--render] [--crops] [--crop-strategy offbb120]
[--detector-preset default] [--shape-sd 1] [--depth-range NEAR FAR --depth-sampling uniform] [--seed S]`
writes `DIR/clip_00000/ ...`. Each clip depends only on (seed, clip index), is built in
a hidden temporary folder and renamed into place when complete, so an interrupted run
resumes where it stopped without redoing or corrupting finished clips.
"""

import dataclasses
import functools
import pathlib
import shutil
import tempfile
import time
import warnings

import jax
import jax.numpy as jnp
import numpy as np

from .. import cameras, clips, mano
from .. import crops as crop_lib
from ..cameras import PinholeCamera, StereoRig
from ..files import check_out_dir, exclusive_lock, read_json, remove_stale_partials, strict_json, write_json
from . import detector, flow, motion, render

CROP_SIZE = 224
ENGINE_REVISION = 5
"""Incremented when the engine makes other clips from the same settings and seed (motion,
built-in hand, renderer); `synth.json` records it, and a record without it was made at
revision 1. Revision 2: the grasp archetypes' thumbs solved for their grasps' contacts
(`mano.builtin_generator.ARCHETYPES`, built-in hand esther-open-hand-2). Revision 3: crop
pixels beyond the source image are black (the renderer drew the scene there, which no
camera records and a crop cut from a recording, `esther crops`, never shows). Revision 4:
so are crop pixels whose rays point behind the source camera (`crops.rectification_map`:
hc crops turned towards the edge of a fisheye's field, which `project` mirrored back into
the image and counted as seen; offbb crops are unchanged). Revision 5: skin of measured
albedos, with a broader sheen and a fine grain on the hand (`render.SKIN_TONES_LAB`,
`render._shade`, `render.hand_skin_albedo`), and more muted backgrounds
(`render.sample_scene`); the pixels only: motion, keypoints and ground truth are those of
revision 4. Not incremented for the fix of `crops.rectified_crop` on boxes reaching far
beyond a fisheye image: it changed only crops that were unusable (an infinite focal,
which the training loader refuses by name), never a paper-rig (esther) clip; remove the
clips the loader refuses and `synthesize` makes them anew."""


@dataclasses.dataclass(frozen=True)
class SynthConfig:
    num_frames: int = 64
    rig: str = "esther"
    detector_preset: str = "default"
    render: bool = False
    """Render both full views to video/*.mp4 and the hand crops with flow tokens."""
    crops: bool = False
    """Render only the S x S hand crops (+ flow tokens), not the full views."""
    crop_size: int = CROP_SIZE
    crop_strategy: str = "offbb120"
    """How the hand crops are rectified to pinhole (the strategies of the paper's appendix M,
    `crops.rectified_crop`); `meta.json` records it. Only the crops depend on it: the same
    seed and index give the same motion, detections and ground truth.

    - `offbb120` / `offbb90` / `offbb150`: axis-aligned crops of the source camera's image
      undistorted to a wide pinhole of virtual focal 120 / 90 / 150 px. The crop window's
      camera does not depend on that focal (the box is found in the wide image, which
      scales with it), and crops are rendered from the scene directly, not resampled from
      a finite wide image: the three give the same crops up to float rounding. On a
      pinhole rig they are the plain axis-aligned crop of the image (`crops.crop_camera`).
    - `hc`: a ray-aligned crop looking along the ray of the box centre (a crop rotation
      `R_cam_crop`, stored with the crops), on fisheye and pinhole rigs alike.
    """
    vertices: bool = False
    """Store ground-truth vertices in gt.npz."""
    motion_config: motion.MotionConfig = motion.MotionConfig()

    def __post_init__(self):
        if self.crop_strategy not in crop_lib.RECTIFICATION_STRATEGIES:
            raise ValueError(f"unknown crop_strategy {self.crop_strategy!r}; choose one of {crop_lib.RECTIFICATION_STRATEGIES}")


def clip_rng(seed: int, index: int) -> np.random.Generator:
    return np.random.default_rng([seed, index])


@dataclasses.dataclass
class Clip:
    """One clip in memory (what `write_clip` stores and `load_clip` returns); the rig's
    display name, which `rig.json` records, is `meta["rig"]` (the preset)."""

    rig: StereoRig
    meta: dict
    keypoints: dict[str, dict[str, np.ndarray]]
    gt: dict[str, dict[str, np.ndarray]]
    crops: dict[str, dict[str, np.ndarray]] = dataclasses.field(default_factory=dict)
    videos: dict[str, np.ndarray] = dataclasses.field(default_factory=dict)  # view -> (T, H, W[, 3]) uint8


def make_clip(seed: int, index: int, cfg: SynthConfig = SynthConfig()) -> Clip:
    """Sample, detect and optionally render one clip (pure function of seed and index)."""
    rng = clip_rng(seed, index)
    rig = cameras.rig_preset(cfg.rig)
    m = motion.sample_clip(rng, rig, cfg.num_frames, cfg.motion_config)
    keypoints, gt = {}, {}
    for side, track in m.hands.items():
        joints = np.asarray(track.joints, np.float64)
        keypoints[side] = detector.simulate_detectors(rng, rig, joints, m.visibility[side], cfg.detector_preset)
        p = track.params
        gt[side] = dict(
            global_orient=np.asarray(p.global_orient, np.float32),
            hand_pose=np.asarray(p.hand_pose, np.float32),
            betas=np.asarray(m.betas, np.float32),
            transl=np.asarray(p.transl, np.float32),
            joints=np.asarray(track.joints, np.float32),
            onscreen=m.onscreen[side],
            visibility=m.visibility[side],
        )
        if cfg.vertices:
            gt[side]["vertices"] = np.asarray(track.vertices, np.float32)
    meta = {
        "fps": m.fps,
        "num_frames": cfg.num_frames,
        "source": "esther-synth",
        "seed": seed,
        "index": index,
        "rig": cfg.rig,
        "detector_preset": cfg.detector_preset,
        "hands": sorted(m.hands),
        "T_world_rig": m.T_world_rig.tolist(),
        "mano_model": {side: dict(_builtin_model_record(side)) for side in sorted(m.hands)},  # what gt.npz is of
    }
    clip = Clip(rig=rig, meta=meta, keypoints=keypoints, gt=gt)
    if cfg.render or cfg.crops:
        meta["crop_strategy"] = cfg.crop_strategy
        scene = render.sample_scene(rng, grayscale=cfg.rig.startswith("hot3d"))
        _render_crops(clip, m, scene, cfg, rng)
        if cfg.render:
            _render_videos(clip, m, scene)
    return clip


def _meshes_in(vertices: dict[str, np.ndarray], m: motion.ClipMotion, scene: render.Scene, t: int, T_cam_rig: np.ndarray):
    """Hands, forearms (bare, or sleeved past the wrist) and the held box of frame t in a
    camera frame, for `render_view`."""
    to_cam = lambda x: x @ T_cam_rig[:3, :3].T + T_cam_rig[:3, 3]  # noqa: E731
    out = []
    for side, v_rig in vertices.items():
        out.append(render.Mesh(to_cam(v_rig[t]), _faces(side), scene.skin, "skin", render.hand_rest_vertices()))
        arm, faces = to_cam(m.forearms[side][t]), _forearm_faces()
        if scene.sleeve_colour is None:
            out.append(render.Mesh(arm, faces, scene.skin, "skin"))
        else:  # a cuff 7 cm up the forearm
            bare = faces.min(axis=1) // motion.FOREARM_AROUND < _SLEEVE_FROM_RING
            out.append(render.Mesh(arm, faces[bare], scene.skin, "skin"))
            out.append(render.Mesh(arm, faces[~bare], scene.sleeve_colour))
    if m.object_corners is not None:
        quads = m.object_faces
        tris = np.concatenate([quads[:, [0, 1, 2]], quads[:, [0, 2, 3]]])
        out.append(render.Mesh(to_cam(m.object_corners[t]), tris, scene.object_colour))
    return out


_SLEEVE_FROM_RING = 4
"""Forearm rings before the sleeve starts (about 7 cm from the wrist)."""


@functools.cache
def _forearm_faces() -> np.ndarray:
    return motion.forearm_faces()


@functools.cache
def _builtin_model_record(side: str) -> dict[str, str]:
    """The ground truth's parameters are of the built-in hand (motion.sample_clip)."""
    return {"id": mano.model_id(mano.load_builtin(side)), "source": "builtin"}


@functools.cache
def _faces(side: str) -> np.ndarray:
    return np.asarray(mano.load_builtin(side).faces)


def _render_videos(clip: Clip, m: motion.ClipMotion, scene: render.Scene) -> None:
    rig = m.rig
    vertices = {side: np.asarray(track.vertices, np.float64) for side, track in m.hands.items()}
    T_rig_cams, T_cams_rig = np.asarray(rig.T_rig_cams, np.float64), np.asarray(rig.T_cams_rig, np.float64)
    for view, camera, T_rig_cam, T_cam_rig in zip(("left", "right"), (rig.left, rig.right), T_rig_cams, T_cams_rig):
        rays = render._pixel_rays(camera)
        frames = []
        for t in range(len(m.T_world_rig)):
            meshes = _meshes_in(vertices, m, scene, t, T_cam_rig)
            image, _ = render.render_view(scene, camera, m.T_world_rig[t] @ T_rig_cam, meshes, rays)
            frames.append(image)
        clip.videos[view] = np.stack(frames)


def _render_crops(clip: Clip, m: motion.ClipMotion, scene: render.Scene, cfg: SynthConfig, rng: np.random.Generator) -> None:
    """Hand-following S x S crops of both views, their intrinsics and the flow tokens.

    The crop window follows the hand's projected joints (an oracle tracker, smoothed
    over time with a little jitter, as a detector-driven crop would be); the crop camera
    around it is `cfg.crop_strategy`'s."""
    rig = m.rig
    S = cfg.crop_size
    T = len(m.T_world_rig)
    T_rig_cams, T_cams_rig = np.asarray(rig.T_rig_cams, np.float64), np.asarray(rig.T_cams_rig, np.float64)
    vertices = {side: np.asarray(track.vertices, np.float64) for side, track in m.hands.items()}
    for side, track in m.hands.items():
        uv = np.moveaxis(np.asarray(rig.project(jnp.asarray(track.joints, jnp.result_type(float))), np.float64), 0, 1)  # (T, 2, 21, 2)
        images = np.zeros((T, 2, S, S) + (() if scene.grayscale else (3,)), np.uint8)
        K = np.zeros((T, 2, 3, 3), np.float32)
        R = np.zeros((T, 2, 3, 3), np.float32)
        valid = np.zeros((T, 2, S, S), bool)
        boxes = np.zeros((T, 2, 4), np.float32)
        for v, (camera, T_rig_cam, T_cam_rig) in enumerate(zip((rig.left, rig.right), T_rig_cams, T_cams_rig)):
            raw = crop_lib.hand_box(uv[:, v])
            smooth = crop_lib.smooth_boxes(raw) if T >= 5 else raw  # (clips shorter than the filter keep their raw float64 boxes)
            smooth = smooth + rng.normal(scale=0.02, size=smooth.shape) * (smooth[:, 2:3] - smooth[:, 0:1])
            make = functools.partial(crop_lib.hand_crop, camera, strategy=cfg.crop_strategy, size=S)
            batch = jax.vmap(make)(jnp.asarray(smooth, jnp.result_type(float)))  # all frames at once
            fx, fy, cx, cy = (np.asarray(x, np.float64) for x in (batch.camera.fx, batch.camera.fy, batch.camera.cx, batch.camera.cy))
            R_all = np.asarray(batch.R_cam_crop, np.float64)
            K[:, v] = np.asarray(jax.vmap(lambda c: c.K)(batch.camera))
            for t in range(T):
                crop = crop_lib.Crop(camera=PinholeCamera(fx[t], fy[t], cx[t], cy[t], S, S), R_cam_crop=jnp.asarray(R_all[t]))
                T_crop_cam = np.eye(4)
                T_crop_cam[:3, :3] = R_all[t].T
                T_world_crop = m.T_world_rig[t] @ T_rig_cam @ np.linalg.inv(T_crop_cam)
                meshes = _meshes_in(vertices, m, scene, t, T_crop_cam @ T_cam_rig)
                valid[t, v] = crop_lib.crop_coverage(camera, crop)
                rendered, _ = render.render_view(scene, crop.camera, T_world_crop, meshes)
                # beyond the source image a camera records nothing: black, as in crops cut from a recording
                images[t, v] = np.where(valid[t, v].reshape(valid[t, v].shape + (1,) * (rendered.ndim - 2)), rendered, 0)
                R[t, v] = R_all[t]
                boxes[t, v] = smooth[t]
        # The token's homography cancels the crop window's own motion. With projections
        # K R^T of source-camera rays (not K alone) it also cancels the window's rotation
        # (hc crops): P_t+1 P_t^-1 = K_t+1 R_t+1^T R_t K_t^-1. Axis-aligned crops have R = I.
        tokens = flow.clip_flow_tokens(images[:, 0], K[:, 0] @ np.swapaxes(R[:, 0], -1, -2), valid[:, 0])
        clip.crops[side] = {"images": images, "K": K, "R_cam_crop": R, "box": boxes, "flow": tokens}


# ----------------------------------------------------------------------------- I/O


def write_clip(clip: Clip, folder: str | pathlib.Path) -> pathlib.Path:
    """Write a clip folder atomically: built next to its destination, then renamed."""
    folder = pathlib.Path(folder)
    folder.parent.mkdir(parents=True, exist_ok=True)
    tmp = pathlib.Path(tempfile.mkdtemp(prefix=f".{folder.name}.partial-", dir=folder.parent))
    try:
        _write_clip_files(clip, tmp)
        if folder.exists():
            shutil.rmtree(folder)
        tmp.rename(folder)
    finally:
        shutil.rmtree(tmp, ignore_errors=True)
    return folder


def _write_clip_files(clip: Clip, tmp: pathlib.Path) -> None:
    clip.rig.to_json(tmp / "rig.json", clip.meta.get("rig", "rig"))  # the preset's name (meta's "rig")
    for side in clip.keypoints:
        clips.save_npz(clips.hand_file(tmp, side, "keypoints"), **clip.keypoints[side])
        clips.save_npz(clips.hand_file(tmp, side, "gt"), **clip.gt[side])
        if side in clip.crops:
            clips.save_crops(clips.crops_file(tmp, side), **clip.crops[side])
    for view, frames in clip.videos.items():
        clips.write_video(tmp / "video" / f"{view}.mp4", frames, clip.meta["fps"])
    clips.write_meta(tmp, **clip.meta)


def load_clip(folder: str | pathlib.Path, *, videos: bool = False) -> Clip:
    """Read a clip folder back (validating every file)."""
    folder = pathlib.Path(folder)
    meta = clips.read_meta(folder)
    try:
        rig = StereoRig.from_json(folder / "rig.json")
    except ValueError as err:
        raise clips.ClipFormatError(str(err)) from err
    keypoints, gt, crop_data = {}, {}, {}
    for side in clips.SIDES:
        path = clips.hand_file(folder, side, "keypoints")
        if not path.exists():
            continue
        keypoints[side] = clips.load_npz(path, "keypoints")
        if clips.hand_file(folder, side, "gt").exists():
            gt[side] = clips.load_npz(clips.hand_file(folder, side, "gt"), "gt")
        if clips.crops_file(folder, side).exists():
            crop_data[side] = clips.load_crops(clips.crops_file(folder, side))
    if not keypoints:
        raise clips.ClipFormatError(f"{folder} has no hands/<side>/keypoints.npz")
    clip = Clip(rig=rig, meta=meta, keypoints=keypoints, gt=gt, crops=crop_data)
    if videos:
        clip.videos = {view: clips.read_video(folder / "video" / f"{view}.mp4") for view in ("left", "right")}
    return clip


def synthesize(out: str | pathlib.Path, num_clips: int, cfg: SynthConfig = SynthConfig(), seed: int = 0, progress: bool = True) -> dict:
    """Make `num_clips` clips under `out` (resuming: finished clips are kept as they are).

    `out/synth.json` records the settings (config and seed) every clip of the folder was
    made with; it is written before the first clip. A folder made with other settings
    (or holding clips without that record) is refused with a ValueError that says what
    differs, so the record stays true: use another folder, or the same settings to add
    clips or resume. A field the record lacks (one added to `SynthConfig` or
    `MotionConfig` after the folder was made) counts as its default, which is what the
    folder's clips were made with; the record is then rewritten with it.

    The record also holds the `ENGINE_REVISION` that made the clips. A folder of another
    revision is never added to (a ValueError: its clips and new ones would differ in
    kind); when it already holds all `num_clips` clips they are used as they are, with a
    warning.
    """
    from tqdm import tqdm

    out = check_out_dir(out)
    settings = strict_json({"config": _config_dict(cfg), "seed": seed, "engine_revision": ENGINE_REVISION})
    record = out / "synth.json"
    if record.exists():
        previous = read_json(record)
        made_by = previous.get("engine_revision", 1)
        recorded = _with_defaults(previous["config"]) if isinstance(previous.get("config"), dict) else {}
        differs = sorted(
            [f"config.{k}" for k in settings["config"] if recorded.get(k) != settings["config"][k]]
            + (["seed"] if previous.get("seed") != seed else [])
        )  # fmt: skip
        if differs:
            first = differs[0]
            old = previous.get("seed") if first == "seed" else recorded.get(first.split(".", 1)[1])
            new = seed if first == "seed" else settings["config"][first.split(".", 1)[1]]
            raise ValueError(
                f"{out} holds clips made with other settings ({', '.join(differs)} differ; e.g. {first} was {old!r}, "
                f"now {new!r}): use another --out, or the same settings to add or resume clips"
            )
        if made_by != ENGINE_REVISION:
            if not all((out / _clip_name(i) / "meta.json").exists() for i in range(num_clips)):
                raise ValueError(
                    f"{out} holds clips made by synth engine revision {made_by}, and this is revision {ENGINE_REVISION} "
                    "(the clips it makes differ): adding to it would mix the two; use another --out"
                )
            warnings.warn(
                f"{out}: its clips were made by synth engine revision {made_by}, and this is revision {ENGINE_REVISION}; "
                "they are used as they are (remove the folder to make them anew)",
                stacklevel=2,
            )
            return {"made": 0, "skipped": num_clips, "seconds": 0.0, "out": str(out)}
    elif any(out.glob("clip_*")):
        raise ValueError(f"{out} holds clips but no synth.json saying how they were made: use another --out")
    else:
        write_json(record, {**settings, "clips": 0})
    made, skipped = 0, 0
    t0 = time.perf_counter()

    def attempt(index: int, *, wait: bool) -> bool:
        """Make clip `index` unless it is finished; False when another run holds it."""
        nonlocal made, skipped
        name = _clip_name(index)
        with exclusive_lock(out / f".{name}.lock", wait=wait) as locked:
            if not locked:
                return False
            if (out / name / "meta.json").exists():  # complete: clips only appear by an atomic rename
                skipped += 1
                return True
            remove_stale_partials(out, name)
            write_clip(make_clip(seed, index, cfg), out / name)
            made += 1
            return True

    busy = [i for i in tqdm(range(num_clips), desc="synth", unit="clip", disable=not progress) if not attempt(i, wait=False)]
    for index in busy:  # another run is making them: wait, then keep what it made
        attempt(index, wait=True)
    summary = {"made": made, "skipped": skipped, "seconds": time.perf_counter() - t0, "out": str(out)}
    finished = sum(1 for p in out.glob("clip_*") if (p / "meta.json").exists())
    write_json(record, {**settings, "clips": finished, "last_run": summary})
    return summary


def _clip_name(index: int) -> str:
    return f"clip_{index:05d}"


def _config_dict(cfg: SynthConfig) -> dict:
    d = dataclasses.asdict(cfg)
    d["motion_config"] = dataclasses.asdict(cfg.motion_config)
    return d


def _with_defaults(recorded: dict) -> dict:
    """A config recorded in synth.json with the fields it lacks (top level and in
    motion_config) at their defaults."""
    defaults = strict_json(_config_dict(SynthConfig()))
    motion_config = recorded.get("motion_config", {})
    if isinstance(motion_config, dict):
        motion_config = {**defaults["motion_config"], **motion_config}
    return {**defaults, **recorded, "motion_config": motion_config}
