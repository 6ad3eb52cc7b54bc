"""The teacher: compilation and cache reuse, accuracy and speed across rigs, and its solvers
side by side, with the public `fitting` API only.

    python benchmarks/teacher.py [--clips 4] [--frames 64] [--section compile|sweep|solvers|step|refine|prior|all] [--quick]

1. Compile / cache (issue 11, point 6). Each measurement runs in a fresh process
   (`--child`) given a fresh temporary directory through `esther_jax.enable_compilation_cache`:
   (a) cold: time to the first label of a 64-frame clip on `esther` (pinhole) and on
       `hot3d_quest3` (fisheye). Targets: pinhole <= 20 s, fisheye <= 40 s.
   (b) a second process on the same rig with the now-warm cache: time to the first label
       (the teacher's programs loaded from `programs/`, not traced; their executables from
       the XLA cache, not compiled), and whether its labels are bit-identical to the cold
       process's. Target: <= 5 s.
   (c) in that warm process, a clip on a third rig of the same camera model and image size
       but another calibration (pinhole: the esther pair with fx 700 px, cx 950 px and a 5 cm
       longer baseline; fisheye: the Quest 3 pair with 5 % longer focals and a 90 mm
       baseline; the image size is a camera's static field): the backend compilations it
       triggers, counted with `jax.monitoring` on "/jax/core/compile/backend_compile_duration"
       (loads from the persistent cache told apart by "/jax/compilation_cache/cache_hits").
       Target: the solver (`solve_round`) compiles nothing.
2. Rig sweep: esther, hot3d_quest3, hot3d_aria; N clips of F frames (default detector
   preset, both hands), the default `LabelConfig`. Coverage (valid and on screen over on
   screen, on screen from the ground truth), P-MPJPE, PA-MPJPE and wrist error (mm, over
   valid on-screen frames) for stereo frames, monocular frames (`labels.stereo`) and
   all; hand-frames/s without the first (compiling) call of each rig. Targets: esther
   P-MPJPE <= 4 mm, wrist <= 5 mm and >= 200 hand-frames/s; hot3d_aria >= 80 % of the
   on-screen hand-frames labelled, with P-MPJPE <= 15 mm and wrist <= 25 mm (read two
   ways: means over the labelled frames, and per frame).
3. Solvers (`fitting.SOLVERS`) side by side on the esther clips, persistent cache off and
   in-memory caches cleared before each: first call (compilation) and the backend
   compilation of the solver's program within it, time per hand after compilation,
   P-MPJPE and wrist error. A solver that fails is reported, not fatal.
4. One solver step (`--section step`): for one hand's frames of an esther clip, the
   residuals, the normal equations formed from forward-mode autodiff of all residuals and
   as the solver assembles them from the objective's structure
   (`objectives.frame_normal_equations`), its closed-form reprojection part, and the
   Cholesky solve, each timed alone; the two normal equations' agreement.
5. Refine (`--section refine`, issue 49): `fitting.refine` from each hand's ground truth
   perturbed as a network's prediction (`START_NOISE`: close, far, and as this project's
   networks predict) against the teacher on the same hands, on the esther and hot3d_aria
   rigs: hand-frames/s, coverage, P-MPJPE (also on the frames both accept), accepted
   labels worse than 15 mm; targets: refine >= 5x the teacher's throughput, within 1 mm
   of its P-MPJPE on the frames both accept.
6. Pose priors (`--section prior`, issue 49): the learned prior (`mano.GMMPosePrior`)
   against the PCA + joint-limit prior inside the teacher and inside refine: coverage,
   rejection rate, P-MPJPE, wrist and accepted labels worse than 15 mm on the same hands.

`--quick` is a smoke run (1 clip of 32 frames; section 1 only when asked for by
`--section compile`, then on 32-frame clips); the targets are for the full settings.
"""

import time

_T_IMPORT = time.perf_counter()

import argparse  # noqa: E402
import hashlib  # noqa: E402
import json  # noqa: E402
import os  # noqa: E402
import subprocess  # noqa: E402
import sys  # noqa: E402
import tempfile  # noqa: E402

import jax  # noqa: E402
import jax.numpy as jnp  # noqa: E402
import numpy as np  # noqa: E402

sys.path.insert(0, os.path.dirname(__file__))
from _timing import machine  # noqa: E402

import esther_jax  # noqa: E402
import fitting  # noqa: E402
from esther_jax import cameras, clips, compilation, mano, metrics  # noqa: E402
from esther_jax.data import detector, motion, synth  # noqa: E402
from fitting import objectives, solve  # noqa: E402
from jax.flatten_util import ravel_pytree  # noqa: E402

_T_IMPORTED = time.perf_counter()

