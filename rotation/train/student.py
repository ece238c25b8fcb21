"""Distill a proprioceptive student from a frozen teacher (Hora stage 2, DAgger-style).

The student is the teacher's actor with its latent z estimated by the adaptation module phi from 30 steps of
proprioception. Only phi (and its history normalization) learns: Adam on MSE(phi(proprio_hist), z_teacher(priv)),
one gradient step per batched env step, while the student acts with phi's own estimate, so it learns on the states
its own mistakes lead to (docs/reference/hora.md "Stage 2"). Writes TensorBoard logs, periodic checkpoints with the
config beside them, and a student bundle (latent source `adaptation`).

    rotate train-student --teacher runs/teacher/bundle --out runs/student --num-envs 64 --total-steps 2000000
    rotate train-student --teacher runs/teacher/bundle --out runs/student --resume   # continue where it stopped

Exact resume: training is cut into checkpoint intervals and every interval starts from fresh resets of all envs
(seeded from the interval's first iteration), so a run resumed from a checkpoint is bit-identical to one that was
never interrupted. Keep checkpoint_every well above num_envs x episode_steps so few episodes are cut short.
Ctrl-C or SIGTERM stop after the current iteration and save a checkpoint there and the bundle (exit status 130 /
143); resuming from that checkpoint starts the rest of its interval from fresh resets (seeded from the iteration it
stopped at), so such a run is reproducible but not bit-identical to an uninterrupted one. A damaged latest checkpoint
falls back to the previous intact one; `curves.jsonl` holds the log points, flushed with each checkpoint.
"""

from __future__ import annotations

import dataclasses
import hashlib
import json
import math
import pickle
import signal
import time
import zipfile
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import torch
from tqdm import tqdm

from envs.errors import RequestRefused
from envs.metrics import EpisodeTracker, summarize
from rotation.configs import save_config, to_jsonable
from rotation.interrupt import SIGNAL_NAMES, Interrupted, StopSignals, end_loop
from rotation.policy.bundle import PolicyBundle, load_policy_bundle, resolve_bundle
from rotation.policy.bundle_checks import timing_problems
from rotation.policy.features import StudentExtractor
from rotation.runs import (
    CurveLog,
    DamagedCheckpoint,
    check_run_dir,
    clear_outputs,
    config_differences,
    refuse_differences,
    run_id,
    save_atomically,
    summary_writer,
    wall_time_fields,
    with_fallback,
)
from rotation.sim_warp.host import make_vec
from rotation.train.student_config import (  # Config and config_from_args: what `rotate train-student` reads here
    CHECKPOINT_GLOB,
    RESUMABLE_CHANGES,
    RUN_OUTPUTS,
    Config,
    config_from_args,  # noqa: F401
)


@dataclass
class Result:
    """What `run` returns: where the student went and the logged history."""

    bundle_dir: Path
    history: list[dict[str, float]]
    """One dict per log point: iteration, env_steps, latent_mse and the episode means of that interval."""


def _file_digest(path: Path) -> str:
    return hashlib.sha256(path.read_bytes()).hexdigest()[:16]


def _obs_tensors(obs: dict[str, np.ndarray], keys: set[str], device: str) -> dict[str, torch.Tensor]:
    return {k: torch.as_tensor(obs[k], device=device) for k in keys}


class HostRollout:
    """The student's env on the cpu backend: numpy physics, tensors for the networks, episodes tracked on the host."""

    def __init__(self, cfg: Config, keys: set[str]) -> None:
        self.env = make_vec("cpu", cfg.env, num_envs=cfg.num_envs, seed=cfg.seed, nthread=cfg.nthread or None)
        self.keys, self.device = keys, cfg.device
        self.tracker = EpisodeTracker(cfg.num_envs, cfg.env.control_dt, cfg.env.episode_steps)
        self.episodes: list = []

    def reset(self, seed: int) -> dict[str, torch.Tensor]:
        self.obs = self.env.reset(seed=seed)
        self.tracker.begin(self.obs)
        return _obs_tensors(self.obs, self.keys, self.device)

    def step(self, actions: torch.Tensor) -> dict[str, torch.Tensor]:
        """Step, track the episodes that end, reset their envs; the next observation."""
        obs, reward, terminated, truncated, info = self.env.step(actions.cpu().numpy())
        self.episodes += self.tracker.step(reward, terminated, truncated, info)
        done = np.flatnonzero(terminated | truncated)
        if len(done):
            obs = self.env.reset(ids=done)
            self.tracker.begin(obs, done)
        self.obs = obs
        return _obs_tensors(obs, self.keys, self.device)

    def collect(self) -> dict[str, float]:
        """Means of the episodes that ended since the last call ({} when none did)."""
        if not self.episodes:
            return {}
        s, self.episodes = summarize(self.episodes), []
        return {"ep_reward": s["reward"], "ep_length": s["length"], "rotation_rate": s["rotation_rate"],
                "ttf": s["ttf"]}

    def close(self) -> None:
        self.env.close()


