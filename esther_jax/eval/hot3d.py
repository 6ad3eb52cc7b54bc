"""A HOT3D-compatible preset of the official hand_tracking_toolkit pose metrics.

What `facebookresearch/hand_tracking_toolkit` (metrics.py, evaluation.py) computes for
the pose track, and what we reproduce:

- landmarks: MANO's 16 FK joints plus the 5 smplx fingertip vertices, reordered to
  HOT3D's canonical order `MANO_TO_CANONICAL_LANDMARK_MAPPING = [16, 17, 18, 19, 20, 0,
  14, 15, 1, 2, 3, 4, 5, 6, 10, 11, 12, 7, 8, 9]` (5 tips, wrist, thumb MCP and IP,
  then index, middle, ring, pinky MCP/PIP/DIP; the thumb CMC is not a landmark);
- evaluated on 19 landmarks: the wrist is excluded (MANO's wrist differs from UmeTrack's);
- MPJPE in millimetres, absolute in the world (here: rig) frame, no alignment;
- PCK-AUC over thresholds `linspace(0, 50 mm, 101)`, normalised trapezoid, x 100; the
  same on the 5 fingertips;
- every 10th frame; sequences averaged with frame-count weights;
- for methods that output MANO, the ground-truth shape is substituted before FK (do
  this before calling us: `dataclasses.replace`-style, `eqx.tree_at(lambda p: p.betas, ...)`).

Our 21 keypoints (MediaPipe order) map onto those 20 landmarks by
`HOT3D_LANDMARKS_FROM_KEYPOINTS` (our keypoint 1, the thumb CMC, is unused).
"""

import pathlib

import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Bool, Float

from .. import metrics
from ..mano.constants import KEYPOINT_FROM_MANO

MANO_TO_CANONICAL_LANDMARK_MAPPING: tuple[int, ...] = (16, 17, 18, 19, 20, 0, 14, 15, 1, 2, 3, 4, 5, 6, 10, 11, 12, 7, 8, 9)
HOT3D_LANDMARKS_FROM_KEYPOINTS: tuple[int, ...] = tuple(KEYPOINT_FROM_MANO.index(m) for m in MANO_TO_CANONICAL_LANDMARK_MAPPING)
"""Canonical landmark i is our keypoint HOT3D_LANDMARKS_FROM_KEYPOINTS[i]."""
LANDMARKS_TO_EVAL: tuple[int, ...] = tuple(i for i in range(20) if i != 5)
"""The 19 evaluated landmarks (the wrist, canonical index 5, is excluded)."""
FINGERTIP_LANDMARKS: tuple[int, ...] = (0, 1, 2, 3, 4)
FRAME_STRIDE = 10


def hot3d_sequence_metrics(
    pred: Float[Array, "frames 21 3"], gt: Float[Array, "frames 21 3"], valid: Bool[Array, "frames"] | None = None,
    frame_stride: int = FRAME_STRIDE,
) -> dict[str, float]:  # fmt: skip
    """MPJPE (mm), PCK-AUC and fingertip PCK-AUC (x100) of one sequence, HOT3D-style.

    Returns also `num_frames`, the frame weight of this sequence in a dataset mean.
    """
    frames = np.arange(0, pred.shape[0], frame_stride)
    if valid is not None:
        frames = frames[np.asarray(valid)[frames]]
    if frames.size == 0:
        return {"mpjpe_mm": float("nan"), "pck_auc": float("nan"), "fingertip_pck_auc": float("nan"), "num_frames": 0}
    p = np.asarray(pred)[frames][:, list(HOT3D_LANDMARKS_FROM_KEYPOINTS)]
    g = np.asarray(gt)[frames][:, list(HOT3D_LANDMARKS_FROM_KEYPOINTS)]
    errors = np.linalg.norm(p - g, axis=-1)  # (F, 20), metres
    finite = np.isfinite(errors)  # HOT3D has NaN ground-truth landmarks (hand_tracking_toolkit#7): masked
    body = errors[:, list(LANDMARKS_TO_EVAL)]
    tips = errors[:, list(FINGERTIP_LANDMARKS)]
    body_ok, tips_ok = finite[:, list(LANDMARKS_TO_EVAL)], finite[:, list(FINGERTIP_LANDMARKS)]
    auc = lambda e, m: float(metrics.pck_auc(jnp.asarray(np.where(m, e, 0.0).reshape(-1)), jnp.asarray(m.reshape(-1)))) * 100  # noqa: E731
    return {
        "mpjpe_mm": float(np.mean(body[body_ok]) * 1000),
        "pck_auc": auc(body, body_ok),
        "fingertip_pck_auc": auc(tips, tips_ok),
        "num_frames": int(frames.size),
    }


