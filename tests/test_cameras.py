import json

import cv2
import jax
import jax.numpy as jnp
import numpy as np
import pytest

from esther_jax import cameras
from esther_jax.cameras import Fisheye624Camera, PinholeCamera, StereoRig

from .helpers import finite_difference_jacobian


def random_points_in_view(camera, n, rng, depth=(0.15, 1.0)):
    """Points in front of the camera whose pixels fall inside the image (and FOV)."""
    pts = []
    while len(pts) < n:
        uv = rng.uniform([0, 0], [camera.width - 1, camera.height - 1], size=(4 * n, 2))
        rays = np.asarray(camera.unproject(jnp.asarray(uv)))
        z = rng.uniform(*depth, size=(4 * n, 1))
        p = rays * z
        ok = np.asarray(camera.is_visible(jnp.asarray(p)))
        pts.extend(p[ok])
    return np.asarray(pts[:n])


def test_pinhole_matches_opencv(x64):
    rng = np.random.default_rng(0)
    cam = PinholeCamera(623.0, 620.0, 924.0, 606.0, 1920, 1200)
    points = rng.uniform([-0.3, -0.2, 0.2], [0.3, 0.2, 1.0], size=(100, 3))
    ref, _ = cv2.projectPoints(points, np.zeros(3), np.zeros(3), np.asarray(cam.K), None)
    np.testing.assert_allclose(np.asarray(cam.project(jnp.asarray(points))), ref[:, 0], atol=1e-9)
    uv = rng.uniform(0, 1000, size=(50, 2))
    undist = cv2.undistortPoints(uv[:, None], np.asarray(cam.K), None)[:, 0]
    np.testing.assert_allclose(np.asarray(cam.unproject(jnp.asarray(uv)))[:, :2], undist, atol=1e-9)


def test_pinhole_known_answers_and_visibility():
    cam = PinholeCamera(500.0, 500.0, 319.5, 239.5, 640, 480)
    np.testing.assert_allclose(np.asarray(cam.project(jnp.asarray([0.0, 0.0, 2.0]))), [319.5, 239.5])
    # pixel-centre convention: the image spans [-0.5, W - 0.5)
    edge = lambda u, v: cam.unproject(jnp.asarray([u, v])) * 0.5  # noqa: E731
    assert bool(cam.is_visible(edge(-0.5, 100.0))) and not bool(cam.is_visible(edge(-0.51, 100.0)))
    assert not bool(cam.is_visible(edge(639.5, 100.0))) and bool(cam.is_visible(edge(639.49, 100.0)))
    assert not bool(cam.is_visible(jnp.asarray([0.0, 0.0, -1.0])))
    assert not bool(cam.is_visible(jnp.asarray([0.0, 0.0, 0.0])))
    assert bool(cam.is_visible(edge(-2.0, 100.0), margin=2.0))


def test_scaled_and_cropped_follow_the_pixel_centre_rule():
    cam = PinholeCamera(500.0, 480.0, 319.5, 239.5, 640, 480)
    p = jnp.asarray([0.03, -0.02, 0.5])
    uv = np.asarray(cam.project(p))
    half = cam.scaled(0.5)
    assert (half.width, half.height) == (320, 240)
    np.testing.assert_allclose(np.asarray(half.project(p)), 0.5 * (uv + 0.5) - 0.5, atol=1e-4)
    np.testing.assert_allclose([float(half.cx), float(half.cy)], [159.5, 119.5])
    crop = cam.cropped(100, 50, 200, 200)
    np.testing.assert_allclose(np.asarray(crop.project(p)), uv - [100, 50], atol=1e-4)
    # a real resize: the image of a point lands on the scaled camera's pixel
    image = np.zeros((480, 640), np.float32)
    cv2.circle(image, (400, 300), 20, 1.0, -1)
    small = cv2.resize(image, (320, 240), interpolation=cv2.INTER_AREA)
    ys, xs = np.nonzero(small > 0)
    centroid = np.average(np.stack([xs, ys], 1), axis=0, weights=small[ys, xs])
    expected = 0.5 * (np.array([400.0, 300.0]) + 0.5) - 0.5
    np.testing.assert_allclose(centroid, expected, atol=0.05)


