"""One contract, derived everywhere: the scenario spec, the env, the generated policy.h, the generated
CAN database and the node's generated glue all say the same thing, field by field (the glue sizes its
vectors by policy.h's own macros)."""

from __future__ import annotations

import re

import gymnasium as gym
import numpy as np

from embedrl import train
from embedrl.export.codegen import generate
from embedrl.export.contract.dbc import database
from embedrl.export.contract.layout import layout
from embedrl.export.contract.sources import c_sources
from embedrl.export.onnx_import import to_ir
from embedrl.hil.codec import Codec
from embedrl.train.scenarios import STATIC
from tests.export.helpers import mlp_model


def test_spec_env_policy_header_can_database_and_node_glue_agree() -> None:
    env = gym.make(train.ENV_ID)
    assert isinstance(env.observation_space, gym.spaces.Box)
    np.testing.assert_array_equal(env.observation_space.low, STATIC.obs_low)
    np.testing.assert_array_equal(env.observation_space.high, STATIC.obs_high)

    graph = to_ir(mlp_model([len(STATIC.observation), 8, len(STATIC.action)], ["Relu", "Tanh"]))
    header = generate(graph, "policy", STATIC.safe_action, interface=STATIC)["policy.h"]
    indices = dict(re.findall(r"#define POLICY_((?:OBS|ACT)_\w+) (\d+)u /\*", header))
    expected = {f"OBS_{f.name.upper()}": str(i) for i, f in enumerate(STATIC.observation)}
    expected |= {f"ACT_{f.name.upper()}": str(i) for i, f in enumerate(STATIC.action)}
    assert indices == expected
    assert f"#define POLICY_OBS_DIM {len(STATIC.observation)}u" in header

    db = database(STATIC)
    plan = layout(STATIC)
    assert [s.index for s in plan.observation_slots] == list(range(len(STATIC.observation)))
    for slot in plan.observation_slots + plan.action_slots:
        signal = db.get_message_by_name(slot.message).get_signal_by_name(slot.signal)
        assert signal.name == slot.field.camel
        assert (signal.minimum, signal.maximum) == (
            float(f"{slot.field.low:.9g}"),
            float(f"{slot.field.high:.9g}"),
        )
        assert (signal.unit or "") == slot.field.unit and signal.comment == slot.field.description

    glue = c_sources(STATIC)["policy_io.h"]
    assert '#include "policy.h"' in glue and "_DIM" not in glue.replace("POLICY_OBS_DIM", "").replace(
        "POLICY_ACT_DIM", ""
    )  # one set of dimensions: the policy header's
    assert f"#define POLICY_IO_OBS_FRAMES {len(plan.observation)}u" in glue

    obs, _ = env.reset(seed=3)
    for _ in range(5):
        obs, *_ = env.step(env.action_space.sample())
        _, decoded = Codec(STATIC).encode_observation(obs, 1)
        np.testing.assert_allclose(decoded, obs, atol=max(s.scale for s in plan.observation_slots) / 2)
