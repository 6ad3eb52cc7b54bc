"""Training (appendices B and C): every loss term against a value computed by hand on a
tiny example, masks and switches, masking and augmentation rates and determinism, and
the terms on the real `cpu-tiny` network (finite, with gradients; no dead switch)."""

import dataclasses
import json
import math
import shutil

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest

from esther_jax import clips, mano, metrics
from esther_jax.files import exclusive_lock
from esther_jax import model as M
from esther_jax import train
from esther_jax.cameras import rig_preset
from esther_jax.model.esther import ESTHEROutput
from esther_jax.model.fusion_decoder import Decoded
from esther_jax.model.motion_encoder import MotionEvidence
from esther_jax.model.stereo_encoder import ImageEvidence
from esther_jax.rotations import axis_angle_to_matrix, matrix_to_rotation_6d

from .helpers import aimed_crop_cameras

T, S = 4, 64
CFG = M.config("cpu-tiny", num_frames=T)


@pytest.fixture(scope="module")
def hand():
    return mano.load_builtin("right")


def _clip(images=True, frames=T) -> M.ClipInput:
    """Crop cameras of both views aimed at a hand 0.4 m ahead (as the model tests do)."""
    rig = rig_preset("esther")
    K, R = aimed_crop_cameras(rig, S, 0.6 * S)  # wide: the whole hand inside both crops
    return M.ClipInput(
        images=jax.random.uniform(jax.random.key(0), (frames, 2, 3, S, S)) if images else None,
        features=None,
        K=jnp.broadcast_to(K, (frames, 2, 3, 3)),
        R_cam_crop=jnp.broadcast_to(R, (frames, 2, 3, 3)),
        T_rig_cams=rig.T_rig_cams,
        flow=jnp.zeros((frames, 192)),
        view_present=jnp.ones((frames, 2), bool),
    )


def _targets(hand) -> train.Targets:
    rng = np.random.default_rng(0)
    orient = jnp.asarray(rng.normal(scale=0.3, size=(T, 3)), jnp.float32)
    pose = jnp.asarray(rng.normal(scale=0.2, size=(T, 15, 3)), jnp.float32)
    betas = jnp.asarray(rng.normal(scale=0.5, size=10), jnp.float32)
    transl = jnp.asarray([[0.0, 0.05, 0.4]]) + jnp.asarray(rng.normal(scale=0.01, size=(T, 3)), jnp.float32)
    joints = jax.vmap(lambda o, p, t: mano.forward_joints(hand, mano.ManoParams(o, p, betas, t)))(orient, pose, transl)
    return train.Targets(orient, pose, betas, transl, joints, jnp.ones(T, bool))


def _perfect_output(hand, clip, targets) -> ESTHEROutput:
    """An output equal to the targets, with neutral logits (hand-computable losses)."""
    G, B = CFG.grid, CFG.depth_bins
    uv, _, _ = M.crop_projections(clip, targets.joints, S)
    local = axis_angle_to_matrix(jnp.concatenate([targets.global_orient[:, None], targets.hand_pose], axis=1))
    params = jax.vmap(lambda o, p, t: mano.ManoParams(o, p, targets.betas, t))(targets.global_orient, targets.hand_pose, targets.transl)
    vertices = jax.vmap(lambda R, t: mano.forward_rotations(hand, R, targets.betas, t).vertices)(local, targets.transl)
    canonical = targets.joints - targets.joints[:, :1]
    return ESTHEROutput(
        image=ImageEvidence(
            features=jnp.zeros((T, 21, 8)), heatmap_logits=jnp.zeros((T, 2, 21, G, G)), keypoints_2d=uv,
            visibility_logits=jnp.zeros((T, 2, 21)), depth_logits=jnp.zeros((T, 2, 21, B)), triangulated=targets.joints,
            triangulation_valid=jnp.ones((T, 21), bool), triangulation_spread=jnp.zeros((T, 21)),
        ),
        motion=MotionEvidence(
            features=jnp.zeros((T, 21, 8)), root=jnp.zeros((T, 8)), onscreen_logits=jnp.zeros(T),
            canonical_joints=canonical, pose_6d=matrix_to_rotation_6d(local),
            root_velocity=jnp.concatenate([targets.transl[1:] - targets.transl[:-1], jnp.zeros((1, 3))]),
        ),
        decoded=Decoded(pose_6d=matrix_to_rotation_6d(local), rotations=local, betas=targets.betas, transl=targets.transl,
                        gates=jnp.full((1, T, 18, 3), 1 / 3)),
        params=params, joints=targets.joints, vertices=vertices,
    )  # fmt: skip


def _means(out, clip, targets, hand, mask=None, cfg=CFG):
    mask = jnp.zeros((T, 21), bool) if mask is None else mask
    terms = train.clip_loss_terms(out, clip, targets, mask, hand, cfg, crop_size=S)
    return train.combine(terms, cfg, "joint")


