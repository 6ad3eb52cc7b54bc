"""Batched least-squares solves of per-frame objectives, with a choice of solver.

Frames are solved independently under `jax.vmap`; every frame reports whether it
converged and how many steps it took, and one failing frame never aborts the batch
(optimistix: `throw=False`). The solvers (`SOLVERS`, `LabelConfig.solver`):

- `"lm"` (default): Levenberg-Marquardt with a fixed number of steps, written here in
  a dozen lines: the normal equations from the objective itself where it provides them
  (`objectives.frame_normal_equations`: about 5x cheaper than forming them from the
  forward-mode Jacobian of all residuals, `benchmarks/teacher.py --section step`), else
  from `jax.jacfwd`; Marquardt's diagonal damping, a Cholesky solve, accept / reject by
  the cost. Its
  program is one loop, about half the size of optimistix's general machinery, so it
  compiles 2-3x faster at the same accuracy (benchmarks/teacher.py measures all four),
  and its step count may be traced: one compiled program serves every stage.
- `"dogleg"`: optimistix's dogleg trust-region Gauss-Newton (Cholesky normal equations).
- `"optx-lm"`: optimistix's Levenberg-Marquardt.
The optimistix solvers linearise the residuals themselves (forward-mode autodiff).

jaxopt's Levenberg-Marquardt was measured beside these (benchmarks/teacher.py, esther
rig, one 32-frame clip, a loaded machine): first call 59 s against 15 s for "lm", 39
against 122 hand-frames/s, no more accurate (3.85 / 7.11 mm P-MPJPE / wrist against
3.41 / 7.80), and upstream no longer develops jaxopt. It earned no place and is not a
dependency.

All take residuals `fn(y, args) -> tuple of arrays` with `y` a Module of unknowns.
"""

import functools
from collections.abc import Callable

import equinox as eqx
import jax
import jax.numpy as jnp
import lineax as lx
import optimistix as optx
from jax.flatten_util import ravel_pytree
from jaxtyping import Array, Bool, Float, Int

SOLVERS = ("lm", "dogleg", "optx-lm")


class Solution(eqx.Module):
    value: eqx.Module
    converged: Bool[Array, "*batch"]
    num_steps: Int[Array, "*batch"]


def _flat(residuals: Callable, unravel: Callable, args) -> Callable:
    def f(x):
        return jnp.concatenate([r.reshape(-1) for r in residuals(unravel(x), args)])

    return f


SMALL_SYSTEM = 8
"""Up to this many unknowns, `gauss_newton` and `cholesky_solve` work element by element."""


def gauss_newton(residuals: Float[Array, "m"], jacobian: Float[Array, "m n"]) -> tuple[Float[Array, "n"], Float[Array, "n n"]]:
    """The Gauss-Newton gradient J^T r and matrix J^T J of residuals r with Jacobian J.

    Up to `SMALL_SYSTEM` unknowns as elementwise products summed over the residuals: under
    `vmap` over many small problems XLA's CPU backend runs that faster than a batch of tiny
    matrix products (1600 palm poses, 36 x 6: 2.0 against 2.9 ms); larger ones as products."""
    if jacobian.shape[1] > SMALL_SYSTEM:
        return jacobian.T @ residuals, jacobian.T @ jacobian
    return jnp.sum(jacobian * residuals[:, None], axis=0), jnp.sum(jacobian[:, :, None] * jacobian[:, None, :], axis=0)


def cholesky_solve(A: Float[Array, "n n"], b: Float[Array, "n"]) -> Float[Array, "n"]:
    """x with A x = b for a symmetric positive definite A, by Cholesky factorisation.

    Up to `SMALL_SYSTEM` unknowns (the palm pose's 6) the factorisation and both triangular
    solves are written out entry by entry: under `vmap` each entry is one elementwise
    operation over the whole batch, about 10x faster on the CPU than a batch of LAPACK calls
    (1600 6x6 systems: 0.11 against 1.2 ms). Larger systems go to `jax.scipy.linalg`."""
    n = A.shape[-1]
    if n > SMALL_SYSTEM:
        return jax.scipy.linalg.cho_solve(jax.scipy.linalg.cho_factor(A), b)
    L = [[None] * n for _ in range(n)]
    for j in range(n):
        L[j][j] = jnp.sqrt(A[j, j] - sum(L[j][k] * L[j][k] for k in range(j)))
        for i in range(j + 1, n):
            L[i][j] = (A[i, j] - sum(L[i][k] * L[j][k] for k in range(j))) / L[j][j]
    y: list = []
    for i in range(n):  # L y = b
        y.append((b[i] - sum(L[i][k] * y[k] for k in range(i))) / L[i][i])
    x: list = [None] * n
    for i in reversed(range(n)):  # L^T x = y
        x[i] = (y[i] - sum(L[k][i] * x[k] for k in range(i + 1, n))) / L[i][i]
    return jnp.stack(x)


