"""Camera models (pinhole, Fisheye624), stereo rigs, rig presets and `rig.json` I/O.

Conventions (docs/architecture.md): OpenCV camera frame (x right, y down, z forward),
pixel centres at integer coordinates (the pixel (i, j) covers [i-0.5, i+0.5] x
[j-0.5, j+0.5]), so the image spans -0.5 <= u < W - 0.5. Scaling an image by s maps
u -> s (u + 0.5) - 0.5; cropping at integer offset (x0, y0) maps u -> u - x0.

`project` / `unproject` take one point / pixel; leading batch axes are accepted as
well (elementwise geometry), and cameras vmap over their fields (a stack of cameras is
a camera whose fields have a leading axis).
"""

import abc
import functools
import math
import pathlib

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Bool, Float

from .files import read_json, write_json
from ._math import apply3, eps, safe_norm

_DEPTH_GUARD_M = 1e-6
"""Depth guard (m): projection divides by this where |z| is smaller (no division by zero),
and a point counts as in front of a camera only beyond it."""


def _safe_depth(z: Array) -> Array:
    return jnp.where(jnp.abs(z) < _DEPTH_GUARD_M, _DEPTH_GUARD_M, z)


def _inside_image(uv: Float[Array, "*batch 2"], width: int, height: int, margin: float = 0.0) -> Bool[Array, "*batch"]:
    u, v = uv[..., 0], uv[..., 1]
    return (u >= -0.5 - margin) & (u < width - 0.5 + margin) & (v >= -0.5 - margin) & (v < height - 0.5 + margin)


def _takes(size: int, what: str):
    """Method decorator: the first argument must have shape (..., size), checked at trace
    time. Without it a 2-vector broadcasts silently (to the principal point) and
    homogeneous (N, 4) points are read as 3D points.

    The method runs as one compiled program (`eqx.filter_jit`; inlined when called inside
    a traced function): called eagerly, a camera model's dozens of small operations would
    each be compiled on their own for every new input shape (a fisheye projection's first
    eager call took about a second, most of it compiling)."""

    def wrap(method):
        compiled = eqx.filter_jit(method)

        @functools.wraps(method)
        def checked(self, x, *args, **kwargs):
            shape = jnp.shape(x)
            if shape[-1:] != (size,):
                raise ValueError(f"{type(self).__name__}.{method.__name__} takes {what} of shape (..., {size}); got shape {shape}")
            return compiled(self, x, *args, **kwargs)

        return checked

    return wrap


class AbstractCamera(eqx.Module):
    """A calibrated camera: `project`, `unproject`, `is_visible`, intrinsics scaling."""

    width: eqx.AbstractVar[int]
    height: eqx.AbstractVar[int]

    @abc.abstractmethod
    def project(self, point_cam: Float[Array, "*batch 3"]) -> Float[Array, "*batch 2"]:
        """Pixel of a point in the camera frame (no validity check; see `is_visible`)."""

    @abc.abstractmethod
    def unproject(self, uv: Float[Array, "*batch 2"]) -> Float[Array, "*batch 3"]:
        """Ray through a pixel, in the camera frame, scaled to z = 1 (not checked: see
        `unproject_with_validity`)."""

    @abc.abstractmethod
    def unproject_with_validity(self, uv: Float[Array, "*batch 2"]) -> tuple[Float[Array, "*batch 3"], Bool[Array, "*batch"]]:
        """`unproject(uv)` and where that ray can be trusted.

        `valid` is True where the ray is the pixel's preimage (`project(ray) == uv`)
        inside the model's valid field of view, False where the model cannot be
        inverted there: a Fisheye624 pixel beyond `max_angle` or beyond the distortion
        polynomial's monotonic range, whose ray is mirrored or unconverged. Always True
        for a pinhole. It is not an image-bounds check. The rays equal `unproject`'s.
        """

    @abc.abstractmethod
    def is_visible(self, point_cam: Float[Array, "*batch 3"], margin: float = 0.0) -> Bool[Array, "*batch"]:
        """In front of the camera, inside the model's valid field of view and inside the
        image (pixel-centre convention, optionally widened by `margin` pixels)."""

    @abc.abstractmethod
    def scaled(self, scale: float) -> "AbstractCamera":
        """The camera of the image resized by `scale` (pixel-centre convention)."""

    @abc.abstractmethod
    def cropped(self, x0: int, y0: int, width: int, height: int) -> "AbstractCamera":
        """The camera of the sub-image whose top-left pixel is (x0, y0)."""


