"""Compare policy bundles under perturbations of friction, object mass and centre of mass.

Every policy meets the same conditions and the same seeds (episode j of every condition runs in an env seeded
seed + j). Metrics per policy and condition, averaged over episodes: rotation_rate (rad/s, signed), rotation_total
(rad), ttf (time to fall / episode length, 1 = never fell), vertical_drift (m), lin_vel (m/s), torque (N m).
Writes OUT/results.json (rows + config), OUT/results.md, OUT/plots/<metric>.png and, with --video, one MP4 per
condition with the policies side by side (headless rendering: MUJOCO_GL=egl).

    rotate evaluate --policy teacher=teacher --policy student=runs/student/bundle --suite perturbations
    rotate evaluate --policy student --friction-scale 0.5 --added-mass 0.1 --episodes 20 --out runs/eval_slippery
    rotate evaluate --policy teacher=teacher --policy student=runs/student/bundle --suite perturbations --resume

Each condition's rows are kept in OUT/conditions/ as soon as it finishes: Ctrl-C or SIGTERM (exit status 130 / 143)
lose at most the condition that was running, and the same command again (or with --resume) runs only the rest. An
OUT that holds an evaluation with other settings or other policy weights is refused, with the differences.
"""

from __future__ import annotations

import argparse
import contextlib
import dataclasses
import signal
import threading
from collections.abc import Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Literal

import torch
from tqdm import tqdm

from envs.config import ContactConfig, EnvConfig, Perturbation, RandomizationConfig
from envs.errors import RequestRefused
from envs.grasp_cache import load_default_cache
from envs.validation import check_int, check_optional_file, check_output_dir, check_seed, check_types
from rotation.bundles import load_bundle
from rotation.configs import save_config
from rotation.evaluate import finished
from rotation.evaluate.report import make_row, write_report
from rotation.evaluate.rollout import run_episodes
from rotation.evaluate.suites import SUITES, Condition, get_suite, make_condition
from rotation.interrupt import SIGNAL_NAMES, Interrupted
from rotation.policy.bundle import PolicyBundle, shipped_bundles
from rotation.sim_warp.host import BACKEND_HELP, BACKENDS, make_vec


