"""Taxel positions of skin sessions (rotation.data.skin_positions): a recording without ``skin/taxel_pos`` gets them
from ``joints/position`` by forward kinematics at each frame's time; the hand model the session names; refusals."""

from __future__ import annotations

import numpy as np
import pytest

from envs.constants import JOINT_LOWER, JOINT_UPPER, NUM_JOINTS
from envs.sensors.xela import NUM_TAXELS, REST
from envs.sensors.xela_kinematics import JOINT_HOLD_S, XelaKinematics, joints_at
from rotation.data.session import SessionError, SessionMeta, StreamSetup
from rotation.data.session_writer import SessionWriter
from rotation.data.skin import SkinWindows, shared_reader
from rotation.data.skin_positions import STORED, session_skin_hand

SKIN_T = 0.013 + np.arange(150) / 100.0
"""Skin frames: 1.5 s at 100 Hz, the first 13 ms into the session."""
JOINT_T = 0.02 + np.arange(24) / 20.0
"""Joint samples: 1.2 s at 20 Hz (the skin goes on after the last one)."""


def joint_path(seed: int = 0) -> np.ndarray:
    """(24, 16) joint angles: a random walk inside the limits, so that the fingers move between samples."""
    rng = np.random.default_rng(seed)
    mid, half = (JOINT_LOWER + JOINT_UPPER) / 2, (JOINT_UPPER - JOINT_LOWER) / 2
    return mid + 0.8 * half * np.sin(np.cumsum(rng.normal(0.0, 0.3, (len(JOINT_T), NUM_JOINTS)), axis=0))


def write_session(path, joints: bool = True, positions: np.ndarray | None = None, skin: bool = True,
                  source: str = "real", hand: str = "allegro", extra: dict | None = None):
    streams: list = (["skin/xela"] if skin else []) + (["skin/taxel_pos"] if positions is not None else [])
    streams += [StreamSetup("joints/position", rate_hz=20.0)] if joints or not streams else []
    meta = SessionMeta(source=source, object="cup", control_hz=20.0, hand=hand, extra=extra or {})
    counts = REST + np.random.default_rng(1).normal(0.0, 20.0, (len(SKIN_T), NUM_TAXELS, 3))
    with SessionWriter(path, meta, streams) as w:
        if skin:
            w.append("skin/xela", counts.astype(np.float32), SKIN_T)
        if positions is not None:
            w.append("skin/taxel_pos", positions.astype(np.float32), SKIN_T)
        if joints:
            w.append("joints/position", joint_path(), JOINT_T)
    return path


