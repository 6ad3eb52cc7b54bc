"""Training data from clip folders (docs/architecture.md): an index of windows, one
example per window as arrays, and the batch of a step as a pure function of
(seed, step).

- A window is `(clip folder, hand, first frame)`; `build_index` lists every window of
  `DataConfig.frames` frames at `DataConfig.stride` over the clips that have crops
  (`crops/<side>.npz`) and a target: the exact ground truth (`gt.npz`, frames on screen)
  or the teacher's labels (`<labels>/<clip>/hands/<side>/labels.npz`, frames `valid`:
  the pseudo-labels the paper trains on). The index is saved once (`save_index`).
- `load_example` reads a window: its frames of the crops (memory-mapped from files that
  `clips.save_crops` wrote, so a window of a long recorded clip reads 16 frames, not the
  clip), resized to the network's crop size with their intrinsics (`crops.resize_crops`),
  the flow tokens, the rig, the targets. A view in
  which no joint of the hand projects into the image in front of the camera is absent
  (`view_present` False, pixels zero): it never reaches the encoder as a real view.
  Left hands are mirrored into right hands (`model.mirror_clip`), their targets with
  them (`mirror_targets`, the exact inverse of what `model.unmirror` does to a
  prediction).
- `batch_indices(num_windows, batch, seed, step)`: the windows of step `step`, a fresh
  permutation per epoch seeded by (seed, epoch). No iterator state: resuming at step s
  continues the exact same stream.
- `load_batch(..., frames_apart=True)` (stage 1 only, `TrainConfig.frames_apart`): each
  example keeps its window's hand and rig but draws its frames one by one from every
  window of that hand on that rig (`frame_pools`). The frames of one window are nearly
  the same image, so a batch of 8 windows of 16 frames shows the image encoder about 8
  hands; drawn apart, 128. Only stage 1 may use it: its losses are per frame, while
  stage 2 reads the window's motion.
"""

import dataclasses
import functools
import pathlib

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from .. import clips, mano
from ..cameras import StereoRig
from ..crops import resize_crops, resize_intrinsics
from ..files import read_json, write_json
from ..model.esther import ClipInput, mirror_clip
from .features import feature_file
from .losses import Targets

TARGET_KINDS = ("gt", "labels")


@dataclasses.dataclass(frozen=True)
class DataConfig:
    frames: int = 16
    """Window length (the network's `num_frames`)."""
    stride: int = 8
    crop_size: int = 224
    """The network's crop size; stored crops are resized to it."""
    targets: str = "gt"
    """'gt' (synthetic ground truth) or 'labels' (the teacher's labels under `labels`)."""
    labels: str | None = None
    """Root of the teacher's label folders (targets = 'labels')."""
    features: str | None = None
    """A feature cache (`features.precompute_features`): read the frozen backbone's
    cached tokens instead of the crops."""

    def __post_init__(self):
        if self.targets not in TARGET_KINDS:
            raise ValueError(f"targets must be one of {TARGET_KINDS}, got {self.targets!r}")
        if self.targets == "labels" and not self.labels:
            raise ValueError("targets = 'labels' needs the labels folder (esther label --out)")
        if self.frames < 2 or self.stride < 1 or self.crop_size < 16:
            raise ValueError(f"need frames >= 2, stride >= 1, crop_size >= 16; got {self.frames}, {self.stride}, {self.crop_size}")


@dataclasses.dataclass(frozen=True)
class Window:
    clip: str
    """The clip folder."""
    side: str
    start: int


def _target_file(clip: pathlib.Path, side: str, cfg: DataConfig) -> pathlib.Path:
    if cfg.targets == "gt":
        return clips.hand_file(clip, side, "gt")
    return clips.hand_file(pathlib.Path(cfg.labels) / clip.name, side, "labels")


