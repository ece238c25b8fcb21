"""The session format: one HDF5 file per recording, the same for simulation and the real hand.

Layout (format version 1). A *stream* is a sequence of samples with one timestamp each; every stream lives in its
own group with two resizable, chunked datasets::

    /                                   attrs: format_version (int), source ("sim" | "real"), object (str),
                                               seed (int, -1 if none), created (ISO 8601 UTC), software_version,
                                               hand (str), control_hz (float), properties (JSON object),
                                               extra (JSON object), complete (bool, only once closed cleanly)
    /streams/<name>/data                (N, *sample_shape)  attrs: rate_hz, units
    /streams/<name>/timestamps          (N,) float64, seconds since the session started, non-decreasing

Stream names (``STREAMS`` is the registry; the reader rejects anything that does not match it):

============================  ==================  ===============  =========  =================================
name                          sample shape        dtype            rate (Hz)  meaning
============================  ==================  ===============  =========  =================================
joints/position               (16,)               float32/64       any        measured joint angles (rad), bus order
joints/target                 (16,)               float32/64       any        commanded joint targets (rad)
joints/torque                 (16,)               float32/64       any        commanded / measured torques (N m)
digit360/<finger>/image       (H, W, 3)           uint8            30         camera frames, RGB
digit360/<finger>/audio       (2,)                int16/float32    48000      two contact microphones, int16 counts
digit360/<finger>/imu         (3,)                float32/64       400        accelerometer (g)
digit360/<finger>/pressure    (1,)                float32/64       200        absolute pressure (hPa)
digit360/<finger>/contact     (20,)               float32          any        simulated contact fields (sim only):
                                                                               envs.sensors.digit360.CONTACT_FIELDS
skin/xela                     (368, 3)            float32/64       100        Xela taxels (raw counts, X Y Z;
                                                                               taxel order envs.sensors.xela.PADS)
skin/taxel_pos                (368, 3)            float32/64       100        taxel positions (m, hand frame) at
                                                                               each skin sample (sim: kinematics)
labels/force                  (4, 3)              float32/64       any        per fingertip [normal, shear x, shear y]
                                                                               (N, force on the dome, sensor frame)
labels/contact_force          (4, 2)              float32/64       any        per fingertip [normal, tangential]
                                                                               (N, force on the dome at its
                                                                               strongest contact, contact frame)
labels/slip                   (4,)                float32/64       any        per fingertip slip speed (m/s)
labels/contact                (4,)                uint8            any        per fingertip contact flag
labels/object_pose            (7,)                float32/64       any        object position (m) + quaternion wxyz,
                                                                               world frame
labels/priv                   (9,)                float32/64       any        privileged vector (envs.constants)
labels/z                      (8,)                float32/64       any        the teacher's latent
labels/skin_force             (18, 3)             float32/64       any        per Xela pad [normal, shear x,
                                                                               shear y] (N, force on the pad, pad
                                                                               frame; envs.sensors.xela.PADS)
labels/joystick               (3,)                float32/64       any        joystick [roll, pitch, yaw] (rad,
                                                                               envs.joystick)
============================  ==================  ===============  =========  =================================

``<finger>`` is one of index, middle, ring, thumb. Fixed rates are the Digit 360's (reference/hardware.md section 4)
and Xela's (reference/sparsh.md); "any" rates are declared per session in the ``rate_hz`` attribute (e.g. the
control rate) and checked against the timestamps: a declared-rate stream off its rate makes a complete session
unreadable (a writer's bug), while a sensor stream at a fixed rate, stamped on arrival at the host, may come out
slower than its sensor when the host fell behind (a busy machine reading a camera): it is kept, with a warning that
names the rate it had, as is every stream of an incomplete session (a run that ended in a fault). A Digit 360
fingertip is stored either as its recorded streams (real hand) or as its contact fields (simulation), from which
the loader renders the four modalities (envs.sensors.digit360_render). A session with skin streams carries the
static taxel facts in ``extra["skin"]`` (envs.sensors.xela.skin_metadata: pad names, taxels per pad, taxel type ids
and names). The object's properties (``properties``) are the simulated parameters in sim (scale, mass kg, friction,
com m) and whatever was measured on the real object.

Crash safety: the writer keeps the file in HDF5's single-writer/multiple-reader mode (SWMR, ``libver="latest"``),
creates every dataset up front, buffers appends in memory and writes + flushes them every ``flush_interval_s``. In
SWMR mode HDF5 orders its metadata writes so that the file is valid at any instant; a writer killed at any point
leaves a file that :class:`SessionReader` opens with everything up to the last flush. Only a cleanly closed
session carries ``complete = True``. With ``background=True`` the writes and flushes run on the writer's own thread
(appends only queue), so a caller with a deadline (the deploy loop recording camera frames, about 18 MB/s for
four Digit 360s) never waits for the disk; a write that fails there is raised by the next ``append`` or ``close``.
"""