COMPILE_EVENT = "/jax/core/compile/backend_compile_duration"
CACHE_HIT_EVENT = "/jax/compilation_cache/cache_hits"
TRACE_EVENT = "/jax/core/compile/jaxpr_trace_duration"  # top-level traces only (no nesting)
LOWER_EVENT = "/jax/core/compile/jaxpr_to_mlir_module_duration"
SOLVER_PROGRAM = "solve_round"
MOTION = motion.MotionConfig(two_hands_probability=1.0)
RIGS = ("esther", "hot3d_quest3", "hot3d_aria")
CAMERA_MODELS = {"pinhole": "esther", "fisheye": "hot3d_quest3"}
COLD_TARGET_S = {"pinhole": 20.0, "fisheye": 40.0}
WARM_TARGET_S = 5.0
ESTHER_TARGETS = {"p_mpjpe": 4.0, "wrist": 5.0, "throughput": 200.0}
ARIA_TARGETS = {"coverage": 0.80, "p_mpjpe": 15.0, "wrist": 25.0}

TARGETS: list[tuple[str, str, bool]] = []  # (what, measured vs target, met)


def target(what: str, value: float, limit: float, unit: str, *, at_most: bool = True, fmt: str = ".1f") -> str:
    """Record a target and return "value (target <= limit): meets|misses"."""
    met = bool(np.isfinite(value) and (value <= limit if at_most else value >= limit))
    text = f"{value:{fmt}}{unit} (target {'<=' if at_most else '>='} {limit:{fmt}}{unit}): {'meets' if met else 'misses'}"
    TARGETS.append((what, text, met))
    return text


def num(value: float, width: int, fmt: str = ".2f") -> str:
    """A right-aligned table cell; "-" where there is nothing to measure (NaN)."""
    return f"{value:>{width}{fmt}}" if np.isfinite(value) else f"{'-':>{width}}"


# ----------------------------------------------------------------------------- compilations


class CompileLog:
    """Every backend compilation of this process, seen through `jax.monitoring`:
    (program, seconds, loaded from the persistent cache), and the seconds spent tracing
    and lowering (which no cache saves)."""

    def __init__(self):
        self.events: list[tuple[str, float, bool]] = []
        self.staging: list[tuple[str, float]] = []  # (event, seconds)
        self._hit = False
        jax.monitoring.register_event_listener(self._on_event)
        jax.monitoring.register_event_duration_secs_listener(self._on_duration)

    def _on_event(self, event, **kwargs):
        if event == CACHE_HIT_EVENT:  # recorded inside the compile call it belongs to
            self._hit = True

    def _on_duration(self, event, seconds, **kwargs):
        if event == COMPILE_EVENT:
            self.events.append((str(kwargs.get("fun_name", "?")), float(seconds), self._hit))
            self._hit = False
        elif event in (TRACE_EVENT, LOWER_EVENT):
            self.staging.append((event, float(seconds)))

    def mark(self) -> tuple[int, int]:
        return len(self.events), len(self.staging)

    def summary(self, since: tuple[int, int] = (0, 0)) -> dict:
        events = self.events[since[0]:]
        staging = self.staging[since[1]:]
        fresh = [e for e in events if not e[2]]
        solver = [e for e in fresh if SOLVER_PROGRAM in e[0]]
        top = sorted(fresh, key=lambda e: -e[1])[:3]
        return {
            "compiled": len(fresh),
            "compiled_s": sum(e[1] for e in fresh),
            "cache_hits": sum(e[2] for e in events),
            "cache_hit_s": sum(e[1] for e in events if e[2]),
            "solver_compiled": len(solver),
            "solver_compiled_s": sum(e[1] for e in solver),
            "top": [(name, round(s, 2)) for name, s, _ in top],
            "trace_s": sum(s for e, s in staging if e == TRACE_EVENT),
            "lower_s": sum(s for e, s in staging if e == LOWER_EVENT),
        }


def pinhole_variant() -> cameras.StereoRig:
    """The esther pair with another calibration: fx = fy 700 px, cx 950 px, baseline 112 mm."""
    base = cameras.rig_preset("esther")
    cam = cameras.PinholeCamera(700.0, 700.0, 950.0, float(base.left.cy), base.left.width, base.left.height)
    T = np.eye(4)
    T[0, 3] = float(base.baseline) + 0.05
    return cameras.StereoRig(cam, cam, jnp.asarray(T, jnp.result_type(float)))


def fisheye_variant() -> cameras.StereoRig:
    """The Quest 3 pair with another calibration: focals 5 % longer, baseline 90 mm."""
    base = cameras.rig_preset("hot3d_quest3")
    longer = lambda cam: cameras.Fisheye624Camera.from_params(cam.params.at[:2].multiply(1.05), cam.width, cam.height)  # noqa: E731
    T = np.array(base.T_left_right, np.float64)
    T[:3, 3] *= 0.090 / float(base.baseline)
    return cameras.StereoRig(longer(base.left), longer(base.right), jnp.asarray(T, jnp.result_type(float)))


THIRD_RIG = {"esther": (pinhole_variant, "esther, fx 700 px, cx 950 px, baseline 112 mm"),
             "hot3d_quest3": (fisheye_variant, "hot3d_quest3, focals 5 % longer, baseline 90 mm")}  # fmt: skip


