"""Image backbones: crops -> patch tokens.

`ViT` has the DINOv3 architecture (patch embedding, a class token and register
tokens, axial rotary position embeddings, LayerScale, pre-norm blocks, a final
LayerNorm); with `BACKBONES["dinov3-vitl16"]` it is DINOv3 ViT-L/16 (303.2M
parameters) and `load_dinov3_weights` fills it from a checkpoint the user owns
(`.pth`, `.npz` or `.safetensors` with DINOv3's own parameter names). Nothing is ever
downloaded. `ConvStem` is a small strided-convolution backbone for CPU experiments.
`HandBackbone` reads a feature map of MediaPipe's pretrained hand landmark network
(`mediapipe_hand`), whose weights ship inside an installed package.

Images are RGB in [0, 1], channels first `(3, S, S)`, normalised inside with the
ImageNet mean and standard deviation DINOv3 was trained with.
"""

import pathlib

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Float, PRNGKeyArray

from ._layers import Block, Dense, LayerNorm, _trunc_normal, grid_rope
from .config import BackboneSpec
from .mediapipe_hand import INPUT_SIZE, STAGES, MediaPipeHand, load_mediapipe_hand

IMAGENET_MEAN = (0.485, 0.456, 0.406)
IMAGENET_STD = (0.229, 0.224, 0.225)


def _normalise(images: Float[Array, "*batch 3 S S"]) -> Float[Array, "*batch 3 S S"]:
    mean = jax.lax.broadcast_to_rank(jnp.asarray(IMAGENET_MEAN, images.dtype)[:, None, None], images.ndim)
    std = jax.lax.broadcast_to_rank(jnp.asarray(IMAGENET_STD, images.dtype)[:, None, None], images.ndim)
    return (images - mean) / std


