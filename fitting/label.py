"""Labelling clip folders: `esther label CLIP_DIR... --out DIR [--resume] [--reject FILE] [--mano DIR]`.

Each clip's labels (`<out>/<clip>/hands/<side>/labels.npz` + `quality.json`) are built
in a hidden folder and renamed into place when complete, so `--resume` skips finished
clips and an interruption never leaves a half-written one. A clip that fails (missing
or corrupt file, degenerate rig) is reported and does not stop the others. A reject
list (human review, the third filter stage) marks hand-frames invalid. The labels are
MANO parameters of the built-in hand or of the user's models (`--mano DIR`: their
official `MANO_RIGHT.pkl` / `MANO_LEFT.pkl`), and record which (`mano.model_id`).

`refine_clips` (`esther refine`) writes the same labels from a network's predictions
(`esther predict`'s folder): each hand is `pipeline.refine`d against the clip's 2D
keypoints, and the labels record the prediction they grew from (`meta.json`
`"prediction"`: its folder, its `labelled_by`, the sha256 of its labels arrays), so
`--resume` redoes a clip whose prediction changed (a later round's network).

Labels also record the method that made them (`meta.json` `"method"`: teacher or refine,
the algorithm's revision, `pipeline.TEACHER_REVISION` / `REFINE_REVISION`, and every
`LabelConfig` setting), and `--resume` keeps only labels made the way this run makes them.
"""

import functools
import hashlib
import json
import pathlib
import shutil
import tempfile
import time

import equinox as eqx
import jax.numpy as jnp
import numpy as np

from esther_jax import clips, mano
from esther_jax.cameras import StereoRig
from esther_jax.files import check_out_dir, exclusive_lock, named_folders, remove_stale_partials, write_json

from .pipeline import REFINE_CONFIG, LabelConfig, label_hands, method_record


def read_reject_list(path: str | pathlib.Path) -> frozenset[tuple[str, str, int]]:
    """Rejected hand-frames, one `clip,side,frame` per line (# comments allowed)."""
    rejects = set()
    for number, line in enumerate(pathlib.Path(path).read_text().splitlines(), 1):
        line = line.split("#", 1)[0].strip()
        if not line:
            continue
        parts = [p.strip() for p in line.split(",")]
        if len(parts) != 3 or parts[1] not in clips.SIDES or not parts[2].isdigit():
            raise ValueError(f"{path}:{number}: expected 'clip,side,frame' (side right|left), got {line!r}")
        rejects.add((parts[0], parts[1], int(parts[2])))
    return frozenset(rejects)


def label_clip(
    clip_dir: str | pathlib.Path,
    out_dir: str | pathlib.Path,
    config: LabelConfig = LabelConfig(),
    rejects: frozenset[tuple[str, str, int]] = frozenset(),
    models: dict[str, mano.ManoModel] | None = None,
    model_sources: dict[str, str] | None = None,
    predictions: str | pathlib.Path | None = None,
) -> dict:
    """Label every hand of one clip folder into `out_dir/<clip name>/` (atomically).

    Args:
        models: the hand model per side ('right', 'left'), e.g. the user's official MANO
            files read with `mano.load_mano_pkl`; a side left out is fitted with the
            built-in hand.
        model_sources: where each of `models` came from (a path), recorded beside the
            model's id; by default 'builtin' when the model is the built-in one, else 'user'.
        predictions: a folder of a network's predictions in the labels format (`esther
            predict --out`): every hand is refined from its prediction
            (`pipeline.refine`; pass `config=REFINE_CONFIG`) instead of labelled from scratch.

    The labels record which model they are parameters of: `meta.json` gets
    `"mano_model": {side: {"id": mano.model_id(model), "source": ...}}` for the labelled
    sides, and each hand's `quality.json` its own `"mano_model"` entry. `meta.json` also
    records the clip they were made from, `"source_clip": {"name", "digest"}`
    (`clips.clip_digest`), which `esther evaluate` checks.

    The clip is labelled under an exclusive lock (`out_dir/.<clip>.lock`): a second
    process (or thread) labelling the same clip into the same folder waits for it.
    """
    clip_dir, out_dir = pathlib.Path(clip_dir), pathlib.Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    with _clip_lock(out_dir, clip_dir.name, wait=True):
        return _label_locked(clip_dir, out_dir, config, rejects, models, model_sources, predictions)


