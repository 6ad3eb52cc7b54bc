"""The data engine measured (paper, "Model-Assisted Labeling and Iterative Enhancement"):
`esther_jax.engine` run on a synthetic raw collection whose ground truth is held aside.

`run_engine_study(scale, study, root)` makes, under `root`:

- `raw/`, `heldout/`: the collections (`collection`), one link per clip named
  `<rig>_<clip>` (the engine and the labels key clips by folder name): the studies' own
  clips on the paper's rig, synthetic clips of other rigs under `data/<rig>_{raw,heldout}/`;
- `reference/`: the teacher's labels of every raw clip (`label_clips`, resumable), which
  the engine itself never reads: the refined labels are compared with them on the frames
  both accepted (`same_frames`), the issue's "within 1 mm of the teacher's";
- `seed_<s>/`: one engine (`run_engine`) per seed, the seed drawing the teacher's share
  and seeding every round's training: a learning result is several seeds.

and returns, per seed, every round's `round.json` plus the same-frames comparison.
`round_table` and `network_table` present them (mean ± sd over seeds) and `verdict`
checks the issue's targets: refinement at least 5x the teacher's hand-frames/s, accepted
refined labels within 1 mm P-MPJPE of the teacher's on the same frames, and round 1's
network better than round 0's on held-out windows (bootstrap intervals apart).
"""

import dataclasses
import os
import pathlib

import numpy as np

from .. import clips
from ..data import synth
from ..engine import EngineConfig, label_errors_mm, round_dir, run_engine
from ..files import read_json, write_json
from . import StudyScale, dataset, model_config, separated


@dataclasses.dataclass(frozen=True)
class EngineStudy:
    """The raw collection, its held-out clips and the engine run over them."""

    name: str
    raw: tuple[tuple[str, int], ...]
    """(rig preset, clips) of the raw collection, per rig."""
    heldout: tuple[tuple[str, int], ...]
    """(rig preset, clips) the networks are scored on, per rig."""
    engine: EngineConfig
    """The engine's settings; its seed is replaced by each of `seeds`."""
    seeds: tuple[int, ...]
    rounds: int


ENGINE_STUDIES: dict[str, EngineStudy] = {
    "smoke": EngineStudy("smoke", raw=(("esther", 2),), heldout=(("esther", 2),), seeds=(0,), rounds=2,
                         engine=EngineConfig("cpu-tiny", teacher_share=0.5, stage1_steps=0, stage2_steps=2, batch=2)),
    "full": EngineStudy("full", raw=(("esther", 150), ("hot3d_aria", 50)), heldout=(("esther", 12), ("hot3d_aria", 12)), seeds=(0, 1, 2),
                        rounds=2, engine=EngineConfig("cpu-tiny", teacher_share=0.2, stage1_steps=300, stage2_steps=500, batch=8)),
}  # fmt: skip
"""smoke: the pipeline and report on the smoke studies' clips (what the tests execute);
full: the issue's measurement, 200 clips of 64 frames on the paper's rig and Aria's, the
teacher labelling 20 %, three seeds of two rounds."""

OTHER_RIG_SEEDS = {"raw": 3001, "heldout": 4001}
"""Seeds of the synthesized clips of rigs other than the studies' own (esther)."""


def collection(scale: StudyScale, study: EngineStudy, root: str | pathlib.Path, name: str, *, progress: bool = True) -> list[pathlib.Path]:
    """The `raw` or `heldout` collection of `study`, linked as `root/<name>/<rig>_<clip>`
    (the engine keys clips by folder name): on the paper's rig (esther) the first clips of
    the studies' own `train` or `heldout` dataset (`studies.dataset`, shared with the other
    studies), on another rig clips synthesized under `root/data/<rig>_<name>` from their
    own seed (other motions than the esther clips', the studies' crop size). Made on first
    use, resumable; two studies on one root make the same links."""
    if name not in ("raw", "heldout"):
        raise ValueError(f"collection is 'raw' or 'heldout', got {name!r}")
    root = pathlib.Path(root)
    links = root / name
    links.mkdir(parents=True, exist_ok=True)
    for number, (rig, count) in enumerate(study.raw if name == "raw" else study.heldout):
        if rig == "esther":
            folders = dataset(scale, "train" if name == "raw" else "heldout", count=count, progress=progress)
        else:
            cfg = synth.SynthConfig(num_frames=scale.clip_frames, rig=rig, crops=True, crop_size=model_config(scale).crop_size)
            seed = OTHER_RIG_SEEDS[name] + 100 * number
            synth.synthesize(root / "data" / f"{rig}_{name}", count, cfg, seed=seed, progress=progress)
            folders = clips.list_clips(root / "data" / f"{rig}_{name}")[:count]
        for clip in folders:
            link = links / f"{rig}_{clip.name}"
            if not link.is_symlink():  # made beside the folder, not in it (list_clips would list a leftover), then renamed in
                tmp = root / f".{name}_{link.name}.{os.getpid()}"
                os.symlink(os.path.relpath(clip, links), tmp)
                os.replace(tmp, link)
    return clips.list_clips(links)


