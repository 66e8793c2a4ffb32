"""End to end: freshly trained tiny SB3 policies through ``embedrl export``, every check in the report."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import gymnasium as gym
import numpy as np
import pytest
from stable_baselines3 import DDPG, PPO, SAC, TD3
from stable_baselines3.common.base_class import BaseAlgorithm
from stable_baselines3.common.running_mean_std import RunningMeanStd
from stable_baselines3.common.vec_env import DummyVecEnv, VecNormalize

from embedrl import train
from embedrl.cli import main
from embedrl.export.contract.sources import C_FILES, DBC_FILE, FOLDERS
from embedrl.export.verify import MAX_DIFFERING_OUTCOMES, MIN_SAMPLES, TOLERANCE
from embedrl.train.interface import Interface
from embedrl.train.models import save_normalization
from embedrl.train.scenarios import STATIC
from tests.conftest import marks_its_users

pytestmark = pytest.mark.slow
ALGOS: dict[str, type[BaseAlgorithm]] = {"ddpg": DDPG, "td3": TD3, "sac": SAC, "ppo": PPO}


def _train(algo: str, env_id: str, steps: int = 300) -> BaseAlgorithm:
    cls = ALGOS[algo]
    kwargs: dict[str, Any] = {"policy_kwargs": {"net_arch": [16, 16]}, "seed": 0, "device": "cpu"}
    if algo == "ppo":
        kwargs.update(n_steps=64, batch_size=32, n_epochs=2)
    else:
        kwargs.update(learning_starts=50, buffer_size=2000)
    model = cls("MlpPolicy", gym.make(env_id), **kwargs)
    model.learn(steps)
    return model


@pytest.fixture(scope="module")
@marks_its_users("training")
def models(tmp_path_factory: pytest.TempPathFactory) -> dict[str, Path]:
    root = tmp_path_factory.mktemp("models")
    paths = {}
    for algo in ALGOS:
        path = root / f"{algo}.zip"
        _train(algo, train.ENV_ID).save(path)
        paths[algo] = path
    return paths


def _export(source: Path, out: Path, *extra: str) -> dict[str, Any]:
    assert main(["export", str(source), "--out", str(out), "--episodes", "20", *extra]) == 0
    report: dict[str, Any] = json.loads((out / "export_report.json").read_text())
    return report


@pytest.mark.parametrize("algo", sorted(ALGOS))
def test_export_of_a_trained_policy_is_verified(algo: str, models: dict[str, Path], tmp_path: Path) -> None:
    out = tmp_path / "export"
    report = _export(models[algo], out)
    v = report["verification"]
    assert v["samples"] >= MIN_SAMPLES and v["samples_from_rollouts"] > 0
    assert v["onnx_vs_sb3_max_abs_error"] <= TOLERANCE
    assert v["c_vs_onnxruntime_max_abs_error"] <= TOLERANCE
    assert v["non_finite_observation"] == {"return_code": 1, "action": [0.0, 0.0]}
    loop = report["closed_loop"]
    assert loop["episodes"] == 20 and loop["differing_outcomes"] <= MAX_DIFFERING_OUTCOMES
    for who in ("reference", "c"):
        assert loop[who]["successes"] + loop[who]["collisions"] + loop[who]["timeouts"] == 20
    can_code = [f"{folder}/{name}" for folder in FOLDERS for name in (DBC_FILE, *C_FILES)]
    assert sorted(report["files"]) == sorted([
        "c/policy.c",
        "c/policy.h",
        "c/policy_host.c",
        "c/policy_host.h",
        *can_code,
        "interface.json",
        "policy.onnx",
        "test/observations.npy",
        "test/test_vectors.c",
    ])  # fmt: skip
    assert report["compiler"]["command"].startswith(
        "cc -std=c99 -Wall -Wextra -Wconversion -Wdouble-promotion -Wcast-qual -Wshadow -Werror -pedantic"
    )
    assert report["code_size"]["text"] > 0
    assert sorted(p.name for p in out.iterdir()) == [
        "bin",
        "c",
        "can",
        "can-fd",
        "chain.json",
        "export_report.json",
        "interface.json",
        "policy.onnx",
        "test",
    ]
    expected_class = {"ddpg": "TD3Policy", "td3": "TD3Policy", "sac": "SACPolicy", "ppo": "ActorCriticPolicy"}
    assert report["source"]["policy_class"] == expected_class[algo]


def test_onnx_is_opset_17_with_inline_weights_and_in_env_units(
    models: dict[str, Path], tmp_path: Path
) -> None:
    import onnx
    import onnxruntime as ort

    out = tmp_path / "export"
    _export(models["sac"], out, "--episodes", "0")
    model = onnx.load(str(out / "policy.onnx"))
    onnx.checker.check_model(model, full_check=True)
    assert model.opset_import[0].version >= 17
    assert not list(out.glob("*.data"))
    assert all(not i.HasField("data_location") or i.data_location == 0 for i in model.graph.initializer)
    session = ort.InferenceSession(str(out / "policy.onnx"))
    obs = gym.make(train.ENV_ID).observation_space.sample().reshape(1, -1)
    assert session.run(None, {"obs": obs})[0].shape == (1, 2)


def test_the_export_carries_the_scenarios_interface(models: dict[str, Path], tmp_path: Path) -> None:
    """One contract: interface.json, the ONNX metadata, policy.h's constants and the report agree with
    the scenario spec the env is built from."""
    import onnx

    out = tmp_path / "export"
    report = _export(models["td3"], out, "--episodes", "0")
    text = (out / "interface.json").read_text()
    assert Interface.from_json(json.loads(text)) == STATIC and text == STATIC.dumps()
    metadata = {p.key: p.value for p in onnx.load(str(out / "policy.onnx")).metadata_props}
    assert metadata["embedrl.interface"] == text
    assert report["interface"] == json.loads(text)
    header = (out / "c" / "policy.h").read_text()
    for kind, fields in (("OBS", STATIC.observation), ("ACT", STATIC.action)):
        for i, f in enumerate(fields):
            assert f"#define POLICY_{kind}_{f.name.upper()} {i}u /* {f.description}: [" in header
    assert "#define POLICY_SAMPLE_TIME_S 0.300000012f" in header
    assert "#define POLICY_SAFE_ACTION {0.0f, 0.0f}" in header


def test_exports_are_deterministic(models: dict[str, Path], tmp_path: Path) -> None:
    a = _export(models["td3"], tmp_path / "a", "--episodes", "0")
    b = _export(models["td3"], tmp_path / "b", "--episodes", "0")
    assert a["files"] == b["files"]


def test_vecnormalize_statistics_go_into_the_graph(tmp_path: Path) -> None:
    venv = VecNormalize(
        DummyVecEnv([lambda: gym.make(train.ENV_ID)]), norm_obs=True, norm_reward=True, clip_obs=5.0
    )
    model = PPO(
        "MlpPolicy",
        venv,
        n_steps=128,
        batch_size=64,
        n_epochs=1,
        seed=0,
        device="cpu",
        policy_kwargs={"net_arch": [16, 16]},
    )
    model.learn(256)
    folder = tmp_path / "run"
    folder.mkdir()
    model.save(folder / "ppo.zip")
    venv.save(str(folder / "vecnormalize.pkl"))  # SB3's pickle: opened only with --trust-pickle
    save_normalization(venv, folder / "vecnormalize.npz")  # what embedrl's training writes beside it
    report = _export(folder / "ppo.zip", tmp_path / "export")
    assert report["source"]["vecnormalize"]["path"].endswith("vecnormalize.npz")
    trusted = _export(
        folder / "ppo.zip",
        tmp_path / "trusted",
        "--vecnormalize",
        str(folder / "vecnormalize.pkl"),
        "--trust-pickle",
    )
    assert trusted["files"]["policy.onnx"] == report["files"]["policy.onnx"]  # the same statistics either way
    assert report["ops"][:3] == ["Sub", "Div", "Clip"]
    assert report["verification"]["onnx_vs_sb3_max_abs_error"] <= TOLERANCE
    assert report["verification"]["c_vs_onnxruntime_max_abs_error"] <= TOLERANCE
    # The graph carries the saved statistics themselves.
    import onnx

    inits = {
        i.name: onnx.numpy_helper.to_array(i)
        for i in onnx.load(str(tmp_path / "export" / "policy.onnx")).graph.initializer
    }
    stats = VecNormalize.load(str(folder / "vecnormalize.pkl"), DummyVecEnv([lambda: gym.make(train.ENV_ID)]))
    rms: Any = stats.obs_rms  # SB3 types it as a dict for Dict spaces; here it is one RunningMeanStd
    assert isinstance(rms, RunningMeanStd)
    np.testing.assert_array_equal(
        inits["normalize_mean"], rms.mean.astype(np.float32)
    )  # names as identifiers
    np.testing.assert_array_equal(inits["normalize_std"], np.sqrt(rms.var + stats.epsilon).astype(np.float32))
    assert float(inits["normalize_high"]) == 5.0


def test_action_unscaling_on_an_env_with_a_wider_action_space(tmp_path: Path) -> None:
    model = _train("sac", "Pendulum-v1", steps=200)
    model.save(tmp_path / "sac_pendulum.zip")
    report = _export(tmp_path / "sac_pendulum.zip", tmp_path / "export", "--env", "Pendulum-v1")
    assert report["ops"][-5:] == ["Add", "Mul", "Mul", "Add", "Identity"]
    assert report["verification"]["onnx_vs_sb3_max_abs_error"] <= TOLERANCE
    assert report["verification"]["c_vs_onnxruntime_max_abs_error"] <= TOLERANCE
    assert "skipped" in report["closed_loop"]
    generic = report["interface"]
    assert [f["name"] for f in generic["observation"]] == ["obs0", "obs1", "obs2"]
    assert generic["sample_time_s"] == 0.05 and generic["safe_action"] == [0.0]
    # Actions reach beyond [-1, 1]: the unscaling to Pendulum's [-2, 2] is inside the graph.
    import onnxruntime as ort

    session = ort.InferenceSession(str(tmp_path / "export" / "policy.onnx"))
    obs = np.random.default_rng(0).uniform([-1, -1, -8], [1, 1, 8], size=(2000, 3)).astype(np.float32)
    actions = session.run(None, {"obs": obs})[0]
    assert actions.min() >= -2.0 and actions.max() <= 2.0


def test_onnx_source_and_name_prefix(models: dict[str, Path], tmp_path: Path) -> None:
    first = tmp_path / "first"
    _export(models["ddpg"], first, "--episodes", "0")
    report = _export(
        first / "policy.onnx", tmp_path / "second", "--name", "drive", "--safe-action", "0.5,-0.5"
    )
    assert report["source"]["kind"] == "onnx" and report["name"] == "drive"
    assert sorted(report["files"]) == [
        "c/drive.c",
        "c/drive.h",
        "c/drive_host.c",  # the batch entry point, for host programs only
        "c/drive_host.h",
        "interface.json",
        "policy.onnx",  # the export carries its ONNX (an ONNX source's too): the folder stands alone
        "test/observations.npy",
        "test/test_vectors.c",
    ]
    assert json.loads((tmp_path / "second" / "interface.json").read_text())["safe_action"] == [0.5, -0.5]
    assert report["verification"]["onnx_vs_sb3_max_abs_error"] is None
    assert report["verification"]["non_finite_observation"] == {"return_code": 1, "action": [0.5, -0.5]}
    assert report["closed_loop"]["differing_outcomes"] == 0
