"""A canonical grasp pose for the vendor-kinematics hand (envs.hand_model) around an upright cup, by sampling IK.

Grasp generation (envs.grasps) samples joint poses around one canonical pose that puts the index, middle and ring
domes on one side of the cup and the thumb's on the other. The pose of the model the env uses today does not fit
the vendor's kinematics (its thumb is mounted elsewhere and joint 0 rolls the finger), so the new hand needs its
own. For each candidate cup centre this searches each finger's four joints on its own (the fingers are independent
chains): random samples within the joint limits, then a shrinking random walk, minimizing the distance of the dome
centre to its target on the cup's surface plus a term that turns the dome (the site's z axis) toward the cup's axis,
so the dome touches the cup rather than the sensor body behind it.

    python experiments/tools/canonical_pose.py --out runs/canonical_pose
    python experiments/tools/canonical_pose.py --centres-x 0.04 0.06 --centres-z 0.06 0.07 --out runs/cp

Writes OUT/canonical_pose.json (the best pose and centre, and every candidate's cost) and OUT/canonical_pose.png
(front, side and top views of the hand holding a cylinder of the cup's radius); the last line printed is the JSON.
"""

from __future__ import annotations

import json
import os
from dataclasses import dataclass
from pathlib import Path

os.environ.setdefault("MUJOCO_GL", "egl")

import mujoco  # noqa: E402
import numpy as np  # noqa: E402

from envs import constants as C  # noqa: E402
from envs.objects import get_object  # noqa: E402
from envs.scene import hand_spec  # noqa: E402
from envs.validation import check_output_dir  # noqa: E402
from rotation.configs import script_main  # noqa: E402


@dataclass
class Config:
    out: Path = Path("runs/canonical_pose")
    """Report directory."""
    object: str = "cup"
    """Object whose radius (at the nominal scale) the domes are placed around."""
    scale: float = 0.78
    """Object scale (the middle of the randomization's buckets)."""
    centres_x: tuple[float, ...] = (0.04, 0.06, 0.08)
    """Candidate cup centres along the fingers (m, world x; the finger roll axes are at 0)."""
    centres_z: tuple[float, ...] = (0.06, 0.07, 0.08)
    """Candidate cup centre heights above the finger roll axes (m, world z)."""
    spread: float = 0.5
    """Angle (rad) between the middle finger's dome and the index's and ring's around the cup's axis."""
    facing_weight: float = 0.02
    """Weight (m) of the dome facing the cup's axis: 0.02 = a dome turned 90 degrees away costs as much as 2 cm."""
    samples: int = 4000
    """Random samples per finger and candidate centre."""
    seed: int = 0
    """Sampling seed."""
    hand: str = "digit360_v4"
    """The vendor-kinematics hand variant: 'digit360_v4' (Digit 360 domes, which touch with their end) or 'xela_v4'
    (Xela shells, which touch with their palmar side: the cost turns the fingertip pad's normal to the cup)."""

    def __post_init__(self) -> None:
        if self.hand not in ("digit360_v4", "xela_v4"):
            raise ValueError(f"hand must be 'digit360_v4' or 'xela_v4', got {self.hand!r}")
        if not self.centres_x or not self.centres_z:
            raise ValueError("centres_x and centres_z need at least one value each")
        if self.samples < 10:
            raise ValueError(f"samples must be >= 10, got {self.samples}")


class Hand:
    """The model and the cost of one finger's dome against its target."""

    def __init__(self, variant: str = "digit360_v4") -> None:
        self.model = hand_spec(variant).compile()
        self.data = mujoco.MjData(self.model)
        self.radius = float(self.model.geom("middle_tip").size[0])
        # the axis that must face the cup: the dome's own (along the finger), or the Xela fingertip pad's normal
        self.facing_site = "{}_tip" if variant == "digit360_v4" else "xela_{}_tip"

    def cost(self, q: np.ndarray, finger: int, target: np.ndarray, centre: np.ndarray, weight: float) -> float:
        self.data.qpos[:16] = q
        mujoco.mj_kinematics(self.model, self.data)
        site = self.data.site(f"{C.FINGERS[finger]}_tip")
        inward = centre - target
        inward[2] = 0.0
        inward /= np.linalg.norm(inward)
        facing = self.data.site(self.facing_site.format(C.FINGERS[finger])).xmat.reshape(3, 3)[:, 2] @ inward
        return float(np.linalg.norm(site.xpos - target)) + weight * (1.0 - facing)