@dataclass
class Config:
    """`rotate evaluate`."""

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
    episode_steps: int = 400
    """Episode length in policy steps (400 = 20 s at 20 Hz); ttf is relative to it."""
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
    touch_lag: int = 0
    """Control steps between the touch a tactile adapter's correction reads and the first action it changes; 0 = the
    same step. A deploy acts on each correction from the first control step after its refresh finishes
    (rotation.deploy.touch): 3 steps later on a 2-core CPU, where a refresh takes 95-120 ms after the policy has acted
    on its step (the deploy summary's touch.first_correction_step is 3-4 there). Other policies ignore it."""
    backend: Literal["cpu", "warp"] = "cpu"
    """Physics backend: 'cpu' (MuJoCo on mujoco.batch threads) or 'warp' (MuJoCo Warp on `warp_device`, the [warp]
    extra). The simulated Digit 360 touch and --video run on the cpu backend only."""
    warp_device: str = "cuda"
    """Device of the warp backend's worlds: 'cuda', 'cuda:<index>' or 'cpu' (Warp's CPU device, slow)."""
    contact: ContactConfig = field(default_factory=ContactConfig)
    """MuJoCo's contact model for every condition (envs.config.ContactConfig); the default is the one the shipped
    policies were trained with, and the report says when another is used."""

    def __post_init__(self) -> None:
        check_types(self, skip=("com_shift",))  # Perturbation checks com_shift with its own message
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
        check_int("touch_lag", self.touch_lag, 0, 10**6, "control steps")
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
            EnvConfig(object=self.object, episode_steps=self.episode_steps, randomization=rand, perturb=cond.perturb)


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
    parser.add_argument("--episode-steps", type=int, default=d.episode_steps,
                        help=f"episode length in policy steps (default {d.episode_steps})")
    parser.add_argument("--randomize", action=argparse.BooleanOptionalAction, default=d.randomize,
                        help="keep the training domain randomization (default on)")
    parser.add_argument("--video", action="store_true", help="write one MP4 per condition (MUJOCO_GL=egl)")
    parser.add_argument("--video-size", type=int, nargs=2, default=list(d.video_size), metavar=("W", "H"),
                        help=f"pixels of each policy's video tile (default {d.video_size[0]} {d.video_size[1]})")
    parser.add_argument("--nthread", type=int, default=d.nthread, help="MuJoCo threads (0 = auto)")
    parser.add_argument("--torch-threads", type=int, default=d.torch_threads, help="torch CPU threads (default 1)")
    parser.add_argument("--progress", action=argparse.BooleanOptionalAction, default=d.progress,
                        help="show a progress bar")
    parser.add_argument("--touch-lag", type=int, default=d.touch_lag, metavar="STEPS",
                        help="a tactile adapter's correction acts STEPS control steps after the touch it read, and "
                        "the next refresh waits for it, as on a robot whose refresh takes that long (rotate deploy "
                        "on a 2-core CPU: 3, its summary's touch.first_correction_step). "
                        f"Default {d.touch_lag}: on the same step")
    parser.add_argument("--backend", choices=list(BACKENDS), default=d.backend, help=BACKEND_HELP)
    parser.add_argument("--warp-device", default=d.warp_device,
                        help=f"device of the warp backend: cuda, cuda:N or cpu (default {d.warp_device})")
    parser.add_argument("--contact-cone", choices=("pyramidal", "elliptic"), default=d.contact.cone,
                        help=f"friction cone of the contact model (default {d.contact.cone}, what the shipped policies "
                        "trained with)")
    parser.add_argument("--contact-impratio", type=float, default=d.contact.impratio,
                        help=f"frictional to normal impedance ratio, 1-100 (default {d.contact.impratio:g})")
    parser.add_argument("--contact-noslip-iterations", type=int, default=d.contact.noslip_iterations,
                        help=f"iterations of MuJoCo's noslip solver, 0 = off (default {d.contact.noslip_iterations})")
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
        policies=dict(args.policies), suite=args.suite, conditions=tuple(args.conditions),
        friction_scale=args.friction_scale, added_mass=args.added_mass,
        com_shift=tuple(args.com_shift) if args.com_shift is not None else None, episodes=args.episodes,
        seed=args.seed, out=args.out, num_envs=args.num_envs, object=args.object, grasp_cache=args.grasp_cache,
        episode_steps=args.episode_steps, randomize=args.randomize, video=args.video,
        video_size=tuple(args.video_size), nthread=args.nthread, torch_threads=args.torch_threads,
        progress=args.progress, resume=args.resume, touch_lag=args.touch_lag, backend=args.backend,
        warp_device=args.warp_device,
        contact=ContactConfig(cone=args.contact_cone, impratio=args.contact_impratio,
                              noslip_iterations=args.contact_noslip_iterations),
    )


def resolve_conditions(cfg: Config) -> list[Condition]:
    """The conditions of a run: a suite, or one condition from the perturbation fields (nominal by default)."""
    custom = {k: v for k, v in (("friction_scale", cfg.friction_scale), ("added_mass", cfg.added_mass),
                                ("com_shift", cfg.com_shift)) if v is not None}
    if cfg.suite is not None:
        if custom:
            raise ValueError(f"give either a suite or perturbation values, not both (suite {cfg.suite!r} with "
                             f"{sorted(custom)})")
        return get_suite(cfg.suite, cfg.conditions)
    if cfg.conditions:
        return get_suite("perturbations", cfg.conditions)
    return [make_condition(Perturbation(**custom))]


