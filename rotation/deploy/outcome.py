"""How a deploy run ends: the fault (or none) that stopped it, whether the motors are confirmed off, and the
summary printed and returned.
"""

from __future__ import annotations

import json
import logging
import sys
from typing import Any

from rotation.deploy.config import Config
from rotation.deploy.hands import OpenedHand

log = logging.getLogger("rotation.deploy")

EXIT_OK, EXIT_FAULT, EXIT_SIGINT, EXIT_SIGTERM = 0, 1, 130, 143
"""Deploy's exit statuses: done, a fault, Ctrl-C, SIGTERM."""


class CriticalRecords(logging.Handler):
    """Collects CRITICAL records of the drivers: each one means a motors-off command could not be sent or was not
    confirmed (rotation.hardware logs exactly those at CRITICAL)."""

    def __init__(self) -> None:
        super().__init__(level=logging.CRITICAL)
        self.messages: list[str] = []

    def emit(self, record: logging.LogRecord) -> None:
        self.messages.append(record.getMessage())


def classify(err: BaseException) -> tuple[str, int, bool]:
    """(fault line, exit status, expected) for whatever ended the run; ``expected`` False = a bug: log a traceback."""
    import can

    from rotation.data.session import SessionError
    from rotation.deploy.policy import PolicyFault
    from rotation.deploy.sensors import SensorError
    from rotation.hardware.hand import HandFault

    if isinstance(err, KeyboardInterrupt):
        return "interrupted (Ctrl-C / SIGINT)", EXIT_SIGINT, True
    if isinstance(err, SystemExit):
        code = err.code if isinstance(err.code, int) else EXIT_FAULT
        return ("terminated (SIGTERM)" if code == EXIT_SIGTERM else f"exit requested (status {code})"), code, True
    if isinstance(err, HandFault):
        return f"hand fault: {err}", EXIT_FAULT, True
    if isinstance(err, PolicyFault):
        return f"policy fault: {err}", EXIT_FAULT, True
    if isinstance(err, SessionError):
        return f"recording failed: {err}", EXIT_FAULT, True
    if isinstance(err, SensorError):
        return f"touch sensor failed: {err}", EXIT_FAULT, True
    if isinstance(err, can.CanError | OSError):
        return f"hand connection failed: {err}", EXIT_FAULT, True
    return f"{type(err).__name__}: {err}", EXIT_FAULT, False


def motors_off_state(opened: OpenedHand | None) -> tuple[bool, bool | None, str | None]:
    """(motors_off, motors_off_confirmed, witness) at the end of a run.

    ``motors_off`` is True only when it is known: the motors were never switched on (confirmed None, witness
    None), or the emulated hand saw them off (witness 'emulator'), or the real hand answered that they are off
    (witness 'hand', rotation.hardware.hand.FeedbackMixin.motors_off_confirmed). A motors-off command that was
    merely sent is not enough: after a lost bus it goes nowhere without an error."""
    driver = opened.driver if opened is not None else None
    if driver is None or not getattr(driver, "motors_switched_on", True):
        return True, None, None
    if opened is not None and opened.emulator is not None:
        confirmed = bool(opened.emulator_saw_motors_off)
        return confirmed, confirmed, "emulator"
    confirmed = getattr(driver, "motors_off_confirmed", None) is True
    return confirmed, confirmed, "hand"


def _driver_stats(opened: OpenedHand | None) -> dict[str, int] | None:
    """The hand driver's counters (cycles, the longest wait for the joints' state, bus errors), None without one."""
    stats = getattr(getattr(opened, "driver", None), "stats", None)
    try:
        return dict(stats()) if callable(stats) else None
    except Exception:  # a driver that never started has nothing to count
        return None


def finish(cfg: Config, hz: float, opened: OpenedHand | None, loop, recorder, critical: CriticalRecords,
            fault: str | None, exit_code: int, wall_s: float, skin=None, readers: dict[str, Any] | None = None,
            sim_faults: list[dict[str, Any]] | None = None) -> dict[str, Any]:
    """Summary dict, final log lines, and the JSON line on stdout. ``readers``: the Digit 360 readers, whose
    counters (frames, bad frames, disconnects, unknown kinds) the summary reports per fingertip; ``sim_faults``:
    the injected faults (rotation.deploy.sim_faults.FaultSchedule.report)."""
    motors_off, confirmed, witness = motors_off_state(opened)
    stats = loop.stats.summary(1.0 / hz) if loop is not None else {
        "steps": 0, "loop_hz": None, "late_steps": 0, "skipped_slots": 0, "held_steps": 0, "rejected_actions": 0,
        "jitter_p50_ms": None, "jitter_p99_ms": None, "max_temperature_c": None, "rotation_rad": None,
        "object_fell": None}
    summary: dict[str, Any] = {
        "hand": cfg.hand, "source": "sim" if cfg.hand.startswith("sim-") else "real", "policy": cfg.policy,
        "control_hz": hz, **stats, "wall_s": wall_s, "fault": fault, "motors_off": motors_off,
        "motors_off_confirmed": confirmed, "motors_off_witness": witness,
        "record": str(recorder.path) if recorder is not None else None, "exit_code": exit_code,
        "skin": None if skin is None else {k: skin.counters[k] for k in ("frames", "skipped", "disconnects")},
        "touch": None if loop is None or loop.touch is None else loop.touch.stats.summary(),
        "digit360": {f: dict(r.counters) for f, r in (readers or {}).items()} or None,
        "hand_bus": _driver_stats(opened),
        "sim_faults": sim_faults or None,
        "model_mismatch_allowed": bool(getattr(cfg, "allow_model_mismatch", False)),
    }
    rot = "" if summary["rotation_rad"] is None else f" (object rotation {summary['rotation_rad']:+.2f} rad)"
    rate = "n/a" if summary["loop_hz"] is None else f"{summary['loop_hz']:.1f} Hz"
    if witness is None:
        off = "motors never switched on"
    elif motors_off:
        off = "motors off (" + ("the emulated hand saw it" if witness == "emulator" else "confirmed by the hand") + ")"
    else:
        msgs = critical.messages or [f"the {'emulated hand' if witness == 'emulator' else 'hand'} did not confirm it"]
        why_not = "; ".join(msgs[:2]) + (f"; and {len(msgs) - 2} more" if len(msgs) > 2 else "")
        off = (f"MOTORS NOT CONFIRMED OFF ({why_not}): the hand may still be driving its joints; SWITCH THE HAND OFF "
               "AT ITS POWER SUPPLY NOW")
    touch = summary["touch"]
    if touch is not None:  # with the rotation: what the adapter did
        rot += (f"; touch: {touch['refreshes']} refreshes (median {touch['refresh_ms_p50'] or 0:.0f} ms), the "
                f"adapter acted {touch['adapter_steps']} steps, the student alone {touch['fallback_steps']}")
    if fault is None:
        log.info("deploy: done after %d steps at %s, late %d, held %d%s -- %s", summary["steps"], rate,
                 summary["late_steps"], summary["held_steps"], rot, off)
    else:
        level = logging.WARNING if exit_code in (EXIT_SIGINT, EXIT_SIGTERM) else logging.ERROR
        log.log(level, "deploy: stopped after %d steps%s: %s -- %s", summary["steps"], rot, fault, off)
    if not motors_off:
        log.critical("deploy: %s", off)
        # also straight to the terminal: whatever the logging setup, the person at the hand must read this
        print(f"rotate deploy: {off}", file=sys.stderr, flush=True)
        summary["exit_code"] = summary["exit_code"] or EXIT_FAULT
    print(json.dumps(summary))
    return summary
