"""Simulated Xela skin: pad layout and geometry on the hand, the reading model (rest value, rise with force, spread,
hysteresis, determinism), and the env's `skin` group with the plain env unchanged when the skin is off."""

from __future__ import annotations

import json
from functools import partial

import mujoco
import numpy as np
import pytest

from envs import EnvConfig, RotateCupVec
from envs.constants import DEFAULT_HAND
from envs.grasp_cache import load_default_cache
from envs.objects import get_object
from envs.scene import build_model, hand_spec, hand_xml_path
from envs.sensors import xela as X
from envs.sensors.skin_obs import CHANNELS
from envs.sensors.xela_hand import XelaReadout, add_xela_sensors, make_xela_hand, pad_geom

FLAT = [p for p in X.PADS if p.kind != "fingertip"]


def test_taxel_count_and_pad_table():
    assert X.NUM_TAXELS == 368 and X.NUM_PADS == 18
    kinds = [p.kind for p in X.PADS]
    assert (kinds.count("fingertip"), kinds.count("phalanx"), kinds.count("palm")) == (4, 11, 3)
    for p in X.PADS:
        n = {"fingertip": 30, "phalanx": 16, "palm": 24}[p.kind]
        assert p.taxels == n and X.PAD_SLICES[p.name].stop - X.PAD_SLICES[p.name].start == n
        assert p.taxels == (p.rows * p.cols if p.kind != "fingertip" else 30)
    assert np.bincount(X.TAXEL_TYPE).tolist() == [11 * 16, 3 * 24, 4 * 30]  # phalanx, palm, fingertip
    assert len(set(X.PAD_NAMES)) == 18 and X.TAXEL_PAD.shape == (368,)
    meta = json.loads(json.dumps(X.skin_metadata()))  # what sessions store
    assert meta["pads"] == list(X.PAD_NAMES) and sum(meta["taxels_per_pad"]) == 368 and len(meta["taxel_type"]) == 368


def test_pad_sizes_and_taxel_grid():
    lay = X.taxel_layout()
    for p in FLAT:
        pos = lay.pos[X.PAD_SLICES[p.name]]
        length, width = p.size
        assert p.size == ((0.026, 0.024) if p.kind == "phalanx" else (0.052, 0.032))  # docs/reference/hardware.md 5
        assert np.all(np.abs(pos[:, 0]) < length / 2) and np.all(np.abs(pos[:, 1]) < width / 2)
        assert np.allclose(pos[:, 2], 0.0)
        pitch = np.diff(np.unique(pos[:, 0]))
        assert np.allclose(pitch, length / p.rows)
    tip = lay.pos[X.PAD_SLICES["index_tip"]]
    radial = np.hypot(tip[:, 1], tip[:, 2])
    on_dome = tip[:, 0] > 0
    assert np.allclose(np.linalg.norm(tip[on_dome], axis=1), X.TIP_RADIUS)  # every taxel on the shell
    assert np.allclose(radial[~on_dome], X.TIP_RADIUS)
    gaps = np.linalg.norm(tip[:, None] - tip[None], axis=-1) + np.eye(30)
    assert gaps.min() > 0.003  # the 6 x 6 grid bent over the dome without crowding the apex
    frames = lay.frames
    assert np.allclose(frames @ np.swapaxes(frames, 1, 2), np.eye(3), atol=1e-9)  # orthonormal reading axes


