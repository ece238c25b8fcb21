"""The Digit 360 wire schema, byte by byte.

Every frame here is built by hand from the published field numbers and wire types of the device's messages
(docs/reference/digit360_protocol.md: the bindings Meta's host code uses, which firmware v1.22's
nanopb field table matches), not by this project's encoder: varints, little-endian 32-bit floats and
length-delimited submessages, COBS-encoded and ended by 0x00 as the device sends them.
"""

from __future__ import annotations

import struct

import numpy as np
import pytest
from cobs import cobs

from rotation.hardware.digit360 import protocol
from rotation.hardware.digit360.reader import Digit360, Digit360Config


def varint(n: int) -> bytes:
    out = bytearray()
    while True:
        b, n = n & 0x7F, n >> 7
        out.append(b | (0x80 if n else 0))
        if not n:
            return bytes(out)


def vfield(number: int, value: int) -> bytes:
    """A varint field (wire type 0)."""
    return varint(number << 3 | 0) + varint(value)


def ffield(number: int, value: float) -> bytes:
    """A float field (wire type 5: fixed 32 bits, little-endian)."""
    return varint(number << 3 | 5) + struct.pack("<f", value)


def lfield(number: int, payload: bytes) -> bytes:
    """A length-delimited field (wire type 2): a submessage or bytes."""
    return varint(number << 3 | 2) + varint(len(payload)) + payload


def frame(message: bytes) -> bytes:
    """What the device writes: the Digit360Message COBS-encoded, then 0x00."""
    return cobs.encode(message) + b"\x00"


@pytest.fixture
def reader():
    """A reader that is never entered (no port opened, no thread): frames are handed to it directly."""
    return Digit360(Digit360Config(port="bytes"))


def feed(reader: Digit360, data: bytes, t: float = 100.0) -> None:
    for chunk in data.split(b"\x00"):
        if chunk:
            reader._on_frame(chunk, t)


def raw_imu(sensor: int, x: float, y: float, z: float, ts: int = 1234, ts_ght: int = 987654321) -> bytes:
    raw = vfield(1, sensor) + vfield(2, ts_ght) + ffield(3, x) + ffield(4, y) + ffield(5, z)  # RawImuData
    return lfield(5, vfield(1, ts) + lfield(2, raw))  # Digit360Message.imu_data (5) = ImuData{ts 1, raw 2}


def test_a_raw_accelerometer_frame_decodes_all_three_axes_in_g(reader):
    """The device sends ts first and floats on fields 3-5: all three axes arrive (an integer schema on other field
    numbers decoded the same bytes into the timestamp on x and zeros on y and z)."""
    feed(reader, frame(raw_imu(1, 409.6, -819.2, 4096.0)))
    t, v = reader.imu.snapshot()
    assert len(v) == 1 and np.allclose(v[0], (0.1, -0.2, 1.0), atol=1e-6)
    assert reader.latest["imu/acc"][1] == {"g": pytest.approx((0.1, -0.2, 1.0))}
    msg = protocol.messages()["Digit360Message"].FromString(raw_imu(1, 1.0, 2.0, 3.0))
    assert msg.imu_data.raw.ts_ght == 987654321 and msg.imu_data.ts == 1234


def test_gyro_linear_acceleration_and_magnetometer_are_decoded_but_do_not_feed_the_window(reader):
    feed(reader, frame(raw_imu(2, 16.384, -32.768, 0.0)) + frame(raw_imu(6, 40.96, 0.0, -4096.0))
         + frame(raw_imu(3, 12.0, 13.0, 14.0)))
    assert reader.imu.written == 0  # the window's IMU is the accelerometer, as the simulated sensor's
    assert reader.latest["imu/gyro"][1]["deg/s"] == pytest.approx((1.0, -2.0, 0.0))
    assert reader.latest["imu/linacc"][1]["g"] == pytest.approx((0.01, 0.0, -1.0))
    assert reader.latest["imu/mag"][1]["counts"] == pytest.approx((12.0, 13.0, 14.0))


def test_the_linear_acceleration_channel_feeds_the_window_when_asked():
    """imu_channel='linacc' (Meta's released Sparsh-X was pretrained on it): the windows take raw IMU type 6, gravity
    removed, and no longer the accelerometer."""
    reader = Digit360(Digit360Config(port="bytes", imu_channel="linacc"))
    feed(reader, frame(raw_imu(1, 0.0, 0.0, 4096.0)) + frame(raw_imu(6, 40.96, 0.0, -81.92)))
    _, v = reader.imu.snapshot()
    assert len(v) == 1 and np.allclose(v[0], (0.01, 0.0, -0.02), atol=1e-6)
    assert reader.latest["imu/acc"][1]["g"] == pytest.approx((0.0, 0.0, 1.0))  # still decoded, not windowed
    with pytest.raises(ValueError, match="imu_channel"):
        Digit360Config(port="bytes", imu_channel="gravity")


def test_fused_orientation_frames(reader):
    euler = lfield(5, vfield(1, 10) + lfield(3, vfield(1, 5) + ffield(2, 90.0) + ffield(3, -10.0) + ffield(4, 2.5)))
    quat = lfield(5, vfield(1, 11) + lfield(4, vfield(1, 6) + ffield(2, 0.0) + ffield(3, 0.0) + ffield(4, 0.6)
                                      + ffield(5, 0.8) + ffield(6, 3.0)))
    feed(reader, frame(euler) + frame(quat))
    assert reader.latest["euler"][1]["deg"] == pytest.approx((90.0, -10.0, 2.5))
    assert reader.latest["quat"][1]["wxyz"] == pytest.approx((0.8, 0.0, 0.0, 0.6))
    assert reader.latest["quat"][1]["accuracy"] == pytest.approx(3.0)


