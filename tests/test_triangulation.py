import json

import cv2
import jax
import jax.numpy as jnp
import numpy as np
import pytest

from esther_jax import cameras, triangulation
from esther_jax.cameras import Fisheye624Camera, PinholeCamera, StereoRig
from esther_jax.triangulation import triangulate, triangulate_stereo

from .helpers import finite_difference_jacobian, mixed_rig


def project_rig(rig: StereoRig, points_rig: np.ndarray) -> jnp.ndarray:
    """(N, 2 views, 2) pixels of rig-frame points."""
    T_right_left = jnp.linalg.inv(rig.T_left_right)
    points = jnp.asarray(points_rig)
    in_right = points @ T_right_left[:3, :3].T + T_right_left[None, :3, 3]
    return jnp.stack([rig.left.project(points), rig.right.project(in_right)], axis=1)


def hand_points(n, rng):
    return rng.uniform([-0.15, -0.1, 0.25], [0.15, 0.15, 0.6], size=(n, 3))


batched = jax.jit(jax.vmap(triangulate_stereo, in_axes=(None, 0, 0)))


@pytest.mark.parametrize("preset", [*cameras.RIG_PRESETS, "mixed"])
def test_triangulating_projections_returns_the_points(preset, x64):
    rig = mixed_rig() if preset == "mixed" else cameras.rig_preset(preset)
    rng = np.random.default_rng(0)
    points = hand_points(600, rng)
    T_right_left = np.linalg.inv(np.asarray(rig.T_left_right))
    seen = np.asarray(rig.left.is_visible(jnp.asarray(points))) & np.asarray(
        rig.right.is_visible(jnp.asarray(points @ T_right_left[:3, :3].T + T_right_left[:3, 3]))
    )
    points = points[seen][:200]  # the toed-out Aria cameras share only part of their views
    assert len(points) >= 50
    uv = project_rig(rig, points)
    result = batched(rig, uv, jnp.ones((len(points), 2)))
    assert np.all(np.asarray(result.valid))
    np.testing.assert_allclose(np.asarray(result.point), points, atol=1e-6)
    assert np.max(np.asarray(result.residual_px)) < 1e-6
    assert np.max(np.asarray(result.spread)) < 1e-7
    over_axes = triangulation.triangulate_rig(rig, uv[:48].reshape(12, 4, 2, 2), jnp.ones((12, 4, 2)))  # any leading axes
    np.testing.assert_allclose(np.asarray(over_axes.point), points[:48].reshape(12, 4, 3), atol=1e-6)
    rays, ok = rig.unproject_with_validity(jnp.moveaxis(uv, 1, 0))  # each view through its own camera
    assert np.all(np.asarray(ok))
    in_views = rig.to_views(jnp.asarray(points))  # (2, N, 3)
    np.testing.assert_allclose(np.asarray(rays), np.asarray(in_views / in_views[..., 2:]), atol=1e-6)


def test_matches_opencv_triangulate_points(x64):
    rig = cameras.rig_preset("esther")
    rng = np.random.default_rng(1)
    points = hand_points(300, rng)
    uv = np.asarray(project_rig(rig, points)) + rng.normal(scale=1.0, size=(300, 2, 2))
    K = np.asarray(rig.left.K)
    P_left = K @ np.eye(3, 4)
    P_right = K @ np.linalg.inv(np.asarray(rig.T_left_right))[:3]
    homogeneous = cv2.triangulatePoints(P_left, P_right, uv[:, 0].T.copy(), uv[:, 1].T.copy())
    ref = (homogeneous[:3] / homogeneous[3]).T
    ours = np.asarray(batched(rig, jnp.asarray(uv), jnp.ones((300, 2))).point)
    # different algebraic estimators (homogeneous SVD vs inhomogeneous normal equations)
    # agree to a small fraction of the noise-induced error, and are equally accurate
    err_ours = np.linalg.norm(ours - points, axis=1)
    err_cv = np.linalg.norm(ref - points, axis=1)
    assert np.median(np.linalg.norm(ours - ref, axis=1)) < 0.1 * np.median(err_cv)
    assert abs(err_ours.mean() - err_cv.mean()) < 0.02 * err_cv.mean()


