"""The hand model's own pose prior, shared by the teacher's fits and the network's
training: the Mahalanobis distance of a pose in the model's 45-D PCA space
(`hands_components` rows are principal directions scaled by their standard deviations,
as in MANO) and hinges on the anatomical joint limits (`JOINT_LIMITS`: flexion,
abduction, twist in `anatomical_frames`); and a learned one, `GMMPosePrior` (a Gaussian
mixture fitted to poses by `fit_gmm_pose_prior`, with the same hinges), which the teacher
and `fitting.refine` take in the PCA prior's place (`esther prior`, `--pose-prior`)."""

import math
import pathlib

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Bool, Float

from .anatomy import JOINT_LIMITS, anatomical_frames, hand_pose_to_anatomical
from .conventions import mirror_hand_pose
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
        return jnp.concatenate([z, self.limit_residuals(hand_pose)])

    def limit_residuals(self, hand_pose: Float[Array, "15 3"]) -> Float[Array, "45"]:
        """The joint-limit hinges: limit_weight times each anatomical angle's excess over its limits (radians)."""
        angles = hand_pose_to_anatomical(hand_pose, self.frames)
        excess = jnp.maximum(angles - self.upper, 0.0) + jnp.maximum(self.lower - angles, 0.0)
        return self.limit_weight * excess.reshape(45)

    def limit_normal_equations(self, hand_pose: Float[Array, "15 3"]) -> tuple[Float[Array, "45"], Float[Array, "45 45"]]:
        """J^T r and J^T J of `limit_residuals` in the 45 pose parameters, in closed form: a
        hinge's Jacobian is +-limit_weight times its joint's anatomical axis where the limit
        is exceeded, 0 inside, so J^T J is block diagonal (one 3x3 block per joint)."""
        hinges = self.limit_residuals(hand_pose).reshape(15, 3)
        angles = hand_pose_to_anatomical(hand_pose, self.frames)
        above, below = angles > self.upper, angles < self.lower
        slope = self.limit_weight * (above.astype(angles.dtype) - below.astype(angles.dtype))  # d residual / d angle
        g = jnp.einsum("jai,ji->ja", self.frames, slope * hinges)
        blocks = jnp.einsum("jai,jbi->jab", self.frames * slope[:, None, :], self.frames * slope[:, None, :])
        return g.reshape(45), jnp.einsum("jk,jab->jakb", jnp.eye(15, dtype=blocks.dtype), blocks).reshape(45, 45)

    def normal_equations(self, hand_pose: Float[Array, "15 3"]) -> tuple[Float[Array, "45"], Float[Array, "45 45"]]:
        """The Gauss-Newton gradient J^T r and matrix J^T J of `self(hand_pose)` in the 45
        pose parameters, in closed form (what a least-squares fit adds to its own): the
        PCA part's Jacobian is the whitening, the hinges' `limit_normal_equations`."""
        z = self.whitening @ (hand_pose.reshape(45) - self.mean)
        g_limits, H_limits = self.limit_normal_equations(hand_pose)
        return self.whitening.T @ z + g_limits, self.whitening.T @ self.whitening + H_limits


