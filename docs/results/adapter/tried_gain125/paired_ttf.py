"""One-off: ttf of gain125 minus the shipped adapter's, episode by episode (episode j is seed s + j for both).

    python paired_ttf.py ADAPTER_REPORT:GAIN_REPORT [...]

Each argument pairs a report holding the `adapter` rows with one holding the `gain125` rows on the same seeds.
"""

import json
import sys

import numpy as np

CONDITIONS = ("friction_0.25", "mass_+0.2kg")


def rows(report: str) -> dict:
    with open(f"{report}/results.json") as f:
        return {(r["condition"], r["policy"]): r for r in json.load(f)["rows"]}


def summary(d: np.ndarray) -> str:
    return f"{d.mean():+.4f} se {d.std(ddof=1) / np.sqrt(len(d)):.4f}"


diffs: dict[str, list[np.ndarray]] = {c: [] for c in CONDITIONS}
for pair in sys.argv[1:]:
    adapter_report, gain_report = pair.split(":")
    shipped, gain = rows(adapter_report), rows(gain_report)
    for cond in CONDITIONS:
        d = (np.array(gain[(cond, "gain125")]["per_episode"]["ttf"])
             - np.array(shipped[(cond, "adapter")]["per_episode"]["ttf"]))
        diffs[cond].append(d)
        print(adapter_report.split("/")[-1], cond, summary(d))
for cond, ds in diffs.items():
    d = np.concatenate(ds)
    print("pooled", cond, len(d), summary(d))
