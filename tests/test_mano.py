import functools
import os
import pickle
import subprocess
import sys
import types

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest
import scipy.sparse
from scipy.spatial.transform import Rotation

from jax.flatten_util import ravel_pytree

from esther_jax import mano
from esther_jax.rotations import axis_angle_to_matrix

from .helpers import finite_difference_jacobian, tree_allclose


@pytest.fixture(scope="module")
def right():
    return mano.load_builtin("right")


@pytest.fixture(scope="module")
def left():
    return mano.load_builtin("left")


def random_params(seed: int, dtype=jnp.float32, pose_scale=0.4) -> mano.ManoParams:
    rng = np.random.default_rng(seed)
    return mano.ManoParams(
        global_orient=jnp.asarray(rng.normal(size=3), dtype),
        hand_pose=jnp.asarray(rng.normal(size=(15, 3)) * pose_scale, dtype),
        betas=jnp.asarray(rng.normal(size=10), dtype),
        transl=jnp.asarray(rng.normal(size=3) * 0.2, dtype),
    )


def stack(params_list):
    return jax.tree.map(lambda *x: jnp.stack(x), *params_list)


def test_zero_pose_and_betas_give_the_template(right):
    params = mano.ManoParams.zeros()
    params = eqx.tree_at(lambda p: p.transl, params, right.joint_template[0])
    out = mano.forward(right, params)
    np.testing.assert_allclose(np.asarray(out.vertices), np.asarray(right.v_template), atol=1e-7)
    np.testing.assert_allclose(np.asarray(out.transforms[:, :3, 3]), np.asarray(right.joint_template), atol=1e-7)
    np.testing.assert_allclose(np.asarray(out.transforms[:, :3, :3]), np.broadcast_to(np.eye(3), (16, 3, 3)), atol=1e-7)


@pytest.mark.parametrize("seed", range(4))
def test_wrist_stays_at_transl(right, seed):
    params = random_params(seed)
    out = mano.forward(right, params)
    np.testing.assert_allclose(np.asarray(out.joints[0]), np.asarray(params.transl), atol=1e-6)


@pytest.mark.parametrize("seed", range(4))
def test_joints_only_path_equals_full_path(right, left, seed):
    for model in (right, left):
        params = random_params(seed, pose_scale=0.8)
        full = mano.forward(model, params).joints
        np.testing.assert_allclose(np.asarray(mano.forward_joints(model, params)), np.asarray(full), atol=2e-7)


def test_keypoints_are_fk_joints_and_tip_vertices(right):
    params = random_params(1)
    out = mano.forward(right, params)
    mano16 = np.asarray(out.transforms[:, :3, 3])
    tips = np.asarray(out.vertices)[np.asarray(right.fingertip_ids)]
    both = np.concatenate([mano16, tips])
    np.testing.assert_allclose(np.asarray(out.joints), both[list(mano.KEYPOINT_FROM_MANO)], atol=1e-7)
    assert mano.KEYPOINT_NAMES[4] == "thumb_tip" and mano.KEYPOINT_NAMES[8] == "index_tip"


def test_global_orient_rotates_the_hand_about_the_wrist(right):
    params = random_params(2)
    rest_orient = eqx.tree_at(lambda p: p.global_orient, params, jnp.zeros(3))
    a = mano.forward(right, rest_orient).vertices - params.transl[None]
    b = mano.forward(right, params).vertices - params.transl[None]
    R = axis_angle_to_matrix(params.global_orient)
    np.testing.assert_allclose(np.asarray(b), np.asarray(a @ R.T), atol=1e-6)


def test_jit_vmap_grad_agree_with_plain_calls(right):
    batch = [random_params(s) for s in range(5)]
    plain = np.stack([np.asarray(mano.forward(right, p).vertices) for p in batch])
    jitted = np.stack([np.asarray(eqx.filter_jit(mano.forward)(right, p).vertices) for p in batch])
    vmapped = np.asarray(jax.vmap(mano.forward, in_axes=(None, 0))(right, stack(batch)).vertices)
    np.testing.assert_allclose(jitted, plain, atol=1e-6)
    np.testing.assert_allclose(vmapped, plain, atol=1e-6)

    def loss(p):
        return jnp.sum(mano.forward_joints(right, p) ** 2)

    g_plain = jax.grad(loss)(batch[0])
    g_jit = eqx.filter_jit(jax.grad(loss))(batch[0])
    g_vmap = jax.vmap(jax.grad(loss))(stack(batch))
    assert tree_allclose(g_plain, g_jit, atol=1e-5)
    assert tree_allclose(g_plain, jax.tree.map(lambda x: x[0], g_vmap), atol=1e-5)


