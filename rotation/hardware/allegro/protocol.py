"""Allegro Hand CAN protocol as data plus pure encode/decode functions (no I/O).

Source of every number: docs/reference/hardware.md section 1 ("Allegro Hand V4 (Wonik Robotics) over CAN" and
"Allegro Hand V5 differences"), which summarizes the vendor manual and drivers. Frames use standard 11-bit IDs,
``wire id = (message id << 2) | hand id``; requests are RTR frames with DLC 0 on the same ID; payloads are
little-endian.
"""

from __future__ import annotations

import math
import struct
from dataclasses import dataclass
from enum import IntEnum

import numpy as np

JOINTS_PER_FINGER = 4
NUM_FINGERS = 4


class Msg(IntEnum):
    """Message ids (before the ``<< 2 | hand_id`` shift). ``+ finger`` for the per-finger messages."""

    SYSTEM_ON = 0x40  # host -> hand, DLC 0: servo on
    SYSTEM_OFF = 0x41  # host -> hand, DLC 0: servo off
    SET_TORQUE = 0x60  # + finger (0..3), host -> hand, 8 B: 4 x int16 effort (V4 PWM, V5 mA)
    FINGER_POSE = 0x20  # + finger, RTR or periodic, 8 B: 4 x int16 position counts
    SET_PERIOD = 0x81  # host -> hand, 6 B: 3 x int16 ms {position, imu, temperature}; 0 stops a stream
    HAND_INFO = 0x80  # RTR -> 7 B: hw u16, fw u16, hand type u8, temperature u8, status u8
    SERIAL = 0x88  # RTR -> 8 ASCII chars
    IMU = 0x30  # RTR/periodic, 6 B: 3 x uint16 (unit undocumented)
    TEMPERATURE = 0x38  # + finger, RTR/periodic, 4 B: 4 x uint8 degrees C (one per joint)
    V5_ERROR = 0xEE  # V5 only, hand -> host, 2 B: motor id, error bits (V5_ERROR_BITS)


V5_ERROR_BITS = {0x01: "input voltage", 0x04: "overheating", 0x10: "electrical shock", 0x20: "overload"}
"""V5 error frame bits (docs/reference/hardware.md "Allegro Hand V5 differences")."""


STATUS_SERVO_ON = 0x01  # HAND_INFO status bit0
STATUS_TEMPERATURE_FAULT = 0x02  # bit1
STATUS_COMM_FAULT = 0x04  # bit2


@dataclass(frozen=True)
class ProtocolVersion:
    """What differs between hand generations: position scale and the effort command's unit and limits."""

    name: str
    rad_per_count: float
    """Joint position resolution (rad per int16 count)."""
    effort_per_torque: float
    """Effort counts per normalized torque unit (V4: PWM per unit, V5: mA per unit)."""
    effort_limits: tuple[int, ...]
    """(16,) per-joint |effort| limits in counts, applied before the int16 is written."""
    effort_unit: str


# V4: rad = count * (333.3 / 65536) * pi / 180; PWM = torque * 1200 (12 V supply, hw version byte 4);
# PWM limits fingers [roll 375, near 675, middle 450, far 285], thumb [525, 405, 270, 270].
V4 = ProtocolVersion(
    name="v4",
    rad_per_count=333.3 / 65536.0 * math.pi / 180.0,
    effort_per_torque=1200.0,
    effort_limits=(375, 675, 450, 285) * 3 + (525, 405, 270, 270),
    effort_unit="pwm",
)
# V5: 0.088 deg per count; current = torque * 1430 mA, clipped to +-240 mA (vendor driver).
V5 = ProtocolVersion(
    name="v5",
    rad_per_count=0.088 * math.pi / 180.0,
    effort_per_torque=1430.0,
    effort_limits=(240,) * 16,
    effort_unit="mA",
)
VERSIONS = {"v4": V4, "v5": V5}


def wire_id(msg: int, hand_id: int = 0, finger: int = 0) -> int:
    """11-bit CAN ID of message ``msg`` (+ ``finger`` for per-finger messages) for hand ``hand_id`` (0..3)."""
    if not 0 <= hand_id <= 3:
        raise ValueError(f"hand_id must be 0..3, got {hand_id}")
    if not 0 <= finger < NUM_FINGERS:
        raise ValueError(f"finger must be 0..3, got {finger}")
    return ((int(msg) + finger) << 2) | hand_id


def split_wire_id(arbitration_id: int) -> tuple[int, int]:
    """11-bit CAN ID -> (message id, hand id)."""
    return arbitration_id >> 2, arbitration_id & 0x3


def finger_of(msg_id: int, base: Msg) -> int | None:
    """Finger index if ``msg_id`` is ``base + finger`` for finger 0..3, else None."""
    f = msg_id - int(base)
    return f if 0 <= f < NUM_FINGERS else None


def encode_positions(q: np.ndarray, version: ProtocolVersion = V4) -> bytes:
    """4 joint angles (rad) -> FINGER_POSE payload (rounded, saturated to int16)."""
    counts = np.clip(np.round(np.asarray(q, dtype=np.float64) / version.rad_per_count), -32768, 32767)
    return struct.pack("<4h", *counts.astype(np.int64).tolist())


def decode_positions(data: bytes, version: ProtocolVersion = V4) -> np.ndarray:
    """FINGER_POSE payload (8 B) -> 4 joint angles (rad)."""
    if len(data) != 8:
        raise ValueError(f"FINGER_POSE payload must be 8 bytes, got {len(data)}")
    return np.array(struct.unpack("<4h", bytes(data)), dtype=np.float64) * version.rad_per_count


