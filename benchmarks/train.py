"""Training cost and a first learning check on this CPU.

    python benchmarks/train.py steps   [--configs cpu-tiny cpu-small] [--batch 8]
    python benchmarks/train.py overfit [--config cpu-tiny] [--steps 300] [--batch 2]

`steps`: the jitted training step (corruption, forward, appendix-B losses, gradient,
AdamW update) per config in float32: compile time apart, then the median step time,
clips per second and the process's peak resident set (cumulative over the rows).
Batches are synthetic windows (a 16-frame synthetic clip with crops at the config's
size, both hands), the same for every step.

`overfit`: the first thing to prove before trusting a curve: one synthetic clip, one
window per hand, trained for `--steps` steps (stage 'joint', warm-up 20 steps, peak
learning rate 1e-3); the loss terms every 10 % of the run and the final P-MPJPE /
wrist error of the network on its own training windows (no augmentation at test time).
"""

import argparse
import os
import resource
import sys
import tempfile
import time

import jax
import jax.numpy as jnp
import numpy as np

sys.path.insert(0, os.path.dirname(__file__))
from _timing import compile_seconds, median_seconds  # noqa: E402

from esther_jax import mano, metrics  # noqa: E402
from esther_jax import model as M  # noqa: E402
from esther_jax import train  # noqa: E402
from esther_jax.data import motion, synth  # noqa: E402


def _clip_folder(crop_size: int, frames: int = 16) -> str:
    root = tempfile.mkdtemp(prefix="esther_bench_train_")
    cfg = synth.SynthConfig(num_frames=frames, crops=True, crop_size=crop_size, motion_config=motion.MotionConfig(two_hands_probability=1.0))
    return str(synth.write_clip(synth.make_clip(0, 0, cfg), os.path.join(root, "clip_00000")))


def bench_steps(configs: list[str], batch: int) -> None:
    print(f"training step, float32, batch {batch}, 16-frame windows (median of rounds; compile apart)")
    print(f"{'config':<10} {'compile s':>10} {'step s':>9} {'clips/s':>8} {'peak RSS MiB':>13}")
    hand = mano.load_builtin("right")
    for name in configs:
        cfg = M.config(name)
        folder = _clip_folder(cfg.crop_size, cfg.num_frames)
        data_cfg = train.DataConfig(frames=cfg.num_frames, crop_size=cfg.crop_size)
        windows = train.build_index([folder], data_cfg)
        clips_b, targets_b = train.load_batch(windows, data_cfg, batch, seed=0, step=0)
        trainer = train.Trainer(M.ESTHER(cfg, key=jax.random.key(0)), train.TrainConfig(batch=batch), hand)
        state = trainer.init()
        step = lambda s: trainer.step(s, clips_b, targets_b)  # noqa: E731
        compiled = compile_seconds(step, state)
        seconds = median_seconds(step, state, rounds=3, min_time=0.5)
        rss = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024
        print(f"{name:<10} {compiled:10.1f} {seconds:9.3f} {batch / seconds:8.1f} {rss:13.0f}")


def overfit(name: str, steps: int, batch: int) -> None:
    cfg = M.config(name)
    folder = _clip_folder(cfg.crop_size, cfg.num_frames)
    data_cfg = train.DataConfig(frames=cfg.num_frames, crop_size=cfg.crop_size)
    windows = train.build_index([folder], data_cfg)
    hand = mano.load_builtin("right")
    tcfg = train.TrainConfig(steps=steps, batch=batch, warmup_steps=20, learning_rate=1e-3)
    trainer = train.Trainer(M.ESTHER(cfg, key=jax.random.key(0)), tcfg, hand)
    state = trainer.init()
    print(f"overfitting {len(windows)} windows of one clip ({name}, batch {batch}, {steps} steps, lr 1e-3)")
    shown = ("loss", "loss/joints", "loss/canonical", "loss/transl", "loss/two_d", "loss/triangulation", "loss/onscreen")
    print(f"{'step':>6} " + " ".join(f"{k.split('/')[-1]:>13}" for k in shown))
    t0 = time.perf_counter()
    for step in range(steps):
        clips_b, targets_b = train.load_batch(windows, data_cfg, batch, tcfg.seed, step)
        state, values = trainer.step(state, clips_b, targets_b)
        if step == 0 or (step + 1) % max(steps // 10, 1) == 0:
            values = jax.device_get(values)
            print(f"{step + 1:6d} " + " ".join(f"{float(values[k]):13.4f}" for k in shown))
    print(f"{time.perf_counter() - t0:.0f} s")
    net = trainer.network(state)
    errors = []
    for window in windows:
        clip, targets = train.load_example(window, data_cfg)
        out = jax.jit(lambda c: net(c, hand))(clip)
        ok = np.asarray(targets.valid)
        p = np.asarray(jax.vmap(metrics.p_mpjpe)(out.joints, targets.joints))[ok]
        w = np.asarray(jnp.linalg.norm(out.joints[:, 0] - targets.joints[:, 0], axis=-1))[ok]
        errors.append((window.side, 1000 * p.mean(), 1000 * w.mean()))
    for side, p, w in errors:
        print(f"{side:>5} hand on its training window: P-MPJPE {p:6.1f} mm, wrist {w:6.1f} mm")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    sub = parser.add_subparsers(dest="what", required=True)
    s = sub.add_parser("steps")
    s.add_argument("--configs", nargs="+", default=["cpu-tiny", "cpu-small"])
    s.add_argument("--batch", type=int, default=8)
    o = sub.add_parser("overfit")
    o.add_argument("--config", default="cpu-tiny")
    o.add_argument("--steps", type=int, default=300)
    o.add_argument("--batch", type=int, default=2)
    args = parser.parse_args()
    from esther_jax import enable_compilation_cache

    enable_compilation_cache()
    if args.what == "steps":
        bench_steps(args.configs, args.batch)
    else:
        overfit(args.config, args.steps, args.batch)


if __name__ == "__main__":
    main()
