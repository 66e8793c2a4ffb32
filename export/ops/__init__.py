"""The supported ONNX ops, one file per family, registered in :data:`EMITTERS` (the only registry).

Each op class owns its meaning: ``check`` (validation and output shape), ``emit`` (C, float32 or with
int8 weights) and ``reference`` (NumPy, in ``float64`` or bit-exact ``int8``), see
:mod:`embedrl.export.ops.base`. Adding an op means one class in its family's file plus one test.
"""

from __future__ import annotations

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

__all__ = ["EMITTERS", "EmitContext", "Emitter", "Shape"]
