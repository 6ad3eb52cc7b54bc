"""The teacher's validation (paper section 3.2, appendices I and N) on synthetic held-out
clips with exact ground truth, across rigs and 2D-detector presets.

`run_validation` makes, per condition (rig preset, detector preset), under
`root/<rig>_<detector>/`:

- `clips/`: held-out clips (`esther_jax.data.synthesize`, resumable);
- `labels/`: the teacher's labels (`label_clips`, what `esther label` runs; resumable:
  finished labels are kept);
- `eval/`: the labels against the exact ground truth (`esther_jax.eval.evaluate_folders`,
  what `esther evaluate` runs: frames on-screen in the ground truth and labelled valid,
  clip-weighted means with bootstrap intervals, appendices J and L);

and returns per condition the accuracy (P-MPJPE, PA-MPJPE, wrist error in mm; jitter
beside the ground truth's own, m/s^2), the share of on-screen hand-frames labelled, the
label-quality table of appendix N pooled over the condition's hand-frames, and the
admissible-band check. `root/validation.json` records the results; `validation_table`,
`label_quality_table`, `plot_band_check` and `plot_error_vs_depth` present them.

The admissible band (appendix N, "From 2D residual to 3D error" and "Bounds"). With r the
reprojection residual of a hand-frame (pixels between the label's joints projected into
the views and the fused 2D keypoints, over the joints of both views with confidence
above tau = 0.3), z the hand's depth, f the focal length and b the baseline:

- lower end: the in-plane error r z / f, the part of a 3D error that the image shows
  ("whatever the labels get wrong in 3D, at least this much is visible in the image");
- upper end: the admissible depth error along the viewing ray, sqrt(2) r z^2 / (f b)
  (a disparity error of sqrt(2) r for independent errors in the two views, times the
  depth per pixel of disparity z^2 / (f b));
- the worst case, both views erring in opposite directions: 2 r z^2 / (f b).

The paper compares the teacher's motion-capture error (15.9 mm P-MPJPE, 19.1 mm wrist)
with the medians over hand-frames (2.8 mm in-plane, 21.3 mm admissible, 30.1 mm worst
case) and finds it inside. `band_check` does the same with the condition's measured
clip-weighted P-MPJPE and wrist error and the medians of its labelled hand-frames, and
also counts the hand-frames whose own errors lie within their own band. The per-pixel
factors are the teacher's (`frame_quality`): on any rig, z / f and z^2 / (f b) become
the local resolution along the ray and the baseline perpendicular to it (exactly z / f
and z^2 / (f b) on a parallel pinhole rig); a hand-frame seen by one view only takes the
hand's length in place of the baseline.

Two bands are reported. `residual`: the paper's, from r, which needs no ground truth.
`detector`: the same formulas with r replaced by the fused detections' own error
against the projected true joints, which only synthetic data knows: the band implied
by the rig and the 2D detector noise alone. The appendix's caveats hold and are visible
here: r mixes the detector's error with the label's (the label's own 2D error,
`label_2d_error_px`, is reported beside both), and the upper end is an allowance for a
single hand-frame, not a measurement; the teacher fits 21 joints over many frames with
priors, so its error may lie well below it; it may also lie below the lower end, when
r is mostly the detector's error. With exact detections (the `clean` preset) the
detector band shrinks to zero and the check says so (the measured error is above it),
while r is then the label's own 2D error.
"""

import functools
import pathlib
from collections.abc import Sequence

import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Float

from fitting import LabelConfig, frame_quality, fuse, label_clips, label_quality, prefilter, reprojection_filter, template_bones
from fitting.pipeline import far_outside_image

from .. import cameras, clips, mano, metrics
from ..cameras import StereoRig
from ..data import SynthConfig, synthesize
from ..data.detector import PRESETS as DETECTOR_PRESETS
from ..data.motion import MotionConfig
from ..eval import evaluate_folders, reports
from ..figures import figure, save_figure
from ..files import check_out_dir, write_json

