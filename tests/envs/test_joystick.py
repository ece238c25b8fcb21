"""The joystick fixture: angle convention, spring return, scripted play moving the stick, labels, determinism."""

from __future__ import annotations

import numpy as np
import pytest

from envs.joystick import JOINT, OPEN_POSE, JoystickConfig, JoystickPlay, joystick_angles
from envs.sensors.xela import NUM_PADS, NUM_TAXELS


def _axis_angle(axis, angle):
    axis = np.asarray(axis, float) / np.linalg.norm(axis)
    return np.r_[np.cos(angle / 2), np.sin(angle / 2) * axis]


def test_angles_convention():
    assert np.allclose(joystick_angles(np.array([1.0, 0, 0, 0])), 0)
    for k, axis in enumerate(np.eye(3)):
        expected = np.zeros(3)
        expected[k] = 0.3
        assert np.allclose(joystick_angles(_axis_angle(axis, 0.3)), expected)
    both = joystick_angles(np.stack([_axis_angle([1, 0, 0], 0.2), _axis_angle([0, 0, 1], -0.4)]))
    assert both.shape == (2, 3) and np.allclose(both[:, [0, 2]], [[0.2, 0], [0, -0.4]])


@pytest.fixture(scope="module")
def played():
    play = JoystickPlay(JoystickConfig(), num_envs=2, seed=5, nthread=1)
    play.reset()
    angles, forces, counts = [], [], []
    for _ in range(80):  # 4 s: at least one grip cycle
        play.step()
        angles.append(play.last_angles)
        forces.append(play.skin.last_force)
        counts.append(play.skin.last_counts)
    return play, np.concatenate(angles, 1), np.concatenate(forces, 1), np.concatenate(counts, 1)


def test_play_pushes_the_stick_and_the_skin_feels_it(played):
    play, angles, forces, counts = played
    assert angles.shape == (2, 400, 3) and forces.shape == (2, 400, NUM_PADS, 3)
    assert counts.shape == (2, 400, NUM_TAXELS, 3)
    assert np.all(angles.std(axis=1) > 0.02)  # roll, pitch and yaw all move
    assert np.all(np.abs(angles) < play.cfg.max_tilt + 0.05)
    touching = forces[..., 0].max(axis=-1) > 0.1  # (2, 400) some pad pressed
    assert 0.1 < touching.mean() < 0.95  # grasped and let go
    assert counts[..., 2].max() > 34000  # pressing shows in the raw counts
    # let go, the stick is near vertical again
    released = ~touching
    assert np.abs(angles[released]).mean() < np.abs(angles[touching]).mean()


def test_spring_returns_the_stick():
    play = JoystickPlay(JoystickConfig(spring=0.2), num_envs=1, seed=0, nthread=1)
    play.reset()
    ball = int(play.model.joint(JOINT).qposadr[0])
    qpos = play.batch.bind("qpos")
    q = qpos[:1].copy()
    q[0, ball : ball + 4] = _axis_angle([1, 1, 0], 0.4)  # tilted, the hand open and clear
    qpos[:1] = q
    play.batch.bind("ctrl")[:] = OPEN_POSE
    play.batch.forward()
    play.batch.step(nstep=150)
    tilt = joystick_angles(play.batch.bind("qpos")[0, ball : ball + 4])
    assert np.abs(tilt).max() < 0.05


def test_play_is_deterministic_under_a_seed(played):
    _, angles, _, counts = played
    again = JoystickPlay(JoystickConfig(), num_envs=1, seed=6, nthread=1)  # env 1 of the batch seeded 5
    again.reset()
    a, c = [], []
    for _ in range(80):
        again.step()
        a.append(again.last_angles)
        c.append(again.skin.last_counts)
    assert np.array_equal(np.concatenate(a, 1)[0], angles[1]) and np.array_equal(np.concatenate(c, 1)[0], counts[1])
    random = JoystickPlay(JoystickConfig(motion="random"), num_envs=1, seed=6, nthread=1)
    random.reset()
    for _ in range(10):
        random.step()
    assert np.abs(random.targets - OPEN_POSE).max() > 0.05 and np.all(np.isfinite(random.last_angles))


def test_bad_settings_are_refused():
    with pytest.raises(ValueError, match="spring"):
        JoystickConfig(spring=0.0)
    with pytest.raises(ValueError, match="motion must be one of"):
        JoystickConfig(motion="dance")
    with pytest.raises(ValueError, match="num_envs"):
        JoystickPlay(num_envs=0)