def targets(centre: np.ndarray, radius: float, spread: float) -> np.ndarray:
    """(4, 3) dome centres: index, middle, ring on the +x side (index toward -y), the thumb on the -x side."""
    angles = (-spread, 0.0, spread, np.pi)
    return np.array([centre + radius * np.array([np.cos(a), np.sin(a), 0.0]) for a in angles])


def solve(hand: Hand, centre: np.ndarray, reach: float, cfg: Config, rng: np.random.Generator
          ) -> tuple[np.ndarray, float]:
    """The pose that best places every dome around a cup at ``centre``, and its summed cost."""
    goal = targets(centre, reach, cfg.spread)
    q = (C.JOINT_LOWER + C.JOINT_UPPER) / 2
    total = 0.0
    for f in range(4):
        sl = slice(4 * f, 4 * f + 4)
        lo, hi = C.JOINT_LOWER[sl], C.JOINT_UPPER[sl]

        def cost(x: np.ndarray, f: int = f, sl: slice = sl) -> float:
            trial = q.copy()
            trial[sl] = x
            return hand.cost(trial, f, goal[f], centre, cfg.facing_weight)

        candidates = rng.uniform(lo, hi, (cfg.samples, 4))
        costs = [cost(x) for x in candidates]
        x, best = candidates[int(np.argmin(costs))], float(min(costs))
        step = 0.1
        for _ in range(400):  # a shrinking random walk from the best sample
            y = np.clip(x + rng.normal(0.0, step, 4), lo, hi)
            c = cost(y)
            if c < best:
                x, best = y, c
            else:
                step = max(step * 0.98, 0.005)
        q[sl] = x
        total += best
    return q, total


def picture(q: np.ndarray, centre: np.ndarray, radius: float, height: float, path: Path,
            variant: str = "digit360_v4") -> list[tuple]:
    """Render the pose with a cylinder of the object's size at ``centre``; returns the hand-object contacts."""
    import imageio

    spec = hand_spec(variant)
    body = spec.worldbody.add_body(name="object", pos=centre.tolist())
    body.add_geom(type=mujoco.mjtGeom.mjGEOM_CYLINDER, size=[radius, height / 2, 0], rgba=[0.85, 0.45, 0.2, 0.7],
                  contype=2, conaffinity=1)
    model = spec.compile()
    data = mujoco.MjData(model)
    data.qpos[:16] = q
    mujoco.mj_forward(model, data)
    contacts = [(model.geom(c.geom1).name or "object", model.geom(c.geom2).name or "object", round(1000 * c.dist, 1))
                for c in data.contact[: data.ncon]]
    renderer = mujoco.Renderer(model, 360, 480)
    views = []
    for cam in ("front", "side", "top"):
        renderer.update_scene(data, camera=cam)
        views.append(renderer.render())
    imageio.imwrite(path, np.concatenate(views, axis=1)[::2, ::2])
    return contacts


def run(cfg: Config) -> dict:
    check_output_dir("out", cfg.out)
    out = Path(cfg.out)
    obj = get_object(cfg.object)
    radius, height = obj.radius * cfg.scale, obj.length * cfg.scale
    hand = Hand(cfg.hand)
    rng = np.random.default_rng(cfg.seed)
    rows = []
    for x in cfg.centres_x:
        for z in cfg.centres_z:
            centre = np.array([x, 0.0, z])
            q, total = solve(hand, centre, radius + hand.radius, cfg, rng)
            rows.append({"centre": centre.tolist(), "cost": total, "pose": q.tolist()})
            print(f"centre ({x:.3f}, 0, {z:.3f}): cost {1000 * total:.1f} mm", flush=True)
    best = min(rows, key=lambda r: r["cost"])
    out.mkdir(parents=True, exist_ok=True)
    contacts = picture(np.asarray(best["pose"]), np.asarray(best["centre"]), radius, height,
                       out / "canonical_pose.png", cfg.hand)
    report = {"object": cfg.object, "scale": cfg.scale, "best": best, "contacts": contacts, "candidates": rows}
    (out / "canonical_pose.json").write_text(json.dumps(report, indent=1))
    print(json.dumps({"best": best, "contacts": contacts}))
    return report


if __name__ == "__main__":
    raise SystemExit(script_main(Config, run, __doc__))
