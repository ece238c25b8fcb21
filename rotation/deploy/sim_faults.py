"""Faults injected into an emulated hand and its emulated fingertips while `rotate deploy` runs (``--sim-faults``):
rehearse what a lab's hardware does wrong before it happens on the real hand.

A schedule is a comma-separated list; times are seconds after the control loop started (motors on, recording open):

============================  ==================================================================================
``unplug=FINGER@T``           that fingertip's Digit 360 is unplugged at T (its data tty closes and stays closed):
                              the reader logs the loss and retries; the recording keeps the other fingertips; an
                              adapter that reads the fingertip acts as the student alone from then on
``corrupt=FINGER@T+N``        the fingertip sends N corrupt frames at T: each is dropped, counted and logged
``stall=FINGER@T+D``          the fingertip stops streaming for D s (samples lost): its windows go stale
``lag=FINGER@T+L``            from T on the fingertip delivers each sample L s after its device time (a slower
                              link): its windows end L further in the past and the summary's touch ages grow by L
                              (the emulated fingertips run on the host's clock; past the emulated readers'
                              stale limit, 0.25 s with the newest sample's own age, touch is stale)
``late=T+D``                  the hand's joint feedback stops for D s at T (Allegro: its position stream pauses;
                              LEAP: its status replies are dropped for D s): late control steps; longer than the
                              driver's feedback timeout, the motors go off and the run ends with a fault
``bus-error=T``               the hand reports an error over its bus at T (Allegro: a V5 error frame of motor 0,
                              overload; LEAP: servo 0's hardware error status, overload): the driver switches
                              the motors off and the run ends with a fault; the recording is kept, marked
                              incomplete
============================  ==================================================================================

FINGER is one of index, middle, ring, thumb (an emulated one: ``--digit360 sim``, or an adapter policy's). The
summary's ``sim_faults`` lists each fault with the loop time it was applied at (or why it was not).
"""

from __future__ import annotations

import logging
import math
import threading
import time
from dataclasses import dataclass
from typing import Any

from envs.constants import FINGERS

log = logging.getLogger("rotation.deploy")

KINDS = ("unplug", "corrupt", "stall", "lag", "late", "bus-error")
SENSOR_KINDS = ("unplug", "corrupt", "stall", "lag")
"""Faults of a fingertip (FINGER@...); the others are the hand's."""
ALLEGRO_ERROR = (0, 0x20)
"""(motor, bits) of the injected Allegro V5 error frame (0x20: overload, rotation.hardware.allegro.protocol)."""
LEAP_OVERLOAD = 0x20
"""Dynamixel Hardware Error Status bit 5: overload (rotation.hardware.leap.dynamixel_protocol)."""
FORM = ("e.g. 'unplug=thumb@4,corrupt=index@2+5,stall=ring@3+0.5,late=6+0.08,bus-error=9' (times in s after the "
        "loop started)")


@dataclass(frozen=True)
class Fault:
    """One scheduled fault."""

    kind: str
    at_s: float
    finger: str | None = None
    amount: float = 0.0
    """corrupt: frames; stall, lag, late: seconds; otherwise unused."""

    def describe(self) -> str:
        where = f"{self.finger} fingertip " if self.finger else "hand "
        what = {"unplug": "unplugged", "corrupt": f"{self.amount:g} corrupt frames",
                "stall": f"stalls {self.amount:g} s", "lag": f"delivers its samples {self.amount:g} s late",
                "late": f"feedback paused {self.amount:g} s",
                "bus-error": "error reported on the bus"}[self.kind]
        return f"{where}{what} at {self.at_s:g} s"


def _number(text: str, what: str, spec: str) -> float:
    try:
        value = float(text)
    except ValueError:
        raise ValueError(f"sim_faults: {what} {text!r} of {spec!r} is not a number; {FORM}") from None
    if not (math.isfinite(value) and value >= 0):
        raise ValueError(f"sim_faults: {what} of {spec!r} must be a finite number >= 0, got {text}")
    return value


