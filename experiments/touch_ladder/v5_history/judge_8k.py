"""RULE_8k.md as code, written before the run's figures: does the 8,000-step encoder replace sparshx-tinier-sim?

    python experiments/touch_ladder/v5_history/judge_8k.py runs/touch_cpu8k/touch_report \
        runs/touch_cpu8k/touch_report_201

Reads the two draws' ladders (seeds 200 and 201, `--friction-reading mean`), averages the fused tokens' figures at
100% of the labels over the draws and applies the rule's criteria against the shipped encoder's mean of the same two
draws (the v5 record and v6_slip_reading's `mean` reading). Prints each criterion and the verdict; exit status 0.
"""

from __future__ import annotations

import json
import sys
from pathlib import Path

from rotation.tactile.ladder.report import FIVE, row_value

SHIPPED = {"friction_tercile": 0.546, "friction": 0.475, "mass": 0.475, "slip": 0.8735, "normal_force": 0.9205}
"""The shipped encoder's fused tokens at 100% labels, mean of seed 200 (v5 record) and seed 201 (v6, mean)."""


def _value(rows: list[dict], stage: str, features: str, target: str, budget: float) -> float:
    v = row_value(rows, stage, features, target, budget)
    if v is None:
        raise SystemExit(f"judge_8k: no row {stage}/{features}/{target} at {budget:.0%}: is the report complete?")
    return v


def main(folders: list[str]) -> int:
    if len(folders) != 2:
        print(__doc__)
        return 2
    results = []
    for f in folders:
        path = Path(f) / "results.json"
        if not path.is_file():
            print(f"judge_8k: {path} does not exist")
            return 2
        r = json.loads(path.read_text())
        if r.get("friction_reading", "mean") != "mean" or float(r.get("history", 0.0)) != 5.0:
            print(f"judge_8k: {path} was not read as the rule says (5 s history, friction reading mean)")
            return 2
        results.append(r)
    mean = {t: sum(_value(r["rows"], "tokens", "all", t, 1.0) for r in results) / 2 for t in SHIPPED}
    wins = [sum(_value(r["rows"], "tokens", "all", t, 0.1) > _value(r["rows"], "e2e", "all", t, 0.1) for t in FIVE)
            for r in results]
    d = {t: mean[t] - SHIPPED[t] for t in SHIPPED}
    criteria = [
        ("friction R^2 at least 0.03 higher", d["friction"] >= 0.03),
        ("friction tercile not lower", d["friction_tercile"] >= 0.0),
        ("mass R^2 no more than 0.02 lower", d["mass"] >= -0.02),
        ("normal force R^2 no more than 0.02 lower", d["normal_force"] >= -0.02),
        ("slip F1 no more than 0.01 lower", d["slip"] >= -0.01),
        ("frozen beats end to end at 10% on at least 3 of 5 (each draw)", min(wins) >= 3),
    ]
    for t in SHIPPED:
        print(f"{t:17s} 8k {mean[t]:.3f}  shipped {SHIPPED[t]:.3f}  difference {d[t]:+.3f}")
    print(f"frozen beats end to end at 10%: {wins[0]} and {wins[1]} of 5")
    for text, ok in criteria:
        print(f"  {'ok  ' if ok else 'FAIL'} {text}")
    print("verdict:", "replaces sparshx-tinier-sim" if all(ok for _, ok in criteria) else "does not ship")
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
