"""Touch sensors during deploy: parse ``--digit360`` / ``--skin``, open the readers, move their samples into the
recording.

``--digit360`` names one sensor per finger, either positionally in the bus order of the fingers
(``index,middle,ring,thumb``: exactly four entries) or by name for any subset (``thumb=D360-A,index=D360-B``).
An entry is a USB serial number (the data tty is found by it) or, if it starts with ``/``, a tty path (e.g. a
pseudo-terminal). ``sim`` (emulated hands only) starts one emulated sensor per finger that senses that finger of the
emulated hand with the env's simulated Digit 360 (rotation.sim_hardware.digit360_touch): IMU and pressure from the
fingertip's contact and motion on its serial stream, and an emulated camera and microphones whose frames and audio
are rendered from the same contact history when a window is asked for.

The sensors are recorded: their serial streams (accelerometer 400 Hz, pressure 200 Hz) go to
``digit360/<finger>/{imu,pressure}``, and a real sensor's camera frames and microphones, when deploy opened them,
to ``digit360/<finger>/{image,audio}`` (an emulated sensor renders its image and audio only for a window, and
records none). Their Sparsh-X windows (image, audio, IMU,
pressure; rotation.hardware.digit360.window) are read by a touch-reading policy (rotation.deploy.touch) through
``reader.window()`` of each finger's reader; emulated sensors give all four modalities, a real one its serial
streams (IMU and pressure) and, when the policy reads the image or the audio, its camera and microphones, found on
the sensor's own USB hub (:func:`find_media`; OpenCV and sounddevice, the ``hardware`` extra).
A sensor that stops streaming leaves a gap in its streams and a log line; it does not stop the hand.

``--skin`` names the Xela skin's ``xela_server`` (a ws:// URL; ``sim`` starts the local stand-in server,
rotation.sim_hardware.xela_emulator, emulated hands only). Its frames (raw counts, our taxel order,
rotation.hardware.xela.reader) are recorded to ``skin/xela``; the median of the frames received before the hand starts
is stored as the session's ``extra["xela_baseline"]`` (the no-contact reading, rotation.data.skin), so start with
the skin free of contact. A skin that stops streaming leaves a gap and a log line, like a Digit 360.
"""

from __future__ import annotations

import contextlib
import logging
import os
import time
from typing import TYPE_CHECKING, Any

import numpy as np

from envs.constants import FINGERS

if TYPE_CHECKING:
    from rotation.sim_hardware.hand_physics import HandPhysics

log = logging.getLogger(__name__)

EMULATED_STALE_S = 0.25
"""Stale limit (s) of the readers of emulated fingertips (`--digit360 sim`), where a real sensor's reader keeps 0.1 s
(rotation.hardware.digit360.reader.Digit360Config). An emulated fingertip renders its streams on this host, beside
the hand, the loop and the encoder: with the generation-2 sensor model four of them take about 40% of a core, and on
a loaded 2-core machine the newest sample of one read 0.11-0.18 s old now and then without any fault. A stall or a
lag fault longer than this limit still makes touch stale."""

STALL_S = 0.5
"""A sensor whose newest sample is older than this (s) is reported as stalled (a gap in its recording)."""
STREAMS = ("imu", "pressure")
"""Recorded serial streams per fingertip (session stream ``digit360/<finger>/<stream>``)."""
MEDIA_STREAMS = ("image", "audio")
"""Recorded camera frames and microphones per fingertip, where a real sensor's were opened."""


