"""MediaPipe's hand landmark network converted to Equinox (`esther_jax.model.mediapipe_hand`)
against LiteRT's own interpreter, on the same batch of 224 px crops in the same run.

    python benchmarks/hand_backbone.py [--batch 32] [--rounds 5] [--threads N] [--grad]

Rows: the converted network's forward (`jit(vmap(net))`, all outputs), its stride-16
feature map alone (what patch tokens need), with `--grad` a forward and backward pass
(d(mean of the stride-16 map squared) / d(weights), fine-tuning's cost); LiteRT
(ai-edge-litert, the test extra) with its default XNNPACK delegate, on the whole batch in
one invoke (its input resized to the batch) and one crop at a time, on `--threads`
threads (default: the cores JAX sees). Every row is compiled / warmed first, then timed
as the median of interleaved rounds (`_timing.interleaved`). The script also prints the
largest relative difference of the outputs from LiteRT's on the batch (the tests' measure).
Crops: real photos' hands, where a folder of real test data is given
(`$ESTHER_SHARED_DATA/mediapipe_oracle`: photos with MediaPipe's reference keypoints), cut
by `mediapipe_hand.upright_crop`, filled up with deterministic noise; noise alone otherwise.
"""

import argparse
import json
import os
import pathlib
import sys

import cv2
import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

sys.path.insert(0, os.path.dirname(__file__))
from _timing import compile_seconds, interleaved, machine  # noqa: E402

from esther_jax.model import mediapipe_hand as mph  # noqa: E402
from esther_jax.model.tflite import load_tflite  # noqa: E402


ORACLE = pathlib.Path(os.environ.get("ESTHER_SHARED_DATA", pathlib.Path(__file__).resolve().parents[2] / "shared" / "data")) / "mediapipe_oracle"


def crops(batch: int) -> np.ndarray:
    found = []
    if ORACLE.is_dir():
        results = json.loads((ORACLE / "mediapipe_tasks_outputs.json").read_text())["results"]
        for name in ("hand_thumb_up.jpg", "hands.jpg"):
            image = cv2.cvtColor(cv2.imread(str(ORACLE / name)), cv2.COLOR_BGR2RGB)
            found += [mph.upright_crop(image, np.asarray(hand["pixels"])) for hand in results[name]["hands"]]
    rng = np.random.default_rng(0)
    found += [rng.random((224, 224, 3), dtype=np.float32) for _ in range(batch - len(found))]
    return np.stack(found[:batch])


def main():
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--batch", type=int, default=32)
    parser.add_argument("--rounds", type=int, default=5)
    parser.add_argument("--threads", type=int, default=len(os.sched_getaffinity(0)))
    parser.add_argument("--grad", action="store_true")
    args = parser.parse_args()
    from ai_edge_litert.interpreter import Interpreter

    model = mph.landmark_model_bytes()
    net = mph.MediaPipeHand(load_tflite(model))
    images = crops(args.batch)
    x = jnp.asarray(images)

    forward = eqx.filter_jit(jax.vmap(lambda n, im: n.graph(im), in_axes=(None, 0)))
    stride16 = eqx.filter_jit(jax.vmap(lambda n, im: n.features(im, ("stride16",))["stride16"], in_axes=(None, 0)))

    @eqx.filter_jit
    @eqx.filter_grad
    def grad(n):
        return jnp.mean(jax.vmap(lambda im: n.features(im, ("stride16",))["stride16"])(x) ** 2)

    compile_s = {"jax forward": compile_seconds(forward, net, x), "jax stride16": compile_seconds(stride16, net, x)}
    if args.grad:
        compile_s["jax fwd+grad"] = compile_seconds(grad, net)

    batched = Interpreter(model_content=model, num_threads=args.threads)
    batched.resize_tensor_input(batched.get_input_details()[0]["index"], list(images.shape))
    batched.allocate_tensors()
    single = Interpreter(model_content=model, num_threads=args.threads)
    single.allocate_tensors()
    outputs = [d["index"] for d in sorted(batched.get_output_details(), key=lambda d: d["index"])]

    def litert_batch():
        batched.set_tensor(batched.get_input_details()[0]["index"], images)
        batched.invoke()
        return [batched.get_tensor(i) for i in outputs]

    def litert_loop():
        for image in images:
            single.set_tensor(single.get_input_details()[0]["index"], image[None])
            single.invoke()
        return single.get_tensor(outputs[0])

    ours = forward(net, x)
    reference = litert_batch()
    order = {i: k for k, i in enumerate(net.graph.outputs)}
    worst = max(
        float(np.abs(np.asarray(ours[order[i]]) - ref).max() / np.abs(ref).max()) for i, ref in zip(outputs, reference)
    )

    candidates = {
        "jax forward": lambda: forward(net, x),
        "jax stride16": lambda: stride16(net, x),
        "litert batch": litert_batch,
        "litert loop": litert_loop,
    }
    if args.grad:
        candidates["jax fwd+grad"] = lambda: grad(net)
    seconds = interleaved(candidates, rounds=args.rounds)

    print(f"{machine()}, {jax.devices()[0].device_kind}; LiteRT XNNPACK on {args.threads} threads")
    print(f"batch of {args.batch} crops at 224 px, float32; max relative difference of the outputs from LiteRT's: {worst:.1e}")
    print(f"{'row':<16}{'ms / batch':>12}{'ms / crop':>11}{'vs litert batch':>17}{'compile s':>11}")
    for name, s in seconds.items():
        ratio = s / seconds["litert batch"]
        print(f"{name:<16}{1e3 * s:>12.1f}{1e3 * s / args.batch:>11.2f}{ratio:>16.2f}x{compile_s.get(name, float('nan')):>11.1f}")


if __name__ == "__main__":
    main()
