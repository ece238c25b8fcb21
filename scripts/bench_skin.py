"""Benchmark: the simulated Xela skin's cost in the batched env (and room for the skin encoder's latency).

Each measurement is one function registered in ``MEASUREMENTS``; it returns a dict that joins the result.

- ``env``: control steps/s (env transitions/s, uniform random actions, finished envs reset) of the batched env in
  three settings built once and timed in alternating rounds in the same process, so that a changing machine load
  biases none of them: ``plain`` (the default env: Digit 360 hand, no touch, no skin), ``xela_off`` (the Xela hand,
  skin off: its pads are collision geoms, so the physics differs slightly) and ``skin`` (the Xela hand with the
  skin on: pad sensors, the reading model of 368 x 3 taxels at every 100 Hz substep, the `skin` window).
  ``skin_over_plain`` = skin / plain; ``skin_over_xela_off`` = skin / xela_off, the cost of the sensor alone.
- ``encoder``: the Sparsh-skin encoder (size ``encoder_size``, tiny by default, random weights; or ``checkpoint``,
  e.g. the shipped ``sparshskin-tiny-sim``) on one hand window on the CPU (``threads`` intra-op threads), from the
  raw window as the env, a session or the Xela reader gives it (baseline subtraction included), under
  ``torch.inference_mode``: ``skin_<size>_ms``, the median over ``iters`` calls after 2 untimed ones, its 95th
  percentile ``skin_<size>_p95_ms``, the rate one hand's windows can be encoded at ``skin_<size>_hz`` (1000 / the
  median; the skin streams at 100 Hz) and ``skin_<size>_params``.

The last line printed is a JSON object with every measurement's figures.

    python scripts/bench_skin.py
    python scripts/bench_skin.py --num-envs 64 --steps 8192 --rounds 3
    python scripts/bench_skin.py --only env
    python scripts/bench_skin.py --only encoder --threads 2
    python scripts/bench_skin.py --only encoder --checkpoint sparshskin-tiny-sim
"""

from __future__ import annotations

import json
import os
import statistics
from collections.abc import Callable
from dataclasses import dataclass

from envs.config import EnvConfig
from envs.core import RotateCupVec, random_steps_per_s
from rotation.configs import script_main


@dataclass
class Config:
    """Benchmark settings."""

    num_envs: int = 16
    """Simulations stepped together (16: a collection's batch, as scripts/bench_tactile.py)."""
    steps: int = 4096
    """Env transitions timed per setting, split over the rounds."""
    rounds: int = 3
    """Alternating rounds; each rate is the median over rounds."""
    object: str = "cup"
    """Object (envs.objects; the Xela hand ships grasps for 'cup')."""
    nthread: int = 0
    """MuJoCo threads (0 = one per CPU core, at most num_envs)."""
    seed: int = 0
    """Seed of the envs and of the actions."""
    only: tuple[str, ...] = ()
    """Measurements to run (names in MEASUREMENTS); empty = all."""
    encoder_size: str = "tiny"
    """Sparsh-skin size of the encoder measurement (tiny: the released size), with random weights."""
    checkpoint: str = ""
    """A skin encoder to time instead (a path or a shipped name: rotation.tactile.models.encoders.load_encoder);
    empty: a random one of ``encoder_size``."""
    iters: int = 20
    """Timed encoder calls (the median is reported)."""
    threads: int = 0
    """torch intra-op threads of the encoder measurement (0 = torch's default)."""


ENV_SETTINGS = {
    "plain": {},
    "xela_off": {"hand": "xela"},
    "skin": {"hand": "xela", "skin": True},
}
"""The env settings of the `env` measurement (EnvConfig keyword arguments)."""


