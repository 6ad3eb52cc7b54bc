import jax
import jax.numpy as jnp
import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from esther_jax import rotations as rot

from .helpers import finite_difference_jacobian

EDGE_ANGLES = [0.0, 1e-8, 1e-4, 0.1, 1.0, np.pi / 2, np.pi - 1e-3, np.pi - 1e-6, np.pi]


def _edge_rotvecs(rng):
    axes = rng.normal(size=(len(EDGE_ANGLES), 3))
    axes /= np.linalg.norm(axes, axis=-1, keepdims=True)
    return axes * np.asarray(EDGE_ANGLES)[:, None]


@pytest.fixture
def rotvecs():
    rng = np.random.default_rng(0)
    random = Rotation.random(200, random_state=1).as_rotvec()
    axis_aligned = np.concatenate([np.eye(3) * a for a in (np.pi, np.pi - 1e-6, 1e-8)])
    return np.concatenate([random, _edge_rotvecs(rng), axis_aligned])


def test_axis_angle_to_matrix_matches_scipy(rotvecs, x64):
    ours = np.array(rot.axis_angle_to_matrix(jnp.asarray(rotvecs)))
    np.testing.assert_allclose(ours, Rotation.from_rotvec(rotvecs).as_matrix(), atol=1e-12)


def test_axis_angle_to_matrix_float32(rotvecs):
    ours = np.array(rot.axis_angle_to_matrix(jnp.asarray(rotvecs, jnp.float32)))
    np.testing.assert_allclose(ours, Rotation.from_rotvec(rotvecs).as_matrix(), atol=2e-6)


def test_matrix_to_axis_angle_matches_scipy(rotvecs, x64):
    matrices = Rotation.from_rotvec(rotvecs).as_matrix()
    ours = np.array(rot.matrix_to_axis_angle(jnp.asarray(matrices)))
    # compare as rotations (at pi, v and -v are the same rotation)
    np.testing.assert_allclose(Rotation.from_rotvec(ours).as_matrix(), matrices, atol=1e-12)
    angles = np.linalg.norm(rotvecs, axis=-1)
    np.testing.assert_allclose(np.linalg.norm(ours, axis=-1), angles, atol=1e-7)
    inside = angles < np.pi - 1e-3
    np.testing.assert_allclose(ours[inside], rotvecs[inside], atol=1e-9)


def test_quaternions_match_scipy(rotvecs, x64):
    q_scipy = Rotation.from_rotvec(rotvecs).as_quat(canonical=True)  # (x, y, z, w)
    q_wxyz = np.concatenate([q_scipy[:, 3:], q_scipy[:, :3]], -1)
    ours = np.array(rot.axis_angle_to_quaternion(jnp.asarray(rotvecs)))
    np.testing.assert_allclose(np.abs(np.sum(ours * q_wxyz, -1)), 1.0, atol=1e-12)
    matrices = Rotation.from_rotvec(rotvecs).as_matrix()
    from_matrix = np.asarray(rot.matrix_to_quaternion(jnp.asarray(matrices)))
    np.testing.assert_allclose(np.abs(np.sum(from_matrix * q_wxyz, -1)), 1.0, atol=1e-12)
    assert np.all(from_matrix[:, 0] >= 0)
    np.testing.assert_allclose(np.asarray(rot.quaternion_to_matrix(jnp.asarray(q_wxyz))), matrices, atol=1e-12)
    back = np.array(rot.quaternion_to_axis_angle(jnp.asarray(q_wxyz)))
    np.testing.assert_allclose(Rotation.from_rotvec(back).as_matrix(), matrices, atol=1e-12)


def test_quaternion_multiply_composes(x64):
    r1, r2 = Rotation.random(2, random_state=3)
    q = lambda r: jnp.asarray(np.roll(r.as_quat(), 1))  # noqa: E731  (x,y,z,w) -> (w,x,y,z)
    product = rot.quaternion_to_matrix(rot.quaternion_multiply(q(r1), q(r2)))
    np.testing.assert_allclose(np.asarray(product), (r1 * r2).as_matrix(), atol=1e-12)


