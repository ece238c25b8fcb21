"""`rotate deploy` reports nothing as safe or done unless it was, and refuses bad input before any motor is on.

- a bundle that would drive the hand badly (inverted or widened joint limits, a rate no loop holds, numbers as
  strings) is refused by the loader: exit status 2, the hand never opened;
- ``motors_off`` is true only when confirmed: by the emulated hand, or by the real hand's own answer; after a lost
  CAN bus (Allegro) or a torque-off write a servo refused (LEAP) it is false, the exit status is non-zero and the
  person at the hand is told to cut its power;
- a recording path or a touch sensor that cannot work is found before the motors are switched on;
- a run whose steps were mostly late or held exits 1, not 0.
"""

from __future__ import annotations

import functools
import json
import shutil
import sys
import threading
import time
from pathlib import Path

import numpy as np
import pytest

from rotation import bundles
from rotation.cli import main
from rotation.deploy import config as deploy_config
from rotation.deploy import job
from rotation.deploy.config import Config
from rotation.deploy.job import run
from rotation.policy import bundle as bundle_module
from rotation.policy.bundle import resolve_bundle


@pytest.fixture
def no_hand(monkeypatch):
    """Fail the test if deploy tries to open the hand."""

    def open_hand(*args, **kwargs):
        raise AssertionError("deploy opened the hand although the input was bad")

    monkeypatch.setattr(job, "open_hand", open_hand)


def edited_bundle(policy: str, folder: Path, **changes) -> str:
    path = folder / "edited"
    shutil.copytree(resolve_bundle(policy), path)
    cfg = json.loads((path / "config.json").read_text())
    cfg.update(changes)
    (path / "config.json").write_text(json.dumps(cfg))
    return str(path)


# ------------------------------------------------------------------------------------- bundles refused up front
LIMITS = {"lower": bundle_module.C.JOINT_LOWER.tolist(), "upper": bundle_module.C.JOINT_UPPER.tolist()}


@pytest.mark.parametrize(("changes", "words"), [
    (dict(joint_lower=LIMITS["upper"], joint_upper=LIMITS["lower"]), "joint_lower must be < joint_upper"),
    (dict(joint_upper=[u + 1.0 for u in LIMITS["upper"]]), "outside the hand's joint limits"),
    (dict(control_hz=1000.0), "control_hz must be in [5, 100] Hz"),
    (dict(action_scale="0.05"), "action_scale must be a number, got '0.05' (str)"),
], ids=["inverted limits", "wider than the hand", "rate no loop holds", "string number"])
def test_bad_bundles_are_refused_before_the_hand_is_opened(tmp_path, capsys, policy, no_hand, changes, words):
    bad = edited_bundle(policy, tmp_path, **changes)
    assert main(["deploy", "--hand", "sim-allegro", "--policy", bad, "--duration", "1"]) == 2
    err = capsys.readouterr().err
    assert err.startswith("rotate deploy: error: ") and words in err and "config.json" in err
    assert "Traceback" not in err


# ------------------------------------------------------------------------------------- motors off, confirmed
def test_lost_can_bus_is_not_reported_as_motors_off(policy, monkeypatch, hand_hook, capsys):
    """The real-hand path (an emulator on a virtual bus deploy does not know about): the bus dies mid-run, the
    driver's SYSTEM_OFF goes nowhere without a send error, and the hand never answers that it is off."""
    from rotation.hardware.allegro import driver as allegro
    from rotation.sim_hardware.allegro_emulator import AllegroEmulator

    monkeypatch.setattr(allegro, "AllegroConfig", functools.partial(allegro.AllegroConfig, feedback_timeout_s=0.3,
                                                                    reply_timeout_s=0.2))
    with AllegroEmulator(channel="deploy-bus-lost") as emu:
        hand_hook.after(1.0, lambda opened: setattr(emu.faults, "bus_off", True))
        summary = run(Config(hand="allegro", can="virtual:deploy-bus-lost", policy=policy, duration=10.0,
                                 allow_model_mismatch=True))
        assert emu.servo_on  # the hand never heard the motors-off command
    assert summary["fault"].startswith("hand fault") and summary["exit_code"] == 1
    assert summary["motors_off"] is False and summary["motors_off_confirmed"] is False
    # the fault text says what the driver did, not that the motors are off: it agrees with motors_off
    assert "switching the motors off" in summary["fault"] and not summary["fault"].endswith("; motors off")
    assert summary["motors_off_witness"] == "hand"
    err = capsys.readouterr().err
    assert "MOTORS NOT CONFIRMED OFF" in err and "SWITCH THE HAND OFF AT ITS POWER SUPPLY" in err


