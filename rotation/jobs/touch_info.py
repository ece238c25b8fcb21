"""List the attached Digit 360 fingertip sensors, or read one for a few seconds and report what each stream gave.

    rotate touch-info                                    # serial, data tty, camera and microphones of each sensor
    rotate touch-info --digit360 /dev/ttyACM0 --seconds 2 [--json]
    rotate touch-info --digit360 D360-XXXX --media       # also its camera and microphones (the hardware extra)
    rotate touch-info --digit360 sim                     # an emulated sensor on a pseudo-terminal, the real reader

A sensor is found by its data tty's USB identity (2833:4001) and its camera and microphones on its own USB hub
(docs/reference/hardware.md section 4). Reading opens the sensor with the deploy reader
(rotation.hardware.digit360.reader), by tty path (an emulator's pty too) or by USB serial number, and reports per
stream the samples seen, the measured rate and the last sample in physical units (acceleration g, angular rate deg/s,
pressure hPa, temperature degrees C: rotation.hardware.digit360.protocol), the firmware version, and the reader's
counters. Times are host ``time.monotonic()`` seconds, the clock deploy stamps the joints with: the reader maps the
device's millisecond clock onto it. A rate counts the samples after the first quarter second (a port that was not
read holds a backlog of old frames) over the span of their times. Read-only: nothing is sent to the sensor.
"""

from __future__ import annotations

import dataclasses
import json
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from envs.errors import RequestRefused
from rotation.configs import to_jsonable

STREAMS = {
    "data tty": "USB CDC 2833:4001, COBS-framed protobuf: accelerometer (g, 400 Hz in Sparsh-X), pressure (hPa, "
                "200 Hz in Sparsh-X) and temperature (C), and the other kinds the firmware sends (gyroscope deg/s, "
                "gas / humidity, system status)",
    "camera": "UVC 2833:b015: 1280x720 asked for, 30 fps; read as 224x224 RGB centre crops",
    "microphones": "USB audio, ALSA hw:N,0: 2 channels, 48 kHz, int16",
}
"""What each function of a Digit 360 gives (docs/reference/hardware.md section 4; rates: docs/reference/sparsh.md)."""
CLOCK = ("host time.monotonic() s, the clock deploy stamps the joints with; the device's millisecond clock is mapped "
         "onto it")
WARMUP_S = 0.25


@dataclass(frozen=True)
class Config:
    digit360: str = ""
    """Sensor to read: its data tty (/dev/ttyACM0, an emulator's pty), its USB serial number, or 'sim' (an emulated
    sensor on a pseudo-terminal, read by the real reader); empty: list the attached sensors."""
    seconds: float = 2.0
    """How long to read the sensor (s, at most 600)."""
    json: bool = False
    """Print one JSON object instead of a table."""
    media: bool = False
    """Also open the camera and microphones on the sensor's USB hub and report their format and rates (OpenCV and
    sounddevice: pip install 'tactile-rotation[hardware]')."""

    def __post_init__(self) -> None:
        from envs.validation import check_number, check_types

        check_types(self)
        check_number("seconds", self.seconds, 0.0, 600.0, low_open=True, unit="s")
        if self.media and self.digit360 in ("", "sim"):
            raise ValueError("media: name the real sensor whose camera and microphones to open with --digit360 "
                             "(an emulated sensor has neither)")


# ------------------------------------------------------------------------------------------ listing
def list_sensors(sysfs: str | Path = "/sys") -> list[dict[str, Any]]:
    """Every attached Digit 360: USB serial, data tty, camera node and microphones (None where not found)."""
    from rotation.hardware.digit360 import discovery

    rows = []
    for tty, serial_number in discovery.find_digit360_ports():
        found = discovery.find_digit360_devices(tty, sysfs)
        rows.append({"serial": serial_number, "data_tty": tty, "camera": found.camera, "microphones": found.audio})
    return rows


def _attached() -> str:
    rows = list_sensors()
    return ("attached Digit 360 sensors: " + ", ".join(f"{r['serial'] or '?'} on {r['data_tty']}" for r in rows)
            if rows else "no Digit 360 is attached")


