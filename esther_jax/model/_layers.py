"""Transformer building blocks shared by the backbones, encoders and decoder.

Every layer maps `[..., tokens, dim]` arrays (any leading axes: frames, views), so one
frame's or one view's tokens form a sequence without a `vmap`. Weights are plain
arrays with `x @ w + b` products: one GEMM per layer on the CPU. Pre-norm residual
blocks, GELU MLPs, multi-head softmax attention; initialisation follows ViT practice
(truncated normal, std 0.02; zero biases; unit LayerNorm scales).

The network runs under strict rank promotion: a bias, scale or table of lower rank
than the tokens is given leading unit axes explicitly (`jax.lax.broadcast_to_rank`,
the same operation NumPy-style rank promotion inserts, so the same program) before it
is combined with them.
"""

import math

import equinox as eqx
import jax
import jax.numpy as jnp
from jaxtyping import Array, Float, PRNGKeyArray


def _trunc_normal(key: PRNGKeyArray, shape: tuple[int, ...], std: float = 0.02) -> Array:
    return std * jax.random.truncated_normal(key, -2.0, 2.0, shape, jnp.result_type(float))


class Dense(eqx.Module):
    """Affine map `x @ weight + bias` over the last axis."""

    weight: Float[Array, "fan_in fan_out"]
    bias: Float[Array, "fan_out"] | None

    def __init__(self, fan_in: int, fan_out: int, *, key: PRNGKeyArray, bias: bool = True):
        self.weight = _trunc_normal(key, (fan_in, fan_out))
        self.bias = jnp.zeros(fan_out, jnp.result_type(float)) if bias else None

    def __call__(self, x: Float[Array, "*batch fan_in"]) -> Float[Array, "*batch fan_out"]:
        y = x @ self.weight
        return y if self.bias is None else y + jax.lax.broadcast_to_rank(self.bias, y.ndim)


class LayerNorm(eqx.Module):
    """LayerNorm over the last axis with a learned scale and shift."""

    weight: Float[Array, "dim"]
    bias: Float[Array, "dim"]
    eps: float = eqx.field(static=True)

    def __init__(self, dim: int, eps: float = 1e-5):
        self.weight = jnp.ones(dim, jnp.result_type(float))
        self.bias = jnp.zeros(dim, jnp.result_type(float))
        self.eps = eps

    def __call__(self, x: Float[Array, "*batch dim"]) -> Float[Array, "*batch dim"]:
        mean = jnp.mean(x, axis=-1, keepdims=True)
        var = jnp.mean(jnp.square(x - mean), axis=-1, keepdims=True)
        weight, bias = jax.lax.broadcast_to_rank(self.weight, x.ndim), jax.lax.broadcast_to_rank(self.bias, x.ndim)
        return (x - mean) * jax.lax.rsqrt(var + self.eps) * weight + bias


class Mlp(eqx.Module):
    """`fc2(gelu(fc1(x)))`, optionally with more hidden layers (`depth` linear maps)."""

    layers: tuple[Dense, ...]

    def __init__(self, fan_in: int, hidden: int, fan_out: int, *, key: PRNGKeyArray, depth: int = 2):
        sizes = [fan_in] + [hidden] * (depth - 1) + [fan_out]
        keys = jax.random.split(key, depth)
        self.layers = tuple(Dense(a, b, key=k) for a, b, k in zip(sizes[:-1], sizes[1:], keys))

    def __call__(self, x: Float[Array, "*batch fan_in"]) -> Float[Array, "*batch fan_out"]:
        for layer in self.layers[:-1]:
            x = jax.nn.gelu(layer(x), approximate=False)
        return self.layers[-1](x)


class Rope(eqx.Module):
    """Sine and cosine tables of an axial rotary position embedding (no weights).

    DINOv3's parametrisation: per head, `head_dim / 4` periods `base**(2i / (head_dim/2))`
    for each of the two grid axes; patch centres normalised to [-1, 1] per axis.
    """

    sin: Float[Array, "tokens head_dim"]
    cos: Float[Array, "tokens head_dim"]


