"""The env's Digit 360 touch: per-env contact history and the `tactile` observation group.

With ``EnvConfig.tactile`` the core keeps, per env and fingertip, the contact-field rows (envs.sensors.digit360) of
the last ``HISTORY_S`` seconds in a ring (:class:`TouchState`, fed from the sensors' history after each policy
step, a few microseconds per env). The observation's ``tactile`` entry is a :class:`TactileObs`: a snapshot of those
rings that renders the Sparsh-X windows (docs/reference/sparsh.md) only when they are read::

    obs["tactile"]["index"]["image"]     # (N, 6, 224, 224) float32 in [0, 1], [R(t-5), R(t), G(t-5), ...]
    obs["tactile"]["index"]["audio"]     # (N, 224, 256) float32 log-mel (Kaldi fbank of int16-count audio)
    obs["tactile"]["index"]["imu"]       # (N, 224, 3) float32, g
    obs["tactile"]["index"]["pressure"]  # (N, 224, 1) float32, hPa

Every window ends at the env's current image timestamp (the last 30 fps frame at or before the env's time) and
holds no later sample. Rendering four fingertips' windows costs tens of milliseconds per env, far more than a
policy step of physics, which is why it is deferred: stepping with touch on costs only the sensors and the ring.
A :class:`TactileObs` is a dict (finger -> dict of modality -> array, values computed when read), so gymnasium's
checks and nested-space tools accept it; like the array groups it also has a leading env axis: indexing it with an
int, slice, mask or index array selects envs (an int drops the axis, as the single env does), and ``copy()`` and
masked assignment work as on arrays, so the vector adapters handle it unchanged.
"""

from __future__ import annotations

import math
from typing import Any

import gymnasium as gym
import numpy as np

from envs.rng import splitmix64
from envs.sensors import kaldi
from envs.sensors.digit360 import FINGERS, NUM_FIELDS, Digit360Readout
from envs.sensors.digit360_image import pack_image
from envs.sensors.digit360_model import (
    AUDIO_SAMPLES,
    DEFAULT_MODEL,
    HISTORY_S,
    IMAGE_HZ,
    IMAGE_SIZE,
    IMU_SAMPLES,
    PRESSURE_SAMPLES,
    ContactTrack,
    Digit360Model,
    finger_key,
)
from envs.sensors.digit360_render import render_window

