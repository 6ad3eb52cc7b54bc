"""Hand-following crop cameras, image warps, fisheye -> pinhole rectification and
Plucker rays (the detect-then-crop convention of the paper, sections 3.4-3.5).

A crop is a virtual pinhole camera `crop_camera` (S x S pixels) plus its rotation
`R_cam_crop` relative to the source camera (identity for axis-aligned crops). Pixel
convention as in `cameras`: centres at integers, so an image crop of side b pixels
resized to S maps `u -> s (u - c_box + b / 2) - 1/2` with `s = S / b` (the +0.5 rule).
"""

import typing

import cv2
import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Bool, Float

from ._math import cross, safe_normalize
from .cameras import AbstractCamera, PinholeCamera

DEFAULT_CROP_SIZE = 224
DEFAULT_BOX_PADDING = 1.25
"""Crop side = padding x the longer side of the hand box (context around the hand)."""


class Crop(eqx.Module):
    """A square hand crop: its virtual pinhole camera and its rotation in the source camera."""

    camera: PinholeCamera
    """Intrinsics of the S x S crop image (pixels)."""
    R_cam_crop: Float[Array, "3 3"]
    """Rotation of the crop camera in the source camera frame (identity when axis-aligned)."""


def square_box(box: Float[Array, "4"], padding: float = DEFAULT_BOX_PADDING) -> tuple[Float[Array, "2"], Float[Array, ""]]:
    """Centre (px) and side b (px) of the square crop window around a box (x0, y0, x1, y1)."""
    centre = 0.5 * (box[:2] + box[2:])
    side = padding * jnp.maximum(box[2] - box[0], box[3] - box[1])
    return centre, side


def crop_camera(
    camera: PinholeCamera, box: Float[Array, "4"], size: int = DEFAULT_CROP_SIZE, padding: float = DEFAULT_BOX_PADDING
) -> Crop:
    """The axis-aligned S x S crop of a pinhole image around a hand box.

    Projecting with the returned camera equals cropping the image to the square window
    and resizing it to S (`crop_affine` + `cv2.warpAffine` do exactly that).
    """
    centre, side = square_box(box, padding)
    s = size / side
    cam = PinholeCamera(
        camera.fx * s,
        camera.fy * s,
        s * (camera.cx - centre[0] + 0.5 * side) - 0.5,
        s * (camera.cy - centre[1] + 0.5 * side) - 0.5,
        size,
        size,
    )
    return Crop(camera=cam, R_cam_crop=jnp.eye(3, dtype=cam.fx.dtype))


def crop_affine(box: Float[Array, "4"], size: int = DEFAULT_CROP_SIZE, padding: float = DEFAULT_BOX_PADDING) -> np.ndarray:
    """2x3 matrix M (full-image pixel -> crop pixel) for `cv2.warpAffine(image, M, (S, S))`."""
    centre, side = (np.asarray(x, np.float64) for x in square_box(jnp.asarray(box), padding))
    s = size / float(side)
    return np.array([[s, 0.0, s * (0.5 * side - centre[0]) - 0.5], [0.0, s, s * (0.5 * side - centre[1]) - 0.5]])


def warp_crop(image: np.ndarray, box, size: int = DEFAULT_CROP_SIZE, padding: float = DEFAULT_BOX_PADDING) -> np.ndarray:
    """Crop and resize an image around a box (bilinear, black outside the image)."""
    M = crop_affine(jnp.asarray(box, jnp.result_type(float)), size, padding)
    return cv2.warpAffine(image, M, (size, size), flags=cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT)


# ----------------------------------------------------------------------------- fisheye rectification

RectificationStrategy = typing.Literal["offbb120", "offbb90", "offbb150", "hc"]
RECTIFICATION_STRATEGIES: tuple[str, ...] = typing.get_args(RectificationStrategy)


