"""Simulated Digit 360: MuJoCo sensors and readout, rendered streams (rates, causality, determinism), env group."""

from __future__ import annotations

import dataclasses
from functools import partial

import mujoco
import numpy as np
import pytest

from envs import EnvConfig, RotateCupVec
from envs.constants import DEFAULT_HAND
from envs.objects import get_object
from envs.scene import build_model, hand_variant, hand_xml_path
from envs.sensors import digit360_image as I
from envs.sensors import digit360_model as M
from envs.sensors import digit360_render as R
from envs.sensors import digit360_signals as S
from envs.sensors.digit360 import (
    DOME_RADIUS,
    FIELD,
    FINGERS,
    NUM_FIELDS,
    Digit360Readout,
    add_digit360_sensors,
    contact_frame_force,
)
from envs.sensors.tactile_obs import WINDOW_SHAPES, TactileObs

SUBSTEPS = 5


@pytest.fixture(scope="module")
def grasp():
    """The default hand + cylinder with the Digit 360 sensors, fingers closed on the object (at the hand's
    canonical pose) for 1 s."""
    model = build_model(get_object("cylinder"), 0.8, 0.01, edit=partial(add_digit360_sensors, history=SUBSTEPS),
                        hand=DEFAULT_HAND)
    data = mujoco.MjData(model)
    pose = hand_variant(DEFAULT_HAND).canonical_pose
    data.qpos[:16] = pose
    data.ctrl[:] = pose
    mujoco.mj_forward(model, data)
    for _ in range(100):
        mujoco.mj_step(model, data)
    return model, data


def test_add_sensors_checks_the_spec():
    spec = mujoco.MjSpec.from_file(hand_xml_path())
    add_digit360_sensors(spec, history=3)
    model = spec.compile()
    ids = [i for i in range(model.nsensor) if "_d360_" in model.sensor(i).name]
    assert len(ids) == 4 * len(FINGERS) and set(model.sensor_history[ids, 0]) == {3}
    with pytest.raises(ValueError, match="already has Digit 360 sensors"):
        add_digit360_sensors(spec, history=3)
    with pytest.raises(ValueError, match="needs a site and a geom named 'index_tip'"):
        add_digit360_sensors(mujoco.MjSpec(), history=3)
    with pytest.raises(ValueError, match="no sensor 'index_d360_contact'"):
        Digit360Readout(build_model(get_object("cylinder")))


def test_history_readout_equals_each_substep_reading(grasp):
    model, data = grasp
    data = mujoco.MjData(model)  # a fresh copy of the grasp state
    mujoco.mj_copyData(data, model, grasp[1])
    readout = Digit360Readout(model)
    expected, times = [], []
    for _ in range(SUBSTEPS):
        times.append(data.time)
        mujoco.mj_step(model, data)  # sensordata: computed at the start of this substep
        expected.append(readout.read_current(data.sensordata[None])[0, :, 0])
    t, rows = readout.read(data.history[None], SUBSTEPS)
    assert t.shape == (1, SUBSTEPS) and rows.shape == (1, 4, SUBSTEPS, NUM_FIELDS)
    assert np.allclose(t[0], times)
    assert np.allclose(rows[0], np.stack(expected, axis=1))


def test_contact_fields_are_physical(grasp):
    model, data = grasp
    rows = Digit360Readout(model).read_current(data.sensordata[None])[0, :, 0]  # (4, D)
    touching = rows[:, FIELD["c0_found"]] > 0
    assert touching.sum() >= 2  # the grasp holds the object
    radius = hand_variant(DEFAULT_HAND).tip_radius  # the default hand's domes (14 mm on 'digit360', 12 mm on v4)
    for row in rows[touching]:
        p = np.array([row[FIELD[f"c0_{a}"]] for a in "xyz"])
        assert abs(np.linalg.norm(p) - radius) < 1e-3  # on the dome surface (m)
        force = np.array([row[FIELD["force_x"]], row[FIELD["force_y"]], -row[FIELD["force_n"]]])  # on the dome
        assert -force @ p / np.linalg.norm(p) == pytest.approx(row[FIELD["c0_fn"]], rel=0.05)  # pushes inward
        assert row[FIELD["c0_fn"]] > 0 and row[FIELD["c0_slip"]] >= 0
    acc = rows[:, FIELD["acc_x"] : FIELD["acc_z"] + 1]
    assert np.allclose(np.linalg.norm(acc, axis=1), 9.81, atol=1.5)  # a hand at rest reads about 1 g


