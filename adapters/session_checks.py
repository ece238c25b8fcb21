"""Which recorded sessions an adapter fine-tune can use: the files of a folder, each checked for the streams,
the measured object properties and the hand the adapter needs, and the properties compared with the ranges
the student was trained on.
"""

from __future__ import annotations

import logging
from collections.abc import Iterable, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Literal

import numpy as np

from envs.config import RandomizationConfig, default_randomization
from envs.errors import RequestRefused
from rotation.data.dataset import find_sessions
from rotation.data.properties import check_properties
from rotation.data.session import SessionError
from rotation.data.session_reader import SessionReader
from rotation.hardware.digit360 import window as dw

log = logging.getLogger(__name__)

Position = Literal["fit", "average", "recorded"]
POSITIONS: tuple[str, ...] = ("fit", "average", "recorded")
SERIAL_WINDOWS: dict[str, float] = {"imu": dw.IMU_RATE, "pressure": dw.PRESSURE_RATE}
"""The Digit 360 serial streams (``digit360/<finger>/<window>``, recorded by every deploy with --digit360) -> their
rate (Hz)."""
MEDIA_WINDOWS = ("image", "audio")
"""The camera frames and microphones (``digit360/<finger>/image``, ``audio``), recorded by deploy with
--record-media or for an adapter that reads them."""
RECORDED_WINDOWS = (*MEDIA_WINDOWS, *SERIAL_WINDOWS)
"""Windows a recorded session can give."""
HANDS = ("allegro", "leap")
"""Hands with the Allegro joint layout that the student runs on (rotation.deploy.hands)."""
JOINT_STREAMS = ("joints/position", "joints/target")


@dataclass(frozen=True)
class SessionInfo:
    """What :func:`check_session` found: the session's hand and source, and its measured properties."""

    path: Path
    hand: str
    source: str
    properties: dict[str, float | list[float]]
    steps: int


def session_files(sources: Iterable[str | Path]) -> list[Path]:
    """The .h5 session files of ``sources`` (files, or directories searched recursively), sorted, each once;
    ValueError when a source is missing or holds none."""
    files: set[Path] = set()
    for source in sources:
        found = find_sessions(source)
        if not found:
            raise RequestRefused(f"sessions: no .h5 session files under {source}")
        files.update(p.resolve() for p in found)
    if not files:
        raise ValueError("sessions: give at least one session file or directory")
    return sorted(files)


def check_session(path: str | Path, fingers: Sequence[str], windows: Sequence[str], control_hz: float,
                  position: Position = "fit") -> SessionInfo:
    """Everything about one session that can be checked without reading its streams; SessionError naming the
    session and what is missing (a stream, a property, the control rate, the hand)."""
    path = Path(path)
    need = [*JOINT_STREAMS, *(f"digit360/{f}/{w}" for f in fingers for w in windows)]
    if position == "recorded":
        need.append("labels/object_pose")
    with SessionReader(path) as r:
        missing = [n for n in need if not r.has(n)]
        if missing:
            hint = ""
            if any(n.startswith("digit360/") for n in missing):
                simulated = [f for f in fingers if r.has(f"digit360/{f}/contact")]
                media = any(n.rsplit("/", 1)[-1] in MEDIA_WINDOWS for n in missing)
                hint = (" (a simulated session from `rotate collect`: fine-tune in simulation instead)" if simulated
                        else " (record with `rotate deploy --digit360 ... --record FILE --record-media`, which also "
                             "records every fingertip's camera frames and microphones)" if media
                        else " (record with `rotate deploy --digit360 ... --record`, which records every fingertip's "
                             "imu and pressure)")
            elif "labels/object_pose" in missing:
                hint = " (position 'recorded' needs the object's tracked pose; use 'fit' or 'average')"
            raise SessionError(f"session {path}: missing stream(s) {', '.join(missing)} needed to train the "
                               f"adapter{hint}")
        meta = r.meta
        if meta.hand not in HANDS:
            raise SessionError(f"session {path}: recorded on the hand {meta.hand!r}; the student runs on "
                               f"{' or '.join(HANDS)} (the Allegro joint layout)")
        if not np.isclose(meta.control_hz, control_hz):
            raise SessionError(f"session {path}: recorded at {meta.control_hz:g} Hz, the student acts at "
                               f"{control_hz:g} Hz")
        try:
            props = check_properties(meta.properties, f"session {path}")
        except ValueError as err:
            raise SessionError(f"{err}. Record with `rotate deploy ... --properties mass=...,friction=...,"
                               "com=X,Y,Z,scale=...` (docs/adapter.md)") from None
        steps = min(len(r.stream(n)) for n in JOINT_STREAMS)
    return SessionInfo(path, meta.hand, meta.source, props, steps)