from __future__ import annotations

import datetime as _dt
import json
import logging
import math
import threading
import time
from collections.abc import Iterable, Sequence
from dataclasses import dataclass, field
from importlib import metadata as _metadata
from pathlib import Path
from typing import Any, Literal

import h5py
import numpy as np

from envs.constants import FINGERS, NUM_JOINTS, PRIV_DIM
from envs.sensors.digit360 import NUM_FIELDS

log = logging.getLogger(__name__)

FORMAT_VERSION = 1
"""Version of the layout above written by this code; a reader refuses files with a newer version."""
LATENT_DIM = 8
"""Size of the teacher's latent z (Hora's env-factor encoder output, reference/hora.md)."""
XELA_TAXELS = 368
"""Taxels of the Xela skin on the Allegro hand (reference/hardware.md section 5)."""
XELA_PADS = 18
"""Pads of the Xela skin on the Allegro hand (envs.sensors.xela.PADS)."""
RATE_TOLERANCE = 0.1
"""A stream's median timestamp step may differ from 1 / rate_hz by this fraction (jittery USB clocks)."""


class SessionError(ValueError):
    """A session file that cannot be written or read as asked; the message names the file and the stream."""


@dataclass(frozen=True)
class StreamSpec:
    """What a stream must look like: per-sample shape (None = any size), allowed dtypes, nominal rate."""

    shape: tuple[int | None, ...]
    dtypes: tuple[str, ...]
    rate_hz: float | None
    """Nominal rate (Hz); None: declared by the writer per session (control rate, physics rate)."""
    units: str
    chunk: int = 256
    """Samples per HDF5 chunk (appends resize by whole chunks cheaply)."""
    compression: str | None = None


_FLOAT = ("float32", "float64")


def _stream_registry() -> dict[str, StreamSpec]:
    streams = {
        "joints/position": StreamSpec((NUM_JOINTS,), _FLOAT, None, "rad"),
        "joints/target": StreamSpec((NUM_JOINTS,), _FLOAT, None, "rad"),
        "joints/torque": StreamSpec((NUM_JOINTS,), _FLOAT, None, "N m"),
        "skin/xela": StreamSpec((XELA_TAXELS, 3), _FLOAT, 100.0, "raw counts"),
        "skin/taxel_pos": StreamSpec((XELA_TAXELS, 3), _FLOAT, 100.0, "m, hand frame"),
        "labels/skin_force": StreamSpec((XELA_PADS, 3), _FLOAT, None, "N, pad frame [normal, shear x, shear y]"),
        "labels/joystick": StreamSpec((3,), _FLOAT, None, "rad [roll, pitch, yaw]"),
        "labels/force": StreamSpec((len(FINGERS), 3), _FLOAT, None, "N"),
        "labels/contact_force": StreamSpec((len(FINGERS), 2), _FLOAT, None, "N, contact frame [normal, tangential]"),
        "labels/slip": StreamSpec((len(FINGERS),), _FLOAT, None, "m/s"),
        "labels/contact": StreamSpec((len(FINGERS),), ("uint8", "bool"), None, "flag"),
        "labels/object_pose": StreamSpec((7,), _FLOAT, None, "m, quaternion wxyz"),
        "labels/priv": StreamSpec((PRIV_DIM,), _FLOAT, None, "envs.constants.PRIV_FIELDS"),
        "labels/z": StreamSpec((LATENT_DIM,), _FLOAT, None, "latent"),
    }
    for f in FINGERS:
        streams[f"digit360/{f}/image"] = StreamSpec((None, None, 3), ("uint8",), 30.0, "RGB", chunk=1,
                                                    compression="lzf")
        streams[f"digit360/{f}/audio"] = StreamSpec((2,), ("int16", "float32"), 48000.0, "int16 counts", chunk=4800)
        streams[f"digit360/{f}/imu"] = StreamSpec((3,), _FLOAT, 400.0, "g", chunk=1024)
        streams[f"digit360/{f}/pressure"] = StreamSpec((1,), _FLOAT, 200.0, "hPa", chunk=1024)
        streams[f"digit360/{f}/contact"] = StreamSpec((NUM_FIELDS,), ("float32",), None, "SI (CONTACT_FIELDS)",
                                                      chunk=512)
    return streams


