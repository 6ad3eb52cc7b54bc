"""The reprojection filter (appendix A, stage two of the filter) and label quality
(appendix N), on any rig geometry, for stereo and monocular frames.

- `reprojection_filter`: residual r per hand-frame, the mean pixel distance between the
  label's 21 joints projected into the views and the fused keypoints, over all (view,
  joint) pairs whose fused confidence exceeds tau = 0.3; r > 15 px is rejected.
- `frame_quality`: per hand-frame, the appendix-N quantities with the real geometry.
  A disparity error of one pixel moves a triangulated point along its ray by
  D^2 / (b_perp rho), with D the distance to the camera, b_perp the component of the
  baseline perpendicular to the viewing ray and rho the camera's local resolution
  (pixels per radian) along the epipolar direction; along the camera's axis that is
  D^2 cos(phi) / (b_perp rho). On a parallel pinhole rig this is z^2 / (f b) exactly,
  for every point (`depth_per_disparity`). A monocular frame's depth comes from the
  hand's known size instead: its image extent l = rho L / D, so a pixel of extent error
  moves it by D^2 cos(phi) / (L rho) (`depth_per_size_pixel`, L the hand's length):
  the same formula with the hand in place of the baseline. In-plane error is r D / rho
  (r z / f on a pinhole's axis).
- `label_quality`: the table (median / mean / p90) over passing hand-frames, for stereo
  and monocular frames separately and together, and the pass rates.
"""

import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Bool, Float

from esther_jax.cameras import AbstractCamera, StereoRig

from .fusion import TAU

REJECT_PX = 15.0


def reprojection_filter(
    rig: StereoRig,
    joints: Float[Array, "frames 21 3"],
    uv_fused: Float[Array, "frames 2 21 2"],
    conf: Float[Array, "frames 2 21"],
    reject_px: float | Float[Array, ""] = REJECT_PX,
) -> tuple[Float[Array, "frames"], Bool[Array, "frames"]]:
    """Residual r (px; NaN where no joint exceeds tau in any view) and whether it passes
    (finite joints and r <= reject_px)."""
    uv = jnp.moveaxis(rig.project(joints), 0, 1)  # (T, 2, 21, 2)
    used = conf > TAU
    diff = jnp.where(used[..., None], uv - uv_fused, 0.0)
    distance = jnp.sqrt(jnp.sum(diff * diff, axis=-1))
    count = jnp.sum(used, axis=(1, 2))
    total = jnp.sum(jnp.where(used, distance, 0.0), axis=(1, 2))
    residual = jnp.where(count > 0, total / jnp.maximum(count, 1).astype(total.dtype), jnp.nan)
    finite = jnp.all(jnp.isfinite(joints), axis=(1, 2)) & jnp.isfinite(residual)
    return residual, finite & (residual <= reject_px)


def _ray_geometry(camera: AbstractCamera, X_cam: Float[Array, "3"]):
    D = jnp.sqrt(jnp.sum(X_cam * X_cam))
    ray = X_cam / D
    J = jax.jacfwd(camera.project)(X_cam)  # (2, 3) pixels per metre
    return D, ray, J


def depth_per_disparity(rig: StereoRig, X_rig: Float[Array, "3"]) -> Float[Array, "2"]:
    """Metres of depth along each camera's axis per pixel of disparity, for a point
    triangulated from both views (see the module docstring)."""
    X_views = rig.to_views(X_rig)
    centres = jnp.stack([rig.T_right_left[:3, 3], rig.T_left_right[:3, 3]])  # the other camera, in each view
    out = []
    for v, camera in enumerate((rig.left, rig.right)):
        D, ray, J = _ray_geometry(camera, X_views[v])
        b = centres[v]
        b_perp_vec = b - jnp.dot(b, ray) * ray
        b_perp = jnp.sqrt(jnp.sum(b_perp_vec * b_perp_vec))
        rho = jnp.sqrt(jnp.sum((J @ (D * b_perp_vec / b_perp)) ** 2))
        out.append(D * D * ray[2] / (b_perp * rho))
    return jnp.stack(out)


def _perpendicular_resolution(camera: AbstractCamera, X_cam: Float[Array, "3"]):
    D, ray, J = _ray_geometry(camera, X_cam)
    helper = jnp.where(jnp.abs(ray[0]) < 0.9, jnp.asarray([1.0, 0.0, 0.0], ray.dtype), jnp.asarray([0.0, 1.0, 0.0], ray.dtype))
    u1 = jnp.cross(ray, helper)
    u1 = u1 / jnp.sqrt(jnp.sum(u1 * u1))
    u2 = jnp.cross(ray, u1)
    Jp = J @ jnp.stack([u1, u2], axis=1) * D  # pixels per radian in the image-parallel plane
    rho = jnp.sqrt(jnp.abs(Jp[0, 0] * Jp[1, 1] - Jp[0, 1] * Jp[1, 0]))
    return D, ray, rho