def test_a_recording_without_positions_gets_them_from_its_joints(tmp_path):
    path = write_session(tmp_path / "real.h5", extra={"hand": "allegro"})  # `rotate deploy --hand allegro`
    ds = SkinWindows([path], stride=1)
    assert ds.positions == ["xela_v4"]  # a real Allegro moves as the vendor's kinematics
    # windows only where every frame has joint angles: from the first joint sample to JOINT_HOLD_S after the last
    assert ds.end_times[0] - 0.09 >= JOINT_T[0] - 1e-9 and ds.end_times[0] - 0.1 < JOINT_T[0]
    last = JOINT_T[-1] + JOINT_HOLD_S
    assert ds.end_times[-1] <= last + 1e-9 and ds.end_times[-1] + 0.01 > last
    assert len(ds) == np.sum((SKIN_T - 0.09 >= JOINT_T[0] - 1e-6) & (SKIN_T <= JOINT_T[-1] + JOINT_HOLD_S + 1e-6))
    kin = XelaKinematics("xela_v4")
    xela = shared_reader(path).stream("skin/xela")
    for i in (0, len(ds) // 2, len(ds) - 1):
        item = ds[i]
        row = int(ds.index[i, 1])
        frames = slice(row - 9, row + 1)
        want = kin.taxel_positions(joints_at(JOINT_T, joint_path(), SKIN_T[frames]))
        assert item["skin"].shape == (10, NUM_TAXELS, 6)
        assert np.array_equal(item["skin"][..., :3].numpy(), xela.data[frames])
        assert np.abs(item["skin"][..., 3:].numpy() - want).max() < 1e-6
        if SKIN_T[row] <= JOINT_T[-1]:  # the fingers moved within the window: per-frame positions
            assert np.abs(want[-1] - want[0]).max() > 1e-3
        else:  # past the last joint sample its angles are held
            assert np.array_equal(want[-1], kin.taxel_positions(joint_path()[-1])[0])


def test_emulated_and_unnamed_hands(tmp_path):
    """An emulated hand moves as the policy's model; a recording that names no hand gets the skin simulation's."""
    emulated = write_session(tmp_path / "sim.h5", source="sim",
                             extra={"hand": "sim-allegro", "policy_sim": {"hand": "digit360"}})
    unnamed = write_session(tmp_path / "old.h5")
    ds = SkinWindows([emulated, unnamed], stride=10)
    assert ds.positions == ["xela", "xela"]
    i = int(np.flatnonzero(ds.index[:, 0] == 1)[0])
    row = int(ds.index[i, 1])
    want = XelaKinematics("xela").taxel_positions(joints_at(JOINT_T, joint_path(), SKIN_T[row - 9 : row + 1]))
    assert np.abs(ds[i]["skin"][..., 3:].numpy() - want).max() < 1e-6


def test_stored_positions_are_used_as_they_are(tmp_path):
    stored = np.broadcast_to(np.arange(len(SKIN_T), dtype=np.float64)[:, None, None] / 1000, (len(SKIN_T),
                                                                                               NUM_TAXELS, 3))
    path = write_session(tmp_path / "stored.h5", positions=stored)
    ds = SkinWindows([path], stride=1)
    assert ds.positions == [STORED] and len(ds) == len(SKIN_T) - 9  # no joint coverage needed
    row = int(ds.index[5, 1])
    assert np.allclose(ds[5]["skin"][..., 3:].numpy(), stored[row - 9 : row + 1])


def test_a_session_without_positions_or_joints_is_refused(tmp_path):
    path = write_session(tmp_path / "bare.h5", joints=False)
    with pytest.raises(SessionError, match=r"no taxel positions: neither a skin/taxel_pos stream nor a "
                                           r"joints/position stream .*\(has: skin/xela\)"):
        SkinWindows([path])
    no_skin = write_session(tmp_path / "joints.h5", skin=False)
    with pytest.raises(SessionError, match=r"no skin/xela stream \(has: joints/position\)"):
        SkinWindows([no_skin])
    leap = write_session(tmp_path / "leap.h5", hand="leap", extra={"hand": "leap"})
    with pytest.raises(SessionError, match=r"leap\.h5: no Xela skin model for the hand 'leap'"):
        SkinWindows([leap])


@pytest.mark.parametrize(("source", "hand", "extra", "want"), [
    ("real", "allegro", {"skin_hand": "xela"}, "xela"),  # named by `rotate deploy --skin`
    ("real", "allegro", {"hand": "allegro", "policy_sim": {"hand": "digit360"}}, "xela_v4"),
    ("sim", "allegro", {"hand": "sim-allegro", "policy_sim": {"hand": "digit360_v4"}}, "xela_v4"),
    ("sim", "leap", {"hand": "sim-leap"}, "xela"),  # an Allegro body on the LEAP bus; no policy_sim: legacy model
    ("sim", "allegro", {"hand": "xela_v4"}, "xela_v4"),  # `rotate collect --skin`
    ("real", "allegro", {}, "xela"),
])
def test_the_hand_a_session_names(source, hand, extra, want):
    assert session_skin_hand(SessionMeta(source=source, object="cup", control_hz=20.0, hand=hand, extra=extra),
                             "s") == want


@pytest.mark.parametrize(("hand", "extra", "match"), [
    ("allegro", {"skin_hand": "digit360"}, r"extra\['skin_hand'\] = 'digit360' is not a Xela hand"),
    ("leap", {}, "no Xela skin model for the hand 'leap'"),
    ("allegro", {"hand": "sim-allegro", "policy_sim": {"hand": "shadow"}}, "no Xela skin model for the hand 'shadow'"),
])
def test_a_hand_without_a_xela_model_is_refused(hand, extra, match):
    with pytest.raises(SessionError, match=match):
        session_skin_hand(SessionMeta(source="real", object="cup", control_hz=20.0, hand=hand, extra=extra), "s")
