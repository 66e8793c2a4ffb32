"""Model files are untrusted: loading one never runs code from it unless the user says --trust-pickle.

Each malicious file carries a payload that creates a marker file when unpickled. The same file opened with
``--trust-pickle`` does create the marker: the payloads are live, so the tests can fail.
"""

from __future__ import annotations

import base64
import json
import os
import pickle
import shutil
import zipfile
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from embedrl.cli import main
from embedrl.train.errors import InvalidModelFileError
from embedrl.train.models import load_normalization, load_sb3, save_normalization
from embedrl.train.sb3_archive import class_reference
from tests.conftest import Exported

POLICIES = Path(__file__).resolve().parents[1] / "policies" / "static"


class _Payload:
    """Unpickling this runs ``touch MARKER``."""

    def __init__(self, marker: Path) -> None:
        self.marker = marker

    def __reduce__(self) -> tuple[Any, ...]:
        return (os.system, (f"touch {self.marker}",))


def _evil_zip(tmp_path: Path, field: str) -> tuple[Path, Path]:
    """td3.zip with ``field``'s pickle replaced by the payload; (the zip, its marker)."""
    marker = tmp_path / f"ran-{field}"
    source, target = POLICIES / "td3.zip", tmp_path / "evil.zip"
    with zipfile.ZipFile(source) as src, zipfile.ZipFile(target, "w") as dst:
        for item in src.infolist():
            content = src.read(item.filename)
            if item.filename == "data":
                data = json.loads(content)
                data[field][":serialized:"] = base64.b64encode(pickle.dumps(_Payload(marker))).decode()
                content = json.dumps(data).encode()
            dst.writestr(item, content)
    return target, marker


