"""Reading and writing clip folders (docs/architecture.md, "File formats").

    clip/
      rig.json, meta.json
      hands/<right|left>/keypoints.npz   uv [D,T,2,21,2], conf [D,T,2,21], box [D,T,2,4], box_score [D,T,2]
      hands/<side>/gt.npz                global_orient [T,3], hand_pose [T,15,3], betas [10], transl [T,3],
                                         joints [T,21,3], onscreen [T] (vertices [T,V,3] optional)
      video/left.mp4, video/right.mp4    optional frames (RGB; grey rigs as grey)
      crops/<side>.npz                   optional hand crops: images [T,2,S,S(,3)] uint8, K [T,2,3,3], R_cam_crop [T,2,3,3],
                                         box [T,2,4] (NaN: no crop), flow [T,F] (`load_crops`)
      hands/<side>/monocular.npz         optional per-view monocular MANO (e.g. WiLoR) in each camera's
                                         frame: global_orient [T,2,3], hand_pose [T,2,15,3], transl [T,2,3]
                                         (wrist position), valid [T,2]; the teacher starts from it
    labels/<clip>/hands/<side>/labels.npz  the gt.npz keys + valid [T], residual_px [T]; optional stereo [T],
                                         converged [T] (the teacher's), onscreen_prob [T] (the network's)

A hand's labels are one typed value, `Labels` (`Labels.from_npz`, `Labels.to_npz`).

Every loader validates keys, shapes and values and says what is wrong with a file
(missing, truncated, not an npz, wrong shape, NaN); writers are atomic.
"""

import hashlib
import math
import pathlib
import zipfile
import zlib
from collections.abc import Iterable, Iterator

import cv2
import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Bool, Float

from .files import atomic_output, read_json, write_json
from .mano import ManoParams, mirror_hand_pose

SIDES = ("right", "left")

_HAND_KEYS = {
    "global_orient": ("T", 3),
    "hand_pose": ("T", 15, 3),
    "betas": (10,),
    "transl": ("T", 3),
    "joints": ("T", 21, 3),
    "onscreen": ("T",),
}
_LABEL_KEYS = {**_HAND_KEYS, "valid": ("T",), "residual_px": ("T",)}
_KEYPOINT_KEYS = {"uv": ("D", "T", 2, 21, 2), "conf": ("D", "T", 2, 21), "box": ("D", "T", 2, 4), "box_score": ("D", "T", 2)}
_MONOCULAR_KEYS = {"global_orient": ("T", 2, 3), "hand_pose": ("T", 2, 15, 3), "transl": ("T", 2, 3), "valid": ("T", 2)}
SCHEMAS = {"gt": _HAND_KEYS, "labels": _LABEL_KEYS, "keypoints": _KEYPOINT_KEYS, "monocular": _MONOCULAR_KEYS}
_NAN_ALLOWED = {"keypoints": {"uv", "box"}, "labels": {"residual_px"}}  # NaN: not detected / not observed
_UNIT_INTERVAL = {"keypoints": ("conf", "box_score")}


class ClipFormatError(ValueError):
    """A clip file is missing, unreadable or does not follow the clip format."""


def save_npz(path: str | pathlib.Path, **arrays) -> pathlib.Path:
    """Write a compressed npz atomically (a temporary file, then a rename)."""
    path = pathlib.Path(path)
    with atomic_output(path) as tmp:
        np.savez_compressed(tmp, **{k: np.asarray(v) for k, v in arrays.items()})
    return path


