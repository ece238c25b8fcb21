"""The batched core against single envs: env i of a batch seeded s is a single env seeded s + i, bit for bit.

MuJoCo's batch steps each simulation with the same code whatever the thread that runs it, and the env's numpy work
is elementwise per env, so the comparisons are exact (np.testing.assert_array_equal), threads or not.
"""

from __future__ import annotations

import gymnasium as gym
import numpy as np
import pytest

from envs import EnvConfig, RotateCupVec
from envs.rotate_cup import RotateCupEnv
from envs.vector import RotateCupVectorEnv

SEED = 5
EPISODE_STEPS = 8
STEPS = 20


def scripted_actions(steps: int, num_envs: int = 3) -> np.ndarray:
    """(steps, N, 16): env 0 opens the hand (the object falls: terminations), env 1 acts randomly, env 2 holds
    still; with EPISODE_STEPS = 8 the envs that keep the object are truncated at steps 8 and 16."""
    a = np.zeros((steps, num_envs, 16))
    a[:, 0] = -1.0
    a[:, 1] = np.random.default_rng(0).uniform(-1.0, 1.0, (steps, 16))
    return a


def assert_same(batched: dict, single: dict, i: int, what: str) -> None:
    assert batched.keys() == single.keys(), what
    for k in batched:
        np.testing.assert_array_equal(batched[k][i], single[k], err_msg=f"{what}: {k}, env {i}")


def single_envs(cfg: EnvConfig, n: int, seed: int) -> tuple[list[RotateCupEnv], list[dict]]:
    envs = [RotateCupEnv(cfg) for _ in range(n)]
    return envs, [e.reset(seed=seed + i)[0] for i, e in enumerate(envs)]


def test_core_matches_single_envs_across_resets():
    """RotateCupVec (N = 3, seed s, 2 threads; done envs reset by id) vs RotateCupEnv seeded s, s+1, s+2."""
    cfg = EnvConfig(episode_steps=EPISODE_STEPS)
    core = RotateCupVec(cfg, num_envs=3, seed=0, nthread=2)
    obs = core.reset(seed=SEED)
    singles, single_obs = single_envs(cfg, 3, SEED)
    for i in range(3):
        assert_same(obs, single_obs[i], i, "reset")
    ends = {"terminated": 0, "truncated": 0}
    for t, actions in enumerate(scripted_actions(STEPS)):
        obs, reward, terminated, truncated, info = core.step(actions)
        for i, env in enumerate(singles):
            o, r, te, tr, inf = env.step(actions[i])
            assert_same(obs, o, i, f"step {t}")
            assert (reward[i], terminated[i], truncated[i]) == (r, te, tr), f"step {t}, env {i}"
            assert_same(info, inf, i, f"info at step {t}")
            if te or tr:
                single_obs[i] = env.reset()[0]
        done = np.flatnonzero(terminated | truncated)
        ends["terminated"] += int(terminated.sum())
        ends["truncated"] += int(truncated.sum())
        if len(done):
            obs = core.reset(ids=done)
            for i in done:
                assert_same(obs, single_obs[i], i, f"reset after step {t}")
    # the scripted actions made both kinds of episode ends happen, so resets were really compared
    assert ends["terminated"] >= 1 and ends["truncated"] >= 4


def test_gymnasium_vector_env_matches_single_envs_across_autoresets():
    """make_vec's batched env (same-step auto-reset) vs single envs reset by hand; final_obs = the single's last."""
    cfg = EnvConfig(episode_steps=EPISODE_STEPS)
    venv = gym.make_vec("envs:RotateCup-v0", num_envs=3, vectorization_mode="vector_entry_point", cfg=cfg)
    obs, _ = venv.reset(seed=SEED)
    singles, single_obs = single_envs(cfg, 3, SEED)
    autoresets = 0
    for t, actions in enumerate(scripted_actions(STEPS)):
        obs, reward, terminated, truncated, info = venv.step(actions)
        for i, env in enumerate(singles):
            o, r, te, tr, inf = env.step(actions[i])
            assert (reward[i], terminated[i], truncated[i]) == (r, te, tr), f"step {t}, env {i}"
            assert info["_final_obs"][i] == (te or tr) if "_final_obs" in info else not (te or tr)
            if te or tr:
                assert_same(info["final_obs"], o, i, f"final obs at step {t}")
                assert_same(info["final_info"], inf, i, f"final info at step {t}")
                assert inf["elapsed_steps"] == EPISODE_STEPS if tr else 1 <= inf["elapsed_steps"] < EPISODE_STEPS
                o = env.reset()[0]  # the batched env returned the first observation of the next episode
                autoresets += 1
            assert_same(obs, o, i, f"step {t}")
    venv.close()
    assert autoresets >= 5


