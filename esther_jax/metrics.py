"""Accuracy metrics, temporal jitter with on-screen gating, aggregation, bootstrap,
and the depth-scatter decomposition (paper section 5 and appendices J, L).

Every function names its variant. Inputs are metres (joints in the 21-keypoint order of
docs/architecture.md) and results are metres (or m/s^2 for jitter); per-frame functions take
one frame and vmap over sequences; optional masks mark valid joints or frames.

- `mpjpe`: absolute mean per-joint position error in the camera/rig frame, no alignment.
- `p_mpjpe`: wrist-relative: both skeletons translated so their wrists (keypoint 0)
  coincide, error averaged over all 21 joints (the wrist contributes zero), as the
  paper's headline P-MPJPE.
- `pa_mpjpe`: similarity Procrustes (Umeyama: rotation with det = +1, i.e. no
  reflection, isotropic scale and translation) of the *prediction onto the ground
  truth*, then MPJPE over all 21 joints (HMR/HaMeR variant; FreiHAND's
  `orthogonal_procrustes` would allow reflections).
- `wrist_error`: distance between the wrists (keypoint 0); `wrist_axes` breaks wrist
  errors down per axis and along / across the line of sight.
- `jitter`: appendix L exactly: mean over valid triplets of the 21-joint mean of
  ||S_{t-1} - 2 S_t + S_{t+1}|| times fps^2; a triplet counts only if its three frames
  are on-screen, so nothing is formed across an off-screen frame.

A masked mean over no valid element is "no data", not NaN: the `Score` it returns has
`count == 0` (and value 0), and aggregation skips it.
"""

import dataclasses
import math

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Bool, Float, PRNGKeyArray

from ._math import eps, safe_norm, safe_normalize
from .cameras import StereoRig

METRIC_LABELS = {
    "p_mpjpe": ("P-MPJPE", "mm"),
    "pa_mpjpe": ("PA-MPJPE", "mm"),
    "wrist": ("Wrist", "mm"),
    "jitter": ("Jitter", "m/s^2"),
    "mpjpe": ("MPJPE", "mm"),
    "gt_jitter": ("GT jitter", "m/s^2"),
}
"""Display name and reported unit of each metric (tables, figures, learning curves)."""

PCK_MAX_THRESHOLD_M = 0.05
PCK_NUM_THRESHOLDS = 101


class Score(eqx.Module):
    """A masked mean and how many elements it averaged (0 means "no data")."""

    value: Float[Array, "*batch"]
    """The mean (0 when count is 0)."""
    count: Float[Array, "*batch"]
    """Number of valid elements averaged (joints, frames, triplets or clips)."""

    @property
    def has_data(self) -> Bool[Array, "*batch"]:
        return self.count > 0


def _masked_mean(values: Float[Array, "*batch n"], mask: Bool[Array, "*batch n"] | None) -> Score:
    if mask is None:
        mask = jnp.ones(values.shape, bool)
    m = mask.astype(values.dtype)
    count = jnp.sum(m, axis=-1)
    safe = jnp.where(mask, values, 0.0)
    return Score(value=jnp.sum(safe, axis=-1) / jnp.maximum(count, 1.0), count=count)


def _check_pair(pred: Array, gt: Array) -> None:
    if pred.shape != gt.shape or pred.ndim != 2 or pred.shape[-1] != 3:
        raise ValueError(f"pred and gt must be one frame of (joints, 3) points; got {pred.shape} and {gt.shape}")


def joint_errors(pred: Float[Array, "joints 3"], gt: Float[Array, "joints 3"]) -> Float[Array, "joints"]:
    """Euclidean distance of each joint (metres)."""
    _check_pair(pred, gt)
    return safe_norm(pred - gt)


