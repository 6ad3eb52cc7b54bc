"""A small z-buffer renderer for synthetic clips (numpy + OpenCV, CPU).

Triangles are rasterised with exact pixel-centre coverage tests (edge functions),
vectorised over triangles grouped by bounding-box size, and resolved per pixel by depth
(a true z-buffer: the nearest fragment wins, perspective-correct depth). The background
is a textured plane 1.5 m in front of the first frame's rig, seen through every camera
(pinhole or fisheye) by ray casting, so head motion moves it consistently (the flow
token's camera motion). Grayscale rigs (HOT3D) get the luminance.

Appearance is made for real detectors to read (a detector trained on photographs must
find the rendered hands, `benchmarks/detect.py`):

- *Skin* (`Mesh.material == "skin"`): albedos of measured skin (`SKIN_TONES_LAB`), wrap
  diffuse lighting with a red-shifted terminator (light scattered under the skin), a
  broad Blinn-Phong sheen (skin's oily surface layer: 0.18 of the key light at its peak,
  exponent 10), low-frequency mottling. On the hand (`Mesh.rest` given) the details are
  painted procedurally in the built-in hand's rest pose, so they follow the skin at any
  pose and resolution (`hand_skin_albedo`): a fine grain (pores), nails with a pale free
  edge and a glossy finish, palmar flexion creases at the finger joints and the palm's
  main lines, knuckle wrinkles, and palms paler than the back of the hand (strongly so
  for dark skin).
- *Lighting*: a key light of random direction and colour temperature, a sky / ground
  hemisphere fill, and screen-space ambient occlusion from the depth buffer, which
  darkens the gaps between fingers and where a finger passes in front of the palm.
- *Camera*: surfaces are lit in linear light and encoded with the display gamma
  (`DISPLAY_GAMMA`: albedos are display values, so an albedo a reflects a ** gamma, and
  the exposed radiance r is written as r ** (1 / gamma), as a camera's tone curve does:
  shading falls off softly instead of sinking half-lit skin into black); exposure
  metered on the scene (centre-weighted towards the hand); slight optical blur
  (anti-aliasing). The background texture is a display image seen by the same camera:
  exposure scales it by exposure ** (1 / gamma), as it scales the encoded hand.
"""

import dataclasses
import functools

import cv2
import jax.numpy as jnp
import numpy as np

from .. import mano
from ..cameras import AbstractCamera
from ..mano.constants import FINGER_CHAINS, FINGER_ORDER

SKIN_TONES_LAB = np.array(
    [[72.0, 15.0, 16.0], [65.71, 18.13, 17.81], [56.0, 16.5, 16.5], [47.0, 15.0, 15.3], [37.99, 13.56, 14.06], [28.0, 11.0, 11.0]],
    np.float32,
)
"""CIELAB skin albedos from very light to very dark: the ColorChecker's two skin patches,
whose reflectances were chosen to match real skin ("light skin" L* 65.71 and "dark skin"
37.99, BabelColor's average of published measurements), and tones between and beyond
them of the same hue and chroma (a*, b* 11 to 18: skin is a pale red-orange)."""
SKIN_TONES = cv2.cvtColor(SKIN_TONES_LAB[None], cv2.COLOR_Lab2RGB)[0]
"""`SKIN_TONES_LAB` as sRGB albedos in [0, 1] (sampled and jittered per clip)."""
BACKGROUND_DEPTH_M = 1.5
DISPLAY_GAMMA = 2.2
"""Display encoding: linear radiance r is written as r ** (1 / DISPLAY_GAMMA) (module docstring, *Camera*)."""
MATERIALS = ("matte", "skin")


@dataclasses.dataclass(frozen=True)
class Mesh:
    """One surface for `render_view`."""

    vertices: np.ndarray
    """(V, 3) in the rendering camera's frame, metres."""
    faces: np.ndarray
    """(F, 3) vertex ids, wound outwards."""
    albedo: np.ndarray
    """(3,) base RGB albedo in [0, 1]."""
    material: str = "matte"
    """"matte" (Lambert) or "skin" (see the module docstring)."""
    rest: np.ndarray | None = None
    """(V, 3) the same vertices on the built-in right hand at rest (its model frame; a
    left hand passes the right hand's rest vertices, the ids correspond): skin details
    are painted there. None for other surfaces."""

    def __post_init__(self):
        if self.material not in MATERIALS:
            raise ValueError(f"unknown material {self.material!r}; expected one of {MATERIALS}")


