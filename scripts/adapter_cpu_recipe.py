"""The tactile adapter of one student on a CPU alone: the five ablation rows of docs/adapter.md trained in simulation
with the measured touch delay, the oracle-latent student, the two-member ensemble, its evaluation beside the
teacher, the student and the oracle on fresh seeds, the rows' evaluation on the same seeds, and the ensemble's ttf
against the delay.

    python scripts/adapter_cpu_recipe.py --student student --teacher teacher --encoder sparshx-tinier-sim \\
        --out runs/adapter_cpu
    python scripts/adapter_cpu_recipe.py ... --dry-run           # the commands, run nothing

Steps (each a `rotate` command or a script; a finished one is skipped, a stopped one resumes):

1. five `rotate finetune-adapter` runs from zero, the same options apart from their inputs (ROWS): all modalities,
   image only, no image, IMU + pressure + the joints' tracking, tracking only (`--blind-touch`); each acts with the
   student alone for its first ``student_steps`` env steps, then DAgger with its own corrections, every refresh
   landing ``touch_delay`` control steps late (default: the delay measured in an emulated deploy on 2 cores);
2. the oracle-latent student (experiments/tools/oracle_latent.py): the student's actor on the teacher's true z,
   the ceiling of any latent correction;
3. `rotate ensemble-adapters` of the all-modality and IMU + pressure + tracking rows (equal weights): the shipped
   adapter's structure;
4. `rotate evaluate` of the teacher, the student, the oracle and the ensemble on the same episodes (fresh seeds,
   the slippery, heavy and combined extremes of the perturbation suite and nominal; ``episodes`` each), with the
   same delay: OUT/evaluation/results.md, the table a shipping decision reads;
5. `rotate evaluate` of the five rows, the ablation, on the first ``ablation_episodes`` of those episodes (the same
   seeds, so every row pairs with the policies of step 4) and ABLATION_CONDITIONS: OUT/ablation/results.md;
6. `scripts/delay_sweep.py` of the ensemble: ttf against the delay, 0 to 4 control steps, on SWEEP_CONDITIONS
   (``sweep_episodes`` each; OUT/delay_sweep/).

Budget on 2 CPU cores: a row of 24,000 env steps takes about 7 min reading IMU and pressure (the shipped
imu_pressure_tracking member's card) and longer with the image and audio, whose windows are rendered and encoded at
every refresh (about 16 env steps/s for the all-modality row: 25 min). An evaluation that renders touch runs at
a few hundred env steps/s, so the ablation and the sweep evaluate fewer episodes and conditions than step 4; give
a GPU's sizes with --ablation-episodes and --sweep-episodes.
Each `rotate` step keeps its checkpoints, so running the script again after a stop continues it.
"""

from __future__ import annotations

import json
import sys
from dataclasses import dataclass
from pathlib import Path

from adapters.finetune.config import CHECKPOINT_GLOB
from rotation.configs import script_main
from rotation.jobs.recipe import progress_args, run_steps

ROWS: tuple[tuple[str, list[str]], ...] = (
    ("all_modalities", ["--modalities", "img,mic,imu,pressure"]),
    ("image_only", ["--modalities", "img"]),
    ("no_image", ["--modalities", "mic,imu,pressure"]),
    ("imu_pressure_tracking", ["--modalities", "imu,pressure", "--tracking"]),
    ("tracking_only", ["--modalities", "pressure", "--tracking", "--blind-touch"]),
)
"""(row, the options that make it): docs/adapter.md "What each input carries"."""
ENSEMBLE = ("all_modalities", "imu_pressure_tracking")
"""The rows the ensemble puts together (the shipped adapter's two members)."""
CONDITIONS = ("nominal", "friction_0.25", "mass_+0.1kg", "friction_0.5+mass_+0.1kg")
"""The perturbation suite's slippery, heavy and combined extremes on the vendor-kinematics hand, and nominal."""
ABLATION_CONDITIONS = ("nominal", "friction_0.25", "mass_+0.1kg")
"""What the ablation rows are evaluated on: which input carries friction, which mass, and what each costs at nominal."""
SWEEP_CONDITIONS = ("friction_0.25", "mass_+0.1kg")
"""What the delay sweep evaluates on: the two perturbations the adapter targets."""
SCRIPTS = Path(__file__).resolve().parent
ORACLE_TOOL = SCRIPTS.parent / "experiments" / "tools" / "oracle_latent.py"


