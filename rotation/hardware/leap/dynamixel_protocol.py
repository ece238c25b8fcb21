"""Dynamixel Protocol 2.0 as data and pure functions, and the XC330-M288 register table of the LEAP hand.

Sources: docs/reference/hardware.md section 3 (packet layout, CRC-16 polynomial 0x8005, byte stuffing, error byte,
sync/fast sync read layouts, test vectors) and section 2 (LEAP registers, units). The driver talks through the
unmodified ``dynamixel_sdk``; these functions serve the emulator and the parts the SDK leaves to its caller
(decoding a fast sync read reply with its per-servo error bytes, unit conversions).
"""

from __future__ import annotations

import math
import struct
from dataclasses import dataclass
from enum import IntEnum

HEADER = b"\xff\xff\xfd\x00"  # header FF FF FD + reserved 00
BROADCAST_ID = 0xFE
STATUS = 0x55  # instruction byte of a status packet


class Inst(IntEnum):
    PING = 0x01
    READ = 0x02
    WRITE = 0x03
    REG_WRITE = 0x04
    ACTION = 0x05
    FACTORY_RESET = 0x06
    REBOOT = 0x08
    CLEAR = 0x10
    SYNC_READ = 0x82
    SYNC_WRITE = 0x83
    FAST_SYNC_READ = 0x8A
    BULK_READ = 0x92
    BULK_WRITE = 0x93
    FAST_BULK_READ = 0x9A


ERROR_ALERT = 0x80
"""Error byte bit 7: the servo has a hardware error; read Hardware Error Status (70)."""
ERRORS = {1: "result fail", 2: "instruction error", 3: "CRC error", 4: "data range error", 5: "data length error",
          6: "data limit error", 7: "access error"}
"""Error byte bits 0-6 hold one error number (docs/reference/hardware.md section 3)."""
HARDWARE_ERRORS = {0x01: "input voltage", 0x04: "overheating", 0x08: "motor encoder", 0x10: "electrical shock",
                   0x20: "overload"}
"""Hardware Error Status (register 70) bits, X-series e-manual."""


def describe_error(error: int) -> str:
    """Error byte -> human-readable text ('' when 0)."""
    parts = []
    if error & 0x7F:
        parts.append(ERRORS.get(error & 0x7F, f"unknown error {error & 0x7F}"))
    if error & ERROR_ALERT:
        parts.append("hardware alert")
    return ", ".join(parts)


def describe_hardware_error(bits: int) -> str:
    return ", ".join(name for bit, name in HARDWARE_ERRORS.items() if bits & bit) or f"0x{bits:02x}"


@dataclass(frozen=True)
class Register:
    """One control-table entry: address, size in bytes, EEPROM (writable only with torque off), signedness."""

    addr: int
    size: int
    eeprom: bool = False
    signed: bool = False
    writable: bool = True


# XC330-M288 control table entries the LEAP hand uses (docs/reference/hardware.md section 2; ROBOTIS X-series e-manual).
REGISTERS: dict[str, Register] = {
    "model_number": Register(0, 2, eeprom=True, writable=False),
    "firmware_version": Register(6, 1, eeprom=True, writable=False),
    "id": Register(7, 1, eeprom=True),
    "baud_rate": Register(8, 1, eeprom=True),  # value 6 = 4,000,000 baud
    "return_delay_time": Register(9, 1, eeprom=True),  # 2 us units; 0 for ~500 Hz loops
    "operating_mode": Register(11, 1, eeprom=True),  # 5 = current-based position control
    "current_limit": Register(38, 2, eeprom=True),  # mA (1.0 mA/unit on XC330-M288); default 2352
    "torque_enable": Register(64, 1),
    "hardware_error_status": Register(70, 1, writable=False),
    "position_d_gain": Register(80, 2),
    "position_i_gain": Register(82, 2),
    "position_p_gain": Register(84, 2),
    "bus_watchdog": Register(98, 1),  # 20 ms units, 0 disables
    "goal_current": Register(102, 2, signed=True),  # mA
    "goal_position": Register(116, 4, signed=True),  # counts, 2 pi / 4096 rad
    "present_current": Register(126, 2, signed=True, writable=False),
    "present_velocity": Register(128, 4, signed=True, writable=False),  # 0.229 rpm
    "present_position": Register(132, 4, signed=True, writable=False),
    "present_input_voltage": Register(144, 2, writable=False),  # 0.1 V
    "present_temperature": Register(146, 1, writable=False),  # degrees C
}
EEPROM_END = 64
"""Addresses below this are EEPROM: the servo refuses writes there while torque is enabled (access error)."""