class DeviceRollout:
    """The student's env on the warp backend: worlds, observations, actions, resets and episode sums all stay on
    the device (rotation.train.teacher_warp.DeviceEpisodeStats); the host reads only the log points."""

    def __init__(self, cfg: Config, keys: set[str]) -> None:
        from rotation.sim_warp.core import RotateCupWarp, WarpConfig
        from rotation.train.teacher_warp import DeviceEpisodeStats

        self.env = RotateCupWarp(cfg.env, num_envs=cfg.num_envs, seed=cfg.seed, warp_cfg=WarpConfig(device=cfg.device))
        self.keys = keys
        self.stats = DeviceEpisodeStats(cfg.num_envs, cfg.env, self.env.torch_device)

    def reset(self, seed: int) -> dict[str, torch.Tensor]:
        obs = self.env.reset(seed=seed)
        self.stats.ep = {}  # the episodes in progress were cut by the reset
        return {k: obs[k] for k in self.keys}

    def step(self, actions: torch.Tensor) -> dict[str, torch.Tensor]:
        _, reward, terminated, truncated, info = self.env.step(actions)
        self.stats.step(reward, terminated, truncated, info)
        self.env.reset_done(terminated | truncated)
        obs = self.env._observe()
        return {k: obs[k] for k in self.keys}

    def collect(self) -> dict[str, float]:
        s = self.stats.collect()
        if not s:
            return {}
        return {"ep_reward": s["r"], "ep_length": s["l"], "rotation_rate": s["rotation_rate"], "ttf": s["ttf"]}

    def close(self) -> None:
        self.env.close()


def _latest_checkpoint(out: Path) -> Path | None:
    ckpts = sorted(out.glob(CHECKPOINT_GLOB))
    return ckpts[-1] if ckpts else None


def _check_resumable(cfg: Config, out: Path) -> None:
    saved = out / "config.json"
    differences = config_differences(json.loads(saved.read_text()), to_jsonable(cfg), RESUMABLE_CHANGES)
    refuse_differences(differences, str(saved), RESUMABLE_CHANGES)


def _load_checkpoint(path: Path, device: str) -> dict[str, Any]:
    """A train-student checkpoint; DamagedCheckpoint when it cannot be read back, ValueError for another file."""
    try:
        ckpt = torch.load(path, map_location=device, weights_only=True)
    except (RuntimeError, EOFError, OSError, pickle.UnpicklingError, zipfile.BadZipFile) as err:
        raise DamagedCheckpoint(f"{path} cannot be read ({type(err).__name__}: "
                                f"{str(err).splitlines()[0] if str(err) else ''})") from None
    keys = {"student", "optim", "iteration", "teacher_digest"}
    if not isinstance(ckpt, dict) or not keys <= set(ckpt):
        raise ValueError(f"{path} is not a train-student checkpoint (expected the entries {sorted(keys)})")
    return ckpt


