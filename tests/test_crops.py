import jax
import jax.numpy as jnp
import numpy as np
import pytest

from esther_jax import cameras, crops
from esther_jax.cameras import PinholeCamera


def blob_image(shape, centre, sigma=3.0):
    """A Gaussian blob centred (sub-pixel) at `centre` in the pixel-centre convention."""
    v, u = np.mgrid[0 : shape[0], 0 : shape[1]].astype(np.float64)
    return np.exp(-((u - centre[0]) ** 2 + (v - centre[1]) ** 2) / (2 * sigma**2)).astype(np.float32)


def centroid(image, threshold=0.05):
    v, u = np.mgrid[0 : image.shape[0], 0 : image.shape[1]]
    w = np.where(image > threshold, image, 0.0)
    return np.array([np.sum(u * w), np.sum(v * w)]) / np.sum(w)


def test_crop_camera_equals_cropping_and_resizing_the_image():
    cam = cameras.rig_preset("esther").left
    point = jnp.asarray([0.04, 0.03, 0.45])
    uv = np.asarray(cam.project(point))
    image = blob_image((1200, 1920), uv, sigma=6.0)
    box = jnp.asarray([uv[0] - 70.0, uv[1] - 40.0, uv[0] + 55.0, uv[1] + 90.0])
    crop = crops.crop_camera(cam, box)
    warped = crops.warp_crop(image, box)
    assert warped.shape == (224, 224)
    np.testing.assert_allclose(centroid(warped), np.asarray(crop.camera.project(point)), atol=0.05)
    M = crops.crop_affine(box)
    np.testing.assert_allclose(M @ np.append(uv, 1.0), np.asarray(crop.camera.project(point)), atol=1e-3)
    # the box centre lands on the crop centre, between pixels 111 and 112
    centre = np.asarray(0.5 * (box[:2] + box[2:]))
    np.testing.assert_allclose(M @ np.append(centre, 1.0), [111.5, 111.5], atol=1e-4)


@pytest.mark.parametrize("strategy", crops.RECTIFICATION_STRATEGIES)
@pytest.mark.parametrize("preset", ["hot3d_aria", "hot3d_quest3"])
def test_rectified_crops_render_points_where_the_crop_camera_projects_them(strategy, preset):
    fisheye = cameras.rig_preset(preset).left
    point = jnp.asarray([-0.06, 0.05, 0.35])
    uv = np.asarray(fisheye.project(point))
    image = blob_image((fisheye.height, fisheye.width), uv, sigma=2.5)
    box = jnp.asarray([uv[0] - 30.0, uv[1] - 25.0, uv[0] + 20.0, uv[1] + 35.0])
    crop = crops.rectified_crop(fisheye, box, strategy)
    rendered = crops.remap_crop(image, fisheye, crop)
    expected = np.asarray(crop.camera.project(crop.R_cam_crop.T @ point))
    assert np.all((expected > 0) & (expected < 223))
    np.testing.assert_allclose(centroid(rendered, threshold=0.2), expected, atol=0.6)
    if strategy.startswith("offbb"):
        np.testing.assert_allclose(np.asarray(crop.R_cam_crop), np.eye(3), atol=1e-7)
        assert float(crop.camera.fx) > float(strategy[5:])  # the crop magnifies the wide pinhole
    else:  # ray-aligned: the box centre is on the crop's optical axis
        centre_ray = fisheye.unproject(0.5 * (box[:2] + box[2:]))
        np.testing.assert_allclose(np.asarray(crop.camera.project(crop.R_cam_crop.T @ centre_ray)), [111.5, 111.5], atol=1e-3)


def test_unknown_strategy_is_named():
    with pytest.raises(ValueError, match="hc"):
        crops.rectified_crop(cameras.rig_preset("hot3d_aria").left, jnp.asarray([0.0, 0.0, 10.0, 10.0]), "fisheye-magic")


def test_plucker_rays(x64):
    rig = cameras.rig_preset("esther")
    box = jnp.asarray([800.0, 500.0, 950.0, 700.0])
    crop = crops.crop_camera(rig.right, box)
    T = rig.T_left_right
    rays = crops.plucker_rays(crop, T, grid=14)
    assert rays.shape == (14, 14, 6)
    d, m = np.asarray(rays[..., :3]), np.asarray(rays[..., 3:])
    np.testing.assert_allclose(np.linalg.norm(d, axis=-1), 1.0, atol=1e-12)
    np.testing.assert_allclose(np.sum(d * m, axis=-1), 0.0, atol=1e-12)
    # every point on the ray has the same moment: X = o + 0.4 d  =>  X x d = m
    origin = np.asarray(T[:3, 3])
    np.testing.assert_allclose(np.cross(origin + 0.4 * d, d), m, atol=1e-12)
    # the ray of a patch centre passes through the 3D point that projects there
    uv = np.asarray(crops.patch_centres(224, 14))[3, 5]
    X_cam = np.asarray(crop.camera.unproject(jnp.asarray(uv))) * 0.5
    X_rig = np.asarray(T[:3, :3]) @ X_cam + origin
    np.testing.assert_allclose(np.cross(X_rig, d[3, 5]), m[3, 5], atol=1e-12)
    # per pixel: grid = S
    assert crops.plucker_rays(crop, T, grid=224).shape == (224, 224, 6)


