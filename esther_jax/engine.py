"""The data engine (paper, "Model-Assisted Labeling and Iterative Enhancement"):
`esther engine CLIP... --out ENGINE --rounds N`.

The teacher is expensive, so it labels only a share of the raw collection; the network
trained on those labels predicts the rest, each prediction is refined against the clip's
2D keypoints and screened by the teacher's own filter (`fitting.refine`), and the
accepted refined labels join the teacher's for the next round's training. Round 0
labels `teacher_share` of the clips with the teacher and trains; round k >= 1 predicts
every other clip with round k-1's network, refines, and trains on the teacher's labels
plus the refined ones (their `valid` frames: what the filter accepted), from scratch or
from round k-1's weights (`EngineConfig.warm_start`).

```
ENGINE/
  engine.json          the plan: the clips, the teacher's share of them, the EngineConfig
  teacher/             the teacher's labels of its share (esther label's format)
  round_000/
    labels/            the round's training labels: links to teacher/<clip> (and refined/<clip>)
    run/               the two training stages (stage1/, stage2/: esther train's run folders)
    round.json         written last: the round is finished; its metrics (`round_metrics`)
  round_001/
    predictions/       round_000's network on the clips the teacher did not label
    refined/           those predictions refined (esther refine's format)
    labels/  run/  round.json
```

Every step resumes: the teacher and refinement keep finished clips (their `--resume`),
predictions keep clips predicted by the same network, training resumes from its
checkpoint, the labels folder is built atomically, and a round with a `round.json` is
kept whole. A second engine on the same folder is refused (a lock), and a resumed
engine must have the plan it was started with (more rounds may be asked for).
"""

import dataclasses
import math
import os
import pathlib
import shutil
import tempfile
import time

import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import ArrayLike, Float

from . import clips, mano, metrics
from . import model as M
from . import train as train_lib
from .files import check_out_dir, exclusive_lock, named_folders, read_json, write_json

ENGINE_FORMAT = 1
"""Version of engine.json (its plan's fields)."""

WORSE_THAN_MM = 15.0
"""An accepted label whose P-MPJPE against the truth exceeds this is a filter miss (issue 49's precision)."""


@dataclasses.dataclass(frozen=True)
class EngineConfig:
    """What an engine trains and how much of the collection the teacher labels."""

    config: str = "cpu-tiny"
    """The network's config (`esther_jax.model.CONFIGS`)."""
    teacher_share: float = 0.2
    """Share of the clips the teacher labels in round 0 (at least one clip)."""
    stage1_steps: int = 400
    stage2_steps: int = 400
    batch: int = 8
    learning_rate: float = 5e-4
    stage1_learning_rate: float | None = None
    frames_apart: bool = False
    """Stage 1 draws each example's frames apart (`TrainConfig.frames_apart`)."""
    warm_start: bool = False
    """Round k >= 1 starts from round k-1's network (else from a fresh one, seeded as round 0's)."""
    seed: int = 0
    """Seed of the teacher's share (which clips) and of every round's training."""
    pose_prior: str | None = None
    """A learned pose prior's file (`esther prior`) for the teacher and the refinement; None: the PCA prior."""

    def __post_init__(self):
        if not 0.0 < self.teacher_share <= 1.0:
            raise ValueError(f"teacher_share must be in (0, 1], got {self.teacher_share}")
        if self.config not in M.CONFIGS:
            raise ValueError(f"unknown network config {self.config!r}; one of {sorted(M.CONFIGS)}")
        if self.stage1_steps < 0 or self.stage2_steps < 0 or self.stage1_steps + self.stage2_steps == 0:
            raise ValueError(f"stage steps must be >= 0 and not both 0, got {self.stage1_steps} and {self.stage2_steps}")


def teacher_share(names: list[str], share: float, seed: int) -> list[str]:
    """The clips (by name) the teacher labels: ceil(share * n) of them, drawn by `seed`
    from the sorted names (so the draw does not depend on the order they were given in)."""
    ordered = sorted(names)
    count = max(1, math.ceil(share * len(ordered)))
    picks = np.random.default_rng(seed).permutation(len(ordered))[:count]
    return sorted(ordered[i] for i in picks)


