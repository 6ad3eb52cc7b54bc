"""`esther evaluate`: compare label folders with ground-truth clip folders.

Ground truth: clip folders (`<gt>/<clip>/hands/<side>/gt.npz`, `meta.json` for fps).
Predictions: `<pred>/<clip>/hands/<side>/labels.npz` (the teacher's output format; a
file without `valid` counts every frame as emitted). Per the paper's protocol
(appendix L), a frame is scored when the hand is on-screen in the ground truth and the
prediction emitted it; jitter is gated the same way. Per-frame errors -> per-clip means
-> clip-weighted dataset means with bootstrap intervals over clips (appendix J).

Joints are always comparable and always scored. MANO parameters are compared
(`pose_angle`: mean geodesic angle of the 15 hand joints' rotations, degrees;
`betas_rmse`: RMS difference of the shape coefficients) only when the prediction and
the ground truth are parameters of the same model: the `mano_model` id
(`mano.model_id`) recorded in the hand's `quality.json` or the folder's `meta.json`
(`esther label` and `esther synth` write it). A hand whose models differ, or where a
side records no model (folders written before ids were recorded), is not compared:
`parameters="auto"` (the default) scores its joints, leaves it out of the parameter
metrics and says why in `metrics.json["parameters"]["not_compared"]`;
`parameters="require"` refuses (ValueError: `esther evaluate` exits 2) so a table of
parameter errors is never silently partial; `parameters="skip"` scores joints only.
"""

import dataclasses
import json
import math
import pathlib

import jax
import jax.numpy as jnp
import numpy as np

from .. import clips, metrics
from ..files import atomic_output, check_out_dir, write_json
from ..rotations import axis_angle_to_matrix, geodesic_angle
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


PARAMETER_MODES = ("auto", "require", "skip")
_PARAM_METRICS = {"pose_angle": (180.0 / math.pi, "deg"), "betas_rmse": (1.0, "")}
"""Parameter metrics: scale from the stored unit (radians, betas) and the table unit."""


@jax.jit
def _parameter_errors(pred_pose, gt_pose, pred_betas, gt_betas):
    angles = geodesic_angle(axis_angle_to_matrix(pred_pose), axis_angle_to_matrix(gt_pose))  # (T, 15) radians
    pose = jnp.mean(angles, axis=-1)
    betas = jnp.sqrt(jnp.mean(jnp.square(pred_betas - gt_betas)))  # one shape per clip: the same every frame
    return {"pose_angle": pose, "betas_rmse": jnp.broadcast_to(betas, pose.shape)}


def _recorded_model(folder: str | pathlib.Path, side: str) -> dict | None:
    """The `{"id", "source"}` of the model whose parameters a folder holds for `side`:
    the hand's `quality.json` `mano_model`, else `meta.json` `mano_model[side]`; None
    when neither records one (or the files cannot be read)."""
    folder = pathlib.Path(folder)
    for path, key in ((folder / "hands" / side / "quality.json", None), (folder / "meta.json", side)):
        try:
            data = json.loads(path.read_text())
        except (OSError, ValueError):
            continue
        record = data.get("mano_model") if isinstance(data, dict) else None
        if key is not None and isinstance(record, dict):
            record = record.get(key)
        if isinstance(record, dict) and isinstance(record.get("id"), str):
            return record
    return None


def _incomparable(pred_model: dict | None, gt_model: dict | None) -> str | None:
    """Why the parameters of two recorded models cannot be compared (None: they can)."""
    unknown = [name for name, m in (("prediction", pred_model), ("ground truth", gt_model)) if m is None]
    if unknown:
        return (
            f"the {' and the '.join(unknown)} record{'s' if len(unknown) == 1 else ''} no MANO model (a folder "
            "written before model ids were recorded?) and parameters of an unknown model are not comparable; "
            'relabel, or record the model in the folder\'s meta.json: "mano_model": {"<side>": {"id": mano.model_id(model)}}'
        )
    if pred_model["id"] != gt_model["id"]:
        return (
            f"the prediction is parameters of MANO model {pred_model['id']} ({pred_model.get('source', '?')}), "
            f"the ground truth of {gt_model['id']} ({gt_model.get('source', '?')})"
        )
    return None


def _table_unit(name: str) -> tuple[float, str]:
    """(scale from the stored unit, unit) of a metric in the tables: mm for distances."""
    if name in _PARAM_METRICS:
        return _PARAM_METRICS[name]
    return (1.0, "m/s^2") if "jitter" in name else (1000.0, "mm")


