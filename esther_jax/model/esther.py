"""ESTHER: backbone -> stereo image encoder -> masked motion encoder -> fusion decoder -> MANO.

`ESTHER(cfg, key=...)` holds the weights; `model(clip, hand_model, motion_mask=...)`
runs one right-hand clip (vmap for batches). The hand model is data, not weights: it
is passed beside the network. `predict` is the inference entry point (left hands by
mirroring, on-screen gating); `save`/`load` write a folder with the JSON config and
the serialised leaves.
"""

import dataclasses
import json
import os
import pathlib
import shutil
import tempfile
from collections.abc import Sequence

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Bool, Float, PRNGKeyArray

from ..files import file_sha256, read_json
from ..crops import crop_poses, resize_crops
from ..mano import ManoModel, ManoParams, forward_rotations, load_builtin, mirror_params, mirror_points, transform_params
from ..rotations import matrix_to_axis_angle
from .backbones import Backbone, make_backbone
from .config import ModelConfig, config
from .fusion_decoder import Decoded, FusionDecoder, evidence_statistics
from .motion_encoder import MotionEncoder, MotionEvidence
from .stereo_encoder import NUM_KEYPOINTS, ImageEvidence, StereoImageEncoder

_MIRROR = (-1.0, 1.0, 1.0)


class ClipInput(eqx.Module):
    """What the network sees of one hand in one clip (views: 0 left, 1 right).

    Exactly one of `images` and `features` is needed: features are the backbone's patch
    tokens of the same crops (`extract_features`), the usual input with a frozen backbone.
    """

    images: Float[Array, "*batch T 2 3 S S"] | None
    """Hand crops, RGB in [0, 1], channels first."""
    features: Float[Array, "*batch T 2 P C"] | None
    """Precomputed backbone patch tokens of the crops."""
    K: Float[Array, "*batch T 2 3 3"]
    """Crop-camera intrinsics (pixels of the S x S crop)."""
    R_cam_crop: Float[Array, "*batch T 2 3 3"]
    """Rotation of each crop camera in its source camera (identity for axis-aligned crops)."""
    T_rig_cams: Float[Array, "*batch 2 4 4"]
    """Pose of each source camera in the rig frame (the left camera's)."""
    flow: Float[Array, "*batch T 192"]
    """Camera-motion flow token per frame (appendix D; computed on the left view)."""
    view_present: Bool[Array, "*batch T 2"]
    """False where a view is missing or blanked: it is replaced by the view-mask token."""


_CROP_NEAR_M = 1e-3
"""Metres: a joint nearer to a crop camera than this (or behind it) projects nowhere in its
crop (its pixel is not used, and it is not inside the crop)."""


def crop_projections(
    clip: ClipInput, joints: Float[Array, "T 21 3"], crop_size: int
) -> tuple[Float[Array, "T 2 21 2"], Float[Array, "T 2 21"], Bool[Array, "T 2 21"]]:
    """Pixels (crop pixel centres) and depths (m) of rig-frame joints in each view's crop
    camera, and whether each projects inside its S x S crop in front of the camera (the
    in-frame projection validity the visibility head learns)."""
    T_rig_crop = crop_poses(jnp.asarray(clip.R_cam_crop, jnp.float32), jnp.asarray(clip.T_rig_cams, jnp.float32))
    R, t = T_rig_crop[..., :3, :3], T_rig_crop[..., :3, 3]  # (T, 2, 3, 3), (T, 2, 3)
    X = jnp.einsum("tvji,tvnj->tvni", R, joints[:, None, :, :] - t[:, :, None, :])  # crop-camera frame
    z = X[..., 2]
    zs = jnp.where(z > _CROP_NEAR_M, z, 1.0)
    K = jnp.asarray(clip.K, jnp.float32)
    uv = jnp.einsum("tvij,tvnj->tvni", K[..., :2, :2], X[..., :2] / zs[..., None]) + K[:, :, None, :2, 2]
    inside = jnp.all((uv >= -0.5) & (uv < crop_size - 0.5), axis=-1) & (z > _CROP_NEAR_M)
    return uv, z, inside


