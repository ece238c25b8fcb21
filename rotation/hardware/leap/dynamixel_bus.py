"""A Dynamixel Protocol 2.0 bus through the unmodified ``dynamixel_sdk``: register access by name with bounded
retries, sync write of goal positions, (fast) sync read of one register block with per-servo error bytes.

Layering (STYLE point 7): SDK (transport) -> this bus (register table :data:`dynamixel_protocol.REGISTERS`,
retries, error bytes) -> :class:`rotation.hardware.leap.driver.LeapHand` (start-up sequence, safety, loop).

Error handling: a failed exchange (timeout, corrupt reply) or a status error other than the hardware alert is
logged and retried up to ``max_retries`` times, then :class:`DynamixelError`; a hardware alert (error bit 7)
raises at once with ``alert=True``. The SDK's ``GroupSyncRead`` drops the per-servo error bytes, so the
replies are received here with the SDK's ``readRx`` / ``rxPacket``.
"""

from __future__ import annotations

import logging
import termios
import threading

import dynamixel_sdk as sdk

from rotation.hardware.hand import HandFault, HandNotResponding
from rotation.hardware.leap import dynamixel_protocol as dp

log = logging.getLogger(__name__)
R = dp.REGISTERS

PORT_ERRORS = (OSError, termios.error)
"""What the SDK raises when the adapter disappears (serial.SerialException is an OSError)."""


class DynamixelError(HandFault):
    """A servo answered with an error byte, or did not answer after the retries."""

    def __init__(self, message: str, dxl_id: int | None = None, alert: bool = False) -> None:
        super().__init__(message)
        self.dxl_id = dxl_id
        self.alert = alert
        """True when the servo set the hardware alert bit (then Hardware Error Status says why)."""


