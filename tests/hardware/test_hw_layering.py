"""The hardware package imports neither torch nor mujoco, and its constants agree with envs.constants."""

from __future__ import annotations

import subprocess
import sys

import numpy as np

from rotation.hardware import hand


def test_no_torch_no_mujoco_in_hardware():
    code = ("import sys, rotation.hardware.allegro.driver, rotation.hardware.leap.driver, "
            "rotation.hardware.digit360.reader, "
            "rotation.hardware.safety, rotation.hardware.allegro.can_bus; "
            "bad = [m for m in ('torch', 'mujoco', 'envs') if m in sys.modules]; print(bad); sys.exit(bool(bad))")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=60)
    assert out.returncode == 0, out.stdout + out.stderr


def test_constants_match_envs():
    from envs import constants

    assert np.array_equal(hand.JOINT_LOWER, constants.JOINT_LOWER)
    assert np.array_equal(hand.JOINT_UPPER, constants.JOINT_UPPER)
    assert np.array_equal(hand.TORQUE_LIMITS, constants.TORQUE_LIMITS)
    assert hand.FINGERS == constants.FINGERS and hand.NUM_JOINTS == constants.NUM_JOINTS
