"""Run a policy on a real or emulated hand with safety limits and recording.

    rotate deploy --hand sim-allegro --policy student --duration 10           # rehearsal: emulated hand, real driver
    rotate deploy --hand sim-leap --policy student --record runs/leap_rehearsal.h5
    rotate deploy --hand allegro --can socketcan:can0 --policy student --gain-scale 0.3 --duration 5
    rotate deploy --hand leap --port /dev/ttyUSB0 --policy student --record runs/leap.h5
    rotate deploy --hand allegro --policy student --skin ws://localhost:5000 --record runs/skin.h5   # + Xela skin
    rotate deploy --hand allegro --policy student --digit360 D360-A,D360-B,D360-C,D360-D --record runs/cup_tape.h5 \
        --properties mass=0.12,friction=0.8,com=0,0,0.01,scale=0.8    # measured object: adapter fine-tuning data
    rotate deploy --hand allegro --policy student --digit360 D360-A,D360-B,D360-C,D360-D --record runs/cup.h5 \
        --record-media --properties ...      # + the sensors' camera frames and microphones (all four modalities)
    rotate deploy --hand sim-allegro --policy adapter --duration 10   # student + tactile adapter, emulated touch
    rotate deploy --hand allegro --policy runs/adapter_pressure/bundle --digit360 SERIAL1,SERIAL2,SERIAL3,SERIAL4

--policy takes a bundle directory or a shipped bundle name (student), or a tactile adapter bundle (a directory, or
a shipped name such as adapter), which is its student plus a latent correction from the Digit 360 fingertips,
refreshed every ``touch_every`` steps on its own thread and held in between (rotation.deploy.touch). On an emulated
hand it starts the emulated fingertips itself (no --digit360 needed); on a real hand --digit360 must name a sensor
for every fingertip the adapter reads, and the sensors must stream every window it reads, else the run is refused
before anything starts: IMU and pressure come from a sensor's serial stream; for an adapter that reads the image or
the audio, deploy opens the camera and microphones it finds on each sensor's USB hub (the ``hardware`` extra). When
touch is unusable (a stalled or missing stream, non-finite embeddings, a correction older than 3 refresh periods,
at least 1 s) the adapter's student acts alone, with one warning, until touch is back.

The loop runs at the bundle's control rate, builds observations with the env's own code
(envs.observation.ProprioHistory), integrates targets as the env does and sends them through the driver, whose
safety layer clamps joints and torques, limits the target rate and holds the last target if commands stop. Ctrl-C
or SIGTERM end the run: motors off, recording closed. Prints a live status line (stderr), then the summary as one
JSON object on the last line of stdout. Exit status: 0 run completed, 1 fault, 130 Ctrl-C (SIGINT), 143 SIGTERM,
2 bad options (nothing was started).

Nothing is reported as safe or done unless it was: the bundle, the --record file, the --digit360 sensors and the
--skin server are checked before any motor is switched on; a run whose steps were mostly late or held is a fault;
the summary's "motors_off" is true only when confirmed (by the emulated hand, or by the real hand's answer), and a
motors-off that was not confirmed ends with a non-zero status and the instruction to cut the hand's power. With
--skin the summary's "skin" counts the frames received, the malformed messages skipped and the disconnects; with a
touch-reading policy its "touch" counts the refreshes, the steps acted with the adapter and as the student alone
(fallback), and the refresh time (rotation.deploy.touch.TouchStats).
"""

from __future__ import annotations

import argparse
import contextlib
import json
import logging
import math
import signal
import sys
import tempfile
import threading
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Literal

from envs.validation import check_int, check_number, check_types
from rotation.configs import add_dataclass_arguments, dataclass_from_args, to_jsonable
from rotation.data.properties import parse_properties
from rotation.deploy.hands import HANDS, HandSetup, OpenedHand, emulated_physics, open_hand
from rotation.deploy.sensors import check_digit360, check_skin, parse_digit360, parse_skin

