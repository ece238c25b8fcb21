"""Xela uSkin on the Allegro hand: a reader of the vendor's ``xela_server`` WebSocket stream, in our taxel order.

Usage::

    with XelaReader(XelaConfig(url="ws://localhost:5000")) as skin:
        t, counts = skin.frames.snapshot()   # host monotonic s (n,), raw counts (n, 368, 3), our taxel order

Stream (docs/reference/hardware.md section 5): USB-CAN adapter -> ``xela_server`` -> WebSocket (default port 5000),
JSON text messages at about 100 Hz. The first is ``{"message": "Welcome"}``; every data message holds one entry
per sensor board under a numeric-string key ("1", "2", ...), each ``{"model": ..., "taxels": n, "data": "hex,hex,
..."}`` with 3 comma-separated hexadecimal 16-bit values (X, Y, Z) per taxel, and optionally ``calibrated`` forces
(ignored: sessions store raw counts). :func:`parse_message` turns one message into a (368, 3) frame.

Taxel order. Ours is the order of ``PADS`` below: per finger (index, middle, ring) tip, medial, distal and
proximal phalanx pads, the thumb's tip, medial, proximal pads, then the three palm pads, row-major inside a pad
(envs.sensors.xela.PADS, which the simulated skin and every session use; tests check the two tables agree). The
vendor numbers boards in the order they are chained on the CAN bus, which the public facts do not give:
``XelaConfig.sensor_pads`` names our pad for each vendor sensor number. The default (``VENDOR_SENSOR_PADS``)
assumes a chain in our pad order; a sensor whose taxel count does not fit its pad (a 16-taxel board mapped to a
fingertip) is refused as malformed, but two boards of one kind swapped are not detectable from the stream: press
each pad once after installing and check which taxels move (rotate inspect-touch on the recording). Inside a
pad the vendor's taxel k is our taxel ``VENDOR_TAXEL_ORDER[kind][k]`` (the identity until a press test says
otherwise).

Faults: a malformed message (not JSON, a missing or extra sensor, a wrong taxel count, a value that is not a
16-bit hexadecimal number) is skipped, counted in ``counters["skipped"]`` and logged with what is wrong (the
first one and every 100th); a lost connection is logged and re-opened every ``reconnect_s``
(``counters["disconnects"]``). Timestamps are host ``time.monotonic()`` seconds at receipt (the stream carries
none). No torch, no MuJoCo: uses the ``websockets`` package (sync client).
"""

from __future__ import annotations

import json
import logging
import threading
import time
from dataclasses import dataclass, field
from urllib.parse import urlparse

import numpy as np

from rotation.hardware.digit360.window import RingBuffer

log = logging.getLogger("rotation.hardware.xela")  # the device's logger (messages name the device)

KIND_TAXELS = {"phalanx": 16, "palm": 24, "fingertip": 30}
"""Taxels of a pad of each kind (docs/reference/hardware.md section 5: 4x4, 4x6, a fingertip's 30 of a 6x6 grid)."""
PADS: tuple[tuple[str, str], ...] = (
    ("index_tip", "fingertip"), ("index_medial", "phalanx"), ("index_proximal_1", "phalanx"),
    ("index_proximal_0", "phalanx"),
    ("middle_tip", "fingertip"), ("middle_medial", "phalanx"), ("middle_proximal_1", "phalanx"),
    ("middle_proximal_0", "phalanx"),
    ("ring_tip", "fingertip"), ("ring_medial", "phalanx"), ("ring_proximal_1", "phalanx"),
    ("ring_proximal_0", "phalanx"),
    ("thumb_tip", "fingertip"), ("thumb_medial", "phalanx"), ("thumb_proximal", "phalanx"),
    ("palm_index", "palm"), ("palm_middle", "palm"), ("palm_ring", "palm"),
)
"""(name, kind) of our 18 pads in taxel order (the same table as envs.sensors.xela.PADS; tested)."""
PAD_TAXELS = tuple(KIND_TAXELS[kind] for _, kind in PADS)
PAD_START = dict(zip((name for name, _ in PADS), np.cumsum([0, *PAD_TAXELS[:-1]]).tolist(), strict=True))
"""Pad name -> index of its first taxel."""
NUM_TAXELS = sum(PAD_TAXELS)
SAMPLE_HZ = 100.0
"""Xela sample rate (docs/reference/hardware.md section 5)."""
VENDOR_SENSOR_PADS: tuple[str, ...] = tuple(name for name, _ in PADS)
"""Default map: vendor sensor number k (1-based) is our pad VENDOR_SENSOR_PADS[k - 1] (see the module docstring)."""
VENDOR_TAXEL_ORDER = {kind: tuple(range(n)) for kind, n in KIND_TAXELS.items()}
"""Per pad kind: vendor taxel k of a pad is our taxel VENDOR_TAXEL_ORDER[kind][k] of that pad (identity)."""
MAX_COUNT = 0xFFFF
assert NUM_TAXELS == 368 and len(PADS) == 18


