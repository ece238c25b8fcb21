"""Initial grasps: generation with Hora's acceptance rule and the hold check (the cache file: envs.grasp_cache).

Generation (docs/reference/hora.md "Grasp cache"): sample a canonical closed pose + U(-0.25, 0.25) rad per joint, start
with the fingers opened a little and the object floating at its nominal place, close the fingers on it, release
it under gravity, run 50 policy steps, and keep the grasp if all four fingertips are within 10 cm of the object
centre, at least two touch it, it did not fall, and (our additions for the upright-cup task) its up axis is within
`max_tilt` of vertical and, with a HoldRule, the grasp holds the object still by itself when the env resets into it.
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import mujoco
import mujoco.batch
import numpy as np

from envs import constants as C
from envs import task
from envs.config import EnvConfig, RandomizationConfig, default_randomization
from envs.constants import DEFAULT_HAND
from envs.core import EpisodeStarts, set_contact, set_torque_limits, task_model
from envs.errors import RequestRefused
from envs.geometry import tilt_angle
from envs.grasp_cache import GRASP_DIM, GraspCache
from envs.objects import ObjectSpec, get_object
from envs.scene import OBJECT_BODY, build_model, hand_variant, skin_geoms

DEFAULT_MAX_TILT = 0.15
"""Grasps must hold the object's up axis within this angle (rad, about 9 degrees) of vertical after settling:
the task is rotating an upright cup, and grasps that already lean 15-25 degrees tipped over under zero action in
about 40% of 10 s holds (with the default randomization and pushes)."""



def surface_distance(obj: ObjectSpec, scale: np.ndarray, pos: np.ndarray, quat: np.ndarray, points: np.ndarray):
    """Signed distance (m) from points (k, P, 3) to the object's main cylinder (k envs with pose and scale)."""
    rot = np.zeros((len(quat), 9))
    for i, qu in enumerate(quat):
        mujoco.mju_quat2Mat(rot[i], qu)
    rot = rot.reshape(-1, 3, 3)
    local = np.einsum("kji,kpj->kpi", rot, points - pos[:, None, :])  # (k, P, 3) in the object frame
    axis = 1 if obj.kind == "cylinder" else 2
    r, h = obj.radius * scale[:, None], obj.length * scale[:, None] / 2
    radial = np.linalg.norm(np.delete(local, axis, axis=2), axis=2) - r
    axial = np.abs(local[:, :, axis]) - h
    outside = np.sqrt(np.maximum(radial, 0) ** 2 + np.maximum(axial, 0) ** 2)
    return np.where((radial > 0) | (axial > 0), outside, np.maximum(radial, axial))


FLEX_JOINTS = [1, 2, 3, 5, 6, 7, 9, 10, 11, 13, 14, 15]
"""Joints that close the hand (all but the three finger abductions and the thumb rotation)."""


def _penetration(model: mujoco.MjModel, data: mujoco.MjData, q: np.ndarray, pos: np.ndarray, o: int) -> float:
    """Deepest contact distance (m, negative = penetration) of the hand at q with the object at pos."""
    data.qpos[:16] = q
    data.qpos[o : o + 3] = pos
    data.qpos[o + 3 : o + 7] = [1, 0, 0, 0]
    mujoco.mj_kinematics(model, data)
    mujoco.mj_collision(model, data)
    return min((data.contact[i].dist for i in range(data.ncon)), default=1.0)


