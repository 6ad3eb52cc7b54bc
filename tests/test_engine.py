"""The data engine (`esther engine`): round 0 trains on the teacher's share, round 1 on the
teacher's labels plus the previous network's refined predictions; every step resumes
and every round keeps its outputs."""

import json

import pytest

from esther_jax import cli, engine
from esther_jax.data import motion, synth
from esther_jax.files import exclusive_lock

FRAMES = 16  # padded to the teacher's length bucket of tests/test_fitting.py and test_refine.py (32): compiled once
SMOKE = engine.EngineConfig(config="cpu-tiny", teacher_share=0.3, stage1_steps=0, stage2_steps=2, batch=2)


@pytest.fixture(scope="module")
def collection(tmp_path_factory):
    """Three raw clips (keypoints, crops, and a ground truth the engine only scores with) and one held out."""
    cfg = synth.SynthConfig(num_frames=FRAMES, crops=True, crop_size=64, detector_preset="easy",
                            motion_config=motion.MotionConfig(two_hands_probability=1.0, leave_view_probability=0.0))  # fmt: skip
    root = tmp_path_factory.mktemp("engine")
    raw = [synth.write_clip(synth.make_clip(31, i, cfg), root / "raw" / f"clip_{i:05d}") for i in range(3)]
    held_out = synth.write_clip(synth.make_clip(32, 0, cfg), root / "val" / "clip_00000")
    return raw, held_out


def test_teacher_share_is_a_seeded_draw_independent_of_order():
    names = [f"clip_{i:05d}" for i in range(10)]
    share = engine.teacher_share(names, 0.2, seed=3)
    assert len(share) == 2 and set(share) <= set(names)
    assert engine.teacher_share(names[::-1], 0.2, seed=3) == share
    assert engine.teacher_share(names, 0.01, seed=0) and len(engine.teacher_share(names, 1.0, seed=0)) == 10
    with pytest.raises(ValueError, match="teacher_share"):
        engine.EngineConfig(teacher_share=0.0)


def test_two_rounds_resume_after_an_interruption_and_keep_every_round(collection, tmp_path, monkeypatch, capsys):
    raw, held_out = collection
    out = tmp_path / "engine"
    [r0] = engine.run_engine(raw, out, SMOKE, rounds=1, val_dirs=[held_out], progress=False)
    assert r0["round"] == 0 and r0["teacher_clips"] == 1 and r0["refined_clips"] == 0 and not r0["failed"]
    taught = json.loads((out / "engine.json").read_text())["teacher_clips"]
    assert sorted(p.name for p in (out / "round_000" / "labels").iterdir()) == taught
    assert 0.0 < r0["labels"]["all"]["coverage"] < 0.5  # one clip of three labelled
    assert r0["network"]["both"]["windows"] > 0 and "intervals" in r0["network"]["both"]

    # round 1 interrupted after its refinement, before training ends
    def interrupted(*args, **kwargs):
        raise KeyboardInterrupt

    monkeypatch.setattr(engine.train_lib, "train_stages", interrupted)
    with pytest.raises(KeyboardInterrupt):
        engine.run_engine(raw, out, SMOKE, rounds=2, val_dirs=[held_out], progress=False)
    monkeypatch.undo()
    r1_dir = engine.round_dir(out, 1)
    assert not (r1_dir / "round.json").exists()
    refined = sorted(r1_dir.glob("refined/*/hands/*/labels.npz"))
    assert refined and len({p.parts[-4] for p in refined}) == 2
    stamps = {p: p.stat().st_mtime_ns for p in [*refined, *r1_dir.glob("predictions/*/meta.json"), *(out / "teacher").glob("*/meta.json"),
                                                  engine.round_dir(out, 0) / "round.json"]}  # fmt: skip

    # resumed through the CLI: nothing finished is redone
    code = cli.main(["engine", *map(str, raw), "--out", str(out), "--rounds", "2", "--val", str(held_out), "--config", "cpu-tiny",
                     "--teacher-share", "0.3", "--stage1-steps", "0", "--stage2-steps", "2", "--batch", "2"])  # fmt: skip
    assert code == 0, capsys.readouterr().err
    assert "round 1: 1 teacher + 2 refined clips" in capsys.readouterr().out
    assert all(p.stat().st_mtime_ns == t for p, t in stamps.items()), "finished work was redone"
    r1 = json.loads((r1_dir / "round.json").read_text())
    assert r1["labels"]["all"]["coverage"] > r0["labels"]["all"]["coverage"]
    assert r1["labels"]["refined"]["accepted"] > 0 and r1["cost"]["refined"]["hand_frames"] == 2 * 2 * FRAMES and r1["cost"]["refined"]["hands"] == 4
    assert r1["cost"]["refined"]["steady_hand_frames_per_s"] > 0
    assert r1["model"].startswith(str(r1_dir)) and (r1_dir / "run" / "stage2" / "model").is_dir()
    for name in ("labels", "predictions", "refined", "run"):
        assert (r1_dir / name).is_dir()
    assert (engine.round_dir(out, 0) / "run" / "stage2" / "model").is_dir()  # round 0's network kept

    # a resume with another plan, and a second engine on the folder, are refused
    with pytest.raises(ValueError, match="started with other"):
        engine.run_engine(raw, out, engine.EngineConfig(config="cpu-tiny", teacher_share=0.5, stage1_steps=0, stage2_steps=2), rounds=2)
    with exclusive_lock(out / ".engine.lock"), pytest.raises(ValueError, match="another engine"):
        engine.run_engine(raw, out, SMOKE, rounds=2)
