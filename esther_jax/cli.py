"""The `esther` command line (thin: parse, call the library, print)."""

import argparse
import dataclasses
import functools
import pathlib
import sys

from .files import check_out_dir, write_json


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    try:  # before minutes of work: the output folder must be a writable folder (crops writes into its clips; train
        # creates and locks its run folder at once, and removes it again when the run fails to start; prior writes a file)
        if args.command not in ("crops", "train", "prior"):
            check_out_dir(args.out)
    except ValueError as err:
        print(f"esther {args.command}: {err}", file=sys.stderr)
        return 2
    from . import enable_compilation_cache

    enable_compilation_cache()
    return args.run(args)


def build_parser() -> argparse.ArgumentParser:
    """`esther`'s parser: a subcommand per `_COMMANDS` entry, its run function `args.run`."""
    top = argparse.ArgumentParser(prog="esther", description="ESTHER: metric 3D hands from egocentric stereo (JAX)")
    commands = top.add_subparsers(dest="command", required=True)
    for add_command in _COMMANDS:  # each adds its parser, whose defaults name its run function
        add_command(commands)
    return top


def _config_flags(parser, cls, flags: dict[str, dict]) -> None:
    """A flag for each field of the dataclass `cls` named in `flags`, in the fields'
    order: `--field-name` (`flags[name]["flag"]` renames it), its type, default and help
    (the field's docstring, then the default) from the field, other `flags[name]` keys
    given to `add_argument` as they are (e.g. `choices`, or a `help` or `default` of the
    command's own). A bool field is a switch, a Literal one a choice. The value lands in
    `args.<cls name>.<field>` (`_config_values`)."""
    import ast
    import inspect
    import textwrap
    import typing

    try:
        source = ast.parse(textwrap.dedent(inspect.getsource(cls))).body[0].body
    except (OSError, TypeError):  # no source (e.g. only compiled files installed): flags without their docstrings
        source = []
    docs = {node.target.id: after.value.value for node, after in zip(source, source[1:])
            if isinstance(node, ast.AnnAssign) and isinstance(after, ast.Expr) and isinstance(after.value, ast.Constant)}  # fmt: skip
    types = typing.get_type_hints(cls)
    for field in dataclasses.fields(cls):
        if field.name not in flags:
            continue
        options = dict(flags[field.name])
        flag = options.pop("flag", "--" + field.name.replace("_", "-"))
        options.setdefault("default", field.default)
        hint = types[field.name]
        if typing.get_origin(hint) is typing.Literal:  # its values are the choices
            options.setdefault("choices", list(typing.get_args(hint)))
            hint = type(typing.get_args(hint)[0])
        kind = next(t for t in (typing.get_args(hint) or (hint,)) if t is not type(None))  # X | None: X
        if kind is bool:
            options.setdefault("action", argparse.BooleanOptionalAction if options["default"] else "store_true")
        else:
            options.setdefault("type", kind)
            if "choices" not in options:
                options.setdefault("metavar", flag.removeprefix("--").replace("-", "_").upper())
        if "help" not in options and field.name in docs:
            text = " ".join(docs[field.name].replace("`", "").replace("%", "%%").split()).removesuffix(".")
            options["help"] = text[0].lower() + text[1:] if text[1:2].islower() else text
        if options["default"] is not None and options["default"] is not False and "help" in options:
            options["help"] += " (default %(default)s)"
        parser.add_argument(flag, dest=f"{cls.__name__}.{field.name}", **options)


def _config_values(args, cls) -> dict:
    """The fields of `cls` that `_config_flags` made flags of, as parsed."""
    prefix = cls.__name__ + "."
    return {key.removeprefix(prefix): value for key, value in vars(args).items() if key.startswith(prefix)}


def _demo_parser(commands) -> None:
    demo = commands.add_parser("demo", help="run the main job on the embedded default (built-in hand model)")
    demo.add_argument("--out", default="esther_demo", help="output folder (default: ./esther_demo)")
    demo.add_argument("--seed", type=int, default=0)
    demo.add_argument("--frames", type=int, default=128, help="frames of the synthetic clip (default 128)")
    demo.set_defaults(run=_demo)


def _demo(args) -> int:
    from .demo import run

    run(args.out, seed=args.seed, frames=args.frames)
    return 0


def _evaluate_parser(commands) -> None:
    evaluate = commands.add_parser("evaluate", help="compare label folders with ground truth; write metrics, tables, figures")
    evaluate.add_argument("--pred", required=True, help="folder of predicted labels (<clip>/hands/<side>/labels.npz)")
    evaluate.add_argument("--gt", required=True, help="folder of clips with ground truth (<clip>/hands/<side>/gt.npz)")
    evaluate.add_argument("--out", default="evaluation", help="output folder (default: ./evaluation)")
    evaluate.add_argument("--method", default="prediction", help="method name for the tables")
    evaluate.add_argument("--seed", type=int, default=0, help="bootstrap seed")
    evaluate.add_argument(
        "--params", default="auto", choices=["auto", "require", "skip"],
        help="MANO parameter metrics (pose angle, betas), only between labels of the same model: 'auto' compares "
        "the hands whose recorded models match and says which it did not; 'require' fails unless all match; "
        "'skip' scores joints only. Joints are always scored",
    )  # fmt: skip
    evaluate.add_argument("--preset", default="esther", choices=["esther", "hot3d"],
                          help="esther: our tables (P-MPJPE, PA-MPJPE, wrist, jitter, ...); hot3d: HOT3D's official pose metrics "
                               "(19 landmarks, absolute MPJPE, PCK-AUC, every 10th frame, frame-weighted, ground-truth shape substituted)")  # fmt: skip
    evaluate.add_argument("--mano", metavar="DIR", help="with --preset hot3d: your MANO files, when the labels are parameters of them")
    evaluate.set_defaults(run=_evaluate)


