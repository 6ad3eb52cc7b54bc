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
cases are reported through `valid`, never as NaN. A pixel its camera cannot invert
(`unproject_with_validity`: a fisheye corner beyond the valid field of view, whose ray
would be mirrored) counts as unobserved (weight 0).
"""

import math
from collections.abc import Sequence

import equinox as eqx
import jax
import jax.numpy as jnp
from jaxtyping import Array, Bool, Float, Int

from ._math import chunked, cross, eps, safe_norm
from .cameras import AbstractCamera, PinholeCamera, StereoRig

MIN_WEIGHT = 0.05
"""Views with a weight at or below this do not count as observing the point (below it a
view barely constrains depth, and the float32 normal equations lose their accuracy)."""
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


@eqx.filter_jit  # one program when called eagerly, inlined when traced (docs/architecture.md, conventions)
def triangulate(
    cameras: AbstractCamera | Sequence[AbstractCamera],
    T_rig_cams: Float[Array, "views 4 4"],
    uv: Float[Array, "views 2"],
    weights: Float[Array, "views"],
) -> Triangulation:
    """Triangulate one point seen in several views.

    Args:
        cameras: the views' cameras, one per view (e.g. `(rig.left, rig.right)`; of any
            models and image sizes), or stacked along a leading axis (`rig.cameras`).
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
    num = uv.shape[0]
    # Written per view and per component on scalars, so that under vmap every quantity
    # is one contiguous vector over points: no tiny dot_generals, no reductions over
    # axes of size 2 or 3 (about 5x faster on CPU than the einsum formulation).
    finite = jnp.all(jnp.isfinite(uv), axis=-1) & jnp.isfinite(weights)
    uv_safe = jnp.where(finite[:, None], uv, 0.0)
    R = [[[T_rig_cams[v, i, j] for j in range(3)] for i in range(3)] for v in range(num)]
    t = [[T_rig_cams[v, i, 3] for i in range(3)] for v in range(num)]
    if isinstance(cameras, AbstractCamera):
        cams = [jax.tree.map(lambda x, v=v: x[v], cameras) for v in range(num)]
    elif len(cameras) == num:
        cams = list(cameras)
    else:
        raise ValueError(f"triangulate: {len(cameras)} cameras for {num} views")
    # A pixel its camera cannot invert (a fisheye corner beyond the valid field of view,
    # whose ray is mirrored) does not observe the point: weight 0, and a harmless ray.
    unprojected = [cams[v].unproject_with_validity(uv_safe[v]) for v in range(num)]
    ray_ok = jnp.stack([ok for _, ok in unprojected])
    w = jnp.where(finite & ray_ok, jnp.clip(weights, 0.0, None), 0.0)
    axis_ray = jnp.asarray([0.0, 0.0, 1.0], uv.dtype)
    rays = [jnp.where(ray_ok[v], unprojected[v][0], axis_ray) for v in range(num)]  # z = 1, camera frame
    del unprojected
    M = [[0.0] * 3 for _ in range(3)]
    rhs = [0.0] * 3
    directions = []
    for v in range(num):
        x, y = rays[v][0], rays[v][1]
        Rv, tv = R[v], t[v]
        # rows (x e3 - e1) and (y e3 - e2) of the camera, expressed in the rig frame
        a1 = [x * Rv[i][2] - Rv[i][0] for i in range(3)]
        a2 = [y * Rv[i][2] - Rv[i][1] for i in range(3)]
        ww = w[v] * w[v]
        for a in (a1, a2):
            b = a[0] * tv[0] + a[1] * tv[1] + a[2] * tv[2]
            for i in range(3):
                rhs[i] = rhs[i] + ww * a[i] * b
                for j in range(i, 3):
                    M[i][j] = M[i][j] + ww * a[i] * a[j]
        directions.append([Rv[i][0] * x + Rv[i][1] * y + Rv[i][2] for i in range(3)])
    M = jnp.stack([jnp.stack([M[0][0], M[0][1], M[0][2]]), jnp.stack([M[0][1], M[1][1], M[1][2]]),
                   jnp.stack([M[0][2], M[1][2], M[2][2]])])  # fmt: skip
    rhs = jnp.stack(rhs)
    # Rank-deficient systems (fewer than two views, parallel rays) take a harmless
    # identity instead (double where: finite values and gradients); `valid` says so.
    eye = jnp.eye(3, dtype=M.dtype)
    scale = (M[0, 0] + M[1, 1] + M[2, 2]) / 3.0
    solvable = _det3(M) > eps(M) * scale**3 + jnp.finfo(M.dtype).tiny
    M_safe = jnp.where(solvable, M + eps(M) * scale * eye, eye)
    point = _solve_symmetric3(M_safe, jnp.where(solvable, rhs, 0.0))

    used = w > MIN_WEIGHT
    num_views = jnp.sum(used.astype(jnp.int32))
    in_front = jnp.asarray(True)
    residuals, distances2 = [], []
    for v in range(num):
        Rv, tv = R[v], t[v]
        offset = [point[i] - tv[i] for i in range(3)]
        point_cam = jnp.stack([sum(Rv[i][k] * offset[i] for i in range(3)) for k in range(3)])  # R^T (X - t)
        in_front = in_front & jnp.where(used[v], point_cam[2] > MIN_DEPTH_M, True)
        residuals.append(safe_norm(cams[v].project(point_cam) - uv_safe[v]))
        d = directions[v]
        d_norm2 = d[0] * d[0] + d[1] * d[1] + d[2] * d[2]
        along = (offset[0] * d[0] + offset[1] * d[1] + offset[2] * d[2]) / d_norm2
        distances2.append(sum((offset[i] - along * d[i]) ** 2 for i in range(3)))
    parallax_ok = jnp.asarray(False)
    sin_min2 = jnp.sin(MIN_PARALLAX_RAD) ** 2
    for v1 in range(num):
        for v2 in range(v1 + 1, num):
            d1, d2 = directions[v1], directions[v2]
            c = cross(jnp.stack(d1), jnp.stack(d2))
            sin2 = jnp.sum(c * c) / ((d1[0] ** 2 + d1[1] ** 2 + d1[2] ** 2) * (d2[0] ** 2 + d2[1] ** 2 + d2[2] ** 2))
            parallax_ok = parallax_ok | (used[v1] & used[v2] & (sin2 >= sin_min2))
    valid = (num_views >= 2) & solvable & in_front & parallax_ok & jnp.all(jnp.isfinite(point))
    residual_px = jnp.stack(residuals)
    distances2 = jnp.stack(distances2)
    # sqrt of the weighted mean square: exactly 0 with one used view (its own ray) or
    # none, where sqrt has an infinite derivative; double where keeps gradients finite.
    spread2 = jnp.sum(w * distances2) / jnp.maximum(jnp.sum(w), eps(w))
    some_spread = spread2 > jnp.finfo(spread2.dtype).tiny
    spread = jnp.where(some_spread, jnp.sqrt(jnp.where(some_spread, spread2, 1.0)), 0.0)
    return Triangulation(point=point, valid=valid, residual_px=residual_px, spread=spread, num_views=num_views)


