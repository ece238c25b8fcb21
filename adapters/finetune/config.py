"""The config of `rotate finetune-adapter` (simulation, recorded sessions or a head refit), its training
randomization, and what a resumed run may change.
"""

from __future__ import annotations

import dataclasses
import json
import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import Literal

from adapters.touch_delay import parse_delay
from envs.config import EnvConfig, RandomizationConfig
from envs.physics import DEFAULT_HAND, MAX_OBJECT_MASS, default_randomization
from envs.validation import check_int, check_number, check_output_dir, check_seed, check_types
from rotation.configs import config_resuming_in_out, from_jsonable
from rotation.tactile.models.encoders import parse_groups

CHECKPOINT_GLOB = "ckpt_*.pt"
RUN_OUTPUTS = ("config.json", "run.json", "bundle", "curves.jsonl", "tb")
RESUMABLE_CHANGES = {"out", "total_steps", "epochs", "resume", "progress", "torch_threads", "nthread", "overwrite"}


def hard_randomization(hand: str = DEFAULT_HAND) -> RandomizationConfig:
    """The training randomization: the hand's own physics (envs.physics.HAND_PHYSICS: its cups, its friction
    split, its hardware randomization), reaching 4x more slippery and to heavier cups, where the student's gap is.

    On the first hand model (one friction for every geom): friction 0.075-1.5, mass 0.05-0.45 kg. On a hand with
    its own link friction (the vendor-kinematics hands): a cup-surface factor of 0.25-1 on the domes' and the
    links' friction together (log-uniform: the perturbation suite's friction x0.25 at its low end) and masses up
    to MAX_OBJECT_MASS (the suite's +0.1 kg on the hand's heaviest cup)."""
    base = default_randomization(hand)
    if base.link_friction is None:  # Hora's 0.3-3.0 and 0.01-0.25 kg
        return dataclasses.replace(base, friction=(0.075, 1.5), mass=(0.05, 0.45))
    return dataclasses.replace(base, surface_friction=(0.25, 1.0), mass=(base.mass[0], MAX_OBJECT_MASS))


