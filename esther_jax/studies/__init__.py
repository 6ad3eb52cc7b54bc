"""The paper's studies as library runners: data, trained models, conditions, statistics
and reports. The notebooks under `notebooks/` are thin scripts over these functions.

The package stands above every other (the apps' floor, beside the CLI and the demo): a
study trains (`esther_jax.train`), labels (`fitting`), synthesizes (`esther_jax.data`)
and scores (`esther_jax.eval`), and nothing below imports it. Its modules beside the
runners here: `attention` (the cross-view attention probe of figure 7), `baselines`
(the triangulation baseline of table 2), `teacher_validation` (the teacher against
exact ground truth, appendices I and N) and `data_engine` (the engine's rounds measured
on a raw collection whose ground truth is held aside).

- **Scale** (`StudyScale`, `scale_from_env`): `smoke` (untrained `cpu-tiny` networks on
  a few tiny clips: every study's pipeline and report in seconds, what the tests execute;
  training itself is tested with `esther_jax.train`) or `full` (`cpu-small`, the two
  training stages of the learning benchmark, a few hundred held-out windows), chosen by
  `ESTHER_STUDY_SCALE`.
- **Data and models** (`dataset`, `trained`): synthetic clip folders and trained networks
  under one root (`ESTHER_STUDY_ROOT`, default `~/.cache/esther_jax/studies/<scale>-engine<N>`,
  N the synthetic engine's `ENGINE_REVISION`: networks trained on another revision's clips
  are never reused),
  made on first use and reused by every study: the studies share the held-out clips and
  the models they compare (the same network is scored in the view-drop, frame-drop,
  corruption and gate studies). Both resume after an interruption (`synth.synthesize`,
  `train.train_stages`).
- **Statistics**: `depth_binding` (section "Why the Monocular Fallback Stays Reliable":
  the fit z_hat = a z + b of the predicted wrist depth, its correlation and
  random/systematic scatter, appendix-J bootstrap intervals over windows),
  `attention_shares` (its figure 7: cross-view attention into the kept view on the hand),
  `gate_stress_test` (appendix L), `condition_table` (a network under named conditions,
  with intervals), `separated` (non-overlap of two bootstrap intervals), `reproduces`
  (a retrained network within the first one's intervals) and `earlier_rows` (the rows of
  an earlier report kept when this run reproduces its reference row).
- **Reports** (`write_report`): `<out>/<study>.json` (every number, the scale, the
  command, the wall time) and `<out>/<study>.md` (verdict paragraph first, then tables and
  figures), written atomically.

Depths are the z of the wrist in the reference camera's frame (the rig frame: the left
camera; the right camera for a left hand, which the network sees mirrored), metres.
"""

import dataclasses
import json
import os
import pathlib
import sys

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Bool, Float

from .. import metrics
from .. import model as M
from ..clips import list_clips
from ..data import motion, synth
from ..eval.reports import Record
from ..files import atomic_output, git_revision, read_json, strict_json, write_json
from ..train import data as data_lib
from ..train import train_stages
from ..train.validation import drop_view, evaluate_windows, predict_windows, score_predictions
from .attention import HandAttention, attention_map, attention_on_hand, hand_patch_mask

SCALE_ENV = "ESTHER_STUDY_SCALE"
ROOT_ENV = "ESTHER_STUDY_ROOT"
OUT_ENV = "ESTHER_STUDY_OUT"
ABLATION_ROWS_ENV = "ESTHER_ABLATION_ROWS"
"""Study 07's table-5 rows to train and score next to the full model (comma-separated; unset: all)."""


@dataclasses.dataclass(frozen=True)
class StudyScale:
    """How big a study runs: the network, its data and its training budget."""

    name: str
    model: str
    """A key of `model.CONFIGS`."""
    train_clips: int
    heldout_clips: int
    clip_frames: int
    stage1_steps: int
    stage2_steps: int
    batch: int
    learning_rate: float
    windows: int | None
    """Held-out windows scored per condition (None: every non-overlapping window)."""
    resamples: int
    """Bootstrap resamples (appendix J: 2000)."""


