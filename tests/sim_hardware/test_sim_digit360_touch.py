"""Emulated Digit 360 fingertips that sense the emulated hand: the hand's contact fields, and streams that equal the
env's simulated touch for the same contact history (what the tactile adapter learnt on is what deploy feeds it)."""

from __future__ import annotations

import numpy as np
import pytest

from envs.sensors import digit360_model as M
from envs.sensors import digit360_render as R
from envs.sensors import kaldi
from envs.sensors.digit360 import DOME_RADIUS, FIELD, FINGERS, NUM_FIELDS
from envs.sensors.tactile_obs import TactileObs
from rotation.hardware.digit360.reader import Digit360, Digit360Config
from rotation.hardware.digit360.window import WindowNotReady
from rotation.sim_hardware.digit360_emulator import Digit360Emulator
from rotation.sim_hardware.digit360_touch import FingertipTouch, audio_counts
from rotation.sim_hardware.hand_physics import HandPhysics

FINGER = "thumb"
SEED = 7
T0 = 100.0
"""Host time of the scripted sensor's device time 0 (s)."""


class ScriptedHand:
    """Stands in for HandPhysics: each contact_fields() call returns the next scripted row on FINGER's tip."""

    def __init__(self, rows: np.ndarray) -> None:
        self.rows, self.calls = rows, 0

    def contact_fields(self) -> np.ndarray:
        out = np.zeros((len(FINGERS), NUM_FIELDS), np.float32)
        out[FINGERS.index(FINGER)] = self.rows[min(self.calls, len(self.rows) - 1)]
        self.calls += 1
        return out


def scripted_rows(count: int) -> np.ndarray:
    """(count, NUM_FIELDS) rows at 10 ms: rest, a press from 0.3 s with a knock at 0.9 s, sliding after 1.1 s."""
    t = np.arange(count) * 0.01
    rows = np.zeros((count, NUM_FIELDS), np.float32)
    rows[:, FIELD["acc_z"]] = 9.81 + 0.3 * np.sin(2 * np.pi * 7 * t)
    on = t >= 0.3
    fn = np.clip((t - 0.3) * 3.0, 0.0, 1.5) + np.where(t >= 0.9, 1.0, 0.0)
    point = np.array([0.3, 0.0, 1.0]) / np.hypot(0.3, 1.0) * DOME_RADIUS
    rows[on, FIELD["c0_found"]] = 1
    rows[on, FIELD["c0_fn"]] = fn[on]
    rows[on, FIELD["force_n"]] = fn[on]
    rows[on, FIELD["force_x"]] = 0.2 * fn[on]
    for axis, value in zip("xyz", point, strict=True):
        rows[on, FIELD[f"c0_{axis}"]] = value
    rows[t >= 1.1, FIELD["c0_slip"]] = 0.02
    return rows


