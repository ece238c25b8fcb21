"""Domain randomization lands in the per-simulation model fields, matches `priv`, stays in range; perturbations
shift exactly the sampled values; with randomization off every env gets the nominal values (worked out by hand).
The randomized env is the default hand's, with its own physics (envs.physics.HAND_PHYSICS)."""

from __future__ import annotations

import numpy as np
import pytest

from envs import EnvConfig, Perturbation, RandomizationConfig, RotateCupVec
from envs import constants as C

PRIV = {name: i for i, name in enumerate(C.PRIV_FIELDS)}
N = 16


def fields(core: RotateCupVec) -> dict[str, np.ndarray]:
    """The per-simulation model values the env wrote, read back from the batch."""
    b, body, geoms = core.batch, core.obj_body, core.obj_geoms
    return {
        "mass": b.expanded("body_mass")[:, body],
        "subtree_mass": b.expanded("body_subtreemass")[:, body],  # derived by set_const from the written mass
        "com": b.expanded("body_ipos")[:, body],
        "inertia": b.expanded("body_inertia")[:, body],
        "friction": b.expanded("geom_friction")[:, :, 0],  # (N, ngeom)
        "size": b.expanded("geom_size")[:, geoms],  # (N, object geoms, 3)
        "gain": b.expanded("actuator_gainprm")[:, :, 0],
        "bias_kp": b.expanded("actuator_biasprm")[:, :, 1],
        "bias_kd": b.expanded("actuator_biasprm")[:, :, 2],
    }


@pytest.fixture(scope="module")
def randomized():
    core = RotateCupVec(EnvConfig(), num_envs=N, seed=11, nthread=1)
    obs = core.reset(seed=11)
    return core, obs


def test_model_fields_equal_priv_and_params(randomized):
    core, obs = randomized
    f, priv, p = fields(core), obs["priv"], core.params
    assert priv.shape == (N, C.PRIV_DIM) and priv.dtype == np.float32
    np.testing.assert_array_equal(f["mass"], p["mass"])
    np.testing.assert_allclose(f["subtree_mass"], p["mass"], rtol=1e-12)
    np.testing.assert_array_equal(f["com"], p["com"])
    # friction: one coefficient for hand and object (Hora's, the shipped physics); on the hardware physics the drawn
    # friction is the fingertips' (the gel domes), the links and palm have their own, and the object takes the lower
    friction = np.repeat(p["friction"][:, None], core.model.ngeom, axis=1)
    st = core.starts
    if "link_friction" in p:
        friction[:, st.link_geoms] = p["link_friction"][:, None]
        friction[:, st.obj_geoms] = np.minimum(p["friction"], p["link_friction"])[:, None]
    np.testing.assert_array_equal(f["friction"], friction)
    assert len(st.tip_geoms) and np.all(f["friction"][:, st.tip_geoms] == p["friction"][:, None])  # the domes
    # the PD gains, in N m per normalized torque unit where the hand's physics draws one (torque_scale)
    scale = p["torque_scale"][:, None] if "torque_scale" in p else 1.0
    np.testing.assert_array_equal(f["gain"], p["kp"] * scale)
    np.testing.assert_array_equal(f["bias_kp"], -p["kp"] * scale)
    np.testing.assert_array_equal(f["bias_kd"], -p["kd"] * scale)
    # the object geoms are the compiled ones (at the largest scale) shrunk to the env's scale
    compiled = core.model.geom_size[core.obj_geoms]  # (geoms, 3)
    used = compiled > 0  # size slots a primitive does not use stay 0
    np.testing.assert_allclose(f["size"][:, used] / compiled[used], np.repeat((p["scale"] / core.max_scale)[:, None],
                               used.sum(), axis=1), rtol=1e-12)
    np.testing.assert_array_equal(f["size"][:, ~used], 0.0)
    # the cup body: radius 4 cm and height 8.5 cm at scale 1 (envs.objects)
    np.testing.assert_allclose(f["size"][:, 0, :2], np.stack([0.040 * p["scale"], 0.0425 * p["scale"]], 1), rtol=1e-12)
    # priv reports exactly these values (in float32), in the PRIV_FIELDS layout
    np.testing.assert_array_equal(priv[:, PRIV["mass"]], f["mass"].astype(np.float32))
    np.testing.assert_array_equal(priv[:, PRIV["friction"]], f["friction"][:, st.tip_geoms[0]].astype(np.float32))
    np.testing.assert_array_equal(priv[:, [PRIV["com_x"], PRIV["com_y"], PRIV["com_z"]]], f["com"].astype(np.float32))
    np.testing.assert_array_equal(priv[:, PRIV["scale"]], p["scale"].astype(np.float32))
    pos = core.batch.bind("qpos")[:, core.obj_qpos : core.obj_qpos + 3]
    np.testing.assert_array_equal(priv[:, [PRIV["pos_x"], PRIV["pos_y"], PRIV["pos_z"]]], pos.astype(np.float32))
    # the model each simulation steps with carries its own values
    for i in (0, N - 1):
        m = core.batch.get_model(i)
        assert m.body_mass[core.obj_body] == p["mass"][i]
        assert m.geom_friction[st.tip_geoms[0], 0] == p["friction"][i]
        assert m.geom_friction[core.obj_geoms[0], 0] == friction[i, core.obj_geoms[0]]
        np.testing.assert_array_equal(m.actuator_gainprm[:, 0], f["gain"][i])


