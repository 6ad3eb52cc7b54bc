"""Which MANO model labels are parameters of: `mano.model_id`, `esther label --mano DIR`,
and `esther evaluate` comparing parameters only between labels of the same model."""

import json
import shutil

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from esther_jax import cli, clips, mano
from esther_jax.data import motion, synth

FRAMES = 32  # the length bucket of tests/test_fitting.py: its compiled solvers are reused

_MIRROR_X = jnp.asarray([-1.0, 1.0, 1.0])[None, :, None]


def _write_official_pair(model_dir, buggy_left: bool = True):
    """MANO_RIGHT.pkl / MANO_LEFT.pkl of the built-in hands, the left one with the official
    file's x-shapedirs sign bug (smplx#48) that the loader must undo."""
    left = mano.load_builtin("left")
    if buggy_left:
        left = left.replace(shapedirs=left.shapedirs * _MIRROR_X)
    mano.save_mano_pkl(mano.load_builtin("right"), model_dir / "MANO_RIGHT.pkl")
    mano.save_mano_pkl(left, model_dir / "MANO_LEFT.pkl")
    return model_dir


# ----------------------------------------------------------------------------- model_id


@pytest.mark.parametrize("side", ["right", "left"])
def test_model_id_survives_the_pickle_round_trip(side, tmp_path):
    model = mano.load_builtin(side)
    loaded = mano.load_mano_pkl(mano.save_mano_pkl(model, tmp_path / f"MANO_{side.upper()}.pkl"))
    assert mano.model_id(loaded) == mano.model_id(model)
    assert mano.model_id(model).startswith(f"{side}-") and len(mano.model_id(model)) == len(side) + 17


def test_model_id_does_not_depend_on_the_float_precision(x64, tmp_path):
    model64 = mano.load_builtin("right")
    assert model64.v_template.dtype == jnp.float64
    path = mano.save_mano_pkl(model64, tmp_path / "MANO_RIGHT.pkl")
    ids64 = {mano.model_id(model64), mano.model_id(mano.load_mano_pkl(path))}
    with jax.enable_x64(False):
        model32 = mano.load_builtin("right")
        assert model32.v_template.dtype == jnp.float32
        ids32 = {mano.model_id(model32), mano.model_id(mano.load_mano_pkl(path))}
    assert len(ids64) == 1 and ids64 == ids32


def test_model_id_differs_between_sides_and_models(tmp_path):
    right, left = mano.load_builtin("right"), mano.load_builtin("left")
    assert mano.model_id(right) != mano.model_id(left)
    changed = right.replace(shapedirs=right.shapedirs.at[0, 0, 0].add(1e-4))
    assert mano.model_id(changed) != mano.model_id(right)
    assert mano.model_id(right.replace(posedirs=right.posedirs * 1.01)) != mano.model_id(right)
    assert mano.model_id(right.replace(fingertip_ids=jnp.asarray(mano.FINGERTIP_IDS_MANOPTH["right"]))) != mano.model_id(right)
    # the same arrays again (a fresh load, a zero made -0.0, faces re-wound) are the same model
    assert mano.model_id(mano.load_builtin("right")) == mano.model_id(right)
    signed_zeros = jnp.where(right.posedirs == 0, -0.0, right.posedirs)
    assert np.signbit(np.asarray(signed_zeros)).sum() > np.signbit(np.asarray(right.posedirs)).sum()
    assert mano.model_id(right.replace(posedirs=signed_zeros)) == mano.model_id(right)
    assert mano.model_id(right.replace(faces=right.faces[:, ::-1])) == mano.model_id(right)
    # the official left file's sign bug, fixed on load, gives the built-in left model back
    buggy = mano.save_mano_pkl(left.replace(shapedirs=left.shapedirs * _MIRROR_X), tmp_path / "MANO_LEFT.pkl")
    assert mano.model_id(mano.load_mano_pkl(buggy)) == mano.model_id(left)
    assert mano.model_id(mano.load_mano_pkl(buggy, fix_left_shapedirs=False)) != mano.model_id(left)


