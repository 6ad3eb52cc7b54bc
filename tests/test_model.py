"""The ESTHER network: configs, shapes, masking semantics, kinematic decoding, mirroring,
gradients, jit/vmap, serialisation, backbone weights (small configs, few frames)."""

import dataclasses
import json

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest

from esther_jax import model as M
from esther_jax.cameras import PinholeCamera, rig_preset
from esther_jax.crops import crop_poses
from esther_jax.data.synth import SynthConfig, make_clip
from esther_jax.mano import MANO_PARENTS, load_builtin
from esther_jax.model._layers import Mlp
from esther_jax.triangulation import triangulate

from .helpers import aimed_crop_cameras

FRAMES = 4
TINY = M.config("cpu-tiny", num_frames=FRAMES)


@pytest.fixture(scope="module")
def hand_model():
    return load_builtin("right")


def random_clip(key, cfg=TINY, frames=FRAMES, features=False):
    """A clip whose crop cameras look at a hand ~0.4 m ahead (both views see it)."""
    S = cfg.crop_size
    rig = rig_preset("esther")
    k1, k2 = jax.random.split(key)
    K, R = aimed_crop_cameras(rig, S, 1.2 * S)  # aimed at (0, 0.05, 0.4) in the rig frame
    R = jnp.broadcast_to(R, (frames, 2, 3, 3))
    P, C = cfg.grid**2, cfg.backbone_spec.width
    return M.ClipInput(
        images=None if features else jax.random.uniform(k1, (frames, 2, 3, S, S)),
        features=jax.random.normal(k1, (frames, 2, P, C)) if features else None,
        K=jnp.broadcast_to(K, (frames, 2, 3, 3)),
        R_cam_crop=R,
        T_rig_cams=rig.T_rig_cams,
        flow=0.01 * jax.random.normal(k2, (frames, 192)),
        view_present=jnp.ones((frames, 2), bool),
    )


@eqx.filter_jit
def run(net, clip, hand_model, motion_mask=None):
    """The forward pass, compiled once per network structure and input shapes (shared by
    the tests of this module)."""
    return net(clip, hand_model, motion_mask=motion_mask)


def assert_finite_output(out, frames):
    assert out.joints.shape == (frames, 21, 3)
    assert out.params.hand_pose.shape == (frames, 15, 3)
    assert out.decoded.betas.shape == (10,)
    assert out.motion.onscreen_logits.shape == (frames,)
    for name, leaf in jax.tree_util.tree_leaves_with_path(out):
        if jnp.issubdtype(leaf.dtype, jnp.floating):
            assert bool(jnp.all(jnp.isfinite(leaf))), jax.tree_util.keystr(name)


# ----------------------------------------------------------------------------- configs


def test_paper_parameter_counts_match_appendix_e():
    counts = M.parameter_counts("paper")
    for part, millions in [("image_encoder", 21.9), ("motion_encoder", 12.8), ("fusion_decoder", 16.6), ("trainable", 51.3)]:
        assert abs(counts[part] / 1e6 - millions) <= 0.05 * millions, (part, counts[part])
    assert abs(counts["backbone"] / 1e6 - 303.1) <= 0.01 * 303.1
    assert counts["total"] == counts["backbone"] + counts["trainable"]  # frozen backbone


def test_config_names_ablations_and_json():
    cfg = M.config("cpu-small", ablation="no-plucker", num_frames=8)
    assert not cfg.plucker and cfg.num_frames == 8 and cfg.name == "cpu-small:no-plucker"
    assert M.ModelConfig.from_json(cfg.to_json()) == cfg
    assert set(M.ABLATIONS) >= {"no-plucker", "no-cross-view", "no-flow-token", "no-2d-guidance", "uniform-gate",
                                "anchored-wrist", "monocular", "no-motion-masking", "no-triangulation-guidance"}  # fmt: skip
    with pytest.raises(ValueError, match="unknown model config"):
        M.config("huge")
    with pytest.raises(ValueError, match="unknown ablation"):
        M.config("paper", ablation="no-hands")
    with pytest.raises(ValueError, match="multiple of the patch size"):
        M.config("paper", crop_size=100)


