"""esther_jax: the JAX core of ESTHER (rotations, MANO, cameras, triangulation, metrics).

Shapes and conventions: docs/architecture.md. Functions take one example; batch with `jax.vmap`.
"""

from .compilation import enable_compilation_cache as enable_compilation_cache

__version__ = "0.1.0"
