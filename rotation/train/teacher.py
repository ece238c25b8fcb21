"""Train the privileged teacher with PPO on the batched env (`rotate train-teacher`).

The teacher sees the normalized proprioception (3 x 32) and a latent z = EnvFactorEncoder(priv) of the privileged
object properties; actor and critic are 512-256-128 ELU MLPs (reference/hora.md). Changes from Hora's GPU recipe,
for a 2-core CPU: 256 envs instead of 16,384 with a horizon of 16 instead of 8 (4,096 transitions per update
instead of 131,072); minibatches of 2,048 instead of 32,768; 3 epochs per update instead of 5 (the updates, not the
physics, bound the step rate on a CPU); a starting learning rate of 1e-3 instead of 5e-3 (smaller batches give
noisier gradients) with the same adaptive-KL schedule (target 0.02); rewards scaled by 0.1 without a value
normalizer (SB3 has none; Hora scaled by 0.01 and normalized values); initial action std 0.6 instead of 1; and in
the env a lighter pose penalty and a fall penalty (envs.config.RewardConfig says why).

    rotate train-teacher --out runs/teacher --total-steps 30000000
    rotate train-teacher --backend warp --out runs/teacher_gpu   # MuJoCo Warp + rsl_rl PPO on a GPU (docs/warp.md)
    rotate train-teacher --resume runs/teacher/checkpoints/last.zip --total-steps 40000000   # the run's options
    tensorboard --logdir runs/teacher/tb

Writes checkpoints (`checkpoints/step_*.zip`, `checkpoints/last.zip`), `config.json`, TensorBoard logs, the training
curve `curves.jsonl` (flushed with each checkpoint) and the final policy bundle `bundle/` (weights + config, what
evaluation and deploy load). An `--out` holding another run is refused unless `--resume` continues it or
`--overwrite` replaces it; a resume takes the run's options the command line leaves out (and its folder as
`--out`), and refuses options that differ from the run's (but the length and speed ones) and a grasp cache
other than the file the run started from (config.json records its digest), and falls back from a damaged
checkpoint to the previous intact one. Ctrl-C / SIGTERM stop at the next step, save the
checkpoint, curves and bundle, and exit with status 130 / 143.
"""

from __future__ import annotations

import dataclasses
import json
import signal
import time
import warnings
import zipfile
import zlib
from dataclasses import dataclass
from pathlib import Path
from typing import Literal

import numpy as np
import torch
from stable_baselines3 import PPO
from stable_baselines3.common.callbacks import BaseCallback, CallbackList

from envs.config import EnvConfig, RandomizationConfig, RewardConfig
from envs.objects import OBJECTS
from envs.validation import check_int, check_number, check_output_dir, check_seed, check_types
from rotation.configs import check_device, save_config, to_jsonable
from rotation.interrupt import SIGNAL_NAMES, Interrupted, StopSignals
from rotation.policy.bundle import PolicyBundle, load_bundle
from rotation.policy.features import (
    LatentMixExtractor,
    PrivilegedExtractor,
    StudentExtractor,
    StudentPPOPolicy,
    policy_kwargs,
)
from rotation.policy.networks import EnvFactorEncoderConfig, RunningNorm
from rotation.train.overlap import RolloutPrefetch
from rotation.train.runs import (
    GRASPS_KEY,
    CurveLog,
    DamagedCheckpoint,
    check_resume_record,
    check_run_dir,
    clear_outputs,
    config_differences,
    refuse_differences,
    run_record,
    save_atomically,
    with_fallback,
)
from rotation.train.vec_env import RotateCupSB3VecEnv