def load_npz(path: str | pathlib.Path, kind: str) -> dict[str, np.ndarray]:
    """Load and validate one hand file of `kind` 'gt', 'labels' or 'keypoints'."""
    path = pathlib.Path(path)
    schema = SCHEMAS[kind]
    if not path.is_file():
        raise ClipFormatError(f"{path} does not exist")
    try:
        with open(path, "rb") as f, np.load(f, allow_pickle=False) as data:
            arrays = {k: data[k] for k in data.files}
    except (zipfile.BadZipFile, zlib.error, EOFError, OSError, ValueError) as err:  # zlib: a damaged deflate stream
        raise ClipFormatError(f"{path} is truncated, damaged or not an npz file ({type(err).__name__}: {err})") from err
    missing = [k for k in schema if k not in arrays]
    if missing:
        raise ClipFormatError(f"{path}: keys {missing} are missing for a {kind} file (found {sorted(arrays)})")
    sizes: dict[str, int] = {}
    for key, spec in schema.items():
        shape = arrays[key].shape
        if len(shape) != len(spec):
            raise ClipFormatError(f"{path}: {key} has shape {shape}, expected {_format(spec)}")
        for dim, want in zip(shape, spec):
            if isinstance(want, str):
                if sizes.setdefault(want, dim) != dim:
                    raise ClipFormatError(f"{path}: {key} has shape {shape}; {want} is {sizes[want]} elsewhere in the file")
            elif dim != want:
                raise ClipFormatError(f"{path}: {key} has shape {shape}, expected {_format(spec)}")
        if arrays[key].dtype.kind not in "biuf":
            raise ClipFormatError(f"{path}: {key} must hold numbers, got dtype {arrays[key].dtype}")
        if arrays[key].dtype.kind == "f" and key not in _NAN_ALLOWED.get(kind, ()) and not np.all(np.isfinite(arrays[key])):
            raise ClipFormatError(f"{path}: {key} contains NaN or infinite values")
    if sizes.get("D") == 0:
        raise ClipFormatError(f"{path}: holds no detector (D = 0); a keypoints file has one or more")
    for key in _UNIT_INTERVAL.get(kind, ()):
        values = arrays[key][np.isfinite(arrays[key])] if arrays[key].dtype.kind == "f" else arrays[key]
        outside = (values < 0) | (values > 1)
        if np.any(outside):
            raise ClipFormatError(
                f"{path}: {key} must lie in [0, 1]; {int(outside.sum())} values do not "
                f"(from {values.min():g} to {values.max():g})"
            )
    for key in ("onscreen", "valid"):
        if key in arrays:
            arrays[key] = arrays[key].astype(bool)
    return arrays


_LABEL_EXTRAS = ("stereo", "converged", "onscreen_prob")


class Labels(eqx.Module):
    """One hand's labels over T frames, in the rig frame (metres, radians): what the teacher
    makes (`fitting.label_hand`), what the network predicts (`esther predict`), what
    `esther evaluate` scores, the demo draws and the review sheet shows. On disk it is
    `labels/<clip>/hands/<side>/labels.npz` (`from_npz`, `to_npz`: the gt.npz keys, one
    `betas [10]` per hand, plus valid, residual_px and the optional extras).

    A pytree of arrays: `jax.vmap` over frames, `jax.tree.map` over fields.
    """

    params: ManoParams
    """Per frame: global_orient [T,3], hand_pose [T,15,3], betas [T,10] (the hand's one
    shape, repeated), transl [T,3] (the wrist)."""
    joints: Float[Array, "T 21 3"]
    """The 21 keypoints (docs/architecture.md's order)."""
    onscreen: Bool[Array, "T"]
    """The hand is seen (the teacher: detected in some view; the network: emitted)."""
    valid: Bool[Array, "T"]
    """The frame's label is emitted (passes the teacher's quality bounds; the network's gate)."""
    residual_px: Float[Array, "T"]
    """Reprojection residual against the fused keypoints (pixels); NaN where not observed."""
    stereo: Bool[Array, "T"] | None = None
    """The teacher's: both views observed the hand."""
    converged: Bool[Array, "T"] | None = None
    """The teacher's: the frame's fit converged."""
    onscreen_prob: Float[Array, "T"] | None = None
    """The network's on-screen probability."""

    @property
    def betas(self) -> Float[Array, "10"]:
        """The hand's shape coefficients (one per hand)."""
        return self.params.betas[0]

    def frame(self, t: int | np.integer) -> ManoParams:
        """The MANO parameters of frame t (one hand: the kinematics' input)."""
        return jax.tree.map(lambda a: a[t], self.params)

    @classmethod
    def from_npz(cls, path: str | pathlib.Path) -> "Labels":
        """Read and validate a labels.npz (`ClipFormatError` naming what is wrong)."""
        arrays = load_npz(path, "labels")
        T = arrays["valid"].shape[0]
        if T == 0:
            raise ClipFormatError(f"{path}: holds no frame (T = 0)")
        params = ManoParams(
            jnp.asarray(arrays["global_orient"]),
            jnp.asarray(arrays["hand_pose"]),
            jnp.broadcast_to(jnp.asarray(arrays["betas"]), (T, arrays["betas"].shape[0])),
            jnp.asarray(arrays["transl"]),
        )
        extras = {k: jnp.asarray(arrays[k]) for k in _LABEL_EXTRAS if k in arrays}
        for key, value in extras.items():
            if value.shape != (T,):
                raise ClipFormatError(f"{path}: {key} has shape {value.shape}, expected [{T}]")
        for key in ("stereo", "converged"):
            if key in extras:
                extras[key] = extras[key].astype(bool)
        return cls(params, jnp.asarray(arrays["joints"]), jnp.asarray(arrays["onscreen"]), jnp.asarray(arrays["valid"]),
                   jnp.asarray(arrays["residual_px"]), **extras)  # fmt: skip

    def to_npz(self, path: str | pathlib.Path) -> pathlib.Path:
        """Write the labels.npz atomically (one `betas [10]`: the shape must not vary over frames)."""
        betas = np.asarray(self.params.betas)
        if betas.ndim != 2 or betas.shape[0] == 0 or np.any(betas != betas[:1]):
            raise ValueError(f"labels hold one shape per hand: betas must be [T, 10] equal over frames, got shape {betas.shape}")
        arrays = {
            "global_orient": self.params.global_orient,
            "hand_pose": self.params.hand_pose,
            "betas": betas[0],
            "transl": self.params.transl,
            "joints": self.joints,
            "onscreen": self.onscreen,
            "valid": self.valid,
            "residual_px": self.residual_px,
        }
        arrays.update({k: getattr(self, k) for k in _LABEL_EXTRAS if getattr(self, k) is not None})
        return save_npz(path, **{k: np.asarray(v) for k, v in arrays.items()})


