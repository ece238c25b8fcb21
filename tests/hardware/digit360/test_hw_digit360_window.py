"""Digit 360 buffers, Sparsh-X windows, the run-time protobuf schema and the device clock mapping."""

from __future__ import annotations

import numpy as np
import pytest

from rotation.hardware.digit360 import window as dw
from rotation.hardware.digit360.capture import SampleClock
from rotation.hardware.digit360.proto_schema import parse_proto
from rotation.hardware.digit360.protocol import IMU_TYPE, PROTO, messages
from rotation.hardware.digit360.reader import Digit360Config, _ClockMap


def test_ring_buffer_wraps_in_time_order():
    buf = dw.RingBuffer(4, (1,))
    for k in range(6):
        buf.append(float(k), k * 10.0)
    t, v = buf.snapshot()
    assert t.tolist() == [2, 3, 4, 5] and v.ravel().tolist() == [20, 30, 40, 50]
    assert buf.newest_time() == 5.0 and len(buf) == 4


def test_ring_buffer_append_stores_what_extend_stores_and_refuses_a_sample_of_another_size():
    """append is extend for one sample, without extend's array building (a reader appends every frame)."""
    one, many = dw.RingBuffer(3, (3,)), dw.RingBuffer(3, (3,))
    samples = [np.array([k, -k, 0.5 * k]) / 3.0 for k in range(5)]
    for k, x in enumerate(samples):
        one.append(k * 0.0025, x)
    many.extend(np.arange(5) * 0.0025, np.stack(samples))
    for a, b in zip(one.snapshot(), many.snapshot(), strict=True):
        assert np.array_equal(a, b)
    assert one.written == 5 and one.v.dtype == np.float32
    with pytest.raises(ValueError, match=r"a sample of 1 value\(s\); this buffer holds samples of shape \(3,\)"):
        one.append(1.0, 5.0)  # would broadcast to all three axes
    assert one.written == 5


def test_ring_buffer_copies_only_what_is_asked_for():
    buf = dw.RingBuffer(4, (1,))
    for k in range(6):
        buf.append(float(k), k * 10.0)
    t, v = buf.since(3.0)  # what a recording drain takes: the samples after its last one
    assert t.tolist() == [4, 5] and v.ravel().tolist() == [40, 50]
    assert buf.since(5.0)[0].size == 0 and buf.since(-1.0)[0].tolist() == [2, 3, 4, 5]
    # a drain passes the count written when it last began: only the samples written after it are looked at
    assert buf.written == 6 and buf.since(-1.0, written=4)[0].tolist() == [4, 5]
    assert buf.since(4.0, written=4)[0].tolist() == [5] and buf.since(-1.0, written=6)[0].size == 0
    assert buf.since(-1.0, written=1)[0].tolist() == [2, 3, 4, 5]  # overwritten samples are gone, not repeated
    t, v = buf.last(2)  # what an image window takes: the newest frames
    assert t.tolist() == [4, 5] and v.ravel().tolist() == [40, 50]
    assert buf.last(9)[0].tolist() == [2, 3, 4, 5] and dw.RingBuffer(3, (1,)).last(2)[0].size == 0


def test_audio_blocks_get_consecutive_sample_times_despite_callback_jitter():
    """A sound card's callbacks arrive with jitter; timed from each arrival, a block could overlap the one before
    and a recording would drop the overlap. The sample clock counts samples, and moves its anchor only for lost
    samples or clock drift beyond 20 ms, never back past the previous sample."""
    clock = SampleClock(48_000.0)
    rng = np.random.default_rng(0)
    times, arrival = [], 0.0
    for _ in range(200):  # 480-sample blocks, arrival jittered by up to +-4 ms
        arrival += 0.01
        times.append(clock(480, arrival + rng.uniform(-0.004, 0.004)))
    t = np.concatenate(times)
    np.testing.assert_allclose(np.diff(t), 1 / 48_000.0, rtol=0, atol=1e-9)  # one sample apart throughout
    assert abs(t[-1] - arrival) < 0.02
    # 100 ms of samples lost (an overflow): the next block is timed from its arrival
    after_gap = clock(480, arrival + 0.11)
    assert after_gap[0] - t[-1] == pytest.approx(0.1, abs=5e-3)  # the anchor had up to 4 ms of jitter
    # a card clock running ahead of the host: re-anchored back, but never before the previous sample
    ahead = clock(480, after_gap[-1] - 0.05 + 0.01)
    assert ahead[0] > after_gap[-1] and ahead[0] - after_gap[-1] < 1 / 48_000.0


def test_series_window_linear_no_future_samples():
    buf = dw.RingBuffer(2000, (1,))
    t = np.arange(0, 2.0, 0.01)  # 100 Hz ramp v = t
    buf.extend(t, t[:, None])
    buf.append(10.0, 1e6)  # a sample after t_end must not leak in
    out = dw.series_window(buf, t_end=1.5, rate=200.0)
    grid = 1.5 - (223 - np.arange(224)) / 200.0
    assert out.shape == (224, 1) and out.dtype == np.float32
    assert np.allclose(out[:, 0], grid, atol=1e-5)
    # t_end between samples and after the newest sample <= t_end: hold, never extrapolate
    out = dw.series_window(buf, t_end=1.995, rate=200.0)
    assert out[-1, 0] == pytest.approx(1.99)