class PinholeCamera(AbstractCamera):
    """Pinhole intrinsics (pixels), no distortion."""

    fx: Float[Array, ""]
    fy: Float[Array, ""]
    cx: Float[Array, ""]
    cy: Float[Array, ""]
    width: int = eqx.field(static=True)
    height: int = eqx.field(static=True)

    def __init__(self, fx, fy, cx, cy, width: int, height: int):
        dtype = jnp.result_type(float)
        self.fx, self.fy, self.cx, self.cy = (jnp.asarray(x, dtype) for x in (fx, fy, cx, cy))
        self.width, self.height = int(width), int(height)

    @classmethod
    def from_K(cls, K: Float[Array, "3 3"], width: int, height: int) -> "PinholeCamera":
        return cls(K[0, 0], K[1, 1], K[0, 2], K[1, 2], width, height)

    @property
    def K(self) -> Float[Array, "3 3"]:
        """The 3x3 intrinsic matrix."""
        z = jnp.zeros_like(self.fx)
        o = jnp.ones_like(self.fx)
        return jnp.stack([jnp.stack([self.fx, z, self.cx]), jnp.stack([z, self.fy, self.cy]), jnp.stack([z, z, o])])

    @_takes(3, "points (m)")
    def project(self, point_cam: Float[Array, "*batch 3"]) -> Float[Array, "*batch 2"]:
        z = _safe_depth(point_cam[..., 2])
        return jnp.stack([self.fx * point_cam[..., 0] / z + self.cx, self.fy * point_cam[..., 1] / z + self.cy], -1)

    @_takes(2, "pixels")
    def unproject(self, uv: Float[Array, "*batch 2"]) -> Float[Array, "*batch 3"]:
        x = (uv[..., 0] - self.cx) / self.fx
        y = (uv[..., 1] - self.cy) / self.fy
        return jnp.stack([x, y, jnp.ones_like(x)], -1)

    @_takes(2, "pixels")
    def unproject_with_validity(self, uv: Float[Array, "*batch 2"]) -> tuple[Float[Array, "*batch 3"], Bool[Array, "*batch"]]:
        return self.unproject(uv), jnp.ones(uv.shape[:-1], bool)

    @_takes(3, "points (m)")
    def is_visible(self, point_cam: Float[Array, "*batch 3"], margin: float = 0.0) -> Bool[Array, "*batch"]:
        return (point_cam[..., 2] > _DEPTH_GUARD_M) & _inside_image(self.project(point_cam), self.width, self.height, margin)

    def scaled(self, scale: float) -> "PinholeCamera":
        return PinholeCamera(
            self.fx * scale,
            self.fy * scale,
            scale * (self.cx + 0.5) - 0.5,
            scale * (self.cy + 0.5) - 0.5,
            round(self.width * scale),
            round(self.height * scale),
        )

    def cropped(self, x0: int, y0: int, width: int, height: int) -> "PinholeCamera":
        return PinholeCamera(self.fx, self.fy, self.cx - x0, self.cy - y0, width, height)


