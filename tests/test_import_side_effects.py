"""Importing the library changes nothing global: in a fresh interpreter, importing every
module of `esther_jax` and `fitting` leaves matplotlib's backend (pyplot is never imported),
JAX's configuration, the environment, the working directory and the warning filters as
they were, starts no process (no `git`) and reads no source file for the program store's
key (it is computed at the first stored call). What other packages do as they load
(OpenCV sets LD_LIBRARY_PATH, scipy adds warning filters) is theirs: a first run lists
them, the second loads them before its snapshot."""

import json
import pathlib
import subprocess
import sys
import textwrap

ROOT = pathlib.Path(__file__).resolve().parents[1]

PROBE = textwrap.dedent(
    """
    import importlib, json, os, pkgutil, subprocess, sys, warnings
    started = []
    original = subprocess.Popen.__init__
    def recording(self, *args, **kwargs):
        started.append(str(args[0] if args else kwargs.get("args")))
        original(self, *args, **kwargs)
    subprocess.Popen.__init__ = recording
    import matplotlib
    matplotlib.use("svg")  # a user's choice (in Jupyter: the inline backend)
    import jax
    for name in json.loads(sys.argv[1]):  # what other packages do as they load is theirs
        importlib.import_module(name)
    jax.devices()  # jaxlib's backend sets TF_CPP_MIN_LOG_LEVEL when it starts
    config = {k: getattr(jax.config, k) for k in ("jax_enable_x64", "jax_compilation_cache_dir", "jax_numpy_rank_promotion", "jax_default_matmul_precision")}
    environ, cwd, filters = dict(os.environ), os.getcwd(), list(warnings.filters)
    import esther_jax, fitting
    modules = []
    for package in (esther_jax, fitting):
        for info in pkgutil.walk_packages(package.__path__, package.__name__ + "."):
            if not info.name.endswith("__main__"):
                importlib.import_module(info.name)
                modules.append(info.name)
    from esther_jax import compilation
    print(json.dumps({
        "modules": len(modules),
        "backend": matplotlib.get_backend(),
        "pyplot": "matplotlib.pyplot" in sys.modules,
        "config": {k: getattr(jax.config, k) for k in config} == config,
        "environ": dict(os.environ) == environ,
        "cwd": os.getcwd() == cwd,
        "filters": list(warnings.filters) == filters,
        "processes": started,
        "source_digest_computed": compilation._source_digest.cache_info().currsize,
        "others": sorted(m for m in sys.modules if not m.startswith(("esther_jax", "fitting", "_")) and "." not in m),
    }))
    """
)


def test_importing_every_module_leaves_the_process_untouched():
    def probe(preload: list[str]) -> dict:
        out = subprocess.run([sys.executable, "-c", PROBE, json.dumps(preload)], capture_output=True, text=True, timeout=300, cwd=ROOT)
        assert out.returncode == 0, out.stderr[-3000:]
        return json.loads(out.stdout.strip().splitlines()[-1])

    others = [m for m in probe([])["others"] if m not in ("matplotlib", "subprocess")]
    report = probe(others)
    assert report["modules"] > 40
    assert report["backend"] == "svg" and not report["pyplot"]
    assert report["config"], "importing the library changed JAX's configuration"
    assert report["environ"], "importing the library changed os.environ"
    assert report["cwd"], "importing the library changed the working directory"
    assert report["filters"], "importing the library changed the warning filters"
    assert report["processes"] == []
    assert report["source_digest_computed"] == 0
