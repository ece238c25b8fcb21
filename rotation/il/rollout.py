"""`rotate evaluate --task insertion`: imitation policies in closed loop on the insertion task (envs.insertion).

Trial j runs the episode seeded ``seed + j`` (socket pose, grasp), the same for every policy; use seeds no
demonstration used (`rotate demos` seeds its episodes ``seed x 1,000,000 + e``). A policy acts at 20 Hz on the wrist
camera's frame, its proprioception and, if it reads touch, the fingertips' windows rendered from the live contact
history (or, on the Xela hand its bundle names, the skin's window). Per policy: the success rate with its 95% Wilson
interval, the time to insert (successes), the peak socket force, how many trials pressed past the force limit and
how many lost the plug from the grasp; OUT/results.json (``{"rows": [{"policy",
"episodes", "success_rate", ...}]}``), results.md, success.png, and per policy a video of the wrist camera in one
success and one failure (videos/<policy>_success.mp4, _failure.mp4) where there is one.

Each finished trial is appended to OUT/trials.jsonl at once, with the policy's name, the sha256 of its bundle's files,
its seed and length: running the same evaluation into the same OUT again (after a stop, a fault, Ctrl-C) takes the
trials kept there and runs only the rest; a trial of another bundle, seed or length is not taken. The videos come
from the trials this run plays.
"""

from __future__ import annotations

import hashlib
import json
import math
from pathlib import Path
from typing import Any

import numpy as np
from tqdm import tqdm

from rotation.runs import CurveLog

Z95 = 1.959964
"""Two-sided 95% normal quantile."""


def wilson(successes: int, n: int) -> tuple[float, float]:
    """The 95% Wilson score interval of a success rate."""
    if n == 0:
        return 0.0, 1.0
    p, z2 = successes / n, Z95**2
    centre = (p + z2 / (2 * n)) / (1 + z2 / n)
    half = Z95 * math.sqrt(p * (1 - p) / n + z2 / (4 * n * n)) / (1 + z2 / n)
    return max(0.0, centre - half), min(1.0, centre + half)


def touch_windows(policy: Any, sim: Any, obs: dict[str, np.ndarray]) -> dict[str, Any] | None:
    """What a touch-reading imitation policy reads on this step of an InsertionSim: the Xela skin's window and its
    baseline, or the fingertips' Digit 360 windows rendered from the live contact history; None for one that reads
    no touch."""
    if not policy.reads_touch:
        return None
    return ({"skin": obs["skin"], "xela_baseline": sim.skin.baseline} if sim.skin is not None
            else sim.touch.windows())


def run_trial(policy: Any, seed: int, grasps: Any, keep_frames: bool, episode_steps: int | None = None
              ) -> tuple[dict[str, float], list[np.ndarray]]:
    """One closed-loop episode (at most ``episode_steps`` actions; None: the task's); its outcome and
    (``keep_frames``) the wrist camera's frames."""
    from envs.insertion import InsertionConfig, InsertionSim, draw_episode

    w, h = policy.model.cfg.image_size
    cfg = InsertionConfig(hand=policy.hand, grip=policy.grip, wrist=policy.wrist, image_size=(w, h),
                          **({} if episode_steps is None else {"episode_steps": episode_steps}))
    sim = InsertionSim(cfg, draw_episode(cfg, seed, grasps), grasps, render=True)
    policy.reset()
    frames: list[np.ndarray] = []
    try:
        obs, done, info = sim.reset(), False, {}
        while not done:
            if keep_frames:
                frames.append(obs["image"])
            obs, done, info = sim.step(policy.act(obs, touch_windows(policy, sim, obs)))
    finally:
        sim.close()
    return {"success": float(info["success"]), "steps": sim.steps, "time_s": sim.steps * cfg.control_dt,
            "max_force": float(info["max_force"]), "depth": float(info["depth"]),
            "lost": float(info["lost"]), "over_force": float(info["max_force"] > cfg.max_force)}, frames


