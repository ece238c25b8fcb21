"""Adapter training samples from recorded sessions: the real-data path of `rotate finetune-adapter`.

A session recorded by ``rotate deploy --digit360 ... --record FILE --properties ...`` (rotation.data.session, a real
or an emulated hand) gives, for every ``every``-th control step k (row k of ``joints/position``, time t_k):

- ``obs``: the student's groups ``proprio`` (3, 32) and ``proprio_hist`` (30, 32), rebuilt with the env's builder
  (envs.observation.ProprioHistory) the way the deploy loop feeds it (rotation.deploy.policy.PolicyState): the
  history starts filled with the start pose, and step k >= 1 pushes the frame (measured q_k, the targets commanded
  at step k - 1). The loop's start pose is read once before its first step, while the hand holds still, and is not
  recorded: the first recorded position stands in for it, so the observations of steps 0..29 (whose history still
  holds start frames) match the loop's to the hand's stillness, and from step 30 on they match exactly (to the
  float32 rounding of the recorded joints).
- ``windows``: per fingertip, the Sparsh-X windows the adapter reads, made as a deployed adapter's reader makes them
  (rotation.hardware.digit360.reader ``Digit360.window``) from the streams deploy records. IMU (224, 3) g and pressure
  (224, 1) hPa (the serial streams) end at the older of the newest IMU and pressure samples at or before t_k (and
  of the newest audio sample, when the adapter reads the audio), resampled by
  rotation.hardware.digit360.window.series_from_samples. With the image (a session recorded with ``--record-media``
  or by an adapter that reads it), every window ends at the newest camera frame at or before t_k: the image is that
  frame and the one 5 frames before it, (2, 224, 224, 3) uint8 RGB; the audio is the 27,000 samples up to the
  window's end, (2, 27000) int16. A step is skipped when any fingertip's window is not ready (the first ~1.1 s, a
  gap) or its sensor is stale (newest serial sample older than the reader's ``stale_timeout_s``, newest frame or
  audio sample older than its ``media_stale_timeout_s``): there the deployed adapter acts as the student alone.
- ``z``: the target, the teacher's env-factor encoder on the privileged vector (envs.constants.PRIV_FIELDS) built
  from the session's measured properties (rotation.data.properties: scale, mass, friction, com).

The object position (pos_x, pos_y, pos_z) is not measured on a real hand, and the teacher's z depends on it
strongly (as much as on friction; docs/adapter.md, "Fine-tuning on your own hand", gives the numbers), so what
stands in for it decides whether the targets are any better than the student's own latent. ``position``:

- ``"fit"`` (the default): per sample, the position that best explains the student's own latent phi(history)
  given the measured properties (least squares through the teacher's encoder, under a prior around the start
  position, within the region the env's objects occupy). The position is a nuisance here: fitted, the target
  keeps what the measured properties say and takes the position the student's history implies, so the adapter
  learns to correct friction, mass, CoM and scale, not to second-guess the position.
- ``"average"``: the teacher's z averaged over the object's start positions in the env (the shipped ``cup`` grasp
  cache, scale bucket nearest the session's scale), the least-squares target that ignores the student.
- ``"recorded"``: the session's ``labels/object_pose`` position (m, world frame of the simulated hand) at the step:
  an emulated hand, or a lab that tracks the object.
"""

from __future__ import annotations

import dataclasses
import logging
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import torch

from adapters.session_checks import (
    SERIAL_WINDOWS,
    Position,
    SessionInfo,
)
from envs import constants as C
from envs.observation import ProprioHistory
from rotation.data.dataset import center_resize
from rotation.data.session import SessionError
from rotation.data.session_reader import SessionReader
from rotation.hardware.digit360 import window as dw
from rotation.hardware.digit360.reader import Digit360Config

log = logging.getLogger(__name__)

POSITION_FIELDS = ("pos_x", "pos_y", "pos_z")
"""The privileged entries a real hand does not measure (envs.constants.PRIV_FIELDS)."""
Encoder = Callable[[torch.Tensor], torch.Tensor]
"""The teacher's env-factor encoder: (n, 9) privileged vectors -> (n, Z) latents."""
POSITION_OBJECT = "cup"
"""The simulated object whose grasp-cache start positions stand in for the unmeasured position."""
FIT_MARGIN_M = 0.02
"""The fitted position stays within the box of the env's start positions widened by this (m): the object drifts
by about 1-2 cm (standard deviation per axis) from its start during the shipped student's rollouts."""
FIT_STEPS, FIT_LR = 200, 2e-3
"""Adam steps and step size (m) of the position fit (100 or 300 steps gave targets of the same accuracy in
simulation)."""
FIT_PRIOR_M, FIT_PRIOR_WEIGHT = 0.015, 0.5
"""The fit's prior: a position FIT_PRIOR_M (m, per axis, about the object's drift during rollouts) from the mean start
position costs as much as a squared latent error of FIT_PRIOR_WEIGHT. Without it the position absorbs part of
what the student gets wrong about the measured properties (the target moves toward the student's latent); the
weight was picked on simulated rollouts and emulated-hand sessions (docs/adapter.md)."""
_READER = {f.name: f.default for f in dataclasses.fields(Digit360Config)}
STALE_S = _READER["stale_timeout_s"]
"""A fingertip whose newest serial sample is older than this (s) is stale (the reader raises SensorStale)."""
MEDIA_STALE_S = _READER["media_stale_timeout_s"]
"""A fingertip whose newest camera frame or audio sample is older than this (s) is stale."""


