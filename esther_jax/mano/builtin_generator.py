"""Generator of the built-in open hand model: MANO format, our own geometry.

    python -m esther_jax.mano.builtin_generator [--out esther_jax/mano/assets/builtin_right.npz]

Nothing here comes from the licensed MANO files. The right hand is built from a
parametric design (joint positions, phalanx lengths, radii; adult proportions, wrist
to middle fingertip ~0.185 m) in MANO's frame and conventions (fingers along -x,
thumb on +z, back of the hand +y, 16-joint tree, fingertips at vertices
744/320/443/554/671), in seven steps:

1. *Surface*: a quad control cage is box-modelled from the design (a palm block whose
   four distal faces are extruded into fingers and one radial face into the thumb,
   one ring per joint) and refined twice by Catmull-Clark. Subdivision is linear in
   the cage, so the mesh is `S @ cage` for one sparse matrix S; the result is a
   closed, consistently oriented surface (1410 vertices, 2816 triangles).
2. *Shape space*: ten named design perturbations (size, finger length, palm width,
   thickness, thumb length, palm length, taper, index/ring ratio, spread, pinky);
   `shapedirs[..., k]` is the central difference of the whole pipeline at
   beta_k = +-1, with per-direction standard deviations in `SHAPE_STD`.
3. *Joints*: the design joints and their shape derivatives are reproduced exactly
   by a dense, local `J_regressor` (minimum-norm weights on the 64 nearest vertices).
4. *Skinning*: inverse-distance weights (power 6) to each joint's bone segment,
   restricted to the vertex's own chain, then diffused over the mesh: smooth,
   non-negative, normalised, blending over about one finger radius at each joint.
5. *Corrective pose blend shapes*: linear blend skinning shrinks a bent joint by up
   to cos(theta/2); each finger joint pushes the skin of its blend zone away from the
   bone in proportion to (1 - cos theta) = -tr(R - I) / 2, which is linear in MANO's
   pose features, so it is an exact `posedirs` entry.
6. *Pose space*: 45-D PCA (components scaled by their standard deviation, as in
   MANO) of 20000 poses from a documented distribution of natural hand poses:
   blends of nine grasp archetypes (flat, spread, relaxed, fist, power grasp, pinch,
   tripod, point, thumb out) in anatomical angles, with joint noise, clipped to the
   limits of `anatomy.JOINT_LIMITS`.
7. *Ids*: vertices are renumbered so the fingertip apices are 744/320/443/554/671
   (smplx) and the manopth ids 745/317/444/445/556/673 are tip vertices next to them.

The left hand is not stored: `load_builtin("left")` mirrors this one exactly.
"""

import argparse
import dataclasses
import math
import pathlib

import jax
import jax.numpy as jnp
import numpy as np
import scipy.sparse as sp

from ..files import atomic_output
from .constants import (
    FINGER_CHAINS,
    FINGER_ORDER,
    FINGERTIP_IDS_MANOPTH,
    FINGERTIP_IDS_SMPLX,
    MANO_PARENTS,
    NUM_BETAS,
)

ASSET_PATH = pathlib.Path(__file__).with_name("assets") / "builtin_right.npz"
GENERATOR_VERSION = "esther-open-hand-2"

WRIST_POSITION = np.array([0.0957, 0.0064, 0.0062])
"""Rest wrist joint in the model frame (placed as MANO's, so smplx-style transl look familiar)."""

FINGERS4 = ("index", "middle", "ring", "pinky")
CAGE_RADIUS_GAIN = 1.09
"""Catmull-Clark pulls a 4-vertex ring inwards; cage half-sizes are radius * this gain."""