def _look_at_rotation(direction: Float[Array, "3"]) -> Float[Array, "3 3"]:
    """Rotation whose z column is `direction`, keeping the source's x axis as horizontal
    as possible (the crop is rolled as little as possible)."""
    z = safe_normalize(direction)
    x = cross(jnp.asarray([0.0, 1.0, 0.0], z.dtype), z)
    x = safe_normalize(x)
    y = cross(z, x)
    return jnp.stack([x, y, z], axis=1)


def box_outline(box: Float[Array, "4"], samples: int = 8) -> Float[Array, "n 2"]:
    """`samples` points along each edge of a box (x0, y0, x1, y1 px): (4 samples, 2)."""
    t = jnp.linspace(0.0, 1.0, samples)
    x0, y0, x1, y1 = box[0], box[1], box[2], box[3]
    top = jnp.stack([x0 + t * (x1 - x0), jnp.full_like(t, y0)], -1)
    bottom = jnp.stack([x0 + t * (x1 - x0), jnp.full_like(t, y1)], -1)
    left = jnp.stack([jnp.full_like(t, x0), y0 + t * (y1 - y0)], -1)
    right = jnp.stack([jnp.full_like(t, x1), y0 + t * (y1 - y0)], -1)
    return jnp.concatenate([top, bottom, left, right])


def wide_pinhole(camera: AbstractCamera, focal: float) -> PinholeCamera:
    """The axis-aligned wide pinhole the whole image of `camera` is undistorted to by the
    offbb strategies (appendix M): virtual focal `focal` px, principal point at the image
    centre, the same image size; its frame is the camera's (no rotation)."""
    return PinholeCamera(focal, focal, (camera.width - 1) / 2, (camera.height - 1) / 2, camera.width, camera.height)


def rectified_crop(
    camera: AbstractCamera,
    box: Float[Array, "4"],
    strategy: str = "offbb120",
    size: int = DEFAULT_CROP_SIZE,
    padding: float = DEFAULT_BOX_PADDING,
) -> Crop:
    """A pinhole crop of a (fisheye) camera around a hand box, for the four strategies of
    the paper's appendix M.

    - `offbb120` / `offbb90` / `offbb150`: the whole image is undistorted to an
      axis-aligned wide pinhole of virtual focal 120 / 90 / 150 px (principal point at
      the image centre, same size); the hand crop is taken from it as from any pinhole
      image. The chain fisheye -> undistort -> crop -> resize is one crop camera.
    - `hc`: a ray-aligned hand crop: the crop camera looks along the ray of the box
      centre and its focal is chosen so the padded box just fills the crop.

    The crop is framed by the rays of the box outline inside the camera's valid field of
    view. A box reaching far beyond a fisheye image (a hand at the edge of its field of
    view) can keep only a ray or two there, which frame a degenerate crop (an infinite
    focal); its crop is then framed by the box clipped to the image, or, were that
    degenerate too, by the whole image.
    """
    if strategy not in RECTIFICATION_STRATEGIES:
        raise ValueError(f"unknown rectification strategy {strategy!r}; choose one of {RECTIFICATION_STRATEGIES}")
    image = jnp.asarray([0.0, 0.0, camera.width - 1.0, camera.height - 1.0], box.dtype)
    clipped = jnp.concatenate([jnp.maximum(box[:2], image[:2]), jnp.minimum(box[2:], image[2:])])
    clipped = jnp.where(jnp.all(clipped[2:] > clipped[:2]), clipped, image)  # a box wholly outside the image
    crop = _framed_crop(camera, image, strategy, size, padding)
    for framing in (clipped, box):  # the first of box, clipped box, image that frames a proper crop
        candidate = _framed_crop(camera, framing, strategy, size, padding)
        focal = jnp.stack([candidate.camera.fx, candidate.camera.fy])
        proper = jnp.all(jnp.isfinite(focal) & (focal > 0)) & jnp.all(jnp.isfinite(candidate.camera.K))
        crop = jax.tree.map(lambda a, b: jnp.where(proper, a, b), candidate, crop)
    return crop