@dataclass
class SessionSamples:
    """Training samples of one session (n of them; see the module docstring)."""

    path: Path
    steps: np.ndarray
    """(n,) control step (row of joints/position)."""
    times: np.ndarray
    """(n,) s, session time of the step."""
    obs: dict[str, np.ndarray]
    """{'proprio': (n, 3, 32), 'proprio_hist': (n, 30, 32)} float32."""
    windows: dict[str, dict[str, np.ndarray]]
    """{finger: {window: (n, 224, c)}} float32."""
    z_student: np.ndarray
    """(n, Z) float32 the student's latent phi(history)."""
    z: np.ndarray
    """(n, Z) float32 target latent."""
    positions: np.ndarray | None
    """(n, 3) m object positions of the targets (fitted or recorded); None for 'average'."""
    skipped: int
    """Steps on the sampling grid left out for want of touch (not ready, stale)."""

    def __len__(self) -> int:
        return len(self.steps)


# ------------------------------------------------------------------------------------------------------- pieces
def proprio_observations(q: np.ndarray, targets: np.ndarray, steps: np.ndarray) -> dict[str, np.ndarray]:
    """The deploy loop's ``proprio`` (n, 3, 32) and ``proprio_hist`` (n, 30, 32) at control ``steps`` (sorted) from
    the recorded positions q (K, 16) and commanded targets (K, 16), rad (see the module docstring)."""
    q, targets = np.asarray(q, np.float64), np.asarray(targets, np.float64)
    history = ProprioHistory(1)
    history.reset(np.array([0]), q[:1])  # the loop's start fill: (q0, q0) in every frame
    proprio = np.zeros((len(steps), C.PROPRIO_STEPS, C.PROPRIO_DIM), np.float32)
    hist = np.zeros((len(steps), C.HISTORY_STEPS, C.PROPRIO_DIM), np.float32)
    j = 0
    for k in range(int(steps[-1]) + 1 if len(steps) else 0):
        if k > 0:  # the frame of step k - 1, pushed at step k: measured q_k with the targets of step k - 1
            history.push(q[k : k + 1], targets[k - 1 : k])
        if k == steps[j]:
            proprio[j], hist[j] = history.proprio[0], history.history[0]
            j += 1
    return {"proprio": proprio, "proprio_hist": hist}