log = logging.getLogger("rotation.deploy")

EXIT_OK, EXIT_FAULT, EXIT_SIGINT, EXIT_SIGTERM = 0, 1, 130, 143
TOUCH_JOIN_S = 5.0
"""Longest wait (s), after the motors are off, for a touch refresh still running (one takes up to ~1 s on a loaded
2-core machine); torch still computing on a daemon thread when the interpreter exits aborts the process."""
DRAIN_JOIN_S = 2.0
"""Longest wait (s), after a fault and with the motors off, for a recording drain in progress (one took up to
0.5 s on a loaded 2-core machine) before the sensors' last samples are moved into the session."""


@dataclass(frozen=True)
class Config:
    hand: Literal["allegro", "leap", "sim-allegro", "sim-leap"] = "sim-allegro"
    """Real Allegro (CAN) or LEAP (Dynamixel), or its MuJoCo emulator driven through the real driver and protocol."""
    policy: str = ""
    """Policy bundle: a directory (config.json + model.safetensors) or a shipped name (student); or a tactile adapter
    bundle (a directory with adapter.safetensors, or a shipped name such as adapter), which reads the Digit 360
    fingertips."""
    can: str = "socketcan:can0"
    """Allegro bus as INTERFACE:CHANNEL: socketcan:can0, pcan:PCAN_USBBUS1, slcan:/dev/ttyACM0 (any serial device)."""
    port: str = "/dev/ttyUSB0"
    """LEAP serial device (U2D2 adapter; any serial device path)."""
    baud: int = 4_000_000
    """LEAP baud rate."""
    digit360: str = ""
    """Digit 360 sensors to record (and to read, for a tactile adapter policy): 4 comma-separated USB serials in
    finger order (index,middle,ring,thumb), FINGER=SERIAL pairs, tty paths, or 'sim' (emulated sensors that sense the
    emulated hand, emulated hands only; what an adapter policy on an emulated hand starts without this option)."""
    skin: str = ""
    """Xela skin to record (skin/xela, 100 Hz): the vendor xela_server's WebSocket URL (ws://HOST:5000), or 'sim'
    (a stand-in server, emulated hands only); empty: none. Start with the skin free of contact (baseline)."""
    duration: float = 10.0
    """Run length (s); 0 runs until Ctrl-C / SIGTERM."""
    record: str = ""
    """Session file (.h5) to record to (must not exist unless --overwrite); empty: no recording."""
    overwrite: bool = False
    """Replace an existing --record file."""
    record_media: bool = False
    """Also record each real --digit360 sensor's camera frames and microphones (digit360/<finger>/image, audio;
    about 4.5 MB/s per sensor; needs the hardware extra), whatever the policy reads: what fine-tuning an adapter
    that reads the image or the audio on your sessions needs. A policy that reads them records them anyway."""
    gain_scale: float = 1.0
    """Factor in (0, 1] on the driver's gains (Allegro kp/kd, LEAP position P/D): start a new hand low."""
    object: str = "cup"
    """Object in the hand: recorded as metadata; emulated hands simulate it (needs a shipped grasp cache)."""
    properties: str = ""
    """Measured object properties to store in the recording (its metadata's ``properties``; needs --record), e.g.
    'mass=0.12,friction=0.8,com=0,0,0.01,scale=0.8': kg, friction coefficient against the fingertips, center of
    mass offset (m, object frame), size relative to the simulated cup (rotation.data.properties). Fine-tuning the
    tactile adapter on the recording needs all four. An emulated hand records its simulated values; stated ones
    replace them."""
    grasp: int = 0
    """Emulated hands: the row of the shipped grasp cache to start from (nominal scale)."""
    sim_transport: Literal["virtual", "slcan"] = "virtual"
    """Emulated Allegro: python-can virtual bus, or an SLCAN serial adapter on a pseudo-terminal."""
    rt_priority: int = 0
    """SCHED_FIFO priority (1..99) for the control threads; 0 leaves scheduling alone (needs CAP_SYS_NICE)."""
    policy_budget: float = 0.6
    """Longest wait for the policy's action, as a fraction of the control period; later = hold the last target."""
    hold_limit_s: float = 1.0
    """Fault (end the run) after this long without a usable action from the policy (s)."""
    status_every_s: float = 1.0
    """Status line period (s)."""

    def __post_init__(self) -> None:
        if self.hand not in HANDS:
            raise ValueError(f"hand: unknown hand {self.hand!r}; choose one of {', '.join(HANDS)}")
        check_types(self)
        if not self.policy:
            raise ValueError("policy: give a bundle directory or a shipped bundle name (--policy student)")
        if not (math.isfinite(self.duration) and self.duration >= 0):
            raise ValueError(f"duration must be >= 0 s (0: until Ctrl-C), got {self.duration}")
        if not (0 < self.gain_scale <= 1):
            raise ValueError(f"gain_scale must be in (0, 1] (a fraction of the driver's gains), got {self.gain_scale}")
        if self.hand == "allegro":
            from rotation.hardware.can_bus import parse_can_spec

            parse_can_spec(self.can)
        if self.hand == "leap":
            from rotation.hardware.dynamixel_protocol import BAUD_CODES

            if self.baud not in BAUD_CODES:
                raise ValueError(f"baud: {self.baud} is not a Dynamixel baud rate; choose one of {sorted(BAUD_CODES)}")
        digit_specs = parse_digit360(self.digit360, emulated=self.hand.startswith("sim-"))
        parse_skin(self.skin, emulated=self.hand.startswith("sim-"))
        if parse_properties(self.properties) and not self.record:
            raise ValueError("properties: they are stored in the recording; give --record FILE.h5 as well")
        if self.record_media:
            if not self.record:
                raise ValueError("record_media: it records the sensors' cameras and microphones; give --record "
                                 "FILE.h5 as well")
            if not digit_specs or any(v == "sim" for v in digit_specs.values()):
                raise ValueError("record_media: name real Digit 360 sensors with --digit360 (serials or tty paths); "
                                 "emulated sensors render their image and audio only for a window and record none")
        if self.grasp < 0:
            raise ValueError(f"grasp must be >= 0, got {self.grasp}")
        if self.sim_transport not in ("virtual", "slcan"):
            raise ValueError(f"sim_transport must be 'virtual' or 'slcan', got {self.sim_transport!r}")
        if not 0 <= self.rt_priority <= 99:
            raise ValueError(f"rt_priority must be 0..99, got {self.rt_priority}")
        if not 0 < self.policy_budget <= 1:
            raise ValueError(f"policy_budget must be in (0, 1] control periods, got {self.policy_budget}")
        if not (self.hold_limit_s > 0 and self.status_every_s > 0):
            raise ValueError("hold_limit_s and status_every_s must be > 0 s")
        # ceilings that catch typos and unit slips (every option is checked, whether this hand uses it or not)
        from rotation.hardware.dynamixel_protocol import BAUD_CODES

        if self.baud not in BAUD_CODES:
            raise ValueError(f"baud: {self.baud} is not a Dynamixel baud rate; choose one of {sorted(BAUD_CODES)}")
        check_number("duration", self.duration, 0.0, 7 * 24 * 3600.0, unit="s (0: until Ctrl-C)")
        check_int("grasp", self.grasp, 0, 10**6)
        check_number("hold_limit_s", self.hold_limit_s, 0.0, 60.0, low_open=True, unit="s")
        check_number("status_every_s", self.status_every_s, 0.0, 3600.0, low_open=True, unit="s")


