"""Bad input from a careless or hostile user, at the library and the command line: each
case ends in a clear error that names the problem or in a correct flag, never in a
traceback, silently wrong output or lost labels.

The batch and concurrency cases replace the teacher by a stand-in (`_fake_label_hands`,
a few milliseconds per clip): what they test is the batch's bookkeeping, locking and
file handling, which do not depend on the fits (tests/test_fitting.py runs the teacher).
"""

import json
import os
import pathlib
import shutil
import subprocess
import sys
import textwrap
import zipfile

import jax.numpy as jnp
import numpy as np
import pytest

from esther_jax import cameras, cli, clips, mano
from esther_jax.eval import evaluate_folders
import fitting
from fitting import label as label_module

T = 8


def _tiny_clip(folder: pathlib.Path, seed: int = 0, frames: int = T, sides=("right",)) -> pathlib.Path:
    """A clip folder written directly (no teacher, no renderer): esther rig, random keypoints, ground truth."""
    rng = np.random.default_rng(seed)
    cameras.rig_preset("esther").to_json(folder / "rig.json")
    clips.write_meta(folder, fps=30.0, num_frames=frames, source="test")
    for side in sides:
        clips.save_npz(
            clips.hand_file(folder, side, "keypoints"),
            uv=rng.uniform(100, 900, size=(1, frames, 2, 21, 2)), conf=rng.uniform(0.5, 1, size=(1, frames, 2, 21)),
            box=np.tile([100.0, 100, 900, 900], (1, frames, 2, 1)), box_score=np.ones((1, frames, 2)),
        )  # fmt: skip
        joints = rng.normal(scale=0.05, size=(frames, 21, 3)) + [0, 0, 0.5]
        clips.save_npz(
            clips.hand_file(folder, side, "gt"),
            global_orient=np.zeros((frames, 3)), hand_pose=np.zeros((frames, 15, 3)), betas=np.zeros(10),
            transl=joints[:, 0], joints=joints, onscreen=np.ones(frames, bool),
        )  # fmt: skip
    return folder


def _fake_label_hands(models, rig, keypoints, fps, config=None, monocular=None, *, share_shape=True, predictions=None, pose_prior=None):
    """The teacher's interface and output format, without fitting: labels = a fixed hand (a prediction is not read)."""
    out = {}
    for side, kp in keypoints.items():
        frames = kp["uv"].shape[1]
        joints = np.zeros((frames, 21, 3), np.float32) + np.float32(0.5)
        params = mano.ManoParams(jnp.zeros((frames, 3)), jnp.zeros((frames, 15, 3)), jnp.zeros((frames, 10)), jnp.asarray(joints[:, 0]))
        labels = clips.Labels(params, jnp.asarray(joints), jnp.ones(frames, bool), jnp.ones(frames, bool), jnp.full(frames, jnp.nan))
        out[side] = labels, {"seconds": 0.001, "notes": [], "median_residual": float("nan"), "inf": float("inf")}
    return out


@pytest.fixture
def fake_teacher(monkeypatch):
    monkeypatch.setattr(label_module, "label_hands", _fake_label_hands)


# ----------------------------------------------------------------------------- clip files


def _edit_json(path: pathlib.Path, edit) -> None:
    data = json.loads(path.read_text())
    edit(data)
    path.write_text(json.dumps(data))