def touch_windows(reader: SessionReader, fingers: Sequence[str], windows: Sequence[str], times: np.ndarray
                  ) -> tuple[dict[str, dict[str, np.ndarray]], np.ndarray]:
    """The fingertips' windows at session ``times`` (n,) s, as a deployed adapter's reader makes them (module
    docstring): ({finger: {window: (n, ...)}}: imu (n, 224, 3) and pressure (n, 224, 1) float32, image
    (n, 2, 224, 224, 3) uint8, audio (n, 2, 27000) int16; ok (n,) bool; rows with ok False are not filled)."""
    n = len(times)
    shapes = {"imu": ((dw.SERIES_LEN, 3), np.float32), "pressure": ((dw.SERIES_LEN, 1), np.float32),
              "image": ((2, dw.IMAGE_SIZE, dw.IMAGE_SIZE, 3), np.uint8), "audio": ((2, dw.AUDIO_SAMPLES), np.int16)}
    out = {f: {w: np.zeros((n, *shapes[w][0]), shapes[w][1]) for w in windows} for f in fingers}
    ok = np.ones(n, bool)
    for f in fingers:
        # the reader's clock streams: both serial streams it holds decide the window's end and staleness
        streams = {w: reader.stream(f"digit360/{f}/{w}") for w in SERIAL_WINDOWS if reader.has(f"digit360/{f}/{w}")}
        newest = np.stack([_newest_before(st.timestamps, times) for st in streams.values()])  # (S, n)
        ok &= np.isfinite(newest).all(axis=0) & (times - newest.max(axis=0) <= STALE_S)
        t_end = newest.min(axis=0)  # the older of the newest samples: no stream needs a future sample
        audio = reader.stream(f"digit360/{f}/audio", lazy=True) if "audio" in windows else None
        if audio is not None:
            newest_audio = _newest_before(audio.timestamps, times)
            ok &= times - newest_audio <= MEDIA_STALE_S
            t_end = np.minimum(t_end, newest_audio)  # the reader's rule: the oldest of its streams' newest
        image, rows = None, None
        if "image" in windows:  # a camera: every window ends at its newest frame
            image = reader.stream(f"digit360/{f}/image", lazy=True)
            rows = np.searchsorted(image.timestamps, times, side="right") - 1
            ok &= rows >= dw.IMAGE_GAP
            t_end = np.where(rows >= 0, image.timestamps[np.clip(rows, 0, None)], -np.inf)
            ok &= times - t_end <= MEDIA_STALE_S
        for i in np.flatnonzero(ok):
            try:
                for w in windows:
                    if w == "image":
                        frames = np.stack([image.data[rows[i] - dw.IMAGE_GAP], image.data[rows[i]]])
                        if frames.shape[1:3] != (dw.IMAGE_SIZE, dw.IMAGE_SIZE):
                            frames = center_resize(frames, dw.IMAGE_SIZE)
                        out[f][w][i] = frames
                    elif w == "audio":
                        out[f][w][i] = dw.audio_from_samples(audio.timestamps, audio.data, t_end[i])
                    else:
                        st, rate = streams[w], SERIAL_WINDOWS[w]
                        t, v = _tail(st.timestamps, st.data, t_end[i], dw.SERIES_LEN / rate)
                        out[f][w][i] = dw.series_from_samples(t, v, t_end[i], rate, dw.SERIES_LEN, name=w)
            except dw.WindowNotReady:
                ok[i] = False
    return out, ok


def _newest_before(t: np.ndarray, times: np.ndarray) -> np.ndarray:
    """(n,) time of the newest sample at or before each of ``times`` (-inf where none)."""
    if len(t) == 0:
        return np.full(len(times), -np.inf)
    idx = np.searchsorted(t, times, side="right") - 1
    return np.where(idx >= 0, t[np.clip(idx, 0, None)], -np.inf)


def _tail(t: np.ndarray, v: np.ndarray, t_end: float, span: float) -> tuple[np.ndarray, np.ndarray]:
    """The samples a window ending at ``t_end`` can use: the last one at or before its start through ``t_end``
    (the same window as from the whole stream, without copying it)."""
    hi = int(np.searchsorted(t, t_end, side="right"))
    lo = max(0, int(np.searchsorted(t, t_end - span, side="right")) - 1)
    return t[lo:hi], v[lo:hi]


def priv_vectors(props: dict[str, float | list[float]], positions: np.ndarray) -> np.ndarray:
    """(n, 9) privileged vectors in envs.constants.PRIV_FIELDS order from measured ``props`` (checked,
    rotation.data.properties) and object ``positions`` (n, 3) m."""
    com = np.asarray(props["com"], np.float64)
    fields = {**{f: positions[:, i] for i, f in enumerate(POSITION_FIELDS)}, "scale": props["scale"],
              "mass": props["mass"], "friction": props["friction"], "com_x": com[0], "com_y": com[1],
              "com_z": com[2]}
    n = len(positions)
    return np.stack([np.broadcast_to(np.asarray(fields[name], np.float64), (n,)) for name in C.PRIV_FIELDS], axis=1)


def _start_table() -> tuple[np.ndarray, np.ndarray]:
    """The shipped grasp cache's bucket scales (S,) and the object's start positions (S, G, 3) m in the env."""
    from envs.grasp_cache import load_default_cache

    cache = load_default_cache(POSITION_OBJECT)
    return cache.scales, cache.grasps[..., C.NUM_JOINTS : C.NUM_JOINTS + 3].astype(np.float64)


def start_positions(scale: float) -> np.ndarray:
    """(G, 3) m: the object's start positions in the env at the grasp-cache bucket nearest ``scale``."""
    scales, table = _start_table()
    return table[int(np.abs(scales - scale).argmin())]


@torch.no_grad()
def latents(encoder: Encoder, props: dict[str, float | list[float]], positions: np.ndarray) -> np.ndarray:
    """(n, Z) float32: ``encoder`` (the teacher's env-factor encoder) on the privileged vectors of ``props`` at the
    object ``positions`` (n, 3) m."""
    return encoder(torch.as_tensor(priv_vectors(props, positions), dtype=torch.float32)).numpy()