RIGS = ("esther_mocap", "hot3d_quest3", "hot3d_aria")
"""The paper's test-set rig (parallel pinhole, 62 mm), Quest 3 (nearly parallel fisheye,
64 mm) and Aria (fisheye, 138 mm, 75 degrees apart: most hand-frames monocular)."""
DETECTORS = ("default", "hard")
CONDITIONS = tuple((rig, detector) for rig in RIGS for detector in DETECTORS)
SEED = 8
"""The teacher learns nothing from data, so every seed is held out from it; one seed for
all conditions gives a rig the same motions under every detector preset (paired)."""
MOTION = MotionConfig(two_hands_probability=1.0)
"""Both hands in every clip, as the paper's validation clips."""
BAND_METRICS = ("p_mpjpe", "wrist")
"""The measured errors the paper compares with the band."""
BAND_SOURCES = {"residual": "", "detector": "detector_"}
"""Band source -> prefix of its per-frame quantities."""
_BAND_RESIDUAL = {"residual": "reprojection_residual_px", "detector": "detector_error_px"}
MASKS = ("onscreen", "observed", "stereo", "valid", "scored")
"""Per-frame masks of `hand_frames` (the rest of its entries are quantities)."""
QUALITY_KEYS = (
    "reprojection_residual_px", "hand_depth_m", "in_plane_error_mm", "depth_per_pixel_mm",
    "admissible_depth_error_independent_mm", "admissible_depth_error_worst_mm",
)  # fmt: skip
"""What `frame_quality` returns per hand-frame (the teacher's quality.json table)."""
QUANTITY_LABELS = {
    "reprojection_residual_px": "Reprojection residual r (px)",
    "hand_depth_m": "Hand depth z (m)",
    "in_plane_error_mm": "In-plane error rz/f (mm)",
    "depth_per_pixel_mm": "Depth per pixel of disparity z^2/(fb) (mm)",
    "admissible_depth_error_independent_mm": "Admissible depth error, independent views (mm)",
    "admissible_depth_error_worst_mm": "Admissible depth error, worst case (mm)",
    "in_plane_mm_per_px": "In-plane mm per pixel z/f (mm)",
    "detector_error_px": "Detector 2D error vs truth (px)",
    "detector_in_plane_error_mm": "Detector in-plane error (mm)",
    "detector_admissible_depth_error_independent_mm": "Detector admissible depth error, independent (mm)",
    "detector_admissible_depth_error_worst_mm": "Detector admissible depth error, worst case (mm)",
    "label_2d_error_px": "Label 2D error vs truth (px)",
    "label_in_plane_error_mm": "Label in-plane error vs truth (mm)",
    "p_mpjpe_mm": "Measured P-MPJPE (mm)",
    "wrist_mm": "Measured wrist error (mm)",
    "wrist_depth_error_mm": "Measured wrist depth error (mm)",
}
"""Rows of the label-quality table, in order (appendix N's six first)."""


def condition_name(rig: str, detector: str) -> str:
    """The folder (and table row) of a condition: `<rig>_<detector>`."""
    return f"{rig}_{detector}"


# ----------------------------------------------------------------------------- per hand-frame


@functools.partial(jax.jit, static_argnames=("min_joints",))
def _hand_frames(
    model: mano.ManoModel,
    rig: StereoRig,
    uv: Float[Array, "detectors frames 2 21 2"],
    conf: Float[Array, "detectors frames 2 21"],
    box: Float[Array, "detectors frames 2 4"],
    box_score: Float[Array, "detectors frames 2"],
    label_joints: Float[Array, "frames 21 3"],
    gt_joints: Float[Array, "frames 21 3"],
    transl: Float[Array, "frames 3"],
    residual_px: Float[Array, "frames"],
    betas: Float[Array, "betas"],
    *,
    min_joints: int,
) -> tuple[dict[str, Float[Array, "4 frames"]], dict[str, Float[Array, "frames"]]]:
    # the teacher's evidence (pipeline._prepare, _observed): which views observe the hand
    fused = fuse(uv, conf, box, box_score)
    evidence = prefilter(rig, fused, template_bones(model))
    seen = jnp.sum(evidence.weight > 0, axis=2) >= min_joints  # (T, 2)
    # residuals over the joints r uses (fused confidence > tau): detections vs truth, label vs truth
    detector_px, _ = reprojection_filter(rig, gt_joints, fused.uv, fused.conf)
    uv_true = jnp.moveaxis(rig.project(gt_joints), 0, 1)  # (T, 2, 21, 2)
    label_px, _ = reprojection_filter(rig, label_joints, uv_true, fused.conf)
    # the hand's length at the label's shape, as pipeline._finish measures it
    zero = jnp.zeros(3, betas.dtype)
    rest = mano.forward_joints(model, mano.ManoParams(zero, jnp.zeros((15, 3), betas.dtype), betas, zero), check_finite=False)
    hand_length = jnp.linalg.norm(rest[12] - rest[0])
    # frame_quality is linear in the residual; the fourth row (1 px) gives the per-pixel factors
    residuals = jnp.stack([residual_px, detector_px, label_px, jnp.ones_like(residual_px)])
    quality = jax.vmap(frame_quality, in_axes=(None, None, 0, None, None))(rig, transl, residuals, seen, hand_length)
    w = seen.astype(transl.dtype)
    depth_error = jnp.abs(rig.depths(label_joints[:, 0]) - rig.depths(gt_joints[:, 0])).T  # (T, 2) along each camera's axis
    errors = {
        "p_mpjpe": jax.vmap(metrics.p_mpjpe)(label_joints, gt_joints),
        "wrist": jax.vmap(metrics.wrist_error)(label_joints, gt_joints),
        "wrist_depth": jnp.sum(depth_error * w, axis=1) / jnp.maximum(jnp.sum(w, axis=1), 1.0),
    }
    return quality, errors