RIG_EDITS = {
    "width Infinity": (lambda r: r["cameras"]["left"].update(width=float("inf")), "'width' must be a positive whole number"),
    "width as text": (lambda r: r["cameras"]["left"].update(width="1920"), "'width' must be a positive whole number"),
    "width true": (lambda r: r["cameras"]["right"].update(width=True), "'width' must be a positive whole number"),
    "fractional height": (lambda r: r["cameras"]["left"].update(height=1200.5), "'height' must be a positive whole number"),
    "negative width": (lambda r: r["cameras"]["left"].update(width=-5), "'width' must be a positive whole number"),
    "fx as text": (lambda r: r["cameras"]["left"].update(fx="1000"), "'fx' must be a finite number"),
    "cx NaN": (lambda r: r["cameras"]["left"].update(cx=float("nan")), "'cx' must be a finite number"),
    "camera not an object": (lambda r: r["cameras"].update(left=[1, 2]), "must be an object"),
    "transform of text": (lambda r: r.update(T_left_right="identity"), "T_left_right"),
    "ragged transform": (lambda r: r.update(T_left_right=[[1, 0], [0, 1, 0]]), "T_left_right"),
}
META_EDITS = {
    "fps as text": (lambda m: m.update(fps="thirty"), "fps must be a positive finite number"),
    "fps Infinity": (lambda m: m.update(fps=float("inf")), "fps must be a positive finite number"),
    "fps zero": (lambda m: m.update(fps=0), "fps must be a positive finite number"),
    "num_frames text": (lambda m: m.update(num_frames="8"), "num_frames must be a positive whole number"),
    "num_frames fractional": (lambda m: m.update(num_frames=8.5), "num_frames must be a positive whole number"),
    "num_frames missing": (lambda m: m.pop("num_frames"), "'num_frames' is missing"),
}


@pytest.mark.parametrize("case", sorted(RIG_EDITS))
def test_bad_rig_json_values_are_named(tmp_path, case):
    clip = _tiny_clip(tmp_path / "c")
    edit, message = RIG_EDITS[case]
    _edit_json(clip / "rig.json", edit)
    with pytest.raises(ValueError, match=message):
        cameras.StereoRig.from_json(clip / "rig.json")


@pytest.mark.parametrize("case", sorted(META_EDITS))
def test_bad_meta_json_values_are_named(tmp_path, case):
    clip = _tiny_clip(tmp_path / "c")
    edit, message = META_EDITS[case]
    _edit_json(clip / "meta.json", edit)
    with pytest.raises(clips.ClipFormatError, match=message):
        clips.read_meta(clip)


def test_meta_that_is_not_an_object_or_not_json(tmp_path):
    clip = _tiny_clip(tmp_path / "c")
    (clip / "meta.json").write_text("[30, 8]")
    with pytest.raises(clips.ClipFormatError, match="must hold a JSON object"):
        clips.read_meta(clip)
    (clip / "meta.json").write_bytes(b"\xff\xfe{")
    with pytest.raises(clips.ClipFormatError, match="not valid JSON"):
        clips.read_meta(clip)


def _damage_deflate_stream(path: pathlib.Path) -> None:
    """Flip bytes inside the compressed data of the npz's first member (the zip
    directory stays intact, so the archive opens and reading the array fails)."""
    with zipfile.ZipFile(path) as z:
        info = z.infolist()[0]
    raw = bytearray(path.read_bytes())
    start = info.header_offset + 30 + len(info.filename.encode()) + len(info.extra)
    for i in range(start + 2, start + min(info.compress_size, 40)):
        raw[i] ^= 0x5A
    path.write_bytes(bytes(raw))


def test_npz_contents_are_validated(tmp_path):
    clip = _tiny_clip(tmp_path / "c")
    path = clips.hand_file(clip, "right", "keypoints")
    good = clips.load_npz(path, "keypoints")
    _damage_deflate_stream(path)
    with pytest.raises(clips.ClipFormatError, match="truncated, damaged or not an npz"):
        clips.load_npz(path, "keypoints")
    cases = {
        "conf above 1": (dict(conf=good["conf"] * 2), r"conf must lie in \[0, 1\]"),
        "negative conf": (dict(conf=good["conf"] - 1.5), r"conf must lie in \[0, 1\]"),
        "box_score above 1": (dict(box_score=good["box_score"] + 1), r"box_score must lie in \[0, 1\]"),
        "uv of text": (dict(uv=good["uv"].astype(str)), "uv must hold numbers"),
        "complex conf": (dict(conf=good["conf"].astype(complex)), "conf must hold numbers"),
        "NaN conf": (dict(conf=np.full_like(good["conf"], np.nan)), "conf contains NaN"),
        "frames disagree": (dict(conf=good["conf"][:, :-1]), "T is"),
        "no detector": ({k: v[:0] for k, v in good.items()}, r"holds no detector \(D = 0\)"),
    }
    for case, (change, message) in cases.items():
        clips.save_npz(path, **{**good, **change})
        with pytest.raises(clips.ClipFormatError, match=message):
            clips.load_npz(path, "keypoints")


