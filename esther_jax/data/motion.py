"""Egocentric hand and head motion with exact ground truth (the synthetic engine's core).

A clip is sampled in a world frame equal to the rig frame at t = 0 (OpenCV axes: x right,
y down, z forward), then expressed in the rig frame of every frame:

- *Head egomotion*: `T_world_rig(t)`, smooth yaw / pitch / roll (sums of random
  sinusoids of 0.1-0.8 Hz; tens of degrees and up to ~60 deg/s, as in head-mounted
  capture) and a few centimetres of translation, plus occasional quick head turns.
- *Wrist*: a reach-and-hold path in front of the body (random waypoints every
  0.5-1.5 s joined by minimum-jerk segments), 0.22-0.7 m from the eyes and mostly
  0.25-0.5 m; some clips swing the hand out of one or both views and back. Held-out
  sets can spread the waypoints evenly over another depth range
  (`MotionConfig.depth_sampling`, `depth_range_m`).
- *Wrist orientation*: carried by the forearm (`wrist_orientations`): the hand continues
  the forearm from an elbow below the head, palm down and rolled towards thumb-up by
  about 30 degrees, the wrist flexing and deviating smoothly by a few tens of degrees
  (the egocentric view of a working hand as a body holds it, forearms entering from below).
- *Articulation*: keyframes from the built-in model's natural-pose archetypes (grasp,
  release, pinch, point, flat, ...) blended with joint noise, joined by minimum-jerk
  interpolation in anatomical angles and clipped to the joint limits.
- *Forearms*: an elliptical tube from each wrist towards the elbow below the head
  (`forearm_surface`): rendered, and an occluder of the joints.
- *Shape*: betas ~ N(0, shape_sd^2 I), one per clip (both hands belong to one person);
  `MotionConfig.shape_sd` > 1 makes hand sizes past the training distribution.

Left hands are sampled as right hands and mirrored (docs/architecture.md), then posed with
the left model. Ground truth per frame and hand: MANO parameters in the rig frame,
21 joints, vertices on request, per-view per-joint visibility (inside the image and not
hidden by the hand itself, the other hand, a forearm or the held object, by a depth test) and the
appendix-L on-screen flag.
"""

import dataclasses
import math

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from .. import mano, metrics
from ..cameras import StereoRig
from ..mano.anatomy import JOINT_LIMITS
from ..mano.builtin_generator import ARCHETYPES, archetype_angles
from ..rotations import axis_angle_to_matrix, matrix_to_axis_angle

FPS = 30.0
DEPTH_SAMPLINGS = ("egocentric", "uniform")


@dataclasses.dataclass(frozen=True)
class MotionConfig:
    """Knobs of the motion sampler (defaults: the paper's label statistics)."""

    fps: float = FPS
    two_hands_probability: float = 0.6
    leave_view_probability: float = 0.3
    head_yaw_deg: float = 18.0
    head_pitch_deg: float = 10.0
    head_roll_deg: float = 4.0
    head_translation_m: float = 0.04
    object_probability: float = 0.5
    depth_range_m: tuple[float, float] = (0.15, 0.8)
    """(near, far) limits of the wrist's depth, metres (z in the world frame, the rig at
    t = 0). With "egocentric" sampling it only clips (the default limits nothing the
    waypoints reach); with "uniform" sampling it is the range the waypoints cover."""
    depth_sampling: str = "egocentric"
    """Depth of the wrist waypoints: "egocentric", the paper's label statistics
    (log-normal, median 0.37 m, clipped to 0.22-0.7 m), or "uniform" in `depth_range_m`
    (held-out sets with depths past the training range, e.g. (0.1, 1.1))."""
    shape_sd: float = 1.0
    """Standard deviation of the clip's MANO betas (1: the training distribution; larger:
    hand sizes past it, beta 0 being overall size, 7% per unit)."""

    def __post_init__(self):
        near, far = self.depth_range_m
        if not 0 < near < far:
            raise ValueError(f"depth_range_m must be 0 < near < far metres; got {self.depth_range_m}")
        if self.depth_sampling not in DEPTH_SAMPLINGS:
            raise ValueError(f"unknown depth_sampling {self.depth_sampling!r}; choose one of {DEPTH_SAMPLINGS}")
        if not 0 <= self.shape_sd < math.inf:
            raise ValueError(f"shape_sd must be a finite number >= 0; got {self.shape_sd}")


