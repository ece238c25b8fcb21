"""The hand variants' physics (envs.physics): the shipped hands keep the physics their policies trained on, the
vendor-kinematics hand gets the hardware's, each of its randomized parameters reaches the simulations it is drawn
for (the held cup's creep: tests/experiments/test_hold_creep.py)."""

from __future__ import annotations

import dataclasses

import mujoco
import numpy as np
import pytest

from envs import constants as C
from envs import task
from envs.config import ContactConfig, EnvConfig, RandomizationConfig, default_randomization
from envs.core import RotateCupVec
from envs.physics import OPTIONAL_RANGES, V4_PHYSICS
from envs.scene import link_geoms

V4 = "digit360_v4"


def test_the_shipped_hands_keep_their_physics_and_the_vendor_hand_gets_the_hardwares():
    for hand in ("digit360", "xela"):
        cfg = EnvConfig(hand=hand)
        assert cfg.randomization == RandomizationConfig() and cfg.contact == ContactConfig()
        assert cfg.joint_torque_limits == "uniform" and not task.uses_hardware_physics(cfg)
    cfg = EnvConfig(hand=V4)
    assert cfg.contact == ContactConfig(cone="elliptic", impratio=10.0, noslip_iterations=10)
    assert cfg.joint_torque_limits == "vendor" and task.uses_hardware_physics(cfg)
    rc = cfg.randomization
    assert all(getattr(rc, name) is not None for name in OPTIONAL_RANGES if name != "surface_friction")
    assert rc.surface_friction is None  # a training's choice (train-teacher --surface-friction), not the hand's
    assert rc.mass[1] == 0.40 and max(rc.scales) * 0.040 >= 0.044  # a ceramic mug, a standard mug's radius
    assert rc.friction == (0.4, 1.2) and rc.link_friction == (0.2, 0.5)
    # a field given explicitly wins over the hand's
    assert EnvConfig(hand=V4, contact=ContactConfig()).contact == ContactConfig()
    assert default_randomization(V4, enabled=False) == dataclasses.replace(V4_PHYSICS.randomization, enabled=False)


def test_with_hand_brings_the_hands_physics():
    cfg = EnvConfig(object="cup_small", episode_steps=50, randomization=RandomizationConfig(enabled=False))
    moved = cfg.with_hand(V4)
    assert moved.hand == V4 and moved.object == "cup_small" and moved.episode_steps == 50
    assert moved.contact == V4_PHYSICS.contact and moved.joint_torque_limits == "vendor"
    assert moved.randomization == dataclasses.replace(V4_PHYSICS.randomization, enabled=False)
    assert moved.with_hand("digit360").contact == ContactConfig()


@pytest.mark.parametrize("field, value, match", [
    ("link_friction", (0.5, 0.2), "inverted"),
    ("action_delay", (0.0, 0.06), "outside"),
    ("torque_scale", (0.0, 1.0), "outside"),
    ("impratio", 3.0, "pair"),
    ("noslip_dropout", 1.5, r"\[0, 1\]"),
])
def test_bad_hardware_ranges_name_the_field(field, value, match):
    with pytest.raises(ValueError, match=f"randomization.{field}.*{match}|{match}.*{field}"):
        RandomizationConfig(**{field: value})


def test_hardware_draws_fall_in_their_ranges_and_leave_the_shipped_draws_alone():
    cfg = EnvConfig(hand=V4)
    u = np.random.default_rng(0).uniform(size=(4000, task.PHYS_DRAWS))
    p = task.sample_hardware_params(np, cfg, u)
    rc = cfg.randomization
    for key, (lo, hi) in (("link_friction", rc.link_friction), ("joint_friction", rc.joint_friction),
                          ("torque_scale", rc.torque_scale), ("impratio", rc.impratio),
                          ("timeconst", rc.contact_timeconst)):
        assert lo <= p[key].min() and p[key].max() <= hi, key
    assert set(np.unique(p["delay"])) == {0, 1, 2, 3}  # 0-40 ms rounded down to 10 ms physics steps
    assert abs(p["noslip"].mean() - 0.75) < 0.03  # a quarter of the episodes without the noslip solver
    nominal = task.sample_hardware_params(np, dataclasses.replace(cfg, randomization=dataclasses.replace(
        rc, enabled=False)), u[:2])
    assert np.allclose(nominal["impratio"], np.sqrt(3.0 * 30.0)) and np.all(nominal["noslip"] == 1.0)
    # the shipped physics' draws come from their own stream: the same episodes whatever the hardware draws
    u40 = np.random.default_rng(1).uniform(size=(8, task.PARAM_DRAWS))
    plain = task.sample_params(np, EnvConfig(), u40)
    with_hw = task.sample_params(np, EnvConfig(), u40, u[:8])
    assert all(np.array_equal(plain[k], with_hw[k]) for k in plain)


