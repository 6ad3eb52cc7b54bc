"""Training cost and a first learning check on this CPU.

    python benchmarks/train.py steps   [--configs cpu-tiny cpu-small paper] [--batch 8] [--dtypes float32 bfloat16]
    python benchmarks/train.py overfit [--config cpu-tiny] [--stage joint|image] [--steps 300] [--batch 2]
    python benchmarks/train.py learn --train DIR --val DIR --out RUN [--config cpu-small]
                                     [--stage1-steps 400] [--stage2-steps 1200] [--lr 5e-4] [--stage1-lr LR] [--frames-apart] [--seed S]
                                     [--set backbone=conv-small ...] [--features DIR]
    python benchmarks/train.py probe --model RUN/stage2/model --data DIR
    python benchmarks/train.py loader [--data DIR] [--clips 40] [--batch 8] [--steps 40]

`steps`: the jitted training step (corruption, forward, appendix-B losses, gradient,
AdamW update) per config, float32 and bfloat16 compute (`paper` on precomputed features
of its frozen backbone): compile time apart, then the median step time,
clips per second and the process's peak resident set (cumulative over the rows).
Batches are synthetic windows (a 16-frame synthetic clip with crops at the config's
size, both hands), the same for every step.

`overfit`: the first thing to prove before trusting a curve: one synthetic clip, one
window per hand, trained for `--steps` steps (`--stage joint` or `image`, warm-up 20
steps, peak learning rate 1e-3, augmentation and token masking off: it is a
memorisation test); the loss terms every 10 % of the run and the final P-MPJPE / wrist
error and the image encoder's 2D error (crop px) of the network on its own training
windows. This is the check that found the un-normalised read-out queries of the stereo
encoder (the 2D error stayed at 22 px of 112 on `cpu-small`, stage image).

`learn`: the learning curve of the training issue: stage 1 (image encoder) then stage 2
(joint, initialised from stage 1) on the clips of `--train`, validated on the held-out
clips of `--val` during training, then scored on every held-out window (both views,
and the right view dropped) next to the trivial baseline: the training set's mean
wrist-relative hand placed at the wrist triangulated from the clip's detected 2D
keypoints (detectors averaged; a frame without a triangulation keeps the last one);
its 2D error is that of the training set's mean keypoints in each view's crop, the
level a 2D head that does not read its crops stays at. The network is also scored on as
many of its own training windows (both views): the generalisation gap, which says
whether more clips (data) or more fitting (steps, size) is the lever.
The wrist with both views is broken down by rig-frame axis (mean absolute error, the
correlation and spread of the prediction against the truth's) and into its parts along
and across the line of sight from the rig origin (`metrics.wrist_axes`): this is what
showed that the network had learned the wrist's x and z but not its height y. Writes
`RUN/learning.json`; a finished stage is not trained again (rerun to rescore);
`--stage2-steps 0` scores stage 1 alone (its 2D error is the number to watch), `--set`
changes model config fields (the levers: backbone, dim, crop_size, ...).

`probe`: where a trained network keeps and where it loses the wrist position and the
hand's global orientation. On the windows of `--data` (16-frame windows, stride 16),
the network's forward pass gives, per frame, the image encoder's joint features F
(mean over the 21 joints, and the wrist's own token), its triangulated wrist, the motion encoder's features Z (mean
over joints) and root feature z_root, and the network's own output. A ridge regression
(standardised inputs) is fitted on the frames of the first half of the clips and scored
on the rest: per rig-frame axis of the wrist, the correlation with the truth and the mean
absolute error (mm); for the orientation, the median angle (degrees) between the truth
and the fitted rotation matrix projected onto SO(3). The triangulated wrist and the
output are scored as they are (no fit) and next to them the constant answer (the
fitted half's mean). This is what located the unlearned wrist height of study 07's full
`cpu-small` model (held-out clips): y is linearly decodable from the wrist's token of F
(correlation 0.93, 31 mm) and the encoder triangulates it (0.97, 18 mm), but the
network's wrist does not carry it (0.21, 70 mm); the global orientation is only weakly in
F (26 degrees against the constant's 36; the network's 31).

    python benchmarks/train.py probe --model RUN/stage2/model --data DIR [--ridge 0.01]

`loader`: the training loader (`train.load_batch`: the batch of a step, read on the
loop's worker thread while the previous step runs) on the same clips with their crops
files compressed (as written before crops files were stored uncompressed) and stored
(`clips.save_crops`, memory-mapped: a window reads its own frames), side by side in one
run: the median seconds per batch of `--batch` random windows over more clip-sides than
the loader's cache keeps, and the same for clips 8x as long (the crops tiled in time, as
a recorded clip's are long). The clips: `--data` (clip folders with crops and gt.npz) or
`--clips` synthetic clips of 64 frames with 112 px crops made in a temporary folder.
"""