def test_no_retracing_for_new_values(right):
    f = eqx.filter_jit(eqx.debug.assert_max_traces(mano.forward_joints, max_traces=1))
    for s in range(3):
        f(right, random_params(s))
    f(mano.load_builtin("left"), random_params(9))  # handedness is data: same graph


def test_pose_prior_limit_weight_is_traced(right):
    """Another joint-limit weight is data, not a new program; the default keeps the numbers
    of the Python float it was (the hinges are 10 times the excess over the limits)."""
    import dataclasses

    prior = mano.PosePrior.from_model(right)
    pose = jnp.zeros((15, 3)).at[1].set(jnp.asarray([0.0, 0.0, -1.5]))  # index PIP hyper-extended: a hinge active
    angles = mano.hand_pose_to_anatomical(pose, prior.frames)
    excess = (jnp.maximum(angles - prior.upper, 0.0) + jnp.maximum(prior.lower - angles, 0.0)).reshape(45)
    residuals = eqx.filter_jit(eqx.debug.assert_max_traces(lambda p, x: (p(x), p.normal_equations(x)), max_traces=1))
    (r10, (g10, _)), (r20, (g20, _)) = residuals(prior, pose), residuals(dataclasses.replace(prior, limit_weight=20.0), pose)
    assert float(jnp.max(excess)) > 0.1 and r10.dtype == pose.dtype
    np.testing.assert_array_equal(np.asarray(r10[45:]), np.asarray(10.0 * excess))
    np.testing.assert_array_equal(np.asarray(r20[45:]), np.asarray(20.0 * excess))
    np.testing.assert_array_equal(np.asarray(r20[:45]), np.asarray(r10[:45]))
    assert not np.allclose(np.asarray(g10), np.asarray(g20))


@pytest.mark.parametrize("at_zero", [True, False])
def test_jacobians_match_finite_differences(x64, at_zero):
    model = mano.load_builtin("right")
    base = mano.ManoParams.zeros(dtype=jnp.float64) if at_zero else random_params(3, jnp.float64)
    flat, unravel = ravel_pytree(base)

    @jax.jit
    def f(x):
        return mano.forward_joints(model, unravel(x)).reshape(-1)

    jf = np.asarray(jax.jit(jax.jacfwd(f))(flat))
    jr = np.asarray(jax.jit(jax.jacrev(f))(flat))
    fd = finite_difference_jacobian(f, np.asarray(flat), h=1e-6)
    assert np.all(np.isfinite(jf))
    np.testing.assert_allclose(jf, jr, atol=1e-10)
    np.testing.assert_allclose(jf, fd, atol=1e-7)
    if at_zero:  # a fit started at the flat hand must be able to move every finger joint
        pose_block = jf[:, 3:48].reshape(21, 3, 15, 3)
        assert np.all(np.abs(pose_block).sum(axis=(0, 1, 3)) > 1e-3)


def test_analytic_joints_jacobian_equals_autodiff_of_the_full_mesh(x64):
    # `forward` skins every vertex with plain autodiff: an independent path to the same joints
    right = mano.load_builtin("right")
    rng = np.random.default_rng(5)
    every_corrective = right.replace(posedirs=jnp.asarray(rng.normal(size=right.posedirs.shape) * 1e-3))
    none = right.replace(posedirs=jnp.zeros_like(right.posedirs))
    reference = jax.jit(lambda m, p: jax.jacfwd(lambda q: mano.forward(m, q).joints)(p))
    with_rule = jax.jit(lambda m, p: jax.jacfwd(lambda q: mano.forward_joints(m, q, analytic_jvp=True))(p))
    for model, k in ((right, 10), (every_corrective, 6), (none, 10)):
        params = eqx.tree_at(lambda p: p.betas, random_params(6, jnp.float64), replace_fn=lambda b: b[:k])
        expected = reference(model, params)
        assert tree_allclose(with_rule(model, params), expected, rtol=0, atol=1e-12)
    jac = jax.jit(mano.joints_jacobian)(model, params)  # the public layout: (21, 3, 16 joints, 3)
    np.testing.assert_allclose(jac.pose[:, :, 1:], expected.hand_pose, atol=1e-12)
    np.testing.assert_allclose(jac.betas, expected.betas, atol=1e-12)
    # reverse mode transposes the rule; derivatives in the model's arrays (a learned hand
    # model) take the autodiff path
    params = random_params(7, jnp.float64)
    rev = jax.jit(jax.jacrev(lambda p: mano.forward_joints(right, p, analytic_jvp=True)))(params)
    assert tree_allclose(rev, reference(right, params), rtol=0, atol=1e-12)

    def model_gradient(analytic_jvp):
        loss = lambda m: jnp.sum(jnp.sin(mano.forward_joints(m, params, analytic_jvp=analytic_jvp)))  # noqa: E731
        return eqx.filter_jit(eqx.filter_grad(loss))(right)

    by_rule, by_autodiff = model_gradient(True), model_gradient(False)
    for name in ("v_template", "shapedirs", "weights", "pose_basis", "joint_template", "joint_shapedirs"):
        np.testing.assert_allclose(getattr(by_rule, name), getattr(by_autodiff, name), atol=1e-12, err_msg=name)
    assert float(jnp.abs(by_rule.joint_shapedirs).max()) > 0


