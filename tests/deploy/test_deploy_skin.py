"""`rotate deploy --skin`: the Xela skin recorded beside the joints (and its taxel positions), from a local stand-in
xela_server; bad --skin values and a server that does not answer are refused before anything starts."""

from __future__ import annotations

import json

import numpy as np
import pytest
from deploy_checks import assert_done_or_load_fault

from envs.sensors.xela_kinematics import XelaKinematics, covered, joints_at
from rotation.data.session_reader import SessionReader
from rotation.deploy.config import Config
from rotation.deploy.job import run
from rotation.sim_hardware.xela_emulator import XelaServerEmulator


def test_skin_is_recorded_beside_the_joints(tmp_path, policy, hand_hook):
    record = tmp_path / "skin.h5"
    with XelaServerEmulator() as server:
        # once the hand runs, one malformed message: skipped and counted, the run goes on
        hand_hook.after(0.3, lambda opened: server.inject("{ not json"))
        summary = run(Config(hand="sim-allegro", policy=policy, duration=1.5, record=str(record), skin=server.url))
    assert_done_or_load_fault(summary)
    skin = summary["skin"]
    # the stand-in sends 100 frames a second; a loaded machine runs fewer control steps in the same time
    least = min(150, 100 * 0.8 * summary["steps"] / 20)
    assert skin["skipped"] == 1 and skin["frames"] >= least and skin["disconnects"] == 0, (skin, summary["steps"])
    with SessionReader(record, require=["skin/xela", "joints/position"]) as r:
        st = r.stream("skin/xela")
        assert r.complete == (summary["exit_code"] == 0) and st.data.shape[1:] == (368, 3) and st.rate_hz == 100.0
        assert len(st) >= min(100, least) and np.all(np.diff(st.timestamps) > 0)
        assert st.timestamps[0] >= 0.0  # session time: the skin's frames after the first joint measurement
        base = np.asarray(r.meta.extra["xela_baseline"])
        assert base.shape == (368, 3) and np.allclose(base, 32768.0, atol=1600.0)
        untouched = np.asarray(st.data)[:, 100:]  # the stand-in presses the index fingertip only (taxels 0..29)
        assert np.all(untouched == 32768.0)
        # the taxel positions of the frames, from the joint angles at each frame's time (computed at close)
        pos, q = r.stream("skin/taxel_pos"), r.stream("joints/position")
        assert np.array_equal(pos.timestamps, st.timestamps[covered(q.timestamps, st.timestamps)])
        assert len(pos) > 0.8 * len(st)
        want = XelaKinematics(r.meta.extra["skin_hand"]).taxel_positions(joints_at(q.timestamps, q.data,
                                                                                   pos.timestamps))
        assert np.abs(pos.data - want).max() < 1e-6


def test_skin_option_errors_before_anything_starts(policy, capsys):
    from rotation.cli import main

    with pytest.raises(ValueError, match="skin: 'http://x:5000' is not a WebSocket URL"):
        Config(hand="sim-allegro", policy=policy, skin="http://x:5000")
    with pytest.raises(ValueError, match="skin: 'sim' .* needs an emulated hand"):
        Config(hand="allegro", policy=policy, skin="sim")
    with XelaServerEmulator() as server:
        url = server.url  # closed on leaving: nothing answers there any more
    summary_or_error = None
    with pytest.raises(ValueError, match=r"--skin ws://127\.0\.0\.1:\d+: xela_server does not answer"):
        summary_or_error = run(Config(hand="sim-allegro", policy=policy, duration=0.5, skin=url))
    assert summary_or_error is None
    assert main(["deploy", "--hand", "sim-allegro", "--policy", policy, "--skin", "localhost:5000"]) == 2
    err = capsys.readouterr().err
    assert "skin" in err and "Traceback" not in err


def test_skin_sim_runs_the_stand_in_server(tmp_path, policy, hand_hook, capsys):
    summary = run(Config(hand="sim-allegro", policy=policy, duration=0.6, skin="sim"))
    assert_done_or_load_fault(summary)
    least = min(50, 100 * 0.8 * summary["steps"] / 20)  # as above
    assert summary["skin"]["frames"] > least and summary["record"] is None
    assert json.loads(capsys.readouterr().out.strip().splitlines()[-1])["skin"] == summary["skin"]