def format_list(rows: list[dict[str, Any]]) -> str:
    if not rows:
        return ("no Digit 360 attached: no USB serial port is a Digit 360's data tty (USB 2833:4001). Check the cable "
                "and `lsusb -d 2833:`; an emulated sensor is read with --digit360 PTY.")
    lines = [f"{len(rows)} Digit 360 sensor(s) attached",
             f"{'serial':<18s} {'data tty':<14s} {'camera':<13s} microphones"]
    lines += [f"{r['serial'] or '?':<18s} {r['data_tty']:<14s} {r['camera'] or '-':<13s} {r['microphones'] or '-'}"
              for r in rows]
    lines += ["streams:"] + [f"  {k}: {v}" for k, v in STREAMS.items()]
    return "\n".join(lines)


# ------------------------------------------------------------------------------------------ reading
def _marks(d) -> dict[str, tuple[int, float]]:
    """Stream -> (samples so far, time of the newest)."""
    out = {name: (d.samples.get(name, 0), t) for name, (t, _) in list(d.latest.items())}
    for name, buf in (("camera", d.image), ("audio", d.audio)):
        if buf is not None and buf.written:
            out[name] = (buf.written, buf.newest_time())
    return out


def _rate(before: tuple[int, float] | None, after: tuple[int, float]) -> float | None:
    if before is None or after[0] <= before[0] or after[1] <= before[1]:
        return None
    return (after[0] - before[0]) / (after[1] - before[1])


def _media_last(d, name: str) -> dict[str, Any]:
    if name == "camera":
        _, frame = d.image.last(1)
        fmt = d.camera.format
        return {"mean_rgb": [round(float(c), 1) for c in frame[0].reshape(-1, 3).mean(axis=0)],
                "format": None if fmt is None else {"width": fmt.width, "height": fmt.height, "fps": fmt.fps,
                                                    "fourcc": fmt.fourcc, "backend": fmt.backend},
                "device": d.cfg.camera}
    _, block = d.audio.last(4800)
    mics = d.microphones
    return {"rms_counts": [round(float(c), 1) for c in np.sqrt(np.mean(block.astype(np.float64) ** 2, axis=0))],
            "device": d.cfg.audio_device, "name": mics.info.get("name"),
            "input_channels": mics.info.get("max_input_channels"), "blocks_with_status": mics.problems}


def _open_spec(cfg: Config) -> tuple[str, str | None]:
    """(data tty, USB serial or None) of the sensor ``cfg.digit360`` names; ValueError naming what is attached."""
    from rotation.hardware.digit360 import discovery

    if cfg.digit360.startswith("/"):
        if not Path(cfg.digit360).exists():
            raise ValueError(f"digit360: {cfg.digit360} does not exist; {_attached()}")
        return cfg.digit360, None
    found = discovery.find_digit360_ports(cfg.digit360)
    if not found:
        raise ValueError(f"digit360: no attached Digit 360 has USB serial {cfg.digit360!r}; {_attached()}")
    return found[0][0], cfg.digit360