def parse_digit360(spec: str, emulated: bool) -> dict[str, str]:
    """``--digit360`` -> {finger: serial number, tty path or 'sim'}; ValueError naming the accepted forms."""
    spec = spec.strip()
    if not spec:
        return {}
    forms = ("expected 4 comma-separated serials in finger order (index,middle,ring,thumb), "
             "FINGER=SERIAL pairs (e.g. thumb=D360-A,index=D360-B), tty paths, or 'sim' with an emulated hand")
    if spec == "sim":
        if not emulated:
            raise ValueError("--digit360 sim (emulated sensors) needs an emulated hand (--hand sim-allegro/sim-leap)")
        return dict.fromkeys(FINGERS, "sim")
    entries = [e.strip() for e in spec.split(",")]
    if any(not e for e in entries):
        raise ValueError(f"--digit360 {spec!r}: empty entry; {forms}")
    named = ["=" in e for e in entries]
    if any(named) and not all(named):
        raise ValueError(f"--digit360 {spec!r}: mixes named and positional entries; {forms}")
    if all(named):
        out: dict[str, str] = {}
        for e in entries:
            finger, value = (x.strip() for x in e.split("=", 1))
            if finger not in FINGERS:
                raise ValueError(f"--digit360 {spec!r}: unknown finger {finger!r}; fingers: {', '.join(FINGERS)}")
            if finger in out:
                raise ValueError(f"--digit360 {spec!r}: finger {finger!r} named twice")
            if not value:
                raise ValueError(f"--digit360 {spec!r}: no serial for {finger!r}")
            out[finger] = value
        return out
    if len(entries) != len(FINGERS):
        raise ValueError(f"--digit360 {spec!r}: {len(entries)} positional entries; {forms}")
    return dict(zip(FINGERS, entries, strict=True))


class SensorError(RuntimeError):
    """A Digit 360 named by ``--digit360`` could not be opened (the hand had not been started yet)."""


def check_digit360(specs: dict[str, str]) -> None:
    """ValueError (naming ``--digit360``) unless every named sensor is there now: a tty path exists, a USB serial
    number belongs to a connected Digit 360. Run before anything starts, so a typo never follows a motors-on."""
    real = {finger: value for finger, value in specs.items() if value != "sim"}
    if not real:
        return
    from rotation.hardware.digit360 import discovery

    connected = discovery.find_digit360_ports()  # (tty, serial) of every Digit 360 plugged in now
    missing = []
    for finger, value in real.items():
        if value.startswith("/"):
            if not os.path.exists(value):
                missing.append(f"{finger}={value} (no such device)")
        elif not discovery.find_digit360_ports(value):  # the hub's serial or the data tty's
            missing.append(f"{finger}={value} (no connected Digit 360 has this USB serial)")
    if missing:
        found = ", ".join(sorted(serial or tty for tty, serial in connected)) or "none"
        raise ValueError(f"--digit360: {'; '.join(missing)}. Connected Digit 360 sensors: {found}")


SIM_WINDOWS = ("image", "audio", "imu", "pressure")
"""Sparsh-X windows of an emulated fingertip beside an emulated hand (its camera and microphones are emulated)."""
SERIAL_WINDOWS = ("imu", "pressure")
"""Sparsh-X windows of a sensor's serial stream: what :func:`open_digit360` opens for a serial number or a tty path,
plus the camera (``image``) and microphones (``audio``) that :func:`find_media` found for it."""


def digit360_windows(value: str, emulated: bool, devices: Any = None) -> tuple[str, ...]:
    """The windows in ``reader.window()`` of the sensor that :func:`open_digit360` starts for one ``--digit360``
    entry (``value``: 'sim', a serial or a tty path) beside an emulated (``emulated``) or a real hand;
    ``devices``: that sensor's camera and microphones to open (rotation.hardware.digit360.discovery.Digit360Devices)."""
    if value == "sim" and emulated:
        return SIM_WINDOWS
    extra = () if devices is None else (("image",) if devices.camera else ()) + (("audio",) if devices.audio else ())
    return (*extra, *SERIAL_WINDOWS)


