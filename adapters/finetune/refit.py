"""`rotate finetune-adapter --refit-head`: solve the adapter's zero layer in closed form on its own rollouts.

The adapter's correction is ``ZeroLinear(h)``, with ``h = g(pooled tokens, phi)`` its last hidden features. Given
``h`` and the exact correction ``z_teacher - phi`` over many states, the best linear map from one to the other is a
ridge regression, which gradient steps on a ring buffer only approach. This mode keeps every weight of the ``--init-
from`` adapter but the zero layer's, rolls that adapter out (acting with its corrections, held between touch
refreshes and acting ``touch_delay`` steps after the touch they read, as at run time) in the training env for
``total_steps`` env steps, records ``h`` and the target at every refresh, and replaces the zero layer's weight and
bias with the ridge solution. The ridge strength is chosen from ``refit_lambdas`` by ``refit_folds``-fold cross-
validation with whole episodes held out (a cup's samples are alike, so held-out samples of a training episode would
flatter a weak penalty); the card records every candidate's held-out latent error.

    rotate finetune-adapter --init-from rotation/policies/adapter/members/all_modalities --refit-head \\
        --total-steps 76800 \\
        --env.randomization.friction 0.075 3.0 --env.randomization.friction-log \\
        --env.randomization.mass 0.01 0.45 --out runs/adapter_refit

The regression is linear in the zero layer, so the result does not depend on a learning rate, minibatch order or
number of updates; it depends on the states the rollouts visit (the env's randomization and seed).
"""

from __future__ import annotations

import math
import signal
from typing import Any

import numpy as np
import torch
from tqdm import tqdm

from adapters.finetune.core import Job, Result, errors_to_teacher, log_point
from adapters.finetune.rollout import refresh_inputs, rollout_point, step_and_restart
from adapters.touch_delay import DelayLine
from envs.metrics import EpisodeTracker
from rotation.interrupt import StopSignals, end_loop


def refit_in_sim(job: Job) -> Result:
    """Roll ``job``'s adapter out, refit its zero layer by ridge regression (the module docstring), save the bundle."""
    cfg, policy, teacher = job.cfg, job.policy, job.teacher
    adapter = policy.adapter.eval()
    n, k = cfg.num_envs, cfg.touch_every
    total_iters = math.ceil(cfg.total_steps / n)

    from rotation.sim_warp.host import make_vec

    env = make_vec("cpu", cfg.env, num_envs=n, seed=cfg.seed, nthread=cfg.nthread or None, device="cpu")
    curves, writer = job.open_outputs("env_steps", 0)
    head = policy.student.net.head
    tracker = EpisodeTracker(n, cfg.env.control_dt, cfg.env.episode_steps)
    refresh = _Samples(policy, teacher, head, n)
    next_id = n
    history: list[dict[str, float]] = []
    episodes: list = []
    line = DelayLine(n, adapter.cfg.latent_dim, k, cfg.delay, [cfg.seed + i for i in range(n)])
    every_env = np.arange(n)
    bar = tqdm(total=total_iters * n, unit="step", disable=not cfg.progress, desc="refit-head", dynamic_ncols=True)
    signum, done_iters = None, 0
    stop = StopSignals()
    try:
        stop.__enter__()
        obs = env.reset(seed=cfg.seed)
        tracker.begin(obs)
        for it in range(total_iters):
            groups = {key: obs[key] for key in policy.config.obs_groups}
            refresh.obs, refresh.groups = obs, groups
            correction = line.step(it, every_env, refresh)  # the envs due refresh from this step's touch
            obs, ended, done = step_and_restart(env, tracker, policy.act_batch(groups, correction=correction),
                                                line.correction)
            line.restart(done, it + 1)
            episodes += ended
            refresh.episode[done] = next_id + np.arange(len(done))
            next_id += len(done)
            bar.update(n)
            done_iters = it + 1
            if refresh.refreshes and ((it + 1) % (cfg.log_every * k) == 0 or done_iters == total_iters):
                point = rollout_point({"iteration": done_iters, "env_steps": done_iters * n}, refresh.sums,
                                      refresh.refreshes, episodes)
                log_point(writer, point, "env_steps")
                history.append(point)
                curves.append([point])  # on disk at once: the rollout is long and has no checkpoints
                refresh.sums, refresh.refreshes, episodes = {}, 0.0, []
            if stop.requested:
                break
    except KeyboardInterrupt as err:
        signum = getattr(err, "signum", signal.SIGINT)
    finally:
        end_loop(stop, bar, writer, env)
    signum = signum or stop.signum

    card: dict[str, Any] = {"env_steps": done_iters * n, "refit_head": None}
    if refresh.features:
        h_all, t_all = np.concatenate(refresh.features), np.concatenate(refresh.targets)
        ids = np.concatenate(refresh.episode_ids)
        n_episodes = len(np.unique(ids))
        before = float(((h_all @ adapter.zero.weight.detach().double().numpy().T
                         + adapter.zero.bias.detach().double().numpy() - t_all) ** 2).mean())
        try:
            weight, bias, table, lam = ridge_by_episode_cv(h_all, t_all, ids, cfg.refit_lambdas, cfg.refit_folds)
        except ValueError as err:
            if signum:  # too little was collected before the stop: keep the adapter as it was
                print(f"finetune-adapter: no refit ({err})")
                table, lam = [], None
            else:
                raise
        if lam is not None:
            with torch.no_grad():
                adapter.zero.weight.copy_(torch.as_tensor(weight.T, dtype=adapter.zero.weight.dtype))
                adapter.zero.bias.copy_(torch.as_tensor(bias, dtype=adapter.zero.bias.dtype))
            card["refit_head"] = {"samples": int(len(h_all)), "episodes": n_episodes,
                                  "lambda": lam, "cv": table, "latent_mse_before": before,
                                  "student_mse": float((t_all**2).mean()),
                                  "fit_latent_mse": float(((h_all @ weight + bias - t_all) ** 2).mean())}
            print(f"finetune-adapter: refit the zero layer on {len(h_all)} samples of {n_episodes} "
                  f"episodes (lambda {lam:g}): held-out latent MSE "
                  f"{min(r['cv_latent_mse'] for r in table):.4f}, the adapter before {before:.4f}, the student "
                  f"{card['refit_head']['student_mse']:.4f} on the same samples")
    kept = "refit on the samples collected" if card["refit_head"] else "not refit: too few samples"
    return job.finish(card, history, signum, f"{done_iters * n} env steps", f"{total_iters * n}",
                      after_stop=f"saved the bundle at {{}} ({kept}); a refit has no resume, run it again in full")


