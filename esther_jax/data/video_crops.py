"""Hand crops of recorded clips (`esther crops`): a clip folder's videos -> its
`crops/<side>.npz`, what `esther train` and `esther predict` read, made as the synthetic
engine makes its crops (the same hand box, smoothing over time, crop camera of the
rectification strategy and flow tokens), so that one network reads both.

Where a hand's crop window comes from, per frame and view, in this order:

1. its 3D joints projected into the view: the teacher's labels (`labels` folder, frames
   `valid`), else the clip's ground truth (`gt.npz`, frames `onscreen`; imported HOT3D
   clips, synthetic clips), where every joint lies in front of the camera;
2. else the detectors' 2D keypoints (`keypoints.npz`): per joint the median over the
   detectors that found it with confidence >= `CropConfig.min_confidence`; a box needs
   `CropConfig.min_joints` such joints.

Gaps of at most `CropConfig.max_gap` frames between boxes are filled linearly, then the
boxes are smoothed (`crops.smooth_boxes`). A frame and view left without a box has no
crop: black pixels and a NaN box, so the network takes the view as absent (its crop
camera is held from the nearest frame with a box: finite geometry for a masked view).
`meta.json` records how the crops were made (`"crops"`: the settings and the digests of
the files the windows came from); a clip whose record matches is skipped, so an
interrupted run resumes, and a lock per clip lets two runs share a folder.
"""

import dataclasses
import pathlib
from collections.abc import Iterable, Iterator, Mapping

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Float
from tqdm import tqdm

from .. import clips
from .. import crops as crop_lib
from ..cameras import AbstractCamera, StereoRig
from ..files import exclusive_lock, file_sha256
from . import flow

CHUNK_FRAMES = 32
"""Frames whose resampling tables are computed at once (memory: CHUNK x S x S x 2 floats per view)."""


@dataclasses.dataclass(frozen=True)
class CropConfig:
    size: int = crop_lib.DEFAULT_CROP_SIZE
    """Crop side in pixels (a network config's `crop_size`: cpu-tiny 64, cpu-small 112, paper 224)."""
    strategy: str = "offbb120"
    """Rectification of the crops (appendix M, `crops.hand_crop`)."""
    min_confidence: float = 0.3
    min_joints: int = 5
    max_gap: int = 8
    """Longest run of frames without a box that is bridged by interpolation."""

    def __post_init__(self):
        if self.strategy not in crop_lib.RECTIFICATION_STRATEGIES:
            raise ValueError(f"unknown crop strategy {self.strategy!r}; choose one of {crop_lib.RECTIFICATION_STRATEGIES}")
        if self.size < 16 or not 0.0 <= self.min_confidence <= 1.0 or not 1 <= self.min_joints <= 21 or self.max_gap < 0:
            raise ValueError(f"need size >= 16, min_confidence in [0, 1], min_joints in 1..21, max_gap >= 0; got {self}")


def joint_boxes(rig: StereoRig, joints: Float[np.ndarray, "T 21 3"], valid: np.ndarray) -> Float[np.ndarray, "T 2 4"]:
    """Per frame and view the `crops.hand_box` of the joints (rig frame, m) projected into
    the view; NaN where the frame is not `valid`, a joint is not in front of the camera,
    or the view sees none of the joints (`StereoRig.is_visible`: the training loader's
    absent view)."""
    joints = jnp.asarray(np.nan_to_num(np.asarray(joints, np.float64)), jnp.result_type(float))
    uv = np.asarray(rig.project(joints), np.float64)  # (2, T, 21, 2)
    ahead = np.all(np.asarray(rig.to_views(joints))[..., 2] > 1e-2, axis=-1)  # (2, T): every joint 1 cm or more ahead
    seen = np.any(np.asarray(rig.is_visible(joints)), axis=-1)  # (2, T)
    shown = np.asarray(valid, bool) & ahead & seen & np.all(np.isfinite(uv), axis=(-1, -2))
    return np.where(shown[..., None], crop_lib.hand_box(uv), np.nan).swapaxes(0, 1)