def test_samples_lie_in_the_configured_ranges(randomized):
    core, _ = randomized
    rc, p = core.cfg.randomization, core.params
    buckets = np.asarray(rc.scales)
    jitter = np.abs(p["scale"][:, None] - buckets[None]).min(axis=1)
    assert np.all(jitter <= rc.scale_jitter + 1e-12)
    ranges = [("mass", rc.mass), ("friction", rc.friction), ("com", rc.com), ("kp", rc.kp), ("kd", rc.kd)]
    if rc.link_friction is not None:  # the hardware physics' own friction of the links and palm
        ranges.append(("link_friction", rc.link_friction))
    for key, (lo, hi) in ranges:
        assert np.all((p[key] >= lo) & (p[key] <= hi)), key
        assert np.unique(p[key]).size == p[key].size, f"{key} is not sampled per env (and per joint)"
    # 16 envs cover a good part (a third) of each range (a sampler stuck in a corner would not)
    for key, (lo, hi) in (("mass", rc.mass), ("friction", rc.friction), ("scale", (min(buckets), max(buckets)))):
        assert np.ptp(p[key]) > (hi - lo) / 3, key


def test_subset_reset_rewrites_only_those_envs():
    core = RotateCupVec(EnvConfig(), num_envs=4, seed=0, nthread=1)
    core.reset(seed=0)
    before = {k: v.copy() for k, v in fields(core).items()}
    core.reset(ids=[2])
    after = fields(core)
    for k in before:
        np.testing.assert_array_equal(after[k][[0, 1, 3]], before[k][[0, 1, 3]], err_msg=k)
    assert after["mass"][2] != before["mass"][2] and after["friction"][2, 0] != before["friction"][2, 0]
    np.testing.assert_array_equal(after["mass"], core.params["mass"])


def test_perturbation_shifts_exactly_the_samples():
    shift = (0.002, -0.003, 0.001)
    base = RotateCupVec(EnvConfig(), num_envs=8, seed=3, nthread=1)
    pert = RotateCupVec(EnvConfig(perturb=Perturbation(friction_scale=0.5, added_mass=0.05, com_shift=shift)),
                        num_envs=8, seed=3, nthread=1)
    ob, op = base.reset(seed=3), pert.reset(seed=3)
    fb, fp = fields(base), fields(pert)
    np.testing.assert_allclose(fp["friction"], 0.5 * fb["friction"], rtol=1e-15)
    np.testing.assert_allclose(fp["mass"], fb["mass"] + 0.05, rtol=1e-15)
    np.testing.assert_allclose(fp["com"], fb["com"] + np.array(shift), rtol=0, atol=1e-15)
    np.testing.assert_allclose(op["priv"][:, PRIV["mass"]], ob["priv"][:, PRIV["mass"]] + 0.05, rtol=1e-6)
    # nothing else moves: scale, gains, geometry, grasp and the whole proprioceptive observation
    for k in ("size", "gain", "bias_kp", "bias_kd"):
        np.testing.assert_array_equal(fp[k], fb[k], err_msg=k)
    for k in ("scale", "kp", "kd"):
        np.testing.assert_array_equal(pert.params[k], base.params[k], err_msg=k)
    np.testing.assert_array_equal(op["proprio_hist"], ob["proprio_hist"])
    np.testing.assert_array_equal(op["priv"][:, :4], ob["priv"][:, :4])  # object position and scale


