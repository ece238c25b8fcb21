"""The Digit 360 data channel's messages (``digit360.proto``, the device's wire schema), their units, and the host's
commands.

Framing (docs/reference/digit360_protocol.md): device -> host frames are a protobuf ``Digit360Message``,
COBS-encoded, ended by 0x00; host -> device commands are the plain protobuf bytes. A ``Digit360Message`` carries one
member of its oneof ``type``; a member this schema does not know (a newer firmware's) parses into a message with no
member set, which the reader counts and skips.

Units. Meta publishes none; what this host assumes, each with its reason:

- device time ``ts`` (uint32): milliseconds (both official rate counters divide its differences by 1e3 to get
  seconds; inference); ``TS_HZ``;
- raw IMU ``x, y, z`` (floats): the IMU hub's LSB counts, as Bosch's BHY2 host code scales its virtual sensors:
  accelerometer and linear acceleration 4096 LSB per g, gyroscope 32768 LSB per 2000 deg/s (the hub is a Bosch
  BHI360; Sparsh-X reads the acceleration divided by 4096; not confirmed for this firmware); ``ACC_LSB_PER_G``,
  ``GYRO_LSB_PER_DPS``;
- pressure (float): hPa when it is about 1000 at rest (Sparsh-X: "absolute, about 1000 hPa at rest"); a value above
  ``PA_THRESHOLD`` is taken as pascals and divided by 100 (the fingertip's barometer, a Bosch BMP585, reports
  pascals); ``pressure_hpa``;
- temperature: degrees C.
"""

from __future__ import annotations

from functools import cache
from pathlib import Path

from rotation.hardware.digit360.proto_schema import enum_values, load_proto

PROTO = str(Path(__file__).with_name("digit360.proto"))
TS_HZ = 1000.0
"""Ticks per second of the device's ``ts`` fields (milliseconds)."""
ACC_LSB_PER_G = 4096.0
"""Raw accelerometer (and linear acceleration) LSB per g."""
GYRO_LSB_PER_DPS = 32768.0 / 2000.0
"""Raw gyroscope LSB per deg/s."""
PA_THRESHOLD = 20000.0
"""A pressure reading above this is in pascals (no atmosphere on Earth is 20,000 hPa; sea level is 101,325 Pa)."""
BOOTLOADER_MAJOR = 0xFF
"""``SystemData.version_major`` that sends the device into its firmware bootloader (Meta's programmer tool)."""
IDENT_STATUS = 0xF7
"""``SystemData.status`` of the "ident" command (Meta's ident tool)."""


@cache
def messages() -> dict[str, type]:
    """The Digit 360 protobuf classes, built from ``digit360.proto``."""
    return load_proto(PROTO)


IMU_TYPE = enum_values(PROTO, "ImuDataType")
"""ImuDataType name -> number (ACC 1, GYRO 2, MAG 3, AUX_IMU 6: linear acceleration, ...)."""
RESET_TYPE = enum_values(PROTO, "ResetType")
LIGHTING_CHANNEL = enum_values(PROTO, "LightingChannel")


def pressure_hpa(value: float) -> float:
    """The device's pressure reading in hPa (see the module docstring)."""
    return value / 100.0 if value > PA_THRESHOLD else value


def raw_imu_physical(sensor: int, x: float, y: float, z: float) -> tuple[str, tuple[float, float, float]]:
    """A raw IMU sample -> (unit, values): g for the accelerometer and linear acceleration, deg/s for the gyroscope,
    the device's counts otherwise (the magnetometer's scale is not published)."""
    if sensor in (IMU_TYPE["ACC"], IMU_TYPE["AUX_IMU"]):
        return "g", (x / ACC_LSB_PER_G, y / ACC_LSB_PER_G, z / ACC_LSB_PER_G)
    if sensor == IMU_TYPE["GYRO"]:
        return "deg/s", (x / GYRO_LSB_PER_DPS, y / GYRO_LSB_PER_DPS, z / GYRO_LSB_PER_DPS)
    return "counts", (x, y, z)


class UnsafeCommand(ValueError):
    """A host -> device message that would put the device into a bootloader or is not a command."""


def command_bytes(msg) -> bytes:
    """The wire bytes of a host -> device command (plain protobuf), refused if it would enter a bootloader:
    ``version_major = 0xFF`` or a bootloader reset. Only system, pressure-control and lighting messages are
    commands."""
    kind = msg.WhichOneof("type")
    if kind not in ("system_data", "pressure_control", "lighting_control"):
        raise UnsafeCommand(f"digit360: {kind or 'an empty message'} is not a host command")
    if kind == "system_data":
        s = msg.system_data
        if s.version_major == BOOTLOADER_MAJOR:
            raise UnsafeCommand("digit360: version_major 0xFF would put the sensor into its firmware bootloader; "
                                "this host never sends it (use Meta's programmer tool to flash firmware)")
        if s.reset in (RESET_TYPE["ICS_BOOTLOADER"], RESET_TYPE["MCU_BOOTLOADER"]):
            raise UnsafeCommand("digit360: a bootloader reset is not sent by this host")
    return msg.SerializeToString()
