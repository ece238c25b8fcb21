"""The RotateCup task definition, written once for both physics backends.

Every function here takes the array namespace ``xp`` as its first argument: the ``numpy`` module for the CPU core
(envs.core, float64 arrays) or the ``torch`` module for the MuJoCo Warp core (rotation.sim_warp, tensors on the
device). The bodies use only the vocabulary both provide under the same names (``where``, ``clip``, ``abs``,
``sqrt``, ``arctan2``, ``arccos``, ``stack(..., axis=)``, ``concatenate(..., axis=)``, ``.sum(-1)``, ``@``); the
two gaps (a constant on the right device, an integer cast) go through :func:`const` and :func:`to_int`. This
module never imports torch: the namespace comes in as an argument (docs/warp.md, "Design notes").

What lives here: the randomization of the physical parameters (ranges from envs.config), the action -> target
rule, Hora's pushes, the reward terms, the termination rule, the privileged vector and the proprioceptive frame.
The physics cores only move arrays in and out of their simulators.
"""

from __future__ import annotations

import dataclasses
from types import ModuleType
from typing import Any

import numpy as np

from envs.config import EnvConfig
from envs.geometry import angular_velocity, tilt_angle
from envs.physics import OPTIONAL_RANGES

Array = Any
"""A numpy array or a torch tensor; every argument of one call lives in the same namespace and device."""

PUSH_DECAY_PERIOD = 0.08
"""Hora decays pushes by `push_decay` every 0.08 s."""
PARAM_DRAWS = 40
"""Uniform draws per env and reset: scale bucket, jitter, mass, CoM (3), friction, kp (16), kd (16), grasp row."""
PARAM_KEYS = ("scale", "mass", "friction", "com", "kp", "kd")
"""Physical parameters of one episode, what `params` holds and `priv` reports (with the object position)."""
PHYS_DRAWS = 23
"""Uniform draws per env and reset for the hardware physics' parameters (their own stream, so the shipped physics'
draws never move): link friction, joint friction (16), torque scale, action delay, impratio, contact time
constant, noslip dropout, surface friction factor. Column j of a draw does not depend on how many are drawn
(envs.rng), so adding one at the end leaves every earlier episode's draws as they were."""
PHYS_KEYS = ("link_friction", "joint_friction", "torque_scale", "delay", "impratio", "timeconst", "noslip")
"""The hardware physics' per-episode parameters (present only where the randomization config sets them)."""


def uses_hardware_physics(cfg: EnvConfig) -> bool:
    """Whether ``cfg`` randomizes any of the hardware physics' parameters (envs.physics.OPTIONAL_RANGES)."""
    rc = cfg.randomization
    return rc.noslip_dropout > 0 or any(getattr(rc, name) is not None for name in OPTIONAL_RANGES)


# ---------------------------------------------------------------------------------------------------------- helpers
def const(xp: ModuleType, values: Any, like: Array) -> Array:
    """``values`` as an array of ``like``'s namespace, dtype and device (numpy: float64 on the host)."""
    if xp is np:
        return np.asarray(values, dtype=like.dtype)
    return xp.as_tensor(values, dtype=like.dtype, device=like.device)


def to_int(xp: ModuleType, x: Array) -> Array:
    """Truncate to int64 (floor for the non-negative values used here)."""
    return x.astype(np.int64) if xp is np else x.to(xp.int64)


