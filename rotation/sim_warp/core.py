"""The RotateCup task on MuJoCo Warp: N worlds of one model stepped on a GPU (or Warp's CPU device, for tests).

The counterpart of envs.core.RotateCupVec with the same contract (reset / step, observation groups, reward terms,
info keys, errors), but every array is a torch tensor on the device: the simulator's state is read and written
through zero-copy views of the Warp arrays (``wp.to_torch``), the task math is envs.task with ``xp = torch``, and
the random streams are envs.rng's, bit for bit (rotation.sim_warp.rng). Nothing is copied to the host.

Differences from the CPU core, all on purpose:

- resets are masks, not index lists, so that finished worlds restart on the device without the host waiting for
  the GPU (:meth:`reset_done`); ``reset(ids=...)`` still takes indices, like the CPU core;
- Warp simulates in float32 (the CPU core in float64), so the two agree to a tolerance, not bit for bit
  (tests/sim_warp/test_equivalence.py states it);
- no simulated touch: the Digit 360 model is CPU-only (``EnvConfig.tactile`` is refused).
"""

from __future__ import annotations

import numbers
from dataclasses import dataclass

import numpy as np
import torch

from envs import constants as C
from envs import task
from envs.config import EnvConfig
from envs.core import action_space, observation_space, task_model
from envs.grasp_cache import GraspCache, load_default_cache
from envs.scene import HANDS, OBJECT_BODY
from envs.validation import check_int, check_seed, check_types
from rotation.sim_warp.rng import TorchCounterRNG, env_keys

# Random streams: the same ids as envs.core, so both backends draw the same numbers for the same use.
_STREAM_RESET, _STREAM_NOISE, _STREAM_PUSH_P, _STREAM_PUSH_F = 1, 2, 3, 4

BATCHED_FIELDS = ("geom_size", "geom_pos", "geom_friction", "body_mass", "body_ipos", "body_inertia",
                  "actuator_gainprm", "actuator_biasprm",
                  # derived by set_const from the ones above, so they must be per world too
                  "body_subtreemass", "body_invweight0", "dof_invweight0", "geom_aabb", "geom_rbound",
                  "actuator_acc0")
"""Model fields with one value per world (put_model batch_sizes): the randomized ones and what they imply."""


@dataclass(frozen=True)
class WarpConfig:
    """Settings of the MuJoCo Warp backend (not of the task: that is envs.EnvConfig)."""

    device: str = "cuda"
    """Warp / torch device: 'cuda', 'cuda:<i>' or 'cpu' (Warp's CPU device: slow, for tests and CI)."""
    nconmax: int = 32
    """Contacts allocated per world on average (MuJoCo Warp pools them over worlds); the hand and cup make at
    most about 10 (measured on the CPU core, 32 envs x 100 random steps)."""
    njmax: int = 192
    """Constraint rows allocated per world: 6 per pyramidal condim-4 contact plus joint limits (at most 76
    measured, as above)."""
    cuda_graph: bool = True
    """Replay the physics substeps of a control step as one captured CUDA graph (GPU only)."""

    def __post_init__(self) -> None:
        check_types(self, "warp.")
        if not (self.device == "cpu" or self.device == "cuda" or self.device.startswith("cuda:")):
            raise ValueError(f"warp.device must be 'cuda', 'cuda:<index>' or 'cpu', got {self.device!r}")
        check_int("warp.nconmax", self.nconmax, 1, 4096)
        check_int("warp.njmax", self.njmax, 1, 65_536)


def physics_problem(cfg: EnvConfig) -> str | None:
    """Why this backend cannot simulate ``cfg``, or None when it can: the hardware physics of envs.physics (what the
    digit360_v4 and xela_v4 hands randomize) and MuJoCo's noslip solver run on the cpu backend only for now."""
    if task.uses_hardware_physics(cfg) or cfg.contact.noslip_iterations:
        return (f"the {cfg.hand} hand's physics (separate tip and link friction, joint friction, torque scale, action "
                "delay, randomized contact, the noslip solver: envs.physics) runs on the cpu backend only for now")
    return None


def simulated_hands() -> tuple[str, ...]:
    """The hand variants (envs.scene.HANDS) whose physics this backend simulates, with their default settings."""
    return tuple(hand for hand in HANDS if physics_problem(EnvConfig(hand=hand)) is None)