def average_latent(encoder: Encoder, props: dict[str, float | list[float]]) -> np.ndarray:
    """(Z,) the teacher's z of ``props`` averaged over the env's start positions at their scale."""
    return latents(encoder, props, start_positions(float(props["scale"]))).mean(0)


def fit_positions(encoder: Encoder, props: dict[str, float | list[float]], z_student: np.ndarray) -> np.ndarray:
    """(n, 3) m: per sample, the object position whose teacher z (with ``props``) is nearest (least squares) to the
    student's latent ``z_student`` (n, Z), under a Gaussian prior around the mean start position (FIT_PRIOR_M,
    FIT_PRIOR_WEIGHT); Adam from the mean start position, kept inside the box of the env's start positions widened by
    FIT_MARGIN_M. Deterministic; the encoder's weights get no gradients."""
    _, table = _start_table()
    lo = torch.as_tensor(table.reshape(-1, 3).min(0) - FIT_MARGIN_M, dtype=torch.float32)
    hi = torch.as_tensor(table.reshape(-1, 3).max(0) + FIT_MARGIN_M, dtype=torch.float32)
    n = len(z_student)
    start = start_positions(float(props["scale"])).mean(0)
    base = torch.as_tensor(priv_vectors(props, np.repeat(start[None], n, axis=0)), dtype=torch.float32)  # (n, 9)
    where = torch.as_tensor([C.PRIV_FIELDS.index(f) for f in POSITION_FIELDS])
    mean = base[:, where].clone()
    pos = mean.clone().requires_grad_(True)  # (n, 3)
    target = torch.as_tensor(z_student, dtype=torch.float32)
    optim = torch.optim.Adam([pos], lr=FIT_LR)
    for _ in range(FIT_STEPS):
        with torch.enable_grad():
            prior = FIT_PRIOR_WEIGHT * (((pos - mean) / FIT_PRIOR_M) ** 2).sum()
            loss = ((encoder(base.index_copy(1, where, pos)) - target) ** 2).sum() + prior
            (pos.grad,) = torch.autograd.grad(loss, [pos])
        optim.step()
        with torch.no_grad():
            pos.copy_(torch.maximum(torch.minimum(pos, hi), lo))
    return pos.detach().numpy().astype(np.float64)


# ------------------------------------------------------------------------------------------------------- samples
def session_samples(info: SessionInfo, encoder: Encoder, student_latent: Callable[[dict[str, np.ndarray]], Any],
                    fingers: Sequence[str], windows: Sequence[str], every: int = 2,
                    position: Position = "fit") -> SessionSamples:
    """The training samples of one checked session (:func:`check_session`): every ``every``-th control step with
    usable touch (module docstring). ``encoder``: the teacher's env-factor encoder; ``student_latent``: the
    student's phi on batched observations ({group: (n, ...)} -> (n, Z))."""
    with SessionReader(info.path) as r:
        pos, tgt = r.stream("joints/position"), r.stream("joints/target")
        k = info.steps
        if not np.array_equal(pos.timestamps[:k], tgt.timestamps[:k]):
            raise SessionError(f"session {info.path}: joints/position and joints/target are not recorded at the same "
                               "control steps")
        grid = np.arange(0, k, every)
        touch, ok = touch_windows(r, fingers, windows, pos.timestamps[grid])
        steps, times = grid[ok], pos.timestamps[grid[ok]]
        obs = proprio_observations(pos.data[:k], tgt.data[:k], steps)
        recorded = None
        if position == "recorded":
            pose = r.stream("labels/object_pose")
            idx = np.searchsorted(pose.timestamps, times, side="right") - 1  # the last pose at or before
            if len(idx) and idx[0] < 0:
                raise SessionError(f"session {info.path}: labels/object_pose starts after the first sampled step")
            recorded = np.asarray(pose.data[idx, :3], np.float64)
    n, props = len(steps), info.properties
    if n == 0:
        empty = np.zeros((0, average_latent(encoder, props).shape[0]), np.float32)
        return SessionSamples(info.path, steps, times, obs, {f: {w: x[:0] for w, x in d.items()}
                                                             for f, d in touch.items()}, empty, empty, None, len(grid))
    z_student = np.concatenate([np.asarray(student_latent({g: x[i : i + 1024] for g, x in obs.items()}), np.float32)
                                for i in range(0, n, 1024)])
    if position == "average":
        positions, z = None, np.repeat(average_latent(encoder, props)[None], n, axis=0)
    else:
        positions = recorded if position == "recorded" else fit_positions(encoder, props, z_student)
        z = latents(encoder, props, positions)
    return SessionSamples(info.path, steps, times, obs, {f: {w: x[ok] for w, x in d.items()} for f, d in touch.items()},
                          z_student, z.astype(np.float32), positions, int((~ok).sum()))
