"""Ship a trained policy bundle inside the package, with a model card.

Copies a bundle directory (config.json + model.safetensors) to rotation/policies/<name>/ and writes MODEL_CARD.md
beside it: the exact training command, seed, steps, wall time, machine, and the rows of an evaluation report
(results.json from `rotate evaluate`) for this policy.

    python scripts/ship_policy.py --bundle runs/teacher/bundle --name teacher --replace \
        --command "rotate train-teacher --out runs/teacher" --evaluation runs/evaluation/results.json

A bundle already shipped under that name (tracked files of the repository) is replaced only with --replace.
"""

from __future__ import annotations

import json
import platform
import shutil
from dataclasses import dataclass
from pathlib import Path

from rotation.bundles import load_bundle
from rotation.configs import script_main

PACKAGE_POLICIES = Path(__file__).resolve().parents[1] / "rotation" / "policies"
METRICS = ("net_rotation_rate", "rotation_rate", "ttf", "upright", "vertical_drift", "lin_vel", "torque")


@dataclass
class Config:
    bundle: Path = Path("runs/teacher/bundle")
    """Bundle directory to ship."""
    name: str = "teacher"
    """Shipped name (rotation/policies/<name>)."""
    command: str = ""
    """The exact command(s) that trained it, as run (several runs joined with ' && ')."""
    evaluation: Path | None = None
    """results.json of an evaluation that includes this policy (its rows go into the card)."""
    label: str = ""
    """The policy's label in that evaluation (default: the shipped name)."""
    wall_time_s: float | None = None
    """Total training wall time (s) across resumes; default: the bundle card's own figure."""
    notes: str = ""
    """Free text for the card (what was tried, known weaknesses)."""
    replace: bool = False
    """Replace the bundle already shipped under ``name`` (its directory is deleted first); without it, refused."""


def machine() -> str:
    import os

    return f"{platform.system()} {platform.machine()}, {os.cpu_count()} CPU cores, Python {platform.python_version()}"


def run(cfg: Config) -> Path:
    bundle = load_bundle(cfg.bundle)  # validates before anything is replaced
    rows = []
    if cfg.evaluation is not None:
        label = cfg.label or cfg.name
        rows = [r for r in json.loads(Path(cfg.evaluation).read_text())["rows"] if r["policy"] == label]
        if not rows:
            raise ValueError(f"{cfg.evaluation} has no rows for policy {label!r}")
    card = dict(bundle.config.card)
    dest = PACKAGE_POLICIES / cfg.name
    if dest.exists() and not cfg.replace:
        raise ValueError(f"a bundle ships as {cfg.name!r} already ({dest}); pass --replace to replace it, or choose "
                         "another --name")
    if dest.exists():
        shutil.rmtree(dest)
    dest.mkdir(parents=True)
    weights = "adapter.safetensors" if hasattr(bundle, "adapter_config") else "model.safetensors"
    for f in ("config.json", weights):  # an adapter bundle names its student and encoder: they are not copied
        shutil.copy2(cfg.bundle / f, dest / f)
    load_bundle(dest)
    wall = cfg.wall_time_s if cfg.wall_time_s is not None else card.get("wall_time_s")
    # teacher cards say steps/seed; student cards env_steps and the seed inside their config
    steps = card.get("steps", card.get("env_steps"))
    seed = card.get("seed", card.get("config", {}).get("seed", "?"))
    lines = [f"# Model card: {cfg.name}", "",
             f"- role: {card.get('role', card.get('kind', '?'))} (latent source `{bundle.config.latent_source}`)",
             f"- env: RotateCup-v0, object `{card.get('object', 'cup')}`, Hora's domain randomization",
             f"- training command: `{cfg.command or card.get('command', 'unknown')}`",
             f"- seed: {seed}",
             f"- environment steps: {steps:,}" if isinstance(steps, int) else f"- environment steps: {steps}",
             f"- wall time: {wall / 3600:.2f} h" if isinstance(wall, int | float) else "- wall time: unknown",
             f"- machine: {machine()}",
             f"- files: config.json, {weights} ({(dest / weights).stat().st_size / 1e6:.2f} MB)",
             ""]
    if rows:
        pooled = len({r["episodes"] for r in rows}) > 1  # a pooled report's conditions can differ in episodes
        columns = ["condition", *(["episodes"] if pooled else []), *METRICS]
        where = f"`{cfg.evaluation}`" if pooled else f"{rows[0]['episodes']} episodes per condition, `{cfg.evaluation}`"
        lines += [f"## Evaluation ({where})", "", "| " + " | ".join(columns) + " |", "|" + "---|" * len(columns)]
        lines += ["| " + " | ".join([r["condition"], *([str(r["episodes"])] if pooled else []),
                                     *(f"{r[m]:.3f}" for m in METRICS)]) + " |" for r in rows]
        lines.append("")
    if cfg.notes:
        lines += ["## Notes", "", cfg.notes, ""]
    (dest / "MODEL_CARD.md").write_text("\n".join(lines))
    print(f"shipped {cfg.bundle} as {dest}")
    return dest


if __name__ == "__main__":
    raise SystemExit(script_main(Config, run, __doc__))