@dataclass
class Config:
    out: Path = Path("runs/teacher")
    """Output directory (checkpoints, TensorBoard logs, config, final bundle)."""
    object: str = "cup"
    """Training object (envs.objects): the upright cup with a handle, scaled per env."""
    hand: Literal["digit360", "xela"] = "digit360"
    """Hand variant (envs.config.EnvConfig.hand): Digit 360 fingertips, or stock fingertips with the Xela skin pads
    (a teacher for a skin adapter; the skin itself is not simulated while the teacher trains)."""
    num_envs: int = 256
    """Simulations stepped together in one process."""
    total_steps: int = 30_000_000
    """Total environment steps (all envs together), counted across resumes."""
    seed: int = 0
    """Seed of the env streams and of torch."""
    n_steps: int = 16
    """Horizon per env per PPO update (transitions per update = num_envs x n_steps)."""
    batch_size: int = 2048
    """PPO minibatch size."""
    n_epochs: int = 3
    """Passes over each rollout (Hora: 5). On one CPU core the minibatch updates cost 2-3x the env stepping, so
    3 epochs buy more env steps per hour than 5 lose in sample efficiency."""
    learning_rate: float = 1e-3
    """Starting learning rate of the adaptive-KL schedule."""
    target_kl: float = 0.02
    """KL target of the adaptive schedule: lr / 1.5 above 2x, lr x 1.5 below 0.5x (Hora / rl_games)."""
    gamma: float = 0.99
    """Discount (Hora: 0.99)."""
    gae_lambda: float = 0.95
    """GAE lambda (Hora: 0.95)."""
    clip_range: float = 0.2
    """PPO ratio clip (Hora: 0.2)."""
    vf_coef: float = 1.0
    """Value loss weight."""
    ent_coef: float = 0.0
    """Entropy bonus (Hora: 0)."""
    max_grad_norm: float = 1.0
    """Gradient norm clip (Hora: 1.0)."""
    net_arch: tuple[int, ...] = (512, 256, 128)
    """Hidden layers of the actor and of the critic MLPs (ELU), Hora's sizes."""
    log_std_init: float = -0.5
    """Initial log standard deviation of the Gaussian actions (Hora: 0). std 0.6 instead of 1 explores with
    coherent finger motions instead of jitter that mostly earns penalties."""
    reward_scale: float = 0.1
    """Multiplies rewards seen by the learner (logged episode returns are unscaled)."""
    rotate_back_clip: float = 0.5
    """Backward clip of the rotate reward term (rad/s; envs.config.RewardConfig.rotate_back_clip). 0.5 (Hora's,
    the shipped teacher's) lets a policy earn the term by turning forward and snapping back; 5 makes a snap back
    cost what it undoes."""
    fall_reward: float = -20.0
    """One-off reward when the cup falls or tips past the tilt limit (envs.config.RewardConfig.fall); a penalty or
    0, never a gain. The per-step reward is small, so at -20 (the default) losing the cup late costs little; the
    shipped teacher's third stage used -60 and held slippery cups longer."""
    checkpoint_every: int = 1_000_000
    """Save a checkpoint every this many env steps."""
    resume: Path | None = None
    """Checkpoint to continue from (cpu backend: checkpoints/last.zip; warp: checkpoints/last.pt); the step count
    continues from it, and options not given are the run's (its config.json), --out its folder."""
    randomize: bool = True
    """Domain randomization on (Hora's ranges); off trains on nominal physics (an easy setting for tests)."""
    episode_steps: int = 400
    """Episode length in policy steps (20 s at 20 Hz)."""
    grasp_cache: str = ""
    """Grasp cache file; empty = the one shipped for the object."""
    torch_threads: int = 1
    """Threads for torch. 1 on a 2-core machine: torch's spinning workers starve MuJoCo's thread pool otherwise."""
    progress: bool = True
    """Show a progress bar."""
    device: str = "cpu"
    """Torch device for PPO ('cpu' is fastest for these small MLPs)."""
    init_from: Path | None = None
    """A teacher bundle (directory) to start the actor from: its normalization, env-factor encoder, actor MLP and
    action head are copied into the new policy; the critic and the action std start fresh. For continuing a run
    whose checkpoint is gone (a bundle is all that was kept); --resume continues exactly."""
    critic_warmup: int = 20
    """With --init-from: PPO updates that train only the fresh critic before the actor moves."""
    freeze_encoder: bool = False
    """Keep the env-factor encoder fixed (weights as initialized or copied by --init-from), so z keeps its meaning:
    a student's phi and a tactile adapter trained against the --init-from bundle's z stay valid for the continued
    teacher. The actor, the critic and the normalization still learn."""
    overlap: bool = True
    """Collect the next rollout on a background thread while PPO updates on the last one (one update of policy
    lag, see rotation.train.overlap): on 2 cores the update no longer leaves a core idle."""
    overwrite: bool = False
    """Delete the outputs of an earlier run in `out` (checkpoints, bundle, curves, config, logs) and start over;
    without it a folder holding a run is refused unless --resume continues that run."""
    backend: Literal["cpu", "warp"] = "cpu"
    """Physics backend: 'cpu' (MuJoCo on mujoco.batch threads, stable-baselines3 PPO) or 'warp' (MuJoCo Warp worlds
    and rsl_rl PPO resident on --device, the [warp] extra; on the command line it starts from the GPU recipe
    rotation.train.teacher_warp.GPU_RECIPE: 8192 worlds, horizon 8, 5 epochs, lr 5e-3, device cuda, which the
    options given win over). The simulated Digit 360 touch runs on the cpu backend only."""
    student: str = ""
    """A distilled student bundle (directory or shipped name) to fine-tune with PPO instead of training a teacher
    (what `rotate finetune-student` sets): its actor learns on its own latent estimate, phi stays frozen, the critic
    reads the privileged groups (rotation.policy.features.StudentPPOPolicy). Empty = train a teacher."""
    latent_mix: float = 0.0
    """Student fine-tune only: share of episodes in which the actor's latent is moved toward the teacher's z by a
    weight drawn uniformly in [0, 1] (rotation.policy.features.LatentMixExtractor); the other episodes use phi
    alone. An actor trained on phi alone learns to distrust z and gains little when a tactile adapter corrects it;
    0 = off."""
    latent_teacher: str = "teacher"
    """With --latent-mix: the teacher bundle whose env-factor encoder gives that z (the one phi was distilled from)."""

    def __post_init__(self) -> None:
        check_types(self)
        if self.freeze_encoder and (self.student or self.backend == "warp"):
            raise ValueError("freeze_encoder: for a cpu-backend teacher (a student fine-tune keeps its phi frozen "
                             "anyway)")
        if self.student:
            if self.init_from is not None or self.backend == "warp":
                raise ValueError("student: a student fine-tune starts from its bundle on the cpu backend; it takes "
                                 "neither --init-from nor --backend warp")
            self.student = str(self.student)
            try:
                student = load_bundle(self.student)
            except ValueError as err:  # a missing or broken bundle (BundleError)
                raise ValueError(f"student: {err}") from None
            student.require("adaptation", f"student: {self.student}")
        check_number("latent_mix", self.latent_mix, 0.0, 1.0)
        if self.latent_mix > 0:
            if not self.student:
                raise ValueError("latent_mix: for a student fine-tune (`rotate finetune-student`); a teacher already "
                                 "acts on its own z")
            try:
                teacher = load_bundle(self.latent_teacher)
            except ValueError as err:
                raise ValueError(f"latent_teacher: {err}") from None
            teacher.require("privileged", f"latent_teacher: {self.latent_teacher}")
            if teacher.config.latent_dim != student.config.latent_dim:
                raise ValueError(f"latent_teacher: its latent has {teacher.config.latent_dim} dims, the student's "
                                 f"{student.config.latent_dim}")
        self.out = Path(self.out)
        if self.resume is not None:
            self.resume = Path(self.resume)
        if self.resume is not None and self.backend == "warp" and self.resume.suffix == ".zip":
            raise ValueError(f"resume: {self.resume} is a cpu-backend checkpoint; the warp backend resumes from its "
                             "checkpoints/last.pt (--init-from BUNDLE starts a warp run from any teacher bundle)")
        if self.init_from is not None:
            self.init_from = Path(self.init_from)
            if not (self.init_from / "config.json").is_file():
                raise ValueError(f"init_from: {self.init_from} is not a policy bundle directory (no config.json)")
            if self.resume is not None:
                raise ValueError("init_from and resume exclude each other: --resume continues a run exactly")
        check_output_dir("out", self.out)
        if self.object not in OBJECTS:
            raise ValueError(f"object: unknown object {self.object!r}; known objects: {', '.join(sorted(OBJECTS))}")
        check_int("num_envs", self.num_envs, 1, 65_536)
        check_int("total_steps", self.total_steps, 1, 10**12)
        check_seed("seed", self.seed)
        check_int("n_steps", self.n_steps, 1, 100_000)
        if self.num_envs * self.n_steps < 2:
            raise ValueError("num_envs x n_steps must be >= 2 transitions per update (PPO normalizes advantages)")
        check_int("batch_size", self.batch_size, 2, self.num_envs * self.n_steps, "(2 .. num_envs x n_steps)")
        check_int("n_epochs", self.n_epochs, 1, 1000)
        # the adaptive-KL schedule keeps the rate within [1e-6, 1e-2]: a start outside would be clamped after one update
        check_number("learning_rate", self.learning_rate, 1e-6, 1e-2)
        check_number("target_kl", self.target_kl, 0.0, 10.0, low_open=True)
        check_number("gamma", self.gamma, 0.0, 1.0, low_open=True)
        check_number("gae_lambda", self.gae_lambda, 0.0, 1.0)
        check_number("clip_range", self.clip_range, 0.0, 1.0, low_open=True)
        check_number("vf_coef", self.vf_coef, 0.0, 1000.0, low_open=True)
        check_number("ent_coef", self.ent_coef, 0.0, 1.0)
        check_number("max_grad_norm", self.max_grad_norm, 0.0, 1000.0, low_open=True)
        if not 1 <= len(self.net_arch) <= 16 or not all(1 <= w <= 8192 for w in self.net_arch):
            raise ValueError(f"net_arch must be 1 to 16 layer widths, each in [1, 8192], got {self.net_arch!r}")
        check_number("log_std_init", self.log_std_init, -10.0, 2.0)  # std e^-10 .. e^2 for actions in [-1, 1]
        check_number("reward_scale", self.reward_scale, 0.0, 1000.0, low_open=True)
        check_number("fall_reward", self.fall_reward, -10000.0, 0.0)  # a penalty or off: falling must never pay
        check_int("checkpoint_every", self.checkpoint_every, 1, 10**12)
        check_int("torch_threads", self.torch_threads, 1, 1024)
        check_int("critic_warmup", self.critic_warmup, 0, 10**6)
        if self.grasp_cache and not Path(self.grasp_cache).is_file():
            raise ValueError(f"grasp_cache: no such file: {self.grasp_cache!r} (generate one with `rotate grasps`)")
        check_device("device", self.device)
        if self.resume is not None and self.overwrite and self.resume.resolve().is_relative_to(self.out.resolve()):
            raise ValueError(f"--overwrite would delete the checkpoint --resume {self.resume} continues from; "
                             "resume into another --out, or drop --overwrite")
        self.env_config()  # episode_steps and the rest of the env, checked by EnvConfig

    def env_config(self) -> EnvConfig:
        rc = RandomizationConfig() if self.randomize else RandomizationConfig(enabled=False)
        return EnvConfig(object=self.object, hand=self.hand, episode_steps=self.episode_steps, randomization=rc,
                         grasp_cache=self.grasp_cache, reward=RewardConfig(rotate_back_clip=self.rotate_back_clip,
                                                               fall=self.fall_reward))


