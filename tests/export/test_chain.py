"""The traceability chain: every link of an export (run config -> model -> ONNX -> C -> binaries ->
reports) hashed; ``embedrl verify-chain`` names the first link a one-byte change broke."""

from __future__ import annotations

import json
import multiprocessing
import shutil
from concurrent.futures import ProcessPoolExecutor
from pathlib import Path
from typing import Any

import pytest

from embedrl.cli import main
from embedrl.common import sha256
from embedrl.export import chain
from embedrl.hil.run import add_to_chain

SHIPPED = Path(__file__).resolve().parents[2] / "policies" / "static"


@pytest.fixture(scope="module")
def traced(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A shipped policy (model and record) copied into a folder of its own, exported for the M4."""
    root = tmp_path_factory.mktemp("chain")
    (root / "policy").mkdir()
    for name in ("td3.zip", "td3.json"):
        shutil.copy(SHIPPED / name, root / "policy" / name)
    argv = ["export", str(root / "policy" / "td3.zip"), "--out", str(root / "export"), "--episodes", "0",
            "--target", "cortex-m4"]  # fmt: skip
    assert main(argv) == 0
    return root


def _copy(traced: Path, tmp_path: Path) -> Path:
    """The policy folder and the export, with the manifest's absolute paths moved along."""
    shutil.copytree(traced, tmp_path / "t")
    manifest = tmp_path / "t" / "export" / chain.MANIFEST
    manifest.write_text(manifest.read_text().replace(str(traced), str(tmp_path / "t")))
    return tmp_path / "t" / "export"


def _flip_one_byte(path: Path) -> None:
    data = bytearray(path.read_bytes())
    data[len(data) // 2] ^= 0x01
    path.write_bytes(bytes(data))


def test_the_export_records_every_link_from_the_run_to_the_report(
    traced: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    links = chain.read(traced / "export")
    names = [k.name for k in links]
    assert names[:4] == ["run config", "model", "ONNX", "interface"]
    assert names[-1] == "verification report"
    assert {"binary host/libpolicy.so", "binary cortex-m4/firmware.elf", "binary cortex-m4/node.elf"} <= set(
        names
    )
    assert links[0].facts == {"seed": 1}  # the shipped run's seed
    assert links[1].sha256 == json.loads((traced / "policy" / "td3.json").read_text())["sha256"]
    assert main(["verify-chain", str(traced / "export"), "--verbose"]) == 0
    out = capsys.readouterr().out.splitlines()
    assert len(out) == len(links) + 1 and all(line.startswith("ok ") for line in out[:-1])
    assert out[-1] == f"chain intact: {len(links)} links, from run config to verification report"


def test_a_one_byte_change_in_any_link_is_named(
    traced: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    links = chain.read(traced / "export")
    for number, k in enumerate(links, 1):
        export = _copy(traced, tmp_path / str(number))
        target = Path(k.path.replace(str(traced), str(tmp_path / str(number) / "t")))
        _flip_one_byte(target if target.is_absolute() else export / k.path)
        assert main(["verify-chain", str(export)]) == 1, k.name
        said = capsys.readouterr().out
        assert said.startswith(f"FAIL link {number}/{len(links)} {k.name}: "), said
        assert "changed: sha256" in said


def test_a_file_regenerated_from_another_parent_is_named_even_with_a_fresh_hash(
    traced: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """The manifest rewritten to the edited C's hash: the C's own header still names another ONNX."""
    export = _copy(traced, tmp_path)
    source = export / "c" / "policy.c"
    onnx_hash = sha256(export / "policy.onnx")
    source.write_text(source.read_text().replace(onnx_hash, "0" * 64, 1))
    manifest = export / chain.MANIFEST
    manifest.write_text(manifest.read_text().replace(chain.read(export)[4].sha256, sha256(source)))
    assert main(["verify-chain", str(export)]) == 1
    assert "C source policy.c: c/policy.c was made from another ONNX" in capsys.readouterr().out


def test_an_edit_rehashed_into_the_manifest_is_named_by_the_export_report_s_own_record(
    traced: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """One weight changed in the C and its new hash put into chain.json: the verification report still
    records the hash the export wrote, and the two are cross-checked."""
    export = _copy(traced, tmp_path)
    source = export / "c" / "policy.c"
    old = sha256(source)
    text = source.read_text()
    start = text.index("static const float")
    weight = text[start:].split("{", 1)[1].split(",", 1)[0].strip()
    source.write_text(text[:start] + text[start:].replace(weight, "0.5f", 1))
    manifest = export / chain.MANIFEST
    manifest.write_text(manifest.read_text().replace(old, sha256(source)))
    assert main(["verify-chain", str(export)]) == 1
    said = capsys.readouterr().out
    assert "verification report: export_report.json records another c/policy.c" in said


def test_a_hil_report_joins_the_chain_and_is_checked_against_the_export(traced: Path, tmp_path: Path) -> None:
    export = _copy(traced, tmp_path)
    report = tmp_path / "hil report.json"
    files = {name: sha256(export / name) for name in ("policy.onnx", "interface.json", "c/policy.c")}
    data: dict[str, Any] = {
        "verdict": {"passed": True}, "node": "c", "target": None, "episodes": 2, "export_files": files,
    }  # fmt: skip
    report.write_text(json.dumps(data))
    assert add_to_chain(export, report, data)
    last = chain.read(export)[-1]
    assert last.name == f"HIL report {report.resolve()}" and last.facts["passed"] is True
    assert all(c.ok for c in chain.verify(export))
    data["export_files"]["c/policy.c"] = "0" * 64  # a report made on other C, re-hashed into the chain
    report.write_text(json.dumps(data))
    assert add_to_chain(export, report, data)
    failed = [c for c in chain.verify(export) if not c.ok]
    assert len(failed) == 1 and "records another c/policy.c (sha256 000000000000...)" in failed[0].detail
    assert not add_to_chain(tmp_path, report, data)  # a folder without a manifest: nothing to add to


@pytest.mark.parametrize("content", [None, "{not json", '{"format": 99, "links": []}', '{"format": 1}'])
def test_a_folder_without_a_readable_manifest_is_refused_in_one_line(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], content: str | None
) -> None:
    if content is not None:
        (tmp_path / chain.MANIFEST).write_text(content)
    assert main(["verify-chain", str(tmp_path)]) == 2
    err = capsys.readouterr().err.strip()
    assert err.startswith("error: ") and len(err.splitlines()) == 1


def _append_reports(export: Path, first: int, count: int) -> None:
    """Append ``count`` HIL report links to ``export``'s manifest (one writer of several)."""
    for index in range(first, first + count):
        report = export / f"report-{index}.json"
        report.write_text(json.dumps({"index": index}))
        chain.append(export, chain.link(export, f"HIL report {index}", report, ["interface"]))


def test_concurrent_appends_keep_every_link_and_every_reader_sees_a_whole_manifest(tmp_path: Path) -> None:
    # Several `hil run --json` on one export append at once: each writer reads, changes and replaces
    # the manifest under its lock, so no link is lost and a reader never sees a half-written file.
    (tmp_path / "interface.json").write_text("{}")
    chain.write(tmp_path, [chain.link(tmp_path, "interface", tmp_path / "interface.json", [])])
    writers, each = 6, 15
    context = multiprocessing.get_context("spawn")
    with ProcessPoolExecutor(max_workers=writers, mp_context=context) as pool:
        futures = [pool.submit(_append_reports, tmp_path, w * each, each) for w in range(writers)]
        reads = 0
        while not all(f.done() for f in futures):
            chain.read(tmp_path)  # a torn manifest raises ChainError ("not a chain manifest")
            reads += 1
        for future in futures:
            future.result()
    names = {k.name for k in chain.read(tmp_path)}
    assert names == {"interface", *(f"HIL report {i}" for i in range(writers * each))}
    assert reads > 0
    assert sorted(p.name for p in tmp_path.iterdir() if p.name.startswith(".")) == []  # no partial file left