def grid_rope(grid: int, head_dim: int, base: float = 100.0) -> Rope:
    """Rope tables of a `grid x grid` patch grid (row-major tokens)."""
    if head_dim % 4:
        raise ValueError(f"rotary embeddings need a head dimension divisible by 4; got {head_dim}")
    dtype = jnp.result_type(float)
    quarter = head_dim // 4
    periods = base ** (2.0 * jnp.arange(quarter, dtype=dtype) / (head_dim // 2))
    coords = 2.0 * (jnp.arange(grid, dtype=dtype) + 0.5) / grid - 1.0
    rows, cols = jnp.meshgrid(coords, coords, indexing="ij")
    yx = jnp.stack([rows.reshape(-1), cols.reshape(-1)], axis=-1)  # (P, 2)
    angles = (2.0 * jnp.pi * yx[:, :, None] / periods[None, None, :]).reshape(grid * grid, 2 * quarter)
    angles = jnp.concatenate([angles, angles], axis=-1)
    return Rope(sin=jnp.sin(angles), cos=jnp.cos(angles))


def _apply_rope(x: Float[Array, "*batch heads tokens head_dim"], rope: Rope) -> Array:
    """Rotate the trailing `rope.sin.shape[0]` tokens (leading prefix tokens stay put)."""
    n = rope.sin.shape[0]
    prefix, patches = x[..., : x.shape[-2] - n, :], x[..., x.shape[-2] - n :, :]
    half = patches.shape[-1] // 2
    rotated = jnp.concatenate([-patches[..., half:], patches[..., :half]], axis=-1)
    cos, sin = jax.lax.broadcast_to_rank(rope.cos, patches.ndim), jax.lax.broadcast_to_rank(rope.sin, patches.ndim)
    return jnp.concatenate([prefix, patches * cos + rotated * sin], axis=-2)


class Attention(eqx.Module):
    """Multi-head softmax attention with a fused q/k/v projection.

    `attn(x)` is self-attention; `attn(x, context)` lets the tokens of `x` read the
    tokens of `context` (queries from x, keys and values from context).
    """

    qkv: Dense
    proj: Dense
    heads: int = eqx.field(static=True)

    def __init__(self, dim: int, heads: int, *, key: PRNGKeyArray):
        if dim % heads:
            raise ValueError(f"model width {dim} is not divisible by {heads} heads")
        k1, k2 = jax.random.split(key)
        self.qkv = Dense(dim, 3 * dim, key=k1)
        self.proj = Dense(dim, dim, key=k2)
        self.heads = heads

    def __call__(
        self,
        x: Float[Array, "*batch queries dim"],
        context: Float[Array, "*batch keys dim"] | None = None,
        rope: Rope | None = None,
    ) -> Float[Array, "*batch queries dim"]:
        return self.attend(x, context, rope)[0]

    def attend(
        self,
        x: Float[Array, "*batch queries dim"],
        context: Float[Array, "*batch keys dim"] | None = None,
        rope: Rope | None = None,
    ) -> tuple[Float[Array, "*batch queries dim"], Float[Array, "*batch heads queries keys"]]:
        """The layer's output and its attention probabilities: per head, the softmax
        weights of each query over the keys (`x`'s tokens for self-attention, else
        `context`'s; each row sums to 1). `attn(...)` is `attn.attend(...)[0]`."""
        dim = x.shape[-1]
        w, b = self.qkv.weight, self.qkv.bias
        if context is None:
            q, k, v = jnp.split(x @ w + jax.lax.broadcast_to_rank(b, x.ndim), 3, axis=-1)
        else:
            q = x @ w[:, :dim] + jax.lax.broadcast_to_rank(b[:dim], x.ndim)
            k, v = jnp.split(context @ w[:, dim:] + jax.lax.broadcast_to_rank(b[dim:], context.ndim), 2, axis=-1)

        def heads(t):
            return jnp.swapaxes(t.reshape(t.shape[:-1] + (self.heads, dim // self.heads)), -2, -3)

        q, k, v = heads(q), heads(k), heads(v)
        if rope is not None:
            q, k = _apply_rope(q, rope), _apply_rope(k, rope)
        logits = jnp.einsum("...qd,...kd->...qk", q, k) / math.sqrt(dim // self.heads)
        probs = jax.nn.softmax(logits, axis=-1)
        out = jnp.einsum("...qk,...kd->...qd", probs, v)
        out = jnp.swapaxes(out, -2, -3)
        return self.proj(out.reshape(out.shape[:-2] + (dim,))), probs


class Block(eqx.Module):
    """Pre-norm transformer block: `x + A(LN x)`, then `x + MLP(LN x)`, with optional
    LayerScale (per-channel residual gains, DINOv3's `ls1`/`ls2`)."""

    norm1: LayerNorm
    attn: Attention
    ls1: Float[Array, "dim"] | None
    norm2: LayerNorm
    mlp: Mlp
    ls2: Float[Array, "dim"] | None

    def __init__(
        self, dim: int, heads: int, *, key: PRNGKeyArray, mlp_ratio: float = 4.0,
        layerscale: float | None = None, eps: float = 1e-5,
    ):  # fmt: skip
        k1, k2 = jax.random.split(key)
        self.norm1, self.norm2 = LayerNorm(dim, eps), LayerNorm(dim, eps)
        self.attn = Attention(dim, heads, key=k1)
        self.mlp = Mlp(dim, int(dim * mlp_ratio), dim, key=k2)
        scale = None if layerscale is None else jnp.full(dim, layerscale, jnp.result_type(float))
        self.ls1, self.ls2 = scale, scale

    def __call__(self, x: Float[Array, "*batch tokens dim"], rope: Rope | None = None) -> Float[Array, "*batch tokens dim"]:
        a = self.attn(self.norm1(x), rope=rope)
        x = x + (a if self.ls1 is None else a * jax.lax.broadcast_to_rank(self.ls1, a.ndim))
        m = self.mlp(self.norm2(x))
        return x + (m if self.ls2 is None else m * jax.lax.broadcast_to_rank(self.ls2, m.ndim))


class CrossBlock(eqx.Module):
    """Queries read a token set: `q + A(LN q, LN s)`, then `q + MLP(LN q)`."""

    norm_query: LayerNorm
    norm_source: LayerNorm
    attn: Attention
    norm_mlp: LayerNorm
    mlp: Mlp

    def __init__(self, dim: int, heads: int, *, key: PRNGKeyArray, mlp_ratio: float = 4.0):
        k1, k2 = jax.random.split(key)
        self.norm_query, self.norm_source, self.norm_mlp = LayerNorm(dim), LayerNorm(dim), LayerNorm(dim)
        self.attn = Attention(dim, heads, key=k1)
        self.mlp = Mlp(dim, int(dim * mlp_ratio), dim, key=k2)

    def __call__(
        self, queries: Float[Array, "*batch queries dim"], source: Float[Array, "*batch keys dim"]
    ) -> Float[Array, "*batch queries dim"]:
        q = queries + self.attn(self.norm_query(queries), self.norm_source(source))
        return q + self.mlp(self.norm_mlp(q))
