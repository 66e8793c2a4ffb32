"""The traceability chain: every link of an export (run config -> model -> ONNX -> C -> binaries ->
reports) hashed; ``embedrl verify-chain`` names the first link a one-byte change broke."""

from __future__ import annotations

import json
import multiprocessing
import shutil
from collections.abc import Callable
from concurrent.futures import ProcessPoolExecutor
from dataclasses import asdict
from pathlib import Path
from typing import Any

import pytest

from embedrl.cli import main
from embedrl.common import sha256
from embedrl.export import chain
from embedrl.hil.run import add_to_chain
from tests.conftest import marks_its_users

SHIPPED = Path(__file__).resolve().parents[2] / "policies" / "static"


@pytest.fixture(scope="module")
@marks_its_users("qemu")  # the export runs the M4 firmware on QEMU
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
    """A copy of the export folder alone: the bundle travels without the policy it was made from."""
    shutil.copytree(traced / "export", tmp_path / "export")
    return tmp_path / "export"


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
    assert len(out) == len(links) + 2 and all(line.startswith("ok ") for line in out[:-2])
    assert out[-2] == (
        f"chain intact: {len(links)} links, from run config to verification report (1 outside the bundle, "
        "digest only)"
    )
    assert out[-1].startswith("warning: signature: not signed (no chain.dsse.json)")


def test_every_path_is_in_the_bundle_and_the_manifest_is_an_in_toto_statement(traced: Path) -> None:
    """The run configuration is copied into provenance/; the model is named by its digest only."""
    export = traced / "export"
    text = (export / chain.MANIFEST).read_text()
    assert str(traced) not in text
    data = json.loads(text)
    assert data["_type"] == "https://in-toto.io/Statement/v1"
    assert data["predicateType"] == chain.PREDICATE_TYPE
    links = {k.name: k for k in chain.read(export)}
    assert links["run config"].path == "provenance/td3.json"
    assert (export / "provenance" / "td3.json").read_bytes() == (traced / "policy" / "td3.json").read_bytes()
    assert links["model"].path == "td3.zip" and not links["model"].in_bundle
    subjects = {s["name"]: s["digest"]["sha256"] for s in data["subject"]}
    assert subjects == {k.path: k.sha256 for k in links.values() if k.in_bundle}
    [step] = data["predicate"]["steps"]
    assert step["name"] == "export" and step["tool"].startswith("embedrl ")
    assert isinstance(step["command"], list)
    assert [i["name"] for i in step["inputs"]] == ["provenance/td3.json", "td3.zip"]
    assert {o["name"]: o["digest"]["sha256"] for o in step["outputs"]} == {
        k: v for k, v in subjects.items() if k != "provenance/td3.json"
    }