def _same_clip(labels_dir: pathlib.Path, clip_dir: pathlib.Path) -> bool:
    """Whether labels record the clip they were made from (`meta.json` `"source_clip"`,
    written by `esther label`): True when they do and it is `clip_dir`; False when they
    record nothing (labels of another tool: scored, listed as unverified). Raises a
    ValueError when they record another clip: scoring them would be meaningless."""
    try:
        source = json.loads((labels_dir / "meta.json").read_text()).get("source_clip")
    except (OSError, ValueError, AttributeError):
        return False
    if not isinstance(source, dict) or "digest" not in source:
        return False
    if source["digest"] != clips.clip_digest(clip_dir):
        raise ValueError(
            f"the labels in {labels_dir} were made from another clip than {clip_dir} (clip '{source.get('name')}', "
            f"digest {str(source['digest'])[:12]}..., while {clip_dir.name}'s rig.json and keypoints give "
            f"{clips.clip_digest(clip_dir)[:12]}...): give --pred and --gt folders of the same clips"
        )
    return True


def evaluate_hand(pred: clips.Labels, gt: dict, fps: float, *, parameters: bool = False) -> dict:
    """Per-clip scores of one hand (metres, m/s^2) and the frames they used: the labels
    `pred` (frames `valid`) against the gt.npz arrays `gt` (frames `onscreen`).

    `parameters=True` also scores `pose_angle` (radians) and `betas_rmse`: only for a
    prediction and ground truth of the same MANO model (the caller checks).
    """
    T = gt["joints"].shape[0]
    if pred.joints.shape != gt["joints"].shape:
        raise clips.ClipFormatError(f"prediction has {pred.joints.shape[0]} frames, ground truth {T}")
    frames = gt["onscreen"] & np.asarray(pred.valid)
    errors = _frame_errors(pred.joints, jnp.asarray(gt["joints"]))
    scores = {name: metrics.clip_mean(errors[name], jnp.asarray(frames)) for name in _FRAME_METRICS}
    scores["jitter"] = metrics.jitter(pred.joints, jnp.asarray(frames), fps)
    scores["gt_jitter"] = metrics.jitter(jnp.asarray(gt["joints"]), jnp.asarray(gt["onscreen"]), fps)
    if parameters:
        dtype = jnp.result_type(float)
        cast = lambda a: jnp.asarray(a, dtype)  # noqa: E731  (files may hold float32 and float64)
        param_errors = _parameter_errors(cast(pred.params.hand_pose), cast(gt["hand_pose"]), cast(pred.betas), cast(gt["betas"]))
        scores.update({name: metrics.clip_mean(param_errors[name], jnp.asarray(frames)) for name in _PARAM_METRICS})
    return {
        "scores": {k: (float(v.value), int(v.count)) for k, v in scores.items()},
        "frames": frames,
        "coverage": (int(frames.sum()), int(gt["onscreen"].sum())),
        "joint_errors_p": np.asarray(errors["joint_errors_p"])[frames],
        "wrist_z": (np.asarray(pred.joints)[frames, 0, 2], gt["joints"][frames, 0, 2]),
    }


def _predictions_folder(pred_root: str | pathlib.Path) -> pathlib.Path:
    """`pred_root`, checked to be a folder."""
    if not pathlib.Path(pred_root).is_dir():
        raise ValueError(f"the predictions folder {pred_root} does not exist (esther label --out or esther predict --out)")
    return pathlib.Path(pred_root)


def _nothing_scored(pred_root: pathlib.Path, gt_root: str | pathlib.Path, missing: list[str]) -> ValueError:
    """Why no hand was scored: the clips hold no ground truth, or no prediction matches."""
    if not missing:
        return ValueError(f"no clip of {gt_root} holds ground truth (hands/<side>/gt.npz): there is nothing to score against")
    return ValueError(f"no prediction in {pred_root} matches a ground-truth hand in {gt_root} (missing: {missing[:5]})")