def _clip_lock(out_dir: pathlib.Path, name: str, *, wait: bool):
    """The lock of one clip's labels: `out_dir/.<name>.lock`."""
    return exclusive_lock(out_dir / f".{name}.lock", wait=wait)


def _label_locked(clip_dir, out_dir, config, rejects, models, model_sources, predictions=None, pose_prior=None) -> dict:
    """`label_clip` with the clip's lock held: nobody else writes `out_dir/<clip>`."""
    meta = clips.read_meta(clip_dir)
    rig = StereoRig.from_json(clip_dir / "rig.json")
    sides = [s for s in clips.SIDES if clips.hand_file(clip_dir, s, "keypoints").is_file()]
    if not sides:
        raise clips.ClipFormatError(f"{clip_dir} has no hands/<side>/keypoints.npz")
    remove_stale_partials(out_dir, clip_dir.name)  # left by an interrupted run (we hold the lock)
    final = out_dir / clip_dir.name
    tmp = pathlib.Path(tempfile.mkdtemp(prefix=f".{clip_dir.name}.partial-", dir=out_dir))
    summary = {"clip": clip_dir.name, "hands": {}}
    try:
        source = {"name": clip_dir.name, "digest": clips.clip_digest(clip_dir)}
        origin = None if predictions is None else prediction_record(pathlib.Path(predictions), clip_dir.name, sides)
        _label_sides(clip_dir, tmp, sides, meta, rig, config, rejects, models, model_sources, summary, predictions, pose_prior)
        # replaces any "mano_model" of the input clip's meta (that one describes its gt.npz)
        recorded = {side: hand["mano_model"] for side, hand in summary["hands"].items()}
        made = {"labelled_by": "esther teacher"} if origin is None else {"labelled_by": "esther refine", "prediction": origin}
        made["pose_prior"] = pose_prior_record(pose_prior)
        made["method"] = method_record(config, predictions is not None)
        clips.write_meta(tmp, **{**meta, **made, "mano_model": recorded, "source_clip": source})
        if final.exists():
            shutil.rmtree(final)
        tmp.rename(final)
    finally:
        shutil.rmtree(tmp, ignore_errors=True)  # a failed clip leaves nothing behind
    return summary


def _hand_model(side: str, models: dict | None, sources: dict | None) -> tuple[mano.ManoModel, dict[str, str]]:
    """The model a side is fitted with, and its record `{"id", "source"}` for the labels."""
    model = (models or {}).get(side)
    if model is None:
        return mano.load_builtin(side), {"id": _builtin_id(side), "source": "builtin"}
    if model.side != side:
        raise ValueError(f"models[{side!r}] is a {model.side} hand model; pass the {side} model (e.g. MANO_{side.upper()}.pkl)")
    model_id = mano.model_id(model)
    source = (sources or {}).get(side)
    if source is None:
        source = "builtin" if model_id == _builtin_id(side) else "user"
    return model, {"id": model_id, "source": str(source)}


@functools.cache
def _builtin_id(side: str) -> str:
    return mano.model_id(mano.load_builtin(side))  # the same with and without x64


def prediction_record(predictions: pathlib.Path, clip: str, sides: list[str]) -> dict:
    """What refined labels record of their prediction (`meta.json` `"prediction"`): its
    folder, what made it (its `labelled_by`) and the sha256 of its sides' labels arrays.
    A side without a prediction is a `ClipFormatError` naming the file."""
    digest = hashlib.sha256()
    for side in sides:
        path = clips.hand_file(predictions / clip, side, "labels")
        if not path.is_file():
            raise clips.ClipFormatError(f"no prediction of the {side} hand: {path} is missing (esther predict --out {predictions} writes it)")
        digest.update(side.encode())
        clips.update_digest(digest, clips.load_npz(path, "labels"))
    try:
        made_by = clips.read_meta(predictions / clip).get("labelled_by")
    except (OSError, ValueError, clips.ClipFormatError):
        made_by = None
    return {"folder": str(predictions.resolve()), "labelled_by": made_by, "sha256": digest.hexdigest()}


