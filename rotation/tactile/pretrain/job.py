"""Pretrain a touch encoder by self-distillation (block-masked token views, EMA teacher): Sparsh-X or Sparsh-skin.

    rotate cache-touch --sessions data/touch --out data/touch_cache --workers 8       # render windows once
    rotate pretrain --sessions data/touch --cache data/touch_cache --size tiny --steps 20000 --out runs/pretrain
    rotate pretrain --sessions data/touch --cache data/touch_cache --out runs/pretrain --resume
    rotate pretrain ... --nproc-per-node 4                   # 4 GPUs of this machine (DDP through torchrun)
    rotate pretrain ... --nnodes 2 --node-rank 0 --master-addr 10.0.0.1 --nproc-per-node 8   # on each node
    rotate pretrain --encoder skin --sessions data/skin --size tiny --weight-decay 0.04 --weight-decay-end 0.4 \
        --out runs/pretrain_skin                             # Sparsh-skin on sessions with skin/xela

What a step computes is the encoder's objective (rotation.tactile.pretrain.objectives): for Sparsh-X, per token
set (modality) one global and four local block-masked views, the teacher (EMA of the student) on the global view,
the student on every view, the DINO loss on their register tokens through a shared projection head, one center
per set (docs/reference/sparsh.md "Sparsh-X self-supervised pretraining"); for Sparsh-skin, two global and eight local
blocks over the taxel order, DINO + iBOT (masked taxels) + KoLeo (docs/reference/sparsh.md "Sparsh-skin"). The loop is
shared: AdamW with a warm-up + cosine learning rate, no weight decay on 1-D parameters, gradient clipping;
bfloat16 autocast on a GPU. Every schedule is a function of the step and every random draw (masks, drop path,
batch order) is seeded by it, so ``--resume`` continues bit-identically (on the same device).

OUT holds config.json, ckpt_<step>.safetensors (the newest few: student, teacher, head, optimizer state, centers,
step), encoder.safetensors (the teacher's encoder at the last checkpoint: what `rotate probe` and the tactile
adapter load), tb/ (TensorBoard) and, after a distributed run, ranks.json (a digest of every rank's weights).
With ``--cache`` windows come from pre-rendered shards (rotation.data.window_cache; missing sessions are rendered
first), else they are rendered on the fly (about 160 windows/s per loader worker). Skin windows are read from the
sessions directly (rotation.data.skin.SkinWindows; no cache).
"""

from __future__ import annotations

import contextlib
import copy
import json
import logging
import os
import subprocess
import sys
import time
from pathlib import Path
from typing import Any

import torch
import torch.distributed as dist
from tqdm import tqdm

from envs.errors import JobFailed, RequestRefused
from rotation.configs import from_jsonable, save_config, to_jsonable
from rotation.interrupt import Interrupted, StopSignals
from rotation.runs import run_id, summary_writer
from rotation.tactile.loading import open_encoder_windows, session_paths, step_loader, to_device
from rotation.tactile.models.encoders import encoder_kind
from rotation.tactile.pretrain.config import RESUMABLE_CHANGES, Config, load_config
from rotation.tactile.pretrain.log import StepLog, log_point
from rotation.tactile.pretrain.objectives import OBJECTIVES, Objective, SkinObjectiveConfig
from rotation.tactile.pretrain.state import checkpoint_run_id, latest_checkpoint, load_checkpoint, save_checkpoint
from rotation.tactile.runtime import (
    Processes,
    any_true,
    autocast,
    init_processes,
    resolve_device,
    state_digest,
    step_seed,
    use_bf16,
)
from rotation.tactile.ssl import (
    DINOHead,
    cosine,
    ema_momentum,
    ema_update,
    param_groups,
    set_hyperparameters,
    step_rng,
    teacher_entropy,
    teacher_temperature,
    warmup_cosine,
)

__all__ = ["Config", "SkinObjectiveConfig", "build", "load_config", "objective", "run", "train"]
WORKER_ENV = "ROTATE_PRETRAIN_WORKER"
"""Set in the processes torchrun starts, so they train instead of launching again."""

log = logging.getLogger(__name__)


def run(cfg: Config) -> dict[str, Any]:
    """Pretrain (or, with nproc_per_node / nnodes > 1, launch torchrun to do it); returns a summary dict."""
    if (cfg.nproc_per_node > 1 or cfg.nnodes > 1) and os.environ.get(WORKER_ENV) != "1":
        return launch(cfg)
    return train(cfg)


