"""Scoring a network on held-out windows: the periodic validation of a training run and
the learning-curve benchmark.

`evaluate_windows` predicts every window (`model.predict`, on-screen gate applied, no
augmentation, no masking), optionally with one view dropped through the view-mask token,
and scores it with `esther_jax.metrics` against the window's targets:

- accuracy per frame with a target (`Targets.valid`): P-MPJPE (wrist-relative), PA-MPJPE
  (similarity Procrustes), wrist error, averaged per window then over windows (the
  paper's clip-weighted mean; a window is the clip unit here);
- jitter (appendix L, m/s^2) of the predicted joints and of the targets' own, on the
  frames with a target, ungated;
- the on-screen gate's precision / recall / F1 pooled over every frame, the truth being
  the training label (`losses.onscreen_label`: a target and a joint projecting into the
  crop of a present view).

Errors are reported in millimetres (`*_mm`). Windows are taken as they are: build them
with `DataConfig.stride == frames` for non-overlapping held-out windows.
"""

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from .. import clips as clip_format
from .. import mano, metrics
from ..model.esther import ESTHER, ClipInput, predict
from .data import DataConfig, Window, load_example
from .losses import Targets, crop_projections, onscreen_label

VALIDATION_METRICS = ("p_mpjpe_mm", "pa_mpjpe_mm", "wrist_mm", "jitter", "gt_jitter", "onscreen_precision", "onscreen_recall", "onscreen_f1")


def drop_view(clip: ClipInput, view: int) -> ClipInput:
    """One view of a clip (0 left, 1 right; leading axes allowed) blanked and marked absent."""
    if view not in (0, 1):
        raise ValueError(f"view must be 0 (left) or 1 (right), got {view!r}")
    present = clip.view_present & jnp.broadcast_to(jnp.arange(2) != view, clip.view_present.shape)
    blank = lambda x: None if x is None else jnp.where(present.reshape(present.shape + (1,) * (x.ndim - present.ndim)), x, 0)  # noqa: E731
    return eqx.tree_at(lambda c: (c.images, c.features, c.view_present), clip, (blank(clip.images), blank(clip.features), present),
                       is_leaf=lambda x: x is None)  # fmt: skip


@eqx.filter_jit
def _window_scores(clip: ClipInput, targets: Targets, joints: jax.Array, emitted: jax.Array, fps: jax.Array, crop_size: int):
    """Per window: accuracy Scores, jitter Scores and gate counts (vmapped over windows)."""

    def one(clip, targets, joints, emitted, fps):
        gt = targets.joints
        valid = targets.valid
        frame = lambda f: jax.vmap(f)(joints, gt)  # noqa: E731
        scores = {
            "p_mpjpe_mm": metrics.clip_mean(frame(metrics.p_mpjpe), valid),
            "pa_mpjpe_mm": metrics.clip_mean(frame(metrics.pa_mpjpe), valid),
            "wrist_mm": metrics.clip_mean(frame(metrics.wrist_error), valid),
            "jitter": metrics.jitter(joints, valid, fps),
            "gt_jitter": metrics.jitter(gt, valid, fps),
        }
        _, _, inside = crop_projections(clip, gt, crop_size)
        truth = onscreen_label(targets, inside & clip.view_present[..., None])
        return scores, metrics.gate_scores(emitted, truth)

    return jax.vmap(one)(clip, targets, joints, emitted, fps)


def evaluate_windows(
    net: ESTHER,
    windows: list[Window],
    data_cfg: DataConfig,
    *,
    hand_model: mano.ManoModel | None = None,
    batch: int = 8,
    view_dropped: int | None = None,
) -> dict[str, float]:
    """The validation metrics (module docstring) of `net` on `windows`; with
    `view_dropped` (0 left, 1 right) that view is blanked in every frame. Returns
    {metric: value} (errors in mm, jitter in m/s^2, gate scores in [0, 1]; None for a
    metric with no data) and `windows`, the number scored."""
    if not windows:
        raise ValueError("no validation window: the held-out clips need crops, targets and at least one window of frames")
    hand_model = mano.load_builtin("right") if hand_model is None else hand_model
    fps_of = {w.clip: float(clip_format.read_meta(w.clip)["fps"]) for w in windows}
    per_window, gates = [], []
    for lo in range(0, len(windows), batch):
        chunk = windows[lo : lo + batch]
        padded = chunk + [chunk[-1]] * (batch - len(chunk))  # one compiled shape; the padding is dropped below
        examples = [load_example(w, data_cfg) for w in padded]
        clip, targets = jax.tree.map(lambda *x: jnp.stack(x), *examples)
        if view_dropped is not None:
            clip = drop_view(clip, view_dropped)
        out = predict(net, clip, hand_model, is_right=True)  # left hands arrive mirrored, as right hands
        fps = jnp.asarray([fps_of[w.clip] for w in padded], clip.flow.dtype)
        scores, gate = jax.device_get(_window_scores(clip, targets, out.joints, out.emitted, fps, data_cfg.crop_size))
        per_window.append(jax.tree.map(lambda x: np.asarray(x)[: len(chunk)], scores))
        gates.append(jax.tree.map(lambda x: np.asarray(x)[: len(chunk)], gate))
    scores = jax.tree.map(lambda *x: np.concatenate(x), *per_window)
    gate = jax.tree.map(lambda *x: np.concatenate(x), *gates)
    result: dict[str, float | None] = {}
    for name, score in scores.items():
        mean = metrics.dataset_mean(jax.tree.map(jnp.asarray, score))
        scale = 1000.0 if name.endswith("_mm") else 1.0
        result[name] = float(mean.value) * scale if float(mean.count) > 0 else None
    pooled = metrics.pooled_gate_scores(*(jnp.asarray(x) for x in (gate.true_positives, gate.false_positives, gate.false_negatives)))
    result.update(onscreen_precision=float(pooled.precision), onscreen_recall=float(pooled.recall), onscreen_f1=float(pooled.f1))
    result["windows"] = len(windows)
    return result


__all__ = ["VALIDATION_METRICS", "drop_view", "evaluate_windows"]
