"""The teacher's validation runner (studies.teacher_validation) at the smallest scale: one clip of
16 frames (the teacher's 32-frame bucket, shared with tests/test_fitting.py through the
persistent compilation cache) under two detector presets of the test-set rig."""

import json

import numpy as np
import pytest

import fitting
from esther_jax import clips
from esther_jax.studies import teacher_validation as validation

CONDITIONS = (("esther_mocap", "default"), ("esther_mocap", "clean"))
FRAMES = 16


@pytest.fixture(scope="module")
def validated(tmp_path_factory):
    root = tmp_path_factory.mktemp("validation")
    return root, validation.run_validation(root, CONDITIONS, num_clips=1, num_frames=FRAMES, num_resamples=200)


def test_results_have_the_schema_and_sane_values(validated):
    root, results = validated
    assert [r["condition"] for r in results] == ["esther_mocap_default", "esther_mocap_clean"]
    for r in results:
        assert r["condition"] == f"{r['rig']}_{r['detector']}" and (r["rig"], r["detector"]) in CONDITIONS
        assert (r["num_clips"], r["num_frames"]) == (1, FRAMES)
        assert r["label"]["labelled"] == ["clip_00000"] and not r["label"]["failed"]
        for metric in ("p_mpjpe", "pa_mpjpe", "wrist", "jitter", "gt_jitter"):
            value = r["accuracy"][metric]["value"]
            assert np.isfinite(value) and value > 0, (r["condition"], metric, value)
        assert r["accuracy"]["p_mpjpe"]["unit"] == "mm" and r["accuracy"]["jitter"]["unit"] == "m/s^2"
        assert r["accuracy"]["p_mpjpe"]["value"] < 50.0 and 0.5 < r["coverage"] <= 1.0
        counts = r["hand_frames"]
        assert counts["frames"] == FRAMES * counts["hands"] and counts["scored"] <= min(counts["onscreen"], counts["valid"])
        frames = r["frames"]
        assert all(v.shape == (counts["frames"],) for v in frames.values())
        table = r["label_quality"]["all"]["table"]
        assert set(validation.QUANTITY_LABELS) == set(table)
        for key, row in table.items():
            assert row["median"] >= 0 and np.isfinite(row["mean"]) and row["p90"] >= row["median"], key
        assert 0.2 < table["hand_depth_m"]["median"] < 0.8
        # z^2 / (f b) on the parallel pinhole rig (f = 623 px, b = 62 mm), z the median depth
        z = table["hand_depth_m"]["median"]
        assert table["depth_per_pixel_mm"]["median"] == pytest.approx(z * z / (623.0 * 0.062) * 1000.0, rel=0.05)
    recorded = json.loads((root / "validation.json").read_text(), parse_constant=pytest.fail)  # strict JSON
    assert [r["condition"] for r in recorded] == [r["condition"] for r in results] and "frames" not in recorded[0]
    assert (root / "esther_mocap_default" / "eval" / "metrics.json").is_file()


def test_hand_frames_reproduce_the_teachers_quality_record(validated):
    """The per-frame recomputation (the views observing the hand, the hand's length) gives
    the appendix-N table the teacher wrote into each hand's quality.json."""
    root, _ = validated
    folder = root / "esther_mocap_default"
    for clip in clips.list_clips(folder / "clips"):
        for side in clips.SIDES:
            if not clips.hand_file(clip, side, "gt").is_file():
                continue
            frames = validation.hand_frames(clip, folder / "labels" / clip.name, side)
            ours = fitting.label_quality({k: frames[k] for k in validation.QUALITY_KEYS}, frames["observed"], frames["stereo"], frames["valid"])
            recorded = json.loads((folder / "labels" / clip.name / "hands" / side / "quality.json").read_text())
            for group in ("stereo", "monocular", "all"):
                assert ours[group]["passing"] == recorded[group]["passing"]
                for key in validation.QUALITY_KEYS:
                    a, b = ours[group]["table"][key], recorded[group]["table"][key]
                    assert (a is None) == (b is None), (side, group, key)
                    if a is not None:
                        assert a == pytest.approx(b, rel=1e-3, abs=1e-4), (side, group, key)


