"""The ladder's report: the checks against the touch targets, results.json / results.md, and three figures
(ladder.png, budgets.png, frames.png)."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import numpy as np

from envs.constants import FINGERS
from envs.sensors.digit360 import contact_frame_force
from envs.sensors.digit360_model import IMAGE_HZ
from rotation.tactile.ladder.samples import TARGETS, HandSamples

TARGET_CHECKS = (
    ("friction tercile accuracy >= 0.70 from the fused tokens (100% labels)", "tokens", "all", "friction_tercile",
     0.70),
    ("mass R^2 >= 0.5 from the fused tokens (100% labels)", "tokens", "all", "mass", 0.5),
    ("slip F1 >= 0.9 from the fused tokens (100% labels)", "tokens", "all", "slip", 0.9),
)
"""(check, stage, features, target, minimum) of the encoder on the streams at the largest budget."""
RUNGS = ("contact", "streams", "tokens")
STAGE_COLORS = {"contact": "k", "streams": "tab:blue", "tokens": "tab:orange", "e2e": "tab:green"}
FIVE = ("friction_tercile", "mass", "com", "normal_force", "slip")
"""The five targets frozen tokens should beat end to end on with few labels (friction counted once)."""


def _row(rows: list[dict], stage: str, features: str, target: str, budget: float) -> dict | None:
    for r in rows:
        if (r["stage"], r["features"], r["target"]) == (stage, features, target) and abs(r["budget"] - budget) < 1e-9:
            return r
    return None


def row_value(rows: list[dict], stage: str, features: str, target: str, budget: float) -> float | None:
    """The score of one (stage, feature set, target, budget) among a report's rows; None when not computed."""
    r = _row(rows, stage, features, target, budget)
    return None if r is None else float(r["value"])


def _shown(row: dict | None) -> str:
    """A row's score with its standard error over the test sessions where the report computed one."""
    if row is None:
        return ""
    se = row.get("se")
    return f"{row['value']:.3f}" + (f" ± {se:.3f}" if se is not None and np.isfinite(se) else "")


def _held(value: float | None, base: float) -> float | None:
    """What a score holds above what ignoring the features scores (rotation.tactile.ladder.fit.chance)."""
    if value is None or not np.isfinite(value):
        return None
    return max(value - base, 0.0)


def checks(result: dict[str, Any], top: float, low: float) -> list[dict[str, Any]]:
    """The targets of the touch path, each with ok True / False (None when its rows were not computed)."""
    rows, base = result["rows"], {c["target"]: c for c in result["chance"]}
    out = []
    for text, stage, fset, target, minimum in TARGET_CHECKS:
        r = _row(rows, stage, fset, target, top)
        out.append({"check": text, "ok": None if r is None else r["value"] >= minimum,
                    "detail": "not computed" if r is None else _shown(r)})
    for target in ("friction_tercile", "slip"):
        r, c = _row(rows, "tokens", "image", target, top), base[target]["value"]
        out.append({"check": f"the image tokens alone read {target} above chance",
                    "ok": None if r is None else r["value"] > c,
                    "detail": "not computed" if r is None else f"{_shown(r)}; chance {c:.3f}"})
    wins, done = [], 0
    for target in FIVE:
        a, b = row_value(rows, "tokens", "all", target, low), row_value(rows, "e2e", "all", target, low)
        if a is not None and b is not None:
            done += 1
            if a > b:
                wins.append(target)
    out.append({"check": f"frozen tokens beat end-to-end at {low:.0%} labels on at least 3 of the 5 targets",
                "ok": None if done < len(FIVE) else len(wins) >= 3,
                "detail": f"wins on {', '.join(wins) or 'none'} ({done} compared)"})
    for below, above in zip(RUNGS, RUNGS[1:], strict=False):
        for target in TARGETS:
            lo = _held(row_value(rows, below, "fields" if below == "contact" else "all", target, top),
                       base[target]["value"])
            hi = _held(row_value(rows, above, "all", target, top), base[target]["value"])
            if lo is None or hi is None or lo < 0.05:
                continue  # nothing to lose (or not computed)
            out.append({"check": f"{above} keep at least two thirds of what {below} holds on {target}",
                        "ok": hi >= 2 / 3 * lo, "detail": f"{hi:.3f} of {lo:.3f} above chance"})
    return out


