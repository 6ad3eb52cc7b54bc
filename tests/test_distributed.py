"""Multi-process training, run: two CPU processes of `esther train --distributed` (JAX's
CPU collectives, the coordinator on the loopback address) train the weights one process
trains with the same global batch, only process 0 writes the run folder, and both resume."""

import os
import pathlib
import shutil
import socket
import subprocess
import sys

import equinox as eqx
import jax
import numpy as np
import pytest

from esther_jax import model as M
from esther_jax.data import synth

pytestmark = pytest.mark.slow
TRAIN = ["--config", "cpu-tiny", "--stage", "image", "--batch", "2", "--checkpoint-every", "2", "--validate-every", "1000"]


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def _train(data: pathlib.Path, out: pathlib.Path, steps: int, processes: int, *extra: str) -> list[str]:
    """`esther train` in `processes` processes (1: not distributed); their outputs."""
    command = [sys.executable, "-m", "esther_jax.cli", "train", "--data", str(data), "--out", str(out), "--steps", str(steps), *TRAIN, *extra]
    env = {**os.environ, "XLA_FLAGS": os.environ.get("XLA_FLAGS", "")}
    if processes == 1:
        runs = [subprocess.Popen(command, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True, env=env)]
    else:
        address = f"127.0.0.1:{_free_port()}"
        runs = [subprocess.Popen([*command, "--distributed"], stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True,
                                 env={**env, "JAX_COORDINATOR_ADDRESS": address, "JAX_NUM_PROCESSES": str(processes), "JAX_PROCESS_ID": str(i)})
                for i in range(processes)]  # fmt: skip
    outputs = [r.communicate(timeout=900)[0] for r in runs]
    assert all(r.returncode == 0 for r in runs), "\n".join(o[-3000:] for o in outputs)
    return outputs


def _weights(run: pathlib.Path) -> list[np.ndarray]:
    return [np.asarray(x) for x in jax.tree.leaves(eqx.filter(M.load(run / "model"), eqx.is_inexact_array))]


def _interrupted_after(run: pathlib.Path, step: int) -> None:
    """Make a finished run look interrupted just after its checkpoint at `step`: later
    checkpoints, the final network and later metrics gone, `latest` pointing at `step`."""
    checkpoints = run / "checkpoints"
    for later in (p for p in checkpoints.glob("step_*") if int(p.name.split("_")[1]) > step):
        shutil.rmtree(later)
    (checkpoints / "latest").write_text(f"step_{step:08d}")
    shutil.rmtree(run / "model")
    lines = (run / "metrics.jsonl").read_text().splitlines()[:step]
    (run / "metrics.jsonl").write_text("".join(line + "\n" for line in lines))


def test_two_processes_train_what_one_trains_and_resume(tmp_path):
    cfg = synth.SynthConfig(num_frames=16, crops=True, crop_size=64)
    data = tmp_path / "clips"
    for i in range(2):
        synth.write_clip(synth.make_clip(61, i, cfg), data / f"clip_{i:05d}")
    _train(data, tmp_path / "one", 4, 1)
    outputs = _train(data, tmp_path / "two", 4, 2)
    assert all("trained 4 steps (from step 0)" in o for o in outputs)
    for a, b in zip(_weights(tmp_path / "one"), _weights(tmp_path / "two"), strict=True):
        np.testing.assert_allclose(b, a, rtol=1e-5, atol=1e-5)
    # process 0 alone wrote the run folder: one metrics line per step, one set of checkpoints
    assert len((tmp_path / "two" / "metrics.jsonl").read_text().splitlines()) == 4
    assert sorted(p.name for p in (tmp_path / "two" / "checkpoints").glob("step_*")) == ["step_00000002", "step_00000004"]
    # interrupted after step 2, both processes resume from its checkpoint and end where one process ended
    _interrupted_after(tmp_path / "two", 2)
    outputs = _train(data, tmp_path / "two", 4, 2, "--resume")
    assert all("trained 4 steps (from step 2)" in o for o in outputs), outputs
    for a, b in zip(_weights(tmp_path / "one"), _weights(tmp_path / "two"), strict=True):
        np.testing.assert_allclose(b, a, rtol=1e-5, atol=1e-5)
    assert len((tmp_path / "two" / "metrics.jsonl").read_text().splitlines()) == 4