def test_float64_mode_matches_float32(x64):
    model64 = mano.load_builtin("right")
    assert model64.v_template.dtype == jnp.float64
    params64 = random_params(4, jnp.float64)
    out64 = mano.forward(model64, params64)
    assert out64.vertices.dtype == jnp.float64
    with jax.enable_x64(False):
        model32 = mano.load_builtin("right")
        out32 = mano.forward(model32, random_params(4, jnp.float32))
    np.testing.assert_allclose(np.asarray(out32.vertices), np.asarray(out64.vertices), atol=2e-6)


def test_mirror_twice_is_identity_and_mirrored_right_is_left(right, left):
    params = random_params(5)
    assert tree_allclose(mano.mirror_params(mano.mirror_params(params)), params, atol=0)
    points = jnp.asarray(np.random.default_rng(0).normal(size=(7, 3)), jnp.float32)
    np.testing.assert_array_equal(np.asarray(mano.mirror_points(mano.mirror_points(points))), np.asarray(points))
    out_right = mano.forward(right, params)
    out_left = mano.forward(left, mano.mirror_params(params))
    np.testing.assert_allclose(np.asarray(out_left.vertices), np.asarray(mano.mirror_points(out_right.vertices)), atol=1e-6)
    np.testing.assert_allclose(np.asarray(out_left.joints), np.asarray(mano.mirror_points(out_right.joints)), atol=1e-6)
    assert right.side == "right" and left.side == "left"


def test_left_mesh_is_outward_oriented(left, right):
    for model in (left, right):
        mesh = mano.export.to_trimesh(model.v_template, model.faces)
        assert mesh.is_watertight and mesh.is_winding_consistent and mesh.volume > 0


@pytest.mark.parametrize("flat_hand_mean", [True, False])
def test_pca_round_trips(right, flat_hand_mean):
    rng = np.random.default_rng(0)
    coeffs = jnp.asarray(rng.normal(size=45), jnp.float32)
    pose = mano.pca_to_hand_pose(right, coeffs, flat_hand_mean=flat_hand_mean)
    back, residual = mano.hand_pose_to_pca(right, pose, 45, flat_hand_mean=flat_hand_mean)
    np.testing.assert_allclose(np.asarray(back), np.asarray(coeffs), atol=2e-3)
    assert float(residual) < 1e-5
    few = jnp.asarray(rng.normal(size=6), jnp.float32)
    pose6 = mano.pca_to_hand_pose(right, few, flat_hand_mean=flat_hand_mean)
    back6, residual6 = mano.hand_pose_to_pca(right, pose6, 6, flat_hand_mean=flat_hand_mean)
    np.testing.assert_allclose(np.asarray(back6), np.asarray(few), atol=1e-4)
    assert float(residual6) < 1e-5
    # a random pose is not in the span of 6 components: the residual says so
    _, residual_random = mano.hand_pose_to_pca(right, jnp.asarray(rng.normal(size=(15, 3)), jnp.float32), 6, flat_hand_mean=flat_hand_mean)
    assert float(residual_random) > 0.1
    zero = mano.pca_to_hand_pose(right, jnp.zeros(6), flat_hand_mean=flat_hand_mean)
    expected = np.zeros(45) if flat_hand_mean else np.asarray(right.hands_mean)
    np.testing.assert_allclose(np.asarray(zero).reshape(45), expected, atol=1e-7)


def test_pca_rejects_bad_component_counts(right):
    with pytest.raises(ValueError, match="num_components"):
        mano.hand_pose_to_pca(right, jnp.zeros((15, 3)), 46, flat_hand_mean=True)


