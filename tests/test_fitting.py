import concurrent.futures
import json

import jax
from jax.flatten_util import ravel_pytree
import jax.numpy as jnp
import numpy as np
import pytest

from esther_jax import cameras, cli, clips, mano, metrics
from esther_jax.data import motion, synth
import fitting
from fitting import evidence, fusion, label_clips, label_hand, quality
from esther_jax.mano import PosePrior
from fitting.priors import MotionPrior, huber_residual

FRAMES = 32  # one length bucket: the solvers compile once for the whole module


def _detections(uv1, c1, uv2, c2, box_side=100.0, s1=0.9, s2=0.8):
    """keypoints.npz-shaped arrays (2 detectors, 1 frame, 2 views) with every joint alike."""
    uv = np.zeros((2, 1, 2, 21, 2))
    uv[0], uv[1] = uv1, uv2
    conf = np.zeros((2, 1, 2, 21))
    conf[0], conf[1] = c1, c2
    box = np.tile(np.array([0.0, 0.0, box_side, box_side]), (2, 1, 2, 1))
    score = np.array([[[s1, s1]], [[s2, s2]]])
    return [jnp.asarray(x, jnp.float32) for x in (uv, conf, box, score)]


def test_fusion_follows_appendix_a():
    a, b = np.array([10.0, 10.0]), np.array([15.0, 10.0])  # 5 px apart, box side 100: agree (eps = 10 px)
    f = fusion.fuse(*_detections(a, 0.9, b, 0.6))
    np.testing.assert_allclose(np.asarray(f.uv[0, 0, 0]), (0.9 * a + 0.6 * b) / 1.5, rtol=1e-6)
    far = np.array([40.0, 10.0])  # 30 px apart: the more confident wins
    f = fusion.fuse(*_detections(a, 0.5, far, 0.8))
    np.testing.assert_allclose(np.asarray(f.uv[0, 0, 0]), far)
    f = fusion.fuse(*_detections(a, 0.70, far, 0.72, s1=0.95, s2=0.5))  # near tie: box score decides
    np.testing.assert_allclose(np.asarray(f.uv[0, 0, 0]), a)
    f = fusion.fuse(*_detections(a, 0.2, far, 0.31))  # only detector 2 is valid (tau = 0.3)
    np.testing.assert_allclose(np.asarray(f.uv[0, 0, 0]), far)
    f = fusion.fuse(*_detections(a, 0.2, far, 0.1))  # none valid: dropped
    assert float(f.conf[0, 0, 0]) == 0.0
    uv, conf, box, score = _detections(a, 0.9, b, 0.9)
    f = fusion.fuse(uv.at[0, 0, 0, 3].set(jnp.nan), conf, box, score)
    assert float(f.num_invalid) == 1 and np.all(np.isfinite(np.asarray(f.uv)))
    np.testing.assert_allclose(np.asarray(f.uv[0, 0, 3]), b)
    f = fusion.fuse(uv.at[0, 0, 0, 3].set(jnp.nan), conf.at[0, 0, 0, 3].set(0.0), box, score)  # the format's "not detected"
    assert float(f.num_invalid) == 0
    np.testing.assert_allclose(np.asarray(f.uv[0, 0, 3]), b)


def test_prefilter_rejects_implausible_depths_and_isolated_bones():
    rig = cameras.rig_preset("esther")
    model = mano.load_builtin("right")
    params = mano.ManoParams(jnp.asarray([0.0, 2.0, 0.0]), jnp.zeros((15, 3)), jnp.zeros(10), jnp.asarray([0.0, 0.05, 0.4]))
    joints = np.asarray(mano.forward_joints(model, params), np.float64)
    joints[8] += np.array([0.0, 0.0, 0.2])  # index tip placed 20 cm behind: both its bones are off by > 40 %
    far = joints.copy()
    far[:, 2] += 1.0  # the whole hand beyond 1 m
    uv = np.stack([motion_uv(rig, joints), motion_uv(rig, far)])  # (2 frames, 2, 21, 2)
    fused = fusion.Fused(uv=jnp.asarray(uv, jnp.float32), conf=jnp.ones((2, 2, 21)), box_side=jnp.full((2, 2), 200.0), num_invalid=jnp.zeros(()))
    ev = evidence.prefilter(rig, fused, evidence.template_bones(model))
    w = np.asarray(ev.weight)
    assert w[0, :, 8].sum() == 0 and w[0, :, 7].sum() > 0 and w[0, :, 0].sum() > 0
    assert w[1].sum() == 0
    assert float(ev.rejected_bones) >= 1 and float(ev.rejected_depth) == 21