@dataclasses.dataclass(frozen=True)
class Scene:
    """Per-clip appearance: albedos, lighting and the background texture."""

    skin: np.ndarray  # (3,) RGB albedo in [0, 1]
    object_colour: np.ndarray  # (3,)
    sleeve_colour: np.ndarray | None  # (3,) a sleeve over the forearm, or None (bare forearm)
    light_dir: np.ndarray  # (3,) unit, camera frame, pointing towards the light
    light_colour: np.ndarray  # (3,) key light RGB
    ambient: float  # hemisphere fill strength
    exposure: float
    texture: np.ndarray  # (Ht, Wt, 3) float32 in [0, 1]
    texture_focal: float
    grayscale: bool


def _luminance(rgb: np.ndarray) -> np.ndarray:
    return np.asarray(rgb @ np.array([0.299, 0.587, 0.114], np.float32))


def sample_scene(rng: np.random.Generator, grayscale: bool = False, texture_size: int = 1024) -> Scene:
    """A random scene: skin tone, light, a textured background (low-frequency colour
    fields, rectangles and strokes like shelves, tables and clutter, and fine grain, at a
    random saturation: indoor scenes are mostly muted, so the texture keeps only 8 to 40 %
    of its random colours' distance from grey), metered exposure."""
    skin = SKIN_TONES[rng.integers(len(SKIN_TONES))] * rng.uniform(0.92, 1.08, size=3)
    light = np.array([rng.uniform(-0.6, 0.6), rng.uniform(-1.0, -0.3), rng.uniform(-1.0, -0.4)])
    warmth = rng.uniform(-1.0, 1.0)  # cool daylight .. warm tungsten
    light_colour = np.array([1.0 + 0.12 * warmth, 1.0, 1.0 - 0.18 * warmth])
    small = rng.uniform(0.15, 0.85, size=(6, 6, 3)).astype(np.float32)
    texture = cv2.resize(small, (texture_size, texture_size), interpolation=cv2.INTER_CUBIC)
    for _ in range(rng.integers(25, 60)):
        colour = tuple(float(c) for c in rng.uniform(0.05, 0.95, size=3))
        p0 = tuple(int(v) for v in rng.integers(0, texture_size, size=2))
        if rng.uniform() < 0.6:
            p1 = tuple(int(v) for v in np.asarray(p0) + rng.integers(20, 260, size=2))
            cv2.rectangle(texture, p0, p1, colour, -1 if rng.uniform() < 0.7 else int(rng.integers(2, 8)))
        else:
            p1 = tuple(int(v) for v in rng.integers(0, texture_size, size=2))
            cv2.line(texture, p0, p1, colour, int(rng.integers(1, 10)))
    texture += rng.normal(scale=0.03, size=texture.shape).astype(np.float32)
    grey = _luminance(texture)[..., None]
    texture = grey + rng.uniform(0.08, 0.4) * (texture - grey)
    texture = cv2.GaussianBlur(np.clip(texture, 0, 1), (3, 3), 0.8)
    skin = np.clip(skin, 0, 1)
    # centre-weighted metering: the hand is a good part of what the camera exposes for
    metered = 0.6 * float(_luminance(texture).mean()) + 0.4 * 0.8 * float(_luminance(skin))
    exposure = float(np.clip(0.45 / metered * rng.uniform(0.85, 1.15), 0.7, 1.8))
    sleeve = rng.uniform(0.05, 0.8, size=3) if rng.uniform() < 0.5 else None
    return Scene(
        skin=skin,
        object_colour=rng.uniform(0.1, 0.9, size=3),
        sleeve_colour=sleeve,
        light_dir=light / np.linalg.norm(light),
        light_colour=light_colour,
        ambient=float(rng.uniform(0.3, 0.5)),
        exposure=exposure,
        texture=texture,
        texture_focal=texture_size / 2.4,  # the texture spans about 135 degrees from the rig
        grayscale=grayscale,
    )