def _evaluate(args) -> int:
    if args.preset == "hot3d":
        return _evaluate_hot3d(args)
    from .eval import evaluate_folders

    if args.mano:
        print("esther evaluate: --mano is for --preset hot3d (our preset compares the labels' own joints)", file=sys.stderr)
        return 2

    try:
        result = evaluate_folders(args.pred, args.gt, args.out, method=args.method, seed=args.seed, parameters=args.params)
    except ValueError as err:  # bad folders or files, models that differ with --params require: say what
        print(f"esther evaluate: {err}", file=sys.stderr)
        return 2
    skipped = result["parameters"]["not_compared"]
    if skipped:
        print(
            f"esther evaluate: MANO parameters (pose, betas) not compared for {len(skipped)} of {result['num_hands']} "
            f"hands, joints scored for all (list in metrics.json); first, {skipped[0]['hand']}: {skipped[0]['reason']}",
            file=sys.stderr,
        )
    if result["identity_unverified"]:
        print(
            f"esther evaluate: {len(result['identity_unverified'])} predicted clips record no source clip (not labelled by "
            f"esther label?), so their identity was not checked: {', '.join(result['identity_unverified'][:5])}",
            file=sys.stderr,
        )
    print((pathlib.Path(args.out) / "table.md").read_text())
    missing = result["missing_predictions"]
    print(
        f"{result['num_hands']} hands scored, {len(missing)} ground-truth hands with no prediction"
        + (f" ({', '.join(missing[:3])}{', ...' if len(missing) > 3 else ''})" if missing else "")
        + f"; coverage {result['coverage']:.1%} of the on-screen ground-truth hand-frames; wrote {pathlib.Path(args.out).resolve()}"
    )
    return 0


def _evaluate_hot3d(args) -> int:
    from .eval import evaluate_hot3d_folders

    try:
        models = _mano_models(args.mano)[0] if args.mano else None
        result = evaluate_hot3d_folders(args.pred, args.gt, args.out, models)
    except (OSError, ValueError) as err:
        print(f"esther evaluate: {err}", file=sys.stderr)
        return 2
    print((pathlib.Path(args.out) / "table.md").read_text())
    print(f"{len(result['per_sequence'])} hands, {len(result['missing'])} not labelled; wrote {pathlib.Path(args.out).resolve()}")
    return 0


def _synth_parser(commands) -> None:
    synth = commands.add_parser("synth", help="make synthetic egocentric stereo clips with exact ground truth")
    synth.add_argument("--out", required=True, help="output folder (clip_00000, clip_00001, ...)")
    synth.add_argument("--clips", type=int, default=10, help="number of clips (an interrupted run resumes)")
    synth.add_argument("--frames", type=int, default=64, help="frames per clip (30 fps)")
    synth.add_argument("--rig", default="esther", choices=["esther", "esther_mocap", "hot3d_aria", "hot3d_quest3"])
    synth.add_argument("--render", action="store_true", help="render both views to video/*.mp4 and the hand crops")
    synth.add_argument("--crops", action="store_true", help="render only the hand crops and flow tokens")
    synth.add_argument("--crop-size", type=int, default=224, help="side of the hand crops in pixels (default 224; cpu-tiny uses 64)")
    synth.add_argument(
        "--crop-strategy", default="offbb120", choices=["offbb120", "offbb90", "offbb150", "hc"],
        help="rectification of the crops (paper, appendix M): offbbF, an axis-aligned crop of the image undistorted to a "
        "pinhole of focal F px (the three give the same crops here: they are rendered directly, so only the crop camera "
        "counts, and it does not depend on F); hc, a crop turned to look along the hand's ray. Default offbb120",
    )  # fmt: skip
    synth.add_argument("--detector-preset", default="default", choices=["clean", "easy", "default", "hard"])
    synth.add_argument("--vertices", action="store_true", help="store ground-truth vertices in gt.npz")
    synth.add_argument("--shape-sd", type=float, default=1.0, help="standard deviation of the hands' MANO betas (default 1; larger: held-out hand sizes)")
    synth.add_argument("--depth-range", type=float, nargs=2, default=[0.15, 0.8], metavar=("NEAR", "FAR"),
                       help="limits of the wrist depth in metres (default 0.15 0.8); with --depth-sampling uniform, the range covered")  # fmt: skip
    synth.add_argument(
        "--depth-sampling", default="egocentric", choices=["egocentric", "uniform"],
        help="wrist depths: egocentric, the training statistics (0.22-0.7 m, mostly 0.25-0.5 m), or uniform over --depth-range "
        "(held-out sets past the training range, e.g. --depth-range 0.1 1.1). Default egocentric",
    )  # fmt: skip
    synth.add_argument("--seed", type=int, default=0)
    synth.set_defaults(run=_synth)


