"""Benchmark: Sparsh-X forward latency for the four fingertips of a hand (batch 4), per size, on CPU and GPU.

Measurements in one run (median over ``iters`` timed calls after ``warmup``, under ``torch.inference_mode``):

- per size, the forward from model inputs on the CPU (``threads`` intra-op threads) and, when a CUDA GPU is
  present, on the GPU in float32 and under bfloat16 autocast;
- bottleneck vs vanilla fusion at one size on the CPU (``bottleneck_over_vanilla``: time ratio; both fuse the same
  tokens, the bottleneck's blocks see 4 + 1 + N_m tokens each, vanilla's shared blocks all 536 at once);
- the tinier all-modality encoder encoding 4 fingertips from RAW windows as the sensor gives them (two uint8
  frames, 2 x 27000 audio samples, IMU, pressure): packing, the Kaldi filterbank and the forward
  (``tinier_4tips_ms``, float32; target < 50 ms on 2 CPU cores), and the same under bfloat16 autocast.

Inputs are random (the cost does not depend on the content). The last line printed is a JSON object; the
pretraining benchmarks may add their own keys to it.

    python scripts/bench_encoder.py
    python scripts/bench_encoder.py --sizes tinier tiny small base --iters 20 --threads 2
"""

from __future__ import annotations

import json
import os
import statistics
import time
from collections.abc import Callable
from dataclasses import dataclass

import torch

from rotation.configs import num_cores, script_main
from rotation.tactile.models.sparshx import SIZES, SparshX, SparshXConfig
from rotation.tactile.models.sparshx_inputs import INPUT_SHAPES, MODALITIES


@dataclass
class Config:
    """Benchmark settings."""

    sizes: tuple[str, ...] = ("tinier", "tiny", "small")
    """Sizes timed on the CPU (base needs about 1.5 s per fingertip on 2 cores; add it to time it)."""
    gpu_sizes: tuple[str, ...] = ("tinier", "tiny", "small", "base")
    """Sizes timed on the GPU, when one is available."""
    batch: int = 4
    """Samples per forward: one per fingertip of the hand."""
    iters: int = 10
    """Timed calls per measurement (the median is reported)."""
    warmup: int = 2
    """Untimed calls before each measurement."""
    threads: int = 0
    """Intra-op threads on the CPU (0 = the cores this process may run on)."""
    fusion_size: str = "tiny"
    """Size at which bottleneck and vanilla fusion are compared (CPU)."""
    gpu: bool = True
    """Also time on a CUDA GPU when one is available."""
    seed: int = 0
    """Seed of the weights and random inputs."""
    pretrain: bool = False
    """Also measure the pretraining data path and step rate (scripts/bench_pretrain.py with its defaults on this
    device): adds loader_windows_per_s (from the cache), loader_windows_per_s_live and pretrain_samples_per_s."""


def median_ms(fn: Callable[[], object], iters: int, warmup: int, device: torch.device) -> float:
    """Median wall time of ``fn()`` in ms (GPU work synchronized before the clock stops)."""
    sync = torch.cuda.synchronize if device.type == "cuda" else (lambda: None)
    for _ in range(warmup):
        fn()
    sync()
    times = []
    for _ in range(iters):
        start = time.perf_counter()
        fn()
        sync()
        times.append((time.perf_counter() - start) * 1e3)
    return statistics.median(times)


def model_inputs(batch: int, device: torch.device, gen: torch.Generator) -> dict[str, torch.Tensor]:
    """Random model inputs of the contract's shapes (pressure around 1000 hPa)."""
    x = {m: torch.rand((batch, *INPUT_SHAPES[m]), generator=gen) for m in MODALITIES}
    x["pressure"] = 1000.0 + x["pressure"]
    return {m: v.to(device) for m, v in x.items()}


