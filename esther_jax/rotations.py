"""Rotation representations and conversions, exact and differentiable at 0 and pi.

Conventions (one place, docs/architecture.md):
- Rotation matrices act on column vectors, `x' = R @ x`.
- Axis-angle is the rotation vector: unit axis times angle (radians).
- Quaternions are scalar-first `(w, x, y, z)` (as jaxlie and Project Aria); the ones
  returned here are unit and canonical (`w >= 0`).
- 6D is Zhou et al., "On the Continuity of Rotation Representations" (CVPR 2019):
  the first two *columns* of R, concatenated `(R[:, 0], R[:, 1])`.

All functions are elementwise over arbitrary leading batch axes. Singular points are
guarded with Taylor branches behind a double `jnp.where`, so values *and* gradients
are exact and finite at angle 0 (where fits start: the flat hand is all zeros).
"""

import jax.numpy as jnp
from jaxtyping import Array, Float

from ._math import eps, matmul3, safe_norm

__all__ = [
    "axis_angle_left_jacobian",
    "axis_angle_to_matrix",
    "axis_angle_to_quaternion",
    "geodesic_angle",
    "matrix_to_axis_angle",
    "matrix_to_quaternion",
    "matrix_to_rotation_6d",
    "quaternion_multiply",
    "quaternion_to_axis_angle",
    "quaternion_to_matrix",
    "rotation_6d_to_matrix",
    "skew",
]


def _taylor_threshold(x: Array) -> float:
    """Squared angle below which the Taylor branch is used.

    eps**(1/4) balances the truncation error of the series below (order theta^6)
    against the cancellation of the closed forms' derivatives (order eps/theta^2):
    about 1.9e-2 in float32 and 1.2e-4 in float64.
    """
    return eps(x) ** 0.25


def skew(v: Float[Array, "*batch 3"]) -> Float[Array, "*batch 3 3"]:
    """The cross-product matrix `[v]_x`, with `skew(v) @ w == cross(v, w)`."""
    x, y, z = v[..., 0], v[..., 1], v[..., 2]
    o = jnp.zeros_like(x)
    return jnp.stack(
        [jnp.stack([o, -z, y], -1), jnp.stack([z, o, -x], -1), jnp.stack([-y, x, o], -1)], -2
    )


def axis_angle_to_matrix(axis_angle: Float[Array, "*batch 3"]) -> Float[Array, "*batch 3 3"]:
    """Rodrigues' formula `R = I + a [w]x + b [w]x^2`, a = sin t / t, b = (1 - cos t) / t^2.

    Written out elementwise (fast on CPU); `b` uses `2 sin^2(t/2)` to avoid
    cancellation, and both coefficients switch to their Taylor series near t = 0.
    """
    x, y, z = axis_angle[..., 0], axis_angle[..., 1], axis_angle[..., 2]
    t2 = x * x + y * y + z * z
    small = t2 < _taylor_threshold(axis_angle)
    t2_safe = jnp.where(small, 1.0, t2)
    t = jnp.sqrt(t2_safe)
    a = jnp.where(small, 1.0 - t2 / 6.0 + t2 * t2 / 120.0, jnp.sin(t) / t)
    half_sin = jnp.sin(0.5 * t)
    b = jnp.where(small, 0.5 - t2 / 24.0 + t2 * t2 / 720.0, 2.0 * half_sin * half_sin / t2_safe)
    row0 = jnp.stack([1.0 - b * (y * y + z * z), -a * z + b * x * y, a * y + b * x * z], -1)
    row1 = jnp.stack([a * z + b * x * y, 1.0 - b * (x * x + z * z), -a * x + b * y * z], -1)
    row2 = jnp.stack([-a * y + b * x * z, a * x + b * y * z, 1.0 - b * (x * x + y * y)], -1)
    return jnp.stack([row0, row1, row2], -2)


def axis_angle_left_jacobian(axis_angle: Float[Array, "*batch 3"]) -> Float[Array, "*batch 3 3"]:
    """The left Jacobian of SO(3), `J_l = I + c [w]x + d [w]x^2`, c = (1 - cos t) / t^2,
    d = (t - sin t) / t^3: the change `dw` of a rotation vector turns `R = exp(w)` by the
    world-frame angle `J_l(w) dw` (`dR = [J_l dw]x R`). Taylor series near t = 0."""
    x, y, z = axis_angle[..., 0], axis_angle[..., 1], axis_angle[..., 2]
    t2 = x * x + y * y + z * z
    small = t2 < _taylor_threshold(axis_angle)
    t2_safe = jnp.where(small, 1.0, t2)
    t = jnp.sqrt(t2_safe)
    half_sin = jnp.sin(0.5 * t)
    c = jnp.where(small, 0.5 - t2 / 24.0 + t2 * t2 / 720.0, 2.0 * half_sin * half_sin / t2_safe)
    d = jnp.where(small, 1.0 / 6.0 - t2 / 120.0 + t2 * t2 / 5040.0, (t - jnp.sin(t)) / (t2_safe * t))
    K = skew(axis_angle)
    eye = jnp.broadcast_to(jnp.eye(3, dtype=axis_angle.dtype), K.shape)
    return eye + c[..., None, None] * K + d[..., None, None] * matmul3(K, K)