def test_pads_sit_on_the_hand_model():
    """Taxels at the zero pose lie on their pad geom's outer face (flat) or on the fingertip shell."""
    spec = hand_spec("xela")
    model = spec.compile()
    data = mujoco.MjData(model)
    mujoco.mj_kinematics(model, data)
    lay = X.taxel_layout()
    for pad in X.PADS:
        g = model.geom(pad_geom(pad))
        site = data.site(f"xela_{pad.name}")
        rot = site.xmat.reshape(3, 3)
        world = site.xpos + lay.pos[X.PAD_SLICES[pad.name]] @ rot.T
        local = (world - data.geom(g.id).xpos) @ data.geom(g.id).xmat.reshape(3, 3)  # in the geom frame
        if pad.kind == "fingertip":
            assert g.type[0] == mujoco.mjtGeom.mjGEOM_CAPSULE and np.isclose(g.size[0], X.TIP_RADIUS)
            seg = np.clip(local[:, 2], -g.size[1], g.size[1])
            dist = np.linalg.norm(local - np.stack([0 * seg, 0 * seg, seg], 1), axis=1)
            assert np.allclose(dist, X.TIP_RADIUS, atol=1e-6), pad.name
            assert np.isclose(2 * (g.size[0] + g.size[1]), X.TIP_LENGTH)
        else:
            assert g.type[0] == mujoco.mjtGeom.mjGEOM_BOX and np.allclose(2 * g.size[:2], pad.size)
            assert np.allclose(local[:, 2], g.size[2], atol=1e-9), pad.name  # the box's outer face
            assert np.allclose(rot[:, 2], data.geom(g.id).xmat.reshape(3, 3)[:, 2])
    plain = build_model(get_object("cup"))
    assert not any(plain.geom(i).name.startswith("xela_") for i in range(plain.ngeom)) and plain.nsensor == 0
    with pytest.raises(ValueError, match="already has the Xela pads"):
        make_xela_hand(spec)
    with pytest.raises(ValueError, match="build it with make_xela_hand first"):
        add_xela_sensors(mujoco.MjSpec.from_file(hand_xml_path()), 5)
    with pytest.raises(ValueError, match="no sensor 'xela_index_tip_contact'"):
        XelaReadout(plain)


def _press(pad: str, taxel: int, force: float, shear: tuple[float, float] = (0.0, 0.0)) -> np.ndarray:
    """pad_load of one contact on ``pad`` at taxel ``taxel``'s position (pad frame), pressing with ``force`` N."""
    p = X.PAD_NAMES.index(pad)
    points, forces, found = np.zeros((18, 2, 3)), np.zeros((18, 2, 3)), np.zeros((18, 2), bool)
    points[p, 0] = X.taxel_layout().pos[X.PAD_SLICES[pad].start + taxel]
    forces[p, 0] = [shear[0], shear[1], -force]  # on the pad: pressed along -z, sheared along x, y
    found[p, 0] = True
    return X.pad_load(points, forces, found)


def test_load_rises_with_force_and_spreads_to_neighbours():
    sl = X.PAD_SLICES["middle_medial"]
    one, two = _press("middle_medial", 5, 1.0), _press("middle_medial", 5, 2.0)
    z = one[sl, 2].reshape(4, 4)  # taxel 5 = row 1, column 1
    assert np.allclose(two, 2 * one)  # linear in the force
    assert z[1, 1] == z.max() > 0
    assert z[1, 1] > z[0, 1] > z[3, 1] > 0 and z[1, 0] > z[1, 3]  # falls off with distance, still > 0 nearby
    assert np.all(np.delete(one, np.arange(sl.start, sl.stop), axis=0) == 0)  # other pads feel nothing
    sheared = _press("middle_medial", 5, 1.0, (0.5, 0.0))
    assert sheared[sl.start + 5, 0] > 0 and np.isclose(sheared[sl.start + 5, 1], 0)
    skin = X.XelaSkin(1)
    skin.reset([0], np.array([7], np.uint64))
    readings = [skin.sample(_press("middle_medial", 5, f)[None])[0, sl.start + 5, 2] for f in (0.0, 0.5, 1.0, 2.0)]
    assert np.all(np.diff(readings) > 200)  # counts rise with the pressing force


def test_pressing_a_pad_in_mujoco_reads_the_weight():
    """A block resting on a palm pad: the pad force label is its weight, and a heavier block reads more."""
    out = []
    for mass in (0.05, 0.2):
        spec = hand_spec("xela")
        block = spec.worldbody.add_body(name="block", pos=[-0.03, 0.0, 0.012])
        block.add_freejoint()
        block.add_geom(type=mujoco.mjtGeom.mjGEOM_BOX, size=[0.008, 0.008, 0.008], contype=2, conaffinity=1,
                       mass=mass)
        add_xela_sensors(spec, history=1)
        model = spec.compile()
        data = mujoco.MjData(model)
        mujoco.mj_forward(model, data)
        for _ in range(100):
            mujoco.mj_step(model, data)
        c = XelaReadout(model).read_current(data.sensordata[None])
        force = c.pad_force()[0, 0]  # (18, 3)
        p = X.PAD_NAMES.index("palm_middle")
        assert np.isclose(force[p, 0], mass * 9.81, rtol=0.02) and np.abs(force[p, 1:]).max() < 1e-6
        assert np.abs(np.delete(force[:, 0], p)).max() == 0
        out.append(X.pad_load(c.points, c.forces, c.found)[0, 0, X.PAD_SLICES["palm_middle"], 2])
    assert np.isclose(out[1].max(), 4 * out[0].max(), rtol=0.02) and out[0].max() > 0