def evaluate_insertion(policies: dict[str, str], episodes: int, seed: int, out: Path, video: bool = True,
                       progress: bool = True, episode_steps: int | None = None) -> list[dict[str, Any]]:
    """Evaluate every policy on ``episodes`` trials (module docstring); returns the rows."""
    import imageio.v2 as imageio

    from envs.grasp_cache import load_default_cache
    from rotation.il.bundle import load_il

    if not policies:
        raise ValueError("give the policies to evaluate: --policy NAME=PATH (imitation policy bundles)")
    loaded = {name: load_il(path) for name, path in policies.items()}
    caches = {hand: load_default_cache("cup", "", hand) for hand in {p.hand for p in loaded.values()}}
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    rows, log = [], CurveLog(out / TRIALS)
    digests = {name: bundle_digest(policies[name]) for name in loaded}
    logged = log.rows()
    kept_trials = {name: _kept_trials(logged, name, digests[name], seed, episodes, episode_steps) for name in loaded}
    done = sum(len(k) for k in kept_trials.values())
    if done:
        print(f"evaluate: {done} of {episodes * len(loaded)} trials kept in {log.path}; running the rest")
    bar = tqdm(total=episodes * len(loaded), initial=done, unit="episode", desc="evaluate insertion",
               disable=not progress)
    for name, policy in loaded.items():
        trials, kept = [], {}
        for j in range(episodes):
            if j in kept_trials[name]:
                trials.append(kept_trials[name][j])
                continue
            want = video and len(kept) < 2
            result, frames = run_trial(policy, seed + j, caches[policy.hand], want, episode_steps)
            log.append([{"policy": name, "bundle_sha256": digests[name], "seed": seed + j,  # kept at once: a stop
                         "episode_steps": episode_steps, "result": result}])  # loses the trial it interrupts
            trials.append(result)
            kind = "success" if result["success"] else "failure"
            if want and kind not in kept:
                kept[kind] = frames
            bar.update(1)
        for kind, frames in kept.items():
            (out / "videos").mkdir(exist_ok=True)
            imageio.mimsave(out / "videos" / f"{name}_{kind}.mp4", frames, fps=20, macro_block_size=8)
        wins = int(sum(t["success"] for t in trials))
        lo, hi = wilson(wins, episodes)
        times = [t["time_s"] for t in trials if t["success"]]
        rows.append({"policy": name, "bundle": policies[name], "hand": policy.hand, "grip": policy.grip,
                     "wrist": policy.wrist,
                     "touch": policy.touch_modalities,
                     "episodes": episodes, "seed": seed, "success_rate": wins / episodes, "ci95": [lo, hi],
                     "time_to_insert_s": float(np.mean(times)) if times else None,
                     "peak_force_N": float(np.mean([t["max_force"] for t in trials])),
                     "lost_plug": int(sum(t["lost"] for t in trials)),
                     "over_force": int(sum(t["over_force"] for t in trials)), "trials": trials})
    bar.close()
    _report(rows, out)
    return rows


TRIALS = "trials.jsonl"
"""The evaluation's finished trials, one JSON object a line (module docstring)."""


def bundle_digest(path: str | Path) -> str:
    """sha256 over an imitation bundle's files (names and bytes, in name order): which weights a kept trial used."""
    from rotation.il.bundle import resolve_il

    h = hashlib.sha256()
    root = resolve_il(path)
    for f in sorted(p for p in root.rglob("*") if p.is_file()):
        h.update(f.relative_to(root).as_posix().encode() + b"\0" + f.read_bytes())
    return h.hexdigest()


def _kept_trials(logged: list[dict[str, Any]], name: str, digest: str, seed: int, episodes: int,
                 episode_steps: int | None) -> dict[int, dict[str, float]]:
    """{j: outcome} of the trials of policy ``name`` (bundle ``digest``) among the ``logged`` rows that belong to this
    evaluation: seeds seed .. seed + episodes - 1, the same length (CurveLog.rows passes over a line cut by a stop)."""
    kept = {}
    for rec in logged:
        if not isinstance(rec, dict) or not isinstance(rec.get("seed"), int) or not isinstance(rec.get("result"), dict):
            continue
        j = rec["seed"] - seed
        if (rec.get("policy"), rec.get("bundle_sha256"), rec.get("episode_steps")) == (name, digest, episode_steps) \
                and 0 <= j < episodes:
            kept[j] = rec["result"]
    return kept


def _report(rows: list[dict[str, Any]], out: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    (out / "results.json").write_text(json.dumps({"task": "insertion", "rows": rows}, indent=2) + "\n")
    lines = ["# Plug insertion", "", "| policy | touch | episodes | success | 95% interval | time to insert (s) | "
             "peak force (N) | pressed past the limit | lost the plug |", "|---|---|---|---|---|---|---|---|---|"]
    for r in rows:
        t = "" if r["time_to_insert_s"] is None else f"{r['time_to_insert_s']:.2f}"
        lines.append(f"| {r['policy']} | {r['touch']} | {r['episodes']} | {100 * r['success_rate']:.0f}% | "
                     f"{100 * r['ci95'][0]:.0f}-{100 * r['ci95'][1]:.0f}% | {t} | {r['peak_force_N']:.1f} | "
                     f"{r['over_force']} | {r['lost_plug']} |")
    (out / "results.md").write_text("\n".join(lines) + "\n\n![success rate](success.png)\n")
    fig, ax = plt.subplots(figsize=(1.2 * len(rows) + 2, 3))
    rates = [r["success_rate"] for r in rows]
    err = np.array([[r["success_rate"] - r["ci95"][0], r["ci95"][1] - r["success_rate"]] for r in rows]).T
    ax.bar([r["policy"] for r in rows], rates, yerr=err, capsize=4, color="tab:blue")
    ax.set_ylim(0, 1)
    ax.set_ylabel("success rate (95% interval)")
    ax.tick_params(axis="x", labelrotation=30, labelsize=8)
    fig.tight_layout()
    fig.savefig(out / "success.png", dpi=110)
    plt.close(fig)