class ESTHEROutput(eqx.Module):
    """Everything the network computes for one clip (right hand, rig frame, metres)."""

    image: ImageEvidence
    motion: MotionEvidence
    decoded: Decoded
    params: ManoParams
    """Per frame (betas repeated): axis-angle pose, betas, wrist translation."""
    joints: Float[Array, "T 21 3"]
    vertices: Float[Array, "T V 3"]


class ESTHER(eqx.Module):
    backbone: Backbone | None
    """None when the config reads precomputed features."""
    image_encoder: StereoImageEncoder
    motion_encoder: MotionEncoder
    fusion_decoder: FusionDecoder
    config: ModelConfig = eqx.field(static=True)

    def __init__(self, cfg: ModelConfig | str = "paper", *, key: PRNGKeyArray):
        cfg = config(cfg) if isinstance(cfg, str) else cfg
        k0, k1, k2, k3 = jax.random.split(key, 4)
        self.backbone = None if cfg.precomputed_features else make_backbone(cfg.backbone_spec, key=k0)
        self.image_encoder = StereoImageEncoder(cfg, key=k1)
        self.motion_encoder = MotionEncoder(cfg, key=k2)
        self.fusion_decoder = FusionDecoder(cfg, key=k3)
        self.config = cfg

    def _views_seen(self, clip: ClipInput) -> Bool[Array, "T 2"]:
        """The views the network reads of one clip: `clip.view_present`, less the second
        view in a monocular config. Checks that `clip` is one clip of at most
        `num_frames` frames."""
        cfg = self.config
        T = clip.flow.shape[0]
        if clip.view_present.shape != (T, 2) or clip.K.shape != (T, 2, 3, 3) or clip.T_rig_cams.shape != (2, 4, 4):
            raise ValueError(
                f"ClipInput of one clip: flow (T, 192), view_present (T, 2), K (T, 2, 3, 3), T_rig_cams (2, 4, 4); got "
                f"{clip.flow.shape}, {clip.view_present.shape}, {clip.K.shape}, {clip.T_rig_cams.shape} (vmap over clips)"
            )
        if T > cfg.num_frames:
            raise ValueError(f"clip has {T} frames; config {cfg.name!r} was built for at most {cfg.num_frames}")
        present = clip.view_present
        if cfg.monocular:
            present = present & jnp.asarray([[True, False]])
        return present

    def patch_features(self, clip: ClipInput) -> Float[Array, "T 2 P C"]:
        """The backbone's patch tokens of the clip's crops (or its precomputed features)."""
        cfg = self.config
        compute = self.image_encoder.feature_proj.weight.dtype  # the weights' dtype (`cast`)
        if clip.features is not None:
            return clip.features.astype(compute)
        if clip.images is None:
            raise ValueError("ClipInput has neither images nor features")
        if self.backbone is None:
            raise ValueError(f"config {cfg.name!r} reads precomputed features (precomputed_features=True); got images only")
        S = cfg.crop_size
        if clip.images.shape[-3:] != (3, S, S) or clip.images.shape[-4] != 2:
            raise ValueError(f"images must be (T, 2, 3, {S}, {S}) for config {cfg.name!r}; got {clip.images.shape}")
        features = self.backbone(clip.images.astype(compute))
        return jax.lax.stop_gradient(features) if cfg.freeze_backbone else features

    def __call__(
        self, clip: ClipInput, hand_model: ManoModel, *, motion_mask: Bool[Array, "T 21"] | None = None
    ) -> ESTHEROutput:
        """Run one right-hand clip.

        Args:
            clip: one clip (no batch axis; vmap for batches).
            hand_model: the MANO-format model for the forward kinematics (a right hand).
            motion_mask: True where the motion encoder must not see F (training's token
                masking); the decoder reads the motion mask token there too.
        """
        present = self._views_seen(clip)
        T = present.shape[0]
        mask = jnp.zeros((T, NUM_KEYPOINTS), bool) if motion_mask is None else motion_mask
        image = self.image_encoder(self.patch_features(clip), clip.K, clip.R_cam_crop, clip.T_rig_cams, present)
        masked = self.motion_encoder.mask(image.features, mask)
        motion = self.motion_encoder(masked, clip.flow)
        evidence = evidence_statistics(image, present, mask)
        wrist_valid = image.triangulation_valid[:, 0] & ~mask[:, 0]
        decoded = self.fusion_decoder(masked, motion, evidence, image.triangulated[:, 0], wrist_valid)
        hands = jax.vmap(forward_rotations, in_axes=(None, 0, None, 0))(
            hand_model, decoded.rotations, decoded.betas, decoded.transl
        )
        axis_angle = matrix_to_axis_angle(decoded.rotations)
        params = ManoParams(
            global_orient=axis_angle[:, 0],
            hand_pose=axis_angle[:, 1:],
            betas=jnp.broadcast_to(decoded.betas, (T, decoded.betas.shape[0])),
            transl=decoded.transl,
        )
        return ESTHEROutput(image=image, motion=motion, decoded=decoded, params=params, joints=hands.joints, vertices=hands.vertices)


