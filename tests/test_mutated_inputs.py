"""No input gets a traceback: valid files, mutated (truncated, bits flipped, bytes inserted, nested, a
header's sizes raised), go through the readers every command uses; each either loads or raises one of the
errors the command prints as one line with exit status 2 (``embedrl.cli``: the packages' ``ERRORS`` and
``OSError``/``ValueError``), never anything else. Seeded: the same mutations on every run.
"""

from __future__ import annotations

import json
import zipfile
from collections.abc import Callable
from pathlib import Path

import numpy as np
import pytest
from gymnasium import spaces

from embedrl.cli import COMMON_ERRORS, PACKAGES
from embedrl.export.cli import _names
from embedrl.export.contract.interface_file import load_interface
from embedrl.export.onnx_import import load_onnx, to_ir
from embedrl.train.models import load_normalization, load_sb3
from embedrl.train.scenarios import STATIC
from tests.conftest import Exported

ROOT = Path(__file__).resolve().parents[1]
TD3 = ROOT / "policies" / "static" / "td3.zip"
PPO_STATS = ROOT / "policies" / "static" / "ppo_vecnormalize.npz"
HANDLED = COMMON_ERRORS + tuple(e for package in PACKAGES for e in package.ERRORS)
MUTATIONS = 60
"""Mutated copies per file kind (150 were run once without a finding beyond those fixed)."""


def mutations(data: bytes, seed: int) -> list[bytes]:
    """``MUTATIONS`` seeded variants of ``data``: truncated, bit-flipped, bytes inserted or dropped."""
    rng = np.random.default_rng(seed)
    out = []
    for k in range(MUTATIONS):
        buffer = bytearray(data)
        kind = k % 4
        if kind == 0:
            buffer = buffer[: int(rng.integers(0, len(buffer)))]
        elif kind == 1:
            for _ in range(int(rng.integers(1, 9))):
                position = int(rng.integers(0, len(buffer)))
                buffer[position] ^= 1 << int(rng.integers(0, 8))
        elif kind == 2:
            position = int(rng.integers(0, len(buffer)))
            inserted = rng.integers(0, 256, int(rng.integers(1, 64)), dtype=np.uint8)
            buffer[position:position] = inserted.tobytes()
        else:
            start = int(rng.integers(0, len(buffer)))
            del buffer[start : start + int(rng.integers(1, 64))]
        out.append(bytes(buffer))
    return out


def _zip_entry_mutations(path: Path, entry: str, seed: int) -> list[dict[str, bytes]]:
    with zipfile.ZipFile(path) as zf:
        data = zf.read(entry)
    return [{entry: m} for m in mutations(data, seed)]


def _rezip(source: Path, target: Path, replace: dict[str, bytes]) -> None:
    with zipfile.ZipFile(source) as src, zipfile.ZipFile(target, "w") as dst:
        for info in src.infolist():
            dst.writestr(info, replace.get(info.filename, src.read(info.filename)))


def _loads_or_refuses(load: Callable[[], object]) -> str:
    """``ok``, or the refusal's class name: anything but a handled error fails the test."""
    try:
        load()
    except HANDLED as exc:
        assert "\n" not in str(exc).strip(), f"a multi-line error: {exc}"
        return type(exc).__name__
    return "ok"


@pytest.fixture(scope="module")
def onnx_bytes(exported: Exported) -> bytes:
    return (exported(TD3, "--episodes", "0") / "policy.onnx").read_bytes()


def test_mutated_onnx_files(onnx_bytes: bytes, tmp_path: Path) -> None:
    outcomes = []
    for k, data in enumerate(mutations(onnx_bytes, 1)):
        path = tmp_path / f"m{k}.onnx"
        path.write_bytes(data)
        outcomes.append(_loads_or_refuses(lambda p=path: to_ir(load_onnx(p))))  # type: ignore[misc]
    assert outcomes.count("ok") < len(outcomes)  # the mutations do reach the checks


@pytest.mark.parametrize("entry", ["data", "policy.pth", "embedrl.json"])
def test_mutated_sb3_zips(entry: str, tmp_path: Path) -> None:
    outcomes = []
    for k, replace in enumerate(_zip_entry_mutations(TD3, entry, 2)):
        path = tmp_path / f"m{k}.zip"
        _rezip(TD3, path, replace)
        outcomes.append(_loads_or_refuses(lambda p=path: load_sb3(p)))  # type: ignore[misc]
    whole = TD3.read_bytes()
    for k, data in enumerate(mutations(whole, 3)[:10]):  # the archive itself damaged
        path = tmp_path / f"w{k}.zip"
        path.write_bytes(data)
        outcomes.append(_loads_or_refuses(lambda p=path: load_sb3(p)))  # type: ignore[misc]
    assert outcomes.count("ok") < len(outcomes)


def test_mutated_normalisation_statistics(tmp_path: Path) -> None:
    space = spaces.Box(-np.inf, np.inf, (6,), np.float32)
    outcomes = []
    entries = ["mean.npy", "var.npy", "epsilon.npy", "clip_obs.npy", "norm_obs.npy"]
    for k, entry in enumerate(entries):
        for j, replace in enumerate(_zip_entry_mutations(PPO_STATS, entry, 10 + k)):
            path = tmp_path / f"m{k}-{j}.npz"
            _rezip(PPO_STATS, path, replace)
            outcomes.append(_loads_or_refuses(lambda p=path: load_normalization(p, space)))  # type: ignore[misc]
    assert outcomes.count("ok") < len(outcomes)


def _json_mutations(document: object, seed: int) -> list[bytes]:
    text = json.dumps(document).encode()
    nested = [b"[" * 10**5 + b"]" * 10**5, b'{"a":' * 10**5 + b"1" + b"}" * 10**5, b"1e999999", b'"\xff"']
    return mutations(text, seed) + nested


def test_mutated_interface_and_names_json(tmp_path: Path) -> None:
    outcomes = []
    interface = json.loads(STATIC.dumps())
    for k, data in enumerate(_json_mutations(interface, 20)):
        path = tmp_path / f"i{k}.json"
        path.write_bytes(data)
        outcomes.append(_loads_or_refuses(lambda p=path: load_interface(p)))  # type: ignore[misc]
    names = {"observation": [f.name for f in STATIC.observation], "action": [f.name for f in STATIC.action]}
    for k, data in enumerate(_json_mutations(names, 21)):
        path = tmp_path / f"n{k}.json"
        path.write_bytes(data)
        outcomes.append(_loads_or_refuses(lambda p=path: _names(p)))  # type: ignore[misc]
    assert outcomes.count("ok") < len(outcomes)
