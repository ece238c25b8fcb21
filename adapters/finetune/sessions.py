"""The recorded-session path of `rotate finetune-adapter` (adapters.finetune.job with ``--sessions``).

1. Every session is checked before anything is read or written (adapters.session_checks.check_sessions: streams,
   measured properties, control rate, one hand), then the files are split into training and validation sessions
   (rotation.data.dataset.split_sessions, by file, under the seed).
2. Each session's samples (adapters.real_data.session_samples) are encoded once by the frozen encoder into a
   TokenBuffer (tokens float16, phi's z, the teacher's z), as the simulation path caches its rollouts.
3. ``epochs`` passes of shuffled minibatch Adam steps on MSE(phi + adapter, z_teacher) (plus the action-matching
   term with ``action_weight``) over the training samples. After each pass the adapted latent's MSE on the training
   and validation samples is logged beside the student's own (``latent_mse`` / ``student_mse``, ``val_latent_mse``
   / ``val_student_mse``; epoch 0 is the untrained adapter, i.e. the student), and so are the errors of the actions
   they give (``action_mse`` / ``student_action_mse``, and ``val_``), and a checkpoint is written. Epoch e draws its
   minibatch order from ``seed + e``, so a resumed run is bit-identical to an uninterrupted one. Ctrl-C / SIGTERM
   stop after the current epoch; a second signal stops at once and keeps the last finished epoch.
"""

from __future__ import annotations

import math
import signal
import time
from collections.abc import Sequence
from typing import Any

import torch
from tqdm import tqdm

from adapters.bundle import TouchUnavailable
from adapters.finetune.core import Job, Result, TokenBuffer, adam_step, errors_to_teacher, log_point
from adapters.real_data import session_samples
from adapters.session_checks import SessionInfo, check_sessions, session_files
from envs.errors import RequestRefused
from rotation.data.dataset import split_sessions
from rotation.data.session import SessionError
from rotation.interrupt import StopSignals, end_loop

ENCODE_BATCH = 64
"""Samples per frozen-encoder call while caching the tokens."""
EVAL_BATCH = 512
"""Samples per adapter call while measuring the latent errors."""


def train_on_sessions(job: Job) -> Result:
    """Train ``job``'s adapter on ``job.cfg.sessions`` (the module docstring); returns the bundle and the history."""
    cfg, policy = job.cfg, job.policy
    adapter = policy.adapter
    files = session_files(cfg.sessions)
    infos = {i.path: i for i in check_sessions(files, policy.fingers, policy.windows,
                                               policy.student.config.control_hz, cfg.position)}
    train_files, val_files = split_sessions(files, cfg.val_fraction, cfg.seed)
    train = encode_sessions(job, [infos[p] for p in train_files], "training")
    val = encode_sessions(job, [infos[p] for p in val_files], "validation") if val_files else None
    if train.size == 0:
        raise RequestRefused(f"sessions: no usable samples in the training sessions {[str(p) for p in train_files]} "
                             "(each needs more than the 1.1 s of touch history the windows span)")
    if job.tracking_norm_needed:  # the joint tracking's normalization, from the training samples
        track = train.track[:train.size]
        adapter.set_tracking_norm(track.mean(0), track.std(0) if train.size > 1 else torch.ones(track.shape[1]))
        job.tracking_norm_needed = False

    curves, writer = job.open_outputs("epoch", job.start)
    batches = math.ceil(train.size / cfg.batch_size)
    history: list[dict[str, float]] = []
    if job.start == 0:  # epoch 0: the untrained adapter (exactly the student)
        history.append(_point(0, 0, train, val, adapter, policy.student.net.head))
        log_point(writer, history[-1], "epoch")
    bar = tqdm(total=cfg.epochs * batches, initial=job.start * batches, unit="step", disable=not cfg.progress,
               desc="finetune-adapter", dynamic_ncols=True)
    gen = torch.Generator()
    done, flushed, signum = job.start, 0, None
    kept = {k: v.clone() for k, v in adapter.state_dict().items()}
    stop = StopSignals()
    try:
        stop.__enter__()
        for epoch in range(job.start, cfg.epochs):
            kept = {k: v.clone() for k, v in adapter.state_dict().items()}  # a second signal goes back to here
            t0 = time.perf_counter()
            order = torch.randperm(train.size, generator=gen.manual_seed(cfg.seed + epoch))
            adapter.train()
            loss = 0.0
            for b in range(batches):
                loss += adam_step(adapter, job.optim, train.batch(order[b * cfg.batch_size:(b + 1) * cfg.batch_size]),
                                  policy.student.net.head, cfg.action_weight)
                bar.update(1)
            adapter.eval()
            point = _point(epoch + 1, (epoch + 1) * batches, train, val, adapter, policy.student.net.head)
            point.update(train_loss=loss / batches, samples_per_s=train.size / max(time.perf_counter() - t0, 1e-9))
            log_point(writer, point, "epoch")
            history.append(point)
            bar.set_postfix({k: f"{point[k]:.4f}" for k in ("latent_mse", "val_latent_mse", "val_student_mse")
                             if k in point})
            done = epoch + 1
            job.checkpoint(done)
            curves.append(history[flushed:])
            flushed = len(history)
            if stop.requested:
                break
    except KeyboardInterrupt as err:  # a second signal: drop the unfinished epoch, keep its checkpointed start
        signum = getattr(err, "signum", signal.SIGINT)
        adapter.load_state_dict(kept)
        curves.append(history[flushed:])
    finally:
        end_loop(stop, bar, writer)
    signum = signum or stop.signum

    card = {"epochs": done, "samples": train.size, "val_samples": val.size if val is not None else 0,
            "sessions": [str(p) for p in train_files], "val_sessions": [str(p) for p in val_files],
            "position": cfg.position}
    if history:
        last = history[-1]
        card.update(final_latent_mse=last.get("val_latent_mse", last["latent_mse"]),
                    final_student_mse=last.get("val_student_mse", last["student_mse"]),
                    final_train_latent_mse=last["latent_mse"], final_train_student_mse=last["student_mse"])
    return job.finish(card, history, signum, f"{done} epochs on {train.size} samples", str(cfg.epochs))


