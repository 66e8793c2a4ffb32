"""Cortex-M targets: firmware for M4 and M3 built, run on QEMU, checked against onnxruntime, measured.

These tests need Debian's gcc-arm-none-eabi, libnewlib-arm-none-eabi and qemu-system-arm
(``make deps``; CI installs them). Without them they fail with the install hint, never skip.
"""

from __future__ import annotations

import json
import re
import subprocess
from dataclasses import replace
from pathlib import Path
from typing import Any

import numpy as np
import onnx
import pytest

from embedrl.cli import main
from embedrl.export import build, target
from embedrl.export.build import RUNTIME_C
from embedrl.export.errors import BuildError
from tests.conftest import marks_its_users
from tests.export.helpers import mlp_model

pytestmark = pytest.mark.slow


def _export(tmp_path: Path, widths: list[int], *extra: str) -> tuple[int, Path]:
    src = tmp_path / "mlp.onnx"
    onnx.save(mlp_model(widths), str(src))
    out = tmp_path / "export"
    return main(["export", str(src), "--out", str(out), "--episodes", "0", *extra]), out


@pytest.fixture(scope="module")
@marks_its_users("qemu")
def study_export(tmp_path_factory: pytest.TempPathFactory) -> dict[str, Any]:
    code, out = _export(
        tmp_path_factory.mktemp("study"), [6, 100, 100, 2], "--target", "cortex-m4", "--target", "cortex-m3"
    )
    assert code == 0
    report: dict[str, Any] = json.loads((out / "export_report.json").read_text())
    return report


@pytest.mark.parametrize(
    ("target", "machine"), [("cortex-m4", "netduinoplus2"), ("cortex-m3", "stm32vldiscovery")]
)
def test_firmware_matches_onnxruntime_on_qemu(
    study_export: dict[str, Any], target: str, machine: str
) -> None:
    t = study_export["targets"][target]
    assert t["qemu_machine"] == machine
    assert t["samples"] == 256
    assert t["max_abs_error"] <= 1e-5
    assert t["quantize"] is None


def test_size_report_is_within_the_bounds_for_the_study_actor(study_export: dict[str, Any]) -> None:
    m4, m3 = study_export["targets"]["cortex-m4"], study_export["targets"]["cortex-m3"]
    weights = (6 * 100 + 100 + 100 * 100 + 100 + 100 * 2 + 2) * 4
    for t, flash_limit in ((m4, 48 * 1024), (m3, 64 * 1024)):
        assert weights < t["flash_bytes"] <= flash_limit
        assert 800 < t["ram_bytes"] <= 1024  # two 100-float buffers plus the measured stack
        assert 0 < t["stack_bytes"] < 512
        assert t["image_flash_bytes"] > t["flash_bytes"]
    # Software floating point costs the M3 flash, not accuracy, and its helper calls cost stack: the
    # painted-stack measurement sees them (it is a measurement, not a constant).
    assert m3["flash_bytes"] > m4["flash_bytes"]
    assert m3["stack_bytes"] > m4["stack_bytes"]


def test_time_on_the_target_is_counted_and_the_cycles_follow_the_traced_mix(
    study_export: dict[str, Any],
) -> None:
    macs = 6 * 100 + 100 * 100 + 100 * 2
    m4, m3 = study_export["targets"]["cortex-m4"], study_export["targets"]["cortex-m3"]
    for t in (m4, m3):
        # counted under -icount over 256 inferences: about 4 instructions per multiply-add on the M4F
        assert 2 * macs < t["instructions_per_inference"]
        model = t["cycle_model"]
        assert sum(model["instruction_classes"].values()) == model["traced_instructions"]
        # the traced inference (the size probe's, on zeros) runs about what the counted ones run (software
        # floating point takes shortcuts on zeros: the M3's differ by about 5%)
        assert (
            abs(model["traced_instructions"] - t["instructions_per_inference"])
            < 0.1 * t["instructions_per_inference"]
        )
        assert t["estimated_cycles_per_inference"] == round(
            t["instructions_per_inference"] * model["cycles_per_instruction"]
        )
        assert 1.0 <= model["cycles_per_instruction"] < 3.0
        assert t["estimated_inference_us"] == pytest.approx(
            t["estimated_cycles_per_inference"] / t["clock"]["hz"] * 1e6, rel=1e-3
        )
    assert m4["instructions_per_inference"] < 6 * macs  # an FPU: a few instructions per multiply-add
    assert m3["instructions_per_inference"] > 5 * m4["instructions_per_inference"]  # software floating point
    assert m4["cycle_model"]["instruction_classes"].get("fp_alu", 0) > macs  # FP instructions did the work
    assert "fp_alu" not in m3["cycle_model"]["instruction_classes"]


