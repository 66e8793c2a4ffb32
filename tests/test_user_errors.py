"""Every error a user can cause is one line on stderr and exit status 2, from the real command, with
nothing written: the table of bad inputs found by a hostile review, walked row by row."""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
import onnx
import pytest
from onnx import TensorProto, helper, numpy_helper

from embedrl.cli import main
from embedrl.common import owned_temporary_folder

ROOT = Path(__file__).resolve().parents[1]
TD3 = ROOT / "policies" / "static" / "td3.zip"


def _gemm_model(
    weights: TensorProto, obs_dim: int, act_dim: int, batch: int | str = "batch"
) -> onnx.ModelProto:
    graph = helper.make_graph(
        [helper.make_node("Gemm", ["obs", weights.name], ["act"], transB=1)],
        "g",
        [helper.make_tensor_value_info("obs", TensorProto.FLOAT, [batch, obs_dim])],
        [helper.make_tensor_value_info("act", TensorProto.FLOAT, [batch, act_dim])],
        [weights],
    )
    return helper.make_model(graph, opset_imports=[helper.make_opsetid("", 17)], ir_version=8)


def _external(name: str, dims: list[int], location: str) -> TensorProto:
    tensor = TensorProto(name=name, data_type=TensorProto.FLOAT, dims=dims)
    tensor.data_location = TensorProto.EXTERNAL
    entry = tensor.external_data.add()
    entry.key, entry.value = "location", location
    return tensor


def traversal(tmp: Path) -> list[str]:
    path = tmp / "traversal.onnx"
    onnx.save(_gemm_model(_external("W", [2, 6], "../../etc/passwd"), 6, 2), path)
    return ["export", str(path), "--out", str(tmp / "out"), "--episodes", "0"]


def huge_declared(tmp: Path) -> list[str]:
    path = tmp / "huge.onnx"
    onnx.save(_gemm_model(_external("W", [50_000, 50_000], "big.bin"), 50_000, 50_000), path)
    (tmp / "big.bin").write_bytes(b"")  # nothing needs reading: the declared size is refused
    return ["export", str(path), "--out", str(tmp / "out"), "--episodes", "0"]


def too_many_bytes(tmp: Path) -> list[str]:
    path = tmp / "inline.onnx"
    weights = np.random.default_rng(0).normal(size=(2, 300_000)).astype(np.float32)  # 2.4 MB inline
    onnx.save(_gemm_model(numpy_helper.from_array(weights, "W"), 300_000, 2), path)
    return ["export", str(path), "--out", str(tmp / "out"), "--episodes", "0", "--max-model-mb", "1"]


NEGATIVE_SEED = "argument --seed: a seed is a whole number within 0..2,147,483,647, got -5"
PF = ["--controller", "potential-field"]

