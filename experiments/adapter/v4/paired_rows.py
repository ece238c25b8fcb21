"""The ablation rows of scripts/adapter_cpu_recipe.py beside the student, the teacher and the ensemble on the same
episodes: the recipe evaluates the rows on the first N episodes of the decision evaluation's seeds, so each row
pairs episode by episode with the policies evaluated there.

    python experiments/adapter/v4/paired_rows.py runs/adapter_cpu

Prints a markdown table per condition: ttf and net rate (total rotation / total time in hand) of every policy on the
shared episodes, and each policy's paired ttf difference to the student (mean ± standard error).
"""

from __future__ import annotations

import json
import sys
from pathlib import Path

import numpy as np


def _rows(path: Path) -> dict[str, dict]:
    data = json.loads(path.read_text())
    rows = data if isinstance(data, list) else data["rows"]
    return {r["policy"]: r["per_episode"] for r in rows}


def main(out: Path) -> None:
    for cond_file in sorted((out / "ablation" / "conditions").glob("*.json")):
        rows = _rows(cond_file)
        decision = out / "evaluation" / "conditions" / cond_file.name
        n = len(next(iter(rows.values()))["ttf"])
        both = {**{k: {m: v[:n] for m, v in e.items()} for k, e in _rows(decision).items()}, **rows}
        base = np.asarray(both["student"]["ttf"], float)
        print(f"\n{cond_file.stem} ({n} episodes)\n")
        print("| policy | ttf | net rate (rad/s) | ttf - student (paired) |\n|---|---|---|---|")
        for name, e in both.items():
            ttf = np.asarray(e["ttf"], float)
            net = float(np.sum(e["rotation_total"]) / np.sum(e["in_hand_time"]))
            diff = ttf - base
            paired = "" if name == "student" else f"{diff.mean():+.3f} ± {diff.std(ddof=1) / np.sqrt(n):.3f}"
            print(f"| {name} | {ttf.mean():.3f} | {net:.3f} | {paired} |")


if __name__ == "__main__":
    main(Path(sys.argv[1] if len(sys.argv) > 1 else "runs/adapter_cpu"))