def _synth(args) -> int:
    from .data.motion import MotionConfig
    from .data.synth import SynthConfig, synthesize

    if args.clips < 0 or args.frames < 3:
        print("esther synth: need --clips >= 0 and --frames >= 3", file=sys.stderr)
        return 2
    if args.crop_size < 16:
        print("esther synth: need --crop-size >= 16", file=sys.stderr)
        return 2
    try:
        motion = MotionConfig(shape_sd=args.shape_sd, depth_range_m=tuple(args.depth_range), depth_sampling=args.depth_sampling)
        cfg = SynthConfig(num_frames=args.frames, rig=args.rig, detector_preset=args.detector_preset, render=args.render,
                          crops=args.crops, vertices=args.vertices, crop_size=args.crop_size, crop_strategy=args.crop_strategy,
                          motion_config=motion)  # fmt: skip
        summary = synthesize(args.out, args.clips, cfg, seed=args.seed)
    except ValueError as err:  # settings out of range, or a folder made with other settings
        print(f"esther synth: {err}", file=sys.stderr)
        return 2
    print(f"made {summary['made']} clips, kept {summary['skipped']} finished ones, in {summary['seconds']:.1f} s: {summary['out']}")
    return 0


def _label_parser(commands) -> None:
    label = commands.add_parser("label", help="label clip folders with the teacher (metric MANO from stereo 2D keypoints)")
    label.add_argument("clips", nargs="+", help="clip folders (or folders of clips)")
    label.add_argument("--out", required=True, help="output folder (<clip>/hands/<side>/labels.npz, quality.json)")
    label.add_argument("--resume", action="store_true", help="skip clips whose labels are complete and made the same way (models, pose prior, method revision and settings)")
    label.add_argument("--reject", help="human-review reject list: lines 'clip,side,frame'")
    label.add_argument("--review", action="store_true", help="also write a contact sheet of flagged frames per hand")
    label.add_argument(
        "--mano", metavar="DIR",
        help="fit your official MANO models, DIR/MANO_RIGHT.pkl and DIR/MANO_LEFT.pkl (or DIR/models/...), "
        "instead of the built-in hand; the labels record which model they are parameters of",
    )  # fmt: skip
    _ray_flag(label)
    label.add_argument("--pose-prior", metavar="FILE", help="a learned pose prior (esther prior --out FILE) in place of the hand model's PCA prior (the joint limits stay)")
    label.set_defaults(run=_label)


def _ray_flag(parser) -> None:
    parser.add_argument("--ray", metavar="ADDRESS", help="one task per clip on a Ray cluster: local (a private instance on this machine), auto (the "
                                                   "cluster ray start runs here, else local) or HOST:PORT; the optional extra 'ray'")


def _pose_prior(path: str | None):
    """The learned pose prior of `--pose-prior FILE` (None without one)."""
    from .mano import GMMPosePrior

    return None if path is None else GMMPosePrior.load(path)


def _label(args) -> int:
    from fitting import label_clips, read_reject_list
    from fitting.label import review_clip

    clips = _clip_folders(args.clips, "label")
    if clips is None:
        return 2
    try:
        rejects = read_reject_list(args.reject) if args.reject else frozenset()
        models, sources = _mano_models(args.mano) if args.mano else (None, None)
        job = functools.partial(label_clips, out_dir=args.out, resume=args.resume, rejects=rejects, models=models, model_sources=sources,
                                pose_prior=_pose_prior(args.pose_prior))  # fmt: skip
        result = _per_clip(job, clips, args.ray, "label", _LABELS_EMPTY)
    except (OSError, ValueError) as err:  # unwritable --out, clashing clip names, bad reject list or MANO file
        print(f"esther label: {err}", file=sys.stderr)
        return 2
    if args.review:
        for summary in result["labelled"]:
            for sheet in review_clip(next(c for c in clips if c.name == summary["clip"]), pathlib.Path(args.out)):
                print(f"review sheet: {sheet}")
    return _report_labels("labelled", result, pathlib.Path(args.out))


_LABELS_EMPTY = {"labelled": [], "skipped": [], "failed": [], "hand_frames": 0, "seconds": 0.0}
"""`label_clips`' result of no clip."""


def _per_clip(job, clip_dirs: list[pathlib.Path], ray_address: str | None, desc: str, empty: dict) -> dict:
    """The batch function `job` over `clip_dirs`: in this process, or one Ray task per clip (`--ray`)."""
    if ray_address is None:
        return job(clip_dirs)
    from .cluster import map_clips

    return map_clips(job, clip_dirs, address=ray_address, desc=desc, empty=empty)


def _report_labels(verb: str, result: dict, out: pathlib.Path) -> int:
    """Print a labelling run's failures and counts, merge its summary into `out`; the exit code."""
    for failure in result["failed"]:
        print(f"FAILED {failure['clip']}: {failure['error']}", file=sys.stderr)
    rate = result["hand_frames"] / max(result["seconds"], 1e-9)
    print(
        f"{verb} {len(result['labelled'])} clips ({result['hand_frames']} hand-frames in {result['seconds']:.1f} s, "
        f"{rate:.3g} hand-frames/s), "
        f"skipped {len(result['skipped'])}, failed {len(result['failed'])} -> {out.resolve()}"
    )
    _write_label_summary(out, result)
    return 1 if result["failed"] else 0