def hand_on(rig: cameras.StereoRig, seed: int, index: int, frames: int):
    """One hand of a synthetic clip on any rig (what `synth.make_clip` does for presets)."""
    rng = synth.clip_rng(seed, index)
    m = motion.sample_clip(rng, rig, frames, MOTION)
    side = sorted(m.hands)[0]
    keypoints = detector.simulate_detectors(rng, rig, np.asarray(m.hands[side].joints, np.float64), m.visibility[side], "default")
    return side, keypoints, m.fps


def child(mode: str, rig_name: str, cache: str, frames: int) -> dict:
    """One process of section 1: first label on `rig_name`; in the warm mode also a third rig."""
    esther_jax.enable_compilation_cache(cache)
    log = CompileLog()
    out = {"imports_s": _T_IMPORTED - _T_IMPORT}
    t0 = time.perf_counter()
    side, keypoints, fps = hand_on(cameras.rig_preset(rig_name), 11, 0, frames)
    model = mano.load_builtin(side)
    out["synthesis_s"] = time.perf_counter() - t0
    mark = log.mark()
    t0 = time.perf_counter()
    labels, _ = fitting.label_hand(model, cameras.rig_preset(rig_name), keypoints, fps)
    out["first_label_s"] = time.perf_counter() - t0
    out["first_label"] = log.summary(mark)
    out["labels_sha256"] = labels_digest(labels)
    if mode == "warm":
        rig = THIRD_RIG[rig_name][0]()
        side, keypoints, fps = hand_on(rig, 11, 1, frames)
        model = mano.load_builtin(side)
        mark = log.mark()
        t0 = time.perf_counter()
        fitting.label_hand(model, rig, keypoints, fps)
        out["third_label_s"] = time.perf_counter() - t0
        out["third_rig"] = log.summary(mark)
    return out


def labels_digest(labels: clips.Labels) -> str:
    """A digest of a hand's labels, to tell whether two processes computed the same bits."""
    h = hashlib.sha256()
    for path, leaf in jax.tree_util.tree_leaves_with_path(labels):
        h.update(jax.tree_util.keystr(path).encode() + np.ascontiguousarray(leaf).tobytes())
    return h.hexdigest()


def run_child(mode: str, rig: str, cache: str, frames: int, timeout: float = 1200.0) -> dict:
    command = [sys.executable, os.path.abspath(__file__), "--child", mode, "--rig", rig, "--cache", cache, "--frames", str(frames)]
    t0 = time.perf_counter()
    try:
        proc = subprocess.run(command, capture_output=True, text=True, timeout=timeout)
    except subprocess.TimeoutExpired:
        return {"error": f"timed out after {timeout:.0f} s"}
    wall = time.perf_counter() - t0
    lines = [line for line in proc.stdout.splitlines() if line.startswith("RESULT ")]
    if proc.returncode or not lines:
        tail = (proc.stderr or proc.stdout).strip().splitlines()[-3:]
        return {"error": f"exit {proc.returncode}: " + " | ".join(tail)}
    result = json.loads(lines[-1][len("RESULT "):])
    result["process_s"] = wall
    return result


def _compiles(s: dict) -> str:
    top = ", ".join(f"{name} {sec:.1f} s" for name, sec in s["top"])
    return (f"trace {s['trace_s']:.1f} s, lower {s['lower_s']:.1f} s; {s['compiled']} programs compiled in {s['compiled_s']:.1f} s, "
            f"{s['cache_hits']} loaded from the cache in {s['cache_hit_s']:.1f} s" + (f"; slowest: {top}" if top else ""))  # fmt: skip


def compile_section(frames: int):
    print(f"\n== 1. compilation and the persistent cache ({frames}-frame clips, a fresh process each) ==")
    if frames != 64:
        print("   (smoke scale: the targets are for 64-frame clips)")
    for kind, rig in CAMERA_MODELS.items():
        third = THIRD_RIG[rig][1]
        print(f"{kind} ({rig}; third rig: {third}):")
        with tempfile.TemporaryDirectory(prefix=f"esther_cache_{kind}_") as cache:
            cold = run_child("cold", rig, cache, frames)
            if "error" in cold:
                print(f"  cold process failed: {cold['error']}")
                TARGETS.append((f"cold compilation, {kind}", "failed", False))
                continue
            print(f"  (a) cold:  first label {target(f'cold compilation, {kind}', cold['first_label_s'], COLD_TARGET_S[kind], ' s')}")
            print(f"        {_compiles(cold['first_label'])}; imports {cold['imports_s']:.1f} s, synthesis {cold['synthesis_s']:.1f} s, process {cold['process_s']:.1f} s")
            entries = sum(len(files) for _, _, files in os.walk(cache))
            stored = len(os.listdir(os.path.join(cache, compilation.PROGRAMS)))
            warm = run_child("warm", rig, cache, frames)
            if "error" in warm:
                print(f"  warm process failed: {warm['error']}")
                TARGETS.append((f"warm cache, {kind}", "failed", False))
                continue
            print(f"  (b) warm:  first label {target(f'warm cache, {kind}', warm['first_label_s'], WARM_TARGET_S, ' s')}")
            print(f"        {_compiles(warm['first_label'])} ({entries} files in the cache, {stored} of them traced programs); "
                  f"imports {warm['imports_s']:.1f} s, process {warm['process_s']:.1f} s")
            same = warm["labels_sha256"] == cold["labels_sha256"]
            print(f"        labels {'bit-identical to' if same else 'DIFFERENT from'} the cold process's")
            third_s = warm["third_rig"]
            met = target(f"third rig, {kind}: solver compilations", third_s["solver_compiled"], 0, "", fmt="d")
            print(f"  (c) third rig, same process: labelled in {warm['third_label_s']:.2f} s; solver compilations {met}")
            print(f"        all programs: {_compiles(third_s)}")


