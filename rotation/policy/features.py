"""stable-baselines3 features extractors for the teacher and the student.

Both produce the same 104 features, ``cat(flatten(RunningNorm(proprio)) (96), z (8))``, so the actor and critic
MLPs that SB3 puts on top (``net_arch=dict(pi=[512, 256, 128], vf=[512, 256, 128])``, ``activation_fn=nn.ELU``)
are shared unchanged between the teacher (z from the privileged encoder) and the student (z from the adaptation
module over the proprioceptive history). Observation groups other than the ones read are ignored.

Teacher PPO::

    policy_kwargs = dict(
        features_extractor_class=PrivilegedExtractor,
        features_extractor_kwargs=dict(encoder=EnvFactorEncoderConfig()),
        net_arch=dict(pi=[512, 256, 128], vf=[512, 256, 128]),
        activation_fn=nn.ELU,
    )
    PPO("MultiInputPolicy", vec_env, policy_kwargs=policy_kwargs)
"""

from __future__ import annotations

import torch
from gymnasium import spaces
from stable_baselines3.common.policies import MultiInputActorCriticPolicy
from stable_baselines3.common.torch_layers import BaseFeaturesExtractor
from torch import nn

from rotation.policy.networks import (
    AdaptationConfig,
    AdaptationModule,
    EnvFactorEncoder,
    EnvFactorEncoderConfig,
    RunningNorm,
    RunningNormConfig,
)

ACTOR_CRITIC_ARCH = dict(pi=[512, 256, 128], vf=[512, 256, 128])
"""SB3 ``net_arch`` of the actor and critic MLPs (docs/reference/hora.md, "Networks"); use with
``activation_fn=nn.ELU``."""


def policy_kwargs(encoder: EnvFactorEncoderConfig | None = None, norm_clip: float = 5.0) -> dict:
    """The teacher's SB3 ``policy_kwargs``: privileged extractor + 512-256-128 ELU actor and critic."""
    return dict(
        features_extractor_class=PrivilegedExtractor,
        features_extractor_kwargs=dict(encoder=encoder or EnvFactorEncoderConfig(), norm_clip=norm_clip),
        net_arch={k: list(v) for k, v in ACTOR_CRITIC_ARCH.items()},
        activation_fn=nn.ELU,
    )


def _group_shape(observation_space: spaces.Space, key: str, extractor: str) -> tuple[int, ...]:
    if not isinstance(observation_space, spaces.Dict):
        raise ValueError(f"{extractor} needs a Dict observation space with named groups, got {observation_space}")
    if key not in observation_space.spaces:
        raise ValueError(f"{extractor} reads observation group {key!r}, which the env does not provide "
                         f"(groups: {sorted(observation_space.spaces)})")
    shape = observation_space.spaces[key].shape
    assert shape is not None
    return tuple(shape)


def _check_shape(shape: tuple[int, ...], expected: tuple[int, ...], key: str, extractor: str) -> None:
    if shape != expected:
        raise ValueError(f"{extractor}: observation group {key!r} has shape {shape}, expected {expected}")


class LatentExtractor(BaseFeaturesExtractor):
    """Shared part: normalized proprioception (``proprio``, (B, S, D)) followed by a latent z from :meth:`z`."""

    def __init__(self, observation_space: spaces.Dict, latent_dim: int, norm_clip: float = 5.0) -> None:
        name = type(self).__name__
        proprio_shape = _group_shape(observation_space, "proprio", name)
        if len(proprio_shape) != 2:
            raise ValueError(f"{name}: observation group 'proprio' must be (steps, features), got {proprio_shape}")
        steps, dim = proprio_shape
        super().__init__(observation_space, features_dim=steps * dim + latent_dim)
        self.proprio_shape = proprio_shape
        self.latent_dim = latent_dim
        # statistics per proprioceptive feature, pooled over the 3 steps (they are the same quantities a step apart)
        self.proprio_norm = RunningNorm(RunningNormConfig(shape=(dim,), clip=norm_clip))

    def z(self, obs: dict[str, torch.Tensor]) -> torch.Tensor:
        """The latent (B, Z) this extractor feeds the actor."""
        raise NotImplementedError

    def forward(self, obs: dict[str, torch.Tensor]) -> torch.Tensor:
        p = self.proprio_norm(obs["proprio"])  # (B, S, D)
        p = p.flatten(1)  # (B, S * D) = (B, 96)
        return torch.cat([p, self.z(obs)], dim=-1)  # (B, 96 + Z) = (B, 104)