def test_pressure_in_hpa_or_pascals_and_the_gas_sensor(reader):
    feed(reader, frame(lfield(2, vfield(1, 50) + ffield(2, 1013.25) + ffield(3, 31.5))))
    feed(reader, frame(lfield(2, vfield(1, 55) + ffield(2, 101400.0) + ffield(3, 31.5))))  # pascals
    _, p = reader.pressure.snapshot()
    assert np.allclose(p[:, 0], (1013.25, 1014.0), atol=1e-3)
    assert reader.latest["pressure"][1]["temperature_C"] == pytest.approx(31.5)
    gas = vfield(2, 60) + vfield(3, 123456) + ffield(4, 29.0) + ffield(5, 1002.0) + ffield(6, 41.0) \
        + ffield(7, 5000.0) + ffield(8, 25.0)  # GasHtData: field 1 unused
    feed(reader, frame(lfield(4, gas)))
    assert reader.latest["gasht"][1] == pytest.approx({"temperature_C": 29.0, "hPa": 1002.0, "humidity": 41.0,
                                                       "gas": 5000.0, "gas_index": 25.0})


def test_high_rate_pressure_channels_are_little_endian_uint16(reader):
    a, b = np.array([1, 2, 65535], "<u2"), np.array([300, 400], "<u2")
    feed(reader, frame(lfield(3, vfield(1, 70) + lfield(2, a.tobytes()) + lfield(3, b.tobytes()))))
    got = reader.latest["pressure_ap"][1]
    assert np.array_equal(got["channel_a"], a) and np.array_equal(got["channel_b"], b)


def test_system_status_unknown_types_and_broken_frames(reader):
    feed(reader, frame(lfield(1, vfield(1, 22) + vfield(2, 1) + vfield(3, 5))))
    assert reader.version == "1.22" and reader.latest["system"][1]["status"] == 5
    feed(reader, frame(lfield(9, vfield(1, 3))))  # a message type of a newer firmware: skipped, counted
    assert reader.counters["unknown"] == 1 and reader.counters["bad_frames"] == 0
    feed(reader, frame(raw_imu(1, 1.0, 2.0, 3.0)[:-3]))  # truncated protobuf
    feed(reader, b"\x05\x01\x02\x00")  # a COBS code pointing past the end
    assert reader.counters["bad_frames"] == 2 and reader.imu.written == 0


def test_commands_never_enter_a_bootloader():
    msg = protocol.messages()["Digit360Message"]
    ident = msg()
    ident.system_data.status = protocol.IDENT_STATUS
    assert protocol.command_bytes(ident) == lfield(1, vfield(3, 0xF7))  # plain protobuf, no COBS
    led = msg()
    led.lighting_control.alpha, led.lighting_control.channel = 255.0, protocol.LIGHTING_CHANNEL["CHANNEL_ALL"]
    led.lighting_control.r = 15
    assert protocol.command_bytes(led) == lfield(7, ffield(1, 255.0) + vfield(2, 9) + vfield(3, 15))
    boot = msg()
    boot.system_data.version_major = 0xFF
    with pytest.raises(protocol.UnsafeCommand, match="bootloader"):
        protocol.command_bytes(boot)
    for reset in ("ICS_BOOTLOADER", "MCU_BOOTLOADER"):
        m = msg()
        m.system_data.reset = protocol.RESET_TYPE[reset]
        with pytest.raises(protocol.UnsafeCommand, match="bootloader"):
            protocol.command_bytes(m)
    data = msg()
    data.imu_data.ts = 1
    with pytest.raises(protocol.UnsafeCommand, match="not a host command"):
        protocol.command_bytes(data)


def _stream(reader: Digit360, ts_ght_of, seconds: float = 2.0, hz: float = 400.0) -> None:
    """Raw accelerometer frames at ``hz`` for ``seconds``, each arriving 2 ms after it was sampled: ``ts`` the
    device's whole milliseconds (as it sends them), ``ts_ght`` = ts_ght_of(true time in s)."""
    for k in range(int(seconds * hz)):
        t = 5.0 + k / hz
        feed(reader, frame(raw_imu(1, 0.0, 0.0, 4096.0, ts=int(t * 1000.0), ts_ght=ts_ght_of(t))), t=95.0 + t + 0.002)


def test_sensor_time_stamps_that_prove_a_finer_clock_time_the_imu_samples():
    """At 400 Hz the device's millisecond ``ts`` rounds each sample by up to 0.5 ms; a ``ts_ght`` that counts a finer
    clock in step with it (here 15.625 us ticks, Bosch's, from an arbitrary start) times them to the microsecond
    once enough samples prove it; one that counts samples (the emulator's) or is noise is not used."""
    runs = {"fine": lambda t: 123_456_789 + round(t * 64_000.0), "samples": lambda t: round(t * 400.0),
            "noise": lambda t: int(np.random.default_rng(round(t * 400)).integers(0, 1 << 40))}
    spacing = {}
    for name, ts_ght_of in runs.items():
        r = Digit360(Digit360Config(port="bytes"))
        _stream(r, ts_ght_of)
        t, _ = r.imu.snapshot()
        spacing[name] = np.diff(t[-200:]) * 1e3  # ms, the last half second
        assert r._fine.active == (name == "fine")
        assert (r._fine.ticks_per_ms is None) == (name != "fine")
        if name == "fine":
            assert r._fine.ticks_per_ms == pytest.approx(64.0, rel=1e-3)  # what `rotate touch-info` reports
    assert np.allclose(spacing["fine"], 2.5, atol=1e-3)  # within a microsecond
    for name in ("samples", "noise"):  # whole milliseconds: 2 or 3 ms apart
        assert set(np.round(spacing[name], 2)) == {2.0, 3.0}
