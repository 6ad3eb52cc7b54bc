"""Test helpers shared across test modules."""

import jax
import jax.numpy as jnp
import numpy as np


def tree_allclose(a, b, *, rtol=1e-5, atol=1e-6) -> bool:
    leaves_a, tree_a = jax.tree_util.tree_flatten(a)
    leaves_b, tree_b = jax.tree_util.tree_flatten(b)
    if tree_a != tree_b:
        return False
    return all(np.allclose(np.asarray(x), np.asarray(y), rtol=rtol, atol=atol) for x, y in zip(leaves_a, leaves_b))


def finite_difference_jacobian(f, x: np.ndarray, h: float = 1e-6) -> np.ndarray:
    """Central differences in float64 of f: R^n -> R^m (numpy in, numpy out)."""
    x = np.asarray(x, np.float64)
    cols = []
    for i in range(x.size):
        e = np.zeros_like(x).reshape(-1)
        e[i] = h
        e = e.reshape(x.shape)
        cols.append((np.asarray(f(jnp.asarray(x + e))) - np.asarray(f(jnp.asarray(x - e)))).reshape(-1) / (2 * h))
    return np.stack(cols, axis=-1)


def aimed_crop_cameras(rig, size: int, focal: float, target=(0.0, 0.05, 0.4)):
    """Crop intrinsics K (3, 3) of an S x S crop with focal length `focal` (pixels) and
    each view's crop rotation R_cam_crop (2, 3, 3) aiming its optical axis at `target`
    (rig frame, metres): the crop cameras of a hand held there."""
    K = jnp.asarray([[focal, 0.0, size / 2 - 0.5], [0.0, focal, size / 2 - 0.5], [0.0, 0.0, 1.0]])
    R = []
    for v in range(2):
        d = jnp.asarray(target) - rig.T_rig_cams[v, :3, 3]
        z = d / jnp.linalg.norm(d)
        x = jnp.cross(jnp.asarray([0.0, 1.0, 0.0]), z)
        x = x / jnp.linalg.norm(x)
        R.append(jnp.stack([x, jnp.cross(z, x), z], axis=1))
    return K, jnp.stack(R)


def mixed_rig():
    """A rig of two different cameras: the esther rig's 1920 x 1200 pinhole on the left and
    a 1280 x 1024 Quest 3 fisheye on the right, 62 mm apart (esther's baseline)."""
    from esther_jax import cameras

    esther, quest3 = cameras.rig_preset("esther"), cameras.rig_preset("hot3d_quest3")
    return cameras.StereoRig(esther.left, quest3.right, esther.T_left_right)