def encode_sessions(job: Job, infos: Sequence[SessionInfo], what: str) -> TokenBuffer:
    """The samples of ``infos`` encoded once: a TokenBuffer holding all of them (the encoder's tokens in float16,
    phi's z from the rebuilt history, the teacher's z from the measured properties)."""
    cfg, policy = job.cfg, job.policy
    adapter = policy.adapter
    encoder = job.teacher.net.extractor.encoder
    parts = []
    for info in tqdm(infos, unit="session", desc=f"finetune-adapter: encoding {what} sessions",
                     disable=not cfg.progress, dynamic_ncols=True):
        s = session_samples(info, encoder, policy.student_latent, policy.fingers, policy.windows, cfg.sample_every,
                            cfg.position)
        if len(s) == 0:
            print(f"finetune-adapter: warning: session {info.path} has no step with usable touch (shorter than the "
                  "windows, or its sensors stalled); skipped")
        for i in range(0, len(s), ENCODE_BATCH):
            rows = slice(i, i + ENCODE_BATCH)
            windows = {f: {w: x[rows] for w, x in d.items()} for f, d in s.windows.items()}
            try:
                tokens = policy.tokens(windows)
            except TouchUnavailable as err:
                raise SessionError(f"session {info.path}: its touch windows cannot be encoded ({err})") from None
            tokens = {f: {g: t.half() for g, t in d.items()} for f, d in tokens.items()}
            obs = {g: x[rows] for g, x in s.obs.items()}
            parts.append((tokens, torch.as_tensor(s.z_student[rows]), torch.as_tensor(s.z[rows]),
                          policy.proprio_features(obs), policy.tracking(obs)))
    interface = adapter.interface
    buf = TokenBuffer(max(1, sum(len(p[1]) for p in parts)), adapter.cfg.samples, interface.counts, interface.width,
                      adapter.cfg.latent_dim, policy.proprio_dim, adapter.tracking_dim)
    for part in parts:
        buf.add(*part)
    return buf


@torch.no_grad()
def latent_errors(adapter: torch.nn.Module, buf: TokenBuffer, head: Any) -> dict[str, float]:
    """adapters.finetune.job.errors_to_teacher over every sample of ``buf`` (phi + adapter as the adapted latent)."""
    sums = dict.fromkeys(("latent_mse", "student_mse", "action_mse", "student_action_mse"), 0.0)
    for i in range(0, buf.size, EVAL_BATCH):
        b = buf.batch(torch.arange(i, min(i + EVAL_BATCH, buf.size)))
        z = b.z_student + adapter(b.tokens, b.z_student, b.track)
        for key, value in errors_to_teacher(head, b.proprio, z, b.z_student, b.z_teacher).items():
            sums[key] += value * len(b.z_student)
    return {k: v / max(buf.size, 1) for k, v in sums.items()}


def _point(epoch: int, updates: int, train: TokenBuffer, val: TokenBuffer | None, adapter: torch.nn.Module,
           head: Any) -> dict[str, float]:
    point: dict[str, float] = {"epoch": epoch, "updates": updates, **latent_errors(adapter, train, head)}
    if val is not None and val.size:
        point.update({f"val_{k}": v for k, v in latent_errors(adapter, val, head).items()})
    return point