# ------------------------------------------------------------------------------------------ distributed launch
def launch(cfg: Config) -> dict[str, Any]:
    """Run this job in ``nproc_per_node`` processes per machine through torchrun (``python -m
    torch.distributed.run``), each training with DistributedDataParallel; returns when they finish."""
    if cfg.cache is not None:  # render missing windows once, here, rather than racing in every process
        open_encoder_windows(cfg.encoder, session_paths(cfg.sessions), cfg.cache, cfg.fingers, cfg.stride,
                             progress=cfg.progress, workers=cfg.num_workers)
    out = Path(cfg.out)
    out.mkdir(parents=True, exist_ok=True)
    spec = out / f"launch_node{cfg.node_rank}.json"
    spec.write_text(json.dumps(to_jsonable(cfg), indent=2) + "\n")
    cmd = [sys.executable, "-m", "torch.distributed.run", f"--nproc-per-node={cfg.nproc_per_node}",
           f"--nnodes={cfg.nnodes}"]
    if cfg.nnodes == 1 and not cfg.master_addr:
        cmd.append("--standalone")  # a free local port, no rendezvous server to set up
    else:
        cmd += [f"--node-rank={cfg.node_rank}", f"--master-addr={cfg.master_addr or '127.0.0.1'}",
                f"--master-port={cfg.master_port}"]
    cmd += ["-m", "rotation.tactile.pretrain.job", "--worker", str(spec)]
    env = {**os.environ, WORKER_ENV: "1"}
    if cfg.torch_threads is None and "OMP_NUM_THREADS" not in env:
        env["OMP_NUM_THREADS"] = str(max(1, (os.cpu_count() or 1) // cfg.nproc_per_node))
    proc = subprocess.Popen(cmd, env=env)
    with StopSignals():  # the workers get Ctrl-C too: they save and stop; wait for them (a second one raises)
        while proc.poll() is None:
            time.sleep(0.2)
    if proc.returncode != 0:
        print(f"pretrain: torchrun exited with status {proc.returncode}", file=sys.stderr)
    return {"exit_code": proc.returncode, "out": str(out)}


def _worker_main(argv: list[str]) -> int:
    """Entry point of a torchrun process: ``python -m rotation.tactile.pretrain.job --worker SPEC.json``."""
    if len(argv) != 2 or argv[0] != "--worker":
        print("usage: python -m rotation.tactile.pretrain.job --worker SPEC.json (started by `rotate pretrain`)",
              file=sys.stderr)
        return 2
    try:
        train(from_jsonable(Config, json.loads(Path(argv[1]).read_text())))
    except Interrupted as err:
        return err.exit_code
    except ValueError as err:
        print(f"rotate pretrain: error: {err}", file=sys.stderr)
        return 2
    return 0


# ----------------------------------------------------------------------------------------------- training
def _check_resumable(cfg: Config, out: Path) -> None:
    # the saved config read back as a Config: fields added since it was written take their defaults, and the token
    # groups are compared as groups ('' = all of them)
    saved_cfg = load_config(out / "config.json")
    saved, now = to_jsonable(saved_cfg), to_jsonable(cfg)
    saved["modalities"], now["modalities"] = list(saved_cfg.groups), list(cfg.groups)
    diff = sorted(k for k in now if k not in RESUMABLE_CHANGES and saved.get(k) != now[k])
    if diff:
        raise ValueError(f"--resume: the config differs from the one saved in {out / 'config.json'} in {diff}; "
                         f"only {sorted(RESUMABLE_CHANGES)} may change on resume")


def objective(cfg: Config) -> Objective:
    """The encoder's self-distillation objective (rotation.tactile.pretrain.objectives)."""
    return OBJECTIVES[cfg.encoder](cfg)


def build(cfg: Config) -> tuple[torch.nn.Module, torch.nn.Module]:
    """The freshly initialized student (encoder + head, seeded by ``cfg.seed``) and the loss of a run."""
    kind = encoder_kind(cfg.encoder)
    torch.manual_seed(cfg.seed)
    encoder = kind.build(cfg.size, cfg.groups, cfg.fusion, cfg.drop_path, (cfg.unimodal_layers, cfg.fusion_layers))
    spec = getattr(encoder, "cfg", None)
    if not getattr(spec, "fuses", True):  # a Sparsh-X that cannot fuse (the skin encoder has one token group)
        log.warning("pretrain: %d unimodal + %d %s fusion layer(s) fuse nothing: no modality's tokens will depend on "
                    "another's (a bottleneck needs 2 fusion layers; SparshXConfig.fuses)", spec.num_unimodal,
                    spec.num_fusion, spec.fusion)
    interface = encoder.token_interface
    hidden, prototypes = cfg.head_sizes()
    head = DINOHead(interface.width, hidden, cfg.head_bottleneck, prototypes)
    return objective(cfg).build(encoder, head, prototypes)


def train(cfg: Config) -> dict[str, Any]:
    """The training loop of one process (all of it without torchrun, one rank of it with)."""
    procs = init_processes(cfg.device)
    threads = torch.get_num_threads()
    if cfg.torch_threads:
        torch.set_num_threads(cfg.torch_threads)
    try:
        result = _train(cfg, procs)
        # every rank finished before any tears the group down: gloo can abort a process whose peer is still
        # sending when the group goes away ("terminate called without an active exception")
        procs.barrier()
        return result
    finally:
        torch.set_num_threads(threads)
        if procs.distributed and dist.is_initialized():
            dist.destroy_process_group()


def _train(cfg: Config, procs: Processes) -> dict[str, Any]:
    device = resolve_device(cfg.device, procs.local_rank)
    bf16 = use_bf16(cfg.precision, device)
    out = Path(cfg.out)
    kind = encoder_kind(cfg.encoder)

    # resume or start: decided before any file is written
    ckpt = latest_checkpoint(out)
    if cfg.resume:
        if ckpt is None or not (out / "config.json").is_file():
            raise RequestRefused(f"--resume: no checkpoint (ckpt_*.safetensors) and config.json in {out}")
        _check_resumable(cfg, out)
        owner = run_id(out, create=False)  # a folder from before run ids: None, its checkpoints as before
        if owner is not None and checkpoint_run_id(ckpt) != owner:
            raise RequestRefused(f"--resume: {ckpt} is not a checkpoint this run wrote (another run's, or no record "
                                 "of which); move it away, or resume the run it belongs to")
    elif ckpt is not None:
        raise ValueError(f"{out} already holds checkpoints; pass --resume to continue or choose another --out")

    paths = session_paths(cfg.sessions)
    if cfg.cache is not None and procs.main:
        open_encoder_windows(cfg.encoder, paths, cfg.cache, cfg.fingers, cfg.stride, progress=cfg.progress,
                             workers=cfg.num_workers)
    procs.barrier()
    windows = open_encoder_windows(cfg.encoder, paths, cfg.cache, cfg.fingers, cfg.stride, labels=(), build=False)

    goal = objective(cfg)
    student, loss_fn = build(cfg)
    encoder = student.encoder
    hidden, prototypes = cfg.head_sizes()
    grids = kind.grids(encoder)
    encoder_meta = {"kind": cfg.encoder, "config": to_jsonable(encoder.cfg)}
    if not cfg.resume and procs.main:  # broadcast to the other ranks below
        stats = encoder.fit_normalization(windows, max_windows=cfg.stats_windows, num_workers=cfg.num_workers,
                                          seed=cfg.seed)
        bad = [k for k, v in stats.items() if not bool(torch.isfinite(v).all())]
        if bad:
            raise ValueError(f"the input statistics {bad} fitted on {cfg.stats_windows} windows are not finite: "
                             f"some windows of {', '.join(map(str, cfg.sessions))} hold NaN or inf")
    student.to(device)
    loss_fn.to(device)
    teacher = copy.deepcopy(student)
    optimizer = torch.optim.AdamW(param_groups([student], cfg.weight_decay), lr=cfg.lr)
    start = 0
    if cfg.resume:
        assert ckpt is not None
        start = load_checkpoint(ckpt, student, teacher, loss_fn, optimizer, encoder_meta, kind.describe(encoder))
    model: torch.nn.Module = student
    if procs.distributed:
        from torch.nn.parallel import DistributedDataParallel

        for buf in student.buffers():  # rank 0's input statistics (DDP below copies only its parameters)
            dist.broadcast(buf, src=0)
        model = DistributedDataParallel(student, device_ids=[device] if device.type == "cuda" else None,
                                        broadcast_buffers=False)  # starts every rank from rank 0's parameters
        if not cfg.resume:
            teacher.load_state_dict(student.state_dict())
    teacher.eval().requires_grad_(False)
    student.train()
    owner = None
    if procs.main:
        save_config(cfg, out / "config.json")
        owner = run_id(out, create=not cfg.resume or run_id(out, create=False) is not None)
        print(f"pretrain: {kind.describe(encoder)}, {sum(p.numel() for p in encoder.parameters()):,} parameters; "
              f"head {hidden} -> {cfg.head_bottleneck} -> {prototypes}; {len(windows)} windows; "
              f"{procs.world} process(es) x batch {cfg.batch_size} on {device}{' (bf16)' if bf16 else ''}")

    total = cfg.steps
    warmup = int(round(cfg.warmup_fraction * total))
    temp_warmup = int(round(cfg.teacher_temp_warmup_fraction * total))
    loader = step_loader(windows, cfg.batch_size, procs, cfg.seed, start, total, cfg.num_workers,
                         pin_memory=device.type == "cuda")
    writer = summary_writer(out / "tb", purge_step=start) if procs.main else None
    bar = tqdm(total=total, initial=start, unit="step", desc="pretrain", disable=not (cfg.progress and procs.main),
               dynamic_ncols=True)
    meta = {"encoder": encoder_meta, "config": to_jsonable(cfg), "world_size": procs.world, "run_id": owner}
    acc = StepLog()
    history: list[dict[str, float]] = []
    step = start
    last_saved = start
    t_wait = time.perf_counter()
    try:
        with StopSignals() as stop:
            for step, batch in enumerate(loader, start):
                acc.wait += time.perf_counter() - t_wait
                lr = warmup_cosine(step, total, warmup, cfg.lr, cfg.lr_start, cfg.lr_end)
                wd = cosine(step, total, cfg.weight_decay, cfg.weight_decay_end)
                momentum = ema_momentum(step, total, cfg.ema_start, cfg.ema_end)
                temp = teacher_temperature(step, temp_warmup, cfg.teacher_temp_start, cfg.teacher_temp)
                set_hyperparameters(optimizer, lr, wd)
                torch.manual_seed(step_seed(cfg.seed, step, procs.rank))  # drop path
                n_batch = len(batch["session"])
                views = goal.views(grids, n_batch, step_rng(cfg.seed, step, procs.rank), device)
                inputs = encoder.preprocess(to_device(batch, device))
                with autocast(device, bf16), _naming_files(batch, windows):
                    fwd = goal.forward(model, teacher, inputs, views)  # teacher without gradient, then student
                loss, terms = goal.loss(loss_fn, fwd, temp)
                optimizer.zero_grad(set_to_none=True)
                loss.backward()
                norm = torch.nn.utils.clip_grad_norm_(student.parameters(), cfg.clip_grad or float("inf"))
                optimizer.step()
                ema_update(teacher, student, momentum)
                goal.update_centers(loss_fn, fwd)
                acc.add(loss, terms, norm, n_batch * procs.world)
                bar.update(1)
                done = step + 1
                if done % cfg.log_every == 0 or done == total:
                    point = acc.point(done, lr=lr, weight_decay=wd, ema_momentum=momentum, teacher_temp=temp,
                                      entropy=teacher_entropy(goal.monitor(loss_fn, fwd, temp)))
                    history.append(point)
                    if writer is not None:
                        log_point(writer, point)
                    bar.set_postfix(loss=f"{point['loss']:.3f}", samples_s=f"{point['samples_per_s']:.0f}")
                # a signal may reach some ranks only: they agree at log points (a check every step would sync)
                stopping = stop.requested if not procs.distributed else (
                    (done % cfg.log_every == 0 or done == total) and any_true(stop.requested, procs, device))
                if done % cfg.checkpoint_every == 0 or done == total or stopping:
                    if procs.main:
                        save_checkpoint(out, done, student, teacher, loss_fn, optimizer, meta, cfg.keep_checkpoints)
                        kind.save(teacher.encoder, out / "encoder.safetensors")
                    last_saved = done
                if stopping:
                    raise Interrupted(stop.signum or 2, f"pretrain: stopped at step {done}; --resume continues")
                t_wait = time.perf_counter()
    finally:
        bar.close()
        if writer is not None:
            writer.close()
    result: dict[str, Any] = {"steps": step + 1 if total > start else start, "out": str(out),
                              "encoder": str(out / "encoder.safetensors"), "last_checkpoint": last_saved,
                              "history": history}
    if history:
        result.update(final_loss=history[-1]["loss"], samples_per_s=history[-1]["samples_per_s"])
    if procs.distributed:
        digests: list[str] = [""] * procs.world
        dist.all_gather_object(digests, state_digest(student))
        result["identical_ranks"] = len(set(digests)) == 1
        if procs.main:
            (out / "ranks.json").write_text(json.dumps({"world_size": procs.world, "student_sha256": digests,
                                                        "identical": result["identical_ranks"]}, indent=2) + "\n")
        if not result["identical_ranks"]:
            raise JobFailed(f"pretrain: the ranks' weights diverged ({digests}); see {out / 'ranks.json'}")
    if procs.main and history:
        print(f"pretrain: {result['steps']} steps, final loss {history[-1]['loss']:.4f}, "
              f"{history[-1]['samples_per_s']:.1f} windows/s; encoder at {result['encoder']}")
    return result


@contextlib.contextmanager
def _naming_files(batch: dict, windows: Any):
    """Bad input found by the encoder (non-finite windows) is reported with the session files of the batch."""
    try:
        yield
    except ValueError as err:
        files = sorted({str(windows.paths[int(s)]) for s in batch["session"].tolist()})
        raise ValueError(f"{err}; the batch holds windows of {', '.join(files[:3])}"
                         f"{' ...' if len(files) > 3 else ''}") from None


if __name__ == "__main__":
    raise SystemExit(_worker_main(sys.argv[1:]))
