"""MANO forward-kinematics throughput: ours (full mesh and joints-only, forward and
forward+VJP, the keypoints' Jacobian in the parameters by autodiff and through the
analytic JVP, float32 and float64) side by side with smplx's MANO layer on the same
model and machine.

    python benchmarks/fk.py [--batches 1 64 1024 8192] [--rounds 5] [--json out.json]

ManoModel is a pytree of arrays, so plain `jax.jit` takes it as an argument (lower
dispatch overhead than `eqx.filter_jit`). Every row is compiled first (compile time reported apart), then timed as the median
of interleaved rounds; ratios compare methods measured in the same run. smplx rows
appear when the `bench` extra (smplx + torch) is installed. Targets (issue 2): full
FK at B=1024 >= 3x smplx's throughput; a single hand >= 5x faster than smplx.
"""

import argparse
import functools
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


def random_params(batch: int, dtype, seed: int = 0) -> mano.ManoParams:
    rng = np.random.default_rng(seed)
    return mano.ManoParams(
        global_orient=jnp.asarray(rng.normal(size=(batch, 3)) * 0.5, dtype),
        hand_pose=jnp.asarray(rng.normal(size=(batch, 15, 3)) * 0.3, dtype),
        betas=jnp.asarray(rng.normal(size=(batch, 10)), dtype),
        transl=jnp.asarray(rng.normal(size=(batch, 3)) * 0.1, dtype),
    )


@jax.jit
def full_forward(model, params):
    out = mano.forward_batch(model, params)
    return out.vertices, out.joints


@jax.jit
def full_vjp(model, params):
    (verts, joints), pullback = jax.vjp(lambda p: full_forward.__wrapped__(model, p), params)
    return pullback((jnp.ones_like(verts), jnp.ones_like(joints)))


@jax.jit
def joints_forward(model, params):
    return jax.vmap(mano.forward_joints, in_axes=(None, 0))(model, params)


@jax.jit
def joints_vjp(model, params):
    joints, pullback = jax.vjp(lambda p: joints_forward.__wrapped__(model, p), params)
    return pullback(jnp.ones_like(joints))


def smplx_candidates(model: mano.ManoModel, params: mano.ManoParams):
    """smplx MANO no-grad forward and forward+backward on our model, or None."""
    try:
        import smplx
        import torch
    except ImportError:
        return None
    torch.set_num_threads(os.cpu_count() or 1)
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


def joints_jacobian(model, params, analytic_jvp: bool):
    """What a fit's Jacobian costs: jacfwd of forward_joints in the parameters."""
    fn = functools.partial(mano.forward_joints, analytic_jvp=analytic_jvp)
    return jax.vmap(jax.jacfwd(fn, argnums=1), in_axes=(None, 0))(model, params)


analytic_jacobian = jax.jit(functools.partial(joints_jacobian, analytic_jvp=True))
autodiff_jacobian = jax.jit(functools.partial(joints_jacobian, analytic_jvp=False))


def run(batches, rounds: int) -> list[dict]:
    rows = []
    for x64 in (False, True):
        with jax.enable_x64(x64):
            dtype = jnp.float64 if x64 else jnp.float32
            model = mano.load_builtin("right")
            for batch in batches:
                params = random_params(batch, dtype)
                ours = {
                    "full": lambda: full_forward(model, params),
                    "full+vjp": lambda: full_vjp(model, params),
                    "joints": lambda: joints_forward(model, params),
                    "joints+vjp": lambda: joints_vjp(model, params),
                    "jacfwd autodiff": lambda: autodiff_jacobian(model, params),
                    "jacfwd analytic": lambda: analytic_jacobian(model, params),
                }
                compiled = {name: compile_seconds(fn) for name, fn in ours.items()}
                candidates = dict(ours)
                peers = smplx_candidates(model, params) if not x64 else None
                if peers:
                    candidates.update(peers)
                times = interleaved(candidates, rounds=rounds)
                for name, seconds in times.items():
                    rows.append(
                        dict(
                            dtype="float64" if x64 else "float32",
                            batch=batch,
                            method=name,
                            ms=seconds * 1e3,
                            hands_per_s=batch / seconds,
                            compile_s=compiled.get(name),
                        )
                    )
                _print_block(rows, batch, "float64" if x64 else "float32")
    return rows


def _print_block(rows, batch, dtype):
    block = [r for r in rows if r["batch"] == batch and r["dtype"] == dtype]
    by = {r["method"]: r for r in block}
    print(f"\n{dtype}  B={batch}")
    for r in block:
        compile_s = f"  compile {r['compile_s']:.2f}s" if r["compile_s"] is not None else ""
        print(f"  {r['method']:<14} {r['ms']:10.3f} ms  {r['hands_per_s']:12.0f} hands/s{compile_s}")
    print(f"  ratio jacfwd autodiff / analytic JVP: {by['jacfwd autodiff']['ms'] / by['jacfwd analytic']['ms']:6.1f}x")
    if "smplx" in by:
        print(f"  ratio smplx / ours full        : {by['smplx']['ms'] / by['full']['ms']:6.1f}x")
        print(f"  ratio smplx / ours joints-only : {by['smplx']['ms'] / by['joints']['ms']:6.1f}x")
        print(f"  ratio smplx fwd+bwd / full+vjp : {by['smplx fwd+bwd']['ms'] / by['full+vjp']['ms']:6.1f}x")
        print(f"  ratio smplx fwd+bwd / joints+vjp: {by['smplx fwd+bwd']['ms'] / by['joints+vjp']['ms']:6.1f}x")


def main():
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--batches", type=int, nargs="+", default=[1, 64, 1024, 8192])
    parser.add_argument("--rounds", type=int, default=5)
    parser.add_argument("--json", type=str, default=None, help="also write the rows as JSON")
    args = parser.parse_args()
    print(machine())
    rows = run(args.batches, args.rounds)
    if args.json:
        with open(args.json, "w") as f:
            json.dump(rows, f, indent=1)


if __name__ == "__main__":
    main()