@dataclass
class Config:
    """Tactile adapter fine-tuning (`rotate finetune-adapter`): in simulation, or on recorded ``sessions``."""

    student: str = "student"
    """The frozen student it corrects: a shipped bundle name or a bundle directory."""
    teacher: str = "teacher"
    """The frozen teacher whose z is the target (the student's teacher)."""
    encoder: str = "sparshx-tinier-sim"
    """The frozen touch encoder: a shipped name (rotation/tactile/pretrained) or a checkpoint / pretrain run."""
    modalities: str = "img,mic,imu,pressure"
    """Encoder token groups the adapter reads (comma-separated subset; e.g. 'img' for the image-only ablation);
    'skin' with a Sparsh-skin encoder (the Xela hand's skin; the env then becomes the Xela hand with its skin)."""
    out: Path = Path("runs/adapter")
    """Run directory: config.json, checkpoints, TensorBoard logs (tb/), curves.jsonl and the adapter bundle."""
    total_steps: int = 60_000
    """Env transitions (num_envs per control step)."""
    num_envs: int = 16
    """Simulations stepped together."""
    touch_every: int = 8
    """Control steps between touch refreshes while training, written into the bundle as its refresh period at run
    time; a shorter one can be set afterwards in the bundle's config.json (the shipped adapter trained with 8 and
    runs with 4, which kept more cups: experiments/adapter/tried_touch4)."""
    touch_delay: str = "measured"
    """Control steps from the touch a refresh reads to the first action its correction changes in the training
    rollouts, drawn per refresh (adapters.touch_delay): 'measured' (what `rotate deploy` measured on 2 CPU cores at
    20 Hz), N (always N; 0: the same step) or STEPS:PROB pairs; recorded in the bundle's card. The regression target
    is the teacher's latent at the step the touch was read."""
    student_steps: int = 10_000
    """Env steps at the start during which the student acts alone (then student + adapter, DAgger)."""
    updates: int = 4
    """Adam steps per touch refresh."""
    batch_size: int = 128
    """Minibatch size of each Adam step (drawn from the buffer)."""
    buffer_size: int = 8192
    """Samples kept in the buffer (the oldest are replaced); each holds every fingertip's tokens in float16."""
    lr: float = 3e-4
    """Adam learning rate."""
    action_weight: float = 0.0
    """Weight of an action-matching term added to the latent MSE: the MSE between the frozen student actor's action
    mean on the adapted latent and on the teacher's z (same proprioception). It weights each latent direction by
    how much it moves the action; 0 = the latent MSE alone."""
    anchor: str = ""
    """An adapter bundle (directory or shipped name) whose corrections stand in for the teacher's z on cups lighter
    than ``anchor_mass`` (simulation only): the target there is phi + the anchor's correction on the same tokens,
    while heavier cups keep the teacher's z. With ``--init-from`` the same adapter, training moves the heavy-cup
    corrections and holds the nominal-cup ones where the anchor had them. Empty: the teacher's z everywhere."""
    anchor_mass: float = 0.2
    """Object mass (kg) below which ``anchor`` sets the target."""
    refit_head: bool = False
    """Instead of Adam steps: roll the ``--init-from`` adapter out for ``total_steps`` env steps and solve its zero
    layer (the last, linear one) by ridge regression on its own hidden features, every other weight kept
    (adapters.finetune.refit; simulation only)."""
    refit_lambdas: tuple[float, ...] = (1e-5, 1e-4, 1e-3, 1e-2, 1e-1)
    """Refit: ridge strengths tried (penalty lambda x samples x |W|^2); the one with the lowest held-out latent error
    is used."""
    refit_folds: int = 4
    """Refit: cross-validation folds over whole episodes that choose the ridge strength."""
    hidden: tuple[int, ...] = (256, 128)
    """Hidden widths of the adapter's MLP g."""
    tracking: bool = False
    """Also feed g the joints' tracking over the proprioceptive history (per joint the mean and spread of target -
    position and the mean position: adapters.model.tracking_features): on the palm-up hand the joints under the cup
    sag with its weight. Their normalization is measured on the student's own rollouts (simulation) or the training
    sessions before the first update, unless ``--init-from`` is an adapter that reads them; ``--init-from`` an
    adapter without them starts with zero weights on them (the same corrections at the start)."""
    blind_touch: bool = False
    """Blank the touch tokens: the adapter learns from the student's latent and, with --tracking, the joints'
    tracking alone (adapters.model.AdapterNetConfig.touch). The ablation that says what touch adds: with --tracking
    it is the row 'tracking only' of an adapter's evaluation (docs/adapter.md). --modalities still names what is
    rendered and encoded, and discarded (pressure is the cheapest)."""
    checkpoint_every: int = 20_000
    """Env transitions between checkpoints (rounded to whole touch periods); each interval starts afresh, so one
    shorter than num_envs x the env's episode_steps cuts every episode short (2,048 with 16 envs: 6.4 s episodes)."""
    log_every: int = 10
    """Touch refreshes between log points."""
    seed: int = 0
    """Seed of the envs (as in train-student), of the adapter's initialization and of the minibatches."""
    resume: bool = False
    """Continue from the latest checkpoint in `out`; options not given are the run's (its config.json), and given
    ones must match it but the length and speed ones (total_steps, threads, progress)."""
    overwrite: bool = False
    """Delete an earlier run's outputs in `out` and start over."""
    init_from: str = ""
    """An adapter bundle (directory or shipped name) whose adapter weights this run starts from instead of zeros,
    e.g. to carry a trained adapter over to a student fine-tuned with `rotate finetune-student` (same phi, new
    actor). Its encoder, modalities and sizes must be this run's; it may name another student."""
    env: EnvConfig = field(default_factory=lambda: EnvConfig(tactile=True, randomization=hard_randomization()))
    """The training env (the touch the adapter reads is forced on: tactile, or for skin the Xela hand's skin)."""
    nthread: int = 0
    """MuJoCo threads of the batched env (0 = one per core)."""
    torch_threads: int = 2
    """torch CPU threads (the encoder's forward dominates the cost)."""
    progress: bool = True
    """Show a progress bar."""
    sessions: tuple[Path, ...] = ()
    """Train on recorded sessions instead of simulation: .h5 session files, or directories searched for them. Each
    needs joints/position, joints/target, every fingertip's Digit 360 streams the adapter reads (imu and pressure;
    image and audio from `--record-media`) and the measured object properties (`rotate deploy --digit360 ... --record
    FILE --properties ...`; docs/adapter.md)."""
    epochs: int = 30
    """Sessions: passes over the training samples."""
    sample_every: int = 2
    """Sessions: control steps between two samples of a session (1 = every step)."""
    val_fraction: float = 0.2
    """Sessions: fraction of the session files held out for validation (by file; with two or more files at least
    one on each side); their latent error is logged beside the student's own."""
    position: Literal["fit", "average", "recorded"] = "fit"
    """Sessions: the object position in the teacher's privileged vector, which a real hand does not measure:
    'fit' = per sample, the position that best explains the student's own latent given the measured properties;
    'average' = the teacher's z averaged over the env's start positions; 'recorded' = the session's
    labels/object_pose (an emulated hand, or a tracked object). See adapters.real_data."""

    def __post_init__(self) -> None:
        check_types(self)
        self.out = Path(self.out)
        check_output_dir("out", self.out)
        for name in ("student", "teacher", "encoder"):
            if not getattr(self, name):
                raise ValueError(f"{name}: give a shipped name or a path")
        parse_groups(self.modalities, self.touch_kind)  # validates them
        check_int("total_steps", self.total_steps, 1, 10**12)
        check_int("num_envs", self.num_envs, 1, 4096)
        check_int("touch_every", self.touch_every, 1, 1000)
        check_int("student_steps", self.student_steps, 0, 10**12)
        self.delay = parse_delay(self.touch_delay)
        check_int("updates", self.updates, 1, 10_000)
        check_int("batch_size", self.batch_size, 1, 1 << 20)
        check_int("buffer_size", self.buffer_size, 1, 1 << 24)
        check_number("lr", self.lr, 0.0, 1.0, low_open=True)
        check_number("action_weight", self.action_weight, 0.0, 1e6)
        check_number("anchor_mass", self.anchor_mass, 0.0, 100.0, low_open=True)
        if not self.hidden or not all(isinstance(h, int) and 1 <= h <= 65_536 for h in self.hidden):
            raise ValueError(f"hidden must be widths in 1..65536, got {self.hidden}")
        check_int("checkpoint_every", self.checkpoint_every, 1, 10**12)
        check_int("log_every", self.log_every, 1, 10**9)
        check_seed("seed", self.seed)
        check_int("nthread", self.nthread, 0, 1024, "(0 = one per CPU core)")
        check_int("torch_threads", self.torch_threads, 1, 1024)
        needs = {"hand": "xela", "skin": True, "tactile": False} if self.touch_kind == "skin" else {"tactile": True}
        if any(getattr(self.env, k) != v for k, v in needs.items()):
            if "hand" in needs and self.env.randomization == hard_randomization(self.env.hand):
                needs["randomization"] = hard_randomization(needs["hand"])  # the new hand's, not the default's
            self.env = dataclasses.replace(self.env, **needs)
        if self.resume and self.overwrite:
            raise ValueError("--resume continues the run in --out and --overwrite deletes it: give one of them")
        self.sessions = tuple(Path(p) for p in self.sessions)
        check_int("epochs", self.epochs, 1, 10**6)
        check_int("sample_every", self.sample_every, 1, 10**6)
        check_number("val_fraction", self.val_fraction, 0.0, 1.0, high_open=True)
        if self.sessions and self.touch_kind == "skin":
            raise ValueError("--sessions trains Digit 360 adapters (imu, pressure) only; fine-tuning a skin adapter "
                             "on recorded skin sessions is not implemented (docs/skin.md): train a skin adapter in "
                             "simulation")
        check_int("refit_folds", self.refit_folds, 2, 100)
        if not self.refit_lambdas or not all(isinstance(v, (int, float)) and math.isfinite(v) and 0 < v <= 1e6
                                             for v in self.refit_lambdas):
            raise ValueError(f"refit_lambdas must be numbers in (0, 1e6], got {list(self.refit_lambdas)}")
        if self.refit_head:
            clashes = [name for name, on in (("--sessions", bool(self.sessions)), ("--resume", self.resume),
                                             ("--anchor", bool(self.anchor)),
                                             ("--action-weight", self.action_weight > 0)) if on]
            if clashes:
                raise ValueError(f"--refit-head is one rollout and one closed-form fit in simulation; it takes no "
                                 f"{', '.join(clashes)} (run it again to redo it)")
            if not self.init_from:
                raise ValueError("--refit-head refits the zero layer of a trained adapter: give it with --init-from "
                                 "(e.g. --init-from rotation/policies/adapter/members/all_modalities)")
        if self.sessions and self.anchor:
            raise ValueError("--anchor sets the target by the simulated cup's mass; recorded sessions carry their "
                             "own measured properties: leave --anchor out with --sessions")


    @property
    def touch_kind(self) -> str:
        """The encoder kind the modalities name: 'skin' for Sparsh-skin's one group, else 'sparshx'."""
        return "skin" if [t.strip() for t in self.modalities.split(",") if t.strip()] == ["skin"] else "sparshx"


def config_from_args(args) -> Config:
    """The command line's config; with --resume, the options it leaves out are the run's in --out."""
    return config_resuming_in_out(Config, args)


def load_config(path: str | Path) -> Config:
    return from_jsonable(Config, json.loads(Path(path).read_text()))
