"""``embedrl report``: the deployment page opened in headless Chromium (Debian's ``chromium``, from
``make deps``), offline, every section and key figure read back from the rendered DOM, nothing fetched."""

from __future__ import annotations

import json
import re
import shutil
import subprocess
from html.parser import HTMLParser
from pathlib import Path

import pytest

from embedrl.cli import main
from tests.conftest import marks_its_users
from tests.hil.conftest import SHIPPED_TD3

SECTIONS = ("conditions", "interface", "entry-points", "verification", "closed-loop", "layers", "resources",
            "coding-standard", "coverage", "traceability")  # fmt: skip
CHROMIUM = ("chromium", "--headless", "--no-sandbox", "--disable-gpu", "--no-first-run",
            "--disable-background-networking", "--disable-component-update",
            "--host-resolver-rules=MAP * ~NOTFOUND")  # fmt: skip
SCREENSHOT = Path("/tmp/embedrl-report-screenshot.png")
"""The rendered page, kept for a person to look at."""


@pytest.fixture(scope="module")
@marks_its_users("qemu")  # the export runs the M4 firmware on QEMU
def reported(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, Path, dict[str, object]]:
    """The shipped TD3 exported for the M4, a HIL run on the Python node, and the report of both, in
    folders with spaces."""
    root = tmp_path_factory.mktemp("report") / "with space"
    export = root / "export dir"
    argv = ["export", str(SHIPPED_TD3), "--out", str(export), "--episodes", "2", "--target", "cortex-m4"]
    assert main(argv) == 0
    hil = root / "hil run.json"
    argv = [
        "hil",
        "run",
        "--export-dir",
        str(export),
        "--node",
        "python",
        "--episodes",
        "2",
        "--json",
        str(hil),
    ]
    assert main(argv) == 0
    page = root / "out" / "report.html"
    assert main(["report", str(export), "--hil", str(hil), "--out", str(page)]) == 0
    return export, page, json.loads((export / "export_report.json").read_text())


def _chromium(page: Path, *flags: str) -> str:
    if shutil.which("chromium") is None:
        pytest.fail("chromium is not installed: run `make deps` (Debian's chromium)")
    result = subprocess.run([*CHROMIUM, *flags, page.as_uri()], capture_output=True, text=True, timeout=120)
    assert result.returncode == 0, result.stderr[-500:]
    return result.stdout


def page_requests(page: Path, net_log: Path) -> list[str]:
    """URLs the page itself asked for (Chromium's own background requests have no origin)."""
    _chromium(page, f"--log-net-log={net_log}", "--dump-dom")
    events = json.loads(net_log.read_text())
    start = events["constants"]["logEventTypes"]["URL_REQUEST_START_JOB"]
    return [
        e["params"]["url"]
        for e in events["events"]
        if e["type"] == start and e.get("params", {}).get("initiator") not in (None, "not an origin")
    ]


class _Keys(HTMLParser):
    """``data-key`` -> text, and the ids of the sections, from the rendered DOM."""

    def __init__(self) -> None:
        super().__init__()
        self.keys: dict[str, str] = {}
        self.sections: list[str] = []
        self._open: str | None = None

    def handle_starttag(self, tag: str, attrs: list[tuple[str, str | None]]) -> None:
        values = dict(attrs)
        if tag == "section" and values.get("id"):
            self.sections.append(str(values["id"]))
        self._open = values.get("data-key") or self._open

    def handle_data(self, data: str) -> None:
        if self._open and data.strip():
            self.keys[self._open] = data.strip()
            self._open = None


def test_the_page_opens_offline_with_every_section_and_key_figure(
    reported: tuple[Path, Path, dict[str, object]], tmp_path: Path
) -> None:
    _, page, export = reported
    html = page.read_text()
    assert "<script" not in html and not re.search(r"""(src|href)=["']?(https?:)?//""", html)
    dom = _Keys()
    dom.feed(_chromium(page, "--dump-dom"))
    assert dom.sections == ["verdict", *SECTIONS]
    assert dom.keys["verdict"] == "PASS" and dom.keys["check-numerics, float32"] == "yes"
    m4 = export["targets"]["cortex-m4"]  # type: ignore[index]
    assert dom.keys["sample-time-s"] == "0.3"
    assert dom.keys["stack-bound-cortex-m4"] == str(m4["stack_bound"]["bytes"])
    assert dom.keys["stack-painted-cortex-m4"] == str(m4["stack_bytes"])
    assert dom.keys["node-stack-bound-cortex-m4"] == str(m4["node_firmware"]["stack_bound"]["bytes"])
    assert dom.keys["instructions-cortex-m4"] == f"{round(m4['instructions_per_inference']):,}"
    assert dom.keys["misra-unexplained"] == "0" and int(dom.keys["misra-findings"]) > 0
    assert dom.keys["misra-configurations"] == "host, cortex-m4"  # the target's code is analysed too
    assert dom.keys["chain-intact"] == "intact"
    assert dom.keys["check-coverage"] == "yes" and dom.keys["coverage-policy.c-lines"] == "86/86 (100%)"
    assert dom.keys["coverage-policy.c-branches"] == "44/44 (100%)"
    assert float(dom.keys["max-error-float32"]) <= 1e-5
    _assert_sign_off_figures(dom.keys, page.parent.parent / "export dir", export)
    assert page_requests(page, tmp_path / "net.json") == []
    _chromium(page, f"--screenshot={SCREENSHOT}", "--window-size=1280,12000", "--hide-scrollbars")
    assert SCREENSHOT.stat().st_size > 100_000  # a page of tables and figures, not a blank one


