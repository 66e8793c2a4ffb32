"""Hostile files and arguments: each class is refused in one line with exit status 2, before it costs
time or memory (the limits are read from headers, never after allocating), and nothing is written.

Every row runs the real command in a child process and asserts its CPU time and peak memory (the child's
own user and system time and maximum resident set, from ``wait4``) against a budget: a class that is refused
only after the cost is paid fails here even if the message is right.
"""

from __future__ import annotations

import io
import json
import os
import shutil
import zipfile
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np
import onnx
import pytest
from onnx import TensorProto, helper, numpy_helper

from embedrl.cli import main
from tests.conftest import Exported, marks_its_users
from tests.export.test_recurrent import lstm_state_of_another_rank
from tests.test_user_errors import TD3, _external, _gemm_model, assert_refused, run_measured

TIME_BUDGET_S = 10.0
"""CPU time (user + system) of a refusal (importing torch alone takes ~2 s). CPU time, not wall time: a busy
machine stretches the wall time (10-16 s seen) but not the work; a refusal that blocks instead of working
is stopped by ``run_measured``'s wall-clock limit."""
MEMORY_BUDGET_MB = 600
"""Peak resident memory of a refusal (the exporter's imports alone take ~340 MB)."""
DEEP = 100_000
"""Nesting depth of the hostile JSON documents (Python's parser recurses once per level)."""


def _onnx_row(make: Callable[[], onnx.ModelProto], *extra: str) -> Callable[[Path], list[str]]:
    def argv(tmp: Path) -> list[str]:
        path = tmp / "model dir" / "m.onnx"
        path.parent.mkdir()
        onnx.save(make(), path)
        return ["export", str(path), "--out", str(tmp / "out"), "--episodes", "0", *extra]

    return argv


def _weights(rows: int = 2, cols: int = 6) -> TensorProto:
    return numpy_helper.from_array(np.random.default_rng(0).normal(size=(rows, cols)).astype(np.float32), "W")


def many_relus() -> onnx.ModelProto:
    nodes = [helper.make_node("Relu", ["obs" if i == 0 else f"r{i - 1}"], [f"r{i}"]) for i in range(20_000)]
    nodes.append(helper.make_node("Gemm", ["r19999", "W"], ["act"], transB=1))
    graph = helper.make_graph(
        nodes,
        "g",
        [helper.make_tensor_value_info("obs", TensorProto.FLOAT, ["batch", 6])],
        [helper.make_tensor_value_info("act", TensorProto.FLOAT, ["batch", 2])],
        [_weights()],
    )
    return helper.make_model(graph, opset_imports=[helper.make_opsetid("", 17)], ir_version=8)


def reshape_with_zero() -> onnx.ModelProto:
    shape = numpy_helper.from_array(np.array([1, 6, 0], dtype=np.int64), "shape")
    graph = helper.make_graph(
        [
            helper.make_node("Reshape", ["obs", "shape"], ["r"]),
            helper.make_node("Gemm", ["r", "W"], ["act"], transB=1),
        ],
        "g",
        [helper.make_tensor_value_info("obs", TensorProto.FLOAT, [1, 6])],
        [helper.make_tensor_value_info("act", TensorProto.FLOAT, [1, 2])],
        [_weights(), shape],
    )
    return helper.make_model(graph, opset_imports=[helper.make_opsetid("", 17)], ir_version=8)


def wide_input() -> onnx.ModelProto:
    # a 2^40-wide input declared in the header; the weights are tiny and do not fit it
    return _gemm_model(_weights(), 2**40, 2)


def external_without_length(tmp: Path) -> list[str]:
    folder = tmp / "model dir"
    folder.mkdir()
    onnx.save(_gemm_model(_external("W", [2, 6], "w.bin"), 6, 2), folder / "m.onnx")
    with (folder / "w.bin").open("wb") as f:
        f.truncate(200 * 2**20)  # 200 MB (sparse): only 48 bytes belong to W
    return ["export", str(folder / "m.onnx"), "--out", str(tmp / "out"), "--episodes", "0"]


def external_through_symlink(tmp: Path) -> list[str]:
    folder = tmp / "model dir"
    folder.mkdir()
    (tmp / "secret.bin").write_bytes(np.zeros(12, np.float32).tobytes())
    (folder / "w.bin").symlink_to(tmp / "secret.bin")
    onnx.save(_gemm_model(_external("W", [2, 6], "w.bin"), 6, 2), folder / "m.onnx")
    return ["export", str(folder / "m.onnx"), "--out", str(tmp / "out"), "--episodes", "0"]


