"""The thread that refreshes a tactile adapter's correction beside the control loop: it reads the fingertips'
newest windows, encodes them, and hands the loop a correction it may act on, or none when touch is stale,
missing or not finite (the student then acts alone).
"""

from __future__ import annotations

import logging
import math
import re
import statistics
import threading
import time
from collections import Counter
from collections.abc import Mapping
from dataclasses import dataclass, field, replace
from typing import Any, NamedTuple

import numpy as np

from adapters.touch_delay import smooth
from rotation.deploy.touch import adapter_inputs, log

STALE_REFRESHES = 3.0
"""A correction older than this many refresh periods (``touch_every`` control periods), and at least
``MIN_STALE_S``, is dropped (its age: since the observation and windows it was computed from)."""
MIN_STALE_S = 2.0
"""Floor of the staleness limit (s). A worker that keeps up replaces a correction at an age of about one refresh
period plus its refresh time; a slow but working one at about twice its refresh time. On a loaded 2-core machine an
all-modality refresh took 0.3-0.5 s, and 0.8-0.9 s on a slower one (the emulated hand and fingertips sharing its
cores), so its corrections reach 1.8 s; the object properties touch estimates (friction, mass) do not change within
a few seconds, and a hung worker is still caught within 2 s."""
SLOW_REFRESHES = 5
"""Refreshes in a row longer than the refresh period that are reported (once) as a worker too slow for the adapter."""
REPEAT_WARN_EVERY = 20
"""A fallback cause that comes back is warned about again every this many times (info in between)."""


class RefreshTiming(NamedTuple):
    """One successful refresh's time line (host s)."""

    t_read: float
    """When the worker had read every fingertip's window."""
    read_age_s: float
    """How old the touch it read was when the refresh started (the sensors' and their link's share of the touch
    age; slightly negative when a sample newer than the start arrived before its fingertip was read)."""
    start_s: float
    """From the observation it was asked with to its start (the policy's inference on that step)."""
    read_s: float
    """Reading the windows (a real sensor's: slicing its ring buffers; an emulated one renders its image and audio
    here, which a real camera and microphones do not cost)."""
    encode_s: float
    """Encoding them and computing the correction."""


@dataclass
class TouchStats:
    """What the touch side did in one run (the summary's ``touch``)."""

    touch_every: int
    """Control steps between refreshes (the adapter's)."""
    control_period_s: float
    """The control loop's period (s)."""
    max_age_s: float
    """Staleness limit (s): older corrections were dropped."""
    refreshes: int = 0
    """Corrections computed."""
    failed_refreshes: int = 0
    """Refreshes without a correction (stalled stream, missing window, non-finite embeddings, worker error)."""
    delayed_refreshes: int = 0
    """Refreshes that fell due while the worker was still busy with the previous one (started later)."""
    adapter_steps: int = 0
    """Steps acted with a correction."""
    fallback_steps: int = 0
    """Steps acted as the student alone (touch unusable, or no correction yet)."""
    first_correction_step: int | None = None
    """Control step at which the adapter first acted (the student alone before it); None if it never did."""
    fallbacks: int = 0
    """Times the fallback started (each logged: a warning the first time per cause)."""
    refresh_s: list[float] = field(default_factory=list)
    """Duration (s) of every refresh (windows + correction), successful or not."""
    last_cause: str | None = None
    """Why the last fallback started."""
    age_s: list[float] = field(default_factory=list)
    """Touch age (s) of every step acted with a correction: from the newest sensor sample of the oldest fingertip
    window it read to the step's command to the hand."""
    first_use_age_s: list[float] = field(default_factory=list)
    """The same at each correction's first step: the touch path's latency."""
    timings: list[RefreshTiming] = field(default_factory=list)
    """How every successful refresh spent its time (the parts of the touch age)."""
    first_use_steps: Counter[int] = field(default_factory=Counter)
    """Corrections by the control steps from the step whose refresh read their touch to their first step: the
    delay simulation applies (adapters.touch_delay)."""

    def summary(self) -> dict[str, Any]:
        ms = [1e3 * t for t in self.refresh_s]
        return {"touch_every": self.touch_every, "max_age_ms": 1e3 * self.max_age_s, "refreshes": self.refreshes,
                "failed_refreshes": self.failed_refreshes, "delayed_refreshes": self.delayed_refreshes,
                "adapter_steps": self.adapter_steps, "fallback_steps": self.fallback_steps,
                "fallbacks": self.fallbacks, "first_correction_step": self.first_correction_step,
                "refresh_ms_p50": statistics.median(ms) if ms else None,
                "refresh_ms_max": max(ms) if ms else None,
                "age_ms_p50": _percentile_ms(self.age_s, 50), "age_ms_p95": _percentile_ms(self.age_s, 95),
                "first_use_age_ms_p50": _percentile_ms(self.first_use_age_s, 50),
                "first_use_age_ms_p95": _percentile_ms(self.first_use_age_s, 95),
                "read_age_ms_p50": _percentile_ms([t.read_age_s for t in self.timings], 50),
                "start_ms_p50": _percentile_ms([t.start_s for t in self.timings], 50),
                "read_ms_p50": _percentile_ms([t.read_s for t in self.timings], 50),
                "encode_ms_p50": _percentile_ms([t.encode_s for t in self.timings], 50),
                "encode_ms_p95": _percentile_ms([t.encode_s for t in self.timings], 95),
                "first_use_steps": {str(k): self.first_use_steps[k] for k in sorted(self.first_use_steps)},
                "first_use_steps_no_render": self.steps_without_reading(),
                "last_fallback_cause": self.last_cause}

    def steps_without_reading(self) -> dict[str, int]:
        """Refreshes by the control steps to their first use had reading the windows cost nothing: the step after
        its start plus its encoding, ceil((start + encode) / control period). A real Digit 360's windows are slices
        of its ring buffers; an emulated one renders its image and audio when they are read, which this leaves out
        (what simulation should apply for real sensors, from a rehearsal on emulated ones)."""
        counts = Counter(max(1, math.ceil((t.start_s + t.encode_s) / self.control_period_s)) for t in self.timings)
        return {str(k): counts[k] for k in sorted(counts)}


