"""Pretrain a touch encoder by self-distillation (DINO on block-masked token views, EMA teacher).

    rotate cache-touch --sessions data/touch --out data/touch_cache --workers 8       # render windows once
    rotate pretrain --sessions data/touch --cache data/touch_cache --size tiny --steps 20000 --out runs/pretrain
    rotate pretrain --sessions data/touch --cache data/touch_cache --out runs/pretrain --resume
    rotate pretrain ... --nproc-per-node 4                   # 4 GPUs of this machine (DDP through torchrun)
    rotate pretrain ... --nnodes 2 --node-rank 0 --master-addr 10.0.0.1 --nproc-per-node 8   # on each node

Per step and token set (modality): one global and four local block-masked views (rotation.tactile.ssl.masking);
the teacher (EMA of the student) sees the global view, the student every view; the DINO loss compares their
register tokens through a shared projection head, one center per set (reference/sparsh.md "Sparsh-X
self-supervised pretraining"). AdamW with a warm-up + cosine learning rate, no weight decay on 1-D parameters,
gradient clipping; bfloat16 autocast on a GPU. Every schedule is a function of the step and every random draw
(masks, drop path, batch order) is seeded by it, so ``--resume`` continues bit-identically (on the same device).

OUT holds config.json, ckpt_<step>.safetensors (the newest few: student, teacher, head, optimizer state, centers,
step), encoder.safetensors (the teacher's encoder at the last checkpoint: what `rotate probe` and the tactile
adapter load), tb/ (TensorBoard) and, after a distributed run, ranks.json (a digest of every rank's weights).
With ``--cache`` windows come from pre-rendered shards (rotation.data.window_cache; missing sessions are rendered
first), else they are rendered on the fly (about 160 windows/s per loader worker).
"""

from __future__ import annotations

import contextlib
import copy
import hashlib
import json
import os
import subprocess
import sys
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Literal

import torch
import torch.distributed as dist
from tqdm import tqdm

from envs.constants import FINGERS
from envs.validation import check_int, check_number, check_output_dir, check_seed, check_types
from rotation.configs import from_jsonable, save_config, to_jsonable
from rotation.interrupt import Interrupted, StopSignals
from rotation.tactile.encoders import ENCODERS, encoder_kind, parse_groups
from rotation.tactile.loading import check_fingers, open_windows, session_paths, step_loader, to_device
from rotation.tactile.pretrain_log import StepLog, log_point
from rotation.tactile.pretrain_state import (
    SelfDistillation,
    latest_checkpoint,
    load_checkpoint,
    save_checkpoint,
)
from rotation.tactile.runtime import (
    Processes,
    any_true,
    autocast,
    check_device,
    init_processes,
    resolve_device,
    step_seed,
    summary_writer,
    use_bf16,
)
from rotation.tactile.ssl import (
    DINOHead,
    DINOLoss,
    MaskConfig,
    cosine,
    ema_momentum,
    ema_update,
    param_groups,
    sample_views,
    set_hyperparameters,
    step_rng,
    teacher_entropy,
    teacher_temperature,
    warmup_cosine,
)

HEAD_SIZES = {"tinier": (256, 1024), "tiny": (1024, 8192), "small": (2048, 16384), "base": (2048, 65536)}
"""Encoder size -> (head hidden width, prototypes) when not given: DINO's 2048 / 65,536 for base (reference/
sparsh.md), smaller for the small models so the head does not dwarf the encoder."""
WORKER_ENV = "ROTATE_PRETRAIN_WORKER"
"""Set in the processes torchrun starts, so they train instead of launching again."""


