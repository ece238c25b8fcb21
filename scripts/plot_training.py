"""Plot training curves from a run's TensorBoard logs or its curves.jsonl (PNG + CSV), e.g. for a model card.

    python scripts/plot_training.py --run runs/teacher --out runs/teacher_plots
    python scripts/plot_training.py --run runs/student --out runs/student_plots --tags train/latent_mse
    python scripts/plot_training.py --curves runs/a/curves.jsonl runs/b/curves.jsonl \
        --out runs/teacher_plots --tags rotation_rate ttf upright l

With --curves, the files are read in order as one history: each file's steps continue after the previous file's
last step (a run started with `train-teacher --init-from` counts its steps from zero).

With --compare, each NAME=curves.jsonl is its own run, drawn as one smoothed line per run on shared panels (the
raw points faint in the same colour), e.g. two recipes step for step:

    python scripts/plot_training.py --compare overlap=runs/a/curves.jsonl no-overlap=runs/b/curves.jsonl \
        --out runs/compare --name compare --tags rotation_rate ttf upright l

The CSV then has a leading ``run`` column.
"""

from __future__ import annotations

import csv
import json
from dataclasses import dataclass
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402
from tensorboard.backend.event_processing.event_accumulator import EventAccumulator  # noqa: E402

from rotation.configs import script_main  # noqa: E402


@dataclass
class Config:
    run: Path = Path("runs/teacher")
    """Run directory holding tb/ (TensorBoard event files, searched recursively)."""
    out: Path = Path("runs/training_plots")
    """Output directory for curves.png and curves.csv."""
    tags: tuple[str, ...] = ("episode/rotation_rate", "episode/ttf", "episode/rew_rotate", "episode/return")
    """Scalar tags to plot, one panel each."""
    smooth: int = 25
    """Moving-average window (log points) drawn over the raw curve."""
    x_label: str = "env steps (M)"
    """Label of the x axis (the logged step, divided by x_scale)."""
    x_scale: float = 1e6
    """The logged step is divided by this (1e6: millions of env steps; 1 for optimizer steps)."""
    curves: tuple[Path, ...] = ()
    """curves.jsonl files (train-teacher's per-rollout episode means) to plot instead of TensorBoard logs."""
    compare: tuple[str, ...] = ()
    """NAME=curves.jsonl entries, one run each, overlaid on shared panels (instead of --run / --curves)."""
    name: str = "curves"
    """Stem of the files written in --out (NAME.png, NAME.csv)."""


TITLES = {"l": "episode length (steps)", "ep_length": "episode length (steps)", "latent_mse": "latent MSE",
          "student_mse": "student's latent MSE", "action_mse": "action MSE (vs on the teacher's z)",
          "student_action_mse": "student's action MSE", "r": "episode return", "ttf": "ttf",
          "upright": "upright (fraction)", "rotation_rate": "rotation rate (rad/s)"}
"""Panel titles of curves.jsonl keys (training episodes, stochastic actions)."""


def read_curves(files: tuple[Path, ...], tags: tuple[str, ...]) -> dict[str, tuple[np.ndarray, np.ndarray]]:
    """One history from curves.jsonl files in order, each continuing the step count of the one before."""
    rows, offset = [], 0
    for path in files:
        if not Path(path).is_file():
            raise ValueError(f"no such curves file: {path}")
        part = [json.loads(line) for line in Path(path).read_text().splitlines() if line.strip()]
        # teacher rows count env steps in "steps", student rows in "env_steps"
        rows += [dict(r, steps=r.get("steps", r.get("env_steps", 0)) + offset) for r in part]
        offset = rows[-1]["steps"] if rows else offset
    return {t: (np.array([r["steps"] for r in rows if t in r]), np.array([r[t] for r in rows if t in r]))
            for t in tags if any(t in r for r in rows)}


def parse_compare(entries: tuple[str, ...]) -> dict[str, Path]:
    """NAME=PATH entries -> {name: path}, with a clear error for a malformed or repeated name."""
    runs: dict[str, Path] = {}
    for entry in entries:
        name, sep, path = entry.partition("=")
        if not sep or not name.strip() or not path.strip():
            raise ValueError(f"--compare entries are NAME=curves.jsonl, got {entry!r}")
        if name.strip() in runs:
            raise ValueError(f"--compare names a run twice: {name.strip()!r}")
        runs[name.strip()] = Path(path.strip())
    return runs


