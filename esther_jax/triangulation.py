"""Confidence-weighted, differentiable triangulation and the monocular unit conversion.

`triangulate` solves the DLT of any number of views in normalised camera coordinates:
for a view with `X_cam = R^T (X - t)` and normalised observation `(x, y)` (the
camera's `unproject`, so fisheye views work too), the two rows are
`x * X_cam[2] - X_cam[0] = 0` and `y * X_cam[2] - X_cam[1] = 0`, i.e. the depth times
the normalised reprojection error: about the metric distance of X from the ray. Rows
are multiplied by the view's weight w (EasyMocap's convention), so the 3x3 normal
equations `sum w^2 a a^T X = sum w^2 a b` depend smoothly on w and stay differentiable
when a weight goes to zero; they are solved in closed form (adjugate, a few dozen
flops: no batched SVD). Rank-deficient systems (one view or none, parallel rays)
are swapped for a harmless one, so every output and gradient stays finite; degenerate
cases are reported through `valid`, never as NaN.
"""

import equinox as eqx
import jax
import jax.numpy as jnp
from jaxtyping import Array, Bool, Float, Int

from ._math import cross, eps, safe_norm
from .cameras import AbstractCamera, PinholeCamera, StereoRig

MIN_WEIGHT = 1e-3
"""Views with a weight at or below this do not count as observing the point."""
MIN_PARALLAX_RAD = 2e-3
"""Smallest angle between two used rays for a valid point (about 30 m at a 62 mm baseline)."""
MIN_DEPTH_M = 1e-3
"""A valid point is at least this far in front of every camera that observes it."""


class Triangulation(eqx.Module):
    """A triangulated point with its diagnostics."""

    point: Float[Array, "3"]
    """The point in the rig frame (metres)."""
    valid: Bool[Array, ""]
    """At least two views with weight, in front of each of them, rays not near-parallel."""
    residual_px: Float[Array, "views"]
    """Reprojection error of the point in each view (pixels; reported for every view)."""
    spread: Float[Array, ""]
    """Weighted RMS distance (m) between the point and the used rays: how far apart they pass."""
    num_views: Int[Array, ""]
    """Number of views with weight above MIN_WEIGHT."""


def _det3(M: Float[Array, "3 3"]) -> Float[Array, ""]:
    return (
        M[0, 0] * (M[1, 1] * M[2, 2] - M[1, 2] * M[2, 1])
        - M[0, 1] * (M[1, 0] * M[2, 2] - M[1, 2] * M[2, 0])
        + M[0, 2] * (M[1, 0] * M[2, 1] - M[1, 1] * M[2, 0])
    )


def _solve_symmetric3(M: Float[Array, "3 3"], b: Float[Array, "3"]) -> Float[Array, "3"]:
    """`M^-1 b` by the adjugate (M symmetric positive definite)."""
    a, d, e = M[0, 0], M[1, 1], M[2, 2]
    f, g, h = M[0, 1], M[0, 2], M[1, 2]
    c00 = d * e - h * h
    c01 = g * h - f * e
    c02 = f * h - g * d
    c11 = a * e - g * g
    c12 = f * g - a * h
    c22 = a * d - f * f
    det = a * c00 + f * c01 + g * c02
    x = (c00 * b[0] + c01 * b[1] + c02 * b[2]) / det
    y = (c01 * b[0] + c11 * b[1] + c12 * b[2]) / det
    z = (c02 * b[0] + c12 * b[1] + c22 * b[2]) / det
    return jnp.stack([x, y, z])


