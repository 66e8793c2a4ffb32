"""Hyperparameters: one typed dataclass per algorithm, and the named presets ``thesis`` and ``tuned``.

``thesis`` is the reference study's setup: fully connected 100-100 ReLU networks (deterministic actors
end in tanh), critics with an observation and an action branch added together, softplus standard
deviations for SAC's and PPO's actors (:mod:`train.study_agents`), discount 0.99, mini-batches of 128, a
replay buffer of 1e6, target smoothing 1e-3 for DDPG and TD3, Ornstein-Uhlenbeck exploration noise with
variance 0.1 and learning rates 1e-4 (actor) and 1e-3 (critic) for DDPG, an experience horizon of 512
for PPO, Adam, and no random warm-up (learning from the first transition). ``tuned`` keeps the network
sizes (so the deployed C stays comparable), SB3's standard network structure, and changes what helps
learning here.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import asdict, dataclass, field, fields, replace
from typing import Any

from embedrl.train.deck_reward import DEFAULT_VARIANT, VARIANTS
from embedrl.train.scenarios import DEFAULT_SCENARIO, SCENARIOS, STATIC, WALKER

STUDY_ALGOS = ("ddpg", "td3", "sac", "ppo")
"""The study's algorithms: what ``bench`` and ``shaping`` train unless told otherwise."""
ALGOS = (*STUDY_ALGOS, "recurrent-ppo")
"""Every algorithm ``train`` knows: the study's and sb3-contrib's RecurrentPPO (an LSTM policy)."""
PRESETS = ("thesis", "tuned", "deck")
NET_ARCH = (100, 100)


@dataclass(frozen=True)
class Budget:
    """When a run stops, besides reaching the stop criterion."""

    max_steps: int = 300_000
    """Env steps at most."""
    max_episodes: int = 100_000
    """Training episodes at most (the study's PPO ran 100,000 without reaching the criterion)."""
    checkpoint_every: int = 10_000
    """Env steps between checkpoints (model, replay buffer, normalisation, episode count)."""
    eval_every: int = 5_000
    """Env steps between validation evaluations (deterministic, no exploration noise)."""
    eval_episodes: int = 100
    """Episodes per validation evaluation, seeded from ``VALIDATION_SEED`` (disjoint from every test seed)."""
    target_success: float = 0.97
    """The deployable criterion: a validation evaluation succeeds in at least this share of episodes."""
    stop: str = "validation"
    """What ends a run before its budget: ``validation`` (the deployable criterion), ``study`` (the
    study's criterion, its protocol) or ``budget`` (train on to max_steps; both are still recorded)."""
    select_best: bool = True
    """The run's model.zip is the checkpoint with the best validation evaluation (as SB3's EvalCallback
    keeps it); the last one is kept as last_model.zip."""


STOP_RULES = ("validation", "study", "budget")


@dataclass(frozen=True)
class OffPolicyConfig:
    """Shared by DDPG, TD3 and SAC."""

    learning_rate: float = 1e-3
    """Adam step size of the critic, and of the actor unless the algorithm has its own for it."""
    gamma: float = 0.99
    """Discount factor."""
    batch_size: int = 128
    """Mini-batch size."""
    buffer_size: int = 1_000_000
    """Replay buffer capacity (transitions)."""
    tau: float = 1e-3
    """Target network smoothing factor."""
    learning_starts: int = 0
    """Random-action steps before learning starts (0: the agent's own noisy actions and updates from
    the first transition on; SB3 samples the first mini-batches with replacement)."""
    train_freq: int = 1
    """Env steps between gradient updates."""
    gradient_steps: int = 1
    """Gradient updates per update."""
    net_arch: tuple[int, ...] = NET_ARCH
    """Hidden layer sizes of actor and critic (ReLU)."""
    two_branch_critic: bool = True
    """The study's critic: observation and action in separate branches, added before the last hidden
    activation (:class:`train.study_agents.TwoBranchCritic`); false: SB3's, joined at the input."""
    demonstrations: int = 0
    """Episodes of the potential-field controller (with exploration noise) put into the replay buffer
    before learning: they show the way through the gap, which random exploration almost never finds."""
    demonstration_noise: float = 0.2
    """Gaussian noise on the demonstrations' actions (they then cover more than one path)."""
    reward: str = "thesis"
    """The env's reward: ``thesis`` (the study's eq. 19), ``potential-field`` (its contours at the four
    corners) or ``shaped`` (eq. 19 plus potential-based shaping at the agent's discount); see
    :mod:`train.rewards`. The walker's: one of the deck's stages (:data:`train.deck_reward.VARIANTS`)."""
    success_bonus: float = 5.0
    """Reward for passing the goal line (the study's two-robot runs tried 5 and 20)."""
    shaping_gain: float = 1.0
    """``reward="shaped"``: potential per metre of way to the goal (:data:`train.rewards.SHAPING_GAIN`)."""