def _smooth_noise(rng: np.random.Generator, T: int, fps: float, amplitude: float, dims: int, freqs=(0.1, 0.8)) -> np.ndarray:
    """(T, dims) sum of four random sinusoids per dimension, RMS about `amplitude`."""
    t = np.arange(T)[:, None] / fps
    out = np.zeros((T, dims))
    for _ in range(4):
        f = rng.uniform(*freqs, size=dims)
        phase = rng.uniform(0, 2 * np.pi, size=dims)
        out += rng.normal(size=dims) * np.sin(2 * np.pi * f * t + phase)
    return out * amplitude / 2.0


def _min_jerk(keys: np.ndarray, key_times: np.ndarray, T: int, fps: float) -> np.ndarray:
    """Minimum-jerk (quintic smoothstep) interpolation through keyframes (K, ...) at times (K,)."""
    t = np.arange(T) / fps
    idx = np.clip(np.searchsorted(key_times, t, side="right") - 1, 0, len(key_times) - 2)
    span = key_times[idx + 1] - key_times[idx]
    s = np.clip((t - key_times[idx]) / span, 0.0, 1.0)
    s = s**3 * (10 - 15 * s + 6 * s**2)
    s = s.reshape((T,) + (1,) * (keys.ndim - 1))
    return keys[idx] * (1 - s) + keys[idx + 1] * s


def _key_times(rng: np.random.Generator, duration: float, lo: float, hi: float) -> np.ndarray:
    times = [0.0]
    while times[-1] < duration:
        times.append(times[-1] + rng.uniform(lo, hi))
    return np.asarray(times)


def _rotation(axis_angle: np.ndarray) -> np.ndarray:
    return np.asarray(axis_angle_to_matrix(jnp.asarray(axis_angle)))


def head_poses(rng: np.random.Generator, T: int, cfg: MotionConfig) -> np.ndarray:
    """(T, 4, 4) T_world_rig: the head's pose, identity at t = 0."""
    angles = _smooth_noise(rng, T, cfg.fps, 1.0, 3) * np.deg2rad([cfg.head_pitch_deg, cfg.head_yaw_deg, cfg.head_roll_deg])
    if rng.uniform() < 0.3:  # a quick look-around
        t0 = rng.uniform(0.2, 0.8) * T / cfg.fps
        turn = np.deg2rad(rng.uniform(-40, 40)) / (1 + np.exp(-(np.arange(T) / cfg.fps - t0) * 8.0))
        angles[:, 1] += turn
    angles -= angles[:1]
    translation = _smooth_noise(rng, T, cfg.fps, cfg.head_translation_m, 3)
    translation -= translation[:1]
    T_world_rig = np.tile(np.eye(4), (T, 1, 1))
    T_world_rig[:, :3, :3] = _rotation(angles)
    T_world_rig[:, :3, 3] = translation
    return T_world_rig


def wrist_path(rng: np.random.Generator, T: int, cfg: MotionConfig, lateral: float, leave_view: bool) -> np.ndarray:
    """(T, 3) right-hand wrist positions in the world frame (metres)."""
    duration = T / cfg.fps
    times = _key_times(rng, duration, 0.5, 1.5)
    if cfg.depth_sampling == "uniform":
        depth = rng.uniform(*cfg.depth_range_m, size=len(times))
    else:
        depth = np.clip(rng.lognormal(np.log(0.37), 0.22, size=len(times)), 0.22, 0.7)
    x = lateral + rng.normal(scale=0.07, size=len(times))
    y = 0.10 + rng.normal(scale=0.06, size=len(times))
    keys = np.stack([x, y, depth], axis=1)
    if leave_view:  # one waypoint far to the side (out of one or both views)
        k = rng.integers(1, len(times))
        keys[k, 0] = np.sign(lateral or 1.0) * rng.uniform(0.45, 0.9) * keys[k, 2] * 1.6
    path = _min_jerk(keys, times, T, cfg.fps)
    path += _smooth_noise(rng, T, cfg.fps, 0.008, 3, freqs=(0.8, 2.5))  # tremor and small adjustments
    path[:, 2] = np.clip(path[:, 2], *cfg.depth_range_m)
    return path


