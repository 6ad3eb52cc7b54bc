"""Numerically safe building blocks shared by the geometry modules.

Every singular point (norm of a zero vector, division by a vanishing depth) is
guarded with the "double where": the unused branch is fed a harmless input so that
reverse-mode gradients stay finite (as brentyi/jaxlie's `SO3.log`).
"""

import jax
import jax.numpy as jnp
from jaxtyping import Array, Float


def eps(x: Array) -> float:
    """Machine epsilon of the (inexact) dtype of `x`."""
    return float(jnp.finfo(x.dtype).eps)


def safe_norm(v: Float[Array, "*batch d"]) -> Float[Array, "*batch"]:
    """Euclidean norm over the last axis, with a zero (not NaN) gradient at 0."""
    sq = jnp.sum(v * v, axis=-1)
    tiny = sq < eps(v) ** 2
    return jnp.where(tiny, 0.0, jnp.sqrt(jnp.where(tiny, 1.0, sq)))


def safe_normalize(v: Float[Array, "*batch d"]) -> Float[Array, "*batch d"]:
    """`v / |v|`; a zero vector maps to zero instead of NaN."""
    n = safe_norm(v)
    return v / jnp.where(n > 0.0, n, 1.0)[..., None]


def cross(a: Float[Array, "*batch 3"], b: Float[Array, "*batch 3"]) -> Float[Array, "*batch 3"]:
    """Cross product written elementwise (fuses better than jnp.cross on XLA:CPU)."""
    ax, ay, az = a[..., 0], a[..., 1], a[..., 2]
    bx, by, bz = b[..., 0], b[..., 1], b[..., 2]
    return jnp.stack([ay * bz - az * by, az * bx - ax * bz, ax * by - ay * bx], axis=-1)


def matmul3(a: Float[Array, "*batch 3 3"], b: Float[Array, "*batch 3 k"]) -> Float[Array, "*batch 3 k"]:
    """`a @ b` for 3x3 blocks as broadcast multiply-adds.

    Tiny batched `dot_general`s are slow on XLA:CPU (a 3x3
    apply as einsum ran 16x slower than unrolled FMAs); elementwise products fuse.
    """
    return (
        a[..., :, 0:1] * b[..., 0:1, :]
        + a[..., :, 1:2] * b[..., 1:2, :]
        + a[..., :, 2:3] * b[..., 2:3, :]
    )


def apply3(a: Float[Array, "*batch 3 3"], v: Float[Array, "*batch 3"]) -> Float[Array, "*batch 3"]:
    """`a @ v` for a 3x3 matrix and a 3-vector, as multiply-adds."""
    return a[..., :, 0] * v[..., 0:1] + a[..., :, 1] * v[..., 1:2] + a[..., :, 2] * v[..., 2:3]


def chunked(batched_fn, inputs, chunk: int):
    """`batched_fn(inputs)` for inputs with a leading axis of any length, evaluated in
    blocks of `chunk` through `lax.map` (the tail block is zero-padded, then dropped).

    Large vmapped batches otherwise materialise every intermediate at full size; blocks
    keep them in cache (2x on CPU for FK at B >= 1024, 1.7x for triangulation).
    """
    n = jax.tree_util.tree_leaves(inputs)[0].shape[0]
    if n <= chunk:
        return batched_fn(inputs)
    blocks = -(-n // chunk)
    pad = blocks * chunk - n

    def to_blocks(x):
        x = jnp.concatenate([x, jnp.zeros((pad,) + x.shape[1:], x.dtype)])
        return x.reshape((blocks, chunk) + x.shape[1:])

    out = jax.lax.map(batched_fn, jax.tree.map(to_blocks, inputs))
    return jax.tree.map(lambda x: x.reshape((blocks * chunk,) + x.shape[2:])[:n], out)