def mpjpe(pred: Float[Array, "joints 3"], gt: Float[Array, "joints 3"], mask: Bool[Array, "joints"] | None = None) -> Float[Array, ""]:
    """Absolute MPJPE (metres), no alignment; masked joints are ignored."""
    return _masked_mean(joint_errors(pred, gt), mask).value


def _wrist_relative(points: Float[Array, "joints 3"]) -> Float[Array, "joints 3"]:
    return points - points[0:1]


def p_mpjpe(pred: Float[Array, "joints 3"], gt: Float[Array, "joints 3"], mask: Bool[Array, "joints"] | None = None) -> Float[Array, ""]:
    """Wrist-relative MPJPE (metres): wrists (keypoint 0) aligned by translation."""
    return mpjpe(_wrist_relative(pred), _wrist_relative(gt), mask)


def _safe_sqrt(x: Float[Array, "*batch"]) -> Float[Array, "*batch"]:
    """`sqrt(x)` for x >= 0, with a zero (not infinite) derivative at 0 (double where)."""
    positive = x > jnp.finfo(x.dtype).tiny
    return jnp.where(positive, jnp.sqrt(jnp.where(positive, x, 1.0)), 0.0)


def _umeyama_svd(cov: Float[Array, "3 3"]):
    U, S, Vt = jnp.linalg.svd(cov)
    sign = jnp.sign(jnp.linalg.det(U @ Vt))
    sign = jnp.where(sign == 0, 1.0, sign)
    D = jnp.asarray([1.0, 1.0, 0.0], cov.dtype) + jnp.asarray([0.0, 0.0, 1.0], cov.dtype) * sign
    return U, S, Vt, D


@jax.custom_jvp
def _umeyama_rotation(cov: Float[Array, "3 3"]) -> tuple[Float[Array, "3 3"], Float[Array, ""]]:
    """The rotation `R = U D V^T` (det +1) maximising `tr(R^T cov)`, and that maximum
    `sum(D S)` (Umeyama 1991, eqs. 39-40)."""
    U, S, Vt, D = _umeyama_svd(cov)
    return (U * D[None]) @ Vt, jnp.sum(S * D)


@_umeyama_rotation.defjvp
def _umeyama_rotation_jvp(primals, tangents):
    """Derivative of the polar factor, not of the SVD: differentiating `jnp.linalg.svd`
    divides by `s_i^2 - s_j^2`, which is NaN whenever two singular values coincide (all
    joints masked or identical: cov = 0; two joints: rank 1), although R's derivative
    only has `s~_i + s~_j` (signed singular values s~ = D S) in its denominators. With
    `cov = R P` (P symmetric) and `A = D U^T dcov V`: `dR = U D Omega V^T`,
    `Omega_ij = (A_ij - A_ji) / (s~_i + s~_j)`, and `d sum(D S) = sum(R * dcov)`.
    Where `s~_i + s~_j` vanishes, R is not unique but the aligned points do not depend
    on that freedom; Omega_ij = 0 there keeps values and gradients finite."""
    (cov,), (dcov,) = primals, tangents
    U, S, Vt, D = _umeyama_svd(cov)
    R = (U * D[None]) @ Vt
    A = D[:, None] * (U.T @ dcov @ Vt.T)
    signed = D * S
    den = signed[:, None] + signed[None, :]
    ok = jnp.abs(den) > eps(cov) * S[0] + jnp.finfo(cov.dtype).tiny
    omega = jnp.where(ok, (A - A.T) / jnp.where(ok, den, 1.0), 0.0)
    return (R, jnp.sum(S * D)), ((U * D[None]) @ omega @ Vt, jnp.sum(R * dcov))