SCALES: dict[str, StudyScale] = {
    "smoke": StudyScale("smoke", "cpu-tiny", train_clips=2, heldout_clips=2, clip_frames=16, stage1_steps=0, stage2_steps=0,
                        batch=2, learning_rate=5e-4, windows=4, resamples=200),
    "full": StudyScale("full", "cpu-small", train_clips=240, heldout_clips=24, clip_frames=64, stage1_steps=400, stage2_steps=1200,
                       batch=8, learning_rate=5e-4, windows=None, resamples=2000),
}  # fmt: skip

TRAIN_SEED, HELDOUT_SEED, WIDE_SEED = 1, 1001, 2001
WIDE_MOTION = motion.MotionConfig(depth_range_m=(0.1, 1.1), depth_sampling="uniform", shape_sd=2.0)
"""Held-out clips past the training distribution: wrist paths drawn uniformly from 0.10 to
1.10 m (training: the egocentric sampler's, about 0.2 to 0.7 m) and hand shapes drawn
with twice the spread of the training hands (betas of standard deviation 2)."""


def scale_from_env(default: str = "smoke") -> StudyScale:
    """The scale named by `ESTHER_STUDY_SCALE` (smoke or full)."""
    name = os.environ.get(SCALE_ENV, default)
    if name not in SCALES:
        raise ValueError(f"{SCALE_ENV}={name!r}: choose one of {sorted(SCALES)}")
    return SCALES[name]


def study_root(scale: StudyScale) -> pathlib.Path:
    """Where the studies of this scale keep their clips and trained models."""
    root = os.environ.get(ROOT_ENV) or pathlib.Path.home() / ".cache" / "esther_jax" / "studies" / f"{scale.name}-engine{synth.ENGINE_REVISION}"
    return pathlib.Path(root)


def report_dir(scale: StudyScale) -> pathlib.Path:
    """Where reports go: `ESTHER_STUDY_OUT`, else, at the full scale run from a checkout
    of esther-jax, its `docs/studies` (the committed reports), and `<root>/reports`
    otherwise (the smoke scale never touches the committed reports)."""
    if os.environ.get(OUT_ENV):
        return pathlib.Path(os.environ[OUT_ENV])
    checkout = pathlib.Path(__file__).resolve().parents[2]
    if scale.name == "full" and (checkout / "pyproject.toml").is_file() and (checkout / "docs").is_dir():
        return checkout / "docs" / "studies"
    return study_root(scale) / "reports"


def model_config(scale: StudyScale, variant: str = "esther") -> M.ModelConfig:
    """The scale's network, or one of its `model.ABLATIONS` rows ('esther': the full model)."""
    return M.config(scale.model, ablation=None if variant == "esther" else variant)


def data_config(scale: StudyScale, *, held_out: bool = False) -> data_lib.DataConfig:
    """Windows of the network's length; held-out windows do not overlap."""
    cfg = model_config(scale)
    return data_lib.DataConfig(frames=cfg.num_frames, crop_size=cfg.crop_size, stride=cfg.num_frames if held_out else 8)


DATASETS = ("train", "heldout", "heldout_wide")