def _zip_with(tmp: Path, replace: dict[str, bytes], name: str = "m.zip") -> Path:
    """The shipped TD3 zip with some entries replaced (its embedrl.json dropped unless given)."""
    path = tmp / name
    with zipfile.ZipFile(TD3) as src, zipfile.ZipFile(path, "w") as dst:
        for info in src.infolist():
            if info.filename in replace or info.filename == "embedrl.json":
                continue
            dst.writestr(info, src.read(info.filename))
        for entry, data in replace.items():
            dst.writestr(entry, data)
    return path


def _data_with(**kwargs: object) -> bytes:
    with zipfile.ZipFile(TD3) as zf:
        data = json.loads(zf.read("data"))
    data["policy_kwargs"].update(kwargs)
    data["policy_kwargs"].pop(":serialized:")
    return json.dumps(data).encode()


def sb3_row(replace: Callable[[], dict[str, bytes]], command: str = "export") -> Callable[[Path], list[str]]:
    def argv(tmp: Path) -> list[str]:
        path = _zip_with(tmp, replace())
        if command == "eval":
            return ["eval", str(path), "--episodes", "1"]
        return ["export", str(path), "--out", str(tmp / "out"), "--episodes", "0"]

    return argv


def _deep_json() -> bytes:
    return b"[" * DEEP + b"]" * DEEP


def _npz(**arrays: object) -> bytes:
    buffer = io.BytesIO()
    np.savez(buffer, **arrays)  # type: ignore[arg-type]
    return buffer.getvalue()


def npz_row(make: Callable[[Path], Path]) -> Callable[[Path], list[str]]:
    def argv(tmp: Path) -> list[str]:
        stats = make(tmp)
        model = _zip_with(tmp, {})  # without embedrl.json: a model from elsewhere, statistics as given
        return [
            "export",
            str(model),
            "--vecnormalize",
            str(stats),
            "--out",
            str(tmp / "out"),
            "--episodes",
            "0",
        ]

    return argv


def vector_epsilon(tmp: Path) -> Path:
    path = tmp / "stats.npz"
    ok = np.zeros(6)
    path.write_bytes(
        _npz(mean=ok, var=ok + 1, epsilon=np.ones(3), clip_obs=np.float64(10), norm_obs=np.bool_(True))
    )
    return path


def huge_header(tmp: Path) -> Path:
    """A ``mean`` whose .npy header declares 1e13 float64 values (80 TB) over 8 bytes of data."""
    path = tmp / "stats.npz"
    header = {"descr": "<f8", "fortran_order": False, "shape": (10**13,)}
    npy = io.BytesIO()
    np.lib.format.write_array_header_1_0(npy, header)
    npy.write(b"\0" * 8)
    ok = np.zeros(6)
    with zipfile.ZipFile(path, "w") as zf:
        zf.writestr("mean.npy", npy.getvalue())
        for name, value in (("var", ok + 1), ("epsilon", np.float64(1e-8)), ("clip_obs", np.float64(10)),
                            ("norm_obs", np.bool_(True))):  # fmt: skip
            buffer = io.BytesIO()
            np.save(buffer, value)
            zf.writestr(f"{name}.npy", buffer.getvalue())
    return path


def deep_names(tmp: Path) -> list[str]:
    names = tmp / "names.json"
    names.write_bytes(_deep_json())
    return ["export", str(TD3), "--names", str(names), "--out", str(tmp / "out"), "--episodes", "0"]


def deep_interface(tmp: Path) -> list[str]:
    export = tmp / "export"
    (export / "c").mkdir(parents=True)
    (export / "c" / "policy.c").write_text("int x;\n")
    (export / "policy.onnx").write_bytes(b"")
    (export / "interface.json").write_bytes(_deep_json())
    return ["hil", "run", "--export-dir", str(export), "--node", "python"]


RUN_CONFIG = {
    "algo": "td3", "preset": "tuned", "seed": 0, "scenario": "static", "hyperparameters": {}, "overrides": [],
    "budget": {"max_steps": 1000, "max_episodes": 100, "checkpoint_every": 500, "eval_every": 500},
    "machine": {"portable": False},
}  # fmt: skip
"""A run's config.json as ``train`` writes it (the hyperparameters left out)."""


def damaged_run(edit: Callable[[dict[str, Any]], object]) -> Callable[[Path], list[str]]:
    """``train --resume`` of a run folder whose config.json was edited."""

    def argv(tmp: Path) -> list[str]:
        config = json.loads(json.dumps(RUN_CONFIG))
        edit(config)
        (tmp / "run").mkdir()
        (tmp / "run" / "config.json").write_text(json.dumps(config))
        return ["train", "--resume", str(tmp / "run")]

    return argv