@dataclass(frozen=True)
class Config:
    """Self-supervised pretraining of a touch encoder (`rotate pretrain`)."""

    sessions: tuple[Path, ...] = (Path("touch_sessions"),)
    """Session files or directories (every *.h5 below them), simulated or recorded."""
    cache: Path | None = None
    """Pre-rendered window cache (rotate cache-touch); sessions missing from it are rendered into it first. None:
    render windows on the fly (slow: use for small runs)."""
    out: Path = Path("runs/pretrain")
    """Run directory: config.json, checkpoints, encoder.safetensors, tb/."""
    encoder: str = "sparshx"
    """Encoder to pretrain (rotation.tactile.encoders.ENCODERS)."""
    size: str = "tiny"
    """Encoder size: tinier, tiny, small or base."""
    modalities: str = "img,mic,imu,pressure"
    """Token groups (Sparsh-X modalities), comma-separated."""
    fusion: str = "bottleneck"
    """Sparsh-X fusion layers: bottleneck or vanilla."""
    drop_path: float = 0.1
    """Stochastic depth of the student's last layer (Sparsh-X: 0.1; 0 = none)."""
    fingers: tuple[str, ...] = FINGERS
    """Fingertips whose windows are used."""
    stride: int = 5
    """Use every stride-th image frame as a window end (30 fps / 5 = 6 windows per second and fingertip)."""
    steps: int = 20_000
    """Optimizer steps."""
    batch_size: int = 64
    """Windows per step and process (the global batch is batch_size x processes)."""
    lr: float = 1e-4
    """Peak learning rate (Sparsh-X: 1e-4)."""
    lr_start: float = 1e-5
    """Learning rate at step 0, warmed up linearly to lr."""
    lr_end: float = 1e-6
    """Learning rate at the last step (cosine from lr)."""
    warmup_fraction: float = 0.15
    """Fraction of the steps spent warming the learning rate up (Sparsh-X: 30 of 200 epochs)."""
    weight_decay: float = 0.05
    """AdamW weight decay at step 0 (parameters with >= 2 dims only)."""
    weight_decay_end: float = 0.05
    """Weight decay at the last step (cosine; equal to weight_decay = constant)."""
    clip_grad: float | None = 10.0
    """Clip the gradients' global norm to this (Sparsh-X: 10); None = no clipping."""
    ema_start: float = 0.994
    """Teacher EMA momentum at step 0, cosine ramp to ema_end."""
    ema_end: float = 1.0
    """Teacher EMA momentum at the last step."""
    student_temp: float = 0.1
    """Temperature of the student's softmax."""
    teacher_temp_start: float = 0.04
    """Teacher temperature at step 0."""
    teacher_temp: float = 0.07
    """Teacher temperature after its warm-up."""
    teacher_temp_warmup_fraction: float = 0.05
    """Fraction of the steps over which the teacher temperature warms up (Sparsh-X: 10 of 200 epochs)."""
    center_momentum: float = 0.9
    """EMA momentum of the per-set centers."""
    head_hidden: int | None = None
    """Hidden width of the projection head (None = by size: 256 tinier, 1024 tiny, 2048 small and base)."""
    head_bottleneck: int = 256
    """Bottleneck width of the projection head (L2-normalized)."""
    prototypes: int | None = None
    """Prototypes K (None = by size: 1024 tinier, 8192 tiny, 16384 small, 65536 base)."""
    mask: MaskConfig = field(default_factory=MaskConfig)
    """Views: block scales, local views, fewest kept tokens."""
    stats_windows: int = 2048
    """Windows (a seeded random subset) from which the encoder's input normalization (audio per mel bin, pressure,
    image) is fitted before the first step."""
    num_workers: int = 4
    """DataLoader worker processes per training process."""
    device: str = "auto"
    """torch device: auto (this process's GPU if there is one), cpu, cuda, cuda:1, ..."""
    precision: Literal["auto", "bf16", "fp32"] = "auto"
    """auto (bfloat16 autocast on a GPU, float32 on the CPU), bf16 or fp32."""
    checkpoint_every: int = 1000
    """Steps between checkpoints (and exports of encoder.safetensors)."""
    keep_checkpoints: int = 3
    """Newest checkpoints kept."""
    log_every: int = 20
    """Steps between TensorBoard points."""
    seed: int = 0
    """Seed of the initialization, batch order, masks and drop path."""
    resume: bool = False
    """Continue from the newest checkpoint in out (the saved config must match, except run-time options)."""
    progress: bool = True
    """Show a progress bar."""
    torch_threads: int | None = None
    """torch CPU threads per process (None = torch's default; with several processes, the cores divided among
    them)."""
    nproc_per_node: int = 1
    """Training processes on this machine (> 1: relaunch through torchrun with DistributedDataParallel)."""
    nnodes: int = 1
    """Machines of a multi-node run (torchrun --nnodes)."""
    node_rank: int = 0
    """This machine's rank in a multi-node run (torchrun --node-rank)."""
    master_addr: str = ""
    """Address of the rank-0 machine of a multi-node run (torchrun --master-addr); empty on one machine."""
    master_port: int = 29500
    """Port of the rank-0 machine (torchrun --master-port)."""

    def __post_init__(self) -> None:
        check_types(self)
        if not self.sessions:
            raise ValueError("sessions: give at least one session file or directory")
        object.__setattr__(self, "sessions", tuple(Path(p) for p in self.sessions))  # JSON gives strings back
        check_output_dir("out", self.out)
        if self.cache is not None:
            check_output_dir("cache", self.cache)
        if self.encoder not in ENCODERS:
            raise ValueError(f"encoder: unknown encoder {self.encoder!r}; encoders: {', '.join(ENCODERS)}")
        kind = encoder_kind(self.encoder)
        if self.size not in kind.sizes:
            raise ValueError(f"size: unknown size {self.size!r}; sizes: {', '.join(kind.sizes)}")
        parse_groups(self.modalities, self.encoder)
        if self.fusion not in ("bottleneck", "vanilla"):
            raise ValueError(f"fusion: must be bottleneck or vanilla, got {self.fusion!r}")
        check_fingers(self.fingers)
        check_number("drop_path", self.drop_path, 0.0, 1.0, high_open=True)
        for name, high in (("stride", 1000), ("steps", 10**9), ("batch_size", 65536), ("checkpoint_every", 10**9),
                           ("keep_checkpoints", 1000), ("log_every", 10**9), ("head_bottleneck", 65536),
                           ("stats_windows", 10**7), ("nproc_per_node", 1024), ("nnodes", 100_000)):
            check_int(name, getattr(self, name), 1, high)
        for name, high in (("head_hidden", 65536), ("prototypes", 2**20), ("torch_threads", 4096)):
            if getattr(self, name) is not None:
                check_int(name, getattr(self, name), 1, high)
        check_int("num_workers", self.num_workers, 0, 1024)
        check_int("node_rank", self.node_rank, 0, self.nnodes - 1)
        check_seed("seed", self.seed)
        for name in ("lr", "lr_start", "lr_end"):
            check_number(name, getattr(self, name), 0.0, 1.0, low_open=True)
        for name in ("student_temp", "teacher_temp_start", "teacher_temp"):
            check_number(name, getattr(self, name), 0.0, 10.0, low_open=True)
        for name in ("weight_decay", "weight_decay_end"):
            check_number(name, getattr(self, name), 0.0, 10.0)
        if self.clip_grad is not None:
            check_number("clip_grad", self.clip_grad, 0.0, 1e6, low_open=True)
        for name in ("warmup_fraction", "teacher_temp_warmup_fraction"):
            check_number(name, getattr(self, name), 0.0, 1.0, high_open=True)
        for name in ("ema_start", "ema_end"):
            check_number(name, getattr(self, name), 0.0, 1.0, low_open=True)
        check_number("center_momentum", self.center_momentum, 0.0, 1.0, low_open=True, high_open=True)
        check_device(self.device, "device")
        if self.nnodes > 1 and not self.master_addr:
            raise ValueError("master_addr: a multi-node run (nnodes > 1) needs the rank-0 machine's address")
        check_int("master_port", self.master_port, 1, 65535)

    @property
    def groups(self) -> tuple[str, ...]:
        return parse_groups(self.modalities, self.encoder)

    def head_sizes(self) -> tuple[int, int]:
        hidden, k = HEAD_SIZES.get(self.size, (2048, 65536))
        return self.head_hidden or hidden, self.prototypes or k  # None: by size