def test_same_seed_same_trajectory_different_seed_differs():
    cfg = EnvConfig()
    actions = np.random.default_rng(1).uniform(-1.0, 1.0, (10, 4, 16))

    def rollout(seed: int, nthread: int):
        core = RotateCupVec(cfg, num_envs=4, seed=seed, nthread=nthread)
        out = [core.reset()]
        for a in actions:
            obs, reward, terminated, truncated, info = core.step(a)
            out.append({**obs, "reward": reward, "terminated": terminated, "height": info["height"]})
        return out

    a, b, c = rollout(3, 1), rollout(3, 2), rollout(4, 1)
    for t, (x, y) in enumerate(zip(a, b, strict=True)):  # same seed (and any thread count): identical
        for k in x:
            np.testing.assert_array_equal(x[k], y[k], err_msg=f"step {t}: {k}")
    # a different seed: other objects, other grasps, other noise, from the first observation on
    assert not np.array_equal(a[0]["priv"], c[0]["priv"])
    assert not np.array_equal(a[0]["proprio"], c[0]["proprio"])
    assert not np.array_equal(a[-1]["reward"], c[-1]["reward"])
    # env i of seed 4 is env i + 1 of seed 3 (keys are seed + i)
    np.testing.assert_array_equal(a[0]["priv"][1:], c[0]["priv"][:-1])


def test_reseeding_restarts_the_streams():
    core = RotateCupVec(EnvConfig(), num_envs=2, seed=0, nthread=1)
    first = core.reset(seed=7)
    for _ in range(3):
        core.step(np.full((2, 16), 0.5))
    later = core.reset()  # no seed: the next episode, other parameters
    assert not np.array_equal(first["priv"], later["priv"])
    again = core.reset(seed=7)
    for k in first:
        np.testing.assert_array_equal(first[k], again[k])


def test_partial_reset_leaves_other_envs_alone():
    core = RotateCupVec(EnvConfig(), num_envs=3, seed=0, nthread=1)
    core.reset(seed=0)
    before, _, _, _, _ = core.step(np.zeros((3, 16)))
    after = core.reset(ids=[1])
    for k in before:
        np.testing.assert_array_equal(after[k][[0, 2]], before[k][[0, 2]], err_msg=k)
    assert not np.array_equal(after["priv"][1], before["priv"][1])
    np.testing.assert_array_equal(core.episode, [0, 1, 0])
    np.testing.assert_array_equal(core.steps, [1, 0, 1])


@pytest.mark.parametrize("front", ["core", "gymnasium"])
def test_long_random_rollout_stays_finite(front):
    """16 envs x 300 steps of uniform random actions with resets: every number the env returns is finite."""
    n, steps = 16, 300
    rng = np.random.default_rng(0)
    if front == "core":
        env = RotateCupVec(EnvConfig(), num_envs=n, seed=0, nthread=2)
        obs = env.reset(seed=0)
    else:
        env = RotateCupVectorEnv(n, cfg=EnvConfig(), nthread=2)
        obs, _ = env.reset(seed=0)
    ends = 0
    for _ in range(steps):
        obs, reward, terminated, truncated, info = env.step(rng.uniform(-1.0, 1.0, (n, 16)))
        arrays = [reward, *obs.values(), *(v for k, v in info.items() if not k.startswith(("final", "_final")))]
        if "final_obs" in info:
            arrays += [*info["final_obs"].values(), *info["final_info"].values()]
        for x in arrays:
            assert np.all(np.isfinite(x))
        done = np.flatnonzero(terminated | truncated)
        ends += len(done)
        if front == "core" and len(done):
            obs = env.reset(ids=done)
    assert ends > 0  # random actions drop some objects: the resets were exercised


def test_constructor_seed_is_the_first_reset_seed():
    """RotateCupVec(seed=s).reset() starts the same episodes as reset(seed=s) (and as single envs seeded s + i)."""
    a = RotateCupVec(EnvConfig(), num_envs=3, seed=6, nthread=1).reset()
    b = RotateCupVec(EnvConfig(), num_envs=3, seed=0, nthread=1).reset(seed=6)
    single = RotateCupEnv().reset(seed=8)[0]
    for k in a:
        np.testing.assert_array_equal(a[k], b[k], err_msg=k)
        np.testing.assert_array_equal(a[k][2], single[k], err_msg=k)