def build_index(clip_dirs: list[str | pathlib.Path], cfg: DataConfig) -> list[Window]:
    """Every training window of the clips (sorted by clip, hand, start). Clips shorter
    than a window, and hands without crops or targets, contribute none."""
    windows = []
    for clip in sorted(pathlib.Path(c) for c in clip_dirs):
        frames = int(clips.read_meta(clip)["num_frames"])
        for side in clips.SIDES:
            if not clips.crops_file(clip, side).is_file() or not _target_file(clip, side, cfg).is_file():
                continue
            windows += [Window(str(clip), side, start) for start in range(0, frames - cfg.frames + 1, cfg.stride)]
    return windows


def save_index(path: str | pathlib.Path, windows: list[Window], cfg: DataConfig) -> pathlib.Path:
    """Write the index (and the data config it was built with) as JSON, atomically."""
    return write_json(path, {"data": dataclasses.asdict(cfg), "windows": [dataclasses.asdict(w) for w in windows]})


def load_index(path: str | pathlib.Path) -> tuple[list[Window], DataConfig]:
    record = read_json(path)
    try:
        return [Window(**w) for w in record["windows"]], DataConfig(**record["data"])
    except (KeyError, TypeError) as err:
        raise ValueError(f"{path} is not a training index ({err})") from err