# ----------------------------------------------------------------------------- accuracy


@jax.jit
def _errors(pred, true):
    per = lambda f: jax.vmap(f)(pred, true) * 1000.0  # noqa: E731
    return {"p_mpjpe": per(metrics.p_mpjpe), "pa_mpjpe": per(metrics.pa_mpjpe), "wrist": per(metrics.wrist_error)}


def frame_rows(labels: clips.Labels, gt: dict) -> dict:
    """Per-frame errors (mm) and masks of one labelled hand."""
    err = {k: np.asarray(v) for k, v in _errors(labels.joints, jnp.asarray(gt["joints"])).items()}
    return dict(err, valid=np.asarray(labels.valid, bool), onscreen=np.asarray(gt["onscreen"], bool), stereo=np.asarray(labels.stereo, bool))


def pooled(hands: list[dict], group: str) -> dict:
    """Frame-weighted accuracy over all hands' on-screen frames of one group."""
    cat = {k: np.concatenate([h[k] for h in hands]) for k in hands[0]}
    pick = {"stereo": cat["stereo"], "monocular": ~cat["stereo"], "all": np.ones_like(cat["stereo"])}[group]
    onscreen = cat["onscreen"] & pick
    ok = onscreen & cat["valid"]
    mean = lambda k: float(np.nanmean(cat[k][ok])) if ok.any() else float("nan")  # noqa: E731
    good = ok & (cat["p_mpjpe"] <= ARIA_TARGETS["p_mpjpe"]) & (cat["wrist"] <= ARIA_TARGETS["wrist"])
    n = int(onscreen.sum())
    return {"frames": n, "coverage": ok.sum() / n if n else float("nan"), "good": good.sum() / n if n else float("nan"),
            "p_mpjpe": mean("p_mpjpe"), "pa_mpjpe": mean("pa_mpjpe"), "wrist": mean("wrist")}  # fmt: skip


def label_clips(rig: str, clips: int, frames: int, config: fitting.LabelConfig, seed: int = 1000, log: CompileLog | None = None) -> dict:
    """Label both hands of `clips` clips; the first call is timed apart (compilation),
    and `log`, if given, summarises the compilations of that call."""
    cfg = synth.SynthConfig(num_frames=frames, rig=rig, motion_config=MOTION)
    hands, calls, stages = [], [], {}
    for i in range(clips):
        clip = synth.make_clip(seed, i, cfg)
        models = {side: mano.load_builtin(side) for side in clip.keypoints}
        mark = log.mark() if log is not None and not calls else None
        results = fitting.label_hands(models, clip.rig, clip.keypoints, clip.meta["fps"], config)  # as `esther label` does
        if mark is not None:
            first = log.summary(mark)
        for side in results:  # in labelling order: the first call of the run is the compiling one
            labels, report = results[side]
            calls.append((frames, report["seconds"]))
            if len(calls) > 1:
                for k, v in report["timings"].items():
                    stages[k] = stages.get(k, 0.0) + v
            hands.append(frame_rows(labels, clip.gt[side]))
    timed = calls[1:]
    hand_frames = sum(c[0] for c in timed)
    seconds = sum(c[1] for c in timed)
    return {"hands": hands, "first_s": calls[0][1], "first": first if log is not None else None, "throughput": hand_frames / seconds if seconds else float("nan"),
            "per_hand_s": seconds / len(timed) if timed else float("nan"), "stages": {k: v / max(len(timed), 1) for k, v in stages.items()}}  # fmt: skip


