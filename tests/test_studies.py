"""The studies: their statistics (`esther_jax.studies`) and every notebook executed at the smoke
scale (as a script in this process, sharing one study root, so the networks they compare
are trained once), one of them also through a Jupyter kernel."""

import dataclasses
import json
import os
import pathlib
import runpy

import jax.numpy as jnp
import numpy as np
import pytest

from esther_jax import metrics
from esther_jax import studies

NOTEBOOKS = sorted((pathlib.Path(__file__).resolve().parents[1] / "notebooks").glob("[0-9][0-9]_*.py"))
REPORT_KEYS = {"study", "scale", "command", "seconds", "git_revision", "verdict", "results"}


def _samples(z_gt, z_pred, windows):
    return studies.DepthSamples(np.asarray(z_pred), np.asarray(z_gt), np.full(len(z_gt), 0.09), np.asarray(windows))


def test_depth_binding_separates_systematic_from_random_error():
    rng = np.random.default_rng(0)
    z = rng.uniform(0.2, 0.8, 200)
    windows = np.repeat(np.arange(20), 10)
    exact = studies.depth_binding(_samples(z, z, windows), resamples=200)
    assert exact["correlation"] == pytest.approx(1.0, abs=1e-6) and exact["random_mm"] < 1e-3 and exact["systematic_mm"] < 1e-3
    compressed = studies.depth_binding(_samples(z, 0.5 * z + 0.2, windows), resamples=200)
    assert compressed["slope"] == pytest.approx(0.5, abs=1e-5) and compressed["intercept_m"] == pytest.approx(0.2, abs=1e-5)
    assert compressed["random_mm"] < 1e-2 and compressed["systematic_mm"] > 50
    noisy = studies.depth_binding(_samples(z, z + rng.normal(0, 0.02, 200), windows), resamples=500)
    assert 10 < noisy["random_mm"] < 30 and noisy["intervals"]["random_mm"][0] < noisy["random_mm"] < noisy["intervals"]["random_mm"][1]
    assert noisy["windows"] == 20 and noisy["frames"] == 200


def test_weighted_scatter_of_one_draw_per_window_is_depth_scatter():
    z = jnp.linspace(0.2, 0.9, 30)
    zp = z * 0.9 + 0.03 * jnp.sin(40 * z)
    window = jnp.repeat(jnp.arange(6), 5)
    stats = studies._resampled_scatter(zp, z, window, jnp.arange(6)[None])[0]
    ref = metrics.depth_scatter(zp, z)
    np.testing.assert_allclose(stats, [ref.correlation, ref.random_mm, ref.systematic_mm, ref.slope], rtol=1e-4)


def test_depth_binding_with_too_few_frames_reports_counts():
    result = studies.depth_binding(_samples([0.3, 0.4], [0.3, 0.4], [0, 1]))
    assert result == {"frames": 2, "windows": 2}


def test_separated_and_table():
    assert studies.separated([1.0, 2.0], [2.5, 3.0]) is True
    assert studies.separated([1.0, 2.6], [2.5, 3.0]) is False
    assert studies.separated(None, [1.0, 2.0]) is None
    text = studies.table([{"m": "a", "x": 12.345, "y": None, "intervals": {"x": [11.0, 13.5]}}], [("x", "X"), ("y", "Y")], first="m")
    assert text.splitlines()[2] == "| a | 12.3 [11.0, 13.5] | n/a |"


def test_scale_from_env(monkeypatch):
    monkeypatch.setenv(studies.SCALE_ENV, "full")
    assert studies.scale_from_env().model == "cpu-small"
    monkeypatch.setenv(studies.SCALE_ENV, "huge")
    with pytest.raises(ValueError, match="smoke"):
        studies.scale_from_env()


@pytest.fixture(scope="module")
def study_env(tmp_path_factory):
    """One smoke-scale study root for every notebook of this module."""
    root = tmp_path_factory.mktemp("studies")
    env = {studies.SCALE_ENV: "smoke", studies.ROOT_ENV: str(root / "root"), studies.OUT_ENV: str(root / "reports")}
    saved = {k: os.environ.get(k) for k in env}
    os.environ.update(env)
    yield root / "reports"
    for k, v in saved.items():
        if v is None:
            os.environ.pop(k, None)
        else:
            os.environ[k] = v


