"""An Allegro V4/V5 hand that answers the CAN protocol, backed by the MuJoCo hand (:mod:`hand_physics`).

Two transports, one hand:

- ``AllegroEmulator(transport="virtual")``: a python-can virtual bus in this process; the driver opens
  ``emu.spec`` (``virtual:<channel>``);
- ``AllegroEmulator(transport="slcan")``: an SLCAN (Lawicel) serial adapter on a pseudo-terminal, so another
  process can open ``can.Bus(interface="slcan", channel=emu.path)`` (``emu.spec`` = ``slcan:<pty>``).

One thread runs the hand: it answers frames as they arrive and, every 3 ms of emulated hand time (the hand's
333 Hz clock, docs/reference/hardware.md section 1), advances the physics by 3 ms with the last SET_TORQUE held
and streams FINGER_POSE frames (and TEMPERATURE/IMU when their periods are set) per SET_PERIOD. Hand time is
paced to the wall clock; when the thread is starved by a whole tick, hand time slips instead of catching up
with a burst of ticks that would all use one stale torque (counted in ``overruns``).
As on the real V4, the last torque command stays applied until SYSTEM_OFF or a new command.

Fault switches (``emu.faults``, change them at any time): see :class:`AllegroFaults`.
"""

from __future__ import annotations

import logging
import time
import uuid
from dataclasses import dataclass

import can
import numpy as np

from rotation.hardware.allegro import protocol as ap
from rotation.sim_hardware.hand_physics import HandPhysics
from rotation.sim_hardware.pty_link import PtyLink
from rotation.sim_hardware.worker import EmulatorThread

log = logging.getLogger(__name__)

TICK_S = 0.003
"""Hand clock period (s): 333 Hz (docs/reference/hardware.md section 1)."""


@dataclass
class AllegroFaults:
    """Fault injection; the driver's documented reaction is in brackets."""

    drop_position_frames: int = 0
    """Drop the next N streamed FINGER_POSE frames [cycle skipped, counted; stall -> motors off]."""
    stream_pause_s: float = 0.0
    """Pause the position stream once for this long, then resume [late cycle; > feedback timeout -> motors off]."""
    reply_delay_s: float = 0.0
    """Answer requests this late [request retried, then HandNotResponding]."""
    ignore_requests: bool = False
    """Never answer RTR requests [retries, then HandNotResponding]."""
    bus_off: bool = False
    """Neither send nor receive, as a controller in BUS-OFF or a pulled cable [feedback timeout -> motors off]."""
    garble_lines: int = 0
    """SLCAN only: corrupt the next N lines sent to the host [receive error logged; repeated -> motors off]."""
    error_frame: tuple[int, int] | None = None
    """Send one V5 error frame (motor id, bits) at the next tick [motors off]."""
    ignore_system_off: int = 0
    """Ignore the next N SYSTEM_OFF frames, as a hand that had not yet handled one when asked [HAND_INFO says the
    servo is on; SYSTEM_OFF sent again; never off -> CRITICAL, motors off unconfirmed]."""


class _VirtualTransport:
    def __init__(self, channel: str) -> None:
        self.bus = can.Bus(interface="virtual", channel=channel)
        self.spec = f"virtual:{channel}"

    def recv(self, timeout: float) -> list[can.Message]:
        msg = self.bus.recv(timeout=max(timeout, 0.0))
        out = []
        while msg is not None:
            out.append(msg)
            msg = self.bus.recv(timeout=0.0)
        return out

    def send(self, msg: can.Message, garble: bool = False) -> None:
        self.bus.send(msg)

    def close(self) -> None:
        self.bus.shutdown()


