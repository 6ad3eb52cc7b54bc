"""ESTHER forward cost on this CPU: time per 16-frame stereo clip and memory, for the
small configs (from crops, backbone included) and for the paper's stack on precomputed
DINOv3-L features (D=512, 4/4/2 layers; the frozen backbone's features are extracted
once), plus forward+gradient (a training step's cost without the optimiser).

    python benchmarks/model.py [--configs cpu-tiny cpu-small paper] [--batch 4] [--backbone] [--rank-promotion] [--json out.json]

Every row is compiled first (compile time reported apart), then timed as the median
of interleaved rounds. Memory is XLA's buffer assignment of the compiled call
(arguments + outputs + temporaries: the peak the executable needs) and the process's
peak resident set. `--backbone` also times the frozen ViT-L/16 on one clip's 32 crops
(slow on 2 cores).

`--rank-promotion` also times, side by side, each config's forward with today's network,
traced under strict rank promotion (every broadcast explicit), and with the network of
commit `IMPLICIT_RANK_COMMIT`, the last whose layers broadcast implicitly under
`jax.numpy_rank_promotion("allow")` (its whole `esther_jax` read with `git archive`
and imported beside today's; same weights from the same key). It prints both times,
their ratio, the largest difference of the joints and whether XLA's optimised programs
are the same text (metadata, which names source lines, left out).
"""

import argparse
import atexit
import dataclasses
import importlib
import io
import json
import os
import pathlib
import re
import resource
import shutil
import subprocess
import sys
import tarfile
import tempfile
import time

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

sys.path.insert(0, os.path.dirname(__file__))
from _timing import compile_seconds, interleaved, machine  # noqa: E402

from esther_jax import model as M  # noqa: E402
from esther_jax.cameras import rig_preset  # noqa: E402
from esther_jax.mano import load_builtin  # noqa: E402

FRAMES = 16
IMPLICIT_RANK_COMMIT = "27eaf3ce8a777d5c929766715d115911e5892731"
"""The last commit whose network broadcast implicitly (its 13 entry points ran under
`jax.numpy_rank_promotion("allow")`); the next made every broadcast explicit."""


def clip_batch(cfg: M.ModelConfig, batch: int, *, features: bool, key) -> M.ClipInput:
    S, T = cfg.crop_size, FRAMES
    k1, k2 = jax.random.split(key)
    f = 1.2 * S
    K = jnp.asarray([[f, 0.0, S / 2 - 0.5], [0.0, f, S / 2 - 0.5], [0.0, 0.0, 1.0]])
    shape = (batch, T, 2)
    return M.ClipInput(
        images=None if features else jax.random.uniform(k1, shape + (3, S, S)),
        features=jax.random.normal(k1, shape + (cfg.grid**2, cfg.backbone_spec.width)) if features else None,
        K=jnp.broadcast_to(K, shape + (3, 3)),
        R_cam_crop=jnp.broadcast_to(jnp.eye(3), shape + (3, 3)),
        T_rig_cams=jnp.broadcast_to(rig_preset("esther").T_rig_cams, (batch, 2, 4, 4)),
        flow=0.01 * jax.random.normal(k2, (batch, T, 192)),
        view_present=jnp.ones(shape, bool),
    )


def _bytes(compiled) -> int:
    m = compiled.memory_analysis()
    return int(m.argument_size_in_bytes + m.output_size_in_bytes + m.temp_size_in_bytes - m.alias_size_in_bytes)


def measure(name: str, batch: int, rounds: int) -> list[dict]:
    features = name == "paper"
    cfg = M.config(name, num_frames=FRAMES, precomputed_features=features)
    net = M.ESTHER(cfg, key=jax.random.key(0))
    hand = load_builtin("right")
    rows = []
    for b in sorted({1, batch}):
        clips = clip_batch(cfg, b, features=features, key=jax.random.key(1))
        forward = jax.jit(jax.vmap(lambda n, c: n(c, hand).joints, in_axes=(None, 0)))

        params, static = eqx.partition(net, eqx.is_array)

        def loss(p, c):
            out = jax.vmap(lambda x: eqx.combine(p, static)(x, hand))(c)
            return jnp.mean(jnp.abs(out.joints)) + jnp.mean(jnp.abs(out.vertices))

        train = jax.jit(jax.grad(loss))
        t0 = time.perf_counter()
        compiled_fwd = forward.lower(net, clips).compile()
        compile_fwd = time.perf_counter() - t0
        t0 = time.perf_counter()
        compiled_grad = train.lower(params, clips).compile()
        compile_grad = time.perf_counter() - t0
        times = interleaved({"fwd": lambda: compiled_fwd(net, clips), "grad": lambda: compiled_grad(params, clips)}, rounds=rounds)
        rows.append(
            dict(
                config=cfg.name, input="features" if features else f"crops {cfg.crop_size}px", batch=b,
                fwd_ms_per_clip=1e3 * times["fwd"] / b, grad_ms_per_clip=1e3 * times["grad"] / b,
                compile_fwd_s=compile_fwd, compile_grad_s=compile_grad,
                xla_fwd_mib=_bytes(compiled_fwd) / 2**20, xla_grad_mib=_bytes(compiled_grad) / 2**20, trainable_m=M.parameter_counts(cfg)["trainable"] / 1e6,
            )
        )  # fmt: skip
    return rows