MODALITIES = ("image", "audio", "imu", "pressure")
WINDOW_SHAPES: dict[str, tuple[int, ...]] = {
    "image": (6, IMAGE_SIZE, IMAGE_SIZE),
    "audio": (1 + (AUDIO_SAMPLES - kaldi.WINDOW_SIZE) // kaldi.WINDOW_SHIFT, 2 * kaldi.NUM_MEL_BINS),
    "imu": (IMU_SAMPLES, 3),
    "pressure": (PRESSURE_SAMPLES, 1),
}
"""Per-fingertip window shapes of the Sparsh-X input contract (docs/reference/sparsh.md)."""


def tactile_space() -> gym.spaces.Dict:
    """Observation space of one env's `tactile` group: finger -> modality -> Box (float32)."""
    return gym.spaces.Dict({
        finger: gym.spaces.Dict({m: gym.spaces.Box(-np.inf, np.inf, WINDOW_SHAPES[m], np.float32) for m in MODALITIES})
        for finger in FINGERS
    })


def contract_window(raw: dict[str, np.ndarray]) -> dict[str, np.ndarray]:
    """Raw streams of :func:`render_window` -> the contract's float32 arrays (audio through the Kaldi fbank)."""
    return {
        "image": pack_image(raw["image"]),
        "audio": kaldi.fbank(raw["audio"]),
        "imu": raw["imu"].astype(np.float32),
        "pressure": raw["pressure"].astype(np.float32)[:, None],
    }


class TouchState:
    """Ring of the last contact-field rows of N envs x 4 fingertips, fed by the batch's sensor history."""

    def __init__(self, model: Any, num_envs: int, dt: float, substeps: int,
                 sensor: Digit360Model = DEFAULT_MODEL):
        self.readout = Digit360Readout(model)
        self.sensor = sensor
        """The sensor model the observation renders with (the hand's dome radius)."""
        self.dt, self.substeps = float(dt), int(substeps)
        self.capacity = int(math.ceil(HISTORY_S / self.dt)) + 2 + self.substeps  # rows kept per env and finger
        n = int(num_envs)
        self.times = np.zeros((n, self.capacity))
        self.rows = np.zeros((n, len(FINGERS), self.capacity, NUM_FIELDS), dtype=np.float32)
        self.head = 0
        """Ring slot of the next row (all envs step together, so one head serves all)."""
        self.episode_keys = np.zeros(n, dtype=np.uint64)
        """(N,) noise key of each env's current episode (sessions store it so loaders render the same noise)."""
        self.keys = np.zeros((n, len(FINGERS)), dtype=np.uint64)
        """(N, 4) per-fingertip noise keys, ``finger_key(episode_key, f)``."""
        self.last_times = np.zeros((n, self.substeps))
        """(N, S) sample times of the last step's substeps (s since each env's reset)."""
        self.last_rows = np.zeros((n, len(FINGERS), self.substeps, NUM_FIELDS), dtype=np.float32)
        """(N, 4, S, NUM_FIELDS) contact fields of the last step's substeps (what sessions store)."""

    def reset(self, ids: np.ndarray, sensordata: np.ndarray, env_keys: np.ndarray, episodes: np.ndarray) -> None:
        """Start envs ``ids`` over: the current reading (after the reset's forward) fills the whole ring, as if the
        fingertips had rested in it; noise keys follow (env key, episode)."""
        rows0 = self.readout.read_current(sensordata[ids])  # (k, 4, 1, D)
        slots = (self.head - 1 - np.arange(self.capacity)) % self.capacity  # newest first
        self.rows[ids] = rows0  # broadcast over the ring
        t = np.empty(self.capacity)
        t[slots] = -self.dt * (np.arange(self.capacity) + 1)  # one step apart, the newest just before time 0
        self.times[ids] = t
        with np.errstate(over="ignore"):
            episode_keys = splitmix64(np.asarray(env_keys, dtype=np.uint64) ^ splitmix64(
                np.asarray(episodes, dtype=np.int64).astype(np.uint64)))  # (k,)
        self.episode_keys[ids] = episode_keys
        for f in range(len(FINGERS)):
            self.keys[ids, f] = [finger_key(int(k), f) for k in episode_keys]
        self.last_times[ids] = 0.0
        self.last_rows[ids] = rows0

    def push(self, history: np.ndarray) -> None:
        """Append every env's last ``substeps`` sensor samples from the batch's ``history`` (N, nhistory)."""
        times, rows = self.readout.read(history, self.substeps)  # (N, S), (N, 4, S, D)
        slots = (self.head + np.arange(self.substeps)) % self.capacity
        self.times[:, slots] = times
        self.rows[:, :, slots] = rows
        self.head = int((self.head + self.substeps) % self.capacity)
        self.last_times, self.last_rows = times, rows

    def observe(self, model: Digit360Model | None = None) -> TactileObs:
        """Snapshot of the rings as the `tactile` observation (rows ordered oldest first), rendered with ``model``
        (default: this state's sensor model)."""
        model = self.sensor if model is None else model
        order = (self.head + np.arange(self.capacity)) % self.capacity
        now = self.times[:, order[-1]] + self.dt  # env time after the last substep
        return TactileObs(self.times[:, order], self.rows[:, :, order], self.keys.copy(), now, self.dt, model=model)


class _LazyDict(dict):
    """A dict whose keys are fixed up front and whose values are computed on first read (by ``_value``).

    A real ``dict`` subclass, so code that checks ``isinstance(x, dict)`` and compares keys (gymnasium's env
    checker, nested-space utilities) accepts it; every read path goes through ``__getitem__``.
    """

    def __init__(self, keys: tuple[str, ...]):
        super().__init__(dict.fromkeys(keys))

    def _value(self, key: str) -> Any:
        raise NotImplementedError

    def __getitem__(self, key: Any) -> Any:
        if not dict.__contains__(self, key):
            raise KeyError(key)
        return self._value(key)

    def get(self, key: Any, default: Any = None) -> Any:
        return self[key] if dict.__contains__(self, key) else default

    def values(self) -> list[Any]:  # type: ignore[override]
        return [self[k] for k in self.keys()]

    def items(self) -> list[tuple[str, Any]]:  # type: ignore[override]
        return [(k, self[k]) for k in self.keys()]


class TactileObs(_LazyDict):
    """N envs' touch snapshots: finger -> modality -> window (N, ...), rendered on first read and cached.

    A dict over the four fingertips (see the module docstring); indexing with anything but a finger name selects
    envs like an array's leading axis.
    """

    def __init__(self, times: np.ndarray, rows: np.ndarray, keys: np.ndarray, now: np.ndarray, dt: float,
                 batched: bool = True, model: Digit360Model = DEFAULT_MODEL):
        super().__init__(FINGERS)
        # (N, R) row times (s), (N, 4, R, NUM_FIELDS) contact fields oldest first, (N, 4) noise keys, (N,) env time
        self.times, self.rows, self.noise_keys, self.now = times, rows, keys, now
        self.dt, self.batched, self.model = dt, batched, model
        self._cache: dict[str, dict[str, np.ndarray]] = {}

    @property
    def num_envs(self) -> int:
        return self.times.shape[0]

    @property
    def frame(self) -> np.ndarray:
        """(N,) index of each env's current image frame: the last 30 fps frame at or before its time."""
        return np.floor(self.now * IMAGE_HZ + 1e-6).astype(np.int64)

    def _value(self, finger: str) -> _FingerWindows:
        return _FingerWindows(self, finger)

    def __getitem__(self, item: Any) -> Any:
        if isinstance(item, str):
            if item not in FINGERS:
                raise KeyError(f"tactile observation: unknown finger {item!r}; fingers: {', '.join(FINGERS)}")
            return _FingerWindows(self, item)
        if not self.batched:
            raise IndexError("tactile observation of a single env has no env axis to index")
        if isinstance(item, int | np.integer):
            sel = slice(int(item), int(item) + 1 if int(item) != -1 else None)
            return TactileObs(self.times[sel], self.rows[sel], self.noise_keys[sel], self.now[sel], self.dt,
                              batched=False, model=self.model)
        return TactileObs(self.times[item], self.rows[item], self.noise_keys[item], self.now[item], self.dt,
                          model=self.model)

    def __setitem__(self, item: Any, other: Any) -> None:
        """Masked / indexed assignment of envs from another snapshot (as the vector adapters do on auto-reset)."""
        if not isinstance(other, TactileObs) or isinstance(item, str):
            raise TypeError("a TactileObs only takes env-indexed assignment from another TactileObs")
        self.times[item], self.rows[item] = other.times, other.rows
        self.noise_keys[item], self.now[item] = other.noise_keys, other.now
        self._cache.clear()

    def copy(self) -> TactileObs:
        return TactileObs(self.times.copy(), self.rows.copy(), self.noise_keys.copy(), self.now.copy(), self.dt,
                          self.batched, self.model)

    def __deepcopy__(self, memo: dict) -> TactileObs:
        return self.copy()

    def __reduce__(self):
        return (TactileObs, (self.times, self.rows, self.noise_keys, self.now, self.dt, self.batched, self.model))

    def window(self, env: int, finger: str) -> dict[str, np.ndarray]:
        """The four contract windows of one env's fingertip."""
        f = FINGERS.index(finger)
        track = ContactTrack(self.times[env], self.rows[env, f], self.dt)
        frame = int(self.frame[env])
        return contract_window(render_window(track, frame, int(self.noise_keys[env, f]), f, self.model))

    def render(self, finger: str) -> dict[str, np.ndarray]:
        """All four windows of ``finger`` for every env: modality -> (N, ...) (no N for a single env)."""
        if finger not in self._cache:
            per_env = [self.window(i, finger) for i in range(self.num_envs)]
            out = {m: np.stack([w[m] for w in per_env]) for m in MODALITIES}
            self._cache[finger] = out if self.batched else {m: v[0] for m, v in out.items()}
        return self._cache[finger]

    def numpy(self) -> dict[str, dict[str, np.ndarray]]:
        """Every window as plain nested dicts of arrays (renders everything)."""
        return {finger: dict(self.render(finger)) for finger in FINGERS}

    def __eq__(self, other: object) -> bool:
        return self is other

    __hash__ = None  # type: ignore[assignment]

    def __repr__(self) -> str:
        shape = f"N={self.num_envs}" if self.batched else "single env"
        return f"TactileObs({shape}, fingers={FINGERS}, modalities={MODALITIES}, rendered on access)"


class _FingerWindows(_LazyDict):
    """modality -> window array of one fingertip; the four are rendered together on first access."""

    def __init__(self, obs: TactileObs, finger: str):
        super().__init__(MODALITIES)
        self._obs, self._finger = obs, finger

    def _value(self, modality: str) -> np.ndarray:
        return self._obs.render(self._finger)[modality]

    def __getitem__(self, modality: Any) -> np.ndarray:
        if modality not in MODALITIES:
            raise KeyError(f"tactile observation: unknown modality {modality!r}; modalities: {', '.join(MODALITIES)}")
        return self._value(modality)

    def __repr__(self) -> str:
        return f"<{self._finger} windows {', '.join(f'{m} {WINDOW_SHAPES[m]}' for m in MODALITIES)}>"
