"""Scoring a network on held-out windows: the periodic validation of a training run, the
learning-curve benchmark, and the robustness conditions of the paper's studies (a view
dropped, frames dropped, a corruption).

`evaluate_windows` predicts every window (what `model.predict` emits, `model.gated`: the
on-screen gate applied; no augmentation, no masking), optionally with one view dropped
through the view-mask token, and scores it with `esther_jax.metrics` against the
window's targets:

- accuracy per frame with a target (`Targets.valid`): MPJPE (absolute, rig frame),
  P-MPJPE (wrist-relative), PA-MPJPE (similarity Procrustes), wrist error, averaged per window then over windows (the
  paper's clip-weighted mean; a window is the clip unit here);
- the image encoder's 2D keypoint error (crop pixels) per joint projecting into the crop
  of a present view, in frames with a target: what stage 1's guidance trains;
- jitter (appendix L, m/s^2) of the predicted joints and of the targets' own, on the
  frames with a target, ungated;
- the on-screen gate's precision / recall / F1 pooled over every frame, the truth being
  the training label (`losses.onscreen_label`: a target and a joint projecting into the
  crop of a present view).

3D errors are reported in millimetres (`*_mm`). Windows are taken as they are: build them
with `DataConfig.stride == frames` for non-overlapping held-out windows.

`score_predictions` is that scoring for any per-window predictions (a baseline's, e.g.
`studies.baselines.triangulation_baseline`); `evaluate_windows` predicts, then calls it.
"""

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Bool, Float

from .. import clips as clip_format
from .. import mano, metrics
from ..eval.protocols import corrupt_clip, frame_drop_mask
from ..model.esther import ESTHER, ClipInput, crop_projections, gated
from .data import DataConfig, Window, load_example
from .losses import Targets, onscreen_label

VALIDATION_METRICS = ("mpjpe_mm", "p_mpjpe_mm", "pa_mpjpe_mm", "wrist_mm", "keypoints_2d_px", "jitter", "gt_jitter", "onscreen_precision", "onscreen_recall", "onscreen_f1")


def _with_present(clip: ClipInput, present: Bool[Array, "*batch T 2"]) -> ClipInput:
    """The clip with these views present and the others' pixels (or tokens) zero."""
    blank = lambda x: None if x is None else jnp.where(present.reshape(present.shape + (1,) * (x.ndim - present.ndim)), x, 0)  # noqa: E731
    return eqx.tree_at(lambda c: (c.images, c.features, c.view_present), clip, (blank(clip.images), blank(clip.features), present),
                       is_leaf=lambda x: x is None)  # fmt: skip


def drop_view(clip: ClipInput, view: int) -> ClipInput:
    """One view of a clip (0 left, 1 right; leading axes allowed) blanked and marked absent."""
    if view not in (0, 1):
        raise ValueError(f"view must be 0 (left) or 1 (right), got {view!r}")
    return _with_present(clip, clip.view_present & jnp.broadcast_to(jnp.arange(2) != view, clip.view_present.shape))


def drop_frames(clip: ClipInput, kept: Bool[Array, "T"]) -> tuple[ClipInput, Bool[Array, "T 21"]]:
    """A clip with the frames not `kept` blanked in both views (absent) and masked for
    the motion encoder: the dropped-frames protocol (table 4). Returns the clip and the
    motion mask."""
    return _with_present(clip, clip.view_present & kept[:, None]), jnp.broadcast_to(~kept[:, None], (kept.shape[0], 21))


def _corrupted(clip: ClipInput, name: str, seed: int) -> ClipInput:
    """The crops under one appendix-K corruption (applied to the crops, uint8)."""
    pixels = np.rint(np.moveaxis(np.asarray(clip.images), -3, -1) * 255.0).astype(np.uint8)  # (T, 2, S, S, 3)
    changed = np.moveaxis(corrupt_clip(pixels, name, seed), -1, -3).astype(np.float32) / 255.0
    return eqx.tree_at(lambda c: c.images, clip, jnp.asarray(changed, clip.images.dtype))