def test_smplx_convention_round_trip_and_frame_change(right):
    params = random_params(6)
    go, transl_smplx = mano.to_smplx(right, params)
    back = mano.from_smplx(right, go, transl_smplx, params.hand_pose, params.betas)
    assert tree_allclose(back, params, atol=1e-6)
    # smplx places vertices at LBS(pose about J0(beta)) + transl_smplx
    rest = mano.rest_joints(right, params.betas)
    np.testing.assert_allclose(np.asarray(rest[0] + transl_smplx), np.asarray(params.transl), atol=1e-6)
    # changing frames with our wrist convention is a rigid motion of the output
    T = np.eye(4)
    T[:3, :3] = Rotation.from_rotvec([0.3, -1.2, 0.5]).as_matrix()
    T[:3, 3] = [0.1, -0.2, 0.4]
    T = jnp.asarray(T, jnp.float32)
    moved = mano.forward(right, mano.transform_params(T, params)).vertices
    expected = mano.forward(right, params).vertices @ T[:3, :3].T + T[None, :3, 3]
    np.testing.assert_allclose(np.asarray(moved), np.asarray(expected), atol=2e-6)


@pytest.mark.parametrize(
    "field, shape",
    [("global_orient", (4,)), ("hand_pose", (16, 3)), ("hand_pose", (45,)), ("transl", (1, 3)), ("betas", (11,))],
)
def test_wrong_shapes_are_named(right, field, shape):
    params = eqx.tree_at(lambda p: getattr(p, field), mano.ManoParams.zeros(), jnp.zeros(shape))
    with pytest.raises(ValueError, match=field):
        mano.forward(right, params)


def test_nan_parameters_are_named(right):
    """Concrete parameters are checked eagerly (a ValueError naming the fields); traced
    ones when the program runs (eqx.filter_jit shows the message plainly)."""
    params = eqx.tree_at(lambda p: p.hand_pose, mano.ManoParams.zeros(), jnp.full((15, 3), jnp.nan))
    for fn in (mano.forward, mano.forward_joints):
        with pytest.raises(ValueError, match=r"ManoParams contains NaN or infinite values \(in hand_pose\)"):
            fn(right, params)
    with pytest.raises(Exception, match="ManoParams contains NaN or infinite"):
        jax.block_until_ready(eqx.filter_jit(mano.forward_joints)(right, params))


def test_builtin_model_properties(right):
    V = right.num_vertices
    assert 600 <= V <= 2000
    mesh = mano.export.to_trimesh(right.v_template, right.faces)
    assert mesh.is_watertight and mesh.euler_number == 2
    assert tuple(np.asarray(right.fingertip_ids)) == mano.FINGERTIP_IDS_SMPLX
    joints = np.asarray(right.joint_template)
    tips = np.asarray(right.v_template)[np.asarray(right.fingertip_ids)]
    assert 0.18 <= np.linalg.norm(tips[2] - joints[0]) <= 0.19
    # manopth's ids are fingertip vertices too (within 6 mm of the smplx apex)
    for side in ("right", "left"):
        near = np.asarray(right.v_template)[list(mano.FINGERTIP_IDS_MANOPTH[side])]
        assert np.all(np.linalg.norm(near - tips, axis=1) < 0.006)
    w = np.asarray(right.weights)
    assert np.all(w >= 0) and np.allclose(w.sum(axis=1), 1.0, atol=1e-6)
    # MANO frame: fingers along -x, thumb on +z, back of the hand +y
    assert tips[2, 0] < joints[0, 0] - 0.15 and tips[0, 2] > joints[4, 2] + 0.04
    # regressor reproduces the joints for any betas: J(beta) equals the regression of V(beta)
    betas = jnp.asarray(np.random.default_rng(0).normal(size=10), jnp.float32)
    v_shaped = right.v_template + jnp.einsum("vcb,b->vc", right.shapedirs, betas)
    np.testing.assert_allclose(np.asarray(right.J_regressor @ v_shaped), np.asarray(mano.rest_joints(right, betas)), atol=1e-6)


def test_builtin_shape_space_is_realistic(right):
    betas = np.random.default_rng(0).normal(size=(2000, 10))
    joints0 = np.asarray(right.joint_template)
    tips = lambda b: np.asarray(right.v_template)[np.asarray(right.fingertip_ids)] + np.einsum(  # noqa: E731
        "tcb,nb->ntc", np.asarray(right.shapedirs)[np.asarray(right.fingertip_ids)], b
    )
    wrist = joints0[0] + np.einsum("cb,nb->nc", np.asarray(right.joint_shapedirs)[0], betas)
    length = np.linalg.norm(tips(betas)[:, 2] - wrist, axis=1)
    only_size = np.zeros_like(betas)
    only_size[:, 0] = betas[:, 0]
    wrist0 = joints0[0] + np.einsum("cb,nb->nc", np.asarray(right.joint_shapedirs)[0], only_size)
    size_length = np.linalg.norm(tips(only_size)[:, 2] - wrist0, axis=1)
    assert 0.06 <= size_length.std() / size_length.mean() <= 0.08
    assert 0.06 <= length.std() / length.mean() <= 0.12
    # every direction moves the mesh, none is a duplicate of another
    dirs = np.asarray(right.shapedirs).reshape(-1, 10)
    corr = np.corrcoef(dirs.T)
    assert np.all(np.linalg.norm(dirs, axis=0) > 1e-3) and np.all(np.abs(corr[np.triu_indices(10, 1)]) < 0.95)


