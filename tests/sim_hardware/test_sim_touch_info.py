"""`rotate touch-info` against the emulated Digit 360 on a pseudo-terminal: the report, its rates and units, the
listing of attached sensors, and one clear line for each bad request."""

from __future__ import annotations

import json
import math
import sys
import threading
import time
import types

import numpy as np
import pytest

from rotation import cli
from rotation.hardware.digit360 import discovery
from rotation.hardware.digit360.discovery import Digit360Devices
from rotation.jobs.touch_info import Config, run
from rotation.sim_hardware.digit360_emulator import HPA_PER_N, IMU_PERIOD_S, PRESSURE_EVERY, REST_HPA, Digit360Emulator
from rotation.sim_hardware.pty_link import PtyLink

IMU_HZ = 1.0 / IMU_PERIOD_S  # the emulator's accelerometer rate
PRESSURE_HZ = IMU_HZ / PRESSURE_EVERY


@pytest.fixture
def rotate(monkeypatch, capsys):
    """``rotate touch-info ARGS`` through rotation.cli.main -> (exit status, stdout, stderr)."""
    monkeypatch.setitem(cli.COMMANDS, "touch-info", ("rotation.jobs.touch_info",
                                                     "list the attached Digit 360 sensors or read one for a while"))

    def call(*args: str) -> tuple[int, str, str]:
        try:
            code = cli.main(["touch-info", *args])
        except SystemExit as exit_:  # argparse's refusal of an option's value (a usage error)
            code = exit_.code
        out, err = capsys.readouterr()
        return code, out, err

    return call


def test_the_json_report_of_an_emulated_sensor(rotate, digit_emu):
    # the emulator sends its system message (the firmware version) once a second: a window of 1 s may fall between two
    code, out, err = rotate("--digit360", digit_emu.path, "--seconds", "2.5", "--json")
    assert code == 0, err
    assert len(out.strip().splitlines()) == 1  # one JSON object
    report = json.loads(out)
    assert report["sensor"] == digit_emu.path and report["firmware"] == "1.22" and "time.monotonic()" in report["time"]
    acc, pressure = report["streams"]["imu/acc"], report["streams"]["pressure"]
    assert acc["rate_hz"] == pytest.approx(IMU_HZ, rel=0.2)
    assert pressure["rate_hz"] == pytest.approx(PRESSURE_HZ, rel=0.2)
    assert acc["samples"] == pytest.approx(2.5 * IMU_HZ, rel=0.3)  # 2.5 s of samples
    g = acc["last"]["g"]  # at rest: gravity on z (plus the emulator's 0.01 g vibration), in g, not raw counts
    assert len(g) == 3 and math.hypot(*g) == pytest.approx(1.0, abs=0.02)
    p = pressure["last"]
    assert REST_HPA - 1e-3 <= p["hPa"] <= REST_HPA + HPA_PER_N + 1e-3 and p["temperature_C"] == pytest.approx(30.0)
    assert report["streams"]["system"]["last"]["version"] == "1.22"
    assert report["counters"]["frames"] > 0 and report["counters"]["bad_frames"] == 0
    assert report["counters"]["unknown_kinds"] == 0 and report["counters"]["disconnects"] == 0
    assert acc["t_last"] <= time.monotonic()  # on the host's clock
    # the emulator's ts_ght counts samples (400 per second): coarser than its milliseconds, so not used
    assert report["imu_timing"].startswith("device milliseconds")


def test_the_table_of_the_built_in_emulated_sensor(capsys):
    report = run(Config(digit360="sim", seconds=1.1))  # the emulator's version comes every second
    out = capsys.readouterr().out
    assert report["sensor"].startswith("/dev/") and "firmware 1.22" in out and "time.monotonic()" in out
    row = next(line for line in out.splitlines() if line.startswith("imu/acc"))
    assert f"{report['streams']['imu/acc']['rate_hz']:.1f}" in row and " g (" in row
    assert "hPa 10" in out and out.strip().splitlines()[-1].startswith("frames ")


