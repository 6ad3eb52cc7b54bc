"""`esther predict`: a trained network's hands for clip folders, in the labels format.

For each clip and hand with crops (`crops/<side>.npz`), the clip is cut into windows of
the network's `num_frames` (the last one shifted back to end at the last frame; a
shorter clip is one window), each window is predicted (`predict`, `PREDICT_BATCH` windows
at a time from the memory-mapped crops: left hands mirrored
and un-mirrored, the on-screen gate applied), and every frame takes the prediction of
the first window that covers it. A view whose crop box lies wholly outside its image is
absent. The output, `<out>/<clip>/hands/<side>/labels.npz`, has the keys of the
teacher's labels with `valid = emitted` (the frames the gate emits) and
`onscreen = emitted`, the clip's shape the mean of its windows' shapes, and `meta.json`
records the model (`mano_model`: the built-in hand), the source clip's digest and the
network (`network`: its folder and the sha256 of its files, so `--resume` redoes a clip
that another network predicted), so `esther evaluate` scores it unchanged.
"""

import hashlib
import json
import pathlib
import shutil
import tempfile

import jax
import jax.numpy as jnp
import numpy as np

from .. import clips, mano
from ..cameras import StereoRig
from ..files import check_out_dir, exclusive_lock, remove_stale_partials
from .esther import ESTHER, clip_input_from_crops, load, predict


def _window_starts(frames: int, window: int) -> list[int]:
    if frames <= window:
        return [0]
    return sorted(set(list(range(0, frames - window + 1, window)) + [frames - window]))


def _views_present(rig: StereoRig, box: np.ndarray) -> np.ndarray:
    """(T, 2): the crop box (x0, y0, x1, y1, source pixels) overlaps its view's image."""
    size = np.array([[rig.left.width, rig.left.height], [rig.right.width, rig.right.height]], np.float64)
    lo, hi = box[..., :2], box[..., 2:]
    return np.all((hi > -0.5) & (lo < size - 0.5) & (hi > lo), axis=-1) & np.all(np.isfinite(box), axis=-1)


PREDICT_BATCH = 8
"""Windows predicted at once (memory: the windows' crops as float32 on the device)."""


def predict_hand(net: ESTHER, clip_dir: pathlib.Path, side: str, rig: StereoRig, *, batch: int = PREDICT_BATCH) -> clips.Labels:
    """One hand of one clip folder, every frame, as `clips.Labels`. The windows are
    predicted `batch` at a time from the memory-mapped crops, so a long recorded clip
    never holds more than a batch of windows in memory."""
    crops = clips.load_crops(clips.crops_file(clip_dir, side), mmap=True)
    cfg = net.config
    T = crops["images"].shape[0]
    present = _views_present(rig, np.asarray(crops["box"], np.float64))
    W = min(cfg.num_frames, T)
    starts = _window_starts(T, W)
    batch = min(batch, len(starts))  # short clips: no padding beyond their windows
    hand = mano.load_builtin("right")
    parts = []
    for lo in range(0, len(starts), batch):
        group = starts[lo : lo + batch]
        windows = []
        for s in group + [group[-1]] * (batch - len(group)):  # the last batch padded: one compiled shape
            sl = slice(s, s + W)
            images = np.asarray(crops["images"][sl])
            seen = present[sl].reshape(present[sl].shape + (1,) * (images.ndim - 2))
            window = {"images": np.where(seen, images, 0), "K": crops["K"][sl], "R_cam_crop": crops["R_cam_crop"][sl], "flow": crops["flow"][sl]}
            windows.append(clip_input_from_crops(window, rig.T_rig_cams, present[sl], size=cfg.crop_size))
        out = jax.device_get(predict(net, jax.tree.map(lambda *x: jnp.stack(x), *windows), hand, is_right=side == "right"))
        parts.append(jax.tree.map(lambda a: np.asarray(a)[: len(group)], out))
    out = jax.tree.map(lambda *x: np.concatenate(x), *parts)
    owner = np.full(T, -1)
    for i, s in reversed(list(enumerate(starts))):
        owner[s : s + W] = i  # the first window covering a frame wins
    offset = np.arange(T) - np.asarray(starts)[owner]
    take = lambda a: np.asarray(a)[owner, offset]  # noqa: E731
    emitted = jnp.asarray(take(out.emitted).astype(bool))
    betas = jnp.asarray(np.asarray(out.params.betas).reshape(-1, 10).mean(axis=0).astype(np.float32))
    f32 = lambda a: jnp.asarray(take(a).astype(np.float32))  # noqa: E731
    params = mano.ManoParams(f32(out.params.global_orient), f32(out.params.hand_pose), jnp.broadcast_to(betas, (T, 10)), f32(out.params.transl))
    return clips.Labels(params, f32(out.joints), emitted, emitted, jnp.full(T, jnp.nan, jnp.float32), onscreen_prob=f32(out.onscreen_prob))