def config_from_args(args) -> Config:
    """The Config of a command line; with --backend warp the GPU recipe replaces the defaults of the options the
    command line does not give (rotation.train.teacher_warp.GPU_RECIPE)."""
    return _config_from_args(Config, args)


def _config_from_args(cls: type[Config], args) -> Config:
    """train-teacher's and finetune-student's config: a --resume takes the run's options the command line leaves
    out, and the warp backend's GPU recipe fills the rest."""
    from rotation.configs import dataclass_from_args, inherit_run_options

    if getattr(args, "resume", None) is not None:
        run_dir = _run_dir_of(Path(args.resume))
        # --out defaults to the run resumed (where it is now); --init-from only starts runs
        if "out" not in vars(args) and run_dir is not None:
            args.out = run_dir
        inherit_run_options(cls, args, run_dir, not_inherited=("out", "init_from", "overwrite", "resume"))
    cfg = dataclass_from_args(cls, args)
    if cfg.backend == "warp":
        from rotation.train.teacher_warp import apply_gpu_recipe

        cfg = apply_gpu_recipe(cfg, given=set(vars(args)))
    return cfg


TEACHER_GROUPS = ("proprio", "priv")
"""Observation groups the teacher reads (rotation.policy.features.PrivilegedExtractor)."""
STUDENT_RL_GROUPS = ("proprio", "proprio_hist", "priv")
"""Observation groups of a student fine-tune: the actor reads proprio and its history, the critic proprio and priv."""