@eqx.filter_jit  # one program when called eagerly (docs/architecture.md, conventions)
def procrustes_align(
    pred: Float[Array, "joints 3"], gt: Float[Array, "joints 3"], mask: Bool[Array, "joints"] | None = None
) -> Float[Array, "joints 3"]:
    """`s R pred + t` that best fits `gt` in least squares (Umeyama 1991), det R = +1.

    Only masked-in joints enter the fit; all joints are transformed. When the masked-in
    predicted joints have no spread (none masked in, or all at one point up to rounding)
    the fit degenerates to scale 0: every joint maps to the gt centroid. Values and
    gradients are finite in every case (see `_umeyama_rotation`).
    """
    _check_pair(pred, gt)
    w = jnp.ones(pred.shape[:1], pred.dtype) if mask is None else mask.astype(pred.dtype)
    total = jnp.maximum(jnp.sum(w), 1.0)
    mu_p = jnp.sum(w[:, None] * pred, axis=0) / total
    mu_g = jnp.sum(w[:, None] * gt, axis=0) / total
    p = pred - mu_p[None]
    g = gt - mu_g[None]
    cov = jnp.einsum("n,ni,nj->ij", w, g, p) / total  # Sigma_gp
    R, trace = _umeyama_rotation(cov)
    var_p = jnp.sum(w * jnp.sum(p * p, axis=-1)) / total
    # No spread: the centroid's rounding error (a few eps of |pred| per joint) is all
    # that is left of p; dividing by it would amplify noise (double where: finite grads).
    size2 = jnp.sum(w * jnp.sum(pred * pred, axis=-1)) / total
    spread = var_p > (pred.shape[0] * eps(pred)) ** 2 * size2 + jnp.finfo(pred.dtype).tiny
    scale = jnp.where(spread, trace / jnp.where(spread, var_p, 1.0), 0.0)
    return scale * p @ R.T + mu_g[None]


@eqx.filter_jit
def pa_mpjpe(pred: Float[Array, "joints 3"], gt: Float[Array, "joints 3"], mask: Bool[Array, "joints"] | None = None) -> Float[Array, ""]:
    """Procrustes-aligned MPJPE (metres): similarity transform of pred onto gt, no reflection."""
    return mpjpe(procrustes_align(pred, gt, mask), gt, mask)


def wrist_error(pred: Float[Array, "joints 3"], gt: Float[Array, "joints 3"]) -> Float[Array, ""]:
    """Distance between the predicted and true wrist (keypoint 0), metres."""
    _check_pair(pred, gt)
    return safe_norm(pred[0] - gt[0])


def pck(errors: Float[Array, "joints"], threshold: float | Float[Array, ""], mask: Bool[Array, "joints"] | None = None) -> Float[Array, ""]:
    """Fraction of (masked-in) joints whose error is at most `threshold` (metres)."""
    return _masked_mean((errors <= threshold).astype(errors.dtype), mask).value


def pck_curve(
    errors: Float[Array, "joints"], mask: Bool[Array, "joints"] | None = None, *, max_threshold: float = PCK_MAX_THRESHOLD_M,
    num: int = PCK_NUM_THRESHOLDS,
) -> tuple[Float[Array, "thresholds"], Float[Array, "thresholds"]]:  # fmt: skip
    """Thresholds `linspace(0, max, num)` (metres) and the PCK at each."""
    thresholds = jnp.linspace(0.0, max_threshold, num, dtype=errors.dtype)
    return thresholds, jax.vmap(lambda t: pck(errors, t, mask))(thresholds)


def pck_auc(
    errors: Float[Array, "joints"], mask: Bool[Array, "joints"] | None = None, *, max_threshold: float = PCK_MAX_THRESHOLD_M,
    num: int = PCK_NUM_THRESHOLDS,
) -> Float[Array, ""]:  # fmt: skip
    """Area under the PCK curve over [0, max_threshold], normalised to [0, 1] (trapezoid rule)."""
    thresholds, curve = pck_curve(errors, mask, max_threshold=max_threshold, num=num)
    return jnp.sum(0.5 * (curve[1:] + curve[:-1]) * jnp.diff(thresholds)) / max_threshold