def test_confidence_weights_favour_the_confident_view(x64):
    rig = cameras.rig_preset("esther")
    point = np.array([0.02, 0.05, 0.4])
    uv = np.asarray(project_rig(rig, point[None]))[0]
    noisy = uv.copy()
    noisy[1] += [0.0, 8.0]  # the right view is off its epipolar line by 8 px
    a = triangulate_stereo(rig, jnp.asarray(noisy), jnp.asarray([1.0, 1.0]))
    b = triangulate_stereo(rig, jnp.asarray(noisy), jnp.asarray([1.0, 0.2]))
    assert float(b.residual_px[0]) < float(a.residual_px[0])
    assert float(a.spread) > 1e-4


def test_any_number_of_views(x64):
    rng = np.random.default_rng(2)
    cam = PinholeCamera(600.0, 600.0, 320.0, 240.0, 640, 480)
    poses = []
    for angle in np.linspace(-0.4, 0.4, 4):
        c, s = np.cos(angle), np.sin(angle)
        T = np.eye(4)
        T[:3, :3] = [[c, 0, s], [0, 1, 0], [-s, 0, c]]
        T[:3, 3] = [-0.5 * s, 0.0, 0.5 - 0.5 * c]
        poses.append(T)
    poses = jnp.asarray(np.stack(poses))
    X = np.array([0.01, -0.02, 0.5]) + rng.normal(scale=0.01, size=3)
    in_cams = np.einsum("vji,vj->vi", np.asarray(poses[:, :3, :3]), X[None] - np.asarray(poses[:, :3, 3]))
    uv = np.asarray(cam.project(jnp.asarray(in_cams)))
    cams = jax.tree.map(lambda x: jnp.stack([x] * 4), cam)
    r = triangulate(cams, poses, jnp.asarray(uv), jnp.ones(4))
    assert bool(r.valid) and int(r.num_views) == 4
    np.testing.assert_allclose(np.asarray(r.point), X, atol=1e-9)


def _finite(result):
    return all(np.all(np.isfinite(np.asarray(x))) for x in jax.tree.leaves(result))


def test_degenerate_inputs_are_invalid_and_finite():
    rig = cameras.rig_preset("esther")
    point = np.array([0.02, 0.05, 0.4])
    uv = project_rig(rig, point[None])[0]
    one_view = triangulate_stereo(rig, uv, jnp.asarray([1.0, 0.0]))
    no_view = triangulate_stereo(rig, uv, jnp.zeros(2))
    nan_view = triangulate_stereo(rig, uv.at[1].set(jnp.nan), jnp.ones(2))
    behind = triangulate_stereo(rig, project_rig(rig, -point[None])[0], jnp.ones(2))
    zero_baseline = StereoRig(rig.left, rig.right, jnp.eye(4))
    same_pixel = triangulate_stereo(zero_baseline, jnp.stack([uv[0], uv[0]]), jnp.ones(2))
    other_pixel = triangulate_stereo(zero_baseline, uv, jnp.ones(2))
    far = triangulate_stereo(rig, project_rig(rig, np.array([[0.0, 0.0, 500.0]]))[0], jnp.ones(2))
    for name, r in dict(one_view=one_view, no_view=no_view, nan_view=nan_view, behind=behind,
                        same_pixel=same_pixel, other_pixel=other_pixel, far=far).items():  # fmt: skip
        assert not bool(r.valid), name
        assert _finite(r), name
    assert int(nan_view.num_views) == 1


@pytest.mark.parametrize("weights", [[1.0, 0.0], [0.0, 0.0], [1.0, 1e-4], [1.0, 0.03], [1.0, 1.0]])
def test_gradients_are_finite_as_weights_vanish(weights):
    rig = cameras.rig_preset("esther")
    uv = project_rig(rig, np.array([[0.02, 0.05, 0.4]]))[0]
    w = jnp.asarray(weights)
    loss = lambda uv, w: jnp.sum(triangulate_stereo(rig, uv, w).point)  # noqa: E731
    g_uv, g_w = jax.grad(loss, argnums=(0, 1))(uv, w)
    assert np.all(np.isfinite(np.asarray(g_uv))) and np.all(np.isfinite(np.asarray(g_w)))


def test_jacobian_matches_finite_differences(x64):
    rig = cameras.rig_preset("esther")
    uv = project_rig(rig, np.array([[0.02, 0.05, 0.4]]))[0] + 0.7
    w = jnp.asarray([0.9, 0.6])

    def f(x):
        return triangulate_stereo(rig, x[:4].reshape(2, 2), x[4:]).point

    x = jnp.concatenate([uv.reshape(4), w])
    jf = np.asarray(jax.jacfwd(f)(x))
    np.testing.assert_allclose(jf, np.asarray(jax.jacrev(f)(x)), atol=1e-10)
    np.testing.assert_allclose(jf, finite_difference_jacobian(f, np.asarray(x), h=1e-6), rtol=1e-5, atol=1e-9)