def test_the_band_is_ordered_and_the_check_is_honest(validated):
    _, results = validated
    for r in results:
        z = r["label_quality"]["all"]["table"]["hand_depth_m"]["median"]
        for band in r["band"].values():
            assert 0 <= band["lower_mm"] <= band["upper_mm"] <= band["worst_mm"]
            assert band["worst_mm"] == pytest.approx(np.sqrt(2) * band["upper_mm"], rel=1e-4, abs=1e-6)  # 2 r vs sqrt(2) r
            if band["lower_mm"] > 1e-3:  # sqrt(2) r z^2 / (f b) over r z / f: sqrt(2) z / b on this rig (b = 62 mm)
                assert band["upper_mm"] / band["lower_mm"] == pytest.approx(np.sqrt(2) * z / 0.062, rel=0.15)
            for metric, check in band["metrics"].items():
                measured = r["accuracy"][metric]["value"]
                assert check["measured_mm"] == measured
                assert check["inside"] == (band["lower_mm"] <= measured <= band["upper_mm"])
                assert check["position"] == ("inside" if check["inside"] else "below" if measured < band["lower_mm"] else "above")
                assert check["inside_worst_case"] == (band["lower_mm"] <= measured <= band["worst_mm"])
                assert 0.0 <= check["share_of_frames_inside"] <= 1.0
            assert band["inside"] == all(c["inside"] for c in band["metrics"].values())
    default, clean = results
    # exact detections: no detector noise, so its band shrinks to zero and no error is inside it
    assert clean["band"]["detector"]["upper_mm"] < 1e-3 and clean["band"]["detector"]["inside"] is False
    assert clean["label_quality"]["all"]["table"]["detector_error_px"]["p90"] < 1e-2
    # the label's 2D error against the truth is then the residual itself
    frames = clean["frames"]
    ok = frames["valid"]
    np.testing.assert_allclose(frames["label_2d_error_px"][ok], frames["reprojection_residual_px"][ok], rtol=1e-3, atol=1e-2)
    assert default["label_quality"]["all"]["table"]["detector_error_px"]["median"] > 1.0


def test_tables_and_figures(validated, tmp_path):
    _, results = validated
    table = validation.validation_table(results)
    lines = table.strip().splitlines()
    assert len(lines) == 2 + len(results) and all(line.count("|") == lines[0].count("|") for line in lines)
    for line, r in zip(lines[2:], results):
        assert line.startswith(f"| {r['condition']} |")
    assert validation.validation_table(results, "detector") != table
    quality = validation.label_quality_table(results[0])
    assert quality.count("\n| ") == 1 + len(validation.QUANTITY_LABELS) and "Depth per pixel of disparity" in quality
    assert validation.plot_band_check(results, tmp_path / "band.png").stat().st_size > 0
    assert validation.plot_error_vs_depth(results, tmp_path / "depth.png").stat().st_size > 0


def test_resume_keeps_finished_work(validated):
    root, results = validated
    labels = clips.hand_file(root / "esther_mocap_default" / "labels" / "clip_00000", "right", "labels")
    stamp = labels.stat().st_mtime_ns
    again = validation.run_validation(root, CONDITIONS[:1], num_clips=1, num_frames=FRAMES, num_resamples=200)
    assert again[0]["synth"]["made"] == 0 and again[0]["label"]["skipped"] == ["clip_00000"] and not again[0]["label"]["labelled"]
    assert labels.stat().st_mtime_ns == stamp
    assert again[0]["accuracy"]["p_mpjpe"]["value"] == results[0]["accuracy"]["p_mpjpe"]["value"]
    assert again[0]["band"] == results[0]["band"]
    with pytest.raises(ValueError, match="other settings"):  # the record of the held-out clips stays true
        validation.run_validation(root, CONDITIONS[:1], num_clips=1, num_frames=FRAMES + 1)
    grown = validation.run_validation(root, CONDITIONS[:1], num_clips=2, num_frames=FRAMES, num_resamples=200)
    assert grown[0]["synth"]["made"] == 1 and grown[0]["label"]["labelled"] == ["clip_00001"] and grown[0]["label"]["skipped"] == ["clip_00000"]
    assert labels.stat().st_mtime_ns == stamp and grown[0]["hand_frames"]["frames"] > again[0]["hand_frames"]["frames"]
    with pytest.raises(ValueError, match="holds 2 clips, 1 were asked for"):  # results would not be of the clips asked for
        validation.run_validation(root, CONDITIONS[:1], num_clips=1, num_frames=FRAMES)


def test_bad_conditions_are_refused_before_any_work(tmp_path):
    with pytest.raises(ValueError, match="unknown rig preset 'nope'"):
        validation.run_validation(tmp_path / "v", [("nope", "default")])
    with pytest.raises(ValueError, match="unknown detector preset 'perfect'"):
        validation.run_validation(tmp_path / "v", [("esther", "perfect")])
    with pytest.raises(ValueError, match="repeat"):
        validation.run_validation(tmp_path / "v", [("esther", "hard"), ("esther", "hard")])
    assert not (tmp_path / "v").exists()
