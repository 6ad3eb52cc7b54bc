"""The teacher for one hand of one clip (paper section 3.1, appendix A): the composition

    fuse -> prefilter -> initialise -> shape_lock -> fit_frames -> refine_motion
         -> reprojection_filter -> label_quality

`label_hand` validates its inputs on the host (shapes, values, fps), moves them to the
device once, runs every stage there and brings the labels back once. Frames are padded
to a multiple of 32 (unobserved frames), so one clip-length bucket compiles once; the
rig's calibration, the hand model, the weights and the fps are traced data, so one
compiled program serves every rig of the same camera models and image sizes (the image
size is a camera's static field; a rig has no name). Nothing compiled contains a host callback, so every program is stored in
the persistent compilation cache (`esther_jax.enable_compilation_cache`).

`refine` is the same composition started from a network's prediction (the data engine's
model-assisted labelling): the prediction replaces the initialisation (the palm pose is
refined from it, or from the triangulated palm where that reprojects better, not
searched; the wrist is the evidence's where a frame has one) and starts the shape lock,
with a second shape-lock round (`REFINE_CONFIG`); the filter and quality record are the teacher's.

Frames seen by both views are stereo frames; frames seen by one view are labelled too
(monocular frames: depth from the locked hand size, the priors and the neighbouring
frames, not from triangulation). `labels["stereo"]` tells them apart, and `quality.json`
reports them separately.
"""

import contextlib
import dataclasses
import threading
import time

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from esther_jax import clips, mano
from esther_jax.cameras import StereoRig
from esther_jax.compilation import CPU_LIGHT_OPTIMISATION, CPU_QUICK_COMPILE, persistent_jit

from . import evidence as ev, fusion, quality, stages
from .objectives import FitWeights, Problem
from .priors import MotionPrior
from .solve import SOLVERS

BUCKET = 32


@dataclasses.dataclass(frozen=True)
class LabelConfig:
    """Static settings of the teacher (changing them recompiles); weights are traced."""

    weights: FitWeights = FitWeights()
    solver: str = "lm"
    """One of `solve.SOLVERS`: "lm" (ours, fixed steps), "dogleg", "optx-lm" (optimistix)."""
    steps: int = 5
    """Solver steps per round of `fit_frames` and `refine_motion` (a monocular frame,
    with no triangulated wrist, needs them: on hot3d_aria 3 steps gave P-MPJPE 4.8 mm,
    5 gave 3.9, 6 gave 3.7; on the esther rig 3 steps suffice)."""
    shape_lock_steps: int = 16
    """Solver steps per round of the shape lock. The locked shape sets every frame's bone
    lengths, so its solve is where steps pay (benchmarks/teacher.py rig sweep, esther rig:
    16 shape-lock steps give P-MPJPE 2.5 mm where two rounds of 6 gave 4.1).
    With the default solver every count shares one compiled program."""
    shape_lock_frames: int = 64
    shape_lock_rounds: int = 1
    stiff_pose: float = 25.0
    """fit_frames first solves with the pose prior this many times stiffer (the wrist's
    orientation and position settle first), then with the normal weights."""
    window: int = 16
    stride: int = 8
    motion_sweeps: int = 1
    reject_px: float = quality.REJECT_PX
    min_joints_per_view: int = 4
    """A view 'observes' the hand in a frame with at least this many fused joints."""

    def __post_init__(self):
        if self.solver not in SOLVERS:
            raise ValueError(f"LabelConfig.solver must be one of {SOLVERS}, got {self.solver!r}")
        if min(self.steps, self.shape_lock_steps, self.shape_lock_rounds, self.shape_lock_frames, self.window, self.stride) < 1:
            raise ValueError("LabelConfig: steps, shape_lock_steps, shape_lock_rounds, shape_lock_frames, window and stride must be >= 1")


TEACHER_REVISION = 1
"""Revision of the teacher's algorithm (`label_hand`): raised by any change that alters the
labels it makes from the same input. Labels record it (`method_record`), and
`label_clips(resume=True)` redoes labels of another revision."""