STREAMS: dict[str, StreamSpec] = _stream_registry()
"""Every stream a session may hold, by name (see the module docstring)."""


def software_version() -> str:
    try:
        return _metadata.version("tactile-rotation")
    except _metadata.PackageNotFoundError:
        return "unknown"


@dataclass(frozen=True)
class SessionMeta:
    """Session-level metadata, stored as root attributes."""

    source: Literal["sim", "real"]
    """Where the data came from."""
    object: str
    """Object name (envs.objects for simulation; free text for a real object)."""
    control_hz: float
    """Policy / command rate of the recording (Hz)."""
    seed: int = -1
    """Seed of a simulated session (-1: none)."""
    properties: dict[str, Any] = field(default_factory=dict)
    """Object properties: simulated parameters, or those measured on the real object (SI units)."""
    hand: str = "allegro"
    """Hand model ('allegro' or 'leap')."""
    created: str = ""
    """ISO 8601 UTC creation time; filled by the writer when empty."""
    software_version: str = ""
    """Version of this package that wrote the file; filled by the writer when empty."""
    extra: dict[str, Any] = field(default_factory=dict)
    """Anything else worth keeping (configs, operator notes), JSON-serializable."""

    def __post_init__(self) -> None:
        if self.source not in ("sim", "real"):
            raise SessionError(f"SessionMeta.source must be 'sim' or 'real', got {self.source!r}")
        if not (math.isfinite(self.control_hz) and self.control_hz > 0):
            raise SessionError(f"SessionMeta.control_hz must be finite and > 0, got {self.control_hz}")


@dataclass(frozen=True)
class StreamSetup:
    """A stream a writer will fill: its shape (required where the spec leaves sizes open), dtype and rate."""

    name: str
    rate_hz: float | None = None
    """Required for streams without a nominal rate; must equal the nominal rate otherwise."""
    shape: tuple[int, ...] | None = None
    dtype: str | None = None


def _to_json(value: dict[str, Any], where: str) -> str:
    """JSON text of a metadata dict (numpy scalars and arrays become plain numbers and lists)."""

    def default(x: Any) -> Any:
        if isinstance(x, np.generic | np.ndarray):
            return x.tolist()
        raise SessionError(f"{where}: {type(x).__name__} is not JSON-serializable")

    return json.dumps(value, sort_keys=True, default=default)


def _check_name(name: str, where: str) -> StreamSpec:
    if name not in STREAMS:
        raise SessionError(f"{where}: unknown stream {name!r}; known streams: {', '.join(sorted(STREAMS))}")
    return STREAMS[name]


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
        f.attrs["properties"] = _to_json(meta.properties, f"session {self.path}: properties")
        f.attrs["extra"] = _to_json(meta.extra, f"session {self.path}: extra")
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
        spec = _check_name(s.name, where)
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
        spec = _check_name(name, f"session {self.path}")
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