def evaluate_folders(
    pred_root: str | pathlib.Path,
    gt_root: str | pathlib.Path,
    out_dir: str | pathlib.Path,
    *,
    method: str = "prediction",
    condition: str = "clean",
    seed: int = 0,
    num_resamples: int = 2000,
    parameters: str = "auto",
) -> dict:
    """Evaluate every (clip, hand) of `gt_root` that `pred_root` labels; write
    `metrics.json`, `table.md`, `table.csv`, `depth_scatter.png` and `pck.png` to `out_dir`.

    `parameters` ('auto', 'require' or 'skip') says what to do with the MANO parameter
    metrics (module docstring): joints are scored in every mode.
    """
    if parameters not in PARAMETER_MODES:
        raise ValueError(f"parameters must be one of {PARAMETER_MODES}, got {parameters!r}")
    pred_root, out_dir = _predictions_folder(pred_root), check_out_dir(out_dir)
    per_clip, missing, compared, not_compared, unverified = [], [], [], [], []
    missing_onscreen = 0  # on-screen ground-truth hand-frames of hands with no prediction
    all_errors, z_pred, z_gt = [], [], []
    for clip in clips.list_clips(gt_root):
        fps = float(clips.read_meta(clip)["fps"])
        for side in clips.SIDES:
            gt_path = clips.hand_file(clip, side, "gt")
            if not gt_path.is_file():
                continue
            pred_path = clips.hand_file(pred_root / clip.name, side, "labels")
            if not pred_path.is_file():
                missing.append(f"{clip.name}/{side}")
                missing_onscreen += int(clips.load_npz(gt_path, "gt")["onscreen"].sum())
                continue
            hand = f"{clip.name}/{side}"
            if not _same_clip(pred_root / clip.name, clip):
                unverified.append(clip.name)
            reason = None if parameters == "skip" else _incomparable(_recorded_model(pred_root / clip.name, side), _recorded_model(clip, side))
            if reason is not None and parameters == "require":
                raise ValueError(
                    f"{hand}: MANO parameters are not comparable: {reason}. Joints always are: "
                    "evaluate with parameters 'auto' or 'skip' (esther evaluate --params auto|skip)"
                )
            if reason is not None:
                not_compared.append({"hand": hand, "reason": reason})
            elif parameters != "skip":
                compared.append(hand)
            pred_labels, gt_arrays = clips.Labels.from_npz(pred_path), clips.load_npz(gt_path, "gt")
            result = evaluate_hand(pred_labels, gt_arrays, fps, parameters=parameters != "skip" and reason is None)
            per_clip.append({"clip": clip.name, "side": side, **result["scores"], "coverage": result["coverage"]})
            all_errors.append(result["joint_errors_p"].reshape(-1))
            z_pred.append(result["wrist_z"][0])
            z_gt.append(result["wrist_z"][1])
    unverified = list(dict.fromkeys(unverified))
    if not per_clip:
        raise _nothing_scored(pred_root, gt_root, missing)

    key = jax.random.key(seed)
    records, summary = [], {}
    names = list(_FRAME_METRICS) + ["jitter", "gt_jitter"] + (list(_PARAM_METRICS) if compared else [])
    for i, name in enumerate(names):
        values = np.asarray([c.get(name, (np.nan, 0))[0] for c in per_clip])
        has = np.asarray([c.get(name, (np.nan, 0))[1] > 0 for c in per_clip])
        b = metrics.bootstrap(values, jax.random.fold_in(key, i), n=num_resamples, mask=has)
        scale, unit = _table_unit(name)
        record = dataclasses.replace(reports.Record.from_bootstrap(method, condition, name, b, scale), unit=unit)
        records.append(record)
        summary[name] = {k: getattr(record, k) for k in ("value", "std", "ci_low", "ci_high", "unit", "num_clips")}
    # per hand, in the summary's units; a hand with no scored frame has null scores
    per_hand = [
        {"clip": c["clip"], "side": c["side"], "coverage": c["coverage"],
         "scores": {name: {"value": c[name][0] * _table_unit(name)[0] if c[name][1] > 0 else None,
                           "unit": _table_unit(name)[1], "frames": c[name][1]} for name in names if name in c}}
        for c in per_clip
    ]  # fmt: skip
    errors = np.concatenate(all_errors) if all_errors else np.zeros(0)
    z_pred_all, z_gt_all = np.concatenate(z_pred), np.concatenate(z_gt)
    scatter = metrics.depth_scatter(jnp.asarray(z_pred_all), jnp.asarray(z_gt_all))
    thresholds, curve = metrics.pck_curve(jnp.asarray(errors))
    summary["pck_auc_p"] = {"value": float(metrics.pck_auc(jnp.asarray(errors))), "unit": "fraction (0-50 mm, wrist-relative)"}
    scored, onscreen = (sum(c["coverage"][k] for c in per_clip) for k in (0, 1))
    onscreen += missing_onscreen

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
        "parameters": {
            "mode": parameters,
            "metrics": list(_PARAM_METRICS) if compared else [],
            "compared": compared,
            "not_compared": not_compared,
        },
        "depth_scatter": {k: float(getattr(scatter, k)) for k in ("slope", "intercept", "correlation", "systematic_mm", "random_mm", "rmse_mm", "count")},
        "identity_unverified": unverified,
        "per_clip": per_hand,
        "figures": figures,
    }
    write_json(out_dir / "metrics.json", result)
    with atomic_output(out_dir / "table.md") as tmp:
        tmp.write_text(reports.markdown_table(records))
    reports.write_csv(records, out_dir / "table.csv")
    return result