CROP_KEYS = ("images", "K", "R_cam_crop", "box", "flow")

FLOW_GRID = 8
"""The camera-motion flow token's grid (appendix D): flow median-pooled over 8 x 8 cells."""
FLOW_TOKEN_SIZE = 3 * FLOW_GRID * FLOW_GRID
"""192 numbers per frame: the pooled flow (x, y per cell, divided by 224 px), then one
in-frame flag per cell (`data.flow` computes them, the motion encoder embeds them)."""


def crops_file(clip_dir: str | pathlib.Path, side: str) -> pathlib.Path:
    """Path of a hand's crops inside a clip folder (`crops/<side>.npz`)."""
    if side not in SIDES:
        raise ValueError(f"side must be one of {SIDES}, got {side!r}")
    return pathlib.Path(clip_dir) / "crops" / f"{side}.npz"


def save_crops(path: str | pathlib.Path, **arrays) -> pathlib.Path:
    """Write a hand's crops file atomically, uncompressed (pixels barely compress, and a
    stored array can be memory-mapped: `load_crops(mmap=True)` reads only the frames used)."""
    path = pathlib.Path(path)
    with atomic_output(path) as tmp:
        np.savez(tmp, **{k: np.asarray(v) for k, v in arrays.items()})
    return path


def _mapped_member(path: pathlib.Path, name: str) -> np.memmap | None:
    """The array `name` of an npz file memory-mapped, when it is stored uncompressed; None
    when it is compressed (read it whole)."""
    with zipfile.ZipFile(path) as archive:
        info = archive.getinfo(f"{name}.npy")
    if info.compress_type != zipfile.ZIP_STORED:
        return None
    with open(path, "rb") as f:
        f.seek(info.header_offset + 26)  # the local file header: name and extra-field lengths at bytes 26-29
        name_len, extra_len = np.frombuffer(f.read(4), "<u2")
        f.seek(info.header_offset + 30 + int(name_len) + int(extra_len))
        version = np.lib.format.read_magic(f)
        read_header = np.lib.format.read_array_header_1_0 if version == (1, 0) else np.lib.format.read_array_header_2_0
        shape, fortran, dtype = read_header(f)
        offset = f.tell()
    return np.memmap(path, dtype, "r", offset, shape, "F" if fortran else "C")