def keypoint_boxes(keypoints: dict[str, np.ndarray], cfg: CropConfig = CropConfig()) -> Float[np.ndarray, "T 2 4"]:
    """Per frame and view the `crops.hand_box` of the detectors' keypoints (`keypoints.npz`
    arrays): each joint the median over the detectors that found it with confidence >=
    `cfg.min_confidence`; NaN with fewer than `cfg.min_joints` such joints."""
    uv = np.where((np.asarray(keypoints["conf"]) >= cfg.min_confidence)[..., None], np.asarray(keypoints["uv"], np.float64), np.nan)
    seen = np.isfinite(uv).all(axis=-1).any(axis=0)  # (T, 2, 21): some detector has the joint
    median = np.nanmedian(np.where(seen[None, ..., None], uv, 0.0), axis=0) if len(uv) > 1 else uv[0]
    median = np.where(seen[..., None], median, np.nan)  # (T, 2, 21, 2)
    return np.where((seen.sum(axis=-1) >= cfg.min_joints)[..., None], crop_lib.hand_box(median), np.nan)


def fill_gaps(boxes: Float[np.ndarray, "T 4"], max_gap: int) -> Float[np.ndarray, "T 4"]:
    """Runs of at most `max_gap` frames without a box (NaN), between two frames with one,
    filled by linear interpolation; longer runs and the ends stay NaN."""
    out = np.array(boxes, np.float64)
    have = np.flatnonzero(np.all(np.isfinite(out), axis=-1))
    for a, b in zip(have[:-1], have[1:]):
        if 1 < b - a <= max_gap + 1:
            w = (np.arange(a + 1, b) - a)[:, None] / (b - a)
            out[a + 1 : b] = (1 - w) * out[a] + w * out[b]
    return out


def hand_crop_boxes(clip_dir: str | pathlib.Path, side: str, rig: StereoRig, cfg: CropConfig = CropConfig(),
                    labels: str | pathlib.Path | None = None) -> tuple[Float[np.ndarray, "T 2 4"], dict[str, int]]:  # fmt: skip
    """The crop windows of one hand (module docstring): (T, 2, 4) source pixels, NaN where
    the view has none, smoothed; and how many frame-views each source gave ('joints',
    'keypoints', 'filled', 'none')."""
    clip_dir = pathlib.Path(clip_dir)
    T = int(clips.read_meta(clip_dir)["num_frames"])

    def read(path, kind):
        arrays = clips.load_npz(path, kind)
        frames = arrays["uv"].shape[1] if kind == "keypoints" else arrays["joints"].shape[0]
        if frames < T:
            raise clips.ClipFormatError(f"{path} has {frames} frames; the clip has {T} (meta.json num_frames)")
        return arrays

    boxes = np.full((T, 2, 4), np.nan)
    target = clips.hand_file(pathlib.Path(labels) / clip_dir.name, side, "labels") if labels is not None else None
    if target is not None and target.is_file():
        arrays = read(target, "labels")
        boxes = joint_boxes(rig, arrays["joints"][:T], arrays["valid"][:T])
    elif clips.hand_file(clip_dir, side, "gt").is_file():
        arrays = read(clips.hand_file(clip_dir, side, "gt"), "gt")
        boxes = joint_boxes(rig, arrays["joints"][:T], arrays["onscreen"][:T])
    from_joints = np.all(np.isfinite(boxes), axis=-1)
    if clips.hand_file(clip_dir, side, "keypoints").is_file():
        keypoints = read(clips.hand_file(clip_dir, side, "keypoints"), "keypoints")
        detected = keypoint_boxes({k: v[:, :T] for k, v in keypoints.items()}, cfg)
        boxes = np.where(from_joints[..., None], boxes, detected)
    found = np.all(np.isfinite(boxes), axis=-1)
    filled = np.stack([fill_gaps(boxes[:, v], cfg.max_gap) for v in range(2)], axis=1)
    smooth = np.stack([crop_lib.smooth_boxes(filled[:, v]) for v in range(2)], axis=1)
    have = np.all(np.isfinite(smooth), axis=-1)
    counts = {"joints": int(from_joints.sum()), "keypoints": int((found & ~from_joints).sum()), "filled": int((have & ~found).sum()),
              "none": int((~have).sum())}  # fmt: skip
    return smooth, counts


