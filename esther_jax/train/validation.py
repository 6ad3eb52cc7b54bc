"""Scoring a network on held-out windows: the periodic validation of a training run, the
learning-curve benchmark, and the robustness conditions of the paper's studies (a view
dropped, frames dropped, a corruption).

`evaluate_windows` predicts every window (what `model.predict` emits, `model.gated`: the
on-screen gate applied; no augmentation, no masking), optionally with one view dropped
through the view-mask token, and scores it with `esther_jax.metrics` against the
window's targets:

- accuracy per frame with a target (`Targets.valid`): P-MPJPE (wrist-relative), PA-MPJPE
  (similarity Procrustes), wrist error, averaged per window then over windows (the
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
"""

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Bool, Float

from .. import clips as clip_format
from .. import mano, metrics
from ..eval.protocols import corrupt_clip, frame_drop_mask
from ..model.esther import ESTHER, ClipInput, gated
from .data import DataConfig, Window, load_example
from .losses import Targets, crop_projections, onscreen_label

VALIDATION_METRICS = ("p_mpjpe_mm", "pa_mpjpe_mm", "wrist_mm", "keypoints_2d_px", "jitter", "gt_jitter", "onscreen_precision", "onscreen_recall", "onscreen_f1")


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
    keypoints_2d: Float[Array, "B T 2 21 2"],
    clip: ClipInput,
    targets: Targets,
    fps: Float[Array, "B"],
    crop_size: int,
):
    """Per window of a batch: ({metric: Score}, GateScores) of predicted rig-frame joints,
    the emitted frames and the 2D keypoints (crop pixels) against the targets (module
    docstring); 3D Scores in metres."""

    def one(joints, emitted, keypoints_2d, clip, targets, fps):
        gt, valid = targets.joints, targets.valid
        frame = lambda f: jax.vmap(f)(joints, gt)  # noqa: E731
        uv, _, inside = crop_projections(clip, gt, crop_size)
        visible = inside & clip.view_present[..., None] & valid[:, None, None]
        error_2d = jnp.linalg.norm(keypoints_2d.astype(uv.dtype) - uv, axis=-1)
        scores = {
            "p_mpjpe_mm": metrics.clip_mean(frame(metrics.p_mpjpe), valid),
            "pa_mpjpe_mm": metrics.clip_mean(frame(metrics.pa_mpjpe), valid),
            "wrist_mm": metrics.clip_mean(frame(metrics.wrist_error), valid),
            "keypoints_2d_px": metrics.clip_mean(error_2d.reshape(-1), visible.reshape(-1)),
            "jitter": metrics.jitter(joints, valid, fps),
            "gt_jitter": metrics.jitter(gt, valid, fps),
        }
        truth = onscreen_label(targets, inside & clip.view_present[..., None])
        return scores, metrics.gate_scores(emitted, truth)

    return jax.vmap(one)(joints, emitted, keypoints_2d, clip, targets, fps)


def evaluate_windows(
    net: ESTHER,
    windows: list[Window],
    data_cfg: DataConfig,
    *,
    hand_model: mano.ManoModel | None = None,
    batch: int = 8,
    view_dropped: int | None = None,
    frames_dropped: int = 0,
    corruption: str | None = None,
    seed: int = 0,
    intervals: bool = False,
) -> dict:
    """The validation metrics (module docstring) of `net` on `windows`, under a condition:

    - `view_dropped` (0 left, 1 right): that view blanked in every frame (table 2);
    - `frames_dropped` N: N frames of each window, drawn per (seed, window), blanked in
      both views and masked for the motion encoder (table 4);
    - `corruption`: an appendix-K corruption (`eval.CORRUPTIONS`) of every crop (table 6;
      applied to the crops, not to the full frames).

    Returns {metric: value} in `VALIDATION_METRICS` order (3D errors in mm, the 2D error
    in crop pixels, jitter in m/s^2, gate scores in [0, 1]; None for a metric with no
    data) and `windows`, the number scored; with `intervals`, also
    `intervals: {metric: [low, high]}`, the appendix-J bootstrap 95% interval over
    windows (2000 resamples, seeded by `seed`) of each per-window metric.
    """
    if not windows:
        raise ValueError("no validation window: the held-out clips need crops, targets and at least one window of frames")
    if not 0 <= frames_dropped <= data_cfg.frames:
        raise ValueError(f"frames_dropped must lie in [0, {data_cfg.frames}], got {frames_dropped}")
    hand_model = mano.load_builtin("right") if hand_model is None else hand_model
    fps_of = {w.clip: float(clip_format.read_meta(w.clip)["fps"]) for w in windows}
    per_window, gates = [], []
    for lo in range(0, len(windows), batch):
        chunk = windows[lo : lo + batch]
        padded = chunk + [chunk[-1]] * (batch - len(chunk))  # one compiled shape; the padding is dropped below
        examples = [load_example(w, data_cfg) for w in padded]
        if corruption is not None:
            examples = [(_corrupted(c, corruption, seed * 1_000_003 + i), t) for i, (c, t) in enumerate(examples, start=lo)]
        clip, targets = jax.tree.map(lambda *x: jnp.stack(x), *examples)
        keys = jax.vmap(lambda i: jax.random.fold_in(jax.random.key(seed), i))(jnp.arange(lo, lo + batch))
        kept = jax.vmap(lambda k: frame_drop_mask(k, data_cfg.frames, frames_dropped))(keys)  # all kept when none drops
        clip, motion_mask = jax.vmap(drop_frames)(clip, kept)
        if view_dropped is not None:
            clip = drop_view(clip, view_dropped)
        fps = jnp.asarray([fps_of[w.clip] for w in padded], clip.flow.dtype)
        joints, emitted, keypoints_2d = _predict_windows(net, hand_model, clip, motion_mask)
        scores, gate = jax.device_get(score_windows(joints, emitted, keypoints_2d, clip, targets, fps, data_cfg.crop_size))
        per_window.append(jax.tree.map(lambda x: np.asarray(x)[: len(chunk)], scores))
        gates.append(jax.tree.map(lambda x: np.asarray(x)[: len(chunk)], gate))
    scores = jax.tree.map(lambda *x: np.concatenate(x), *per_window)
    gate = jax.tree.map(lambda *x: np.concatenate(x), *gates)
    result: dict = {}
    spans: dict = {}
    for name, score in scores.items():
        mean = metrics.dataset_mean(jax.tree.map(jnp.asarray, score))
        scale = 1000.0 if name.endswith("_mm") else 1.0
        result[name] = float(mean.value) * scale if float(mean.count) > 0 else None
        if intervals:
            b = metrics.bootstrap(np.asarray(score.value) * scale, jax.random.key(seed), mask=np.asarray(score.count) > 0)
            spans[name] = None if b is None else [b.ci_low, b.ci_high]
    pooled = metrics.pooled_gate_scores(*(jnp.asarray(x) for x in (gate.true_positives, gate.false_positives, gate.false_negatives)))
    result.update(onscreen_precision=float(pooled.precision), onscreen_recall=float(pooled.recall), onscreen_f1=float(pooled.f1))
    out = {**{name: result[name] for name in VALIDATION_METRICS}, "windows": len(windows)}
    if intervals:
        out["intervals"] = spans
    return out


__all__ = ["VALIDATION_METRICS", "drop_frames", "drop_view", "evaluate_windows", "score_windows"]