def hand_frames(
    clip_dir: str | pathlib.Path, labels_dir: str | pathlib.Path, side: str, config: LabelConfig = LabelConfig()
) -> dict[str, np.ndarray]:
    """Per hand-frame quantities of one labelled hand of a clip with ground truth.

    Args:
        clip_dir: the clip folder (rig.json, hands/<side>/keypoints.npz and gt.npz).
        labels_dir: the folder of its labels (`<labels root>/<clip name>`), of the
            built-in hand (what `run_validation` makes).
        config: the `LabelConfig` the labels were made with (`min_joints_per_view`).
    Returns:
        Arrays over the clip's frames. Masks (`MASKS`): `onscreen` (ground truth),
        `observed`, `stereo`, `valid` (the labels'), `scored` (on-screen and valid: the
        frames `esther evaluate` scores). Quantities: the teacher's `frame_quality` from
        the labels' residual r (appendix N; the views that observe the hand are
        recomputed as the teacher finds them), `in_plane_mm_per_px`; `detector_error_px`
        (fused detections vs the projected true joints, over the joints r uses) and the
        band quantities from it (`detector_*`); `label_2d_error_px` and
        `label_in_plane_error_mm` (the label's projection vs the truth's); the measured
        `p_mpjpe_mm`, `wrist_mm` and `wrist_depth_error_mm` (along the observing cameras'
        axes), NaN where the frame is not scored.
    """
    clip_dir, labels_dir = pathlib.Path(clip_dir), pathlib.Path(labels_dir)
    rig = StereoRig.from_json(clip_dir / "rig.json")
    keypoints = clips.load_npz(clips.hand_file(clip_dir, side, "keypoints"), "keypoints")
    gt = clips.load_npz(clips.hand_file(clip_dir, side, "gt"), "gt")
    labels = clips.Labels.from_npz(clips.hand_file(labels_dir, side, "labels"))
    dtype = jnp.result_type(float)
    conf = np.array(keypoints["conf"], np.float64)
    conf[far_outside_image(rig, keypoints["uv"])] = 0.0  # not observations, as the teacher treats them
    arrays = [keypoints["uv"], conf, keypoints["box"], keypoints["box_score"], labels.joints, gt["joints"], labels.params.transl,
              labels.residual_px, labels.betas]  # fmt: skip
    quality, errors = jax.device_get(
        _hand_frames(mano.load_builtin(side), rig, *(jnp.asarray(a, dtype) for a in arrays), min_joints=config.min_joints_per_view)
    )
    masks = {
        "onscreen": np.asarray(gt["onscreen"], bool),
        "observed": np.asarray(labels.onscreen, bool),
        "stereo": np.asarray(labels.stereo, bool),
        "valid": np.asarray(labels.valid, bool),
    }
    masks["scored"] = masks["onscreen"] & masks["valid"]
    residual, detector, label, per_pixel = ({k: np.asarray(v[i], np.float64) for k, v in quality.items()} for i in range(4))
    out = dict(masks, **residual)
    out["in_plane_mm_per_px"] = per_pixel["in_plane_error_mm"]
    out["detector_error_px"] = detector["reprojection_residual_px"]
    for key in ("in_plane_error_mm", "admissible_depth_error_independent_mm", "admissible_depth_error_worst_mm"):
        out[f"detector_{key}"] = detector[key]
    out["label_2d_error_px"] = label["reprojection_residual_px"]
    out["label_in_plane_error_mm"] = label["in_plane_error_mm"]
    for name, values in errors.items():
        out[f"{name}_error_mm" if name == "wrist_depth" else f"{name}_mm"] = np.where(masks["scored"], np.asarray(values, np.float64) * 1000.0, np.nan)
    return out