@dataclasses.dataclass(frozen=True)
class HandDesign:
    """Rest geometry of the right hand relative to the wrist (metres, radians)."""

    mcp: np.ndarray = dataclasses.field(
        default_factory=lambda: np.array(
            [[-0.086, 0.000, 0.026], [-0.090, 0.000, 0.005], [-0.085, -0.001, -0.0145], [-0.077, -0.003, -0.032]]
        )
    )
    """MCP joints of index, middle, ring, pinky."""
    splay: np.ndarray = dataclasses.field(default_factory=lambda: np.deg2rad(np.array([4.0, 0.0, -4.0, -9.0])))
    """Rest direction of each finger in the palm plane, positive towards the thumb."""
    lengths: np.ndarray = dataclasses.field(
        default_factory=lambda: np.array(
            [[0.040, 0.024, 0.021], [0.044, 0.027, 0.022], [0.041, 0.026, 0.022], [0.033, 0.020, 0.019]]
        )
    )
    """MCP->PIP, PIP->DIP, DIP->tip per finger."""
    radii: np.ndarray = dataclasses.field(
        default_factory=lambda: np.array(
            [
                [0.0100, 0.0088, 0.0077, 0.0066],
                [0.0104, 0.0091, 0.0079, 0.0068],
                [0.0097, 0.0085, 0.0074, 0.0064],
                [0.0086, 0.0076, 0.0067, 0.0059],
            ]
        )
    )
    """Half-width at MCP, PIP, DIP and near the tip."""
    thickness_ratio: float = 0.86
    """Finger half-thickness (dorsal-palmar) over half-width."""
    thumb_cmc: np.ndarray = dataclasses.field(default_factory=lambda: np.array([-0.024, -0.010, 0.019]))
    thumb_direction: np.ndarray = dataclasses.field(default_factory=lambda: np.array([-0.62, -0.30, 0.72]))
    thumb_lengths: np.ndarray = dataclasses.field(default_factory=lambda: np.array([0.044, 0.032, 0.027]))
    """CMC->MCP, MCP->IP, IP->tip."""
    thumb_radii: np.ndarray = dataclasses.field(default_factory=lambda: np.array([0.0125, 0.0108, 0.0093, 0.0080]))
    thumb_bend: float = math.radians(16.0)
    """Each distal thumb segment turns this much towards the fingers (-x)."""
    palm_mid_x: float = -0.046
    palm_half_thickness: np.ndarray = dataclasses.field(default_factory=lambda: np.array([0.0125, 0.0135, 0.0100]))
    """At the wrist, mid-palm and knuckle rows."""
    wrist_half_width: float = 0.0255
    wrist_cap_x: float = 0.008
    tip_cap_offset: np.ndarray = dataclasses.field(default_factory=lambda: np.full(5, 0.006))
    """How far beyond each designed tip (FINGER_ORDER) the cage's cap ring sits; fitted so
    that the subdivided surface ends at the tip (see `_fit_tip_caps`)."""


SHAPE_STD = np.array([0.07, 0.05, 0.05, 0.08, 0.06, 0.04, 0.06, 0.04, 1.0, 0.06])
"""Relative size of each shape direction at beta_k = 1 (direction 8, spread, is in units
of 2 degrees of splay per finger)."""

SHAPE_NAMES = (
    "size", "finger_length", "palm_width", "thickness", "thumb_length",
    "palm_length", "finger_taper", "index_ring_ratio", "finger_spread", "pinky_length",
)  # fmt: skip


def perturb(design: HandDesign, k: int, beta: float) -> HandDesign:
    """The design moved along shape direction k by beta standard deviations."""
    s = 1.0 + SHAPE_STD[k] * beta
    d = dataclasses.asdict(design)
    if k == 0:  # overall size about the wrist
        for name in ("mcp", "lengths", "radii", "thumb_cmc", "thumb_lengths", "thumb_radii", "palm_half_thickness", "tip_cap_offset"):
            d[name] = d[name] * s
        d["palm_mid_x"] *= s
        d["wrist_half_width"] *= s
        d["wrist_cap_x"] *= s
    elif k == 1:
        d["lengths"] = d["lengths"] * s
        d["thumb_lengths"] = d["thumb_lengths"] * (1.0 + 0.6 * SHAPE_STD[k] * beta)
    elif k == 2:
        d["mcp"] = d["mcp"] * np.array([1.0, 1.0, s])
        d["wrist_half_width"] *= s
        d["thumb_cmc"] = d["thumb_cmc"] * np.array([1.0, 1.0, s])
        d["radii"] = d["radii"] * (1.0 + 0.4 * SHAPE_STD[k] * beta)
    elif k == 3:
        d["palm_half_thickness"] = d["palm_half_thickness"] * s
        d["thickness_ratio"] *= s
        d["radii"] = d["radii"] * (1.0 + 0.5 * SHAPE_STD[k] * beta)
        d["thumb_radii"] = d["thumb_radii"] * (1.0 + 0.5 * SHAPE_STD[k] * beta)
    elif k == 4:
        d["thumb_lengths"] = d["thumb_lengths"] * s
        d["thumb_radii"] = d["thumb_radii"] * (1.0 + 0.3 * SHAPE_STD[k] * beta)
    elif k == 5:
        d["mcp"] = d["mcp"] * np.array([s, 1.0, 1.0])
        d["palm_mid_x"] *= s
    elif k == 6:
        taper = np.linspace(-0.5, 1.0, 4) * SHAPE_STD[k] * beta
        d["radii"] = d["radii"] * (1.0 + taper)
        d["thumb_radii"] = d["thumb_radii"] * (1.0 + taper)
    elif k == 7:
        d["lengths"] = d["lengths"] * (1.0 + SHAPE_STD[k] * beta * np.array([1.0, 0.0, -1.0, 0.0]))[:, None]
    elif k == 8:
        d["splay"] = d["splay"] + np.deg2rad(2.0) * beta * np.array([1.0, 0.0, -1.0, -2.0])
        d["mcp"] = d["mcp"] + np.array([0.0, 0.0, 0.0015]) * beta * np.array([1.0, 0.0, -1.0, -2.0])[:, None]
    elif k == 9:
        d["lengths"] = d["lengths"] * (1.0 + SHAPE_STD[k] * beta * np.array([0.0, 0.0, 0.0, 1.0]))[:, None]
    else:
        raise ValueError(k)
    return HandDesign(**d)