def test_paper_config_shapes_from_precomputed_features(hand_model):
    cfg = M.config("paper", precomputed_features=True)
    net = eqx.filter_eval_shape(M.ESTHER, cfg, key=jax.random.key(0))
    clip = random_clip(jax.random.key(1), cfg, frames=16, features=True)
    out = eqx.filter_eval_shape(lambda n, c, h: n(c, h), net, clip, hand_model)
    assert out.image.features.shape == (16, 21, 512)
    assert out.image.heatmap_logits.shape == (16, 2, 21, 14, 14)
    assert out.image.depth_logits.shape == (16, 2, 21, 64)
    assert out.motion.features.shape == (16, 21, 512) and out.motion.root.shape == (16, 512)
    assert out.decoded.gates.shape == (2, 16, 18, 3)
    assert out.vertices.shape == (16, hand_model.v_template.shape[0], 3)


NETWORK_ABLATIONS = [row for row, fields in M.ABLATIONS.items() if not set(fields) <= {"guidance_2d", "guidance_triangulation", "motion_masking", "image_augmentation"}]
"""Rows that change the network's graph; the training rows change the losses and the
corruption, not the forward pass (tests/test_train.py checks them)."""


@pytest.mark.parametrize("ablation", [None, *NETWORK_ABLATIONS])
def test_every_ablation_runs_finite(ablation, hand_model):
    cfg = M.config("cpu-tiny", ablation=ablation, num_frames=FRAMES)
    net = M.ESTHER(cfg, key=jax.random.key(0))
    out = run(net, random_clip(jax.random.key(1), cfg), hand_model)
    assert_finite_output(out, FRAMES)
    if ablation == "uniform-gate":
        np.testing.assert_allclose(out.decoded.gates, 1.0 / 3.0)
    if ablation == "monocular":  # the second view never contributes
        assert not bool(jnp.any(out.image.triangulation_valid))


def test_triangulated_wrist_input_is_read_only_where_the_triangulation_is_valid(hand_model):
    base = M.ESTHER(TINY, key=jax.random.key(0))
    net = M.ESTHER(TINY.replace(triangulated_wrist_input=True), key=jax.random.key(0))
    # the switch adds one embedding and leaves every other weight's initialisation as it was
    without = eqx.tree_at(lambda n: n.fusion_decoder.wrist_input, net, None, is_leaf=lambda x: x is None)
    assert all(bool(jnp.array_equal(a, b)) for a, b in zip(jax.tree.leaves(without), jax.tree.leaves(base), strict=True))
    clip = random_clip(jax.random.key(1))
    both, both_base = run(net, clip, hand_model), run(base, clip, hand_model)
    assert_finite_output(both, FRAMES)
    assert bool(jnp.all(both.image.triangulation_valid[:, 0]))
    assert float(jnp.abs(both.decoded.transl - both_base.decoded.transl).max()) > 0
    # one view blanked throughout: no triangulation, so the input is absent and the two networks agree
    one = dataclasses.replace(clip, view_present=clip.view_present.at[:, 1].set(False))
    for a, b in zip(jax.tree.leaves(run(net, one, hand_model)), jax.tree.leaves(run(base, one, hand_model))):
        np.testing.assert_array_equal(a, b)

    def wrist_given_input(embedding, c):
        return jnp.sum(eqx.tree_at(lambda n: n.fusion_decoder.wrist_input, net, embedding)(c, hand_model).decoded.transl)

    grad = eqx.filter_jit(eqx.filter_grad(wrist_given_input))
    assert max(float(jnp.abs(g).max()) for g in jax.tree.leaves(grad(net.fusion_decoder.wrist_input, clip))) > 0
    assert max(float(jnp.abs(g).max()) for g in jax.tree.leaves(grad(net.fusion_decoder.wrist_input, one))) == 0


def test_cpu_small_runs_finite(hand_model):
    cfg = M.config("cpu-small", num_frames=FRAMES)
    net = M.ESTHER(cfg, key=jax.random.key(0))
    out = run(net, random_clip(jax.random.key(1), cfg), hand_model)
    assert_finite_output(out, FRAMES)
    assert out.image.heatmap_logits.shape == (FRAMES, 2, 21, 7, 7)


