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
motors-off that was not confirmed ends with a non-zero status and the instruction to cut the hand's power. With --skin
the summary's "skin" counts the frames received, the malformed messages skipped and the disconnects; with a touch-
reading policy its "touch" counts the refreshes, the steps acted with the adapter and as the student alone (fallback),
the refresh time and its parts, the touch ages and each correction's delay in control steps
(rotation.deploy.touch_worker.TouchStats; a recorded run holds each step's touch age, ``touch/age``). Its "hand_bus"
holds the hand driver's counters (PD cycles, the longest wait for the joints' state in ms, bus errors), its "digit360"
each fingertip reader's (frames, bad frames, disconnects, unknown message kinds), and with --sim-faults its "sim_faults"
each injected fault with the time it was applied (rotation.deploy.sim_faults).
"""

from __future__ import annotations

import contextlib
import json
import logging
import math
import signal
import sys
import threading
import time
from typing import TYPE_CHECKING, Any

from rotation.configs import to_jsonable
from rotation.data.properties import parse_properties
from rotation.deploy.config import (  # Config, add_arguments, config_from_args: what `rotate deploy` reads here
    Config,
    add_arguments,  # noqa: F401
    check_before_start,
    config_from_args,  # noqa: F401
)
from rotation.deploy.hands import HandSetup, OpenedHand, emulated_physics, open_hand
from rotation.deploy.outcome import EXIT_FAULT, EXIT_OK, CriticalRecords, classify, finish
from rotation.deploy.sensors import check_digit360, parse_digit360, parse_skin
from rotation.deploy.sim_faults import FaultSchedule, check_sim_faults, parse_sim_faults

if TYPE_CHECKING:
    from rotation.deploy.loop import ControlLoop

log = logging.getLogger("rotation.deploy")

TOUCH_JOIN_S = 5.0
"""Longest wait (s), after the motors are off, for a touch refresh still running (one takes up to ~1 s on a loaded
2-core machine); torch still computing on a daemon thread when the interpreter exits aborts the process."""
DRAIN_JOIN_S = 2.0
"""Longest wait (s), after the run and with the motors off, for a recording drain in progress (one took up to
0.5 s on a loaded 2-core machine) before the sensors' last samples are moved into the session."""


def _settle_sensors(loop: ControlLoop) -> None:
    """Let the sensors deliver their samples up to the loop's end before they close (DrainThread.settle)."""
    if loop.drainer is not None and loop.ended_at is not None:
        loop.drainer.settle(loop.ended_at)


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