@eqx.filter_jit
def _predict_windows(net: ESTHER, hand_model: mano.ManoModel, clip: ClipInput, motion_mask: Bool[Array, "B T 21"]):
    """What `predict` emits for a batch of right-hand windows, and the 2D keypoints."""
    out = jax.vmap(lambda c, m: net(c, hand_model, motion_mask=m))(clip, motion_mask)
    pred = gated(out)
    return pred.joints, pred.emitted, out.image.keypoints_2d


@eqx.filter_jit
def score_windows(
    joints: Float[Array, "B T 21 3"],
    emitted: Bool[Array, "B T"],
    keypoints_2d: Float[Array, "B T 2 21 2"] | None,
    clip: ClipInput,
    targets: Targets,
    fps: Float[Array, "B"],
    crop_size: int,
):
    """Per window of a batch: ({metric: Score}, GateScores) of predicted rig-frame joints,
    the emitted frames and the 2D keypoints (crop pixels; None for a prediction without
    them, whose 2D Score then has no data) against the targets (module docstring); 3D
    Scores in metres."""

    def one(joints, emitted, keypoints_2d, clip, targets, fps):
        gt, valid = targets.joints, targets.valid
        frame = lambda f: jax.vmap(f)(joints, gt)  # noqa: E731
        uv, _, inside = crop_projections(clip, gt, crop_size)
        visible = inside & clip.view_present[..., None] & valid[:, None, None]
        if keypoints_2d is None:  # static
            no_data = jnp.zeros((), uv.dtype)
            error_2d = metrics.Score(no_data, no_data)
        else:
            error_2d = metrics.clip_mean(jnp.linalg.norm(keypoints_2d.astype(uv.dtype) - uv, axis=-1).reshape(-1), visible.reshape(-1))
        scores = {
            "mpjpe_mm": metrics.clip_mean(frame(metrics.mpjpe), valid),
            "p_mpjpe_mm": metrics.clip_mean(frame(metrics.p_mpjpe), valid),
            "pa_mpjpe_mm": metrics.clip_mean(frame(metrics.pa_mpjpe), valid),
            "wrist_mm": metrics.clip_mean(frame(metrics.wrist_error), valid),
            "keypoints_2d_px": error_2d,
            "jitter": metrics.jitter(joints, valid, fps),
            "gt_jitter": metrics.jitter(gt, valid, fps),
        }
        truth = onscreen_label(targets, inside & clip.view_present[..., None])
        return scores, metrics.gate_scores(emitted, truth)

    return jax.vmap(one)(joints, emitted, keypoints_2d, clip, targets, fps)


def _check_windows(windows: list[Window], data_cfg: DataConfig, frames_dropped: int) -> None:
    if not windows:
        raise ValueError("no validation window: the held-out clips need crops, targets and at least one window of frames")
    if not 0 <= frames_dropped <= data_cfg.frames:
        raise ValueError(f"frames_dropped must lie in [0, {data_cfg.frames}], got {frames_dropped}")


