"""Timestamped ring buffers and the Sparsh-X input window of one Digit 360 (pure numpy, no device I/O).

Window contract (docs/reference/sparsh.md "Sparsh-X input contract"), all ending at ``t_end`` = the newest image
timestamp (host ``time.monotonic()`` seconds), never using a sample later than ``t_end``:

- ``image`` (6, 224, 224) uint8: frames t-5 and t stacked channel-major [R(t-5), R(t), G(t-5), G(t), B(t-5), B(t)];
- ``audio`` (2, 27000) int16: the 27,000 samples (0.5625 s at 48 kHz) up to ``t_end`` (nearest sample);
- ``imu`` (224, 3) float32 g: accelerometer linearly resampled onto a 400 Hz grid ending at ``t_end``;
- ``pressure`` (224, 1) float32 hPa: linearly resampled onto a 200 Hz grid ending at ``t_end``.

Grid points after the newest sample (<= ``t_end``) hold that sample (no extrapolation into the future);
a stream that does not cover at least ``min_coverage`` of its window raises :class:`WindowNotReady`.
"""

from __future__ import annotations

import threading
from collections.abc import Sequence
from typing import Any

import numpy as np

IMAGE_SIZE = 224
IMAGE_GAP = 5
"""Frames between the two stacked images (t-5 and t at 30 fps, about 167 ms)."""
AUDIO_RATE = 48_000
AUDIO_SAMPLES = 27_000
"""0.5625 s: 224 Kaldi fbank frames of 5 ms every 2.5 ms = (223 x 120 + 240) samples (docs/reference/sparsh.md)."""
IMU_RATE = 400.0
PRESSURE_RATE = 200.0
SERIES_LEN = 224


class WindowNotReady(RuntimeError):
    """Not enough data yet (or a stream stopped) to fill a window."""


class RingBuffer:
    """Thread-safe fixed-capacity buffer of (timestamp, value) samples, oldest overwritten first."""

    def __init__(self, capacity: int, shape: tuple[int, ...], dtype: np.dtype | type = np.float32) -> None:
        self.t = np.full(capacity, -np.inf)
        self.v = np.zeros((capacity, *shape), dtype=dtype)
        self._n = 0  # total samples ever written
        self._sample_size = int(np.prod(shape))
        self._lock = threading.Lock()

    def __len__(self) -> int:
        return min(self._n, len(self.t))

    def extend(self, t: np.ndarray, v: np.ndarray) -> None:
        """Append samples (times (k,) s, increasing; values (k, *shape))."""
        t = np.atleast_1d(np.asarray(t, dtype=np.float64))
        v = np.asarray(v).reshape(len(t), *self.v.shape[1:])
        cap = len(self.t)
        if len(t) > cap:
            t, v = t[-cap:], v[-cap:]
        with self._lock:
            idx = (self._n + np.arange(len(t))) % cap
            self.t[idx] = t
            self.v[idx] = v
            self._n += len(t)

    def append(self, t: float, v: np.ndarray | Sequence[float] | float) -> None:
        """Append one sample: what :meth:`extend` does for one, without its array building (a reader thread appends
        every frame, hundreds a second per sensor, holding the interpreter's lock meanwhile)."""
        if np.size(v) != self._sample_size:  # what extend's reshape refuses (no silent broadcast)
            raise ValueError(f"a sample of {np.size(v)} value(s); this buffer holds samples of shape "
                             f"{self.v.shape[1:]}")
        with self._lock:
            slot = self._n % len(self.t)
            self.t[slot] = t
            self.v[slot] = v
            self._n += 1

    def _newest(self, k: int) -> np.ndarray:
        """Slots of the newest ``k`` stored samples (at most all of them), oldest first; call with the lock held."""
        k = min(int(k), len(self))
        return (self._n - k + np.arange(k)) % len(self.t)

    def snapshot(self) -> tuple[np.ndarray, np.ndarray]:
        """All stored samples in time order: (t (n,), v (n, *shape)) copies."""
        return self.last(len(self.t))

    def last(self, n: int) -> tuple[np.ndarray, np.ndarray]:
        """The newest ``n`` stored samples (fewer if fewer are stored) in time order, copies."""
        with self._lock:
            order = self._newest(n)
            return self.t[order].copy(), self.v[order].copy()

    @property
    def written(self) -> int:
        """Samples ever written (a drain reads it before :meth:`since` and passes it to its next call)."""
        return self._n

    def since(self, t_last: float, written: int = 0) -> tuple[np.ndarray, np.ndarray]:
        """The stored samples with a time after ``t_last``, in time order, copies (only those are copied: what a
        recording drain takes from a camera's frame buffer). ``written``: only the samples written after the first
        ``written`` ever are looked at, so that a drain's cost follows what is new, not the buffer's capacity (4 s of
        48 kHz audio are 192,000 slots)."""
        with self._lock:
            order = self._newest(max(self._n - int(written), 0))
            order = order[self.t[order] > t_last]
            return self.t[order].copy(), self.v[order].copy()

    def newest_time(self) -> float:
        with self._lock:
            return float(self.t[(self._n - 1) % len(self.t)]) if self._n else -np.inf


