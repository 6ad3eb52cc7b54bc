"""MANO forward-kinematics throughput: ours (full mesh by `forward_batch` and by plain
`jit(vmap(forward))`, joints-only, forward and forward+VJP, the keypoints' Jacobian in
the parameters by autodiff and through the analytic JVP, float32 and float64) side by
side with smplx's MANO layer on the same model and machine.

    python benchmarks/fk.py [--batches 1 64 1024 8192] [--rounds 5] [--methods ROW ...]
                            [--dtypes float32 float64] [--baseline DIR] [--json out.json]

ManoModel is a pytree of arrays, so plain `jax.jit` takes it as an argument (lower
dispatch overhead than `eqx.filter_jit`). Every row is compiled first (compile time
reported apart), then timed as the median of interleaved rounds; ratios compare rows
measured in the same run. smplx rows appear when the `bench` extra (smplx + torch) is
installed; torch gets as many threads as the process has cores (XLA:CPU's pool takes
them all too), and the header prints numpy's and torch's SGEMM and the load average.
`--baseline DIR` times another checkout's `esther_jax` (a `git worktree` of an older
revision) beside this one's, its rows named `<row> [base]`: how a kernel change is
measured, old and new in one run.

What the ratios mean: a 2-core machine's speed drifts from run to run (numpy SGEMM 150
to 450 GFLOP/s), and a second job on one of the cores slows smplx (torch's OpenMP team)
about 3.5x and us 1.1-1.5x, so ratios against smplx are only worth something measured
side by side on a quiet machine (load well under 1). Measured so (float32, 2 cores,
torch 2.13.0 on 2 threads; 2026-12-06, numpy SGEMM 344 GFLOP/s, load 0.64):
`forward_batch` at B = 1024 5.1x smplx's throughput (the per-hand kernel in chunks that
it replaced, timed in the same run: 2.2x); `jit(vmap(forward))` 1.2x; a single hand
6.4x faster (earlier runs at SGEMM 341 and 150 GFLOP/s: 5.4x / 5.5x against 2.5x / 2.7x).
Every revision since forward_batch came (d643fdb) read 1.9-2.4x at B = 1024 on this
machine (d643fdb itself 2.1x beside the new kernel's 4.6x): higher readings of the old kernel (4-5x) came from contended runs, where
smplx's time triples (a busy core: 7x). Targets (issue 2): full FK at B = 1024 >= 3x
smplx's throughput (issue 46: >= 4x); a single hand >= 5x faster than smplx.
"""

import argparse
import functools
import importlib
import json
import os
import sys
import tempfile

import jax
import jax.numpy as jnp
import numpy as np

sys.path.insert(0, os.path.dirname(__file__))
from _timing import compile_seconds, interleaved, machine  # noqa: E402

from esther_jax import mano  # noqa: E402

OURS = ("full", "vmap forward", "full+vjp", "joints", "joints+vjp", "jacfwd autodiff", "jacfwd analytic")
PEERS = ("smplx", "smplx fwd+bwd")
BASELINE = OURS  # the rows --baseline repeats with the other checkout's package (those its API has)
SUFFIX = " [base]"


def cores() -> int:
    """CPUs this process may run on (what XLA's CPU thread pool and torch each get)."""
    try:
        return len(os.sched_getaffinity(0))
    except AttributeError:
        return os.cpu_count() or 1


def random_params(mano_mod, batch: int, dtype, seed: int = 0):
    rng = np.random.default_rng(seed)
    return mano_mod.ManoParams(
        global_orient=jnp.asarray(rng.normal(size=(batch, 3)) * 0.5, dtype),
        hand_pose=jnp.asarray(rng.normal(size=(batch, 15, 3)) * 0.3, dtype),
        betas=jnp.asarray(rng.normal(size=(batch, 10)), dtype),
        transl=jnp.asarray(rng.normal(size=(batch, 3)) * 0.1, dtype),
    )