def write_report(out: Path, result: dict[str, Any], samples: HandSamples, frames_session: int) -> None:
    (out / "results.json").write_text(json.dumps(result, indent=1))
    (out / "results.md").write_text(_markdown(result))
    import matplotlib

    matplotlib.use("Agg")
    _ladder_plot(out / "ladder.png", result)
    _budget_plot(out / "budgets.png", result)
    _frames_plot(out / "frames.png", samples, int(frames_session))


def _markdown(result: dict[str, Any]) -> str:
    rows = result["rows"]
    budgets = sorted({r["budget"] for r in rows})
    sets = sorted({(r["stage"], r["features"]) for r in rows},
                  key=lambda s: (["contact", "streams", "tokens", "e2e"].index(s[0]), s[1]))
    base = {c["target"]: c["value"] for c in result["chance"]}
    lines = [f"# Information ladder ({result['samples']} samples, {result['sessions']} sessions: "
             f"{len(result['train_sessions'])} training, {len(result['test_sessions'])} test)", "",
             "Scores on the test sessions: accuracy (friction tercile), F1 (slip), R^2 (the others); after ± their "
             "standard error over which test sessions were drawn (the sessions resampled with replacement, "
             "each session's moments together).", "",
             _reading(float(result.get("history", 0.0)), result.get("friction_reading", "mean")), ""]
    for b in budgets:
        lines += [f"## {b:.0%} of the training sessions' labels", "",
                  "| stage | features | " + " | ".join(TARGETS) + " |", "|---|---|" + "---|" * len(TARGETS)]
        for stage, fset in sets:
            cells = [_shown(_row(rows, stage, fset, t, b)) for t in TARGETS]
            lines.append(f"| {stage} | {fset} | " + " | ".join(cells) + " |")
        lines.append("| chance | | " + " | ".join(f"{base[t]:.3f}" for t in TARGETS) + " |")
        lines.append("")
    lines += ["## Checks", ""]
    for c in result["checks"]:
        mark = "ok" if c["ok"] else ("FAIL" if c["ok"] is False else "n/a")
        lines.append(f"- {mark}: {c['check']} ({c['detail']})")
    if not result.get("complete", True):
        lines += ["", "Stopped before the end: rows are missing."]
    return "\n".join(lines) + "\n"


def _reading(history: float, friction: str) -> str:
    if history <= 0:
        return "Every target is read from the moment's window alone."
    text = (f"The object's mass and centre of mass are read from the mean of the features over the windows of the "
            f"last {history:g} s (nothing later than the moment; end to end: its outputs averaged); normal force and "
            "slip from the moment's window. ")
    if friction == "slip":
        return text + ("Friction from the same windows, each fingertip's weighted by how likely the rung's own slip "
                       "reader finds it sliding (at least 0.05), its tercile as the cut of that estimate at the "
                       "terciles' edges.")
    return text + "Friction from the plain mean as well, its tercile by a classifier of its own."


def _ladder_plot(path: Path, result: dict[str, Any]) -> None:
    import matplotlib.pyplot as plt

    rows, top = result["rows"], max(r["budget"] for r in result["rows"]) if result["rows"] else 1.0
    sets = [("contact", "fields"), *[(s, m) for s in ("streams", "tokens") for m in
                                       ("image", "audio", "imu", "pressure", "all")], ("e2e", "all")]
    sets = [s for s in sets if any((r["stage"], r["features"]) == s for r in rows)]
    fig, axes = plt.subplots(1, len(TARGETS), figsize=(3.2 * len(TARGETS), 4.2), sharey=True)
    base = {c["target"]: c["value"] for c in result["chance"]}
    for ax, t in zip(np.atleast_1d(axes), TARGETS, strict=True):
        picked = [_row(rows, s, f, t, top) for s, f in sets]
        vals = [0.0 if r is None or not np.isfinite(r["value"]) else float(r["value"]) for r in picked]
        errs = [0.0 if r is None or not np.isfinite(r.get("se", np.nan)) else float(r["se"]) for r in picked]
        colors = [STAGE_COLORS[s] for s, _ in sets]
        ax.bar(range(len(sets)), vals, yerr=errs, color=colors, error_kw={"lw": 0.8, "capsize": 2})
        ax.axhline(base[t], color="gray", ls="--", lw=1)
        ax.set_xticks(range(len(sets)), [f"{s}:{f}" for s, f in sets], rotation=90, fontsize=7)
        ax.set_title(t, fontsize=9)
        ax.set_ylim(-0.1, 1.0)
    np.atleast_1d(axes)[0].set_ylabel(f"score at {top:.0%} labels\n(dashed: chance; bars: 1 s.e.)")
    fig.tight_layout()
    fig.savefig(path, dpi=90)
    plt.close(fig)


