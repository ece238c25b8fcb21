"""One-off: ttf of a candidate minus the shipped adapter's, episode by episode (episode j is seed s + j for both).

    python paired_ttf.py [--policy=NAME] ADAPTER_REPORT:CANDIDATE_REPORT [...]

Each argument pairs a report holding the `adapter` rows with one holding the candidate's rows (NAME, default
gain125) on the same seeds.
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


args = sys.argv[1:]
name = "gain125"
if args and args[0].startswith("--policy="):
    name, args = args[0].split("=", 1)[1], args[1:]
diffs: dict[str, list[np.ndarray]] = {c: [] for c in CONDITIONS}
for pair in args:
    adapter_report, gain_report = pair.split(":")
    shipped, gain = rows(adapter_report), rows(gain_report)
    for cond in CONDITIONS:
        d = (np.array(gain[(cond, name)]["per_episode"]["ttf"])
             - np.array(shipped[(cond, "adapter")]["per_episode"]["ttf"]))
        diffs[cond].append(d)
        print(adapter_report.split("/")[-1], cond, summary(d))
for cond, ds in diffs.items():
    d = np.concatenate(ds)
    print("pooled", cond, len(d), summary(d))