@pytest.mark.parametrize("joint", range(1, 16))
def test_every_joint_bends_cleanly(right, joint):
    """90 degrees of flexion at one joint: volume within 3%, no edge collapses, and at
    most 4 of the 2816 faces turn inside out (only in the crease), measured against
    rest normals carried by each face's dominant joint."""
    frames = mano.anatomical_frames(right.joint_template, right.v_template[right.fingertip_ids], right.is_right)
    angles = np.zeros((15, 3), np.float32)
    angles[joint - 1, 0] = np.pi / 2
    hand_pose = mano.anatomical_to_hand_pose(jnp.asarray(angles), frames)
    out = mano.forward(right, eqx.tree_at(lambda p: p.hand_pose, mano.ManoParams.zeros(), hand_pose))
    bent = np.asarray(out.vertices)
    rest = np.asarray(mano.forward(right, mano.ManoParams.zeros()).vertices)
    faces = np.asarray(right.faces)

    def normals(v):
        t = v[faces]
        n = np.cross(t[:, 1] - t[:, 0], t[:, 2] - t[:, 0])
        return n / np.linalg.norm(n, axis=1, keepdims=True)

    dominant = np.argmax(np.asarray(right.weights)[faces].sum(axis=1), axis=1)
    carried = np.einsum("fij,fj->fi", np.asarray(out.transforms)[dominant, :3, :3], normals(rest))
    assert np.sum(np.sum(normals(bent) * carried, axis=1) < 0) <= 4
    edges = np.concatenate([faces[:, [0, 1]], faces[:, [1, 2]], faces[:, [2, 0]]])
    ratio = np.linalg.norm(bent[edges[:, 0]] - bent[edges[:, 1]], axis=1) / np.linalg.norm(
        rest[edges[:, 0]] - rest[edges[:, 1]], axis=1
    )
    assert ratio.min() > 0.1
    volume_ratio = mano.export.to_trimesh(bent, faces).volume / mano.export.to_trimesh(rest, faces).volume
    assert abs(volume_ratio - 1.0) < 0.03


def test_replace_recomputes_derived_fields(right):
    moved = right.replace(v_template=right.v_template + 0.01)
    np.testing.assert_allclose(np.asarray(moved.joint_template), np.asarray(right.joint_template) + 0.01, atol=1e-6)
    assert right.replace(posedirs=jnp.zeros_like(right.posedirs)).pose_feature_ids == ()
    with pytest.raises(TypeError, match="unknown"):
        right.replace(colour=1)


def test_pose_blend_shapes_restore_volume(right):
    frames = mano.anatomical_frames(right.joint_template, right.v_template[right.fingertip_ids], right.is_right)
    angles = np.zeros((15, 3), np.float32)
    angles[[1, 4, 10, 7], 0] = np.deg2rad(100.0)  # PIP joints
    params = eqx.tree_at(lambda p: p.hand_pose, mano.ManoParams.zeros(), mano.anatomical_to_hand_pose(jnp.asarray(angles), frames))
    no_correctives = right.replace(posedirs=jnp.zeros_like(right.posedirs))
    faces = np.asarray(right.faces)
    rest = mano.export.to_trimesh(mano.forward(right, mano.ManoParams.zeros()).vertices, faces).volume
    with_c = mano.export.to_trimesh(mano.forward(right, params).vertices, faces).volume
    without = mano.export.to_trimesh(mano.forward(no_correctives, params).vertices, faces).volume
    assert abs(with_c - rest) < abs(without - rest)