def cross_view_attention(net: ESTHER, clip: ClipInput) -> Float[Array, "layers T 2 heads P P"]:
    """The cross-view attention probabilities of the stereo blocks on one clip, as the
    forward pass `net(clip, ...)` computes them (same weights, same code): the probe of
    the paper's size-depth binding study (section 5.4, figure 7). Vmap over clips.

    Entry `[l, t, v, h, q, k]` is the softmax weight that, in stereo block l and frame t,
    head h of view v's patch token q (views: 0 left, 1 right) gives to patch token k of
    the other view 1 - v. Patches are row-major over the crop's grid x grid patch tiling
    (`crops.patch_centres`); the keys are exactly the other view's P patch tokens (no
    class or register tokens), so every row sums to 1. The views are those the network
    reads: a view that is absent (`view_present` False) or removed by a monocular config
    (the second view) is the learned view-mask token at every patch, so
    `[:, :, 1 - kept]` are the placeholder's queries into the kept view.

    Memory: layers x T x 2 x heads x P^2 numbers per clip (the paper's config: 4 x 16 x
    2 x 8 x 196^2, 160 MB in float32).

    Raises:
        ValueError: the config has no cross-view attention (`cross_view=False`).
    """
    present = net._views_seen(clip)
    return net.image_encoder.cross_view_attention(net.patch_features(clip), clip.K, clip.R_cam_crop, clip.T_rig_cams, present)


def trainable(model: ESTHER):
    """Filter spec (a pytree of bools like `model`) of the weights training updates:
    every inexact array except a frozen backbone's. Use with `eqx.partition`."""
    spec = jax.tree.map(eqx.is_inexact_array, model)
    if model.backbone is not None and model.config.freeze_backbone:
        spec = eqx.tree_at(lambda m: m.backbone, spec, jax.tree.map(lambda _: False, model.backbone))
    return spec


def cast(model: ESTHER, dtype) -> ESTHER:
    """The network with its floating-point weights in `dtype` (e.g. `jnp.bfloat16` for
    mixed-precision training: the step casts float32 master weights with this, and the
    gradients flow back to them). The network computes in its weights' dtype and keeps
    the geometry (Plucker rays, triangulation, 6D -> rotation, forward kinematics) in
    its inputs' (the clip's calibration) dtype."""
    return jax.tree.map(lambda x: x.astype(dtype) if eqx.is_inexact_array(x) else x, model)


def extract_features(backbone: Backbone, images: Float[Array, "*batch 2 3 S S"]) -> Float[Array, "*batch 2 P C"]:
    """Backbone patch tokens of crops, one frame at a time (bounded memory): what a
    frozen-backbone training set stores once (`ClipInput.features`)."""
    lead = images.shape[:-4]
    flat = images.reshape((-1,) + images.shape[-4:])
    out = jax.lax.map(backbone, flat)
    return out.reshape(lead + out.shape[1:])


def parameter_counts(name: str | ModelConfig = "paper") -> dict[str, int]:
    """Parameter counts by part, from shapes only (`eqx.filter_eval_shape`, nothing allocated).

    Keys: image_encoder (stereo blocks and heads), motion_encoder, fusion_decoder,
    trainable (their sum, plus the backbone when it is not frozen), backbone, total.
    """
    cfg = config(name) if isinstance(name, str) else name
    shapes = eqx.filter_eval_shape(ESTHER, cfg.replace(precomputed_features=True), key=jax.random.key(0))
    backbone = eqx.filter_eval_shape(make_backbone, cfg.backbone_spec, key=jax.random.key(0))

    def count(tree) -> int:
        return int(sum(np.prod(leaf.shape, dtype=np.int64) for leaf in jax.tree.leaves(tree) if hasattr(leaf, "shape")))

    parts = {
        "image_encoder": count(shapes.image_encoder),
        "motion_encoder": count(shapes.motion_encoder),
        "fusion_decoder": count(shapes.fusion_decoder),
    }
    parts["backbone"] = count(backbone)
    head = sum(parts[k] for k in ("image_encoder", "motion_encoder", "fusion_decoder"))
    parts["trainable"] = head + (0 if cfg.freeze_backbone else parts["backbone"])
    parts["total"] = head + parts["backbone"]
    return parts


