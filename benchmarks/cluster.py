"""`esther label` on Ray against one process: clips per minute and the cost of a task.

    python benchmarks/cluster.py [--clips 8] [--frames 64]

Side by side in one run, on synthetic clips (both hands, the default detector), after one
clip labelled to fill the compilation cache (every path then loads the teacher's programs):
1. one process (`fitting.label_clips`);
2. a local Ray instance with 1 worker CPU, then with 2 (`esther_jax.cluster.map_clips`),
   each started afresh (its workers start, import JAX and load the programs inside the time);
3. the overhead of a task: an empty job over as many clips on a started instance (per task),
   and the start of an instance with its first worker (once per job).
A user projects a cluster's rate as workers x the one-worker rate, minus the overhead per
task, for as long as the filesystem keeps up.
"""

import argparse
import os
import pathlib
import sys
import tempfile
import time

os.environ.setdefault("RAY_USAGE_STATS_ENABLED", "0")

import fitting  # noqa: E402
from esther_jax import cluster, enable_compilation_cache  # noqa: E402
from esther_jax.data import synth  # noqa: E402


def _nothing(clip_dirs, progress):
    return {"clips": [str(c) for c in clip_dirs]}


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
    fitting.label_clips([warm], root / "warm_labels", progress=False)  # compilation apart
    print(f"{args.clips} clips of {args.frames} frames, both hands; {os.cpu_count()} CPUs")

    rows = []
    t0 = time.perf_counter()
    fitting.label_clips(clips, root / "one", progress=False)
    rows.append(("one process", time.perf_counter() - t0))
    for cpus in (1, 2):
        t0 = time.perf_counter()
        result = cluster.map_clips(lambda c, progress: fitting.label_clips(c, root / f"ray{cpus}", progress=progress), clips, address="local",
                                   num_cpus=cpus, progress=False)  # fmt: skip
        rows.append((f"Ray, {cpus} worker{'s' if cpus > 1 else ''}", time.perf_counter() - t0))
        assert not result["failed"], result["failed"]
    for what, seconds in rows:
        print(f"  {what:<16} {seconds:7.1f} s   {60.0 * args.clips / seconds:6.2f} clips/min   {rows[0][1] / seconds:5.2f}x one process")

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


if __name__ == "__main__":
    main()
