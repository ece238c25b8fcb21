"""Pre-rendered touch windows: sessions rendered once into memory-mappable shards, read back fast for training.

    rotate cache-touch --sessions data/touch data/touch_lowfric --out data/touch_cache --stride 5 --workers 14
    rotate pretrain --sessions data/touch --cache data/touch_cache ...    # builds what is missing, then trains

Simulated sessions hold contact fields that :class:`~rotation.data.dataset.TouchWindows` renders into images,
audio, IMU and pressure on every read (about 160 windows/s per process, rendering dominates). A GPU training step
consumes thousands of windows per second, so the windows are rendered once, here, by TouchWindows itself (the
cache holds exactly what the reader returns; recorded sessions work the same way) and stored per session::

    OUT/manifest.json                       cache format, fingers, stride, session path -> shard name
    OUT/<shard>/shard.json                  written last: the shard is complete (session size and mtime, counts)
    OUT/<shard>/frames.npy      (F, 224, 224, 3) uint8   every image frame the windows use, once
    OUT/<shard>/frame_rows.npy  (W, 2) int32             rows of each window's [t-5, t] frames in frames.npy
    OUT/<shard>/audio.npy       (W, 224, 256) float16    log-mel features (rotation.data.audio.fbank)
    OUT/<shard>/imu.npy         (W, 224, 3) float32      g
    OUT/<shard>/pressure.npy    (W, 224, 1) float32      hPa
    OUT/<shard>/finger.npy, time.npy (W,)                fingertip (0..3), window end (s)
    OUT/<shard>/label_<name>.npy (W, ...) float32        every label the session has (rotation.data.dataset.LABELS)

Size: with the default stride of 5 frames (6 windows per second and fingertip) consecutive windows share a frame,
so a window costs one 150 kB frame + 115 kB of audio features: about 1 GB per hour of one fingertip.
Images and IMU/pressure are stored exactly; audio features in float16 (absolute error below 0.016 on log-mel
values within +-32, far below their spread). :class:`CachedWindows` reads a cache like TouchWindows reads
sessions, returning the image as its two raw frames ``(2, 224, 224, 3)`` uint8 and the audio as float16, which
``rotation.tactile.models.sparshx_inputs.window_inputs`` (the encoders' ``preprocess``) converts on the device: a loader
worker moves 4x fewer bytes than with float32 windows.
"""

from __future__ import annotations

import hashlib
import json
import multiprocessing
import os
from collections.abc import Sequence
from concurrent.futures import ProcessPoolExecutor, as_completed
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Literal

import numpy as np
import torch
from torch.utils.data import Dataset
from tqdm import tqdm

from envs.constants import FINGERS
from envs.errors import RequestRefused
from envs.validation import check_int, check_output_dir, check_types
from rotation.configs import to_jsonable
from rotation.data.audio import fbank
from rotation.data.dataset import TouchWindows, check_fingers, check_session_sources, find_sessions
from rotation.data.session import SessionError

CACHE_VERSION = 1
MANIFEST = "manifest.json"
SHARD_DONE = "shard.json"
_MODALITY_FILES = ("audio", "imu", "pressure")


def shard_name(session: Path) -> str:
    """A session's shard directory: its file stem + a digest of its absolute path (unique, readable)."""
    path = Path(session).resolve()
    return f"{path.stem}-{hashlib.sha1(str(path).encode()).hexdigest()[:12]}"


def _identity(session: Path) -> dict[str, Any]:
    st = Path(session).stat()
    return {"path": str(Path(session).resolve()), "size": st.st_size, "mtime_ns": st.st_mtime_ns}


def _unpack_image(image: torch.Tensor) -> np.ndarray:
    """(6, H, W) float in [0, 1], channels [R(t-5), R(t), G(t-5), ...] -> (2, H, W, 3) uint8 [t-5, t] (exact:
    the reader's image is uint8 / 255 in float32)."""
    x = torch.round(image * 255.0).to(torch.uint8)  # (6, H, W)
    return x.reshape(3, 2, *x.shape[1:]).permute(1, 2, 3, 0).numpy()  # (3, 2, H, W) -> (2, H, W, 3)


def _collate(items: list[dict[str, Any]]) -> dict[str, Any]:
    out: dict[str, Any] = {}
    for key in items[0]:
        out[key] = torch.stack([torch.as_tensor(it[key]) for it in items])
    return out