@pytest.mark.parametrize("field", ["policy_class", "observation_space", "policy_kwargs"])
def test_a_pickle_in_the_archive_never_runs(
    field: str, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    evil, marker = _evil_zip(tmp_path, field)
    out = tmp_path / "export"
    code = main(["export", str(evil), "--out", str(out), "--episodes", "0"])
    err = capsys.readouterr().err
    assert not marker.exists(), "the export ran code from the model file"
    if field == "policy_class":  # the one pickle the loader must understand: refused, never run
        assert code == 2 and "policy_class is not a plain class reference" in err and "--trust-pickle" in err
        assert not out.exists()
    else:  # the readable copy beside the pickle is used; the pickle is never touched
        assert code == 0
    assert main(["eval", str(evil), "--episodes", "1"]) in (0, 2)
    assert not marker.exists(), "eval ran code from the model file"
    # The control: the payload is live, and --trust-pickle (SB3's own reader) runs it.
    main(["eval", str(evil), "--episodes", "1", "--trust-pickle"])
    assert marker.exists()


def test_normalisation_pickles_beside_a_model_are_refused_without_trust(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    marker = tmp_path / "ran-pkl"
    shutil.copy(POLICIES / "ppo.zip", tmp_path / "ppo.zip")
    (tmp_path / "ppo_vecnormalize.pkl").write_bytes(pickle.dumps(_Payload(marker)))
    out = tmp_path / "export"
    assert main(["export", str(tmp_path / "ppo.zip"), "--out", str(out), "--episodes", "0"]) == 2
    err = capsys.readouterr().err
    assert "ppo_vecnormalize.pkl is a pickle that needs more than VecNormalize's statistics" in err
    assert "posix.system" in err and "--trust-pickle" in err
    assert not marker.exists() and not out.exists()
    assert main(["eval", str(tmp_path / "ppo.zip"), "--episodes", "1"]) == 2
    assert not marker.exists()
    main(["export", str(tmp_path / "ppo.zip"), "--out", str(out), "--episodes", "0", "--trust-pickle"])
    assert marker.exists()  # the control: opted in, the pickle is opened


def test_a_pickle_in_the_network_parameters_is_refused(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    marker = tmp_path / "ran-pth"
    target = tmp_path / "evil.zip"
    with zipfile.ZipFile(POLICIES / "td3.zip") as src, zipfile.ZipFile(target, "w") as dst:
        for item in src.infolist():
            content = src.read(item.filename)
            if item.filename == "policy.pth":
                import torch

                path = tmp_path / "evil.pth"
                torch.save({"payload": _Payload(marker)}, path)
                content = path.read_bytes()
            dst.writestr(item, content)
    assert main(["export", str(target), "--out", str(tmp_path / "x"), "--episodes", "0"]) == 2
    assert "not a readable Stable-Baselines3 model" in capsys.readouterr().err
    assert not marker.exists()


def test_exporting_an_onnx_file_unpickles_nothing(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, exported: Exported
) -> None:
    onnx = exported(POLICIES / "td3.zip", "--episodes", "0") / "policy.onnx"

    def refuse(*args: object, **kwargs: object) -> None:
        raise AssertionError("something was unpickled")

    monkeypatch.setattr(pickle, "load", refuse)
    monkeypatch.setattr(pickle, "loads", refuse)
    monkeypatch.setattr(pickle, "Unpickler", refuse)
    assert main(["export", str(onnx), "--out", str(tmp_path / "b"), "--episodes", "0"]) == 0
    # ... and neither does an SB3 zip without --trust-pickle.
    assert main(["export", str(POLICIES / "ppo.zip"), "--out", str(tmp_path / "c"), "--episodes", "0"]) == 0


@pytest.mark.parametrize("name", ["td3", "sac", "ddpg", "ppo"])
def test_the_safe_reader_gives_the_same_policy_as_sb3s(name: str) -> None:
    model = POLICIES / f"{name}.zip"
    safe, trusted = load_sb3(model), load_sb3(model, trust_pickle=True)
    assert type(safe.policy) is type(trusted.policy)
    for a, b in (
        (safe.observation_space, trusted.observation_space),
        (safe.action_space, trusted.action_space),
    ):
        assert a == b and np.array_equal(a.low, b.low) and np.array_equal(a.high, b.high)
    obs = np.random.default_rng(0).uniform(-1, 1, (200, 6)).astype(np.float32)
    assert np.array_equal(safe.predict(obs), trusted.predict(obs))


def test_class_references_are_decoded_without_running_the_pickle() -> None:
    from stable_baselines3.td3.policies import TD3Policy

    assert class_reference(base64.b64encode(pickle.dumps(TD3Policy)).decode()) == (
        "stable_baselines3.td3.policies",
        "TD3Policy",
    )
    with pytest.raises(ValueError, match="not a plain class reference"):
        class_reference(base64.b64encode(pickle.dumps(_Payload(Path("/nonexistent/x")))).decode())
    with pytest.raises(ValueError, match="not a pickle"):
        class_reference(base64.b64encode(b"garbage").decode())


def test_normalisation_statistics_round_trip_as_npz(tmp_path: Path) -> None:
    from gymnasium import spaces

    class Stats:
        class obs_rms:
            mean = np.array([0.5, -1.0])
            var = np.array([2.0, 0.25])

        epsilon, clip_obs, norm_obs = 1e-8, 10.0, True

    save_normalization(Stats(), tmp_path / "n.npz")
    loaded = load_normalization(tmp_path / "n.npz", spaces.Box(-1, 1, (2,)))
    assert loaded is not None
    assert loaded.mean.tolist() == [0.5, -1.0] and loaded.var.tolist() == [2.0, 0.25] and loaded.clip == 10.0
    with pytest.raises(InvalidModelFileError, match=r"mean has shape \(2,\) \(2 values\); expected \(3,\)"):
        load_normalization(tmp_path / "n.npz", spaces.Box(-1, 1, (3,)))


def _stats_pickle(npz: Path, target: Path) -> None:
    """SB3's own VecNormalize pickle holding the statistics of ``npz`` (as RL Zoo saves them)."""
    import gymnasium as gym
    from stable_baselines3.common.vec_env import DummyVecEnv, VecNormalize

    with np.load(npz) as f:
        env = VecNormalize(
            DummyVecEnv([lambda: gym.make("embedrl/WarehouseRobot-v0")]), epsilon=float(f["epsilon"])
        )
        rms: Any = env.obs_rms
        rms.mean, rms.var = f["mean"].copy(), f["var"].copy()
        env.clip_obs = float(f["clip_obs"])
    target.parent.mkdir(parents=True, exist_ok=True)
    env.save(str(target))


def test_a_model_without_its_own_statistics_is_refused_and_rl_zoo_layout_is_found(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    alone = tmp_path / "alone"
    alone.mkdir()
    shutil.copy(POLICIES / "ppo.zip", alone / "ppo.zip")  # copied without its statistics
    export = ["export", str(alone / "ppo.zip"), "--out", str(tmp_path / "x"), "--episodes", "0"]
    for argv in (["eval", str(alone / "ppo.zip"), "--episodes", "2"], export):
        assert main(argv) == 2
        err = capsys.readouterr().err
        assert "trained with observation normalisation but its statistics are missing" in err
        assert len(err.strip().splitlines()) == 1 and not (tmp_path / "x").exists()
    # other statistics (a changed mean): refused, named
    with np.load(POLICIES / "ppo_vecnormalize.npz") as f:
        arrays = {k: f[k] for k in f.files}
    arrays["mean"] = arrays["mean"] + 0.01
    np.savez(alone / "other.npz", **arrays)
    assert (
        main(["eval", str(alone / "ppo.zip"), "--episodes", "2", "--vecnormalize", str(alone / "other.npz")])
        == 2
    )
    assert "are not" in capsys.readouterr().err
    # its own, given explicitly: accepted
    own = ["--vecnormalize", str(POLICIES / "ppo_vecnormalize.npz")]
    assert (
        main(["eval", str(alone / "ppo.zip"), "--episodes", "2", "--json", str(tmp_path / "a.json"), *own])
        == 0
    )
    # RL Zoo's layout: logs/ppo/<env>_1/<env>.zip with <env>/vecnormalize.pkl, read without running code
    zoo = tmp_path / "logs" / "ppo" / "WarehouseRobot-v0_1"
    zoo.mkdir(parents=True)
    shutil.copy(POLICIES / "ppo.zip", zoo / "WarehouseRobot-v0.zip")
    _stats_pickle(POLICIES / "ppo_vecnormalize.npz", zoo / "WarehouseRobot-v0" / "vecnormalize.pkl")
    assert (
        main(
            [
                "eval",
                str(zoo / "WarehouseRobot-v0.zip"),
                "--episodes",
                "2",
                "--json",
                str(tmp_path / "z.json"),
            ]
        )
        == 0
    )
    a, z = (json.loads((tmp_path / n).read_text()) for n in ("a.json", "z.json"))
    assert a["per_episode"] == z["per_episode"]  # the same statistics, so the same episodes
    # a model trained without normalisation refuses statistics given to it
    assert main(["eval", str(POLICIES / "td3.zip"), "--episodes", "2", *own]) == 2
    assert "trained without observation normalisation" in capsys.readouterr().err
