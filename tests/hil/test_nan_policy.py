"""A policy that is NaN only where verification's samples never look, on the bus: the observation decodes to
exactly 0 there, the exported C (with the clamp the export appends) reports the fault, and the node answers
every such step with the safe action and counts an action fault, never a clamped value in state RUN."""

from __future__ import annotations

import shutil
from pathlib import Path
from typing import Any

import numpy as np
import onnx
import pytest

from embedrl.cli import main
from embedrl.export.reference import OBSERVATIONS_FILE
from embedrl.hil.sandbox import Guest
from embedrl.hil.session import OPEN_LOOP_STEPS
from tests.export.test_nan import _nan_at_zero_unclamped
from tests.hil.helpers import hil_report

SAFE_ACTION = [0.25, 0.0]


@pytest.fixture(scope="module")
def nan_export(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """The export of ``W (x / x) + b`` (a clamp appended), its replayed observations all with x0 = 0."""
    work = tmp_path_factory.mktemp("nan policy")
    onnx.save(_nan_at_zero_unclamped(), work / "nan.onnx")
    out = work / "export"
    argv = ["export", str(work / "nan.onnx"), "--out", str(out), "--obs-range=-10:10", "--act-range=-1:1",
            "--sample-time", "0.1", "--safe-action", "0.25,0", "--episodes", "0"]  # fmt: skip
    assert main(argv) == 0
    replayed = work / "replayed"
    shutil.copytree(out, replayed)
    observations = np.load(replayed / "test" / OBSERVATIONS_FILE)[:OPEN_LOOP_STEPS].copy()
    observations[:, 0] = 0.0
    np.save(replayed / "test" / OBSERVATIONS_FILE, observations)
    return replayed


def _check(report: dict[str, Any]) -> None:
    # The harness expects the safe action wherever the ONNX policy's action is not a valid one (NaN here).
    assert report["steps"] == OPEN_LOOP_STEPS and report["faults"] == 0
    assert report["max_action_abs_diff"] <= 1e-5  # every answer was the safe action
    faults = report["node_diag"]["action_faults"]
    assert faults >= OPEN_LOOP_STEPS // 4  # a fault, SAFE for K = 3 steps, RUN, a fault...
    assert report["verdict"]["passed"] is False  # a policy that faults fails its HIL run
    assert report["verdict"]["failures"] == [
        f"the node refused {faults} policy output(s) (non-finite, outside the action range or an error "
        "status) and sent the safe action instead"
    ]


def test_the_python_node_answers_a_nan_policy_with_the_safe_action(nan_export: Path) -> None:
    _check(hil_report(None, nan_export, "--node", "python", "--episodes", "1"))


@pytest.mark.slow
def test_the_c_node_answers_a_nan_policy_with_the_safe_action_over_vcan(
    guest: Guest, nan_export: Path
) -> None:
    _check(hil_report(guest, nan_export, "--episodes", "1"))