def set_nominal_physics(model: mujoco.MjModel, cfg: EnvConfig) -> None:
    """Write ``cfg``'s contact model, torque limits and, for the hardware physics, the middles of its friction, joint
    friction, torque scale and contact ranges into ``model`` itself (in place): what a grasp is settled under, so
    that an episode starting from it does not first settle again."""
    m = model
    set_contact(m, cfg.contact)
    set_torque_limits(m, cfg)
    if not task.uses_hardware_physics(cfg):
        return
    p = {k: v[0] for k, v in task.nominal_hardware_params(cfg, 1).items()}
    rc = cfg.randomization
    tips = skin_geoms(m)  # the env's own split (envs.core.EpisodeStarts): the Xela pads are skin too
    obj = np.flatnonzero(m.geom_bodyid == m.body(OBJECT_BODY).id)
    tip_friction = float(np.mean(rc.friction))
    if "link_friction" in p:
        m.geom_friction[m.geom_contype > 0, 0] = p["link_friction"]
        m.geom_friction[tips, 0] = tip_friction
        m.geom_friction[obj, 0] = min(tip_friction, float(p["link_friction"]))
    if "joint_friction" in p:
        m.dof_frictionloss[: C.NUM_JOINTS] = p["joint_friction"]
    if "torque_scale" in p:
        m.actuator_forcerange[:] *= p["torque_scale"]
    if "impratio" in p:
        m.opt.impratio = p["impratio"]
    if "timeconst" in p:
        m.geom_solref[:, 0] = p["timeconst"]


HOLD_DROP = 0.02
"""How far (m) the object may sink below its grasped height during a hold check before it counts as dropped."""


@dataclass(frozen=True)
class HoldRule:
    """A grasp must hold the object still by itself: reset into the grasp as the env does (joint targets = the
    grasp's joints, so the fingers press no harder than the grasp's own contacts), hold still (zero action) for
    ``seconds`` with the env's physics at ``friction`` (hand and object) and object ``mass``, no pushes, the centre
    of mass in the middle and the nominal PD gains; keep the grasp if the object's tilt stays under ``max_tilt`` and
    it does not sink more than HOLD_DROP. Grasps that fail this start the policy from a cup that is already falling:
    of the cup grasps that passed Hora's rule alone, about a third tipped past 20 degrees or dropped within 3 s."""

    seconds: float = 3.0
    friction: float = float(np.mean(RandomizationConfig().friction))
    """Default: the middle of the randomization range (1.65), the nominal env's friction."""
    mass: float = float(np.mean(RandomizationConfig().mass))
    """Default (kg): the middle of the randomization range (0.13), the nominal env's mass."""
    max_tilt: float = 0.35
    """rad (about 20 degrees)."""
    surface: float = 1.0
    """The cup surface's factor on the friction of the domes (``friction``) and of the links together, as an
    evaluation's friction condition applies it (1: the hand's own materials; 0.25: grasps that hold a cup at a
    quarter of the friction)."""

    def as_array(self) -> np.ndarray:
        """What a cache records of the rule: seconds, friction, mass, max_tilt, and the surface where it is not 1
        (so the caches checked before the surface existed keep their record)."""
        return np.array([self.seconds, self.friction, self.mass, self.max_tilt]
                        + ([self.surface] if self.surface != 1.0 else []))

    @classmethod
    def for_hand(cls, hand: str, **changes) -> HoldRule:
        """The rule at a hand's nominal physics (the middle of its friction and mass ranges, envs.physics), with
        ``changes`` on top; on the shipped physics that is the default rule."""
        rc = default_randomization(hand)
        return replace(cls(friction=float(np.mean(rc.friction)), mass=float(np.mean(rc.mass))), **changes)