def policy_paths(cfg: Config) -> dict[str, str]:
    """Label -> bundle directory or shipped name: the given policies, or every shipped bundle."""
    return dict(cfg.policies) or {name: name for name in shipped_bundles()}


def load_policies(cfg: Config) -> dict[str, PolicyBundle]:
    """Load every bundle up front (a bad name fails before any simulation) and check they share a control rate."""
    policies = policy_paths(cfg)
    if not policies:
        raise RequestRefused("no policies given (--policy NAME=PATH) and no bundles are shipped with the package")
    bundles = {name: load_bundle(path) for name, path in policies.items()}
    touch = [name for name, b in bundles.items() if reads_touch(b)]
    if touch and cfg.backend != "cpu":
        raise ValueError(f"--policy {', '.join(touch)} read(s) touch, which the simulated Digit 360 provides on the "
                         "cpu backend only; evaluate with --backend cpu")
    timing = {(b.config.control_hz, b.config.action_scale) for b in bundles.values()}
    if len(timing) > 1:
        raise ValueError(f"the policies were trained at different control rates / action scales {sorted(timing)}; "
                         "evaluate them in separate runs")
    needs = {name: bundles[name].env_needs for name in touch}
    if len({tuple(sorted(n.items())) for n in needs.values()}) > 1:
        raise ValueError(f"--policy {', '.join(touch)} read different touch ({needs}): a Digit 360 adapter runs on "
                         "the Digit 360 hand, a skin adapter on the Xela hand; evaluate them in separate runs")
    return bundles


def touch_env(bundles: dict[str, PolicyBundle]) -> dict[str, Any]:
    """The EnvConfig fields the touch-reading policies need (every policy of the run then meets that env: a skin
    adapter's run puts all of them on the Xela hand); {} when none reads touch."""
    return next((b.env_needs for b in bundles.values() if reads_touch(b)), {})


def env_config(cfg: Config, bundle: PolicyBundle, perturb: Perturbation, touch: dict[str, Any] | None = None
               ) -> EnvConfig:
    """The env of one condition; control rate and action scale come from the bundle, not from this config.
    ``touch``: the fields a touch-reading policy needs (:func:`touch_env`): the simulated Digit 360 fingertips
    change no other policy's episodes; the Xela hand with its skin is another hand for all of them."""
    rand = RandomizationConfig() if cfg.randomize else RandomizationConfig(enabled=False)
    return EnvConfig(object=cfg.object, grasp_cache=cfg.grasp_cache, episode_steps=cfg.episode_steps,
                     control_hz=bundle.config.control_hz, action_scale=bundle.config.action_scale,
                     randomization=rand, perturb=perturb, contact=cfg.contact, **(touch or {}))


def reads_touch(bundle: PolicyBundle) -> bool:
    """True for a policy with a tactile adapter (it needs the env's `tactile` or `skin` group)."""
    return bool(getattr(bundle, "touch_every", 0))


