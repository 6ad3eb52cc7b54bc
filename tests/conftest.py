"""Strict test environment (STYLE.md): strict dtype promotion, rank promotion raises,
warnings are errors (pyproject), shape annotations checked at run time (addopts)."""

import os
import pathlib
import subprocess
import sys

# The tests run small shapes, where XLA's compilation is most of the time, and what is
# compiled runs a few times at most: LLVM's cheapest level (0: no optimisation of the
# generated code) and the loop emitters for fusions compile the same programs in far less
# time. Measured on 2 cores: the `cpu-tiny` forward compiles in 3.3 s at level 0 against
# 8.6 s at level 1 (and runs in 45 ms against 27 ms); the whole suite cold used 1212 s of
# CPU against 1719 s at level 1 (and test_model.py 249 s at level 1 against 409 s with
# XLA's defaults). Programs compiled with their own options (the teacher's
# `persistent_jit(compiler_options=...)`) keep those. The benchmarks measure the default
# compiler. Flags the caller sets come after these and override them. An XLA
# that does not know a flag of XLA_FLAGS aborts the process, so a subprocess tries them
# first, once per run (xdist workers inherit the answer), and they are left out if refused.
QUICK_COMPILE_FLAGS = "--xla_backend_optimization_level=0 --xla_cpu_use_fusion_emitters=false"
if "ESTHER_TEST_XLA_FLAGS" not in os.environ:
    _probe = subprocess.run([sys.executable, "-c", "import jax; jax.devices()"], env={**os.environ, "XLA_FLAGS": QUICK_COMPILE_FLAGS},
                            capture_output=True, timeout=300)  # fmt: skip
    os.environ["ESTHER_TEST_XLA_FLAGS"] = QUICK_COMPILE_FLAGS if _probe.returncode == 0 else ""
os.environ["XLA_FLAGS"] = f"--xla_force_host_platform_device_count=1 {os.environ['ESTHER_TEST_XLA_FLAGS']} {os.environ.get('XLA_FLAGS', '')}".strip()

import jax
import pytest

jax.config.update("jax_numpy_dtype_promotion", "strict")
jax.config.update("jax_numpy_rank_promotion", "raise")

SHARED_DATA = pathlib.Path(__file__).resolve().parents[1].parent / "shared" / "data"


@pytest.fixture(scope="session", autouse=True)
def compilation_cache():
    """Keep compiled solvers (and the teacher's traced programs) between runs, as the
    `esther` CLI does: the teacher's take ~40 s to compile cold. (A fixture, so that the
    library is imported after the run-time shape checks are installed.)"""
    import esther_jax

    esther_jax.enable_compilation_cache(min_compile_time_s=1.0)


@pytest.fixture
def getkey():
    """A fresh PRNG key per call, deterministic per test."""
    keys = iter(jax.random.split(jax.random.key(0), 10_000))
    return lambda: next(keys)


@pytest.fixture
def x64():
    """Run the test body with float64 enabled, restoring the flag afterwards."""
    previous = jax.config.jax_enable_x64
    jax.config.update("jax_enable_x64", True)
    try:
        yield
    finally:
        jax.config.update("jax_enable_x64", previous)


@pytest.fixture
def shared_data():
    if not SHARED_DATA.is_dir():
        pytest.skip("../shared/data is not present")
    return SHARED_DATA


@pytest.fixture(scope="module", autouse=True)
def _release_compiled_programs():
    """Drop each module's compiled programs when it ends: a worker runs many modules, and
    their executables otherwise accumulate (several GB). What a later module needs again
    comes back from the persistent compilation cache."""
    yield
    jax.clear_caches()


# Longest modules first (cold compilation cache, 2 cores: measured seconds), so the two
# xdist workers, which take whole files in collection order, finish together.
_MODULE_SECONDS = {
    "test_train": 225, "test_fitting": 200, "test_model": 155, "test_studies": 140, "test_synth": 60, "test_detect": 50,
    "test_triangulation": 50, "test_mano": 40, "test_rotations": 40, "test_cameras": 35, "test_metrics": 25, "test_hot3d_import": 20,
    "test_readme": 20, "test_mano_identity": 15, "test_hardening": 15, "test_teacher_validation": 15, "test_cli": 15,
    "test_baselines": 10, "test_crops": 10, "test_attention": 10, "test_eval": 5,
}  # fmt: skip


def pytest_collection_modifyitems(items):
    items.sort(key=lambda item: -_MODULE_SECONDS.get(item.module.__name__.rsplit(".", 1)[-1], 0))
