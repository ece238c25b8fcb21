"""The MuJoCo Warp backend against the CPU backend, on Warp's CPU device with a few worlds.

Both cores seeded alike draw the same parameters, grasps, pushes and noise (rotation.sim_warp.rng), so they start
from identical states and parameters. Stated tolerance over the first two policy steps (10 physics steps), after
which contact dynamics amplify float32-vs-float64 rounding and the two solvers' differences, as two runs of any
chaotic simulation do:

- at reset: observations and parameters equal up to float32 rounding (1e-6);
- joint and object positions (qpos) within 2e-3 (m / rad / quaternion units);
- every observation group within 2e-3;
- every scaled reward term and the reward within 2e-3 (absolute), the termination flags identical.
Over ten policy steps the states stay within 3 cm / 0.05 rad of each other.
"""

from __future__ import annotations

import numpy as np
import pytest
import torch

from envs.config import EnvConfig
from envs.core import RotateCupVec

TOL = 2e-3
SEED = 7
NUM_WORLDS = 3
"""The size of the session's warp_env (tests/sim_warp/conftest.py)."""
HAND = "digit360"
"""The hand of the session's warp_env, the one the warp backend simulates (it refuses the digit360_v4 hand's)."""


@pytest.fixture(scope="module")
def cpu_env():
    env = RotateCupVec(EnvConfig(hand=HAND), num_envs=NUM_WORLDS, seed=SEED, nthread=1)
    yield env
    env.close()


def _host(x):
    return x.detach().cpu().numpy()


def test_identical_start(warp_env, cpu_env):
    oc, ow = cpu_env.reset(seed=SEED), warp_env.reset(seed=SEED)
    assert set(oc) == set(ow) == {"proprio", "proprio_hist", "priv"}
    for k in oc:
        assert ow[k].dtype == torch.float32 and tuple(ow[k].shape) == oc[k].shape
        np.testing.assert_allclose(_host(ow[k]), oc[k], atol=1e-6, err_msg=k)
    for k, v in cpu_env.params.items():
        np.testing.assert_allclose(_host(warp_env.params[k]), v, rtol=1e-6, atol=1e-7, err_msg=k)
    np.testing.assert_allclose(_host(warp_env._qpos), cpu_env._qpos, atol=1e-6)
    # the per-world model fields the randomization writes
    g = cpu_env.obj_geoms
    np.testing.assert_allclose(_host(warp_env._geom_size)[:, g], cpu_env._geom_size[:, g], rtol=1e-6)
    np.testing.assert_allclose(_host(warp_env._body_inertia)[:, cpu_env.obj_body],
                               cpu_env._body_inertia[:, cpu_env.obj_body], rtol=1e-5)
    np.testing.assert_allclose(_host(warp_env._gainprm)[..., 0], cpu_env._gainprm[..., 0], rtol=1e-6)


def test_first_policy_steps_match(warp_env, cpu_env):
    cpu_env.reset(seed=SEED)
    warp_env.reset(seed=SEED)
    actions = np.random.default_rng(0).uniform(-1, 1, (10, NUM_WORLDS, 16))
    for t in range(10):
        oc, rc, tc, trc, ic = cpu_env.step(actions[t])
        ow, rw, tw, trw, iw = warp_env.step(torch.as_tensor(actions[t]))
        qpos_err = np.abs(_host(warp_env._qpos) - cpu_env._qpos).max()
        if t < 2:
            assert qpos_err < TOL, (t, qpos_err)
            for k in oc:
                np.testing.assert_allclose(_host(ow[k]), oc[k], atol=TOL, err_msg=f"step {t} {k}")
            np.testing.assert_allclose(_host(rw), rc, atol=TOL, err_msg=f"step {t} reward")
            for k in ic:
                if k.startswith("rew_"):
                    np.testing.assert_allclose(_host(iw[k]), ic[k], atol=TOL, err_msg=f"step {t} {k}")
            assert np.array_equal(_host(tw), tc) and np.array_equal(_host(trw), trc)
        else:
            assert qpos_err < 0.05, (t, qpos_err)
        assert set(iw) == set(ic)
        assert np.array_equal(_host(iw["elapsed_steps"]), ic["elapsed_steps"])


def test_masked_reset_starts_the_same_next_episode(warp_env, cpu_env):
    cpu_env.reset(seed=SEED)
    warp_env.reset(seed=SEED)
    a = np.zeros((NUM_WORLDS, 16))
    cpu_env.step(a)
    warp_env.step(torch.as_tensor(a))
    oc = cpu_env.reset(ids=np.array([1]))
    warp_env.reset_done(torch.tensor([False, True, False]))
    ow = warp_env._observe()
    for k in oc:  # world 1 starts its episode 1 (same draws), the others keep their state
        np.testing.assert_allclose(_host(ow[k])[1], oc[k][1], atol=1e-6, err_msg=k)
        np.testing.assert_allclose(_host(ow[k])[[0, 2]], oc[k][[0, 2]], atol=TOL, err_msg=k)
    assert _host(warp_env.episode).tolist() == cpu_env.episode.tolist() == [0, 1, 0]
    assert _host(warp_env.steps).tolist() == cpu_env.steps.tolist() == [1, 0, 1]
