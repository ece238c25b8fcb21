"""Object-action-surface: the hand holds an object of some material and taps, presses, slides or rotates it against
a surface; the fingertips' Digit 360s feel the contact through the object. Labels: object, action, surface.

The scene is the held-hand scene (envs.held_hand: the hand on a wrist that follows a scripted motion, the object at
one of its cup grasps). The hand holds objects only palm up (its cup grasps hold against gravity that way), so the
surface faces down, 5 mm above the object's top, and the wrist brings the object up against it: the contact
mechanics are those of a surface below, the weight of the held object adds to the press instead of taking from it.

Objects (OBJECTS): a closed cylinder with the cup's outer size at the grasp's scale, of one of four materials: its
contact with the surface has the material's friction coefficient, stiffness and damping (an explicit contact pair
with MuJoCo's solref: time constant and damping ratio; a ratio below 1 bounces), and its mass the material's density.
These are assumptions chosen to span the materials' order (rubber grips and gives, metal is slippery, stiff and
rings, plastic and wood between), not measured figures. Where the hand holds it, every object meets the fingers as
the rotation env's objects do (a grip sleeve of one material: a bouncy metal contact in the hand threw the object
out of the grasps).

Surfaces (SURFACES): ``flat`` (a plate), ``ridged`` (rounded 2 mm ridges every 8 mm across the plate), ``rough`` (a
height field of random bumps up to 1.5 mm on a 3 mm grain).

Actions (ACTIONS), after the object settles: ``tap`` (the wrist rises and falls at 1.5-3 Hz, 1-3 mm past contact
at the top), ``press`` (it rises slowly 2-4 mm past contact, holds, lowers, twice), ``slide`` (1-2 mm past contact,
then 1-2 cm back and forth at 0.5-1 Hz), ``rotate`` (1-2 mm past contact, then 15-30 degrees back and forth about the
object's axis at 0.5-1 Hz).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import mujoco
import numpy as np

from envs.grasp_cache import GraspCache, load_default_cache
from envs.held_hand import (
    OBJECT_CONTYPE,
    WristRun,
    check_touch_hand,
    contact_force,
    finish,
    grip,
    tilt_quat,
    wrist_spec,
)

TIMESTEP = 0.002
"""Physics step (s)."""
GAP = 0.005
"""Distance (m) from the object's top to the surface at the start."""
SETTLE_S = 0.3
"""The object settles in the still hand first."""


@dataclass(frozen=True)
class Material:
    friction: float
    timeconst: float
    """Contact time constant (s): smaller is stiffer."""
    dampratio: float
    """Contact damping ratio: below 1 the contact bounces."""
    density: float
    """Of the closed cylinder (kg/m^3): a hollow object's mean density."""


OBJECTS: dict[str, Material] = {
    "plastic": Material(0.35, 0.006, 1.0, 300.0),
    "rubber": Material(1.0, 0.02, 1.0, 500.0),
    "metal": Material(0.2, 0.005, 0.4, 500.0),
    "wood": Material(0.5, 0.008, 0.7, 400.0),
}
"""Held object materials (module docstring: assumptions spanning the materials' order)."""
SURFACES = ("flat", "ridged", "rough")
ACTIONS = ("tap", "press", "slide", "rotate")


@dataclass(frozen=True)
class OasConfig:
    hand: str = "digit360_v4"
    """A hand variant with Digit 360 fingertips."""
    duration_s: float = 3.0
    """Episode length (s), settling included."""

    def __post_init__(self) -> None:
        check_touch_hand("oas", self.hand)
        if not 1.2 <= self.duration_s <= 600:
            raise ValueError(f"oas: duration_s must be 1.2-600 s, got {self.duration_s}")


@dataclass(frozen=True)
class OasEpisode:
    seed: int
    object: str
    action: str
    surface: str
    bucket: int
    grasp_u: float
    depth: float
    """How far past contact the wrist goes (m)."""
    frequency: float
    """Hz."""
    extent: float
    """slide: amplitude (m); rotate: amplitude (rad); otherwise unused."""
    direction: float
    """slide: the sliding direction's azimuth (rad)."""

    @property
    def labels(self) -> dict[str, int]:
        return {"object": list(OBJECTS).index(self.object), "action": ACTIONS.index(self.action),
                "surface": SURFACES.index(self.surface)}