def test_leap_servo_refusing_torque_off_is_not_reported_as_motors_off(policy, monkeypatch, capsys):
    """A servo answers the torque-off write with an error (and keeps its torque): real-LEAP path, not confirmed."""
    from rotation.hardware.leap import driver as leap
    from rotation.hardware.leap import dynamixel_protocol as dp
    from rotation.sim_hardware.hand_physics import HandPhysics
    from rotation.sim_hardware.leap_emulator import LeapEmulator

    monkeypatch.setattr(leap, "LeapConfig", functools.partial(leap.LeapConfig, feedback_timeout_s=0.5,
                                                              max_retries=6))
    switch = sys.getswitchinterval()
    sys.setswitchinterval(5e-4)  # the emulator shares the GIL with the busy-polling SDK (as deploy does in emulation)
    try:
        with LeapEmulator(physics=HandPhysics.at_grasp("cup", 0, hold=False)) as emu:
            stubborn = 3
            write = emu._write

            def refuse_torque_off(dxl_id: int, addr: int, data: bytes) -> int:
                switching_off = addr == dp.REGISTERS["torque_enable"].addr and not data[0]
                if dxl_id == stubborn and switching_off and emu.register(dxl_id, "torque_enable"):
                    return 7  # access error: the write is not applied (once the torque is on)
                return write(dxl_id, addr, data)

            monkeypatch.setattr(emu, "_write", refuse_torque_off)
            summary = run(Config(hand="leap", port=emu.path, policy=policy, duration=1.0, allow_model_mismatch=True))
            assert emu.register(stubborn, "torque_enable") == 1
    finally:
        sys.setswitchinterval(switch)
    assert summary["motors_off"] is False and summary["motors_off_confirmed"] is False
    assert summary["exit_code"] != 0
    err = capsys.readouterr().err
    assert "servo 3 answered torque off with an error (access error)" in err
    assert "SWITCH THE HAND OFF AT ITS POWER SUPPLY" in err


def test_emulated_run_reports_confirmed_motors_off(policy, hand_hook):
    summary = run(Config(hand="sim-allegro", policy=policy, duration=1.0))
    assert summary["motors_off"] is True and summary["motors_off_confirmed"] is True
    assert summary["motors_off_witness"] == "emulator" and summary["exit_code"] in (0, 1)
    assert hand_hook.opened.driver.motors_off_confirmed is True  # the driver heard the hand say so, too


# ------------------------------------------------------------------------------------- checked before the start
@pytest.mark.skipif(not Path("/proc/self").is_dir(), reason="needs Linux /proc (a place nobody can create files)")
def test_unwritable_record_path_is_refused_before_the_motors_are_on(policy, no_hand, capsys):
    # as root every permission check passes; /proc refuses new files even to root: only trying it tells
    assert main(["deploy", "--hand", "sim-allegro", "--policy", policy, "--record", "/proc/rotate-test.h5"]) == 2
    err = capsys.readouterr().err
    assert "record: cannot write /proc/rotate-test.h5" in err and "Traceback" not in err


def test_record_path_must_be_a_new_file(tmp_path, policy, no_hand):
    with pytest.raises(ValueError, match="is a directory"):
        run(Config(hand="sim-allegro", policy=policy, record=str(tmp_path)))
    (tmp_path / "taken.h5").write_bytes(b"earlier run")
    with pytest.raises(ValueError, match="exists; choose a new file name, or pass --overwrite"):
        run(Config(hand="sim-allegro", policy=policy, record=str(tmp_path / "taken.h5")))
    assert (tmp_path / "taken.h5").read_bytes() == b"earlier run"
    (tmp_path / "file").write_text("")
    with pytest.raises(ValueError, match="is not a directory"):
        run(Config(hand="sim-allegro", policy=policy, record=str(tmp_path / "file" / "run.h5")))


