"""The query-gated fusion decoder (paper 3.7, appendix E).

Per frame 16 pose tokens (MANO joints, root first), one shape token and one wrist
token (with `triangulated_wrist_input`, not in the paper, the wrist token's query also
carries an embedding of the encoder's triangulated wrist). Per layer the clip's tokens
self-attend, then read three sources, F (S_img, the same frame's 21 joint features),
Z (S_mot, the same frame's motion features) and z_root (S_root, the clip's root
features), mixed by a per-token softmax gate:

    q+ = FFN(h + sum_k g^k CrossAttn(h, S_k)),   g = softmax(MLP([h, mean S_k..., e]))

with e the four evidence statistics of the frame (`evidence_statistics`). The FFN is
a pre-norm residual MLP. Pose is decoded along MANO's tree, each joint's local 6D
rotation from its token and its parent's world rotation; betas once per clip from the
time-pooled shape token; the wrist translation (rig frame, metres) by an MLP on the
wrist token.
"""

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Bool, Float, PRNGKeyArray

from .._math import matmul3
from ..mano.constants import MANO_PARENTS
from ..mano.kinematics import _levels
from ..rotations import matrix_to_rotation_6d, rotation_6d_to_matrix
from ._layers import Attention, LayerNorm, Mlp, _trunc_normal
from .config import ModelConfig
from .motion_encoder import MotionEvidence
from .stereo_encoder import ImageEvidence

NUM_POSE_TOKENS = 16
SHAPE_TOKEN = 16
WRIST_TOKEN = 17
NUM_QUERIES = 18
NUM_SOURCES = 3
"""Sources in gate order: S_img, S_mot, S_root."""
NUM_EVIDENCE = 4
WRIST_PRIOR_M = (0.0, 0.0, 0.4)
"""The wrist MLP predicts an offset from a typical egocentric hand 0.4 m ahead of the rig."""
WRIST_INPUT_SCALE_M = 0.1
"""The triangulated wrist enters the wrist query as (t - WRIST_PRIOR_M) / 0.1 m: unit-scale
inputs, so its small axis (the height y) is not left in a direction of small variance."""
_IDENTITY_6D = (1.0, 0.0, 0.0, 0.0, 1.0, 0.0)


def evidence_statistics(
    image: ImageEvidence, view_present: Bool[Array, "T 2"], motion_mask: Bool[Array, "T 21"]
) -> Float[Array, "T 4"]:
    """The gate's four evidence statistics per frame (appendix E), masked slots excluded.

    Mean and minimum predicted visibility over present views and unmasked keypoints
    (absent views and masked keypoints count as invisible), the norm of the
    triangulated wrist (m) and the mean triangulation spread (cm) over valid unmasked
    keypoints (0 where there is none). Gradient-free: they are evidence, not features.
    """
    image = jax.lax.stop_gradient(image)
    keep = view_present[:, :, None] & ~motion_mask[:, None, :]
    vis = jnp.where(keep, jax.nn.sigmoid(image.visibility_logits.astype(image.triangulated.dtype)), 0.0)
    usable = image.triangulation_valid & ~motion_mask
    wrist = jnp.where(usable[:, 0], jnp.linalg.norm(image.triangulated[:, 0], axis=-1), 0.0)
    count = jnp.sum(usable.astype(vis.dtype), axis=1)
    spread = jnp.sum(jnp.where(usable, image.triangulation_spread, 0.0), axis=1) / jnp.maximum(count, 1.0)
    return jnp.stack([jnp.mean(vis, axis=(1, 2)), jnp.min(vis, axis=(1, 2)), wrist, 100.0 * spread], axis=-1)