# ----------------------------------------------------------------------------- left hands


def _mirror_conjugate(A: Float[Array, "*batch n n"]) -> Float[Array, "*batch n n"]:
    """`M A M` with `M = diag(-1, 1, 1[, 1])`: a rotation or rigid transform seen in the mirror world."""
    m = jnp.asarray(_MIRROR + (1.0,) * (A.shape[-1] - 3), A.dtype)
    return A * jax.lax.broadcast_to_rank(m[:, None], A.ndim) * jax.lax.broadcast_to_rank(m[None, :], A.ndim)


def mirror_clip(clip: ClipInput, *, mirrored_features: Array | None = None, crop_size: int | None = None) -> ClipInput:
    """The mirror image of a clip (x -> -x in the rig frame), views swapped.

    A left hand becomes a right hand seen by a rig whose left camera is the mirrored
    right camera: crops are flipped horizontally (u -> S - 1 - u), crop rotations and
    camera poses conjugated by the mirror, and the rig frame moved to the new left
    camera. The flow token is mirrored (the left view's flow stands in for the new left
    view's). Mirroring twice gives the input back when its rig frame is its left camera.
    Leading batch axes are kept.

    Features cannot be mirrored: a clip without crops needs `mirrored_features`, the
    backbone's features of its mirrored crops (`extract_features` of this function's
    `images`, as a feature cache stores them), and the crops' side `crop_size`.
    """
    if clip.images is None and (mirrored_features is None or crop_size is None):
        raise ValueError("cannot mirror precomputed features: mirror the crops (mirror_clip), extract their features and pass "
                         "them as mirrored_features with the crop_size")  # fmt: skip
    size = clip.images.shape[-1] if clip.images is not None else crop_size
    K = clip.K[..., ::-1, :, :]
    K = K.at[..., 0, 2].set(size - 1.0 - K[..., 0, 2])
    T_mirror = _mirror_conjugate(clip.T_rig_cams)[..., ::-1, :, :]
    lead = clip.flow.shape[:-1]
    flow_grid = clip.flow[..., :128].reshape(lead + (8, 8, 2))[..., ::-1, :]
    flow_grid = flow_grid * jax.lax.broadcast_to_rank(jnp.asarray([-1.0, 1.0], clip.flow.dtype), flow_grid.ndim)
    flow_flags = clip.flow[..., 128:].reshape(lead + (8, 8))[..., ::-1]
    return ClipInput(
        images=None if clip.images is None else clip.images[..., ::-1, :, :, :][..., ::-1],
        features=None if clip.images is not None else mirrored_features,
        K=K,
        R_cam_crop=_mirror_conjugate(clip.R_cam_crop[..., ::-1, :, :]),
        T_rig_cams=jnp.linalg.inv(T_mirror[..., :1, :, :]) @ T_mirror,
        flow=jnp.concatenate([flow_grid.reshape(lead + (128,)), flow_flags.reshape(lead + (64,))], axis=-1),
        view_present=clip.view_present[..., ::-1],
    )


class HandPrediction(eqx.Module):
    """What `predict` emits per clip and frame (the input's rig frame, metres)."""

    params: ManoParams
    """MANO parameters of the hand's own side (left-hand convention for left hands)."""
    joints: Float[Array, "*batch T 21 3"]
    vertices: Float[Array, "*batch T V 3"]
    onscreen_prob: Float[Array, "*batch T"]
    emitted: Bool[Array, "*batch T"]
    """On-screen probability above the threshold: the frames whose hand is emitted."""


