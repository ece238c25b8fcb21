"""Run folders that never lose or mix data: one run per folder, atomic checkpoints, resumes that match the run.

- A job refuses to write into a folder that holds another run's outputs unless it resumes that run or the user
  asked to replace it (``--overwrite``, which deletes exactly those outputs first).
- A resume compares its options with the run's saved ``config.json`` and refuses with the list of differences;
  only options that change the run's length or its speed (``may_differ``) may change. ``config.json`` also records
  a digest of the grasp cache the episodes start from (the options name only its path), and a resume refuses
  another file at that path.
- Checkpoints are written to a temporary file and renamed, so a crash leaves the previous one intact; a damaged
  latest checkpoint (a truncated file from an older version or a full disk) falls back to the newest intact
  earlier one, with a warning.
- The training curve (``curves.jsonl``) is appended and flushed to disk with each checkpoint.
- A run folder records a random run id (``run.json``), and every checkpoint it writes proves it belongs to that run
  (the id and the checkpoint's sha256 in a ``<checkpoint>.owner.json`` beside it, or inside the checkpoint): a
  resume refuses a checkpoint of another run copied into the folder, in one line naming it. A folder from before
  run ids (no ``run.json``) resumes its checkpoints as it always did.
"""

from __future__ import annotations

import hashlib
import json
import os
import shutil
import sys
import uuid
from collections.abc import Callable, Iterable, Sequence
from pathlib import Path
from typing import Any, TypeVar

from envs.errors import RequestRefused

T = TypeVar("T")


class DamagedCheckpoint(RequestRefused):
    """A checkpoint file that exists but cannot be read back (truncated, corrupted); earlier ones may be intact."""


def existing_outputs(out: Path, names: Iterable[str]) -> list[str]:
    """The run outputs among ``names`` that exist in ``out``."""
    return [n for n in names if (out / n).exists() or (out / n).is_symlink()]


def check_run_dir(out: Path, names: Sequence[str], *, overwrite: bool, resuming_here: bool, resume_hint: str) -> None:
    """Refuse to start a run in ``out`` if it holds another run's outputs (unless overwriting or resuming it)."""
    found = existing_outputs(out, names)
    if not found or resuming_here or overwrite:
        return
    raise ValueError(f"out {out} already holds a run ({', '.join(found)}); {resume_hint}, pass --overwrite to "
                     "delete it and start over, or choose another --out")


def clear_outputs(out: Path, names: Sequence[str]) -> list[str]:
    """Delete the run outputs ``names`` in ``out`` (--overwrite); returns what was deleted."""
    found = existing_outputs(out, names)
    for name in found:
        path = out / name
        if path.is_dir() and not path.is_symlink():
            shutil.rmtree(path)
        else:
            path.unlink()
    return found


def _flatten(d: dict[str, Any], prefix: str = "") -> dict[str, Any]:
    flat: dict[str, Any] = {}
    for k, v in d.items():
        if isinstance(v, dict):
            flat.update(_flatten(v, f"{prefix}{k}."))
        else:
            flat[prefix + k] = v
    return flat


def config_differences(saved: dict[str, Any], now: dict[str, Any], may_differ: Iterable[str]) -> list[str]:
    """'field: saved -> now' for every (nested, dotted) field that differs, but those in ``may_differ``.

    A field the saved config does not have (an option added since) is not compared.
    """
    allowed = set(may_differ)
    a, b = _flatten(saved), _flatten(now)
    return [f"{k}: {a[k]!r} -> {b[k]!r}" for k in sorted(b)
            if k in a and a[k] != b[k] and k.split(".")[0] not in allowed]


def refuse_differences(differences: list[str], where: str, may_differ: Iterable[str]) -> None:
    if differences:
        raise ValueError(f"--resume: the options differ from the run's ({where}): {'; '.join(differences)}. Resume "
                         f"with the run's values; only {', '.join(sorted(may_differ))} may change")


GRASPS_KEY = "grasp_cache_sha256"
"""The key of the grasp cache's digest in a training run's config.json (beside the options)."""


