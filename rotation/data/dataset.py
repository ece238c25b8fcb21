"""Sparsh-X input windows from session files (simulated or real), one fingertip per sample.

A sample is one fingertip's window ending at one of its image timestamps (docs/reference/sparsh.md "Sparsh-X input
contract"), with the labels known at that time::

    image     (6, 224, 224) float32 in [0, 1], channels [R(t-5), R(t), G(t-5), G(t), B(t-5), B(t)]
    audio     (224, 256) float32 log-mel (Kaldi fbank of the 2 x 27000 int16-count window,
              rotation.data.audio)
              or, with ``audio_features=False``, ``audio_wave`` (2, 27000) float32 for a batched fbank on the GPU
    imu       (224, 3) float32, g (400 Hz)
    pressure  (224, 1) float32, hPa (200 Hz)
    finger    int64 (0..3, envs.constants.FINGERS), session int64 (index into ``paths``), time float64 (s)
    labels    any of force (3,), slip (), contact (), object_pose (7,), priv (9,), z (8,): the last label sample
              at or before the window's end (labels are at the control rate, images at 30 fps)

Causality: every sample of a window has a timestamp at or before the window's end; windows whose history does not
reach back far enough (the first ~1.1 s of a session, for the 1.12 s pressure window) are not indexed.
Simulated fingertips (a ``contact`` stream) are rendered on the fly by envs.sensors.digit360_render with the
session's noise key, so a window read here equals the env's `tactile` observation at the same step; recorded
fingertips are read and resampled (linear for IMU and pressure, nearest for audio and images).
"""

from __future__ import annotations

import math
import os
from collections.abc import Iterable, Sequence
from pathlib import Path
from typing import Any

import numpy as np
import torch
from torch.utils.data import Dataset

from envs.constants import FINGERS
from envs.errors import RequestRefused
from envs.rng import splitmix64
from envs.scene import HANDS, touch_model
from envs.sensors.digit360_image import pack_image
from envs.sensors.digit360_model import (
    AUDIO_SAMPLES,
    FRAME_GAP,
    IMAGE_HZ,
    IMAGE_SIZE,
    IMU_HZ,
    IMU_SAMPLES,
    PRESSURE_HZ,
    PRESSURE_SAMPLES,
    ContactTrack,
    Digit360Model,
    finger_key,
)
from envs.sensors.digit360_render import WindowIndex, render_window
from rotation.data.audio import fbank
from rotation.data.session import SessionError
from rotation.data.session_reader import SessionReader

LABELS = ("force", "contact_force", "slip", "contact", "object_pose", "priv", "z", "content", "fill", "content_mass",
          "object", "action", "surface", "surface_force", "socket", "prong", "depth", "socket_force")
"""Per-step labels a sample may carry (streams ``labels/<name>``)."""
PER_FINGERTIP = ("force", "contact_force", "slip", "contact")
"""The labels with one value per fingertip (a sample carries its own fingertip's)."""
_RECORDED = ("image", "audio", "imu", "pressure")
_TIME_EPS = 1e-6


def session_key(reader: SessionReader) -> int:
    """The noise key of a simulated session: the env's episode key stored by the collector, else from the seed."""
    key = reader.meta.extra.get("touch_key")
    if key is not None:
        return int(key)
    with np.errstate(over="ignore"):
        return int(splitmix64(np.asarray([reader.meta.seed & 0xFFFFFFFFFFFFFFFF], dtype=np.uint64))[0])