def jitter(joints: Float[Array, "time joints 3"], onscreen: Bool[Array, "time"], fps: float | Float[Array, ""]) -> Score:
    """Appendix L jitter (m/s^2): mean over triplets (t-1, t, t+1) with all three frames
    on-screen of mean_j ||S_{t-1} - 2 S_t + S_{t+1}|| * fps^2. `count` is the number
    of triplets used; a sequence with none is "no data"."""
    if joints.ndim != 3 or joints.shape[-1] != 3 or onscreen.shape != joints.shape[:1]:
        raise ValueError(f"jitter takes joints (T, J, 3) and onscreen (T,); got {joints.shape} and {onscreen.shape}")
    second = joints[:-2] - 2.0 * joints[1:-1] + joints[2:]
    per_triplet = jnp.mean(safe_norm(second), axis=-1) * fps**2
    ok = onscreen[:-2] & onscreen[1:-1] & onscreen[2:]
    ok = ok & jnp.isfinite(per_triplet)
    return _masked_mean(jnp.where(ok, per_triplet, 0.0), ok)


def onscreen(joints_rig: Float[Array, "joints 3"], rig: StereoRig, min_fraction: float = 0.5) -> Bool[Array, ""]:
    """Appendix L rule: at least half of the joints project inside the image (and the
    cameras' valid field of view) in at least one eye. Joints are in the rig (left) frame."""
    need = math.ceil(min_fraction * joints_rig.shape[0])
    per_view = jnp.sum(rig.is_visible(joints_rig).astype(jnp.int32), axis=-1)  # (2,) joints visible per view
    return jnp.any(per_view >= need)


class GateScores(eqx.Module):
    """Precision, recall and F1 of a predicted on-screen gate against the truth.

    With no predicted (true) positives, precision (recall) is 1: there was nothing to
    get wrong. The counts are kept so scores can be pooled over clips."""

    precision: Float[Array, ""]
    recall: Float[Array, ""]
    f1: Float[Array, ""]
    true_positives: Float[Array, ""]
    false_positives: Float[Array, ""]
    false_negatives: Float[Array, ""]


def gate_scores(predicted: Bool[Array, "frames"], truth: Bool[Array, "frames"]) -> GateScores:
    dtype = jnp.result_type(float)
    tp = jnp.sum((predicted & truth).astype(dtype))
    fp = jnp.sum((predicted & ~truth).astype(dtype))
    fn = jnp.sum((~predicted & truth).astype(dtype))
    return pooled_gate_scores(tp, fp, fn)


def pooled_gate_scores(true_positives: Float[Array, "*n"], false_positives: Float[Array, "*n"], false_negatives: Float[Array, "*n"]) -> GateScores:
    """Precision, recall and F1 of counts summed over every clip (`GateScores`'s counts)."""
    tp, fp, fn = (jnp.sum(jnp.asarray(x, jnp.result_type(float))) for x in (true_positives, false_positives, false_negatives))
    precision = jnp.where(tp + fp > 0, tp / jnp.maximum(tp + fp, 1.0), 1.0)
    recall = jnp.where(tp + fn > 0, tp / jnp.maximum(tp + fn, 1.0), 1.0)
    f1 = jnp.where(precision + recall > 0, 2 * precision * recall / jnp.maximum(precision + recall, 1e-12), 0.0)
    return GateScores(precision, recall, f1, tp, fp, fn)


class DepthScatter(eqx.Module):
    """Section 5.4: fit z_pred = a z_gt + b, and split the error into the part the linear
    fit removes (systematic) and what remains (random)."""

    slope: Float[Array, ""]
    intercept: Float[Array, ""]
    """Metres."""
    correlation: Float[Array, ""]
    systematic_mm: Float[Array, ""]
    """RMS of (a z_gt + b) - z_gt: error a single linear correction would remove (mm)."""
    random_mm: Float[Array, ""]
    """RMS of the residual z_pred - (a z_gt + b) about the fit: irreducible scatter (mm)."""
    rmse_mm: Float[Array, ""]
    """RMS of z_pred - z_gt (mm)."""
    count: Float[Array, ""]