def test_series_window_not_ready():
    buf = dw.RingBuffer(100, (3,))
    buf.extend(np.array([0.0, 0.1]), np.zeros((2, 3)))
    with pytest.raises(dw.WindowNotReady, match="imu"):
        dw.series_window(buf, 0.1, dw.IMU_RATE, name="imu")


def test_audio_window_ends_at_t_end():
    buf = dw.RingBuffer(60_000, (2,), np.int16)
    n = 50_000
    t = np.arange(n) / 48_000
    v = np.stack([np.arange(n) % 30000, -(np.arange(n) % 30000)], axis=1).astype(np.int16)
    buf.extend(t, v)
    out = dw.audio_window(buf, t_end=t[40_000] + 1e-6)
    assert out.shape == (2, 27_000) and out.dtype == np.int16
    assert out[0, -1] == 40_000 % 30000 and out[1, 0] == -((40_001 - 27_000) % 30000)


def test_image_window_channel_major_order():
    buf = dw.RingBuffer(12, (2, 2, 3), np.uint8)
    for k in range(8):  # frame k: R = k, G = 10 + k, B = 20 + k
        buf.append(k / 30, np.stack([np.full((2, 2), c + k) for c in (0, 10, 20)], axis=-1).astype(np.uint8))
    img, t = dw.image_window(buf)
    assert t == pytest.approx(7 / 30)
    assert img[:, 0, 0].tolist() == [2, 7, 12, 17, 22, 27]  # [R(t-5), R(t), G(t-5), G(t), B(t-5), B(t)]


def test_sparshx_window_without_camera_ends_at_oldest_newest_sample():
    imu, pressure = dw.RingBuffer(1000, (3,)), dw.RingBuffer(1000, (1,))
    ti, tp = np.arange(0, 1.5, 1 / 400), np.arange(0, 1.49, 1 / 200)
    imu.extend(ti, np.ones((len(ti), 3)))
    pressure.extend(tp, np.full((len(tp), 1), 1000.0))
    out = dw.sparshx_window(None, None, imu, pressure)
    assert out["t_end"] == pytest.approx(tp[-1])
    assert out["imu"].shape == (224, 3) and out["pressure"].shape == (224, 1)


def test_schema_round_trip_and_parser_errors():
    msg = messages()["Digit360Message"]()
    msg.imu_data.ts = 7
    msg.imu_data.raw.sensor = IMU_TYPE["ACC"]
    msg.imu_data.raw.z = 4096.0
    again = messages()["Digit360Message"].FromString(msg.SerializeToString())
    assert again.WhichOneof("type") == "imu_data" and again.imu_data.raw.z == 4096.0
    with open(PROTO) as f:
        fdp = parse_proto(f.read())
    assert [o.name for m in fdp.message_type for o in m.oneof_decl] == ["imu_type", "type"]
    with pytest.raises(ValueError, match="unsupported"):
        parse_proto('syntax = "proto3";\nmessage A { map<string, int32> m = 1; }\n')
    with pytest.raises(ValueError, match="unknown type"):
        parse_proto('syntax = "proto3";\nmessage A {\n  Missing m = 1;\n}\n')


def test_clock_map_takes_the_least_delayed_offset_and_never_the_future():
    clock = _ClockMap(1e6)
    assert clock(1_000_000, 10.5) == pytest.approx(10.5)  # first sample: offset 9.5
    assert clock(1_010_000, 10.54) == pytest.approx(10.51, abs=1e-4)  # 30 ms late: device time wins
    assert clock(1_020_000, 10.52) == pytest.approx(10.52)  # a faster arrival lowers the offset
    assert clock(1_030_000, 10.529) <= 10.529


def test_digit_config_needs_a_device():
    with pytest.raises(ValueError, match="serial_number"):
        Digit360Config()


def test_clock_map_reanchors_after_a_device_clock_pause():
    clock = _ClockMap(1e6)
    clock(1_000_000, 10.0)
    assert clock(1_002_500, 10.5) == pytest.approx(10.5)  # 0.5 s late: not USB latency, re-anchored


def test_discovery_by_usb_serial(monkeypatch):
    from types import SimpleNamespace

    from rotation.hardware.digit360 import discovery

    ports = [SimpleNamespace(device="ttyACM0", vid=0x2833, pid=0x4001, serial_number="D360-A"),
             SimpleNamespace(device="ttyACM1", vid=0x2833, pid=0x4001, serial_number="D360-B"),
             SimpleNamespace(device="ttyACM2", vid=0x0403, pid=0x6014, serial_number="D360-B")]  # an FTDI, not a Digit
    monkeypatch.setattr(discovery.list_ports, "comports", lambda: ports)
    assert discovery.find_digit360_ports("D360-B") == [("ttyACM1", "D360-B")]
    assert len(discovery.find_digit360_ports()) == 2