def run(cfg: Config) -> Result:
    """Distill the student; returns the bundle directory and the logged history. Everything is checked before
    anything in `out` is written; Ctrl-C / SIGTERM save a checkpoint and the bundle, then raise Interrupted."""
    out = Path(cfg.out)
    timing = timing_problems(cfg.env.control_hz, cfg.env.action_scale)
    if timing:  # the student bundle carries the env's timing: refuse now, not after the training
        raise ValueError(f"env: a student bundle cannot act at this env's timing: {'; '.join(timing)}")
    checkpoints = sorted(p.name for p in out.glob(CHECKPOINT_GLOB))
    check_run_dir(out, (*RUN_OUTPUTS, *checkpoints), overwrite=cfg.overwrite, resuming_here=cfg.resume,
                  resume_hint="pass --resume to continue it")
    torch.set_num_threads(cfg.torch_threads)
    teacher_dir = resolve_bundle(cfg.teacher)
    teacher = load_policy_bundle(teacher_dir).require("privileged", f"--teacher {cfg.teacher}")
    if cfg.adaptation.latent_dim != teacher.config.latent_dim:
        raise ValueError(f"adaptation.latent_dim {cfg.adaptation.latent_dim} != the teacher's latent size "
                         f"{teacher.config.latent_dim}")
    teacher_digest = _file_digest(teacher_dir / "model.safetensors")

    # the student: teacher's actor and proprio normalization, fresh phi; only phi and its normalization train
    torch.manual_seed(cfg.seed)
    student = teacher.to_student(cfg.adaptation)
    teacher.net.to(cfg.device).eval().requires_grad_(False)
    student.net.to(cfg.device).eval().requires_grad_(False)
    ext = student.net.extractor
    assert isinstance(ext, StudentExtractor)
    ext.adaptation.train().requires_grad_(True)
    ext.hist_norm.train()
    optim = torch.optim.Adam(ext.adaptation.parameters(), lr=cfg.lr)

    n = cfg.num_envs
    total_iters = math.ceil(cfg.total_steps / n)
    interval = max(1, round(cfg.checkpoint_every / n))
    start_iter, owner = 0, None
    wall_before: float | None = 0.0  # the earlier legs' training time (None: a checkpoint from before it was kept)
    if cfg.resume:
        ckpt_path = _latest_checkpoint(out)
        if ckpt_path is None or not (out / "config.json").is_file():
            raise RequestRefused(f"--resume: no checkpoint ({CHECKPOINT_GLOB}) and config.json in {out}")
        _check_resumable(cfg, out)
        older = sorted(out.glob(CHECKPOINT_GLOB), reverse=True)[1:]
        ckpt, ckpt_path = with_fallback(ckpt_path, older, lambda p: _load_checkpoint(p, cfg.device))
        owner = run_id(out, create=False)  # a run folder from before run ids: None, its checkpoints as before
        if owner is not None and ckpt.get("run_id") != owner:
            raise RequestRefused(f"--resume: {ckpt_path} is not a checkpoint this run wrote (another run's, or no "
                                 "record of which); move it away, or resume the run it belongs to")
        if ckpt["teacher_digest"] != teacher_digest:
            raise ValueError(f"--resume: {ckpt_path} was trained with another teacher (weights digest "
                             f"{ckpt['teacher_digest']}, this teacher {teacher_digest})")
        try:
            student.net.load_state_dict(ckpt["student"])
            optim.load_state_dict(ckpt["optim"])
        except (RuntimeError, ValueError, KeyError) as err:
            raise ValueError(f"--resume: {ckpt_path} does not fit this student ({type(err).__name__}: "
                             f"{str(err).splitlines()[0]})") from None
        start_iter = int(ckpt["iteration"])
        wall_before = ckpt.get("wall_time_s")
    keys = set(teacher.config.obs_groups) | set(student.config.obs_groups)
    rollout_cls = DeviceRollout if cfg.backend == "warp" else HostRollout
    env = rollout_cls(cfg, keys)  # checks the grasp cache
    # every check passed: only now is anything in `out` written or deleted
    if cfg.overwrite:
        removed = clear_outputs(out, (*RUN_OUTPUTS, *checkpoints))
        if removed:
            print(f"train-student: --overwrite deleted {', '.join(removed)} in {out}")
    save_config(cfg, out / "config.json")
    if not cfg.resume:
        owner = run_id(out, create=True)  # every checkpoint of this run carries it (rotation.runs)
    curves = CurveLog(out / "curves.jsonl", key="env_steps")
    curves.trim(start_iter * n)  # points a crashed or interrupted run logged after its last checkpoint

    writer = summary_writer(out / "tb", purge_step=start_iter * n)
    history: list[dict[str, float]] = []
    mse_sum, mse_count = 0.0, 0
    bar = tqdm(total=total_iters * n, initial=start_iter * n, unit="step", disable=not cfg.progress,
               desc="train-student", dynamic_ncols=True)
    t_log = t_start = time.perf_counter()

    def run_wall_s() -> float | None:  # the run's training time so far, over every leg
        return None if wall_before is None else wall_before + time.perf_counter() - t_start

    t_obs: dict[str, torch.Tensor] = {}
    done_iters, flushed, signum = start_iter, 0, None
    stop = StopSignals()
    try:
        stop.__enter__()
        for it in range(start_iter, total_iters):
            if it == start_iter or it % interval == 0:
                # each checkpoint interval starts from fresh resets (what makes resume exact)
                t_obs = env.reset(seed=cfg.seed + it * n)
            with torch.no_grad():
                z_teacher = teacher.net.extractor.z(t_obs)  # (N, Z)
            z_student = ext.z(t_obs)  # (N, Z), updates the history normalization (train mode)
            loss = torch.nn.functional.mse_loss(z_student, z_teacher)
            optim.zero_grad(set_to_none=True)
            loss.backward()
            optim.step()
            # act with phi's estimate (DAgger: the student visits its own states)
            with torch.no_grad():
                actions = student.net.mean(t_obs, z_student.detach()).clamp(-1.0, 1.0)  # (N, 16)
            t_obs = env.step(actions)

            mse_sum, mse_count = mse_sum + loss.item(), mse_count + 1
            bar.update(n)
            step = (it + 1) * n
            if (it + 1) % cfg.log_every == 0 or it + 1 == total_iters:
                point: dict[str, float] = {"iteration": it + 1, "env_steps": step, "latent_mse": mse_sum / mse_count}
                now = time.perf_counter()
                point["steps_per_s"] = mse_count * n / max(now - t_log, 1e-9)
                point.update(env.collect())
                _log(writer, point)
                history.append(point)
                bar.set_postfix(latent_mse=f"{point['latent_mse']:.4f}")
                mse_sum, mse_count, t_log = 0.0, 0, now
            done_iters = it + 1
            if (it + 1) % interval == 0 or it + 1 == total_iters or stop.requested:
                _save_checkpoint(out, student, optim, it + 1, teacher_digest, owner, run_wall_s())
                curves.append(history[flushed:])
                flushed = len(history)
            if stop.requested:
                break
    except KeyboardInterrupt as err:  # a second signal (stop at once), or Ctrl-C where no handler could be installed
        signum = getattr(err, "signum", signal.SIGINT)
        _save_checkpoint(out, student, optim, done_iters, teacher_digest, owner, run_wall_s())
        curves.append(history[flushed:])
    finally:
        end_loop(stop, bar, writer, env)
    signum = signum or stop.signum

    card = _card(cfg, teacher_digest, history)
    card.update(wall_time_fields(time.perf_counter() - t_start, run_wall_s(), cfg.resume))
    if signum:
        card["interrupted"] = (f"stopped by {SIGNAL_NAMES.get(signum, signum)} at {done_iters * n} of "
                               f"{total_iters * n} env steps")
    # the bundle carries the rate and action scale the student was trained at (cfg.env), not the teacher's:
    # evaluation, view, collect and deploy all act at the bundle's
    student.config = dataclasses.replace(student.config, card=card, control_hz=cfg.env.control_hz,
                                         action_scale=cfg.env.action_scale)
    bundle_dir = student.save(out / "bundle")
    final = f"; final latent MSE {history[-1]['latent_mse']:.5f}" if history else ""
    if signum:
        message = (f"train-student: interrupted by {SIGNAL_NAMES.get(signum, signum)} at {done_iters * n} of "
                   f"{total_iters * n} env steps{final}; saved the checkpoint and the bundle at {bundle_dir}; "
                   "continue with --resume")
        print(message)
        raise Interrupted(signum, message)
    print(f"train-student: {total_iters * n} env steps{final}; bundle at {bundle_dir}")
    return Result(bundle_dir, history)