# ----------------------------------------------------------------------------- skeleton


def _unit(v: np.ndarray) -> np.ndarray:
    return v / np.linalg.norm(v, axis=-1, keepdims=True)


def finger_direction(splay: float) -> np.ndarray:
    return np.array([-math.cos(splay), 0.0, math.sin(splay)])


def skeleton(design: HandDesign) -> tuple[np.ndarray, np.ndarray]:
    """Rest joints (16, MANO order) and fingertips (5, FINGER_ORDER), relative to the wrist."""
    joints = np.zeros((16, 3))
    tips = np.zeros((5, 3))
    for f, name in enumerate(FINGERS4):
        d = finger_direction(design.splay[f])
        chain = FINGER_CHAINS[name]
        p = design.mcp[f].copy()
        joints[chain[0]] = p
        for level in (1, 2):
            p = p + design.lengths[f, level - 1] * d
            joints[chain[level]] = p
        tips[FINGER_ORDER.index(name)] = p + design.lengths[f, 2] * d
    d = _unit(design.thumb_direction)
    chain = FINGER_CHAINS["thumb"]
    p = design.thumb_cmc.copy()
    joints[chain[0]] = p
    for level, length in enumerate(design.thumb_lengths):
        p = p + length * d
        if level < 2:
            joints[chain[level + 1]] = p
        d = _unit(d + math.tan(design.thumb_bend) * np.array([-1.0, 0.0, 0.0]))
    tips[0] = p
    return joints, tips


def _thumbnail_up(design: HandDesign, d: np.ndarray) -> np.ndarray:
    """The thumb's dorsal direction (the same definition as anatomy.anatomical_frames)."""
    from .anatomy import THUMBNAIL_TURN_RAD

    up = math.cos(THUMBNAIL_TURN_RAD) * np.array([0.0, 1.0, 0.0]) + math.sin(THUMBNAIL_TURN_RAD) * np.array([0, 0, 1.0])
    return _unit(up - np.dot(up, d) * d)


# ----------------------------------------------------------------------------- cage


@dataclasses.dataclass
class Cage:
    quads: np.ndarray  # (F, 4) int, outward (counter-clockwise seen from outside)
    tags: np.ndarray  # (V,) int: 0 palm, 1 + FINGER_ORDER index for finger rings
    rings: dict  # finger name -> list of 4-vertex index arrays (base first, then extruded)


def cage_topology() -> Cage:
    """Palm block (3 rows along the fingers x 5 columns across x 2 layers) with the four
    distal faces extruded three times (fingers) and one radial face three times (thumb)."""
    vid = lambda r, c, top: (r * 5 + c) * 2 + top  # noqa: E731
    n = 30
    quads = []
    for r in range(2):
        for c in range(4):
            quads.append([vid(r, c, 1), vid(r + 1, c, 1), vid(r + 1, c + 1, 1), vid(r, c + 1, 1)])  # dorsal
            quads.append([vid(r, c + 1, 0), vid(r + 1, c + 1, 0), vid(r + 1, c, 0), vid(r, c, 0)])  # palmar
    for c in range(4):
        quads.append([vid(0, c, 0), vid(0, c, 1), vid(0, c + 1, 1), vid(0, c + 1, 0)])  # wrist cap
    distal = {}
    for c, name in enumerate(("pinky", "ring", "middle", "index")):
        distal[name] = len(quads)
        quads.append([vid(2, c, 0), vid(2, c + 1, 0), vid(2, c + 1, 1), vid(2, c, 1)])
    for r in range(2):
        quads.append([vid(r, 0, 0), vid(r + 1, 0, 0), vid(r + 1, 0, 1), vid(r, 0, 1)])  # ulnar side
    thumb_face = None
    for r in range(2):
        if r == 0:
            thumb_face = len(quads)
        quads.append([vid(r, 4, 0), vid(r, 4, 1), vid(r + 1, 4, 1), vid(r + 1, 4, 0)])  # radial side
    tags = [0] * n
    rings = {}
    for name, face_index in list(distal.items()) + [("thumb", thumb_face)]:
        base = list(quads[face_index])
        rings[name] = [np.array(base)]
        face = base
        for _ in range(3):
            new = list(range(n, n + 4))
            n += 4
            tags += [1 + FINGER_ORDER.index(name)] * 4
            for i in range(4):
                p, q = face[i], face[(i + 1) % 4]
                quads.append([p, q, new[(i + 1) % 4], new[i]])
            face = new
            rings[name].append(np.array(new))
        quads[face_index] = face  # the last ring is the fingertip cap
    return Cage(np.asarray(quads), np.asarray(tags), rings)


