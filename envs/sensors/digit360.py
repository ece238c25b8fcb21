"""Simulated Digit 360 fingertips, MuJoCo side: the sensors added to the hand and the per-substep contact fields.

What MuJoCo measures (physical, exact up to the contact model): per fingertip dome geom, a ``contact`` sensor
(MuJoCo >= 3.3) reporting the two strongest contacts (``reduce="maxforce"``) with their force in the contact
frame, position, frame, and the relative velocity at the contact point; an ``accelerometer`` at the dome centre
(specific force, m/s^2, +g upward at rest); ``framepos``/``framequat`` of the fingertip site to express all of it
in the sensor frame. Every sensor keeps a history ring of ``substeps`` samples (``nsample``), so one
``Batch.step(nstep=substeps)`` yields every substep's reading through the ``history`` field without a Python loop
over substeps (with ``mujoco.batch.Batch`` only DATA_FIELDS such as ``history`` are readable per simulation,
not ``data.contact``). Sensors do not change the dynamics.

:class:`Digit360Readout` turns the raw history into the *contact fields*: one row of ``CONTACT_FIELDS`` per
fingertip per physics substep, all in the sensor frame (site frame: origin at the dome centre, z out of the dome).
These rows are what simulated sessions store; the four Digit 360 streams (image, audio, IMU, pressure) are rendered
from them by :mod:`envs.sensors.digit360_render`, in the env and in the data loader alike.
"""

from __future__ import annotations

import mujoco
import numpy as np

from envs import constants as C

FINGERS = C.FINGERS
"""Fingertips in bus order: index, middle, ring, thumb."""
DOME_RADIUS = 0.014
"""Radius of the Digit 360 dome (m): the fingertip sphere geoms of the hand MJCF (envs/assets)."""
CONTACT_SLOTS = 2
"""Contacts reported per fingertip (the strongest first). A dome touching one convex object has one contact;
the second slot catches a cup's handle or rim at the same time."""

_SLOT_FIELDS = ("found", "fn", "x", "y", "z", "vn", "slip")
CONTACT_FIELDS: tuple[str, ...] = (
    "force_n", "force_x", "force_y", "acc_x", "acc_y", "acc_z",
    *(f"c{k}_{name}" for k in range(CONTACT_SLOTS) for name in _SLOT_FIELDS),
)
"""Columns of a contact-field row (sensor frame, SI units):

- ``force_n, force_x, force_y``: net contact force of the world on the fingertip (N); ``force_n = -F_z`` is the
  normal part (> 0 when pressed), ``force_x, force_y`` the shear.
- ``acc_x, acc_y, acc_z``: specific force at the dome centre (m/s^2), what an accelerometer there reads.
- per contact slot k: ``ck_found`` (1 if the slot holds a contact), ``ck_fn`` (normal force, N, >= 0),
  ``ck_x, ck_y, ck_z`` (contact point, m), ``ck_vn`` (normal relative velocity, m/s, > 0 separating),
  ``ck_slip`` (tangential relative speed at the contact point, m/s).
"""
NUM_FIELDS = len(CONTACT_FIELDS)
FIELD = {name: i for i, name in enumerate(CONTACT_FIELDS)}
"""Column index by name."""

_SLOT_DATA = "found force pos normal tangent linvel"
_SLOT_DIM = 1 + 3 + 3 + 3 + 3 + 3
"""Numbers per contact slot for data="found force pos normal tangent linvel" (MuJoCo XML reference, contact)."""
_SENSORS = ("contact", "acc", "pos", "quat")


def sensor_name(finger: str, kind: str) -> str:
    """Name of a Digit 360 sensor in the model, e.g. ``index_d360_contact``."""
    return f"{finger}_d360_{kind}"