def motion_uv(rig, joints):
    return np.asarray(rig.project(jnp.asarray(joints, jnp.result_type(float))), np.float64)


def test_initialisation_recovers_the_wrist_and_orientation_without_flips():
    rig = cameras.rig_preset("esther")
    model = mano.load_builtin("right")
    rng = np.random.default_rng(0)
    for _ in range(5):
        go = jnp.asarray(rng.normal(size=3) * 1.2, jnp.float32)
        params = mano.ManoParams(go, jnp.asarray(rng.normal(size=(15, 3)) * 0.3, jnp.float32), jnp.zeros(10), jnp.asarray([0.02, 0.05, 0.4]))
        joints = np.asarray(mano.forward_joints(model, params), np.float64)
        uv = motion_uv(rig, joints)[None]
        fused = fusion.Fused(uv=jnp.asarray(uv, jnp.float32), conf=jnp.ones((1, 2, 21)), box_side=jnp.full((1, 2), 200.0), num_invalid=jnp.zeros(()))
        ev = evidence.prefilter(rig, fused, evidence.template_bones(model))
        init = evidence.initialise(model, rig, ev, jnp.zeros(10))
        np.testing.assert_allclose(np.asarray(init.transl[0]), np.asarray(params.transl), atol=2e-3)
        from esther_jax.rotations import axis_angle_to_matrix, geodesic_angle

        angle = float(geodesic_angle(axis_angle_to_matrix(init.global_orient[0]), axis_angle_to_matrix(go)))
        assert angle < np.deg2rad(3.0)


def test_palm_jacobian_in_closed_form_equals_autodiff():
    model = mano.load_builtin("right")
    rest = mano.forward_joints(model, mano.ManoParams.zeros())
    P = rest[np.asarray(mano.PALM_KEYPOINTS)] - rest[0][None]
    rng = np.random.default_rng(3)
    for rig in (cameras.rig_preset("esther"), cameras.rig_preset("hot3d_aria")):
        rays = jnp.asarray(rng.normal(size=(2, 6, 3)) * 0.05 + np.array([0.0, 0.0, 1.0]), jnp.float32)
        rays = rays / jnp.linalg.norm(rays, axis=-1, keepdims=True)
        w = jnp.asarray(rng.uniform(0.2, 1.0, size=(2, 6)), jnp.float32).at[1].set(0.0)  # one view unseen
        for scale in (1e-3, 0.5):  # inside the Huber threshold, then far outside it
            y = evidence.PalmUnknowns(jnp.asarray(rng.normal(size=3) * scale, jnp.float32), jnp.asarray(rng.normal(size=3), jnp.float32))
            args = (rig, rays, w, P, jnp.eye(3), jnp.asarray([0.0, 0.0, 0.45]))
            residuals, jacobian = evidence.palm_residuals_and_jacobian(y, args)
            flat, unravel = ravel_pytree(y)
            expected = jax.jacfwd(lambda x: evidence.palm_residuals(unravel(x), args)[0])(flat)
            np.testing.assert_allclose(residuals, evidence.palm_residuals(y, args)[0], atol=1e-7)
            np.testing.assert_allclose(jacobian, expected, atol=2e-6 * float(jnp.abs(expected).max()))
            assert float(jnp.abs(jacobian[18:]).max()) == 0.0  # the unseen view's rows