# ----------------------------------------------------------------------------- the band


def band_check(table: dict, accuracy: dict, frames: dict[str, np.ndarray] | None = None, *, source: str = "residual",
               statistic: str = "median") -> dict:  # fmt: skip
    """Appendix N's admissible band and whether the measured errors fall inside it.

    Args:
        table: a label-quality table over hand-frames (`label_quality(...)[group]["table"]`
            with the rows of `hand_frames`).
        accuracy: the measured errors, `{metric: {"value": mm}}` (`evaluate_folders`'
            `metrics`); `BAND_METRICS` are checked.
        frames: the same hand-frames' `hand_frames` arrays, to count the frames whose own
            errors lie within their own band (optional).
        source: "residual" (the paper's band, from r) or "detector" (from the detections'
            own error against the truth).
        statistic: the table's "median" (the paper's comparison), "mean" or "p90".
    Returns:
        `lower_mm` (in-plane error), `upper_mm` (admissible depth error, independent
        views), `worst_mm` (worst case), `residual_px` (the r they come from), and per
        metric `measured_mm`, `position` ("below", "inside" or "above" the band),
        `inside` (lower <= measured <= upper), `inside_worst_case`
        (lower <= measured <= worst) and `share_of_frames_inside` (scored hand-frames with
        lower_t <= error_t <= upper_t); `inside` overall (every metric inside). Bounds
        are None, and the checks too, where no hand-frame has them.
    """
    if source not in BAND_SOURCES:
        raise ValueError(f"source must be one of {tuple(BAND_SOURCES)}, got {source!r}")
    if statistic not in ("median", "mean", "p90"):
        raise ValueError(f"statistic must be 'median', 'mean' or 'p90', got {statistic!r}")
    prefix = BAND_SOURCES[source]
    keys = {"lower_mm": "in_plane_error_mm", "upper_mm": "admissible_depth_error_independent_mm", "worst_mm": "admissible_depth_error_worst_mm"}
    value = lambda key: (table.get(key) or {}).get(statistic)  # noqa: E731  (a row without frames is None)
    out = {"source": source, "statistic": statistic, "residual_px": value(_BAND_RESIDUAL[source])}
    out.update({name: value(prefix + key) for name, key in keys.items()})
    known = all(out[k] is not None for k in keys)
    checks = {}
    for metric in BAND_METRICS:
        measured = (accuracy.get(metric) or {}).get("value")
        check = {"measured_mm": measured, "position": None, "inside": None, "inside_worst_case": None, "share_of_frames_inside": None}
        if known and measured is not None and np.isfinite(measured):
            check["position"] = "below" if measured < out["lower_mm"] else "above" if measured > out["upper_mm"] else "inside"
            check["inside"] = check["position"] == "inside"
            check["inside_worst_case"] = bool(out["lower_mm"] <= measured <= out["worst_mm"])
        if frames is not None:
            error, lower, upper = (np.asarray(frames[k]) for k in (f"{metric}_mm", prefix + keys["lower_mm"], prefix + keys["upper_mm"]))
            ok = frames["scored"] & np.isfinite(error) & np.isfinite(lower) & np.isfinite(upper)
            check["share_of_frames_inside"] = float(np.mean((lower[ok] <= error[ok]) & (error[ok] <= upper[ok]))) if ok.any() else None
        checks[metric] = check
    out["metrics"] = checks
    inside = [c["inside"] for c in checks.values()]
    out["inside"] = None if None in inside else all(inside)
    return out


# ----------------------------------------------------------------------------- the runner