class Fisheye624Camera(AbstractCamera):
    """Project Aria / Quest 3 FisheyeRadTanThinPrism: 6 radial, 2 tangential, 4 thin-prism
    coefficients (projectaria_tools `FisheyeRadTanThinPrism.h`).

    `a, b = x/z, y/z; r = |(a, b)|; t = atan(r)`;
    radial `xr = t (1 + k0 t^2 + ... + k5 t^12) / r * (a, b)`; with `rd2 = |xr|^2`,
    `ud = xr + 2 (xr . p) xr + rd2 p + (s0 rd2 + s1 rd2^2, s2 rd2 + s3 rd2^2)`;
    pixel `(fx ud_x + cx, fy ud_y + cy)`. As in projectaria, a point and its negation
    project to the same pixel; `is_visible` is what rejects points behind the camera.
    """

    fx: Float[Array, ""]
    fy: Float[Array, ""]
    cx: Float[Array, ""]
    cy: Float[Array, ""]
    radial: Float[Array, "6"]
    tangential: Float[Array, "2"]
    thin_prism: Float[Array, "4"]
    max_angle: Float[Array, ""]
    """Largest angle from the optical axis (radians) inside the valid field of view."""
    width: int = eqx.field(static=True)
    height: int = eqx.field(static=True)
    newton_iterations: int = eqx.field(static=True, default=12)

    def __init__(self, fx, fy, cx, cy, radial, tangential, thin_prism, width: int, height: int, max_angle=1.4, newton_iterations=12):
        dtype = jnp.result_type(float)
        self.fx, self.fy, self.cx, self.cy = (jnp.asarray(x, dtype) for x in (fx, fy, cx, cy))
        self.radial = jnp.asarray(radial, dtype)
        self.tangential = jnp.asarray(tangential, dtype)
        self.thin_prism = jnp.asarray(thin_prism, dtype)
        self.max_angle = jnp.asarray(max_angle, dtype)
        self.width, self.height = int(width), int(height)
        self.newton_iterations = int(newton_iterations)

    @classmethod
    def from_params(cls, params, width: int, height: int, max_angle: float = 1.4) -> "Fisheye624Camera":
        """From projectaria's layout: 15 values `[f, cx, cy, k0..k5, p0, p1, s0..s3]` (Aria,
        one focal) or 16 values `[fx, fy, cx, cy, ...]` (Quest 3 in HOT3D)."""
        p = np.asarray(params, dtype=np.float64).reshape(-1)
        if p.size == 15:
            p = np.concatenate([p[:1], p[:1], p[1:]])
        elif p.size != 16:
            raise ValueError(f"Fisheye624 needs 15 or 16 parameters, got {p.size}")
        if not np.all(np.isfinite(p)):
            raise ValueError("Fisheye624 parameters contain NaN or infinite values")
        if p[0] <= 0 or p[1] <= 0:
            raise ValueError(f"Fisheye624 focal lengths must be positive, got fx={p[0]}, fy={p[1]}")
        return cls(p[0], p[1], p[2], p[3], p[4:10], p[10:12], p[12:16], width, height, max_angle)

    @property
    def params(self) -> Float[Array, "16"]:
        """`[fx, fy, cx, cy, k0..k5, p0, p1, s0..s3]`."""
        head = jnp.stack([self.fx, self.fy, self.cx, self.cy])
        return jnp.concatenate([head, self.radial, self.tangential, self.thin_prism])

    def _radial_factor(self, r2: Array, dtype) -> Array:
        """`atan(r) (1 + k0 t^2 + ...) / r` with its Taylor series near the optical axis."""
        small = r2 < eps(jnp.zeros((), dtype)) ** 0.5
        r = jnp.sqrt(jnp.where(small, 1.0, r2))
        theta = jnp.arctan(jnp.where(small, 0.0, r))
        atan_over_r = jnp.where(small, 1.0 - r2 / 3.0 + r2 * r2 / 5.0, theta / r)
        theta2 = jnp.where(small, r2, theta * theta)
        poly = 1.0 + theta2 * (
            self.radial[0] + theta2 * (self.radial[1] + theta2 * (self.radial[2] + theta2 * (self.radial[3] + theta2 * (self.radial[4] + theta2 * self.radial[5]))))
        )
        return atan_over_r * poly

    def _tangential_prism(self, xr: Float[Array, "*batch 2"]) -> Float[Array, "*batch 2"]:
        x, y = xr[..., 0], xr[..., 1]
        p0, p1 = self.tangential[0], self.tangential[1]
        s = self.thin_prism
        rd2 = x * x + y * y
        dot2 = 2.0 * (x * p0 + y * p1)
        ux = x + dot2 * x + rd2 * p0 + s[0] * rd2 + s[1] * rd2 * rd2
        uy = y + dot2 * y + rd2 * p1 + s[2] * rd2 + s[3] * rd2 * rd2
        return jnp.stack([ux, uy], -1)

    @_takes(3, "points (m)")
    def project(self, point_cam: Float[Array, "*batch 3"]) -> Float[Array, "*batch 2"]:
        z = _safe_depth(point_cam[..., 2])
        ab = point_cam[..., :2] / z[..., None]
        factor = self._radial_factor(jnp.sum(ab * ab, axis=-1), point_cam.dtype)
        ud = self._tangential_prism(factor[..., None] * ab)
        return jnp.stack([self.fx * ud[..., 0] + self.cx, self.fy * ud[..., 1] + self.cy], -1)

    @_takes(2, "pixels")
    def unproject(self, uv: Float[Array, "*batch 2"]) -> Float[Array, "*batch 3"]:
        """Fixed-iteration Newton (jit-friendly): first undo the tangential/thin-prism
        part (2x2 Newton), then the radial polynomial in theta (scalar Newton).

        Beyond the valid field of view (the image corners of a wide fisheye) the ray is
        mirrored or unconverged; `unproject_with_validity` says where."""
        return self.unproject_with_validity(uv)[0]

    @_takes(2, "pixels")
    def unproject_with_validity(self, uv: Float[Array, "*batch 2"]) -> tuple[Float[Array, "*batch 3"], Bool[Array, "*batch"]]:
        """`unproject` and its validity: both Newton solves converged (residual within
        `sqrt(eps)`, in normalised units), the tangential/thin-prism map is locally
        invertible there (Jacobian determinant > 0), and the angle from the optical axis
        `0 <= theta <= max_angle` (< pi/2) lies in the radial polynomial's monotonic
        range (`d theta_d / d theta > 0` at theta and at theta/4, theta/2, 3 theta/4)."""
        ud = jnp.stack([(uv[..., 0] - self.cx) / self.fx, (uv[..., 1] - self.cy) / self.fy], -1)
        flat = ud.reshape(-1, 2)
        rays, valid = jax.vmap(self._unproject_normalised)(flat)
        return rays.reshape(ud.shape[:-1] + (3,)), valid.reshape(ud.shape[:-1])

    def _unproject_normalised(self, ud: Float[Array, "2"]) -> tuple[Float[Array, "3"], Bool[Array, ""]]:
        jac = jax.jacfwd(self._tangential_prism)

        def newton_xy(_, xr):
            J = jac(xr)
            f = self._tangential_prism(xr) - ud
            det = J[0, 0] * J[1, 1] - J[0, 1] * J[1, 0]
            step = jnp.stack([J[1, 1] * f[0] - J[0, 1] * f[1], -J[1, 0] * f[0] + J[0, 0] * f[1]]) / det
            return xr - step

        xr = jax.lax.fori_loop(0, self.newton_iterations, newton_xy, ud)
        theta_d2 = jnp.sum(xr * xr)
        small = theta_d2 < eps(xr) ** 2
        theta_d = jnp.sqrt(jnp.where(small, 1.0, theta_d2))
        k = self.radial

        def radial(t):
            t2 = t * t
            return t * (1.0 + t2 * (k[0] + t2 * (k[1] + t2 * (k[2] + t2 * (k[3] + t2 * (k[4] + t2 * k[5]))))))

        def radial_slope(t):
            t2 = t * t
            return 1.0 + t2 * (3 * k[0] + t2 * (5 * k[1] + t2 * (7 * k[2] + t2 * (9 * k[3] + t2 * (11 * k[4] + t2 * 13 * k[5])))))

        def newton_theta(_, t):
            return t - (radial(t) - theta_d) / radial_slope(t)

        theta = jax.lax.fori_loop(0, self.newton_iterations, newton_theta, theta_d)
        scale = jnp.where(small, 1.0, jnp.tan(theta) / theta_d)
        ray = jnp.concatenate([scale * xr, jnp.ones((1,), xr.dtype)])

        # Validity (no gradient flows through it). A pixel beyond the valid field of view
        # either has no preimage on the monotonic branch (Newton does not converge) or
        # converges to theta > pi/2, whose z = 1 ray is the mirror image.
        tol = eps(xr) ** 0.5
        J = jac(xr)
        converged_xy = jnp.max(jnp.abs(self._tangential_prism(xr) - ud)) <= tol * (1.0 + jnp.max(jnp.abs(ud)))
        invertible_xy = J[0, 0] * J[1, 1] - J[0, 1] * J[1, 0] > 0.0
        theta_eff = jnp.where(small, 0.0, theta)
        converged_theta = small | (jnp.abs(radial(theta) - theta_d) <= tol * (1.0 + theta_d))
        in_angle = (theta_eff >= 0.0) & (theta_eff <= self.max_angle) & (theta_eff < 0.5 * math.pi)
        monotonic = jnp.all(radial_slope(theta_eff * jnp.asarray([0.25, 0.5, 0.75, 1.0], xr.dtype)) > 0.0)
        valid = converged_xy & invertible_xy & converged_theta & in_angle & monotonic & jnp.all(jnp.isfinite(ray))
        return ray, jax.lax.stop_gradient(valid)

    @_takes(3, "points (m)")
    def is_visible(self, point_cam: Float[Array, "*batch 3"], margin: float = 0.0) -> Bool[Array, "*batch"]:
        z = point_cam[..., 2]
        lateral = jnp.sqrt(jnp.sum(point_cam[..., :2] ** 2, axis=-1))
        in_angle = jnp.arctan2(lateral, z) <= self.max_angle
        return (z > _DEPTH_GUARD_M) & in_angle & _inside_image(self.project(point_cam), self.width, self.height, margin)

    def scaled(self, scale: float) -> "Fisheye624Camera":
        return Fisheye624Camera(
            self.fx * scale, self.fy * scale, scale * (self.cx + 0.5) - 0.5, scale * (self.cy + 0.5) - 0.5,
            self.radial, self.tangential, self.thin_prism, round(self.width * scale), round(self.height * scale),
            self.max_angle, self.newton_iterations,
        )  # fmt: skip

    def cropped(self, x0: int, y0: int, width: int, height: int) -> "Fisheye624Camera":
        return Fisheye624Camera(
            self.fx, self.fy, self.cx - x0, self.cy - y0, self.radial, self.tangential, self.thin_prism,
            width, height, self.max_angle, self.newton_iterations,
        )  # fmt: skip