def _special(tmp: Path, kind: str) -> Path:
    """A path that is no regular file: a FIFO (opening it waits for a writer), /dev/zero (endless), or a
    sparse file above the JSON size limit."""
    if kind == "/dev/zero":
        return Path("/dev/zero")
    path = tmp / f"{kind}.json"
    if kind == "fifo":
        os.mkfifo(path)
    else:
        with path.open("wb") as f:
            f.truncate(100 * 2**20)
    return path


def _report_of_a_fake_export(kind: str) -> Callable[[Path], list[str]]:
    """``report --hil`` of a special file, on a folder with just what the report reads first."""

    def argv(tmp: Path) -> list[str]:
        export = tmp / "export"
        (export / "c").mkdir(parents=True)
        for name in ("policy.c", "policy.h"):
            (export / "c" / name).write_text("")
        (export / "interface.json").write_text("{}")
        (export / "export_report.json").write_text('{"name": "policy", "interface": {"observation": []}}')
        hil = _special(tmp, kind)
        return ["report", str(export), "--hil", str(hil), "--out", str(tmp / "out" / "r.html")]

    return argv


def _names_row(kind: str) -> Callable[[Path], list[str]]:
    return lambda tmp: ["export", str(TD3), "--names", str(_special(tmp, kind)), "--out", str(tmp / "out")]


def bench_from(result: object) -> Callable[[Path], list[str]]:
    """``bench --from`` a folder whose one run's result.json holds ``result``."""

    def argv(tmp: Path) -> list[str]:
        run = tmp / "bench" / "runs" / "td3-seed0"
        run.mkdir(parents=True)
        (run / "result.json").write_text(json.dumps(result))
        return ["bench", "--from", str(tmp / "bench"), "--out", str(tmp / "table")]

    return argv


ROWS: dict[str, tuple[Callable[[Path], list[str]], str]] = {
    "bench --from a result.json that is a list": (
        bench_from([]),
        "not a bench result (a list, not an object)",
    ),
    "bench --from a result.json without its keys": (
        bench_from({"algo": "td3", "seed": 0}),
        "not a bench result (preset is missing)",
    ),
    "train --resume of a config.json with budget []": (
        damaged_run(lambda c: c.update(budget=[])),
        "config.json is damaged (budget is [], not an object)",
    ),
    "train --resume of a config.json with machine 'x'": (
        damaged_run(lambda c: c.update(machine="x")),
        "machine is 'x', not an object",
    ),
    "train --resume of a config.json with max_steps 'lots'": (
        damaged_run(lambda c: c["budget"].update(max_steps="lots")),
        "budget.max_steps is 'lots', not a whole number",
    ),
    "ONNX of 20,000 Relu nodes": (_onnx_row(many_relus), "20,001 nodes exceed the limit"),
    "ONNX LSTM whose next state has another rank": (
        _onnx_row(lstm_state_of_another_rank, "--obs-range=-1:1", "--act-range=-1:1", "--sample-time", "0.1"),
        "output 'h_next' [1, 16], differ in shape",
    ),
    "ONNX Reshape to [1, 6, 0]": (_onnx_row(reshape_with_zero), "Reshape"),
    "ONNX input 2^40 wide": (_onnx_row(wide_input), "1,099,511,627,776"),
    "ONNX input 2^40 wide with --obs-range": (
        _onnx_row(wide_input, "--obs-range=-1:1", "--act-range=-1:1", "--sample-time", "0.1"),
        "1,099,511,627,776",
    ),
    "ONNX external data through a symlink": (external_through_symlink, "symbolic link"),
    "SB3 net_arch [10000, 10000]": (
        sb3_row(lambda: {"data": _data_with(net_arch=[10_000, 10_000])}),
        "exceed the limit of 4,000,000",
    ),
    "SB3 net_arch [-5]": (sb3_row(lambda: {"data": _data_with(net_arch=[-5])}), "net_arch"),
    "SB3 net_arch [-5] (eval)": (sb3_row(lambda: {"data": _data_with(net_arch=[-5])}, "eval"), "net_arch"),
    "SB3 deeply nested data": (sb3_row(lambda: {"data": _deep_json()}), "nested too deeply"),
    "SB3 deeply nested embedrl.json": (sb3_row(lambda: {"embedrl.json": _deep_json()}), "nested too deeply"),
    "SB3 deeply nested policy_kwargs literal": (
        sb3_row(lambda: {"data": _data_with(net_arch="[" * DEEP + "]" * DEEP)}),
        "net_arch",
    ),
    "--names deeply nested": (deep_names, "nested too deeply"),
    "interface.json deeply nested": (deep_interface, "nested too deeply"),
    "vecnormalize .npz with a vector epsilon": (npz_row(vector_epsilon), "epsilon"),
    "vecnormalize .npz declaring 1e13 values": (npz_row(huge_header), "(10,000,000,000,000 values)"),
    "--max-model-mb inf": (
        lambda tmp: ["export", str(TD3), "--out", str(tmp / "out"), "--max-model-mb", "inf"],
        "--max-model-mb",
    ),
    "--max-params -1": (
        lambda tmp: ["export", str(TD3), "--out", str(tmp / "out"), "--max-params", "-1"],
        "--max-params",
    ),
    "tune --ray at a closed port": (
        lambda tmp: ["tune", "--algo", "td3", "--ray", "127.0.0.1:1", "--out", str(tmp / "out")],
        "--ray 127.0.0.1:1: cannot connect",
    ),
    "bench --ray at an unknown host": (
        lambda tmp: ["bench", "--ray", "not-a-host.invalid:6379", "--out", str(tmp / "out")],
        "--ray not-a-host.invalid:6379: cannot connect",
    ),
    "shaping --ray without a port": (
        lambda tmp: ["shaping", "--ray", "somehost", "--out", str(tmp / "out")],
        "give local, auto, HOST:PORT",
    ),
    "report --hil a FIFO": (_report_of_a_fake_export("fifo"), "fifo.json: not a regular file but a FIFO"),
    "report --hil /dev/zero": (_report_of_a_fake_export("/dev/zero"), "not a regular file but a character"),
    "report --hil of 100 MB": (_report_of_a_fake_export("big"), "104,857,600 bytes exceed the limit"),
    "--names a FIFO": (_names_row("fifo"), "fifo.json: not a regular file but a FIFO"),
    "--names /dev/zero": (_names_row("/dev/zero"), "/dev/zero: not a regular file but a character device"),
    "--names of 100 MB": (_names_row("big"), "104,857,600 bytes exceed the limit"),
    "train --preset a FIFO": (
        lambda tmp: ["train", "--preset", str(_special(tmp, "fifo")), "--out", str(tmp / "out")],
        "fifo.json: not a regular file but a FIFO",
    ),
}