def _conditioned(
    windows: list[Window],
    data_cfg: DataConfig,
    lo: int,
    batch: int,
    *,
    view_dropped: int | None,
    frames_dropped: int,
    blanked: Bool[Array, "T"] | None,
    corruption: str | None,
    seed: int,
) -> tuple[ClipInput, Targets, Bool[Array, "B T 21"]]:
    """Windows lo..lo + batch (the last one repeated to fill the batch: one compiled shape)
    under the condition of `predict_windows`: the clips as the network sees them, their
    targets and the motion encoder's masks."""
    chunk = windows[lo : lo + batch]
    padded = chunk + [chunk[-1]] * (batch - len(chunk))
    examples = [load_example(w, data_cfg) for w in padded]
    if corruption is not None:
        examples = [(_corrupted(c, corruption, seed * 1_000_003 + i), t) for i, (c, t) in enumerate(examples, start=lo)]
    clip, targets = jax.tree.map(lambda *x: jnp.stack(x), *examples)
    keys = jax.vmap(lambda i: jax.random.fold_in(jax.random.key(seed), i))(jnp.arange(lo, lo + batch))
    kept = jax.vmap(lambda k: frame_drop_mask(k, data_cfg.frames, frames_dropped))(keys)  # all kept when none drops
    clip, motion_mask = jax.vmap(drop_frames)(clip, kept)
    if blanked is not None:
        clip = _with_present(clip, clip.view_present & jnp.broadcast_to(~blanked[:, None], clip.view_present.shape))
    if view_dropped is not None:
        clip = drop_view(clip, view_dropped)
    return clip, targets, motion_mask


def _summarise(per_window: list, gates: list, count: int, *, intervals: bool, seed: int, resamples: int) -> dict:
    """The batches' per-window Scores and GateScores (padding dropped) of `count` windows
    -> the metrics dict of `score_predictions`."""
    scores = jax.tree.map(lambda *x: np.concatenate(x), *per_window)
    gate = jax.tree.map(lambda *x: np.concatenate(x), *gates)
    result: dict = {}
    spans: dict = {}
    for name, score in scores.items():
        mean = metrics.dataset_mean(jax.tree.map(jnp.asarray, score))
        scale = 1000.0 if name.endswith("_mm") else 1.0
        result[name] = float(mean.value) * scale if float(mean.count) > 0 else None
        if intervals:
            b = metrics.bootstrap(np.asarray(score.value) * scale, jax.random.key(seed), resamples, mask=np.asarray(score.count) > 0)
            spans[name] = None if b is None else [b.ci_low, b.ci_high]
    pooled = metrics.pooled_gate_scores(*(jnp.asarray(x) for x in (gate.true_positives, gate.false_positives, gate.false_negatives)))
    result.update(onscreen_precision=float(pooled.precision), onscreen_recall=float(pooled.recall), onscreen_f1=float(pooled.f1))
    out = {**{name: result[name] for name in VALIDATION_METRICS}, "windows": count}
    if intervals:
        out["intervals"] = spans
    return out