def test_the_cup_surface_factor_scales_both_frictions_and_moves_no_other_draw():
    """--surface-friction multiplies the domes' and the links' friction of an episode by one log-uniform factor;
    every other parameter of the same episodes is drawn as without it, and nominal physics has no factor."""
    cfg = EnvConfig(hand=V4)
    rough = dataclasses.replace(cfg, randomization=dataclasses.replace(cfg.randomization, surface_friction=(0.25, 1.0)))
    u40 = np.random.default_rng(2).uniform(size=(4000, task.PARAM_DRAWS))
    u = np.random.default_rng(3).uniform(size=(4000, task.PHYS_DRAWS))
    plain, scaled = task.sample_params(np, cfg, u40, u), task.sample_params(np, rough, u40, u)
    factor = 0.25 * 4.0 ** u[:, 22]
    assert np.allclose(scaled["friction"], plain["friction"] * factor)
    assert np.allclose(scaled["link_friction"], plain["link_friction"] * factor)
    assert set(scaled) == set(plain)
    assert all(np.array_equal(plain[k], scaled[k]) for k in plain if k not in ("friction", "link_friction"))
    assert abs(np.mean(np.log(factor) < np.log(0.5)) - 0.5) < 0.03  # log-uniform: half the episodes below x0.5
    assert scaled["friction"].min() >= 0.1 - 1e-9  # the suite's friction x0.25 of the domes' 0.4
    off = dataclasses.replace(rough.randomization, enabled=False)
    nominal = task.sample_params(np, dataclasses.replace(rough, randomization=off), u40[:3], u[:3])
    assert np.allclose(nominal["friction"], np.mean(cfg.randomization.friction))
    with pytest.raises(ValueError, match="surface_friction"):
        RandomizationConfig(surface_friction=(0.0, 1.0))


def test_a_surface_share_keeps_the_other_episodes_on_the_nominal_surface():
    """With surface_share s, the episodes whose column-22 draw u is below s get the factor drawn log-uniformly from
    u / s, the others exactly 1; s = 1 is the plain factor; no other parameter moves."""
    cfg = EnvConfig(hand=V4)
    rc = dataclasses.replace(cfg.randomization, surface_friction=(0.25, 1.0))
    u40 = np.random.default_rng(4).uniform(size=(4000, task.PARAM_DRAWS))
    u = np.random.default_rng(5).uniform(size=(4000, task.PHYS_DRAWS))
    plain = task.sample_params(np, cfg, u40, u)
    half = task.sample_params(np, dataclasses.replace(cfg, randomization=dataclasses.replace(rc, surface_share=0.5)),
                              u40, u)
    whole = task.sample_params(np, dataclasses.replace(cfg, randomization=rc), u40, u)
    factor = half["friction"] / plain["friction"]
    drawn = u[:, 22] < 0.5
    assert np.allclose(factor[~drawn], 1.0)
    assert np.allclose(half["link_friction"][~drawn], plain["link_friction"][~drawn])
    assert np.allclose(factor[drawn], 0.25 * 4.0 ** (u[drawn, 22] / 0.5))
    assert abs(np.mean(factor == 1.0) - 0.5) < 0.03 and factor.min() >= 0.25 - 1e-9
    assert abs(np.mean(factor[drawn] < 0.5) - 0.5) < 0.04  # the drawn half is still log-uniform over 0.25-1
    assert np.allclose(whole["friction"] / plain["friction"], 0.25 * 4.0 ** u[:, 22])  # share 1: the plain factor
    assert all(np.array_equal(plain[k], half[k]) for k in plain if k not in ("friction", "link_friction"))
    for bad in (0.0, 1.5, -0.1):
        with pytest.raises(ValueError, match="surface_share"):
            RandomizationConfig(surface_share=bad)