def backbone_row(rounds: int) -> dict:
    spec = M.BACKBONES["dinov3-vitl16"]
    vit = M.make_backbone(spec, key=jax.random.key(0))
    images = jax.random.uniform(jax.random.key(1), (FRAMES, 2, 3, 224, 224))
    extract = jax.jit(M.extract_features)
    compile_s = compile_seconds(extract, vit, images)
    seconds = interleaved({"vit": lambda: extract(vit, images)}, rounds=rounds, min_time=0.0)["vit"]
    return dict(config="dinov3-vitl16 backbone", input="crops 224px", batch=1, fwd_ms_per_clip=1e3 * seconds,
                grad_ms_per_clip=float("nan"), compile_fwd_s=compile_s, compile_grad_s=float("nan"),
                xla_fwd_mib=_bytes(extract.lower(vit, images).compile()) / 2**20, xla_grad_mib=float("nan"), trainable_m=0.0)  # fmt: skip


def model_at(commit: str):
    """`esther_jax.model` as of `commit`: the whole `esther_jax` tree of that commit
    (`git archive`) imported as the package `esther_jax_<commit>`, so the old network runs
    on the core, hand model and clip format of its own time."""
    root = pathlib.Path(__file__).resolve().parents[1]
    package = f"esther_jax_{commit[:7]}"
    if package not in sys.modules:
        done = subprocess.run(["git", "-C", str(root), "archive", "--format=tar", commit, "esther_jax"], capture_output=True)
        if done.returncode:
            raise SystemExit(f"--rank-promotion reads the network of commit {commit[:7]} from git in {root}: {done.stderr.decode().strip()}")
        folder = pathlib.Path(tempfile.mkdtemp(prefix=f"{package}-"))
        atexit.register(shutil.rmtree, folder, ignore_errors=True)
        with tarfile.open(fileobj=io.BytesIO(done.stdout)) as tar:
            tar.extractall(folder, filter="data")
        (folder / "esther_jax").rename(folder / package)
        sys.path.insert(0, str(folder))
    try:
        return importlib.import_module(f"{package}.model")
    except ImportError as err:
        raise SystemExit(f"the network of commit {commit[:7]} does not import ({err})") from err


def _program_text(compiled) -> str:
    """XLA's optimised program without its metadata (op names, source lines and the
    tables of files and stack frames they point into)."""
    return re.sub(r", metadata=\{[^}]*\}", "", compiled.as_text().split("\nFileNames\n")[0])