@dataclass(frozen=True)
class DDPGConfig(OffPolicyConfig):
    """DDPG with Ornstein-Uhlenbeck exploration noise."""

    noise_sigma: float = math.sqrt(0.1)
    """Standard deviation of the OU noise (variance 0.1 in the study)."""
    noise_theta: float = 0.15
    """Mean reversion rate of the OU noise."""
    actor_learning_rate: float = 1e-4
    """Adam step size of the actor (``learning_rate`` is the critic's)."""
    noise_dt: float = 1e-2
    """Time step of the OU noise process (SB3's default; the deck's preset uses the sample time, as MATLAB's
    noise model does)."""
    gradient_threshold: float = 0.0
    """Each parameter's gradient is scaled down to this L2 norm at most (MATLAB's ``l2norm`` threshold; 0:
    none, SB3's DDPG)."""
    l2: float = 0.0
    """L2 regularisation factor of actor and critic (Adam's ``weight_decay``)."""


@dataclass(frozen=True)
class TD3Config(OffPolicyConfig):
    """TD3 with Gaussian exploration noise."""

    noise_sigma: float = 0.1
    """Standard deviation of the Gaussian exploration noise."""
    policy_delay: int = 2
    """Critic updates per actor update."""
    target_policy_noise: float = 0.2
    """Target policy smoothing noise."""
    backend: str = "torch"
    """Where the updates run: ``torch`` (SB3) or ``jax`` (sbx-rl, :mod:`train.jax_agents`: one compiled
    program per ``train_freq`` block; the run's models are saved as SB3 torch zips all the same)."""


@dataclass(frozen=True)
class SACConfig(OffPolicyConfig):
    """SAC with automatic entropy tuning."""

    ent_coef: str = "auto"
    """Entropy coefficient ("auto" learns it)."""
    softplus_std: bool = True
    """The study's actor: standard deviation = softplus of a linear head
    (:class:`train.study_agents.SoftplusSACPolicy`); false: SB3's clamped log-std head."""


@dataclass(frozen=True)
class PPOConfig:
    """PPO with a Gaussian policy whose mean is clipped to the action space at prediction."""

    learning_rate: float = 3e-4
    """Adam step size."""
    gamma: float = 0.99
    """Discount factor."""
    n_steps: int = 512
    """Env steps per rollout (the study's experience horizon)."""
    batch_size: int = 128
    """Mini-batch size."""
    n_epochs: int = 10
    """Passes over each rollout."""
    gae_lambda: float = 0.95
    """GAE smoothing."""
    clip_range: float = 0.2
    """PPO clipping."""
    ent_coef: float = 0.0
    """Entropy bonus."""
    net_arch: tuple[int, ...] = NET_ARCH
    """Hidden layer sizes of the policy and the value networks (ReLU)."""
    normalize_observations: bool = True
    """VecNormalize observations (PPO needs it); the statistics are saved with the model."""
    log_std_init: float = 0.0
    """Initial log standard deviation of the Gaussian policy (exploration)."""
    softplus_std: bool = True
    """The study's actor: a state-dependent standard deviation, softplus of a linear head
    (:class:`train.study_agents.SoftplusActorCriticPolicy`); false: SB3's state-independent parameter."""
    warm_start_demonstrations: int = 0
    """Episodes of the potential-field controller (noisy actions, clean labels) whose observations
    pretrain the policy mean by behaviour cloning before PPO (the on-policy analogue of the off-policy
    agents' demonstrations: PPO alone learns to crash, as in the study)."""
    warm_start_epochs: int = 40
    """Passes of behaviour cloning over the demonstrations."""
    reward: str = "thesis"
    """The env's reward: ``thesis`` (the study's eq. 19), ``potential-field`` (its contours at the four
    corners) or ``shaped`` (eq. 19 plus potential-based shaping at the agent's discount); see
    :mod:`train.rewards`."""
    success_bonus: float = 5.0
    """Reward for passing the goal line (the study's two-robot runs tried 5 and 20)."""
    shaping_gain: float = 1.0
    """``reward="shaped"``: potential per metre of way to the goal (:data:`train.rewards.SHAPING_GAIN`)."""


