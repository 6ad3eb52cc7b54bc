"""`esther demo`: the main job on the embedded default (no dataset, no licensed model).

1. Make a synthetic clip on the paper's rig (1920x1200 pinhole pair, 62 mm) with both
   hands, 128 frames, and the default (realistic) detector noise.
2. Label it with the teacher (fusion, prefilter, shape lock, per-frame fits, motion stage).
3. Evaluate the labels against the exact ground truth (P-MPJPE, PA-MPJPE, wrist, jitter
   with bootstrap intervals) and print the label-quality table (appendix N).
4. Draw the fitted meshes over both rendered views for a few frames (PNG), and export
   one fitted mesh.
"""

import json
import pathlib
import time

import jax.numpy as jnp
import numpy as np

from . import clips, mano
from .data import motion, render, synth
from .eval import evaluate_folders


def run(out_dir: str | pathlib.Path = "esther_demo", *, seed: int = 0, frames: int = 128) -> dict[str, pathlib.Path]:
    from fitting import label_clips
    from fitting.review import contact_sheet, overlay_mesh

    t_start = time.perf_counter()
    out = pathlib.Path(out_dir)
    clips_dir, labels_dir, eval_dir = out / "clips", out / "labels", out / "evaluation"
    cfg = synth.SynthConfig(num_frames=frames, motion_config=motion.MotionConfig(two_hands_probability=1.0))
    print(f"1/4 synthetic clip: rig 'esther', {frames} frames, both hands, detector preset '{cfg.detector_preset}'")
    clip = synth.make_clip(seed, 0, cfg)
    clip_path = synth.write_clip(clip, clips_dir / "clip_00000")

    print("2/4 labelling with the teacher (the first run compiles its solvers; later runs reuse the cache)")
    t0 = time.perf_counter()
    result = label_clips([clip_path], labels_dir, progress=False)
    if result["failed"]:
        raise RuntimeError(f"labelling failed: {result['failed']}")
    label_seconds = time.perf_counter() - t0

    print("3/4 evaluating the labels against the ground truth")
    metrics = evaluate_folders(labels_dir, clips_dir, eval_dir, method="teacher", seed=seed)
    print()
    print((eval_dir / "table.md").read_text())
    for side, hand in result["labelled"][0]["hands"].items():
        quality = json.loads((labels_dir / "clip_00000" / "hands" / side / "quality.json").read_text())
        print(f"{side} hand: {hand['valid']}/{hand['frames']} frames valid, {hand['seconds']:.2f} s "
              f"(the first hand of a cold run includes compilation), pass rate {quality['share_passing']:.1%}")
        for group in ("stereo", "monocular"):
            if not quality[group]["passing"]:
                continue
            print(f"  {group} frames ({quality[group]['passing']} passing):")
            for name, row in quality[group]["table"].items():
                if row:
                    print(f"    {name:<40} median {row['median']:7.2f}  mean {row['mean']:7.2f}  p90 {row['p90']:7.2f}")
    gt_jitter = metrics["metrics"]["gt_jitter"]["value"]
    print(f"ground truth's own jitter: {gt_jitter:.2f} m/s^2; labelling took {label_seconds:.1f} s including compilation")

    print("4/4 drawing the fitted meshes over both views")
    figure = _overlays(clip, labels_dir / "clip_00000", out / "overlays.png", seed, contact_sheet, overlay_mesh)
    right_labels = clips.Labels.from_npz(clips.hand_file(labels_dir / "clip_00000", "right", "labels"))
    model = mano.load_builtin("right")
    t = int(np.flatnonzero(right_labels.valid)[0]) if right_labels.valid.any() else 0
    mesh = mano.export_mesh(model, mano.forward(model, right_labels.frame(t)), out / "right_hand_fitted.glb")
    paths = {
        "clip": clip_path,
        "labels": labels_dir,
        "metrics": eval_dir / "metrics.json",
        "table": eval_dir / "table.md",
        "depth_scatter": eval_dir / "depth_scatter.png",
        "overlays": figure,
        "mesh": mesh,
    }
    print(f"\ndone in {time.perf_counter() - t_start:.0f} s. Outputs:")
    for name, path in paths.items():
        print(f"  {name:<14} {path.resolve()}")
    return paths


def _overlays(clip, labels_path, path, seed, contact_sheet, overlay_mesh, num: int = 3) -> pathlib.Path:
    """Render a few frames of both views and blend the fitted meshes over them."""
    rig = clip.rig
    scene = render.sample_scene(np.random.default_rng([seed, 99]))
    T_world_rig = np.asarray(clip.meta["T_world_rig"])
    labels = {side: clips.Labels.from_npz(clips.hand_file(labels_path, side, "labels")) for side in clip.gt}
    T = len(T_world_rig)
    frames = np.linspace(T // 8, T - 1 - T // 8, num).astype(int)
    colours = {"right": (236, 112, 150), "left": (90, 150, 240)}  # pink right, blue left (the paper's figures)
    tiles, captions = [], []
    for t in frames:
        meshes_gt, fitted = [], []
        for side, lab in labels.items():
            model = mano.load_builtin(side)
            gt = clip.gt[side]
            gt_params = mano.ManoParams(*(jnp.asarray(gt[k][t]) for k in ("global_orient", "hand_pose")), jnp.asarray(gt["betas"]), jnp.asarray(gt["transl"][t]))
            meshes_gt.append((np.asarray(mano.forward(model, gt_params).vertices, np.float64), np.asarray(model.faces)))
            fitted.append((side, np.asarray(mano.forward(model, lab.frame(t)).vertices, np.float64), np.asarray(model.faces), bool(lab.valid[t])))
        dtype = jnp.result_type(float)
        gt_views = [(np.asarray(rig.to_views(jnp.asarray(m, dtype)), np.float64), f) for m, f in meshes_gt]  # (2, V, 3) each
        fit_uv = [np.asarray(rig.project(jnp.asarray(verts, dtype)), np.float64) for _, verts, _, _ in fitted]  # (2, V, 2)
        fit_depth = [np.asarray(rig.depths(jnp.asarray(verts, dtype)), np.float64) for _, verts, _, _ in fitted]  # (2, V)
        row = []
        for v, (camera, T_rig_cam) in enumerate(zip((rig.left, rig.right), np.asarray(rig.T_rig_cams, np.float64))):
            in_cam = [render.Mesh(m[v], f, scene.skin, "skin", render.hand_rest_vertices()) for m, f in gt_views]
            image, _ = render.render_view(scene, camera, T_world_rig[t] @ T_rig_cam, in_cam)
            for (side, _, faces, ok), uv, depth in zip(fitted, fit_uv, fit_depth):
                if ok:
                    image = overlay_mesh(image, uv[v], depth[v], faces, colours[side], alpha=0.55)
            row.append(image)
        tiles.append(row)
        captions.append(f"frame {t}: fitted labels (pink right, blue left) over the rendered left / right views")
    return contact_sheet(tiles, captions, path)