import argparse
import os
import resource
import sys
import tempfile
import time

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

sys.path.insert(0, os.path.dirname(__file__))
from _timing import compile_seconds, machine, median_seconds  # noqa: E402

from esther_jax import mano, metrics  # noqa: E402
from esther_jax import model as M  # noqa: E402
from esther_jax import train  # noqa: E402
from esther_jax.data import motion, synth  # noqa: E402


def _clip_folder(crop_size: int, frames: int = 16) -> str:
    root = tempfile.mkdtemp(prefix="esther_bench_train_")
    cfg = synth.SynthConfig(num_frames=frames, crops=True, crop_size=crop_size, motion_config=motion.MotionConfig(two_hands_probability=1.0))
    return str(synth.write_clip(synth.make_clip(0, 0, cfg), os.path.join(root, "clip_00000")))


def _paper_batch(cfg, batch: int, frames: int):
    """A batch of the paper config on precomputed features (its backbone is frozen):
    random patch tokens of the backbone's width, the geometry of a synthetic clip."""
    folder = _clip_folder(64, frames)
    data_cfg = train.DataConfig(frames=frames, crop_size=64)
    clips_b, targets_b = train.load_batch(train.build_index([folder], data_cfg), data_cfg, batch, seed=0, step=0)
    patches, width = cfg.grid**2, cfg.backbone_spec.width
    features = jax.random.normal(jax.random.key(0), (batch, frames, 2, patches, width), jnp.float32)
    scale = cfg.crop_size / 64.0  # the crop intrinsics of a 64 px crop, scaled to the paper's crop size
    K = clips_b.K * jnp.asarray([scale, scale, 1.0])[:, None]
    clips_b = M.ClipInput(images=None, features=features, K=K, R_cam_crop=clips_b.R_cam_crop, T_rig_cams=clips_b.T_rig_cams,
                          flow=clips_b.flow, view_present=clips_b.view_present)  # fmt: skip
    return clips_b, targets_b


def bench_steps(configs: list[str], batch: int, dtypes: list[str]) -> None:
    print(f"training step, batch {batch}, 16-frame windows (median of rounds; compile apart)")
    print("the paper config runs on precomputed backbone features (its DINOv3 backbone is frozen)")
    print(f"{'config':<10} {'compute':>9} {'compile s':>10} {'step s':>9} {'clips/s':>8} {'peak RSS MiB':>13}")
    hand = mano.load_builtin("right")
    for name in configs:
        cfg = M.config(name)
        if cfg.freeze_backbone:
            cfg = cfg.replace(precomputed_features=True)
            clips_b, targets_b = _paper_batch(cfg, batch, cfg.num_frames)
        else:
            folder = _clip_folder(cfg.crop_size, cfg.num_frames)
            data_cfg = train.DataConfig(frames=cfg.num_frames, crop_size=cfg.crop_size)
            windows = train.build_index([folder], data_cfg)
            clips_b, targets_b = train.load_batch(windows, data_cfg, batch, seed=0, step=0)
        for dtype in dtypes:
            trainer = train.Trainer(M.ESTHER(cfg, key=jax.random.key(0)), train.TrainConfig(batch=batch, compute_dtype=dtype), hand)
            state = trainer.init()
            step = lambda s: trainer.step(s, clips_b, targets_b)  # noqa: E731
            compiled = compile_seconds(step, state)
            seconds = median_seconds(step, state, rounds=3, min_time=0.5)
            rss = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024
            print(f"{name:<10} {dtype:>9} {compiled:10.1f} {seconds:9.3f} {batch / seconds:8.1f} {rss:13.0f}", flush=True)


