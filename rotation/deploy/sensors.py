"""Digit 360 fingertips during deploy: parse ``--digit360``, open the readers, move their samples into the recording.

``--digit360`` names one sensor per finger, either positionally in the bus order of the fingers
(``index,middle,ring,thumb``: exactly four entries) or by name for any subset (``thumb=D360-A,index=D360-B``).
An entry is a USB serial number (the data tty is found by it) or, if it starts with ``/``, a tty path (e.g. a
pseudo-terminal). ``sim`` (emulated hands only) starts one emulated sensor per finger.

No policy reads touch yet (the tactile adapter comes in a later issue), so the sensors are recorded only:
their serial streams (accelerometer 400 Hz, pressure 200 Hz) go to ``digit360/<finger>/{imu,pressure}``. A sensor
that stops streaming leaves a gap in its streams and a log line; it does not stop the hand.
"""

from __future__ import annotations

import contextlib
import logging
import os
import time
from typing import Any

import numpy as np

from envs.constants import FINGERS

log = logging.getLogger(__name__)

STALL_S = 0.5
"""A sensor whose newest sample is older than this (s) is reported as stalled (a gap in its recording)."""
STREAMS = ("imu", "pressure")
"""Recorded serial streams per fingertip (session stream ``digit360/<finger>/<stream>``)."""


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
    from rotation.hardware.digit360 import find_digit360_ports

    connected = find_digit360_ports()  # (tty, USB serial) of every Digit 360 plugged in now
    serials = {serial for _, serial in connected}
    missing = []
    for finger, value in real.items():
        if value.startswith("/"):
            if not os.path.exists(value):
                missing.append(f"{finger}={value} (no such device)")
        elif value not in serials:
            missing.append(f"{finger}={value} (no connected Digit 360 has this USB serial)")
    if missing:
        found = ", ".join(sorted(serial or tty for tty, serial in connected)) or "none"
        raise ValueError(f"--digit360: {'; '.join(missing)}. Connected Digit 360 sensors: {found}")


def open_digit360(specs: dict[str, str], stack: contextlib.ExitStack) -> dict[str, Any]:
    """Start one reader per finger (and its emulator for 'sim') inside ``stack``; {finger: Digit360}. A sensor that
    does not open raises :class:`SensorError` naming the finger."""
    if not specs:
        return {}
    from rotation.hardware.digit360 import Digit360, Digit360Config

    readers: dict[str, Any] = {}
    for finger, value in specs.items():
        try:
            if value == "sim":
                from rotation.sim_hardware.digit360_emulator import Digit360Emulator

                cfg = Digit360Config(port=stack.enter_context(Digit360Emulator()).path)
            elif value.startswith("/"):
                cfg = Digit360Config(port=value)
            else:
                cfg = Digit360Config(serial_number=value)
            readers[finger] = stack.enter_context(Digit360(cfg, name=f"digit360-{finger}"))
        except OSError as err:  # pyserial's SerialException is an OSError
            raise SensorError(f"digit360 {finger} ({value}) did not open: {err}") from err
        log.info("digit360 %s: %s", finger, value if value != "sim" else f"emulated on {cfg.port}")
    return readers


class DigitDrain:
    """Moves new samples from the readers' ring buffers to the recording (host ``time.monotonic()`` s -> session
    time ``t - t0``); keeps each stream's timestamps strictly increasing, as the session format requires."""

    def __init__(self, readers: dict[str, Any], t0: float) -> None:
        self.readers = readers
        self.t0 = t0
        self._last = {(f, s): t0 for f in readers for s in STREAMS}
        self._stalled = dict.fromkeys(readers, False)

    def drain(self, append) -> None:
        """Call ``append(stream_name, data (n, ...), timestamps (n,))`` with the samples since the last drain."""
        now = time.monotonic()
        for finger, reader in self.readers.items():
            newest = -np.inf
            for stream in STREAMS:
                t, v = getattr(reader, stream).snapshot()
                key = (finger, stream)
                # a clock re-anchoring may map a sample before an earlier one: keep a strictly increasing series
                keep = t > np.maximum.accumulate(np.concatenate([[self._last[key]], t]))[:-1]
                t, v = t[keep], v[keep]
                if len(t):
                    append(f"digit360/{finger}/{stream}", v, t - self.t0)
                    self._last[key] = float(t[-1])
                newest = max(newest, float(getattr(reader, stream).newest_time()))
            stalled = now - newest > STALL_S
            if stalled != self._stalled[finger]:
                if stalled:
                    log.warning("digit360 %s: no samples for %.1f s (a gap in its recording; the hand goes on)",
                                finger, now - newest if np.isfinite(newest) else float("inf"))
                else:
                    log.info("digit360 %s: streaming again", finger)
                self._stalled[finger] = stalled