def sweep_section(clips: int, frames: int):
    print(f"\n== 2. rig sweep: {clips} clips x {frames} frames, both hands, default detector preset, default LabelConfig ==")
    head = f"{'rig':<14}{'frames':<11}{'on screen':>10}{'coverage':>10}{'P-MPJPE':>9}{'PA-MPJPE':>10}{'wrist':>8}{'<=15/25mm':>11}"
    print(head + "   (mm; on screen from the ground truth; last column: share of on-screen frames labelled within 15 mm P-MPJPE and 25 mm wrist)")
    results = {}
    for rig in RIGS:
        results[rig] = r = label_clips(rig, clips, frames, fitting.LabelConfig())
        for group in ("stereo", "monocular", "all"):
            g = pooled(r["hands"], group)
            r[group] = g
            print(f"{rig if group == 'stereo' else '':<14}{group:<11}{g['frames']:>10d}{num(g['coverage'], 10, '.1%')}{num(g['p_mpjpe'], 9)}"
                  f"{num(g['pa_mpjpe'], 10)}{num(g['wrist'], 8)}{num(g['good'], 11, '.1%')}")  # fmt: skip
    print("\nspeed (after compilation; first call = compilation or in-memory reuse; each stage's time includes\n"
          " waiting for its device work, as quality.json's timings do):")
    for rig, r in results.items():
        stages = ", ".join(f"{k.removesuffix('_s')} {v * 1000:.0f}" for k, v in r["stages"].items())
        print(f"  {rig:<14} first call {r['first_s']:6.1f} s, then {r['per_hand_s']:.2f} s per {frames}-frame hand = "
              f"{r['throughput']:6.0f} hand-frames/s   [ms per hand: {stages}]")  # fmt: skip
    e, a = results["esther"]["all"], results["hot3d_aria"]["all"]
    print("\ntargets:")
    print(f"  esther P-MPJPE {target('esther P-MPJPE', e['p_mpjpe'], ESTHER_TARGETS['p_mpjpe'], ' mm', fmt='.2f')}")
    print(f"  esther wrist {target('esther wrist', e['wrist'], ESTHER_TARGETS['wrist'], ' mm', fmt='.2f')}")
    print(f"  esther throughput {target('esther throughput', results['esther']['throughput'], ESTHER_TARGETS['throughput'], ' hand-frames/s', at_most=False, fmt='.0f')}")
    met = a["coverage"] >= ARIA_TARGETS["coverage"] and a["p_mpjpe"] <= ARIA_TARGETS["p_mpjpe"] and a["wrist"] <= ARIA_TARGETS["wrist"]
    text = (f"coverage {a['coverage']:.1%} (>= 80 %), P-MPJPE {a['p_mpjpe']:.2f} mm (<= 15), wrist {a['wrist']:.2f} mm (<= 25): "
            f"{'meets' if met else 'misses'}")  # fmt: skip
    TARGETS.append(("hot3d_aria, means over labelled frames", text, met))
    print(f"  hot3d_aria, means over the labelled frames: {text}")
    print(f"  hot3d_aria, per frame: labelled within 15 / 25 mm {target('hot3d_aria, per frame', a['good'] * 100, ARIA_TARGETS['coverage'] * 100, ' %', at_most=False)}")


# ----------------------------------------------------------------------------- solvers


def solvers_section(clips: int, frames: int, solvers: tuple[str, ...] = fitting.SOLVERS):
    print(f"\n== 3. solvers on the esther rig: {clips} clips x {frames} frames, both hands; persistent cache off, caches cleared per solver ==")
    jax.config.update("jax_enable_compilation_cache", False)
    log = CompileLog()
    print(f"{'solver':<11}{'first call':>11}{'trace+lower':>12}{'compile':>9}{'solver compile':>16}{'per hand':>10}{'hand-frames/s':>15}{'P-MPJPE':>9}{'PA-MPJPE':>10}{'wrist':>8}{'coverage':>10}")
    for name in solvers:
        jax.clear_caches()
        try:
            r = label_clips("esther", clips, frames, fitting.LabelConfig(solver=name), log=log)
        except Exception as err:  # noqa: BLE001 - a failing backend is a result, not a crash
            print(f"{name:<11}failed: {type(err).__name__}: {str(err).splitlines()[0][:160] if str(err) else ''}")
            continue
        s = r["first"]
        g = pooled(r["hands"], "all")
        print(f"{name:<11}{r['first_s']:>10.1f}s{s['trace_s'] + s['lower_s']:>11.1f}s{s['compiled_s']:>8.1f}s{s['solver_compiled_s']:>15.1f}s{r['per_hand_s']:>9.2f}s"
              f"{num(r['throughput'], 15, '.0f')}{num(g['p_mpjpe'], 9)}{num(g['pa_mpjpe'], 10)}{num(g['wrist'], 8)}{num(g['coverage'], 10, '.1%')}")  # fmt: skip
    print("  (first call: trace + lower + compile + one label; compile: XLA's backend compilation of all programs in it;\n"
          "   solver compile: of the `solve_round` programs; per hand and hand-frames/s: the later calls)")


# ----------------------------------------------------------------------------- step


def _per_frame_ms(fn, *args, repeats: int = 20) -> float:
    fn = jax.jit(fn)
    jax.block_until_ready(fn(*args))
    start = time.perf_counter()
    for _ in range(repeats):
        jax.block_until_ready(fn(*args))
    return (time.perf_counter() - start) / repeats * 1000.0