def obs_groups(cfg: Config) -> tuple[str, ...]:
    """The observation groups a run's rollouts keep."""
    return STUDENT_RL_GROUPS if cfg.student else TEACHER_GROUPS


class KLSchedule:
    """A learning-rate 'schedule' holding the current rate, which the adaptive-KL rule moves (saved with the model)."""

    def __init__(self, lr: float, target: float) -> None:
        self.lr, self.target = lr, target

    def __call__(self, _progress_remaining: float) -> float:
        return self.lr

    def update(self, kl: float) -> None:
        """rl_games' rule: divide by 1.5 above 2x the target, multiply by 1.5 below half of it, within [1e-6, 1e-2]."""
        if kl > 2.0 * self.target:
            self.lr = max(self.lr / 1.5, 1e-6)
        elif kl < 0.5 * self.target:
            self.lr = min(self.lr * 1.5, 1e-2)


class AdaptiveKLPPO(RolloutPrefetch, PPO):
    """PPO whose learning rate follows the adaptive-KL rule after every update (rl_games / Hora), optionally with
    the next rollout collected during the update (``overlap``; rotation.train.overlap)."""

    def _setup_model(self) -> None:
        # a loaded model already holds its schedule (the current rate and the target), which SB3's setup would
        # replace with a constant one at the starting rate: keep it, so a resume continues the schedule exactly
        loaded = getattr(self, "lr_schedule", None)
        super()._setup_model()
        fresh = not isinstance(loaded, KLSchedule)
        self.lr_schedule = KLSchedule(float(self.learning_rate), Config.target_kl) if fresh else loaded

    critic_warmup: int = 0
    """Updates left that train only the critic (after --init-from: a fresh critic's first value estimates would
    otherwise steer the copied actor with noise)."""

    def train(self) -> None:
        if self.critic_warmup > 0:
            self._train_critic_only()
            return
        super().train()
        kl = self.logger.name_to_value.get("train/approx_kl")
        if kl is not None and np.isfinite(kl):
            # with overlap the KL is taken from the policy that acted, one update back (lag + this update): the
            # schedule judges both together, which keeps each update inside the trust region the target sets
            self.lr_schedule.update(float(kl))
        self.logger.record("train/adaptive_lr", self.lr_schedule.lr)

    def _train_critic_only(self) -> None:
        critic = ("mlp_extractor.value_net.", "value_net.", "vf_features_extractor.")
        frozen = [p for n, p in self.policy.named_parameters() if not n.startswith(critic) and p.requires_grad]
        norms = [m for m in self.policy.modules() if isinstance(m, RunningNorm) and not m.frozen]
        for p in frozen:
            p.requires_grad_(False)
        try:
            for m in norms:  # the actor's input statistics stay as they were too
                m.frozen = True
            super().train()  # the schedule is left alone: the actor did not move
        finally:
            for p in frozen:
                p.requires_grad_(True)
            for m in norms:
                m.frozen = False
        self.critic_warmup -= 1
        self.logger.record("train/critic_warmup_left", self.critic_warmup)