def depth_scatter(
    z_pred: Float[Array, "n"], z_gt: Float[Array, "n"], mask: Bool[Array, "n"] | None = None, weights: Float[Array, "n"] | None = None
) -> DepthScatter:
    """Least-squares line, correlation and the systematic / random decomposition of the
    samples in `mask`, each counted `weights` times (e.g. how often a bootstrap resample
    draws it; `count` is then the weighted number)."""
    if mask is None:
        mask = jnp.ones(z_pred.shape, bool)
    mask = mask & jnp.isfinite(z_pred) & jnp.isfinite(z_gt)
    w = mask.astype(z_pred.dtype) if weights is None else jnp.where(mask, weights, 0.0).astype(z_pred.dtype)
    n = jnp.sum(w)
    safe_n = jnp.maximum(n, 1.0)
    zp = jnp.where(mask, z_pred, 0.0)
    zg = jnp.where(mask, z_gt, 0.0)
    mean_p, mean_g = jnp.sum(w * zp) / safe_n, jnp.sum(w * zg) / safe_n
    dp, dg = zp - mean_p, zg - mean_g
    var_g, var_p, cov = jnp.sum(w * dg * dg) / safe_n, jnp.sum(w * dp * dp) / safe_n, jnp.sum(w * dp * dg) / safe_n
    # Without spread in z_gt (or z_pred) the slope (correlation) is 0 with a zero
    # gradient, not d(cov) / tiny (double where).
    tiny = jnp.finfo(z_pred.dtype).tiny
    has_var_g = var_g > tiny
    slope = jnp.where(has_var_g, cov / jnp.where(has_var_g, var_g, 1.0), 0.0)
    intercept = mean_p - slope * mean_g
    sd_gp = _safe_sqrt(var_g * var_p)
    has_sd = sd_gp > tiny
    correlation = jnp.where(has_sd, cov / jnp.where(has_sd, sd_gp, 1.0), 0.0)
    fit = slope * zg + intercept
    rms = lambda x: _safe_sqrt(jnp.sum(w * x * x) / safe_n) * 1000.0  # noqa: E731  (finite gradient at 0 error)
    return DepthScatter(
        slope=slope, intercept=intercept, correlation=correlation,
        systematic_mm=rms(fit - zg), random_mm=rms(zp - fit), rmse_mm=rms(zp - zg), count=n,
    )  # fmt: skip


class WristAxes(eqx.Module):
    """Where wrist errors lie: per axis of the frame (x, y, z) and along / across the
    line of sight from the frame's origin to the true wrist (millimetres)."""

    mae_mm: Float[Array, "3"]
    """Mean absolute error per axis."""
    correlation: Float[Array, "3"]
    """Per axis, the correlation of the predicted with the true coordinate."""
    pred_sd_mm: Float[Array, "3"]
    """Per axis, the spread (standard deviation) of the predicted coordinate."""
    true_sd_mm: Float[Array, "3"]
    along_mm: Float[Array, ""]
    """Mean |e . u|, with e the error and u the unit direction to the true wrist: range error."""
    across_mm: Float[Array, ""]
    """Mean |e - (e . u) u|: the error across the line of sight."""


