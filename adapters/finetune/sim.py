"""The simulation path of `rotate finetune-adapter` (adapters.finetune.job; its module docstring describes it).

DAgger over the batched env with simulated touch (Digit 360 fingertips, or the Xela hand's skin): every
``touch_every`` control steps each env's windows are encoded into the TokenBuffer, ``updates`` Adam steps per
``num_envs`` such samples draw minibatches from it, and the correction acts ``touch_delay`` steps later, as on a
robot (adapters.touch_delay: each env's schedule starts over with its episode). Checkpoint intervals start from
fresh resets, an empty buffer and reseeded delays, so a resumed run is bit-identical.
"""

from __future__ import annotations

import dataclasses
import math
import signal
import time
from typing import Any

import numpy as np
import torch
from tqdm import tqdm

from adapters.finetune.core import Job, Result, TokenBuffer, adam_step, errors_to_teacher, log_point
from adapters.finetune.rollout import refresh_inputs, rollout_point, step_and_restart
from adapters.touch_delay import DelayLine
from envs.constants import PRIV_FIELDS
from envs.metrics import EpisodeTracker
from rotation.interrupt import StopSignals, end_loop

_MASS = PRIV_FIELDS.index("mass")


def train_in_sim(job: Job) -> Result:
    """Train ``job``'s adapter in simulation (the module docstring); returns the bundle and the history."""
    cfg, policy = job.cfg, job.policy
    adapter = policy.adapter
    n, k = cfg.num_envs, cfg.touch_every
    total_iters = math.ceil(cfg.total_steps / n)
    interval = max(k, round(cfg.checkpoint_every / n / k) * k)  # whole touch periods
    start_iter = job.start

    from rotation.sim_warp.host import make_vec

    env = make_vec("cpu", cfg.env, num_envs=n, seed=cfg.seed, nthread=cfg.nthread or None, device="cpu")
    curves, writer = job.open_outputs("env_steps", start_iter * n)

    interface = adapter.interface
    if job.tracking_norm_needed:
        adapter.set_tracking_norm(*tracking_norm(policy, cfg))
        job.tracking_norm_needed = False
    buffer = TokenBuffer(cfg.buffer_size, adapter.cfg.samples, interface.counts, interface.width,
                         adapter.cfg.latent_dim, policy.proprio_dim, adapter.tracking_dim)
    head = policy.student.net.head
    tracker = EpisodeTracker(n, cfg.env.control_dt, cfg.env.episode_steps)
    history: list[dict[str, float]] = []
    gen = torch.Generator().manual_seed(cfg.seed)
    bar = tqdm(total=total_iters * n, initial=start_iter * n, unit="step", disable=not cfg.progress,
               desc="finetune-adapter", dynamic_ncols=True)
    t_log = time.perf_counter()
    refresh = _Refresh(job, buffer, head, gen)
    line = DelayLine(n, adapter.cfg.latent_dim, k, cfg.delay, [cfg.seed] * n, policy.touch_smoothing)
    every_env = np.arange(n)
    done_iters, flushed, signum = start_iter, 0, None
    stop = StopSignals()
    try:
        stop.__enter__()
        for it in range(start_iter, total_iters):
            if it == start_iter or it % interval == 0:  # fresh resets, empty buffer, reseeded minibatches and delays
                refresh.obs = env.reset(seed=cfg.seed + it * n)
                tracker.begin(refresh.obs)
                buffer.clear()
                gen.manual_seed(cfg.seed + it)
                line = DelayLine(n, adapter.cfg.latent_dim, k, cfg.delay, [cfg.seed + it * n + i for i in range(n)],
                                 policy.touch_smoothing)
                line.restart(every_env, it)
            refresh.groups = {key: refresh.obs[key] for key in policy.config.obs_groups}
            correction = line.step(it, every_env, refresh)  # refreshes the envs due, from this step's touch
            refresh.train()
            adapted = it * n >= cfg.student_steps
            actions = policy.act_batch(refresh.groups, correction=correction if adapted else None)
            refresh.obs, ended, restarted = step_and_restart(env, tracker, actions, line.correction)
            line.restart(restarted, it + 1)
            refresh.episodes += ended
            bar.update(n)
            if (it + 1) % (cfg.log_every * k) == 0 or it + 1 == total_iters:
                if refresh.count:
                    now = time.perf_counter()
                    point = rollout_point({"iteration": it + 1, "env_steps": (it + 1) * n, "adapted": float(adapted),
                                           "steps_per_s": refresh.count * k / max(now - t_log, 1e-9)},
                                          refresh.sums, refresh.count / n, refresh.episodes)
                    log_point(writer, point, "env_steps")
                    history.append(point)
                    bar.set_postfix(latent_mse=f"{point['latent_mse']:.4f}",
                                    student_mse=f"{point['student_mse']:.4f}",
                                    action_mse=f"{point['action_mse']:.4f}")
                    refresh.sums, refresh.count, refresh.episodes, t_log = {}, 0, [], now
            done_iters = it + 1
            if (it + 1) % interval == 0 or it + 1 == total_iters or stop.requested:
                job.checkpoint(it + 1)
                curves.append(history[flushed:])
                flushed = len(history)
            if stop.requested:
                break
    except KeyboardInterrupt as err:
        signum = getattr(err, "signum", signal.SIGINT)
        job.checkpoint(done_iters)
        curves.append(history[flushed:])
    finally:
        end_loop(stop, bar, writer, env)
    signum = signum or stop.signum

    card: dict[str, Any] = {"env_steps": done_iters * n}
    if history:
        card["final_latent_mse"] = history[-1]["latent_mse"]
        card["final_student_mse"] = history[-1]["student_mse"]
        card["final_action_mse"] = history[-1]["action_mse"]
        card["final_student_action_mse"] = history[-1]["student_action_mse"]
    return job.finish(card, history, signum, f"{done_iters * n} env steps", f"{total_iters * n}")