def find_media(specs: dict[str, str], windows: tuple[str, ...], sysfs: str = "/sys") -> dict[str, Any]:
    """{finger: Digit360Devices} for the real sensors in ``specs`` when ``windows`` (what a policy reads) include
    the image or the audio: the camera and microphones on each sensor's USB hub
    (rotation.hardware.digit360.discovery.find_digit360_devices), only those the windows need. A sensor that is not
    connected (``check_digit360`` says so before the start) or a tty that is not a Digit 360's finds nothing."""
    wanted = {"image", "audio"} & set(windows)
    real = {finger: value for finger, value in specs.items() if value != "sim"}
    if not wanted or not real:
        return {}
    from rotation.hardware.digit360 import discovery

    out = {}
    for finger, value in real.items():
        found_ports = [] if value.startswith("/") else discovery.find_digit360_ports(value, sysfs)
        port = value if value.startswith("/") else (found_ports[0][0] if found_ports else None)
        found = discovery.find_digit360_devices(port, sysfs) if port else discovery.Digit360Devices()
        out[finger] = discovery.Digit360Devices(camera=found.camera if "image" in wanted else None,
                                      audio=found.audio if "audio" in wanted else None)
        log.info("digit360 %s (%s): camera %s, microphones %s", finger, value, out[finger].camera or "-",
                 out[finger].audio or "-")
    return out


def check_media_extras(media: dict[str, Any]) -> None:
    """ValueError (the install command) unless the libraries that read the cameras and microphones in ``media``
    import: OpenCV and sounddevice, the ``hardware`` extra. Run before anything starts."""
    needs = {"cv2": any(d.camera for d in media.values()), "sounddevice": any(d.audio for d in media.values())}
    missing = []
    for module, needed in needs.items():
        if needed:
            try:
                __import__(module)
            except (ImportError, OSError) as err:  # sounddevice raises OSError without the PortAudio library
                missing.append(f"{module} ({err})")
    if missing:
        raise ValueError(f"--digit360: reading the sensors' cameras and microphones needs {', '.join(missing)}: "
                         "pip install 'tactile-rotation[hardware]' (sounddevice also needs the PortAudio library, "
                         "e.g. apt install libportaudio2)")


def open_digit360(specs: dict[str, str], stack: contextlib.ExitStack, physics: HandPhysics | None = None,
                  media: dict[str, Any] | None = None, emulators: dict[str, Any] | None = None,
                  imu_channel: str = "acc") -> dict[str, Any]:
    """Start one reader per finger (and its emulator for 'sim') inside ``stack``; {finger: Digit360}. A sensor that
    does not open (its data tty, or the camera or microphones it is given) raises :class:`SensorError` naming the
    finger.

    ``physics``: the emulated hand (rotation.deploy.hands.emulated_physics); a 'sim' sensor then senses its finger
    of that hand and its reader gets the emulated camera and microphones. Without it, 'sim' sensors stream the
    emulator's synthetic readings (IMU and pressure only). ``media``: {finger: Digit360Devices} of real sensors
    (:func:`find_media`), whose camera and microphones their readers open beside the serial stream. ``emulators``:
    filled with {finger: Digit360Emulator} of the 'sim' sensors (their fault switches, rotation.deploy.sim_faults).
    ``imu_channel``: the accelerometer channel of the imu windows (Digit360Config.imu_channel; emulated sensors then
    send it too).
    """
    if not specs:
        return {}
    from rotation.hardware.digit360.reader import Digit360, Digit360Config

    readers: dict[str, Any] = {}
    epoch = time.monotonic()  # one device clock for the emulated fingertips of the hand: they sample it together
    for finger, value in specs.items():
        rendered = None  # an emulated sensor's camera and microphones
        try:
            if value == "sim":
                from rotation.sim_hardware.digit360_emulator import Digit360Emulator

                linacc = imu_channel == "linacc"  # the emulator then also sends the linear acceleration
                emulator = Digit360Emulator(epoch=epoch, linacc=linacc) if physics is None else Digit360Emulator(
                    physics=physics, finger=finger, epoch=epoch, linacc=linacc)
                # an emulated sensor runs on this host's clock: the reader times its samples exactly
                cfg = Digit360Config(port=stack.enter_context(emulator).path, imu_channel=imu_channel,
                                     host_epoch_s=epoch, stale_timeout_s=EMULATED_STALE_S)
                rendered = emulator.media
                if emulators is not None:
                    emulators[finger] = emulator
            else:
                devices = (media or {}).get(finger)
                where = {"port": value} if value.startswith("/") else {"serial_number": value}
                cfg = Digit360Config(**where, camera=getattr(devices, "camera", None),
                                     audio_device=getattr(devices, "audio", None), imu_channel=imu_channel)
            readers[finger] = stack.enter_context(Digit360(cfg, name=f"digit360-{finger}", media=rendered))
        except (OSError, ImportError) as err:  # pyserial's SerialException is an OSError
            raise SensorError(f"digit360 {finger} ({value}) did not open: {err}") from err
        log.info("digit360 %s: %s", finger, value if value != "sim" else f"emulated on {cfg.port}")
    return readers


