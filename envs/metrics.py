"""Per-episode rollout metrics over a batched env (docs/reference/hora.md "Metrics"; Sparsh-X's vertical drift).

:class:`EpisodeTracker` accumulates, for each of N envs, the quantities the env reports in ``info`` every policy
step and emits one :class:`EpisodeMetrics` per finished episode. The same definitions serve training logs and the
evaluation report, so a rotation rate means one thing everywhere.
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass

import numpy as np

from envs import constants as C

METRICS: dict[str, str] = {
    "rotation_rate": "rad/s",
    "rotation_total": "rad",
    "ttf": "fraction",
    "upright": "fraction",
    "vertical_drift": "m",
    "lin_vel": "m/s",
    "torque": "N m",
}
"""Reported metric -> unit, in report order."""

_POS_Z = C.PRIV_FIELDS.index("pos_z")
UPRIGHT_TILT = math.radians(30.0)
"""The object counts as upright while its up axis is within this angle (rad) of the world vertical."""


@dataclass(frozen=True)
class EpisodeMetrics:
    """One finished episode."""

    reward: float
    """Sum of env rewards."""
    length: int
    """Policy steps."""
    fell: bool
    """The episode ended because the object fell."""
    rotation_total: float
    """Signed rotation about the commanded axis while in hand (rad): sum of info['rotation'] before any fall."""
    rotation_rate: float
    """rotation_total / time in hand (rad/s); 0 when the object fell on the first step."""
    in_hand_time: float
    """Seconds the object spent in the hand."""
    ttf: float
    """Time to fall / episode duration (episode_steps / control_hz); 1.0 = never fell."""
    upright: float
    """Fraction of the time in hand with the object's up axis within 30 degrees of vertical (info['tilt']); 0 when
    the object fell on the first step."""
    vertical_drift: float
    """Mean |object height - height at the episode start| over the episode's steps (m)."""
    lin_vel: float
    """Mean object linear speed (m/s)."""
    torque: float
    """Mean over steps of the mean |joint torque| (N m)."""

    def as_dict(self) -> dict:
        return asdict(self)


class EpisodeTracker:
    """Running per-env sums for N envs; call :meth:`begin` after each reset and :meth:`step` after each env step."""

    def __init__(self, num_envs: int, control_dt: float, episode_steps: int) -> None:
        self.n, self.dt, self.episode_steps = num_envs, control_dt, episode_steps
        self.start_z = np.zeros(num_envs)
        self.sums = {k: np.zeros(num_envs) for k in ("reward", "rotation", "in_hand", "upright", "drift", "lin_vel",
                                                  "torque")}
        self.length = np.zeros(num_envs, dtype=np.int64)

    def begin(self, obs: dict[str, np.ndarray], ids: np.ndarray | None = None) -> None:
        """Start episodes for envs ``ids`` (all by default) from the reset observation (object height from priv)."""
        ids = np.arange(self.n) if ids is None else np.asarray(ids)
        self.start_z[ids] = obs["priv"][ids, _POS_Z]
        for v in self.sums.values():
            v[ids] = 0.0
        self.length[ids] = 0

    def step(self, reward: np.ndarray, terminated: np.ndarray, truncated: np.ndarray, info: dict[str, np.ndarray]
             ) -> list[EpisodeMetrics]:
        """Accumulate one policy step of every env; returns the metrics of the episodes that ended on it."""
        in_hand = ~np.asarray(info["fell"], dtype=bool)
        s = self.sums
        s["reward"] += reward
        s["rotation"] += np.where(in_hand, info["rotation"], 0.0)
        s["in_hand"] += in_hand
        s["upright"] += in_hand & (np.asarray(info["tilt"]) < UPRIGHT_TILT)
        s["drift"] += np.abs(info["height"] - self.start_z)
        s["lin_vel"] += info["lin_vel"]
        s["torque"] += info["torque"]
        self.length += 1
        done = np.flatnonzero(np.asarray(terminated) | np.asarray(truncated))
        return [self._finish(i, bool(terminated[i])) for i in done]

    def _finish(self, i: int, fell: bool) -> EpisodeMetrics:
        s, n = self.sums, int(self.length[i])
        in_hand_time = s["in_hand"][i] * self.dt
        return EpisodeMetrics(
            reward=float(s["reward"][i]),
            length=n,
            fell=fell,
            rotation_total=float(s["rotation"][i]),
            in_hand_time=float(in_hand_time),
            rotation_rate=float(s["rotation"][i] / in_hand_time) if in_hand_time > 0 else 0.0,
            ttf=min(1.0, n / self.episode_steps) if fell else 1.0,
            upright=float(s["upright"][i] / s["in_hand"][i]) if s["in_hand"][i] > 0 else 0.0,
            vertical_drift=float(s["drift"][i] / n),
            lin_vel=float(s["lin_vel"][i] / n),
            torque=float(s["torque"][i] / n),
        )


def summarize(episodes: list[EpisodeMetrics]) -> dict[str, float]:
    """Mean of every reported metric over episodes, plus the mean reward, length and the number of episodes."""
    if not episodes:
        raise ValueError("no finished episodes to summarize")
    out = {k: float(np.mean([getattr(e, k) for e in episodes])) for k in METRICS}
    in_hand = sum(e.in_hand_time for e in episodes)
    # the pooled rate: total rotation over total time in hand (long episodes weigh more than a quick drop)
    out["net_rotation_rate"] = float(sum(e.rotation_total for e in episodes) / in_hand) if in_hand > 0 else 0.0
    out["reward"] = float(np.mean([e.reward for e in episodes]))
    out["length"] = float(np.mean([e.length for e in episodes]))
    out["episodes"] = len(episodes)
    return out