def test_each_loss_term_equals_its_hand_computed_value(hand):
    clip, targets = _clip(), _targets(hand)
    perfect = _perfect_output(hand, clip, targets)
    _, means = _means(perfect, clip, targets, hand)
    uv, depth, inside = M.crop_projections(clip, targets.joints, S)
    assert bool(jnp.all(inside)), "the test hand must project into both crops"
    for name in ("two_d", "triangulation", "joints", "canonical", "vertices", "six_d", "betas", "transl"):
        assert float(means[name]) == pytest.approx(0.0, abs=2e-6), name
    assert float(means["rotation"]) == pytest.approx(0.0, abs=2e-3)  # arccos near 1 in float32
    assert float(means["visibility"]) == pytest.approx(math.log(2.0), rel=1e-5)  # logit 0, every joint visible
    assert float(means["onscreen"]) == pytest.approx(math.log(2.0), rel=1e-5)
    assert float(means["depth"]) == pytest.approx(math.log(CFG.depth_bins), rel=1e-5)  # uniform over the bins
    # heatmap: uniform logits against the Gaussian targets: CE = log(G^2)
    assert float(means["heatmap"]) == pytest.approx(math.log(CFG.grid**2), rel=1e-5)
    assert float(means["motion"]) == 0.0  # nothing masked: no motion term
    # priors from the core's PosePrior, by hand
    prior = mano.PosePrior.from_model(hand)
    z = np.stack([np.asarray(prior.whitening) @ (np.asarray(p).reshape(45) - np.asarray(prior.mean)) for p in targets.hand_pose])
    assert float(means["pose_prior"]) == pytest.approx(float(np.mean(z**2)), rel=1e-4)
    assert float(means["shape_prior"]) == pytest.approx(float(np.mean(np.asarray(targets.betas) ** 2)), rel=1e-6)
    # the 2D term's norm is the core's safe norm: a finite, zero gradient at a zero error
    with_keypoints = lambda k: dataclasses.replace(perfect, image=dataclasses.replace(perfect.image, keypoints_2d=k))  # noqa: E731
    grad = jax.grad(lambda k: _means(with_keypoints(k), clip, targets, hand)[1]["two_d"])(perfect.image.keypoints_2d)
    assert bool(jnp.all(jnp.isfinite(grad))) and float(jnp.abs(grad).max()) < 1e-6

    # now each term moved by a known amount
    shift = jnp.asarray([0.01, -0.02, 0.0])
    off = dataclasses.replace(
        perfect,
        joints=perfect.joints + shift[None, None],  # joints: |0.01| + |-0.02| = 0.03 per joint; canonical unchanged
        image=dataclasses.replace(perfect.image, keypoints_2d=perfect.image.keypoints_2d + jnp.asarray([[[[3.0, 4.0]]]]),
                                  triangulated=perfect.image.triangulated + jnp.asarray([[[0.0, 0.0, 0.002]]])),
        decoded=dataclasses.replace(perfect.decoded, betas=perfect.decoded.betas + 0.1),
        params=dataclasses.replace(perfect.params, transl=perfect.params.transl + jnp.asarray([[0.005, 0.0, 0.0]])),
    )  # fmt: skip
    _, means = _means(off, clip, targets, hand)
    assert float(means["joints"]) == pytest.approx(0.03, rel=1e-4)
    assert float(means["canonical"]) == pytest.approx(0.0, abs=1e-6)
    norm, delta = 5.0 / S, train.LossWeights().huber_delta  # a 3-4-5 pixel error, beyond delta
    assert float(means["two_d"]) == pytest.approx(delta * (norm - delta / 2), rel=1e-4)
    assert float(means["triangulation"]) == pytest.approx(0.002, rel=1e-3)
    assert float(means["betas"]) == pytest.approx(1.0, rel=1e-5)  # ten coefficients, 0.1 each
    assert float(means["transl"]) == pytest.approx(0.005, rel=1e-4)


def test_masks_decide_which_entries_count(hand):
    clip, targets = _clip(), _targets(hand)
    perfect = _perfect_output(hand, clip, targets)
    off = dataclasses.replace(perfect, image=dataclasses.replace(perfect.image, keypoints_2d=perfect.image.keypoints_2d + 1.0))
    # a blanked view contributes no 2D / heatmap / visibility entries; triangulation needs both views
    blanked = dataclasses.replace(clip, view_present=clip.view_present.at[0, 1].set(False))
    terms = train.clip_loss_terms(off, blanked, targets, jnp.zeros((T, 21), bool), hand, CFG, crop_size=S)
    assert float(terms["two_d"].count) == T * 2 * 21 - 21
    assert float(terms["heatmap"].count) == T * 2 * 21 - 21 and float(terms["visibility"].count) == T * 2 * 21 - 21
    assert float(terms["triangulation"].count) == (T - 1) * 21
    # a frame without a target: no 3D terms there; it is an on-screen negative
    no_target = dataclasses.replace(targets, valid=targets.valid.at[2].set(False))
    terms = train.clip_loss_terms(perfect, clip, no_target, jnp.zeros((T, 21), bool), hand, CFG, crop_size=S)
    assert float(terms["joints"].count) == (T - 1) * 21 and float(terms["transl"].count) == T - 1
    assert train.onscreen_label(no_target, jnp.ones((T, 2, 21), bool)).tolist() == [True, True, False, True]
    # the motion term: only at masked positions, L1 of canonical joints per masked joint
    mask = jnp.zeros((T, 21), bool).at[1, 3].set(True)
    moved = dataclasses.replace(perfect, motion=dataclasses.replace(
        perfect.motion, canonical_joints=perfect.motion.canonical_joints.at[1, 3].add(jnp.asarray([0.0, 0.01, 0.0])),
        root_velocity=perfect.motion.root_velocity.at[2].add(1.0)))  # fmt: skip  (frame 2 is not masked: ignored)
    _, means = _means(moved, clip, targets, hand, mask)
    assert float(means["motion"]) == pytest.approx(0.01, rel=1e-4)
    # its pose part: per masked frame, the 6D L1 of each rotation averaged over the 16
    turned = dataclasses.replace(moved, motion=dataclasses.replace(moved.motion, pose_6d=moved.motion.pose_6d.at[1, 5, 2].add(0.32)))
    _, means = _means(turned, clip, targets, hand, mask)
    assert float(means["motion"]) == pytest.approx(0.01 + 0.32 / 16, rel=1e-4)


def test_terms_are_masked_means_independent_of_the_batch(hand):
    clip, targets = _clip(), _targets(hand)
    out = _perfect_output(hand, clip, targets)
    out = dataclasses.replace(out, joints=out.joints + 0.01)
    one = train.clip_loss_terms(out, clip, targets, jnp.zeros((T, 21), bool), hand, CFG, crop_size=S)
    batch = jax.tree.map(lambda x: jnp.stack([x, x, x]), one)  # three copies: same means
    for stage in train.STAGES:
        a, _ = train.combine(one, CFG, stage)
        b, _ = train.combine(batch, CFG, stage)
        assert float(a) == pytest.approx(float(b), rel=1e-6)
    assert float(train.combine(one, CFG, "joint")[0]) > float(train.combine(one, CFG, "image")[0])
    # the table-5 switches take their terms out
    loss, _ = train.combine(one, CFG, "image")
    no_2d, means = train.combine(one, CFG.replace(guidance_2d=False), "image")
    w = train.LossWeights()
    assert float(loss - no_2d) == pytest.approx(float(w.two_d * means["two_d"] + w.heatmap * means["heatmap"]), rel=1e-5)
    assert set(means) == set(train.STAGE_TERMS["image"])  # stage 1 logs (and computes) its own terms only
    no_tri, _ = train.combine(one, CFG.replace(guidance_triangulation=False), "image")
    assert float(loss - no_tri) == pytest.approx(float(w.triangulation * means["triangulation"]), rel=1e-5)
    with pytest.raises(ValueError, match="stage"):
        train.combine(one, CFG, "both")


