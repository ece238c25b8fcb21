"""The unmodified dynamixel-sdk and the LEAP driver against the emulated servo bus on a pty; injected faults."""

from __future__ import annotations

import logging
import time

import dynamixel_sdk as sdk
import numpy as np
import pytest

from rotation.hardware.hand import Hand, HandFault
from rotation.hardware.leap import dynamixel_protocol as dp
from rotation.hardware.leap.driver import LeapConfig, LeapHand
from rotation.hardware.safety import SafetyConfig

# generous retries and timeouts: the emulator shares the CPU (and the GIL) with the busy-polling SDK and with
# whatever else runs on the test machine
CFG = LeapConfig(feedback_timeout_s=0.5, max_retries=6)


def sdk_call(fn, *args):
    """One SDK exchange, repeated while it times out (a starved emulator), at most 5 times."""
    for _ in range(5):
        out = fn(*args)
        result = out[1] if len(out) == 3 else out[0]
        if result != sdk.COMM_RX_TIMEOUT:
            return out
    return out


def wait_until(pred, timeout=2.0):
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        if pred():
            return True
        time.sleep(0.005)
    return False


@pytest.fixture
def port(leap_emu):
    p = sdk.PortHandler(leap_emu.path)
    assert p.openPort() and p.setBaudRate(4_000_000)
    yield p
    p.closePort()


def test_sdk_ping_read_write(leap_emu, port):
    ph = sdk.PacketHandler(2.0)
    model, result, error = sdk_call(ph.ping, port, 3)
    assert (model, result, error) == (dp.MODEL_XC330_M288, sdk.COMM_SUCCESS, 0)
    _, result, _ = ph.ping(port, 42)  # nobody home: the SDK times out
    assert result == sdk.COMM_RX_TIMEOUT
    pos, result, error = sdk_call(ph.read4ByteTxRx, port, 0, dp.REGISTERS["present_position"].addr)
    assert result == sdk.COMM_SUCCESS and error == 0 and abs(pos - 2048) < 5  # index abduction at 0 rad
    assert sdk_call(ph.write2ByteTxRx, port, 1, 84, 640) == (sdk.COMM_SUCCESS, 0)
    assert leap_emu.register(1, "position_p_gain") == 640
    # EEPROM is locked while torque is on: access error (7), reported by the SDK as such
    assert sdk_call(ph.write1ByteTxRx, port, 1, 64, 1) == (sdk.COMM_SUCCESS, 0)
    result, error = sdk_call(ph.write1ByteTxRx, port, 1, 11, 5)
    assert result == sdk.COMM_SUCCESS and error == 7 and "not available" in ph.getRxPacketError(error)
    # read-only registers refuse writes too
    assert sdk_call(ph.write4ByteTxRx, port, 1, 132, 0)[1] == 7


@pytest.mark.parametrize("fast", [False, True])
def test_sdk_sync_read_and_sync_write(leap_emu, port, fast):
    ph = sdk.PacketHandler(2.0)
    reader = sdk.GroupSyncRead(port, ph, dp.STATE_ADDR, dp.STATE_LEN)
    writer = sdk.GroupSyncWrite(port, ph, 116, 4)
    for i in range(16):
        reader.addParam(i)
        writer.addParam(i, list(dp.encode_value(2048 + i, 4)))
    assert writer.txPacket() == sdk.COMM_SUCCESS
    assert wait_until(lambda: leap_emu.register(15, "goal_position") == 2063)
    for _ in range(5):
        if (reader.fastSyncRead() if fast else reader.txRxPacket()) == sdk.COMM_SUCCESS:
            break
    else:
        pytest.fail("no sync read reply in 5 attempts")
    for i in range(16):
        assert reader.isAvailable(i, 132, 4)
        # the hand moves between the reply and this look at the emulator: within 200 ticks (17 degrees) of it
        assert abs(reader.getData(i, 132, 4) - leap_emu.register(i, "present_position")) < 200
    assert abs(reader.getData(0, 132, 4) - 2048) < 5


def test_leap_hand_startup_and_tracking(leap_emu):
    with LeapHand(leap_emu.path, CFG) as hand:
        assert isinstance(hand, Hand)
        assert all(leap_emu.register(i, "operating_mode") == 5 for i in range(16))
        assert leap_emu.register(0, "position_p_gain") == 600 and leap_emu.register(1, "position_p_gain") == 800
        assert leap_emu.register(4, "position_d_gain") == 150 and leap_emu.register(7, "goal_current") == 550
        assert all(leap_emu.register(i, "torque_enable") == 1 for i in range(16))
        q0 = hand.read_state().q
        goal = q0 + 0.1
        t0 = time.monotonic()
        while time.monotonic() - t0 < 0.5:
            hand.set_targets(goal)
            time.sleep(0.02)
        state = hand.read_state()
        assert np.allclose(state.target, np.clip(goal, SafetyConfig().lower, SafetyConfig().upper))
        assert np.median(np.abs(state.q - state.target)) < 0.03
        # goal positions on the servos are the Allegro targets + pi
        assert abs(leap_emu.register(2, "goal_position") - dp.allegro_to_counts(state.target[2])) <= 30
        info = hand.info()
        assert info.kind == "leap" and info.hardware == "XC330-M288 x16" and np.all(info.temperatures == 30)
    assert all(leap_emu.register(i, "torque_enable") == 0 for i in range(16))