def test_model_id_needs_a_concrete_model():
    with pytest.raises(ValueError, match="outside jit"):
        jax.jit(lambda m: jnp.zeros(()) if mano.model_id(m) else jnp.ones(()))(mano.load_builtin("right"))


# ----------------------------------------------------------------------------- esther label --mano


@pytest.fixture(scope="module")
def clip_and_models(tmp_path_factory):
    """One two-handed clip folder (synth records its ground truth's model) and a folder of
    the built-in hands written as official-format MANO pickles."""
    root = tmp_path_factory.mktemp("mano_cli")
    cfg = synth.SynthConfig(num_frames=FRAMES, detector_preset="easy", motion_config=motion.MotionConfig(two_hands_probability=1.0, leave_view_probability=0.0))
    clip = synth.write_clip(synth.make_clip(28, 0, cfg), root / "clips" / "c0")
    model_dir = root / "mano_models"
    model_dir.mkdir()
    _write_official_pair(model_dir)
    return root, clip, model_dir


@pytest.fixture(scope="module")
def labelled(clip_and_models):
    """The clip labelled once with the built-in hands and once with `--mano DIR`."""
    from fitting import label_clips

    root, clip, model_dir = clip_and_models
    builtin = label_clips([clip], root / "builtin", progress=False)
    assert not builtin["failed"]
    assert cli.main(["label", str(clip), "--out", str(root / "official"), "--mano", str(model_dir)]) == 0
    return root, clip, model_dir


@pytest.mark.slow
def test_label_with_official_models_matches_the_builtin_labels(labelled, capsys):
    root, clip, model_dir = labelled
    for side in clips.SIDES:
        ours = clips.load_npz(clips.hand_file(root / "builtin" / "c0", side, "labels"), "labels")
        theirs = clips.load_npz(clips.hand_file(root / "official" / "c0", side, "labels"), "labels")
        np.testing.assert_array_equal(ours["valid"], theirs["valid"])
        assert ours["valid"].sum() >= FRAMES // 2
        for key in ("joints", "hand_pose", "betas", "transl", "global_orient"):
            np.testing.assert_allclose(theirs[key], ours[key], atol=1e-5, err_msg=f"{side} {key}")
        quality = json.loads((root / "official" / "c0" / "hands" / side / "quality.json").read_text())
        want_id = mano.model_id(mano.load_builtin(side))
        assert quality["mano_model"] == {"id": want_id, "source": str((model_dir / f"MANO_{side.upper()}.pkl").resolve())}
        builtin_quality = json.loads((root / "builtin" / "c0" / "hands" / side / "quality.json").read_text())
        assert builtin_quality["mano_model"] == {"id": want_id, "source": "builtin"}
    meta = json.loads((root / "official" / "c0" / "meta.json").read_text())
    assert set(meta["mano_model"]) == {"right", "left"}
    assert meta["mano_model"]["left"]["source"].endswith("MANO_LEFT.pkl")
    gt_meta = json.loads((clip / "meta.json").read_text())  # synth records the ground truth's model
    assert gt_meta["mano_model"]["right"] == {"id": mano.model_id(mano.load_builtin("right")), "source": "builtin"}
    # the same models again: --resume skips the clip
    capsys.readouterr()
    assert cli.main(["label", str(clip), "--out", str(root / "official"), "--mano", str(model_dir), "--resume"]) == 0
    assert "skipped 1" in capsys.readouterr().out


@pytest.mark.slow
def test_evaluate_compares_parameters_of_the_same_model(labelled, tmp_path):
    root, clip, _ = labelled
    out = tmp_path / "eval"
    assert cli.main(["evaluate", "--pred", str(root / "official"), "--gt", str(clip.parent), "--out", str(out), "--params", "require"]) == 0
    result = json.loads((out / "metrics.json").read_text())
    assert result["parameters"]["compared"] == ["c0/right", "c0/left"] and not result["parameters"]["not_compared"]
    assert 0.0 < result["metrics"]["pose_angle"]["value"] < 30.0 and result["metrics"]["pose_angle"]["unit"] == "deg"
    assert result["metrics"]["betas_rmse"]["value"] >= 0.0
    assert result["metrics"]["p_mpjpe"]["value"] < 15.0


