"""A QDQ-quantised ONNX from elsewhere, exported to int8 C, closes the loop over vcan on the C node as
the simulation does with the same C (and on the Python node running its integer model)."""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path

import pytest

from embedrl.hil.sandbox import Guest
from tests.export.helpers import quantized
from tests.hil.conftest import SHIPPED_TD3
from tests.hil.helpers import hil


@pytest.fixture(scope="module")
def qdq_export(exported: Callable[..., Path], tmp_path_factory: pytest.TempPathFactory) -> Path:
    source = quantized(exported(SHIPPED_TD3, "--episodes", "0"), tmp_path_factory.mktemp("qdq") / "qdq.onnx")
    return exported(source, "--scenario", "static", "--episodes", "0")


@pytest.mark.parametrize(
    "node",
    ["python", pytest.param("c", marks=pytest.mark.sandbox)],  # the C node runs in the guest
)
def test_a_qdq_export_passes_hil_on_every_node(
    node: str, qdq_export: Path, tmp_path: Path, request: pytest.FixtureRequest
) -> None:
    guest: Guest | None = request.getfixturevalue("guest") if node == "c" else None
    report = hil(guest, qdq_export, tmp_path, "--node", node, "--episodes", "1", "--seed", "3")
    assert report["precision"] == "int8"
    assert report["outcomes_differing_from_simulation"] == [] and report["faults"] == 0
    assert report["max_action_abs_diff"] <= CAN_RESOLUTION  # the same integers; the signal's resolution


CAN_RESOLUTION = 1e-5
"""How far a decoded action may be from the computed one: the CAN signal's scaling."""