def test_normal_equations_from_the_objectives_structure_equal_the_full_jacobians(x64):
    """`frame_normal_equations` (closed-form reprojection and pose-prior Jacobians,
    diagonal terms) equals J^T r, J^T J of forward-mode autodiff through all of
    `frame_residuals`, in every kind of round (the projection's Jacobian is generic forward
    mode, so one camera model suffices)."""
    from fitting import objectives as O, solve

    rig = cameras.rig_preset("esther")
    model = mano.load_builtin("right")
    rng = np.random.default_rng(5)
    frames = 3
    normal = lambda *shape, s=1.0: jnp.asarray(rng.normal(size=shape) * s)  # noqa: E731
    y = O.FrameUnknowns(normal(frames, 3, s=0.5), normal(frames, 15, 3, s=0.6), normal(frames, 3), normal(frames, 10, s=0.5))
    anchor = jnp.asarray([[0.05, 0.1, 0.35]]) + normal(frames, 3, s=0.02)
    params = jax.vmap(lambda yi, a: mano.ManoParams(yi.global_orient, yi.hand_pose, yi.betas, a))(y, anchor)
    uv = jax.vmap(lambda p: rig.project(mano.forward_joints(model, p)))(params) + normal(frames, 2, 21, 2, s=6.0)  # inside and outside 4 px
    weight = jnp.asarray(rng.uniform(0.0, 1.0, size=(frames, 2, 21))).at[0, 1].set(0.0)  # frame 0 monocular
    data = O.FrameData(uv, weight, anchor, jnp.asarray([1.0, 0.3, 1.0]), anchor / jnp.linalg.norm(anchor, axis=-1, keepdims=True))
    track = O.Track(normal(frames, 16, 3, s=0.5), anchor + normal(frames, 3, s=0.01), jnp.full(frames, 60.0), normal(frames, 3),
                    normal(frames, 3), anchor + normal(frames, 3, s=0.1), anchor, jnp.ones(frames), jnp.asarray([1.0, 0.0, 1.0]))  # fmt: skip
    problem = O.Problem(model, rig, PosePrior.from_model(model), MotionPrior(), O.FitWeights(), normal(10, s=0.3), jnp.asarray(30.0))

    @jax.jit
    def both(round):
        def one(y1, d1, t1):
            a = (problem, d1, t1, round)
            flat, unravel = ravel_pytree(y1)
            f = lambda x: jnp.concatenate([r.reshape(-1) for r in O.frame_residuals(unravel(x), a)])  # noqa: E731
            return solve.gauss_newton(f(flat), jax.jacfwd(f)(flat)), O.frame_normal_equations(y1, a)

        return jax.vmap(one)(y, data, track)

    for free, stiff, motion_ in ((1.0, 1.0, 0.0), (0.0, 25.0, 0.0), (0.0, 1.0, 1.0)):
        (g, H), (g_fast, H_fast) = both(O.Round.make(free, stiff, motion_, jnp.float64))
        np.testing.assert_allclose(g_fast, g, rtol=1e-9, atol=1e-9 * float(jnp.abs(g).max()))
        np.testing.assert_allclose(H_fast, H, rtol=1e-9, atol=1e-9 * float(jnp.abs(H).max()))


def test_huber_vector_is_finite_at_zero_and_equals_the_smoothed_norms():
    """The robust vector terms scale by the core's safe norm: at a zero residual the value,
    the closed-form Jacobian and the gradient are finite (no 0 / 0), and elsewhere they equal
    what the former sqrt(|e|^2 + 1e-12) gave, to float32 precision."""
    from fitting.priors import huber_factor, huber_vector, huber_vector_with_jacobian

    e = jnp.asarray([[0.0, 0.0], [1e-9, 0.0], [0.3, -0.4], [3.0, 4.0], [-20.0, 7.0]], jnp.float32)
    delta = 1.5
    smoothed = e * huber_factor(jnp.sqrt(jnp.sum(e * e, axis=-1) + 1e-12), delta)[..., None]
    np.testing.assert_allclose(np.asarray(huber_vector(e, delta)), np.asarray(smoothed), rtol=1e-6, atol=0.0)
    de = jnp.asarray(np.random.default_rng(0).normal(size=(5, 2, 3)), jnp.float32)  # e's Jacobian in 3 unknowns
    value, jacobian = huber_vector_with_jacobian(e, de, delta)
    autodiff = jnp.einsum("kab,kbn->kan", jax.vmap(jax.jacfwd(lambda v: huber_vector(v, delta)))(e), de)
    assert bool(jnp.all(jnp.isfinite(jacobian)))
    np.testing.assert_allclose(np.asarray(value), np.asarray(huber_vector(e, delta)), rtol=1e-6)
    np.testing.assert_allclose(np.asarray(jacobian), np.asarray(autodiff), rtol=1e-5, atol=1e-6)
    grad = jax.grad(lambda v: jnp.sum(huber_vector(v, delta) ** 2))(e)
    assert bool(jnp.all(jnp.isfinite(grad)))
    np.testing.assert_allclose(np.asarray(grad[:3]), 2.0 * np.asarray(e[:3]), rtol=1e-6, atol=1e-12)  # within delta: |e|^2


