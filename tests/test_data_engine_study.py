"""The data-engine study's statistics (`esther_jax.studies.data_engine`): refined labels
against the teacher's on the frames both accepted, the round tables and the targets. (The
notebook runs at the smoke scale in tests/test_studies.py.)"""

import numpy as np
import jax.numpy as jnp
import pytest

from esther_jax import clips, mano
from esther_jax.data import synth
from esther_jax.studies import data_engine


def _labels(gt: dict, offset_m: float, valid: np.ndarray) -> clips.Labels:
    """The truth's joints moved by `offset_m` along x for every joint but the wrist (a
    P-MPJPE-visible error of that size on 20 of 21 joints), accepted on `valid`."""
    T = gt["joints"].shape[0]
    joints = np.asarray(gt["joints"], np.float32).copy()
    joints[:, 1:, 0] += offset_m
    params = mano.ManoParams(*(jnp.asarray(gt[k], jnp.float32) for k in ("global_orient", "hand_pose")),
                              jnp.broadcast_to(jnp.asarray(gt["betas"], jnp.float32), (T, 10)), jnp.asarray(gt["transl"], jnp.float32))  # fmt: skip
    return clips.Labels(params, jnp.asarray(joints), jnp.asarray(gt["onscreen"]), jnp.asarray(valid), jnp.zeros(T, jnp.float32))


def test_same_frames_compares_on_the_frames_both_accepted(tmp_path):
    clip = synth.write_clip(synth.make_clip(5, 0, synth.SynthConfig(num_frames=16)), tmp_path / "raw" / "clip_00000")
    counted, ours_err, teacher_err = 0, [], []
    for side in clips.SIDES:
        path = clips.hand_file(clip, side, "gt")
        if not path.is_file():
            continue
        gt = clips.load_npz(path, "gt")
        onscreen = np.asarray(gt["onscreen"], bool)
        ours_valid, teacher_valid = onscreen.copy(), onscreen.copy()
        ours_valid[:4] = False  # frames only the teacher accepted: not compared
        _labels(gt, 0.004, ours_valid).to_npz(clips.hand_file(tmp_path / "refined" / clip.name, side, "labels"))
        _labels(gt, 0.001, teacher_valid).to_npz(clips.hand_file(tmp_path / "teacher" / clip.name, side, "labels"))
        counted += int((onscreen & ours_valid).sum())
    assert counted > 0
    result = data_engine.same_frames([clip], tmp_path / "refined", tmp_path / "teacher", {clip.name})
    assert result["frames"] == counted
    assert result["p_mpjpe_mm"] > result["teacher_p_mpjpe_mm"] > 0
    assert result["p_mpjpe_difference_mm"] == pytest.approx(result["p_mpjpe_mm"] - result["teacher_p_mpjpe_mm"])
    assert result["p_mpjpe_difference_mm"] > 1.0  # 4 mm against 1 mm on 20 joints: the refined labels are worse
    assert data_engine.same_frames([clip], tmp_path / "refined", tmp_path / "teacher", set()) == {}


def _round(number, teacher_rate, refined_rate, difference, p_mpjpe, span):
    labels = {"coverage": 0.5, "accepted": 10, "p_mpjpe_mm": 3.0, "wrist_mm": 4.0, "worse_than_15mm": 0}
    record = {"round": number, "labels": {"teacher": labels, "refined": labels if number else {}, "all": labels},
              "cost": {"teacher": {"steady_hand_frames_per_s": teacher_rate}, "refined": {"steady_hand_frames_per_s": refined_rate}},
              "network": {"both": {"p_mpjpe_mm": p_mpjpe, "intervals": {"p_mpjpe_mm": span}}}}  # fmt: skip
    if number:
        record["same_frames"] = {"p_mpjpe_difference_mm": difference}
    return record


def test_targets_and_tables():
    met = {"seeds": {0: [_round(0, 10.0, None, None, 40.0, [38.0, 42.0]), _round(1, 10.0, 60.0, 0.5, 30.0, [28.0, 32.0])]}}
    assert data_engine.verdict(met) == {"throughput_ratio": [6.0], "throughput_target_met": True, "same_frames_difference_mm": [0.5],
                                        "same_frames_target_met": True, "round1_better": [True], "round1_target_met": True}  # fmt: skip
    overlapping = {"seeds": {0: [_round(0, 10.0, None, None, 40.0, [35.0, 45.0]), _round(1, 10.0, 12.0, 2.0, 38.0, [34.0, 42.0])]}}
    check = data_engine.verdict(overlapping)
    assert not (check["throughput_target_met"] or check["same_frames_target_met"] or check["round1_target_met"])
    table = data_engine.round_table(met)
    assert "| 1 | refined | 50.00 | 3.00 | 4.00 | 0.00 of 10.00 | 0.50 | 60.00 |" in table
    assert "| 1 | 0 | both | 30.0 [28.0, 32.0] |" in data_engine.network_table(met)
