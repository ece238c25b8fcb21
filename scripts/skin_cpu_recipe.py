"""A pretrained Sparsh-skin on a CPU alone: collect simulated skin sessions on the Xela hand with the vendor's
kinematics, pretrain a smaller skin encoder on them, export it, probe it against end to end, and compute the figure
its model card states for the shipped weights to reproduce.

Steps (each a `rotate` command or the export; a finished one is skipped, a stopped one resumes):

1. two collections of scripted cup play on the ``xela_v4`` hand (up to 20 s each): the pretraining sessions and, on
   other seeds, the probe's (labels: pad forces, object pose);
2. `rotate pretrain --encoder skin` (``size``: tinier, 96 wide, 8 layers), checkpoints every ``checkpoint_every``
   steps, resumed with --resume;
3. `scripts/export_encoder.py` into OUT/encoder (weights in float16; ship it with `--out
   rotation/tactile/pretrained/sparshskin-tiny-sim` and a card from OUT/probe's figures);
4. `rotate probe --encoder skin` on the probe's sessions: pretrained (frozen) against end to end at 10%, 33% and
   100% of the labels (force, pose), both variants with the same steps, batch and learning rate;
5. the card check (:func:`card_commands`): a small deterministic split (8 sessions on seed 500) and a frozen force
   probe of 200 steps on it, into OUT/card_check; its figures go into the shipped folder's ``card_check.json``, and
   tests/scripts/test_skin_cpu_recipe.py holds the shipped weights to them.

    python scripts/skin_cpu_recipe.py --out runs/skin_cpu
    python scripts/skin_cpu_recipe.py --out runs/skin_cpu --dry-run        # the commands, run nothing

Budget on 2 CPU cores: the collections take 15 s (96 and 40 sessions of scripted cup play: an episode ends when the
cup falls, at a median of 3.8 s; 23 of 96 play the whole 20 s); pretraining the tinier encoder at batch 16 is the
cost, about 1.3 s a step alone (4,000 steps: 1.5 hours; the shipped run took 125 min beside other jobs; resumable);
the probe (20 min) is dominated by the end-to-end pose probe, whose every sample is ``probe_sequence_windows``
windows through a trained encoder (hence, on a CPU, batch 8, 3 windows of history and 250 steps); the card check
takes 30 s. The joystick probe needs the joystick fixture, which is built for the first Xela hand ('xela'): collect
its sessions there (`rotate collect --skin --task joystick`) and probe them separately. On a GPU machine use
docs/pretraining.md's Sparsh-skin recipe.
"""

from __future__ import annotations

import json
import shlex
import shutil
import sys
from dataclasses import dataclass
from pathlib import Path

from rotation.configs import script_main
from rotation.jobs.recipe import pretrained, progress_args, report_complete, run_steps

PROBE_SEED = 300
"""Seed of the probe's sessions (the pretraining collection uses 0)."""
CARD_SEED = 500
"""Seed of the card check's sessions."""
CARD_FILE = "card_check.json"
"""The card check's figures, beside a shipped encoder's weights."""


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
    steps: int = 4000
    """Pretraining steps (about 1.3 s each on 2 CPU cores at batch 16: 1.5 hours). The warm-up (a tenth), the teacher
    temperature's rise and the cosine decay scale with it. A first run of 2,000 steps left the DINO loss at uniform
    (ln 1024 = 6.92) after 900 steps, the teacher's entropy at 6.85 of 6.93: no learning yet; the Sparsh-X encoder's
    run broke its plateau a quarter of the way through 4,000 steps."""
    batch_size: int = 16
    checkpoint_every: int = 100
    lr: float = 3e-4
    device: str = "cpu"
    num_workers: int = 1
    probe_steps: int = 250
    """Optimizer steps per probe (the same for both variants and every budget). The cost is the end-to-end pose
    probe: on 2 cores one of its steps (8 samples x 3 windows read from the sessions and through the encoder, forward
    and backward) takes about 0.7 s (a frozen one 0.25 s), and its evaluation passes the test sessions' sequences
    through the encoder; the shipped run's probe took 20 min."""
    probe_batch_size: int = 8
    """Samples per probe step (a pose sample is ``probe_sequence_windows`` windows)."""
    probe_sequence_windows: int = 3
    """Windows of 0.1 s per pose sample (rotate probe --sequence-windows; the paper's decoders see longer)."""
    probe_lr: float = 1e-3
    """Adam learning rate of the probes and of the end-to-end encoder (the papers' 1e-4 runs for many epochs; the
    touch benchmarks' frozen probes at 1e-4 x 1,000 steps were undertrained, at 1e-3 x 10,000 they were not)."""
    progress: bool = True
    dry_run: bool = False
    """Print the commands without running them."""
    ship: Path | None = None
    """After the steps, copy OUT/encoder's weights into this folder (e.g.
    rotation/tactile/pretrained/sparshskin-tiny-sim) with the card check's figures (card_check.json); its
    MODEL_CARD.md is written by hand from OUT/probe. The folder's name is the encoder's shipped name."""

    def __post_init__(self) -> None:
        self.out = Path(self.out)
        self.ship = None if self.ship is None else Path(self.ship)
        for name in ("episodes", "probe_episodes", "steps", "batch_size", "checkpoint_every", "probe_steps",
                     "probe_batch_size", "probe_sequence_windows"):
            if int(getattr(self, name)) < 1:
                raise ValueError(f"{name} must be >= 1, got {getattr(self, name)}")
        if not 0 < float(self.probe_lr) <= 1:
            raise ValueError(f"probe_lr must be in (0, 1], got {self.probe_lr}")


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
            str(out / "probe_sessions"), "--steps", str(cfg.probe_steps), "--batch-size", str(cfg.probe_batch_size),
            "--sequence-windows", str(cfg.probe_sequence_windows), "--lr", str(cfg.probe_lr), "--num-workers",
            str(cfg.num_workers), "--device", cfg.device, "--out", str(out / "probe"), *progress]))
    if not report_complete(out / "card_check"):
        todo += card_commands(str(out / "encoder"), out, cfg.progress)
    return todo


