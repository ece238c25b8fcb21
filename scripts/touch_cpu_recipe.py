"""The touch encoder on the generation-2 streams on a CPU alone: collect pretraining sessions on the vendor-kinematics
hand, pretrain a tinier Sparsh-X on them, then the information ladder on held-out sessions (docs/tactile.md).

Steps (each a `rotate` command; a finished one is skipped, a stopped one resumes):

1. six collections on the policy's hand, the shipped encoder's data mix (rotation/tactile/pretrained/
   sparshx-tinier-sim/MODEL_CARD.md) moved to the v4 hand's limits: the policy at nominal randomization, with
   friction x0.5, +0.1 kg, both, friction x0.3, and the gentle random policy;
2. `rotate pretrain` (tinier, on the fly, no window cache: on 2 cores the encoder's step, not rendering, is the
   cost), checkpoints every ``checkpoint_every`` steps, resumed with --resume;
3. `scripts/export_encoder.py` of the pretraining run into OUT/encoder;
4. the report's own sessions (other seeds: randomization draws the encoder never saw) and `rotate touch-report`
   with all four rungs into OUT/touch_report; then a second draw of them (seed 201) into OUT/touch_report_201, since
   a figure from one draw's 40 test sessions moves by about 0.1 between draws (``--report-draws``).

    python scripts/touch_cpu_recipe.py --policy runs/sim_v4/teacher/stage5/bundle --out runs/touch_cpu   # 3 + 1 layers
    python scripts/touch_cpu_recipe.py --policy ... --out runs/touch_cpu --dry-run     # the commands, run nothing

Budget on 2 CPU cores: the collections take minutes; pretraining runs at about 12.7 windows/s (tinier, batch 32,
rendering on the fly: measured on v4 sessions), so the default 3,000 steps (96,000 windows, a quarter of what the
shipped encoder saw) take about 2.1 h; each ladder (rendering, tokens, readers and three end-to-end trainings)
about 25 min.
On a GPU machine pass --device cuda and a larger --batch-size (the shipped encoder: 256, 1,800 steps, 7.5 min on
one H200 from a window cache; see its model card).
"""

from __future__ import annotations

import sys
from dataclasses import dataclass
from pathlib import Path

from rotation.configs import script_main
from rotation.jobs.recipe import pretrained, progress_args, run_steps

COLLECTIONS: tuple[tuple[str, bool, int, list[str]], ...] = (
    ("policy", True, 0, []),
    ("policy_mu05", True, 1, ["--friction-scale", "0.5"]),
    ("policy_m01", True, 2, ["--added-mass", "0.1"]),
    ("policy_mu05_m01", True, 3, ["--friction-scale", "0.5", "--added-mass", "0.1"]),
    ("policy_mu03", True, 5, ["--friction-scale", "0.3"]),
    ("random", False, 4, ["--random-scale", "0.15"]),
)
"""(folder under OUT/sessions, whether the policy acts (else the random policy), seed, options)."""
REPORT_SEED = 200
"""Seed of the report's first draw of sessions (the pretraining collections use 0-5); a draw k > 0 uses
REPORT_SEED + k."""


@dataclass
class Config:
    policy: str = ""
    """A policy bundle of the touch hand (the retrained digit360_v4 teacher or student) that collects the sessions."""
    out: Path = Path("runs/touch_cpu")
    """Folder of the recipe: sessions/, pretrain/, encoder/, report_sessions/, touch_report/."""
    hand: str = "digit360_v4"
    """The Digit 360 hand (its touch generation: envs.scene.touch_model); the policy must act on it."""
    episodes: int = 32
    """Episodes per pretraining collection (six collections)."""
    report_episodes: int = 160
    """Episodes of the report's held-out sessions (a quarter of them test sessions: 40, so that the friction
    terciles of the test split are not left to a few draws)."""
    report_draws: int = 2
    """Draws of the report's sessions, each its own ladder (seeds REPORT_SEED, REPORT_SEED + 1, ...): a figure from 40
    test sessions moves by about 0.1 on mass between draws (experiments/touch_ladder/v6_slip_reading), so an encoder
    is judged on more than one."""
    episode_steps: int = 400
    """Policy steps per episode (20 s)."""
    size: str = "tinier"
    """Encoder size (rotate pretrain --size)."""
    layers: tuple[int, ...] = (3, 1)
    """Unimodal and fusion layers instead of the size's (rotate pretrain --unimodal-layers, --fusion-layers); empty:
    the size's (6 + 2). The per-step touch path's target is 50 ms on 2 cores: a fresh all-modality adapter's touch
    step takes 41 ms with 3 + 1 layers and 89 ms with 6 + 2 (scripts/bench_adapter.py, both threads, the machine
    otherwise idle); in an emulated deploy its correction acts 2-5 control steps after its touch (median 3) against
    3-7 (median 4), without the emulator's rendering (bench_adapter --deploy 40, docs/adapter.md). But one
    bottleneck fusion layer fuses nothing (SparshXConfig.fuses; `rotate pretrain` warns): 2 + 2 is the same depth
    with one exchange between the modalities, not pretrained yet."""
    steps: int = 3000
    """Pretraining steps."""
    batch_size: int = 32
    """Pretraining batch (windows)."""
    lr: float = 5e-4
    """Peak learning rate."""
    checkpoint_every: int = 100
    """Steps between pretraining checkpoints (what a stop loses at most)."""
    device: str = "cpu"
    """torch device of the pretraining (cpu, cuda)."""
    num_workers: int = 1
    """DataLoader workers of the pretraining (rendering windows on the fly)."""
    progress: bool = True
    """Progress bars."""
    dry_run: bool = False
    """Print the commands without running them."""

    def __post_init__(self) -> None:
        self.out = Path(self.out)
        if not self.policy:
            raise ValueError("policy: give the policy bundle that collects the sessions (a digit360_v4 teacher or "
                             "student)")
        if self.layers and (len(self.layers) != 2 or min(self.layers) < 0 or sum(self.layers) < 1):
            raise ValueError(f"layers: give two counts, unimodal and fusion (e.g. 3 1), got {list(self.layers)}")
        for name in ("episodes", "report_episodes", "report_draws", "episode_steps", "steps", "batch_size",
                     "checkpoint_every"):
            if int(getattr(self, name)) < 1:
                raise ValueError(f"{name} must be >= 1, got {getattr(self, name)}")