class _ShardWriter:
    """Fills one session's shard (arrays preallocated on disk), then marks it complete."""

    def __init__(self, root: Path, ds: TouchWindows, session: int, rows: np.ndarray, audio_dtype: str):
        self.dir = root / shard_name(ds.paths[session])
        self.dir.mkdir(parents=True, exist_ok=True)
        (self.dir / SHARD_DONE).unlink(missing_ok=True)
        self.session_path = ds.paths[session]
        self.rows = rows  # (W,) indices into ds of this session's windows, in order
        idx = ds.index[rows]  # (W, 3) session, finger, end
        keys = sorted({(int(f), int(e) - d) for _, f, e in idx for d in (5, 0)})  # (finger, frame) pairs used
        self.frame_row = {k: i for i, k in enumerate(keys)}
        self.frame_rows = np.array([[self.frame_row[(int(f), int(e) - 5)], self.frame_row[(int(f), int(e))]]
                                    for _, f, e in idx], dtype=np.int32).reshape(-1, 2)
        self.frame_done = np.zeros(len(keys), bool)
        n = len(rows)
        self.labels = ds.labels
        shapes = {"frames": ((len(keys), 224, 224, 3), np.uint8), "audio": ((n, 224, 256), np.dtype(audio_dtype)),
                  "imu": ((n, 224, 3), np.float32), "pressure": ((n, 224, 1), np.float32)}
        # filled in place on disk (an hour of one fingertip is about 1 GB); numpy cannot map an empty file
        self.arrays = {k: np.lib.format.open_memmap(self.dir / f"{k}.npy", "w+", dt, shape) if shape[0] else
                       np.zeros(shape, dt) for k, (shape, dt) in shapes.items()}
        self.small: dict[str, np.ndarray] = {"finger": idx[:, 1].astype(np.int64), "time": ds.end_times[rows]}
        self.label_arrays: dict[str, np.ndarray] = {}
        self.filled = 0

    def add(self, batch: dict[str, Any], audio: torch.Tensor, lo: int, hi: int, offset: int) -> None:
        """Windows [lo, hi) of this shard from batch rows [offset, offset + hi - lo)."""
        sl = slice(offset, offset + hi - lo)
        for w, b in zip(range(lo, hi), range(sl.start, sl.stop), strict=True):
            frames = _unpack_image(batch["image"][b])  # (2, H, W, 3)
            for j in range(2):
                r = self.frame_rows[w, j]
                if not self.frame_done[r]:
                    self.arrays["frames"][r] = frames[j]
                    self.frame_done[r] = True
                elif not np.array_equal(self.arrays["frames"][r], frames[j]):  # the reader is deterministic
                    raise SessionError(f"session {self.session_path}: frame {self.frame_rows[w, j]} differs between "
                                       "two windows (is the file being written?)")
        self.arrays["audio"][lo:hi] = audio[sl].numpy().astype(self.arrays["audio"].dtype)
        self.arrays["imu"][lo:hi] = batch["imu"][sl].numpy()
        self.arrays["pressure"][lo:hi] = batch["pressure"][sl].numpy()
        for name in self.labels:
            value = batch[name][sl].numpy().astype(np.float32)
            if name not in self.label_arrays:
                self.label_arrays[name] = np.zeros((len(self.rows), *value.shape[1:]), np.float32)
            self.label_arrays[name][lo:hi] = value
        self.filled = max(self.filled, hi)

    def close(self) -> None:
        for k, a in self.arrays.items():
            if isinstance(a, np.memmap):
                a.flush()
            else:
                np.save(self.dir / f"{k}.npy", a)
        for name in self.labels:  # an empty shard still declares its labels
            self.label_arrays.setdefault(name, np.zeros((0,), np.float32))
        np.save(self.dir / "frame_rows.npy", self.frame_rows)
        for name, value in {**self.small, **{f"label_{k}": v for k, v in self.label_arrays.items()}}.items():
            np.save(self.dir / f"{name}.npy", value)
        info = {"version": CACHE_VERSION, "session": _identity(self.session_path), "windows": len(self.rows),
                "frames": len(self.frame_row), "labels": list(self.labels),
                "audio_dtype": str(self.arrays["audio"].dtype)}
        tmp = self.dir / (SHARD_DONE + ".tmp")
        tmp.write_text(json.dumps(info, indent=2) + "\n")
        tmp.replace(self.dir / SHARD_DONE)  # written last and atomically: the shard is complete