def card_commands(encoder: str, out: Path, progress: bool = False) -> list[tuple[str, list[str]]]:
    """The card check of a skin encoder (a path or a shipped name): 8 sessions of cup play on seed
    :data:`CARD_SEED` into OUT/card_sessions, then a frozen force probe of 200 steps on one thread (seed 0, all the
    training labels) into OUT/card_check. Deterministic on one machine; across machines the simulation's float
    differences grow into different trajectories, and the figures moved up to 6.2% on three float variants
    (tests/scripts/test_skin_cpu_recipe.py allows 15%)."""
    out = Path(out)
    return [("card check: its sessions", ["collect", "--skin", "--hand", "xela_v4", "--policy", "play", "--num-envs",
                                          "8", *progress_args(progress), "--episodes", "8", "--seed", str(CARD_SEED),
                                          "--out", str(out / "card_sessions")]),
            ("card check: a frozen force probe", [
                "probe", "--encoder", "skin", "--checkpoint", encoder, "--sessions", str(out / "card_sessions"),
                "--tasks", "force", "--variants", "pretrained", "--budgets", "1.0", "--steps", "200", "--batch-size",
                "16", "--lr", "1e-3", "--seed", "0", "--num-workers", "0", "--torch-threads", "1", "--device", "cpu",
                "--out", str(out / "card_check"), *progress_args(progress)])]


def card_lines(encoder: str) -> list[str]:
    """The card check's commands as a user types them (OUT for the output folder)."""
    return [shlex.join(["rotate", *args]) for _what, args in card_commands(encoder, Path("OUT"))]


def token_summary(encoder: str | Path, sessions: Path, windows: int = 32) -> list[float]:
    """The mean of the encoder's tokens (float32, one thread) over the first ``windows`` windows (stride 5) of the
    sessions under ``sessions`` and over the taxels, per channel: a fingerprint of the weights that any change to
    them or to the way they are loaded moves (the tokens are layer-normalized, so their overall mean and spread are
    the same for any weights; the channels' means are not)."""
    import torch
    from torch.utils.data import default_collate

    from rotation.data.skin import SkinWindows
    from rotation.tactile.loading import session_paths
    from rotation.tactile.models.encoders import load_encoder

    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    try:
        data = SkinWindows(session_paths([sessions]), labels=())
        batch = default_collate([data[i] for i in range(min(windows, len(data)))])
        with torch.inference_mode():
            tokens = load_encoder(encoder).eval().encode(batch)["skin"].double()
    finally:
        torch.set_num_threads(threads)
    return [round(float(v), 6) for v in tokens.mean(dim=(0, 1))]


def card_figures(report: Path) -> dict[str, float]:
    """The card check's figures from its report folder: force RMSE per axis (N)."""
    rows = json.loads((Path(report) / "results.json").read_text())["rows"]
    return {r["metric"]: float(r["value"]) for r in rows if r["task"] == "force" and r["variant"] == "pretrained"}


def ship(cfg: Config) -> Path:
    """Copy the exported weights into ``cfg.ship`` with card_check.json (the check's commands, run on the shipped
    name, and its figures)."""
    dest = Path(cfg.ship)
    dest.mkdir(parents=True, exist_ok=True)
    shutil.copyfile(cfg.out / "encoder" / "encoder.safetensors", dest / "encoder.safetensors")
    record = {"command": card_lines(dest.name), "figures": card_figures(cfg.out / "card_check"),
              "unit": "N (force RMSE per axis on the check's test windows)",
              "tokens": token_summary(dest / "encoder.safetensors", cfg.out / "card_sessions")}
    (dest / CARD_FILE).write_text(json.dumps(record, indent=2) + "\n")
    return dest


def run(cfg: Config) -> int:
    status = run_steps("skin_cpu_recipe", commands(cfg), cfg.dry_run)
    if status == 0 and not cfg.dry_run:
        print(f"skin_cpu_recipe: done; the encoder is {cfg.out / 'encoder'}, the probe {cfg.out / 'probe'}")
        if cfg.ship is not None:
            print(f"skin_cpu_recipe: shipped into {ship(cfg)} (write its MODEL_CARD.md from {cfg.out / 'probe'})")
    return status


def main(argv: list[str] | None = None) -> int:
    return script_main(Config, run, __doc__, argv)


if __name__ == "__main__":
    sys.exit(main())
