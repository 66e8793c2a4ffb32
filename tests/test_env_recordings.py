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


@pytest.mark.parametrize("scenario", ["static", "moving-shelf"])
def test_an_env_pickled_mid_episode_goes_on_the_same(scenario: str) -> None:
    """A training checkpoint pickles the env: the copy steps exactly as the original does."""
    import pickle

    import gymnasium as gym
    import numpy as np

    from embedrl.train.scenarios import SCENARIOS

    env = gym.make(SCENARIOS[scenario].env_id).unwrapped
    env.reset(seed=3)
    rng = np.random.default_rng(0)
    for action in rng.uniform(-1, 1, (3, 2)):
        env.step(action)
    copy = pickle.loads(pickle.dumps(env))
    actions = rng.uniform(-1, 1, (12, 2))
    original = [env.step(a)[0].tobytes() for a in actions]
    assert [copy.step(a)[0].tobytes() for a in actions] == original


def test_the_observation_clip_gives_np_clips_bits() -> None:
    """ObsBounds.clip against np.clip on float32, on values around, at and past the bounds, NaN and inf."""
    import numpy as np

    from embedrl.train.world import ObsBounds, held_action

    low = np.array([-1.0, -0.7, -2.5], dtype=np.float32)
    high = np.array([1.0, 0.7, 2.5], dtype=np.float32)
    rng = np.random.default_rng(0)
    specials = [np.nan, np.inf, -np.inf, 0.7, np.nextafter(0.7, 1.0), float(np.float32(0.7)), -0.0]
    states = [rng.uniform(-3, 3, 3).tolist() for _ in range(2000)]
    states += [[s, -s if s == s else s, s] for s in specials]
    bounds = ObsBounds(low, high)
    for state in states:
        expected = np.clip(np.array(state, dtype=np.float32), low, high)
        assert bounds.clip(state).tobytes() == expected.tobytes(), state
    for action in ([0.5, -2.0], [np.inf, -np.inf], [1.0000001, -0.9999999], np.array([0.25, 3.0])):
        expected = np.clip(np.asarray(action, dtype=np.float32).reshape(2), -1.0, 1.0)
        assert held_action(action).tobytes() == expected.tobytes()
    with pytest.raises(ValueError, match="must be finite"):
        held_action([np.nan, 0.0])
