"""A HIL report is evidence the deployment report copies into its bundle: one that does not name the files it
ran with, or whose counts do not add up to its own rows, is refused in one line before anything is
gathered."""

from __future__ import annotations

import json
import shutil
from pathlib import Path
from typing import Any

import pytest

from embedrl.cli import main
from embedrl.common import sha256
from embedrl.hil.errors import HilError
from embedrl.hil.signoff import facts
from tests.conftest import Exported

SHIPPED_TD3 = Path(__file__).resolve().parents[2] / "policies" / "static" / "td3.zip"
C_NODE_FILES = (
    "policy.onnx", "interface.json", "c/policy.c", "can/policy_dbc.h", "can/policy_dbc.c", "can/policy_io.h",
    "can/policy_io.c", "can/e2e_params.h",
)  # fmt: skip


@pytest.fixture(scope="module")
def export(exported: Exported) -> Path:
    return exported(SHIPPED_TD3, "--episodes", "0")


def _report(export: Path, outcomes: list[str]) -> dict[str, Any]:
    """A report of the C node's run with ``outcomes``, as `hil run --json` writes its keys the page reads."""
    rows = [{"seed": k, "outcome": o, "steps": 10} for k, o in enumerate(outcomes)]
    counted = {key: outcomes.count(o) for key, o in facts.OUTCOME_COUNTS.items()}
    return {
        "export_files": {name: sha256(export / name) for name in C_NODE_FILES},
        "verdict": {"passed": True, "failures": []},
        "node": "c",
        "target": None,
        "simulation": None,
        "firmware": None,
        "per_episode": rows,
        "episodes": len(rows),
        **counted,
        "success_rate": counted["successes"] / len(rows),
    }


def _load(tmp_path: Path, export: Path, data: dict[str, Any]) -> dict[str, Any]:
    path = tmp_path / "hil.json"
    path.write_text(json.dumps(data))
    return facts.load_hil(path, export)


def test_a_report_whose_counts_add_up_and_names_its_files_is_read(export: Path, tmp_path: Path) -> None:
    assert _load(tmp_path, export, _report(export, ["success", "success", "collision"]))["successes"] == 2


@pytest.mark.parametrize(
    ("forge", "message"),
    [
        (lambda d: d.update(export_files={}), "does not name the export files it ran with: policy.onnx"),
        (lambda d: d["export_files"].pop("can/policy_io.c"), "the CAN code it was built from"),
        (lambda d: d.update(successes=999), "'successes' is 999 but 2 of its episodes ended in success"),
        (lambda d: d.update(episodes=999), "'episodes' is 999 but 'per_episode' has 3 rows"),
        (lambda d: d.update(collisions=0), "'collisions' is 0 but 1 of its episodes ended in collision"),
        (lambda d: d.update(success_rate=1.0), "'success_rate' is 1.0, not its successes over its episodes"),
        (lambda d: d["per_episode"].append("row"), "not a list of episodes with their outcomes"),
        (lambda d: d.update(successes="2"), "'successes' is '2', not a count"),
    ],
)
def test_a_forged_report_is_refused_naming_what_does_not_hold(
    export: Path, tmp_path: Path, forge: Any, message: str
) -> None:
    data = _report(export, ["success", "success", "collision"])
    forge(data)
    with pytest.raises(HilError) as caught:
        _load(tmp_path, export, data)
    assert message in str(caught.value) and "\n" not in str(caught.value)


def test_the_report_command_refuses_a_forged_report_before_writing_anything(
    export: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    data = _report(export, ["success"])
    data.update(export_files={}, successes=999)
    forged = tmp_path / "hil.json"
    forged.write_text(json.dumps(data))
    page = tmp_path / "report.html"
    assert main(["report", str(export), "--hil", str(forged), "--out", str(page)]) == 2
    err = capsys.readouterr().err
    assert err.startswith("error: ") and err.count("\n") == 1
    assert not page.exists()


@pytest.mark.parametrize(
    ("edit", "message"),
    [
        (lambda r: r["source"].update(sha256="<!--" + "0" * 60), "source/sha256"),
        (lambda r: r["source"].update(sha256='<img src="//evil.example/x">'), "source/sha256"),
        (lambda r: r.update(observation_dim="6"), "observation_dim: '6' is not allowed (type"),
        (lambda r: r["verification"].update(tolerance="1e-5"), "verification/tolerance"),
        (lambda r: r.update(ops=["Gemm<script>"]), "ops/0"),
        (lambda r: r.update(targets={"<b>m4</b>": {}}), "targets"),
        (lambda r: r["files"].update({"../../etc/passwd": "0" * 64}), "files"),
        (lambda r: r["compiler"].update(command="cc\n<script>"), "compiler/command"),
    ],
)
def test_an_edited_export_report_is_refused_before_anything_is_rendered(
    export: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str], edit: Any, message: str
) -> None:
    folder = tmp_path / "export"
    shutil.copytree(export, folder)
    report = json.loads((folder / "export_report.json").read_text())
    edit(report)
    (folder / "export_report.json").write_text(json.dumps(report))
    page = tmp_path / "report.html"
    assert main(["report", str(folder), "--out", str(page)]) == 2
    err = capsys.readouterr().err
    assert err.startswith("error: ") and err.count("\n") == 1 and message in err, err
    assert not page.exists()
