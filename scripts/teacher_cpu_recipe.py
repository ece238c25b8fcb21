"""The teacher from random weights on a CPU alone, then its student: five `rotate train-teacher` stages (seven on a
hand other than the first), then `rotate train-student` and `rotate finetune-student`
(experiments/teacher_cpu_recipe).

It trains on the default hand (envs.constants.DEFAULT_HAND) unless --hand names another. The figures below are the
first hand's ('digit360', `--hand digit360`), whose shipped teacher's first stage ran on a GPU machine. This recipe
needs none: on 2 CPU cores it took about 2.8 h (37.1 M environment steps) to a teacher that meets issue 8's targets
on fresh seeds (net rate >= 0.30 rad/s, ttf >= 0.90, upright >= 0.90 at nominal randomization), and 39 min more to a
student from it that meets the student's (net rate >= 80% of the teacher's on the same episodes, ttf >= 0.85,
upright >= 0.85). Any other hand (the vendor-kinematics 'digit360_v4') adds stages 4b and 6 and its own hold-checked
grasps. The stages:

0. the grasp cache from before the hold check (`rotate grasps --hold-seconds 0`), a third of whose grasps cannot
   hold the cup by themselves: from grasps that slip, keeping the cup needs the fingers to move it, and stage 1
   learns a gait that turns it (from grasps that hold, standing still is a strong local optimum);
1. 11.1 M steps from random weights, 2048 envs x 16 steps, on those grasps (the shipped teacher's GPU stage);
2. 6.9 M steps from stage 1's bundle, 512 envs x 32 steps, with the backward clip at 5 rad/s (the default 0.5 lets
   the policy learn a forward-then-snap-back ratchet);
3. 5.0 M steps on the shipped, hold-checked grasps with a fall costing 60: the policy learns to hold the cup
   (ttf 0.98) and turns it slowly (0.22 rad/s);
4. 12.0 M steps with a fall costing 35: it turns the cup faster again (0.5 rad/s) and keeps holding it;
4b. on a hand other than the first (the vendor-kinematics 'digit360_v4'): 6.0 M steps more at a fall cost of 35
   with the rotate term capped at 1.0 rad/s instead of 0.5 and half the pose penalty (SPEED_STAGE says why);
5. 2.0 M steps with a fall costing 60 again (on another hand, then 6: 8.0 M more at 60 with stage 4b's reward for
   speed: HOLD_STAGE says why): it holds the cup longer (ttf 0.91 -> 0.95) at the same rate;
6. the student (folder student/): 6.0 M steps distilling stage 5's bundle, 64 envs (`rotate train-student`: phi
   learns the teacher's latent from 30 steps of proprioception); it turns the cup as fast as the teacher but drops
   it more (ttf 0.78-0.79);
7. its RL fine-tune (folder student_rl/): 4.0 M steps of PPO on the student's actor, phi frozen, a fall costing 60
   (`rotate finetune-student`, the shipped student's last stage): ttf 0.86-0.90 at 91-95% of the teacher's rate.

Then the teacher and the final student are evaluated side by side at nominal randomization on fresh seeds (the same
episodes for both, in evaluation_student/). The whole recipe took about 3.5 h on 2 cores: the teacher 2.83 h, the
distillation 15.7 min, the RL fine-tune 23.2 min. --teacher-only stops after stage 5 and evaluates the teacher
alone (in evaluation/); --student-from STAGE distills a teacher stage other than the last (on the
vendor-kinematics hand, the one experiments/teacher_v4's rule picks). Each stage writes its own run folder under
--out (checkpoints, curves, TensorBoard logs, bundle). Running the script again continues: a finished stage is
skipped, a stopped one resumes from its last checkpoint. Ctrl-C stops the running stage with a checkpoint.

    python scripts/teacher_cpu_recipe.py --out runs/teacher_cpu --hand digit360                 # about 3.5 h
    python scripts/teacher_cpu_recipe.py --out runs/teacher_cpu --hand digit360 --teacher-only  # about 2.8 h
    python scripts/teacher_cpu_recipe.py --out runs/teacher_v4 --dry-run   # the default hand's commands, run nothing
    tensorboard --logdir runs/teacher_cpu

Stage lengths are whole rollouts; a reproduction is not bit for bit the documented one (MuJoCo and torch differ
across CPUs in the last bits, and the documented stage 2 was resumed once, which reseeds its episodes), so judge
it by its evaluation, as the report does.
"""