def add_digit360_sensors(spec: mujoco.MjSpec, history: int) -> None:
    """Add the Digit 360 sensors of the four fingertips to a hand spec (before compiling).

    Args:
        spec: the hand (+ object) spec; needs sites and dome geoms named ``<finger>_tip`` (envs.constants).
        history: samples kept per sensor (MuJoCo ``nsample``); the env passes its substeps per policy step so that
            every substep of the last step stays readable after one multi-substep ``Batch.step``.
    """
    if int(history) < 1:
        raise ValueError(f"add_digit360_sensors: history must be >= 1 sample, got {history}")
    sites = {s.name for s in spec.sites}
    geoms = {g.name for g in spec.geoms}
    existing = {s.name for s in spec.sensors}
    for finger in FINGERS:
        tip = f"{finger}_tip"
        if tip not in sites or tip not in geoms:
            raise ValueError(f"add_digit360_sensors: the spec needs a site and a geom named {tip!r}")
        if sensor_name(finger, "contact") in existing:
            raise ValueError(f"add_digit360_sensors: the spec already has Digit 360 sensors ({finger})")
        for kind, stype, objtype in (
            ("contact", mujoco.mjtSensor.mjSENS_CONTACT, mujoco.mjtObj.mjOBJ_GEOM),
            ("acc", mujoco.mjtSensor.mjSENS_ACCELEROMETER, mujoco.mjtObj.mjOBJ_SITE),
            ("pos", mujoco.mjtSensor.mjSENS_FRAMEPOS, mujoco.mjtObj.mjOBJ_SITE),
            ("quat", mujoco.mjtSensor.mjSENS_FRAMEQUAT, mujoco.mjtObj.mjOBJ_SITE),
        ):
            sensor = spec.add_sensor(name=sensor_name(finger, kind), type=stype, objtype=objtype, objname=tip)
            sensor.nsample = int(history)  # a history ring: every substep of a multi-substep step stays readable
            if kind == "contact":
                # intprm = [data bits, reduce, num] as the XML parser writes it; reduce 2 = "maxforce" (strongest
                # first), see the MuJoCo XML reference, sensor/contact
                sensor.intprm[:3] = [_contact_data_bits(), 2, CONTACT_SLOTS]


def _contact_data_bits() -> int:
    """Bit mask of the contact sensor's data fields (one bit per ``mjtConDataField``)."""
    return sum(1 << int(getattr(mujoco.mjtConDataField, f"mjCONDATA_{name.upper()}")) for name in _SLOT_DATA.split())


def quat_to_mat(q: np.ndarray) -> np.ndarray:
    """(..., 4) unit quaternions (w, x, y, z) -> (..., 3, 3) rotation matrices (body -> world)."""
    w, x, y, z = np.moveaxis(q, -1, 0)
    return np.stack(
        [
            1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y),
            2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x),
            2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y),
        ],
        axis=-1,
    ).reshape(*q.shape[:-1], 3, 3)


