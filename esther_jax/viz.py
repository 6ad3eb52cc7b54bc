"""Quick matplotlib figures of hand meshes (PNG, no screen needed).

A lightweight look at a mesh for demos and reports; the synthetic data engine has its
own z-buffer renderer for images that networks consume.
"""

import pathlib

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402
from mpl_toolkits.mplot3d.art3d import Poly3DCollection  # noqa: E402

from .files import atomic_output  # noqa: E402

_LIGHT = np.array([0.3, 0.8, 0.5]) / np.linalg.norm([0.3, 0.8, 0.5])


def plot_hand_meshes(
    meshes: list[tuple[str, np.ndarray, np.ndarray]],
    path: str | pathlib.Path,
    *,
    elevation: float = 25.0,
    azimuth: float = -60.0,
) -> pathlib.Path:
    """One Lambert-shaded panel per (title, vertices (V, 3) metres, faces (F, 3)); saves a PNG."""
    path = pathlib.Path(path)
    fig = plt.figure(figsize=(3.2 * len(meshes), 3.4))
    for i, (title, vertices, faces) in enumerate(meshes):
        ax = fig.add_subplot(1, len(meshes), i + 1, projection="3d")
        tri = np.asarray(vertices)[np.asarray(faces)]
        normal = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
        normal /= np.linalg.norm(normal, axis=1, keepdims=True) + 1e-12
        shade = 0.35 + 0.65 * np.clip(normal @ _LIGHT, 0.0, 1.0)
        colors = np.stack([0.93 * shade, 0.72 * shade, 0.60 * shade, np.ones_like(shade)], axis=1)
        ax.add_collection3d(Poly3DCollection(tri, facecolors=colors, edgecolor="none"))
        centre = np.asarray(vertices).mean(axis=0)
        radius = 0.5 * np.ptp(np.asarray(vertices), axis=0).max()
        for setter, c in zip((ax.set_xlim, ax.set_ylim, ax.set_zlim), centre):
            setter(c - radius, c + radius)
        ax.set_box_aspect((1, 1, 1))
        ax.view_init(elev=elevation, azim=azimuth)
        ax.set_title(title, fontsize=9)
        ax.axis("off")
    fig.tight_layout()
    with atomic_output(path) as tmp:
        fig.savefig(tmp, dpi=90)
    plt.close(fig)
    return path
