import jax
import jax.numpy as jnp
import numpy as np
import pytest
from scipy.linalg import orthogonal_procrustes
from scipy.spatial.transform import Rotation

from esther_jax import cameras, metrics

from .helpers import finite_difference_jacobian


def hand(rng, n=21):
    return rng.normal(scale=0.04, size=(n, 3)) + np.array([0.0, 0.0, 0.4])


def similarity(points, rng, scale=None):
    R = Rotation.random(random_state=int(rng.integers(1 << 30))).as_matrix()
    s = rng.uniform(0.5, 2.0) if scale is None else scale
    return s * points @ R.T + rng.normal(size=3)


def freihand_align_w_scale(gt, pred):
    """FreiHAND / HO3D eval.py reference (scipy orthogonal Procrustes with scale)."""
    t1, t2 = gt.mean(0), pred.mean(0)
    g, p = gt - t1, pred - t2
    s1, s2 = np.linalg.norm(g), np.linalg.norm(p)
    g, p = g / s1, p / s2
    R, s = orthogonal_procrustes(g, p)
    return p @ R.T * s * s1 + t1


def test_pa_mpjpe_is_zero_for_a_similarity_transformed_truth(x64):
    rng = np.random.default_rng(0)
    for _ in range(10):
        gt = hand(rng)
        pred = similarity(gt, rng)
        assert float(metrics.pa_mpjpe(jnp.asarray(pred), jnp.asarray(gt))) < 1e-12
        assert float(metrics.mpjpe(jnp.asarray(pred), jnp.asarray(gt))) > 1e-3


def test_pa_mpjpe_matches_the_scipy_reference(x64):
    rng = np.random.default_rng(1)
    for _ in range(20):
        gt = hand(rng)
        pred = similarity(gt + rng.normal(scale=0.005, size=gt.shape), rng)
        ref = np.mean(np.linalg.norm(freihand_align_w_scale(gt, pred) - gt, axis=1))
        np.testing.assert_allclose(float(metrics.pa_mpjpe(jnp.asarray(pred), jnp.asarray(gt))), ref, rtol=1e-9)


def test_pa_mpjpe_never_reflects(x64):
    rng = np.random.default_rng(2)
    gt = hand(rng)
    mirrored = gt * np.array([-1.0, 1.0, 1.0])
    ours = float(metrics.pa_mpjpe(jnp.asarray(mirrored), jnp.asarray(gt)))
    reflecting = np.mean(np.linalg.norm(freihand_align_w_scale(gt, mirrored) - gt, axis=1))
    assert reflecting < 1e-9 < 1e-3 < ours  # the reference "fixes" a mirror image; ours does not
    aligned = np.asarray(metrics.procrustes_align(jnp.asarray(mirrored), jnp.asarray(gt)))
    # the fitted map is a proper similarity: it preserves orientation of every triangle
    tri = lambda x: np.linalg.det(np.stack([x[1] - x[0], x[2] - x[0], x[3] - x[0]]))  # noqa: E731
    assert np.sign(tri(aligned)) == np.sign(tri(mirrored))


def test_p_mpjpe_ignores_translation_and_mpjpe_does_not(x64):
    rng = np.random.default_rng(3)
    gt = hand(rng)
    pred = gt + rng.normal(scale=0.004, size=gt.shape)
    shift = np.array([0.1, -0.2, 0.3])
    a = metrics.p_mpjpe(jnp.asarray(pred), jnp.asarray(gt))
    b = metrics.p_mpjpe(jnp.asarray(pred + shift), jnp.asarray(gt))
    np.testing.assert_allclose(float(a), float(b), rtol=1e-12)
    assert float(metrics.mpjpe(jnp.asarray(pred + shift), jnp.asarray(gt))) > 0.3
    np.testing.assert_allclose(float(metrics.wrist_error(jnp.asarray(pred + shift), jnp.asarray(gt))), np.linalg.norm(pred[0] + shift - gt[0]))