# ----------------------------------------------------------------------------- semantics


@pytest.fixture(scope="module")
def tiny_net():
    return M.ESTHER(TINY, key=jax.random.key(0))


def test_blanked_view_is_the_view_mask_token(tiny_net, hand_model):
    clip = random_clip(jax.random.key(1))
    present = clip.view_present.at[1, 1].set(False)
    blanked = dataclasses.replace(clip, view_present=present)
    out = run(tiny_net, blanked, hand_model)
    # the blanked view's pixels and calibration are never read
    garbage = dataclasses.replace(
        blanked,
        images=blanked.images.at[1, 1].set(jax.random.uniform(jax.random.key(9), blanked.images.shape[2:])),
        K=blanked.K.at[1, 1].set(0.0),
        R_cam_crop=blanked.R_cam_crop.at[1, 1].set(jnp.nan),
    )
    out2 = run(tiny_net, garbage, hand_model)
    for a, b in zip(jax.tree.leaves(out), jax.tree.leaves(out2)):
        np.testing.assert_array_equal(a, b)
    # ... the view-mask token is read instead, and only when a view is blanked
    def joints_given_token(token, c):
        net = eqx.tree_at(lambda n: n.image_encoder.view_mask_token, tiny_net, token)
        return jnp.sum(net(c, hand_model).joints)

    token = tiny_net.image_encoder.view_mask_token
    grad = jax.jit(jax.grad(joints_given_token))
    assert float(jnp.abs(grad(token, blanked)).max()) > 0
    assert float(jnp.abs(grad(token, clip)).max()) == 0


def test_masked_frames_change_nothing_the_mask_hides(tiny_net, hand_model):
    clip = random_clip(jax.random.key(1))
    mask = jnp.zeros((FRAMES, 21), bool).at[2].set(True).at[0, 5].set(True)
    out = run(tiny_net, clip, hand_model, motion_mask=mask)
    changed = dataclasses.replace(clip, images=clip.images.at[2].set(1.0 - clip.images[2]))
    out2 = run(tiny_net, changed, hand_model, motion_mask=mask)
    assert not np.allclose(out.image.features[2], out2.image.features[2])  # the image encoder saw it
    hidden = lambda o: (o.motion, o.decoded, o.params, o.joints, o.vertices)
    for a, b in zip(jax.tree.leaves(hidden(out)), jax.tree.leaves(hidden(out2))):
        np.testing.assert_array_equal(a, b)
    # a single masked joint slot: the motion encoder never reads its feature
    enc = tiny_net.motion_encoder
    F = jax.random.normal(jax.random.key(3), (FRAMES, 21, TINY.dim))
    z1 = enc(enc.mask(F, mask), clip.flow)
    z2 = enc(enc.mask(F.at[0, 5].add(5.0), mask), clip.flow)
    for a, b in zip(jax.tree.leaves(z1), jax.tree.leaves(z2)):
        np.testing.assert_allclose(a, b, rtol=0, atol=0)
    # ... whereas the flow token is never masked: it still matters in a fully masked frame
    z3 = enc(enc.mask(F, mask), clip.flow.at[2].add(1.0))
    assert not np.allclose(z1.root[2], z3.root[2])


def test_gate_sums_to_one_per_token(tiny_net, hand_model):
    out = run(tiny_net, random_clip(jax.random.key(1)), hand_model)
    gates = out.decoded.gates
    assert gates.shape == (TINY.fusion_layers, FRAMES, 18, 3)
    np.testing.assert_allclose(jnp.sum(gates, axis=-1), 1.0, atol=1e-6)
    assert bool(jnp.all(gates > 0))


