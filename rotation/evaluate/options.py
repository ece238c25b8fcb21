"""The options of `rotate evaluate`: its Config (every check that needs no policy loaded), the command line, and
the conditions a run evaluates (rotation.evaluate.job runs them)."""

from __future__ import annotations

import argparse
from dataclasses import dataclass, field
from pathlib import Path
from typing import Literal

from adapters.touch_delay import MEASURED, parse_delay
from envs.config import ContactConfig, EnvConfig, Perturbation, RandomizationConfig
from envs.constants import DEFAULT_HAND
from envs.validation import check_int, check_number, check_optional_file, check_output_dir, check_seed, check_types
from rotation.evaluate.suites import SUITES, Condition, get_suite, make_condition
from rotation.policy.bundle import shipped_bundles
from rotation.sim_warp.host import BACKEND_HELP, BACKENDS

ROTATION_EPISODE_STEPS = EnvConfig.episode_steps
"""The rotation task's episode length (policy steps): 400 = 20 s at 20 Hz."""


@dataclass
class Config:
    """`rotate evaluate`."""

    task: Literal["rotation", "insertion"] = "rotation"
    """'rotation': rotation policies under the conditions below; 'insertion': imitation policies on plug insertion
    (rotation.il.rollout: --policy, --episodes, --seed, --out, --video apply)."""
    policies: dict[str, str] = field(default_factory=dict)
    """Policy label -> bundle directory or shipped bundle name; empty = every shipped bundle."""
    suite: str | None = None
    """Suite of conditions (see rotation.evaluate.suites.SUITES); None = one condition from the perturbation fields
    below (nominal when they are all unset)."""
    conditions: tuple[str, ...] = ()
    """Run only these conditions of the suite (names as in its table)."""
    friction_scale: float | None = None
    """Multiplies the friction the env would otherwise use."""
    added_mass: float | None = None
    """Added to the object mass (kg)."""
    com_shift: tuple[float, float, float] | None = None
    """Added to the object's centre-of-mass offset (m, object frame)."""
    episodes: int = 10
    """Episodes per policy and condition."""
    seed: int = 0
    """Episode j of every condition runs in an env seeded seed + j."""
    out: Path = Path("runs/evaluate")
    """Report directory."""
    num_envs: int = 16
    """Simulations stepped together (at most `episodes`). Results depend on it only through float rounding in batched
    network evaluation (which contact dynamics can amplify); keep it fixed when comparing runs."""
    object: str = "cup"
    """Object to rotate (envs.objects); the shipped policies were trained on 'cup'."""
    grasp_cache: str = ""
    """Grasp cache file; empty = the one shipped for the object."""
    episode_steps: int | None = None
    """Episode length in policy steps; None = the task's own: rotation 400 (20 s at 20 Hz, ttf is relative to
    it), insertion 300 actions (15 s)."""
    randomize: bool = True
    """Keep the training domain randomization (the perturbations apply on top); off = nominal physics, no pushes."""
    video: bool = False
    """Write OUT/videos/<condition>.mp4 (first episode, policies side by side)."""
    video_size: tuple[int, int] = (320, 240)
    """Width and height (pixels) of each policy's tile in the video."""
    nthread: int = 0
    """MuJoCo threads (0 = one per CPU core, at most num_envs)."""
    torch_threads: int = 1
    """torch CPU threads for the policies (1 keeps runs bit-reproducible and leaves the cores to MuJoCo)."""
    progress: bool = True
    """Show a progress bar."""
    resume: bool = False
    """Continue the evaluation in `out` (an interrupted one): keep its finished conditions, run the rest. Running
    the same command into the same `out` does this too; --resume also insists that there is something to continue."""
    touch_delay: str = "measured"
    """Control steps between the touch a tactile adapter's correction reads and the first action it changes, drawn
    per refresh (adapters.touch_delay): 'measured' (what `rotate deploy` measured on 2 CPU cores at 20 Hz), a whole
    number N (always N; 0 = the same step, the ideal) or STEPS:PROB pairs (e.g. 1:0.7,2:0.3 for your machine's,
    from its deploy summary's touch.first_use_steps). Other policies ignore it."""
    backend: Literal["cpu", "warp"] = "cpu"
    """Physics backend: 'cpu' (MuJoCo on mujoco.batch threads) or 'warp' (MuJoCo Warp on `warp_device`, the [warp]
    extra). The simulated Digit 360 touch and --video run on the cpu backend only."""
    warp_device: str = "cuda"
    """Device of the warp backend's worlds: 'cuda', 'cuda:<index>' or 'cpu' (Warp's CPU device, slow)."""
    contact: ContactConfig | None = None
    """MuJoCo's contact model for every condition (envs.config.ContactConfig); None = the one the policies' hand
    trains with (envs.physics.HAND_PHYSICS), with that hand's contact randomization. A model given here replaces
    both: every episode runs exactly it. The report says when another is used."""
    physics_dt: float | None = None
    """Physics step (s) of every condition; None = the env's 0.01. The control rate stays the policies'."""

    def __post_init__(self) -> None:
        check_types(self, skip=("com_shift",))  # Perturbation checks com_shift with its own message
        if self.episode_steps is None and self.task == "rotation":
            self.episode_steps = ROTATION_EPISODE_STEPS
        if self.episode_steps is not None:
            check_int("episode_steps", self.episode_steps, 1, 10**6)
        self.out = Path(self.out)
        if self.suite is not None and self.suite not in SUITES:
            raise ValueError(f"suite: unknown suite {self.suite!r}; choose one of: {', '.join(SUITES)}")
        check_int("episodes", self.episodes, 1, 10**6)
        check_seed("seed", self.seed)
        check_output_dir("out", self.out)
        check_int("num_envs", self.num_envs, 1, 4096)
        check_optional_file("grasp_cache", self.grasp_cache, "generate one with `rotate grasps`")
        check_int("video_size width", self.video_size[0], 16, 640, "pixels (MuJoCo's offscreen framebuffer)")
        check_int("video_size height", self.video_size[1], 16, 480, "pixels (MuJoCo's offscreen framebuffer)")
        check_int("nthread", self.nthread, 0, 1024, "(0 = one per CPU core)")
        check_int("torch_threads", self.torch_threads, 1, 1024)
        self.delay = parse_delay(self.touch_delay)
        if self.physics_dt is not None:
            check_number("physics_dt", self.physics_dt, 1e-4, 0.02, unit="s")
        if self.com_shift is not None and (not isinstance(self.com_shift, tuple | list) or len(self.com_shift) != 3):
            raise ValueError(f"com_shift needs 3 values (X Y Z, m), got {self.com_shift!r}")
        if self.backend == "warp" and self.video:
            raise ValueError("video: the videos render the cpu backend's simulations; drop --video or use "
                             "--backend cpu")
        if not (self.warp_device == "cpu" or self.warp_device == "cuda" or self.warp_device.startswith("cuda:")):
            raise ValueError(f"warp_device must be 'cuda', 'cuda:<index>' or 'cpu', got {self.warp_device!r}")
        rand = RandomizationConfig() if self.randomize else RandomizationConfig(enabled=False)
        try:
            conditions = resolve_conditions(self)
        except ValueError as err:
            raise ValueError(f"conditions: {err}" if "condition" in str(err) else str(err)) from None
        for cond in conditions:  # the object, the episode length and each perturbation's physical limits
            EnvConfig(object=self.object, episode_steps=self.episode_steps or ROTATION_EPISODE_STEPS,
                      randomization=rand, perturb=cond.perturb)


