"""`rotate collect --task shake|oas`: one session per benchmark episode, deterministic per seed, whose windows carry
the labels of their episode; a resumed collection keeps its files; options that do not apply are refused in one
line."""

from __future__ import annotations

import numpy as np
import pytest

from envs.grasp_cache import load_default_cache
from envs.oas import SURFACES, OasConfig
from envs.oas import draw_episode as oas_draw
from envs.shake import ShakeConfig, draw_episode
from envs.shake_contents import CONTENT_NAMES, FILL_LEVELS
from rotation.cli import main
from rotation.data.dataset import TouchWindows, find_sessions
from rotation.data.session_reader import SessionReader
from rotation.jobs import collect
from rotation.jobs.collect_bench import bench_seed as shake_seed


def _collect(out, episodes=2, seed=4):
    return collect.run(collect.Config(task="shake", episodes=episodes, out=out, seed=seed, shake_s=1.3,
                                      progress=False))


@pytest.fixture(scope="module")
def sessions(tmp_path_factory):
    out = tmp_path_factory.mktemp("shake") / "c"
    figures = _collect(out)
    return out, figures


def test_sessions_hold_the_contact_fields_and_their_episodes_labels(sessions):
    out, figures = sessions
    assert figures["episodes"] == 2 and figures["sim_s_per_s"] > 0
    paths = find_sessions(out)
    assert len(paths) == 2
    grasps = load_default_cache("cup", "", "digit360_v4")
    for e, path in enumerate(paths):
        ep = draw_episode(ShakeConfig(duration_s=1.3), shake_seed(4, e), grasps)
        with SessionReader(path) as r:
            assert r.meta.properties["content"] == ep.content and r.meta.properties["fill"] == FILL_LEVELS[ep.fill]
            assert r.meta.extra["sim_hand"] == "digit360_v4" and r.meta.extra["task"] == "shake"
            contact = r.stream("digit360/thumb/contact")
            assert len(contact) == 650 and np.all(np.isfinite(contact.data))
            assert np.all(r.stream("labels/content").data == CONTENT_NAMES.index(ep.content))
    ds = TouchWindows(paths, labels=("content", "fill"))
    assert len(ds) > 0
    rows = np.linspace(0, len(ds) - 1, 5).astype(int)
    for i in rows:  # a window's labels are its session's
        sample = ds[int(i)]
        with SessionReader(paths[int(sample["session"])]) as r:
            assert int(sample["content"][0]) == CONTENT_NAMES.index(r.meta.properties["content"])
            assert int(sample["fill"][0]) == FILL_LEVELS.index(r.meta.properties["fill"])
        assert sample["imu"].shape == (224, 3) and sample["image"].shape == (6, 224, 224)


def test_a_collection_is_deterministic_and_resumes(sessions, tmp_path, capsys):
    out, _ = sessions
    again = tmp_path / "again"
    _collect(again, episodes=1)
    with SessionReader(find_sessions(out)[0]) as a, SessionReader(find_sessions(again)[0]) as b:
        assert np.array_equal(a.stream("digit360/index/contact").data, b.stream("digit360/index/contact").data)
    assert _collect(out)["episodes"] == 0  # both already there


@pytest.mark.parametrize("options", [["--policy", "student"], ["--skin"], ["--hand", "digit360"],
                                     ["--shake-s", "1.0"]])
@pytest.mark.parametrize("task", ["shake", "oas"])
def test_options_that_do_not_apply_are_refused(options, task, tmp_path, capsys):
    assert main(["collect", "--task", task, "--episodes", "1", "--out", str(tmp_path / "x"), *options]) == 2
    err = capsys.readouterr().err
    assert "Traceback" not in err and (task in err or "1.12 s" in err), err
    assert not (tmp_path / "x").exists()