MODEL_XC330_M288 = 1240
OPERATING_MODE_CURRENT_POSITION = 5
BAUD_CODES = {57_600: 1, 115_200: 2, 1_000_000: 3, 2_000_000: 4, 3_000_000: 5, 4_000_000: 6}

STATE_ADDR = 126
"""One sync read covers present current (126, 2 B), velocity (128, 4 B) and position (132, 4 B)."""
STATE_LEN = 10

RAD_PER_COUNT = 2.0 * math.pi / 4096.0
RAD_S_PER_VELOCITY_UNIT = 0.229 * 2.0 * math.pi / 60.0  # 0.229 rpm per unit
AMP_PER_CURRENT_UNIT = 1e-3  # XC330-M288: 1.0 mA per unit
LEAP_OFFSET = math.pi
"""LEAP angle = Allegro angle + pi (docs/reference/hardware.md section 2); the open hand sits at count 2048."""


def allegro_to_counts(q_allegro: float) -> int:
    """Allegro-frame joint angle (rad) -> LEAP goal position (counts)."""
    return int(round((q_allegro + LEAP_OFFSET) / RAD_PER_COUNT))


def counts_to_allegro(counts: int) -> float:
    """LEAP present position (counts) -> Allegro-frame joint angle (rad)."""
    return counts * RAD_PER_COUNT - LEAP_OFFSET


def decode_state(data: bytes) -> tuple[float, float, float]:
    """10 bytes from address 126 -> (q rad Allegro frame, qdot rad/s, current A)."""
    if len(data) != STATE_LEN:
        raise ValueError(f"state block must be {STATE_LEN} bytes, got {len(data)}")
    current, velocity, position = struct.unpack("<hii", bytes(data))
    return counts_to_allegro(position), velocity * RAD_S_PER_VELOCITY_UNIT, current * AMP_PER_CURRENT_UNIT


def encode_value(value: int, size: int) -> bytes:
    """Little-endian register value of ``size`` bytes (negative values two's complement)."""
    return (value & ((1 << (8 * size)) - 1)).to_bytes(size, "little")


def decode_value(data: bytes, signed: bool = False) -> int:
    return int.from_bytes(bytes(data), "little", signed=signed)


def _crc_table() -> list[int]:
    table = []
    for i in range(256):
        crc = i << 8
        for _ in range(8):
            crc = ((crc << 1) ^ 0x8005) if crc & 0x8000 else (crc << 1)
        table.append(crc & 0xFFFF)
    return table


_CRC_TABLE = _crc_table()


def crc16(data: bytes) -> int:
    """CRC-16 (polynomial 0x8005, initial 0, MSB first) over the stuffed packet from the header on."""
    crc = 0
    for byte in data:
        crc = ((crc << 8) ^ _CRC_TABLE[((crc >> 8) ^ byte) & 0xFF]) & 0xFFFF
    return crc


def stuff(body: bytes) -> bytes:
    """Byte stuffing of INST..params: every ``FF FF FD`` gets an extra ``FD``."""
    out = bytearray()
    for b in body:
        out.append(b)
        if b == 0xFD and len(out) >= 3 and out[-3] == 0xFF and out[-2] == 0xFF:
            out.append(0xFD)
    return bytes(out)


def unstuff(body: bytes) -> bytes:
    """Inverse of :func:`stuff`: drop the ``FD`` that follows each ``FF FF FD``."""
    out = bytearray()
    i = 0
    while i < len(body):
        out.append(body[i])
        if body[i] == 0xFD and len(out) >= 3 and out[-3] == 0xFF and out[-2] == 0xFF:
            i += 1  # skip the stuffing byte
        i += 1
    return bytes(out)