def _axis_rotation(axis: np.ndarray, angle: np.ndarray) -> np.ndarray:
    """(T, 3, 3) rotations by `angle` (T,) about unit axes (T, 3) (Rodrigues)."""
    return _rotation(axis * angle[:, None])


def wrist_orientations(rng: np.random.Generator, T: int, cfg: MotionConfig, wrist: np.ndarray, hand_axes: np.ndarray) -> np.ndarray:
    """(T, 3, 3) right-hand wrist rotations in the world frame, carried by the forearm.

    Args:
        wrist: (T, 3) the wrist's path (`wrist_path`, world frame, metres).
        hand_axes: (3, 3) the hand's rest axes in the model frame, as columns: long axis
            (wrist -> middle knuckle), back-of-hand normal, and their cross product.
    The forearm runs from `ELBOW_WORLD_M` to the wrist; with the wrist joint at rest the
    hand continues it, palm down, then rolled about the forearm towards thumb-up
    (supination). The wrist joint flexes / extends about the hand's across axis and
    deviates radially / ulnarly about its back normal. Each of the three angles is a
    per-clip offset plus smooth variation (deg): roll 30 +- 25 (offset) +- 20 (smooth),
    flexion 0 +- 15 +- 20, deviation 0 +- 8 +- 8: the egocentric view of a working hand,
    as a body holds it.
    """
    mean, offset_sd, smooth_sd = np.deg2rad([30.0, 0.0, 0.0]), np.deg2rad([25.0, 15.0, 8.0]), np.deg2rad([20.0, 20.0, 8.0])
    roll, flexion, deviation = (mean + rng.normal(size=3) * offset_sd + _smooth_noise(rng, T, cfg.fps, 1.0, 3, freqs=(0.1, 0.6)) * smooth_sd).T
    along = wrist - ELBOW_WORLD_M
    along /= np.linalg.norm(along, axis=-1, keepdims=True)
    up = np.array([0.0, -1.0, 0.0])
    back = up - (along @ up)[:, None] * along
    back /= np.linalg.norm(back, axis=-1, keepdims=True)
    back = np.einsum("tij,tj->ti", _axis_rotation(along, roll), back)  # a right hand's thumb turns up
    across = np.cross(along, back)
    forearm = np.stack([along, back, across], axis=-1)  # (T, 3, 3) columns: the hand's axes at rest
    joint = np.einsum("tij,tjk->tik", _axis_rotation(np.broadcast_to([0.0, 0.0, 1.0], (T, 3)), flexion),
                      _axis_rotation(np.broadcast_to([0.0, 1.0, 0.0], (T, 3)), deviation))  # fmt: skip
    return np.einsum("tij,tjk,lk->til", forearm, joint, hand_axes)


def hand_axes(model: mano.ManoModel) -> np.ndarray:
    """(3, 3) a hand model's rest axes in its frame, as columns: wrist -> middle knuckle,
    the back-of-hand normal (model +y, orthogonalised; the palm faces -y), their cross product."""
    joints = np.asarray(mano.forward_joints(model, mano.ManoParams.zeros()), np.float64)
    long = joints[9] - joints[0]
    long /= np.linalg.norm(long)
    back = np.array([0.0, 1.0, 0.0]) - long[1] * long
    back /= np.linalg.norm(back)
    return np.stack([long, back, np.cross(long, back)], axis=-1)


