"""Record demonstrations of the scripted expert: `rotate demos --task insertion --episodes 100 --out data/demos`.

Episode e (seed ``seed * 1_000_000 + e``: the socket's pose, the grasp and the expert's aim) of the insertion task
(envs.insertion) is played by the privileged expert (envs.insertion_expert) and written as one session file,
OUT/shard_<e // 100>/episode_<e>.h5 (rotation.data.session), at the 20 Hz control rate unless noted:

- ``camera/wrist`` (H, W, 3) uint8: the wrist camera's frame the action was chosen on;
- ``joints/position`` (16,) rad and ``wrist/pose`` (7,): the measured joints and the wrist target's offset from its
  start (position m, quaternion wxyz): the proprioception a policy reads;
- ``actions/wrist`` (6,): the expert's action (dx, dy, dz m; droll, dpitch, dyaw rad) on that frame;
- ``digit360/<finger>/contact`` (500 Hz): the fingertips' contact fields from the start of the plug's settling
  (t = 0; the first action at 1.2 s, so that its touch window has its 1.12 s of history), which the loader renders
  into the four Digit 360 streams; or, with ``--hand xela_v4``, the Xela skin from t = 0 at 100 Hz: ``skin/xela``
  (368, 3) raw counts and ``skin/taxel_pos`` (368, 3) taxel positions (m, hand frame), as `rotate collect --skin`
  records them (``extra["skin_key"]`` keys the simulated skin: its baseline);
- ``labels/socket`` (7,), ``labels/prong`` (7,), ``labels/depth`` (1,) m, ``labels/socket_force`` (1,) N:
  privileged state, for analysis and probes, never a policy's input.

With ``--noise-m`` / ``--noise-rad`` the wrist executes the expert's action plus Gaussian noise while the session
records the expert's own action on what that produced (noise injection, "DART": Laskey et al., CoRL 2017): the
demonstrations then hold the expert correcting the drifts, misaligned pushes and jams that a policy's own errors
lead to, which a clean expert seldom shows (experiments/insertion: 3 of 100 clean demonstrations ever press past
7.5 N). The noise of episode e is drawn from its own seed, so the same command records the same files.

With ``--policy`` an imitation policy (`rotate train-il`) drives the wrist while the expert, run alongside on the same
states, labels each of them (DAgger: Ross, Gordon and Bagnell, AISTATS 2011): a step executes the policy's action, or
with probability ``--beta`` the expert's, and the session records the expert's action on that frame. The
demonstrations then hold the expert's corrections in the states the policy itself reaches (a plug dragged beside the
hole, pressed too hard), which neither a clean expert nor its noise visits; training on them beside the first
demonstrations (`rotate train-il --demos` takes several folders) is the next round's policy. Give each round a
seed of its own; the files record the policy's bundle digest, and a rerun with other weights is refused.

The expert finds the hole by feel by default (``--expert-align feel``: after touching the plate it steps away from
where the socket presses on the prong, a moment on the held plug that the fingertips sense), so that what it does
follows from what a policy's touch can carry; ``--expert-align state`` slides to the hole's true centre, which
neither the camera nor touch shows (the first demonstrations, experiments/insertion).

The session's properties record the outcome (``success``, ``steps``, ``max_force``, ``lost``: the plug left the
grasp, ``retries``: the expert's back-offs after a jam, ``policy_steps``: the steps a --policy drove, ``slipped``:
a --policy episode ended because the plug moved ``slip_stop`` in the hand). A run that
stops keeps the finished episodes; running the same command again records the rest (an episode's file is complete or
recorded again). Other tasks follow as they are added.
"""

from __future__ import annotations

import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Literal

import numpy as np
from tqdm import tqdm

from envs.constants import FINGERS, NUM_JOINTS
from envs.plug_grip import FIRST_GRIP
from envs.validation import check_int, check_number, check_output_dir, check_seed, check_types
from envs.wrist_compliance import FIRST_WRIST
from rotation.configs import to_jsonable
from rotation.data.session import SessionMeta, StreamSetup
from rotation.data.session_writer import SessionWriter

SHARD_SIZE = 100