def _label_sides(clip_dir, tmp, sides, meta, rig, config, rejects, models, sources, summary, predictions=None, pose_prior=None) -> None:
    keypoints, hand_models, records, monocular = {}, {}, {}, {}
    for side in sides:
        keypoints[side] = clips.load_npz(clips.hand_file(clip_dir, side, "keypoints"), "keypoints")
        frames = keypoints[side]["uv"].shape[1]
        if frames != meta["num_frames"]:
            raise clips.ClipFormatError(
                f"{clip_dir}: meta.json says num_frames = {meta['num_frames']}, but hands/{side}/keypoints.npz has {frames} frames"
            )
        hand_models[side], records[side] = _hand_model(side, models, sources)
        mono_path = clips.hand_file(clip_dir, side, "monocular")
        monocular[side] = clips.load_npz(mono_path, "monocular") if mono_path.is_file() else None
    # one person's hands share a shape only when both are fitted with the same kind of model
    share = len({record["source"] == "builtin" for record in records.values()}) == 1
    start = None if predictions is None else {side: clips.Labels.from_npz(clips.hand_file(pathlib.Path(predictions) / clip_dir.name, side, "labels")).params
                                              for side in sides}  # fmt: skip
    results = label_hands(hand_models, rig, keypoints, float(meta["fps"]), config, monocular, share_shape=share, predictions=start, pose_prior=pose_prior)
    for side in sides:
        labels, report = results[side]
        record = records[side]
        report["mano_model"] = record
        rejected = [f for (c, s, f) in rejects if c == clip_dir.name and s == side and f < len(labels.valid)]
        if rejected:
            labels = eqx.tree_at(lambda x: x.valid, labels, labels.valid.at[jnp.asarray(rejected)].set(False))
            report["human_rejected_frames"] = sorted(rejected)
        labels.to_npz(clips.hand_file(tmp, side, "labels"))
        write_json(tmp / "hands" / side / "quality.json", report)
        summary["hands"][side] = {
            "frames": len(labels.valid),
            "valid": int(labels.valid.sum()),
            "seconds": report["seconds"],
            "notes": report.get("notes", []),
            "mano_model": record,
        }


