"""`fitting.refine` (the data engine's model-assisted labelling): a prediction refined
against the clip's 2D keypoints by the teacher's stages, screened by its filter, and
`esther refine` writing the teacher's format with the prediction's origin."""

import json
import shutil

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest

from esther_jax import cli, clips, mano, metrics, rotations
from esther_jax.data import motion, synth
import fitting

FRAMES = 32  # one length bucket, as tests/test_fitting.py: the teacher's programs compile once


@pytest.fixture(scope="module")
def clip():
    cfg = synth.SynthConfig(num_frames=FRAMES, detector_preset="easy", motion_config=motion.MotionConfig(two_hands_probability=1.0, leave_view_probability=0.0))
    return synth.make_clip(28, 0, cfg)  # both hands on screen throughout


@pytest.fixture(scope="module")
def teacher(clip):
    return {side: fitting.label_hand(mano.load_builtin(side), clip.rig, clip.keypoints[side], 30.0) for side in ("right",)}


def _perturbed(gt: dict, seed: int) -> mano.ManoParams:
    """Ground truth perturbed as a poor network would: 0.15 rad per joint angle and frame,
    3 cm of wrist, 0.5 per beta."""
    rng = np.random.default_rng(seed)
    return _params(gt["global_orient"] + rng.normal(scale=0.15, size=(FRAMES, 3)), gt["hand_pose"] + rng.normal(scale=0.15, size=(FRAMES, 15, 3)),
                   gt["betas"] + rng.normal(scale=0.5, size=10), gt["transl"] + rng.normal(scale=0.03, size=(FRAMES, 3)))  # fmt: skip


def _params(global_orient, hand_pose, betas, transl) -> mano.ManoParams:
    """Per-frame MANO parameters (float32, the shape repeated per frame) from host arrays."""
    f32 = lambda x: jnp.asarray(x, jnp.float32)  # noqa: E731
    return mano.ManoParams(f32(global_orient), f32(hand_pose), f32(np.broadcast_to(betas, (FRAMES, 10))), f32(transl))


def _errors(labels: clips.Labels, gt: dict) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Accepted frames, per-frame P-MPJPE and wrist error (metres)."""
    ok = np.asarray(labels.valid) & gt["onscreen"]
    true = jnp.asarray(gt["joints"])
    return ok, np.asarray(jax.vmap(metrics.p_mpjpe)(labels.joints, true)), np.asarray(jax.vmap(metrics.wrist_error)(labels.joints, true))


def test_refine_recovers_a_perturbed_hand_to_the_teachers_accuracy(clip, teacher):
    gt = clip.gt["right"]
    labels, report = fitting.refine(mano.load_builtin("right"), clip.rig, clip.keypoints["right"], 30.0, _perturbed(gt, 0))
    ok, p, w = _errors(labels, gt)
    t_ok, t_p, t_w = _errors(teacher["right"][0], gt)
    assert report["initialised_from"] == "prediction" and teacher["right"][1]["initialised_from"] == "teacher"
    assert ok.sum() >= t_ok.sum()
    assert p[ok].mean() <= t_p[t_ok].mean() + 0.0005  # within half a millimetre of the teacher's P-MPJPE
    assert w[ok].mean() <= t_w[t_ok].mean() + 0.002
    # a pose the 2D evidence contradicts (a fist where the hand is open) is undone
    fist = _params(gt["global_orient"], np.tile([0.0, 0.0, 1.4], (FRAMES, 15, 1)), gt["betas"], gt["transl"])
    ok, p, _ = _errors(fitting.refine(mano.load_builtin("right"), clip.rig, clip.keypoints["right"], 30.0, fist)[0], gt)
    assert ok.sum() >= t_ok.sum() and p[ok].mean() < 0.003
    # so is a palm on the wrong one of its two mirror-image poses (upside down, 10 cm off):
    # the triangulated palm's pose reprojects better and wins (a refit of the prediction alone
    # cannot leave that local minimum)
    R = rotations.axis_angle_to_matrix(jnp.asarray(gt["global_orient"]))
    flipped = np.asarray(rotations.matrix_to_axis_angle(jnp.diag(jnp.asarray([1.0, -1.0, -1.0])) @ R))
    upside_down = _params(flipped, gt["hand_pose"], gt["betas"], gt["transl"] + 0.1)
    ok, p, _ = _errors(fitting.refine(mano.load_builtin("right"), clip.rig, clip.keypoints["right"], 30.0, upside_down)[0], gt)
    assert ok.sum() >= t_ok.sum() and p[ok].mean() < 0.003


def test_a_prediction_the_2d_evidence_contradicts_is_rejected(clip):
    """Every finger bent backwards far past its limit is a local minimum the refit cannot
    leave: its residuals fail the teacher's reprojection filter, no frame passes."""
    gt = clip.gt["right"]
    bent_back = _params(gt["global_orient"], np.tile([0.0, 0.0, -1.4], (FRAMES, 15, 1)), gt["betas"], gt["transl"])
    labels, report = fitting.refine(mano.load_builtin("right"), clip.rig, clip.keypoints["right"], 30.0, bent_back)
    assert not np.asarray(labels.valid).any() and report["share_passing"] == 0.0
    assert np.nanmedian(np.asarray(labels.residual_px)) > fitting.LabelConfig().reject_px