def _policy_arg(text: str) -> tuple[str, str]:
    name, sep, path = text.partition("=")
    if not sep:
        name, path = text, text
    if not name or not path:
        raise argparse.ArgumentTypeError(f"expected NAME=PATH or a bundle name, got {text!r}")
    return name, path


def add_arguments(parser: argparse.ArgumentParser) -> None:
    d = Config()
    parser.add_argument("--policy", dest="policies", action="append", type=_policy_arg, default=[],
                        metavar="NAME=PATH", help="a policy to evaluate: label=bundle directory or shipped bundle "
                        f"name (repeatable; shipped: {', '.join(shipped_bundles()) or 'none yet'}); a bare name "
                        "or path is its own label. Default: every shipped bundle")
    parser.add_argument("--task", choices=("rotation", "insertion"), default=d.task,
                        help="rotation (default): rotation policies under perturbations; insertion: imitation "
                        "policies (rotate train-il bundles) inserting a plug, success rate with its 95%% interval")
    parser.add_argument("--suite", nargs="?", const="perturbations", default=None, choices=list(SUITES),
                        help="run a suite of conditions (bare --suite = perturbations)")
    parser.add_argument("--conditions", nargs="+", default=[], metavar="NAME",
                        help="only these conditions of the suite")
    parser.add_argument("--friction-scale", type=float, metavar="F", help="multiply the friction by F")
    parser.add_argument("--added-mass", type=float, metavar="KG", help="add KG to the object mass")
    parser.add_argument("--com-shift", type=float, nargs=3, metavar=("X", "Y", "Z"),
                        help="add (X, Y, Z) m to the object's centre of mass")
    parser.add_argument("--episodes", type=int, default=d.episodes, help=f"episodes per policy and condition "
                        f"(default {d.episodes})")
    parser.add_argument("--seed", type=int, default=d.seed, help="episode j is seeded seed + j (default 0)")
    parser.add_argument("--out", type=Path, default=d.out, help=f"report directory (default {d.out})")
    parser.add_argument("--num-envs", type=int, default=d.num_envs, help=f"parallel simulations (default "
                        f"{d.num_envs}); keep it fixed when comparing runs")
    parser.add_argument("--object", default=d.object, help=f"object to rotate (default {d.object})")
    parser.add_argument("--grasp-cache", default=d.grasp_cache, help="grasp cache file (default: shipped)")
    parser.add_argument("--episode-steps", type=int, default=None,
                        help=f"episode length in policy steps (default: the task's own, rotation "
                             f"{ROTATION_EPISODE_STEPS} = 20 s at 20 Hz, insertion 300 actions)")
    parser.add_argument("--randomize", action=argparse.BooleanOptionalAction, default=d.randomize,
                        help="keep the training domain randomization (default on)")
    parser.add_argument("--video", action="store_true", help="write one MP4 per condition (MUJOCO_GL=egl)")
    parser.add_argument("--video-size", type=int, nargs=2, default=list(d.video_size), metavar=("W", "H"),
                        help=f"pixels of each policy's video tile (default {d.video_size[0]} {d.video_size[1]})")
    parser.add_argument("--nthread", type=int, default=d.nthread, help="MuJoCo threads (0 = auto)")
    parser.add_argument("--torch-threads", type=int, default=d.torch_threads, help="torch CPU threads (default 1)")
    parser.add_argument("--progress", action=argparse.BooleanOptionalAction, default=d.progress,
                        help="show a progress bar")
    measured = MEASURED.describe().split(": ", 1)[1].replace("%", "%%")  # argparse formats help with %
    parser.add_argument("--touch-delay", default=d.touch_delay, metavar="DELAY",
                        help="control steps from the touch a tactile adapter's correction reads to the first action "
                        "it changes, drawn per refresh; the next refresh waits for it, as on a robot: 'measured' "
                        f"(rotate deploy on 2 CPU cores: {measured}), N (always N; 0: the same step) or STEPS:PROB "
                        "pairs such as 1:0.7,2:0.3 (your deploy summary's touch.first_use_steps). "
                        f"Default {d.touch_delay}")
    parser.add_argument("--backend", choices=list(BACKENDS), default=d.backend, help=BACKEND_HELP)
    parser.add_argument("--warp-device", default=d.warp_device,
                        help=f"device of the warp backend: cuda, cuda:N or cpu (default {d.warp_device})")
    usual = ContactConfig()
    parser.add_argument("--contact-cone", choices=("pyramidal", "elliptic"), default=None,
                        help="friction cone of the contact model. Default: the model the policies' hand trains with "
                        "(envs.physics.HAND_PHYSICS); giving any --contact-* option sets the whole model, the others "
                        f"then default to {usual.cone} / {usual.impratio:g} / {usual.noslip_iterations}")
    parser.add_argument("--contact-impratio", type=float, default=None,
                        help="frictional to normal impedance ratio, 1-100 (see --contact-cone for the default)")
    parser.add_argument("--contact-noslip-iterations", type=int, default=None,
                        help="iterations of MuJoCo's noslip solver, 0 = off (see --contact-cone for the default)")
    parser.add_argument("--contact-timeconst", type=float, default=None,
                        help="time constant (s) of every contact, MuJoCo's solref[0] (default: the model's 0.02; at "
                        "least two physics steps)")
    parser.add_argument("--contact-solimp", type=float, nargs=3, default=None, metavar=("DMIN", "DMAX", "WIDTH"),
                        help="every contact's impedance, MuJoCo's solimp (default: the model's 0.9 0.95 0.001)")
    parser.add_argument("--physics-dt", type=float, default=None,
                        help="physics step (s) of every condition (default 0.01; 1 / (control rate x step) must be a "
                        "whole number)")
    parser.add_argument("--resume", action="store_true",
                        help="continue the interrupted evaluation in --out (its finished conditions are kept; the "
                        "same command without --resume continues it too)")


