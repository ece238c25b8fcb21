"""What the three paths of `rotate finetune-adapter` (adapters.finetune.sim, .sessions, .refit) share: the job
(checked config, frozen teacher, the student with the adapter that learns, its optimizer and run directory),
the buffer of cached token samples, one Adam step, the errors to the teacher, checkpoints and logging.
"""

from __future__ import annotations

import copy
import dataclasses
import json
import pickle
import time
import zipfile
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import torch

from adapters.bundle import build_adapted
from adapters.bundle_config import file_digest, read_adapter, student_weights
from adapters.finetune.config import CHECKPOINT_GLOB, RESUMABLE_CHANGES, RUN_OUTPUTS, Config
from envs.errors import RequestRefused
from rotation.configs import save_config, to_jsonable
from rotation.interrupt import SIGNAL_NAMES, Interrupted
from rotation.policy.bundle import load_policy_bundle
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
    with_fallback,
)
from rotation.tactile.models.encoders import parse_groups


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
    owner: str | None = None
    """The run's id (rotation.runs.run_id), carried by every checkpoint; None in a folder from before run ids."""
    t_start: float = field(default_factory=time.perf_counter)

    @classmethod
    def start_from(cls, cfg: Config) -> Job:
        """Load and check the models and resume the adapter; nothing in ``cfg.out`` is written yet."""
        out = Path(cfg.out)
        checkpoints = sorted(p.name for p in out.glob(CHECKPOINT_GLOB))
        check_run_dir(out, (*RUN_OUTPUTS, *checkpoints), overwrite=cfg.overwrite, resuming_here=cfg.resume,
                      resume_hint="pass --resume to continue it")
        torch.set_num_threads(cfg.torch_threads)
        teacher = load_policy_bundle(cfg.teacher).require("privileged", f"--teacher {cfg.teacher}")
        modalities = parse_groups(cfg.modalities, cfg.touch_kind)
        policy = build_adapted(cfg.student, cfg.encoder, modalities, touch_every=cfg.touch_every, hidden=cfg.hidden,
                               seed=cfg.seed, tracking=cfg.tracking, touch=not cfg.blind_touch)
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
            raise RequestRefused(f"--resume: no checkpoint ({CHECKPOINT_GLOB}) and config.json in {out}")
        diffs = config_differences(json.loads((out / "config.json").read_text()), to_jsonable(self.cfg),
                                   RESUMABLE_CHANGES)
        refuse_differences(diffs, str(out / "config.json"), RESUMABLE_CHANGES)
        older = sorted(out.glob(CHECKPOINT_GLOB), reverse=True)[1:]
        ckpt, path = with_fallback(path, older, _load_checkpoint)
        self.owner = run_id(out, create=False)  # a folder from before run ids: None, its checkpoints as before
        if self.owner is not None and ckpt.get("run_id") != self.owner:
            raise RequestRefused(f"--resume: {path} is not a checkpoint this run wrote (another run's, or no record "
                                 "of which); move it away, or resume the run it belongs to")
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
        if not self.cfg.resume:
            self.owner = run_id(self.out, create=True)  # every checkpoint of this run carries it
        curves = CurveLog(self.out / "curves.jsonl", key=key)
        curves.trim(trim_to)
        return curves, summary_writer(self.out / "tb", purge_step=trim_to)

    @property
    def wall_time_s(self) -> float:
        return self.wall_before + time.perf_counter() - self.t_start

    def checkpoint(self, iteration: int) -> None:
        _save_checkpoint(self.out, self.policy.adapter, self.optim, iteration, self.student_sha, self.wall_time_s,
                         self.owner)

    def finish(self, card: dict[str, Any], history: list[dict[str, float]], signum: int | None, done: str,
               of: str, after_stop: str = "saved the checkpoint and the bundle at {}; continue with --resume"
               ) -> Result:
        """Save the adapter bundle with ``card`` (plus the common entries); raise Interrupted after a signal, saying
        ``after_stop`` (formatted with the bundle directory). ``done`` / ``of``: how far it got and the total (e.g.
        '384 env steps' / '768')."""
        card = {"kind": "adapter", "trained_by": "rotate finetune-adapter", **card,
                "touch_delay": self.cfg.delay.describe(1.0 / self.cfg.env.control_dt),
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


def adam_step(adapter: torch.nn.Module, optim: torch.optim.Optimizer, batch: Sample, head: Any,
              action_weight: float = 0.0) -> float:
    """One Adam step on MSE(phi + adapter(tokens, phi), z_teacher), plus with ``action_weight`` > 0
    ``action_weight`` x MSE(head(proprio, that latent), head(proprio, z_teacher)) where ``head`` is the frozen
    student's :meth:`ActorNet.head <rotation.policy.actor.ActorNet.head>`; returns the loss."""
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
                     student_sha: str, wall_time_s: float, owner: str | None = None) -> None:
    state = {k: v.detach().cpu() for k, v in adapter.state_dict().items()}
    save_atomically(lambda tmp: torch.save({"adapter": state, "optim": optim.state_dict(), "iteration": iteration,
                                            "student_sha256": student_sha, "wall_time_s": wall_time_s,
                                            "run_id": owner}, tmp),
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
