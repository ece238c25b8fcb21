"""The deploy control loop: measure, act (within a deadline), command, record, at the bundle's control rate.

One control step k, scheduled at ``t_k = t_start + k / control_hz`` (host ``time.monotonic()`` s):

1. read the hand's latest state; for k > 0 push the frame of the previous step (measured q, current targets);
2. hand the observation to the policy worker and wait at most ``policy_budget`` control periods for the action;
   a touch-reading policy (a tactile adapter) gets with it the newest touch correction, which the touch worker
   (rotation.deploy.touch) refreshes on its own thread every ``touch_every`` steps from the observation of the
   step that asked; the loop never waits for touch, and without a usable correction the policy acts as its
   student alone (the documented fallback);
3. a usable action moves the targets as in the env; no action in time, a worker still busy with an earlier step,
   or a NaN/inf action (logged) HOLDS the last safe target for this step (the step still counts and its frame is
   still pushed one period later, so the history keeps the env's 20 Hz spacing);
4. send the targets through the driver (its safety layer clamps, rate-limits and runs its own watchdog);
5. record the step (the sensors' samples reach the recording from a drain thread, :class:`DrainThread`, so the
   loop never waits for them), update the status line, sleep until ``t_{k+1}``. A step that starts more than
   ``late_fraction`` of a period after its slot is counted late; a loop more than a whole period behind skips
   the missed slots instead of bursting through them.

Reaction bounds: a stalled or hung policy is held within one step (``policy_budget`` periods) and ends the run
after ``hold_limit_s`` without a usable action; a stalled control loop is held by the driver's watchdog after
``WATCHDOG_PERIODS`` periods (rotation.deploy.hands); lost feedback makes the driver switch the motors off
within its feedback timeout and raise HandFault at the next read. Every fault propagates to ``rotate deploy``'s
``run``, which leaves the hand (motors off) and closes the recording.
"""

from __future__ import annotations

import logging
import math
import time
from dataclasses import dataclass
from typing import TextIO

import numpy as np

from rotation.deploy.drain import Drains, DrainThread
from rotation.deploy.hands import OpenedHand
from rotation.deploy.monitors import LoopStats, RotationMeter, StatusLine, TemperatureMonitor
from rotation.deploy.policy import PolicyFault, PolicyState, PolicyWorker, action_problem
from rotation.deploy.recording import DeployRecorder
from rotation.deploy.sensors import DigitDrain, SkinDrain
from rotation.deploy.touch import reads_touch
from rotation.deploy.touch_worker import STALE_REFRESHES, TouchWorker
from rotation.hardware.hand import HandFault
from rotation.policy.bundle import PolicyBundle, combined_correction

log = logging.getLogger(__name__)



@dataclass(frozen=True)
class LoopConfig:
    """Timing and reaction limits of the control loop."""

    control_hz: float
    """Policy rate (Hz), from the bundle."""
    duration_s: float
    """Run length (s); 0 runs until Ctrl-C / SIGTERM."""
    policy_budget: float = 0.6
    """Longest wait for the policy's action, as a fraction of the control period (30 ms at 20 Hz)."""
    hold_limit_s: float = 1.0
    """End the run (fault) after this long (s) without a usable action (policy stalled, busy or non-finite)."""
    late_fraction: float = 0.2
    """A step starting later than this fraction of a period after its slot counts as late (10 ms at 20 Hz)."""
    status_every_s: float = 1.0
    """Status line period (s)."""
    temperature_every_s: float = 5.0
    """Joint temperature poll period (s), on its own thread (a LEAP poll is 48 register reads)."""
    drain_every_s: float = 0.25
    """Period (s) of moving Digit 360 and skin samples into the recording."""
    touch_stale_refreshes: float = STALE_REFRESHES
    """A touch-reading policy drops a correction older than this many refresh periods (``touch_every`` control
    periods; at least rotation.deploy.touch_worker.MIN_STALE_S) and acts as its student alone until a fresh one
    arrives."""
    max_degraded_fraction: float = 0.5
    """A run in which more than this fraction of the control slots were late, held or skipped did not run the
    policy at its rate: ``rotate deploy`` reports it as a fault (exit status 1), not as done."""