def _budget_plot(path: Path, result: dict[str, Any]) -> None:
    import matplotlib.pyplot as plt

    rows = result["rows"]
    fig, axes = plt.subplots(1, len(TARGETS), figsize=(3.2 * len(TARGETS), 3.2), sharey=True)
    for ax, t in zip(np.atleast_1d(axes), TARGETS, strict=True):
        for stage, fset in (("contact", "fields"), ("streams", "all"), ("tokens", "all"), ("tokens", "image"),
                            ("e2e", "all")):
            pts = sorted((r["budget"], r["value"], r.get("se", np.nan)) for r in rows
                         if (r["stage"], r["features"], r["target"]) == (stage, fset, t))
            if pts:
                b, v, se = (np.asarray(c, np.float64) for c in zip(*pts, strict=True))
                line = ax.plot(b, v, marker="o", label=f"{stage}:{fset}")[0]
                if np.isfinite(se).any():  # one standard error over the test sessions
                    ax.fill_between(b, v - se, v + se, color=line.get_color(), alpha=0.15, lw=0)
        ax.set_xscale("log")
        ax.set_title(t, fontsize=9)
        ax.set_xlabel("label budget")
    np.atleast_1d(axes)[0].legend(fontsize=7)
    fig.tight_layout()
    fig.savefig(path, dpi=90)
    plt.close(fig)


def _frames_plot(path: Path, samples: HandSamples, session: int) -> None:
    """Six moments of one session's most-touching fingertip, spread over the moments it touches: the image at t,
    the audio, the accelerometer and the pressure windows, under the contact force at the strongest contact over the
    session."""
    import matplotlib.pyplot as plt

    mine = np.flatnonzero(samples.session == session)
    if not len(mine):
        return
    ds = samples.windows
    force = {f: contact_frame_force(ds.contact_track(session, f).rows) for f in FINGERS}
    finger = max(FINGERS, key=lambda f: float(force[f][:, 0].mean()))
    fi = FINGERS.index(finger)
    track = ds.contact_track(session, finger)
    at = track.last_row(samples.frame[mine] / IMAGE_HZ)
    touching = mine[force[finger][at, 0] > 0]  # moments the fingertip touches, spread over the ones there are
    pool = touching if len(touching) >= 6 else mine
    picks = pool[np.linspace(0, len(pool) - 1, 6).round().astype(int)]
    fig = plt.figure(figsize=(15, 9))
    top = fig.add_subplot(5, 1, 1)
    top.plot(track.times, force[finger][:, 0], label="normal (N)")
    top.plot(track.times, force[finger][:, 1], label="tangential (N)")
    for m in picks:
        top.axvline(samples.frame[m] / IMAGE_HZ, color="gray", lw=0.8)
    top.set_title(f"{Path(ds.paths[session]).name}, {finger}: contact force at the strongest contact "
                  f"(friction {samples.friction[session]:.2f}, mass {samples.mass[session]:.3f} kg)", fontsize=9)
    top.legend(fontsize=7, loc="upper right")
    for col, m in enumerate(picks):
        w = ds[int(samples.items[m, fi])]
        img = w["image"].numpy()[1::2].transpose(1, 2, 0)
        ax = fig.add_subplot(5, 6, 7 + col)
        ax.imshow(np.clip(img, 0, 1))
        ax.set_title(f"t = {samples.frame[m] / IMAGE_HZ:.2f} s", fontsize=8)
        ax.axis("off")
        for row, (name, data) in enumerate((("audio log-mel", w["audio"].numpy().T), ("IMU (g)", w["imu"].numpy()),
                                            ("pressure (hPa)", w["pressure"].numpy()[:, 0]))):
            ax = fig.add_subplot(5, 6, 13 + 6 * row + col)
            if data.ndim == 2 and name.startswith("audio"):
                ax.imshow(data, aspect="auto", origin="lower")
            else:
                ax.plot(data, lw=0.8)
            ax.set_title(name, fontsize=7)
            ax.tick_params(labelsize=6)
    fig.tight_layout()
    fig.savefig(path, dpi=80)
    plt.close(fig)
