import json

import pytest


@pytest.mark.slow
def test_demo_labels_evaluates_and_draws(tmp_path, capsys):
    from esther_jax import cli

    assert cli.main(["demo", "--out", str(tmp_path), "--frames", "32"]) == 0
    printed = capsys.readouterr().out
    assert "P-MPJPE" in printed and "pass rate" in printed and "overlays" in printed
    metrics = json.loads((tmp_path / "evaluation" / "metrics.json").read_text())
    assert metrics["metrics"]["p_mpjpe"]["value"] < 15.0  # mm, on 32 frames
    assert (tmp_path / "overlays.png").stat().st_size > 50_000
    assert (tmp_path / "right_hand_fitted.glb").exists()
