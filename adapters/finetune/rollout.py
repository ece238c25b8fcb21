"""The student-with-adapter rollouts that the simulation path and the head refit both run: one env step with
restarts, the inputs of one touch refresh, and a logged point per interval.
"""

from __future__ import annotations

from typing import Any

import numpy as np
import torch

from adapters.bundle import TouchUnavailable
from envs.errors import JobFailed
from envs.metrics import EpisodeTracker, summarize


def step_and_restart(env: Any, tracker: EpisodeTracker, actions: np.ndarray, correction: np.ndarray
                     ) -> tuple[dict[str, Any], list, np.ndarray]:
    """Step every env; reset the ones whose episode ended and zero their held correction (a fresh episode starts as
    the student until its first touch refresh). Returns the observation, the ended episodes' records and the ids of
    the envs that restarted."""
    obs, reward, terminated, truncated, info = env.step(actions)
    ended = tracker.step(reward, terminated, truncated, info)
    done = np.flatnonzero(terminated | truncated)
    if len(done):
        obs = env.reset(ids=done)
        tracker.begin(obs, done)
        correction[done] = 0.0
    return obs, ended, done


def rollout_point(base: dict[str, float], sums: dict[str, float], refreshes: int, episodes: list) -> dict[str, float]:
    """A log point: ``base``, the per-refresh means of ``sums`` and the rollout summary of the ended ``episodes``."""
    point = {**base, **{key: v / refreshes for key, v in sums.items()}}
    if episodes:
        s = summarize(episodes)
        point.update(rotation_rate=s["rotation_rate"], ttf=s["ttf"], ep_length=s["length"])
    return point


@torch.no_grad()
def refresh_inputs(policy: Any, teacher: Any, obs: dict[str, Any], groups: dict[str, Any],
                   ids: np.ndarray | None = None
                   ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, dict, torch.Tensor]:
    """What a touch refresh of the simulated env gives the adapter's training: the teacher's z, phi's latent, the
    student actor's proprioceptive input, the frozen encoder's tokens and the joint tracking features (width 0 for
    an adapter that reads none) of every env, or of the envs ``ids`` (``groups`` then holds theirs only)."""
    priv = {key: obs[key] if ids is None else obs[key][ids] for key in teacher.config.obs_groups}
    z_teacher = teacher.net.extractor.z({key: torch.as_tensor(v) for key, v in priv.items()})
    try:
        tokens = policy.tokens(policy.env_windows(obs, ids))
    except TouchUnavailable as err:  # cannot happen in simulation unless the renderer breaks
        raise JobFailed(f"simulated touch unusable: {err}") from None
    return z_teacher, policy.student_latent(groups), policy.proprio_features(groups), tokens, policy.tracking(groups)
