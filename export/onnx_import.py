"""ONNX -> IR: validate everything at the boundary so the code generator can run blindly.

Accepted: one float32 input (the observation) and one float32 output (the action), static shapes
except a dynamic batch (first) dimension, which is fixed to 1; a recurrent policy's state as further
inputs, each paired with the further output of the same position and shape that holds its next value
(``obs, h, c -> action, h_next, c_next``); ops from :data:`export.ops.EMITTERS` in the default domain;
float32 weights (int64 only for shape operands), all finite.
"""

from __future__ import annotations

import functools
import math
from dataclasses import dataclass
from pathlib import Path, PurePosixPath

import numpy as np
import onnx
import onnx.external_data_helper
from google.protobuf.message import DecodeError
from onnx import numpy_helper

from embedrl.escape import c_comment
from embedrl.export.errors import InvalidModelError, UnsupportedOpError
from embedrl.export.ir import AttrValue, Graph, Node
from embedrl.export.onnx_text import safe_text
from embedrl.export.ops import EMITTERS

MIN_OPSET = 13
"""Oldest default-domain opset accepted (Clip bounds as inputs, Softplus/Gemm semantics fixed)."""


@dataclass(frozen=True)
class Limits:
    """How large a model the exporter accepts (a policy for a microcontroller is far smaller): checked
    before anything large is read, so an oversized or hostile file costs neither memory nor minutes."""

    max_bytes: int = 64 * 2**20
    """The model file plus its external data."""
    max_parameters: int = 4_000_000
    """Weights in all initializers (16 MB as float32); also the most values of the graph's input or
    output."""
    max_nodes: int = 2_000
    """Nodes in the graph (the study's policy has 7; a recurrent or large one a few hundred)."""


LIMITS_HINT = "--max-model-mb and --max-params raise the limits"


def load_onnx(path: Path, limits: Limits = Limits()) -> onnx.ModelProto:
    """Read and check an ONNX file within ``limits``; any problem is an :class:`InvalidModelError` naming
    the file. External data must lie in the model's folder (no absolute path, no ``..``)."""
    if not path.is_file():
        raise InvalidModelError(f"{path}: no such file")
    size = path.stat().st_size
    if size > limits.max_bytes:
        raise InvalidModelError(
            f"{path}: {size / 2**20:.1f} MB exceeds the {_mb(limits.max_bytes)} limit; {LIMITS_HINT}"
        )
    try:
        model = onnx.load(str(path), load_external_data=False)
    except (DecodeError, ValueError, RuntimeError, OSError) as exc:
        raise InvalidModelError(
            f"{path}: not a readable ONNX model ({exc.__class__.__name__}: {c_comment(str(exc))})"
        ) from None
    safe_text(model)  # the author's names and text never go further as they came
    _check_sizes(path, model, size, limits)
    _check_graph(path, model, limits)
    try:
        onnx.external_data_helper.load_external_data_for_model(model, str(path.parent))
    except (OSError, ValueError, RuntimeError) as exc:
        raise InvalidModelError(f"{path}: cannot read its external data ({exc})") from None
    if model.ir_version > runtime_ir_version():
        # Newer files (onnx's own default may be ahead of onnxruntime) hold nothing the importer accepts
        # that an older IR cannot: float32 and int64 tensors, default-domain ops.
        model.ir_version = runtime_ir_version()
    if not model.graph.node and not model.graph.output:
        raise InvalidModelError(f"{path}: not an ONNX model (empty graph)")
    try:
        onnx.checker.check_model(model)
    except onnx.checker.ValidationError as exc:
        first = str(exc).strip().splitlines()[0]
        raise InvalidModelError(f"{path}: invalid ONNX model: {first}") from None
    return model


def _mb(n: int) -> str:
    return f"{n / 2**20:.0f} MB"


