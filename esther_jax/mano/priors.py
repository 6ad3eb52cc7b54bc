"""The hand model's own pose prior, shared by the teacher's fits and the network's
training: the Mahalanobis distance of a pose in the model's 45-D PCA space
(`hands_components` rows are principal directions scaled by their standard deviations,
as in MANO) and hinges on the anatomical joint limits (`JOINT_LIMITS`: flexion,
abduction, twist in `anatomical_frames`)."""

import equinox as eqx
import jax.numpy as jnp
from jaxtyping import Array, Float

from .anatomy import JOINT_LIMITS, anatomical_frames, hand_pose_to_anatomical
from .kinematics import forward
from .model import ManoModel, ManoParams


class PosePrior(eqx.Module):
    """PCA Mahalanobis distance of the hand pose plus anatomical joint-limit hinges."""

    whitening: Float[Array, "45 45"]
    """Maps a centred pose to its standardised PCA coefficients (inverse of components^T)."""
    mean: Float[Array, "45"]
    frames: Float[Array, "15 3 3"]
    lower: Float[Array, "15 3"]
    upper: Float[Array, "15 3"]
    limit_weight: Float[Array, ""] = eqx.field(converter=jnp.asarray, default=10.0)
    """Weight of the joint-limit hinges: traced (priors of other weights share compiled
    programs); the default is weakly typed, as the Python float it was, so it takes the
    pose's dtype."""

    @classmethod
    def from_model(cls, model: ManoModel, betas: Float[Array, "10"] | None = None) -> "PosePrior":
        comps = model.hands_components
        whitening = jnp.linalg.inv(comps.T)
        b = jnp.zeros(model.num_betas, comps.dtype) if betas is None else betas
        rest = forward(model, ManoParams(jnp.zeros(3), jnp.zeros((15, 3)), b, jnp.zeros(3)), check_finite=False)
        tips = rest.vertices[model.fingertip_ids]
        frames = anatomical_frames(rest.transforms[:, :3, 3], tips, model.is_right)
        limits = jnp.asarray(JOINT_LIMITS, comps.dtype)
        return cls(whitening, model.hands_mean, frames, limits[..., 0], limits[..., 1])

    def __call__(self, hand_pose: Float[Array, "15 3"]) -> Float[Array, "90"]:
        z = self.whitening @ (hand_pose.reshape(45) - self.mean)
        angles = hand_pose_to_anatomical(hand_pose, self.frames)
        excess = jnp.maximum(angles - self.upper, 0.0) + jnp.maximum(self.lower - angles, 0.0)
        return jnp.concatenate([z, self.limit_weight * excess.reshape(45)])

    def normal_equations(self, hand_pose: Float[Array, "15 3"]) -> tuple[Float[Array, "45"], Float[Array, "45 45"]]:
        """The Gauss-Newton gradient J^T r and matrix J^T J of `self(hand_pose)` in the 45
        pose parameters, in closed form (what a least-squares fit adds to its own): the
        PCA part's Jacobian is the whitening; a hinge's is +-limit_weight times its joint's
        anatomical axis where the limit is exceeded, 0 inside, so its share is block
        diagonal (one 3x3 block per joint)."""
        r = self(hand_pose)
        z, hinges = r[:45], r[45:].reshape(15, 3)
        angles = hand_pose_to_anatomical(hand_pose, self.frames)
        above, below = angles > self.upper, angles < self.lower
        slope = self.limit_weight * (above.astype(angles.dtype) - below.astype(angles.dtype))  # d residual / d angle
        g_limits = jnp.einsum("jai,ji->ja", self.frames, slope * hinges)
        blocks = jnp.einsum("jai,jbi->jab", self.frames * slope[:, None, :], self.frames * slope[:, None, :])
        H_limits = jnp.einsum("jk,jab->jakb", jnp.eye(15, dtype=blocks.dtype), blocks).reshape(45, 45)
        return self.whitening.T @ z + g_limits.reshape(45), self.whitening.T @ self.whitening + H_limits
