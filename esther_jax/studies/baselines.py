"""The triangulation baseline of the missing-view study (paper table 2, "One stereo view
missing"): what a triangulation-anchored method places, scored with the network's own
metrics (`train.validation.score_predictions`).

`triangulation_baseline` predicts the 21 joints of every held-out window from the clip's
2D keypoints alone (`hands/<side>/keypoints.npz`, the rig from `rig.json`):

1. Fusion: the D detectors are fused per joint and view exactly as the teacher fuses
   them (`fitting.fuse`, appendix A: the most confident detection anchors the joint,
   agreeing detections are averaged by confidence; a joint below the confidence
   threshold is not observed).
2. Stereo: a joint observed in both views is triangulated (`triangulate_rig`, DLT
   weighted by the fused confidences, as the teacher's prefilter does).
3. One view: a joint observed in one view only, or whose two rays give no valid point,
   lies on its ray in the (more confident) view at the prior depth `prior_depth_m`
   (camera z): without disparity nothing else fixes its distance. With a view dropped
   (`view_dropped`, the paper's condition) every joint is placed so: this is what a
   triangulation-anchored method falls back to when its anchor vanishes with the view.
4. Unobserved: a joint observed in no view of a frame is interpolated linearly over
   time between the frames of the window that place it (held at the window's ends); a
   joint placed in no frame of the window takes the centroid of the frame's other
   joints; a window without any keypoint puts every joint at the prior depth on the
   left camera's optical axis.

Frames with no observed keypoint in any view are not emitted. The joints come in the
frame of the window's targets: a left hand is mirrored by `train.mirror_targets`, as
`train.load_example` mirrors its targets. `view_dropped` names a view of that frame,
as `evaluate_windows` does: a left hand's mirrored clip has its views swapped, so its
original right camera is the view 0 dropped.

`mean_joint_depth` is the prior: the training windows' mean joint depth.

It is a study's machinery (`esther_jax.studies`): it uses the teacher's fusion
(`fitting`) and reads training windows (`esther_jax.train`).
"""

import functools
import pathlib

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Bool, Float

from fitting import fuse

from .. import clips
from ..cameras import StereoRig, apply_transform
from ..eval.protocols import drop_view_keypoints
from ..model import ClipInput, crop_projections
from ..train.data import DataConfig, Window, load_example, mirror_targets
from ..train.losses import Targets
from ..triangulation import triangulate_rig


@functools.lru_cache(maxsize=64)
def _hand_keypoints(clip: str, side: str) -> tuple[StereoRig, dict[str, np.ndarray]]:
    """A clip's rig and one hand's detections, read and validated once per process."""
    folder = pathlib.Path(clip)
    return StereoRig.from_json(folder / "rig.json"), clips.load_npz(clips.hand_file(folder, side, "keypoints"), "keypoints")


def _fill_over_time(points: Float[Array, "T 21 3"], placed: Bool[Array, "T 21"]) -> tuple[Float[Array, "T 21 3"], Bool[Array, "T 21"]]:
    """Each joint linearly interpolated between the frames that place it, held at the
    ends; and whether the joint is placed in some frame (elsewhere its points mean nothing)."""
    T = points.shape[0]
    t = jnp.arange(T)[:, None]
    before = jax.lax.cummax(jnp.where(placed, t, -1), axis=0)  # last placing frame up to t (-1: none)
    after = jax.lax.cummin(jnp.where(placed, t, T), axis=0, reverse=True)  # first from t on (T: none)
    joint = jnp.arange(points.shape[1])[None, :]
    p0, p1 = points[jnp.maximum(before, 0), joint], points[jnp.minimum(after, T - 1), joint]
    has0, has1 = before >= 0, after < T
    frac = ((t - before) / jnp.maximum(after - before, 1)).astype(points.dtype)  # 0 where placed (before == after == t)
    between = p0 + frac[..., None] * (p1 - p0)
    filled = jnp.where((has0 & has1)[..., None], between, jnp.where(has0[..., None], p0, p1))
    return filled, has0 | has1