def test_priors_are_residual_callables():
    model = mano.load_builtin("right")
    prior = PosePrior.from_model(model)
    assert float(jnp.sum(prior(model.hands_mean.reshape(15, 3)) ** 2)) < 1e-6
    bent_back = jnp.zeros((15, 3)).at[1].set(jnp.asarray([0.0, 0.0, -1.5]))  # index PIP hyper-extended
    assert float(jnp.sum(prior(bent_back)[45:] ** 2)) > 1.0
    # its normal equations in closed form, with hinges active and not
    pose = bent_back + 0.3 * jnp.asarray(np.random.default_rng(2).normal(size=(15, 3)), jnp.float32)
    J = jax.jacfwd(prior)(pose).reshape(90, 45)
    g, H = prior.normal_equations(pose)
    np.testing.assert_allclose(g, J.T @ prior(pose), rtol=1e-4, atol=1e-3)
    np.testing.assert_allclose(H, J.T @ J, rtol=1e-4, atol=1e-3)
    smooth = MotionPrior()
    line = jnp.linspace(0.0, 1.0, 16)[:, None] * jnp.ones((1, 4))
    assert float(jnp.abs(smooth(line)).max()) < 1e-6
    noisy = line + 0.01 * jnp.asarray(np.random.default_rng(0).normal(size=(16, 4)), jnp.float32)
    cleaned = smooth.smooth(noisy, jnp.ones(16))
    assert float(jnp.abs(cleaned - line).mean()) < float(jnp.abs(noisy - line).mean())
    np.testing.assert_allclose(float(huber_residual(jnp.asarray(3.0), 1.0)) ** 2 / 2, 1.0 * (3.0 - 0.5), rtol=1e-6)


def test_depth_per_disparity_is_z2_over_fb_on_a_parallel_rig():
    """Appendix N's z^2 / (f b) is the parallel pinhole case of the general geometry,
    for every point, not only on the optical axis."""
    rig = cameras.rig_preset("esther")
    rng = np.random.default_rng(0)
    X = jnp.asarray(rng.uniform([-0.3, -0.2, 0.2], [0.3, 0.2, 0.9], size=(50, 3)), jnp.float32)
    got = np.asarray(jax.vmap(quality.depth_per_disparity, in_axes=(None, 0))(rig, X))
    z = np.asarray(X[:, 2], np.float64)
    expected = z**2 / (623.0 * 0.062)
    np.testing.assert_allclose(got[:, 0], expected, rtol=1e-4)
    np.testing.assert_allclose(got[:, 1], expected, rtol=1e-4)
    on_axis = jnp.asarray([[0.0, 0.0, 0.4]], jnp.float32)
    np.testing.assert_allclose(np.asarray(jax.vmap(quality.metres_per_pixel, in_axes=(None, 0))(rig, on_axis))[0, 0], 0.4 / 623.0, rtol=1e-5)


def test_quality_table_reports_stereo_and_monocular_frames():
    rig = cameras.rig_preset("hot3d_aria")
    wrist = jnp.tile(jnp.asarray([0.05, 0.1, 0.35], jnp.float32), (10, 1))
    residual = jnp.full(10, 5.0, jnp.float32)
    seen = jnp.asarray([[True, True]] * 6 + [[False, True]] * 4)
    per_frame = jax.device_get(quality.frame_quality(rig, wrist, residual, seen, jnp.asarray(0.18, jnp.float32)))
    # the divergent rig's geometry: depth along the observing cameras' axes, not the rig frame's z
    assert abs(per_frame["hand_depth_m"][0] - np.asarray(rig.depths(wrist[0])).mean()) < 1e-6
    assert np.all(np.isfinite(per_frame["admissible_depth_error_independent_mm"]))
    np.testing.assert_allclose(per_frame["admissible_depth_error_worst_mm"], np.sqrt(2.0) * per_frame["admissible_depth_error_independent_mm"], rtol=1e-5)
    stereo = np.asarray(jnp.all(seen, axis=1))
    q = quality.label_quality(per_frame, np.ones(10, bool), stereo, np.ones(10, bool))
    assert q["stereo"]["hand_frames"] == 6 and q["monocular"]["hand_frames"] == 4 and q["all"]["share_passing"] == 1.0
    assert q["monocular"]["table"]["reprojection_residual_px"]["median"] == 5.0
    json.dumps(q, allow_nan=False)  # strict JSON