def build_packet(dxl_id: int, inst: int, params: bytes = b"") -> bytes:
    """Instruction (or, with ``inst=STATUS``, status) packet with stuffing and CRC; LEN counts the stuffed bytes."""
    body = stuff(bytes([inst]) + bytes(params))
    head = HEADER + bytes([dxl_id]) + struct.pack("<H", len(body) + 2)
    packet = head + body
    return packet + struct.pack("<H", crc16(packet))


def build_status(dxl_id: int, error: int, params: bytes = b"") -> bytes:
    """Status packet: INST 0x55, error byte, params."""
    return build_packet(dxl_id, STATUS, bytes([error]) + bytes(params))


@dataclass(frozen=True)
class Packet:
    dxl_id: int
    inst: int
    params: bytes
    """Unstuffed parameters (for a status packet: the error byte first)."""
    crc_ok: bool


def parse_packet(buf: bytes) -> tuple[Packet | None, int]:
    """Find the first packet in ``buf``: (packet or None if incomplete, number of bytes consumed).

    Bytes before a header are consumed as garbage; a packet with a bad CRC is returned with ``crc_ok=False``.
    """
    start = buf.find(HEADER)
    if start < 0:
        keep = max(0, len(buf) - 3)  # a header may be split across reads
        return None, keep
    if len(buf) - start < 7:
        return None, start
    length = struct.unpack_from("<H", buf, start + 5)[0]
    end = start + 7 + length
    if length < 3:
        return None, start + 4  # malformed: skip this header
    if len(buf) < end:
        return None, start
    packet = bytes(buf[start:end])
    crc_ok = crc16(packet[:-2]) == struct.unpack_from("<H", packet, len(packet) - 2)[0]
    body = unstuff(packet[7:-2])
    return Packet(dxl_id=packet[4], inst=body[0], params=body[1:], crc_ok=crc_ok), end


def build_fast_sync_status(blocks: list[tuple[int, int, bytes]]) -> bytes:
    """Fast sync read reply: one status packet from ID 0xFE holding ``[err, id, data, crc(2)]`` per servo,
    where the last block's CRC is the packet CRC (the layout the SDK slices: (len + 4) bytes per servo).

    The SDK never checks the inner block CRCs and docs/reference/hardware.md does not define them; this emulator
    writes the CRC-16 of the block's own ``[err, id, data]`` bytes there.
    """
    raw = bytearray([STATUS])
    for k, (err, dxl_id, data) in enumerate(blocks):
        block = bytes([err, dxl_id]) + bytes(data)
        raw += block
        if k < len(blocks) - 1:
            raw += struct.pack("<H", crc16(block))
    return build_packet(BROADCAST_ID, raw[0], bytes(raw[1:]))


def parse_fast_sync_status(packet: bytes | list[int], ids: list[int], length: int) -> dict[int, tuple[int, bytes]]:
    """Decode a raw fast sync read reply (as returned by the SDK's ``rxPacket(port, True)``, still stuffed)
    into ``{id: (error byte, data)}``. Raises ValueError if the layout or the IDs do not match the request."""
    raw = bytes(packet)
    if len(raw) < 11 or raw[:4] != HEADER or raw[4] != BROADCAST_ID:
        raise ValueError("not a fast sync read reply")
    body = unstuff(raw[7:-2])
    if body[0] != STATUS:
        raise ValueError(f"not a status packet (instruction 0x{body[0]:02x})")
    blocks = body[1:] + raw[-2:]  # the last block's CRC is the packet CRC
    step = length + 4
    if len(blocks) != step * len(ids):
        raise ValueError(f"fast sync read reply holds {len(blocks)} bytes, expected {step * len(ids)}")
    out: dict[int, tuple[int, bytes]] = {}
    for k, expected in enumerate(ids):
        err, dxl_id = blocks[k * step], blocks[k * step + 1]
        if dxl_id != expected:
            raise ValueError(f"fast sync read block {k}: id {dxl_id}, expected {expected}")
        out[dxl_id] = (err, bytes(blocks[k * step + 2: k * step + 2 + length]))
    return out