def label_clips(
    clip_dirs: list[str | pathlib.Path],
    out_dir: str | pathlib.Path,
    *,
    resume: bool = False,
    config: LabelConfig = LabelConfig(),
    rejects: frozenset[tuple[str, str, int]] = frozenset(),
    progress: bool = True,
    models: dict[str, mano.ManoModel] | None = None,
    model_sources: dict[str, str] | None = None,
    predictions: str | pathlib.Path | None = None,
    pose_prior: mano.GMMPosePrior | None = None,
) -> dict:
    """Label many clips; per-clip failures are collected, not raised.

    `models` / `model_sources` as in `label_clip` (checked once, before any clip). With
    `resume`, a clip is skipped only when its finished labels are of the same models
    (the `mano_model` ids of its `meta.json`; labels that record none are of the built-in
    hand); labels of other models are redone. With `predictions` (`label_clip`'s; see
    `refine_clips`) a finished clip is kept only when it was refined from the same
    prediction, and labels of the teacher are not kept for it (nor refined ones without).
    `pose_prior`: a learned pose prior in the PCA prior's place (`pipeline.label_hand`'s),
    recorded in each clip's `meta.json` (`"pose_prior"`); `resume` keeps only labels made
    under the same prior. Each clip's `meta.json` records the method too (`"method"`:
    teacher or refine, its revision, `config`: `pipeline.method_record`); `resume` redoes
    labels made by another revision of the algorithm or with other settings, and labels
    that record no method (made before revisions were recorded).

    Safe to run twice at once on one `out_dir`: each clip is labelled under its own lock;
    a clip another process is labelling is put back and taken last (waiting for the
    lock), and skipped then if that process finished it with the same models after this
    run began. Raises ValueError before any work when `out_dir` cannot be written, when
    two clips share a folder name (their labels would overwrite each other) or when
    `clip_dirs` is empty.
    """
    from tqdm import tqdm

    unknown = set(models or {}) - set(clips.SIDES)
    if unknown:
        raise ValueError(f"models has unknown sides {sorted(unknown)}; use {clips.SIDES}")
    wanted = {side: _hand_model(side, models, model_sources)[1]["id"] for side in clips.SIDES}
    clip_dirs = named_folders(clip_dirs)
    if not clip_dirs:
        raise ValueError("no clip to label (a clip folder holds rig.json, meta.json and hands/<side>/keypoints.npz)")
    out_dir = check_out_dir(out_dir)
    prior = pose_prior_record(pose_prior)
    method = method_record(config, predictions is not None)
    started = time.time()
    done, skipped, failed = [], [], []
    frames, seconds = 0, 0.0

    def attempt(clip: pathlib.Path, *, wait: bool) -> bool:
        """Label `clip` (or skip it); False when another process holds it and `wait` is False."""
        nonlocal frames, seconds
        meta_path = out_dir / clip.name / "meta.json"
        with _clip_lock(out_dir, clip.name, wait=wait) as locked:
            if not locked:
                return False
            finished = (_labelled_with(meta_path, wanted) and _made_from(meta_path, clip) and _refined_from(meta_path, clip, predictions)
                        and _recorded(meta_path, "pose_prior") == prior and _recorded(meta_path, "method") == method)  # fmt: skip
            if finished and (resume or (wait and meta_path.stat().st_mtime >= started)):
                skipped.append(clip.name)  # done before (--resume), or by the other process just now
                return True
            try:
                summary = _label_locked(clip, out_dir, config, rejects, models, model_sources, predictions, pose_prior)
            except Exception as err:  # a bad clip never stops the batch: report it and go on
                failed.append({"clip": str(clip), "error": f"{type(err).__name__}: {err}"})
                return True
        done.append(summary)
        frames += sum(h["frames"] for h in summary["hands"].values())
        seconds += sum(h["seconds"] for h in summary["hands"].values())
        return True

    busy = [clip for clip in tqdm(clip_dirs, desc="label", unit="clip", disable=not progress) if not attempt(clip, wait=False)]
    for clip in busy:  # another process holds them: wait, then skip what it finished
        attempt(clip, wait=True)
    return {"labelled": done, "skipped": skipped, "failed": failed, "hand_frames": frames, "seconds": seconds}


def refine_clips(
    clip_dirs: list[str | pathlib.Path],
    predictions: str | pathlib.Path,
    out_dir: str | pathlib.Path,
    *,
    resume: bool = False,
    config: LabelConfig = REFINE_CONFIG,
    progress: bool = True,
    models: dict[str, mano.ManoModel] | None = None,
    model_sources: dict[str, str] | None = None,
    pose_prior: mano.GMMPosePrior | None = None,
) -> dict:
    """Refine a network's predictions (`predictions`: `esther predict`'s folder) of many
    clips into labels in the teacher's format (`esther refine`): `label_clips` with every
    hand started from its prediction (`pipeline.refine`), the same locks, atomic writes
    and resume, and each clip's labels recording their prediction (module docstring)."""
    predictions = pathlib.Path(predictions)
    if not predictions.is_dir():
        raise ValueError(f"{predictions} is not a folder of predictions (esther predict --model RUN CLIP... --out {predictions} writes one)")
    return label_clips(clip_dirs, out_dir, resume=resume, config=config, progress=progress, models=models, model_sources=model_sources,
                       predictions=predictions, pose_prior=pose_prior)  # fmt: skip


