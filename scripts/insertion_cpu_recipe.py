"""The plug-insertion benchmark on a CPU alone: demonstrations, the imitation policies of each row, and their
closed-loop evaluation on seeds no demonstration used (docs/insertion.md).

Steps (each a `rotate` command; a finished one is skipped, a stopped one resumes):

1. `rotate demos --task insertion` on the Digit 360 hand (and, with --skin-encoder, on the Xela hand);
2. `rotate train-il` per row: camera only (``camera``), camera + the frozen encoder's image tokens
   (``touch_image``), camera + all four modalities (``touch_all``), camera + all modalities trained end to end from
   random weights (``touch_e2e``, the row without pretraining) and, with --skin-encoder, camera + a frozen
   Sparsh-skin (``skin``); a stopped training continues with --resume;
3. with ``--dagger-rounds N``, per row and round r = 1..N: `rotate demos --policy` (the row's latest policy drives
   ``dagger_episodes`` episodes seeded r x 1,000,000 + e while the expert labels the states it reaches, DAgger) into
   dagger_<row>_<r>/, then `rotate train-il` on the expert's demonstrations and every round so far, il_<row>_r<r>/;
4. `rotate evaluate --task insertion` of every row's last policy over ``trials`` closed-loop trials seeded from
   ``eval_seed`` (the demonstrations' episodes are seeded ``e`` for e < episodes: no trial shares one); with DAgger
   rounds also each row's policy before them (``<row>_bc``, behaviour cloning alone) on the same trials, so that
   the table pairs what the rounds changed.

    python scripts/insertion_cpu_recipe.py --out runs/insertion_cpu
    python scripts/insertion_cpu_recipe.py --out runs/insertion_cpu --rows camera touch_all --dry-run
    python scripts/insertion_cpu_recipe.py --out runs/insertion_dagger --rows camera touch_all --dagger-rounds 2

Ship the best touch row as `insertion` and the camera row as `insertion-camera` by copying their bundle folders to
rotation/policies/<name> with a card naming this command (docs/insertion.md). Budget on 2 CPU cores: the
demonstrations take minutes; each frozen-touch training first embeds every demonstrated step once, then runs
``steps`` optimizer steps (the end-to-end row renders its windows per batch, hence its smaller batch and fewer
steps); each row's evaluation is ``trials`` episodes of up to 15 s. The recipe prints each step's wall time through
the commands' own reports; size ``steps`` to the time a session has.
"""

from __future__ import annotations

import sys
from dataclasses import dataclass
from pathlib import Path

from envs.insertion_expert import ALIGNS
from envs.plug_grip import check_grip
from envs.wrist_compliance import check_wrist
from rotation.configs import script_main
from rotation.jobs.recipe import progress_args, run_steps

ROWS = ("camera", "touch_image", "touch_all", "touch_e2e", "skin")
"""Rows of the benchmark's table, in its order."""
TOUCH = {"camera": "none", "touch_image": "image", "touch_all": "all", "touch_e2e": "e2e", "skin": "skin"}
"""Each row's `rotate train-il --touch`."""


@dataclass
class Config:
    out: Path = Path("runs/insertion_cpu")
    """Folder of the recipe: demos/, demos_xela/, il_<row>/, eval/."""
    rows: tuple[str, ...] = ("camera", "touch_image", "touch_all", "touch_e2e")
    """Rows to train and evaluate (camera, touch_image, touch_all, touch_e2e, skin)."""
    episodes: int = 100
    """Demonstrations per hand."""
    noise_m: float = 0.0
    """Demonstrations' executed-action noise, translation std (m; `rotate demos --noise-m`: the recorded actions
    stay the expert's, which then shows its corrections)."""
    noise_rad: float = 0.0
    """Demonstrations' executed-action noise, rotation std (rad; `rotate demos --noise-rad`)."""
    expert_align: str = "feel"
    """How the demonstrations' expert finds the hole (`rotate demos --expert-align`: feel or state)."""
    grip: str = "fingertips"
    """How the demonstrations' hand holds the plug (`rotate demos --grip`: fingertips or palm)."""
    wrist: str = "stiff"
    """How the arm moves the wrist (`rotate demos --wrist`: stiff or compliant; envs.wrist_compliance)."""
    encoder: str = "sparshx-tinier-sim"
    """The Sparsh-X encoder of the touch rows (a shipped name or an encoder folder)."""
    skin_encoder: str = ""
    """The Sparsh-skin encoder of the skin row (needed only with the row ``skin``)."""
    steps: int = 3000
    """Optimizer steps of each frozen-touch and camera row."""
    e2e_steps: int = 1500
    """Optimizer steps of the end-to-end row."""
    e2e_batch_size: int = 8
    """Batch of the end-to-end row (each sample renders four fingertip windows)."""
    dagger_rounds: int = 0
    """DAgger rounds per row (step 3; 0: the policies learn from the expert's demonstrations alone)."""
    dagger_episodes: int = 100
    """Episodes each DAgger round records per row."""
    trials: int = 100
    """Closed-loop trials per row."""
    eval_seed: int = 500_000
    """Seed of the first trial (trial j: eval_seed + j)."""
    progress: bool = True
    dry_run: bool = False
    """Print the commands without running them."""

    def __post_init__(self) -> None:
        self.out = Path(self.out)
        self.rows = tuple(self.rows)
        bad = [r for r in self.rows if r not in ROWS]
        if bad or not self.rows or len(set(self.rows)) != len(self.rows):
            raise ValueError(f"rows: give distinct rows of {', '.join(ROWS)}, got {list(self.rows)}")
        if self.expert_align not in ALIGNS:
            raise ValueError(f"expert_align must be feel or state, got {self.expert_align!r}")
        check_grip("grip", self.grip)
        check_wrist("wrist", self.wrist)
        if "skin" in self.rows and not self.skin_encoder:
            raise ValueError("rows: the skin row needs --skin-encoder (a pretrained Sparsh-skin: "
                             "scripts/skin_cpu_recipe.py)")
        for name in ("episodes", "steps", "e2e_steps", "e2e_batch_size", "trials", "dagger_episodes"):
            if int(getattr(self, name)) < 1:
                raise ValueError(f"{name} must be >= 1, got {getattr(self, name)}")
        if not 0 <= int(self.dagger_rounds) <= 20:
            raise ValueError(f"dagger_rounds must be in [0, 20], got {self.dagger_rounds}")
        if self.eval_seed < self.episodes:
            raise ValueError(f"eval_seed must be >= episodes ({self.episodes}): trials would repeat demonstrated "
                             f"episodes, got {self.eval_seed}")


