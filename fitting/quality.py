"""Label quality (appendix A stage two and appendix N).

- Residual r per hand-frame: mean pixel distance between the label's 21 joints
  projected into both views and the fused keypoints, over all (view, joint) pairs whose
  fused confidence exceeds tau = 0.3; hand-frames with r > 15 px are rejected.
- Label-quality table over the passing hand-frames: r; hand (wrist) depth z; in-plane
  error r z / f; depth per pixel of disparity z^2 / (f b); admissible depth error for
  independent views sqrt(2) r z^2 / (f b) and worst case 2 r z^2 / (f b); median /
  mean / p90 of each, and the share of hand-frames that pass.
"""

import numpy as np

from esther_jax.cameras import StereoRig

REJECT_PX = 15.0


def reprojection_residual(uv_label: np.ndarray, uv_fused: np.ndarray, conf: np.ndarray, tau: float = 0.3) -> np.ndarray:
    """(T,) residual r in pixels (NaN where no joint exceeds tau in either view).

    Args:
        uv_label: label joints projected into both views (T, 2, 21, 2).
        uv_fused, conf: fused keypoints (T, 2, 21, 2) and confidences (T, 2, 21).
    """
    used = conf > tau
    distance = np.linalg.norm(uv_label - uv_fused, axis=-1)
    count = used.sum(axis=(1, 2))
    total = np.where(used, distance, 0.0).sum(axis=(1, 2))
    return np.where(count > 0, total / np.maximum(count, 1), np.nan)


def quality_table(residual_px: np.ndarray, depth_m: np.ndarray, passing: np.ndarray, rig: StereoRig) -> dict:
    """Appendix N's table (mm and px) over passing hand-frames, and the pass rate."""
    f = float(rig.left.fx)
    b = float(rig.baseline)
    r = residual_px[passing]
    z = depth_m[passing]
    per_px = z**2 / (f * b)  # metres of depth per pixel of disparity
    quantities = {
        "reprojection_residual_px": r,
        "hand_depth_m": z,
        "in_plane_error_mm": r * z / f * 1000.0,
        "depth_per_disparity_px_mm": per_px * 1000.0,
        "admissible_depth_error_independent_mm": np.sqrt(2.0) * r * per_px * 1000.0,
        "admissible_depth_error_worst_mm": 2.0 * r * per_px * 1000.0,
    }
    table = {}
    for name, values in quantities.items():
        values = values[np.isfinite(values)]
        table[name] = (
            {"median": float(np.median(values)), "mean": float(np.mean(values)), "p90": float(np.percentile(values, 90))}
            if values.size
            else None
        )
    observed = np.isfinite(residual_px)
    share = float(passing.sum() / max(observed.sum(), 1))
    below10 = float(np.mean(r < 10.0)) if r.size else float("nan")
    return {"table": table, "share_passing": share, "share_of_passing_below_10px": below10, "hand_frames_observed": int(observed.sum())}