def test_keypoint_contracts_of_the_teacher():
    from fitting.pipeline import check_keypoints, far_outside_image

    rng = np.random.default_rng(0)
    kp = dict(uv=rng.uniform(0, 900, (1, 4, 2, 21, 2)), conf=rng.uniform(0.4, 1, (1, 4, 2, 21)), box=np.zeros((1, 4, 2, 4)), box_score=np.ones((1, 4, 2)))
    assert check_keypoints(kp, 30.0) == (1, 4)
    with pytest.raises(ValueError, match=r"conf must lie in \[0, 1\]; 168 values do not \(from -0.897"):
        check_keypoints({**kp, "conf": kp["conf"] - 1.3}, 30.0)
    with pytest.raises(ValueError, match="must be real numbers"):
        check_keypoints({**kp, "uv": kp["uv"].astype(str)}, 30.0)
    with pytest.raises(ValueError, match="fps"):
        check_keypoints(kp, float("nan"))
    rig = cameras.rig_preset("esther")  # 1920 x 1200 both views
    uv = np.array([[[[0.0, 0.0], [1919.0, 1199.0], [-900.0, 50.0], [50.0, 1e30], [np.nan, 3.0], [2800.0, 600.0], [2900.0, 10.0]]] * 2])
    assert far_outside_image(rig, uv).tolist() == [[[False, False, False, True, False, False, True]] * 2]


# ----------------------------------------------------------------------------- geometry and parameters


def test_camera_inputs_need_the_right_trailing_dimension():
    rig = cameras.rig_preset("hot3d_aria")
    for camera in (cameras.rig_preset("esther").left, rig.left):
        with pytest.raises(ValueError, match=r"takes points \(m\) of shape \(\.\.\., 3\); got shape \(2,\)"):
            camera.project(jnp.array([0.1, 0.2]))
        with pytest.raises(ValueError, match=r"shape \(5, 4\)"):
            camera.project(jnp.ones((5, 4)))
        with pytest.raises(ValueError, match=r"takes pixels of shape \(\.\.\., 2\)"):
            camera.unproject(jnp.ones((5, 3)))
        with pytest.raises(ValueError, match=r"takes points"):
            camera.is_visible(jnp.ones(4))
    with pytest.raises(ValueError, match=r"StereoRig.project takes points"):
        rig.project(jnp.ones((7, 4)))
    assert rig.project(jnp.array([0.0, 0.0, 0.5])).shape == (2, 2)


# ----------------------------------------------------------------------------- label batches


def test_a_bad_clip_never_aborts_the_batch(tmp_path, fake_teacher):
    root = tmp_path / "clips"
    bad = {}
    bad["width_inf"] = _tiny_clip(root / "a_width_inf")
    _edit_json(bad["width_inf"] / "rig.json", lambda r: r["cameras"]["left"].update(width=float("inf")))
    bad["fps_text"] = _tiny_clip(root / "b_fps_text")
    _edit_json(bad["fps_text"] / "meta.json", lambda m: m.update(fps="thirty"))
    bad["deflate"] = _tiny_clip(root / "c_deflate")
    _damage_deflate_stream(clips.hand_file(bad["deflate"], "right", "keypoints"))
    bad["frames"] = _tiny_clip(root / "d_frames")
    _edit_json(bad["frames"] / "meta.json", lambda m: m.update(num_frames=T + 3))
    good = _tiny_clip(root / "z_good")
    result = label_module.label_clips(clips.list_clips(root), tmp_path / "labels", progress=False)
    errors = {pathlib.Path(f["clip"]).name: f["error"] for f in result["failed"]}
    assert [s["clip"] for s in result["labelled"]] == [good.name]
    assert "'width' must be a positive whole number" in errors["a_width_inf"]
    assert "fps must be a positive finite number" in errors["b_fps_text"]
    assert "damaged" in errors["c_deflate"]
    assert f"num_frames = {T + 3}, but hands/right/keypoints.npz has {T} frames" in errors["d_frames"]
    assert not any("partial" in p.name for p in (tmp_path / "labels").iterdir())
    # the stand-in's report holds NaN and infinity: quality.json is strict JSON all the same
    text = (tmp_path / "labels" / good.name / "hands" / "right" / "quality.json").read_text()
    quality = json.loads(text, parse_constant=lambda c: pytest.fail(f"quality.json holds {c}"))
    assert quality["median_residual"] is None and quality["inf"] is None
    meta = json.loads((tmp_path / "labels" / good.name / "meta.json").read_text())
    assert meta["source_clip"] == {"name": good.name, "digest": clips.clip_digest(good)}