@pytest.mark.parametrize("row", list(ROWS))
def test_a_hostile_input_is_refused_in_one_line_before_it_costs(row: str, tmp_path: Path) -> None:
    make_argv, said = ROWS[row]
    cpu_s, peak_mb = assert_refused(make_argv(tmp_path), said, tmp_path)
    assert cpu_s < TIME_BUDGET_S, f"{cpu_s:.1f} s of CPU"
    assert peak_mb < MEMORY_BUDGET_MB, f"{peak_mb:.0f} MB"


def test_external_data_without_a_length_reads_only_what_its_shape_needs(tmp_path: Path) -> None:
    # 48 bytes of weights at the start of a 200 MB file: the export reads those, not the file.
    argv = external_without_length(tmp_path)
    result, _, peak_mb = run_measured(argv, {**os.environ})
    assert result.returncode == 0, result.stderr[-2000:]
    assert peak_mb < MEMORY_BUDGET_MB, f"{peak_mb:.0f} MB"
    exported = onnx.load(str(tmp_path / "out" / "policy.onnx"))  # weights inline: the folder stands alone
    assert all(t.data_location != TensorProto.EXTERNAL for t in exported.graph.initializer)


def test_an_onnx_at_the_installed_onnx_default_ir_version_exports(tmp_path: Path) -> None:
    # onnx saves at its own newest IR version, which onnxruntime may not run yet
    model = _gemm_model(_weights(), 6, 2)
    model.ir_version = onnx.IR_VERSION
    path = tmp_path / "m.onnx"
    onnx.save(model, path)
    argv = ["export", str(path), "--out", str(tmp_path / "out"), "--episodes", "0"]
    result, _, _ = run_measured(argv, {**os.environ})
    assert result.returncode == 0, result.stderr[-2000:]


@pytest.fixture(scope="module")
@marks_its_users("qemu")  # the export runs the M4 firmware on QEMU
def export(tmp_path_factory: pytest.TempPathFactory, exported: Exported) -> Path:
    """The shipped TD3 exported for the M4 (a firmware node image in bin/), with a HIL report of the Python
    node on it (``hil.json`` beside the export) in its chain."""
    root = tmp_path_factory.mktemp("hostile")
    shutil.copytree(exported(TD3, "--episodes", "0", "--target", "cortex-m4"), root / "export")
    argv = ["hil", "run", "--export-dir", str(root / "export"), "--node", "python", "--episodes", "1",
            "--json", str(root / "hil.json")]  # fmt: skip
    assert main(argv) == 0
    return root / "export"