@dataclass(frozen=True)
class Config:
    task: Literal["insertion"] = "insertion"
    """The task to demonstrate."""
    hand: Literal["digit360_v4", "xela_v4"] = "digit360_v4"
    """The hand: Digit 360 fingertips, or the Xela skin (the benchmark's Sparsh-skin row)."""
    episodes: int = 100
    """Episodes (session files) to have in OUT when done."""
    out: Path = Path("data/demos")
    """Output directory."""
    seed: int = 0
    """Seed of the demonstrations (episode e is seeded seed * 1,000,000 + e)."""
    image_size: tuple[int, int] = (160, 120)
    """Wrist camera width and height (pixels)."""
    episode_steps: int = 300
    """Actions per episode at most (15 s at 20 Hz)."""
    noise_m: float = 0.0
    """Standard deviation (m) of the Gaussian noise added to each executed wrist translation, per axis (the recorded
    action stays the expert's; 0: none)."""
    noise_rad: float = 0.0
    """Standard deviation (rad) of the noise added to each executed wrist rotation, per axis."""
    expert_align: Literal["feel", "state"] = "feel"
    """How the scripted expert finds the hole after touching the plate: 'feel' steps away from where the socket
    presses on the prong (a correction touch can sense); 'state' slides to the hole's true centre (which no policy
    sees). envs.insertion_expert."""
    policy: str | None = None
    """An imitation policy bundle (`rotate train-il`, a folder or shipped name) that drives the wrist while the expert
    labels the states it reaches (DAgger; module docstring); None: the expert drives."""
    beta: float = 0.0
    """With --policy: the probability that a step executes the expert's action instead of the policy's."""
    slip_stop: float = 0.012
    """With --policy: end the episode once the plug has moved this far in the hand (m). The expert has no answer
    for a slipping grasp, and its near-still labels there taught a policy to hold still (experiments/insertion); its
    own seated demonstrations move the plug at most 10.5 mm (60 seeds). 0: run on to the env's own end."""
    grip: Literal["fingertips", "palm"] = "fingertips"
    """How the hand holds the plug: 'fingertips' (only the domes touch it, squeezed, so the socket's forces reach the
    sensors) or 'palm' (the cup's body on the phalanges; the first version's demonstrations). envs.plug_grip."""
    wrist: Literal["stiff", "compliant"] = "stiff"
    """How the arm moves the wrist: 'stiff' (jumps to each action's target, a stiff weld; the demonstrations recorded
    before the setting) or 'compliant' (moves there over the action and yields to the socket's forces, as an arm
    under admittance control). envs.wrist_compliance."""
    flush_interval_s: float = 2.0
    """Session writers flush at least this often (s)."""
    progress: bool = True
    """Show a progress bar."""

    def __post_init__(self) -> None:
        check_types(self)
        check_int("episodes", self.episodes, 1, 10**6)
        check_seed("seed", self.seed)
        check_output_dir("out", self.out)
        check_int("image_size width", self.image_size[0], 16, 640, "pixels")
        check_int("image_size height", self.image_size[1], 16, 480, "pixels")
        check_int("episode_steps", self.episode_steps, 1, 100_000)
        check_number("noise_m", self.noise_m, 0.0, 0.003, unit="m")
        check_number("noise_rad", self.noise_rad, 0.0, 0.05, unit="rad")
        check_number("flush_interval_s", self.flush_interval_s, 0.0, 3600.0, low_open=True, unit="s")
        check_number("beta", self.beta, 0.0, 1.0)
        check_number("slip_stop", self.slip_stop, 0.0, 0.06, unit="m")
        if self.policy is None and self.beta:
            raise ValueError("beta mixes the expert's actions into a policy's rollouts: give --policy")
        if self.policy is not None and (self.noise_m or self.noise_rad):
            raise ValueError("--noise-m/--noise-rad and --policy are two ways to reach states the expert would not: "
                             "use one")


def episode_path(out: Path, episode: int) -> Path:
    return Path(out) / f"shard_{episode // SHARD_SIZE:03d}" / f"episode_{episode:06d}.h5"


def demo_streams(image_size: tuple[int, int], control_hz: float, skin: bool = False) -> list[StreamSetup]:
    from envs.sensors.xela import SAMPLE_HZ

    w, h = image_size
    touch = ([StreamSetup(n, rate_hz=SAMPLE_HZ) for n in ("skin/xela", "skin/taxel_pos")] if skin else
             [StreamSetup(f"digit360/{f}/contact", rate_hz=500.0) for f in FINGERS])
    return [StreamSetup("camera/wrist", shape=(h, w, 3), rate_hz=control_hz),
            *(StreamSetup(n, rate_hz=control_hz) for n in ("joints/position", "wrist/pose", "actions/wrist",
                                                           "labels/socket", "labels/prong", "labels/depth",
                                                           "labels/socket_force")),
            *touch]


