"""`--digit360 sim` beside an emulated hand: each emulated fingertip senses its finger of the hand, and its reader's
window has all four Sparsh-X modalities, rendered with the env's sensor model of that hand (envs.scene.touch_model:
the older 'digit360' hand's generation-1 model, the vendor-kinematics hands' generation-2 one)."""

from __future__ import annotations

import contextlib
import time

import numpy as np
import pytest

from envs.scene import touch_model
from envs.sensors import digit360_model as M
from envs.sensors import digit360_render as R
from envs.sensors import digit360_signals as S
from envs.sensors.digit360 import FIELD, FINGERS
from rotation.deploy.sensors import open_digit360
from rotation.hardware.digit360.reader import SensorStale
from rotation.hardware.digit360.window import WindowNotReady
from rotation.sim_hardware.hand_physics import HandPhysics

SHAPES = {"image": ((6, 224, 224), np.uint8), "audio": ((2, 27000), np.int16), "imu": ((224, 3), np.float32),
          "pressure": ((224, 1), np.float32)}
"""The reader's Sparsh-X window (rotation.hardware.digit360.window)."""


def first_window(reader, timeout_s: float = 5.0) -> dict:
    deadline = time.monotonic() + timeout_s
    while True:
        try:
            return reader.window()
        except (WindowNotReady, SensorStale):
            if time.monotonic() > deadline:
                raise
            time.sleep(0.05)


def test_sim_fingertips_sense_the_emulated_hand(pressed_and_free_grasp):
    physics = HandPhysics.at_grasp("cup", pressed_and_free_grasp, hold=True)  # the thumb presses, the middle is free
    fields = physics.contact_fields()
    rise: dict[str, float] = {}  # pressure above the sensor's no-contact level (hPa)
    with contextlib.ExitStack() as stack:
        readers = open_digit360({"thumb": "sim", "middle": "sim"}, stack, physics)
        windows = {finger: first_window(reader) for finger, reader in readers.items()}
        for finger, w in windows.items():
            for modality, (shape, dtype) in SHAPES.items():
                assert w[modality].shape == shape and w[modality].dtype == dtype, (finger, modality)
                assert np.all(np.isfinite(w[modality]))
            touch = readers[finger].media
            fi = FINGERS.index(finger)
            model = touch.model
            assert model == touch_model(physics.hand)  # the hand's own sensor model (dome radius, generation)
            frame = int(round((w["t_end"] - touch.t0) * M.IMAGE_HZ))  # the window ends at this frame of the sensor
            assert w["t_end"] == pytest.approx(touch.t0 + frame / M.IMAGE_HZ)
            # pressure: the no-contact level of this sensor (rest, offset, drift) plus the env's gain x the normal
            # force of the contacts on the dome
            level, _ = S.pressure_terms(R.WindowIndex(frame).pressure, touch.key, model)
            rise[finger] = float(w["pressure"].mean() - level.mean())
            gain = model.pressure_per_newton
            normal = fields[fi, FIELD["c0_fn"]] + fields[fi, FIELD["c1_fn"]]
            assert rise[finger] == pytest.approx(gain * normal, abs=0.05), finger
            assert np.linalg.norm(w["imu"].mean(axis=0)) == pytest.approx(1.0, abs=0.05)  # a held hand: gravity
            # image and audio: the env's renderer on the sensor's contact track
            raw = R.render_window(touch.track(), frame, touch.key, fi, model)
            assert np.array_equal(w["image"], raw["image"].transpose(3, 0, 1, 2).reshape(6, 224, 224))
            assert np.array_equal(w["audio"], np.rint(raw["audio"]).astype(np.int16))
    assert rise["thumb"] > 1.0  # pressed: above rest
    assert abs(rise["middle"]) < 0.05  # free: rest pressure