def run(cfg: Config) -> Path:
    if not cfg.x_scale > 0:
        raise ValueError(f"x_scale must be > 0, got {cfg.x_scale}")
    if not cfg.name or "/" in cfg.name:
        raise ValueError(f"name must be a file stem without '/', got {cfg.name!r}")
    if cfg.compare:
        if cfg.curves:
            raise ValueError("give either --compare or --curves, not both")
        return _plot_compare(cfg, {name: read_curves((path,), cfg.tags) for name, path in
                                   parse_compare(cfg.compare).items()})
    series: dict[str, tuple[np.ndarray, np.ndarray]] = read_curves(cfg.curves, cfg.tags) if cfg.curves else {}
    files = [] if cfg.curves else sorted(cfg.run.rglob("events.out.tfevents.*"))
    if not files and not cfg.curves:
        raise ValueError(f"no TensorBoard event files under {cfg.run}")
    for f in files:
        acc = EventAccumulator(str(f), size_guidance={"scalars": 0})
        acc.Reload()
        for tag in cfg.tags:
            if tag in acc.Tags()["scalars"]:
                ev = acc.Scalars(tag)
                series[tag] = (np.array([e.step for e in ev]), np.array([e.value for e in ev]))
    missing = [t for t in cfg.tags if t not in series]
    if missing:
        raise ValueError(f"tags {missing} are not in {cfg.run}'s logs")
    return _write(cfg, {"": series})


def _plot_compare(cfg: Config, runs: dict[str, dict[str, tuple[np.ndarray, np.ndarray]]]) -> Path:
    for name, series in runs.items():
        missing = [t for t in cfg.tags if t not in series]
        if missing:
            raise ValueError(f"tags {missing} are not in run {name!r}'s curves")
    return _write(cfg, runs)


def _write(cfg: Config, runs: dict[str, dict[str, tuple[np.ndarray, np.ndarray]]]) -> Path:
    """Panels (one per tag) with one raw + smoothed line per run; a legend when runs are named (--compare)."""
    named = any(runs)
    cfg.out.mkdir(parents=True, exist_ok=True)
    fig, axes = plt.subplots(1, len(cfg.tags), figsize=(4.2 * len(cfg.tags), 3.2))
    for ax, tag in zip(np.atleast_1d(axes), cfg.tags, strict=True):
        for i, (name, series) in enumerate(runs.items()):
            steps, values = series[tag]
            color = f"C{i}"
            if not len(values) >= cfg.smooth > 1:  # nothing to smooth (few points): the raw line is the curve
                ax.plot(steps / cfg.x_scale, values, color=color, lw=1.6, marker="o", ms=3, label=name or None)
                continue
            ax.plot(steps / cfg.x_scale, values, color=color if named else "0.75", alpha=0.25 if named else 1.0,
                    lw=0.8)
            kernel = np.ones(cfg.smooth) / cfg.smooth
            ax.plot(steps[cfg.smooth - 1 :] / cfg.x_scale, np.convolve(values, kernel, mode="valid"),
                    color=color, lw=1.6, label=name or None)
        ax.set_title(TITLES.get(tag, tag))
        ax.set_xlabel(cfg.x_label)
        ax.grid(alpha=0.3)
    if named:
        np.atleast_1d(axes)[0].legend(fontsize=8)
    fig.tight_layout()
    png = cfg.out / f"{cfg.name}.png"
    fig.savefig(png, dpi=110)
    plt.close(fig)
    with (cfg.out / f"{cfg.name}.csv").open("w", newline="") as f:
        writer = csv.writer(f)
        writer.writerow((["run"] if named else []) + ["tag", "step", "value"])
        for name, series in runs.items():
            for tag in cfg.tags:  # at most ~500 rows per tag and run (every k-th log point)
                steps, values = series[tag]
                k = max(1, len(steps) // 500)
                for s, v in zip(steps[::k], values[::k], strict=True):
                    writer.writerow(([name] if named else []) + [tag, int(s), float(v)])
    print(f"wrote {png}")
    return png


def main(argv: list[str] | None = None) -> int:
    return script_main(Config, run, __doc__, argv)


if __name__ == "__main__":
    raise SystemExit(main())
