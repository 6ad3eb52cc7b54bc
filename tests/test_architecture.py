"""The package map is the code's: import-linter's layers contract (pyproject.toml's
`[tool.importlinter]`: apps > train > peers > clip format > hand model > core) is kept, it breaks when
a peer imports a floor above it, and docs/architecture.md's map names its layers."""

import pathlib
import re
import shutil
import subprocess
import sys
import tomllib

import pytest

pytest.importorskip("importlinter")

ROOT = pathlib.Path(__file__).resolve().parents[1]
LINT = "import sys; from importlinter.cli import lint_imports; sys.exit(lint_imports(config_filename='pyproject.toml', no_cache=True, no_logo=True))"


def _lint(root: pathlib.Path) -> subprocess.CompletedProcess:
    """`lint-imports` on the packages under `root` (its pyproject.toml's contract)."""
    return subprocess.run([sys.executable, "-c", LINT], cwd=root, capture_output=True, text=True, env={"PYTHONPATH": str(root), "PATH": ""})


def _layers() -> list[str]:
    (contract,) = tomllib.loads((ROOT / "pyproject.toml").read_text())["tool"]["importlinter"]["contracts"]
    return contract["layers"]


def test_layers_contract_is_kept():
    result = _lint(ROOT)
    assert result.returncode == 0, result.stdout + result.stderr
    assert "1 kept, 0 broken" in result.stdout


def test_layers_contract_breaks_when_a_peer_imports_upwards(tmp_path):
    for package in ("esther_jax", "fitting"):
        shutil.copytree(ROOT / package, tmp_path / package, ignore=shutil.ignore_patterns("__pycache__", "assets"))
    shutil.copy(ROOT / "pyproject.toml", tmp_path)
    fusion = tmp_path / "fitting" / "fusion.py"
    fusion.write_text(fusion.read_text() + "\nfrom esther_jax.train import losses  # a peer reaching into the floor above\n")
    result = _lint(tmp_path)
    assert result.returncode == 1, result.stdout + result.stderr
    assert "fitting.fusion -> esther_jax.train.losses" in result.stdout


def test_architecture_doc_draws_the_contract():
    doc = (ROOT / "docs" / "architecture.md").read_text()
    block = re.search(r"## Package map\n.*?```text\n(.*?)```", doc, re.S)
    assert block, "docs/architecture.md has no '## Package map' section with a text block"
    drawn = block.group(1)
    for layer in _layers():
        for module in re.split(r"[|:]", layer):
            name = module.strip().removeprefix("esther_jax.")
            assert re.search(rf"\b{re.escape(name)}\b", drawn), f"the map in docs/architecture.md does not name {module.strip()}"