def cage_positions(design: HandDesign, cage: Cage) -> np.ndarray:
    """Cage vertex positions (relative to the wrist) for a design."""
    joints, tips = skeleton(design)
    pos = np.zeros((cage.tags.size, 3))
    g = CAGE_RADIUS_GAIN
    # palm grid: column boundaries across z at the wrist, mid and knuckle rows
    order = ("pinky", "ring", "middle", "index")
    mcp = {name: design.mcp[FINGERS4.index(name)] for name in order}
    rad = {name: design.radii[FINGERS4.index(name), 0] * g for name in order}
    knuckle_z = [mcp["pinky"][2] - rad["pinky"]]
    knuckle_x = [mcp["pinky"][0]]
    knuckle_y = [design.thickness_ratio * rad["pinky"]]
    for a, b in zip(order[:-1], order[1:]):
        knuckle_z.append(0.5 * (mcp[a][2] + mcp[b][2]))
        knuckle_x.append(0.5 * (mcp[a][0] + mcp[b][0]))
        knuckle_y.append(design.thickness_ratio * 0.5 * (rad[a] + rad[b]))
    knuckle_z.append(mcp["index"][2] + rad["index"])
    knuckle_x.append(mcp["index"][0])
    knuckle_y.append(design.thickness_ratio * rad["index"])
    knuckle_z, knuckle_x, knuckle_y = map(np.asarray, (knuckle_z, knuckle_x, knuckle_y))
    knuckle_y = np.maximum(knuckle_y, design.palm_half_thickness[2] * g)
    knuckle_center_y = np.interp(knuckle_z, [mcp[o][2] for o in order], [mcp[o][1] for o in order])
    wrist_z = np.linspace(-design.wrist_half_width, design.wrist_half_width, 5) * g - 0.002
    mid_z = 0.45 * wrist_z + 0.55 * knuckle_z + np.array([-0.002, 0.0, 0.0, 0.0, 0.003])
    rows = [
        (np.full(5, design.wrist_cap_x), wrist_z, np.zeros(5), np.full(5, design.palm_half_thickness[0] * g)),
        (np.full(5, design.palm_mid_x), mid_z, 0.5 * knuckle_center_y, np.full(5, design.palm_half_thickness[1] * g)),
        (knuckle_x, knuckle_z, knuckle_center_y, knuckle_y),
    ]
    for r, (xs, zs, cy, hy) in enumerate(rows):
        for c in range(5):
            for top in (0, 1):
                pos[(r * 5 + c) * 2 + top] = [xs[c], cy[c] + (hy[c] if top else -hy[c]), zs[c]]
    # finger and thumb rings
    for name, ring_list in cage.rings.items():
        base = pos[ring_list[0]]
        center = base.mean(axis=0)
        offsets = base - center
        if name == "thumb":
            chain = FINGER_CHAINS["thumb"]
            centers = [joints[chain[1]], joints[chain[2]], tips[0]]
            radii = design.thumb_radii[1:]
        else:
            f = FINGERS4.index(name)
            chain = FINGER_CHAINS[name]
            centers = [joints[chain[1]], joints[chain[2]], tips[FINGER_ORDER.index(name)]]
            radii = design.radii[f, 1:]
        prev = joints[chain[0]]
        for level, (c, radius) in enumerate(zip(centers, radii)):
            d = _unit(c - prev)
            up = _thumbnail_up(design, d) if name == "thumb" else _unit(np.array([0, 1.0, 0]) - d[1] * d)
            lat = np.cross(up, d)
            s_lat = np.sign(offsets @ lat)
            s_up = np.sign(offsets @ up)
            assert len({(a, b) for a, b in zip(s_lat, s_up)}) == 4, "ring corners must be distinct"
            hw = radius * g
            hh = radius * g * (design.thickness_ratio if name != "thumb" else 0.9)
            if level == 2:  # the cap sits beyond the tip: subdivision rounds it back
                c = c + design.tip_cap_offset[FINGER_ORDER.index(name)] * d
                hw, hh = 0.75 * hw, 0.75 * hh
            pos[ring_list[level + 1]] = c + s_lat[:, None] * hw * lat + s_up[:, None] * hh * up
            prev = c
    return pos