def test_pca_space_and_limits(right):
    comps = np.asarray(right.hands_components, np.float64)
    norms = np.linalg.norm(comps, axis=1)
    assert np.all(np.diff(norms) <= 1e-6)  # sorted by standard deviation
    unit = comps / norms[:, None]
    np.testing.assert_allclose(unit @ unit.T, np.eye(45), atol=1e-4)
    assert mano.JOINT_LIMITS.shape == (15, 3, 2) and np.all(mano.JOINT_LIMITS[..., 0] < mano.JOINT_LIMITS[..., 1])
    # the mean pose lies inside the limits and curls the fingers (natural poses are not flat)
    frames = mano.anatomical_frames(right.joint_template, right.v_template[right.fingertip_ids], right.is_right)
    mean_angles = np.asarray(mano.hand_pose_to_anatomical(right.hands_mean.reshape(15, 3), frames))
    assert np.all(mean_angles >= mano.JOINT_LIMITS[..., 0]) and np.all(mean_angles <= mano.JOINT_LIMITS[..., 1])
    assert np.all(mean_angles[[0, 3, 6, 9], 0] > np.deg2rad(10))


def test_anatomical_angles_are_mirror_invariant(right, left):
    hand_pose = random_params(7).hand_pose
    f_r = mano.anatomical_frames(right.joint_template, right.v_template[right.fingertip_ids], right.is_right)
    f_l = mano.anatomical_frames(left.joint_template, left.v_template[left.fingertip_ids], left.is_right)
    mirrored = mano.mirror_params(mano.ManoParams(jnp.zeros(3), hand_pose, jnp.zeros(10), jnp.zeros(3))).hand_pose
    np.testing.assert_allclose(
        np.asarray(mano.hand_pose_to_anatomical(hand_pose, f_r)), np.asarray(mano.hand_pose_to_anatomical(mirrored, f_l)), atol=1e-6
    )


def test_generator_reproduces_the_shipped_model():
    from esther_jax.mano import builtin_generator

    fresh = builtin_generator.generate()
    with np.load(builtin_generator.ASSET_PATH) as shipped:
        for key in ("v_template", "shapedirs", "posedirs", "J_regressor", "weights", "hands_mean"):
            np.testing.assert_allclose(shipped[key], fresh[key].astype(np.float32), atol=2e-6, err_msg=key)
        np.testing.assert_array_equal(shipped["f"], fresh["f"])
        np.testing.assert_allclose(np.abs(shipped["hands_components"]), np.abs(fresh["hands_components"]), atol=1e-4)


@pytest.mark.parametrize(
    "grasp, palmar_m, gap_m",
    [("fist", 0.016, 0.0), ("point", 0.016, 0.0), ("pinch", 0.0, 0.012), ("tripod", 0.0, 0.012), ("power_grasp", 0.035, 0.0)],
)
def test_grasp_archetypes_make_their_thumb_contact(right, grasp, palmar_m, gap_m):
    """A grasp archetype's thumb tip rests where the grasp puts it: on the curled fingers'
    middle phalanges (fist, point; `palmar_m` out of the palm, a finger's and the thumb's
    half-thickness), at the index tip (pinch) or between the index and middle tips
    (tripod) with the pads' gap, opposite the index round a held object (power grasp)."""
    from esther_jax.mano import builtin_generator

    frames = mano.anatomical_frames(right.joint_template, right.v_template[right.fingertip_ids], right.is_right)
    hand_pose = mano.anatomical_to_hand_pose(jnp.asarray(builtin_generator.archetype_angles(grasp)), frames)
    j = np.asarray(mano.forward_joints(right, mano.ManoParams(jnp.zeros(3), hand_pose, jnp.zeros(10), jnp.zeros(3))), np.float64)
    dorsal = np.cross(j[17] - j[0], j[5] - j[0])
    dorsal /= np.linalg.norm(dorsal)
    middle_phalanx = lambda pip: 0.5 * (j[pip] + j[pip + 1])  # noqa: E731
    finger_point = {"fist": 0.5 * (middle_phalanx(6) + middle_phalanx(10)), "point": middle_phalanx(10), "pinch": j[8],
                    "tripod": 0.5 * (j[8] + j[12]), "power_grasp": middle_phalanx(6)}[grasp]  # fmt: skip
    contact = finger_point - palmar_m * dorsal
    assert abs(np.linalg.norm(j[4] - contact) - gap_m) < 0.005


# ----------------------------------------------------------------------------- pickles


def test_pickle_round_trip(right, tmp_path):
    path = mano.save_mano_pkl(right, tmp_path / "MANO_RIGHT.pkl")
    loaded = mano.load_mano_pkl(path)
    params = random_params(8)
    np.testing.assert_allclose(np.asarray(mano.forward(loaded, params).vertices), np.asarray(mano.forward(right, params).vertices), atol=1e-6)
    manopth = mano.load_mano_pkl(path, fingertips="manopth")
    assert tuple(np.asarray(manopth.fingertip_ids)) == mano.FINGERTIP_IDS_MANOPTH["right"]


