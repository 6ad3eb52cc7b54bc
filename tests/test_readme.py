"""The README's code runs as written: its Python blocks in order, in a folder holding
the clip its text says to make (`esther synth --out clips --clips 1 --frames 16 --crops --crop-size 64`)."""

import pathlib
import re

import jax
import numpy as np
import pytest

README = pathlib.Path(__file__).resolve().parents[1] / "README.md"


@pytest.mark.slow
def test_readme_python_blocks_run_on_a_synthetic_clip(tmp_path, monkeypatch, capsys):
    from esther_jax import cli

    text = README.read_text()
    command = "esther synth --out clips --clips 1 --frames 16 --crops --crop-size 64"
    assert command in text
    monkeypatch.chdir(tmp_path)
    assert cli.main(command.split()[1:]) == 0
    blocks = re.findall(r"```python\n(.*?)```", text, flags=re.S)
    assert len(blocks) >= 4
    namespace: dict = {}
    for number, block in enumerate(blocks, 1):
        exec(compile(block, f"README.md python block {number}", "exec"), namespace)  # noqa: S102
    labels = namespace["labels"]
    assert labels.joints.shape == (16, 21, 3) and labels.params.hand_pose.shape == (16, 15, 3) and labels.stereo.dtype == bool
    again = namespace["clips"].Labels.from_npz(tmp_path / "my_labels.npz")  # the file round-trips
    for a, b in zip(jax.tree.leaves(labels), jax.tree.leaves(again)):
        assert a.dtype == b.dtype
        np.testing.assert_array_equal(a, b)  # NaN residuals (unobserved frames) compare equal
    assert namespace["pred"].joints.shape == (1, 16, 21, 3)
    assert bool(namespace["tri"].valid)
    counts = namespace["M"].parameter_counts("paper")  # what the README says they are
    assert f"{counts['image_encoder'] / 1e6:.1f}M / {counts['motion_encoder'] / 1e6:.1f}M / {counts['fusion_decoder'] / 1e6:.1f}M" in text
    assert str(counts["trainable"]) in capsys.readouterr().out