def test_fusion_with_one_and_three_detectors():
    a, far = np.array([10.0, 10.0]), np.array([40.0, 10.0])
    uv, conf, box, score = (x[:1] for x in _detections(a, 0.9, far, 0.6))
    f = fusion.fuse(uv, conf.at[0, 0, 0, 2].set(0.2), box, score)  # D = 1: its joints above tau
    np.testing.assert_allclose(np.asarray(f.uv[0, 0, 0]), a)
    assert float(f.conf[0, 0, 2]) == 0.0 and float(f.conf[0, 0, 0]) == pytest.approx(0.9)
    b = np.array([14.0, 10.0])  # D = 3: two agree, one outlier; the outlier is ignored
    uv2, conf2, box2, score2 = _detections(a, 0.9, b, 0.6)
    uv3 = jnp.concatenate([uv2, jnp.broadcast_to(jnp.asarray(far, jnp.float32), uv2[:1].shape)])
    conf3 = jnp.concatenate([conf2, conf2[:1] * 0 + 0.8])
    f = fusion.fuse(uv3, conf3, jnp.concatenate([box2, box2[:1]]), jnp.concatenate([score2, score2[:1]]))
    np.testing.assert_allclose(np.asarray(f.uv[0, 0, 0]), (0.9 * a + 0.6 * b) / 1.5, rtol=1e-6)
    # with two detectors the general rule is appendix A's case analysis
    f2 = fusion.fuse(uv2, conf2, box2, score2)
    np.testing.assert_allclose(np.asarray(f2.uv), np.asarray(fusion.fuse(uv3[:2], conf3[:2], box2, score2).uv))


@pytest.fixture(scope="module")
def clean_two_hands():
    cfg = synth.SynthConfig(num_frames=FRAMES, detector_preset="easy", motion_config=motion.MotionConfig(two_hands_probability=1.0, leave_view_probability=0.0))
    return synth.make_clip(28, 0, cfg)  # both hands stay on-screen (many clips see a hand leave)


@pytest.mark.slow
def test_labels_match_the_ground_truth(clean_two_hands):
    clip = clean_two_hands
    sequential = {}
    for side in clip.keypoints:
        labels, report = label_hand(mano.load_builtin(side), clip.rig, clip.keypoints[side], 30.0)
        sequential[side] = labels
        gt = clip.gt[side]
        ok = np.asarray(labels.valid) & gt["onscreen"]
        assert ok.sum() >= 0.7 * gt["onscreen"].sum()
        pred, true = labels.joints, jnp.asarray(gt["joints"])
        assert np.asarray(jax.vmap(metrics.p_mpjpe)(pred, true))[ok].mean() < 0.008
        assert np.asarray(jax.vmap(metrics.wrist_error)(pred, true))[ok].mean() < 0.01
        assert report["share_passing"] > 0.7 and report["all"]["table"]["reprojection_residual_px"]["median"] < 12.0
    # from two threads at once: the calls take turns (both hung in XLA's CPU runtime before) and label the same
    with concurrent.futures.ThreadPoolExecutor(2) as pool:
        futures = {side: pool.submit(label_hand, mano.load_builtin(side), clip.rig, clip.keypoints[side], 30.0) for side in clip.keypoints}
        for side, future in futures.items():
            np.testing.assert_array_equal(future.result(timeout=600)[0].joints, sequential[side].joints)


def _scores(labels, gt):
    ok = np.asarray(labels.valid) & gt["onscreen"]
    pred, true = labels.joints, jnp.asarray(gt["joints"])
    p = np.asarray(jax.vmap(metrics.p_mpjpe)(pred, true))
    w = np.asarray(jax.vmap(metrics.wrist_error)(pred, true))
    return ok, p, w


@pytest.mark.slow
def test_one_and_three_detectors_label(clean_two_hands):
    """D = 1 (a single real detector) and D = 3 clips label; the solver does not recompile."""
    clip = clean_two_hands
    kp = clip.keypoints["right"]
    one = {k: v[:1] for k, v in kp.items()}
    rng = np.random.default_rng(1)
    three = {k: np.concatenate([v, v[:1]]) for k, v in kp.items()}
    three["uv"][2] += rng.normal(scale=1.0, size=three["uv"][2].shape)
    for keypoints in (one, three):
        labels, _ = label_hand(mano.load_builtin("right"), clip.rig, keypoints, 30.0)
        ok, p, w = _scores(labels, clip.gt["right"])
        assert ok.sum() >= 0.7 * clip.gt["right"]["onscreen"].sum()
        assert p[ok].mean() < 0.010 and w[ok].mean() < 0.012