def draw_episode(cfg: OasConfig, seed: int, grasps: GraspCache, object: str | None = None,
                 action: str | None = None, surface: str | None = None) -> OasEpisode:
    """An episode's draws from its seed (object, action and surface uniform unless given)."""
    for name, value, known in (("object", object, tuple(OBJECTS)), ("action", action, ACTIONS),
                               ("surface", surface, SURFACES)):
        if value is not None and value not in known:
            raise ValueError(f"oas: unknown {name} {value!r}; {name}s: {', '.join(known)}")
    rng = np.random.default_rng([int(seed), 0x0A5])
    drawn = (list(OBJECTS)[int(rng.integers(len(OBJECTS)))], ACTIONS[int(rng.integers(len(ACTIONS)))],
             SURFACES[int(rng.integers(len(SURFACES)))])
    act = action if action is not None else drawn[1]
    depth = {"tap": (0.0005, 0.0015), "press": (0.001, 0.002)}.get(act, (0.0005, 0.001))
    freq = {"tap": (1.5, 3.0), "press": (0.8, 1.2)}.get(act, (0.5, 1.0))
    extent = {"slide": (0.01, 0.02), "rotate": (math.radians(15), math.radians(30))}.get(act, (0.0, 0.0))
    return OasEpisode(int(seed), object if object is not None else drawn[0], act,
                      surface if surface is not None else drawn[2], int(rng.integers(len(grasps.scales))),
                      float(rng.uniform()), float(rng.uniform(*depth)), float(rng.uniform(*freq)),
                      float(rng.uniform(*extent)), float(rng.uniform(0, 2 * math.pi)))


def _add_surface(spec: mujoco.MjSpec, kind: str, rng: np.random.Generator) -> list[str]:
    """The surface, facing down, its lowest points at its mocap body's origin (placed once the object has settled:
    :meth:`OasSim.run`); returns its geoms' names. They collide with nothing by themselves: the object's contacts
    with them are explicit pairs with the object's material."""
    body = spec.worldbody.add_body(name="surface", mocap=True, pos=[0.0, 0.0, 1.0])
    common = dict(contype=0, conaffinity=0, rgba=[0.55, 0.5, 0.45, 1.0])
    half = 0.06
    if kind == "rough":
        n, bump, grain = 41, 0.0015, 0.003
        noise = rng.normal(size=(n, n))
        k = max(1, int(round(grain / (2 * half / (n - 1)))))
        kernel = np.ones(2 * k + 1) / (2 * k + 1)  # a box blur to the grain size, separable
        for axis in (0, 1):
            noise = np.apply_along_axis(lambda row: np.convolve(row, kernel, mode="same"), axis, noise)
        heights = (noise - noise.min()) / max(np.ptp(noise), 1e-12)
        spec.add_hfield(name="rough", size=[half, half, bump, 0.002], nrow=n, ncol=n,
                        userdata=heights.ravel().tolist())
        # the height field faces down: turned half a turn about x, its base 2 mm + bump above z
        body.add_geom(name="surface_rough", type=mujoco.mjtGeom.mjGEOM_HFIELD, hfieldname="rough",
                      pos=[0, 0, bump], quat=[0.0, 1.0, 0.0, 0.0], **common)
        return ["surface_rough"]
    body.add_geom(name="surface_plate", type=mujoco.mjtGeom.mjGEOM_BOX, size=[half, half, 0.004],
                  pos=[0, 0, 0.004 + (0.002 if kind == "ridged" else 0.0)], **common)
    names = ["surface_plate"]
    if kind == "ridged":
        for i, x in enumerate(np.arange(-half + 0.004, half - 0.003, 0.008)):
            # a rounded ridge (a capsule along y): a box's edge under a stiff contact spiked to hundreds of newtons
            body.add_geom(name=f"surface_ridge{i}", type=mujoco.mjtGeom.mjGEOM_CAPSULE, size=[0.001, half, 0],
                          pos=[float(x), 0, 0.001], quat=[math.cos(math.pi / 4), math.sin(math.pi / 4), 0, 0],
                          **common)
            names.append(f"surface_ridge{i}")
    return names


@dataclass
class OasRecording:
    """What one episode gives (:meth:`OasSim.run`)."""

    episode: OasEpisode
    times: np.ndarray
    """(T,) s."""
    contact: np.ndarray
    """(4, T, NUM_FIELDS) float32: each fingertip's contact fields."""
    surface_force: np.ndarray
    """(T,) N: the normal force between the object and the surface."""
    held: bool
    """The object stayed in the hand (it moved at most HELD_TOLERANCE relative to the palm)."""


HELD_TOLERANCE = 0.015
"""An object that moved more than this (m) relative to the palm by the end was not held."""


def _smooth(x: float) -> float:
    """0 -> 1 with zero slope at both ends (x clipped to [0, 1])."""
    x = min(max(x, 0.0), 1.0)
    return 0.5 - 0.5 * math.cos(math.pi * x)