def _refine_parser(commands) -> None:
    refine = commands.add_parser("refine", help="a trained network's predictions refined against clips' 2D keypoints into labels (the data engine)")
    refine.add_argument("clips", nargs="+", help="clip folders (or folders of clips) with hands/<side>/keypoints.npz (and crops/ for --model)")
    refine.add_argument("--model", help="a run folder of esther train (or its model/ folder): predict every hand first, into --predictions")
    refine.add_argument("--predictions", metavar="DIR", help="the network's predictions (esther predict --out; default OUT/.predictions): "
                                                             "written there with --model, else read from there")  # fmt: skip
    refine.add_argument("--out", required=True, help="output folder, the teacher's format (<clip>/hands/<side>/labels.npz, quality.json)")
    refine.add_argument("--resume", action="store_true", help="skip clips whose labels are complete and refined from the same prediction the same way (method revision and settings)")
    _ray_flag(refine)
    refine.add_argument("--pose-prior", metavar="FILE", help="a learned pose prior (esther prior --out FILE) in place of the hand model's PCA prior (the joint limits stay)")
    refine.set_defaults(run=_refine)


def _refine(args) -> int:
    from fitting import refine_clips

    from .model.folders import predict_folders

    clip_dirs = _clip_folders(args.clips, "refine")
    if clip_dirs is None:
        return 2
    predictions = pathlib.Path(args.predictions) if args.predictions else pathlib.Path(args.out) / ".predictions"
    try:
        pose_prior = _pose_prior(args.pose_prior)
        if args.model:
            job = functools.partial(predict_folders, args.model, out_dir=predictions, resume=args.resume)
            predicted = _per_clip(job, clip_dirs, args.ray, "predict", {"predicted": [], "skipped": [], "failed": []})
            for failure in predicted["failed"]:
                print(f"FAILED to predict {failure['clip']}: {failure['error']}", file=sys.stderr)
        elif not predictions.is_dir():
            print(f"esther refine: no predictions in {predictions}: pass --model RUN (or --predictions DIR of esther predict)", file=sys.stderr)
            return 2
        job = functools.partial(refine_clips, predictions=predictions, out_dir=args.out, resume=args.resume, pose_prior=pose_prior)
        result = _per_clip(job, clip_dirs, args.ray, "refine", _LABELS_EMPTY)
    except (OSError, ValueError) as err:  # no saved network, unwritable --out, clashing clip names
        print(f"esther refine: {err}", file=sys.stderr)
        return 2
    return _report_labels("refined", result, pathlib.Path(args.out))


def _write_label_summary(out: pathlib.Path, result: dict) -> None:
    """`out/label_summary.json`: this run's result (its counts and seconds are this run's),
    its 'labelled' list also keeping the earlier runs' entries of the clips this run did
    not label or fail (skipped as done, or not in its list: their labels are still in
    `out`); under a lock, as two runs may label into one folder."""
    from .files import exclusive_lock, read_json

    path = out / "label_summary.json"
    with exclusive_lock(out / ".label_summary.lock"):
        earlier = read_json(path).get("labelled", []) if path.is_file() else []
        now = {entry["clip"] for entry in result["labelled"]} | {pathlib.Path(f["clip"]).name for f in result["failed"]}
        kept = [entry for entry in earlier if entry.get("clip") not in now]
        write_json(path, {**result, "labelled": kept + result["labelled"]})


def _detect_parser(commands) -> None:
    detect = commands.add_parser("detect", help="stereo videos (or image folders) + rig.json -> a clip folder with 2D keypoints")
    detect.add_argument("recordings", nargs="*", metavar="RECORDING",
                        help="recording folders (rig.json beside left/ and right/ image folders or left.mp4 and right.mp4): each becomes "
                             "--out/<recording>; or give one recording's --left, --right and --rig")  # fmt: skip
    detect.add_argument("--left", help="the left view: a video file or a folder of images (sorted by name)")
    detect.add_argument("--right", help="the right view, same number of frames")
    detect.add_argument("--rig", help="rig.json (docs/architecture.md, 'File formats'): the calibration of both views")
    detect.add_argument("--out", required=True, help="the clip folder to write (esther label reads it); with RECORDINGs, the folder of their clips")
    detect.add_argument("--detector", action="append", metavar="NAME",
                        help="mediapipe (default; the detect extra; each image and its mirror), mediapipe:direct (the image only, "
                             "half the time), onnx:MODEL.onnx (a YOLO-pose hand model you own) or "
                             "vitpose:MODEL.onnx[@BOXES] (a top-down heatmap model you own, on the boxes of the detector BOXES, "
                             "default mediapipe); repeat for several detectors (the D axis of keypoints.npz)")  # fmt: skip
    detect.add_argument("--fps", type=float, help="frame rate (read from the videos when omitted; needed for image folders)")
    detect.add_argument("--rectify", default="offbb120", choices=["offbb120", "offbb90", "offbb150"],
                        help="fisheye views are undistorted to this wide pinhole for detection (appendix M), keypoints mapped back")  # fmt: skip
    detect.add_argument("--videos", default="link", choices=["link", "copy", "encode"], help="how the clip's video/*.mp4 are made (image folders: encoded)")
    detect.add_argument("--resume", action="store_true", help="with RECORDINGs: skip those whose clip is complete (detected by the same detectors)")
    _ray_flag(detect)
    detect.set_defaults(run=_detect)