# ----------------------------------------------------------------------------- subdivision


def catmull_clark(quads: np.ndarray, num_vertices: int) -> tuple[sp.csr_matrix, np.ndarray]:
    """One Catmull-Clark step on a closed quad mesh as a linear map.

    Returns S (V'+E+F x V) with new positions `S @ old` (order: vertex points, edge
    points, face points) and the 4F new quads (same orientation as their parents).
    """
    F = len(quads)
    directed = np.stack([quads, np.roll(quads, -1, axis=1)], -1).reshape(-1, 2)
    undirected, edge_of = np.unique(np.sort(directed, axis=1), axis=0, return_inverse=True)
    edge_of = edge_of.reshape(F, 4)
    E = len(undirected)
    if np.bincount(edge_of.ravel(), minlength=E).max() != 2 or np.bincount(edge_of.ravel(), minlength=E).min() != 2:
        raise ValueError("the cage is not a closed 2-manifold")
    V = num_vertices
    face_pts = sp.csr_matrix((np.full(4 * F, 0.25), (np.repeat(np.arange(F), 4), quads.ravel())), shape=(F, V))
    mid = sp.csr_matrix((np.full(2 * E, 0.5), (np.repeat(np.arange(E), 2), undirected.ravel())), shape=(E, V))
    edge_faces = sp.csr_matrix((np.full(4 * F, 0.5), (edge_of.ravel(), np.repeat(np.arange(F), 4))), shape=(E, F))
    edge_pts = 0.5 * mid + 0.5 * (edge_faces @ face_pts)
    valence = np.bincount(quads.ravel(), minlength=V).astype(float)
    vf = sp.csr_matrix((1.0 / valence[quads.ravel()], (quads.ravel(), np.repeat(np.arange(F), 4))), shape=(V, F))
    ve = sp.csr_matrix(
        (1.0 / valence[undirected.ravel()], (undirected.ravel(), np.repeat(np.arange(E), 2))), shape=(V, E)
    )
    inv_n = sp.diags(1.0 / valence)
    vertex_pts = inv_n @ (vf @ face_pts) + 2.0 * inv_n @ (ve @ mid) + sp.diags((valence - 3.0) / valence)
    S = sp.vstack([vertex_pts, edge_pts, face_pts]).tocsr()
    new_quads = []
    for i in range(4):
        new_quads.append(
            np.stack([quads[:, i], V + edge_of[:, i], V + E + np.arange(F), V + edge_of[:, (i - 1) % 4]], -1)
        )
    return S, np.stack(new_quads, 1).reshape(-1, 4)


def triangulate(quads: np.ndarray, positions: np.ndarray) -> np.ndarray:
    """Split each quad along its shorter diagonal (orientation kept)."""
    a, b, c, d = quads.T
    short_ac = np.linalg.norm(positions[a] - positions[c], axis=1) <= np.linalg.norm(positions[b] - positions[d], axis=1)
    t1 = np.where(short_ac[:, None], np.stack([a, b, c], 1), np.stack([a, b, d], 1))
    t2 = np.where(short_ac[:, None], np.stack([a, c, d], 1), np.stack([b, c, d], 1))
    return np.concatenate([t1, t2])


# ----------------------------------------------------------------------------- model pieces


def _segment_distance(points: np.ndarray, a: np.ndarray, b: np.ndarray) -> np.ndarray:
    ab = b - a
    t = np.clip(((points - a) @ ab) / (ab @ ab), 0.0, 1.0)
    return np.linalg.norm(points - (a + t[:, None] * ab), axis=1)


