"""Pluggable priors: callables that return residual vectors (so any least-squares solver
can use them, and a learned prior can be dropped in with the same signature).

The paper uses DPoser-X as the pose prior and an AMASS-pretrained motion prior; neither
is available offline, so these are our documented stand-ins:

- `PosePrior` (from the core, `esther_jax.mano.PosePrior`, shared with the network's
  training): the hand model's own pose distribution, i.e. the Mahalanobis distance
  of the pose in its 45-D PCA space plus hinges on the anatomical joint limits.
- `MotionPrior`: smoothness of the trajectory over a 16-frame window (wrist rotation
  as 6D, the 15 joints' rotation vectors, the wrist position): residuals are the
  second temporal differences; combined with per-frame confidences from the 2D
  evidence (adaptive weights: frames with few observed joints lean on their
  neighbours, well-observed fast motion is kept), the role appendix A gives to the
  AMASS prior's gradient feedback. Unlike the paper's AMASS prior it also smooths the
  wrist position, whose per-frame stereo depth noise (z^2/(f b) per pixel of
  disparity) is the main source of jitter.

Interface: a pose prior is `prior(hand_pose (15, 3)) -> residuals (n,)` with
`prior.normal_equations(hand_pose) -> (J^T r (45,), J^T J (45, 45))` in the pose
(the teacher's solver adds those; a learned prior can form them from `jax.jacfwd`); a
motion prior is `prior(trajectory (window, features)) -> residuals (n,)`.
"""

import equinox as eqx
import jax
import jax.numpy as jnp
from jaxtyping import Array, Float

from esther_jax import safe_norm


def huber_residual(r: Array, delta: float | Array) -> Array:
    """s with 0.5 * s**2 == huber(r); s == r when |r| <= delta."""
    a = jnp.maximum(jnp.abs(r), delta)
    return r * jnp.sqrt(delta * (2.0 * a - delta)) / a


def huber_factor(norm: Array, delta: float | Array) -> Array:
    """The factor `huber_vector` multiplies a vector of length `norm` by (1 up to `delta`)."""
    a = jnp.maximum(norm, delta)
    return jnp.sqrt(delta * (2.0 * a - delta)) / a


def huber_vector(e: Float[Array, "*batch d"], delta: float | Array) -> Float[Array, "*batch d"]:
    """Isotropic Huber on the norm of each vector (e.g. a 2D reprojection error)."""
    return e * huber_factor(safe_norm(e), delta)[..., None]


def huber_vector_with_jacobian(
    e: Float[Array, "*batch d"], de: Float[Array, "*batch d n"], delta: float | Array
) -> tuple[Float[Array, "*batch d"], Float[Array, "*batch d n"]]:
    """`huber_vector(e, delta)` and its Jacobian in n unknowns, given e's Jacobian `de`
    (the chain rule through the norm: the factor's slope times d|e| = e . de / |e|; at
    e = 0 the slope is 0, and so is d|e|, not NaN)."""
    norm = safe_norm(e)
    factor, slope = jax.jvp(lambda n: huber_factor(n, delta), (norm,), (jnp.ones_like(norm),))  # elementwise
    d_norm = jnp.einsum("...a,...an->...n", e, de) / jnp.where(norm > 0.0, norm, 1.0)[..., None]
    return e * factor[..., None], factor[..., None, None] * de + e[..., None] * (slope[..., None] * d_norm)[..., None, :]


class MotionPrior(eqx.Module):
    """Quadratic smoothness of a window's trajectory: residuals sqrt(stiffness) times the
    second temporal differences of every feature (rotations as 6D, radians; joints'
    rotation vectors; the wrist in centimetres)."""

    stiffness: float = 12.0
    """Weight of the second differences relative to unit data confidence (about a 2.5 Hz
    cutoff at 30 fps); frames with thin evidence have lower confidence and are smoothed more."""

    def __call__(self, trajectory: Float[Array, "window features"]) -> Float[Array, "n"]:
        second = trajectory[:-2] - 2.0 * trajectory[1:-1] + trajectory[2:]
        return jnp.sqrt(self.stiffness) * second.reshape(-1)

    def smooth(self, observed: Float[Array, "window features"], confidence: Float[Array, "window"]) -> Float[Array, "window features"]:
        """argmin_x sum_t c_t |x_t - observed_t|^2 + |self(x)|^2 (a linear solve: the prior's
        residuals are linear in x). A learned, non-linear prior would use a least-squares
        solver here instead."""
        W = observed.shape[0]
        D = jnp.eye(W, dtype=observed.dtype)[:-2] - 2.0 * jnp.eye(W, k=1, dtype=observed.dtype)[:-2] + jnp.eye(W, k=2, dtype=observed.dtype)[:-2]
        c = jnp.maximum(confidence, 1e-3)
        A = jnp.diag(c) + self.stiffness * D.T @ D
        return jnp.linalg.solve(A, c[:, None] * observed)
