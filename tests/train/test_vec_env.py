"""The SB3 adapter of the batched env: auto-reset with `terminal_observation`, `TimeLimit.truncated` on time-limit
ends only, per-episode statistics in `infos[i]["episode"]`, all checked against the bare core stepped in parallel."""

from __future__ import annotations

import numpy as np
import pytest

from envs import EnvConfig, RotateCupVec
from rotation.train.vec_env import RotateCupSB3VecEnv

pytestmark = pytest.mark.filterwarnings("ignore:The `render_mode` attribute is not defined")


def test_time_limit_end():
    """episode_steps = 3: every env ends at step 3 as a time-limit end; SB3 must bootstrap it."""
    cfg = EnvConfig(episode_steps=3)
    env = RotateCupSB3VecEnv(cfg, num_envs=2, seed=4, nthread=1, reward_scale=0.5)
    ref = RotateCupVec(cfg, num_envs=2, seed=4, nthread=1)
    obs, ref_obs = env.reset(), ref.reset()
    for k in ref_obs:
        np.testing.assert_array_equal(obs[k], ref_obs[k])
    actions = np.random.default_rng(0).uniform(-0.2, 0.2, (3, 2, 16)).astype(np.float32)
    ret = np.zeros(2)
    for t in range(3):
        obs, reward, done, infos = env.step(actions[t])
        ref_obs, ref_reward, terminated, truncated, info = ref.step(actions[t])
        ret += ref_reward
        assert reward.dtype == np.float32
        np.testing.assert_array_equal(reward, (0.5 * ref_reward).astype(np.float32))  # reward_scale: learner only
        if t < 2:
            assert not done.any() and infos == [{}, {}]
    np.testing.assert_array_equal(done, [True, True])
    assert not terminated.any() and truncated.all()
    for i, inf in enumerate(infos):
        assert inf["TimeLimit.truncated"] is True
        for k in ref_obs:  # the last observation of the finished episode
            np.testing.assert_array_equal(inf["terminal_observation"][k], ref_obs[k][i])
        ep = inf["episode"]
        assert ep["l"] == 3 and ep["ttf"] == 1.0
        assert ep["r"] == ret[i]  # the unscaled return, summed in the same order
        assert ep["rotation"] == pytest.approx(ref_rotation_sum(cfg, actions, i), rel=1e-12, abs=1e-15)
        assert ep["rotation_rate"] == pytest.approx(ep["rotation"] / (3 * 0.05), rel=1e-12)
        assert {f"rew_{k}" for k in ("rotate", "obj_linvel", "pose_diff", "torque", "work", "fall")} <= set(ep)
        assert ep["r"] == pytest.approx(sum(v for k, v in ep.items() if k.startswith("rew_")), rel=1e-12)
    # the returned observation starts the next episode, exactly as a reset of those envs in the core
    fresh = ref.reset(ids=[0, 1])
    for k in fresh:
        np.testing.assert_array_equal(obs[k], fresh[k])
    # and the episode accumulators restarted: one more step reports nothing
    obs, reward, done, infos = env.step(np.zeros((2, 16), np.float32))
    assert not done.any() and infos == [{}, {}]


def ref_rotation_sum(cfg: EnvConfig, actions: np.ndarray, i: int) -> float:
    core = RotateCupVec(cfg, num_envs=2, seed=4, nthread=1)
    core.reset()
    return float(sum(core.step(a)[4]["rotation"][i] for a in actions))


def test_termination_is_not_a_time_limit():
    """Env 0 opens the hand and drops the object; env 1 holds still and goes on."""
    cfg = EnvConfig(episode_steps=50)
    env = RotateCupSB3VecEnv(cfg, num_envs=2, seed=5, nthread=1)
    env.reset()
    actions = np.zeros((2, 16), np.float32)
    actions[0] = -1.0
    done, t = np.zeros(2, bool), 0
    while not done.any() and t < 49:
        obs, reward, done, infos = env.step(actions)
        t += 1
    np.testing.assert_array_equal(done, [True, False])
    assert infos[1] == {}
    inf = infos[0]
    assert inf["TimeLimit.truncated"] is False
    assert inf["episode"]["l"] == t and inf["episode"]["ttf"] == pytest.approx(t / 50)
    assert inf["terminal_observation"]["priv"].shape == (9,)
    assert env.core.episode.tolist() == [1, 0] and env.core.steps.tolist() == [0, t]


def test_seeding_and_vec_env_methods():
    cfg = EnvConfig()
    env = RotateCupSB3VecEnv(cfg, num_envs=3, seed=0, nthread=1)
    assert env.seed(9) == [9, 10, 11]
    obs = env.reset()
    ref = RotateCupVec(cfg, num_envs=3, seed=9, nthread=1).reset(seed=9)
    np.testing.assert_array_equal(obs["priv"], ref["priv"])
    again = env.reset()  # without a new seed, the next episodes: other objects
    assert not np.array_equal(again["priv"], obs["priv"])
    assert env.get_attr("num_envs") == [3, 3, 3] and env.get_attr("num_envs", indices=1) == [3]
    assert env.env_is_wrapped(object) == [False] * 3
    assert env.env_method("reset", indices=[0])[0]["priv"].shape == (3, 9)
    assert env.observation_space["proprio"].shape == (3, 32) and env.action_space.shape == (16,)
    env.close()