@dataclass(frozen=True)
class RecurrentPPOConfig(PPOConfig):
    """sb3-contrib's RecurrentPPO: PPO whose actor and critic each read an LSTM's output (``net_arch`` is the
    MLP after it). Its warm start clones the potential-field controller over whole demonstration episodes,
    the LSTM state carried through each."""

    softplus_std: bool = False
    """SB3's state-independent log standard deviation (the study's softplus head has no recurrent form)."""
    lstm_hidden_size: int = 64
    """Units of each LSTM (its hidden and cell state: 2 x this many floats per layer on the controller)."""
    n_lstm_layers: int = 1
    """Stacked LSTM layers."""


AlgoConfig = DDPGConfig | TD3Config | SACConfig | PPOConfig | RecurrentPPOConfig


@dataclass(frozen=True)
class RunConfig:
    """Everything that defines a training run (saved as config.json in the run directory)."""

    algo: str
    preset: str
    seed: int
    scenario: str = DEFAULT_SCENARIO
    hyperparameters: dict[str, Any] = field(default_factory=dict)
    budget: dict[str, Any] = field(default_factory=dict)
    overrides: list[str] = field(default_factory=list)
    """``--set NAME=VALUE`` assignments applied to the preset (already in ``hyperparameters``)."""


SCENARIO_NAMES = tuple(SCENARIOS)
BUDGET_COUNTS = ("max_steps", "max_episodes", "checkpoint_every", "eval_every")
"""The counts of a run's budget that config.json records and ``--resume`` takes from it."""


def check_run_config(saved: Any) -> None:
    """A run's config.json as read back for ``--resume`` (the user's file): ValueError naming the first
    key that is missing or not of its kind."""
    if not isinstance(saved, dict):
        raise ValueError(f"a {type(saved).__name__}, not an object")

    def one_of(key: str, choices: Sequence[str], value: Any) -> None:
        if value not in choices:
            raise ValueError(f"{key} is {value!r}, not one of {', '.join(choices)}")

    for key in ("algo", "preset", "seed", "budget"):
        if key not in saved:
            raise ValueError(f"no {key!r}")
    one_of("algo", ALGOS, saved["algo"])
    one_of("preset", PRESETS, saved["preset"])
    one_of("scenario", SCENARIO_NAMES, saved.get("scenario", DEFAULT_SCENARIO))
    seed = saved["seed"]
    if not isinstance(seed, int) or isinstance(seed, bool) or seed < 0:
        raise ValueError(f"seed is {seed!r}, not a whole number >= 0")
    budget = saved["budget"]
    if not isinstance(budget, dict):
        raise ValueError(f"budget is {budget!r}, not an object")
    for key in BUDGET_COUNTS:
        value = budget.get(key)
        if not isinstance(value, int) or isinstance(value, bool) or value < 1:
            raise ValueError(f"budget.{key} is {value!r}, not a whole number >= 1")
    one_of("budget.stop", STOP_RULES, budget.get("stop", "validation"))
    kinds: dict[str, type] = {"machine": dict, "overrides": list, "extensions": list}
    for key, kind in kinds.items():
        if key in saved and not isinstance(saved[key], kind):
            raise ValueError(f"{key} is {saved[key]!r}, not {'an object' if kind is dict else 'a list'}")
    if not all(isinstance(o, str) for o in saved.get("overrides", [])):
        raise ValueError("overrides is not a list of NAME=VALUE texts")


