"""Configurations of the ESTHER network: the paper's, small CPU ones, and the ablations.

A `ModelConfig` is static (hashable): every field fixes a shape or a branch of the
graph, so changing one recompiles. `config(name, ablation=..., **overrides)` builds one;
`ABLATIONS` names each row of the paper's table 5 (plus the pure-monocular variant of
the size-depth binding study). The rows about losses, masking and augmentation switch
flags that the training code reads (`esther_jax.train`); the others change the network.
"""

import dataclasses
import json
from typing import Literal


@dataclasses.dataclass(frozen=True)
class BackboneSpec:
    """Architecture of an image backbone that maps an S x S crop to (S/16)^2 patch tokens."""

    kind: Literal["vit", "conv", "mediapipe-hand"]
    """A ViT (DINOv3's architecture), a conv stem, or MediaPipe's pretrained hand network
    (its weights come from the installed package: `esther_jax.model.mediapipe_hand`)."""
    width: int
    """Channels of the output patch tokens."""
    depth: int = 0
    """Transformer blocks (vit) or stride-2 convolutions after the stem (conv)."""
    heads: int = 0
    registers: int = 0
    """Register ('storage') tokens besides the class token (vit)."""
    layerscale: float | None = None
    patch_size: int = 16
    stage: str = ""
    """mediapipe-hand: the feature map read as patch tokens (a key of
    `mediapipe_hand.STAGES` whose stride is `patch_size`)."""


BACKBONES: dict[str, BackboneSpec] = {
    # DINOv3 ViT-L/16: 24 blocks, width 1024, 16 heads, 4 registers, RoPE, LayerScale.
    "dinov3-vitl16": BackboneSpec("vit", 1024, depth=24, heads=16, registers=4, layerscale=1e-5),
    # Small trainable backbones for CPU experiments (same code paths).
    "vit-tiny": BackboneSpec("vit", 96, depth=2, heads=4, registers=1, layerscale=1e-1),
    "conv-small": BackboneSpec("conv", 64, depth=4),
    # MediaPipe's pretrained hand landmark network (2.7M weights), its stride-16 map:
    # 112 channels, (S/16)^2 tokens (14 x 14 at its native 224 px).
    "mediapipe-hand": BackboneSpec("mediapipe-hand", 112, patch_size=16, stage="stride16"),
}