def test_rest_value_noise_and_offsets():
    skin = X.XelaSkin(3)
    skin.reset(np.arange(3), np.array([1, 2, 3], np.uint64))
    zero = np.zeros((3, 368, 3))
    r = np.stack([skin.sample(zero) for _ in range(200)])  # (T, N, 368, 3)
    assert r.shape == (200, 3, 368, 3) and r.dtype == np.float32 and np.all(r == np.rint(r))
    assert abs(r.mean() - X.REST) < 50  # around 32768
    per_taxel = r.mean(axis=0) - X.REST
    assert 200 < per_taxel.std() < 600  # per-taxel offsets (400 counts) and drift
    assert 3 < np.median(r.std(axis=0)) < 20  # a few counts of noise over 2 s


def test_hysteresis_reading_does_not_snap_back():
    skin, m = X.XelaSkin(1), X.DEFAULT_MODEL
    skin.reset([0], np.array([5], np.uint64))
    sl = X.PAD_SLICES["index_tip"].start + 20
    press = _press("index_tip", 20, 2.0)[None]
    base = np.mean([skin.sample(np.zeros_like(press))[0, sl, 2] for _ in range(20)])
    loaded = [skin.sample(press)[0, sl, 2] for _ in range(30)]
    assert loaded[0] - base > 0.9 * (loaded[-1] - base)  # loading is followed at once
    peak = loaded[-1] - base
    released = np.array([skin.sample(np.zeros_like(press))[0, sl, 2] for _ in range(1000)]) - base
    assert released[0] > 0.5 * peak  # the elastomer lags at release
    assert 0.5 * m.memory * peak < released[30] < 0.2 * peak  # 0.3 s later a residual remains
    assert abs(released[-50:].mean()) < 0.1 * m.memory * peak + 30  # 10 s later it has faded (drift aside)


def test_readings_are_deterministic_under_a_seed():
    press = _press("thumb_tip", 3, 1.5)[None].repeat(2, 0)

    def run(keys):
        skin = X.XelaSkin(2)
        skin.reset([0, 1], np.asarray(keys, np.uint64))
        return np.stack([skin.sample(press * (t % 7)) for t in range(40)])

    a, b, c = run([11, 12]), run([11, 12]), run([11, 13])
    assert np.array_equal(a, b) and np.array_equal(a[:, 0], c[:, 0]) and not np.array_equal(a[:, 1], c[:, 1])
    with pytest.raises(ValueError, match="memory"):
        X.XelaModel(memory=1.0)


@pytest.fixture(scope="module")
def skin_env():
    env = RotateCupVec(EnvConfig(hand="xela", skin=True), num_envs=2, seed=3, nthread=1)
    obs = env.reset(seed=3)
    actions = np.random.default_rng(0).uniform(-0.5, 0.5, (6, 2, 16))
    trace = [(obs, None)]
    for a in actions:
        obs, _, _, _, info = env.step(a)
        trace.append((obs, info))
    return env, trace, actions


def test_env_skin_group(skin_env):
    env, trace, _ = skin_env
    obs, info = trace[-1]
    assert obs["skin"].shape == (2, X.WINDOW, 368, CHANNELS) and obs["skin"].dtype == np.float32
    assert env.single_observation_space["skin"].shape == (X.WINDOW, 368, CHANNELS)
    assert info["skin_force"].shape == (2, 18, 3) and info["skin_force"][..., 0].max() > 0.05  # the grasp presses
    counts, pos = obs["skin"][..., :3], obs["skin"][..., 3:]
    assert np.all((counts >= 0) & (counts <= X.FULL_SCALE)) and abs(np.median(counts) - X.REST) < 200
    assert np.allclose(obs["skin"][:, -5:], np.concatenate([env.skin.last_counts, env.skin.last_pos], -1))
    assert np.allclose(obs["skin"][:, :5], np.concatenate(
        [trace[-2][0]["skin"][:, -5:]], axis=0))  # the window slides by one step's 5 samples
    # taxel positions follow the kinematics: the palm's never move, the fingers' do
    palm = X.PAD_SLICES["palm_index"]
    assert np.allclose(pos[:, :, palm], trace[0][0]["skin"][:, :1, palm, 3:], atol=1e-9)
    assert np.abs(pos[:, -1, X.PAD_SLICES["index_tip"]] - trace[0][0]["skin"][:, -1, X.PAD_SLICES["index_tip"], 3:]
                  ).max() > 1e-3
    # the taxels under the grasp's contacts read their load above their rest (offset, drift and noise aside)
    c = env.skin.readout.read(env.batch.bind("history"), env.cfg.substeps)
    load = X.pad_load(c.points, c.forces, c.found)[:, -1]  # (2, 368, 3)
    pressed = load[..., 2] > 300
    above = counts[:, -1, :, 2] - X.REST - env.skin.skin.offset[..., 2] - env.skin.skin.drift[..., 2]
    assert pressed.sum() >= 3 and np.all(above[pressed] > 0.5 * load[..., 2][pressed])