def test_listing_the_attached_sensors(rotate, monkeypatch):
    monkeypatch.setattr(discovery, "find_digit360_ports", lambda serial=None: [])
    code, out, err = rotate()
    assert code == 0 and "no Digit 360 attached" in out and "2833:4001" in out
    attached = [("/dev/ttyACM0", "D360-A"), ("/dev/ttyACM1", "D360-B")]
    monkeypatch.setattr(discovery, "find_digit360_ports", lambda serial=None: attached)
    hubs = {"/dev/ttyACM0": Digit360Devices("/dev/video2", "(hw:1,0)"), "/dev/ttyACM1": Digit360Devices()}
    monkeypatch.setattr(discovery, "find_digit360_devices", lambda port, sysfs="/sys": hubs[port])
    code, out, err = rotate()
    assert code == 0 and "2 Digit 360 sensor(s) attached" in out
    assert any(line.split() == ["D360-A", "/dev/ttyACM0", "/dev/video2", "(hw:1,0)"] for line in out.splitlines())
    assert any(line.split() == ["D360-B", "/dev/ttyACM1", "-", "-"] for line in out.splitlines())
    assert "48 kHz" in out and "30 fps" in out and "400 Hz" in out
    code, out, err = rotate("--json")
    rows = json.loads(out)["sensors"]
    assert rows[1] == {"serial": "D360-B", "data_tty": "/dev/ttyACM1", "camera": None, "microphones": None}


def _one_line(err: str) -> str:
    assert "Traceback" not in err and len(err.strip().splitlines()) == 1, err
    return err


def test_bad_requests_are_one_line(rotate, tmp_path, monkeypatch):
    monkeypatch.setattr(discovery, "find_digit360_ports", lambda serial=None: [])  # this machine's USB is not asked
    code, _, err = rotate("--digit360", "/dev/no-such-tty", "--seconds", "0.5")
    assert code == 2 and "/dev/no-such-tty does not exist; no Digit 360 is attached" in _one_line(err)
    code, _, err = rotate("--digit360", "D360-NOT-HERE")
    assert code == 2 and "no attached Digit 360 has USB serial 'D360-NOT-HERE'" in _one_line(err)
    for seconds in ("0", "-1", "1e9"):
        code, _, err = rotate("--digit360", "/dev/null", "--seconds", seconds)
        assert code == 2 and "seconds must be a finite number in (0, 600] s" in _one_line(err), (seconds, err)
    code, _, err = rotate("--digit360", "/dev/null", "--seconds", "nan")  # argparse's refusal: usage, then the line
    assert code == 2 and "Traceback" not in err and "--seconds: 'nan' is not a finite number" in err
    for args in (["--media"], ["--media", "--digit360", "sim"]):
        code, _, err = rotate(*args)
        assert code == 2 and "media: name the real sensor" in _one_line(err)
    not_a_tty = tmp_path / "notes.txt"
    not_a_tty.write_text("not a serial port")
    code, _, err = rotate("--digit360", str(not_a_tty), "--seconds", "0.2")
    assert code == 1 and "did not open as a serial port" in _one_line(err)


def test_a_port_that_sends_nothing_or_only_garbage(rotate, monkeypatch):
    monkeypatch.setattr(discovery, "find_digit360_ports", lambda serial=None: [])
    link = PtyLink()  # a pseudo-terminal nobody writes to
    try:
        code, _, err = rotate("--digit360", link.path, "--seconds", "0.3")
    finally:
        link.close()
    assert code == 1 and f"{link.path} sent no Digit 360 message in 0.3 s" in _one_line(err)
    emu = Digit360Emulator()
    emu.faults.corrupt_frames = 10**9  # before its thread starts: its first message (system) is corrupted too
    with emu:
        code, _, err = rotate("--digit360", emu.path, "--seconds", "0.3")
    assert code == 1 and "undecodable frame(s) and no Digit 360 message in 0.3 s" in _one_line(err)


# ------------------------------------------------------------------------------------------ --media
class _Stream(threading.Thread):
    """A sounddevice stream stand-in calling back with 10 ms blocks of 2-channel int16 from its own thread."""

    def __init__(self, callback) -> None:
        super().__init__(name="fake-portaudio", daemon=True)
        self.callback, self.halt = callback, threading.Event()

    def run(self) -> None:
        n, t0 = 0, time.monotonic()
        while not self.halt.wait(max(0.0, t0 + (n + 480) / 48_000 - time.monotonic())):
            self.callback(np.full((480, 2), 100, np.int16), 480, None, None)
            n += 480

    def stop(self) -> None:
        self.halt.set()
        self.join()

    def close(self) -> None:
        pass


