"""Precomputed backbone features: with a frozen backbone (the paper's DINOv3), the patch
tokens of every training crop are computed once and read instead of the crops.

`precompute_features(backbone, clip_dirs, crop_size, out)` writes, per clip and hand
with crops, `out/<clip name>-<clip digest>/<side>.npy` (`feature_file`): float16
(T, 2, P, C), the backbone's tokens of the crops resized to `crop_size` *as the network
sees them*: a left hand's of its mirrored crops (`model.mirror_clip`), since features
cannot be mirrored afterwards.
`out/features.json` records the backbone (name, sha256 of its weights) and the crop
size; a cache made by another backbone is refused. The job resumes (finished files are
kept), writes each file atomically (streamed to disk, `FEATURE_CHUNK` frames at a
time from the memory-mapped crops, so a long recorded clip fits in memory), and holds a
lock per clip, so two processes can fill one cache. `DataConfig.features = out` makes `load_example` read them
(`ClipInput.features`, no images): pixel-level augmentation is then impossible and only
the blanking of views and frames applies (`masking.corrupt`).
"""

import functools
import hashlib
import io
import pathlib

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from .. import clips
from ..cameras import StereoRig
from ..files import atomic_output, exclusive_lock, read_json, write_json
from ..model.backbones import Backbone
from ..model.esther import ClipInput, clip_input_from_crops, extract_features, mirror_clip

RECORD = "features.json"
FEATURE_CHUNK = 16
"""Frames whose crops go through the backbone at once."""


def backbone_digest(backbone: Backbone) -> str:
    """sha256 of a backbone's serialised weights: which backbone a cache belongs to."""
    buffer = io.BytesIO()
    eqx.tree_serialise_leaves(buffer, backbone)
    return hashlib.sha256(buffer.getvalue()).hexdigest()


def feature_file(root: str | pathlib.Path, clip: str | pathlib.Path, side: str) -> pathlib.Path:
    """`root/<clip name>-<digest>/<side>.npy`: clips of one name in different folders
    (a training and a held-out `clip_00000`) do not share a file."""
    return pathlib.Path(root) / _clip_key(str(clip)) / f"{side}.npy"


@functools.lru_cache(maxsize=4096)
def _clip_key(clip: str) -> str:
    return f"{pathlib.Path(clip).name}-{clips.clip_digest(clip)[:16]}"


@eqx.filter_jit
def _features(backbone, clip: ClipInput, mirrored: bool) -> jax.Array:
    """The backbone's tokens of a clip's crops (of its mirror image for a left hand)."""
    images = (mirror_clip(clip) if mirrored else clip).images
    return extract_features(backbone, images).astype(jnp.float16)


def precompute_features(
    backbone: Backbone, clip_dirs: list[str | pathlib.Path], crop_size: int, out: str | pathlib.Path, *, progress: bool = True
) -> pathlib.Path:
    """Fill the feature cache `out` for every hand with crops of `clip_dirs` (module
    docstring); returns `out`."""
    from tqdm import tqdm

    out = pathlib.Path(out)
    out.mkdir(parents=True, exist_ok=True)
    record = {"backbone": type(backbone).__name__, "backbone_sha256": backbone_digest(backbone), "crop_size": int(crop_size)}
    with exclusive_lock(out / ".features.lock"):
        if (out / RECORD).exists():
            previous = read_json(out / RECORD)
            if previous != record:
                raise ValueError(f"{out} caches the features of another backbone or crop size ({previous}); use another folder")
        else:
            write_json(out / RECORD, record)
    hands = [(pathlib.Path(c), s) for c in clip_dirs for s in clips.SIDES if clips.crops_file(c, s).is_file()]
    for clip, side in tqdm(hands, desc="features", unit="hand", disable=not progress):
        target = feature_file(out, clip, side)
        if target.exists():
            continue
        target.parent.mkdir(parents=True, exist_ok=True)
        with exclusive_lock(target.parent / f".{side}.lock"):
            if target.exists():  # another process made it meanwhile
                continue
            crops = clips.load_crops(clips.crops_file(clip, side), mmap=True)
            rig = StereoRig.from_json(clip / "rig.json")
            T = crops["images"].shape[0]
            with atomic_output(target) as tmp:
                cache = None
                for start in range(0, T, FEATURE_CHUNK):  # a chunk of frames at a time: long clips fit in memory
                    frames = np.minimum(np.arange(start, start + FEATURE_CHUNK), T - 1)  # the last chunk padded: one compiled shape
                    chunk = {k: np.asarray(crops[k][frames]) for k in ("images", "K", "R_cam_crop", "flow")}
                    tokens = np.asarray(_features(backbone, clip_input_from_crops(chunk, rig.T_rig_cams, size=crop_size), side == "left"))
                    if cache is None:
                        cache = np.lib.format.open_memmap(tmp, mode="w+", dtype=tokens.dtype, shape=(T,) + tokens.shape[1:])
                    cache[start : start + FEATURE_CHUNK] = tokens[: T - start]
                cache.flush()
                del cache
    return out


__all__ = ["FEATURE_CHUNK", "backbone_digest", "feature_file", "precompute_features"]