def _detect(args) -> int:
    from .clips import ClipFormatError
    from .detect import DetectorUnavailable, detect_clip, detect_recordings

    detectors = tuple(args.detector or ["mediapipe"])
    one = [flag for flag in ("left", "right", "rig") if getattr(args, flag) is not None]
    if args.recordings and one:
        print(f"esther detect: give RECORDING folders or --left, --right and --rig, not both (got RECORDING folders and --{', --'.join(one)})", file=sys.stderr)
        return 2
    if not args.recordings and len(one) < 3:
        print("esther detect: give RECORDING folders, or one recording's --left, --right and --rig", file=sys.stderr)
        return 2
    if not args.recordings and (args.resume or args.ray):
        print("esther detect: --resume and --ray are for RECORDING folders (one clip resumes from its saved frames by itself)", file=sys.stderr)
        return 2
    try:
        if args.recordings:
            job = functools.partial(detect_recordings, out_dir=args.out, detectors=detectors, fps=args.fps, strategy=args.rectify,
                                    videos=args.videos, resume=args.resume)  # fmt: skip
            result = _per_clip(job, [pathlib.Path(r) for r in args.recordings], args.ray, "detect",
                               {"detected": [], "skipped": [], "failed": []})  # fmt: skip
        else:
            report = detect_clip(args.left, args.right, args.rig, args.out, detectors=detectors, fps=args.fps, strategy=args.rectify,
                                 videos=args.videos)  # fmt: skip
    except (DetectorUnavailable, ClipFormatError, OSError, ValueError, RuntimeError) as err:
        print(f"esther detect: {err}", file=sys.stderr)
        return 2
    if args.recordings:
        for failure in result["failed"]:
            print(f"FAILED {failure['clip']}: {failure['error']}", file=sys.stderr)
        for clip in result["detected"]:
            print(f"{clip['clip']}: {clip['frames']} frames, sides {', '.join(clip['sides']) or 'none'}")
        print(f"detected {len(result['detected'])} recordings, skipped {len(result['skipped'])}, failed {len(result['failed'])} "
              f"-> {pathlib.Path(args.out).resolve()} (next: esther label {args.out} --out LABELS)")  # fmt: skip
        return 1 if result["failed"] else 0
    for name, frames in report["frames_with_hands"].items():
        tracks = report["handedness"][name]["tracks"]
        dropped = sum(t["side"] == "dropped" for t in tracks)
        print(f"{name}: hands in {frames} frames; {len(tracks)} tracks" + (f" ({dropped} dropped: a side already taken)" if dropped else ""))
    print(f"sides: {', '.join(report['sides']) or 'none'} -> {pathlib.Path(args.out).resolve()} (next: esther label {args.out} --out LABELS)")
    return 0


def _import_hot3d_parser(commands) -> None:
    importer = commands.add_parser(
        "import-hot3d", help="HOT3D sequences or HOT3D-Clips tars -> clip folders (calibration, head motion, boxes, MANO ground truth)"
    )
    importer.add_argument("sources", nargs="+", help="per-sequence export folders (metadata.json, mano_hand_pose_trajectory.jsonl, ...) or clip tars")
    importer.add_argument("--out", required=True, help="output folder (one clip folder per source)")
    importer.add_argument("--mano", metavar="DIR", help="your MANO_RIGHT.pkl and MANO_LEFT.pkl: needed for gt.npz (HOT3D's ground truth is MANO)")
    importer.set_defaults(run=_import_hot3d)


def _import_hot3d(args) -> int:
    from .clips import ClipFormatError
    from .data.hot3d import import_hot3d
    from .mano import ManoFileError

    try:
        models, sources = _mano_models(args.mano) if args.mano else (None, None)
        reports = import_hot3d(args.sources, args.out, models, sources)
    except (ClipFormatError, ManoFileError, OSError, ValueError) as err:
        print(f"esther import-hot3d: {err}", file=sys.stderr)
        return 2
    for report in reports:
        print(f"{report['source']} -> {report['clip']}: {len(report['timestamps_ns'])} frames; wrote {', '.join(report['written'])}")
        for missing in report["not_written"]:
            print(f"  not written: {missing['file']} ({missing['why']})")
    return 0


def _clip_folders(paths: list[str], command: str) -> list[pathlib.Path] | None:
    """The clip folders under `paths` (each a clip or a folder of clips); None (after
    saying why) when a path is not a folder or holds no clip."""
    from .clips import ClipFormatError, list_clips

    found = []
    for path in paths:
        try:
            more = list_clips(path)
        except ClipFormatError as err:
            print(f"esther {command}: {err}", file=sys.stderr)
            return None
        if not more:
            print(f"esther {command}: no clip found in {path} (a clip folder holds rig.json, meta.json and hands/)", file=sys.stderr)
            return None
        found += more
    return found


def _initialize_distributed() -> None:
    """`jax.distributed.initialize`, its arguments from JAX_COORDINATOR_ADDRESS,
    JAX_NUM_PROCESSES and JAX_PROCESS_ID where set (else JAX's cluster auto-detection)."""
    import os

    import jax

    env = {"coordinator_address": os.environ.get("JAX_COORDINATOR_ADDRESS"), "num_processes": os.environ.get("JAX_NUM_PROCESSES"),
           "process_id": os.environ.get("JAX_PROCESS_ID")}  # fmt: skip
    kwargs = {k: (int(v) if k != "coordinator_address" else v) for k, v in env.items() if v is not None}
    jax.distributed.initialize(**kwargs)