class OasSim:
    """One object-action-surface episode (see the module docstring)."""

    def __init__(self, cfg: OasConfig, episode: OasEpisode, grasps: GraspCache | None = None) -> None:
        self.cfg, self.episode = cfg, episode
        grasps = grasps if grasps is not None else load_default_cache("cup", "", cfg.hand)
        g = grip(grasps, episode.bucket, episode.grasp_u)
        spec, self._palm_quat0 = wrist_spec(cfg.hand, TIMESTEP)
        mat = OBJECTS[episode.object]
        body = spec.worldbody.add_body(name="object", pos=g.pose[:3].tolist(), quat=g.pose[3:].tolist())
        body.add_freejoint(name="object_free")
        body.add_geom(name="object_body", type=mujoco.mjtGeom.mjGEOM_CYLINDER, size=[g.radius, g.height / 2, 0],
                      density=mat.density, contype=OBJECT_CONTYPE, conaffinity=1, condim=4,
                      rgba=[0.7, 0.4, 0.3, 1.0])
        self._center = g.pose[:3].copy()
        self._half_height = g.height / 2
        for name in _add_surface(spec, episode.surface, np.random.default_rng([episode.seed, 0x5F])):
            spec.add_pair(geomname1="object_body", geomname2=name, condim=4, solref=[mat.timeconst, mat.dampratio],
                          friction=[mat.friction, mat.friction, 0.005, 0.0001, 0.0001])
        m = self.model = finish(spec, cfg.hand, "object_")
        obj = m.geom("object_body").id
        self._run = WristRun(m, g, self._palm_quat0, "object")
        self.data = self._run.data
        self._obj, self._surface = obj, m.body("surface").id

    def _wrist(self, t: float) -> tuple[np.ndarray, np.ndarray]:
        """The wrist's mocap position and quaternion at time ``t`` (module docstring: the actions)."""
        ep = self.episode
        s = t - SETTLE_S
        reach = GAP + ep.depth
        pos, quat = np.zeros(3), self._palm_quat0
        if s <= 0:
            return pos, quat
        if ep.action == "tap":
            pos[2] = reach * (1 - math.cos(2 * math.pi * ep.frequency * s)) / 2
            return pos, quat
        if ep.action == "press":
            phase = (s * ep.frequency) % 1.0  # rise 35%, hold 30%, lower 35% of each cycle
            pos[2] = reach * (_smooth(phase / 0.35) - _smooth((phase - 0.65) / 0.35))
            return pos, quat
        approach = 0.4
        pos[2] = reach * _smooth(s / approach)
        w = math.sin(2 * math.pi * ep.frequency * max(s - approach, 0.0))
        if ep.action == "slide":
            pos[:2] += ep.extent * w * np.array([math.cos(ep.direction), math.sin(ep.direction)])
            return pos, quat
        angle = ep.extent * w  # rotate about the object's vertical axis: the wrist swings around it
        c, sn = math.cos(angle), math.sin(angle)
        x, y = -self._center[0], -self._center[1]  # the palm's origin relative to the object's axis
        pos[0] += c * x - sn * y - x
        pos[1] += sn * x + c * y - y
        return pos, tilt_quat(self._palm_quat0, np.array([0.0, 0.0, 1.0]), angle)

    def reset(self) -> None:
        self._run.reset(*self._wrist(0.0))

    def run(self) -> OasRecording:
        """Step the episode from its start; the contact fields of every physics step and the labels."""
        self.reset()
        steps = int(round(self.cfg.duration_s / TIMESTEP))
        settle = int(round(SETTLE_S / TIMESTEP))
        force = np.zeros(steps)
        k = [0]
        wrench = np.zeros(6)
        rot = np.zeros(9)

        def surface_force(d: mujoco.MjData) -> None:
            if k[0] == settle - 1:  # the object has settled in the hand: the surface GAP above its top
                obj = self.model.geom_bodyid[self._obj]
                mujoco.mju_quat2Mat(rot, d.xquat[obj])
                top = d.xpos[obj] + rot.reshape(3, 3) @ np.array([0.0, 0.0, self._half_height])
                d.mocap_pos[1] = [top[0], top[1], top[2] + GAP]
            total = contact_force(self.model, d, self._surface, wrench)
            force[k[0]] = total
            k[0] += 1

        try:
            times, rows, offset = self._run.run(steps, self._wrist, surface_force)
        except FloatingPointError as err:
            raise FloatingPointError(f"oas: episode seed {self.episode.seed}: {err}") from None
        held = bool(np.linalg.norm(offset[-1] - offset[0]) <= HELD_TOLERANCE)
        return OasRecording(self.episode, times, rows, force, held)