REQUIRED = ("hand", "policy")


def add_arguments(parser: argparse.ArgumentParser) -> None:
    add_dataclass_arguments(parser, Config)
    for action in parser._actions:  # the hand and the policy are never implied
        if action.dest in REQUIRED:
            action.required = True
            action.help = (action.help or "").split(" (default:")[0]


def config_from_args(args: argparse.Namespace) -> Config:
    return dataclass_from_args(Config, args)


class _CriticalRecords(logging.Handler):
    """Collects CRITICAL records of the drivers: each one means a motors-off command could not be sent or was not
    confirmed (rotation.hardware logs exactly those at CRITICAL)."""

    def __init__(self) -> None:
        super().__init__(level=logging.CRITICAL)
        self.messages: list[str] = []

    def emit(self, record: logging.LogRecord) -> None:
        self.messages.append(record.getMessage())


class _RunSignals:
    """SIGINT / SIGTERM around one run (main thread only; elsewhere the drivers' atexit hooks still apply).

    While the hand runs, the drivers' own handlers (rotation.hardware.safety.motors_off_on_exit) switch the motors
    off at once and raise KeyboardInterrupt / SystemExit(143) here; :meth:`arm` makes SIGTERM do the same before
    the hand has started (default: instant death without closing anything). :meth:`defer` is for the final
    clean-up, when the motors are already off: a second Ctrl-C is logged instead of cutting the recording's close
    short. :meth:`restore` puts the previous handlers back.
    """

    def __init__(self) -> None:
        self.active = threading.current_thread() is threading.main_thread()
        self.previous = {sig: signal.getsignal(sig) for sig in (signal.SIGINT, signal.SIGTERM)} if self.active else {}

    @staticmethod
    def _terminate(signum: int, frame: object) -> None:
        raise SystemExit(128 + signum)

    @staticmethod
    def _later(signum: int, frame: object) -> None:
        log.warning("deploy: signal %d during shut-down (motors already off); finishing the recording first", signum)

    def arm(self) -> None:
        if self.active:
            signal.signal(signal.SIGTERM, self._terminate)

    def defer(self) -> None:
        if self.active:
            for sig in self.previous:
                signal.signal(sig, self._later)

    def restore(self) -> None:
        for sig, handler in self.previous.items():
            signal.signal(sig, handler)  # type: ignore[arg-type]