def pose_prior_record(pose_prior: mano.GMMPosePrior | None) -> dict | None:
    """What labels record of the pose prior they were fitted under (`meta.json`
    `"pose_prior"`): None for the hand model's PCA prior, else the mixture's size and the
    sha256 of its arrays."""
    if pose_prior is None:
        return None
    digest = hashlib.sha256()
    for array in (pose_prior.means, pose_prior.factors, pose_prior.log_weights):
        digest.update(np.ascontiguousarray(np.asarray(array, np.float32)).tobytes())
    return {"kind": "gmm", "components": int(pose_prior.means.shape[0]), "sha256": digest.hexdigest()}


def _recorded(meta_path: pathlib.Path, key: str):
    """`meta.json`'s `key` (None when absent or unreadable)."""
    try:
        return json.loads(meta_path.read_text()).get(key)
    except (OSError, ValueError, AttributeError):
        return None


def _refined_from(meta_path: pathlib.Path, clip: pathlib.Path, predictions: str | pathlib.Path | None) -> bool:
    """True when finished labels were made as this run would make them: the teacher's
    from scratch (`predictions` None), or refined from the prediction now in `predictions`."""
    try:
        recorded = json.loads(meta_path.read_text()).get("prediction")
        if predictions is None:
            return recorded is None
        sides = [s for s in clips.SIDES if clips.hand_file(clip, s, "keypoints").is_file()]
        return isinstance(recorded, dict) and recorded.get("sha256") == prediction_record(pathlib.Path(predictions), clip.name, sides)["sha256"]
    except (OSError, ValueError, AttributeError, clips.ClipFormatError):
        return False  # unreadable: label again (a missing prediction then reports its error)


def _made_from(meta_path: pathlib.Path, clip: pathlib.Path) -> bool:
    """False when finished labels record another source clip than `clip` (same folder
    name, other content): they are redone, not kept by --resume. Labels that record no
    source (older ones) count as made from it."""
    try:
        source = json.loads(meta_path.read_text()).get("source_clip")
        return not isinstance(source, dict) or source.get("digest") == clips.clip_digest(clip)
    except (OSError, ValueError, AttributeError):
        return False  # unreadable labels or clip: label again (a bad clip then reports its error)


def _labelled_with(meta_path: pathlib.Path, wanted: dict[str, str]) -> bool:
    """True when `meta_path` exists (labels are complete) and records the `wanted` model ids."""
    if not meta_path.exists():
        return False
    try:
        recorded = json.loads(meta_path.read_text()).get("mano_model")
    except (OSError, ValueError, AttributeError):
        return False  # unreadable: label again
    if recorded is None:  # labels written before models were recorded are of the built-in hand
        recorded = {side: {"id": _builtin_id(side)} for side in clips.SIDES}
    if not isinstance(recorded, dict):
        return False
    return all(isinstance(r, dict) and r.get("id") == wanted.get(side) for side, r in recorded.items())



def review_clip(clip_dir: str | pathlib.Path, out_dir: str | pathlib.Path) -> list[pathlib.Path]:
    """Write `<out>/<clip>/hands/<side>/review.png` for the flagged frames of each hand."""
    from .fusion import fuse
    from .review import review_sheet

    clip_dir, out_dir = pathlib.Path(clip_dir), pathlib.Path(out_dir)
    rig = StereoRig.from_json(clip_dir / "rig.json")
    videos = None
    if (clip_dir / "video" / "left.mp4").is_file():
        videos = {view: clips.read_video(clip_dir / "video" / f"{view}.mp4") for view in ("left", "right")}
    sheets = []
    for side in clips.SIDES:
        path = clips.hand_file(out_dir / clip_dir.name, side, "labels")
        if not path.is_file():
            continue
        labels = clips.Labels.from_npz(path)
        kp = clips.load_npz(clips.hand_file(clip_dir, side, "keypoints"), "keypoints")
        fused = fuse(*(jnp.asarray(kp[k]) for k in ("uv", "conf", "box", "box_score")))
        sheet = review_sheet(rig, labels, np.asarray(fused.uv), np.asarray(fused.conf), path.with_name("review.png"), images=videos)
        if sheet is not None:
            sheets.append(sheet)
    return sheets