def preset(algo: str, name: str, scenario: str = DEFAULT_SCENARIO) -> AlgoConfig:
    """The named preset of an algorithm in a scenario.

    In the moving-shelf and two-robot scenarios ``thesis`` trains on the study's potential-field reward
    (the reward of its changing and multi-agent experiments); ``tuned`` keeps the static scenario's
    tuning, demonstrations from the scenario's potential-field controller included. The walker has its own
    presets (:func:`walker_preset`).
    """
    if scenario not in SCENARIO_NAMES:
        raise ValueError(f"unknown scenario {scenario!r}; choose from {', '.join(SCENARIO_NAMES)}")
    if scenario == WALKER.name:
        return walker_preset(algo, name)
    if name == "deck":
        raise ValueError("the deck preset trains the walker scenario (--scenario walker)")
    config = _preset(algo, name)
    if name == "thesis" and scenario != STATIC.name:
        config = replace(config, reward="potential-field")
    return config


def _preset(algo: str, name: str) -> AlgoConfig:
    if algo not in ALGOS:
        raise ValueError(f"unknown algorithm {algo!r}; choose from {', '.join(ALGOS)}")
    if name not in PRESETS:
        raise ValueError(f"unknown preset {name!r}; choose from {', '.join(PRESETS)}")
    thesis: dict[str, AlgoConfig] = {
        "ddpg": DDPGConfig(),
        "td3": TD3Config(),
        "sac": SACConfig(learning_rate=3e-4),
        "ppo": PPOConfig(),
        "recurrent-ppo": RecurrentPPOConfig(),
    }
    if name == "thesis":
        return thesis[algo]
    tuned: dict[str, AlgoConfig] = {
        # Random exploration almost never finds the 18-step path through the gap, and crashing at once
        # (-2) beats wandering (-25): with the study's settings the agents learn to crash. Demonstrations
        # from the baseline controller in the replay buffer, wider exploration noise and faster target
        # tracking avoid that.
        # DDPG's single critic overestimated (Episode Q0 +14 with returns near -20): a shorter horizon and a
        # slower learner keep it honest.
        "ddpg": replace(
            DDPGConfig(),
            tau=5e-3,
            learning_starts=10_000,
            demonstrations=100,
            noise_sigma=0.2,
            learning_rate=1e-4,
            actor_learning_rate=1e-4,
            gamma=0.98,
            two_branch_critic=False,
        ),
        "td3": replace(
            TD3Config(),
            tau=5e-3,
            learning_starts=10_000,
            noise_sigma=0.2,
            demonstrations=100,
            two_branch_critic=False,
        ),
        "sac": replace(
            SACConfig(),
            softplus_std=False,
            two_branch_critic=False,
            learning_rate=7.3e-4,
            tau=0.02,
            learning_starts=10_000,
            gamma=0.98,
            train_freq=8,
            gradient_steps=8,
            demonstrations=100,
        ),
        "ppo": replace(
            PPOConfig(),
            softplus_std=False,
            n_steps=1024,
            batch_size=64,
            gamma=0.98,
            learning_rate=1e-4,
            clip_range=0.1,
            log_std_init=-1.5,
            warm_start_demonstrations=100,
        ),
    }
    # The same PPO with an LSTM in front of each network (its own sizes; the rest of PPO's tuning).
    ppo = tuned["ppo"]
    assert isinstance(ppo, PPOConfig)
    tuned["recurrent-ppo"] = RecurrentPPOConfig(**{f.name: getattr(ppo, f.name) for f in fields(PPOConfig)})
    return tuned[algo]


WALKER_NET_ARCH = (400, 300)
"""The walker presets' hidden layers: RL Zoo's for Walker2d (the deck's option list does not fix them)."""
WALKER_TD3_NET_ARCH = (64, 64)
"""The walker's TD3: a network the Cortex-M4F runs well inside the 8 ms sample time, and the JAX backend
trains at several times SB3's speed (docs/walker.md)."""
WALKER_BLOCK = 32
"""The walker's TD3 collects this many env steps, then makes as many updates in one compiled program (the
deck's workers also send their experiences every 32 steps)."""