def score_predictions(
    joints: Float[Array, "N T 21 3"],
    emitted: Bool[Array, "N T"],
    windows: list[Window],
    data_cfg: DataConfig,
    *,
    keypoints_2d: Float[Array, "N T 2 21 2"] | None = None,
    view_dropped: int | None = None,
    frames_dropped: int = 0,
    blanked: Bool[Array, "T"] | None = None,
    batch: int = 8,
    seed: int = 0,
    intervals: bool = False,
    resamples: int = 2000,
) -> dict:
    """The validation metrics (module docstring) of per-window predictions on `windows`.

    Args:
        joints: rig-frame joints (m) of each window's frames, in the frame of the window's
            targets (`load_example`: left hands mirrored into right hands).
        emitted: the frames the predictor claims a hand in (the gate's prediction).
        keypoints_2d: the 2D keypoints of each view (crop pixels), for a network; None
            (a baseline): `keypoints_2d_px` is None.
        view_dropped, frames_dropped, blanked, seed: the condition the predictions were made
            under, as in `predict_windows` (the same frames are dropped for the same `seed`): the
            gate's truth and the 2D error count the views present under it only.
        batch: windows scored per compiled call.
        intervals, resamples: also the appendix-J bootstrap intervals (below), from
            `resamples` resamples.

    Returns {metric: value} in `VALIDATION_METRICS` order (3D errors in mm, the 2D error
    in crop pixels, jitter in m/s^2, gate scores in [0, 1]; None for a metric with no
    data) and `windows`, the number scored; with `intervals`, also
    `intervals: {metric: [low, high]}`, the appendix-J bootstrap 95% interval over
    windows (`resamples` resamples, seeded by `seed`) of each per-window metric.
    """
    _check_windows(windows, data_cfg, frames_dropped)
    rows = (len(windows), data_cfg.frames)
    if joints.shape[:2] != rows or emitted.shape != rows or (keypoints_2d is not None and keypoints_2d.shape[:2] != rows):
        got = f"joints {joints.shape}, emitted {emitted.shape}" + ("" if keypoints_2d is None else f", keypoints_2d {keypoints_2d.shape}")
        raise ValueError(f"predictions need one row per window and frame, {rows}; got {got}")
    fps_of = {w.clip: float(clip_format.read_meta(w.clip)["fps"]) for w in windows}
    per_window, gates = [], []
    for lo in range(0, len(windows), batch):
        take = np.minimum(np.arange(lo, lo + batch), len(windows) - 1)  # padded as `_conditioned` pads
        clip, targets, _ = _conditioned(windows, data_cfg, lo, batch, view_dropped=view_dropped, frames_dropped=frames_dropped,
                                        blanked=blanked, corruption=None, seed=seed)  # fmt: skip
        fps = jnp.asarray([fps_of[windows[i].clip] for i in take], clip.flow.dtype)
        kp = None if keypoints_2d is None else keypoints_2d[take]
        scores, gate = jax.device_get(score_windows(joints[take], emitted[take], kp, clip, targets, fps, data_cfg.crop_size))
        n = min(batch, len(windows) - lo)
        per_window.append(jax.tree.map(lambda x: np.asarray(x)[:n], scores))
        gates.append(jax.tree.map(lambda x: np.asarray(x)[:n], gate))
    return _summarise(per_window, gates, len(windows), intervals=intervals, seed=seed, resamples=resamples)


class Predictions(eqx.Module):
    """A network's outputs on held-out windows under a condition (`predict_windows`), with
    what they are scored against; one row per window."""

    joints: Float[Array, "N T 21 3"]
    """Rig-frame joints (m), in the frame of the targets (left hands mirrored)."""
    emitted: Bool[Array, "N T"]
    """Frames the on-screen gate emits."""
    keypoints_2d: Float[Array, "N T 2 21 2"]
    """The image encoder's 2D keypoints (crop pixels)."""
    targets: Targets
    onscreen: Bool[Array, "N T"]
    """The gate's truth under the condition: a target and a joint in a present view's crop
    (`losses.onscreen_label`); a blanked or dropped view holds no hand."""
    fps: Float[Array, "N"]

    def wrist_axes(self) -> metrics.WristAxes:
        """Where the predicted wrists miss the targets' (`metrics.wrist_axes`), over the
        frames with a target: per rig-frame axis and along / across the line of sight."""
        valid = np.asarray(self.targets.valid)
        return metrics.wrist_axes(self.joints[..., 0, :][valid], self.targets.joints[..., 0, :][valid])


def predict_windows(
    net: ESTHER,
    windows: list[Window],
    data_cfg: DataConfig,
    *,
    hand_model: mano.ManoModel | None = None,
    batch: int = 8,
    view_dropped: int | None = None,
    frames_dropped: int = 0,
    blanked: Bool[Array, "T"] | None = None,
    corruption: str | None = None,
    seed: int = 0,
) -> Predictions:
    """What `net` predicts (`model.gated`) for every window, under a condition:

    - `view_dropped` (0 left, 1 right): that view blanked in every frame (table 2);
    - `frames_dropped` N: N frames of each window, drawn per (seed, window), blanked in
      both views and masked for the motion encoder (table 4);
    - `blanked`: these frames of every window blanked in both views and not masked (the
      off-screen stress test of appendix L);
    - `corruption`: an appendix-K corruption (`eval.CORRUPTIONS`) of every crop (table 6;
      applied to the crops, not to the full frames).
    """
    parts = []
    for n, clip, targets, fps, (joints, emitted, keypoints_2d) in _predicted_batches(
        net, windows, data_cfg, hand_model=hand_model, batch=batch, view_dropped=view_dropped, frames_dropped=frames_dropped,
        blanked=blanked, corruption=corruption, seed=seed,
    ):  # fmt: skip
        onscreen = _onscreen_truth(clip, targets, data_cfg.crop_size)
        parts.append(jax.tree.map(lambda x: x[:n], (joints, emitted, keypoints_2d, targets, onscreen, fps)))  # the padding dropped
    return Predictions(*jax.tree.map(lambda *x: jnp.concatenate(x), *parts))