def _check_sizes(path: Path, model: onnx.ModelProto, size: int, limits: Limits) -> None:
    """Parameters and bytes as the file declares them, external data's locations and sizes; each external
    tensor gets an explicit ``length`` (its declared size), so that no more than that is ever read."""
    parameters, external = 0, 0
    folder = path.parent.resolve()
    for tensor in model.graph.initializer:
        if any(d < 0 for d in tensor.dims):
            raise InvalidModelError(f"{path}: initializer '{tensor.name}' has a negative dimension")
        count = math.prod(tensor.dims) if tensor.dims else 1
        parameters += count
        if parameters > limits.max_parameters:
            break
        if tensor.data_location != onnx.TensorProto.EXTERNAL:
            continue
        external += _check_external(path, folder, tensor, count)
    if parameters > limits.max_parameters:
        raise InvalidModelError(
            f"{path}: {parameters:,} parameters exceed the limit of {limits.max_parameters:,}; {LIMITS_HINT}"
        )
    if size + external > limits.max_bytes:
        raise InvalidModelError(
            f"{path}: {(size + external) / 2**20:.1f} MB with its external data exceeds the "
            f"{_mb(limits.max_bytes)} limit; {LIMITS_HINT}"
        )


def _check_external(path: Path, folder: Path, tensor: onnx.TensorProto, count: int) -> int:
    """The bytes ``tensor``'s external data will read, after checking where and how much."""
    info = {e.key: e.value for e in tensor.external_data}
    location = PurePosixPath(info.get("location", ""))
    if not info.get("location") or location.is_absolute() or ".." in location.parts:
        raise InvalidModelError(
            f"{path}: external data of '{tensor.name}' at {str(location)!r} is outside the model's folder"
        )
    target = folder / location
    if target.is_symlink() or not target.resolve().is_relative_to(folder):
        raise InvalidModelError(
            f"{path}: external data of '{tensor.name}' ({location}) is a symbolic link; copy the file into "
            "the model's folder"
        )
    if not target.is_file():
        raise InvalidModelError(f"{path}: external data of '{tensor.name}' ({location}): no such file")
    try:
        itemsize = onnx.helper.tensor_dtype_to_np_dtype(tensor.data_type).itemsize
        offset = int(info.get("offset", 0))
        length = int(info.get("length", count * itemsize))
    except (KeyError, ValueError, TypeError) as exc:
        raise InvalidModelError(f"{path}: external data of '{tensor.name}' is not readable ({exc})") from None
    if length != count * itemsize or offset < 0:
        raise InvalidModelError(
            f"{path}: external data of '{tensor.name}' ({location}) declares {length:,} bytes at offset "
            f"{offset:,}; its shape {list(tensor.dims)} needs {count * itemsize:,}"
        )
    if offset + length > target.stat().st_size:
        raise InvalidModelError(
            f"{path}: external data of '{tensor.name}' ({location}) is {target.stat().st_size:,} bytes, "
            f"too short for {length:,} bytes at offset {offset:,}"
        )
    if "length" not in info:
        entry = tensor.external_data.add()
        entry.key, entry.value = "length", str(length)  # onnx would read to the end of the file
    return length


def _check_graph(path: Path, model: onnx.ModelProto, limits: Limits) -> None:
    """Node count and the declared sizes of the graph's inputs and outputs, before any work on them."""
    nodes = len(model.graph.node)
    if nodes > limits.max_nodes:
        raise InvalidModelError(f"{path}: {nodes:,} nodes exceed the limit of {limits.max_nodes:,}")
    for role, values in (("input", model.graph.input), ("output", model.graph.output)):
        for value in values:
            dims = [d.dim_value for d in value.type.tensor_type.shape.dim if d.HasField("dim_value")]
            size = math.prod(dims) if dims else 1
            if size > limits.max_parameters:
                raise InvalidModelError(
                    f"{path}: graph {role} '{value.name}' of shape {dims} has {size:,} values, above the "
                    f"limit of {limits.max_parameters:,}; {LIMITS_HINT}"
                )