def skinning_weights(vertices, joints, tips, tags, faces, power=6.0, diffusion_steps=4) -> np.ndarray:
    """(V, 16) smooth, normalised skinning weights (see module docstring, step 4)."""
    bones: dict[int, list[tuple[np.ndarray, np.ndarray]]] = {
        0: [(joints[0], joints[FINGER_CHAINS[f][0]]) for f in FINGERS4]
        + [(joints[0], joints[0] + np.array([0.012, 0.0, 0.0]))]
    }
    for finger in FINGER_ORDER:
        chain = FINGER_CHAINS[finger]
        ends = [joints[chain[1]], joints[chain[2]], tips[FINGER_ORDER.index(finger)]]
        for j, end in zip(chain, ends):
            bones[j] = [(joints[j], end)]
    mcps = [FINGER_CHAINS[f][0] for f in FINGERS4]
    candidates = {0: [0, 13] + mcps}
    for i, finger in enumerate(FINGER_ORDER):
        candidates[1 + i] = [0] + list(FINGER_CHAINS[finger])
    V = len(vertices)
    w = np.zeros((V, 16))
    for tag, joint_list in candidates.items():
        sel = tags == tag
        for j in joint_list:
            d = np.min([_segment_distance(vertices[sel], a, b) for a, b in bones[j]], axis=0)
            w[sel, j] = np.maximum(d, 1e-4) ** -power
    w /= w.sum(axis=1, keepdims=True)
    adjacency = _vertex_adjacency(faces, V)
    degree = np.asarray(adjacency.sum(axis=1)).ravel()
    for _ in range(diffusion_steps):
        w = 0.5 * w + 0.5 * (adjacency @ w) / degree[:, None]
    w[w < 5e-4] = 0.0
    return w / w.sum(axis=1, keepdims=True)


def _vertex_adjacency(faces: np.ndarray, num_vertices: int) -> sp.csr_matrix:
    e = np.concatenate([faces[:, [0, 1]], faces[:, [1, 2]], faces[:, [2, 0]]])
    e = np.unique(np.sort(np.concatenate([e, e[:, ::-1]]), axis=1), axis=0)
    rows = np.concatenate([e[:, 0], e[:, 1]])
    cols = np.concatenate([e[:, 1], e[:, 0]])
    return sp.csr_matrix((np.ones(rows.size), (rows, cols)), shape=(num_vertices, num_vertices))


def joint_regressor(vertices, vertex_dirs, joints, joint_dirs) -> tuple[np.ndarray, float]:
    """Dense (16, V) regressor reproducing the joints and their shape derivatives exactly.

    Per joint, the minimum-norm affine weights on its nearest vertices that satisfy
    `w @ (vertices + dirs_k) = joints + joint_dirs_k` for the template and all ten
    directions; the neighbourhood doubles from 64 vertices until the solve is exact
    and no weight exceeds 1 in magnitude. Returns the regressor and the worst residual (m).
    """
    V = len(vertices)
    R = np.zeros((16, V))
    worst = 0.0
    for j in range(16):
        order = np.argsort(np.linalg.norm(vertices - joints[j], axis=1))
        neighbours = 64
        while True:
            near = order[:neighbours]
            blocks = [vertices[near].T] + [vertex_dirs[near, :, k].T for k in range(vertex_dirs.shape[-1])]
            A = np.concatenate(blocks + [np.ones((1, neighbours))])
            b = np.concatenate([joints[j]] + [joint_dirs[j, :, k] for k in range(joint_dirs.shape[-1])] + [np.ones(1)])
            w, *_ = np.linalg.lstsq(A, b, rcond=None)
            residual = float(np.abs(A @ w - b).max())
            if (residual < 1e-9 and np.abs(w).max() <= 1.0) or neighbours >= V:
                break
            neighbours = min(2 * neighbours, V)
        worst = max(worst, residual)
        R[j, near] = w
    return R, worst


def pose_blend_shapes(vertices, weights, joints, strength=0.3) -> np.ndarray:
    """(V, 3, 135) corrective offsets linear in MANO's pose features vec(R_j - I)."""
    posedirs = np.zeros((len(vertices), 3, 135))
    for j in range(1, 16):
        p = MANO_PARENTS[j]
        blend = np.clip(4.0 * weights[:, j] * weights[:, p], 0.0, 1.0)
        axis = _unit(joints[j] - joints[p])
        rel = vertices - joints[j]
        radial = rel - (rel @ axis)[:, None] * axis
        # offset = strength * (1 - cos t) * blend * radial, and 1 - cos t = -(tr(R - I)) / 2
        for diag in (0, 4, 8):
            posedirs[:, :, 9 * (j - 1) + diag] = -0.5 * strength * blend[:, None] * radial
    return posedirs


