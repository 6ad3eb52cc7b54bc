"""TFLite flatbuffers as Equinox modules: a graph's float weights become arrays (jit, vmap,
grad and a bfloat16 cast of the float leaves all work), its operators a static program
evaluated in `jax.numpy` / `jax.lax` with TFLite's semantics.

`load_tflite(data)` parses a `.tflite` file with the `tflite` package (pure Python over
flatbuffers; `python -m pip install tflite`, or the `detect` extra), imported only when
called. Stored float16 weights (the DEQUANTIZE ops in front of them are folded) and int8 /
uint8 weights with a scale and zero point (per tensor or per channel) become float32
arrays. The graph is written for one example: a TFLite image model's leading batch
dimension of 1 is added on the way in and dropped on the way out, and `jax.vmap` batches it
(XLA folds the mapped axis into the convolutions' batch dimension).

Operators (`SUPPORTED_OPS`): CONV_2D, DEPTHWISE_CONV_2D, FULLY_CONNECTED, ADD, SUB, MUL,
MAX_POOL_2D, AVERAGE_POOL_2D, MEAN, RESHAPE, PAD, PADV2, CONCATENATION, RESIZE_BILINEAR,
LOGISTIC, TANH, RELU, RELU6, HARD_SWISH, PRELU, SOFTMAX, DEQUANTIZE, with the fused
activations NONE, RELU, RELU_N1_TO_1 and RELU6. A graph with any other operator, a
custom operator, quantised activations or several subgraphs is refused at load time with
the operator named. Semantics follow TFLite's reference kernels
(tensorflow/lite/kernels/internal/reference/): SAME padding puts the odd pixel after (as
`lax`'s "SAME"), average pooling divides by the pixels inside the image, bilinear
resizing uses `ComputeInterpolationValues` (half-pixel centres, aligned corners or
neither).
"""

import dataclasses
import pathlib
from collections.abc import Callable, Sequence
from typing import Any

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Float, Shaped

SUPPORTED_OPS = (
    "CONV_2D", "DEPTHWISE_CONV_2D", "FULLY_CONNECTED", "ADD", "SUB", "MUL", "MAX_POOL_2D", "AVERAGE_POOL_2D",
    "MEAN", "RESHAPE", "PAD", "PADV2", "CONCATENATION", "RESIZE_BILINEAR", "LOGISTIC", "TANH", "RELU", "RELU6",
    "HARD_SWISH", "PRELU", "SOFTMAX", "DEQUANTIZE",
)  # fmt: skip
"""TFLite builtin operators `load_tflite` converts."""

_ACTIVATIONS = {0: "NONE", 1: "RELU", 2: "RELU_N1_TO_1", 3: "RELU6"}
"""tflite.ActivationFunctionType values the converter applies. TANH (4) and SIGN_BIT (5) are
refused: LiteRT's convolution, pooling, elementwise and FULLY_CONNECTED kernels clamp to
`CalculateActivationRange`, which knows only the ReLUs and silently ignores the others."""
_PADDINGS = {0: "SAME", 1: "VALID"}
_NUMPY_TYPES = {
    "FLOAT32": np.float32, "FLOAT16": np.float16, "FLOAT64": np.float64, "INT32": np.int32, "INT64": np.int64,
    "INT8": np.int8, "UINT8": np.uint8, "INT16": np.int16, "BOOL": np.bool_,
}  # fmt: skip


class UnsupportedTFLiteGraph(ValueError):
    """A TFLite graph uses an operator or feature the converter does not implement."""


@dataclasses.dataclass(frozen=True)
class TensorInfo:
    """A tensor of the graph as the flatbuffer declares it."""

    name: str
    shape: tuple[int, ...]
    """TFLite's static shape, leading batch dimension included."""
    dtype: str
    """TFLite's type name (FLOAT32, FLOAT16, INT8, ...)."""


@dataclasses.dataclass(frozen=True)
class Node:
    """One operator: tensor indices in and out, and its options, all hashable (static)."""

    op: str
    """The builtin operator's name, e.g. "CONV_2D"."""
    inputs: tuple[int, ...]
    """Tensors read at run time (activations and float weights); constant integer inputs
    (axes, paddings, sizes) are folded into `options`."""
    outputs: tuple[int, ...]
    options: tuple[tuple[str, Any], ...]

    def option(self, key: str) -> Any:
        return dict(self.options)[key]


