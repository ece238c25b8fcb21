"""Allegro CAN protocol, byte-exact against docs/reference/hardware.md section 1, and the bus string parser."""

from __future__ import annotations

import math

import numpy as np
import pytest

from rotation.hardware.allegro import protocol as ap
from rotation.hardware.allegro.can_bus import open_bus, parse_can_spec


def test_wire_ids_match_the_table():
    assert ap.wire_id(ap.Msg.SYSTEM_ON) == 0x100
    assert ap.wire_id(ap.Msg.SYSTEM_OFF) == 0x104
    assert [ap.wire_id(ap.Msg.SET_TORQUE, finger=f) for f in range(4)] == [0x180, 0x184, 0x188, 0x18C]
    assert [ap.wire_id(ap.Msg.FINGER_POSE, finger=f) for f in range(4)] == [0x080, 0x084, 0x088, 0x08C]
    assert ap.wire_id(ap.Msg.SET_PERIOD) == 0x204
    assert ap.wire_id(ap.Msg.HAND_INFO) == 0x200
    assert ap.wire_id(ap.Msg.SERIAL) == 0x220
    assert ap.wire_id(ap.Msg.IMU) == 0x0C0
    assert [ap.wire_id(ap.Msg.TEMPERATURE, finger=f) for f in range(4)] == [0x0E0, 0x0E4, 0x0E8, 0x0EC]
    assert ap.wire_id(ap.Msg.SYSTEM_ON, hand_id=2) == 0x102
    assert ap.split_wire_id(0x18E) == (0x63, 2)
    with pytest.raises(ValueError):
        ap.wire_id(ap.Msg.SET_TORQUE, finger=4)


def test_real_trace_hand_info():
    info = ap.decode_hand_info(bytes.fromhex("02 04 06 04 00 3C 05"))
    assert (info.hardware, info.firmware, info.right_hand, info.temperature_c, info.status) == (
        0x0402, 0x0406, True, 60, 0x05)
    assert info.generation == 4 and ap.version_for(info) is ap.V4
    assert ap.encode_hand_info(info) == bytes.fromhex("02 04 06 04 00 3C 05")
    with pytest.raises(ValueError, match="v5"):
        ap.version_for(info, "v5")


def test_position_scale_v4_and_v5():
    assert ap.V4.rad_per_count == pytest.approx(8.88e-5, rel=1e-3)
    data = bytes.fromhex("0100 FFFF 0080 FF7F")  # 1, -1, -32768, 32767
    q = ap.decode_positions(data, ap.V4)
    assert np.allclose(q, np.array([1, -1, -32768, 32767]) * 333.3 / 65536 * math.pi / 180)
    assert ap.encode_positions(q, ap.V4) == data
    assert ap.decode_positions(bytes.fromhex("0A00 0000 0000 0000"), ap.V5)[0] == pytest.approx(math.radians(0.88))
    assert ap.encode_positions(np.array([100.0, -100.0, 0, 0])) == bytes.fromhex("FF7F 0080 0000 0000")


def test_torques_scaled_and_clamped_per_joint():
    # index finger: PWM limits [375, 675, 450, 285]; 0.1 -> 120 PWM
    payload = ap.encode_torques(np.array([0.1, 1.0, -1.0, np.nan]), finger=0)
    assert payload == (120).to_bytes(2, "little", signed=True) + (675).to_bytes(2, "little", signed=True) + \
        (-450).to_bytes(2, "little", signed=True) + bytes(2)
    thumb = ap.decode_torques(ap.encode_torques(np.full(4, 10.0), finger=3))
    assert np.allclose(thumb * 1200, [525, 405, 270, 270])
    v5 = ap.decode_torques(ap.encode_torques(np.array([0.1, 1.0, 0, 0]), 0, ap.V5), ap.V5)
    assert np.allclose(v5 * 1430, [143, 240, 0, 0])


def test_period_serial_temperature_and_v5_error():
    assert ap.encode_period(3, 0, 0) == bytes.fromhex("0300 0000 0000")
    assert ap.decode_period(bytes.fromhex("0300 0000 0000 0A00")) == (3, 0, 0)
    assert ap.decode_serial(b"SAH040E1") == "SAH040E1"
    assert ap.decode_serial(ap.encode_serial("AB")) == "AB"
    assert np.array_equal(ap.decode_temperatures(bytes([30, 31, 32, 255])), [30, 31, 32, 255])
    assert ap.decode_v5_error(bytes([3, 0x24])) == (3, 0x24, ["overheating", "overload"])
    for bad in (lambda: ap.decode_hand_info(b"\x00"), lambda: ap.decode_positions(b"\x00" * 7),
                lambda: ap.decode_period(b"\x00" * 5)):
        with pytest.raises(ValueError):
            bad()


@pytest.mark.parametrize("spec, expected", [
    ("socketcan:can0", ("socketcan", "can0")),
    ("pcan:PCAN_USBBUS1", ("pcan", "PCAN_USBBUS1")),
    ("slcan:/dev/ttyACM0", ("slcan", "/dev/ttyACM0")),
    ("virtual:x", ("virtual", "x")),
])
def test_parse_can_spec(spec, expected):
    assert parse_can_spec(spec) == expected


@pytest.mark.parametrize("spec, message", [("can0", "INTERFACE:CHANNEL"), ("kvaser:0", "unknown interface"),
                                           ("socketcan:", "empty channel")])
def test_parse_can_spec_errors(spec, message):
    with pytest.raises(ValueError, match=message):
        parse_can_spec(spec)


def test_open_virtual_bus():
    bus = open_bus("virtual:test-open")
    try:
        assert bus.channel_info
    finally:
        bus.shutdown()
