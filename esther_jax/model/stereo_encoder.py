"""The stereo image encoder (paper 3.5): two views' patch tokens -> joint features F.

Per frame (no temporal mixing): each view's backbone patch tokens are projected to the
model width and given the embedding of their patch's Plucker ray in the rig frame
(from the crop camera and the rig pose); a blanked view's tokens are all the learned
view-mask token instead (no pixels, no rays). Stereo blocks alternate intra-view
self-attention and cross-view attention (each view's tokens read the other view's);
21 joint queries per view then read their view's fused tokens and are merged across
views into F [T, 21, D]. The read-out queries are layer-normalised before the heads and
the merge: the heads share them, and on the raw residual stream the visibility and
depth-bin cross-entropies (whose optimum is unbounded logits) grow the queries' scale
until the heatmap softmax saturates and the 2D keypoints stop learning (measured: one
clip could not be overfitted, 22 px of 112 after 100 steps and NaN later; with the norm
2.4 px after 300). Guidance heads per view and joint: heatmap logits over the
patch grid, 2D keypoints (the heatmap's soft-argmax, crop pixels), visibility logits
and log-spaced depth-bin logits; the 2D keypoints are triangulated (core
`triangulate`, weighted by predicted visibility of the present views).
`cross_view_attention` returns the stereo blocks' cross-view attention probabilities,
computed by the same code as the forward pass (the attention probe of paper 5.4 and
figure 7, "Why the Monocular Fallback Stays Reliable").
"""

import math

import equinox as eqx
import jax
import jax.numpy as jnp
from jaxtyping import Array, Bool, Float, PRNGKeyArray

from ..cameras import PinholeCamera
from ..crops import Crop, crop_poses, patch_centres, plucker_rays
from ..triangulation import triangulate
from ._layers import Attention, CrossBlock, Dense, LayerNorm, Mlp, _trunc_normal
from .config import ModelConfig

NUM_KEYPOINTS = 21
PLUCKER_MOMENT_SCALE = 10.0
"""Ray moments `o x d` are fed in decimetres (a 62 mm baseline gives moments of ~0.6)."""


class ImageEvidence(eqx.Module):
    """Outputs of the stereo image encoder for one clip (views: 0 left, 1 right)."""

    features: Float[Array, "T 21 D"]
    """F: per-frame joint features, both views merged."""
    heatmap_logits: Float[Array, "T 2 21 G G"]
    """Per view and keypoint, logits over the patch grid (row-major, rows = v)."""
    keypoints_2d: Float[Array, "T 2 21 2"]
    """Soft-argmax of the heatmaps: (u, v) crop pixels."""
    visibility_logits: Float[Array, "T 2 21"]
    depth_logits: Float[Array, "T 2 21 B"]
    """Logits over `depth_bin_centres` of each keypoint's depth in each crop camera."""
    triangulated: Float[Array, "T 21 3"]
    """Visibility-weighted triangulation of the 2D keypoints (rig frame, metres)."""
    triangulation_valid: Bool[Array, "T 21"]
    triangulation_spread: Float[Array, "T 21"]
    """Weighted RMS distance of the point to the two rays (metres)."""


def depth_bin_centres(cfg: ModelConfig) -> Float[Array, "B"]:
    """Log-spaced depth-bin centres (metres) of the depth head."""
    lo, hi = cfg.depth_range_m
    return jnp.exp(jnp.linspace(math.log(lo), math.log(hi), cfg.depth_bins, dtype=jnp.result_type(float)))


class StereoBlock(eqx.Module):
    """Intra-view self-attention, cross-view attention (optional), MLP; pre-norm residuals."""

    norm_self: LayerNorm
    self_attn: Attention
    norm_cross: LayerNorm | None
    cross_attn: Attention | None
    norm_mlp: LayerNorm
    mlp: Mlp

    def __init__(self, cfg: ModelConfig, *, key: PRNGKeyArray):
        k1, k2, k3 = jax.random.split(key, 3)
        d = cfg.dim
        self.norm_self, self.norm_mlp = LayerNorm(d), LayerNorm(d)
        self.self_attn = Attention(d, cfg.heads, key=k1)
        self.norm_cross = LayerNorm(d) if cfg.cross_view else None
        self.cross_attn = Attention(d, cfg.heads, key=k2) if cfg.cross_view else None
        self.mlp = Mlp(d, int(d * cfg.mlp_ratio), d, key=k3)

    def __call__(self, x: Float[Array, "T 2 P D"]) -> tuple[Float[Array, "T 2 P D"], Float[Array, "T 2 heads P P"] | None]:
        """The block's output tokens and its cross-view attention probabilities
        `[t, v, h, q, k]`: the weight head h of view v's patch q gives to patch k of the
        other view (None without cross-view attention)."""
        x = x + self.self_attn(self.norm_self(x))
        probs = None
        if self.cross_attn is not None:
            y = self.norm_cross(x)
            read, probs = self.cross_attn.attend(y, y[:, ::-1])  # each view reads the other
            x = x + read
        return x + self.mlp(self.norm_mlp(x)), probs