def run(cfg: Config) -> dict[str, Any]:
    """Deploy ``cfg.policy`` on ``cfg.hand``; returns the summary (also printed as JSON on the last stdout line).

    Bad options raise ValueError before anything is started. Once the hand is being started nothing escapes:
    faults, Ctrl-C and SIGTERM end the run with one log line, the motors off and the recording closed (readable up
    to the last flush), and are reported in the summary (``fault``, ``exit_code``).
    """
    _ensure_logging()
    import numpy as np
    import torch

    from rotation.bundles import load_bundle
    from rotation.deploy.loop import ControlLoop, LoopConfig
    from rotation.deploy.policy import check_deployable, deploy_sim_hand
    from rotation.deploy.recording import DeployRecorder
    from rotation.deploy.sensors import MEDIA_STREAMS, check_media_extras, find_media, open_digit360, open_skin
    from rotation.deploy.touch import reads_touch, touch_sensors, wait_for_touch
    from rotation.hardware.realtime import frozen_heap, set_realtime_priority

    bundle = load_bundle(cfg.policy)
    touch = reads_touch(bundle)
    check_deployable(bundle.config, cfg.policy, reads_touch=touch)
    sim_hand = deploy_sim_hand(cfg.hand, bundle, cfg.policy, cfg.allow_model_mismatch)
    hz = float(bundle.config.control_hz)
    setup = HandSetup(hand=cfg.hand, can=cfg.can, port=cfg.port, baud=cfg.baud, gain_scale=cfg.gain_scale,
                      control_hz=hz, object=cfg.object, grasp=cfg.grasp, sim_transport=cfg.sim_transport,
                      sim_hand=sim_hand,
                      sim_object=tuple((k, tuple(v) if isinstance(v, list) else v)
                                       for k, v in parse_properties(cfg.sim_object, "sim_object").items()))
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
    check_before_start(cfg)
    faults = parse_sim_faults(cfg.sim_faults)
    check_sim_faults(faults, setup.emulated, tuple(f for f, v in digit_specs.items() if v == "sim"))
    loop_cfg = LoopConfig(control_hz=hz, duration_s=cfg.duration, policy_budget=cfg.policy_budget,
                          hold_limit_s=cfg.hold_limit_s, status_every_s=cfg.status_every_s)
    kind = bundle.config.latent_source + (f" + tactile adapter: {', '.join(bundle.windows)}, every "
                                          f"{bundle.touch_every} steps" if touch else "")
    log.info("deploying %s (%s, %.0f Hz, action scale %.4f rad) on %s for %s", cfg.policy, kind, hz,
             bundle.config.action_scale, cfg.hand,
             f"{cfg.duration:g} s" if cfg.duration > 0 else "until Ctrl-C")

    critical = CriticalRecords()
    hw_log = logging.getLogger("rotation.hardware")
    hw_log.addHandler(critical)
    switch_interval, torch_threads = sys.getswitchinterval(), torch.get_num_threads()
    created: list[OpenedHand] = []  # the hand as soon as its driver exists, also when its start-up fails
    loop: ControlLoop | None = None
    recorder: DeployRecorder | None = None
    skin = None
    emulators: dict[str, Any] = {}  # the emulated fingertips, by finger (their fault switches)
    schedule: FaultSchedule | None = None
    readers: dict[str, Any] = {}
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
            readers = open_digit360(digit_specs, stack, physics, media, emulators=emulators,
                                    imu_channel=cfg.digit360_imu)
            if touch:  # the windows fill while the motors are off (a hand holding its pose meanwhile lets go)
                took = wait_for_touch(bundle, readers)
                if took is not None:
                    log.info("touch: every fingertip's windows ready %.0f ms after the sensors opened, before the "
                             "motors go on", 1e3 * took)
            skin, skin_baseline = open_skin(parse_skin(cfg.skin, setup.emulated), stack)
            # on exit after the hand (motors off), before the sensors close: their samples of the run's last moments
            stack.callback(lambda: loop is not None and _settle_sensors(loop))
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
            schedule = FaultSchedule(faults, opened.emulator, emulators)
            stack.callback(schedule.stop)  # no fault lands after the motors went off
            schedule.start()
            loop.run()
        # the motors are off; a run that was mostly late or held did not run the policy as it was trained
        shortfall = loop.stats.shortfall(loop_cfg.max_degraded_fraction)
        if shortfall is not None:
            fault, exit_code = f"the loop could not hold {hz:g} Hz: {shortfall}", EXIT_FAULT
    except BaseException as err:  # noqa: B036 - every way out ends here, Ctrl-C and SIGTERM included
        fault, exit_code, expected = classify(err)
        if not expected:
            log.error("deploy: unexpected error", exc_info=err)
    finally:
        signals.defer()  # the hand has left (motors off): nothing may cut the rest short
        if loop is not None and loop.touch is not None:
            loop.touch.join(TOUCH_JOIN_S)  # a refresh still encoding; now that the motors are off it may be waited for
        if loop is not None and loop.drainer is not None:  # the run's last moments (after a fault: before it)
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
        return finish(cfg, hz, opened, loop, recorder, critical, fault, exit_code, time.monotonic() - t_start,
                       skin, readers=readers, sim_faults=None if schedule is None else schedule.report())
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
        properties = {**physics.object_properties(), "grasp": physics.grasp}
    stated = parse_properties(cfg.properties)
    differ = [k for k, v in stated.items() if k in properties and not np.allclose(v, properties[k])]
    if differ:
        log.warning("--properties: the stated %s replace the emulated object's %s", {k: stated[k] for k in differ},
                    {k: properties[k] for k in differ})
    properties.update(stated)
    if cfg.friction_method.strip():
        properties["friction_method"] = cfg.friction_method.strip()
    extra = {
        "hand": cfg.hand, "policy": cfg.policy, "policy_latent_source": bundle.config.latent_source,
        "policy_card": bundle.config.card, "policy_sim": bundle.config.sim,
        "model_mismatch_allowed": cfg.allow_model_mismatch, "torque_unit": opened.hand.torque_unit,
        "hand_info": {"kind": info.kind, "firmware": info.firmware, "hardware": info.hardware,
                      "serial": info.serial},
        "target": "targets commanded by the policy (before the driver's rate limit)",
        "policy_touch": None if not bundle.config.adapter else {
            "adapter": bundle.config.adapter, "touch_encoder": bundle.config.touch_encoder,
            "windows": list(getattr(bundle, "windows", ())), "touch_every": getattr(bundle, "touch_every", None),
            "touch_smoothing": getattr(bundle, "touch_smoothing", None)},
        "deploy_config": to_jsonable(cfg),
        "stated_properties": sorted(stated),
        "digit360_imu": cfg.digit360_imu,
    }
    if skin_baseline is not None:
        from rotation.data.skin import BASELINE_KEY

        extra[BASELINE_KEY] = skin_baseline.tolist()  # (368, 3) counts before the hand started
    meta = SessionMeta(source=opened.source, object=cfg.object, control_hz=hz, hand=opened.kind,
                       properties=properties, extra=json.loads(json.dumps(extra, default=str)))
    try:
        recorder = DeployRecorder(cfg.record, meta, fingers=tuple(readers), object_pose=physics is not None,
                                  overwrite=cfg.overwrite, skin=skin_baseline is not None,
                                  media={f: media_streams(r) for f, r in readers.items()},
                                  touch_age=bool(bundle.config.adapter))
    except OSError as err:  # checked before the start, but the disk may have changed since
        raise SessionError(f"could not create {cfg.record}: {err}") from err
    log.info("recording to %s", recorder.path)
    return recorder