def test_jit_vmap_agree_with_plain_calls():
    rig = cameras.rig_preset("hot3d_quest3")
    rng = np.random.default_rng(3)
    points = hand_points(8, rng)
    uv = project_rig(rig, points)
    w = jnp.asarray(rng.uniform(0.3, 1.0, size=(8, 2)), jnp.float32)
    one = jax.jit(triangulate_stereo)  # one example per call
    plain = np.stack([np.asarray(one(rig, uv[i], w[i]).point) for i in range(8)])
    np.testing.assert_allclose(np.asarray(batched(rig, uv, w).point), plain, atol=1e-5)
    frames = jax.vmap(jax.vmap(triangulate_stereo, in_axes=(None, 0, 0)), in_axes=(None, 0, 0))
    np.testing.assert_allclose(np.asarray(frames(rig, uv.reshape(2, 4, 2, 2), w.reshape(2, 4, 2)).point).reshape(8, 3), plain, atol=1e-5)


def test_triangulate_batch_equals_nested_vmaps(x64):
    rig = cameras.rig_preset("esther")
    rng = np.random.default_rng(5)
    uv = project_rig(rig, hand_points(3 * 21, rng)).reshape(3, 21, 2, 2) + rng.normal(size=(3, 21, 2, 2))
    w = jnp.asarray(rng.uniform(0.0, 1, size=(3, 21, 2)))
    nested = jax.jit(jax.vmap(jax.vmap(triangulate_stereo, in_axes=(None, 0, 0)), in_axes=(None, 0, 0)))(rig, uv, w)
    for chunk in (8, 1000):
        got = triangulation.triangulate_batch(rig.cameras, rig.T_rig_cams, uv, w, chunk=chunk)
        assert got.point.shape == (3, 21, 3) and got.residual_px.shape == (3, 21, 2)
        for a, b in zip(jax.tree.leaves(got), jax.tree.leaves(nested)):
            np.testing.assert_allclose(np.asarray(a), np.asarray(b), rtol=1e-9, atol=1e-9)


def test_bad_shapes_are_named():
    rig = cameras.rig_preset("esther")
    with pytest.raises((ValueError, TypeError), match="one point|uv"):  # jaxtyping checks first in tests
        triangulate_stereo(rig, jnp.zeros((21, 2, 2)), jnp.ones((21, 2)))


def test_real_quest3_landmarks_triangulate(shared_data, x64):
    """HOT3D ground-truth landmarks projected by projectaria-tools into the two real
    Quest 3 fisheye cameras triangulate back to the landmarks."""
    data = json.loads((shared_data / "hot3d_quest3_landmarks_projected.json").read_text())["devices"]["quest3"]
    cams, T_device = {}, {}
    for name in ("camera-slam-left", "camera-slam-right"):
        c = data["cameras"][name]
        cams[name] = Fisheye624Camera.from_params(c["params"], *c["image_size"])
        T_device[name] = np.asarray(c["T_device_camera"])
    stacked = jax.tree.map(lambda a, b: jnp.stack([a, b]), cams["camera-slam-left"], cams["camera-slam-right"])
    triangulate_landmarks = jax.jit(jax.vmap(triangulate, in_axes=(None, None, 0, None)))
    errors = []
    for frame in data["frames"]:
        T_world_device = np.asarray(frame["T_world_device"])
        T_world_cams = jnp.asarray(np.stack([T_world_device @ T_device[n] for n in cams]))
        for hand in frame["hands"].values():
            uv = np.stack([np.asarray(hand["pixels"][n]) for n in cams], axis=1)  # (21, 2, 2)
            r = triangulate_landmarks(stacked, T_world_cams, jnp.asarray(uv), jnp.ones(2))
            assert np.all(np.asarray(r.valid))
            errors.append(np.linalg.norm(np.asarray(r.point) - np.asarray(hand["landmarks_world"]), axis=1))
    assert np.max(np.concatenate(errors)) < 2e-5


