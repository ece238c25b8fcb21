"""Plot training curves from a run's TensorBoard logs (PNG + CSV), e.g. for a model card or a report.

    python scripts/plot_training.py --run runs/teacher --out docs/results/teacher_training
    python scripts/plot_training.py --run runs/student --out docs/results/student_training --tags train/latent_mse
"""

from __future__ import annotations

import csv
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
    out: Path = Path("docs/results/teacher_training")
    """Output directory for curves.png and curves.csv."""
    tags: tuple[str, ...] = ("episode/rotation_rate", "episode/ttf", "episode/rew_rotate", "episode/return")
    """Scalar tags to plot, one panel each."""
    smooth: int = 25
    """Moving-average window (log points) drawn over the raw curve."""


def run(cfg: Config) -> Path:
    files = sorted(cfg.run.rglob("events.out.tfevents.*"))
    if not files:
        raise ValueError(f"no TensorBoard event files under {cfg.run}")
    series: dict[str, tuple[np.ndarray, np.ndarray]] = {}
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
    cfg.out.mkdir(parents=True, exist_ok=True)
    fig, axes = plt.subplots(1, len(cfg.tags), figsize=(4.2 * len(cfg.tags), 3.2))
    for ax, tag in zip(np.atleast_1d(axes), cfg.tags, strict=True):
        steps, values = series[tag]
        ax.plot(steps / 1e6, values, color="0.75", lw=0.8)
        if len(values) >= cfg.smooth > 1:
            kernel = np.ones(cfg.smooth) / cfg.smooth
            ax.plot(steps[cfg.smooth - 1 :] / 1e6, np.convolve(values, kernel, mode="valid"), color="C0", lw=1.6)
        ax.set_title(tag)
        ax.set_xlabel("env steps (M)")
        ax.grid(alpha=0.3)
    fig.tight_layout()
    png = cfg.out / "curves.png"
    fig.savefig(png, dpi=110)
    plt.close(fig)
    with (cfg.out / "curves.csv").open("w", newline="") as f:
        writer = csv.writer(f)
        writer.writerow(["tag", "step", "value"])
        for tag in cfg.tags:  # at most ~500 rows per tag (every k-th log point)
            steps, values = series[tag]
            k = max(1, len(steps) // 500)
            for s, v in zip(steps[::k], values[::k], strict=True):
                writer.writerow([tag, int(s), float(v)])
    print(f"wrote {png}")
    return png


def main(argv: list[str] | None = None) -> int:
    return script_main(Config, run, __doc__, argv)


if __name__ == "__main__":
    raise SystemExit(main())
