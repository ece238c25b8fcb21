"""What an evaluation keeps on disk while it runs, so that an interrupted one loses no finished condition.

Layout under the report directory OUT:

    OUT/progress.json               what the results depend on: the config (less the fields in RESUMABLE_CHANGES),
                                    a digest of every policy's weights and one of the grasp cache
    OUT/conditions/<name>.json      the result rows of one finished condition, written (atomically) as it completes

A later run into the same OUT continues: it checks that progress.json describes the same evaluation (refusing with
the differences otherwise, so rows of two different evaluations never end up in one report), keeps every finished
condition and runs the rest. An OUT that holds the report of an evaluation without progress.json (written by an
earlier version) is refused rather than overwritten.
"""

from __future__ import annotations

import hashlib
import json
import os
import tempfile
from pathlib import Path
from typing import Any

from adapters.touch_delay import delay_spec, parse_delay
from envs.constants import DEFAULT_HAND
from envs.errors import RequestRefused
from envs.grasp_cache import cache_digest
from envs.metrics import METRICS
from rotation.bundles import weights_digest
from rotation.configs import to_jsonable
from rotation.evaluate.report import json_text

PROGRESS_FILE = "progress.json"
CONDITIONS_DIR = "conditions"
RESUMABLE_CHANGES = frozenset({"out", "resume", "progress", "nthread", "video", "video_size"})
"""Config fields that do not change a single result row (threads of MuJoCo, where and whether videos are drawn):
they may differ between a run and its continuation. Everything else must match."""

LATER_FIELDS = {"touch_delay": "0", "contact": None, "physics_dt": None, "task": "rotation"}
"""Config fields added after evaluations were first recorded, with their defaults: at its default such a field is
left out of the identity, so an interrupted evaluation recorded before it existed still continues."""


def identity(cfg: Any, policies: dict[str, str], hand: str = DEFAULT_HAND, reads_touch: bool = True
             ) -> dict[str, Any]:
    """What the rows of an evaluation depend on: its config (without RESUMABLE_CHANGES, and without the touch delay
    when no policy reads touch: ``reads_touch``), the policies' weights and the grasp cache (of ``hand``, the hand
    the episodes run on)."""
    config = {k: v for k, v in to_jsonable(cfg).items()
              if k not in RESUMABLE_CHANGES and not (k in LATER_FIELDS and v == LATER_FIELDS[k])}
    if not reads_touch:
        config.pop("touch_delay", None)
    elif "touch_delay" in config:  # the distribution itself: 'measured' changes when deploy is measured again
        config["touch_delay"] = delay_spec(parse_delay(config["touch_delay"]))
    return {"config": config, "policy_weights": {name: weights_digest(path) for name, path in policies.items()},
            "grasps": {"cache": cache_digest(cfg.grasp_cache, cfg.object, hand)}}


def _differences(old: dict[str, Any], new: dict[str, Any]) -> list[str]:
    out = []
    for section in ("config", "policy_weights", "grasps"):
        a, b = old.get(section, {}), new.get(section, {})
        for key in sorted(set(a) | set(b)):
            if a.get(key) != b.get(key):
                names = {"policy_weights": f"the weights of policy {key!r}", "grasps": "the grasp cache"}
                what = names.get(section, key)
                out.append(f"{what}: {a.get(key, '(not set)')!r} -> {b.get(key, '(not set)')!r}")
    return out


def check_out(out: Path, ident: dict[str, Any], resume: bool) -> bool:
    """Whether ``out`` continues an earlier run of this same evaluation (True) or starts a new one (False).

    ValueError when ``out`` holds another evaluation (listing the differences), a report without progress
    information, or nothing to continue although ``resume`` was asked for. Reads only."""
    progress = out / PROGRESS_FILE
    if progress.is_file():
        try:
            old = json.loads(progress.read_text())
            if not isinstance(old, dict):
                raise TypeError(f"a JSON {type(old).__name__}, not an object")
        except (json.JSONDecodeError, UnicodeDecodeError, TypeError) as err:
            raise ValueError(f"{progress} is not readable ({err}); use another --out") from None
        diff = _differences(old, ident)
        if diff:
            raise ValueError(f"{out} holds an evaluation with other settings ({'; '.join(diff)}); use another --out, "
                             f"or the same settings to continue it (only {sorted(RESUMABLE_CHANGES)} may differ)")
        return True
    if (out / "results.json").exists():
        raise RequestRefused(f"{out} holds the report of an earlier evaluation (results.json) that cannot be "
                             "continued; use another --out so it is not overwritten")
    if resume:
        raise RequestRefused(f"--resume: {out} holds no evaluation to continue ({PROGRESS_FILE} is missing)")
    return False


def start(out: Path, ident: dict[str, Any]) -> None:
    """Write progress.json (before the first condition runs)."""
    _write_atomically(out / PROGRESS_FILE, ident)


def _condition_file(out: Path, name: str) -> Path:
    return out / CONDITIONS_DIR / f"{name.replace(os.sep, '_')}.json"


def identity_digest(ident: dict[str, Any]) -> str:
    """sha256 of an evaluation's identity (:func:`identity`): what each of its condition files carries."""
    return hashlib.sha256(json.dumps(ident, sort_keys=True, default=str).encode()).hexdigest()


def rows(out: Path, name: str, policies: list[str], digest: str) -> list[dict[str, Any]] | None:
    """The saved rows of condition ``name``, or None when it must run (never finished, or rows from a version that
    reported other metrics). A file there that this evaluation did not write (another evaluation's, one without
    its identity digest, an unreadable one) is refused (RequestRefused) and left as it is. Reads only."""
    path = _condition_file(out, name)
    if not path.is_file():
        return None
    try:
        saved = json.loads(path.read_text())
        rows = saved["rows"]
        mine = saved.get("identity_sha256") == digest and saved.get("condition") == name
    except (json.JSONDecodeError, UnicodeDecodeError, KeyError, TypeError, AttributeError):
        mine = False
    if not mine:
        raise RequestRefused(f"{path} is not a condition this evaluation wrote (another evaluation's, or no "
                             "record of which); move it away, or use another --out")
    if [r.get("policy") for r in rows] != policies or not all(all(k in r for k in METRICS) for r in rows):
        return None
    return rows


def save_rows(out: Path, name: str, rows: list[dict[str, Any]], digest: str) -> None:
    """Keep the rows of one finished condition with the evaluation's identity digest (atomic: an interruption
    leaves the old file or the new one)."""
    _write_atomically(_condition_file(out, name), {"condition": name, "identity_sha256": digest, "rows": rows})


def _write_atomically(path: Path, data: Any) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(dir=path.parent, prefix=f".{path.name}.", suffix=".tmp")
    try:
        with os.fdopen(fd, "w") as f:
            f.write(json_text(data))
            f.flush()
            os.fsync(f.fileno())
        os.replace(tmp, path)
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise
