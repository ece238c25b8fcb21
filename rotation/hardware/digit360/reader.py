"""Digit 360 fingertip sensor: serial data stream (COBS-framed protobuf), audio and camera, as Sparsh-X windows.

Usage::

    with Digit360(Digit360Config(serial_number="D360-XXXX", camera=0, audio_device="Digit 360")) as d:
        sample = d.window()   # dict: image (6,224,224) uint8, audio (2,27000) int16, imu (224,3) g,
                              # pressure (224,1) hPa, t_end (s, host monotonic)

Interfaces (docs/reference/hardware.md section 4): the data tty is a USB CDC device (vendor 0x2833, product 0x4001),
found by its USB serial number with pyserial's ``list_ports``; each device -> host message is a protobuf
``Digit360Message`` of the device's wire schema (``digit360.proto`` beside this file, loaded at run time; units:
rotation.hardware.digit360.protocol) COBS-encoded and terminated by 0x00. The accelerometer feeds the windows; every
other message kind (gyroscope, linear acceleration, fused orientation, gas / humidity / temperature, the high-rate
pressure channels, system status) is decoded into :attr:`Digit360.latest`; a kind the schema does not know is
counted and skipped. Audio (48 kHz, 2 microphones, int16) comes through ``sounddevice`` and the camera (UVC)
through OpenCV, each opened and checked against the device's conventions when the reader starts
(rotation.hardware.digit360.capture); both are imported only when enabled (extra ``[hardware]``).

Emulated sensors have no camera or microphone device: ``Digit360(cfg, media=...)`` takes a :class:`Digit360Media`
instead, which renders the two frames and the audio of a window when :meth:`Digit360.window` asks for them (the
emulated fingertips of rotation.sim_hardware render them from their contact history with the env's sensor model;
rendering every frame at 30 fps would cost more than the control loop can spare). Configs stay plain data: the
media object is a constructor argument, not a config field, and with it OpenCV and sounddevice are never imported.

Timestamps are host ``time.monotonic()`` seconds. Serial samples carry the device's millisecond clock; it is mapped
to host time by the smallest observed (receive time - device time) offset (USB delivers in bursts, the minimum is
the least-delayed sample), allowed to drift by 100 ppm and re-anchored when a sample would map more than 50 ms
before its arrival; a sensor on this host's clock (emulated: ``host_epoch_s``) is timed exactly. The windowed IMU
channel's samples are timed more finely by their sensor time stamp where it proves to be a finer clock that agrees
with the millisecond one (rotation.hardware.digit360.fine_clock).

Faults: an undecodable frame is logged and dropped; a disconnect is logged, the port is reopened every
``reconnect_s``; :meth:`window` raises :class:`SensorStale` when the newest serial sample is older than
``stale_timeout_s``, which the deploy watchdog treats as a sensor stall.
"""

from __future__ import annotations

import logging
import threading
import time
from dataclasses import dataclass
from typing import Literal, Protocol

import numpy as np
import serial
from cobs import cobs

from rotation.hardware.digit360 import discovery
from rotation.hardware.digit360 import window as dw
from rotation.hardware.digit360.capture import AudioCapture, CameraCapture
from rotation.hardware.digit360.fine_clock import FineClock
from rotation.hardware.digit360.protocol import IMU_TYPE, TS_HZ, messages, pressure_hpa, raw_imu_physical

log = logging.getLogger("rotation.hardware.digit360")  # the device's logger (messages name the device)

IMAGE_BUFFER_FRAMES = 45
"""Camera frames a reader keeps (1.5 s at 30 fps): a window needs the newest and the one 5 before it, and a deploy
recording drains the frames every 0.25 s, so a late drain still finds every frame since the last one."""


_IMU_NAMES = {IMU_TYPE["ACC"]: "imu/acc", IMU_TYPE["GYRO"]: "imu/gyro", IMU_TYPE["MAG"]: "imu/mag",
              IMU_TYPE["AUX_IMU"]: "imu/linacc"}


class SensorStale(RuntimeError):
    """The sensor's newest sample is older than the timeout (disconnected or stalled)."""


@dataclass(frozen=True)
class Digit360Config:
    """One fingertip sensor."""

    serial_number: str | None = None
    """USB serial number of the sensor (the setup names fingers by it); None with ``port`` set."""
    port: str | None = None
    """Data tty to open directly (skips discovery, e.g. an emulator's pty)."""
    camera: int | str | None = None
    """OpenCV capture index or device path; None disables the image stream."""
    audio_device: int | str | None = None
    """sounddevice input device (index or name substring); None disables audio."""
    device_clock_hz: float = TS_HZ
    """Tick rate of the device's ``ts`` fields (milliseconds: rotation.hardware.digit360.protocol)."""
    stale_timeout_s: float = 0.1
    """Newest serial sample older than this (s) -> SensorStale from window()."""
    media_stale_timeout_s: float = 0.5
    """Newest camera frame or audio block older than this (s) -> SensorStale from window() (a frozen camera or a
    silent audio stream never passes its last frames off as the present)."""
    reconnect_s: float = 0.5
    """Retry period (s) for reopening the data tty after a disconnect."""
    imu_channel: Literal["acc", "linacc"] = "acc"
    """The accelerometer channel that feeds the imu windows: 'acc', the raw accelerometer (specific force, gravity
    included: what the simulated sensor gives and the shipped encoders trained on), or 'linacc', the sensor fusion's
    linear acceleration (raw IMU type 6, gravity removed: what Meta's released Sparsh-X was pretrained on,
    docs/reference/hardware.md section 4). The other channel is still decoded into ``latest``."""
    read_every_s: float = 0.005
    """Pause (s) after each read of the data tty, so that one read takes the frames of a few ms at once: waking for
    every 400 Hz frame of four sensors kept the interpreter's lock so busy that the policy's thread missed its
    budget on a slower 2-core machine. The samples keep their device time stamps; 0 reads every frame at once."""
    buffer_s: float = 3.0
    """History kept per stream (s); must exceed the longest window (pressure, 1.12 s)."""
    host_epoch_s: float | None = None
    """For a sensor on this host's clock (an emulated one): the host ``time.monotonic()`` of its device time 0. Its
    samples are then timed exactly (epoch + device time), so a delay in their delivery shows in every age the
    reader and deploy report. None (a real sensor): the minimum-offset mapping of the module docstring, which
    cannot see a delay that stays."""

    def __post_init__(self) -> None:
        if self.serial_number is None and self.port is None:
            raise ValueError("Digit360Config: set serial_number (USB discovery) or port")
        if not self.buffer_s > 1.2:
            raise ValueError(f"Digit360Config.buffer_s must exceed the 1.12 s pressure window, got {self.buffer_s}")
        if not (self.stale_timeout_s > 0 and self.media_stale_timeout_s > 0 and self.reconnect_s > 0
                and self.device_clock_hz > 0):
            raise ValueError("Digit360Config: stale_timeout_s, media_stale_timeout_s, reconnect_s and device_clock_hz "
                             "must be > 0")
        if self.imu_channel not in ("acc", "linacc"):
            raise ValueError(f"Digit360Config: imu_channel must be 'acc' or 'linacc', got {self.imu_channel!r}")
        if not 0 <= self.read_every_s < self.stale_timeout_s:
            raise ValueError(f"Digit360Config: read_every_s must be in [0, stale_timeout_s), got {self.read_every_s}")


class Digit360Media(Protocol):
    """Camera and microphones rendered on request instead of read from devices (an emulated sensor's)."""

    def media_window(self, t_end: float | None = None) -> tuple[np.ndarray, np.ndarray, float]:
        """Image and audio of the window ending at the newest frame at or before ``t_end`` (host
        ``time.monotonic()`` s; None: now): ``image`` (6, 224, 224) uint8 channel-major
        [R(t-5), R(t), G(t-5), G(t), B(t-5), B(t)], ``audio`` (2, 27000) int16 up to that frame, and the frame's
        host time. Raises :class:`digit360_window.WindowNotReady` while there is not enough history."""
        ...


class _ClockMap:
    """Device clock (ticks, uint32, wraps) -> host seconds by the minimum-offset rule (see module docstring)."""

    max_latency_s = 0.05
    """A sample mapped more than this before its arrival means the mapping is wrong (device clock paused or
    reset), not that USB was that slow: re-anchor on it."""

    def __init__(self, hz: float, epoch: float | None = None) -> None:
        self.hz = hz
        self.epoch = epoch
        """Host time of device time 0 for a device on this host's clock (Digit360Config.host_epoch_s), else None."""
        self.offset: float | None = epoch
        self.t_last = 0.0
        self.ts_last = 0

    def __call__(self, ts: int, t_recv: float) -> float:
        if self.epoch is not None:  # the host's own clock: exact, whatever the delivery's delay
            if ts < self.ts_last and self.ts_last - ts > 2**31:
                self.offset += 2**32 / self.hz  # type: ignore[operator]  # counter wrapped
            self.ts_last = ts
            return min(ts / self.hz + self.offset, t_recv)  # type: ignore[operator]
        if self.offset is not None and ts < self.ts_last and self.ts_last - ts > 2**31:
            self.offset += 2**32 / self.hz  # counter wrapped
        elif self.offset is not None and ts < self.ts_last - 1:  # (within a tick: a sub-tick IMU time before it)
            self.offset = None  # device restarted
        off = t_recv - ts / self.hz
        if self.offset is None or off - self.offset > self.max_latency_s:
            self.offset = off  # first sample, or the device clock jumped back relative to ours: re-anchor
        else:
            self.offset = min(self.offset + 1e-4 * max(t_recv - self.t_last, 0.0), off)
        self.t_last, self.ts_last = t_recv, ts
        return min(ts / self.hz + self.offset, t_recv)


class Digit360:
    """Reader threads filling ring buffers; :meth:`window` assembles a Sparsh-X sample.

    ``media``: an emulated sensor's camera and microphones (:class:`Digit360Media`), used instead of the devices
    named by ``cfg.camera`` / ``cfg.audio_device`` (which must then be None).
    """

    def __init__(self, cfg: Digit360Config, name: str = "digit360", media: Digit360Media | None = None) -> None:
        if media is not None and (cfg.camera is not None or cfg.audio_device is not None):
            raise ValueError(f"{name}: an emulated sensor's image and audio come from `media`; leave "
                             "Digit360Config.camera and audio_device unset")
        self.cfg = cfg
        self.name = name
        self.media = media
        n = int(cfg.buffer_s * 1.5 * dw.IMU_RATE)
        self.imu = dw.RingBuffer(n, (3,))
        self.pressure = dw.RingBuffer(int(cfg.buffer_s * 1.5 * dw.PRESSURE_RATE), (1,))
        self.audio = dw.RingBuffer(int(cfg.buffer_s * dw.AUDIO_RATE), (2,), np.int16) if cfg.audio_device is not None \
            else None
        self.image = dw.RingBuffer(IMAGE_BUFFER_FRAMES, (dw.IMAGE_SIZE, dw.IMAGE_SIZE, 3), np.uint8) \
            if cfg.camera is not None else None
        self.camera = CameraCapture(cfg.camera, name) if cfg.camera is not None else None
        """The camera (opened when the reader starts; a test may replace it with one on a stand-in OpenCV)."""
        self.microphones = AudioCapture(cfg.audio_device, self.audio.extend, name) if self.audio is not None else None
        """The microphones (opened when the reader starts), feeding :attr:`audio`."""
        self.version = ""
        self.counters = {"frames": 0, "bad_frames": 0, "disconnects": 0, "unknown": 0}
        self.latest: dict[str, tuple[float, object]] = {}
        """Stream -> (host time, newest decoded sample in physical units) of every message kind the device sent
        (``imu/acc``, ``imu/gyro``, ``imu/linacc``, ``pressure``, ``gasht``, ``euler``, ``quat``, ...)."""
        self.samples: dict[str, int] = {}
        """Stream -> samples decoded since the reader started (the streams of :attr:`latest`)."""
        self._msg = messages()["Digit360Message"]
        self._window_imu = IMU_TYPE["ACC"] if cfg.imu_channel == "acc" else IMU_TYPE["AUX_IMU"]
        self._clock = _ClockMap(cfg.device_clock_hz, cfg.host_epoch_s)
        self._fine = FineClock()
        self._stop = threading.Event()
        self._threads: list[threading.Thread] = []
        self._serial: serial.Serial | None = None
        self.connected = threading.Event()

    def __enter__(self) -> Digit360:
        self._open_serial()  # fail loudly at start if the sensor is not there
        try:
            self._start(self._serial_loop, "serial")
            if self.camera is not None:
                self.camera.open()  # checks the format it agreed to (OSError when refused)
                self._start(lambda: self.camera.run(self._stop, self.image.append, self.cfg.reconnect_s), "camera")
            if self.microphones is not None:
                self.microphones.open()
        except BaseException:
            self.close()  # no reader thread outlives a sensor that did not open
            raise
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def close(self) -> None:
        self._stop.set()
        for t in self._threads:
            t.join(timeout=2.0)
        if self.camera is not None and not any(t.is_alive() for t in self._threads):
            self.camera.close()  # else its thread, still in a read, releases it when the read returns
        self._threads.clear()
        if self.microphones is not None:
            self.microphones.close()
        if self._serial is not None:
            self._serial.close()
            self._serial = None

    def window(self, t_end: float | None = None, now: float | None = None,
               serial_only: bool = False) -> dict[str, np.ndarray | float]:
        """One Sparsh-X sample (see :mod:`digit360_window`); SensorStale if the serial stream stopped.

        With ``media`` the sample has all four modalities and every window ends at the media's frame (the newest at
        or before ``t_end``); WindowNotReady until each stream has enough history. ``serial_only``: only the IMU and
        pressure windows (a reader of those alone skips rendering an emulated sensor's image and audio).
        """
        now = time.monotonic() if now is None else now
        age = now - max(self.imu.newest_time(), self.pressure.newest_time())
        if age > self.cfg.stale_timeout_s:
            raise SensorStale(f"{self.name}: newest IMU/pressure sample is {age:.3f} s old "
                              f"(> {self.cfg.stale_timeout_s} s); connected={self.connected.is_set()}")
        if serial_only:
            return dw.sparshx_window(None, None, self.imu, self.pressure, t_end)
        if self.media is None:
            for what, buf in (("camera frame", self.image), ("audio block", self.audio)):
                if buf is None:
                    continue
                if not len(buf):
                    raise dw.WindowNotReady(f"{self.name}: no {what} yet")
                media_age = now - buf.newest_time()
                if media_age > self.cfg.media_stale_timeout_s:
                    raise SensorStale(f"{self.name}: newest {what} is {media_age:.3f} s old "
                                      f"(> {self.cfg.media_stale_timeout_s} s)")
            return dw.sparshx_window(self.image, self.audio, self.imu, self.pressure, t_end)
        image, audio, t_frame = self.media.media_window(t_end)
        serial = dw.sparshx_window(None, None, self.imu, self.pressure, t_frame)
        return {"image": image, "t_end": serial["t_end"], "audio": audio, "imu": serial["imu"],
                "pressure": serial["pressure"]}

    # ------------------------------------------------------------------ serial
    def _start(self, fn, what: str) -> None:
        t = threading.Thread(target=fn, name=f"{self.name}-{what}", daemon=True)
        t.start()
        self._threads.append(t)

    def _open_serial(self) -> None:
        port = self.cfg.port
        if port is None:
            found = discovery.find_digit360_ports(self.cfg.serial_number)
            if not found:
                raise serial.SerialException(f"{self.name}: no Digit 360 data tty with USB serial "
                                             f"{self.cfg.serial_number!r} (vendor 0x2833, product 0x4001)")
            port = found[0][0]
        self._serial = serial.Serial(port, timeout=0.05)  # CDC: no baud rate needed
        self.connected.set()

    def _serial_loop(self) -> None:
        buf = bytearray()
        live = False  # the open port has delivered data: losing it now is a disconnect
        while not self._stop.is_set():
            if self._serial is None:
                try:
                    self._open_serial()
                    buf.clear()
                except (serial.SerialException, OSError) as err:
                    log.debug("%s: reopen failed: %s", self.name, err)
                    self._stop.wait(self.cfg.reconnect_s)
                continue
            try:
                chunk = self._serial.read(max(1, self._serial.in_waiting))
            except (serial.SerialException, OSError, TypeError) as err:
                if live:  # one disconnect per loss, not one per failed reopen while the sensor is away
                    self.counters["disconnects"] += 1
                    log.error("%s: data tty lost (%s); retrying every %.1f s", self.name, err, self.cfg.reconnect_s)
                else:
                    log.debug("%s: the reopened data tty failed again: %s", self.name, err)
                live = False
                self.connected.clear()
                try:
                    self._serial.close()
                finally:
                    self._serial = None
                self._stop.wait(self.cfg.reconnect_s)
                continue
            if chunk and not live:
                if self.counters["disconnects"]:
                    log.warning("%s: data tty back after a disconnect", self.name)
                live = True
            t_recv = time.monotonic()
            buf.extend(chunk)
            start = 0  # frames are cut from the front once per read, not one by one (a late read holds hundreds)
            while (end := buf.find(b"\x00", start)) >= 0:
                frame, start = bytes(buf[start:end]), end + 1
                if frame:
                    try:
                        self._on_frame(frame, t_recv)
                    except Exception:  # a reader thread must not die silently
                        log.exception("%s: error handling a frame", self.name)
            del buf[:start]
            if len(buf) > 1 << 16:  # no frame delimiter for 64 KiB: not our stream; resynchronize
                log.error("%s: %d bytes without a frame delimiter dropped", self.name, len(buf))
                buf.clear()
            if self.cfg.read_every_s > 0:
                self._stop.wait(self.cfg.read_every_s)

    def _on_frame(self, frame: bytes, t_recv: float) -> None:
        try:
            msg = self._msg.FromString(cobs.decode(frame))
        except Exception as err:  # cobs.DecodeError or protobuf DecodeError
            self.counters["bad_frames"] += 1
            n = self.counters["bad_frames"]
            if n == 1 or n % 100 == 0:
                log.warning("%s: dropped an undecodable frame (%d so far): %s", self.name, n, err)
            return
        self.counters["frames"] += 1
        kind = msg.WhichOneof("type")
        if kind == "pressure_data":
            p = msg.pressure_data
            t = self._clock(p.ts, t_recv)
            hpa = pressure_hpa(p.pressure)
            self.pressure.append(t, hpa)
            self._seen("pressure", t, {"hPa": hpa, "temperature_C": p.temperature})
        elif kind == "imu_data":
            imu = msg.imu_data
            part = imu.WhichOneof("imu_type")
            windowed = part == "raw" and imu.raw.sensor == self._window_imu
            # the windowed channel's samples timed by their sensor time stamp where it proves to be a finer clock
            t = self._clock(self._fine(imu.ts, imu.raw.ts_ght) if windowed else imu.ts, t_recv)
            if part == "raw":
                r = imu.raw
                unit, values = raw_imu_physical(r.sensor, r.x, r.y, r.z)
                if windowed:
                    self.imu.append(t, values)  # the channel cfg.imu_channel names feeds the windows
                name = _IMU_NAMES.get(r.sensor, f"imu/type{r.sensor}")
                self._seen(name, t, {unit: values})
            elif part == "euler":
                e = imu.euler
                self._seen("euler", t, {"deg": (e.heading, e.pitch, e.roll)})
            elif part == "quat":
                q = imu.quat
                self._seen("quat", t, {"wxyz": (q.w, q.x, q.y, q.z), "accuracy": q.accuracy})
        elif kind == "gasht_data":
            g = msg.gasht_data
            self._seen("gasht", self._clock(g.ts, t_recv), {
                "temperature_C": g.temperature, "hPa": pressure_hpa(g.pressure), "humidity": g.humidity,
                "gas": g.gas, "gas_index": g.gas_index})
        elif kind == "pressure_ap_data":
            a = msg.pressure_ap_data
            self._seen("pressure_ap", self._clock(a.ts, t_recv), {
                "channel_a": np.frombuffer(a.channel_a[: len(a.channel_a) // 2 * 2], "<u2"),
                "channel_b": np.frombuffer(a.channel_b[: len(a.channel_b) // 2 * 2], "<u2")})
        elif kind == "system_data":
            self.version = f"{msg.system_data.version_major}.{msg.system_data.version_minor}"
            self._seen("system", t_recv, {"version": self.version, "status": msg.system_data.status})
        else:  # a message type this schema does not know (a newer firmware's), or an empty one: skipped
            self.counters["unknown"] += 1
            n = self.counters["unknown"]
            if n == 1 or n % 1000 == 0:
                log.info("%s: skipped a message of a type this host does not know (%d so far)", self.name, n)

    def _seen(self, stream: str, t: float, value: object) -> None:
        self.latest[stream] = (t, value)
        self.samples[stream] = self.samples.get(stream, 0) + 1