def test_missing_touch_sensor_is_refused_before_the_motors_are_on(policy, no_hand, capsys):
    code = main(["deploy", "--hand", "sim-allegro", "--policy", policy, "--digit360",
                 "thumb=/dev/no-such-digit360-tty"])
    err = capsys.readouterr().err
    assert code == 2 and "--digit360: thumb=/dev/no-such-digit360-tty (no such device)" in err
    with pytest.raises(ValueError, match=r"index=D360-NOT-HERE \(no connected Digit 360 has this USB serial\)"):
        run(Config(hand="allegro", can="virtual:unused", policy=policy, digit360="index=D360-NOT-HERE",
                   allow_model_mismatch=True))


@pytest.mark.skipif(not Path("/proc/self").is_dir(), reason="needs Linux /proc")
def test_recording_that_fails_after_the_start_is_a_recording_fault(policy, monkeypatch, hand_hook):
    """If the file cannot be created after all (the disk changed since the check), the fault names the recording,
    not the hand's connection, and the motors are confirmed off."""
    monkeypatch.setattr(deploy_config, "check_record_path", lambda path, overwrite: None)
    summary = run(Config(hand="sim-allegro", policy=policy, duration=1.0, record="/proc/rotate-test.h5"))
    assert summary["fault"].startswith("recording failed: could not create /proc/rotate-test.h5")
    assert summary["exit_code"] == 1 and summary["motors_off"] is True


def test_touch_sensor_that_does_not_open_is_named(policy, tmp_path, hand_hook):
    """A path that exists but is no serial device: the run stops before the hand starts, and says why."""
    not_a_tty = tmp_path / "ttyFAKE"
    not_a_tty.write_text("")
    summary = run(Config(hand="sim-allegro", policy=policy, duration=1.0, digit360=f"index={not_a_tty}"))
    assert summary["fault"].startswith("touch sensor failed: digit360 index") and summary["exit_code"] == 1
    assert hand_hook.opened is None  # the hand was never opened
    assert summary["motors_off"] is True and summary["motors_off_confirmed"] is None
    assert summary["motors_off_witness"] is None


# ------------------------------------------------------------------------------------- a rate the loop could not hold
class MostlySlowPolicy:
    """Two of every three actions take longer than the loop's budget (0.6 periods): held, yet never for the whole
    hold limit, so the run goes on, holding most of its steps."""

    def __init__(self, inner):
        self.inner, self.config, self.calls, self.lock = inner, inner.config, 0, threading.Lock()

    def start_correction(self, step):
        return self.inner.start_correction(step)

    def act(self, obs):
        with self.lock:
            self.calls += 1
            slow = self.calls % 3 != 0
        if slow:
            time.sleep(0.8 / self.config.control_hz)
        return self.inner.act(obs)


def test_run_with_most_steps_held_is_not_reported_as_done(policy, monkeypatch, hand_hook):
    real_load = bundles.load_bundle
    monkeypatch.setattr(bundles, "load_bundle", lambda name: MostlySlowPolicy(real_load(name)))
    summary = run(Config(hand="sim-allegro", policy=policy, duration=2.0))
    assert summary["exit_code"] == 1 and summary["fault"].startswith("the loop could not hold 20 Hz")
    assert "control slots were late, held or skipped" in summary["fault"]
    assert summary["held_steps"] > summary["steps"] / 2 and summary["motors_off"]


def test_shortfall_counts_each_slot_once():
    from rotation.deploy.monitors import LoopStats

    stats = LoopStats(tick_times=list(np.arange(10.0)), late_steps=3, held_steps=3, degraded_steps=4)
    assert stats.shortfall(0.5) is None  # 4 of 10
    stats.skipped_slots = 2
    assert stats.shortfall(0.5) is None  # 6 of 12: not more than half
    stats.degraded_steps = 5
    assert stats.shortfall(0.5) == (
        "7 of 12 control slots were late, held or skipped (more than 50%; late 3, held 3, skipped 2): the policy "
        "did not run as it was trained")
