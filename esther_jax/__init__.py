"""esther_jax: the JAX core of ESTHER (rotations, MANO, cameras, triangulation, metrics).

Shapes and conventions: ARCHITECTURE.md. Functions take one example; batch with `jax.vmap`.
"""

__version__ = "0.1.0"
