"""The teacher: accuracy over synthetic clips and speed per stage, with peers on one objective.

    python benchmarks/teacher.py [--clips 20] [--frames 128]

1. Accuracy (issue 6 acceptance): clips of the paper's rig, default detector noise, both
   hands; P-MPJPE, PA-MPJPE, wrist error over valid on-screen frames, label jitter vs the
   ground truth's own; then the same clips with one view missing for a quarter of the
   frames (stereo frames must keep their accuracy, mono frames must be flagged).
2. Speed: hand-frames per second of the whole pipeline and per stage (after compilation).
3. Peers on the same per-frame objective (stage 2: Huber 2D + pose prior + wrist anchor)
   and the same starts: our vmapped optimistix dogleg (stage 2's two phases), scipy `least_squares` (JAX residual
   and jitted `jacfwd` Jacobian, one frame at a time) and Adam (optax, 300 steps, vmapped).
   Target: ours >= 10x faster than scipy at an equal or lower final error.
"""

import argparse
import os
import sys
import time

import jax
import jax.numpy as jnp
import numpy as np

sys.path.insert(0, os.path.dirname(__file__))

from esther_jax import mano, metrics  # noqa: E402
from esther_jax.data import motion, synth  # noqa: E402
from fitting import objectives, pipeline  # noqa: E402
from fitting.pipeline import LabelConfig, label_hand  # noqa: E402


def evaluate(labels, gt, frames=None):
    ok = labels["valid"] & gt["onscreen"]
    if frames is not None:
        ok &= frames
    pred, true = jnp.asarray(labels["joints"]), jnp.asarray(gt["joints"])
    per = lambda f: np.asarray(jax.vmap(f)(pred, true))[ok]  # noqa: E731
    return {
        "p_mpjpe": per(metrics.p_mpjpe).mean() * 1000 if ok.any() else np.nan,
        "pa_mpjpe": per(metrics.pa_mpjpe).mean() * 1000 if ok.any() else np.nan,
        "wrist": per(metrics.wrist_error).mean() * 1000 if ok.any() else np.nan,
        "jitter": float(metrics.jitter(pred, jnp.asarray(ok), 30.0).value),
        "gt_jitter": float(metrics.jitter(true, jnp.asarray(gt["onscreen"]), 30.0).value),
        "coverage": ok.sum() / max(gt["onscreen"].sum(), 1),
    }


def drop_view(keypoints, rng, fraction=0.25):
    kp = {k: v.copy() for k, v in keypoints.items()}
    T = kp["uv"].shape[1]
    frames = rng.choice(T, int(fraction * T), replace=False)
    view = rng.integers(2, size=len(frames))
    for t, v in zip(frames, view):
        kp["conf"][:, t, v] = 0.0
        kp["box_score"][:, t, v] = 0.0
    dropped = np.zeros(T, bool)
    dropped[frames] = True
    return kp, dropped


def accuracy(num_clips, frames):
    cfg = synth.SynthConfig(num_frames=frames, motion_config=motion.MotionConfig(two_hands_probability=1.0))
    rows, rows_drop, mono_flagged, speed = [], [], [], []
    for i in range(num_clips):
        clip = synth.make_clip(1000, i, cfg)
        for side in clip.keypoints:
            model = mano.load_builtin(side)
            t0 = time.perf_counter()
            labels, report = label_hand(model, clip.rig, clip.keypoints[side], 30.0)
            speed.append((frames, time.perf_counter() - t0, report["timings"]))
            rows.append(evaluate(labels, clip.gt[side]))
            kp, dropped = drop_view(clip.keypoints[side], np.random.default_rng([i, len(side)]))
            labels_drop, _ = label_hand(model, clip.rig, kp, 30.0)
            rows_drop.append(evaluate(labels_drop, clip.gt[side], frames=~dropped))
            seen = clip.gt[side]["onscreen"] & dropped
            mono_flagged.append((~labels_drop["stereo"][seen]).mean() if seen.any() else 1.0)
    return rows, rows_drop, mono_flagged, speed