class PrivilegedExtractor(LatentExtractor):
    """Teacher features: ``proprio`` (B, 3, 32) and ``priv`` (B, 9) -> (B, 104), z = EnvFactorEncoder(priv)."""

    def __init__(
        self,
        observation_space: spaces.Dict,
        encoder: EnvFactorEncoderConfig | None = None,
        norm_clip: float = 5.0,
    ) -> None:
        encoder = encoder or EnvFactorEncoderConfig()
        super().__init__(observation_space, latent_dim=encoder.latent_dim, norm_clip=norm_clip)
        name = type(self).__name__
        _check_shape(_group_shape(observation_space, "priv", name), (encoder.in_dim,), "priv", name)
        self.encoder = EnvFactorEncoder(encoder)

    def z(self, obs: dict[str, torch.Tensor]) -> torch.Tensor:
        return self.encoder(obs["priv"])  # (B, Z)


class StudentExtractor(LatentExtractor):
    """Student features: ``proprio`` (B, 3, 32) and ``proprio_hist`` (B, 30, 32) -> (B, 104).

    z = AdaptationModule(RunningNorm(proprio_hist)); the history has its own normalization statistics (Hora keeps
    a separate running mean/std for it), which :meth:`from_teacher` starts from the teacher's proprio statistics.
    """

    def __init__(
        self,
        observation_space: spaces.Dict,
        adaptation: AdaptationConfig | None = None,
        norm_clip: float = 5.0,
    ) -> None:
        adaptation = adaptation or AdaptationConfig()
        super().__init__(observation_space, latent_dim=adaptation.latent_dim, norm_clip=norm_clip)
        name = type(self).__name__
        hist_shape = _group_shape(observation_space, "proprio_hist", name)
        _check_shape(hist_shape, (adaptation.steps, adaptation.in_dim), "proprio_hist", name)
        self.hist_norm = RunningNorm(RunningNormConfig(shape=(adaptation.in_dim,), clip=norm_clip))
        self.adaptation = AdaptationModule(adaptation)

    def z(self, obs: dict[str, torch.Tensor]) -> torch.Tensor:
        return self.adaptation(self.hist_norm(obs["proprio_hist"]))  # (B, T, D) -> (B, Z)

    @classmethod
    def from_teacher(
        cls, teacher: PrivilegedExtractor, observation_space: spaces.Dict, adaptation: AdaptationConfig | None = None
    ) -> StudentExtractor:
        """A student extractor with the teacher's proprio normalization (copied) and a fresh adaptation module."""
        adaptation = adaptation or AdaptationConfig(latent_dim=teacher.latent_dim)
        if adaptation.latent_dim != teacher.latent_dim:
            raise ValueError(
                f"adaptation latent_dim {adaptation.latent_dim} != teacher latent_dim {teacher.latent_dim}"
            )
        student = cls(observation_space, adaptation, norm_clip=teacher.proprio_norm.cfg.clip)
        student.proprio_norm.load_state_dict(teacher.proprio_norm.state_dict())
        student.hist_norm.load_state_dict(teacher.proprio_norm.state_dict())
        return student


LATENT_MIX_GROUP = "latent_mix"
"""Training-only observation group (B, 1) of :class:`LatentMixExtractor`: the weight w of the teacher's z, drawn per
episode by rotation.train.vec_env.RotateCupSB3VecEnv (``latent_mix``)."""


