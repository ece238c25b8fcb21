"""The config of `rotate train-teacher` (and of `finetune-student`, which extends it), the GPU recipe of
the warp backend, and what a resumed run may change.
"""

from __future__ import annotations

import dataclasses
import json
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Literal

from envs.config import EnvConfig, RewardConfig, default_randomization
from envs.constants import DEFAULT_HAND
from envs.objects import OBJECTS
from envs.sim_identity import bundle_hand
from envs.validation import check_int, check_number, check_output_dir, check_seed, check_types
from rotation.configs import check_device
from rotation.policy.bundle import load_policy_bundle
from rotation.sim_warp.core import physics_problem, simulated_hands


@dataclass
class Config:
    out: Path = Path("runs/teacher")
    """Output directory (checkpoints, TensorBoard logs, config, final bundle)."""
    object: str = "cup"
    """Training object (envs.objects): the upright cup with a handle, scaled per env."""
    hand: Literal["digit360", "xela", "digit360_v4", "xela_v4"] = DEFAULT_HAND
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
    rotate_clip: float = 0.5
    """Upper clip of the rotate reward term (rad/s; envs.config.RewardConfig.rotate_clip): turning faster earns no
    more. 0.5 is Hora's and every shipped teacher's; a higher clip pays a faster gait for its speed."""
    pose_diff_reward: float = -0.1
    """Weight of the joints' squared distance from the episode's grasp (RewardConfig.pose_diff): a penalty or 0."""
    work_reward: float = -2.0
    """Weight of the mechanical power penalty (tau . qdot)^2 (RewardConfig.work): a penalty or 0."""
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
    """Domain randomization on (the hand's ranges, envs.physics.HAND_PHYSICS); off trains on nominal physics (an
    easy setting for tests)."""
    friction: tuple[float, float] | None = None
    """Range of the sliding friction the randomization draws: the gel tips' on a hand whose links have their own
    (digit360_v4), every geom's on the first hand; None = the hand's. A range reaching below the hand's trains on
    the slippery cups the perturbation suite tries (friction x0.25 of the hand's range)."""
    mass: tuple[float, float] | None = None
    """Range of the cup's mass (kg) the randomization draws; None = the hand's. The heaviest cup, with the
    evaluation's added mass, must stay within what the actuators hold (envs.config.MAX_OBJECT_MASS)."""
    surface_friction: tuple[float, float] | None = None
    """Range of a per-episode factor of the cup's surface (log-uniform) that multiplies the gel tips' and the links'
    friction together, as the perturbation suite's friction scale does (envs.physics.RandomizationConfig); None =
    1. (0.2, 1.0) trains on cups down to a fifth of the hand's friction everywhere, past the suite's friction x0.25."""
    surface_share: float = 1.0
    """With --surface-friction: the share of episodes whose cup surface is drawn from it; the others keep the nominal
    surface (factor 1). 1 = every episode (a log-uniform factor makes the nominal cup the edge of what it practises)."""
    noslip_dropout: float | None = None
    """Share of episodes run without MuJoCo's noslip solver, on a hand whose contact model uses it (digit360_v4:
    0.25); None = the hand's. Those episodes are where a held cup creeps, and where the v4 teacher drops it most
    (experiments/teacher_v4)."""
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
    rotation.train.teacher_config.GPU_RECIPE: 8192 worlds, horizon 8, 5 epochs, lr 5e-3, device cuda, which the
    options given win over). The simulated Digit 360 touch runs on the cpu backend only, and so does the physics of
    the vendor-kinematics hands (digit360_v4, xela_v4): a warp run takes --hand digit360 or xela."""
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
                student = load_policy_bundle(self.student)
            except ValueError as err:  # a missing or broken bundle (BundleError)
                raise ValueError(f"student: {err}") from None
            student.require("adaptation", f"student: {self.student}")
            self._follow_bundle_hand(student.config.sim, f"student {self.student}")
        check_number("latent_mix", self.latent_mix, 0.0, 1.0)
        if self.latent_mix > 0:
            if not self.student:
                raise ValueError("latent_mix: for a student fine-tune (`rotate finetune-student`); a teacher already "
                                 "acts on its own z")
            try:
                teacher = load_policy_bundle(self.latent_teacher)
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
            init_sim = _recorded_sim(self.init_from)
            if bundle_hand(init_sim) != self.hand:
                raise ValueError(f"init_from: {self.init_from} was trained on the {bundle_hand(init_sim)} hand, not "
                                 f"the {self.hand} hand (pass --hand {bundle_hand(init_sim)}, or start from scratch)")
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
        check_number("rotate_clip", self.rotate_clip, 0.0, 100.0, low_open=True)
        check_number("pose_diff_reward", self.pose_diff_reward, -1000.0, 0.0)  # penalties: a reward would pay for
        check_number("work_reward", self.work_reward, -1000.0, 0.0)  # leaving the grasp or for burning power
        check_int("checkpoint_every", self.checkpoint_every, 1, 10**12)
        check_int("torch_threads", self.torch_threads, 1, 1024)
        check_int("critic_warmup", self.critic_warmup, 0, 10**6)
        if self.grasp_cache and not Path(self.grasp_cache).is_file():
            raise ValueError(f"grasp_cache: no such file: {self.grasp_cache!r} (generate one with `rotate grasps`)")
        if self.backend == "warp":
            self._check_warp_physics()
        check_device("device", self.device)
        if self.resume is not None and self.overwrite and self.resume.resolve().is_relative_to(self.out.resolve()):
            raise ValueError(f"--overwrite would delete the checkpoint --resume {self.resume} continues from; "
                             "resume into another --out, or drop --overwrite")
        self.env_config()  # episode_steps and the rest of the env, checked by EnvConfig

    def _check_warp_physics(self) -> None:
        """The warp backend simulates the first hand model's physics only (rotation.sim_warp.core.physics_problem):
        a run it cannot simulate is refused here, in one line that names the hand to pass."""
        problem = physics_problem(self.env_config())
        if problem is None:
            return
        hands = simulated_hands()
        if self.hand in hands:  # an option of this run turned on physics the backend lacks
            raise ValueError(f"backend: {problem}; use --backend cpu for these settings")
        raise ValueError(f"backend: {problem}; pass --hand {hands[0]} to train on the warp backend (it simulates the "
                         f"{' and '.join(hands)} hands), or use --backend cpu")

    def _follow_bundle_hand(self, sim: dict, what: str) -> None:
        """A fine-tune trains on its bundle's hand: the default hand follows it, another one is refused."""
        hand = bundle_hand(sim)
        if hand == self.hand:
            return
        if self.hand != DEFAULT_HAND:  # left at the default: follow the bundle
            raise ValueError(f"hand: the {what} was trained on the {hand} hand, not the {self.hand} hand")
        self.hand = hand  # type: ignore[assignment]

    def env_config(self) -> EnvConfig:
        rc = default_randomization(self.hand, self.randomize)  # the hand's physics (envs.physics.HAND_PHYSICS)
        ranges: dict[str, Any] = {k: tuple(v) for k, v in (("friction", self.friction), ("mass", self.mass),
                                                           ("surface_friction", self.surface_friction))
                                  if v is not None}
        if self.noslip_dropout is not None:
            ranges["noslip_dropout"] = self.noslip_dropout
        if self.surface_share != 1.0:
            if self.surface_friction is None:
                raise ValueError("surface_share: the share of episodes drawn from --surface-friction; give that range "
                                 "too")
            ranges["surface_share"] = self.surface_share
        if ranges:
            if not self.randomize:
                raise ValueError(f"{' / '.join(ranges)}: settings of the randomization, which --no-randomize turns "
                                 "off")
            rc = dataclasses.replace(rc, **ranges)
        return EnvConfig(object=self.object, hand=self.hand, episode_steps=self.episode_steps, randomization=rc,
                         grasp_cache=self.grasp_cache, reward=self.reward_config())

    def reward_config(self) -> RewardConfig:
        """The reward terms this run sets (the rest at RewardConfig's defaults)."""
        return RewardConfig(rotate_clip=self.rotate_clip, rotate_back_clip=self.rotate_back_clip,
                            pose_diff=self.pose_diff_reward, work=self.work_reward, fall=self.fall_reward)


