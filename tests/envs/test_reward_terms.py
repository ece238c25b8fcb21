"""The rotate term on hand-made states: the commanded-axis spin is clipped above by rotate_clip and below by
rotate_back_clip, so a forward-then-snap-back ratchet earns the term only when the backward clip is small."""

from __future__ import annotations

import numpy as np
import pytest

from envs import task
from envs.config import EnvConfig, RewardConfig
from rotation.train.teacher_config import Config as TeacherConfig


def _rotate_terms(cfg: EnvConfig, spins: list[float]) -> np.ndarray:
    """The rotate term of one step per spin (rad/s about the commanded axis -z), the cup upright and still."""
    n, dt = len(spins), cfg.control_dt
    half = 0.5 * np.asarray(spins) * dt
    quat = np.stack([np.cos(half), np.zeros(n), np.zeros(n), -np.sin(half)], axis=1)  # about -z by spin * dt
    quat0 = np.tile([1.0, 0.0, 0.0, 0.0], (n, 1))
    zeros16, pos = np.zeros((n, 16)), np.tile([0.0, 0.0, 0.1], (n, 1))
    out = task.reward_and_termination(np, cfg, q=zeros16, qdot=zeros16, tau=zeros16, qpos=np.zeros((n, 23)),
                                      qvel=np.zeros((n, 22)), pos0=pos, quat0=quat0, pos=pos, quat=quat,
                                      grasp_q=zeros16, start_pos=pos, axis=np.array(cfg.reward.axis))
    np.testing.assert_allclose(out["spin"], spins, rtol=1e-9)
    return out["terms"]["rotate"]


def test_spin_is_clipped_at_both_ends():
    cfg = EnvConfig(reward=RewardConfig(rotate_clip=0.5, rotate_back_clip=2.0))
    np.testing.assert_allclose(_rotate_terms(cfg, [0.3, 1.5, -0.3, -1.5, -4.0]), [0.3, 0.5, -0.3, -1.5, -2.0],
                               rtol=1e-9)


def test_a_ratchet_with_no_net_rotation_earns_nothing_once_the_back_clip_is_wide():
    # five steps forward at 0.4 rad/s, then one step back at 2 rad/s: the cup ends where it started
    ratchet = [0.4] * 5 + [-2.0]
    assert sum(ratchet) == pytest.approx(0.0)
    hora = _rotate_terms(EnvConfig(), ratchet).sum()  # the default, symmetric 0.5
    wide = _rotate_terms(EnvConfig(reward=RewardConfig(rotate_back_clip=5.0)), ratchet).sum()
    assert hora == pytest.approx(2.0 - 0.5)  # the snap back costs a quarter of what it undoes
    assert wide == pytest.approx(0.0, abs=1e-9)


def test_teacher_option_reaches_the_env_and_is_checked():
    assert TeacherConfig().env_config().reward.rotate_back_clip == 0.5
    assert TeacherConfig(rotate_back_clip=5.0).env_config().reward.rotate_back_clip == 5.0
    with pytest.raises(ValueError, match=r"reward\.rotate_back_clip must be > 0"):
        TeacherConfig(rotate_back_clip=0.0)


def test_teacher_fall_reward_reaches_the_env_and_must_not_pay():
    assert TeacherConfig().env_config().reward.fall == -20.0
    assert TeacherConfig(fall_reward=-60.0).env_config().reward.fall == -60.0
    with pytest.raises(ValueError, match="fall_reward"):
        TeacherConfig(fall_reward=5.0)


def test_teacher_reward_weights_reach_the_env_and_stay_penalties():
    """--rotate-clip, --pose-diff-reward and --work-reward set the env's terms (defaults: RewardConfig's, so a
    run recorded before they existed resumes unchanged); a positive pose or work weight is refused."""
    assert TeacherConfig().env_config().reward == RewardConfig(fall=-20.0)
    rc = TeacherConfig(rotate_clip=1.0, pose_diff_reward=-0.05, work_reward=-1.0).env_config().reward
    assert (rc.rotate_clip, rc.pose_diff, rc.work) == (1.0, -0.05, -1.0)
    for bad in ({"pose_diff_reward": 0.1}, {"work_reward": 1.0}, {"rotate_clip": 0.0}):
        with pytest.raises(ValueError, match=next(iter(bad))):
            TeacherConfig(**bad)


def test_teacher_friction_and_mass_ranges_reach_the_randomization_and_keep_the_rest_of_the_hands():
    """--friction / --mass widen what the teacher trains on (65's lever: slippery and heavy cups) and leave the
    hand's other physics alone; they need the randomization on, and the heaviest cup stays within the actuators."""
    base = TeacherConfig(hand="digit360_v4").env_config().randomization
    rc = TeacherConfig(hand="digit360_v4", friction=(0.1, 1.2), mass=(0.02, 0.3)).env_config().randomization
    assert (rc.friction, rc.mass) == ((0.1, 1.2), (0.02, 0.3))
    assert (rc.link_friction, rc.friction_log, rc.impratio) == (base.link_friction, base.friction_log, base.impratio)
    with pytest.raises(ValueError, match="--no-randomize"):
        TeacherConfig(friction=(0.1, 1.2), randomize=False)
    assert base.noslip_dropout == 0.25
    assert TeacherConfig(hand="digit360_v4", noslip_dropout=0.1).env_config().randomization.noslip_dropout == 0.1
    with pytest.raises(ValueError, match="noslip_dropout"):
        TeacherConfig(hand="digit360_v4", noslip_dropout=1.5)
    with pytest.raises(ValueError, match="mass"):
        TeacherConfig(hand="digit360_v4", mass=(0.02, 0.9))