@functools.cache
def runtime_ir_version() -> int:
    """The newest ONNX IR version the installed onnxruntime runs (probed once with a one-node model)."""
    import onnxruntime as ort

    graph = onnx.helper.make_graph(
        [onnx.helper.make_node("Relu", ["x"], ["y"])],
        "probe",
        [onnx.helper.make_tensor_value_info("x", onnx.TensorProto.FLOAT, [1])],
        [onnx.helper.make_tensor_value_info("y", onnx.TensorProto.FLOAT, [1])],
    )
    for version in range(onnx.IR_VERSION, 3, -1):
        model = onnx.helper.make_model(
            graph, opset_imports=[onnx.helper.make_opsetid("", 13)], ir_version=version
        )
        try:
            ort.InferenceSession(model.SerializeToString(), providers=["CPUExecutionProvider"])
        except Exception:
            continue
        return version
    return 3


def _attr(attribute: onnx.AttributeProto) -> AttrValue | np.ndarray:
    value = onnx.helper.get_attribute_value(attribute)
    if isinstance(value, bytes):
        return value.decode()
    if isinstance(value, onnx.TensorProto):
        return numpy_helper.to_array(value)
    if isinstance(value, list):
        return tuple(v.decode() if isinstance(v, bytes) else v for v in value)
    if isinstance(value, int | float | str):
        return value
    raise UnsupportedOpError(f"attribute '{attribute.name}' of type {type(value).__name__} is not supported")


def _static_shape(value: onnx.ValueInfoProto, role: str) -> tuple[int, ...]:
    t = value.type.tensor_type
    if t.elem_type != onnx.TensorProto.FLOAT:
        dtype = onnx.TensorProto.DataType.Name(t.elem_type)
        raise UnsupportedOpError(
            f"graph {role} '{value.name}' has dtype {dtype}; only FLOAT (float32) is supported"
        )
    dims = []
    for axis, d in enumerate(t.shape.dim):
        if d.HasField("dim_value") and d.dim_value > 0:
            dims.append(int(d.dim_value))
        elif axis == 0 and len(t.shape.dim) > 1:
            dims.append(1)  # dynamic batch: the C function handles one observation
        else:
            raise UnsupportedOpError(
                f"graph {role} '{value.name}' has a dynamic dimension {axis} "
                f"('{d.dim_param or '?'}'); only the batch (first) dimension may be dynamic"
            )
    if not dims:
        raise UnsupportedOpError(f"graph {role} '{value.name}' has no shape")
    return tuple(dims)


def _constant(name: str, array: np.ndarray, where: str) -> np.ndarray:
    if array.dtype == np.int64:
        return array
    if array.dtype not in (np.float32, np.float64):
        raise UnsupportedOpError(f"{where} '{name}' has dtype {array.dtype}; only float32 is supported")
    if array.dtype == np.float64:
        raise UnsupportedOpError(f"{where} '{name}' is float64; only float32 is supported")
    if not np.isfinite(array).all():
        bad = int(np.size(array) - np.count_nonzero(np.isfinite(array)))
        raise InvalidModelError(f"{where} '{name}' contains {bad} NaN/Inf value(s)")
    return array