# ----------------------------------------------------------------------------- masking and augmentation


def _binomial_ok(hits: float, n: int, p: float) -> bool:
    return abs(hits - n * p) <= 4.0 * math.sqrt(n * p * (1 - p)) + 1


def test_token_masking_rates_and_anchor_frames():
    frames, draws = 16, 3000
    rates = train.MaskingRates()
    keys = jax.random.split(jax.random.key(1), draws)
    masks = np.asarray(jax.jit(jax.vmap(lambda k: train.motion_mask(k, frames, rates)))(keys))
    anchors = np.asarray(train.anchor_frames(frames))
    assert anchors.tolist() == [t % 4 == 0 for t in range(frames)]
    assert not masks[:, anchors].any()  # anchor frames are never masked
    free = ~anchors
    whole = masks.all(axis=2)  # (draws, T) whole frames masked (frame or span)
    # P(whole frame) at frame t: 1 - (1 - 0.1)(1 - 0.1 * starts covering t / starts)
    starts = frames - rates.span_length + 1
    for t in np.flatnonzero(free):
        covering = sum(1 for s in range(starts) if s <= t < s + rates.span_length)
        p = 1 - (1 - rates.frame) * (1 - rates.span * covering / starts)
        assert _binomial_ok(whole[:, t].sum(), draws, p + (1 - p) * rates.joint**21), t
    partial = masks[:, free][~whole[:, free]]  # joints of frames not wholly masked: per-joint rate
    assert _binomial_ok(partial.sum(), partial.size, rates.joint)
    views = np.asarray(jax.vmap(lambda k: train.dropped_views(k, rates))(keys))
    assert _binomial_ok(views.sum(), views.size, rates.view)


def test_augmentation_rates_and_determinism():
    draws, frames = 400, 4
    rates = train.AugmentRates()
    images = jnp.full((frames, 2, 3, 16, 16), 0.5)
    keys = jax.vmap(lambda i: train.example_key(7, 3, i))(jnp.arange(draws))
    out, present = jax.jit(jax.vmap(lambda k: train.augment_images(k, images, rates)))(keys)
    out, present = np.asarray(out), np.asarray(present)
    absent = ~present
    p_view = 1 - (1 - rates.view_blank) * (1 - rates.frame_blank)
    assert _binomial_ok(absent.sum(), absent.size, p_view)
    p_frame = rates.frame_blank + (1 - rates.frame_blank) * rates.view_blank**2
    assert _binomial_ok(absent.all(axis=2).sum(), draws * frames, p_frame)
    assert np.all(out[absent] == 0.0) and out.min() >= 0.0 and out.max() <= 1.0
    # erasing: fills whole rectangles with noise in about half the present views
    kept = out[present]  # (n, 3, 16, 16)
    deviation = np.abs(kept - 0.5).max(axis=1)
    erased = (deviation > 0.35).reshape(len(kept), -1).mean(axis=1) > 0.005  # noise sigma <= 0.08 rarely exceeds 0.35
    assert abs(erased.mean() - rates.erase) < 0.08
    # reproducible per (seed, step, example); another step or example differs
    again = train.augment_images(train.example_key(7, 3, 5), images, rates)
    np.testing.assert_allclose(np.asarray(again[0]), out[5], atol=1e-6)  # one example alone, unbatched and eager
    np.testing.assert_array_equal(np.asarray(again[1]), present[5])
    np.testing.assert_array_equal(np.asarray(train.augment_images(train.example_key(7, 3, 5), images, rates)[0]), np.asarray(again[0]))
    other = train.augment_images(train.example_key(7, 4, 5), images, rates)
    assert not np.array_equal(np.asarray(other[0]), out[5])


def test_corruption_follows_the_switches():
    clip = _clip(frames=16)  # 16 frames: anchors 0, 4, 8, 12 (with 4 frames every frame is an anchor)
    key = train.example_key(0, 0, 0)
    same, mask = train.corrupt(key, clip, CFG.replace(motion_masking=False, image_augmentation=False))
    assert not bool(mask.any())
    for a, b in zip(jax.tree.leaves(same), jax.tree.leaves(clip)):
        np.testing.assert_array_equal(np.asarray(a), np.asarray(b))
    found_blank, masked = False, 0
    for step in range(20):
        changed, mask = train.corrupt(train.example_key(0, step, 0), clip, CFG)
        masked += int(mask.sum())
        assert not bool(mask[train.anchor_frames(16)].any())
        absent = ~np.asarray(changed.view_present)
        assert np.all(np.asarray(changed.images)[absent] == 0.0)  # an absent view is never fed as a real view
        found_blank |= bool(absent.any())
    assert found_blank and masked > 0
    assert not bool(train.motion_mask(key, 4).any())  # 4 frames: all anchors
    features = dataclasses.replace(clip, images=None, features=jnp.ones((16, 2, CFG.grid**2, 8)))
    blanked, _ = train.corrupt(key, features, CFG)
    assert blanked.images is None and blanked.view_present.shape == (16, 2)


# ----------------------------------------------------------------------------- data


def test_mirrored_targets_are_what_unmirror_inverts(hand):
    """Mirroring a left hand's targets into its mirrored clip, then `unmirror`ing them as
    a prediction, gives the targets back (joints and, through the left model, params)."""
    left = mano.load_builtin("left")
    clip, t = _clip(), _targets(hand)
    joints = jax.vmap(lambda o, p, x: mano.forward_joints(left, mano.ManoParams(o, p, t.betas, x)))(t.global_orient, t.hand_pose, t.transl)
    targets = dataclasses.replace(t, joints=joints)
    mirrored = train.mirror_targets(targets, clip.T_rig_cams)
    # the mirrored targets are a right hand: the right model reproduces their joints
    right_joints = jax.vmap(lambda o, p, x: mano.forward_joints(hand, mano.ManoParams(o, p, t.betas, x)))(
        mirrored.global_orient, mirrored.hand_pose, mirrored.transl)  # fmt: skip
    np.testing.assert_allclose(right_joints, mirrored.joints, atol=1e-5)
    params = jax.vmap(lambda o, p, x: mano.ManoParams(o, p, t.betas, x))(mirrored.global_orient, mirrored.hand_pose, mirrored.transl)
    prediction = M.HandPrediction(params=params, joints=mirrored.joints, vertices=jnp.zeros((T, 1, 3)),
                                  onscreen_prob=jnp.ones(T), emitted=jnp.ones(T, bool))  # fmt: skip
    back = M.unmirror(prediction, clip.T_rig_cams)
    np.testing.assert_allclose(back.joints, joints, atol=1e-5)
    np.testing.assert_allclose(back.params.transl, t.transl, atol=1e-5)
    np.testing.assert_allclose(axis_angle_to_matrix(back.params.global_orient), axis_angle_to_matrix(t.global_orient), atol=1e-5)