class TFLiteGraph(eqx.Module):
    """A TFLite graph (subgraph 0) as an Equinox module; see the module docstring.

    Calling it on one example per graph input returns the graph's outputs in its order;
    `tensor_values` returns any tensors by name (intermediate feature maps), evaluating
    only the operators they depend on.
    """

    params: dict[str, Float[Array, "..."]]
    """The float constants (weights, biases, PReLU slopes) by tensor name, dequantised;
    for a folded DEQUANTIZE the name of its float output."""
    tensors: tuple[TensorInfo, ...] = eqx.field(static=True)
    nodes: tuple[Node, ...] = eqx.field(static=True)
    """Operators in execution order."""
    inputs: tuple[int, ...] = eqx.field(static=True)
    outputs: tuple[int, ...] = eqx.field(static=True)
    batched: bool = eqx.field(static=True)
    """Every graph input and output has a leading batch dimension of 1, which the module's
    one-example interface leaves out."""

    def __check_init__(self):
        missing = [self.tensors[i].name for n in self.nodes for i in n.inputs if i >= 0 and not self._produced(i)]
        if missing:
            raise ValueError(f"tensors read by the graph but neither inputs, weights nor produced: {missing[:5]}")

    def _produced(self, index: int) -> bool:
        return index in self.inputs or self.tensors[index].name in self.params or any(index in n.outputs for n in self.nodes)

    def index(self, name: str) -> int:
        """The index of the tensor called `name` (a `KeyError` naming near matches otherwise)."""
        for i, t in enumerate(self.tensors):
            if t.name == name:
                return i
        near = [t.name for t in self.tensors if name.lower() in t.name.lower()][:5]
        raise KeyError(f"no tensor {name!r} in the graph; names containing it: {near}")

    def shape(self, name: str) -> tuple[int, ...]:
        """The per-example shape of a tensor (without the batch dimension when `batched`)."""
        shape = self.tensors[self.index(name)].shape
        return shape[1:] if self.batched and shape[:1] == (1,) else shape

    @property
    def dtype(self) -> Any:
        """The compute dtype: that of the float weights (inputs are cast to it)."""
        leaves = jax.tree.leaves(self.params)
        return jnp.result_type(*leaves) if leaves else jnp.result_type(float)

    def __call__(self, *inputs: Shaped[Array, "..."]) -> tuple[Float[Array, "..."], ...]:
        values = self._evaluate(inputs, self.outputs, strict=True)
        return tuple(values[i] for i in self.outputs)

    def tensor_values(self, *inputs: Shaped[Array, "..."], names: Sequence[str], strict: bool = True) -> dict[str, Float[Array, "..."]]:
        """The values of the tensors called `names`, one example (see `shape`).

        strict=False accepts inputs of other spatial sizes than the graph declares: right
        for the convolutional operators, wrong past a RESHAPE or FULLY_CONNECTED sized for
        the declared input (which then fail on the shapes).
        """
        wanted = tuple(self.index(n) for n in names)
        values = self._evaluate(inputs, wanted, strict=strict)
        return {n: values[i] for n, i in zip(names, wanted)}

    def _evaluate(self, inputs: Sequence[Array], wanted: tuple[int, ...], strict: bool) -> dict[int, Array]:
        if len(inputs) != len(self.inputs):
            raise ValueError(f"the graph takes {len(self.inputs)} inputs, got {len(inputs)}")
        dtype = self.dtype
        env: dict[int, Array] = {}
        for i, x in zip(self.inputs, inputs):
            info = self.tensors[i]
            expected = info.shape[1:] if self.batched else info.shape
            x = jnp.asarray(x)
            if x.shape != expected and (strict or x.ndim != len(expected) or x.shape[-1:] != expected[-1:]):
                raise ValueError(f"input {info.name!r} must have shape {expected} (one example), got {x.shape}")
            x = x.astype(dtype) if info.dtype.startswith("FLOAT") else x
            env[i] = x[None] if self.batched else x
        for node in self._needed(wanted):
            args = [None if j < 0 else env[j] if j in env else self.params[self.tensors[j].name] for j in node.inputs]
            outs = _APPLY[node.op](node, self.tensors, *args)
            env.update(zip(node.outputs, outs))
        missing = [self.tensors[i].name for i in wanted if i not in env]
        if missing:
            raise KeyError(f"{missing} are weights or unused tensors, not values the graph computes")
        if self.batched:
            return {i: env[i][0] if env[i].shape[:1] == (1,) else env[i] for i in wanted}
        return {i: env[i] for i in wanted}

    def _needed(self, wanted: tuple[int, ...]) -> list[Node]:
        """The nodes `wanted` depends on, in execution order (static: unrolled when traced)."""
        producer = {o: k for k, n in enumerate(self.nodes) for o in n.outputs}
        keep, todo = set(), [producer[i] for i in wanted if i in producer]
        while todo:
            k = todo.pop()
            if k not in keep:
                keep.add(k)
                todo += [producer[j] for j in self.nodes[k].inputs if j in producer]
        return [n for k, n in enumerate(self.nodes) if k in keep]

    def summary(self) -> str:
        """One line per operator: op, input and output shapes, output name."""
        lines = []
        for n in self.nodes:
            ins = ", ".join(str(self.tensors[j].shape) for j in n.inputs if j >= 0)
            lines.append(f"{n.op:18s} {ins} -> {self.tensors[n.outputs[0]].shape} {self.tensors[n.outputs[0]].name}")
        return "\n".join(lines)


