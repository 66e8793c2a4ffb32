"""The reference study's agent structure on Stable-Baselines3: two-branch critics, softplus standard
deviations, and separate actor and critic learning rates.

The study built its agents with MATLAB's Reinforcement Learning Toolbox, whose standard networks differ
from SB3's ``MlpPolicy`` in three places; the ``thesis`` preset uses the classes here for each:

- **Two-branch critic** (:class:`TwoBranchCritic`): the observation passes through the hidden layers,
  the action through one fully connected layer of the last hidden width, the two are added, and a ReLU
  and a linear layer give Q. SB3 instead joins observation and action at the input.
- **Softplus standard deviation** (SAC: :class:`StudySACPolicy`; PPO: :class:`SoftplusActorCriticPolicy`):
  a linear head on the actor's last hidden layer, through softplus, gives each action's standard
  deviation, depending on the state. SB3's SAC uses a linear log-std head; its PPO a state-independent
  log-std parameter. The logarithm is clamped to SB3's bounds [-20, 2] in both, for numerical safety.
- **Separate learning rates** (:class:`SeparateRatesDDPG`): the actor's Adam steps at
  ``actor_learning_rate``, the critic's at the algorithm's ``learning_rate`` (SB3 gives both the same).
- **Gradient threshold and L2 regularisation** (:class:`ClippedAdam`, used by :class:`SeparateRatesDDPG` when
  asked): MATLAB's ``GradientThreshold`` with its default method ``l2norm`` scales each learnable parameter's
  gradient down to that L2 norm; its ``L2RegularizationFactor`` adds ``factor * w`` to the gradient. SB3's
  DDPG has neither (its off-policy algorithms never clip gradients).

The deterministic action (the mean) is computed exactly as in SB3's classes, so export, evaluation and
the C runtime treat these policies like SB3's own.
"""

from __future__ import annotations

from typing import Any

import torch as th
from gymnasium import spaces
from stable_baselines3 import DDPG
from stable_baselines3.common.distributions import DiagGaussianDistribution, Distribution
from stable_baselines3.common.policies import ActorCriticPolicy, ContinuousCritic
from stable_baselines3.common.torch_layers import BaseFeaturesExtractor
from stable_baselines3.common.type_aliases import Schedule
from stable_baselines3.common.utils import update_learning_rate
from stable_baselines3.sac.policies import LOG_STD_MAX, LOG_STD_MIN, Actor, SACPolicy
from stable_baselines3.td3.policies import TD3Policy
from torch import nn
from torch.nn import functional as F


class TwoBranchQ(nn.Module):
    """Q(s, a) = out(act(obs_path(s) + action_path(a))).

    ``obs_path``: the hidden layers of ``net_arch`` with ``activation_fn`` between them (none after the
    last); ``action_path``: one linear layer to the last hidden width."""

    def __init__(
        self, obs_dim: int, action_dim: int, net_arch: list[int], activation_fn: type[nn.Module]
    ) -> None:
        super().__init__()
        if not net_arch:
            raise ValueError("a two-branch critic needs at least one hidden layer")
        layers: list[nn.Module] = []
        width = obs_dim
        for i, size in enumerate(net_arch):
            if i:
                layers.append(activation_fn())
            layers.append(nn.Linear(width, size))
            width = size
        self.obs_path = nn.Sequential(*layers)
        self.action_path = nn.Linear(action_dim, width)
        self.activation = activation_fn()
        self.out = nn.Linear(width, 1)

    def forward(self, features: th.Tensor, actions: th.Tensor) -> th.Tensor:
        q: th.Tensor = self.out(self.activation(self.obs_path(features) + self.action_path(actions)))
        return q