def encode_torques(torque: np.ndarray, finger: int, version: ProtocolVersion = V4) -> bytes:
    """4 normalized torques of ``finger`` -> SET_TORQUE payload: scaled to counts, clamped to the per-joint
    effort limits of that finger (the last line of defence after the safety layer), int16. NaN -> 0."""
    t = np.asarray(torque, dtype=np.float64)
    if t.shape != (JOINTS_PER_FINGER,):
        raise ValueError(f"encode_torques expects 4 values, got shape {t.shape}")
    limits = np.asarray(version.effort_limits[4 * finger: 4 * finger + 4], dtype=np.float64)
    counts = np.clip(np.round(np.nan_to_num(t, nan=0.0) * version.effort_per_torque), -limits, limits)
    return struct.pack("<4h", *counts.astype(np.int64).tolist())


def decode_torques(data: bytes, version: ProtocolVersion = V4) -> np.ndarray:
    """SET_TORQUE payload -> 4 normalized torques."""
    if len(data) != 8:
        raise ValueError(f"SET_TORQUE payload must be 8 bytes, got {len(data)}")
    return np.array(struct.unpack("<4h", bytes(data)), dtype=np.float64) / version.effort_per_torque


def encode_period(position_ms: int, imu_ms: int = 0, temperature_ms: int = 0) -> bytes:
    """SET_PERIOD payload: 3 x int16 stream periods (ms; 0 stops that stream)."""
    return struct.pack("<3h", position_ms, imu_ms, temperature_ms)


def decode_period(data: bytes) -> tuple[int, int, int]:
    """SET_PERIOD payload (6 B, or 8 B from drivers that add a status period) -> (position, imu, temperature) ms."""
    if len(data) not in (6, 8):
        raise ValueError(f"SET_PERIOD payload must be 6 or 8 bytes, got {len(data)}")
    return struct.unpack("<3h", bytes(data[:6]))


@dataclass(frozen=True)
class AllegroInfo:
    """Decoded HAND_INFO reply."""

    hardware: int
    firmware: int
    right_hand: bool
    temperature_c: int
    status: int

    @property
    def generation(self) -> int:
        """Hand generation from the high byte of the hardware version (4 for a V4: 0x0402)."""
        return self.hardware >> 8


def encode_hand_info(info: AllegroInfo) -> bytes:
    return struct.pack("<HHBBB", info.hardware, info.firmware, 0 if info.right_hand else 1,
                       info.temperature_c, info.status)


def decode_hand_info(data: bytes) -> AllegroInfo:
    """HAND_INFO payload (7 B) -> :class:`AllegroInfo`. A real trace: ``02 04 06 04 00 3C 05``."""
    if len(data) != 7:
        raise ValueError(f"HAND_INFO payload must be 7 bytes, got {len(data)}")
    hw, fw, hand_type, temp, status = struct.unpack("<HHBBB", bytes(data))
    return AllegroInfo(hardware=hw, firmware=fw, right_hand=hand_type == 0, temperature_c=temp, status=status)


def encode_serial(serial: str) -> bytes:
    raw = serial.encode("ascii")
    if len(raw) > 8:
        raise ValueError(f"SERIAL payload holds 8 ASCII characters, got {serial!r}")
    return raw.ljust(8, b"\x00")


def decode_serial(data: bytes) -> str:
    """SERIAL payload (8 ASCII chars) -> string (trailing NULs/spaces removed)."""
    return bytes(data).rstrip(b"\x00 ").decode("ascii", errors="replace")


def encode_temperatures(temps_c: np.ndarray) -> bytes:
    return struct.pack("<4B", *np.clip(np.round(temps_c), 0, 255).astype(np.int64).tolist())


def decode_temperatures(data: bytes) -> np.ndarray:
    """TEMPERATURE payload (4 x uint8 degrees C, one per joint of the finger) -> (4,) float."""
    if len(data) != 4:
        raise ValueError(f"TEMPERATURE payload must be 4 bytes, got {len(data)}")
    return np.array(struct.unpack("<4B", bytes(data)), dtype=np.float64)


def version_for(info: AllegroInfo, requested: str = "auto") -> ProtocolVersion:
    """Protocol for a hand: ``requested`` ('v4'/'v5') must agree with the HAND_INFO generation; 'auto' picks it."""
    detected = {4: "v4", 5: "v5"}.get(info.generation)
    if requested == "auto":
        if detected is None:
            raise ValueError(f"unknown Allegro generation in hw version 0x{info.hardware:04x}; "
                             "set the protocol explicitly (v4 or v5)")
        return VERSIONS[detected]
    if requested not in VERSIONS:
        raise ValueError(f"unknown Allegro protocol {requested!r}; choose auto, v4 or v5")
    if detected is not None and detected != requested:
        raise ValueError(f"protocol {requested!r} requested but the hand reports hw 0x{info.hardware:04x} "
                         f"({detected})")
    return VERSIONS[requested]


def decode_v5_error(data: bytes) -> tuple[int, int, list[str]]:
    """V5 error frame [motor id, bits] -> (motor id, bits, names of the set bits)."""
    if len(data) < 2:
        raise ValueError(f"V5 error payload must be at least 2 bytes, got {len(data)}")
    motor, bits = data[0], data[1]
    return motor, bits, [name for bit, name in V5_ERROR_BITS.items() if bits & bit]