def step_section(frames: int):
    """One Levenberg-Marquardt step's pieces for one hand's frames, side by side."""
    print(f"\n== 4. one solver step for {frames} frames (esther rig, right hand, shape-lock round, float32) ==")
    clip = synth.make_clip(1000, 0, synth.SynthConfig(num_frames=frames, rig="esther", motion_config=MOTION))
    model, kp, gt, rig = mano.load_builtin("right"), clip.keypoints["right"], clip.gt["right"], clip.rig
    f32 = jnp.float32
    fused = fitting.fuse(*(jnp.asarray(kp[k], f32) for k in ("uv", "conf", "box", "box_score")))
    evidence = fitting.prefilter(rig, fused, fitting.template_bones(model))
    prior = fitting.PosePrior.from_model(model)
    problem = fitting.Problem(model, rig, prior, fitting.MotionPrior(), fitting.FitWeights(), jnp.zeros(10, f32), jnp.asarray(30.0, f32))
    data = fitting.frame_data(evidence, jax.jit(fitting.initialise)(model, rig, evidence, problem.betas), problem)
    noise = lambda x, s: jnp.asarray(x, f32) + s * jax.random.normal(jax.random.key(0), np.shape(x), f32)  # noqa: E731
    offset_cm = 100.0 * (gt["transl"] - data.anchor)
    y = objectives.FrameUnknowns(noise(gt["global_orient"], 0.1), noise(gt["hand_pose"], 0.1), noise(offset_cm, 0.5), jnp.zeros((frames, 10), f32))
    track, round = objectives.Track.none(frames, f32), objectives.Round.make(1.0, 1.0, 0.0, f32)
    per_frame = lambda fn: jax.vmap(lambda y1, d1, t1: fn(y1, (problem, d1, t1, round)))  # noqa: E731

    def autodiff(y1, args):
        flat, unravel = ravel_pytree(y1)
        f = lambda x: jnp.concatenate([r.reshape(-1) for r in objectives.frame_residuals(unravel(x), args)])  # noqa: E731
        return solve.gauss_newton(f(flat), jax.jacfwd(f)(flat))

    def cholesky(g, H):
        A = H + 1e-3 * jnp.eye(H.shape[-1], dtype=H.dtype)
        return jax.scipy.linalg.cho_solve(jax.scipy.linalg.cho_factor(A), g)

    g, H = jax.jit(per_frame(objectives.frame_normal_equations))(y, data, track)
    g_ad, H_ad = jax.jit(per_frame(autodiff))(y, data, track)
    rows = [
        ("residuals (243 per frame)", _per_frame_ms(per_frame(objectives.frame_residuals), y, data, track)),
        ("normal equations, autodiff (J^T J of the 243 x 61 Jacobian)", _per_frame_ms(per_frame(autodiff), y, data, track)),
        ("normal equations from the objective's structure", _per_frame_ms(per_frame(objectives.frame_normal_equations), y, data, track)),
        ("  of which the reprojection's closed form (r, J)", _per_frame_ms(per_frame(objectives.reprojection_with_jacobian), y, data, track)),
        ("Cholesky solve of the 61 x 61 systems", _per_frame_ms(jax.vmap(cholesky), g, H)),
    ]
    for what, ms in rows:
        print(f"  {what:<62}{ms:8.2f} ms")
    print(f"  structured / autodiff: {rows[2][1] / rows[1][1]:.2f}x the time; the two agree to "
          f"{float(jnp.max(jnp.abs(H - H_ad)) / jnp.max(jnp.abs(H_ad))):.1e} (J^T J, relative to its largest entry)")


# ----------------------------------------------------------------------------- main


START_NOISE = {
    "close": dict(orient=0.15, pose=0.15, wrist=0.03, betas=0.5),
    "far": dict(orient=0.45, pose=0.3, wrist=0.10, betas=1.0),
    "network": dict(orient=0.45, pose=0.1, wrist=0.10, betas=0.0, fingers="mean"),
}
"""How far refine's start is from the truth: per joint angle and frame (rad, the global
orientation's and the fingers'), the wrist (m, per axis), each beta. "close": a good
network; "far": the truth's fingers and shape, noised, with the orientation and wrist as
far off as this project's CPU-trained networks (orientation about 26 degrees off, wrist
90 mm and more: docs/training.md); "network": as those networks predict, the hand
model's mean finger pose (noised) and its mean shape, whatever the hand does."""


def _perturbed_start(gt: dict, side: str, rng: np.random.Generator, noise: dict) -> mano.ManoParams:
    """A hand's ground truth perturbed as a network's prediction (`START_NOISE`)."""
    T = gt["transl"].shape[0]
    f32 = lambda x: jnp.asarray(x, jnp.float32)  # noqa: E731
    fingers = gt["hand_pose"] if noise.get("fingers", "truth") == "truth" else np.asarray(mano.load_builtin(side).hands_mean).reshape(1, 15, 3)
    return mano.ManoParams(f32(gt["global_orient"] + rng.normal(scale=noise["orient"], size=(T, 3))),
                           f32(fingers + rng.normal(scale=noise["pose"], size=(T, 15, 3))),
                           f32(np.broadcast_to(gt["betas"] + rng.normal(scale=noise["betas"], size=10), (T, 10))),
                           f32(gt["transl"] + rng.normal(scale=noise["wrist"], size=(T, 3))))  # fmt: skip


