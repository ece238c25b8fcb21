"""The deploy recording: one session file (rotation.data.session) per run, the same format as simulated sessions.

Streams, all in session time (s since the first joint measurement of the run):

- ``joints/position`` (16,) rad: measured joint angles, bus order, Allegro frame, one per control step;
- ``joints/target`` (16,) rad: the targets the policy commanded at that step (before the driver's rate limit);
- ``joints/torque`` (16,): the driver's effort at that step, in the driver's unit (metadata ``extra.torque_unit``:
  normalized torque = PWM / 1200 on an Allegro V4, = N m in simulation; measured current in A on LEAP);
- ``labels/object_pose`` (7,): object position (m) + quaternion wxyz, world frame, where known (emulation);
- ``digit360/<finger>/{imu,pressure}``: the Digit 360 serial streams when ``--digit360`` is given;
- ``digit360/<finger>/image`` (224, 224, 3) uint8 RGB at 30 fps and ``digit360/<finger>/audio`` (2,) int16 at 48 kHz:
  a real sensor's camera frames (centre crop, resized, as the reader keeps them for the encoder) and microphones,
  when deploy opened them (``--record-media``, or a policy that reads them; an emulated sensor renders its image and
  audio only when a window is asked for, so it records none); about 4.5 MB/s per sensor;
- ``touch/age`` (1,) s, at each control step a touch-reading policy acted with a correction: the age of the touch it
  acted on, from the newest sensor sample of the oldest fingertip window the correction read to the step's command
  to the hand (no sample where the student acted alone);
- ``skin/xela`` (368, 3) raw counts at 100 Hz when ``--skin`` is given (baseline in ``extra["xela_baseline"]``);
- ``skin/taxel_pos`` (368, 3) taxel positions (m, hand frame) of those frames, computed when the recording closes
  (after the run, the motors off: nothing in the control loop) by forward kinematics of ``joints/position``
  interpolated per joint to each frame's timestamp (envs.sensors.xela_kinematics), on the Xela hand model named in
  ``extra["skin_hand"]`` (rotation.data.skin_positions.session_skin_hand: the vendor's kinematics on a real
  Allegro, the policy's model on an emulated hand). Frames before the first joint sample or past the last by more
  than JOINT_HOLD_S have none. About 4 s for a 10-minute run (60,000 frames) on a busy 2-core machine, 1 s more to
  write them; a run killed before it closes has none, and the skin dataset computes them the same way when it reads
  it (rotation.data.skin). None on a LEAP hand (no Xela layout for it).

Joint streams share the control step's timestamp (the state read then was measured at most one driver cycle
earlier: 3 ms Allegro, 10 ms LEAP). The writer flushes every ``flush_interval_s`` from its own thread, never from
the control loop's (a flush on the loop's thread made steps start late: 5-7 late steps in a 5 s run of the shipped
adapter on the emulated 2-core deploy, 1-3 from the writer's thread), so a crash or a fault loses at most that
much; a run that ends by a fault or a signal is left without the ``complete`` mark.
"""

from __future__ import annotations

import dataclasses
import logging
from pathlib import Path
from typing import Any

import numpy as np

from envs.constants import NUM_JOINTS
from envs.sensors.xela_kinematics import covered, joints_at, kinematics
from rotation.data.session import SessionError, SessionMeta, StreamSetup
from rotation.data.session_writer import SessionWriter
from rotation.data.skin_positions import SKIN_HAND_KEY, session_skin_hand
from rotation.deploy.sensors import STREAMS as DIGIT_STREAMS
from rotation.hardware.digit360 import window as dw

log = logging.getLogger("rotation.deploy")

JOINT_STREAMS = ("joints/position", "joints/target", "joints/torque")
TOUCH_AGE = "touch/age"
POSITION_CHUNK = 1000
"""Skin frames whose taxel positions are computed and queued at once when the recording closes (1.3 MB float32)."""


