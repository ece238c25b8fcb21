"""The Digit 360's camera and microphones (rotation.hardware.digit360.capture): what is checked when they open, the
frames and samples they give, and the reader built on them.

Where OpenCV is installed, the real ``cv2.VideoCapture`` reads a synthetic MJPG video written with
``cv2.VideoWriter`` through the camera capture; the formats a Digit 360 must not give (1-channel frames, 160 x 120,
5 fps) come from a stand-in with ``VideoCapture``'s calls, and the microphones from a stand-in sounddevice module
whose stream calls back with int16 blocks. The tests marked ``hardware`` read a real sensor (DIGIT360_SERIAL, its
camera and microphones on its USB hub): ``DIGIT360_SERIAL=... make test-hardware``, or
``pytest -m hardware tests/hardware/digit360/test_hw_digit360_capture.py``.
"""

from __future__ import annotations

import os
import sys
import time
import types

import numpy as np
import pytest

from rotation.hardware.digit360 import window as dw
from rotation.hardware.digit360.capture import (
    AudioCapture,
    CameraCapture,
    fourcc_code,
    fourcc_text,
)
from rotation.hardware.digit360.reader import Digit360, Digit360Config
from rotation.sim_hardware.digit360_emulator import Digit360Emulator

EXTRA = "pip install 'tactile-rotation\\[hardware\\]'"


# ------------------------------------------------------------------------------------------ stand-ins
class FakeCapture:
    """``cv2.VideoCapture``-like: frames of ``shape`` and ``dtype`` reporting ``fps`` in ``fourcc``; asked for MJPG
    it reports ``mjpg_fps`` when given (a camera whose full rate needs compression). Frame k: BGR (30, 60, k) inside
    a centre region, black bars ``bar`` px wide on the left and right; ``paced``: frames come at ``fps``."""

    def __init__(self, shape=(720, 1280, 3), dtype=np.uint8, fps=30.0, fourcc="YUYV", mjpg_fps=None, opened=True,
                 bar=0, fail_reads=0, paced=False) -> None:
        self.shape, self.dtype, self.fps, self.fourcc, self.mjpg_fps = shape, dtype, fps, fourcc, mjpg_fps
        self.opened, self.bar, self.fail_reads, self.paced = opened, bar, fail_reads, paced
        self.k, self.asked, self.released, self.t0 = 0, {}, False, time.monotonic()

    def isOpened(self) -> bool:  # noqa: N802 (OpenCV's name)
        return self.opened and not self.released

    def set(self, prop, value) -> bool:
        self.asked[prop] = value
        if prop == 6 and value == fourcc_code("MJPG"):
            self.fourcc, self.fps = "MJPG", self.fps if self.mjpg_fps is None else self.mjpg_fps
        return True

    def get(self, prop) -> float:
        return {3: self.shape[1], 4: self.shape[0], 5: self.fps, 6: fourcc_code(self.fourcc)}.get(prop, 0.0)

    def read(self):
        if self.fail_reads > 0:
            self.fail_reads -= 1
            return False, None
        if self.paced:
            time.sleep(max(0.0, self.t0 + self.k / self.fps - time.monotonic()))
        frame = np.zeros(self.shape, self.dtype)
        if frame.ndim == 3 and frame.shape[2] == 3:
            frame[:, self.bar:self.shape[1] - self.bar] = (30, 60, self.k % 256)
        self.k += 1
        return True, frame

    def release(self) -> None:
        self.released = True


