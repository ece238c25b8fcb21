"""Allegro Hand V4/V5 driver over CAN: vendor start-up/shut-down, host-side PD at the hand's 333 Hz stream.

Usage::

    with AllegroHand("socketcan:can0") as hand:
        hand.set_targets(q)          # (16,) rad, bus order; passes the safety layer
        state = hand.read_state()    # q, qdot, torque, target, t_host

One background thread owns the receive side: every complete cycle of four FINGER_POSE frames (the hand streams
them every ``period_ms`` after SET_PERIOD) runs one PD step ``tau = kp (target - q) - kd qdot`` (normalized
torque units), clamps it per joint and sends four SET_TORQUE frames, as the vendor loop does
(docs/reference/hardware.md section 1). Replies to requests (HAND_INFO, SERIAL, TEMPERATURE) are routed to waiters.

Fault reactions (each logged at ERROR, then every public call raises :class:`HandFault`):

- no complete position cycle for ``feedback_timeout_s`` (hand off, bus-off, unplugged): motors off;
- ``max_send_errors`` consecutive failed sends, or ``max_recv_errors`` consecutive receive errors: motors off;
  a single failure is logged and the next cycle retries;
- a V5 error frame (overheating, overload, ...): motors off;
- a lost finger frame: that cycle is skipped (counted in :meth:`stats`), the next complete one proceeds
  (cycles start at the index finger's frame, which the hand sends first).

A request without reply is retried ``request_retries`` times, then :class:`HandNotResponding` is raised.
"""

from __future__ import annotations

import contextlib
import logging
import threading
import time
from collections import deque

import can
import numpy as np

from rotation.hardware.allegro import protocol as ap
from rotation.hardware.allegro.can_bus import open_bus
from rotation.hardware.allegro.control import AllegroConfig, CycleAssembler, VelocityFilter, pd_torque
from rotation.hardware.hand import NUM_JOINTS, FeedbackMixin, HandFault, HandInfo, HandNotResponding, HandState
from rotation.hardware.safety import SafetyLayer, motors_off_on_exit

log = logging.getLogger("rotation.hardware.allegro")  # the device's logger (messages name the device)
__all__ = ["AllegroConfig", "AllegroHand"]


