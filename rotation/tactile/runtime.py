"""What the touch-encoder jobs (pretrain, probe) share at run time: devices, mixed precision, processes of a
distributed run, per-step seeds, TensorBoard."""

from __future__ import annotations

import contextlib
import hashlib
import os
from dataclasses import dataclass

import numpy as np
import torch
import torch.distributed as dist

PRECISIONS = ("auto", "bf16", "fp32")
"""'auto': bfloat16 autocast on a GPU, float32 on the CPU."""


def check_device(device: str, field: str = "device") -> None:
    """``device`` is 'auto' or a torch device this machine has ('cpu', 'cuda', 'cuda:N'), else a ValueError naming
    ``field``."""
    if not isinstance(device, str):
        raise ValueError(f"{field} must be a string (auto, cpu, cuda, cuda:N), got {device!r}")
    if device == "auto":
        return
    from rotation.configs import check_device as check_torch_device

    check_torch_device(field, device)


def resolve_device(device: str, local_rank: int = 0) -> torch.device:
    """'auto' -> the process's GPU (cuda:LOCAL_RANK) when there is one, else the CPU; 'cuda' in a distributed run
    -> cuda:LOCAL_RANK. A GPU asked for on a machine without one is a ValueError."""
    if device == "auto":
        device = "cuda" if torch.cuda.is_available() else "cpu"
    dev = torch.device(device)
    if dev.type == "cuda":
        if not torch.cuda.is_available():
            raise ValueError(f"device {device!r}: this machine (or this torch build) has no CUDA GPU; use --device cpu")
        if dev.index is None:
            dev = torch.device("cuda", local_rank)
        torch.cuda.set_device(dev)
    return dev


def use_bf16(precision: str, device: torch.device) -> bool:
    if precision not in PRECISIONS:
        raise ValueError(f"precision: {precision!r} not in {PRECISIONS}")
    return precision == "bf16" or (precision == "auto" and device.type == "cuda")


def autocast(device: torch.device, bf16: bool):
    """bfloat16 autocast on ``device`` when ``bf16`` (weights and optimizer stay float32), else nothing."""
    if not bf16:
        return contextlib.nullcontext()
    return torch.autocast(device_type=device.type, dtype=torch.bfloat16)


@dataclass(frozen=True)
class Processes:
    """This process's place in a (torchrun) distributed run; rank 0 of 1 when not distributed."""

    rank: int = 0
    world: int = 1
    local_rank: int = 0

    @property
    def main(self) -> bool:
        return self.rank == 0

    @property
    def distributed(self) -> bool:
        return self.world > 1

    def barrier(self) -> None:
        if self.distributed:
            dist.barrier()


def init_processes(device_hint: str) -> Processes:
    """Join the process group torchrun set up (RANK, WORLD_SIZE, LOCAL_RANK in the environment): nccl on GPUs,
    gloo on the CPU. Without those variables: a single process."""
    world = int(os.environ.get("WORLD_SIZE", "1"))
    if world <= 1:
        return Processes()
    rank, local = int(os.environ["RANK"]), int(os.environ.get("LOCAL_RANK", "0"))
    gpu = device_hint.startswith("cuda") or (device_hint == "auto" and torch.cuda.is_available())
    if not dist.is_initialized():
        if gpu:
            torch.cuda.set_device(local)
        dist.init_process_group(backend="nccl" if gpu else "gloo")
    return Processes(rank, world, local)


def any_true(flag: bool, procs: Processes, device: torch.device) -> bool:
    """True on every process if ``flag`` is true on any (e.g. a stop request that reached one rank)."""
    if not procs.distributed:
        return flag
    t = torch.tensor([1.0 if flag else 0.0], device=device)
    dist.all_reduce(t)
    return bool(t.item() > 0)


def step_seed(seed: int, step: int, rank: int = 0, stream: int = 0) -> int:
    """A 63-bit seed that is a pure function of (seed, step, rank, stream): per-step randomness (drop path, masks)
    that a resumed run reproduces exactly."""
    return int(np.random.SeedSequence([int(seed), int(step), int(rank), int(stream)]).generate_state(2, np.uint64)[0]
               >> np.uint64(1))


def state_digest(module: torch.nn.Module) -> str:
    """SHA-256 of a module's state dict (names and raw bytes, in its order): the same weights give the same digest
    (the pretraining's ranks compare theirs; a probe report records its encoder's)."""
    h = hashlib.sha256()
    for name, value in module.state_dict().items():
        h.update(name.encode())
        h.update(value.detach().cpu().contiguous().reshape(-1).view(torch.uint8).numpy().tobytes())
    return h.hexdigest()
