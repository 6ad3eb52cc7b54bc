"""Per-clip jobs on a Ray cluster: `esther label | refine | crops ... --ray local|auto|ADDRESS`.

A collection of thousands of clips outgrows one process. `map_clips` runs one of the
project's batch functions (`fitting.label_clips`, `fitting.refine_clips`,
`model.folders.predict_folders`, `data.video_crops.crop_clips`) as one Ray task per
clip and merges their results into the one-process result. The guarantees are the batch
functions' own, since each task is one of them on one clip: atomic outputs, the per-clip
locks (POSIX `flock`, released when a process dies), resume, one writer per clip, so two
drivers on one output folder, or a driver beside a one-process run, lose and duplicate
nothing. A task whose worker dies is retried by Ray (`max_retries`), and the retry
removes the dead task's partial folder under the clip's lock and redoes the clip.

Each task gets `cpus_per_task` of its node's CPUs and limits XLA's and the BLAS
libraries' threads to them (environment variables set before its worker imports JAX),
and enables the persistent compilation cache (`$ESTHER_JAX_CACHE`, the driver's value
or the default on each node), so a node compiles each program once, not once per task.
Ray's usage statistics are off (`RAY_USAGE_STATS_ENABLED=0`) and its dashboard is not
started; nothing but the cluster is contacted.

Addresses: `local` starts a private Ray instance on this machine for the job; `auto`
connects to the cluster `ray start` runs on this machine (or `RAY_ADDRESS`) and starts a
local instance when there is none; `HOST:PORT` (or `ray://HOST:PORT`) connects there.
Ray is the optional extra `ray` (`pip install -e '.[ray]'`).
"""

import os
import pathlib
from collections.abc import Callable

from .files import named_folders

USAGE_STATS = {"RAY_USAGE_STATS_ENABLED": "0"}
"""Ray's usage statistics, off in the driver and every worker."""


def _import_ray():
    os.environ.update(USAGE_STATS)  # before ray reads it
    try:
        import ray
    except ImportError as err:
        raise ValueError("--ray needs Ray, the optional extra 'ray': pip install -e '.[ray]' (or pip install 'esther-jax[ray]')") from err
    return ray


def worker_environment(cpus_per_task: int) -> dict[str, str]:
    """The environment of every worker: the driver's XLA_FLAGS (so workers compile as it
    does) with XLA's CPU intra-op parallelism limited to `cpus_per_task` threads (and
    Eigen's multi-threading off for one), the BLAS libraries' threads likewise, the
    compilation cache's folder (the driver's `$ESTHER_JAX_CACHE` when set), usage
    statistics off."""
    threads = str(cpus_per_task)
    limits = f"--xla_cpu_multi_thread_eigen={'true' if cpus_per_task > 1 else 'false'} intra_op_parallelism_threads={threads}"
    env = {
        **USAGE_STATS,
        "XLA_FLAGS": f"{os.environ.get('XLA_FLAGS', '')} {limits}".strip(),
        "OMP_NUM_THREADS": threads, "OPENBLAS_NUM_THREADS": threads, "MKL_NUM_THREADS": threads,
    }  # fmt: skip
    if os.environ.get("ESTHER_JAX_CACHE"):
        env["ESTHER_JAX_CACHE"] = os.environ["ESTHER_JAX_CACHE"]
    return env


def merge_results(results: list[dict], empty: dict | None = None) -> dict:
    """One batch result from per-clip ones: lists concatenated, numbers summed, other
    values (e.g. the output folder) the first result's; `empty`, the result of no clip
    (its keys' empty values), gives every key even when no clip's result has it."""
    merged: dict = {k: (list(v) if isinstance(v, list) else v) for k, v in (empty or {}).items()}
    for result in results:
        for key, value in result.items():
            if isinstance(value, list):
                merged.setdefault(key, []).extend(value)
            elif isinstance(value, (int, float)) and not isinstance(value, bool):
                merged[key] = merged.get(key, 0) + value
            else:
                merged.setdefault(key, value)
    return merged


def _run_clip(job: Callable[..., dict], clip: str) -> dict:
    """One task: `job([clip])` with the persistent compilation cache on."""
    from .compilation import enable_compilation_cache

    enable_compilation_cache()
    return job([pathlib.Path(clip)], progress=False)


def _connect(ray, address: str, cpus: int | None, env: dict[str, str]) -> bool:
    """Connect (or start a local instance); True when this call started Ray."""
    if ray.is_initialized():
        return False
    options = dict(runtime_env={"env_vars": env}, include_dashboard=False, log_to_driver=False, configure_logging=False)
    if address == "local":
        ray.init(num_cpus=cpus, **options)
        return True
    try:
        ray.init(address=address, **options)
    except ConnectionError:
        if address != "auto":
            raise ValueError(f"no Ray cluster at {address} (ray start --head starts one; --ray local runs one for this job)") from None
        ray.init(num_cpus=cpus, **options)  # no cluster running here: a local instance
    return True


def map_clips(
    job: Callable[..., dict],
    clip_dirs: list[str | pathlib.Path],
    *,
    address: str = "auto",
    cpus_per_task: int = 1,
    max_retries: int = 3,
    num_cpus: int | None = None,
    progress: bool = True,
    desc: str = "clips",
    empty: dict | None = None,
) -> dict:
    """Run the batch function `job` (called as `job([clip], progress=False)`: e.g.
    `functools.partial(fitting.label_clips, out_dir=OUT, resume=True)`) as one Ray task
    per clip of `clip_dirs` and merge the results (`merge_results`). A clip whose task
    failed after `max_retries` retries (its worker died each time) is reported in the
    result's "failed" list, as the batch functions report a bad clip. `num_cpus`: the
    CPUs of a local instance this call starts (default: all of the machine's). `empty`:
    the batch function's result of no clip (`merge_results`).

    Raises ValueError before any work when Ray is not installed, the address has no
    cluster, or two clips share a folder name (`files.named_folders`); an exception the
    job itself raises (one the batch functions do not report per clip, e.g. a detector
    that is not installed) is raised here, the other tasks cancelled.
    """
    from tqdm import tqdm

    clip_dirs = named_folders(clip_dirs)
    if cpus_per_task < 1:
        raise ValueError(f"cpus_per_task must be >= 1, got {cpus_per_task}")
    ray = _import_ray()
    started = _connect(ray, address, num_cpus, worker_environment(cpus_per_task))
    try:
        task = ray.remote(_run_clip).options(num_cpus=cpus_per_task, max_retries=max_retries, retry_exceptions=False)
        job_ref = ray.put(job)
        pending = {task.remote(job_ref, str(clip)): clip for clip in clip_dirs}
        results = []
        with tqdm(total=len(pending), desc=desc, unit="clip", disable=not progress) as bar:
            while pending:
                done, _ = ray.wait(list(pending), num_returns=1)
                for ref in done:
                    clip = pending.pop(ref)
                    try:
                        results.append(ray.get(ref))
                    except ray.exceptions.RayTaskError as err:  # the job raised: the batch functions report a bad clip, so this stops the run
                        for other in pending:
                            ray.cancel(other)
                        cause = getattr(err, "cause", None)
                        raise (cause if isinstance(cause, Exception) else err) from None
                    except ray.exceptions.RayError as err:  # its worker died on every try
                        results.append({"failed": [{"clip": str(clip), "error": f"{type(err).__name__}: {str(err).splitlines()[0]}"}]})
                    bar.update(1)
        return merge_results(results, empty)
    finally:
        if started:
            ray.shutdown()


__all__ = ["USAGE_STATS", "map_clips", "merge_results", "worker_environment"]
