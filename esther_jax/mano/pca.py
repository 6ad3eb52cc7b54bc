"""Conversions between MANO's PCA pose coefficients and full axis-angle hand poses.

`flat_hand_mean` is always explicit: with False (smplx's default, HOT3D) a zero
coefficient vector is the model's mean pose `hands_mean`; with True (manopth's
default, HaMeR) it is the flat hand. Components need not be orthonormal (the
official basis is not), so full -> PCA is a least-squares solve with its residual.
"""

import jax.numpy as jnp
from jaxtyping import Array, Float

from .model import ManoModel


def _basis(model: ManoModel, num_components: int) -> Float[Array, "k 45"]:
    if not 1 <= num_components <= 45:
        raise ValueError(f"num_components must be in 1..45, got {num_components}")
    return model.hands_components[:num_components]


def pca_to_hand_pose(
    model: ManoModel, coefficients: Float[Array, "k"], *, flat_hand_mean: bool
) -> Float[Array, "15 3"]:
    """Full hand pose (15, 3) axis-angle from k PCA coefficients."""
    pose = coefficients @ _basis(model, coefficients.shape[0])
    if not flat_hand_mean:
        pose = pose + model.hands_mean
    return pose.reshape(15, 3)


def hand_pose_to_pca(
    model: ManoModel, hand_pose: Float[Array, "15 3"], num_components: int, *, flat_hand_mean: bool
) -> tuple[Float[Array, "k"], Float[Array, ""]]:
    """Least-squares PCA coefficients of a full hand pose, and the RMS residual (radians,
    per axis-angle entry) of what k components cannot represent."""
    basis = _basis(model, num_components)
    target = hand_pose.reshape(45)
    if not flat_hand_mean:
        target = target - model.hands_mean
    gram = basis @ basis.T
    coefficients = jnp.linalg.solve(gram, basis @ target)
    residual = jnp.sqrt(jnp.mean((coefficients @ basis - target) ** 2))
    return coefficients, residual