def _shard_complete(root: Path, session: Path) -> bool:
    done = root / shard_name(session) / SHARD_DONE
    if not done.is_file():
        return False
    try:
        info = json.loads(done.read_text())
    except ValueError:
        return False
    ident = _identity(session)
    return info.get("version") == CACHE_VERSION and all(info["session"].get(k) == ident[k] for k in ident)


def _check_manifest(root: Path, fingers: Sequence[str], stride: int, audio_dtype: str) -> dict[str, Any]:
    settings = {"version": CACHE_VERSION, "fingers": list(fingers), "stride": int(stride), "audio_dtype": audio_dtype}
    path = root / MANIFEST
    if path.is_file():
        manifest = json.loads(path.read_text())
        diff = {k: (manifest.get(k), v) for k, v in settings.items() if manifest.get(k) != v}
        if diff:
            changes = ", ".join(f"{k}: {a!r} -> {b!r}" for k, (a, b) in diff.items())
            raise ValueError(f"cache {root} was built with other settings ({changes}); use another directory or the "
                             "same settings")
        return manifest
    return {**settings, "sessions": {}}


def build_shard(session: str | Path, root: str | Path, fingers: Sequence[str], stride: int,
                audio_dtype: str = "float16", batch_size: int = 32) -> int:
    """Render one session's windows into its shard under ``root`` (one process: rendering, filterbank, writes);
    returns the number of windows."""
    ds = TouchWindows([Path(session)], fingers=fingers, labels=None, stride=stride, audio_features=False)
    writer = _ShardWriter(Path(root), ds, 0, np.arange(len(ds)), audio_dtype)
    with torch.no_grad():
        for lo in range(0, len(ds), batch_size):
            hi = min(lo + batch_size, len(ds))
            batch = _collate([ds[i] for i in range(lo, hi)])
            audio = fbank(batch["audio_wave"])  # (n, 224, 256) log-mel, batched
            _check_finite(batch, audio, ds, lo, hi - lo)
            writer.add(batch, audio, lo, hi, 0)
    writer.close()
    return len(ds)


def _build_shard_job(args: tuple) -> tuple[str, int]:
    torch.set_num_threads(1)  # one core per worker process
    return str(args[0]), build_shard(*args)


def build_cache(sessions: Sequence[str | Path], out: str | Path, fingers: Sequence[str] = FINGERS, stride: int = 5,
                workers: int = 0, audio_dtype: str = "float16", progress: bool = True) -> Path:
    """Render every session (files or directories of ``*.h5``) not yet in the cache at ``out``; returns ``out``.

    Resumable: complete shards of unchanged session files are kept, anything else is (re)rendered. ``workers``
    processes render one session each at a time (0: all in this process); rendering dominates (about 6 ms per
    window and core), the log-mel filterbank and the writes cost far less.
    """
    check_int("stride", stride, 1, 1000)
    check_int("workers", workers, 0, 1024)
    if audio_dtype not in ("float16", "float32"):
        raise ValueError(f"audio_dtype must be float16 or float32, got {audio_dtype!r}")
    root = Path(out)
    paths = sorted({p.resolve() for s in sessions for p in find_sessions(s)})
    if not paths:
        raise RequestRefused(f"no session files (*.h5) in {', '.join(map(str, sessions))}")
    manifest = _check_manifest(root, fingers, stride, audio_dtype)
    todo = [p for p in paths if not _shard_complete(root, p)]
    root.mkdir(parents=True, exist_ok=True)
    jobs = [(str(p), str(root), tuple(fingers), stride, audio_dtype) for p in todo]
    bar = tqdm(total=len(todo), unit="session", desc="cache-touch", disable=not (progress and todo),
               dynamic_ncols=True)

    def done(session: str, windows: int) -> None:
        manifest["sessions"][session] = shard_name(Path(session))
        _write_manifest(root, manifest)  # after every shard: an interrupted build keeps what it finished
        bar.update(1)
        bar.set_postfix(windows=windows)

    try:
        if workers == 0 or len(jobs) <= 1:
            for job in jobs:
                done(job[0], build_shard(*job))
        else:
            # spawn, not fork: the caller may hold CUDA or open HDF5 files, which forked children must not inherit
            ctx = multiprocessing.get_context("spawn")
            with ProcessPoolExecutor(max_workers=min(workers, len(jobs)), mp_context=ctx) as pool:
                for future in as_completed([pool.submit(_build_shard_job, job) for job in jobs]):
                    done(*future.result())
    finally:
        bar.close()
    for p in paths:
        manifest["sessions"].setdefault(str(p), shard_name(p))
    _write_manifest(root, manifest)
    return root