def _assert_sign_off_figures(keys: dict[str, str], export_dir: Path, export: dict[str, object]) -> None:
    """Measurement conditions, the layer table, the entry points, MISRA by line and the verdict's resource
    and stack lines, each against its own oracle."""
    import onnx
    from onnx import numpy_helper

    m4 = export["targets"]["cortex-m4"]  # type: ignore[index]
    assert keys["compiler-host"] == export["compiler"]["version"]  # type: ignore[index]
    assert (
        keys["compiler-cortex-m4"] == m4["compiler"]["version"]
        and "arm-none-eabi-gcc" in m4["compiler"]["command"]
    )
    assert keys["embedrl-version"] == export["tool"]
    from embedrl.common import source_commit

    commit = r"[0-9a-f]{40}( \+ modified files)?" if source_commit() else "not recorded"  # a git checkout?
    assert re.fullmatch(commit, keys["commit-0"])  # the export's
    model = onnx.load(export_dir / "policy.onnx")
    weights = {i.name: numpy_helper.to_array(i) for i in model.graph.initializer}
    gemm_macs = sum(weights[n.input[1]].size for n in model.graph.node if n.op_type == "Gemm")
    assert keys["layers-macs"] == f"{gemm_macs:,}"
    header = re.search(r"weights: (\d+) bytes", (export_dir / "c" / "policy.h").read_text())
    assert header and keys["layers-weight-bytes"] == f"{int(header.group(1)):,}"
    assert keys["layers-header-agrees"] == "agrees"
    assert keys["entry-policy_step"].startswith("int32_t policy_step(const float obs[POLICY_OBS_DIM]")
    assert keys["entry-node_init"].startswith("void node_init(")
    per_rule = [int(v) for k, v in keys.items() if k.startswith("misra-at-")]
    assert len(per_rule) > 5 and sum(per_rule) == int(keys["misra-findings"])
    assert keys["cycle-model-flash-wait-states"].startswith("not in the model")
    assert keys["clock-mhz-cortex-m4"] == f"{m4['clock']['hz'] / 1e6:.4g}"
    assert keys["check-resources within the part, cortex-m4"] == "yes"
    assert keys["check-stack bound, cortex-m4"] == "yes"


def test_the_entry_points_are_every_public_function_in_call_order(
    reported: tuple[Path, Path, dict[str, object]],
) -> None:
    from embedrl.hil.signoff.conditions import entry_points

    export, _, _ = reported
    rows = entry_points(export, "policy")
    assert [r["function"] for r in rows if r["when"] is None] == []  # each one described
    order = [r["function"] for r in rows]
    assert order.index("node_init") < order.index("node_poll") < order.index("node_on_frame")
    assert order.index("policy_reset") < order.index("policy_step")
    assert {"node_link_lost", "node_receive_ids"} <= set(order)
    assert "policy_step_batch" not in order  # host-only: c/policy_host.h, not in the deployed program


