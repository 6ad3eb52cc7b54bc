"""Mesh export of a forward pass (.obj, .ply, .glb, ... through trimesh)."""

import pathlib

import numpy as np
import trimesh
from jaxtyping import Array, Float, Int

from ..files import atomic_output
from .model import ManoModel, ManoOutput


def to_trimesh(
    vertices: Float[Array | np.ndarray, "verts 3"], faces: Int[Array | np.ndarray, "faces 3"]
) -> trimesh.Trimesh:
    """A trimesh of one posed hand (vertices in metres, faces as in the model)."""
    return trimesh.Trimesh(np.asarray(vertices, np.float64), np.asarray(faces), process=False)


def export_mesh(model: ManoModel, output: ManoOutput, path: str | pathlib.Path) -> pathlib.Path:
    """Write the mesh of `forward(model, params)` to `path`; the suffix picks the format
    (.obj, .ply, .glb, .stl, .off). Written atomically."""
    path = pathlib.Path(path)
    suffix = path.suffix.lower().lstrip(".")
    if suffix not in ("obj", "ply", "glb", "gltf", "stl", "off"):
        raise ValueError(f"unsupported mesh format '.{suffix}' for {path}; use .obj, .ply, .glb, .stl or .off")
    if output.vertices.ndim != 2:
        raise ValueError(f"export one hand at a time; got vertices of shape {output.vertices.shape}")
    mesh = to_trimesh(output.vertices, model.faces)
    with atomic_output(path) as tmp:
        mesh.export(tmp, file_type=suffix)
    return path