def raw_windows(batch: int, gen: torch.Generator) -> dict[str, torch.Tensor]:
    """Random raw windows as the sensor and the simulated Digit 360 give them (on the CPU, as a loader would)."""
    return {
        "image": torch.randint(0, 256, (batch, 2, 224, 224, 3), generator=gen, dtype=torch.uint8),
        "audio_wave": torch.randint(-2000, 2000, (batch, 2, 27000), generator=gen).to(torch.float32),
        "imu": torch.randn((batch, 224, 3), generator=gen),
        "pressure": 1000.0 + torch.randn((batch, 224), generator=gen),
    }


def build(size: str, device: torch.device, fusion: str = "bottleneck", seed: int = 0) -> SparshX:
    torch.manual_seed(seed)
    return SparshX(SparshXConfig(size=size, fusion=fusion)).to(device).eval()


def forward_ms(model: SparshX, inputs: dict, cfg: Config, device: torch.device, bf16: bool = False) -> float:
    def call() -> None:
        with torch.autocast(device.type, dtype=torch.bfloat16, enabled=bf16):
            model(inputs)

    return median_ms(call, cfg.iters, cfg.warmup, device)


def run(cfg: Config) -> dict:
    """All measurements; prints a table and, last, the JSON result (also returned)."""
    unknown = [s for s in (*cfg.sizes, *cfg.gpu_sizes, cfg.fusion_size) if s not in SIZES]
    if unknown:
        raise ValueError(f"unknown size(s) {unknown}; sizes: {', '.join(SIZES)}")
    if cfg.batch < 1 or cfg.iters < 1 or cfg.warmup < 0 or cfg.threads < 0:
        raise ValueError(f"batch and iters must be >= 1, warmup and threads >= 0, got {cfg}")
    threads, threads_before = cfg.threads or num_cores(), torch.get_num_threads()
    torch.set_num_threads(threads)
    try:
        return _measure(cfg, threads)
    finally:
        torch.set_num_threads(threads_before)