def import_warp():
    """(warp, mujoco_warp), or a ValueError that says how to install them."""
    try:
        import mujoco_warp
        import warp
    except ImportError as err:
        raise ValueError(f"the warp backend needs MuJoCo Warp ({err.name} is not installed): "
                         "pip install 'tactile-rotation[warp]'") from None
    return warp, mujoco_warp


def resolve_device(device: str) -> str:
    """A Warp device name for ``device``; ValueError when it names a GPU this machine does not have."""
    if device == "cpu":
        return "cpu"
    if not torch.cuda.is_available():
        raise ValueError(f"device {device!r}: no CUDA GPU is available (use --warp-device cpu for Warp's CPU "
                         "device, or the cpu backend)")
    return "cuda:0" if device == "cuda" else device


class RotateCupWarp:
    """N RotateCup worlds on MuJoCo Warp; observations, rewards and info are (N, ...) torch tensors on ``device``.

    World i of a batch seeded s draws the same parameters, grasp, pushes and noise as env i of an
    envs.core.RotateCupVec seeded s.
    """

    def __init__(self, cfg: EnvConfig | None = None, num_envs: int = 1, seed: int = 0,
                 warp_cfg: WarpConfig | None = None, grasps: GraspCache | None = None):
        self.cfg = cfg = cfg if cfg is not None else EnvConfig()
        if not isinstance(cfg, EnvConfig):
            raise ValueError(f"cfg must be an EnvConfig, got {type(cfg).__name__}")
        if not isinstance(num_envs, numbers.Integral) or isinstance(num_envs, bool):
            raise ValueError(f"num_envs must be an integer, got {type(num_envs).__name__} {num_envs!r}")
        if num_envs < 1:
            raise ValueError(f"num_envs must be >= 1, got {num_envs}")
        seed = check_seed("seed", seed)
        if cfg.tactile:
            raise ValueError("tactile: the simulated Digit 360 runs on the cpu backend only; use --backend cpu for "
                             "touch (the warp backend simulates proprioception and privileged info)")
        if getattr(cfg, "skin", False):
            raise ValueError("skin: the simulated Xela skin runs on the cpu backend only; use --backend cpu for it")
        problem = physics_problem(cfg)
        if problem is not None:
            raise ValueError(f"hand: {problem}; use --backend cpu")
        self.warp_cfg = wcfg = warp_cfg if warp_cfg is not None else WarpConfig()
        if not isinstance(wcfg, WarpConfig):
            raise ValueError(f"warp_cfg must be a WarpConfig, got {type(wcfg).__name__}")
        wp, mjw = import_warp()
        self._wp, self._mjw = wp, mjw
        wp.config.quiet = True
        wp.init()
        self.device = resolve_device(wcfg.device)
        self.num_envs = n = int(num_envs)
        self.model, self.obj, self.max_scale = task_model(cfg)
        m = self.model

        import mujoco  # the host model only seeds the device copies

        with wp.ScopedDevice(self.device):
            self.wm = mjw.put_model(m, batch_sizes=dict.fromkeys(BATCHED_FIELDS, n))
            # the solver and line search stop at the model's iteration limits silently, as MuJoCo does on the CPU;
            # real overflows (contacts, constraint rows) still warn
            overflow = mjw.OverflowType
            self.wm.opt.warn_overflow = int(overflow.ALL & ~(overflow.ITERATIONS | overflow.LS_ITERATIONS))
            host = mujoco.MjData(m)
            mujoco.mj_forward(m, host)
            self.wd = mjw.put_data(m, host, nworld=n, nconmax=wcfg.nconmax, njmax=wcfg.njmax)
            self._reset_flags = wp.zeros(n, dtype=wp.bool)
        self.torch_device = torch.device(self.device)
        self._cuda = self.torch_device.type == "cuda"
        if self._cuda:
            # torch and Warp on one stream: every torch op and Warp launch is ordered without host waits, and the
            # captured graph runs on a non-default stream (CUDA cannot capture the legacy default stream)
            torch.cuda.set_stream(wp.stream_to_torch(wp.get_stream(self.device)))
        self._graph = None

        # model indices
        self.obj_body = m.body(OBJECT_BODY).id
        self.obj_qpos = int(m.joint("object_free").qposadr[0])
        obj_geoms = np.flatnonzero(m.geom_bodyid == self.obj_body)
        dev, f32 = self.torch_device, torch.float32
        self._obj_geoms = torch.as_tensor(obj_geoms, device=dev)
        self._geom_size1 = torch.as_tensor(m.geom_size[obj_geoms] / self.max_scale, dtype=f32, device=dev)
        self._geom_pos1 = torch.as_tensor(m.geom_pos[obj_geoms] / self.max_scale, dtype=f32, device=dev)
        self._lower = torch.as_tensor(C.JOINT_LOWER, dtype=f32, device=dev)
        self._upper = torch.as_tensor(C.JOINT_UPPER, dtype=f32, device=dev)
        self._axis = torch.as_tensor(cfg.reward.axis, dtype=f32, device=dev)

        # zero-copy views of the Warp arrays (per-world model fields and live state)
        t = wp.to_torch
        wm, wd = self.wm, self.wd
        self._geom_size, self._geom_pos = t(wm.geom_size), t(wm.geom_pos)  # (N, ngeom, 3)
        self._geom_friction = t(wm.geom_friction)  # (N, ngeom, 3)
        self._body_mass, self._body_ipos = t(wm.body_mass), t(wm.body_ipos)  # (N, nbody), (N, nbody, 3)
        self._body_inertia = t(wm.body_inertia)  # (N, nbody, 3)
        self._gainprm, self._biasprm = t(wm.actuator_gainprm), t(wm.actuator_biasprm)  # (N, nu, 10)
        self._qpos, self._qvel, self._ctrl = t(wd.qpos), t(wd.qvel), t(wd.ctrl)  # (N, nq), (N, nv), (N, nu)
        self._xfrc = t(wd.xfrc_applied)  # (N, nbody, 6)
        self._act_force = t(wd.actuator_force)  # (N, nu)
        self._reset_mask = t(self._reset_flags)  # (N,) bool

        if grasps is None:  # the cache of the object (and of the hand variant, where the config names one)
            hand = {"hand": cfg.hand} if hasattr(cfg, "hand") else {}
            grasps = load_default_cache(cfg.object, cfg.grasp_cache, **hand)
        self._grasp_scales = torch.as_tensor(grasps.scales, dtype=torch.float64, device=dev)
        self._grasp_table = torch.as_tensor(grasps.grasps, dtype=f32, device=dev)  # (S, G, 23)
        self.rng = TorchCounterRNG(env_keys(seed, n, dev))
        self.episode = torch.full((n,), -1, dtype=torch.int64, device=dev)
        self.steps = torch.zeros(n, dtype=torch.int64, device=dev)
        self.targets = torch.zeros((n, C.NUM_JOINTS), dtype=f32, device=dev)
        self.grasp_q = torch.zeros((n, C.NUM_JOINTS), dtype=f32, device=dev)
        self.start_pos = torch.zeros((n, 3), dtype=f32, device=dev)
        self.push = torch.zeros((n, 3), dtype=f32, device=dev)
        self.params = {k: torch.zeros(s, dtype=f32, device=dev) for k, s in
                       (("scale", n), ("mass", n), ("friction", n), ("com", (n, 3)), ("kp", (n, 16)),
                        ("kd", (n, 16)))}
        self.history = torch.zeros((n, C.HISTORY_STEPS, C.PROPRIO_DIM), dtype=f32, device=dev)  # newest last
        self._needs_reset = True
        self.single_observation_space = observation_space(cfg)  # touch and skin are refused above
        self.single_action_space = action_space()

    # ------------------------------------------------------------------ API
    def reset(self, seed: int | None = None, ids=None) -> dict[str, torch.Tensor]:
        """Reset worlds ``ids`` (all by default; indices or an (N,) bool mask); a seed (0 .. 2**64 - 1) re-keys
        every world (world i gets seed + i) and resets all of them."""
        if seed is not None:
            self.rng = TorchCounterRNG(env_keys(check_seed("seed", seed), self.num_envs, self.torch_device))
            self.episode.fill_(-1)
            ids = None
        mask = torch.ones(self.num_envs, dtype=torch.bool, device=self.torch_device)
        if ids is not None:
            ids = torch.as_tensor(np.asarray(ids) if not isinstance(ids, torch.Tensor) else ids,
                                  device=self.torch_device)
            if ids.dtype != torch.bool:
                mask = torch.zeros_like(mask).index_fill_(0, ids.to(torch.int64), True)
            else:
                mask = ids
        self.reset_done(mask)
        self._needs_reset = False
        return self._observe()

    def reset_done(self, mask: torch.Tensor) -> None:
        """Start new episodes in the worlds where ``mask`` (N,) bool is set, entirely on the device."""
        cfg, n = self.cfg, self.num_envs
        self._reset_mask.copy_(mask)
        m1, m2, m3 = mask[:, None], mask[:, None, None], mask
        self.episode += mask.to(torch.int64)
        u = self.rng.uniform(self.episode, torch.zeros_like(self.steps), _STREAM_RESET, task.PARAM_DRAWS)
        p = task.sample_params(torch, cfg, u)  # float64, every world (the masked ones are used)
        f = {k: v.to(torch.float32) for k, v in p.items() if k != "bucket"}
        with self._wp.ScopedDevice(self.device):
            self._mjw.reset_data(self.wm, self.wd, reset=self._reset_flags)

        # per-world model fields (envs.core.EpisodeStarts.start)
        s = f["scale"][:, None, None]
        g = self._obj_geoms
        self._geom_size[:, g] = torch.where(m2, self._geom_size1[None] * s, self._geom_size[:, g])
        self._geom_pos[:, g] = torch.where(m2, self._geom_pos1[None] * s, self._geom_pos[:, g])
        fr = self._geom_friction[:, :, 0]
        self._geom_friction[:, :, 0] = torch.where(m1, f["friction"][:, None], fr)  # hand and object (Hora)
        b = self.obj_body
        self._body_mass[:, b] = torch.where(m3, f["mass"], self._body_mass[:, b])
        self._body_ipos[:, b] = torch.where(m1, f["com"], self._body_ipos[:, b])
        inertia = task.object_inertia(torch, self.obj.kind, self.obj.radius, self.obj.length, p["scale"], p["mass"])
        self._body_inertia[:, b] = torch.where(m1, inertia.to(torch.float32), self._body_inertia[:, b])
        gain, bias = self._gainprm.clone(), self._biasprm.clone()
        task.set_gains(gain, bias, f["kp"], f["kd"])
        self._gainprm.copy_(torch.where(m2, gain, self._gainprm))
        self._biasprm.copy_(torch.where(m2, bias, self._biasprm))
        with self._wp.ScopedDevice(self.device):
            groups = self._mjw.SetConstGroup.FIXED | self._mjw.SetConstGroup.INERT0
            self._mjw.set_const(self.wm, self.wd, groups=groups)
        for key in task.PARAM_KEYS:
            self.params[key] = torch.where(m1 if self.params[key].dim() == 2 else m3, f[key], self.params[key])

        # the grasp and the task state
        q, pose = task.pick_grasps(torch, self._grasp_scales, self._grasp_table, p["scale"], p["grasp_u"])
        o = self.obj_qpos
        self._qpos[:, : C.NUM_JOINTS] = torch.where(m1, q, self._qpos[:, : C.NUM_JOINTS])
        self._qpos[:, o : o + 7] = torch.where(m1, pose, self._qpos[:, o : o + 7])
        self._ctrl.copy_(torch.where(m1, q, self._ctrl))
        self.targets = torch.where(m1, q, self.targets)
        self.grasp_q = torch.where(m1, q, self.grasp_q)
        self.start_pos = torch.where(m1, pose[:, :3], self.start_pos)
        self.steps = torch.where(m3, 0, self.steps)
        self.push = torch.where(m1, 0.0, self.push)
        frame = task.proprio_frame(torch, q, q, self._lower, self._upper)  # (N, 32)
        self.history = torch.where(m2, frame[:, None, :].expand(n, C.HISTORY_STEPS, C.PROPRIO_DIM), self.history)

    def _observe(self) -> dict[str, torch.Tensor]:
        # each step and reset builds a new history tensor, so these views are never overwritten later
        pos = self._qpos[:, self.obj_qpos : self.obj_qpos + 3]
        return {"proprio": self.history[:, -C.PROPRIO_STEPS :], "proprio_hist": self.history,
                "priv": task.priv_vector(torch, pos, self.params).to(torch.float32)}

    def _physics(self) -> None:
        """``substeps`` MuJoCo Warp steps of every world (a captured graph on a GPU)."""
        wp, mjw = self._wp, self._mjw
        with wp.ScopedDevice(self.device):
            if not (self._cuda and self.warp_cfg.cuda_graph):
                for _ in range(self.cfg.substeps):
                    mjw.step(self.wm, self.wd)
                return
            if self._graph is None:
                with wp.ScopedCapture() as capture:
                    for _ in range(self.cfg.substeps):
                        mjw.step(self.wm, self.wd)
                self._graph = capture.graph
            wp.capture_launch(self._graph)

    def step(self, actions) -> tuple[dict[str, torch.Tensor], torch.Tensor, torch.Tensor, torch.Tensor, dict]:
        """Advance every world one policy step. Returns (obs, reward, terminated, truncated, info), all tensors on
        the device. No auto-reset here (see :meth:`reset_done` and rotation.sim_warp.vector)."""
        if self._needs_reset:
            raise RuntimeError("call reset() before step()")
        a = torch.as_tensor(actions, device=self.torch_device).to(torch.float32)
        if tuple(a.shape) != (self.num_envs, C.NUM_JOINTS):
            raise ValueError(f"actions must have shape ({self.num_envs}, {C.NUM_JOINTS}), got {tuple(a.shape)}")
        bad = ~torch.isfinite(a)
        if bool(bad.any()):  # one small host read per step: non-finite actions are refused, as on the CPU
            i, j = (int(v) for v in torch.nonzero(bad)[0])
            raise ValueError(f"actions must be finite; env {i} joint {j} is {float(a[i, j])}")
        cfg, rc = self.cfg, self.cfg.randomization
        self.targets = task.step_targets(torch, cfg, self.targets, a, self._lower, self._upper)
        self._ctrl.copy_(self.targets)

        # random pushes on the object (Hora): new with probability p, otherwise decaying
        if rc.enabled and rc.push_prob > 0:
            new = self.rng.uniform(self.episode, self.steps, _STREAM_PUSH_P, 1)[:, 0] < rc.push_prob
            normal = self.rng.normal(self.episode, self.steps, _STREAM_PUSH_F, 3)
            self.push = task.step_push(torch, cfg, self.push, new, normal, self.params["mass"]).to(torch.float32)
            self._xfrc[:, self.obj_body, :3] = self.push

        o = self.obj_qpos
        pos0 = self._qpos[:, o : o + 3].clone()
        quat0 = self._qpos[:, o + 3 : o + 7].clone()
        self._physics()
        qpos, qvel = self._qpos, self._qvel
        q, qdot = qpos[:, : C.NUM_JOINTS], qvel[:, : C.NUM_JOINTS]
        pos, quat = qpos[:, o : o + 3], qpos[:, o + 3 : o + 7]
        tau = self._act_force

        out = task.reward_and_termination(torch, cfg, q=q, qdot=qdot, tau=tau, qpos=qpos, qvel=qvel, pos0=pos0,
                                          quat0=quat0, pos=pos, quat=quat, grasp_q=self.grasp_q,
                                          start_pos=self.start_pos, axis=self._axis)
        self.steps = self.steps + 1
        terminated = out["fell"]
        truncated = (self.steps >= cfg.episode_steps) & ~terminated

        u = self.rng.uniform(self.episode, self.steps, _STREAM_NOISE, 16).to(torch.float32)
        seen = task.observed_joints(torch, cfg, q, self.grasp_q, out["finite"], u)
        frame = task.proprio_frame(torch, seen, self.targets, self._lower, self._upper)  # (N, 32)
        self.history = torch.cat([self.history[:, 1:], frame[:, None]], dim=1)  # (N, 30, 32), a new tensor
        info = task.step_info(torch, cfg, out, pos, tau, self.steps)
        return self._observe(), out["reward"], terminated, truncated, info

    def close(self) -> None:
        self._graph = None
