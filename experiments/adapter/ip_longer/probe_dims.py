"""The evidence behind scaling some latent dimensions of the shipped ensemble's correction (RULE.md): diagnostic
rollouts of the ensemble under each condition, every member's correction recorded at every touch refresh, then,
per mass bin, the mean of each latent dimension for the student, the ensemble and the teacher, and the student
actor's action error against its action on the teacher's z for a few per-dimension scalings of the correction.
Offline: every variant is scored on the shipped ensemble's own rollouts.

    python experiments/adapter/ip_longer/probe_dims.py --out runs/probe_dims      # about 6 min on 2 cores

Writes probe.json and probe.md in --out. Seeds 2100000+ (16 envs x 400 steps per condition) serve diagnostics only,
never a decision.
"""

from __future__ import annotations

import argparse
import importlib.util
import json
from pathlib import Path

import numpy as np
import torch

CONDITIONS = ("friction_0.25", "mass_+0.2kg", "nominal")
MASS_BINS = ((0.0, 0.15), (0.15, 0.25), (0.25, 0.35), (0.35, np.inf))
# name -> per-dimension factor on the shipped correction (dimensions not named keep 1)
VARIANTS = {
    "shipped": {},
    "z[2] x1.5": {2: 1.5},
    "z[2] x2": {2: 2.0},
    "z[2], z[5] x1.5": {2: 1.5, 5: 1.5},
    "z[2], z[5] x2": {2: 2.0, 5: 2.0},
    "z[5] x2": {5: 2.0},
    "z[1] x0.5": {1: 0.5},
    "z[1] x0.5, z[2] x1.5": {1: 0.5, 2: 1.5},
}


def _collect():
    """probe_gate.collect, which records the same rollouts (one copy of that code)."""
    path = Path(__file__).resolve().parent.parent / "gated_z1" / "probe_gate.py"
    spec = importlib.util.spec_from_file_location("probe_gate", path)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module.collect


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--adapter", default="adapter", help="the ensemble to probe")
    parser.add_argument("--seed", type=int, default=2_100_000)
    parser.add_argument("--num-envs", type=int, default=16)
    parser.add_argument("--steps", type=int, default=400)
    parser.add_argument("--conditions", nargs="+", default=list(CONDITIONS), choices=CONDITIONS)
    parser.add_argument("--out", type=Path, required=True)
    args = parser.parse_args()
    if (args.out / "probe.json").exists():
        raise SystemExit(f"{args.out} already holds a probe; give another --out")
    torch.set_num_threads(2)
    from rotation.bundles import load_bundle

    collect = _collect()
    head = load_bundle(args.adapter).student.net.head

    def action(d, z):
        with torch.no_grad():
            return head(torch.as_tensor(d["proprio"]), torch.as_tensor(z, dtype=torch.float32)).numpy()

    report: dict = {"config": vars(args) | {"out": str(args.out)}, "conditions": {}}
    for condition in args.conditions:
        d = collect(args.adapter, condition, args.seed, args.num_envs, args.steps)
        c = d["parts"].sum(1)
        zdim = c.shape[1]
        a_teacher = action(d, d["zt"])
        entry = {"samples": len(c), "mass_bins": [], "variants": {}}
        for lo, hi in MASS_BINS:
            m = (d["mass"] >= lo) & (d["mass"] < hi)
            if m.sum() < 20:
                continue
            entry["mass_bins"].append({
                "low": lo, "high": None if np.isinf(hi) else hi, "samples": int(m.sum()),
                "z_student": d["zs"][m].mean(0).round(3).tolist(),
                "z_adapted": (d["zs"][m] + c[m]).mean(0).round(3).tolist(),
                "z_teacher": d["zt"][m].mean(0).round(3).tolist(),
                "correction_per_member": d["parts"][m].mean(0).round(3).tolist()})
        for name, scale in VARIANTS.items():
            f = np.ones(zdim, np.float32)
            for k, v in scale.items():
                f[k] = v
            z = d["zs"] + c * f
            err = ((action(d, z) - a_teacher) ** 2).mean(1)
            per_bin = {}
            for lo, hi in MASS_BINS:
                m = (d["mass"] >= lo) & (d["mass"] < hi)
                if m.sum() >= 20:
                    per_bin[f"{lo:g}"] = float(err[m].mean())
            entry["variants"][name] = {"action_mse": float(err.mean()),
                                       "latent_mse": float(((z - d["zt"]) ** 2).mean()),
                                       "action_mse_by_mass_bin": per_bin}
        report["conditions"][condition] = entry
        print(condition, json.dumps(entry["variants"], indent=1), flush=True)
    args.out.mkdir(parents=True, exist_ok=True)
    (args.out / "probe.json").write_text(json.dumps(report, indent=1) + "\n")

    def fmt(v):
        return " ".join(f"{x:+.2f}" for x in v)

    lines = ["# Per-dimension latents of the ensemble's rollouts, and scaling some of its correction", "",
             f"`{args.adapter}`, {args.num_envs} envs x {args.steps} steps from seed {args.seed} per condition.", "",
             "| condition | mass bin (kg) | samples | z student | z adapted | z teacher | correction per member |",
             "|---|---|---|---|---|---|---|"]
    for condition, entry in report["conditions"].items():
        for b in entry["mass_bins"]:
            hi = "" if b["high"] is None else f"{b['high']:g}"
            members = " / ".join(fmt(p) for p in b["correction_per_member"])
            lines.append(f"| {condition} | {b['low']:g}-{hi} | {b['samples']} | {fmt(b['z_student'])} | "
                         f"{fmt(b['z_adapted'])} | {fmt(b['z_teacher'])} | {members} |")
    lines += ["", "Action MSE (the student actor on each latent against its action on the teacher's z) and latent "
              "MSE; in brackets the action MSE per mass bin (lower edge, kg).", "",
              "| variant | " + " | ".join(f"{c}: action MSE / latent MSE [by mass]" for c in args.conditions) + " |",
              "|---|" + "---|" * len(args.conditions)]
    for name in VARIANTS:
        cells = []
        for condition in args.conditions:
            v = report["conditions"][condition]["variants"][name]
            bins = " ".join(f"{k}: {x:.4f}" for k, x in v["action_mse_by_mass_bin"].items())
            cells.append(f"{v['action_mse']:.4f} / {v['latent_mse']:.4f} [{bins}]")
        lines.append(f"| {name} | " + " | ".join(cells) + " |")
    (args.out / "probe.md").write_text("\n".join(lines) + "\n")
    print("\n".join(lines))


if __name__ == "__main__":
    main()
