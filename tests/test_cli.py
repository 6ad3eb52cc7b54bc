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


TRAIN_FLAGS = (
    "--config", "--data", "--out", "--stage", "--init", "--resume", "--steps", "--batch", "--lr", "--warmup", "--ablation",
    "--triangulated-wrist-input", "--frames", "--frames-apart", "--targets", "--labels", "--val", "--validate-every",
    "--validation-windows", "--features", "--backbone-weights", "--bf16", "--no-bf16", "--ema", "--checkpoint-every",
    "--distributed", "--seed", "--backbone", "--freeze-backbone", "--no-freeze-backbone",
)  # fmt: skip
"""esther train's flags (users' scripts name them)."""


def test_train_flags_take_their_defaults_from_the_configs():
    """esther train keeps its flags; those of TrainConfig, DataConfig and ModelConfig fields
    default to the fields' defaults (a --frames left out: the named config's num_frames)."""
    import argparse
    import dataclasses

    from esther_jax import cli
    from esther_jax.model import ModelConfig
    from esther_jax.train import DataConfig, TrainConfig

    parser = cli.build_parser()
    train = next(a for a in parser._actions if isinstance(a, argparse._SubParsersAction)).choices["train"]
    assert set(TRAIN_FLAGS) <= {flag for action in train._actions for flag in action.option_strings}
    args = parser.parse_args(["train", "--data", "d", "--out", "o"])
    for cls in (TrainConfig, DataConfig):
        values = cli._config_values(args, cls)
        assert values and values == {f.name: f.default for f in dataclasses.fields(cls) if f.name in values}
    given_none = {"num_frames": None, "backbone": None, "freeze_backbone": None, "triangulated_wrist_input": None}
    assert cli._config_values(args, ModelConfig) == given_none  # a flag left out keeps the named config's value
    given = parser.parse_args(["train", "--data", "d", "--out", "o", "--lr", "1e-3", "--warmup", "7", "--ema", "0.99", "--stage", "image"])
    assert {k: cli._config_values(given, TrainConfig)[k] for k in ("learning_rate", "warmup_steps", "ema_decay", "stage")} == {
        "learning_rate": 1e-3, "warmup_steps": 7, "ema_decay": 0.99, "stage": "image"}  # fmt: skip
