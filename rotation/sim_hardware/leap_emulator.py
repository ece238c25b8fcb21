"""A LEAP hand as a Dynamixel Protocol 2.0 servo bus on a pseudo-terminal, backed by the MuJoCo hand.

The unmodified dynamixel-sdk opens ``emu.path`` like a U2D2 adapter. Each of the 16 emulated XC330-M288
servos has a control table (:data:`rotation.hardware.leap.dynamixel_protocol.REGISTERS`) and answers PING, READ,
WRITE, SYNC_READ, FAST_SYNC_READ, SYNC_WRITE and REBOOT with byte-stuffed, CRC-checked packets. Writes to EEPROM
(addresses < 64) with torque on are refused with an access error, as on the real servo.

The servo's own loop (current-based position mode) is emulated every 2 ms of hand time, as a PD on the Allegro
MuJoCo hand with a current clamp. The mapping from register values to physics is this emulator's own
approximation (the reference gives no motor constants): torque [N m] = (P/800 * 3.0) * error - (D/200 * 0.1) *
velocity, clamped to Goal Current * 0.5/550 N m per mA, and Present Current = torque / (0.5/550) mA.
Positions: LEAP angle = Allegro angle + pi.
"""

from __future__ import annotations

import logging
import time
from dataclasses import dataclass, field

import numpy as np

from rotation.hardware.leap import dynamixel_protocol as dp
from rotation.sim_hardware.hand_physics import HandPhysics
from rotation.sim_hardware.pty_link import PtyLink
from rotation.sim_hardware.worker import EmulatorThread

log = logging.getLogger(__name__)
R = dp.REGISTERS

TICK_S = 0.002
"""Servo loop period emulated (s)."""
NM_PER_MA = 0.5 / 550.0
"""Emulator's torque per mA of current (its own choice: 550 mA, LEAP's full-hand goal current, = 0.5 N m,
the simulated hand's torque clamp)."""


@dataclass
class LeapFaults:
    """Fault injection; the driver's documented reaction is in brackets."""

    drop_replies: int = 0
    """Drop the next N status packets [read retried; stale > feedback timeout -> torque off]."""
    reply_delay_s: float = 0.0
    """Answer every request this late [SDK timeout (~34 ms) -> retried]."""
    corrupt_crc: int = 0
    """Send the next N status packets with a wrong CRC [SDK reports corrupt -> retried]."""
    error_byte: dict[int, int] = field(default_factory=dict)
    """Servo id -> error byte OR-ed into its status packets (e.g. 0x03 CRC error) [retried, then torque off]."""
    hardware_error: dict[int, int] = field(default_factory=dict)
    """Servo id -> Hardware Error Status bits (e.g. 0x20 overload); sets the alert bit and torque off in that
    servo [driver logs the bits and switches every servo off]."""


