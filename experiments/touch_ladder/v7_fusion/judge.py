"""RULE.md as code, written before the run's figures: does the 2 + 2-layer encoder replace sparshx-tinier-sim?

    python experiments/touch_ladder/v7_fusion/judge.py runs/touch_cpu22/touch_report runs/touch_cpu22/touch_report_201 \
        runs/touch_cpu22/shipped_report runs/touch_cpu22/shipped_report_201

The first two folders: the new encoder's ladders on the report draws of seeds 200 and 201; the last two: the shipped
encoder's ladders on the same sessions. Averages each encoder's fused-token figures at 100% of the labels over the
two draws and applies the rule's criteria (the adapter's touch-step budget is read from scripts/bench_adapter.py's
output by hand: it is printed as a reminder). Exit status 0 with a verdict, 2 on missing or mismatched reports.
"""

from __future__ import annotations

import json
import sys
from pathlib import Path

from rotation.tactile.ladder.report import FIVE, row_value

TARGETS = ("friction_tercile", "friction", "mass", "normal_force", "slip")


def _value(rows: list[dict], stage: str, features: str, target: str, budget: float) -> float:
    v = row_value(rows, stage, features, target, budget)
    if v is None:
        raise SystemExit(f"judge: no row {stage}/{features}/{target} at {budget:.0%}: is the report complete?")
    return v


def _load(folder: str) -> dict:
    path = Path(folder) / "results.json"
    if not path.is_file():
        raise SystemExit(f"judge: {path} does not exist")
    r = json.loads(path.read_text())
    if r.get("friction_reading", "mean") != "mean" or float(r.get("history", 0.0)) != 5.0:
        raise SystemExit(f"judge: {path} was not read as the rule says (5 s history, friction reading mean)")
    return r


def main(folders: list[str]) -> int:
    if len(folders) != 4:
        print(__doc__)
        return 2
    new, shipped = [_load(f) for f in folders[:2]], [_load(f) for f in folders[2:]]
    for a, b in zip(new, shipped, strict=True):  # the same sessions at the same stride give the same counts
        if (a.get("sessions"), a.get("samples")) != (b.get("sessions"), b.get("samples")):
            print(f"judge: the two encoders were not read on the same sessions (sessions, windows: "
                  f"{a.get('sessions')}, {a.get('samples')} against {b.get('sessions')}, {b.get('samples')})")
            return 2

    def mean(results: list[dict]) -> dict[str, float]:
        return {t: sum(_value(r["rows"], "tokens", "all", t, 1.0) for r in results) / len(results) for t in TARGETS}

    m_new, m_old = mean(new), mean(shipped)
    d = {t: m_new[t] - m_old[t] for t in TARGETS}
    wins = [sum(_value(r["rows"], "tokens", "all", t, 0.1) > _value(r["rows"], "e2e", "all", t, 0.1) for t in FIVE)
            for r in new]
    criteria = [
        ("friction R^2 at least 0.03 higher, or mass R^2 at least 0.05 higher",
         d["friction"] >= 0.03 or d["mass"] >= 0.05),
        ("friction tercile, mass and normal force R^2 no more than 0.02 lower",
         min(d["friction_tercile"], d["mass"], d["normal_force"]) >= -0.02),
        ("slip F1 no more than 0.01 lower", d["slip"] >= -0.01),
        ("frozen beats end to end at 10% on at least 3 of 5 (each draw)", min(wins) >= 3),
    ]
    for t in TARGETS:
        print(f"{t:17s} 2+2 {m_new[t]:.3f}  shipped {m_old[t]:.3f}  difference {d[t]:+.3f}")
    print(f"frozen beats end to end at 10%: {wins[0]} and {wins[1]} of 5")
    for text, ok in criteria:
        print(f"  {'ok  ' if ok else 'FAIL'} {text}")
    print("  (and the adapter's touch step within 50 ms on 2 cores: scripts/bench_adapter.py --encoder, read by hand)")
    print("verdict:", "replaces sparshx-tinier-sim (if the touch step is within budget)"
          if all(ok for _, ok in criteria) else "does not ship")
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
