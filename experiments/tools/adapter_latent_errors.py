"""Where an adapter's latent is wrong: its error to the teacher's z along its own rollouts, by friction and mass.

The adapter is a regressor trained on the cups its DAgger run drew. Evaluated on cups outside that range, it can
move the student's latent the wrong way. This script runs an adapter bundle under one evaluation condition, and at
every touch refresh records three latents for every env: the student's own (phi), the adapted one (phi plus the
correction) and the teacher's z from the privileged friction, mass and center of mass, and the frozen student
actor's action mean on each of the three (same proprioception). A latent error only matters as far as it moves the
action, so the action errors say which latent errors cost something. It then groups the samples by the friction
and the mass actually in force, and by the time into the episode:

- ``errors.md`` / ``errors.json``: per bin, the samples, the mean squared error of the student's and the adapted
  latent to the teacher's z, the same for the actor's actions on them against its action on the teacher's z, and
  the mean of every latent dimension for the three (a dimension the adapter moves away from the teacher's shows up
  there); the time bins say whether the errors grow late in an episode, where the cup is lost;
- ``errors.png``: the latent and the action errors per friction, mass and time bin.

The same condition and seed give the same cups as ``rotate evaluate`` with that seed (env i of a batch seeded s is
an env seeded s + i), so the bins can be read beside an evaluation's ttf.

    python experiments/tools/adapter_latent_errors.py --adapter adapter --condition mass_+0.2kg --seed 2100000 \\
        --out runs/latent_errors
"""

from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch

from rotation.configs import save_config, script_main


@dataclass
class Config:
    adapter: str = "adapter"
    """Adapter bundle (a shipped name or a directory) to run."""
    teacher: str = "teacher"
    """Teacher bundle whose env-factor encoder gives the target z."""
    condition: str = "mass_+0.2kg"
    """A condition of the perturbations suite (rotation.evaluate.suites), on top of the training randomization."""
    seed: int = 2_100_000
    """Env i is seeded seed + i; episodes that end restart in the same env."""
    num_envs: int = 16
    """Simulations stepped together."""
    steps: int = 400
    """Control steps per env (a refresh every touch_every of them is recorded)."""
    friction_edges: tuple[float, ...] = (0.75, 1.5, 2.25)
    """Inner edges of the friction bins."""
    mass_edges: tuple[float, ...] = (0.15, 0.25, 0.35)
    """Inner edges of the mass bins (kg)."""
    time_edges: tuple[float, ...] = (6.4, 12.8)
    """Inner edges of the time-into-episode bins (s; 6.4 s is where the shipped adapters' training episodes were
    cut)."""
    torch_threads: int = 2
    """torch CPU threads."""
    out: Path = Path("runs/latent_errors")
    """Report directory (refused if it already holds a report)."""


@dataclass
class Samples:
    """Per refresh and env: the three latents (M, Z), the friction and mass in force and the time into the episode
    in s (M,), and the student actor's action means (M, A) on the three latents (None when not recorded)."""

    student: np.ndarray
    adapted: np.ndarray
    teacher: np.ndarray
    friction: np.ndarray
    mass: np.ndarray
    time: np.ndarray
    action_student: np.ndarray | None = None
    action_adapted: np.ndarray | None = None
    action_teacher: np.ndarray | None = None


