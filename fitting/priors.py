"""Pluggable priors: callables that return residual vectors (so any least-squares solver
can use them, and a learned prior can be dropped in with the same signature).

The paper uses DPoser-X as the pose prior and an AMASS-pretrained motion prior; neither
is available offline, so these are our documented stand-ins:

- `PosePrior`: the hand model's own pose distribution, i.e. the Mahalanobis distance
  of the pose in its 45-D PCA space (`hands_components` rows are principal directions
  scaled by their standard deviations, as in MANO), plus a hinge on the anatomical
  joint limits (`esther_jax.mano.JOINT_LIMITS`, flexion / abduction / twist).
- `MotionPrior`: smoothness of the trajectory over a 16-frame window (wrist rotation
  as 6D, the 15 joints' rotation vectors, the wrist position): residuals are the
  second temporal differences; combined with per-frame confidences from the 2D
  evidence (adaptive weights: frames with few observed joints lean on their
  neighbours, well-observed fast motion is kept), the role appendix A gives to the
  AMASS prior's gradient feedback. Unlike the paper's AMASS prior it also smooths the
  wrist position, whose per-frame stereo depth noise (z^2/(f b) per pixel of
  disparity) is the main source of jitter.

Interface: a pose prior is `prior(hand_pose (15, 3)) -> residuals (n,)`; a motion prior
is `prior(trajectory (window, features)) -> residuals (n,)`.
"""

import equinox as eqx
import jax.numpy as jnp
from jaxtyping import Array, Float

from esther_jax import mano


def huber_residual(r: Array, delta: float | Array) -> Array:
    """s with 0.5 * s**2 == huber(r); s == r when |r| <= delta."""
    a = jnp.maximum(jnp.abs(r), delta)
    return r * jnp.sqrt(delta * (2.0 * a - delta)) / a


def huber_vector(e: Float[Array, "*batch d"], delta: float | Array) -> Float[Array, "*batch d"]:
    """Isotropic Huber on the norm of each vector (e.g. a 2D reprojection error)."""
    n = jnp.sqrt(jnp.sum(e * e, axis=-1) + 1e-12)
    a = jnp.maximum(n, delta)
    return e * (jnp.sqrt(delta * (2.0 * a - delta)) / a)[..., None]


class PosePrior(eqx.Module):
    """PCA Mahalanobis distance of the hand pose plus anatomical joint-limit hinges."""

    whitening: Float[Array, "45 45"]
    """Maps a centred pose to its standardised PCA coefficients (inverse of components^T)."""
    mean: Float[Array, "45"]
    frames: Float[Array, "15 3 3"]
    lower: Float[Array, "15 3"]
    upper: Float[Array, "15 3"]
    limit_weight: float = eqx.field(static=True, default=10.0)

    @classmethod
    def from_model(cls, model: mano.ManoModel, betas: Float[Array, "10"] | None = None) -> "PosePrior":
        comps = model.hands_components
        whitening = jnp.linalg.inv(comps.T)
        b = jnp.zeros(model.num_betas, comps.dtype) if betas is None else betas
        rest = mano.forward(model, mano.ManoParams(jnp.zeros(3), jnp.zeros((15, 3)), b, jnp.zeros(3)), check_finite=False)
        tips = rest.vertices[model.fingertip_ids]
        frames = mano.anatomical_frames(rest.transforms[:, :3, 3], tips, model.is_right)
        limits = jnp.asarray(mano.JOINT_LIMITS, comps.dtype)
        return cls(whitening, model.hands_mean, frames, limits[..., 0], limits[..., 1])

    def __call__(self, hand_pose: Float[Array, "15 3"]) -> Float[Array, "90"]:
        z = self.whitening @ (hand_pose.reshape(45) - self.mean)
        angles = mano.hand_pose_to_anatomical(hand_pose, self.frames)
        excess = jnp.maximum(angles - self.upper, 0.0) + jnp.maximum(self.lower - angles, 0.0)
        return jnp.concatenate([z, self.limit_weight * excess.reshape(45)])


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
