"""Small file helpers shared by the loaders and writers (one place for their error
messages, their atomic writes and their output-folder checks)."""

import contextlib
import functools
import fcntl
import glob
import hashlib
import json
import math
import os
import pathlib
import shutil
import subprocess
import uuid
from collections.abc import Iterable, Iterator

import numpy as np


def read_json(path: str | pathlib.Path, error: type[ValueError] = ValueError) -> dict:
    """Parse a JSON file holding an object (every JSON file of the project does), raising
    `error` that names the file and what is wrong."""
    path = pathlib.Path(path)
    try:
        value = json.loads(path.read_text())
    except OSError as err:
        raise error(f"cannot read {path}: {err.strerror or err}") from err
    except (json.JSONDecodeError, UnicodeDecodeError) as err:
        where = f"{err.msg} at line {err.lineno}" if isinstance(err, json.JSONDecodeError) else "not UTF-8 text"
        raise error(f"{path} is not valid JSON ({where})") from err
    if not isinstance(value, dict):
        raise error(f"{path} must hold a JSON object, not a {type(value).__name__}")
    return value


@contextlib.contextmanager
def atomic_output(path: str | pathlib.Path) -> Iterator[pathlib.Path]:
    """A fresh temporary path beside `path` (same suffix, unique to this writer); renamed
    onto `path` when the block succeeds, removed when it fails. Readers never see a
    half-written file, and two writers never share a temporary file."""
    path = pathlib.Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(f".{path.stem}.{uuid.uuid4().hex[:12]}.tmp{path.suffix}")
    try:
        yield tmp
        os.replace(tmp, path)
    finally:
        tmp.unlink(missing_ok=True)


def strict_json(value):
    """`value` with numpy scalars and arrays as Python numbers and lists, and every NaN or
    infinity as None: what strict JSON (RFC 8259) can carry."""
    if isinstance(value, dict):
        return {str(k): strict_json(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [strict_json(v) for v in value]
    if isinstance(value, np.ndarray):
        return strict_json(value.tolist())
    if isinstance(value, (np.bool_, bool)):
        return bool(value)
    if isinstance(value, (np.integer, int)):
        return int(value)
    if isinstance(value, (np.floating, float)):
        return float(value) if math.isfinite(value) else None
    return value


def write_json(path: str | pathlib.Path, value, *, indent: int = 1) -> pathlib.Path:
    """Write strict JSON atomically (NaN and infinities as null)."""
    path = pathlib.Path(path)
    with atomic_output(path) as tmp:
        tmp.write_text(json.dumps(strict_json(value), indent=indent, allow_nan=False))
    return path


@contextlib.contextmanager
def exclusive_lock(path: str | pathlib.Path, *, wait: bool = True) -> Iterator[bool]:
    """An exclusive advisory lock (POSIX `flock`) on the file `path` (created if needed),
    held for the block and released when it ends or the process dies. Yields True when
    held; False at once when `wait` is False and another holder (process or thread) has it.
    The lock file stays: removing it would let a third writer lock a fresh file."""
    with open(path, "a+b") as handle:
        try:
            fcntl.flock(handle, fcntl.LOCK_EX | (0 if wait else fcntl.LOCK_NB))
        except BlockingIOError:
            yield False
            return
        try:
            yield True
        finally:
            fcntl.flock(handle, fcntl.LOCK_UN)


def remove_stale_partials(parent: pathlib.Path, name: str) -> None:
    """Remove `parent/.<name>.partial-*` folders left by interrupted writers of `name`
    (call it holding `name`'s lock: nobody else is writing one)."""
    for stale in parent.glob(glob.escape(f".{name}.partial") + "*"):
        shutil.rmtree(stale, ignore_errors=True)


def check_out_dir(path: str | pathlib.Path, what: str = "--out") -> pathlib.Path:
    """Create the output folder `path` if needed and check that it can be written, before
    any long work starts; a `ValueError` names the problem (a file, not writable)."""
    path = pathlib.Path(path)
    if path.exists() and not path.is_dir():
        raise ValueError(f"{what} {path} is a file, not a folder")
    try:
        path.mkdir(parents=True, exist_ok=True)
        probe = path / f".write-test.{uuid.uuid4().hex[:12]}"
        probe.write_bytes(b"")
        probe.unlink()
    except OSError as err:
        raise ValueError(f"{what} {path} cannot be written: {err.strerror or err}") from err
    return path


def file_sha256(path: str | pathlib.Path) -> str:
    """The sha256 (hex) of a file's bytes, read in 1 MiB blocks."""
    digest = hashlib.sha256()
    with open(path, "rb") as f:
        for block in iter(lambda: f.read(1 << 20), b""):
            digest.update(block)
    return digest.hexdigest()


@functools.cache
def git_revision() -> str | None:
    """The commit of this checkout of esther_jax (None outside a git checkout), recorded
    with runs and reports so a number can be traced to the code that made it. Read once per
    process, at the first call (runs and studies call it when they start, not at import): a
    process that runs for hours keeps the commit it started with, not the HEAD the checkout
    has moved to meanwhile."""
    try:
        root = pathlib.Path(__file__).resolve().parents[1]
        out = subprocess.run(["git", "-C", str(root), "rev-parse", "HEAD"], capture_output=True, text=True, timeout=5)
        return out.stdout.strip() or None
    except (OSError, subprocess.SubprocessError):
        return None


def named_folders(folders: Iterable[str | pathlib.Path], what: str = "clip folders") -> list[pathlib.Path]:
    """`folders` as absolute, normalised paths (symlinks kept: a link's name is its clip's
    name), each once, in their order: what a batch whose outputs are keyed by folder
    name (`OUT/<name>`) runs over. ValueError when a folder has no name (`/`) or two
    folders share a name (their outputs would overwrite each other); `what` names them."""
    unique = list(dict.fromkeys(pathlib.Path(os.path.abspath(f)) for f in folders))
    names: dict[str, pathlib.Path] = {}
    for folder in unique:
        if not folder.name:
            raise ValueError(f"{folder} has no folder name to key its output by; give a folder below it")
        if names.setdefault(folder.name, folder) != folder:
            raise ValueError(f"two {what} share the name {folder.name!r}: {names[folder.name]} and {folder}; their outputs would overwrite each other")
    return unique