def _card(cfg: Config, digest: str, history: list[dict[str, float]]) -> dict[str, Any]:
    last = history[-1] if history else {}
    return {
        "kind": "student",
        "trained_by": "rotate train-student",
        "teacher": cfg.teacher,
        "teacher_weights_sha256_16": digest,
        "env_steps": int(last.get("env_steps", 0)),
        "final_latent_mse": last.get("latent_mse"),
        "config": to_jsonable(cfg),
    }


def _save_checkpoint(out: Path, student: PolicyBundle, optim: torch.optim.Optimizer, iteration: int,
                     teacher_digest: str, owner: str | None = None, wall_time_s: float | None = None) -> Path:
    path = out / f"ckpt_{iteration:09d}.pt"
    state = {k: v.detach().cpu() for k, v in student.net.state_dict().items()}
    # atomic: a crash never leaves a half-written checkpoint as the latest
    save_atomically(lambda tmp: torch.save({"student": state, "optim": optim.state_dict(), "iteration": iteration,
                                            "teacher_digest": teacher_digest, "run_id": owner,
                                            "wall_time_s": wall_time_s}, tmp), path)
    return path


_TB_TAGS = {
    "latent_mse": "student/latent_mse",
    "ep_reward": "rollout/episode_reward",
    "rotation_rate": "rollout/rotation_rate",
    "ep_length": "rollout/episode_length",
    "ttf": "rollout/ttf",
    "steps_per_s": "time/steps_per_s",
}


def _log(writer, point: dict[str, float]) -> None:
    for key, tag in _TB_TAGS.items():
        if key in point:
            writer.add_scalar(tag, point[key], global_step=int(point["env_steps"]))