class FusionLayer(eqx.Module):
    norm_self: LayerNorm
    self_attn: Attention
    norm_query: LayerNorm
    norm_sources: tuple[LayerNorm, LayerNorm, LayerNorm]
    cross_attn: tuple[Attention, Attention, Attention]
    gate: Mlp | None
    """Gate logits from [h, pooled S_img, pooled S_mot, S_root, evidence]; None = uniform."""
    norm_mlp: LayerNorm
    mlp: Mlp

    def __init__(self, cfg: ModelConfig, *, key: PRNGKeyArray):
        keys = jax.random.split(key, 6)
        d = cfg.dim
        self.norm_self, self.norm_query, self.norm_mlp = LayerNorm(d), LayerNorm(d), LayerNorm(d)
        self.self_attn = Attention(d, cfg.heads, key=keys[0])
        self.norm_sources = (LayerNorm(d), LayerNorm(d), LayerNorm(d))
        self.cross_attn = tuple(Attention(d, cfg.heads, key=k) for k in keys[1:4])
        self.gate = Mlp((1 + NUM_SOURCES) * d + NUM_EVIDENCE, d, NUM_SOURCES, key=keys[4]) if cfg.learned_gate else None
        self.mlp = Mlp(d, int(d * cfg.mlp_ratio), d, key=keys[5])

    def __call__(
        self,
        queries: Float[Array, "T 18 D"],
        image: Float[Array, "T 21 D"],
        motion: Float[Array, "T 21 D"],
        root: Float[Array, "T D"],
        evidence: Float[Array, "T 4"],
    ) -> tuple[Float[Array, "T 18 D"], Float[Array, "T 18 3"]]:
        T, Q, d = queries.shape
        h = queries + self.self_attn(self.norm_self(queries).reshape(T * Q, d)).reshape(T, Q, d)  # clip-wide
        s_img, s_mot, s_root = (norm(s) for norm, s in zip(self.norm_sources, (image, motion, root)))
        hq = self.norm_query(h)
        reads = jnp.stack(
            [
                self.cross_attn[0](hq, s_img),  # the same frame's joint features
                self.cross_attn[1](hq, s_mot),
                self.cross_attn[2](hq.reshape(T * Q, d), s_root).reshape(T, Q, d),  # the clip's root features
            ],
            axis=-2,
        )  # (T, Q, 3, D)
        if self.gate is None:
            gate = jnp.full((T, Q, NUM_SOURCES), 1.0 / NUM_SOURCES, h.dtype)
        else:
            pooled = jnp.concatenate([jnp.mean(s_img, axis=1), jnp.mean(s_mot, axis=1), s_root, evidence], axis=-1)
            inputs = jnp.concatenate([hq, jnp.broadcast_to(pooled[:, None, :], (T, Q, pooled.shape[-1]))], axis=-1)
            gate = jax.nn.softmax(self.gate(inputs), axis=-1)
        h = h + jnp.einsum("tqk,tqkd->tqd", gate, reads)
        return h + self.mlp(self.norm_mlp(h)), gate


class Decoded(eqx.Module):
    """Decoder outputs for one clip (right hand, rig frame)."""

    pose_6d: Float[Array, "T 16 6"]
    """Local MANO joint rotations, root (global orientation) first, 6D."""
    rotations: Float[Array, "T 16 3 3"]
    betas: Float[Array, "10"]
    transl: Float[Array, "T 3"]
    """Wrist position (rig frame, metres)."""
    gates: Float[Array, "layers T 18 3"]
    """Softmax gate per layer and token over (S_img, S_mot, S_root)."""


def decode_kinematic_tree(head: Mlp, tokens: Float[Array, "16 D"], dtype=None) -> tuple[Float[Array, "16 6"], Float[Array, "16 3 3"]]:
    """Local 6D rotation of each MANO joint from its token and its parent's world rotation.

    Joints are decoded level by level down the tree (root; the fingers' first, second,
    third joints), each conditioned on its parent's world rotation (6D), so a joint's
    output depends only on its own and its ancestors' tokens. The rotations are in
    `dtype` (default: the tokens'; float32 geometry under mixed precision).
    """
    dtype = tokens.dtype if dtype is None else dtype
    identity6 = jnp.asarray(_IDENTITY_6D, dtype)
    order: list[int] = []  # the joints decoded so far: the rows of `world`
    local6, local, world = [], [], None
    for joints in _levels(MANO_PARENTS):  # the root alone, then whole levels at once
        if world is None:
            parent_world, parent6 = None, jnp.broadcast_to(identity6, (len(joints), 6))
        else:
            parent_world = world[np.asarray([order.index(MANO_PARENTS[j]) for j in joints])]
            parent6 = matrix_to_rotation_6d(parent_world)
        out = head(jnp.concatenate([tokens[np.asarray(joints)], parent6.astype(tokens.dtype)], axis=-1)).astype(dtype) + identity6[None]
        R = rotation_6d_to_matrix(out)
        level_world = R if parent_world is None else matmul3(parent_world, R)
        world = level_world if world is None else jnp.concatenate([world, level_world])
        order += joints
        local6.append(out)
        local.append(R)
    mano_order = np.argsort(order)
    return jnp.concatenate(local6)[mano_order], jnp.concatenate(local)[mano_order]