def test_disabled_randomization_gives_nominal_values_by_hand():
    cfg = EnvConfig(object="cylinder", randomization=RandomizationConfig(enabled=False),
                    perturb=Perturbation(friction_scale=0.5, added_mass=0.05, com_shift=(0.0, 0.0, 0.004)))
    core = RotateCupVec(cfg, num_envs=3, seed=0, nthread=1)
    obs = core.reset(seed=0)
    f = fields(core)
    # middle of 9 scale buckets: 0.78; mass (0.01 + 0.25) / 2 + 0.05 = 0.18 kg; friction (0.3 + 3.0) / 2 x 0.5 = 0.825
    np.testing.assert_allclose(core.params["scale"], 0.78, rtol=1e-15)
    np.testing.assert_allclose(f["mass"], 0.18, rtol=1e-15)
    np.testing.assert_allclose(f["friction"], 0.825, rtol=1e-15)
    np.testing.assert_allclose(f["com"], [[0.0, 0.0, 0.004]] * 3, rtol=0, atol=1e-18)
    np.testing.assert_array_equal(f["gain"], 3.0)
    np.testing.assert_array_equal(f["bias_kp"], -3.0)
    np.testing.assert_array_equal(f["bias_kd"], -0.1)
    # Hora's cylinder 'cylinder': radius 4 cm, length 8 cm -> at 0.78: radius 0.0312 m, half length 0.0312 m
    np.testing.assert_allclose(f["size"][:, 0, :2], 0.0312, rtol=1e-12)
    # solid cylinder with its axis along y: I_yy = m r^2 / 2 = 0.18 * 0.0312^2 / 2 = 8.761e-5,
    # I_xx = I_zz = m (3 r^2 + h^2) / 12 = 0.18 * (3 * 0.0312^2 + 0.0624^2) / 12 = 1.022112e-4 (kg m^2)
    np.testing.assert_allclose(f["inertia"], [[1.022112e-4, 8.76096e-5, 1.022112e-4]] * 3, rtol=1e-9)
    np.testing.assert_allclose(obs["priv"][:, 3:6], [[0.78, 0.18, 0.825]] * 3, rtol=1e-6)
    # no observation noise and no pushes: the observed joints are the true ones, the object feels no force
    for _ in range(3):
        obs, *_ = core.step(np.full((3, 16), 0.3))
    q = core.batch.bind("qpos")[:, :16]
    np.testing.assert_allclose(C.unscale_joints(obs["proprio"][:, -1, :16].astype(np.float64)), q, atol=1e-6)
    np.testing.assert_array_equal(core.batch.bind("xfrc_applied"), 0.0)


def test_observation_noise_is_bounded_by_the_config():
    core = RotateCupVec(EnvConfig(), num_envs=8, seed=2, nthread=1)
    core.reset(seed=2)
    obs, *_ = core.step(np.zeros((8, 16)))
    q = core.batch.bind("qpos")[:, :16]
    noise = C.unscale_joints(obs["proprio"][:, -1, :16].astype(np.float64)) - q
    assert np.abs(noise).max() <= 0.02 + 1e-5  # U(-0.02, 0.02) rad, plus float32 rounding
    assert np.abs(noise).max() > 0.015  # 128 draws: the noise is really there
    np.testing.assert_allclose(obs["proprio"][:, -1, 16:], core.targets, rtol=1e-6)  # targets are not noisy


def test_log_uniform_friction_maps_the_same_draws_onto_a_log_scale():
    """friction_log: the same per-env draw u gives lo * (hi / lo) ** u instead of lo + (hi - lo) * u; the other
    parameters are unchanged, and the nominal friction (randomization off) stays the range's middle."""
    lo, hi = 0.075, 3.0
    base = RandomizationConfig(friction=(lo, hi))
    lin = RotateCupVec(EnvConfig(randomization=base), num_envs=N, seed=5, nthread=1)
    log = RotateCupVec(EnvConfig(randomization=RandomizationConfig(friction=(lo, hi), friction_log=True)),
                       num_envs=N, seed=5, nthread=1)
    lin.reset(seed=5), log.reset(seed=5)
    u = (lin.params["friction"] - lo) / (hi - lo)
    np.testing.assert_allclose(log.params["friction"], lo * (hi / lo) ** u, rtol=1e-12)
    np.testing.assert_allclose(fields(log)["friction"][:, 0], log.params["friction"], rtol=1e-15)
    for key in ("mass", "com", "scale", "kp"):
        np.testing.assert_array_equal(log.params[key], lin.params[key])
    off = RotateCupVec(EnvConfig(randomization=RandomizationConfig(enabled=False, friction=(lo, hi),
                                                                   friction_log=True)), num_envs=2, seed=5, nthread=1)
    off.reset(seed=5)
    np.testing.assert_allclose(off.params["friction"], (lo + hi) / 2, rtol=1e-15)