def axis_angle_to_quaternion(axis_angle: Float[Array, "*batch 3"]) -> Float[Array, "*batch 4"]:
    """`(cos(t/2), sin(t/2) / t * w)`, with a Taylor branch for sin(t/2)/t near 0."""
    t2 = jnp.sum(axis_angle * axis_angle, axis=-1)
    small = t2 < _taylor_threshold(axis_angle)
    t = jnp.sqrt(jnp.where(small, 1.0, t2))
    w = jnp.where(small, 1.0 - t2 / 8.0 + t2 * t2 / 384.0, jnp.cos(0.5 * t))
    k = jnp.where(small, 0.5 - t2 / 48.0 + t2 * t2 / 3840.0, jnp.sin(0.5 * t) / t)
    return jnp.concatenate([w[..., None], k[..., None] * axis_angle], axis=-1)


def quaternion_to_axis_angle(quaternion: Float[Array, "*batch 4"]) -> Float[Array, "*batch 3"]:
    """Rotation vector of a unit quaternion; angle in [0, pi].

    `2 atan2(|v|, w) / |v| * v` after flipping to `w >= 0`; stable near 0 (Taylor
    branch in |v|/w) and near pi (atan2 needs no arccos of a value near -1).
    """
    q = jnp.where(quaternion[..., :1] < 0.0, -quaternion, quaternion)
    w, v = q[..., 0], q[..., 1:]
    n2 = jnp.sum(v * v, axis=-1)
    small = n2 < _taylor_threshold(quaternion) * w * w
    n = jnp.sqrt(jnp.where(small, 1.0, n2))
    w_safe = jnp.where(small, w, 1.0)
    r2 = n2 / (w_safe * w_safe)
    # 2 atan(n / w) / n = (2 / w) (1 - r^2 / 3 + r^4 / 5 - ...), r = n / w
    k = jnp.where(small, (2.0 / w_safe) * (1.0 - r2 / 3.0 + r2 * r2 / 5.0), 2.0 * jnp.arctan2(n, w) / n)
    return k[..., None] * v


def quaternion_to_matrix(quaternion: Float[Array, "*batch 4"]) -> Float[Array, "*batch 3 3"]:
    """Rotation matrix of a quaternion (normalised first, so any non-zero q works)."""
    q = quaternion / jnp.linalg.norm(quaternion, axis=-1, keepdims=True)
    w, x, y, z = q[..., 0], q[..., 1], q[..., 2], q[..., 3]
    row0 = jnp.stack([1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)], -1)
    row1 = jnp.stack([2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)], -1)
    row2 = jnp.stack([2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)], -1)
    return jnp.stack([row0, row1, row2], -2)


def matrix_to_quaternion(matrix: Float[Array, "*batch 3 3"]) -> Float[Array, "*batch 4"]:
    """Unit quaternion (w >= 0) of a rotation matrix, by Shepperd's method.

    Four candidates `4 q_k q` are formed; the one with the largest pivot
    `4 q_k^2 >= 1` is normalised, so no branch ever divides by a small number.
    """
    m = matrix
    m00, m01, m02 = m[..., 0, 0], m[..., 0, 1], m[..., 0, 2]
    m10, m11, m12 = m[..., 1, 0], m[..., 1, 1], m[..., 1, 2]
    m20, m21, m22 = m[..., 2, 0], m[..., 2, 1], m[..., 2, 2]
    candidates = jnp.stack(
        [
            jnp.stack([1.0 + m00 + m11 + m22, m21 - m12, m02 - m20, m10 - m01], -1),
            jnp.stack([m21 - m12, 1.0 + m00 - m11 - m22, m01 + m10, m02 + m20], -1),
            jnp.stack([m02 - m20, m01 + m10, 1.0 - m00 + m11 - m22, m12 + m21], -1),
            jnp.stack([m10 - m01, m02 + m20, m12 + m21, 1.0 - m00 - m11 + m22], -1),
        ],
        -2,
    )
    pivots = jnp.stack(
        [1.0 + m00 + m11 + m22, 1.0 + m00 - m11 - m22, 1.0 - m00 + m11 - m22, 1.0 - m00 - m11 + m22], -1
    )
    best = jnp.argmax(pivots, axis=-1)[..., None, None]
    q = jnp.take_along_axis(candidates, best, axis=-2)[..., 0, :]
    q = q / jnp.linalg.norm(q, axis=-1, keepdims=True)
    return jnp.where(q[..., :1] < 0.0, -q, q)


