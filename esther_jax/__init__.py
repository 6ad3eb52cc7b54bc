"""esther_jax: the JAX core of ESTHER (rotations, MANO, cameras, triangulation, metrics).

Shapes and conventions: docs/architecture.md. Functions take one example; batch with `jax.vmap`.
`safe_norm` / `safe_normalize`: the vector norm and direction every package uses (zero, not
NaN, value and gradient at the zero vector).
"""

from ._math import safe_norm as safe_norm
from ._math import safe_normalize as safe_normalize
from .compilation import enable_compilation_cache as enable_compilation_cache

__version__ = "0.1.0"
