"""The upright metric and the tilt terms on hand-made trajectories and states."""

from __future__ import annotations

import math

import numpy as np
import pytest

from envs.config import EnvConfig, RandomizationConfig
from envs.core import RotateCupVec
from envs.geometry import tilt_angle
from envs.metrics import EpisodeTracker, summarize


def _quat(axis: tuple[float, float, float], angle: float) -> np.ndarray:
    a = np.asarray(axis, dtype=np.float64) / np.linalg.norm(axis)
    return np.concatenate([[math.cos(angle / 2)], math.sin(angle / 2) * a])


def test_tilt_angle_ignores_spin_about_the_vertical():
    assert tilt_angle(_quat((0, 0, 1), 0.0)) == pytest.approx(0.0, abs=1e-12)
    assert tilt_angle(_quat((0, 0, 1), 2.5)) == pytest.approx(0.0, abs=1e-7)  # spinning upright
    assert tilt_angle(_quat((1, 0, 0), math.radians(30))) == pytest.approx(math.radians(30))
    assert tilt_angle(_quat((1, 1, 0), 2.0)) == pytest.approx(2.0)
    # a tilt followed by a spin is still the same tilt; unnormalized quaternions too
    q = 3.0 * _quat((0, 1, 0), 0.4)
    assert tilt_angle(q) == pytest.approx(0.4)


def _run(tracker: EpisodeTracker, tilts: np.ndarray, spin_per_step: float, fall_at: int | None = None):
    steps = len(tilts)
    for t in range(steps):
        fell = fall_at is not None and t == fall_at
        info = {"fell": np.array([fell]), "rotation": np.array([spin_per_step]), "tilt": np.array([tilts[t]]),
                "height": np.array([0.1]), "lin_vel": np.array([0.0]), "torque": np.array([0.05])}
        done = tracker.step(np.array([0.0]), np.array([fell]), np.array([t == steps - 1 and not fell]), info)
        if done:
            return done[0]
    raise AssertionError("the episode did not end")


def test_upright_spinning_cup_scores_one_and_a_tipped_cup_does_not():
    dt = 0.05
    tracker = EpisodeTracker(1, dt, 400)
    tracker.begin({"priv": np.full((1, 9), 0.1, dtype=np.float32)})
    upright = _run(tracker, np.full(400, math.radians(5)), spin_per_step=0.5 * dt)
    assert upright.upright == 1.0 and upright.ttf == 1.0
    assert upright.rotation_rate == pytest.approx(0.5) and upright.in_hand_time == pytest.approx(20.0)

    tracker.begin({"priv": np.full((1, 9), 0.1, dtype=np.float32)})
    tilts = np.concatenate([np.full(200, math.radians(10)), np.full(200, math.radians(35))])  # tips halfway
    tipped = _run(tracker, tilts, spin_per_step=0.5 * dt)
    assert tipped.upright == pytest.approx(0.5)

    tracker.begin({"priv": np.full((1, 9), 0.1, dtype=np.float32)})
    dropped = _run(tracker, np.zeros(400), spin_per_step=0.2 * dt, fall_at=99)  # falls on step 100
    assert dropped.ttf == pytest.approx(100 / 400) and dropped.in_hand_time == pytest.approx(99 * dt)
    assert dropped.upright == 1.0  # upright while in hand

    # the pooled rate weighs each episode by its time in hand
    net = summarize([upright, dropped])["net_rotation_rate"]
    assert net == pytest.approx((0.5 * 20.0 + 0.2 * 99 * dt) / (20.0 + 99 * dt))


@pytest.mark.parametrize("tilt_deg, ends", [(20.0, False), (50.0, True)])
def test_a_tipped_cup_costs_the_tilt_term_and_ends_the_episode(tilt_deg, ends):
    cfg = EnvConfig(randomization=RandomizationConfig(enabled=False))
    env = RotateCupVec(cfg, num_envs=2, seed=0, nthread=1)
    env.reset(seed=0)
    o = env.obj_qpos
    qpos = env._qpos.copy()
    qpos[1, o + 3 : o + 7] = _quat((1, 0, 0), math.radians(tilt_deg))  # env 1 tilted about x; env 0 as grasped
    env._qpos[:] = qpos
    env.batch.forward()
    _, reward, terminated, _, info = env.step(np.zeros((2, 16)))
    tilt = info["tilt"][1]
    assert tilt == pytest.approx(math.radians(tilt_deg), abs=math.radians(5))  # one step of physics later
    assert info["rew_tilt"][1] == pytest.approx(cfg.reward.tilt * tilt**2)
    assert bool(terminated[1]) is ends and bool(info["fell"][1]) is ends
    assert info["rew_fall"][1] == (cfg.reward.fall if ends else 0.0)
    assert not terminated[0] and info["tilt"][0] < math.radians(15)
    assert abs(info["rew_tilt"][0]) < abs(info["rew_tilt"][1])