def _train_parser(commands) -> None:
    from .model.config import BACKBONES, CONFIGS, ModelConfig
    from .train.data import TARGET_KINDS, DataConfig
    from .train.losses import STAGES
    from .train.loop import TrainConfig

    train = commands.add_parser("train", help="train the ESTHER network on clip folders (appendices B, C, E)")
    train.add_argument("--config", default="cpu-small", choices=list(CONFIGS),
                       help="model config (esther_jax.model.CONFIGS; default cpu-small; cpu-small-hand: MediaPipe's pretrained hand backbone)")
    train.add_argument("--data", nargs="+", required=True, help="clip folders (or folders of clips) with crops and targets")
    train.add_argument("--out", required=True, help="run folder (config.json, checkpoints/, metrics.jsonl, model/)")
    train.add_argument("--init", help="start from a previous run's network (e.g. stage 1's run folder)")
    train.add_argument("--resume", action="store_true", help="continue --out from its latest checkpoint")
    train.add_argument("--val", nargs="+", help="held-out clip folders (or folders of clips) validated during training")
    train.add_argument("--backbone-weights", metavar="FILE", help="DINOv3 weights (.pth, .npz, .safetensors) for the ViT backbone of a fresh network")
    train.add_argument("--distributed", action="store_true",
                       help="one process of a multi-host run: jax.distributed.initialize() from the environment (JAX_COORDINATOR_ADDRESS, "
                            "JAX_NUM_PROCESSES, JAX_PROCESS_ID, or SLURM / Open MPI / TPU auto-detection)")  # fmt: skip
    model = train.add_argument_group("network (the named --config, changed by these)")
    model.add_argument("--ablation", help="a table-5 row (esther_jax.model.ABLATIONS)")
    _config_flags(model, ModelConfig, {
        "num_frames": {"flag": "--frames", "default": None, "help": f"window length (the config's num_frames by default: {ModelConfig.num_frames})"},
        "backbone": {"default": None, "choices": list(BACKBONES), "help": "the image backbone (default: the config's; "
                                                                      "mediapipe-hand: MediaPipe's pretrained hand network, crops a multiple of 32 px)"},
        "freeze_backbone": {"default": None, "action": argparse.BooleanOptionalAction,
                            "help": "keep the backbone's weights fixed (default: the config's; frozen for paper and cpu-small-hand); "
                                    "--no-freeze-backbone fine-tunes it (a feature cache needs it frozen)"},
        "triangulated_wrist_input": {"default": None, "help": "the wrist query also reads the encoder's triangulated wrist (not in the paper: "
                                                              "docs/architecture.md); give it to both stages"},
    })  # fmt: skip
    model.add_argument("--bf16", action=argparse.BooleanOptionalAction, default=None,
                       help="mixed precision: bfloat16 compute, float32 weights, geometry and losses (default: on for the paper config)")
    _config_flags(train.add_argument_group("training (esther_jax.train.TrainConfig)"), TrainConfig, {
        "stage": {"choices": list(STAGES)}, "steps": {}, "batch": {}, "learning_rate": {"flag": "--lr"}, "warmup_steps": {"flag": "--warmup"},
        "seed": {}, "ema_decay": {"flag": "--ema", "metavar": "DECAY"}, "checkpoint_every": {}, "validate_every": {}, "validation_windows": {},
        "frames_apart": {"help": "--stage image: draw each example's frames one by one from every window of its hand and rig (more hands per batch)"},
    })  # fmt: skip
    _config_flags(train.add_argument_group("data (esther_jax.train.DataConfig)"), DataConfig, {
        "targets": {"choices": list(TARGET_KINDS), "help": "gt.npz of synthetic clips, or the teacher's labels"},
        "labels": {"help": "the teacher's label folder (esther label --out) when --targets labels"},
        "features": {"metavar": "DIR", "help": "a feature cache for a frozen backbone: filled once (resumable), then read instead of the crops"},
    })  # fmt: skip
    train.set_defaults(run=_train)


def _train(args) -> int:
    if args.distributed:
        _initialize_distributed()
    from . import model as M
    from . import train

    data = _clip_folders(args.data, "train")
    val = _clip_folders(args.val, "train") if args.val else None
    if data is None or (args.val and val is None):
        return 2
    try:
        overrides = {k: v for k, v in _config_values(args, M.ModelConfig).items() if v is not None}  # given: the named config's otherwise
        model_cfg = M.config(args.config, ablation=args.ablation, **overrides)
        bf16 = args.bf16 if args.bf16 is not None else args.config == "paper"
        cfg = train.TrainConfig(**_config_values(args, train.TrainConfig), compute_dtype="bfloat16" if bf16 else "float32")
        data_cfg = train.DataConfig(frames=model_cfg.num_frames, crop_size=model_cfg.crop_size, **_config_values(args, train.DataConfig))
        summary = train.train(args.out, data, model_cfg, cfg, data_cfg=data_cfg, val_dirs=val, init=args.init, resume=args.resume,
                              backbone_weights=args.backbone_weights)  # fmt: skip
    except train.NonFiniteLoss as err:
        print(f"esther train: {err}", file=sys.stderr)
        return 1
    except (OSError, ValueError) as err:  # bad configs, folders, a run that exists, a mismatched resume
        print(f"esther train: {err}", file=sys.stderr)
        return 2
    if summary["steps"] == summary["resumed_from"]:
        print(f"{args.out} was already trained to step {summary['steps']}: nothing to train -> {summary['model']}")
    else:
        fresh = " (no checkpoint to resume: from the start)" if args.resume and summary["resumed_from"] == 0 else ""
        print(f"trained {summary['steps']} steps (from step {summary['resumed_from']}){fresh} in {summary['seconds']:.0f} s -> {summary['model']}")
    for views, scores in summary.get("validation", {}).items():
        shown = ", ".join(f"{k} {v:.1f}" if v is not None else f"{k} n/a" for k, v in scores.items() if k.endswith(("_mm", "_px")))
        print(f"validation ({views}, {scores['windows']} windows): {shown}, on-screen F1 {scores['onscreen_f1']:.2f}")
    print(f"learning curves: {summary['curves']}")
    return 0


