"""The teacher's networks as rsl_rl models for the warp backend: the actor wraps this project's ActorNet (so
the bundle is the CPU learner's format) and the critic reads the same groups.
"""

from __future__ import annotations

import math

import torch
from torch import nn

from envs.config import EnvConfig
from envs.sim_identity import sim_record
from rotation.policy.actor import ActorNet
from rotation.policy.bundle_config import BundleConfig
from rotation.policy.features import PrivilegedExtractor
from rotation.policy.networks import EnvFactorEncoderConfig, mlp
from rotation.train.teacher_config import TEACHER_GROUPS

# --------------------------------------------------------------------------------------------------------------------
# rsl_rl models around this project's networks


def _orthogonal_init(module: nn.Module, gain: float) -> None:
    """stable-baselines3's initialization, so both learners start alike: orthogonal weights, zero biases."""
    for m in module.modules():
        if isinstance(m, nn.Linear):
            nn.init.orthogonal_(m.weight, gain=gain)
            nn.init.zeros_(m.bias)


class _Feedforward:
    """The part of rsl_rl's actor / critic interface that only recurrent models use: no hidden state."""

    is_recurrent = False

    def reset(self, dones=None, hidden_state=None) -> None:
        pass

    def get_hidden_state(self):
        return None

    def detach_hidden_state(self, dones=None) -> None:
        pass


class TeacherActor(_Feedforward, nn.Module):
    """rsl_rl actor interface over an ActorNet: a diagonal Gaussian with mean ActorNet.mean(obs) and a learned,
    state-independent log std (SB3's DiagGaussianDistribution)."""

    def __init__(self, net: ActorNet, log_std_init: float) -> None:
        super().__init__()
        self.net = net
        self.log_std = nn.Parameter(torch.full((net.action_mean.out_features,), float(log_std_init)))
        self._mean: torch.Tensor | None = None
        self.learn_normalization = True  # off while a fresh critic warms up (the actor stays as it was)
        for m in net.modules():  # the statistics move in update_normalization, once per rollout
            if hasattr(m, "frozen"):
                m.frozen = True

    def forward(self, obs, masks=None, hidden_state=None, stochastic_output: bool = False) -> torch.Tensor:
        mean = self.net.mean({k: obs[k] for k in TEACHER_GROUPS})  # (B, A), unclipped
        self._mean = mean
        if stochastic_output:
            return mean + self.log_std.exp() * torch.randn_like(mean)
        return mean

    def _dist(self) -> torch.distributions.Normal:
        assert self._mean is not None, "call forward first"
        return torch.distributions.Normal(self._mean, self.log_std.exp().expand_as(self._mean))

    def get_output_log_prob(self, actions: torch.Tensor) -> torch.Tensor:
        return self._dist().log_prob(actions).sum(-1)

    @property
    def output_entropy(self) -> torch.Tensor:
        return self._dist().entropy().sum(-1)

    @property
    def output_distribution_params(self) -> tuple[torch.Tensor, torch.Tensor]:
        d = self._dist()
        return d.mean, d.stddev

    def get_kl_divergence(self, old, new) -> torch.Tensor:
        p = torch.distributions.Normal(*old)
        q = torch.distributions.Normal(*new)
        return torch.distributions.kl_divergence(p, q).sum(-1)

    def update_normalization(self, obs) -> None:
        if self.learn_normalization:
            self.net.extractor.proprio_norm.update(obs["proprio"])


class TeacherCritic(_Feedforward, nn.Module):
    """rsl_rl critic interface: the teacher's extractor (its own copy) -> the actor's MLP sizes -> a value (B, 1)."""

    def __init__(self, space, hidden: tuple[int, ...]) -> None:
        super().__init__()
        self.extractor = PrivilegedExtractor(space, EnvFactorEncoderConfig())
        self.extractor.proprio_norm.frozen = True
        self.mlp = mlp([self.extractor.features_dim, *hidden], nn.ELU, activate_last=True)
        self.value = nn.Linear(hidden[-1], 1)

    def forward(self, obs, masks=None, hidden_state=None) -> torch.Tensor:
        return self.value(self.mlp(self.extractor({k: obs[k] for k in TEACHER_GROUPS})))  # (B, 1)

    def update_normalization(self, obs) -> None:
        self.extractor.proprio_norm.update(obs["proprio"])


def build_models(cfg, env_cfg: EnvConfig) -> tuple[BundleConfig, TeacherActor, TeacherCritic]:
    """The bundle config and fresh actor / critic, initialized like stable-baselines3's (gains sqrt(2), 0.01, 1)."""
    config = BundleConfig(latent_source="privileged", actor_hidden=tuple(cfg.net_arch),
                          control_hz=env_cfg.control_hz, action_scale=env_cfg.action_scale,
                          sim=sim_record(env_cfg))
    net = ActorNet(config)
    _orthogonal_init(net, math.sqrt(2))
    _orthogonal_init(net.action_mean, 0.01)
    actor = TeacherActor(net, cfg.log_std_init)
    critic = TeacherCritic(config.observation_space(), tuple(cfg.net_arch))
    _orthogonal_init(critic, math.sqrt(2))
    _orthogonal_init(critic.value, 1.0)
    return config, actor, critic