def test_kinematic_decoding_follows_the_mano_tree(tiny_net):
    head = tiny_net.fusion_decoder.pose_head
    tokens = jax.random.normal(jax.random.key(2), (16, TINY.dim))
    jac = jax.jacobian(lambda t: M.decode_kinematic_tree(head, t)[0])(tokens)  # (16, 6, 16, D)
    depends = np.asarray(jnp.abs(jac).max(axis=(1, 3)) > 0)
    for j in range(16):
        ancestors, p = {j}, MANO_PARENTS[j]
        while p >= 0:
            ancestors.add(p)
            p = MANO_PARENTS[p]
        assert set(np.flatnonzero(depends[j])) == ancestors, j


def test_zero_head_outputs_decode_the_flat_hand():
    head = Mlp(8 + 6, 8, 6, key=jax.random.key(0), depth=2)
    head = eqx.tree_at(lambda h: h.layers[-1].weight, head, jnp.zeros((8, 6)))
    _, R = M.decode_kinematic_tree(head, jnp.ones((16, 8)))
    np.testing.assert_allclose(R, jnp.broadcast_to(jnp.eye(3), (16, 3, 3)), atol=1e-6)


# ----------------------------------------------------------------------------- left hands


def _project_through_crops(clip, X_rig):
    """Pixels of rig-frame points in each crop (T, 2, n, 2)."""
    T_crop_rig = jnp.linalg.inv(crop_poses(clip.R_cam_crop, clip.T_rig_cams))
    X = jnp.einsum("tvij,nj->tvni", T_crop_rig[..., :3, :3], X_rig) + T_crop_rig[..., None, :3, 3]
    uv = X[..., :2] / X[..., 2:]
    return jnp.einsum("tvij,tvnj->tvni", clip.K[..., :2, :2], uv) + clip.K[..., None, :2, 2]


def test_mirror_clip_geometry_and_involution():
    clip = random_clip(jax.random.key(1))
    mirrored = M.mirror_clip(clip)
    np.testing.assert_allclose(mirrored.T_rig_cams[0], jnp.eye(4), atol=1e-6)
    X = jnp.asarray([[0.02, 0.05, 0.4], [-0.03, 0.08, 0.45]])
    uv = _project_through_crops(clip, X)
    # the mirrored point in the mirrored rig frame (the new left camera = old right, mirrored)
    M4 = jnp.diag(jnp.asarray([-1.0, 1.0, 1.0, 1.0]))
    T_mirrored_newrig = M4 @ clip.T_rig_cams[1] @ M4  # the new rig frame: the mirrored right camera
    X_h = jnp.concatenate([X, jnp.ones((2, 1))], axis=1) @ M4  # mirrored points (M4 is symmetric)
    X_m = (X_h @ jnp.linalg.inv(T_mirrored_newrig).T)[:, :3]
    uv_m = _project_through_crops(mirrored, X_m)
    S = clip.images.shape[-1]
    np.testing.assert_allclose(uv_m[:, ::-1, :, 0], S - 1.0 - uv[..., 0], atol=2e-3)
    np.testing.assert_allclose(uv_m[:, ::-1, :, 1], uv[..., 1], atol=2e-3)
    twice = M.mirror_clip(mirrored)
    for a, b in zip(jax.tree.leaves(twice), jax.tree.leaves(clip)):
        np.testing.assert_allclose(a, b, atol=1e-5)


def test_left_hand_path_is_the_mirrored_right_hand_path(tiny_net, hand_model):
    clip = random_clip(jax.random.key(1))
    batch = jax.tree.map(lambda x: x[None], clip)
    # one batch: the clip as a right hand, its mirror image as a left hand
    mixed = M.predict(tiny_net, jax.tree.map(lambda a, b: jnp.concatenate([a, b]), batch, M.mirror_clip(batch)),
                      hand_model, is_right=np.array([True, False]))  # fmt: skip
    right, left = (jax.tree.map(lambda x, i=i: x[i], mixed) for i in range(2))
    direct = run(tiny_net, clip, hand_model)  # a right hand goes straight through
    np.testing.assert_allclose(right.joints, direct.joints, atol=1e-5)
    # the left prediction on the mirrored clip is the right prediction, mirrored into its frame
    expected = M.unmirror(right, M.mirror_clip(clip).T_rig_cams)
    np.testing.assert_allclose(left.joints, expected.joints, atol=1e-4)
    np.testing.assert_allclose(left.params.transl, expected.params.transl, atol=1e-4)
    np.testing.assert_array_equal(left.emitted, right.emitted)
    assert mixed.emitted.dtype == bool
    np.testing.assert_array_equal(mixed.emitted, mixed.onscreen_prob > 0.5)