def hot3d_dataset_metrics(per_sequence: list[dict[str, float]]) -> dict[str, float]:
    """Frame-count-weighted mean over sequences (hand_tracking_toolkit's evaluation.py)."""
    weights = np.asarray([s["num_frames"] for s in per_sequence], np.float64)
    if weights.sum() == 0:
        return {"mpjpe_mm": float("nan"), "pck_auc": float("nan"), "fingertip_pck_auc": float("nan"), "num_frames": 0}
    out = {}
    for key in ("mpjpe_mm", "pck_auc", "fingertip_pck_auc"):
        values = np.asarray([s[key] if s["num_frames"] else 0.0 for s in per_sequence])
        out[key] = float(np.sum(values * weights) / weights.sum())
    out["num_frames"] = int(weights.sum())
    return out


def evaluate_hot3d_folders(
    pred_root: str | pathlib.Path, gt_root: str | pathlib.Path, out_dir: str | pathlib.Path, models: dict | None = None
) -> dict:
    """The HOT3D preset over label folders: every (clip, hand) of `gt_root` with a `gt.npz`
    that `pred_root` labels, scored with `hot3d_sequence_metrics` on the frames the
    prediction emits (`valid`), the ground-truth shape substituted before FK (the model
    the labels are parameters of: the built-in hand, or one of `models`, the user's MANO
    files); sequences averaged frame-weighted. Writes `metrics.json` and `table.md`."""
    from .. import clips, mano
    from ..files import check_out_dir, write_json
    from .folders import _nothing_scored, _predictions_folder, _recorded_model

    pred_root, out_dir = _predictions_folder(pred_root), check_out_dir(out_dir)
    candidates = [mano.load_builtin(side) for side in clips.SIDES] + list((models or {}).values())
    by_id = {(m.side, mano.model_id(m)): m for m in candidates}
    fk = jax.jit(jax.vmap(lambda model, p: mano.forward(model, p, check_finite=False).joints, in_axes=(None, 0)))
    per_sequence, missing = [], []
    for clip in clips.list_clips(gt_root):
        for side in clips.SIDES:
            gt_path = clips.hand_file(clip, side, "gt")
            if not gt_path.is_file():
                continue
            pred_dir = pred_root / clip.name
            pred_path = clips.hand_file(pred_dir, side, "labels")
            if not pred_path.is_file():
                missing.append(f"{clip.name}/{side}")
                continue
            record = _recorded_model(pred_dir, side)
            if record is None:
                raise ValueError(f"{pred_dir}: the labels record no MANO model, so the ground-truth shape cannot be substituted")
            model = by_id.get((side, record["id"]))
            if model is None:
                raise ValueError(
                    f"{pred_dir.name}/{side}: the labels are parameters of MANO model {record['id']} ({record.get('source', '?')}); "
                    "give those files with --mano DIR"
                )
            gt, pred = clips.load_npz(gt_path, "gt"), clips.Labels.from_npz(pred_path)
            if len(pred.valid) != len(gt["onscreen"]):
                raise ValueError(f"{clip.name}/{side}: {len(pred.valid)} predicted frames, {len(gt['onscreen'])} in the ground truth")
            T = len(pred.valid)
            params = mano.ManoParams(pred.params.global_orient, pred.params.hand_pose,
                                     jnp.broadcast_to(jnp.asarray(gt["betas"]), (T, 10)), pred.params.transl)  # fmt: skip
            joints = np.asarray(fk(model, params))
            scores = hot3d_sequence_metrics(jnp.asarray(joints), jnp.asarray(gt["joints"]), pred.valid)
            per_sequence.append({"hand": f"{clip.name}/{side}", **scores})
    if not per_sequence:
        raise _nothing_scored(pred_root, gt_root, missing)
    scores_only = [{k: v for k, v in s.items() if k != "hand"} for s in per_sequence]
    result = {"preset": "hot3d", "dataset": hot3d_dataset_metrics(scores_only), "per_sequence": per_sequence, "missing": missing,
              "frame_stride": FRAME_STRIDE, "landmarks": "19 (HOT3D canonical without the wrist), absolute, millimetres"}  # fmt: skip
    write_json(out_dir / "metrics.json", result)
    d = result["dataset"]
    lines = ["| preset | MPJPE (mm) | PCK-AUC | fingertip PCK-AUC | frames |", "|---|---|---|---|---|",
             f"| hot3d | {d['mpjpe_mm']:.1f} | {d['pck_auc']:.1f} | {d['fingertip_pck_auc']:.1f} | {d['num_frames']} |"]  # fmt: skip
    (out_dir / "table.md").write_text("\n".join(lines) + "\n")
    return result