class ViT(eqx.Module):
    """Vision transformer with DINOv3's architecture; returns normalised patch tokens."""

    patch_embed: Dense
    """Linear patch embedding over (channel, row, column)-flattened 16 x 16 patches."""
    cls_token: Float[Array, "width"]
    register_tokens: Float[Array, "registers width"]
    blocks: tuple[Block, ...]
    norm: LayerNorm
    patch_size: int = eqx.field(static=True)
    heads: int = eqx.field(static=True)

    def __init__(self, spec: BackboneSpec, *, key: PRNGKeyArray):
        keys = jax.random.split(key, spec.depth + 3)
        p = spec.patch_size
        self.patch_embed = Dense(3 * p * p, spec.width, key=keys[0])
        self.cls_token = _trunc_normal(keys[1], (spec.width,))
        self.register_tokens = _trunc_normal(keys[2], (spec.registers, spec.width))
        self.blocks = tuple(
            Block(spec.width, spec.heads, key=k, layerscale=spec.layerscale, eps=1e-5) for k in keys[3:]
        )
        self.norm = LayerNorm(spec.width, 1e-5)
        self.patch_size, self.heads = p, spec.heads

    def __call__(self, images: Float[Array, "*batch 3 S S"]) -> Float[Array, "*batch patches width"]:
        p = self.patch_size
        size = images.shape[-1]
        if images.shape[-3:] != (3, size, size) or size % p:
            raise ValueError(f"images must be (..., 3, S, S) with S a multiple of {p}; got {images.shape}")
        g = size // p
        lead = images.shape[:-3]
        x = _normalise(images).reshape(lead + (3, g, p, g, p))
        x = jnp.moveaxis(x, (-5, -3, -1), (-3, -2, -1)).reshape(lead + (g * g, 3 * p * p))
        x = self.patch_embed(x)
        width = x.shape[-1]
        prefix = jnp.concatenate([self.cls_token[None], self.register_tokens], axis=0)
        x = jnp.concatenate([jnp.broadcast_to(prefix, lead + prefix.shape), x], axis=-2)
        rope = grid_rope(g, width // self.heads)
        for block in self.blocks:
            x = block(x, rope)
        return self.norm(x[..., prefix.shape[0] :, :])


class ConvStem(eqx.Module):
    """Stride-2 3x3 convolutions with GELU (S -> S/16), then a LayerNorm per patch token."""

    kernels: tuple[Float[Array, "out in 3 3"], ...]
    biases: tuple[Float[Array, "out"], ...]
    norm: LayerNorm

    def __init__(self, spec: BackboneSpec, *, key: PRNGKeyArray):
        if 2**spec.depth != spec.patch_size:
            raise ValueError(f"a conv stem of {spec.depth} stride-2 layers has patch size {2**spec.depth}, not {spec.patch_size}")
        widths = [3] + [max(spec.width >> (spec.depth - 1 - i), 8) for i in range(spec.depth)]
        widths[-1] = spec.width
        keys = jax.random.split(key, spec.depth)
        self.kernels = tuple(
            jax.random.normal(k, (b, a, 3, 3), jnp.result_type(float)) * np.sqrt(2.0 / (9 * a))
            for a, b, k in zip(widths[:-1], widths[1:], keys)
        )
        self.biases = tuple(jnp.zeros(b, jnp.result_type(float)) for b in widths[1:])
        self.norm = LayerNorm(spec.width)

    def __call__(self, images: Float[Array, "*batch 3 S S"]) -> Float[Array, "*batch patches width"]:
        lead = images.shape[:-3]
        x = _normalise(images).reshape((-1,) + images.shape[-3:])
        for i, (kernel, bias) in enumerate(zip(self.kernels, self.biases)):
            x = jax.lax.conv_general_dilated(x, kernel, (2, 2), ((1, 1), (1, 1))) + bias[None, :, None, None]
            x = jax.nn.gelu(x, approximate=False) if i < len(self.kernels) - 1 else x
        x = jnp.moveaxis(x, 1, -1)
        return self.norm(x.reshape(lead + (-1, x.shape[-1])))


class HandBackbone(eqx.Module):
    """MediaPipe's pretrained hand landmark network read as a backbone: the feature map
    `spec.stage` of an RGB crop as (S / stride)^2 patch tokens (row-major, as the other
    backbones' patches), each LayerNorm-ed over its channels.

    The network expects crops in which the hand is upright (wrist below the middle
    knuckle) and fills about 1 / 2.6 of the side: MediaPipe's own crops. ESTHER's crops are
    not rotated; fine-tune it (`freeze_backbone=False`) to adapt it.
    """

    net: MediaPipeHand
    norm: LayerNorm
    stage: str = eqx.field(static=True)

    def __init__(self, spec: BackboneSpec, net: MediaPipeHand | None = None):
        if spec.stage not in STAGES or len(STAGES[spec.stage][1]) != 3:
            raise ValueError(f"a hand backbone reads a feature map: stage {spec.stage!r} is not one of "
                             f"{[k for k, (_, shape) in STAGES.items() if len(shape) == 3]}")  # fmt: skip
        rows, _, channels = STAGES[spec.stage][1]
        if INPUT_SIZE // rows != spec.patch_size or channels != spec.width:
            raise ValueError(f"stage {spec.stage} has stride {INPUT_SIZE // rows} and {channels} channels; "
                             f"the spec says {spec.patch_size} and {spec.width}")  # fmt: skip
        self.net = load_mediapipe_hand() if net is None else net
        self.norm = LayerNorm(spec.width, 1e-5)
        self.stage = spec.stage

    def __call__(self, images: Float[Array, "*batch 3 S S"]) -> Float[Array, "*batch patches width"]:
        size = images.shape[-1]
        if images.shape[-3:] != (3, size, size) or size % 32:
            raise ValueError(f"images must be (..., 3, S, S) with S a multiple of 32; got {images.shape}")
        lead = images.shape[:-3]
        flat = jnp.moveaxis(images.reshape((-1,) + images.shape[-3:]), 1, -1)
        maps = jax.vmap(lambda image: self.net.features(image, (self.stage,))[self.stage])(flat)
        return self.norm(maps.reshape(lead + (-1, maps.shape[-1])))


Backbone = ViT | ConvStem | HandBackbone
"""Any image backbone: `(..., 3, S, S)` crops -> `(..., P, width)` patch tokens."""


def make_backbone(spec: BackboneSpec, *, key: PRNGKeyArray) -> Backbone:
    """A backbone of the given architecture: randomly initialised (ViT, conv), or
    MediaPipe's pretrained hand network from the installed package (`key` unused)."""
    if spec.kind == "mediapipe-hand":
        return HandBackbone(spec)
    return ViT(spec, key=key) if spec.kind == "vit" else ConvStem(spec, key=key)


# ----------------------------------------------------------------------------- DINOv3 weights


def _dinov3_layout(vit: ViT) -> list[tuple[str, object, object, object]]:
    """(DINOv3 name, where in `vit`, DINOv3 array -> ours, ours -> DINOv3 array)."""
    p = vit.patch_size
    width = vit.cls_token.shape[0]
    transpose = (lambda a: a.T, lambda a: a.T)
    same = (lambda a: a, lambda a: a)
    layout = [
        ("patch_embed.proj.weight", lambda m: m.patch_embed.weight,
         lambda a: a.reshape(width, 3 * p * p).T, lambda a: a.T.reshape(width, 3, p, p)),
        ("patch_embed.proj.bias", lambda m: m.patch_embed.bias, *same),
        ("cls_token", lambda m: m.cls_token, lambda a: a.reshape(width), lambda a: a.reshape(1, 1, width)),
        ("norm.weight", lambda m: m.norm.weight, *same),
        ("norm.bias", lambda m: m.norm.bias, *same),
    ]  # fmt: skip
    if vit.register_tokens.shape[0]:
        layout.append(("storage_tokens", lambda m: m.register_tokens,
                       lambda a: a.reshape(-1, width), lambda a: a.reshape(1, -1, width)))  # fmt: skip
    for i, block in enumerate(vit.blocks):
        b = f"blocks.{i}."

        for ours, theirs, conv in [
            ("norm1.weight", "norm1.weight", same), ("norm1.bias", "norm1.bias", same),
            ("attn.qkv.weight", "attn.qkv.weight", transpose), ("attn.qkv.bias", "attn.qkv.bias", same),
            ("attn.proj.weight", "attn.proj.weight", transpose), ("attn.proj.bias", "attn.proj.bias", same),
            ("norm2.weight", "norm2.weight", same), ("norm2.bias", "norm2.bias", same),
            ("mlp.layers.0.weight", "mlp.fc1.weight", transpose), ("mlp.layers.0.bias", "mlp.fc1.bias", same),
            ("mlp.layers.1.weight", "mlp.fc2.weight", transpose), ("mlp.layers.1.bias", "mlp.fc2.bias", same),
        ]:  # fmt: skip
            layout.append((b + theirs, _at_path(i, ours), *conv))
        if block.ls1 is not None:
            layout.append((b + "ls1.gamma", _at_path(i, "ls1"), *same))
            layout.append((b + "ls2.gamma", _at_path(i, "ls2"), *same))
    return layout


def _at_path(block: int, path: str):
    def where(m):
        node = m.blocks[block]
        for part in path.split("."):
            node = node[int(part)] if part.isdigit() else getattr(node, part)
        return node

    return where


_IGNORED_DINOV3_KEYS = ("mask_token", "rope_embed.periods", "local_cls_norm.", "cls_norm.", "head.")
"""Checkpoint entries with no role in frozen patch-feature extraction."""


def _read_state_dict(path: pathlib.Path) -> dict[str, np.ndarray]:
    if not path.is_file():
        raise FileNotFoundError(f"backbone weights {path} not found (weights are only read from local files)")
    suffix = path.suffix.lower()
    try:
        if suffix == ".npz":
            with np.load(path) as f:
                return {k: np.asarray(f[k]) for k in f.files}
        if suffix == ".safetensors":
            from safetensors.numpy import load_file

            return load_file(str(path))
        if suffix in (".pth", ".pt"):
            import torch

            state = torch.load(path, map_location="cpu", weights_only=True)
            state = state.get("model", state.get("teacher", state)) if isinstance(state, dict) else state
            return {k.removeprefix("backbone."): v.float().numpy() for k, v in state.items()}
    except ImportError as err:
        raise ImportError(f"reading {path.name} needs {err.name!r} (python -m pip install -e '.[dinov3]'); or convert it to .npz") from err
    except Exception as err:  # corrupt or foreign file
        raise ValueError(f"could not read backbone weights {path}: {err}") from err
    raise ValueError(f"unsupported weight file {path.name!r}: use .pth, .npz or .safetensors")


def load_dinov3_weights(vit: ViT, path: str | pathlib.Path) -> ViT:
    """`vit` with the weights of a DINOv3 checkpoint (DINOv3's parameter names).

    The k-part of the fused q/k/v bias is multiplied by the checkpoint's `bias_mask`
    when it has one (DINOv3's masked key bias). Raises naming every missing,
    unexpected or mis-shaped entry.
    """
    path = pathlib.Path(path)
    state = _read_state_dict(path)
    layout = _dinov3_layout(vit)
    missing = [name for name, *_ in layout if name not in state]
    known = {name for name, *_ in layout}
    unexpected = [k for k in state if k not in known and not k.endswith("bias_mask") and not k.startswith(_IGNORED_DINOV3_KEYS)]
    if missing or unexpected:
        raise ValueError(
            f"{path.name} does not match this ViT: missing {missing[:8]}{'...' if len(missing) > 8 else ''}, "
            f"unexpected {unexpected[:8]}{'...' if len(unexpected) > 8 else ''} (is it the right DINOv3 size?)"
        )
    wheres, values = [], []
    for name, where, to_ours, _ in layout:
        array = np.asarray(state[name], np.float32)
        if name.endswith("attn.qkv.bias") and name.replace("bias", "bias_mask") in state:
            array = array * np.asarray(state[name.replace("bias", "bias_mask")], np.float32)
        ours = to_ours(array)
        target = where(vit)
        if ours.shape != target.shape:
            raise ValueError(f"{path.name}: {name} has shape {array.shape}, which does not fit {target.shape}")
        wheres.append(where)
        values.append(jnp.asarray(ours, target.dtype))
    return eqx.tree_at(lambda m: [w(m) for w in wheres], vit, values)


def dinov3_state_dict(vit: ViT) -> dict[str, np.ndarray]:
    """The weights of `vit` under DINOv3's parameter names and shapes (the inverse of
    `load_dinov3_weights`); `np.savez(path, **dinov3_state_dict(vit))` writes a file it reads."""
    return {name: np.asarray(to_theirs(np.asarray(where(vit)))) for name, where, _, to_theirs in _dinov3_layout(vit)}
