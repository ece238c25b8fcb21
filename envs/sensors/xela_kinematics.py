"""Xela taxel positions from the hand's joint angles (forward kinematics), for recordings of the real hand.

A simulated skin session (`rotate collect --skin`) stores ``skin/taxel_pos`` from the simulator's pad-frame sensors
(envs.sensors.xela_hand.PadContacts.taxel_pos); a real recording (`rotate deploy --skin`) has only the measured
joint angles. :class:`XelaKinematics` computes the same positions from those angles::

    kin = XelaKinematics("xela")            # a Xela hand variant (XELA_HANDS); see xela_hand_for()
    pos = kin.taxel_positions(q)            # q (T, 16) rad -> (T, 368, 3) m, hand frame, taxel order (PADS)
    q_at = joints_at(t_joint, q, t_skin)    # joint angles at the skin frames' times (per joint, linear)

What is assumed:

- Joint order: the Allegro bus order of every joint vector in this project (envs.constants.JOINT_NAMES: index 0-3,
  middle 4-7, ring 8-11, thumb 12-15, each finger [abduction, MCP, PIP, DIP]), radians, Allegro frame: the order
  of ``joints/position`` in a session and of the drivers' HandState.q. Each angle is written to the qpos of the
  MJCF joint of that name (the env writes qpos[:16] in this order: the hand models declare their joints in it).
- Model: the hand alone (envs.scene.hand_spec of the variant, no object), the pad sites of make_xela_hand and the
  taxels of taxel_layout placed by xela_hand.place_taxels: the model, pad frames and layout the simulator uses.
- Hand frame: the model's world frame, in which the palm body is fixed at the origin (as in the simulator; the
  'xela_v4' palm's own axes are turned in it). It is the frame of a simulated session's ``skin/taxel_pos``.
- Which hand: the Xela variant with the kinematics of the hand that moved (:func:`xela_hand_for`): a real
  Allegro moves as the vendor's kinematics (REAL_ALLEGRO_HAND); an emulated one as the policy's model.
- Between joint samples (20 Hz control steps) the angles are interpolated linearly per joint (:func:`joints_at`);
  a frame after the last joint sample holds it for at most JOINT_HOLD_S, a frame before the first has none.

Speed: one mj_kinematics per frame, the placement batched: about 30 us a frame on this project's busy 2-core
machine, so the 60,000 frames of a 10-minute recording at 100 Hz take 2-4 s when passed in chunks of ~1,000 frames
(one call for all of them fills a 530 MB array and ran 3x slower). tests/envs/test_xela_kinematics.py bounds it.
"""

from __future__ import annotations

import os
import threading

import mujoco
import numpy as np

from envs.constants import JOINT_NAMES, NUM_JOINTS
from envs.sensors.xela_hand import pad_site, place_taxels
from envs.sensors.xela_layout import NUM_PADS, NUM_TAXELS, PADS, XELA_HANDS

DEFAULT_HAND = "xela"
"""The hand of the skin simulation (`rotate collect --skin`): used when a recording names no hand."""
REAL_ALLEGRO_HAND = "xela_v4"
"""The Xela variant of the vendor's Allegro V4 kinematics (envs.hand_model), the kinematics of a real Allegro (the
model rotation.deploy.policy.REAL_ALLEGRO_MODEL names for policies)."""
XELA_HAND_OF = {"xela": "xela", "digit360": "xela", "xela_v4": "xela_v4", "digit360_v4": "xela_v4"}
"""Hand variant (envs.scene.HANDS) -> the Xela variant of the same kinematics (the Digit 360 hands differ in their
fingertips only)."""
JOINT_HOLD_S = 0.1
"""Longest time (s) past the last joint sample a skin frame may take that sample's angles (two control steps at
20 Hz): after that nothing says where the fingers were (a run's end: the motors go off)."""
_TIME_EPS = 1e-9
_CHUNK = 256
"""Frames placed at once (their arrays stay in the cache)."""


def xela_hand_for(hand: str) -> str:
    """The Xela hand variant with the kinematics of ``hand`` (a variant of envs.scene.HANDS); ValueError otherwise."""
    if hand not in XELA_HAND_OF:
        raise ValueError(f"no Xela skin model for the hand {hand!r}: taxel positions are computed on the Allegro "
                         f"models {', '.join(XELA_HAND_OF)} (a LEAP hand has no Xela layout here)")
    return XELA_HAND_OF[hand]


def _joint_array(q: np.ndarray, where: str) -> np.ndarray:
    q = np.asarray(q, dtype=np.float64)
    if q.ndim == 1:
        q = q[None]
    if q.ndim != 2 or q.shape[1] != NUM_JOINTS:
        raise ValueError(f"{where}: joint angles must be (T, {NUM_JOINTS}) rad in the Allegro bus order "
                         f"(envs.constants.JOINT_NAMES), got shape {q.shape}")
    if not np.all(np.isfinite(q)):
        bad = np.flatnonzero(~np.isfinite(q).all(axis=1))
        raise ValueError(f"{where}: non-finite joint angles in {len(bad)} of {len(q)} rows (first: row {bad[0]})")
    return q


