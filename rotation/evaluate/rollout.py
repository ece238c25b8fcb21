"""Deterministic evaluation rollouts of a policy bundle on the batched env, with optional video frames.

Episode j of an evaluation seeded ``s`` runs in an env seeded ``s + j`` (the core's contract: env i of a batch
seeded ``s`` behaves like a single env seeded ``s + i``), so every policy meets the same grasps, physical
parameters, pushes and noise, whatever the number of parallel envs.
"""

from __future__ import annotations

from collections.abc import Callable
from functools import partial

import numpy as np

from adapters.touch_delay import DelayLine, TouchDelay, parse_delay
from envs.core import RotateCupVec
from envs.metrics import EpisodeMetrics, EpisodeTracker
from rotation.policy.bundle import PolicyBundle, combined_correction

FrameHook = Callable[[RotateCupVec], None]
"""Called after the reset and after every step of the first episode, e.g. to render simulation 0."""


def run_episodes(bundle: PolicyBundle, env: RotateCupVec, episodes: int, seed: int,
                 on_frame: FrameHook | None = None, on_episode: Callable[[], None] | None = None,
                 touch_delay: TouchDelay | None = None) -> list[EpisodeMetrics]:
    """Run ``episodes`` episodes (episode j seeded ``seed + j``) in chunks of ``env.num_envs``; one metrics entry
    per episode, in episode order. Each env runs one episode per chunk; finished envs are no longer acted for.

    A tactile adapter's correction is refreshed every ``touch_every`` control steps and held in between (smoothed
    over refreshes where the bundle's ``touch_smoothing`` says: adapters.touch_delay.smooth); each one
    acts from ``touch_delay`` steps after the step whose touch it read (drawn per refresh from episode j's own
    stream; None: 0, at once), and the next refresh starts when it is due and the previous one has landed, as in
    ``rotate deploy``, where a refresh runs beside the control loop (adapters.touch_delay). The student acts alone
    until the first correction lands."""
    if episodes < 1:
        raise ValueError(f"episodes must be >= 1, got {episodes}")
    delay = touch_delay if touch_delay is not None else parse_delay("0")
    n = env.num_envs
    touch_every = getattr(bundle, "touch_every", 0)  # a tactile adapter (adapters.bundle.AdaptedPolicy)
    if touch_every and any(getattr(env.cfg, k) != v for k, v in bundle.env_needs.items()):
        raise ValueError(f"this policy reads touch: evaluate it in an env with {bundle.env_needs} (the cpu backend)")
    tracker = EpisodeTracker(n, env.cfg.control_dt, env.cfg.episode_steps)
    results: list[EpisodeMetrics | None] = [None] * episodes
    for first in range(0, episodes, n):
        obs = env.reset(seed=seed + first)
        tracker.begin(obs)
        active = np.arange(n) < episodes - first  # the last chunk may use fewer envs
        record = on_frame is not None and first == 0
        if record:
            on_frame(env)
        actions = np.zeros((n, env.single_action_space.shape[0]), dtype=np.float32)
        line = (DelayLine(n, bundle.config.latent_dim, touch_every, delay, [seed + first + i for i in range(n)],
                          getattr(bundle, "touch_smoothing", 0.0))
                if touch_every else None)
        k = 0
        while active.any():
            idx = np.flatnonzero(active)
            actions[:] = 0.0
            groups = {key: obs[key][idx] for key in bundle.config.obs_groups}
            # refreshes due read this step's touch of their envs; a cautious start's shift goes under it
            touch = None if line is None else line.step(k, idx, partial(envs_correction, bundle, obs))
            correction = combined_correction(touch, bundle.start_correction(k))
            actions[idx] = (bundle.act_batch(groups) if correction is None
                            else bundle.act_batch(groups, correction=correction))
            k += 1
            obs, reward, terminated, truncated, info = env.step(actions)
            if record and active[0]:
                on_frame(env)
            done = (terminated | truncated) & active
            for i, ep in zip(np.flatnonzero(terminated | truncated), tracker.step(reward, terminated, truncated, info),
                             strict=True):
                if done[i]:
                    results[first + i] = ep
                    if on_episode is not None:
                        on_episode()
            active &= ~done
    assert all(r is not None for r in results)
    return results  # type: ignore[return-value]


def touch_correction(policy, obs, groups: dict[str, np.ndarray], idx: np.ndarray | None = None) -> np.ndarray:
    """The adapter's (N, Z) correction from the env observation's touch (the `tactile` group, rendered here for the
    envs ``idx`` only, or the `skin` group); zero (the student alone) when touch is unusable, as on the robot."""
    from adapters.bundle import TouchUnavailable

    try:
        return policy.correction(policy.env_windows(obs, idx), groups)
    except TouchUnavailable:
        return np.zeros((len(next(iter(groups.values()))), policy.config.latent_dim), dtype=np.float32)


def envs_correction(policy, obs, ids: np.ndarray) -> np.ndarray:
    """:func:`touch_correction` of the envs ``ids`` of an env observation."""
    return touch_correction(policy, obs, {key: obs[key][ids] for key in policy.config.obs_groups}, ids)