class EpisodeStats(BaseCallback):
    """Logs per-episode statistics (return, length, rotation rate, time to fall, each reward term) to TensorBoard."""

    def __init__(self) -> None:
        super().__init__()
        self.episodes: list[dict] = []
        self.history: list[dict] = []

    def _on_step(self) -> bool:
        for info in self.locals["infos"]:
            ep = info.get("episode")
            if ep is not None:
                self.episodes.append(ep)
        return True

    def _on_rollout_end(self) -> None:
        if not self.episodes:
            return
        keys = self.episodes[0].keys()
        means = {k: float(np.mean([e[k] for e in self.episodes])) for k in keys}
        for k, v in means.items():
            self.logger.record(f"episode/{ {'r': 'return', 'l': 'length'}.get(k, k) }", v)
        self.history.append({"steps": int(self.num_timesteps), "episodes": len(self.episodes), **means})
        self.episodes = []


class Checkpoints(BaseCallback):
    """Saves `step_<n>.zip` every `every` steps and `last.zip` (keeps the newest two numbered ones), each written
    atomically, and appends the curve rows logged since the last one to `curves` (flushed to disk). Stops training
    (returns False) once ``stop`` saw a signal."""

    def __init__(self, folder: Path, every: int, stats: EpisodeStats | None = None, curves: CurveLog | None = None,
                 stop: StopSignals | None = None) -> None:
        super().__init__()
        self.folder, self.every = folder, every
        self.stats, self.curves, self.stop = stats, curves, stop
        self.flushed = 0  # rows of stats.history already in curves
        self.next_at = 0

    def _on_training_start(self) -> None:
        self.folder.mkdir(parents=True, exist_ok=True)
        self.next_at = (self.num_timesteps // self.every + 1) * self.every

    def _on_step(self) -> bool:
        if self.num_timesteps >= self.next_at:
            self.save()
            self.next_at += self.every
        return not (self.stop is not None and self.stop.requested)

    def save(self) -> Path:
        self.folder.mkdir(parents=True, exist_ok=True)
        path = self.folder / f"step_{self.num_timesteps:010d}.zip"
        save_atomically(self.model.save, path)
        save_atomically(self.model.save, self.folder / "last.zip")
        for old in sorted(self.folder.glob("step_*.zip"))[:-2]:
            old.unlink()
        if self.stats is not None and self.curves is not None:
            self.curves.append(self.stats.history[self.flushed :])
            self.flushed = len(self.stats.history)
        return path


def load_checkpoint(path: str | Path, env: RotateCupSB3VecEnv | None = None, device: str = "cpu") -> AdaptiveKLPPO:
    """A train-teacher checkpoint (.zip). Raises DamagedCheckpoint for a file that cannot be read back (truncated,
    corrupted) and ValueError for one of another program, policy or observation space."""
    path = Path(path)
    if not path.is_file():
        raise ValueError(f"no such checkpoint: {path}" + (" (a directory; give a .zip file)" if path.is_dir() else ""))
    try:
        with zipfile.ZipFile(path) as archive:
            names = archive.namelist()
            broken = archive.testzip()  # reads every member and checks its CRC
    except (zipfile.BadZipFile, OSError, EOFError, zlib.error) as err:
        raise DamagedCheckpoint(f"{path} is not a readable zip file ({type(err).__name__}: {err})") from None
    if broken is not None:
        raise DamagedCheckpoint(f"{path}: member {broken!r} is corrupted")
    if not {"data", "policy.pth"} <= set(names):
        raise ValueError(f"{path} is not a train-teacher checkpoint: a zip of {sorted(names)[:6]}, not a "
                         "stable-baselines3 model ('data', 'policy.pth')")
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")  # SB3 warns about version differences; a mismatch fails below
            model = AdaptiveKLPPO.load(path, env=env, device=device)
    except Exception as err:  # SB3 raises many kinds (ValueError for other spaces, KeyError, pickle errors)
        raise ValueError(f"{path} cannot be loaded as a train-teacher checkpoint ({type(err).__name__}: "
                         f"{str(err).splitlines()[0] if str(err) else ''})") from None
    extractor = getattr(model.policy, "features_extractor", None)
    if not (isinstance(extractor, PrivilegedExtractor)
            or (isinstance(model.policy, StudentPPOPolicy) and isinstance(extractor, StudentExtractor))):
        raise ValueError(f"{path} holds a {type(model.policy).__name__} with a {type(extractor).__name__} features "
                         "extractor, not the teacher's privileged policy (PrivilegedExtractor) or a student "
                         "fine-tune (StudentPPOPolicy)")
    return model


def _older_checkpoints(path: Path) -> list[Path]:
    """The numbered checkpoints beside ``path`` that precede it, newest first (all of them for last.zip)."""
    steps = sorted(path.parent.glob("step_*.zip"), reverse=True)
    if path.name.startswith("step_"):
        steps = [p for p in steps if p.name < path.name]
    return [p for p in steps if p != path]


PPO_OPTIONS = ("n_steps", "batch_size", "n_epochs", "learning_rate", "target_kl", "gamma", "gae_lambda",
               "clip_range", "vf_coef", "ent_coef", "max_grad_norm", "net_arch", "log_std_init")
"""Options a checkpoint records itself (compared on resume even without the run's config.json)."""
RESUMABLE_CHANGES = {"out", "total_steps", "progress", "checkpoint_every", "resume", "torch_threads", "device",
                     "overwrite", "overlap", "init_from", "critic_warmup"}
"""Options that may change on resume: the run's length, where it writes, and how fast it runs."""


def _checkpoint_options(model: AdaptiveKLPPO) -> dict:
    """The PPO options a checkpoint was trained with, in Config's names and JSON form."""
    arch = model.policy_kwargs.get("net_arch", {})
    arch = arch.get("pi") if isinstance(arch, dict) else arch
    schedule = model.lr_schedule
    return to_jsonable({
        "num_envs": model.n_envs, "n_steps": model.n_steps, "batch_size": model.batch_size,
        "n_epochs": model.n_epochs, "learning_rate": float(model.learning_rate),
        "target_kl": schedule.target if isinstance(schedule, KLSchedule) else None, "gamma": model.gamma,
        "gae_lambda": model.gae_lambda, "clip_range": float(model.clip_range(1.0)), "vf_coef": model.vf_coef,
        "ent_coef": model.ent_coef, "max_grad_norm": model.max_grad_norm, "net_arch": list(arch or []),
        "log_std_init": model.policy_kwargs.get("log_std_init"),
    })


def bundle_from_checkpoint(path: str | Path, card: dict | None = None) -> PolicyBundle:
    """The policy bundle of a training checkpoint (.zip), e.g. to evaluate or ship a run that is still going."""
    path = Path(path)
    if not path.is_file():
        raise ValueError(f"no such checkpoint: {path}")
    model = load_checkpoint(path)
    run_cfg = path.parent.parent / "config.json"
    train_config = json.loads(run_cfg.read_text()) if run_cfg.is_file() else {}
    role = "student" if isinstance(model.policy, StudentPPOPolicy) else "teacher"
    info = {"role": role, "object": train_config.get("object", "cup"), "steps": int(model.num_timesteps),
            "seed": train_config.get("seed"), "checkpoint": path.name, "train_config": train_config}
    if train_config.get("student"):  # a student fine-tune: what it started from, as the run's own bundle records it
        info["finetuned_from"] = {"bundle": train_config["student"],
                                  "card": load_bundle(train_config["student"]).config.card}
    return PolicyBundle.from_sb3(model, card=info | (card or {}))


def build_model(cfg: Config, env: RotateCupSB3VecEnv) -> AdaptiveKLPPO:
    if cfg.resume is not None:
        if not Path(cfg.resume).is_file():
            raise ValueError(f"--resume {cfg.resume}: no such checkpoint")
        return AdaptiveKLPPO.load(cfg.resume, env=env, device=cfg.device)
    if cfg.student:
        return build_student_model(cfg, env)
    model = _new_ppo(cfg, env, "MultiInputPolicy", policy_kwargs())
    model.overlap = cfg.overlap
    if cfg.init_from is not None:
        init_actor(model, cfg.init_from)
        model.critic_warmup = cfg.critic_warmup
    return model


def _new_ppo(cfg: Config, env: RotateCupSB3VecEnv, policy: str | type, kwargs: dict) -> AdaptiveKLPPO:
    """A fresh AdaptiveKLPPO with the run's PPO options; ``kwargs`` are the policy's, completed with the run's
    log std and actor/critic sizes."""
    kwargs = dict(kwargs, log_std_init=cfg.log_std_init, net_arch=dict(pi=list(cfg.net_arch), vf=list(cfg.net_arch)))
    model = AdaptiveKLPPO(
        policy, env, learning_rate=cfg.learning_rate, n_steps=cfg.n_steps, batch_size=cfg.batch_size,
        n_epochs=cfg.n_epochs, gamma=cfg.gamma, gae_lambda=cfg.gae_lambda, clip_range=cfg.clip_range,
        ent_coef=cfg.ent_coef, vf_coef=cfg.vf_coef, max_grad_norm=cfg.max_grad_norm, policy_kwargs=kwargs,
        tensorboard_log=str(cfg.out / "tb"), seed=cfg.seed, device=cfg.device, verbose=0,
    )
    model.lr_schedule = KLSchedule(cfg.learning_rate, cfg.target_kl)
    return model


def build_student_model(cfg: Config, env: RotateCupSB3VecEnv) -> AdaptiveKLPPO:
    """PPO over a student bundle's acting path (StudentPPOPolicy): phi frozen, a fresh privileged critic that trains
    alone for ``critic_warmup`` updates first."""
    student = load_bundle(cfg.student)
    scfg = student.config
    if list(scfg.actor_hidden) != list(cfg.net_arch):
        raise ValueError(f"net_arch {list(cfg.net_arch)} differs from the student's actor {list(scfg.actor_hidden)}; "
                         "give --net-arch " + " ".join(map(str, scfg.actor_hidden)))
    extractor_kwargs = dict(adaptation=scfg.adaptation, norm_clip=scfg.norm_clip)
    teacher = load_bundle(cfg.latent_teacher) if cfg.latent_mix > 0 else None
    if teacher is not None:
        extractor_kwargs["teacher_encoder"] = teacher.net.extractor.encoder.cfg
    kwargs = dict(policy_kwargs(norm_clip=scfg.norm_clip),
                  features_extractor_class=LatentMixExtractor if teacher is not None else StudentExtractor,
                  features_extractor_kwargs=extractor_kwargs,
                  critic_encoder=EnvFactorEncoderConfig(latent_dim=scfg.latent_dim))
    model = _new_ppo(cfg, env, StudentPPOPolicy, kwargs)
    policy = model.policy
    state = student.net.extractor.state_dict()
    if teacher is not None:
        state |= {f"teacher_encoder.{k}": v for k, v in teacher.net.extractor.encoder.state_dict().items()}
    policy.pi_features_extractor.load_state_dict(state)
    policy.mlp_extractor.policy_net.load_state_dict(student.net.actor.state_dict())
    policy.action_net.load_state_dict(student.net.action_mean.state_dict())
    # the critic's proprio statistics start from the student's (they stay fixed while the critic warms up)
    policy.vf_features_extractor.proprio_norm.load_state_dict(student.net.extractor.proprio_norm.state_dict())
    model.critic_warmup = cfg.critic_warmup
    return model


def init_actor(model: AdaptiveKLPPO, path: Path) -> None:
    """Copy a teacher bundle's acting path (normalization, encoder, actor MLP, action head) into ``model``."""
    bundle = load_bundle(path).require("privileged", f"--init-from {path}")
    policy = model.policy
    try:
        policy.features_extractor.load_state_dict(bundle.net.extractor.state_dict())
        policy.mlp_extractor.policy_net.load_state_dict(bundle.net.actor.state_dict())
        policy.action_net.load_state_dict(bundle.net.action_mean.state_dict())
    except RuntimeError as err:  # other layer sizes
        raise ValueError(f"--init-from {path}: the bundle's networks do not fit this run's (--net-arch "
                         f"{list(policy.mlp_extractor.policy_net)}): {str(err).splitlines()[0]}") from None


RUN_OUTPUTS = ("config.json", "checkpoints", "bundle", "curves.jsonl", "tb")
"""What a run writes into `out` (what --overwrite deletes)."""


def _role(cfg: Config) -> str:
    return "student" if cfg.student else "teacher"


def _run_dir_of(checkpoint: Path) -> Path | None:
    """The run folder of a checkpoint at <run>/checkpoints/<name>.zip."""
    return checkpoint.parent.parent if checkpoint.parent.name == "checkpoints" else None


def run(cfg: Config) -> PolicyBundle:
    """Train (or continue) the teacher. Everything is checked before anything is written: a folder holding another
    run, a resume whose options differ from the run's, a checkpoint of another program. Ctrl-C / SIGTERM stop at the
    next step, save the checkpoint, curves and bundle, then raise Interrupted (exit status 130 / 143)."""
    if cfg.backend == "warp":  # MuJoCo Warp worlds and a GPU-resident PPO (rotation.train.teacher_warp)
        from rotation.train.teacher_warp import train as train_warp

        return train_warp(cfg)
    out = cfg.out
    resume_dir = _run_dir_of(cfg.resume) if cfg.resume is not None else None
    resuming_here = resume_dir is not None and resume_dir.resolve() == out.resolve()
    check_run_dir(out, RUN_OUTPUTS, overwrite=cfg.overwrite, resuming_here=resuming_here,
                  resume_hint=f"pass --resume {out / 'checkpoints' / 'last.zip'} to continue it")
    record = run_record(cfg)
    if cfg.resume is not None:
        if not cfg.resume.is_file():
            raise ValueError(f"--resume {cfg.resume}: no such checkpoint")
        saved = resume_dir / "config.json" if resume_dir is not None else None
        if saved is not None and saved.is_file():
            check_resume_record(json.loads(saved.read_text()), record, str(saved), RESUMABLE_CHANGES)
    torch.set_num_threads(cfg.torch_threads)
    torch.manual_seed(cfg.seed)
    env_cfg = cfg.env_config()
    env = RotateCupSB3VecEnv(env_cfg, cfg.num_envs, seed=cfg.seed, reward_scale=cfg.reward_scale,
                             obs_groups=obs_groups(cfg), latent_mix=cfg.latent_mix)
    try:
        resumed_from = None
        if cfg.resume is not None:
            model, resumed_from = with_fallback(cfg.resume, _older_checkpoints(cfg.resume),
                                                lambda p: load_checkpoint(p, env, cfg.device))
            differences = config_differences(_checkpoint_options(model), {k: record[k] for k in PPO_OPTIONS}, ())
            refuse_differences(differences, f"recorded in {resumed_from}", RESUMABLE_CHANGES)
            env.seed(cfg.seed + model.num_timesteps)  # fresh, reproducible episodes after a resume
        else:
            model = build_model(cfg, env)
        model.overlap = cfg.overlap
        if cfg.freeze_encoder:  # (a resumed model is rebuilt with every parameter trainable)
            for p in model.policy.features_extractor.encoder.parameters():
                p.requires_grad_(False)
        # every check passed: only now is anything in `out` written or deleted
        if cfg.overwrite and not resuming_here:
            removed = clear_outputs(out, RUN_OUTPUTS)
            if removed:
                print(f"{_role(cfg)}: --overwrite deleted {', '.join(removed)} in {out}")
        out.mkdir(parents=True, exist_ok=True)
        save_config(record, out / "config.json")
        curves = CurveLog(out / "curves.jsonl")
        if resuming_here and (dropped := curves.trim(model.num_timesteps)):
            print(f"{_role(cfg)}: dropped {dropped} curve rows logged after step {model.num_timesteps} (not in the "
                  "checkpoint resumed from)")
        return _train(cfg, model, env, env_cfg, curves, resumed_from, record[GRASPS_KEY])
    finally:
        env.close()


def _train(cfg: Config, model: AdaptiveKLPPO, env: RotateCupSB3VecEnv, env_cfg: EnvConfig, curves: CurveLog,
           resumed_from: Path | None, grasps_sha256: str) -> PolicyBundle:
    stats = EpisodeStats()
    with StopSignals() as stop:
        ckpt = Checkpoints(cfg.out / "checkpoints", cfg.checkpoint_every, stats, curves, stop)
        remaining = cfg.total_steps - model.num_timesteps
        start = time.time()
        signum = None
        if remaining > 0:
            try:
                model.learn(remaining, callback=CallbackList([stats, ckpt]), progress_bar=cfg.progress,
                            reset_num_timesteps=cfg.resume is None, tb_log_name=_role(cfg))
            except KeyboardInterrupt as err:  # a second signal, or Ctrl-C where no handler could be installed
                signum = getattr(err, "signum", signal.SIGINT)
        signum = signum or stop.signum
        wall = time.time() - start
        # the checkpoint, curves and bundle are written whether training finished or was stopped
        ckpt.model = model
        ckpt.num_timesteps = model.num_timesteps
        ckpt.save()
        steps = int(model.num_timesteps)
        card = {"role": _role(cfg), "object": cfg.object, "steps": steps, "seed": cfg.seed,
                "wall_time_s": round(wall, 1), "train_config": dataclasses.asdict(cfg) | {"out": str(cfg.out),
                                                                                       "resume": str(cfg.resume)}}
        card[GRASPS_KEY] = grasps_sha256  # the cache's path alone does not show a regenerated file
        if resumed_from is not None:
            card["resumed_from"] = str(resumed_from)
        if cfg.student:  # what the fine-tune started from: the distilled student's own card (teacher, distillation)
            card["finetuned_from"] = {"bundle": cfg.student, "card": load_bundle(cfg.student).config.card}
        if signum:
            card["interrupted"] = f"stopped by {SIGNAL_NAMES.get(signum, signum)} at {steps} of {cfg.total_steps} steps"
        bundle = PolicyBundle.from_sb3(model, control_hz=env_cfg.control_hz, action_scale=env_cfg.action_scale,
                                       card=card)
        bundle.save(cfg.out / "bundle")
    last = cfg.out / "checkpoints" / "last.zip"
    if signum:
        message = (f"{_role(cfg)}: interrupted by {SIGNAL_NAMES.get(signum, signum)} at {steps} of {cfg.total_steps} "
                   f"steps; saved {last} and the bundle {cfg.out / 'bundle'}; continue with --resume {last}")
        print(message)
        raise Interrupted(signum, message)
    print(f"{_role(cfg)}: {steps} steps in {wall:.0f} s; bundle at {cfg.out / 'bundle'}")
    return bundle