def test_the_fingertip_grip_is_recorded_and_keeps_its_own_collection(sessions, tmp_path, capsys):
    """--shake-grip fingertips holds the bottle on the domes (envs.shake): the same episode's contact fields differ
    from the palm grip's and the sessions say which grip; an OUT of one grip refuses the other; oas refuses it."""
    out, _ = sessions
    tips = tmp_path / "tips"
    collect.run(collect.Config(task="shake", episodes=1, out=tips, seed=4, shake_s=1.3, shake_grip="fingertips",
                               progress=False))
    with SessionReader(find_sessions(out)[0]) as a, SessionReader(find_sessions(tips)[0]) as b:
        assert a.meta.properties["grip"] == "palm" and b.meta.properties["grip"] == "fingertips"
        assert a.meta.properties["content"] == b.meta.properties["content"]
        pa, pb = a.stream("digit360/index/contact").data, b.stream("digit360/index/contact").data
        assert pa.shape == pb.shape and not np.array_equal(pa, pb)
    base = ["collect", "--task", "shake", "--episodes", "1", "--shake-s", "1.3", "--seed", "4"]
    assert main([*base, "--out", str(tips)]) == 1  # the palm grip into the fingertip grip's OUT
    err = capsys.readouterr().err
    assert "was not written by this collection" in err and "Traceback" not in err
    assert main(["collect", "--task", "oas", "--episodes", "1", "--out", str(tmp_path / "o"), "--shake-grip",
                 "fingertips"]) == 2
    err = capsys.readouterr().err
    assert "only --task shake holds a bottle" in err and not (tmp_path / "o").exists()


def test_the_strokes_motion_is_recorded_and_keeps_its_own_collection(sessions, tmp_path, capsys):
    """--shake-motion strokes shakes the same episode's bottle by strokes (envs.shake.stroke): its contact fields
    differ from the sinusoid's, the sessions say which motion, an OUT of one motion refuses the other, oas refuses
    the option."""
    out, _ = sessions
    strokes = tmp_path / "strokes"
    collect.run(collect.Config(task="shake", episodes=1, out=strokes, seed=4, shake_s=1.3, shake_motion="strokes",
                               progress=False))
    with SessionReader(find_sessions(out)[0]) as a, SessionReader(find_sessions(strokes)[0]) as b:
        assert a.meta.properties["motion"] == "sine" and b.meta.properties["motion"] == "strokes"
        assert (a.meta.properties["content"], a.meta.properties["amplitude"]) == (
            b.meta.properties["content"], b.meta.properties["amplitude"])
        pa, pb = a.stream("digit360/index/contact").data, b.stream("digit360/index/contact").data
        assert pa.shape == pb.shape and not np.array_equal(pa, pb)
    base = ["collect", "--task", "shake", "--episodes", "1", "--shake-s", "1.3", "--seed", "4"]
    assert main([*base, "--out", str(strokes)]) == 1  # the sinusoid into the strokes' OUT
    assert "was not written by this collection" in capsys.readouterr().err
    assert main(["collect", "--task", "oas", "--episodes", "1", "--out", str(tmp_path / "o"), "--shake-motion",
                 "strokes"]) == 2
    err = capsys.readouterr().err
    assert "only --task shake holds a bottle" in err and not (tmp_path / "o").exists()


def test_oas_sessions_carry_the_object_action_and_surface_and_the_surface_force(tmp_path):
    out = tmp_path / "oas"
    collect.run(collect.Config(task="oas", episodes=2, out=out, seed=3, shake_s=1.3, progress=False))
    paths = find_sessions(out)
    grasps = load_default_cache("cup", "", "digit360_v4")
    for e, path in enumerate(paths):
        ep = oas_draw(OasConfig(duration_s=1.3), shake_seed(3, e), grasps)
        with SessionReader(path) as r:
            props = r.meta.properties
            assert (props["object"], props["action"], props["surface"]) == (ep.object, ep.action, ep.surface)
            for name, value in ep.labels.items():
                assert np.all(r.stream(f"labels/{name}").data == value)
            force = r.stream("labels/surface_force")
            assert len(force) == len(r.stream("digit360/index/contact")) == 650 and np.all(force.data >= 0)
    ds = TouchWindows(paths, labels=("object", "action", "surface"))
    sample = ds[len(ds) // 2]
    with SessionReader(paths[int(sample["session"])]) as r:
        assert int(sample["surface"][0]) == SURFACES.index(r.meta.properties["surface"])