# ----------------------------------------------------------------------------- rasterisation


def rasterize(uv: np.ndarray, depth: np.ndarray, faces: np.ndarray, width: int, height: int):
    """Z-buffer rasterisation of one triangle mesh.

    Args:
        uv: (V, 2) projected vertices (pixels, centres at integers).
        depth: (V,) view depth of the vertices (metres); triangles with a vertex at
            depth <= 1 cm are skipped.
        faces: (F, 3) vertex ids.
    Returns:
        face (H, W) int32 (-1 where empty), bary (H, W, 3) screen-space barycentrics,
        zbuf (H, W) float32 (inf where empty).
    """
    face_out = np.full(height * width, -1, np.int32)
    bary_out = np.zeros((height * width, 3), np.float32)
    zbuf = np.full(height * width, np.inf, np.float32)
    p = uv[faces]  # (F, 3, 2)
    z = depth[faces]
    ok = np.all(z > 0.01, axis=1) & np.all(np.isfinite(p), axis=(1, 2)) & np.all(np.abs(p) < 1e6, axis=(1, 2))
    p = np.where(ok[:, None, None], p, 0.0)
    lo = np.ceil(p.min(axis=1)).astype(np.int64)
    hi = np.floor(p.max(axis=1)).astype(np.int64)
    lo = np.maximum(lo, 0)
    hi = np.minimum(hi, [width - 1, height - 1])
    ok &= np.all(hi >= lo, axis=1)
    area = (p[:, 1, 0] - p[:, 0, 0]) * (p[:, 2, 1] - p[:, 0, 1]) - (p[:, 1, 1] - p[:, 0, 1]) * (p[:, 2, 0] - p[:, 0, 0])
    ok &= np.abs(area) > 1e-9
    # bucket triangles by the power-of-two width and height of their pixel box (long thin
    # triangles are tested over their box, not over a square around it)
    bucket = np.maximum(np.ceil(np.log2(np.maximum(hi - lo + 1, 1))), 1).astype(np.int64)  # (F, 2)
    pixel_ids, depths, face_ids, barys = [], [], [], []
    for bx, by in np.unique(bucket[ok], axis=0):
        sel = np.flatnonzero(ok & (bucket[:, 0] == bx) & (bucket[:, 1] == by))
        oy, ox = np.mgrid[0 : 2**by, 0 : 2**bx]
        px = lo[sel, 0:1] + ox.reshape(1, -1)
        py = lo[sel, 1:2] + oy.reshape(1, -1)
        inside = (px <= hi[sel, 0:1]) & (py <= hi[sel, 1:2])
        a, b, c = p[sel, 0][:, None], p[sel, 1][:, None], p[sel, 2][:, None]  # (n, 1, 2)
        w0 = (b[..., 0] - px) * (c[..., 1] - py) - (b[..., 1] - py) * (c[..., 0] - px)
        w1 = (c[..., 0] - px) * (a[..., 1] - py) - (c[..., 1] - py) * (a[..., 0] - px)
        w2 = (a[..., 0] - px) * (b[..., 1] - py) - (a[..., 1] - py) * (b[..., 0] - px)
        s = area[sel][:, None]
        l0, l1, l2 = w0 / s, w1 / s, w2 / s
        inside &= (l0 >= 0) & (l1 >= 0) & (l2 >= 0)
        n, k = np.nonzero(inside)
        if n.size == 0:
            continue
        lam = np.stack([l0[n, k], l1[n, k], l2[n, k]], axis=1)
        inv_z = (lam / z[sel[n]]).sum(axis=1)  # 1/z is affine in screen space: perspective-correct depth
        pixel_ids.append(py[n, k] * width + px[n, k])
        depths.append(1.0 / inv_z)
        face_ids.append(sel[n])
        barys.append(lam)
    if not pixel_ids:
        return face_out.reshape(height, width), bary_out.reshape(height, width, 3), zbuf.reshape(height, width)
    pix = np.concatenate(pixel_ids)
    dep = np.concatenate(depths)
    order = np.lexsort((dep, pix))  # by pixel, nearest first
    pix, first = np.unique(pix[order], return_index=True)
    win = order[first]
    face_out[pix] = np.concatenate(face_ids)[win]
    bary_out[pix] = np.concatenate(barys)[win]
    zbuf[pix] = dep[win]
    return face_out.reshape(height, width), bary_out.reshape(height, width, 3), zbuf.reshape(height, width)


