"""Which detected hand is the right one: stereo geometry and time, not the detector's label.

A detector's left/right label is unreliable (MediaPipe's flips with mirrored input and
changed between versions), so `assign_hands` decides by evidence, in four steps:

1. **Stereo pairing.** In each frame, every (left-view hand, right-view hand) pair is
   triangulated keypoint by keypoint with the rig (`triangulation.triangulate_rig`, each
   view through its own camera: the two may differ in model and image size); a pair is
   the same hand when the median reprojection error of its keypoints is below
   `pair_tolerance` of the hand box diagonal. Pairs are chosen by minimum total error
   (Hungarian). Unpaired hands stay one-view observations.
2. **Tracks.** Observations are linked frame to frame (Hungarian on the mean keypoint
   distance in a view both saw, over the box diagonal, below `link_tolerance`; a track
   survives `max_gap` frames without observations).
3. **Evidence per track.** Chirality is a geometric fact of a 3D hand (`chirality`): a
   right hand's fingers curl towards the side its palm normal points to, a left hand's
   away. Each paired observation adds the chirality of its *triangulated* keypoints
   (weight `STEREO_WEIGHT`), each view adds the chirality of the detector's own 3D
   estimate if it has one (`MONOCULAR_WEIGHT`), and the detector's label adds a little
   (`LABEL_WEIGHT` x its score: a tie-breaker). A track's side is the sign of the sum. With no
   evidence at all, a track in the right half of its image is the right hand (the
   egocentric prior, a last resort).
4. **One hand per side.** Tracks of fewer than `min_observations` frames (a hand glimpsed
   once or twice: mostly a spurious detection, or a detection of a hand that failed to
   link) are dropped, as a tracker confirms a track only after a few hits. The others are
   given their side strongest evidence first; a track that overlaps in time with a track
   already holding its side takes the other side if free during its frames, and is
   dropped otherwise. The report says which tracks were dropped and why.
"""

import dataclasses

import jax.numpy as jnp
import numpy as np
from jaxtyping import Float
from scipy.optimize import linear_sum_assignment

from ..cameras import StereoRig
from ..triangulation import triangulate_rig
from .base import NUM_KEYPOINTS, Candidates

STEREO_WEIGHT = 1.0
MONOCULAR_WEIGHT = 0.5
LABEL_WEIGHT = 0.02
"""A tie-breaker: a stereo frame of a relaxed hand gives chirality 0.2-0.8, two confident labels 0.04."""
_TIPS, _MCPS = (8, 12, 16, 20), (5, 9, 13, 17)


def chirality(points: Float[np.ndarray, "*batch 21 3"]) -> Float[np.ndarray, "*batch"]:
    """Signed handedness of 3D keypoints in a right-handed frame (OpenCV camera or rig):
    the mean fingertip offset from the knuckles along the palm normal
    `(index_mcp - wrist) x (pinky_mcp - wrist)`, over the wrist-to-middle-knuckle length.
    Positive for a right hand whose fingers curl towards the palm, negative for a left
    hand (mirroring flips it); near 0 for a flat hand. 0 where undefined (NaN input)."""
    points = np.asarray(points, np.float64)
    wrist = points[..., 0, :]
    normal = np.cross(points[..., 5, :] - wrist, points[..., 17, :] - wrist)
    normal = normal / np.maximum(np.linalg.norm(normal, axis=-1, keepdims=True), 1e-12)
    curl = points[..., _TIPS, :].mean(axis=-2) - points[..., _MCPS, :].mean(axis=-2)
    length = np.maximum(np.linalg.norm(points[..., 9, :] - wrist, axis=-1), 1e-12)
    value = np.sum(normal * curl, axis=-1) / length
    return np.where(np.isfinite(value), value, 0.0)


@dataclasses.dataclass
class _Observation:
    frame: int
    slots: dict[int, int]  # view -> candidate slot
    evidence: float
    stereo: bool