def unmirror(out: HandPrediction, T_rig_cams: Float[Array, "2 4 4"]) -> HandPrediction:
    """Bring one clip's prediction on `mirror_clip(clip)` back to `clip` (a left hand)."""
    T1 = T_rig_cams[1]

    def points(x):
        return mirror_points(x) @ T1[:3, :3].T + jax.lax.broadcast_to_rank(T1[:3, 3], x.ndim)

    params = jax.vmap(lambda p: transform_params(T1, mirror_params(p)))(out.params)
    return dataclasses.replace(out, params=params, joints=points(out.joints), vertices=points(out.vertices))


def gated(out: ESTHEROutput, threshold: float | Float[Array, ""] = 0.5) -> HandPrediction:
    """A network output as the hand `predict` emits (its frame, right hand): frames whose
    on-screen probability is above `threshold` are emitted."""
    prob = jax.nn.sigmoid(out.motion.onscreen_logits.astype(out.joints.dtype))
    return HandPrediction(params=out.params, joints=out.joints, vertices=out.vertices, onscreen_prob=prob, emitted=prob > threshold)


@eqx.filter_jit
def _predict(model: ESTHER, clips: ClipInput, hand_model: ManoModel, is_right: Bool[Array, "batch"], threshold: Float[Array, ""]):
    def one(clip, right):
        seen = jax.tree.map(lambda a, b: jnp.where(right, a, b), clip, mirror_clip(clip)) if clip.images is not None else clip
        pred = gated(model(seen, hand_model), threshold)
        if clip.images is None:
            return pred
        return jax.tree.map(lambda a, b: jnp.where(right, a, b), pred, unmirror(pred, clip.T_rig_cams))

    return jax.vmap(one)(clips, is_right)


def predict(
    model: ESTHER,
    clip_batch: ClipInput,
    hand_model: ManoModel | None = None,
    *,
    is_right: bool | Sequence[bool] | np.ndarray = True,
    threshold: float = 0.5,
) -> HandPrediction:
    """Hands of a batch of clips (leading batch axis), gated by the on-screen probability.

    Right hands go straight through; left hands (`is_right` False, per clip or for
    all) are mirrored with their views swapped (`mirror_clip`), predicted as right
    hands and un-mirrored (`unmirror`), as the paper and WiLoR do. Frames whose
    on-screen probability is at most `threshold` are not emitted (`emitted` False).
    `hand_model` defaults to the built-in right hand.
    """
    batch = clip_batch.flow.shape[0] if clip_batch.flow.ndim == 3 else None
    if batch is None:
        raise ValueError(f"predict takes a batch of clips (flow (B, T, 192)); got flow {clip_batch.flow.shape}. Add a leading axis.")
    right = np.broadcast_to(np.asarray(is_right, bool), (batch,))
    if clip_batch.images is None and not right.all():
        raise ValueError("left hands need crops to mirror; precomputed features must be extracted from mirrored crops")
    hand_model = load_builtin("right") if hand_model is None else hand_model
    return _predict(model, clip_batch, hand_model, jnp.asarray(right), jnp.asarray(threshold, clip_batch.flow.dtype))


# ----------------------------------------------------------------------------- inputs


def clip_input_from_crops(
    crops: dict[str, np.ndarray],
    T_rig_cams: Float[Array, "2 4 4"] | Float[np.ndarray, "2 4 4"],
    view_present: np.ndarray | None = None,
    *,
    size: int | None = None,
    frames: slice = slice(None),
) -> ClipInput:
    """A `ClipInput` from one hand's stored crops (`crops/<side>.npz` of a clip:
    images (T, 2, S, S[, 3]) uint8, K, R_cam_crop, flow) and the rig's camera poses.

    Args:
        size: resize the crops to `size` x `size` pixels (a config's `crop_size`; the
            synthetic engine stores 224), scaling K with them (pixel-centre convention).
        frames: the frames to take (e.g. `slice(0, cfg.num_frames)`: a network sees at
            most its config's `num_frames`).
    """
    images = np.asarray(crops["images"])[frames]
    if images.ndim == 4:  # grayscale rigs: replicate to RGB
        images = np.repeat(images[..., None], 3, axis=-1)
    if images.ndim != 5 or images.shape[1] != 2 or images.shape[-1] != 3 or images.shape[2] != images.shape[3]:
        raise ValueError(f"crop images must be (T, 2, S, S[, 3]); got {crops['images'].shape}")
    K = np.asarray(crops["K"], np.float64)[frames]
    if size is not None:
        images, K = resize_crops(images, K, size)
    dtype = jnp.result_type(float)
    T = images.shape[0]
    present = np.ones((T, 2), bool) if view_present is None else np.asarray(view_present, bool)[frames]
    return ClipInput(
        images=jnp.asarray(np.moveaxis(images, -1, 2), dtype) / 255.0,
        features=None,
        K=jnp.asarray(K, dtype),
        R_cam_crop=jnp.asarray(np.asarray(crops["R_cam_crop"])[frames], dtype),
        T_rig_cams=jnp.asarray(T_rig_cams, dtype),
        flow=jnp.asarray(np.asarray(crops["flow"])[frames], dtype),
        view_present=jnp.asarray(present),
    )