def _check_report(out: pathlib.Path, study: str) -> dict:
    record = json.loads((out / f"{study}.json").read_text())
    assert REPORT_KEYS <= set(record) and record["scale"]["name"] == "smoke" and record["seconds"] > 0
    text = (out / f"{study}.md").read_text()
    assert text.startswith("# ") and record["verdict"] in text and "## How this was made" in text
    for image in (line.split("](", 1)[1].rstrip(")") for line in text.splitlines() if line.startswith("![")):
        assert (out / image).is_file()
    return record


STUDY_OF = {
    "01_size_depth_binding": "size_depth_binding", "02_missing_views": "missing_views", "03_dropped_frames": "dropped_frames",
    "04_corruptions": "corruptions", "05_undistortion": "undistortion", "06_gate": "gate", "07_ablations": "ablations",
    "08_teacher_validation": "teacher_validation", "09_data_engine": "data_engine",
}  # fmt: skip


KERNEL_NOTEBOOK = "06_gate"
"""Run in a Jupyter kernel (`test_notebook_runs_in_a_jupyter_kernel`) instead of in-process."""


@pytest.mark.parametrize("notebook", [p for p in NOTEBOOKS if p.stem != KERNEL_NOTEBOOK], ids=lambda p: p.stem)
def test_notebook_runs_at_smoke_scale(notebook, study_env):
    runpy.run_path(str(notebook), run_name="__main__")
    record = _check_report(study_env, STUDY_OF[notebook.stem])
    assert record["results"]


def test_ablation_rows_are_chosen_by_name_and_kept_across_sittings(study_env, monkeypatch, tmp_path):
    """`ESTHER_ABLATION_ROWS` picks study 07's rows (the full model always scored), a
    misspelt row is refused by name before anything is trained or scored, and a later
    sitting keeps the earlier report's rows when its full model reproduces that one's."""
    notebook = next(p for p in NOTEBOOKS if p.stem == "07_ablations")
    monkeypatch.setenv(studies.OUT_ENV, str(tmp_path))
    monkeypatch.setenv(studies.ABLATION_ROWS_ENV, "no-plucker,no-such-row")
    with pytest.raises(ValueError, match=r"unknown rows \['no-such-row'\]"):
        runpy.run_path(str(notebook), run_name="__main__")
    monkeypatch.setenv(studies.ABLATION_ROWS_ENV, "anchored-wrist")
    runpy.run_path(str(notebook), run_name="__main__")
    assert list(_check_report(tmp_path, "ablations")["results"]["rows"]) == ["esther", "anchored-wrist"]
    monkeypatch.setenv(studies.ABLATION_ROWS_ENV, "no-flow-token")
    runpy.run_path(str(notebook), run_name="__main__")
    record = _check_report(tmp_path, "ablations")
    assert list(record["results"]["rows"]) == ["esther", "no-flow-token", "anchored-wrist"]  # table order
    assert set(record["results"]["trained_at"]) == set(record["results"]["rows"])
    assert "1 kept from an earlier sitting" in record["verdict"]
    assert f"{studies.ABLATION_ROWS_ENV}=no-flow-token" in record["command"]


def test_earlier_rows_are_kept_only_when_the_reference_reproduces(tmp_path):
    scale = studies.SCALES["smoke"]
    row = lambda mm, lo, hi: {"mpjpe_mm": mm, "p_mpjpe_mm": mm, "wrist_mm": mm, "windows": 4,  # noqa: E731
                              "intervals": {k: [lo, hi] for k in studies.REPRODUCED_KEYS}}  # fmt: skip
    earlier = {"esther": row(10.0, 9.0, 11.0), "no-plucker": row(20.0, 18.0, 22.0)}
    studies.write_report(tmp_path, "t", title="t", verdict="v", results={"rows": earlier}, scale=scale, seconds=1.0)
    kept, trained_at = studies.earlier_rows(tmp_path, "t", scale, "esther", row(10.5, 9.6, 11.4))
    assert kept == earlier and set(trained_at) == set(earlier)
    assert studies.earlier_rows(tmp_path, "t", scale, "esther", row(11.5, 11.1, 12.0))[0] == {}  # 10.0 outside [11.1, 12.0]
    assert studies.earlier_rows(tmp_path, "t", scale, "esther", {**row(10.0, 9.0, 11.0), "windows": 5})[0] == {}
    assert studies.earlier_rows(tmp_path, "t", studies.SCALES["full"], "esther", row(10.0, 9.0, 11.0))[0] == {}
    assert studies.earlier_rows(tmp_path, "missing", scale, "esther", row(10.0, 9.0, 11.0)) == ({}, {})