def parse_skin(spec: str, emulated: bool) -> str:
    """``--skin`` -> '' (none), 'sim' (emulated hands only) or a checked ws:// URL; ValueError naming ``skin``."""
    spec = spec.strip()
    if spec in ("", "sim"):
        if spec == "sim" and not emulated:
            raise ValueError("skin: 'sim' (the stand-in xela_server) needs an emulated hand "
                             "(--hand sim-allegro/sim-leap)")
        return spec
    from rotation.hardware.xela.reader import parse_url

    return parse_url(spec, "skin")


def check_skin(spec: str) -> None:
    """ValueError (naming ``--skin``) unless the xela_server at the URL answers now (before anything starts)."""
    if spec in ("", "sim"):
        return
    from rotation.hardware.xela.reader import probe_server

    problem = probe_server(spec)
    if problem:
        raise ValueError(f"--skin {spec}: xela_server does not answer ({problem}); start it, or drop --skin")


SKIN_BASELINE_S = 0.5
"""Frames (s) before the hand starts whose median is the session's skin baseline."""


def open_skin(spec: str, stack: contextlib.ExitStack) -> tuple[Any, Any]:
    """Start the skin reader (and for 'sim' the stand-in server) inside ``stack``; (reader, baseline (368, 3) or
    None). Waits up to 2 s for ``SKIN_BASELINE_S`` of frames; :class:`SensorError` if none arrives."""
    if not spec:
        return None, None
    from rotation.hardware.xela.reader import SAMPLE_HZ, XelaConfig, XelaReader

    url = spec
    if spec == "sim":
        from rotation.sim_hardware.xela_emulator import XelaServerEmulator

        url = stack.enter_context(XelaServerEmulator()).url
    reader = stack.enter_context(XelaReader(XelaConfig(url=url)))
    if not reader.wait_frames(int(SKIN_BASELINE_S * SAMPLE_HZ), timeout_s=2.0) and reader.counters["frames"] == 0:
        raise SensorError(f"skin ({url}): no frame within 2 s ({reader.last_error or 'nothing received'})")
    from rotation.data.skin import estimate_baseline

    baseline = estimate_baseline(reader.recent(SKIN_BASELINE_S)[1])
    log.info("skin: %s, %d frames before the start (baseline from the last %.1f s)", url,
             reader.counters["frames"], SKIN_BASELINE_S)
    return reader, baseline


class SampleCursor:
    """Where a recording drain stands in one ring buffer: the newest time it took (host s), and how many samples the
    buffer had written when it last looked, so that each take looks only at newer ones (RingBuffer.since; its cost
    follows what is new, not the buffer's capacity: four fingertips' audio are 576,000 slots)."""

    def __init__(self, t0: float) -> None:
        self.last, self.seen = t0, 0

    def take(self, buf: Any) -> tuple[np.ndarray, np.ndarray]:
        """The samples newer than those taken before, strictly increasing (a clock re-anchoring may map a sample
        before an earlier one): (t (n,), v (n, ...))."""
        seen, self.seen = self.seen, buf.written  # read first: a sample written meanwhile is taken now or, being
        t, v = buf.since(self.last, seen)  # newer than ``last``, next time
        keep = t > np.maximum.accumulate(np.concatenate([[self.last], t]))[:-1]
        t, v = t[keep], v[keep]
        if len(t):
            self.last = float(t[-1])
        return t, v