# ---------------------------------------------------------------------------------------------------- randomization
def sample_params(xp: ModuleType, cfg: EnvConfig, u: Array, u_phys: Array | None = None) -> dict[str, Array]:
    """Physical parameters of k episodes from (k, PARAM_DRAWS) uniform draws in [0, 1).

    Returns ``scale`` (k,), ``bucket`` (k,) int64 index into ``randomization.scales``, ``mass`` (k,) kg, ``com``
    (k, 3) m, ``friction`` (k,), ``kp`` / ``kd`` (k, 16) and ``grasp_u`` (k,) (picks the grasp row), with the
    evaluation perturbation applied on top; with (k, PHYS_DRAWS) draws ``u_phys`` also the hardware physics'
    parameters (sample_hardware_params).
    """
    rc = cfg.randomization

    def lerp(lo_hi, x):
        return lo_hi[0] + (lo_hi[1] - lo_hi[0]) * x

    scales = const(xp, rc.scales, u)
    zero = u[:, 0] * 0.0  # (k,) zeros of the right namespace, dtype and device
    if rc.enabled:
        bucket = xp.clip(to_int(xp, u[:, 0] * len(rc.scales)), None, len(rc.scales) - 1)
        scale = scales[bucket] + (2 * u[:, 1] - 1) * rc.scale_jitter
        friction = (rc.friction[0] * (rc.friction[1] / rc.friction[0]) ** u[:, 6] if rc.friction_log
                    else lerp(rc.friction, u[:, 6]))
        p = dict(scale=scale, bucket=bucket, mass=lerp(rc.mass, u[:, 2]), com=lerp(rc.com, u[:, 3:6]),
                 friction=friction, kp=lerp(rc.kp, u[:, 7:23]), kd=lerp(rc.kd, u[:, 23:39]))
    else:
        bucket = to_int(xp, zero) + len(rc.scales) // 2
        p = dict(scale=scales[bucket], bucket=bucket, mass=zero + float(np.mean(rc.mass)), com=u[:, 3:6] * 0.0,
                 friction=zero + float(np.mean(rc.friction)), kp=u[:, 7:23] * 0.0 + cfg.kp,
                 kd=u[:, 23:39] * 0.0 + cfg.kd)
    if u_phys is not None:
        p.update(sample_hardware_params(xp, cfg, u_phys))
    pert = cfg.perturb
    # the cup's surface (a training draw) and the evaluation's friction scale
    scale_surface(p, p.pop("surface_friction", 1.0) * pert.friction_scale)
    p["mass"] = p["mass"] + pert.added_mass
    p["com"] = p["com"] + const(xp, pert.com_shift, u)
    p["grasp_u"] = u[:, 39]
    return p


def scale_surface(p: dict[str, Array], scale) -> None:
    """Scale the friction of the cup's surface in ``p`` in place: the domes' (``friction``) and the links'
    (``link_friction``, where the hand has its own) together, as a slippery or grippy cup changes both."""
    p["friction"] = p["friction"] * scale
    if "link_friction" in p:
        p["link_friction"] = p["link_friction"] * scale


def sample_hardware_params(xp: ModuleType, cfg: EnvConfig, u: Array) -> dict[str, Array]:
    """The hardware physics' parameters of k episodes from (k, PHYS_DRAWS) uniform draws, for the ranges the
    randomization sets (envs.physics.RandomizationConfig; without randomization each range's middle, noslip on):
    ``link_friction`` (k,), ``joint_friction`` (k, 16) N m, ``torque_scale`` (k,), ``delay`` (k,) whole physics
    steps, ``impratio`` (k,), ``timeconst`` (k,) s, ``noslip`` (k,) 1.0 where the episode runs the noslip solver,
    ``surface_friction`` (k,) the cup surface's factor, 1 on the episodes past ``surface_share`` (sample_params folds
    it into both frictions)."""
    rc = cfg.randomization
    if not rc.enabled:
        u = u * 0.0 + 0.5  # the middle of every range
    p: dict[str, Array] = {}

    def draw(lo_hi, x, log=False):
        lo, hi = float(lo_hi[0]), float(lo_hi[1])
        return lo * (hi / lo) ** x if log else lo + (hi - lo) * x

    if rc.link_friction is not None:
        p["link_friction"] = draw(rc.link_friction, u[:, 0])
    if rc.joint_friction is not None:
        p["joint_friction"] = draw(rc.joint_friction, u[:, 1:17])
    if rc.torque_scale is not None:
        p["torque_scale"] = draw(rc.torque_scale, u[:, 17])
    if rc.action_delay is not None:  # whole physics steps, at most one control step less one
        steps = to_int(xp, draw(rc.action_delay, u[:, 18]) / cfg.physics_dt + 1e-9)
        p["delay"] = xp.clip(steps, 0, cfg.substeps - 1)
    if rc.impratio is not None:
        p["impratio"] = draw(rc.impratio, u[:, 19], log=True)
    if rc.contact_timeconst is not None:
        p["timeconst"] = draw(rc.contact_timeconst, u[:, 20])
    if rc.surface_friction is not None and rc.enabled:
        share = rc.surface_share  # below the share the draw, rescaled to [0, 1), picks the factor; above it: 1
        p["surface_friction"] = xp.where(u[:, 22] < share, draw(rc.surface_friction, u[:, 22] / share, log=True), 1.0)
    if rc.noslip_dropout > 0:
        p["noslip"] = (u[:, 21] >= rc.noslip_dropout) * 1.0 if rc.enabled else u[:, 21] * 0.0 + 1.0
    return p


