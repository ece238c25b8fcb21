"""Dynamixel Protocol 2.0 byte-exact against the reference test vectors (docs/reference/hardware.md section 3)."""

from __future__ import annotations

import math

import pytest

from rotation.hardware.leap import dynamixel_protocol as dp


def test_crc_test_vectors():
    assert dp.crc16(bytes.fromhex("FFFFFD00 01 0300 01")).to_bytes(2, "little") == bytes.fromhex("194E")
    status = bytes.fromhex("FFFFFD00 01 0800 55 00 A6000000")
    assert dp.crc16(status).to_bytes(2, "little") == bytes.fromhex("8CC0")


def test_packets_match_reference_examples():
    assert dp.build_packet(1, dp.Inst.PING) == bytes.fromhex("FFFFFD00 01 0300 01 194E")
    assert dp.build_status(1, 0, bytes.fromhex("A6000000")) == bytes.fromhex("FFFFFD00 01 0800 55 00 A6000000 8CC0")
    sync_read = dp.build_packet(dp.BROADCAST_ID, dp.Inst.SYNC_READ, bytes([0x84, 0, 4, 0, 1, 2]))
    assert sync_read == bytes.fromhex("FF FF FD 00 FE 09 00 82 84 00 04 00 01 02 CE FA")
    sync_write = dp.build_packet(dp.BROADCAST_ID, dp.Inst.SYNC_WRITE,
                                 bytes([0x74, 0, 4, 0, 1, 0x96, 0, 0, 0, 2, 0xAA, 0, 0, 0]))
    assert sync_write == bytes.fromhex("FF FF FD 00 FE 11 00 83 74 00 04 00 01 96 00 00 00 02 AA 00 00 00 82 87")


def test_byte_stuffing_round_trip_and_length():
    params = bytes([0xFF, 0xFF, 0xFD, 0x01])
    assert dp.stuff(params) == bytes([0xFF, 0xFF, 0xFD, 0xFD, 0x01])
    assert dp.unstuff(dp.stuff(params)) == params
    packet = dp.build_packet(3, dp.Inst.WRITE, params)
    assert packet[5] == 1 + 5 + 2  # LEN counts the stuffed bytes: inst + 5 + crc
    parsed, used = dp.parse_packet(b"\x00\x12" + packet + b"\xff")
    assert parsed == dp.Packet(3, dp.Inst.WRITE, params, True) and used == 2 + len(packet)


def test_parse_packet_incomplete_and_bad_crc():
    packet = dp.build_packet(1, dp.Inst.PING)
    assert dp.parse_packet(packet[:6]) == (None, 0)
    bad = packet[:-1] + bytes([packet[-1] ^ 1])
    parsed, _ = dp.parse_packet(bad)
    assert parsed is not None and not parsed.crc_ok


def test_fast_sync_status_round_trip_with_stuffing():
    # current -1 (FF FF) then velocity -3 (FD FF FF FF): the bytes FF FF FD appear and get stuffed
    data1 = dp.encode_value(-1, 2) + dp.encode_value(-3, 4) + dp.encode_value(2048, 4)
    data2 = dp.encode_value(5, 2) + dp.encode_value(0, 4) + dp.encode_value(1000, 4)
    packet = dp.build_fast_sync_status([(0, 1, data1), (0x80, 2, data2)])
    out = dp.parse_fast_sync_status(packet, [1, 2], 10)
    assert out == {1: (0, data1), 2: (0x80, data2)}
    with pytest.raises(ValueError, match="id 1, expected 2"):
        dp.parse_fast_sync_status(packet, [2, 1], 10)


def test_units_and_errors():
    assert dp.counts_to_allegro(2048) == pytest.approx(0.0)
    assert dp.allegro_to_counts(0.0) == 2048
    assert dp.allegro_to_counts(math.pi / 2) == 3072
    q, qdot, amps = dp.decode_state(dp.encode_value(-100, 2) + dp.encode_value(10, 4) + dp.encode_value(3072, 4))
    assert q == pytest.approx(math.pi / 2) and qdot == pytest.approx(10 * 0.229 * 2 * math.pi / 60)
    assert amps == pytest.approx(-0.1)
    assert dp.describe_error(0x83) == "CRC error, hardware alert"
    assert dp.describe_hardware_error(0x24) == "overheating, overload"
    assert dp.REGISTERS["present_current"].addr == dp.STATE_ADDR and dp.STATE_LEN == 2 + 4 + 4
