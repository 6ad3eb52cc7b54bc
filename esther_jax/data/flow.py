"""The camera-motion flow token of appendix D.

Between consecutive hand-following crops (each with its own intrinsics K_t), the
previous crop is first warped by the homography H = K_{t+1} K_t^{-1} into the current
crop's pixel coordinates, which cancels the crop window's own motion; dense classical
optical flow (OpenCV DIS) on that compensated pair is median-pooled over an 8 x 8 grid,
divided by 224 (the crop side of the paper), and paired with a per-cell in-frame flag:

    f_t = [vec(F_t / 224), vec(M_t)]  in R^192   (128 flow values, 64 flags)

Flags mark cells whose pixels mostly come from inside both source images (the warped
previous crop and the current crop can reach outside their camera's image, where there
is nothing to measure). The first frame of a clip has no predecessor: its token is
zero with all flags 0. Computed online, frame by frame.
"""

import cv2
import numpy as np

from ..clips import FLOW_GRID, FLOW_TOKEN_SIZE

NORMALISER_PX = 224.0

_dis = None


def _flow_estimator():
    global _dis
    if _dis is None:
        _dis = cv2.DISOpticalFlow_create(cv2.DISOPTICAL_FLOW_PRESET_MEDIUM)
    return _dis


def _gray(image: np.ndarray) -> np.ndarray:
    return image if image.ndim == 2 else cv2.cvtColor(image, cv2.COLOR_RGB2GRAY)


def flow_token(
    previous: np.ndarray,
    current: np.ndarray,
    K_previous: np.ndarray,
    K_current: np.ndarray,
    valid_previous: np.ndarray | None = None,
    valid_current: np.ndarray | None = None,
) -> np.ndarray:
    """(192,) float32 token from two consecutive S x S crops and their intrinsics.

    Args:
        previous, current: uint8 crops (S, S[, 3]).
        K_previous, K_current: their 3x3 intrinsics (pixels of the crop).
        valid_previous, valid_current: optional (S, S) masks of pixels that come from
            inside the source image (default: all).
    """
    size = current.shape[0]
    H = np.asarray(K_current, np.float64) @ np.linalg.inv(np.asarray(K_previous, np.float64))
    warped = cv2.warpPerspective(_gray(previous), H, (size, size), flags=cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)
    flow = _flow_estimator().calc(warped, _gray(current), None)  # (S, S, 2), pixels
    ones = np.ones((size, size), np.float32)
    vp = ones if valid_previous is None else valid_previous.astype(np.float32)
    vc = ones if valid_current is None else valid_current.astype(np.float32)
    warped_valid = cv2.warpPerspective(vp, H, (size, size), flags=cv2.INTER_NEAREST, borderValue=0.0)
    valid = (warped_valid > 0.5) & (vc > 0.5)
    cell = size // FLOW_GRID
    cells = flow[: cell * FLOW_GRID, : cell * FLOW_GRID].reshape(FLOW_GRID, cell, FLOW_GRID, cell, 2).transpose(0, 2, 1, 3, 4).reshape(FLOW_GRID, FLOW_GRID, -1, 2)
    pooled = np.median(cells, axis=2)
    in_frame = valid[: cell * FLOW_GRID, : cell * FLOW_GRID].reshape(FLOW_GRID, cell, FLOW_GRID, cell).mean(axis=(1, 3)) > 0.5
    pooled = np.where(in_frame[..., None], pooled, 0.0)
    return np.concatenate([(pooled / NORMALISER_PX).reshape(-1), in_frame.reshape(-1).astype(np.float32)]).astype(np.float32)


def clip_flow_tokens(crops: np.ndarray, K: np.ndarray, valid: np.ndarray | None = None) -> np.ndarray:
    """(T, 192) tokens of a crop sequence (T, S, S[, 3]) with intrinsics (T, 3, 3)."""
    tokens = np.zeros((len(crops), FLOW_TOKEN_SIZE), np.float32)
    for t in range(1, len(crops)):
        tokens[t] = flow_token(
            crops[t - 1], crops[t], K[t - 1], K[t], None if valid is None else valid[t - 1], None if valid is None else valid[t]
        )
    return tokens