class XelaMessageError(ValueError):
    """A message from xela_server that is not a frame of this skin (the text says what is wrong)."""


class SensorStale(RuntimeError):
    """No frame for longer than the stale timeout (server down, or the skin stopped)."""


def parse_url(url: str, field_name: str = "url") -> str:
    """``url`` if it is a ws:// or wss:// URL with a host, else a ValueError naming ``field_name``."""
    parts = urlparse(url.strip()) if isinstance(url, str) else None
    if parts is None or parts.scheme not in ("ws", "wss") or not parts.hostname:
        raise ValueError(f"{field_name}: {url!r} is not a WebSocket URL; expected ws://HOST:PORT (xela_server "
                         "listens on port 5000 by default, e.g. ws://localhost:5000)")
    try:
        parts.port  # noqa: B018 - raises ValueError on a bad port
    except ValueError as err:
        raise ValueError(f"{field_name}: {url!r}: {err}") from None
    return url.strip()


@dataclass(frozen=True)
class XelaLayout:
    """How vendor sensors map onto our taxels: for vendor sensor k, our pad ``sensor_pads[k - 1]``."""

    sensor_pads: tuple[str, ...] = VENDOR_SENSOR_PADS

    def __post_init__(self) -> None:
        names = [name for name, _ in PADS]
        bad = [p for p in self.sensor_pads if p not in names]
        if bad or sorted(self.sensor_pads) != sorted(names):
            raise ValueError(f"sensor_pads: need each of our 18 pads exactly once ({', '.join(names)}), got "
                             f"{list(self.sensor_pads)}")

    def targets(self) -> dict[str, tuple[int, np.ndarray]]:
        """Vendor sensor key -> (taxel count, our taxel index of each vendor taxel)."""
        kinds = dict(PADS)
        out = {}
        for k, pad in enumerate(self.sensor_pads, start=1):
            kind = kinds[pad]
            order = np.asarray(VENDOR_TAXEL_ORDER[kind], dtype=np.int64)
            out[str(k)] = (KIND_TAXELS[kind], PAD_START[pad] + order)
        return out


def parse_message(text: str | bytes, layout: XelaLayout | None = None,
                  _targets: dict[str, tuple[int, np.ndarray]] | None = None) -> np.ndarray | None:
    """One xela_server message -> (368, 3) float32 raw counts in our taxel order; None for a message without sensor
    data (the welcome message, other status messages). Raises :class:`XelaMessageError` naming what is wrong."""
    targets = _targets if _targets is not None else (layout or XelaLayout()).targets()
    try:
        obj = json.loads(text)
    except (json.JSONDecodeError, UnicodeDecodeError) as err:
        raise XelaMessageError(f"not JSON ({err.msg if hasattr(err, 'msg') else err}): {str(text)[:60]!r}") from None
    if not isinstance(obj, dict):
        raise XelaMessageError(f"expected a JSON object, got {type(obj).__name__}")
    sensors = {k: v for k, v in obj.items() if k.strip().isdigit()}
    if not sensors:
        if "message" in obj:
            return None  # {"message": "Welcome"} and the like
        raise XelaMessageError(f"no sensor entries (numeric keys) and no 'message': keys {sorted(obj)[:6]}")
    missing = sorted(set(targets) - set(sensors), key=int)
    extra = sorted(set(sensors) - set(targets), key=int)
    if missing or extra:
        raise XelaMessageError(f"sensors {sorted(sensors, key=int)}: "
                               + "; ".join(p for p in (f"missing {missing}" if missing else "",
                                                       f"unexpected {extra}" if extra else "") if p)
                               + f" (the skin has sensors 1..{len(targets)})")
    frame = np.empty((NUM_TAXELS, 3), np.float32)
    for key, (count, taxels) in targets.items():
        entry = sensors[key]
        if not isinstance(entry, dict) or not isinstance(entry.get("data"), str):
            raise XelaMessageError(f"sensor {key}: expected an object with a 'data' string, got {str(entry)[:60]!r}")
        n = entry.get("taxels", count)
        if not isinstance(n, int) or isinstance(n, bool) or n != count:
            raise XelaMessageError(f"sensor {key}: {n!r} taxels, but it maps to a pad of {count} (check "
                                   "XelaConfig.sensor_pads)")
        words = [w.strip() for w in entry["data"].split(",") if w.strip()]
        if len(words) != 3 * count:
            raise XelaMessageError(f"sensor {key}: {len(words)} values in 'data', expected 3 x {count} = {3 * count}")
        try:
            values = np.array([int(w, 16) for w in words], dtype=np.int64)
        except ValueError:
            bad = next(w for w in words if not _is_hex(w))
            raise XelaMessageError(f"sensor {key}: {bad!r} is not a hexadecimal number") from None
        if values.min() < 0 or values.max() > MAX_COUNT:
            raise XelaMessageError(f"sensor {key}: values outside the 16-bit range 0..{MAX_COUNT:#x}")
        frame[taxels] = values.reshape(count, 3)
    return frame