def _check_finite(batch: dict[str, torch.Tensor], audio: torch.Tensor, ds: TouchWindows, pos: int, n: int) -> None:
    for name, x in (("audio", audio), ("imu", batch["imu"]), ("pressure", batch["pressure"])):
        bad = ~torch.isfinite(x.reshape(n, -1)).all(dim=1)
        if bool(bad.any()):
            i = pos + int(torch.nonzero(bad)[0])
            s, _, _ = ds.index[i]
            raise SessionError(f"session {ds.paths[int(s)]}: non-finite {name} in the window ending at "
                               f"t={ds.end_times[i]:.4f} s")


def _write_manifest(root: Path, manifest: dict[str, Any]) -> None:
    tmp = root / (MANIFEST + ".tmp")
    tmp.write_text(json.dumps(manifest, indent=2, sort_keys=True) + "\n")
    tmp.replace(root / MANIFEST)


class CachedWindows(Dataset):
    """Windows of a cache (see the module docstring), for some or all of its sessions.

    Args:
        root: the cache directory.
        sessions: session files to read (e.g. one side of ``split_sessions``); None = every session in the cache.
        labels: labels to return; None = those every selected session has.

    Samples: ``image`` (2, 224, 224, 3) uint8 frames [t-5, t]; ``audio`` (224, 256) float16 log-mel; ``imu``
    (224, 3), ``pressure`` (224, 1) float32; ``finger``, ``session`` (index into ``paths``), ``time``; labels as
    TouchWindows returns them. ``paths``, ``index`` and ``end_times`` mean what they mean in TouchWindows.
    """

    def __init__(self, root: str | Path, sessions: Sequence[str | Path] | None = None,
                 labels: Sequence[str] | None = None):
        self.root = Path(root)
        path = self.root / MANIFEST
        if not path.is_file():
            raise ValueError(f"cache {self.root}: no {MANIFEST} (build it with `rotate cache-touch`)")
        manifest = json.loads(path.read_text())
        if manifest.get("version") != CACHE_VERSION:
            raise ValueError(f"cache {self.root}: format version {manifest.get('version')}, this code reads "
                             f"{CACHE_VERSION}; rebuild it")
        self.fingers, self.stride = tuple(manifest["fingers"]), int(manifest["stride"])
        known = manifest["sessions"]
        wanted = sorted(known) if sessions is None else [str(Path(s).resolve()) for s in sessions]
        missing = [s for s in wanted if s not in known]
        if missing:
            raise ValueError(f"cache {self.root}: session(s) not cached: {', '.join(missing[:3])}"
                             f"{' ...' if len(missing) > 3 else ''} (run `rotate cache-touch` on them)")
        self.paths = [Path(s) for s in wanted]
        self.shards = [self.root / known[s] for s in wanted]
        infos = []
        for shard, session in zip(self.shards, self.paths, strict=True):
            done = shard / SHARD_DONE
            if not done.is_file():
                raise ValueError(f"cache {self.root}: shard {shard.name} of {session} is incomplete (rebuild it)")
            infos.append(json.loads(done.read_text()))
        present = set.intersection(*(set(i["labels"]) for i in infos)) if infos else set()
        self.labels = tuple(sorted(present)) if labels is None else tuple(labels)
        lacking = [n for n in self.labels if n not in present]
        if lacking:
            raise SessionError(f"cache {self.root}: label(s) {lacking} are missing from some of the sessions "
                               f"(every session has: {sorted(present)})")
        counts = np.array([int(i["windows"]) for i in infos], dtype=np.int64)
        self._starts = np.concatenate([[0], np.cumsum(counts)])
        fingers = [np.load(s / "finger.npy") for s in self.shards]
        times = [np.load(s / "time.npy") for s in self.shards]
        self.index = (np.stack([np.repeat(np.arange(len(self.shards)), counts), np.concatenate(fingers) if fingers
                                else np.zeros(0, np.int64), np.zeros(int(counts.sum()), np.int64)], axis=1)
                      if len(self.shards) else np.zeros((0, 3), np.int64))
        """(num_windows, 3): session, finger, 0 (window ends are not needed once rendered)."""
        self.end_times = np.concatenate(times) if times else np.zeros(0)
        self._pid = -1
        self._maps: dict[int, dict[str, np.ndarray]] = {}

    def __len__(self) -> int:
        return int(self._starts[-1])

    def _shard(self, s: int) -> dict[str, np.ndarray]:
        if self._pid != os.getpid():  # memory maps are opened per process (DataLoader workers)
            self._maps, self._pid = {}, os.getpid()
        if s not in self._maps:
            d = self.shards[s]
            maps = {k: np.load(d / f"{k}.npy", mmap_mode="r") for k in ("frames", *_MODALITY_FILES)}  # lazy reads
            maps["frame_rows"] = np.load(d / "frame_rows.npy")
            for name in self.labels:
                maps[f"label_{name}"] = np.load(d / f"label_{name}.npy")
            self._maps[s] = maps
        return self._maps[s]

    def __getitem__(self, i: int) -> dict[str, Any]:
        if not 0 <= i < len(self):
            raise IndexError(f"window {i} out of range ({len(self)})")
        s = int(np.searchsorted(self._starts, i, side="right")) - 1
        w = i - int(self._starts[s])
        m = self._shard(s)
        out: dict[str, Any] = {
            "image": torch.from_numpy(m["frames"][m["frame_rows"][w]]),  # (2, H, W, 3), fancy indexing copies
            "audio": torch.from_numpy(np.array(m["audio"][w])),  # a copy: the map is read-only
            "imu": torch.from_numpy(np.array(m["imu"][w])),
            "pressure": torch.from_numpy(np.array(m["pressure"][w])),
            "finger": torch.tensor(int(self.index[i, 1]), dtype=torch.int64),
            "session": torch.tensor(s, dtype=torch.int64),
            "time": torch.tensor(float(self.end_times[i]), dtype=torch.float64),
        }
        for name in self.labels:
            out[name] = torch.from_numpy(np.array(m[f"label_{name}"][w], dtype=np.float32))
        return out

    def describe(self) -> str:
        return (f"CachedWindows: {len(self)} windows from {len(self.paths)} session(s) in {self.root}, fingers "
                f"{', '.join(self.fingers)}, labels {', '.join(self.labels) or 'none'}")

    def __getstate__(self) -> dict[str, Any]:
        state = dict(self.__dict__)
        state["_maps"], state["_pid"] = {}, -1
        return state