def _crops_parser(commands) -> None:
    crops = commands.add_parser("crops", help="cut each hand's crops from clip folders' videos (esther train and predict read them)")
    crops.add_argument("clips", nargs="+", help="clip folders (or folders of clips) with video/left.mp4, video/right.mp4 and hands/")
    crops.add_argument("--labels", metavar="DIR", help="the teacher's labels (esther label --out): crop around the labelled hands where valid "
                                                       "(else around gt.npz's hands; else the detectors' keypoints)")  # fmt: skip
    crops.add_argument("--size", type=int, default=224, help="crop side in pixels, the network config's (cpu-tiny 64, cpu-small 112, paper 224)")
    crops.add_argument("--strategy", default="offbb120", choices=["offbb120", "offbb90", "offbb150", "hc"],
                       help="rectification of the crops (appendix M), as esther synth --crop-strategy")  # fmt: skip
    crops.add_argument("--overwrite", action="store_true", help="replace crops made by esther synth or with other settings")
    _ray_flag(crops)
    crops.set_defaults(run=_crops)


def _crops(args) -> int:
    from .data.video_crops import CropConfig, crop_clips

    clip_dirs = _clip_folders(args.clips, "crops")
    if clip_dirs is None:
        return 2
    try:
        job = functools.partial(crop_clips, cfg=CropConfig(size=args.size, strategy=args.strategy), labels=args.labels, overwrite=args.overwrite)
        result = _per_clip(job, clip_dirs, args.ray, "crops", {"cropped": [], "skipped": [], "failed": []})
    except ValueError as err:  # settings out of range, no labels folder
        print(f"esther crops: {err}", file=sys.stderr)
        return 2
    for failure in result["failed"]:
        print(f"FAILED {failure['clip']}: {failure['error']}", file=sys.stderr)
    hands = sum(len(r["hands"]) for r in result["cropped"])
    print(f"cropped {hands} hands of {len(result['cropped'])} clips ({args.size} px, {args.strategy}), "
          f"{len(result['skipped'])} already done, failed {len(result['failed'])}")
    return 1 if result["failed"] else 0


def _predict_parser(commands) -> None:
    predict = commands.add_parser("predict", help="a trained network's hands for clip folders, in the labels format")
    predict.add_argument("--model", required=True, help="a run folder of esther train (or its model/ folder)")
    predict.add_argument("clips", nargs="+", help="clip folders (or folders of clips) with crops/<side>.npz")
    predict.add_argument("--out", required=True, help="output folder (<clip>/hands/<side>/labels.npz: esther evaluate reads it)")
    predict.add_argument("--resume", action="store_true", help="keep clips already predicted by the same network")
    predict.set_defaults(run=_predict)


def _predict(args) -> int:
    from .model.folders import predict_folders

    clip_dirs = _clip_folders(args.clips, "predict")
    if clip_dirs is None:
        return 2
    try:
        result = predict_folders(args.model, clip_dirs, args.out, resume=args.resume)
    except (OSError, ValueError) as err:  # no saved network there, a damaged one
        print(f"esther predict: {err}", file=sys.stderr)
        return 2
    for failure in result["failed"]:
        print(f"FAILED {failure['clip']}: {failure['error']}", file=sys.stderr)
    kept = f", kept {len(result['skipped'])}" if result["skipped"] else ""
    print(f"predicted {len(result['predicted'])} clips{kept}, failed {len(result['failed'])} -> {pathlib.Path(args.out).resolve()}")
    return 1 if result["failed"] else 0


def _mano_models(folder: str) -> tuple[dict, dict[str, str]]:
    """Both hands of the user's official MANO models (`--mano DIR`) and their paths."""
    from . import mano

    root = pathlib.Path(folder)
    if not root.is_dir():
        raise mano.ManoFileError(f"--mano {folder} is not a folder; give the folder that holds MANO_RIGHT.pkl and MANO_LEFT.pkl")
    if not (root / "MANO_RIGHT.pkl").exists() and (root / "models" / "MANO_RIGHT.pkl").exists():
        root = root / "models"  # the official download unpacks to mano_v*_*/models/
    models, sources = {}, {}
    for side in ("right", "left"):
        path = root / f"MANO_{side.upper()}.pkl"
        if not path.is_file():
            raise mano.ManoFileError(
                f"{path} is missing: --mano needs both MANO_RIGHT.pkl and MANO_LEFT.pkl (your licensed files from "
                "https://mano.is.tue.mpg.de; we never ship or download them)"
            )
        models[side] = mano.load_mano_pkl(path, side=side)
        sources[side] = str(path.resolve())
        fixed = " (x shapedirs negated: the official left model's sign bug, smplx#48)" if bool(models[side].left_shapedirs_fixed) else ""
        print(f"{side} hand: {path} = MANO model {mano.model_id(models[side])}{fixed}")
    return models, sources


def _prior_parser(commands) -> None:
    prior = commands.add_parser("prior", help="fit a learned pose prior (a Gaussian mixture) to labels and/or the synthetic engine's motion")
    prior.add_argument("--out", required=True, help="the prior's file (.npz): esther label / refine --pose-prior read it")
    prior.add_argument("--labels", nargs="+", metavar="DIR", help="label folders (esther label --out): their accepted frames' poses")
    prior.add_argument("--synthetic", type=int, default=0, metavar="SEQUENCES",
                       help="also this many 3-second sequences of the synthetic engine's articulation (default 0)")
    prior.add_argument("--components", type=int, default=8, help="mixture components (default 8)")
    prior.add_argument("--iterations", type=int, default=100, help="EM iterations (default 100)")
    prior.add_argument("--seed", type=int, default=0)
    prior.set_defaults(run=_prior)


