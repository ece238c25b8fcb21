"""Benchmark: physics steps per second of the batched RotateCup env against raw MuJoCo and SB3's SubprocVecEnv.

Three measurements in one run, on the same machine, thread count and env config:

- raw: `mujoco.batch.Batch.step(nstep=substeps)` on the env's own compiled model and per-env model fields, from
  the state of a reset, with the controls held at the grasp pose. No Python work between calls: the limit.
- vec: the batched gymnasium env (`RotateCupVectorEnv`, same-step auto-reset) stepped with the configured actions;
  physics steps/s = control steps/s x substeps x num_envs. Also the SB3 adapter used for training.
- subproc: stable-baselines3 `SubprocVecEnv` over the single `RotateCupEnv`, one worker process per core (the fair
  setting: more workers than cores only adds context switches).

The default batch size, 256, is the teacher's `num_envs` (rotation/train/teacher.py). The steppers take turns of
a fraction of a second within each round, and each rate is the median over rounds, so that a load that changes
during the run (e.g. a training job on the same cores) biases none of them. The last line printed is a JSON object
with `vec_over_raw` (target >= 0.8) and `vec_over_subproc` (target >= 3 on 2 cores).

    python scripts/bench_env.py
    python scripts/bench_env.py --num-envs 1024 --seconds 5 --action 0.2 --rounds 5
    python scripts/bench_env.py --hand digit360_v4                      # on the hardware's physics
"""

from __future__ import annotations

import json
import os
import statistics
import time
import warnings
from dataclasses import dataclass
from functools import partial

import numpy as np
from stable_baselines3.common.vec_env import SubprocVecEnv

from envs.config import EnvConfig
from envs.constants import DEFAULT_HAND
from envs.core import RotateCupVec
from envs.rotate_cup import RotateCupEnv
from envs.vector import RotateCupVectorEnv
from rotation.configs import num_cores, script_main
from rotation.train.vec_env import RotateCupSB3VecEnv


@dataclass
class Config:
    """Benchmark settings."""

    num_envs: int = 256
    """Simulations in the batch; 256 is the teacher's num_envs (rotation/train/teacher.py)."""
    nthread: int = 0
    """MuJoCo threads of the batch (0 = all cores of this process)."""
    subproc_envs: int = 0
    """Worker processes of the SubprocVecEnv baseline (0 = one per core, the fair setting)."""
    seconds: float = 3.0
    """Wall time given to each stepper in each round (s)."""
    slice: float = 0.25
    """The steppers take turns of this many seconds within a round, so that all of them see the same load."""
    rounds: int = 3
    """Rounds of measurements; each rate is the median over rounds."""
    action: float = 0.0
    """Actions are uniform in [-action, action] (0 = zero actions: the targets stay at the grasp pose, the ctrl
    of the raw measurement)."""
    object: str = "cup"
    """Object (envs.objects)."""
    grasp_cache: str = ""
    """Grasp cache file; empty = the one shipped for the object."""
    seed: int = 0
    """Seed of the envs and of the actions."""
    hand: str = DEFAULT_HAND
    """Hand variant (envs.scene.HANDS) with its physics: 'digit360_v4' measures the hardware's physics (elliptic
    cones, noslip, the action delay's split steps)."""


def _timed(step, seconds: float) -> tuple[int, float]:
    """Call ``step()`` until ``seconds`` have passed (at least once); returns (calls, wall s)."""
    calls, start = 0, time.perf_counter()
    while True:
        step()
        calls += 1
        wall = time.perf_counter() - start
        if wall >= seconds:
            return calls, wall


class Bench:
    """The steppers, built once: ``steppers[name] = (step, physics steps per call)``."""

    def __init__(self, cfg: Config):
        self.cfg = cfg
        self.env_cfg = EnvConfig(object=cfg.object, grasp_cache=cfg.grasp_cache, hand=cfg.hand)
        self.substeps = self.env_cfg.substeps
        self.nthread = cfg.nthread or num_cores()
        self.subproc_envs = cfg.subproc_envs or num_cores()
        n, a = cfg.num_envs, cfg.action
        rng = np.random.default_rng(cfg.seed)
        # a pool of action batches, cycled, so that drawing them is not timed and targets do not drift one way
        self.pool = [rng.uniform(-a, a, (n, 16)).astype(np.float32) for _ in range(16)]
        self.calls = 0
        # raw: a core reset like the env's, whose batch is then stepped directly with the ctrl left at the grasp
        self.raw = RotateCupVec(self.env_cfg, num_envs=n, seed=cfg.seed, nthread=self.nthread)
        self.raw.reset(seed=cfg.seed)
        self.vec = RotateCupVectorEnv(n, cfg=self.env_cfg, nthread=self.nthread)
        self.vec.reset(seed=cfg.seed)
        with warnings.catch_warnings():  # SB3 asks the adapter for a render_mode it does not have: harmless
            warnings.filterwarnings("ignore", message="The `render_mode` attribute is not defined")
            self.sb3 = RotateCupSB3VecEnv(self.env_cfg, n, seed=cfg.seed, nthread=self.nthread)
        self.sb3.reset()
        # one single-env worker process per core; RotateCupEnv steps its one simulation on one thread
        self.subproc = SubprocVecEnv([partial(RotateCupEnv, self.env_cfg) for _ in range(self.subproc_envs)])
        self.subproc.seed(cfg.seed)
        self.subproc.reset()
        self.episode_ends = {"vec": 0, "sb3": 0, "subproc": 0}
        per_batch = self.substeps * n
        self.steppers = {
            "raw": (self._step_raw, per_batch),
            "vec": (self._step_vec, per_batch),
            "sb3": (self._step_sb3, per_batch),
            "subproc": (self._step_subproc, self.substeps * self.subproc_envs),
        }

    def _actions(self) -> np.ndarray:
        self.calls += 1
        return self.pool[self.calls % len(self.pool)]

    def _step_raw(self) -> None:
        self.raw.batch.step(nstep=self.substeps)

    def _step_vec(self) -> None:
        _, _, terminated, truncated, _ = self.vec.step(self._actions())
        self.episode_ends["vec"] += int(np.count_nonzero(terminated | truncated))

    def _step_sb3(self) -> None:
        self.sb3.step_async(self._actions())
        self.episode_ends["sb3"] += int(np.count_nonzero(self.sb3.step_wait()[2]))

    def _step_subproc(self) -> None:
        self.subproc.step_async(self._actions()[: self.subproc_envs])
        self.episode_ends["subproc"] += int(np.count_nonzero(self.subproc.step_wait()[2]))

    def round(self, seconds: float, slice_s: float) -> dict[str, float]:
        """Physics steps/s of each stepper over one round: slices of ``slice_s`` in turn, ``seconds`` each in all."""
        calls = dict.fromkeys(self.steppers, 0)
        wall = dict.fromkeys(self.steppers, 0.0)
        while min(wall.values()) < seconds:
            for name, (step, _) in self.steppers.items():
                c, w = _timed(step, min(slice_s, max(seconds - wall[name], 0.0)))
                calls[name] += c
                wall[name] += w
        return {name: calls[name] * per_call / wall[name] for name, (_, per_call) in self.steppers.items()}

    def close(self) -> None:
        self.subproc.close()
        self.vec.close()
        self.sb3.close()
        self.raw.close()