def run_record(cfg: Any) -> dict[str, Any]:
    """What a training run's config.json holds (written with rotation.configs.save_config): its options (a Config
    with object, hand and grasp_cache) and the digest of the grasp cache its episodes start from. Computed once when
    the run starts; the bundle card takes the same digest."""
    from envs.grasp_cache import cache_digest
    from rotation.configs import to_jsonable

    return to_jsonable(cfg) | {GRASPS_KEY: cache_digest(cfg.grasp_cache, cfg.object, cfg.hand)}


def wall_time_fields(leg_s: float, total_s: float | None, resumed: bool) -> dict[str, Any]:
    """A bundle card's wall-time entries: ``wall_time_s``, the run's training time over every leg (``total_s``, from
    the checkpoints; this leg's where an earlier leg's is unknown), and after a resume this leg's beside it, with a
    note where the total could not be known."""
    fields: dict[str, Any] = {"wall_time_s": round(leg_s if total_s is None else total_s, 1)}
    if resumed:
        fields["wall_time_this_leg_s"] = round(leg_s, 1)
        if total_s is None:
            fields["wall_time_note"] = ("wall_time_s is this leg's alone: the checkpoint resumed is from before "
                                        "checkpoints kept the run's training time")
    return fields


def check_resume_record(saved: dict[str, Any], now: dict[str, Any], where: str, may_differ: Iterable[str]) -> None:
    """Refuse a resume whose options (or grasp cache) differ from the run's record ``saved`` (read from ``where``).
    A record written before the digest was kept has none, and its cache is not compared."""
    old, new = saved.get(GRASPS_KEY), now.get(GRASPS_KEY)
    if old is not None and new is not None and old != new:
        cache = now.get("grasp_cache") or f"the shipped cache of {now.get('object')!r}"
        raise ValueError(f"--resume: the grasp cache ({cache}) is not the file the run started from (SHA-256 "
                         f"{new}..., the run's {old}..., recorded in {where}); a regenerated cache changes every "
                         "episode's start. Resume with the run's cache, or start a new run from its bundle "
                         "(--init-from)")
    refuse_differences(config_differences(saved, now, {*may_differ, GRASPS_KEY}), where, may_differ)


def save_atomically(write: Callable[[Path], None], path: Path) -> None:
    """``write(tmp)`` then rename ``tmp`` over ``path``: readers see the old file or the new one, never half of it.

    The temporary name keeps ``path``'s suffix (stable-baselines3 appends '.zip' to names without one).
    """
    tmp = path.with_name(f".tmp_{path.name}")
    write(tmp)
    os.replace(tmp, path)


def with_fallback(path: Path, older: Sequence[Path], load: Callable[[Path], T]) -> tuple[T, Path]:
    """``load(path)``; if it is damaged (DamagedCheckpoint), the newest intact of ``older`` (newest first), with a
    warning on stderr. Any other error (a file of another program) is raised as it is."""
    try:
        return load(path), path
    except DamagedCheckpoint as err:
        damage = err
    for candidate in older:
        try:
            value = load(candidate)
        except DamagedCheckpoint:
            continue
        print(f"warning: checkpoint {path} is damaged ({damage}); resuming from {candidate}, the newest intact "
              "checkpoint before it", file=sys.stderr, flush=True)
        return value, candidate
    raise ValueError(f"checkpoint {path} is damaged ({damage}) and no intact earlier checkpoint is beside it")


