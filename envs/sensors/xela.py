"""Simulated Xela uSkin on the Allegro hand, numpy side: the taxel reading model, and the layout's names.

The layout (``PADS``, ``NUM_TAXELS``, ``TAXEL_TYPE``, ``taxel_layout()``, ...) lives in envs.sensors.xela_layout
and is re-exported here, so ``from envs.sensors.xela import PADS, TAXEL_TYPE, XelaSkin`` is the one import a skin
consumer needs (no MuJoCo, no torch).

The reading model (:class:`XelaSkin`, all stand-ins, documented in docs/skin.md): the contact force of each pad
contact is spread over the taxels through the elastomer with a Gaussian kernel (``spread``, each taxel gets the
share of the load over its cell), scaled by counts per newton, per-taxel gains and offsets, a slow random-walk
drift, white noise, and hysteresis: loading is followed at once, unloading recovers with ``release_tau`` and a
fraction ``memory`` of the peak stays and fades with ``memory_tau`` (a reading that does not snap back at release).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, fields
from functools import cache

import numpy as np

from envs.rng import splitmix64
from envs.sensors.xela_layout import (  # noqa: F401 (re-exported: the layout's names)
    AXES,
    FULL_SCALE,
    LINK_RADIUS,
    MAX_PAD_TAXELS,
    NUM_PADS,
    NUM_TAXELS,
    PAD_NAMES,
    PAD_SLICES,
    PAD_TAXEL_INDEX,
    PAD_TAXELS,
    PAD_THICKNESS,
    PADS,
    PALM_SIZE,
    PHALANX_SIZE,
    REST,
    SAMPLE_HZ,
    TAXEL_PAD,
    TAXEL_TYPE,
    TAXEL_TYPES,
    TIP_LENGTH,
    TIP_PITCH,
    TIP_RADIUS,
    TIP_START,
    V4_TIP_START,
    VALID_RANGE,
    WINDOW,
    XELA_HANDS,
    PadMount,
    PadSpec,
    TaxelLayout,
    pad_mounts,
    skin_metadata,
    taxel_layout,
)


@dataclass(frozen=True)
class XelaModel:
    """Parameters of the reading model. Stand-ins chosen to look like the real sensor's raw stream (docs/skin.md);
    none is a vendor figure."""

    counts_per_newton: tuple[float, float, float] = (900.0, 900.0, 1800.0)
    """Counts per newton of load over one taxel's cell (X, Y shear, Z normal): a 2 N fingertip press moves the taxel
    under it by about 1,700 counts in Z, well inside the 20k..60k window Sparsh-skin keeps."""
    spread: float = 0.0035
    """Standard deviation (m) of the Gaussian that spreads a contact's load through the elastomer (about its
    thickness); a taxel reads the share of the load over its cell."""
    gain_std: float = 0.1
    """Per taxel and axis gain ~ N(1, gain_std), drawn per episode (a sensor's unit-to-unit variation)."""
    offset_std: float = 400.0
    """Per taxel and axis baseline offset ~ N(0, offset_std) counts around REST."""
    noise_std: tuple[float, float, float] = (6.0, 6.0, 10.0)
    """White noise per sample (counts, X Y Z)."""
    drift_std: float = 40.0
    """Stationary standard deviation of the slow drift (counts), an Ornstein-Uhlenbeck walk per taxel and axis."""
    drift_tau: float = 30.0
    """Correlation time of the drift (s)."""
    release_tau: float = 0.05
    """Recovery time of the elastomer after unloading (s); loading is followed at once."""
    memory: float = 0.05
    """Fraction of the peak reading that stays after release (magnet / elastomer hysteresis)."""
    memory_tau: float = 2.0
    """Time over which that residual fades (s)."""

    def __post_init__(self) -> None:
        for f in fields(self):
            value = getattr(self, f.name)
            values = value if isinstance(value, tuple) else (value,)
            if len(values) not in (1, 3) or not all(isinstance(v, int | float) and not isinstance(v, bool)
                                                    and math.isfinite(v) and v >= 0 for v in values):
                raise ValueError(f"XelaModel.{f.name} must be finite and >= 0, got {value!r}")
        for name in ("spread", "drift_tau", "release_tau", "memory_tau"):
            if getattr(self, name) <= 0:
                raise ValueError(f"XelaModel.{name} must be > 0, got {getattr(self, name)}")
        if self.memory >= 1:
            raise ValueError(f"XelaModel.memory must be in [0, 1), got {self.memory}")


DEFAULT_MODEL = XelaModel()
_BANK_ROWS = 1024
_STREAM_NOISE, _STREAM_DRIFT = 1, 2


@cache
def _noise_bank() -> np.ndarray:
    """(1024, 368 x 3) standard normals, fixed: per-sample noise is a hashed pick of two rows (cheap and keyed)."""
    bank = np.random.default_rng(0x58454C41).standard_normal((_BANK_ROWS, NUM_TAXELS * 3)).astype(np.float32)
    bank.setflags(write=False)
    return bank


def _keyed_normals(keys: np.ndarray, counter: np.ndarray, stream: int) -> np.ndarray:
    """(*counter.shape, 368, 3) standard normals keyed by (env key, sample counter, stream): (row a +- row b) / sqrt 2
    of the bank, a, b and the sign hashed (over a million combinations; no per-sample random generator). ``keys``
    (N,) and ``counter`` (N,) or (N, S)."""
    keys = keys.reshape(keys.shape + (1,) * (counter.ndim - 1))
    with np.errstate(over="ignore"):
        h = splitmix64(keys ^ splitmix64(counter.astype(np.uint64) * np.uint64(0x9E3779B97F4A7C15)
                                         + np.uint64(stream)))
    a = (h % np.uint64(_BANK_ROWS)).astype(np.int64)
    b = ((h >> np.uint64(20)) % np.uint64(_BANK_ROWS)).astype(np.int64)
    sign = np.where((h >> np.uint64(40)) & np.uint64(1), 1.0, -1.0).astype(np.float32)
    bank = _noise_bank()
    out = (bank[a] + sign[..., None] * bank[b]) * np.float32(1 / math.sqrt(2))
    return out.reshape(*counter.shape, NUM_TAXELS, 3)


def pad_load(points: np.ndarray, forces: np.ndarray, found: np.ndarray, model: XelaModel = DEFAULT_MODEL
             ) -> np.ndarray:
    """Per-taxel load (counts before gains) from the pads' contacts.

    Each contact's force is shared among its pad's taxels by a Gaussian of the distance from the contact point
    (the elastomer), each taxel taking the part over its cell, and read in the taxel's own axes.

    Args:
        points: (..., 18, K, 3) contact points in each pad's frame (m).
        forces: (..., 18, K, 3) contact force on the pad, pad frame (N).
        found: (..., 18, K) whether each contact slot holds a contact.
    Returns:
        (..., 368, 3) load in counts per taxel axis (X, Y shear, Z normal).
    """
    lead = found.shape[:-2]
    out = np.zeros((int(np.prod(lead, dtype=np.int64)), NUM_TAXELS, 3))
    where = np.nonzero(found.reshape(-1, *found.shape[-2:]))  # the few slots holding a contact: (sample, pad, slot)
    if len(where[0]):
        lay = taxel_layout()
        sample, pad = where[0], where[1]
        flat_pts = points.reshape(-1, *points.shape[-3:])[where]  # (M, 3)
        flat_f = forces.reshape(-1, *forces.shape[-3:])[where]  # (M, 3)
        tax = PAD_TAXEL_INDEX[pad]  # (M, 30), -1 = none
        valid = tax >= 0
        tax = np.where(valid, tax, 0)
        d2 = ((lay.pos[tax] - flat_pts[:, None, :]) ** 2).sum(-1)  # (M, 30)
        s2 = 2.0 * model.spread**2
        w = lay.area[tax] / (math.pi * s2) * np.exp(-d2 / s2) * valid  # share of the load over each taxel's cell
        local = np.einsum("mtab,mb->mta", lay.frames[tax], flat_f)  # (M, 30, 3) in the taxel's axes
        # the pad pushes back against the contact: pressing is a force on the pad along -normal, read as +Z
        scale = np.asarray(model.counts_per_newton) * np.array([1.0, 1.0, -1.0])
        contrib = w[..., None] * local * scale  # (M, 30, 3)
        flat = (sample[:, None] * NUM_TAXELS + tax).ravel()
        for a in range(3):
            out[..., a] = np.bincount(flat, contrib[..., a].ravel(), minlength=out.shape[0] * NUM_TAXELS).reshape(
                out.shape[:2])
    return out.reshape(*lead, NUM_TAXELS, 3)


class XelaSkin:
    """The reading model of N skins, one 100 Hz sample at a time (deterministic under the per-episode keys)."""

    def __init__(self, num_envs: int, dt: float = 1.0 / SAMPLE_HZ, model: XelaModel = DEFAULT_MODEL):
        if not isinstance(model, XelaModel):
            raise ValueError(f"XelaSkin: model must be a XelaModel, got {type(model).__name__}")
        n, shape = int(num_envs), (int(num_envs), NUM_TAXELS, 3)
        self.model, self.dt = model, float(dt)
        self.keys = np.zeros(n, dtype=np.uint64)
        """(N,) per-episode key of each skin (gains, offsets, noise and drift follow it)."""
        self.counter = np.zeros(n, dtype=np.int64)
        """(N,) samples drawn in the episode."""
        self.gain = np.ones(shape, np.float32)
        self.offset = np.zeros(shape, np.float32)
        self.drift = np.zeros(shape, np.float32)
        self.elastic = np.zeros(shape, np.float32)
        """Load the elastomer passes on (counts): follows loading at once, lags at unloading."""
        self.residual = np.zeros(shape, np.float32)
        """Hysteresis memory (counts): a fraction of the last peak, fading."""
        self._a_release = math.exp(-self.dt / model.release_tau)
        self._a_memory = math.exp(-self.dt / model.memory_tau)
        self._a_drift = math.exp(-self.dt / model.drift_tau)

    def reset(self, ids: np.ndarray, keys: np.ndarray, load: np.ndarray | None = None) -> None:
        """Start skins ``ids`` on new episodes keyed ``keys`` (uint64); ``load`` (k, 368, 3) is the load they start
        under, as if held for a while (None: unloaded)."""
        ids = np.asarray(ids, dtype=np.int64)
        keys = np.asarray(keys, dtype=np.uint64)
        m = self.model
        for i, key in zip(ids, keys, strict=True):  # once per episode: a generator per env is fine here
            rng = np.random.default_rng(int(key))
            self.gain[i] = 1.0 + m.gain_std * rng.standard_normal((NUM_TAXELS, 3))
            self.offset[i] = m.offset_std * rng.standard_normal((NUM_TAXELS, 3))
            self.drift[i] = m.drift_std * rng.standard_normal((NUM_TAXELS, 3))
        self.keys[ids] = keys
        self.counter[ids] = 0
        start = np.zeros((len(ids), NUM_TAXELS, 3), np.float32) if load is None else load * self.gain[ids]
        self.elastic[ids] = start
        self.residual[ids] = m.memory * start

    def sample(self, load: np.ndarray, ids: np.ndarray | None = None) -> np.ndarray:
        """Advance the skins (all, or ``ids``) one sample under ``load`` (N or k, 368, 3) counts (see
        :func:`pad_load`); returns their raw readings (N or k, 368, 3) float32: whole counts in [0, 65535]."""
        return self.run(load[:, None], ids)[:, 0]

    def run(self, load: np.ndarray, ids: np.ndarray | None = None) -> np.ndarray:
        """Advance the skins (all, or ``ids``) through S samples under ``load`` (N or k, S, 368, 3); returns the raw
        readings (N or k, S, 368, 3) float32."""
        m = self.model
        sel = slice(None) if ids is None else np.asarray(ids, dtype=np.int64)
        keys, counter = self.keys[sel], self.counter[sel]
        samples = load.shape[1]
        counters = counter[:, None] + np.arange(samples)  # (k, S)
        drift_steps = _keyed_normals(keys, counters, _STREAM_DRIFT) * np.float32(
            m.drift_std * math.sqrt(1.0 - self._a_drift**2))
        raw = _keyed_normals(keys, counters, _STREAM_NOISE) * np.asarray(m.noise_std, np.float32)  # noise first
        raw += np.float32(REST) + self.offset[sel][:, None]
        x_all = (load * self.gain[sel][:, None]).astype(np.float32)
        elastic, residual, drift = self.elastic[sel], self.residual[sel], self.drift[sel]
        a_release, a_memory, a_drift = (np.float32(a) for a in (self._a_release, self._a_memory, self._a_drift))
        for s in range(samples):  # the recurrences: elastomer lag, hysteresis memory, drift
            x = x_all[:, s]
            elastic = np.where(np.abs(x) >= np.abs(elastic), x, x + (elastic - x) * a_release)
            faded = residual * a_memory
            peak = np.float32(m.memory) * elastic
            residual = np.where(np.abs(peak) > np.abs(faded), peak, faded)
            drift = drift * a_drift + drift_steps[:, s]
            raw[:, s] += drift + elastic + residual
        self.elastic[sel], self.residual[sel], self.drift[sel] = elastic, residual, drift
        self.counter[sel] += samples
        return np.clip(np.rint(raw, out=raw), 0.0, FULL_SCALE, out=raw)
