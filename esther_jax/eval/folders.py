"""`esther evaluate`: compare label folders with ground-truth clip folders.

Ground truth: clip folders (`<gt>/<clip>/hands/<side>/gt.npz`, `meta.json` for fps).
Predictions: `<pred>/<clip>/hands/<side>/labels.npz` (the teacher's output format; a
file without `valid` counts every frame as emitted). Per the paper's protocol
(appendix L), a frame is scored when the hand is on-screen in the ground truth and the
prediction emitted it; jitter is gated the same way. Per-frame errors -> per-clip means
-> clip-weighted dataset means with bootstrap intervals over clips (appendix J).
"""

import json
import pathlib

import jax
import jax.numpy as jnp
import numpy as np

from .. import metrics
from ..data import clip_io
from . import reports

_FRAME_METRICS = {
    "mpjpe": metrics.mpjpe,
    "p_mpjpe": metrics.p_mpjpe,
    "pa_mpjpe": metrics.pa_mpjpe,
    "wrist": lambda p, g: metrics.wrist_error(p, g),
}


@jax.jit
def _frame_errors(pred, gt):
    out = {name: jax.vmap(fn)(pred, gt) for name, fn in _FRAME_METRICS.items()}
    out["joint_errors_p"] = jax.vmap(lambda p, g: metrics.joint_errors(p - p[0:1], g - g[0:1]))(pred, gt)
    return out


def evaluate_hand(pred: dict, gt: dict, fps: float) -> dict:
    """Per-clip scores of one hand (metres, m/s^2) and the frames they used."""
    T = gt["joints"].shape[0]
    if pred["joints"].shape != gt["joints"].shape:
        raise clip_io.ClipFormatError(f"prediction has {pred['joints'].shape[0]} frames, ground truth {T}")
    emitted = pred.get("valid", np.ones(T, bool))
    frames = gt["onscreen"] & emitted
    errors = _frame_errors(jnp.asarray(pred["joints"]), jnp.asarray(gt["joints"]))
    scores = {name: metrics.clip_mean(errors[name], jnp.asarray(frames)) for name in _FRAME_METRICS}
    scores["jitter"] = metrics.jitter(jnp.asarray(pred["joints"]), jnp.asarray(frames), fps)
    scores["gt_jitter"] = metrics.jitter(jnp.asarray(gt["joints"]), jnp.asarray(gt["onscreen"]), fps)
    return {
        "scores": {k: (float(v.value), int(v.count)) for k, v in scores.items()},
        "frames": frames,
        "coverage": (int(frames.sum()), int(gt["onscreen"].sum())),
        "joint_errors_p": np.asarray(errors["joint_errors_p"])[frames],
        "wrist_z": (np.asarray(pred["joints"])[frames, 0, 2], gt["joints"][frames, 0, 2]),
    }


def evaluate_folders(
    pred_root: str | pathlib.Path,
    gt_root: str | pathlib.Path,
    out_dir: str | pathlib.Path,
    *,
    method: str = "prediction",
    condition: str = "clean",
    seed: int = 0,
    num_resamples: int = 2000,
) -> dict:
    """Evaluate every (clip, hand) of `gt_root` that `pred_root` labels; write
    `metrics.json`, `table.md`, `table.csv`, `depth_scatter.png` and `pck.png` to `out_dir`."""
    pred_root, out_dir = pathlib.Path(pred_root), pathlib.Path(out_dir)
    per_clip, missing = [], []
    all_errors, z_pred, z_gt = [], [], []
    for clip in clip_io.list_clips(gt_root):
        fps = float(clip_io.read_meta(clip)["fps"])
        for side in clip_io.SIDES:
            gt_path = clip_io.hand_file(clip, side, "gt")
            if not gt_path.is_file():
                continue
            pred_path = clip_io.hand_file(pred_root / clip.name, side, "labels")
            if not pred_path.is_file():
                missing.append(f"{clip.name}/{side}")
                continue
            result = evaluate_hand(clip_io.load_npz(pred_path, "labels"), clip_io.load_npz(gt_path, "gt"), fps)
            per_clip.append({"clip": clip.name, "side": side, **result["scores"], "coverage": result["coverage"]})
            all_errors.append(result["joint_errors_p"].reshape(-1))
            z_pred.append(result["wrist_z"][0])
            z_gt.append(result["wrist_z"][1])
    if not per_clip:
        raise ValueError(f"no prediction in {pred_root} matches a ground-truth hand in {gt_root} (missing: {missing[:5]})")

    key = jax.random.key(seed)
    records, summary = [], {}
    for i, name in enumerate(list(_FRAME_METRICS) + ["jitter", "gt_jitter"]):
        values = np.asarray([c[name][0] for c in per_clip])
        has = np.asarray([c[name][1] > 0 for c in per_clip])
        b = metrics.bootstrap(values, jax.random.fold_in(key, i), n=num_resamples, mask=has)
        scale = 1.0 if "jitter" in name else 1000.0
        record = reports.Record.from_bootstrap(method, condition, name, b, scale)
        records.append(record)
        summary[name] = {k: getattr(record, k) for k in ("value", "std", "ci_low", "ci_high", "unit", "num_clips")}
    errors = np.concatenate(all_errors) if all_errors else np.zeros(0)
    z_pred_all, z_gt_all = np.concatenate(z_pred), np.concatenate(z_gt)
    scatter = metrics.depth_scatter(jnp.asarray(z_pred_all), jnp.asarray(z_gt_all))
    thresholds, curve = metrics.pck_curve(jnp.asarray(errors))
    summary["pck_auc_p"] = {"value": float(metrics.pck_auc(jnp.asarray(errors))), "unit": "fraction (0-50 mm, wrist-relative)"}
    scored, onscreen = (sum(c["coverage"][k] for c in per_clip) for k in (0, 1))

    out_dir.mkdir(parents=True, exist_ok=True)
    figures = {
        "depth_scatter": str(reports.plot_depth_scatter(z_gt_all, z_pred_all, scatter, out_dir / "depth_scatter.png", title=method)),
        "pck": str(reports.plot_pck(np.asarray(thresholds), np.asarray(curve), out_dir / "pck.png", label=method)),
    }
    result = {
        "method": method,
        "condition": condition,
        "protocol": "frames scored when on-screen in GT and emitted by the prediction; clip-weighted means; "
        f"bootstrap {num_resamples} resamples of per-clip means, 95% percentile interval (seed {seed})",
        "num_hands": len(per_clip),
        "missing_predictions": missing,
        "coverage": scored / max(onscreen, 1),
        "metrics": summary,
        "depth_scatter": {k: float(getattr(scatter, k)) for k in ("slope", "intercept", "correlation", "systematic_mm", "random_mm", "rmse_mm", "count")},
        "per_clip": per_clip,
        "figures": figures,
    }
    tmp = out_dir / ".metrics.json.tmp"
    tmp.write_text(json.dumps(result, indent=1))
    tmp.replace(out_dir / "metrics.json")
    table = reports.markdown_table(records)
    (out_dir / "table.md").write_text(table)
    reports.write_csv(records, out_dir / "table.csv")
    return result