class DynamixelBus:
    """Servos ``ids`` on ``port`` at ``baudrate``; every use of the port is serialized by one lock."""

    def __init__(self, port: str, baudrate: int, ids: list[int], max_retries: int = 3, name: str = "dxl") -> None:
        self.port_name = port
        self.baudrate = baudrate
        self.ids = list(ids)
        self.max_retries = max_retries
        self.name = name
        self.port = sdk.PortHandler(port)
        self.ph = sdk.PacketHandler(2.0)
        self.io = threading.RLock()
        self.counters = {"read_retries": 0, "failed_reads": 0}
        self._writer = sdk.GroupSyncWrite(self.port, self.ph, R["goal_position"].addr, 4)
        for i in self.ids:
            self._writer.addParam(i, [0, 0, 0, 0])
        self._readers: dict[tuple[int, int], sdk.GroupSyncRead] = {}

    # ------------------------------------------------------------------ port
    def open(self) -> None:
        try:
            opened = self.port.openPort() and self.port.setBaudRate(self.baudrate)
        except (*PORT_ERRORS, ValueError) as err:
            raise HandNotResponding(f"{self.name}: could not open {self.port_name}: {err}") from err
        if not opened:
            raise HandNotResponding(f"{self.name}: could not open {self.port_name} at {self.baudrate} baud")

    @property
    def is_open(self) -> bool:
        return bool(self.port.is_open)

    def close(self) -> None:
        if self.port.is_open:
            self.port.closePort()

    # ------------------------------------------------------------------ register access
    def _check(self, what: str, dxl_id: int, result: int, error: int, allow_alert: bool = False) -> bool:
        """True on success; False for a retryable failure (logged); raises on a hardware alert."""
        if result != sdk.COMM_SUCCESS:
            log.warning("%s: %s servo %d: %s", self.name, what, dxl_id, self.ph.getTxRxResult(result))
            return False
        if error & dp.ERROR_ALERT and not allow_alert:
            raise DynamixelError(f"{self.name}: servo {dxl_id} hardware alert during {what}", dxl_id, alert=True)
        error &= ~dp.ERROR_ALERT if allow_alert else 0xFF
        if error:
            log.warning("%s: %s servo %d: %s", self.name, what, dxl_id, dp.describe_error(error))
            return False
        return True

    def ping(self, dxl_id: int) -> int:
        """Model number of a servo; HandNotResponding after the retries."""
        for _ in range(self.max_retries):
            with self.io:
                model, result, _ = self.ph.ping(self.port, dxl_id)
            if result == sdk.COMM_SUCCESS:
                return model
        raise HandNotResponding(f"{self.name}: servo {dxl_id} does not answer ping on {self.port_name} at "
                                f"{self.baudrate} baud (powered? ID? baud rate?)")

    def read(self, dxl_id: int, name: str) -> int:
        """Register value by name (signed where the table says so)."""
        reg = R[name]
        for _ in range(self.max_retries):
            with self.io:
                data, result, error = self.ph.readTxRx(self.port, dxl_id, reg.addr, reg.size)
            if self._check(f"read {name}", dxl_id, result, error, allow_alert=name == "hardware_error_status"):
                return dp.decode_value(bytes(data), reg.signed)
        raise DynamixelError(f"{self.name}: read {name} from servo {dxl_id} failed {self.max_retries} times", dxl_id)

    def write(self, dxl_id: int, name: str, value: int) -> None:
        """Write a register by name and check the servo's status reply."""
        reg = R[name]
        data = list(dp.encode_value(value, reg.size))
        for _ in range(self.max_retries):
            with self.io:
                result, error = self.ph.writeTxRx(self.port, dxl_id, reg.addr, reg.size, data)
            if self._check(f"write {name}={value}", dxl_id, result, error):
                return
        raise DynamixelError(f"{self.name}: write {name}={value} to servo {dxl_id} failed {self.max_retries} times",
                             dxl_id)

    def write_all(self, name: str, value: int) -> None:
        for i in self.ids:
            self.write(i, name, value)

    def write_goal_positions(self, counts: list[int]) -> None:
        """One SYNC_WRITE of Goal Position (116, 4 B) to every servo (no reply: errors show in the next read)."""
        for i, c in zip(self.ids, counts, strict=True):
            self._writer.changeParam(i, list(dp.encode_value(int(c), 4)))
        with self.io:
            result = self._writer.txPacket()
        if result != sdk.COMM_SUCCESS:
            log.warning("%s: goal position sync write: %s", self.name, self.ph.getTxRxResult(result))

    def torque_off_all(self) -> bool:
        """Torque off at every servo: one broadcast write, then a write to each servo, whose status reply is the
        confirmation. True only if every servo replied without an error number (the alert bit alone is fine: a
        servo in alert has switched its torque off itself); every failure is logged at CRITICAL, never raised."""
        if not self.port.is_open:
            log.critical("%s: torque off not sent: %s is closed; cut the power of the hand", self.name, self.port_name)
            return False
        confirmed = True
        with self.io:
            try:
                self.ph.write1ByteTxOnly(self.port, dp.BROADCAST_ID, R["torque_enable"].addr, 0)
                for i in self.ids:
                    result, error = self.ph.write1ByteTxRx(self.port, i, R["torque_enable"].addr, 0)
                    if result != sdk.COMM_SUCCESS:
                        confirmed = False
                        log.critical("%s: torque off not confirmed by servo %d (%s); cut its power if it moves",
                                     self.name, i, self.ph.getTxRxResult(result))
                    elif error & ~dp.ERROR_ALERT:  # an error number: the servo did not take the write
                        confirmed = False
                        log.critical("%s: servo %d answered torque off with an error (%s); cut its power if it moves",
                                     self.name, i, dp.describe_error(error))
            except PORT_ERRORS as err:
                log.critical("%s: torque off could not be sent (%s); cut the power of the hand", self.name, err)
                return False
        return confirmed

    # ------------------------------------------------------------------ sync read
    def sync_read(self, addr: int, length: int, fast: bool = True) -> dict[int, bytes]:
        """``{id: length bytes from addr}`` for every servo, retried; DynamixelError after ``max_retries``."""
        for attempt in range(self.max_retries):
            if attempt:
                self.counters["read_retries"] += 1
            blocks = self._sync_read_once(addr, length, fast)
            if blocks is not None:
                return blocks
        self.counters["failed_reads"] += 1
        raise DynamixelError(f"{self.name}: sync read of {length} bytes at {addr} failed {self.max_retries} times")

    def _sync_read_once(self, addr: int, length: int, fast: bool) -> dict[int, bytes] | None:
        reader = self._readers.get((addr, length))
        if reader is None:
            reader = self._readers[(addr, length)] = sdk.GroupSyncRead(self.port, self.ph, addr, length)
            for i in self.ids:
                reader.addParam(i)
        what = "fast sync read" if fast else "sync read"
        with self.io:
            result = reader.fastSyncReadTxPacket() if fast else reader.txPacket()
            if not self._check(what, dp.BROADCAST_ID, result, 0):
                return None
            if fast:
                raw, result = self.ph.rxPacket(self.port, True)
                if not self._check(what, dp.BROADCAST_ID, result, 0):
                    return None
                try:
                    replies = dp.parse_fast_sync_status(raw, self.ids, length)
                except ValueError as err:
                    log.warning("%s: %s: %s", self.name, what, err)
                    return None
            else:
                replies = {}
                for i in self.ids:
                    data, result, error = self.ph.readRx(self.port, i, length)
                    if not self._check(what, i, result, 0):
                        return None
                    replies[i] = (error, bytes(data))
        ok = True
        for i, (error, _) in replies.items():
            ok &= self._check(what, i, sdk.COMM_SUCCESS, error)
        return {i: data for i, (_, data) in replies.items()} if ok else None