_REFUSED = re.compile(
    r"^error: cortex-m3: the policy does not fit the STM32F100RB: "
    r"(FLASH|RAM) (\d+) bytes needed, (\d+) available"
)


@pytest.mark.parametrize(
    ("widths", "region", "available"),
    [
        ([6, 300, 300, 2], "FLASH", 128 * 1024),  # float weights of 370 KB
        ([6, 1500, 2], "RAM", 8 * 1024),  # 48 KB of weights fit the flash; a 6 KB activation buffer and the
        # reserved stack and heap do not fit the RAM
    ],
)
def test_a_policy_too_large_for_the_part_is_refused_in_one_line(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], widths: list[int], region: str, available: int
) -> None:
    """At export time (``--target``): one line naming what the image needs against what the STM32F100 has,
    exit 2, nothing written."""
    code, out = _export(tmp_path, widths, "--target", "cortex-m3")
    assert code == 2
    err = capsys.readouterr().err
    assert len(err.strip().splitlines()) == 1, err
    refused = _REFUSED.match(err.strip())
    assert refused and refused.group(1) == region and int(refused.group(3)) == available, err
    assert int(refused.group(2)) > available
    assert not out.exists()


def test_make_refuses_a_policy_too_large_for_the_part_in_one_line(tmp_path: Path) -> None:
    """At make time, the same refusal from the link (cortex_m/fit.sh): one line of its own naming the part and
    the image, before make's summary of the failed recipe, and make's exit status 2; the firmware node (what
    ``hil run --node firmware`` builds) is refused in that one line too."""
    code, out = _export(tmp_path, [6, 1500, 2])
    assert code == 0
    result = subprocess.run(
        ["make", "-s", "-C", str(RUNTIME_C), "TARGET=cortex-m3", f"POLICY_DIR={out / 'c'}",
         f"BUILD_DIR={tmp_path / 'b'}"],
        capture_output=True, text=True,
    )  # fmt: skip
    assert result.returncode == 2
    ours = [line for line in result.stderr.splitlines() if not line.startswith("make")]
    assert len(ours) == 1, result.stderr
    part = re.escape("cortex-m3 (Cortex-M3 without FPU, STM32F100RB)")
    assert re.fullmatch(
        part + r": firmware\.elf does not fit the part's memory: RAM (\d+) bytes needed, 8192 available",
        ours[0],
    ), ours
    assert "collect2" not in result.stderr
    with pytest.raises(BuildError) as refused:
        build.make("node", out / "c", tmp_path / "node", extra={"TARGET": "cortex-m3"})
    assert re.fullmatch(
        part + r": node\.elf does not fit the part's memory: RAM (\d+) bytes needed, 8192 available",
        str(refused.value),
    ), str(refused.value)