SAME_RUN = {"task": None, "seed": None, "image_size": None, "episode_steps": None, "hand": "digit360_v4",
            "noise_m": 0.0, "noise_rad": 0.0, "expert_align": "state", "grip": FIRST_GRIP, "policy": None,
            "beta": 0.0, "wrist": FIRST_WRIST}
"""Settings an episode's file must share with this run to be kept (complete) or recorded again (incomplete), with
the value a file recorded before the setting existed had."""


def _kept(cfg: Config, episode: int, policy_sha256: str | None = None) -> bool:
    """Whether episode ``episode``'s file is this run's (its settings and the driving policy's bundle digest) and
    complete (then kept); False when there is none or it is this run's unfinished one (recorded again). Any other
    file there is refused, never overwritten."""
    from envs.errors import RequestRefused
    from rotation.data.session import SessionError
    from rotation.data.session_reader import SessionReader
    from rotation.jobs.collect_resume import is_complete

    path = episode_path(cfg.out, episode)
    if not path.exists():
        return False
    try:
        with SessionReader(path) as r:
            extra = r.meta.extra
    except (SessionError, OSError) as err:
        raise RequestRefused(f"{path} is not a demonstration of this run ({err}); move it away or use another --out") \
            from None
    mine = to_jsonable(cfg)
    theirs = extra.get("demos") or {}
    if (extra.get("episode") != episode or any(theirs.get(k, old) != mine[k] for k, old in SAME_RUN.items())
            or extra.get("policy_sha256") != policy_sha256):
        raise RequestRefused(f"{path} holds another run's demonstration (episode {extra.get('episode')}, settings "
                             f"{ {k: theirs.get(k, old) for k, old in SAME_RUN.items()} }); use another --out")
    return is_complete(path)


def record_episode(cfg: Config, episode: int, grasps: Any, policy: Any = None, policy_sha256: str | None = None
                   ) -> dict[str, Any]:
    """Play and write episode ``episode`` (driven by ``policy``, an ILPolicy, where given); returns its outcome."""
    from envs.insertion import TIMESTEP, InsertionConfig, InsertionSim, draw_episode
    from envs.insertion_expert import ExpertConfig, InsertionExpert
    from envs.scene import touch_model
    from rotation.il.rollout import touch_windows

    icfg = InsertionConfig(hand=cfg.hand, image_size=cfg.image_size, episode_steps=cfg.episode_steps, grip=cfg.grip,
                           wrist=cfg.wrist)
    seed = cfg.seed * 1_000_000 + episode
    ep = draw_episode(icfg, seed, grasps)
    sim = InsertionSim(icfg, ep, grasps, render=True)
    expert = InsertionExpert(icfg, seed, ExpertConfig(align=cfg.expert_align))
    noise_rng = np.random.default_rng([seed, 0xDA27])  # the executed action's noise (DART), apart from the expert's
    noise_std = np.array([cfg.noise_m] * 3 + [cfg.noise_rad] * 3)
    mix_rng = np.random.default_rng([seed, 0xDA66])  # which steps execute the expert's action (DAgger's beta)
    policy_steps, slipped = 0, False
    if policy is not None:
        policy.reset()
    key = sim.touch_key
    meta_base = dict(source="sim", object="plug", control_hz=1.0 / icfg.control_dt, seed=seed)
    extra = {"episode": episode, "task": "insertion", "sim_hand": icfg.hand, "physics_dt": TIMESTEP,
             "insertion": to_jsonable(ep), "demos": to_jsonable(cfg), "policy_sha256": policy_sha256}
    if sim.skin is None:
        extra |= {"touch_key": key, "touch_generation": touch_model(icfg.hand).generation}
    else:
        from envs.sensors.xela import skin_metadata

        extra |= {"skin_key": key, "skin": skin_metadata()}
    path = episode_path(cfg.out, episode)
    frames: list[tuple] = []
    try:
        obs, info = sim.reset(), {"force": 0.0}
        settle = sim.contact.copy()  # the settling's contact fields, from t = 0: the first windows' history
        skin = [sim.skin.drain()] if sim.skin is not None else []  # its skin samples, from t = 0
        done = False
        while not done:
            action = expert.act(obs, info)
            t = sim.data.time
            frames.append((t, obs, action, info.get("force", 0.0)))
            executed = action + noise_std * noise_rng.standard_normal(6) if noise_std.any() else action
            if policy is not None:  # it acts on every step (its chunks' ensemble), executed unless beta draws
                driven = policy.act(obs, touch_windows(policy, sim, obs))
                if mix_rng.random() >= cfg.beta:
                    executed, policy_steps = driven, policy_steps + 1
            obs, done, info = sim.step(executed)
            if policy is not None and cfg.slip_stop and info["slip"] > cfg.slip_stop:
                done = slipped = True  # the grasp is going: nothing the expert labels from here is worth learning
            frames[-1] = (*frames[-1], sim.contact.copy(), t + np.arange(icfg.substeps) * TIMESTEP)
            if sim.skin is not None:
                skin.append(sim.skin.drain())
    finally:
        sim.close()
    outcome = {"success": bool(info["success"]), "steps": sim.steps, "max_force": float(info["max_force"]),
               "lost": bool(info["lost"]), "retries": expert.retries, "grasp_u": sim.grasp_u,
               "regrips": sim.regrips, "policy_steps": policy_steps, "slipped": slipped}
    meta = SessionMeta(**meta_base, properties=outcome, extra=extra)
    with SessionWriter(path, meta, demo_streams(cfg.image_size, 1.0 / icfg.control_dt, bool(skin)),
                       flush_interval_s=cfg.flush_interval_s, overwrite=True) as w:
        for t_skin, counts, pos in skin:
            if len(t_skin):
                w.append("skin/xela", counts, t_skin)
                w.append("skin/taxel_pos", pos, t_skin)
        t_settle = np.arange(settle.shape[1]) * TIMESTEP
        for f, finger in enumerate(FINGERS if not skin else ()):
            w.append(f"digit360/{finger}/contact", settle[f], t_settle)
        for t, o, action, force, rows, t_rows in frames:
            ts = np.array([t])
            w.append("camera/wrist", o["image"][None], ts)
            w.append("joints/position", o["joints"][None, :NUM_JOINTS].astype(np.float64), ts)
            w.append("wrist/pose", o["wrist"][None].astype(np.float64), ts)
            w.append("actions/wrist", np.asarray(action, np.float64)[None], ts)
            w.append("labels/socket", o["socket"][None].astype(np.float64), ts)
            w.append("labels/prong", o["prong"][None].astype(np.float64), ts)
            w.append("labels/depth", np.array([[float(o["depth"])]]), ts)
            w.append("labels/socket_force", np.array([[float(force)]]), ts)
            for f, finger in enumerate(FINGERS if not skin else ()):
                w.append(f"digit360/{finger}/contact", rows[f], t_rows)
    return outcome


