"""Batched least-squares solves with optimistix (dogleg Gauss-Newton; LM is a drop-in).

Frames (and windows' frames) are solved independently under `jax.vmap`; `throw=False`
keeps one failing frame from aborting the batch, and every frame reports whether it
converged and how many steps it took. The solver is built once; the normal equations
are solved by Cholesky (`lineax.Normal(lineax.Cholesky())`), 1.3-1.7x faster than QR
on these small dense problems (reference/performance.md). Pass `solver=make_lm()` for
Levenberg-Marquardt.
"""

from collections.abc import Callable

import equinox as eqx
import jax
import lineax as lx
import optimistix as optx
from jaxtyping import Array, Bool, Int


class Solution(eqx.Module):
    value: eqx.Module
    converged: Bool[Array, "*batch"]
    num_steps: Int[Array, "*batch"]


def make_solver(rtol: float = 1e-3, atol: float = 1e-3) -> optx.AbstractLeastSquaresSolver:
    """optimistix's dogleg trust-region Gauss-Newton with Cholesky normal equations.

    On the stage-2 objective from the same starts (benchmarks/teacher.py), 12 steps of
    it reach a 3x lower objective than 12 steps of `optx.LevenbergMarquardt` in under
    half the time (its steps reuse one factorisation per accepted Jacobian)."""
    return optx.Dogleg(rtol=rtol, atol=atol, linear_solver=lx.Normal(lx.Cholesky()))


def make_lm(rtol: float = 1e-3, atol: float = 1e-3) -> optx.AbstractLeastSquaresSolver:
    """optimistix Levenberg-Marquardt with Cholesky normal equations."""
    return optx.LevenbergMarquardt(rtol=rtol, atol=atol, linear_solver=lx.Normal(lx.Cholesky()))


SOLVER = make_solver()


def solve_batch(residuals: Callable, y0, shared, per_item, *, max_steps: int, solver=SOLVER) -> Solution:
    """Solve `residuals(y, (shared, *per_item))` for every item of a leading batch axis.

    Args:
        residuals: an objective of `objectives`.
        y0: batched initial unknowns.
        shared: arguments common to all items (the `Problem`).
        per_item: tuple of batched per-item arguments (e.g. `FrameData`, `Neighbours`).
    """

    def one(y, item):
        sol = optx.least_squares(residuals, solver, y, args=(shared, *item), max_steps=max_steps, throw=False)
        return sol.value, sol.result == optx.RESULTS.successful, sol.stats["num_steps"]

    value, ok, steps = jax.vmap(one, in_axes=(0, 0))(y0, per_item)
    return Solution(value=value, converged=ok, num_steps=steps)