def test_firmware_builds_by_hand_from_an_export(tmp_path: Path) -> None:
    code, out = _export(tmp_path, [6, 8, 2])
    assert code == 0 and (out / "test" / "test_vectors.c").is_file()
    result = subprocess.run(
        [
            "make",
            "-C",
            str(RUNTIME_C),
            "TARGET=cortex-m4",
            f"POLICY_DIR={out / 'c'}",
            f"BUILD_DIR={tmp_path / 'b'}",
        ],
        capture_output=True,
        text=True,
    )
    assert result.returncode == 0, result.stderr
    run = subprocess.run(
        [
            "qemu-system-arm",
            "-M",
            "netduinoplus2",
            "-nographic",
            "-monitor",
            "none",
            "-semihosting",
            "-kernel",
            str(tmp_path / "b" / "cortex-m4" / "firmware.elf"),
        ],
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert run.returncode == 0 and "DONE 256" in run.stdout


def test_unknown_target_and_renamed_policy_are_rejected(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    code, _ = _export(tmp_path, [6, 8, 2], "--target", "cortex-m4", "--name", "drive")
    assert code == 2 and "use the default --name policy" in capsys.readouterr().err
    with pytest.raises(SystemExit):
        main(["export", "x.onnx", "--out", "o", "--target", "cortex-m0"])
    result = subprocess.run(
        ["make", "-C", str(RUNTIME_C), "TARGET=avr", "POLICY_DIR=/tmp"], capture_output=True, text=True
    )
    assert result.returncode != 0 and "unknown TARGET=avr" in result.stderr


def test_int8_weights_firmware_is_bit_exact_on_qemu_and_fits_14_kb(tmp_path: Path) -> None:
    code, out = _export(
        tmp_path,
        [6, 100, 100, 2],
        "--quantize",
        "int8-weights",
        "--target",
        "cortex-m4",
        "--target",
        "cortex-m3",
    )
    assert code == 0
    report = json.loads((out / "export_report.json").read_text())
    assert report["quantize"] == "int8-weights"
    assert report["verification"]["quantization"]["model_mismatches"] == 0
    for name in ("cortex-m4", "cortex-m3"):
        t = report["targets"][name]
        assert t["quantize"] == "int8-weights" and t["bit_exact_with_model"] is True
        assert t["ram_bytes"] <= 1024
    assert report["targets"]["cortex-m4"]["flash_bytes"] <= 14 * 1024
    assert "int8_t" in (out / "c" / "policy.c").read_text()


SHIPPED_TD3 = Path(__file__).resolve().parents[2] / "policies" / "static" / "td3.zip"
INT8_FLASH_TARGET = 14 * 1024
INT8_CYCLES_TARGET = 25_000
"""The project's int8 targets for the study actor on the Cortex-M4F: flash for its weights and code, and
estimated cycles per inference."""


def test_int8_study_actor_meets_the_flash_and_cycle_targets_on_the_m4f(tmp_path: Path) -> None:
    """The shipped TD3 actor in full-integer int8 on the STM32F405: bit-exact with the model, within 14 KB of
    flash and 25,000 estimated cycles, no weight padding (10,800 int8 weights: the first layer's two inputs
    beyond a word in tail words) and one shift per hidden layer (no shift table)."""
    out = tmp_path / "export"
    args = ["export", str(SHIPPED_TD3), "--out", str(out), "--episodes", "0", "--quantize", "int8"]
    assert main([*args, "--target", "cortex-m4"]) == 0
    m4 = json.loads((out / "export_report.json").read_text())["targets"]["cortex-m4"]
    assert m4["bit_exact_with_model"] is True
    assert m4["flash_bytes"] <= INT8_FLASH_TARGET
    assert m4["estimated_cycles_per_inference"] <= INT8_CYCLES_TARGET
    text = (out / "c" / "policy.c").read_text()
    assert "int32_t policy_w0[150]" in text  # 100 rows x (one word + half a tail word)
    assert "actor_mu_0 shifts */" not in text and "actor_mu_2 shifts */" not in text


def test_int8_folded_normalisation_is_bit_exact_on_the_m4f(tmp_path: Path) -> None:
    """The shipped PPO with its VecNormalize statistics in int8: the Sub, Div and Clip before the layers fold
    into the input quantisation (no float loop of theirs), and the M4F image prints the model's bits."""
    static = SHIPPED_TD3.parent
    out = tmp_path / "export"
    args = ["export", str(static / "ppo.zip"), "--vecnormalize", str(static / "ppo_vecnormalize.npz")]
    args += ["--out", str(out), "--episodes", "0", "--quantize", "int8", "--target", "cortex-m4"]
    assert main(args) == 0
    report = json.loads((out / "export_report.json").read_text())
    assert report["verification"]["quantization"]["model_mismatches"] == 0
    assert report["targets"]["cortex-m4"]["bit_exact_with_model"] is True
    text = (out / "c" / "policy.c").read_text()
    assert (
        "folded in: normalize_sub, normalize_div, normalize_clip" in text
        and "Sub 'normalize_sub'" not in text
    )


def test_q15_firmware_on_the_fpu_less_m3_is_bit_exact(tmp_path: Path) -> None:
    code, out = _export(tmp_path, [6, 100, 100, 2], "--quantize", "q15", "--target", "cortex-m3")
    assert code == 0
    report = json.loads((out / "export_report.json").read_text())
    t = report["targets"]["cortex-m3"]
    assert t["quantize"] == "q15" and t["bit_exact_with_model"] is True
    assert report["verification"]["quantization"]["worst_action_error_vs_float"] < 0.05
    assert t["ram_bytes"] <= 1024 and t["flash_bytes"] < 32 * 1024
    source = (out / "c" / "policy.c").read_text()
    assert "int16_t" in source and "int64_t acc" in source


def test_one_table_gives_the_linker_script_and_the_report_their_memory(tmp_path: Path) -> None:
    """runtime_c/cortex_m/targets.mk is read by both make (linker script, flags) and the exporter."""
    from embedrl.export import build
    from embedrl.export.target import TARGETS

    assert list(TARGETS) == ["cortex-m4", "cortex-m3", "cortex-m7"]
    for name, t in TARGETS.items():
        script = tmp_path / name / "memory.ld"
        subprocess.run(
            [
                "make",
                "-s",
                "-C",
                str(build.RUNTIME_C),
                f"TARGET={name}",
                f"BUILD_DIR={tmp_path}",
                str(script),
            ],
            check=True,
            capture_output=True,
        )
        text = script.read_text()
        assert f"LENGTH = {t.flash_kib}K" in text and f"LENGTH = {t.ram_kib}K" in text and t.part in text
        flash_at = "0x08000000" if t.board.startswith("stm32") else "0x00000000"  # STM32 flash; MPS2 code
        assert f"FLASH (rx) : ORIGIN = {flash_at}" in text
        assert "STACK_SIZE = " in text and "HEAP_SIZE = " in text
        flags = subprocess.run(
            ["make", "-s", "-C", str(build.RUNTIME_C), f"TARGET={name}", "flags"],
            check=True,
            capture_output=True,
            text=True,
        ).stdout
        assert t.cpu_flags in flags


def test_make_reads_a_relative_policy_dir_from_where_it_was_started_and_refuses_a_space(
    tmp_path: Path,
) -> None:
    (tmp_path / "out").mkdir()
    code, source = _export(tmp_path / "out", [6, 8, 2])
    assert code == 0
    lib = tmp_path / "build"
    # as a user types it from the folder that holds out/: make -C changes folder, the path does not move
    command = f"make -C {RUNTIME_C} lib POLICY_DIR={source.relative_to(tmp_path)}/c BUILD_DIR={lib}"
    result = subprocess.run(["bash", "-c", command], cwd=tmp_path, capture_output=True, text=True)
    assert result.returncode == 0, result.stderr
    assert (lib / "libpolicy.so").is_file()
    spaced = tmp_path / "with space"
    source.rename(spaced)
    result = subprocess.run(
        ["make", "-C", str(RUNTIME_C), "lib", f"POLICY_DIR={spaced}/c", f"BUILD_DIR={lib}"],
        capture_output=True, text=True,
    )  # fmt: skip
    assert result.returncode == 2 and "contains a space, which make cannot handle" in result.stderr


@pytest.mark.parametrize("widths", [[6, 23, 41, 2], [6, 100, 100, 2]])
def test_int8_full_dsp_and_portable_loops_give_the_models_bits_at_every_level(
    tmp_path: Path, widths: list[int]
) -> None:
    """The Cortex-M4 image of an int8 export: the DSP loop at -O0, -O2 (the export's build, checked
    against the Python model) and -O3, and the portable loop on the same core, print the same action bits.
    The first shape has outputs left over from the 4-row passes (23 = 5 x 4 + 2 + 1) and groups of four
    inputs left over from the unrolled loop (41 inputs: 11 groups)."""
    code, out = _export(tmp_path, widths, "--quantize", "int8", "--target", "cortex-m4")
    assert code == 0
    report = json.loads((out / "export_report.json").read_text())
    assert report["targets"]["cortex-m4"]["bit_exact_with_model"] is True
    m4 = target.TARGETS["cortex-m4"]
    vectors = out / "test" / "test_vectors.c"
    runs = {}
    for opt in ("-O2", "-O0", "-O3", "-O2 -DPOLICY_PORTABLE"):
        build_dir = tmp_path / opt.replace(" ", "_")
        build.make(
            "firmware", out / "c", build_dir, opt=opt, extra={"TARGET": m4.name, "TEST_VECTORS": str(vectors)}
        )
        runs[opt] = target.run_qemu(m4, build_dir / m4.name / "firmware.elf", 256, widths[-1])
    for opt, run in runs.items():
        assert run.actions.tobytes() == runs["-O2"].actions.tobytes(), opt
    # the DSP loop is the faster one (instructions counted under -icount)
    assert runs["-O2"].instructions_per_inference < runs["-O2 -DPOLICY_PORTABLE"].instructions_per_inference


def _test_vectors(export: Path) -> np.ndarray:
    """The observations compiled into the test image (exact float literals in test/test_vectors.c)."""
    text = (export / "test" / "test_vectors.c").read_text()
    rows = re.findall(r"\{([^{}]*)\}", text[text.index("= {") + 3 :])
    return np.array([[float(v.strip().rstrip("f")) for v in row.split(",")] for row in rows], np.float32)


def _policy_step_disassembly(elf: Path) -> str:
    """``policy_step`` of an image, disassembled (arm-none-eabi-objdump)."""
    text = subprocess.run(
        ["arm-none-eabi-objdump", "-d", "--no-show-raw-insn", str(elf)],
        capture_output=True,
        text=True,
        check=True,
    ).stdout
    return text.split("<policy_step>:", 1)[1].split("\n\n", 1)[0]


@pytest.mark.parametrize("widths", [[6, 23, 41, 2], [6, 1, 5, 2]])
def test_float_dot_products_on_cortex_m_give_the_host_input_major_bits(
    tmp_path: Path, widths: list[int]
) -> None:
    """float32: the Cortex-M images (dot products, 8/4/2/1 outputs per pass: 23 = 2 x 8 + 4 + 2 + 1,
    41 = 5 x 8 + 1, 5 = 4 + 1; a layer of one output) print the bits of the host's build of the same policy.c
    (input-major loops): the M4F and M7 in the VLDM form (weights in the passes' order, each input's weights
    of a pass and each iteration's four inputs in one VLDM; inputs left over after the iterations of four:
    41 = 10 x 4 + 1, 23 = 5 x 4 + 3, 6 = 4 + 2, 5 = 4 + 1, and a layer of one input), at -O2, -O0 and -O3,
    and in C (-DPOLICY_PORTABLE); the M3 (no FPU) in C. The output layer has no tanh: the C libraries'
    tanhf (glibc, newlib) may differ in the last bit."""
    src, out = tmp_path / "mlp.onnx", tmp_path / "export"
    onnx.save(mlp_model(widths, ["Relu"] * (len(widths) - 2) + ["Identity"]), str(src))
    targets = ["--target", "cortex-m4", "--target", "cortex-m3", "--target", "cortex-m7"]
    assert main(["export", str(src), "--out", str(out), "--episodes", "0", *targets]) == 0
    layers = len(widths) - 1
    source = (out / "c" / "policy.c").read_text()
    assert source.count("#if POLICY_VLDM\n") > layers and source.count("#elif POLICY_DOT_PRODUCTS") == layers
    obs = _test_vectors(out)
    act = widths[-1]
    host = np.asarray(
        build.CPolicy(out / "bin" / "host" / "libpolicy.so", "policy", widths[0], act).rows(obs)[0]
    )
    for name in ("cortex-m4", "cortex-m3", "cortex-m7"):
        run = target.run_qemu(target.TARGETS[name], out / "bin" / name / "firmware.elf", len(obs), act)
        assert run.actions.tobytes() == host.astype(np.float32).tobytes(), name
    m4 = target.TARGETS["cortex-m4"]
    runs = {}
    for opt in ("-O0", "-O3", "-O2 -DPOLICY_PORTABLE"):
        build_dir = tmp_path / opt.replace(" ", "_")
        vectors = {"TARGET": m4.name, "TEST_VECTORS": str(out / "test" / "test_vectors.c")}
        build.make("firmware", out / "c", build_dir, opt=opt, extra=vectors)
        runs[opt] = target.run_qemu(m4, build_dir / m4.name / "firmware.elf", len(obs), act)
        assert runs[opt].actions.tobytes() == host.astype(np.float32).tobytes(), opt
    # the VLDM form loads a pass's weights of one input in one instruction; C and the M3 never do
    vldm = re.compile(r"vldmia\s+r\d+!, \{s16-s(23|19|17)\}")
    for name in ("cortex-m4", "cortex-m7"):
        assert vldm.search(_policy_step_disassembly(out / "bin" / name / "firmware.elf")), name
    assert not vldm.search(_policy_step_disassembly(out / "bin" / "cortex-m3" / "firmware.elf"))
    portable = tmp_path / "-O2_-DPOLICY_PORTABLE" / m4.name / "firmware.elf"
    assert not vldm.search(_policy_step_disassembly(portable))


def test_the_stm32f100_counts_an_inference_as_the_mps2_board_does(tmp_path: Path) -> None:
    """The Cortex-M3 on QEMU's stm32vldiscovery (STM32F100RB) times the test image with the core's SysTick at
    24 MHz (125/3 instructions per tick: QEMU models none of the part's timers); the same image built for
    the MPS2 board (its CMSDK timer at 25 MHz, 40 instructions per tick) counts the same instructions per
    inference, to the two timers' resolution. The F100 image sits in the part's memory map."""
    code, out = _export(tmp_path, [6, 32, 2], "--quantize", "q15", "--target", "cortex-m3")
    assert code == 0
    f100 = target.TARGETS["cortex-m3"]
    assert (f100.qemu_machine, f100.flash_kib, f100.ram_kib) == ("stm32vldiscovery", 128, 8)
    assert f100.tick_instructions == pytest.approx(1e9 / 24e6)
    elf = out / "bin" / "cortex-m3" / "firmware.elf"
    symbols = dict(
        (name, int(address, 16))
        for address, _, name in (
            line.split() for line in subprocess.run(
                ["arm-none-eabi-nm", str(elf)], capture_output=True, text=True, check=True
            ).stdout.splitlines() if len(line.split()) == 3
        )
    )  # fmt: skip
    assert symbols["vector_table"] == 0x08000000 and symbols["_estack"] == 0x20000000 + 8 * 1024
    mps2 = {"cortex-m3.BOARD": "mps2", "cortex-m3.FLASH_AT": "0x00000000", "cortex-m3.FLASH": "256",
            "cortex-m3.RAM": "64"}  # fmt: skip
    build.make("firmware", out / "c", tmp_path / "mps2", extra={"TARGET": "cortex-m3", **mps2,
               "TEST_VECTORS": str(out / "test" / "test_vectors.c")})  # fmt: skip
    on_mps2 = target.run_qemu(
        replace(f100, qemu_machine="mps2-an385", tick_instructions=40.0),
        tmp_path / "mps2" / "cortex-m3" / "firmware.elf", 256, 2,
    )  # fmt: skip
    on_f100 = target.run_qemu(f100, elf, 256, 2)
    assert on_f100.actions.tobytes() == on_mps2.actions.tobytes()
    assert on_f100.instructions_per_inference > 1000
    resolution = 2 * (40 + f100.tick_instructions) / 256  # a tick at each end of each timed loop
    assert abs(on_f100.instructions_per_inference - on_mps2.instructions_per_inference) <= resolution


def test_bench_targets_peer_is_the_checkouts_from_any_working_directory(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    from embedrl.cli import build_parser

    monkeypatch.chdir(tmp_path)
    emx = build_parser().parse_args(["bench-target", "an export"]).emx
    assert emx == RUNTIME_C.parent / "tools" / "emx" / "bin" / "emx-onnx-cgen" and emx.is_absolute()