def overfit(name: str, stage: str, steps: int, batch: int) -> None:
    cfg = M.config(name, image_augmentation=False, motion_masking=False)
    folder = _clip_folder(cfg.crop_size, cfg.num_frames)
    data_cfg = train.DataConfig(frames=cfg.num_frames, crop_size=cfg.crop_size)
    windows = train.build_index([folder], data_cfg)
    hand = mano.load_builtin("right")
    tcfg = train.TrainConfig(stage=stage, steps=steps, batch=batch, warmup_steps=20, learning_rate=1e-3)
    trainer = train.Trainer(M.ESTHER(cfg, key=jax.random.key(0)), tcfg, hand)
    state = trainer.init()
    print(f"overfitting {len(windows)} windows of one clip ({name}, stage {stage}, batch {batch}, {steps} steps, lr 1e-3)")
    shown = ("loss", "loss/heatmap", "loss/two_d", "loss/triangulation", "loss/depth")
    if stage == "joint":
        shown += ("loss/joints", "loss/canonical", "loss/transl", "loss/onscreen")
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
    for side in dict.fromkeys(w.side for w in windows):
        own = [w for w in windows if w.side == side]
        scores = train.evaluate_windows(net, own, data_cfg, hand_model=hand, batch=len(own))
        print(f"{side:>5} hand on its {len(own)} training windows: P-MPJPE {scores['p_mpjpe_mm']:6.1f} mm, wrist {scores['wrist_mm']:6.1f} mm, "
              f"2D {scores['keypoints_2d_px']:5.1f} px of {cfg.crop_size}")