def test_an_image_larger_than_the_part_fails_the_report(
    reported: tuple[Path, Path, dict[str, object]],
    tmp_path: Path,
    capsys: pytest.CaptureFixture[str],
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    """The part's memory comes from the target table: an image that no longer fits it is a FAIL line."""
    import dataclasses

    from embedrl.export.target import TARGETS
    from embedrl.hil.signoff import checks

    export, _, _ = reported
    small = dataclasses.replace(TARGETS["cortex-m4"], flash_kib=32, ram_kib=8)
    monkeypatch.setattr(checks, "TARGETS", {**TARGETS, "cortex-m4": small})
    capsys.readouterr()
    assert main(["report", str(export), "--out", str(tmp_path / "page.html")]) == 1
    out = capsys.readouterr().out
    line = next(x for x in out.splitlines() if "resources within the part, cortex-m4" in x)
    assert (
        line.startswith("  FAIL") and "node.elf's flash" in line and "exceed the part's 32 KiB flash" in line
    )
    assert "  PASS  stack bound, cortex-m4" in out and out.rstrip().endswith("verdict: FAIL")


def test_a_painted_stack_above_its_static_bound_fails_the_report(
    reported: tuple[Path, Path, dict[str, object]], tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """A bound below what was measured is no bound: the report says FAIL and exits 1 (the edit re-hashed
    into the chain, so only the stack line fails)."""
    from embedrl.common import sha256

    export, _, data = reported
    copy = tmp_path / "copy"
    shutil.copytree(export, copy)
    bound = data["targets"]["cortex-m4"]["stack_bound"]["bytes"]  # type: ignore[index]
    report = copy / "export_report.json"
    old = sha256(report)
    edited = json.loads(report.read_text())
    edited["targets"]["cortex-m4"]["stack_bytes"] = bound + 1
    report.write_text(json.dumps(edited, indent=2) + "\n")
    manifest = copy / "chain.json"
    manifest.write_text(manifest.read_text().replace(old, sha256(report)))
    capsys.readouterr()
    assert main(["report", str(copy), "--out", str(tmp_path / "page.html")]) == 1
    out = capsys.readouterr().out
    assert (
        f"  FAIL  stack bound, cortex-m4: policy_step painted {bound + 1} B above its bound {bound} B" in out
    )
    assert "  PASS  traceability chain" in out and out.rstrip().endswith("verdict: FAIL")


def test_the_fetch_check_sees_a_page_that_fetches(tmp_path: Path) -> None:
    """The control: a page with a remote image and style sheet is caught."""
    page = tmp_path / "fetching.html"
    page.write_text('<html><body><img src="http://127.0.0.1:9/x.png"><link rel="stylesheet" '
                    'href="https://example.com/a.css"></body></html>')  # fmt: skip
    assert sorted(page_requests(page, tmp_path / "net.json")) == [
        "http://127.0.0.1:9/x.png", "https://example.com/a.css"
    ]  # fmt: skip


def test_a_hil_report_of_another_export_or_a_folder_that_is_no_export_is_refused(
    reported: tuple[Path, Path, dict[str, object]], tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    export, _, _ = reported
    other = tmp_path / "other.json"
    data = json.loads(next(export.parent.glob("*.json")).read_text())
    data["export_files"]["c/policy.c"] = "0" * 64
    other.write_text(json.dumps(data))
    out = tmp_path / "r.html"
    assert main(["report", str(export), "--hil", str(other), "--out", str(out)]) == 2
    assert "was made on another export: its c/policy.c differs" in capsys.readouterr().err
    assert main(["report", str(tmp_path), "--out", str(out)]) == 2
    err = capsys.readouterr().err.strip()
    assert "not an `embedrl export` folder" in err and len(err.splitlines()) == 1
    assert not out.exists()


def _copy_with_c_edit(export: Path, tmp_path: Path, edit: str) -> Path:
    """A copy of ``export`` whose c/policy.c got ``edit`` appended, its new hash put consistently into
    chain.json and export_report.json (as someone rewriting the evidence would)."""
    from embedrl.common import sha256

    copy = tmp_path / "copy of export"
    shutil.copytree(export, copy)
    source = copy / "c" / "policy.c"
    old = sha256(source)
    source.write_text(source.read_text() + edit)
    report = copy / "export_report.json"
    report.write_text(report.read_text().replace(old, sha256(source)))
    manifest = copy / "chain.json"
    manifest.write_text(manifest.read_text().replace(old, sha256(source)))
    return copy


def test_the_report_never_builds_or_runs_c_that_is_not_the_generators(
    reported: tuple[Path, Path, dict[str, object]], tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    export, _, _ = reported
    marker = tmp_path / "ran on the host"
    payload = (
        "\n#include <stdio.h>\n__attribute__((constructor)) static void payload(void)\n{\n"
        f'    FILE *f = fopen("{marker}", "w");\n    if (f != NULL) {{\n        (void)fclose(f);\n    }}\n'
        "}\n"
    )
    copy = _copy_with_c_edit(export, tmp_path, payload)
    page = tmp_path / "page.html"
    assert main(["report", str(copy), "--out", str(page)]) == 1
    out = capsys.readouterr().out
    assert not marker.exists()
    assert "FAIL  numerics, float32: not recomputed: " in out and "is not what embedrl generates" in out
    assert out.rstrip().endswith("verdict: FAIL") and page.is_file()  # the page is written, with its FAIL
    assert '<span class="fail">FAIL</span>' in page.read_text()


def test_a_weight_edit_rewritten_into_every_manifest_fails_the_report(
    reported: tuple[Path, Path, dict[str, object]], tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    export, _, _ = reported
    copy = _copy_with_c_edit(export, tmp_path, "")
    source = copy / "c" / "policy.c"
    text = source.read_text()
    start = text.index("static const float")
    weight = text[start:].split("{", 1)[1].split(",", 1)[0].strip()
    source.write_text(text[:start] + text[start:].replace(weight, "0.5f", 1))
    from embedrl.common import sha256

    for record in ("chain.json", "export_report.json"):
        path = copy / record
        path.write_text(path.read_text().replace(sha256(export / "c" / "policy.c"), sha256(source)))
    capsys.readouterr()
    assert main(["report", str(copy), "--out", str(tmp_path / "page.html")]) == 1
    out = capsys.readouterr().out
    assert "FAIL  numerics, float32: not recomputed" in out and "verdict: FAIL" in out


def test_the_hil_report_is_kept_in_the_bundle_so_a_moved_copy_verifies_and_names_an_edit(
    reported: tuple[Path, Path, dict[str, object]], tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """The HIL report was written outside the export folder: the bundle keeps a copy in hil/, links that,
    and the page says the chain is unsigned."""
    from embedrl.export import chain

    export, page, _ = reported
    kept = export / "hil" / "hil run.json"
    assert kept.read_bytes() == (export.parent / "hil run.json").read_bytes()
    link = chain.read(export)[-1]
    assert (link.name, link.path, link.in_bundle) == ("HIL report hil/hil run.json", "hil/hil run.json", True)
    html = page.read_text()
    assert 'data-key="signature">not signed (no chain.dsse.json)' in html
    assert 'data-key="check-signature"' not in html  # a warning, not a line of the verdict
    assert 'class="warn" data-key="warning-1">signature: not signed' in html
    moved = tmp_path / "moved" / "bundle"
    shutil.copytree(export, tmp_path / "copy")
    moved.parent.mkdir()
    shutil.move(tmp_path / "copy", moved)
    assert main(["verify-chain", str(moved)]) == 0
    copied_report = moved / "hil" / "hil run.json"
    copied_report.write_text(copied_report.read_text().replace('"episodes": 2', '"episodes": 3'))
    capsys.readouterr()
    assert main(["verify-chain", str(moved)]) == 1
    said = capsys.readouterr().out
    assert "HIL report hil/hil run.json: hil/hil run.json changed: sha256" in said


def test_a_hil_report_from_elsewhere_whose_name_is_taken_in_the_bundle_is_refused(
    reported: tuple[Path, Path, dict[str, object]], tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    export, _, _ = reported
    other = tmp_path / "hil run.json"
    data = json.loads((export / "hil" / "hil run.json").read_text())
    data["mean_return"] += 1.0  # another report of the same run (its counts still add up)
    other.write_text(json.dumps(data))
    out = tmp_path / "r.html"
    assert main(["report", str(export), "--hil", str(other), "--out", str(out)]) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and "holds another file (rename one of them)" in err
    assert not out.exists()


def _key_pair(folder: Path, name: str) -> tuple[Path, Path]:
    from cryptography.hazmat.primitives import serialization
    from cryptography.hazmat.primitives.asymmetric import ed25519

    key = ed25519.Ed25519PrivateKey.generate()
    private, public = folder / f"{name}.pem", folder / f"{name}.pub.pem"
    pem = serialization.Encoding.PEM
    pkcs8 = serialization.PrivateFormat.PKCS8
    private.write_bytes(key.private_bytes(pem, pkcs8, serialization.NoEncryption()))
    public.write_bytes(key.public_key().public_bytes(pem, serialization.PublicFormat.SubjectPublicKeyInfo))
    return private, public


def test_the_report_signs_the_chain_and_its_verdict_checks_the_signature(
    reported: tuple[Path, Path, dict[str, object]], tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    export, _, _ = reported
    copy = tmp_path / "signed export"
    shutil.copytree(export, copy)
    ours, _ = _key_pair(tmp_path, "ours")
    _, theirs = _key_pair(tmp_path, "theirs")
    capsys.readouterr()
    hil = ["--hil", str(copy / "hil" / "hil run.json")]
    assert main(["report", str(copy), *hil, "--out", str(tmp_path / "a.html"), "--sign", str(ours)]) == 0
    out = capsys.readouterr().out
    assert re.search(r"PASS  signature: signed by key [0-9a-f]{16}\.\.\. and valid", out), out
    assert main(["report", str(copy), *hil, "--out", str(tmp_path / "b.html"), "--key", str(theirs)]) == 1
    out = capsys.readouterr().out
    assert "FAIL  signature: signed by key" in out and "not by the key given" in out
    assert out.rstrip().endswith("verdict: FAIL")