def dataset(
    scale: StudyScale, name: str, *, rig: str = "esther", crop_strategy: str = "offbb120", count: int | None = None, progress: bool = True
) -> list[pathlib.Path]:
    """The clip folders of a study dataset, synthesized on first use (resumable):
    'train', 'heldout' (the training distribution, other seeds) or 'heldout_wide'
    (`WIDE_MOTION`); another `rig` or crop `crop_strategy` makes a separate folder of
    the same motions (same seed). `count` asks for only the dataset's first clips (the
    same clips: clip i depends only on the seed and i), making no more than those."""
    if name not in DATASETS:
        raise ValueError(f"unknown study dataset {name!r}; choose one of {DATASETS}")
    full = scale.train_clips if name == "train" else scale.heldout_clips
    if count is not None and not 0 < count <= full:
        raise ValueError(f"the {scale.name} studies' {name} dataset has {full} clips; asked for the first {count}")
    count = full if count is None else count
    seed = {"train": TRAIN_SEED, "heldout": HELDOUT_SEED, "heldout_wide": WIDE_SEED}[name]
    cfg = synth.SynthConfig(num_frames=scale.clip_frames, rig=rig, crops=True, crop_size=model_config(scale).crop_size,
                            crop_strategy=crop_strategy, motion_config=WIDE_MOTION if name == "heldout_wide" else motion.MotionConfig())  # fmt: skip
    folder = name if (rig, crop_strategy) == ("esther", "offbb120") else f"{name}_{rig}_{crop_strategy}"
    out = study_root(scale) / "data" / folder
    synth.synthesize(out, count, cfg, seed=seed, progress=progress)
    return list_clips(out)[:count]


def trained(scale: StudyScale, variant: str = "esther", *, progress: bool = True) -> M.ESTHER:
    """The scale's network (or ablation row `variant`) trained on the 'train' dataset by
    the two stages (`train.train_stages`), validated on 'heldout'; trained once under
    `<root>/runs/<variant>` and loaded from there afterwards. A scale without training
    steps (smoke) gives the network as initialised from seed 0."""
    cfg = model_config(scale, variant)
    if scale.stage1_steps == scale.stage2_steps == 0:  # the smoke scale: the network as initialised from the seed
        return M.ESTHER(cfg, key=jax.random.key(0))
    final = train_stages(study_root(scale) / "runs" / variant, dataset(scale, "train", progress=progress), cfg,
                         stage1_steps=scale.stage1_steps, stage2_steps=scale.stage2_steps, batch=scale.batch,
                         learning_rate=scale.learning_rate, val_dirs=dataset(scale, "heldout", progress=progress), progress=progress)  # fmt: skip
    net = M.load(final)
    if net.config != cfg:
        raise ValueError(f"{final} holds a {net.config.name} network, not {cfg.name}: remove it or use another {ROOT_ENV}")
    return net


def trained_at(scale: StudyScale, variant: str = "esther") -> str | None:
    """The git revision that trained the scale's network `variant` (`trained`): the one its
    last training stage recorded (`config.json` of `<root>/runs/<variant>/stage2`, else
    `stage1`); the current revision at a scale that does not train; None before training."""
    if scale.stage1_steps == scale.stage2_steps == 0:
        return git_revision()
    for stage in ("stage2", "stage1"):
        record = study_root(scale) / "runs" / variant / stage / "config.json"
        if record.is_file():
            return read_json(record).get("git_revision")
    return None


def training_minutes(scale: StudyScale, variant: str = "esther") -> float | None:
    """The minutes the training steps of the scale's network `variant` (`trained`) took,
    both stages: the sum of the logged step intervals of `<root>/runs/<variant>/stage*/metrics.jsonl`
    (each step's `batch / clips_per_s`: the step, its batch's wait, the first step's
    compilation, the validations and checkpoints between steps; not the setup before the
    first step, the last validation or the model's save, nor steps an interruption lost);
    None when no stage has logged a step (not trained under this root)."""
    seconds, found = 0.0, False
    for stage in ("stage1", "stage2"):
        run = study_root(scale) / "runs" / variant / stage
        log = run / "metrics.jsonl"
        if not log.is_file():
            continue
        batch = read_json(run / "config.json")["train"]["batch"]
        for line in log.read_text().splitlines():
            if line.strip():
                seconds += batch / json.loads(line)["clips_per_s"]
                found = True
    return seconds / 60.0 if found else None


def training_windows(scale: StudyScale) -> list[data_lib.Window]:
    """The windows the scale's networks are trained on (the 'train' dataset)."""
    return data_lib.build_index(dataset(scale, "train"), data_config(scale))


