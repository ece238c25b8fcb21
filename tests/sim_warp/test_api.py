"""The Warp backend's contract: the CPU backend's spaces, errors on bad input, and the gymnasium vector entry point
(torch tensors on the device, same-step auto-reset)."""

from __future__ import annotations

import gymnasium as gym
import numpy as np
import pytest
import torch

from envs.config import EnvConfig
from envs.core import RotateCupVec
from rotation.sim_warp.core import RotateCupWarp, WarpConfig

NUM_WORLDS = 3
"""The size of the session's warp_env (tests/sim_warp/conftest.py)."""
HAND = "digit360"
"""The hand of the session's warp_env, the one the warp backend simulates (it refuses the digit360_v4 hand's)."""


def test_same_spaces(warp_env):
    cpu = RotateCupVec(EnvConfig(hand=HAND), num_envs=1, nthread=1)
    assert warp_env.single_observation_space == cpu.single_observation_space
    assert warp_env.single_action_space == cpu.single_action_space


def _message(fn):
    with pytest.raises((ValueError, RuntimeError)) as err:
        fn()
    return type(err.value), str(err.value)


@pytest.mark.parametrize("actions", [np.zeros((NUM_WORLDS, 15)), np.zeros((NUM_WORLDS + 1, 16)),
                                     np.where(np.eye(NUM_WORLDS, 16) > 0, np.nan, 0.0),
                                     np.where(np.eye(NUM_WORLDS, 16) > 0, np.inf, 0.0)])
def test_same_errors_on_bad_actions(warp_env, actions):
    cpu = RotateCupVec(EnvConfig(hand=HAND), num_envs=NUM_WORLDS, nthread=1)
    cpu.reset(seed=0)
    warp_env.reset(seed=0)
    assert _message(lambda: warp_env.step(torch.as_tensor(actions))) == _message(lambda: cpu.step(actions))


@pytest.mark.parametrize("kwargs", [dict(num_envs=0), dict(num_envs=2.5), dict(num_envs=True), dict(seed=-1),
                                    dict(seed=2**64), dict(cfg="cup")])
def test_same_errors_on_bad_arguments(kwargs):
    args = dict(cfg=EnvConfig(hand=HAND), num_envs=2, seed=0) | kwargs
    cpu = _message(lambda: RotateCupVec(**args, nthread=1))
    assert _message(lambda: RotateCupWarp(**args, warp_cfg=WarpConfig(device="cpu"))) == cpu


def test_step_before_reset_and_cpu_only_features():
    env = RotateCupWarp(EnvConfig(hand=HAND), num_envs=1, warp_cfg=WarpConfig(device="cpu"))
    with pytest.raises(RuntimeError, match="call reset"):
        env.step(torch.zeros(1, 16))
    with pytest.raises(ValueError, match="tactile: the simulated Digit 360 runs on the cpu backend only"):
        RotateCupWarp(EnvConfig(hand=HAND, tactile=True), num_envs=1, warp_cfg=WarpConfig(device="cpu"))
    with pytest.raises(ValueError, match="digit360_v4 hand's physics .* cpu backend only for now; use --backend cpu"):
        RotateCupWarp(EnvConfig(hand="digit360_v4"), num_envs=1, warp_cfg=WarpConfig(device="cpu"))
    with pytest.raises(ValueError, match="warp.device"):
        WarpConfig(device="tpu")
    if not torch.cuda.is_available():
        with pytest.raises(ValueError, match="no CUDA GPU"):
            RotateCupWarp(EnvConfig(hand=HAND), num_envs=1, warp_cfg=WarpConfig(device="cuda"))


def test_gymnasium_vector_entry_point():
    env = gym.make_vec("rotation.sim_warp:RotateCupWarp-v0", num_envs=2, vectorization_mode="vector_entry_point",
                       device="cpu", episode_steps=2, hand=HAND)
    obs, _ = env.reset(seed=3)
    assert isinstance(obs["proprio"], torch.Tensor) and tuple(obs["proprio"].shape) == (2, 3, 32)
    assert env.observation_space["priv"].shape == (2, 9)
    obs, reward, terminated, truncated, info = env.step(torch.zeros(2, 16))
    assert reward.shape == (2,) and not (terminated | truncated).any()
    obs, reward, terminated, truncated, info = env.step(torch.zeros(2, 16))
    assert (terminated | truncated).all()  # episode_steps=2: both finished and restarted on the device
    assert info["_final_obs"].all() and info["final_info"]["elapsed_steps"].tolist() == [2, 2]
    assert env.unwrapped.core.steps.tolist() == [0, 0]
    env.close()
    with pytest.raises(ValueError, match="batched"):
        gym.make("rotation.sim_warp:RotateCupWarp-v0")


@pytest.mark.gpu
def test_thousands_of_worlds_on_the_gpu():
    env = RotateCupWarp(EnvConfig(hand=HAND), num_envs=1024, warp_cfg=WarpConfig(device="cuda"))
    obs = env.reset(seed=0)
    assert obs["proprio"].device.type == "cuda"
    for _ in range(5):
        obs, reward, terminated, truncated, _ = env.step(torch.zeros(1024, 16, device="cuda"))
        env.reset_done(terminated | truncated)
    assert torch.isfinite(reward).all() and not terminated.all()