def parse_sim_faults(spec: str) -> tuple[Fault, ...]:
    """``--sim-faults`` -> the faults in time order; ValueError naming ``sim_faults`` and the bad item."""
    faults = []
    for item in (t.strip() for t in spec.split(",")):
        if not item:
            continue
        kind, sep, rest = item.partition("=")
        kind = kind.strip()
        if not sep or kind not in KINDS:
            raise ValueError(f"sim_faults: cannot read {item!r}; the kinds are {', '.join(KINDS)}; {FORM}")
        finger = None
        if kind in SENSOR_KINDS:
            finger, at, rest = rest.partition("@")
            finger = finger.strip()
            if not at or finger not in FINGERS:
                raise ValueError(f"sim_faults: {item!r} must name a fingertip ({', '.join(FINGERS)}) as "
                                 f"{kind}=FINGER@T; {FORM}")
        when, plus, amount = rest.partition("+")
        needs_amount = kind in ("corrupt", "stall", "lag", "late")
        if needs_amount != bool(plus):
            tail = ("+N" if kind == "corrupt" else "+D") if needs_amount else ""
            form = f"{kind}={'FINGER@' if finger else ''}T{tail}"
            raise ValueError(f"sim_faults: {item!r} must be written {form}; {FORM}")
        at_s = _number(when.strip(), "the time", item)
        value = _number(amount.strip(), "the amount", item) if plus else 0.0
        if needs_amount and value <= 0:
            raise ValueError(f"sim_faults: the amount of {item!r} must be > 0")
        if kind == "corrupt" and value != int(value):
            raise ValueError(f"sim_faults: {item!r}: the number of corrupt frames must be a whole number")
        faults.append(Fault(kind, at_s, finger, value))
    return tuple(sorted(faults, key=lambda f: f.at_s))


def check_sim_faults(faults: tuple[Fault, ...], emulated: bool, sim_fingers: tuple[str, ...]) -> None:
    """ValueError when a schedule cannot be applied: a real hand, or a fingertip that is not emulated."""
    if not faults:
        return
    if not emulated:
        raise ValueError("sim_faults: faults are injected into emulated hardware only (--hand sim-allegro/sim-leap)")
    lacking = sorted({f.finger for f in faults if f.finger is not None and f.finger not in sim_fingers})
    if lacking:
        raise ValueError(f"sim_faults: the fingertip(s) {', '.join(lacking)} are not emulated in this run (give "
                         "--digit360 sim, or an adapter policy that reads them)")


class FaultSchedule:
    """Applies the faults on a timer thread once :meth:`start` is called (the loop's start)."""

    def __init__(self, faults: tuple[Fault, ...], hand_emulator: Any, sensor_emulators: dict[str, Any]) -> None:
        self.faults = faults
        self.hand = hand_emulator
        self.sensors = sensor_emulators
        self.applied: list[dict[str, Any]] = []
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        self._t0 = 0.0

    def start(self) -> None:
        if not self.faults:
            return
        self._t0 = time.monotonic()
        self._thread = threading.Thread(target=self._run, name="sim-faults", daemon=True)
        self._thread.start()

    def stop(self) -> None:
        self._stop.set()
        if self._thread is not None:
            self._thread.join(timeout=2.0)

    def report(self) -> list[dict[str, Any]]:
        """Each fault: what, when it was due, when it was applied (None: the run had ended before)."""
        done = {id(a["fault"]): a for a in self.applied}
        return [{"fault": f.describe(), "due_s": f.at_s,
                 "applied_s": done[id(f)]["at_s"] if id(f) in done else None} for f in self.faults]

    def _run(self) -> None:
        pending = [(f.at_s, i, f, None) for i, f in enumerate(self.faults)]  # (due s, order, fault, undo or None)
        while pending:
            pending.sort(key=lambda e: (e[0], e[1]))
            due, order, fault, undo = pending.pop(0)
            if self._stop.wait(max(0.0, self._t0 + due - time.monotonic())):
                return
            if undo is not None:
                undo()
                continue
            try:
                later = self._apply(fault)
            except Exception as err:  # a fault that cannot be applied must not kill the run it rehearses
                log.error("sim-faults: could not apply '%s': %s", fault.describe(), err)
                continue
            at = time.monotonic() - self._t0
            self.applied.append({"fault": fault, "at_s": round(at, 3)})
            log.warning("sim-faults: %s (applied at %.2f s)", fault.describe(), at)
            if later is not None:
                pending.append((at + fault.amount, order, fault, later))

    def _apply(self, fault: Fault):
        """Apply ``fault``; returns what ends it ``fault.amount`` s later, or None."""
        if fault.finger is not None:
            emu = self.sensors[fault.finger]
            if fault.kind == "unplug":
                emu.disconnect()
            elif fault.kind == "corrupt":
                emu.faults.corrupt_frames += int(fault.amount)
            elif fault.kind == "lag":
                emu.faults.latency_s = fault.amount
            else:
                emu.faults.pause(fault.amount)
            return None
        faults = self.hand.faults
        allegro = hasattr(faults, "stream_pause_s")
        if fault.kind == "late":
            if allegro:
                faults.stream_pause_s = fault.amount
                return None
            faults.drop_replies = 1 << 30  # LEAP: every status reply dropped until the pause ends

            def resume() -> None:
                faults.drop_replies = 0
            return resume
        if allegro:
            faults.error_frame = ALLEGRO_ERROR
        else:
            faults.hardware_error[0] = LEAP_OVERLOAD
        return None
