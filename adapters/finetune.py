"""Fine-tune a tactile adapter (`rotate finetune-adapter`) in simulation or on recorded sessions: regress the frozen
teacher's z.

The student, the touch encoder and the teacher stay frozen; only the adapter learns, on

    MSE(phi(history) + adapter(tokens, phi(history)), z_teacher(priv))

optionally plus ``action_weight`` x the MSE between the frozen student actor's action mean on that latent and on
z_teacher (same proprioception: the action the student would take knowing the teacher's z), over the student's own
rollouts (DAgger): for the first ``student_steps`` env steps the student acts alone, then
the student with the adapter's current correction, so the adapter learns on the states its own corrections lead
to. The env simulates the Digit 360 fingertips under a randomization that emphasizes low friction and heavy
objects. Every ``touch_every`` control steps (the adapter's refresh period, as at run time) the fingertip windows
of every env are rendered and encoded once by the frozen encoder; the tokens (float16), phi's latent and the
teacher's z go to an in-memory buffer (the cached embeddings) from which ``updates`` Adam steps draw minibatches,
so each encoder pass feeds many gradient steps.

    rotate finetune-adapter --student student --teacher teacher --encoder sparshx-tinier-sim --out runs/adapter
    rotate finetune-adapter --out runs/adapter --resume          # continue where it stopped

Exact resume: as in train-student, training is cut into checkpoint intervals that each start from fresh env
resets and an empty buffer, so a resumed run is bit-identical to an uninterrupted one. Ctrl-C / SIGTERM stop after
the current step, save a checkpoint and the adapter bundle (exit status 130 / 143).

The simulation loop is adapters.finetune_sim. With ``--sessions`` it trains on recorded sessions instead
(adapters.finetune_sessions; the procedure: docs/adapter.md, "Fine-tuning on your own hand"): sessions of the hand
recorded by ``rotate deploy`` with the measured object properties give the student's observations, the fingertip
windows and the teacher's z (adapters.real_data); the windows are encoded once into the same buffer, then
``epochs`` passes of Adam steps train the adapter, with a held-out share of the sessions for validation::

    rotate finetune-adapter --sessions sessions/ --modalities imu,pressure --out runs/adapter_lab

With ``--refit-head`` (adapters.refit_head) it trains nothing by gradient: it rolls an ``--init-from`` adapter out
and solves its last, linear layer in closed form (ridge regression on its own hidden features, the strength chosen
by cross-validation over whole episodes)::

    rotate finetune-adapter --init-from rotation/policies/adapter/members/all_modalities --refit-head \\
        --total-steps 76800 --out runs/adapter_refit
"""

from __future__ import annotations

import copy
import dataclasses
import json
import math
import pickle
import time
import zipfile
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Literal

import torch

from adapters.bundle import build_adapted, file_digest, read_adapter, student_weights
from envs.config import EnvConfig, RandomizationConfig
from envs.validation import check_int, check_number, check_output_dir, check_seed, check_types
from rotation.configs import config_resuming_in_out, from_jsonable, save_config, to_jsonable
from rotation.interrupt import SIGNAL_NAMES, Interrupted
from rotation.policy.bundle import load_bundle
from rotation.tactile.encoders import parse_groups
from rotation.train.runs import (
    CurveLog,
    DamagedCheckpoint,
    check_run_dir,
    clear_outputs,
    config_differences,
    refuse_differences,
    save_atomically,
    summary_writer,
    with_fallback,
)

CHECKPOINT_GLOB = "ckpt_*.pt"
RUN_OUTPUTS = ("config.json", "bundle", "curves.jsonl", "tb")
RESUMABLE_CHANGES = {"out", "total_steps", "epochs", "resume", "progress", "torch_threads", "nthread", "overwrite"}