def test_a_moved_bundle_verifies(traced: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    export = _copy(traced, tmp_path / "first place")
    moved = tmp_path / "elsewhere" / "bundle"
    moved.parent.mkdir()
    shutil.move(export, moved)
    assert main(["verify-chain", str(moved)]) == 0
    assert capsys.readouterr().out.startswith("chain intact: ")


def test_a_subject_that_disagrees_with_its_link_is_named(
    traced: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """A tool reading the Statement's subjects sees the digests verify-chain checks, or verify-chain fails."""
    export = _copy(traced, tmp_path)
    manifest = export / chain.MANIFEST
    data = json.loads(manifest.read_text())
    data["subject"][1]["digest"]["sha256"] = "0" * 64
    manifest.write_text(json.dumps(data))
    assert main(["verify-chain", str(export)]) == 1
    assert "chain.json gives policy.onnx two digests: 000000000000..." in capsys.readouterr().out


@pytest.mark.parametrize("path", ["/etc/hostname", "../export/policy.onnx", "c/../../x"])
def test_a_path_out_of_the_bundle_is_refused(traced: Path, tmp_path: Path, path: str) -> None:
    export = _copy(traced, tmp_path)
    manifest = export / chain.MANIFEST
    data = json.loads(manifest.read_text())
    data["predicate"]["links"][2]["path"] = path
    manifest.write_text(json.dumps(data))
    with pytest.raises(chain.ChainError, match="is not a path inside the export folder"):
        chain.verify(export)


def test_a_manifest_of_the_old_format_is_read_with_its_outside_files_by_digest_only(
    traced: Path, tmp_path: Path
) -> None:
    export = _copy(traced, tmp_path)
    links = chain.read(export)
    old = [
        {k: v for k, v in asdict(link).items() if k != "in_bundle"}
        | ({"path": str(traced / "policy" / link.path)} if not link.in_bundle else {})
        for link in links
    ]
    (export / chain.MANIFEST).write_text(json.dumps({"format": 1, "links": old}))
    assert chain.read(export) == links
    assert all(c.ok for c in chain.verify(export))


def test_a_one_byte_change_in_any_link_is_named(
    traced: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    links = chain.read(traced / "export")
    for number, k in enumerate(links, 1):
        if not k.in_bundle:
            continue  # the model: not in the bundle, its digest checked against the files that record it
        export = _copy(traced, tmp_path / str(number))
        _flip_one_byte(export / k.path)
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
    assert last.name == "HIL report hil/hil report.json" and last.facts["passed"] is True
    assert (export / "hil" / "hil report.json").read_bytes() == report.read_bytes()  # kept in the bundle
    step = chain.read_manifest(export).steps[-1]
    assert step.name == "hil run" and step.outputs == [last.name] and "interface" in step.inputs
    assert all(c.ok for c in chain.verify(export))
    data["export_files"]["c/policy.c"] = "0" * 64  # a report made on other C, re-hashed into the chain
    report.write_text(json.dumps(data))
    assert add_to_chain(export, report, data)
    failed = [c for c in chain.verify(export) if not c.ok]
    assert len(failed) == 1 and "records another c/policy.c (sha256 000000000000...)" in failed[0].detail
    assert not add_to_chain(tmp_path, report, data)  # a folder without a manifest: nothing to add to


def _hil_report(export: Path, folder: Path, log: bool) -> tuple[Path, dict[str, Any]]:
    """A HIL report on ``export`` written in ``folder``, with a frame log beside it if ``log``."""
    files = {name: sha256(export / name) for name in ("policy.onnx", "interface.json", "c/policy.c")}
    data: dict[str, Any] = {
        "verdict": {"passed": True}, "node": "c", "target": None, "episodes": 2, "export_files": files,
    }  # fmt: skip
    folder.mkdir(exist_ok=True)
    if log:
        (folder / "frames.log").write_text("(0.000000) vcan0 100#0011223344556677\n")
        data["log"] = {"file": "hil/frames.log", "sha256": sha256(folder / "frames.log")}
    (folder / "host.json").write_text(json.dumps(data))
    return folder / "host.json", data


def test_a_hil_run_s_frame_log_is_kept_in_the_bundle_and_checked(traced: Path, tmp_path: Path) -> None:
    export = _copy(traced, tmp_path)
    report, data = _hil_report(export, tmp_path / "elsewhere", log=True)
    assert add_to_chain(export, report, data, tmp_path / "elsewhere" / "frames.log")
    names = [k.name for k in chain.read(export)]
    assert names[-2:] == ["HIL log hil/frames.log", "HIL report hil/host.json"]
    assert chain.read_manifest(export).steps[-1].outputs == names[-1:] + names[-2:-1]
    assert all(c.ok for c in chain.verify(export))
    (export / "hil" / "frames.log").write_text("(0.000000) vcan0 100#FF11223344556677\n")
    [failed] = [c for c in chain.verify(export) if not c.ok]
    assert failed.link.name == "HIL log hil/frames.log" and "changed: sha256" in failed.detail


def test_the_report_gathers_a_hil_report_and_its_log_from_elsewhere_into_the_bundle(
    traced: Path, tmp_path: Path
) -> None:
    from embedrl.hil.errors import HilError
    from embedrl.hil.signoff import bundle

    export = _copy(traced, tmp_path)
    report, _ = _hil_report(export, tmp_path / "elsewhere", log=True)
    assert bundle.gather(export, [report]) == [export / "hil" / "host.json"]
    kept = export / "hil" / "frames.log"
    assert kept.read_bytes() == (tmp_path / "elsewhere" / "frames.log").read_bytes()
    links = {k.name: k for k in chain.read(export)}
    assert {"HIL report hil/host.json", "HIL log hil/frames.log"} <= set(links)
    assert all(c.ok for c in chain.verify(export))
    assert bundle.gather(export, [report]) == [export / "hil" / "host.json"]  # again: nothing changes
    assert len(chain.read(export)) == len(links)
    lonely, _ = _hil_report(export, tmp_path / "no log here", log=True)
    (tmp_path / "no log here" / "frames.log").unlink()
    (export / "hil" / "frames.log").unlink()
    said = r"the frame log it records, frames.log \(sha256 [0-9a-f]{12}\.\.\.\), is not beside it"
    with pytest.raises(HilError, match=said):
        bundle.gather(export, [lonely])


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
    chain.write(tmp_path, [chain.link(tmp_path, "interface", tmp_path / "interface.json", [])], [])
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


# The signature: an Ed25519 signature over chain.json, in a DSSE envelope (chain.dsse.json).


@pytest.fixture(scope="module")
def keys(tmp_path_factory: pytest.TempPathFactory) -> dict[str, Path]:
    """PEM files: a signing key and its public key, another key pair, and files that are no such key."""
    from cryptography.hazmat.primitives import serialization
    from cryptography.hazmat.primitives.asymmetric import ec, ed25519

    root = tmp_path_factory.mktemp("keys")
    pem, pkcs8 = serialization.Encoding.PEM, serialization.PrivateFormat.PKCS8
    private_format = (pem, pkcs8, serialization.NoEncryption())
    public_format = (pem, serialization.PublicFormat.SubjectPublicKeyInfo)
    ours, theirs = ed25519.Ed25519PrivateKey.generate(), ed25519.Ed25519PrivateKey.generate()
    files = {
        "private": ours.private_bytes(*private_format),
        "public": ours.public_key().public_bytes(*public_format),
        "other private": theirs.private_bytes(*private_format),
        "other public": theirs.public_key().public_bytes(*public_format),
        "ec public": ec.generate_private_key(ec.SECP256R1()).public_key().public_bytes(*public_format),
        "garbage": b"-----BEGIN PUBLIC KEY-----\nnot base64\n-----END PUBLIC KEY-----\n",
    }
    paths = {name: root / f"{name.replace(' ', '_')}.pem" for name in files}
    for name, data in files.items():
        paths[name].write_bytes(data)
    return paths


def _signed(traced: Path, tmp_path: Path, keys: dict[str, Path], key: str = "private") -> Path:
    from embedrl.export import signature

    export = _copy(traced, tmp_path)
    signature.sign(export, signature.load_private_key(keys[key]))
    return export


def test_a_signed_export_verifies_with_its_public_key(
    traced: Path, tmp_path: Path, keys: dict[str, Path], capsys: pytest.CaptureFixture[str]
) -> None:
    export = _signed(traced, tmp_path, keys)
    envelope = json.loads((export / "chain.dsse.json").read_text())
    assert envelope["payloadType"] == "application/vnd.in-toto+json"
    assert main(["verify-chain", str(export), "--key", str(keys["public"])]) == 0
    out = capsys.readouterr().out.splitlines()
    assert out[-1].startswith("signature: signed by key ") and out[-1].endswith("and valid")
    assert main(["verify-chain", str(export)]) == 0  # no key: not checked, and no key id shown as a fact
    last = capsys.readouterr().out.splitlines()[-1]
    assert last.startswith("warning: signature: signature not checked: no trusted key given")
    assert key_id_of(envelope) not in last


def key_id_of(envelope: dict[str, Any]) -> str:
    return str(envelope["signatures"][0]["keyid"][:16])


def test_a_forged_envelope_without_a_trusted_key_is_never_a_pass(
    traced: Path, tmp_path: Path, keys: dict[str, Path], capsys: pytest.CaptureFixture[str]
) -> None:
    """An envelope with a zero signature over the export's own manifest, naming the owner's key id: without
    a trusted key it is a warning that says nothing was checked; with the owner's key it fails."""
    import base64

    export = _copy(traced, tmp_path)
    owner = _signed(traced, tmp_path / "owner", keys)
    keyid = json.loads((owner / "chain.dsse.json").read_text())["signatures"][0]["keyid"]
    forged = {
        "payloadType": "application/vnd.in-toto+json",
        "payload": base64.b64encode((export / chain.MANIFEST).read_bytes()).decode(),
        "signatures": [{"keyid": keyid, "sig": base64.b64encode(bytes(64)).decode()}],
    }
    (export / "chain.dsse.json").write_text(json.dumps(forged))
    assert main(["verify-chain", str(export)]) == 0
    out = capsys.readouterr().out
    assert "warning: signature: signature not checked" in out and keyid[:16] not in out
    assert "signed by" not in out
    assert main(["verify-chain", str(export), "--key", str(keys["public"])]) == 1
    assert "FAIL signature: the signature does not match" in capsys.readouterr().out


def test_a_consistent_rewrite_of_every_manifest_fails_the_signature(
    traced: Path, tmp_path: Path, keys: dict[str, Path], capsys: pytest.CaptureFixture[str]
) -> None:
    """One weight changed, its hash rewritten into export_report.json, chain.json and the envelope's payload:
    every digest agrees, only the signature does not."""
    import base64

    export = _signed(traced, tmp_path, keys)
    source, report = export / "c" / "policy.c", export / "export_report.json"
    old_c, old_report = sha256(source), sha256(report)
    text = source.read_text()
    start = text.index("static const float")
    weight = text[start:].split("{", 1)[1].split(",", 1)[0].strip()
    source.write_text(text[:start] + text[start:].replace(weight, "0.5f", 1))
    report.write_text(report.read_text().replace(old_c, sha256(source)))
    manifest = export / chain.MANIFEST
    rewritten = manifest.read_text().replace(old_c, sha256(source)).replace(old_report, sha256(report))
    manifest.write_text(rewritten)
    envelope_file = export / "chain.dsse.json"
    envelope = json.loads(envelope_file.read_text())
    envelope["payload"] = base64.b64encode(manifest.read_bytes()).decode()
    envelope_file.write_text(json.dumps(envelope))
    assert all(c.ok for c in chain.verify(export))  # the rewrite is consistent
    assert main(["verify-chain", str(export), "--key", str(keys["public"])]) == 1
    out = capsys.readouterr().out
    assert "FAIL signature: the signature does not match chain.json: rewritten since it was signed" in out


def test_a_signature_by_another_key_fails(
    traced: Path, tmp_path: Path, keys: dict[str, Path], capsys: pytest.CaptureFixture[str]
) -> None:
    export = _signed(traced, tmp_path, keys, key="other private")  # re-signed by whoever rewrote it
    assert main(["verify-chain", str(export), "--key", str(keys["public"])]) == 1
    assert "not by the key given" in capsys.readouterr().out


def test_a_link_appended_after_signing_breaks_the_signature_even_without_a_key(
    traced: Path, tmp_path: Path, keys: dict[str, Path], capsys: pytest.CaptureFixture[str]
) -> None:
    export = _signed(traced, tmp_path, keys)
    _append_reports(export, 0, 1)
    assert main(["verify-chain", str(export)]) == 1
    assert "FAIL signature: chain.json changed since it was signed" in capsys.readouterr().out


def test_unsigned_says_so_and_fails_when_a_key_was_given(
    traced: Path, tmp_path: Path, keys: dict[str, Path], capsys: pytest.CaptureFixture[str]
) -> None:
    export = _copy(traced, tmp_path)
    assert main(["verify-chain", str(export)]) == 0
    assert (
        capsys.readouterr()
        .out.splitlines()[-1]
        .startswith("warning: signature: not signed (no chain.dsse.json)")
    )
    assert main(["verify-chain", str(export), "--key", str(keys["public"])]) == 1
    assert "FAIL signature: unsigned (no chain.dsse.json), but a key was given" in capsys.readouterr().out


@pytest.mark.parametrize("bad", ["private", "ec public", "garbage", "missing", "/dev/zero", "folder"])
def test_a_bad_key_file_is_refused_in_one_line(
    traced: Path, tmp_path: Path, keys: dict[str, Path], capsys: pytest.CaptureFixture[str], bad: str
) -> None:
    """Key files are untrusted input: one line, exit 2, for verify-chain --key and export --sign (before any
    work: no export folder is made)."""
    key = {"missing": tmp_path / "nothing.pem", "/dev/zero": Path("/dev/zero"), "folder": tmp_path}.get(bad)
    key = key or keys[bad]
    assert main(["verify-chain", str(traced / "export"), "--key", str(key)]) == 2
    err = capsys.readouterr().err.strip()
    assert err.startswith(f"error: --key {key}: ") or err.startswith(f"error: {key}: "), err
    assert len(err.splitlines()) == 1
    out = tmp_path / "not made"
    sign = keys["public"] if bad == "private" else key  # a public key where the private one is wanted
    argv = ["export", str(traced / "policy" / "td3.zip"), "--out", str(out), "--sign", str(sign)]
    assert main(argv) == 2 and not out.exists()
    err = capsys.readouterr().err.strip()
    assert err.startswith("error: ") and len(err.splitlines()) == 1


def _rewrite_without(export: Path, keep: Callable[[chain.TraceLink], bool]) -> None:
    """chain.json written again with only the links ``keep`` accepts (its steps dropped with them)."""
    manifest = chain.read_manifest(export)
    chain.write(export, [k for k in manifest.links if keep(k)], [])


def test_a_dropped_link_of_an_edited_file_is_named(
    traced: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """The C's link removed from the manifest and the C edited: the chain no longer covers c/policy.c."""
    export = _copy(traced, tmp_path)
    _rewrite_without(export, lambda k: k.path != "c/policy.c")
    source = export / "c" / "policy.c"
    source.write_text(source.read_text() + "\n/* edited */\n")
    assert main(["verify-chain", str(export)]) == 1
    assert "records c/policy.c, which the chain does not link" in capsys.readouterr().out
    assert dict(chain.layout(export, chain.read(export)))["c/policy.c"].endswith(
        "no link of the chain covers it"
    )


def test_a_chain_cut_to_its_first_link_is_named(
    traced: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    export = _copy(traced, tmp_path)
    first = chain.read(export)[0]
    _rewrite_without(export, lambda k: k.name == first.name)
    assert main(["verify-chain", str(export)]) == 1
    out = capsys.readouterr().out
    assert "the chain has no 'ONNX' link" in out, out
    problems = dict(chain.layout(export, chain.read(export)))
    assert {
        "ONNX",
        "verification report",
        "C source",
        "binary host/",
        "export_report.json",
    } <= problems.keys()
    assert any(p.startswith("bin/cortex-m4/") for p in problems)  # the target's images too


def test_a_report_that_records_a_file_the_chain_does_not_link_is_named(
    traced: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """The verification report's record of a file stands only beside the chain's own link of that file."""
    export = _copy(traced, tmp_path)
    _rewrite_without(export, lambda k: k.path != "test/test_vectors.c")
    (export / "test" / "test_vectors.c").unlink()  # so the layout's own rule does not name it first
    assert main(["verify-chain", str(export)]) == 1
    assert "records test/test_vectors.c, which the chain does not link" in capsys.readouterr().out