def round_dir(out: str | pathlib.Path, number: int) -> pathlib.Path:
    """`out/round_NNN`."""
    return pathlib.Path(out) / f"round_{number:03d}"


def _plan(clip_dirs: list[pathlib.Path], cfg: EngineConfig) -> dict:
    names = [c.name for c in clip_dirs]
    return {"format": ENGINE_FORMAT, "clips": sorted(names), "teacher_clips": teacher_share(names, cfg.teacher_share, cfg.seed),
            "config": dataclasses.asdict(cfg)}  # fmt: skip


def _check_plan(out: pathlib.Path, plan: dict) -> None:
    """Write the plan of a fresh engine; refuse to resume one started with another."""
    path = out / "engine.json"
    if not path.is_file():
        write_json(path, plan)
        return
    recorded = read_json(path)
    for key in ("clips", "teacher_clips", "config"):
        if recorded.get(key) != plan[key]:
            raise ValueError(
                f"{out} is an engine started with other {key} ({path}): resume it with the same clips and options, or choose another --out"
            )


def _finished(folder: pathlib.Path) -> set[str]:
    """Names of the clips whose labels in `folder` are complete (their meta.json exists)."""
    return {p.parent.name for p in folder.glob("*/meta.json")} if folder.is_dir() else set()


def _link_labels(labels: pathlib.Path, sources: dict[str, pathlib.Path]) -> pathlib.Path:
    """`labels/<clip>` -> `sources[clip]` (relative links), built in a hidden folder and
    renamed into place, so a labels folder is either complete or absent."""
    if labels.is_dir():
        return labels
    tmp = pathlib.Path(tempfile.mkdtemp(prefix=".labels.partial-", dir=labels.parent))
    try:
        for name, source in sorted(sources.items()):
            os.symlink(os.path.relpath(source, tmp), tmp / name)
        tmp.rename(labels)
    finally:
        shutil.rmtree(tmp, ignore_errors=True)
    return labels


def label_errors_mm(labels: clips.Labels, truth: Float[ArrayLike, "T 21 3"]) -> tuple[np.ndarray, np.ndarray]:
    """Per frame, the labels' P-MPJPE and wrist error against the true joints `truth`
    (rig frame, metres), in millimetres: two float arrays of shape [T], every frame
    (mask them by `labels.valid` and the truth's `onscreen`)."""
    joints = labels.joints
    truth = jnp.asarray(truth, joints.dtype)
    return (np.asarray(jax.vmap(metrics.p_mpjpe)(joints, truth)) * 1000.0, np.asarray(jax.vmap(metrics.wrist_error)(joints, truth)) * 1000.0)


def label_accuracy(clip_dirs: list[pathlib.Path], labels_root: pathlib.Path, names: set[str]) -> dict:
    """The accepted labels of the clips `names` against their ground truth (clips with
    `hands/<side>/gt.npz`), pooled over hand-frames: `onscreen` (the truth's on-screen
    hand-frames), `accepted` (of those, the labels' `valid` ones), `coverage`, the
    accepted frames' mean `p_mpjpe_mm` and `wrist_mm`, and `worse_than_15mm` (how many
    accepted labels exceed `WORSE_THAN_MM` of P-MPJPE). `None` values where nothing was
    accepted; an empty dict when no clip has ground truth."""
    onscreen, accepted, p, wrist = 0, 0, [], []
    for clip in clip_dirs:
        if clip.name not in names:
            continue
        for side in clips.SIDES:
            gt_path, label_path = clips.hand_file(clip, side, "gt"), clips.hand_file(labels_root / clip.name, side, "labels")
            if not gt_path.is_file():
                continue
            gt = clips.load_npz(gt_path, "gt")
            seen = np.asarray(gt["onscreen"], bool)
            onscreen += int(seen.sum())
            if not label_path.is_file():
                continue
            labels = clips.Labels.from_npz(label_path)
            ok = seen & np.asarray(labels.valid, bool)
            accepted += int(ok.sum())
            errors = label_errors_mm(labels, gt["joints"])
            p.append(errors[0][ok])
            wrist.append(errors[1][ok])
    if onscreen == 0:
        return {}
    p_all, wrist_all = (np.concatenate(x) if x else np.zeros(0) for x in (p, wrist))
    mean = lambda x: float(np.mean(x)) if x.size else None  # noqa: E731
    return {"onscreen": onscreen, "accepted": accepted, "coverage": accepted / onscreen, "p_mpjpe_mm": mean(p_all), "wrist_mm": mean(wrist_all),
            "worse_than_15mm": int(np.sum(p_all > WORSE_THAN_MM))}  # fmt: skip