def test_label_cli_usage_errors_come_before_any_work(tmp_path, capsys, fake_teacher):
    (tmp_path / "empty").mkdir()
    assert cli.main(["label", str(tmp_path / "empty"), "--out", str(tmp_path / "labels")]) == 2
    assert "no clip found in" in capsys.readouterr().err
    clip = _tiny_clip(tmp_path / "a" / "clip_x")
    twin = _tiny_clip(tmp_path / "b" / "clip_x", seed=1)
    assert cli.main(["label", str(tmp_path / "a"), str(tmp_path / "b"), "--out", str(tmp_path / "labels")]) == 2
    err = capsys.readouterr().err
    assert "'clip_x'" in err and str(clip) in err and str(twin) in err and "overwrite each other" in err
    assert not (tmp_path / "labels" / "clip_x").exists()
    a_file = tmp_path / "out.txt"
    a_file.write_text("not a folder")
    for command in (["label", str(clip)], ["synth", "--clips", "1"], ["evaluate", "--pred", str(tmp_path), "--gt", str(tmp_path)]):
        assert cli.main([*command, "--out", str(a_file)]) == 2
        assert "is a file, not a folder" in capsys.readouterr().err
        assert cli.main([*command, "--out", str(a_file / "sub")]) == 2
        assert "cannot be written" in capsys.readouterr().err
    assert a_file.read_text() == "not a folder"
    # a batch with a failing clip: the others are labelled, the failure printed, exit 1
    broken = _tiny_clip(tmp_path / "c" / "broken")
    _edit_json(broken / "meta.json", lambda m: m.update(fps="thirty"))
    assert cli.main(["label", str(clip), str(broken), "--out", str(tmp_path / "labels")]) == 1
    captured = capsys.readouterr()
    assert "FAILED" in captured.err and "thirty" in captured.err and "labelled 1 clips" in captured.out
    json.loads((tmp_path / "labels" / "label_summary.json").read_text(), parse_constant=pytest.fail)


def test_resume_redoes_labels_of_another_clip_with_the_same_name(tmp_path, fake_teacher):
    clip = _tiny_clip(tmp_path / "clips" / "clip_x", seed=0)
    first = label_module.label_clips([clip], tmp_path / "labels", progress=False)
    assert len(first["labelled"]) == 1
    again = label_module.label_clips([clip], tmp_path / "labels", resume=True, progress=False)
    assert again["skipped"] == ["clip_x"]
    shutil.rmtree(clip)
    _tiny_clip(tmp_path / "clips" / "clip_x", seed=5)  # another clip under the same name
    redone = label_module.label_clips([clip], tmp_path / "labels", resume=True, progress=False)
    assert [s["clip"] for s in redone["labelled"]] == ["clip_x"] and not redone["skipped"]
    meta = json.loads((tmp_path / "labels" / "clip_x" / "meta.json").read_text())
    assert meta["source_clip"]["digest"] == clips.clip_digest(clip)