def test_batches_are_a_pure_function_of_seed_and_step():
    a = [train.batch_indices(10, 4, seed=3, step=s) for s in range(6)]
    b = [train.batch_indices(10, 4, seed=3, step=s) for s in range(6)]
    assert all(np.array_equal(x, y) for x, y in zip(a, b))
    assert len(set(np.concatenate(a[:2]).tolist())) == 8  # one epoch (2 steps of 4): no window twice
    assert not np.array_equal(np.concatenate(a[:2]), np.concatenate(a[2:4]))  # a new permutation per epoch
    assert train.batch_indices(3, 8, seed=0, step=0).shape == (8,)  # fewer windows than a batch: repeated
    with pytest.raises(ValueError, match="empty"):
        train.batch_indices(0, 4, 0, 0)


@pytest.fixture(scope="module")
def synth_clip(tmp_path_factory):
    from esther_jax.data import motion, synth

    cfg = synth.SynthConfig(num_frames=8, crops=True, crop_size=64, motion_config=motion.MotionConfig(two_hands_probability=1.0))
    return synth.write_clip(synth.make_clip(0, 0, cfg), tmp_path_factory.mktemp("synth") / "clip_00000")


def test_windows_load_as_network_inputs_with_consistent_targets(synth_clip, tmp_path):
    cfg = train.DataConfig(frames=4, stride=2, crop_size=S)
    windows = train.build_index([synth_clip], cfg)
    assert [(w.side, w.start) for w in windows] == [(s, i) for s in ("right", "left") for i in (0, 2, 4)]
    loaded, loaded_cfg = train.load_index(train.save_index(tmp_path / "index.json", windows, cfg))
    assert loaded == windows and loaded_cfg == cfg
    for window in windows:
        clip, targets = train.load_example(window, cfg)
        assert clip.images.shape == (4, 2, 3, S, S) and targets.joints.shape == (4, 21, 3)
        absent = ~np.asarray(clip.view_present)
        assert np.all(np.asarray(clip.images)[absent] == 0.0)  # an absent view is never a real view
        # the targets project where the crops show the hand, also for mirrored left hands
        uv, _, inside = M.crop_projections(clip, targets.joints, S)
        seen = np.asarray(inside) & np.asarray(clip.view_present)[..., None] & np.asarray(targets.valid)[:, None, None]
        assert seen.mean() > 0.3, window
        shown = np.asarray(clip.images)[~absent]
        assert shown.size == 0 or shown.std() > 0.01  # present views carry the rendered crops
    batch = train.load_batch(windows, cfg, batch=4, seed=0, step=1)
    assert batch[0].images.shape == (4, 4, 2, 3, S, S) and batch[1].valid.shape == (4, 4)
    with pytest.raises(ValueError, match="labels folder"):
        train.DataConfig(targets="labels")


def test_frames_apart_examples_mix_frames_of_one_hand_and_rig(synth_clip, tmp_path):
    """Stage 1's frames-apart batches: every frame is a frame of the example's hand (as a
    consecutive window loads it), the draw is a pure function of (seed, step, position),
    a process's share loads the same examples, and stage 2 refuses it."""
    cfg = train.DataConfig(frames=4, stride=2, crop_size=S)
    windows = train.build_index([synth_clip], cfg)
    pools = train.frame_pools(tuple(windows), cfg.frames)
    assert sorted(side for side, _ in pools) == ["left", "right"]
    assert all(pool == [(str(synth_clip), t) for t in range(8)] for pool in pools.values())  # windows 0, 2, 4 cover frames 0-7
    twin = shutil.copytree(synth_clip, tmp_path / "clip_renamed_rig")  # the same rig under another name (HOT3D names rigs per clip)
    record = json.loads((twin / "rig.json").read_text())
    (twin / "rig.json").write_text(json.dumps({**record, "name": "another"}))
    shared = train.frame_pools(tuple(train.build_index([synth_clip, twin], cfg)), cfg.frames)
    assert len(shared) == 2 and all(len({clip for clip, _ in pool}) == 2 for pool in shared.values())
    whole = {side: train.load_example(train.Window(str(synth_clip), side, 0), cfg, frames=8) for side in ("left", "right")}
    batch = train.load_batch(windows, cfg, batch=4, seed=0, step=1, frames_apart=True)
    assert batch[0].images.shape == (4, 4, 2, 3, S, S) and batch[1].joints.shape == (4, 4, 21, 3)
    sides = [windows[i].side for i in train.batch_indices(len(windows), 4, 0, 1)]
    drawn = []
    for b, side in enumerate(sides):
        clip, targets = whole[side]
        for k in range(cfg.frames):
            t = int(np.argmin(np.abs(np.asarray(targets.joints) - np.asarray(batch[1].joints[b, k])).sum(axis=(1, 2))))
            np.testing.assert_array_equal(np.asarray(batch[0].images[b, k]), np.asarray(clip.images[t]))
            np.testing.assert_allclose(np.asarray(batch[1].joints[b, k]), np.asarray(targets.joints[t]), atol=1e-6)
            assert batch[0].view_present[b, k].tolist() == clip.view_present[t].tolist()
            drawn.append(t)
        np.testing.assert_array_equal(np.asarray(batch[0].T_rig_cams[b]), np.asarray(clip.T_rig_cams))
    assert len(set(drawn)) > 4  # frames from across the clip, not one window's
    again = train.load_batch(windows, cfg, batch=4, seed=0, step=1, frames_apart=True)
    halves = [train.load_batch(windows, cfg, batch=4, seed=0, step=1, part=part, frames_apart=True) for part in (slice(0, 2), slice(2, 4))]
    joined = jax.tree.map(lambda x, y: jnp.concatenate([x, y]), *halves)
    for x, y, z in zip(jax.tree.leaves(batch), jax.tree.leaves(again), jax.tree.leaves(joined)):
        np.testing.assert_array_equal(np.asarray(x), np.asarray(y))
        np.testing.assert_array_equal(np.asarray(x), np.asarray(z))
    other = train.load_batch(windows, cfg, batch=4, seed=1, step=1, frames_apart=True)
    assert not np.array_equal(np.asarray(other[1].joints), np.asarray(batch[1].joints))
    with pytest.raises(ValueError, match="frames_apart is for stage 'image'"):
        train.TrainConfig(stage="joint", frames_apart=True)