class Digit360Readout:
    """Reads the Digit 360 sensors' history rings of N simulations and converts them to contact-field rows.

    Built from the compiled model; :meth:`read` takes the batch's ``history`` array, :meth:`read_current` the
    ``sensordata`` array (the state after a reset / forward).
    """

    def __init__(self, model: mujoco.MjModel):
        self.nsample = None
        self._hist: dict[str, tuple[np.ndarray, int, int]] = {}  # kind -> (history adrs (4,), nsample, dim)
        self._data: dict[str, tuple[np.ndarray, int]] = {}  # kind -> (sensordata adrs (4,), dim)
        for kind in _SENSORS:
            ids = []
            for finger in FINGERS:
                name = sensor_name(finger, kind)
                sid = mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_SENSOR, name)
                if sid < 0:
                    raise ValueError(f"Digit360Readout: the model has no sensor {name!r}; build it with "
                                     "add_digit360_sensors(spec, history=substeps)")
                ids.append(sid)
            ids = np.asarray(ids)
            dims, ns = model.sensor_dim[ids], model.sensor_history[ids, 0]
            if len(set(dims)) != 1 or len(set(ns)) != 1 or ns[0] < 1:
                raise ValueError(f"Digit360Readout: sensors '*_d360_{kind}' need one dim and nsample >= 1")
            self._hist[kind] = (model.sensor_historyadr[ids], int(ns[0]), int(dims[0]))
            self._data[kind] = (model.sensor_adr[ids], int(dims[0]))
            self.nsample = int(ns[0]) if self.nsample is None else min(self.nsample, int(ns[0]))
        if self._data["contact"][1] != CONTACT_SLOTS * _SLOT_DIM:
            raise ValueError("Digit360Readout: contact sensors must report "
                             f"{CONTACT_SLOTS} slots of '{_SLOT_DATA}'")

    def _ring(self, history: np.ndarray, kind: str, count: int) -> tuple[np.ndarray, np.ndarray]:
        """Last ``count`` samples of sensor ``kind``, oldest first: times (N, 4, S), values (N, 4, S, dim).

        History block of one sensor (MuJoCo sensor history): [last compute time, cursor, nsample timestamps,
        nsample x dim values]; ``cursor`` is the slot of the newest sample.
        """
        adr, ns, dim = self._hist[kind]
        n = history.shape[0]
        cursor = history[:, adr + 1].astype(np.int64)  # (N, 4)
        slots = (cursor[..., None] - count + 1 + np.arange(count)) % ns  # (N, 4, S), oldest first
        t_idx = adr[None, :, None] + 2 + slots  # (N, 4, S)
        times = np.take_along_axis(history, t_idx.reshape(n, -1), axis=1).reshape(n, 4, count)
        v_idx = (adr[None, :, None, None] + 2 + ns + slots[..., None] * dim + np.arange(dim))  # (N, 4, S, dim)
        values = np.take_along_axis(history, v_idx.reshape(n, -1), axis=1).reshape(n, 4, count, dim)
        return times, values

    def read(self, history: np.ndarray, count: int) -> tuple[np.ndarray, np.ndarray]:
        """Contact fields of the last ``count`` substeps from the batch's ``history`` (N, nhistory).

        Returns:
            times (N, S) float64: simulation time of each sample (s), the time at the start of the substep whose
                sensor stage computed it (the state MuJoCo's sensors describe);
            rows (N, 4, S, NUM_FIELDS) float32: contact fields per fingertip, oldest first.
        """
        if count > self.nsample:
            raise ValueError(f"Digit360Readout.read: {count} substeps requested, sensors keep {self.nsample}")
        history = np.asarray(history)
        times, contact = self._ring(history, "contact", count)
        _, acc = self._ring(history, "acc", count)
        _, pos = self._ring(history, "pos", count)
        _, quat = self._ring(history, "quat", count)
        return times[:, 0], fields_from_sensors(contact, acc, pos, quat)

    def read_current(self, sensordata: np.ndarray) -> np.ndarray:
        """Contact fields (N, 4, 1, NUM_FIELDS) of the current ``sensordata`` (N, nsensordata), e.g. after reset."""
        sensordata = np.asarray(sensordata)

        def take(kind: str) -> np.ndarray:
            adr, dim = self._data[kind]
            return sensordata[:, adr[:, None] + np.arange(dim)][:, :, None, :]  # (N, 4, 1, dim)

        return fields_from_sensors(take("contact"), take("acc"), take("pos"), take("quat"))


