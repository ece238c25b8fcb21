"""Reading a session: its metadata and streams, checked against the format (rotation.data.session), each stream
as timestamps and values.
"""

from __future__ import annotations

import json
import math
from collections.abc import Iterable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import h5py
import numpy as np

from envs.constants import FINGERS
from rotation.data.session import FORMAT_VERSION, RATE_TOLERANCE, SessionError, SessionMeta, check_name, log


@dataclass
class Stream:
    """One stream read from a session: data (N, *shape) and timestamps (N,) (s), with its declared rate."""

    name: str
    data: Any
    """np.ndarray, or an h5py.Dataset for lazily read streams (images)."""
    timestamps: np.ndarray
    rate_hz: float

    def __len__(self) -> int:
        return len(self.timestamps)


class SessionReader:
    """Opens a session and validates it; every problem is a :class:`SessionError` naming the file and stream.

    Checks at open: format version (missing, or newer than this code), metadata, and the presence of the streams
    in ``require``. Checks per stream on first read: known name, sample shape and dtype, declared rate against the
    format and against the timestamps, finite and non-decreasing timestamps, finite samples (float streams), as
    many timestamps as samples. Nothing is reshaped or cast to make a bad file fit.
    """

    def __init__(self, path: str | Path, require: Iterable[str] = ()):
        self.path = Path(path)
        if not self.path.is_file():
            raise SessionError(f"session {self.path}: no such file")
        try:
            self._file = h5py.File(self.path, "r", swmr=True)  # also opens a file whose writer was killed
        except OSError:
            try:
                self._file = h5py.File(self.path, "r")
            except OSError as err:
                raise SessionError(f"session {self.path}: not a readable HDF5 file ({err})") from None
        attrs = self._file.attrs
        if "format_version" not in attrs:
            self.close()
            raise SessionError(f"session {self.path}: no format_version attribute (not a session file)")
        version = int(attrs["format_version"])
        if version > FORMAT_VERSION:
            self.close()
            raise SessionError(f"session {self.path}: format version {version} is newer than this code reads "
                               f"({FORMAT_VERSION}); update the package")
        try:
            self.meta = SessionMeta(
                source=str(attrs["source"]), object=str(attrs["object"]), control_hz=float(attrs["control_hz"]),
                seed=int(attrs.get("seed", -1)), properties=json.loads(attrs.get("properties", "{}")),
                hand=str(attrs.get("hand", "allegro")), created=str(attrs.get("created", "")),
                software_version=str(attrs.get("software_version", "")), extra=json.loads(attrs.get("extra", "{}")),
            )
        except (KeyError, ValueError) as err:
            self.close()
            raise SessionError(f"session {self.path}: bad metadata ({err})") from None
        self.version = version
        self.complete = bool(attrs.get("complete", False))
        """False for a session whose writer did not close it (crashed or still recording)."""
        self.names: tuple[str, ...] = tuple(sorted(self._walk()))
        missing = [n for n in require if n not in self.names]
        if missing:
            self.close()
            raise SessionError(f"session {self.path}: missing stream(s) {', '.join(missing)} "
                               f"(has: {', '.join(self.names) or 'none'})")
        self._cache: dict[str, Stream] = {}

    def _walk(self) -> list[str]:
        out: list[str] = []
        if "streams" not in self._file:
            return out

        def visit(name: str, obj: Any) -> None:
            if isinstance(obj, h5py.Group) and "data" in obj and "timestamps" in obj:
                out.append(name)

        self._file["streams"].visititems(visit)
        return out

    def has(self, name: str) -> bool:
        return name in self.names

    def stream(self, name: str, lazy: bool = False) -> Stream:
        """Validated stream ``name``; ``lazy`` keeps the data as an h5py dataset (images, audio: read window by
        window, so the finite-sample check is left to the reader of each window)."""
        if name in self._cache and (lazy or not isinstance(self._cache[name].data, h5py.Dataset)):
            return self._cache[name]
        where = f"session {self.path}, stream {name!r}"
        if name not in self.names:
            raise SessionError(f"{where}: missing (has: {', '.join(self.names) or 'none'})")
        spec = check_name(name, f"session {self.path}")
        group = self._file[f"streams/{name}"]
        d, ts = group["data"], group["timestamps"]
        if isinstance(d, h5py.Dataset) and self._file.swmr_mode:
            d.refresh()
            ts.refresh()
        shape = d.shape[1:]
        if len(shape) != len(spec.shape) or any(e is not None and e != s for e, s in zip(spec.shape, shape,
                                                                                          strict=True)):
            raise SessionError(f"{where}: sample shape {shape}, the format needs {spec.shape}")
        if d.dtype.name not in spec.dtypes:
            raise SessionError(f"{where}: dtype {d.dtype.name}, the format allows {spec.dtypes}")
        rate = float(d.attrs.get("rate_hz", float("nan")))
        if not (math.isfinite(rate) and rate > 0):
            raise SessionError(f"{where}: missing or bad rate_hz attribute ({rate})")
        if spec.rate_hz is not None and not math.isclose(rate, spec.rate_hz, rel_tol=1e-6):
            raise SessionError(f"{where}: declared rate {rate} Hz, the format needs {spec.rate_hz} Hz")
        t = np.asarray(ts[:], dtype=np.float64)
        n = len(d)
        if len(t) != n:
            if self.complete:
                raise SessionError(f"{where}: {n} samples but {len(t)} timestamps")
            n = min(n, len(t))  # an interrupted writer: keep the samples that have both
            t = t[:n]
        if not np.all(np.isfinite(t)) or np.any(np.diff(t) < 0):
            raise SessionError(f"{where}: timestamps are not finite and non-decreasing")
        if n >= 3:
            step = float(np.median(np.diff(t)))
            if not math.isclose(step, 1.0 / rate, rel_tol=RATE_TOLERANCE):
                message = f"{where}: timestamps step {step:.6g} s, but rate_hz={rate} (expected {1.0 / rate:.6g} s)"
                if self.complete and spec.rate_hz is None:
                    raise SessionError(message)
                # a run that ended in a fault (a control loop that could not hold its rate), or a sensor the host
                # read slower than it streams: the timestamps are the true ones, so the record is kept, and said
                # to be off its declared rate
                why = ("the session is not complete (its run ended early or in a fault)" if not self.complete else
                       f"a sensor stream stamped on arrival: it came at {1.0 / step:.3g} of its declared {rate:g} "
                       "samples a second")
                log.warning("%s; kept, as %s", message, why)
        if lazy:
            data: Any = d
        else:
            data = d[:n]
            if data.dtype.kind == "f" and not np.all(np.isfinite(data)):
                bad = int(np.flatnonzero(~np.isfinite(data.reshape(n, -1)).all(axis=1))[0])
                raise SessionError(f"{where}: non-finite samples (first at index {bad}, t={t[bad]:.4f} s)")
        out = Stream(name, data, t, rate)
        self._cache[name] = out
        return out

    def fingers_with_touch(self) -> tuple[str, ...]:
        """Fingertips with Digit 360 data: recorded streams or simulated contact fields."""
        return tuple(f for f in FINGERS if any(n.startswith(f"digit360/{f}/") for n in self.names))

    def close(self) -> None:
        if getattr(self, "_file", None) is not None:
            self._file.close()
            self._file = None

    def __enter__(self) -> SessionReader:
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    def __repr__(self) -> str:
        return (f"SessionReader({str(self.path)!r}, source={self.meta.source}, object={self.meta.object!r}, "
                f"streams={len(self.names)}, complete={self.complete})")
