"""Human review (the third filter stage): reprojected labels drawn over both views.

`review_sheet` writes a contact sheet of the hand-frames the automatic filters flagged
(or any frames asked for): per frame, the left and right views with the fused 2D
keypoints (dots, coloured by confidence) and the label's skeleton reprojected through
the rig. A reviewer lists the frames to reject in a `clip,side,frame` file and passes it
back with `esther label ... --reject FILE`.
"""

import pathlib

import cv2
import jax.numpy as jnp
import numpy as np

from esther_jax import clips
from esther_jax.cameras import StereoRig
from esther_jax.files import atomic_output
from esther_jax.mano import KEYPOINT_PARENTS

_FINGER_COLOURS = [(255, 255, 255)] + [(230, 80, 80)] * 4 + [(240, 200, 60)] * 4 + [(80, 200, 90)] * 4 + [(70, 150, 240)] * 4 + [(200, 90, 220)] * 4


def draw_skeleton(image: np.ndarray, uv: np.ndarray, thickness: int = 2) -> np.ndarray:
    out = image.copy() if image.ndim == 3 else cv2.cvtColor(image, cv2.COLOR_GRAY2RGB)
    for j, p in enumerate(KEYPOINT_PARENTS):
        if p >= 0 and np.all(np.isfinite(uv[[j, p]])):
            cv2.line(out, tuple(int(v) for v in uv[j]), tuple(int(v) for v in uv[p]), _FINGER_COLOURS[j], thickness, cv2.LINE_AA)
    return out


def draw_keypoints(image: np.ndarray, uv: np.ndarray, conf: np.ndarray, radius: int = 4) -> np.ndarray:
    out = image.copy()
    for (u, v), c in zip(uv, conf):
        if c > 0:
            cv2.circle(out, (int(u), int(v)), radius, (int(255 * (1 - c)), int(255 * c), 40), -1, cv2.LINE_AA)
    return out


def overlay_mesh(image: np.ndarray, uv: np.ndarray, depth: np.ndarray, faces: np.ndarray, colour, alpha: float = 0.5) -> np.ndarray:
    """Blend a projected mesh (vertex pixels and depths) over an image, far faces first."""
    out = image.copy() if image.ndim == 3 else cv2.cvtColor(image, cv2.COLOR_GRAY2RGB)
    layer = out.copy()
    order = np.argsort(-depth[faces].mean(axis=1))
    tri = uv[faces[order]]
    ok = np.all(np.isfinite(tri), axis=(1, 2)) & np.all(depth[faces[order]] > 0.01, axis=1)
    shade = np.linspace(0.75, 1.0, len(order))
    for t, s in zip(tri[ok], shade[ok]):
        cv2.fillConvexPoly(layer, np.round(t * 4).astype(np.int32), tuple(int(c * s) for c in colour), cv2.LINE_AA, 2)
    return cv2.addWeighted(layer, alpha, out, 1 - alpha, 0)


def contact_sheet(tiles: list[list[np.ndarray]], captions: list[str], path: str | pathlib.Path, width: int = 640) -> pathlib.Path:
    """Rows of equally sized tiles (each row: left view, right view) with a caption each."""
    rows = []
    for tiles_row, caption in zip(tiles, captions):
        scaled = [cv2.resize(t, (width, int(t.shape[0] * width / t.shape[1]))) for t in tiles_row]
        row = np.concatenate(scaled, axis=1)
        cv2.putText(row, caption, (10, 28), cv2.FONT_HERSHEY_SIMPLEX, 0.8, (255, 255, 255), 2, cv2.LINE_AA)
        rows.append(row)
    sheet = np.concatenate(rows, axis=0)
    path = pathlib.Path(path)
    with atomic_output(path) as tmp:
        cv2.imwrite(str(tmp), sheet[..., ::-1])
    return path


def review_sheet(
    rig: StereoRig,
    labels: clips.Labels,
    fused_uv: np.ndarray,
    fused_conf: np.ndarray,
    path: str | pathlib.Path,
    frames: list[int] | None = None,
    images: dict[str, np.ndarray] | None = None,
    max_frames: int = 12,
) -> pathlib.Path | None:
    """Contact sheet of flagged (or the given) frames; None when there is nothing to show.

    Args:
        labels: the hand's labels; fused_uv (T, 2, 21, 2), fused_conf (T, 2, 21).
        images: optional {"left": (T, H, W[, 3]), "right": ...} video frames; grey otherwise.
    """
    if frames is None:
        frames = [int(t) for t in np.flatnonzero(np.asarray(labels.onscreen & ~labels.valid))][:max_frames]
    if not frames:
        return None
    tiles, captions = [], []
    for t in frames:
        uv = np.asarray(rig.project(jnp.asarray(labels.joints[t], rig.T_left_right.dtype)), np.float64)  # (2 views, 21, 2)
        row = []
        for v, (view, camera) in enumerate((("left", rig.left), ("right", rig.right))):
            base = images[view][t] if images else np.full((camera.height, camera.width, 3), 60, np.uint8)
            base = base if base.ndim == 3 else cv2.cvtColor(base, cv2.COLOR_GRAY2RGB)
            row.append(draw_skeleton(draw_keypoints(base, fused_uv[t, v], fused_conf[t, v]), uv[v]))
        tiles.append(row)
        captions.append(f"frame {t}: residual {float(labels.residual_px[t]):.1f} px, valid={bool(labels.valid[t])}" + ("" if labels.stereo is None else f", stereo={bool(labels.stereo[t])}"))
    return contact_sheet(tiles, captions, path)