def test_each_drawn_parameter_reaches_its_simulation():
    env = RotateCupVec(EnvConfig(hand=V4), num_envs=6, seed=5, nthread=1)
    env.reset()
    p = env.params
    st = env.starts
    for i in range(env.num_envs):
        m = env.batch.get_model(i)
        assert np.allclose(m.geom_friction[st.tip_geoms, 0], p["friction"][i])
        assert np.allclose(m.geom_friction[st.link_geoms, 0], p["link_friction"][i])
        assert np.allclose(m.geom_friction[st.obj_geoms, 0], min(p["friction"][i], p["link_friction"][i]))
        assert np.allclose(m.dof_frictionloss[: C.NUM_JOINTS], p["joint_friction"][i])
        assert np.allclose(m.actuator_forcerange[:, 1], C.TORQUE_LIMITS * p["torque_scale"][i])
        assert np.allclose(m.actuator_gainprm[:, 0], p["kp"][i] * p["torque_scale"][i])
        assert np.isclose(m.opt.impratio, p["impratio"][i])
        assert np.allclose(m.geom_solref[:, 0], p["timeconst"][i])
        assert m.opt.noslip_iterations == (10 if p["noslip"][i] else 0)
        assert m.opt.cone == mujoco.mjtCone.mjCONE_ELLIPTIC
    assert np.array_equal(env.delay, p["delay"].astype(int))
    # a hand on the shipped physics (Hora's: 'digit360', 'xela') leaves its simulations as compiled: no per-simulation
    # copies of these fields
    plain = RotateCupVec(EnvConfig(hand="digit360"), num_envs=2, seed=5, nthread=1)
    plain.reset()
    assert plain.starts._fields == {} and not plain.delay.any()


def test_an_action_reaches_the_motors_after_its_delay():
    """The same command from the same state: with 30 ms of delay the joint has moved less by the end of the 50 ms
    control step than without, because the new target acted for 20 ms instead of 50."""
    rc = dataclasses.replace(default_randomization(V4, enabled=True), push_prob=0.0, joint_noise=0.0)
    moved = {}
    for delay in (0.0, 0.03):
        cfg = EnvConfig(hand=V4, randomization=dataclasses.replace(rc, action_delay=(delay, delay)))
        env = RotateCupVec(cfg, num_envs=1, seed=2, nthread=1)
        env.reset()
        q0 = env._qpos[0, : C.NUM_JOINTS].copy()
        action = np.zeros((1, C.NUM_JOINTS))
        action[0, 1] = 1.0  # index MCP flexes by 1/24 rad
        env.step(action)
        moved[delay] = env._qpos[0, 1] - q0[1]
        assert env.delay[0] == round(delay / cfg.physics_dt)
    assert moved[0.0] > 0 and moved[0.03] < 0.7 * moved[0.0]



def test_the_xela_hand_on_the_vendor_kinematics_feels_its_grasp():
    """hand='xela_v4' (the vendor's kinematics, stock-length tips under Xela shells, pads on its own links) with
    the skin on: it starts from its own shipped grasps on the hardware's physics, and the pads holding the cup carry
    its load (a few newtons on two or more pads per env)."""
    env = RotateCupVec(EnvConfig(hand="xela_v4", skin=True), num_envs=4, seed=0, nthread=1)
    assert env.cfg.contact.cone == "elliptic" and env.grasps.hand == "xela_v4"
    env.reset()
    for _ in range(5):
        obs, _, terminated, _, info = env.step(np.zeros((4, C.NUM_JOINTS)))
    normal = info["skin_force"][..., 0]  # (envs, 18 pads) N
    assert not terminated.any()
    assert np.all((normal > 0.05).sum(axis=1) >= 2) and np.all(normal.sum(axis=1) > 0.5), normal.sum(axis=1)
    assert obs["skin"].shape == (4, 10, 368, 6)


def test_each_contact_with_the_cup_reads_the_friction_of_the_hand_material_it_touches():
    """envs.physics.object_friction: MuJoCo combines two geoms' coefficients by their maximum, so with the cup's
    geom at the smaller of the two, a dome contact reads the domes' coefficient and a link or palm contact the
    links'. Checked on the contacts MuJoCo itself builds while the hand holds the cup."""
    env = RotateCupVec(EnvConfig(hand=V4), num_envs=2, seed=5)
    env.reset()
    for _ in range(3):
        env.step(np.zeros((2, C.NUM_JOINTS), np.float32))
    seen = set()
    for i in range(2):
        m, d = env.get_data(i)
        obj = m.body("object").id
        links = set(link_geoms(m, np.flatnonzero(m.geom_bodyid == obj)).tolist())
        for c in d.contact[: d.ncon]:
            pair = {int(c.geom1), int(c.geom2)}
            if not any(m.geom_bodyid[g] == obj for g in pair):
                continue
            hand_geom = next(g for g in pair if m.geom_bodyid[g] != obj)
            dome = hand_geom not in links
            want = env.params["friction"][i] if dome else env.params["link_friction"][i]
            assert c.friction[0] == pytest.approx(want, rel=1e-6)
            seen.add(dome)
    assert seen == {True, False}  # both materials touched the cup