def accepted(rows: list[dict], same: list[np.ndarray] | None = None) -> dict:
    """The accepted on-screen frames of many hands' `frame_rows`: coverage, mean P-MPJPE
    and wrist (mm), how many are worse than 15 mm; `same`: per hand, frames to also
    average P-MPJPE over (those another method accepts too)."""
    cat = {k: np.concatenate([h[k] for h in rows]) for k in ("p_mpjpe", "wrist", "valid", "onscreen")}
    ok = cat["valid"] & cat["onscreen"]
    out = {"coverage": ok.sum() / cat["onscreen"].sum(), "p_mpjpe": np.mean(cat["p_mpjpe"][ok]), "wrist": np.mean(cat["wrist"][ok]),
           "worse": int(np.sum(ok & (cat["p_mpjpe"] > 15.0)))}  # fmt: skip
    if same is not None:
        out["p_mpjpe_same"] = np.mean(np.concatenate([h["p_mpjpe"][b] for h, b in zip(rows, same)]))
    return out


def _hands(seed: int, clips: int, frames: int, rig: str = "esther") -> list:
    cfg = synth.SynthConfig(num_frames=frames, rig=rig, motion_config=motion.MotionConfig(two_hands_probability=1.0))
    return [(c, side) for c in (synth.make_clip(seed, i, cfg) for i in range(clips)) for side in c.keypoints]


def _runs(pose_prior=None) -> dict:
    return {"teacher": lambda c, side, start: fitting.label_hand(mano.load_builtin(side), c.rig, c.keypoints[side], c.meta["fps"], pose_prior=pose_prior),
            "refine": lambda c, side, start: fitting.refine(mano.load_builtin(side), c.rig, c.keypoints[side], c.meta["fps"], start,
                                                            pose_prior=pose_prior)}  # fmt: skip


REFINE_RIGS = ("esther", "hot3d_aria")
"""The rigs of refine's section: the data engine study's raw collection's."""


def refine_section(clips: int, frames: int, seed: int = 2000):
    """`fitting.refine` against the teacher on the same hands, on each of `REFINE_RIGS`:
    each hand's ground truth perturbed as a network's prediction (`START_NOISE`) is
    refined; throughput in hand-frames/s (compilation apart) and accuracy, also on the
    frames both accept (the data engine's target: within 1 mm of the teacher's)."""
    runs = _runs()
    for rig in REFINE_RIGS:
        hands = _hands(seed, clips, frames, rig)
        for run in runs.values():
            run(*hands[0], _perturbed_start(hands[0][0].gt[hands[0][1]], hands[0][1], np.random.default_rng(0), START_NOISE["close"]))  # compilation apart
        total = sum(c.gt[side]["transl"].shape[0] for c, side in hands)
        t0 = time.perf_counter()
        teacher = [frame_rows(runs["teacher"](c, side, None)[0], c.gt[side]) for c, side in hands]
        teacher_s = time.perf_counter() - t0
        for start, noise in START_NOISE.items():
            print(f"\n== refine against the teacher on {rig}: {clips} synthetic clips of {frames} frames, both hands, start = {start} {noise}")
            rng = np.random.default_rng(0)
            starts = [_perturbed_start(c.gt[side], side, rng, noise) for c, side in hands]
            t0 = time.perf_counter()
            refined = [frame_rows(runs["refine"](c, side, s)[0], c.gt[side]) for (c, side), s in zip(hands, starts)]
            refine_s = time.perf_counter() - t0
            both = [t["valid"] & r["valid"] & t["onscreen"] for t, r in zip(teacher, refined)]
            start_rows = [start_errors(side, s, c.gt[side]) for (c, side), s in zip(hands, starts)]
            on_screen = lambda k: np.mean(np.concatenate([h[k][c.gt[side]["onscreen"]] for h, (c, side) in zip(start_rows, hands)]))  # noqa: E731
            print(f"{'start':<8} the prediction itself, on-screen frames: P-MPJPE {on_screen('p_mpjpe'):5.2f} mm   wrist {on_screen('wrist'):6.2f} mm")
            same = {}
            for name, rows, seconds in (("teacher", teacher, teacher_s), ("refine", refined, refine_s)):
                a = accepted(rows, both)
                same[name] = a["p_mpjpe_same"]
                print(f"{name:<8} {total / seconds:8.0f} hand-frames/s   coverage {a['coverage']:6.1%}   "
                      f"P-MPJPE {a['p_mpjpe']:5.2f} mm (on the frames both accept {a['p_mpjpe_same']:5.2f})   wrist {a['wrist']:5.2f} mm   "
                      f"accepted worse than 15 mm: {a['worse']}")  # fmt: skip
            print(f"refine - teacher on the frames both accept ({rig}, {start}): "
                  + target(f"refine accuracy ({rig}, {start} start)", same["refine"] - same["teacher"], 1.0, " mm", fmt="+.2f"))
            print(f"refine / teacher throughput ({rig}, {start}): " + target(f"refine throughput ({rig}, {start} start)", teacher_s / refine_s, 5.0, "x", at_most=False))