def test_resume_redoes_labels_made_by_another_method(tmp_path, fake_teacher):
    clip = _tiny_clip(tmp_path / "clips" / "clip_x", seed=0)
    out = tmp_path / "labels"
    label_module.label_clips([clip], out, progress=False)
    meta_path = out / "clip_x" / "meta.json"
    assert json.loads(meta_path.read_text())["method"] == fitting.method_record(fitting.LabelConfig(), refined=False)
    # other settings: redone, and the labels record the new ones
    other = fitting.LabelConfig(steps=3)
    redone = label_module.label_clips([clip], out, resume=True, progress=False, config=other)
    assert [s["clip"] for s in redone["labelled"]] == ["clip_x"] and not redone["skipped"]
    assert json.loads(meta_path.read_text())["method"]["config"]["steps"] == 3
    assert label_module.label_clips([clip], out, resume=True, progress=False, config=other)["skipped"] == ["clip_x"]
    # labels of an older revision of the algorithm, or recording none (made before
    # revisions were recorded): redone
    for edit in (lambda m: m["method"].update(revision=fitting.TEACHER_REVISION - 1), lambda m: m.pop("method")):
        _edit_json(meta_path, edit)
        again = label_module.label_clips([clip], out, resume=True, progress=False, config=other)
        assert [s["clip"] for s in again["labelled"]] == ["clip_x"] and not again["skipped"]
        assert json.loads(meta_path.read_text())["method"] == fitting.method_record(other, refined=False)


_WORKER = textwrap.dedent(
    """
    import json, sys, time
    sys.path.insert(0, {tests!r})
    from fitting import label
    from test_hardening import _fake_label_hands

    def slow(*args, **kwargs):
        time.sleep(0.05)
        return _fake_label_hands(*args, **kwargs)

    label.label_hands = slow
    clips = sys.argv[2:]
    result = label.label_clips(clips, sys.argv[1], resume=True, progress=False)
    print(json.dumps({{"labelled": [s["clip"] for s in result["labelled"]], "skipped": result["skipped"], "failed": result["failed"]}}))
    """
)


def test_two_concurrent_label_runs_lose_nothing(tmp_path):
    """Two `label --resume` processes on one --out: every clip labelled exactly once,
    each hand's labels complete and readable, no temporary folder left behind."""
    clip_dirs = [_tiny_clip(tmp_path / "clips" / f"clip_{i:02d}", seed=i, sides=("right", "left")) for i in range(12)]
    out = tmp_path / "labels"
    script = _WORKER.format(tests=str(pathlib.Path(__file__).parent))
    env = {**os.environ, "PYTHONPATH": os.pathsep.join(filter(None, [str(pathlib.Path(__file__).parents[1]), os.environ.get("PYTHONPATH")]))}
    args = [sys.executable, "-c", script, str(out), *map(str, clip_dirs)]
    runs = [subprocess.Popen(args, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, env=env) for _ in range(2)]
    results = []
    for run in runs:
        stdout, stderr = run.communicate(timeout=300)
        assert run.returncode == 0, stderr
        results.append(json.loads(stdout.strip().splitlines()[-1]))
    labelled = [name for r in results for name in r["labelled"]]
    assert sorted(labelled) == sorted(c.name for c in clip_dirs), results  # each once, none lost
    assert not any(r["failed"] for r in results)
    for r in results:
        assert sorted(r["labelled"] + r["skipped"]) == sorted(c.name for c in clip_dirs)
    for clip in clip_dirs:
        for side in ("right", "left"):
            assert clips.Labels.from_npz(clips.hand_file(out / clip.name, side, "labels")).valid.all()
    assert sorted(p.name for p in out.iterdir() if p.is_dir()) == sorted(c.name for c in clip_dirs)


def test_the_clip_lock_excludes_a_second_holder(tmp_path):
    from esther_jax.files import exclusive_lock

    with exclusive_lock(tmp_path / ".x.lock") as first:
        assert first
        with exclusive_lock(tmp_path / ".x.lock", wait=False) as second:
            assert not second
    with exclusive_lock(tmp_path / ".x.lock", wait=False) as again:
        assert again


# ----------------------------------------------------------------------------- evaluation identity and reports


