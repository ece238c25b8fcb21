"""What a policy was trained on, in a form a bundle can record and a job can check: the hand model (a fingerprint
of its kinematics and fingertips) and the contact settings.

    sim = sim_record(cfg)                 # {"hand", "hand_sha256", "contact", "joint_torque_limits"}
    problem = hand_problem(sim, "digit360_v4")   # None, or one line saying why the policy does not fit

A bundle written before bundles recorded their sim trained on the 'digit360' hand (every shipped policy did).
"""

from __future__ import annotations

import dataclasses
import hashlib
from functools import cache
from typing import Any

import numpy as np

from envs.config import EnvConfig
from envs.scene import HANDS, hand_spec

LEGACY_HAND = "digit360"
"""The hand of a bundle that records no sim: the model every policy trained on before bundles recorded it."""
LEGACY_HANDS = ("digit360", "xela")
"""The variants of that model (the same kinematics; the Xela hand's tips are shorter): a bundle recording no sim
acts on either, as skin adapters on the Xela hand always have."""
_FIELDS = ("body_pos", "body_quat", "jnt_axis", "jnt_pos", "jnt_range", "geom_type", "geom_size", "geom_pos",
           "geom_quat", "site_pos")
"""Model arrays the fingerprint covers: where every link, joint, collision shape and fingertip site is."""


@cache
def hand_fingerprint(hand: str) -> str:
    """sha256 of a hand variant's kinematics and collision shapes (envs.scene.hand_spec compiled without an object),
    each array rounded to a micrometre / microradian so that float noise across machines does not change it."""
    if hand not in HANDS:
        raise ValueError(f"unknown hand {hand!r}; hands: {', '.join(HANDS)}")
    model = hand_spec(hand).compile()
    digest = hashlib.sha256(hand.encode())
    for name in _FIELDS:
        values = np.round(np.asarray(getattr(model, name), dtype=np.float64), 6) + 0.0  # -0.0 -> 0.0
        digest.update(name.encode())
        digest.update(values.tobytes())
    return digest.hexdigest()


def sim_record(cfg: EnvConfig) -> dict[str, Any]:
    """The sim a policy trained in ``cfg`` records in its bundle."""
    return {"hand": cfg.hand, "hand_sha256": hand_fingerprint(cfg.hand), "contact": dataclasses.asdict(cfg.contact),
            "joint_torque_limits": cfg.joint_torque_limits}


def bundle_hand(sim: dict[str, Any] | None) -> str:
    """The hand variant a bundle's recorded sim names (LEGACY_HAND when it records none)."""
    return str((sim or {}).get("hand", LEGACY_HAND))


def hand_problem(sim: dict[str, Any] | None, hand: str) -> str | None:
    """Why a policy with recorded ``sim`` cannot act on ``hand`` (a hand variant), or None when it can: another
    hand, or this hand's model changed since the policy trained on it."""
    trained = bundle_hand(sim)
    if not sim and hand in LEGACY_HANDS:
        return None
    if trained != hand:
        return f"it was trained on the {trained} hand, not the {hand} hand"
    recorded = (sim or {}).get("hand_sha256")
    if recorded is not None and trained in HANDS and recorded != hand_fingerprint(trained):
        return (f"the {trained} hand's model changed since it was trained (kinematics fingerprint "
                f"{str(recorded)[:12]} then, {hand_fingerprint(trained)[:12]} now)")
    return None