def _ensure_logging() -> None:
    """INFO lines of this package on stderr when the program has not configured logging itself (the CLI)."""
    if not logging.getLogger().handlers:
        logging.basicConfig(level=logging.WARNING, format="%(asctime)s %(levelname)s %(name)s: %(message)s")
    pkg = logging.getLogger("rotation")
    if pkg.level == logging.NOTSET:
        pkg.setLevel(logging.INFO)


def _check_record_path(path: Path, overwrite: bool) -> None:
    """ValueError unless a session file can be created at ``path``: never an existing file without ``--overwrite``
    (a recording is never replaced silently), never a directory, and a location this process can write to."""
    if path.is_dir():
        raise ValueError(f"record: {path} is a directory; give a file name such as {path / 'run.h5'}")
    if path.exists() and not overwrite:
        raise ValueError(f"record: {path} exists; choose a new file name, or pass --overwrite to replace it")
    parent = path.parent if str(path.parent) else Path(".")
    existing = next((p for p in (parent, *parent.parents) if p.exists()), Path("."))
    if not existing.is_dir():
        raise ValueError(f"record: cannot create {path}: {existing} is not a directory")
    # try it: permission bits say nothing when running as root or on a read-only file system
    try:
        if path.exists():
            with open(path, "r+b"):
                pass
        else:
            with tempfile.TemporaryFile(dir=existing):
                pass
    except OSError as err:
        raise ValueError(f"record: cannot write {path} ({err.strerror or err} in {existing}); choose a writable "
                         "location") from err