def triangulate_stereo(rig: StereoRig, uv: Float[Array, "2 2"], weights: Float[Array, "2"]) -> Triangulation:
    """`triangulate` with the two cameras of a stereo rig (views ordered left, right; the
    cameras may differ in model and image size)."""
    return triangulate((rig.left, rig.right), rig.T_rig_cams, uv, weights)


def triangulate_rig(
    rig: StereoRig, uv: Float[Array, "*batch 2 2"], weights: Float[Array, "*batch 2"], *, chunk: int = 8192
) -> Triangulation:
    """`triangulate_stereo` over any leading axes (e.g. frames x joints): `triangulate_batch`
    with the rig's two cameras, which may differ in model and image size."""
    return triangulate_batch((rig.left, rig.right), rig.T_rig_cams, uv, weights, chunk=chunk)


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


@eqx.filter_jit
def triangulate_batch(
    cameras: AbstractCamera | Sequence[AbstractCamera],
    T_rig_cams: Float[Array, "views 4 4"],
    uv: Float[Array, "*batch views 2"],
    weights: Float[Array, "*batch views"],
    *,
    chunk: int = 8192,
) -> Triangulation:
    """`triangulate` over any leading axes (e.g. frames x joints), in chunks.

    Equal to nested `jax.vmap`s of `triangulate`; blocks of `chunk` points go through
    `lax.map` so intermediates stay in cache (1.7x faster at 2M points on CPU).
    """
    batch_shape = uv.shape[:-2]
    n = math.prod(batch_shape)
    flat_uv = uv.reshape((n,) + uv.shape[-2:])
    flat_w = weights.reshape((n, weights.shape[-1]))
    one = jax.vmap(triangulate, in_axes=(None, None, 0, 0))
    out = chunked(lambda a: one(cameras, T_rig_cams, a[0], a[1]), (flat_uv, flat_w), chunk)
    return jax.tree.map(lambda x: x.reshape(batch_shape + x.shape[1:]), out)
