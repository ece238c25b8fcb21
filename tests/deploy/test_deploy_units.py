"""Deploy pieces without a hand: the env's observation/target bookkeeping, the policy worker, option checks."""

from __future__ import annotations

import logging
import threading
import time

import numpy as np
import pytest

from envs import EnvConfig, RandomizationConfig, RotateCupVec
from envs import constants as C
from envs.constants import DEFAULT_HAND
from envs.grasp_cache import load_default_cache
from envs.physics import default_randomization
from rotation.cli import main
from rotation.deploy.config import Config
from rotation.deploy.job import run
from rotation.deploy.policy import PolicyFault, PolicyState, PolicyWorker, action_problem, check_deployable
from rotation.deploy.sensors import parse_digit360
from rotation.policy.bundle_config import BundleConfig
from rotation.sim_hardware.hand_physics import HandPhysics


def test_observations_and_targets_are_the_envs():
    """Fed the env's joint angles and the same actions, deploy builds bit-identical observations and targets."""
    env = RotateCupVec(EnvConfig(randomization=RandomizationConfig(enabled=False)), num_envs=1, seed=3)
    obs = env.reset(seed=3)
    state = PolicyState(env.grasp_q[0], C.JOINT_LOWER, C.JOINT_UPPER, C.ACTION_SCALE)
    rng = np.random.default_rng(0)
    for _ in range(35):  # more than the 30-step history
        mine = state.observation()
        assert mine["proprio"].dtype == np.float32 and mine["proprio_hist"].shape == (30, 32)
        np.testing.assert_array_equal(mine["proprio"], obs["proprio"][0])
        np.testing.assert_array_equal(mine["proprio_hist"], obs["proprio_hist"][0])
        action = rng.uniform(-1.5, 1.5, C.NUM_JOINTS)  # beyond [-1, 1]: both clip
        obs, *_ = env.step(action[None])
        state.apply(action)
        np.testing.assert_array_equal(state.targets, env.targets[0])
        state.push(env._qpos[0, : C.NUM_JOINTS])  # the measured joints after the step (no noise: randomization off)
    env.close()


def test_worker_deadline_hold_and_errors():
    calls = []

    def act(obs):
        calls.append(obs["x"])
        if obs["x"] == 1:
            time.sleep(0.3)  # a stalled step
        if obs["x"] == 3:
            raise RuntimeError("boom")
        return np.full(16, obs["x"], dtype=np.float32)

    worker = PolicyWorker(act)
    try:
        assert worker.submit(0, {"x": 0}) and worker.wait(0, 1.0)[0] == 0
        assert worker.submit(1, {"x": 1})
        assert worker.wait(1, 0.05) is None  # not ready in time: the loop holds
        assert not worker.submit(2, {"x": 2})  # still busy with step 1: refused, the loop holds again
        time.sleep(0.4)
        assert worker.submit(2, {"x": 2}) and worker.wait(2, 1.0)[0] == 2  # the late result of step 1 is dropped
        assert worker.submit(3, {"x": 3})
        with pytest.raises(PolicyFault, match="boom"):
            worker.wait(3, 1.0)
    finally:
        worker.close()
    assert calls == [0, 1, 2, 3]


def test_action_problems():
    assert action_problem(np.zeros(16, np.float32)) is None
    assert "non-finite" in action_problem(np.r_[np.zeros(15), np.nan])
    assert "non-finite" in action_problem(np.r_[np.inf, np.zeros(15)])
    assert "shape" in action_problem(np.zeros(15))


def test_only_proprioceptive_bundles_deploy():
    check_deployable(BundleConfig(latent_source="adaptation"), "student")
    with pytest.raises(ValueError, match="'priv'.*student"):
        check_deployable(BundleConfig(latent_source="privileged"), "teacher")
    # an adapter reference deploys as the adapter bundle itself (it reads touch), never as a plain student
    check_deployable(BundleConfig(latent_source="adaptation", adapter="adapters/x"), "adapter", reads_touch=True)
    with pytest.raises(ValueError, match="deploy the adapter bundle itself"):
        check_deployable(BundleConfig(latent_source="adaptation", adapter="adapters/x"), "student+adapter")