def test_masks_and_no_data():
    gt = jnp.zeros((21, 3))
    pred = gt.at[5].set(jnp.asarray([1.0, 0.0, 0.0]))
    mask = jnp.ones(21, bool).at[5].set(False)
    assert float(metrics.mpjpe(pred, gt, mask)) == 0.0
    np.testing.assert_allclose(float(metrics.mpjpe(pred, gt)), 1.0 / 21, rtol=1e-6)
    empty = metrics.clip_mean(jnp.full(16, jnp.nan), jnp.zeros(16, bool))
    assert float(empty.count) == 0 and np.isfinite(float(empty.value)) and not bool(empty.has_data)
    sequence = jnp.zeros((16, 21, 3))
    gated_off = metrics.jitter(sequence, jnp.zeros(16, bool), fps=30.0)
    assert float(gated_off.count) == 0 and np.isfinite(float(gated_off.value))
    clips = metrics.Score(value=jnp.asarray([1.0, 0.0, 3.0]), count=jnp.asarray([10.0, 0.0, 30.0]))
    np.testing.assert_allclose(float(metrics.dataset_mean(clips, "clip").value), 2.0)
    np.testing.assert_allclose(float(metrics.dataset_mean(clips, "frame").value), 2.5)
    assert metrics.bootstrap(jnp.full(5, jnp.nan), jax.random.key(0)) is None


def test_jitter_of_constant_acceleration_is_the_acceleration(x64):
    fps, T = 30.0, 40
    t = np.arange(T) / fps
    accel = np.array([0.3, -1.2, 2.0])  # m/s^2
    base = np.random.default_rng(4).normal(scale=0.05, size=(21, 3))
    joints = base[None] + 0.5 * t[:, None, None] ** 2 * accel + t[:, None, None] * np.array([0.1, 0.0, 0.2])
    all_on = metrics.jitter(jnp.asarray(joints), jnp.ones(T, bool), fps)
    np.testing.assert_allclose(float(all_on.value), np.linalg.norm(accel), rtol=1e-9)
    assert float(all_on.count) == T - 2
    for off in (0, 1, 17, T - 1):  # an off-screen frame anywhere: garbage there changes nothing
        broken = joints.copy()
        broken[off] += 5.0
        gated = metrics.jitter(jnp.asarray(broken), jnp.ones(T, bool).at[off].set(False), fps)
        np.testing.assert_allclose(float(gated.value), np.linalg.norm(accel), rtol=1e-9)
        assert float(gated.count) == T - 2 - (1 if off in (0, T - 1) else 2 if off in (1, T - 2) else 3)


def test_pck_and_auc():
    errors = jnp.linspace(0.0, 0.1, 21)
    assert float(metrics.pck(errors, 0.0501)) == pytest.approx(11 / 21)
    assert 0.0 < float(metrics.pck_auc(errors)) < 1.0
    assert float(metrics.pck_auc(jnp.zeros(21))) == pytest.approx(1.0)
    assert float(metrics.pck_auc(jnp.full(21, 0.2))) == pytest.approx(0.0)
    uniform = jnp.linspace(0.0, 0.05, 10001)  # errors uniform on [0, 50 mm]: AUC = 1/2
    assert float(metrics.pck_auc(uniform)) == pytest.approx(0.5, abs=2e-3)


def test_onscreen_rule():
    rig = cameras.rig_preset("esther")
    in_view = jnp.asarray(np.random.default_rng(5).normal(scale=0.02, size=(21, 3)) + np.array([0.0, 0.0, 0.4]))
    assert bool(metrics.onscreen(in_view, rig))
    half_out = in_view.at[:11].add(jnp.asarray([5.0, 0.0, 0.0]))  # 10 joints left in view
    assert not bool(metrics.onscreen(half_out, rig))
    ten_out = in_view.at[:10].add(jnp.asarray([5.0, 0.0, 0.0]))  # 11 = at least half
    assert bool(metrics.onscreen(ten_out, rig))
    assert not bool(metrics.onscreen(in_view * jnp.asarray([[1.0, 1.0, -1.0]]), rig))  # behind the rig


def test_gate_scores():
    truth = jnp.asarray([True, True, False, False, True])
    pred = jnp.asarray([True, False, True, False, True])
    s = metrics.gate_scores(pred, truth)
    assert float(s.precision) == pytest.approx(2 / 3) and float(s.recall) == pytest.approx(2 / 3)
    assert float(s.f1) == pytest.approx(2 / 3)
    perfect = metrics.gate_scores(truth, truth)
    assert float(perfect.f1) == 1.0 and float(metrics.gate_scores(jnp.zeros(3, bool), jnp.zeros(3, bool)).f1) == 1.0


