"""The Digit 360 reader against the emulated serial stream: windows, faults, a callback source."""

from __future__ import annotations

import logging
import threading
import time

import numpy as np
import pytest
import serial
from cobs import cobs

from rotation.hardware.digit360.protocol import ACC_LSB_PER_G, IMU_TYPE, messages
from rotation.hardware.digit360.reader import Digit360, Digit360Config, SensorStale
from rotation.hardware.digit360.window import WindowNotReady
from rotation.sim_hardware.digit360_emulator import HPA_PER_N, REST_HPA, Digit360Emulator


def wait_for_window(d: Digit360, timeout: float = 3.0) -> dict:
    deadline = time.monotonic() + timeout
    while True:
        try:
            return d.window()
        except (WindowNotReady, SensorStale):
            if time.monotonic() > deadline:
                raise
            time.sleep(0.05)


def test_emulator_frames_are_cobs_protobuf(digit_emu):
    with serial.Serial(digit_emu.path, timeout=0.5) as port:
        data = port.read(400)
    frames = [f for f in data.split(b"\x00")[1:-1] if f]
    kinds = {messages()["Digit360Message"].FromString(cobs.decode(f)).WhichOneof("type") for f in frames}
    assert {"imu_data", "pressure_data"} <= kinds


def test_windows_from_the_stream(digit_emu):
    with Digit360(Digit360Config(port=digit_emu.path)) as d:
        w = wait_for_window(d)
        assert w["imu"].shape == (224, 3) and w["pressure"].shape == (224, 1)
        assert np.allclose(w["imu"][:, 2], 1.0, atol=1e-3)  # gravity on z, in g
        assert REST_HPA <= w["pressure"].min() and w["pressure"].max() <= REST_HPA + HPA_PER_N + 1e-3
        assert w["t_end"] <= time.monotonic()
        assert d.version == "1.22" and d.counters["bad_frames"] == 0


def test_callback_source_drives_pressure():
    def pressing(t: float):
        return 2.0, np.array([0.5, 0.0, 1.0])

    with Digit360Emulator(source=pressing) as emu, Digit360(Digit360Config(port=emu.path)) as d:
        w = wait_for_window(d)
        assert np.allclose(w["pressure"], REST_HPA + 2.0 * HPA_PER_N)
        assert np.allclose(w["imu"][-1], [0.5, 0.0, 1.0], atol=1e-3)


def test_fault_corrupt_frames_dropped_and_logged(digit_emu, caplog):
    with Digit360(Digit360Config(port=digit_emu.path)) as d, caplog.at_level(logging.WARNING):
        wait_for_window(d)
        digit_emu.faults.corrupt_frames = 3
        deadline = time.monotonic() + 2.0
        while d.counters["bad_frames"] < 3 and time.monotonic() < deadline:
            time.sleep(0.01)
        assert d.counters["bad_frames"] == 3 and "undecodable frame" in caplog.text
        d.window()  # the stream carries on


class _Backlog:
    """A serial port whose host fell behind: everything it holds comes in one read, then nothing."""

    def __init__(self, data: bytes) -> None:
        self.data = data

    @property
    def in_waiting(self) -> int:
        return len(self.data)

    def read(self, n: int) -> bytes:
        out, self.data = self.data[:n], self.data[n:]
        if not out:
            time.sleep(0.01)  # a port's read timeout
        return out

    def close(self) -> None:
        pass


def test_a_late_read_keeps_every_frame_and_drops_only_bytes_without_a_delimiter(monkeypatch, caplog):
    """A host that reads late gets many frames in one read (here 4,000 IMU frames, 10 s, over 64 KiB): every one
    is kept. Only 64 KiB that hold no frame delimiter at all are dropped, with an error."""
    msg = messages()["Digit360Message"]
    frames = []
    for k in range(4000):
        m = msg()
        m.imu_data.ts, m.imu_data.raw.sensor = 5 * k // 2, IMU_TYPE["ACC"]  # the device's milliseconds
        m.imu_data.raw.x, m.imu_data.raw.y, m.imu_data.raw.z = k % 7, -(k % 5), ACC_LSB_PER_G
        frames.append(cobs.encode(m.SerializeToString()) + b"\x00")
    data = b"".join(frames)
    assert len(data) > 1 << 16

    def backlog(self: Digit360) -> None:
        self._serial = _Backlog(data + b"\x01" * (1 << 17))  # then noise: no delimiter for 128 KiB
        self.connected.set()

    monkeypatch.setattr(Digit360, "_open_serial", backlog)
    with caplog.at_level(logging.ERROR), Digit360(Digit360Config(port="backlog")) as d:
        deadline = time.monotonic() + 10.0
        while "without a frame delimiter" not in caplog.text and time.monotonic() < deadline:
            time.sleep(0.01)
        assert d.counters["frames"] == 4000 and d.counters["bad_frames"] == 0 and d.imu.written == 4000
        t, v = d.imu.snapshot()  # the newest samples the buffer holds, in order
    # all arrived at once, before any sample set the device clock's offset: stamped at their arrival, in order
    assert np.all(np.diff(t) >= 0)
    k = np.arange(4000 - len(v), 4000)
    want = np.stack([k % 7, -(k % 5), np.full(len(k), ACC_LSB_PER_G)], 1) / ACC_LSB_PER_G
    assert np.array_equal(v, want.astype(np.float32))
    assert "bytes without a frame delimiter dropped" in caplog.text