ARCHETYPES = {
    # per finger (MCP, PIP, DIP) flexion in degrees; thumb (CMC flex, CMC abd, CMC twist, MCP flex, IP flex).
    # The grasps' thumb angles were solved on the built-in hand for each grasp's contact (tested in
    # test_mano): fist and point lay the thumb tip across the curled fingers' middle phalanges, pinch
    # and tripod bring it to the index tip (tripod: between the index and middle tips), and the power
    # grasp wraps it round the held object opposite the index's middle phalanx.
    "flat": ({f: (0, 0, 0) for f in FINGERS4}, (0, 0, 0, 0, 0), 0.0),
    "spread": ({f: (-5, 0, 0) for f in FINGERS4}, (-10, 30, 0, 0, 0), 12.0),
    "relaxed": ({"index": (20, 30, 15), "middle": (25, 35, 18), "ring": (28, 38, 20), "pinky": (30, 40, 22)}, (10, 15, 10, 15, 15), 3.0),
    "fist": ({f: (85, 100, 65) for f in FINGERS4}, (0, 5, -30, 70, 40), -3.0),
    "power_grasp": ({f: (55, 60, 30) for f in FINGERS4}, (35, -15, 10, 0, 0), 0.0),
    "pinch": ({"index": (45, 55, 20), "middle": (40, 60, 30), "ring": (45, 65, 35), "pinky": (50, 70, 40)}, (40, -10, 0, 0, 0), 0.0),
    "tripod": ({"index": (40, 45, 20), "middle": (40, 45, 20), "ring": (60, 80, 40), "pinky": (70, 85, 45)}, (40, -20, 0, 0, 0), 0.0),
    "point": ({"index": (0, 5, 0), "middle": (85, 100, 60), "ring": (85, 100, 60), "pinky": (85, 100, 60)}, (15, 0, -30, 50, 60), 0.0),
    "thumb_out": ({f: (10, 10, 5) for f in FINGERS4}, (-15, 40, -10, 0, 0), 5.0),
}  # fmt: skip


def archetype_angles(name: str) -> np.ndarray:
    """(15, 3) anatomical (flexion, abduction, twist) angles in radians of an archetype."""
    fingers, thumb, spread = ARCHETYPES[name]
    angles = np.zeros((15, 3))
    spread_sign = {"index": 1.0, "middle": 0.0, "ring": -1.0, "pinky": -2.0}
    for f in FINGERS4:
        chain = FINGER_CHAINS[f]
        for level, j in enumerate(chain):
            angles[j - 1, 0] = fingers[f][level]
        angles[chain[0] - 1, 1] = spread * spread_sign[f] * 0.5
    cmc, mcp, ip = FINGER_CHAINS["thumb"]
    angles[cmc - 1] = thumb[0], thumb[1], thumb[2]
    angles[mcp - 1, 0] = thumb[3]
    angles[ip - 1, 0] = thumb[4]
    return np.deg2rad(angles)


def natural_pose_angles(num: int, seed: int = 0) -> np.ndarray:
    """(num, 15, 3) anatomical angles from the natural-pose distribution (step 6)."""
    from .anatomy import JOINT_LIMITS

    rng = np.random.default_rng(seed)
    names = list(ARCHETYPES)
    table = np.stack([archetype_angles(n) for n in names])
    a = rng.integers(len(names), size=num)
    b = rng.integers(len(names), size=num)
    t = rng.uniform(size=(num, 1, 1))
    angles = (1 - t) * table[a] + t * table[b]
    noise_std = np.deg2rad(np.array([10.0, 5.0, 3.0]))
    noise = rng.normal(size=(num, 15, 3)) * noise_std
    for f in FINGERS4:  # PIP and DIP flex together (tendon coupling)
        _, pip, dip = FINGER_CHAINS[f]
        noise[:, dip - 1, 0] = 0.6 * noise[:, pip - 1, 0] + 0.8 * noise[:, dip - 1, 0]
    angles = angles + noise
    return np.clip(angles, JOINT_LIMITS[None, :, :, 0], JOINT_LIMITS[None, :, :, 1])


