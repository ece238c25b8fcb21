"""Initial grasps: generation with Hora's acceptance rule, a cache file, and sampling at reset.

Generation (reference/hora.md "Grasp cache"): sample a canonical closed pose + U(-0.25, 0.25) rad per joint, start
with the fingers opened a little and the object floating at its nominal place, close the fingers on it, release
it under gravity, run 50 policy steps, and keep the grasp if all four fingertips are within 10 cm of the object
centre, at least two touch it, it did not fall, and (our additions for the upright-cup task) its up axis is within
`max_tilt` of vertical and, with a HoldRule, the grasp holds the object still by itself when the env resets into it.
A cached row is 16 joint positions + 7 object pose numbers.

The cache file (.npz) holds `object` (name), `scales` (S,), `grasps` (S, G, 23) and `seed`; one bucket per
randomization scale. Reset picks the bucket of the env's scale and a row uniformly.
"""

from __future__ import annotations

import math
import zipfile
import zlib
from dataclasses import dataclass
from pathlib import Path

import mujoco
import mujoco.batch
import numpy as np

from envs import constants as C
from envs.config import EnvConfig, RandomizationConfig
from envs.geometry import tilt_angle
from envs.objects import OBJECTS, ObjectSpec, get_object
from envs.scene import HANDS, OBJECT_BODY, OBJECT_START, build_model
from envs.task import pick_grasps

GRASP_DIM = C.NUM_JOINTS + 7
CANONICAL_POSE = np.array(
    [0.05, 0.34, 0.60, 0.89, -0.03, 0.42, 0.38, 0.80, -0.19, 0.70, -0.07, 1.04, 1.34, 0.02, 0.35, 1.17]
)
"""Pose putting three fingertips on the +x side and the thumb on the -x side of an object at OBJECT_START
(found by a sampling IK on fingertip targets); grasps are sampled around it."""
DEFAULT_MAX_TILT = 0.15
"""Grasps must hold the object's up axis within this angle (rad, about 9 degrees) of vertical after settling:
the task is rotating an upright cup, and grasps that already lean 15-25 degrees tipped over under zero action in
about 40% of 10 s holds (with the default randomization and pushes)."""
TIP_RADIUS = 0.014
"""Digit 360 dome radius (m), the fingertip geoms in the hand MJCF."""