@dataclasses.dataclass
class _Track:
    observations: list[_Observation] = dataclasses.field(default_factory=list)
    last: dict[int, tuple[int, np.ndarray, float]] = dataclasses.field(default_factory=dict)  # view -> (frame, uv, diagonal)

    @property
    def frames(self) -> set[int]:
        return {o.frame for o in self.observations}

    @property
    def evidence(self) -> float:
        return float(sum(o.evidence for o in self.observations))


def _diagonal(box: np.ndarray) -> np.ndarray:
    return np.asarray(np.maximum(np.hypot(box[..., 2] - box[..., 0], box[..., 3] - box[..., 1]), 1.0))


def _stereo_pairs(c: Candidates, rig: StereoRig, tolerance: float) -> tuple[np.ndarray, np.ndarray]:
    """cost [T, H, H] (median reprojection error over the box diagonal; inf where no pair)
    and the triangulated keypoints [T, H, H, 21, 3] of every (left slot, right slot) pair."""
    T, _, H = c.score.shape
    uv = np.stack(np.broadcast_arrays(c.uv[:, 0, :, None], c.uv[:, 1, None, :]), axis=-2)  # T H H 21 2views 2
    conf = np.stack(np.broadcast_arrays(c.conf[:, 0, :, None], c.conf[:, 1, None, :]), axis=-1)  # T H H 21 2views
    tri = triangulate_rig(rig, jnp.asarray(np.nan_to_num(uv)), jnp.asarray(conf))
    residual = np.asarray(tri.residual_px).max(axis=-1)
    used = np.asarray(tri.valid) & np.all(conf > 0, axis=-1)
    enough = used.sum(axis=-1) >= NUM_KEYPOINTS // 2
    ranked = np.sort(np.where(used, residual, np.inf), axis=-1)
    median = np.take_along_axis(ranked, np.maximum(used.sum(axis=-1) - 1, 0)[..., None] // 2, axis=-1)[..., 0]  # over used keypoints
    diagonal = 0.5 * (_diagonal(c.box[:, 0, :, None]) + _diagonal(c.box[:, 1, None, :]))
    both = (c.score[:, 0, :, None] > 0) & (c.score[:, 1, None, :] > 0)
    cost = np.where(both & enough & np.isfinite(median), median / np.where(np.isfinite(diagonal), diagonal, 1.0), np.inf)
    return np.where(cost < tolerance, cost, np.inf), np.asarray(tri.point)


def assign_hands(
    c: Candidates,
    rig: StereoRig,
    *,
    pair_tolerance: float = 0.1,
    link_tolerance: float = 0.5,
    max_gap: int = 5,
    min_observations: int = 3,
) -> tuple[dict[str, dict[str, np.ndarray]], dict]:
    """Left/right hands from one detector's candidates (see the module docstring).

    Returns `({side: {"uv" [T,2,21,2], "conf" [T,2,21], "box" [T,2,4], "box_score" [T,2]}},
    report)`: the keypoints.npz arrays of each side found (without the detector axis),
    and a report of the tracks (side, frames, evidence, stereo observations; a dropped
    track's `dropped` says why). A clip shorter than `min_observations` frames needs a
    track in every frame.
    """
    T, V, H = c.score.shape
    cost, points = _stereo_pairs(c, rig, pair_tolerance)
    stereo_chirality = chirality(points)
    observations: list[list[_Observation]] = []
    for t in range(T):
        here, used = [], set()
        if np.isfinite(cost[t]).any():
            rows, cols = linear_sum_assignment(np.where(np.isfinite(cost[t]), cost[t], 1e9))
            for i, j in zip(rows, cols):
                if np.isfinite(cost[t, i, j]):
                    here.append(_Observation(t, {0: int(i), 1: int(j)}, STEREO_WEIGHT * float(np.clip(stereo_chirality[t, i, j], -1, 1)), True))
                    used |= {(0, i), (1, j)}
        for v in range(V):
            for k in range(H):
                if c.score[t, v, k] > 0 and (v, k) not in used:
                    here.append(_Observation(t, {v: k}, 0.0, False))
        for o in here:
            for v, k in o.slots.items():
                o.evidence += MONOCULAR_WEIGHT * float(np.clip(c.chirality[t, v, k], -1, 1))
                o.evidence += LABEL_WEIGHT * float(c.label[t, v, k]) * float(c.label_score[t, v, k])
        observations.append(here)

    tracks: list[_Track] = []
    for t, here in enumerate(observations):
        alive = [tr for tr in tracks if any(t - f <= max_gap for f, _, _ in tr.last.values())]
        link = np.full((len(here), len(alive)), np.inf)
        for i, o in enumerate(here):
            for j, tr in enumerate(alive):
                for v, k in o.slots.items():
                    if v in tr.last and t - tr.last[v][0] <= max_gap:
                        ok = c.conf[t, v, k] > 0
                        if ok.any():
                            d = np.linalg.norm(c.uv[t, v, k][ok] - tr.last[v][1][ok], axis=-1).mean() / tr.last[v][2]
                            link[i, j] = min(link[i, j], d)
        link = np.where(link < link_tolerance, link, np.inf)
        matched = {}
        if np.isfinite(link).any():
            rows, cols = linear_sum_assignment(np.where(np.isfinite(link), link, 1e9))
            matched = {i: alive[j] for i, j in zip(rows, cols) if np.isfinite(link[i, j])}
        for i, o in enumerate(here):
            track = matched.get(i)
            if track is None:
                track = _Track()
                tracks.append(track)
            track.observations.append(o)
            for v, k in o.slots.items():
                track.last[v] = (t, c.uv[t, v, k], float(_diagonal(c.box[t, v, k])))

    def prior_side(track: _Track) -> int:  # the egocentric last resort
        o = track.observations[0]
        v, k = next(iter(o.slots.items()))
        width = (rig.left if v == 0 else rig.right).width
        return 1 if np.nanmean(c.uv[o.frame, v, k, :, 0]) > (width - 1) / 2 else -1

    taken: dict[int, set[int]] = {1: set(), -1: set()}
    out = {s: {"uv": np.full((T, 2, NUM_KEYPOINTS, 2), np.nan), "conf": np.zeros((T, 2, NUM_KEYPOINTS)),
               "box": np.full((T, 2, 4), np.nan), "box_score": np.zeros((T, 2))} for s in (1, -1)}  # fmt: skip
    report_tracks = []
    for track in sorted(tracks, key=lambda tr: -abs(tr.evidence)):
        evidence = track.evidence
        preferred = int(np.sign(evidence)) if evidence != 0 else prior_side(track)
        frames = track.frames
        needed = min(min_observations, T)
        short = len(track.observations) < needed
        side = 0 if short else next((s for s in (preferred, -preferred) if not frames & taken[s]), 0)
        report_tracks.append({
            "side": {1: "right", -1: "left", 0: "dropped"}[side], "first_frame": min(frames), "last_frame": max(frames),
            "observations": len(track.observations), "stereo_observations": sum(o.stereo for o in track.observations),
            "evidence": evidence, "evidence_side": {1: "right", -1: "left"}[preferred] if evidence != 0 else "none (image position)",
        })  # fmt: skip
        if side == 0:
            report_tracks[-1]["dropped"] = f"fewer than {needed} frames" if short else "both sides held during its frames"
            continue
        taken[side] |= frames
        for o in track.observations:
            for v, k in o.slots.items():
                out[side]["uv"][o.frame, v] = c.uv[o.frame, v, k]
                out[side]["conf"][o.frame, v] = c.conf[o.frame, v, k]
                out[side]["box"][o.frame, v] = c.box[o.frame, v, k]
                out[side]["box_score"][o.frame, v] = c.score[o.frame, v, k]
    hands = {name: out[s] for s, name in ((1, "right"), (-1, "left")) if out[s]["box_score"].any()}
    report = {"tracks": sorted(report_tracks, key=lambda r: (r["first_frame"], r["side"]))}
    return hands, report