def test_contact_frame_force_splits_the_force_at_the_contact(grasp):
    # a contact on the side of the dome (+x): pressed 2 N inward and dragged 1 N down. Along the camera axis (z) the
    # sensor-frame columns read 1 N "normal" and 2 N across; at the contact it is 2 N normal, 1 N tangential
    row = np.zeros(NUM_FIELDS, np.float32)
    row[FIELD["force_x"]], row[FIELD["force_n"]] = -2.0, 1.0  # force on the dome (-2, 0, -1): force_n = -F_z
    row[FIELD["c0_found"]], row[FIELD["c0_fn"]], row[FIELD["c0_x"]] = 1.0, 2.0, DOME_RADIUS
    assert np.allclose(contact_frame_force(row), [2.0, 1.0])
    row[FIELD["c0_found"]] = 0.0
    assert np.array_equal(contact_frame_force(row), [0.0, 0.0])  # no contact: zeros

    model, data = grasp  # the real grasp: the normal part is the contact's normal force, the magnitude is kept
    rows = Digit360Readout(model).read_current(data.sensordata[None])[0, :, 0]  # (4, D)
    split = contact_frame_force(rows)
    touching = rows[:, FIELD["c0_found"]] > 0
    assert touching.sum() >= 2 and np.all(split[~touching] == 0)
    net = np.linalg.norm(rows[:, [FIELD["force_n"], FIELD["force_x"], FIELD["force_y"]]], axis=1)
    assert np.allclose(np.linalg.norm(split, axis=1)[touching], net[touching], rtol=1e-4)
    assert np.allclose(split[touching, 0], rows[touching, FIELD["c0_fn"]], rtol=0.05)


def test_touch_leaves_the_dynamics_unchanged():
    runs = {}
    for tactile in (False, True):
        env = RotateCupVec(EnvConfig(tactile=tactile), num_envs=2, seed=5, nthread=1)
        env.reset()
        actions = np.random.default_rng(0).uniform(-1, 1, (12, 2, 16))
        for a in actions:
            obs, reward, *_ = env.step(a)
        runs[tactile] = (obs["proprio_hist"], obs["priv"], reward)
        assert ("tactile" in obs) == tactile and ("tactile" in env.single_observation_space.spaces) == tactile
    for a, b in zip(runs[False], runs[True], strict=True):
        assert np.array_equal(a, b)


def test_env_tactile_group_follows_the_contract():
    env = RotateCupVec(EnvConfig(tactile=True), num_envs=2, seed=1, nthread=1)
    env.reset()
    for _ in range(7):
        obs, *_ = env.step(np.zeros((2, 16)))
    tac = obs["tactile"]
    assert isinstance(tac, TactileObs) and isinstance(tac, dict) and tac.num_envs == 2
    assert list(tac.keys()) == list(FINGERS) and list(tac["index"].keys()) == list(WINDOW_SHAPES)
    assert np.array_equal(tac.frame, [10, 10])  # 7 steps = 0.35 s: the last 30 fps frame is 10 (0.333 s)
    windows = tac["thumb"]
    for m, shape in WINDOW_SHAPES.items():
        assert windows[m].shape == (2, *shape) and windows[m].dtype == np.float32 and np.isfinite(windows[m]).all()
    single = tac[1]  # the gymnasium env's view: no env axis
    assert np.array_equal(single["thumb"]["imu"], windows["imu"][1])
    merged = tac.copy()
    merged[np.array([True, False])] = tac[np.array([1, 0])][np.array([True, False])]  # auto-reset style masking
    assert np.array_equal(merged["thumb"]["audio"][0], windows["audio"][1])
    with pytest.raises(KeyError, match="unknown finger"):
        tac["pinky"]


def _track(seconds=2.0, press_at=0.5, impact_at=1.2) -> M.ContactTrack:
    times = np.arange(int(seconds / 0.01)) * 0.01
    rows = np.zeros((len(times), NUM_FIELDS), np.float32)
    rows[:, FIELD["acc_z"]] = 9.81
    on = times >= press_at
    fn = np.clip((times - press_at) * 2.0, 0.0, 1.0) + np.where(times >= impact_at, 1.0, 0.0)
    rows[on, FIELD["c0_found"]] = 1
    rows[on, FIELD["c0_fn"]] = fn[on]
    rows[on, FIELD["c0_z"]] = DOME_RADIUS
    rows[on, FIELD["force_n"]] = fn[on]
    return M.ContactTrack(times, rows, 0.01)


def test_window_grids_and_rates():
    w = R.WindowIndex(45)  # t = 1.5 s
    assert w.time == 1.5 and list(w.frames) == [40, 45]
    assert w.imu[-1] / M.IMU_HZ <= w.time and len(w.imu) == 224 and np.all(np.diff(w.imu) == 1)
    assert w.pressure[-1] / M.PRESSURE_HZ <= w.time and len(w.pressure) == 224
    assert w.audio_first + M.AUDIO_SAMPLES - 1 == 72000  # the sample at exactly 1.5 s is the last one
    assert w.start_time == pytest.approx(1.5 - 223 / 200)
    raw = R.render_window(_track(), 45, key=3)
    assert raw["image"].shape == (2, 224, 224, 3) and raw["image"].dtype == np.uint8
    assert raw["audio"].shape == (2, 27000) and raw["imu"].shape == (224, 3) and raw["pressure"].shape == (224,)