def _check_conditions(conditions: Sequence[tuple[str, str]]) -> list[tuple[str, str]]:
    conditions = [tuple(c) for c in conditions]
    if not conditions:
        raise ValueError(f"no condition to validate; give (rig, detector) pairs, e.g. {CONDITIONS[:2]}")
    for condition in conditions:
        if len(condition) != 2:
            raise ValueError(f"a condition is a (rig preset, detector preset) pair, got {condition!r}")
        rig, detector = condition
        if rig not in cameras.RIG_PRESETS:
            raise ValueError(f"unknown rig preset {rig!r}; choose one of {cameras.RIG_PRESETS}")
        if detector not in DETECTOR_PRESETS:
            raise ValueError(f"unknown detector preset {detector!r}; choose one of {tuple(DETECTOR_PRESETS)}")
    names = [condition_name(*c) for c in conditions]
    if len(set(names)) != len(names):
        raise ValueError(f"conditions repeat: {names}")
    return conditions


def _held_out_clips(folder: pathlib.Path, num_clips: int) -> list[pathlib.Path]:
    """The clips of a condition's folder; refuses a folder that holds more than asked
    for (its results would not be of the clips asked for)."""
    present = clips.list_clips(folder)
    if len(present) > num_clips:
        raise ValueError(
            f"{folder} holds {len(present)} clips, {num_clips} were asked for: ask for {len(present)} or more, or use another root"
        )
    return present


def _run_condition(root: pathlib.Path, rig: str, detector: str, num_clips: int, num_frames: int, seed: int, config: LabelConfig,
                   motion_config: MotionConfig, num_resamples: int, progress: bool) -> dict:  # fmt: skip
    name = condition_name(rig, detector)
    folder = root / name
    folders = {k: folder / k for k in ("clips", "labels", "eval")}
    cfg = SynthConfig(num_frames=num_frames, rig=rig, detector_preset=detector, motion_config=motion_config)
    made = synthesize(folders["clips"], num_clips, cfg, seed=seed, progress=progress)
    clip_dirs = _held_out_clips(folders["clips"], num_clips)
    labelled = label_clips(clip_dirs, folders["labels"], resume=True, config=config, progress=progress)
    evaluation = evaluate_folders(folders["labels"], folders["clips"], folders["eval"], method="teacher", condition=name, seed=seed,
                                  num_resamples=num_resamples)  # fmt: skip
    hands = [
        hand_frames(clip, folders["labels"] / clip.name, side, config)
        for clip in clip_dirs
        for side in clips.SIDES
        if clips.hand_file(clip, side, "gt").is_file() and clips.hand_file(folders["labels"] / clip.name, side, "labels").is_file()
    ]  # fmt: skip
    frames = {k: np.concatenate([h[k] for h in hands]) for k in hands[0]}
    quantities = {k: v for k, v in frames.items() if k not in MASKS}
    quality = label_quality(quantities, frames["observed"], frames["stereo"], frames["valid"])
    table = quality["all"]["table"]
    return {
        "condition": name,
        "rig": rig,
        "detector": detector,
        "num_clips": num_clips,
        "num_frames": num_frames,
        "seed": seed,
        "folders": {k: str(v) for k, v in folders.items()},
        "synth": {k: made[k] for k in ("made", "skipped", "seconds")},
        "label": {
            "labelled": [s["clip"] for s in labelled["labelled"]],
            "skipped": labelled["skipped"],
            "failed": labelled["failed"],
            "seconds": labelled["seconds"],
        },
        "accuracy": evaluation["metrics"],
        "coverage": evaluation["coverage"],
        "hand_frames": {"hands": len(hands), "frames": int(frames["onscreen"].size), **{k: int(frames[k].sum()) for k in MASKS}},
        "label_quality": quality,
        "band": {source: band_check(table, evaluation["metrics"], frames, source=source) for source in BAND_SOURCES},
        "depth_scatter": evaluation["depth_scatter"],
        "frames": frames,
    }