def ridge(h: np.ndarray, t: np.ndarray, lam: float) -> tuple[np.ndarray, np.ndarray]:
    """Ridge regression ``t ~ h @ W + b`` with penalty ``lam * len(h) * |W|^2`` (the bias is not penalized):
    returns W (H, Z) and b (Z,)."""
    mh, mt = h.mean(0), t.mean(0)
    a = h - mh
    weight = np.linalg.solve(a.T @ a + lam * len(a) * np.eye(a.shape[1]), a.T @ (t - mt))
    return weight, mt - mh @ weight


def ridge_by_episode_cv(h: np.ndarray, t: np.ndarray, episodes: np.ndarray, lambdas: tuple[float, ...],
                        folds: int) -> tuple[np.ndarray, np.ndarray, list[dict[str, float]], float]:
    """Choose the ridge strength among ``lambdas`` by ``folds``-fold cross-validation over whole episodes (samples
    with the same id in ``episodes`` stay together), then fit on everything. Returns W, b, the table of held-out
    latent MSE per strength, and the chosen strength."""
    ids = np.unique(episodes)
    if len(ids) < folds:
        raise ValueError(f"refit-head: {len(ids)} episodes collected, need at least --refit-folds {folds}: give "
                         "more --total-steps")
    order = np.random.default_rng(0).permutation(len(ids))
    fold_of_id = dict(zip(ids[order].tolist(), (np.arange(len(ids)) % folds).tolist(), strict=True))
    fold = np.array([fold_of_id[e] for e in episodes.tolist()])
    table = []
    for lam in lambdas:
        sq = 0.0
        for i in range(folds):
            weight, bias = ridge(h[fold != i], t[fold != i], lam)
            sq += float(((h[fold == i] @ weight + bias - t[fold == i]) ** 2).sum())
        table.append({"lambda": float(lam), "cv_latent_mse": sq / t.size})
    best = min(table, key=lambda r: r["cv_latent_mse"])["lambda"]
    weight, bias = ridge(h, t, best)
    return weight, bias, table, best


class _Samples:
    """The refreshes of the refit's rollouts: called by the delay line with the envs whose refresh starts (``obs``,
    ``groups`` and ``episode`` are this step's), it keeps their hidden features, targets and episode ids and returns
    their corrections."""

    def __init__(self, policy: Any, teacher: Any, head: Any, n: int) -> None:
        self.policy, self.teacher, self.head, self.n = policy, teacher, head, n
        self.obs: dict[str, Any] = {}
        self.groups: dict[str, Any] = {}
        self.episode = np.arange(n)
        """A distinct id per episode: env i's next episode gets the next free id."""
        self.features: list[np.ndarray] = []
        self.targets: list[np.ndarray] = []
        self.episode_ids: list[np.ndarray] = []
        self.sums: dict[str, float] = {}
        self.refreshes = 0.0
        """Refreshes of every env since the last log point (samples / n)."""

    @torch.no_grad()
    def __call__(self, ids: np.ndarray) -> np.ndarray:
        adapter = self.policy.adapter
        z_teacher, z_student, proprio, tokens, track = refresh_inputs(
            self.policy, self.teacher, self.obs, {key: v[ids] for key, v in self.groups.items()}, ids)
        h = adapter.hidden(adapter.pooled(tokens), z_student, track)
        corr = adapter.zero(h)
        self.features.append(h.double().numpy())
        self.targets.append((z_teacher - z_student).double().numpy())
        self.episode_ids.append(self.episode[ids].copy())
        for key, value in errors_to_teacher(self.head, proprio, z_student + corr, z_student, z_teacher).items():
            self.sums[key] = self.sums.get(key, 0.0) + value * len(ids) / self.n
        self.refreshes += len(ids) / self.n
        return corr.numpy()
