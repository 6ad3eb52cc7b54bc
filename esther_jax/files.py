"""Small file helpers shared by the loaders (one place for their error messages)."""

import json
import pathlib


def read_json(path: str | pathlib.Path, error: type[ValueError] = ValueError) -> dict:
    """Parse a JSON file, raising `error` that names the file and what is wrong."""
    path = pathlib.Path(path)
    try:
        return json.loads(path.read_text())
    except OSError as err:
        raise error(f"cannot read {path}: {err.strerror or err}") from err
    except json.JSONDecodeError as err:
        raise error(f"{path} is not valid JSON ({err.msg} at line {err.lineno})") from err