class _Refresh:
    """The touch refreshes of the training rollouts: called by the delay line with the envs whose refresh starts
    (``obs`` and ``groups`` are this step's), it adds their samples to the buffer and returns their corrections;
    :meth:`train` then runs the Adam steps they are owed (``cfg.updates`` per ``num_envs`` samples)."""

    def __init__(self, job: Job, buffer: TokenBuffer, head: Any, gen: torch.Generator) -> None:
        self.job, self.buffer, self.head, self.gen = job, buffer, head, gen
        self.obs: dict[str, Any] = {}
        self.groups: dict[str, Any] = {}
        self.sums: dict[str, float] = {}
        """Per-sample error and loss sums since the last log point, in refreshes of every env (samples / n)."""
        self.count = 0
        """Samples since the last log point."""
        self.episodes: list = []
        """Episodes ended since the last log point."""
        self._owed = 0.0

    def __call__(self, ids: np.ndarray) -> np.ndarray:
        job, n = self.job, self.job.cfg.num_envs
        groups = {key: v[ids] for key, v in self.groups.items()}
        z_teacher, z_student, proprio, tokens, track = refresh_inputs(job.policy, job.teacher, self.obs, groups, ids)
        self.buffer.add(tokens, z_student, anchored_target(job, self.obs["priv"][ids], tokens, z_student, z_teacher,
                                                           track), proprio, track)
        adapter = job.policy.adapter
        with torch.no_grad():
            corr = adapter(tokens, z_student, track)
        # errors on the fresh samples, before the adapter trains on them
        for key, value in errors_to_teacher(self.head, proprio, z_student + corr, z_student, z_teacher).items():
            _add(self.sums, key, value * len(ids) / n)
        self.count += len(ids)
        self._owed += job.cfg.updates * len(ids) / n
        return corr.numpy()

    def train(self) -> None:
        """The Adam steps owed for the samples added so far (none while the buffer is empty)."""
        cfg, adapter = self.job.cfg, self.job.policy.adapter
        steps = int(self._owed)
        if steps < 1 or not self.buffer.size:
            return
        self._owed -= steps
        loss_sum = 0.0
        adapter.train()
        for _ in range(steps):
            idx = torch.randint(0, self.buffer.size, (min(cfg.batch_size, self.buffer.size),), generator=self.gen)
            loss_sum += adam_step(adapter, self.job.optim, self.buffer.batch(idx), self.head, cfg.action_weight)
        adapter.eval()
        _add(self.sums, "train_loss", loss_sum / cfg.updates)  # per-step mean loss x refreshes of every env


def anchored_target(job: Job, priv: np.ndarray, tokens: dict, z_student: torch.Tensor,
                    z_teacher: torch.Tensor, track: torch.Tensor | None = None) -> torch.Tensor:
    """The regression target of a refresh's samples: the teacher's z, or with ``job.anchor`` on cups lighter than
    ``cfg.anchor_mass`` (the privileged vector's mass) the student's latent plus the anchor's correction."""
    if job.anchor is None:
        return z_teacher
    with torch.no_grad():
        held = z_student + job.anchor(tokens, z_student, track)
    light = torch.as_tensor(np.asarray(priv)[:, _MASS] < job.cfg.anchor_mass)
    return torch.where(light[:, None], held, z_teacher)


@torch.no_grad()
def tracking_norm(policy: Any, cfg: Any, steps: int = 200, warmup: int = 30, every: int = 5
                  ) -> tuple[torch.Tensor, torch.Tensor]:
    """Mean and standard deviation of the joint tracking features (adapters.model.tracking_features) on the
    student's own rollouts, without touch, in the training env (``cfg.env``, ``cfg.num_envs`` envs, ``steps`` control
    steps, every ``every``-th after ``warmup``; an env whose episode ends restarts): what an adapter that reads them
    normalizes them by."""
    from rotation.sim_warp.host import make_vec

    env_cfg = dataclasses.replace(cfg.env, tactile=False, skin=False)
    env = make_vec("cpu", env_cfg, num_envs=cfg.num_envs, seed=cfg.seed, nthread=cfg.nthread or None, device="cpu")
    groups_of = tuple(policy.config.obs_groups)
    rows = []
    try:
        obs = env.reset(seed=cfg.seed)
        for t in tqdm(range(steps), desc="finetune-adapter: tracking statistics", unit="step",
                      disable=not cfg.progress, leave=False, dynamic_ncols=True):
            groups = {key: obs[key] for key in groups_of}
            if t >= warmup and t % every == 0:
                rows.append(policy.tracking(groups))
            obs, _, terminated, truncated, _ = env.step(policy.act_batch(groups))
            done = np.flatnonzero(terminated | truncated)
            if len(done):
                obs = env.reset(ids=done)
    finally:
        env.close()
    x = torch.cat(rows)
    return x.mean(0), x.std(0)


def _add(sums: dict[str, float], key: str, value: float) -> None:
    sums[key] = sums.get(key, 0.0) + value
