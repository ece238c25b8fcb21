"""The teacher from random weights on a CPU alone: five `rotate train-teacher` stages (docs/results/teacher_cpu_recipe).

The shipped teacher's first stage ran on a GPU machine. This recipe needs none: on 2 CPU cores it took about 2.8 h
(37.1 M environment steps) to a teacher that meets issue 8's targets on fresh seeds (net rate >= 0.30 rad/s, ttf
>= 0.90, upright >= 0.90 at nominal randomization). The stages:

0. the grasp cache from before the hold check (`rotate grasps --hold-seconds 0`), a third of whose grasps cannot
   hold the cup by themselves: from grasps that slip, keeping the cup needs the fingers to move it, and stage 1
   learns a gait that turns it (from grasps that hold, standing still is a strong local optimum);
1. 11.1 M steps from random weights, 2048 envs x 16 steps, on those grasps (the shipped teacher's GPU stage);
2. 6.9 M steps from stage 1's bundle, 512 envs x 32 steps, with the backward clip at 5 rad/s (the default 0.5 lets
   the policy learn a forward-then-snap-back ratchet);
3. 5.0 M steps on the shipped, hold-checked grasps with a fall costing 60: the policy learns to hold the cup
   (ttf 0.98) and turns it slowly (0.22 rad/s);
4. 12.0 M steps with a fall costing 35: it turns the cup faster again (0.5 rad/s) and keeps holding it;
5. 2.0 M steps with a fall costing 60 again: it holds the cup longer (ttf 0.91 -> 0.95) at the same rate.

Then the final bundle is evaluated at nominal randomization on fresh seeds. Each stage writes its own run folder
under --out (checkpoints, curves, TensorBoard logs, bundle). Running the script again continues: a finished stage
is skipped, a stopped one resumes from its last checkpoint. Ctrl-C stops the running stage with a checkpoint.

    python scripts/teacher_cpu_recipe.py --out runs/teacher_cpu              # about 2.8 h on 2 cores
    python scripts/teacher_cpu_recipe.py --out runs/teacher_cpu --dry-run    # the commands, run nothing
    tensorboard --logdir runs/teacher_cpu

Stage lengths are whole rollouts; a reproduction is not bit for bit the documented one (MuJoCo and torch differ
across CPUs in the last bits, and the documented stage 2 was resumed once, which reseeds its episodes), so judge
it by its evaluation, as the report does.
"""

from __future__ import annotations

import json
import shlex
import sys
from dataclasses import dataclass
from pathlib import Path

from rotation.configs import script_main

STAGE2_PPO = ["--critic-warmup", "20", "--num-envs", "512", "--n-steps", "32", "--batch-size", "4096", "--n-epochs",
              "5", "--learning-rate", "3e-4", "--log-std-init", "-1.0", "--rotate-back-clip", "5", "--no-overlap"]
"""The PPO options of stages 2-5 (the shipped teacher's CPU stages, with the backward clip at 5)."""

STAGES: tuple[tuple[str, int, list[str]], ...] = (
    ("stage1", 340 * 2048 * 16, ["--num-envs", "2048", "--n-steps", "16", "--batch-size", "8192", "--n-epochs", "5",
                                 "--no-overlap", "--seed", "0", "--grasp-cache", "{grasps}"]),
    ("stage2", 423 * 512 * 32, ["--init-from", "{prev}", *STAGE2_PPO, "--seed", "3", "--grasp-cache", "{grasps}"]),
    ("stage3", 305 * 512 * 32, ["--init-from", "{prev}", *STAGE2_PPO, "--fall-reward", "-60", "--seed", "7"]),
    ("stage4", 732 * 512 * 32, ["--init-from", "{prev}", *STAGE2_PPO, "--fall-reward", "-35", "--seed", "11"]),
    ("stage5", 122 * 512 * 32, ["--init-from", "{prev}", *STAGE2_PPO, "--fall-reward", "-60", "--seed", "13"]),
)
"""(run folder, environment steps, options): {grasps} is the stage-0 cache, {prev} the previous stage's bundle.
Stages 3-5 start from the shipped hold-checked grasps, which evaluation uses."""