RESUMABLE_CHANGES = {"out", "cache", "resume", "progress", "num_workers", "device", "precision", "torch_threads",
                     "checkpoint_every", "keep_checkpoints", "log_every", "nproc_per_node", "nnodes", "node_rank",
                     "master_addr", "master_port"}
"""Config fields that may differ between a run and its resumption (run-time options, not the training math;
a different device, precision or number of processes continues correctly but not bit-identically)."""


def load_config(path: str | Path) -> Config:
    """The Config a run saved (``<out>/config.json``)."""
    return from_jsonable(Config, json.loads(Path(path).read_text()))


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
        open_windows(session_paths(cfg.sessions), cfg.cache, cfg.fingers, cfg.stride, progress=cfg.progress,
                     workers=cfg.num_workers)
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
    cmd += ["-m", "rotation.tactile.pretrain", "--worker", str(spec)]
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
    """Entry point of a torchrun process: ``python -m rotation.tactile.pretrain --worker SPEC.json``."""
    if len(argv) != 2 or argv[0] != "--worker":
        print("usage: python -m rotation.tactile.pretrain --worker SPEC.json (started by `rotate pretrain`)",
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
    saved = json.loads((out / "config.json").read_text())
    now = to_jsonable(cfg)
    diff = sorted(k for k in now if k not in RESUMABLE_CHANGES and saved.get(k) != now[k])
    if diff:
        raise ValueError(f"--resume: the config differs from the one saved in {out / 'config.json'} in {diff}; "
                         f"only {sorted(RESUMABLE_CHANGES)} may change on resume")


def _state_digest(module: torch.nn.Module) -> str:
    h = hashlib.sha256()
    for name, value in module.state_dict().items():
        h.update(name.encode())
        h.update(value.detach().cpu().contiguous().reshape(-1).view(torch.uint8).numpy().tobytes())
    return h.hexdigest()


def build(cfg: Config) -> tuple[SelfDistillation, DINOLoss]:
    """The freshly initialized student (encoder + head, seeded by ``cfg.seed``) and the loss of a run."""
    kind = encoder_kind(cfg.encoder)
    torch.manual_seed(cfg.seed)
    encoder = kind.build(cfg.size, cfg.groups, cfg.fusion, cfg.drop_path)
    interface = encoder.token_interface
    hidden, prototypes = cfg.head_sizes()
    head = DINOHead(interface.width, hidden, cfg.head_bottleneck, prototypes)
    return SelfDistillation(encoder, head), DINOLoss(interface.names, prototypes, cfg.student_temp,
                                                      cfg.center_momentum)


def train(cfg: Config) -> dict[str, Any]:
    """The training loop of one process (all of it without torchrun, one rank of it with)."""
    procs = init_processes(cfg.device)
    threads = torch.get_num_threads()
    if cfg.torch_threads:
        torch.set_num_threads(cfg.torch_threads)
    try:
        return _train(cfg, procs)
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
            raise ValueError(f"--resume: no checkpoint (ckpt_*.safetensors) and config.json in {out}")
        _check_resumable(cfg, out)
    elif ckpt is not None:
        raise ValueError(f"{out} already holds checkpoints; pass --resume to continue or choose another --out")

    paths = session_paths(cfg.sessions)
    if cfg.cache is not None and procs.main:
        open_windows(paths, cfg.cache, cfg.fingers, cfg.stride, progress=cfg.progress, workers=cfg.num_workers)
    procs.barrier()
    windows = open_windows(paths, cfg.cache, cfg.fingers, cfg.stride, labels=(), build=False)

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
    if procs.main:
        save_config(cfg, out / "config.json")
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
    meta = {"encoder": encoder_meta, "config": to_jsonable(cfg), "world_size": procs.world}
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
                views = sample_views(grids, len(batch["time"]), cfg.mask, step_rng(cfg.seed, step, procs.rank),
                                     device)
                inputs = encoder.preprocess(to_device(batch, device))
                with autocast(device, bf16), _naming_files(batch, windows):
                    with torch.no_grad():
                        t_logits = {n: x[0] for n, x in teacher(inputs, views[:1]).items()}  # (B, K)
                    s_logits = model(inputs, views)  # (V, B, K)
                loss, per_set = loss_fn(s_logits, t_logits, temp)
                optimizer.zero_grad(set_to_none=True)
                loss.backward()
                norm = torch.nn.utils.clip_grad_norm_(student.parameters(), cfg.clip_grad or float("inf"))
                optimizer.step()
                ema_update(teacher, student, momentum)
                loss_fn.update_center(t_logits)
                acc.add(loss, per_set, norm, len(batch["time"]) * procs.world)
                bar.update(1)
                done = step + 1
                if done % cfg.log_every == 0 or done == total:
                    point = acc.point(done, lr=lr, weight_decay=wd, ema_momentum=momentum, teacher_temp=temp,
                                      entropy=teacher_entropy(loss_fn.teacher_probs(t_logits, temp)))
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
        dist.all_gather_object(digests, _state_digest(student))
        result["identical_ranks"] = len(set(digests)) == 1
        if procs.main:
            (out / "ranks.json").write_text(json.dumps({"world_size": procs.world, "student_sha256": digests,
                                                        "identical": result["identical_ranks"]}, indent=2) + "\n")
        if not result["identical_ranks"]:
            raise RuntimeError(f"pretrain: the ranks' weights diverged ({digests}); see {out / 'ranks.json'}")
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
