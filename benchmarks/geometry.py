"""Geometry kernels: confidence-weighted stereo triangulation against OpenCV, and
Fisheye624 project / unproject throughput.

    python benchmarks/geometry.py [--frames 1 1000 100000] [--rounds 5]

Triangulation: N frames x 21 joints x 2 views on the paper's rig (f 623 px, 62 mm),
points 0.25-0.6 m away, 2 px pixel noise, confidences in [0.3, 1]. Ours returns the
point, a validity flag, per-view reprojection residuals and the ray spread; OpenCV's
`triangulatePoints` (one vectorised call, unweighted) returns the point only. Both are
timed round robin in one run; the mean 3D error against the truth is printed beside
the times (equal accuracy is part of the target). Target (issue 3): >= 10x OpenCV's
throughput at N = 100000.
"""

import argparse
import os
import sys

import cv2
import jax
import jax.numpy as jnp
import numpy as np

sys.path.insert(0, os.path.dirname(__file__))
from _timing import compile_seconds, interleaved, machine  # noqa: E402

from esther_jax import cameras  # noqa: E402
from esther_jax.triangulation import triangulate_batch  # noqa: E402


def stereo_data(frames: int, seed: int = 0):
    rig = cameras.rig_preset("esther")
    rng = np.random.default_rng(seed)
    points = rng.uniform([-0.15, -0.1, 0.25], [0.15, 0.15, 0.6], size=(frames, 21, 3)).astype(np.float32)
    uv = np.moveaxis(np.asarray(rig.project(jnp.asarray(points)), np.float64), 0, 2)  # (N, 21, 2 views, 2)
    uv = (uv + rng.normal(scale=2.0, size=uv.shape)).astype(np.float32)
    conf = rng.uniform(0.3, 1.0, size=(frames, 21, 2)).astype(np.float32)
    # OpenCV's projection matrices (its own input format; the rig's pinhole intrinsics).
    K = np.asarray(rig.left.K, np.float64)
    P_left = K @ np.eye(3, 4)
    P_right = K @ np.asarray(rig.T_right_left, np.float64)[:3]
    return rig, points, uv, conf, P_left, P_right


@jax.jit
def ours(rig, uv, conf):
    r = triangulate_batch(rig.cameras, rig.T_rig_cams, uv, conf)
    return r.point, r.valid, r.residual_px, r.spread


def run_triangulation(frame_counts, rounds):
    print("\ntriangulation: N frames x 21 joints x 2 views (float32; OpenCV in float64)")
    print(f"  {'N':>7} {'ours ms':>10} {'cv2 ms':>10} {'ours pts/s':>12} {'cv2 pts/s':>12} {'ratio':>6} {'err ours mm':>12} {'err cv2 mm':>11}")
    for n in frame_counts:
        rig, points, uv, conf, P_left, P_right = stereo_data(n)
        uv_j, conf_j = jnp.asarray(uv), jnp.asarray(conf)
        left = np.ascontiguousarray(uv[:, :, 0].reshape(-1, 2).T.astype(np.float64))
        right = np.ascontiguousarray(uv[:, :, 1].reshape(-1, 2).T.astype(np.float64))

        def cv():
            h = cv2.triangulatePoints(P_left, P_right, left, right)
            return (h[:3] / h[3]).T

        compile_s = compile_seconds(ours, rig, uv_j, conf_j)
        times = interleaved({"ours": lambda: ours(rig, uv_j, conf_j), "cv2": cv}, rounds=rounds)
        err_ours = np.linalg.norm(np.asarray(ours(rig, uv_j, conf_j)[0]).reshape(-1, 3) - points.reshape(-1, 3), axis=1)
        err_cv = np.linalg.norm(cv() - points.reshape(-1, 3), axis=1)
        pts = n * 21
        print(
            f"  {n:>7} {times['ours'] * 1e3:>10.3f} {times['cv2'] * 1e3:>10.3f} {pts / times['ours']:>12.3g} "
            f"{pts / times['cv2']:>12.3g} {times['cv2'] / times['ours']:>6.1f} {err_ours.mean() * 1e3:>12.3f} {err_cv.mean() * 1e3:>11.3f}"
            f"   (compile {compile_s:.2f} s)"
        )


def run_fisheye(rounds):
    print("\nFisheye624 (hot3d_quest3 left), points per second, float32")
    cam = cameras.rig_preset("hot3d_quest3").left
    for n in (1, 10_000, 1_000_000):
        rng = np.random.default_rng(0)
        uv = jnp.asarray(rng.uniform([100, 100], [1180, 924], size=(n, 2)), jnp.float32)
        points = cam.unproject(uv) * 0.4
        project = jax.jit(lambda c, p: c.project(p))
        unproject = jax.jit(lambda c, p: c.unproject(p))
        times = interleaved({"project": lambda: project(cam, points), "unproject": lambda: unproject(cam, uv)}, rounds=rounds)
        error = float(jnp.max(jnp.abs(project(cam, unproject(cam, uv)) - uv)))
        print(
            f"  n={n:>8}: project {n / times['project']:>10.3g}/s ({times['project'] * 1e3:.3f} ms), "
            f"unproject {n / times['unproject']:>10.3g}/s ({times['unproject'] * 1e3:.3f} ms); round trip max {error:.1e} px"
        )


def main():
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--frames", type=int, nargs="+", default=[1, 1000, 100_000])
    parser.add_argument("--rounds", type=int, default=5)
    args = parser.parse_args()
    print(f"{machine()}, OpenCV {cv2.__version__}")
    run_triangulation(args.frames, args.rounds)
    run_fisheye(args.rounds)


if __name__ == "__main__":
    main()