class GMMPosePrior(eqx.Module):
    """A learned pose prior: a Gaussian mixture over the 45 hand-pose parameters (the
    mixture pose prior of SMPLify, for the hand), fitted to poses by `fit_gmm_pose_prior`,
    plus the joint-limit hinges of a `PosePrior` (`limits`).

    As a least-squares prior (the interface of `PosePrior`), its residuals are those of
    the mixture's best component at the pose: L_k (pose - mu_k), with L_k^T L_k the
    component's precision and k the component of least energy 0.5 |L_k (pose - mu_k)|^2 -
    log w_k - log det L_k (SMPLify's max-component approximation of the mixture's negative
    log-likelihood), so 0.5 |r|^2 is that energy up to a constant per component.

    Measured against the PCA prior (`benchmarks/teacher.py --section prior`: 4 held-out
    synthetic clips of 64 frames, both hands, 8 components): it does not improve the
    labels at the teacher's prior weight. Teacher P-MPJPE 2.65 mm (PCA), 2.70 (mixture of
    the synthetic engine's motion), 3.50 (mixture of 1937 poses of the teacher's own
    labels); refine from a perturbed start 2.08, 2.47, 2.79; no frame rejected by any.
    Its precision is far sharper than the PCA prior's, so the weight tuned for the PCA
    prior over-weights it; the weight was not re-tuned.
    """

    means: Float[Array, "components 45"]
    factors: Float[Array, "components 45 45"]
    """L_k: each component's precision factor, L_k^T L_k = Sigma_k^-1 (radians^-1)."""
    log_weights: Float[Array, "components"]
    limits: PosePrior | None = None
    """The joint-limit hinges (a `PosePrior` of the hand being fitted: `with_limits`); None: none."""

    def for_side(self, is_right: bool | Bool[Array, ""]) -> "GMMPosePrior":
        """The mixture for a right hand (as fitted: `fit_gmm_pose_prior` takes right-hand
        poses) or its mirror image for the left model (`mirror_hand_pose`); `is_right` may
        be traced (a model's `is_right`)."""
        mirrored = mirror_hand_pose(jnp.ones((15, 3), self.means.dtype)).reshape(45)
        signs = jnp.where(jnp.asarray(is_right), jnp.ones_like(mirrored), mirrored)
        return GMMPosePrior(self.means * signs[None], self.factors * signs[None, None], self.log_weights, self.limits)

    def with_limits(self, base: PosePrior) -> "GMMPosePrior":
        """This mixture with `base`'s joint-limit hinges (its anatomical frames, limits and weight)."""
        return GMMPosePrior(self.means, self.factors, self.log_weights, base)

    def energies(self, hand_pose: Float[Array, "15 3"]) -> Float[Array, "components"]:
        """Each component's negative log-density at the pose, up to one shared constant."""
        z = jnp.einsum("kij,kj->ki", self.factors, hand_pose.reshape(45)[None] - self.means)
        log_det = jnp.sum(jnp.log(jnp.abs(jnp.diagonal(self.factors, axis1=1, axis2=2))), axis=1)
        return 0.5 * jnp.sum(z**2, axis=1) - self.log_weights - log_det

    def negative_log_likelihood(self, hand_pose: Float[Array, "15 3"]) -> Float[Array, ""]:
        """-log p(pose) of the mixture (nats, without the 45/2 log 2 pi constant)."""
        return -jax.nn.logsumexp(-self.energies(hand_pose))

    def _best(self, hand_pose: Float[Array, "15 3"]) -> tuple[Float[Array, "45"], Float[Array, "45 45"]]:
        k = jnp.argmin(jax.lax.stop_gradient(self.energies(hand_pose)))
        L = self.factors[k]
        return L @ (hand_pose.reshape(45) - self.means[k]), L

    def __call__(self, hand_pose: Float[Array, "15 3"]) -> Float[Array, "n"]:
        z, _ = self._best(hand_pose)
        return z if self.limits is None else jnp.concatenate([z, self.limits.limit_residuals(hand_pose)])

    def normal_equations(self, hand_pose: Float[Array, "15 3"]) -> tuple[Float[Array, "45"], Float[Array, "45 45"]]:
        """J^T r and J^T J in the 45 pose parameters (the best component's Jacobian is its
        factor L_k), plus the hinges' (`PosePrior.limit_normal_equations`)."""
        z, L = self._best(hand_pose)
        g, H = L.T @ z, L.T @ L
        if self.limits is not None:
            g_limits, H_limits = self.limits.limit_normal_equations(hand_pose)
            g, H = g + g_limits, H + H_limits
        return g, H

    def save(self, path: str | pathlib.Path) -> pathlib.Path:
        """Write the mixture (not its hinges, which belong to the hand fitted) to an .npz, atomically."""
        from ..files import atomic_output

        path = pathlib.Path(path)
        with atomic_output(path) as tmp:
            with open(tmp, "wb") as f:
                np.savez(f, format=np.int64(GMM_FORMAT), means=np.asarray(self.means), factors=np.asarray(self.factors),
                         log_weights=np.asarray(self.log_weights))  # fmt: skip
        return path

    @classmethod
    def load(cls, path: str | pathlib.Path) -> "GMMPosePrior":
        """Read a mixture `save` wrote; a clear ValueError for anything else."""
        try:
            with np.load(path, allow_pickle=False) as f:
                arrays = {k: np.asarray(f[k]) for k in ("format", "means", "factors", "log_weights")}
        except (OSError, KeyError, ValueError) as err:
            raise ValueError(f"{path} is not a pose prior file (esther prior --out writes one): {err}") from err
        K = arrays["means"].shape[0]
        if int(arrays["format"]) != GMM_FORMAT or arrays["means"].shape != (K, 45) or arrays["factors"].shape != (K, 45, 45) or arrays["log_weights"].shape != (K,):
            raise ValueError(f"{path}: a pose prior holds means (K, 45), factors (K, 45, 45), log_weights (K,) of format {GMM_FORMAT}; "
                             f"got {[(k, v.shape) for k, v in arrays.items()]}")  # fmt: skip
        if not all(np.isfinite(arrays[k]).all() for k in ("means", "factors", "log_weights")):
            raise ValueError(f"{path}: the pose prior holds NaN or infinite values")
        dtype = jnp.result_type(float)
        return cls(*(jnp.asarray(arrays[k], dtype) for k in ("means", "factors", "log_weights")))


