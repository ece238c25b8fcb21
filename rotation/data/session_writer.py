"""Writing a session: streams appended as they arrive and flushed so that a crash loses at most the last flush
interval and never corrupts what was flushed (the format: rotation.data.session).
"""

from __future__ import annotations

import datetime as _dt
import math
import threading
import time
from collections.abc import Iterable, Sequence
from pathlib import Path

import h5py
import numpy as np

from rotation.data.session import (
    FORMAT_VERSION,
    STREAMS,
    SessionError,
    SessionMeta,
    StreamSetup,
    check_name,
    software_version,
    to_json,
)


class SessionWriter:
    """Appends streams to a new session file; crash-safe up to the last flush (SWMR, see the module docstring).

    Usage::

        with SessionWriter(path, meta, [StreamSetup("joints/position", rate_hz=20.0), ...]) as w:
            w.append("joints/position", q[None], np.array([t]))   # (n, 16), (n,)
    """

    def __init__(self, path: str | Path, meta: SessionMeta, streams: Iterable[StreamSetup | str],
                 flush_interval_s: float = 1.0, overwrite: bool = False, background: bool = False):
        self.path = Path(path)
        if not flush_interval_s >= 0:
            raise SessionError(f"session {self.path}: flush_interval_s must be >= 0, got {flush_interval_s}")
        if self.path.exists() and not overwrite:
            raise SessionError(f"session {self.path}: file exists (pass overwrite=True to replace it)")
        self.flush_interval_s = float(flush_interval_s)
        setups = [StreamSetup(s) if isinstance(s, str) else s for s in streams]
        if not setups:
            raise SessionError(f"session {self.path}: a session needs at least one stream")
        self._resolved: dict[str, tuple[tuple[int, ...], np.dtype, float]] = {}
        for s in setups:
            self._resolved[s.name] = self._resolve(s)
        self.path.parent.mkdir(parents=True, exist_ok=True)
        self._file = h5py.File(self.path, "w", libver="latest")
        f = self._file
        f.attrs["format_version"] = FORMAT_VERSION
        f.attrs["source"] = meta.source
        f.attrs["object"] = meta.object
        f.attrs["seed"] = int(meta.seed)
        f.attrs["control_hz"] = float(meta.control_hz)
        f.attrs["hand"] = meta.hand
        f.attrs["created"] = meta.created or _dt.datetime.now(_dt.UTC).isoformat(timespec="seconds")
        f.attrs["software_version"] = meta.software_version or software_version()
        f.attrs["properties"] = to_json(meta.properties, f"session {self.path}: properties")
        f.attrs["extra"] = to_json(meta.extra, f"session {self.path}: extra")
        self._data: dict[str, h5py.Dataset] = {}
        self._times: dict[str, h5py.Dataset] = {}
        for name, (shape, dtype, rate) in self._resolved.items():
            spec = STREAMS[name]
            g = f.create_group(f"streams/{name}")
            d = g.create_dataset("data", shape=(0, *shape), maxshape=(None, *shape), dtype=dtype,
                                 chunks=(spec.chunk, *shape), compression=spec.compression)
            d.attrs["rate_hz"] = rate
            d.attrs["units"] = spec.units
            t = g.create_dataset("timestamps", shape=(0,), maxshape=(None,), dtype="float64",
                                 chunks=(max(spec.chunk, 256),))
            self._data[name], self._times[name] = d, t
        f.swmr_mode = True  # from here on no new objects or attributes: the structure is final
        self._pending: dict[str, list[tuple[np.ndarray, np.ndarray]]] = {name: [] for name in self._resolved}
        self._last_t = {name: -math.inf for name in self._resolved}
        self.flushed = {name: 0 for name in self._resolved}
        """Samples per stream written and flushed to disk (what a crash now would keep)."""
        self._last_flush = time.monotonic()
        self.closed = False
        self._lock = threading.Lock()  # guards _pending (appends queue, the flusher takes)
        self._io_lock = threading.Lock()  # one HDF5 writer at a time
        self._error: BaseException | None = None
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        if background:
            self._thread = threading.Thread(target=self._flush_loop, name=f"session-writer:{self.path.name}",
                                            daemon=True)
            self._thread.start()

    def _resolve(self, s: StreamSetup) -> tuple[tuple[int, ...], np.dtype, float]:
        where = f"session {self.path}"
        spec = check_name(s.name, where)
        if s.name in self._resolved:
            raise SessionError(f"{where}: stream {s.name!r} listed twice")
        shape = tuple(s.shape) if s.shape is not None else spec.shape
        if any(d is None for d in shape):
            raise SessionError(f"{where}: stream {s.name!r} needs an explicit shape (spec {spec.shape})")
        if len(shape) != len(spec.shape) or any(e is not None and e != d for e, d in zip(spec.shape, shape,
                                                                                          strict=True)):
            raise SessionError(f"{where}: stream {s.name!r} has sample shape {shape}, the format needs {spec.shape}")
        dtype = np.dtype(s.dtype or spec.dtypes[0])
        if dtype.name not in spec.dtypes:
            raise SessionError(f"{where}: stream {s.name!r} dtype {dtype.name} not in {spec.dtypes}")
        rate = s.rate_hz if s.rate_hz is not None else spec.rate_hz
        if rate is None or not (math.isfinite(rate) and rate > 0):
            raise SessionError(f"{where}: stream {s.name!r} needs a positive rate_hz, got {rate}")
        if spec.rate_hz is not None and not math.isclose(rate, spec.rate_hz, rel_tol=1e-9):
            raise SessionError(f"{where}: stream {s.name!r} runs at {spec.rate_hz} Hz, got rate_hz={rate}")
        return tuple(int(d) for d in shape), dtype, float(rate)

    def append(self, name: str, data: np.ndarray, timestamps: np.ndarray | Sequence[float]) -> None:
        """Queue n samples (n, *sample_shape) with their timestamps (n,) (s); flushes when the interval is due."""
        if self.closed:
            raise SessionError(f"session {self.path}: append to a closed writer")
        where = f"session {self.path}, stream {name!r}"
        if name not in self._resolved:
            raise SessionError(f"{where}: not declared when the writer was opened ({', '.join(self._resolved)})")
        shape, dtype, _ = self._resolved[name]
        data = np.asarray(data)
        t = np.asarray(timestamps, dtype=np.float64)
        if data.shape[1:] != shape or t.shape != data.shape[:1]:
            raise SessionError(f"{where}: expected data (n, {', '.join(map(str, shape))}) and timestamps (n,), got "
                               f"{data.shape} and {t.shape}")
        if data.dtype.kind == "f" and not np.all(np.isfinite(data)):
            raise SessionError(f"{where}: non-finite samples")
        if data.dtype != dtype and not np.can_cast(data.dtype, dtype, casting="same_kind"):
            raise SessionError(f"{where}: cannot store {data.dtype} as {dtype}")
        if len(t) and (not np.all(np.isfinite(t)) or np.any(np.diff(t) < 0) or t[0] < self._last_t[name]):
            raise SessionError(f"{where}: timestamps must be finite and non-decreasing")
        self._raise_background_error()
        if len(t):
            self._last_t[name] = float(t[-1])
            with self._lock:
                self._pending[name].append((data.astype(dtype, copy=False), t))
        if self._thread is None and time.monotonic() - self._last_flush >= self.flush_interval_s:
            self.flush()

    def flush(self) -> None:
        """Write every queued sample and flush the file: what is on disk now survives a crash."""
        with self._io_lock:
            with self._lock:  # take what is queued; appends go on meanwhile
                taken = {name: chunks for name, chunks in self._pending.items() if chunks}
                for name in taken:
                    self._pending[name] = []
            for name, chunks in taken.items():
                data = np.concatenate([c[0] for c in chunks])
                t = np.concatenate([c[1] for c in chunks])
                d, ts = self._data[name], self._times[name]
                n = d.shape[0]
                # timestamps last: a reader never sees a timestamp without its sample
                d.resize(n + len(data), axis=0)
                d[n:] = data
                ts.resize(n + len(t), axis=0)
                ts[n:] = t
            self._file.flush()
            self.flushed = {name: d.shape[0] for name, d in self._data.items()}
            self._last_flush = time.monotonic()

    def _flush_loop(self) -> None:
        """The background writer: flush every ``flush_interval_s`` until stopped; a failure is kept for the caller
        (raised by its next append or close) and ends the loop."""
        while not self._stop.wait(max(self.flush_interval_s, 0.05)):  # an interval of 0 would spin
            try:
                self.flush()
            except BaseException as err:  # noqa: BLE001 -- handed to the caller's thread
                self._error = err
                return

    def _raise_background_error(self) -> None:
        if self._error is not None:
            err = self._error
            raise SessionError(f"session {self.path}: writing failed: {err}") from err

    def _stop_background(self) -> None:
        if self._thread is not None:
            self._stop.set()
            self._thread.join()
            self._thread = None

    def close(self) -> None:
        """Flush, close, and mark the session complete."""
        if self.closed:
            return
        self._stop_background()
        try:
            self._raise_background_error()
            self.flush()
        except BaseException:
            self._file.close()
            self.closed = True
            raise
        self._file.close()
        self.closed = True
        with h5py.File(self.path, "r+", libver="latest") as f:
            f.attrs["complete"] = True

    def abort(self) -> None:
        """Flush and close without marking the session complete (an interrupted recording)."""
        if self.closed:
            return
        self._stop_background()
        try:
            self.flush()
        finally:
            self._file.close()
            self.closed = True

    def __enter__(self) -> SessionWriter:
        return self

    def __exit__(self, exc_type, exc, tb) -> None:
        if exc_type is None:
            self.close()
        else:  # keep what was recorded, but do not mark it complete
            self.abort()