def test_evaluate_refuses_labels_of_another_clip(tmp_path, capsys, fake_teacher):
    gt = tmp_path / "gt"
    clip = _tiny_clip(gt / "clip_00000", seed=0)
    other = _tiny_clip(tmp_path / "elsewhere" / "clip_00000", seed=7)  # same name, another clip
    label_module.label_clips([other], tmp_path / "pred", progress=False)
    assert cli.main(["evaluate", "--pred", str(tmp_path / "pred"), "--gt", str(gt), "--out", str(tmp_path / "e")]) == 2
    assert "made from another clip than" in capsys.readouterr().err
    assert not (tmp_path / "e" / "metrics.json").exists()
    label_module.label_clips([clip], tmp_path / "pred", progress=False)  # the right clip: scored
    result = evaluate_folders(tmp_path / "pred", gt, tmp_path / "e", num_resamples=50)
    assert result["identity_unverified"] == [] and result["num_hands"] == 1
    # labels of another tool (no source record): scored, listed, warned about
    meta = json.loads((tmp_path / "pred" / "clip_00000" / "meta.json").read_text())
    meta.pop("source_clip")
    clips.write_meta(tmp_path / "pred" / "clip_00000", **meta)
    assert cli.main(["evaluate", "--pred", str(tmp_path / "pred"), "--gt", str(gt), "--out", str(tmp_path / "e")]) == 0
    assert "identity was not checked: clip_00000" in capsys.readouterr().err


def test_reports_are_strict_and_honest_about_one_clip(tmp_path, fake_teacher):
    gt = tmp_path / "gt"
    clip = _tiny_clip(gt / "clip_00000", sides=("right", "left"))
    gt_left = clips.load_npz(clips.hand_file(clip, "left", "gt"), "gt")
    gt_left["onscreen"][:] = False  # the left hand is never on screen: nothing to score
    clips.save_npz(clips.hand_file(clip, "left", "gt"), **gt_left)
    label_module.label_clips([clip], tmp_path / "pred", progress=False)
    evaluate_folders(tmp_path / "pred", gt, tmp_path / "e", num_resamples=50)
    text = (tmp_path / "e" / "metrics.json").read_text()
    result = json.loads(text, parse_constant=lambda c: pytest.fail(f"metrics.json holds {c}"))
    p_mpjpe = result["metrics"]["p_mpjpe"]
    assert p_mpjpe["num_clips"] == 1 and p_mpjpe["std"] is None and p_mpjpe["ci_low"] is None
    hands = {h["side"]: h for h in result["per_clip"]}
    right = hands["right"]["scores"]["p_mpjpe"]
    assert right["unit"] == "mm" == p_mpjpe["unit"] and right["value"] == pytest.approx(p_mpjpe["value"])
    assert hands["left"]["scores"]["p_mpjpe"] == {"value": None, "unit": "mm", "frames": 0}
    assert "± n/a" in (tmp_path / "e" / "table.md").read_text() and "± 0.00" not in (tmp_path / "e" / "table.md").read_text()


# ----------------------------------------------------------------------------- synthetic folders


def test_synth_keeps_its_record_true(tmp_path, capsys):
    from esther_jax.data.synth import SynthConfig, synthesize

    out = tmp_path / "clips"
    synthesize(out, 0, SynthConfig(num_frames=8), seed=3, progress=False)  # the record, no clip yet
    with pytest.raises(ValueError, match=r"seed differ; e.g. seed was 3, now 4"):
        synthesize(out, 0, SynthConfig(num_frames=8), seed=4, progress=False)
    with pytest.raises(ValueError, match=r"config.num_frames differ"):
        synthesize(out, 0, SynthConfig(num_frames=9), seed=3, progress=False)
    assert cli.main(["synth", "--out", str(out), "--clips", "0", "--frames", "8", "--seed", "5"]) == 2
    assert "other settings" in capsys.readouterr().err
    assert json.loads((out / "synth.json").read_text())["seed"] == 3
    synthesize(out, 0, SynthConfig(num_frames=8), seed=3, progress=False)  # same settings: fine
    (tmp_path / "old").mkdir()
    (tmp_path / "old" / "clip_00000").mkdir()
    with pytest.raises(ValueError, match="no synth.json"):
        synthesize(tmp_path / "old", 1, SynthConfig(num_frames=8), progress=False)