class FusionDecoder(eqx.Module):
    queries: Float[Array, "18 D"]
    """16 pose tokens (MANO joint order), the shape token, the wrist token."""
    time_embed: Float[Array, "frames D"]
    layers: tuple[FusionLayer, ...]
    norm_out: LayerNorm
    pose_head: Mlp
    shape_head: Mlp
    wrist_head: Mlp
    wrist_input: Mlp | None
    """Embeds the standardised triangulated wrist into the wrist query (None: no such input)."""
    anchored_wrist: bool = eqx.field(static=True)

    def __init__(self, cfg: ModelConfig, *, key: PRNGKeyArray):
        keys = jax.random.split(key, 6)
        d = cfg.dim
        self.queries = _trunc_normal(keys[0], (NUM_QUERIES, d))
        self.time_embed = _trunc_normal(keys[1], (cfg.num_frames, d))
        self.layers = tuple(FusionLayer(cfg, key=k) for k in jax.random.split(keys[2], cfg.fusion_layers))
        self.norm_out = LayerNorm(d)
        self.pose_head = Mlp(d + 6, d, 6, key=keys[3], depth=3)
        self.shape_head = Mlp(d, d, 10, key=keys[4], depth=3)
        self.wrist_head = Mlp(d, d, 3, key=keys[5], depth=3)
        # its own key, so the switch leaves every other weight's initialisation unchanged
        self.wrist_input = Mlp(3, d, d, key=jax.random.fold_in(key, 6)) if cfg.triangulated_wrist_input else None
        self.anchored_wrist = cfg.anchored_wrist

    def __call__(
        self,
        image_features: Float[Array, "T 21 D"],
        motion: MotionEvidence,
        evidence: Float[Array, "T 4"],
        triangulated_wrist: Float[Array, "T 3"],
        wrist_valid: Bool[Array, "T"],
    ) -> Decoded:
        T = image_features.shape[0]
        geometry = triangulated_wrist.dtype  # the outputs' dtype (float32 under mixed precision)
        q = jnp.broadcast_to(self.queries, (T,) + self.queries.shape) + self.time_embed[:T, None, :]
        evidence = evidence.astype(q.dtype)
        prior = jnp.asarray(WRIST_PRIOR_M, geometry)
        if self.wrist_input is not None:  # evidence, like the gate's statistics: no gradient into the triangulation
            seen = jnp.where(wrist_valid[:, None], jax.lax.stop_gradient(triangulated_wrist), prior[None])
            embedded = self.wrist_input(((seen - prior[None]) / WRIST_INPUT_SCALE_M).astype(q.dtype))
            q = q.at[:, WRIST_TOKEN].add(jnp.where(wrist_valid[:, None], embedded, 0.0))
        gates = []
        for layer in self.layers:
            q, gate = layer(q, image_features, motion.features, motion.root, evidence)
            gates.append(gate)
        q = self.norm_out(q)
        pose_6d, rotations = jax.vmap(decode_kinematic_tree, in_axes=(None, 0, None))(self.pose_head, q[:, :NUM_POSE_TOKENS], geometry)
        betas = self.shape_head(jnp.mean(q[:, SHAPE_TOKEN], axis=0)).astype(geometry)
        base = jnp.broadcast_to(prior, (T, 3))
        if self.anchored_wrist:
            base = jnp.where(wrist_valid[:, None], triangulated_wrist, base)
        transl = base + self.wrist_head(q[:, WRIST_TOKEN]).astype(geometry)
        return Decoded(pose_6d=pose_6d, rotations=rotations, betas=betas, transl=transl, gates=jnp.stack(gates))