# ----------------------------------------------------------------------------- save / load

WEIGHTS_FILE = "weights.eqx"
CONFIG_FILE = "config.json"
DIGEST_KEY = "weights_sha256"
REVISION_KEY = "architecture_revision"
ARCHITECTURE_REVISION = 2
"""Incremented when the same weights would compute something else; `load` refuses other revisions.

1. The network as first trained (folders without the key).
2. The motion encoder's on-screen head reads its frame's pooled joint tokens, not z_root.
"""


def save(folder: str | pathlib.Path, model: ESTHER) -> pathlib.Path:
    """Write `config.json` (the config, the sha256 of the weights and the architecture
    revision) and `weights.eqx`
    (`eqx.tree_serialise_leaves`) atomically: a new folder renamed into place."""
    folder = pathlib.Path(folder)
    folder.parent.mkdir(parents=True, exist_ok=True)
    tmp = pathlib.Path(tempfile.mkdtemp(prefix=f".{folder.name}.", dir=folder.parent))
    try:
        eqx.tree_serialise_leaves(tmp / WEIGHTS_FILE, model)
        record = {**json.loads(model.config.to_json()), DIGEST_KEY: file_sha256(tmp / WEIGHTS_FILE), REVISION_KEY: ARCHITECTURE_REVISION}
        (tmp / CONFIG_FILE).write_text(json.dumps(record, indent=2, sort_keys=True))
        if folder.exists():
            shutil.rmtree(folder)
        os.replace(tmp, folder)
    finally:
        shutil.rmtree(tmp, ignore_errors=True)
    return folder


def load(folder: str | pathlib.Path) -> ESTHER:
    """A model written by `save`: the weights' digest is checked against `config.json`,
    a folder of another `ARCHITECTURE_REVISION` is refused (its weights were trained for
    a network that computed something else), the config rebuilds the structure from
    shapes, then the leaves are read (no training code needed)."""
    folder = pathlib.Path(folder)
    for name in (CONFIG_FILE, WEIGHTS_FILE):
        if not (folder / name).is_file():
            raise FileNotFoundError(f"{folder} is not a saved ESTHER model: {name} is missing")
    record = read_json(folder / CONFIG_FILE)
    if DIGEST_KEY not in record:
        raise ValueError(f"{folder / CONFIG_FILE} records no {DIGEST_KEY}: the weights cannot be verified (save the model again)")
    expected = record.pop(DIGEST_KEY)
    revision = record.pop(REVISION_KEY, 1)
    if revision != ARCHITECTURE_REVISION:
        raise ValueError(
            f"{folder} holds a network of architecture revision {revision}; this esther-jax runs revision "
            f"{ARCHITECTURE_REVISION} (see model.ARCHITECTURE_REVISION): its weights would compute something else, retrain it"
        )
    actual = file_sha256(folder / WEIGHTS_FILE)
    if actual != expected:
        raise ValueError(
            f"{folder / WEIGHTS_FILE} is damaged or was replaced: its sha256 {actual[:16]}... differs from "
            f"{expected[:16] if isinstance(expected, str) else expected!r}... recorded in {CONFIG_FILE}"
        )
    cfg = ModelConfig.from_json(json.dumps(record))
    skeleton = eqx.filter_eval_shape(ESTHER, cfg, key=jax.random.key(0))
    try:
        return eqx.tree_deserialise_leaves(folder / WEIGHTS_FILE, skeleton)
    except Exception as err:
        raise ValueError(f"{folder / WEIGHTS_FILE} does not match its config.json ({cfg.name}): {err}") from err