def levenberg_marquardt(
    residuals: Callable, y0: eqx.Module, args, *, steps: int | Int[Array, ""], rtol: float = 1e-3, normal_equations: Callable | None = None
) -> tuple:
    """`steps` Levenberg-Marquardt steps on one problem: a fixed count, so under `vmap`
    every problem runs in lockstep with no per-problem exit. `steps` may be traced (an
    array): one compiled program then serves every step count.

    `normal_equations(y, args) -> (J^T r, J^T J)` (flat, in `ravel_pytree(y)`'s order)
    replaces forming them from `jax.jacfwd` of the concatenated residuals where the
    objective's structure makes them cheaper (a closed-form Jacobian, terms that touch
    few unknowns); `residuals` still gives the cost.

    Damping follows Marquardt (lambda * diag(J^T J), plus a floor), halved after an
    accepted step and quadrupled after a rejected one. Returns (solution, converged,
    steps): converged when the last accepted step reduced the cost by less than `rtol`
    relatively, or the gradient vanished."""
    flat0, unravel = ravel_pytree(y0)
    f = _flat(residuals, unravel, args)
    dtype = flat0.dtype
    eye = jnp.eye(flat0.shape[0], dtype=dtype)

    if normal_equations is None:
        linearise = lambda x, res: gauss_newton(res, jax.jacfwd(f)(x))  # noqa: E731
    else:
        linearise = lambda x, res: normal_equations(unravel(x), args)  # noqa: E731

    def step(_, carry):
        x, res, lam, _ = carry
        g, H = linearise(x, res)
        A = H + lam * (jnp.diag(jnp.diag(H)) + 1e-6 * eye)
        dx = -cholesky_solve(A, g)
        trial = f(x + dx)
        cost, new_cost = jnp.sum(res * res), jnp.sum(trial * trial)
        accept = jnp.isfinite(new_cost) & (new_cost < cost)
        small = (cost - jnp.where(accept, new_cost, cost)) <= rtol * cost
        return (
            jnp.where(accept, x + dx, x),
            jnp.where(accept, trial, res),
            jnp.where(accept, lam * 0.5, lam * 4.0),
            (accept & small) | (jnp.max(jnp.abs(g)) < 1e-8),
        )

    init = (flat0, f(flat0), jnp.asarray(1e-3, dtype), jnp.asarray(False))
    x, _, _, converged = jax.lax.fori_loop(0, steps, step, init)
    return unravel(x), converged, jnp.asarray(steps)


def _optimistix(solver: optx.AbstractLeastSquaresSolver) -> Callable:
    def run(residuals, y0, args, *, steps):
        sol = optx.least_squares(residuals, solver, y0, args=args, max_steps=steps, throw=False)
        return sol.value, sol.result == optx.RESULTS.successful, sol.stats["num_steps"]

    return run


def make_solver(name: str) -> Callable:
    """The per-problem solve `run(residuals, y0, args, *, steps) -> (value, converged, steps)`."""
    if name == "lm":
        return levenberg_marquardt
    if name == "dogleg":
        return _optimistix(optx.Dogleg(rtol=1e-3, atol=1e-3, linear_solver=lx.Normal(lx.Cholesky())))
    if name == "optx-lm":
        return _optimistix(optx.LevenbergMarquardt(rtol=1e-3, atol=1e-3, linear_solver=lx.Normal(lx.Cholesky())))
    raise ValueError(f"unknown solver {name!r}; choose one of {SOLVERS}")


def solve_batch(
    residuals: Callable, y0, shared, per_item, *, steps: int | Int[Array, ""], solver: str = "lm", normal_equations: Callable | None = None
) -> Solution:
    """Solve `residuals(y, (shared, *per_item))` for every item of a leading batch axis.

    Args:
        residuals: an objective of `objectives`.
        y0: batched initial unknowns.
        shared: arguments common to all items (the `Problem`, the `Round`), appended
            after the per-item ones as `(shared[0], *per_item, *shared[1:])`.
        per_item: tuple of batched per-item arguments (`FrameData`, `Track`).
        steps: solver steps per item (a traced count only for "lm"; optimistix's
            solvers take a Python int, their maximum).
        normal_equations: the objective's own `(J^T r, J^T J)` with the residuals'
            signature ("lm" only: optimistix's solvers linearise `residuals` themselves).
    """
    run = make_solver(solver)
    if normal_equations is not None and solver == "lm":
        run = functools.partial(run, normal_equations=normal_equations)
    problem, *rest = shared

    def one(y, item):
        return run(residuals, y, (problem, *item, *rest), steps=steps)

    value, ok, num = jax.vmap(one)(y0, per_item)
    return Solution(value=value, converged=ok, num_steps=num)
