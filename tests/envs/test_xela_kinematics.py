"""Xela taxel positions from joint angles (envs.sensors.xela_kinematics): equal to the simulator's at the same joint
state, with the joints in the bus order; per-joint interpolation between joint samples; clear refusals."""

from __future__ import annotations

import time
from functools import partial

import mujoco
import numpy as np
import pytest

from envs.constants import FINGERS, JOINT_LOWER, JOINT_NAMES, JOINT_UPPER, NUM_JOINTS
from envs.objects import get_object
from envs.scene import build_model
from envs.sensors import xela as X
from envs.sensors.xela_hand import XelaReadout, add_xela_sensors
from envs.sensors.xela_kinematics import (
    JOINT_HOLD_S,
    XelaKinematics,
    covered,
    joints_at,
    kinematics,
    xela_hand_for,
)


def random_joints(n: int, seed: int) -> np.ndarray:
    return np.random.default_rng(seed).uniform(JOINT_LOWER, JOINT_UPPER, (n, NUM_JOINTS))


def simulated_positions(hand: str, q: np.ndarray) -> np.ndarray:
    """(T, 368, 3) taxel positions the simulator reports at joint states ``q`` (T, 16): the env's model (hand + cup,
    the pad sensors), the joints written as the env writes them (qpos[:16], envs.core), read as skin_obs reads them
    (XelaReadout -> PadContacts.taxel_pos)."""
    model = build_model(get_object("cup"), hand=hand, edit=partial(add_xela_sensors, history=1))
    assert tuple(model.joint(i).name for i in range(NUM_JOINTS)) == JOINT_NAMES  # the env's positional mapping
    data, readout = mujoco.MjData(model), XelaReadout(model)
    out = []
    for qi in q:
        data.qpos[:NUM_JOINTS] = qi
        mujoco.mj_forward(model, data)
        out.append(readout.read_current(data.sensordata[None]).taxel_pos()[0, 0])
    return np.stack(out)


@pytest.mark.parametrize("hand", X.XELA_HANDS)
def test_positions_equal_the_simulators(hand):
    q = random_joints(6, seed=len(hand))
    sim = simulated_positions(hand, q)
    fk = XelaKinematics(hand).taxel_positions(q)
    assert fk.shape == (6, X.NUM_TAXELS, 3) and fk.dtype == np.float64
    assert np.abs(fk - sim).max() < 1e-6
    # the joint states differ enough that a wrong joint order could not pass: the taxels move by centimetres
    assert np.abs(sim[1:] - sim[:1]).max() > 0.02
    # a joint vector read in another order (fingers swapped, or each finger's joints reversed) is far off
    swapped = q.reshape(6, 4, 4)[:, [1, 0, 2, 3]].reshape(6, NUM_JOINTS)
    reversed_ = q.reshape(6, 4, 4)[:, :, ::-1].reshape(6, NUM_JOINTS)
    for wrong in (swapped, reversed_):
        assert np.abs(XelaKinematics(hand).taxel_positions(wrong) - sim).max() > 0.01
    # one joint state: (16,) gives one frame
    assert np.array_equal(kinematics(hand).taxel_positions(q[0]), fk[:1])


