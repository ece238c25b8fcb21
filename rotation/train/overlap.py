"""Rollout prefetch for stable-baselines3's on-policy algorithms: the next rollout's physics runs while PPO updates.

On a CPU the learner's update and the simulation take turns in plain PPO: MuJoCo's batch waits while torch
updates, and torch (one thread) leaves the other core idle. :class:`RolloutPrefetch` starts collecting rollout
k + 1 on a background thread, with a frozen copy of the policy as it was before update k, while the main thread
updates on rollout k (``mujoco.batch`` and torch both release the GIL in their heavy work).

The price is one update of policy lag: rollout k + 1 was sampled by the policy before update k, and PPO trains
on it starting from the policy after it. PPO's ratio is taken against the stored log-probabilities of the policy
that acted, so the objective stays correct and the clip bounds the step from that policy. The lag's own KL is
measured before each update and reported as ``train/lag_kl``; the adaptive learning rate judges lag plus update
together (subtracting the lag let the rate climb until a run collapsed). Callbacks still see every
step, in order, on the main thread: the background rollout records what they need and replays it.
"""

from __future__ import annotations

import copy
from concurrent.futures import Future, ThreadPoolExecutor
from typing import Any

import numpy as np
import torch
from stable_baselines3.common.utils import obs_as_tensor


class RolloutPrefetch:
    """Mixin for an SB3 ``OnPolicyAlgorithm`` (put it before the algorithm class); set ``overlap = True`` to use.

    With ``overlap`` False the algorithm is unchanged. With it True, ``train()`` starts the next rollout in the
    background and ``collect_rollouts()`` hands over the finished one (collecting in the foreground only for the
    first rollout of a ``learn`` call).
    """

    overlap: bool = False
    lag_kl: float = 0.0
    _PREFETCH_STATE = ("_prefetch", "_prefetch_pool", "_spare_buffer", "_behavior")

    # ------------------------------------------------------------------ SB3 hooks
    def _excluded_save_params(self) -> list[str]:
        return [*super()._excluded_save_params(), *self._PREFETCH_STATE]  # type: ignore[misc]

    def learn(self, *args: Any, **kwargs: Any):
        try:
            return super().learn(*args, **kwargs)  # type: ignore[misc]
        finally:
            # a rollout still running when training stops (done, interrupted or failed) is finished and dropped,
            # so nothing steps the env behind the caller's back
            self.drop_prefetch()

    def collect_rollouts(self, env, callback, rollout_buffer, n_rollout_steps: int) -> bool:
        future: Future | None = getattr(self, "_prefetch", None)
        if not self.overlap or future is None:
            return super().collect_rollouts(env, callback, rollout_buffer, n_rollout_steps)  # type: ignore[misc]
        self._prefetch = None
        filled, steps = future.result()
        # the filled buffer becomes the one PPO trains on; the old one is the next prefetch's target
        self._spare_buffer, self.rollout_buffer = self.rollout_buffer, filled
        callback.on_rollout_start()
        for infos, dones in steps:
            self.num_timesteps += env.num_envs
            callback.update_locals({"infos": infos, "dones": dones})
            if not callback.on_step():
                return False
            self._update_info_buffer(infos, dones)  # type: ignore[attr-defined]
        callback.update_locals({"infos": steps[-1][0], "dones": steps[-1][1]})
        callback.on_rollout_end()
        return True

    def train(self) -> None:
        if self.overlap:
            self.lag_kl = self._lag_kl()
            self.logger.record("train/lag_kl", self.lag_kl)  # type: ignore[attr-defined]
            self._start_prefetch()
        super().train()  # type: ignore[misc]

    # ------------------------------------------------------------------ prefetch
    def drop_prefetch(self) -> None:
        """Wait for a background rollout, if any, and discard it."""
        future = getattr(self, "_prefetch", None)
        self._prefetch = None
        if future is not None:
            future.exception()  # waits; an error there is moot once training has stopped

    def _start_prefetch(self) -> None:
        if getattr(self, "_spare_buffer", None) is None:
            buf = self.rollout_buffer  # type: ignore[attr-defined]
            self._spare_buffer = type(buf)(self.n_steps, self.observation_space, self.action_space,  # type: ignore
                                           device=self.device, gamma=self.gamma, gae_lambda=self.gae_lambda,
                                           n_envs=self.n_envs, **self.rollout_buffer_kwargs)
            self._prefetch_pool = ThreadPoolExecutor(max_workers=1, thread_name_prefix="rollout")
        if getattr(self, "_behavior", None) is None:
            self._behavior = copy.deepcopy(self.policy)  # type: ignore[attr-defined]
        # the acting copy: the policy as it is now, before this update (statistics of the normalizers included)
        self._behavior.load_state_dict(self.policy.state_dict())  # type: ignore[attr-defined]
        self._behavior.set_training_mode(False)
        self._prefetch = self._prefetch_pool.submit(self._collect_background, self._spare_buffer, self._behavior)

    def _collect_background(self, buffer, policy) -> tuple[Any, list[tuple[list[dict], np.ndarray]]]:
        """SB3's collect_rollouts with ``policy`` acting and the callback steps recorded instead of called."""
        env, steps = self.env, []  # type: ignore[attr-defined]
        buffer.reset()
        low, high = self.action_space.low, self.action_space.high  # type: ignore[attr-defined]
        new_obs = dones = None
        for _ in range(self.n_steps):  # type: ignore[attr-defined]
            with torch.no_grad():
                actions, values, log_probs = policy(obs_as_tensor(self._last_obs, self.device))
            actions = actions.cpu().numpy()
            new_obs, rewards, dones, infos = env.step(np.clip(actions, low, high))
            steps.append((infos, dones))
            # a time-limit end bootstraps from the value of its last observation (SB3 issue 633), in one batch
            cut = [i for i, d in enumerate(dones) if d and infos[i].get("TimeLimit.truncated", False)
                   and infos[i].get("terminal_observation") is not None]
            if cut:
                term = {k: np.stack([infos[i]["terminal_observation"][k] for i in cut]) for k in new_obs}
                with torch.no_grad():
                    v = policy.predict_values(obs_as_tensor(term, self.device)).cpu().numpy().ravel()
                rewards[cut] += self.gamma * v  # type: ignore[attr-defined]
            buffer.add(self._last_obs, actions, rewards, self._last_episode_starts, values, log_probs)
            self._last_obs, self._last_episode_starts = new_obs, dones
        with torch.no_grad():
            last_values = policy.predict_values(obs_as_tensor(new_obs, self.device))
        buffer.compute_returns_and_advantage(last_values=last_values, dones=dones)
        return buffer, steps

    def _lag_kl(self, samples: int = 2048) -> float:
        """Approximate KL (SB3's estimator) from the policy that collected the rollout to the current one."""
        data = next(self.rollout_buffer.get(min(samples, self.rollout_buffer.buffer_size * self.n_envs)))
        self.policy.set_training_mode(False)  # type: ignore[attr-defined]  # no normalizer updates here
        with torch.no_grad():
            _, log_prob, _ = self.policy.evaluate_actions(data.observations, data.actions)  # type: ignore
            log_ratio = log_prob - data.old_log_prob
            return float(((torch.exp(log_ratio) - 1) - log_ratio).mean())