def test_label_mano_dir_errors_are_clear(clip_and_models, tmp_path, capsys):
    root, clip, model_dir = clip_and_models
    out = str(tmp_path / "labels")
    assert cli.main(["label", str(clip), "--out", out, "--mano", str(tmp_path / "absent")]) == 2
    assert "is not a folder" in capsys.readouterr().err
    only_right = tmp_path / "only_right"
    only_right.mkdir()
    shutil.copy(model_dir / "MANO_RIGHT.pkl", only_right)
    assert cli.main(["label", str(clip), "--out", out, "--mano", str(only_right)]) == 2
    err = capsys.readouterr().err
    assert "MANO_LEFT.pkl is missing" in err and "both" in err
    (only_right / "MANO_LEFT.pkl").write_bytes(b"not a pickle at all")
    assert cli.main(["label", str(clip), "--out", out, "--mano", str(only_right)]) == 2
    assert "MANO_LEFT.pkl is not a pickle" in capsys.readouterr().err
    nested = tmp_path / "mano_v1_2" / "models"  # the official download's layout
    shutil.copytree(model_dir, nested)
    from esther_jax.cli import _mano_models

    models, sources = _mano_models(str(nested.parent))
    assert {s: mano.model_id(m) for s, m in models.items()} == {s: mano.model_id(mano.load_builtin(s)) for s in clips.SIDES}
    assert sources["left"] == str((nested / "MANO_LEFT.pkl").resolve())
    assert not (tmp_path / "labels").exists() or not any((tmp_path / "labels").iterdir())


def test_label_clips_checks_models_and_resume_compares_ids(tmp_path):
    from fitting import label_clips
    from fitting.label import _labelled_with

    with pytest.raises(ValueError, match="left hand model"):
        label_clips([], tmp_path / "o", models={"right": mano.load_builtin("left")}, progress=False)
    with pytest.raises(ValueError, match="unknown sides"):
        label_clips([], tmp_path / "o", models={"Right": mano.load_builtin("right")}, progress=False)
    ids = {s: mano.model_id(mano.load_builtin(s)) for s in clips.SIDES}
    clips.write_meta(tmp_path / "c", fps=30.0, num_frames=4, mano_model={"right": {"id": ids["right"], "source": "builtin"}})
    assert _labelled_with(tmp_path / "c" / "meta.json", ids)
    assert not _labelled_with(tmp_path / "c" / "meta.json", {**ids, "right": "right-0000000000000000"})
    clips.write_meta(tmp_path / "old", fps=30.0, num_frames=4)  # older labels: of the built-in hand
    assert _labelled_with(tmp_path / "old" / "meta.json", ids)
    assert not _labelled_with(tmp_path / "absent" / "meta.json", ids)


# ----------------------------------------------------------------------------- esther evaluate


def _hand_folders(tmp_path, gt_model, pred_model, *, T=12, betas_offset=0.1, pose_offset=0.2):
    """A ground-truth clip and a prediction of it whose pose is off by `pose_offset` rad
    about x in every joint and whose betas are off by `betas_offset` (joints off by 5 mm)."""
    rng = np.random.default_rng(0)
    joints = rng.normal(scale=0.04, size=(T, 21, 3)) + np.array([0.0, 0.0, 0.4])
    gt = dict(
        global_orient=np.zeros((T, 3)), hand_pose=np.zeros((T, 15, 3)), betas=np.zeros(10), transl=joints[:, 0],
        joints=joints, onscreen=np.ones(T, bool),
    )  # fmt: skip
    clip = tmp_path / "gt" / "c0"
    clips.save_npz(clips.hand_file(clip, "right", "gt"), **gt)
    meta = {"fps": 30.0, "num_frames": T}
    if gt_model is not None:
        meta["mano_model"] = {"right": gt_model}
    clips.write_meta(clip, **meta)
    pred = dict(gt, valid=np.ones(T, bool), residual_px=np.zeros(T))
    pred["joints"] = joints + np.array([0.005, 0.0, 0.0])
    pred["hand_pose"] = gt["hand_pose"] + np.array([pose_offset, 0.0, 0.0])
    pred["betas"] = gt["betas"] + betas_offset
    labels = tmp_path / "pred" / "c0"
    clips.save_npz(clips.hand_file(labels, "right", "labels"), **pred)
    if pred_model is not None:
        (labels / "hands" / "right" / "quality.json").write_text(json.dumps({"mano_model": pred_model}))
    return tmp_path / "pred", tmp_path / "gt"