def commands(cfg: Config) -> list[tuple[str, list[str]]]:
    """(what, command) still to run, in order; `rotate` commands start with their subcommand, the export with
    'python'. Collections are always listed: `rotate collect` itself keeps what is complete and records the rest."""
    out, todo, progress = cfg.out, [], progress_args(cfg.progress)
    common = ["--episode-steps", str(cfg.episode_steps), "--num-envs", "16", "--hand", cfg.hand, *progress]
    for name, acts, seed, options in COLLECTIONS:
        todo.append((f"collect {name}", ["collect", "--policy", cfg.policy if acts else "random", "--episodes",
                                         str(cfg.episodes), "--seed", str(seed), "--out", str(out / "sessions" / name),
                                         *options, *common]))
    pretrain = out / "pretrain"
    if not pretrained(pretrain, cfg.steps):
        resume = ["--resume"] if any(pretrain.glob("ckpt_*.safetensors")) else []
        todo.append((f"pretrain: {cfg.steps} steps of {cfg.batch_size} windows{' (resumed)' if resume else ''}",
                     ["pretrain", "--sessions", str(out / "sessions"), "--out", str(pretrain), "--size", cfg.size,
                      "--stride", "10", "--steps", str(cfg.steps), "--batch-size", str(cfg.batch_size), "--lr",
                      str(cfg.lr), "--warmup-fraction", "0.1", "--checkpoint-every", str(cfg.checkpoint_every),
                      "--keep-checkpoints", "2", "--log-every", "25", "--num-workers", str(cfg.num_workers),
                      "--device", cfg.device, *_layers(cfg), *resume, *progress]))
    encoder = out / "encoder" / "encoder.safetensors"
    if not encoder.is_file() or (pretrain / "encoder.safetensors").is_file() and \
            (pretrain / "encoder.safetensors").stat().st_mtime > encoder.stat().st_mtime:
        todo.append(("export the encoder", ["python", str(Path(__file__).resolve().parent / "export_encoder.py"),
                                            "--checkpoint", str(pretrain), "--out", str(out / "encoder")]))
    for k in range(cfg.report_draws):
        sessions, report = report_folders(out, k)
        which = "" if k == 0 else f" (draw {k + 1}, seed {REPORT_SEED + k})"
        todo.append((f"collect the report's sessions{which}",
                     ["collect", "--policy", cfg.policy, "--episodes", str(cfg.report_episodes), "--seed",
                      str(REPORT_SEED + k), "--out", str(sessions), *common]))
        if not (report / "results.md").is_file():
            todo.append((f"the information ladder{which}", ["touch-report", "--sessions", str(sessions),
                                                            "--checkpoint", str(out / "encoder"), "--stride", "15",
                                                            "--out", str(report), *progress]))
    return todo


def report_folders(out: Path, draw: int) -> tuple[Path, Path]:
    """The sessions and the ladder of the report's draw ``draw`` (0: report_sessions/ and touch_report/; k > 0: the
    same names with _<seed>)."""
    tail = "" if draw == 0 else f"_{REPORT_SEED + draw}"
    return out / f"report_sessions{tail}", out / f"touch_report{tail}"


def _layers(cfg: Config) -> list[str]:
    return [] if not cfg.layers else ["--unimodal-layers", str(cfg.layers[0]), "--fusion-layers", str(cfg.layers[1])]


def run(cfg: Config) -> int:
    status = run_steps("touch_cpu_recipe", commands(cfg), cfg.dry_run)
    if status == 0 and not cfg.dry_run:
        ladders = ", ".join(str(report_folders(cfg.out, k)[1] / "results.md") for k in range(cfg.report_draws))
        print(f"touch_cpu_recipe: done; the encoder is {cfg.out / 'encoder'}, the ladders {ladders}")
    return status


def main(argv: list[str] | None = None) -> int:
    return script_main(Config, run, __doc__, argv)


if __name__ == "__main__":
    sys.exit(main())