# ----------------------------------------------------------------------------- rigs


def apply_transform(T: Float[Array, "*#batch 4 4"], X: Float[Array, "*#batch 3"]) -> Float[Array, "*#batch 3"]:
    """Apply a rigid (or any affine) 4x4 transform to points: `R X + t`.

    Frames follow docs/architecture.md: `X_a = apply_transform(T_a_b, X_b)` takes points from
    frame b to frame a. Leading axes broadcast (NumPy rules, also across ranks), so one
    `T` of shape (4, 4) applies to points of any batch shape, and a stack of transforms
    applies to a matching stack of points. Units follow the inputs (metres here).

    Args:
        T: transform(s) `T_a_b`; only the top 3x4 block is read.
        X: point(s) in frame b.

    Returns:
        The point(s) in frame a, of the broadcast batch shape.
    """
    if T.shape[-2:] != (4, 4) or X.shape[-1:] != (3,):
        raise ValueError(f"apply_transform takes T (..., 4, 4) and X (..., 3); got {T.shape} and {X.shape}")
    # Broadcast explicitly: strict rank promotion forbids implicit broadcasts across ranks.
    batch = jnp.broadcast_shapes(T.shape[:-2], X.shape[:-1])
    R_a_b = jnp.broadcast_to(T[..., :3, :3], batch + (3, 3))
    t_a_b = jnp.broadcast_to(T[..., :3, 3], batch + (3,))
    return apply3(R_a_b, jnp.broadcast_to(X, batch + (3,))) + t_a_b