def summarise(rows, title):
    keys = ("p_mpjpe", "pa_mpjpe", "wrist", "jitter", "gt_jitter", "coverage")
    mean = {k: float(np.nanmean([r[k] for r in rows])) for k in keys}
    print(f"{title}: P-MPJPE {mean['p_mpjpe']:.2f} mm, PA-MPJPE {mean['pa_mpjpe']:.2f} mm, wrist {mean['wrist']:.2f} mm, "
          f"jitter {mean['jitter']:.2f} m/s^2 (GT {mean['gt_jitter']:.2f}, ratio {mean['jitter'] / mean['gt_jitter']:.2f}), "
          f"coverage {mean['coverage']:.1%}  [{len(rows)} hands]")
    return mean


def peers(frames=32):
    """Stage-2 objective on `frames` frames: ours vs scipy least_squares vs Adam."""
    import optax

    cfg = synth.SynthConfig(num_frames=frames, motion_config=motion.MotionConfig(two_hands_probability=0.0))
    clip = synth.make_clip(7, 3, cfg)
    side = next(iter(clip.keypoints))
    model = mano.load_builtin(side)
    dtype = jnp.result_type(float)
    length = max(pipeline.BUCKET, frames)
    padded = {k: jnp.asarray(pipeline._pad(np.moveaxis(v, 1, 0), length).swapaxes(0, 1), dtype) for k, v in clip.keypoints[side].items()}
    fused, evidence = pipeline._fuse_and_filter(clip.rig, padded["uv"], padded["conf"], padded["box"], padded["box_score"], pipeline.initialise.template_bones(model))
    betas = jnp.asarray(clip.gt[side]["betas"], dtype)
    init = pipeline.initialise.initialise(model, evidence, betas)
    problem = objectives.Problem(model, clip.rig, objectives.PosePrior.from_model(model, betas), objectives.MotionPrior(), objectives.FitWeights(), betas, 30.0)
    idx = np.arange(frames)
    data = pipeline._frame_data(evidence, init, idx)
    track = objectives.Track.none(frames, dtype)
    y0 = objectives.FrameUnknowns(init.global_orient[idx], jnp.broadcast_to(model.hands_mean.reshape(15, 3), (frames, 15, 3)), jnp.zeros((frames, 3), dtype))
    gt_joints = clip.gt[side]["joints"][:frames]

    def cost(y, d, tr):
        r = objectives.frame_residuals(y, (problem, d, tr))
        return sum(jnp.sum(x * x) for x in r)

    costs = jax.jit(jax.vmap(cost))
    joints_of = jax.jit(jax.vmap(lambda y, d: mano.forward_joints(model, objectives._params(y, d, betas))))

    def report(name, seconds, y):
        err = np.linalg.norm(np.asarray(joints_of(y, data)) - gt_joints, axis=-1).mean() * 1000
        c = np.asarray(costs(y, data, track))
        print(f"  {name:<34} {seconds * 1000:9.1f} ms ({frames / seconds:7.1f} frames/s)  objective {c.mean():9.2f}  joint error {err:6.2f} mm")
        return seconds, c.mean(), err

    config = LabelConfig()
    jax.block_until_ready(pipeline.solve_frames_staged(problem, y0, data, config).value)
    times = []
    for _ in range(5):  # median of 5 (scipy: of 3)
        t0 = time.perf_counter()
        y_ours = jax.block_until_ready(pipeline.solve_frames_staged(problem, y0, data, config).value)
        times.append(time.perf_counter() - t0)
    r_ours = report(f"ours: optimistix dogleg (2 x {config.stage2_steps} steps)", float(np.median(times)), y_ours)

    try:
        from scipy.optimize import least_squares
    except ImportError:
        print("  scipy not installed: skipped")
        return
    from jax.flatten_util import ravel_pytree

    flat0, unravel = ravel_pytree(jax.tree.map(lambda x: x[0], y0))

    def resid_flat(x, d):
        return jnp.concatenate([r.reshape(-1) for r in objectives.frame_residuals(unravel(x), (problem, d, jax.tree.map(lambda a: a[0], track)))])

    f = jax.jit(resid_flat)
    jac = jax.jit(jax.jacfwd(resid_flat))
    solutions = []
    frame = lambda t: jax.tree.map(lambda a: a[t], data)  # noqa: E731
    f(flat0, frame(0)).block_until_ready()
    jac(flat0, frame(0)).block_until_ready()
    times = []
    for _ in range(3):
        solutions = []
        t0 = time.perf_counter()
        for t in range(frames):
            x0 = ravel_pytree(jax.tree.map(lambda a: a[t], y0))[0]
            d = frame(t)
            sol = least_squares(lambda x: np.asarray(f(x, d), np.float64), np.asarray(x0, np.float64), jac=lambda x: np.asarray(jac(x, d), np.float64), method="trf")
            solutions.append(unravel(jnp.asarray(sol.x, dtype)))
        times.append(time.perf_counter() - t0)
    y_scipy = jax.tree.map(lambda *x: jnp.stack(x), *solutions)
    r_scipy = report("scipy least_squares + JAX jacobian", float(np.median(times)), y_scipy)

    optimiser = optax.adam(0.01)

    @jax.jit
    def adam(y):
        def step(carry, _):
            y, state = carry
            g = jax.vmap(jax.grad(cost))(y, data, track)
            updates, state = optimiser.update(g, state)
            return (optax.apply_updates(y, updates), state), None

        (y, _), _ = jax.lax.scan(step, (y, optimiser.init(y)), None, length=300)
        return y

    jax.block_until_ready(adam(y0))
    times = []
    for _ in range(5):
        t0 = time.perf_counter()
        y_adam = jax.block_until_ready(adam(y0))
        times.append(time.perf_counter() - t0)
    report("Adam (optax, 300 steps, vmapped)", float(np.median(times)), y_adam)
    print(f"  ours vs scipy: {r_scipy[0] / r_ours[0]:.1f}x faster; objective {r_ours[1]:.2f} vs {r_scipy[1]:.2f}; joint error {r_ours[2]:.2f} vs {r_scipy[2]:.2f} mm")