# ----------------------------------------------------------------------------- Fisheye624


@pytest.fixture
def golden(shared_data):
    return json.loads((shared_data / "fisheye624_golden.json").read_text())


def test_fisheye624_matches_projectaria_golden_vectors(golden, x64):
    points = np.asarray(golden["points_cam_m"])
    for name, ref in golden["cameras"].items():
        w, h = ref["image_size"]
        cam = Fisheye624Camera.from_params(ref["params"], w, h)
        np.testing.assert_allclose(np.asarray(cam.project(jnp.asarray(points))), np.asarray(ref["pixels"]), atol=1e-8, err_msg=name)
        rays = np.asarray(cam.unproject(jnp.asarray(ref["pixels"])))
        expected = np.asarray(ref["unprojected_rays_z1"])
        ok = np.asarray(ref["pixel_inside_image"])  # Newton converges inside the image
        np.testing.assert_allclose(rays[ok], expected[ok], atol=1e-9, err_msg=name)
        jp = np.asarray(jax.jacfwd(cam.project)(jnp.asarray(points[1])))
        np.testing.assert_allclose(jp, np.asarray(ref["jacobian_wrt_point_of_point1"]), rtol=1e-8, atol=1e-6)

        def project_with(params15):
            return Fisheye624Camera.from_params(params15, w, h).project(jnp.asarray(points[1]))

        jk = np.asarray(jax.jacfwd(lambda p: Fisheye624Camera(
            p[0], p[0], p[1], p[2], p[3:9], p[9:11], p[11:15], w, h).project(jnp.asarray(points[1])))(jnp.asarray(ref["params"])))  # fmt: skip
        np.testing.assert_allclose(jk, np.asarray(ref["jacobian_wrt_params_of_point1"]), rtol=1e-7, atol=1e-5)
        del project_with


def test_fisheye624_rectification_map_matches_projectaria(golden, x64):
    from esther_jax.crops import Crop, rectification_map

    ref = golden["cameras"]["aria_camera-rgb"]
    fisheye = Fisheye624Camera.from_params(ref["params"], *ref["image_size"])
    fx, fy, cx, cy = golden["linear_camera"]["params_fx_fy_cx_cy"]
    linear = PinholeCamera(fx, fy, cx, cy, 512, 512)
    table = np.asarray(rectification_map(fisheye, Crop(camera=linear, R_cam_crop=jnp.eye(3))))
    samples = golden["linear_camera"]["rectification_map_from_aria_rgb"]
    dst = np.asarray(samples["dst_pixels"])
    src = np.asarray(samples["src_pixels"])
    integral = np.all(dst == np.round(dst), axis=1)
    got = table[dst[integral, 1].astype(int), dst[integral, 0].astype(int)]
    np.testing.assert_allclose(got, src[integral], atol=1e-6)


@pytest.mark.parametrize("preset", ["hot3d_aria", "hot3d_quest3"])
def test_fisheye_round_trip_inside_the_field_of_view(preset, x64):
    cam = cameras.rig_preset(preset).left
    rng = np.random.default_rng(1)
    points = random_points_in_view(cam, 500, rng)
    uv = cam.project(jnp.asarray(points))
    back = cam.project(cam.unproject(uv))
    assert np.max(np.abs(np.asarray(back - uv))) < 1e-3
    rays = np.asarray(cam.unproject(uv))
    np.testing.assert_allclose(rays * points[:, 2:3], points, atol=1e-6)


def test_fisheye_float32_round_trip():
    cam = cameras.rig_preset("hot3d_quest3").left
    points = random_points_in_view(cam, 200, np.random.default_rng(2))
    uv = cam.project(jnp.asarray(points, jnp.float32))
    assert np.max(np.abs(np.asarray(cam.project(cam.unproject(uv)) - uv))) < 1e-2