def test_depth_scatter_recovers_a_linear_model(x64):
    rng = np.random.default_rng(6)
    z_gt = rng.uniform(0.2, 0.7, size=20000)
    a, b, sigma = 0.8, 0.07, 0.011
    z_pred = a * z_gt + b + rng.normal(scale=sigma, size=z_gt.shape)
    d = metrics.depth_scatter(jnp.asarray(z_pred), jnp.asarray(z_gt))
    assert float(d.slope) == pytest.approx(a, abs=0.01) and float(d.intercept) == pytest.approx(b, abs=0.005)
    assert float(d.random_mm) == pytest.approx(sigma * 1000, rel=0.03)
    expected_systematic = np.sqrt(np.mean(((a - 1) * z_gt + b) ** 2)) * 1000
    assert float(d.systematic_mm) == pytest.approx(expected_systematic, rel=0.03)
    assert float(d.correlation) == pytest.approx(np.corrcoef(z_pred, z_gt)[0, 1], rel=1e-9)
    masked = metrics.depth_scatter(jnp.asarray(z_pred), jnp.asarray(z_gt), jnp.asarray(rng.uniform(size=z_gt.shape) < 0.5))
    assert float(masked.count) < z_gt.size and float(masked.slope) == pytest.approx(a, abs=0.02)
    # integer weights count a sample that many times (a bootstrap resample)
    k = rng.integers(0, 3, size=200)
    weighted = metrics.depth_scatter(jnp.asarray(z_pred[:200]), jnp.asarray(z_gt[:200]), weights=jnp.asarray(k, jnp.float64))
    repeated = metrics.depth_scatter(jnp.asarray(np.repeat(z_pred[:200], k)), jnp.asarray(np.repeat(z_gt[:200], k)))
    for field in ("slope", "intercept", "correlation", "random_mm", "systematic_mm", "count"):
        assert float(getattr(weighted, field)) == pytest.approx(float(getattr(repeated, field)), rel=1e-9)


def test_bootstrap_is_reproducible_and_covers_at_the_nominal_rate():
    rng = np.random.default_rng(7)
    covered, trials = 0, 300
    for i in range(trials):
        scores = rng.normal(loc=17.7, scale=4.0, size=120)
        b = metrics.bootstrap(scores, jax.random.key(i), n=400)
        covered += b.ci_low <= 17.7 <= b.ci_high
    assert 0.91 <= covered / trials <= 0.98
    a1 = metrics.bootstrap(scores, jax.random.key(3))
    a2 = metrics.bootstrap(scores, jax.random.key(3))
    assert a1 == a2 and a1.num_resamples == 2000 and a1.num_clips == 120
    np.testing.assert_allclose(a1.std, 4.0 / np.sqrt(120), rtol=0.2)
    other = metrics.bootstrap(scores + 5.0, jax.random.key(4))
    assert not metrics.intervals_overlap(a1, other) and metrics.intervals_overlap(a1, a1)
    with_mask = metrics.bootstrap(np.append(scores, 1e9), jax.random.key(3), mask=np.append(np.ones(120, bool), False))
    assert with_mask == a1


def test_metrics_vmap_and_jit_over_sequences():
    rng = np.random.default_rng(8)
    gt = jnp.asarray(np.stack([hand(rng) for _ in range(6)]), jnp.float32)
    pred = gt + jnp.asarray(rng.normal(scale=0.003, size=gt.shape), jnp.float32)
    for fn in (metrics.mpjpe, metrics.p_mpjpe, metrics.pa_mpjpe, metrics.wrist_error):
        batched = jax.jit(jax.vmap(fn))(pred, gt)
        loop = np.asarray([fn(p, g) for p, g in zip(pred, gt)])
        np.testing.assert_allclose(np.asarray(batched), loop, rtol=1e-4, atol=1e-7)
    with pytest.raises((ValueError, TypeError), match="one frame|pred"):  # jaxtyping checks first in tests
        metrics.mpjpe(pred, gt)


