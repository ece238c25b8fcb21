"""RotateCup-v0 through the public doors: gymnasium's and SB3's env checkers, gymnasium.make / make_vec with
keyword arguments reaching EnvConfig, the observation contract, and same-step auto-reset of the vector env."""

from __future__ import annotations

import warnings

import gymnasium as gym
import numpy as np
from gymnasium.utils.env_checker import check_env as gym_check_env
from gymnasium.vector import AutoresetMode
from stable_baselines3.common.env_checker import check_env as sb3_check_env

import envs
from envs import constants as C
from envs.rotate_cup import RotateCupEnv
from envs.vector import RotateCupVectorEnv

OBS_SHAPES = {"proprio": (C.PROPRIO_STEPS, C.PROPRIO_DIM), "proprio_hist": (C.HISTORY_STEPS, C.PROPRIO_DIM),
              "priv": (C.PRIV_DIM,)}
INFO_KEYS = {"rotation", "height", "tilt", "lin_vel", "torque", "fell", "elapsed_steps", "rew_rotate", "rew_obj_linvel",
             "rew_pose_diff", "rew_torque", "rew_work", "rew_tilt", "rew_fall"}


def test_gymnasium_env_checker():
    env = RotateCupEnv()
    with warnings.catch_warnings():
        # unbounded Box observations are what the env declares on purpose (raw positions, targets, priv)
        warnings.filterwarnings("ignore", message=".*Box observation space (minimum|maximum) value is")
        gym_check_env(env, skip_render_check=True)
    env.close()


def test_sb3_env_checker():
    with warnings.catch_warnings():
        # SB3 notes that (3, 32) and (30, 32) groups are neither images nor flat: the policies read them as such
        warnings.filterwarnings("ignore", message=".*unconventional shape")
        sb3_check_env(RotateCupEnv(object="cylinder"), warn=True)


def check_obs(obs: dict, space: gym.spaces.Dict, batch: tuple[int, ...] = ()) -> None:
    assert set(obs) == set(OBS_SHAPES)
    for k, shape in OBS_SHAPES.items():
        assert obs[k].shape == batch + shape and obs[k].dtype == np.float32, k
        assert np.all(np.isfinite(obs[k])), k
    if not batch:
        assert space.contains(obs)


def test_make_with_module_prefix_passes_kwargs_to_the_config():
    env = gym.make("envs:RotateCup-v0", object="cylinder", episode_steps=3, randomization={"mass": (0.1, 0.1)})
    cfg = env.unwrapped.cfg
    assert isinstance(env.unwrapped, RotateCupEnv) and env.spec.id == envs.ENV_ID
    assert (cfg.object, cfg.episode_steps, cfg.randomization.mass) == ("cylinder", 3, (0.1, 0.1))
    obs, info = env.reset(seed=0)
    check_obs(obs, env.observation_space)
    assert info == {}
    assert obs["priv"][C.PRIV_FIELDS.index("mass")] == np.float32(0.1)
    # at reset the history is the reset pose, as both q (scaled to [-1, 1]) and target (rad)
    frame = obs["proprio_hist"][0]
    np.testing.assert_array_equal(obs["proprio_hist"], np.broadcast_to(frame, (C.HISTORY_STEPS, C.PROPRIO_DIM)))
    np.testing.assert_allclose(C.unscale_joints(frame[:16].astype(np.float64)), frame[16:], atol=1e-6)
    for t in range(3):
        obs, reward, terminated, truncated, info = env.step(env.action_space.sample())
        check_obs(obs, env.observation_space)
        assert isinstance(reward, float) and np.isfinite(reward)
        assert isinstance(terminated, bool) and isinstance(truncated, bool)
        assert set(info) == INFO_KEYS and info["elapsed_steps"] == t + 1
        assert all(np.isfinite(v) for v in info.values())
        # the reward is the sum of the scaled terms reported one by one
        assert np.isclose(reward, sum(v for k, v in info.items() if k.startswith("rew_")), rtol=1e-12, atol=0)
    assert truncated or terminated  # episode_steps=3 ends it
    env.close()


def test_make_by_plain_id_after_import():
    env = gym.make("RotateCup-v0", object="cylinder", control_hz=10.0)
    assert env.unwrapped.cfg.object == "cylinder" and env.unwrapped.cfg.substeps == 10
    check_obs(env.reset(seed=1)[0], env.observation_space)
    env.close()


def test_make_vec_is_the_batched_env_with_same_step_autoreset():
    venv = gym.make_vec("envs:RotateCup-v0", num_envs=3, vectorization_mode="vector_entry_point", episode_steps=2,
                        object="cylinder")
    assert isinstance(venv, RotateCupVectorEnv) and venv.num_envs == 3 and venv.core.num_envs == 3
    assert venv.metadata["autoreset_mode"] == AutoresetMode.SAME_STEP
    assert venv.cfg.object == "cylinder"
    assert venv.action_space.shape == (3, 16) and venv.observation_space["priv"].shape == (3, 9)
    obs, _ = venv.reset(seed=0)
    check_obs(obs, venv.single_observation_space, (3,))
    obs, reward, terminated, truncated, info = venv.step(np.zeros((3, 16)))
    assert "final_obs" not in info and reward.shape == (3,)
    assert set(info) == INFO_KEYS and all(v.shape[0] == 3 for v in info.values())
    obs, reward, terminated, truncated, info = venv.step(np.zeros((3, 16)))
    np.testing.assert_array_equal(truncated, [True, True, True])  # episode_steps = 2 (none fell holding still)
    np.testing.assert_array_equal(info["_final_obs"], [True, True, True])
    check_obs(info["final_obs"], venv.single_observation_space, (3,))
    np.testing.assert_array_equal(info["final_info"]["elapsed_steps"], [2, 2, 2])
    # the returned observation is already the first of the next episode: a history filled with one frame
    for i in range(3):
        assert np.all(obs["proprio_hist"][i] == obs["proprio_hist"][i, :1])
        assert not np.all(info["final_obs"]["proprio_hist"][i] == info["final_obs"]["proprio_hist"][i, :1])
    np.testing.assert_array_equal(venv.core.steps, [0, 0, 0])
    np.testing.assert_array_equal(venv.core.episode, [1, 1, 1])
    venv.close()


def test_env_renders_nothing_without_a_render_mode():
    env = RotateCupEnv()
    env.reset(seed=0)
    assert env.render() is None