def matrix_to_axis_angle(matrix: Float[Array, "*batch 3 3"]) -> Float[Array, "*batch 3"]:
    """Rotation vector (angle in [0, pi]) of a rotation matrix; stable near 0 and pi."""
    return quaternion_to_axis_angle(matrix_to_quaternion(matrix))


def quaternion_multiply(q1: Float[Array, "*batch 4"], q2: Float[Array, "*batch 4"]) -> Float[Array, "*batch 4"]:
    """Hamilton product `q1 * q2` (the rotation q2 first, then q1)."""
    w1, x1, y1, z1 = q1[..., 0], q1[..., 1], q1[..., 2], q1[..., 3]
    w2, x2, y2, z2 = q2[..., 0], q2[..., 1], q2[..., 2], q2[..., 3]
    return jnp.stack(
        [
            w1 * w2 - x1 * x2 - y1 * y2 - z1 * z2,
            w1 * x2 + x1 * w2 + y1 * z2 - z1 * y2,
            w1 * y2 - x1 * z2 + y1 * w2 + z1 * x2,
            w1 * z2 + x1 * y2 - y1 * x2 + z1 * w2,
        ],
        -1,
    )


def rotation_6d_to_matrix(rotation_6d: Float[Array, "*batch 6"]) -> Float[Array, "*batch 3 3"]:
    """Gram-Schmidt of the two 3-vectors of a 6D representation into R's columns.

    Zhou et al.: `b1 = a1/|a1|`, `b2 = normalise(a2 - (b1.a2) b1)`, `b3 = b1 x b2`.
    The inputs need not be orthonormal (that is the point: a network emits them).

    Degenerate inputs still give a proper rotation with finite values and gradients
    (double `jnp.where`): when `|a1| < eps`, `b1 = e_x`; when `a2` has no usable part
    orthogonal to `b1` (`|u2|^2 <= eps |a2|^2 + eps^2`: zero, or parallel to `a1` up to
    rounding), `b2` is Gram-Schmidt of the basis axis least aligned with `b1`. Both
    fallbacks have zero gradient with respect to the degenerate column. Other inputs
    are unchanged.
    """
    a1, a2 = rotation_6d[..., 0:3], rotation_6d[..., 3:6]
    dtype_eps = eps(rotation_6d)
    one_hot = lambda k: jnp.stack([k == 0, k == 1, k == 2], -1).astype(rotation_6d.dtype)  # noqa: E731
    a1_sq = jnp.sum(a1 * a1, axis=-1, keepdims=True)
    a1_tiny = a1_sq < dtype_eps**2
    a1_safe = jnp.where(a1_tiny, one_hot(jnp.zeros(a1.shape[:-1], jnp.int32)), a1)
    b1 = a1_safe / jnp.sqrt(jnp.where(a1_tiny, 1.0, a1_sq))
    u2 = a2 - jnp.sum(b1 * a2, axis=-1, keepdims=True) * b1
    u2_sq = jnp.sum(u2 * u2, axis=-1, keepdims=True)
    u2_tiny = u2_sq <= dtype_eps * jnp.sum(a2 * a2, axis=-1, keepdims=True) + dtype_eps**2
    # The axis with the smallest |b1_k| keeps |e_k - b1_k b1|^2 = 1 - b1_k^2 >= 2/3.
    e_k = one_hot(jnp.argmin(jnp.abs(b1), axis=-1))
    u2_safe = jnp.where(u2_tiny, e_k - jnp.sum(b1 * e_k, axis=-1, keepdims=True) * b1, u2)
    b2 = u2_safe / jnp.sqrt(jnp.sum(u2_safe * u2_safe, axis=-1, keepdims=True))
    b3 = jnp.cross(b1, b2)
    return jnp.stack([b1, b2, b3], axis=-1)


def matrix_to_rotation_6d(matrix: Float[Array, "*batch 3 3"]) -> Float[Array, "*batch 6"]:
    """The first two columns of R, concatenated (inverse of `rotation_6d_to_matrix`)."""
    return jnp.concatenate([matrix[..., :, 0], matrix[..., :, 1]], axis=-1)


def geodesic_angle(r1: Float[Array, "*batch 3 3"], r2: Float[Array, "*batch 3 3"]) -> Float[Array, "*batch"]:
    """Angle (radians, in [0, pi]) of the relative rotation `r1^T r2`.

    `atan2(|vee(M - M^T)| / 2, (tr M - 1) / 2)`: accurate at both ends, unlike
    `arccos` of the trace. The gradient at exactly 0 is zero (a subgradient: the
    distance has a cone point there).
    """
    m = matmul3(jnp.swapaxes(r1, -1, -2), r2)
    vee = jnp.stack([m[..., 2, 1] - m[..., 1, 2], m[..., 0, 2] - m[..., 2, 0], m[..., 1, 0] - m[..., 0, 1]], -1)
    cos = 0.5 * (m[..., 0, 0] + m[..., 1, 1] + m[..., 2, 2] - 1.0)
    return jnp.arctan2(0.5 * safe_norm(vee), cos)