def invert_transform(T: Float[Array, "*batch 4 4"]) -> Float[Array, "*batch 4 4"]:
    """The exact rigid inverse `[R^T, -R^T t]` of rigid transform(s) `T_a_b`: `T_b_a` (no
    general matrix inverse, so a rotation stays a rotation)."""
    R_b_a = jnp.swapaxes(T[..., :3, :3], -1, -2)
    t_b_a = -apply3(R_b_a, T[..., :3, 3])
    top = jnp.concatenate([R_b_a, t_b_a[..., None]], axis=-1)
    bottom = jnp.broadcast_to(jnp.eye(4, dtype=T.dtype)[3:], top.shape[:-2] + (1, 4))
    return jnp.concatenate([top, bottom], axis=-2)


class StereoRig(eqx.Module):
    """Two calibrated cameras; the rig frame is the left camera's frame.

    The point methods (`to_views`, `project`, `is_visible`, `depths`, `distances`) take
    points in the rig frame (metres) with any leading batch shape and return one result
    per view stacked on a new leading axis (0 left, 1 right). The two cameras may be of
    different models: each view is projected with its own camera.

    A rig is calibration only: its display name is metadata beside it (`rig_preset`'s
    key, `rig.json`'s "name": `rig_name`, `to_json(path, name)`), not a field, so two rigs
    differing only in name are one pytree structure and share every compiled program."""

    left: AbstractCamera
    right: AbstractCamera
    T_left_right: Float[Array, "4 4"]
    """Pose of the right camera in the left (rig) frame: `X_left = T_left_right @ X_right`."""

    @property
    def baseline(self) -> Float[Array, ""]:
        """Distance between the optical centres (m)."""
        return jnp.linalg.norm(self.T_left_right[:3, 3])

    @property
    def T_rig_cams(self) -> Float[Array, "2 4 4"]:
        """Pose of (left, right) in the rig frame."""
        return jnp.stack([jnp.eye(4, dtype=self.T_left_right.dtype), self.T_left_right])

    @property
    def T_right_left(self) -> Float[Array, "4 4"]:
        """Pose of the left (rig) frame in the right camera's: `X_right = T_right_left @ X_left`.

        The exact rigid inverse of `T_left_right` (`invert_transform`)."""
        return invert_transform(self.T_left_right)

    @property
    def T_cams_rig(self) -> Float[Array, "2 4 4"]:
        """Pose of the rig frame in (left, right): `X_view = T_cams_rig[v] @ X_rig`, the
        exact rigid inverses of `T_rig_cams`."""
        return jnp.stack([jnp.eye(4, dtype=self.T_left_right.dtype), self.T_right_left])

    @_takes(3, "points (m)")
    def to_views(self, X_rig: Float[Array, "*batch 3"]) -> Float[Array, "2 *batch 3"]:
        """Rig-frame points (m) in the left and right camera frames (m), stacked on a
        leading view axis. The left view is the rig frame itself, returned unchanged."""
        X_right = apply_transform(self.T_right_left, X_rig)
        return jnp.stack([X_rig, X_right])

    @_takes(3, "points (m)")
    def project(self, X_rig: Float[Array, "*batch 3"]) -> Float[Array, "2 *batch 2"]:
        """Pixels (pixel-centre convention) of rig-frame points (m) in each view, each
        projected with its own camera; no validity check (see `is_visible`)."""
        X_left, X_right = self.to_views(X_rig)
        return jnp.stack([self.left.project(X_left), self.right.project(X_right)])

    @_takes(3, "points (m)")
    def is_visible(self, X_rig: Float[Array, "*batch 3"], margin: float = 0.0) -> Bool[Array, "2 *batch"]:
        """Per view: in front of the camera, inside its valid field of view and inside the
        image (optionally widened by `margin` pixels), for rig-frame points (m)."""
        X_left, X_right = self.to_views(X_rig)
        return jnp.stack([self.left.is_visible(X_left, margin), self.right.is_visible(X_right, margin)])

    def unproject_with_validity(self, uv: Float[Array, "2 *batch 2"]) -> tuple[Float[Array, "2 *batch 3"], Bool[Array, "2 *batch"]]:
        """Per view, the rays of pixels (pixel-centre convention) in that camera's frame
        (z = 1), each view with its own camera, and whether the camera can invert the pixel
        (`AbstractCamera.unproject_with_validity`)."""
        if uv.ndim < 2 or uv.shape[0] != 2 or uv.shape[-1] != 2:
            raise ValueError(f"StereoRig.unproject_with_validity takes pixels (2 views, ..., 2); got shape {uv.shape}")
        (rays_l, ok_l), (rays_r, ok_r) = self.left.unproject_with_validity(uv[0]), self.right.unproject_with_validity(uv[1])
        return jnp.stack([rays_l, rays_r]), jnp.stack([ok_l, ok_r])

    def depths(self, X_rig: Float[Array, "*batch 3"]) -> Float[Array, "2 *batch"]:
        """Depth (m) of rig-frame points along each camera's optical axis (camera z;
        negative behind the camera)."""
        return self.to_views(X_rig)[..., 2]

    def distances(self, X_rig: Float[Array, "*batch 3"]) -> Float[Array, "2 *batch"]:
        """Euclidean distance (m) of rig-frame points to each camera's optical centre
        (zero, not NaN, gradient at the centre)."""
        return safe_norm(self.to_views(X_rig))

    @property
    def cameras(self) -> AbstractCamera:
        """Both cameras stacked along a leading view axis (for vmap); they must be of the
        same model and image size. Rig-level code that must also run on rigs of two
        different cameras uses the point methods, `unproject_with_validity` and
        `triangulation.triangulate_rig` instead."""
        if type(self.left) is not type(self.right) or (self.left.width, self.left.height) != (
            self.right.width,
            self.right.height,
        ):
            raise ValueError("stacking needs two cameras of the same model and image size")
        return jax.tree.map(lambda a, b: jnp.stack([a, b]), self.left, self.right)

    @classmethod
    def from_json(cls, path: str | pathlib.Path) -> "StereoRig":
        """Read `rig.json` (docs/architecture.md, "File formats"), validating it; its
        "name", if any, is read by `rig_name`."""
        return cls.from_dict(read_json(path), source=str(path))

    @classmethod
    def from_dict(cls, data: dict, source: str = "rig") -> "StereoRig":
        """The rig of a `rig.json` record (its "name", if any, is not part of the rig)."""
        cams = data.get("cameras") if isinstance(data, dict) else None
        if not isinstance(cams, dict):
            raise ValueError(f"{source}: missing 'cameras' with 'left' and 'right'")
        for view in ("left", "right"):
            if view not in cams:
                raise ValueError(f"{source}: camera '{view}' is missing (found {sorted(cams)})")
        left, right = (_camera_from_dict(cams[v], f"{source}: camera '{v}'") for v in ("left", "right"))
        try:
            T = np.asarray(data.get("T_left_right", np.nan), dtype=np.float64)
        except (TypeError, ValueError) as err:
            raise ValueError(f"{source}: T_left_right must be a finite 4x4 matrix of numbers ({err})") from err
        if T.shape != (4, 4) or not np.all(np.isfinite(T)):
            raise ValueError(f"{source}: T_left_right must be a finite 4x4 matrix, got shape {T.shape}")
        R = T[:3, :3]
        if not np.allclose(R @ R.T, np.eye(3), atol=1e-5) or np.linalg.det(R) < 0 or not np.allclose(T[3], [0, 0, 0, 1]):
            raise ValueError(f"{source}: T_left_right is not a rigid transform (rotation not orthonormal or bottom row not 0 0 0 1)")
        baseline = float(np.linalg.norm(T[:3, 3]))
        if baseline < 1e-4:
            raise ValueError(f"{source}: the stereo baseline is {baseline * 1000:.3f} mm; a degenerate rig cannot triangulate")
        return cls(left, right, jnp.asarray(T, jnp.result_type(float)))

    def to_dict(self, name: str = "rig") -> dict:
        """The `rig.json` record of the rig, with the display name `name` beside it."""
        return {
            "name": str(name),
            "cameras": {"left": _camera_to_dict(self.left), "right": _camera_to_dict(self.right)},
            "T_left_right": np.asarray(self.T_left_right, np.float64).tolist(),
        }

    def to_json(self, path: str | pathlib.Path, name: str = "rig") -> pathlib.Path:
        """Write `rig.json` atomically, with the display name `name` (`rig_name` reads it)."""
        return write_json(path, self.to_dict(name))


