"""Sub-millisecond times for a Digit 360's raw IMU samples, from their sensor time stamp when it proves to be a clock.

Every message carries the device's ``ts`` in milliseconds (docs/reference/digit360_protocol.md: both of Meta's
rate counters treat it as ms). At 400 Hz that rounds each sample's time by up to 0.5 ms, a fifth of the 2.5 ms
between samples: resampled onto the window's 400 Hz grid, the rounding becomes noise in the 100-200 Hz band where
slip and impacts ring. A raw IMU sample also carries ``ts_ght``, the sensor's own time stamp; what it counts is not
published (Bosch's BHY2 code counts 15.625 us ticks, an inference only). So it is not assumed: :class:`FineClock`
fits ``ts_ght`` against ``ts`` over the recent samples and uses it only when the fit says it is a clock finer than
the millisecond one that agrees with it:

- a fit over at least ``MIN_SAMPLES`` samples spanning at least ``MIN_SPAN_MS``;
- more than ``MIN_TICKS_PER_MS`` ticks per millisecond (finer than ``ts``);
- every sample within ``MAX_RESIDUAL_MS`` of the fit (the millisecond rounding alone gives up to 0.5 ms).

Then a sample's device time is ``(ts_ght - a) / b`` milliseconds (a float, on the ``ts`` clock's scale, so the
host mapping of rotation.hardware.digit360.reader is unchanged), refitted every ``REFIT_EVERY`` samples over the
last ``HISTORY`` (drift); otherwise, and after a sensor-time jump (a restart), its ``ts``. The emulated sensor's
``ts_ght`` counts samples (400 per second): coarser than ``ts``, so never used.
"""

from __future__ import annotations

from collections import deque

import numpy as np

MIN_SAMPLES = 200
MIN_SPAN_MS = 1000.0
MIN_TICKS_PER_MS = 2.0
MAX_RESIDUAL_MS = 1.0
REFIT_EVERY = 400
HISTORY = 2000


class FineClock:
    """``__call__(ts_ms, ts_ght) -> device time in ms`` (float): refined by ``ts_ght`` when it is a clock (above)."""

    def __init__(self) -> None:
        self._pairs: deque[tuple[int, int]] = deque(maxlen=HISTORY)
        self._fit: tuple[float, float] | None = None  # (a, b): ts_ght = a + b * ts_ms
        self._since_fit = 0

    @property
    def active(self) -> bool:
        """Whether sample times come from ``ts_ght`` now."""
        return self._fit is not None

    @property
    def ticks_per_ms(self) -> float | None:
        """``ts_ght`` ticks per millisecond of the current fit (None while sample times are the milliseconds)."""
        return None if self._fit is None else float(self._fit[1])

    def __call__(self, ts_ms: int, ts_ght: int) -> float:
        if self._pairs and (ts_ght < self._pairs[-1][1] or ts_ms < self._pairs[-1][0]):
            self._pairs.clear()  # a restart of either clock: start over
            self._fit = None
        self._pairs.append((int(ts_ms), int(ts_ght)))
        self._since_fit += 1
        if self._since_fit >= (REFIT_EVERY if self._fit is not None else 50):
            self._since_fit = 0
            self._fit = self._refit()
        if self._fit is None:
            return float(ts_ms)
        a, b = self._fit
        return (ts_ght - a) / b

    def _refit(self) -> tuple[float, float] | None:
        if len(self._pairs) < MIN_SAMPLES:
            return None
        pairs = np.array(self._pairs, dtype=np.float64)
        ms, ght = pairs[:, 0], pairs[:, 1]
        if ms[-1] - ms[0] < MIN_SPAN_MS:
            return None
        ms0, ght0 = ms[0], ght[0]  # fitted about the first pair: large counters keep their precision
        b, a0 = np.polyfit(ms - ms0, ght - ght0, 1)
        if not (np.isfinite(b) and b > MIN_TICKS_PER_MS):
            return None
        residual_ms = (ght - ght0 - a0) / b - (ms - ms0)
        if np.max(np.abs(residual_ms)) > MAX_RESIDUAL_MS:
            return None
        return ght0 + a0 - b * ms0, b