ROWS = {
    "external data outside the model's folder": (traversal, "is outside the model's folder"),
    "a declared 50,000 x 50,000 Gemm": (huge_declared, "parameters exceed the limit of 4,000,000"),
    "a model above the size limit": (too_many_bytes, "exceeds the 1 MB limit"),
    "an unknown env": (
        lambda tmp: ["export", str(TD3), "--env", "NoSuchEnv-v0", "--out", str(tmp / "out")],
        "Environment `NoSuchEnv` doesn't exist",
    ),
    "--name int": (lambda tmp: ["export", str(TD3), "--name", "int", "--out", str(tmp / "out")], "int"),
    "--name math": (lambda tmp: ["export", str(TD3), "--name", "math", "--out", str(tmp / "out")], "math"),
    "--name _": (lambda tmp: ["export", str(TD3), "--name", "_", "--out", str(tmp / "out")], "_"),
    "a missing model": (
        lambda tmp: ["export", str(tmp / "no.zip"), "--out", str(tmp / "out")],
        "no such file",
    ),
    "eval of a file that is no model": (
        lambda tmp: ["eval", str(ROOT / "README.md")],
        "give a Stable-Baselines3",
    ),
    "an unknown algorithm": (
        lambda tmp: ["train", "--algo", "nosuch", "--out", str(tmp / "out")],
        "invalid choice",
    ),
    "resume of a folder that is no run": (lambda tmp: ["train", "--resume", str(tmp)], "not a run directory"),
    "a negative shaping gain": (
        lambda tmp: [
            "train",
            "--set",
            "reward=shaped",
            "--set",
            "shaping_gain=-1",
            "--out",
            str(tmp / "out"),
        ],
        "shaping_gain must be a finite number >= 0",
    ),
    "hil run without an export": (
        lambda tmp: ["hil", "run", "--export-dir", str(tmp), "--json", str(tmp / "out" / "h.json")],
        "no c/policy.c",
    ),
    "an unknown fault": (
        lambda tmp: ["hil", "run", "--export-dir", str(tmp), "--json", str(tmp / "h.json"), "--inject", "x"],
        "unknown fault 'x'",
    ),
    "eval --seed -5": (
        lambda tmp: ["eval", *PF, "--seed", "-5", "--json", str(tmp / "e.json")],
        NEGATIVE_SEED,
    ),
    "render --seed -5": (
        lambda tmp: ["render", *PF, "--seed", "-5", "--out", str(tmp / "r.png")],
        NEGATIVE_SEED,
    ),
    "scope --seed -5": (
        lambda tmp: ["scope", *PF, "--seed", "-5", "--out", str(tmp / "s.png")],
        NEGATIVE_SEED,
    ),
    "hil run --seed -5": (
        lambda tmp: ["hil", "run", "--export-dir", str(tmp), "--node", "python", "--seed", "-5"],
        NEGATIVE_SEED,
    ),
    "hil run --node python --target cortex-m3": (
        lambda tmp: ["hil", "run", "--export-dir", str(tmp), "--node", "python", "--target", "cortex-m3"],
        "--target does not apply to --node python",
    ),
    "hil run --node python --target cortex-m0": (
        lambda tmp: ["hil", "run", "--export-dir", str(tmp), "--node", "python", "--target", "cortex-m0"],
        "argument --target: invalid choice: 'cortex-m0'",
    ),
    "hil run --node python --sandbox uml": (
        lambda tmp: ["hil", "run", "--export-dir", str(tmp), "--node", "python", "--sandbox", "uml"],
        "--sandbox does not apply to --node python",
    ),
    "hil run --timeout-ms 1": (
        lambda tmp: ["hil", "run", "--export-dir", str(tmp), "--node", "python", "--timeout-ms", "1"],
        "--timeout-ms 1: the node's watchdog must be within 50..60000 ms",
    ),
}


LAUNCHER = """
import os, sys
pid = os.fork()
if pid == 0:
    os.execv(sys.argv[2], sys.argv[2:])
_, status, usage = os.wait4(pid, 0)
with open(sys.argv[1], "w") as f:
    f.write(f"{usage.ru_maxrss} {usage.ru_utime + usage.ru_stime}")
sys.exit(os.waitstatus_to_exitcode(status))
"""
"""Runs a command and writes its peak resident memory (kB) and its CPU time (user + system, s, its own
children included). Linux counts a forked child's peak from its parent's memory at the fork, so the command
is forked from this small launcher, not from pytest."""

WALL_LIMIT_S = 120
"""A measured command still running after this wall time fails the test (it blocks or loops)."""


def run_measured(
    argv: list[str], env: dict[str, str]
) -> tuple[subprocess.CompletedProcess[str], float, float]:
    """``embedrl ARGV`` in a child: the result, its CPU time in s and its peak resident memory in MB.

    CPU time, not wall time: it holds on a loaded machine, where another job's share of the cores would
    otherwise be counted against the command. A command that blocks instead of working is stopped after
    ``WALL_LIMIT_S``."""
    with tempfile.TemporaryDirectory() as scratch:
        measured = Path(scratch) / "measured"
        result = subprocess.run(
            [sys.executable, "-c", LAUNCHER, str(measured), sys.executable, "-m", "embedrl.cli", *argv],
            capture_output=True,
            text=True,
            env=env,
            timeout=WALL_LIMIT_S,
        )
        maxrss_kb, cpu_s = measured.read_text().split()
    return (
        subprocess.CompletedProcess(argv, result.returncode, result.stdout, result.stderr),
        float(cpu_s),
        int(maxrss_kb) / 1024,
    )