def articulation(rng: np.random.Generator, T: int, cfg: MotionConfig, frames: np.ndarray) -> np.ndarray:
    """(T, 15, 3) right-hand poses (axis-angle) moving through natural-pose keyframes."""
    names = list(ARCHETYPES)
    table = np.stack([archetype_angles(n) for n in names])
    times = _key_times(rng, T / cfg.fps, 0.4, 1.2)
    a, b = rng.integers(len(names), size=(2, len(times)))
    mix = rng.uniform(size=(len(times), 1, 1))
    keys = (1 - mix) * table[a] + mix * table[b] + rng.normal(size=(len(times), 15, 3)) * np.deg2rad([8.0, 4.0, 2.0])
    keys = np.clip(keys, JOINT_LIMITS[None, ..., 0], JOINT_LIMITS[None, ..., 1])
    angles = _min_jerk(keys, times, T, cfg.fps)
    return np.einsum("jai,tji->tja", frames, angles)


def sample_hand_poses(seed: int, num_sequences: int, frames: int = 90, cfg: MotionConfig = MotionConfig()) -> np.ndarray:
    """(num_sequences * frames, 15, 3) right-hand poses (axis-angle, radians) of the
    synthetic engine's articulation (`articulation`), each sequence of `frames` frames
    drawn from `seed`'s generator: data for a learned pose prior (`esther prior --synthetic`)."""
    axes = _anatomical_frames(mano.load_builtin("right"))
    rng = np.random.default_rng(seed)
    return np.concatenate([articulation(rng, frames, cfg, axes) for _ in range(num_sequences)])


def _anatomical_frames(model: mano.ManoModel) -> np.ndarray:
    """(15, 3, 3) the model's anatomical joint frames at its template (what `articulation` poses in)."""
    return np.asarray(mano.anatomical_frames(model.joint_template, model.v_template[model.fingertip_ids], model.is_right), np.float64)


