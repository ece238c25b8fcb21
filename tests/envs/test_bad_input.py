"""Every bad input is a ValueError that names the field and what is allowed, raised before any work is done."""

from __future__ import annotations

import math
import re

import gymnasium as gym
import numpy as np
import pytest

from envs import EnvConfig, Perturbation, RandomizationConfig, RewardConfig, RotateCupVec
from envs.config import default_randomization
from envs.constants import DEFAULT_HAND
from envs.rotate_cup import RotateCupEnv
from envs.vector import RotateCupVectorEnv

CONFIG_ERRORS = [
    # (what to build, keyword arguments, the message must match)
    (EnvConfig, dict(object="mug"), r"object: unknown object 'mug'; known objects: cup, cup_large, .*cylinder_8"),
    (EnvConfig, dict(control_hz=30.0), r"whole number of substeps, got 3\.3333 \(control_hz=30\.0, physics_dt=0\.01"),
    (EnvConfig, dict(physics_dt=0.003), r"whole number of substeps, got 16\.6667"),
    (EnvConfig, dict(physics_dt=0.1), r"physics_dt must be in \[1e-4, 0\.02\] s, got 0\.1"),
    (EnvConfig, dict(control_hz=0.0), r"control_hz must be in \[1, 500\] Hz, got 0\.0"),
    (EnvConfig, dict(episode_steps=0), r"episode_steps must be >= 1, got 0"),
    (EnvConfig, dict(action_scale=math.nan), r"action_scale must be finite and > 0, got nan"),
    (EnvConfig, dict(torque_limit=-0.5), r"torque_limit must be finite and > 0, got -0\.5"),
    (EnvConfig, dict(kd=-0.1), r"kd must be finite and >= 0, got -0\.1"),
    (EnvConfig, dict(randomization={"mass": (0.1, 0.2)}),
     r"randomization must be a RandomizationConfig or None, got dict"),
    (RandomizationConfig, dict(scales=()), r"randomization\.scales must list at least one scale"),
    (RandomizationConfig, dict(scales=(0.05, 0.8)), r"randomization\.scales must lie in \[0\.1, 3\.0\]"),
    (RandomizationConfig, dict(scale_jitter=0.9), r"randomization\.scale_jitter must be in \[0, 0\.7\)"),
    (RandomizationConfig, dict(mass=(0.2, 0.1)),
     r"randomization\.mass is inverted: low 0\.2 > high 0\.1; expected a \(low, high\) pair with low <= high within "
     r"\[0\.0001, 0\.5\]"),
    (RandomizationConfig, dict(mass=(-0.1, 0.2)), r"randomization\.mass=\(-0\.1, 0\.2\) is outside the allowed "
                                                  r"interval \[0\.0001, 0\.5\]"),
    (RandomizationConfig, dict(mass=(-0.2, -0.1)), r"randomization\.mass=.* outside the allowed interval"),
    (RandomizationConfig, dict(mass=0.1), r"randomization\.mass must be a \(low, high\) pair .* got 0\.1"),
    (RandomizationConfig, dict(mass=(0.1, 0.2, 0.3)), r"randomization\.mass must be a \(low, high\) pair"),
    (RandomizationConfig, dict(friction=(0.3, math.inf)), r"randomization\.friction must be finite"),
    (RandomizationConfig, dict(friction=(0.0, 1.0)), r"randomization\.friction=.* allowed interval \[0\.01, 3\.0\]"),
    (RandomizationConfig, dict(com=(-0.1, 0.1)), r"randomization\.com=.* allowed interval \[-0\.05, 0\.05\]"),
    (RandomizationConfig, dict(kp=(3.1, 2.9)), r"randomization\.kp is inverted"),
    (RandomizationConfig, dict(joint_noise=-0.01), r"randomization\.joint_noise must be finite and >= 0"),
    (RandomizationConfig, dict(push_prob=1.5), r"randomization\.push_prob must be in \[0, 1\], got 1\.5"),
    (RandomizationConfig, dict(push_decay=-0.1), r"randomization\.push_decay must be in \[0, 1\]"),
    (RewardConfig, dict(axis=(1.0, 1.0, 0.0)), r"reward\.axis must be a unit 3-vector"),
    (RewardConfig, dict(rotate_clip=0.0), r"reward\.rotate_clip must be > 0"),
    (Perturbation, dict(friction_scale=0.0), r"perturb\.friction_scale must be finite and > 0, got 0\.0"),
    (Perturbation, dict(friction_scale=math.nan), r"perturb\.friction_scale must be finite and > 0, got nan"),
    (Perturbation, dict(added_mass=-0.05), r"perturb\.added_mass must be finite and >= 0 kg, got -0\.05"),
    (Perturbation, dict(added_mass=math.inf), r"perturb\.added_mass must be finite and >= 0 kg, got inf"),
    (Perturbation, dict(com_shift=(0.1, 0.0, 0.0)), r"perturb\.com_shift must be 3 finite values within \+-0\.05 m"),
    (Perturbation, dict(com_shift=(0.01, 0.0)), r"perturb\.com_shift must be 3 finite values"),
    (Perturbation, dict(com_shift=(math.nan, 0.0, 0.0)), r"perturb\.com_shift must be 3 finite values"),
    (Perturbation, dict(com_shift=0.01), r"perturb\.com_shift must be 3 finite values .* got 0\.01"),
]


