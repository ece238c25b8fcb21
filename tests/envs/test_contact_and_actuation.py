"""The contact model and the joint torque limits are config fields: their defaults are each hand's physics (on the
first hand, 'digit360', its model's own settings), and other values reach the compiled model the env steps."""

from __future__ import annotations

import mujoco
import numpy as np
import pytest

from envs import constants as C
from envs.config import ContactConfig, EnvConfig, hand_physics
from envs.constants import DEFAULT_HAND
from envs.core import RotateCupVec, task_model
from envs.scene import hand_xml_path


def test_defaults_keep_the_hand_models_own_settings():
    # the first hand ('digit360', Hora's physics): its MJCF's own contact settings and one torque limit
    model, _, _ = task_model(EnvConfig(hand="digit360"))
    reference = mujoco.MjModel.from_xml_path(hand_xml_path())
    assert model.opt.cone == reference.opt.cone == mujoco.mjtCone.mjCONE_PYRAMIDAL
    assert model.opt.impratio == reference.opt.impratio == 3.0
    assert model.opt.noslip_iterations == 0
    assert np.all(model.actuator_forcerange == [[-C.DEFAULT_TORQUE_LIMIT, C.DEFAULT_TORQUE_LIMIT]] * 16)
    # the default hand: its physics' contact model and torque limits (envs.physics.HAND_PHYSICS; on 'digit360_v4'
    # elliptic cones, impratio 10, the noslip solver and the vendor's per-joint limits)
    physics = hand_physics(DEFAULT_HAND)
    model, _, _ = task_model(EnvConfig())
    cone = {"pyramidal": mujoco.mjtCone.mjCONE_PYRAMIDAL, "elliptic": mujoco.mjtCone.mjCONE_ELLIPTIC}
    assert model.opt.cone == cone[physics.contact.cone] and model.opt.impratio == physics.contact.impratio
    assert model.opt.noslip_iterations == physics.contact.noslip_iterations
    limits = C.TORQUE_LIMITS if physics.joint_torque_limits == "vendor" else np.full(16, C.DEFAULT_TORQUE_LIMIT)
    assert np.array_equal(model.actuator_forcerange, np.stack([-limits, limits], axis=1))


def test_other_settings_reach_the_stepped_model():
    # on the first hand, whose own physics has none of them
    cfg = EnvConfig(hand="digit360", contact=ContactConfig(cone="elliptic", impratio=10.0, noslip_iterations=10),
                    joint_torque_limits="vendor")
    env = RotateCupVec(cfg, num_envs=2, seed=0, nthread=1)
    m = env.model
    assert m.opt.cone == mujoco.mjtCone.mjCONE_ELLIPTIC and m.opt.impratio == 10.0 and m.opt.noslip_iterations == 10
    assert np.allclose(m.actuator_forcerange[:, 1], C.TORQUE_LIMITS)
    assert np.allclose(m.actuator_forcerange[:, 0], -C.TORQUE_LIMITS)
    obs = env.reset(seed=3)
    for _ in range(3):
        obs, *_ = env.step(np.zeros((2, 16), dtype=np.float32))
    assert all(np.all(np.isfinite(v)) for v in obs.values() if isinstance(v, np.ndarray))


def test_bad_values_name_the_field():
    with pytest.raises(ValueError, match="contact.cone"):
        ContactConfig(cone="round")
    with pytest.raises(ValueError, match="contact.noslip_iterations"):
        ContactConfig(noslip_iterations=-1)
    with pytest.raises(ValueError, match="joint_torque_limits"):
        EnvConfig(joint_torque_limits="strong")