def test_bad_predictions_are_named(clip):
    gt, model, kp = clip.gt["right"], mano.load_builtin("right"), clip.keypoints["right"]
    good = _perturbed(gt, 1)
    with pytest.raises(ValueError, match="hand_pose must be"):
        fitting.refine(model, clip.rig, kp, 30.0, eqx.tree_at(lambda x: x.hand_pose, good, good.hand_pose[:, :14]))
    nan = good.transl.at[3].set(jnp.nan)
    with pytest.raises(ValueError, match="NaN or infinite values in transl"):
        fitting.refine(model, clip.rig, kp, 30.0, eqx.tree_at(lambda x: x.transl, good, nan))
    with pytest.raises(ValueError, match="lack the left hand"):
        fitting.label_hands({s: mano.load_builtin(s) for s in clip.keypoints}, clip.rig, clip.keypoints, 30.0, predictions={"right": good})


def _write_predictions(root, name: str, gt: dict, seed: int) -> None:
    on = jnp.ones(FRAMES, bool)
    clips.Labels(_perturbed(gt, seed), jnp.asarray(gt["joints"], jnp.float32), on, on, jnp.full(FRAMES, jnp.nan, jnp.float32)).to_npz(clips.hand_file(root / name, "right", "labels"))
    clips.write_meta(root / name, num_frames=FRAMES, fps=30.0, labelled_by="a test's network")


def test_refine_cli_writes_the_teachers_format_with_the_predictions_origin(clip, tmp_path, capsys):
    # the right hand only, so that the clip's one prediction covers every hand it labels
    one_hand = synth.write_clip(clip, tmp_path / "clips" / "clip_a")
    shutil.rmtree(one_hand / "hands" / "left")
    gt = clip.gt["right"]
    predictions, out = tmp_path / "predictions", tmp_path / "labels"
    _write_predictions(predictions, "clip_a", gt, 2)
    assert cli.main(["refine", str(one_hand), "--predictions", str(predictions), "--out", str(out)]) == 0
    meta = json.loads((out / "clip_a" / "meta.json").read_text())
    assert meta["labelled_by"] == "esther refine" and meta["source_clip"]["digest"] == clips.clip_digest(one_hand)
    assert meta["method"] == fitting.method_record(fitting.REFINE_CONFIG, refined=True) and meta["method"]["revision"] == fitting.REFINE_REVISION
    assert meta["prediction"]["labelled_by"] == "a test's network" and meta["prediction"]["folder"] == str(predictions.resolve())
    quality = json.loads((out / "clip_a" / "hands" / "right" / "quality.json").read_text())
    assert quality["initialised_from"] == "prediction"
    ok, p, _ = _errors(clips.Labels.from_npz(clips.hand_file(out / "clip_a", "right", "labels")), gt)
    assert ok.mean() > 0.9 and p[ok].mean() < 0.003
    first = (out / "clip_a" / "meta.json").stat().st_mtime_ns
    # resume keeps a clip refined from the same prediction, rewritten equal (a zip's timestamps differ)
    _write_predictions(predictions, "clip_a", gt, 2)
    assert cli.main(["refine", str(one_hand), "--predictions", str(predictions), "--out", str(out), "--resume"]) == 0
    assert (out / "clip_a" / "meta.json").stat().st_mtime_ns == first and "skipped 1" in capsys.readouterr().out
    # and redoes it from a new prediction (a later round's network)
    _write_predictions(predictions, "clip_a", gt, 3)
    assert cli.main(["refine", str(one_hand), "--predictions", str(predictions), "--out", str(out), "--resume"]) == 0
    assert json.loads((out / "clip_a" / "meta.json").read_text())["prediction"]["sha256"] != meta["prediction"]["sha256"]
    # no predictions anywhere: a clear error, nothing written
    assert cli.main(["refine", str(one_hand), "--out", str(tmp_path / "other")]) == 2
    assert "no predictions in" in capsys.readouterr().err
