"""The persistent XLA compilation cache: compile the teacher's solvers (and the
network's steps) once per machine, not once per process.

    import esther_jax
    esther_jax.enable_compilation_cache()   # notebooks, scripts; the `esther` CLI calls it

Programs are stored under `$ESTHER_JAX_CACHE` (default `~/.cache/esther_jax/xla`) and
reused by every later process with the same program, jax version and backend. JAX never
stores a program that contains a host callback (`jax.pure_callback`, `eqx.error_if`,
`jax.debug.print`): the library's compiled hot paths contain none, and validate their
inputs at the edge instead.
"""

import os
import pathlib

DEFAULT_DIR = pathlib.Path("~/.cache/esther_jax/xla")


def enable_compilation_cache(directory: str | os.PathLike | None = None, *, min_compile_time_s: float = 0.0) -> pathlib.Path:
    """Store compiled programs that took longer than `min_compile_time_s` to compile in
    `directory` (default `$ESTHER_JAX_CACHE` or `~/.cache/esther_jax/xla`) and load them
    from there in later processes. Returns the directory; safe to call more than once.

    The default stores every program, however small: besides its few large solvers the
    teacher runs about thirty small programs (tens of milliseconds each), and a warm
    process loads them faster than it compiles them (first label of a 64-frame clip,
    `benchmarks/teacher.py --section compile`: 5.2 -> 4.3 s on the pinhole rig, 6.7 -> 5.7 s
    on the fisheye rig, against a 0.5 s threshold). The price is more, smaller files in
    the cache (a few hundred per rig and process)."""
    import jax

    path = pathlib.Path(directory or os.environ.get("ESTHER_JAX_CACHE") or DEFAULT_DIR).expanduser()
    path.mkdir(parents=True, exist_ok=True)
    jax.config.update("jax_compilation_cache_dir", str(path))
    jax.config.update("jax_persistent_cache_min_compile_time_secs", float(min_compile_time_s))
    jax.config.update("jax_persistent_cache_min_entry_size_bytes", 0)
    return path
