"""The Xela hand variant in MuJoCo: stock-length fingertips with Xela shells, the 18 pads, their sensors, readout.

:func:`make_xela_hand` turns the Digit 360 hand spec (envs/assets) into the Xela variant: each fingertip becomes the
curved Xela shell (a capsule of envs.sensors.xela.TIP_RADIUS and TIP_LENGTH on the stock-length distal link), and
each phalanx and palm pad becomes a thin box geom whose outer face is the skin, with a site at its pad frame. The
pads collide with the object like the rest of the hand (so the Xela hand has its own grasp caches); they add no mass.

:func:`add_xela_sensors` adds, per pad, a MuJoCo contact sensor on the pad geom (the ``CONTACT_SLOTS`` strongest
contacts with force, point and frame) and the pose of the pad frame, each with a history ring of ``substeps``
samples, as the Digit 360 sensors do (envs.sensors.digit360): one ``Batch.step(nstep=substeps)`` yields every
substep's reading. :class:`XelaReadout` turns that history into :class:`PadContacts` in the pad frames.
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import cache

import mujoco
import numpy as np

from envs.sensors.digit360 import quat_to_mat
from envs.sensors.xela import (
    LINK_RADIUS,
    PAD_TAXEL_INDEX,
    PAD_THICKNESS,
    PADS,
    TIP_LENGTH,
    TIP_RADIUS,
    TIP_START,
    V4_TIP_START,
    PadSpec,
    taxel_layout,
)

DISTAL_LINK = 0.02
"""Length (m) of the distal link's capsule inside the fingertip shell (the Digit 360 hand's is longer)."""
CONTACT_SLOTS = 4
"""Contacts reported per pad (the strongest first): a flat face resting on a pad makes 4 (box-box collision)."""
_SLOT_DATA = "found force pos normal tangent"
_SLOT_DIM = 1 + 3 + 3 + 3 + 3
_PAD_RGBA = [0.55, 0.62, 0.72, 1.0]


def pad_geom(pad: PadSpec) -> str:
    """Name of the geom that is a pad's skin (the fingertip shell keeps the hand's ``<finger>_tip`` name)."""
    return pad.body.replace("_distal", "_tip") if pad.kind == "fingertip" else f"xela_{pad.name}"


def pad_site(pad: PadSpec) -> str:
    """Name of the site at a pad's frame."""
    return f"xela_{pad.name}"


def sensor_name(pad: PadSpec, kind: str) -> str:
    return f"xela_{pad.name}_{kind}"


def _quat(rot: np.ndarray) -> list[float]:
    q = np.zeros(4)
    mujoco.mju_mat2Quat(q, np.ascontiguousarray(rot).ravel())
    return q.tolist()


