"""Per-clip jobs on a Ray cluster (`esther_jax.cluster`, `--ray`): the same labels as one
process, nothing lost when a worker dies mid-clip, nothing lost or duplicated with two
drivers on one output folder. Skipped without the `ray` extra."""

import functools
import os
import pathlib
import subprocess
import sys
import threading
import time

import numpy as np
import pytest

ray = pytest.importorskip("ray")

from esther_jax import cli, clips, cluster  # noqa: E402
from esther_jax.data import motion, synth  # noqa: E402
from esther_jax.files import exclusive_lock  # noqa: E402
import fitting  # noqa: E402

# Ray starts its processes with fork(), which JAX (already running threads here) warns of; the
# children exec Ray's own programs at once, so the warning does not apply.
pytestmark = [pytest.mark.filterwarnings("ignore:os.fork:RuntimeWarning"), pytest.mark.filterwarnings("ignore::pytest.PytestUnraisableExceptionWarning")]

FRAMES = 32  # the teacher's length bucket of tests/test_fitting.py: compiled once


@pytest.fixture(scope="module")
def raw(tmp_path_factory) -> list[pathlib.Path]:
    cfg = synth.SynthConfig(num_frames=FRAMES, detector_preset="easy", motion_config=motion.MotionConfig(two_hands_probability=1.0))
    root = tmp_path_factory.mktemp("cluster")
    return [synth.write_clip(synth.make_clip(41, i, cfg), root / "raw" / f"clip_{i:05d}") for i in range(3)]


@pytest.fixture(scope="module")
def one_process(raw, tmp_path_factory) -> pathlib.Path:
    out = tmp_path_factory.mktemp("one_process") / "labels"
    assert not fitting.label_clips(raw, out, progress=False)["failed"]
    return out


@pytest.fixture(scope="module")
def local_cluster():
    """A two-CPU Ray instance on this machine for the module (map_clips uses it as found)."""
    os.environ.update(cluster.USAGE_STATS)
    ray.init(num_cpus=2, runtime_env={"env_vars": cluster.worker_environment(1)}, include_dashboard=False, log_to_driver=False, configure_logging=False)
    yield ray.get_runtime_context().gcs_address
    ray.shutdown()


def _same_labels(a: pathlib.Path, b: pathlib.Path, names: list[str]) -> None:
    """The labels of `names` in `a` and `b` agree: the same accepted frames, joints within
    0.1 mm and parameters within 1e-3 (the solver's `converged` flag, a threshold on its last
    step, is not compared). (Not bitwise: a Ray worker's XLA runs on one thread,
    and a different order of float32 sums moves the fits by about 1e-4 rad.)"""
    for name in names:
        for side in clips.SIDES:
            pa, pb = clips.hand_file(a / name, side, "labels"), clips.hand_file(b / name, side, "labels")
            assert pa.is_file() == pb.is_file()
            if pa.is_file():
                x, y = clips.load_npz(pa, "labels"), clips.load_npz(pb, "labels")
                assert set(x) == set(y)
                for key in set(x) - {"converged"}:
                    tolerance = 1e-4 if key == "joints" else 1e-3
                    np.testing.assert_allclose(np.asarray(x[key], np.float64), np.asarray(y[key], np.float64), rtol=0, atol=tolerance,
                                               equal_nan=True, err_msg=f"{name}/{side}/{key}")  # fmt: skip
    leftovers = [p.name for p in b.iterdir() if ".partial" in p.name]
    assert not leftovers, f"partial folders left: {leftovers}"


def test_labels_on_ray_equal_one_process(raw, one_process, local_cluster, tmp_path, capsys):
    out = tmp_path / "labels"
    code = cli.main(["label", *map(str, raw), "--out", str(out), "--ray", local_cluster])
    assert code == 0, capsys.readouterr().err
    assert "labelled 3 clips" in capsys.readouterr().out
    _same_labels(one_process, out, [c.name for c in raw])
    summary = (out / "label_summary.json").read_text()
    assert all(c.name in summary for c in raw)


def test_a_worker_killed_mid_clip_loses_nothing(raw, one_process, local_cluster, tmp_path):
    out, marker, victim = tmp_path / "labels", tmp_path / "died", raw[1].name
    out.mkdir()

    def dies_once(clip_dirs, progress):
        """Label; the first time the victim clip comes, die in the middle of it: its partial folder written, its lock held."""
        if clip_dirs[0].name == victim and not marker.exists():
            marker.touch()
            with exclusive_lock(out / f".{victim}.lock"):
                partial = out / f".{victim}.partial-dying"
                (partial / "hands" / "right").mkdir(parents=True)
                (partial / "hands" / "right" / "labels.npz").write_bytes(b"half a file")
                os._exit(1)  # the worker process dies (Ray retries the task on another)
        return fitting.label_clips(clip_dirs, out, progress=progress)

    result = cluster.map_clips(dies_once, raw, address=local_cluster, progress=False, empty={"labelled": [], "failed": []})
    assert marker.exists(), "the worker did not die: nothing was tested"
    assert not result["failed"] and sorted(r["clip"] for r in result["labelled"]) == [c.name for c in raw]
    _same_labels(one_process, out, [c.name for c in raw])


def _waiting_for(lock: pathlib.Path) -> int:
    """How many processes wait for the `flock` on the file `lock` (Linux's /proc/locks,
    whose waiting requests are its '->' lines, named by device and inode)."""
    st = lock.stat()
    ident = f"{os.major(st.st_dev):02x}:{os.minor(st.st_dev):02x}:{st.st_ino}"
    lines = pathlib.Path("/proc/locks").read_text().splitlines()
    return sum(1 for line in lines if " -> " in line and line.split()[-3] == ident)