def collect(cfg: Config) -> Samples:
    """Run the adapter (deterministic actions, the correction held between refreshes as in evaluation)."""
    from envs.constants import PRIV_FIELDS
    from rotation.bundles import load_bundle, policy_hand
    from rotation.evaluate import job
    from rotation.evaluate.rollout import touch_correction
    from rotation.evaluate.suites import get_suite
    from rotation.sim_warp.host import make_vec

    policy, teacher = load_bundle(cfg.adapter), load_bundle(cfg.teacher)
    if not job.reads_touch(policy):
        raise ValueError(f"--adapter {cfg.adapter!r} is not an adapter bundle (it reads no touch)")
    teacher.require("privileged", f"--teacher {cfg.teacher!r}")
    if teacher.config.latent_dim != policy.config.latent_dim:
        raise ValueError(f"--teacher {cfg.teacher!r} has a {teacher.config.latent_dim}-dim latent, the adapter's "
                         f"student a {policy.config.latent_dim}-dim one")
    cond = get_suite("perturbations", [cfg.condition], hand=policy_hand(policy))[0]  # on the hand the env runs
    ecfg = job.Config(policies={"adapter": cfg.adapter}, seed=cfg.seed, num_envs=cfg.num_envs)
    env_cfg = job.env_config(ecfg, policy, cond.perturb, policy.env_needs)
    env = make_vec("cpu", env_cfg, num_envs=cfg.num_envs, seed=cfg.seed, nthread=None, device="cpu")
    i_fr, i_mass = PRIV_FIELDS.index("friction"), PRIV_FIELDS.index("mass")
    rows: dict[str, list[np.ndarray]] = {k: [] for k in ("student", "adapted", "teacher", "friction", "mass", "time",
                                                         "action_student", "action_adapted", "action_teacher")}
    elapsed = np.zeros(cfg.num_envs, np.int64)  # control steps since each env's episode began
    head = policy.student.net.head
    try:
        obs = env.reset(seed=cfg.seed)
        correction = np.zeros((cfg.num_envs, policy.config.latent_dim), np.float32)
        for k in range(cfg.steps):
            groups = {key: obs[key] for key in policy.config.obs_groups}
            if k % policy.touch_every == 0:
                correction = touch_correction(policy, obs, groups)
                with torch.no_grad():
                    z_student = policy.student_latent(groups)
                    z_teacher = teacher.net.extractor.z(
                        {key: torch.as_tensor(obs[key]) for key in teacher.config.obs_groups})
                    z_adapted = z_student + torch.as_tensor(correction)
                    proprio = policy.proprio_features(groups)
                    for name, z in (("student", z_student), ("adapted", z_adapted), ("teacher", z_teacher)):
                        rows[name].append(z.numpy())
                        rows[f"action_{name}"].append(head(proprio, z).numpy())
                rows["friction"].append(obs["priv"][:, i_fr].copy())
                rows["mass"].append(obs["priv"][:, i_mass].copy())
                rows["time"].append(elapsed * env_cfg.control_dt)
            obs, _, terminated, truncated, _ = env.step(policy.act_batch(groups, correction=correction))
            elapsed += 1
            done = np.flatnonzero(terminated | truncated)
            if len(done):
                obs = env.reset(ids=done)
                elapsed[done] = 0
                correction[done] = 0.0  # a fresh episode is the student until its first refresh
    finally:
        env.close()
    return Samples(**{k: np.concatenate(v) for k, v in rows.items()})


def bin_table(samples: Samples, values: np.ndarray, edges: tuple[float, ...]) -> list[dict]:
    """One row per non-empty bin of ``values``: range, samples, both latent errors (and both action errors when the
    samples hold actions), per-dimension means."""
    bounds = [-np.inf, *edges, np.inf]
    rows = []
    for lo, hi in zip(bounds[:-1], bounds[1:], strict=True):
        m = (values >= lo) & (values < hi)
        if not m.any():
            continue
        s, a, t = samples.student[m], samples.adapted[m], samples.teacher[m]
        rows.append({"low": None if np.isinf(lo) else float(lo), "high": None if np.isinf(hi) else float(hi),
                     "samples": int(m.sum()),
                     "mse_student": float(((s - t) ** 2).mean()), "mse_adapted": float(((a - t) ** 2).mean()),
                     "mean_student": s.mean(0).round(3).tolist(), "mean_adapted": a.mean(0).round(3).tolist(),
                     "mean_teacher": t.mean(0).round(3).tolist()})
        if samples.action_teacher is not None:
            target = samples.action_teacher[m]
            rows[-1]["action_mse_student"] = float(((samples.action_student[m] - target) ** 2).mean())
            rows[-1]["action_mse_adapted"] = float(((samples.action_adapted[m] - target) ** 2).mean())
    return rows


_BINNINGS = (("friction", "", "friction in force"), ("mass", " kg", "mass in force"),
             ("time", " s", "time into the episode"))
"""Report tables in order: what the samples are grouped by (a Samples field, its inner edges Config.<name>_edges),
its unit, and the plot's axis label."""


def _label(row: dict, unit: str = "") -> str:
    if row["low"] is None:
        return f"< {row['high']:g}{unit}"
    if row["high"] is None:
        return f">= {row['low']:g}{unit}"
    return f"{row['low']:g}-{row['high']:g}{unit}"