@eqx.filter_jit
def _window_joints(
    rig: StereoRig,
    uv: Float[Array, "D T 2 21 2"],
    conf: Float[Array, "D T 2 21"],
    box: Float[Array, "D T 2 4"],
    box_score: Float[Array, "D T 2"],
    prior_depth: Float[Array, ""],
    left: Bool[Array, ""],
) -> tuple[Float[Array, "T 21 3"], Bool[Array, "T"]]:
    """One window's baseline joints (the targets' frame) and emitted frames (module docstring)."""
    fused = fuse(uv, conf, box, box_score)  # (T, 2, 21, 2), (T, 2, 21); confidence 0: not observed
    tri = triangulate_rig(rig, jnp.swapaxes(fused.uv, 1, 2), jnp.swapaxes(fused.conf, 1, 2))  # (T, 21)
    rays, ray_ok = rig.unproject_with_validity(jnp.moveaxis(fused.uv, 1, 0))
    view_conf = jnp.moveaxis(fused.conf, 1, 0)  # (2, T, 21)
    seen = (view_conf > 0) & ray_ok
    on_ray = jax.vmap(apply_transform)(rig.T_rig_cams, rays * prior_depth)  # rays have z = 1: camera z = prior depth
    best = jnp.argmax(jnp.where(seen, view_conf, -1.0), axis=0)  # (T, 21)
    one_view = jnp.take_along_axis(on_ray, best[None, ..., None], axis=0)[0]
    placed = jnp.any(seen, axis=0)  # (T, 21); a valid triangulation has both views seen
    filled, known = _fill_over_time(jnp.where(tri.valid[..., None], tri.point, one_view), placed)
    count = jnp.sum(known, axis=1, keepdims=True).astype(filled.dtype)  # (T, 1)
    centroid = jnp.sum(jnp.where(known[..., None], filled, 0.0), axis=1) / jnp.maximum(count, 1.0)
    on_axis = jnp.zeros((1, 3), filled.dtype).at[0, 2].set(prior_depth)
    fallback = jnp.where(count > 0, centroid, on_axis)
    joints = jnp.where(known[..., None], filled, fallback[:, None, :])
    emitted = jnp.any(placed, axis=1)
    # `mirror_targets` maps whole targets; only the joints matter here (no MANO fit: the
    # parameters are zeros with the wrist as translation, and are dropped).
    T = joints.shape[0]
    as_targets = Targets(jnp.zeros((T, 3), joints.dtype), jnp.zeros((T, 15, 3), joints.dtype), jnp.zeros(10, joints.dtype),
                         joints[:, 0], joints, emitted)  # fmt: skip
    return jnp.where(left, mirror_targets(as_targets, rig.T_rig_cams).joints, joints), emitted


def triangulation_baseline(
    windows: list[Window],
    data_cfg: DataConfig,
    *,
    prior_depth_m: float,
    view_dropped: int | None = None,
) -> tuple[Float[Array, "N T 21 3"], Bool[Array, "N T"]]:
    """The triangulation baseline's joints on each window (module docstring).

    Args:
        windows: the held-out windows (as `evaluate_windows` scores them); `data_cfg`
            gives their length.
        prior_depth_m: the depth (m, camera z) of a joint seen by one view only: the
            training set's mean joint depth (`mean_joint_depth`).
        view_dropped: 0 or 1, that view (of the window's frame) blanked in every frame.
    Returns:
        joints: rig-frame joints (m) in the frame of each window's targets.
        emitted: frames with an observed keypoint in some view.
    Score them with `train.validation.score_predictions(joints, emitted, windows, data_cfg,
    view_dropped=view_dropped)`: the same condition for the gate's truth.
    """
    if view_dropped not in (None, 0, 1):
        raise ValueError(f"view_dropped must be None, 0 (left) or 1 (right), got {view_dropped!r}")
    dtype = jnp.result_type(float)
    joints, emitted = [], []
    for window in windows:
        rig, keypoints = _hand_keypoints(window.clip, window.side)
        frames = slice(window.start, window.start + data_cfg.frames)
        if keypoints["uv"].shape[1] < frames.stop:
            raise clips.ClipFormatError(f"{window.clip}: the {window.side} hand has {keypoints['uv'].shape[1]} frames of keypoints, "
                                        f"the window needs {frames.stop}")  # fmt: skip
        uv, conf, box, box_score = (jnp.asarray(keypoints[k][:, frames], dtype) for k in ("uv", "conf", "box", "box_score"))
        left = window.side == "left"
        if view_dropped is not None:
            conf = drop_view_keypoints(conf, 1 - view_dropped if left else view_dropped)  # a left hand's views are swapped
        j, e = _window_joints(rig, uv, conf, box, box_score, jnp.asarray(prior_depth_m, dtype), jnp.asarray(left))
        joints.append(j)
        emitted.append(e)
    return jnp.stack(joints), jnp.stack(emitted)


@eqx.filter_jit
def _seen_depths(clip: ClipInput, targets: Targets, crop_size: int) -> tuple[Float[Array, ""], Float[Array, ""]]:
    """Sum and count of the target joints' depths (camera z, m) over the views whose crop
    they project into, in frames with a target."""
    T_cams_rig = jnp.linalg.inv(clip.T_rig_cams)
    depth = jax.vmap(lambda T: apply_transform(T, targets.joints)[..., 2])(T_cams_rig)  # (2, T, 21)
    _, _, inside = crop_projections(clip, targets.joints, crop_size)
    seen = jnp.moveaxis(inside & clip.view_present[..., None] & targets.valid[:, None, None], 1, 0)
    return jnp.sum(jnp.where(seen, depth, 0.0)), jnp.sum(seen).astype(depth.dtype)


def mean_joint_depth(windows: list[Window], data_cfg: DataConfig) -> float:
    """The training windows' mean joint depth (m): the camera z of every target joint in
    each view whose crop it projects into (present views, frames with a target), the
    prior `triangulation_baseline` places single-view joints at. A frame in two
    overlapping windows counts twice."""
    total = count = 0.0
    for window in windows:
        clip, targets = load_example(window, data_cfg)
        s, n = _seen_depths(clip, targets, data_cfg.crop_size)
        total, count = total + float(s), count + float(n)
    if count == 0:
        raise ValueError("no target joint projects into a crop of the given windows: pass the training windows (build_index)")
    return total / count


__all__ = ["mean_joint_depth", "triangulation_baseline"]