# ----------------------------------------------------------------------------- training hooks


def test_gradients_reach_every_trainable_weight_and_no_frozen_one(hand_model):
    cfg = M.config("cpu-tiny", num_frames=FRAMES, freeze_backbone=True)
    net = M.ESTHER(cfg, key=jax.random.key(0))
    clip = random_clip(jax.random.key(1))
    clip = dataclasses.replace(clip, view_present=clip.view_present.at[0, 1].set(False))
    mask = jnp.zeros((FRAMES, 21), bool).at[1, 3].set(True)

    def loss(n):
        out = n(clip, hand_model, motion_mask=mask)
        terms = [out.joints, out.vertices, out.decoded.pose_6d, out.decoded.betas, out.image.heatmap_logits,
                 out.image.keypoints_2d, out.image.visibility_logits, out.image.depth_logits, out.image.triangulated,
                 out.motion.onscreen_logits, out.motion.canonical_joints, out.motion.pose_6d, out.motion.root_velocity]  # fmt: skip
        return sum(jnp.mean(jnp.square(t)) for t in terms)

    grads = eqx.filter_jit(eqx.filter_grad(loss))(net)
    spec = M.trainable(net)
    for (path, g), train in zip(jax.tree_util.tree_leaves_with_path(grads), jax.tree.leaves(spec)):
        if "backbone" in jax.tree_util.keystr(path):
            assert not train and float(jnp.abs(g).max()) == 0.0, jax.tree_util.keystr(path)
        else:
            assert train and float(jnp.abs(g).max()) > 0.0, jax.tree_util.keystr(path)
    # unfrozen (cpu configs train their small backbone), training moves it: tests/test_train.py


def test_jit_and_vmap_agree_with_single_calls(tiny_net, hand_model):
    clips = [random_clip(jax.random.key(k)) for k in (1, 2)]
    batch = jax.tree.map(lambda *x: jnp.stack(x), *clips)
    batched = eqx.filter_jit(jax.vmap(lambda c: tiny_net(c, hand_model)))(batch)
    for i, clip in enumerate(clips):
        single = run(tiny_net, clip, hand_model)
        for a, b in zip(jax.tree.leaves(single), jax.tree.leaves(batched)):
            np.testing.assert_allclose(a, b[i], rtol=2e-4, atol=2e-5)


def test_precomputed_features_equal_images(hand_model):
    cfg = TINY.replace(freeze_backbone=True)
    net = M.ESTHER(cfg, key=jax.random.key(0))
    clip = random_clip(jax.random.key(1))
    features = M.extract_features(net.backbone, clip.images)
    from_features = dataclasses.replace(clip, images=None, features=features)
    a, b = run(net, clip, hand_model), run(net, from_features, hand_model)
    np.testing.assert_allclose(a.joints, b.joints, atol=1e-5)
    headless = eqx.tree_at(lambda n: n.backbone, net, None, is_leaf=lambda x: x is None)
    np.testing.assert_allclose(run(headless, from_features, hand_model).joints, a.joints, atol=1e-5)


def test_clear_errors(tiny_net, hand_model):
    clip = random_clip(jax.random.key(1))
    with pytest.raises(ValueError, match="images must be"):
        tiny_net(dataclasses.replace(clip, images=clip.images[..., :32, :32]), hand_model)
    with pytest.raises(ValueError, match="at most"):
        tiny_net(random_clip(jax.random.key(1), frames=FRAMES + 2), hand_model)
    with pytest.raises(ValueError, match="vmap over clips"):
        tiny_net(jax.tree.map(lambda x: x[None], clip), hand_model)
    with pytest.raises(ValueError, match="batch of clips"):
        M.predict(tiny_net, clip, hand_model)
    with pytest.raises(ValueError, match="neither images nor features"):
        tiny_net(dataclasses.replace(clip, images=None), hand_model)