def test_crop_cameras_vmap_and_grad():
    cam = PinholeCamera(623.0, 623.0, 924.0, 606.0, 1920, 1200)
    boxes = jnp.asarray([[800.0, 500.0, 950.0, 700.0], [100.0, 100.0, 400.0, 300.0]])
    batched = jax.vmap(lambda b: crops.crop_camera(cam, b).camera.fx)(boxes)
    np.testing.assert_allclose(np.asarray(batched), [crops.crop_camera(cam, b).camera.fx for b in boxes], rtol=1e-6)
    g = jax.grad(lambda b: crops.crop_camera(cam, b).camera.project(jnp.asarray([0.0, 0.0, 0.5])).sum())(boxes[0])
    assert np.all(np.isfinite(np.asarray(g)))
    rays = jax.vmap(lambda b: crops.plucker_rays(crops.crop_camera(cam, b), jnp.eye(4), 14))(boxes)
    assert rays.shape == (2, 14, 14, 6)


def test_warp_crop_fills_outside_with_black():
    image = np.full((100, 100, 3), 200, np.uint8)
    out = crops.warp_crop(image, [-50.0, -50.0, 10.0, 10.0], size=64)
    assert out.shape == (64, 64, 3) and out[0, 0].sum() == 0 and out[-1, -1].sum() > 0


@pytest.mark.parametrize("preset", ["hot3d_aria", "hot3d_quest3"])
def test_crop_pixels_behind_the_camera_are_black_and_uncovered(preset):
    """A ray-aligned (hc) crop of a hand at the edge of a fisheye's field of view (its
    centre 1.3 rad off the axis towards the top-left) has pixels whose rays point behind
    the camera; `project` folds them back into the image, mirrored. They sample nothing
    and count as uncovered."""
    cam = cameras.rig_preset(preset).left
    image = np.zeros((cam.height, cam.width, 3), np.uint8)
    image[cam.height // 2 :, cam.width // 2 :] = 255  # light only in the opposite quadrant
    centre = np.asarray(cam.project(jnp.asarray([-np.sin(1.3) / np.sqrt(2), -np.sin(1.3) / np.sqrt(2), np.cos(1.3)])))
    crop = crops.hand_crop(cam, jnp.asarray(np.concatenate([centre - 60.0, centre + 60.0])), "hc", 64)
    v, u = np.mgrid[:64, :64].astype(np.float32)
    rays = np.asarray(crop.camera.unproject(jnp.asarray(np.stack([u, v], -1)))) @ np.asarray(crop.R_cam_crop).T
    unseen = rays[..., 2] <= 0
    assert unseen.sum() > 100  # the case at hand: many crop rays behind the camera
    table = np.asarray(crops.rectification_map(cam, crop))
    assert not crops.table_coverage(table, cam)[unseen].any() and not crops.crop_coverage(cam, crop)[unseen].any()
    assert crops.remap_table(image, table).max() == 0  # nothing from the lit quadrant leaks in


def test_wide_pinhole_table_has_the_source_image_size():
    """The offbb wide pinhole of a non-square fisheye (Aria's 640 x 480 preset) keeps the
    image's W x H, and so does its rectification table (`esther detect` remaps whole frames
    with it); each table entry is the fisheye pixel of that pinhole pixel's ray."""
    cam = cameras.rig_preset("hot3d_aria").left
    wide = crops.wide_pinhole(cam, 120.0)
    table = np.asarray(crops.rectification_map(cam, crops.Crop(wide, jnp.eye(3))))
    assert table.shape == (cam.height, cam.width, 2)
    pixels = np.array([[0.0, 0.0], [cam.width - 1.0, cam.height - 1.0], [101.0, 407.0]])
    expected = np.asarray(cam.project(wide.unproject(jnp.asarray(pixels))))
    np.testing.assert_allclose(table[pixels[:, 1].astype(int), pixels[:, 0].astype(int)], expected, atol=1e-3)


@pytest.mark.parametrize("strategy", ["offbb120", "hc"])
def test_a_box_far_beyond_a_fisheye_frames_a_proper_crop(strategy):
    """A hand at the edge of Aria's field of view: its box reaches far beyond the image and
    one outline sample lies inside the valid field of view, which framed the offbb crop
    with an infinite focal. It is framed by the box clipped to the image instead (hc's
    crop of the one ray was proper: kept); every crop is proper."""
    camera = cameras.rig_preset("hot3d_aria").right
    beyond = jnp.asarray([-19.96, -122.16, 652.45, 586.47])
    crop = jax.jit(lambda b: crops.rectified_crop(camera, b, strategy, 64))(beyond)
    assert np.all(np.isfinite(np.asarray(crop.camera.K))) and float(crop.camera.fx) > 0
    if strategy == "offbb120":
        clipped = crops.rectified_crop(camera, jnp.asarray([0.0, 0.0, camera.width - 1.0, camera.height - 1.0]), strategy, 64)
        np.testing.assert_allclose(np.asarray(crop.camera.K), np.asarray(clipped.camera.K), rtol=1e-6)
    outside = crops.rectified_crop(camera, jnp.asarray([-500.0, -500.0, -300.0, -300.0]), strategy, 64)
    assert np.all(np.isfinite(np.asarray(outside.camera.K))) and float(outside.camera.fx) > 0
    ordinary = jnp.asarray([200.0, 150.0, 320.0, 270.0])  # well inside: framed by its own outline, unchanged
    K = jax.vmap(lambda b: crops.rectified_crop(camera, b, strategy, 64).camera.K)(jnp.stack([ordinary, beyond]))
    assert np.all(np.isfinite(np.asarray(K))) and float(K[0, 0, 0]) > float(K[1, 0, 0])