def run(cfg: Config) -> dict:
    """All measurements; prints a table and, last, the JSON result (also returned)."""
    if cfg.num_envs < 1 or cfg.rounds < 1 or not (cfg.seconds > 0 and cfg.slice > 0):
        raise ValueError(f"num_envs and rounds must be >= 1, seconds and slice > 0, got {cfg}")
    if cfg.nthread < 0 or cfg.subproc_envs < 0 or not 0.0 <= cfg.action <= 1.0:
        raise ValueError(f"nthread and subproc_envs must be >= 0 and action in [0, 1], got {cfg}")
    load_before = os.getloadavg()[0]
    bench = Bench(cfg)
    try:
        bench.round(min(cfg.slice, cfg.seconds), cfg.slice)  # warm-up: first calls allocate and fault pages in
        rounds = [bench.round(cfg.seconds, cfg.slice) for _ in range(cfg.rounds)]
    finally:
        bench.close()
    rates = {name: [r[name] for r in rounds] for name in bench.steppers}
    med = {k: statistics.median(v) for k, v in rates.items()}
    result = {
        "num_envs": cfg.num_envs,
        "nthread": bench.nthread,
        "subproc_envs": bench.subproc_envs,
        "substeps": bench.substeps,
        "object": cfg.object,
        "action": cfg.action,
        "rounds": cfg.rounds,
        "seconds": cfg.seconds,
        "raw_steps_per_s": round(med["raw"], 1),
        "vec_steps_per_s": round(med["vec"], 1),
        "sb3_vec_steps_per_s": round(med["sb3"], 1),
        "subproc_steps_per_s": round(med["subproc"], 1),
        "vec_over_raw": round(med["vec"] / med["raw"], 4),
        "sb3_vec_over_raw": round(med["sb3"] / med["raw"], 4),
        "vec_over_subproc": round(med["vec"] / med["subproc"], 4),
        "episode_ends": bench.episode_ends,
        "loadavg_1min_before": round(load_before, 2),
        "loadavg_1min_after": round(os.getloadavg()[0], 2),
    }
    rows = [
        ("raw mujoco.batch.Batch.step", f"{cfg.num_envs} sims, {bench.nthread} threads", "raw"),
        ("RotateCupVectorEnv (gymnasium)", f"{cfg.num_envs} envs, {bench.nthread} threads", "vec"),
        ("RotateCupSB3VecEnv (training)", f"{cfg.num_envs} envs, {bench.nthread} threads", "sb3"),
        ("SB3 SubprocVecEnv(RotateCupEnv)", f"{bench.subproc_envs} processes x 1 env", "subproc"),
    ]
    print(f"physics steps/s, {bench.substeps} substeps per control step; median of {cfg.rounds} rounds of "
          f"{cfg.seconds:g} s per stepper, taken in turns of {cfg.slice:g} s; 1-min load average {load_before:.2f}")
    print(f"{'stepper':34s} {'setting':24s} {'median':>9s} {'min':>9s} {'max':>9s} {'/ raw':>7s}")
    for name, setting, key in rows:
        print(f"{name:34s} {setting:24s} {med[key]:9,.0f} {min(rates[key]):9,.0f} {max(rates[key]):9,.0f} "
              f"{med[key] / med['raw']:7.3f}")
    print(f"vec / raw = {result['vec_over_raw']:.3f} (target >= 0.8); vec / subproc = "
          f"{result['vec_over_subproc']:.2f} (target >= 3 on 2 cores)")
    print(json.dumps(result))
    return result


def main(argv: list[str] | None = None) -> int:
    return script_main(Config, run, __doc__, argv)


if __name__ == "__main__":
    raise SystemExit(main())
