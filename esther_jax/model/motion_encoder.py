"""The masked temporal motion encoder (paper 3.6, appendices C-D).

One temporal transformer over the whole clip: per frame the 21 joint tokens of F (plus
joint and time embeddings), the camera-motion flow token (the 192-D token of
appendix D, projected) and a learned root token. Masked joint slots (per joint, per
frame, over spans: any boolean `[T, 21]` mask) hold the learned motion mask token
instead of F (it is distinct from the stereo encoder's view-mask token); the flow token
is never masked. Outputs: Z [T, 21, D], z_root [T, D], an on-screen logit per frame, and
the auxiliary reconstructions read at masked positions in training: canonical
(wrist-relative) joints, MANO pose (6D per joint) and root (wrist) velocity.

The per-frame heads (on-screen, pose) read the frame's own joint tokens Z_t, pooled.
z_root enters every frame as the same learned token plus its time embedding, so it
learns about its own frame only through attention; read by the on-screen head it left
blanked frames indistinguishable from their neighbours (the gate then emitted 99 % of
the off-screen frames of appendix L's stress test). Z_t carries its frame's evidence F_t
on the residual stream, so a frame whose views are all absent is told apart directly.
"""

import equinox as eqx
import jax
import jax.numpy as jnp
from jaxtyping import Array, Bool, Float, PRNGKeyArray

from ..clips import FLOW_TOKEN_SIZE
from ._layers import Block, Dense, LayerNorm, _trunc_normal
from .config import ModelConfig
from .stereo_encoder import NUM_KEYPOINTS


class MotionEvidence(eqx.Module):
    """Outputs of the motion encoder for one clip."""

    features: Float[Array, "T 21 D"]
    """Z: temporally contextualised joint features."""
    root: Float[Array, "T D"]
    """z_root: the root token's output per frame."""
    onscreen_logits: Float[Array, "T"]
    """Logit of 'the hand is visible in at least one present view'."""
    canonical_joints: Float[Array, "T 21 3"]
    """Wrist-relative keypoints (rig axes, metres)."""
    pose_6d: Float[Array, "T 16 6"]
    """Local MANO joint rotations (root first), 6D."""
    root_velocity: Float[Array, "T 3"]
    """Wrist velocity (metres per frame, rig frame): t_{t+1} - t_t."""


class MotionEncoder(eqx.Module):
    mask_token: Float[Array, "D"]
    """Fills masked joint slots: the learned motion mask token."""
    joint_embed: Float[Array, "21 D"]
    time_embed: Float[Array, "frames D"]
    root_token: Float[Array, "D"]
    flow_embed: Dense | None
    blocks: tuple[Block, ...]
    norm: LayerNorm
    onscreen_head: Dense
    joints_head: Dense
    pose_head: Dense
    velocity_head: Dense

    def __init__(self, cfg: ModelConfig, *, key: PRNGKeyArray):
        keys = jax.random.split(key, 10)
        d = cfg.dim
        self.mask_token = _trunc_normal(keys[0], (d,))
        self.joint_embed = _trunc_normal(keys[1], (NUM_KEYPOINTS, d))
        self.time_embed = _trunc_normal(keys[2], (cfg.num_frames, d))
        self.root_token = _trunc_normal(keys[3], (d,))
        self.flow_embed = Dense(FLOW_TOKEN_SIZE, d, key=keys[4]) if cfg.flow_token else None
        self.blocks = tuple(
            Block(d, cfg.heads, key=k, mlp_ratio=cfg.mlp_ratio) for k in jax.random.split(keys[5], cfg.temporal_layers)
        )
        self.norm = LayerNorm(d)
        self.onscreen_head = Dense(d, 1, key=keys[6])
        self.joints_head = Dense(d, 3, key=keys[7])
        self.pose_head = Dense(d, 16 * 6, key=keys[8])
        self.velocity_head = Dense(d, 3, key=keys[9])

    def mask(self, features: Float[Array, "T 21 D"], motion_mask: Bool[Array, "T 21"]) -> Float[Array, "T 21 D"]:
        """F with its masked slots replaced by the motion mask token."""
        return jnp.where(motion_mask[..., None], self.mask_token[None, None], features)

    def __call__(self, masked_features: Float[Array, "T 21 D"], flow: Float[Array, "T 192"]) -> MotionEvidence:
        """Encode `mask(F, motion_mask)` with the flow tokens."""
        T = masked_features.shape[0]
        if T > self.time_embed.shape[0]:
            raise ValueError(f"clip has {T} frames; this model was built for at most {self.time_embed.shape[0]}")
        time = self.time_embed[:T, None, :]
        joints = masked_features + self.joint_embed[None] + time
        root = jnp.broadcast_to(self.root_token, (T, 1, self.root_token.shape[0])) + time
        parts = [joints, root]
        if self.flow_embed is not None:
            parts.append(self.flow_embed(flow.astype(joints.dtype))[:, None, :] + time)
        width = sum(p.shape[1] for p in parts)
        x = jnp.concatenate(parts, axis=1).reshape(T * width, -1)  # one sequence over the clip
        for block in self.blocks:
            x = block(x)
        x = self.norm(x).reshape(T, width, -1)
        z, z_root = x[:, :NUM_KEYPOINTS], x[:, NUM_KEYPOINTS]
        z_frame = jnp.mean(z, axis=1)
        return MotionEvidence(
            features=z,
            root=z_root,
            onscreen_logits=self.onscreen_head(z_frame)[:, 0],
            canonical_joints=self.joints_head(z),
            pose_6d=self.pose_head(z_frame).reshape(T, 16, 6),
            root_velocity=self.velocity_head(z_root),
        )
