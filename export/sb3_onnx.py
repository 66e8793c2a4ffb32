"""SB3 model (.zip, optional VecNormalize statistics) -> ONNX: the deterministic actor with
observation normalisation and action post-processing inside the graph.

The ONNX graph is built directly from the policy's layers (no torch tracing): raw observation
in, final action in the environment's units out, exactly what ``predict(deterministic=True)``
returns after the same normalisation.

Supported: ``TD3Policy`` (TD3, DDPG), ``SACPolicy`` (SAC, without gSDE) and
``ActorCriticPolicy`` with a diagonal Gaussian (PPO, A2C, without gSDE), MLP layers
(Linear, ReLU, Tanh, LeakyReLU, Sigmoid, Softplus, Identity) after a flatten extractor, on
1-D Box observation and action spaces; sb3-contrib's ``RecurrentActorCriticPolicy`` (RecurrentPPO) with
its actor's LSTM layers as ONNX ``LSTM`` nodes whose hidden and cell states are explicit inputs
(``lstm_h0``, ``lstm_c0``, ...) and outputs (``lstm_h0_next``, ...) after the observation and the action,
batch 1: one control step per call.
"""

from __future__ import annotations

from typing import Any

import numpy as np
import onnx
from onnx import TensorProto, helper, numpy_helper
from stable_baselines3.common.distributions import DiagGaussianDistribution
from stable_baselines3.common.policies import ActorCriticPolicy, BasePolicy
from stable_baselines3.common.torch_layers import FlattenExtractor
from stable_baselines3.sac.policies import SACPolicy
from stable_baselines3.td3.policies import TD3Policy
from torch import nn

from embedrl.export.errors import UnsupportedModelError
from embedrl.train.models import LoadedPolicy

OPSET = 17
IR_VERSION = 8
"""ONNX IR version written (opset 17's); newer IR versions are rejected by onnxruntime 1.31."""
INPUT_NAME = "obs"
OUTPUT_NAME = "action"
SUPPORTED_LAYERS = "Linear, ReLU, Tanh, LeakyReLU, Sigmoid, Softplus(beta=1), Identity"


class _GraphBuilder:
    """Accumulates ONNX nodes and initializers with deterministic names."""

    def __init__(self) -> None:
        self.nodes: list[onnx.NodeProto] = []
        self.initializers: list[onnx.TensorProto] = []
        self.last = INPUT_NAME

    def const(self, name: str, value: np.ndarray | float) -> str:
        self.initializers.append(numpy_helper.from_array(np.asarray(value, dtype=np.float32), name))
        return name

    def const_int(self, name: str, value: list[int]) -> str:
        """An int64 operand (axes), declared once."""
        if not any(t.name == name for t in self.initializers):
            self.initializers.append(numpy_helper.from_array(np.asarray(value, dtype=np.int64), name))
        return name

    def add(self, op: str, name: str, *extra_inputs: str, **attrs: Any) -> None:
        out = f"{name}_out"
        self.nodes.append(helper.make_node(op, [self.last, *extra_inputs], [out], name=name, **attrs))
        self.last = out

    def module(self, module: nn.Module, prefix: str) -> None:
        """Append one torch layer (or a Sequential of them)."""
        if isinstance(module, nn.Sequential):
            for i, child in enumerate(module):
                self.module(child, f"{prefix}.{i}")
        elif isinstance(module, nn.Linear):
            w = self.const(f"{prefix}.weight", module.weight.detach().numpy())
            extra = (
                [w]
                if module.bias is None
                else [w, self.const(f"{prefix}.bias", module.bias.detach().numpy())]
            )
            self.add("Gemm", prefix, *extra, transB=1)
        elif isinstance(module, nn.ReLU):
            self.add("Relu", prefix)
        elif isinstance(module, nn.Tanh):
            self.add("Tanh", prefix)
        elif isinstance(module, nn.Sigmoid):
            self.add("Sigmoid", prefix)
        elif isinstance(module, nn.LeakyReLU):
            self.add("LeakyRelu", prefix, alpha=float(module.negative_slope))
        elif isinstance(module, nn.Softplus) and module.beta == 1:
            self.add("Softplus", prefix)
        elif isinstance(module, nn.Identity | nn.Flatten | FlattenExtractor):
            pass
        else:
            raise UnsupportedModelError(
                f"layer '{prefix}' ({type(module).__name__}) is not supported; "
                f"supported layers: {SUPPORTED_LAYERS}"
            )


def _network(b: _GraphBuilder, policy: BasePolicy) -> str:
    """Append the deterministic actor; return 'squash' or 'clip' for the post-processing it needs."""
    if isinstance(policy, TD3Policy):
        b.module(policy.actor.features_extractor, "actor.features_extractor")
        b.module(policy.actor.mu, "actor.mu")
        return "squash"
    if isinstance(policy, SACPolicy):
        b.module(policy.actor.features_extractor, "actor.features_extractor")
        b.module(policy.actor.latent_pi, "actor.latent_pi")
        b.module(policy.actor.mu, "actor.mu")
        b.add("Tanh", "actor.squash")  # the squashed Gaussian's mode is tanh(mean)
        return "squash"
    assert isinstance(policy, ActorCriticPolicy)
    if not isinstance(policy.action_dist, DiagGaussianDistribution) or policy.squash_output:
        raise UnsupportedModelError(
            f"{type(policy.action_dist).__name__} is not supported; need a diagonal Gaussian"
        )
    b.module(policy.pi_features_extractor, "pi_features_extractor")
    lstm = getattr(policy, "lstm_actor", None)
    if lstm is not None:
        _lstm(b, lstm)
    b.module(policy.mlp_extractor.policy_net, "mlp_extractor.policy_net")
    b.module(policy.action_net, "action_net")
    return "clip"