class DeployRecorder:
    """Session writer for one deploy run (see the module docstring)."""

    def __init__(self, path: str | Path, meta: SessionMeta, fingers: tuple[str, ...] = (),
                 object_pose: bool = False, flush_interval_s: float = 1.0, overwrite: bool = False,
                 skin: bool = False, media: dict[str, tuple[str, ...]] | None = None, touch_age: bool = False
                 ) -> None:
        """``media``: per finger, which of ``image`` and ``audio`` its sensor streams (real sensors whose camera
        and microphones deploy opened); ``touch_age``: record each step's touch age (a touch-reading policy)."""
        rate = meta.control_hz
        streams: list[StreamSetup | str] = [StreamSetup(name, rate_hz=rate) for name in JOINT_STREAMS]
        if object_pose:
            streams.append(StreamSetup("labels/object_pose", rate_hz=rate))
        if touch_age:
            streams.append(StreamSetup(TOUCH_AGE, rate_hz=rate))
        self.touch_age = touch_age
        streams += [f"digit360/{f}/{s}" for f in fingers for s in DIGIT_STREAMS]
        media = {f: tuple(m) for f, m in (media or {}).items() if m}
        for f, kinds in media.items():
            if "image" in kinds:
                streams.append(StreamSetup(f"digit360/{f}/image", shape=(dw.IMAGE_SIZE, dw.IMAGE_SIZE, 3)))
            if "audio" in kinds:
                streams.append(StreamSetup(f"digit360/{f}/audio", dtype="int16"))
        self.skin_hand: str | None = None
        """The Xela hand model of the recorded taxel positions (None: none recorded)."""
        if skin:
            streams.append("skin/xela")
            try:
                self.skin_hand = session_skin_hand(meta, f"recording {path}")
            except SessionError as err:
                log.warning("skin: the taxel positions (skin/taxel_pos) are not recorded: %s", err)
            if self.skin_hand is not None:
                streams.append("skin/taxel_pos")
                meta = dataclasses.replace(meta, extra={**meta.extra, SKIN_HAND_KEY: self.skin_hand})
        self._joint_t: list[float] = []
        self._joint_q: list[np.ndarray] = []
        self._skin_t: list[np.ndarray] = []  # the skin frames' timestamps, for their positions at close
        self._positions_done = False
        self.writer = SessionWriter(path, meta, streams, flush_interval_s=flush_interval_s, overwrite=overwrite,
                                    background=True)
        self.path = self.writer.path
        self.object_pose = object_pose
        self.steps = 0

    def step(self, t: float, q: np.ndarray, target: np.ndarray, torque: np.ndarray,
             object_pose: np.ndarray | None = None, touch_age: float | None = None) -> None:
        """One control step at session time ``t`` (s): joint vectors (16,), object pose (7,) if recorded, the touch
        age (s; None: the student acted alone, no sample) if recorded."""
        ts = np.array([t])
        q = np.asarray(q, dtype=np.float64).reshape(1, NUM_JOINTS)
        self.writer.append("joints/position", q, ts)
        if self.skin_hand is not None:
            self._joint_t.append(float(t))
            self._joint_q.append(q[0].copy())
        self.writer.append("joints/target", np.asarray(target, dtype=np.float64).reshape(1, NUM_JOINTS), ts)
        self.writer.append("joints/torque", np.asarray(torque, dtype=np.float64).reshape(1, NUM_JOINTS), ts)
        if self.object_pose and object_pose is not None:
            self.writer.append("labels/object_pose", np.asarray(object_pose, dtype=np.float64).reshape(1, 7), ts)
        if self.touch_age and touch_age is not None:
            self.writer.append(TOUCH_AGE, np.array([[touch_age]]), ts)
        self.steps += 1

    def append(self, name: str, data: np.ndarray, timestamps: np.ndarray) -> None:
        """Samples of any other declared stream (Digit 360, skin)."""
        self.writer.append(name, data, timestamps)
        if name == "skin/xela" and self.skin_hand is not None and not self._positions_done:
            self._skin_t.append(np.array(timestamps, dtype=np.float64))

    def record_positions(self) -> int:
        """Compute and queue ``skin/taxel_pos`` for the skin frames recorded so far (see the module docstring);
        returns how many. Called once, by :meth:`close`; a failure is logged, never raised (the recording closes,
        and the skin dataset can compute them later)."""
        if self._positions_done or self.skin_hand is None or not self._skin_t or not self._joint_t:
            return 0
        self._positions_done = True
        try:
            t = np.concatenate(list(self._skin_t))
            tj, qj = np.asarray(self._joint_t), np.stack(self._joint_q)
            t = t[covered(tj, t)]
            kin = kinematics(self.skin_hand)
            for a in range(0, len(t), POSITION_CHUNK):
                tc = t[a : a + POSITION_CHUNK]
                self.writer.append("skin/taxel_pos", kin.taxel_positions(joints_at(tj, qj, tc)).astype(np.float32),
                                   tc)
        except (ValueError, SessionError) as err:
            log.error("skin: the taxel positions could not be recorded (the skin dataset computes them from "
                      "joints/position when it reads the session): %s", err)
            return 0
        return len(t)

    def __enter__(self) -> DeployRecorder:
        return self

    def __exit__(self, exc_type: Any, exc: Any, tb: Any) -> None:
        self.record_positions()
        self.writer.__exit__(exc_type, exc, tb)  # complete only on a clean exit; abort keeps what was flushed

    def close(self, complete: bool) -> None:
        """Flush and close; ``complete=False`` leaves the file without the ``complete`` mark (fault, signal). The
        skin frames' taxel positions are computed and written first (:meth:`record_positions`)."""
        self.record_positions()
        if complete:
            self.writer.close()
        else:
            self.writer.abort()
