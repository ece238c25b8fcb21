"""A pretrained Sparsh-skin on a CPU alone: collect simulated skin sessions on the Xela hand with the vendor's
kinematics, pretrain a smaller skin encoder on them, export it, and probe it against end to end.

Steps (each a `rotate` command or the export; a finished one is skipped, a stopped one resumes):

1. two collections of scripted cup play on the ``xela_v4`` hand (up to 20 s each): the pretraining sessions and, on
   other seeds, the probe's (labels: pad forces, object pose);
2. `rotate pretrain --encoder skin` (``size``: tinier, 96 wide, 8 layers), checkpoints every ``checkpoint_every``
   steps, resumed with --resume;
3. `scripts/export_encoder.py` into OUT/encoder (ship it with `--out rotation/tactile/pretrained/sparshskin-tiny-sim`
   and a card from OUT/probe's figures);
4. `rotate probe --encoder skin` on the probe's sessions: pretrained against end to end at 10%, 33% and 100% of
   the labels (force, pose).

    python scripts/skin_cpu_recipe.py --out runs/skin_cpu
    python scripts/skin_cpu_recipe.py --out runs/skin_cpu --dry-run        # the commands, run nothing

Budget on 2 CPU cores: the collections take 15 s (96 and 40 sessions of scripted cup play: an episode ends when the
cup falls, at a median of 3.8 s; 23 of 96 play the whole 20 s); pretraining the tinier encoder at batch 16 is the
cost, about 1.2 s a step (8,000 steps: 2.7 hours, resumable); the probe about 30 minutes. The joystick probe needs
the joystick fixture, which is built for the first Xela hand ('xela'): collect its sessions there (`rotate collect
--skin --task joystick`) and probe them separately. On a GPU machine use docs/pretraining.md's Sparsh-skin recipe.
"""

from __future__ import annotations

import sys
from dataclasses import dataclass
from pathlib import Path

from rotation.configs import script_main
from rotation.jobs.recipe import pretrained, progress_args, report_complete, run_steps

PROBE_SEED = 300
"""Seed of the probe's sessions (the pretraining collection uses 0)."""


@dataclass
class Config:
    out: Path = Path("runs/skin_cpu")
    """Folder of the recipe: sessions/, probe_sessions/, pretrain/, encoder/, probe/."""
    episodes: int = 96
    """Pretraining sessions (scripted cup play, up to 20 s each: a session ends when the cup falls)."""
    probe_episodes: int = 40
    """The probe's sessions (a fifth held out for testing)."""
    size: str = "tinier"
    """Encoder size (rotate pretrain --size)."""
    steps: int = 8000
    """Pretraining steps (about 1.2 s each on 2 CPU cores at batch 16: 2.7 hours). A first run of 2,000 steps left the
    DINO loss at uniform (ln 1024 = 6.92) after 900 steps, the teacher's entropy at 6.85 of 6.93: no learning yet;
    the Sparsh-X encoder's run broke its plateau a quarter of the way through 4,000 steps."""
    batch_size: int = 16
    checkpoint_every: int = 100
    lr: float = 3e-4
    device: str = "cpu"
    num_workers: int = 1
    probe_steps: int = 600
    """Optimizer steps per probe."""
    progress: bool = True
    dry_run: bool = False
    """Print the commands without running them."""

    def __post_init__(self) -> None:
        self.out = Path(self.out)
        for name in ("episodes", "probe_episodes", "steps", "batch_size", "checkpoint_every", "probe_steps"):
            if int(getattr(self, name)) < 1:
                raise ValueError(f"{name} must be >= 1, got {getattr(self, name)}")


def commands(cfg: Config) -> list[tuple[str, list[str]]]:
    """(what, command) still to run, in order (collections are always listed: `rotate collect` keeps what is
    complete)."""
    out, todo, progress = cfg.out, [], progress_args(cfg.progress)
    common = ["--skin", "--hand", "xela_v4", "--policy", "play", "--num-envs", "8", *progress]
    todo.append(("collect the pretraining sessions", ["collect", *common, "--episodes", str(cfg.episodes), "--seed",
                                                      "0", "--out", str(out / "sessions")]))
    todo.append(("collect the probe's sessions", ["collect", *common, "--episodes", str(cfg.probe_episodes),
                                                  "--seed", str(PROBE_SEED), "--out", str(out / "probe_sessions")]))
    pretrain = out / "pretrain"
    if not pretrained(pretrain, cfg.steps):
        resume = ["--resume"] if any(pretrain.glob("ckpt_*.safetensors")) else []
        todo.append((f"pretrain: {cfg.steps} steps of {cfg.batch_size} windows{' (resumed)' if resume else ''}",
                     ["pretrain", "--encoder", "skin", "--sessions", str(out / "sessions"), "--out", str(pretrain),
                      "--size", cfg.size, "--steps", str(cfg.steps), "--batch-size", str(cfg.batch_size), "--lr",
                      str(cfg.lr), "--weight-decay", "0.04", "--weight-decay-end", "0.4", "--warmup-fraction", "0.1",
                      "--checkpoint-every", str(cfg.checkpoint_every), "--keep-checkpoints", "2", "--log-every", "25",
                      "--num-workers", str(cfg.num_workers), "--device", cfg.device, *resume,
                      *progress]))
    encoder = out / "encoder" / "encoder.safetensors"
    if not encoder.is_file() or (pretrain / "encoder.safetensors").is_file() and \
            (pretrain / "encoder.safetensors").stat().st_mtime > encoder.stat().st_mtime:
        todo.append(("export the encoder", ["python", str(Path(__file__).resolve().parent / "export_encoder.py"),
                                            "--checkpoint", str(pretrain), "--out", str(out / "encoder")]))
    if not report_complete(out / "probe"):
        todo.append(("probe: pretrained against end to end", [
            "probe", "--encoder", "skin", "--checkpoint", str(out / "encoder"), "--sessions",
            str(out / "probe_sessions"), "--steps", str(cfg.probe_steps), "--num-workers", str(cfg.num_workers),
            "--device", cfg.device, "--out", str(out / "probe"), *progress]))
    return todo


def run(cfg: Config) -> int:
    status = run_steps("skin_cpu_recipe", commands(cfg), cfg.dry_run)
    if status == 0 and not cfg.dry_run:
        print(f"skin_cpu_recipe: done; the encoder is {cfg.out / 'encoder'}, the probe {cfg.out / 'probe'}")
    return status


def main(argv: list[str] | None = None) -> int:
    return script_main(Config, run, __doc__, argv)


if __name__ == "__main__":
    sys.exit(main())