def _all_finite(tree):
    return all(np.all(np.isfinite(np.asarray(x))) for x in jax.tree.leaves(tree))


def test_pa_mpjpe_gradients_are_finite_when_the_fit_degenerates():
    rng = np.random.default_rng(9)
    gt = jnp.asarray(hand(rng), jnp.float32)
    pred = gt + jnp.asarray(rng.normal(scale=0.004, size=gt.shape), jnp.float32)
    same = jnp.broadcast_to(jnp.asarray([0.01, -0.02, 0.4], jnp.float32), gt.shape)
    first = lambda k: jnp.arange(21) < k  # noqa: E731
    cases = {
        "all_masked": (pred, gt, jnp.zeros(21, bool)),
        "pred_identical": (same, gt, None),
        "gt_identical": (pred, same, None),
        "both_identical": (same, same, None),
        "one_joint": (pred, gt, first(1)),
        "two_joints": (pred, gt, first(2)),  # rank-1 covariance: two zero singular values
        "perfect_fit": (gt, gt, None),
    }
    for name, (p, g, m) in cases.items():
        value = metrics.pa_mpjpe(p, g, m)
        assert np.isfinite(float(value)), name
        grads = jax.grad(metrics.pa_mpjpe, argnums=(0, 1))(p, g, m)
        assert _all_finite(grads), name
        assert _all_finite(jax.jacfwd(metrics.pa_mpjpe, argnums=(0, 1))(p, g, m)), name
        assert _all_finite(jax.jacrev(metrics.procrustes_align)(p, g, m)), name
    # no spread in the prediction: the best similarity is scale 0 onto the gt centroid
    centroid = np.asarray(gt).mean(0)
    expected = np.mean(np.linalg.norm(np.asarray(gt) - centroid, axis=-1))
    assert float(metrics.pa_mpjpe(same, gt)) == pytest.approx(expected, rel=1e-5)
    assert float(metrics.pa_mpjpe(pred, gt, jnp.zeros(21, bool))) == 0.0


def _svd_pa_mpjpe(pred, gt, mask):
    """The plain Umeyama formulation, differentiated through `jnp.linalg.svd` (the
    implementation before the degenerate cases were made safe)."""
    w = mask.astype(pred.dtype)
    total = jnp.sum(w)
    mu_p, mu_g = jnp.sum(w[:, None] * pred, 0) / total, jnp.sum(w[:, None] * gt, 0) / total
    p, g = pred - mu_p[None], gt - mu_g[None]
    U, S, Vt = jnp.linalg.svd(jnp.einsum("n,ni,nj->ij", w, g, p) / total)
    D = jnp.stack([jnp.ones_like(S[0]), jnp.ones_like(S[0]), jnp.sign(jnp.linalg.det(U @ Vt))])
    R = (U * D[None]) @ Vt
    scale = jnp.sum(S * D) / (jnp.sum(w * jnp.sum(p * p, -1)) / total)
    errors = jnp.sqrt(jnp.sum((scale * p @ R.T + mu_g[None] - gt) ** 2, -1))
    return jnp.sum(w * errors) / total


def test_pa_mpjpe_values_and_gradients_unchanged_in_the_normal_case(x64):
    rng = np.random.default_rng(10)
    gt = hand(rng)
    for pred, mask in (
        (similarity(gt + rng.normal(scale=0.005, size=gt.shape), rng), np.ones(21, bool)),
        (similarity(gt * np.array([-1.0, 1.0, 1.0]), rng), np.ones(21, bool)),  # needs the det = +1 correction
        (similarity(gt + rng.normal(scale=0.005, size=gt.shape), rng), rng.uniform(size=21) < 0.7),
    ):
        m = jnp.asarray(mask)
        x = jnp.asarray(np.concatenate([pred.reshape(-1), gt.reshape(-1)]))
        ours = lambda v: metrics.pa_mpjpe(v[:63].reshape(21, 3), v[63:].reshape(21, 3), m)  # noqa: E731
        plain = lambda v: _svd_pa_mpjpe(v[:63].reshape(21, 3), v[63:].reshape(21, 3), m)  # noqa: E731
        assert float(ours(x)) == pytest.approx(float(plain(x)), rel=1e-12)
        grad = np.asarray(jax.grad(ours)(x))
        np.testing.assert_allclose(grad, np.asarray(jax.grad(plain)(x)), rtol=1e-9, atol=1e-13)
        np.testing.assert_allclose(grad, np.asarray(jax.jacfwd(ours)(x)), rtol=1e-9, atol=1e-13)
        np.testing.assert_allclose(grad, finite_difference_jacobian(lambda v: ours(v)[None], np.asarray(x), h=1e-7)[0], rtol=1e-5, atol=1e-7)


