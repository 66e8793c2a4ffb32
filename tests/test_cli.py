"""The ``embedrl`` command: eval report format, pictures, bad input, benchmark output."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import pytest
from PIL import Image

from embedrl.cli import main
from embedrl.train.evaluate import REPORT_KEYS
from embedrl.train.rendering import STRIP_FRAMES

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