def make_xela_hand(spec: mujoco.MjSpec, hand: str = "xela") -> None:
    """Edit a hand spec into a Xela hand (before compiling): fingertip shells, pad geoms and sites, at the pad
    mounts of ``hand`` (envs.sensors.xela_layout.pad_mounts): 'xela' edits the older model's Digit 360 hand,
    'xela_v4' the vendor-kinematics model with stock tips (envs.hand_model.hand_xml(tips='stock'))."""
    lay = taxel_layout(hand)
    if any(s.name == pad_site(PADS[0]) for s in spec.sites):
        raise ValueError("make_xela_hand: the spec already has the Xela pads")
    for p, pad in enumerate(PADS):
        body = spec.body(lay.pad_body[p])
        if body is None:
            raise ValueError(f"make_xela_hand: the spec has no body {lay.pad_body[p]!r} for pad {pad.name!r}")
        rot = lay.pad_rot[p]  # columns: pad x, y, z in the body frame
        origin = np.asarray(lay.pad_pos[p])
        body.add_site(name=pad_site(pad), pos=origin.tolist(), quat=_quat(rot), size=[0.002, 0, 0],
                      rgba=[0.2, 0.4, 1.0, 1.0], group=3)
        if pad.kind == "fingertip":
            tip = spec.geom(pad_geom(pad))
            site = spec.site(pad_geom(pad))
            if tip is None or site is None:
                raise ValueError(f"make_xela_hand: the spec needs a fingertip geom and site {pad_geom(pad)!r}")
            axis = rot[:, 0]
            # a capsule along the finger: its local z turned onto the finger axis
            turn = np.stack([rot[:, 1], np.cross(axis, rot[:, 1]), axis], axis=1)
            half = (TIP_LENGTH - 2 * TIP_RADIUS) / 2
            tip.type = mujoco.mjtGeom.mjGEOM_CAPSULE
            tip.size = [TIP_RADIUS, half, 0.0]
            start = TIP_START if hand == "xela" else V4_TIP_START["thumb" if pad.name.startswith("thumb") else "finger"]
            tip.pos = (axis * (start + TIP_RADIUS + half)).tolist()
            tip.quat = _quat(turn)
            tip.rgba = _PAD_RGBA
            for g in body.geoms:  # the distal link inside the shell
                if g.name == tip.name:
                    continue
                if g.type == mujoco.mjtGeom.mjGEOM_CAPSULE:  # the older model: back to the stock link's length
                    g.fromto = [0.0, 0.0, 0.0, *(axis * DISTAL_LINK).tolist()]
                    g.size = [LINK_RADIUS, 0.0, 0.0]
                elif g.type == mujoco.mjtGeom.mjGEOM_BOX:  # the vendor's: the shell covers it, the shell touches
                    g.contype, g.conaffinity = 0, 0
            site.pos = origin.tolist()  # the fingertip site: the dome centre, z along the finger as before
        else:
            length, width = pad.size
            body.add_geom(
                name=pad_geom(pad), type=mujoco.mjtGeom.mjGEOM_BOX,
                size=[length / 2, width / 2, PAD_THICKNESS / 2], pos=(origin - rot[:, 2] * PAD_THICKNESS / 2).tolist(),
                quat=_quat(rot), contype=1, conaffinity=2, condim=3, friction=[1.0, 0.01, 0.001],
                solref=[0.02, 1.0], solimp=[0.9, 0.95, 0.001, 0.5, 2.0], density=0.0, rgba=_PAD_RGBA,
            )


def _contact_data_bits() -> int:
    return sum(1 << int(getattr(mujoco.mjtConDataField, f"mjCONDATA_{name.upper()}")) for name in _SLOT_DATA.split())


def add_xela_sensors(spec: mujoco.MjSpec, history: int) -> None:
    """Add the contact and pad-frame sensors of the 18 pads (after :func:`make_xela_hand`), each keeping
    ``history`` samples (the env's substeps per policy step)."""
    if int(history) < 1:
        raise ValueError(f"add_xela_sensors: history must be >= 1 sample, got {history}")
    sites = {s.name for s in spec.sites}
    if pad_site(PADS[0]) not in sites:
        raise ValueError("add_xela_sensors: the spec has no Xela pads; build it with make_xela_hand first")
    if any(s.name == sensor_name(PADS[0], "contact") for s in spec.sensors):
        raise ValueError("add_xela_sensors: the spec already has the Xela sensors")
    for pad in PADS:
        for kind, stype, objtype, obj in (
            ("contact", mujoco.mjtSensor.mjSENS_CONTACT, mujoco.mjtObj.mjOBJ_GEOM, pad_geom(pad)),
            ("pos", mujoco.mjtSensor.mjSENS_FRAMEPOS, mujoco.mjtObj.mjOBJ_SITE, pad_site(pad)),
            ("quat", mujoco.mjtSensor.mjSENS_FRAMEQUAT, mujoco.mjtObj.mjOBJ_SITE, pad_site(pad)),
        ):
            sensor = spec.add_sensor(name=sensor_name(pad, kind), type=stype, objtype=objtype, objname=obj)
            sensor.nsample = int(history)
            if kind == "contact":
                # intprm = [data bits, reduce, num]; reduce 2 = "maxforce" (MuJoCo XML reference, sensor/contact)
                sensor.intprm[:3] = [_contact_data_bits(), 2, CONTACT_SLOTS]