def same_frames(clip_dirs: list[pathlib.Path], labels_root: pathlib.Path, reference_root: pathlib.Path, names: set[str]) -> dict:
    """The accepted labels of the clips `names` in `labels_root` against the teacher's
    (`reference_root`) on the on-screen hand-frames both accepted, each against the
    ground truth: `frames`, `p_mpjpe_mm` and `wrist_mm` of both, and the differences
    (labels minus teacher; positive: the labels are worse). An empty dict when no frame
    is shared."""
    errors = {"labels": ([], []), "teacher": ([], [])}
    for clip in clip_dirs:
        if clip.name not in names:
            continue
        for side in clips.SIDES:
            paths = [clips.hand_file(clip, side, "gt")] + [clips.hand_file(r / clip.name, side, "labels") for r in (labels_root, reference_root)]
            if not all(p.is_file() for p in paths):
                continue
            gt = clips.load_npz(paths[0], "gt")
            ours, teacher = (clips.Labels.from_npz(p) for p in paths[1:])
            both = np.asarray(gt["onscreen"], bool) & np.asarray(ours.valid, bool) & np.asarray(teacher.valid, bool)
            for key, labels in (("labels", ours), ("teacher", teacher)):
                p_mm, wrist_mm = label_errors_mm(labels, gt["joints"])
                errors[key][0].append(p_mm[both])
                errors[key][1].append(wrist_mm[both])
    frames = sum(len(x) for x in errors["labels"][0])
    if frames == 0:
        return {}
    mean = {key: [float(np.mean(np.concatenate(x))) for x in pair] for key, pair in errors.items()}
    return {"frames": frames, "p_mpjpe_mm": mean["labels"][0], "wrist_mm": mean["labels"][1], "teacher_p_mpjpe_mm": mean["teacher"][0],
            "teacher_wrist_mm": mean["teacher"][1], "p_mpjpe_difference_mm": mean["labels"][0] - mean["teacher"][0],
            "wrist_difference_mm": mean["labels"][1] - mean["teacher"][1]}  # fmt: skip


def run_engine_study(scale: StudyScale, study: EngineStudy, root: str | pathlib.Path, *, progress: bool = True) -> dict:
    """Every seed's engine over the raw collection (module docstring); returns
    `{"seeds": {seed: [round record, ...]}, "clips": n, "heldout_clips": n}`, each round
    record a `round.json` with `"same_frames"` (its refined labels against the
    teacher's, rounds >= 1). Resumable: every part keeps its finished work."""
    from fitting import label_clips

    root = pathlib.Path(root)
    raw = collection(scale, study, root, "raw", progress=progress)
    heldout = collection(scale, study, root, "heldout", progress=progress)
    label_clips(raw, root / "reference", resume=True, progress=progress)
    names = {c.name for c in raw}
    seeds = {}
    for seed in study.seeds:
        out = root / f"seed_{seed}"
        cfg = dataclasses.replace(study.engine, seed=seed)
        rounds = run_engine(raw, out, cfg, rounds=study.rounds, val_dirs=heldout, progress=progress)
        taught = set(read_json(out / "engine.json")["teacher_clips"])
        for number, record in enumerate(rounds):
            if number > 0:
                record["same_frames"] = same_frames(raw, round_dir(out, number) / "refined", root / "reference", names - taught)
        seeds[seed] = rounds
    results = {"clips": len(raw), "heldout_clips": len(heldout), "raw": [list(r) for r in study.raw], "heldout": [list(r) for r in study.heldout],
               "seeds": seeds}  # fmt: skip
    write_json(root / "engine_study.json", results)
    return results


def _spread(values: list) -> str:
    values = [v for v in values if v is not None]
    if not values:
        return "n/a"
    return f"{np.mean(values):.2f}" if len(values) == 1 else f"{np.mean(values):.2f} ± {np.std(values, ddof=1):.2f}"