def _box_object(rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
    """A held box: 8 corners in the hand frame (metres) and its 6 quad faces."""
    size = rng.uniform([0.03, 0.03, 0.06], [0.07, 0.06, 0.14])
    corners = np.array([[x, y, z] for x in (-1, 1) for y in (-1, 1) for z in (-1, 1)]) * size / 2
    # in the MANO frame the palm faces -y; the box sits under the palm, between thumb and fingers
    corners = corners + np.array([-0.07, -0.045, 0.01])
    faces = np.array([[0, 1, 3, 2], [4, 6, 7, 5], [0, 4, 5, 1], [2, 3, 7, 6], [0, 2, 6, 4], [1, 5, 7, 3]])
    return corners, faces


class HandTrack(eqx.Module):
    """Ground truth of one hand over a clip, in the rig frame of each frame."""

    params: mano.ManoParams
    """(T,)-batched MANO parameters; betas repeated per frame."""
    joints: jax.Array
    """(T, 21, 3) keypoints, metres."""
    vertices: jax.Array
    """(T, V, 3) mesh vertices, metres."""


@dataclasses.dataclass
class ClipMotion:
    """Everything the detector simulator and the renderer need, per frame."""

    rig: StereoRig
    fps: float
    T_world_rig: np.ndarray  # (T, 4, 4)
    hands: dict[str, HandTrack]  # side -> track
    visibility: dict[str, np.ndarray]  # side -> (T, 2 views, 21) bool
    onscreen: dict[str, np.ndarray]  # side -> (T,) bool
    object_corners: np.ndarray | None  # (T, 8, 3) rig frame
    object_faces: np.ndarray | None
    betas: np.ndarray
    forearms: dict[str, np.ndarray]  # side -> (T, V, 3) rig frame (`forearm_surface`, faces `forearm_faces`)


@eqx.filter_jit
def _pose_track(model: mano.ManoModel, params: mano.ManoParams) -> tuple[jax.Array, jax.Array]:
    out = mano.forward_batch(model, params)
    return out.joints, out.vertices


def _to_rig(T_rig_world: np.ndarray, points: np.ndarray) -> np.ndarray:
    return np.einsum("tij,t...j->t...i", T_rig_world[:, :3, :3], points) + T_rig_world[:, None, :3, 3]


def sample_clip(rng: np.random.Generator, rig: StereoRig, num_frames: int, cfg: MotionConfig = MotionConfig()) -> ClipMotion:
    """Sample one clip's motion and compute its ground truth (joints, vertices, visibility)."""
    T = num_frames
    models = {"right": mano.load_builtin("right"), "left": mano.load_builtin("left")}
    right = models["right"]
    frames = _anatomical_frames(right)
    axes = hand_axes(right)
    sides = ["right", "left"] if rng.uniform() < cfg.two_hands_probability else [str(rng.choice(["right", "left"]))]
    betas = rng.normal(size=10) * cfg.shape_sd
    T_world_rig = head_poses(rng, T, cfg)
    T_rig_world = np.linalg.inv(T_world_rig)
    leave = rng.uniform() < cfg.leave_view_probability
    hands, object_corners, object_faces = {}, None, None
    with_object = rng.uniform() < cfg.object_probability
    holder = sides[0]
    for side in sides:
        # sampled as a right hand (on the right of the body); a left hand is its mirror image
        wrist = wrist_path(rng, T, cfg, 0.09 if side == "right" else 0.07, leave and side == sides[-1])
        R_world = wrist_orientations(rng, T, cfg, wrist, axes)
        hand_pose = articulation(rng, T, cfg, frames)
        if side == "left":
            wrist = wrist * np.array([-1.0, 1.0, 1.0])
            M = np.diag([-1.0, 1.0, 1.0])
            R_world = M @ R_world @ M
            hand_pose = hand_pose * np.array([1.0, -1.0, -1.0])
        R_rig = np.einsum("tij,tjk->tik", T_rig_world[:, :3, :3], R_world)
        params = mano.ManoParams(
            global_orient=jnp.asarray(np.asarray(matrix_to_axis_angle(jnp.asarray(R_rig))), jnp.result_type(float)),
            hand_pose=jnp.asarray(hand_pose, jnp.result_type(float)),
            betas=jnp.asarray(np.tile(betas, (T, 1)), jnp.result_type(float)),
            transl=jnp.asarray(_to_rig(T_rig_world, wrist[:, None])[:, 0], jnp.result_type(float)),
        )
        joints, vertices = _pose_track(models[side], params)
        hands[side] = HandTrack(params=params, joints=joints, vertices=vertices)
        if with_object and side == holder:
            corners, object_faces = _box_object(rng)
            corners = corners * np.array([1.0 if side == "right" else -1.0, 1.0, 1.0])
            # the box follows the wrist: model frame -> world (rotation about the rest wrist)
            rest_wrist = np.asarray(mano.rest_joints(models[side], jnp.asarray(betas, jnp.result_type(float)))[0])
            in_world = np.einsum("tij,kj->tki", R_world, corners - rest_wrist) + wrist[:, None]
            object_corners = _to_rig(T_rig_world, in_world)
    forearms = _forearms(hands, T_rig_world)
    visibility, onscreen = _visibility(rig, hands, np.asarray(right.faces), forearms, object_corners, object_faces)
    return ClipMotion(rig, cfg.fps, T_world_rig, hands, visibility, onscreen, object_corners, object_faces, betas, forearms)


# ----------------------------------------------------------------------------- forearms

ELBOW_WORLD_M = np.array([0.20, 0.45, 0.08])
"""Where a right forearm points from the wrist (world frame: right of, below and a little
in front of the eyes; the left one's is mirrored). The forearm runs straight from the
wrist towards this point, bent from the hand's long axis by at most 70 degrees: it comes
into egocentric views from below, as real forearms do, and does not cover the hand."""
FOREARM_LENGTH_M = 0.26
FOREARM_MAX_BEND_RAD = math.radians(70.0)
FOREARM_RINGS = 14
FOREARM_AROUND = 20


def forearm_faces(rings: int = FOREARM_RINGS, around: int = FOREARM_AROUND) -> np.ndarray:
    """(F, 3) outward triangles of the open forearm tube of `forearm_surface`."""
    i, j = np.meshgrid(np.arange(rings - 1), np.arange(around), indexing="ij")
    a, b = i * around + j, i * around + (j + 1) % around
    c, d = b + around, a + around
    return np.concatenate([np.stack([a, b, c], -1).reshape(-1, 3), np.stack([a, c, d], -1).reshape(-1, 3)])


def forearm_surface(
    joints: np.ndarray, elbow: np.ndarray, rings: int = FOREARM_RINGS, around: int = FOREARM_AROUND
) -> np.ndarray:
    """(T, rings * around, 3) vertices of a forearm attached to a hand (same frame).

    Args:
        joints: (T, 21, 3) the hand's keypoints (metres).
        elbow: (T, 3) the point the forearm runs towards (`ELBOW_WORLD_M` in that frame).
    A straight tube from 5 mm inside the wrist, bent from the hand's long axis by at most
    `FOREARM_MAX_BEND_RAD`; its cross-section is an ellipse, wide across the palm, 5.0 x
    3.0 cm at the wrist (the built-in hand's wrist) and 7.2 x 6.0 cm at the elbow, for a
    hand of 9 cm from the wrist to the middle knuckle (scaled with the hand). Faces:
    `forearm_faces`.
    """
    wrist, index, middle, pinky = joints[:, 0], joints[:, 5], joints[:, 9], joints[:, 17]
    hand_length = np.linalg.norm(middle - wrist, axis=-1, keepdims=True)  # (T, 1)
    back = (wrist - middle) / hand_length
    to_elbow = elbow - wrist
    to_elbow /= np.linalg.norm(to_elbow, axis=-1, keepdims=True)
    # straight towards the elbow, the wrist bent by at most FOREARM_MAX_BEND_RAD
    cos = np.clip(np.sum(back * to_elbow, axis=-1, keepdims=True), -1.0, 1.0)
    normal = to_elbow - cos * back
    normal /= np.maximum(np.linalg.norm(normal, axis=-1, keepdims=True), 1e-9)
    bend = np.minimum(np.arccos(cos), FOREARM_MAX_BEND_RAD)
    direction = np.cos(bend) * back + np.sin(bend) * normal  # (T, 3)
    s = np.linspace(-0.005, FOREARM_LENGTH_M, rings)  # distance from the wrist
    tangent = np.broadcast_to(direction[:, None], (len(joints), rings, 3))
    centre = wrist[:, None] + s[None, :, None] * tangent
    across = (index - pinky)[:, None] * np.ones((1, rings, 1))
    across = across - np.sum(across * tangent, axis=-1, keepdims=True) * tangent
    across /= np.linalg.norm(across, axis=-1, keepdims=True)
    thick = np.cross(tangent, across)  # (tangent, across, thick) is right-handed: outward faces
    scale = hand_length[:, None] / 0.09  # (T, 1, 1)
    half_w = (0.025 + 0.011 * s / FOREARM_LENGTH_M)[None, :, None] * scale
    half_t = (0.015 + 0.015 * s / FOREARM_LENGTH_M)[None, :, None] * scale
    phi = 2 * np.pi * np.arange(around) / around
    ring = (
        centre[:, :, None]
        + np.cos(phi)[None, None, :, None] * (half_w * across)[:, :, None]
        + np.sin(phi)[None, None, :, None] * (half_t * thick)[:, :, None]
    )
    return ring.reshape(len(joints), rings * around, 3)


def _forearms(hands: dict[str, HandTrack], T_rig_world: np.ndarray) -> dict[str, np.ndarray]:
    out = {}
    for side, track in hands.items():
        elbow_world = ELBOW_WORLD_M * np.array([1.0 if side == "right" else -1.0, 1.0, 1.0])
        elbow = _to_rig(T_rig_world, np.broadcast_to(elbow_world, (len(T_rig_world), 1, 3)))[:, 0]
        out[side] = forearm_surface(np.asarray(track.joints, np.float64), elbow)
    return out


# ----------------------------------------------------------------------------- visibility

_SPLAT_CELL_PX = 5.0
"""Cell size of the splatted depth buffer used for occlusion (px). The hands are splatted
densely (`_surface_points`: about 2.5 mm apart), so that on the paper's rig (623 px focal)
the cells of a hand from 0.3 m on hold surface points and no hole lets a hidden joint through."""
_FACE_SAMPLES = np.array([[1 / 3, 1 / 3, 1 / 3], [2 / 3, 1 / 6, 1 / 6], [1 / 6, 2 / 3, 1 / 6], [1 / 6, 1 / 6, 2 / 3]])
"""Barycentric points per triangle added to a hand's vertices for the depth test."""
JOINT_DEPTH_BELOW_SKIN_M = np.array([0.025, 0.025, 0.016, 0.014, 0.012] + [0.022, 0.016, 0.014, 0.012] * 4)
"""A joint lies inside the hand: it counts as visible when no surface is more than its
own depth below the skin (palm joints deeper than finger joints) in front of it, i.e.
only other parts of the hand, the other hand or the object occlude it."""


_OBJECT_POINTS_PER_SIDE = 12


def _object_points(corners: np.ndarray, faces: np.ndarray, per_side: int = _OBJECT_POINTS_PER_SIDE) -> np.ndarray:
    """(T, n, 3) points densely covering the box faces (for the depth test)."""
    s = (np.arange(per_side) + 0.5) / per_side
    u, v = np.meshgrid(s, s)
    pts = []
    for f in faces:
        a, b, _, d = corners[:, f[0]], corners[:, f[1]], corners[:, f[2]], corners[:, f[3]]
        pts.append(a[:, None] + u.reshape(1, -1, 1) * (b - a)[:, None] + v.reshape(1, -1, 1) * (d - a)[:, None])
    return np.concatenate(pts, axis=1)


def _occluders_depth(camera, points_cam: jax.Array) -> tuple[jax.Array, jax.Array]:
    """Per-point splat depth buffer lookup helper: (cell ids, depths) of occluder points."""
    uv = camera.project(points_cam)
    cell = jnp.floor((uv + 0.5) / _SPLAT_CELL_PX).astype(jnp.int32)
    return cell, points_cam[..., 2]


@eqx.filter_jit
def _joint_visibility(camera, joints_cam: jax.Array, occluders_cam: jax.Array, occluder_mask: jax.Array, below_skin: jax.Array) -> jax.Array:
    """(J,) bool: inside the image and not behind an occluder splat (one frame, one view;
    the joints of every hand at once, so the splat is made once).

    Occluder points (those `occluder_mask` keeps) are splatted into cells of `_SPLAT_CELL_PX` px, keeping the nearest
    depth in each cell; a joint is hidden when the nearest surface in its cell is more
    than `below_skin` (per joint, `JOINT_DEPTH_BELOW_SKIN_M`) in front of it.
    """
    in_image = camera.is_visible(joints_cam)
    cells_w = int(math.ceil(camera.width / _SPLAT_CELL_PX)) + 2
    cells_h = int(math.ceil(camera.height / _SPLAT_CELL_PX)) + 2
    occ_cell, occ_depth = _occluders_depth(camera, occluders_cam)
    in_grid = (occ_cell[:, 0] >= 0) & (occ_cell[:, 0] < cells_w - 2) & (occ_cell[:, 1] >= 0) & (occ_cell[:, 1] < cells_h - 2)
    inside = occluder_mask & (occ_depth > 1e-3) & in_grid
    flat = (occ_cell[:, 1] + 1) * cells_w + (occ_cell[:, 0] + 1)
    big = jnp.asarray(1e9, occ_depth.dtype)
    buffer = jnp.full(cells_w * cells_h, big).at[jnp.where(inside, flat, 0)].min(jnp.where(inside, occ_depth, big))
    nearest = buffer.reshape(cells_h, cells_w)
    j_cell, j_depth = _occluders_depth(camera, joints_cam)
    jx = jnp.clip(j_cell[:, 0] + 1, 0, cells_w - 1)
    jy = jnp.clip(j_cell[:, 1] + 1, 0, cells_h - 1)
    front = nearest[jy, jx]
    return in_image & (front > j_depth - below_skin)


def _surface_points(vertices: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """(T, V + 4 F, 3) a hand's vertices and four points inside each triangle (depth test)."""
    inside = np.einsum("kc,tfcd->tfkd", _FACE_SAMPLES, vertices[:, faces])
    return np.concatenate([vertices, inside.reshape(len(vertices), -1, 3)], axis=1)


def _forearm_points(forearm: np.ndarray, factor: int = 4) -> np.ndarray:
    """(T, n, 3) the forearm tube resampled `factor` times finer (for the depth test)."""
    T = len(forearm)
    grid = forearm.reshape(T, FOREARM_RINGS, FOREARM_AROUND, 3)
    grid = np.concatenate([grid, grid[:, :, :1]], axis=2)  # close the ring
    r = np.linspace(0, FOREARM_RINGS - 1, (FOREARM_RINGS - 1) * factor + 1)
    a = np.linspace(0, FOREARM_AROUND, FOREARM_AROUND * factor, endpoint=False)
    r0, a0 = np.minimum(r.astype(int), FOREARM_RINGS - 2), a.astype(int)
    fr, fa = (r - r0)[:, None, None], (a - a0)[None, :, None]
    g = lambda i, j: grid[:, i][:, :, j]  # noqa: E731
    points = (1 - fr) * ((1 - fa) * g(r0, a0) + fa * g(r0, a0 + 1)) + fr * ((1 - fa) * g(r0 + 1, a0) + fa * g(r0 + 1, a0 + 1))
    return points.reshape(T, -1, 3)


def _visibility(rig: StereoRig, hands: dict[str, HandTrack], hand_faces: np.ndarray, forearms: dict[str, np.ndarray], object_corners, object_faces):
    """Per-view per-joint visibility and the on-screen flag of each hand. The occluders and
    joints are padded to two hands, two forearms and a box (masked points), so every clip
    of a length reuses one compiled program."""
    T = len(next(iter(hands.values())).joints)
    parts = {side: (_surface_points(np.asarray(h.vertices), hand_faces), _forearm_points(forearms[side])) for side, h in hands.items()}
    surface, forearm = (p.shape[1] for p in next(iter(parts.values())))
    hand_slots = [slice(i * surface, (i + 1) * surface) for i in range(2)]
    arm_slots = [slice(2 * surface + i * forearm, 2 * surface + (i + 1) * forearm) for i in range(2)]
    box_slot = slice(2 * (surface + forearm), None)
    occ_rig = np.zeros((T, 2 * (surface + forearm) + 6 * _OBJECT_POINTS_PER_SIDE**2, 3))
    occ_mask = np.zeros(occ_rig.shape[1], bool)
    for hand_slot, arm_slot, (hand_points, arm_points) in zip(hand_slots, arm_slots, parts.values()):
        occ_rig[:, hand_slot], occ_rig[:, arm_slot] = hand_points, arm_points
        occ_mask[hand_slot] = occ_mask[arm_slot] = True
    if object_corners is not None:
        occ_rig[:, box_slot], occ_mask[box_slot] = _object_points(object_corners, object_faces), True
    sides = list(hands)
    joints = np.zeros((T, 2 * 21, 3))
    for i, side in enumerate(sides):
        joints[:, 21 * i : 21 * (i + 1)] = np.asarray(hands[side].joints)
    dtype = jnp.result_type(float)
    below_skin = jnp.asarray(np.tile(JOINT_DEPTH_BELOW_SKIN_M, 2), dtype)
    occ_views, joint_views = rig.to_views(jnp.asarray(occ_rig, dtype)), rig.to_views(jnp.asarray(joints, dtype))
    per_frame = jax.vmap(_joint_visibility, in_axes=(None, 0, 0, None, None))
    seen = np.stack([np.asarray(per_frame(camera, joint_views[v], occ_views[v], jnp.asarray(occ_mask), below_skin))
                     for v, camera in enumerate((rig.left, rig.right))], axis=1)  # fmt: skip
    visibility = {side: seen[:, :, 21 * i : 21 * (i + 1)] for i, side in enumerate(sides)}
    onscreen = {side: np.asarray(jax.vmap(metrics.onscreen, in_axes=(0, None))(jnp.asarray(hands[side].joints, dtype), rig)) for side in sides}
    return visibility, onscreen
