"""Shapes and contracts of the policy networks and SB3 extractors."""

from __future__ import annotations

import numpy as np
import pytest
import torch
from gymnasium import spaces
from torch import nn

from rotation.policy.features import PrivilegedExtractor, StudentExtractor, policy_kwargs
from rotation.policy.networks import (
    AdaptationConfig,
    AdaptationModule,
    EnvFactorEncoder,
    RunningNorm,
    RunningNormConfig,
    mlp,
)


def obs_space(**extra) -> spaces.Dict:
    groups = {
        "proprio": spaces.Box(-np.inf, np.inf, (3, 32), np.float32),
        "proprio_hist": spaces.Box(-np.inf, np.inf, (30, 32), np.float32),
        "priv": spaces.Box(-np.inf, np.inf, (9,), np.float32),
        **extra,
    }
    return spaces.Dict(groups)


def random_obs(b: int) -> dict[str, torch.Tensor]:
    g = torch.Generator().manual_seed(0)
    return {
        "proprio": torch.randn(b, 3, 32, generator=g),
        "proprio_hist": torch.randn(b, 30, 32, generator=g),
        "priv": torch.rand(b, 9, generator=g),
    }


def test_mlp_layout_matches_sb3():
    net = mlp([104, 512, 256, 128], nn.ELU, activate_last=True)
    assert [type(m) for m in net] == [nn.Linear, nn.ELU] * 3
    assert [m.out_features for m in net if isinstance(m, nn.Linear)] == [512, 256, 128]
    assert isinstance(mlp([4, 3, 2])[-1], nn.Linear)
    with pytest.raises(ValueError):
        mlp([4])


def test_env_factor_encoder_shape_and_range():
    enc = EnvFactorEncoder()
    z = enc(torch.randn(5, 9) * 100)
    assert z.shape == (5, 8)
    assert torch.all(z.abs() <= 1.0)


def test_adaptation_module_lengths_and_shape():
    cfg = AdaptationConfig()
    assert cfg.conv_lengths() == [30, 11, 7, 3]
    phi = AdaptationModule(cfg)
    assert phi.proj.in_features == 96
    z = phi(torch.randn(4, 30, 32))
    assert z.shape == (4, 8)
    assert torch.all(z.abs() < 1.0)
    with pytest.raises(ValueError, match="too short"):
        AdaptationConfig(steps=10).conv_lengths()


def test_running_norm_matches_numpy_moments():
    norm = RunningNorm(RunningNormConfig(shape=(3,), clip=100.0))
    data = np.random.default_rng(0).normal([1.0, -2.0, 5.0], [0.5, 2.0, 3.0], size=(700, 3)).astype(np.float32)
    for chunk in np.array_split(data, 7):  # batched updates must equal the moments of everything seen
        norm(torch.from_numpy(chunk).reshape(-1, 1, 3))  # (B, 1, 3): leading dims are pooled
    np.testing.assert_allclose(norm.mean.numpy(), data.mean(0), rtol=1e-5, atol=1e-5)
    np.testing.assert_allclose(norm.var.numpy(), data.var(0), rtol=1e-4)
    assert norm.count.item() == 700
    norm.eval()
    y = norm(torch.from_numpy(data))
    assert norm.count.item() == 700  # frozen in eval mode
    np.testing.assert_allclose(y.mean(0).numpy(), 0.0, atol=1e-4)
    assert set(dict(norm.named_buffers())) == {"mean", "var", "count"}


def test_running_norm_clips():
    norm = RunningNorm(RunningNormConfig(shape=(2,), clip=5.0)).eval()
    assert torch.equal(norm(torch.tensor([[100.0, -100.0]])), torch.tensor([[5.0, -5.0]]))


def test_privileged_extractor_features_and_latent():
    ext = PrivilegedExtractor(obs_space(tactile=spaces.Box(0, 1, (4,), np.float32)))  # extra groups ignored
    obs = random_obs(6)
    feats = ext(obs)
    assert ext.features_dim == 104
    assert feats.shape == (6, 104)
    assert torch.equal(feats[:, 96:], ext.z(obs))


def test_student_extractor_matches_teacher_layout():
    teacher = PrivilegedExtractor(obs_space())
    teacher(random_obs(64))  # training mode: moves the proprio statistics away from the identity
    student = StudentExtractor.from_teacher(teacher, obs_space())
    assert student.features_dim == teacher.features_dim == 104
    torch.testing.assert_close(student.proprio_norm.mean, teacher.proprio_norm.mean)
    teacher.eval()
    student.eval()
    obs = random_obs(3)
    fs, ft = student(obs), teacher(obs)
    assert fs.shape == (3, 104)
    torch.testing.assert_close(fs[:, :96], ft[:, :96])  # same normalized proprioception
    assert torch.equal(fs[:, 96:], student.z(obs))


def test_extractors_reject_missing_or_wrong_groups():
    with pytest.raises(ValueError, match="'priv'"):
        PrivilegedExtractor(spaces.Dict({"proprio": spaces.Box(-1, 1, (3, 32), np.float32)}))
    with pytest.raises(ValueError, match=r"expected \(9,\)"):
        PrivilegedExtractor(obs_space(priv=spaces.Box(-1, 1, (7,), np.float32)))
    with pytest.raises(ValueError, match="proprio_hist"):
        StudentExtractor(obs_space(proprio_hist=spaces.Box(-1, 1, (20, 32), np.float32)))


def test_sb3_policy_builds_with_extractor():
    from stable_baselines3.common.policies import MultiInputActorCriticPolicy

    space = obs_space()
    policy = MultiInputActorCriticPolicy(
        space, spaces.Box(-1, 1, (16,), np.float32), lambda _: 3e-4, **policy_kwargs()
    )
    obs = random_obs(2)
    actions, values, log_prob = policy(obs, deterministic=True)
    assert actions.shape == (2, 16) and values.shape == (2, 1) and log_prob.shape == (2,)
    assert isinstance(policy.features_extractor, PrivilegedExtractor)