def run(cfg: Config) -> list[dict]:
    """Evaluate every policy under every condition; returns the result rows (also written to ``cfg.out``).

    Each finished condition is kept on disk at once (rotation.evaluate.finished); a run into an `out` that holds
    the same evaluation continues it. Ctrl-C / SIGTERM stop at once, keep every finished condition and raise
    Interrupted (exit status 130 / 143)."""
    if cfg.episodes < 1 or cfg.num_envs < 1:
        raise ValueError(f"episodes and num_envs must be >= 1, got {cfg.episodes} and {cfg.num_envs}")
    torch.set_num_threads(cfg.torch_threads)
    conditions = resolve_conditions(cfg)
    bundles = load_policies(cfg)
    first = next(iter(bundles.values()))
    out = Path(cfg.out)
    hand = touch_env(bundles).get("hand", "digit360")
    # a grasp cache that cannot be used is refused before `out` is touched (the envs load it again)
    load_default_cache(cfg.object, cfg.grasp_cache, hand)
    ident = finished.identity(cfg, policy_paths(cfg), hand)
    continuing = finished.check_out(out, ident, cfg.resume)  # refuses another evaluation's folder: reads only
    names = list(bundles)
    done = {c.name: rows for c in conditions if (rows := finished.rows(out, c.name, names)) is not None}
    if continuing:
        print(f"evaluate: continuing the evaluation in {out}: {len(done)} of {len(conditions)} conditions done")
    out.mkdir(parents=True, exist_ok=True)
    save_config(cfg, out / "config.json")
    finished.start(out, ident)

    todo = [c for c in conditions if c.name not in done]
    total = len(todo) * len(bundles) * cfg.episodes
    try:
        with _sigterm_interrupts(), tqdm(total=total, unit="episode", desc="evaluate", disable=not cfg.progress,
                                         dynamic_ncols=True) as bar:
            for cond in todo:
                done[cond.name] = _run_condition(cfg, cond, bundles, first, out, bar)
                finished.save_rows(out, cond.name, done[cond.name])  # kept now, whatever happens next
    except KeyboardInterrupt as err:  # Ctrl-C, or SIGTERM through _sigterm_interrupts
        signum = getattr(err, "signum", signal.SIGINT)
        message = (f"evaluate: stopped by {SIGNAL_NAMES.get(signum, f'signal {signum}')}; {len(done)} of "
                   f"{len(conditions)} conditions are kept in {out / finished.CONDITIONS_DIR}; run the same command "
                   "again (or add --resume) to finish the rest")
        print(message, flush=True)
        raise Interrupted(signum, message) from None
    rows = [row for cond in conditions for row in done[cond.name]]
    write_report(out, rows, dataclasses.replace(cfg, out=out), conditions)
    print(f"evaluate: {len(rows)} rows -> {out / 'results.md'}")
    return rows


def _run_condition(cfg: Config, cond: Condition, bundles: dict[str, PolicyBundle], first: PolicyBundle, out: Path,
                   bar: tqdm) -> list[dict]:
    """Every policy under one condition (same env, same seeds): one row per policy; the video if asked for."""
    env = make_vec(cfg.backend, env_config(cfg, first, cond.perturb, touch_env(bundles)),
                   num_envs=min(cfg.num_envs, cfg.episodes), seed=cfg.seed, nthread=cfg.nthread or None,
                   device=cfg.warp_device)
    recorder = None
    try:
        if cfg.video:
            from rotation.evaluate.video import FrameRecorder

            recorder = FrameRecorder(env, *cfg.video_size)
        rows = []
        for name, bundle in bundles.items():
            bar.set_postfix(condition=cond.name, policy=name)
            hook = recorder.hook(name) if recorder is not None else None
            episodes = run_episodes(bundle, env, cfg.episodes, cfg.seed, on_frame=hook,
                                    on_episode=lambda: bar.update(1), touch_lag=cfg.touch_lag)
            rows.append(make_row(name, cond, episodes))
        if recorder is not None:
            recorder.write(out / "videos" / f"{cond.name}.mp4", fps=_video_fps(first))
        return rows
    finally:
        if recorder is not None:
            recorder.close()
        env.close()


@contextlib.contextmanager
def _sigterm_interrupts() -> Iterator[None]:
    """SIGTERM stops the evaluation at once, as Ctrl-C does (finished conditions are on disk already): it raises
    Interrupted(SIGTERM) in the main thread. Elsewhere Python cannot install handlers and nothing changes."""
    if threading.current_thread() is not threading.main_thread():
        yield
        return

    def stop(signum: int, frame: object) -> None:
        raise Interrupted(signum)

    previous = signal.signal(signal.SIGTERM, stop)
    try:
        yield
    finally:
        signal.signal(signal.SIGTERM, previous)


def _video_fps(bundle: PolicyBundle) -> int:
    """Video frame rate: one frame per policy step, in real time."""
    return max(1, round(bundle.config.control_hz))