def test_rendered_streams_are_causal_and_deterministic():
    track = _track()
    cut = M.ContactTrack(track.times[track.times <= 1.5], track.rows[track.times <= 1.5], 0.01)
    a, b, c = R.render_window(track, 45, key=3), R.render_window(cut, 45, key=3), R.render_window(track, 45, key=3)
    other = R.render_window(track, 45, key=4)
    for k in a:
        assert np.array_equal(a[k], b[k]), f"{k} used rows after the window's end"
        assert np.array_equal(a[k], c[k])
    assert not np.array_equal(a["audio"], other["audio"]) and not np.array_equal(a["imu"], other["imu"])
    # overlapping audio windows agree sample for sample on their overlap
    x = S.render_audio(track, 30000, 27000, key=3)
    y = S.render_audio(track, 40000, 27000, key=3)
    assert np.array_equal(x[:, 10000:], y[:, :17000])


def test_streams_respond_to_contact():
    track = _track()
    rest = S.render_pressure(track, np.arange(0, 90), key=3)  # 0 .. 0.45 s: no contact
    pressed = S.render_pressure(track, np.arange(200, 220), key=3)  # 1.0 .. 1.1 s: 1 N
    assert 985 < rest.mean() < 1030 and rest.std() < 0.1
    assert pressed.mean() - rest.mean() == pytest.approx(M.DEFAULT_MODEL.pressure_per_newton, abs=0.2)
    frames = I.render_frames(track, np.array([9, 36]), key=3)  # 0.3 s (no contact), 1.2 s (2 N)
    assert np.abs(frames[1].astype(int) - frames[0].astype(int)).max() > 20
    mean = frames[0].reshape(-1, 3).mean(axis=0) / 255  # the background's mean color is the released image mean
    assert np.allclose(mean, M.DEFAULT_MODEL.background_mean, atol=0.01)
    audio = S.render_audio(track, int(1.1 * 48000), 9600, key=3)  # 1.1 .. 1.3 s: the impact at 1.2 s rings
    before, after = audio[:, :4800], audio[:, 4800:5800]
    assert np.abs(after).max() > 10 * np.abs(before).std()
    imu = S.render_imu(track, np.arange(100), key=3)
    assert np.allclose(imu[:, 2], 1.0, atol=0.05) and np.allclose(imu * 4096, np.round(imu * 4096))  # 1/4096 g


def test_gymnasium_wrappers_accept_the_tactile_group():
    import gymnasium as gym

    env = gym.make("RotateCup-v0", tactile=True)  # the passive env checker walks the nested Dict space
    obs, _ = env.reset(seed=0)
    obs, *_ = env.step(np.zeros(16, np.float32))
    assert obs["tactile"]["ring"]["pressure"].shape == (224, 1)
    vec = gym.make_vec("envs:RotateCup-v0", num_envs=2, vectorization_mode="vector_entry_point", tactile=True)
    vec.reset(seed=0)
    obs, *_ = vec.step(np.zeros((2, 16), np.float32))
    assert obs["tactile"]["index"]["imu"].shape == (2, 224, 3)


def test_the_vendor_hands_domes_render_at_their_own_radius():
    """hand='digit360_v4' carries Meta's 12 mm domes: its touch renders with that radius (the older hand's 14 mm is
    the default model), and the same press makes a smaller imprint on the smaller dome (Hertz: contact radius grows
    as R^(1/3), and the image's arc per pixel with R)."""
    env = RotateCupVec(EnvConfig(hand="digit360_v4", tactile=True), num_envs=2, seed=1, nthread=1)
    env.reset()
    for _ in range(3):
        obs, *_ = env.step(np.zeros((2, 16)))
    assert obs["tactile"].model.dome_radius == 0.012 and obs["tactile"]["index"]["image"].shape[0] == 2
    older = RotateCupVec(EnvConfig(hand="digit360", tactile=True), num_envs=1, seed=1, nthread=1)
    assert older.touch.sensor == M.DEFAULT_MODEL and M.DEFAULT_MODEL.dome_radius == 0.014
    track = _track()
    small = dataclasses.replace(M.DEFAULT_MODEL, dome_radius=0.012)
    frames = {m: I.render_frames(track, np.array([9, 36]), key=3, model=m).astype(int)
              for m in (M.DEFAULT_MODEL, small)}
    touched = {m.dome_radius: int((np.abs(f[1] - f[0]).max(axis=-1) > 10).sum()) for m, f in frames.items()}
    assert 0 < touched[0.012] and touched[0.012] != touched[0.014], touched
