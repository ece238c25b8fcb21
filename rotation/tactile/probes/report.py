"""The report of `rotate probe`: results.json, a markdown table, a plot of each metric against the label budget, and
for temporal tasks plots of predicted vs true over time."""

from __future__ import annotations

import json
import math
from pathlib import Path
from typing import Any

from rotation.runs import save_atomically

HIGHER_IS_BETTER = {"balanced_accuracy", "accuracy"}
"""Metrics where a larger value is better (all others are errors)."""


def write_report(report: dict[str, Any], out: Path) -> None:
    """results.json, results.md (one table: task / metric / budget x variant) and probe.png."""
    out.mkdir(parents=True, exist_ok=True)
    text = json.dumps(report, indent=2) + "\n"
    save_atomically(lambda tmp: tmp.write_text(text), out / "results.json")  # a stop never leaves half a report
    rows = report["rows"]
    variants = list(dict.fromkeys(r["variant"] for r in rows))
    keys = list(dict.fromkeys((r["task"], r["metric"]) for r in rows))
    budgets = sorted({r["budget"] for r in rows})
    value = {(r["task"], r["metric"], r["budget"], r["variant"]): r["value"] for r in rows}
    base = {(b["task"], b["metric"]): b["value"] for b in report.get("baselines", [])}
    lines = [f"# Probes: {report.get('encoder', '')}", "",
             f"Checkpoint `{report.get('checkpoint', '')}`; {report.get('train_sessions')} training and "
             f"{report.get('test_sessions')} test sessions ({report.get('train_windows')} / "
             f"{report.get('test_windows')} windows), split by session. Budget = fraction of the training sessions. "
             "RMSE: lower is better; accuracy and balanced accuracy: higher is better. Baseline: the training mean "
             "(the majority class for classification).", "",
             "| task | metric | budget | " + " | ".join(variants) + " | baseline |",
             "|---" * (4 + len(variants)) + "|"]
    for task, metric in keys:
        for b in budgets:
            cells = [f"{value[(task, metric, b, v)]:.4g}" if (task, metric, b, v) in value else "" for v in variants]
            ref = base.get((task, metric))
            lines.append(f"| {task} | {metric} | {b:g} | " + " | ".join(cells) +
                         f" | {'' if ref is None else f'{ref:.4g}'} |")
    figures = ["![metric vs label budget](probe.png)"]
    figures += [f"![{name.split('_confusion')[0]}: confusion matrices]({name})"
                for name in report.get("confusion_plots", [])]
    figures += [f"![{name.split('_over_time')[0]}: predicted vs true over time]({name})"
                for name in report.get("trace_plots", [])]
    (out / "results.md").write_text("\n".join(lines) + "\n\n" + "\n\n".join(figures) + "\n")
    _plot(keys, budgets, variants, value, base, out / "probe.png")


