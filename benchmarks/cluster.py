"""`esther label` on Ray against one process: clips per minute, the cost of a task, and
where Ray starts to pay.

    python benchmarks/cluster.py [--clips 8] [--frames 64]

Side by side in one run, on synthetic clips (both hands, the default detector):
0. the compilation caches filled: one clip labelled in this process, and one clip on a
   fresh one-worker Ray instance (a worker limits XLA to its one thread, which is another
   compiled program than this process's: the cost a node pays once, reported);
1. one process (`fitting.label_clips`, XLA on all of the machine's cores);
2. a fresh local Ray instance with 1 worker CPU, then with 2 (`esther_jax.cluster.map_clips`),
   each timed whole: the instance starts, its workers import JAX and load the teacher's
   programs from the cache, then label. Each task also times its own clip, which splits a
   run into its per-clip work and its fixed cost (start and loading, once per job);
3. the overhead of a task: an empty job over as many clips on a started instance.

From these a user projects a job: with W workers of the measured per-clip time c and the
fixed cost S, N clips take about S + N c / W, against N s for one process (s its per-clip
time); the script prints the N past which Ray is faster, for this machine's workers and for
a cluster of 16 and 64 of them (the filesystem keeping up).
"""

import argparse
import os
import pathlib
import statistics
import sys
import tempfile
import time

os.environ.setdefault("RAY_USAGE_STATS_ENABLED", "0")

import fitting  # noqa: E402
from esther_jax import cluster, enable_compilation_cache  # noqa: E402
from esther_jax.data import synth  # noqa: E402


def _nothing(clip_dirs, progress):
    return {"clips": [str(c) for c in clip_dirs]}


def _timed_label(out_dir: pathlib.Path):
    """The labelling job of a run, each task reporting its own seconds ("task_seconds")."""

    def job(clip_dirs, progress):
        t0 = time.perf_counter()
        result = fitting.label_clips(clip_dirs, out_dir, progress=progress)
        return {**result, "task_seconds": [time.perf_counter() - t0]}

    return job


def _break_even(fixed: float, per_clip: float, workers: int, one_process: float) -> str:
    """Clips past which `workers` Ray workers (fixed cost, per-clip seconds each) beat one process."""
    gain = one_process - per_clip / workers
    return f"{fixed / gain:.0f} clips" if gain > 0 else "never (a worker is no faster than one process)"


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--clips", type=int, default=8)
    parser.add_argument("--frames", type=int, default=64)
    args = parser.parse_args()
    sys.stdout.reconfigure(line_buffering=True)
    import ray

    enable_compilation_cache()
    root = pathlib.Path(tempfile.mkdtemp(prefix="esther-cluster-bench-"))
    cfg = synth.SynthConfig(num_frames=args.frames)
    clips = [synth.write_clip(synth.make_clip(5000, i, cfg), root / "clips" / f"clip_{i:05d}") for i in range(args.clips)]
    warm = synth.write_clip(synth.make_clip(5001, 0, cfg), root / "warm" / "clip_00000")
    fitting.label_clips([warm], root / "warm_labels", progress=False)
    t0 = time.perf_counter()
    first = cluster.map_clips(_timed_label(root / "warm_ray"), [warm], address="local", num_cpus=1, progress=False)
    cold = time.perf_counter() - t0
    print(f"{args.clips} clips of {args.frames} frames, both hands; {os.cpu_count()} CPUs")
    print(f"  a node's first clip on a cold worker cache: {cold:.1f} s (its task {first['task_seconds'][0]:.1f} s, compiling once per node)")

    t0 = time.perf_counter()
    fitting.label_clips(clips, root / "one", progress=False)
    one = time.perf_counter() - t0
    rows = [("one process", one, None)]
    for cpus in (1, 2):
        t0 = time.perf_counter()
        result = cluster.map_clips(_timed_label(root / f"ray{cpus}"), clips, address="local", num_cpus=cpus, progress=False)
        rows.append((f"Ray, {cpus} worker{'s' if cpus > 1 else ''}", time.perf_counter() - t0, result["task_seconds"]))
        assert not result["failed"] and len(result["labelled"]) == args.clips, result["failed"]
    for what, seconds, _ in rows:
        print(f"  {what:<16} {seconds:7.1f} s   {60.0 * args.clips / seconds:6.2f} clips/min   {one / seconds:5.2f}x one process")

    t0 = time.perf_counter()
    ray.init(num_cpus=1, include_dashboard=False, log_to_driver=False, configure_logging=False,
             runtime_env={"env_vars": cluster.worker_environment(1)})  # fmt: skip
    cluster.map_clips(_nothing, clips[:1], progress=False)
    start = time.perf_counter() - t0
    t0 = time.perf_counter()
    cluster.map_clips(_nothing, clips, progress=False)
    per_task = (time.perf_counter() - t0) / len(clips)
    ray.shutdown()
    print(f"  overhead: {start:.1f} s to start an instance and its first worker; {1000 * per_task:.0f} ms per task on a started one")

    s = one / args.clips
    print(f"  per clip: one process {s:.2f} s")
    split = []  # per Ray row: a worker's steady clip and the job's fixed cost
    for (what, seconds, tasks), workers in zip(rows[1:], (1, 2)):
        c = statistics.median(tasks)  # a worker's first task also loads the programs: the median is its steady clip
        split.append((c, max(seconds - sum(min(t, c) for t in tasks) / workers, 0.0)))
        print(f"  {what}: a clip {c:.2f} s on a worker (first task {tasks[0]:.2f} s), fixed cost {split[-1][1]:.1f} s a job; "
              f"faster than one process past {_break_even(split[-1][1], c, workers, s)}")  # fmt: skip
    c, fixed = split[0]  # one worker's, undisturbed by a second on the same cores
    for workers in (16, 64):
        print(f"  projected, {workers} such workers: {60.0 * workers / c:.0f} clips/min steady; "
              f"faster than this machine's one process past {_break_even(fixed, c, workers, s)}")  # fmt: skip


if __name__ == "__main__":
    main()