def test_fisheye_visibility_rules():
    cam = cameras.rig_preset("hot3d_aria").left
    assert bool(cam.is_visible(jnp.asarray([0.0, 0.0, 0.5])))
    assert not bool(cam.is_visible(jnp.asarray([0.0, 0.0, -0.5])))  # projects like its negation
    np.testing.assert_allclose(np.asarray(cam.project(jnp.asarray([0.1, 0.1, -0.5]))), np.asarray(cam.project(jnp.asarray([-0.1, -0.1, 0.5]))), atol=1e-4)
    wide = jnp.asarray([np.tan(1.45), 0.0, 1.0])  # beyond max_angle = 1.4 rad
    assert not bool(cam.is_visible(wide, margin=1e6))


def test_fisheye_parameter_layouts():
    p15 = [241.0, 319.5, 239.5] + [0.01] * 12
    p16 = [241.0, 242.0, 319.5, 239.5] + [0.01] * 12
    a = Fisheye624Camera.from_params(p15, 640, 480)
    b = Fisheye624Camera.from_params(p16, 640, 480)
    assert float(a.fy) == 241.0 and float(b.fy) == 242.0
    with pytest.raises(ValueError, match="15 or 16"):
        Fisheye624Camera.from_params([1.0] * 14, 640, 480)
    with pytest.raises(ValueError, match="NaN"):
        Fisheye624Camera.from_params([np.nan] * 15, 640, 480)


@pytest.mark.parametrize("model", ["pinhole", "fisheye"])
def test_gradients_are_finite_on_the_optical_axis(model, x64):
    if model == "fisheye":
        camera = cameras.rig_preset("hot3d_quest3").left
    else:
        camera = PinholeCamera(500.0, 500.0, 319.5, 239.5, 640, 480)
    on_axis = jnp.asarray([0.0, 0.0, 0.7])
    centre = camera.project(on_axis)
    for f, x in ((camera.project, on_axis), (camera.unproject, centre)):
        jf = np.asarray(jax.jacfwd(f)(x))
        jr = np.asarray(jax.jacrev(f)(x))
        assert np.all(np.isfinite(jf)) and np.all(np.isfinite(jr))
        np.testing.assert_allclose(jf, jr, atol=1e-9)
        np.testing.assert_allclose(jf, finite_difference_jacobian(f, np.asarray(x), h=1e-7), rtol=1e-5, atol=1e-6)
    off_axis = jnp.asarray([0.05, -0.03, 0.4])
    np.testing.assert_allclose(
        np.asarray(jax.jacfwd(camera.project)(off_axis)), finite_difference_jacobian(camera.project, np.asarray(off_axis)), rtol=1e-5
    )


def test_cameras_jit_and_vmap_agree():
    rig = cameras.rig_preset("hot3d_quest3")
    points = jnp.asarray(random_points_in_view(rig.left, 16, np.random.default_rng(3)), jnp.float32)
    plain = rig.left.project(points)
    np.testing.assert_allclose(np.asarray(jax.jit(lambda c, p: c.project(p))(rig.left, points)), np.asarray(plain), atol=1e-3)
    np.testing.assert_allclose(np.asarray(jax.vmap(rig.left.project)(points)), np.asarray(plain), atol=1e-3)
    stacked = rig.cameras
    both = jax.vmap(lambda cam: cam.project(points))(stacked)
    np.testing.assert_allclose(np.asarray(both[0]), np.asarray(plain), atol=1e-3)


# ----------------------------------------------------------------------------- rigs


@pytest.mark.parametrize("name", cameras.RIG_PRESETS)
def test_presets_and_json_round_trip(name, tmp_path):
    rig = cameras.rig_preset(name)
    expected = {"esther": (623, 62, 1920), "esther_mocap": (623, 62, 1920), "hot3d_aria": (241, 138, 640), "hot3d_quest3": (504, 64, 1280)}
    focal, baseline_mm, width = expected[name]
    assert abs(float(rig.left.fx) - focal) < 1.5 and rig.left.width == width
    assert abs(float(rig.baseline) * 1000 - baseline_mm) < 0.5
    loaded = StereoRig.from_json(rig.to_json(tmp_path / "rig.json", name))
    assert type(loaded.left) is type(rig.left) and cameras.rig_name(tmp_path / "rig.json") == name
    assert jax.tree.structure(loaded) == jax.tree.structure(rig)
    np.testing.assert_allclose(np.asarray(loaded.T_left_right), np.asarray(rig.T_left_right), atol=1e-6)
    p = jnp.asarray([0.02, 0.05, 0.4])
    np.testing.assert_allclose(np.asarray(loaded.right.project(p)), np.asarray(rig.right.project(p)), atol=1e-3)