@dataclass
class PadContacts:
    """The pads' contacts over S samples of N envs (P = 18 pads, K = CONTACT_SLOTS), in the pad frames."""

    times: np.ndarray
    """(N, S) sample times (s)."""
    found: np.ndarray
    """(N, S, P, K) bool: the slot holds a contact."""
    points: np.ndarray
    """(N, S, P, K, 3) contact points, pad frame (m)."""
    forces: np.ndarray
    """(N, S, P, K, 3) contact force on the pad, pad frame (N)."""
    normal: np.ndarray
    """(N, S, P, K) normal force magnitude (N, >= 0)."""
    shear: np.ndarray
    """(N, S, P, K, 3) tangential part of the force on the pad (across the contact normal), pad frame (N)."""
    pad_pos: np.ndarray
    """(N, S, P, 3) pad frame origins, world frame (m)."""
    pad_rot: np.ndarray
    """(N, S, P, 3, 3) pad frame axes (columns) in the world frame."""

    def pad_force(self) -> np.ndarray:
        """(N, S, P, 3) per-pad label [normal, shear x, shear y] (N, pad frame): the summed normal force of the
        pad's contacts and their summed tangential force along the pad frame's x and y."""
        return np.concatenate([self.normal.sum(axis=-1)[..., None], self.shear.sum(axis=-2)[..., :2]], axis=-1)

    def taxel_pos(self) -> np.ndarray:
        """(N, S, 368, 3) taxel positions in the world frame (= the hand frame: the palm is fixed at the origin)."""
        return place_taxels(self.pad_pos, self.pad_rot)


def place_taxels(pad_pos: np.ndarray, pad_rot: np.ndarray) -> np.ndarray:
    """Taxel positions (..., 368, 3) from the pad frames: origins (..., 18, 3) and axes (..., 18, 3, 3) (columns)
    in one frame, in taxel order (the simulator's readout and envs.sensors.xela_kinematics both place them here)."""
    local, taken = _padded_taxels()
    world = pad_rot @ local + pad_pos[..., None]  # (..., P, 3, 30): each pad's taxels, padded
    return np.swapaxes(world, -1, -2).reshape(*world.shape[:-3], -1, 3)[..., taken, :]


@cache
def _padded_taxels() -> tuple[np.ndarray, np.ndarray]:
    """Taxel positions per pad (18, 3, 30) in the pad frames, padded with zeros, and the indices (368,) of the real
    ones in the flattened (18 x 30) order (a batched matmul then places every pad's taxels at once)."""
    pos = taxel_layout().pos[np.maximum(PAD_TAXEL_INDEX, 0)] * (PAD_TAXEL_INDEX >= 0)[..., None]  # (P, 30, 3)
    return np.ascontiguousarray(np.swapaxes(pos, 1, 2)), np.flatnonzero(PAD_TAXEL_INDEX.ravel() >= 0)


def read_ring(history: np.ndarray, adr: np.ndarray, nsample: int, dim: int,
              count: int) -> tuple[np.ndarray, np.ndarray]:
    """Last ``count`` samples of P sensors whose history blocks start at ``adr`` (P,), oldest first: times
    (N, P, S), values (N, P, S, dim). A block is [last compute time, cursor, nsample times, nsample x dim values]
    (MuJoCo sensor history), ``cursor`` the slot of the newest sample."""
    n, p = history.shape[0], len(adr)
    cursor = history[:, adr + 1].astype(np.int64)  # (N, P)
    slots = (cursor[..., None] - count + 1 + np.arange(count)) % nsample  # (N, P, S)
    t_idx = adr[None, :, None] + 2 + slots
    times = np.take_along_axis(history, t_idx.reshape(n, -1), axis=1).reshape(n, p, count)
    v_idx = adr[None, :, None, None] + 2 + nsample + slots[..., None] * dim + np.arange(dim)
    values = np.take_along_axis(history, v_idx.reshape(n, -1), axis=1).reshape(n, p, count, dim)
    return times, values