def _framed_crop(camera: AbstractCamera, box: Float[Array, "4"], strategy: str, size: int, padding: float) -> Crop:
    """`rectified_crop` framed by the valid rays of `box`'s outline (possibly degenerate)."""
    outline, outline_ok = camera.unproject_with_validity(box_outline(box))  # rays of the box outline, camera frame
    # Outline pixels beyond the camera's valid field of view (fisheye corners) have
    # mirrored rays that would blow the box up: leave them out (unless all are).
    keep = (outline_ok | ~jnp.any(outline_ok))[:, None]
    if strategy.startswith("offbb"):
        wide = wide_pinhole(camera, float(strategy[len("offbb"):]))
        projected = wide.project(outline)
        wide_box = jnp.concatenate([jnp.where(keep, projected, jnp.inf).min(axis=0), jnp.where(keep, projected, -jnp.inf).max(axis=0)])
        return crop_camera(wide, wide_box, size, padding)
    centre_ray = camera.unproject(0.5 * (box[:2] + box[2:]))
    R = _look_at_rotation(centre_ray)
    in_crop = outline @ R  # rays in the crop frame (R^T x)
    tangent = jnp.abs(in_crop[:, :2] / in_crop[:, 2:3])
    half_extent = padding * jnp.max(jnp.where(keep, tangent, 0.0))
    focal = (size / 2) / half_extent
    c = (size - 1) / 2
    return Crop(camera=PinholeCamera(focal, focal, c, c, size, size), R_cam_crop=R)


HAND_CROP_PADDING = 1.5
"""The network's crops (synthetic and recorded alike): crop side = 1.5 x the hand box."""
MIN_HAND_BOX_PX = 40.0
"""`hand_box` never makes a box smaller than this (px): a far hand keeps some context."""


def hand_box(uv: Float[np.ndarray, "*batch n 2"], size_floor: float = MIN_HAND_BOX_PX) -> Float[np.ndarray, "*batch 4"]:
    """The square box (x0, y0, x1, y1, px) of a hand's 2D keypoints: centred on their
    extent, its side their longer extent (at least `size_floor`). Keypoints with a NaN
    coordinate are left out; a box of no keypoint is NaN."""
    uv = np.asarray(uv, np.float64)
    seen = np.all(np.isfinite(uv), axis=-1, keepdims=True)
    lo, hi = np.where(seen, uv, np.inf).min(axis=-2), np.where(seen, uv, -np.inf).max(axis=-2)
    with np.errstate(invalid="ignore"):  # no keypoint: inf - inf, NaN below
        centre, half = 0.5 * (lo + hi), np.maximum(0.5 * np.max(hi - lo, axis=-1), size_floor / 2)[..., None]
    return np.where(np.any(seen, axis=-2), np.concatenate([centre - half, centre + half], axis=-1), np.nan)


def smooth_boxes(boxes: Float[np.ndarray, "T 4"]) -> Float[np.ndarray, "T 4"]:
    """Boxes smoothed over time as a tracker's crop window would be (float32, as crops
    files store them): a Gaussian of one frame's deviation (5 taps, edges reflected)
    over each run of at least 5 frames with a box; frames without a box (NaN) stay NaN,
    shorter runs as they are."""
    boxes = np.asarray(boxes, np.float32)
    out = boxes.copy()
    finite = np.all(np.isfinite(boxes), axis=-1)
    edges = np.flatnonzero(np.diff(np.concatenate([[0], finite.astype(np.int8), [0]])))
    for start, stop in zip(edges[::2], edges[1::2]):
        if stop - start >= 5:
            out[start:stop] = cv2.GaussianBlur(boxes[start:stop, None], (1, 5), 1.0)[:, 0]
    return out


def hand_crop(
    camera: AbstractCamera, box: Float[Array, "4"], strategy: str = "offbb120", size: int = DEFAULT_CROP_SIZE, padding: float = HAND_CROP_PADDING
) -> Crop:
    """The S x S crop of `strategy` (appendix M) around a hand box. On a pinhole camera
    the offbb strategies are the axis-aligned crop (`crop_camera`): undistorting a
    pinhole image to another pinhole is an affine map of its pixels, which leaves the
    crop window's camera as it is, whatever the virtual focal; otherwise
    `rectified_crop`."""
    if isinstance(camera, PinholeCamera) and strategy != "hc":
        return crop_camera(camera, box, size, padding)
    return rectified_crop(camera, box, strategy, size, padding)