def heldout_windows(scale: StudyScale, clip_dirs: list[pathlib.Path]) -> list[data_lib.Window]:
    """The non-overlapping windows of held-out clips, the first `scale.windows` of them
    (spread over the clips: taken in turn from each clip) when the scale limits them."""
    windows = data_lib.build_index(clip_dirs, data_config(scale, held_out=True))
    if scale.windows is None or len(windows) <= scale.windows:
        return windows
    by_clip: dict[str, list] = {}
    for w in windows:
        by_clip.setdefault(w.clip, []).append(w)
    queues, chosen = list(by_clip.values()), []
    while len(chosen) < scale.windows:
        for q in queues:
            if q and len(chosen) < scale.windows:
                chosen.append(q.pop(0))
    return sorted(chosen, key=lambda w: (w.clip, w.side, w.start))


def condition_table(
    net: M.ESTHER, windows: list[data_lib.Window], scale: StudyScale, conditions: dict[str, dict], *, seed: int = 0
) -> dict[str, dict]:
    """`evaluate_windows` of one network under named conditions (its keyword arguments:
    `view_dropped`, `frames_dropped`, `blanked`, `corruption`), with appendix-J intervals."""
    cfg = data_config(scale, held_out=True)
    return {name: evaluate_windows(net, windows, cfg, batch=scale.batch, seed=seed, intervals=True, resamples=scale.resamples, **kw)
            for name, kw in conditions.items()}  # fmt: skip


def no_image(scale: StudyScale) -> dict:
    """The control condition of the robustness studies: every view of every frame blanked
    (absent, not masked), so the network sees no pixel. A metric that does not move under
    a perturbation is robust only if it moves here: otherwise the network ignores the
    images and its invariance says nothing."""
    return {"blanked": jnp.ones(data_config(scale, held_out=True).frames, bool)}


def separated(a: list[float] | None, b: list[float] | None) -> bool | None:
    """Whether two 95% intervals ([low, high]) do not overlap (a significant gap); None
    when either is unknown."""
    if a is None or b is None or any(v is None or not np.isfinite(v) for v in (*a, *b)):
        return None
    return bool(a[1] < b[0] or b[1] < a[0])


REPRODUCED_KEYS = ("mpjpe_mm", "p_mpjpe_mm", "wrist_mm")


def reproduces(now: dict, earlier: dict, keys: tuple[str, ...] = REPRODUCED_KEYS) -> bool:
    """Whether two `condition_table` entries, scorings of what should be the same network
    on the same windows, agree: the same number of windows and, for every key, each one's
    mean inside the other's 95% interval (a retrained network that lands within the
    bootstrap noise of the first one)."""

    def inside(x, span):
        return x is not None and span is not None and None not in span and span[0] <= x <= span[1]

    return now.get("windows") == earlier.get("windows") and all(
        inside(now.get(k), (earlier.get("intervals") or {}).get(k)) and inside(earlier.get(k), (now.get("intervals") or {}).get(k)) for k in keys
    )


def earlier_rows(out: str | pathlib.Path, study: str, scale: StudyScale, reference: str, now: dict) -> tuple[dict[str, dict], dict[str, str | None]]:
    """The rows of an earlier run of `study` (`<out>/<study>.json`, `results["rows"]`) that
    this run may show next to its own, and the revision each was trained at
    (`results["trained_at"]`, else "<that report's revision> or earlier"). Kept only when the earlier
    report is of the same scale and its `reference` row is `reproduced` by this run's
    (`now`): the same network trained again on the same data and budget lands where it
    did, so rows trained then are comparable with rows trained now. Otherwise, or without
    an earlier report, none (and a line says why). This is how a table of trainings of
    an hour each is built over several sittings."""
    path = pathlib.Path(out) / f"{study}.json"
    if not path.is_file():
        return {}, {}
    record = read_json(path)
    rows = (record.get("results") or {}).get("rows") or {}
    if record.get("scale") != dataclasses.asdict(scale) or reference not in rows:
        print(f"{path}: of another scale or without a {reference!r} row; its rows are not kept")
        return {}, {}
    if not reproduces(now, rows[reference]):
        print(f"{path}: its {reference!r} row (MPJPE {rows[reference].get('mpjpe_mm')} mm) is not reproduced by this run's "
              f"({now.get('mpjpe_mm')} mm); its rows are not kept")  # fmt: skip
        return {}, {}
    made = record.get("git_revision")
    trained_at = {r: (record["results"].get("trained_at") or {}).get(r, made and f"{made} or earlier") for r in rows}
    return rows, trained_at


