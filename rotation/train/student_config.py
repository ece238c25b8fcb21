"""The config of `rotate train-student` and what a resumed run may change.
"""

from __future__ import annotations

import json
from dataclasses import dataclass, field
from pathlib import Path
from typing import Literal

from envs.config import EnvConfig
from envs.constants import DEFAULT_HAND, HISTORY_STEPS, PROPRIO_DIM
from envs.sim_identity import bundle_hand
from envs.validation import check_int, check_number, check_output_dir, check_seed, check_types
from rotation.configs import check_device, config_resuming_in_out, from_jsonable
from rotation.policy.networks import AdaptationConfig

CHECKPOINT_GLOB = "ckpt_*.pt"


@dataclass
class Config:
    """Student distillation (`rotate train-student`)."""

    teacher: str = "teacher"
    """Teacher bundle: a directory or a shipped bundle name (latent source 'privileged')."""
    out: Path = Path("runs/student")
    """Run directory: config.json, checkpoints, TensorBoard logs (tb/) and the student bundle (bundle/)."""
    total_steps: int = 2_000_000
    """Env transitions to train on (num_envs per iteration, one gradient step per iteration)."""
    num_envs: int = 64
    """Simulations stepped together; also the batch size of each gradient step."""
    lr: float = 3e-4
    """Adam learning rate for the adaptation module (Hora: 3e-4)."""
    checkpoint_every: int = 200_000
    """Env transitions between checkpoints (rounded to whole iterations); each interval starts with fresh resets."""
    log_every: int = 20
    """Iterations between TensorBoard points."""
    seed: int = 0
    """Seed of the envs (env i of an interval starting at iteration t is seeded seed + t * num_envs + i) and of phi."""
    resume: bool = False
    """Continue from the latest checkpoint in `out`; options not given are the run's (its config.json), and given
    ones must match it but the length and speed ones (total_steps, threads, progress)."""
    adaptation: AdaptationConfig = field(default_factory=AdaptationConfig)
    """Sizes of the adaptation module phi."""
    env: EnvConfig = field(default_factory=EnvConfig)
    """The env the student trains in; use the teacher's training env (object, randomization, grasp cache)."""
    nthread: int = 0
    """MuJoCo threads of the batched env (0 = one per CPU core, at most num_envs)."""
    torch_threads: int = 1
    """torch CPU threads (the env steps on its own threads)."""
    device: str = "cpu"
    """torch device of the networks ('cpu' or 'cuda')."""
    progress: bool = True
    """Show a progress bar."""
    overwrite: bool = False
    """Delete the outputs of an earlier run in `out` (checkpoints, bundle, curves, config, logs) and start over;
    without it a folder holding a run is refused unless --resume continues it."""
    backend: Literal["cpu", "warp"] = "cpu"
    """Physics backend: 'cpu' (MuJoCo on mujoco.batch threads) or 'warp' (MuJoCo Warp worlds on --device, the
    [warp] extra; observations, actions, resets and episode statistics stay on the device, one host read per log
    point). The simulated Digit 360 touch runs on the cpu backend only."""

    def __post_init__(self) -> None:
        check_types(self)
        self.out = Path(self.out)
        if not self.teacher:
            raise ValueError("teacher: give a teacher bundle directory or a shipped bundle name (--teacher teacher)")
        check_output_dir("out", self.out)
        check_int("total_steps", self.total_steps, 1, 10**12)
        check_int("num_envs", self.num_envs, 1, 65_536)
        check_number("lr", self.lr, 0.0, 1.0, low_open=True)
        check_int("checkpoint_every", self.checkpoint_every, 1, 10**12)
        check_int("log_every", self.log_every, 1, 10**9)
        check_seed("seed", self.seed)
        check_int("nthread", self.nthread, 0, 1024, "(0 = one per CPU core)")
        check_int("torch_threads", self.torch_threads, 1, 1024)
        check_device("device", self.device)
        for name, want in (("in_dim", PROPRIO_DIM), ("steps", HISTORY_STEPS)):
            if getattr(self.adaptation, name) != want:  # phi reads the env's proprio_hist group as it is
                raise ValueError(f"adaptation.{name} must be {want} (the env's proprio_hist is {HISTORY_STEPS} x "
                                 f"{PROPRIO_DIM}), got {getattr(self.adaptation, name)}")
        if self.resume and self.overwrite:
            raise ValueError("--resume continues the run in --out and --overwrite deletes it: give one of them")
        self._follow_teacher_hand()

    def _follow_teacher_hand(self) -> None:
        """The student trains on its teacher's hand (and that hand's physics); an env on another hand is refused."""
        from rotation.policy.bundle import load_policy_bundle

        try:
            sim = load_policy_bundle(self.teacher).config.sim
        except ValueError:  # unreadable or missing: run() names the problem
            return
        hand = bundle_hand(sim)
        if hand == self.env.hand:
            return
        if self.env.hand != DEFAULT_HAND:  # left at the default: follow the bundle
            raise ValueError(f"env.hand: the teacher {self.teacher} was trained on the {hand} hand; its student "
                             f"trains on the same hand, not on {self.env.hand}")
        self.env = self.env.with_hand(hand)


RUN_OUTPUTS = ("config.json", "run.json", "bundle", "curves.jsonl", "tb")
"""What a run writes into `out` besides its checkpoints (what --overwrite deletes, with them)."""
RESUMABLE_CHANGES = {"out", "total_steps", "resume", "progress", "nthread", "torch_threads", "device", "overwrite"}
"""Config fields that may differ between a run and its resumption without breaking exactness of the result."""


def config_from_args(args) -> Config:
    """The command line's config; with --resume, the options it leaves out are the run's in --out."""
    return config_resuming_in_out(Config, args)


def load_config(path: str | Path) -> Config:
    """The Config a run saved (``<out>/config.json``)."""
    return from_jsonable(Config, json.loads(Path(path).read_text()))