def _prior(args) -> int:
    import numpy as np

    from .clips import accepted_hand_poses
    from .data.motion import sample_hand_poses
    from .mano import fit_gmm_pose_prior

    if not args.labels and args.synthetic <= 0:
        print("esther prior: nothing to fit: give --labels DIR... and/or --synthetic SEQUENCES", file=sys.stderr)
        return 2
    try:
        poses = [accepted_hand_poses(d) for d in args.labels or []]
        if args.synthetic > 0:
            poses.append(sample_hand_poses(args.seed, args.synthetic).astype(np.float32))
        poses = np.concatenate(poses)
        prior = fit_gmm_pose_prior(poses, components=args.components, iterations=args.iterations, seed=args.seed)
        path = prior.save(args.out)
    except (OSError, ValueError) as err:  # unreadable labels (ClipFormatError), too few poses
        print(f"esther prior: {err}", file=sys.stderr)
        return 2
    print(f"fitted a {args.components}-component pose prior to {len(poses)} poses -> {path}")
    return 0


def _engine_parser(commands) -> None:
    from .engine import EngineConfig
    from .model.config import CONFIGS

    engine = commands.add_parser("engine", help="the data engine: teacher labels a share, then rounds of train, predict, refine, filter")
    engine.add_argument("clips", nargs="+", help="the raw collection: clip folders (or folders of clips) with hands/<side>/keypoints.npz and crops/")
    engine.add_argument("--out", required=True, help="engine folder (engine.json, teacher/, round_NNN/: labels, run, round.json)")
    engine.add_argument("--rounds", type=int, default=2, help="rounds to run or resume (round 0: the teacher's labels alone; default 2)")
    engine.add_argument("--val", nargs="+", help="held-out clips with ground truth: each round's network is scored on them")
    engine.add_argument("--features", metavar="DIR", help="a feature cache of a frozen backbone (e.g. --config cpu-small-hand), shared by the rounds")
    d = EngineConfig()
    engine.add_argument("--config", default=d.config, choices=list(CONFIGS), help=f"the network's config (default {d.config})")
    engine.add_argument("--teacher-share", type=float, default=d.teacher_share, help=f"share of the clips the teacher labels (default {d.teacher_share})")
    engine.add_argument("--stage1-steps", type=int, default=d.stage1_steps)
    engine.add_argument("--stage2-steps", type=int, default=d.stage2_steps)
    engine.add_argument("--batch", type=int, default=d.batch)
    engine.add_argument("--lr", type=float, default=d.learning_rate, help="peak learning rate (of both stages unless --stage1-lr)")
    engine.add_argument("--stage1-lr", type=float, help="stage 1's peak learning rate")
    engine.add_argument("--frames-apart", action="store_true", help="stage 1 draws each example's frames apart")
    engine.add_argument("--warm-start", action="store_true", help="a later round starts from the previous round's network (default: from scratch)")
    engine.add_argument("--seed", type=int, default=d.seed, help="seed of the teacher's share and of the training")
    engine.add_argument("--pose-prior", metavar="FILE", help="a learned pose prior (esther prior) for the teacher and the refinement")
    engine.set_defaults(run=_engine)


def _engine(args) -> int:
    from .engine import EngineConfig, run_engine

    clip_dirs = _clip_folders(args.clips, "engine")
    val = _clip_folders(args.val, "engine") if args.val else None
    if clip_dirs is None or (args.val and val is None):
        return 2
    try:
        cfg = EngineConfig(config=args.config, teacher_share=args.teacher_share, stage1_steps=args.stage1_steps, stage2_steps=args.stage2_steps,
                           batch=args.batch, learning_rate=args.lr, stage1_learning_rate=args.stage1_lr, frames_apart=args.frames_apart,
                           warm_start=args.warm_start, seed=args.seed, pose_prior=args.pose_prior)  # fmt: skip
        records = run_engine(clip_dirs, args.out, cfg, rounds=args.rounds, val_dirs=val, features=args.features)
    except (OSError, ValueError) as err:  # a bad plan, another engine on --out, a resume with other options
        print(f"esther engine: {err}", file=sys.stderr)
        return 2
    for r in records:
        labels = r["labels"]["all"]
        cover = f", coverage {labels['coverage']:.1%} of {labels['onscreen']} on-screen hand-frames" if labels else ""
        net = r.get("network", {}).get("both")
        scored = f"; held-out P-MPJPE {net['p_mpjpe_mm']:.1f} mm, wrist {net['wrist_mm']:.1f} mm" if net else ""
        print(f"round {r['round']}: {r['teacher_clips']} teacher + {r['refined_clips']} refined clips{cover}{scored}")
        for failure in r["failed"]:
            print(f"  FAILED {failure['clip']}: {failure['error']}", file=sys.stderr)
    print(f"-> {pathlib.Path(args.out).resolve()}")
    return 1 if any(r["failed"] for r in records) else 0


_COMMANDS = (_demo_parser, _evaluate_parser, _synth_parser, _detect_parser, _import_hot3d_parser, _crops_parser, _label_parser,
             _train_parser, _predict_parser, _refine_parser, _prior_parser, _engine_parser)  # fmt: skip
"""The commands in `esther --help`'s order: each function adds one's parser."""


if __name__ == "__main__":
    sys.exit(main())