def _measure(cfg: Config, threads: int) -> dict:
    cpu = torch.device("cpu")
    gpu = torch.device("cuda") if cfg.gpu and torch.cuda.is_available() else None
    gen = torch.Generator().manual_seed(cfg.seed)
    load_before = os.getloadavg()[0]
    params, cpu_ms, gpu_ms, gpu_bf16_ms = {}, {}, {}, {}
    with torch.inference_mode():
        x_cpu = model_inputs(cfg.batch, cpu, gen)
        for size in cfg.sizes:
            model = build(size, cpu, seed=cfg.seed)
            params[size] = model.num_parameters()
            cpu_ms[size] = forward_ms(model, x_cpu, cfg, cpu)
            del model
        if gpu is not None:
            x_gpu = {m: v.to(gpu) for m, v in x_cpu.items()}
            for size in cfg.gpu_sizes:
                model = build(size, gpu, seed=cfg.seed)
                params[size] = model.num_parameters()
                gpu_ms[size] = forward_ms(model, x_gpu, cfg, gpu)
                gpu_bf16_ms[size] = forward_ms(model, x_gpu, cfg, gpu, bf16=True)
                del model
            torch.cuda.empty_cache()
        fusion_ms = {f: forward_ms(build(cfg.fusion_size, cpu, f, cfg.seed), x_cpu, cfg, cpu)
                     for f in ("bottleneck", "vanilla")}
        # the tinier encoder from raw windows: packing + filterbank + forward, the real-time path on a robot's PC
        tinier = build("tinier", cpu, seed=cfg.seed)
        raw = raw_windows(cfg.batch, gen)
        prep_ms = median_ms(lambda: tinier.preprocess(raw), cfg.iters, cfg.warmup, cpu)
        raw_ms = median_ms(lambda: tinier.encode(raw), cfg.iters, cfg.warmup, cpu)

        def encode_bf16() -> None:
            with torch.autocast("cpu", dtype=torch.bfloat16):
                tinier.encode(raw)

        raw_bf16_ms = median_ms(encode_bf16, cfg.iters, cfg.warmup, cpu)
        gpu_raw_ms = None
        if gpu is not None:
            tinier_gpu = build("tinier", gpu, seed=cfg.seed)
            gpu_raw_ms = median_ms(lambda: tinier_gpu.encode(raw), cfg.iters, cfg.warmup, gpu)
    result = {
        "batch": cfg.batch,
        "threads": threads,
        "iters": cfg.iters,
        "gpu": torch.cuda.get_device_name(gpu) if gpu is not None else None,
        "params": params,
        "cpu_ms": {k: round(v, 2) for k, v in cpu_ms.items()},
        "gpu_ms": {k: round(v, 2) for k, v in gpu_ms.items()} if gpu is not None else None,
        "gpu_bf16_ms": {k: round(v, 2) for k, v in gpu_bf16_ms.items()} if gpu is not None else None,
        "fusion_size": cfg.fusion_size,
        "bottleneck_ms": round(fusion_ms["bottleneck"], 2),
        "vanilla_ms": round(fusion_ms["vanilla"], 2),
        "bottleneck_over_vanilla": round(fusion_ms["bottleneck"] / fusion_ms["vanilla"], 4),
        "tinier_4tips_ms": round(raw_ms, 2),
        "tinier_4tips_preprocess_ms": round(prep_ms, 2),
        "tinier_4tips_bf16_ms": round(raw_bf16_ms, 2),
        "gpu_tinier_4tips_ms": round(gpu_raw_ms, 2) if gpu_raw_ms is not None else None,
        "loadavg_1min_before": round(load_before, 2),
        "loadavg_1min_after": round(os.getloadavg()[0], 2),
    }
    print(f"Sparsh-X forward, batch {cfg.batch} (4 fingertips), median of {cfg.iters} calls; CPU {threads} "
          f"thread(s), GPU {result['gpu'] or 'none'}; 1-min load average {load_before:.2f}")
    print(f"{'size':8s} {'params':>13s} {'CPU ms':>9s} {'GPU ms':>9s} {'GPU bf16':>9s}")
    for size in SIZES:
        if size not in params:
            continue

        def cell(table: dict, key: str = size) -> str:
            return f"{table[key]:9.2f}" if key in table else f"{'-':>9s}"

        print(f"{size:8s} {params[size]:13,d} {cell(cpu_ms)} {cell(gpu_ms)} {cell(gpu_bf16_ms)}")
    print(f"fusion at {cfg.fusion_size} (CPU): bottleneck {fusion_ms['bottleneck']:.2f} ms, vanilla "
          f"{fusion_ms['vanilla']:.2f} ms, ratio {result['bottleneck_over_vanilla']:.3f}")
    gpu_part = f"; GPU {gpu_raw_ms:.2f} ms" if gpu_raw_ms is not None else ""
    print(f"tinier, 4 fingertips from raw windows (CPU): {raw_ms:.2f} ms (target < 50 ms on 2 cores; of which "
          f"packing + filterbank {prep_ms:.2f} ms), bfloat16 autocast {raw_bf16_ms:.2f} ms{gpu_part}")
    if cfg.pretrain:
        result.update(_pretrain_figures(gpu))
    print(json.dumps(result))
    return result


def _pretrain_figures(gpu: torch.device | None) -> dict:
    """scripts/bench_pretrain.py's loader and pretraining rates (it prints its own summary)."""
    import importlib.util
    import sys
    from pathlib import Path

    spec = importlib.util.spec_from_file_location("bench_pretrain", Path(__file__).with_name("bench_pretrain.py"))
    module = importlib.util.module_from_spec(spec)
    sys.modules[spec.name] = module  # dataclasses look their module up while the class is created
    spec.loader.exec_module(module)
    figures = module.run(module.Config(device=str(gpu or "cpu")))
    keys = ("loader_windows_per_s", "loader_windows_per_s_live", "cache_windows_per_s", "pretrain_samples_per_s")
    return {k: figures[k] for k in keys}


def main(argv: list[str] | None = None) -> int:
    return script_main(Config, run, __doc__, argv)


if __name__ == "__main__":
    raise SystemExit(main())
