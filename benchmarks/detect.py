"""The real detector on pixels with exact ground truth (issue 15, point 3), side by side
with the simulated detector.

    python benchmarks/detect.py [--crop-clips 96] [--crop-frames 1] [--clips 8] [--frames 16] [--rig esther] [--out DIR]

1. Real-photo control (optional: skipped unless the MediaPipe reference photos with their
   published expected keypoints, tensorflow/tfjs-models' hand-pose-detection test data, sit
   in ORACLE): hands found in `hands.jpg` and the worst keypoint error against the reference;
   and degraded crops of the real hands (`real_hands_mirrored`), found as they are, mirrored,
   and with two looks: is MediaPipe mirror-symmetric on real hands?
2. Hand-centred crops: for every on-screen, in-view hand of `--crop-clips` one-frame rendered
   synthetic clips (`esther synth --render`; one frame each, because the frames of one clip
   are nearly the same image: 12 clips of 4 frames are about 20 distinct hands, and there an
   imperceptible change of the pixels, the frames before or after mp4 encoding, moved the
   count by 13 of 160 crops), a 224 px crop around its projected
   ground-truth keypoints (padding 1.25, 2.0 and 2.5 of the keypoints' box, `CROP_PADDINGS`)
   of the rendered frame, run through MediaPipe (image mode), on the crop alone and with its
   mirror pass (`MediaPipeHands`, the crop and its mirror). Detection rate (the hand
   itself found: median keypoint error under a quarter of its box), the failures split
   into "nothing detected" and "a hand detected in the wrong place", and the median over
   found hands of the median 2D keypoint error (crop px) against the projected ground
   truth, with the wrist's and the thumb's own medians (the keypoints a detector reads
   least well from our renders), and the rate for the left and the right hands apart (the
   detector is not mirror-symmetric). Target: >= 80 % detected, median error <= 8 px.
3. Canonical views (the renderer alone, no egocentric viewpoint): the built-in hand in
   each natural-pose archetype, palm or back to the camera, upright or rolled 35 degrees,
   light and dark skin, 42 cm away, filling about half of a 224 px image over a sampled
   background. Detection rate and median 2D error per skin tone.
4. Full frames end to end: `detect_clip` (MediaPipe, video mode, without and with the mirror
   pass: `mediapipe:direct`, `mediapipe`) on the rendered videos of
   `--clips` clips of `--frames` frames, then the teacher; coverage (labelled over on-screen hand-frames), P-MPJPE and
   wrist error (mm) against the ground truth, next to the teacher on the simulated
   detector's keypoints of the same clips; and where the on-screen hand-frames went:
   found under their own side, only under the other (handedness swapped), or not found.

Everything runs on the CPU, one process; the synthetic clips are made in `--out`
(default: a temporary folder). About 7 minutes on a 2-core machine (4 of them making the clips).
"""

import argparse
import dataclasses
import json
import pathlib
import tempfile
import time

import jax
import jax.numpy as jnp
import numpy as np

from esther_jax import clips, crops, metrics
from esther_jax.cameras import StereoRig
from esther_jax.data import SynthConfig, synthesize
from esther_jax.detect import MediaPipeHands, detect_clip
from fitting import label_clips

ORACLE = pathlib.Path(__file__).resolve().parents[2] / "shared" / "data" / "mediapipe_oracle"
CROP = 224
CROP_PADDINGS = (1.25, 2.0, 2.5)
"""Crop side over the hand box's longer side: 1.25, the network's crops (the hand fills
the crop); 2.0, the hand filling half of it, the context MediaPipe's palm detector,
which runs first on the whole image, is trained with; 2.5, more context (the 2D error
scales with the hand's size in the crop: about the same fraction of its box at every
padding)."""


