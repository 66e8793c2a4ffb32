"""Shared fixtures: a fresh registered environment per test."""

from __future__ import annotations

from collections.abc import Iterator

import gymnasium as gym
import numpy as np
import pytest

from embedrl import train


@pytest.fixture
def env() -> Iterator[gym.Env[np.ndarray, np.ndarray]]:
    e = gym.make(train.ENV_ID)
    yield e
    e.close()


def pytest_addoption(parser: pytest.Parser) -> None:
    parser.addoption(
        "--regen-golden",
        action="store_true",
        help="rewrite the generated-code golden files instead of comparing with them",
    )