from __future__ import annotations

import json
import sys
from dataclasses import dataclass
from pathlib import Path

from envs.constants import DEFAULT_HAND
from envs.grasp_cache import default_cache_path
from rotation.configs import script_main
from rotation.jobs.recipe import progress_args, run_steps

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

SPEED_STAGE = ("stage4b", 366 * 512 * 32, ["--init-from", "{prev}", *STAGE2_PPO, "--fall-reward", "-35",
                                           "--rotate-clip", "1.0", "--pose-diff-reward", "-0.05", "--seed", "17"])
"""A stage between 4 and 5 on a hand other than the first ('digit360'): 6.0 M steps that pay a faster gait (the
rotate term's cap at 1.0 rad/s instead of 0.5) and charge half as much for leaving the grasp. On the vendor-kinematics
hand stage 4 ended at about 0.34 rad/s (training curves), its pose penalty per step larger than the first hand's at
0.63 rad/s (-0.11 against -0.08): its roll joints move the fingers further for the same turn. Measured on 128 fresh
episodes (experiments/teacher_v4): 0.384 rad/s net against stage 4's 0.322, ttf 0.826 against 0.883."""

HOLD_STAGE = ("stage6", 488 * 512 * 32, ["--init-from", "{prev}", *STAGE2_PPO, "--fall-reward", "-60",
                                          "--rotate-clip", "1.0", "--pose-diff-reward", "-0.05", "--seed", "19"])
"""After stage 5 on a hand other than the first: 8.0 M steps at a fall cost of 60 with stage 4b's reward for speed.
On the vendor-kinematics hand stage 5 (2.0 M steps at 60 with the usual reward) lost stage 4b's speed (0.314 rad/s
net) without holding the cup longer (ttf 0.852; 128 fresh episodes, experiments/teacher_v4). Stage 6 read 0.444 rad/s
net, ttf 0.917, upright 0.979 on 128 fresh episodes, the teacher that ships by that record's rule."""

STUDENT_STAGES: tuple[tuple[str, str, int, list[str]], ...] = (
    ("student", "train-student", 6_000_000,
     ["--teacher", "{prev}", "--out", "{run}", "--total-steps", "{steps}", "--num-envs", "64", "--seed", "0"]),
    ("student_rl", "finetune-student", 4_000_000,
     ["--student", "{prev}", "--out", "{run}", "--total-steps", "{steps}", "--checkpoint-every", "500000", "--seed",
      "12", "--no-overlap", "--fall-reward", "-60"]),
)
"""(run folder, `rotate` job, environment steps, options) of the student's stages, the report's commands: {prev} is
the previous stage's bundle (stage 5's for the distillation), {run} the stage's folder, {steps} its length. Both
train in the default env (the shipped hold-checked grasps), as stage 5 did."""

DISTILL_CHECKPOINTS = "ckpt_*.pt"
"""train-student's checkpoints, in its run folder (rotation.train.student_config.CHECKPOINT_GLOB)."""


