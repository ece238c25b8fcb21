"""Xela skin windows from session files: the Sparsh-skin dataset (the whole hand per sample) and its baselines.

A sample is the whole hand's skin over the 10 frames (0.1 s at 100 Hz) ending at one ``skin/xela`` frame
(docs/reference/sparsh.md "Sparsh-skin"), in the layout of the env's `skin` observation (envs.sensors.skin_obs) and of
the live reader (rotation.hardware.xela.reader), with the labels known at that time::

    skin           (10, 368, 6) float32  [..., :3] raw counts (X, Y, Z, about 32768 at rest), [..., 3:] taxel
                                         positions (m, hand frame) at the same frame
    xela_baseline  (368, 3) float32      the session's no-contact reading of every taxel and axis (counts)
    session        int64 (index into ``paths``), time float64 (s, the window's end)
    labels         any of skin_force (18, 3), object_pose (7,), joystick (3,), priv (9,), z (8,): the last label
                   sample at or before the window's end

The encoder's ``preprocess`` (rotation.tactile.models.sparsh_skin) subtracts the baseline and zeroes raw values outside
VALID_RANGE: one conditioning step for sessions, the env and the live reader. With ``sequence=S`` a sample is S
consecutive, non-overlapping windows ending at the same frame (the temporal decoders' input): ``skin``
(S, 10, 368, 6), ``time`` (S,) and every label (S, ...), one per window.

Frames are taken on a 100 Hz grid ending at the window's end (the last frame at or before each grid time), so a
recording with jitter or a dropped frame still gives 10 frames 10 ms apart, and nothing after the end is used.
Taxel positions are the session's ``skin/taxel_pos``; a recording of the real hand without them (an older one)
gets them from its ``joints/position`` by forward kinematics at each frame's timestamp (joint angles interpolated
linearly per joint; rotation.data.skin_positions says which hand model and which frames have them); a session
with neither stream is refused.
Baseline of a session, first found of: ``extra["xela_baseline"]`` (a reading measured without contact, e.g. by
`rotate deploy --skin` before the hand starts); for a simulated session (``extra["skin_key"]``) the simulated
skin's rest reading with that key's per-taxel offsets (envs.sensors.xela.XelaSkin); else the median of the valid
readings over the session's first ``baseline_s`` seconds (record real sessions so that they start without contact).
"""

from __future__ import annotations

import os
import warnings
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np
import torch
from torch.utils.data import Dataset

from envs.errors import RequestRefused
from envs.sensors.xela import NUM_TAXELS, REST, SAMPLE_HZ, VALID_RANGE, WINDOW, XelaSkin
from rotation.data.session import SessionError
from rotation.data.session_reader import SessionReader
from rotation.data.skin_positions import STORED, computed_positions, position_source, position_span

SKIN_LABELS = ("skin_force", "object_pose", "joystick", "priv", "z")
"""Labels a skin sample may carry (streams ``labels/<name>``)."""
BASELINE_KEY = "xela_baseline"
"""Session ``extra`` key of a measured no-contact baseline (368 x 3 counts)."""
_TIME_EPS = 1e-6


def estimate_baseline(raw: np.ndarray) -> np.ndarray:
    """(n, 368, 3) raw counts of a stretch without contact -> (368, 3) per taxel and axis median of the valid
    readings (REST where a taxel has none)."""
    raw = np.asarray(raw, dtype=np.float64)
    valid = (raw >= VALID_RANGE[0]) & (raw <= VALID_RANGE[1])
    masked = np.where(valid, raw, np.nan)
    with warnings.catch_warnings():  # a taxel without valid readings: 'All-NaN slice', handled below
        warnings.simplefilter("ignore", RuntimeWarning)
        base = np.nanmedian(masked, axis=0) if len(raw) else np.full(raw.shape[1:], np.nan)
    return np.where(np.isfinite(base), base, REST).astype(np.float32)


def session_baseline(r: SessionReader, baseline_s: float) -> np.ndarray:
    """The baseline of a session (see the module docstring): (368, 3) float32 counts."""
    stored = r.meta.extra.get(BASELINE_KEY)
    if stored is not None:
        base = np.asarray(stored, dtype=np.float32)
        if base.shape != (NUM_TAXELS, 3) or not np.isfinite(base).all():
            raise SessionError(f"session {r.path}: extra[{BASELINE_KEY!r}] must be {NUM_TAXELS} x 3 finite counts, "
                               f"got shape {base.shape}")
        return base
    key = r.meta.extra.get("skin_key")
    if r.meta.source == "sim" and key is not None:
        sim = XelaSkin(1)
        sim.reset(np.zeros(1, np.int64), np.array([int(key)], dtype=np.uint64))
        return (REST + sim.offset[0]).astype(np.float32)  # the simulated reading without load, drift or noise
    st = r.stream("skin/xela", lazy=True)
    n = int(np.searchsorted(st.timestamps, st.timestamps[0] + baseline_s + _TIME_EPS, side="right")) if len(st) else 0
    raw = np.asarray(st.data[: max(n, 1)]) if len(st) else np.zeros((0, NUM_TAXELS, 3))
    if not np.isfinite(raw).all():
        raise SessionError(f"session {r.path}, stream 'skin/xela': non-finite samples in the first {baseline_s} s")
    return estimate_baseline(raw)