TORCH_TO_ONNX_GATES = (0, 3, 1, 2)
"""torch's LSTM gate blocks are i, f, g, o; ONNX's are i, o, f, c (g): ONNX block k is torch block [k]."""


def state_names(layers: int) -> list[str]:
    """The state inputs of a recurrent export, in order (each output is the name with ``_next``)."""
    return [f"lstm_{kind}{k}" for k in range(layers) for kind in ("h", "c")]


def _lstm(b: _GraphBuilder, lstm: nn.LSTM) -> None:
    """Append the actor's LSTM, one ONNX LSTM node per layer, over one time step of batch 1."""
    if lstm.batch_first or lstm.bidirectional or not lstm.bias or lstm.proj_size:
        raise UnsupportedModelError("only a unidirectional LSTM with biases and no projection is supported")
    hidden = lstm.hidden_size

    def gates(tensor: Any) -> np.ndarray:
        blocks = np.split(tensor.detach().numpy().astype(np.float32), 4, axis=0)
        return np.concatenate([blocks[k] for k in TORCH_TO_ONNX_GATES], axis=0)

    b.add("Unsqueeze", "lstm.sequence", b.const_int("lstm.axis0", [0]))
    for k in range(lstm.num_layers):
        w = b.const(f"lstm.W{k}", gates(getattr(lstm, f"weight_ih_l{k}"))[None])
        r = b.const(f"lstm.R{k}", gates(getattr(lstm, f"weight_hh_l{k}"))[None])
        bias = np.concatenate([gates(getattr(lstm, f"bias_ih_l{k}")), gates(getattr(lstm, f"bias_hh_l{k}"))])
        h, c = f"lstm_h{k}", f"lstm_c{k}"
        y = f"lstm.layer{k}_y"
        b.nodes.append(
            helper.make_node(
                "LSTM",
                [b.last, w, r, b.const(f"lstm.B{k}", bias[None]), "", h, c],
                [y, f"{h}_next", f"{c}_next"],
                name=f"lstm.layer{k}",
                hidden_size=hidden,
            )
        )
        b.last = y
        b.add("Squeeze", f"lstm.layer{k}_step", b.const_int("lstm.axis1", [1]))  # [1, 1, 1, H] -> [1, 1, H]
    b.add("Squeeze", "lstm.output", b.const_int("lstm.axis0", [0]))  # -> [1, H]


def build_onnx(loaded: LoadedPolicy, producer_version: str) -> onnx.ModelProto:
    """The ONNX graph of the deterministic actor, normalisation and post-processing included."""
    b = _GraphBuilder()
    if loaded.normalization is not None:
        n = loaded.normalization
        b.add("Sub", "normalize.sub", b.const("normalize.mean", n.mean))
        b.add("Div", "normalize.div", b.const("normalize.std", np.sqrt(n.var + n.epsilon)))
        b.add("Clip", "normalize.clip", b.const("normalize.low", -n.clip), b.const("normalize.high", n.clip))
    post = _network(b, loaded.policy)
    low = loaded.action_space.low.astype(np.float32)
    high = loaded.action_space.high.astype(np.float32)
    if post == "squash":
        if not (np.all(low == -1.0) and np.all(high == 1.0)):
            # SB3's unscale_action: low + 0.5 * (a + 1) * (high - low), in this order.
            b.add("Add", "unscale.add_one", b.const("unscale.one", 1.0))
            b.add("Mul", "unscale.half", b.const("unscale.half_value", 0.5))
            b.add("Mul", "unscale.range", b.const("unscale.range_value", high - low))
            b.add("Add", "unscale.low", b.const("unscale.low_value", low))
    elif np.all(np.isfinite(low)) and np.all(np.isfinite(high)):
        # predict() clips PPO's Gaussian mean to the action space.
        if np.all(low == low[0]) and np.all(high == high[0]):
            b.add("Clip", "clip", b.const("clip.low", low[0]), b.const("clip.high", high[0]))
        else:
            b.add("Max", "clip.low", b.const("clip.low_value", low))
            b.add("Min", "clip.high", b.const("clip.high_value", high))
    b.nodes.append(helper.make_node("Identity", [b.last], [OUTPUT_NAME], name="output"))
    obs_dim, act_dim = loaded.observation_space.shape[0], loaded.action_space.shape[0]
    lstm = getattr(loaded.policy, "lstm_actor", None)
    states = state_names(lstm.num_layers) if lstm is not None else []
    batch: int | str = 1 if states else "batch"  # a recurrent step is one observation of one episode
    hidden = [1, 1, lstm.hidden_size] if lstm is not None else []
    graph = helper.make_graph(
        b.nodes,
        "embedrl_policy",
        [helper.make_tensor_value_info(INPUT_NAME, TensorProto.FLOAT, [batch, obs_dim])]
        + [helper.make_tensor_value_info(s, TensorProto.FLOAT, hidden) for s in states],
        [helper.make_tensor_value_info(OUTPUT_NAME, TensorProto.FLOAT, [batch, act_dim])]
        + [helper.make_tensor_value_info(f"{s}_next", TensorProto.FLOAT, hidden) for s in states],
        b.initializers,
    )
    model = helper.make_model(
        graph,
        opset_imports=[helper.make_opsetid("", OPSET)],
        ir_version=IR_VERSION,
        producer_name="embedrl",
        producer_version=producer_version,
    )
    onnx.checker.check_model(model, full_check=True)
    return model