def assert_refused(argv: list[str], said: str, tmp_path: Path) -> tuple[float, float]:
    """Run ``embedrl ARGV`` (TMPDIR inside ``tmp_path``): one line on stderr containing ``said``, exit
    status 2, nothing written to ``tmp_path``, no temporary folder left; its CPU time and peak memory."""
    temporary = tmp_path / "tmp"
    temporary.mkdir()
    before = sorted(p.name for p in tmp_path.iterdir())
    result, cpu_s, peak_mb = run_measured(argv, {**os.environ, "TMPDIR": str(temporary)})
    lines = result.stderr.strip().splitlines()
    assert result.returncode == 2, result.stderr[-2000:]
    assert len(lines) == 1 and said in lines[0] and "Traceback" not in result.stderr, result.stderr[-2000:]
    assert sorted(p.name for p in tmp_path.iterdir()) == before  # no output, no staging folder
    assert not [p for p in temporary.iterdir() if p.name.startswith("embedrl")]  # no temporary folder
    return cpu_s, peak_mb


@pytest.mark.parametrize("row", list(ROWS))
def test_a_user_error_is_one_line_exit_2_and_writes_nothing(row: str, tmp_path: Path) -> None:
    make_argv, said = ROWS[row]
    assert_refused(make_argv(tmp_path), said, tmp_path)


def test_the_firmware_node_without_its_tools_is_refused_before_anything_is_built(tmp_path: Path) -> None:
    # PATH without qemu-system-arm and arm-none-eabi-gcc: refused before the sandbox boots or make runs
    argv = [
        "hil",
        "run",
        "--export-dir",
        str(tmp_path),
        "--node",
        "firmware",
        "--json",
        str(tmp_path / "h.json"),
    ]
    empty = tmp_path / "empty"
    empty.mkdir()
    result, _, _ = run_measured(argv, {**os.environ, "PATH": str(empty)})
    lines = result.stderr.strip().splitlines()
    assert result.returncode == 2 and len(lines) == 1, result.stderr[-2000:]
    assert "--node firmware needs arm-none-eabi-gcc and qemu-system-arm, not found on PATH" in lines[0]
    assert sorted(p.name for p in tmp_path.iterdir()) == ["empty"]


def _export_over_an_input(tmp: Path, where: str) -> tuple[list[str], list[Path]]:
    """``export --force`` into a folder that holds one of its inputs: the argv and the inputs."""
    run = tmp / "run"
    run.mkdir()
    model = run / "model.zip"
    model.write_bytes(TD3.read_bytes())
    if where == "the model's folder":
        return ["export", str(model), "--out", str(run), "--force"], [model]
    if where == "a folder above the model":
        return ["export", str(model), "--out", str(tmp), "--force"], [model]
    stats = tmp / "given" / ("stats.npz" if where == "--vecnormalize" else "names.json")
    stats.parent.mkdir()
    stats.write_text("{}")
    option = "--vecnormalize" if where == "--vecnormalize" else "--names"
    return ["export", str(model), option, str(stats), "--out", str(stats.parent), "--force"], [model, stats]


@pytest.mark.parametrize(
    "where", ["the model's folder", "a folder above the model", "--vecnormalize", "--names"]
)
def test_export_force_refuses_a_folder_that_holds_an_input(where: str, tmp_path: Path) -> None:
    argv, inputs = _export_over_an_input(tmp_path, where)
    before = {path: path.read_bytes() for path in inputs}
    assert_refused(argv, "holds the input", tmp_path)
    assert {path: path.read_bytes() for path in inputs} == before  # nothing deleted


def run_and_interrupt(
    argv: list[str],
    tmp: Path,
    wait_for: str,
    sig: signal.Signals,
    again_after_s: float | None = None,
    settle_s: float = 0.0,
) -> subprocess.CompletedProcess[str]:
    """Start ``embedrl ARGV``, send ``sig`` ``settle_s`` after its output shows ``wait_for`` (and once
    more ``again_after_s`` later); the finished process, its ``seconds_to_exit`` after the first signal."""
    env = {**os.environ, "TMPDIR": str(tmp / "tmp"), "PYTHONUNBUFFERED": "1"}
    proc = subprocess.Popen(
        [sys.executable, "-m", "embedrl.cli", *argv],
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
        env=env,
    )
    assert proc.stdout is not None
    seen = []
    for line in proc.stdout:
        seen.append(line)
        if wait_for in line:
            break
    time.sleep(settle_s)
    proc.send_signal(sig)
    first = time.monotonic()
    if again_after_s is not None:
        time.sleep(again_after_s)
        if proc.poll() is None:
            proc.send_signal(sig)
    out, err = proc.communicate(timeout=120)
    done = subprocess.CompletedProcess(argv, proc.returncode, "".join(seen) + out, err)
    done.seconds_to_exit = time.monotonic() - first  # type: ignore[attr-defined]
    return done