def rig_name(path: str | pathlib.Path) -> str:
    """The display name a `rig.json` records ("rig" when it has none): metadata beside the
    calibration, which `StereoRig.from_json` reads."""
    data = read_json(path)
    return str(data.get("name", "rig")) if isinstance(data, dict) else "rig"


def _image_size(d: dict, key: str, where: str) -> int:
    """A positive whole number of pixels (JSON 640 or 640.0; not "640", true, Infinity or 640.5)."""
    value = d.get(key)
    if isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(value) or value != int(value) or value <= 0:
        raise ValueError(f"{where}: '{key}' must be a positive whole number of pixels, got {value!r}")
    return int(value)


def _number(d: dict, key: str, where: str) -> float:
    value = d.get(key)
    if isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(value):
        raise ValueError(f"{where}: '{key}' must be a finite number, got {value!r}")
    return float(value)


def _camera_from_dict(d: object, where: str) -> AbstractCamera:
    if not isinstance(d, dict) or "model" not in d:
        raise ValueError(f"{where}: must be an object with 'model', 'width' and 'height'")
    model, width, height = d["model"], _image_size(d, "width", where), _image_size(d, "height", where)
    if model == "pinhole":
        values = [_number(d, k, where) for k in ("fx", "fy", "cx", "cy")]
        if values[0] <= 0 or values[1] <= 0:
            raise ValueError(f"{where}: focal lengths must be positive and finite, got fx={values[0]}, fy={values[1]}")
        return PinholeCamera(*values, width, height)
    if model == "fisheye624":
        try:
            max_angle = _number(d, "max_angle", where) if "max_angle" in d else 1.4
            return Fisheye624Camera.from_params(d["params"], width, height, max_angle)
        except KeyError as err:
            raise ValueError(f"{where}: a fisheye624 camera needs 'params'") from err
        except (TypeError, ValueError) as err:
            raise ValueError(f"{where}: {err}") from err
    raise ValueError(f"{where}: unknown camera model {model!r} (expected 'pinhole' or 'fisheye624')")