def split_sessions(paths: Iterable[str | Path], val_fraction: float = 0.1, seed: int = 0
                   ) -> tuple[list[Path], list[Path]]:
    """Split session files into (train, val) by file, deterministically under ``seed``.

    Files are sorted by path first, so the split depends only on the set of files and the seed. With two or more
    files and ``val_fraction > 0`` both sides get at least one.
    """
    if not 0.0 <= val_fraction < 1.0:
        raise ValueError(f"val_fraction must be in [0, 1), got {val_fraction}")
    files = sorted(Path(p) for p in paths)
    if len(set(files)) != len(files):
        raise ValueError("split_sessions: a session file is listed twice")
    order = np.random.default_rng(seed).permutation(len(files))
    n_val = 0 if val_fraction == 0 or len(files) < 2 else min(len(files) - 1, max(1, round(val_fraction * len(files))))
    val = sorted(files[i] for i in order[:n_val])
    train = sorted(files[i] for i in order[n_val:])
    return train, val


def check_session_sources(sources: Sequence[str | os.PathLike]) -> tuple[Path, ...]:
    """The ``sessions`` field of a config: at least one session file or directory; returned as Paths (a config read
    back from JSON holds strings). ValueError naming the field otherwise."""
    if not sources:
        raise ValueError("sessions: give at least one session file or directory")
    return tuple(Path(p) for p in sources)


def check_fingers(fingers: Sequence[str]) -> None:
    """The ``fingers`` field of a config: distinct fingertip names (ValueError naming the field otherwise)."""
    bad = [f for f in fingers if f not in FINGERS]
    if bad or not fingers or len(set(fingers)) != len(fingers):
        raise ValueError(f"fingers: need distinct names among {', '.join(FINGERS)}, got {list(fingers)}")


def find_sessions(root: str | Path) -> list[Path]:
    """Every ``*.h5`` session under ``root`` (a file is returned as is), sorted."""
    root = Path(root)
    if root.is_file():
        return [root]
    if not root.is_dir():
        raise RequestRefused(f"no session file or directory at {root}")
    return sorted(root.rglob("*.h5"))


def _resample_linear(t_src: np.ndarray, x_src: np.ndarray, t_grid: np.ndarray, t_end: float) -> np.ndarray:
    """Linear interpolation of (n, c) samples onto t_grid using only samples at or before t_end (held at the ends)."""
    keep = int(np.searchsorted(t_src, t_end + _TIME_EPS, side="right"))
    t, x = t_src[:keep], x_src[:keep].astype(np.float64)
    return np.stack([np.interp(t_grid, t, x[:, c]) for c in range(x.shape[1])], axis=1).astype(np.float32)


def _session_sensor(r: SessionReader) -> Digit360Model:
    """The simulated sensor a session was collected with: its hand's (``extra["sim_hand"]``, written by `rotate
    collect`; 'digit360' when unnamed, as in collections before the vendor-kinematics hand)."""
    hand = str(r.meta.extra.get("sim_hand", "digit360"))
    if hand not in HANDS:
        raise SessionError(f"session {r.path}: extra['sim_hand'] = {hand!r} is not a simulated hand "
                           f"({', '.join(HANDS)})")
    return touch_model(hand)


