"""The slide deck's walking-robot reward and its four shaping stages.

The deck's reward for one step::

    r_t = v_x - 3 y^2 - 50 z_hat^2 + 25 Ts/Tf - 0.02 sum_i (u_{t-1}^i)^2

- ``v_x``: forward velocity of the trunk [m/s];
- ``y``: lateral deviation from the straight line [m] (the path term);
- ``z_hat``: change of the trunk's height from its height at the start of the episode [m];
- ``25 Ts/Tf``: the survive bonus, ``Ts`` the sample time and ``Tf`` the episode length [s], so a walker that
  never falls earns 25 over a whole episode;
- ``u_{t-1}``: the previous step's action (the effort term lags the action by one step, as in the deck's
  Simulink model; zero before the first action).

The deck builds the reward up in four stages to show that shaping helps learning (:data:`VARIANTS`): ``v_x``
alone; plus the survive (upright) bonus and the height penalty; plus the effort penalty; plus the path
penalty (the whole reward). The planar walker cannot leave its line, so ``y`` is identically 0 and the last
two stages give the same rewards; the path term is still computed and logged.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True)
class DeckReward:
    """The weights of the deck's reward terms (a weight of 0 leaves its term out)."""

    forward: float = 1.0
    """Weight of the forward velocity ``v_x``."""
    path: float = 3.0
    """Weight of the lateral deviation's square ``y^2``."""
    height: float = 50.0
    """Weight of the height change's square ``z_hat^2``."""
    survive: float = 25.0
    """The survive bonus over a whole episode (per step: ``survive * Ts / Tf``)."""
    effort: float = 0.02
    """Weight of the previous action's squared norm."""

    def terms(
        self,
        v_x: float,
        y: float,
        z_hat: float,
        previous_action: np.ndarray,
        sample_time: float,
        episode_s: float,
    ) -> dict[str, float]:
        """Each term of one step's reward, signed as it enters the sum (keys: :data:`TERMS`)."""
        u = np.asarray(previous_action, dtype=np.float64)
        return {
            "forward": self.forward * float(v_x),
            "path": -self.path * float(y) ** 2,
            "height": -self.height * float(z_hat) ** 2,
            "survive": self.survive * sample_time / episode_s,
            "effort": -self.effort * float(np.sum(u * u)),
        }


TERMS = ("forward", "path", "height", "survive", "effort")
"""The reward's terms in the order of the deck's formula (the keys of :meth:`DeckReward.terms`)."""

VARIANTS: dict[str, DeckReward] = {
    "velocity": DeckReward(path=0.0, height=0.0, survive=0.0, effort=0.0),
    "upright": DeckReward(path=0.0, effort=0.0),
    "effort": DeckReward(path=0.0),
    "deck": DeckReward(),
}
"""The deck's shaping stages, in its order: ``v_x`` alone; + the survive bonus and the height penalty;
+ the effort penalty; + the path penalty (the whole reward, the default)."""
DEFAULT_VARIANT = "deck"


def variant(name: str) -> DeckReward:
    """The named shaping stage (ValueError naming the known ones)."""
    if name not in VARIANTS:
        raise ValueError(f"walker reward {name!r} is not one of {', '.join(VARIANTS)}")
    return VARIANTS[name]
