"""The scripted insertion expert: privileged state (the socket's and the prong's poses, the socket force) in, wrist
actions out; what the demonstrations of `rotate demos --task insertion` record.

Phases, each a proportional controller on the prong tip's error in the socket's frame (the wrist moves what the
grasp holds; rotations about the palm move the tip too, which the next step's translation takes back):

1. **approach**: turn the prong's axes onto the socket's (within half a degree), and bring the tip under a point
   ``miss`` away from the hole's centre (drawn per episode: the expert's own aim is off, as a camera's would be),
   6 mm below the entry;
2. **contact**: rise until the prong touches the plate (socket force above ``touch_force``), or enters the hole;
3. **align**: find the hole at the plate's height, keeping a light contact and the axes aligned (``align`` below);
4. **push**: rise into the hole, centring as it goes, the more gently the larger the socket force (not at all at
   ``jam_force``); if the force stays above half of it for two actions without the depth growing (jammed), back off
   2 mm and align again (at most ``retries`` times).

``align``: how the expert finds the hole after contact. ``"state"`` slides to the hole's true centre, which no
policy can see (the camera's view of the final alignment is ambiguous by design). ``"feel"`` never reads the hole's
position: while the prong presses on the plate it steps ``feel_step`` away from where the socket presses on it
(``press_x``, ``press_y`` of envs.insertion.InsertionSim.step's info: the part of the prong's face on the plate,
beside the hole, a moment on the held plug that the fingertips feel) and holds still without contact, until the tip
rises into the hole; in
the hole it centres the prong as ``"state"`` does (the last half-millimetre: the walls allow no more; following
the walls' sideways force instead wedged the prong on 7 of 40 seeds). Its corrections follow from what touch
carries, so an imitation policy that reads touch can learn them.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import mujoco
import numpy as np

from envs.insertion import InsertionConfig

ALIGNS = ("feel", "state")
"""How the expert can find the hole after contact (``ExpertConfig.align``; the module docstring)."""


@dataclass(frozen=True)
class ExpertConfig:
    gain: float = 0.6
    """Share of the position error corrected per action."""
    turn_gain: float = 0.5
    """Share of the orientation error corrected per action."""
    miss: float = 0.002
    """Largest aim error of the approach (m)."""
    touch_force: float = 1.0
    """Socket force (N) that counts as contact."""
    jam_force: float = 15.0
    """Socket force (N) above which a push that does not go deeper is jammed."""
    aligned: float = 0.0003
    """Lateral error (m) below which the tip is over the hole."""
    push_step: float = 0.0015
    """Rise per action while pushing (m)."""
    retries: int = 3
    """Back-offs after a jam before the expert keeps pushing regardless."""
    align: str = "feel"
    """'state' (slide to the hole's true centre) or 'feel' (step away from the socket's press; module docstring)."""
    feel_step: float = 0.0004
    """Largest lateral target step (m) of a 'feel' correction (times ``gain`` per action)."""

    def __post_init__(self) -> None:
        if self.align not in ALIGNS:
            raise ValueError(f"align must be 'state' or 'feel', got {self.align!r}")


def _rot(quat: np.ndarray) -> np.ndarray:
    r = np.zeros(9)
    mujoco.mju_quat2Mat(r, np.asarray(quat, dtype=np.float64))
    return r.reshape(3, 3)


class InsertionExpert:
    """Acts on an InsertionSim's privileged observation (see the module docstring)."""

    def __init__(self, cfg: InsertionConfig, seed: int, expert: ExpertConfig = ExpertConfig()) -> None:
        self.cfg, self.x = cfg, expert
        rng = np.random.default_rng([int(seed), 0xE7])
        a = rng.uniform(0, 2 * math.pi)
        r = expert.miss * math.sqrt(rng.uniform(0.25, 1.0))
        self.miss = np.array([r * math.cos(a), r * math.sin(a)])
        self.phase = "approach"
        self.retries = 0
        self._best_depth = -1.0
        self._stuck = 0

    def _turn(self, socket_q: np.ndarray, prong_q: np.ndarray) -> np.ndarray:
        """World-frame rotation vector (rad) that turns the prong's axes onto the socket's, times the gain."""
        err = _rot(socket_q) @ _rot(prong_q).T
        quat = np.zeros(4)
        mujoco.mju_mat2Quat(quat, err.ravel())
        vel = np.zeros(3)
        mujoco.mju_quat2Vel(vel, quat, 1.0)
        return self.x.turn_gain * vel

    def _away(self, tip: np.ndarray, info: dict[str, float]) -> np.ndarray:
        """The 'feel' rule's lateral target: a step away from where the socket presses on the prong, or stay."""
        press = np.array([info.get("press_x", 0.0), info.get("press_y", 0.0)])
        size = float(np.linalg.norm(press))
        return tip[:2] - self.x.feel_step * press / size if size > 1e-4 else tip[:2].copy()

    def act(self, obs: dict[str, np.ndarray], info: dict[str, float] | None = None) -> np.ndarray:
        info = info or {}
        socket, prong = np.asarray(obs["socket"], np.float64), np.asarray(obs["prong"], np.float64)
        rot = _rot(socket[3:])
        tip = rot.T @ (prong[:3] - socket[:3])  # the tip in the socket's frame: z up the hole, 0 at the entry
        force, depth = float(info.get("force", 0.0)), float(tip[2])
        target = np.zeros(3)
        turn = self._turn(socket[3:], prong[3:])
        if self.phase == "approach":  # well below the plate while the axes turn (the tip swings with them)
            target[:2], target[2] = self.miss, -0.006
            if force > self.x.touch_force:  # touched the plate on the way (the plug sits tilted in the grasp)
                self.phase = "align"
            elif (np.linalg.norm(tip[:2] - self.miss) < 0.0005 and abs(tip[2] + 0.006) < 0.001
                  and np.linalg.norm(turn) < 0.5 * self.x.turn_gain * math.radians(1)):
                self.phase = "contact"
        if self.phase == "contact":
            target[:2], target[2] = self.miss, depth + 0.0015
            if force > self.x.touch_force or depth > 0.001:
                self.phase = "align"
        feel = self.x.align == "feel"
        if self.phase == "align":
            target[2] = depth - 0.0003 if force >= self.x.touch_force else (
                depth + 0.0005 if feel else min(depth + 0.0005, 0.0))  # feel: rising is how it finds the hole
            if feel:
                target[:2] = self._away(tip, info)
            if (depth > 0.001) if feel else (np.linalg.norm(tip[:2]) < self.x.aligned):
                self.phase, self._best_depth, self._stuck = "push", depth, 0
        if self.phase == "push":  # rise more gently as the force grows; none at the jam force
            target[2] = depth + self.x.push_step * max(0.0, 1.0 - force / self.x.jam_force)
            if depth > self._best_depth + 0.0002:
                self._best_depth, self._stuck = depth, 0
            elif force > 0.5 * self.x.jam_force:
                self._stuck += 1
            if self._stuck >= 2 and self.retries < self.x.retries:  # jammed: back off and align again
                self.retries += 1
                self.phase = "back_off"
        if self.phase == "back_off":
            target[2] = min(depth, 0.0) - 0.002
            if feel:
                target[:2] = tip[:2]
            if depth < -0.0015:
                self.phase = "align"
        move = rot @ (self.x.gain * (target - tip))
        return np.concatenate([move, turn]).astype(np.float32)