def start_errors(side: str, start: mano.ManoParams, gt: dict) -> dict:
    """Per-frame errors (mm) of a start itself, as `frame_rows` scores a label."""
    model = mano.load_builtin(side)
    joints = jax.vmap(lambda p: mano.forward_joints(model, p))(start)
    return {k: np.asarray(v) for k, v in _errors(joints, jnp.asarray(gt["joints"])).items()}


def prior_section(clips: int, frames: int, seed: int = 3000, train_clips: int = 16):
    """The learned pose prior (`mano.GMMPosePrior`, 8 components) against the PCA +
    joint-limit prior, inside the teacher and inside `refine` (from `_perturbed_start`), on
    the same held-out hands. Two mixtures: fitted to the synthetic engine's articulation
    (other draws than the clips'), and to the teacher's accepted labels of `train_clips`
    other clips (left hands mirrored), what a user without our engine's motion has."""
    print(f"\n== pose priors: {clips} held-out clips of {frames} frames, both hands; mixtures of 8 components")
    t0 = time.perf_counter()
    synthetic = mano.fit_gmm_pose_prior(motion.sample_hand_poses(seed + 1, 300, 90), components=8)
    poses = []
    for c, side in _hands(seed + 2, train_clips, frames):
        labels, _ = fitting.label_hand(mano.load_builtin(side), c.rig, c.keypoints[side], c.meta["fps"])
        pose = np.asarray(labels.params.hand_pose)[np.asarray(labels.valid)]
        poses.append(pose if side == "right" else np.asarray(mano.mirror_hand_pose(jnp.asarray(pose))))
    from_labels = mano.fit_gmm_pose_prior(np.concatenate(poses), components=8)
    print(f"  fitted in {time.perf_counter() - t0:.0f} s (the teacher's labels: {sum(len(p) for p in poses)} poses of {train_clips} clips)")
    hands = _hands(seed, clips, frames)
    rng = np.random.default_rng(0)
    starts = [_perturbed_start(c.gt[side], side, rng, START_NOISE["close"]) for c, side in hands]
    priors = {"PCA + limits": None, "GMM, synthetic motion": synthetic, "GMM, teacher labels": from_labels}
    print(f"  {'method':<8} {'prior':<22} {'coverage':>8} {'rejected':>8} {'P-MPJPE':>8} {'wrist':>7} {'>15 mm':>7}")
    for method in ("teacher", "refine"):
        for name, prior in priors.items():
            run = _runs(prior)[method]
            a = accepted([frame_rows(run(c, side, start)[0], c.gt[side]) for (c, side), start in zip(hands, starts)])
            print(f"  {method:<8} {name:<22} {a['coverage']:8.1%} {1 - a['coverage']:8.1%} {a['p_mpjpe']:8.2f} {a['wrist']:7.2f} {a['worse']:7d}")


def main():
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--clips", type=int, default=4)
    parser.add_argument("--frames", type=int, default=64)
    parser.add_argument("--section", choices=("compile", "sweep", "solvers", "step", "refine", "prior", "all"), default="all")
    parser.add_argument("--solvers", nargs="+", choices=fitting.SOLVERS, default=fitting.SOLVERS, help="section 3's solvers")
    parser.add_argument("--quick", action="store_true", help="smoke run: 1 clip of 32 frames, section 1 only when asked for")
    parser.add_argument("--child", choices=("cold", "warm"), help=argparse.SUPPRESS)
    parser.add_argument("--rig", default="esther", help=argparse.SUPPRESS)
    parser.add_argument("--cache", help=argparse.SUPPRESS)
    args = parser.parse_args()
    sys.stdout.reconfigure(line_buffering=True)  # partial results survive a crash or a kill
    if args.child:
        print("RESULT " + json.dumps(child(args.child, args.rig, args.cache, args.frames)), flush=True)
        return
    if args.quick:
        args.clips, args.frames = 1, 32
    print(f"{machine()}; solvers {', '.join(fitting.SOLVERS)}")
    if args.section in ("compile", "all") and not (args.quick and args.section == "all"):
        compile_section(args.frames)
    if args.section in ("sweep", "all"):
        sweep_section(args.clips, args.frames)
    if args.section in ("solvers", "all"):
        solvers_section(args.clips, args.frames, tuple(args.solvers))
    if args.section in ("step", "all"):
        step_section(args.frames)
    if args.section in ("refine", "all"):
        refine_section(args.clips, args.frames)
    if args.section in ("prior", "all"):
        prior_section(args.clips, args.frames)
    if TARGETS:
        print("\nsummary:")
        for what, text, _ in TARGETS:
            print(f"  {what}: {text}")


if __name__ == "__main__":
    main()