def hard_randomization() -> RandomizationConfig:
    """The training randomization: the env's, with friction reaching 4x lower and mass 0.2 kg heavier."""
    return RandomizationConfig(friction=(0.075, 1.5), mass=(0.05, 0.45))


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
    runs with 4, which kept more cups: docs/results/adapter/tried_touch4)."""
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
    (adapters.refit_head; simulation only)."""
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
            self.env = dataclasses.replace(self.env, **needs)
        if self.resume and self.overwrite:
            raise ValueError("--resume continues the run in --out and --overwrite deletes it: give one of them")
        self.sessions = tuple(Path(p) for p in self.sessions)
        check_int("epochs", self.epochs, 1, 10**6)
        check_int("sample_every", self.sample_every, 1, 10**6)
        check_number("val_fraction", self.val_fraction, 0.0, 1.0, high_open=True)
        if self.sessions and self.touch_kind == "skin":
            raise ValueError("--sessions trains Digit 360 adapters (imu, pressure); recorded skin sessions lack the "
                             "taxel positions the skin encoder reads (docs/skin.md): train a skin adapter in "
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


@dataclass
class Result:
    bundle_dir: Path
    history: list[dict[str, float]]


class TokenBuffer:
    """A ring buffer of samples: per fingertip and token group (S, N_g, D) float16 tokens, phi's z, the target z,
    the student actor's proprioceptive input (for the action-matching loss) and the joint tracking features (width
    ``track`` 0 for an adapter that reads none)."""

    def __init__(self, capacity: int, samples: tuple[str, ...], groups: dict[str, int], width: int, latent: int,
                 proprio: int, track: int = 0):
        self.capacity, self.samples, self.size, self.next = capacity, samples, 0, 0
        self.tokens = {g: torch.zeros(capacity, len(samples), n, width, dtype=torch.float16) for g, n in groups.items()}
        self.z_student = torch.zeros(capacity, latent)
        self.z_teacher = torch.zeros(capacity, latent)
        self.proprio = torch.zeros(capacity, proprio)
        self.track = torch.zeros(capacity, track)

    def clear(self) -> None:
        self.size = self.next = 0

    def add(self, tokens: dict[str, dict[str, torch.Tensor]], z_student: torch.Tensor, z_teacher: torch.Tensor,
            proprio: torch.Tensor, track: torch.Tensor | None = None) -> None:
        n = z_student.shape[0]
        idx = (self.next + torch.arange(n)) % self.capacity
        if track is not None and track.shape[-1]:
            self.track[idx] = track
        for g, store in self.tokens.items():
            store[idx] = torch.stack([tokens[s][g] for s in self.samples], dim=1).to(torch.float16)  # (n, S, N, D)
        self.z_student[idx], self.z_teacher[idx], self.proprio[idx] = z_student, z_teacher, proprio
        self.next = int((self.next + n) % self.capacity)
        self.size = min(self.capacity, self.size + n)

    def batch(self, idx: torch.Tensor) -> Sample:
        toks = {s: {g: store[idx, i].float() for g, store in self.tokens.items()} for i, s in enumerate(self.samples)}
        return Sample(toks, self.z_student[idx], self.z_teacher[idx], self.proprio[idx], self.track[idx])


@dataclass
class Sample:
    """A minibatch of a TokenBuffer."""

    tokens: dict[str, dict[str, torch.Tensor]]
    z_student: torch.Tensor
    z_teacher: torch.Tensor
    proprio: torch.Tensor
    track: torch.Tensor


def _latest(out: Path) -> Path | None:
    ckpts = sorted(out.glob(CHECKPOINT_GLOB))
    return ckpts[-1] if ckpts else None


def _load_checkpoint(path: Path) -> dict[str, Any]:
    try:
        ckpt = torch.load(path, map_location="cpu", weights_only=True)
    except (RuntimeError, EOFError, OSError, pickle.UnpicklingError, zipfile.BadZipFile) as err:
        raise DamagedCheckpoint(f"{path} cannot be read ({type(err).__name__})") from None
    keys = {"adapter", "optim", "iteration", "student_sha256"}
    if not isinstance(ckpt, dict) or not keys <= set(ckpt):
        raise ValueError(f"{path} is not a finetune-adapter checkpoint (expected the entries {sorted(keys)})")
    return ckpt


@dataclass
class Job:
    """What both training paths (simulation, recorded sessions) share: the checked config, the frozen teacher, the
    student with its fresh (or resumed) adapter and optimizer, and the run directory's outputs."""

    cfg: Config
    out: Path
    checkpoints: list[str]
    """Checkpoint files of an earlier run in ``out`` (deleted with the other outputs by --overwrite)."""
    teacher: Any
    policy: Any
    """adapters.bundle.AdaptedPolicy: the frozen student and encoder, and the adapter that learns."""
    optim: torch.optim.Optimizer
    student_sha: str
    start: int = 0
    """Iteration (simulation: env steps / num_envs; sessions: epochs) of the checkpoint resumed from."""
    wall_before: float = 0.0
    """Wall time (s) of the run before the resumed checkpoint."""
    anchor: torch.nn.Module | None = None
    """The frozen ``cfg.anchor`` adapter, or None."""
    tracking_norm_needed: bool = False
    """The adapter reads joint tracking whose normalization is still to be measured (a fresh one, or one started
    from an adapter without it)."""
    t_start: float = field(default_factory=time.perf_counter)

    @classmethod
    def start_from(cls, cfg: Config) -> Job:
        """Load and check the models and resume the adapter; nothing in ``cfg.out`` is written yet."""
        out = Path(cfg.out)
        checkpoints = sorted(p.name for p in out.glob(CHECKPOINT_GLOB))
        check_run_dir(out, (*RUN_OUTPUTS, *checkpoints), overwrite=cfg.overwrite, resuming_here=cfg.resume,
                      resume_hint="pass --resume to continue it")
        torch.set_num_threads(cfg.torch_threads)
        teacher = load_bundle(cfg.teacher).require("privileged", f"--teacher {cfg.teacher}")
        modalities = parse_groups(cfg.modalities, cfg.touch_kind)
        policy = build_adapted(cfg.student, cfg.encoder, modalities, touch_every=cfg.touch_every, hidden=cfg.hidden,
                               seed=cfg.seed, tracking=cfg.tracking)
        if teacher.config.latent_dim != policy.config.latent_dim:
            raise ValueError(f"the teacher's latent size {teacher.config.latent_dim} differs from the student's "
                             f"{policy.config.latent_dim}: give the student's own teacher")
        if not cfg.sessions and policy.student.config.control_hz != cfg.env.control_hz:
            raise ValueError(f"env: control_hz {cfg.env.control_hz} differs from the student's "
                             f"{policy.student.config.control_hz}")
        anchor = None
        if cfg.anchor:  # a frozen copy of the adapter's network with the anchor's weights
            anchor = copy.deepcopy(policy.adapter)
            anchor.load_state_dict(_compatible_weights(policy, cfg.anchor, "anchor"), strict=True)
            anchor.requires_grad_(False).eval()
        norm_needed = cfg.tracking
        if cfg.init_from:
            policy.adapter.load_state_dict(_compatible_weights(policy, cfg.init_from, "init_from"), strict=True)
            norm_needed = cfg.tracking and not read_adapter(cfg.init_from)[1].net.tracking
        student_sha = file_digest(student_weights(cfg.student))
        job = cls(cfg, out, checkpoints, teacher, policy, torch.optim.Adam(policy.adapter.parameters(), lr=cfg.lr),
                  student_sha, anchor=anchor, tracking_norm_needed=norm_needed)
        if cfg.resume:
            job._resume()
        return job

    def _resume(self) -> None:
        out = self.out
        path = _latest(out)
        if path is None or not (out / "config.json").is_file():
            raise ValueError(f"--resume: no checkpoint ({CHECKPOINT_GLOB}) and config.json in {out}")
        diffs = config_differences(json.loads((out / "config.json").read_text()), to_jsonable(self.cfg),
                                   RESUMABLE_CHANGES)
        refuse_differences(diffs, str(out / "config.json"), RESUMABLE_CHANGES)
        older = sorted(out.glob(CHECKPOINT_GLOB), reverse=True)[1:]
        ckpt, path = with_fallback(path, older, _load_checkpoint)
        if ckpt["student_sha256"] != self.student_sha:
            raise ValueError(f"--resume: {path} was trained for another student (weights {ckpt['student_sha256']}, "
                             f"this student {self.student_sha})")
        self.policy.adapter.load_state_dict(ckpt["adapter"])
        self.tracking_norm_needed = False  # the checkpoint holds the run's normalization
        self.optim.load_state_dict(ckpt["optim"])
        self.start = int(ckpt["iteration"])
        self.wall_before = float(ckpt.get("wall_time_s", 0.0))

    def open_outputs(self, key: str, trim_to: int) -> tuple[CurveLog, Any]:
        """Start writing ``out`` (after every check passed): --overwrite's deletion, config.json, curves.jsonl
        (rows logged after ``trim_to`` of a resumed run dropped; ``key`` its step field) and the TensorBoard writer."""
        if self.cfg.overwrite:
            removed = clear_outputs(self.out, (*RUN_OUTPUTS, *self.checkpoints))
            if removed:
                print(f"finetune-adapter: --overwrite deleted {', '.join(removed)} in {self.out}")
        save_config(self.cfg, self.out / "config.json")
        curves = CurveLog(self.out / "curves.jsonl", key=key)
        curves.trim(trim_to)
        return curves, summary_writer(self.out / "tb", purge_step=trim_to)

    @property
    def wall_time_s(self) -> float:
        return self.wall_before + time.perf_counter() - self.t_start

    def checkpoint(self, iteration: int) -> None:
        _save_checkpoint(self.out, self.policy.adapter, self.optim, iteration, self.student_sha, self.wall_time_s)

    def finish(self, card: dict[str, Any], history: list[dict[str, float]], signum: int | None, done: str,
               of: str, after_stop: str = "saved the checkpoint and the bundle at {}; continue with --resume"
               ) -> Result:
        """Save the adapter bundle with ``card`` (plus the common entries); raise Interrupted after a signal, saying
        ``after_stop`` (formatted with the bundle directory). ``done`` / ``of``: how far it got and the total (e.g.
        '384 env steps' / '768')."""
        card = {"kind": "adapter", "trained_by": "rotate finetune-adapter", **card,
                "wall_time_s": round(self.wall_time_s, 1), "teacher": self.cfg.teacher, "config": to_jsonable(self.cfg)}
        if signum:
            card["interrupted"] = f"stopped by {SIGNAL_NAMES.get(signum, signum)} at {done}"
        policy = self.policy
        policy.adapter_config = dataclasses.replace(policy.adapter_config, card=card)
        bundle_dir = policy.save(self.out / "bundle")
        if signum:
            message = (f"finetune-adapter: interrupted by {SIGNAL_NAMES.get(signum, signum)} at {done} of {of}; "
                       + after_stop.format(bundle_dir))
            print(message)
            raise Interrupted(signum, message)
        print(f"finetune-adapter: {done}; adapter bundle at {bundle_dir}")
        return Result(bundle_dir, history)


def _compatible_weights(policy: Any, name: str, option: str) -> dict[str, torch.Tensor]:
    """The adapter weights of the bundle ``name`` (for ``option``), checked to fit ``policy``'s adapter: the same
    encoder, modalities and network (it may name another student)."""
    try:
        path, other, weights = read_adapter(name)
    except ValueError as err:
        raise ValueError(f"{option}: {err}") from None
    want = policy.adapter_config
    if option == "init_from" and want.net.tracking and not other.net.tracking and \
            dataclasses.replace(other.net, tracking=True) == want.net:
        weights = padded_for_tracking(weights, policy.adapter)
        other = dataclasses.replace(other, net=want.net)
    if other.encoder_sha256 != want.encoder_sha256 or other.net != want.net:
        raise ValueError(f"{option}: adapter {path} reads encoder {other.encoder!r} ({other.encoder_sha256}) "
                         f"with modalities {list(other.modalities)} and network {to_jsonable(other.net)}; this "
                         f"run has {want.encoder!r} ({want.encoder_sha256}), {list(want.modalities)}, "
                         f"{to_jsonable(want.net)}")
    return weights


def padded_for_tracking(weights: dict[str, torch.Tensor], adapter: torch.nn.Module) -> dict[str, torch.Tensor]:
    """The weights of an adapter without joint tracking made to fit ``adapter`` (the same network with it): zero
    input weights on the tracking features in g's first layer, and ``adapter``'s own (yet unmeasured) normalization,
    so the padded adapter gives the same corrections as the original."""
    out = dict(weights)
    state = adapter.state_dict()
    first = "g.0.weight"
    w, want = weights[first], state[first]
    if w.shape[0] != want.shape[0] or w.shape[1] + adapter.tracking_dim != want.shape[1]:
        raise ValueError(f"init_from: g's first layer {tuple(w.shape)} does not fit {tuple(want.shape)} less the "
                         "tracking features")
    out[first] = torch.cat([w, w.new_zeros(w.shape[0], adapter.tracking_dim)], dim=1)
    out["track_mean"], out["track_std"] = state["track_mean"].clone(), state["track_std"].clone()
    return out


def config_from_args(args) -> Config:
    """The command line's config; with --resume, the options it leaves out are the run's in --out."""
    return config_resuming_in_out(Config, args)


def run(cfg: Config) -> Result:
    """Fine-tune the adapter, in simulation or (``cfg.sessions``) on recorded sessions; returns the bundle directory
    and the logged history. Everything is checked before anything in `out` is written."""
    job = Job.start_from(cfg)
    if cfg.sessions:
        from adapters.finetune_sessions import train_on_sessions

        return train_on_sessions(job)
    if cfg.refit_head:
        from adapters.refit_head import refit_in_sim

        return refit_in_sim(job)
    from adapters.finetune_sim import train_in_sim

    return train_in_sim(job)


def adam_step(adapter: torch.nn.Module, optim: torch.optim.Optimizer, batch: Sample, head: Any,
              action_weight: float = 0.0) -> float:
    """One Adam step on MSE(phi + adapter(tokens, phi), z_teacher), plus with ``action_weight`` > 0
    ``action_weight`` x MSE(head(proprio, that latent), head(proprio, z_teacher)) where ``head`` is the frozen
    student's :meth:`ActorNet.head <rotation.policy.bundle.ActorNet.head>`; returns the loss."""
    z = batch.z_student + adapter(batch.tokens, batch.z_student, batch.track)
    loss = torch.nn.functional.mse_loss(z, batch.z_teacher)
    if action_weight > 0.0:
        with torch.no_grad():
            target = head(batch.proprio, batch.z_teacher)
        loss = loss + action_weight * torch.nn.functional.mse_loss(head(batch.proprio, z), target)
    optim.zero_grad(set_to_none=True)
    loss.backward()
    optim.step()
    return loss.item()


@torch.no_grad()
def errors_to_teacher(head: Any, proprio: torch.Tensor, z_adapted: torch.Tensor, z_student: torch.Tensor,
                      z_teacher: torch.Tensor) -> dict[str, float]:
    """Mean squared errors over a batch: of the adapted and the student's latent against the teacher's z
    (``latent_mse``, ``student_mse``), and of the student actor's action means on them (``head``, the frozen
    student's ActorNet.head) against its action on the teacher's z (``action_mse``, ``student_action_mse``)."""
    target = head(proprio, z_teacher)
    return {"latent_mse": float(((z_adapted - z_teacher) ** 2).mean()),
            "student_mse": float(((z_student - z_teacher) ** 2).mean()),
            "action_mse": float(((head(proprio, z_adapted) - target) ** 2).mean()),
            "student_action_mse": float(((head(proprio, z_student) - target) ** 2).mean())}


def _save_checkpoint(out: Path, adapter: torch.nn.Module, optim: torch.optim.Optimizer, iteration: int,
                     student_sha: str, wall_time_s: float) -> None:
    state = {k: v.detach().cpu() for k, v in adapter.state_dict().items()}
    save_atomically(lambda tmp: torch.save({"adapter": state, "optim": optim.state_dict(), "iteration": iteration,
                                            "student_sha256": student_sha, "wall_time_s": wall_time_s}, tmp),
                    out / f"ckpt_{iteration:09d}.pt")


_TB_TAGS = {"latent_mse": "adapter/latent_mse", "student_mse": "adapter/student_latent_mse",
            "train_loss": "adapter/train_loss", "rotation_rate": "rollout/rotation_rate", "ttf": "rollout/ttf",
            "ep_length": "rollout/episode_length", "steps_per_s": "time/steps_per_s",
            "val_latent_mse": "adapter/val_latent_mse", "val_student_mse": "adapter/val_student_latent_mse",
            "samples_per_s": "time/samples_per_s", "action_mse": "adapter/action_mse",
            "student_action_mse": "adapter/student_action_mse", "val_action_mse": "adapter/val_action_mse",
            "val_student_action_mse": "adapter/val_student_action_mse"}


def log_point(writer, point: dict[str, float], step_key: str) -> None:
    for key, tag in _TB_TAGS.items():
        if key in point:
            writer.add_scalar(tag, point[key], global_step=int(point[step_key]))


def load_config(path: str | Path) -> Config:
    return from_jsonable(Config, json.loads(Path(path).read_text()))