class SkinDrain:
    """Moves new skin frames into ``skin/xela`` (session time ``t - t0``), logging stalls like :class:`DigitDrain`."""

    def __init__(self, reader: Any, t0: float) -> None:
        self.reader, self.t0 = reader, t0
        self._cursor = SampleCursor(t0)
        self._stalled = False

    def drain(self, append) -> None:
        t, v = self._cursor.take(self.reader.frames)
        if len(t):
            append("skin/xela", v, t - self.t0)
        age = time.monotonic() - self.reader.frames.newest_time()
        stalled = age > STALL_S
        if stalled != self._stalled:
            if stalled:
                log.warning("skin: no frames for %.1f s (a gap in its recording; the hand goes on): %s",
                            age if np.isfinite(age) else float("inf"), self.reader.last_error or "no error reported")
            else:
                log.info("skin: streaming again")
            self._stalled = stalled

    def newest(self) -> dict[str, float]:
        """The newest frame's time (host s), as ``{"skin": t}``."""
        return {"skin": float(self.reader.frames.newest_time())}


def media_streams(reader: Any) -> tuple[str, ...]:
    """Which of ``image`` and ``audio`` a Digit 360 reader streams into ring buffers (a real sensor's camera and
    microphones that deploy opened; an emulated sensor renders them per window and has neither)."""
    return tuple(m for m in MEDIA_STREAMS if getattr(reader, m, None) is not None)


class DigitDrain:
    """Moves new samples from the readers' ring buffers to the recording (host ``time.monotonic()`` s -> session
    time ``t - t0``); keeps each stream's timestamps strictly increasing, as the session format requires. The
    serial streams of every reader, and the camera frames and audio of those that have them (:func:`media_streams`;
    the drain must run more often than the reader's frame buffer turns over, ``Digit360.image``)."""

    def __init__(self, readers: dict[str, Any], t0: float) -> None:
        self.readers = readers
        self.t0 = t0
        self._streams = {f: STREAMS + media_streams(r) for f, r in readers.items()}
        self._cursors = {(f, s): SampleCursor(t0) for f in readers for s in self._streams[f]}
        self._stalled = dict.fromkeys(readers, False)

    def newest(self) -> dict[str, float]:
        """Each fingertip's newest serial sample time (host s), by ``digit360 <finger>``."""
        return {f"digit360 {finger}": max(float(getattr(reader, s).newest_time()) for s in STREAMS)
                for finger, reader in self.readers.items()}

    def drain(self, append) -> None:
        """Call ``append(stream_name, data (n, ...), timestamps (n,))`` with the samples since the last drain."""
        now = time.monotonic()
        for finger, reader in self.readers.items():
            newest = -np.inf
            for stream in self._streams[finger]:
                buf = getattr(reader, stream)
                t, v = self._cursors[finger, stream].take(buf)
                if len(t):
                    append(f"digit360/{finger}/{stream}", v, t - self.t0)
                if stream in STREAMS:  # a stall is the serial stream's; a frozen camera makes windows stale
                    newest = max(newest, float(buf.newest_time()))
            stalled = now - newest > STALL_S
            if stalled != self._stalled[finger]:
                if stalled:
                    log.warning("digit360 %s: no samples for %.1f s (a gap in its recording; the hand goes on)",
                                finger, now - newest if np.isfinite(newest) else float("inf"))
                else:
                    log.info("digit360 %s: streaming again", finger)
                self._stalled[finger] = stalled