def test_rotation_6d_round_trip_and_gram_schmidt(rotvecs, x64):
    matrices = jnp.asarray(Rotation.from_rotvec(rotvecs).as_matrix())
    six = rot.matrix_to_rotation_6d(matrices)
    np.testing.assert_allclose(np.asarray(six[:, :3]), np.asarray(matrices[:, :, 0]))
    np.testing.assert_allclose(np.asarray(rot.rotation_6d_to_matrix(six)), np.asarray(matrices), atol=1e-12)
    noisy = six * 3.0 + 0.05 * jnp.asarray(np.random.default_rng(0).normal(size=six.shape))
    r = np.asarray(rot.rotation_6d_to_matrix(noisy))
    np.testing.assert_allclose(r @ np.swapaxes(r, -1, -2), np.broadcast_to(np.eye(3), r.shape), atol=1e-12)
    np.testing.assert_allclose(np.linalg.det(r), 1.0, atol=1e-12)


def test_geodesic_angle(rotvecs, x64):
    r1 = Rotation.random(len(rotvecs), random_state=5)
    r2 = r1 * Rotation.from_rotvec(rotvecs)
    ours = np.array(rot.geodesic_angle(jnp.asarray(r1.as_matrix()), jnp.asarray(r2.as_matrix())))
    np.testing.assert_allclose(ours, np.linalg.norm(rotvecs, axis=-1), atol=1e-7)


@pytest.mark.parametrize("angle", [0.0, 1e-8, 1e-3, 0.5, 2.0, np.pi - 1e-3])
def test_axis_angle_to_matrix_jacobians(angle, x64):
    axis = np.array([0.3, -0.5, 0.8]) / np.linalg.norm([0.3, -0.5, 0.8])
    x = jnp.asarray(axis * angle)
    f = rot.axis_angle_to_matrix
    jf = np.asarray(jax.jacfwd(f)(x)).reshape(9, 3)
    jr = np.asarray(jax.jacrev(f)(x)).reshape(9, 3)
    fd = finite_difference_jacobian(f, np.asarray(x))
    assert np.all(np.isfinite(jf))
    np.testing.assert_allclose(jf, jr, atol=1e-12)
    np.testing.assert_allclose(jf, fd, atol=1e-7)
    if angle == 0.0:  # d R / d w at 0 is the generator: d(R)/dw_k = [e_k]_x
        expected = np.stack([np.asarray(rot.skew(jnp.asarray(e))) for e in np.eye(3)], -1).reshape(9, 3)
        np.testing.assert_allclose(jf, expected, atol=1e-15)


def test_left_jacobian_turns_the_rotation_as_its_derivative_does(rotvecs, x64):
    # dR/dw_c = [J_l e_c]x R, checked against the autodiff derivative of Rodrigues' formula
    w = jnp.asarray(rotvecs)
    dR = jax.vmap(jax.jacfwd(rot.axis_angle_to_matrix))(w)  # (n, 3, 3, c)
    J = rot.axis_angle_left_jacobian(w)
    turned = jnp.einsum("ncab,nbd->nadc", rot.skew(jnp.swapaxes(J, 1, 2)), rot.axis_angle_to_matrix(w))
    np.testing.assert_allclose(turned, dR, atol=1e-10)
    np.testing.assert_allclose(rot.axis_angle_left_jacobian(jnp.zeros(3)), np.eye(3), atol=0)
    with jax.enable_x64(False):
        w32 = jnp.asarray(rotvecs, jnp.float32)
        np.testing.assert_allclose(rot.axis_angle_left_jacobian(w32), J, atol=2e-6)


@pytest.mark.parametrize("angle", [0.0, 1e-8, 1e-3, 0.5, 2.0, np.pi - 1e-2])
def test_matrix_to_axis_angle_jacobians(angle, x64):
    axis = np.array([-0.6, 0.2, 0.7]) / np.linalg.norm([-0.6, 0.2, 0.7])
    w0 = jnp.asarray(axis * angle)
    f = lambda w: rot.matrix_to_axis_angle(rot.axis_angle_to_matrix(w))  # noqa: E731 (identity map)
    jf = np.asarray(jax.jacfwd(f)(w0))
    jr = np.asarray(jax.jacrev(f)(w0))
    np.testing.assert_allclose(jf, np.eye(3), atol=1e-7)
    np.testing.assert_allclose(jr, np.eye(3), atol=1e-7)


def test_quaternion_and_6d_gradients_finite_at_identity():
    for f in (
        lambda w: rot.axis_angle_to_quaternion(w),
        lambda w: rot.quaternion_to_axis_angle(rot.axis_angle_to_quaternion(w)),
        lambda w: rot.rotation_6d_to_matrix(rot.matrix_to_rotation_6d(rot.axis_angle_to_matrix(w))),
        lambda w: rot.geodesic_angle(jnp.eye(3), rot.axis_angle_to_matrix(w)),
    ):
        for jac in (jax.jacfwd, jax.jacrev):
            assert np.all(np.isfinite(np.asarray(jax.jit(jac(f))(jnp.zeros(3)))))  # one program each