@functools.cache
def programs(mano_mod):
    """Our rows' jitted programs for one `esther_jax.mano` module (this checkout's, or
    --baseline's); a row whose function the module lacks is left out."""

    @jax.jit
    def full_forward(model, params):
        out = mano_mod.forward_batch(model, params)
        return out.vertices, out.joints

    @jax.jit
    def vmap_forward(model, params):
        out = jax.vmap(mano_mod.forward, in_axes=(None, 0))(model, params)
        return out.vertices, out.joints

    @jax.jit
    def full_vjp(model, params):
        (verts, joints), pullback = jax.vjp(lambda p: full_forward.__wrapped__(model, p), params)
        return pullback((jnp.ones_like(verts), jnp.ones_like(joints)))

    @jax.jit
    def joints_forward(model, params):
        return jax.vmap(mano_mod.forward_joints, in_axes=(None, 0))(model, params)

    @jax.jit
    def joints_vjp(model, params):
        joints, pullback = jax.vjp(lambda p: joints_forward.__wrapped__(model, p), params)
        return pullback(jnp.ones_like(joints))

    def joints_jacobian(model, params, analytic_jvp: bool):
        """What a fit's Jacobian costs: jacfwd of forward_joints in the parameters."""
        fn = functools.partial(mano_mod.forward_joints, analytic_jvp=analytic_jvp)
        return jax.vmap(jax.jacfwd(fn, argnums=1), in_axes=(None, 0))(model, params)

    return {
        "full": full_forward,
        "vmap forward": vmap_forward,
        "full+vjp": full_vjp,
        "joints": joints_forward,
        "joints+vjp": joints_vjp,
        "jacfwd autodiff": jax.jit(functools.partial(joints_jacobian, analytic_jvp=False)),
        "jacfwd analytic": jax.jit(functools.partial(joints_jacobian, analytic_jvp=True)),
    }


def smplx_candidates(model, params, threads: int):
    """smplx MANO no-grad forward and forward+backward on our model, or None."""
    try:
        import smplx
        import torch
    except ImportError:
        return None
    torch.set_num_threads(threads)
    path = os.path.join(tempfile.mkdtemp(), "MANO_RIGHT.pkl")
    mano.save_mano_pkl(model, path)
    batch = params.transl.shape[0]
    layer = smplx.MANO(path, use_pca=False, flat_hand_mean=True, batch_size=batch)
    go, transl = jax.vmap(mano.to_smplx, in_axes=(None, 0))(model, params)
    t = lambda x: torch.tensor(np.asarray(x, np.float32))  # noqa: E731
    inputs = dict(global_orient=t(go), hand_pose=t(params.hand_pose.reshape(batch, 45)), betas=t(params.betas), transl=t(transl))
    tips = torch.tensor(mano.FINGERTIP_IDS_SMPLX)

    def forward():
        with torch.no_grad():
            out = layer(**inputs)
            return torch.cat([out.joints, out.vertices[:, tips]], 1)

    grad_inputs = {k: v.clone().requires_grad_(True) for k, v in inputs.items()}

    def forward_backward():
        out = layer(**grad_inputs)
        (out.vertices.sum() + out.joints.sum() + out.vertices[:, tips].sum()).backward()
        return grad_inputs["hand_pose"].grad

    return {"smplx": forward, "smplx fwd+bwd": forward_backward}


def torch_sgemm(threads: int) -> str:
    """torch's (MKL's) SGEMM reading, 2048 x 2048, best of 5 (numpy's BLAS and its
    environment, e.g. OPENBLAS_CORETYPE, do not touch it)."""
    try:
        import time

        import torch
    except ImportError:
        return "torch not installed"
    torch.set_num_threads(threads)
    a = torch.rand(2048, 2048)
    a @ a
    best = float("inf")
    for _ in range(5):
        t0 = time.perf_counter()
        a @ a
        best = min(best, time.perf_counter() - t0)
    return f"torch {torch.__version__} SGEMM {2 * 2048**3 / best / 1e9:.0f} GFLOP/s, {torch.get_num_threads()} threads"


def import_baseline(root: str):
    """`esther_jax.mano` of another checkout (root holds its esther_jax/), imported under
    another name beside this one's (the package's imports are relative)."""
    alias = tempfile.mkdtemp()
    os.symlink(os.path.join(os.path.abspath(root), "esther_jax"), os.path.join(alias, "esther_jax_baseline"))
    sys.path.insert(0, alias)
    return importlib.import_module("esther_jax_baseline.mano")