def _percentile_ms(values_s: list[float], q: float) -> float | None:
    return float(np.percentile(values_s, q) * 1e3) if values_s else None


@dataclass(frozen=True)
class _Result:
    """One finished refresh: the correction (Z,) or None with the cause (and the exception of a bug)."""

    seq: int
    t_obs: float
    """Host time (s) of the observation and windows it was computed from."""
    correction: np.ndarray | None
    t_touch: float = float("nan")
    """Host time (s) of the newest sensor sample of the oldest fingertip window it read (its touch's time)."""
    cause: str | None = None
    error: BaseException | None = None
    """The exception of a bug-level failure (logged with its traceback); None for the expected ones."""


class TouchWorker:
    """Refreshes ``policy``'s touch correction from ``readers`` ({finger: Digit360}) on a daemon thread.

    The control loop calls, once per control step, :meth:`correction` before the policy acts (the correction to act
    with; None: act as the student alone) and :meth:`refresh_if_due` once the policy has acted (so that the refresh
    starts in the slack of the step, not beside the policy's inference). Neither blocks. See the module docstring.
    """

    def __init__(self, policy: Any, readers: Mapping[str, Any], control_period_s: float,
                 stale_refreshes: float = STALE_REFRESHES) -> None:
        self.policy = policy
        self.readers = dict(readers)
        self.every = int(policy.touch_every)
        self.refresh_period_s = self.every * control_period_s
        self.stats = TouchStats(touch_every=self.every, control_period_s=control_period_s,
                                max_age_s=max(stale_refreshes * self.refresh_period_s, MIN_STALE_S))
        self._groups = tuple(policy.config.obs_groups)
        self._cv = threading.Condition()
        self._request: tuple[int, float, dict[str, np.ndarray]] | None = None
        self._busy = False
        self._stop = False
        self._latest: _Result | None = None
        self._state = "starting"
        """'starting' (no correction yet, nothing logged), 'acting' (the adapter acts) or 'fallback' (the student
        alone since ``_fallback_since``, after one warning)."""
        self._fallback_since = 0.0
        self._last_request: int | None = None  # control step of the newest refresh request
        self._delayed = False  # the due refresh found the worker busy (counted once)
        self._slow_reported = False
        self._acting: _Result | None = None  # the result the current step acts with
        self._t_read = 0.0  # when the running refresh had read its windows (the worker thread's)
        self._first_used: int | None = None  # seq of the newest result whose first step was recorded
        self._causes: Counter[str] = Counter()  # fallbacks per cause (its message without the numbers)
        self.smoothing = float(getattr(policy, "touch_smoothing", 0.0))
        """How much of the previous correction a refresh keeps (adapters.touch_delay.smooth); a failed refresh
        starts the average over, as a new episode does in simulation."""
        self._smoothed: np.ndarray | None = None  # the newest successful refresh's (smoothed) correction
        self._thread = threading.Thread(target=self._run, name="touch-worker", daemon=True)
        self._thread.start()

    @property
    def active(self) -> bool:
        """True while the adapter acts (the status line's ``touch on``)."""
        return self._state == "acting"

    @property
    def max_age_s(self) -> float:
        """Corrections older than this (s, since their observation) are dropped."""
        return self.stats.max_age_s

    @property
    def busy(self) -> bool:
        """True while a refresh is running."""
        with self._cv:
            return self._busy

    # ------------------------------------------------------------------ the control loop's side
    def refresh_if_due(self, step: int, obs: Mapping[str, np.ndarray], now: float) -> None:
        """Control step ``step``, observation ``obs`` taken at host time ``now``: request a refresh from it when one is
        due (``touch_every`` steps after the previous request) and the worker is free; never waits."""
        if self._last_request is None or step - self._last_request >= self.every:
            if self.request(step, obs, now):
                self._last_request, self._delayed = step, False
            elif not self._delayed:
                self.stats.delayed_refreshes += 1
                self._delayed = True

    def request(self, seq: int, obs: Mapping[str, np.ndarray], now: float) -> bool:
        """Ask for a refresh from observation ``seq`` (taken at host time ``now``); False while the previous refresh
        is still running (nothing queued)."""
        with self._cv:
            if self._busy or self._stop:
                return False
            self._request, self._busy = (seq, now, {k: np.asarray(obs[k]) for k in self._groups}), True
            self._cv.notify_all()
            return True

    def correction(self, step: int, now: float) -> np.ndarray | None:
        """The correction to act with at control step ``step`` (host time ``now``): the newest finished one if it is
        usable and younger than ``max_age_s``, else None (the student alone). Counts the step, and logs when the
        fallback starts (warning, with the cause) and ends (info)."""
        result = self._latest  # one reference read: the worker replaces it whole
        cause, error = None, None
        if result is None:
            cause = "no touch correction yet"
        elif result.correction is None:
            cause, error = result.cause, result.error
        elif now - result.t_obs > self.max_age_s:
            cause = (f"the newest touch correction is {1e3 * (now - result.t_obs):.0f} ms old (> "
                     f"{1e3 * self.max_age_s:.0f} ms): the touch worker is behind")
        self._acting = result if cause is None else None
        if cause is None:
            self.stats.adapter_steps += 1
            if self.stats.first_correction_step is None:
                self.stats.first_correction_step = step
                log.info("step %d: first touch correction; the adapter acts (the student alone before it)", step)
            elif self._state == "fallback":
                log.info("step %d: touch is back; the adapter acts again after %.2f s as the student alone", step,
                         now - self._fallback_since)
            self._state = "acting"
            return result.correction  # type: ignore[union-attr]
        self.stats.fallback_steps += 1
        if self._state == "acting" or (self._state == "starting" and result is not None):
            self._enter_fallback(f"step {step}", cause, error, now)
        return None

    def commanded(self, step: int, now: float) -> float | None:
        """The control loop sent step ``step``'s command at host time ``now``: record the touch age of the correction
        it acted with (returned, s; None for the student alone) and, at a correction's first step, its latency."""
        result = self._acting
        if result is None:
            return None
        age = now - result.t_touch
        self.stats.age_s.append(age)
        if result.seq != self._first_used:
            self._first_used = result.seq
            self.stats.first_use_age_s.append(age)
            self.stats.first_use_steps[step - result.seq] += 1
        return age

    def _enter_fallback(self, when: str, cause: str | None, error: BaseException | None, now: float) -> None:
        """Start acting as the student alone: one warning naming the cause. A cause that keeps coming back (its
        message up to the numbers: a worker slower than the limit, a flaky stream) warns again only every
        ``REPEAT_WARN_EVERY``-th time and is logged at info in between."""
        self.stats.fallbacks += 1
        self.stats.last_cause = cause
        self._state, self._fallback_since = "fallback", now
        kind = re.sub(r"\d+(\.\d+)?", "#", cause or "")
        self._causes[kind] += 1
        n = self._causes[kind]
        level = logging.WARNING if n == 1 or n % REPEAT_WARN_EVERY == 0 else logging.INFO
        again = "" if n == 1 else f" ({n} times so far)"
        log.log(level, "%s: touch unavailable (%s)%s; acting as the student alone until it is back", when, cause,
                again, exc_info=error)

    def close(self) -> None:
        """Stop the thread without waiting for a refresh in progress (it ends after its current step: reading the
        windows or encoding them). Called by the control loop while the motors may still be on: never blocks."""
        with self._cv:
            self._stop = True
            self._cv.notify_all()

    def join(self, timeout_s: float) -> bool:
        """After :meth:`close`, once the hand is off: wait for a refresh in progress to end (a torch call still running
        on a daemon thread when the interpreter exits aborts the process). False (logged) if it did not."""
        self._thread.join(timeout=timeout_s)
        if self._thread.is_alive():
            log.warning("touch worker still busy %.1f s after the run; leaving it behind", timeout_s)
            return False
        return True

    # ------------------------------------------------------------------ the worker's side
    def _refresh(self, obs: dict[str, np.ndarray]) -> tuple[np.ndarray, float]:
        """One correction (Z,) from every fingertip's window now and ``obs``, and the host time of the newest sample of
        the oldest window; raises when touch is unusable."""
        import torch

        from adapters.bundle import TouchUnavailable

        names = tuple(self.policy.windows)
        serial_only = not {"image", "audio"} & set(names)  # an emulated camera and microphones render on request
        windows, t_touch = {}, math.inf
        for finger in self.policy.fingers:
            reader = self.readers.get(finger)
            if reader is None:
                raise TouchUnavailable(f"no Digit 360 on {finger}")
            window = reader.window(serial_only=serial_only)
            t_touch = min(t_touch, float(window["t_end"]))
            windows[finger] = adapter_inputs(window, names, finger)
        self._t_read = time.monotonic()
        if self._stop:  # closed meanwhile: do not start encoding
            raise TouchUnavailable("the run ended")
        batched = {k: v[None] for k, v in obs.items()}  # (1, ...)
        with torch.inference_mode():
            correction = np.asarray(self.policy.correction(windows, batched), dtype=np.float32)[0]  # (Z,)
        if not np.all(np.isfinite(correction)):  # the policy checks too; nothing non-finite reaches the actor
            raise TouchUnavailable("non-finite touch correction")
        return correction, t_touch

    def _run(self) -> None:
        import torch

        from adapters.bundle import TouchUnavailable
        from rotation.hardware.digit360.reader import SensorStale
        from rotation.hardware.digit360.window import WindowNotReady

        torch.set_num_threads(1)  # this thread's intra-op pool: the control loop and the drivers keep their core
        while True:
            with self._cv:
                self._cv.wait_for(lambda: self._request is not None or self._stop)
                if self._stop:
                    return
                seq, t_obs, obs = self._request  # type: ignore[misc]
                self._request = None
            start = time.monotonic()
            try:
                result = _Result(seq, t_obs, *self._refresh(obs))
            except (SensorStale, WindowNotReady, TouchUnavailable) as err:  # the expected ways touch goes missing
                result = _Result(seq, t_obs, None, cause=f"{type(err).__name__}: {err}")
            except Exception as err:  # a reader's or the encoder's bug must not stop the hand: fall back, say why
                result = _Result(seq, t_obs, None, cause=f"the touch refresh raised {type(err).__name__}: {err}",
                                 error=err)
            done = time.monotonic()
            if result.correction is not None and self._smoothed is not None:
                result = replace(result, correction=smooth(self._smoothed, result.correction, self.smoothing))
            self._smoothed = result.correction  # None after a failed refresh: the next one starts the average over
            with self._cv:
                self.stats.refresh_s.append(done - start)
                if result.correction is not None:
                    self.stats.timings.append(RefreshTiming(self._t_read, start - result.t_touch,
                                                            start - t_obs, self._t_read - start, done - self._t_read))
                if result.correction is None:
                    self.stats.failed_refreshes += 1
                else:
                    self.stats.refreshes += 1
                self._latest = result
                self._busy = False
                self._cv.notify_all()
            self._report_if_slow()

    def _report_if_slow(self) -> None:
        """Warn once when the recent refreshes take longer than the refresh period (the adapter then sees touch
        less often than it was trained with; the loop is not slowed down)."""
        recent = self.stats.refresh_s[-SLOW_REFRESHES:]
        if self._slow_reported or len(recent) < SLOW_REFRESHES or min(recent) <= self.refresh_period_s:
            return
        self._slow_reported = True
        log.warning("touch refreshes take %.0f-%.0f ms, longer than the adapter's refresh period (%d steps, %.0f ms): "
                    "its correction is refreshed less often than in training (a busy or slow machine; an adapter "
                    "reading fewer windows is cheaper)", 1e3 * min(recent), 1e3 * max(recent), self.every,
                    1e3 * self.refresh_period_s)
