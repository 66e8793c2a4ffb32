"""The report's back-to-back table: SB3 -> ONNX -> C on the host -> C on the Cortex-M4 under QEMU -> the bus,
the largest absolute difference and ULP distance at each link, and the verdict's line over them."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np
import pytest

from embedrl.export.verify import max_ulp
from embedrl.hil.signoff import back_to_back, facts
from tests.conftest import Exported, marks_its_users
from tests.hil.conftest import SHIPPED_TD3

F32 = np.float32


def test_ulp_distance_counts_float32_steps() -> None:
    one = np.array([F32(1.0), F32(-1.0)])
    assert max_ulp(one, one) == 0
    assert max_ulp(one, np.nextafter(one, F32(0.0))) == 1
    assert max_ulp(np.array([F32(0.0)]), np.array([F32(-0.0)])) == 0
    tiny = np.nextafter(F32(0.0), F32(1.0))
    assert max_ulp(np.array([tiny]), np.array([-tiny])) == 2  # across zero
    assert max_ulp(np.array([F32(1.0)]), np.array([F32(2.0)])) == 2**23
    with pytest.raises(ValueError, match="shapes differ"):
        max_ulp(one, one[:1])


@pytest.fixture(scope="module")
@marks_its_users("qemu")
def m4_links(exported: Exported) -> list[dict[str, Any]]:
    export_dir = exported(SHIPPED_TD3, "--episodes", "0", "--target", "cortex-m4")
    export = facts.load_export(export_dir)
    row = facts.recompute(export_dir, export)
    hil = {"node": "firmware", "target": "cortex-m4", "steps": 120,
           "per_episode": [{"max_action_abs_diff": 9.5e-7}, {"max_action_abs_diff": 2.1e-7}]}  # fmt: skip
    return back_to_back.links(export_dir, export, row, [("hil.json", hil)])


def test_every_link_from_sb3_to_the_bus_is_within_its_tolerance(m4_links: list[dict[str, Any]]) -> None:
    assert [(r["source"], r["to"]) for r in m4_links] == [
        ("SB3 predict(deterministic=True)", "ONNX (onnxruntime)"),
        ("ONNX (onnxruntime)", "C on the host"),
        ("C on the host", "C on cortex-m4 (QEMU)"),
        ("C on cortex-m4 (hil.json)", "action decoded from the bus"),
    ]
    sb3, host, firmware, bus = m4_links
    assert (
        sb3["samples"] == host["samples"] == 10_000 and firmware["samples"] == 256 and bus["samples"] == 120
    )
    for link in m4_links:
        assert link["passed"] is True and 0.0 <= link["max_abs"] <= 1e-5, link
    # other summation orders (torch, onnxruntime, the C) round differently: ~1e-6 apart, which near an
    # action of 0 is thousands of float32 steps; the C on the M4 (same order, newlib's tanhf) is the host's
    assert 1_000 < sb3["max_ulp"] < 100_000 and 1_000 < host["max_ulp"] < 100_000
    assert firmware["max_abs"] == 0.0 and firmware["max_ulp"] == 0
    assert firmware["how"].startswith("measured by the report")
    assert bus["max_abs"] == 9.5e-7 and bus["max_ulp"] is None
    passed, detail = back_to_back.check(m4_links)
    assert passed and detail.startswith("4 of 4 links measured, each within its tolerance")


def test_a_link_outside_its_tolerance_or_with_other_codes_fails_the_check() -> None:
    ok = {"source": "a", "to": "b", "max_abs": 1e-7, "tolerance": 1e-5, "passed": True, "how": ""}
    far = {**ok, "source": "C on the host", "to": "C on cortex-m4 (QEMU)", "max_abs": 3e-4, "passed": False}
    assert back_to_back.check([ok, far]) == (
        False, "C on the host -> C on cortex-m4 (QEMU): max |difference| 0.0003 > 1e-05"
    )  # fmt: skip
    codes = {**far, "max_abs": None, "how": "return codes differ on 3 vectors"}
    assert back_to_back.check([ok, codes])[1].endswith(": return codes differ on 3 vectors")
    unmeasured = {**ok, "max_abs": None, "passed": None, "how": "not measured: the export had no SB3 model"}
    assert back_to_back.check([ok, unmeasured]) == (
        True, "1 of 2 links measured, each within its tolerance (worst 1e-07)"
    )  # fmt: skip


def test_the_firmware_link_never_runs_c_that_is_not_the_generators(tmp_path: Path) -> None:
    export = {"verification": {"tolerance": 1e-5, "samples": 10, "onnx_vs_sb3_max_abs_error": None},
              "targets": {"cortex-m4": {}}}  # fmt: skip
    row = {"generated_c": "c/policy.c differs", "samples": 0, "max_error": None}
    links = back_to_back.links(tmp_path, export, row, [])
    assert [r["how"] for r in links] == [
        "not measured: the export had no SB3 model",
        "not recomputed: c/policy.c differs",
        "not run: c/policy.c differs",
    ]
    assert all(r["passed"] is None for r in links)
