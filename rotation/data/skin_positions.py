"""Taxel positions of a skin session: the stored ``skin/taxel_pos``, or computed from ``joints/position``.

A simulated skin session (`rotate collect --skin`) stores the simulator's taxel positions; a recording of the real
hand (`rotate deploy --skin`) stores them too from now on, computed when it closes (rotation.deploy.recording). A
recording without them (an older one, or one whose run was killed before it closed) gets them here, frame by frame
as they are read, from its measured joint angles by forward kinematics (envs.sensors.xela_kinematics): the angles
of the ``joints/position`` stream (bus order, rad) interpolated linearly per joint to the ``skin/xela`` frame's
timestamp, on the Xela hand model of :func:`session_skin_hand`, in the hand frame of the simulator (palm fixed at
the origin). Frames before the first joint sample, or more than envs.sensors.xela_kinematics.JOINT_HOLD_S after
the last, have no position (SkinWindows leaves their windows out).

Which hand model (:func:`session_skin_hand`), first found of: ``extra["skin_hand"]`` (written by `rotate deploy
--skin`); ``extra["hand"]`` when it names a hand variant (simulated sessions); for a deploy recording, the real
Allegro's kinematics (envs.sensors.xela_kinematics.REAL_ALLEGRO_HAND) on ``--hand allegro``, the policy's model
(``extra["policy_sim"]``) on an emulated hand; else the skin simulation's hand (DEFAULT_HAND). A LEAP hand, or a
hand without a Xela model, is refused (SessionError).
"""

from __future__ import annotations

from typing import Any

import numpy as np

from envs.sensors.xela_kinematics import (
    DEFAULT_HAND,
    JOINT_HOLD_S,
    REAL_ALLEGRO_HAND,
    joints_at,
    kinematics,
    xela_hand_for,
)
from envs.sensors.xela_layout import XELA_HANDS
from envs.sim_identity import bundle_hand
from rotation.data.session import SessionError, SessionMeta
from rotation.data.session_reader import SessionReader

SKIN_HAND_KEY = "skin_hand"
"""Session ``extra`` key naming the Xela hand model (envs.sensors.xela.XELA_HANDS) the taxel positions are of."""
EMULATED_HANDS = ("sim-allegro", "sim-leap")
"""`rotate deploy --hand` values whose body is the policy's simulated Allegro model (sim-leap: the LEAP's bus)."""
STORED = "stored"
"""What :func:`position_source` returns for a session that stores its taxel positions."""


def session_skin_hand(meta: SessionMeta, where: str) -> str:
    """The Xela hand model of a session's taxel positions (see the module docstring); SessionError naming
    ``where`` when the session's hand has none."""
    extra: dict[str, Any] = meta.extra
    named = extra.get(SKIN_HAND_KEY)
    if named is not None:
        if named not in XELA_HANDS:
            raise SessionError(f"{where}: extra[{SKIN_HAND_KEY!r}] = {named!r} is not a Xela hand "
                               f"({', '.join(XELA_HANDS)})")
        return str(named)
    hand = extra.get("hand")
    if hand is None:
        if meta.hand == "leap" and meta.source == "real":
            hand = "leap"
        else:
            return DEFAULT_HAND
    if hand == "allegro":  # `rotate deploy --hand allegro`: the real hand moves as the vendor's kinematics
        return REAL_ALLEGRO_HAND
    if hand in EMULATED_HANDS:  # the emulated body is the policy's model
        hand = bundle_hand(extra.get("policy_sim"))
    try:
        return xela_hand_for(str(hand))
    except ValueError as err:
        raise SessionError(f"{where}: {err}") from None


def position_source(r: SessionReader) -> str:
    """:data:`STORED` when the session stores taxel positions, else the Xela hand model to compute them on from
    ``joints/position``; SessionError when it has neither."""
    if r.has("skin/taxel_pos") and len(r.stream("skin/taxel_pos", lazy=True)):
        return STORED
    if not r.has("joints/position") or not len(r.stream("joints/position", lazy=True)):
        raise SessionError(f"session {r.path}: no taxel positions: neither a skin/taxel_pos stream nor a "
                           f"joints/position stream to compute them from (has: {', '.join(r.names) or 'none'}); "
                           "`rotate collect --skin` and `rotate deploy --skin --record` record them")
    return session_skin_hand(r.meta, f"session {r.path}")


def position_span(r: SessionReader, source: str) -> tuple[float, float]:
    """First and last session time (s) a skin frame may have a taxel position at."""
    if source == STORED:
        t = r.stream("skin/taxel_pos", lazy=True).timestamps
        return float(t[0]), float(t[-1])
    t = r.stream("joints/position", lazy=True).timestamps
    return float(t[0]), float(t[-1]) + JOINT_HOLD_S


def computed_positions(r: SessionReader, hand: str, t: np.ndarray) -> np.ndarray:
    """Taxel positions (n, 368, 3) float32 at session times ``t`` (n,) (non-decreasing, inside position_span; one
    before the first joint sample takes it), from ``joints/position`` interpolated per joint, on the Xela hand
    model ``hand``."""
    st = r.stream("joints/position", lazy=True)
    tj = st.timestamps
    # a frame of a window inside the span may be stamped a little before the first joint sample (jitter): it
    # takes that sample; the span's end is compared with a tolerance: clip to it
    t = np.clip(np.asarray(t, np.float64), tj[0], tj[-1] + JOINT_HOLD_S)
    lo = max(int(np.searchsorted(tj, t[0], side="right")) - 1, 0)  # the samples around the frames only
    hi = min(int(np.searchsorted(tj, t[-1], side="left")) + 1, len(tj))
    q = np.asarray(st.data[lo:hi], dtype=np.float64)
    try:
        return kinematics(hand).taxel_positions(joints_at(tj[lo:hi], q, t)).astype(np.float32)
    except ValueError as err:
        raise SessionError(f"session {r.path}, stream 'joints/position': {err}") from None