def _predicted_batches(net, windows, data_cfg, *, hand_model, batch, view_dropped, frames_dropped, blanked, corruption, seed):
    """Per batch of windows under the condition (`predict_windows`): the number of real
    (unpadded) windows, the clips as the network sees them, their targets, their fps and
    the network's (joints, emitted, keypoints_2d)."""
    _check_windows(windows, data_cfg, frames_dropped)
    if blanked is not None and blanked.shape != (data_cfg.frames,):
        raise ValueError(f"blanked must mark each of the {data_cfg.frames} frames of a window, got shape {blanked.shape}")
    hand_model = mano.load_builtin("right") if hand_model is None else hand_model
    fps_of = {w.clip: float(clip_format.read_meta(w.clip)["fps"]) for w in windows}
    for lo in range(0, len(windows), batch):
        clip, targets, motion_mask = _conditioned(windows, data_cfg, lo, batch, view_dropped=view_dropped, frames_dropped=frames_dropped,
                                                  blanked=blanked, corruption=corruption, seed=seed)  # fmt: skip
        take = np.minimum(np.arange(lo, lo + batch), len(windows) - 1)  # padded as `_conditioned` pads
        fps = jnp.asarray([fps_of[windows[i].clip] for i in take], clip.flow.dtype)
        yield min(batch, len(windows) - lo), clip, targets, fps, _predict_windows(net, hand_model, clip, motion_mask)


@eqx.filter_jit
def _onscreen_truth(clip: ClipInput, targets: Targets, crop_size: int) -> Bool[Array, "B T"]:
    _, _, inside = jax.vmap(lambda c, t: crop_projections(c, t, crop_size))(clip, targets.joints)
    return jax.vmap(onscreen_label)(targets, inside & clip.view_present[..., None])


def evaluate_windows(
    net: ESTHER,
    windows: list[Window],
    data_cfg: DataConfig,
    *,
    hand_model: mano.ManoModel | None = None,
    batch: int = 8,
    view_dropped: int | None = None,
    frames_dropped: int = 0,
    blanked: Bool[Array, "T"] | None = None,
    corruption: str | None = None,
    seed: int = 0,
    intervals: bool = False,
    resamples: int = 2000,
) -> dict:
    """The validation metrics (module docstring) of `net` on `windows` under a condition
    (`predict_windows`): what `score_predictions` returns for its predictions, each batch
    scored as it is predicted (every window loaded once)."""
    per_window, gates = [], []
    for n, clip, targets, fps, (joints, emitted, keypoints_2d) in _predicted_batches(
        net, windows, data_cfg, hand_model=hand_model, batch=batch, view_dropped=view_dropped, frames_dropped=frames_dropped,
        blanked=blanked, corruption=corruption, seed=seed,
    ):  # fmt: skip
        scores, gate = jax.device_get(score_windows(joints, emitted, keypoints_2d, clip, targets, fps, data_cfg.crop_size))
        per_window.append(jax.tree.map(lambda x: np.asarray(x)[:n], scores))
        gates.append(jax.tree.map(lambda x: np.asarray(x)[:n], gate))
    return _summarise(per_window, gates, len(windows), intervals=intervals, seed=seed, resamples=resamples)


__all__ = ["VALIDATION_METRICS", "Predictions", "drop_frames", "drop_view", "evaluate_windows", "predict_windows", "score_predictions", "score_windows"]