def fields_from_sensors(contact: np.ndarray, acc: np.ndarray, pos: np.ndarray, quat: np.ndarray) -> np.ndarray:
    """Raw sensor values (..., 2 x 16), (..., 3), (..., 3), (..., 4) -> contact-field rows (..., NUM_FIELDS).

    The contact sensor's force is the force of geom1 (the dome) on geom2, in the contact frame
    [normal, tangent, normal x tangent] (MuJoCo XML reference, sensor/contact "Direction convention"); the force on
    the dome is its negative. ``linvel`` is the velocity of the other body relative to the dome at the contact
    point, in the contact frame (first component > 0: separating).
    """
    slots = contact.reshape(*contact.shape[:-1], CONTACT_SLOTS, _SLOT_DIM)  # (..., K, 16)
    found = (slots[..., 0] > 0).astype(np.float64)  # (..., K); 'found' holds the number of matches
    f_c = slots[..., 1:4]  # (..., K, 3) contact frame
    p_w = slots[..., 4:7]
    n_w, t_w = slots[..., 7:10], slots[..., 10:13]
    b_w = np.cross(n_w, t_w)
    v_c = slots[..., 13:16]
    f_dome_w = -(f_c[..., :1] * n_w + f_c[..., 1:2] * t_w + f_c[..., 2:3] * b_w)  # (..., K, 3) on the dome, world
    rot = quat_to_mat(quat)  # (..., 3, 3) sensor -> world
    net_s = np.einsum("...ji,...j->...i", rot, f_dome_w.sum(axis=-2))  # (..., 3) R^T F
    p_s = np.einsum("...ji,...kj->...ki", rot, p_w - pos[..., None, :])  # (..., K, 3) contact points, sensor frame
    fn = np.maximum(f_c[..., 0], 0.0) * found
    out = np.empty((*acc.shape[:-1], NUM_FIELDS), dtype=np.float32)
    out[..., 0] = -net_s[..., 2]
    out[..., 1:3] = net_s[..., :2]
    out[..., 3:6] = acc
    per_slot = np.concatenate(
        [found[..., None], fn[..., None], p_s * found[..., None], (v_c[..., :1]) * found[..., None],
         np.hypot(v_c[..., 1], v_c[..., 2])[..., None] * found[..., None]],
        axis=-1,
    )  # (..., K, 7) in _SLOT_FIELDS order
    out[..., 6:] = per_slot.reshape(*per_slot.shape[:-2], -1)
    return out


def slot_values(rows: np.ndarray, name: str) -> np.ndarray:
    """Contact-field rows (..., NUM_FIELDS) -> (..., CONTACT_SLOTS) float64 values of the per-slot field ``name``
    (one of found, fn, x, y, z, vn, slip) of every contact slot."""
    rows = np.asarray(rows)
    return np.stack([rows[..., FIELD[f"c{k}_{name}"]] for k in range(CONTACT_SLOTS)], axis=-1).astype(np.float64)


def contact_slip(rows: np.ndarray) -> np.ndarray:
    """(..., NUM_FIELDS) -> (...) the fastest slip speed (m/s) among the dome's contacts that press (0 without
    one): what the per-step ``slip`` label records."""
    return np.where(slot_values(rows, "fn") > 0, slot_values(rows, "slip"), 0.0).max(axis=-1)


def mean_slip(rows: np.ndarray) -> np.ndarray:
    """(..., NUM_FIELDS) -> (...) the dome's slip speed (m/s), its contacts' weighted by their normal force (0 without
    contact)."""
    fn = slot_values(rows, "fn")
    return (fn * np.maximum(slot_values(rows, "slip"), 0.0)).sum(-1) / np.maximum(fn.sum(-1), 1e-9)


def contact_frame_force(rows: np.ndarray) -> np.ndarray:
    """Contact-field rows (..., NUM_FIELDS) -> (..., 2) float32 [normal, tangential] force on the dome (N) at its
    strongest contact: the net force split along the dome's outward normal at that contact point (pressing > 0) and
    across it (magnitude). Zeros without a contact. Exact for one contact; a second contact's force is split along
    the first one's normal.

    The ``force_n, force_x, force_y`` columns split the same force along the camera axis instead; for a contact on
    the side of the dome (where many of this hand's grasps touch it) that axis is close to tangent to the contact."""
    rows = np.asarray(rows, dtype=np.float64)
    force = np.stack([rows[..., FIELD["force_x"]], rows[..., FIELD["force_y"]], -rows[..., FIELD["force_n"]]], -1)
    point = np.stack([rows[..., FIELD[f"c0_{a}"]] for a in "xyz"], -1)
    norm = np.linalg.norm(point, axis=-1, keepdims=True)
    touching = (rows[..., FIELD["c0_found"]] > 0) & (norm[..., 0] > 1e-9)
    outward = point / np.maximum(norm, 1e-9)
    along = (force * outward).sum(-1, keepdims=True)
    tangential = np.linalg.norm(force - along * outward, axis=-1)
    out = np.stack([-along[..., 0], tangential], -1)
    return np.where(touching[..., None], out, 0.0).astype(np.float32)