def real_photo_control() -> dict | None:
    if not ORACLE.is_dir():
        return None
    import cv2

    expected = np.asarray(json.loads((ORACLE / "mediapipe_tasks_outputs.json").read_text())["tfjs_expected_hands_jpg"]["keypoints_px"])
    with MediaPipeHands(video=False) as detector:
        hands = detector.detect(cv2.imread(str(ORACLE / "hands.jpg"))[..., ::-1])
    worst = max(min(np.abs(h.uv + 0.5 - e).max() for h in hands) for e in expected) if hands else float("nan")
    return {"hands_found": len(hands), "hands_expected": len(expected), "worst_keypoint_error_px": float(worst)}


def _degraded_crop(image: np.ndarray, keypoints: np.ndarray, rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
    """A hard CROP px crop of a real hand (`keypoints` (21, 2) px, pixel centres): rotated by
    any angle, the hand's box 1/1.6 to 1/3 of the crop, contrast 25-100 %, exposure 50-120 %,
    Gaussian blur sigma 0.5-3 px, noise sigma 0-12, up to two flat rectangles over it; and
    its keypoints in the crop."""
    import cv2

    centre, size = keypoints.mean(axis=0), np.ptp(keypoints, axis=0).max()
    M = cv2.getRotationMatrix2D((float(centre[0]), float(centre[1])), rng.uniform(-180, 180), CROP / (rng.uniform(1.6, 3.0) * size))
    M[:, 2] += CROP / 2 - centre
    crop = cv2.warpAffine(image, M, (CROP, CROP), flags=cv2.INTER_AREA, borderMode=cv2.BORDER_REFLECT).astype(np.float32)
    crop = (crop - crop.mean()) * rng.uniform(0.25, 1.0) + crop.mean() * rng.uniform(0.5, 1.2)
    crop = cv2.GaussianBlur(crop, (0, 0), rng.uniform(0.5, 3.0)) + rng.normal(0.0, rng.uniform(0.0, 12.0), crop.shape)
    for _ in range(rng.integers(0, 3)):
        (x, y), (w, h) = rng.integers(0, CROP, 2), rng.integers(20, 80, 2)
        crop[y : y + h, x : x + w] = rng.uniform(0, 255, 3)
    return np.clip(crop, 0, 255).astype(np.uint8), keypoints @ M[:, :2].T + M[:, 2]


def real_hands_mirrored(repeats: int = 80) -> dict | None:
    """Is MediaPipe mirror-symmetric on real hands? `repeats` degraded crops (`_degraded_crop`,
    seeded) of each real hand of the oracle (the two left hands of `hands.jpg` at their
    published keypoints; the right hand of the ASL video, every 25th frame, at the reference
    output), each run with one look, its mirror with one look, and two looks
    (`MediaPipeHands`). Found: `found_hand`."""
    if not ORACLE.is_dir():
        return None
    import cv2

    oracle = json.loads((ORACLE / "mediapipe_tasks_outputs.json").read_text())
    photo = cv2.imread(str(ORACLE / "hands.jpg"))[..., ::-1]
    hands = [("left (hands.jpg)", photo, k - 0.5) for k in np.asarray(oracle["tfjs_expected_hands_jpg"]["keypoints_px"], np.float64)]
    reference = np.asarray(json.loads((ORACLE / "asl_hand.full.json").read_text()), np.float64)[..., :2]
    for t, frame in enumerate(clips.iter_video(ORACLE / "asl_hand.25fps.mp4")):
        if t % 25 == 0:
            hands.append(("right (ASL video)", frame, reference[t] - 0.5))
    rng = np.random.default_rng(0)
    found: dict[str, list] = {}
    with MediaPipeHands(video=False, mirror_pass=False) as one_look, MediaPipeHands(video=False) as two_looks:
        for _ in range(repeats):
            for name, image, keypoints in hands:
                crop, truth = _degraded_crop(image, keypoints, rng)
                mirrored_truth = truth * np.array([-1.0, 1.0]) + np.array([CROP - 1.0, 0.0])
                found.setdefault(name, []).append((
                    any(found_hand(h.uv, truth) for h in one_look.detect(crop)),
                    any(found_hand(h.uv, mirrored_truth) for h in one_look.detect(np.ascontiguousarray(crop[:, ::-1]))),
                    any(found_hand(h.uv, truth) for h in two_looks.detect(crop)),
                ))  # fmt: skip
    return {name: {"crops": len(v), "as_is": float(np.mean([r[0] for r in v])), "mirrored": float(np.mean([r[1] for r in v])),
                   "two_looks": float(np.mean([r[2] for r in v]))} for name, v in found.items()}  # fmt: skip


def found_hand(uv: np.ndarray, truth: np.ndarray) -> np.ndarray:
    """Whether detected keypoints `uv` (..., 21, 2) are the hand whose projected ground truth
    is `truth` (..., 21, 2): median keypoint error under a quarter of the longer side of
    the truth's box (a detection of the other hand, or of nothing in particular, is not)."""
    error = np.median(np.linalg.norm(uv - truth, axis=-1), axis=-1)
    return error < 0.25 * (truth.max(axis=-2) - truth.min(axis=-2)).max(axis=-1)


def crop_detection(clip_dirs: list[pathlib.Path], padding: float, mirror_pass: bool) -> dict:
    """MediaPipe on a CROP px crop around every on-screen, in-view hand (its projected
    ground-truth keypoints' box, `padding` x its longer side). The hand counts as found when
    a detection is it (`found_hand`)."""
    found, total, missed, errors, per_keypoint = 0, 0, 0, [], []
    found_per_side, total_per_side = dict.fromkeys(clips.SIDES, 0), dict.fromkeys(clips.SIDES, 0)
    seconds = 0.0
    with MediaPipeHands(video=False, mirror_pass=mirror_pass) as detector:
        for clip in clip_dirs:
            rig = StereoRig.from_json(clip / "rig.json")
            videos = [clips.read_video(clip / "video" / f"{v}.mp4") for v in ("left", "right")]
            for side in clips.SIDES:
                path = clips.hand_file(clip, side, "gt")
                if not path.is_file():
                    continue
                gt = clips.load_npz(path, "gt")
                uv = np.asarray(rig.project(jnp.asarray(gt["joints"])))  # (2, T, 21, 2)
                visible = np.asarray(rig.is_visible(jnp.asarray(gt["joints"])))  # (2, T, 21)
                for view in (0, 1):
                    for t in np.flatnonzero(gt["onscreen"] & (visible[view].mean(axis=-1) >= 0.5)):
                        box = np.concatenate([uv[view, t].min(axis=0), uv[view, t].max(axis=0)])
                        M = crops.crop_affine(jnp.asarray(box), CROP, padding)
                        image = crops.warp_crop(videos[view][t], box, CROP, padding)
                        truth = uv[view, t] @ M[:, :2].T + M[:, 2]
                        image = np.asarray(image)
                        tic = time.perf_counter()
                        hands = detector.detect(image)
                        seconds += time.perf_counter() - tic
                        total += 1
                        total_per_side[side] += 1
                        missed += not hands
                        best = min(hands, key=lambda h: np.median(np.linalg.norm(h.uv - truth, axis=-1)), default=None)
                        if best is not None and found_hand(best.uv, truth):
                            distances = np.linalg.norm(best.uv - truth, axis=-1)
                            found += 1
                            found_per_side[side] += 1
                            errors.append(np.median(distances))
                            per_keypoint.append(distances)
    median = lambda values: float(np.median(values)) if len(values) else None  # noqa: E731
    per_keypoint = np.asarray(per_keypoint).reshape(-1, 21)
    return {"hand_crops": total, "detected": found, "detection_rate": found / max(total, 1),
            "nothing_detected": missed, "detected_elsewhere": total - found - missed,
            "median_error_px": median(errors), "wrist_median_error_px": median(per_keypoint[:, 0]),
            "thumb_median_error_px": median(per_keypoint[:, 1:5].ravel()),
            "finger_median_error_px": median(per_keypoint[:, 5:].ravel()),
            "detection_rate_per_side": {s: found_per_side[s] / max(total_per_side[s], 1) for s in clips.SIDES},
            "ms_per_crop": 1000 * seconds / max(total, 1)}  # fmt: skip


def canonical_views() -> dict:
    from esther_jax import mano
    from esther_jax.cameras import PinholeCamera
    from esther_jax.data import render
    from esther_jax.mano.builtin_generator import ARCHETYPES, archetype_angles
    from esther_jax.rotations import matrix_to_axis_angle

    model = mano.load_builtin("right")
    frames = mano.anatomical_frames(model.joint_template, model.v_template[model.fingertip_ids], model.is_right)
    camera = PinholeCamera(260.0, 260.0, (CROP - 1) / 2, (CROP - 1) / 2, CROP, CROP)
    upright = np.array([[0.0, 0.0, 1.0], [1.0, 0.0, 0.0], [0.0, 1.0, 0.0]])  # model x (wrist side) -> image down
    rows = {}
    with MediaPipeHands(video=False, mirror_pass=False) as detector:  # the renderer alone: right hands, one look
        for tone, skin in (("light", render.SKIN_TONES[1]), ("dark", render.SKIN_TONES[4])):
            scene = dataclasses.replace(render.sample_scene(np.random.default_rng(0)), skin=skin)
            found, errors = 0, []
            for name in ARCHETYPES:
                hand_pose = mano.anatomical_to_hand_pose(jnp.asarray(archetype_angles(name)), frames)
                for palm_to_camera in (True, False):
                    for roll in (0.0, 0.6):
                        flip = np.diag([1.0, 1.0, 1.0]) if palm_to_camera else np.diag([1.0, -1.0, -1.0])
                        c, s_ = np.cos(roll), np.sin(roll)
                        R = np.array([[c, -s_, 0.0], [s_, c, 0.0], [0.0, 0.0, 1.0]]) @ upright @ flip
                        params = mano.ManoParams(matrix_to_axis_angle(jnp.asarray(R)), hand_pose, jnp.zeros(10), jnp.zeros(3))
                        out = mano.forward(model, params)
                        joints = np.asarray(out.joints, np.float64)
                        shift = np.array([0.0, 0.0, 0.42]) - 0.5 * (joints.min(axis=0) + joints.max(axis=0))
                        mesh = render.Mesh(np.asarray(out.vertices, np.float64) + shift, np.asarray(model.faces), skin, "skin", render.hand_rest_vertices())
                        image, _ = render.render_view(scene, camera, np.eye(4), [mesh])
                        truth = np.asarray(camera.project(jnp.asarray(joints + shift)))
                        hands = detector.detect(image)
                        if hands:
                            found += 1
                            errors.append(min(np.median(np.linalg.norm(h.uv - truth, axis=-1)) for h in hands))
            total = len(ARCHETYPES) * 4
            rows[tone] = {"views": total, "detected": found, "median_error_px": float(np.median(errors)) if errors else None}
    return rows


def _label_scores(clip_dirs: list[pathlib.Path], labels_root: pathlib.Path) -> dict:
    p, w, labelled, onscreen = [], [], 0, 0
    for clip in clip_dirs:
        for side in clips.SIDES:
            gt_path = clips.hand_file(clip, side, "gt")
            if not gt_path.is_file():
                continue
            gt = clips.load_npz(gt_path, "gt")
            onscreen += int(gt["onscreen"].sum())
            path = clips.hand_file(labels_root / clip.name, side, "labels")
            if not path.is_file():
                continue
            labels = clips.Labels.from_npz(path)
            ok = np.asarray(labels.valid) & gt["onscreen"]
            labelled += int(ok.sum())
            if ok.any():
                pred, true = labels.joints[ok], jnp.asarray(gt["joints"][ok])
                p += list(np.asarray(jax.vmap(metrics.p_mpjpe)(pred, true)) * 1000)
                w += list(np.asarray(jax.vmap(metrics.wrist_error)(pred, true)) * 1000)
    return {"coverage": labelled / max(onscreen, 1), "p_mpjpe_mm": float(np.mean(p)) if p else None,
            "wrist_mm": float(np.mean(w)) if w else None, "hand_frames": labelled}  # fmt: skip


def _where_hands_went(clip_dirs: list[pathlib.Path], detected_root: pathlib.Path) -> dict:
    """Each on-screen ground-truth hand-frame, by what `detect_clip` made of it: found under
    its own side in at least one view (`found_hand` in that view), found only under the other
    side (handedness swapped), or not found."""
    counts = {"own_side": 0, "other_side_only": 0, "not_found": 0}
    for clip in clip_dirs:
        rig = StereoRig.from_json(clip / "rig.json")
        for side, other in zip(clips.SIDES, clips.SIDES[::-1]):
            gt_path = clips.hand_file(clip, side, "gt")
            if not gt_path.is_file():
                continue
            gt = clips.load_npz(gt_path, "gt")
            truth = np.asarray(rig.project(jnp.asarray(gt["joints"]))).transpose(1, 0, 2, 3)  # (T, 2, 21, 2)

            def found(name: str) -> np.ndarray:
                path = clips.hand_file(detected_root / clip.name, name, "keypoints")
                if not path.is_file():
                    return np.zeros(len(truth), bool)
                keypoints = clips.load_npz(path, "keypoints")  # uv (D, T, 2, 21, 2), box_score (D, T, 2)
                return ((keypoints["box_score"] > 0) & found_hand(keypoints["uv"], truth[None])).any(axis=(0, 2))

            own, swapped, onscreen = found(side), found(other), gt["onscreen"]
            counts["own_side"] += int((onscreen & own).sum())
            counts["other_side_only"] += int((onscreen & swapped & ~own).sum())
            counts["not_found"] += int((onscreen & ~own & ~swapped).sum())
    return counts


def end_to_end(clip_dirs: list[pathlib.Path], work: pathlib.Path, detector: str) -> dict:
    """`detect_clip` with `detector` on every clip, then the teacher on its keypoints."""
    folder = detector.replace(":", "_")
    detected_root, labels_root = work / f"detected_{folder}", work / f"labels_{folder}"
    detected = []
    frames_with_hands = 0
    tic = time.perf_counter()
    for clip in clip_dirs:
        out = detected_root / clip.name
        report = detect_clip(clip / "video" / "left.mp4", clip / "video" / "right.mp4", clip / "rig.json", out, detectors=(detector,), progress=False)
        frames_with_hands += report["frames_with_hands"][detector]
        detected.append(out)
    rows = {"frames_with_hands": frames_with_hands, "detect_s": time.perf_counter() - tic, "hand_frames": _where_hands_went(clip_dirs, detected_root)}
    with_keypoints = [c for c in detected if any(clips.hand_file(c, s, "keypoints").is_file() for s in clips.SIDES)]
    if with_keypoints:
        label_clips(with_keypoints, labels_root)
        rows["labels"] = _label_scores(clip_dirs, labels_root)
    else:
        rows["labels"] = {"coverage": 0.0, "p_mpjpe_mm": None, "wrist_mm": None, "hand_frames": 0}
    return rows


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--crop-clips", type=int, default=96, help="clips for the hand-centred crops")
    parser.add_argument("--crop-frames", type=int, default=1, help="frames per crop clip")
    parser.add_argument("--clips", type=int, default=8, help="clips for the end-to-end run")
    parser.add_argument("--frames", type=int, default=16, help="frames per end-to-end clip")
    parser.add_argument("--rig", default="esther")
    parser.add_argument("--out", help="work folder (default: temporary)")
    args = parser.parse_args()
    work = pathlib.Path(args.out) if args.out else pathlib.Path(tempfile.mkdtemp(prefix="esther_detect_bench_"))
    start = time.perf_counter()
    synthesize(work / "crop_clips", args.crop_clips, SynthConfig(num_frames=args.crop_frames, rig=args.rig, render=True), seed=15, progress=False)
    synthesize(work / "clips", args.clips, SynthConfig(num_frames=args.frames, rig=args.rig, render=True), seed=16, progress=False)
    crop_clips, clip_dirs = clips.list_clips(work / "crop_clips"), clips.list_clips(work / "clips")
    print(f"made {len(crop_clips)} + {len(clip_dirs)} rendered clips ({args.rig}, {args.crop_frames} and {args.frames} frames) "
          f"in {time.perf_counter() - start:.0f} s")  # fmt: skip
    control = real_photo_control()
    if control:
        print(f"real photo (hands.jpg): {control['hands_found']}/{control['hands_expected']} hands, worst keypoint error "
              f"{control['worst_keypoint_error_px']:.1f} px (reference tolerance 20 px)")  # fmt: skip
    for name, row in (real_hands_mirrored() or {}).items():
        print(f"degraded crops of a real {name} hand: found {row['as_is']:.0%} as they are, {row['mirrored']:.0%} mirrored, "
              f"{row['two_looks']:.0%} with two looks ({row['crops']} crops)")  # fmt: skip
    px = lambda v: f"{v:.1f} px" if v is not None else "n/a"  # noqa: E731
    for padding in CROP_PADDINGS:
        for mirror_pass, looks in ((False, "the image"), (True, "the image and its mirror")):
            crop = crop_detection(crop_clips, padding, mirror_pass)
            per_side = crop["detection_rate_per_side"]
            print(f"hand-centred {CROP} px crops of renders, padding {padding}, MediaPipe on {looks}: "
                  f"{crop['detected']}/{crop['hand_crops']} detected ({crop['detection_rate']:.0%}; target >= 80 %; "
                  f"left hands {per_side['left']:.0%}, right {per_side['right']:.0%}; missed: {crop['nothing_detected']} "
                  f"nothing detected, {crop['detected_elsewhere']} a hand in the wrong place), median 2D error "
                  f"{px(crop['median_error_px'])} (target <= 8 px; wrist {px(crop['wrist_median_error_px'])}, "
                  f"thumb {px(crop['thumb_median_error_px'])}, fingers {px(crop['finger_median_error_px'])}); "
                  f"{crop['ms_per_crop']:.1f} ms per crop")  # fmt: skip
    for tone, row in canonical_views().items():
        print(f"canonical views, {tone} skin: {row['detected']}/{row['views']} detected, median 2D error {px(row['median_error_px'])}")
    rows = {}
    for detector in ("mediapipe:direct", "mediapipe"):
        run = end_to_end(clip_dirs, work, detector)
        went = run["hand_frames"]
        print(f"full frames, {detector} (video mode, {run['detect_s']:.0f} s for {len(clip_dirs)} clips): hands in {run['frames_with_hands']} frames; of "
              f"{sum(went.values())} on-screen hand-frames, {went['own_side']} found under their own side, "
              f"{went['other_side_only']} only under the other side (handedness swapped), {went['not_found']} not found")  # fmt: skip
        rows[detector] = run["labels"]
    label_clips(clip_dirs, work / "labels_simulated")
    rows["simulated"] = _label_scores(clip_dirs, work / "labels_simulated")
    print("| keypoints | coverage | P-MPJPE (mm) | wrist (mm) |\n|---|---|---|---|")
    fmt = lambda v: f"{v:.1f}" if v is not None else "n/a"  # noqa: E731
    for name, r in rows.items():
        print(f"| {name} | {r['coverage']:.0%} | {fmt(r['p_mpjpe_mm'])} | {fmt(r['wrist_mm'])} |")
    print(f"total {time.perf_counter() - start:.0f} s; work folder {work}")


if __name__ == "__main__":
    main()
