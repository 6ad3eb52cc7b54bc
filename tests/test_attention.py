"""The cross-view attention probe (size-depth binding study, paper 5.4): the probabilities
come from the forward pass's own code (bit-identical outputs), form distributions over
the other view's patches, see the placeholder where a view is dropped or removed; hand
patches and the share of attention on them; the figures."""

import dataclasses
import math

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest

from esther_jax import model as M
from esther_jax.crops import patch_centres
from esther_jax.studies import attention as A
from esther_jax.eval import reports
from esther_jax.mano import KEYPOINT_PARENTS
from esther_jax.model._layers import _apply_rope, grid_rope

from .test_model import random_clip

FRAMES = 2
CFG = M.config("cpu-tiny", num_frames=FRAMES, stereo_layers=2)
TARGET = np.asarray([0.0, 0.05, 0.4])
"""Where `random_clip`'s crop cameras look (rig frame, metres)."""

probe = eqx.filter_jit(M.cross_view_attention)
hand_patch_mask = jax.jit(A.hand_patch_mask, static_argnames=("crop_size", "grid", "radius"))
attention_on_hand = jax.jit(A.attention_on_hand, static_argnums=2)


def network(cfg):
    """A network of config `cfg` with weights drawn by numpy (normal, std 0.2): the pytree
    of `M.ESTHER(cfg, key=...)` (from an abstract trace) without compiling its
    initialisers, which takes most of this module's time on a small CPU. Configs of one
    structure get the same weights."""
    skeleton = eqx.filter_eval_shape(M.ESTHER, cfg, key=jax.random.key(0))
    rng = np.random.default_rng(0)
    return jax.tree.map(lambda leaf: jnp.asarray(rng.normal(0.0, 0.2, leaf.shape), leaf.dtype), skeleton)


@pytest.fixture(scope="module")
def net():
    return network(CFG)


@pytest.fixture(scope="module")
def clip():
    return random_clip(jax.random.key(1), CFG, frames=FRAMES, features=True)


def dropped(clip, view):
    """The clip with `view` marked absent in every frame."""
    return dataclasses.replace(clip, view_present=clip.view_present.at[:, view].set(False))


# ----------------------------------------------------------------------------- the forward pass is unchanged