def nominal_hardware_params(cfg: EnvConfig, n: int) -> dict[str, np.ndarray]:
    """The hardware physics' parameters of ``n`` episodes at the middles of their ranges (sample_hardware_params
    without randomization; numpy); {} on the shipped physics."""
    if not uses_hardware_physics(cfg):
        return {}
    nominal = dataclasses.replace(cfg, randomization=dataclasses.replace(cfg.randomization, enabled=False))
    return sample_hardware_params(np, nominal, np.zeros((n, PHYS_DRAWS)))


def object_inertia(xp: ModuleType, kind: str, radius: float, length: float, scale: Array, mass: Array) -> Array:
    """(k, 3) diagonal inertia (kg m^2) of a solid cylinder about the body frame: the axis is y for Hora's
    cylinders and z for cups."""
    r, h = radius * scale, length * scale
    i_axis, i_perp = 0.5 * mass * r**2, mass * (3 * r**2 + h**2) / 12.0
    cols = [i_perp, i_perp, i_perp]
    cols[1 if kind == "cylinder" else 2] = i_axis
    return xp.stack(cols, axis=1)


def set_gains(gainprm: Array, biasprm: Array, kp: Array, kd: Array) -> None:
    """Write PD gains into actuator parameters (in place): force = kp * ctrl - kp * q - kd * qdot (MuJoCo's
    position actuator with kv)."""
    gainprm[..., 0] = kp
    biasprm[..., 1] = -kp
    biasprm[..., 2] = -kd


def pick_grasps(xp: ModuleType, table_scales: Array, table: Array, scale: Array, u: Array) -> tuple[Array, Array]:
    """Grasp rows for envs with the given scales: the nearest cached bucket, row ``floor(u * G)``.

    ``table_scales`` (S,), ``table`` (S, G, 23); returns q (k, 16) and the object pose (k, 7)."""
    b = xp.abs(table_scales[None, :] - scale[:, None]).argmin(1)  # nearest cached bucket
    g = xp.clip(to_int(xp, u * table.shape[1]), None, table.shape[1] - 1)
    rows = table[b, g]  # (k, 23)
    return rows[:, :16] * 1.0, rows[:, 16:] * 1.0  # copies


# ---------------------------------------------------------------------------------------------------------- control
def step_targets(xp: ModuleType, cfg: EnvConfig, targets: Array, actions: Array, lower: Array, upper: Array) -> Array:
    """New joint targets: actions clipped to [-1, 1] move them by action_scale rad, clamped to the joint limits."""
    a = xp.clip(actions, -1.0, 1.0)
    return xp.clip(targets + a * cfg.action_scale, lower, upper)


def step_push(xp: ModuleType, cfg: EnvConfig, push: Array, new: Array, normal: Array, mass: Array) -> Array:
    """Hora's random pushes: where ``new`` (N,) a fresh force N(0, 1) x mass x push_scale per axis, otherwise the
    old one decayed by push_decay per 0.08 s. ``normal`` (N, 3) standard normal draws."""
    rc = cfg.randomization
    force = normal * (mass * rc.push_scale)[:, None]
    return xp.where(new[:, None], force, push * rc.push_decay ** (cfg.control_dt / PUSH_DECAY_PERIOD))