@pytest.mark.parametrize(("cls", "kwargs", "message"), CONFIG_ERRORS,
                         ids=[f"{c.__name__}-{next(iter(k))}-{i}" for i, (c, k, _) in enumerate(CONFIG_ERRORS)])
def test_bad_config(cls, kwargs, message):
    with pytest.raises(ValueError, match=message):
        cls(**kwargs)


def test_bad_core_arguments():
    with pytest.raises(ValueError, match=r"num_envs must be >= 1, got 0"):
        RotateCupVec(EnvConfig(), num_envs=0)
    with pytest.raises(ValueError, match=r"cfg must be an EnvConfig, got dict"):
        RotateCupVec({"object": "cup"})  # type: ignore[arg-type]


def test_unknown_gymnasium_kwargs():
    with pytest.raises(ValueError, match=r"unknown RotateCup option\(s\) \['frction'\]; known: \[.*'episode_steps'"):
        gym.make("envs:RotateCup-v0", frction=0.5)
    with pytest.raises(ValueError, match=r"unknown RotateCup option\(s\) \['num_env'\]"):
        gym.make_vec("envs:RotateCup-v0", num_envs=2, vectorization_mode="vector_entry_point", num_env=3)
    with pytest.raises(ValueError, match=r"\['randomization\.masss'\]; known randomization options: \[.*'mass'"):
        gym.make("envs:RotateCup-v0", randomization={"masss": (0.1, 0.2)})
    with pytest.raises(ValueError, match=r"\['perturb\.mass'\]; known perturb options: \['added_mass', 'com_shift'"):
        RotateCupEnv(perturb={"mass": 0.1})
    # values given through the nested dicts are validated like any other
    with pytest.raises(ValueError, match=r"randomization\.mass is inverted"):
        gym.make("envs:RotateCup-v0", randomization={"mass": (0.2, 0.1)})
    with pytest.raises(ValueError, match=r"object: unknown object 'mug'"):
        gym.make("RotateCup-v0", object="mug")
    with pytest.raises(ValueError, match=r"render_mode must be None or 'rgb_array', got 'human'"):
        RotateCupEnv(render_mode="human")


@pytest.fixture(scope="module")
def single():
    env = RotateCupEnv()
    env.reset(seed=0)
    return env


@pytest.mark.parametrize("value", [math.nan, math.inf, -math.inf])
def test_non_finite_actions(single, value):
    a = np.zeros(16)
    a[5] = value
    with pytest.raises(ValueError, match=rf"actions must be finite; env 0 joint 5 is {value}"):
        single.step(a)
    core = RotateCupVec(EnvConfig(), num_envs=3, seed=0, nthread=1)
    core.reset()
    batch = np.zeros((3, 16))
    batch[2, 7] = value
    with pytest.raises(ValueError, match=rf"actions must be finite; env 2 joint 7 is {value}"):
        core.step(batch)
    np.testing.assert_array_equal(core.steps, 0)  # nothing was stepped


@pytest.mark.parametrize("shape", [(15,), (17,), (1, 16), (16, 1), ()])
def test_wrong_action_shape_single(single, shape):
    with pytest.raises(ValueError, match=rf"action must have shape \(16,\), got {re_shape(shape)}"):
        single.step(np.zeros(shape))