def _edit_json(path: Path, edit: Callable[[Any], object]) -> None:
    data = json.loads(path.read_text())
    edit(data)
    path.write_text(json.dumps(data))


def _damaged_export(tmp: Path, export: Path, name: str, edit: Callable[[Any], object]) -> Path:
    """A copy of ``export`` in ``tmp`` with its JSON file ``name`` edited."""
    copy = tmp / "export"
    shutil.copytree(export, copy)
    _edit_json(copy / name, edit)
    return copy


def _damaged_hil(tmp: Path, export: Path, edit: Callable[[dict[str, Any]], object]) -> Path:
    """A copy of the HIL report made on ``export``, edited."""
    path = tmp / "hil.json"
    shutil.copy(export.parent / "hil.json", path)
    _edit_json(path, edit)
    return path


def _link(field: str, value: object) -> Callable[[Any], object]:
    return lambda data: data["predicate"]["links"][2].update({field: value})


def _no_links(data: Any) -> None:
    data["predicate"]["links"] = []


def _chain_row(edit: Callable[[Any], object]) -> Callable[[Path, Path], list[str]]:
    return lambda tmp, export: ["verify-chain", str(_damaged_export(tmp, export, "chain.json", edit))]


def _report_row(edit: Callable[[dict[str, Any]], object]) -> Callable[[Path, Path], list[str]]:
    def argv(tmp: Path, export: Path) -> list[str]:
        return ["report", str(export), "--hil", str(_damaged_hil(tmp, export, edit)), "--out",
                str(tmp / "out" / "r.html")]  # fmt: skip

    return argv


def non_elf_node(tmp: Path, export: Path) -> list[str]:
    copy = tmp / "export"
    shutil.copytree(export, copy)
    (copy / "bin" / "cortex-m4" / "node.elf").write_text("not an image\n")
    return ["report", str(copy), "--out", str(tmp / "out" / "r.html")]


def renamed_policy(tmp: Path, export: Path) -> list[str]:
    copy = _damaged_export(tmp, export, "export_report.json", lambda d: d.update(name="other"))
    return ["report", str(copy), "--out", str(tmp / "out" / "r.html")]


def firmware_run_without_firmware(data: dict[str, Any]) -> None:
    data.update(node="firmware", target="cortex-m4")
    del data["firmware"]


def also_another_policy(tmp: Path, export: Path) -> list[str]:
    sac = export.parent / "sac"
    if not sac.is_dir():
        assert main(["export", str(TD3.with_name("sac.zip")), "--out", str(sac), "--episodes", "0"]) == 0
    return ["report", str(export), "--also", str(sac), "--out", str(tmp / "out" / "r.html")]


EXPORT_ROWS: dict[str, tuple[Callable[[Path, Path], list[str]], str]] = {
    "verify-chain of a chain without links": (_chain_row(_no_links), "(no links)"),
    "verify-chain of a number for a digest": (_chain_row(_link("sha256", 5)), "sha256 5 is not a SHA-256"),
    "verify-chain of a number for a path": (_chain_row(_link("path", 5)), "path 5 is not a file's path"),
    "report of an export whose node.elf is no ELF": (non_elf_node, "node.elf: not an ELF image"),
    "report of an export_report.json naming another policy": (renamed_policy, "there is no c/other.c"),
    "report --hil without node": (_report_row(lambda d: d.pop("node")), "(no 'node')"),
    "report --hil of the firmware node without firmware": (
        _report_row(firmware_run_without_firmware),
        "(no 'firmware')",
    ),
    "report --hil with export_files a list": (
        _report_row(lambda d: d.update(export_files=list(d["export_files"]))),
        "'export_files' is ['policy.onnx'",
    ),
    "report --also of another policy's export": (also_another_policy, "exports another policy"),
}


@pytest.mark.parametrize("row", list(EXPORT_ROWS))
def test_a_damaged_export_or_report_is_refused_in_one_line(row: str, tmp_path: Path, export: Path) -> None:
    make_argv, said = EXPORT_ROWS[row]
    cpu_s, peak_mb = assert_refused(make_argv(tmp_path, export), said, tmp_path)
    assert cpu_s < TIME_BUDGET_S, f"{cpu_s:.1f} s of CPU"
    assert peak_mb < MEMORY_BUDGET_MB, f"{peak_mb:.0f} MB"
