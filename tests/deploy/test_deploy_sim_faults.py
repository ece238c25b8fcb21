"""`rotate deploy --sim-faults` and `--sim-object` on the emulated Allegro: faults land when scheduled, the stack
reacts as documented (a lost fingertip, corrupt frames, late feedback, a bus error), and the emulated object is the
one asked for."""

from __future__ import annotations

import mujoco
import numpy as np
import pytest
from deploy_checks import again_if_loaded, load_fault

from envs.physics import default_randomization
from envs.scene import skin_geoms
from rotation.data.session_reader import SessionReader
from rotation.deploy.config import Config
from rotation.deploy.job import run
from rotation.deploy.sim_faults import Fault, parse_sim_faults
from rotation.sim_hardware.hand_physics import HandPhysics


def test_parse_sim_faults_reads_every_kind_in_time_order():
    faults = parse_sim_faults("bus-error=9, unplug=thumb@4,corrupt=index@2+5,stall=ring@3+0.5,late=6+0.08")
    assert faults == (Fault("corrupt", 2.0, "index", 5.0), Fault("stall", 3.0, "ring", 0.5),
                      Fault("unplug", 4.0, "thumb"), Fault("late", 6.0, None, 0.08), Fault("bus-error", 9.0))
    assert parse_sim_faults("") == ()


@pytest.mark.parametrize("spec, words", [
    ("unplug=4", "must name a fingertip"), ("unplug=pinky@4", "must name a fingertip"),
    ("late=6", "must be written late=T+D"), ("bus-error=9+1", "must be written bus-error=T"),
    ("corrupt=index@2+2.5", "whole number"), ("late=x+1", "is not a number"), ("late=-1+1", ">= 0"),
    ("stall=ring@3+0", "must be > 0"), ("explode=3", "the kinds are"),
])
def test_bad_fault_schedules_are_refused_with_the_item(spec, words):
    with pytest.raises(ValueError, match="sim_faults") as err:
        parse_sim_faults(spec)
    assert words in str(err.value)


def test_faults_and_the_emulated_object_are_for_emulated_hardware_only():
    with pytest.raises(ValueError, match="emulated hardware only"):
        Config(hand="allegro", policy="student", sim_faults="late=1+0.1")
    with pytest.raises(ValueError, match="not emulated in this run"):
        Config(hand="sim-allegro", policy="student", digit360="/dev/ttyACM0,/dev/ttyACM1,/dev/ttyACM2,/dev/ttyACM3",
               sim_faults="unplug=thumb@1")
    with pytest.raises(ValueError, match="sim_object: it sets the emulated object"):
        Config(hand="allegro", policy="student", sim_object="mass=0.3")
    with pytest.raises(ValueError, match="scale is the grasp cache's nominal"):
        Config(hand="sim-allegro", policy="student", sim_object="scale=0.9")
    with pytest.raises(ValueError, match="digit360_imu must be"):
        Config(hand="sim-allegro", policy="student", digit360="sim", digit360_imu="gravity")
    with pytest.raises(ValueError, match="friction_method"):
        Config(hand="allegro", policy="student", record="x.h5", friction_method="tilt")


def test_set_object_changes_the_contacts_friction_and_the_bodys_mass():
    physics = HandPhysics.at_grasp("cup", 0, hold=True)
    physics.set_object(mass=0.31, friction=0.45, com=(0.0, 0.0, 0.012))
    props = physics.object_properties()
    assert props["mass"] == pytest.approx(0.31) and props["friction"] == pytest.approx(0.45)
    assert props["com"] == pytest.approx([0.0, 0.0, 0.012])
    m, d = physics.model, physics.data
    body = m.body("object").id
    assert m.body_subtreemass[body] == pytest.approx(0.31)  # the derived constants were recomputed
    assert physics.object_pose() == pytest.approx(HandPhysics.at_grasp("cup", 0).object_pose())  # still in the grasp
    c = d.contact
    on_cup = (m.geom_bodyid[c.geom1] == body) | (m.geom_bodyid[c.geom2] == body)
    assert d.ncon and on_cup.sum() >= 3, "the grasp holds the cup by contacts"
    # what MuJoCo's contacts use (the larger of the two geoms' coefficients), as the env's randomization writes them
    # (envs.core): the stated one against the skin; against the links and palm, on a hand whose links have their own
    # friction (the default 'digit360_v4'), the links' nominal one (the middle of its range), else the stated one too
    on_skin = np.isin(c.geom1, skin_geoms(m)) | np.isin(c.geom2, skin_geoms(m))
    assert (on_cup & on_skin).any(), "the grasp holds the cup by fingertips"
    assert c.friction[on_cup & on_skin, 0] == pytest.approx(0.45)
    link_range = default_randomization(physics.hand).link_friction
    link = 0.45 if link_range is None else float(np.mean(link_range))
    assert c.friction[on_cup & ~on_skin, 0] == pytest.approx(link)
    physics.set_object(friction=1.1)  # grippier than any link: the object's geom keeps the links' coefficient
    assert physics.object_properties()["friction"] == pytest.approx(1.1)  # what the fingertips' contacts use
    assert physics.data.contact.friction[on_cup & on_skin, 0] == pytest.approx(1.1)
    fresh = HandPhysics.at_grasp("cup", 0, hold=True)
    fresh.set_object(mass=0.31)
    light = fresh.model.body_inertia[body].copy()
    fresh.set_object(mass=0.62)
    assert fresh.model.body_inertia[body] == pytest.approx(2 * light)  # a solid body: inertia in proportion to its mass
    assert fresh.model.body_subtreemass[0] == pytest.approx(mujoco.mj_getTotalmass(fresh.model))