def _check_before_start(cfg: Config) -> None:
    """Everything that can be checked without touching the hardware (ValueError: bad input)."""
    if cfg.record:
        _check_record_path(Path(cfg.record), cfg.overwrite)
    check_skin(parse_skin(cfg.skin, emulated=cfg.hand.startswith("sim-")))
    if cfg.hand.startswith("sim-"):
        from envs.grasps import load_default_cache

        cache = load_default_cache(cfg.object)
        if cfg.grasp >= cache.grasps.shape[1]:
            raise ValueError(f"grasp {cfg.grasp} out of range: the {cfg.object!r} cache has "
                             f"{cache.grasps.shape[1]} grasps per scale")


def _classify(err: BaseException) -> tuple[str, int, bool]:
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


def run(cfg: Config) -> dict[str, Any]:
    """Deploy ``cfg.policy`` on ``cfg.hand``; returns the summary (also printed as JSON on the last stdout line).

    Bad options raise ValueError before anything is started. Once the hand is being started nothing escapes:
    faults, Ctrl-C and SIGTERM end the run with one log line, the motors off and the recording closed (readable up
    to the last flush), and are reported in the summary (``fault``, ``exit_code``).
    """
    _ensure_logging()
    import numpy as np
    import torch

    from rotation.deploy.loop import ControlLoop, LoopConfig
    from rotation.deploy.policy import check_deployable
    from rotation.deploy.recording import DeployRecorder
    from rotation.deploy.sensors import MEDIA_STREAMS, check_media_extras, find_media, open_digit360, open_skin
    from rotation.deploy.touch import reads_touch, touch_sensors, wait_for_touch
    from rotation.hardware.realtime import frozen_heap, set_realtime_priority
    from rotation.policy.bundle import load_bundle

    bundle = load_bundle(cfg.policy)
    touch = reads_touch(bundle)
    check_deployable(bundle.config, cfg.policy, reads_touch=touch)
    hz = float(bundle.config.control_hz)
    setup = HandSetup(hand=cfg.hand, can=cfg.can, port=cfg.port, baud=cfg.baud, gain_scale=cfg.gain_scale,
                      control_hz=hz, object=cfg.object, grasp=cfg.grasp, sim_transport=cfg.sim_transport)
    digit_specs = parse_digit360(cfg.digit360, setup.emulated)
    check_digit360(digit_specs)  # first: a sensor that is not there is named as such, not as one without a camera
    media: dict[str, Any] = {}
    if touch:  # the sensors the adapter reads, checked (or, emulated, started) before anything else
        media = find_media(digit_specs, tuple(bundle.windows) + (MEDIA_STREAMS if cfg.record_media else ()))
        digit_specs = touch_sensors(bundle, cfg.policy, digit_specs, setup.emulated, media)
    elif cfg.record_media:
        media = find_media(digit_specs, MEDIA_STREAMS)
    if cfg.record_media:
        lacking = [f"{f}={digit_specs[f]}" for f, d in media.items() if not (d.camera and d.audio)]
        if lacking:
            raise ValueError(f"record_media: no camera or microphones found on the USB hub of the Digit 360 "
                             f"{', '.join(lacking)} (is the whole sensor plugged in, not only its serial port?)")
    check_media_extras(media)
    _check_before_start(cfg)
    loop_cfg = LoopConfig(control_hz=hz, duration_s=cfg.duration, policy_budget=cfg.policy_budget,
                          hold_limit_s=cfg.hold_limit_s, status_every_s=cfg.status_every_s)
    kind = bundle.config.latent_source + (f" + tactile adapter: {', '.join(bundle.windows)}, every "
                                          f"{bundle.touch_every} steps" if touch else "")
    log.info("deploying %s (%s, %.0f Hz, action scale %.4f rad) on %s for %s", cfg.policy, kind, hz,
             bundle.config.action_scale, cfg.hand,
             f"{cfg.duration:g} s" if cfg.duration > 0 else "until Ctrl-C")

    critical = _CriticalRecords()
    hw_log = logging.getLogger("rotation.hardware")
    hw_log.addHandler(critical)
    switch_interval, torch_threads = sys.getswitchinterval(), torch.get_num_threads()
    created: list[OpenedHand] = []  # the hand as soon as its driver exists, also when its start-up fails
    loop: ControlLoop | None = None
    recorder: DeployRecorder | None = None
    skin = None
    fault: str | None = None
    exit_code = EXIT_OK
    t_start = time.monotonic()
    signals = _RunSignals()
    try:
        signals.arm()
        with contextlib.ExitStack() as stack:
            # a full GC pass over the loaded process would stall the drivers' threads past their watchdogs
            stack.enter_context(frozen_heap())
            # the policy's small network gains nothing from more threads; they would compete with the drivers
            torch.set_num_threads(1)
            # the network traced for one observation: it runs without taking the interpreter's lock op by op
            # (PolicyBundle and AdaptedPolicy; any other object with act() acts as it is)
            prepare = getattr(bundle, "prepare_realtime", None)
            if prepare is not None:
                prepare()
            # one inference before the hand starts: the first call of a network is slow (allocation, dispatch)
            bundle.act(bundle.config.zero_observation())
            if setup.emulated:
                # the emulator shares this process (and the GIL) with the busy-polling drivers: switch threads
                # every 0.5 ms instead of 5 ms so the emulated hardware answers in time
                sys.setswitchinterval(5e-4)
            sched = set_realtime_priority(cfg.rt_priority)
            physics = emulated_physics(setup)  # emulation: the hand's world, which the emulated fingertips sense
            # before the hand: the hand leaves first on exit
            readers = open_digit360(digit_specs, stack, physics, media)
            if touch:  # the windows fill while the motors are off (a hand holding its pose meanwhile lets go)
                took = wait_for_touch(bundle, readers)
                if took is not None:
                    log.info("touch: every fingertip's windows ready %.0f ms after the sensors opened, before the "
                             "motors go on", 1e3 * took)
            skin, skin_baseline = open_skin(parse_skin(cfg.skin, setup.emulated), stack)
            # motors on, holding the current pose; the stack switches them off
            opened = open_hand(setup, stack, created=created.append, physics=physics)
            hand = opened.hand
            info = hand.info()
            temps = np.asarray(info.temperatures, dtype=np.float64)
            temp0 = float(np.nanmax(temps)) if np.any(np.isfinite(temps)) else float("nan")
            log.info("%s: firmware %s, hardware %s, serial %s, hottest joint %s; scheduling %s", info.kind,
                     info.firmware, info.hardware, info.serial,
                     "n/a" if math.isnan(temp0) else f"{temp0:.0f} C", sched)
            if cfg.record:
                recorder = _open_recorder(cfg, bundle, opened, info, readers, hz, skin_baseline)
            loop = ControlLoop(opened, bundle, loop_cfg, recorder=recorder, readers=readers, status_out=sys.stderr,
                               temperature_c=temp0, skin=skin)
            loop.run()
        # the motors are off; a run that was mostly late or held did not run the policy as it was trained
        shortfall = loop.stats.shortfall(loop_cfg.max_degraded_fraction)
        if shortfall is not None:
            fault, exit_code = f"the loop could not hold {hz:g} Hz: {shortfall}", EXIT_FAULT
    except BaseException as err:  # noqa: B036 - every way out ends here, Ctrl-C and SIGTERM included
        fault, exit_code, expected = _classify(err)
        if not expected:
            log.error("deploy: unexpected error", exc_info=err)
    finally:
        signals.defer()  # the hand has left (motors off): nothing may cut the rest short
        if loop is not None and loop.touch is not None:
            loop.touch.join(TOUCH_JOIN_S)  # a refresh still encoding; now that the motors are off it may be waited for
        if loop is not None and loop.drainer is not None:  # after a fault: the moments before it (else a no-op)
            loop.drainer.drain_rest(DRAIN_JOIN_S)
        sys.setswitchinterval(switch_interval)
        torch.set_num_threads(torch_threads)
        hw_log.removeHandler(critical)
        if recorder is not None:
            try:
                recorder.close(complete=fault is None)
            except Exception as err:  # the hand is already off; say what happened to the file
                log.error("deploy: closing the recording %s failed: %s", recorder.path, err)
                fault = fault or f"recording failed: {err}"
                exit_code = exit_code or EXIT_FAULT
    try:
        opened = created[0] if created else None
        return _finish(cfg, hz, opened, loop, recorder, critical, fault, exit_code, time.monotonic() - t_start,
                       skin)
    finally:
        signals.restore()