@dataclass
class Config:
    out: Path = Path("runs/teacher_cpu")
    """Folder of the recipe's runs: grasps_unchecked/, stage1/ ... stage5/, student/, student_rl/ and
    evaluation_student/ (evaluation/ with --teacher-only), evaluation_contact/."""
    eval_seed: int = 3_300_000
    """First seed of the final evaluation (128 nominal episodes); keep it away from training seeds."""
    eval_episodes: int = 128
    """Episodes of the final evaluation, per policy (0 skips it)."""
    contact_check: bool = True
    """Evaluate the final policies again under a contact model their hand never trains on (evaluation_contact/):
    pyramidal cones, impratio 3, no noslip (the first simulation's) for a hand trained on elliptic cones, else
    elliptic, impratio 10, noslip 10; issue 72's target is >= 80% of the nominal rotation rate there."""
    teacher_only: bool = False
    """Stop after the teacher's stages (no student) and evaluate the teacher alone, in evaluation/."""
    student_from: str = ""
    """The teacher stage (a run folder's name: stage4, stage4b, stage5, ...) the student distills from and the final
    evaluation takes as the teacher; empty: the last stage. A student folder distilled from another teacher is
    refused rather than resumed."""
    progress: bool = True
    """Progress bars."""
    dry_run: bool = False
    """Print the commands (what is left to run, and how) without running them."""
    hand: str = DEFAULT_HAND
    """Hand variant (envs.scene.HANDS) the recipe trains on, the default hand unless told: its grasps and its
    physics (envs.physics.HAND_PHYSICS). The first hand, 'digit360', trains stages 1-5 with its shipped hold-checked
    grasps for stages 3 on; any other ('digit360_v4': the vendor's kinematics on the hardware's physics) adds stages
    4b and 6 and generates its own hold-checked grasps. Every teacher stage and grasp cache is given --hand; the
    student stages and the evaluation take the hand from the teacher's bundle."""

    def __post_init__(self) -> None:
        from envs.scene import HANDS

        if self.hand not in HANDS:
            raise ValueError(f"hand: unknown hand {self.hand!r}; hands: {', '.join(HANDS)}")
        self.out = Path(self.out)
        if self.eval_episodes < 0:
            raise ValueError(f"eval_episodes must be >= 0, got {self.eval_episodes}")
        names = [name for name, _, _ in _teacher_stages(self.hand)]
        if self.student_from and self.student_from not in names:
            raise ValueError(f"student_from: one of the {self.hand} recipe's stages ({', '.join(names)}), got "
                             f"{self.student_from!r}")


def _card(run_dir: Path) -> dict | None:
    """The card of the bundle in ``run_dir`` (None without a readable one)."""
    try:
        card = json.loads((run_dir / "bundle" / "config.json").read_text())["card"]
    except (OSError, ValueError, KeyError, TypeError):
        return None
    return card if isinstance(card, dict) else None


def _bundle_done(run_dir: Path, steps: int) -> bool:
    """Whether ``run_dir`` holds the finished bundle of a train-teacher or finetune-student stage of ``steps`` steps
    (not one saved by a stop, whose card says "interrupted")."""
    card = _card(run_dir)
    try:
        return card is not None and "interrupted" not in card and int(card.get("steps", 0)) >= steps
    except (TypeError, ValueError):
        return False


def _distillation_done(run_dir: Path, steps: int) -> bool:
    """Whether ``run_dir`` holds the finished bundle of a train-student stage of ``steps`` steps. Its card counts
    "env_steps" and holds the run's config; a bundle saved by a stop says "interrupted". One that does not was
    written only once the run reached its config's total_steps, which is what counts when a resume found nothing
    left to train (it logs no point, so its card says env_steps 0)."""
    card = _card(run_dir)
    if card is None or "interrupted" in card:
        return False
    try:
        config = card.get("config") or {}
        return max(int(card.get("env_steps") or 0), int(config.get("total_steps") or 0)) >= steps
    except (AttributeError, TypeError, ValueError):
        return False