class HoldTest:
    """Runs HoldRule checks on batches of grasp rows of one object (the env's model, built once)."""

    def __init__(self, object_name: str, hand: str = DEFAULT_HAND, batch_size: int = 128, nthread: int | None = None):
        self.cfg = EnvConfig(object=object_name, hand=hand)
        model, obj, max_scale = task_model(self.cfg)
        self.batch_size = batch_size
        self.batch = mujoco.batch.Batch(model, batch_size, nthread or 0, persistent=True)
        self.starts = EpisodeStarts(self.batch, model, obj, max_scale)  # the env's own episode start

    def worst_tilt(self, rows: np.ndarray, scales: np.ndarray, rule: HoldRule) -> np.ndarray:
        """(k,) worst tilt (rad) of each row (k, 23) at its object scale (k,) under ``rule``; inf where the object
        sank more than HOLD_DROP or the state went non-finite. ``rule.surface`` scales the friction of the domes and
        of the links together, as an evaluation's friction perturbation does (envs.task.sample_params)."""
        rows, scales = np.asarray(rows, dtype=np.float64), np.asarray(scales, dtype=np.float64)
        n, cfg, st = self.batch_size, self.cfg, self.starts
        o, ids = st.obj_qpos, np.arange(n)
        steps = max(1, round(rule.seconds * cfg.control_hz))
        params = {"friction": np.full(n, rule.friction), "mass": np.full(n, rule.mass), "com": np.zeros((n, 3)),
                  "kp": np.full((n, C.NUM_JOINTS), cfg.kp), "kd": np.full((n, C.NUM_JOINTS), cfg.kd)}
        params.update(task.nominal_hardware_params(cfg, n))  # the hand's other parameters at their nominal values
        task.scale_surface(params, rule.surface)
        worst = np.zeros(len(rows))
        for first in range(0, len(rows), n):
            k = min(n, len(rows) - first)
            pad = np.r_[np.arange(first, first + k), np.full(n - k, first + k - 1)]  # repeat the last row
            chunk = rows[pad]
            st.start(ids, {**params, "scale": scales[pad]}, chunk[:, : C.NUM_JOINTS], chunk[:, C.NUM_JOINTS :])
            z0 = chunk[:, C.NUM_JOINTS + 2]
            tilt = np.zeros(n)
            for _ in range(steps):
                self.batch.step(nstep=cfg.substeps)
                pose = st.qpos[:, o : o + 7]
                t = tilt_angle(pose[:, 3:])
                t[(pose[:, 2] < z0 - HOLD_DROP) | ~np.all(np.isfinite(pose), axis=1)] = np.inf
                tilt = np.maximum(tilt, t)
            worst[first : first + k] = tilt[:k]
        return worst


def hold_check(cache: GraspCache, rule: HoldRule | None = None, batch_size: int = 128,
               nthread: int | None = None) -> np.ndarray:
    """Worst tilt (rad, (S, G)) of every cached grasp under ``rule`` (HoldRule; default: the rule at the cache's
    hand's nominal physics, HoldRule.for_hand); a grasp passes where it is below ``rule.max_tilt``."""
    rule = HoldRule.for_hand(cache.hand) if rule is None else rule
    s, g = cache.grasps.shape[:2]
    test = HoldTest(cache.object, cache.hand, batch_size, nthread)
    return test.worst_tilt(cache.grasps.reshape(s * g, GRASP_DIM), np.repeat(cache.scales, g), rule).reshape(s, g)