def triangulate(
    cameras: AbstractCamera,
    T_rig_cams: Float[Array, "views 4 4"],
    uv: Float[Array, "views 2"],
    weights: Float[Array, "views"],
) -> Triangulation:
    """Triangulate one point seen in several views.

    Args:
        cameras: the views' cameras stacked along a leading axis (e.g. `rig.cameras`).
        T_rig_cams: pose of each camera in the rig frame (`X_rig = T @ X_cam`).
        uv: the observed pixel in each view.
        weights: per-view confidence in [0, 1]; 0 means "not observed".
    Returns:
        `Triangulation` (point in the rig frame, validity, residuals, spread).

    vmap over joints and frames: `jax.vmap(triangulate, in_axes=(None, None, 0, 0))`.
    """
    if uv.ndim != 2 or uv.shape[-1] != 2 or weights.shape != uv.shape[:1] or T_rig_cams.shape != uv.shape[:1] + (4, 4):
        raise ValueError(
            f"triangulate takes one point: uv (views, 2), weights (views,), T_rig_cams (views, 4, 4); "
            f"got {uv.shape}, {weights.shape}, {T_rig_cams.shape}. vmap over joints and frames."
        )
    R = T_rig_cams[:, :3, :3]
    t = T_rig_cams[:, :3, 3]
    finite = jnp.all(jnp.isfinite(uv), axis=-1) & jnp.isfinite(weights)
    w = jnp.where(finite, jnp.clip(weights, 0.0, None), 0.0)
    uv_safe = jnp.where(finite[:, None], uv, 0.0)
    rays_cam = jax.vmap(lambda cam, p: cam.unproject(p))(cameras, uv_safe)  # (V, 3), z = 1
    # rows a . X = b with X_cam = R^T (X - t):  (x e3 - e1) . R^T (X - t) = 0
    e1 = jnp.asarray([1.0, 0.0, 0.0], uv.dtype)
    e2 = jnp.asarray([0.0, 1.0, 0.0], uv.dtype)
    e3 = jnp.asarray([0.0, 0.0, 1.0], uv.dtype)
    row_x = rays_cam[:, 0:1] * e3[None] - e1[None]  # in the camera frame
    row_y = rays_cam[:, 1:2] * e3[None] - e2[None]
    rows = jnp.stack([row_x, row_y], axis=1)  # (V, 2, 3)
    a = jnp.einsum("vki,vji->vkj", rows, R)  # rows in the rig frame: R a_cam
    b = jnp.sum(a * t[:, None, :], axis=-1)  # a . t
    aw = a * w[:, None, None]
    bw = b * w[:, None]
    M = jnp.einsum("vki,vkj->ij", aw, aw)
    rhs = jnp.einsum("vki,vk->i", aw, bw)
    # Rank-deficient systems (fewer than two views, parallel rays) take a harmless
    # identity instead (double where: finite values and gradients); `valid` says so.
    eye = jnp.eye(3, dtype=M.dtype)
    scale = jnp.trace(M) / 3.0
    solvable = _det3(M) > eps(M) * scale**3 + jnp.finfo(M.dtype).tiny
    M_safe = jnp.where(solvable, M + eps(M) * scale * eye, eye)
    point = _solve_symmetric3(M_safe, jnp.where(solvable, rhs, 0.0))

    used = w > MIN_WEIGHT
    num_views = jnp.sum(used.astype(jnp.int32))
    point_cams = jnp.einsum("vji,vj->vi", R, point[None] - t)  # R^T (X - t)
    in_front = jnp.all(jnp.where(used, point_cams[:, 2] > MIN_DEPTH_M, True))
    directions = jnp.einsum("vij,vj->vi", R, rays_cam)
    directions = directions / safe_norm(directions)[:, None]
    pairs = (uv.shape[0], uv.shape[0], 3)
    sines = safe_norm(cross(jnp.broadcast_to(directions[:, None], pairs), jnp.broadcast_to(directions[None], pairs)))
    pair_used = used[:, None] & used[None, :]
    parallax_ok = jnp.max(jnp.where(pair_used, sines, 0.0)) >= jnp.sin(MIN_PARALLAX_RAD)
    valid = (num_views >= 2) & solvable & in_front & parallax_ok & jnp.all(jnp.isfinite(point))

    offsets = point[None] - t
    along = jnp.sum(offsets * directions, axis=-1, keepdims=True)
    distances = safe_norm(offsets - along * directions)
    spread = jnp.sqrt(jnp.sum(w * distances**2) / jnp.maximum(jnp.sum(w), eps(w)))
    projected = jax.vmap(lambda cam, p: cam.project(p))(cameras, point_cams)
    residual_px = safe_norm(projected - uv_safe)
    return Triangulation(point=point, valid=valid, residual_px=residual_px, spread=spread, num_views=num_views)


def triangulate_stereo(rig: StereoRig, uv: Float[Array, "2 2"], weights: Float[Array, "2"]) -> Triangulation:
    """`triangulate` with the two cameras of a stereo rig (views ordered left, right)."""
    return triangulate(rig.cameras, rig.T_rig_cams, uv, weights)


def weak_perspective_to_translation(
    scale: Float[Array, ""],
    translation_xy: Float[Array, "2"],
    box_centre: Float[Array, "2"],
    box_side: Float[Array, ""],
    camera: PinholeCamera,
) -> Float[Array, "3"]:
    """Metric camera-frame translation from a monocular weak-perspective camera
    (paper section 5.2, "Monocular wrist").

    A crop model predicts `x_crop = s (X + t_xy)` on the crop normalised to [-1, 1]
    (`x_crop = 2 (u - c_box) / b` for a crop box of side b px). Matching the pinhole
    `u = f (X + T_x) / T_z + c` gives `T_z = 2 f / (s b)` (metres, since X is metric)
    and `T_x = t_x + (c_box_x - c_x) T_z / f_x` (likewise for y).
    """
    t_z = 2.0 * camera.fx / (scale * box_side)
    t_x = translation_xy[0] + (box_centre[0] - camera.cx) * t_z / camera.fx
    t_y = translation_xy[1] + (box_centre[1] - camera.cy) * t_z / camera.fy
    return jnp.stack([t_x, t_y, t_z])
