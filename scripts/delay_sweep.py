"""What the touch delay costs a tactile adapter: its ttf against the delay, beside its student and teacher.

Runs `rotate evaluate` (rotation.evaluate.job) once for the student and the teacher (they read no touch) and once
per delay for the adapter, on the same conditions, episodes and seeds, each into its own folder under OUT (a stopped
sweep continues where it stopped: every evaluation resumes), then writes:

- ``OUT/delay_sweep.md``: per condition, the ttf (mean ± standard error) of the student, of the adapter at each
  delay and of the teacher, and the share of the student-to-teacher ttf gap the adapter closes at each delay;
- ``OUT/delay_sweep.json``: the same numbers;
- ``OUT/delay_sweep.png``: ttf against the delay (control steps) per condition, the student's and the teacher's as
  horizontal lines.

    python scripts/delay_sweep.py --adapter runs/adapter/bundle --student runs/student/bundle \\
        --teacher runs/teacher/bundle --episodes 128 --seed 50000 --out runs/delay_sweep

Delays are whole control steps (``--touch-delay N`` of every refresh); ``measured`` may be given among them.
"""

from __future__ import annotations

import json
import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from adapters.touch_delay import parse_delay
from rotation.configs import script_main

DEFAULT_CONDITIONS = ("nominal", "friction_0.25", "mass_+0.1kg", "friction_0.5+mass_+0.1kg")
"""The perturbation suite's slippery, heavy and combined extremes on the vendor-kinematics hand (whose heaviest cup
leaves room for +0.1 kg; rotation.evaluate.suites), and nominal."""


@dataclass
class Config:
    adapter: str = "adapter"
    """The tactile adapter bundle (path or shipped name)."""
    student: str = "student"
    """Its student (the gap's lower end)."""
    teacher: str = "teacher"
    """The teacher (the gap's upper end)."""
    delays: tuple[str, ...] = ("0", "1", "2", "3", "4")
    """Touch delays to evaluate the adapter at (adapters.touch_delay text: N, or 'measured')."""
    conditions: tuple[str, ...] = DEFAULT_CONDITIONS
    """Conditions of the perturbation suite (rotation.evaluate.suites)."""
    episodes: int = 64
    """Episodes per policy, condition and delay."""
    seed: int = 50000
    """Episode j runs in an env seeded seed + j (the same for every policy and delay)."""
    num_envs: int = 16
    """Simulations stepped together."""
    episode_steps: int = 400
    """Episode length in policy steps (ttf is relative to it)."""
    out: Path = Path("runs/delay_sweep")
    """Folder of the sweep's evaluations and report."""
    progress: bool = True
    """Show progress bars."""


def _evaluate(cfg: Config, policies: dict[str, str], delay: str, out: Path) -> list[dict]:
    from rotation.evaluate.job import Config as EvaluateConfig
    from rotation.evaluate.job import run

    return run(EvaluateConfig(policies=policies, suite="perturbations", conditions=tuple(cfg.conditions),
                              episodes=cfg.episodes, seed=cfg.seed, num_envs=cfg.num_envs, out=out,
                              episode_steps=cfg.episode_steps,
                              touch_delay=delay, progress=cfg.progress))


def _ttf(row: dict) -> tuple[float, float]:
    """Mean ttf and its standard error over the row's episodes."""
    return row["ttf"], row["ttf_std"] / math.sqrt(max(row["episodes"], 1))


def sweep(cfg: Config) -> dict:
    for d in cfg.delays:
        parse_delay(d)  # every delay is checked before anything runs
    cfg.out.mkdir(parents=True, exist_ok=True)
    base = _evaluate(cfg, {"student": cfg.student, "teacher": cfg.teacher}, "0", cfg.out / "baselines")
    table: dict[str, dict] = {c: {"delays": {}} for c in cfg.conditions}
    for row in base:
        table[row["condition"]][row["policy"]] = _ttf(row)
    for d in cfg.delays:
        for row in _evaluate(cfg, {"adapter": cfg.adapter}, d, cfg.out / f"delay_{d}"):
            entry = table[row["condition"]]
            ttf, se = _ttf(row)
            gap = entry["teacher"][0] - entry["student"][0]
            entry["delays"][d] = {"ttf": ttf, "se": se,
                                  "gap_closed": (ttf - entry["student"][0]) / gap if abs(gap) > 1e-9 else None}
    report = {"adapter": cfg.adapter, "student": cfg.student, "teacher": cfg.teacher, "episodes": cfg.episodes,
              "seed": cfg.seed, "conditions": table}
    (cfg.out / "delay_sweep.json").write_text(json.dumps(report, indent=2) + "\n")
    (cfg.out / "delay_sweep.md").write_text(markdown(cfg, table))
    plot(cfg, table, cfg.out / "delay_sweep.png")
    print(f"delay_sweep: {cfg.out / 'delay_sweep.md'}")
    return report


def markdown(cfg: Config, table: dict) -> str:
    head = "| condition | student | " + " | ".join(f"adapter, delay {d}" for d in cfg.delays) + " | teacher |"
    lines = [f"# ttf against the touch delay ({cfg.episodes} episodes per cell, seeds {cfg.seed}+)", "",
             "Mean ttf ± standard error; in brackets the share of the student-to-teacher gap the adapter closes.", "",
             head, "|" + "---|" * (len(cfg.delays) + 3)]
    for cond, entry in table.items():
        cells = []
        for d in cfg.delays:
            e = entry["delays"][d]
            share = "" if e["gap_closed"] is None else f" ({100 * e['gap_closed']:.0f}%)"
            cells.append(f"{e['ttf']:.3f} ± {e['se']:.3f}{share}")
        s, t = entry["student"], entry["teacher"]
        lines.append(f"| {cond} | {s[0]:.3f} ± {s[1]:.3f} | " + " | ".join(cells) + f" | {t[0]:.3f} ± {t[1]:.3f} |")
    return "\n".join(lines) + "\n"


def plot(cfg: Config, table: dict, path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    steps = [parse_delay(d).mean for d in cfg.delays]
    fig, axes = plt.subplots(1, len(table), figsize=(3.2 * len(table), 3.2), sharey=True, squeeze=False)
    for ax, (cond, entry) in zip(axes[0], table.items(), strict=True):
        ttf = np.array([entry["delays"][d]["ttf"] for d in cfg.delays])
        se = np.array([entry["delays"][d]["se"] for d in cfg.delays])
        ax.errorbar(steps, ttf, yerr=se, marker="o", label="adapter")
        ax.axhline(entry["student"][0], color="tab:gray", ls="--", label="student")
        ax.axhline(entry["teacher"][0], color="tab:green", ls=":", label="teacher")
        ax.set_title(cond, fontsize=9)
        ax.set_xlabel("touch delay (control steps)")
    axes[0][0].set_ylabel("ttf")
    axes[0][0].legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def main(argv: list[str] | None = None) -> int:
    return script_main(Config, sweep, __doc__, argv)


if __name__ == "__main__":
    raise SystemExit(main())