def measure_env(cfg: Config) -> dict:
    """Env transitions/s with the skin on and off (see the module docstring)."""
    envs = {name: RotateCupVec(EnvConfig(object=cfg.object, **kw), num_envs=cfg.num_envs, seed=cfg.seed,
                               nthread=cfg.nthread or None) for name, kw in ENV_SETTINGS.items()}
    per_round = max(cfg.num_envs, cfg.steps // cfg.rounds)
    rates: dict[str, list[float]] = {name: [] for name in envs}
    try:
        for env in envs.values():  # warm-up: first calls allocate and fault pages in
            random_steps_per_s(env, cfg.num_envs, cfg.seed)
        for r in range(cfg.rounds):
            for name, env in envs.items():
                rates[name].append(random_steps_per_s(env, per_round, cfg.seed + r))
    finally:
        for env in envs.values():
            env.close()
    med = {name: statistics.median(v) for name, v in rates.items()}
    print(f"env, {cfg.num_envs} envs: " + ", ".join(f"{name} {med[name]:,.0f} steps/s" for name in med)
          + f"; skin / plain = {med['skin'] / med['plain']:.3f}")
    return {
        "num_envs": cfg.num_envs,
        **{f"{name}_steps_per_s": round(v, 1) for name, v in med.items()},
        "skin_over_plain": round(med["skin"] / med["plain"], 4),
        "skin_over_xela_off": round(med["skin"] / med["xela_off"], 4),
    }


def measure_encoder(cfg: Config) -> dict:
    """Sparsh-skin latency for one hand window on the CPU (see the module docstring)."""
    import time

    import numpy as np
    import torch

    from envs.sensors.xela import NUM_TAXELS, REST, WINDOW
    from rotation.tactile.models.encoders import load_encoder
    from rotation.tactile.models.sparsh_skin import SIZES, SparshSkin, SparshSkinConfig

    if cfg.encoder_size not in SIZES or cfg.iters < 1 or cfg.threads < 0:
        raise ValueError(f"encoder_size must be one of {', '.join(SIZES)}, iters >= 1 and threads >= 0, got "
                         f"{cfg.encoder_size!r}, {cfg.iters}, {cfg.threads}")
    threads = torch.get_num_threads()
    if cfg.threads:
        torch.set_num_threads(cfg.threads)
    try:
        torch.manual_seed(cfg.seed)
        if cfg.checkpoint:
            model = load_encoder(cfg.checkpoint).eval()
            if not isinstance(model, SparshSkin):
                raise ValueError(f"checkpoint: {cfg.checkpoint} is not a Sparsh-skin encoder")
        else:
            model = SparshSkin(SparshSkinConfig(size=cfg.encoder_size)).eval()
        size = model.cfg.size
        rng = np.random.default_rng(cfg.seed)
        counts = REST + 300.0 * rng.standard_normal((1, WINDOW, NUM_TAXELS, 3))
        window = {"skin": torch.as_tensor(np.concatenate([counts, 0.1 * rng.random((1, WINDOW, NUM_TAXELS, 3))],
                                                         axis=-1), dtype=torch.float32),
                  "xela_baseline": torch.full((1, NUM_TAXELS, 3), REST)}
        times = []
        with torch.inference_mode():
            for k in range(cfg.iters + 2):
                start = time.perf_counter()
                model.encode(window)
                if k >= 2:  # the first calls allocate
                    times.append(1e3 * (time.perf_counter() - start))
        ms, p95 = statistics.median(times), float(np.percentile(times, 95))
        used = torch.get_num_threads()
    finally:
        torch.set_num_threads(threads)
    print(f"encoder: Sparsh-skin {size}{f' ({cfg.checkpoint})' if cfg.checkpoint else ''}, one hand window "
          f"(368 taxels x 10 frames), CPU, {used} thread(s): {ms:.1f} ms median, {p95:.1f} ms p95 over {cfg.iters}: "
          f"{1e3 / ms:.0f} windows/s (the skin streams at 100 Hz)")
    return {f"skin_{size}_ms": round(ms, 2), f"skin_{size}_p95_ms": round(p95, 2),
            f"skin_{size}_hz": round(1e3 / ms, 1), f"skin_{size}_params": model.num_parameters(),
            "encoder_threads": used}


MEASUREMENTS: dict[str, Callable[[Config], dict]] = {
    "env": measure_env,
    "encoder": measure_encoder,
}
"""Name -> measurement."""


def run(cfg: Config) -> dict:
    """The selected measurements; prints a line per measurement and, last, the JSON result (also returned)."""
    if min(cfg.num_envs, cfg.steps, cfg.rounds) < 1 or cfg.nthread < 0:
        raise ValueError(f"num_envs, steps and rounds must be >= 1 and nthread >= 0, got {cfg}")
    unknown = [name for name in cfg.only if name not in MEASUREMENTS]
    if unknown:
        raise ValueError(f"only: unknown measurement(s) {unknown}; measurements: {', '.join(MEASUREMENTS)}")
    load_before = os.getloadavg()[0]
    result: dict = {}
    for name, measure in MEASUREMENTS.items():
        if not cfg.only or name in cfg.only:
            result.update(measure(cfg))
    result["loadavg_1min_before"] = round(load_before, 2)
    print(json.dumps(result))
    return result


def main(argv: list[str] | None = None) -> int:
    return script_main(Config, run, __doc__, argv)


if __name__ == "__main__":
    raise SystemExit(main())