def rank_promotion_rows(name: str, batch: int, rounds: int) -> list[dict]:
    """Today's forward (explicit broadcasts, traced under strict rank promotion) against
    the forward of `IMPLICIT_RANK_COMMIT` (implicit broadcasts), timed round robin."""
    old = model_at(IMPLICIT_RANK_COMMIT)
    features = name == "paper"
    hand = load_builtin("right")
    nets = {
        "explicit": M.ESTHER(M.config(name, num_frames=FRAMES, precomputed_features=features), key=jax.random.key(0)),
        "implicit": old.ESTHER(old.config(name, num_frames=FRAMES, precomputed_features=features), key=jax.random.key(0)),
    }
    same_weights = all(bool(jnp.array_equal(a, b)) for a, b in zip(*(jax.tree.leaves(n) for n in nets.values()), strict=True))
    rows = []
    for b in sorted({1, batch}):
        clips = clip_batch(nets["explicit"].config, b, features=features, key=jax.random.key(1))
        inputs = {"explicit": clips, "implicit": old.ClipInput(**{f.name: getattr(clips, f.name) for f in dataclasses.fields(clips)})}
        forward = jax.jit(jax.vmap(lambda n, c: n(c, hand).joints, in_axes=(None, 0)))
        compiled, compile_s = {}, {}
        for kind, net in nets.items():
            t0 = time.perf_counter()
            with jax.numpy_rank_promotion("raise" if kind == "explicit" else "allow"):
                compiled[kind] = forward.lower(net, inputs[kind]).compile()
            compile_s[kind] = time.perf_counter() - t0
        calls = {kind: (lambda kind=kind: compiled[kind](nets[kind], inputs[kind])) for kind in nets}
        times = interleaved(calls, rounds=rounds)
        joints = {kind: np.asarray(call()) for kind, call in calls.items()}
        rows.append(dict(
            config=name, batch=b, explicit_ms_per_clip=1e3 * times["explicit"] / b, implicit_ms_per_clip=1e3 * times["implicit"] / b,
            ratio=times["explicit"] / times["implicit"], compile_explicit_s=compile_s["explicit"], compile_implicit_s=compile_s["implicit"],
            max_abs_joint_diff_m=float(np.max(np.abs(joints["explicit"] - joints["implicit"]))), same_weights=same_weights,
            same_program=_program_text(compiled["explicit"]) == _program_text(compiled["implicit"]),
        ))  # fmt: skip
    return rows


def main():
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--configs", nargs="+", default=["cpu-tiny", "cpu-small", "paper"])
    parser.add_argument("--batch", type=int, default=4)
    parser.add_argument("--rounds", type=int, default=5)
    parser.add_argument("--backbone", action="store_true")
    parser.add_argument("--rank-promotion", action="store_true", help="explicit broadcasts against the implicit ones of IMPLICIT_RANK_COMMIT")
    parser.add_argument("--json")
    args = parser.parse_args()
    rows = [row for name in args.configs for row in measure(name, args.batch, args.rounds)]
    if args.backbone:
        rows.append(backbone_row(max(1, args.rounds // 2)))
    print(f"{machine()}, {jax.devices()[0].device_kind}, {FRAMES}-frame stereo clips, float32")
    header = (f"{'config':<24}{'input':<14}{'B':>3}{'fwd ms/clip':>13}{'fwd+grad ms/clip':>18}{'compile s':>12}"
              f"{'XLA MiB fwd/grad':>18}{'train M':>9}")
    print(header)
    for r in rows:
        print(f"{r['config']:<24}{r['input']:<14}{r['batch']:>3}{r['fwd_ms_per_clip']:>13.1f}{r['grad_ms_per_clip']:>18.1f}"
              f"{r['compile_fwd_s']:>7.1f}/{r['compile_grad_s']:<4.0f}{r['xla_fwd_mib']:>10.0f}/{r['xla_grad_mib']:<7.0f}"
              f"{r['trainable_m']:>9.2f}")  # fmt: skip
    rank_rows = [row for name in args.configs for row in rank_promotion_rows(name, args.batch, args.rounds)] if args.rank_promotion else []
    if rank_rows:
        print(f"forward, explicit broadcasts (strict rank promotion) against implicit ones (commit {IMPLICIT_RANK_COMMIT[:7]}, rank promotion allowed)")
        print(f"{'config':<24}{'B':>3}{'explicit ms/clip':>18}{'implicit ms/clip':>18}{'explicit/implicit':>19}{'compile s':>13}"
              f"{'max |d joints| m':>18}{'same weights':>14}{'same program':>14}")  # fmt: skip
        for r in rank_rows:
            print(f"{r['config']:<24}{r['batch']:>3}{r['explicit_ms_per_clip']:>18.1f}{r['implicit_ms_per_clip']:>18.1f}{r['ratio']:>19.3f}"
                  f"{r['compile_explicit_s']:>8.1f}/{r['compile_implicit_s']:<4.1f}{r['max_abs_joint_diff_m']:>18.1e}"
                  f"{'yes' if r['same_weights'] else 'NO':>14}{'yes' if r['same_program'] else 'no':>14}")  # fmt: skip
    peak = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024
    print(f"process peak RSS: {peak:.0f} MiB")
    if args.json:
        with open(args.json, "w") as f:
            json.dump({"rows": rows, "rank_promotion_rows": rank_rows, "peak_rss_mib": peak}, f, indent=2)


if __name__ == "__main__":
    main()