def test_rig_json_format_of_the_architecture(tmp_path):
    data = {
        "name": "esther-rig",
        "cameras": {
            "left": {"model": "pinhole", "width": 1920, "height": 1200, "fx": 623.0, "fy": 623.0, "cx": 924.0, "cy": 606.0},
            "right": {"model": "pinhole", "width": 1920, "height": 1200, "fx": 623.0, "fy": 623.0, "cx": 924.0, "cy": 606.0},
        },
        "T_left_right": [[1, 0, 0, 0.062], [0, 1, 0, 0], [0, 0, 1, 0], [0, 0, 0, 1]],
    }
    (tmp_path / "rig.json").write_text(json.dumps(data))
    rig = StereoRig.from_json(tmp_path / "rig.json")
    assert abs(float(rig.baseline) - 0.062) < 1e-7 and cameras.rig_name(tmp_path / "rig.json") == "esther-rig"


@pytest.mark.parametrize(
    "mutate, message",
    [
        (lambda d: d["cameras"].pop("right"), "camera 'right' is missing"),
        (lambda d: d.update(T_left_right=np.eye(4).tolist()), "baseline"),
        (lambda d: d["cameras"]["left"].update(fx=0.0), "positive"),
        (lambda d: d["cameras"]["left"].update(model="orthographic"), "unknown camera model"),
        (lambda d: d.update(T_left_right=(2 * np.eye(4)).tolist()), "not a rigid transform"),
        (lambda d: d["cameras"]["left"].pop("width"), "width"),
    ],
)
def test_bad_rig_files_say_what_is_wrong(tmp_path, mutate, message):
    data = cameras.rig_preset("esther").to_dict()
    mutate(data)
    (tmp_path / "rig.json").write_text(json.dumps(data))
    with pytest.raises(ValueError, match=message):
        StereoRig.from_json(tmp_path / "rig.json")


def test_unreadable_rig_files(tmp_path):
    with pytest.raises(ValueError, match="cannot read"):
        StereoRig.from_json(tmp_path / "absent.json")
    (tmp_path / "rig.json").write_text('{"cameras": {"left": ')
    with pytest.raises(ValueError, match="not valid JSON"):
        StereoRig.from_json(tmp_path / "rig.json")
    with pytest.raises(ValueError, match="unknown rig preset"):
        cameras.rig_preset("kinect")


@pytest.mark.parametrize("preset", ["hot3d_aria", "hot3d_quest3"])
def test_fisheye624_matches_projectaria_tools_on_random_points(preset, x64):
    """Live oracle: `pip install --no-deps projectaria-tools==2.3.0` (skipped when absent)."""
    calibration = pytest.importorskip("projectaria_tools.core.calibration")
    from projectaria_tools.core.sophus import SE3

    for cam in (cameras.rig_preset(preset).left, cameras.rig_preset(preset).right):
        params = np.asarray(cam.params, np.float64)
        aria_params = np.concatenate([params[:1], params[2:]])  # single focal (fx == fy in the presets)
        ref = calibration.CameraCalibration(
            "cam", calibration.CameraModelType.FISHEYE624, aria_params, SE3.from_matrix(np.eye(4)),
            cam.width, cam.height, None, float(cam.max_angle), "serial",
        )  # fmt: skip
        points = random_points_in_view(cam, 100, np.random.default_rng(7))
        ours = np.asarray(cam.project(jnp.asarray(points)))
        theirs = np.stack([ref.project_no_checks(p).reshape(2) for p in points])
        np.testing.assert_allclose(ours, theirs, atol=1e-8)
        rays = np.asarray(cam.unproject(jnp.asarray(theirs)))
        their_rays = np.stack([ref.unproject_no_checks(uv).reshape(3) for uv in theirs])
        np.testing.assert_allclose(rays, their_rays / their_rays[:, 2:3], atol=1e-9)
        visible = np.asarray(cam.is_visible(jnp.asarray(points)))
        assert np.all(visible == np.array([ref.project(p) is not None for p in points]))