def run(batches, rounds: int, methods, dtypes, baseline=None, threads: int = 1) -> list[dict]:
    rows = []
    for dtype_name in dtypes:
        x64 = dtype_name == "float64"
        with jax.enable_x64(x64):
            dtype = jnp.float64 if x64 else jnp.float32
            modules = [(mano, "")] + ([(baseline, SUFFIX)] if baseline is not None else [])
            models = {suffix: mod.load_builtin("right") for mod, suffix in modules}
            for batch in batches:
                candidates, compiled = {}, {}
                for mod, suffix in modules:
                    params = random_params(mod, batch, dtype)
                    for name, program in programs(mod).items():
                        if name + suffix not in methods:
                            continue
                        fn = functools.partial(program, models[suffix], params)
                        try:
                            compiled[name + suffix] = compile_seconds(fn)
                        except (AttributeError, TypeError) as e:  # an older API
                            print(f"  ({name + suffix} skipped: {type(e).__name__}: {e})")
                            continue
                        candidates[name + suffix] = fn
                if not x64 and any(p in methods for p in PEERS):
                    peers = smplx_candidates(models[""], random_params(mano, batch, dtype), threads)
                    candidates.update({k: v for k, v in (peers or {}).items() if k in methods})
                times = interleaved(candidates, rounds=rounds)
                for name, seconds in times.items():
                    rows.append(
                        dict(
                            dtype=dtype_name,
                            batch=batch,
                            method=name,
                            ms=seconds * 1e3,
                            hands_per_s=batch / seconds,
                            compile_s=compiled.get(name),
                        )
                    )
                _print_block(rows, batch, dtype_name)
    return rows


def _print_block(rows, batch, dtype):
    block = [r for r in rows if r["batch"] == batch and r["dtype"] == dtype]
    by = {r["method"]: r for r in block}
    print(f"\n{dtype}  B={batch}")
    for r in block:
        compile_s = f"  compile {r['compile_s']:.2f}s" if r["compile_s"] is not None else ""
        print(f"  {r['method']:<21} {r['ms']:10.3f} ms  {r['hands_per_s']:12.0f} hands/s{compile_s}")

    def ratio(label, slow, fast):
        if slow in by and fast in by:
            print(f"  ratio {label:<34}: {by[slow]['ms'] / by[fast]['ms']:6.2f}x")

    ratio("jacfwd autodiff / analytic JVP", "jacfwd autodiff", "jacfwd analytic")
    for suffix in ("", SUFFIX):
        ratio(f"smplx / full{suffix}", "smplx", "full" + suffix)
        ratio(f"smplx / vmap forward{suffix}", "smplx", "vmap forward" + suffix)
        ratio(f"smplx / joints{suffix}", "smplx", "joints" + suffix)
    ratio("smplx fwd+bwd / full+vjp", "smplx fwd+bwd", "full+vjp")
    ratio("smplx fwd+bwd / joints+vjp", "smplx fwd+bwd", "joints+vjp")
    for name in BASELINE:
        ratio(f"{name}{SUFFIX} / {name}", name + SUFFIX, name)


def main():
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--batches", type=int, nargs="+", default=[1, 64, 1024, 8192])
    parser.add_argument("--rounds", type=int, default=5)
    parser.add_argument("--methods", nargs="+", default=list(OURS + PEERS), choices=OURS + PEERS, metavar="ROW",
                        help=f"rows to time (default all): {', '.join(OURS + PEERS)}")
    parser.add_argument("--dtypes", nargs="+", default=["float32", "float64"], choices=["float32", "float64"])
    parser.add_argument("--baseline", type=str, default=None, metavar="DIR",
                        help=f"a checkout (e.g. a git worktree) whose esther_jax is timed beside this one's "
                             f"for the rows {', '.join(BASELINE)} (named '<row>{SUFFIX}')")
    parser.add_argument("--json", type=str, default=None, help="also write the rows as JSON")
    args = parser.parse_args()
    threads = cores()
    print(machine())
    if any(p in args.methods for p in PEERS):
        print(f"{torch_sgemm(threads)}; XLA:CPU and torch both on {threads} threads")
    blas_env = {k: v for k, v in os.environ.items() if k.startswith("OPENBLAS_")}
    if blas_env:
        print(f"numpy's BLAS environment: {blas_env}")
    methods = set(args.methods)
    baseline = None
    if args.baseline:
        baseline = import_baseline(args.baseline)
        methods |= {name + SUFFIX for name in BASELINE if name in methods}
        print(f"baseline: {os.path.abspath(args.baseline)}")
    rows = run(args.batches, args.rounds, methods, args.dtypes, baseline, threads)
    if args.json:
        with open(args.json, "w") as f:
            json.dump(rows, f, indent=1)


if __name__ == "__main__":
    main()