def _held(boxes: Float[np.ndarray, "T 4"], camera: AbstractCamera) -> Float[np.ndarray, "T 4"]:
    """Every frame's box, frames without one taking the nearest frame's with one (the
    centre of the image when no frame has one): the crop geometry of absent views."""
    have = np.flatnonzero(np.all(np.isfinite(boxes), axis=-1))
    if not len(have):
        side = 0.25 * min(camera.width, camera.height)
        centre = np.array([(camera.width - 1) / 2, (camera.height - 1) / 2])
        return np.tile(np.concatenate([centre - side, centre + side]), (len(boxes), 1))
    nearest = have[np.abs(np.arange(len(boxes))[:, None] - have[None]).argmin(axis=1)]
    return boxes[nearest]


@eqx.filter_jit
def _crop_tables(camera: AbstractCamera, boxes: Float[jax.Array, "n 4"], strategy: str, size: int):
    """The crops of a run of boxes and, per crop pixel, the source pixel to sample."""
    batch = jax.vmap(lambda b: crop_lib.hand_crop(camera, b, strategy, size))(boxes)
    return batch, jax.vmap(crop_lib.rectification_map, in_axes=(None, 0))(camera, batch)


def _chunk_geometry(
    rig: StereoRig, held: Float[np.ndarray, "T 2 4"], t: int, size: int, strategy: str
) -> tuple[Float[np.ndarray, "n 2 3 3"], Float[np.ndarray, "n 2 3 3"], list[Float[np.ndarray, "chunk S S 2"]]]:
    """The crop intrinsics, rotations and resampling tables of frames t .. t + CHUNK_FRAMES
    (n of them, fewer at the clip's end) of one hand, from its held boxes."""
    T = len(held)
    n = min(CHUNK_FRAMES, T - t)
    chunk = np.minimum(np.arange(t, t + CHUNK_FRAMES), T - 1)  # the last chunk padded: one compiled shape
    K, R, tables = np.zeros((n, 2, 3, 3), np.float32), np.zeros((n, 2, 3, 3), np.float32), []
    for v, camera in enumerate((rig.left, rig.right)):
        batch, table = _crop_tables(camera, jnp.asarray(held[chunk, v], jnp.result_type(float)), strategy, size)
        K[:, v] = np.asarray(jax.vmap(lambda c: c.K)(batch.camera))[:n]
        R[:, v] = np.asarray(batch.R_cam_crop)[:n]
        tables.append(np.asarray(table, np.float32))
    return K, R, tables