def round_table(results: dict) -> str:
    """Per round, mean ± sd over seeds: each group's coverage of on-screen hand-frames,
    the accepted labels' P-MPJPE and wrist error, the filter's misses (accepted labels
    worse than 15 mm), the refined labels against the teacher's on the same frames, and
    the cost (steady hand-frames/s: `engine.labelling_cost`)."""
    rows = list(zip(*results["seeds"].values()))  # per round, one record per seed
    head = ("| round | group | coverage % | P-MPJPE mm | wrist mm | accepted worse than 15 mm | same frames: P-MPJPE − teacher's mm "
            "| steady hand-frames/s |\n|---|---|---|---|---|---|---|---|")  # fmt: skip
    lines = [head]
    for number, records in enumerate(rows):
        for group in ("teacher", "refined", "all"):
            labels = [r["labels"].get(group) or {} for r in records]
            if not any(labels):
                continue
            cost = [r["cost"].get(group, {}).get("steady_hand_frames_per_s") for r in records] if group != "all" else []
            diff = [r.get("same_frames", {}).get("p_mpjpe_difference_mm") for r in records] if group == "refined" else []
            worse = [lab.get("worse_than_15mm") for lab in labels]
            accepted = [lab.get("accepted") for lab in labels]
            lines.append(
                f"| {number} | {group} | {_spread([100 * lab['coverage'] for lab in labels if lab])} | {_spread([lab.get('p_mpjpe_mm') for lab in labels])} "
                f"| {_spread([lab.get('wrist_mm') for lab in labels])} | {_spread(worse)} of {_spread(accepted)} | {_spread(diff)} | {_spread(cost)} |"
            )  # fmt: skip
    return "\n".join(lines)


NETWORK_METRICS = (("p_mpjpe_mm", "P-MPJPE mm"), ("pa_mpjpe_mm", "PA-MPJPE mm"), ("wrist_mm", "wrist mm"), ("keypoints_2d_px", "2D px"))


def network_table(results: dict) -> str:
    """Each round's network on the held-out windows, per seed with its bootstrap
    intervals (both views; the right view dropped)."""
    head = "| round | seed | views | " + " | ".join(title for _, title in NETWORK_METRICS) + " |\n|" + "---|" * (3 + len(NETWORK_METRICS))
    lines = [head]
    for seed, rounds in results["seeds"].items():
        for record in rounds:
            for views, scores in (record.get("network") or {}).items():
                cells = []
                for key, _ in NETWORK_METRICS:
                    value, span = scores.get(key), (scores.get("intervals") or {}).get(key)
                    cells.append("n/a" if value is None else f"{value:.1f}" + (f" [{span[0]:.1f}, {span[1]:.1f}]" if span else ""))
                lines.append(f"| {record['round']} | {seed} | {views} | " + " | ".join(cells) + " |")
    return "\n".join(lines)


def verdict(results: dict) -> dict:
    """The issue's three targets, per seed and overall: `throughput_ratio` (refined
    steady hand-frames/s over the teacher's, last round: compilation excluded, so a seed
    that compiled first is not slower), `same_frames_difference_mm` (refined
    minus teacher P-MPJPE on the same frames, last round), `round1_better` (round 1's
    held-out P-MPJPE below round 0's with intervals apart, both views)."""
    ratios, differences, better = [], [], []
    for rounds in results["seeds"].values():
        last = rounds[-1]
        teacher, refined = (last["cost"].get(g, {}).get("steady_hand_frames_per_s") for g in ("teacher", "refined"))
        ratios.append(refined / teacher if teacher and refined else None)
        differences.append(last.get("same_frames", {}).get("p_mpjpe_difference_mm"))
        if len(rounds) > 1 and rounds[0].get("network") and rounds[1].get("network"):
            a, b = rounds[0]["network"]["both"], rounds[1]["network"]["both"]
            span_a, span_b = (x.get("intervals", {}).get("p_mpjpe_mm") for x in (a, b))
            scored = None not in (a.get("p_mpjpe_mm"), b.get("p_mpjpe_mm"))
            better.append(bool(scored and b["p_mpjpe_mm"] < a["p_mpjpe_mm"] and separated(span_a, span_b)))
    present = lambda xs: [x for x in xs if x is not None]  # noqa: E731
    return {
        "throughput_ratio": ratios, "throughput_target_met": bool(present(ratios)) and min(present(ratios)) >= 5.0,
        "same_frames_difference_mm": differences, "same_frames_target_met": bool(present(differences)) and max(present(differences)) <= 1.0,
        "round1_better": better, "round1_target_met": bool(better) and all(better),
    }  # fmt: skip


__all__ = ["ENGINE_STUDIES", "EngineStudy", "collection", "network_table", "round_table", "run_engine_study", "same_frames", "verdict"]