def test_weak_perspective_unit_conversion(x64):
    cam = cameras.rig_preset("esther").left
    T = np.array([0.05, -0.03, 0.42])
    X = np.random.default_rng(4).normal(scale=0.03, size=(21, 3)) * np.array([1.0, 1.0, 0.1])  # a flat-ish hand
    uv = np.asarray(cam.project(jnp.asarray(X + T)))
    box_centre, box_side = uv.mean(axis=0), 180.0
    # the weak-perspective camera that best matches, fitted by least squares
    crop = 2.0 * (uv - box_centre) / box_side
    A = np.concatenate([X[:, :1], np.ones((21, 1))], 1)
    s_x, st_x = np.linalg.lstsq(A, crop[:, 0], rcond=None)[0]
    A_y = np.concatenate([X[:, 1:2], np.ones((21, 1))], 1)
    _, st_y = np.linalg.lstsq(A_y, crop[:, 1], rcond=None)[0]
    t = triangulation.weak_perspective_to_translation(
        jnp.asarray(s_x), jnp.asarray([st_x / s_x, st_y / s_x]), jnp.asarray(box_centre), jnp.asarray(box_side), cam
    )
    np.testing.assert_allclose(np.asarray(t), T, atol=0.005)  # weak perspective is an approximation
    exact_s = 2 * float(cam.fx) / (T[2] * box_side)
    t_exact = triangulation.weak_perspective_to_translation(jnp.asarray(exact_s), jnp.zeros(2), jnp.asarray(box_centre), jnp.asarray(box_side), cam)
    assert abs(float(t_exact[2]) - T[2]) < 1e-12


@pytest.mark.parametrize("weights", [[1.0, 0.0], [0.0, 1.0], [0.0, 0.0], [1.0, 1.0], [0.7, 0.4]])
def test_spread_is_finite_with_finite_gradients_as_weights_vanish(weights):
    rig = cameras.rig_preset("esther")
    uv = project_rig(rig, np.array([[0.02, 0.05, 0.4]]))[0] + jnp.asarray([[0.0, 0.0], [0.8, -0.5]])
    w = jnp.asarray(weights)
    spread = lambda uv, w: triangulate_stereo(rig, uv, w).spread  # noqa: E731
    assert np.isfinite(float(spread(uv, w)))
    for grads in (jax.grad(spread, argnums=(0, 1))(uv, w), jax.jacfwd(spread, argnums=(0, 1))(uv, w)):
        assert all(np.all(np.isfinite(np.asarray(g))) for g in grads), weights


def test_spread_value_is_the_weighted_rms_ray_distance(x64):
    rig = cameras.rig_preset("esther")
    uv = project_rig(rig, np.array([[0.02, 0.05, 0.4]]))[0] + jnp.asarray([[0.0, 0.0], [1.5, -1.0]])
    w = np.array([0.9, 0.6])
    r = triangulate_stereo(rig, uv, jnp.asarray(w))
    point = np.asarray(r.point)
    distances2 = []
    for v, camera in enumerate((rig.left, rig.right)):
        T = np.asarray(rig.T_rig_cams[v])
        d = T[:3, :3] @ np.asarray(camera.unproject(uv[v]))
        offset = point - T[:3, 3]
        distances2.append(np.sum(np.cross(offset, d / np.linalg.norm(d)) ** 2))
    assert float(r.spread) == pytest.approx(np.sqrt(np.sum(w * np.asarray(distances2)) / np.sum(w)), rel=1e-9)


def test_a_fisheye_pixel_beyond_the_field_of_view_does_not_observe():
    rig = cameras.rig_preset("hot3d_aria")
    uv = project_rig(rig, np.array([[-0.05, 0.1, 0.35]]))[0]
    corner = jnp.asarray([rig.right.width - 0.5, rig.right.height - 0.5], uv.dtype)
    assert not bool(rig.right.unproject_with_validity(corner)[1])  # its ray would be mirrored
    with_corner = triangulate_stereo(rig, uv.at[1].set(corner), jnp.ones(2))
    left_only = triangulate_stereo(rig, uv, jnp.asarray([1.0, 0.0]))
    assert int(with_corner.num_views) == 1 and not bool(with_corner.valid)
    np.testing.assert_allclose(np.asarray(with_corner.point), np.asarray(left_only.point), atol=1e-6)
    assert float(with_corner.spread) == pytest.approx(float(left_only.spread), abs=1e-6)
    loss = lambda uv, w: jnp.sum(triangulate_stereo(rig, uv, w).point) + triangulate_stereo(rig, uv, w).spread  # noqa: E731
    grads = jax.grad(loss, argnums=(0, 1))(uv.at[1].set(corner), jnp.ones(2))
    assert all(np.all(np.isfinite(np.asarray(g))) for g in grads)
