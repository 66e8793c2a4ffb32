"""The README runs as written: every command of its ``sh`` blocks, in order, shortened only by options the
commands document (fewer steps, episodes and seeds; :data:`SHORTER`).

``embedrl`` and ``make -C runtime_c`` commands run in a temporary copy of the checkout's ``policies/`` and
``runtime_c/`` (their outputs go to its ``out/``). The top-level ``make`` targets run in the checkout with
``OUT`` in a temporary folder, except those that are this suite, rewrite files or run beside it in CI:
``make test`` and ``make test-fast`` (the suite itself), ``make demo``, ``make lint`` and ``make type`` (run
by CI, ``.ci/run``, as written), ``make format`` and ``pytest --regen-golden`` (they rewrite the sources;
``make lint`` checks the same).
"""

from __future__ import annotations

import os
import re
import shutil
import subprocess
import sys
from collections.abc import Callable
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
README = ROOT / "README.md"
NOT_RUN = {
    "make demo": "run by CI (.ci/run)",
    "make lint": "run by CI (.ci/run) before make test",
    "make type": "run by CI (.ci/run) before make test",
    "make test": "the suite itself",
    "make test-fast": "the suite itself",
    "make format": "rewrites the sources (make lint checks the same)",
    "pytest --regen-golden": "rewrites the golden files on purpose",
}


def _scaled_steps(match: re.Match[str]) -> str:
    return f"--max-steps {max(int(match.group(1)) * 3 // 1000, 100)}"


SHORTER: list[tuple[re.Pattern[str], str | Callable[[re.Match[str]], str]]] = [
    (re.compile(r"--max-steps (\d+)"), _scaled_steps),  # 100,000 -> 300: a resumed run keeps its order
    (re.compile(r"--episodes \d+"), "--episodes 2"),
    (re.compile(r"--seeds \d+"), "--seeds 1"),
    (re.compile(r"--steps \d+"), "--steps 500"),
    (re.compile(r"--trials \d+"), "--trials 2"),
]
"""How a README command is shortened: documented options only."""


def readme_commands() -> list[str]:
    """Every command of the README's ``sh`` blocks: continuation lines joined, comments dropped."""
    commands, in_block, pending = [], False, ""
    for line in README.read_text().splitlines():
        if line.startswith("```"):
            in_block = line == "```sh"
            continue
        if not in_block:
            continue
        text = pending + re.sub(r"\s+#.*$", "", line).strip()
        if text.endswith("\\"):
            pending = text[:-1].rstrip() + " "
            continue
        pending = ""
        if text:
            commands.append(text)
    return commands


def shortened(command: str) -> str:
    for pattern, replacement in SHORTER:
        command = pattern.sub(replacement, command)
    words = command.split()
    if words[:2] in (["embedrl", "bench"], ["embedrl", "shaping"]) and "--eval-episodes" not in words:
        command += " --eval-episodes 5"
    if words[:2] == ["embedrl", "export"] and "--episodes" not in words:
        command += " --episodes 2"
    return command


def test_the_readme_commands_are_found() -> None:
    commands = readme_commands()
    assert "make demo" in commands and "make test" in commands
    assert any(c.startswith("embedrl hil run --export-dir out/td3 ") for c in commands)
    assert all("\\" not in c for c in commands)


@pytest.mark.slow
def test_every_readme_command_runs_as_written(tmp_path: Path) -> None:
    work = tmp_path / "checkout"  # make cannot take a path with spaces (embedrl can)
    work.mkdir()
    (work / "policies").symlink_to(ROOT / "policies", target_is_directory=True)
    shutil.copytree(ROOT / "runtime_c", work / "runtime_c", ignore=shutil.ignore_patterns("build"))
    bin_dir = Path(sys.executable).parent
    env = {**os.environ, "PATH": f"{bin_dir}{os.pathsep}{os.environ['PATH']}"}  # as after activating .venv
    ran = []
    for command in readme_commands():
        if command in NOT_RUN:
            continue
        run = shortened(command)
        top_level_make = run.startswith("make ") and not run.startswith("make -C ")
        cwd = ROOT if top_level_make else work
        if top_level_make:
            run += f" OUT={tmp_path / 'make-out'}"
        result = subprocess.run(
            ["bash", "-c", run], cwd=cwd, env=env, capture_output=True, text=True, timeout=1800
        )
        assert result.returncode == 0, f"`{run}` failed:\n{(result.stdout + result.stderr)[-3000:]}"
        assert "Traceback" not in result.stderr, run
        ran.append(command)
    assert len(ran) == sum(c not in NOT_RUN for c in readme_commands()) > 25
    assert (work / "out" / "td3-hil" / "hil.json").is_file() and (
        work / "out" / "td3-m4" / "policy.onnx"
    ).is_file()
