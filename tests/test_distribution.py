"""The wheel is the product: installed outside the checkout, it exports a policy and runs it over CAN.

The wheel is built from this checkout and installed without dependencies into a fresh virtual environment
outside it; the dependencies come from the project's own environment through a path file (so the test
downloads nothing). Every command then runs from a folder outside the checkout, so nothing can be found
through the repository.
"""

from __future__ import annotations

import json
import subprocess
import sys
import sysconfig
import zipfile
from pathlib import Path

import pytest

import embedrl

pytestmark = pytest.mark.slow
REPO = Path(__file__).resolve().parents[1]
POLICY = REPO / "policies" / "static" / "td3.zip"


def _run(argv: list[str], cwd: Path) -> subprocess.CompletedProcess[str]:
    result = subprocess.run(argv, cwd=cwd, capture_output=True, text=True)
    assert result.returncode == 0, f"{argv}:\n{result.stdout[-3000:]}\n{result.stderr[-3000:]}"
    return result


@pytest.fixture(scope="module")
def installed(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """The bin folder of a fresh virtual environment with only the wheel installed (plus the deps' path)."""
    root = tmp_path_factory.mktemp("dist")
    _run(
        [
            sys.executable,
            "-m",
            "pip",
            "wheel",
            str(REPO),
            "--no-deps",
            "--no-build-isolation",
            "-w",
            str(root),
        ],
        root,
    )
    wheel = next(root.glob("embedrl-*.whl"))
    names = zipfile.ZipFile(wheel).namelist()
    for required in (
        "embedrl/runtime_c/Makefile", "embedrl/runtime_c/node/node.c", "embedrl/hil/policy.dbc",
        "embedrl/runtime_c/tests/can_static/policy_io.c",  # make -C runtime_c test: no Python needed
    ):  # fmt: skip
        assert required in names
    assert not any(n.startswith(("train/", "export/", "hil/")) for n in names)  # one namespace only
    for folder in ("train", "export", "hil"):  # every package of the checkout, subpackages included
        for module in (REPO / folder).rglob("*.py"):
            assert f"embedrl/{module.relative_to(REPO)}" in names
    venv = root / "venv"
    _run([sys.executable, "-m", "venv", str(venv)], root)
    site = next((venv / "lib").glob("python3.*/site-packages"))
    (site / "embedrl-test-deps.pth").write_text(sysconfig.get_paths()["purelib"] + "\n")
    _run(
        [str(venv / "bin" / "python"), "-m", "pip", "install", "--no-deps", "--no-index", "-q", str(wheel)],
        root,
    )
    return venv / "bin"


def test_the_installed_command_knows_its_version_and_location(installed: Path, tmp_path: Path) -> None:
    assert (
        _run([str(installed / "embedrl"), "--version"], tmp_path).stdout.strip()
        == f"embedrl {embedrl.__version__}"
    )
    where = _run(
        [str(installed / "python"), "-c", "import embedrl.export.build as b; print(b.RUNTIME_C)"], tmp_path
    )
    assert not Path(where.stdout.strip()).is_relative_to(REPO)  # the wheel's own copy of runtime_c


def test_the_installed_wheel_exports_and_runs_hil_outside_the_checkout(
    installed: Path, tmp_path: Path
) -> None:
    out = tmp_path / "export"
    _run([str(installed / "embedrl"), "export", str(POLICY), "--out", str(out), "--episodes", "0"], tmp_path)
    assert (out / "interface.json").is_file() and (out / "c" / "policy.h").is_file()
    report = tmp_path / "hil.json"
    _run(
        [
            str(installed / "embedrl"),
            "hil",
            "run",
            "--export-dir",
            str(out),
            "--episodes",
            "1",
            "--json",
            str(report),
        ],
        tmp_path,
    )
    data = json.loads(report.read_text())
    assert data["successes"] == data["simulation"]["successes"] == 1
    assert data["max_action_abs_diff"] <= 1e-5