@pytest.mark.parametrize("model", [M.DEFAULT_MODEL, M.CONTACT_MODEL], ids=["generation1", "generation2"])
def test_emulated_fingertip_streams_equal_the_env_windows(model):
    rows = scripted_rows(160)  # 1.6 s
    touch = FingertipTouch(ScriptedHand(rows), FINGER, seed=SEED, model=model)
    touch.start(T0)
    with pytest.raises(WindowNotReady):
        touch.media_window()  # no row taken yet
    serial = [touch.readings(k) for k in range(1, 4 * 159 + 1)]  # what the emulator streams, tick by tick
    imu = np.stack([a for a, _ in serial])  # samples 1..636 at 400 Hz
    pressure = np.array([p for _, p in serial if p is not None])  # samples 1..318 at 200 Hz
    track = touch.track()
    np.testing.assert_array_equal(track.rows, rows[-len(track.rows):])  # one scripted row per 10 ms of device time
    assert track.times[-1] == pytest.approx(1.59) and len(track.rows) > M.HISTORY_S / 0.01  # the newest 1.2 s
    with pytest.raises(WindowNotReady, match="history"):
        touch.media_window(T0 + 0.3)  # the audio window reaches back before the sensor started

    # the env's `tactile` observation over the same contact track, at frame 45 (1.5 s)
    fi = FINGERS.index(FINGER)
    keys = np.zeros((1, len(FINGERS)), np.uint64)
    keys[0, fi] = M.finger_key(SEED, fi)
    env_rows = np.zeros((1, len(FINGERS), len(track.rows), NUM_FIELDS), np.float32)
    env_rows[0, fi] = track.rows
    env = TactileObs(track.times[None], env_rows, keys, np.array([1.5 + 0.005]), 0.01,
                     model=model).window(0, FINGER)

    touch.media_window(T0 + 40 / 30)  # frame 40 is rendered (and kept) first: it is frame 45's t-5 frame
    image, audio, t_frame = touch.media_window(T0 + 1.5 + 0.001)
    assert t_frame == pytest.approx(T0 + 1.5)
    assert image.shape == (6, 224, 224) and image.dtype == np.uint8
    assert audio.shape == (2, 27000) and audio.dtype == np.int16
    np.testing.assert_array_equal(image.astype(np.float32) / 255.0, env["image"])
    raw = R.render_window(track, 45, int(keys[0, fi]), fi, model)
    np.testing.assert_array_equal(audio, audio_counts(raw["audio"]))  # the env's audio as int16 counts
    assert np.abs(audio).max() > 500  # the knock and the sliding are heard
    # the env's log-mels are of unrounded counts: rounding to int16, as a microphone delivers, moves them little
    # (the features' per-bin spread is ~1-2)
    error = np.abs(kaldi.fbank(audio.astype(np.float32)) - env["audio"])
    assert error.mean() < 0.1 and np.percentile(error, 99) < 0.5
    w = R.WindowIndex(45)
    np.testing.assert_array_equal(imu[w.imu - 1], env["imu"])
    np.testing.assert_array_equal(pressure[w.pressure - 1, None], env["pressure"])
    assert env["pressure"][-1, 0] - env["pressure"][0, 0] > 5  # 2.5 N at the end, none at the start


def test_held_hand_reads_gravity_and_the_grasp(pressed_and_free_grasp):
    physics = HandPhysics.at_grasp("cup", pressed_and_free_grasp, hold=True)
    fields = physics.contact_fields()  # (4, NUM_FIELDS)
    acc = fields[:, FIELD["acc_x"] : FIELD["acc_z"] + 1]
    np.testing.assert_allclose(np.linalg.norm(acc, axis=1), 9.81, atol=1e-3)  # a held scene is still
    thumb, middle = fields[FINGERS.index("thumb")], fields[FINGERS.index("middle")]
    assert thumb[FIELD["force_n"]] > 0.2 and thumb[FIELD["c0_found"]] == 1  # the thumb presses the cup
    assert middle[FIELD["c0_found"]] == 0 and middle[FIELD["force_n"]] == 0
    physics.release()
    physics.advance(0.01)
    moving = physics.contact_fields()
    assert not np.array_equal(moving[:, FIELD["acc_x"] : FIELD["acc_z"] + 1], acc)  # recomputed after a step


def test_emulated_media_options_are_checked():
    physics = HandPhysics.at_grasp("cup", 0, hold=True)
    with pytest.raises(ValueError, match="not both"):
        Digit360Emulator(source=lambda t: (0.0, np.zeros(3)), physics=physics, finger="index")
    with pytest.raises(ValueError, match="unknown finger"):
        Digit360Emulator(physics=physics, finger="pinky")
    emu = Digit360Emulator()
    emu.close()
    assert emu.media is None  # without a hand: no camera, no microphones
    touch = FingertipTouch(physics, "index")
    with pytest.raises(ValueError, match="leave Digit360Config.camera"):
        Digit360(Digit360Config(port="/dev/null", camera=0), media=touch)