def _evaluate(pred, gt, out, *args):
    return cli.main(["evaluate", "--pred", str(pred), "--gt", str(gt), "--out", str(out), *args])


def test_evaluate_scores_parameters_of_one_model(tmp_path, capsys):
    builtin = {"id": mano.model_id(mano.load_builtin("right")), "source": "builtin"}
    pred, gt = _hand_folders(tmp_path, builtin, dict(builtin, source="/data/MANO_RIGHT.pkl"))
    assert _evaluate(pred, gt, tmp_path / "out", "--params", "require") == 0
    result = json.loads((tmp_path / "out" / "metrics.json").read_text())
    assert result["metrics"]["pose_angle"]["value"] == pytest.approx(np.degrees(0.2), rel=1e-4)
    assert result["metrics"]["betas_rmse"]["value"] == pytest.approx(0.1, rel=1e-5)
    assert result["metrics"]["mpjpe"]["value"] == pytest.approx(5.0, rel=1e-4)
    assert result["parameters"] == {"mode": "require", "metrics": ["pose_angle", "betas_rmse"], "compared": ["c0/right"], "not_compared": []}
    assert "not compared" not in capsys.readouterr().err


def test_evaluate_refuses_parameters_of_different_models(tmp_path, capsys):
    builtin = {"id": mano.model_id(mano.load_builtin("right")), "source": "builtin"}
    other = {"id": "right-0123456789abcdef", "source": "/data/MANO_RIGHT.pkl"}
    pred, gt = _hand_folders(tmp_path, builtin, other)
    assert _evaluate(pred, gt, tmp_path / "strict", "--params", "require") == 2
    err = capsys.readouterr().err
    assert "not comparable" in err and other["id"] in err and builtin["id"] in err and "--params auto|skip" in err
    assert not (tmp_path / "strict" / "metrics.json").exists()
    assert _evaluate(pred, gt, tmp_path / "auto") == 0  # the default: joints scored, parameters refused
    err = capsys.readouterr().err
    assert "not compared for 1 of 1 hands" in err and other["id"] in err
    result = json.loads((tmp_path / "auto" / "metrics.json").read_text())
    assert result["metrics"]["mpjpe"]["value"] == pytest.approx(5.0, rel=1e-4)
    assert "pose_angle" not in result["metrics"] and "betas_rmse" not in result["metrics"]
    assert result["parameters"]["compared"] == [] and result["parameters"]["not_compared"][0]["hand"] == "c0/right"
    assert _evaluate(pred, gt, tmp_path / "skip", "--params", "skip") == 0
    assert "not compared" not in capsys.readouterr().err
    result = json.loads((tmp_path / "skip" / "metrics.json").read_text())
    assert result["parameters"]["not_compared"] == [] and "pose_angle" not in result["metrics"]


def test_evaluate_treats_unrecorded_models_as_not_comparable(tmp_path, capsys):
    pred, gt = _hand_folders(tmp_path, {"id": mano.model_id(mano.load_builtin("right")), "source": "builtin"}, None)
    assert _evaluate(pred, gt, tmp_path / "out") == 0
    assert "the prediction records no MANO model" in capsys.readouterr().err
    result = json.loads((tmp_path / "out" / "metrics.json").read_text())
    assert "pose_angle" not in result["metrics"] and result["metrics"]["wrist"]["value"] == pytest.approx(5.0, rel=1e-4)
    assert _evaluate(pred, gt, tmp_path / "strict", "--params", "require") == 2
    assert "records no MANO model" in capsys.readouterr().err