class TwoBranchCritic(ContinuousCritic):
    """SB3's continuous critic (``n_critics`` Q networks, clipped double-Q where the algorithm uses it)
    with two-branch Q networks."""

    def __init__(
        self,
        observation_space: spaces.Space[Any],
        action_space: spaces.Box,
        net_arch: list[int],
        features_extractor: BaseFeaturesExtractor,
        features_dim: int,
        activation_fn: type[nn.Module] = nn.ReLU,
        normalize_images: bool = True,
        n_critics: int = 2,
        share_features_extractor: bool = True,
    ) -> None:
        super().__init__(
            observation_space,
            action_space,
            net_arch,
            features_extractor,
            features_dim,
            activation_fn,
            normalize_images,
            n_critics,
            share_features_extractor,
        )
        action_dim = int(action_space.shape[0])
        self.q_networks = []
        for idx in range(n_critics):
            q_net = TwoBranchQ(features_dim, action_dim, net_arch, activation_fn)
            self.add_module(f"qf{idx}", q_net)  # replaces the joined-input network of the same name
            self.q_networks.append(q_net)

    def forward(self, obs: th.Tensor, actions: th.Tensor) -> tuple[th.Tensor, ...]:
        with th.set_grad_enabled(not self.share_features_extractor):
            features = self.extract_features(obs, self.features_extractor)
        return tuple(q_net(features, actions) for q_net in self.q_networks)

    def q1_forward(self, obs: th.Tensor, actions: th.Tensor) -> th.Tensor:
        with th.no_grad():
            features = self.extract_features(obs, self.features_extractor)
        return self.q_networks[0](features, actions)  # type: ignore[no-any-return]


def _two_branch_critic(
    policy: TD3Policy | SACPolicy, features_extractor: BaseFeaturesExtractor | None
) -> ContinuousCritic:
    """The critic SB3's ``make_critic`` would build, with two-branch Q networks."""
    critic_kwargs = policy._update_features_extractor(policy.critic_kwargs, features_extractor)
    return TwoBranchCritic(**critic_kwargs).to(policy.device)


class StudyTD3Policy(TD3Policy):
    """TD3's and DDPG's policy, with two-branch critics if ``two_branch_critic``."""

    def __init__(self, *args: Any, two_branch_critic: bool = True, **kwargs: Any) -> None:
        self.two_branch_critic = two_branch_critic
        super().__init__(*args, **kwargs)

    def make_critic(self, features_extractor: BaseFeaturesExtractor | None = None) -> ContinuousCritic:
        if not self.two_branch_critic:
            return super().make_critic(features_extractor)
        return _two_branch_critic(self, features_extractor)

    def _get_constructor_parameters(self) -> dict[str, Any]:
        return {**super()._get_constructor_parameters(), "two_branch_critic": self.two_branch_critic}


def _softplus_log_std(head: th.Tensor) -> th.Tensor:
    """log(softplus(head)), clamped to SB3's log-std bounds."""
    return th.clamp(th.log(F.softplus(head)), LOG_STD_MIN, LOG_STD_MAX)


class SoftplusActor(Actor):
    """SAC's squashed Gaussian actor whose standard deviation is softplus of a linear head."""

    def __init__(self, *args: Any, **kwargs: Any) -> None:
        super().__init__(*args, **kwargs)
        if self.use_sde:
            raise ValueError("softplus standard deviations do not combine with gSDE")
        head: Any = self.log_std  # a Linear without gSDE (SB3 annotates the gSDE case)
        self.std: nn.Linear = head  # the same linear head, read through softplus
        del self.log_std

    def get_action_dist_params(self, obs: Any) -> tuple[th.Tensor, th.Tensor, dict[str, th.Tensor]]:
        features = self.extract_features(obs, self.features_extractor)
        latent_pi = self.latent_pi(features)
        return self.mu(latent_pi), _softplus_log_std(self.std(latent_pi)), {}


class StudySACPolicy(SACPolicy):
    """SAC's policy, with a softplus standard-deviation head if ``softplus_std`` and two-branch critics
    if ``two_branch_critic``."""

    def __init__(
        self, *args: Any, softplus_std: bool = True, two_branch_critic: bool = True, **kwargs: Any
    ) -> None:
        self.softplus_std, self.two_branch_critic = softplus_std, two_branch_critic
        super().__init__(*args, **kwargs)

    def make_actor(self, features_extractor: BaseFeaturesExtractor | None = None) -> Actor:
        if not self.softplus_std:
            return super().make_actor(features_extractor)
        actor_kwargs = self._update_features_extractor(self.actor_kwargs, features_extractor)
        return SoftplusActor(**actor_kwargs).to(self.device)

    def make_critic(self, features_extractor: BaseFeaturesExtractor | None = None) -> ContinuousCritic:
        if not self.two_branch_critic:
            return super().make_critic(features_extractor)
        return _two_branch_critic(self, features_extractor)

    def _get_constructor_parameters(self) -> dict[str, Any]:
        flags = {"softplus_std": self.softplus_std, "two_branch_critic": self.two_branch_critic}
        return {**super()._get_constructor_parameters(), **flags}