def wrist_axes(pred: Float[Array, "n 3"], truth: Float[Array, "n 3"]) -> WristAxes:
    """How predicted wrists (or any points, metres, one row per frame) miss the true ones,
    per axis of their frame and along / across the line of sight from its origin (the
    rig frame's: the left camera). A coordinate a network has not learned shows as a
    correlation near 0 and a predicted spread far below the truth's (`pred_sd_mm`)."""
    if pred.shape != truth.shape or pred.ndim != 2 or pred.shape[-1] != 3:
        raise ValueError(f"pred and truth must be (n, 3) points; got {pred.shape} and {truth.shape}")
    if pred.shape[0] == 0:
        raise ValueError("no wrists to compare (n = 0): every frame was masked out")
    err = pred - truth
    sight = safe_normalize(truth)
    along = jnp.sum(err * sight, axis=-1)
    per_axis = jax.vmap(depth_scatter, in_axes=(1, 1))(pred, truth)
    return WristAxes(
        mae_mm=1000.0 * jnp.mean(jnp.abs(err), axis=0), correlation=per_axis.correlation,
        pred_sd_mm=1000.0 * jnp.std(pred, axis=0), true_sd_mm=1000.0 * jnp.std(truth, axis=0),
        along_mm=1000.0 * jnp.mean(jnp.abs(along)), across_mm=1000.0 * jnp.mean(safe_norm(err - along[:, None] * sight)),
    )  # fmt: skip


# ----------------------------------------------------------------------------- aggregation


def clip_mean(values: Float[Array, "frames"], valid: Bool[Array, "frames"]) -> Score:
    """Per-frame values -> the clip's mean over its valid frames (frame-weighted)."""
    return _masked_mean(jnp.where(valid, values, 0.0), valid & jnp.isfinite(values))


def dataset_mean(clips: Score, weighting: str = "clip") -> Score:
    """Clip scores (stacked, shape (C,)) -> one dataset score.

    `weighting="clip"`: every clip with data counts once (per-clip means, then their
    mean: the paper's and the bootstrap's unit); `"frame"`: clips weighted by their
    number of valid frames (HOT3D's hand_tracking_toolkit convention).
    """
    has = clips.count > 0
    if weighting == "clip":
        return _masked_mean(clips.value, has)
    if weighting == "frame":
        total = jnp.sum(clips.count)
        return Score(value=jnp.sum(clips.value * clips.count) / jnp.maximum(total, 1.0), count=total)
    raise ValueError(f"weighting must be 'clip' or 'frame', got {weighting!r}")


@dataclasses.dataclass(frozen=True)
class Bootstrap:
    """Appendix J statistics of a mean over clips."""

    mean: float
    std: float
    ci_low: float
    ci_high: float
    num_clips: int
    num_resamples: int

    def overlaps(self, other: "Bootstrap") -> bool:
        """Whether the two 95% intervals overlap (no overlap: a significant gap)."""
        return not (self.ci_high < other.ci_low or other.ci_high < self.ci_low)


def bootstrap(scores, key: PRNGKeyArray, n: int = 2000, *, mask=None, level: float = 0.95) -> Bootstrap | None:
    """Resample per-clip scores with replacement `n` times (appendix J: 2000).

    Returns the mean of the scores, the standard deviation of the resampled means and
    the percentile interval at `level`, or None when no clip has data. Reproducible
    from `key`. `mask` (or NaN scores) drops clips without data before resampling.
    One clip has no spread to resample: its std and interval are NaN (unknown), not 0.
    """
    values = np.asarray(scores, dtype=np.float64).reshape(-1)
    keep = np.isfinite(values) if mask is None else (np.asarray(mask, bool).reshape(-1) & np.isfinite(values))
    values = values[keep]
    if values.size == 0:
        return None
    if values.size == 1:
        return Bootstrap(float(values[0]), math.nan, math.nan, math.nan, 1, n)
    idx = jax.random.randint(key, (n, values.size), 0, values.size)
    means = values[np.asarray(idx)].mean(axis=1)
    lo, hi = np.quantile(means, [(1 - level) / 2, 1 - (1 - level) / 2])
    return Bootstrap(float(values.mean()), float(means.std(ddof=1)), float(lo), float(hi), int(values.size), n)


def intervals_overlap(a: Bootstrap, b: Bootstrap) -> bool:
    """Whether two methods' bootstrap intervals overlap."""
    return a.overlaps(b)