@pytest.mark.parametrize("shape", [(16,), (2, 16), (4, 16), (3, 15), (3, 16, 1), (48,)])
def test_wrong_action_shape_batched(shape):
    core = RotateCupVec(EnvConfig(), num_envs=3, seed=0, nthread=1)
    core.reset()
    with pytest.raises(ValueError, match=rf"actions must have shape \(3, 16\), got {re_shape(shape)}"):
        core.step(np.zeros(shape))
    venv = RotateCupVectorEnv(3)
    venv.reset(seed=0)
    with pytest.raises(ValueError, match=rf"actions must have shape \(3, 16\), got {re_shape(shape)}"):
        venv.step(np.zeros(shape))


def test_step_before_reset():
    with pytest.raises(RuntimeError, match=r"call reset\(\) before step\(\)"):
        RotateCupVec(EnvConfig(), num_envs=2).step(np.zeros((2, 16)))


def re_shape(shape: tuple[int, ...]) -> str:
    """The regex of a shape as numpy prints it, e.g. (3, 16) -> '\\(3, 16\\)'."""
    return str(tuple(shape)).replace("(", r"\(").replace(")", r"\)")


# -- types, physical limits ------------------------------------------------------------------------------------------


@pytest.mark.parametrize(("kwargs", "message"), [
    (dict(tactile="no"), r"tactile must be True or False, got str 'no'"),
    (dict(tactile=1), r"tactile must be True or False, got int 1"),
    (dict(episode_steps=400.0), r"episode_steps must be an integer, got float 400\.0"),
    (dict(episode_steps=True), r"episode_steps must be an integer, got bool True"),
    (dict(kp="3"), r"kp must be a number, got str '3'"),
    (dict(object=3), r"object must be a string, got int 3"),
    (dict(grasp_cache=None), r"grasp_cache must be a string, got NoneType None"),
    (dict(randomization={"enabled": "no"}), r"randomization\.enabled must be True or False, got str 'no'"),
    (dict(randomization={"scales": (0.8, "0.9")}),
     r"randomization\.scales must be a tuple of numbers, got tuple \(0\.8, '0\.9'\)"),
    (dict(randomization={"mass": ("0.1", 0.2)}), r"randomization\.mass must be a \(low, high\) pair"),
    (dict(reward={"tilt": float("nan")}), r"reward\.tilt must be a finite number, got nan"),
    (dict(reward={"fall": "-20"}), r"reward\.fall must be a number, got str '-20'"),
    (dict(reward={"axis": (0, 0, True)}), r"reward\.axis must be a unit 3-vector"),
    (dict(perturb={"friction_scale": True}), r"perturb\.friction_scale must be a number, got bool True"),
    (dict(perturb={"com_shift": ("0.01", 0, 0)}), r"perturb\.com_shift must be 3 finite values"),
    (dict(kp=1e30), r"kp must be at most 100 N m / rad, got 1e\+30"),
    (dict(max_distance=12.0), r"max_distance must be at most 1 m, got 12\.0"),
])
def test_values_of_the_wrong_type_or_size_are_refused_through_gymnasium(kwargs, message):
    with pytest.raises(ValueError, match=message):
        gym.make("envs:RotateCup-v0", **kwargs)
    with pytest.raises(ValueError, match=message):
        gym.make_vec("envs:RotateCup-v0", num_envs=2, vectorization_mode="vector_entry_point", **kwargs)


@pytest.mark.parametrize(("kwargs", "message"), [
    (dict(num_envs="3"), r"num_envs must be an integer, got str '3'"),
    (dict(num_envs=2.7), r"num_envs must be an integer, got float 2\.7"),
    (dict(nthread=0), r"nthread must be an integer in \[1, 1024\], got 0"),
    (dict(nthread="2"), r"nthread must be an integer in \[1, 1024\], got '2'"),
])
def test_bad_vector_arguments(kwargs, message):
    with pytest.raises(ValueError, match=message):
        gym.make_vec("envs:RotateCup-v0", vectorization_mode="vector_entry_point", **{"num_envs": 2, **kwargs})


