"""Shared timing helpers for the benchmark scripts (compile apart, medians of rounds, and
the machine's speed printed beside every run's numbers)."""

import os
import statistics
import time
from collections.abc import Callable

import jax
import numpy as np


def machine() -> str:
    """The machine the numbers were taken on: JAX's version and backend, the CPU cores,
    numpy's single-precision matrix product (2048 x 2048, best of 5, GFLOP/s) and the
    1-minute load average. Machines of one class differ from day to day (on 2-core
    CI-class machines we read 71 to 450 GFLOP/s), so a timing is only comparable with
    another of a similar reading; a load near 1 or more on 2 cores means another job
    shares them (peers with OpenMP thread teams, torch, slow down far more than XLA, so
    ratios against them inflate: benchmarks/fk.py)."""
    a = np.random.default_rng(0).random((2048, 2048), dtype=np.float32)
    a @ a
    best = float("inf")
    for _ in range(5):
        t0 = time.perf_counter()
        a @ a
        best = min(best, time.perf_counter() - t0)
    try:
        cores = len(os.sched_getaffinity(0))
    except AttributeError:
        cores = os.cpu_count()
    return (
        f"jax {jax.__version__} on {jax.default_backend()}, {cores} cores, numpy SGEMM {2 * 2048**3 / best / 1e9:.0f} GFLOP/s, "
        f"load {os.getloadavg()[0]:.2f}"
    )


def compile_seconds(fn: Callable, *args) -> float:
    """Wall time of the first call (trace + compile + one run)."""
    t0 = time.perf_counter()
    jax.block_until_ready(fn(*args))
    return time.perf_counter() - t0


def median_seconds(fn: Callable, *args, min_time: float = 0.2, rounds: int = 5) -> float:
    """Median over `rounds` of the mean time per call, each round lasting >= min_time."""
    jax.block_until_ready(fn(*args))
    t0 = time.perf_counter()
    jax.block_until_ready(fn(*args))
    one = max(time.perf_counter() - t0, 1e-6)
    reps = max(1, int(min_time / one))
    per_round = []
    for _ in range(rounds):
        t0 = time.perf_counter()
        for _ in range(reps):
            out = fn(*args)
        jax.block_until_ready(out)
        per_round.append((time.perf_counter() - t0) / reps)
    return statistics.median(per_round)


def interleaved(candidates: dict[str, Callable[[], object]], rounds: int = 5, min_time: float = 0.2) -> dict[str, float]:
    """Median seconds per call of several zero-argument callables, timed round robin so
    that machine noise hits all of them alike (peers' timings
    were taken the same way)."""
    reps = {}
    for name, fn in candidates.items():
        jax.block_until_ready(fn())
        t0 = time.perf_counter()
        jax.block_until_ready(fn())
        reps[name] = max(1, int(min_time / max(time.perf_counter() - t0, 1e-6)))
    samples: dict[str, list[float]] = {name: [] for name in candidates}
    for _ in range(rounds):
        for name, fn in candidates.items():
            t0 = time.perf_counter()
            for _ in range(reps[name]):
                out = fn()
            jax.block_until_ready(out)
            samples[name].append((time.perf_counter() - t0) / reps[name])
    return {name: statistics.median(s) for name, s in samples.items()}