def test_depth_scatter_gradients_are_finite_at_zero_error():
    rng = np.random.default_rng(11)
    z_gt = jnp.asarray(rng.uniform(0.2, 0.7, size=64), jnp.float32)
    constant = jnp.full((64,), 0.4, jnp.float32)
    fields = ("slope", "intercept", "correlation", "systematic_mm", "random_mm", "rmse_mm")
    for name, (zp, zg) in {"exact": (z_gt, z_gt), "constant_pred": (constant, z_gt), "constant_gt": (z_gt, constant),
                           "all_constant": (constant, constant)}.items():  # fmt: skip
        d = metrics.depth_scatter(zp, zg)
        assert _all_finite(d), name
        for field in fields:
            g = jax.grad(lambda a, b, field=field: getattr(metrics.depth_scatter(a, b), field), argnums=(0, 1))(zp, zg)
            assert _all_finite(g), (name, field)
    exact = metrics.depth_scatter(z_gt, z_gt)
    assert float(exact.rmse_mm) == 0.0 and float(exact.slope) == pytest.approx(1.0, abs=1e-5)
    # normal case: values as the plain formulas
    z_pred = 0.9 * z_gt + 0.02 + jnp.asarray(rng.normal(scale=0.01, size=64), jnp.float32)
    d = metrics.depth_scatter(z_pred, z_gt)
    zp, zg = np.asarray(z_pred, np.float64), np.asarray(z_gt, np.float64)
    assert float(d.rmse_mm) == pytest.approx(np.sqrt(np.mean((zp - zg) ** 2)) * 1000, rel=1e-4)
    assert float(d.correlation) == pytest.approx(np.corrcoef(zp, zg)[0, 1], rel=1e-4)


def test_wrist_axes_locate_an_error_per_axis_and_along_the_line_of_sight():
    rng = np.random.default_rng(0)
    truth = jnp.asarray(np.c_[rng.uniform(-0.2, 0.2, 64), rng.uniform(-0.1, 0.2, 64), rng.uniform(0.3, 0.6, 64)])
    pred = truth.at[:, 1].set(0.05)  # y not learned: a constant height
    axes = jax.tree.map(np.asarray, metrics.wrist_axes(pred, truth))
    np.testing.assert_allclose(axes.mae_mm[[0, 2]], 0.0, atol=1e-9)
    np.testing.assert_allclose(axes.mae_mm[1], 1000 * np.mean(np.abs(0.05 - np.asarray(truth[:, 1]))), rtol=1e-5)
    np.testing.assert_allclose(axes.correlation[[0, 2]], 1.0, rtol=1e-5)
    assert abs(axes.correlation[1]) < 1e-6 and axes.pred_sd_mm[1] < 1e-3 < axes.true_sd_mm[1]
    # on the optical axis, a y error is all across the line of sight, a z error all along it
    on_axis = jnp.asarray([[0.0, 0.0, 0.4]])
    across = metrics.wrist_axes(on_axis + jnp.asarray([[0.0, 0.01, 0.0]]), on_axis)
    along = metrics.wrist_axes(on_axis + jnp.asarray([[0.0, 0.0, -0.02]]), on_axis)
    np.testing.assert_allclose([across.across_mm, across.along_mm, along.across_mm, along.along_mm], [10.0, 0.0, 0.0, 20.0], atol=1e-4)
    with pytest.raises((ValueError, TypeError), match="truth"):  # jaxtyping checks first in tests
        metrics.wrist_axes(truth, truth[:, :2])
    with pytest.raises(ValueError, match="no wrists"):
        metrics.wrist_axes(truth[:0], truth[:0])
