"""Real-device checks, deselected by default: run with ``make test-hardware`` (``pytest -m hardware``).

Devices come from environment variables (defaults in brackets): ALLEGRO_CAN [socketcan:can0],
LEAP_PORT [/dev/ttyUSB0], DIGIT360_SERIAL (USB serial number of one sensor, plugged in whole: its camera and
microphones are read too). These tests only read: motors stay off.
"""

from __future__ import annotations

import os

import numpy as np
import pytest

from rotation.hardware.allegro.driver import AllegroConfig, AllegroHand
from rotation.hardware.digit360.reader import Digit360, Digit360Config
from rotation.hardware.leap.driver import LeapConfig, LeapHand

pytestmark = pytest.mark.hardware


def test_allegro_reads_info_and_state():
    with AllegroHand(os.environ.get("ALLEGRO_CAN", "socketcan:can0"), AllegroConfig(enable_motors=False)) as h:
        info = h.info()
        assert info.kind.startswith("allegro") and info.serial
        state = h.read_state()
        assert state.q.shape == (16,) and np.all(np.isfinite(state.q))


def test_leap_reads_info_and_state():
    with LeapHand(os.environ.get("LEAP_PORT", "/dev/ttyUSB0"), LeapConfig(enable_motors=False)) as h:
        assert h.info().kind == "leap"
        assert np.all(np.isfinite(h.read_state().q))


def test_digit360_serial_stream():
    serial_number = os.environ.get("DIGIT360_SERIAL")
    assert serial_number, "set DIGIT360_SERIAL to the USB serial number of the sensor under test"
    import time

    with Digit360(Digit360Config(serial_number=serial_number)) as d:
        time.sleep(1.5)
        w = d.window()
        assert w["imu"].shape == (224, 3) and 800 < float(w["pressure"].mean()) < 1200


def test_digit360_camera_and_microphones_on_its_hub():
    """The camera and microphones that deploy finds for the sensor (its USB hub) open and fill a whole window."""
    serial_number = os.environ.get("DIGIT360_SERIAL")
    assert serial_number, "set DIGIT360_SERIAL to the USB serial number of the sensor under test"
    import time

    from rotation.hardware.digit360.discovery import find_digit360_devices, find_digit360_ports

    (tty, _), = find_digit360_ports(serial_number)
    devices = find_digit360_devices(tty)
    assert devices.camera and devices.audio, f"found {devices} on the hub of {tty}"
    cfg = Digit360Config(serial_number=serial_number, camera=devices.camera, audio_device=devices.audio)
    with Digit360(cfg) as d:
        time.sleep(2.0)
        w = d.window()
        assert w["image"].shape == (6, 224, 224) and w["audio"].shape == (2, 27000)