@pytest.mark.parametrize("hand", X.XELA_HANDS)
def test_each_bus_joint_moves_its_own_finger(hand):
    """Bus order (envs.constants): finger f owns joints 4f..4f+3 = [abduction, MCP, PIP, DIP]. Moving joint 4f+3
    moves that finger's fingertip pad only; moving any joint of finger f moves no other finger's pads nor the palm."""
    kin = XelaKinematics(hand)
    q0 = (JOINT_LOWER + JOINT_UPPER) / 2
    base = kin.taxel_positions(q0)[0]
    for j in range(NUM_JOINTS):
        q = q0.copy()
        q[j] += 0.3 if q[j] + 0.3 <= JOINT_UPPER[j] else -0.3
        moved = np.linalg.norm(kin.taxel_positions(q)[0] - base, axis=1) > 1e-9
        pads = {X.PAD_NAMES[p] for p in np.unique(X.TAXEL_PAD[moved])}
        finger = FINGERS[j // 4]
        assert pads and all(p.startswith(finger) for p in pads), (JOINT_NAMES[j], pads)
        if j % 4 == 3:  # the DIP joint carries the fingertip
            assert pads == {f"{finger}_tip"}, (JOINT_NAMES[j], pads)


def test_hand_frame_is_the_palm_at_the_origin():
    kin = XelaKinematics("xela")
    data = mujoco.MjData(kin.model)
    mujoco.mj_kinematics(kin.model, data)
    assert np.allclose(data.body("palm").xpos, 0.0)
    palm = kin.taxel_positions(random_joints(3, seed=1))[:, X.PAD_SLICES["palm_middle"]]
    assert np.allclose(palm, palm[0]) and np.allclose(palm[0, :, 2], X.PAD_THICKNESS)  # fixed, on the palm's face


def test_joints_are_interpolated_linearly_per_joint():
    t_joint = np.array([0.0, 0.05, 0.10, 0.15])
    q = random_joints(4, seed=2)
    t = np.array([0.0, 0.01, 0.05, 0.07, 0.15, 0.15 + JOINT_HOLD_S])
    out = joints_at(t_joint, q, t)
    assert np.allclose(out[0], q[0]) and np.allclose(out[2], q[1]) and np.allclose(out[4], q[3])
    assert np.allclose(out[1], 0.8 * q[0] + 0.2 * q[1]) and np.allclose(out[3], 0.6 * q[1] + 0.4 * q[2])
    assert np.allclose(out[5], q[3])  # the last sample held
    assert covered(t_joint, np.array([-0.01, 0.0, 0.25, 0.26])).tolist() == [False, True, True, False]
    with pytest.raises(ValueError, match=r"no joint angles at t=-0\.0100 s .* sampled from 0\.0000 to 0\.1500 s"):
        joints_at(t_joint, q, np.array([-0.01, 0.02]))
    with pytest.raises(ValueError, match="no joint angles at t=0.3000"):
        joints_at(t_joint, q, np.array([0.3]))
    with pytest.raises(ValueError, match="non-decreasing"):
        joints_at(t_joint[::-1], q, np.array([0.05]))


def test_bad_input_is_refused_clearly():
    with pytest.raises(ValueError, match=r"unknown Xela hand 'digit360'.*xela_hand_for"):
        XelaKinematics("digit360")
    assert [xela_hand_for(h) for h in ("xela", "digit360", "xela_v4", "digit360_v4")] == [
        "xela", "xela", "xela_v4", "xela_v4"]
    with pytest.raises(ValueError, match="no Xela skin model for the hand 'leap'"):
        xela_hand_for("leap")
    kin = kinematics("xela")
    with pytest.raises(ValueError, match=r"must be \(T, 16\) rad in the Allegro bus order.*got shape \(4, 15\)"):
        kin.taxel_positions(np.zeros((4, 15)))
    bad = np.zeros((3, NUM_JOINTS))
    bad[1, 5] = np.nan
    with pytest.raises(ValueError, match=r"non-finite joint angles in 1 of 3 rows \(first: row 1\)"):
        kin.taxel_positions(bad)


def test_fast_enough_for_a_long_recording():
    """A 10-minute recording at 100 Hz is 60,000 frames; ~30 us a frame here (1-2 s). The bound is loose (a busy
    machine) but catches a per-taxel loop."""
    kin = kinematics("xela")
    q = random_joints(2000, seed=3)
    start = time.perf_counter()
    kin.taxel_positions(q)
    per_frame = (time.perf_counter() - start) / len(q)
    assert per_frame < 1e-3, f"{1e6 * per_frame:.0f} us per frame"