# ----------------------------------------------------------------------------- runs


def test_optimiser_masks_and_stages():
    net = M.ESTHER(CFG, key=jax.random.key(0))
    image_only = train.stage_spec(net, "image")
    assert not any(jax.tree.leaves(image_only.motion_encoder)) and not any(jax.tree.leaves(image_only.fusion_decoder))
    assert any(jax.tree.leaves(image_only.image_encoder))
    params, _ = eqx.partition(net, train.stage_spec(net, "joint"))
    mask = train.decay_mask(params)
    paths = {jax.tree_util.keystr(p): m for p, m in jax.tree_util.tree_leaves_with_path(mask)}
    assert any(m for k, m in paths.items() if k.endswith(".weight"))
    assert not any(m for k, m in paths.items() if "token" in k or k.endswith(".bias") or "norm" in k)
    frozen = M.ESTHER(CFG.replace(freeze_backbone=True), key=jax.random.key(0))
    state = train.Trainer(frozen, train.TrainConfig(steps=2), mano.load_builtin("right")).init()
    assert state.params.backbone is None or not any(x is not None for x in jax.tree.leaves(state.params.backbone))
    with pytest.raises(ValueError, match="stage"):
        train.TrainConfig(stage="both")


RUN_FRAMES = 8  # anchors every 2 frames: the other frames can be token-masked
RUN_BATCH = 4  # splits over the four devices of the data-parallel test, which shares the run tests' compiled step


def test_hooks_run_every_n_steps_in_order_and_all_when_forced(tmp_path):
    """Hooks: each hook every `every` steps, in the order added, all of them at a forced
    step; the non-finite guard names the step (0-based, as the batch's) and the terms."""
    state = train.TrainState(jnp.zeros((), jnp.int32), M.ESTHER(CFG, key=jax.random.key(0)), (), None)
    seen = []
    hooks = train.Hooks()
    hooks.add(lambda info: seen.append(("a", info.step)))
    hooks.add(lambda info: seen.append(("b", info.step)), every=2)
    with pytest.raises(ValueError, match="every=0"):
        hooks.add(print, every=0)
    for step in (1, 2, 3):
        hooks.run(train.StepInfo(step, state, {"loss": 1.0}, 0.1), force=step == 3)
    assert seen == [("a", 1), ("a", 2), ("b", 2), ("a", 3), ("b", 3)]
    guard = train.nonfinite_guard(tmp_path)
    guard(train.StepInfo(1, state, {"loss": 1.0, "loss/joints": 1.0}, 0.1))
    with pytest.raises(train.NonFiniteLoss, match=r"step 4: the loss is inf \(non-finite terms: joints\)"):
        guard(train.StepInfo(5, state, {"loss": math.inf, "loss/joints": math.inf, "loss/two_d": 1.0}, 0.1))


def test_a_run_trains_stops_on_nan_and_resumes_bit_for_bit(synth_clip, tmp_path, monkeypatch):
    """Run A trains 4 steps: every term finite, the motion term active, every part of the
    network moved. Run B meets a NaN target at step 3: it stops, names the step and the
    terms, and keeps its step-2 checkpoint; resumed, it ends with run A's losses and weights."""
    from esther_jax.train import data as data_lib

    model_cfg = M.config("cpu-tiny", num_frames=RUN_FRAMES)
    cfg = train.TrainConfig(steps=4, batch=RUN_BATCH, warmup_steps=2, checkpoint_every=2, keep_checkpoints=1)
    data_cfg = train.DataConfig(frames=RUN_FRAMES, stride=2, crop_size=model_cfg.crop_size)
    a = train.train(tmp_path / "a", [synth_clip], model_cfg, cfg, data_cfg=data_cfg, progress=False)
    assert a["steps"] == 4 and (tmp_path / "a" / "model" / "weights.eqx").is_file()
    start, trained = M.ESTHER(model_cfg, key=jax.random.key(cfg.seed)), M.load(tmp_path / "a" / "model")
    for part in ("backbone", "image_encoder", "motion_encoder", "fusion_decoder"):
        moved = [float(jnp.abs(x - y).max()) for x, y in zip(jax.tree.leaves(getattr(start, part)), jax.tree.leaves(getattr(trained, part)))]
        assert max(moved) > 0, part

    clean = data_lib.load_batch

    def poisoned(windows, dcfg, batch, seed, step, **options):
        clips_b, targets_b = clean(windows, dcfg, batch, seed, step, **options)
        if step == 2:
            targets_b = dataclasses.replace(targets_b, joints=targets_b.joints.at[0, 1, 5].set(jnp.nan))
        return clips_b, targets_b

    monkeypatch.setattr(data_lib, "load_batch", poisoned)
    with pytest.raises(train.NonFiniteLoss, match=r"step 2: the loss is nan \(non-finite terms: .*joints"):
        train.train(tmp_path / "b", [synth_clip], model_cfg, cfg, data_cfg=data_cfg, progress=False)
    assert (tmp_path / "b" / "checkpoints" / "latest").read_text() == "step_00000002"
    monkeypatch.setattr(data_lib, "load_batch", clean)
    with pytest.raises(ValueError, match="already holds a run"):
        train.train(tmp_path / "b", [synth_clip], model_cfg, cfg, data_cfg=data_cfg, progress=False)
    record = json.loads((tmp_path / "b" / "config.json").read_text())
    del record["train"]["frames_apart"]  # a run recorded before the setting existed had its default
    (tmp_path / "b" / "config.json").write_text(json.dumps(record))
    b = train.train(tmp_path / "b", [synth_clip], model_cfg, cfg, data_cfg=data_cfg, progress=False, resume=True)
    assert b["resumed_from"] == 2 and b["steps"] == 4

    def log(run):
        return [json.loads(line) for line in (tmp_path / run / "metrics.jsonl").read_text().splitlines()]

    la, lb = log("a"), log("b")
    assert [e["step"] for e in lb] == [1, 2, 3, 4]  # no duplicate after the resume
    for ea, eb in zip(la, lb):
        assert ea["loss"] == eb["loss"] and ea["grad_norm"] == eb["grad_norm"], (ea["step"], ea["loss"], eb["loss"])
    net_a, net_b = M.load(tmp_path / "a" / "model"), M.load(tmp_path / "b" / "model")
    for x, y in zip(jax.tree.leaves(net_a), jax.tree.leaves(net_b)):
        np.testing.assert_array_equal(np.asarray(x), np.asarray(y))
    assert sorted(p.name for p in (tmp_path / "b" / "checkpoints").iterdir()) == ["latest", "step_00000004"]
    record = json.loads((tmp_path / "a" / "config.json").read_text())
    assert record["train"]["steps"] == 4 and record["model"]["name"] == model_cfg.name and "git_revision" in record
    assert set(la[0]) >= {"loss", "grad_norm", "learning_rate", "clips_per_s", "loss/joints", "loss/two_d"}
    assert {f"loss/{t}" for t in train.STAGE_TERMS["joint"]} <= set(la[0])
    assert all(np.isfinite(v) for e in la for v in e.values()) and all(e["grad_norm"] > 0 for e in la)
    parts = ("backbone", "image_encoder", "motion_encoder", "fusion_decoder")
    assert all(e[f"grad_norm/{part}"] > 0 for e in la for part in parts)  # the gradient reaches every module
    assert any(e["loss/motion"] > 0 for e in la)