def render_crops(
    frames: Iterable[tuple[np.ndarray, np.ndarray]],
    rig: StereoRig,
    boxes: Mapping[str, Float[np.ndarray, "T 2 4"]],
    cfg: CropConfig = CropConfig(),
) -> dict[str, dict[str, np.ndarray]]:
    """The crops file arrays (docs/architecture.md: images (T, 2, S, S, 3) uint8, K,
    R_cam_crop, box, flow) of each hand in `boxes` ({side: its boxes, `hand_crop_boxes`}),
    all cut in one pass over the views' frames (any iterable of (left, right) RGB images,
    read once, frame by frame: a clip's videos are decoded once for both hands)."""
    if len({len(b) for b in boxes.values()}) > 1:
        raise ValueError(f"the hands' boxes cover different numbers of frames: {({side: len(b) for side, b in boxes.items()})}")
    T, S = len(next(iter(boxes.values()), ())), cfg.size
    cameras = (rig.left, rig.right)
    out = {side: {"images": np.zeros((T, 2, S, S, 3), np.uint8), "K": np.zeros((T, 2, 3, 3), np.float32),
                  "R_cam_crop": np.zeros((T, 2, 3, 3), np.float32)} for side in boxes}  # fmt: skip
    covered = {side: np.zeros((T, 2, S, S), bool) for side in boxes}
    present = {side: np.all(np.isfinite(b), axis=-1) for side, b in boxes.items()}
    held = {side: np.stack([_held(b[:, v], camera) for v, camera in enumerate(cameras)], axis=1) for side, b in boxes.items()}
    tables: dict[str, list[np.ndarray]] = {}
    read = 0
    for t, views in zip(range(T), frames):
        read += 1
        for v, (camera, image) in enumerate(zip(cameras, views)):
            if image.shape[:2] != (camera.height, camera.width):
                raise clips.ClipFormatError(f"frame {t} of the {('left', 'right')[v]} view is {image.shape[1]} x {image.shape[0]} px; "
                                            f"the rig's camera is {camera.width} x {camera.height}")  # fmt: skip
        for side, arrays in out.items():
            if t % CHUNK_FRAMES == 0:
                stop = min(t + CHUNK_FRAMES, T)
                arrays["K"][t:stop], arrays["R_cam_crop"][t:stop], tables[side] = _chunk_geometry(rig, held[side], t, S, cfg.strategy)
            for v, (camera, image) in enumerate(zip(cameras, views)):
                if present[side][t, v]:
                    table = tables[side][v][t % CHUNK_FRAMES]
                    arrays["images"][t, v] = crop_lib.remap_table(image, table)
                    covered[side][t, v] = crop_lib.table_coverage(table, camera)
    if read < T:
        raise clips.ClipFormatError(f"the videos hold {read} frames; the clip has {T} (meta.json num_frames)")
    for side, arrays in out.items():
        K, R = arrays["K"], arrays["R_cam_crop"]
        arrays["box"] = np.where(present[side][..., None], boxes[side], np.nan).astype(np.float32)
        arrays["flow"] = flow.clip_flow_tokens(arrays["images"][:, 0], K[:, 0] @ np.swapaxes(R[:, 0], -1, -2), covered[side][:, 0])
    return out


def _frames(clip_dir: pathlib.Path) -> Iterator[tuple[np.ndarray, np.ndarray]]:
    """The clip's (left, right) video frames, in step (a view with fewer frames ends them)."""
    return zip(*(clips.iter_video(clip_dir / "video" / f"{view}.mp4") for view in ("left", "right")))


def _evidence(clip_dir: pathlib.Path, labels: str | pathlib.Path | None) -> dict:
    """The sha256 of the files the crop windows are computed from: `rig.json`, and per hand
    each of its labels in `labels`, `gt.npz` and `keypoints.npz` that exists now. Crops are
    cut again when one changes (labels that arrived after the crops, detection run again,
    a new calibration); the videos are not hashed (replace them with --overwrite)."""
    files = {side: {"labels": None if labels is None else clips.hand_file(pathlib.Path(labels) / clip_dir.name, side, "labels"),
                    "gt": clips.hand_file(clip_dir, side, "gt"), "keypoints": clips.hand_file(clip_dir, side, "keypoints")}
             for side in clips.SIDES}  # fmt: skip
    hands = {side: {kind: file_sha256(path) for kind, path in kinds.items() if path is not None and path.is_file()} for side, kinds in files.items()}
    return {"rig": file_sha256(clip_dir / "rig.json") if (clip_dir / "rig.json").is_file() else None, **hands}


def crop_clip(clip_dir: str | pathlib.Path, cfg: CropConfig = CropConfig(), *, labels: str | pathlib.Path | None = None,
              overwrite: bool = False) -> dict:  # fmt: skip
    """Write `crops/<side>.npz` of every hand of a clip folder with a target or keypoints,
    from its `video/left.mp4` and `video/right.mp4`, and record how in `meta.json`
    (`"crops"`). Skipped (returns the record) when the clip's record already says these
    settings and the files the windows come from are unchanged (their digests: labels
    that arrive later, a new detection, are taken up); crops made otherwise (by `esther
    synth`, or with other settings) are kept unless `overwrite`. Returns the record: the
    settings, the evidence digests and per hand the frame-views whose boxes came from each
    source."""
    return _crop_clip(pathlib.Path(clip_dir), cfg, labels, overwrite)[0]


