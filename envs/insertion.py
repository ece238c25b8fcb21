"""Plug insertion by touch: the hand, on a wrist that moves in 6 DoF, holds a plug and pushes it into a socket whose
pose it does not know exactly; a wrist camera sees the approach, and the fingertips feel the contact.

The scene is the held-hand scene (envs.held_hand): the hand palm up on a welded wrist, holding at one of its cup
grasps the plug's grip, from whose top a prong (PRONG: 12 x 6 mm, 24 mm long) sticks up. The grip is held in the
fingertips by default (``grip='fingertips'``: a disc that only the four domes touch, squeezed by them, so the
socket's forces reach the plug through the sensors, as in the benchmark this task rebuilds; envs.plug_grip), or
(``grip='palm'``, the first version) is a cylinder of the cup's size resting on the phalanges, which leaves the domes
about a tenth of the load (experiments/insertion). The socket faces down above it: a plate SOCKET_DEPTH thick with a
rectangular hole CLEARANCE wider than the prong on each side (1 mm in all, no chamfer), its pose drawn per episode (a
few millimetres in the plate's plane, a few degrees of yaw and tilt, a few millimetres of height: ``socket_xy``,
``socket_yaw``, ``socket_tilt``, ``socket_z``) around the prong's settled pose. Only the prong meets the socket.

Control: every ``control_dt`` the wrist's target moves by the action, a 6-vector (dx, dy, dz in m; droll, dpitch,
dyaw in rad, world axes) clipped to ``max_step`` and ``max_turn``. Success: the prong's tip at least
``success_depth`` into the hole within ``episode_steps``, with the largest socket force below ``max_force``. A trial
also ends, failed, when the plug leaves the grasp (its centre more than ``lost_distance`` from where it settled in
the palm's frame): nothing the wrist does afterwards can seat it.

Observation (a dict of numpy arrays): ``wrist`` (7,) the wrist target's offset from its start (position, m;
quaternion wxyz), ``joints`` (16,) the measured joint angles (rad), ``image`` (H, W, 3) uint8 from the wrist camera
when rendering is on, ``skin`` (10, 368, 6) the Sparsh-skin window on the Xela hand ('xela_v4': raw counts and
taxel positions, envs.held_skin); and, privileged (for the scripted expert and the labels): ``socket`` (7,) the
hole's entry centre and orientation, ``prong`` (7,) the prong tip's pose, ``depth`` (m, > 0 once inside the
hole), ``force`` (N, the socket's contact force). The fingertips' contact fields of the physics steps since the last
call (the settling after :meth:`reset`, the action's steps after :meth:`step`) are in ``contact`` (4, S, F; F = 0 on
the Xela hand); the simulation's time in ``data.time``.

The wrist camera (``wrist_cam``) sits on the palm's side and looks up at the prong at a grazing angle: near the
socket the prong hides the hole's edge from it, so its picture of the final alignment is ambiguous, as in the
benchmark this task rebuilds.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import mujoco
import numpy as np

from envs.grasp_cache import GraspCache, load_default_cache
from envs.held_hand import (
    OBJECT_CONTYPE,
    Grip,
    TouchHistory,
    WristRun,
    check_touch_hand,
    contact_press,
    finish,
    grip,
    tilt_quat,
    wrist_spec,
)
from envs.held_skin import SkinHistory
from envs.plug_grip import GRIP_HEIGHT, MAX_REGRIPS, check_grip, fingertip_grip, holds, regrip_row
from envs.render import offscreen_renderer
from envs.rng import splitmix64
from envs.sensors.xela_layout import XELA_HANDS
from envs.wrist_compliance import FIRST_WRIST, check_wrist, wrist_model

TIMESTEP = 0.002
PRONG = (0.012, 0.006, 0.024)
"""Prong size (m): width, thickness, length."""
CLEARANCE = 0.0005
"""Hole wider than the prong on each side (m): 1 mm in all."""
SOCKET_DEPTH = 0.016
"""Plate thickness = hole depth (m)."""
ENTRY_GAP = 0.01
"""The socket's entry sits this far above the prong's settled tip (m), before its drawn offsets."""
_NO_EFFECTS = (mujoco.mjtRndFlag.mjRND_SHADOW, mujoco.mjtRndFlag.mjRND_REFLECTION, mujoco.mjtRndFlag.mjRND_SKYBOX)
"""Render flags the wrist camera turns off (a camera sees no shadow maps; a CPU renderer pays 20x for them)."""
SOCKET_BIT = 8
"""Collision bit of the socket: only the prong (conaffinity has it) touches it."""


@dataclass(frozen=True)
class InsertionConfig:
    hand: str = "digit360_v4"
    """'digit360_v4' (Digit 360 fingertips) or 'xela_v4' (the Xela skin)."""
    control_dt: float = 0.05
    """Seconds between actions (20 Hz)."""
    episode_steps: int = 300
    """Actions per episode (15 s)."""
    settle_s: float = 1.2
    """The plug settles in the still hand before the first action: long enough for a Digit 360 window's 1.12 s of
    history (the fingertips' contact fields of the settling are kept: :attr:`InsertionSim.contact`)."""
    socket_xy: float = 0.003
    """Largest socket offset in its plane (m)."""
    socket_yaw: float = math.radians(5)
    """Largest socket yaw (rad)."""
    socket_tilt: float = math.radians(3)
    """Largest socket tilt (rad)."""
    socket_z: float = 0.003
    """Largest socket height offset (m)."""
    max_step: float = 0.003
    """Largest wrist translation per action (m)."""
    max_turn: float = math.radians(2)
    """Largest wrist rotation per action (rad)."""
    success_depth: float = 0.012
    """Prong depth in the hole that counts as seated (m)."""
    max_force: float = 40.0
    """A socket force above this (N) fails the episode: excess force."""
    lost_distance: float = 0.06
    """The plug's centre this far (m) from where it settled in the palm's frame: it left the grasp, the episode
    fails. The plug shifts in the grasp while the expert seats it (with ``align='state'``: at most 31 mm over 51
    seated trials, seeds 200-251); a plug that falls ends up metres away."""
    image_size: tuple[int, int] = (160, 120)
    """Wrist camera width, height (pixels)."""
    grip: str = "fingertips"
    """How the plug is held: 'fingertips' (the domes alone) or 'palm' (the cup's body on the phalanges; the first
    version's runs)."""
    wrist: str = FIRST_WRIST
    """How the arm moves the wrist: 'stiff' (the target jumps to each action's pose, held by a stiff weld: the runs
    recorded before the setting) or 'compliant' (the target moves there over the action, and the arm yields to the
    socket's forces as under admittance control; envs.wrist_compliance)."""

    def __post_init__(self) -> None:
        check_touch_hand("insertion", self.hand, skin=True)
        check_grip("insertion", self.grip)
        check_wrist("insertion", self.wrist)
        steps = self.control_dt / TIMESTEP
        if abs(steps - round(steps)) > 1e-9 or steps < 1:
            raise ValueError(f"insertion: control_dt must be a whole number of {TIMESTEP} s steps, got "
                             f"{self.control_dt}")
        if self.success_depth > SOCKET_DEPTH:
            raise ValueError(f"insertion: success_depth must be at most the hole's depth {SOCKET_DEPTH} m")

    @property
    def substeps(self) -> int:
        return int(round(self.control_dt / TIMESTEP))


@dataclass(frozen=True)
class InsertionEpisode:
    seed: int
    bucket: int
    grasp_u: float
    offset: tuple[float, float, float]
    """Socket entry offset (m) from the prong's settled tip, ENTRY_GAP above it."""
    yaw: float
    tilt: tuple[float, float]
    """Socket roll and pitch (rad)."""


def clip_action(cfg: InsertionConfig, action: np.ndarray) -> np.ndarray:
    """The wrist action (..., 6) as a step executes it: translation clipped to ``max_step``, rotation to
    ``max_turn`` per component. The scripted expert's corrections can be far larger (a proportional step toward a
    target 1 cm away, a turn of 0.5 rad where a policy has tilted the wrist): what a step does with them is this."""
    a = np.asarray(action, dtype=np.float64)
    return np.concatenate([np.clip(a[..., :3], -cfg.max_step, cfg.max_step),
                           np.clip(a[..., 3:], -cfg.max_turn, cfg.max_turn)], axis=-1)


def draw_episode(cfg: InsertionConfig, seed: int, grasps: GraspCache) -> InsertionEpisode:
    rng = np.random.default_rng([int(seed), 0x1A5])
    r = cfg.socket_xy * math.sqrt(rng.uniform())
    a = rng.uniform(0, 2 * math.pi)
    return InsertionEpisode(int(seed), int(rng.integers(len(grasps.scales))), float(rng.uniform()),
                            (r * math.cos(a), r * math.sin(a), float(rng.uniform(-cfg.socket_z, cfg.socket_z))),
                            float(rng.uniform(-cfg.socket_yaw, cfg.socket_yaw)),
                            (float(rng.uniform(-cfg.socket_tilt, cfg.socket_tilt)),
                             float(rng.uniform(-cfg.socket_tilt, cfg.socket_tilt))))


def _add_socket(spec: mujoco.MjSpec) -> list[str]:
    """The socket plate, facing down, its entry (the hole's lower opening) at its mocap body's origin: four boxes
    around the hole. Returns their names."""
    body = spec.worldbody.add_body(name="socket", mocap=True, pos=[0.0, 0.0, 1.0])
    w, t = PRONG[0] / 2 + CLEARANCE, PRONG[1] / 2 + CLEARANCE  # the hole's half sizes
    outer = 0.03
    bar_x, bar_y = ((outer - w) / 2, outer, SOCKET_DEPTH / 2), (w, (outer - t) / 2, SOCKET_DEPTH / 2)
    boxes = {"socket_px": bar_x, "socket_nx": bar_x, "socket_py": bar_y, "socket_ny": bar_y}  # half sizes: x bars
    # span the whole plate, y bars fill between them
    centres = {"socket_px": ((outer + w) / 2, 0), "socket_nx": (-(outer + w) / 2, 0),
               "socket_py": (0, (outer + t) / 2), "socket_ny": (0, -(outer + t) / 2)}
    for name, size in boxes.items():
        cx, cy = centres[name]
        body.add_geom(name=name, type=mujoco.mjtGeom.mjGEOM_BOX, size=list(size), pos=[cx, cy, SOCKET_DEPTH / 2],
                      contype=SOCKET_BIT, conaffinity=0, condim=4, friction=[0.3, 0.005, 0.0001],
                      rgba=[0.8, 0.8, 0.75, 1.0])
    body.add_site(name="socket_entry", pos=[0, 0, 0], size=[0.002, 0, 0], rgba=[1, 0, 0, 0])
    return list(boxes)


class InsertionSim:
    """One insertion episode (see the module docstring)."""

    def __init__(self, cfg: InsertionConfig, episode: InsertionEpisode, grasps: GraspCache | None = None,
                 render: bool = False) -> None:
        self.cfg, self.episode = cfg, episode
        grasps = grasps if grasps is not None else load_default_cache("cup", "", cfg.hand)
        self.grasp_u, self.regrips = episode.grasp_u, 0
        """The grasp row the plug is held at, and how many rows were passed over for it (a fingertip grip that did
        not hold: envs.plug_grip)."""
        for attempt in range(MAX_REGRIPS + 1):
            self.grasp_u, self.regrips = regrip_row(episode.grasp_u, attempt), attempt
            self._build(grip(grasps, episode.bucket, self.grasp_u))
            if cfg.grip == "palm" or attempt == MAX_REGRIPS:
                break
            self._run.reset(np.zeros(3), self._palm_quat0)
            if holds(self._run.run(int(round(cfg.settle_s / TIMESTEP)), self._target_start)[2]):
                break
        self._plug, self._socket = self.model.body("plug").id, self.model.body("socket").id
        self._renderer = offscreen_renderer(self.model, cfg.image_size[1], cfg.image_size[0],
                                            "the wrist camera") if render else None
        self._wrench = np.zeros(6)
        self._wrist = wrist_model(cfg.wrist)
        self._from: tuple[np.ndarray, np.ndarray, float] | None = None
        """The wrist target's pose and the time at the start of the current action (a ramped wrist moves from it)."""
        with np.errstate(over="ignore"):
            self.touch_key = int(splitmix64(np.asarray([episode.seed], dtype=np.uint64))[0])
        """The episode's touch noise key: a recorded demonstration stores it as its session's (rotation.jobs.demos)."""
        self.skin = SkinHistory(self.model, self.touch_key, TIMESTEP) if cfg.hand in XELA_HANDS else None
        """On the Xela hand: its skin (``skin.window``: the Sparsh-skin window now; envs.held_skin)."""
        self.touch = TouchHistory(self.touch_key, TIMESTEP, cfg.hand) if self.skin is None else None
        """On a Digit 360 hand: the fingertips' recent contact fields; ``touch.windows()`` renders what the Digit 360s
        show now."""
        self.steps = 0
        self.max_force = 0.0
        self.contact = np.zeros((4, 0, 0), np.float32)

    def _build(self, g: Grip) -> None:
        """The scene with the plug held at cup grasp ``g`` (in the fingertips, or as the cup), the socket and the
        wrist camera."""
        spec, self._palm_quat0 = wrist_spec(self.cfg.hand, TIMESTEP)
        height, radius, targets = g.height, g.radius, None
        if self.cfg.grip == "fingertips":  # a disc at the domes' height, squeezed: only they touch it
            g, targets, radius = fingertip_grip(spec, g)
            height = GRIP_HEIGHT
        plug = spec.worldbody.add_body(name="plug", pos=g.pose[:3].tolist(), quat=g.pose[3:].tolist())
        plug.add_freejoint(name="plug_free")
        plug.add_geom(name="plug_grip", type=mujoco.mjtGeom.mjGEOM_CYLINDER, size=[radius, height / 2, 0],
                      density=300.0, contype=OBJECT_CONTYPE, conaffinity=1, condim=4, rgba=[0.2, 0.2, 0.22, 1.0])
        tip_z = height / 2 + PRONG[2]
        plug.add_geom(name="plug_prong", type=mujoco.mjtGeom.mjGEOM_BOX,
                      size=[PRONG[0] / 2, PRONG[1] / 2, PRONG[2] / 2], pos=[0, 0, height / 2 + PRONG[2] / 2],
                      density=1000.0, contype=OBJECT_CONTYPE, conaffinity=1 | SOCKET_BIT, condim=4,
                      friction=[0.3, 0.005, 0.0001], rgba=[0.85, 0.7, 0.3, 1.0])
        plug.add_body(name="plug_tip", pos=[0, 0, tip_z])
        self._tip_local = np.array([0.0, 0.0, tip_z])
        self._socket_geoms = _add_socket(spec)
        palm = spec.body("palm")
        palm_rot = np.zeros(9)
        mujoco.mju_quat2Mat(palm_rot, self._palm_quat0)
        # the wrist camera: 8 cm beside and 3 cm below the prong's tip at the start, tracking the tip
        tip0 = g.pose[:3] + np.array([0.0, 0.0, tip_z])
        cam_world = tip0 + np.array([0.06, -0.05, -0.03])
        palm.add_camera(name="wrist_cam", pos=(palm_rot.reshape(3, 3).T @ cam_world).tolist(),
                        mode=mujoco.mjtCamLight.mjCAMLIGHT_TARGETBODY, targetbody="plug_tip", fovy=45)
        self.model = finish(spec, self.cfg.hand, "plug_")
        self._run = WristRun(self.model, g, self._palm_quat0, "plug", targets)
        self.data = self._run.data

    def _target_start(self, t: float) -> tuple[np.ndarray, np.ndarray]:
        return np.zeros(3), self._palm_quat0

    # ------------------------------------------------------------------ poses
    def _pose_of(self, local: np.ndarray) -> np.ndarray:
        d = self.data
        rot = np.zeros(9)
        mujoco.mju_quat2Mat(rot, d.xquat[self._plug])
        return np.concatenate([d.xpos[self._plug] + rot.reshape(3, 3) @ local, d.xquat[self._plug]])

    def socket_pose(self) -> np.ndarray:
        """The hole's entry centre (m) and the socket's orientation (wxyz)."""
        return np.concatenate([self.data.mocap_pos[1], self.data.mocap_quat[1]])

    def _socket_rot(self) -> np.ndarray:
        """The socket's orientation (3 x 3, its axes as columns)."""
        rot = np.zeros(9)
        mujoco.mju_quat2Mat(rot, self.data.mocap_quat[1])
        return rot.reshape(3, 3)

    def depth(self) -> tuple[float, bool]:
        """How far (m) the prong's tip is above the socket's entry plane, along the socket's axis, and whether it is
        within the hole's outline."""
        local = self._socket_rot().T @ (self._pose_of(self._tip_local)[:3] - self.data.mocap_pos[1])
        inside = abs(local[0]) <= PRONG[0] / 2 + CLEARANCE + 1e-4 and abs(local[1]) <= PRONG[1] / 2 + CLEARANCE + 1e-4
        return float(local[2]), bool(inside)

    # ------------------------------------------------------------------ episode
    def reset(self) -> dict[str, np.ndarray]:
        """The start: the plug settles in the still hand, then the socket is placed from the episode's draws."""
        cfg, ep, d = self.cfg, self.episode, self.data
        self._pos, self._quat = np.zeros(3), self._palm_quat0.copy()
        self._run.reset(self._pos, self._quat)
        d.mocap_pos[1] = [0.0, 0.0, 1.0]
        if self.skin is not None:
            self.skin.reset(d)
        times, self.contact, held = self._run.run(int(round(cfg.settle_s / TIMESTEP)), self._target,
                                                  None if self.skin is None else self.skin.on_step)
        self._held0 = held[-1].copy()
        if self.touch is not None:
            self.touch = TouchHistory(self.touch_key, TIMESTEP, cfg.hand)
            self.touch.extend(times, self.contact)
        tip = self._pose_of(self._tip_local)[:3]
        d.mocap_pos[1] = tip + np.array([0.0, 0.0, ENTRY_GAP]) + np.asarray(ep.offset)
        quat = tilt_quat(np.array([1.0, 0.0, 0.0, 0.0]), np.array([0.0, 0.0, 1.0]), ep.yaw)
        quat = tilt_quat(quat, np.array([1.0, 0.0, 0.0]), ep.tilt[0])
        d.mocap_quat[1] = tilt_quat(quat, np.array([0.0, 1.0, 0.0]), ep.tilt[1])
        mujoco.mj_forward(self.model, d)
        self._start_pos, self._start_quat = self._pos.copy(), self._quat.copy()
        self._wrist.reset()
        self._from = None
        self.steps, self.max_force = 0, 0.0
        return self.observe()

    def _target(self, t: float) -> tuple[np.ndarray, np.ndarray]:
        pos, quat = self._pos, self._quat
        if self._wrist.ramps and self._from is not None:  # the arm moves to the new target over the action
            pos0, quat0, t0 = self._from
            u = min(1.0, (t - t0 + TIMESTEP) / self.cfg.control_dt)
            pos = pos0 + u * (pos - pos0)
            q = (1.0 - u) * quat0 + u * (quat if float(np.dot(quat, quat0)) >= 0.0 else -quat)
            quat = q / np.linalg.norm(q)
        return pos + self._wrist.offset, quat

    def step(self, action: np.ndarray) -> tuple[dict[str, np.ndarray], bool, dict[str, float]]:
        """Move the wrist's target by ``action`` (see the module docstring) and step ``control_dt``; returns the
        observation, whether the episode ended, and info: success, depth, force, max_force, lost (1 once the plug
        has left the grasp), slip (m: how far the plug's centre has moved from where it settled, in the palm's
        frame; lost is slip past ``lost_distance``), press_x and press_y (m: where the socket pressed on the prong
        over the action's steps, force-weighted, relative to its tip in the socket's plane; 0 without contact;
        privileged, but what a hand feels: a press off the prong's axis is a moment on the held plug, and the
        fingertips' forces shift with it)."""
        cfg = self.cfg
        a = np.asarray(action, dtype=np.float64).reshape(6)
        if not np.all(np.isfinite(a)):
            raise ValueError(f"insertion: the action must be 6 finite numbers, got {action!r}")
        executed = clip_action(cfg, a)
        move, turn = executed[:3], executed[3:]
        self._from = (self._pos, self._quat, self.data.time)  # where a ramped wrist moves from over the action
        self._pos = self._pos + move
        for axis, angle in zip(np.eye(3), turn, strict=True):
            self._quat = tilt_quat(self._quat, axis, float(angle))
        forces, moment = [], np.zeros(3)

        def on_step(d: mujoco.MjData) -> None:
            nonlocal moment
            on_socket = np.zeros(3) if self._wrist.active else None  # the prong's force on the socket (world)
            total, pressed = contact_press(self.model, d, self._socket, self._wrench, on_socket)
            forces.append(total)
            if total > 0.0:  # where the socket presses, relative to the prong's tip at that step
                moment = moment + pressed - total * self._pose_of(self._tip_local)[:3]
            if self.skin is not None:
                self.skin.on_step(d)
            if on_socket is not None:  # the arm yields to what the socket does to the plug
                self._wrist.update(-on_socket, TIMESTEP)

        times, rows, held = self._run.run(cfg.substeps, self._target, on_step)
        self.contact = rows
        if self.touch is not None:
            self.touch.extend(times, rows)
        self.steps += 1
        force = float(max(forces)) if forces else 0.0
        self.max_force = max(self.max_force, force)
        depth, inside = self.depth()
        success = inside and depth >= cfg.success_depth and self.max_force <= cfg.max_force
        slip = float(np.linalg.norm(held[-1] - self._held0))  # how far the plug has moved in the hand
        lost = slip > cfg.lost_distance
        press = (self._socket_rot().T @ moment)[:2] / max(sum(forces), 1e-9)  # over the action's steps, in the
        # socket's plane: a press off the prong's axis is a moment on the held plug, which the fingertips feel
        done = success or lost or self.steps >= cfg.episode_steps or self.max_force > cfg.max_force
        return self.observe(), done, {"success": float(success), "depth": depth, "inside": float(inside),
                                      "force": force, "max_force": self.max_force, "lost": float(lost), "slip": slip,
                                      "press_x": float(press[0]), "press_y": float(press[1])}

    def observe(self) -> dict[str, np.ndarray]:
        d = self.data
        rel = np.zeros(4)
        inv = np.zeros(4)
        mujoco.mju_negQuat(inv, self._start_quat)
        mujoco.mju_mulQuat(rel, self._quat, inv)
        obs = {"wrist": np.concatenate([self._pos - self._start_pos, rel]).astype(np.float32),
               "joints": d.qpos[self._run._joints].astype(np.float32),
               "socket": self.socket_pose().astype(np.float32),
               "prong": self._pose_of(self._tip_local).astype(np.float32),
               "depth": np.float32(self.depth()[0])}
        if self._renderer is not None:
            self._renderer.update_scene(d, camera="wrist_cam")
            for flag in _NO_EFFECTS:  # shadows and reflections: 146 ms a frame on a CPU renderer, 6 ms without
                self._renderer.scene.flags[flag] = 0
            obs["image"] = self._renderer.render().copy()
        if self.skin is not None:
            obs["skin"] = self.skin.window.copy()
        return obs

    def close(self) -> None:
        if self._renderer is not None:
            self._renderer.close()
            self._renderer = None