def walker_preset(algo: str, name: str) -> AlgoConfig:
    """The walker's presets, all on the deck's reward.

    ``deck`` (DDPG only): the deck's DDPG options. Critic learning rate 1e-3, actor 1e-4 (SB3 has one rate:
    :class:`~train.study_agents.SeparateRatesDDPG`); gradient threshold 1 and L2 factor 1e-5 (SB3's DDPG has
    neither: :class:`~train.study_agents.ClippedAdam`, per parameter as MATLAB's ``l2norm`` method); discount
    0.99, mini-batch 128, buffer 1e6, target smoothing 1e-3; Ornstein-Uhlenbeck noise with mean attraction
    (theta) 1 and 0.1 as the factor of its random term over one sample time as time step (MATLAB's noise
    model, whose option called ``Variance`` multiplies ``randn``: SB3's ``sigma``); the deck's MATLAB-style
    critic (two branches). Its stop criterion and save threshold are the scenario's
    (:data:`train.monitor.CRITERIA`).

    ``tuned`` (DDPG, TD3, SAC): RL Zoo's Walker2d settings (10,000 random steps first, exploration noise 0.1:
    Gaussian for TD3, DDPG keeps its OU noise; batch 256, SB3's standard networks). TD3 runs on JAX with
    64-64 networks, collecting and updating in blocks of :data:`WALKER_BLOCK` steps.
    """
    if name == "deck":
        if algo != "ddpg":
            raise ValueError(
                f"the deck preset is DDPG's (the deck trains DDPG); use --preset tuned for {algo}"
            )
        return DDPGConfig(
            learning_rate=1e-3, actor_learning_rate=1e-4, gradient_threshold=1.0, l2=1e-5, gamma=0.99,
            batch_size=128, buffer_size=1_000_000, tau=1e-3, noise_theta=1.0, noise_sigma=0.1,
            noise_dt=WALKER.sample_time_s, net_arch=WALKER_NET_ARCH, reward=DEFAULT_VARIANT,
        )  # fmt: skip
    if name != "tuned":
        raise ValueError(f"the walker's presets are deck (DDPG) and tuned (DDPG, TD3, SAC), not {name!r}")
    arch, start, batch, reward = WALKER_NET_ARCH, 10_000, 256, DEFAULT_VARIANT
    tuned: dict[str, AlgoConfig] = {
        "ddpg": DDPGConfig(
            learning_starts=start, batch_size=batch, net_arch=arch, two_branch_critic=False, reward=reward,
            tau=5e-3, actor_learning_rate=1e-3, noise_sigma=0.1,
        ),
        "td3": TD3Config(
            learning_starts=start, batch_size=batch, net_arch=WALKER_TD3_NET_ARCH, two_branch_critic=False,
            reward=reward, tau=5e-3, noise_sigma=0.1, backend="jax", train_freq=WALKER_BLOCK,
            gradient_steps=WALKER_BLOCK,
        ),
        "sac": SACConfig(
            learning_starts=start, batch_size=batch, net_arch=(256, 256), two_branch_critic=False,
            reward=reward, learning_rate=3e-4, tau=5e-3, softplus_std=False,
        ),
    }  # fmt: skip
    if algo not in tuned:
        raise ValueError(f"no walker preset for {algo}; the walker trains with {', '.join(tuned)}")
    return tuned[algo]


RANGES: dict[str, tuple[float, float, str]] = {
    "learning_rate": (0.0, math.inf, "> 0"),
    "actor_learning_rate": (0.0, math.inf, "> 0"),
    "noise_dt": (0.0, math.inf, "> 0"),
    "gamma": (0.0, 1.0, "in (0, 1]"),
    "tau": (0.0, 1.0, "in (0, 1]"),
    "gae_lambda": (0.0, 1.0, "in (0, 1]"),
    "clip_range": (0.0, math.inf, "> 0"),
    "target_success": (0.0, 1.0, "in (0, 1]"),
}
"""Fields whose values must lie in ``(low, high]``, with the rule as the error states it."""
NON_NEGATIVE = (
    "noise_sigma",
    "noise_theta",
    "gradient_threshold",
    "l2",
    "target_policy_noise",
    "demonstration_noise",
    "ent_coef",
)
"""Fields that may be zero but not negative."""
AT_LEAST_ONE = (
    "batch_size",
    "buffer_size",
    "n_steps",
    "n_epochs",
    "train_freq",
    "policy_delay",
    "eval_episodes",
    "lstm_hidden_size",
    "n_lstm_layers",
)
"""Counts that must be at least one."""
MAX_LAYERS = 8
"""Hidden layers a network may have (``net_arch``)."""
MAX_LAYER_WIDTH = 4096
"""Units a hidden layer may have: wider layers do not fit a microcontroller (or this machine's memory)."""
BACKENDS = ("torch", "jax")
"""TD3's update engines (:data:`train.jax_agents.BACKENDS`; kept here so the config imports no JAX)."""