def test_small_systems_element_by_element_equal_the_matrix_forms(x64):
    """`solve.gauss_newton` and `solve.cholesky_solve` below and above `SMALL_SYSTEM`
    unknowns (element by element, and matrix products / LAPACK), batched under vmap."""
    from fitting import solve

    rng = np.random.default_rng(3)
    for n in (solve.SMALL_SYSTEM - 2, solve.SMALL_SYSTEM + 4):
        J, r = rng.normal(size=(5, 3 * n, n)), rng.normal(size=(5, 3 * n))
        g, H = jax.vmap(solve.gauss_newton)(jnp.asarray(r), jnp.asarray(J))
        np.testing.assert_allclose(g, np.einsum("bmn,bm->bn", J, r), rtol=1e-12, atol=1e-12)
        np.testing.assert_allclose(H, np.einsum("bmn,bmk->bnk", J, J), rtol=1e-12, atol=1e-12)
        b = rng.normal(size=(5, n))
        x = jax.vmap(solve.cholesky_solve)(H, jnp.asarray(b))
        np.testing.assert_allclose(x, np.linalg.solve(np.asarray(H), b[..., None])[..., 0], rtol=1e-9, atol=1e-9)


def test_step_counts_do_not_recompile(clean_two_hands):
    """The solver's step counts are traced: other counts per stage reuse the compiled programs."""
    clip = clean_two_hands
    model, keypoints = mano.load_builtin("right"), clip.keypoints["right"]
    label_hand(model, clip.rig, keypoints, 30.0)
    compiled = []
    jax.monitoring.register_event_duration_secs_listener(
        lambda event, seconds, **_: compiled.append(event) if event == "/jax/core/compile/backend_compile_duration" else None
    )
    labels, _ = label_hand(model, clip.rig, keypoints, 30.0, fitting.LabelConfig(steps=2, shape_lock_steps=7))
    assert compiled == []
    assert labels.valid.any()


def test_palm_pose_is_exact_in_one_fisheye_view():
    """The palm's perspective-n-point recovers the wrist and orientation exactly from one
    Aria view (no triangulation), whatever the starting guess."""
    from esther_jax.rotations import axis_angle_to_matrix, geodesic_angle

    rig = cameras.rig_preset("hot3d_aria")
    model = mano.load_builtin("left")
    rest = mano.forward_joints(model, mano.ManoParams.zeros())
    rng = np.random.default_rng(3)
    for _ in range(4):
        go = jnp.asarray(rng.normal(size=3) * 1.5, jnp.float32)
        wrist = jnp.asarray([-0.12, 0.08, 0.35], jnp.float32)
        joints = mano.forward_joints(model, mano.ManoParams(go, jnp.asarray(rng.normal(size=(15, 3)) * 0.3, jnp.float32), jnp.zeros(10), wrist))
        uv = np.asarray(rig.project(joints))  # (2, 21, 2)
        weight = np.zeros((2, 21), np.float32)
        weight[0] = 1.0  # the left camera only
        pose = evidence.palm_pose(rig, jnp.asarray(uv, jnp.float32), jnp.asarray(weight), rest, jnp.eye(3), jnp.zeros(3), jnp.asarray(False))
        assert float(jnp.linalg.norm(pose.wrist - wrist)) < 1e-3
        assert float(geodesic_angle(pose.rotation, axis_angle_to_matrix(go))) < 1e-2
        assert float(pose.residual_rad) < 1e-3 and float(pose.points) == 6


def _on_aria(frames: int, index: int):
    cfg = synth.SynthConfig(num_frames=frames, rig="hot3d_aria", motion_config=motion.MotionConfig(two_hands_probability=1.0))
    return synth.make_clip(1000, index, cfg)


