"""The evaluation report: results.json (rows + config), results.md (a table) and plots (matplotlib, Agg).

A row is one (policy, condition): the condition's perturbation, the number of episodes and, for every metric in
:data:`envs.metrics.METRICS`, the mean over episodes and ``<metric>_std``. ``per_episode`` keeps the
values of :data:`EPISODE_FIELDS` for each episode, in episode order (episode j was seeded seed + j for every policy),
so two policies can be compared episode by episode (experiments/tools/pool_evaluations.py's paired rates).
"""

from __future__ import annotations

import json
import re
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np

from adapters.touch_delay import parse_delay
from envs.config import hand_physics
from envs.constants import DEFAULT_HAND
from envs.metrics import METRICS, EpisodeMetrics, summarize
from rotation.configs import to_jsonable
from rotation.evaluate.suites import NOMINAL, Condition, axis_level

EPISODE_FIELDS = ("ttf", "rotation_total", "in_hand_time", "vertical_drift")
"""Per-episode values a results row keeps (``row["per_episode"][field]``, one per episode)."""

PLOT_AXES = {"friction": "friction scale", "mass": "added mass (kg)", "com": "CoM shift (m)"}


def make_row(policy: str, cond: Condition, episodes: list[EpisodeMetrics]) -> dict[str, Any]:
    """One results row: the condition, the episode count, mean and std of each metric (+ mean reward)."""
    p = cond.perturb
    row: dict[str, Any] = {"policy": policy, "condition": cond.name, "friction_scale": p.friction_scale,
                           "added_mass": p.added_mass, "com_shift": list(p.com_shift), "episodes": len(episodes)}
    for key in [*METRICS, "reward"]:
        values = np.array([getattr(e, key) for e in episodes], dtype=np.float64)
        row[key] = float(values.mean())
        row[f"{key}_std"] = float(values.std())
    row["net_rotation_rate"] = summarize(episodes)["net_rotation_rate"]
    row["per_episode"] = {key: [round(float(getattr(e, key)), 5) for e in episodes] for key in EPISODE_FIELDS}
    return row


def json_text(data: Any) -> str:
    """Indented JSON with every list of numbers on one line (a row's per-episode values stay readable and small).
    Only the lists json.dumps spread over lines are joined: their text starts with a raw newline, which no JSON
    string can hold, so string values are never touched."""
    text = json.dumps(data, indent=2)
    return re.sub(r"\[(\n[^\[\]{}\"]*)\]", lambda m: "[" + " ".join(m.group(1).split()) + "]", text) + "\n"


def write_report(out: Path, rows: list[dict[str, Any]], config: Any, conditions: list[Condition],
                 hand: str = DEFAULT_HAND, touch_policies: Sequence[str] = ()) -> None:
    """results.json, results.md and plots/<metric>.png under ``out`` (the episodes ran on ``hand``; the policies
    ``touch_policies`` read touch, with the config's touch delay)."""
    out.mkdir(parents=True, exist_ok=True)
    (out / "results.json").write_text(json_text({"rows": rows, "config": to_jsonable(config)}))
    delay = parse_delay(getattr(config, "touch_delay", "0"))
    touch_note = (f"\n{', '.join(touch_policies)}: each touch correction first acted a drawn number of control steps "
                  f"after the step whose touch it read, {delay.describe()} (--touch-delay).\n"
                  if touch_policies else "")
    contact, usual = getattr(config, "contact", None), hand_physics(hand).contact
    contact_note = (f"\nContact model: {_contact_text(contact)}: not the settings the policies were trained with on "
                    f"the {hand} hand ({_contact_text(usual)}).\n" if contact is not None and contact != usual else "")
    dt = getattr(config, "physics_dt", None)
    if dt is not None:
        contact_note += f"\nPhysics step: {dt:g} s (the policies trained at 0.01 s).\n"
    (out / "results.md").write_text(markdown_table(rows) + touch_note + contact_note)
    plot_metrics(out / "plots", rows, conditions)
    plot_bars(out / "plots" / "bars.png", rows, conditions)


def _contact_text(contact: Any) -> str:
    """A contact model in words: cone, impratio, noslip iterations and, where set, time constant and impedance."""
    text = f"{contact.cone} cones, impratio {contact.impratio:g}, noslip iterations {contact.noslip_iterations}"
    if contact.timeconst is not None:
        text += f", time constant {contact.timeconst:g} s"
    if contact.solimp is not None:
        text += ", solimp " + " ".join(f"{v:g}" for v in contact.solimp)
    return text


