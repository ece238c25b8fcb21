"""Bundle the oracle-latent student: a student's actor acting on the teacher's privileged latent z.

The tactile adapter corrects only the student's latent; the student's actor stays frozen. So the best any latent
correction can do is make the student act as if it knew the teacher's z exactly. Evaluating this bundle beside the
teacher, the student and an adapter shows how much of the student's gap to the teacher is the latent's (what an
adapter can close) and how much is its actor's (what no adapter can):

    python experiments/tools/oracle_latent.py --student student --teacher teacher --out runs/oracle_latent
    rotate evaluate --policy student --policy adapter --policy oracle=runs/oracle_latent \\
        --suite perturbations --conditions friction_0.25 mass_+0.2kg --episodes 128 --seed 1500000

It reads the simulator's privileged friction, mass and center of mass, like the teacher: a yardstick in
simulation, not a policy for a real hand.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

from rotation.bundles import load_bundle
from rotation.configs import script_main


@dataclass
class Config:
    student: str = "student"
    """Student bundle (a shipped name or a directory) whose actor acts."""
    teacher: str = "teacher"
    """Teacher bundle (a shipped name or a directory) whose env-factor encoder gives z."""
    out: Path = Path("runs/oracle_latent")
    """Directory for the bundle (refused if it already holds one)."""


def run(cfg: Config) -> Path:
    if (cfg.out / "config.json").exists():
        raise ValueError(f"{cfg.out} already holds a bundle; give another --out or remove it")
    oracle = load_bundle(cfg.student).with_teacher_latent(
        load_bundle(cfg.teacher), card={"role": "oracle-latent student", "student": cfg.student,
                                        "teacher": cfg.teacher})
    oracle.save(cfg.out)
    print(f"oracle-latent student ({cfg.student}'s actor on {cfg.teacher}'s z) at {cfg.out}")
    return cfg.out


def main(argv: list[str] | None = None) -> int:
    return script_main(Config, run, __doc__, argv)


if __name__ == "__main__":
    raise SystemExit(main())