# ----------------------------------------------------------------------------- rig geometry

GEOMETRY_RIGS = ("esther", "hot3d_aria", "hot3d_quest3")


def _rig_points(shape: tuple[int, ...], seed: int = 0) -> jax.Array:
    """Rig-frame points around both rigs' fields of view: some visible in one view, some
    in both, some in neither, a few behind the cameras."""
    rng = np.random.default_rng(seed)
    return jnp.asarray(rng.uniform([-0.6, -0.5, -0.1], [0.6, 0.5, 0.8], size=shape + (3,)), jnp.result_type(float))


def _explicit_views(rig: StereoRig, X: jax.Array) -> np.ndarray:
    """The formula the rig API replaces: X_right = inv(T_left_right) X_rig, homogeneous, float64."""
    X = np.asarray(X, np.float64)
    T_right_left = np.linalg.inv(np.asarray(rig.T_left_right, np.float64))
    right = np.einsum("ij,...j->...i", T_right_left, np.concatenate([X, np.ones(X.shape[:-1] + (1,))], -1))[..., :3]
    return np.stack([X, right])


def _rig_geometry(rig: StereoRig, X: jax.Array):
    return rig.to_views(X), rig.project(X), rig.is_visible(X), rig.depths(X), rig.distances(X)


_rig_geometry_jit = jax.jit(_rig_geometry)
_rig_geometry_vmap = jax.jit(jax.vmap(_rig_geometry, in_axes=(None, 0), out_axes=1))


@pytest.mark.parametrize("shape", [(), (3, 4)])
@pytest.mark.parametrize("name", GEOMETRY_RIGS)
def test_rig_geometry_equals_the_per_view_formulas(name, shape):
    rig = cameras.rig_preset(name)
    X = _rig_points(shape, seed=len(shape))
    views, uv, visible, depths, distances = _rig_geometry(rig, X)
    assert views.shape == (2,) + shape + (3,) and uv.shape == (2,) + shape + (2,)
    assert visible.shape == depths.shape == distances.shape == (2,) + shape and visible.dtype == jnp.bool_
    assert views.dtype == uv.dtype == depths.dtype == distances.dtype == X.dtype
    explicit = _explicit_views(rig, X)
    np.testing.assert_array_equal(np.asarray(views[0]), np.asarray(X))  # the rig frame is the left camera's
    np.testing.assert_allclose(np.asarray(views), explicit, atol=1e-6)
    np.testing.assert_allclose(np.asarray(depths), explicit[..., 2], atol=1e-6)
    np.testing.assert_allclose(np.asarray(distances), np.linalg.norm(explicit, axis=-1), atol=1e-6)
    for v, camera in enumerate((rig.left, rig.right)):  # each view with its own camera
        # the same arithmetic in two compiled programs: equal up to float32 rounding (1e-7 relative)
        np.testing.assert_allclose(np.asarray(uv[v]), np.asarray(camera.project(views[v])), rtol=1e-6, atol=1e-4)
        np.testing.assert_array_equal(np.asarray(visible[v]), np.asarray(camera.is_visible(views[v])))
        np.testing.assert_array_equal(np.asarray(rig.is_visible(X, margin=50.0)[v]), np.asarray(camera.is_visible(views[v], 50.0)))
        in_front = explicit[v][..., 2] > 0.1  # pixels of the explicit points, away from the z = 0 singularity
        ref = np.asarray(camera.project(jnp.asarray(explicit[v], X.dtype)))
        np.testing.assert_allclose(np.asarray(uv[v])[in_front], ref[in_front], atol=2e-3)
    if shape:  # the sample exercises both answers of the visibility test in each view
        assert np.asarray(visible).any(axis=-1).any(axis=-1).all() and not np.asarray(visible).all(axis=-1).all(axis=-1).any()
    for got, want in zip(_rig_geometry_jit(rig, X), (views, uv, visible, depths, distances)):
        np.testing.assert_allclose(np.asarray(got), np.asarray(want), atol=1e-4)
    if shape:
        for got, want in zip(_rig_geometry_vmap(rig, X), (views, uv, visible, depths, distances)):
            np.testing.assert_allclose(np.asarray(got), np.asarray(want), atol=1e-4)