class SoftplusActorCriticPolicy(ActorCriticPolicy):
    """PPO's policy whose standard deviation is softplus of a linear head on the policy's last hidden
    layer (state-dependent); at the start it is ``exp(log_std_init)`` wherever the head's weights are
    small (they start orthogonal with gain 0.01, as the mean's)."""

    def _build(self, lr_schedule: Schedule) -> None:
        super()._build(lr_schedule)
        if not isinstance(self.action_dist, DiagGaussianDistribution):
            raise ValueError("softplus standard deviations need a Box action space without gSDE")
        action_dim = int(self.action_space.shape[0])  # type: ignore[index]
        self.std_net = nn.Linear(self.mlp_extractor.latent_dim_pi, action_dim)
        nn.init.orthogonal_(self.std_net.weight, gain=0.01)
        std0 = th.exp(th.tensor(float(self.log_std_init)))
        nn.init.constant_(self.std_net.bias, float(th.log(th.expm1(std0))))  # softplus(bias) = std0
        del self.log_std
        # The optimizer must see the new head (SB3 built it over the parameters before).
        self.optimizer = self.optimizer_class(
            self.parameters(),
            lr=lr_schedule(1),
            **self.optimizer_kwargs,  # type: ignore[call-arg]
        )

    def _get_action_dist_from_latent(self, latent_pi: th.Tensor) -> Distribution:
        mean_actions = self.action_net(latent_pi)
        dist = self.action_dist
        assert isinstance(dist, DiagGaussianDistribution)
        return dist.proba_distribution(mean_actions, _softplus_log_std(self.std_net(latent_pi)))


class ClippedAdam(th.optim.Adam):
    """Adam whose step first scales each parameter's gradient down to an L2 norm of at most
    ``gradient_threshold`` (0: no limit), MATLAB's ``l2norm`` gradient threshold. ``weight_decay`` is torch's
    L2 term, added to the (clipped) gradient inside Adam's step."""

    def __init__(
        self, params: Any, lr: float, weight_decay: float = 0.0, gradient_threshold: float = 0.0
    ) -> None:
        super().__init__(params, lr=lr, weight_decay=weight_decay)
        self.gradient_threshold = gradient_threshold

    @th.no_grad()
    def step(self, closure: Any = None) -> Any:
        if self.gradient_threshold > 0:
            for group in self.param_groups:
                for p in group["params"]:
                    if p.grad is not None:
                        norm = th.linalg.vector_norm(p.grad)
                        if norm > self.gradient_threshold:
                            p.grad.mul_(self.gradient_threshold / norm)
        return super().step(closure)


class SeparateRatesDDPG(DDPG):
    """DDPG whose actor learns at ``actor_learning_rate`` and critic at ``learning_rate``; with a
    ``gradient_threshold`` or an ``l2`` factor both learn with :class:`ClippedAdam`."""

    def __init__(
        self,
        *args: Any,
        actor_learning_rate: float | None = None,
        gradient_threshold: float = 0.0,
        l2: float = 0.0,
        **kwargs: Any,
    ) -> None:
        self.actor_learning_rate = actor_learning_rate
        """The actor's Adam step size (None: ``learning_rate``, as in SB3)."""
        self.gradient_threshold = gradient_threshold
        """Each parameter's gradient is scaled down to this L2 norm at most (0: no limit)."""
        self.l2 = l2
        """L2 regularisation factor of both networks (Adam's ``weight_decay``)."""
        super().__init__(*args, **kwargs)

    def _update_learning_rate(self, optimizers: list[th.optim.Optimizer] | th.optim.Optimizer) -> None:
        super()._update_learning_rate(optimizers)
        if self.actor_learning_rate is not None:
            update_learning_rate(self.actor.optimizer, self.actor_learning_rate)
            self.logger.record("train/actor_learning_rate", self.actor_learning_rate)

    def _setup_model(self) -> None:
        super()._setup_model()
        if self.gradient_threshold or self.l2:
            for net in (self.actor, self.critic):
                rate = net.optimizer.param_groups[0]["lr"]
                net.optimizer = ClippedAdam(net.parameters(), rate, self.l2, self.gradient_threshold)
        if self.actor_learning_rate is not None:  # from the first update on
            update_learning_rate(self.actor.optimizer, self.actor_learning_rate)