def _recorded_sim(bundle_dir: Path) -> dict:
    """The sim a bundle's config.json records ({} when it records none or cannot be read: loading the bundle
    reports that later)."""
    try:
        sim = json.loads((bundle_dir / "config.json").read_text()).get("sim")
    except (OSError, ValueError, AttributeError):
        return {}
    return sim if isinstance(sim, dict) else {}


def config_from_args(args) -> Config:
    """The Config of a command line; with --backend warp the GPU recipe replaces the defaults of the options the
    command line does not give (rotation.train.teacher_config.GPU_RECIPE)."""
    return _config_from_args(Config, args)


def _config_from_args(cls: type[Config], args) -> Config:
    """train-teacher's and finetune-student's config: a --resume takes the run's options the command line leaves
    out, and the warp backend's GPU recipe fills the rest."""
    from rotation.configs import dataclass_from_args, inherit_run_options

    if getattr(args, "resume", None) is not None:
        run_dir = run_dir_of(Path(args.resume))
        # --out defaults to the run resumed (where it is now); --init-from only starts runs
        if "out" not in vars(args) and run_dir is not None:
            args.out = run_dir
        inherit_run_options(cls, args, run_dir, not_inherited=("out", "init_from", "overwrite", "resume"))
    cfg = dataclass_from_args(cls, args)
    if cfg.backend == "warp":
        cfg = apply_gpu_recipe(cfg, given=set(vars(args)))
    return cfg