def _crop_clip(clip_dir: pathlib.Path, cfg: CropConfig, labels: str | pathlib.Path | None, overwrite: bool) -> tuple[dict, bool]:
    """`crop_clip`'s record, and whether it cut the crops (False: skipped, already done)."""
    settings = {**dataclasses.asdict(cfg), "labels": None if labels is None else str(pathlib.Path(labels).resolve())}
    with exclusive_lock(clip_dir / ".crops.lock"):
        meta = clips.read_meta(clip_dir)
        done = meta.get("crops")
        evidence = _evidence(clip_dir, labels)
        same_settings = done is not None and done.get("settings") == settings
        if same_settings and done.get("evidence") == evidence and all(clips.crops_file(clip_dir, s).is_file() for s in done["hands"]):
            return done, False
        made_elsewhere = [s for s in clips.SIDES if clips.crops_file(clip_dir, s).is_file()]
        if made_elsewhere and not overwrite and not same_settings and (done is not None or "crop_strategy" in meta):
            raise ValueError(f"{clip_dir} has crops made {'with other settings' if done else 'by esther synth'}; "
                             "overwrite them to replace them (esther crops --overwrite)")  # fmt: skip
        for view in ("left", "right"):
            if not (clip_dir / "video" / f"{view}.mp4").is_file():
                raise clips.ClipFormatError(f"{clip_dir} has no video/{view}.mp4: crops are cut from the clip's videos")
        try:
            rig = StereoRig.from_json(clip_dir / "rig.json")
        except ValueError as err:
            raise clips.ClipFormatError(str(err)) from err
        boxes, hands = {}, {}
        for side in clips.SIDES:
            boxes[side], counts = hand_crop_boxes(clip_dir, side, rig, cfg, labels)
            if counts["none"] < boxes[side].shape[0] * 2:  # some evidence of this hand
                hands[side] = counts
        for side, arrays in render_crops(_frames(clip_dir), rig, {side: boxes[side] for side in hands}, cfg).items():
            clips.save_crops(clips.crops_file(clip_dir, side), **arrays)
        for side in set(made_elsewhere) - set(hands):  # replaced crops of a hand with no evidence now: not left behind
            clips.crops_file(clip_dir, side).unlink()
        record = {"settings": settings, "evidence": evidence, "hands": hands}
        meta = {k: v for k, v in clips.read_meta(clip_dir).items() if k != "crop_strategy"}  # esther synth's, of the crops replaced
        clips.write_meta(clip_dir, **{**meta, "crops": record})
    return record, True


def crop_clips(clip_dirs: list[str | pathlib.Path], cfg: CropConfig = CropConfig(), *, labels: str | pathlib.Path | None = None,
               overwrite: bool = False, progress: bool = True) -> dict:  # fmt: skip
    """`crop_clip` for every clip folder, with a progress bar; a clip that fails is
    reported and the others go on. Returns {'cropped': [records], 'skipped': [records of
    clips already done], 'failed': [{clip, error}]}."""
    if labels is not None and not pathlib.Path(labels).is_dir():
        raise ValueError(f"the labels folder {labels} does not exist (esther label --out)")
    result: dict[str, list] = {"cropped": [], "skipped": [], "failed": []}
    for clip in tqdm([pathlib.Path(c) for c in clip_dirs], desc="crops", unit="clip", disable=not progress):
        try:
            record, cut = _crop_clip(clip, cfg, labels, overwrite)
            result["cropped" if cut else "skipped"].append({"clip": str(clip), **record})
        except (OSError, ValueError) as err:
            result["failed"].append({"clip": str(clip), "error": str(err)})
    return result


__all__ = ["CHUNK_FRAMES", "CropConfig", "crop_clip", "crop_clips", "fill_gaps", "hand_crop_boxes", "joint_boxes", "keypoint_boxes", "render_crops"]