def main():
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--clips", type=int, default=20)
    parser.add_argument("--frames", type=int, default=128)
    args = parser.parse_args()
    print(f"jax {jax.__version__}, {os.cpu_count()} cores; {args.clips} clips x {args.frames} frames, both hands, default detector preset")
    warm = synth.make_clip(0, 0, synth.SynthConfig(num_frames=args.frames))
    for side in warm.keypoints:  # compile once per side (left and right share graphs)
        t0 = time.perf_counter()
        label_hand(mano.load_builtin(side), warm.rig, warm.keypoints[side], 30.0)
        print(f"warm-up (compilation or cache load): {time.perf_counter() - t0:.1f} s")
    rows, rows_drop, mono, speed = accuracy(args.clips, args.frames)
    print()
    summarise(rows, "all views")
    summarise(rows_drop, "one view missing in 25% of frames, scored on the stereo frames")
    print(f"mono frames flagged (stereo = False): {np.mean(mono):.1%}")
    frames = sum(s[0] for s in speed)
    seconds = sum(s[1] for s in speed)
    stages = {k: sum(s[2][k] for s in speed) for k in speed[0][2]}
    print(f"\nspeed: {frames / seconds:.0f} hand-frames/s over {len(speed)} hands ({seconds / len(speed):.2f} s per {args.frames}-frame hand)")
    for k, v in stages.items():
        print(f"  {k:<16} {v / len(speed) * 1000:8.1f} ms per hand ({frames / max(v, 1e-9):8.0f} hand-frames/s)")
    print("\npeers on the stage-2 objective (32 frames, same starts):")
    peers()


if __name__ == "__main__":
    main()
