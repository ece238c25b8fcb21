"""How the ladder reads the tokens and the object's properties: the fused and image tokens pooled by their mean alone
(the ladder before) or by mean and maximum (now), and every rung read from the moment's window alone or from the mean
of its features over the last 5 s of windows (now, for friction, mass and centre of mass). One table on the
report's own cached features and split (ridge readers, as the ladder's), at 10% and 100% of the labels; then how
the object's properties read against the history's length (0-20 s, 100% of the labels), drawn into OUT/history.png.

    python experiments/touch_ladder/v5_history/readings.py REPORT_DIR SESSIONS_DIR OUT_DIR
"""

import sys
from pathlib import Path

import numpy as np

from envs.constants import FINGERS
from rotation.tactile.ladder.fit import budget_sessions, fit_and_score
from rotation.tactile.ladder.job import prepare
from rotation.tactile.ladder.samples import MODALITIES, history_mean
from rotation.tactile.loading import session_paths

TARGETS = ("friction_tercile", "friction", "mass", "normal_force", "slip")
HISTORY = 5.0
"""The history the ladder reads the object's properties over (touch-report's default, chosen before its run)."""
CURVE = (0.0, 1.0, 2.0, 5.0, 10.0, 20.0)
"""History lengths (s) of the curve; 20 s is a whole session."""


def mean_only(x: np.ndarray) -> np.ndarray:
    """(M, 4 x 2D) tokens pooled [mean, max] per fingertip (ladder.encode.pool) -> (M, 4 x D) their mean halves."""
    m = x.reshape(len(x), len(FINGERS), 2, -1)
    return m[:, :, 0, :].reshape(len(x), -1)


def main(report: Path, sessions: Path, out: Path) -> None:
    history = HISTORY
    split = prepare(session_paths([sessions]), 0.25, 15, 0)  # touch-report's defaults, stride 15
    s = split.samples
    rendered, contact = dict(np.load(report / "features_rendered.npz")), dict(np.load(report / "features_contact.npz"))
    tok = {m: rendered[f"tokens/{m}"] for m in MODALITIES}
    sets = {
        "contact fields": contact["fields"],
        "streams, all": np.concatenate([rendered[f"stream/{m}"] for m in MODALITIES], 1),
        "streams, image": rendered["stream/image"],
        "tokens, all (mean)": np.concatenate([mean_only(tok[m]) for m in MODALITIES], 1),
        "tokens, all (mean + max)": np.concatenate([tok[m] for m in MODALITIES], 1),
        "tokens, image (mean)": mean_only(tok["image"]),
        "tokens, image (mean + max)": tok["image"],
    }
    print(f"{len(s)} samples, {len(split.train_ids)} training / {len(split.test_ids)} test sessions\n")
    print("| features | reading | labels | " + " | ".join(TARGETS) + " |")
    print("|---|---|---|" + "---|" * len(TARGETS))
    for budget in (0.1, 1.0):
        tr = np.isin(s.session, budget_sessions(split.train_ids, budget, 0))
        for name, x in sets.items():
            for reading, secs in (("window", 0.0), (f"{history:g} s", history)):
                xr = history_mean(x, s.session, s.frame, secs)
                vals = []
                for t in TARGETS:
                    if secs > 0 and t in ("normal_force", "slip"):
                        vals.append("")  # the moment's own: always read from its window
                        continue
                    v, _ = fit_and_score(split.kinds[t], xr[tr], split.y[t][tr], s.session[tr], xr[split.is_test],
                                         split.y[t][split.is_test], classes=3)
                    vals.append(f"{v:.3f}")
                print(f"| {name} | {reading} | {budget:.0%} | " + " | ".join(vals) + " |", flush=True)
    curve(split, sets, out)


def curve(split, sets: dict[str, np.ndarray], out: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    s, tr = split.samples, ~split.is_test
    shown = ("contact fields", "streams, all", "tokens, all (mean + max)", "tokens, image (mean + max)")
    targets = ("friction_tercile", "friction", "mass")
    fig, axes = plt.subplots(1, len(targets), figsize=(12, 3.6))
    print("\n| features | target | " + " | ".join(f"{h:g} s" for h in CURVE) + " |")
    print("|---|---|" + "---|" * len(CURVE))
    for ax, t in zip(axes, targets, strict=True):
        for name in shown:
            vals = []
            for h in CURVE:
                xr = history_mean(sets[name], s.session, s.frame, h)
                v, _ = fit_and_score(split.kinds[t], xr[tr], split.y[t][tr], s.session[tr], xr[split.is_test],
                                     split.y[t][split.is_test], classes=3)
                vals.append(v)
            print(f"| {name} | {t} | " + " | ".join(f"{v:.3f}" for v in vals) + " |", flush=True)
            ax.plot(CURVE, vals, marker="o", label=name)
        ax.set_xlabel("history (s)")
        ax.set_title(f"{t} ({'accuracy' if t.endswith('tercile') else 'R^2'}, 100% labels)", fontsize=9)
    axes[0].legend(fontsize=7)
    fig.tight_layout()
    out.mkdir(parents=True, exist_ok=True)
    fig.savefig(out / "history.png", dpi=80)
    plt.close(fig)


if __name__ == "__main__":
    main(Path(sys.argv[1]), Path(sys.argv[2]), Path(sys.argv[3]))
