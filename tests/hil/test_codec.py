"""The Python side of the CAN contract: E2E as the C node does it, codec from the same generated DBC."""

from __future__ import annotations

import re
import subprocess
from pathlib import Path

import can
import numpy as np
import pytest
from crccheck.crc import Crc8SaeJ1850

from embedrl.export.build import RUNTIME_C
from embedrl.export.contract import e2e as e2e_params
from embedrl.hil import e2e
from embedrl.hil.codec import Action, Codec, Status, decode_fields
from embedrl.train.scenarios import STATIC


def test_crc8_reference_vector_matches_the_c_node() -> None:
    # CRC-8 SAE J1850 of "123456789" is 0x4B; the C unit tests check the same vector.
    assert e2e.crc8(ord("1") | ord("2") << 8, b"\x003456789") == 0x4B


@pytest.mark.parametrize("length", [2, 8, 64])
def test_crc8_equals_a_library_crc8_sae_j1850_over_the_data_id_and_payload(length: int) -> None:
    rng = np.random.default_rng(length)
    for _ in range(200):
        data_id = int(rng.integers(0, 0x800))
        data = bytes(rng.integers(0, 256, length, dtype=np.uint8))
        oracle = Crc8SaeJ1850.calc(bytes([data_id & 0xFF, data_id >> 8]) + data[1:])
        assert e2e.crc8(data_id, data) == oracle


def test_the_c_node_takes_its_e2e_constants_from_the_generated_header() -> None:
    generated = dict(
        (name, int(value.rstrip("u"), 16))
        for name, value in re.findall(r"#define E2E_(\w+) (0x[0-9A-F]+u)", e2e_params.params_header())
    )
    assert generated == {
        "CRC8_POLY": e2e_params.CRC8_POLY, "CRC8_INIT": e2e_params.CRC8_INIT,
        "CRC8_XOR_OUT": e2e_params.CRC8_XOR_OUT, "COUNTER_MODULO": e2e_params.COUNTER_MODULO,
        "MAX_FORWARD_JUMP": e2e_params.MAX_FORWARD_JUMP, "RESYNC_FRAMES": e2e_params.RESYNC_FRAMES,
    }  # fmt: skip
    assert (
        Crc8SaeJ1850._poly,
        Crc8SaeJ1850._initvalue,
        Crc8SaeJ1850._xor_output,
    ) == (e2e_params.CRC8_POLY, e2e_params.CRC8_INIT, e2e_params.CRC8_XOR_OUT)
    for source in ("e2e.h", "e2e.c", "node.c", "node.h"):  # typed nowhere else
        text = (RUNTIME_C / "node" / source).read_text()
        assert not re.search(r"#define\s+\w*(POLY|COUNTER_MODULO|FORWARD_JUMP|RESYNC_FRAMES)\b", text), source


def test_receiver_accepts_increments_and_rejects_repeats_and_old_frames() -> None:
    rx = e2e.Receiver()
    assert [rx.check(c) for c in (5, 6, 6, 4, 9, 10, 15, 0)] == [
        "ok",
        "ok",
        "repeated",
        "wrong_sequence",
        "lost",
        "ok",
        "lost",
        "ok",
    ]


def test_receiver_resynchronises_on_two_consecutive_counters_outside_its_window() -> None:
    rx = e2e.Receiver()
    # 9 frames lost after 3 (the next is 13): dropped, then the second consecutive counter resyncs
    assert [rx.check(c) for c in (3, 13, 14, 15, 0)] == ["ok", "wrong_sequence", "resync", "ok", "ok"]
    # an isolated old frame (9) never moves the sequence
    assert [rx.check(c) for c in (9, 1)] == ["wrong_sequence", "ok"]
    # a sender restarted from 0, 11 behind: its second frame resyncs
    rx = e2e.Receiver(last=5)
    assert [rx.check(c) for c in (0, 1, 2)] == ["wrong_sequence", "resync", "ok"]
    # counters that are not consecutive never resync
    rx = e2e.Receiver(last=5)
    assert [rx.check(c) for c in (14, 2, 15, 0)] == ["wrong_sequence"] * 3 + ["resync"]