def run_validation(
    root: str | pathlib.Path,
    conditions: Sequence[tuple[str, str]] = CONDITIONS,
    *,
    num_clips: int = 6,
    num_frames: int = 64,
    seed: int = SEED,
    config: LabelConfig = LabelConfig(),
    motion_config: MotionConfig = MOTION,
    num_resamples: int = 2000,
    progress: bool = False,
) -> list[dict]:
    """Synthesize, label and evaluate held-out clips per (rig preset, detector preset).

    Resumable: finished clips and labels are kept (labels whatever `LabelConfig` made
    them: `label_clips` checks the hand model and the source clip, not the config; use
    another root for another config); the evaluation is redone. Unknown presets are
    refused before any work; a condition folder made with other settings (frames, seed,
    motion) by `synthesize`, one holding more clips than `num_clips` before labelling
    (ValueError: its results would not be of the clips asked for).

    Args:
        root: the study's folder; condition `(rig, detector)` lives in
            `root/<rig>_<detector>/{clips,labels,eval}`.
        conditions: (rig, detector) pairs of `esther_jax.cameras.RIG_PRESETS` and
            `esther_jax.data.detector.PRESETS`.
        num_clips, num_frames, seed, motion_config: the held-out clips of every condition
            (`SynthConfig`; clip i depends only on (seed, i)).
        config: the teacher's settings.
        num_resamples: bootstrap resamples of the clip means (appendix J).
    Returns:
        One dict per condition, in order: `condition`, `rig`, `detector`, `num_clips`,
        `num_frames`, `seed`, `folders`; `synth` and `label` (what was made, kept,
        failed); `accuracy` (`evaluate_folders`' metrics: `p_mpjpe`, `pa_mpjpe`, `wrist`,
        `mpjpe` in mm, `jitter` and `gt_jitter` in m/s^2, `pose_angle`, `betas_rmse`,
        `pck_auc_p`, each with bootstrap std and interval); `coverage` (on-screen
        hand-frames labelled valid); `hand_frames` (counts per mask of `hand_frames`);
        `label_quality` (appendix N's table over the labelled hand-frames, `label_quality`
        layout, rows `QUANTITY_LABELS`); `band` (`band_check` per source, "residual" and
        "detector"); `depth_scatter`; `frames` (the pooled `hand_frames` arrays). This
        call's results, without `frames`, are also written to `root/validation.json`.
    """
    conditions = _check_conditions(conditions)
    if min(num_clips, num_frames) < 1:
        raise ValueError(f"num_clips and num_frames must be >= 1, got {num_clips} and {num_frames}")
    root = check_out_dir(root, "root")
    results = [
        _run_condition(root, rig, detector, num_clips, num_frames, seed, config, motion_config, num_resamples, progress)
        for rig, detector in conditions
    ]  # fmt: skip
    write_json(root / "validation.json", [{k: v for k, v in r.items() if k != "frames"} for r in results])
    return results


# ----------------------------------------------------------------------------- tables and figures


def _mm(value: float | None, digits: int = 1) -> str:
    return "n/a" if value is None or not np.isfinite(value) else f"{value:.{digits}f}"


def _median(table: dict, key: str) -> float | None:
    return (table.get(key) or {}).get("median")  # a row without hand-frames is None


def _metric_cell(summary: dict | None) -> str:
    """`mean ± std` as `reports.markdown_table` writes it (one clip: no interval)."""
    if not summary or summary.get("value") is None or not np.isfinite(summary["value"]):
        return "no data"
    std = summary.get("std")
    return f"{summary['value']:.2f} ± {'n/a' if std is None else f'{std:.2f}'}"


def _yes_no(flag: bool | None) -> str:
    return "n/a" if flag is None else ("yes" if flag else "no")


def validation_table(results: list[dict], source: str = "residual") -> str:
    """One row per condition: accuracy against the exact ground truth, the share of
    on-screen hand-frames labelled, appendix N's median residual, depth and depth per
    pixel, and the admissible band of `source` with whether P-MPJPE and the wrist error
    fall inside it (and inside the worst case)."""
    columns = (
        "Condition", "Rig", "Detector", "Clips x frames", "Labelled", "P-MPJPE (mm)", "PA-MPJPE (mm)", "Wrist (mm)",
        "Jitter / GT (m/s^2)", "r (px)", "z (m)", "Depth/px (mm)", "Band (mm)", "Worst (mm)", "Inside: P / wrist",
        "Worst case: P / wrist",
    )  # fmt: skip
    lines = ["| " + " | ".join(columns) + " |", "|---" * len(columns) + "|"]
    for r in results:
        table = r["label_quality"]["all"]["table"]
        band = r["band"][source]
        a = r["accuracy"]
        jitter = f"{_mm(a['jitter']['value'], 2)} / {_mm(a['gt_jitter']['value'], 2)}"
        checks = [band["metrics"][m] for m in BAND_METRICS]
        cells = [
            r["condition"], r["rig"], r["detector"], f"{r['num_clips']} x {r['num_frames']}", f"{r['coverage']:.1%}",
            _metric_cell(a.get("p_mpjpe")), _metric_cell(a.get("pa_mpjpe")), _metric_cell(a.get("wrist")), jitter,
            _mm(_median(table, "reprojection_residual_px")), _mm(_median(table, "hand_depth_m"), 2),
            _mm(_median(table, "depth_per_pixel_mm"), 2),
            f"{_mm(band['lower_mm'])} - {_mm(band['upper_mm'])}", _mm(band["worst_mm"]),
            " / ".join(_yes_no(c["inside"]) for c in checks), " / ".join(_yes_no(c["inside_worst_case"]) for c in checks),
        ]  # fmt: skip
        lines.append("| " + " | ".join(cells) + " |")
    return "\n".join(lines) + "\n"