@pytest.mark.parametrize("name", GEOMETRY_RIGS)
def test_rig_inverse_is_exact_and_rigid(name):
    rig = cameras.rig_preset(name)
    T = np.asarray(rig.T_right_left)
    np.testing.assert_allclose(np.asarray(rig.T_right_left @ rig.T_left_right), np.eye(4), atol=1e-6)
    np.testing.assert_allclose(T, np.linalg.inv(np.asarray(rig.T_left_right, np.float64)), atol=1e-6)
    np.testing.assert_array_equal(T[3], [0, 0, 0, 1])
    np.testing.assert_array_equal(T[:3, :3], np.asarray(rig.T_left_right)[:3, :3].T)
    np.testing.assert_allclose(np.asarray(rig.T_cams_rig @ rig.T_rig_cams), np.broadcast_to(np.eye(4), (2, 4, 4)), atol=1e-6)


def test_rig_of_two_camera_models_projects_each_view_with_its_own_camera():
    aria = cameras.rig_preset("hot3d_aria")
    pinhole = PinholeCamera(300.0, 300.0, 319.5, 239.5, 640, 480)
    rig = StereoRig(pinhole, aria.right, aria.T_left_right)
    X = _rig_points((5,))
    views = rig.to_views(X)
    np.testing.assert_array_equal(np.asarray(rig.project(X)[0]), np.asarray(pinhole.project(X)))
    np.testing.assert_array_equal(np.asarray(rig.project(X)[1]), np.asarray(aria.right.project(views[1])))
    np.testing.assert_array_equal(np.asarray(rig.is_visible(X)[1]), np.asarray(aria.is_visible(X)[1]))


def test_rig_geometry_in_float64_and_gradients(x64):
    rig = cameras.rig_preset("hot3d_aria")
    X = _rig_points((4,))
    assert X.dtype == jnp.float64 and rig.to_views(X).dtype == jnp.float64
    np.testing.assert_allclose(np.asarray(rig.to_views(X)), _explicit_views(rig, X), atol=1e-12)
    np.testing.assert_allclose(np.asarray(rig.T_right_left @ rig.T_left_right), np.eye(4), atol=1e-12)
    # distances are differentiable everywhere, also at an optical centre
    centre = jnp.zeros(3)
    grad = jax.grad(lambda x: jnp.sum(rig.distances(x)))(centre)
    assert np.all(np.isfinite(np.asarray(grad)))
    p = X[0]
    jac = jax.jacfwd(rig.depths)(p)
    np.testing.assert_allclose(np.asarray(jac), np.stack([[0.0, 0.0, 1.0], np.asarray(rig.T_right_left)[2, :3]]), atol=1e-12)


@pytest.mark.parametrize(
    "t_shape, x_shape",
    [((), ()), ((), (3, 4)), ((3, 4), (3, 4)), ((3, 1), (1, 4)), ((3, 4), ())],
)
def test_apply_transform_equals_homogeneous_multiplication(t_shape, x_shape):
    rng = np.random.default_rng(3)
    T = np.tile(np.eye(4), t_shape + (1, 1))
    for index in np.ndindex(*t_shape):
        T[index][:3, :3] = cv2.Rodrigues(rng.normal(size=3))[0]
        T[index][:3, 3] = rng.normal(size=3)
    X = rng.normal(size=x_shape + (3,))
    dtype = jnp.result_type(float)
    got = cameras.apply_transform(jnp.asarray(T, dtype), jnp.asarray(X, dtype))
    want = np.einsum("...ij,...j->...i", T, np.concatenate([X, np.ones(x_shape + (1,))], -1))[..., :3]
    assert got.shape == want.shape and got.dtype == dtype
    np.testing.assert_allclose(np.asarray(got), want, atol=1e-5)
    unchecked = getattr(cameras.apply_transform, "__wrapped__", cameras.apply_transform)  # past the tests' jaxtyping check
    with pytest.raises(ValueError, match="apply_transform takes"):
        unchecked(jnp.asarray(T, dtype)[..., :3, :], jnp.asarray(X, dtype))


