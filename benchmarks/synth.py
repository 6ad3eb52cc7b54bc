"""Synthetic clip engine throughput.

    python benchmarks/synth.py [--clips 5]

Keypoint-only clips (64 frames; motion, FK, visibility, two detectors), rendering of
full 1920x1200 stereo frames and of 224x224 hand crops (+ flow tokens). Targets
(issue 5): a 64-frame keypoint-only clip in under 1 s; crops fast enough for 1000
training clips of 16 frames in under 30 minutes. Medians over clips after a warm-up.
"""

import argparse
import os
import statistics
import sys
import time

import numpy as np

sys.path.insert(0, os.path.dirname(__file__))

from esther_jax.data import motion, render, synth  # noqa: E402


def timed(fn, repeats):
    times = []
    for i in range(repeats):
        t0 = time.perf_counter()
        out = fn(i)
        times.append(time.perf_counter() - t0)
    return statistics.median(times), out


def main():
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--clips", type=int, default=5)
    args = parser.parse_args()
    cfg64 = synth.SynthConfig(num_frames=64, motion_config=motion.MotionConfig(two_hands_probability=1.0))
    synth.make_clip(0, 0, cfg64)  # compile
    seconds, _ = timed(lambda i: synth.make_clip(0, 100 + i, cfg64), args.clips)
    print(f"keypoint-only clip, 64 frames, two hands: {seconds:.3f} s  (target < 1 s)")

    crop_cfg = synth.SynthConfig(num_frames=16, crops=True)
    synth.make_clip(0, 0, crop_cfg)
    hands = []
    seconds, _ = timed(lambda i: hands.append(len(synth.make_clip(0, 200 + i, crop_cfg).crops)), args.clips)
    per_crop = seconds / (16 * 2 * np.mean(hands))
    print(f"crops clip, 16 frames ({np.mean(hands):.1f} hands avg): {seconds:.3f} s per clip, "
          f"{1 / per_crop:.1f} crops/s (224x224, incl. flow tokens)")
    print(f"  -> 1000 training clips of 16 frames: {seconds * 1000 / 60:.1f} min  (target < 30 min)")

    m = motion.sample_clip(np.random.default_rng(0), synth.cameras.rig_preset("esther"), 8)
    scene = render.sample_scene(np.random.default_rng(0))
    rig = m.rig
    rays = render._pixel_rays(rig.left)
    vertices = {side: np.asarray(track.vertices, np.float64) for side, track in m.hands.items()}
    seconds, _ = timed(lambda i: render.render_view(scene, rig.left, m.T_world_rig[i % 8], synth._meshes_in(vertices, m, scene, i % 8, np.eye(4)), rays), 8)
    print(f"full frame 1920x1200, one view: {seconds * 1000:.0f} ms ({1 / seconds:.1f} views/s)")


if __name__ == "__main__":
    main()