def load_crops(path: str | pathlib.Path, *, mmap: bool = False) -> dict[str, np.ndarray]:
    """Load and validate a hand's crops file: images (T, 2, S, S[, 3]) uint8, K and
    R_cam_crop (T, 2, 3, 3) finite, box (T, 2, 4) source pixels (NaN: no crop), flow
    (T, F) finite. With `mmap`, images written by `save_crops` are memory-mapped (read
    from disk as frames are used; compressed files, e.g. of earlier versions, are read
    whole)."""
    path = pathlib.Path(path)
    if not path.is_file():
        raise ClipFormatError(f"{path} does not exist")
    try:
        with open(path, "rb") as f, np.load(f, allow_pickle=False) as data:
            mapped = _mapped_member(path, "images") if mmap and "images" in data.files else None
            arrays = {k: mapped if k == "images" and mapped is not None else data[k] for k in data.files}
    except (zipfile.BadZipFile, zlib.error, EOFError, OSError, ValueError) as err:
        raise ClipFormatError(f"{path} is truncated, damaged or not an npz file ({type(err).__name__}: {err})") from err
    missing = [k for k in CROP_KEYS if k not in arrays]
    if missing:
        raise ClipFormatError(f"{path}: keys {missing} are missing for a crops file (found {sorted(arrays)})")
    images = arrays["images"]
    square = images.ndim in (4, 5) and images.shape[1] == 2 and images.shape[2] == images.shape[3] and images.shape[4:] in ((), (3,))
    if images.dtype != np.uint8 or not square:
        raise ClipFormatError(f"{path}: images must be (T, 2, S, S[, 3]) uint8, got {images.shape} {images.dtype}")
    T = images.shape[0]
    for key, shape in (("K", (T, 2, 3, 3)), ("R_cam_crop", (T, 2, 3, 3)), ("box", (T, 2, 4))):
        if arrays[key].shape != shape:
            raise ClipFormatError(f"{path}: {key} has shape {arrays[key].shape}, expected {_format(shape)} (T = {T} frames of images)")
    if arrays["flow"].ndim != 2 or arrays["flow"].shape[0] != T:
        raise ClipFormatError(f"{path}: flow has shape {arrays['flow'].shape}, expected [{T}, F]")
    for key in ("K", "R_cam_crop", "flow"):
        if not np.all(np.isfinite(arrays[key])):
            raise ClipFormatError(f"{path}: {key} contains NaN or infinite values")
    return arrays


def _format(spec) -> str:
    return "[" + ", ".join(str(s) for s in spec) + "]"


def read_meta(clip_dir: str | pathlib.Path) -> dict:
    """`meta.json` of a clip: an object with at least `fps` (a positive finite number)
    and `num_frames` (a positive whole number), checked here, at the edge."""
    path = pathlib.Path(clip_dir) / "meta.json"
    meta = read_json(path, ClipFormatError)
    for key in ("fps", "num_frames"):
        if key not in meta:
            raise ClipFormatError(f"{path}: '{key}' is missing")
    fps, frames = meta["fps"], meta["num_frames"]
    if isinstance(fps, bool) or not isinstance(fps, (int, float)) or not math.isfinite(fps) or fps <= 0:
        raise ClipFormatError(f"{path}: fps must be a positive finite number, got {fps!r}")
    if isinstance(frames, bool) or not isinstance(frames, int) or frames < 1:
        raise ClipFormatError(f"{path}: num_frames must be a positive whole number, got {frames!r}")
    return meta


def write_meta(clip_dir: str | pathlib.Path, **meta) -> pathlib.Path:
    return write_json(pathlib.Path(clip_dir) / "meta.json", meta)


def hand_file(root: str | pathlib.Path, side: str, kind: str) -> pathlib.Path:
    """Path of a hand file inside a clip (or label) folder."""
    if side not in SIDES:
        raise ValueError(f"side must be one of {SIDES}, got {side!r}")
    return pathlib.Path(root) / "hands" / side / f"{kind}.npz"