def labelling_cost(labels_root: pathlib.Path, names: set[str]) -> dict:
    """Hand-frames and seconds of the labels of the clips `names` (each hand's
    `quality.json` `seconds`: its fit, compilation included when it compiled), and two
    rates: `hand_frames_per_s` (all frames over all seconds: what this run paid, so it
    depends on whether its programs were compiled before, e.g. by an earlier seed in
    the same process) and `steady_hand_frames_per_s` (all frames over the hands' count
    times their median seconds: the rate once compiled, the same whatever ran first)."""
    frames, per_hand = 0, []
    for name in names:
        for side in clips.SIDES:
            quality = labels_root / name / "hands" / side / "quality.json"
            if quality.is_file():
                frames += int(clips.Labels.from_npz(clips.hand_file(labels_root / name, side, "labels")).valid.shape[0])
                per_hand.append(float(read_json(quality).get("seconds", 0.0)))
    seconds, median = float(np.sum(per_hand)), float(np.median(per_hand)) if per_hand else 0.0
    return {"hand_frames": frames, "hands": len(per_hand), "seconds": seconds, "hand_frames_per_s": frames / seconds if seconds > 0 else None,
            "steady_hand_frames_per_s": frames / (len(per_hand) * median) if median > 0 else None}  # fmt: skip


def network_accuracy(model_dir: pathlib.Path, val_dirs: list[pathlib.Path], *, batch: int = 8) -> dict:
    """The network's held-out scores (`train.validation.evaluate_windows` on every
    non-overlapping window of `val_dirs`' ground truth, with bootstrap intervals over
    windows), both views and the right view dropped."""
    net = M.load(model_dir)
    cfg = train_lib.DataConfig(frames=net.config.num_frames, crop_size=net.config.crop_size)
    cfg = dataclasses.replace(cfg, stride=cfg.frames)
    windows = train_lib.build_index(val_dirs, cfg)
    if not windows:
        raise ValueError(f"no held-out window in {len(val_dirs)} --val clips (need crops, gt.npz and {cfg.frames} frames)")
    from .train.validation import evaluate_windows

    return {views: evaluate_windows(net, windows, cfg, batch=batch, view_dropped=dropped, intervals=True)
            for views, dropped in (("both", None), ("right dropped", 1))}  # fmt: skip


def run_engine(
    clip_dirs: list[str | pathlib.Path],
    out: str | pathlib.Path,
    cfg: EngineConfig = EngineConfig(),
    *,
    rounds: int = 2,
    val_dirs: list[str | pathlib.Path] | None = None,
    features: str | pathlib.Path | None = None,
    progress: bool = True,
) -> list[dict]:
    """Run (or resume) `rounds` rounds of the engine over the raw collection `clip_dirs`
    (clip folders with keypoints and crops) into `out` (module docstring); returns every
    round's `round.json`. `val_dirs`: held-out clips with ground truth the networks are
    scored on; `features`: a feature cache of a frozen backbone (`DataConfig.features`),
    shared by every round."""
    if rounds < 1:
        raise ValueError(f"rounds must be >= 1, got {rounds}")
    clip_dirs = named_folders(clip_dirs)
    if not clip_dirs:
        raise ValueError("no clip for the engine (clip folders with hands/<side>/keypoints.npz and crops/)")
    out = check_out_dir(out)
    out.mkdir(parents=True, exist_ok=True)
    with exclusive_lock(out / ".engine.lock", wait=False) as held:
        if not held:
            raise ValueError(f"{out} is being run by another engine: wait for it to end, or choose another --out")
        plan = _plan(clip_dirs, cfg)
        _check_plan(out, plan)
        return [_round(out, number, clip_dirs, plan, cfg, val_dirs, features, progress) for number in range(rounds)]