def format_message(frame: np.ndarray, layout: XelaLayout | None = None, models: dict[str, str] | None = None) -> str:
    """The inverse of :func:`parse_message`: a (368, 3) frame in our taxel order -> one xela_server data message
    (sensors "1".."18", ``model``, ``taxels``, ``data`` as 4-digit hexadecimal words). For emulators and tests."""
    frame = np.asarray(frame)
    if frame.shape != (NUM_TAXELS, 3):
        raise ValueError(f"format_message: expected a ({NUM_TAXELS}, 3) frame, got {frame.shape}")
    kinds = dict(PADS)
    layout = layout or XelaLayout()
    out = {}
    for (key, (count, taxels)), pad in zip(layout.targets().items(), layout.sensor_pads, strict=True):
        values = np.clip(np.rint(frame[taxels]), 0, MAX_COUNT).astype(np.int64).reshape(-1)
        out[key] = {"model": (models or {}).get(kinds[pad], kinds[pad]), "taxels": count,
                    "data": ",".join(f"{v:04x}" for v in values)}
    return json.dumps(out)


def _is_hex(word: str) -> bool:
    try:
        int(word, 16)
    except ValueError:
        return False
    return True


@dataclass(frozen=True)
class XelaConfig:
    """One Xela skin behind xela_server."""

    url: str = "ws://localhost:5000"
    """xela_server's WebSocket URL."""
    sensor_pads: tuple[str, ...] = VENDOR_SENSOR_PADS
    """Our pad of each vendor sensor number (1, 2, ...): see the module docstring."""
    reconnect_s: float = 0.5
    """Wait (s) before re-opening a lost connection."""
    open_timeout_s: float = 2.0
    """Longest wait (s) for the WebSocket handshake."""
    stale_timeout_s: float = 0.1
    """Newest frame older than this (s) -> :meth:`XelaReader.check_fresh` raises SensorStale."""
    buffer_s: float = 5.0
    """History kept (s)."""
    layout: XelaLayout = field(init=False)

    def __post_init__(self) -> None:
        parse_url(self.url)
        object.__setattr__(self, "layout", XelaLayout(tuple(self.sensor_pads)))
        for name in ("reconnect_s", "open_timeout_s", "stale_timeout_s", "buffer_s"):
            value = getattr(self, name)
            if isinstance(value, bool) or not isinstance(value, int | float) or not 0 < value < 3600:
                raise ValueError(f"XelaConfig.{name} must be in (0, 3600) s, got {value!r}")