def test_friction_above_what_the_contact_model_holds_is_refused():
    from envs.config import MAX_FRICTION

    assert MAX_FRICTION == 3.0
    # the shipped physics (hand 'digit360'): its randomization reaches 3.0 already, any friction_scale above 1 exceeds
    # the limit
    with pytest.raises(ValueError, match=r"perturb\.friction_scale 3 makes the friction reach 9, above 3\.0, the most "
                                         r"the contact model holds .*friction_scale must be in \(0, 1\]"):
        EnvConfig(hand="digit360", perturb=Perturbation(friction_scale=3.0))
    with pytest.raises(ValueError, match=r"friction_scale must be in \(0, 1\]"):
        gym.make("envs:RotateCup-v0", hand="digit360", perturb={"friction_scale": 1.2})
    # without randomization the friction is the middle of the range (1.65): up to x1.82
    nominal = RandomizationConfig(enabled=False)
    EnvConfig(hand="digit360", randomization=nominal, perturb=Perturbation(friction_scale=1.8))
    with pytest.raises(ValueError, match=r"friction_scale must be in \(0, 1\.82\]"):
        EnvConfig(hand="digit360", randomization=nominal, perturb=Perturbation(friction_scale=1.9))
    # the default hand: the top of its own friction range sets the limit (on 'digit360_v4' the gel's 1.2: up to x2.5)
    top = MAX_FRICTION / default_randomization(DEFAULT_HAND).friction[1]
    EnvConfig(perturb=Perturbation(friction_scale=top))
    with pytest.raises(ValueError, match=rf"perturb\.friction_scale {2 * top:g} makes the friction reach 6, above 3\.0"
                                         rf".*friction_scale must be in \(0, {re.escape(f'{top:.3g}')}\]"):
        EnvConfig(perturb=Perturbation(friction_scale=2 * top))
    with pytest.raises(ValueError, match=rf"friction_scale must be in \(0, {re.escape(f'{top:.3g}')}\]"):
        gym.make("envs:RotateCup-v0", perturb={"friction_scale": 1.1 * top})
    with pytest.raises(ValueError, match=r"randomization\.friction=\(0\.3, 4\.0\) is outside the allowed interval "
                                         r"\[0\.01, 3\.0\]"):
        RandomizationConfig(friction=(0.3, 4.0))


def test_added_mass_above_what_the_actuators_lift_is_refused():
    from envs.config import MAX_OBJECT_MASS

    assert MAX_OBJECT_MASS == 0.5
    # the shipped physics (hand 'digit360'): 0.25 kg randomized + 0.25 kg = 0.5 kg, the ceiling
    EnvConfig(hand="digit360", perturb=Perturbation(added_mass=0.25))
    with pytest.raises(ValueError, match=r"perturb\.added_mass 0\.3 kg makes the object weigh up to 0\.55 kg, above "
                                         r"0\.5 kg, what the 0\.5 N m actuators can lift; .* added_mass must be in "
                                         r"\[0, 0\.25\] kg"):
        EnvConfig(hand="digit360", perturb=Perturbation(added_mass=0.3))
    # the default hand: the top of its own mass range (on 'digit360_v4' a 0.4 kg mug: up to +0.1 kg)
    top = MAX_OBJECT_MASS - default_randomization(DEFAULT_HAND).mass[1]
    assert top > 0
    EnvConfig(perturb=Perturbation(added_mass=top))
    with pytest.raises(ValueError, match=rf"makes the object weigh up to 0\.55 kg, above 0\.5 kg.* added_mass must be "
                                         rf"in \[0, {re.escape(f'{top:.3g}')}\] kg"):
        EnvConfig(perturb=Perturbation(added_mass=top + 0.05))
    with pytest.raises(ValueError, match=r"perturb\.added_mass must be in \[0, 0\.5\] kg"):
        Perturbation(added_mass=2.0)
    with pytest.raises(ValueError, match=r"randomization\.mass=\(0\.1, 1\.0\) is outside the allowed interval"):
        RandomizationConfig(mass=(0.1, 1.0))


def test_every_shipped_evaluation_condition_is_within_the_limits():
    from rotation.evaluate.suites import SUITES

    for hand in ("digit360", "digit360_v4"):  # each hand's suite within its own physics' limits
        for suite in SUITES.values():
            for cond in suite(hand):
                EnvConfig(hand=hand, perturb=cond.perturb)