def _camera_to_dict(camera: AbstractCamera) -> dict:
    if isinstance(camera, PinholeCamera):
        return {"model": "pinhole", "width": camera.width, "height": camera.height,
                "fx": float(camera.fx), "fy": float(camera.fy), "cx": float(camera.cx), "cy": float(camera.cy)}  # fmt: skip
    if isinstance(camera, Fisheye624Camera):
        params = np.asarray(camera.params, np.float64)
        if params[0] == params[1]:
            params = np.concatenate([params[:1], params[2:]])
        return {"model": "fisheye624", "width": camera.width, "height": camera.height,
                "params": params.tolist(), "max_angle": float(camera.max_angle)}  # fmt: skip
    raise TypeError(f"cannot serialise a {type(camera).__name__}")


# ----------------------------------------------------------------------------- presets


def _toed_out_pair(baseline: float, toe_out_rad: float) -> np.ndarray:
    """T_left_right of two cameras `baseline` apart on a horizontal bar, each turned
    outwards by half of `toe_out_rad` about the vertical (y) axis."""

    def pose(x: float, yaw: float) -> np.ndarray:
        c, s = math.cos(yaw), math.sin(yaw)
        T = np.eye(4)
        T[:3, :3] = [[c, 0, s], [0, 1, 0], [-s, 0, c]]
        T[0, 3] = x
        return T

    return np.linalg.inv(pose(-baseline / 2, -toe_out_rad / 2)) @ pose(baseline / 2, toe_out_rad / 2)


