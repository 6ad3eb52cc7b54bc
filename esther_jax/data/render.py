"""A small z-buffer renderer for synthetic clips (numpy + OpenCV, CPU).

Triangles are rasterised with exact pixel-centre coverage tests (edge functions),
vectorised over triangles grouped by bounding-box size, and resolved per pixel by depth
(a true z-buffer: the nearest fragment wins, perspective-correct depth). Shading is
Lambert with smooth vertex normals, an ambient term and one directional light per clip;
skin tones and lighting are sampled per clip. The background is a textured plane 1.5 m
in front of the first frame's rig, seen through every camera (pinhole or fisheye) by
ray casting, so head motion moves it consistently (the flow token's camera motion).
Grayscale rigs (HOT3D) get the luminance.
"""

import dataclasses

import cv2
import jax.numpy as jnp
import numpy as np

from ..cameras import AbstractCamera

SKIN_TONES = np.array(
    [[255, 224, 196], [241, 194, 161], [224, 172, 105], [198, 134, 66], [141, 85, 36], [92, 59, 38]], np.float32
) / 255.0
"""sRGB albedos from very light to very dark skin (sampled and jittered per clip)."""
BACKGROUND_DEPTH_M = 1.5


@dataclasses.dataclass(frozen=True)
class Scene:
    """Per-clip appearance: albedos, lighting and the background texture."""

    skin: np.ndarray  # (3,) RGB albedo in [0, 1]
    object_colour: np.ndarray  # (3,)
    light_dir: np.ndarray  # (3,) unit, camera frame, pointing towards the light
    ambient: float
    exposure: float
    texture: np.ndarray  # (Ht, Wt, 3) float32 in [0, 1]
    texture_focal: float
    grayscale: bool


def sample_scene(rng: np.random.Generator, grayscale: bool = False, texture_size: int = 1024) -> Scene:
    """A random scene: skin tone, light, a textured background (low-frequency colour
    fields, rectangles and strokes like shelves, tables and clutter, and fine grain)."""
    skin = SKIN_TONES[rng.integers(len(SKIN_TONES))] * rng.uniform(0.92, 1.08, size=3)
    light = np.array([rng.uniform(-0.6, 0.6), rng.uniform(-1.0, -0.3), rng.uniform(-1.0, -0.4)])
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
    texture = cv2.GaussianBlur(np.clip(texture, 0, 1), (3, 3), 0.8)
    return Scene(
        skin=np.clip(skin, 0, 1),
        object_colour=rng.uniform(0.1, 0.9, size=3),
        light_dir=light / np.linalg.norm(light),
        ambient=float(rng.uniform(0.25, 0.45)),
        exposure=float(rng.uniform(0.8, 1.15)),
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
    extent = np.max(hi - lo + 1, axis=1)
    pixel_ids, depths, face_ids, barys = [], [], [], []
    for size in (2, 4, 8, 16, 32, 64, 128, 256, 512, 1024, 2048):
        sel = np.flatnonzero(ok & (extent <= size) & (extent > size // 2 if size > 2 else True))
        if sel.size == 0:
            continue
        oy, ox = np.mgrid[0:size, 0:size]
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


# ----------------------------------------------------------------------------- frames


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


def render_view(
    scene: Scene,
    camera: AbstractCamera,
    T_world_cam: np.ndarray,
    meshes: list[tuple[np.ndarray, np.ndarray, np.ndarray]],
    rays: np.ndarray | None = None,
) -> tuple[np.ndarray, np.ndarray]:
    """Render one view: uint8 image (H, W, 3) (or (H, W) for grayscale scenes) and the
    depth buffer (H, W) in metres (inf on the background).

    Args:
        meshes: (vertices in this camera's frame (V, 3), faces (F, 3), albedo (3,)).
    """
    image = render_background(scene, camera, T_world_cam, rays)
    W, H = camera.width, camera.height
    depth = np.full((H, W), np.inf, np.float32)
    if meshes:
        offsets = np.cumsum([0] + [len(v) for v, _, _ in meshes])
        verts = np.concatenate([v for v, _, _ in meshes])
        faces = np.concatenate([f + o for (_, f, _), o in zip(meshes, offsets)])
        albedo = np.concatenate([np.broadcast_to(a, (len(f), 3)) for _, f, a in meshes])
        normals = np.concatenate([vertex_normals(v, f) for v, f, _ in meshes])
        uv = np.asarray(camera.project(jnp.asarray(verts, jnp.result_type(float))), np.float64)
        face, bary, depth = rasterize(uv, verts[:, 2], faces, W, H)
        hit = face >= 0
        f_ids = face[hit]
        n = np.einsum("pk,pkc->pc", bary[hit], normals[faces[f_ids]])
        n /= np.maximum(np.linalg.norm(n, axis=1, keepdims=True), 1e-9)
        lambert = np.clip(n @ scene.light_dir, 0.0, None)
        shade = scene.ambient + (1.0 - scene.ambient) * lambert
        image[hit] = albedo[f_ids] * shade[:, None]
    image = np.clip(image * scene.exposure, 0.0, 1.0)
    out = (image * 255.0 + 0.5).astype(np.uint8)
    if scene.grayscale:
        out = cv2.cvtColor(out, cv2.COLOR_RGB2GRAY)
    return out, depth