class StereoImageEncoder(eqx.Module):
    feature_proj: Dense
    ray_embed: Mlp | None
    view_embed: Float[Array, "2 D"]
    view_mask_token: Float[Array, "D"]
    """Replaces every patch token of a blanked view."""
    blocks: tuple[StereoBlock, ...]
    joint_queries: Float[Array, "21 D"]
    readout: tuple[CrossBlock, ...]
    norm_tokens: LayerNorm
    norm_queries: LayerNorm
    """Before the heads and the merge (see the module docstring)."""
    heatmap_proj: Dense
    visibility_head: Dense
    depth_head: Mlp
    merge: Dense
    """F = merge([q_left, q_right]) over the concatenated views' joint queries."""
    crop_size: int = eqx.field(static=True)
    grid: int = eqx.field(static=True)

    def __init__(self, cfg: ModelConfig, *, key: PRNGKeyArray):
        keys = jax.random.split(key, 10)
        d = cfg.dim
        self.feature_proj = Dense(cfg.backbone_spec.width, d, key=keys[0])
        self.ray_embed = Mlp(6, d, d, key=keys[1]) if cfg.plucker else None
        self.view_embed = _trunc_normal(keys[2], (2, d))
        self.view_mask_token = _trunc_normal(keys[3], (d,))
        self.blocks = tuple(StereoBlock(cfg, key=k) for k in jax.random.split(keys[4], cfg.stereo_layers))
        self.joint_queries = _trunc_normal(keys[5], (NUM_KEYPOINTS, d))
        self.readout = tuple(
            CrossBlock(d, cfg.heads, key=k, mlp_ratio=cfg.mlp_ratio) for k in jax.random.split(keys[6], cfg.readout_layers)
        )
        self.norm_tokens = LayerNorm(d)
        self.norm_queries = LayerNorm(d)
        self.heatmap_proj = Dense(d, d, key=keys[7])
        k8, k9 = jax.random.split(keys[8])
        self.visibility_head = Dense(d, 1, key=k8)
        self.depth_head = Mlp(d, d, cfg.depth_bins, key=k9)
        self.merge = Dense(2 * d, d, key=keys[9])
        self.crop_size, self.grid = cfg.crop_size, cfg.grid

    def _calibration(
        self, K: Float[Array, "T 2 3 3"], R_cam_crop: Float[Array, "T 2 3 3"], view_present: Bool[Array, "T 2"]
    ) -> tuple[Float[Array, "T 2 3 3"], Float[Array, "T 2 3 3"], PinholeCamera]:
        """The crop cameras the encoder uses: a blanked view's calibration may be garbage,
        so it gets the other view's (never read). Returns K, R_cam_crop and the cameras."""
        K = jnp.where(view_present[..., None, None], K, K[:, ::-1])
        R_cam_crop = jnp.where(view_present[..., None, None], R_cam_crop, R_cam_crop[:, ::-1])
        cameras = jax.vmap(jax.vmap(lambda k: PinholeCamera.from_K(k, self.crop_size, self.crop_size)))(K)
        return K, R_cam_crop, cameras

    def _stereo_tokens(
        self,
        features: Float[Array, "T 2 P C"],
        cameras: PinholeCamera,
        R_cam_crop: Float[Array, "T 2 3 3"],
        T_rig_cams: Float[Array, "2 4 4"],
        view_present: Bool[Array, "T 2"],
    ) -> tuple[Float[Array, "T 2 P D"], tuple[Float[Array, "T 2 heads P P"] | None, ...]]:
        """Each view's patch tokens (projected, ray-embedded; the view-mask token for a
        blanked view) through the stereo blocks, and each block's cross-view attention
        probabilities (`StereoBlock`)."""
        P = features.shape[2]
        if P != self.grid**2:
            raise ValueError(f"backbone features have {P} patches per view; this model expects {self.grid}^2 = {self.grid**2}")
        tokens = self.feature_proj(features)
        if self.ray_embed is not None:
            def rays(camera, R, T_rig_cam):
                return plucker_rays(Crop(camera=camera, R_cam_crop=R), T_rig_cam, self.grid).reshape(P, 6)

            ray = jax.vmap(jax.vmap(rays, in_axes=(0, 0, 0)), in_axes=(0, 0, None))(cameras, R_cam_crop, T_rig_cams)
            ray = ray * jax.lax.broadcast_to_rank(jnp.asarray([1.0, 1.0, 1.0] + [PLUCKER_MOMENT_SCALE] * 3, ray.dtype), ray.ndim)
            tokens = tokens + self.ray_embed(ray.astype(tokens.dtype))
        tokens = jnp.where(view_present[..., None, None], tokens, self.view_mask_token[None, None, None])
        tokens = tokens + self.view_embed[None, :, None, :]
        cross = []
        for block in self.blocks:
            tokens, probs = block(tokens)
            cross.append(probs)
        return tokens, tuple(cross)

    def cross_view_attention(
        self,
        features: Float[Array, "T 2 P C"],
        K: Float[Array, "T 2 3 3"],
        R_cam_crop: Float[Array, "T 2 3 3"],
        T_rig_cams: Float[Array, "2 4 4"],
        view_present: Bool[Array, "T 2"],
    ) -> Float[Array, "layers T 2 heads P P"]:
        """The cross-view attention probabilities of every stereo block, computed by the
        forward pass itself (same weights, same operations; arguments as `__call__`).

        Entry `[l, t, v, h, q, k]` is the softmax weight that head h of view v's patch
        token q gives, in stereo block l and frame t, to patch token k of the other view
        (1 - v). Patches are row-major over the grid x grid tiling of the crop (as the
        heatmaps); the keys are exactly the other view's P patch tokens (the encoder has
        no class or register tokens), so each row sums to 1. A blanked view's tokens are
        the view-mask token: its queries are the placeholder's, and the other view's
        queries attend into placeholder keys.
        """
        if not self.blocks or self.blocks[0].cross_attn is None:
            raise ValueError("this network has no cross-view attention to probe (its config has cross_view=False, "
                             "e.g. the 'no-cross-view' ablation, or no stereo blocks); probe a model with cross_view=True")  # fmt: skip
        _, R_cam_crop, cameras = self._calibration(K, R_cam_crop, view_present)
        _, cross = self._stereo_tokens(features, cameras, R_cam_crop, T_rig_cams, view_present)
        return jnp.stack(cross)

    def __call__(
        self,
        features: Float[Array, "T 2 P C"],
        K: Float[Array, "T 2 3 3"],
        R_cam_crop: Float[Array, "T 2 3 3"],
        T_rig_cams: Float[Array, "2 4 4"],
        view_present: Bool[Array, "T 2"],
    ) -> ImageEvidence:
        T, _, P, _ = features.shape
        K, R_cam_crop, cameras = self._calibration(K, R_cam_crop, view_present)
        tokens, _ = self._stereo_tokens(features, cameras, R_cam_crop, T_rig_cams, view_present)

        queries = jnp.broadcast_to(self.joint_queries[None] + self.view_embed[:, None, :], (T, 2) + self.joint_queries.shape)
        for block in self.readout:
            queries = block(queries, tokens)
        queries = self.norm_queries(queries)
        normed = self.norm_tokens(tokens)
        heat = jnp.einsum("tvjd,tvpd->tvjp", self.heatmap_proj(queries), normed) / math.sqrt(normed.shape[-1])
        # the 2D keypoints and their triangulation in the calibration's dtype (float32
        # under mixed precision), whatever the network computes in
        geometry = K.dtype
        centres = patch_centres(self.crop_size, self.grid).reshape(P, 2).astype(geometry)
        keypoints = jax.nn.softmax(heat.astype(geometry), axis=-1) @ centres
        visibility = self.visibility_head(queries)[..., 0]
        features_out = self.merge(jnp.concatenate([queries[:, 0], queries[:, 1]], axis=-1))

        weights = jax.nn.sigmoid(visibility.astype(geometry)) * view_present[..., None].astype(geometry)
        T_rig_crops = crop_poses(R_cam_crop, T_rig_cams)
        per_joint = jax.vmap(triangulate, in_axes=(None, None, 1, 1))  # over joints
        tri = jax.vmap(per_joint)(cameras, T_rig_crops, keypoints, weights)  # over frames
        return ImageEvidence(
            features=features_out,
            heatmap_logits=heat.reshape(T, 2, NUM_KEYPOINTS, self.grid, self.grid),
            keypoints_2d=keypoints,
            visibility_logits=visibility,
            depth_logits=self.depth_head(queries),
            triangulated=tri.point,
            triangulation_valid=tri.valid,
            triangulation_spread=tri.spread,
        )