@dataclass
class GraspCache:
    """Cached grasps per object scale bucket."""

    object: str
    scales: np.ndarray
    """(S,) bucket scales."""
    grasps: np.ndarray
    """(S, G, 23): 16 joint positions (rad, bus order) + object position (3, m) and quaternion (4, wxyz)."""
    seed: int = 0
    source: str = ""
    """Where the cache was read from (named in error messages); empty for a cache built in memory."""
    hand: str = "digit360"
    """Hand variant the grasps were generated with (envs.scene.HANDS); caches of older versions are 'digit360'."""
    hold: tuple[float, ...] = ()
    """The HoldRule every grasp passed (seconds, friction, mass, max_tilt), or () for a cache generated without one."""

    def __post_init__(self) -> None:
        where = self.where
        self.hold = tuple(float(x) for x in self.hold)
        self.scales = np.asarray(self.scales, dtype=np.float64)
        self.grasps = np.asarray(self.grasps, dtype=np.float64)
        if self.scales.ndim != 1 or not np.all(np.isfinite(self.scales) & (self.scales >= 0.1) & (self.scales <= 3.0)):
            raise ValueError(f"{where}: scales must be finite numbers in [0.1, 3.0] (one per bucket), got "
                             f"{self.scales.tolist()}")
        if self.grasps.ndim != 3 or self.grasps.shape[2] != GRASP_DIM or self.grasps.shape[0] != len(self.scales):
            raise ValueError(
                f"{where}: grasps must have shape (S={len(self.scales)}, G, {GRASP_DIM}), got {self.grasps.shape}"
            )
        if self.grasps.shape[1] == 0:
            raise ValueError(f"{where} is empty")
        _check_rows(self.grasps, self.scales, where)

    @property
    def where(self) -> str:
        return f"grasp cache {self.source}" if self.source else f"grasp cache for {self.object!r}"

    def sample(self, bucket: np.ndarray, scale: np.ndarray, u: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Rows for envs with the given scales; ``u`` in [0, 1) picks the row. Returns q (k, 16), pose (k, 7)."""
        return pick_grasps(np, self.scales, self.grasps, np.asarray(scale), np.asarray(u))  # envs.task

    def save(self, path: str | Path) -> None:
        """Write the cache to exactly ``path`` (through a file object: numpy would append '.npz' to a name)."""
        Path(path).parent.mkdir(parents=True, exist_ok=True)
        with open(path, "wb") as f:
            np.savez_compressed(f, object=self.object, scales=self.scales, grasps=self.grasps.astype(np.float32),
                                seed=self.seed, hand=self.hand, hold=np.asarray(self.hold, dtype=np.float64))

    @classmethod
    def load(cls, path: str | Path) -> GraspCache:
        path = Path(path)
        if not path.is_file():
            raise ValueError(f"grasp cache {path} does not exist (generate one with `rotate grasps`)")
        damaged = (OSError, ValueError, EOFError, zipfile.BadZipFile, zlib.error)  # what numpy / zipfile raise
        try:
            f = np.load(path, allow_pickle=False)
        except damaged as err:
            raise ValueError(f"grasp cache {path} is not a readable .npz file ({type(err).__name__}: {err}); "
                             f"regenerate it with `rotate grasps`") from err
        if not isinstance(f, np.lib.npyio.NpzFile):
            raise ValueError(f"grasp cache {path} is a single .npy array, not an .npz grasp cache; "
                             f"regenerate it with `rotate grasps`")
        with f:
            missing = {"object", "scales", "grasps"} - set(f.files)
            if missing:
                raise ValueError(f"grasp cache {path} is missing {sorted(missing)}")
            try:  # members are read (decompressed, CRC-checked) here
                name, scales, grasps = str(f["object"]), f["scales"], f["grasps"]
                seed = int(f["seed"]) if "seed" in f.files else 0
                hand = str(f["hand"]) if "hand" in f.files else "digit360"
                hold = tuple(float(x) for x in f["hold"]) if "hold" in f.files else ()
            except damaged as err:
                raise ValueError(f"grasp cache {path} is corrupted ({type(err).__name__}: {err}); "
                                 f"regenerate it with `rotate grasps`") from err
        if name not in OBJECTS:
            raise ValueError(f"grasp cache {path}: unknown object {name!r}; known objects: "
                             f"{', '.join(sorted(OBJECTS))}")
        if hand not in HANDS:
            raise ValueError(f"grasp cache {path}: unknown hand {hand!r}; hands: {', '.join(HANDS)}")
        if hold and (len(hold) != 4 or not all(math.isfinite(x) for x in hold)):
            raise ValueError(f"grasp cache {path}: 'hold' must be 4 finite numbers (seconds, friction, mass, "
                             f"max_tilt), got {list(hold)}; regenerate it with `rotate grasps`")
        return cls(name, scales, grasps, seed, source=str(path), hand=hand, hold=hold)


JOINT_TOLERANCE = 0.02
"""How far (rad) a cached joint may lie outside its limit: the PD settles a few mrad past it (the shipped caches:
at most 7.5 mrad)."""
QUAT_TOLERANCE = 1e-4
"""How far a cached quaternion's norm may be from 1 (rows are stored as float32: about 3e-8)."""
MAX_OBJECT_OFFSET = 0.10
"""How far (m) a cached object centre may be from OBJECT_START, where grasps are generated: Hora's rule keeps every
fingertip within 10 cm of it (the shipped caches: at most 5 cm)."""


def _check_rows(grasps: np.ndarray, scales: np.ndarray, where: str) -> None:
    """Every row is finite, its joints within the limits, its quaternion a unit one, its object in the hand."""

    def fail(mask: np.ndarray, what: str) -> None:
        b, g = (int(i) for i in np.argwhere(mask)[0][:2])
        raise ValueError(f"{where}: bucket {b} (scale {scales[b]:g}), row {g}: {what(b, g)}; "
                         f"{int(mask.sum())} row(s) like it. Regenerate the cache with `rotate grasps`")

    finite = np.all(np.isfinite(grasps), axis=2)
    if not finite.all():
        fail(~finite, lambda b, g: f"non-finite values {grasps[b, g].tolist()}")
    q = grasps[..., : C.NUM_JOINTS]
    outside = (q < C.JOINT_LOWER - JOINT_TOLERANCE) | (q > C.JOINT_UPPER + JOINT_TOLERANCE)  # (S, G, 16)
    if outside.any():
        def joint(b: int, g: int) -> str:
            j = int(np.flatnonzero(outside[b, g])[0])
            return (f"joint {j} ({C.JOINT_NAMES[j]}) = {q[b, g, j]:.4f} rad is outside its limits "
                    f"[{C.JOINT_LOWER[j]}, {C.JOINT_UPPER[j]}] (+-{JOINT_TOLERANCE})")
        fail(outside.any(axis=2), joint)
    norm = np.linalg.norm(grasps[..., C.NUM_JOINTS + 3 :], axis=2)
    bad = np.abs(norm - 1.0) > QUAT_TOLERANCE
    if bad.any():
        fail(bad, lambda b, g: f"the object quaternion has norm {norm[b, g]:.6f}, not 1 (+-{QUAT_TOLERANCE})")
    offset = np.linalg.norm(grasps[..., C.NUM_JOINTS : C.NUM_JOINTS + 3] - OBJECT_START, axis=2)
    far = offset > MAX_OBJECT_OFFSET
    if far.any():
        fail(far, lambda b, g: f"the object centre {grasps[b, g, 16:19].tolist()} m is {offset[b, g]:.3f} m from "
                               f"the hand's grasp point {OBJECT_START.tolist()} (at most {MAX_OBJECT_OFFSET} m)")


def default_cache_path(object_name: str, hand: str = "digit360") -> Path:
    """The shipped cache of an object: grasps_<object>.npz for the Digit 360 hand, grasps_<object>_<hand>.npz for
    another hand variant."""
    suffix = "" if hand == "digit360" else f"_{hand}"
    return Path(__file__).resolve().parent / "assets" / f"grasps_{object_name}{suffix}.npz"


def _shipped_objects(folder: Path, hand: str) -> list[str]:
    """Objects with a shipped cache for ``hand`` (file names as in default_cache_path)."""
    names = [p.stem.removeprefix("grasps_") for p in folder.glob("grasps_*.npz")]
    if hand == "digit360":
        tags = tuple(f"_{h}" for h in HANDS if h != "digit360")
        return sorted(n for n in names if not n.endswith(tags))
    return sorted(n.removesuffix(f"_{hand}") for n in names if n.endswith(f"_{hand}"))


def load_default_cache(object_name: str, path: str = "", hand: str = "digit360") -> GraspCache:
    """The cache at ``path``, or the one shipped for ``object_name`` and ``hand``; errors name the object and the
    fix."""
    if path:
        cache = GraspCache.load(path)
    else:
        shipped = default_cache_path(object_name, hand)
        if not shipped.is_file():
            have = _shipped_objects(shipped.parent, hand)
            flag, on = ("", "") if hand == "digit360" else (f" --hand {hand}", f" on the {hand} hand")
            raise ValueError(
                f"no grasp cache ships for object {object_name!r}{on} (shipped: {', '.join(have) or 'none'}); "
                f"generate one with `rotate grasps --objects {object_name}{flag} --out DIR` and pass "
                f"grasp_cache=DIR/{default_cache_path(object_name, hand).name}"
            )
        cache = GraspCache.load(shipped)
    if cache.object != object_name:
        raise ValueError(f"grasp cache was generated for {cache.object!r}, not for {object_name!r}")
    if cache.hand != hand:
        raise ValueError(f"{cache.where} was generated for the {cache.hand} hand, not for the {hand} hand; "
                         f"generate one with `rotate grasps --hand {hand}`")
    return cache


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

    def as_array(self) -> np.ndarray:
        return np.array([self.seconds, self.friction, self.mass, self.max_tilt])


class HoldTest:
    """Runs HoldRule checks on batches of grasp rows of one object (the env's model, built once)."""

    def __init__(self, object_name: str, hand: str = "digit360", batch_size: int = 128, nthread: int | None = None):
        from envs.core import EpisodeStarts, task_model  # envs.core imports this module

        self.cfg = EnvConfig(object=object_name, hand=hand)
        model, obj, max_scale = task_model(self.cfg)
        self.batch_size = batch_size
        self.batch = mujoco.batch.Batch(model, batch_size, nthread or 0, persistent=True)
        self.starts = EpisodeStarts(self.batch, model, obj, max_scale)  # the env's own episode start

    def worst_tilt(self, rows: np.ndarray, scales: np.ndarray, rule: HoldRule) -> np.ndarray:
        """(k,) worst tilt (rad) of each row (k, 23) at its object scale (k,) under ``rule``; inf where the object
        sank more than HOLD_DROP or the state went non-finite."""
        rows, scales = np.asarray(rows, dtype=np.float64), np.asarray(scales, dtype=np.float64)
        n, cfg, st = self.batch_size, self.cfg, self.starts
        o, ids = st.obj_qpos, np.arange(n)
        steps = max(1, round(rule.seconds * cfg.control_hz))
        params = {"friction": np.full(n, rule.friction), "mass": np.full(n, rule.mass), "com": np.zeros((n, 3)),
                  "kp": np.full((n, C.NUM_JOINTS), cfg.kp), "kd": np.full((n, C.NUM_JOINTS), cfg.kd)}
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


def hold_check(cache: GraspCache, rule: HoldRule = HoldRule(), batch_size: int = 128,
               nthread: int | None = None) -> np.ndarray:
    """Worst tilt (rad, (S, G)) of every cached grasp under ``rule`` (HoldRule); a grasp passes where it is below
    ``rule.max_tilt``."""
    s, g = cache.grasps.shape[:2]
    test = HoldTest(cache.object, cache.hand, batch_size, nthread)
    return test.worst_tilt(cache.grasps.reshape(s * g, GRASP_DIM), np.repeat(cache.scales, g), rule).reshape(s, g)


def generate_grasps(object_name: str, scales: tuple[float, ...], per_scale: int, seed: int = 0,
                    batch_size: int = 128, max_rounds: int = 200, noise: float = 0.25, nthread: int | None = None,
                    progress=None, max_tilt: float = DEFAULT_MAX_TILT, hand: str = "digit360",
                    hold: HoldRule | None = None) -> GraspCache:
    """Generate ``per_scale`` accepted grasps for each scale (see the module docstring for the rule); with ``hold``
    a grasp must also pass that HoldRule."""
    if per_scale < 1:
        raise ValueError(f"per_scale must be >= 1, got {per_scale}")
    obj = get_object(object_name)
    model = build_model(obj, max(scales), hand=hand)
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
    mass = 0.1
    hold_test = HoldTest(object_name, hand, batch_size, nthread) if hold is not None else None
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
            pose = np.clip(CANONICAL_POSE + rng.uniform(-noise, noise, (batch_size, 16)), C.JOINT_LOWER, C.JOINT_UPPER)
            start = OBJECT_START + rng.uniform(-0.004, 0.004, (batch_size, 3))
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
            touching = (surface_distance(obj, np.full(batch_size, scale), pos, quat, tips) < TIP_RADIUS + 0.004).sum(1)
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
            raise RuntimeError(
                f"only {len(accepted)} of {per_scale} grasps accepted for {object_name} at scale {scale} after "
                f"{max_rounds} rounds of {batch_size}; the canonical pose may not fit this object"
                + (" or the hold check may be too strict for it" if hold is not None else "")
            )
        out.append(np.stack(accepted[:per_scale]))
    return GraspCache(object_name, np.asarray(scales), np.stack(out), seed, hand=hand,
                      hold=tuple(hold.as_array()) if hold is not None else ())
