"""The deploy recording's ``skin/taxel_pos``: computed when the recording closes from the recorded joint angles
(forward kinematics at each skin frame's time), equal to what the skin dataset computes for a recording without
them; none on a LEAP hand (no Xela layout), with a warning."""

from __future__ import annotations

import logging

import numpy as np
import pytest

from envs.constants import JOINT_LOWER, JOINT_UPPER, NUM_JOINTS
from envs.sensors.xela import NUM_TAXELS, REST
from envs.sensors.xela_kinematics import JOINT_HOLD_S, XelaKinematics, covered, joints_at
from rotation.data.session import SessionMeta, StreamSetup
from rotation.data.session_reader import SessionReader
from rotation.data.session_writer import SessionWriter
from rotation.data.skin import SkinWindows, shared_reader
from rotation.deploy.recording import DeployRecorder

HZ = 20.0


def emulated_meta(hand: str = "sim-allegro", policy_hand: str = "digit360") -> SessionMeta:
    """What `rotate deploy --hand <hand> --skin ... --record` writes (rotation.deploy.job._open_recorder), in short."""
    return SessionMeta(source="sim" if hand.startswith("sim-") else "real", object="cup", control_hz=HZ,
                       hand="leap" if hand.endswith("leap") else "allegro",
                       extra={"hand": hand, "policy": "student", "policy_sim": {"hand": policy_hand}})


def run_recorder(path, meta: SessionMeta, complete: bool = True) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """1 s of control steps at 20 Hz and skin frames at 100 Hz, drained in batches as the deploy's drain thread does,
    the skin going on 0.3 s after the last step; returns the joint times, angles and the skin frames' times."""
    rng = np.random.default_rng(4)
    t_joint = 0.012 + np.arange(20) / HZ
    q = rng.uniform(JOINT_LOWER, JOINT_UPPER, (len(t_joint), NUM_JOINTS))
    t_skin = 0.003 + np.arange(130) / 100.0
    rec = DeployRecorder(path, meta, skin=True, flush_interval_s=0.05)
    for k, t in enumerate(t_joint):
        rec.step(t, q[k], q[k], np.zeros(NUM_JOINTS))
    for a in range(0, len(t_skin), 25):
        ts = t_skin[a : a + 25]
        rec.append("skin/xela", np.full((len(ts), NUM_TAXELS, 3), REST, np.float32), ts)
    rec.close(complete=complete)
    return t_joint, q, t_skin


@pytest.mark.parametrize("complete", [True, False])
def test_positions_are_recorded_at_close(tmp_path, complete):
    """Also after a fault (``complete=False``): the moments before it are those a lab most wants to look at."""
    path = tmp_path / "skin.h5"
    t_joint, q, t_skin = run_recorder(path, emulated_meta(), complete)
    with SessionReader(path, require=["skin/xela", "skin/taxel_pos", "joints/position"]) as r:
        assert r.complete == complete and r.meta.extra["skin_hand"] == "xela"  # the emulated policy's model
        pos = r.stream("skin/taxel_pos")
        assert pos.rate_hz == 100.0 and pos.data.dtype == np.float32 and pos.data.shape[1:] == (NUM_TAXELS, 3)
        # every skin frame from the first step to JOINT_HOLD_S after the last, at the frame's own time
        keep = covered(t_joint, t_skin)
        assert np.array_equal(pos.timestamps, t_skin[keep]) and 0 < keep.sum() < len(t_skin)
        assert pos.timestamps[-1] <= t_joint[-1] + JOINT_HOLD_S and not keep[0]  # the first frame precedes the steps
        want = XelaKinematics("xela").taxel_positions(joints_at(t_joint, q, pos.timestamps))
        assert np.abs(pos.data - want).max() < 1e-6


def test_recorded_and_computed_positions_agree(tmp_path):
    """The same run recorded without skin/taxel_pos (an older recording) gives the skin dataset the same windows."""
    recorded = tmp_path / "recorded.h5"
    run_recorder(recorded, emulated_meta("allegro", policy_hand="digit360_v4"))
    older = tmp_path / "older.h5"
    with SessionReader(recorded) as r:
        assert r.meta.extra["skin_hand"] == "xela_v4"  # a real Allegro: the vendor's kinematics
        extra = {k: v for k, v in r.meta.extra.items() if k != "skin_hand"}
        meta = SessionMeta(source=r.meta.source, object="cup", control_hz=HZ, hand=r.meta.hand, extra=extra)
        with SessionWriter(older, meta, ["skin/xela", StreamSetup("joints/position", rate_hz=HZ)]) as w:
            for name in ("skin/xela", "joints/position"):
                st = r.stream(name)
                w.append(name, st.data, st.timestamps)
    try:
        a, b = SkinWindows([recorded], stride=1), SkinWindows([older], stride=1)
        assert a.positions == ["stored"] and b.positions == ["xela_v4"]
        assert np.array_equal(a.end_times, b.end_times) and len(a) > 50
        for i in (0, len(a) // 2, len(a) - 1):
            assert np.abs(a[i]["skin"].numpy() - b[i]["skin"].numpy()).max() < 1e-6
    finally:  # the datasets' process-wide readers (the deploy tests check that no file is left open)
        for path in (recorded, older):
            shared_reader(path).close()


def test_a_leap_hand_records_no_positions(tmp_path, caplog):
    path = tmp_path / "leap.h5"
    with caplog.at_level(logging.WARNING, logger="rotation.deploy"):
        run_recorder(path, emulated_meta("leap"))
    assert "taxel positions (skin/taxel_pos) are not recorded" in caplog.text and "'leap'" in caplog.text
    with SessionReader(path, require=["skin/xela"]) as r:
        assert not r.has("skin/taxel_pos") and "skin_hand" not in r.meta.extra