# ----------------------------------------------------------------------------- operators


def _activation(x: Array, name: str) -> Array:
    if name == "NONE":
        return x
    if name == "RELU":
        return jnp.maximum(x, 0.0)
    if name == "RELU6":
        return jnp.clip(x, 0.0, 6.0)
    if name == "RELU_N1_TO_1":
        return jnp.clip(x, -1.0, 1.0)
    raise UnsupportedTFLiteGraph(f"fused activation {name}")


def _channels_last(bias: Array, ndim: int) -> Array:
    """A per-channel vector shaped to broadcast over an (N, ..., C) tensor without rank promotion."""
    return bias.reshape((1,) * (ndim - 1) + (-1,))


def _same_rank(a: Array, b: Array) -> tuple[Array, Array]:
    """Prepend unit axes to the lower-rank operand (TFLite's numpy-style broadcasting,
    spelled out for `jax_numpy_rank_promotion="raise"`)."""
    if a.ndim < b.ndim:
        a = a.reshape((1,) * (b.ndim - a.ndim) + a.shape)
    elif b.ndim < a.ndim:
        b = b.reshape((1,) * (a.ndim - b.ndim) + b.shape)
    return a, b


def _conv(node: Node, tensors, x, w, b):
    groups = x.shape[-1] // w.shape[-1]
    if w.shape[1:3] == (1, 1) and groups == 1:  # pointwise: a matrix product (XLA's CPU dot beats its 1x1 conv)
        sh, sw = node.option("stride")
        y = jnp.einsum("nhwc,oc->nhwo", x[:, ::sh, ::sw], w[:, 0, 0].astype(x.dtype))
    else:
        y = jax.lax.conv_general_dilated(
            x, w.astype(x.dtype), node.option("stride"), node.option("padding"), rhs_dilation=node.option("dilation"),
            dimension_numbers=("NHWC", "OHWI", "NHWC"), feature_group_count=groups,
        )  # fmt: skip
    y = y if b is None else y + _channels_last(b, y.ndim)
    return (_activation(y, node.option("activation")),)