GPU_RECIPE: dict[str, Any] = {
    "num_envs": 8192,  # Hora: 16,384 worlds; MuJoCo Playground's LEAP rotation: 8,192
    "n_steps": 8,  # Hora's horizon
    "n_epochs": 5,  # Hora
    "learning_rate": 5e-3,  # Hora's start; the adaptive-KL rule moves it
    "total_steps": 200_000_000,
    "checkpoint_every": 10_000_000,
    "device": "cuda",
}
"""Defaults of `rotate train-teacher --backend warp` (docs/reference/hora.md, "Training"); options given on the command
line win. The minibatch size defaults to a quarter of the rollout (Hora: 4 minibatches of 32,768)."""

def apply_gpu_recipe(cfg, given: set[str]):
    """``cfg`` with GPU_RECIPE for every field not in ``given`` (the options named on the command line)."""
    changes = {k: v for k, v in GPU_RECIPE.items() if k not in given}
    num_envs = changes.get("num_envs", cfg.num_envs)
    n_steps = changes.get("n_steps", cfg.n_steps)
    if "batch_size" not in given:
        changes["batch_size"] = max(2, num_envs * n_steps // 4)
    return dataclasses.replace(cfg, **changes)


TEACHER_GROUPS = ("proprio", "priv")
"""Observation groups the teacher reads (rotation.policy.features.PrivilegedExtractor)."""
STUDENT_RL_GROUPS = ("proprio", "proprio_hist", "priv")
"""Observation groups of a student fine-tune: the actor reads proprio and its history, the critic proprio and priv."""


def obs_groups(cfg: Config) -> tuple[str, ...]:
    """The observation groups a run's rollouts keep."""
    return STUDENT_RL_GROUPS if cfg.student else TEACHER_GROUPS


PPO_OPTIONS = ("n_steps", "batch_size", "n_epochs", "learning_rate", "target_kl", "gamma", "gae_lambda",
               "clip_range", "vf_coef", "ent_coef", "max_grad_norm", "net_arch", "log_std_init")
"""Options a checkpoint records itself (compared on resume even without the run's config.json)."""
RESUMABLE_CHANGES = {"out", "total_steps", "progress", "checkpoint_every", "resume", "torch_threads", "device",
                     "overwrite", "overlap", "init_from", "critic_warmup"}
"""Options that may change on resume: the run's length, where it writes, and how fast it runs."""


RUN_OUTPUTS = ("config.json", "run.json", "checkpoints", "bundle", "curves.jsonl", "tb")
"""What a run writes into `out` (what --overwrite deletes)."""


def run_dir_of(checkpoint: Path) -> Path | None:
    """The run folder of a checkpoint at <run>/checkpoints/<name>.zip."""
    return checkpoint.parent.parent if checkpoint.parent.name == "checkpoints" else None


RUN_FILES = {"out": ".", "init_from": None, "resume": None, "grasp_cache": "", "student": "", "latent_mix": 0.0}
"""Fields of a finished run's config that name files on the machine that trained it (and the fine-tune settings that
need them): :func:`recorded_config` sets them to these values, since a clone of the repository has none of them."""


def recorded_config(data: dict[str, Any]) -> Config:
    """The Config a bundle's card records (``card["train_config"]``) read back as a record of what the run trained on:
    its hand, object, randomization and reward, without the run's own files (RUN_FILES). Raises ValueError on a record
    that does not load."""
    from rotation.configs import from_jsonable

    if not isinstance(data, dict):
        raise ValueError(f"train_config: expected a mapping, got {type(data).__name__}")
    kept = {k: v for k, v in data.items() if k not in RUN_FILES}
    return from_jsonable(Config, {**kept, **{k: v for k, v in RUN_FILES.items() if k in data}})