def generate_grasps(object_name: str, scales: tuple[float, ...], per_scale: int, seed: int = 0,
                    batch_size: int = 128, max_rounds: int = 200, noise: float = 0.25, nthread: int | None = None,
                    progress=None, max_tilt: float = DEFAULT_MAX_TILT, hand: str = DEFAULT_HAND,
                    hold: HoldRule | None = None) -> GraspCache:
    """Generate ``per_scale`` accepted grasps for each scale (see the module docstring for the rule); with ``hold``
    a grasp must also pass that HoldRule."""
    if per_scale < 1:
        raise ValueError(f"per_scale must be >= 1, got {per_scale}")
    obj = get_object(object_name)
    model = build_model(obj, max(scales), hand=hand)
    env_cfg = EnvConfig(object=object_name, hand=hand)
    mass = 0.1
    if task.uses_hardware_physics(env_cfg):  # settle the grasps under the physics the env starts them in
        set_nominal_physics(model, env_cfg)
    rng = np.random.default_rng(seed)
    batch = mujoco.batch.Batch(model, batch_size, nthread or 0, persistent=True)
    geom_size, geom_pos = batch.expand("geom_size"), batch.expand("geom_pos")
    body_mass = batch.expand("body_mass")
    obj_body = model.body(OBJECT_BODY).id
    obj_geoms = np.flatnonzero(model.geom_bodyid == obj_body)
    size1, pos1 = model.geom_size[obj_geoms] / max(scales), model.geom_pos[obj_geoms] / max(scales)
    qpos, qvel, ctrl, xfrc = batch.bind("qpos"), batch.bind("qvel"), batch.bind("ctrl"), batch.bind("xfrc_applied")
    tip_sites = [model.site(s).id for s in C.FINGERTIP_SITES]
    probe = mujoco.MjData(model)
    site_xpos = batch.bind("site_xpos")
    o = int(model.joint("object_free").qposadr[0])
    substeps = round(0.05 / model.opt.timestep)
    hold_test = HoldTest(object_name, hand, batch_size, nthread) if hold is not None else None
    variant = hand_variant(hand)
    canonical, centre, tip_radius = variant.canonical_pose, variant.object_start, variant.tip_radius
    out = []
    for scale in scales:
        accepted: list[np.ndarray] = []
        geom_size[:, obj_geoms] = size1[None] * scale
        geom_pos[:, obj_geoms] = pos1[None] * scale
        body_mass[:, obj_body] = mass
        batch.set_const()
        for _ in range(max_rounds):
            if len(accepted) >= per_scale:
                break
            pose = np.clip(canonical + rng.uniform(-noise, noise, (batch_size, 16)), C.JOINT_LOWER, C.JOINT_UPPER)
            start = centre + rng.uniform(-0.004, 0.004, (batch_size, 3))
            # open the fingers of samples that cut into the object until they only touch it
            clear = np.zeros(batch_size, dtype=bool)
            for i in range(batch_size):
                for _ in range(10):
                    if _penetration(model, probe, pose[i], start[i], o) > -0.004:
                        clear[i] = True
                        break
                    pose[i, FLEX_JOINTS] = np.maximum(pose[i, FLEX_JOINTS] - 0.05, C.JOINT_LOWER[FLEX_JOINTS])
            batch.reset(stage=mujoco.mjtStage.mjSTAGE_NONE)
            qp = qpos.copy()
            qp[:, :16] = pose
            qp[:, o : o + 3] = start
            qp[:, o + 3 : o + 7] = [1, 0, 0, 0]
            qpos[:] = qp
            qvel[:] = 0
            squeeze = pose.copy()
            squeeze[:, FLEX_JOINTS] += 0.3  # close further than the pose: the fingers close onto the object
            ctrl[:] = np.clip(squeeze, C.JOINT_LOWER, C.JOINT_UPPER)
            f = np.zeros(xfrc.shape)
            f[:, obj_body, 2] = mass * 9.81  # float the object while the fingers close
            xfrc[:] = f
            batch.forward()
            batch.step(nstep=6 * substeps)
            xfrc[:] = 0.0
            z0 = qpos[:, o + 2].copy()
            batch.step(nstep=50 * substeps)  # 50 policy steps under gravity
            batch.forward()
            pos, quat = qpos[:, o : o + 3], qpos[:, o + 3 : o + 7]
            tips = site_xpos[:, tip_sites]  # (B, 4, 3)
            near = np.linalg.norm(tips - pos[:, None], axis=2).max(axis=1) < 0.10
            touching = (surface_distance(obj, np.full(batch_size, scale), pos, quat, tips) < tip_radius + 0.004).sum(1)
            still = np.linalg.norm(qvel[:, 16:19], axis=1) < 0.05
            upright = tilt_angle(quat) < max_tilt
            ok = clear & near & (touching >= 2) & (pos[:, 2] > z0 - 0.02) & still & upright
            ok &= np.all(np.isfinite(qpos), axis=1)
            rows = np.concatenate([qpos[:, :16], qpos[:, o : o + 7]], axis=1)[ok]
            if hold_test is not None and len(rows):
                rows = rows[hold_test.worst_tilt(rows, np.full(len(rows), scale), hold) < hold.max_tilt]
            accepted.extend(rows)
            if progress is not None:
                progress(scale, len(accepted), per_scale)
        if len(accepted) < per_scale:
            raise RequestRefused(
                f"only {len(accepted)} of {per_scale} grasps accepted for {object_name} at scale {scale} after "
                f"{max_rounds} rounds of {batch_size}; the canonical pose may not fit this object"
                + (" or the hold check may be too strict for it" if hold is not None else "")
            )
        out.append(np.stack(accepted[:per_scale]))
    return GraspCache(object_name, np.asarray(scales), np.stack(out), seed, hand=hand,
                      hold=tuple(hold.as_array()) if hold is not None else ())
