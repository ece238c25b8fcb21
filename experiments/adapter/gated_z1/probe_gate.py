"""The evidence behind gating the ensemble's z[1] correction (RULE.md): diagnostic rollouts of an adapter ensemble
under each condition, every member's correction recorded at every touch refresh, and the student actor's action
error for the correction as shipped, with the z[1] correction dropped, and with it gated by the ensemble's own
z[3] + z[4] reading at a few widths. Offline: every variant is scored on the shipped ensemble's own rollouts.

    python experiments/adapter/gated_z1/probe_gate.py --out runs/probe_gate      # about 6 min on 2 cores

Writes probe.json and probe.md (the tables RULE.md quotes) in --out. Seeds 2100000+ (16 envs x 400 steps per
condition) serve diagnostics only, never a decision.
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np
import torch

CONDITIONS = ("friction_0.25", "mass_+0.2kg", "nominal")
MASS_BINS = ((0.0, 0.15), (0.15, 0.25), (0.25, 0.35), (0.35, np.inf))


def collect(adapter: str, condition: str, seed: int, num_envs: int, steps: int) -> dict[str, np.ndarray]:
    """Per refresh and env: the student's z, each member's weighted correction, the teacher's z, the actor's
    proprioceptive features, and the mass in force; the ensemble acts as in evaluation."""
    from envs.constants import PRIV_FIELDS
    from rotation.bundles import load_bundle
    from rotation.evaluate import job
    from rotation.evaluate.suites import get_suite
    from rotation.sim_warp.host import make_vec

    policy, teacher = load_bundle(adapter), load_bundle("teacher")
    cond = get_suite("perturbations", [condition])[0]
    env_cfg = job.env_config(job.Config(policies={"adapter": adapter}, seed=seed, num_envs=num_envs), policy,
                             cond.perturb, policy.env_needs)
    env = make_vec("cpu", env_cfg, num_envs=num_envs, seed=seed, nthread=None, device="cpu")
    i_mass = PRIV_FIELDS.index("mass")
    rows: dict[str, list[np.ndarray]] = {k: [] for k in ("zs", "parts", "zt", "proprio", "mass")}
    try:
        obs = env.reset(seed=seed)
        correction = np.zeros((num_envs, policy.config.latent_dim), np.float32)
        for k in range(steps):
            groups = {key: obs[key] for key in policy.config.obs_groups}
            if k % policy.touch_every == 0:
                with torch.no_grad():
                    z = policy.student_latent(groups)
                    tokens = policy.tokens(policy.env_windows(obs))
                    parts = torch.stack([w * m.adapter(t, z) for w, m, t in
                                         zip(policy.weights, policy.members, tokens, strict=True)], 1)
                    total = parts.sum(1)
                    gate = policy.ensemble_config.gate
                    correction = (gate.apply(total) if gate is not None else total).numpy()
                    zt = teacher.net.extractor.z({key: torch.as_tensor(obs[key]) for key in teacher.config.obs_groups})
                    rows["zs"].append(z.numpy())
                    rows["parts"].append(parts.numpy())
                    rows["zt"].append(zt.numpy())
                    rows["proprio"].append(policy.proprio_features(groups).numpy())
                rows["mass"].append(obs["priv"][:, i_mass].copy())
            obs, _, terminated, truncated, _ = env.step(policy.act_batch(groups, correction=correction))
            done = np.flatnonzero(terminated | truncated)
            if len(done):
                obs = env.reset(ids=done)
                correction[done] = 0.0
    finally:
        env.close()
    return {k: np.concatenate(v) for k, v in rows.items()}


def gated(c: np.ndarray, width: float, offset: float = 0.0) -> tuple[np.ndarray, np.ndarray]:
    """The correction with z[1] scaled by clip((-(c[3] + c[4]) - offset) / width, 0, 1), and that gate."""
    g = np.clip((-(c[:, 3] + c[:, 4]) - offset) / width, 0.0, 1.0)
    out = c.copy()
    out[:, 1] *= g
    return out, g


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--adapter", default="adapter", help="the ensemble to probe (ungated)")
    parser.add_argument("--seed", type=int, default=2_100_000)
    parser.add_argument("--num-envs", type=int, default=16)
    parser.add_argument("--steps", type=int, default=400)
    parser.add_argument("--out", type=Path, required=True)
    args = parser.parse_args()
    if (args.out / "probe.json").exists():
        raise SystemExit(f"{args.out} already holds a probe; give another --out")
    torch.set_num_threads(2)
    from rotation.bundles import load_bundle

    head = load_bundle(args.adapter).student.net.head

    def action(d, z):
        with torch.no_grad():
            return head(torch.as_tensor(d["proprio"]), torch.as_tensor(z, dtype=torch.float32)).numpy()

    variants = {"student": lambda c: (0 * c, None), "shipped": lambda c: (c, None),
                "z[1] correction dropped": lambda c: (c * np.array([1, 0, 1, 1, 1, 1, 1, 1], np.float32), None)}
    for width in (0.2, 0.4, 0.8):
        for offset in (0.0, 0.2):
            variants[f"gated, width {width:g}, offset {offset:g}"] = (
                lambda c, w=width, o=offset: gated(c, w, o))
    report: dict = {"config": vars(args) | {"out": str(args.out)}, "conditions": {}}
    for condition in CONDITIONS:
        d = collect(args.adapter, condition, args.seed, args.num_envs, args.steps)
        c = d["parts"].sum(1)
        a_teacher = action(d, d["zt"])
        signal = c[:, 3] + c[:, 4]
        entry = {"samples": len(c), "signal_quartiles": np.percentile(signal, [25, 50, 75]).round(3).tolist(),
                 "mass_bins": [], "variants": {}}
        for lo, hi in MASS_BINS:
            m = (d["mass"] >= lo) & (d["mass"] < hi)
            if m.sum() < 20:
                continue
            entry["mass_bins"].append({"low": lo, "high": None if np.isinf(hi) else hi, "samples": int(m.sum()),
                                       "z1_student": float(d["zs"][m, 1].mean()),
                                       "z1_teacher": float(d["zt"][m, 1].mean()),
                                       "z1_correction_per_member": d["parts"][m, :, 1].mean(0).round(3).tolist()})
        for name, make in variants.items():
            corr, g = make(c)
            z = d["zs"] + corr
            entry["variants"][name] = {"action_mse": float(((action(d, z) - a_teacher) ** 2).mean()),
                                       "latent_mse": float(((z - d["zt"]) ** 2).mean()),
                                       "gate_open": None if g is None else float(g.mean())}
        report["conditions"][condition] = entry
        print(condition, json.dumps(entry["variants"], indent=1), flush=True)
    args.out.mkdir(parents=True, exist_ok=True)
    (args.out / "probe.json").write_text(json.dumps(report, indent=1) + "\n")
    lines = ["# z[1] of the ensemble's correction, and gating it", "",
             f"`{args.adapter}`, {args.num_envs} envs x {args.steps} steps from seed {args.seed} per condition.", "",
             "| condition | mass bin (kg) | samples | z[1] student / teacher | z[1] correction per member |",
             "|---|---|---|---|---|"]
    for condition, entry in report["conditions"].items():
        for b in entry["mass_bins"]:
            hi = "" if b["high"] is None else f"{b['high']:g}"
            lines.append(f"| {condition} | {b['low']:g}-{hi} | {b['samples']} | {b['z1_student']:+.2f} / "
                         f"{b['z1_teacher']:+.2f} | {' '.join(f'{v:+.2f}' for v in b['z1_correction_per_member'])} |")
    lines += ["", "Quartiles of the z[3] + z[4] correction: " + "; ".join(
        f"{c} {e['signal_quartiles']}" for c, e in report["conditions"].items()), "",
        "| variant | " + " | ".join(f"{c}: action MSE / latent MSE / gate open" for c in CONDITIONS) + " |",
        "|---|" + "---|" * len(CONDITIONS)]
    for name in variants:
        cells = []
        for condition in CONDITIONS:
            v = report["conditions"][condition]["variants"][name]
            gate = "-" if v["gate_open"] is None else f"{v['gate_open']:.2f}"
            cells.append(f"{v['action_mse']:.4f} / {v['latent_mse']:.4f} / {gate}")
        lines.append(f"| {name} | " + " | ".join(cells) + " |")
    (args.out / "probe.md").write_text("\n".join(lines) + "\n")
    print("\n".join(lines))


if __name__ == "__main__":
    main()