class _Capture:
    """A VideoCapture stand-in: 1280 x 720 BGR (10, 20, 30) at 30 fps, MJPG."""

    def __init__(self) -> None:
        self.k, self.t0, self.open = 0, time.monotonic(), True

    def isOpened(self) -> bool:  # noqa: N802 (OpenCV's name)
        return self.open

    def set(self, prop, value) -> bool:
        return True

    def get(self, prop) -> float:
        return {3: 1280.0, 4: 720.0, 5: 30.0, 6: float(int.from_bytes(b"MJPG", "little"))}.get(prop, 0.0)

    def read(self):
        time.sleep(max(0.0, self.t0 + self.k / 30 - time.monotonic()))
        self.k += 1
        return True, np.full((720, 1280, 3), (10, 20, 30), np.uint8)

    def release(self) -> None:
        self.open = False


def _libraries(channels: int = 2) -> tuple[types.ModuleType, types.ModuleType]:
    cv2 = types.ModuleType("cv2")
    cv2.CAP_ANY, cv2.CAP_V4L2, cv2.CAP_PROP_FRAME_WIDTH, cv2.CAP_PROP_FRAME_HEIGHT = 0, 200, 3, 4
    cv2.CAP_PROP_FPS, cv2.CAP_PROP_FOURCC, cv2.INTER_AREA, cv2.COLOR_BGR2RGB = 5, 6, 3, 4
    cv2.VideoCapture = lambda device, api: _Capture()
    cv2.resize = lambda img, size, interpolation=None: img[:size[1], :size[0]]
    cv2.cvtColor = lambda img, code: np.ascontiguousarray(img[..., ::-1])
    sd = types.ModuleType("sounddevice")
    sd.query_devices = lambda device, kind: {"name": f"Digit 360 {device}", "max_input_channels": channels,
                                             "default_samplerate": 48000.0}
    sd.check_input_settings = lambda **settings: None
    sd.InputStream = lambda *, callback, **settings: _Stream(callback)
    return cv2, sd


def test_media_reports_the_camera_and_microphones(rotate, digit_emu, monkeypatch):
    """--media opens the camera and microphones found on the sensor's USB hub (here: stand-in libraries, and a hub
    faked for the emulator's pty) and reports their format and measured rates."""
    cv2, sd = _libraries()
    monkeypatch.setitem(sys.modules, "cv2", cv2)
    monkeypatch.setitem(sys.modules, "sounddevice", sd)
    monkeypatch.setattr(discovery, "find_digit360_devices",
                        lambda port, sysfs="/sys": Digit360Devices("/dev/video2", "(hw:1,0)"))
    code, out, err = rotate("--digit360", digit_emu.path, "--seconds", "1", "--media", "--json")
    assert code == 0, err
    streams = json.loads(out)["streams"]
    camera, audio = streams["camera"], streams["audio"]
    assert camera["rate_hz"] == pytest.approx(30.0, rel=0.2) and camera["last"]["mean_rgb"] == [30.0, 20.0, 10.0]
    assert camera["last"]["format"] == {"width": 1280, "height": 720, "fps": 30.0, "fourcc": "MJPG", "backend": ""}
    assert audio["rate_hz"] == pytest.approx(48_000, rel=0.2) and audio["last"]["rms_counts"] == [100.0, 100.0]
    assert audio["last"]["input_channels"] == 2 and streams["imu/acc"]["samples"] > 0


def test_media_refusals_are_one_line(rotate, digit_emu, monkeypatch):
    code, _, err = rotate("--digit360", digit_emu.path, "--media")  # a pty has no USB hub
    assert code == 2 and "no camera or microphones on the USB hub" in _one_line(err)
    monkeypatch.setattr(discovery, "find_digit360_devices",
                        lambda port, sysfs="/sys": Digit360Devices(None, "(hw:1,0)"))
    _, sd = _libraries(channels=1)
    monkeypatch.setitem(sys.modules, "sounddevice", sd)
    code, _, err = rotate("--digit360", digit_emu.path, "--media", "--seconds", "0.5")
    assert code == 1 and "has 1 input channel(s); a Digit 360 has 2 microphones" in _one_line(err)
    monkeypatch.setitem(sys.modules, "sounddevice", None)  # the hardware extra is not installed
    code, _, err = rotate("--digit360", digit_emu.path, "--media", "--seconds", "0.5")
    assert code == 1 and "pip install 'tactile-rotation[hardware]'" in _one_line(err)