def depth_per_size_pixel(rig: StereoRig, X_rig: Float[Array, "3"], size_m: Float[Array, ""]) -> Float[Array, "2"]:
    """Monocular counterpart of `depth_per_disparity`: metres of depth along each
    camera's axis per pixel of error in the image extent of a hand of length `size_m`."""
    X_views = rig.to_views(X_rig)
    out = []
    for v, camera in enumerate((rig.left, rig.right)):
        D, ray, rho = _perpendicular_resolution(camera, X_views[v])
        out.append(D * D * ray[2] / (size_m * rho))
    return jnp.stack(out)


def metres_per_pixel(rig: StereoRig, X_rig: Float[Array, "3"]) -> Float[Array, "2"]:
    """In-plane metres per pixel at a rig-frame point in each view (z / f on a pinhole's axis)."""
    X_views = rig.to_views(X_rig)
    out = []
    for v, camera in enumerate((rig.left, rig.right)):
        D, _, rho = _perpendicular_resolution(camera, X_views[v])
        out.append(D / rho)
    return jnp.stack(out)


def frame_quality(
    rig: StereoRig,
    wrist: Float[Array, "frames 3"],
    residual_px: Float[Array, "frames"],
    seen: Bool[Array, "frames 2"],
    hand_length_m: Float[Array, ""],
) -> dict[str, Float[Array, "frames"]]:
    """Per hand-frame appendix-N quantities (m, px), averaged over the views that see the
    hand: depth along the observing cameras' axes, in-plane error, depth per pixel of
    disparity (stereo) or of hand extent (monocular), and the admissible depth errors
    sqrt(2) r and 2 r times that (independent views / worst case)."""
    stereo = jnp.all(seen, axis=1)
    w = seen.astype(wrist.dtype)
    mean = lambda x: jnp.sum(x * w, axis=1) / jnp.maximum(jnp.sum(w, axis=1), 1.0)  # noqa: E731
    depth = mean(jnp.moveaxis(rig.depths(wrist), 0, 1))
    per_m = mean(jax.vmap(metres_per_pixel, in_axes=(None, 0))(rig, wrist))
    per_disparity = mean(jax.vmap(depth_per_disparity, in_axes=(None, 0))(rig, wrist))
    per_size = mean(jax.vmap(depth_per_size_pixel, in_axes=(None, 0, None))(rig, wrist, hand_length_m))
    per_px = jnp.where(stereo, per_disparity, per_size)
    return {
        "reprojection_residual_px": residual_px,
        "hand_depth_m": depth,
        "in_plane_error_mm": residual_px * per_m * 1000.0,
        "depth_per_pixel_mm": per_px * 1000.0,
        "admissible_depth_error_independent_mm": jnp.sqrt(2.0) * residual_px * per_px * 1000.0,
        "admissible_depth_error_worst_mm": 2.0 * residual_px * per_px * 1000.0,
    }


def _summary(values: np.ndarray) -> dict | None:
    values = values[np.isfinite(values)]
    if not values.size:
        return None
    return {"median": float(np.median(values)), "mean": float(np.mean(values)), "p90": float(np.percentile(values, 90))}


def label_quality(per_frame: dict[str, np.ndarray], observed: np.ndarray, stereo: np.ndarray, passing: np.ndarray) -> dict:
    """Appendix N's table over passing hand-frames (host side, from `frame_quality`),
    for stereo frames, monocular frames and all; pass rates of the observed frames.

    The stereo table's 'depth per pixel' is per pixel of disparity, the monocular
    table's per pixel of hand extent (see the module docstring)."""
    groups = {"stereo": observed & stereo, "monocular": observed & ~stereo, "all": observed}
    out = {}
    for name, frames in groups.items():
        ok = frames & passing
        table = {k: _summary(np.asarray(v)[ok]) for k, v in per_frame.items()}
        r = np.asarray(per_frame["reprojection_residual_px"])[ok]
        out[name] = {
            "table": table,
            "hand_frames": int(frames.sum()),
            "passing": int(ok.sum()),
            "share_passing": float(ok.sum() / frames.sum()) if frames.any() else None,
            "share_of_passing_below_10px": float(np.mean(r < 10.0)) if r.size else None,
        }
    return out