def rig_preset(name: str) -> StereoRig:
    """The camera setups of the paper's camera table (appendix F).

    - `esther`, `esther_mocap`: 1920x1200 pinhole pair, focal 623 px, principal point
      (924, 606), 62 mm baseline, parallel (the collection and test rigs).
    - `hot3d_aria`: Project Aria's two SLAM cameras, 640x480 Fisheye624, focal 241 px,
      138 mm baseline, turned 75 degrees apart (each 37.5 degrees outwards).
    - `hot3d_quest3`: Quest 3's two SLAM cameras, 1280x1024 Fisheye624, focal 504 px,
      64 mm baseline, nearly parallel.

    The HOT3D distortion coefficients are *plausible values* of the magnitude real
    Aria / Quest 3 calibrations have (rounded, smoothed), not any device's calibration;
    images are upright with the baseline along +x. The rig does not carry `name`: a
    `rig.json` records it beside the calibration (`rig.to_json(path, name)`).
    """
    if name in ("esther", "esther_mocap"):
        cam = PinholeCamera(623.0, 623.0, 924.0, 606.0, 1920, 1200)
        T = np.eye(4)
        T[0, 3] = 0.062
        return StereoRig(cam, cam, jnp.asarray(T, jnp.result_type(float)))
    if name == "hot3d_aria":
        left = Fisheye624Camera.from_params(
            [241.0, 319.5, 239.5, -0.027, 0.100, -0.070, 0.012, 0.002, -0.0005, 0.0005, -0.0015, 0.0, 0.0, 0.002, 0.0], 640, 480
        )
        right = Fisheye624Camera.from_params(
            [241.0, 320.5, 238.5, -0.026, 0.095, -0.062, 0.006, 0.003, -0.0006, 0.002, -0.001, -0.002, 0.0, 0.002, 0.0], 640, 480
        )
        T = _toed_out_pair(0.138, math.radians(75.0))
        return StereoRig(left, right, jnp.asarray(T, jnp.result_type(float)))
    if name == "hot3d_quest3":
        left = Fisheye624Camera.from_params(
            [504.0, 504.0, 639.5, 511.5, 0.044, -0.045, 0.017, -0.011, 0.0035, -0.0005, 0.0005, 0.0, 0.0, 0.0, 0.0, 0.0], 1280, 1024
        )
        right = Fisheye624Camera.from_params(
            [503.0, 503.0, 638.5, 512.5, 0.043, -0.046, 0.020, -0.015, 0.005, -0.0008, 0.0, 0.0002, 0.0, 0.0, 0.0, 0.0], 1280, 1024
        )
        T = _toed_out_pair(0.064, math.radians(1.5))
        return StereoRig(left, right, jnp.asarray(T, jnp.result_type(float)))
    raise ValueError(f"unknown rig preset {name!r}; choose one of {RIG_PRESETS}")


RIG_PRESETS = ("esther", "esther_mocap", "hot3d_aria", "hot3d_quest3")