# ----------------------------------------------------------------------------- size-depth binding


def palm_length(joints: Float[Array, "*batch 21 3"]) -> Float[Array, "*batch"]:
    """Wrist to middle-finger MCP (metres): the hand's size, independent of its pose."""
    return jnp.linalg.norm(joints[..., 9, :] - joints[..., 0, :], axis=-1)


@dataclasses.dataclass(frozen=True)
class DepthSamples:
    """Per held-out frame with a target: predicted and true wrist depth (m), the hand's
    palm length (m), and the window it came from."""

    z_pred: np.ndarray
    z_gt: np.ndarray
    palm_m: np.ndarray
    window: np.ndarray


def wrist_depths(net: M.ESTHER, windows: list[data_lib.Window], scale: StudyScale, *, view_dropped: int | None = None) -> DepthSamples:
    """The network's wrist depth against the truth on every held-out frame with a target
    (ungated: the study is about depth, not the gate)."""
    pred = predict_windows(net, windows, data_config(scale, held_out=True), batch=scale.batch, view_dropped=view_dropped)
    valid = np.asarray(pred.targets.valid)
    window = np.broadcast_to(np.arange(valid.shape[0])[:, None], valid.shape)
    z_pred, z_gt = np.asarray(pred.joints[..., 0, 2]), np.asarray(pred.targets.joints[..., 0, 2])
    palm = np.asarray(palm_length(pred.targets.joints))
    return DepthSamples(z_pred[valid], z_gt[valid], palm[valid], window[valid])


@jax.jit
def _resampled_scatter(z_pred: Float[Array, "n"], z_gt: Float[Array, "n"], window: Array, picks: Array) -> Float[Array, "resamples 4"]:
    """(correlation, random mm, systematic mm, slope) of `metrics.depth_scatter` for each
    resample of windows (`picks`: (resamples, W) window indices drawn with replacement;
    every frame of a drawn window counts as often as its window is drawn)."""

    def one(pick):
        fit = metrics.depth_scatter(z_pred, z_gt, weights=jnp.zeros(picks.shape[1], z_pred.dtype).at[pick].add(1.0)[window])
        return jnp.stack([fit.correlation, fit.random_mm, fit.systematic_mm, fit.slope])

    return jax.lax.map(one, picks, batch_size=64)


def depth_binding(samples: DepthSamples, *, mask: np.ndarray | None = None, resamples: int = 2000, seed: int = 0) -> dict:
    """The fit z_hat = a z + b of predicted against true wrist depth on the frames of
    `samples` (those in `mask`): slope a, intercept b (m), correlation, random and
    systematic scatter and RMSE (mm) (`metrics.depth_scatter`), with appendix-J 95%
    intervals of the correlation, the random and systematic scatter and the slope from
    resampling the held-out windows (all frames of a drawn window together)."""
    keep = np.ones(samples.z_gt.shape, bool) if mask is None else np.asarray(mask, bool)
    if keep.sum() < 3:
        return {"frames": int(keep.sum()), "windows": int(np.unique(samples.window[keep]).size)}
    zp, zg, win = samples.z_pred[keep], samples.z_gt[keep], samples.window[keep]
    fit = metrics.depth_scatter(jnp.asarray(zp), jnp.asarray(zg))
    _, dense = np.unique(win, return_inverse=True)
    result = {
        "slope": float(fit.slope), "intercept_m": float(fit.intercept), "correlation": float(fit.correlation),
        "random_mm": float(fit.random_mm), "systematic_mm": float(fit.systematic_mm), "rmse_mm": float(fit.rmse_mm),
        "frames": int(keep.sum()), "windows": int(dense.max() + 1),
    }  # fmt: skip
    if dense.max() >= 1:
        picks = jax.random.randint(jax.random.key(seed), (resamples, dense.max() + 1), 0, dense.max() + 1)
        stats = np.asarray(_resampled_scatter(jnp.asarray(zp), jnp.asarray(zg), jnp.asarray(dense), picks))
        lo, hi = np.quantile(stats, [0.025, 0.975], axis=0)
        result["intervals"] = {k: [float(lo[i]), float(hi[i])] for i, k in enumerate(("correlation", "random_mm", "systematic_mm", "slope"))}
    return result