class LeapEmulator(EmulatorThread):
    """16 emulated servos on a pty; a context manager that starts and stops its thread."""

    def __init__(self, ids: tuple[int, ...] = tuple(range(16)), physics: HandPhysics | None = None,
                 firmware: int = 52) -> None:  # firmware: any byte; 52 is only a plausible X-series version
        self.ids = list(ids)
        self.physics = physics or HandPhysics()
        self.faults = LeapFaults()
        self.link = PtyLink()
        self.path = self.link.path
        self.tables: dict[int, bytearray] = {}
        for i in self.ids:
            t = bytearray(256)
            self._set(t, "model_number", dp.MODEL_XC330_M288)
            self._set(t, "firmware_version", firmware)
            self._set(t, "id", i)
            self._set(t, "baud_rate", dp.BAUD_CODES[4_000_000])
            self._set(t, "operating_mode", 3)  # factory default: position control
            self._set(t, "current_limit", 2352)
            self._set(t, "position_p_gain", 800)
            self._set(t, "goal_current", 2352)
            self._set(t, "present_input_voltage", 50)
            self._set(t, "present_temperature", 30)
            self.tables[i] = t
        self._buf = bytearray()
        self._init_worker("leap-emulator")
        self.packets_in = 0
        self.crc_errors = 0
        self._refresh_present()
        for i in self.ids:
            self._set(self.tables[i], "goal_position", self._get(self.tables[i], "present_position"))

    def _close_link(self) -> None:
        self.link.close()

    def disconnect(self) -> None:
        """Emulate unplugging the U2D2: the pty closes, the host's next read fails."""
        self.link.disconnect()

    # ------------------------------------------------------------------ register helpers
    @staticmethod
    def _set(table: bytearray, name: str, value: int) -> None:
        reg = R[name]
        table[reg.addr: reg.addr + reg.size] = dp.encode_value(int(value), reg.size)

    @staticmethod
    def _get(table: bytearray, name: str) -> int:
        reg = R[name]
        return dp.decode_value(table[reg.addr: reg.addr + reg.size], reg.signed)

    def register(self, dxl_id: int, name: str) -> int:
        """Current value of a register of one servo (for tests)."""
        return self._get(self.tables[dxl_id], name)

    # ------------------------------------------------------------------ servo physics
    def _servo_torques(self) -> np.ndarray:
        q, qdot = self.physics.joint_state()
        tau = np.zeros(len(self.ids))
        for j, i in enumerate(self.ids):
            t = self.tables[i]
            if not self._get(t, "torque_enable") or self._get(t, "hardware_error_status"):
                continue
            goal = dp.counts_to_allegro(self._get(t, "goal_position"))
            kp = self._get(t, "position_p_gain") / 800.0 * 3.0
            kd = self._get(t, "position_d_gain") / 200.0 * 0.1
            limit = min(abs(self._get(t, "goal_current")), self._get(t, "current_limit")) * NM_PER_MA
            tau[j] = np.clip(kp * (goal - q[j]) - kd * qdot[j], -limit, limit)
        return tau

    def _refresh_present(self) -> None:
        q, qdot = self.physics.joint_state()
        tau = self.physics.torque()
        for j, i in enumerate(self.ids):
            t = self.tables[i]
            self._set(t, "present_position", dp.allegro_to_counts(q[j]))
            self._set(t, "present_velocity", int(round(qdot[j] / dp.RAD_S_PER_VELOCITY_UNIT)))
            self._set(t, "present_current", int(round(tau[j] / NM_PER_MA)))
            hw = self.faults.hardware_error.get(i, 0)
            self._set(t, "hardware_error_status", hw)
            if hw:
                self._set(t, "torque_enable", 0)

    # ------------------------------------------------------------------ thread
    def _run(self) -> None:
        next_tick = time.perf_counter()
        while not self._stop.is_set():
            try:
                data = self.link.read(max(0.0, next_tick - time.perf_counter()))
                if data:
                    self._buf.extend(data)
                    self._process()
                if time.perf_counter() >= next_tick:
                    self.physics.set_torque(self._servo_torques())
                    self.physics.advance(TICK_S)
                    self._refresh_present()
                    next_tick += TICK_S
                    if time.perf_counter() - next_tick > 0.1:
                        next_tick = time.perf_counter()
            except Exception:  # keep the bus alive, but say so
                log.exception("leap emulator: error in the servo loop")
                time.sleep(TICK_S)

    def _process(self) -> None:
        while True:
            packet, used = dp.parse_packet(bytes(self._buf))
            del self._buf[:used]
            if packet is None:
                return
            self.packets_in += 1
            self._execute(packet)

    def _reply(self, dxl_id: int, error: int, params: bytes = b"") -> None:
        t = self.tables[dxl_id]
        if self._get(t, "hardware_error_status"):
            error |= dp.ERROR_ALERT
        error |= self.faults.error_byte.get(dxl_id, 0)
        self._emit(dp.build_status(dxl_id, error, params))

    def _emit(self, packet: bytes) -> None:
        faults = self.faults
        if faults.drop_replies > 0:
            faults.drop_replies -= 1
            return
        if faults.corrupt_crc > 0:
            faults.corrupt_crc -= 1
            packet = packet[:-1] + bytes([packet[-1] ^ 0xFF])
        if faults.reply_delay_s > 0:
            time.sleep(faults.reply_delay_s)
        self.link.write(packet)

    def _execute(self, p: dp.Packet) -> None:
        broadcast = p.dxl_id == dp.BROADCAST_ID
        if not broadcast and p.dxl_id not in self.tables:
            return  # not on this bus: silence, as on a real bus
        if not p.crc_ok:
            self.crc_errors += 1
            if not broadcast:
                self._reply(p.dxl_id, 3)  # error 3: CRC mismatch
            return
        inst, prm = p.inst, p.params
        if inst == dp.Inst.PING:
            for i in (self.ids if broadcast else [p.dxl_id]):
                t = self.tables[i]
                model = self._get(t, "model_number")
                self._reply(i, 0, bytes([model & 0xFF, model >> 8, self._get(t, "firmware_version")]))
        elif inst == dp.Inst.READ and not broadcast:
            addr, length = int.from_bytes(prm[0:2], "little"), int.from_bytes(prm[2:4], "little")
            if addr + length > 256:
                self._reply(p.dxl_id, 7)
            else:
                self._reply(p.dxl_id, 0, bytes(self.tables[p.dxl_id][addr: addr + length]))
        elif inst == dp.Inst.WRITE:
            addr = int.from_bytes(prm[0:2], "little")
            for i in (self.ids if broadcast else [p.dxl_id]):
                err = self._write(i, addr, prm[2:])
                if not broadcast:
                    self._reply(i, err)
        elif inst in (dp.Inst.SYNC_READ, dp.Inst.FAST_SYNC_READ) and broadcast:
            addr, length = int.from_bytes(prm[0:2], "little"), int.from_bytes(prm[2:4], "little")
            ids = [i for i in prm[4:] if i in self.tables]
            if inst == dp.Inst.SYNC_READ:
                for i in ids:
                    self._reply(i, 0, bytes(self.tables[i][addr: addr + length]))
            else:
                blocks = []
                for i in ids:
                    err = self.faults.error_byte.get(i, 0)
                    err |= dp.ERROR_ALERT if self._get(self.tables[i], "hardware_error_status") else 0
                    blocks.append((err, i, bytes(self.tables[i][addr: addr + length])))
                if blocks:
                    self._emit(dp.build_fast_sync_status(blocks))
        elif inst == dp.Inst.SYNC_WRITE and broadcast:
            addr, length = int.from_bytes(prm[0:2], "little"), int.from_bytes(prm[2:4], "little")
            body = prm[4:]
            for k in range(0, len(body) - length, length + 1):
                if body[k] in self.tables:
                    self._write(body[k], addr, body[k + 1: k + 1 + length])
        elif inst == dp.Inst.REBOOT and not broadcast:
            t = self.tables[p.dxl_id]
            self.faults.hardware_error.pop(p.dxl_id, None)
            self._set(t, "hardware_error_status", 0)
            self._set(t, "torque_enable", 0)
            self._reply(p.dxl_id, 0)
        elif not broadcast:
            self._reply(p.dxl_id, 2)  # instruction error

    def _write(self, dxl_id: int, addr: int, data: bytes) -> int:
        """Apply a write to one servo; returns the error number (0 ok, 5 length, 7 access)."""
        t = self.tables[dxl_id]
        if addr + len(data) > 256 or not data:
            return 5
        for reg in R.values():
            if reg.addr < addr + len(data) and addr < reg.addr + reg.size and not reg.writable:
                return 7
        if addr < dp.EEPROM_END and self._get(t, "torque_enable"):
            return 7  # EEPROM is locked while torque is on
        if addr == R["torque_enable"].addr and data[0] and self._get(t, "hardware_error_status"):
            return 7
        t[addr: addr + len(data)] = data
        return 0
