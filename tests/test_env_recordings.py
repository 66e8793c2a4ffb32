"""Every scenario plays its recorded episodes bit for bit (``tests/env_recordings.py``): the physics may get
faster, never different, so the shipped policies, their exports and the study's tables stay valid."""

from __future__ import annotations

import json

import pytest

from tests.env_recordings import GOLDEN, record


@pytest.fixture(scope="module")
def played() -> dict[str, dict[str, list[str]]]:
    return record()


@pytest.mark.parametrize("scenario", sorted(json.loads(GOLDEN.read_text())))
@pytest.mark.parametrize("kind", ["random", "potential-field"])
def test_recorded_episodes_replay_bit_for_bit(
    played: dict[str, dict[str, list[str]]], scenario: str, kind: str
) -> None:
    recorded = json.loads(GOLDEN.read_text())[scenario][kind]
    differing = [i for i, (a, b) in enumerate(zip(played[scenario][kind], recorded, strict=True)) if a != b]
    assert not differing, f"{scenario} {kind}: episodes {differing[:10]} differ from the recording"