REFINE_REVISION = 2
"""Revision of `refine`'s algorithm, as `TEACHER_REVISION` is the teacher's (2: its start
from the evidence's palm pose and wrist, 2026-12-07; 1: from the prediction's)."""


def method_record(config: LabelConfig, refined: bool) -> dict:
    """What labels record of the method that made them (`meta.json` `"method"`): the
    teacher or refine, that algorithm's revision and every setting of `config` (its
    weights included), so labels made another way are told apart from this run's."""
    settings = {f.name: getattr(config, f.name) for f in dataclasses.fields(config) if f.name != "weights"}
    settings["weights"] = {name: float(value) for name, value in vars(config.weights).items()}
    return {"name": "refine" if refined else "teacher", "revision": REFINE_REVISION if refined else TEACHER_REVISION, "config": settings}


def bucket_length(frames: int) -> int:
    """Padded clip length: a multiple of 32 (one compiled program per bucket)."""
    return max(BUCKET, -(-frames // BUCKET) * BUCKET)


FAR_OUTSIDE = 0.5
"""Detections farther outside the image than this fraction of its width (height) are not
observations: a detector extrapolates a cut-off hand's joints a little beyond the border,
never by half an image."""


def far_outside_image(rig: StereoRig, uv: np.ndarray) -> np.ndarray:
    """Which detections `uv [..., 2 views, 21, 2]` (pixels) lie far outside their view's
    image (`FAR_OUTSIDE`); NaN pixels count as not far (they are missing already)."""
    size = np.array([[rig.left.width, rig.left.height], [rig.right.width, rig.right.height]], np.float64)  # (2 views, 2)
    lo, hi = -FAR_OUTSIDE * size - 0.5, (1.0 + FAR_OUTSIDE) * size - 0.5
    uv = np.asarray(uv, np.float64)
    with np.errstate(invalid="ignore"):
        far = (uv < lo[:, None, :]) | (uv > hi[:, None, :])
    return np.any(far, axis=-1)


def check_keypoints(keypoints: dict, fps: float) -> tuple[int, int]:
    """Validate a keypoints.npz dictionary at the edge; returns (D, T)."""
    for key in ("uv", "conf", "box", "box_score"):
        if key not in keypoints:
            raise ValueError(f"keypoints lack {key!r} (need uv, conf, box, box_score)")
    shapes = {k: np.shape(keypoints[k]) for k in ("uv", "conf", "box", "box_score")}
    uv = shapes["uv"]
    if len(uv) != 5 or uv[2:] != (2, 21, 2):
        raise ValueError(f"keypoints uv must be [D, T, 2, 21, 2], got {uv}")
    D, T = uv[:2]
    expected = {"conf": (D, T, 2, 21), "box": (D, T, 2, 4), "box_score": (D, T, 2)}
    for k, shape in expected.items():
        if shapes[k] != shape:
            raise ValueError(f"keypoints {k} must be {list(shape)} to match uv {list(uv)}, got {list(shapes[k])}")
    if D < 1 or T < 1:
        raise ValueError(f"keypoints need at least one detector and one frame, got D = {D}, T = {T}")
    for k in expected | {"uv": None}:
        if np.asarray(keypoints[k]).dtype.kind not in "biuf":
            raise ValueError(f"keypoints {k} must be real numbers, got dtype {np.asarray(keypoints[k]).dtype}")
    for k in ("conf", "box_score"):
        values = np.asarray(keypoints[k], np.float64)
        outside = np.isfinite(values) & ((values < 0) | (values > 1))
        if outside.any():
            raise ValueError(
                f"keypoints {k} must lie in [0, 1]; {int(outside.sum())} values do not "
                f"(from {values[outside].min():g} to {values[outside].max():g})"
            )
    if not (isinstance(fps, (int, float)) and np.isfinite(fps) and fps > 0):
        raise ValueError(f"fps must be a positive finite number, got {fps!r}")
    return D, T


def check_prediction(prediction: mano.ManoParams, frames: int, num_betas: int) -> dict[str, np.ndarray]:
    """Validate a prediction to refine at the edge: per frame global_orient [T,3],
    hand_pose [T,15,3], transl [T,3] and betas [T,B] (or one [B]), all finite; returns its
    fields as float64 host arrays, the betas per frame."""
    expected = {"global_orient": (frames, 3), "hand_pose": (frames, 15, 3), "transl": (frames, 3)}
    arrays = {}
    for name, shape in expected.items():
        value = np.asarray(getattr(prediction, name), np.float64)
        if value.shape != shape:
            raise ValueError(f"prediction {name} must be {list(shape)} to match the keypoints' {frames} frames, got {list(value.shape)}")
        arrays[name] = value
    betas = np.asarray(prediction.betas, np.float64)
    if betas.shape not in ((num_betas,), (frames, num_betas)):
        raise ValueError(f"prediction betas must be [{num_betas}] or [{frames}, {num_betas}], got {list(betas.shape)}")
    arrays["betas"] = np.broadcast_to(betas, (frames, num_betas))
    bad = [name for name, value in arrays.items() if not np.isfinite(value).all()]
    if bad:
        raise ValueError(f"prediction has NaN or infinite values in {', '.join(bad)}: refine needs a finite start in every frame")
    return arrays


@persistent_jit(compiler_options=CPU_QUICK_COMPILE)
def _prediction_fits(prediction: mano.ManoParams, observed) -> stages.Fits:
    """A prediction as the stages' starting fits: its pose and wrist per frame, one shape
    (the mean of the observed frames' betas; of all frames when none is observed)."""
    w = jnp.where(jnp.any(observed), observed, True).astype(prediction.betas.dtype)
    betas = jnp.sum(prediction.betas * w[:, None], axis=0) / jnp.sum(w)
    T = prediction.transl.shape[0]
    return stages.Fits(prediction.global_orient, prediction.hand_pose, prediction.transl, jnp.broadcast_to(betas, (T, betas.shape[0])), jnp.zeros(T, bool))


@persistent_jit(compiler_options=CPU_QUICK_COMPILE)
def _prepare(model, rig, uv, conf, box, box_score):
    fused = fusion.fuse(uv, conf, box, box_score)
    evidence = ev.prefilter(rig, fused, ev.template_bones(model))
    return fused, evidence


@persistent_jit(compiler_options=CPU_QUICK_COMPILE)
def _problem(model, rig, weights, betas, fps) -> Problem:
    return Problem(model, rig, mano.PosePrior.from_model(model, betas), MotionPrior(), weights, betas, fps)


def _with_pose_prior(problem: Problem, pose_prior: mano.GMMPosePrior | None, model: mano.ManoModel) -> Problem:
    """The problem under a learned pose prior in the PCA prior's place (its mixture for
    this side, with the PCA prior's joint-limit hinges); unchanged without one."""
    if pose_prior is None:
        return problem
    learned = pose_prior.for_side(model.is_right).with_limits(problem.pose_prior)
    return eqx.tree_at(lambda p: p.pose_prior, problem, learned)


def _initial(model, rig, evidence, betas, mono_orient, mono_has, previous, triangulated_start: bool = False) -> ev.Initial:
    """Each frame's palm pose (`evidence.initialise`), with the monocular fit's orientation
    where a frame has one."""
    init = ev.initialise(model, rig, evidence, betas, previous, triangulated_start=triangulated_start)
    return ev.Initial(
        init.transl, jnp.where(mono_has[:, None], mono_orient, init.global_orient),
        init.wrist_triangulated, init.wrist_monocular, init.palm_seen,
    )  # fmt: skip


@persistent_jit(compiler_options=CPU_LIGHT_OPTIMISATION)
def _start(model, rig, evidence, betas, mono_orient, mono_pose, mono_has):
    """The initialisation at the mean shape: the palm pose search (about 100 ms of a 64-frame
    hand's 400 ms on 2 cores), compiled for run time; and the starting finger pose (the
    monocular fit's where a frame has one, else the mean pose)."""
    pose = jnp.where(mono_has[:, None, None], mono_pose, jnp.broadcast_to(model.hands_mean.reshape(15, 3), mono_pose.shape))
    return _initial(model, rig, evidence, betas, mono_orient, mono_has, None), pose


@persistent_jit(compiler_options=CPU_QUICK_COMPILE)
def _restart(model, rig, evidence, betas, mono_orient, mono_has, previous):
    """The initialisation refined with the locked shape (each frame's palm pose from its
    previous one only, about 11 ms of a hand), compiled cheaply: 2.6-3.0 s where it took
    3.7-4.9 s with the search's options, its run time the same within noise. The starting
    pose of `_start` is not recomputed: the frame fits start from the shape lock's."""
    return _initial(model, rig, evidence, betas, mono_orient, mono_has, previous)


@persistent_jit(compiler_options=CPU_QUICK_COMPILE)
def _predicted_start(model, rig, evidence, mono_orient, mono_has, predicted: stages.Fits) -> tuple[ev.Initial, stages.Fits]:
    """Refine's initialisation and starting fits. Each frame's palm pose is refined from
    the prediction's, or from the triangulated palm's rigid fit where that reprojects
    better (`evidence.initialise`). The fits keep the prediction's finger pose and shape;
    per frame they take that palm pose where the palm is seen, and the evidence's wrist
    (triangulated, else the refined palm's) where the frame has one; the prediction's own
    elsewhere. A network's wrist is its weakest output (tens of millimetres off), and the
    shape lock started from it settled in local fits that passed the filter
    (docs/benchmarks.md, refinement against the teacher)."""
    previous = ev.Initial(predicted.transl, predicted.global_orient, *(jnp.zeros(predicted.transl.shape[0], bool),) * 3)
    init = _initial(model, rig, evidence, predicted.betas[0], mono_orient, mono_has, previous, triangulated_start=True)
    known = init.wrist_triangulated | init.wrist_monocular
    start = stages.Fits(
        jnp.where(init.palm_seen[:, None], init.global_orient, predicted.global_orient), predicted.hand_pose,
        jnp.where(known[:, None], init.transl, predicted.transl), predicted.betas, predicted.converged,
    )  # fmt: skip
    return init, start


@persistent_jit(static_argnames=("min_joints",), compiler_options=CPU_QUICK_COMPILE)
def _observed(evidence, min_joints: int):
    per_view = jnp.sum(evidence.weight > 0, axis=2)  # (L, 2)
    seen = per_view >= min_joints
    return seen, jnp.any(seen, axis=1), jnp.all(seen, axis=1)


@persistent_jit(compiler_options=CPU_QUICK_COMPILE)
def _finish(model, rig, fits, fused, seen, observed, reject_px):
    joints = jax.vmap(lambda p: mano.forward_joints(model, p, check_finite=False))(fits.params())
    residual, passing = quality.reprojection_filter(rig, joints, fused.uv, fused.conf, reject_px)
    rest = mano.forward_joints(model, mano.ManoParams(jnp.zeros(3), jnp.zeros((15, 3)), fits.betas[0], jnp.zeros(3)), check_finite=False)
    hand_length = jnp.linalg.norm(rest[12] - rest[0])  # wrist to middle fingertip, flat hand
    per_frame = quality.frame_quality(rig, fits.transl, residual, seen, hand_length)
    return joints, residual, passing & observed, per_frame


def label_hand(
    model: mano.ManoModel, rig: StereoRig, keypoints: dict, fps: float, config: LabelConfig = LabelConfig(),
    monocular: dict | None = None, shape: np.ndarray | None = None, pose_prior: mano.GMMPosePrior | None = None,
) -> tuple[clips.Labels, dict]:  # fmt: skip
    """Label one hand of one clip.

    Args:
        model: the hand model of this side (`load_builtin(side)` or the user's MANO).
        rig: the clip's stereo rig (any geometry; the cameras must share a model).
        keypoints: the keypoints.npz arrays (uv [D,T,2,21,2], conf, box, box_score), D >= 1.
        fps: frame rate (the velocity limits are per second).
        monocular: optional per-view monocular MANO estimates (monocular.npz arrays);
            where present they initialise the wrist orientation and the pose.
        shape: optional betas locked elsewhere for the same person (`label_hands` passes
            the other hand's); used only when no frame sees this hand in both views,
            in place of the mean shape (one view cannot tell size from distance).
        pose_prior: a learned pose prior (`mano.GMMPosePrior`, `esther prior`) in place
            of the hand model's PCA prior (the joint-limit hinges stay); None: the PCA prior.
    Returns:
        (labels, quality): the hand's `clips.Labels` (labels.npz) and the quality.json content.

    Calls from several threads take turns on the CPU (`_CPU_TURNS`).
    """
    with _CPU_TURNS if jax.default_backend() == "cpu" else contextlib.nullcontext():
        return _label_hand(model, rig, keypoints, fps, config, monocular, shape, pose_prior=pose_prior)


REFINE_CONFIG = LabelConfig(shape_lock_rounds=2)
"""`refine`'s default: the teacher's stages and step counts with a second shape-lock
round, which a gross prediction needs (tests/test_refine.py: every finger curled where
the hand is open ends at P-MPJPE 3.8 mm after one round, under 3 mm after two).
`python benchmarks/teacher.py --section refine` measures it against the teacher on the
same 8 hands (4 clips of 64 frames), started from ground truth perturbed as a network's
prediction: "close" (0.15 rad per joint, 3 cm, 0.5 per beta; the start at P-MPJPE
18.6 mm, wrist 48 mm), "far" (0.45 rad orientation, 0.3 rad per finger joint, 10 cm,
1.0 per beta; 48.6 mm, wrist 159 mm) and "network" (the mean fingers and shape, as this
project's CPU-trained networks predict). On the esther rig, on the frames both accept,
P-MPJPE 2.1 mm (close) and 2.3 mm (far) against the teacher's 4.2 and 4.0, no accepted
label worse than 15 mm (the teacher's: 28), at about its throughput; on hot3d_aria's,
from the far start, 2.0 mm worse than the teacher (docs/benchmarks.md). Fewer steps buy throughput at the price of accuracy: one round 2.2 and
2.5 mm at 1.3x; 8 shape-lock steps and 3 per fit 2.5 and 3.9 mm at 1.9x; 4 and 2,
2.8 and 6.0 mm at 2.5x (the data engine's 5x is not reached at the teacher's accuracy)."""


def refine(
    model: mano.ManoModel, rig: StereoRig, keypoints: dict, fps: float, prediction: mano.ManoParams,
    config: LabelConfig = REFINE_CONFIG, shape: np.ndarray | None = None, pose_prior: mano.GMMPosePrior | None = None,
) -> tuple[clips.Labels, dict]:  # fmt: skip
    """Refine a network's prediction of one hand of one clip into a label (the paper's
    model-assisted labelling, "Model-Assisted Labeling and Iterative Enhancement"): the
    teacher's own stages and objectives against the clip's 2D keypoints in every view that
    sees the hand (one view is enough), under the pose prior and the temporal terms,
    started from the prediction instead of the teacher's initialisation (`_predicted_start`:
    its finger pose and shape, not the mean ones; its palm pose refined, not searched,
    unless the triangulated palm's reprojects better; the wrist triangulated where both
    views see it), then the teacher's reprojection filter and label quality.

    Args:
        model, rig, keypoints, fps, shape, pose_prior: as in `label_hand`.
        prediction: the network's MANO parameters per frame (rig frame, metres, radians):
            global_orient [T,3], hand_pose [T,15,3], transl [T,3], betas [T,10] (e.g.
            `clips.Labels.params` of `esther predict`); finite in every frame.
        config: the teacher's settings (`REFINE_CONFIG`).
    Returns:
        (labels, quality report) as `label_hand`'s; the report's "initialised_from" is
        "prediction".
    """
    with _CPU_TURNS if jax.default_backend() == "cpu" else contextlib.nullcontext():
        return _label_hand(model, rig, keypoints, fps, config, None, shape, prediction, pose_prior)


_CPU_TURNS = threading.Lock()
"""Held while a `label_hand` call runs on the CPU. Two threads labelling hands at once hung
for good on a 2-core machine (both waiting in the shape lock's solver): XLA's CPU runtime
runs a while loop's iterations on its thread pool and can block a pool thread in it
(openxla/xla#33048), so two programs of while loops can take every thread of a small pool
and wait on each other. So concurrent calls run one after another, as from one thread."""


def _label_hand(model, rig, keypoints, fps, config, monocular, shape, prediction=None, pose_prior=None) -> tuple[clips.Labels, dict]:
    D, T = check_keypoints(keypoints, fps)
    if prediction is not None:
        prediction = check_prediction(prediction, T, model.num_betas)
    timings = {}  # seconds per stage, each stage waited for (JAX dispatches asynchronously)
    t0 = time.perf_counter()
    L = bucket_length(T)
    dtype = jnp.result_type(float)
    pad = lambda x: np.pad(np.asarray(x, np.float64), [(0, 0), (0, L - T)] + [(0, 0)] * (np.ndim(x) - 2))  # noqa: E731
    pad_edge = lambda x: np.pad(np.asarray(x, np.float64), [(0, L - T)] + [(0, 0)] * (np.ndim(x) - 1), mode="edge")  # noqa: E731
    far = far_outside_image(rig, keypoints["uv"])
    host = {k: pad(keypoints[k]) for k in ("uv", "conf", "box", "box_score")}
    host["conf"][:, :T][far] = 0.0  # not observations
    mono_orient, mono_pose, mono_has = np.zeros((L, 3)), np.zeros((L, 15, 3)), np.zeros(L, bool)
    if monocular is not None:
        orient, pose, has = ev.monocular_average(rig, monocular)
        mono_orient[:T], mono_pose[:T], mono_has[:T] = orient, pose, has
    host.update(mono_orient=mono_orient, mono_pose=mono_pose)
    dev = {k: jnp.asarray(v, dtype) for k, v in host.items()}  # the one transfer in
    mono_has = jnp.asarray(mono_has)
    weights = jax.tree.map(lambda x: jnp.asarray(x, dtype), config.weights)
    zeros = jnp.zeros(model.num_betas, dtype)
    fps_t = jnp.asarray(fps, dtype)

    fused, evidence = _prepare(model, rig, dev["uv"], dev["conf"], dev["box"], dev["box_score"])
    seen, observed, stereo = _observed(evidence, config.min_joints_per_view)
    frame_valid = jnp.arange(L) < T
    observed, stereo = jax.block_until_ready((observed & frame_valid, stereo & frame_valid))
    timings["fuse_filter_s"] = time.perf_counter() - t0

    t1 = time.perf_counter()
    problem = _with_pose_prior(_problem(model, rig, weights, zeros, fps_t), pose_prior, model)
    if prediction is None:  # the teacher: the palm pose search, the mean (or monocular) pose
        init, pose0 = _start(model, rig, evidence, zeros, dev["mono_orient"], dev["mono_pose"], mono_has)
        start = stages.start_fits(init, pose0, zeros)
    else:  # refine: the prediction starts every frame, its palm pose refined, not searched
        padded = {k: jnp.asarray(pad_edge(v), dtype) for k, v in prediction.items()}
        predicted = _prediction_fits(mano.ManoParams(padded["global_orient"], padded["hand_pose"], padded["betas"], padded["transl"]), observed)
        init, start = _predicted_start(model, rig, evidence, dev["mono_orient"], mono_has, predicted)
    data = stages.frame_data(evidence, init, problem)
    solver = dict(steps=config.steps, solver=config.solver)
    lock = stages.shape_lock(
        problem, data, start, stereo, observed,
        frames=config.shape_lock_frames, rounds=config.shape_lock_rounds, steps=config.shape_lock_steps, solver=config.solver,
    )  # fmt: skip
    jax.block_until_ready(lock)
    timings["shape_lock_s"] = time.perf_counter() - t1

    t2 = time.perf_counter()
    has_shape = shape is not None
    if has_shape and np.shape(shape) != (model.num_betas,):
        raise ValueError(f"shape must be betas of shape ({model.num_betas},), got {np.shape(shape)}")
    borrowed = jnp.asarray(shape if has_shape else np.zeros(model.num_betas), dtype)
    betas = jnp.where(lock.from_monocular & has_shape, borrowed, lock.betas)
    problem = _with_pose_prior(_problem(model, rig, weights, betas, fps_t), pose_prior, model)
    init = _restart(model, rig, evidence, betas, dev["mono_orient"], mono_has, init)
    data = stages.frame_data(evidence, init, problem)
    fits = stages.fit_frames(problem, data, lock.fits, stiff_pose=config.stiff_pose, **solver)
    jax.block_until_ready(fits)
    timings["fit_frames_s"] = time.perf_counter() - t2

    t3 = time.perf_counter()
    fits = stages.refine_motion(problem, data, fits, observed, sweeps=config.motion_sweeps, window=config.window, stride=config.stride, **solver)
    jax.block_until_ready(fits)
    timings["refine_motion_s"] = time.perf_counter() - t3

    t4 = time.perf_counter()
    joints, residual, passing, per_frame = _finish(model, rig, fits, fused, seen, observed, jnp.asarray(config.reject_px, dtype))
    out = jax.device_get(  # the one transfer out
        dict(fits=fits, joints=joints, residual=residual, passing=passing, per_frame=per_frame, observed=observed,
             stereo=stereo, seen=seen, betas=betas, chosen=lock.chosen, from_mono=lock.from_monocular,
             num_invalid=fused.num_invalid, rejected_depth=evidence.rejected_depth, rejected_bones=evidence.rejected_bones,
             wrist_monocular=init.wrist_monocular)
    )  # fmt: skip
    timings["labels_s"] = time.perf_counter() - t4
    out["far_outside"] = int(far.sum())
    labels, report = _package(out, T, model, mono_has, config, timings, has_shape)
    report["initialised_from"] = "teacher" if prediction is None else "prediction"
    return labels, report


def _package(out: dict, T: int, model: mano.ManoModel, mono_has, config: LabelConfig, timings: dict, has_shape: bool) -> tuple[clips.Labels, dict]:
    sl = slice(0, T)
    fits = out["fits"]
    observed, stereo = out["observed"][sl], out["stereo"][sl]
    mono = observed & ~stereo
    betas = jnp.asarray(np.asarray(out["betas"], np.float32))
    labels = clips.Labels(
        params=mano.ManoParams(
            jnp.asarray(np.asarray(fits.global_orient[sl], np.float32)),
            jnp.asarray(np.asarray(fits.hand_pose[sl], np.float32)),
            jnp.broadcast_to(betas, (T,) + betas.shape),
            jnp.asarray(np.asarray(fits.transl[sl], np.float32)),
        ),
        joints=jnp.asarray(np.asarray(out["joints"][sl], np.float32)),
        onscreen=jnp.asarray(observed),
        valid=jnp.asarray(out["passing"][sl]),
        residual_px=jnp.asarray(np.asarray(out["residual"][sl], np.float32)),  # NaN where the hand is not observed
        stereo=jnp.asarray(stereo),
        converged=jnp.asarray(fits.converged[sl]),
    )
    per_frame = {k: np.asarray(v[sl]) for k, v in out["per_frame"].items()}
    report = quality.label_quality(per_frame, observed, stereo, np.asarray(labels.valid))
    notes = []
    if out["num_invalid"]:
        notes.append(f"{int(out['num_invalid'])} keypoints had NaN or infinite values but a nonzero confidence and were treated as missing")
    if out["far_outside"]:
        notes.append(f"{out['far_outside']} keypoints lay far outside the image (beyond {FAR_OUTSIDE:g} of its size) and were treated as missing")
    if not observed.any():
        notes.append("the hand is never detected in either view: no label (all frames invalid)")
    elif bool(out["from_mono"]) and has_shape:
        notes.append("no frame sees the hand in both views: the shape is the one locked on the other hand (same person)")
    elif bool(out["from_mono"]):
        notes.append("no frame sees the hand in both views: the shape is the mean shape (one view cannot tell the hand's size from its distance)")
    if mono.any():
        notes.append(f"{int(mono.sum())} frames see the hand in one view only: labelled as monocular frames (stereo = False)")
    if int(np.asarray(mono_has).sum()):
        notes.append(f"initialised from monocular estimates in {int(np.asarray(mono_has).sum())} frames")
    report.update(
        notes=notes,
        hand_frames=T,
        stereo_frames=int(stereo.sum()),
        monocular_frames=int(mono.sum()),
        share_passing=report["all"]["share_passing"] or 0.0,
        shape_from_monocular=bool(out["from_mono"]),
        shape_from_other_hand=bool(out["from_mono"]) and has_shape,
        converged_share=float(np.asarray(labels.converged)[observed].mean()) if observed.any() else 0.0,
        rejected_joints_depth=int(out["rejected_depth"]),
        rejected_joints_bones=int(out["rejected_bones"]),
        shape_lock_frames=int(out["chosen"][sl].sum()),
        betas=np.asarray(out["betas"]).tolist(),
        solver=config.solver,
        timings=timings,
    )
    return labels, report


def label_hands(
    models: dict[str, mano.ManoModel], rig: StereoRig, keypoints: dict[str, dict], fps: float,
    config: LabelConfig = LabelConfig(), monocular: dict[str, dict | None] | None = None, *, share_shape: bool = True,
    predictions: dict[str, mano.ManoParams] | None = None, pose_prior: mano.GMMPosePrior | None = None,
) -> dict[str, tuple[clips.Labels, dict]]:  # fmt: skip
    """Label the hands of one clip (`label_hand` per side), the two hands as one person's:
    a hand that no frame sees in both views takes the shape locked on the other hand when
    that one has stereo frames (the hand models must share their shape space, as MANO's
    right and left models do), instead of the mean shape.

    Args:
        models, keypoints (and optionally monocular): per side ('right', 'left').
        share_shape: False labels each hand on its own (models of different shape spaces).
        predictions: per side, a network's prediction to `refine` instead of labelling
            from scratch (every side of `keypoints` needs one).
        pose_prior: a learned pose prior for both hands (`label_hand`'s).
    Returns:
        {side: (labels, quality report)}; each report's "seconds" is the time spent on
        that hand (both passes when it took the other hand's shape).
    """
    monocular = monocular or {}
    missing = sorted(set(keypoints) - set(predictions)) if predictions is not None else []
    if missing:
        raise ValueError(f"predictions lack the {', '.join(missing)} hand: refine needs a prediction of every hand it labels")

    def one(side: str, shape=None, spent: float = 0.0) -> tuple[clips.Labels, dict]:
        t0 = time.perf_counter()
        if predictions is None:
            labels, report = label_hand(models[side], rig, keypoints[side], fps, config, monocular.get(side), shape=shape, pose_prior=pose_prior)
        else:
            labels, report = refine(models[side], rig, keypoints[side], fps, predictions[side], config, shape=shape, pose_prior=pose_prior)
        report["seconds"] = spent + time.perf_counter() - t0
        return labels, report

    out = {side: one(side) for side in keypoints}
    locked = {side: report["betas"] for side, (_, report) in out.items() if share_shape and not report["shape_from_monocular"]}
    for side, (_, report) in list(out.items()):
        donors = [other for other in locked if other != side]
        if report["shape_from_monocular"] and donors:
            out[side] = one(side, np.asarray(locked[donors[0]], np.float64), report["seconds"])
    return out
