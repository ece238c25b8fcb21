"""LEAP hand driver: 16 Dynamixel XC330-M288 over Protocol 2.0 through the unmodified ``dynamixel_sdk``.

Usage::

    with LeapHand("/dev/ttyUSB0") as hand:   # Allegro-frame radians in and out: LEAP angle = Allegro + pi
        hand.set_targets(q)
        state = hand.read_state()

Start-up (docs/reference/hardware.md section 2): ping every servo, check the Hardware Error Status, torque off,
Operating Mode 5 (current-based position), position P/I/D (side joints 0/4/8 x ``side_gain_scale``), Goal
Current, Goal Position = present position, then Torque Enable. The servos run the position loop; a host thread
at ``loop_hz`` reads current/velocity/position with one (fast) sync read from address 126 (10 bytes), moves the
target through the safety layer (limits, rate limit, watchdog) and sync-writes Goal Position.

Fault reactions (logged; afterwards every public call raises :class:`HandFault`):

- a failed read (timeout, bad CRC, bad layout) or a status error other than the hardware alert: retried up to
  ``max_retries`` times in the same cycle; feedback older than ``feedback_timeout_s``: torque off;
- a hardware alert (error bit 7): Hardware Error Status is read and logged; torque off;
- policy watchdog 'release': torque off until commands resume, then goal = present pose and torque on again.
"""

from __future__ import annotations

import contextlib
import logging
import threading
import time
from dataclasses import dataclass, field

import numpy as np

from rotation.hardware.hand import NUM_JOINTS, FeedbackMixin, HandFault, HandInfo, HandState
from rotation.hardware.leap import dynamixel_protocol as dp
from rotation.hardware.leap.dynamixel_bus import PORT_ERRORS, DynamixelBus, DynamixelError
from rotation.hardware.safety import SafetyConfig, SafetyLayer, motors_off_on_exit

log = logging.getLogger("rotation.hardware.leap")  # the device's logger (messages name the device)
__all__ = ["DynamixelError", "LeapConfig", "LeapHand"]
R = dp.REGISTERS


@dataclass(frozen=True)
class LeapConfig:
    """LEAP driver settings (register values as the servo stores them)."""

    baudrate: int = 4_000_000
    """Serial baud rate; the LEAP hand runs at 4 Mbaud (register 8 value 6; factory 57,600)."""
    ids: tuple[int, ...] = tuple(range(NUM_JOINTS))
    """Servo ID of each joint, bus order (index, middle, ring, thumb x 4)."""
    p_gain: int = 800
    """Position P gain register (84); LEAP uses 600-800."""
    i_gain: int = 0
    """Position I gain register (82)."""
    d_gain: int = 200
    """Position D gain register (80)."""
    side_gain_scale: float = 0.75
    """Factor on P and D of the side (abduction) joints 0, 4, 8 (LEAP's API)."""
    current_limit_ma: int = 550
    """Goal Current (102), mA, the effort limit of every joint (LEAP: 300-350, 550 for the full hand); must not
    exceed each servo's Current Limit (38)."""
    loop_hz: float = 100.0
    """Host loop rate: one state read and one goal write per cycle."""
    fast_sync_read: bool = True
    """Use FAST_SYNC_READ (one reply for all servos) instead of SYNC_READ (one reply per servo)."""
    max_retries: int = 3
    """Attempts per read/write before it counts as failed."""
    feedback_timeout_s: float = 0.1
    """No good state read for this long (s) -> torque off and HandFault."""
    enable_motors: bool = True
    """False: read-only (no mode/gain writes, no torque), e.g. for ``rotate hand-info``."""
    safety: SafetyConfig = field(default_factory=SafetyConfig)
    """Joint limits (Allegro frame), rate limit and the policy watchdog; ``torque_limits`` must stay None
    (the LEAP effort limit is ``current_limit_ma``)."""

    def __post_init__(self) -> None:
        if self.baudrate not in dp.BAUD_CODES:
            raise ValueError(f"LeapConfig.baudrate must be one of {sorted(dp.BAUD_CODES)}, got {self.baudrate}")
        if len(self.ids) != NUM_JOINTS or len(set(self.ids)) != NUM_JOINTS:
            raise ValueError(f"LeapConfig.ids must be {NUM_JOINTS} distinct servo IDs, got {self.ids}")
        if not all(0 <= i < dp.BROADCAST_ID for i in self.ids):
            raise ValueError("LeapConfig.ids must be in 0..253")
        for name in ("p_gain", "i_gain", "d_gain"):
            if not 0 <= getattr(self, name) <= 16383:
                raise ValueError(f"LeapConfig.{name} must be in 0..16383, got {getattr(self, name)}")
        if not 0 < self.side_gain_scale <= 1:
            raise ValueError(f"LeapConfig.side_gain_scale must be in (0, 1], got {self.side_gain_scale}")
        if not 0 < self.current_limit_ma <= 2352:
            raise ValueError(f"LeapConfig.current_limit_ma must be in 1..2352 mA, got {self.current_limit_ma}")
        if not 1 <= self.loop_hz <= 1000:
            raise ValueError(f"LeapConfig.loop_hz must be in 1..1000, got {self.loop_hz}")
        if self.max_retries < 1 or not self.feedback_timeout_s > 0:
            raise ValueError("LeapConfig.max_retries must be >= 1 and feedback_timeout_s > 0")
        if self.safety.torque_limits is not None:
            raise ValueError("LeapConfig.safety.torque_limits must be None: LEAP limits effort with current_limit_ma")


class LeapHand(FeedbackMixin):
    """The LEAP hand as a context manager; implements ``rotation.hardware.Hand`` (Allegro-frame radians)."""

    torque_unit = "A (present motor current)"

    def __init__(self, port: str, cfg: LeapConfig | None = None, name: str = "leap") -> None:
        self.cfg = cfg or LeapConfig()
        self.name = name
        self.port_name = port
        self._ids = list(self.cfg.ids)
        self._bus = DynamixelBus(port, self.cfg.baudrate, self._ids, self.cfg.max_retries, name)
        self._safety = SafetyLayer(self.cfg.safety, np.full(NUM_JOINTS, np.inf), name=name)
        self._lock = threading.Lock()
        self._exit = contextlib.ExitStack()
        self._thread: threading.Thread | None = None
        self._stop = threading.Event()
        self._off_requested = threading.Event()
        self._state: HandState | None = None
        self._fault: HandFault | None = None
        self._torque_on = False
        self._released = False
        self._models: dict[int, int] = {}
        self._counters = {"cycles": 0, "longest_gap_ms": 0}

    # ------------------------------------------------------------------ lifecycle
    def __enter__(self) -> LeapHand:
        try:
            self._startup()
        except BaseException:
            self._shutdown()
            raise
        return self

    def __exit__(self, *exc: object) -> None:
        self._shutdown()

    def _startup(self) -> None:
        cfg = self.cfg
        self._bus.open()
        for i in self._ids:
            self._models[i] = self._bus.ping(i)
            if self._models[i] != dp.MODEL_XC330_M288:
                log.warning("%s: servo %d is model %d, expected XC330-M288 (%d)", self.name, i, self._models[i],
                            dp.MODEL_XC330_M288)
        for i in self._ids:
            hw = self._bus.read(i, "hardware_error_status")
            if hw:
                raise DynamixelError(f"{self.name}: servo {i} reports a hardware error "
                                     f"({dp.describe_hardware_error(hw)}); fix the cause, then reboot or power-cycle",
                                     i, alert=True)
        self._bus.write_all("torque_enable", 0)
        limits = {i: self._bus.read(i, "current_limit") for i in self._ids}
        low = {i: v for i, v in limits.items() if v < cfg.current_limit_ma}
        if low:
            raise ValueError(f"{self.name}: current_limit_ma={cfg.current_limit_ma} exceeds the Current Limit "
                             f"register (38) of servos {low}")
        q, _, _ = self._read_state_once()
        self._safety.reset(q)
        if cfg.enable_motors:
            self._exit.enter_context(motors_off_on_exit(self._motors_off, self._off_requested.set, self.name))
            self._bus.write_all("operating_mode", dp.OPERATING_MODE_CURRENT_POSITION)
            for j, i in enumerate(self._ids):
                scale = cfg.side_gain_scale if j in (0, 4, 8) else 1.0
                self._bus.write(i, "position_p_gain", int(round(cfg.p_gain * scale)))
                self._bus.write(i, "position_i_gain", cfg.i_gain)
                self._bus.write(i, "position_d_gain", int(round(cfg.d_gain * scale)))
                self._bus.write(i, "goal_current", cfg.current_limit_ma)
            self._write_goals(q)
            self._motors_switched_on = True  # before the writes: some servos may take it even if a later one fails
            self._bus.write_all("torque_enable", 1)
            self._torque_on = True
            log.info("%s: torque on at %d servos, holding the current pose", self.name, len(self._ids))
        self._publish(q, np.zeros(NUM_JOINTS), np.zeros(NUM_JOINTS), q, time.monotonic(), 0)
        self._thread = threading.Thread(target=self._run, name=f"{self.name}-loop", daemon=True)
        self._thread.start()

    def _shutdown(self) -> None:
        self._stop.set()
        if self._thread is not None:
            self._thread.join(timeout=2.0)
            if self._thread.is_alive():
                log.error("%s: loop thread did not stop within 2 s", self.name)
            self._thread = None
        try:
            self._exit.close()
        finally:
            self._bus.close()

    def _motors_off(self) -> None:
        """Torque off at every servo (failures logged at CRITICAL, never raised); ``motors_off_confirmed`` says
        whether every servo acknowledged it."""
        self._torque_on = False
        self._off_confirmed = self._bus.torque_off_all()

    # ------------------------------------------------------------------ public API
    def set_targets(self, q: np.ndarray) -> bool:
        """Joint targets (16,) rad, bus order, Allegro frame; False if rejected (NaN/inf, last target held)."""
        self._raise_if_fault()
        return self._safety.accept(q, time.monotonic())

    def info(self) -> HandInfo:
        """Model/firmware per servo, temperatures (146) and input voltages (144, 0.1 V)."""
        self._raise_if_fault()
        temps = np.array([self._bus.read(i, "present_temperature") for i in self._ids], dtype=np.float64)
        volts = [0.1 * self._bus.read(i, "present_input_voltage") for i in self._ids]
        firmware = {self._bus.read(i, "firmware_version") for i in self._ids}
        models = sorted(set(self._models.values()))
        return HandInfo(kind="leap", firmware=",".join(str(f) for f in sorted(firmware)),
                        hardware=f"XC330-M288 x{len(self._ids)}" if models == [dp.MODEL_XC330_M288] else str(models),
                        serial=self.port_name, temperatures=temps,
                        extra={"input_voltage_v": volts, "model_numbers": self._models.copy()})

    def stats(self) -> dict[str, int]:
        """Counters since start: cycles, the longest time between two good reads of the joints (longest_gap_ms),
        read_retries, failed_reads, rejected_targets."""
        with self._lock:
            return dict(self._counters, **self._bus.counters, rejected_targets=self._safety.rejected)

    # ------------------------------------------------------------------ helpers
    def _write_goals(self, q: np.ndarray) -> None:
        self._bus.write_goal_positions([dp.allegro_to_counts(float(qi)) for qi in q])

    def _read_state_once(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """One sync read of (q rad, qdot rad/s, current A), each (16,), with the bus's retries."""
        blocks = self._bus.sync_read(dp.STATE_ADDR, dp.STATE_LEN, self.cfg.fast_sync_read)
        states = np.array([dp.decode_state(blocks[i]) for i in self._ids])  # (16, 3)
        return states[:, 0], states[:, 1], states[:, 2]

    # ------------------------------------------------------------------ loop thread
    def _publish(self, q, qdot, current, target, now, seq) -> None:
        state = HandState(q=q, qdot=qdot, torque=current, target=target, t_host=now, seq=seq)
        with self._lock:
            self._state = state

    def _run(self) -> None:
        period = 1.0 / self.cfg.loop_hz
        next_t = time.monotonic()
        last_good = next_t
        last = next_t
        seq = 1
        while not self._stop.is_set():
            now = time.monotonic()
            try:
                if self._off_requested.is_set():
                    raise HandFault(f"{self.name}: motors off requested by a signal")
                try:
                    q, qdot, current = self._read_state_once()
                    gap_ms = round(1e3 * (now - last_good))
                    last_good = now
                except PORT_ERRORS as err:
                    raise HandFault(f"{self.name}: serial port {self.port_name} failed ({err}); adapter unplugged?") \
                        from err
                except DynamixelError as err:
                    if err.alert or time.monotonic() - last_good > self.cfg.feedback_timeout_s:
                        raise
                    log.warning("%s: %s; holding the last goal", self.name, err)
                else:
                    target, release = self._safety.step(q, min(now - last, 5 * period), now)
                    if self.cfg.enable_motors:
                        self._apply(q, target, release)
                    self._publish(q, qdot, current, target, now, seq)
                    with self._lock:
                        self._counters["cycles"] += 1
                        if seq > 1:  # the longest wait for the joints' state (feedback_timeout_s ends the run)
                            self._counters["longest_gap_ms"] = max(self._counters["longest_gap_ms"], gap_ms)
                    seq += 1
                last = now
            except Exception as err:  # every failure ends in torque off
                self._set_fault(err)
                return
            next_t += period
            delay = next_t - time.monotonic()
            if delay > 0:
                self._stop.wait(delay)
            else:
                next_t = time.monotonic()

    def _apply(self, q: np.ndarray, target: np.ndarray, release: bool) -> None:
        if release:
            if not self._released:
                self._released = True
                self._motors_off()
            return
        if self._released:  # commands resumed: restart from the present pose, then torque on
            self._released = False
            self._write_goals(q)
            self._off_confirmed = None  # on again: the earlier confirmation no longer holds
            self._bus.write_all("torque_enable", 1)
            self._torque_on = True
            return
        self._write_goals(target)

    def _set_fault(self, err: BaseException) -> None:
        fault = err if isinstance(err, HandFault) else HandFault(f"{self.name}: loop failed: {err}")
        if fault is not err:
            fault.__cause__ = err
        if isinstance(err, DynamixelError) and err.alert and err.dxl_id is not None:
            try:
                bits = self._bus.read(err.dxl_id, "hardware_error_status")
                fault = DynamixelError(f"{err} (Hardware Error Status 0x{bits:02x}: "
                                       f"{dp.describe_hardware_error(bits)})", err.dxl_id, alert=True)
            except (HandFault, *PORT_ERRORS) as read_err:
                log.error("%s: could not read Hardware Error Status of servo %d: %s", self.name, err.dxl_id, read_err)
        log.error("%s: FAULT: %s; torque off", self.name, fault)
        self._fault = fault
        self._motors_off()
