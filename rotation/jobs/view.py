"""Render the hand holding an object: a still of one grasp (PNG) or a short rollout (MP4), headless.

    rotate view --object cup --out cup.png
    rotate view --object cup --out cup.mp4 --steps 100 --policy random
    rotate view --object cup --out cup.mp4 --policy student --steps 400

Rendering is MuJoCo's offscreen OpenGL; on a machine without a display it uses EGL (MUJOCO_GL=egl, set by `rotate`
when nothing else is chosen). `--policy` is `zero` (hold still), `random` (uniform actions) or a policy bundle
(a shipped name such as `student`, or a bundle directory).
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Literal

import imageio.v2 as imageio
import numpy as np

from envs.config import EnvConfig, default_randomization
from envs.constants import DEFAULT_HAND
from envs.core import RotateCupVec
from envs.objects import OBJECTS
from envs.render import offscreen_renderer, render_frame
from envs.validation import check_int, check_optional_file, check_output_file, check_seed, check_types

MAX_WIDTH, MAX_HEIGHT = 640, 480
"""MuJoCo's default offscreen framebuffer (the hand model sets no larger one): the largest frames it renders."""


@dataclass
class Config:
    out: Path = Path("view.png")
    """Output file: .png for a still of the reset grasp, .mp4 (or .gif) for a rollout."""
    object: str = "cup"
    """Object name (envs.objects.OBJECTS)."""
    seed: int = 0
    """Env seed: picks the randomized scale, mass, friction and the grasp from the cache."""
    steps: int = 100
    """Policy steps of the rollout (video only); 20 steps = 1 s."""
    policy: str = "random"
    """'zero', 'random', or a policy bundle (shipped name or directory), for videos."""
    camera: str = "front"
    """Camera name in the hand model: front, side or top."""
    width: int = 480
    """Frame width (pixels)."""
    height: int = 480
    """Frame height (pixels)."""
    grasp_cache: str = ""
    """Grasp cache file; empty = the one shipped for the object."""
    randomize: bool = True
    """Domain randomization on (as in training)."""
    hand: Literal["digit360", "xela", "digit360_v4", "xela_v4"] = DEFAULT_HAND
    """Hand variant of a still or of a 'zero' / 'random' video (envs.scene.HANDS); a policy's video runs on the hand
    the policy was trained on."""

    def __post_init__(self) -> None:
        check_types(self)
        self.out = Path(self.out)
        if self.out.suffix.lower() not in (".png", ".mp4", ".gif"):
            raise ValueError(f"out must end in .png, .mp4 or .gif, got {self.out}")
        check_output_file("out", self.out)
        if self.object not in OBJECTS:
            raise ValueError(f"object: unknown object {self.object!r}; known objects: {', '.join(sorted(OBJECTS))}")
        check_seed("seed", self.seed)
        check_int("steps", self.steps, 1, 100_000)
        if not self.policy:
            raise ValueError("policy: give 'zero', 'random' or a policy bundle (shipped name or directory)")
        check_int("width", self.width, 16, MAX_WIDTH, "pixels (MuJoCo's default offscreen framebuffer)")
        check_int("height", self.height, 16, MAX_HEIGHT, "pixels (MuJoCo's default offscreen framebuffer)")
        check_optional_file("grasp_cache", self.grasp_cache, "generate one with `rotate grasps`")


def _load_bundle(cfg: Config):
    """The policy bundle a video acts with, or None ('zero', 'random', or a still that needs no policy)."""
    if cfg.policy in ("zero", "random") or cfg.out.suffix.lower() == ".png":
        return None
    from rotation.bundles import load_bundle

    return load_bundle(cfg.policy)


def env_config(cfg: Config, bundle) -> EnvConfig:
    """The env to render; with a bundle, at the control rate and action scale it was trained at (as evaluate does)."""
    timing = {} if bundle is None else dict(control_hz=bundle.config.control_hz,
                                            action_scale=bundle.config.action_scale)
    touch = dict(bundle.env_needs) if getattr(bundle, "touch_every", 0) else {}  # a tactile adapter: its touch
    if bundle is None:
        hand = touch.pop("hand", cfg.hand)
    else:
        from rotation.bundles import check_policy_hand, policy_hand

        hand = touch.pop("hand", policy_hand(bundle))
        check_policy_hand(f"--policy {cfg.policy}", bundle, hand)
    return EnvConfig(object=cfg.object, grasp_cache=cfg.grasp_cache, hand=hand,
                     randomization=default_randomization(hand, cfg.randomize), **touch, **timing)


def _actor(cfg: Config, bundle):
    if cfg.policy == "zero":
        return lambda obs: np.zeros((1, 16))
    if cfg.policy == "random":
        rng = np.random.default_rng(cfg.seed)
        return lambda obs: rng.uniform(-1.0, 1.0, (1, 16))
    from rotation.policy.bundle import combined_correction

    line = None
    if getattr(bundle, "touch_every", 0):  # a tactile adapter: refresh its correction as evaluate and deploy do
        from adapters.touch_delay import DelayLine, parse_delay
        from rotation.evaluate.rollout import touch_correction

        line = DelayLine(1, bundle.config.latent_dim, bundle.touch_every, parse_delay("0"), [cfg.seed],
                         bundle.touch_smoothing)
    state = {"k": 0}

    def act(obs):
        groups = {key: obs[key] for key in bundle.config.obs_groups}
        touch = (None if line is None else
                 line.step(state["k"], np.arange(1), lambda ids: touch_correction(bundle, obs, groups)))
        correction = combined_correction(touch, bundle.start_correction(state["k"]))  # a cautious start under touch
        state["k"] += 1
        return bundle.act_batch(groups, correction=correction)

    return act


def run(cfg: Config) -> Path:
    suffix = cfg.out.suffix.lower()
    bundle = _load_bundle(cfg)  # before the env: the env runs at the bundle's rate and scale
    env = RotateCupVec(env_config(cfg, bundle), num_envs=1, seed=cfg.seed, nthread=1)
    cameras = [env.model.camera(i).name for i in range(env.model.ncam)]
    if cfg.camera not in cameras:
        raise ValueError(f"unknown camera {cfg.camera!r}; cameras: {', '.join(cameras)}")
    obs = env.reset(seed=cfg.seed)
    renderer = offscreen_renderer(env.model, cfg.height, cfg.width, "rotate view")
    cfg.out.parent.mkdir(parents=True, exist_ok=True)
    try:
        if suffix == ".png":
            imageio.imwrite(cfg.out, render_frame(renderer, env, 0, cfg.camera))
            print(f"wrote {cfg.out}")
            return cfg.out
        act = _actor(cfg, bundle)
        frames, total, fell_at = [render_frame(renderer, env, 0, cfg.camera)], 0.0, None
        for t in range(cfg.steps):
            obs, _, terminated, truncated, info = env.step(act(obs))
            total += float(info["rotation"][0])
            frames.append(render_frame(renderer, env, 0, cfg.camera))
            if terminated[0] or truncated[0]:
                fell_at = t + 1 if terminated[0] else None
                break
        fps = int(round(env.cfg.control_hz))
        if suffix == ".gif":
            imageio.mimsave(cfg.out, frames, duration=1000.0 / fps)  # ms per frame (imageio's pillow plugin)
        else:
            imageio.mimsave(cfg.out, frames, fps=fps, macro_block_size=8)
    finally:
        renderer.close()
    status = f"fell after {fell_at} steps" if fell_at else "held"
    print(f"wrote {cfg.out}: {len(frames) - 1} steps, object rotated {total:+.2f} rad, {status}")
    return cfg.out