def markdown_table(rows: list[dict[str, Any]]) -> str:
    """Rows grouped by condition, one line per policy, each metric as mean ± std."""
    head = ["condition", "policy", "episodes", "net_rotation_rate (rad/s)", *(f"{k} ({u})" for k, u in METRICS.items())]
    lines = ["# Evaluation", "", "| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
    for r in rows:
        cells = [r["condition"], r["policy"], str(r["episodes"]), f"{r['net_rotation_rate']:.3g}"]
        cells += [f"{r[k]:.3g} ± {r[k + '_std']:.2g}" for k in METRICS]
        lines.append("| " + " | ".join(cells) + " |")
    lines += ["", "net_rotation_rate: total signed rotation about the commanded axis / total time in hand over all "
              "episodes; rotation_rate: the same per episode, averaged; ttf: time to fall / episode length (1 = never "
              "fell; tipping past the env's max_tilt counts as a fall); upright: fraction of the time in hand with the "
              "object's axis within 30 degrees of vertical; vertical_drift: mean |object height - start height|.", ""]
    return "\n".join(lines)


def _plot_groups(conditions: list[Condition]) -> dict[str, list[Condition]]:
    """Plot panels: one per perturbation axis with its levels (nominal as the neutral point), one for the rest."""
    nominal = [c for c in conditions if c.axis == NOMINAL]
    groups: dict[str, list[Condition]] = {}
    for axis in PLOT_AXES:
        on_axis = [c for c in conditions if c.axis == axis]
        if on_axis:
            groups[axis] = sorted(nominal + on_axis, key=lambda c, a=axis: axis_level(c, a))
    rest = [c for c in conditions if c.axis == "combined" or (c.axis == NOMINAL and not groups)]
    if rest:
        groups["other"] = rest
    return groups


def plot_metrics(folder: Path, rows: list[dict[str, Any]], conditions: list[Condition]) -> list[Path]:
    """plots/<metric>.png: the metric against each perturbation level, one line per policy (mean ± std)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    folder.mkdir(parents=True, exist_ok=True)
    policies = list(dict.fromkeys(r["policy"] for r in rows))
    by_key = {(r["policy"], r["condition"]): r for r in rows}
    groups = _plot_groups(conditions)
    paths = []
    for metric, unit in METRICS.items():
        fig, axes = plt.subplots(1, len(groups), figsize=(4.2 * len(groups), 3.4), squeeze=False)
        for ax, (axis, conds) in zip(axes[0], groups.items(), strict=True):
            categorical = axis == "other"
            x = np.arange(len(conds)) if categorical else np.array([axis_level(c, axis) for c in conds])
            for policy in policies:
                ys = np.array([by_key[(policy, c.name)][metric] for c in conds])
                err = np.array([by_key[(policy, c.name)][metric + "_std"] for c in conds])
                ax.errorbar(x, ys, yerr=err, marker="o", capsize=3, label=policy)
            if categorical:
                ax.set_xticks(x, [c.name for c in conds], rotation=20, ha="right", fontsize=7)
            ax.set_xlabel(PLOT_AXES.get(axis, "condition"))
            ax.set_ylabel(f"{metric} ({unit})")
            ax.grid(alpha=0.3)
        axes[0][0].legend(fontsize=8)
        fig.suptitle(metric)
        fig.tight_layout()
        path = folder / f"{metric}.png"
        fig.savefig(path, dpi=100)
        plt.close(fig)
        paths.append(path)
    return paths


BAR_METRICS = ("ttf", "vertical_drift", "upright")
"""Metrics of the bar chart: whether the cup is kept, how much it sinks, how upright it stays."""


def plot_bars(path: Path, rows: list[dict[str, Any]], conditions: list[Condition]) -> Path:
    """plots/bars.png: one panel per metric of BAR_METRICS, a group of bars per condition, one bar per policy
    (mean; the error bar is the standard error over episodes, std / sqrt(episodes)); a policy without a row for
    a condition has no bar there."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    path.parent.mkdir(parents=True, exist_ok=True)
    policies = list(dict.fromkeys(r["policy"] for r in rows))
    by_key = {(r["policy"], r["condition"]): r for r in rows}
    x = np.arange(len(conditions))
    width = 0.8 / max(len(policies), 1)
    size = (max(5.0, 0.8 * len(conditions) + 2.0), 3.0 * len(BAR_METRICS))
    fig, axes = plt.subplots(len(BAR_METRICS), 1, figsize=size, squeeze=False)
    for ax, metric in zip(axes[:, 0], BAR_METRICS, strict=True):
        for j, policy in enumerate(policies):
            cells = [by_key.get((policy, c.name)) for c in conditions]  # no bar where a policy was not run
            ys = np.array([np.nan if r is None else r[metric] for r in cells])
            se = np.array([np.nan if r is None else r[metric + "_std"] / np.sqrt(max(r["episodes"], 1))
                           for r in cells])
            ax.bar(x + (j - (len(policies) - 1) / 2) * width, ys, width, yerr=se, capsize=2, label=policy)
        ax.set_xticks(x, [c.name for c in conditions], rotation=20, ha="right", fontsize=8)
        ax.set_ylabel(f"{metric} ({METRICS[metric]})")
        ax.set_title(metric)
        ax.grid(axis="y", alpha=0.3)
    axes[0][0].legend(fontsize=7)
    fig.tight_layout()
    fig.savefig(path, dpi=100)
    plt.close(fig)
    return path