class _SlcanTransport:
    """Lawicel SLCAN adapter: commands C/O/L/S/V/N/F, frames t/T/r/R ``\\r``-terminated; BEL (0x07) on error."""

    def __init__(self) -> None:
        self.link = PtyLink()
        self.spec = f"slcan:{self.link.path}"
        self.open = False
        self._buf = bytearray()

    def recv(self, timeout: float) -> list[can.Message]:
        data = self.link.read(timeout)
        if not data:
            return []
        self._buf.extend(data)
        out = []
        while b"\r" in self._buf:
            line, _, rest = bytes(self._buf).partition(b"\r")
            self._buf = bytearray(rest)
            msg = self._command(line.decode("ascii", errors="replace"))
            if msg is not None:
                out.append(msg)
        return out

    def _command(self, line: str) -> can.Message | None:
        if not line:
            return None
        cmd = line[0]
        if cmd in "COLSs":  # close / open / listen-only / bitrate: acknowledge
            if cmd in "COL":
                self.open = cmd != "C"
            self.link.write(b"\r")
            return None
        if cmd == "V":
            self.link.write(b"V1013\r")
            return None
        if cmd == "N":
            self.link.write(b"NEMU1\r")
            return None
        if cmd == "F":
            self.link.write(b"F00\r")
            return None
        if cmd in "tTrR" and self.open:
            try:
                ext = cmd in "TR"
                n = 8 if ext else 3
                arb = int(line[1: 1 + n], 16)
                dlc = int(line[1 + n])
                remote = cmd in "rR"
                data = b"" if remote else bytes.fromhex(line[2 + n: 2 + n + 2 * dlc])
            except ValueError:
                self.link.write(b"\a")
                return None
            self.link.write(b"Z\r" if ext else b"z\r")
            return can.Message(arbitration_id=arb, is_extended_id=ext, is_remote_frame=remote,
                               data=None if remote else data, dlc=dlc, timestamp=time.time())
        self.link.write(b"\a")
        return None

    def send(self, msg: can.Message, garble: bool = False) -> None:
        if not self.open:
            return
        kind = "r" if msg.is_remote_frame else "t"
        payload = "" if msg.is_remote_frame else bytes(msg.data).hex().upper()
        line = f"{kind}{msg.arbitration_id:03X}{msg.dlc}{payload}"
        if garble:
            line = line[:5] + "GZ" + line[7:]  # not hex: the host's parser must cope
        self.link.write(line.encode("ascii") + b"\r")

    def close(self) -> None:
        self.link.close()


