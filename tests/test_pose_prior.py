"""The learned pose prior (`mano.GMMPosePrior`): its least-squares form, mirroring, file,
fitting, and the teacher and `fitting.refine` under it (`esther prior`, `--pose-prior`)."""

import json

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from esther_jax import cli, clips, mano, metrics
from esther_jax.data import motion, synth
import fitting

FRAMES = 32  # the teacher's length bucket of tests/test_refine.py


@pytest.fixture(scope="module")
def prior():
    return mano.fit_gmm_pose_prior(motion.sample_hand_poses(5, 60, 90), components=4, iterations=40)


def test_least_squares_form_matches_autodiff_and_mirrors(prior):
    pose = jnp.asarray(motion.sample_hand_poses(9, 1, 30)[7]) + 0.1  # off the data: some hinges active
    for side in ("right", "left"):
        model = mano.load_builtin(side)
        p = prior.for_side(model.is_right).with_limits(mano.PosePrior.from_model(model))
        x = pose if side == "right" else mano.mirror_hand_pose(pose)
        J = jax.jacfwd(lambda v: p(v.reshape(15, 3)))(x.reshape(45))
        g, H = p.normal_equations(x)
        r = p(x)
        assert r.shape == (90,)
        np.testing.assert_allclose(g, J.T @ r, rtol=1e-4, atol=1e-3)
        np.testing.assert_allclose(H, J.T @ J, rtol=1e-4, atol=1e-3)
        # 0.5 |r_gmm|^2 is the best component's energy up to its constant; the mirror image scores the same
        assert float(prior.for_side(model.is_right).negative_log_likelihood(x)) == pytest.approx(float(prior.negative_log_likelihood(pose)), rel=1e-5)


def test_fitted_prior_prefers_natural_poses_and_round_trips(prior, tmp_path):
    held_out = jnp.asarray(motion.sample_hand_poses(11, 4, 90))
    scrambled = jnp.asarray(np.random.default_rng(0).permutation(np.asarray(held_out).reshape(-1, 45).T).T.reshape(-1, 15, 3))  # joints mixed up
    nll = lambda x: float(jnp.mean(jax.vmap(prior.negative_log_likelihood)(x)))  # noqa: E731
    assert nll(held_out) < nll(scrambled) - 50.0
    loaded = mano.GMMPosePrior.load(prior.save(tmp_path / "prior.npz"))
    np.testing.assert_array_equal(loaded.factors, prior.factors)
    (tmp_path / "bad.npz").write_bytes(b"not a prior")
    with pytest.raises(ValueError, match="not a pose prior file"):
        mano.GMMPosePrior.load(tmp_path / "bad.npz")
    with pytest.raises(ValueError, match="needs many poses"):
        mano.fit_gmm_pose_prior(held_out[:10], components=4)
    with pytest.raises(ValueError, match="NaN"):
        mano.fit_gmm_pose_prior(jnp.full((1000, 15, 3), jnp.nan), components=4)


def test_teacher_and_refine_under_the_learned_prior(prior, tmp_path, capsys):
    cfg = synth.SynthConfig(num_frames=FRAMES, detector_preset="easy", motion_config=motion.MotionConfig(two_hands_probability=1.0, leave_view_probability=0.0))
    clip = synth.make_clip(28, 0, cfg)
    gt = clip.gt["right"]
    model = mano.load_builtin("right")
    true = jnp.asarray(gt["joints"])
    start = mano.ManoParams(*(jnp.asarray(gt[k], jnp.float32) for k in ("global_orient", "hand_pose")),
                            jnp.asarray(np.broadcast_to(gt["betas"], (FRAMES, 10)), jnp.float32), jnp.asarray(gt["transl"], jnp.float32))  # fmt: skip
    for labels, _ in (fitting.label_hand(model, clip.rig, clip.keypoints["right"], 30.0, pose_prior=prior),
                      fitting.refine(model, clip.rig, clip.keypoints["right"], 30.0, start, pose_prior=prior)):  # fmt: skip
        ok = np.asarray(labels.valid) & gt["onscreen"]
        assert ok.mean() > 0.8
        assert float(jnp.mean(jax.vmap(metrics.p_mpjpe)(labels.joints, true)[ok])) < 0.006

    # esther prior fits a file; esther label records it and --resume redoes labels of another prior
    folder = synth.write_clip(clip, tmp_path / "clips" / "clip_00000")
    assert cli.main(["prior", "--out", str(tmp_path / "prior.npz"), "--synthetic", "40", "--components", "4", "--iterations", "20"]) == 0
    assert cli.main(["label", str(folder), "--out", str(tmp_path / "labels")]) == 0
    assert json.loads((tmp_path / "labels" / "clip_00000" / "meta.json").read_text())["pose_prior"] is None
    assert cli.main(["label", str(folder), "--out", str(tmp_path / "labels"), "--resume", "--pose-prior", str(tmp_path / "prior.npz")]) == 0
    recorded = json.loads((tmp_path / "labels" / "clip_00000" / "meta.json").read_text())["pose_prior"]
    assert recorded["kind"] == "gmm" and recorded["components"] == 4
    poses = clips.accepted_hand_poses(tmp_path / "labels")
    assert poses.shape[1:] == (15, 3) and len(poses) > FRAMES  # both hands' accepted frames, the left mirrored
    assert cli.main(["prior", "--out", str(tmp_path / "p.npz")]) == 2
