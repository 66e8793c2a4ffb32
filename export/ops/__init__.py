"""The supported ONNX ops, one file per family, registered in :data:`EMITTERS` (the only registry).

Each op class owns its meaning: ``check`` (validation and output shape), ``emit`` (C, float32 or with
int8 weights) and ``reference`` (NumPy, in ``float64`` or bit-exact ``int8``), see
:mod:`embedrl.export.ops.base`. Adding an op means one class in its family's file plus one test.
"""

from __future__ import annotations

from typing import Any

from embedrl.export.ops.base import EmitContext, Emitter, Shape
from embedrl.export.ops.elementwise import (
    Add,
    Clip,
    Div,
    LeakyRelu,
    Max,
    Min,
    Mul,
    Relu,
    Sigmoid,
    Softplus,
    Sub,
    Tanh,
)  # fmt: skip
from embedrl.export.ops.linear import Gemm, MatMul
from embedrl.export.ops.recurrent import GRU, LSTM
from embedrl.export.ops.shape import Constant, Flatten, Gather, Identity, Reshape, Squeeze, Unsqueeze

EMITTERS: dict[str, Emitter] = {
    "Gemm": Gemm(),
    "MatMul": MatMul(),
    "Add": Add(),
    "Sub": Sub(),
    "Mul": Mul(),
    "Div": Div(),
    "Max": Max(),
    "Min": Min(),
    "Relu": Relu(),
    "LeakyRelu": LeakyRelu(),
    "Tanh": Tanh(),
    "Sigmoid": Sigmoid(),
    "Softplus": Softplus(),
    "Clip": Clip(),
    "Identity": Identity(),
    "Flatten": Flatten(),
    "Reshape": Reshape(),
    "Squeeze": Squeeze(),
    "Gather": Gather(),
    "Unsqueeze": Unsqueeze(),
    "Constant": Constant(),
    "LSTM": LSTM(),
    "GRU": GRU(),
}
"""The supported ops: the only place an op is registered."""


def multiply_adds(node: Any, graph: Any) -> int:
    """Multiply-accumulates of one step of ``node``: a matrix product's weights, a recurrent cell's input and
    recurrent weights; element-wise and shape ops have none."""
    emitter = EMITTERS[node.op]
    if getattr(emitter, "linear", False):
        return int(emitter.affine(node, graph.constants).weights.size)
    if isinstance(emitter, (LSTM, GRU)):
        return sum(graph.size(i) for i in node.inputs[1:3] if i and graph.is_constant(i))
    return 0


def graph_multiply_adds(graph: Any) -> int:
    """Multiply-accumulates of one step of the whole graph."""
    return sum(multiply_adds(node, graph) for node in graph.nodes)


__all__ = ["EMITTERS", "EmitContext", "Emitter", "Shape", "graph_multiply_adds", "multiply_adds"]