def config_from_args(args: argparse.Namespace) -> Config:
    names = [n for n, _ in args.policies]
    duplicated = sorted({n for n in names if names.count(n) > 1})
    if duplicated:
        raise ValueError(f"--policy: label(s) {duplicated} given more than once; give each policy its own label "
                         "(--policy NAME=PATH)")
    return Config(
        task=args.task, policies=dict(args.policies), suite=args.suite, conditions=tuple(args.conditions),
        friction_scale=args.friction_scale, added_mass=args.added_mass,
        com_shift=tuple(args.com_shift) if args.com_shift is not None else None, episodes=args.episodes,
        seed=args.seed, out=args.out, num_envs=args.num_envs, object=args.object, grasp_cache=args.grasp_cache,
        episode_steps=args.episode_steps, randomize=args.randomize, video=args.video,
        video_size=tuple(args.video_size), nthread=args.nthread, torch_threads=args.torch_threads,
        progress=args.progress, resume=args.resume, touch_delay=args.touch_delay, backend=args.backend,
        warp_device=args.warp_device,
        contact=_contact_from_args(args), physics_dt=args.physics_dt,
    )


def _contact_from_args(args: argparse.Namespace) -> ContactConfig | None:
    """The contact model the --contact-* options set (the unset ones at ContactConfig's defaults), None when none
    is given (the policies' own)."""
    given = {k: v for k, v in (("cone", args.contact_cone), ("impratio", args.contact_impratio),
                                ("noslip_iterations", args.contact_noslip_iterations),
                                ("timeconst", args.contact_timeconst),
                                ("solimp", tuple(args.contact_solimp) if args.contact_solimp else None))
             if v is not None}
    return ContactConfig(**given) if given else None


def resolve_conditions(cfg: Config, hand: str = DEFAULT_HAND) -> list[Condition]:
    """The conditions of a run on ``hand``: a suite, or one condition from the perturbation fields (nominal by
    default)."""
    custom = {k: v for k, v in (("friction_scale", cfg.friction_scale), ("added_mass", cfg.added_mass),
                                ("com_shift", cfg.com_shift)) if v is not None}
    if cfg.suite is not None:
        if custom:
            raise ValueError(f"give either a suite or perturbation values, not both (suite {cfg.suite!r} with "
                             f"{sorted(custom)})")
        return get_suite(cfg.suite, cfg.conditions, hand)
    if cfg.conditions:
        return get_suite("perturbations", cfg.conditions, hand)
    return [make_condition(Perturbation(**custom))]