@pytest.mark.parametrize("sig", [signal.SIGTERM, signal.SIGINT])
def test_an_interrupted_export_leaves_nothing_behind(sig: signal.Signals, tmp_path: Path) -> None:
    (tmp_path / "tmp").mkdir()
    out = tmp_path / "export"
    done = run_and_interrupt(
        ["export", str(TD3), "--out", str(out), "--episodes", "200"], tmp_path, "[4/5]", sig
    )
    assert done.returncode == 128 + sig and done.stderr.strip().splitlines()[-1] == "interrupted", done.stderr
    assert sorted(p.name for p in tmp_path.iterdir()) == ["tmp"]  # no export, no staging folder
    assert not [p for p in (tmp_path / "tmp").iterdir() if p.name.startswith("embedrl")]  # no build folder


def test_a_killed_export_s_folders_are_removed_by_the_next_export(tmp_path: Path) -> None:
    # kill -9 runs no clean-up: the staging folder beside the output and the build folder in TMPDIR stay
    # until the next export, which removes them (and only them: a live export's build folder stays).
    (tmp_path / "tmp").mkdir()
    weights = np.random.default_rng(2).normal(scale=0.3, size=(2, 6)).astype(np.float32)
    model = tmp_path / "m.onnx"
    onnx.save(_gemm_model(numpy_helper.from_array(weights, "W"), 6, 2), model)
    argv = ["export", str(model), "--out", str(tmp_path / "export"), "--episodes", "0"]
    done = run_and_interrupt(argv, tmp_path, "[4/5]", signal.SIGKILL)
    assert done.returncode == -signal.SIGKILL
    staging = [p.name for p in tmp_path.iterdir() if p.name.startswith(".export.partial-")]
    built = [p.name for p in (tmp_path / "tmp").iterdir() if p.name.startswith("embedrl-build-")]
    assert len(staging) == 1 and len(built) == 1
    with owned_temporary_folder("embedrl-build-", tmp_path / "tmp") as live:
        result, _, _ = run_measured(argv, {**os.environ, "TMPDIR": str(tmp_path / "tmp")})
        assert result.returncode == 0, result.stderr[-2000:]
        assert [p.name for p in (tmp_path / "tmp").iterdir() if p.name.startswith("embedrl")] == [live.name]
    assert sorted(p.name for p in tmp_path.iterdir()) == ["export", "m.onnx", "tmp"]


def test_an_onnx_with_a_fixed_batch_of_one_exports_and_verifies(tmp_path: Path) -> None:
    # Common in files from elsewhere; onnxruntime then takes one observation per call.
    weights = np.random.default_rng(1).normal(scale=0.3, size=(2, 6)).astype(np.float32)
    path = tmp_path / "batch1.onnx"
    onnx.save(_gemm_model(numpy_helper.from_array(weights, "W"), 6, 2, batch=1), path)
    out = tmp_path / "export"
    result = subprocess.run(
        [sys.executable, "-m", "embedrl.cli", "export", str(path), "--out", str(out), "--episodes", "0"],
        capture_output=True,
        text=True,
        timeout=300,
    )
    assert result.returncode == 0, result.stderr[-2000:]
    report = json.loads((out / "export_report.json").read_text())
    assert report["verification"]["c_vs_onnxruntime_max_abs_error"] <= 1e-5


def test_the_walker_has_no_reward_field(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    out = tmp_path / "field.png"
    assert main(["reward-field", "--scenario", "walker", "--out", str(out)]) == 2
    err = capsys.readouterr().err
    assert err.startswith("error: the walker has no map") and err.count("\n") == 1
    assert not out.exists()


def test_a_network_too_big_for_a_microcontroller_is_refused_before_the_run_folder(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    run = tmp_path / "run"
    argv = ["train", "--scenario", "walker", "--set", "net_arch=100000,100000", "--out", str(run)]
    assert main(argv) == 2
    err = capsys.readouterr().err
    assert "at most 8 layers of at most 4096 units" in err and err.count("\n") == 1
    assert not run.exists()