def test_leap_config_errors_are_loud(leap_emu):
    with pytest.raises(ValueError, match="baudrate"):
        LeapConfig(baudrate=12345)
    with pytest.raises(ValueError, match="current_limit_ma"):
        LeapConfig(safety=SafetyConfig(torque_limits=(0.1,) * 16))
    leap_emu.tables[3][38:40] = dp.encode_value(300, 2)  # this servo's Current Limit is below the goal current
    with pytest.raises(ValueError, match="servos {3: 300}"):
        with LeapHand(leap_emu.path, CFG):
            pass


# ---------------------------------------------------------------------------------------------- injected faults
@pytest.mark.parametrize("fault", ["drop_replies", "corrupt_crc"])
def test_fault_lost_or_corrupt_replies_are_retried(leap_emu, fault, caplog):
    with LeapHand(leap_emu.path, CFG) as hand, caplog.at_level(logging.WARNING):
        seq = hand.read_state().seq
        setattr(leap_emu.faults, fault, 1)
        assert wait_until(lambda: hand.stats()["read_retries"] >= 1)
        assert wait_until(lambda: hand.read_state().seq > seq + 5) and hand.fault is None
    assert "fast sync read" in caplog.text


def test_fault_servo_error_byte_retried_then_torque_off(leap_emu, caplog):
    with LeapHand(leap_emu.path, CFG) as hand, caplog.at_level(logging.WARNING):
        leap_emu.faults.error_byte[5] = 0x03  # the servo keeps reporting a CRC error
        assert wait_until(lambda: hand.fault is not None)
        assert "CRC error" in caplog.text
        assert wait_until(lambda: all(leap_emu.register(i, "torque_enable") == 0 for i in range(16)))
        with pytest.raises(HandFault):
            hand.set_targets(np.zeros(16))


def test_fault_hardware_alert_switches_every_servo_off(leap_emu, caplog):
    with LeapHand(leap_emu.path, CFG) as hand, caplog.at_level(logging.ERROR):
        leap_emu.faults.hardware_error[9] = 0x20  # overload
        assert wait_until(lambda: hand.fault is not None)
        assert "servo 9" in str(hand.fault) and "overload" in str(hand.fault)
        assert wait_until(lambda: all(leap_emu.register(i, "torque_enable") == 0 for i in range(16)))


def test_fault_hardware_error_at_startup_is_refused(leap_emu):
    leap_emu.faults.hardware_error[2] = 0x04
    time.sleep(0.01)
    with pytest.raises(HandFault, match="servo 2 .*overheating"):
        with LeapHand(leap_emu.path, CFG):
            pass


def test_fault_disconnect_switches_off_within_timeout(leap_emu, caplog):
    with LeapHand(leap_emu.path, CFG) as hand, caplog.at_level(logging.ERROR):
        leap_emu.disconnect()
        t0 = time.monotonic()
        assert wait_until(lambda: hand.fault is not None, timeout=3.0)
        assert time.monotonic() - t0 < CFG.feedback_timeout_s + 1.0
        assert "FAULT" in caplog.text


def test_torque_off_is_confirmed_by_every_servo(leap_emu):
    with LeapHand(leap_emu.path, CFG) as hand:
        assert hand.motors_switched_on and hand.motors_off_confirmed is None
    assert hand.motors_off_confirmed is True


def test_fault_disconnect_leaves_torque_off_unconfirmed(leap_emu, caplog):
    with LeapHand(leap_emu.path, CFG) as hand, caplog.at_level(logging.CRITICAL):
        leap_emu.disconnect()
        assert wait_until(lambda: hand.fault is not None, timeout=3.0)
    assert hand.motors_off_confirmed is False and "cut the power" in caplog.text


def test_policy_stall_release_and_resume(leap_emu):
    safety = SafetyConfig(policy_timeout_s=0.1, on_policy_stall="release")
    cfg = LeapConfig(feedback_timeout_s=0.5, max_retries=6, safety=safety)
    with LeapHand(leap_emu.path, cfg) as hand:
        q = hand.read_state().q
        hand.set_targets(q)
        assert wait_until(lambda: leap_emu.register(0, "torque_enable") == 0)  # the policy went quiet: released

        def commanding() -> bool:  # the policy is back
            hand.set_targets(q)
            return leap_emu.register(0, "torque_enable") == 1

        assert wait_until(commanding)
