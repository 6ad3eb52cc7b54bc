"""The teacher's public stages compose with jax.jit, jax.vmap and jax.grad (and jax.jvp)
with the program store enabled, and compute what the same calls compute without it.

The stages run a fixed number of Levenberg-Marquardt steps in a `fori_loop` whose count is
traced (one program serves every count), so reverse mode does not pass through the solver
itself (`lax.while_loop`): gradients are taken through `pooled_betas` and `smooth_track`,
forward mode (`jax.jvp`) through the solver stages."""

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest

import fitting
from esther_jax import compilation, mano
from esther_jax.cameras import rig_preset
from fitting import stages

from .helpers import tree_allclose

FRAMES = 16
TOLERANCE = dict(rtol=2e-3, atol=1e-4)
"""Programs compiled whole (the stages inside one `jax.jit`) are fused differently from the
stages' own programs: in float32 the solver's steps carry those rounding differences to
about 1e-4 relative (the shape's betas)."""
STAGE_OPTIONS = dict(steps=2)
MOTION_OPTIONS = dict(steps=2, window=8, stride=4)


def _teacher_inputs(seed: int):
    """A hand seen by both views of the paper's rig, its keypoints projected from a known
    pose (no noise): the stages' inputs as `label_hand` builds them."""
    rng = np.random.default_rng(seed)
    model = mano.load_builtin("right")
    rig = rig_preset("esther")
    t = np.linspace(0.0, 1.0, FRAMES)[:, None]
    params = mano.ManoParams(
        global_orient=jnp.asarray(np.array([2.6, 0.2, -0.3]) + 0.2 * t * rng.normal(size=3), jnp.float32),
        hand_pose=jnp.asarray(np.broadcast_to(0.15 * rng.normal(size=(15, 3)), (FRAMES, 15, 3)), jnp.float32),
        betas=jnp.zeros((FRAMES, 10), jnp.float32),
        transl=jnp.asarray(np.array([0.05, 0.1, 0.4]) + 0.05 * t * rng.normal(size=3), jnp.float32),
    )
    joints = jax.vmap(lambda p: mano.forward_joints(model, p))(params)  # (T, 21, 3), rig frame
    uv = jnp.stack([jax.vmap(lambda X: rig.project(X)[v])(joints) for v in range(2)], axis=1)  # (T, 2, 21, 2)
    box = jnp.concatenate([uv.min(axis=2), uv.max(axis=2)], axis=-1)
    fused = fitting.fuse(uv[None], jnp.ones(uv.shape[:-1])[None], box[None], jnp.ones(uv.shape[:2])[None])
    evidence = fitting.prefilter(rig, fused, fitting.template_bones(model))
    zeros = jnp.zeros(10, jnp.float32)
    problem = fitting.Problem(
        model, rig, mano.PosePrior.from_model(model, zeros), fitting.MotionPrior(), fitting.FitWeights(), zeros, jnp.asarray(30.0, jnp.float32)
    )
    problem = jax.tree.map(lambda x: jnp.asarray(x, jnp.float32) if eqx.is_inexact_array_like(x) else x, problem)
    initial = fitting.initialise(model, rig, evidence, zeros)
    data = fitting.frame_data(evidence, initial, problem)
    start = stages.start_fits(initial, jnp.broadcast_to(model.hands_mean.reshape(15, 3), (FRAMES, 15, 3)), zeros)
    observed = jnp.ones(FRAMES, bool)
    return problem, data, start, observed


def _run_stages(problem, data, start, observed):
    lock = fitting.shape_lock(problem, data, start, observed, observed, frames=8, **STAGE_OPTIONS)
    fits = fitting.fit_frames(problem, data, lock.fits, **STAGE_OPTIONS)
    return lock.betas, fitting.refine_motion(problem, data, fits, observed, **MOTION_OPTIONS)


@pytest.fixture(scope="module")
def inputs():
    return _teacher_inputs(0), _teacher_inputs(1)


@pytest.fixture(scope="module")
def without_store(inputs):
    """The same calls with the program store off (eagerly: the stages' own jit)."""
    saved = list(compilation._store)
    compilation._store.clear()
    try:
        yield [_run_stages(*one) for one in inputs]
    finally:
        compilation._store[:] = saved


@pytest.fixture
def with_store(tmp_path, monkeypatch):
    monkeypatch.setattr(compilation, "_store", [tmp_path / compilation.PROGRAMS])
    (tmp_path / compilation.PROGRAMS).mkdir()
    return tmp_path / compilation.PROGRAMS


def test_the_stages_under_jit_equal_the_calls_without_the_store(inputs, without_store, with_store):
    direct = _run_stages(*inputs[0])  # the store's own, compiled programs
    assert list(with_store.glob("*.jaxexport"))
    jitted = jax.jit(_run_stages)(*inputs[0])
    for got in (direct, jitted):
        assert tree_allclose(got, without_store[0], **TOLERANCE)


def test_the_stages_under_vmap_equal_each_call_without_the_store(inputs, without_store, with_store):
    stacked = jax.tree.map(lambda *xs: jnp.stack(xs), *inputs)
    batched = jax.vmap(_run_stages)(*stacked)
    for i, expected in enumerate(without_store):
        assert tree_allclose(jax.tree.map(lambda x: x[i], batched), expected, **TOLERANCE)


def test_gradients_through_the_stages_with_and_without_the_store(inputs, with_store, monkeypatch):
    problem, data, start, observed = inputs[0]
    lock = fitting.shape_lock(problem, data, start, observed, observed, frames=8, **STAGE_OPTIONS)
    y = stages._unknowns(lock.fits, data, problem.betas)
    track = stages.Track.none(FRAMES, jnp.float32)
    free = stages.Round.make(1.0, 1.0, 0.0, jnp.float32)

    def shape_of(uv):  # reverse mode: the pooled shape's dependence on the 2D evidence
        return jnp.sum(fitting.pooled_betas(problem, y, eqx.tree_at(lambda d: d.uv, data, uv), track, free, observed) ** 2)

    def smoothed(fits_transl):
        fits = eqx.tree_at(lambda f: f.transl, lock.fits, fits_transl)
        return jnp.sum(stages.smooth_track(problem, fits, jnp.ones(FRAMES), observed, window=8, stride=4).transl_target ** 2)

    def fitted(uv):  # forward mode through the solver stage
        return fitting.fit_frames(problem, eqx.tree_at(lambda d: d.uv, data, uv), lock.fits, **STAGE_OPTIONS).transl

    tangent = jnp.ones_like(data.uv)
    results = []
    for store in (True, False):
        if not store:
            monkeypatch.setattr(compilation, "_store", [])
        results.append((jax.grad(shape_of)(data.uv), jax.grad(smoothed)(lock.fits.transl), jax.jvp(fitted, (data.uv,), (tangent,))))
    on, off = results
    assert all(bool(jnp.all(jnp.isfinite(leaf))) for leaf in jax.tree.leaves(on))
    assert float(jnp.max(jnp.abs(on[0]))) > 0.0 and float(jnp.max(jnp.abs(on[2][1]))) > 0.0  # gradients reach the evidence
    assert tree_allclose(on, off, rtol=2e-3, atol=1e-5)