def _round(out, number, clip_dirs, plan, cfg, val_dirs, features, progress) -> dict:
    from fitting import label_clips, refine_clips

    from .model.folders import predict_folders

    here = round_dir(out, number)
    if (here / "round.json").is_file():
        return read_json(here / "round.json")
    here.mkdir(parents=True, exist_ok=True)
    by_name = {c.name: c for c in clip_dirs}
    taught = set(plan["teacher_clips"])
    started = time.time()
    pose_prior = None if cfg.pose_prior is None else mano.GMMPosePrior.load(cfg.pose_prior)
    result = label_clips([by_name[n] for n in sorted(taught)], out / "teacher", resume=True, progress=progress, pose_prior=pose_prior)
    failures = list(result["failed"])
    sources = {n: out / "teacher" / n for n in _finished(out / "teacher")}
    others = [c for c in clip_dirs if c.name not in taught]
    if number > 0 and others:
        previous = round_dir(out, number - 1) / "run"
        model_dir = _final_model(previous)
        predicted = predict_folders(model_dir, others, here / "predictions", resume=True, progress=progress)
        failures += predicted["failed"]
        ready = [c for c in others if c.name in _finished(here / "predictions")]
        if ready:
            failures += refine_clips(ready, here / "predictions", here / "refined", resume=True, progress=progress, pose_prior=pose_prior)["failed"]
        sources.update({n: here / "refined" / n for n in _finished(here / "refined")})
    labels = _link_labels(here / "labels", sources)
    init = _final_model(round_dir(out, number - 1) / "run") if number > 0 and cfg.warm_start else None
    model_cfg = M.config(cfg.config)
    final = train_lib.train_stages(
        here / "run", clip_dirs, model_cfg, stage1_steps=cfg.stage1_steps, stage2_steps=cfg.stage2_steps, batch=cfg.batch,
        learning_rate=cfg.learning_rate, stage1_learning_rate=cfg.stage1_learning_rate, stage1_frames_apart=cfg.frames_apart,
        seed=cfg.seed, features=features, labels=labels, init=init, progress=progress,
    )  # fmt: skip
    refined = set(sources) - taught
    record = {
        "round": number,
        "teacher_clips": len(taught & set(sources)),
        "refined_clips": len(refined),
        "failed": failures,
        "labels": {"teacher": label_accuracy(clip_dirs, out / "teacher", taught), "refined": label_accuracy(clip_dirs, here / "refined", refined),
                   "all": label_accuracy(clip_dirs, labels, set(by_name))},  # fmt: skip
        "cost": {"teacher": labelling_cost(out / "teacher", taught), "refined": labelling_cost(here / "refined", refined)},
        "model": str(final),
        "warm_start": init is not None,
        "seconds_this_run": time.time() - started,
    }
    if val_dirs:
        record["network"] = network_accuracy(final, [pathlib.Path(v) for v in val_dirs], batch=cfg.batch)
    write_json(here / "round.json", record)
    return record


def _final_model(run: pathlib.Path) -> pathlib.Path:
    """The model folder a finished round's training ended with (stage 2's, else stage 1's)."""
    for stage in ("stage2", "stage1"):
        if (run / stage / "model").is_dir():
            return run / stage / "model"
    raise ValueError(f"{run} holds no trained network (stage1/model or stage2/model): the round did not finish")


__all__ = ["ENGINE_FORMAT", "EngineConfig", "WORSE_THAN_MM", "label_accuracy", "label_errors_mm", "labelling_cost", "network_accuracy", "round_dir", "run_engine",
           "teacher_share"]  # fmt: skip
