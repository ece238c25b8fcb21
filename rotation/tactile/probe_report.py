"""The report of `rotate probe`: results.json, a markdown table and a plot of each metric against the label budget."""

from __future__ import annotations

import json
import math
from pathlib import Path
from typing import Any

HIGHER_IS_BETTER = {"balanced_accuracy"}
"""Metrics where a larger value is better (all others are errors)."""


def write_report(report: dict[str, Any], out: Path) -> None:
    """results.json, results.md (one table: task / metric / budget x variant) and probe.png."""
    out.mkdir(parents=True, exist_ok=True)
    (out / "results.json").write_text(json.dumps(report, indent=2) + "\n")
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
             "RMSE: lower is better; balanced accuracy: higher is better. Baseline: the training mean (majority "
             "class for slip).", "",
             "| task | metric | budget | " + " | ".join(variants) + " | baseline |",
             "|---" * (4 + len(variants)) + "|"]
    for task, metric in keys:
        for b in budgets:
            cells = [f"{value[(task, metric, b, v)]:.4g}" if (task, metric, b, v) in value else "" for v in variants]
            ref = base.get((task, metric))
            lines.append(f"| {task} | {metric} | {b:g} | " + " | ".join(cells) +
                         f" | {'' if ref is None else f'{ref:.4g}'} |")
    (out / "results.md").write_text("\n".join(lines) + "\n\n![metric vs label budget](probe.png)\n")
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
