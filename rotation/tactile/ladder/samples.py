"""The samples of the information ladder (`rotate touch-report`): hand-level windows, their targets, and the
features of the two stages below the encoder.

A *sample* is one moment of one session: the four fingertips' Sparsh-X windows ending at the same image frame
(rotation.data.dataset.TouchWindows). Its targets:

- ``friction_tercile``: the session's friction coefficient in the lower, middle or upper third of the report's
  sessions (accuracy; chance 1/3); ``friction``: the coefficient itself (R^2);
- ``mass`` (kg) and ``com`` (the centre-of-mass shift, m, 3 values) of the session's object (R^2);
- ``normal_force``: each fingertip's normal force at its strongest contact in the last contact row of the window
  (N, 4 values, R^2; the per-step labels lag the window's end by up to a control step, the rows by under one physics
  step);
- ``slip``: whether a contact of each fingertip slides faster than ``SLIP_THRESHOLD`` in that row (F1 over the
  four).

Stage 1 reads the simulated contact fields of the window's span (envs.sensors.digit360.CONTACT_FIELDS: what MuJoCo
gives the sensor, the ceiling); stage 2 the rendered streams through simple fixed features (the ceiling a renderer
leaves); both per fingertip, concatenated over the four.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from envs.constants import FINGERS
from envs.errors import RequestRefused
from envs.sensors.digit360 import FIELD, contact_frame_force, contact_slip, mean_slip
from envs.sensors.digit360_model import IMAGE_HZ
from envs.sensors.digit360_render import WindowIndex
from rotation.data.dataset import TouchWindows
from rotation.data.session_reader import SessionReader

SLIP_THRESHOLD = 0.005
"""Slip speed (m/s) above which a fingertip counts as sliding (the probes' default)."""
TARGETS = ("friction_tercile", "friction", "mass", "com", "normal_force", "slip")
"""What the ladder reads, in report order."""
SESSION_TARGETS = ("friction_tercile", "friction", "mass", "com")
"""Properties of the session's object, constant over it: read from a history of windows (:func:`history_mean`)
when the report is given one; the others (normal force, slip) are the moment's own and read from its window."""
CLASSIFY = {"friction_tercile": "accuracy", "slip": "f1"}
"""Classification targets and their metric; the others are regressions scored by R^2."""
MODALITIES = ("image", "audio", "imu", "pressure")
FEATURE_VERSION = 4
"""Version of the feature definitions of stages 1-3: a report's saved features are reused only when it matches
(raise it when a feature changes)."""
END_AUDIO, END_SERIAL = 20, 20
"""Audio feature frames (2.5 ms each) and IMU samples (400 Hz) in the window's last 50 ms."""


@dataclass
class HandSamples:
    """Hand-level samples of a set of sessions: ``items`` (M, 4) indices into ``windows`` (one per fingertip),
    ``session`` (M,) and ``frame`` (M,) of each; per-session ``properties`` (friction, mass, com)."""

    windows: TouchWindows
    items: np.ndarray
    session: np.ndarray
    frame: np.ndarray
    friction: np.ndarray
    mass: np.ndarray
    com: np.ndarray

    def __len__(self) -> int:
        return len(self.items)

    @property
    def paths(self) -> list[Path]:
        return self.windows.paths


def open_samples(paths: Sequence[Path], stride: int) -> HandSamples:
    """Every ``stride``-th image frame at which all four fingertips of a session have a whole window."""
    ds = TouchWindows(paths, fingers=FINGERS, labels=(), stride=1)
    props = []
    for p in ds.paths:
        with SessionReader(p) as r:
            meta = r.meta.properties
            missing = [k for k in ("friction", "mass", "com") if k not in meta]
            if missing:
                raise RequestRefused(f"touch-report: session {p} lacks the object properties {', '.join(missing)}; "
                                     "simulated sessions from `rotate collect` carry them")
            props.append((float(meta["friction"]), float(meta["mass"]), np.asarray(meta["com"], float)))
    lookup = {(int(s), int(f), int(e)): i for i, (s, f, e) in enumerate(ds.index)}
    items, sessions, frames = [], [], []
    for s in range(len(ds.paths)):
        ends = sorted({int(e) for (ss, f, e) in lookup if ss == s and f == 0})
        for e in ends[::stride]:
            row = [lookup.get((s, f, e)) for f in range(len(FINGERS))]
            if all(i is not None for i in row):
                items.append(row)
                sessions.append(s)
                frames.append(e)
    if not items:
        raise RequestRefused("touch-report: the sessions hold no whole window (each needs 1.12 s of touch)")
    fr, ma, co = (np.asarray([p[i] for p in props]) for i in range(3))
    return HandSamples(ds, np.asarray(items, np.int64), np.asarray(sessions), np.asarray(frames), fr, ma, co)


def history_mean(values: np.ndarray, session: np.ndarray, frame: np.ndarray, seconds: float) -> np.ndarray:
    """(M, F) -> (M, F): each sample's ``values`` averaged over the samples of its session whose window ends within
    the ``seconds`` before its own, its own included (causal: nothing later; 0 returns the values unchanged). What
    a reader that keeps a running mean of the features over the last ``seconds`` sees, as a policy with a history
    of touch could."""
    values = np.asarray(values, np.float64)
    if seconds <= 0:
        return values
    out = np.empty_like(values)
    span = seconds * IMAGE_HZ
    for s in np.unique(session):
        mine = np.flatnonzero(session == s)
        mine = mine[np.argsort(frame[mine], kind="stable")]
        f = frame[mine].astype(np.float64)
        first = np.searchsorted(f, f - span, side="right")  # the earliest sample inside the history
        sums = np.concatenate([np.zeros((1, values.shape[1])), np.cumsum(values[mine], 0)])
        last = np.arange(1, len(mine) + 1)
        out[mine] = (sums[last] - sums[first]) / (last - first)[:, None]
    return out


SLIP_FLOOR = 0.05
"""The least weight a window has in a slip-weighted history (:func:`slip_history`): with no slip in the history the
reading is the plain mean."""


def finger_columns(widths: Sequence[int]) -> np.ndarray:
    """The fingertip (0-3) of each column of features concatenated from blocks of the given widths, each block the
    four fingertips' equal parts side by side (the layout of every rung's features)."""
    parts = []
    for w in widths:
        if w % len(FINGERS):
            raise ValueError(f"a block of {w} columns does not split over {len(FINGERS)} fingertips")
        parts.append(np.repeat(np.arange(len(FINGERS)), w // len(FINGERS)))
    return np.concatenate(parts) if parts else np.zeros(0, np.int64)


def slip_history(values: np.ndarray, finger: np.ndarray, weights: np.ndarray, session: np.ndarray,
                 frame: np.ndarray, seconds: float) -> np.ndarray:
    """(M, F) -> (M, F): :func:`history_mean` with each window weighted per fingertip, a fingertip's columns
    (``finger``: (F,) fingertip of each column) by ``weights`` (M, 4: how likely that fingertip slides in the window,
    at least ``SLIP_FLOOR``). The friction coefficient shows only while a contact slides (then the shear is mu times
    the normal load; while it sticks, anything below), so a reader of friction should count the sliding windows most.
    Causal as history_mean; 0 seconds returns the values unchanged."""
    values, weights = np.asarray(values, np.float64), np.maximum(np.asarray(weights, np.float64), SLIP_FLOOR)
    if seconds <= 0:
        return values
    out = np.empty_like(values)
    for f in range(weights.shape[1]):
        cols = np.flatnonzero(finger == f)
        w = weights[:, f:f + 1]
        num = history_mean(values[:, cols] * w, session, frame, seconds)
        out[:, cols] = num / history_mean(w, session, frame, seconds)
    return out


def targets(samples: HandSamples, tercile_edges: np.ndarray) -> dict[str, np.ndarray]:
    """Target name -> (M, k) float array (classes as integers)."""
    s = samples.session
    friction = samples.friction[s]
    out = {
        "friction_tercile": np.searchsorted(tercile_edges, friction, side="right")[:, None].astype(np.float64),
        "friction": friction[:, None],
        "mass": samples.mass[s][:, None],
        "com": samples.com[s],
    }
    force, slip = np.zeros((len(samples), len(FINGERS))), np.zeros((len(samples), len(FINGERS)))
    for f, finger in enumerate(FINGERS):
        for sess in np.unique(s):
            mine = np.flatnonzero(s == sess)
            track = samples.windows.contact_track(int(sess), finger)
            rows = track.rows[track.last_row(samples.frame[mine] / IMAGE_HZ)].astype(np.float64)  # (k, D)
            force[mine, f] = contact_frame_force(rows)[:, 0]
            slip[mine, f] = contact_slip(rows) > SLIP_THRESHOLD  # the per-step slip label, at this row
    out["normal_force"], out["slip"] = force, slip
    return out


# ------------------------------------------------------------------------------------------ stage 1: contact fields
CONTACT_FEATURES = ("fn", "ft", "slip", "ratio_sliding", "sliding", "vn", "acc", "force", "point", "vertical_shear")


def contact_features(samples: HandSamples) -> np.ndarray:
    """(M, F) physical features of each sample's window span, per fingertip: mean, spread and last value of the
    normal and tangential force at the contact, slip speed, the shear-to-normal ratio while sliding (the friction
    coefficient when it slides), the sliding fraction, normal velocity, accelerometer, net force, contact point,
    and the shear along gravity (the accelerometer's mean direction: what carries the weight)."""
    ds, out = samples.windows, []
    for m in range(len(samples)):
        s, frame = int(samples.session[m]), int(samples.frame[m])
        w = WindowIndex(frame)
        per_finger = []
        for finger in FINGERS:
            track = ds.contact_track(s, finger)
            lo = int(np.searchsorted(track.times, w.start_time - 1e-6))
            hi = int(np.searchsorted(track.times, frame / IMAGE_HZ + 1e-6, side="right"))
            per_finger.append(_track_features(track.rows[lo:max(hi, lo + 1)]))
        out.append(np.concatenate(per_finger))
    return np.asarray(out, np.float64)


def _track_features(rows: np.ndarray) -> np.ndarray:
    rows = np.asarray(rows, np.float64)
    cf = contact_frame_force(rows).astype(np.float64)  # (T, 2) normal, tangential at the strongest contact
    fn, ft = cf[:, 0], cf[:, 1]
    slip = mean_slip(rows)
    sliding = slip > SLIP_THRESHOLD
    ratio = float((ft[sliding] / np.maximum(fn[sliding], 1e-3)).mean()) if sliding.any() else 0.0
    vn = rows[:, FIELD["c0_vn"]]
    acc = rows[:, FIELD["acc_x"]:FIELD["acc_z"] + 1]
    force = rows[:, [FIELD["force_x"], FIELD["force_y"], FIELD["force_n"]]]
    point = rows[:, [FIELD["c0_x"], FIELD["c0_y"], FIELD["c0_z"]]]
    down = -acc.mean(0) / max(np.linalg.norm(acc.mean(0)), 1e-6)  # gravity's direction in the sensor frame
    on_dome = np.stack([force[:, 0], force[:, 1], -force[:, 2]], 1)  # the force on the dome, sensor frame
    vertical = on_dome @ -down  # what the dome pushes up with
    stats = lambda x: [x.mean(), x.std(), x[-1]]  # noqa: E731
    return np.asarray([*stats(fn), *stats(ft), *stats(slip), ratio, sliding.mean(), vn.std(), *acc.mean(0),
                       *acc.std(0), *force.mean(0), *point.mean(0), *stats(vertical)], np.float64)


# ------------------------------------------------------------------------------------------ stage 2: rendered streams
def stream_features(window: dict, reference: np.ndarray) -> dict[str, np.ndarray]:
    """Simple features of one fingertip's contract window (rotation.data.dataset item) per modality.

    image: 7 x 7 average pools of the frame at t minus the sensor's no-contact reference (signed and absolute)
    and of the change from t-5 to t, and the markers' motion (:func:`marker_flow`) from the reference to t and from
    t-5 to t; audio: mean, spread and maximum over time of 16 mel bands per microphone; IMU: mean, spread, the
    spread of its first difference (the high band) and the last sample; pressure (high-passed as the encoder sees
    it): spread, range, the end's offset from the window mean and the linear trend. The window's end is where the
    per-fingertip targets are read, so audio, IMU and pressure also keep its last 50 ms apart (the mel bands' mean
    over the last 20 frames, the accelerometer's spread and jerk over its last 20 samples, the pressure's change
    over the last 10).
    """
    img = np.asarray(window["image"], np.float32)  # (6, H, W): [R(t-5), R(t), G(t-5), G(t), B(t-5), B(t)]
    now, before = img[1::2], img[0::2]
    pool = lambda x: _pool(x, 7).ravel()  # noqa: E731
    image = np.concatenate([pool(now - reference), pool(np.abs(now - reference)), pool(now - before),
                            marker_flow(reference, now).ravel(), marker_flow(before, now).ravel()])
    mel = np.asarray(window["audio"], np.float32)  # (224, 256): two microphones x 128 bins
    bands = mel.reshape(len(mel), 2, 16, 8).mean(-1).reshape(len(mel), 32)
    audio = np.concatenate([bands.mean(0), bands.std(0), bands.max(0), bands[-END_AUDIO:].mean(0)])
    imu = np.asarray(window["imu"], np.float64)
    end = imu[-END_SERIAL:]
    imu_f = np.concatenate([imu.mean(0), imu.std(0), np.diff(imu, axis=0).std(0), imu[-1], end.std(0),
                            np.diff(end, axis=0).std(0)])
    p = np.asarray(window["pressure"], np.float64)[:, 0]
    hp = p - p.mean()
    slope = np.polyfit(np.arange(len(hp)), hp, 1)[0]
    pressure = np.asarray([hp.std(), hp.max() - hp.min(), hp[-1], slope * len(hp), hp[-1] - hp[-END_SERIAL // 2]])
    return {"image": image, "audio": audio, "imu": imu_f, "pressure": pressure}


def marker_flow(a: np.ndarray, b: np.ndarray, n: int = 7) -> np.ndarray:
    """(n, n, 2) motion (pixels: column, row) of the fine texture from image ``a`` to ``b`` ((3, H, W) each) in
    n x n blocks: Lucas-Kanade on the gray images high-passed (minus a 5 x 5 box blur), which keeps the markers and
    drops the imprint's smooth shading. Fixed, not learnt: what a lab's marker tracker reports."""
    ga, gb = (_highpass(np.asarray(x, np.float64).mean(0)) for x in (a, b))
    gy, gx = np.gradient(0.5 * (ga + gb))
    gt = gb - ga
    terms = [gx * gx, gx * gy, gy * gy, gx * gt, gy * gt]
    sums = [_pool(t[None], n)[0] for t in terms]  # (n, n) block means
    sxx, sxy, syy, sxt, syt = sums
    det = sxx * syy - sxy * sxy
    ok = det > 1e-12
    u = np.where(ok, -(syy * sxt - sxy * syt) / np.where(ok, det, 1.0), 0.0)
    v = np.where(ok, -(sxx * syt - sxy * sxt) / np.where(ok, det, 1.0), 0.0)
    return np.stack([u, v], -1)


def _highpass(g: np.ndarray, k: int = 5) -> np.ndarray:
    """``g`` minus its k x k box blur (edges padded by reflection)."""
    pad = k // 2
    p = np.pad(g, pad, mode="reflect")
    c = np.cumsum(np.cumsum(np.pad(p, ((1, 0), (1, 0))), 0), 1)
    blur = (c[k:, k:] - c[:-k, k:] - c[k:, :-k] + c[:-k, :-k]) / (k * k)
    return g - blur


def _pool(x: np.ndarray, n: int) -> np.ndarray:
    """(C, H, W) -> (C, n, n) block means (H and W cropped to a multiple of n)."""
    c, h, w = x.shape
    h2, w2 = h // n * n, w // n * n
    return x[:, :h2, :w2].reshape(c, n, h2 // n, n, w2 // n).mean((2, 4))