def markdown(cfg: Config, tables: dict[str, list[dict]], total: dict) -> str:
    lines = [f"# Latent errors of `{cfg.adapter}` under `{cfg.condition}`", "",
             f"{cfg.num_envs} envs x {cfg.steps} steps from seed {cfg.seed}; every touch refresh of every env is a "
             f"sample ({total['samples']} in all). Mean squared error to the teacher's z: student "
             f"{total['mse_student']:.4f}, adapted {total['mse_adapted']:.4f}. The student actor's action mean on "
             f"each latent against its action on the teacher's z: student {total['action_mse_student']:.5f}, "
             f"adapted {total['action_mse_adapted']:.5f}.", ""]
    for name, unit, _ in _BINNINGS:
        lines += [f"## By {name}", "",
                  "| bin | samples | latent MSE student | latent MSE adapted | action MSE student | action MSE adapted "
                  "| mean z: student / adapted / teacher |",
                  "|---|---|---|---|---|---|---|"]
        for row in tables[name]:
            means = " / ".join(" ".join(f"{v:+.2f}" for v in row[k])
                               for k in ("mean_student", "mean_adapted", "mean_teacher"))
            lines.append(f"| {_label(row, unit)} | {row['samples']} | {row['mse_student']:.4f} | "
                         f"{row['mse_adapted']:.4f} | {row['action_mse_student']:.5f} | "
                         f"{row['action_mse_adapted']:.5f} | {means} |")
        lines.append("")
    return "\n".join(lines)


def plot(tables: dict[str, list[dict]], path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(2, len(_BINNINGS), figsize=(5 * len(_BINNINGS), 7.2))
    for col, (name, unit, axis) in enumerate(_BINNINGS):
        rows = tables[name]
        x = np.arange(len(rows))
        for ax, key, what in ((axes[0, col], "mse", "latent MSE to the teacher's z"),
                              (axes[1, col], "action_mse", "action MSE to the action on the teacher's z")):
            ax.bar(x - 0.2, [r[f"{key}_student"] for r in rows], 0.4, label="student")
            ax.bar(x + 0.2, [r[f"{key}_adapted"] for r in rows], 0.4, label="student + adapter")
            ax.set_xticks(x, [f"{_label(r, unit)}\n({r['samples']})" for r in rows])
            ax.set_xlabel(f"{axis} (samples)")
            ax.set_ylabel(what)
            ax.grid(axis="y", alpha=0.3)
    axes[0, 0].legend()
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def run(cfg: Config) -> dict:
    if cfg.num_envs < 1 or cfg.steps < 1 or cfg.torch_threads < 1:
        raise ValueError(f"num_envs, steps and torch_threads must be >= 1, got {cfg.num_envs}, {cfg.steps}, "
                         f"{cfg.torch_threads}")
    for name, _, _ in _BINNINGS:
        edges = getattr(cfg, f"{name}_edges")
        if list(edges) != sorted(set(edges)):
            raise ValueError(f"{name}_edges must be strictly increasing, got {list(edges)}")
    if (cfg.out / "errors.json").exists():
        raise ValueError(f"{cfg.out} already holds a report; give another --out or remove it")
    torch.set_num_threads(cfg.torch_threads)
    samples = collect(cfg)
    tables = {name: bin_table(samples, getattr(samples, name), getattr(cfg, f"{name}_edges"))
              for name, _, _ in _BINNINGS}
    total = bin_table(samples, samples.mass, ())[0]
    cfg.out.mkdir(parents=True, exist_ok=True)
    save_config(cfg, cfg.out / "config.json")
    report = {"total": {k: total[k] for k in ("samples", "mse_student", "mse_adapted", "action_mse_student",
                                              "action_mse_adapted")}, **tables}
    (cfg.out / "errors.json").write_text(json.dumps(report, indent=1) + "\n")
    (cfg.out / "errors.md").write_text(markdown(cfg, tables, report["total"]))
    plot(tables, cfg.out / "errors.png")
    print(markdown(cfg, tables, report["total"]))
    return report


def main(argv: list[str] | None = None) -> int:
    return script_main(Config, run, __doc__, argv)


if __name__ == "__main__":
    raise SystemExit(main())
