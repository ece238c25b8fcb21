"""What happened in recorded insertion episodes (`rotate demos`, with or without --policy): outcomes, and where the
plug started to slip in the hand, from each session's privileged labels.

For each folder: episodes seated, lost (the plug left the grasp), slipped (a --policy episode ended by --slip-stop)
and the rest (timed out); the steps recorded; the share of steps in which the prong has moved more than ``--slip-mm``
from where it sat at the first step, in the wrist's frame (the prong's tip pose relative to the wrist's target pose,
both recorded per step); and, over the episodes whose prong moved that far, the median step at which it first did,
how many had touched the socket before (socket force above 0.5 N) and the median largest socket force up to that
step, beside the median largest socket force of each outcome.

    python experiments/tools/insertion_rounds.py runs/insertion_dagger_slip/demos \
        runs/insertion_dagger_slip/dagger_camera_1
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import mujoco
import numpy as np

from rotation.data.dataset import find_sessions
from rotation.data.session_reader import SessionReader

TOUCH_N = 0.5
"""Socket force (N) above which the prong counts as touching the socket."""


def in_wrist(wrist: np.ndarray, prong: np.ndarray) -> np.ndarray:
    """The prong tip's position in the wrist's frame per step (wrist, prong: (T, 7) position + quaternion wxyz)."""
    out = np.empty((len(wrist), 3))
    inv = np.empty(4)
    for i, (w, p) in enumerate(zip(wrist, prong, strict=True)):
        mujoco.mju_negQuat(inv, w[3:].astype(np.float64))
        mujoco.mju_rotVecQuat(out[i], (p[:3] - w[:3]).astype(np.float64), inv)
    return out


def episode(path: Path, slip_m: float) -> dict:
    with SessionReader(path) as r:
        props = r.meta.properties
        data = {k: np.asarray(r.stream(k).data) for k in ("wrist/pose", "labels/prong", "labels/socket_force")}
    rel = in_wrist(data["wrist/pose"], data["labels/prong"])
    moved = np.linalg.norm(rel - rel[0], axis=1)
    force = data["labels/socket_force"][:, 0]
    first = int(np.argmax(moved > slip_m)) if (moved > slip_m).any() else -1
    touch = int(np.argmax(force > TOUCH_N)) if (force > TOUCH_N).any() else -1
    outcome = ("seated" if props["success"] else "lost" if props["lost"] else
               "slipped" if props.get("slipped") else "timed out")
    return {"outcome": outcome, "steps": len(moved), "moved_steps": int((moved > slip_m).sum()), "first": first,
            "touched_before": 0 <= touch <= first if first >= 0 else False,
            "force_before": float(force[:first + 1].max()) if first >= 0 else float("nan"),
            "max_force": float(force.max())}


def summary(folder: Path, slip_m: float) -> list[str]:
    files = find_sessions(folder) if folder.exists() else []
    if not files:
        raise SystemExit(f"insertion_rounds: no episodes under {folder}")
    eps = [episode(p, slip_m) for p in files]
    steps = sum(e["steps"] for e in eps)
    moved = [e for e in eps if e["first"] >= 0]
    lines = [f"{folder}: {len(eps)} episodes, {steps} steps; prong moved > {slip_m * 1e3:g} mm in the hand in "
             f"{sum(e['moved_steps'] for e in eps) / steps:.1%} of the steps and in {len(moved)} episodes"]
    if moved:
        lines.append(f"  those episodes: first such step median {np.median([e['first'] for e in moved]):g}; "
                     f"touched the socket before it in {sum(e['touched_before'] for e in moved)}; largest socket "
                     f"force up to it median {np.median([e['force_before'] for e in moved]):.1f} N")
    for outcome in ("seated", "lost", "slipped", "timed out"):
        sel = [e for e in eps if e["outcome"] == outcome]
        if sel:
            lines.append(f"  {outcome}: {len(sel)}; median length {np.median([e['steps'] for e in sel]):g} steps, "
                         f"largest socket force median {np.median([e['max_force'] for e in sel]):.1f} N")
    return lines


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("folders", nargs="+", type=Path, help="folders of recorded insertion episodes")
    parser.add_argument("--slip-mm", type=float, default=5.0, help="in-hand movement of the prong that counts (mm)")
    args = parser.parse_args(argv)
    for folder in args.folders:
        print("\n".join(summary(folder, args.slip_mm * 1e-3)))
    return 0


if __name__ == "__main__":
    sys.exit(main())