def label_quality_table(result: dict, group: str = "all") -> str:
    """Appendix N's table (median, mean, p90) of one condition's labelled hand-frames
    (`group`: "stereo", "monocular" or "all"), with the synthetic-only rows (errors
    against the truth) below the paper's six."""
    quality = result["label_quality"][group]
    lines = [
        f"{result['condition']}, {group} hand-frames: {quality['passing']} labelled of {quality['hand_frames']} observed",
        "",
        "| Quantity | Median | Mean | p90 |",
        "|---|---|---|---|",
    ]
    for key, label in QUANTITY_LABELS.items():
        row = quality["table"].get(key)
        cells = ["n/a"] * 3 if row is None else [f"{row[s]:.3g}" for s in ("median", "mean", "p90")]
        lines.append(f"| {label} | " + " | ".join(cells) + " |")
    if group != "stereo" and result["label_quality"]["monocular"]["passing"]:
        note = ("Monocular hand-frames: depth per pixel of the hand's image extent, z^2/(fL) with L the hand's length, "
                "in place of the disparity's z^2/(fb) (`fitting.quality`).")
        lines += ["", note]
    return "\n".join(lines) + "\n"


def plot_band_check(results: list[dict], path: str | pathlib.Path, source: str = "residual") -> pathlib.Path:
    """Per condition, the admissible band of `source` (median in-plane error to median
    admissible depth error; the line on to the worst case) and the measured P-MPJPE and
    wrist error."""
    bands = [r["band"][source] for r in results]
    nan = lambda v: np.nan if v is None else v  # noqa: E731
    return reports.plot_intervals(
        [r["condition"] for r in results],
        [nan(b["lower_mm"]) for b in bands],
        [nan(b["upper_mm"]) for b in bands],
        path,
        outer=[nan(b["worst_mm"]) for b in bands],
        points={metrics.METRIC_LABELS[m][0]: [nan(b["metrics"][m]["measured_mm"]) for b in bands] for m in BAND_METRICS},
        ylabel="error (mm)",
        title=f"measured error vs admissible band ({source}, {bands[0]['statistic'] if bands else 'median'})",
    )


def plot_error_vs_depth(results: list[dict], path: str | pathlib.Path, source: str = "residual") -> pathlib.Path:
    """Per condition, every scored hand-frame's wrist error and P-MPJPE against its
    depth, with its own band of `source` (a vertical line from the in-plane error to the
    admissible depth error)."""
    prefix = BAND_SOURCES[source]
    cols = min(len(results), 3)
    rows = -(-len(results) // cols)
    fig, axes = figure(rows, cols, figsize=(4.2 * cols, 3.4 * rows), squeeze=False)
    for ax, r in zip(axes.flat, results):
        f = r["frames"]
        ok = f["scored"] & np.isfinite(f["wrist_mm"]) & np.isfinite(f[prefix + "in_plane_error_mm"])
        z = f["hand_depth_m"][ok]
        ax.vlines(z, f[prefix + "in_plane_error_mm"][ok], f[prefix + "admissible_depth_error_independent_mm"][ok], color="#a0aec0",
                  lw=0.8, alpha=0.6, label="admissible band")  # fmt: skip
        ax.scatter(z, f["wrist_mm"][ok], s=6, color="#c53030", label="wrist error", zorder=3)
        ax.scatter(z, f["p_mpjpe_mm"][ok], s=6, color="#2b6cb0", marker="x", label="P-MPJPE", zorder=3)
        ax.set_title(r["condition"], fontsize=9)
        ax.set_xlabel("hand depth z (m)")
        ax.set_ylabel("mm")
    for ax in list(axes.flat)[len(results) :]:
        ax.set_visible(False)
    axes.flat[0].legend(fontsize=7)
    return save_figure(fig, path)