def test_left_shapedirs_bug_is_fixed_and_recorded(left, tmp_path):
    buggy = left.replace(shapedirs=left.shapedirs * jnp.asarray([-1.0, 1.0, 1.0])[None, :, None])
    path = mano.save_mano_pkl(buggy, tmp_path / "MANO_LEFT.pkl")
    fixed = mano.load_mano_pkl(path)
    assert fixed.side == "left" and bool(fixed.left_shapedirs_fixed)
    np.testing.assert_allclose(np.asarray(fixed.shapedirs), np.asarray(left.shapedirs), atol=1e-7)
    clean_path = mano.save_mano_pkl(left, tmp_path / "clean_MANO_LEFT.pkl")
    assert not bool(mano.load_mano_pkl(clean_path).left_shapedirs_fixed)
    assert not bool(mano.load_mano_pkl(path, fix_left_shapedirs=False).left_shapedirs_fixed)


def test_chumpy_pickles_load_without_chumpy(right, tmp_path, monkeypatch):
    """A pickle whose arrays are chumpy `Ch` objects loads with chumpy absent."""
    fake = types.ModuleType("chumpy.ch")

    class Ch:
        def __init__(self, x):
            self.x = x

        def __reduce__(self):
            return (Ch, (), {"x": self.x, "_dirty_vars": set()})

    Ch.__module__, Ch.__qualname__ = "chumpy.ch", "Ch"
    fake.Ch = Ch
    monkeypatch.setitem(sys.modules, "chumpy", types.ModuleType("chumpy"))
    monkeypatch.setitem(sys.modules, "chumpy.ch", fake)
    path = mano.save_mano_pkl(right, tmp_path / "MANO_RIGHT.pkl")
    with open(path, "rb") as f:
        data = pickle.load(f)
    data["shapedirs"] = Ch(data["shapedirs"])
    data["v_template"] = Ch(data["v_template"])
    with open(path, "wb") as f:
        pickle.dump(data, f, protocol=2)
    monkeypatch.delitem(sys.modules, "chumpy.ch")
    monkeypatch.delitem(sys.modules, "chumpy")
    loaded = mano.load_mano_pkl(path)
    np.testing.assert_allclose(np.asarray(loaded.shapedirs), np.asarray(right.shapedirs), atol=1e-7)