def batch_indices(num_windows: int, batch: int, seed: int, step: int) -> np.ndarray:
    """Which windows make the batch of `step`: consecutive slices of a permutation drawn
    per epoch from (seed, epoch); a pure function, so a resumed run sees the same stream."""
    if num_windows < 1:
        raise ValueError("the training index is empty: no clip has crops and targets of at least one window")
    per_epoch = max(num_windows // batch, 1)
    epoch, offset = divmod(step, per_epoch)
    order = np.random.default_rng([seed, epoch]).permutation(num_windows)
    return np.resize(order, per_epoch * batch)[offset * batch : (offset + 1) * batch]


def mirror_targets(targets: Targets, T_rig_cams: jax.Array) -> Targets:
    """Targets of a left hand in the frame of its mirrored clip (`mirror_clip`), as the
    right hand it becomes: the inverse of `model.unmirror` (which maps predictions on the
    mirrored clip back). `T_rig_cams` are the original clip's camera poses."""
    T1_inv = jnp.linalg.inv(T_rig_cams[1])
    R, t = T1_inv[:3, :3], T1_inv[:3, 3]

    def params_of(frame):
        p = mano.ManoParams(frame[0], frame[1], targets.betas, frame[2])
        return mano.mirror_params(mano.transform_params(T1_inv, p))

    params = jax.vmap(params_of)((targets.global_orient, targets.hand_pose, targets.transl))
    joints = mano.mirror_points(jnp.einsum("ij,tnj->tni", R, targets.joints) + t[None, None])
    return Targets(params.global_orient, params.hand_pose, targets.betas, params.transl, joints, targets.valid)


@functools.lru_cache(maxsize=2048)
def _clip_arrays(clip: str, side: str, target_file: str):
    """A hand's small arrays, read once per process: the shape of its crops, their
    cameras and flow tokens, its clip's rig and its targets. Kept for many hands, since a
    frames-apart batch reads frames of hands all over the training set (with 256 hands
    kept, the studies' 432 made the loader, not the step, set the pace); the images are
    `_crop_images`'."""
    folder = pathlib.Path(clip)
    crops = clips.load_crops(clips.crops_file(folder, side), mmap=True)
    kind = "gt" if target_file.endswith("gt.npz") else "labels"
    target = clips.load_npz(target_file, kind)
    return crops["images"].shape, crops["K"], crops["R_cam_crop"], crops["flow"], StereoRig.from_json(folder / "rig.json"), target, kind


@functools.lru_cache(maxsize=256)
def _crop_images(clip: str, side: str) -> np.ndarray:
    """A hand's crops, memory-mapped where the file allows (`clips.load_crops`): fewer
    kept than `_clip_arrays`, as each holds an open file."""
    return clips.load_crops(clips.crops_file(pathlib.Path(clip), side), mmap=True)["images"]


def _window_arrays(window: Window, cfg: DataConfig, frames: int | None = None) -> tuple[dict, StereoRig]:
    """The arrays `_example` reads for `frames` of a window from its start (`cfg.frames` by
    default; only those frames are read), and its clip's rig."""
    clip = pathlib.Path(window.clip)
    crops_shape, K, R_cam_crop, flow, rig, target, kind = _clip_arrays(window.clip, window.side, str(_target_file(clip, window.side, cfg)))
    sl = slice(window.start, window.start + (cfg.frames if frames is None else frames))
    if crops_shape[0] < sl.stop or target["joints"].shape[0] < sl.stop:
        raise clips.ClipFormatError(f"{clip}: the {window.side} hand has fewer than {sl.stop} frames of crops or targets")
    K = K[sl]
    dtype = np.dtype(jnp.result_type(float))
    if cfg.features:
        cached = np.load(feature_file(cfg.features, clip, window.side), mmap_mode="r")
        if cached.shape[0] < sl.stop:
            raise clips.ClipFormatError(f"{feature_file(cfg.features, clip, window.side)} has {cached.shape[0]} frames; "
                                        f"the crops have {crops_shape[0]}: rebuild the feature cache")  # fmt: skip
        visual = {"features": np.asarray(cached[sl])}
        K = resize_intrinsics(K, crops_shape[2], cfg.crop_size)  # the crops the features were computed from
    else:
        pixels, K = resize_crops(np.asarray(_crop_images(window.clip, window.side)[sl]), K, cfg.crop_size)
        visual = {"pixels": pixels if pixels.ndim == 5 else np.repeat(pixels[..., None], 3, axis=-1)}  # grey rigs: RGB
    arrays = {
        **visual,
        "K": K.astype(dtype),
        "R_cam_crop": R_cam_crop[sl].astype(dtype),
        "flow": flow[sl].astype(dtype),
        "global_orient": target["global_orient"][sl].astype(dtype),
        "hand_pose": target["hand_pose"][sl].astype(dtype),
        "betas": target["betas"].astype(dtype),
        "transl": target["transl"][sl].astype(dtype),
        "joints": target["joints"][sl].astype(dtype),
        "valid": np.asarray(target["onscreen"][sl] if kind == "gt" else target["valid"][sl], bool),
    }
    return arrays, rig


def load_example(window: Window, cfg: DataConfig, frames: int | None = None) -> tuple[ClipInput, Targets]:
    """One window as the network's input and its targets (a right hand: left hands
    mirrored); `frames` from its start (`cfg.frames` by default)."""
    arrays, rig = _window_arrays(window, cfg, frames)
    return _example(arrays, rig, window.side == "left", cfg.crop_size)


@eqx.filter_jit
def _example(arrays: dict, rig: StereoRig, left: bool, crop_size: int) -> tuple[ClipInput, Targets]:
    """The arrays of a window as (ClipInput, Targets), compiled once per shape and side.
    A view in which no joint is visible (in the image, in front of the camera) is absent
    and its pixels (or cached tokens) are zero."""
    joints = arrays["joints"]
    present = jnp.any(rig.is_visible(joints), axis=-1).T  # (T, 2)
    images = features = None
    if "pixels" in arrays:
        pixels = jnp.moveaxis(arrays["pixels"], -1, 2).astype(joints.dtype) / 255.0  # (T, 2, 3, S, S)
        images = jnp.where(present[:, :, None, None, None], pixels, 0.0)
    else:  # cached tokens, of the mirrored crops (views swapped) for a left hand
        seen = present[:, ::-1] if left else present
        features = jnp.where(seen[:, :, None, None], arrays["features"].astype(joints.dtype), 0.0)
    example = ClipInput(
        images=images,
        features=None if left else features,
        K=arrays["K"],
        R_cam_crop=arrays["R_cam_crop"],
        T_rig_cams=jnp.asarray(rig.T_rig_cams, joints.dtype),
        flow=arrays["flow"],
        view_present=present,
    )
    targets = Targets(arrays["global_orient"], arrays["hand_pose"], arrays["betas"], arrays["transl"], joints, arrays["valid"])
    if left:
        mirrored = mirror_clip(example) if images is not None else mirror_clip(example, mirrored_features=features, crop_size=crop_size)
        return mirrored, mirror_targets(targets, example.T_rig_cams)
    return example, targets


@functools.lru_cache(maxsize=2048)
def _rig_key(clip: str) -> tuple:
    """A clip's rig (camera models, sizes, intrinsics, poses; `rig.json`'s name is not part
    of the rig) as a key: clips of one rig share it."""
    leaves, structure = jax.tree.flatten(StereoRig.from_json(pathlib.Path(clip) / "rig.json"))
    return str(structure), tuple(np.asarray(x, np.float64).tobytes() for x in leaves)


@functools.lru_cache(maxsize=4)
def frame_pools(windows: tuple[Window, ...], frames: int) -> dict[tuple[str, tuple], list[tuple[str, int]]]:
    """Every frame `(clip, t)` the windows cover, grouped by hand and rig (`(side, rig
    key)`): the frames a frames-apart example may combine, since one example has one rig
    and all its frames are mirrored alike."""
    pools: dict[tuple[str, tuple], set] = {}
    for w in windows:
        pools.setdefault((w.side, _rig_key(w.clip)), set()).update((w.clip, t) for t in range(w.start, w.start + frames))
    return {key: sorted(members) for key, members in pools.items()}


def frames_apart_example(window: Window, pool: list[tuple[str, int]], cfg: DataConfig, rng: np.random.Generator) -> tuple[ClipInput, Targets]:
    """An example of `cfg.frames` frames drawn at random from `pool` (the frames of the
    window's hand and rig, `frame_pools`), made in one `_example` call as a window is. The
    rig is the pool's; the shape (`betas`) is the first drawn frame's hand (stage 1 reads
    only the joints)."""
    drawn = [_window_arrays(Window(clip, window.side, t), cfg, frames=1) for clip, t in (pool[i] for i in rng.integers(len(pool), size=cfg.frames))]
    parts, rig = [arrays for arrays, _ in drawn], drawn[0][1]
    arrays = {k: parts[0][k] if k == "betas" else np.concatenate([part[k] for part in parts]) for k in parts[0]}
    return _example(arrays, rig, window.side == "left", cfg.crop_size)


def load_batch(windows: list[Window], cfg: DataConfig, batch: int, seed: int, step: int, *, part: slice = slice(None),
               frames_apart: bool = False) -> tuple[ClipInput, Targets]:  # fmt: skip
    """The stacked examples of `step` (leading batch axis); `part` of them only (one
    process's share of a multi-process batch, `loop.process_batch_slice`). With
    `frames_apart`, each example's frames are drawn from its window's pool
    (`frames_apart_example`), seeded by (seed, step, position in the batch): the same
    frames whichever process loads the example."""
    chosen = batch_indices(len(windows), batch, seed, step)
    positions = np.arange(len(chosen))[part]
    if not frames_apart:
        examples = [load_example(windows[chosen[p]], cfg) for p in positions]
    else:
        pools = frame_pools(tuple(windows), cfg.frames)
        examples = []
        for p in positions:
            window = windows[chosen[p]]
            pool = pools[(window.side, _rig_key(window.clip))]
            examples.append(frames_apart_example(window, pool, cfg, np.random.default_rng([seed, step, int(p)])))
    return jax.tree.map(lambda *x: jnp.stack(x), *examples)


__all__ = [
    "DataConfig", "TARGET_KINDS", "Window", "batch_indices", "build_index", "frame_pools", "frames_apart_example", "load_batch",
    "load_example", "load_index", "mirror_targets", "save_index",
]  # fmt: skip