class ControlLoop:
    """Runs one policy on one started hand (see the module docstring). ``stats`` stays valid after a fault."""

    def __init__(self, opened: OpenedHand, bundle: PolicyBundle, cfg: LoopConfig,
                 recorder: DeployRecorder | None = None, readers: dict | None = None,
                 status_out: TextIO | None = None, temperature_c: float = float("nan"), skin=None) -> None:
        """``readers``: Digit 360 readers by finger (recorded, and read by a touch-reading ``bundle``);
        ``temperature_c``: hottest joint at start (C); ``skin``: the Xela skin reader (recorded only)."""
        self.opened = opened
        self.hand = opened.hand
        self.bundle = bundle
        self.cfg = cfg
        self.recorder = recorder
        self.readers = readers or {}
        self.skin = skin
        self.status = StatusLine(status_out)
        self.stats = LoopStats(max_temperature_c=temperature_c)
        self.period = 1.0 / cfg.control_hz
        self.t0: float | None = None
        """Session time zero: host monotonic time (s) of the first joint measurement."""
        self._monitor: TemperatureMonitor | None = None
        self.touch: TouchWorker | None = None
        """The touch worker of a touch-reading policy (its ``stats`` stay valid after the run); None otherwise."""
        self.drainer: DrainThread | None = None
        """The recording's drain thread (a recorded run with sensors); ``rotate deploy`` calls its ``settle`` and
        ``drain_rest`` once the motors are off."""
        self.ended_at: float | None = None
        """Host monotonic time (s) at which the run's loop ended (well or by a fault); None before."""

    def _act(self, request: tuple[dict[str, np.ndarray], np.ndarray | None]) -> np.ndarray:
        """The policy worker's call: one observation and the touch correction to act with (None: the policy alone,
        for an adapter its student)."""
        obs, correction = request
        return self.bundle.act(obs) if correction is None else self.bundle.act(obs, correction=correction)

    def run(self) -> None:
        """Run until ``duration_s`` has passed; raises on a fault (HandFault, PolicyFault, SessionError, signals)."""
        cfg, stats, hand = self.cfg, self.stats, self.hand
        state = hand.read_state()
        self.t0 = t0 = state.t_host
        bundle_cfg = self.bundle.config
        policy = PolicyState(state.q, np.asarray(bundle_cfg.joint_lower), np.asarray(bundle_cfg.joint_upper),
                             bundle_cfg.action_scale)
        pose0 = self.opened.object_pose()
        meter = RotationMeter(pose0) if pose0 is not None else None
        drains = ([DigitDrain(self.readers, t0)] if self.readers else []) + (
            [SkinDrain(self.skin, t0)] if self.skin is not None else [])
        drain = Drains(drains) if drains else None
        worker = PolicyWorker(self._act)
        touch = self.touch = (TouchWorker(self.bundle, self.readers, self.period, cfg.touch_stale_refreshes)
                              if reads_touch(self.bundle) else None)
        try:  # before the clock starts; the hand holds its start pose meanwhile (keep it short: the grasp slips)
            log.info("policy warm-up: first inference took %.0f ms",
                     1e3 * worker.warm_up((policy.observation(), self.bundle.start_correction(0))))  # step 0's path
            if touch is not None:  # the sensors' windows were made ready before the motors went on (job.run)
                log.info("touch: first correction asked for at step 0, then every %d steps (dropped when older "
                         "than %.0f ms); the student acts alone until it arrives", touch.every,
                         1e3 * touch.max_age_s)
        except BaseException:
            worker.close(join_timeout_s=0.0)
            if touch is not None:
                touch.close()
            raise
        self._monitor = TemperatureMonitor(hand, cfg.temperature_every_s, stats.max_temperature_c)
        budget = cfg.policy_budget * self.period
        start = next_tick = time.monotonic()
        last_status = start
        held_since: float | None = None
        k = 0
        drainer = self.drainer = None
        try:
            if drain is not None and self.recorder is not None:
                drainer = self.drainer = DrainThread(drain, self.recorder.append, cfg.drain_every_s)
            while True:
                now = time.monotonic()
                if cfg.duration_s > 0 and now - start >= cfg.duration_s:
                    break
                degraded = now - next_tick > cfg.late_fraction * self.period  # late; held steps join below
                if degraded:
                    stats.late_steps += 1
                    if stats.late_steps == 1 or stats.late_steps % 20 == 0:
                        log.warning("step %d started %.1f ms late (%d late steps so far)", k,
                                    1e3 * (now - next_tick), stats.late_steps)
                stats.tick_times.append(now)

                # 1. measure; the env pushes the frame of a step once the step is over
                state = hand.read_state()
                if not np.all(np.isfinite(state.q)):
                    raise HandFault(f"non-finite joint feedback at joints {np.flatnonzero(~np.isfinite(state.q))}")
                if k > 0:
                    policy.push(state.q)

                # 2. act within the budget, with the newest touch correction (never waited for)
                obs = policy.observation()
                correction = combined_correction(None if touch is None else touch.correction(k, now),
                                                 self.bundle.start_correction(k))  # a cautious start under touch
                action, why = None, ""
                if worker.submit(k, (obs, correction)):
                    action = worker.wait(k, now + budget - time.monotonic())
                    if action is None:
                        why = f"no action within {1e3 * budget:.0f} ms"
                else:
                    why = "the policy is still computing an earlier step"
                if action is not None and (problem := action_problem(action)) is not None:
                    stats.rejected_actions += 1
                    log.error("step %d: rejected the policy's action (%s); holding the last safe target", k, problem)
                    action, why = None, f"rejected action ({problem})"

                if touch is not None:  # a due touch refresh starts now, after the policy's inference, from this step
                    touch.refresh_if_due(k, obs, now)

                # 3. move the targets, or hold them
                if action is not None:
                    policy.apply(action)
                    if held_since is not None:
                        log.info("step %d: the policy is acting again after %.0f ms of hold", k,
                                 1e3 * (now - held_since))
                    held_since = None
                else:
                    stats.held_steps += 1
                    degraded = True
                    if held_since is None:
                        held_since = now
                        if not why.startswith("rejected"):  # a rejection has its own line above
                            log.warning("step %d: %s; holding the last safe target", k, why)
                    if now - held_since >= cfg.hold_limit_s:
                        raise PolicyFault(f"no usable action for {now - held_since:.2f} s "
                                          f"(>= {cfg.hold_limit_s} s): {why}")

                stats.degraded_steps += int(degraded)  # once per step, whether late, held or both

                # 4. command (the driver's safety layer clamps and rate-limits)
                hand.set_targets(policy.targets)
                touch_age = None if touch is None else touch.commanded(k, time.monotonic())

                # 5. record and report
                pose = self.opened.object_pose()
                if meter is not None and pose is not None:
                    meter.update(pose)
                    stats.rotation_rad, stats.object_fell = meter.rotation, meter.fell
                if self.recorder is not None:
                    self.recorder.step(now - t0, state.q, policy.targets, state.torque, pose, touch_age)
                if drainer is not None:
                    drainer.check()
                stats.max_temperature_c = self._monitor.max_c
                if now - last_status >= cfg.status_every_s:
                    self.status.show(self.status_text(now - start, last_status))
                    last_status = now

                # 6. wait for the next slot; never burst through missed ones
                k += 1
                next_tick += self.period
                remaining = next_tick - time.monotonic()
                if remaining > 0:
                    time.sleep(remaining)
                elif -remaining > self.period:
                    missed = int(-remaining // self.period)
                    stats.skipped_slots += missed
                    next_tick += missed * self.period
            if drainer is not None:
                drainer.stop(final_drain=True)
        finally:
            self.ended_at = time.monotonic()
            if drainer is not None:
                drainer.stop(final_drain=False)  # after a fault: the motors first (job.py then calls drain_rest)
            worker.close(join_timeout_s=0.0)
            if touch is not None:
                touch.close()
            self._monitor.stop()
            stats.max_temperature_c = self._monitor.max_c
            self.status.end()

    def status_text(self, elapsed: float, since: float) -> str:
        """``deploy 3.0/5.0 s | loop 20.0 Hz | late 0 | held 0 | touch on | temp max 41 C | rotation +0.52 rad``
        (``touch on`` / ``touch off``: whether a touch-reading policy's adapter acts now)."""
        s = self.stats
        recent = [t for t in s.tick_times if t >= since]
        rate = (len(recent) - 1) / (recent[-1] - recent[0]) if len(recent) > 1 and recent[-1] > recent[0] else 0.0
        total = f"/{self.cfg.duration_s:.0f}" if self.cfg.duration_s > 0 else ""
        parts = [f"deploy {elapsed:5.1f}{total} s", f"loop {rate:4.1f} Hz", f"late {s.late_steps}",
                 f"held {s.held_steps}"]
        if self.touch is not None:
            parts.append("touch on" if self.touch.active else "touch off")
        parts.append(f"temp max {s.max_temperature_c:.0f} C" if not math.isnan(s.max_temperature_c)
                     else "temp max n/a")
        if s.rotation_rad is not None:
            parts.append(f"rotation {s.rotation_rad:+.2f} rad" + (" (fell)" if s.object_fell else ""))
        return " | ".join(parts)