class XelaReadout:
    """Reads the pads' sensors of N simulations (history rings or current sensordata) into :class:`PadContacts`."""

    def __init__(self, model: mujoco.MjModel):
        self._hist: dict[str, tuple[np.ndarray, int, int]] = {}
        self._data: dict[str, tuple[np.ndarray, int]] = {}
        self.nsample = 0
        for kind in ("contact", "pos", "quat"):
            ids = []
            for pad in PADS:
                sid = mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_SENSOR, sensor_name(pad, kind))
                if sid < 0:
                    raise ValueError(f"XelaReadout: the model has no sensor {sensor_name(pad, kind)!r}; build it "
                                     "with the Xela hand and add_xela_sensors(spec, history=substeps)")
                ids.append(sid)
            ids = np.asarray(ids)
            dims, ns = model.sensor_dim[ids], model.sensor_history[ids, 0]
            if len(set(dims)) != 1 or len(set(ns)) != 1 or ns[0] < 1:
                raise ValueError(f"XelaReadout: sensors 'xela_*_{kind}' need one dim and nsample >= 1")
            self._hist[kind] = (model.sensor_historyadr[ids], int(ns[0]), int(dims[0]))
            self._data[kind] = (model.sensor_adr[ids], int(dims[0]))
            self.nsample = int(ns[0]) if not self.nsample else min(self.nsample, int(ns[0]))
        if self._data["contact"][1] != CONTACT_SLOTS * _SLOT_DIM:
            raise ValueError(f"XelaReadout: contact sensors must report {CONTACT_SLOTS} slots of '{_SLOT_DATA}'")

    def read(self, history: np.ndarray, count: int) -> PadContacts:
        """The last ``count`` samples from the batch's ``history`` (N, nhistory), oldest first."""
        if count > self.nsample:
            raise ValueError(f"XelaReadout.read: {count} samples requested, the sensors keep {self.nsample}")
        history = np.asarray(history)
        times, contact = read_ring(history, *self._hist["contact"], count)
        _, pos = read_ring(history, *self._hist["pos"], count)
        _, quat = read_ring(history, *self._hist["quat"], count)
        sw = (0, 2, 1, 3)  # (N, P, S, d) -> (N, S, P, d)
        return contacts_from_sensors(times[:, 0], contact.transpose(sw), pos.transpose(sw), quat.transpose(sw))

    def read_current(self, sensordata: np.ndarray) -> PadContacts:
        """One sample (S = 1) from the current ``sensordata`` (N, nsensordata), e.g. after a reset."""
        sensordata = np.asarray(sensordata)

        def take(kind: str) -> np.ndarray:
            adr, dim = self._data[kind]
            return sensordata[:, adr[:, None] + np.arange(dim)][:, None]  # (N, 1, P, dim)

        return contacts_from_sensors(np.zeros((len(sensordata), 1)), take("contact"), take("pos"), take("quat"))


def contacts_from_sensors(times: np.ndarray, contact: np.ndarray, pos: np.ndarray, quat: np.ndarray) -> PadContacts:
    """Raw sensor values (N, S, P, K x 13), (N, S, P, 3), (N, S, P, 4) -> :class:`PadContacts`.

    The contact sensor's force is the force of its geom (the pad) on the other geom, in the contact frame
    [normal, tangent, normal x tangent] (MuJoCo XML reference, sensor/contact); the force on the pad is its negative.
    """
    slots = contact.reshape(*contact.shape[:-1], CONTACT_SLOTS, _SLOT_DIM)  # (N, S, P, K, 13)
    found = slots[..., 0] > 0
    f_c, p_w, n_w, t_w = slots[..., 1:4], slots[..., 4:7], slots[..., 7:10], slots[..., 10:13]
    b_w = np.cross(n_w, t_w)
    f_w = -(f_c[..., :1] * n_w + f_c[..., 1:2] * t_w + f_c[..., 2:3] * b_w)  # (N, S, P, K, 3) on the pad, world
    rot = quat_to_mat(quat)  # (N, S, P, 3, 3) pad -> world
    mask = found[..., None]
    forces = (f_w @ rot) * mask  # (..., K, 3) rows times R = R^T applied to each: pad frame
    points = ((p_w - pos[..., None, :]) @ rot) * mask
    normal = np.maximum(f_c[..., 0], 0.0) * found
    # tangential force, pad frame: the force minus its part along the contact normal (the force is along -normal)
    t_pad = ((f_w + normal[..., None] * n_w) @ rot) * mask
    return PadContacts(times, found, points, forces, normal, t_pad, pos, rot)