@pytest.mark.slow
def test_monocular_frames_on_a_divergent_rig():
    """Acceptance of the divergent rig: on the Aria rig (75 degrees apart) most frames see a
    hand in one camera only; >= 80 % of the on-screen hand-frames are labelled within
    15 mm P-MPJPE and 25 mm wrist of the exact ground truth (default detector), monocular
    frames included. A hand never seen in stereo takes the other hand's shape; alone, the
    mean shape, flagged."""
    on = good = mono = borrowed = 0
    for index in range(4):
        clip = _on_aria(FRAMES, index)
        results = fitting.label_hands({s: mano.load_builtin(s) for s in clip.keypoints}, clip.rig, clip.keypoints, 30.0)
        for side, (labels, report) in results.items():
            ok, p, w = _scores(labels, clip.gt[side])
            onscreen = clip.gt[side]["onscreen"]
            on += onscreen.sum()
            good += (ok & (p <= 0.015) & (w <= 0.025)).sum()
            mono += (onscreen & ~np.asarray(labels.stereo)).sum()
            borrowed += report["shape_from_other_hand"]
            assert report["monocular"]["hand_frames"] == int((labels.onscreen & ~labels.stereo).sum())
    assert mono > 0.5 * on and borrowed >= 1
    assert good >= 0.8 * on
    clip = _on_aria(FRAMES, 0)
    kp = {k: v.copy() for k, v in clip.keypoints["left"].items()}
    kp["conf"][:, :, 0] = 0.0  # the left camera never sees this hand
    labels, report = label_hand(mano.load_builtin("left"), clip.rig, kp, 30.0)
    assert report["shape_from_monocular"] and not labels.stereo.any() and labels.valid.any()
    assert np.allclose(labels.betas, 0.0) and any("the mean shape" in n for n in report["notes"])


@pytest.mark.slow
def test_bad_inputs_are_labelled_flagged_or_reported(clean_two_hands, tmp_path):
    clip = clean_two_hands
    side = "right"
    model = mano.load_builtin(side)
    kp = {k: v.copy() for k, v in clip.keypoints[side].items()}
    kp["uv"][:, 3, :, 5] = np.nan  # NaN keypoints
    kp["conf"][:, 10:18, 1] = 0.0  # the right view sees nothing for 8 frames
    kp["uv"][:, 24:27] = 1e30  # absurd pixels, confidently reported: not observations
    labels, report = label_hand(model, clip.rig, kp, 30.0)
    assert np.all(np.isfinite(labels.joints))
    assert any("NaN" in n for n in report["notes"]) and any("one view" in n for n in report["notes"])
    assert any("far outside the image" in n for n in report["notes"])
    assert not labels.onscreen[24:27].any() and not labels.valid[24:27].any()
    assert not np.isinf(labels.residual_px).any()
    # frames seen by one view are labelled as monocular frames, not dropped
    assert not labels.stereo[10:18].any() and labels.onscreen[10:18].all() and labels.valid[10:18].sum() >= 6
    assert report["monocular"]["hand_frames"] == 8 and report["stereo"]["hand_frames"] == int(labels.stereo.sum())
    json.dumps(report, allow_nan=False, default=float)
    never = {k: v.copy() for k, v in clip.keypoints[side].items()}
    never["conf"][:] = 0.0
    labels, report = label_hand(model, clip.rig, never, 30.0)
    assert not labels.valid.any() and "never detected" in report["notes"][-1]
    short = {k: v[:, :10] for k, v in clip.keypoints[side].items()}  # fewer frames than a window
    labels, _ = label_hand(model, clip.rig, short, 30.0)
    assert labels.joints.shape == (10, 21, 3) and labels.valid.sum() >= 5

    good = synth.write_clip(clip, tmp_path / "clips" / "good")
    zero = synth.write_clip(clip, tmp_path / "clips" / "zero_baseline")
    rig = json.loads((zero / "rig.json").read_text())
    rig["T_left_right"][0][3] = 0.0
    (zero / "rig.json").write_text(json.dumps(rig))
    missing = synth.write_clip(clip, tmp_path / "clips" / "missing_camera")
    rig = json.loads((missing / "rig.json").read_text())
    del rig["cameras"]["right"]
    (missing / "rig.json").write_text(json.dumps(rig))
    truncated = synth.write_clip(clip, tmp_path / "clips" / "truncated")
    path = clips.hand_file(truncated, "left", "keypoints")
    path.write_bytes(path.read_bytes()[:200])
    result = label_clips([good, zero, missing, truncated], tmp_path / "labels", progress=False)
    errors = {f["clip"].split("/")[-1]: f["error"] for f in result["failed"]}
    assert [s["clip"] for s in result["labelled"]] == ["good"]
    assert "baseline" in errors["zero_baseline"] and "'right' is missing" in errors["missing_camera"] and "truncated" in errors["truncated"]
    assert not any("partial" in p.name for p in (tmp_path / "labels").iterdir())


