"""The CAN database is generated from the interface: golden file, today's logs, scales, any shape."""

from __future__ import annotations

import json
import math
from pathlib import Path

import can
import numpy as np
import pytest

from embedrl.hil import candb
from embedrl.hil.codec import Action, Codec
from embedrl.hil.errors import HilError
from embedrl.train.interface import Field, Interface
from embedrl.train.scenarios import STATIC

GOLDEN = Path(__file__).parent / "golden"
SHIPPED_DBC = Path(candb.__file__).with_name("policy.dbc")


def test_the_shipped_dbc_is_the_generated_one(request: pytest.FixtureRequest) -> None:
    text = candb.dbc_text(STATIC)
    if request.config.getoption("--regen-golden"):
        SHIPPED_DBC.write_bytes(text.encode())
    assert SHIPPED_DBC.read_bytes() == text.encode(), (
        "hil/policy.dbc is generated: --regen-golden rewrites it"
    )


README = Path(__file__).resolve().parents[2] / "README.md"
TABLE_START, TABLE_END = (
    "<!-- can-table static: python -m embedrl.hil.candb --scenario static --markdown -->",
    ("<!-- /can-table -->"),
)


def test_the_readmes_can_table_is_the_generated_one(request: pytest.FixtureRequest) -> None:
    text = README.read_text()
    before, rest = text.split(TABLE_START + "\n", 1)
    table, after = rest.split(TABLE_END, 1)
    generated = candb.markdown_table(STATIC)
    if request.config.getoption("--regen-golden"):
        README.write_text(before + TABLE_START + "\n" + generated + TABLE_END + after)
        table = generated
    assert table == generated, "the README's CAN table is generated: --regen-golden rewrites it"


def test_the_generated_database_decodes_recorded_logs_as_the_hand_written_one_did() -> None:
    # frames_static.log: 120 frames of a HIL run with the hand-written DBC this generator replaced;
    # frames_static_decoded.json: every frame's signals as that DBC decoded them.
    db = candb.database(STATIC)
    expected = json.loads((GOLDEN / "frames_static_decoded.json").read_text())
    frames = list(can.LogReader(str(GOLDEN / "frames_static.log")))
    assert len(frames) == len(expected) == 120
    for frame, row in zip(frames, expected, strict=True):
        message = db.get_message_by_frame_id(frame.arbitration_id)
        assert message.name == row["message"]
        assert message.decode(bytes(frame.data), decode_choices=False) == row["signals"]


def test_scales_are_powers_of_two_that_cover_each_range() -> None:
    for slot in candb.layout(STATIC).observation_slots + candb.layout(STATIC).action_slots:
        assert math.log2(slot.scale).is_integer()
        reach = slot.scale * 2 ** (candb.VALUE_BITS - 1)
        assert reach > max(abs(slot.field.low), abs(slot.field.high))
        assert slot.scale / 2 < 1e-5  # the rounding error stays below the verification tolerance
    assert [s.scale for s in candb.layout(STATIC).observation_slots] == [2**-18] * 5 + [2**-17]


def test_the_dbc_carries_ranges_timing_and_descriptions() -> None:
    db = candb.database(STATIC)
    y = db.get_message_by_name("ObservationA").get_signal_by_name("Y")
    assert (y.minimum, y.maximum, y.unit, y.comment) == (-0.15, 1.3, "m", "y, position across the shelves")
    assert db.get_message_by_name("NodeStatus").cycle_time == candb.STATUS_PERIOD_MS


def _wide() -> Interface:
    """Seven observations (four frames) and three actions (two frames)."""
    obs = tuple(Field(f"o{i}", f"o{i}", -(i + 1.0), i + 1.0) for i in range(7))
    act = tuple(Field(f"a{i}", f"a{i}", -1.0, 1.0) for i in range(3))
    return Interface("wide", "Wide-v0", obs, act, 0.1, (0.0, 0.5, -0.5), 100)


def test_any_number_of_fields_is_split_over_frames_and_decoded_back() -> None:
    wide = _wide()
    plan = candb.layout(wide)
    assert [name for name, _, _ in plan.observation] == [f"Observation{c}" for c in "ABCD"]
    assert [fid for _, fid, _ in plan.action] == [0x200, 0x201]
    codec = Codec(wide)
    obs = np.linspace(-0.9, 6.9, 7).astype(np.float32)
    frames, decoded = codec.encode_observation(obs, 5)
    assert len(frames) == 4
    np.testing.assert_allclose(decoded, obs, atol=2**-14)
    db = candb.database(wide)
    parts = []
    for name, values in (("ActionA", {"A0": 0.25, "A1": -0.75}), ("ActionB", {"A2": 1.0})):
        message = db.get_message_by_name(name)
        data = candb_frame(message, {"Counter": 0, "Step": 5, **values})
        parts.append(can.Message(arbitration_id=message.frame_id, data=data, is_extended_id=False))
    assert codec.decode(parts[0]) is None  # half an action is not an action
    action = codec.decode(parts[1])
    assert isinstance(action, Action) and action.step == 5
    np.testing.assert_allclose(action.action, [0.25, -0.75, 1.0], atol=4e-6)
    sources = candb.c_sources(wide)
    assert "#define POLICY_IO_OBS_FRAMES 4u" in sources["policy_io.h"]
    assert sources["policy_io.c"].count("_is_in_range(") == 7


def candb_frame(message: object, fields: dict[str, float]) -> bytes:
    from embedrl.hil import e2e

    encoded = message.encode({"Crc": 0, **fields})  # type: ignore[attr-defined]
    return e2e.protect(message.frame_id, encoded)  # type: ignore[attr-defined]


def test_too_many_fields_for_classic_can_is_a_clear_error() -> None:
    many = tuple(Field(f"o{i}", "", -1.0, 1.0) for i in range(60))
    wide = Interface("many", "Many-v0", many, (Field("a", "", -1.0, 1.0),), 0.1, (0.0,), 10)
    with pytest.raises(
        HilError,
        match=r"60 observation fields need 30 classic CAN frames; at most 26 \(--fd carries 24 a frame\)",
    ):
        candb.layout(wide)
    assert len(candb.layout(wide, fd=True).observation) == 3  # CAN FD: 24 values a frame


def test_the_generator_cli_writes_the_node_sources(tmp_path: Path) -> None:
    (tmp_path / "i.json").write_text(STATIC.dumps())
    assert candb.main(["--interface", str(tmp_path / "i.json"), "--out", str(tmp_path / "can")]) == 0
    names = sorted(p.name for p in (tmp_path / "can").iterdir())
    assert names == [
        "e2e_params.h",
        "policy.dbc",
        "policy_dbc.c",
        "policy_dbc.h",
        "policy_io.c",
        "policy_io.h",
    ]
    (tmp_path / "bad.json").write_text('{"format": 1, "name": "x"}')
    assert candb.main(["--interface", str(tmp_path / "bad.json"), "--out", str(tmp_path / "b")]) == 2
    assert not (tmp_path / "b").exists()


def test_use_float_scales_signals_in_single_precision() -> None:
    double = candb.c_sources(STATIC)["policy_dbc.c"]
    single = candb.c_sources(STATIC, use_float=True)["policy_dbc.c"]
    assert "double policy_dbc_observation_a_x_decode" in double
    assert (
        "float policy_dbc_observation_a_x_decode" in single
        and "double" not in single.split("_decode")[1][:40]
    )