def test_save_and_load_round_trip(tmp_path, tiny_net, hand_model):
    folder = M.save(tmp_path / "model", tiny_net)
    loaded = M.load(folder)
    assert loaded.config == tiny_net.config
    for a, b in zip(jax.tree.leaves(tiny_net), jax.tree.leaves(loaded)):
        np.testing.assert_array_equal(a, b)
    M.save(folder, tiny_net)  # overwrite in place
    weights = folder / "weights.eqx"
    raw = bytearray(weights.read_bytes())
    raw[len(raw) // 2] ^= 0xFF  # one flipped byte inside a weight
    weights.write_bytes(bytes(raw))
    with pytest.raises(ValueError, match="damaged or was replaced"):
        M.load(folder)
    weights.write_bytes(b"not weights")
    with pytest.raises(ValueError, match="damaged or was replaced"):
        M.load(folder)
    config = json.loads((folder / "config.json").read_text())
    config.pop("weights_sha256")
    (folder / "config.json").write_text(json.dumps(config))
    with pytest.raises(ValueError, match="records no weights_sha256"):
        M.load(folder)
    M.save(folder, tiny_net)
    config = json.loads((folder / "config.json").read_text())
    config.pop("architecture_revision")  # a folder saved before revisions were recorded
    (folder / "config.json").write_text(json.dumps(config))
    with pytest.raises(ValueError, match="architecture revision 1;.*retrain"):
        M.load(folder)
    with pytest.raises(FileNotFoundError, match="not a saved ESTHER model"):
        M.load(tmp_path)


# ----------------------------------------------------------------------------- backbones and real crops


def test_dinov3_weights_round_trip_and_mismatch(tmp_path):
    spec = M.BACKBONES["vit-tiny"]
    vit = M.make_backbone(spec, key=jax.random.key(0))
    state = M.dinov3_state_dict(vit)
    assert state["patch_embed.proj.weight"].shape == (spec.width, 3, 16, 16)
    assert state["blocks.0.attn.qkv.weight"].shape == (3 * spec.width, spec.width)
    state["mask_token"] = np.zeros((1, spec.width), np.float32)  # in real checkpoints, unused here
    np.savez(tmp_path / "w.npz", **state)
    loaded = M.load_dinov3_weights(M.make_backbone(spec, key=jax.random.key(5)), tmp_path / "w.npz")
    images = jax.random.uniform(jax.random.key(1), (2, 3, 64, 64))
    np.testing.assert_array_equal(loaded(images), vit(images))
    del state["norm.bias"]
    np.savez(tmp_path / "bad.npz", **state)
    with pytest.raises(ValueError, match="missing"):
        M.load_dinov3_weights(vit, tmp_path / "bad.npz")
    with pytest.raises(FileNotFoundError, match="local files"):
        M.load_dinov3_weights(vit, tmp_path / "none.pth")


def test_synthetic_crops_triangulate_through_the_crop_cameras(hand_model):
    clip = make_clip(0, 1, SynthConfig(num_frames=FRAMES, crops=True, crop_size=64))
    side = next(iter(clip.crops))
    inputs = M.clip_input_from_crops(clip.crops[side], np.asarray(clip.rig.T_rig_cams))
    assert inputs.images.shape == (FRAMES, 2, 3, 64, 64)
    joints = jnp.asarray(clip.gt[side]["joints"], inputs.K.dtype)
    T_rig_crop = crop_poses(inputs.R_cam_crop, inputs.T_rig_cams)
    uv = _project_through_crops(inputs, joints[0])[0]  # frame 0: (2, 21, 2)
    cams = jax.vmap(lambda k: PinholeCamera.from_K(k, 64, 64))(inputs.K[0])
    for j in range(21):
        tri = triangulate(cams, T_rig_crop[0], uv[:, j], jnp.ones(2))
        np.testing.assert_allclose(tri.point, joints[0, j], atol=1e-4)
    net = M.ESTHER(TINY, key=jax.random.key(0))
    assert_finite_output(run(net, inputs, hand_model), FRAMES)