def with_overrides(config: AlgoConfig, assignments: Sequence[str]) -> AlgoConfig:
    """``config`` with ``NAME=VALUE`` assignments applied (``--set``), each parsed as its field's type.

    Numbers must be finite and inside their field's range (:data:`RANGES`, :data:`NON_NEGATIVE`,
    :data:`AT_LEAST_ONE`); tuples are comma-separated (``net_arch=64,64``, positive); booleans are
    true/false.
    """
    names = {f.name for f in fields(config)}
    changes: dict[str, Any] = {}
    for text in assignments:
        key, sep, raw = text.partition("=")
        key = key.strip()
        if not sep or key not in names:
            raise ValueError(
                f"--set {text!r}: expected NAME=VALUE with NAME one of {', '.join(sorted(names))}"
            )
        changes[key] = _parse(key, raw.strip(), getattr(config, key))
        _check_range(key, changes[key])
    return replace(config, **changes)


def _check_range(key: str, value: Any) -> None:
    if key in RANGES:
        low, high, rule = RANGES[key]
        if not low < value <= high:
            raise ValueError(f"--set {key}={value}: must be {rule}")
    elif key in NON_NEGATIVE and value < 0:
        raise ValueError(f"--set {key}={value}: must be >= 0")
    elif key in AT_LEAST_ONE and value < 1:
        raise ValueError(f"--set {key}={value}: must be at least 1")
    elif isinstance(value, tuple) and any(v < 1 for v in value):
        raise ValueError(f"--set {key}={','.join(map(str, value))}: every size must be at least 1")
    elif isinstance(value, tuple) and (len(value) > MAX_LAYERS or any(v > MAX_LAYER_WIDTH for v in value)):
        raise ValueError(
            f"--set {key}={','.join(map(str, value))}: at most {MAX_LAYERS} layers of at most "
            f"{MAX_LAYER_WIDTH} units (a policy for a microcontroller)"
        )


def _parse(key: str, raw: str, current: Any) -> Any:
    from embedrl.train.rewards import REWARDS

    if key == "reward" and raw not in (*REWARDS, *VARIANTS):
        raise ValueError(f"--set reward={raw}: choose from {', '.join((*REWARDS, *VARIANTS))}")
    if key == "backend" and raw not in BACKENDS:
        raise ValueError(f"--set backend={raw}: choose from {', '.join(BACKENDS)}")
    try:
        if isinstance(current, bool):
            if raw.lower() not in ("true", "false"):
                raise ValueError("use true or false")
            return raw.lower() == "true"
        if isinstance(current, tuple):
            return tuple(int(v) for v in raw.split(",") if v.strip())
        if isinstance(current, int):
            return int(raw)
        if isinstance(current, float):
            value = float(raw)
            if not math.isfinite(value):
                raise ValueError("not a finite number")
            return value
        return raw
    except ValueError as exc:
        raise ValueError(f"--set {key}={raw}: {exc}") from None


def to_dict(config: AlgoConfig) -> dict[str, Any]:
    return asdict(config)


def warmup_steps(config: AlgoConfig) -> int:
    """Env steps of random actions before the first training update (off-policy agents'
    ``learning_starts``; PPO has none: it updates after every rollout, the first one included)."""
    return 0 if isinstance(config, PPOConfig) else int(config.learning_starts)


def untrained_budget(config: AlgoConfig, max_steps: int) -> str | None:
    """Why a run of ``max_steps`` env steps would end without a single training update (SB3 updates an
    off-policy agent only once more than ``learning_starts`` steps were taken), or None when it trains."""
    warmup = warmup_steps(config)
    if max_steps > warmup:
        return None
    return (
        f"a budget of {max_steps:,} steps ends within the random warm-up ({warmup:,} steps, "
        "learning_starts): no training update, the policy stays untrained"
    )