def test_train_predict_evaluate_from_the_command_line(synth_clip, tmp_path, capsys):
    """esther train -> esther predict -> esther evaluate, on a synthetic clip folder."""
    from esther_jax import cli

    clips_root = str(synth_clip.parent)
    run = tmp_path / "run"
    # the settings of the run test above: the compiled step is shared
    args = ["train", "--config", "cpu-tiny", "--frames", str(RUN_FRAMES), "--data", clips_root, "--out", str(run),
            "--steps", "4", "--batch", str(RUN_BATCH), "--warmup", "2", "--checkpoint-every", "2",
            "--val", clips_root, "--validate-every", "2", "--validation-windows", "2"]  # fmt: skip
    assert cli.main(args) == 0
    out = capsys.readouterr().out
    assert "trained 4 steps" in out and "validation (right dropped, 2 windows): " in out
    assert "p_mpjpe_mm" in out and "keypoints_2d_px" in out
    rows = [json.loads(line) for line in (run / "validation.jsonl").read_text().splitlines()]
    assert [(r["step"], r["views"]) for r in rows] == [(2, "both"), (2, "right dropped"), (4, "both"), (4, "right dropped")]
    assert all(r["windows"] == 2 and r["p_mpjpe_mm"] > 0 and r["keypoints_2d_px"] > 0 and 0 <= r["onscreen_f1"] <= 1 for r in rows)
    assert (run / "curves.png").stat().st_size > 10_000
    assert cli.main(args) == 2 and "already holds a run" in capsys.readouterr().err
    assert cli.main(args + ["--resume"]) == 0 and "already trained to step 4: nothing to train" in capsys.readouterr().out
    longer = [*args[: args.index("--steps") + 1], "6", *args[args.index("--steps") + 2 :], "--resume"]
    assert cli.main(longer) == 2
    assert "train.steps was 4, now 6" in (err := capsys.readouterr().err) and "--init" in err
    with exclusive_lock(run / ".train.lock"):  # another process training into it
        assert cli.main(args + ["--resume"]) == 2 and "being trained by another process" in capsys.readouterr().err
    stage2 = [a if a != str(run) else str(tmp_path / "run2") for a in args] + ["--init", str(run), "--triangulated-wrist-input"]
    assert cli.main(stage2) == 2 and "triangulated_wrist_input False vs True" in capsys.readouterr().err
    assert not (tmp_path / "run2").exists()  # a run that never started leaves no folder
    no_labels = [a if a != str(run) else str(tmp_path / "run3") for a in args] + ["--targets", "labels", "--labels", str(tmp_path / "nolabels")]
    assert cli.main(no_labels) == 2 and "nolabels does not exist" in capsys.readouterr().err
    (tmp_path / "afile").write_text("")
    on_a_file = [a if a != str(run) else str(tmp_path / "afile") for a in args]
    assert cli.main(on_a_file) == 2 and "afile is a file, not a folder" in capsys.readouterr().err
    assert cli.main(["predict", "--model", str(run), clips_root, "--out", str(tmp_path / "pred")]) == 0
    labels = {side: clips.Labels.from_npz(clips.hand_file(tmp_path / "pred" / synth_clip.name, side, "labels")) for side in ("right", "left")}
    assert labels["right"].joints.shape == (8, 21, 3) and labels["left"].valid.dtype == bool
    assert np.all(np.isnan(labels["left"].residual_px)) and labels["left"].stereo is None  # the network measures no residual
    assert cli.main(["evaluate", "--pred", str(tmp_path / "pred"), "--gt", clips_root, "--out", str(tmp_path / "ev")]) == 0
    assert "identity" not in capsys.readouterr().err  # the predictions record their source clip
    assert cli.main(["predict", "--model", str(tmp_path / "nowhere"), clips_root, "--out", str(tmp_path / "p2")]) == 2