# ----------------------------------------------------------------------------- unprojection validity


@jax.jit
def _unproject_checked(cam, uv):
    rays, valid = cam.unproject_with_validity(uv)
    return rays, valid, cam.unproject(uv), cam.project(rays), cam.is_visible(0.5 * rays)


@pytest.mark.parametrize("view", ["left", "right"])
def test_fisheye_unproject_validity_mask(view, x64):
    cam = getattr(cameras.rig_preset("hot3d_aria"), view)
    W, H = cam.width, cam.height
    v, u = np.meshgrid(np.linspace(0.0, H - 1.0, 25), np.linspace(0.0, W - 1.0, 33), indexing="ij")
    corners = np.asarray([[-0.5, -0.5], [W - 0.5, -0.5], [-0.5, H - 0.5], [W - 0.5, H - 0.5]])
    centre = np.asarray([[float(cam.cx), float(cam.cy)]])
    uv = np.concatenate([centre, corners, np.stack([u, v], -1).reshape(-1, 2)])
    rays, valid, plain, back, visible = (np.asarray(x) for x in _unproject_checked(cam, jnp.asarray(uv)))
    assert valid.shape == (uv.shape[0],) and valid.dtype == bool
    assert valid[0] and not np.any(valid[1:5])  # True at the centre, False in every corner
    np.testing.assert_array_equal(rays, plain)  # the rays are `unproject`'s
    error = np.max(np.abs(back - uv), axis=-1)
    # what the mask catches: in the corners the plain ray is mirrored or does not round-trip
    mirrored = np.sign(rays[:, 0]) != np.sign(uv[:, 0] - float(cam.cx))
    assert np.all(mirrored[1:5] | (error[1:5] > 1.0))
    # where valid: project(unproject(uv)) round-trips, within max_angle, visible
    assert 0.5 < valid.mean() < 1.0
    assert np.max(error[valid]) < 1e-6
    assert np.max(np.arctan(np.linalg.norm(rays[valid, :2], axis=-1))) <= float(cam.max_angle)
    assert np.all(visible[valid])
    # leading batch axes; eager equals jit
    _, grid_valid = cam.unproject_with_validity(jnp.asarray(uv[5:]).reshape(25, 33, 2))
    assert grid_valid.shape == (25, 33)
    np.testing.assert_array_equal(np.asarray(grid_valid).reshape(-1), valid[5:])


def test_fisheye_unproject_validity_float32_and_gradients():
    cam = cameras.rig_preset("hot3d_quest3").left
    points = jnp.asarray(np.random.default_rng(4).uniform([-0.3, -0.25, 0.3], [0.3, 0.25, 0.6], size=(100, 3)), jnp.float32)
    uv = cam.project(points)
    corner = jnp.asarray([[cam.width - 0.5, cam.height - 0.5]], jnp.float32)
    rays, valid, _, back, _ = _unproject_checked(cam, jnp.concatenate([uv, corner]))
    assert np.all(np.asarray(valid[:-1])) and not bool(valid[-1])  # float32 Newton residuals pass the sqrt(eps) tolerance
    assert np.max(np.abs(np.asarray(back[:-1] - uv))) < 1e-2
    jac = jax.jit(jax.vmap(jax.jacrev(cam.unproject)))(jnp.concatenate([uv[:1], corner]))
    assert np.all(np.isfinite(np.asarray(jac)))


def test_pinhole_unproject_is_valid_everywhere():
    cam = PinholeCamera(500.0, 500.0, 319.5, 239.5, 640, 480)
    for shape in ((), (3, 1, 2)):
        uv = jnp.full(shape + (2,), 7000.0)
        rays, valid = cam.unproject_with_validity(uv)
        assert valid.shape == shape and bool(jnp.all(valid))
        np.testing.assert_array_equal(np.asarray(rays), np.asarray(cam.unproject(uv)))
