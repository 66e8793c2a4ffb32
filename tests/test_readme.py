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

import itertools
import os
import re
import shutil
import subprocess
import sys
import time
from collections.abc import Callable
from concurrent.futures import ThreadPoolExecutor
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
MAKE_SHORTER = "BENCH_ENV_STEPS=500 BENCH_HIL_EPISODES=2 BENCH_HIL_EXCHANGES=200 EXAMPLE_EPISODES=2"
"""How a top-level ``make`` target is shortened: the Makefile's variables for ``make bench``'s lengths and the
example's closed-loop episodes."""


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


OUTPUT_PATH = re.compile(r"(?<![\w./-])out/[^\s'\"]+")
"""A path under a command's ``out/`` folder, as written in the README."""


def _is_top_level_make(command: str) -> bool:
    return command.startswith("make ") and not command.startswith("make -C ")


def _shares_a_folder(a: str, b: str) -> bool:
    """Whether two commands can meet in a file: one names a path the other's path lies in or under, both
    build in ``runtime_c/`` (``make -C runtime_c``), or both are top-level ``make`` targets (one ``OUT``)."""
    if _is_top_level_make(a) and _is_top_level_make(b):
        return True
    if a.startswith("make -C runtime_c") and b.startswith("make -C runtime_c"):
        return True
    parts_a = [Path(m).parts for m in OUTPUT_PATH.findall(a)]
    parts_b = [Path(m).parts for m in OUTPUT_PATH.findall(b)]
    return any(x[: len(y)] == y or y[: len(x)] == x for x in parts_a for y in parts_b)


def chains(commands: list[str]) -> list[list[str]]:
    """The commands in chains that share no file: each chain in the README's order, the chains ordered by
    their first command. Commands in one chain run in order; different chains may run side by side."""
    owner = list(range(len(commands)))

    def root(i: int) -> int:
        while owner[i] != i:
            owner[i] = owner[owner[i]]
            i = owner[i]
        return i

    for i, j in itertools.combinations(range(len(commands)), 2):
        if _shares_a_folder(commands[i], commands[j]):
            owner[root(j)] = root(i)
    grouped: dict[int, list[str]] = {}
    for i, command in enumerate(commands):
        grouped.setdefault(root(i), []).append(command)
    return [grouped[k] for k in sorted(grouped)]


def test_commands_that_share_a_folder_are_in_one_chain() -> None:
    found = chains(
        [
            "embedrl export p.zip --out out/td3",
            "embedrl train --out out/runs/a",
            "make -C runtime_c POLICY_DIR=out/td3/c",
            "embedrl eval out/runs/a/model.zip --json out/runs/a-eval.json",
            "make -C runtime_c test",
            "embedrl hil doctor",
            "make bench",
            "make deps",
        ]
    )
    assert found == [
        [
            "embedrl export p.zip --out out/td3",
            "make -C runtime_c POLICY_DIR=out/td3/c",
            "make -C runtime_c test",
        ],
        ["embedrl train --out out/runs/a", "embedrl eval out/runs/a/model.zip --json out/runs/a-eval.json"],
        ["embedrl hil doctor"],
        ["make bench", "make deps"],
    ]
    readme = [c for c in readme_commands() if c not in NOT_RUN]
    assert sorted(c for chain in chains(readme) for c in chain) == sorted(readme)
    assert len(chains(readme)) > 3


class _Checkout:
    """The README's commands run against a copy of the checkout's ``policies/`` and ``runtime_c/``."""

    def __init__(self, tmp_path: Path) -> None:
        self.tmp_path = tmp_path
        self.work = tmp_path / "checkout"  # make cannot take a path with spaces (embedrl can)
        self.work.mkdir()
        (self.work / "policies").symlink_to(ROOT / "policies", target_is_directory=True)
        shutil.copytree(ROOT / "runtime_c", self.work / "runtime_c", ignore=shutil.ignore_patterns("build"))
        bin_dir = Path(sys.executable).parent
        self.env = {
            **os.environ,
            "PATH": f"{bin_dir}{os.pathsep}{os.environ['PATH']}",
        }  # as after activating .venv

    def run(self, chain: list[str]) -> tuple[list[str], str | None]:
        """The chain's commands in order until one fails: those that ran, and the failure (or None)."""
        ran: list[str] = []
        for command in chain:
            run = shortened(command)
            top_level_make = _is_top_level_make(run)
            if top_level_make:
                run += f" OUT={self.tmp_path / 'make-out'} {MAKE_SHORTER}"
            started = time.monotonic()
            result = subprocess.run(
                ["bash", "-c", run],
                cwd=ROOT if top_level_make else self.work,
                env=self.env,
                capture_output=True,
                text=True,
                timeout=1800,
            )
            print(f"{time.monotonic() - started:6.1f} s  {run}")
            if result.returncode != 0 or "Traceback" in result.stderr:
                return (
                    ran,
                    f"`{run}` failed ({result.returncode}):\n{(result.stdout + result.stderr)[-3000:]}",
                )
            ran.append(command)
        return ran, None


CHAINS_AT_ONCE = 2
"""The README's independent chains run this many at a time (the machines here have two cores)."""


@pytest.mark.slow
def test_every_readme_command_runs_as_written(tmp_path: Path) -> None:
    checkout = _Checkout(tmp_path)
    todo = chains([c for c in readme_commands() if c not in NOT_RUN])
    with ThreadPoolExecutor(CHAINS_AT_ONCE) as pool:
        results = list(pool.map(checkout.run, sorted(todo, key=len, reverse=True)))
    failures = [failure for _, failure in results if failure]
    assert not failures, "\n\n".join(failures)
    ran = [c for done, _ in results for c in done]
    assert len(ran) == sum(c not in NOT_RUN for c in readme_commands()) > 25
    work = checkout.work
    assert (work / "out" / "td3-hil" / "hil.json").is_file() and (
        work / "out" / "td3-m4" / "policy.onnx"
    ).is_file()