def _baseline(train_windows, val_windows, data_cfg) -> dict:
    """The trivial baseline's P-MPJPE / PA-MPJPE / wrist (mm) on the held-out windows, and
    the 2D error (crop pixels, as the network's is scored: each window's mean over its
    in-frame joints of present views in valid frames, then the windows' mean) of the
    training set's mean keypoints in each view's crop, which a 2D head must beat to show
    that it reads the crops."""
    from esther_jax import clips as clip_format
    from esther_jax.cameras import StereoRig
    from esther_jax.model import crop_projections
    from esther_jax.triangulation import triangulate_rig

    def crop_keypoints(clip, t):
        uv, _, inside = crop_projections(clip, t.joints, data_cfg.crop_size)
        seen = np.asarray(inside & clip.view_present[..., None] & t.valid[:, None, None])
        return np.asarray(uv), seen  # (T, 2, 21, 2), (T, 2, 21)

    canonical, wrists_seen, uv_sum, uv_count = [], [], 0.0, 0
    for w in train_windows:
        clip, t = train.load_example(w, data_cfg)
        ok = np.asarray(t.valid)
        canonical.append(np.asarray(t.joints - t.joints[:, :1])[ok])
        wrists_seen.append(np.asarray(t.joints[:, 0])[ok])
        uv, seen = crop_keypoints(clip, t)
        uv_sum, uv_count = uv_sum + (uv * seen[..., None]).sum(0), uv_count + seen.sum(0)
    mean_hand = np.concatenate(canonical).mean(axis=0)  # (21, 3), right-hand frame
    mean_uv = uv_sum / np.maximum(uv_count, 1)[..., None]  # (2, 21, 2): each view's mean crop keypoints
    mean_wrist = np.concatenate(wrists_seen).mean(axis=0)  # for a window without any triangulated wrist
    p, pa, wrist, two_d = [], [], [], []
    for w in val_windows:
        clip, t = train.load_example(w, data_cfg)
        uv, seen = crop_keypoints(clip, t)
        if seen.any():
            two_d.append(np.linalg.norm(mean_uv - uv, axis=-1)[seen].mean())
        rig = StereoRig.from_json(f"{w.clip}/rig.json")
        kp = clip_format.load_npz(clip_format.hand_file(w.clip, w.side, "keypoints"), "keypoints")
        sl = slice(w.start, w.start + data_cfg.frames)
        uv, conf = jnp.asarray(kp["uv"][:, sl, :, 0], jnp.float32), jnp.asarray(kp["conf"][:, sl, :, 0], jnp.float32)
        tri = triangulate_rig(rig, uv, conf)  # (D, T): the wrist, per detector
        ok = np.asarray(tri.valid)
        pts = np.where(ok[..., None], np.asarray(tri.point), 0.0).sum(0) / np.maximum(ok.sum(0), 1)[:, None]
        have = ok.any(0)
        wrists = jnp.asarray(pts, jnp.float32)
        if w.side == "left":  # into the mirrored frame of the targets (train.mirror_targets)
            T1_inv = jnp.linalg.inv(jnp.asarray(rig.T_rig_cams[1], jnp.float32))
            wrists = mano.mirror_points(wrists @ T1_inv[:3, :3].T + T1_inv[:3, 3])
        held, last = [], (np.asarray(wrists)[np.argmax(have)] if have.any() else mean_wrist)
        for i in range(len(have)):  # a frame without a triangulation keeps the last one
            last = np.asarray(wrists[i]) if have[i] else last
            held.append(last)
        wrists = jnp.asarray(np.stack(held), jnp.float32)
        pred = jnp.asarray(mean_hand)[None] + wrists[:, None]
        valid = np.asarray(t.valid)
        if not valid.any():
            continue
        p.append(np.asarray(jax.vmap(metrics.p_mpjpe)(pred, t.joints))[valid].mean())
        pa.append(np.asarray(jax.vmap(metrics.pa_mpjpe)(pred, t.joints))[valid].mean())
        wrist.append(np.asarray(jax.vmap(metrics.wrist_error)(pred, t.joints))[valid].mean())
    return {"p_mpjpe_mm": 1000 * float(np.mean(p)), "pa_mpjpe_mm": 1000 * float(np.mean(pa)), "wrist_mm": 1000 * float(np.mean(wrist)),
            "keypoints_2d_px": float(np.mean(two_d)), "windows": len(p)}  # fmt: skip