def check_sessions(paths: Sequence[str | Path], fingers: Sequence[str], windows: Sequence[str], control_hz: float,
                   position: Position = "fit") -> list[SessionInfo]:
    """:func:`check_session` for every session, and one hand for all: an adapter learns one hand's touch, so
    sessions of another hand kind (allegro / leap) or source (a real hand / its emulator) are refused."""
    bad = [w for w in windows if w not in RECORDED_WINDOWS]
    if bad:
        raise ValueError(f"recorded sessions give the windows {', '.join(RECORDED_WINDOWS)}; the adapter reads "
                         f"{', '.join(bad)}")
    if position not in POSITIONS:
        raise ValueError(f"position must be one of {', '.join(POSITIONS)}, got {position!r}")
    if not paths:
        raise ValueError("sessions: give at least one session file or directory")
    infos = [check_session(p, fingers, windows, control_hz, position) for p in paths]
    first = infos[0]
    for info in infos[1:]:
        if (info.hand, info.source) != (first.hand, first.source):
            raise SessionError(f"session {info.path} comes from another hand ({info.hand}, {info.source}) than "
                               f"{first.path} ({first.hand}, {first.source}): fine-tune one adapter per hand")
    trained = teacher_randomization()  # read once, not per session
    for info in infos:
        notes = outside_training_ranges(info.properties, trained)
        if notes:
            log.warning("session %s: %s outside the teacher's training ranges; its z there is an extrapolation",
                        info.path, "; ".join(notes))
    return infos


def teacher_randomization(teacher: str | Path = "teacher") -> RandomizationConfig:
    """The randomization the teacher ``teacher`` (a shipped name or a bundle directory) trained on, from its card's
    training config; the default hand's when the card does not say (a bundle from before cards kept it)."""
    import json

    from rotation.policy.bundle import resolve_bundle
    from rotation.train.teacher_config import recorded_config

    try:
        card = json.loads((resolve_bundle(teacher) / "config.json").read_text()).get("card", {})
    except (OSError, ValueError, AttributeError):
        return default_randomization()
    if not isinstance(card, dict) or "train_config" not in card:
        return default_randomization()
    try:
        return recorded_config(card["train_config"]).env_config().randomization
    except (ValueError, KeyError, TypeError) as err:  # a card that says, but does not load: say so, not silently
        log.warning("the teacher %s's card has a training config that does not load (%s); the measured properties "
                    "are checked against the hand's default randomization instead", teacher, err)
        return default_randomization()


def outside_training_ranges(props: dict[str, float | list[float]],
                            rc: RandomizationConfig | None = None) -> list[str]:
    """The measured properties outside the randomization ``rc`` (default: the shipped teacher's,
    :func:`teacher_randomization`), as 'key value (range)'. Friction is the gel domes' (the cup against the
    sensors); a cup-surface factor (``surface_friction``) multiplies it in training, so its low end widens the range."""
    rc = rc or teacher_randomization()
    low = rc.friction[0] * (rc.surface_friction[0] if rc.surface_friction is not None else 1.0)
    ranges = {"scale": (min(rc.scales) - rc.scale_jitter, max(rc.scales) + rc.scale_jitter), "mass": rc.mass,
              "friction": (low, rc.friction[1]), "com": rc.com}
    out = []
    for key, (lo, hi) in ranges.items():
        values = np.atleast_1d(props[key])
        if np.any(values < lo - 1e-9) or np.any(values > hi + 1e-9):
            out.append(f"{key} {props[key]} ({lo:g}..{hi:g})")
    return out
