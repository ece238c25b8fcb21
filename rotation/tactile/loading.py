"""Touch windows for the encoder jobs: sessions or a pre-rendered cache (Sparsh-X), skin windows (Sparsh-skin), and
the per-step batch order.

The order of batches is a pure function of (seed, step): epoch e = step // steps_per_epoch reads
``DistributedSampler``'s permutation for epoch e (each process its own share of it), so a resumed run (or a run
restarted on as many processes) reads exactly the batches the uninterrupted one would have read.
"""

from __future__ import annotations

from collections.abc import Iterator, Sequence
from pathlib import Path

import torch
from torch.utils.data import DataLoader, Dataset, DistributedSampler, Sampler

from envs.errors import RequestRefused
from rotation.data.dataset import TouchWindows, find_sessions
from rotation.data.skin import SkinWindows
from rotation.data.window_cache import CachedWindows, build_cache
from rotation.interrupt import ignore_stop_signals
from rotation.tactile.runtime import Processes


def session_paths(sources: Sequence[str | Path]) -> list[Path]:
    """Every session file under the given files or directories, resolved and sorted (RequestRefused if none)."""
    paths = sorted({p.resolve() for s in sources for p in find_sessions(s)})
    if not paths:
        raise RequestRefused(f"no session files (*.h5) in {', '.join(map(str, sources))}")
    return paths


def open_windows(paths: Sequence[Path], cache: Path | None, fingers: Sequence[str], stride: int,
                 labels: Sequence[str] | None = (), build: bool = True, progress: bool = True,
                 workers: int = 0) -> Dataset:
    """The windows of ``paths``: from the cache at ``cache`` (rendering what is missing first, with ``workers``
    processes, when ``build``), or rendered on the fly (TouchWindows, raw audio for a batched filterbank on the
    device) when ``cache`` is None."""
    if cache is None:
        return TouchWindows(paths, fingers=fingers, labels=labels, stride=stride, audio_features=False)
    if build:
        build_cache(paths, cache, fingers=fingers, stride=stride, workers=workers, progress=progress)
    ds = CachedWindows(cache, sessions=paths, labels=labels)
    if tuple(ds.fingers) != tuple(fingers) or ds.stride != stride:
        raise ValueError(f"cache {cache} holds fingers {list(ds.fingers)} at stride {ds.stride}; this run asks for "
                         f"{list(fingers)} at stride {stride}")
    return ds


def open_encoder_windows(encoder: str, paths: Sequence[Path], cache: Path | None, fingers: Sequence[str],
                         stride: int, labels: Sequence[str] | None = (), build: bool = True, progress: bool = True,
                         workers: int = 0, sequence: int | None = None) -> Dataset:
    """The windows an encoder kind reads: Sparsh-X fingertip windows (:func:`open_windows`), or whole-hand skin
    windows (rotation.data.skin.SkinWindows; ``sequence`` consecutive windows per sample when given) read from
    the sessions directly (``cache`` must be None; ``fingers`` does not apply)."""
    if encoder == "skin":
        if cache is not None:
            raise ValueError("cache: the skin encoder reads its windows from the sessions (no cache); drop --cache")
        return SkinWindows(paths, labels=labels, stride=stride, sequence=sequence)
    if sequence is not None:
        raise ValueError(f"sequences of windows are read for the skin encoder only, not {encoder!r}")
    return open_windows(paths, cache, fingers, stride, labels=labels, build=build, progress=progress, workers=workers)


class StepBatches(Sampler[list[int]]):
    """One process's batches for steps [start, total) (see the module docstring); ``len`` = total - start."""

    def __init__(self, dataset: Dataset, batch_size: int, procs: Processes, seed: int, start: int, total: int):
        self.sampler = DistributedSampler(dataset, num_replicas=procs.world, rank=procs.rank, shuffle=True,  # type: ignore[arg-type]
                                          seed=seed, drop_last=True)
        self.batch_size, self.start, self.total = batch_size, start, total
        self.per_epoch = len(self.sampler) // batch_size
        if self.per_epoch < 1:
            raise ValueError(f"{len(dataset)} windows are fewer than one batch of {batch_size} on each of "  # type: ignore[arg-type]
                             f"{procs.world} process(es); record more sessions or lower --batch-size")

    def __len__(self) -> int:
        return max(0, self.total - self.start)

    def __iter__(self) -> Iterator[list[int]]:
        epoch, order = -1, []
        for step in range(self.start, self.total):
            e, k = divmod(step, self.per_epoch)
            if e != epoch:
                self.sampler.set_epoch(e)
                epoch, order = e, list(self.sampler)
            yield order[k * self.batch_size : (k + 1) * self.batch_size]


def step_loader(dataset: Dataset, batch_size: int, procs: Processes, seed: int, start: int, total: int,
                workers: int, pin_memory: bool) -> DataLoader:
    """A DataLoader yielding this process's batch of every step from ``start`` to ``total``."""
    return DataLoader(dataset, batch_sampler=StepBatches(dataset, batch_size, procs, seed, start, total),
                      num_workers=workers, pin_memory=pin_memory, persistent_workers=False,
                      prefetch_factor=4 if workers > 0 else None,
                      worker_init_fn=ignore_stop_signals)


def to_device(batch: dict, device: torch.device) -> dict:
    """Tensors of a batch onto ``device`` (non-blocking from pinned memory)."""
    return {k: v.to(device, non_blocking=True) if isinstance(v, torch.Tensor) else v for k, v in batch.items()}