def _stage(name: str, job: str, steps: int, options: list[str], run_dir: Path, progress: list[str], **fields: object
           ) -> tuple[str, list[str]] | None:
    """(what, `rotate` arguments) of a training stage still to run, None when it is finished; a stopped one resumes
    (--resume takes the run's own options, the bundle or grasps it started from included). ``fields`` fill the
    options' placeholders besides {run} and {steps}."""
    if job == "train-student":
        if _distillation_done(run_dir, steps):
            return None
        ckpts = sorted(run_dir.glob(DISTILL_CHECKPOINTS))
        if ckpts and (run_dir / "config.json").is_file():  # resumes from its latest intact checkpoint
            return (f"{name}: resume at {ckpts[-1]}",
                    [job, "--out", str(run_dir), "--resume", "--total-steps", str(steps), *progress])
    else:  # train-teacher and finetune-student keep checkpoints/last.zip and a card counting "steps"
        if _bundle_done(run_dir, steps):
            return None
        last = run_dir / "checkpoints" / "last.zip"
        if last.is_file():
            return f"{name}: resume at {last}", [job, "--resume", str(last), "--total-steps", str(steps), *progress]
    filled = [a.format(run=run_dir, steps=steps, **fields) for a in options]
    return f"{name}: {steps / 1e6:.2f} M steps", [job, *filled, *progress]


def _evaluation(cfg: Config) -> tuple[Path, dict[str, Path]]:
    """The final evaluation's folder and its policies (label -> bundle)."""
    policies = {"teacher_cpu": _teacher_run(cfg) / "bundle"}
    if cfg.teacher_only:
        return cfg.out / "evaluation", policies
    return cfg.out / "evaluation_student", policies | {"student_cpu": cfg.out / STUDENT_STAGES[-1][0] / "bundle"}


def commands(cfg: Config) -> list[tuple[str, list[str]]]:
    """(what, `rotate` arguments) still to run, in order: finished steps are left out, stopped stages resume."""
    out = cfg.out
    grasps_dir = out / "grasps_unchecked"
    grasps = grasps_dir / default_cache_path("cup", cfg.hand).name
    hand = ["--hand", cfg.hand]  # always: the jobs' default hand need not be the recipe's
    checked = _checked_cache(cfg)
    todo: list[tuple[str, list[str]]] = []
    if not grasps.is_file():
        todo.append(("stage 0: the grasp cache without the hold check",
                     ["grasps", "--objects", "cup", "--hold-seconds", "0", "--out", str(grasps_dir), *hand]))
    progress = progress_args(cfg.progress)
    prev = None
    # stages 3 on train (and the evaluation runs) on the hold-checked grasps: the shipped ones of the first hand,
    # the recipe's own for another hand (generated before stage 3 needs them)
    on_checked = {"train-teacher": ["--grasp-cache", str(checked)], "train-student": ["--env.grasp-cache",
                  str(checked)], "finetune-student": ["--grasp-cache", str(checked)]} if checked else {}
    stages = [(name, "train-teacher", steps, ["--out", "{run}", *options, "--total-steps", "{steps}",
                                               "--checkpoint-every", "1000000", *hand])
              for name, steps, options in _teacher_stages(cfg.hand)]
    for name, job, steps, options in stages + ([] if cfg.teacher_only else list(STUDENT_STAGES)):
        run_dir = out / name
        if job == "train-student":
            prev = _teacher_run(cfg) / "bundle"
            _check_student_teacher(run_dir, prev)
        if checked and "{grasps}" not in options:
            options = [*options, *on_checked[job]]
            if not checked.is_file() and not any(what.startswith("grasps checked") for what, _ in todo):
                todo.append((f"grasps checked: the {cfg.hand} hand's hold-checked grasp cache",
                             ["grasps", "--objects", "cup", "--out", str(checked.parent), *hand]))
        if (stage := _stage(name, job, steps, options, run_dir, progress, grasps=grasps, prev=prev)) is not None:
            todo.append(stage)
        prev = run_dir / "bundle"
    evaluation, policies = _evaluation(cfg)
    if cfg.eval_episodes and not (evaluation / "results.md").is_file():
        todo.append((f"evaluation: {' and '.join(policies)}, nominal, fresh seeds",
                     ["evaluate", *(a for label, path in policies.items() for a in ("--policy", f"{label}={path}")),
                      "--conditions", "nominal", "--episodes", str(cfg.eval_episodes), "--num-envs", "32", "--seed",
                      str(cfg.eval_seed), "--out", str(evaluation), *progress,
                      *(["--grasp-cache", str(checked)] if checked else [])]))
    if cfg.eval_episodes and cfg.contact_check and not (out / "evaluation_contact" / "results.md").is_file():
        other = _unseen_contact(cfg.hand)
        todo.append((f"evaluation: {' and '.join(policies)}, nominal, fresh seeds, a contact model never trained on",
                     ["evaluate", *(a for label, path in policies.items() for a in ("--policy", f"{label}={path}")),
                      "--conditions", "nominal", "--episodes", str(cfg.eval_episodes), "--num-envs", "32", "--seed",
                      str(cfg.eval_seed), "--out", str(out / "evaluation_contact"), *progress, *other,
                      *(["--grasp-cache", str(checked)] if checked else [])]))
    return todo