class XelaReader:
    """A reader thread filling ``frames`` (RingBuffer of (368, 3) raw counts, host monotonic timestamps); a context
    manager. ``counters``: ``frames``, ``skipped`` (malformed messages), ``connects``, ``disconnects``;
    ``last_error``: the newest problem, as text."""

    LOG_EVERY = 100

    def __init__(self, cfg: XelaConfig, name: str = "xela") -> None:
        self.cfg, self.name = cfg, name
        self.frames = RingBuffer(int(cfg.buffer_s * SAMPLE_HZ * 1.5), (NUM_TAXELS, 3), np.float32)
        self.counters = {"frames": 0, "skipped": 0, "connects": 0, "disconnects": 0}
        self.last_error = ""
        self.connected = threading.Event()
        self._targets = cfg.layout.targets()
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None

    # ---------------------------------------------------------------------------------------- lifecycle
    def __enter__(self) -> XelaReader:
        self._thread = threading.Thread(target=self._run, name=f"{self.name}-reader", daemon=True)
        self._thread.start()
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def close(self) -> None:
        self._stop.set()
        if self._thread is not None:
            self._thread.join(timeout=self.cfg.open_timeout_s + 1.0)
            self._thread = None

    def _run(self) -> None:
        from websockets.exceptions import ConnectionClosed, InvalidHandshake, InvalidURI
        from websockets.sync.client import connect

        while not self._stop.is_set():
            try:
                with connect(self.cfg.url, open_timeout=self.cfg.open_timeout_s, proxy=None) as ws:
                    self.counters["connects"] += 1
                    self.connected.set()
                    if self.counters["connects"] > 1:
                        log.info("%s: reconnected to %s", self.name, self.cfg.url)
                    while not self._stop.is_set():
                        try:
                            message = ws.recv(timeout=0.2)
                        except TimeoutError:
                            continue
                        self.handle(message, time.monotonic())
            except (ConnectionClosed, InvalidHandshake, InvalidURI, OSError, TimeoutError) as err:
                self.connected.clear()
                if self._stop.is_set():
                    break
                self.counters["disconnects"] += 1
                self.last_error = f"connection to {self.cfg.url}: {type(err).__name__}: {err}"
                if self.counters["disconnects"] == 1 or self.counters["disconnects"] % self.LOG_EVERY == 0:
                    log.warning("%s: %s; retrying every %.1f s (%d disconnects)", self.name, self.last_error,
                                self.cfg.reconnect_s, self.counters["disconnects"])
                self._stop.wait(self.cfg.reconnect_s)
        self.connected.clear()

    def handle(self, message: str | bytes, t: float) -> None:
        """One received message at host time ``t``: a frame into the buffer, a malformed one counted and logged."""
        try:
            frame = parse_message(message, _targets=self._targets)
        except XelaMessageError as err:
            self.counters["skipped"] += 1
            self.last_error = f"skipped a malformed message: {err}"
            if self.counters["skipped"] == 1 or self.counters["skipped"] % self.LOG_EVERY == 0:
                log.warning("%s: %s (%d skipped so far)", self.name, self.last_error, self.counters["skipped"])
            return
        if frame is not None:
            self.frames.append(t, frame)
            self.counters["frames"] += 1

    # --------------------------------------------------------------------------------------------- access
    def check_fresh(self, now: float | None = None) -> None:
        """SensorStale unless the newest frame is younger than ``stale_timeout_s``."""
        now = time.monotonic() if now is None else now
        age = now - self.frames.newest_time()
        if not age < self.cfg.stale_timeout_s:
            raise SensorStale(f"{self.name}: no frame for {age:.3f} s (> {self.cfg.stale_timeout_s} s); "
                              f"{self.last_error or 'no problem reported'}")

    def recent(self, seconds: float) -> tuple[np.ndarray, np.ndarray]:
        """Frames of the last ``seconds`` (up to the newest): (t (n,), counts (n, 368, 3))."""
        t, v = self.frames.snapshot()
        keep = t >= (t[-1] - seconds) if len(t) else np.zeros(0, bool)
        return t[keep], v[keep]

    def wait_frames(self, count: int, timeout_s: float) -> bool:
        """Wait until ``count`` frames have arrived (True) or ``timeout_s`` passed (False)."""
        end = time.monotonic() + timeout_s
        while self.counters["frames"] < count and time.monotonic() < end:
            time.sleep(0.01)
        return self.counters["frames"] >= count


def probe_server(url: str, timeout_s: float = 2.0) -> str:
    """Connect once and read the first message: '' if xela_server answers, else why not (one line)."""
    from websockets.exceptions import InvalidHandshake, InvalidURI, WebSocketException
    from websockets.sync.client import connect

    try:
        with connect(url, open_timeout=timeout_s, proxy=None) as ws:
            ws.recv(timeout=timeout_s)
    except TimeoutError:
        return f"connected to {url} but no message within {timeout_s:g} s"
    except (InvalidHandshake, InvalidURI, WebSocketException, OSError) as err:
        return f"{type(err).__name__}: {err}"
    return ""