def _depthwise(node: Node, tensors, x, w, b):
    # A sum of shifted, strided slices times the per-channel taps: on CPU, XLA runs a
    # grouped convolution (feature_group_count = channels) 4 to 20 times slower
    # (benchmarks/hand_backbone.py). TFLite's filter is (1, H, W, C * multiplier), output
    # channel c * multiplier + m reading input channel c.
    kh, kw, out_channels = w.shape[1:]
    if out_channels != x.shape[-1]:
        x = jnp.repeat(x, out_channels // x.shape[-1], axis=-1)
    (sh, sw), (dh, dw) = node.option("stride"), node.option("dilation")
    window = ((kh - 1) * dh + 1, (kw - 1) * dw + 1)
    (top, bottom), (left, right) = jax.lax.padtype_to_pads(x.shape[1:3], window, (sh, sw), node.option("padding"))
    x = jnp.pad(x, ((0, 0), (top, bottom), (left, right), (0, 0)))
    ho, wo = (x.shape[1] - window[0]) // sh + 1, (x.shape[2] - window[1]) // sw + 1
    taps = w[0].astype(x.dtype)
    y = None
    for i in range(kh):  # static: unrolled, and fused by XLA into one loop
        for j in range(kw):
            start = (0, i * dh, j * dw, 0)
            end = (x.shape[0], i * dh + (ho - 1) * sh + 1, j * dw + (wo - 1) * sw + 1, out_channels)
            term = jax.lax.slice(x, start, end, (1, sh, sw, 1)) * _channels_last(taps[i, j], 4)
            y = term if y is None else y + term
    y = y if b is None else y + _channels_last(b, y.ndim)
    return (_activation(y, node.option("activation")),)


def _fully_connected(node: Node, tensors, x, w, b):
    y = jnp.einsum("...k,nk->...n", x.reshape(-1, w.shape[1]), w)
    y = y if b is None else y + b[None]
    lead = x.shape[:-1] if node.option("keep_num_dims") else (-1,)
    return (_activation(y.reshape(lead + (w.shape[0],)), node.option("activation")),)


def _binary(fn: Callable[[Array, Array], Array]):
    def apply(node: Node, tensors, a, b):
        return (_activation(fn(*_same_rank(a, b)), node.option("activation")),)

    return apply


def _max_pool(node: Node, tensors, x):
    window, stride = (1, *node.option("filter"), 1), (1, *node.option("stride"), 1)
    y = jax.lax.reduce_window(x, jnp.array(-jnp.inf, x.dtype), jax.lax.max, window, stride, node.option("padding"))
    return (_activation(y, node.option("activation")),)


def _average_pool(node: Node, tensors, x):
    # SAME padding: TFLite divides by the number of pixels of the window inside the image.
    window, stride = (1, *node.option("filter"), 1), (1, *node.option("stride"), 1)
    zero = jnp.array(0, x.dtype)
    total = jax.lax.reduce_window(x, zero, jax.lax.add, window, stride, node.option("padding"))
    ones = jnp.ones((1,) + x.shape[1:3] + (1,), x.dtype)
    count = jax.lax.reduce_window(ones, zero, jax.lax.add, window, stride, node.option("padding"))
    return (_activation(total / count, node.option("activation")),)


def _mean(node: Node, tensors, x):
    axes = tuple(a % x.ndim for a in node.option("axes"))
    return (jnp.mean(x, axis=axes, keepdims=node.option("keep_dims")),)


def _reshape(node: Node, tensors, x, *unused):
    return (x.reshape(tensors[node.outputs[0]].shape),)


def _pad(node: Node, tensors, x, *unused):
    return (jnp.pad(x, node.option("paddings"), constant_values=jnp.array(node.option("value"), x.dtype)),)


def _concatenation(node: Node, tensors, *xs):
    return (_activation(jnp.concatenate(xs, axis=node.option("axis")), node.option("activation")),)


def _interpolation(out_size: int, in_size: int, align_corners: bool, half_pixel: bool):
    """Lower and upper source indices and the upper weight per output index, as TFLite's
    reference ResizeBilinear (`ComputeInterpolationValues`) computes them."""
    scale = (in_size - 1) / (out_size - 1) if align_corners and out_size > 1 else in_size / out_size
    dst = np.arange(out_size, dtype=np.float32)
    src = (dst + 0.5) * np.float32(scale) - 0.5 if half_pixel else dst * np.float32(scale)
    lower = np.maximum(np.floor(src), 0).astype(np.int32)
    upper = np.minimum(np.ceil(src), in_size - 1).astype(np.int32)
    return lower, upper, (src - lower).astype(np.float32)


def _resize_bilinear(node: Node, tensors, x, *unused):
    out_h, out_w = node.option("size")
    align, half = node.option("align_corners"), node.option("half_pixel_centers")
    y0, y1, fy = _interpolation(out_h, x.shape[1], align, half)
    x0, x1, fx = _interpolation(out_w, x.shape[2], align, half)
    fy = jnp.asarray(fy, x.dtype)[None, :, None, None]
    fx = jnp.asarray(fx, x.dtype)[None, None, :, None]
    rows = x[:, y0] * (1 - fy) + x[:, y1] * fy
    return (rows[:, :, x0] * (1 - fx) + rows[:, :, x1] * fx,)


def _prelu(node: Node, tensors, x, alpha):
    x, alpha = _same_rank(x, alpha)
    return (jnp.where(x >= 0, x, alpha * x),)


def _softmax(node: Node, tensors, x):
    return (jax.nn.softmax(x * jnp.array(node.option("beta"), x.dtype), axis=-1),)


def _dequantize(node: Node, tensors, x):
    # Constant inputs were folded at load time, and float inputs enter in the compute dtype,
    # so what reaches a DEQUANTIZE at run time is already float.
    return (x,)


def _unary(fn: Callable[[Array], Array]):
    return lambda node, tensors, x: (fn(x),)


_APPLY: dict[str, Callable] = {
    "CONV_2D": _conv,
    "DEPTHWISE_CONV_2D": _depthwise,
    "FULLY_CONNECTED": _fully_connected,
    "ADD": _binary(jnp.add),
    "SUB": _binary(jnp.subtract),
    "MUL": _binary(jnp.multiply),
    "MAX_POOL_2D": _max_pool,
    "AVERAGE_POOL_2D": _average_pool,
    "MEAN": _mean,
    "RESHAPE": _reshape,
    "PAD": _pad,
    "PADV2": _pad,
    "CONCATENATION": _concatenation,
    "RESIZE_BILINEAR": _resize_bilinear,
    "LOGISTIC": _unary(jax.nn.sigmoid),
    "TANH": _unary(jnp.tanh),
    "RELU": _unary(lambda x: jnp.maximum(x, 0.0)),
    "RELU6": _unary(lambda x: jnp.clip(x, 0.0, 6.0)),
    "HARD_SWISH": _unary(lambda x: x * jnp.clip(x + 3.0, 0.0, 6.0) / 6.0),
    "PRELU": _prelu,
    "SOFTMAX": _softmax,
    "DEQUANTIZE": _dequantize,
}
assert set(_APPLY) == set(SUPPORTED_OPS)


# ----------------------------------------------------------------------------- parsing


def _enum_names(enum_class) -> dict[int, str]:
    return {v: k for k, v in vars(enum_class).items() if not k.startswith("_") and isinstance(v, int)}


def _options(tfl, op, cls_name: str):
    table = op.BuiltinOptions()
    if table is None:
        return None
    options = getattr(tfl, cls_name)()
    options.Init(table.Bytes, table.Pos)
    return options


def _fused(options, where: str) -> str:
    code = options.FusedActivationFunction() if options is not None else 0
    if code not in _ACTIVATIONS:
        raise UnsupportedTFLiteGraph(
            f"{where}: fused activation {code} (TANH, SIGN_BIT or newer) is not supported (LiteRT's kernels ignore it there)"
        )
    return _ACTIVATIONS[code]


def _node_options(tfl, op, name: str, const: Callable[[int], np.ndarray | None], ins: list[int], where: str) -> dict[str, Any]:
    """Static options of one operator (the constant integer inputs read here)."""

    def static(position: int) -> np.ndarray:
        value = const(ins[position]) if position < len(ins) and ins[position] >= 0 else None
        if value is None:
            raise UnsupportedTFLiteGraph(f"{where}: input {position} must be a constant (dynamic shapes are not supported)")
        return value

    if name in ("CONV_2D", "DEPTHWISE_CONV_2D"):
        o = _options(tfl, op, "Conv2DOptions" if name == "CONV_2D" else "DepthwiseConv2DOptions")
        return {"stride": (o.StrideH(), o.StrideW()), "dilation": (o.DilationHFactor(), o.DilationWFactor()),
                "padding": _PADDINGS[o.Padding()], "activation": _fused(o, where)}  # fmt: skip
    if name == "FULLY_CONNECTED":
        o = _options(tfl, op, "FullyConnectedOptions")
        if o is not None and o.WeightsFormat() != 0:
            raise UnsupportedTFLiteGraph(f"{where}: shuffled FULLY_CONNECTED weights are not supported")
        return {"activation": _fused(o, where), "keep_num_dims": bool(o.KeepNumDims()) if o is not None else False}
    if name in ("ADD", "SUB", "MUL"):
        return {"activation": _fused(_options(tfl, op, {"ADD": "AddOptions", "SUB": "SubOptions", "MUL": "MulOptions"}[name]), where)}
    if name in ("MAX_POOL_2D", "AVERAGE_POOL_2D"):
        o = _options(tfl, op, "Pool2DOptions")
        return {"filter": (o.FilterHeight(), o.FilterWidth()), "stride": (o.StrideH(), o.StrideW()),
                "padding": _PADDINGS[o.Padding()], "activation": _fused(o, where)}  # fmt: skip
    if name == "MEAN":
        o = _options(tfl, op, "ReducerOptions")
        return {"axes": tuple(int(a) for a in np.atleast_1d(static(1))), "keep_dims": bool(o.KeepDims()) if o is not None else False}
    if name in ("PAD", "PADV2"):
        value = float(np.asarray(static(2)).reshape(())) if name == "PADV2" and len(ins) > 2 else 0.0
        return {"paddings": tuple((int(a), int(b)) for a, b in static(1)), "value": value}
    if name == "CONCATENATION":
        o = _options(tfl, op, "ConcatenationOptions")
        return {"axis": o.Axis(), "activation": _fused(o, where)}
    if name == "RESIZE_BILINEAR":
        o = _options(tfl, op, "ResizeBilinearOptions")
        return {"size": tuple(int(s) for s in static(1)), "align_corners": bool(o.AlignCorners()) if o is not None else False,
                "half_pixel_centers": bool(o.HalfPixelCenters()) if o is not None else False}  # fmt: skip
    if name == "SOFTMAX":
        o = _options(tfl, op, "SoftmaxOptions")
        return {"beta": float(o.Beta()) if o is not None else 1.0}
    return {}


_STATIC_INPUTS = {"MEAN": (1,), "RESHAPE": (1,), "PAD": (1,), "PADV2": (1, 2), "RESIZE_BILINEAR": (1,)}
"""Operator inputs folded into the options (integer shapes, axes, sizes, pad values)."""


def _dequantised(values: np.ndarray, quantization, dtype: str, where: str) -> np.ndarray:
    if dtype in ("FLOAT32", "FLOAT16", "FLOAT64"):
        return values.astype(np.float32)
    if quantization is None or quantization.ScaleLength() == 0:
        raise UnsupportedTFLiteGraph(f"{where}: an integer ({dtype}) weight without a quantisation scale")
    scale = quantization.ScaleAsNumpy().astype(np.float32)
    zero = quantization.ZeroPointAsNumpy().astype(np.float32) if quantization.ZeroPointLength() else np.zeros_like(scale)
    if scale.size > 1:  # per channel, along quantized_dimension
        shape = [1] * values.ndim
        shape[quantization.QuantizedDimension()] = -1
        scale, zero = scale.reshape(shape), zero.reshape(shape)
    return ((values.astype(np.float32) - zero) * scale).astype(np.float32)


def load_tflite(data: bytes | str | pathlib.Path) -> TFLiteGraph:
    """A `TFLiteGraph` from a `.tflite` file (its bytes or its path).

    Raises `UnsupportedTFLiteGraph` naming every unsupported operator of the graph, and
    `ImportError` saying what to install when the `tflite` package is missing.
    """
    try:
        import tflite as tfl
    except ImportError as err:
        raise ImportError("reading .tflite files needs the `tflite` package: python -m pip install tflite (or the detect extra)") from err
    if not isinstance(data, (bytes, bytearray)):
        data = pathlib.Path(data).read_bytes()
    buf = bytes(data)
    if buf[4:8] != b"TFL3":  # the flatbuffer's file identifier
        raise ValueError(f"not a TFLite flatbuffer: file identifier {buf[4:8]!r}, expected b'TFL3'")
    try:
        model = tfl.Model.GetRootAsModel(buf, 0)
        subgraphs = model.SubgraphsLength()
    except Exception as err:  # not a flatbuffer
        raise ValueError(f"not a TFLite flatbuffer: {err}") from err
    if subgraphs != 1:
        raise UnsupportedTFLiteGraph(f"the graph has {subgraphs} subgraphs; only single-subgraph models are supported")
    graph = model.Subgraphs(0)
    op_names, type_names = _enum_names(tfl.BuiltinOperator), _enum_names(tfl.TensorType)

    def opcode(op) -> str:
        code = model.OperatorCodes(op.OpcodeIndex())
        builtin = max(code.BuiltinCode(), code.DeprecatedBuiltinCode())  # schema v3a: small codes live in the deprecated field
        name = op_names.get(builtin, f"builtin {builtin}")
        return f"CUSTOM({code.CustomCode().decode()})" if name == "CUSTOM" else name

    ops = [graph.Operators(k) for k in range(graph.OperatorsLength())]
    unsupported = sorted({opcode(op) for op in ops} - set(SUPPORTED_OPS))
    if unsupported:
        raise UnsupportedTFLiteGraph(f"the graph uses operators the converter does not support: {unsupported} (supported: {list(SUPPORTED_OPS)})")

    tensors, raw = [], {}
    for i in range(graph.TensorsLength()):
        t = graph.Tensors(i)
        dtype = type_names.get(t.Type(), str(t.Type()))
        shape = tuple(int(s) for s in t.ShapeAsNumpy()) if t.ShapeLength() else ()
        tensors.append(TensorInfo(t.Name().decode(), shape, dtype))
        buffer = model.Buffers(t.Buffer())
        if buffer.DataLength():
            blob = buffer.DataAsNumpy().tobytes()
        elif buffer.Offset() > 1:  # models over 2 GB keep buffers after the flatbuffer
            blob = buf[buffer.Offset() : buffer.Offset() + buffer.Size()]
        else:
            continue
        if dtype not in _NUMPY_TYPES:
            raise UnsupportedTFLiteGraph(f"tensor {tensors[-1].name!r} has type {dtype}")
        raw[i] = (np.frombuffer(blob, np.dtype(_NUMPY_TYPES[dtype]).newbyteorder("<")).reshape(shape), t.Quantization())

    def const(i: int) -> np.ndarray | None:
        return raw[i][0] if i in raw else None

    params: dict[str, np.ndarray] = {}
    owner: dict[str, int] = {}  # weight name -> its tensor
    nodes = []
    for k, op in enumerate(ops):
        name = opcode(op)
        ins = [int(j) for j in op.InputsAsNumpy()] if op.InputsLength() else []
        outs = tuple(int(j) for j in op.OutputsAsNumpy())
        where = f"operator {k} ({name}, output {tensors[outs[0]].name!r})"
        if name == "DEQUANTIZE" and ins[0] in raw:  # a stored weight: fold
            if owner.setdefault(tensors[outs[0]].name, outs[0]) != outs[0]:
                raise UnsupportedTFLiteGraph(f"two constant tensors are called {tensors[outs[0]].name!r}; weights are kept by name")
            params[tensors[outs[0]].name] = _dequantised(raw[ins[0]][0], raw[ins[0]][1], tensors[ins[0]].dtype, where)
            continue
        options = _node_options(tfl, op, name, const, ins, where)
        runtime = []
        for position, j in enumerate(ins):
            if position in _STATIC_INPUTS.get(name, ()):
                continue
            if j in raw:
                if owner.setdefault(tensors[j].name, j) != j:
                    raise UnsupportedTFLiteGraph(f"two constant tensors are called {tensors[j].name!r}; weights are kept by name")
                params[tensors[j].name] = _dequantised(raw[j][0], raw[j][1], tensors[j].dtype, where)
            elif j >= 0 and not tensors[j].dtype.startswith("FLOAT"):
                raise UnsupportedTFLiteGraph(f"{where}: quantised or integer activation {tensors[j].name!r} ({tensors[j].dtype}); convert a float model")
            runtime.append(j)
        nodes.append(Node(name, tuple(runtime), outs, tuple(sorted(options.items()))))

    inputs = tuple(int(j) for j in graph.InputsAsNumpy())
    outputs = tuple(int(j) for j in graph.OutputsAsNumpy())
    batched = all(tensors[i].shape[:1] == (1,) for i in inputs + outputs)
    return TFLiteGraph(
        params={n: jnp.asarray(a) for n, a in params.items()}, tensors=tuple(tensors), nodes=tuple(nodes),
        inputs=inputs, outputs=outputs, batched=batched,
    )  # fmt: skip