def crop_coverage(camera: AbstractCamera, crop: Crop) -> Bool[np.ndarray, "H W"]:
    """The crop pixels that come from inside the source image."""
    axis_aligned = np.array_equal(np.asarray(crop.R_cam_crop), np.eye(3))
    if isinstance(camera, PinholeCamera) and axis_aligned:  # the window's overlap with the image
        S = crop.camera.width
        scale = float(camera.fx) / float(crop.camera.fx)
        u = (np.arange(S) - float(crop.camera.cx)) * scale + float(camera.cx)
        v = (np.arange(S) - float(crop.camera.cy)) * scale + float(camera.cy)
        return ((v[:, None] >= -0.5) & (v[:, None] < camera.height - 0.5)) & ((u[None] >= -0.5) & (u[None] < camera.width - 0.5))
    return table_coverage(np.asarray(rectification_map(camera, crop)), camera)


def table_coverage(table: Float[np.ndarray, "H W 2"], camera: AbstractCamera) -> Bool[np.ndarray, "H W"]:
    """The crop pixels whose source pixel (a `rectification_map` table) lies in the image."""
    u, v = table[..., 0], table[..., 1]
    return (u >= -0.5) & (u < camera.width - 0.5) & (v >= -0.5) & (v < camera.height - 0.5)


def rectification_map(camera: AbstractCamera, crop: Crop) -> Float[Array, "H W 2"]:
    """For every pixel of the crop camera's H x W image (S x S for a hand crop; the source
    image's size for a `wide_pinhole`), the source-image pixel to sample: `cv2.remap(image,
    map[..., 0], map[..., 1], cv2.INTER_LINEAR)` renders the crop. A crop pixel whose ray
    points behind the camera (an `hc` crop turned towards the edge of a fisheye's field:
    `project` folds such a ray back into the image, onto the pixel of its mirror image)
    maps far outside the image: black, and not covered (`table_coverage`)."""
    dtype = crop.camera.fx.dtype
    v, u = jnp.meshgrid(jnp.arange(crop.camera.height, dtype=dtype), jnp.arange(crop.camera.width, dtype=dtype), indexing="ij")
    rays_crop = crop.camera.unproject(jnp.stack([u, v], -1))
    rays_cam = rays_crop @ crop.R_cam_crop.T
    return jnp.where(rays_cam[..., 2:3] > 0, camera.project(rays_cam), -float(camera.width + camera.height))


def remap_crop(image: np.ndarray, camera: AbstractCamera, crop: Crop) -> np.ndarray:
    """Render a rectified crop from a source image (bilinear; black outside the image)."""
    return remap_table(image, np.asarray(rectification_map(camera, crop), np.float32))


def remap_table(image: np.ndarray, table: Float[np.ndarray, "H W 2"]) -> np.ndarray:
    """Sample an image at a `rectification_map` table's source pixels (bilinear; black outside)."""
    table = np.asarray(table, np.float32)
    return cv2.remap(image, table[..., 0], table[..., 1], cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT)


# ----------------------------------------------------------------------------- Plucker rays


def patch_centres(size: int, grid: int) -> Float[Array, "grid grid 2"]:
    """Pixel coordinates (u, v) of the centres of a grid x grid patch tiling of an S x S crop."""
    step = size / grid
    c = (jnp.arange(grid, dtype=jnp.result_type(float)) + 0.5) * step - 0.5
    v, u = jnp.meshgrid(c, c, indexing="ij")
    return jnp.stack([u, v], -1)