def test_two_drivers_on_one_folder_lose_and_duplicate_nothing(raw, one_process, local_cluster, tmp_path):
    """Two drivers on one output folder at once (a subprocess `esther label --resume --ray` and
    `map_clips` in a thread here), made to meet on one clip: its lock is held (as a third
    writer in the middle of it would hold it) until both drivers' tasks are seen waiting for
    it; then one labels it and the other skips it, and every clip is labelled once."""
    if not pathlib.Path("/proc/locks").is_file():
        pytest.skip("needs Linux's /proc/locks to see the drivers wait on one clip")
    out = tmp_path / "labels"
    out.mkdir()
    lock = out / f".{raw[0].name}.lock"
    here: dict = {}

    def second_driver():
        try:
            here.update(cluster.map_clips(functools.partial(fitting.label_clips, out_dir=out, resume=True), raw, address=local_cluster,
                                          progress=False))  # fmt: skip
        except BaseException as err:  # noqa: BLE001 - reported by the test below
            here["error"] = err

    command = [sys.executable, "-m", "esther_jax.cli", "label", *map(str, raw), "--out", str(out), "--resume", "--ray", local_cluster]
    with exclusive_lock(lock):
        other = subprocess.Popen(command, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, env={**os.environ, **cluster.USAGE_STATS})
        thread = threading.Thread(target=second_driver, daemon=True)  # a failed test does not wait for it
        thread.start()
        deadline = time.monotonic() + 300
        while _waiting_for(lock) < 2:
            assert other.poll() is None and thread.is_alive(), "a driver ended before it reached the held clip"
            assert time.monotonic() < deadline, f"{_waiting_for(lock)} of the 2 drivers' tasks wait for the held clip after 300 s"
            time.sleep(0.2)
    thread.join(timeout=600)
    stdout, stderr = other.communicate(timeout=600)
    assert other.returncode == 0, stderr[-2000:]
    assert "error" not in here, here.get("error")
    there = int(stdout.split("labelled ")[1].split(" clips")[0])
    assert not here["failed"] and len(here["labelled"]) + there == len(raw), (here, stdout)  # each clip labelled once, by one driver
    assert len(here["labelled"]) + len(here["skipped"]) == there + int(stdout.split("skipped ")[1].split(",")[0]) == len(raw), (here, stdout)
    _same_labels(one_process, out, [c.name for c in raw])


def test_an_error_of_the_job_itself_stops_the_run(raw, local_cluster):
    def no_detector(clip_dirs, progress):
        """What a batch function does not report per clip (e.g. DetectorUnavailable): it raises."""
        raise RuntimeError("the detector is not installed")

    with pytest.raises(RuntimeError, match="the detector is not installed"):
        cluster.map_clips(no_detector, raw, address=local_cluster, progress=False)


def test_clashing_names_are_refused_and_results_merge(raw, tmp_path):
    twin = synth.write_clip(synth.make_clip(41, 0, synth.SynthConfig(num_frames=FRAMES)), tmp_path / "other" / raw[0].name)
    job = functools.partial(fitting.label_clips, out_dir=tmp_path / "labels")
    with pytest.raises(ValueError, match="share the name"):
        cluster.map_clips(job, [raw[0], twin], address="local")
    assert cluster.merge_results([{"a": [1], "n": 2, "out": "x"}, {"a": [2], "n": 3, "out": "y"}], {"a": [], "b": []}) == {
        "a": [1, 2], "b": [], "n": 5, "out": "x"}  # fmt: skip


def test_detection_on_ray_equals_one_process(local_cluster, tmp_path):
    """`detect_recordings` as one Ray task per recording (what `esther detect REC... --ray`
    runs) writes the keypoints one process writes, with test_detect's exact detector."""
    from esther_jax import cameras
    from esther_jax.detect import detect_recordings

    from . import test_detect

    ray.cloudpickle.register_pickle_by_value(test_detect)  # its detector travels to the workers with the task
    cfg = synth.SynthConfig(num_frames=test_detect.FRAMES, detector_preset="clean",
                            motion_config=motion.MotionConfig(two_hands_probability=1.0, leave_view_probability=0.0))  # fmt: skip
    hands = {side: gt["joints"].astype(np.float64) for side, gt in synth.make_clip(5, 0, cfg).gt.items()}
    rig = cameras.rig_preset("esther")
    recordings = [test_detect._recording(tmp_path / "recordings" / f"rec_{i}", rig) for i in range(2)]
    job = functools.partial(detect_recordings, detectors=("truth",), fps=30.0, factories={"truth": test_detect._factory(hands, rig, [])})
    here = job(recordings, out_dir=tmp_path / "one", progress=False)
    there = cluster.map_clips(functools.partial(job, out_dir=tmp_path / "ray"), recordings, address=local_cluster, progress=False,
                              empty={"detected": [], "skipped": [], "failed": []})  # fmt: skip
    assert not there["failed"] and sorted(c["clip"] for c in there["detected"]) == sorted(c["clip"] for c in here["detected"]) == ["rec_0", "rec_1"]
    for name in ("rec_0", "rec_1"):
        for side in clips.SIDES:
            a, b = (clips.load_npz(clips.hand_file(tmp_path / root / name, side, "keypoints"), "keypoints") for root in ("one", "ray"))
            for key in a:
                np.testing.assert_array_equal(a[key], b[key])