class LatentMixExtractor(StudentExtractor):
    """Student features whose latent is moved toward a frozen teacher's: ``z = phi + w (mu(priv) - phi)``.

    For PPO fine-tuning of a student's actor (`rotate finetune-student --latent-mix P`) only. ``w`` comes per episode
    from the ``latent_mix`` group: 0 in most episodes (the student's own latent, as it acts alone), uniform in
    [0, 1] in a share P of them, the kind of partial correction a tactile adapter makes. Trained on its own latent
    alone, an actor learns to distrust z where phi is often wrong (friction, mass) and then gains little when an
    adapter corrects z; here it also meets informative latents and is rewarded for using them. The teacher's
    env-factor encoder is frozen; a bundle keeps only the student's part (:attr:`bundle_skip`).
    """

    bundle_skip = ("teacher_encoder.",)
    """State-dict prefixes that are not part of the student's acting path (PolicyBundle.from_sb3 drops them)."""

    def __init__(
        self,
        observation_space: spaces.Dict,
        adaptation: AdaptationConfig | None = None,
        norm_clip: float = 5.0,
        teacher_encoder: EnvFactorEncoderConfig | None = None,
    ) -> None:
        super().__init__(observation_space, adaptation, norm_clip=norm_clip)
        name = type(self).__name__
        teacher_encoder = teacher_encoder or EnvFactorEncoderConfig(latent_dim=self.latent_dim)
        if teacher_encoder.latent_dim != self.latent_dim:
            raise ValueError(f"{name}: the teacher's latent has {teacher_encoder.latent_dim} dims, the student's "
                             f"{self.latent_dim}")
        _check_shape(_group_shape(observation_space, "priv", name), (teacher_encoder.in_dim,), "priv", name)
        _check_shape(_group_shape(observation_space, LATENT_MIX_GROUP, name), (1,), LATENT_MIX_GROUP, name)
        self.teacher_encoder = EnvFactorEncoder(teacher_encoder)
        for p in self.teacher_encoder.parameters():
            p.requires_grad_(False)

    def z(self, obs: dict[str, torch.Tensor]) -> torch.Tensor:
        phi = super().z(obs)  # (B, Z)
        with torch.no_grad():
            z_teacher = self.teacher_encoder(obs["priv"])  # (B, Z)
        return phi + obs[LATENT_MIX_GROUP] * (z_teacher - phi)  # w (B, 1) broadcast over Z


class StudentPPOPolicy(MultiInputActorCriticPolicy):
    """SB3 policy for PPO fine-tuning of a distilled student (`rotate finetune-student`): asymmetric actor-critic.

    The actor is the student's acting path: features from :class:`StudentExtractor` (z estimated by phi over
    ``proprio_hist``), then the actor MLP. phi and its history normalization are frozen, so the latent stays an
    estimate of the teacher's z (what a tactile adapter corrects toward); only the actor MLP, the action head, the
    actor's proprio normalization and the action std learn. The critic reads the privileged groups through its own
    :class:`PrivilegedExtractor` (a fresh env-factor encoder of ``critic_encoder`` sizes): values need not be
    guessed from history, only actions must.
    """

    def __init__(self, *args, critic_encoder: EnvFactorEncoderConfig | None = None, **kwargs) -> None:
        self.critic_encoder = critic_encoder or EnvFactorEncoderConfig()
        kwargs["share_features_extractor"] = False
        super().__init__(*args, **kwargs)
        actor = self.pi_features_extractor
        if not isinstance(actor, StudentExtractor):
            raise ValueError(f"StudentPPOPolicy needs features_extractor_class=StudentExtractor, got "
                             f"{type(actor).__name__}")
        for p in actor.adaptation.parameters():
            p.requires_grad_(False)
        actor.hist_norm.frozen = True

    def _build(self, lr_schedule) -> None:
        actor = self.pi_features_extractor
        self.vf_features_extractor = PrivilegedExtractor(self.observation_space, self.critic_encoder,
                                                         norm_clip=actor.proprio_norm.cfg.clip)
        if self.vf_features_extractor.features_dim != actor.features_dim:
            raise ValueError(f"critic latent size {self.critic_encoder.latent_dim} differs from the student's "
                             f"{actor.latent_dim}")
        super()._build(lr_schedule)

    def _get_constructor_parameters(self) -> dict:
        return super()._get_constructor_parameters() | {"critic_encoder": self.critic_encoder}
