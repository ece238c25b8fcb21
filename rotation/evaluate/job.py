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

import contextlib
import dataclasses
import signal
import threading
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import torch
from tqdm import tqdm

from envs.config import EnvConfig, Perturbation, default_randomization
from envs.errors import RequestRefused
from envs.grasp_cache import load_default_cache
from envs.sim_identity import hand_problem
from rotation.bundles import load_bundle, policy_hand
from rotation.configs import save_config
from rotation.evaluate import finished
from rotation.evaluate.options import (  # noqa: F401 (re-exported: the job's options)
    Config,
    add_arguments,
    config_from_args,
    resolve_conditions,
)
from rotation.evaluate.report import make_row, write_report
from rotation.evaluate.rollout import run_episodes
from rotation.evaluate.suites import Condition
from rotation.interrupt import SIGNAL_NAMES, Interrupted
from rotation.policy.bundle import PolicyBundle, shipped_bundles
from rotation.policy.bundle_config import BundleRefused
from rotation.sim_warp.host import make_vec


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
    # one hand for the run: the one a touch-reading policy needs (a skin adapter: the Xela hand), else the first
    # policy's; every policy must act on it
    first = next(iter(bundles.values()))
    run_hand = next((b.env_needs["hand"] for b in bundles.values() if reads_touch(b) and "hand" in b.env_needs),
                    policy_hand(first))
    for name, b in bundles.items():
        problem = hand_problem(b.config.sim, run_hand)
        if problem is not None:
            raise BundleRefused(f"--policy {name}: {problem}; the policies of one run act on one hand ({run_hand} "
                                "here): evaluate policies of different hands in separate runs")
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
    touch = dict(touch or {})
    hand = touch.pop("hand", policy_hand(bundle))
    rand = default_randomization(hand, cfg.randomize)
    if cfg.contact is not None:  # exactly the contact model asked for: none of the hand's contact randomization
        rand = dataclasses.replace(rand, impratio=None, contact_timeconst=None, noslip_dropout=0.0)
    timing = {"physics_dt": cfg.physics_dt} if cfg.physics_dt is not None else {}
    return EnvConfig(object=cfg.object, grasp_cache=cfg.grasp_cache, episode_steps=cfg.episode_steps,
                     control_hz=bundle.config.control_hz, action_scale=bundle.config.action_scale, hand=hand,
                     randomization=rand, perturb=perturb, contact=cfg.contact, **timing, **touch)


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
    if cfg.task == "insertion":
        from rotation.il.rollout import evaluate_insertion

        rows = evaluate_insertion(cfg.policies, cfg.episodes, cfg.seed, Path(cfg.out), cfg.video, cfg.progress,
                                  cfg.episode_steps)
        print(f"evaluate: {len(rows)} insertion rows -> {Path(cfg.out) / 'results.md'}")
        return rows
    bundles = load_policies(cfg)
    first = next(iter(bundles.values()))
    out = Path(cfg.out)
    hand = touch_env(bundles).get("hand", policy_hand(first))
    try:  # the conditions on the policies' hand, each within its physical limits, before `out` is touched
        conditions = resolve_conditions(cfg, hand)
        for cond in conditions:
            env_config(cfg, first, cond.perturb, touch_env(bundles))
    except ValueError as err:
        raise RequestRefused(f"on the {hand} hand: {err}") from None
    # a grasp cache that cannot be used is refused before `out` is touched (the envs load it again)
    load_default_cache(cfg.object, cfg.grasp_cache, hand)
    touch_policies = [name for name, b in bundles.items() if reads_touch(b)]
    ident = finished.identity(cfg, policy_paths(cfg), hand, reads_touch=bool(touch_policies))
    continuing = finished.check_out(out, ident, cfg.resume)  # refuses another evaluation's folder: reads only
    names = list(bundles)
    digest = finished.identity_digest(ident)
    done = {c.name: rows for c in conditions if (rows := finished.rows(out, c.name, names, digest)) is not None}
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
                finished.save_rows(out, cond.name, done[cond.name], digest)  # kept now, whatever happens next
    except KeyboardInterrupt as err:  # Ctrl-C, or SIGTERM through _sigterm_interrupts
        signum = getattr(err, "signum", signal.SIGINT)
        message = (f"evaluate: stopped by {SIGNAL_NAMES.get(signum, f'signal {signum}')}; {len(done)} of "
                   f"{len(conditions)} conditions are kept in {out / finished.CONDITIONS_DIR}; run the same command "
                   "again (or add --resume) to finish the rest")
        print(message, flush=True)
        raise Interrupted(signum, message) from None
    rows = [row for cond in conditions for row in done[cond.name]]
    smoothing = {name: getattr(bundles[name], "touch_smoothing", 0.0) for name in touch_policies}
    touch_notes = [name + (f" (corrections smoothed over refreshes by {a:g})" if a else "")
                   for name, a in smoothing.items()]
    write_report(out, rows, dataclasses.replace(cfg, out=out), conditions, hand, touch_notes)
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
                                    on_episode=lambda: bar.update(1), touch_delay=cfg.delay)
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