def fake_cv2(capture: FakeCapture) -> types.SimpleNamespace:
    """An OpenCV stand-in whose VideoCapture is ``capture`` (nearest-pixel resize, channel-order swap)."""
    opened: list[tuple] = []

    def video_capture(device, api):
        opened.append((device, api))
        return capture

    def resize(img, size, interpolation=None):
        rows = np.arange(size[1]) * img.shape[0] // size[1]
        return img[rows[:, None], np.arange(size[0]) * img.shape[1] // size[0]]

    return types.SimpleNamespace(
        CAP_ANY=0, CAP_V4L2=200, CAP_PROP_FRAME_WIDTH=3, CAP_PROP_FRAME_HEIGHT=4, CAP_PROP_FPS=5, CAP_PROP_FOURCC=6,
        INTER_AREA=3, COLOR_BGR2RGB=4, VideoCapture=video_capture, resize=resize, opened=opened,
        cvtColor=lambda img, code: np.ascontiguousarray(img[..., ::-1]))


class FakeSounddevice:
    """A sounddevice stand-in: ``query_devices`` reports ``channels`` inputs; the stream calls back only when the
    test calls :meth:`FakeStream.deliver`."""

    def __init__(self, channels: int = 2, rate_ok: bool = True) -> None:
        self.channels, self.rate_ok, self.streams, self.checked = channels, rate_ok, [], []

    def query_devices(self, device, kind):
        if device == "no-such-device":
            raise ValueError(f"No {kind} device matching {device!r}")
        return {"name": "Digit 360: USB Audio (hw:3,0)", "index": 7, "max_input_channels": self.channels,
                "default_samplerate": 48000.0 if self.rate_ok else 44100.0}

    def check_input_settings(self, **settings):
        self.checked.append(settings)
        if not self.rate_ok:
            raise RuntimeError("Invalid sample rate [PaErrorCode -9997]")

    def InputStream(self, **kw):  # noqa: N802 (sounddevice's name)
        self.streams.append(FakeStream(**kw))
        return self.streams[-1]


class FakeStream:
    def __init__(self, *, samplerate, channels, dtype, device, callback) -> None:
        self.settings = {"samplerate": samplerate, "channels": channels, "dtype": dtype, "device": device}
        self.callback, self.started, self.closed = callback, False, False

    def deliver(self, block: np.ndarray, status=None) -> None:
        self.callback(block, len(block), None, status)

    def start(self) -> None:
        self.started = True

    def stop(self) -> None:
        self.started = False

    def close(self) -> None:
        self.closed = True


# ------------------------------------------------------------------------------------------ camera
def test_the_real_opencv_reads_a_synthetic_video_through_the_capture(tmp_path):
    """MJPG 1280 x 720 at 30 fps: a centre region whose top half is BGR (200, 10 k, 50) and bottom half
    (40, 10 k, 220) in frame k, between black (left) and white (right) bars that the square crop must cut away."""
    cv2 = pytest.importorskip("cv2")
    path = str(tmp_path / "digit360.avi")
    writer = cv2.VideoWriter(path, cv2.VideoWriter_fourcc(*"MJPG"), 30.0, (1280, 720))
    assert writer.isOpened()
    n = 12
    for k in range(n):
        frame = np.zeros((720, 1280, 3), np.uint8)
        frame[:360, 280:1000] = (200, 10 * k, 50)
        frame[360:, 280:1000] = (40, 10 * k, 220)
        frame[:, 1000:] = 255
        writer.write(frame)
    writer.release()

    cam = CameraCapture(path, name="test")
    fmt = cam.open()
    assert (fmt.width, fmt.height, fmt.fourcc) == (1280, 720, "MJPG") and fmt.fps == pytest.approx(30.0)
    assert fmt.frame_shape == (720, 1280, 3)
    got = []
    while (item := cam.read()) is not None:
        got.append(item)
    cam.close()
    assert len(got) == n
    times = np.array([t for t, _ in got])
    assert np.all(np.diff(times) > 0) and times[-1] <= time.monotonic()
    for k, (_, rgb) in enumerate(got):
        assert rgb.shape == (224, 224, 3) and rgb.dtype == np.uint8
        top, bottom = rgb[8:100, 8:216].reshape(-1, 3), rgb[124:216, 8:216].reshape(-1, 3)
        # RGB now, JPEG-compressed: within a few counts of the pattern
        np.testing.assert_allclose(np.median(top, axis=0), (50, 10 * k, 200), atol=6)
        np.testing.assert_allclose(np.median(bottom, axis=0), (220, 10 * k, 40), atol=6)
        for rows, rgb_expected in ((slice(8, 100), (50, 10 * k, 200)), (slice(124, 216), (220, 10 * k, 40))):
            edges = rgb[rows][:, [0, 223]].astype(int)  # the crop's own outer columns, not the bars beside them
            assert np.abs(edges - rgb_expected).max() < 40, (k, edges.min(axis=(0, 1)), edges.max(axis=(0, 1)))


def test_a_v4l2_path_opens_with_the_v4l2_backend_and_frames_are_centre_cropped():
    cap = FakeCapture(shape=(600, 800, 3), bar=100)  # 4:3 with bars: the 600 x 600 centre is all pattern
    cv2 = fake_cv2(cap)
    cam = CameraCapture("/dev/video2", cv2=cv2)
    fmt = cam.open()
    assert cv2.opened == [("/dev/video2", 200 if sys.platform.startswith("linux") else 0)]
    assert cap.asked == {3: 1280, 4: 720, 5: 30.0}  # asked for 1280 x 720 at 30 fps, nothing else
    assert (fmt.width, fmt.height, fmt.fps, fmt.fourcc) == (800, 600, 30.0, "YUYV")
    for k in range(3):
        t, rgb = cam.read()
        assert rgb.shape == (224, 224, 3) and np.all(rgb == (k, 60, 30))  # BGR (30, 60, k) -> RGB, no bar
    cam.close()
    assert cap.released
    CameraCapture(3, cv2=(cv2 := fake_cv2(FakeCapture()))).open()
    assert cv2.opened == [(3, 0)]  # an index: OpenCV's default backend


@pytest.mark.parametrize(("capture", "message"), [
    (FakeCapture(shape=(720, 1280)), r"expected 3-channel 8-bit \(BGR\) frames of 1280x720, got frames of shape "
                                     r"\(720, 1280\) uint8"),
    (FakeCapture(dtype=np.uint16), r"expected 3-channel 8-bit .* got frames of shape \(720, 1280, 3\) uint16"),
    (FakeCapture(shape=(120, 160, 3)), r"expected frames of 1280x720 \(at least 224 px on the short side\), "
                                       r"got 160x120"),
    (FakeCapture(fps=5.0), r"expected 30 fps \(\+-10%\) at 1280x720, got 5.0 fps at 1280x720 MJPG"),
    (FakeCapture(fps=5.0, fourcc="MJPG"), r"expected 30 fps .* got 5.0 fps at 1280x720 MJPG"),
    (FakeCapture(opened=False), r"did not open \(OpenCV backend .*\); is it the sensor's UVC capture node"),
    (FakeCapture(fail_reads=10**6), r"opened but gave no frame in 0.1 s"),
])
def test_a_camera_at_an_unexpected_format_is_refused(capture, message):
    cam = CameraCapture("/dev/video4", name="digit360-thumb", cv2=fake_cv2(capture), first_frame_s=0.1)
    with pytest.raises(OSError, match=r"^digit360-thumb: camera '/dev/video4' " + message):
        cam.open()
    assert capture.released and cam.read() is None  # nothing left open


def test_a_slow_rate_is_asked_again_in_mjpg_before_it_is_refused():
    cap = FakeCapture(fps=10.0, fourcc="YUYV", mjpg_fps=30.0)  # 720p30 only compressed
    fmt = CameraCapture("/dev/video2", cv2=fake_cv2(cap)).open()
    assert (fmt.fps, fmt.fourcc) == (30.0, "MJPG") and cap.asked[6] == fourcc_code("MJPG")
    fmt = CameraCapture("/dev/video2", cv2=fake_cv2(FakeCapture(fps=29.97))).open()
    assert fmt.fourcc == "YUYV"  # within 10% of 30 fps: nothing else asked
    fmt = CameraCapture("/dev/video2", cv2=fake_cv2(FakeCapture(fps=0.0))).open()
    assert fmt.fps == 0.0  # a camera that reports no rate is accepted (a warning)
    assert fourcc_text(0) == "" and fourcc_text(float("nan")) == "" and fourcc_text(fourcc_code("MJPG")) == "MJPG"


def test_without_opencv_the_camera_names_the_extra(monkeypatch):
    monkeypatch.setitem(sys.modules, "cv2", None)
    with pytest.raises(ImportError, match=f"camera needs OpenCV: {EXTRA}"):
        CameraCapture("/dev/video2").open()


# ------------------------------------------------------------------------------------------ microphones
def test_audio_blocks_land_in_the_ring_buffer_on_the_host_clock():
    sd = FakeSounddevice()
    buf = dw.RingBuffer(48_000, (2,), np.int16)
    mics = AudioCapture("(hw:3,0)", buf.extend, sounddevice=sd)
    mics.open()
    (stream,) = sd.streams
    assert stream.settings == {"samplerate": 48_000, "channels": 2, "dtype": "int16", "device": "(hw:3,0)"}
    assert stream.started and sd.checked == [{"device": "(hw:3,0)", "channels": 2, "dtype": "int16",
                                              "samplerate": 48_000}]
    before = time.monotonic()
    blocks = [np.stack([np.arange(480) + 480 * b, -np.arange(480)], axis=1).astype(np.int16) for b in range(3)]
    for block in blocks:
        stream.deliver(block)
        time.sleep(0.01)  # 480 samples at 48 kHz
    t, v = buf.snapshot()
    np.testing.assert_array_equal(v, np.concatenate(blocks))
    np.testing.assert_allclose(np.diff(t), 1 / 48_000, rtol=0, atol=1e-9)  # one sample apart, across blocks too
    assert before - 0.02 < t[0] and t[-1] <= time.monotonic()
    assert mics.blocks == 3 and mics.info["max_input_channels"] == 2
    mics.close()
    assert stream.closed and not stream.started


@pytest.mark.parametrize(("sd", "device", "message"), [
    (FakeSounddevice(channels=1), "(hw:3,0)",
     r"microphones '\(hw:3,0\)' did not open: input device 'Digit 360: USB Audio \(hw:3,0\)' has 1 input channel\(s\); "
     r"a Digit 360 has 2 microphones"),
    (FakeSounddevice(rate_ok=False), "(hw:3,0)",
     r"microphones '\(hw:3,0\)' did not open: input device 'Digit 360: USB Audio \(hw:3,0\)' cannot record 2 "
     r"channels of int16 at 48000 Hz \(default rate 44100.0 Hz\): Invalid sample rate"),
    (FakeSounddevice(), "no-such-device", r"microphones 'no-such-device' did not open: No input device matching"),
])
def test_microphones_of_the_wrong_kind_are_refused(sd, device, message):
    with pytest.raises(OSError, match=r"^digit360-index: " + message):
        AudioCapture(device, lambda t, v: None, name="digit360-index", sounddevice=sd).open()
    assert not sd.streams  # refused before a stream opened


def test_without_sounddevice_the_microphones_name_the_extra(monkeypatch):
    monkeypatch.setitem(sys.modules, "sounddevice", None)
    with pytest.raises(ImportError, match=f"microphones need sounddevice: {EXTRA}"):
        AudioCapture("(hw:3,0)", lambda t, v: None).open()


# ------------------------------------------------------------------------------------------ the reader
def test_the_reader_takes_injected_captures_and_fills_a_whole_window():
    """Digit360 with its camera and microphones on stand-ins (the serial stream is the emulator's): the capture
    objects are the reader's, opened when it starts, closed when it stops."""
    cap, sd = FakeCapture(paced=True), FakeSounddevice()
    with Digit360Emulator() as emu:
        d = Digit360(Digit360Config(port=emu.path, camera="/dev/video2", audio_device="(hw:3,0)"))
        d.camera = CameraCapture("/dev/video2", name=d.name, cv2=fake_cv2(cap))
        d.microphones = AudioCapture("(hw:3,0)", d.audio.extend, name=d.name, sounddevice=sd)
        with d:
            stream = sd.streams[0]
            deadline = time.monotonic() + 5.0
            while True:
                block = np.zeros((480, 2), np.int16)
                stream.deliver(block)
                time.sleep(0.01)
                try:
                    w = d.window()
                    break
                except (dw.WindowNotReady, RuntimeError):
                    assert time.monotonic() < deadline, "no whole window in 5 s"
        assert cap.released and stream.closed
    assert w["image"].shape == (6, 224, 224) and w["audio"].shape == (2, 27_000) and w["imu"].shape == (224, 3)
    assert np.all(w["image"][2:4] == 60) and np.all(w["image"][4:] == 30)  # G and B of BGR (30, 60, k)
    assert d.samples["imu/acc"] == d.imu.written > 0 and d.samples["pressure"] == d.pressure.written > 0


# ------------------------------------------------------------------------------------------ real sensor
def _real_devices():
    serial_number = os.environ.get("DIGIT360_SERIAL")
    assert serial_number, "set DIGIT360_SERIAL to the USB serial number of the sensor under test"
    from rotation.hardware.digit360.discovery import find_digit360_devices, find_digit360_ports

    (tty, _), = find_digit360_ports(serial_number)
    devices = find_digit360_devices(tty)
    assert devices.camera and devices.audio, f"found {devices} on the hub of {tty}"
    return devices


@pytest.mark.hardware
def test_a_real_digit360_camera_gives_1280x720_at_30_fps():
    cam = CameraCapture(_real_devices().camera)
    fmt = cam.open()
    try:
        assert (fmt.width, fmt.height) == (1280, 720) and fmt.fps == pytest.approx(30.0, rel=0.1), fmt
        times = []
        while len(times) < 61:
            item = cam.read()
            assert item is not None, "a read failed"
            times.append(item[0])
    finally:
        cam.close()
    assert 60 / (times[-1] - times[0]) == pytest.approx(30.0, rel=0.2)


@pytest.mark.hardware
def test_real_digit360_microphones_give_48_khz_stereo():
    buf = dw.RingBuffer(96_000, (2,), np.int16)
    mics = AudioCapture(_real_devices().audio, buf.extend)
    mics.open()
    try:
        time.sleep(1.5)
    finally:
        mics.close()
    t, _ = buf.snapshot()
    assert mics.info["max_input_channels"] >= 2 and mics.problems == 0
    assert len(t) / (t[-1] - t[0]) == pytest.approx(48_000, rel=0.05)