def _run(tmp_path, name: str, policy: str, **kw) -> dict:
    return run(Config(hand="sim-allegro", policy=policy, record=str(tmp_path / name), digit360="sim",
                      status_every_s=10.0, **kw))


def test_a_lost_fingertip_and_corrupt_frames_leave_the_run_going_and_are_reported(tmp_path, policy):
    runs = iter(range(2))
    summary = again_if_loaded(lambda: _run(tmp_path, f"faults{next(runs)}.h5", policy, duration=3.0,
                                           sim_faults="corrupt=index@0.5+3,unplug=thumb@1.2,late=1.8+0.05",
                                           sim_object="mass=0.25,friction=0.5"))
    if load_fault(summary):
        pytest.skip(f"the machine was too loaded to run the loop twice: {summary['fault']}")
    assert summary["fault"] is None and summary["exit_code"] == 0 and summary["motors_off"]
    applied = {f["fault"]: f for f in summary["sim_faults"]}
    assert all(f["applied_s"] is not None and f["applied_s"] >= f["due_s"] - 1e-3 for f in applied.values()), applied
    assert summary["hand_bus"]["longest_gap_ms"] >= 40  # the driver saw the 50 ms pause of its joint feedback
    counters = summary["digit360"]
    assert counters["thumb"]["disconnects"] >= 1 and counters["index"]["disconnects"] == 0
    assert counters["index"]["bad_frames"] >= 3 and counters["middle"]["bad_frames"] == 0
    with SessionReader(summary["record"]) as r:
        assert r.meta.properties["mass"] == pytest.approx(0.25) and r.meta.extra["digit360_imu"] == "acc"
        assert r.meta.properties["friction"] == pytest.approx(0.5)
        t_joint = r.stream("joints/position").timestamps
        thumb = r.stream("digit360/thumb/imu").timestamps
        middle = r.stream("digit360/middle/imu").timestamps
    # the thumb's samples stop when it is unplugged; the others run to the end
    assert thumb[-1] < t_joint[0] + 1.2 + 0.3 < middle[-1] - 1.0


def test_a_bus_error_switches_the_motors_off_and_keeps_the_recording(tmp_path, policy):
    summary = _run(tmp_path, "bus.h5", policy, duration=3.0, sim_faults="bus-error=1.0")
    assert summary["exit_code"] == 1 and "error frame" in summary["fault"] and "overload" in summary["fault"]
    assert summary["motors_off"] and summary["motors_off_confirmed"]
    with SessionReader(summary["record"]) as r:
        assert not r.complete and len(r.stream("joints/position")) >= 10


def test_leap_late_feedback_a_stalled_fingertip_and_a_servo_overload(tmp_path, policy):
    """The same faults on the emulated LEAP: its status replies dropped for 50 ms (the driver retries and goes on),
    a fingertip's stream stalled for 0.3 s (its windows go stale, the recording keeps the others), then servo 0's
    overload bit (torque off, the run ends, the recording kept)."""
    summary = run(Config(hand="sim-leap", policy=policy, record=str(tmp_path / "leap.h5"), digit360="sim",
                         status_every_s=10.0, duration=4.0,
                         sim_faults="late=0.8+0.05,stall=ring@1.2+0.3,bus-error=2.5"))
    if load_fault(summary):
        pytest.skip(f"the machine was too loaded to run the loop: {summary['fault']}")
    assert [f["applied_s"] is not None for f in summary["sim_faults"]] == [True, True, True], summary["sim_faults"]
    assert summary["exit_code"] == 1 and "overload" in summary["fault"], summary["fault"]
    assert summary["motors_off"]
    assert summary["hand_bus"]["longest_gap_ms"] >= 40  # the dropped replies seen as a wait for the joints
    with SessionReader(summary["record"]) as r:
        ring = r.stream("digit360/ring/imu").timestamps
        middle = r.stream("digit360/middle/imu").timestamps
        t0 = r.stream("joints/position").timestamps[0]
    gaps = np.diff(ring)
    assert gaps.max() > 0.25 and np.diff(middle).max() < 0.1  # the stall in the ring's samples only
    # a gap of the stall's length starts where it was injected (on a loaded machine the ring may lag elsewhere too)
    starts = ring[:-1][gaps > 0.25] - t0
    assert np.any((starts > 1.0) & (starts < 1.6)), (starts, gaps.max())