# ------------------------------------------------------------------------------------------------ reward and ending
def reward_and_termination(xp: ModuleType, cfg: EnvConfig, *, q: Array, qdot: Array, tau: Array, qpos: Array,
                           qvel: Array, pos0: Array, quat0: Array, pos: Array, quat: Array, grasp_q: Array,
                           start_pos: Array, axis: Array) -> dict[str, Any]:
    """One policy step's reward terms and termination from the state before (pos0, quat0) and after it.

    Returns ``terms`` (name -> (N,) scaled term), ``reward`` (N,) (0 for a non-finite simulation), ``fell`` (N,)
    bool, ``finite`` (N,) bool, ``spin`` (N,) rad/s about ``axis``, ``lin_vel`` (N, 3) m/s, ``tilt`` (N,) rad.
    """
    dt = cfg.control_dt
    omega = angular_velocity(quat0, quat, dt, xp)  # (N, 3), measured once per policy step (Hora v0.0.2)
    spin = omega @ axis
    lin_vel = (pos - pos0) / dt
    rw = cfg.reward
    terms = {
        "rotate": rw.rotate * xp.clip(spin, -rw.rotate_back_clip, rw.rotate_clip),
        "obj_linvel": rw.obj_linvel * xp.abs(lin_vel).sum(-1),
        "pose_diff": rw.pose_diff * ((q - grasp_q) ** 2).sum(-1),
        "torque": rw.torque * (tau**2).sum(-1),
        "work": rw.work * (tau * qdot).sum(-1) ** 2,
    }
    tilt = tilt_angle(quat, xp)
    terms["tilt"] = rw.tilt * tilt**2
    finite = xp.isfinite(qpos).all(1) & xp.isfinite(qvel).all(1)
    # fell: dropped below the grasp, left the hand in any direction (e.g. flicked away), or tipped over
    d = pos - start_pos
    away = xp.sqrt((d * d).sum(-1)) > cfg.max_distance
    fell = (pos[:, 2] < start_pos[:, 2] - cfg.fall_drop) | away | (tilt > cfg.max_tilt) | ~finite
    terms["fall"] = rw.fall * fell
    reward = sum(terms.values())
    reward = xp.where(finite, reward, 0.0)
    return dict(terms=terms, reward=reward, fell=fell, finite=finite, spin=spin, lin_vel=lin_vel, tilt=tilt)


def step_info(xp: ModuleType, cfg: EnvConfig, out: dict[str, Any], pos: Array, tau: Array,
              steps: Array) -> dict[str, Array]:
    """The step's ``info``: each scaled reward term as ``rew_<term>`` and the diagnostics (docs/CONTRACTS.md)."""
    info = {f"rew_{k}": v for k, v in out["terms"].items()}
    lin_vel = out["lin_vel"]
    info.update(
        rotation=out["spin"] * cfg.control_dt,
        height=pos[:, 2] * 1.0,
        tilt=xp.where(out["finite"], out["tilt"], np.pi),
        lin_vel=xp.sqrt((lin_vel * lin_vel).sum(-1)),
        torque=xp.abs(tau).mean(1),
        fell=out["fell"],
        elapsed_steps=steps * 1,
    )
    return info


# ----------------------------------------------------------------------------------------------------- observation
def observed_joints(xp: ModuleType, cfg: EnvConfig, q: Array, grasp_q: Array, finite: Array, u: Array) -> Array:
    """Joint positions as the policy sees them: the grasp pose for a non-finite simulation, plus the observation
    noise U(-joint_noise, joint_noise) rad from uniform draws ``u`` (N, 16) when randomization is on."""
    rc = cfg.randomization
    seen = xp.where(finite[:, None], q, grasp_q)
    if rc.enabled:
        seen = seen + (2.0 * u - 1.0) * rc.joint_noise
    return seen


def proprio_frame(xp: ModuleType, q: Array, targets: Array, lower: Array, upper: Array) -> Array:
    """(N, 16) joint positions and targets (rad) -> (N, 32) frame: positions scaled to [-1, 1] by the joint limits
    (envs.constants.scale_joints), then the targets in radians."""
    return xp.concatenate([2.0 * (q - lower) / (upper - lower) - 1.0, targets], axis=-1)


def priv_vector(xp: ModuleType, pos: Array, params: dict[str, Array]) -> Array:
    """(N, 9) privileged vector in envs.constants.PRIV_FIELDS order: object position, scale, mass, friction, CoM."""
    return xp.concatenate([pos, params["scale"][:, None], params["mass"][:, None], params["friction"][:, None],
                           params["com"]], axis=1)