def learn(args) -> None:
    import dataclasses
    import json
    import pathlib

    from esther_jax.clips import list_clips
    from esther_jax.files import write_json
    from esther_jax.train.validation import evaluate_windows, predict_windows, score_predictions

    def parse(field: str, text: str):
        kind = type(getattr(M.config(args.config), field))
        return text.lower() in ("1", "true", "yes") if kind is bool else kind(text)

    overrides = {k: parse(k, v) for k, v in (item.split("=", 1) for item in args.set)}
    cfg = M.config(args.config, **overrides)
    train_dirs, val_dirs = list_clips(args.train), list_clips(args.val)
    data_cfg = train.DataConfig(frames=cfg.num_frames, crop_size=cfg.crop_size)
    out = pathlib.Path(args.out)
    t0 = time.perf_counter()
    final = train.train_stages(out, train_dirs, cfg, stage1_steps=args.stage1_steps, stage2_steps=args.stage2_steps, batch=args.batch,
                               learning_rate=args.lr, stage1_learning_rate=args.stage1_lr, stage1_frames_apart=args.frames_apart,
                               val_dirs=val_dirs, validate_every=args.validate_every, seed=args.seed, features=args.features)  # fmt: skip
    timings = {"both stages (or what was left of them)": time.perf_counter() - t0}
    last = final.parent
    net = M.load(final)
    val_cfg = dataclasses.replace(data_cfg, stride=data_cfg.frames)
    val_windows = train.build_index(val_dirs, val_cfg)
    result = {"config": cfg.name, "overrides": overrides, "evaluated": last.name, "train_clips": len(train_dirs), "val_clips": len(val_dirs),
              "seconds": timings, "stage1_steps": args.stage1_steps, "stage2_steps": args.stage2_steps, "batch": args.batch, "lr": args.lr,
              "stage1_lr": args.lr if args.stage1_lr is None else args.stage1_lr, "frames_apart": args.frames_apart, "seed": args.seed,
              "features": args.features}  # fmt: skip
    seen = predict_windows(net, val_windows, val_cfg, batch=args.batch)  # both views: predicted once, scored and broken down
    result["both"] = score_predictions(seen.joints, seen.emitted, val_windows, val_cfg, keypoints_2d=seen.keypoints_2d, batch=args.batch)
    result["right dropped"] = evaluate_windows(net, val_windows, val_cfg, batch=args.batch, view_dropped=1)
    result["wrist_axes"] = {k: np.asarray(v).tolist() for k, v in dataclasses.asdict(seen.wrist_axes()).items()}
    result["baseline"] = _baseline(train.build_index(train_dirs, data_cfg), val_windows, val_cfg)
    seen_windows = train.build_index(train_dirs, val_cfg)  # as many training windows, spread over the clips: the generalisation gap
    seen_windows = [seen_windows[i] for i in np.linspace(0, len(seen_windows) - 1, len(val_windows)).round().astype(int)]
    result["training windows, both"] = evaluate_windows(net, seen_windows, val_cfg, batch=args.batch)
    write_json(out / "learning.json", result)
    print(json.dumps(result, indent=1))
    print(f"{'':<22} {'P-MPJPE':>8} {'PA-MPJPE':>9} {'wrist':>7} {'2D px':>6} {'jitter':>7} {'gt jitter':>9} {'F1':>5}  (mm, m/s^2)")
    trained = f"  ({result['training windows, both']['windows']} training windows, both views)"
    rows = (("ESTHER both", "both", ""), ("ESTHER right dropped", "right dropped", ""), ("ESTHER on its training", "training windows, both", trained))
    for label, key, note in rows:
        r = result[key]
        print(f"{label:<22} {r['p_mpjpe_mm']:8.1f} {r['pa_mpjpe_mm']:9.1f} {r['wrist_mm']:7.1f} {r['keypoints_2d_px']:6.1f} "
              f"{r['jitter']:7.2f} {r['gt_jitter']:9.2f} {r['onscreen_f1']:5.2f}{note}")  # fmt: skip
    b = result["baseline"]
    print(f"{'trivial baseline':<22} {b['p_mpjpe_mm']:8.1f} {b['pa_mpjpe_mm']:9.1f} {b['wrist_mm']:7.1f} {b['keypoints_2d_px']:6.1f}")
    w = result["wrist_axes"]
    print("wrist, both views:  " + "   ".join(f"{a}: {w['mae_mm'][i]:.1f} mm, corr {w['correlation'][i]:.2f}, spread "
                                           f"{w['pred_sd_mm'][i]:.0f} / {w['true_sd_mm'][i]:.0f} mm" for i, a in enumerate("xyz"))
          + f"   along the line of sight {w['along_mm']:.1f} mm, across {w['across_mm']:.1f} mm")  # fmt: skip


def _ridge(x_fit: np.ndarray, y_fit: np.ndarray, x_test: np.ndarray, strength: float) -> np.ndarray:
    """Ridge regression of y on standardised x (with an intercept), fitted on the first
    set and evaluated on the second; `strength` is the penalty per fitted sample."""
    mean, sd = x_fit.mean(0), x_fit.std(0) + 1e-9
    design = lambda x: np.c_[(x - mean) / sd, np.ones(len(x))]  # noqa: E731
    a = design(x_fit)
    penalty = strength * len(a) * np.eye(a.shape[1])
    penalty[-1, -1] = 0.0  # the intercept is not shrunk
    return design(x_test) @ np.linalg.solve(a.T @ a + penalty, a.T @ y_fit)