class AllegroHand(FeedbackMixin):
    """The Allegro hand as a context manager (see the module docstring). Implements ``rotation.hardware.Hand``."""

    torque_unit = "normalized torque (V4: PWM/1200, V5: mA/1430), commanded"

    def __init__(self, bus: can.BusABC | str, cfg: AllegroConfig | None = None, name: str = "allegro") -> None:
        self.cfg = cfg or AllegroConfig()
        self.name = name
        self._spec = bus if isinstance(bus, str) else None
        self._bus: can.BusABC | None = None if isinstance(bus, str) else bus
        self._owns_bus = isinstance(bus, str)
        self.version: ap.ProtocolVersion | None = None
        self._hand_info: ap.AllegroInfo | None = None
        self._serial = ""
        self._safety: SafetyLayer | None = None
        self._exit = contextlib.ExitStack()
        self._send_lock = threading.RLock()
        self._lock = threading.Lock()  # state, waiters, counters
        self._thread: threading.Thread | None = None
        self._stop = threading.Event()
        self._off_requested = threading.Event()
        self._closing = threading.Event()
        self._first_cycle = threading.Event()
        self._waiters: dict[int, list] = {}
        self._servo_on = False
        self._fault: HandFault | None = None
        # loop state (owned by the thread)
        self._cycle = CycleAssembler()
        self._velocity = VelocityFilter(self.cfg.velocity_smoothing, 1e-3 * self.cfg.period_ms)
        self._t_cycle = 0.0
        self._seq = 0
        self._send_errors = 0
        self._recv_errors = 0
        self._temperatures = np.full(NUM_JOINTS, np.nan)
        self._state: HandState | None = None
        self._counters = {"cycles": 0, "incomplete_cycles": 0, "send_errors": 0, "recv_errors": 0,
                          "longest_gap_ms": 0}
        self._cycle_times: deque[float] = deque(maxlen=200_000)

    # ------------------------------------------------------------------ lifecycle
    def __enter__(self) -> AllegroHand:
        try:
            if self._bus is None:
                self._bus = open_bus(self._spec)  # type: ignore[arg-type]
            self._startup()
        except BaseException:
            self._shutdown()
            raise
        return self

    def __exit__(self, *exc: object) -> None:
        self._shutdown()

    def _startup(self) -> None:
        cfg = self.cfg
        self._flush()
        self._thread = threading.Thread(target=self._run, name=f"{self.name}-pd", daemon=True)
        self._thread.start()
        self._send_checked(ap.Msg.SYSTEM_OFF)
        self._hand_info = ap.decode_hand_info(self._request(ap.Msg.HAND_INFO))
        self.version = ap.version_for(self._hand_info, cfg.protocol)
        hw_limits = np.asarray(self.version.effort_limits, dtype=np.float64) / self.version.effort_per_torque
        self._safety = SafetyLayer(cfg.safety, hw_limits, name=self.name)
        self._serial = ap.decode_serial(self._request(ap.Msg.SERIAL))
        log.info("%s: hw 0x%04x fw 0x%04x serial %s protocol %s", self.name, self._hand_info.hardware,
                 self._hand_info.firmware, self._serial, self.version.name)
        self._send_checked(ap.Msg.SET_PERIOD, ap.encode_period(cfg.period_ms, 0, 0))
        if not self._first_cycle.wait(max(cfg.reply_timeout_s, 0.02 * cfg.period_ms) * cfg.request_retries):
            raise HandNotResponding(f"{self.name}: no position stream after SET_PERIOD {cfg.period_ms} ms")
        self._raise_if_fault()
        if cfg.enable_motors:
            self._exit.enter_context(motors_off_on_exit(self._motors_off, self._off_requested.set, self.name))
            with self._send_lock:
                self._motors_switched_on = True  # before the send: the frame may reach the hand even if it raises
                self._send_checked(ap.Msg.SYSTEM_ON)
                self._servo_on = True
            log.info("%s: servo on, holding the current pose", self.name)

    def _shutdown(self) -> None:
        try:
            self._exit.close()  # motors off (once) and signal handlers restored
            if self._bus is not None and self._thread is not None:
                self._motors_off("shutdown")
                self._closing.set()  # the stream stops now: its silence is no fault
                with contextlib.suppress(can.CanError, OSError):
                    self._send(ap.wire_id(ap.Msg.SET_PERIOD, self.cfg.hand_id), ap.encode_period(0, 0, 0))
                if self._motors_switched_on:  # the receive thread still runs: it routes the hand's answer
                    self._off_confirmed = self._confirm_motors_off()
        finally:
            self._stop.set()
            if self._thread is not None:
                self._thread.join(timeout=1.0)
                if self._thread.is_alive():
                    log.error("%s: receive thread did not stop within 1 s", self.name)
                self._thread = None
            if self._owns_bus and self._bus is not None:
                self._bus.shutdown()
                self._bus = None

    def _motors_off(self, reason: str = "") -> None:
        """Zero torques on every finger, then SYSTEM_OFF; each send failure is logged, the rest still sent."""
        if self._bus is None:
            return
        with self._send_lock:
            self._servo_on = False
            for f in range(ap.NUM_FINGERS):
                try:
                    self._send(ap.wire_id(ap.Msg.SET_TORQUE, self.cfg.hand_id, f), bytes(8))
                except (can.CanError, OSError) as err:
                    log.error("%s: could not send zero torque to finger %d: %s", self.name, f, err)
            try:
                self._send(ap.wire_id(ap.Msg.SYSTEM_OFF, self.cfg.hand_id))
            except (can.CanError, OSError) as err:
                log.critical("%s: could not send SYSTEM_OFF (%s): %s; switch the hand off at its power supply",
                             self.name, reason, err)

    def _confirm_motors_off(self) -> bool:
        """Ask the hand whether its servo is off (HAND_INFO status bit 0), sending SYSTEM_OFF again while it says
        on. Only the hand's answer counts: on a bus in BUS-OFF or with the cable out, SYSTEM_OFF "succeeds" into
        the adapter's queue and never arrives. Works after a fault too (the request bypasses the fault check).
        False, logged at CRITICAL, when no answer said 'off' within ``request_retries`` requests."""
        arb = ap.wire_id(ap.Msg.HAND_INFO, self.cfg.hand_id)
        for attempt in range(1, self.cfg.request_retries + 1):
            waiter = self._ask(arb, "the HAND_INFO request (is the servo off?)", attempt)
            # a fault wakes every waiter without data: only a reply with data is an answer
            if waiter[0].is_set() and waiter[1]:
                try:
                    status = ap.decode_hand_info(waiter[1]).status
                except ValueError as err:
                    log.error("%s: unreadable HAND_INFO reply: %s", self.name, err)
                    continue
                if not status & ap.STATUS_SERVO_ON:
                    log.info("%s: the hand confirms its servo is off", self.name)
                    return True
                # seen once, with the emulated hand on a busy machine, before the repeat switched it off: a warning
                # per repeat; a hand that never says off is CRITICAL below
                log.warning("%s: the hand still reports its servo on (request %d of %d); sending SYSTEM_OFF again",
                            self.name, attempt, self.cfg.request_retries)
                with contextlib.suppress(can.CanError, OSError):
                    self._send(ap.wire_id(ap.Msg.SYSTEM_OFF, self.cfg.hand_id))
        with self._lock:
            self._waiters.pop(arb, None)
        log.critical("%s: the hand did not confirm that its servo is off (%d requests); its motors may still be on: "
                     "switch the hand off at its power supply", self.name, self.cfg.request_retries)
        return False

    # ------------------------------------------------------------------ public API
    def set_targets(self, q: np.ndarray) -> bool:
        """Joint targets (16,) rad, bus order, Allegro frame. False if rejected (NaN/inf; the last target held)."""
        self._raise_if_fault()
        if self._safety is None:
            raise RuntimeError(f"{self.name}: use the hand inside `with` before commanding it")
        return self._safety.accept(q, time.monotonic())

    def info(self) -> HandInfo:
        """Firmware/hardware versions, serial and temperatures (requests HAND_INFO and TEMPERATURE now)."""
        self._raise_if_fault()
        hand_info = ap.decode_hand_info(self._request(ap.Msg.HAND_INFO))
        for f in range(ap.NUM_FINGERS):
            self._temperatures[4 * f: 4 * f + 4] = ap.decode_temperatures(self._request(ap.Msg.TEMPERATURE, f))
        if hand_info.status & (ap.STATUS_TEMPERATURE_FAULT | ap.STATUS_COMM_FAULT):
            log.warning("%s: hand reports status 0x%02x (bit1 temperature fault, bit2 internal comm fault)",
                        self.name, hand_info.status)
        assert self.version is not None
        return HandInfo(
            kind=f"allegro-{self.version.name}",
            firmware=f"0x{hand_info.firmware:04x}",
            hardware=f"0x{hand_info.hardware:04x}",
            serial=self._serial,
            temperatures=self._temperatures.copy(),
            extra={"right_hand": hand_info.right_hand, "board_temperature_c": hand_info.temperature_c,
                   "status": hand_info.status, "servo_on": bool(hand_info.status & ap.STATUS_SERVO_ON)},
        )

    def stats(self) -> dict[str, int]:
        """Counters since start: cycles, the longest time between two complete position cycles (longest_gap_ms),
        incomplete_cycles, send_errors, recv_errors, rejected_targets."""
        with self._lock:
            out = dict(self._counters)
        out["rejected_targets"] = self._safety.rejected if self._safety else 0
        return out

    def cycle_times(self) -> np.ndarray:
        """Host monotonic times (s) of the most recent PD cycles (for rate/jitter measurements)."""
        with self._lock:
            return np.array(self._cycle_times, dtype=np.float64)

    # ------------------------------------------------------------------ bus helpers
    def _send(self, arbitration_id: int, data: bytes = b"", remote: bool = False) -> None:
        msg = can.Message(arbitration_id=arbitration_id, is_extended_id=False, is_remote_frame=remote,
                          data=None if remote else data, dlc=0 if remote else len(data))
        with self._send_lock:
            self._bus.send(msg, timeout=self.cfg.send_timeout_s)  # type: ignore[union-attr]

    def _send_checked(self, msg: ap.Msg, data: bytes = b"") -> None:
        try:
            self._send(ap.wire_id(msg, self.cfg.hand_id), data)
        except (can.CanError, OSError) as err:
            raise HandFault(f"{self.name}: could not send {msg.name}: {err}") from err

    def _flush(self) -> None:
        """Drop frames queued before start-up (bounded, so a babbling bus cannot hang us)."""
        for _ in range(10_000):
            if self._bus.recv(timeout=0.0) is None:  # type: ignore[union-attr]
                return

    def _ask(self, arb: int, what: str, attempt: int) -> list:
        """Send one remote frame on ``arb`` and wait up to reply_timeout_s for the data frame on the same ID.
        Returns the waiter ``[event, data]``: the event is set by a reply (data) or by a fault (no data)."""
        waiter: list = [threading.Event(), b""]
        with self._lock:
            self._waiters[arb] = waiter
        try:
            self._send(arb, remote=True)
        except (can.CanError, OSError) as err:
            log.error("%s: could not send %s (attempt %d): %s", self.name, what, attempt, err)
        waiter[0].wait(self.cfg.reply_timeout_s)
        return waiter

    def _request(self, msg: ap.Msg, finger: int = 0) -> bytes:
        """RTR ``msg`` and wait for the data frame on the same ID; retried, then HandNotResponding."""
        arb = ap.wire_id(msg, self.cfg.hand_id, finger)
        for attempt in range(1, self.cfg.request_retries + 1):
            waiter = self._ask(arb, f"{msg.name} request", attempt)
            self._raise_if_fault()
            if waiter[0].is_set():
                return waiter[1]
            log.warning("%s: no reply to %s (finger %d) within %.0f ms, attempt %d/%d", self.name, msg.name,
                        finger, 1e3 * self.cfg.reply_timeout_s, attempt, self.cfg.request_retries)
        with self._lock:
            self._waiters.pop(arb, None)
        raise HandNotResponding(f"{self.name}: no reply to {msg.name} after {self.cfg.request_retries} attempts "
                                "(hand powered? CAN cabled and terminated? bitrate 1 Mbit/s?)")

    # ------------------------------------------------------------------ receive / PD thread
    def _run(self) -> None:
        try:
            while not self._stop.is_set():
                try:
                    msg = self._bus.recv(timeout=0.005)  # type: ignore[union-attr]
                except (can.CanError, OSError, ValueError) as err:  # adapter error or an unparsable SLCAN line
                    self._recv_errors += 1
                    with self._lock:
                        self._counters["recv_errors"] += 1
                    log.error("%s: receive error %d/%d: %s", self.name, self._recv_errors,
                              self.cfg.max_recv_errors, err)
                    if self._recv_errors >= self.cfg.max_recv_errors:
                        self._set_fault(f"{self._recv_errors} consecutive receive errors", err)
                    time.sleep(0.001)
                    continue
                now = time.monotonic()
                if self._off_requested.is_set() and self._fault is None:
                    self._set_fault("motors off requested by a signal")
                if msg is not None:
                    self._recv_errors = 0
                    self._dispatch(msg, now)
                if self._first_cycle.is_set() and self._fault is None and not self._closing.is_set():
                    stall = now - self._t_cycle
                    if stall > self.cfg.feedback_timeout_s:
                        limit = 1e3 * self.cfg.feedback_timeout_s
                        self._set_fault(f"no complete position cycle for {1e3 * stall:.0f} ms (> {limit:.0f} ms): "
                                        "hand off, bus-off or unplugged")
        except Exception as err:  # never die silently with the motors on
            log.exception("%s: receive thread crashed", self.name)
            self._set_fault("receive thread crashed", err)

    def _set_fault(self, reason: str, cause: BaseException | None = None) -> None:
        if self._fault is not None:
            return
        fault = HandFault(f"{self.name}: {reason}; switching the motors off")
        fault.__cause__ = cause
        self._fault = fault
        log.error("%s: FAULT: %s; switching motors off", self.name, reason)
        self._motors_off(reason)
        with self._lock:  # wake any request waiting for a reply
            for waiter in self._waiters.values():
                waiter[0].set()

    def _dispatch(self, msg: can.Message, now: float) -> None:
        if msg.is_remote_frame or msg.is_error_frame or msg.is_extended_id:
            return
        msg_id, hand_id = ap.split_wire_id(msg.arbitration_id)
        if hand_id != self.cfg.hand_id:
            return
        finger = ap.finger_of(msg_id, ap.Msg.FINGER_POSE)
        if finger is not None and self._safety is not None:
            self._on_position(finger, bytes(msg.data), now)
            return
        if msg_id == ap.Msg.V5_ERROR:
            motor, bits, names = ap.decode_v5_error(bytes(msg.data))
            self._set_fault(f"hand error frame: motor {motor} bits 0x{bits:02x} ({', '.join(names) or 'unknown'})")
            return
        with self._lock:
            waiter = self._waiters.pop(msg.arbitration_id, None)
        if waiter is not None:
            waiter[1] = bytes(msg.data)
            waiter[0].set()

    def _on_position(self, finger: int, data: bytes, now: float) -> None:
        assert self.version is not None
        try:
            q4 = ap.decode_positions(data, self.version)
        except ValueError as err:
            log.error("%s: bad position frame from finger %d: %s", self.name, finger, err)
            return
        before = self._cycle.incomplete
        q = self._cycle.add(finger, q4)
        if self._cycle.incomplete != before:
            with self._lock:
                self._counters["incomplete_cycles"] = n = self._cycle.incomplete
            if n == 1 or n % 1000 == 0:
                log.warning("%s: incomplete position cycle (%d so far); skipped", self.name, n)
        if q is not None:
            self._pd_cycle(q, now)

    def _pd_cycle(self, q: np.ndarray, now: float) -> None:
        cfg, safety = self.cfg, self._safety
        assert safety is not None
        nominal = 1e-3 * cfg.period_ms
        dt = nominal if self._seq == 0 else now - self._t_cycle
        qdot = self._velocity.update(q, dt)
        if self._seq == 0:
            target, release = safety.reset(q), True
        else:
            target, release = safety.step(q, min(dt, 5 * nominal), now)
        if release or not self._servo_on:
            tau = np.zeros(NUM_JOINTS)
        else:
            tau = safety.torques(pd_torque(q, qdot, target, cfg.kp, cfg.kd))
        self._send_torques(tau)
        state = HandState(q=q, qdot=qdot, torque=tau, target=target, t_host=now, seq=self._seq)
        with self._lock:
            self._state = state
            self._counters["cycles"] += 1
            if self._seq > 0:  # the longest wait for a complete position cycle (feedback_timeout_s ends the run)
                self._counters["longest_gap_ms"] = max(self._counters["longest_gap_ms"], round(1e3 * dt))
            self._cycle_times.append(now)
        self._t_cycle = now
        self._seq += 1
        self._first_cycle.set()

    def _send_torques(self, tau: np.ndarray) -> None:
        assert self.version is not None
        with self._send_lock:
            if not self._servo_on:
                return
            try:
                for f in range(ap.NUM_FINGERS):
                    payload = ap.encode_torques(tau[4 * f: 4 * f + 4], f, self.version)
                    self._send(ap.wire_id(ap.Msg.SET_TORQUE, self.cfg.hand_id, f), payload)
                self._send_errors = 0
            except (can.CanError, OSError) as err:
                self._send_errors += 1
                with self._lock:
                    self._counters["send_errors"] += 1
                log.error("%s: torque send failed (%d/%d consecutive): %s", self.name, self._send_errors,
                          self.cfg.max_send_errors, err)
                if self._send_errors >= self.cfg.max_send_errors:
                    self._set_fault(f"{self._send_errors} consecutive torque send failures", err)
