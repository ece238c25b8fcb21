"""The touch delay of a tactile adapter in simulation: how many control steps pass between the touch a correction
reads and the first action it changes, drawn per refresh from what `rotate deploy` measures on a robot.

On a robot the touch path takes time: the worker reads the fingertips' newest windows after the policy has acted on
step k, encodes them beside the control loop (rotation.deploy.touch_worker) and the loop acts on the correction from
the first control step after it lands. Deploy records how many control steps that took for each correction (the
summary's ``touch.first_use_steps``, and its age then, ``touch.first_use_age_ms_p50`` / ``_p95``; on emulated
fingertips also ``touch.first_use_steps_no_render``, without the emulator's rendering of their image and audio,
which a real sensor does not cost); scripts/bench_adapter.py ``--deploy`` reports them. That distribution is what
training and evaluation apply here, so an adapter learns and is judged with the delay it will meet.

A delay is written as text, the form every command takes (``--touch-delay``):

- ``measured``: :data:`MEASURED`, the distribution deploy measured for the shipped adapter on 2 CPU cores at 20 Hz
  (its source below);
- ``N``: always N steps (``0``: the correction acts on the very step whose touch it read, the ideal);
- ``N:P,M:Q,...``: N steps with probability P, M with Q, ... (the probabilities are normalized).

The delay line (:class:`DelayLine`) keeps one schedule per env, as deploy does for its one hand: a refresh falls due
``touch_every`` steps after the previous one started, starts only once the previous correction has landed (never two
at once), and its correction acts from ``d`` steps later, ``d`` drawn from the env's own generator (seeded per
episode, so an episode's delays do not depend on how many envs run beside it). Between refreshes the newest landed
correction is held; before the first one lands the student acts alone (a zero correction).

A bundle may also *smooth* its corrections over time (``touch_smoothing`` a in [0, 1), 0 by default): each landing
correction c then replaces the held one h by ``a * h + (1 - a) * c`` (:func:`smooth`), the first of an episode
(or of a deploy's run of usable touch) taken as it is. Friction and mass stay put over an episode while a single
1.12 s window reads them poorly; averaging the readings of many windows reads them better (the information ladder's
per-session rows: experiments/touch_ladder/v4_encoder). The time constant is ``touch_every / (1 - a)`` control steps.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass

import numpy as np

DELAY_SALT = 0x70C4
"""Mixed into each env's seed for its delay draws (a stream of its own, apart from the env's physics)."""
MAX_DELAY_STEPS = 100
"""Longest delay a spec may name (5 s at 20 Hz: beyond it a deploy drops the correction as stale)."""


@dataclass(frozen=True)
class TouchDelay:
    """A distribution of touch delays in control steps (see the module docstring)."""

    steps: tuple[int, ...]
    """Delays (control steps), increasing."""
    probs: tuple[float, ...]
    """Their probabilities (sum 1)."""
    spec: str
    """The text it was parsed from (what configs, cards and reports record)."""

    @property
    def mean(self) -> float:
        """Expected delay (control steps)."""
        return float(np.dot(self.steps, self.probs))

    @property
    def is_zero(self) -> bool:
        """True when every correction acts on the step whose touch it read."""
        return self.steps == (0,)

    def draw(self, rng: np.random.Generator) -> int:
        """One delay (control steps)."""
        if len(self.steps) == 1:
            return self.steps[0]
        return int(self.steps[int(rng.choice(len(self.steps), p=self.probs))])

    def describe(self, control_hz: float = 20.0) -> str:
        """One line for reports and cards, e.g. ``touch delay 'measured': 2 steps (60%), 3 steps (40%); mean 2.4
        steps = 120 ms at 20 Hz``."""
        parts = ", ".join(f"{s} step{'s' * (s != 1)}" + (f" ({100 * p:.0f}%)" if len(self.steps) > 1 else "")
                          for s, p in zip(self.steps, self.probs, strict=True))
        return (f"touch delay {self.spec!r}: {parts}; mean {self.mean:.2f} steps = {1e3 * self.mean / control_hz:.0f} "
                f"ms at {control_hz:g} Hz")


def _from_table(table: Sequence[tuple[int, float]], spec: str) -> TouchDelay:
    merged: dict[int, float] = {}
    for steps, p in table:
        merged[steps] = merged.get(steps, 0.0) + p
    total = sum(merged.values())
    keys = sorted(k for k, p in merged.items() if p > 0)
    return TouchDelay(tuple(keys), tuple(merged[k] / total for k in keys), spec)


MEASURED_TABLE: tuple[tuple[int, float], ...] = ((1, 0.170), (2, 0.830))
"""The measured default, in control steps at 20 Hz: (steps, fraction of corrections) from each correction's read to
its first action, for the adapter structure the recipe ships (a two-member ensemble on the 3 + 1-layer
sparshx-tinier-sim: every modality, and IMU + pressure + tracking; fresh members, the delay depends on the networks'
size, not their weights) in a 60 s `rotate deploy --hand sim-allegro` of the vendor-kinematics hand on 2 CPU cores,
the emulated hand and fingertips sharing them, 0 late steps, without the emulated fingertips' rendering of their
image and audio (a real sensor's window costs no rendering; the module docstring). Median 2 steps (100 ms): the
touch worker encodes in 52 ms (median; p95 59 ms). ``python scripts/bench_adapter.py --deploy 60 --adapter
ENSEMBLE`` (``delay_spec_no_render``, 300 corrections; with the rendering: median 120 ms, 2-3 steps). The first
hand model's ensemble (6 + 2 layers) was 3-9 steps, median 6, on a slower 2-core machine. Measure again whenever
the shipped adapter's encoder or members change (``--adapter`` with an ensemble of fresh ``build_adapted`` members
gives it before training)."""
MEASURED = _from_table(MEASURED_TABLE, "measured")


def parse_delay(text: str) -> TouchDelay:
    """``measured``, ``N`` or ``N:P,M:Q,...`` (module docstring) -> TouchDelay; ValueError naming the form."""
    form = "'measured', a whole number of control steps (e.g. 2) or steps:probability pairs (e.g. 2:0.6,3:0.4)"
    text = str(text).strip()
    if text == "measured":
        return MEASURED
    table: list[tuple[int, float]] = []
    try:
        for part in text.split(","):
            steps, sep, p = part.partition(":")
            table.append((int(steps), float(p) if sep else 1.0))
    except ValueError:
        raise ValueError(f"touch_delay: expected {form}, got {text!r}") from None
    if not table or (len(table) > 1 and any(":" not in part for part in text.split(","))):
        raise ValueError(f"touch_delay: expected {form}, got {text!r}")
    for steps, p in table:
        if not 0 <= steps <= MAX_DELAY_STEPS:
            raise ValueError(f"touch_delay: a delay of {steps} control steps is outside 0-{MAX_DELAY_STEPS}")
        if not (np.isfinite(p) and p >= 0):
            raise ValueError(f"touch_delay: probability {p} of {steps} steps must be a finite number >= 0")
    if sum(p for _, p in table) <= 0:
        raise ValueError(f"touch_delay: the probabilities of {text!r} add up to 0")
    return _from_table(table, text)


def check_smoothing(value: object) -> float:
    """``value`` as a touch smoothing factor (module docstring); ValueError unless a number in [0, 1)."""
    if isinstance(value, bool) or not isinstance(value, int | float) or not 0.0 <= float(value) < 1.0:
        raise ValueError(f"touch_smoothing must be a number in [0, 1) (0: each refresh replaces the correction), "
                         f"got {value!r}")
    return float(value)


def smooth(held: np.ndarray, fresh: np.ndarray, smoothing: float) -> np.ndarray:
    """The correction after ``fresh`` lands on ``held`` (module docstring): ``fresh`` itself when ``smoothing`` is 0."""
    if smoothing == 0.0:
        return np.asarray(fresh, np.float32)
    return (smoothing * np.asarray(held, np.float32) + (1.0 - smoothing) * np.asarray(fresh, np.float32)).astype(
        np.float32)


def delay_spec(delay: TouchDelay) -> str:
    """The ``N:P,...`` text of a distribution (fractions to 3 digits), e.g. for a measured one to be written down."""
    if len(delay.steps) == 1:
        return str(delay.steps[0])
    return ",".join(f"{s}:{p:.3f}" for s, p in zip(delay.steps, delay.probs, strict=True))


class DelayLine:
    """The touch corrections of ``n`` envs under ``delay`` (see the module docstring).

    Call :meth:`step` once per control step with the envs that act; it lands the corrections due, asks
    ``compute(ids)`` for the refreshes that start now (the (len(ids), Z) corrections from this step's touch) and
    returns the corrections to act with. :meth:`restart` starts envs over (a fresh episode: the student alone until
    its first correction lands). ``smoothing``: the bundle's ``touch_smoothing`` (:func:`smooth`)."""

    def __init__(self, n: int, latent_dim: int, touch_every: int, delay: TouchDelay, seeds: Sequence[int],
                 smoothing: float = 0.0) -> None:
        if len(seeds) != n:
            raise ValueError(f"DelayLine: {len(seeds)} seeds for {n} envs")
        self.delay, self.every, self.smoothing = delay, int(touch_every), check_smoothing(smoothing)
        self.correction = np.zeros((n, latent_dim), np.float32)
        """The correction each env acts with now (zero: the student alone)."""
        self._pending = np.zeros((n, latent_dim), np.float32)
        self._lands = np.full(n, -1, np.int64)  # step its pending correction lands; -1: none in flight
        self._due = np.zeros(n, np.int64)  # step its next refresh falls due
        self._rngs = [np.random.default_rng([int(s), DELAY_SALT]) for s in seeds]
        self.read_step = np.full(n, -1, np.int64)
        """Step whose touch the correction acting now read (-1: none yet): what the tests check."""
        self._pending_read = np.full(n, -1, np.int64)

    def restart(self, ids: np.ndarray, step: int, seeds: Sequence[int] | None = None) -> None:
        """Envs ``ids`` begin an episode at ``step``: no correction, nothing in flight, a refresh due at once;
        ``seeds``: their episodes' seeds (new delay streams)."""
        ids = np.asarray(ids, dtype=np.int64)
        self.correction[ids] = 0.0
        self._lands[ids] = -1
        self._due[ids] = step
        self.read_step[ids] = -1
        if seeds is not None:
            for i, s in zip(ids, seeds, strict=True):
                self._rngs[i] = np.random.default_rng([int(s), DELAY_SALT])

    def step(self, step: int, ids: np.ndarray, compute: Callable[[np.ndarray], np.ndarray]) -> np.ndarray:
        """The (len(ids), Z) corrections envs ``ids`` act with at control step ``step`` (see the class docstring)."""
        ids = np.asarray(ids, dtype=np.int64)
        land = ids[(self._lands[ids] >= 0) & (self._lands[ids] <= step)]
        self._land(land, self._pending[land])
        self.read_step[land] = self._pending_read[land]
        self._lands[land] = -1
        ask = ids[(self._lands[ids] < 0) & (self._due[ids] <= step)]
        if len(ask):
            fresh = np.asarray(compute(ask), dtype=np.float32)
            self._due[ask] = step + self.every
            for j, i in enumerate(ask):
                d = self.delay.draw(self._rngs[i])
                if d == 0:
                    self._land(np.asarray([i]), fresh[j : j + 1])
                    self.read_step[i] = step
                else:
                    self._pending[i] = fresh[j]
                    self._pending_read[i] = step
                    self._lands[i] = step + d
        return self.correction[ids]

    def _land(self, ids: np.ndarray, fresh: np.ndarray) -> None:
        """Corrections ``fresh`` land for envs ``ids``: held as they are where none landed yet this episode, else
        smoothed into the held ones."""
        first = self.read_step[ids] < 0
        self.correction[ids] = np.where(first[:, None], fresh, smooth(self.correction[ids], fresh, self.smoothing))
