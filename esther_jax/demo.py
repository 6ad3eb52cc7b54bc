"""`esther demo`: the main job on the embedded default (no dataset, no licensed model).

Until the teacher pipeline lands, the demo poses the built-in open hand (both sides)
through a few natural poses drawn from its PCA pose space, prints the forward
kinematics (21 keypoints of the right hand, metres) and the timing of the jitted
kernels, exports the meshes (.obj, .ply, .glb) and renders them to a PNG.
"""

import pathlib
import time

import jax
import jax.numpy as jnp
import numpy as np

from . import mano
from .viz import plot_hand_meshes


def run(out_dir: str | pathlib.Path = "esther_demo", *, seed: int = 0) -> dict[str, pathlib.Path]:
    out = pathlib.Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    t0 = time.perf_counter()
    right, left = mano.load_builtin("right"), mano.load_builtin("left")
    print(f"built-in open hand: {right.num_vertices} vertices, {right.faces.shape[0]} faces, "
          f"{right.num_betas} shape directions, 45-D PCA pose space")

    rng = np.random.default_rng(seed)
    poses = {"flat": jnp.zeros((15, 3))}
    for name, coefficients in (("mean pose", np.zeros(6)), ("natural sample", rng.normal(size=6))):
        poses[name] = mano.pca_to_hand_pose(right, jnp.asarray(coefficients, jnp.float32), flat_hand_mean=False)
    betas = jnp.asarray(rng.normal(size=10), jnp.float32)

    forward = jax.jit(mano.forward)
    panels, paths = [], {}
    for name, hand_pose in poses.items():
        params = mano.ManoParams(jnp.zeros(3), hand_pose, betas, jnp.asarray([0.0, 0.0, 0.4]))
        out_right = forward(right, params)
        out_left = forward(left, mano.mirror_params(params))
        panels.append((f"right: {name}", np.asarray(out_right.vertices), np.asarray(right.faces)))
        panels.append((f"left: {name}", np.asarray(out_left.vertices), np.asarray(left.faces)))
        stem = name.replace(" ", "_")
        for suffix in ("obj", "ply", "glb"):
            paths[f"right_{stem}.{suffix}"] = mano.export_mesh(right, out_right, out / f"right_{stem}.{suffix}")
    sample = mano.ManoParams(jnp.zeros(3), poses["natural sample"], betas, jnp.asarray([0.0, 0.0, 0.4]))
    keypoints = np.asarray(forward(right, sample).joints)
    print("\nright hand, natural sample, wrist at (0, 0, 0.4) m: 21 keypoints (m)")
    for name, xyz in zip(mano.KEYPOINT_NAMES, keypoints):
        print(f"  {name:<11} {xyz[0]:+.4f} {xyz[1]:+.4f} {xyz[2]:+.4f}")

    joints_only = jax.jit(jax.vmap(mano.forward_joints, in_axes=(None, 0)))
    batch = jax.tree.map(lambda x: jnp.broadcast_to(x, (1024,) + x.shape), sample)
    jax.block_until_ready(joints_only(right, batch))
    t1 = time.perf_counter()
    jax.block_until_ready(joints_only(right, batch))
    rate = 1024 / (time.perf_counter() - t1)
    print(f"\njoints-only FK: {rate:,.0f} hands/s at batch 1024 (after compilation)")
    paths["figure"] = plot_hand_meshes(panels, out / "hands.png")
    print(f"\nwrote {len(paths)} files to {out.resolve()} (figure: {paths['figure'].name}) "
          f"in {time.perf_counter() - t0:.1f} s")
    return paths