def vertex_normals(vertices: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """Area-weighted vertex normals (unit), for outward-wound faces."""
    tri = vertices[faces]
    fn = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    n = np.zeros_like(vertices)
    for i in range(3):
        np.add.at(n, faces[:, i], fn)
    return n / np.maximum(np.linalg.norm(n, axis=1, keepdims=True), 1e-12)


def _pixel_rays(camera: AbstractCamera) -> np.ndarray:
    """(H, W, 3) camera-frame rays (z = 1) of every pixel centre."""
    v, u = np.mgrid[0 : camera.height, 0 : camera.width].astype(np.float32)
    return np.asarray(camera.unproject(jnp.asarray(np.stack([u, v], -1))), np.float32)


def render_background(scene: Scene, camera: AbstractCamera, T_world_cam: np.ndarray, rays: np.ndarray | None = None) -> np.ndarray:
    """(H, W, 3) the textured background plane z_world = 1.5 m seen by a camera."""
    rays = _pixel_rays(camera) if rays is None else rays
    has_ray = np.all(np.isfinite(rays), axis=-1)  # fisheye corners beyond the model's domain have none
    rays = np.where(has_ray[..., None], rays, 0.0)
    d = rays @ T_world_cam[:3, :3].T.astype(np.float32)
    o = T_world_cam[:3, 3].astype(np.float32)
    t = (BACKGROUND_DEPTH_M - o[2]) / np.where(np.abs(d[..., 2]) > 1e-6, d[..., 2], 1e-6)
    hit = o + t[..., None] * d
    size = scene.texture.shape[0]
    f = scene.texture_focal
    seen = has_ray & (t > 0) & np.all(np.abs(hit) < 1e3, axis=-1)
    map_x = np.where(seen, f * hit[..., 0] / BACKGROUND_DEPTH_M + (size - 1) / 2, -1.0).astype(np.float32)
    map_y = np.where(seen, f * hit[..., 1] / BACKGROUND_DEPTH_M + (size - 1) / 2, -1.0).astype(np.float32)
    image = cv2.remap(scene.texture, map_x, map_y, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REFLECT)
    return np.where(seen[..., None], image, 0.0)


# ----------------------------------------------------------------------------- skin


def _smoothstep(edge0, edge1, x):
    t = np.clip((x - edge0) / (edge1 - edge0), 0.0, 1.0)
    return t * t * (3.0 - 2.0 * t)


@functools.cache
def _hand_rest() -> dict[str, np.ndarray]:
    """The built-in right hand at rest: vertices, normals and its bones with their dorsal
    directions (the anatomical frames), where `hand_skin_albedo` paints the details."""
    model = mano.load_builtin("right")
    verts = np.asarray(model.v_template, np.float64)
    joints = np.asarray(model.joint_template, np.float64)
    tips = verts[np.asarray(model.fingertip_ids)]
    frames = np.asarray(mano.anatomical_frames(jnp.asarray(joints), jnp.asarray(tips), True), np.float64)
    starts, ends, ups, finger, level = [], [], [], [], []
    for f, name in enumerate(FINGER_ORDER):
        chain = FINGER_CHAINS[name]
        if name != "thumb":  # the metacarpal, inside the palm
            starts.append(joints[0]), ends.append(joints[chain[0]]), ups.append(frames[chain[0] - 1][:, 1])
            finger.append(f), level.append(-1)
        for k, j in enumerate(chain):
            starts.append(joints[j]), ends.append(joints[chain[k + 1]] if k < 2 else tips[f]), ups.append(frames[j - 1][:, 1])
            finger.append(f), level.append(k)
    starts, ends = np.asarray(starts), np.asarray(ends)
    # distal phalanx radius per finger (nail width), from the rest surface around its middle
    radius = np.zeros(5)
    for f in range(5):
        b = np.flatnonzero((np.asarray(finger) == f) & (np.asarray(level) == 2))[0]
        axis = ends[b] - starts[b]
        s = (verts - starts[b]) @ axis / (axis @ axis)
        ring = (s > 0.3) & (s < 0.6)
        radial = verts[ring] - starts[b] - s[ring, None] * axis
        near = np.linalg.norm(radial, axis=1)
        radius[f] = np.median(near[near < 0.015])
    return dict(
        vertices=verts, normals=vertex_normals(verts, np.asarray(model.faces)), joints=joints, tips=tips,
        starts=starts, ends=ends, ups=np.asarray(ups), finger=np.asarray(finger), level=np.asarray(level), radius=radius,
    )  # fmt: skip


def hand_rest_vertices() -> np.ndarray:
    """(V, 3) rest vertices of the built-in right hand (`Mesh.rest` of either hand)."""
    return _hand_rest()["vertices"]


# The palm's main lines in palm coordinates (a: wrist -> middle MCP in units of that
# length, b: across the palm towards the index in units of the index-pinky MCP width).
_PALM_LINES = (
    np.array([[0.80, -0.66], [0.83, -0.30], [0.86, 0.0], [0.93, 0.22]]),  # distal transverse ("heart")
    np.array([[0.80, 0.60], [0.70, 0.25], [0.60, -0.10], [0.52, -0.42]]),  # proximal transverse ("head")
    np.array([[0.78, 0.62], [0.58, 0.42], [0.36, 0.36], [0.12, 0.42]]),  # thenar ("life")
    np.array([[0.03, -0.45], [0.02, 0.0], [0.04, 0.45]]),  # wrist
)


def _polyline_distance(points: np.ndarray, line: np.ndarray) -> np.ndarray:
    best = np.full(len(points), np.inf)
    for a, b in zip(line[:-1], line[1:]):
        ab = b - a
        t = np.clip(((points - a) @ ab) / (ab @ ab), 0.0, 1.0)
        best = np.minimum(best, np.linalg.norm(points - (a + t[:, None] * ab), axis=1))
    return best


def _mottle(points: np.ndarray) -> np.ndarray:
    """(N,) smooth multiplicative skin variation about 1 (wavelengths 8-30 mm)."""
    rng = np.random.default_rng(7)
    directions = rng.normal(size=(8, 3))
    directions /= np.linalg.norm(directions, axis=1, keepdims=True)
    k = 2 * np.pi / rng.uniform(0.008, 0.03, size=8)
    phase = rng.uniform(0, 2 * np.pi, size=8)
    return 1.0 + 0.05 * np.cos(points @ (directions * k[:, None]).T + phase).mean(axis=1) * np.sqrt(2.0)


def _skin_grain(points: np.ndarray, cell_m: float = 0.0015, amplitude: float = 0.08) -> np.ndarray:
    """(N,) fine multiplicative skin grain about 1 (pores, fine lines) at `points` (N, 3),
    metres: an independent value in [1 - amplitude / 2, 1 + amplitude / 2) for each `cell_m`
    cube (hashed lattice cells, so it is fixed to the surface when `points` are rest
    coordinates; every hand has the same pattern)."""
    cell = np.floor(points / cell_m).astype(np.int64)
    hashed = (cell[:, 0] * 73856093) ^ (cell[:, 1] * 19349663) ^ (cell[:, 2] * 83492791)
    return 1.0 + amplitude * (hashed % 1000 / 1000.0 - 0.5)


def hand_skin_albedo(rest: np.ndarray, rest_normals: np.ndarray, skin: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Skin details painted on the built-in right hand at rest (see the module docstring).

    Args:
        rest: (N, 3) surface points in the rest hand's model frame (metres).
        rest_normals: (N, 3) their unit rest normals.
        skin: (3,) the back-of-hand albedo.
    Returns:
        albedo (N, 3) in [0, 1] and gloss (N,) (0 for skin, 1 on nails).
    """
    h = _hand_rest()
    axis = h["ends"] - h["starts"]  # (B, 3)
    rel = rest[:, None, :] - h["starts"][None]  # (N, B, 3)
    s = np.einsum("nbk,bk->nb", rel, axis) / np.einsum("bk,bk->b", axis, axis)
    closest = h["starts"][None] + np.clip(s, 0.0, 1.0)[..., None] * axis[None]
    bone = np.argmin(np.linalg.norm(rest[:, None, :] - closest, axis=-1), axis=1)
    take = lambda x: x[np.arange(len(rest)), bone]  # noqa: E731
    s_b, finger, level = take(s), h["finger"][bone], h["level"][bone]
    d = axis[bone] / np.linalg.norm(axis[bone], axis=1, keepdims=True)
    up = h["ups"][bone]
    dorsal = np.einsum("nk,nk->n", rest_normals, up)
    lateral = np.einsum("nk,nk->n", take(rel), np.cross(up, d))
    palmar = _smoothstep(-0.1, -0.5, dorsal)

    darkness = float(np.clip(1.0 - _luminance(skin) / 0.8, 0.0, 1.0))
    palm_tone = skin + (np.array([0.86, 0.64, 0.55]) - skin) * (0.15 + 0.45 * darkness)
    albedo = skin[None] + palmar[:, None] * (palm_tone - skin)[None]
    albedo = albedo * (_mottle(rest) * _skin_grain(rest))[:, None]

    shade = np.ones(len(rest))
    joints, tips = h["joints"], h["tips"]
    for f, name in enumerate(FINGER_ORDER):
        chain = FINGER_CHAINS[name]
        on = finger == f
        # palmar flexion creases at the two distal joints and the base of the finger
        creases = [(joints[chain[1]], joints[chain[2]], 0.30), (joints[chain[2]], tips[f], 0.35)]
        if name != "thumb":
            creases.append((joints[chain[0]] + 0.3 * (joints[chain[1]] - joints[chain[0]]), joints[chain[1]], 0.30))
        for at, child, strength in creases:
            bone_dir = (child - at) / np.linalg.norm(child - at)
            along = (rest - at) @ bone_dir
            near = on & (np.linalg.norm(rest - at, axis=1) < 0.016)
            line = np.exp(-((along / 0.0006) ** 2)) + 0.6 * np.exp(-(((along - 0.0016) / 0.0005) ** 2))
            shade -= strength * near * palmar * line
        # knuckle wrinkles on the back of the two distal joints
        for j, strength in ((chain[1], 0.08), (chain[2], 0.05)):
            child = joints[chain[2]] if j == chain[1] else tips[f]
            bone_dir = (child - joints[j]) / np.linalg.norm(child - joints[j])
            along = (rest - joints[j]) @ bone_dir
            near = on & (np.linalg.norm(rest - joints[j], axis=1) < 0.014)
            lines = sum(np.exp(-(((along - o) / 0.00035) ** 2)) for o in (-0.0013, 0.0, 0.0013))
            shade -= strength * near * _smoothstep(0.3, 0.6, dorsal) * lines
    # the palm's main lines
    wrist, middle = joints[0], joints[FINGER_CHAINS["middle"][0]]
    index, pinky = joints[FINGER_CHAINS["index"][0]], joints[FINGER_CHAINS["pinky"][0]]
    e1 = middle - wrist
    length = np.linalg.norm(e1)
    e1 /= length
    e2 = (index - pinky) - ((index - pinky) @ e1) * e1
    width = np.linalg.norm(e2)
    e2 /= width
    metric = np.stack([(rest - wrist) @ e1, (rest - wrist) @ e2], axis=1)  # palm coordinates in metres
    in_palm = (level == -1) | ((finger == 0) & (level == 0))
    for line in _PALM_LINES:
        dist = _polyline_distance(metric, line * np.array([length, width]))
        shade -= 0.32 * in_palm * palmar * np.exp(-((dist / 0.0006) ** 2))
    albedo = albedo * np.clip(shade, 0.4, 1.0)[:, None]

    # nails on the back of the distal phalanges, with a pale free edge and a darker fold round them
    width_nail = 0.8 * h["radius"][finger]
    nail = (
        (level == 2)
        * _smoothstep(0.36, 0.44, s_b)
        * (1.0 - _smoothstep(0.98, 1.06, s_b))
        * (1.0 - _smoothstep(0.75 * width_nail, width_nail, np.abs(lateral)))
        * _smoothstep(0.2, 0.45, dorsal)
    )
    nail_colour = 0.35 * skin + 0.65 * np.array([0.93, 0.70, 0.70])
    free_edge = _smoothstep(0.86, 0.93, s_b)[:, None]
    nail_colour = nail_colour[None] * (1 - free_edge) + np.array([0.97, 0.93, 0.87])[None] * free_edge
    fold = 1.0 - 0.8 * nail * (1.0 - nail)  # the nail folds around its border
    albedo = (albedo * (1 - nail[:, None]) + nail_colour * nail[:, None]) * fold[:, None]
    return np.clip(albedo, 0.0, 1.0), nail


# ----------------------------------------------------------------------------- frames


def _pixels_per_metre_at_unit_depth(uv: np.ndarray, points: np.ndarray, faces: np.ndarray) -> float:
    """The image scale near a mesh (px per metre at 1 m), from its projected edges."""
    a, b = faces[:, 0], faces[:, 1]
    ok = (points[a, 2] > 0.01) & (points[b, 2] > 0.01)
    if not ok.any():
        return 1.0
    plane = points[:, :2] / np.maximum(points[:, 2:], 1e-3)
    ratio = np.linalg.norm(uv[a] - uv[b], axis=1)[ok] / np.maximum(np.linalg.norm(plane[a] - plane[b], axis=1)[ok], 1e-9)
    return float(np.median(ratio))


def ambient_occlusion(depth: np.ndarray, scale_px: float) -> np.ndarray:
    """(H, W) factor in [0.5, 1]: screen-space occlusion from the depth buffer. A surface
    pixel deeper than the mean depth of the surface around it (about a centimetre wide,
    `scale_px`) sits in a crevice or behind a nearer part and gets less ambient light."""
    out = np.ones(depth.shape, np.float32)
    rows, cols = np.nonzero(np.isfinite(depth))
    if rows.size == 0:
        return out
    sigma = float(np.clip(scale_px, 1.5, 16.0))
    margin = int(3 * sigma) + 1
    window = np.s_[max(rows.min() - margin, 0) : rows.max() + margin + 1, max(cols.min() - margin, 0) : cols.max() + margin + 1]
    mask = np.isfinite(depth[window]).astype(np.float32)
    d = np.where(mask > 0, depth[window], 0.0).astype(np.float32)
    local = cv2.GaussianBlur(d, (0, 0), sigma) / np.maximum(cv2.GaussianBlur(mask, (0, 0), sigma), 1e-6)
    occlusion = np.clip((d - local) / 0.012, 0.0, 1.0)
    out[window] = np.where(mask > 0, 1.0 - 0.5 * occlusion, 1.0)
    return out


def _shade(scene: Scene, n: np.ndarray, points: np.ndarray, albedo: np.ndarray, skin: np.ndarray, gloss: np.ndarray) -> np.ndarray:
    """(P, 3) linear radiance of surface pixels (`albedo` linear): hemisphere fill + key
    light, wrap diffuse with a red-shifted terminator on skin, Blinn-Phong sheen (skin) and
    gloss (nails)."""
    view = -points / np.maximum(np.linalg.norm(points, axis=1, keepdims=True), 1e-9)
    n = np.where((np.einsum("pk,pk->p", n, view) < 0)[:, None], -n, n)  # seen from inside: shade the side we see
    up = np.array([0.0, -1.0, 0.0])
    fill = scene.ambient * (0.75 + 0.25 * (n @ up))[:, None]
    ndl = (n @ scene.light_dir)[:, None]
    wrap = np.where(skin[:, None], np.array([0.45, 0.25, 0.2]), 0.0)
    diffuse = np.clip((ndl + wrap) / (1.0 + wrap), 0.0, None) * scene.light_colour
    half = scene.light_dir[None] + view
    half /= np.maximum(np.linalg.norm(half, axis=1, keepdims=True), 1e-9)
    ndh = np.clip(np.einsum("pk,pk->p", n, half), 0.0, 1.0)
    sheen = np.where(skin, 0.18 * ndh**10, 0.0) + 0.35 * gloss * ndh**60
    return albedo * (fill + (1.0 - scene.ambient) * diffuse) + sheen[:, None] * scene.light_colour


def render_view(
    scene: Scene,
    camera: AbstractCamera,
    T_world_cam: np.ndarray,
    meshes: list[Mesh],
    rays: np.ndarray | None = None,
) -> tuple[np.ndarray, np.ndarray]:
    """Render one view: uint8 image (H, W, 3) (or (H, W) for grayscale scenes) and the
    depth buffer (H, W) in metres (inf on the background).

    Args:
        meshes: the surfaces, in this camera's frame.
        rays: `_pixel_rays(camera)`, when rendering many frames of one camera.
    """
    image = render_background(scene, camera, T_world_cam, rays) * scene.exposure ** (1.0 / DISPLAY_GAMMA)
    W, H = camera.width, camera.height
    depth = np.full((H, W), np.inf, np.float32)
    hit = np.zeros((H, W), bool)
    if meshes:
        offsets = np.cumsum([0] + [len(m.vertices) for m in meshes])
        verts = np.concatenate([m.vertices for m in meshes])
        faces = np.concatenate([m.faces + o for m, o in zip(meshes, offsets)])
        owner = np.repeat(np.arange(len(meshes)), [len(m.faces) for m in meshes])
        normals = np.concatenate([vertex_normals(m.vertices, m.faces) for m in meshes])
        uv = np.asarray(camera.project(jnp.asarray(verts, jnp.result_type(float))), np.float64)
        face, bary, depth = rasterize(uv, verts[:, 2], faces, W, H)
        hit = face >= 0
    if hit.any():
        f_ids = face[hit]
        lam = bary[hit]
        corners = faces[f_ids]
        interpolate = lambda values, sel=slice(None), offset=0: np.einsum("pk,pkc->pc", lam[sel], values[corners[sel] - offset])  # noqa: E731
        n = interpolate(normals)
        n /= np.maximum(np.linalg.norm(n, axis=1, keepdims=True), 1e-9)
        points = interpolate(verts)
        mesh_of = owner[f_ids]
        albedo = np.stack([m.albedo for m in meshes])[mesh_of].astype(np.float64)
        skin = np.array([m.material == "skin" for m in meshes])[mesh_of]
        gloss = np.zeros(len(f_ids))
        for i, m in enumerate(meshes):
            here = mesh_of == i
            if not here.any():
                continue
            if m.rest is not None:
                rest = interpolate(m.rest, here, offsets[i])
                rn = interpolate(_hand_rest()["normals"], here, offsets[i])
                rn /= np.maximum(np.linalg.norm(rn, axis=1, keepdims=True), 1e-9)
                albedo[here], gloss[here] = hand_skin_albedo(rest, rn, m.albedo)
            elif m.material == "skin":
                albedo[here] *= _mottle(points[here])[:, None]
        ao = ambient_occlusion(depth, 0.01 * _pixels_per_metre_at_unit_depth(uv, verts, faces) / float(np.median(depth[hit])))
        radiance = _shade(scene, n, points, albedo**DISPLAY_GAMMA, skin, gloss) * ao[hit][:, None]
        image[hit] = (scene.exposure * radiance) ** (1.0 / DISPLAY_GAMMA)
    image = cv2.GaussianBlur(np.clip(image, 0.0, 1.0).astype(np.float32), (0, 0), 0.6)
    out = (image * 255.0 + 0.5).astype(np.uint8)
    if scene.grayscale:
        out = cv2.cvtColor(out, cv2.COLOR_RGB2GRAY)
    return out, depth