@dataclass
class Config:
    student: str = ""
    """The student bundle the adapters correct (its hand is the evaluation's)."""
    teacher: str = ""
    """The teacher whose privileged latent they learn (the student's own teacher)."""
    encoder: str = ""
    """The frozen touch encoder (a shipped name, an exported encoder folder or file)."""
    out: Path = Path("runs/adapter_cpu")
    """Folder of the recipe: members/<row>/, oracle/, ensemble/, evaluation/, delay_sweep/."""
    total_steps: int = 24_000
    """Env steps of each row's training."""
    student_steps: int = 6_000
    """Env steps at the start of each row during which the student acts alone."""
    num_envs: int = 16
    touch_every: int = 4
    """Control steps between touch refreshes (5 Hz at 20 Hz)."""
    touch_delay: str = "measured"
    """The delay every refresh lands with, in training and evaluation (adapters.touch_delay: 'measured', N or
    N:P,...)."""
    seed: int = 31
    """Seed of every row's training (the same episodes for all rows)."""
    episodes: int = 128
    """Evaluation episodes per policy and condition of step 4 (teacher, student, oracle, ensemble)."""
    ablation_episodes: int = 64
    """Episodes per row and condition of the ablation (the first of step 4's episodes)."""
    sweep_episodes: int = 64
    """Episodes per delay and condition of the delay sweep."""
    eval_seed: int = 9_700_000
    """First seed of the evaluation and of the delay sweep (keep it away from every seed a choice used)."""
    progress: bool = True
    """Progress bars."""
    dry_run: bool = False
    """Print the commands without running them."""

    def __post_init__(self) -> None:
        self.out = Path(self.out)
        missing = [name for name in ("student", "teacher", "encoder") if not getattr(self, name)]
        if missing:
            raise ValueError(f"give {', '.join('--' + m for m in missing)}: the student the adapters correct, its "
                             "teacher, and the touch encoder they read")
        for name in ("total_steps", "student_steps", "num_envs", "touch_every", "episodes", "ablation_episodes",
                     "sweep_episodes"):
            if int(getattr(self, name)) < 1:
                raise ValueError(f"{name} must be >= 1, got {getattr(self, name)}")
        if self.student_steps >= self.total_steps:
            raise ValueError(f"student_steps ({self.student_steps}) must be below total_steps ({self.total_steps})")


def _finished(run: Path, steps: int) -> bool:
    """Whether ``run`` holds the finished bundle of a `rotate finetune-adapter` run of ``steps`` env steps."""
    try:
        card = json.loads((run / "bundle" / "config.json").read_text())["card"]
    except (OSError, ValueError, KeyError, TypeError):
        return False
    return isinstance(card, dict) and "interrupted" not in card and int(card.get("env_steps", 0)) >= steps


def commands(cfg: Config) -> list[tuple[str, list[str]]]:
    """(what, command) still to run, in order (`rotate` subcommands, or 'python' and a script)."""
    out, todo = cfg.out, []
    progress = progress_args(cfg.progress)
    for row, options in ROWS:
        run = out / "members" / row
        if _finished(run, cfg.total_steps):
            continue
        if any(run.glob(CHECKPOINT_GLOB)):
            todo.append((f"{row}: resume", ["finetune-adapter", "--out", str(run), "--resume", *progress]))
            continue
        todo.append((f"{row}: {cfg.total_steps} env steps", [
            "finetune-adapter", "--student", cfg.student, "--teacher", cfg.teacher, "--encoder", cfg.encoder,
            *options, "--total-steps", str(cfg.total_steps), "--num-envs", str(cfg.num_envs), "--touch-every",
            str(cfg.touch_every), "--student-steps", str(cfg.student_steps), "--seed", str(cfg.seed),
            "--checkpoint-every", str(max(cfg.total_steps // 6, 1)), "--touch-delay", cfg.touch_delay,
            "--out", str(run), *progress]))
    if not (out / "oracle" / "config.json").is_file():
        todo.append(("the oracle-latent student", ["python", str(ORACLE_TOOL), "--student", cfg.student,
                                                   "--teacher", cfg.teacher, "--out", str(out / "oracle")]))
    if not (out / "ensemble" / "config.json").is_file():
        todo.append(("the ensemble", ["ensemble-adapters", "--members",
                                      *(str(out / "members" / row / "bundle") for row in ENSEMBLE),
                                      "--out", str(out / "ensemble")]))
    policies = {"teacher": cfg.teacher, "student": cfg.student, "oracle": str(out / "oracle"),
                "ensemble": str(out / "ensemble")}
    rows = {row: str(out / "members" / row / "bundle") for row, _ in ROWS}
    for what, folder, chosen, conditions, episodes in (
            ("the evaluation", "evaluation", policies, CONDITIONS, cfg.episodes),
            ("the ablation", "ablation", rows, ABLATION_CONDITIONS, cfg.ablation_episodes)):
        if not (out / folder / "results.md").is_file():
            todo.append((what, ["evaluate", *(a for n, p in chosen.items() for a in ("--policy", f"{n}={p}")),
                                "--conditions", *conditions, "--episodes", str(episodes), "--num-envs", "16",
                                "--seed", str(cfg.eval_seed), "--touch-delay", cfg.touch_delay,
                                "--out", str(out / folder), *progress]))
    if not (out / "delay_sweep" / "delay_sweep.md").is_file():
        todo.append(("ttf against the delay", ["python", str(SCRIPTS / "delay_sweep.py"), "--adapter",
                                               str(out / "ensemble"), "--student", cfg.student, "--teacher",
                                               cfg.teacher, "--conditions", *SWEEP_CONDITIONS, "--episodes",
                                               str(cfg.sweep_episodes), "--seed", str(cfg.eval_seed), "--out",
                                               str(out / "delay_sweep"), *progress]))
    return todo


def run(cfg: Config) -> int:
    todo = commands(cfg)
    if not todo:
        print(f"adapter_cpu_recipe: every step is done; the table is {cfg.out / 'evaluation' / 'results.md'}")
        return 0
    status = run_steps("adapter_cpu_recipe", todo, cfg.dry_run)
    if status == 0 and not cfg.dry_run:
        print(f"adapter_cpu_recipe: done; the table is {cfg.out / 'evaluation' / 'results.md'}, the ablation "
              f"{cfg.out / 'ablation' / 'results.md'}, the delay sweep {cfg.out / 'delay_sweep' / 'delay_sweep.md'}")
    return status


def main(argv: list[str] | None = None) -> int:
    return script_main(Config, run, __doc__, argv)


if __name__ == "__main__":
    sys.exit(main())