@dataclass
class Config:
    out: Path = Path("runs/teacher_cpu")
    """Folder of the recipe's runs: grasps_unchecked/, stage1/ ... stage5/, evaluation/."""
    eval_seed: int = 3_300_000
    """First seed of the final evaluation (128 nominal episodes); keep it away from training seeds."""
    eval_episodes: int = 128
    """Episodes of the final evaluation (0 skips it)."""
    progress: bool = True
    """Progress bars."""
    dry_run: bool = False
    """Print the commands (what is left to run, and how) without running them."""

    def __post_init__(self) -> None:
        self.out = Path(self.out)
        if self.eval_episodes < 0:
            raise ValueError(f"eval_episodes must be >= 0, got {self.eval_episodes}")


def _bundle_done(run_dir: Path, steps: int) -> bool:
    """Whether ``run_dir`` holds the finished bundle of a stage of ``steps`` steps (not one saved by a stop)."""
    try:
        card = json.loads((run_dir / "bundle" / "config.json").read_text())["card"]
    except (OSError, ValueError, KeyError, TypeError):
        return False
    return "interrupted" not in card and int(card.get("steps", 0)) >= steps


def commands(cfg: Config) -> list[tuple[str, list[str]]]:
    """(what, `rotate` arguments) still to run, in order: finished steps are left out, stopped stages resume."""
    out = cfg.out
    grasps_dir = out / "grasps_unchecked"
    grasps = grasps_dir / "grasps_cup.npz"
    todo: list[tuple[str, list[str]]] = []
    if not grasps.is_file():
        todo.append(("stage 0: the grasp cache without the hold check",
                     ["grasps", "--objects", "cup", "--hold-seconds", "0", "--out", str(grasps_dir)]))
    progress = [] if cfg.progress else ["--no-progress"]
    prev = None
    for name, steps, options in STAGES:
        run_dir = out / name
        if not _bundle_done(run_dir, steps):
            last = run_dir / "checkpoints" / "last.zip"
            if last.is_file():  # a stopped stage: --resume takes the run's own options
                args = ["train-teacher", "--resume", str(last), "--total-steps", str(steps), *progress]
                todo.append((f"{name}: resume at {last}", args))
            else:
                filled = [a.format(grasps=grasps, prev=prev) for a in options]
                args = ["train-teacher", "--out", str(run_dir), *filled, "--total-steps", str(steps),
                        "--checkpoint-every", "1000000", *progress]
                todo.append((f"{name}: {steps / 1e6:.2f} M steps", args))
        prev = run_dir / "bundle"
    evaluation = out / "evaluation"
    if cfg.eval_episodes and not (evaluation / "results.md").is_file():
        todo.append(("evaluation: nominal, fresh seeds",
                     ["evaluate", "--policy", f"teacher_cpu={prev}", "--conditions", "nominal", "--episodes",
                      str(cfg.eval_episodes), "--num-envs", "32", "--seed", str(cfg.eval_seed), "--out",
                      str(evaluation), *progress]))
    return todo


def run(cfg: Config) -> int:
    from rotation import cli

    todo = commands(cfg)
    if not todo:
        print(f"teacher_cpu_recipe: every stage is done; the teacher is {cfg.out / STAGES[-1][0] / 'bundle'}")
        return 0
    for what, args in todo:
        print(f"teacher_cpu_recipe: {what}\n  rotate {shlex.join(args)}", flush=True)
        if cfg.dry_run:
            continue
        status = cli.main(args)
        if status != 0:
            print(f"teacher_cpu_recipe: stopped ({what} ended with status {status}); run the script again to "
                  "continue", file=sys.stderr)
            return status
    if not cfg.dry_run:
        print(f"teacher_cpu_recipe: done; the teacher is {cfg.out / STAGES[-1][0] / 'bundle'}"
              + (f", evaluated in {cfg.out / 'evaluation' / 'results.md'}" if cfg.eval_episodes else ""))
    return 0


def main(argv: list[str] | None = None) -> int:
    status: list[int] = []
    code = script_main(Config, lambda cfg: status.append(run(cfg)), __doc__, argv)
    return code or (status[0] if status else 0)


if __name__ == "__main__":
    sys.exit(main())