def covered(t_joint: np.ndarray, t: np.ndarray, hold_s: float = JOINT_HOLD_S) -> np.ndarray:
    """(n,) bool: which times ``t`` have joint angles (:func:`joints_at`) from samples at ``t_joint``."""
    t_joint, t = np.asarray(t_joint, np.float64), np.asarray(t, np.float64)
    if len(t_joint) == 0:
        return np.zeros(t.shape, bool)
    return (t >= t_joint[0] - _TIME_EPS) & (t <= t_joint[-1] + hold_s + _TIME_EPS)


def joints_at(t_joint: np.ndarray, q: np.ndarray, t: np.ndarray, hold_s: float = JOINT_HOLD_S) -> np.ndarray:
    """Joint angles (n, 16) at times ``t`` (n,) from samples ``q`` (m, 16) at ``t_joint`` (m,), all in one clock:
    linear per joint between the samples around each time, the last sample held up to ``hold_s`` after it.
    ValueError when a time lies before the first sample or later than that, or the samples are malformed."""
    q = _joint_array(q, "joints_at")
    t_joint, t = np.asarray(t_joint, np.float64), np.asarray(t, np.float64).reshape(-1)
    if t_joint.shape != (len(q),) or len(q) == 0 or not np.all(np.isfinite(t_joint)) or np.any(np.diff(t_joint) < 0):
        raise ValueError(f"joints_at: need at least one joint sample with finite, non-decreasing times (m,) for the "
                         f"angles (m, 16); got times {t_joint.shape}, angles {q.shape}")
    ok = covered(t_joint, t, hold_s)
    if not ok.all():
        first = t[~ok][0]
        raise ValueError(f"joints_at: no joint angles at t={first:.4f} s ({int((~ok).sum())} of {len(t)} times): "
                         f"the joints were sampled from {t_joint[0]:.4f} to {t_joint[-1]:.4f} s (held "
                         f"{hold_s:g} s after); select the covered times first (covered())")
    return np.stack([np.interp(t, t_joint, q[:, j]) for j in range(NUM_JOINTS)], axis=1)


class XelaKinematics:
    """Forward kinematics of one Xela hand variant: joint angles -> pad frames -> taxel positions (see the module
    docstring). One MjData, used under a lock (threads may share an instance; worker processes build their own)."""

    def __init__(self, hand: str = DEFAULT_HAND):
        if hand not in XELA_HANDS:
            raise ValueError(f"XelaKinematics: unknown Xela hand {hand!r}; Xela hands: {', '.join(XELA_HANDS)} "
                             "(xela_hand_for() maps a policy's hand to one)")
        from envs.scene import hand_spec  # envs.scene imports the sensors' modules lazily: no cycle

        self.hand = hand
        self.model = hand_spec(hand).compile()
        self._data = mujoco.MjData(self.model)
        ids = [mujoco.mj_name2id(self.model, mujoco.mjtObj.mjOBJ_JOINT, n) for n in JOINT_NAMES]
        if min(ids) < 0:
            raise ValueError(f"XelaKinematics: the {hand} hand model lacks joint(s) "
                             f"{[n for n, i in zip(JOINT_NAMES, ids, strict=True) if i < 0]}")
        self.qpos_adr = self.model.jnt_qposadr[ids].copy()
        """(16,) qpos address of each bus-order joint."""
        self.site_ids = np.array([mujoco.mj_name2id(self.model, mujoco.mjtObj.mjOBJ_SITE, pad_site(p)) for p in PADS])
        """(18,) the pad-frame sites, in PADS order."""
        self._lock = threading.Lock()

    def pad_frames(self, q: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Joint angles (T, 16) or (16,), bus order, rad -> pad frame origins (T, 18, 3) m and axes (T, 18, 3, 3)
        (columns x, y, z), hand frame."""
        q = _joint_array(q, f"XelaKinematics({self.hand!r})")
        pos = np.empty((len(q), NUM_PADS, 3))
        rot = np.empty((len(q), NUM_PADS, 9))
        m, d, adr, sites = self.model, self._data, self.qpos_adr, self.site_ids
        with self._lock:
            for i, qi in enumerate(q):
                d.qpos[adr] = qi
                mujoco.mj_kinematics(m, d)
                pos[i] = d.site_xpos[sites]
                rot[i] = d.site_xmat[sites]
        return pos, rot.reshape(len(q), NUM_PADS, 3, 3)

    def taxel_positions(self, q: np.ndarray) -> np.ndarray:
        """Joint angles (T, 16) or (16,), bus order, rad -> taxel positions (T, 368, 3) float64, m, hand frame, in
        taxel order (envs.sensors.xela.PADS)."""
        q = _joint_array(q, f"XelaKinematics({self.hand!r})")
        out = np.empty((len(q), NUM_TAXELS, 3))
        for a in range(0, len(q), _CHUNK):  # in chunks: the placement of 6,000 frames at once ran 10x slower
            out[a : a + _CHUNK] = place_taxels(*self.pad_frames(q[a : a + _CHUNK]))
        return out


_SHARED: dict[tuple[int, str], XelaKinematics] = {}


def kinematics(hand: str = DEFAULT_HAND) -> XelaKinematics:
    """The process's one :class:`XelaKinematics` of ``hand`` (a forked worker, e.g. a DataLoader's, builds its own:
    a lock held by another thread at the fork would stay held there)."""
    key = (os.getpid(), hand)
    if key not in _SHARED:
        _SHARED[key] = XelaKinematics(hand)
    return _SHARED[key]