def pose_pca(hand_poses: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Mean (45,) and components (45, 45): rows are principal directions times their std."""
    x = hand_poses.reshape(len(hand_poses), 45)
    mean = x.mean(axis=0)
    _, s, vt = np.linalg.svd(x - mean, full_matrices=False)
    vt *= np.sign(vt[np.arange(45), np.argmax(np.abs(vt), axis=1)])[:, None]  # deterministic signs
    std = s / math.sqrt(len(x) - 1)
    return mean, vt * std[:, None]


# ----------------------------------------------------------------------------- assembly


def build_mesh(design: HandDesign, cage: Cage, subdivision: sp.csr_matrix) -> np.ndarray:
    return subdivision @ cage_positions(design, cage)


def _fit_tip_caps(design: HandDesign, cage: Cage, subdivision, apex) -> HandDesign:
    """Move the cap rings so the apex vertices land on the designed fingertips."""
    for _ in range(8):
        verts = build_mesh(design, cage, subdivision)
        joints, tips = skeleton(design)
        offsets = design.tip_cap_offset.copy()
        for i, finger in enumerate(FINGER_ORDER):
            along = _unit(tips[i] - joints[FINGER_CHAINS[finger][2]])
            offsets[i] += float(np.dot(tips[i] - verts[apex[i]], along))
        design = dataclasses.replace(design, tip_cap_offset=offsets)
    return design


def generate() -> dict[str, np.ndarray]:
    """All arrays of the built-in right hand, in MANO-pickle names (float64)."""
    from .anatomy import anatomical_frames

    cage = cage_topology()
    s1, quads1 = catmull_clark(cage.quads, len(cage.tags))
    s2, quads2 = catmull_clark(quads1, s1.shape[0])
    subdivision = (s2 @ s1).tocsr()
    tag_weights = subdivision @ np.eye(6)[cage.tags]
    tags = np.argmax(tag_weights, axis=1)

    design0 = HandDesign()
    verts0 = build_mesh(design0, cage, subdivision)
    _, tips0 = skeleton(design0)
    apex = []
    for i, finger in enumerate(FINGER_ORDER):
        own = np.flatnonzero(tags == 1 + i)
        apex.append(own[np.argmin(np.linalg.norm(verts0[own] - tips0[i], axis=1))])
    design = _fit_tip_caps(design0, cage, subdivision, apex)

    verts = build_mesh(design, cage, subdivision)
    joints, tips = skeleton(design)
    vertex_dirs = np.zeros(verts.shape + (NUM_BETAS,))
    joint_dirs = np.zeros(joints.shape + (NUM_BETAS,))
    for k in range(NUM_BETAS):
        plus, minus = perturb(design, k, 1.0), perturb(design, k, -1.0)
        vertex_dirs[..., k] = 0.5 * (build_mesh(plus, cage, subdivision) - build_mesh(minus, cage, subdivision))
        joint_dirs[..., k] = 0.5 * (skeleton(plus)[0] - skeleton(minus)[0])

    faces = triangulate(quads2, verts)
    weights = skinning_weights(verts, joints, tips, tags, faces)
    J_regressor, regression_residual = joint_regressor(verts, vertex_dirs, joints, joint_dirs)
    posedirs = pose_blend_shapes(verts, weights, joints)

    # renumber vertices: tip apices to smplx ids, their neighbours to manopth ids
    adjacency = _vertex_adjacency(faces, len(verts))
    wanted = {}
    for i, finger in enumerate(FINGER_ORDER):
        wanted[FINGERTIP_IDS_SMPLX[i]] = apex[i]
        neighbours = [v for v in adjacency[apex[i]].indices if v not in wanted.values()]
        neighbours.sort(key=lambda v: np.linalg.norm(verts[v] - verts[apex[i]]))
        extra_ids = sorted({FINGERTIP_IDS_MANOPTH["right"][i], FINGERTIP_IDS_MANOPTH["left"][i]})
        for target, v in zip(extra_ids, neighbours):
            wanted[target] = v
    new_of_old = np.full(len(verts), -1)
    for target, old in wanted.items():
        new_of_old[old] = target
    free = iter(sorted(set(range(len(verts))) - set(wanted)))
    for old in range(len(verts)):
        if new_of_old[old] < 0:
            new_of_old[old] = next(free)
    old_of_new = np.argsort(new_of_old)

    with jax.enable_x64(True):
        frames = np.asarray(anatomical_frames(jnp.asarray(joints), jnp.asarray(tips), True))
    # rotation vector in model axes: sum_i frames[j, :, i] * angle_i
    hand_mean, hand_components = pose_pca(np.einsum("jai,nji->nja", frames, natural_pose_angles(20000)))
    kintree = np.array([[4294967295] + list(MANO_PARENTS[1:]), list(range(16))], dtype=np.int64)
    return {
        "v_template": verts[old_of_new] + WRIST_POSITION,
        "shapedirs": vertex_dirs[old_of_new],
        "posedirs": posedirs[old_of_new],
        "J_regressor": J_regressor[:, old_of_new],
        "weights": weights[old_of_new],
        "f": new_of_old[faces],
        "kintree_table": kintree,
        "hands_components": hand_components,
        "hands_mean": hand_mean,
        "fingertip_ids": np.asarray(FINGERTIP_IDS_SMPLX),
        "regression_residual": np.asarray(regression_residual),
    }


def write(path: pathlib.Path = ASSET_PATH) -> pathlib.Path:
    arrays = generate()
    stored = {k: (v.astype(np.float32) if v.dtype == np.float64 else v) for k, v in arrays.items()}
    stored["generator_version"] = np.asarray(GENERATOR_VERSION)
    with atomic_output(path) as tmp:
        np.savez_compressed(tmp, **stored)
    return path


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", type=pathlib.Path, default=ASSET_PATH)
    args = parser.parse_args()
    path = write(args.out)
    print(f"wrote {path} ({path.stat().st_size / 1024:.0f} KiB)")


if __name__ == "__main__":
    main()