def _network_digest(model_dir: pathlib.Path) -> str:
    """sha256 of a saved network's files (`save`'s folder): which network predicted."""
    digest = hashlib.sha256()
    for path in sorted(p for p in model_dir.rglob("*") if p.is_file()):
        digest.update(path.relative_to(model_dir).as_posix().encode())
        digest.update(path.read_bytes())
    return digest.hexdigest()


def _predicted_by(meta_path: pathlib.Path, clip: pathlib.Path, network: str) -> bool:
    """True when finished predictions in `meta_path` are of this clip by this network."""
    try:
        meta = json.loads(meta_path.read_text())
        return meta.get("network", {}).get("sha256") == network and meta.get("source_clip", {}).get("digest") == clips.clip_digest(clip)
    except (OSError, ValueError, AttributeError):
        return False  # missing or unreadable: predict again


def predict_folders(
    model_dir: str | pathlib.Path, clip_dirs: list[str | pathlib.Path], out_dir: str | pathlib.Path, *, resume: bool = False, progress: bool = True
) -> dict:
    """Predict every hand with crops of `clip_dirs` with the network saved in `model_dir`
    (a run folder's `model/`, or the run folder) into `out_dir` (labels format, each
    clip written atomically under its lock, its `meta.json` recording the network:
    `"network": {"folder", "sha256"}`). With `resume`, a clip already predicted by the
    same network (same sha256) from the same clip is kept. Per-clip failures are collected."""
    from tqdm import tqdm

    model_dir = pathlib.Path(model_dir)
    model_dir = model_dir / "model" if (model_dir / "model").is_dir() else model_dir
    net = load(model_dir)
    network = {"folder": str(model_dir), "sha256": _network_digest(model_dir)}
    out_dir = check_out_dir(out_dir)
    done, skipped, failed = [], [], []
    for clip in tqdm([pathlib.Path(c) for c in clip_dirs], desc="predict", unit="clip", disable=not progress):
        try:
            if resume and _predicted_by(out_dir / clip.name / "meta.json", clip, network["sha256"]):
                skipped.append(clip.name)
                continue
            meta = clips.read_meta(clip)
            rig = StereoRig.from_json(clip / "rig.json")
            sides = [s for s in clips.SIDES if clips.crops_file(clip, s).is_file()]
            if not sides:
                raise clips.ClipFormatError(f"{clip} has no crops/<side>.npz (esther crops cuts them from its videos; esther synth --crops renders them)")
            with exclusive_lock(out_dir / f".{clip.name}.lock"):
                remove_stale_partials(out_dir, clip.name)
                tmp = pathlib.Path(tempfile.mkdtemp(prefix=f".{clip.name}.partial-", dir=out_dir))
                try:
                    for side in sides:
                        predict_hand(net, clip, side, rig).to_npz(clips.hand_file(tmp, side, "labels"))
                    record = {side: {"id": mano.model_id(mano.load_builtin(side)), "source": "builtin"} for side in sides}
                    source = {"name": clip.name, "digest": clips.clip_digest(clip)}
                    clips.write_meta(tmp, **{**meta, "labelled_by": f"esther predict ({net.config.name})", "mano_model": record, "source_clip": source,
                                                     "network": network})
                    final = out_dir / clip.name
                    if final.exists():
                        shutil.rmtree(final)
                    tmp.rename(final)
                finally:
                    shutil.rmtree(tmp, ignore_errors=True)
            done.append(clip.name)
        except Exception as err:  # a bad clip never stops the batch
            failed.append({"clip": str(clip), "error": f"{type(err).__name__}: {err}"})
    return {"predicted": done, "skipped": skipped, "failed": failed, "out": str(out_dir)}


__all__ = ["PREDICT_BATCH", "predict_folders", "predict_hand"]
