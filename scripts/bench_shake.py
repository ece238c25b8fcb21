"""Benchmark: how fast `rotate collect --task shake` records shaking windows on this machine.

Collects ``episodes`` shaking episodes (``shake_s`` seconds each; the content drawn per episode, the count of each
printed) into a temporary folder with the real collector, then prints the simulated seconds per wall second and:

- ``windows_per_s``: Sparsh-X windows the sessions hold per wall second (one per 30 fps frame and fingertip once a
  window's 1.12 s of history is there, as the loader cuts them);
- ``minutes_per_1000_windows`` and ``target_ratio``: the target is 1,000 windows in under 10 minutes on 2 cores
  (ratio < 1 meets it).

The last line printed is a JSON object with every figure.

    python scripts/bench_shake.py
    python scripts/bench_shake.py --episodes 20 --shake-s 3
"""

from __future__ import annotations

import json
import os
import tempfile
import time
from dataclasses import dataclass
from pathlib import Path

from rotation.configs import script_main


@dataclass
class Config:
    episodes: int = 10
    """Episodes to collect."""
    shake_s: float = 3.0
    """Seconds per episode."""
    seed: int = 0
    """Collection seed."""


def run(cfg: Config) -> dict:
    from rotation.data.dataset import TouchWindows, find_sessions
    from rotation.data.session_reader import SessionReader
    from rotation.jobs import collect

    if cfg.episodes < 1 or cfg.shake_s < 1.2:
        raise ValueError(f"episodes must be >= 1 and shake_s >= 1.2 s, got {cfg.episodes} and {cfg.shake_s}")
    load = os.getloadavg()[0]
    with tempfile.TemporaryDirectory() as tmp:
        out = Path(tmp) / "shake"
        t0 = time.perf_counter()
        collect.run(collect.Config(task="shake", episodes=cfg.episodes, out=out, seed=cfg.seed, shake_s=cfg.shake_s,
                                   progress=False))
        elapsed = time.perf_counter() - t0
        paths = find_sessions(out)
        windows = len(TouchWindows(paths))
        contents: dict[str, int] = {}
        for p in paths:
            with SessionReader(p) as r:
                name = r.meta.properties["content"]
                contents[name] = contents.get(name, 0) + 1
    result = {"episodes": cfg.episodes, "shake_s": cfg.shake_s, "wall_s": round(elapsed, 2),
              "sim_s_per_s": round(cfg.episodes * cfg.shake_s / elapsed, 3), "windows": windows,
              "windows_per_s": round(windows / elapsed, 2),
              "minutes_per_1000_windows": round(1000 / (windows / elapsed) / 60, 3),
              "contents": contents, "loadavg_1min_before": round(load, 2)}
    result["target_ratio"] = round(result["minutes_per_1000_windows"] / 10.0, 4)
    print(f"shake collection: {cfg.episodes} episodes ({cfg.shake_s:g} s) in {elapsed:.1f} s, {windows} windows: "
          f"{result['minutes_per_1000_windows']:.2f} min per 1,000 windows (target < 10)")
    print(json.dumps(result))
    return result


def main(argv: list[str] | None = None) -> int:
    return script_main(Config, run, __doc__, argv)


if __name__ == "__main__":
    raise SystemExit(main())