def test_bad_files_say_what_is_wrong(right, tmp_path):
    good = mano.save_mano_pkl(right, tmp_path / "MANO_RIGHT.pkl")
    truncated = tmp_path / "truncated.pkl"
    truncated.write_bytes(good.read_bytes()[: good.stat().st_size // 2])
    with pytest.raises(mano.ManoFileError, match="truncated"):
        mano.load_mano_pkl(truncated)
    text = tmp_path / "notes.pkl"
    text.write_text("these are not the hands you are looking for")
    with pytest.raises(mano.ManoFileError, match="not a pickle"):
        mano.load_mano_pkl(text)
    other = tmp_path / "other.pkl"
    other.write_bytes(pickle.dumps({"weights": np.zeros(3)}))
    with pytest.raises(mano.ManoFileError, match="missing"):
        mano.load_mano_pkl(other)
    a_list = tmp_path / "list.pkl"
    a_list.write_bytes(pickle.dumps([1, 2, 3]))
    with pytest.raises(mano.ManoFileError, match="not a MANO model"):
        mano.load_mano_pkl(a_list)
    with open(good, "rb") as f:
        data = pickle.load(f)
    data["posedirs"] = data["posedirs"][:, :, :100]
    broken = tmp_path / "broken.pkl"
    broken.write_bytes(pickle.dumps(data))
    with pytest.raises(mano.ManoFileError, match="posedirs has shape"):
        mano.load_mano_pkl(broken)
    with pytest.raises(mano.ManoFileError, match="cannot read"):
        mano.load_mano_pkl(tmp_path / "absent.pkl")
    with pytest.raises(ValueError, match="side"):
        mano.load_builtin("both")


class _Payload:
    """Unpickles to `call(*args)`: what a hostile MANO file would do."""

    def __init__(self, call, *args):
        self.call, self.args = call, args

    def __reduce__(self):
        return self.call, self.args


def test_pickles_that_would_run_code_are_refused(right, tmp_path):
    """Loading never calls what a file names unless a MANO file needs it: a payload
    alone, or hidden as one extra entry of a valid MANO dictionary, creates nothing."""
    good = mano.save_mano_pkl(right, tmp_path / "MANO_RIGHT.pkl")
    with open(good, "rb") as f:
        valid = pickle.load(f)
    witness = tmp_path / "pwned"
    payloads = {
        "os.system": _Payload(os.system, f"touch {witness}"),
        "builtins.open": _Payload(open, str(witness), "w"),
        "builtins.eval": _Payload(eval, f"open({str(witness)!r}, 'w')"),
        "subprocess.run": _Payload(subprocess.run, ["touch", str(witness)]),
        # scipy.sparse is allowed for its matrix classes only: its functions write files
        "scipy.sparse.save_npz": _Payload(scipy.sparse.save_npz, str(witness), scipy.sparse.eye(2, format="csr")),
    }
    for name, payload in payloads.items():
        for protocol in (2, pickle.HIGHEST_PROTOCOL):
            for content in (payload, {**valid, "hands_coeffs": payload}):
                path = tmp_path / "MANO_RIGHT.pkl"
                path.write_bytes(pickle.dumps(content, protocol=protocol))
                with pytest.raises(mano.ManoFileError, match="not a safe MANO file: it names "):
                    mano.load_mano_pkl(path)
                assert not witness.exists() and not witness.with_suffix(".npz").exists(), name


def test_smplx_gives_the_same_vertices_and_joints(right, left, tmp_path):
    smplx = pytest.importorskip("smplx")
    torch = pytest.importorskip("torch")
    for model, name in ((right, "MANO_RIGHT.pkl"), (left, "MANO_LEFT.pkl")):
        path = mano.save_mano_pkl(model, tmp_path / name)
        layer = smplx.MANO(str(path), use_pca=False, flat_hand_mean=True, is_rhand=model.side == "right")
        for seed in range(3):
            params = random_params(seed)
            out = mano.forward(model, params)
            go, transl_smplx = mano.to_smplx(model, params)
            t = lambda x: torch.tensor(np.asarray(x, np.float32)[None])  # noqa: E731
            ref = layer(global_orient=t(go), hand_pose=t(params.hand_pose.reshape(45)), betas=t(params.betas), transl=t(transl_smplx))
            np.testing.assert_allclose(ref.vertices[0].numpy(), np.asarray(out.vertices), atol=1e-6)
            np.testing.assert_allclose(ref.joints[0, :16].numpy(), np.asarray(out.transforms[:, :3, 3]), atol=1e-6)


@pytest.mark.parametrize("suffix", ["obj", "ply", "glb"])
def test_export(right, tmp_path, suffix):
    import trimesh

    out = mano.forward(right, random_params(0))
    path = mano.export_mesh(right, out, tmp_path / f"hand.{suffix}")
    loaded = trimesh.load(path, force="mesh", process=False)
    assert len(loaded.vertices) == right.num_vertices
    np.testing.assert_allclose(np.asarray(loaded.vertices), np.asarray(out.vertices), atol=1e-6)
    with pytest.raises(ValueError, match="unsupported"):
        mano.export_mesh(right, out, tmp_path / "hand.xyz")


def test_forward_batch_equals_vmap_for_any_batch_size(right):
    batch = stack([random_params(s) for s in range(70)])  # not a multiple of the chunk
    reference = jax.vmap(mano.forward, in_axes=(None, 0))(right, batch)
    chunked = eqx.filter_jit(mano.forward_batch)(right, batch, chunk=16)
    assert tree_allclose(chunked, reference, atol=1e-6)


def test_forward_batch_kernel_checks_and_differentiates_as_vmap(right):
    """Above 32 hands forward_batch runs its own batch kernel: NaN named eagerly and at run
    time, bad shapes named, and its gradient is vmap(forward)'s."""
    batch = stack([random_params(s) for s in range(40)])
    bad = eqx.tree_at(lambda p: p.betas, batch, batch.betas.at[3, 0].set(jnp.nan))
    with pytest.raises(ValueError, match=r"NaN or infinite values \(in betas\)"):
        mano.forward_batch(right, bad)
    with pytest.raises(Exception, match="ManoParams contains NaN or infinite"):
        jax.block_until_ready(eqx.filter_jit(mano.forward_batch)(right, bad))
    with pytest.raises(ValueError, match="transl"):
        mano.forward_batch(right, eqx.tree_at(lambda p: p.transl, batch, batch.transl[:5]))

    def loss(forward, params):
        out = forward(params)
        return jnp.sum(out.vertices**2) + jnp.sum(out.joints**2)

    kernel = jax.grad(functools.partial(loss, lambda p: mano.forward_batch(right, p)))(batch)
    reference = jax.grad(functools.partial(loss, lambda p: jax.vmap(mano.forward, in_axes=(None, 0))(right, p)))(batch)
    assert tree_allclose(kernel, reference, rtol=1e-4, atol=1e-4)