def test_option_errors_before_anything_starts(tmp_path, policy):
    with pytest.raises(ValueError, match="unknown interface"):
        Config(hand="allegro", policy=policy, can="kvaser:0")
    with pytest.raises(ValueError, match="baud"):
        Config(hand="leap", policy=policy, baud=123)
    with pytest.raises(ValueError, match="gain_scale"):
        Config(hand="sim-leap", policy=policy, gain_scale=1.5)
    with pytest.raises(ValueError, match="no bundle directory"):
        run(Config(hand="sim-allegro", policy=str(tmp_path / "nope")))
    taken = tmp_path / "taken.h5"
    taken.write_bytes(b"")
    with pytest.raises(ValueError, match="exists"):
        run(Config(hand="sim-allegro", policy=policy, record=str(taken)))
    with pytest.raises(ValueError, match="out of range"):
        run(Config(hand="sim-allegro", policy=policy, grasp=10_000))


def test_cli_requires_hand_and_policy_and_reports_bad_options(capsys, tmp_path):
    with pytest.raises(SystemExit) as exc:
        main(["deploy", "--policy", "student"])
    assert exc.value.code == 2 and "--hand" in capsys.readouterr().err
    with pytest.raises(SystemExit) as exc:  # the adapter bundle is the policy: no separate --adapter
        main(["deploy", "--hand", "sim-leap", "--policy", "x", "--adapter", str(tmp_path)])
    assert exc.value.code == 2 and "--adapter" in capsys.readouterr().err


def test_digit360_option():
    assert parse_digit360("", emulated=False) == {}
    assert parse_digit360("A,B,C,D", emulated=False) == {"index": "A", "middle": "B", "ring": "C", "thumb": "D"}
    assert parse_digit360("thumb=D360-1, index=/dev/pts/7", emulated=False) == {"thumb": "D360-1",
                                                                                 "index": "/dev/pts/7"}
    assert set(parse_digit360("sim", emulated=True)) == set(C.FINGERS)
    for bad, match in (("A,B", "4 comma-separated"), ("pinky=A", "unknown finger"), ("thumb=A,B", "mixes"),
                       ("thumb=A,thumb=B", "twice"), ("A,,B,C", "empty")):
        with pytest.raises(ValueError, match=match):
            parse_digit360(bad, emulated=False)
    with pytest.raises(ValueError, match="emulated hand"):
        parse_digit360("sim", emulated=False)