def _plot(keys, budgets, variants, value, base, path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    cols = min(3, len(keys)) or 1
    nrows = math.ceil(len(keys) / cols) or 1
    fig, axes = plt.subplots(nrows, cols, figsize=(4.2 * cols, 3.2 * nrows), squeeze=False)
    for ax, (task, metric) in zip(axes.flat, keys, strict=False):
        for v in variants:
            xs = [b for b in budgets if (task, metric, b, v) in value]
            ax.plot(xs, [value[(task, metric, b, v)] for b in xs], marker="o", label=v)
        if (task, metric) in base:
            ax.axhline(base[(task, metric)], color="gray", linestyle="--", linewidth=1, label="baseline")
        ax.set_xscale("log")
        ax.minorticks_off()
        ax.set_xticks(budgets, [f"{b:g}" for b in budgets])
        ax.ticklabel_format(axis="y", useOffset=False)
        ax.set_title(f"{task}: {metric}" + (" (higher is better)" if metric in HIGHER_IS_BETTER else ""), fontsize=9)
        ax.set_xlabel("label budget (fraction of training sessions)", fontsize=8)
        ax.grid(alpha=0.3)
    for ax in list(axes.flat)[len(keys):]:
        ax.axis("off")
    axes.flat[0].legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def write_traces(traces: dict[str, dict[str, dict[str, Any]]], out: Path, budget: float) -> list[str]:
    """``<task>_over_time.png`` per temporal task: on the first test session, every output over time, true and
    each variant's prediction (the last window of each sequence, trained at ``budget``). Returns the file names.

    ``traces``: task -> variant -> {"pred", "true": (N, outputs), "time": (N,) s, "session": (N,)}.
    """
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    import numpy as np

    from rotation.tactile.probes.skin import TRACE_NAMES

    out.mkdir(parents=True, exist_ok=True)
    names = []
    for task, by_variant in traces.items():
        first = next(iter(by_variant.values()))
        session = int(np.min(first["session"]))
        outputs = first["true"].shape[1]
        labels = TRACE_NAMES.get(task, tuple(f"output {i}" for i in range(outputs)))
        fig, axes = plt.subplots(outputs, 1, figsize=(8, 1.8 * outputs + 0.6), sharex=True, squeeze=False)
        for i, ax in enumerate(axes[:, 0]):
            for k, (variant, tr) in enumerate(by_variant.items()):
                rows = np.flatnonzero(tr["session"] == session)
                order = rows[np.argsort(tr["time"][rows], kind="stable")]
                if k == 0:
                    ax.plot(tr["time"][order], tr["true"][order, i], color="black", linewidth=1.5, label="true")
                ax.plot(tr["time"][order], tr["pred"][order, i], linewidth=1, label=variant)
            ax.set_ylabel(labels[i] if i < len(labels) else f"output {i}", fontsize=8)
            ax.grid(alpha=0.3)
        axes[0, 0].set_title(f"{task}: predicted vs true on test session {session} (budget {budget:g})", fontsize=9)
        axes[0, 0].legend(fontsize=7, loc="upper right")
        axes[-1, 0].set_xlabel("time (s)", fontsize=8)
        fig.tight_layout()
        name = f"{task}_over_time.png"
        fig.savefig(out / name, dpi=100)
        plt.close(fig)
        names.append(name)
    return names


def write_confusions(confusions: dict[str, dict[str, Any]], out: Path, budget: float) -> list[str]:
    """``<task>_confusion.png`` per multi-class task: each variant's confusion matrix on the test windows (rows true,
    columns predicted, each row normalized), trained at ``budget``. Returns the file names."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    import numpy as np

    from rotation.tactile.probes.config import CLASS_NAMES

    out.mkdir(parents=True, exist_ok=True)
    names = []
    for task, by_variant in confusions.items():
        labels = CLASS_NAMES.get(task)
        fig, axes = plt.subplots(1, len(by_variant), figsize=(2.6 * len(by_variant) + 0.4, 2.9), squeeze=False)
        for ax, (variant, matrix) in zip(axes[0], by_variant.items(), strict=True):
            m = np.asarray(matrix, dtype=np.float64)
            share = m / np.maximum(m.sum(axis=1, keepdims=True), 1)
            ax.imshow(share, vmin=0, vmax=1, cmap="Blues")
            k = len(m)
            ticks = labels if labels is not None and len(labels) == k else [str(i) for i in range(k)]
            ax.set_xticks(range(k), ticks, rotation=60, fontsize=7)
            ax.set_yticks(range(k), ticks, fontsize=7)
            for i in range(k):
                for j in range(k):
                    ax.text(j, i, f"{share[i, j]:.2f}", ha="center", va="center", fontsize=6,
                            color="white" if share[i, j] > 0.6 else "black")
            ax.set_title(f"{variant}: {np.trace(m) / max(m.sum(), 1):.2f}", fontsize=8)
            ax.set_xlabel("predicted", fontsize=7)
        axes[0, 0].set_ylabel("true", fontsize=7)
        fig.suptitle(f"{task}: confusion on the test windows (budget {budget:g}; title: accuracy)", fontsize=9)
        fig.tight_layout()
        name = f"{task}_confusion.png"
        fig.savefig(out / name, dpi=100)
        plt.close(fig)
        names.append(name)
    return names
