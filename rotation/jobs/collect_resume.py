"""What a collection keeps when it resumes: its manifest (the settings it records with), the settings digest
every session it writes carries, and the check that an episode's file is this collection's own.
"""

from __future__ import annotations

import hashlib
import json
from pathlib import Path
from typing import Any

from envs.errors import RequestRefused
from rotation.configs import to_jsonable
from rotation.data.session_reader import SessionReader

Config = Any
"""rotation.jobs.collect.Config (that module imports this one; the annotations name it without importing it)."""

MANIFEST = "collect.json"
SETTINGS = ("policy", "object", "seed", "num_envs", "friction_scale", "added_mass", "com_shift", "episode_steps",
             "random_scale")
"""Settings that must match to resume into an existing output directory."""
LATER_SETTINGS = ("control_hz", "action_scale", "policy_weights_sha256")
"""Also compared on resume, when the earlier manifest recorded them (manifests of older versions lack them): the
env's timing (a bundle's own) and the digest of a bundle's weights (the same path may hold a retrained policy)."""
SKIN_SETTINGS = {"skin": False, "task": "cup"}
"""Settings added with the skin; a manifest without them recorded these defaults."""


SETTINGS_KEY = "collect_settings_sha256"
"""Session ``extra`` key of the collection's settings digest: a resume keeps only the files that carry its own."""


def settings_digest(settings: dict[str, Any]) -> str:
    """First 16 hex digits of the SHA-256 of a collection's settings (what its manifest records)."""
    return hashlib.sha256(json.dumps(settings, sort_keys=True).encode()).hexdigest()[:16]


def kept_episode(path: Path, episode: int, digest: str, streams: list[str]) -> bool:
    """Whether the file at an episode's path is this collection's finished episode, which a resume keeps. False
    when there is none, or when it is this collection's unfinished one (recorded again). A file this collection did
    not write (another collection's, a deploy recording, anything unreadable or without the streams these settings
    record) is refused with RequestRefused and left as it is."""
    if not path.exists() or path.stat().st_size == 0:  # an empty file: a writer that died before writing anything
        return False
    fix = "move it away, or collect into another --out"
    try:
        with SessionReader(path) as r:
            extra, complete, names = r.meta.extra, r.complete, set(r.names)
    except ValueError as err:
        raise RequestRefused(f"{path} is not a session this collection wrote ({' '.join(str(err).split())}); "
                             f"{fix}") from None
    if extra.get(SETTINGS_KEY) != digest or extra.get("episode") != episode:
        raise RequestRefused(f"{path} was not written by this collection (it records episode "
                             f"{extra.get('episode')!r} with settings {extra.get(SETTINGS_KEY)!r}; this is episode "
                             f"{episode} with settings {digest}); {fix}")
    missing = sorted(set(streams) - names)
    if complete and missing:
        raise RequestRefused(f"{path} lacks the stream(s) {', '.join(missing)} these settings record; {fix}")
    return complete


def is_complete(path: Path) -> bool:
    """A session file that exists and whose writer closed it."""
    if not path.is_file():
        return False
    try:
        with SessionReader(path) as r:
            return r.complete
    except ValueError:
        return False


def check_manifest(cfg: Config, settings: dict[str, Any]) -> None:
    """Refuse (ValueError) an OUT that holds sessions recorded with other settings; reads, never writes."""
    path = cfg.out / MANIFEST
    if cfg.out.exists() and not cfg.out.is_dir():
        raise ValueError(f"out: {cfg.out} is a file; give a directory for the sessions")
    if not path.is_file():
        return
    try:
        old = json.loads(path.read_text())["settings"]
        if not isinstance(old, dict):
            raise TypeError(f"'settings' is a {type(old).__name__}")
    except (json.JSONDecodeError, UnicodeDecodeError, KeyError, TypeError) as err:
        raise RequestRefused(f"{path} is not a readable collect manifest ({type(err).__name__}: {err}); use another "
                             "--out, or remove the file if the sessions beside it are yours to replace") from None
    old = {**SKIN_SETTINGS, "hand": "auto", **old}
    diff = {k: (old.get(k), v) for k, v in {"hand": "auto", **settings}.items()
            if old.get(k) != v and (k not in LATER_SETTINGS or k in old)}
    if not diff:
        return
    if not any(cfg.out.glob("shard_*/episode_*.h5")):
        # an earlier run that recorded nothing (stopped or refused before its first episode): nothing to protect
        print(f"collect: {path} belongs to a run that recorded no session; replacing its settings")
        return
    changes = ", ".join(f"{k}: {a!r} -> {b!r}" for k, (a, b) in diff.items())
    raise RequestRefused(f"{cfg.out} holds a collection with other settings ({changes}); use another --out or "
                         "the same settings to resume")


def write_manifest(cfg: Config, settings: dict[str, Any]) -> None:
    cfg.out.mkdir(parents=True, exist_ok=True)
    (cfg.out / MANIFEST).write_text(json.dumps({"settings": settings, "config": to_jsonable(cfg)}, indent=2) + "\n")