def test_jit_vmap_agree_with_plain_calls():
    w = jnp.asarray(Rotation.random(7, random_state=2).as_rotvec(), jnp.float32)
    batched = rot.axis_angle_to_matrix(w)
    np.testing.assert_allclose(np.asarray(jax.jit(rot.axis_angle_to_matrix)(w)), np.asarray(batched), atol=1e-6)
    np.testing.assert_allclose(np.asarray(jax.vmap(rot.axis_angle_to_matrix)(w)), np.asarray(batched), atol=1e-6)
    deep = jnp.reshape(jnp.tile(w[:6], (1, 1)), (3, 1, 2, 3))
    assert rot.matrix_to_axis_angle(rot.axis_angle_to_matrix(deep)).shape == (3, 1, 2, 3)


DEGENERATE_6D = {
    "zero": [0.0, 0.0, 0.0, 0.0, 0.0, 0.0],
    "first_zero": [0.0, 0.0, 0.0, 0.3, -1.0, 0.2],
    "first_tiny": [1e-30, 0.0, 0.0, 0.0, 1.0, 0.0],
    "second_zero": [0.3, -0.2, 0.9, 0.0, 0.0, 0.0],
    "parallel": [0.3, -0.2, 0.9, 0.6, -0.4, 1.8],
    "antiparallel": [0.0, 1.0, 0.0, 0.0, -5.0, 0.0],
    "nearly_parallel": [1.0, 0.0, 0.0, 1.0, 1e-9, 0.0],
}


@pytest.mark.parametrize("dtype_x64", [False, True])
@pytest.mark.parametrize("name", sorted(DEGENERATE_6D))
def test_rotation_6d_degenerate_inputs_give_rotations_with_finite_gradients(name, dtype_x64, request):
    if dtype_x64:
        request.getfixturevalue("x64")
    x = jnp.asarray(DEGENERATE_6D[name], jnp.result_type(float))
    r = np.asarray(rot.rotation_6d_to_matrix(x))
    assert np.all(np.isfinite(r)), name
    np.testing.assert_allclose(r.T @ r, np.eye(3), atol=1e-6)
    assert np.linalg.det(r) == pytest.approx(1.0, abs=1e-6)
    a1 = np.asarray(DEGENERATE_6D[name][:3])
    if np.linalg.norm(a1) > 1e-3:  # a usable first column is kept
        np.testing.assert_allclose(r[:, 0], a1 / np.linalg.norm(a1), atol=1e-6)
    for jac in (jax.jacfwd, jax.jacrev):
        assert np.all(np.isfinite(np.asarray(jac(rot.rotation_6d_to_matrix)(x)))), (name, jac.__name__)
    loss = lambda v: jnp.sum(rot.rotation_6d_to_matrix(v) * jnp.arange(9.0, dtype=v.dtype).reshape(3, 3))  # noqa: E731
    assert np.all(np.isfinite(np.asarray(jax.grad(loss)(x)))), name
    # batched (a network head's output): the degenerate rows do not affect the others
    batch = jnp.stack([x, jnp.asarray([1.0, 0.0, 0.0, 0.0, 1.0, 0.0], x.dtype)])
    assert np.all(np.isfinite(np.asarray(jax.grad(lambda b: jnp.sum(jax.vmap(loss)(b)))(batch))))


def test_rotation_6d_unchanged_on_normal_inputs(x64):
    rng = np.random.default_rng(4)
    six = rng.normal(size=(50, 6))
    a1, a2 = six[:, :3], six[:, 3:]
    b1 = a1 / np.linalg.norm(a1, axis=-1, keepdims=True)
    u2 = a2 - np.sum(b1 * a2, axis=-1, keepdims=True) * b1
    b2 = u2 / np.linalg.norm(u2, axis=-1, keepdims=True)
    reference = np.stack([b1, b2, np.cross(b1, b2)], axis=-1)
    np.testing.assert_allclose(np.asarray(rot.rotation_6d_to_matrix(jnp.asarray(six))), reference, atol=1e-14)
    f = lambda v: rot.rotation_6d_to_matrix(v).reshape(-1)  # noqa: E731
    jf = np.asarray(jax.jacfwd(f)(jnp.asarray(six[0])))
    np.testing.assert_allclose(jf, np.asarray(jax.jacrev(f)(jnp.asarray(six[0]))), atol=1e-12)
    np.testing.assert_allclose(jf, finite_difference_jacobian(f, six[0]), rtol=1e-6, atol=1e-8)
