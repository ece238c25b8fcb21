"""`rotate collect --skin`: Xela sessions on the cup (scripted play) and the joystick task, readable with the new
streams and labels; bad combinations refused on the command line."""

from __future__ import annotations

import json

import numpy as np
import pytest

from envs.sensors.xela import NUM_PADS, NUM_TAXELS, PAD_NAMES, REST, TAXEL_TYPE
from rotation.cli import main
from rotation.data.session import STREAMS
from rotation.data.session_reader import SessionReader
from rotation.jobs import collect, collect_resume

SKIN = {"skin/xela": (NUM_TAXELS, 3), "skin/taxel_pos": (NUM_TAXELS, 3), "labels/skin_force": (NUM_PADS, 3)}


def cfg_for(out, **kw):
    return collect.Config(**{**dict(out=out, episodes=2, num_envs=2, episode_steps=12, seed=3, progress=False,
                                    skin=True, policy="play"), **kw})


def test_registry_declares_the_skin_streams():
    assert STREAMS["skin/xela"].rate_hz == STREAMS["skin/taxel_pos"].rate_hz == 100.0
    assert STREAMS["labels/skin_force"].shape == (18, 3) and STREAMS["labels/joystick"].shape == (3,)


@pytest.mark.parametrize("task", ["cup", "joystick"])
def test_collect_writes_readable_skin_sessions(task, tmp_path):
    out = tmp_path / task
    result = collect.run(cfg_for(out, task=task))
    assert result["episodes"] == 2
    extra = {"cup": {"labels/object_pose", "labels/priv"}, "joystick": {"labels/joystick"}}[task]
    with SessionReader(collect.episode_path(out, 1), require=[*SKIN, *extra]) as r:
        assert r.complete and r.meta.object == ("cup" if task == "cup" else "joystick")
        assert not any(n.startswith("digit360/") for n in r.names) and "labels/force" not in r.names
        meta = r.meta.extra["skin"]
        assert meta["pads"] == list(PAD_NAMES) and meta["taxel_type"] == TAXEL_TYPE.tolist()
        steps = r.stream("joints/position")
        for name, shape in SKIN.items():
            s = r.stream(name)
            assert s.data.shape[1:] == shape and s.rate_hz == 100.0, name
            assert len(s) == 5 * (len(steps) - 1) and np.allclose(np.diff(s.timestamps), 0.01)
        xela = r.stream("skin/xela").data
        assert abs(np.median(xela) - REST) < 500 and xela.max() > REST + 500  # rest value, and pressing shows
        pos = r.stream("skin/taxel_pos").data
        assert np.all(np.abs(pos) < 0.25) and pos[:, :, 2].max() > 0.05  # metres, hand frame, fingers above palm
        if task == "joystick":
            angles = r.stream("labels/joystick")
            assert angles.data.shape == (len(xela), 3) and np.abs(angles.data).max() < 1.0
    manifest = json.loads((out / collect_resume.MANIFEST).read_text())["settings"]
    assert manifest["skin"] is True and manifest["task"] == task


def test_collect_skin_is_deterministic_and_resumes(tmp_path):
    a, b = tmp_path / "a", tmp_path / "b"
    collect.run(cfg_for(a, episodes=1, num_envs=1))
    collect.run(cfg_for(b, episodes=1, num_envs=1))
    with SessionReader(collect.episode_path(a, 0)) as ra, SessionReader(collect.episode_path(b, 0)) as rb:
        assert np.array_equal(ra.stream("skin/xela").data, rb.stream("skin/xela").data)
    stamp = collect.episode_path(a, 0).stat().st_mtime_ns
    collect.run(cfg_for(a, episodes=2, num_envs=1))  # resumes: keeps episode 0, records episode 1
    assert collect.episode_path(a, 0).stat().st_mtime_ns == stamp
    assert collect_resume.is_complete(collect.episode_path(a, 1))
    with pytest.raises(ValueError, match=r"other settings \(skin: True -> False\)"):
        collect.run(cfg_for(a, episodes=3, num_envs=1, skin=False))


@pytest.mark.parametrize(("argv", "message"), [
    (["--task", "joystick"], "the joystick task records the Xela skin; add --skin"),
    (["--task", "joystick", "--skin", "--policy", "student"], "the joystick task moves the hand by script"),
    (["--task", "wheel"], "--task"),
])
def test_bad_combinations_are_cli_errors(argv, message, tmp_path, capsys):
    try:
        status = main(["collect", "--out", str(tmp_path / "x"), *argv])
    except SystemExit as exit_:  # argparse's own usage errors
        status = exit_.code
    err = capsys.readouterr().err
    assert status == 2 and message in err and "Traceback" not in err
    assert not (tmp_path / "x").exists()  # refused before any work


def test_skin_sessions_on_the_vendor_kinematics_hand(tmp_path, capsys):
    """--skin --hand xela_v4: the Xela skin on the vendor's kinematics (what the skin encoder pretrains on), its
    sessions name their hand; the joystick fixture and a hand without the skin are refused in one line."""
    from rotation.cli import main
    from rotation.data.dataset import find_sessions
    from rotation.data.session_reader import SessionReader
    from rotation.data.skin import SkinWindows

    out = tmp_path / "skin_v4"
    assert main(["collect", "--skin", "--hand", "xela_v4", "--policy", "play", "--episodes", "1", "--num-envs", "1",
                 "--episode-steps", "30", "--out", str(out), "--no-progress"]) == 0
    [path] = find_sessions(out)
    with SessionReader(path) as r:
        assert r.meta.extra["hand"] == "xela_v4"
    assert len(SkinWindows([path])) > 0
    for bad in (["--hand", "xela_v4"], ["--skin", "--hand", "digit360_v4"],
                ["--skin", "--task", "joystick", "--hand", "xela_v4"]):
        assert main(["collect", "--policy", "play", "--episodes", "1", "--out", str(tmp_path / "x"), *bad]) == 2
        assert "hand" in capsys.readouterr().err