def clip_digest(clip_dir: str | pathlib.Path) -> str:
    """sha256 (hex) of what a clip's labels are made from: the bytes of `rig.json` and
    every hand's keypoints arrays (names, dtypes, shapes, values). Labels record it
    (`meta.json` `"source_clip"`), so an evaluation can tell the clip they belong to
    from another clip of the same folder name."""
    clip_dir = pathlib.Path(clip_dir)
    digest = hashlib.sha256()
    try:
        digest.update((clip_dir / "rig.json").read_bytes())
    except OSError as err:
        raise ClipFormatError(f"cannot read {clip_dir / 'rig.json'}: {err.strerror or err}") from err
    for side in SIDES:
        path = hand_file(clip_dir, side, "keypoints")
        if not path.is_file():
            continue
        digest.update(side.encode())
        update_digest(digest, load_npz(path, "keypoints"))
    return digest.hexdigest()


def update_digest(digest, arrays: dict) -> None:
    """Feed a file's arrays to a `hashlib` digest by content (names, dtypes, shapes,
    values), not by the file's bytes (a zip's timestamps differ between equal writes)."""
    for key in sorted(arrays):
        a = np.ascontiguousarray(arrays[key])
        digest.update(f"{key}:{a.dtype.str}:{a.shape}".encode())
        digest.update(a.tobytes())


def list_clips(root: str | pathlib.Path) -> list[pathlib.Path]:
    """Clip folders under `root` (folders holding a hands/ subfolder), sorted by name;
    `root` itself if it is one."""
    root = pathlib.Path(root)
    if not root.is_dir():
        raise ClipFormatError(f"{root} is not a folder")
    if (root / "hands").is_dir():
        return [root]
    return sorted(p for p in root.iterdir() if (p / "hands").is_dir())


def accepted_hand_poses(labels_root: str | pathlib.Path) -> Float[np.ndarray, "n 15 3"]:
    """The hand poses (axis-angle, radians) of every accepted (`valid`) frame of the
    labels under `labels_root` (`<clip>/hands/<side>/labels.npz`), as right hands: left
    hands' poses mirrored (`mano.mirror_hand_pose`). What a learned pose prior is fitted to."""
    poses = []
    for labels_dir in list_clips(labels_root):
        for side in SIDES:
            path = hand_file(labels_dir, side, "labels")
            if path.is_file():
                labels = Labels.from_npz(path)
                pose = np.asarray(labels.params.hand_pose)[np.asarray(labels.valid, bool)]
                poses.append(pose if side == "right" else np.asarray(mirror_hand_pose(jnp.asarray(pose))))
    return np.concatenate(poses) if poses else np.zeros((0, 15, 3), np.float32)


def iter_video(path: str | pathlib.Path) -> Iterator[np.ndarray]:
    """The frames of a video file one at a time, RGB (H, W, 3) uint8 (grey videos come
    out as three equal channels, as OpenCV decodes them)."""
    path = pathlib.Path(path)
    if not path.is_file():
        raise ClipFormatError(f"{path} does not exist")
    capture = cv2.VideoCapture(str(path))
    if not capture.isOpened():
        raise ClipFormatError(f"{path} cannot be opened as a video (unknown container or codec)")
    try:
        while True:
            ok, frame = capture.read()
            if not ok:
                return
            yield np.ascontiguousarray(frame[..., ::-1])
    finally:
        capture.release()


def read_video(path: str | pathlib.Path) -> np.ndarray:
    """(T, H, W, 3) RGB frames of a video (clear error when missing or unreadable)."""
    frames = list(iter_video(path))
    if not frames:
        raise ClipFormatError(f"{path} holds no readable video frames (truncated or not a video)")
    return np.stack(frames)


def write_video(path: str | pathlib.Path, frames: Iterable[np.ndarray], fps: float) -> pathlib.Path:
    """Write RGB (H, W, 3) or grey (H, W) uint8 frames (an array or any iterable, written as
    they come) as an mp4 (mp4v), atomically."""
    path = pathlib.Path(path)
    writer = None
    with atomic_output(path) as tmp:
        for frame in frames:
            if writer is None:
                h, w = frame.shape[:2]
                writer = cv2.VideoWriter(str(tmp), cv2.VideoWriter_fourcc(*"mp4v"), fps, (w, h), isColor=frame.ndim == 3)
                if not writer.isOpened():
                    raise RuntimeError(f"OpenCV cannot write {path} (no mp4v encoder in this OpenCV build)")
            writer.write(np.ascontiguousarray(frame[..., ::-1]) if frame.ndim == 3 else frame)  # RGB -> BGR
        if writer is None:
            raise ValueError(f"no frames to write to {path}")
        writer.release()
    return path