def test_fault_pause_makes_windows_stale_then_recovers(digit_emu):
    with Digit360(Digit360Config(port=digit_emu.path, stale_timeout_s=0.1)) as d:
        wait_for_window(d)
        digit_emu.faults.pause_s = 0.5
        time.sleep(0.3)
        with pytest.raises(SensorStale, match="old"):
            d.window()
        wait_for_window(d)


def test_fault_disconnect_is_logged_and_stale(digit_emu, caplog):
    with Digit360(Digit360Config(port=digit_emu.path, stale_timeout_s=0.1)) as d, caplog.at_level(logging.ERROR):
        wait_for_window(d)
        digit_emu.disconnect()
        time.sleep(0.3)
        with pytest.raises(SensorStale, match="connected=False"):
            d.window()
        assert d.counters["disconnects"] == 1 and "data tty lost" in caplog.text


def test_missing_sensor_fails_loudly():
    with pytest.raises(serial.SerialException, match="no Digit 360"):
        with Digit360(Digit360Config(serial_number="not-plugged-in")):
            pass


def test_the_linear_acceleration_channel_of_an_emulated_fingertip_is_free_of_gravity():
    """A held hand is still: its fingertips' accelerometers read 1 g (gravity), their linear acceleration (the
    sensor fusion's channel, --digit360-imu linacc) about 0; the reader's windows take the channel it is asked for."""
    from rotation.sim_hardware.hand_physics import HandPhysics

    physics = HandPhysics.at_grasp("cup", 0, hold=True)
    with Digit360Emulator(physics=physics, finger="index", linacc=True) as emu, \
            Digit360(Digit360Config(port=emu.path, imu_channel="linacc")) as d:
        window = wait_for_window(d)
        acc = np.asarray(d.latest["imu/acc"][1]["g"])
        lin = np.asarray(d.latest["imu/linacc"][1]["g"])
    assert 0.95 < np.linalg.norm(acc) < 1.05 and np.linalg.norm(lin) < 0.05, (acc, lin)
    assert np.abs(window["imu"]).max() < 0.05  # the windows hold the linear acceleration
    # the gravity the emulator removes is the fingertip frame's: not the world's z, a tilted finger's
    assert abs(physics.gravity_in_sensor("index")[2]) < 0.99


def test_a_pause_loses_only_its_own_samples_when_the_emulator_ran_late():
    """A stall injected while the emulator's thread is behind (a loaded machine) must not also drop the backlog of
    samples that were due before it: the gap in the device's timestamps is the pause, not the pause plus the lag."""
    emu: Digit360Emulator | None = None
    blocked = []

    def late_once(t: float):
        if t >= 0.5 and not blocked:  # the thread falls 0.4 s behind, and a 0.2 s pause arrives meanwhile
            blocked.append(t)
            time.sleep(0.4)
            emu.faults.pause_s = 0.2
        return 0.0, np.array([0.0, 0.0, 1.0])

    emu = Digit360Emulator(source=late_once)
    with emu, serial.Serial(emu.path, timeout=0.2) as port:
        data = b""
        deadline = time.monotonic() + 1.8
        while time.monotonic() < deadline:
            data += port.read(4096)
    msgs = [messages()["Digit360Message"].FromString(cobs.decode(f)) for f in data.split(b"\x00")[1:-1] if f]
    ts = np.array([m.imu_data.ts for m in msgs if m.WhichOneof("type") == "imu_data"], dtype=float) / 1e3
    assert blocked and ts[-1] > 1.3, ts[-1]
    gap = np.diff(ts).max()
    assert 0.15 < gap < 0.3, gap  # the old order lost the 0.4 s backlog too (a gap of about 0.6 s)


def test_a_pause_requested_while_the_emulator_is_late_starts_at_its_request():
    """``faults.pause(s)`` (what ``rotate deploy --sim-faults stall=...`` calls) loses the samples of the device times
    from the request on, even when the emulator's thread is busy and sees the request only later."""
    emu: Digit360Emulator | None = None
    blocked = threading.Event()

    def late_once(t: float):
        if t >= 0.5 and not blocked.is_set():  # the thread falls 0.4 s behind
            blocked.set()
            time.sleep(0.4)
        return 0.0, np.array([0.0, 0.0, 1.0])

    epoch = time.monotonic()
    emu = Digit360Emulator(source=late_once, epoch=epoch)
    with emu, serial.Serial(emu.path, timeout=0.2) as port:
        data = b""
        requested = None
        deadline = time.monotonic() + 1.8
        while time.monotonic() < deadline:
            if blocked.is_set() and requested is None:
                time.sleep(0.1)  # the thread is still asleep in the source
                requested = time.monotonic() - epoch
                emu.faults.pause(0.2)
            data += port.read(4096)
    msgs = [messages()["Digit360Message"].FromString(cobs.decode(f)) for f in data.split(b"\x00")[1:-1] if f]
    ts = np.array([m.imu_data.ts for m in msgs if m.WhichOneof("type") == "imu_data"], dtype=float) / 1e3
    gaps = np.diff(ts)
    assert requested is not None and ts[-1] > 1.3, ts[-1]
    start = ts[np.argmax(gaps)]
    assert 0.15 < gaps.max() < 0.25 and abs(start - requested) < 0.02, (gaps.max(), start, requested)