def training_ranges(scale: StudyScale) -> dict[str, list[float]]:
    """The wrist depths and palm lengths of the training windows' targets, as
    [min, max] (m): what 'inside the training distribution' means in the study."""
    z, palm = [], []
    for w in training_windows(scale):
        _, t = data_lib.load_example(w, data_config(scale))
        valid = np.asarray(t.valid)
        z.append(np.asarray(t.joints[:, 0, 2])[valid])
        palm.append(np.asarray(palm_length(t.joints))[valid])
    z, palm = np.concatenate(z), np.concatenate(palm)
    return {"wrist_depth_m": [float(z.min()), float(z.max())], "palm_m": [float(palm.min()), float(palm.max())]}


def inside(samples: DepthSamples, ranges: dict[str, list[float]]) -> Bool[np.ndarray, "n"]:
    """Frames whose wrist depth and palm length both lie in the training ranges."""
    (z0, z1), (p0, p1) = ranges["wrist_depth_m"], ranges["palm_m"]
    return (samples.z_gt >= z0) & (samples.z_gt <= z1) & (samples.palm_m >= p0) & (samples.palm_m <= p1)


@eqx.filter_jit
def _attention_on_hand(
    net: M.ESTHER, clip: M.ClipInput, joints: Float[Array, "T 21 3"]
) -> tuple[HandAttention, Float[Array, "layers T grid grid"], Bool[Array, "T 2 grid grid"]]:
    mask = hand_patch_mask(clip, joints, crop_size=net.config.crop_size, grid=net.config.grid)
    attention = M.cross_view_attention(net, clip)
    return attention_on_hand(attention, mask, kept_view=0), attention_map(attention, kept_view=0), mask


def attention_shares(
    net: M.ESTHER, windows: list[data_lib.Window], scale: StudyScale, *, view_dropped: int | None = None
) -> tuple[dict, dict]:
    """Figure 7: per stereo block, the share of the cross-view attention into the kept
    view (view 0; drop view 1 for the view-mask model, the monocular model removes it
    itself) that lands on the hand's patches (`studies.attention`), pooled over the frames
    of `windows` with hand patches, beside the uniform-attention share. Returns the
    result ({share: [layers], chance, frames}) and, for the figure, the first window's
    crop of the kept view, its hand mask and the attention maps of its middle frame."""
    cfg = data_config(scale, held_out=True)
    share_sum, chance_sum, frames, example = 0.0, 0.0, 0, None
    for w in windows:
        clip, targets = data_lib.load_example(w, cfg)
        if view_dropped is not None:
            clip = drop_view(clip, view_dropped)
        result, maps, mask = _attention_on_hand(net, clip, targets.joints)
        n = int(result.frames)
        if n:
            share_sum, chance_sum, frames = share_sum + np.asarray(result.share) * n, chance_sum + float(result.chance) * n, frames + n
        if example is None and n:
            t = cfg.frames // 2
            image = None if clip.images is None else np.moveaxis(np.asarray(clip.images[t, 0]), 0, -1)
            example = {"crop": image, "hand_mask": np.asarray(mask[t, 0]), "maps": np.asarray(maps[:, t])}
    if not frames:
        return {"share": None, "chance": None, "frames": 0}, example or {}
    return {"share": (share_sum / frames).tolist(), "chance": chance_sum / frames, "frames": frames}, example


