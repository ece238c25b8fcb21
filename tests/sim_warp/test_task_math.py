"""The task math written once (envs.task) gives the same numbers on numpy and on torch, and the torch port of the
counter-based random streams draws exactly envs.rng's numbers."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from envs import task
from envs.config import EnvConfig, Perturbation, RandomizationConfig
from envs.geometry import angular_velocity, tilt_angle
from envs.rng import CounterRNG, env_keys
from rotation.sim_warp.rng import TorchCounterRNG
from rotation.sim_warp.rng import env_keys as torch_keys


@pytest.mark.parametrize("seed", [0, 11, 2**64 - 2])
def test_torch_streams_match_envs_rng_bit_for_bit(seed):
    n = 6
    cpu, dev = CounterRNG(env_keys(seed, n)), TorchCounterRNG(torch_keys(seed, n, "cpu"))
    episode = np.array([0, 1, 2, 40, 2**30, 5])
    step = np.array([0, 1, 399, 7, 100_000, 3])
    for stream, size in ((1, task.PARAM_DRAWS), (2, 16), (3, 1)):
        ref = cpu.uniform(np.arange(n), episode, step, stream, size)
        got = dev.uniform(torch.as_tensor(episode), torch.as_tensor(step), stream, size).numpy()
        assert np.array_equal(ref, got)
    ref = cpu.normal(np.arange(n), episode, step, 4, 3)
    got = dev.normal(torch.as_tensor(episode), torch.as_tensor(step), 4, 3).numpy()
    np.testing.assert_allclose(got, ref, rtol=0, atol=1e-12)  # log / cos may differ in the last bit


@pytest.mark.parametrize("cfg", [
    EnvConfig(),
    EnvConfig(randomization=RandomizationConfig(enabled=False), object="cylinder",
              perturb=Perturbation(friction_scale=0.5, added_mass=0.1, com_shift=(0.01, 0.0, -0.01))),
])
def test_sampled_parameters_agree(cfg):
    u = np.random.default_rng(0).uniform(size=(64, task.PARAM_DRAWS))
    ref = task.sample_params(np, cfg, u)
    got = task.sample_params(torch, cfg, torch.as_tensor(u))
    assert set(ref) == set(got)
    for k in ref:  # a log-uniform range goes through pow, which numpy and torch may round differently in the last bit
        np.testing.assert_allclose(got[k].numpy(), ref[k], rtol=1e-12, atol=0, err_msg=k)
        assert got[k].numpy().dtype.kind == np.asarray(ref[k]).dtype.kind, k


def test_reward_terms_and_geometry_agree():
    rng = np.random.default_rng(1)
    n, cfg = 32, EnvConfig()
    quat0, quat = rng.normal(size=(n, 4)), rng.normal(size=(n, 4))
    quat0 /= np.linalg.norm(quat0, axis=1, keepdims=True)
    quat /= np.linalg.norm(quat, axis=1, keepdims=True)
    state = dict(q=rng.normal(size=(n, 16)), qdot=rng.normal(size=(n, 16)), tau=rng.normal(size=(n, 16)),
                 qpos=rng.normal(size=(n, 23)), qvel=rng.normal(size=(n, 22)), pos0=rng.normal(size=(n, 3)) * 0.01,
                 quat0=quat0, pos=rng.normal(size=(n, 3)) * 0.05, quat=quat, grasp_q=rng.normal(size=(n, 16)),
                 start_pos=rng.normal(size=(n, 3)) * 0.01, axis=np.array(cfg.reward.axis))
    state["qpos"][3, 5] = np.nan  # one non-finite simulation
    ref = task.reward_and_termination(np, cfg, **state)
    got = task.reward_and_termination(torch, cfg, **{k: torch.as_tensor(v) for k, v in state.items()})
    for k in ("reward", "fell", "finite", "spin", "lin_vel", "tilt"):
        np.testing.assert_allclose(got[k].numpy(), ref[k], rtol=1e-12, atol=1e-12, err_msg=k)
    for k in ref["terms"]:
        np.testing.assert_allclose(got["terms"][k].numpy(), ref["terms"][k], rtol=1e-12, atol=1e-12, err_msg=k)
    np.testing.assert_allclose(angular_velocity(torch.as_tensor(quat0), torch.as_tensor(quat), 0.05, torch).numpy(),
                               angular_velocity(quat0, quat, 0.05), rtol=1e-12, atol=1e-12)
    np.testing.assert_allclose(tilt_angle(torch.as_tensor(quat), torch).numpy(), tilt_angle(quat), atol=1e-12)