def read_sensor(cfg: Config) -> dict[str, Any]:
    """Open the sensor, read it for ``cfg.seconds``; the report (see the module docstring)."""
    import serial

    from rotation.hardware.digit360 import discovery
    from rotation.hardware.digit360.reader import Digit360, Digit360Config

    if cfg.digit360 == "sim":
        from rotation.sim_hardware.digit360_emulator import Digit360Emulator

        with Digit360Emulator() as emu:
            return read_sensor(dataclasses.replace(cfg, digit360=emu.path))
    port, usb_serial = _open_spec(cfg)
    devices = discovery.Digit360Devices()
    if cfg.media:
        devices = discovery.find_digit360_devices(port)
        if not (devices.camera or devices.audio):
            raise ValueError(f"media: no camera or microphones on the USB hub of {port} (a Digit 360's own data tty "
                             "has them beside it; a pseudo-terminal or another maker's tty has none)")
    reader = Digit360(Digit360Config(port=port, camera=devices.camera, audio_device=devices.audio))
    warmup = min(WARMUP_S, cfg.seconds / 4)
    try:
        with reader as d:
            time.sleep(warmup)
            before = _marks(d)
            time.sleep(cfg.seconds - warmup)
            after = _marks(d)
            last = {name: _media_last(d, name) for name in ("camera", "audio") if name in after}
    except serial.SerialException as err:  # pyserial's: the tty did not open or could not be configured
        raise OSError(f"digit360: {port} did not open as a serial port: {' '.join(str(err).split())}") from err
    except ImportError as err:  # the hardware extra is missing (--media)
        raise RequestRefused(str(err)) from err
    c = reader.counters
    if not after:
        what = (f"{c['bad_frames']} undecodable frame(s) and no Digit 360 message" if c["bad_frames"]
                else "no Digit 360 message")
        raise OSError(f"digit360: {port} sent {what} in {cfg.seconds:g} s; is it a Digit 360's data tty, and is the "
                      f"sensor powered? ({_attached()})")
    streams = {}
    for name in sorted(after):
        value = last[name] if name in last else reader.latest[name][1]
        rate = _rate(before.get(name), after[name])
        streams[name] = {"samples": after[name][0], "rate_hz": None if rate is None else round(rate, 2),
                         "t_last": after[name][1], "last": to_jsonable(value)}
    return {"sensor": port, "usb_serial": usb_serial, "seconds": cfg.seconds, "firmware": reader.version or None,
            "time": CLOCK, "streams": streams, "imu_timing": _imu_timing(reader),
            "counters": {"frames": c["frames"], "bad_frames": c["bad_frames"], "unknown_kinds": c["unknown"],
                         "disconnects": c["disconnects"]}}


def _imu_timing(reader: Any) -> str:
    """How the windowed IMU samples are timed (rotation.hardware.digit360.fine_clock): by the sensor time stamp
    once it proves to be a finer clock, else by the device's milliseconds (what a lab's first sensor tells)."""
    ticks = reader._fine.ticks_per_ms
    if ticks is None:
        return "device milliseconds (the sensor time stamp ts_ght is not a finer clock in step with them, or not yet)"
    return f"sensor time stamp ts_ght, {ticks:.3f} ticks per ms ({1e3 / ticks:.3f} us per tick)"


def _text(value: Any) -> str:
    if isinstance(value, dict):
        return ", ".join(f"{k} {_text(v)}" for k, v in value.items() if v is not None)
    if isinstance(value, list):
        return f"[{len(value)} values]" if len(value) > 4 else "(" + ", ".join(_text(v) for v in value) + ")"
    if isinstance(value, float):
        return f"{value:.2f}" if abs(value) >= 100 else f"{value:.4f}"
    return str(value)


def format_report(report: dict[str, Any]) -> str:
    lines = [f"Digit 360 {report['sensor']} (USB serial {report['usb_serial'] or '-'}), read for "
             f"{report['seconds']:g} s; firmware {report['firmware'] or 'not reported'}",
             f"times: {report['time']}", f"IMU sample times: {report['imu_timing']}",
             f"{'stream':<12s} {'samples':>8s} {'rate (Hz)':>10s}  last sample"]
    for name, s in report["streams"].items():
        rate = "-" if s["rate_hz"] is None else f"{s['rate_hz']:.1f}"
        lines.append(f"{name:<12s} {s['samples']:>8d} {rate:>10s}  {_text(s['last'])}")
    c = report["counters"]
    lines.append(f"frames {c['frames']}, bad frames {c['bad_frames']}, unknown kinds {c['unknown_kinds']}, "
                 f"disconnects {c['disconnects']}")
    return "\n".join(lines)


def run(cfg: Config) -> dict[str, Any]:
    if not cfg.digit360:
        rows = list_sensors()
        print(json.dumps({"sensors": rows, "streams": STREAMS}) if cfg.json else format_list(rows))
        return {"sensors": rows}
    report = read_sensor(cfg)
    print(json.dumps(report) if cfg.json else format_report(report))
    return report