def _teacher_stages(hand: str) -> list[tuple[str, int, list[str]]]:
    """The teacher's stages on ``hand``: STAGES, with SPEED_STAGE before stage 5 and HOLD_STAGE after it on a hand
    other than the first."""
    if hand == "digit360":
        return list(STAGES)
    return [*STAGES[:4], SPEED_STAGE, STAGES[4], HOLD_STAGE]


def _teacher_run(cfg: Config) -> Path:
    """The run folder of the teacher the student distills from: --student-from, else the last stage."""
    return cfg.out / (cfg.student_from or _teacher_stages(cfg.hand)[-1][0])


def _check_student_teacher(run_dir: Path, teacher: Path) -> None:
    """Refuse to resume or accept a distillation in ``run_dir`` started from a teacher other than ``teacher``."""
    try:
        started = json.loads((run_dir / "config.json").read_text()).get("teacher")
    except (OSError, ValueError, AttributeError):
        return  # nothing started there yet
    if started is not None and Path(started).resolve() != teacher.resolve():
        raise ValueError(f"{run_dir} distills {started}, not {teacher}; move that folder aside to distill {teacher}")


def _unseen_contact(hand: str) -> list[str]:
    """`rotate evaluate` options of a contact model ``hand``'s training never uses (see Config.contact_check)."""
    from envs.physics import hand_physics

    if hand_physics(hand).contact.cone == "elliptic":
        return ["--contact-cone", "pyramidal", "--contact-impratio", "3", "--contact-noslip-iterations", "0"]
    return ["--contact-cone", "elliptic", "--contact-impratio", "10", "--contact-noslip-iterations", "10"]


def _checked_cache(cfg: Config) -> Path | None:
    """The recipe's own hold-checked grasp cache on a hand other than the first ('digit360', whose shipped cup
    cache is the hold-checked one), None on that hand."""
    if cfg.hand == "digit360":
        return None
    return cfg.out / "grasps_checked" / default_cache_path("cup", cfg.hand).name


def _result(cfg: Config) -> str:
    """What the recipe made: the teacher's bundle, and the student's unless --teacher-only."""
    _, policies = _evaluation(cfg)
    return "; ".join(f"the {'teacher' if label == 'teacher_cpu' else 'student'} is {path}"
                     for label, path in policies.items())


def run(cfg: Config) -> int:
    todo = commands(cfg)
    if not todo:
        print(f"teacher_cpu_recipe: every stage is done; {_result(cfg)}")
        return 0
    status = run_steps("teacher_cpu_recipe", todo, cfg.dry_run)
    if status != 0:
        return status
    if not cfg.dry_run:
        print(f"teacher_cpu_recipe: done; {_result(cfg)}"
              + (f"; evaluated in {_evaluation(cfg)[0] / 'results.md'}" if cfg.eval_episodes else "")
              + (f" and {cfg.out / 'evaluation_contact' / 'results.md'}" if cfg.eval_episodes and cfg.contact_check
                 else ""))
    return 0


def main(argv: list[str] | None = None) -> int:
    return script_main(Config, run, __doc__, argv)


if __name__ == "__main__":
    sys.exit(main())