def test_validation_scores_known_errors(synth_clip):
    """score_windows on predictions equal to the targets shifted by 10 mm and 2D keypoints
    off by (3, 4) px: P-MPJPE 0, wrist 10 mm, 2D 5 px, the targets' own jitter, every
    on-screen frame recalled; drop_view blanks a view."""
    from esther_jax.train import validation

    data_cfg = train.DataConfig(frames=RUN_FRAMES, stride=RUN_FRAMES, crop_size=64)
    windows = train.build_index([synth_clip], data_cfg)
    clip, targets = jax.tree.map(lambda *x: jnp.stack(x), *[train.load_example(w, data_cfg) for w in windows])
    shift = jnp.asarray([0.006, 0.0, -0.008])
    uv = jax.vmap(lambda c, j: M.crop_projections(c, j, 64)[0])(clip, targets.joints)
    fps = jnp.full((len(windows),), 30.0)
    per_window, gate = validation.score_windows(targets.joints + shift[None, None, None], jnp.ones(targets.valid.shape, bool),
                                                uv + jnp.asarray([3.0, 4.0])[None, None, None, None], clip, targets, fps, 64)  # fmt: skip
    mean = lambda name: float(metrics.dataset_mean(per_window[name]).value)  # noqa: E731
    assert mean("p_mpjpe_mm") == pytest.approx(0.0, abs=1e-6) and mean("pa_mpjpe_mm") == pytest.approx(0.0, abs=1e-5)
    assert mean("wrist_mm") == pytest.approx(0.010, rel=1e-4) and mean("keypoints_2d_px") == pytest.approx(5.0, rel=1e-4)
    assert mean("jitter") == pytest.approx(mean("gt_jitter"), rel=1e-5)
    pooled = metrics.pooled_gate_scores(gate.true_positives, gate.false_positives, gate.false_negatives)
    assert float(pooled.recall) == 1.0 and 0 < float(pooled.precision) <= 1.0
    dropped = validation.drop_view(train.load_example(windows[0], data_cfg)[0], 1)
    assert not bool(dropped.view_present[:, 1].any()) and float(jnp.abs(dropped.images[:, 1]).max()) == 0.0
    kept = jnp.arange(RUN_FRAMES) % 3 != 1
    blanked, mask = validation.drop_frames(train.load_example(windows[0], data_cfg)[0], kept)
    assert np.array_equal(np.asarray(blanked.view_present.any(axis=1)), np.asarray(kept) & np.asarray(clip.view_present[0].any(axis=1)))
    assert float(jnp.abs(blanked.images[~kept]).max()) == 0.0 and np.array_equal(np.asarray(mask[:, 0]), ~np.asarray(kept))


def test_predict_hand_is_the_same_window_batch_by_batch(synth_clip):
    """`esther predict` predicts a clip's windows a batch at a time (the last batch padded):
    the labels do not depend on the batch."""
    from esther_jax.cameras import StereoRig
    from esther_jax.model.folders import predict_hand

    net = M.ESTHER(M.config("cpu-tiny", num_frames=3), key=jax.random.key(0))  # windows at 0, 3, 5 of 8 frames
    rig = StereoRig.from_json(synth_clip / "rig.json")
    one, two = (predict_hand(net, synth_clip, "left", rig, batch=b) for b in (1, 2))
    assert one.joints.shape == (8, 21, 3) and one.params.betas.shape == (8, 10) and one.onscreen_prob is not None
    for (path, a), b in zip(jax.tree_util.tree_leaves_with_path(one), jax.tree.leaves(two)):
        np.testing.assert_allclose(a, b, atol=1e-5, err_msg=jax.tree_util.keystr(path))


def test_robustness_conditions_run_through_the_network(synth_clip):
    """evaluate_windows under dropped frames plus a corruption, with bootstrap intervals
    (the conditions of the paper's tables 4 and 6)."""
    net = M.ESTHER(M.config("cpu-tiny", num_frames=RUN_FRAMES), key=jax.random.key(0))
    data_cfg = train.DataConfig(frames=RUN_FRAMES, stride=RUN_FRAMES, crop_size=64)
    windows = train.build_index([synth_clip], data_cfg)
    clean = train.evaluate_windows(net, windows, data_cfg, batch=RUN_BATCH)  # the validation's compiled shape (command-line test)
    harsh = train.evaluate_windows(net, windows, data_cfg, batch=RUN_BATCH, frames_dropped=4, corruption="low_light", intervals=True)
    assert list(harsh)[:-2] == list(train.validation.VALIDATION_METRICS) and harsh["windows"] == 2
    assert harsh["p_mpjpe_mm"] != clean["p_mpjpe_mm"]  # the condition reached the network
    low, high = harsh["intervals"]["p_mpjpe_mm"]
    assert low <= harsh["p_mpjpe_mm"] <= high
    with pytest.raises(ValueError, match="frames_dropped"):
        train.evaluate_windows(net, windows, data_cfg, frames_dropped=RUN_FRAMES + 1)
    stress = jnp.arange(RUN_FRAMES) < 2  # appendix L's stress test: frames blanked in both views, not masked
    pred = train.predict_windows(net, windows, data_cfg, batch=RUN_BATCH, blanked=stress)
    assert pred.joints.shape == (2, RUN_FRAMES, 21, 3) and not bool(pred.onscreen[:, :2].any()) and bool(pred.onscreen[:, 2:].any())


_DATA_PARALLEL = r"""
import os, sys
os.environ["XLA_FLAGS"] = os.environ.get("XLA_FLAGS", "") + " --xla_force_host_platform_device_count=4"  # the suite's compiler flags, 4 devices
import jax
import numpy as np
jax.config.update("jax_compilation_cache_dir", os.environ["ESTHER_JAX_CACHE"])
jax.config.update("jax_persistent_cache_min_compile_time_secs", 1.0)
from esther_jax import mano, model as M, train

clip, frames, batch, out = sys.argv[1], int(sys.argv[2]), int(sys.argv[3]), sys.argv[4]
model_cfg = M.config("cpu-tiny", num_frames=frames)
cfg = train.TrainConfig(steps=4, batch=batch, warmup_steps=2)
data_cfg = train.DataConfig(frames=frames, stride=2, crop_size=model_cfg.crop_size)
windows = train.build_index([clip], data_cfg)
trainer = train.Trainer(M.ESTHER(model_cfg, key=jax.random.key(0)), cfg, mano.load_builtin("right"), mesh=train.data_mesh())
state, losses = trainer.init(), []
for step in range(3):
    state, metrics = trainer.step(state, *train.load_batch(windows, data_cfg, cfg.batch, cfg.seed, step))
    losses.append(float(metrics["loss"]))
images = trainer.shard(train.load_batch(windows, data_cfg, cfg.batch, cfg.seed, 0))[0].images
np.savez(out, devices=jax.device_count(), split=[s.data.shape[0] for s in images.addressable_shards], losses=losses,
         replicated=all(x.sharding.is_fully_replicated for x in jax.tree.leaves(state.params)),
         **{f"w{i}": np.asarray(x) for i, x in enumerate(jax.tree.leaves(state.params))})
"""