class AllegroEmulator(EmulatorThread):
    """The emulated hand; use as a context manager (starts and stops its thread, closes its bus or pty)."""

    def __init__(self, transport: str = "virtual", channel: str | None = None, version: str = "v4",
                 serial: str = "SAH040E1", hand_id: int = 0, physics: HandPhysics | None = None) -> None:
        if transport not in ("virtual", "slcan"):
            raise ValueError(f"transport must be 'virtual' or 'slcan', got {transport!r}")
        if version not in ap.VERSIONS:
            raise ValueError(f"version must be one of {sorted(ap.VERSIONS)}, got {version!r}")
        self.version = ap.VERSIONS[version]
        self.hand_id = hand_id
        self.serial = serial
        # versions of the real V4 bus trace (hw 0x0402, fw 0x0406, docs/reference/hardware.md section 1);
        # 0x05xx marks a V5
        self.info = ap.AllegroInfo(hardware=0x0402 if version == "v4" else 0x0500, firmware=0x0406,
                                   right_hand=True, temperature_c=38, status=0)
        self.physics = physics or HandPhysics()
        self.faults = AllegroFaults()
        self._transport = (_VirtualTransport(channel or f"allegro-emu-{uuid.uuid4().hex[:8]}")
                           if transport == "virtual" else _SlcanTransport())
        self.spec = self._transport.spec
        self.servo_on = False
        self.periods_ms = (0, 0, 0)  # position, imu, temperature
        self._ticks = 0
        self._torque = np.zeros(16)
        self._delayed: list[tuple[float, can.Message]] = []
        self._init_worker("allegro-emulator")
        self.overruns = 0
        self.frames_in = 0
        self.frames_out = 0

    @property
    def path(self) -> str:
        """The pty of the SLCAN adapter (slcan transport only)."""
        return self._transport.link.path  # type: ignore[union-attr]

    def _close_link(self) -> None:
        self._transport.close()

    def temperatures(self) -> np.ndarray:
        """(16,) joint temperatures, degrees C: 35 C plus 10 C per unit of applied |torque| (a made-up model)."""
        return 35.0 + 10.0 * np.abs(self._torque)

    # ------------------------------------------------------------------ thread
    def _run(self) -> None:
        next_tick = time.perf_counter()
        while not self._stop.is_set():
            now = time.perf_counter()
            try:
                for msg in self._transport.recv(next_tick - now):
                    self._handle(msg)
                now = time.perf_counter()
                if self._delayed:
                    self._flush_delayed(now)
                if now >= next_tick:
                    self._tick()
                    next_tick += TICK_S
                    if now > next_tick:  # late by a whole tick: hand time slips, no burst of catch-up ticks
                        self.overruns += 1
                        next_tick = now
            except Exception:  # keep the emulated hand alive, but say so
                log.exception("allegro emulator: error in the hand loop")
                time.sleep(TICK_S)

    def _send(self, msg: can.Message) -> None:
        if self.faults.bus_off:
            return
        garble = self.faults.garble_lines > 0
        if garble:
            self.faults.garble_lines -= 1
        self.frames_out += 1
        self._transport.send(msg, garble=garble)

    def _frame(self, msg_id: int, data: bytes, finger: int = 0) -> can.Message:
        return can.Message(arbitration_id=ap.wire_id(msg_id, self.hand_id, finger), is_extended_id=False,
                           data=data, timestamp=time.time())

    def _reply(self, msg: can.Message) -> None:
        if self.faults.ignore_requests:
            return
        if self.faults.reply_delay_s > 0:
            self._delayed.append((time.perf_counter() + self.faults.reply_delay_s, msg))
        else:
            self._send(msg)

    def _flush_delayed(self, now: float) -> None:
        due = [m for t, m in self._delayed if t <= now]
        self._delayed = [(t, m) for t, m in self._delayed if t > now]
        for msg in due:
            self._send(msg)

    def _handle(self, msg: can.Message) -> None:
        if self.faults.bus_off or msg.is_extended_id or msg.is_error_frame:
            return
        self.frames_in += 1
        msg_id, hand_id = ap.split_wire_id(msg.arbitration_id)
        if hand_id != self.hand_id:
            return
        data = bytes(msg.data)
        if msg.is_remote_frame:
            self._answer_request(msg_id)
        elif msg_id == ap.Msg.SYSTEM_ON:
            self.servo_on = True
        elif msg_id == ap.Msg.SYSTEM_OFF and self.faults.ignore_system_off > 0:
            self.faults.ignore_system_off -= 1
        elif msg_id == ap.Msg.SYSTEM_OFF:
            self.servo_on = False
            self._torque[:] = 0.0
            self.physics.set_torque(self._torque)
        elif msg_id == ap.Msg.SET_PERIOD:
            try:
                self.periods_ms = ap.decode_period(data)
            except ValueError as err:
                log.warning("allegro emulator: ignoring SET_PERIOD: %s", err)
        elif (f := ap.finger_of(msg_id, ap.Msg.SET_TORQUE)) is not None:
            try:
                tau = ap.decode_torques(data, self.version)
            except ValueError as err:
                log.warning("allegro emulator: ignoring SET_TORQUE: %s", err)
                return
            if self.servo_on:  # the firmware ignores torque commands while the servo is off
                self._torque[4 * f: 4 * f + 4] = tau
                self.physics.set_torque(self._torque)

    def _answer_request(self, msg_id: int) -> None:
        if msg_id == ap.Msg.HAND_INFO:
            status = ap.STATUS_SERVO_ON if self.servo_on else 0
            info = ap.AllegroInfo(self.info.hardware, self.info.firmware, self.info.right_hand,
                                  int(self.temperatures().max()), status)
            self._reply(self._frame(ap.Msg.HAND_INFO, ap.encode_hand_info(info)))
        elif msg_id == ap.Msg.SERIAL:
            self._reply(self._frame(ap.Msg.SERIAL, ap.encode_serial(self.serial)))
        elif msg_id == ap.Msg.IMU:
            self._reply(self._frame(ap.Msg.IMU, bytes(6)))
        elif (f := ap.finger_of(msg_id, ap.Msg.FINGER_POSE)) is not None:
            q, _ = self.physics.joint_state()
            self._reply(self._frame(ap.Msg.FINGER_POSE, ap.encode_positions(q[4 * f: 4 * f + 4], self.version), f))
        elif (f := ap.finger_of(msg_id, ap.Msg.TEMPERATURE)) is not None:
            temps = self.temperatures()[4 * f: 4 * f + 4]
            self._reply(self._frame(ap.Msg.TEMPERATURE, ap.encode_temperatures(temps), f))

    def _tick(self) -> None:
        self.physics.advance(TICK_S)
        self._ticks += 1
        faults = self.faults
        if faults.error_frame is not None:
            motor, bits = faults.error_frame
            faults.error_frame = None
            self._send(self._frame(ap.Msg.V5_ERROR, bytes([motor, bits])))
        if faults.stream_pause_s > 0:
            pause, faults.stream_pause_s = faults.stream_pause_s, 0.0
            time.sleep(pause)
        pos_ms, imu_ms, temp_ms = self.periods_ms
        if pos_ms > 0 and self._ticks % max(1, round(pos_ms / 3)) == 0:
            q, _ = self.physics.joint_state()
            for f in range(ap.NUM_FINGERS):
                if faults.drop_position_frames > 0:
                    faults.drop_position_frames -= 1
                    continue
                self._send(self._frame(ap.Msg.FINGER_POSE, ap.encode_positions(q[4 * f: 4 * f + 4], self.version),
                                       f))
        if temp_ms > 0 and self._ticks % max(1, round(temp_ms / 3)) == 0:
            for f in range(ap.NUM_FINGERS):
                self._send(self._frame(ap.Msg.TEMPERATURE, ap.encode_temperatures(self.temperatures()[4 * f:4 * f + 4]),
                                       f))
        if imu_ms > 0 and self._ticks % max(1, round(imu_ms / 3)) == 0:
            self._send(self._frame(ap.Msg.IMU, bytes(6)))