def test_observation_frames_round_trip_within_the_signal_resolution() -> None:
    codec = Codec(STATIC)
    obs = np.array([-1.7, 1.25, -0.6, 0.8, -0.69, 1.99], dtype=np.float32)
    frames, decoded = codec.encode_observation(obs, step=4097)
    assert [f.arbitration_id for f in frames] == [0x100, 0x101, 0x102]
    assert all(len(f.data) == 8 and e2e.crc_ok(f.arbitration_id, bytes(f.data)) for f in frames)
    np.testing.assert_allclose(decoded, obs, atol=4e-6)
    steps = [
        decode_fields(codec.db.get_message_by_frame_id(f.arbitration_id), bytes(f.data))["Step"]
        for f in frames
    ]
    assert steps == [1, 1, 1]  # 4097 mod 4096, the same in every part


def _frame(codec: Codec, name: str, fields: dict[str, float]) -> can.Message:
    message = codec.db.get_message_by_name(name)
    data = e2e.protect(message.frame_id, message.encode({"Crc": 0, **fields}))
    return can.Message(arbitration_id=message.frame_id, data=data, is_extended_id=False)


def test_actions_and_status_are_decoded_only_when_e2e_valid() -> None:
    codec = Codec(STATIC)
    good = _frame(codec, "Action", {"Counter": 0, "Step": 12, "ForceLeft": 0.5, "ForceRight": -1.0})
    decoded = codec.decode(good)
    assert isinstance(decoded, Action) and decoded.step == 12
    np.testing.assert_allclose(decoded.action, [0.5, -1.0], atol=4e-6)
    assert codec.decode(good) is None and codec.sequence_errors == 1  # repeated counter
    bad = _frame(codec, "Action", {"Counter": 1, "Step": 13, "ForceLeft": 0.5, "ForceRight": 0.5})
    bad.data = bytearray(bad.data)
    bad.data[6] ^= 0x01
    assert codec.decode(bad) is None and codec.crc_errors == 1
    status = _frame(
        codec,
        "NodeStatus",
        {
            "Counter": 3,
            "State": 1,
            "FramesOk": 9,
            "CrcErrors": 2,
            "SequenceErrors": 0,
            "Timeouts": 1,
            "InferenceUs": 17,
        },
    )
    s = codec.decode(status)
    assert isinstance(s, Status) and s.state == "SAFE" and s.crc_errors == 2 and s.inference_us == 17
    assert codec.decode(can.Message(arbitration_id=0x7FF, data=bytes(8), is_extended_id=False)) is None


@pytest.mark.parametrize("target", ["test", "asan"])
def test_c_unit_tests_pass(target: str, tmp_path: Path) -> None:
    """The node's C unit tests (fake transport), plain and under AddressSanitizer + UBSan."""
    result = subprocess.run(
        ["make", "-s", "-C", str(RUNTIME_C), target, f"BUILD_DIR={tmp_path}"],
        capture_output=True,
        text=True,
    )
    assert result.returncode == 0, result.stdout + result.stderr
    assert "0 failures" in result.stdout


FUZZ_SECONDS = 15
"""A bounded libFuzzer run in the suite; docs/safety.md quotes a longer one."""


@pytest.mark.slow
def test_the_node_survives_a_bounded_fuzzing_run_with_its_invariants(tmp_path: Path) -> None:
    """libFuzzer + ASan + UBSan over the receive path from the committed seed corpus; the harness aborts
    on an action from a partial or mixed observation, a SAFE action that is not the safe action, or a
    late watchdog (runtime_c/tests/fuzz_node.c)."""
    corpus = RUNTIME_C / "tests" / "fuzz_corpus"
    before = sorted(p.read_bytes() for p in corpus.iterdir())
    result = subprocess.run(
        ["make", "-s", "-C", str(RUNTIME_C), "fuzz", f"BUILD_DIR={tmp_path}", f"FUZZ_SECONDS={FUZZ_SECONDS}"],
        capture_output=True,
        text=True,
        timeout=600,
    )  # fmt: skip
    log = result.stdout + result.stderr
    assert result.returncode == 0, log[-3000:]
    runs = int(log.split("stat::number_of_executed_units:")[1].split()[0])
    assert runs >= 10_000, log[-2000:]  # it really ran (about 30,000 runs/s here)
    assert "ERROR:" not in log and "runtime error" not in log
    assert sorted(p.read_bytes() for p in corpus.iterdir()) == before  # new inputs go to the build folder