@dataclasses.dataclass(frozen=True)
class ModelConfig:
    """Every static choice of the network (defaults: the paper's appendix E)."""

    name: str = "paper"
    dim: int = 512
    """Model width D of the stereo, temporal and fusion transformers."""
    heads: int = 8
    stereo_layers: int = 4
    """Stereo blocks (each: intra-view self-attention, cross-view attention, MLP)."""
    readout_layers: int = 1
    """Cross-attention blocks through which the 21 joint queries read a view's tokens."""
    temporal_layers: int = 4
    fusion_layers: int = 2
    mlp_ratio: float = 4.0
    num_frames: int = 16
    crop_size: int = 224
    depth_bins: int = 64
    """Log-spaced bins of the depth head over `depth_range_m`."""
    depth_range_m: tuple[float, float] = (0.1, 1.5)
    backbone: str = "dinov3-vitl16"
    """A key of `BACKBONES`."""
    freeze_backbone: bool = True
    """No gradient reaches the backbone (the paper keeps DINOv3 frozen)."""
    precomputed_features: bool = False
    """The model holds no backbone and reads `ClipInput.features` (extract once, train many)."""
    # --- network ablations (table 5)
    plucker: bool = True
    """Add the Plucker-ray embedding of each patch to its token."""
    cross_view: bool = True
    """Cross-view attention in the stereo blocks."""
    flow_token: bool = True
    """Feed the camera-motion flow token to the motion encoder."""
    learned_gate: bool = True
    """Per-token softmax gate over the decoder's sources (False: uniform 1/3, concat-style)."""
    anchored_wrist: bool = False
    """Wrist = triangulated wrist + MLP residual (the table-5 variant), not MLP alone."""
    triangulated_wrist_input: bool = False
    """The wrist token's query also reads the image encoder's triangulated wrist (an MLP
    embedding of it, added where the triangulation is valid): an input, not an anchor, the
    wrist is still predicted freely. Not in the paper, which keeps the triangulation out of
    the decoder's inputs; see docs/architecture.md for why and what it measured."""
    monocular: bool = False
    """The second view is always removed (the size-depth binding study's mono model)."""
    # --- training ablations (read by esther_jax.train)
    guidance_2d: bool = True
    """2D-keypoint and heatmap guidance losses."""
    guidance_triangulation: bool = True
    motion_masking: bool = True
    image_augmentation: bool = True

    def __post_init__(self):
        if self.backbone not in BACKBONES:
            raise ValueError(f"unknown backbone {self.backbone!r}; choose one of {sorted(BACKBONES)}")
        if self.dim % self.heads or (self.dim // self.heads) % 2:
            raise ValueError(f"dim {self.dim} must split into {self.heads} heads of even width")
        if self.backbone_spec.kind == "mediapipe-hand" and self.crop_size % 32:
            raise ValueError(f"crop_size {self.crop_size}: MediaPipe's hand network needs a multiple of 32 (224 native)")
        if self.crop_size % self.backbone_spec.patch_size:
            raise ValueError(f"crop_size {self.crop_size} is not a multiple of the patch size {self.backbone_spec.patch_size}")
        lo, hi = self.depth_range_m
        if not 0 < lo < hi:
            raise ValueError(f"depth_range_m must be 0 < near < far metres; got {self.depth_range_m}")

    @property
    def backbone_spec(self) -> BackboneSpec:
        return BACKBONES[self.backbone]

    @property
    def grid(self) -> int:
        """Patches per crop side (heatmap resolution)."""
        return self.crop_size // self.backbone_spec.patch_size

    def replace(self, **changes) -> "ModelConfig":
        return dataclasses.replace(self, **changes)

    def to_json(self) -> str:
        return json.dumps(dataclasses.asdict(self), indent=2, sort_keys=True)

    @classmethod
    def from_json(cls, text: str) -> "ModelConfig":
        fields = json.loads(text)
        unknown = set(fields) - {f.name for f in dataclasses.fields(cls)}
        if unknown:
            raise ValueError(f"model config has unknown fields {sorted(unknown)} (written by a newer esther_jax?)")
        fields["depth_range_m"] = tuple(fields.get("depth_range_m", cls.depth_range_m))
        return cls(**fields)


CONFIGS: dict[str, ModelConfig] = {
    "paper": ModelConfig(),
    # Trains on a 2-core CPU in minutes: 112 px crops, a small trainable ViT.
    "cpu-small": ModelConfig(
        name="cpu-small", dim=128, heads=4, stereo_layers=2, temporal_layers=2, fusion_layers=1,
        crop_size=112, depth_bins=32, backbone="vit-tiny", freeze_backbone=False,
    ),
    # cpu-small's network on MediaPipe's frozen, pretrained hand features: 128 px crops
    # (8 x 8 tokens), where a hand of our crops (its keypoints' box is the crop) spans
    # about as many pixels as in MediaPipe's own 224 px crops (2.6 palm boxes wide).
    "cpu-small-hand": ModelConfig(
        name="cpu-small-hand", dim=128, heads=4, stereo_layers=2, temporal_layers=2, fusion_layers=1,
        crop_size=128, depth_bins=32, backbone="mediapipe-hand", freeze_backbone=True,
    ),
    # For tests and smoke runs: 64 px crops, a conv stem, one block per stage.
    "cpu-tiny": ModelConfig(
        name="cpu-tiny", dim=64, heads=4, stereo_layers=1, temporal_layers=1, fusion_layers=1, mlp_ratio=2.0,
        crop_size=64, depth_bins=16, backbone="conv-small", freeze_backbone=False,
    ),
}  # fmt: skip

ABLATIONS: dict[str, dict] = {
    "no-plucker": {"plucker": False},
    "no-cross-view": {"cross_view": False},
    "no-guidance-masking-augmentation": {
        "guidance_2d": False, "guidance_triangulation": False, "motion_masking": False, "image_augmentation": False,
    },
    "no-flow-token": {"flow_token": False},
    "no-2d-guidance": {"guidance_2d": False},
    "no-image-augmentation": {"image_augmentation": False},
    "uniform-gate": {"learned_gate": False},
    "no-triangulation-guidance": {"guidance_triangulation": False},
    "no-motion-masking": {"motion_masking": False},
    "anchored-wrist": {"anchored_wrist": True},
    "monocular": {"monocular": True},
}  # fmt: skip
"""Table 5 of the paper, row by row (in its order), plus the pure-monocular variant."""


def config(name: str = "paper", *, ablation: str | None = None, **overrides) -> ModelConfig:
    """A named configuration, optionally with one ablation row and field overrides.

    >>> config("cpu-small", ablation="no-plucker", num_frames=8)
    """
    if name not in CONFIGS:
        raise ValueError(f"unknown model config {name!r}; choose one of {sorted(CONFIGS)}")
    cfg = CONFIGS[name]
    if ablation is not None:
        if ablation not in ABLATIONS:
            raise ValueError(f"unknown ablation {ablation!r}; choose one of {list(ABLATIONS)}")
        cfg = cfg.replace(name=f"{cfg.name}:{ablation}", **ABLATIONS[ablation])
    return cfg.replace(**overrides) if overrides else cfg