def to_ir(model: onnx.ModelProto) -> Graph:
    """Convert a checked ONNX model into a validated, frozen :class:`Graph`."""
    opset = {o.domain: o.version for o in model.opset_import}.get("", 0)
    if opset < MIN_OPSET:
        raise UnsupportedOpError(f"default-domain opset {opset} is not supported; need >= {MIN_OPSET}")
    g = model.graph
    constants: dict[str, np.ndarray] = {}
    for init in g.initializer:
        constants[init.name] = _constant(init.name, numpy_helper.to_array(init), "initializer")
    inputs = [v for v in g.input if v.name not in constants]
    if not inputs or len(inputs) != len(g.output):
        raise UnsupportedOpError(
            "the graph must have one input and one output (the observation and the action), and for a "
            f"recurrent policy one more output per further input (its next state); got {len(inputs)} "
            f"input(s) and {len(g.output)} output(s)"
        )
    shapes: dict[str, tuple[int, ...]] = {v.name: _static_shape(v, "input") for v in inputs}
    shapes.update({k: tuple(int(d) for d in v.shape) for k, v in constants.items()})

    nodes = []
    for index, proto in enumerate(g.node):
        name = proto.name or f"{proto.op_type}_{index}"
        if proto.domain not in ("", "ai.onnx"):
            raise UnsupportedOpError(f"node '{name}': op {proto.domain}.{proto.op_type} is not supported")
        emitter = EMITTERS.get(proto.op_type)
        if emitter is None:
            raise UnsupportedOpError(
                f"node '{name}': op {proto.op_type} is not supported; "
                f"supported ops: {', '.join(sorted(EMITTERS))}"
            )
        attrs = {a.name: _attr(a) for a in proto.attribute}
        ins = tuple(proto.input)
        if proto.op_type == "Constant":
            value = attrs.get("value")
            if set(attrs) != {"value"} or not isinstance(value, np.ndarray):
                raise UnsupportedOpError(
                    f"node '{name}': Constant supports only the 'value' tensor attribute"
                )
            constants[proto.output[0]] = _constant(proto.output[0], value, f"Constant node '{name}'")
            shapes[proto.output[0]] = tuple(int(d) for d in value.shape)
            continue
        for i in ins:
            if i and i not in shapes:
                raise UnsupportedOpError(f"node '{name}': input '{i}' is not produced before it is used")
        if emitter.commutative and len(ins) == 2 and ins[0] in constants and ins[1] not in constants:
            ins = (ins[1], ins[0])
        node = Node(proto.op_type, name, ins, tuple(proto.output), {k: v for k, v in attrs.items()})  # type: ignore[misc]
        first = emitter.check(node, shapes, constants)
        shapes.update(
            (out, shape)
            for out, shape in zip(node.outputs, emitter.output_shapes(node, first), strict=True)
            if out
        )
        nodes.append(node)

    for value in g.output:
        if value.name not in shapes or value.name in constants:
            raise UnsupportedOpError(f"graph output '{value.name}' is not computed from the input")
        if value.type.tensor_type.elem_type != onnx.TensorProto.FLOAT:
            raise UnsupportedOpError(f"graph output '{value.name}' must be FLOAT (float32)")
    states = tuple((read.name, write.name) for read, write in zip(inputs[1:], g.output[1:], strict=True))
    for read, write in states:
        if math.prod(shapes[read]) != math.prod(shapes[write]):
            raise UnsupportedOpError(
                f"state input '{read}' {list(shapes[read])} and its next value, output '{write}' "
                f"{list(shapes[write])}, differ in size (inputs after the first pair with outputs in order)"
            )
        if shapes[read] != shapes[write]:  # onnxruntime feeds the output back as the input: same shape
            raise UnsupportedOpError(
                f"state input '{read}' {list(shapes[read])} and its next value, output '{write}' "
                f"{list(shapes[write])}, differ in shape: the next state is fed back as the state input, so "
                "it needs the input's shape (reshape it before the output)"
            )
    output = g.output[0].name
    used_nodes = _live_nodes(nodes, {value.name for value in g.output})
    return Graph.freeze(inputs[0].name, output, used_nodes, shapes, constants, states)


def _live_nodes(nodes: list[Node], outputs: set[str]) -> list[Node]:
    """Drop nodes whose results never reach an output (e.g. a value head in the same file)."""
    needed = set(outputs)
    keep = []
    for node in reversed(nodes):
        if needed & set(node.outputs):
            keep.append(node)
            needed.update(i for i in node.inputs if i)
    return list(reversed(keep))
