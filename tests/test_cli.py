"""The ``embedrl`` command: eval report format, pictures, bad input, benchmark output."""

from __future__ import annotations

import argparse
import json
import os
import re
import stat
import subprocess
import sys
from collections.abc import Iterator
from pathlib import Path

import onnx
import pytest
from PIL import Image

from embedrl.cli import build_parser, main
from embedrl.export.target import TARGETS
from embedrl.train.evaluate import REPORT_KEYS
from embedrl.train.rendering import STRIP_FRAMES
from tests.export.helpers import mlp_model
from tests.source_tree import REPO

PNG_MAGIC = b"\x89PNG\r\n\x1a\n"


def _eval(tmp_path: Path, name: str, *extra: str) -> dict[str, object]:
    out = tmp_path / name
    assert (
        main(
            [
                "eval",
                "--controller",
                "potential-field",
                "--episodes",
                "6",
                "--seed",
                "3",
                "--json",
                str(out),
                *extra,
            ]
        )
        == 0
    )
    data: dict[str, object] = json.loads(out.read_text())
    return data


def test_eval_json_has_the_documented_keys_and_consistent_numbers(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    plot = tmp_path / "plots" / "trajectories.png"
    data = _eval(tmp_path, "eval.json", "--plot", str(plot))
    assert set(REPORT_KEYS) <= set(data)
    assert list(data)[: len(REPORT_KEYS)] == list(REPORT_KEYS)
    episodes = data["per_episode"]
    assert isinstance(episodes, list) and len(episodes) == data["episodes"] == 6
    assert [e["seed"] for e in episodes] == [3, 4, 5, 6, 7, 8]
    outcomes = [e["outcome"] for e in episodes]
    assert data["successes"] == outcomes.count("success")
    assert data["collisions"] == outcomes.count("collision")
    assert data["timeouts"] == outcomes.count("timeout")
    assert data["success_rate"] == pytest.approx(outcomes.count("success") / 6)
    assert data["mean_return"] == pytest.approx(sum(e["episode_return"] for e in episodes) / 6)
    wins = [e["time_s"] for e in episodes if e["outcome"] == "success"]
    assert data["mean_time_s"] == pytest.approx(sum(wins) / len(wins))
    assert all(e["time_s"] == pytest.approx(0.3 * e["steps"]) for e in episodes)
    assert data["provenance"]["versions"]["pymunk"] == "7.3.1"  # type: ignore[index]
    assert plot.read_bytes().startswith(PNG_MAGIC)
    printed = capsys.readouterr().out
    assert "success rate" in printed and f"{data['successes']} / " in printed


def test_eval_is_reproducible(tmp_path: Path) -> None:
    a = _eval(tmp_path, "a.json")
    b = _eval(tmp_path, "b.json")
    a.pop("provenance")
    b.pop("provenance")
    assert a == b


def test_eval_of_a_missing_model_is_a_clear_error_and_writes_nothing(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    out = tmp_path / "eval.json"
    assert main(["eval", str(tmp_path / "agent.zip"), "--json", str(out)]) == 2
    err = capsys.readouterr().err
    assert err.startswith("error: ") and "agent.zip: no such file" in err
    assert "Traceback" not in err
    assert list(tmp_path.iterdir()) == []


def test_eval_needs_exactly_one_policy(capsys: pytest.CaptureFixture[str]) -> None:
    with pytest.raises(SystemExit) as exc:
        main(["eval", "--episodes", "3"])
    assert exc.value.code == 2
    with pytest.raises(SystemExit):
        main(["eval", "--controller", "potential-field", "--episodes", "0"])
    assert "must be at least 1" in capsys.readouterr().err


def test_unwritable_report_is_an_error_and_leaves_nothing_behind(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    target = tmp_path / "report.json"
    target.mkdir()  # a directory where the file should go
    code = main(["eval", "--controller", "potential-field", "--episodes", "2", "--json", str(target)])
    assert code == 2
    assert "error:" in capsys.readouterr().err
    assert sorted(p.name for p in tmp_path.iterdir()) == ["report.json"]
    assert target.is_dir() and list(target.iterdir()) == []


def test_render_gif_has_one_frame_per_step(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    out = tmp_path / "episode.gif"
    assert main(["render", "--controller", "potential-field", "--seed", "0", "--out", str(out)]) == 0
    steps = int(capsys.readouterr().out.split(": ")[1].split()[0])
    with Image.open(out) as gif:
        assert gif.format == "GIF"
        assert getattr(gif, "n_frames", 1) == steps + 1


def test_render_png_strip(tmp_path: Path) -> None:
    out = tmp_path / "episode.png"
    assert main(["render", "--controller", "potential-field", "--seed", "0", "--out", str(out)]) == 0
    with Image.open(out) as strip:
        assert strip.format == "PNG"
        width, height = strip.size
    assert width == STRIP_FRAMES * 608 and height == 304


def test_render_rejects_other_formats_before_running(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    out = tmp_path / "episode.mp4"
    assert main(["render", "--controller", "potential-field", "--out", str(out)]) == 2
    assert "use a .gif" in capsys.readouterr().err
    assert list(tmp_path.iterdir()) == []


def test_bench_env_reports_steps_per_second_and_ratios(tmp_path: Path) -> None:
    out = tmp_path / "bench.json"
    assert main(["bench-env", "--steps", "300", "--json", str(out)]) == 0
    data = json.loads(out.read_text())
    assert data["steps"] == 300 and data["steps_per_second"] > 0
    assert data["ratio_to_target"] == pytest.approx(data["steps_per_second"] / 10_000, abs=0.01)
    assert data["reference_env_id"] == "Pendulum-v1"
    assert data["ratio_to_reference"] == pytest.approx(
        data["steps_per_second"] / data["reference_steps_per_second"], rel=0.01
    )


def test_console_script_is_installed() -> None:
    exe = Path(sys.executable).parent / "embedrl"
    result = subprocess.run([str(exe), "--help"], capture_output=True, text=True, check=True)
    for command in ("eval", "render", "bench-env"):
        assert command in result.stdout


@pytest.mark.parametrize(
    ("argv", "said"),
    [
        (
            ["eval", "--ep", "3"],
            "embedrl eval: error: unrecognized arguments: --ep (see embedrl eval --help)",
        ),
        (["eval", "--contr", "potential-field"], "unrecognized arguments: --contr"),
        (["hil", "run", "--export-dir", "x", "--bogus"], "(see embedrl hil run --help)"),
    ],
)
def test_options_are_whole_words_and_errors_name_the_subcommands_help(
    argv: list[str], said: str, capsys: pytest.CaptureFixture[str]
) -> None:
    with pytest.raises(SystemExit) as stop:
        main(argv)
    assert stop.value.code == 2
    err = capsys.readouterr().err.strip()
    assert said in err and len(err.splitlines()) == 1


def test_help_states_the_defaults_and_the_pipeline(capsys: pytest.CaptureFixture[str]) -> None:
    with pytest.raises(SystemExit):
        main(["eval", "--help"])
    text = capsys.readouterr().out
    assert "(default: 200)" in text and "seed + i (default: 0)" in text
    with pytest.raises(SystemExit):
        main(["--help"])
    text = capsys.readouterr().out
    assert text.count("embedrl ") > 5 and "registered" not in text  # a user's page, not the developer's


@pytest.mark.parametrize(
    "argv",
    [["hil", "run", "--export-dir"], ["verify-chain"], ["report", "--out", "r.html"]],
)
def test_a_missing_folder_is_named_as_missing(
    argv: list[str], tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    missing = tmp_path / "no such export"
    where = argv.index("--export-dir") + 1 if "--export-dir" in argv else 1
    assert main([*argv[:where], str(missing), *argv[where:]]) == 2
    assert (
        capsys.readouterr()
        .err.strip()
        .endswith(("no such folder", "no such folder (give an `embedrl export` folder)"))
    )


def test_python_dash_m_runs_the_command() -> None:
    result = subprocess.run([sys.executable, "-m", "embedrl", "--version"], capture_output=True, text=True)
    assert result.returncode == 0 and result.stdout.startswith("embedrl ")


@pytest.mark.training
@pytest.mark.parametrize("terminal", [True, False])
def test_progress_bars_only_on_a_terminal(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], monkeypatch: pytest.MonkeyPatch, terminal: bool
) -> None:
    monkeypatch.setattr("sys.stderr.isatty", lambda: terminal)
    argv = ["eval", "--controller", "potential-field", "--episodes", "2", "--json", str(tmp_path / "e.json")]
    assert main(argv) == 0
    argv = ["train", "--algo", "td3", "--max-steps", "200", "--out", str(tmp_path / "run")]
    assert main(argv) == 0
    err = capsys.readouterr().err
    assert ("eval potential-field: 100%" in err) == terminal and ("train: 100%" in err) == terminal


def _commands(
    parser: argparse.ArgumentParser, name: str = "embedrl"
) -> Iterator[tuple[str, argparse.ArgumentParser]]:
    """Every (sub)command's parser, ``embedrl hil run`` included, with its name."""
    yield name, parser
    for action in parser._actions:
        if isinstance(action, argparse._SubParsersAction):
            for word, sub in action.choices.items():
                yield from _commands(sub, f"{name} {word}")


def _options(parser: argparse.ArgumentParser) -> list[argparse.Action]:
    skip = (argparse._HelpAction, argparse._VersionAction, argparse._SubParsersAction)
    return [a for a in parser._actions if not isinstance(a, skip)]


def test_every_option_has_help_lists_its_choices_and_states_defaults_one_way() -> None:
    commands = dict(_commands(build_parser()))
    assert {"embedrl report", "embedrl hil run", "embedrl tune", "embedrl bench-target"} <= set(commands)
    for name, parser in commands.items():
        for action in _options(parser):
            option = f"{name} {'/'.join(action.option_strings) or action.dest}"
            assert action.help, f"{option} has no help"
            formatter = parser.formatter_class(prog=parser.prog)
            formatter.add_argument(action)
            shown = formatter.format_help()
            missing = [c for c in action.choices or () if str(c) not in shown]
            assert not missing, f"{option}: its help does not list {missing}"
        # one way to state a default: "(default: X)", whether the formatter or the help wrote it
        other = re.sub(r"\(default:\s", "", parser.format_help())
        assert "default" not in other.lower(), f"{name}: a default not written as (default: X)"


def test_every_target_option_offers_the_same_targets() -> None:
    targets = [
        (name, action.choices)
        for name, parser in _commands(build_parser())
        for action in _options(parser)
        if "--target" in action.option_strings
    ]
    assert {name for name, _ in targets} == {"embedrl export", "embedrl bench-target", "embedrl hil run"}
    assert all(tuple(choices or ()) == tuple(TARGETS) for _, choices in targets)


EXPORT_READERS = [
    ["report", "--out", "r.html"],
    ["verify-chain"],
    ["bench-export"],
    ["bench-target"],
    ["hil", "run"],
    ["hil", "bench"],
]
"""Every command that reads an export folder (and an option it needs besides)."""


@pytest.mark.parametrize("command", EXPORT_READERS, ids=lambda c: " ".join(c[: 2 if c[0] == "hil" else 1]))
def test_every_command_takes_the_export_folder_both_ways(
    command: list[str], capsys: pytest.CaptureFixture[str]
) -> None:
    parser = build_parser()
    words = 2 if command[0] == "hil" else 1
    head, rest = command[:words], command[words:]
    given = parser.parse_args([*head, "out/td3", *rest]).export_dir
    assert given == parser.parse_args([*head, *rest, "--export-dir", "out/td3"]).export_dir == Path("out/td3")
    for argv in ([*head, "a", "--export-dir", "b", *rest], [*head, "--export-dir", "b", *rest, "a"]):
        with pytest.raises(SystemExit) as stop:
            parser.parse_args(argv)
        assert stop.value.code == 2
        err = capsys.readouterr().err.strip()
        assert len(err.splitlines()) == 1 and "the export folder is given twice" in err
    if command[0] == "bench-export":  # without one it times the study's actor
        assert parser.parse_args(head).export_dir is None
        return
    with pytest.raises(SystemExit) as stop:
        parser.parse_args([*head, *rest])
    assert stop.value.code == 2
    err = capsys.readouterr().err.strip()
    assert err == (
        f"embedrl {' '.join(head)}: error: the export folder is missing: give EXPORT_DIR or --export-dir "
        f"EXPORT_DIR (see embedrl {' '.join(head)} --help)"
    )


def test_export_writes_the_folder_it_is_given_either_way() -> None:
    parser = build_parser()
    for option in ("--out", "--export-dir"):
        assert parser.parse_args(["export", "m.zip", option, "out/td3"]).out == Path("out/td3")


def test_make_help_lists_every_target_in_one_line() -> None:
    makefile = REPO / "Makefile"
    phony = re.search(r"^\.PHONY:(.*)$", makefile.read_text(), re.MULTILINE)
    assert phony is not None
    result = subprocess.run(["make", "-s", "-f", str(makefile), "help"], capture_output=True, text=True)
    assert result.returncode == 0, result.stderr
    listed = {line.split()[0]: line for line in result.stdout.splitlines()}
    assert set(listed) == set(phony.group(1).split())
    assert all(len(line.split()) > 2 for line in listed.values())  # a target and what it does


@pytest.mark.parametrize("umask", [0o022, 0o027])
def test_an_export_folder_is_created_with_the_users_umask(tmp_path: Path, umask: int) -> None:
    """The export is written into a private temporary folder (mkdtemp: 0700) and renamed into place: it must
    still have the mode a plain mkdir would give it, so that the group and CI users can read it."""
    model = tmp_path / "mlp.onnx"
    onnx.save(mlp_model([6, 8, 2]), model)
    out = tmp_path / "export"
    argv = [sys.executable, "-m", "embedrl.cli", "export", str(model), "--out", str(out), "--episodes", "0"]
    result = subprocess.run(
        argv, capture_output=True, text=True, timeout=300, preexec_fn=lambda: os.umask(umask)
    )
    assert result.returncode == 0, result.stderr[-2000:]
    folders = [out, *(p for p in out.rglob("*") if p.is_dir())]
    files = [p for p in out.rglob("*") if p.is_file()]
    assert len(files) > 5
    assert {oct(stat.S_IMODE(p.stat().st_mode)) for p in folders} == {oct(0o777 & ~umask)}
    assert {oct(stat.S_IMODE(p.stat().st_mode) & 0o666) for p in files} == {oct(0o666 & ~umask)}


def test_quantize_names_the_full_integer_scheme_and_takes_its_former_name(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """``--quantize int8`` is full-integer, ``int8-weights`` the weight-only scheme; ``int8-full`` still
    parses, as int8, with a one-line note; anything else is a one-line usage error."""
    from embedrl.export.cli import QUANTIZE_METAVAR
    from embedrl.export.quantize import SCHEMES, WEIGHTS_ONLY

    assert "{" + ",".join(SCHEMES) + "}" == QUANTIZE_METAVAR and WEIGHTS_ONLY in SCHEMES
    parser = build_parser()
    source, out = str(tmp_path / "agent.zip"), ["--out", str(tmp_path / "out")]
    assert parser.parse_args(["export", source, *out, "--quantize", "int8"]).quantize == "int8"
    assert (
        parser.parse_args(["export", source, *out, "--quantize", "int8-weights"]).quantize == "int8-weights"
    )
    assert capsys.readouterr().err == ""
    assert parser.parse_args(["export", source, *out, "--quantize", "int8-full"]).quantize == "int8"
    assert capsys.readouterr().err == "note: --quantize int8-full is now --quantize int8\n"
    with pytest.raises(SystemExit) as stop:
        main(["export", source, *out, "--quantize", "int4"])
    assert stop.value.code == 2
    err = capsys.readouterr().err.strip()
    assert (
        "invalid choice: 'int4' (choose from int8, int8-weights, q15)" in err and len(err.splitlines()) == 1
    )