def _nearest_rotation(m: np.ndarray) -> np.ndarray:
    """The rotations nearest (Frobenius) to the 3 x 3 matrices `m (..., 3, 3)`: SVD with
    the determinant's sign folded into the last singular vector."""
    u, _, vt = np.linalg.svd(m)
    vt[..., -1, :] *= np.sign(np.linalg.det(u @ vt))[..., None]
    return u @ vt


def probe(model: str, data: str, strength: float) -> None:
    from esther_jax.clips import list_clips
    from esther_jax.rotations import axis_angle_to_matrix, geodesic_angle

    net = M.load(model)
    cfg = net.config
    data_cfg = train.DataConfig(frames=cfg.num_frames, crop_size=cfg.crop_size, stride=cfg.num_frames)
    clips = list_clips(data)
    if len(clips) < 4:
        raise SystemExit(f"probe: {data} holds {len(clips)} clip folders; fitting on half and scoring on the rest needs at least 4")
    windows = train.build_index(clips, data_cfg)
    hand = mano.load_builtin("right")

    @eqx.filter_jit
    def stages(net, clip):
        out = jax.vmap(lambda c: net(c, hand))(clip)
        return {
            "F (image encoder)": out.image.features.mean(axis=2),
            "F, the wrist's token": out.image.features[:, :, 0],
            "Z (motion encoder)": out.motion.features.mean(axis=2),
            "z_root (motion encoder)": out.motion.root,
            "triangulated wrist": jnp.where(out.image.triangulation_valid[:, :, :1], out.image.triangulated[:, :, 0], jnp.nan),
            "output": out.joints[:, :, 0],
            "output orientation": axis_angle_to_matrix(out.params.global_orient),
        }

    rows, wrist, orient, fit = [], [], [], []
    half = {str(c) for c in clips[: len(clips) // 2]}
    for start in range(0, len(windows), 8):
        chunk = windows[start : start + 8]
        n = len(chunk)
        examples = [train.load_example(w, data_cfg) for w in chunk + chunk[-1:] * (8 - n)]  # padded: one compilation
        clip_b, targets_b = jax.tree.map(lambda *x: np.stack(x), *examples)
        valid = targets_b.valid[:n]
        got = jax.device_get(stages(net, clip_b))
        rows.append({k: v[:n][valid] for k, v in got.items()})
        wrist.append(targets_b.joints[:n, :, 0][valid])
        orient.append(np.asarray(axis_angle_to_matrix(targets_b.global_orient[:n][valid])))
        fit.append(np.repeat([w.clip in half for w in chunk], valid.sum(1)))
    got = {k: np.concatenate([r[k] for r in rows]) for k in rows[0]}
    wrist, orient, fit = np.concatenate(wrist), np.concatenate(orient), np.concatenate(fit)
    test = ~fit

    def wrist_scores(pred):
        seen = ~np.isnan(pred[:, 0])  # the triangulated wrist: frames where the encoder triangulates it
        pred, truth = pred[seen], wrist[test][seen]
        corr = [np.nan if np.allclose(pred[:, i], pred[0, i]) else np.corrcoef(pred[:, i], truth[:, i])[0, 1] for i in range(3)]
        return corr, 1000 * np.abs(pred - truth).mean(0), seen.mean()

    def angle(pred):
        return float(np.degrees(np.median(np.asarray(geodesic_angle(jnp.asarray(pred), jnp.asarray(orient[test]))))))

    print(f"{model} on {len(windows)} windows of {data}: fitted on {fit.sum()} frames ({len(half)} clips), scored on {test.sum()}")
    print(f"{'':<32} {'wrist corr x / y / z':>22} {'wrist MAE mm x / y / z':>24} {'orientation deg':>16}")
    constant = (np.broadcast_to(wrist[fit].mean(0), wrist[test].shape), _nearest_rotation(np.broadcast_to(orient[fit].mean(0), orient[test].shape)))
    table = {"constant (fitted mean)": constant}
    for name in ("F (image encoder)", "F, the wrist's token", "Z (motion encoder)", "z_root (motion encoder)"):
        x = got[name]
        table[name + ", linear"] = (_ridge(x[fit], wrist[fit], x[test], strength),
                                    _nearest_rotation(_ridge(x[fit], orient[fit].reshape(-1, 9), x[test], strength).reshape(-1, 3, 3)))  # fmt: skip
    table["triangulated wrist"] = (got["triangulated wrist"][test], None)
    table["network output"] = (got["output"][test], got["output orientation"][test])
    for name, (w, r) in table.items():
        corr, mae, share = wrist_scores(w)
        deg = f"{angle(r):16.1f}" if r is not None else f"{'':>16} (on the {100 * share:.0f} % of frames it triangulates)"
        print(f"{name:<32} {' / '.join('    -' if np.isnan(c) else f'{c:5.2f}' for c in corr):>22} {' / '.join(f'{e:6.1f}' for e in mae):>24} {deg}")


def _crops_copies(clip_dirs: list, root: str, tile: int) -> dict[str, list]:
    """Copies of the clips whose crops files are compressed or stored (the rest linked),
    their crops and targets tiled `tile` times in time."""
    import json
    import pathlib

    from esther_jax import clips as clip_format

    out = {"compressed": [], "stored": []}
    for clip in map(pathlib.Path, clip_dirs):
        meta = clip_format.read_meta(clip)
        for kind, save in (("compressed", clip_format.save_npz), ("stored", clip_format.save_crops)):
            copy = pathlib.Path(root) / f"{kind}_x{tile}" / clip.name
            (copy / "hands").mkdir(parents=True, exist_ok=True)
            os.symlink(clip / "rig.json", copy / "rig.json")
            (copy / "meta.json").write_text(json.dumps({**meta, "num_frames": meta["num_frames"] * tile}))
            for side in clip_format.SIDES:
                if not clip_format.crops_file(clip, side).is_file():
                    continue
                crops = clip_format.load_crops(clip_format.crops_file(clip, side))
                save(clip_format.crops_file(copy, side), **{k: np.concatenate([v] * tile) for k, v in crops.items()})
                gt = clip_format.load_npz(clip_format.hand_file(clip, side, "gt"), "gt")
                clip_format.save_npz(clip_format.hand_file(copy, side, "gt"), **{k: v if k == "betas" else np.concatenate([v] * tile) for k, v in gt.items()})
            out[kind].append(str(copy))
    return out


def bench_loader(data: str | None, num_clips: int, batch: int, steps: int) -> None:
    from esther_jax import clips as clip_format

    root = tempfile.mkdtemp(prefix="esther_bench_loader_")
    if data is None:
        print(f"making {num_clips} synthetic clips of 64 frames with 112 px crops ...", flush=True)
        cfg = synth.SynthConfig(num_frames=64, crops=True, crop_size=112, motion_config=motion.MotionConfig(two_hands_probability=1.0))
        synth.synthesize(os.path.join(root, "clips"), num_clips, cfg, seed=0, progress=False)
        data = os.path.join(root, "clips")
    clip_dirs = clip_format.list_clips(data)[:num_clips]
    data_cfg = train.DataConfig(frames=16, stride=8, crop_size=112)
    print(f"{len(clip_dirs)} clips; batches of {batch} random 16-frame windows, {steps} steps after 2 of warm-up (median s / batch)")
    print(f"{'clip length':<12} {'crops file':<11} {'windows':>8} {'s / batch':>10} {'windows/s':>10}")
    for tile in (1, 8):
        copies = _crops_copies(clip_dirs, root, tile)
        for kind, dirs in copies.items():
            windows = train.build_index(dirs, data_cfg)
            for path in (p for d in dirs for p in (clip_format.crops_file(d, "left"), clip_format.crops_file(d, "right")) if p.is_file()):
                path.read_bytes()  # both kinds from the page cache, as in a long run
            for step in range(2):
                train.load_batch(windows, data_cfg, batch, seed=1, step=step)
            times = []
            for step in range(2, 2 + steps):
                t0 = time.perf_counter()
                train.load_batch(windows, data_cfg, batch, seed=1, step=step)
                times.append(time.perf_counter() - t0)
            sec = float(np.median(times))
            print(f"{64 * tile:<12} {kind:<11} {len(windows):>8} {sec:>10.3f} {batch / sec:>10.1f}", flush=True)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    sub = parser.add_subparsers(dest="what", required=True)
    s = sub.add_parser("steps")
    s.add_argument("--configs", nargs="+", default=["cpu-tiny", "cpu-small", "paper"])
    s.add_argument("--batch", type=int, default=8)
    s.add_argument("--dtypes", nargs="+", default=["float32", "bfloat16"])
    o = sub.add_parser("overfit")
    o.add_argument("--config", default="cpu-tiny")
    o.add_argument("--stage", choices=train.STAGES, default="joint")
    o.add_argument("--steps", type=int, default=300)
    o.add_argument("--batch", type=int, default=2)
    lp = sub.add_parser("learn")
    lp.add_argument("--train", required=True, help="folder of training clips (esther synth --crops --crop-size 112)")
    lp.add_argument("--val", required=True, help="folder of held-out clips (another --seed)")
    lp.add_argument("--out", required=True)
    lp.add_argument("--config", default="cpu-small")
    lp.add_argument("--stage1-steps", type=int, default=400)
    lp.add_argument("--stage2-steps", type=int, default=1200)
    lp.add_argument("--batch", type=int, default=8)
    lp.add_argument("--lr", type=float, default=5e-4, help="peak learning rate (of both stages unless --stage1-lr)")
    lp.add_argument("--stage1-lr", type=float, help="stage 1's peak learning rate (default: --lr)")
    lp.add_argument("--frames-apart", action="store_true", help="stage 1 draws each example's frames apart (TrainConfig.frames_apart)")
    lp.add_argument("--validate-every", type=int, default=400)
    lp.add_argument("--seed", type=int, default=0, help="seed of both stages' batches, masking and augmentation (a finished stage kept in --out keeps its own)")
    lp.add_argument("--features", metavar="DIR", help="a feature cache of the frozen backbone (e.g. --config cpu-small-hand): filled once, read by both stages")
    lp.add_argument("--set", nargs="*", default=[], metavar="FIELD=VALUE", help="model config overrides, e.g. backbone=conv-small")
    pp = sub.add_parser("probe")
    pp.add_argument("--model", required=True, help="a saved network (a run's model folder)")
    pp.add_argument("--data", required=True, help="folder of clips with ground truth (held-out clips)")
    pp.add_argument("--ridge", type=float, default=0.01, help="ridge penalty per fitted frame (inputs standardised)")
    ld = sub.add_parser("loader")
    ld.add_argument("--data", help="clip folders with crops and gt.npz (default: synthetic clips made here)")
    ld.add_argument("--clips", type=int, default=40)
    ld.add_argument("--batch", type=int, default=8)
    ld.add_argument("--steps", type=int, default=40)
    args = parser.parse_args()
    from esther_jax import enable_compilation_cache

    enable_compilation_cache()
    print(machine(), flush=True)
    if args.what == "steps":
        bench_steps(args.configs, args.batch, args.dtypes)
    elif args.what == "overfit":
        overfit(args.config, args.stage, args.steps, args.batch)
    elif args.what == "probe":
        probe(args.model, args.data, args.ridge)
    elif args.what == "loader":
        bench_loader(args.data, args.clips, args.batch, args.steps)
    else:
        learn(args)


if __name__ == "__main__":
    main()