def test_env_skin_is_deterministic_and_batch_consistent(skin_env):
    _, trace, actions = skin_env
    single = RotateCupVec(EnvConfig(hand="xela", skin=True), num_envs=1, seed=4, nthread=1)
    obs = single.reset(seed=4)  # env 1 of the batch seeded 3
    for a in actions:
        obs, *_ = single.step(a[1:])
    assert np.array_equal(obs["skin"][0], trace[-1][0]["skin"][1])


def test_skin_does_not_change_the_physics_or_the_plain_env(skin_env):
    _, trace, actions = skin_env
    quiet = RotateCupVec(EnvConfig(hand="xela"), num_envs=2, seed=3, nthread=1)  # the Xela hand, skin off
    obs = quiet.reset(seed=3)
    for a in actions:
        obs, _, _, _, info = quiet.step(a)
    assert set(obs) == {"proprio", "proprio_hist", "priv"} and "skin_force" not in info and quiet.skin is None
    assert np.array_equal(obs["proprio"], trace[-1][0]["proprio"]) and np.array_equal(obs["priv"], trace[-1][0]["priv"])
    plain = RotateCupVec(EnvConfig(), num_envs=1, seed=0, nthread=1)  # the default: a Digit 360 hand, no skin
    assert plain.skin is None and plain.model.nsensor == 0 and plain.cfg.hand == DEFAULT_HAND
    assert not any(plain.model.geom(i).name.startswith("xela_") for i in range(plain.model.ngeom))
    assert set(plain.reset(seed=0)) == {"proprio", "proprio_hist", "priv"}


def test_config_refuses_mismatched_hand_and_sensors():
    with pytest.raises(ValueError, match="skin: the Xela skin needs hand='xela'"):
        EnvConfig(skin=True)
    with pytest.raises(ValueError, match="tactile: the Digit 360 touch needs hand='digit360'"):
        EnvConfig(hand="xela", tactile=True)
    with pytest.raises(ValueError, match="hand must be one of"):
        EnvConfig(hand="leap")
    with pytest.raises(ValueError, match="skin: the Xela skin samples at 100 Hz"):
        EnvConfig(hand="xela", skin=True, physics_dt=0.005)
    with pytest.raises(ValueError, match=f"generated for the {DEFAULT_HAND} hand, not for the xela hand"):
        load_default_cache("cup", str(load_default_cache("cup").source), hand="xela")  # the default hand's cache
    with pytest.raises(ValueError, match="no grasp cache ships for object 'cylinder' on the xela hand"):
        RotateCupVec(EnvConfig(object="cylinder", hand="xela"))
    assert load_default_cache("cup", hand="xela").hand == "xela"
    with pytest.raises(ValueError, match="history"):
        partial(add_xela_sensors, history=0)(hand_spec("xela"))


def test_gymnasium_env_checker_with_the_skin():
    import warnings

    from gymnasium.utils.env_checker import check_env

    from envs.rotate_cup import RotateCupEnv

    env = RotateCupEnv(hand="xela", skin=True)
    with warnings.catch_warnings():  # unbounded Box observations are what the env declares on purpose
        warnings.filterwarnings("ignore", message=".*Box observation space (minimum|maximum) value is")
        check_env(env, skip_render_check=True)
    obs, _ = env.reset(seed=1)
    assert obs["skin"].shape == (X.WINDOW, 368, CHANNELS)