def _attention_before(attn, x, context=None, rope=None):
    """`Attention.__call__` as it was before the probe (the reference for bit-identity)."""
    dim = x.shape[-1]
    w, b = attn.qkv.weight, attn.qkv.bias
    if context is None:
        q, k, v = jnp.split(x @ w + b, 3, axis=-1)
    else:
        q = x @ w[:, :dim] + b[:dim]
        k, v = jnp.split(context @ w[:, dim:] + b[dim:], 2, axis=-1)

    def heads(t):
        return jnp.swapaxes(t.reshape(t.shape[:-1] + (attn.heads, dim // attn.heads)), -2, -3)

    q, k, v = heads(q), heads(k), heads(v)
    if rope is not None:
        q, k = _apply_rope(q, rope), _apply_rope(k, rope)
    logits = jnp.einsum("...qd,...kd->...qk", q, k) / math.sqrt(dim // attn.heads)
    out = jnp.einsum("...qk,...kd->...qd", jax.nn.softmax(logits, axis=-1), v)
    out = jnp.swapaxes(out, -2, -3)
    return attn.proj(out.reshape(out.shape[:-2] + (dim,)))


def _stereo_block_before(block, x):
    """`StereoBlock.__call__` as it was before the probe."""
    x = x + _attention_before(block.self_attn, block.norm_self(x))
    y = block.norm_cross(x)
    x = x + _attention_before(block.cross_attn, y, y[:, ::-1])
    return x + block.mlp(block.norm_mlp(x))


@eqx.filter_jit
def _layers_now_and_before(block, x):
    """(now, before) pairs of the attention layer (self, cross, rotary as in the ViT) and
    of the stereo block's tokens (its probabilities unused, as in the forward pass)."""
    attn = block.cross_attn
    rope = grid_rope(CFG.grid, CFG.dim // CFG.heads)
    cases = [(None, None), (x[:, ::-1], None), (None, rope)]
    now, before = [], []
    for context, rp in cases:
        now += [attn(x, context, rp), attn.attend(x, context, rp)[0]]
    now.append(block(x)[0])
    with jax.numpy_rank_promotion("allow"):  # the references add (D,) biases to token arrays implicitly, as the layers then did
        for context, rp in cases:
            before += [_attention_before(attn, x, context, rp)] * 2
        before.append(_stereo_block_before(block, x))
    return list(zip(now, before))


def test_layers_compute_what_they_did_before_the_probe(net):
    x = jnp.asarray(np.random.default_rng(2).normal(size=(FRAMES, 2, CFG.grid**2, CFG.dim)), jnp.float32)
    for now, before in _layers_now_and_before(net.image_encoder.blocks[0], x):
        np.testing.assert_array_equal(now, before)


# ----------------------------------------------------------------------------- the probe


def test_probabilities_are_distributions_over_the_other_views_patches(net, clip):
    probs = probe(net, clip)
    P = CFG.grid**2
    assert probs.shape == (CFG.stereo_layers, FRAMES, 2, CFG.heads, P, P)
    assert bool(jnp.all(probs >= 0))
    np.testing.assert_allclose(jnp.sum(probs, axis=-1), 1.0, atol=1e-5)
    # the views read each other: view 0's queries see view 1's keys and vice versa, so
    # the two directions differ
    assert not np.allclose(probs[:, :, 0], probs[:, :, 1])
    # one clip in, vmap out
    clips = jax.tree.map(lambda a, b: jnp.stack([a, b]), clip, dropped(clip, 0))
    batched = eqx.filter_jit(jax.vmap(M.cross_view_attention, in_axes=(None, 0)))(net, clips)
    np.testing.assert_allclose(batched[0], probs, atol=1e-6)
    np.testing.assert_allclose(batched[1], probe(net, dropped(clip, 0)), atol=1e-6)


def test_dropped_view_queries_are_the_placeholder(net, clip):
    blanked = dropped(clip, 1)
    probs = probe(net, blanked)
    assert bool(jnp.all(jnp.isfinite(probs)))
    # every patch of the dropped view is the same view-mask token: its queries (the
    # placeholder's, into the kept view 0) are one row repeated over the patches
    placeholder = probs[:, :, 1]  # (layers, T, heads, P, P)
    np.testing.assert_allclose(placeholder, jnp.broadcast_to(placeholder[..., :1, :], placeholder.shape), atol=1e-6)
    assert not np.allclose(probs[:, :, 1], probe(net, clip)[:, :, 1])  # not the right view's own queries
    # the dropped view's features and calibration are never read
    garbage = dataclasses.replace(
        blanked,
        features=blanked.features.at[:, 1].set(jnp.asarray(np.random.default_rng(5).normal(size=blanked.features.shape[2:]), jnp.float32)),
        K=blanked.K.at[:, 1].set(0.0),
        R_cam_crop=blanked.R_cam_crop.at[:, 1].set(jnp.nan),
    )
    np.testing.assert_array_equal(probe(net, garbage), probs)


def test_monocular_model_sees_the_placeholder_in_its_second_view(net, clip):
    # the ablation changes no weight (`network` gives both configs the same weights);
    # the monocular network drops the second view itself
    mono = network(M.config("cpu-tiny", ablation="monocular", num_frames=FRAMES, stereo_layers=2))
    np.testing.assert_array_equal(probe(mono, clip), probe(net, dropped(clip, 1)))


def test_probe_needs_cross_view_attention(clip):
    flat = network(M.config("cpu-tiny", ablation="no-cross-view", num_frames=FRAMES))
    with pytest.raises(ValueError, match="no cross-view attention"):
        M.cross_view_attention(flat, clip)


# ----------------------------------------------------------------------------- hand patches


def _crop_pixels(clip, joints):
    """Numpy reference: pixels (T, 2, n, 2) of rig-frame points (T, n, 3) in each crop."""
    K, R_cam_crop, T_rig_cams = (np.asarray(a, np.float64) for a in (clip.K, clip.R_cam_crop, clip.T_rig_cams))
    R_rig_crop = np.einsum("vij,tvjk->tvik", T_rig_cams[:, :3, :3], R_cam_crop)
    X = np.einsum("tvji,tvnj->tvni", R_rig_crop, joints[:, None] - T_rig_cams[None, :, None, :3, 3])  # R^T (X - t)
    return np.einsum("tvij,tvnj->tvni", K[..., :2, :2], X[..., :2] / X[..., 2:]) + K[:, :, None, :2, 2]


def _segment_distance(points, start, end):
    """Numpy reference: distance of each point (n, 2) to each segment (m, 2 ends) -> (n, m)."""
    d = end - start
    t = np.clip(np.einsum("nmi,mi->nm", points[:, None] - start[None], d) / np.maximum(np.sum(d * d, -1), 1e-12), 0, 1)
    return np.linalg.norm(points[:, None] - (start[None] + t[..., None] * d[None]), axis=-1)


def test_hand_patch_mask_holds_the_projected_skeleton(clip):
    S, G = CFG.crop_size, CFG.grid
    joints = TARGET + 0.03 * np.random.default_rng(3).normal(size=(FRAMES, 21, 3))
    half_dropped = dataclasses.replace(clip, view_present=clip.view_present.at[1, 1].set(False))
    mask = np.asarray(hand_patch_mask(half_dropped, jnp.asarray(joints, jnp.float32), crop_size=S, grid=G))
    assert mask.shape == (FRAMES, 2, G, G) and mask.dtype == bool
    assert not mask[1, 1].any()  # an absent view has no hand patches
    uv = _crop_pixels(clip, joints)
    cell = S / G
    centres = np.asarray(patch_centres(S, G)).reshape(-1, 2)
    child = np.arange(1, 21)
    parent = np.asarray(KEYPOINT_PARENTS)[1:]
    for t, v in [(0, 0), (0, 1), (1, 0)]:
        # the patch holding each joint that projects into the crop is a hand patch
        for u, w in uv[t, v]:
            if -0.5 <= u < S - 0.5 and -0.5 <= w < S - 0.5:
                assert mask[t, v, int((w + 0.5) // cell), int((u + 0.5) // cell)], (t, v, u, w)
        # and the mask is the patches within one patch side of a bone (up to float32
        # rounding at the boundary)
        distance = _segment_distance(centres, uv[t, v, parent], uv[t, v, child]).min(axis=1).reshape(G, G)
        assert np.all(mask[t, v][distance < cell - 1e-3]) and not np.any(mask[t, v][distance > cell + 1e-3])
    assert 0 < mask[0, 0].sum() < G * G  # the hand covers part of the crop
    # every keypoint at one point (a fist seen end-on): the patches within `radius`
    # patch sides of its pixel
    point = np.broadcast_to(TARGET, (FRAMES, 21, 3))
    wide = np.asarray(hand_patch_mask(clip, jnp.asarray(point, jnp.float32), crop_size=S, grid=G, radius=1.5))
    distance = np.linalg.norm(centres - _crop_pixels(clip, point)[0, 0, 0], axis=-1)
    np.testing.assert_array_equal(wide[0, 0].reshape(-1), distance <= 1.5 * cell)
    with pytest.raises(ValueError, match="radius"):
        A.hand_patch_mask(clip, jnp.asarray(joints, jnp.float32), crop_size=S, grid=G, radius=0.0)


# ----------------------------------------------------------------------------- the share on the hand


def test_attention_on_hand_known_answers():
    L, H, G = 3, 2, 4
    P = G * G
    logits = np.random.default_rng(4).normal(size=(L, FRAMES, 2, H, P, P))
    attention = np.exp(logits) / np.sum(np.exp(logits), axis=-1, keepdims=True)
    everywhere = np.ones((FRAMES, 2, G, G), bool)
    np.testing.assert_allclose(attention_on_hand(jnp.asarray(attention, jnp.float32), everywhere, 0).share, 1.0, rtol=1e-6)
    # uniform attention lands on the hand in proportion to its patches: the chance share
    uniform = np.full((L, FRAMES, 2, H, P, P), 1.0 / P)
    mask = np.zeros((FRAMES, 2, G, G), bool)
    mask[0, 0, :2, :3] = mask[1, 0, 1, :] = True
    chance = attention_on_hand(jnp.asarray(uniform, jnp.float32), mask, 0)
    assert int(chance.frames) == FRAMES
    np.testing.assert_allclose(chance.chance, (6 / P + 4 / P) / 2, rtol=1e-6)
    np.testing.assert_allclose(chance.share, np.full(L, chance.chance), rtol=1e-6)
    # a frame where the kept view has no hand patches does not count; nor does the other view's mask
    some = mask.copy()
    some[1, 0] = False
    some[:, 1] = True
    result = attention_on_hand(jnp.asarray(attention, jnp.float32), some, 0)
    assert int(result.frames) == 1
    expected = attention[:, 0, 1][..., some[0, 0].reshape(-1)].sum(-1).mean(axis=(1, 2))  # queries of view 1, frame 0
    np.testing.assert_allclose(result.share, expected, rtol=1e-5)
    np.testing.assert_allclose(result.chance, 6 / P, rtol=1e-6)
    assert bool(jnp.all(jnp.isnan(attention_on_hand(jnp.asarray(attention, jnp.float32), np.zeros_like(mask), 0).share)))
    # clips (leading axes) pool with the frames
    pooled = attention_on_hand(jnp.asarray(np.stack([attention, uniform]), jnp.float32), np.stack([some, mask]), 0)
    assert int(pooled.frames) == 3
    np.testing.assert_allclose(pooled.share, (expected + 2 * chance.share) / 3, rtol=1e-5)
    # the map is a distribution over the kept view's patches
    np.testing.assert_allclose(np.sum(np.asarray(A.attention_map(jnp.asarray(attention), 1)), axis=(-2, -1)), 1.0, rtol=1e-5)
    with pytest.raises(ValueError, match="kept_view"):
        A.attention_on_hand(jnp.asarray(attention), jnp.asarray(mask), 2)
    with pytest.raises(ValueError, match="does not match"):
        A.attention_on_hand(jnp.asarray(attention), jnp.asarray(mask[..., :2, :2]), 0)  # a 2 x 2 grid for 16 patches


def test_attention_figures(tmp_path, net, clip):
    S, G = CFG.crop_size, CFG.grid
    probs = probe(net, dropped(clip, 1))
    maps = np.asarray(A.attention_map(probs, 0))[:, 0]  # frame 0: (layers, G, G)
    hand = np.zeros((G, G), bool)
    hand[1:3, 1:3] = True
    crop = np.random.default_rng(0).uniform(size=(S, S, 3))
    path = reports.plot_attention_maps(crop, {"view-mask": maps, "stereo": maps[::-1]}, tmp_path / "maps.png", hand_mask=hand)
    assert path.stat().st_size > 0
    shares = {"stereo": np.asarray([0.6, 0.7]), "view-mask": np.asarray([0.4, 0.3])}
    path = reports.plot_attention_shares(shares, {"stereo": 0.25, "view-mask": 0.25}, tmp_path / "shares.png", title="held-out")
    assert path.stat().st_size > 0