# ----------------------------------------------------------------------------- the gate (appendix L)


def gate_stress_test(net: M.ESTHER, windows: list[data_lib.Window], scale: StudyScale, *, blanked: tuple[int, ...] | None = None) -> dict:
    """Appendix L: the on-screen gate and its effect on jitter, on clean windows and
    under the off-screen stress test that blanks the middle four frames of every window
    (both views absent; `blanked` overrides which frames).

    Per condition: the gate's precision / recall / F1 (pooled over frames; the truth is
    the training label: a target and a joint in a present view's crop, so blanked
    frames are off-screen), and jitter (m/s^2) three ways, each over the frames with a
    target: ungated (every such frame), ground-truth-gated (the truly on-screen ones)
    and prediction-gated (the ones the gate emits). Off-screen recall (blanked frames
    the gate withholds) is reported for the stress test.
    """
    cfg = data_config(scale, held_out=True)
    T = cfg.frames
    blanked = tuple(range(T // 2 - 2, T // 2 + 2)) if blanked is None else blanked
    out: dict = {"blanked_frames": list(blanked)}
    for name, frames in (("clean", ()), ("stress", blanked)):
        mask = jnp.zeros(T, bool).at[jnp.asarray(frames, jnp.int32)].set(True)
        pred = predict_windows(net, windows, cfg, batch=scale.batch, blanked=mask)
        scores = score_predictions(pred.joints, pred.emitted, windows, cfg, keypoints_2d=pred.keypoints_2d, blanked=mask, batch=scale.batch)
        valid, emitted = pred.targets.valid, pred.emitted
        gated = lambda gate: float(metrics.dataset_mean(jax.vmap(metrics.jitter)(pred.joints, gate, pred.fps)).value)  # noqa: E731
        row = {
            "precision": scores["onscreen_precision"], "recall": scores["onscreen_recall"], "f1": scores["onscreen_f1"],
            "jitter": {"ungated": scores["jitter"], "gt_gated": gated(valid & pred.onscreen), "prediction_gated": gated(valid & emitted)},
            "hand_frames": int(jnp.sum(valid)),
        }  # fmt: skip
        if frames:
            off = mask[None, :] & valid
            row["offscreen_recall"] = float(jnp.sum(off & ~emitted) / jnp.maximum(jnp.sum(off), 1))
        out[name] = row
    return out


# ----------------------------------------------------------------------------- reports


def command_line() -> str:
    """How this process was started, with the study's environment variables."""
    env = " ".join(f"{k}={os.environ[k]}" for k in (SCALE_ENV, ROOT_ENV, OUT_ENV, ABLATION_ROWS_ENV) if os.environ.get(k))
    return " ".join(x for x in (env, "python", *sys.argv) if x)


def data_revisions(scale: StudyScale) -> dict[str, int]:
    """The synth engine revision that made each dataset under the scale's study root
    (`<root>/data/<name>/synth.json`): a report made from clips of an earlier revision
    (reused, with a warning, by `dataset`) says so."""
    revisions = {}
    for record in sorted((study_root(scale) / "data").glob("*/synth.json")):
        revisions[record.parent.name] = int(read_json(record).get("engine_revision", 1))
    return revisions


def write_report(
    out: str | pathlib.Path,
    study: str,
    *,
    title: str,
    verdict: str,
    results: dict,
    scale: StudyScale,
    seconds: float,
    sections: list[str] = (),
    figures: list[str | pathlib.Path] = (),
) -> tuple[pathlib.Path, pathlib.Path]:
    """`<out>/<study>.json` (results, scale, command, wall time, revision) and
    `<out>/<study>.md`: the title, the verdict paragraph (does the paper's claim
    reproduce here, and by how much), the Markdown `sections`, the figures (paths
    relative to `out`), then how it was made. Atomic; returns both paths."""
    out = pathlib.Path(out)
    out.mkdir(parents=True, exist_ok=True)
    revisions = data_revisions(scale)
    record = {"study": study, "scale": dataclasses.asdict(scale), "command": command_line(), "seconds": round(seconds, 1),
              "git_revision": git_revision(), "engine_revisions": revisions, "verdict": verdict, "results": results}  # fmt: skip
    json_path = write_json(out / f"{study}.json", strict_json(record))
    figs = "\n".join(f"![{pathlib.Path(f).stem}]({pathlib.Path(f).relative_to(out) if pathlib.Path(f).is_absolute() else f})" for f in figures)
    made = (f"Made by `{record['command']}` at the `{scale.name}` scale ({scale.model}, {scale.train_clips} training clips, "
            f"stages of {scale.stage1_steps} + {scale.stage2_steps} steps at batch {scale.batch}) in {seconds / 60:.1f} min of wall time "
            f"on this machine; revision {record['git_revision'] or 'unknown'}. Every number is in `{study}.json`.")  # fmt: skip
    older = sorted({r for r in revisions.values() if r != synth.ENGINE_REVISION})
    if older:
        made += (f" The study root's clips were made by synth engine revision {', '.join(map(str, older))} "
                 f"({', '.join(f'{k}: {v}' for k, v in revisions.items())}; this library's is {synth.ENGINE_REVISION}), reused as they were: "
                 f"the default study root of this revision makes its own.")  # fmt: skip
    text = "\n\n".join(x for x in (f"# {title}", verdict, *sections, figs, "## How this was made", made) if x) + "\n"
    md_path = out / f"{study}.md"
    with atomic_output(md_path) as tmp:
        pathlib.Path(tmp).write_text(text)
    return json_path, md_path


def table(rows: list[dict], columns: list[tuple[str, str]], *, first: str = "") -> str:
    """A Markdown table: one row per dict (its `first` key names the row), one column per
    (key, header); floats to one decimal (three below 10), None as 'n/a', and an
    `intervals` entry of the row printed under its value as [low, high]."""

    def cell(row, key):
        v = row.get(key)
        if v is None:
            return "n/a"
        if isinstance(v, bool) or not isinstance(v, float):
            return str(v)
        fmt = (lambda x: f"{x:.3f}") if abs(v) < 10 else (lambda x: f"{x:.1f}")  # noqa: E731
        span = (row.get("intervals") or {}).get(key)
        return fmt(v) + (f" [{fmt(span[0])}, {fmt(span[1])}]" if span and None not in span else "")

    head = "| " + " | ".join([first] + [h for _, h in columns]) + " |"
    rule = "|" + "---|" * (len(columns) + 1)
    body = ["| " + " | ".join([str(r.get(first, ""))] + [cell(r, k) for k, _ in columns]) + " |" for r in rows]
    return "\n".join([head, rule, *body])


def dumps(results: dict) -> str:
    """Results as indented strict JSON (what a notebook prints)."""
    return json.dumps(strict_json(results), indent=1)


def records(method: str, results: dict[str, dict]) -> list[Record]:
    """`reports.Record`s of `condition_table` results (one per condition and metric; 3D
    errors in mm, jitter in m/s^2, with their intervals), for the report figures."""
    out = []
    for condition, row in results.items():
        for key, value in row.items():
            if key in ("windows", "intervals") or value is None:
                continue
            metric = key.removesuffix("_mm")
            span = (row.get("intervals") or {}).get(key) or [None, None]
            unit = "mm" if key.endswith("_mm") else "m/s^2" if "jitter" in key else ""
            out.append(Record(method, condition, metric, float(value), ci_low=span[0], ci_high=span[1], unit=unit, num_clips=row["windows"]))
    return out