_SHARED: dict[Path, SessionReader] = {}
_SHARED_PID = [-1]


def shared_reader(path: str | Path) -> SessionReader:
    """The one open reader of a session file in this process, shared by every SkinWindows (windows and sequences
    of the same sessions): two HDF5 handles on one SWMR file, each refreshing its datasets, corrupt each other's
    chunk cache ("can't insert duplicate key"). A forked worker opens its own."""
    if _SHARED_PID[0] != os.getpid():  # h5py handles do not survive fork
        _SHARED.clear()
        _SHARED_PID[0] = os.getpid()
    key = Path(path).resolve()
    if key not in _SHARED:
        _SHARED[key] = SessionReader(key)
    return _SHARED[key]


class SkinWindows(Dataset):
    """Sparsh-skin windows (or sequences of windows) of a set of sessions (see the module docstring).

    Args:
        paths: session files, each with ``skin/xela`` and either ``skin/taxel_pos`` or ``joints/position`` (the
            positions are then computed: rotation.data.skin_positions).
        labels: label names to return (see ``SKIN_LABELS``); None = those present in every session.
        stride: index every ``stride``-th ``skin/xela`` frame as a window end (5: 20 windows per second).
        sequence: None for single windows, else the number S of consecutive windows per sample.
        baseline_s: seconds at the start of a session whose median is its baseline (when none is stored).
    """

    def __init__(self, paths: Sequence[str | Path], labels: Sequence[str] | None = None, stride: int = 5,
                 sequence: int | None = None, baseline_s: float = 0.5):
        self.paths = [Path(p) for p in paths]
        if not self.paths:
            raise RequestRefused("SkinWindows: no session files given")
        if not isinstance(stride, int) or stride < 1:
            raise ValueError(f"SkinWindows: stride must be an integer >= 1, got {stride!r}")
        if sequence is not None and (not isinstance(sequence, int) or sequence < 1):
            raise ValueError(f"SkinWindows: sequence must be None or an integer >= 1, got {sequence!r}")
        if not baseline_s > 0:
            raise ValueError(f"SkinWindows: baseline_s must be > 0 s, got {baseline_s}")
        self.sequence = sequence
        self.length = WINDOW * (sequence or 1)
        """Frames per sample (10 per window)."""
        present: set[str] | None = None
        index, times = [], []
        self.baselines: list[np.ndarray] = []
        self.positions: list[str] = []
        """Per session, where its taxel positions come from: rotation.data.skin_positions.STORED, or the Xela hand
        model they are computed on from ``joints/position``."""
        for s, path in enumerate(self.paths):
            r = shared_reader(path)
            if not r.has("skin/xela"):
                raise SessionError(f"session {r.path}: no skin/xela stream (has: {', '.join(r.names) or 'none'}); "
                                   "`rotate collect --skin` and `rotate deploy --skin` record it")
            self.positions.append(position_source(r))
            have = {n.split("/", 1)[1] for n in r.names if n.startswith("labels/")}
            present = have if present is None else present & have
            ends = self._window_ends(r, self.positions[-1])[::stride]
            index.append(np.stack([np.full(len(ends), s), ends], axis=1))
            times.append(r.stream("skin/xela", lazy=True).timestamps[ends])
            self.baselines.append(session_baseline(r, baseline_s))
        self.labels = tuple(sorted(present & set(SKIN_LABELS))) if labels is None else tuple(labels)
        bad = [n for n in self.labels if n not in SKIN_LABELS]
        if bad:
            raise ValueError(f"SkinWindows: unknown label(s) {bad}; labels: {', '.join(SKIN_LABELS)}")
        lacking = [n for n in self.labels if n not in (present or set())]
        if lacking:
            raise SessionError(f"SkinWindows: label(s) {lacking} are missing from some of the sessions "
                               f"(every session has: {sorted(present or ())})")
        self.index = np.concatenate(index).astype(np.int64) if index else np.zeros((0, 2), np.int64)
        """(num_samples, 2): session, row of the window's last ``skin/xela`` frame."""
        self.end_times = np.concatenate(times) if times else np.zeros(0)
        """(num_samples,) time of each sample's end (s since its session started)."""

    def _window_ends(self, r: SessionReader, source: str) -> np.ndarray:
        """Rows of ``skin/xela`` whose whole history (and taxel positions, and labels) lies inside the session."""
        t = r.stream("skin/xela", lazy=True).timestamps
        if len(t) == 0:
            return np.zeros(0, np.int64)
        pos_first, pos_last = position_span(r, source)
        span = (self.length - 1) / SAMPLE_HZ
        starts = [t[0], pos_first] + [r.stream(f"labels/{n}").timestamps[0] for n in SKIN_LABELS
                                      if r.has(f"labels/{n}") and len(r.stream(f"labels/{n}"))]
        first_label = max(starts[2:], default=-np.inf)
        ok = (t - span >= max(starts[:2]) - _TIME_EPS) & (t - span >= first_label - _TIME_EPS)
        return np.flatnonzero(ok & (t <= pos_last + _TIME_EPS))

    def __len__(self) -> int:
        return len(self.index)

    def _reader(self, s: int) -> SessionReader:
        return shared_reader(self.paths[s])

    def _rows(self, timestamps: np.ndarray, t_end: float) -> np.ndarray:
        """(length,) rows of a stream on the 100 Hz grid ending at ``t_end``: the last sample at or before each."""
        grid = t_end - np.arange(self.length - 1, -1, -1) / SAMPLE_HZ
        return np.maximum(np.searchsorted(timestamps, grid + _TIME_EPS, side="right") - 1, 0)

    def _frames(self, r: SessionReader, name: str, t_end: float) -> np.ndarray:
        """(length, 368, 3) samples of ``name`` on the 100 Hz grid ending at ``t_end`` (causal)."""
        st = r.stream(name, lazy=True)
        rows = self._rows(st.timestamps, t_end)
        lo, hi = int(rows[0]), int(rows[-1]) + 1
        x = np.asarray(st.data[lo:hi])[rows - lo]
        if not np.isfinite(x).all():  # lazily read streams are checked window by window
            raise SessionError(f"session {r.path}, stream {name!r}: non-finite samples before t={t_end:.4f} s")
        return x

    def _positions(self, r: SessionReader, s: int, t_end: float) -> np.ndarray:
        """(length, 368, 3) taxel positions of the frames :meth:`_frames` takes from ``skin/xela``: stored, or
        computed from the joint angles at those frames' timestamps."""
        if self.positions[s] == STORED:
            return self._frames(r, "skin/taxel_pos", t_end)
        t = r.stream("skin/xela", lazy=True).timestamps
        return computed_positions(r, self.positions[s], t[self._rows(t, t_end)])

    def _shape(self, x: np.ndarray) -> np.ndarray:
        if self.sequence is None:
            return x  # (10, 368, 6)
        return x.reshape(self.sequence, WINDOW, *x.shape[1:])  # (S, 10, 368, 6)

    def window_end_times(self, t_end: float) -> np.ndarray:
        """End time of each window of the sample ending at ``t_end``: (S,), or () for single windows."""
        if self.sequence is None:
            return np.asarray(t_end)
        return t_end - (self.sequence - 1 - np.arange(self.sequence)) * WINDOW / SAMPLE_HZ

    def __getitem__(self, i: int) -> dict[str, Any]:
        s, _ = (int(v) for v in self.index[i])
        r = self._reader(s)
        t_end = float(self.end_times[i])
        window = np.concatenate([self._frames(r, "skin/xela", t_end), self._positions(r, s, t_end)],
                                axis=-1).astype(np.float32)  # (length, 368, 6)
        ends = self.window_end_times(t_end)
        out: dict[str, Any] = {
            "skin": torch.from_numpy(np.ascontiguousarray(self._shape(window))),
            "xela_baseline": torch.from_numpy(self.baselines[s].copy()),
            "session": torch.tensor(s, dtype=torch.int64),
            "time": torch.as_tensor(ends, dtype=torch.float64),
        }
        for name in self.labels:
            st = r.stream(f"labels/{name}")
            j = np.searchsorted(st.timestamps, ends + _TIME_EPS, side="right") - 1  # last label <= each end
            out[name] = torch.from_numpy(np.asarray(np.asarray(st.data)[j], dtype=np.float32))
        return out

    def labels_array(self, name: str) -> np.ndarray:
        """Label ``name`` of every sample, read without the skin: (N, ...) or (N, S, ...) float32."""
        if name not in self.labels:
            raise ValueError(f"SkinWindows: label {name!r} was not requested (labels: {', '.join(self.labels)})")
        out = []
        for s in range(len(self.paths)):
            rows = np.flatnonzero(self.index[:, 0] == s)
            if not len(rows):
                continue
            st = self._reader(s).stream(f"labels/{name}")
            ends = np.stack([self.window_end_times(t) for t in self.end_times[rows]])  # (n,) or (n, S)
            j = np.searchsorted(st.timestamps, ends + _TIME_EPS, side="right") - 1
            out.append(np.asarray(st.data)[j].astype(np.float32))
        return np.concatenate(out) if out else np.zeros((0,), np.float32)

    def describe(self) -> str:
        what = f"sequences of {self.sequence} windows" if self.sequence else "windows"
        return (f"SkinWindows: {len(self)} {what} from {len(self.paths)} session(s), labels "
                f"{', '.join(self.labels) or 'none'}")