class TouchWindows(Dataset):
    """Sparsh-X windows of every fingertip and image timestamp of a set of sessions (see the module docstring).

    Args:
        paths: session files.
        fingers: fingertips to index (default all four; sessions must hold touch data for each).
        labels: label names to return (see ``LABELS``); None = those present in every session.
        stride: index every ``stride``-th image timestamp.
        audio_features: return the log-mel ``audio`` (True) or the raw ``audio_wave`` (False).
        model: the simulated sensor's parameters for sessions from simulation; None (the default): each session's
            own, the sensor of the hand it was collected on (``extra["sim_hand"]``, envs.scene.touch_model; sessions
            that name none are from the 'digit360' hand).
    """

    def __init__(self, paths: Sequence[str | Path], fingers: Sequence[str] = FINGERS,
                 labels: Sequence[str] | None = None, stride: int = 1, audio_features: bool = True,
                 model: Digit360Model | None = None):
        self.paths = [Path(p) for p in paths]
        if not self.paths:
            raise RequestRefused("TouchWindows: no session files given")
        unknown = [f for f in fingers if f not in FINGERS]
        if unknown:
            raise ValueError(f"TouchWindows: unknown finger(s) {unknown}; fingers: {', '.join(FINGERS)}")
        if stride < 1:
            raise ValueError(f"TouchWindows: stride must be >= 1, got {stride}")
        self.fingers = tuple(fingers)
        self.audio_features, self.model = audio_features, model
        present: set[str] | None = None
        index: list[np.ndarray] = []
        times: list[np.ndarray] = []
        self._kind: list[dict[str, str]] = []
        self._models: list[Digit360Model] = []
        for s, path in enumerate(self.paths):
            with SessionReader(path) as r:
                have = {n.split("/", 1)[1] for n in r.names if n.startswith("labels/")}
                present = have if present is None else present & have
                kinds = {}
                for f in self.fingers:
                    kinds[f] = self._finger_kind(r, f)
                    ends = self._window_ends(r, f, kinds[f])[::stride]  # (W,) frame numbers or image rows
                    fi = FINGERS.index(f)
                    index.append(np.stack([np.full(len(ends), s), np.full(len(ends), fi), ends], axis=1))
                    if kinds[f] == "sim":
                        times.append(ends / IMAGE_HZ)
                    else:
                        times.append(r.stream(f"digit360/{f}/image", lazy=True).timestamps[ends])
                self._kind.append(kinds)
                self._models.append(model if model is not None else _session_sensor(r))
        self.labels = tuple(sorted(present or ())) if labels is None else tuple(labels)
        bad = [n for n in self.labels if n not in LABELS]
        if bad:
            raise ValueError(f"TouchWindows: unknown label(s) {bad}; labels: {', '.join(LABELS)}")
        if present is not None:
            lacking = [n for n in self.labels if n not in present]
            if lacking:
                raise SessionError(f"TouchWindows: label(s) {lacking} are missing from some of the sessions "
                                   f"(every session has: {sorted(present)})")
        self.index = np.concatenate(index).astype(np.int64) if index else np.zeros((0, 3), np.int64)
        """(num_windows, 3): session, finger, window end (frame number for simulated, image row for recorded)."""
        self.end_times = np.concatenate(times) if times else np.zeros(0)
        """(num_windows,) time of each window's end (s since its session started)."""
        self._pid = -1
        self._readers: dict[int, SessionReader] = {}
        self._tracks: dict[tuple[int, int], ContactTrack] = {}

    # --------------------------------------------------------------------------------------- index
    @staticmethod
    def _finger_kind(r: SessionReader, finger: str) -> str:
        names = {n for n in r.names if n.startswith(f"digit360/{finger}/")}
        if f"digit360/{finger}/contact" in names:
            return "sim"
        missing = [m for m in _RECORDED if f"digit360/{finger}/{m}" not in names]
        if missing:
            raise SessionError(f"session {r.path}: fingertip {finger!r} has neither simulated contact fields "
                               f"(digit360/{finger}/contact) nor the recorded streams "
                               f"(missing: {', '.join(f'digit360/{finger}/{m}' for m in missing)})")
        return "real"

    def _window_ends(self, r: SessionReader, finger: str, kind: str) -> np.ndarray:
        """Window ends of one fingertip whose whole history lies inside the session."""
        label_start = max([r.stream(f"labels/{n}").timestamps[0] for n in LABELS if r.has(f"labels/{n}")] + [-np.inf])
        if kind == "sim":
            t = r.stream(f"digit360/{finger}/contact").timestamps
            if len(t) == 0:
                return np.zeros(0, np.int64)
            first, last = math.ceil(t[0] * IMAGE_HZ - _TIME_EPS), math.floor(t[-1] * IMAGE_HZ + _TIME_EPS)
            frames = np.arange(int(first), int(last) + 1)  # 30 fps frames inside the recorded contact rows
            ok = [WindowIndex(int(k)).start_time >= t[0] - _TIME_EPS and k / IMAGE_HZ >= label_start - _TIME_EPS
                  for k in frames]
            return frames[np.asarray(ok, dtype=bool)] if len(frames) else frames
        t_img = r.stream(f"digit360/{finger}/image", lazy=True).timestamps
        rows = np.arange(FRAME_GAP, len(t_img))
        need = {"imu": IMU_SAMPLES / IMU_HZ, "pressure": PRESSURE_SAMPLES / PRESSURE_HZ}
        ok = t_img[rows] >= label_start - _TIME_EPS
        for m, span in need.items():
            ts = r.stream(f"digit360/{finger}/{m}").timestamps
            ok &= (t_img[rows] - span >= ts[0] - _TIME_EPS) if len(ts) else False
        t_audio = r.stream(f"digit360/{finger}/audio", lazy=True).timestamps
        ok &= np.searchsorted(t_audio, t_img[rows] + _TIME_EPS, side="right") >= AUDIO_SAMPLES
        return rows[ok]

    # --------------------------------------------------------------------------------------- access
    def __len__(self) -> int:
        return len(self.index)

    def _reader(self, s: int) -> SessionReader:
        if self._pid != os.getpid():  # h5py handles do not survive fork: reopen in each worker
            self._readers, self._tracks, self._pid = {}, {}, os.getpid()
        if s not in self._readers:
            self._readers[s] = SessionReader(self.paths[s])
        return self._readers[s]

    def contact_track(self, s: int, finger: str) -> ContactTrack:
        """The simulated contact fields of session ``s``'s fingertip ``finger`` (a simulated session's)."""
        if self._kind[s][finger] != "sim":
            raise SessionError(f"session {self.paths[s]}: fingertip {finger!r} is recorded, not simulated: it has "
                               "no contact fields")
        return self._track(s, finger)

    def sensor_model(self, s: int) -> Digit360Model:
        """The simulated sensor session ``s`` renders with."""
        return self._models[s]

    def labels_at(self, rows: np.ndarray, name: str) -> np.ndarray:
        """Label ``name`` of windows ``rows`` (indices into this dataset), read without rendering: (len(rows), ...),
        a per-fingertip label at the window's own fingertip."""
        rows = np.asarray(rows, np.int64)
        out: list[np.ndarray | None] = [None] * len(rows)
        for s in np.unique(self.index[rows, 0]):
            mine = np.flatnonzero(self.index[rows, 0] == s)
            st = self._reader(int(s)).stream(f"labels/{name}")
            j = np.searchsorted(st.timestamps, self.end_times[rows[mine]] + _TIME_EPS, side="right") - 1
            value = np.asarray(st.data)[np.maximum(j, 0)]
            if name in PER_FINGERTIP:
                value = value[np.arange(len(mine)), self.index[rows[mine], 1]]
            for k, m in enumerate(mine):
                out[m] = value[k]
        return np.asarray(out, np.float32)

    def _track(self, s: int, finger: str) -> ContactTrack:
        key = (s, FINGERS.index(finger))
        if key not in self._tracks:
            r = self._reader(s)
            st = r.stream(f"digit360/{finger}/contact")
            self._tracks[key] = ContactTrack(st.timestamps, st.data, 1.0 / st.rate_hz)
        return self._tracks[key]

    def __getitem__(self, i: int) -> dict[str, Any]:
        s, fi, end = (int(v) for v in self.index[i])
        finger = FINGERS[fi]
        r = self._reader(s)
        if self._kind[s][finger] == "sim":
            key = finger_key(session_key(r), fi)
            raw = render_window(self._track(s, finger), end, int(key), fi, self._models[s])
            t_end = end / IMAGE_HZ
            frames, wave, imu, pressure = raw["image"], raw["audio"], raw["imu"], raw["pressure"][:, None]
        else:
            t_end, frames, wave, imu, pressure = self._recorded(r, finger, end)
        out: dict[str, Any] = {
            "image": torch.from_numpy(pack_image(frames)),
            "imu": torch.from_numpy(np.ascontiguousarray(imu, dtype=np.float32)),
            "pressure": torch.from_numpy(np.ascontiguousarray(pressure, dtype=np.float32)),
            "finger": torch.tensor(fi, dtype=torch.int64),
            "session": torch.tensor(s, dtype=torch.int64),
            "time": torch.tensor(t_end, dtype=torch.float64),
        }
        wave_t = torch.from_numpy(np.ascontiguousarray(wave, dtype=np.float32))  # (2, 27000) int16 counts
        if self.audio_features:
            out["audio"] = fbank(wave_t)  # (224, 256)
        else:
            out["audio_wave"] = wave_t
        for name in self.labels:
            st = r.stream(f"labels/{name}")
            j = int(np.searchsorted(st.timestamps, t_end + _TIME_EPS, side="right")) - 1  # last label <= t_end
            value = np.asarray(st.data[j])
            if name in PER_FINGERTIP:
                value = value[fi]
            out[name] = torch.from_numpy(np.asarray(value, dtype=np.float32))
        return out

    def _recorded(self, r: SessionReader, finger: str, row: int):
        """A recorded fingertip's window ending at image row ``row``."""
        img = r.stream(f"digit360/{finger}/image", lazy=True)
        t_end = float(img.timestamps[row])
        frames = np.stack([img.data[row - FRAME_GAP], img.data[row]])  # (2, H, W, 3) uint8
        if frames.shape[1:3] != (IMAGE_SIZE, IMAGE_SIZE):
            frames = center_resize(frames, IMAGE_SIZE)
        audio = r.stream(f"digit360/{finger}/audio", lazy=True)
        last = int(np.searchsorted(audio.timestamps, t_end + _TIME_EPS, side="right"))  # samples at or before t_end
        wave = np.asarray(audio.data[last - AUDIO_SAMPLES : last], dtype=np.float32).T  # (2, 27000)
        if not np.isfinite(wave).all():  # lazily read streams are checked window by window
            raise SessionError(f"session {r.path}, stream 'digit360/{finger}/audio': non-finite samples before "
                               f"t={t_end:.4f} s")
        imu_grid = t_end - np.arange(IMU_SAMPLES - 1, -1, -1) / IMU_HZ
        p_grid = t_end - np.arange(PRESSURE_SAMPLES - 1, -1, -1) / PRESSURE_HZ
        imu_st, p_st = r.stream(f"digit360/{finger}/imu"), r.stream(f"digit360/{finger}/pressure")
        imu = _resample_linear(imu_st.timestamps, imu_st.data, imu_grid, t_end)
        pressure = _resample_linear(p_st.timestamps, p_st.data, p_grid, t_end)
        return t_end, frames, wave, imu, pressure

    def describe(self) -> str:
        kinds = sorted({k for d in self._kind for k in d.values()})
        return (f"TouchWindows: {len(self)} windows from {len(self.paths)} session(s) ({', '.join(kinds)}), "
                f"fingers {', '.join(self.fingers)}, labels {', '.join(self.labels) or 'none'}")

    def __getstate__(self) -> dict[str, Any]:
        state = dict(self.__dict__)
        state["_readers"], state["_tracks"], state["_pid"] = {}, {}, -1  # handles are per process
        return state


def center_resize(frames: np.ndarray, size: int) -> np.ndarray:
    """(K, H, W, 3) uint8 -> (K, size, size, 3): centre square crop, then bilinear resize with antialiasing."""
    h, w = frames.shape[1:3]
    side = min(h, w)
    top, left = (h - side) // 2, (w - side) // 2
    x = torch.from_numpy(np.ascontiguousarray(frames[:, top : top + side, left : left + side])).permute(0, 3, 1, 2)
    x = torch.nn.functional.interpolate(x.float(), size=(size, size), mode="bilinear", antialias=True,
                                        align_corners=False)
    return x.round().clamp(0, 255).to(torch.uint8).permute(0, 2, 3, 1).numpy()