# ------------------------------------------------------------------------------------------------ the command
@dataclass(frozen=True)
class Config:
    """Pre-render touch windows of sessions into a cache (`rotate cache-touch`)."""

    sessions: tuple[Path, ...] = (Path("touch_sessions"),)
    """Session files or directories (every *.h5 below them)."""
    out: Path = Path("touch_cache")
    """Cache directory (created; completed with whatever is missing if it exists)."""
    fingers: tuple[str, ...] = FINGERS
    """Fingertips to cache."""
    stride: int = 5
    """Index every stride-th image frame (30 fps / 5 = 6 windows per second and fingertip)."""
    workers: int = 0
    """Processes rendering sessions in parallel, one session each (0 = in this process; about 160 windows/s each)."""
    audio_dtype: Literal["float16", "float32"] = "float16"
    """Storage of the log-mel features: float16 (half the size) or float32 (exact)."""
    progress: bool = True
    """Show a progress bar."""

    def __post_init__(self) -> None:
        check_types(self)
        object.__setattr__(self, "sessions", check_session_sources(self.sessions))
        check_output_dir("out", self.out)
        check_fingers(self.fingers)
        check_int("stride", self.stride, 1, 1000)
        check_int("workers", self.workers, 0, 1024)


def run(cfg: Config) -> dict[str, Any]:
    out = build_cache(cfg.sessions, cfg.out, cfg.fingers, cfg.stride, cfg.workers, cfg.audio_dtype, cfg.progress)
    ds = CachedWindows(out)
    print(f"cache-touch: {ds.describe()}")
    (out / "config.json").write_text(json.dumps(to_jsonable(cfg), indent=2) + "\n")
    return {"windows": len(ds), "sessions": len(ds.paths)}