def _run_dir(cfg: Config, row: str, round_: int) -> Path:
    """The training run of a row after DAgger round ``round_`` (0: on the expert's demonstrations alone)."""
    return cfg.out / (f"il_{row}" if round_ == 0 else f"il_{row}_r{round_}")


def _train(cfg: Config, row: str, round_: int = 0) -> list[str]:
    run = _run_dir(cfg, row, round_)
    demos = [cfg.out / ("demos_xela" if row == "skin" else "demos")]
    demos += [cfg.out / f"dagger_{row}_{r}" for r in range(1, round_ + 1)]
    args = ["train-il", "--demos", *map(str, demos), "--touch", TOUCH[row], "--out", str(run),
            *progress_args(cfg.progress)]
    if row != "camera":
        args += ["--encoder", cfg.skin_encoder if row == "skin" else cfg.encoder]
    if row == "touch_e2e":
        args += ["--steps", str(cfg.e2e_steps), "--batch-size", str(cfg.e2e_batch_size)]
    else:
        args += ["--steps", str(cfg.steps)]
    return [*args, "--resume"] if (run / "checkpoint.pt").is_file() else args


def commands(cfg: Config) -> list[tuple[str, list[str]]]:
    """(what, command) still to run, in order (demonstrations are always listed: `rotate demos` keeps what is
    complete and records the rest)."""
    out, todo, progress = cfg.out, [], progress_args(cfg.progress)
    expert = ["--expert-align", cfg.expert_align, "--grip", cfg.grip,
              "--wrist", cfg.wrist]  # the demonstrations' and every round's
    noise = ["--noise-m", str(cfg.noise_m), "--noise-rad", str(cfg.noise_rad)] if cfg.noise_m or cfg.noise_rad else []
    demo_flags = [*noise, *expert]
    todo.append(("demonstrations (Digit 360 hand)", ["demos", "--task", "insertion", "--episodes", str(cfg.episodes),
                                                    "--seed", "0", *demo_flags, "--out", str(out / "demos"),
                                                    *progress]))
    if "skin" in cfg.rows:
        todo.append(("demonstrations (Xela hand)", ["demos", "--task", "insertion", "--hand", "xela_v4",
                                                    "--episodes", str(cfg.episodes), "--seed", "0", *demo_flags,
                                                    "--out", str(out / "demos_xela"), *progress]))
    for row in cfg.rows:
        if not (out / f"il_{row}" / "bundle").is_dir():
            todo.append((f"train {row}", _train(cfg, row)))
        for r in range(1, cfg.dagger_rounds + 1):
            hand = ["--hand", "xela_v4"] if row == "skin" else []
            todo.append((f"DAgger round {r} of {row}", [
                "demos", "--task", "insertion", *hand, "--policy", str(_run_dir(cfg, row, r - 1) / "bundle"),
                "--episodes", str(cfg.dagger_episodes), "--seed", str(r), *expert, "--out",
                str(out / f"dagger_{row}_{r}"), *progress]))
            if not (_run_dir(cfg, row, r) / "bundle").is_dir():
                todo.append((f"train {row} after round {r}", _train(cfg, row, r)))
    if not (out / "eval" / "results.json").is_file():
        runs = [(row, _run_dir(cfg, row, cfg.dagger_rounds)) for row in cfg.rows]
        if cfg.dagger_rounds:  # the same rows before DAgger, on the same trials: what the rounds changed, paired
            runs += [(f"{row}_bc", _run_dir(cfg, row, 0)) for row in cfg.rows]
        policies = [a for name, run in runs for a in ("--policy", f"{name}={run / 'bundle'}")]
        todo.append((f"evaluate {len(runs)} policies over {cfg.trials} trials",
                     ["evaluate", "--task", "insertion", *policies, "--episodes", str(cfg.trials), "--seed",
                      str(cfg.eval_seed), "--out", str(out / "eval"), *progress]))
    return todo


def run(cfg: Config) -> int:
    status = run_steps("insertion_cpu_recipe", commands(cfg), cfg.dry_run)
    if status == 0 and not cfg.dry_run:
        print(f"insertion_cpu_recipe: done; the table is {cfg.out / 'eval' / 'results.md'}")
    return status


def main(argv: list[str] | None = None) -> int:
    return script_main(Config, run, __doc__, argv)


if __name__ == "__main__":
    sys.exit(main())