class CurveLog:
    """``curves.jsonl``: one JSON object per line, appended and flushed to disk (fsync) at each checkpoint."""

    def __init__(self, path: Path, key: str = "steps") -> None:
        self.path, self.key = path, key

    def append(self, rows: Sequence[dict[str, Any]]) -> None:
        if not rows:
            return
        cut = False
        if self.path.is_file() and self.path.stat().st_size > 0:
            with self.path.open("rb") as f:
                f.seek(-1, os.SEEK_END)
                cut = f.read(1) != b"\n"
        with self.path.open("a") as f:
            if cut:  # a line cut short by a stop: end it, so the first new row is not glued onto it
                f.write("\n")
            for row in rows:
                f.write(json.dumps(row) + "\n")
            f.flush()
            os.fsync(f.fileno())

    def rows(self) -> list[dict[str, Any]]:
        """The complete rows (a line cut short by a crash is skipped)."""
        if not self.path.is_file():
            return []
        out = []
        for line in self.path.read_text().splitlines():
            try:
                out.append(json.loads(line))
            except json.JSONDecodeError:
                continue
        return out

    def trim(self, upto: int) -> int:
        """Drop rows logged after step ``upto`` (a resume from an earlier checkpoint); returns how many went."""
        if not self.path.is_file():
            return 0
        rows = self.rows()
        keep = [r for r in rows if int(r.get(self.key, 0)) <= upto]
        text = "".join(json.dumps(r) + "\n" for r in keep)
        if text != self.path.read_text():
            save_atomically(lambda tmp: tmp.write_text(text), self.path)
        return len(rows) - len(keep)


def summary_writer(log_dir: Path, purge_step: int):
    """TensorBoard writer; ``purge_step`` drops points a crashed run logged after its last checkpoint, so curves stay
    continuous on resume."""
    from torch.utils.tensorboard import SummaryWriter

    return SummaryWriter(log_dir=str(log_dir), purge_step=purge_step or None)


RUN_FILE = "run.json"
"""The run's identity in its folder: {"run_id": 32 hex digits}."""
OWNER_SUFFIX = ".owner.json"


def run_id(out: Path, create: bool) -> str | None:
    """The run id recorded in ``out`` (None for a folder from before run ids); with ``create`` a new run records a
    fresh one (call it only once the run may write). A RUN_FILE that cannot be read is refused."""
    path = out / RUN_FILE
    if path.is_file():
        try:
            value = json.loads(path.read_text())["run_id"]
            if not (isinstance(value, str) and len(value) == 32):
                raise ValueError(value)
        except (ValueError, KeyError, TypeError, UnicodeDecodeError) as err:
            raise RequestRefused(f"{path} is not a run record ({type(err).__name__}); move it away, or use another "
                                 "--out") from None
        return value
    if not create:
        return None
    value = uuid.uuid4().hex
    save_atomically(lambda tmp: Path(tmp).write_text(json.dumps({"run_id": value}) + "\n"), path)
    return value


def file_sha256(path: Path) -> str:
    digest = hashlib.sha256()
    with open(path, "rb") as f:
        for block in iter(lambda: f.read(1 << 20), b""):
            digest.update(block)
    return digest.hexdigest()


def write_owner(checkpoint: Path, owner: str | None) -> None:
    """Record beside ``checkpoint`` that run ``owner`` wrote it (its sha256 too); nothing for a run without an id."""
    if owner is None:
        return
    record = {"run_id": owner, "sha256": file_sha256(checkpoint)}
    save_atomically(lambda tmp: Path(tmp).write_text(json.dumps(record) + "\n"),
                    checkpoint.with_name(checkpoint.name + OWNER_SUFFIX))


def remove_owner(checkpoint: Path) -> None:
    checkpoint.with_name(checkpoint.name + OWNER_SUFFIX).unlink(missing_ok=True)


def check_owner(checkpoint: Path, owner: str | None) -> None:
    """Refuse (RequestRefused, one line) a checkpoint that run ``owner`` did not write: no owner record beside it,
    another run's, or a file changed since. A run without an id (``owner`` None) checks nothing."""
    if owner is None:
        return
    sidecar = checkpoint.with_name(checkpoint.name + OWNER_SUFFIX)
    try:
        record = json.loads(sidecar.read_text())
        mine = record.get("run_id") == owner and record.get("sha256") == file_sha256(checkpoint)
    except (OSError, ValueError, AttributeError, UnicodeDecodeError):
        mine = False
    if not mine:
        raise RequestRefused(f"--resume: {checkpoint} is not a checkpoint this run wrote (no record of it, another "
                             "run's, or changed since); move it away, or resume the run it belongs to")