def _open_recorder(cfg: Config, bundle, opened: OpenedHand, info, readers: dict[str, Any], hz: float,
                   skin_baseline=None):
    import numpy as np

    from rotation.data.session import SessionError, SessionMeta
    from rotation.deploy.recording import DeployRecorder
    from rotation.deploy.sensors import media_streams

    properties: dict[str, Any] = {}
    physics = opened.physics
    if physics is not None:  # the simulated object's values (com: its inertial frame's offset, object frame)
        body = physics.model.body("object")
        properties = {"scale": physics.scale, "grasp": physics.grasp, "mass": float(body.mass[0]),
                      "friction": float(physics.model.geom_friction[physics.model.body_geomadr[body.id], 0]),
                      "com": [float(x) for x in physics.model.body_ipos[body.id]]}
    stated = parse_properties(cfg.properties)
    differ = [k for k, v in stated.items() if k in properties and not np.allclose(v, properties[k])]
    if differ:
        log.warning("--properties: the stated %s replace the emulated object's %s", {k: stated[k] for k in differ},
                    {k: properties[k] for k in differ})
    properties.update(stated)
    extra = {
        "hand": cfg.hand, "policy": cfg.policy, "policy_latent_source": bundle.config.latent_source,
        "policy_card": bundle.config.card, "torque_unit": opened.hand.torque_unit,
        "hand_info": {"kind": info.kind, "firmware": info.firmware, "hardware": info.hardware,
                      "serial": info.serial},
        "target": "targets commanded by the policy (before the driver's rate limit)",
        "policy_touch": None if not bundle.config.adapter else {
            "adapter": bundle.config.adapter, "touch_encoder": bundle.config.touch_encoder,
            "windows": list(getattr(bundle, "windows", ())), "touch_every": getattr(bundle, "touch_every", None)},
        "deploy_config": to_jsonable(cfg),
        "stated_properties": sorted(stated),
    }
    if skin_baseline is not None:
        from rotation.data.skin import BASELINE_KEY

        extra[BASELINE_KEY] = skin_baseline.tolist()  # (368, 3) counts before the hand started
    meta = SessionMeta(source=opened.source, object=cfg.object, control_hz=hz, hand=opened.kind,
                       properties=properties, extra=json.loads(json.dumps(extra, default=str)))
    try:
        recorder = DeployRecorder(cfg.record, meta, fingers=tuple(readers), object_pose=physics is not None,
                                  overwrite=cfg.overwrite, skin=skin_baseline is not None,
                                  media={f: media_streams(r) for f, r in readers.items()})
    except OSError as err:  # checked before the start, but the disk may have changed since
        raise SessionError(f"could not create {cfg.record}: {err}") from err
    log.info("recording to %s", recorder.path)
    return recorder


def _motors_off_state(opened: OpenedHand | None) -> tuple[bool, bool | None, str | None]:
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


def _finish(cfg: Config, hz: float, opened: OpenedHand | None, loop, recorder, critical: _CriticalRecords,
            fault: str | None, exit_code: int, wall_s: float, skin=None) -> dict[str, Any]:
    """Summary dict, final log lines, and the JSON line on stdout."""
    motors_off, confirmed, witness = _motors_off_state(opened)
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
