"""Safety layer on hand-made cases: clamps, rate limit, NaN rejection, watchdog, motors off on every exit path."""

from __future__ import annotations

import logging
import os
import signal

import numpy as np
import pytest

from rotation.hardware.hand import JOINT_LOWER, JOINT_UPPER, TORQUE_LIMITS
from rotation.hardware.safety import SafetyConfig, SafetyLayer, clamp_targets, clamp_torques, motors_off_on_exit

LO = np.array([-1.0, 0.0])
HI = np.array([1.0, 2.0])


def test_clamp_targets_limits_then_rate():
    prev = np.array([0.0, 1.0])
    # within limits and within the step: unchanged
    assert np.allclose(clamp_targets(np.array([0.05, 1.05]), prev, LO, HI, 0.1), [0.05, 1.05])
    # large jump: moved by exactly max_step towards the goal
    assert np.allclose(clamp_targets(np.array([0.9, 0.0]), prev, LO, HI, 0.1), [0.1, 0.9])
    # beyond the limits: the goal is clipped first, so the target stops at the limit
    assert np.allclose(clamp_targets(np.array([5.0, -3.0]), np.array([0.95, 0.05]), LO, HI, 0.1), [1.0, 0.0])


def test_clamp_targets_rejects_non_finite_whole_command():
    prev = np.array([0.2, 0.3])
    for bad in ([np.nan, 0.0], [0.0, np.inf], [-np.inf, np.nan]):
        out = clamp_targets(np.array(bad), prev, LO, HI, 0.1)
        assert np.array_equal(out, prev) and out is not prev


def test_clamp_targets_previous_outside_limits_comes_back_inside():
    out = clamp_targets(np.array([-2.0, 1.0]), np.array([-1.05, 1.0]), LO, HI, 0.01)
    assert np.allclose(out, [-1.0, 1.0])


def test_clamp_torques():
    lim = np.array([0.3, 0.5, 0.2])
    out = clamp_torques(np.array([1.0, np.nan, -0.25]), lim)
    assert np.allclose(out, [0.3, 0.0, -0.2])


def test_config_validation_is_loud():
    with pytest.raises(ValueError, match="max_target_rate"):
        SafetyConfig(max_target_rate=0.0)
    with pytest.raises(ValueError, match="lower must be below"):
        SafetyConfig(lower=JOINT_UPPER, upper=JOINT_LOWER)
    with pytest.raises(ValueError, match="on_policy_stall"):
        SafetyConfig(on_policy_stall="panic")  # type: ignore[arg-type]
    with pytest.raises(ValueError, match="16 values"):
        SafetyConfig(torque_limits=(0.1,) * 3)
    # above the hardware limits: an error naming the joints, never a silent clamp
    too_big = tuple(t + 0.1 if i == 5 else t for i, t in enumerate(TORQUE_LIMITS))
    with pytest.raises(ValueError, match=r"joints \[5\]"):
        SafetyLayer(SafetyConfig(torque_limits=too_big), TORQUE_LIMITS)


def test_layer_rate_limit_nan_and_watchdog(caplog):
    layer = SafetyLayer(SafetyConfig(max_target_rate=1.0, policy_timeout_s=0.1, on_policy_stall="hold"))
    q0 = np.array(JOINT_LOWER) + 0.1
    layer.reset(q0)
    assert layer.accept(q0 + 1.0, now=0.0)
    target, release = layer.step(q0, dt=0.01, now=0.01)  # 1 rad/s x 10 ms
    assert np.allclose(target, np.minimum(q0 + 0.01, JOINT_UPPER)) and not release
    with caplog.at_level(logging.ERROR):
        assert not layer.accept(np.full(16, np.nan), now=0.02)
    assert "non-finite" in caplog.text and layer.rejected == 1
    target2, _ = layer.step(q0, dt=0.01, now=0.03)  # the last good goal is still tracked
    assert np.all(target2 >= target)
    caplog.clear()
    with caplog.at_level(logging.ERROR):
        _, release = layer.step(q0, dt=0.01, now=0.5)
    assert not release and "holding" in caplog.text
    with pytest.raises(ValueError, match="shape"):
        layer.accept(np.zeros(3), now=0.6)


def test_layer_release_then_resume_from_measured_pose():
    layer = SafetyLayer(SafetyConfig(policy_timeout_s=0.1, on_policy_stall="release"))
    q0 = np.array(JOINT_LOWER) + 0.2
    layer.reset(q0)
    _, release = layer.step(q0, 0.003, now=1.0)
    assert not release  # the watchdog is armed by the first command only
    layer.accept(q0, now=1.0)
    _, release = layer.step(q0, 0.003, now=1.2)
    assert release
    sagged = q0 + 0.05  # the released hand moved
    layer.accept(q0, now=1.3)
    target, release = layer.step(sagged, 0.003, now=1.3)
    assert not release and np.allclose(target, np.clip(sagged - 0.003, JOINT_LOWER, JOINT_UPPER), atol=1e-9)


def test_motors_off_once_on_context_exit_and_exception():
    before = signal.getsignal(signal.SIGINT)  # default_int_handler, or SIG_IGN under a background shell
    calls = []
    with motors_off_on_exit(lambda: calls.append("off")):
        pass
    assert calls == ["off"]
    with pytest.raises(RuntimeError), motors_off_on_exit(lambda: calls.append("off2")) as off:
        off("manual")
        raise RuntimeError("policy crashed")
    assert calls == ["off", "off2"]
    assert signal.getsignal(signal.SIGINT) is before  # handlers restored


@pytest.mark.parametrize("sig, exc", [(signal.SIGTERM, SystemExit), (signal.SIGINT, KeyboardInterrupt)])
def test_motors_off_on_signal(sig, exc):
    calls = []
    with pytest.raises(exc), motors_off_on_exit(lambda: calls.append("off"), lambda: calls.append("request")):
        os.kill(os.getpid(), sig)
        for _ in range(1000):  # the handler runs between bytecodes of the main thread
            pass
    assert calls == ["request", "off"]


def test_motors_off_nested_hands_both_switch_off():
    calls = []
    with pytest.raises(SystemExit):
        with motors_off_on_exit(lambda: calls.append("a"), lambda: calls.append("req a"), name="a"):
            with motors_off_on_exit(lambda: calls.append("b"), lambda: calls.append("req b"), name="b"):
                os.kill(os.getpid(), signal.SIGTERM)
                for _ in range(1000):
                    pass
    assert calls == ["req b", "req a", "b", "a"]
    assert signal.getsignal(signal.SIGTERM) is signal.SIG_DFL