def crop_poses(R_cam_crop: Float[Array, "*batch views 3 3"], T_rig_cams: Float[Array, "views 4 4"]) -> Float[Array, "*batch views 4 4"]:
    """Pose `T_rig_crop` of each view's crop camera in the rig frame: the source camera's
    pose with the crop's rotation `R_cam_crop` applied (same centre)."""
    R = jnp.einsum("vij,...vjk->...vik", T_rig_cams[:, :3, :3], R_cam_crop)
    t = jnp.broadcast_to(T_rig_cams[:, :3, 3], R.shape[:-1])
    top = jnp.concatenate([R, t[..., None]], axis=-1)
    bottom = jnp.broadcast_to(jnp.asarray([0.0, 0.0, 0.0, 1.0], R.dtype), R.shape[:-2] + (1, 4))
    return jnp.concatenate([top, bottom], axis=-2)


def plucker_rays(crop: Crop, T_rig_cam: Float[Array, "4 4"], grid: int) -> Float[Array, "grid grid 6"]:
    """Plucker coordinates (unit direction d, moment m = o x d) in the rig frame of the
    rays through the patch centres of a crop (grid = S for every pixel).

    Args:
        crop: the crop camera and its rotation in its source camera.
        T_rig_cam: pose of the source camera in the rig frame.
        grid: patches per side (S / patch size, e.g. 224 / 16 = 14).
    """
    uv = patch_centres(crop.camera.width, grid)
    R_rig_crop = T_rig_cam[:3, :3] @ crop.R_cam_crop
    directions = safe_normalize(crop.camera.unproject(uv) @ R_rig_crop.T)
    origin = jnp.broadcast_to(T_rig_cam[:3, 3], directions.shape)
    return jnp.concatenate([directions, cross(origin, directions)], axis=-1)


__all__ = [
    "RECTIFICATION_STRATEGIES",
    "Crop",
    "box_outline",
    "crop_affine",
    "crop_camera",
    "crop_poses",
    "patch_centres",
    "plucker_rays",
    "rectification_map",
    "rectified_crop",
    "remap_crop",
    "square_box",
    "warp_crop",
    "wide_pinhole",
]


def resize_crops(images: np.ndarray, K: np.ndarray, size: int) -> tuple[np.ndarray, np.ndarray]:
    """Stored crops `images` (..., S, S, 3) RGB or (..., S, S) grey, resized to `size` x
    `size` pixels, and their intrinsics `K (..., 3, 3)` scaled with them (pixel-centre
    convention: a pixel centre u maps to scale (u + 0.5) - 0.5), so the crop cameras
    still project the scene onto the resized pixels. Area averaging when shrinking,
    bilinear when enlarging. The one place where crops change size."""
    images, K = np.asarray(images), np.asarray(K, np.float64)
    rgb = images.shape[-1] == 3
    square = images.shape[-3:-1] if rgb else images.shape[-2:]
    if len(square) != 2 or square[0] != square[1]:
        raise ValueError(f"crops must be (..., S, S, 3) or (..., S, S); got {images.shape}")
    if size < 1:
        raise ValueError(f"crop size must be positive, got {size}")
    S = square[0]
    if size == S:
        return images, K
    scale = size / S
    interpolation = cv2.INTER_AREA if scale < 1 else cv2.INTER_LINEAR
    lead = images.shape[: -3 if rgb else -2]
    flat = images.reshape((-1,) + images.shape[len(lead):])
    resized = np.stack([cv2.resize(im, (size, size), interpolation=interpolation) for im in flat])
    return resized.reshape(lead + resized.shape[1:]), resize_intrinsics(K, S, size)


def resize_intrinsics(K: Float[np.ndarray, "*batch 3 3"], source_size: int, size: int) -> Float[np.ndarray, "*batch 3 3"]:
    """The intrinsics of S x S crops (`source_size` S) as those of the crops resized to
    `size` x `size` (`resize_crops`; pixel-centre convention), e.g. for cached features."""
    K = np.array(K, np.float64)
    scale = size / source_size
    K[..., :2, :2] *= scale
    K[..., :2, 2] = scale * (K[..., :2, 2] + 0.5) - 0.5
    return K
