"""Real-device checks, deselected by default: run with ``pytest -m hardware``.

Devices come from environment variables (defaults in brackets): ALLEGRO_CAN [socketcan:can0],
LEAP_PORT [/dev/ttyUSB0], DIGIT360_SERIAL (USB serial number of one sensor). These tests only read: motors
stay off.
"""

from __future__ import annotations

import os

import numpy as np
import pytest

from rotation.hardware.allegro import AllegroConfig, AllegroHand
from rotation.hardware.digit360 import Digit360, Digit360Config
from rotation.hardware.leap import LeapConfig, LeapHand

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