def test_training_minutes_sum_the_logged_steps_of_both_stages(tmp_path, monkeypatch):
    monkeypatch.setenv(studies.ROOT_ENV, str(tmp_path))
    scale = studies.SCALES["full"]
    assert studies.training_minutes(scale, "esther") is None
    for stage, rates in (("stage1", [4.0, 8.0]), ("stage2", [2.0])):
        run = tmp_path / "runs" / "esther" / stage
        run.mkdir(parents=True)
        (run / "config.json").write_text(json.dumps({"train": {"batch": 8}}))
        (run / "metrics.jsonl").write_text("".join(json.dumps({"step": i + 1, "clips_per_s": r}) + "\n" for i, r in enumerate(rates)))
    assert studies.training_minutes(scale, "esther") == pytest.approx((2.0 + 1.0 + 4.0) / 60.0)


def test_a_report_names_clips_of_an_earlier_engine_revision(tmp_path, monkeypatch):
    from esther_jax.data import synth

    monkeypatch.setenv(studies.ROOT_ENV, str(tmp_path / "root"))
    scale = studies.SCALES["full"]
    for name, revision in (("train", synth.ENGINE_REVISION - 1), ("heldout", synth.ENGINE_REVISION)):
        (tmp_path / "root" / "data" / name).mkdir(parents=True)
        (tmp_path / "root" / "data" / name / "synth.json").write_text(json.dumps({"engine_revision": revision}))
    json_path, md_path = studies.write_report(tmp_path / "out", "t", title="t", verdict="v", results={}, scale=scale, seconds=1.0)
    assert json.loads(json_path.read_text())["engine_revisions"] == {"heldout": synth.ENGINE_REVISION, "train": synth.ENGINE_REVISION - 1}
    assert f"made by synth engine revision {synth.ENGINE_REVISION - 1} (" in md_path.read_text()
    (tmp_path / "root" / "data" / "train" / "synth.json").write_text(json.dumps({"engine_revision": synth.ENGINE_REVISION}))
    assert "synth engine revision" not in studies.write_report(tmp_path / "out", "t", title="t", verdict="v", results={}, scale=scale,
                                                               seconds=1.0)[1].read_text()  # fmt: skip


def test_every_study_has_a_notebook():
    assert sorted(p.stem for p in NOTEBOOKS) == sorted(STUDY_OF)


def test_notebook_runs_in_a_jupyter_kernel(study_env, tmp_path):
    jupytext = pytest.importorskip("jupytext")
    nbclient = pytest.importorskip("nbclient")
    notebook = next(p for p in NOTEBOOKS if p.stem == KERNEL_NOTEBOOK)
    out = tmp_path / "kernel_reports"
    os.environ[studies.OUT_ENV] = str(out)
    try:
        nb = jupytext.read(notebook)
        nbclient.NotebookClient(nb, kernel_name="python3", timeout=900, resources={"metadata": {"path": str(tmp_path)}}).execute()
    finally:
        os.environ[studies.OUT_ENV] = str(study_env)
    assert any(o.get("name") == "stdout" for cell in nb.cells if cell.cell_type == "code" for o in cell.get("outputs", []))
    assert _check_report(out, "gate")["results"]["clean"]["hand_frames"] > 0


def test_the_first_clips_of_a_dataset_are_the_full_datasets_first(tmp_path, monkeypatch):
    monkeypatch.setenv(studies.ROOT_ENV, str(tmp_path))
    scale = dataclasses.replace(studies.SCALES["smoke"], clip_frames=4)
    first = studies.dataset(scale, "heldout", count=1, progress=False)
    assert [p.name for p in first] == ["clip_00000"] and len(list(first[0].parent.glob("clip_*"))) == 1  # made no more
    full = studies.dataset(scale, "heldout", progress=False)
    assert len(full) == scale.heldout_clips and full[0] == first[0]
    with pytest.raises(ValueError, match="asked for the first 3"):
        studies.dataset(scale, "heldout", count=3)