@pytest.mark.slow
def test_label_cli_resume_reject_and_review(clean_two_hands, tmp_path, capsys):
    folder = synth.write_clip(clean_two_hands, tmp_path / "clips" / "c0")
    out = tmp_path / "labels"
    (tmp_path / "reject.txt").write_text("# reviewer's list\nc0,right,3\nc0,left,4\n")
    assert cli.main(["label", str(tmp_path / "clips"), "--out", str(out), "--reject", str(tmp_path / "reject.txt"), "--review"]) == 0
    labels = clips.Labels.from_npz(clips.hand_file(out / "c0", "right", "labels"))
    assert not labels.valid[3]
    q = json.loads((out / "c0" / "hands" / "right" / "quality.json").read_text(), parse_constant=pytest.fail)  # strict JSON
    assert q["human_rejected_frames"] == [3]
    stamp = (out / "c0" / "meta.json").stat().st_mtime_ns
    first = json.loads((out / "label_summary.json").read_text())["labelled"]
    assert cli.main(["label", str(folder), "--out", str(out), "--resume"]) == 0
    assert (out / "c0" / "meta.json").stat().st_mtime_ns == stamp and "skipped 1" in capsys.readouterr().out
    summary = json.loads((out / "label_summary.json").read_text())
    assert summary["skipped"] == ["c0"] and summary["labelled"] == first  # the resumed run keeps the first run's notes
    (tmp_path / "bad.txt").write_text("c0;right;3\n")
    assert cli.main(["label", str(folder), "--out", str(out), "--reject", str(tmp_path / "bad.txt")]) == 2
    assert (out / "c0" / "hands" / "right" / "review.png").exists() or labels.valid[labels.onscreen].all()


@pytest.mark.slow
def test_monocular_estimates_initialise_the_fit(clean_two_hands):
    """Per-view monocular MANO (as WiLoR gives), each in its camera's frame, is moved to
    the rig frame, averaged, and used as the starting orientation and pose."""
    from esther_jax.rotations import axis_angle_to_matrix, geodesic_angle, matrix_to_axis_angle

    clip = clean_two_hands
    side = "left"
    gt = clip.gt[side]
    rng = np.random.default_rng(0)
    T_lr = np.asarray(clip.rig.T_left_right, np.float64)
    R_rig = np.asarray(axis_angle_to_matrix(jnp.asarray(gt["global_orient"])), np.float64)
    R_right = np.einsum("ji,tjk->tik", T_lr[:3, :3], R_rig)  # R_right_rig @ R
    orient = np.stack([gt["global_orient"], np.asarray(matrix_to_axis_angle(jnp.asarray(R_right, jnp.float32)))], axis=1)
    orient = orient + rng.normal(scale=0.05, size=orient.shape)
    pose = np.stack([gt["hand_pose"]] * 2, axis=1) + rng.normal(scale=0.1, size=(FRAMES, 2, 15, 3))
    transl = np.stack([gt["transl"], (gt["transl"] - T_lr[:3, 3]) @ T_lr[:3, :3]], axis=1)
    monocular = {"global_orient": orient, "hand_pose": pose, "transl": transl, "valid": np.ones((FRAMES, 2), bool)}
    from fitting.evidence import monocular_average

    avg_orient, avg_pose, has = monocular_average(clip.rig, monocular)
    assert has.all()
    angle = lambda a, b: geodesic_angle(axis_angle_to_matrix(a), axis_angle_to_matrix(b))  # noqa: E731
    err = np.asarray(jax.vmap(angle)(jnp.asarray(avg_orient, jnp.float32), jnp.asarray(gt["global_orient"])))
    assert np.median(err) < 0.06
    labels, report = label_hand(mano.load_builtin(side), clip.rig, clip.keypoints[side], 30.0, monocular=monocular)
    assert any("monocular" in n for n in report["notes"])
    ok = np.asarray(labels.valid) & gt["onscreen"]
    assert np.asarray(jax.vmap(metrics.p_mpjpe)(labels.joints, jnp.asarray(gt["joints"])))[ok].mean() < 0.008
