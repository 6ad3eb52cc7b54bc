"""Labelling clip folders: `esther label CLIP_DIR... --out DIR [--resume] [--reject FILE]`.

Each clip's labels (`<out>/<clip>/hands/<side>/labels.npz` + `quality.json`) are built
in a hidden folder and renamed into place when complete, so `--resume` skips finished
clips and an interruption never leaves a half-written one. A clip that fails (missing
or corrupt file, degenerate rig) is reported and does not stop the others. A reject
list (human review, the third filter stage) marks hand-frames invalid.
"""

import json
import pathlib
import shutil
import time

import numpy as np

from esther_jax import mano
from esther_jax.cameras import StereoRig
from esther_jax.data import clip_io

from .pipeline import LabelConfig, label_hand


def read_reject_list(path: str | pathlib.Path) -> frozenset[tuple[str, str, int]]:
    """Rejected hand-frames, one `clip,side,frame` per line (# comments allowed)."""
    rejects = set()
    for number, line in enumerate(pathlib.Path(path).read_text().splitlines(), 1):
        line = line.split("#", 1)[0].strip()
        if not line:
            continue
        parts = [p.strip() for p in line.split(",")]
        if len(parts) != 3 or parts[1] not in clip_io.SIDES or not parts[2].isdigit():
            raise ValueError(f"{path}:{number}: expected 'clip,side,frame' (side right|left), got {line!r}")
        rejects.add((parts[0], parts[1], int(parts[2])))
    return frozenset(rejects)


def label_clip(
    clip_dir: str | pathlib.Path,
    out_dir: str | pathlib.Path,
    config: LabelConfig = LabelConfig(),
    rejects: frozenset[tuple[str, str, int]] = frozenset(),
    models: dict[str, mano.ManoModel] | None = None,
) -> dict:
    """Label every hand of one clip folder into `out_dir/<clip name>/` (atomically)."""
    clip_dir, out_dir = pathlib.Path(clip_dir), pathlib.Path(out_dir)
    meta = clip_io.read_meta(clip_dir)
    rig = StereoRig.from_json(clip_dir / "rig.json")
    sides = [s for s in clip_io.SIDES if clip_io.hand_file(clip_dir, s, "keypoints").is_file()]
    if not sides:
        raise clip_io.ClipFormatError(f"{clip_dir} has no hands/<side>/keypoints.npz")
    final = out_dir / clip_dir.name
    tmp = out_dir / f".{clip_dir.name}.partial"
    if tmp.exists():
        shutil.rmtree(tmp)
    summary = {"clip": clip_dir.name, "hands": {}}
    try:
        _label_sides(clip_dir, tmp, sides, meta, rig, config, rejects, models, summary)
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)  # a failed clip leaves nothing behind
        raise
    clip_io.write_meta(tmp, **{**meta, "labelled_by": "esther teacher"})
    if final.exists():
        shutil.rmtree(final)
    tmp.rename(final)
    return summary


def _label_sides(clip_dir, tmp, sides, meta, rig, config, rejects, models, summary) -> None:
    for side in sides:
        keypoints = clip_io.load_npz(clip_io.hand_file(clip_dir, side, "keypoints"), "keypoints")
        if keypoints["uv"].shape[0] != 2:
            raise clip_io.ClipFormatError(f"{clip_dir}: {side} keypoints have {keypoints['uv'].shape[0]} detectors; the fusion needs 2")
        model = (models or {}).get(side) or mano.load_builtin(side)
        mono_path = clip_io.hand_file(clip_dir, side, "monocular")
        monocular = clip_io.load_npz(mono_path, "monocular") if mono_path.is_file() else None
        t0 = time.perf_counter()
        labels, report = label_hand(model, rig, keypoints, float(meta["fps"]), config, monocular)
        report["seconds"] = time.perf_counter() - t0
        rejected = [f for (c, s, f) in rejects if c == clip_dir.name and s == side and f < len(labels["valid"])]
        if rejected:
            labels["valid"][rejected] = False
            report["human_rejected_frames"] = sorted(rejected)
        clip_io.save_npz(clip_io.hand_file(tmp, side, "labels"), **labels)
        (tmp / "hands" / side / "quality.json").write_text(json.dumps(report, indent=1, default=float))
        summary["hands"][side] = {
            "frames": len(labels["valid"]),
            "valid": int(labels["valid"].sum()),
            "seconds": report["seconds"],
            "notes": report.get("notes", []),
        }


def label_clips(
    clip_dirs: list[str | pathlib.Path],
    out_dir: str | pathlib.Path,
    *,
    resume: bool = False,
    config: LabelConfig = LabelConfig(),
    rejects: frozenset[tuple[str, str, int]] = frozenset(),
    progress: bool = True,
) -> dict:
    """Label many clips; failures are collected, not raised."""
    from tqdm import tqdm

    out_dir = pathlib.Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    done, skipped, failed = [], [], []
    frames, seconds = 0, 0.0
    for clip in tqdm([pathlib.Path(c) for c in clip_dirs], desc="label", unit="clip", disable=not progress):
        if resume and (out_dir / clip.name / "meta.json").exists():
            skipped.append(clip.name)
            continue
        try:
            summary = label_clip(clip, out_dir, config, rejects)
        except (ValueError, OSError) as err:  # bad files, degenerate rigs: report and go on
            failed.append({"clip": str(clip), "error": str(err)})
            continue
        done.append(summary)
        frames += sum(h["frames"] for h in summary["hands"].values())
        seconds += sum(h["seconds"] for h in summary["hands"].values())
    return {"labelled": done, "skipped": skipped, "failed": failed, "hand_frames": frames, "seconds": seconds}



def review_clip(clip_dir: str | pathlib.Path, out_dir: str | pathlib.Path) -> list[pathlib.Path]:
    """Write `<out>/<clip>/hands/<side>/review.png` for the flagged frames of each hand."""
    import jax.numpy as jnp

    from esther_jax.data.synth import read_video

    from .fusion import fuse
    from .review import review_sheet

    clip_dir, out_dir = pathlib.Path(clip_dir), pathlib.Path(out_dir)
    rig = StereoRig.from_json(clip_dir / "rig.json")
    videos = None
    if (clip_dir / "video" / "left.mp4").is_file():
        videos = {view: read_video(clip_dir / "video" / f"{view}.mp4") for view in ("left", "right")}
    sheets = []
    for side in clip_io.SIDES:
        path = clip_io.hand_file(out_dir / clip_dir.name, side, "labels")
        if not path.is_file():
            continue
        labels = clip_io.load_npz(path, "labels")
        kp = clip_io.load_npz(clip_io.hand_file(clip_dir, side, "keypoints"), "keypoints")
        fused = fuse(*(jnp.asarray(kp[k]) for k in ("uv", "conf", "box", "box_score")))
        sheet = review_sheet(rig, labels, np.asarray(fused.uv), np.asarray(fused.conf), path.with_name("review.png"), images=videos)
        if sheet is not None:
            sheets.append(sheet)
    return sheets
