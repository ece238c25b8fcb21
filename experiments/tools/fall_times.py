"""When do the cups fall? Fall times of `rotate evaluate` runs, per condition and policy, as survival curves.

A mean ttf hides two different failures: a cup the grasp never held (it falls in the first second, before the policy
has done much) and a cup lost while turning. This script reads the per-episode values an evaluation keeps
(results.json: ``per_episode.ttf`` and ``in_hand_time``) and reports, per condition and policy: episodes, falls, falls
within the first ``--early`` seconds, cups held to the end, and the median fall time; and draws the share of cups
still in the hand against time (``survival.png``, one panel per condition).

    python experiments/tools/fall_times.py --runs runs/eval_s11 --out runs/fall_times
    python experiments/tools/fall_times.py --runs old=runs/eval_a new=runs/eval_b --early 1.0 --out runs/fall_times

With several runs, each policy's name is prefixed by its run's name. The last line printed is a JSON object with
every figure (also OUT/fall_times.json).
"""

from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402

from envs.validation import check_number, check_output_dir  # noqa: E402
from rotation.configs import script_main  # noqa: E402


@dataclass
class Config:
    """Fall-time settings."""

    runs: tuple[str, ...] = ()
    """`rotate evaluate` output folders (each holding results.json), or NAME=FOLDER."""
    early: float = 2.0
    """A fall within this many seconds of the start counts as early (s)."""
    out: Path = Path("runs/fall_times")
    """Folder of survival.png and fall_times.json."""

    def __post_init__(self) -> None:
        if not self.runs:
            raise ValueError("runs: give at least one `rotate evaluate` output folder")
        check_number("early", self.early, 0.0, 3600.0, low_open=True, unit="s")
        self.out = Path(self.out)
        check_output_dir("out", self.out)


def _named(entry: str) -> tuple[str, Path]:
    name, sep, path = entry.partition("=")
    return (name, Path(path)) if sep and name and path else (Path(entry).name, Path(entry))


def read_rows(entry: str) -> tuple[str, list[dict]]:
    """(run name, result rows) of one evaluation folder; a clear error for a folder without usable results."""
    name, folder = _named(entry)
    path = folder / "results.json"
    if not path.is_file():
        raise ValueError(f"runs: {path} does not exist (give a `rotate evaluate` output folder)")
    try:
        rows = json.loads(path.read_text())["rows"]
        for row in rows:
            per = row["per_episode"]
            if len(per["ttf"]) != len(per["in_hand_time"]):
                raise ValueError("per-episode lists of different lengths")
    except (KeyError, TypeError, ValueError) as err:
        raise ValueError(f"runs: {path} holds no per-episode ttf and in_hand_time ({err})") from None
    return name, rows


def fall_stats(ttf: np.ndarray, in_hand: np.ndarray, early: float) -> dict:
    """Figures of one (condition, policy): ``ttf`` (fractions, 1 = held to the end) and the seconds in hand."""
    fell = ttf < 1.0
    times = in_hand[fell]
    return {"episodes": int(ttf.size), "fell": int(fell.sum()), "fell_early": int((fell & (in_hand <= early)).sum()),
            "held": int((~fell).sum()), "ttf": round(float(ttf.mean()), 4),
            "median_fall_s": round(float(np.median(times)), 2) if times.size else None}


def run(cfg: Config) -> dict:
    runs = [read_rows(entry) for entry in cfg.runs]  # every folder checked before any work
    several = len(runs) > 1
    result: dict[str, dict[str, dict]] = {}
    curves: dict[str, dict[str, tuple[np.ndarray, float]]] = {}
    for run_name, rows in runs:
        for row in rows:
            policy = f"{run_name}/{row['policy']}" if several else row["policy"]
            ttf = np.asarray(row["per_episode"]["ttf"], np.float64)
            in_hand = np.asarray(row["per_episode"]["in_hand_time"], np.float64)
            held = ttf >= 1.0
            duration = float(in_hand[held].max()) if held.any() else float((in_hand / np.maximum(ttf, 1e-9)).max())
            result.setdefault(row["condition"], {})[policy] = fall_stats(ttf, in_hand, cfg.early)
            curves.setdefault(row["condition"], {})[policy] = (np.where(held, np.inf, in_hand), duration)
    print(f"{'condition':<28} {'policy':<22} {'episodes':>8} {'fell':>5} {'early':>6} {'held':>5} {'ttf':>6}")
    for cond, by_policy in result.items():
        for policy, s in by_policy.items():
            print(f"{cond:<28} {policy:<22} {s['episodes']:>8} {s['fell']:>5} {s['fell_early']:>6} {s['held']:>5} "
                  f"{s['ttf']:>6.3f}")
    cfg.out.mkdir(parents=True, exist_ok=True)
    cols = min(3, len(curves))
    rows = -(-len(curves) // cols)
    fig, axes = plt.subplots(rows, cols, figsize=(4.2 * cols, 3.2 * rows), squeeze=False, sharey=True)
    for ax in axes.ravel()[len(curves):]:
        ax.set_visible(False)
    for ax, (cond, by_policy) in zip(axes.ravel(), curves.items(), strict=False):
        for i, (policy, (falls, duration)) in enumerate(by_policy.items()):
            t = np.linspace(0.0, duration, 201)
            ax.plot(t, (falls[None, :] > t[:, None]).mean(1), color=f"C{i}", lw=1.6, label=policy)
        ax.axvline(cfg.early, color="0.5", ls="--", lw=0.8)
        ax.set_title(cond, fontsize=9)
        ax.set_xlabel("time (s)")
        ax.set_ylim(0, 1.02)
        ax.legend(fontsize=7, loc="lower left")
    for row in axes:
        row[0].set_ylabel(f"cups in hand (dashed: {cfg.early:g} s)")
    fig.tight_layout()
    fig.savefig(cfg.out / "survival.png", dpi=110)
    plt.close(fig)
    out = {"early_s": cfg.early, "conditions": result}
    (cfg.out / "fall_times.json").write_text(json.dumps(out, indent=2) + "\n")
    print(json.dumps(out))
    return out


def main(argv: list[str] | None = None) -> int:
    return script_main(Config, run, __doc__, argv)


if __name__ == "__main__":
    raise SystemExit(main())