GMM_FORMAT = 1
"""Version of `GMMPosePrior.save`'s file."""


def _log_densities(poses, means, covs, log_w):
    """log w_k + log N(pose | mu_k, Sigma_k) per component and pose (K, n), up to one constant."""
    C = jnp.linalg.cholesky(covs)  # Sigma = C C^T
    d = poses[None] - means[:, None]  # (K, n, 45)
    z = jax.scipy.linalg.solve_triangular(C, jnp.swapaxes(d, 1, 2), lower=True)  # (K, 45, n)
    log_det = jnp.sum(jnp.log(jnp.diagonal(C, axis1=1, axis2=2)), axis=1)
    return log_w[:, None] - 0.5 * jnp.sum(z**2, axis=1) - log_det[:, None]


@jax.jit
def _em_step(poses, means, covs, log_w, floor):
    """One expectation-maximisation step of a full-covariance mixture (each covariance
    regularised by `floor` on its diagonal)."""
    logp = _log_densities(poses, means, covs, log_w)
    resp = jnp.exp(logp - jax.nn.logsumexp(logp, axis=0, keepdims=True))  # (K, n)
    mass = jnp.sum(resp, axis=1) + 1e-9
    means = resp @ poses / mass[:, None]
    d = poses[None] - means[:, None]
    covs = jnp.einsum("kn,kni,knj->kij", resp, d, d) / mass[:, None, None] + floor * jnp.eye(45, dtype=poses.dtype)[None]
    return means, covs, jnp.log(mass / poses.shape[0])


def fit_gmm_pose_prior(
    poses: Float[Array | np.ndarray, "n 15 3"], *, components: int = 8, iterations: int = 100, floor: float = 1e-4, seed: int = 0
) -> GMMPosePrior:
    """Fit a `GMMPosePrior` to right-hand poses (axis-angle per joint, radians; left hands' mirrored, `mirror_hand_pose`) by
    expectation-maximisation (full covariances, each regularised by `floor` rad^2 on its
    diagonal; the means start at `components` poses drawn by `seed`). A few thousand poses
    or more: each component needs many more than its 45 dimensions."""
    poses = jnp.asarray(poses, jnp.result_type(float)).reshape(-1, 45)
    if poses.shape[0] < 100 * components:
        raise ValueError(f"fitting a {components}-component pose prior needs many poses; got {poses.shape[0]}")
    if not bool(jnp.all(jnp.isfinite(poses))):
        raise ValueError("the poses hold NaN or infinite values")
    # the iterations are dispatched from Python, one compiled step each (never waited on): an XLA
    # while loop of these batched linear-algebra steps hung on a 2-core CPU (XLA's thread pool)
    picks = jax.random.choice(jax.random.key(seed), poses.shape[0], (components,), replace=False)
    spread = jnp.cov(poses.T) + floor * jnp.eye(45, dtype=poses.dtype)
    means, covs, log_w = poses[picks], jnp.broadcast_to(spread, (components, 45, 45)), jnp.full(components, -math.log(components), poses.dtype)
    floor_t = jnp.asarray(floor, poses.dtype)
    for _ in range(iterations):
        means, covs, log_w = _em_step(poses, means, covs, log_w, floor_t)
    factors = jnp.linalg.inv(jnp.linalg.cholesky(covs))  # L = C^-1: L^T L = Sigma^-1
    return GMMPosePrior(means, factors, log_w)
