"""clips.Labels: the labels.npz file round-trips bit for bit, the value composes with
jax.vmap / jax.jit (a pytree of per-frame MANO parameters), and bad files or values are
refused with the problem named."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from esther_jax import clips, mano
from esther_jax.files import named_folders

T = 5


def _labels(key=0) -> clips.Labels:
    rng = np.random.default_rng(key)
    f32 = lambda *shape: jnp.asarray(rng.normal(size=shape).astype(np.float32))  # noqa: E731
    params = mano.ManoParams(0.3 * f32(T, 3), 0.2 * f32(T, 15, 3), jnp.broadcast_to(f32(10), (T, 10)), f32(T, 3))
    residual = f32(T).at[1].set(jnp.nan)  # NaN: not observed
    return clips.Labels(params, f32(T, 21, 3), jnp.ones(T, bool), jnp.arange(T) % 2 == 0, residual, stereo=jnp.arange(T) < 3)


def test_labels_round_trip_through_the_file_format(tmp_path):
    labels = _labels()
    path = labels.to_npz(tmp_path / "labels.npz")
    with np.load(path) as data:  # the file format: one betas per hand, the teacher's keys
        assert data["betas"].shape == (10,) and set(data.files) == set(clips.SCHEMAS["labels"]) | {"stereo"}
    again = clips.Labels.from_npz(path)
    assert again.converged is None and again.onscreen_prob is None
    for (where, a), b in zip(jax.tree_util.tree_leaves_with_path(labels), jax.tree.leaves(again)):
        assert a.dtype == b.dtype, jax.tree_util.keystr(where)
        np.testing.assert_array_equal(a, b, err_msg=jax.tree_util.keystr(where))
    np.testing.assert_array_equal(again.betas, labels.params.betas[0])


def test_labels_compose_with_vmap_and_jit():
    labels, model = _labels(), mano.load_builtin("right")
    joints = jax.jit(jax.vmap(lambda p: mano.forward_joints(model, p)))(labels.params)
    assert joints.shape == (T, 21, 3)
    np.testing.assert_allclose(joints[2], mano.forward_joints(model, labels.frame(np.int64(2))), atol=1e-6)
    shifted = jax.jit(lambda l: jax.tree.map(lambda a: a + 1.0 if a.dtype == jnp.float32 else a, l))(labels)
    assert isinstance(shifted, clips.Labels) and bool(jnp.all(shifted.valid == labels.valid))


def test_bad_labels_are_refused_with_the_problem_named(tmp_path):
    labels = _labels()
    varying = clips.Labels(mano.ManoParams(labels.params.global_orient, labels.params.hand_pose,
                                           labels.params.betas.at[0, 0].add(1.0), labels.params.transl),
                           labels.joints, labels.onscreen, labels.valid, labels.residual_px)  # fmt: skip
    with pytest.raises(ValueError, match="one shape per hand"):
        varying.to_npz(tmp_path / "x.npz")
    arrays = {k: np.asarray(v) for k, v in np.load(labels.to_npz(tmp_path / "ok.npz")).items()}
    clips.save_npz(tmp_path / "extra.npz", **{**arrays, "stereo": np.ones(T + 1, bool)})
    with pytest.raises(clips.ClipFormatError, match=r"stereo has shape \(6,\), expected \[5\]"):
        clips.Labels.from_npz(tmp_path / "extra.npz")
    clips.save_npz(tmp_path / "nan.npz", **{**arrays, "joints": np.full((T, 21, 3), np.nan, np.float32)})
    with pytest.raises(clips.ClipFormatError, match="joints contains NaN"):
        clips.Labels.from_npz(tmp_path / "nan.npz")
    with pytest.raises(clips.ClipFormatError, match="does not exist"):
        clips.Labels.from_npz(tmp_path / "missing.npz")


def test_named_folders_keeps_each_folder_once_and_refuses_a_name_clash(tmp_path, monkeypatch):
    (tmp_path / "a" / "clip").mkdir(parents=True)
    (tmp_path / "b" / "clip").mkdir(parents=True)
    (tmp_path / "b" / "link").symlink_to(tmp_path / "a" / "clip")
    monkeypatch.chdir(tmp_path / "a")
    same = named_folders(["clip", tmp_path / "a" / "clip", "../a/clip", tmp_path / "b" / "link"])
    assert same == [tmp_path / "a" / "clip", tmp_path / "b" / "link"]  # one folder three ways; a link keeps its own name
    monkeypatch.chdir(tmp_path / "a" / "clip")
    assert named_folders(["."]) == [tmp_path / "a" / "clip"]  # "." is the folder by its name
    with pytest.raises(ValueError, match="two recordings share the name 'clip'"):
        named_folders([tmp_path / "a" / "clip", tmp_path / "b" / "clip"], "recordings")
    with pytest.raises(ValueError, match="no folder name"):
        named_folders(["/"])
