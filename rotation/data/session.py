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
                                                                               each skin sample (sim: kinematics;
                                                                               real: forward kinematics of
                                                                               joints/position, computed at close)
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
labels/content                (1,)                float32/64       any        shaken bottle's content class
                                                                               (envs.shake_contents.CONTENT_NAMES)
labels/fill                   (1,)                float32/64       any        its fill level (FILL_LEVELS)
labels/content_mass           (1,)                float32/64       any        its content's mass (kg)
labels/object                 (1,)                float32/64       any        object-action-surface: the held
                                                                               object's material (envs.oas.OBJECTS)
labels/action                 (1,)                float32/64       any        the action (envs.oas.ACTIONS)
labels/surface                (1,)                float32/64       any        the surface (envs.oas.SURFACES)
labels/surface_force          (1,)                float32/64       any        the object's normal force on the
                                                                               surface (N)
camera/wrist                  (H, W, 3)           uint8            any        a wrist camera's frames, RGB
wrist/pose                    (7,)                float32/64       any        the wrist target's offset from its
                                                                               start (m, quaternion wxyz)
actions/wrist                 (6,)                float32/64       any        a wrist action (dx dy dz m, droll
                                                                               dpitch dyaw rad)
labels/socket                 (7,)                float32/64       any        insertion: the socket's entry pose
labels/prong                  (7,)                float32/64       any        the prong tip's pose
labels/depth                  (1,)                float32/64       any        the prong's depth in the hole (m)
labels/socket_force           (1,)                float32/64       any        the socket's contact force (N)
touch/age                     (1,)                float32/64       any        deploy: the touch age (s) of each
                                                                               step acted with a correction
                                                                               (rotation.deploy.recording)
============================  ==================  ===============  =========  =================================

``<finger>`` is one of index, middle, ring, thumb. Fixed rates are the Digit 360's (docs/reference/hardware.md
section 4) and Xela's (docs/reference/sparsh.md); "any" rates are declared per session in the ``rate_hz`` attribute
(e.g. the control rate) and checked against the timestamps: a declared-rate stream off its rate makes a complete
session unreadable (a writer's bug), while a sensor stream at a fixed rate, stamped on arrival at the host, may come
out slower than its sensor when the host fell behind (a busy machine reading a camera): it is kept, with a warning
that names the rate it had, as is every stream of an incomplete session (a run that ended in a fault). A Digit 360
fingertip is stored either as its recorded streams (real hand) or as its contact fields (simulation), from which the
loader renders the four modalities (envs.sensors.digit360_render). A session with skin streams carries the static
taxel facts in ``extra["skin"]`` (envs.sensors.xela.skin_metadata: pad names, taxels per pad, taxel type ids and
names). A simulated Digit 360 session names its hand in ``extra["sim_hand"]`` (the loader renders its contact
fields with that hand's sensor, envs.scene.touch_model; without the key: 'digit360'). The object's properties
(``properties``) are the simulated parameters in sim (scale, mass kg, friction, com
m) and whatever was measured on the real object.

Crash safety: the writer keeps the file in HDF5's single-writer/multiple-reader mode (SWMR, ``libver="latest"``),
creates every dataset up front, buffers appends in memory and writes + flushes them every ``flush_interval_s``. In
SWMR mode HDF5 orders its metadata writes so that the file is valid at any instant; a writer killed at any point
leaves a file that :class:`SessionReader` opens with everything up to the last flush. Only a cleanly closed
session carries ``complete = True``. With ``background=True`` the writes and flushes run on the writer's own thread
(appends only queue), so a caller with a deadline (the deploy loop recording camera frames, about 18 MB/s for
four Digit 360s) never waits for the disk; a write that fails there is raised by the next ``append`` or ``close``.
"""

from __future__ import annotations

import json
import logging
import math
from dataclasses import dataclass, field
from importlib import metadata as _metadata
from typing import Any, Literal

import numpy as np

from envs.constants import FINGERS, NUM_JOINTS, PRIV_DIM
from envs.errors import RequestRefused
from envs.sensors.digit360 import NUM_FIELDS

log = logging.getLogger(__name__)

FORMAT_VERSION = 1
"""Version of the layout above written by this code; a reader refuses files with a newer version."""
LATENT_DIM = 8
"""Size of the teacher's latent z (Hora's env-factor encoder output, docs/reference/hora.md)."""
XELA_TAXELS = 368
"""Taxels of the Xela skin on the Allegro hand (docs/reference/hardware.md section 5)."""
XELA_PADS = 18
"""Pads of the Xela skin on the Allegro hand (envs.sensors.xela.PADS)."""
RATE_TOLERANCE = 0.1
"""A stream's median timestamp step may differ from 1 / rate_hz by this fraction (jittery USB clocks)."""


class SessionError(RequestRefused):
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
        "touch/age": StreamSpec((1,), _FLOAT, None, "s"),
        "camera/wrist": StreamSpec((None, None, 3), ("uint8",), None, "RGB", chunk=1, compression="lzf"),
        "wrist/pose": StreamSpec((7,), _FLOAT, None, "m, quaternion wxyz"),
        "actions/wrist": StreamSpec((6,), _FLOAT, None, "m, rad"),
        "labels/socket": StreamSpec((7,), _FLOAT, None, "m, quaternion wxyz"),
        "labels/prong": StreamSpec((7,), _FLOAT, None, "m, quaternion wxyz"),
        "labels/depth": StreamSpec((1,), _FLOAT, None, "m"),
        "labels/socket_force": StreamSpec((1,), _FLOAT, None, "N"),
        "labels/content": StreamSpec((1,), _FLOAT, None, "class id (envs.shake_contents.CONTENT_NAMES)"),
        "labels/fill": StreamSpec((1,), _FLOAT, None, "level id (envs.shake_contents.FILL_LEVELS)"),
        "labels/content_mass": StreamSpec((1,), _FLOAT, None, "kg"),
        "labels/object": StreamSpec((1,), _FLOAT, None, "class id (envs.oas.OBJECTS)"),
        "labels/action": StreamSpec((1,), _FLOAT, None, "class id (envs.oas.ACTIONS)"),
        "labels/surface": StreamSpec((1,), _FLOAT, None, "class id (envs.oas.SURFACES)"),
        "labels/surface_force": StreamSpec((1,), _FLOAT, None, "N"),
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


def to_json(value: dict[str, Any], where: str) -> str:
    """JSON text of a metadata dict (numpy scalars and arrays become plain numbers and lists)."""

    def default(x: Any) -> Any:
        if isinstance(x, np.generic | np.ndarray):
            return x.tolist()
        raise SessionError(f"{where}: {type(x).__name__} is not JSON-serializable")

    return json.dumps(value, sort_keys=True, default=default)


def check_name(name: str, where: str) -> StreamSpec:
    if name not in STREAMS:
        raise SessionError(f"{where}: unknown stream {name!r}; known streams: {', '.join(sorted(STREAMS))}")
    return STREAMS[name]