def test_emulated_hand_starts_at_a_cached_grasp_and_holds_until_released():
    scales = default_randomization(DEFAULT_HAND).scales
    nominal = scales[len(scales) // 2]  # RotateCup-v0's nominal scale on the default hand (0.78 on 'digit360')
    cache = load_default_cache("cup", hand=DEFAULT_HAND)
    bucket = int(np.abs(cache.scales - nominal).argmin())
    physics = HandPhysics.at_grasp("cup", grasp=3)
    row = cache.grasps[bucket, 3]
    q, _ = physics.joint_state()
    assert physics.hand == DEFAULT_HAND and physics.scale == pytest.approx(nominal)
    assert physics.grasp == 3 and physics.held
    np.testing.assert_allclose(q, row[:16])
    np.testing.assert_allclose(physics.object_pose(), row[16:])
    physics.advance(0.05)  # held: nothing moves, not even under gravity
    np.testing.assert_allclose(physics.object_pose(), row[16:])
    assert physics.time == 0.0
    physics.release()
    physics.advance(0.05)
    assert physics.time > 0.0 and not physics.held
    with pytest.raises(ValueError, match="out of range"):
        HandPhysics.at_grasp("cup", grasp=cache.grasps.shape[1])


# ------------------------------------------------------------------------------------------ the recording's drain
def test_the_drain_thread_drains_off_the_loop_and_hands_over_its_error():
    """DrainThread moves the sensors' samples into the recording on its own thread every ``every_s``, drains once
    more when a run that ended well stops it, and keeps a failed drain's error for the loop's next check()."""
    from rotation.data.session import SessionError
    from rotation.deploy.drain import DrainThread

    calls, appended = [], []

    class Drain:
        fail = False

        def drain(self, append):
            calls.append(time.monotonic())
            if self.fail:
                raise SessionError("disk full")
            append("digit360/index/imu", np.zeros((1, 3)), np.array([len(calls)]))

    def wait_until(condition):
        deadline = time.monotonic() + 10.0
        while not condition():
            assert time.monotonic() < deadline
            time.sleep(0.01)

    drainer = DrainThread(Drain(), lambda *a: appended.append(a), every_s=0.02)
    wait_until(lambda: len(calls) >= 3)
    drainer.check()  # nothing failed
    drainer.stop(final_drain=True)
    n = len(calls)
    assert len(appended) == n  # the final drain ran on the caller's thread before stop() returned
    time.sleep(0.1)
    assert len(calls) == n  # and nothing drains after it

    failing = Drain()
    failing.fail = True
    drainer = DrainThread(failing, lambda *a: None, every_s=0.02)
    wait_until(lambda: drainer.error is not None)
    count = len(calls)
    with pytest.raises(SessionError, match="disk full"):
        drainer.check()
    time.sleep(0.1)
    assert len(calls) == count  # a failed drain ends the thread
    drainer.stop(final_drain=False)  # a fault's stop: no drain, no raise
    with pytest.raises(SessionError, match="disk full"):
        drainer.stop(final_drain=True)


def test_after_a_fault_drain_rest_moves_the_last_samples_once_the_motors_are_off(caplog):
    """DrainThread.drain_rest (called once the hand is off): one more drain after a fault's stop, and after the final
    drain of a run that ended well (what arrived since); False, logged, when the drain is still busy or had failed
    (nothing is waited for forever)."""
    from rotation.data.session import SessionError
    from rotation.deploy.drain import DrainThread

    class Drain:
        def __init__(self, block: threading.Event | None = None, fail: bool = False):
            self.calls, self.block, self.fail = 0, block, fail

        def drain(self, append):
            self.calls += 1
            if self.block is not None:
                self.block.wait()
            if self.fail:
                raise SessionError("disk full")
            append("digit360/index/imu", np.zeros((1, 3)), np.array([float(self.calls)]))

    appended = []
    faulted = DrainThread(Drain(), lambda *a: appended.append(a), every_s=60.0)  # no drain before the fault
    faulted.stop(final_drain=False)
    assert appended == []
    assert faulted.drain_rest(timeout_s=5.0) and len(appended) == 1

    ended = DrainThread(Drain(), lambda *a: appended.append(a), every_s=60.0)
    ended.stop(final_drain=True)
    assert len(appended) == 2 and ended.drain_rest(timeout_s=5.0) and len(appended) == 3

    release = threading.Event()
    busy = DrainThread(Drain(block=release), lambda *a: None, every_s=0.01)
    time.sleep(0.2)  # a drain now blocks
    busy.stop(final_drain=False)
    t = time.monotonic()
    assert not busy.drain_rest(timeout_s=0.3) and time.monotonic() - t < 2.0
    assert "drain still busy" in caplog.text
    release.set()

    failing = DrainThread(Drain(fail=True), lambda *a: None, every_s=0.01)
    time.sleep(0.2)
    failing.stop(final_drain=False)
    assert not failing.drain_rest(timeout_s=5.0) and "a drain failed: disk full" in caplog.text


def test_settle_waits_for_late_sensors_but_not_for_a_stalled_one(caplog):
    """DrainThread.settle (the motors off, the sensors still open) waits while a sensor's samples of the run's last
    moments are still arriving, stops waiting for one whose newest sample no longer advances (stalled, unplugged),
    never waits for one that delivered nothing, and reports how far the ones that did not catch up end early."""
    from rotation.deploy import drain as drain_module
    from rotation.deploy.drain import DrainThread

    t_end = time.monotonic()
    started = time.monotonic()

    class Late:
        def drain(self, append):
            pass

        def newest(self):
            elapsed = time.monotonic() - started
            return {"digit360 index": t_end - 0.5 + elapsed,  # 0.5 s behind, catching up in real time
                    "digit360 ring": t_end - 2.0,  # stalled before the end
                    "skin": -np.inf}  # never delivered

    drainer = DrainThread(Late(), lambda *a: None, every_s=60.0)
    drainer.stop(final_drain=False)
    with caplog.at_level(logging.WARNING):
        behind = drainer.settle(t_end, cap_s=5.0)
    waited = time.monotonic() - started
    assert 0.5 <= waited < 1.5, waited  # until the index caught up, not the 5 s cap for the ring
    assert set(behind) == {"digit360 ring"} and behind["digit360 ring"] == pytest.approx(2.0)
    assert "digit360 ring's samples end 2.00 s before the run's last step" in caplog.text

    started = time.monotonic()
    assert set(drainer.settle(t_end + 10.0, cap_s=0.3)) == {"digit360 index", "digit360 ring"}  # the cap holds
    assert time.monotonic() - started < 0.3 + 5 * drain_module.POLL_S + 0.5

    class Broken(Late):
        def newest(self):
            raise RuntimeError("reader gone")

    broken = DrainThread(Broken(), lambda *a: None, every_s=60.0)
    broken.stop(final_drain=False)
    with caplog.at_level(logging.WARNING):
        assert broken.settle(t_end) == {}
    assert "could not wait for the sensors' last samples" in caplog.text