def _driving_policy(cfg: Config) -> tuple[Any, str | None]:
    """The imitation policy of ``--policy`` and its bundle digest, (None, None) without one; refused where it was
    trained on another hand, grip, wrist or camera size than this run records."""
    if cfg.policy is None:
        return None, None
    from rotation.il.bundle import load_il
    from rotation.il.rollout import bundle_digest

    policy = load_il(cfg.policy)
    size = tuple(policy.model.cfg.image_size)
    for what, flag, theirs, mine in (("hand", "hand", policy.hand, cfg.hand), ("grip", "grip", policy.grip, cfg.grip),
                                     ("wrist", "wrist", policy.wrist, cfg.wrist),
                                     ("camera size", "image-size", size, tuple(cfg.image_size))):
        if theirs != mine:
            raise ValueError(f"policy: {cfg.policy} was trained with the {what} {theirs}, this run records {mine}; "
                             f"give the same --{flag}")
    return policy, bundle_digest(cfg.policy)


def run(cfg: Config) -> dict[str, Any]:
    """Record every episode OUT does not hold complete yet; returns the counts."""
    from envs.grasp_cache import load_default_cache

    grasps = load_default_cache("cup", "", cfg.hand)
    policy, digest = _driving_policy(cfg)
    todo = [e for e in range(cfg.episodes) if not _kept(cfg, e, digest)]
    if not todo:
        print(f"demos: {cfg.out} already holds {cfg.episodes} complete demonstrations")
        return {"episodes": 0, "successes": 0}
    successes, t0 = 0, time.perf_counter()
    with tqdm(todo, unit="episode", desc="demos", disable=not cfg.progress, dynamic_ncols=True) as bar:
        for e in bar:
            successes += record_episode(cfg, e, grasps, policy, digest)["success"]
            bar.set_postfix(success=f"{successes}/{bar.n + 1}")
    elapsed = time.perf_counter() - t0
    print(f"demos: {len(todo)} insertion demonstrations ({successes} seated) in {elapsed:.0f} s -> {cfg.out}")
    return {"episodes": len(todo), "successes": successes, "wall_s": elapsed}