def test_data_parallel_steps_equal_the_single_device_run(synth_clip, tmp_path):
    """Four virtual CPU devices (a subprocess: the device count is fixed at start-up):
    the batch split four ways, the weights replicated, and after three steps the losses
    and weights equal this process's one-device run's to 1e-5."""
    import os
    import subprocess
    import sys

    model_cfg = M.config("cpu-tiny", num_frames=RUN_FRAMES)
    cfg = train.TrainConfig(steps=4, batch=RUN_BATCH, warmup_steps=2)  # the run tests' step settings: compiled already
    data_cfg = train.DataConfig(frames=RUN_FRAMES, stride=2, crop_size=model_cfg.crop_size)
    windows = train.build_index([synth_clip], data_cfg)
    net = M.ESTHER(model_cfg, key=jax.random.key(0))
    trainer = train.Trainer(net, cfg, mano.load_builtin("right"))
    state, losses = trainer.init(), []
    for step in range(3):
        state, metrics = trainer.step(state, *train.load_batch(windows, data_cfg, cfg.batch, cfg.seed, step))
        losses.append(float(metrics["loss"]))

    env = {**os.environ, "ESTHER_JAX_CACHE": jax.config.jax_compilation_cache_dir}
    out = tmp_path / "four.npz"
    done = subprocess.run([sys.executable, "-c", _DATA_PARALLEL, str(synth_clip), str(RUN_FRAMES), str(RUN_BATCH), str(out)],
                          capture_output=True, text=True, env=env, timeout=900)  # fmt: skip
    assert done.returncode == 0, done.stderr[-3000:]
    four = np.load(out)
    assert int(four["devices"]) == 4 and four["split"].tolist() == [1, 1, 1, 1] and bool(four["replicated"])
    np.testing.assert_allclose(four["losses"], losses, rtol=1e-5)
    weights = [np.asarray(x) for x in jax.tree.leaves(state.params)]
    initial = jax.tree.leaves(trainer.init().params)
    assert max(float(np.max(np.abs(w - np.asarray(w0)))) for w, w0 in zip(weights, initial)) > 1e-4  # the steps moved the weights ...
    assert max(float(np.max(np.abs(w - four[f"w{i}"]))) for i, w in enumerate(weights)) < 1e-5  # ... identically


def test_mixed_precision_computes_in_bfloat16_and_keeps_geometry_in_float32(synth_clip):
    """model.cast(net, bfloat16): the transformer's evidence in bfloat16, the keypoints,
    triangulation, rotations and hands in float32, close to the float32 network's."""
    model_cfg = M.config("cpu-tiny", num_frames=RUN_FRAMES)
    data_cfg = train.DataConfig(frames=RUN_FRAMES, crop_size=model_cfg.crop_size)
    clip, _ = train.load_example(train.build_index([synth_clip], data_cfg)[0], data_cfg)
    net, hand = M.ESTHER(model_cfg, key=jax.random.key(1)), mano.load_builtin("right")
    forward = eqx.filter_jit(lambda n, c: n(c, hand))
    full, half = forward(net, clip), forward(M.cast(net, jnp.bfloat16), clip)
    assert half.image.features.dtype == jnp.bfloat16 and half.image.heatmap_logits.dtype == jnp.bfloat16
    for x in (half.image.keypoints_2d, half.image.triangulated, half.decoded.rotations, half.params.transl, half.joints, half.vertices):
        assert x.dtype == jnp.float32
    np.testing.assert_allclose(np.asarray(half.image.keypoints_2d), np.asarray(full.image.keypoints_2d), atol=0.5)  # px of 64
    np.testing.assert_allclose(np.asarray(half.joints), np.asarray(full.joints), atol=2e-3)  # m
    with pytest.raises(ValueError, match="compute_dtype"):
        train.TrainConfig(compute_dtype="float16")


def test_feature_cache_holds_what_the_frozen_backbone_sees(synth_clip, tmp_path, monkeypatch):
    """precompute_features once (a chunk of frames at a time, the last one padded); windows
    then carry the cached tokens, equal (float16) to the backbone's tokens of the crops the
    network would see, mirrored ones for the left hand; another backbone is refused, a
    second fill does nothing."""
    from esther_jax.train import features as F

    monkeypatch.setattr(F, "FEATURE_CHUNK", 3)  # 8 frames: chunks of 3, 3 and 2 (padded)

    model_cfg = M.config("cpu-tiny", num_frames=RUN_FRAMES, freeze_backbone=True)
    backbone = M.ESTHER(model_cfg, key=jax.random.key(0)).backbone
    cache = F.precompute_features(backbone, [synth_clip], model_cfg.crop_size, tmp_path / "features", progress=False)
    files = sorted(cache.glob("*/*.npy"))
    assert [f.name for f in files] == ["left.npy", "right.npy"] and files[0].parent.name.startswith(synth_clip.name + "-")
    stamp = [f.stat().st_mtime_ns for f in files]
    F.precompute_features(backbone, [synth_clip], model_cfg.crop_size, cache, progress=False)
    assert [f.stat().st_mtime_ns for f in files] == stamp  # resumable: nothing redone
    crops_cfg = train.DataConfig(frames=RUN_FRAMES, crop_size=model_cfg.crop_size)
    cached_cfg = dataclasses.replace(crops_cfg, features=str(cache))
    extract = jax.jit(M.extract_features)
    for window in train.build_index([synth_clip], crops_cfg):
        seen, targets = train.load_example(window, crops_cfg)
        cached, cached_targets = train.load_example(window, cached_cfg)
        assert cached.images is None and cached.features.shape == seen.view_present.shape + (model_cfg.grid**2, model_cfg.backbone_spec.width)
        expected = np.where(np.asarray(seen.view_present)[..., None, None], np.asarray(extract(backbone, seen.images)), 0.0)
        np.testing.assert_allclose(np.asarray(cached.features), expected, atol=2e-2, rtol=1e-2)
        np.testing.assert_array_equal(np.asarray(cached.K), np.asarray(seen.K))
        np.testing.assert_array_equal(np.asarray(cached_targets.joints), np.asarray(targets.joints))
    other = M.ESTHER(model_cfg, key=jax.random.key(1)).backbone
    with pytest.raises(ValueError, match="another backbone"):
        F.precompute_features(other, [synth_clip], model_cfg.crop_size, cache, progress=False)