def resample_linear(t: np.ndarray, v: np.ndarray, grid: np.ndarray) -> np.ndarray:
    """Linear interpolation of samples (t (n,), v (n, c)) at ``grid`` (m,) -> (m, c); edges hold (no extrapolation)."""
    v2 = v.reshape(len(t), -1).astype(np.float64)
    return np.stack([np.interp(grid, t, v2[:, c]) for c in range(v2.shape[1])], axis=1)


def series_window(buf: RingBuffer, t_end: float, rate: float, n: int = SERIES_LEN,
                  min_coverage: float = 0.9, name: str = "series") -> np.ndarray:
    """(n, c) float32: ``buf`` resampled linearly on the ``rate`` Hz grid of n points ending at ``t_end``."""
    t, v = buf.snapshot()
    return series_from_samples(t, v, t_end, rate, n, min_coverage, name)


def series_from_samples(t: np.ndarray, v: np.ndarray, t_end: float, rate: float, n: int = SERIES_LEN,
                        min_coverage: float = 0.9, name: str = "series") -> np.ndarray:
    """:func:`series_window` on samples already in hand (t (k,) increasing, v (k, c)): a live buffer's snapshot or
    a recorded session's stream, so both give the same window from the same samples."""
    keep = t <= t_end  # never a future sample
    t, v = t[keep], v[keep]
    grid = t_end - (n - 1 - np.arange(n)) / rate
    if len(t) < 2 or (t[-1] - max(t[0], grid[0])) < min_coverage * (grid[-1] - grid[0]):
        span = 0.0 if len(t) < 2 else t[-1] - t[0]
        raise WindowNotReady(f"{name}: {len(t)} samples spanning {span:.3f} s before t_end, need "
                             f"{min_coverage:.0%} of {(n - 1) / rate:.3f} s")
    return resample_linear(t, v, grid).astype(np.float32)


def audio_window(buf: RingBuffer, t_end: float, n: int = AUDIO_SAMPLES) -> np.ndarray:
    """(channels, n) int16: the n audio samples up to the last one at or before ``t_end``."""
    return audio_from_samples(*buf.snapshot(), t_end, n)


def audio_from_samples(t: np.ndarray, v: Any, t_end: float, n: int = AUDIO_SAMPLES) -> np.ndarray:
    """:func:`audio_window` on samples already in hand (t (k,) increasing, v (k, channels), an array or a recorded
    session's lazily read stream): a live buffer's snapshot and a recording give the same window."""
    last = int(np.searchsorted(t, t_end, side="right"))
    if last < n:
        raise WindowNotReady(f"audio: {last} samples before t_end, need {n}")
    return np.ascontiguousarray(np.asarray(v[last - n: last]).T)


def image_window(buf: RingBuffer, gap: int = IMAGE_GAP) -> tuple[np.ndarray, float]:
    """((6, 224, 224) uint8 channel-major [R(t-gap), R(t), G(t-gap), G(t), B(t-gap), B(t)], t of frame t)."""
    t, v = buf.last(gap + 1)
    if len(t) < gap + 1:
        raise WindowNotReady(f"image: {len(t)} frames, need {gap + 1}")
    return channel_major(np.stack([v[0], v[-1]])), float(t[-1])


def channel_major(pair: np.ndarray) -> np.ndarray:
    """Frames t-gap and t (2, H, W, 3) RGB -> (6, H, W) channel-major [R(t-gap), R(t), G(t-gap), G(t), B(...)]."""
    pair = np.asarray(pair)
    return np.ascontiguousarray(pair.transpose(3, 0, 1, 2).reshape(6, *pair.shape[1:3]))  # (3, 2, H, W) -> (6, H, W)


def sparshx_window(image: RingBuffer | None, audio: RingBuffer | None, imu: RingBuffer | None,
                   pressure: RingBuffer | None, t_end: float | None = None) -> dict[str, np.ndarray | float]:
    """Assemble one Sparsh-X sample from the buffers that exist (see the module docstring).

    ``t_end`` defaults to the newest image timestamp; without a camera, to the oldest of the newest sample
    times of the other streams (so no stream needs a future sample). Returns a dict with ``t_end`` and one
    array per available modality.
    """
    out: dict[str, np.ndarray | float] = {}
    if image is not None:
        out["image"], t_img = image_window(image)
        t_end = t_img if t_end is None else t_end
    if t_end is None:
        newest = [b.newest_time() for b in (audio, imu, pressure) if b is not None]
        if not newest or not np.isfinite(min(newest)):
            raise WindowNotReady("no samples yet")
        t_end = min(newest)
    out["t_end"] = float(t_end)
    if audio is not None:
        out["audio"] = audio_window(audio, t_end)
    if imu is not None:
        out["imu"] = series_window(imu, t_end, IMU_RATE, name="imu")
    if pressure is not None:
        out["pressure"] = series_window(pressure, t_end, PRESSURE_RATE, name="pressure")
    return out
