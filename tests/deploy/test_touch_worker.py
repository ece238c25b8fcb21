"""The pieces of `rotate deploy`'s touch path, on fakes: the sensors checked before the start, the adapter's inputs
in the env's tactile layout, the wait for the first windows, and the touch worker's refresh, hold, smoothing and
fallback (the end-to-end runs on the emulated hand: test_deploy_adapter.py).
"""

from __future__ import annotations

import logging
import time
from types import SimpleNamespace

import numpy as np
import pytest
from deploy_checks import touch_warnings

from adapters.bundle import TouchUnavailable
from rotation.deploy.sensors import SIM_WINDOWS
from rotation.deploy.touch import adapter_inputs, touch_sensors, wait_for_touch
from rotation.deploy.touch_worker import TouchWorker
from rotation.hardware.digit360.reader import SensorStale
from rotation.hardware.digit360.window import WindowNotReady


def fake_policy(windows=("pressure",), touch_every: int = 2) -> SimpleNamespace:
    return SimpleNamespace(fingers=("index", "thumb"), windows=windows, touch_every=touch_every,
                           config=SimpleNamespace(obs_groups={"proprio": (3, 32)}))


def test_touch_sensors_are_checked_before_the_start(caplog):
    caplog.set_level(logging.INFO, logger="rotation")
    policy = fake_policy()
    assert touch_sensors(policy, "a", {}, emulated=True) == {"index": "sim", "thumb": "sim"}
    assert "starting emulated Digit 360 fingertips" in caplog.text
    with pytest.raises(ValueError, match="no --digit360 was given.*index, thumb"):
        touch_sensors(policy, "a", {}, emulated=False)
    with pytest.raises(ValueError, match="Digit 360 for each of thumb"):
        touch_sensors(policy, "a", {"index": "D360-A"}, emulated=False)
    specs = {"index": "D360-A", "thumb": "/dev/ttyACM3"}
    assert touch_sensors(policy, "a", specs, emulated=False) == specs  # pressure: every sensor streams it
    with pytest.raises(ValueError, match="index=D360-A gives imu, pressure, not image"):
        touch_sensors(fake_policy(("image", "pressure")), "a", specs, emulated=False)  # no camera opened
    sim = {"index": "sim", "thumb": "sim"}
    assert touch_sensors(fake_policy(SIM_WINDOWS), "a", sim, emulated=True) == sim


def test_adapter_inputs_match_the_envs_tactile_group():
    rng = np.random.default_rng(0)
    window = {"image": rng.integers(0, 256, (6, 224, 224), dtype=np.uint8),
              "audio": rng.integers(-99, 99, (2, 27000), dtype=np.int16),
              "imu": np.zeros((224, 3), np.float32), "pressure": np.zeros((224, 1), np.float32), "t_end": 1.0}
    out = adapter_inputs(window, SIM_WINDOWS, "index")
    assert out["image"].dtype == np.float32 and out["image"].shape == (1, 6, 224, 224)
    np.testing.assert_array_equal(out["image"][0], window["image"] / np.float32(255.0))  # the env's [0, 1]
    assert out["audio_wave"].dtype == np.int16 and out["audio_wave"].shape == (1, 2, 27000)
    assert set(out) == {"image", "audio_wave", "imu", "pressure"}
    with pytest.raises(TouchUnavailable, match="index: its window has no image"):
        adapter_inputs({"pressure": window["pressure"]}, ("image", "pressure"), "index")


class FakeReader:
    """A fingertip whose window is pressure at rest, or SensorStale while ``stale``."""

    def __init__(self) -> None:
        self.stale = False

    def window(self, serial_only: bool = False) -> dict:
        if self.stale:
            raise SensorStale("digit360-thumb: newest IMU/pressure sample is 0.200 s old")
        return {"imu": np.zeros((224, 3), np.float32), "pressure": np.full((224, 1), 1013.0, np.float32),
                "t_end": time.monotonic()}  # the reader's window: its newest sample's host time


class SlowReader(FakeReader):
    """A fingertip whose windows need ``ready_after`` calls of history first (WindowNotReady before)."""

    def __init__(self, ready_after: int) -> None:
        super().__init__()
        self.calls, self.ready_after = 0, ready_after

    def window(self, serial_only: bool = False) -> dict:
        self.calls += 1
        if self.calls <= self.ready_after:
            raise WindowNotReady("digit360-index: 0.2 s of IMU history, the window needs 0.56 s")
        return super().window(serial_only)


def test_touch_windows_are_waited_for_before_the_start(caplog):
    """wait_for_touch: polls until every fingertip gives its windows, then runs the encoder once; a sensor that
    never gets ready (or stalls) ends the wait with one warning naming it, and the run starts as the student."""
    policy = fake_policy()
    encoded: list[dict] = []
    policy.tokens = encoded.append
    index = SlowReader(ready_after=3)
    took = wait_for_touch(policy, {"index": index, "thumb": FakeReader()}, timeout_s=5.0, poll_s=0.01)
    assert took is not None and 0.02 <= took < 5.0 and index.calls == 4
    assert len(encoded) == 1 and set(encoded[0]) == {"index", "thumb"}
    assert encoded[0]["thumb"]["pressure"].shape == (1, 224, 1)
    stalled = FakeReader()
    stalled.stale = True
    start = time.monotonic()
    assert wait_for_touch(policy, {"index": SlowReader(10 ** 6), "thumb": stalled}, timeout_s=0.2, poll_s=0.01) is None
    assert 0.2 <= time.monotonic() - start < 2.0 and len(encoded) == 1
    warning = next(r.getMessage() for r in caplog.records if r.levelno == logging.WARNING)
    assert "index: digit360-index: 0.2 s of IMU history" in warning and "thumb: digit360-thumb: newest" in warning
    assert wait_for_touch(policy, {"index": FakeReader()}, timeout_s=0.05, poll_s=0.01) is None  # no thumb sensor
    assert "thumb: no sensor" in caplog.records[-1].getMessage()


class FakeAdapter:
    """Checks the batch of one; returns 0.5 everywhere, or raises ``fail``; sleeps ``delay_s`` first."""

    def __init__(self) -> None:
        self.fail: BaseException | None = None
        self.delay_s = 0.0
        self.calls = 0

    def __call__(self, windows: dict, obs: dict) -> np.ndarray:
        self.calls += 1
        assert set(windows) == {"index", "thumb"} and windows["thumb"]["pressure"].shape == (1, 224, 1)
        assert obs["proprio"].shape == (1, 3, 32)
        time.sleep(self.delay_s)
        if self.fail is not None:
            raise self.fail
        return np.full((1, 8), 0.5, np.float32)


def settle(worker: TouchWorker) -> None:
    deadline = time.monotonic() + 5.0
    while worker.busy and time.monotonic() < deadline:
        time.sleep(0.005)
    assert not worker.busy


def stepper(worker: TouchWorker):
    """One control step k of a loop at 20 Hz on a made-up clock: the correction it acts with (None: the student),
    then the refresh it requests, waited for, so that step k + 1 sees what the refresh of step k gave."""
    obs = {"proprio": np.zeros((3, 32), np.float32)}

    def step(k: int) -> np.ndarray | None:
        corr = worker.correction(k, 0.05 * k)
        worker.refresh_if_due(k, obs, 0.05 * k)
        settle(worker)
        return corr

    return step


def test_touch_worker_holds_refreshes_and_falls_back_once_per_cause(caplog):
    """Driven step by step on a made-up clock (20 Hz, refresh every 2 steps, stale after 2 s)."""
    caplog.set_level(logging.INFO, logger="rotation")
    policy, adapter, thumb = fake_policy(), FakeAdapter(), FakeReader()
    policy.correction = adapter
    worker = TouchWorker(policy, {"index": FakeReader(), "thumb": thumb}, control_period_s=0.05)
    assert worker.max_age_s == pytest.approx(2.0)  # 3 refresh periods (0.3 s), at least 2 s
    step = stepper(worker)

    try:
        assert step(0) is None and not touch_warnings(caplog)  # no correction yet: the student, no warning
        assert np.all(step(1) == 0.5) and worker.active and adapter.calls == 1  # refreshed at 0; held at 1
        assert np.all(step(2) == 0.5) and adapter.calls == 2  # refreshed again at 2 (every 2 steps)
        thumb.stale = True
        assert np.all(step(3) == 0.5)  # the refresh of step 2 was fine; the stall shows at the refresh of step 4
        assert step(4) is not None and step(5) is None and step(6) is None and step(7) is None
        assert not worker.active and len(touch_warnings(caplog)) == 1  # one warning, not one per step
        assert "SensorStale: digit360-thumb" in touch_warnings(caplog)[0].getMessage()
        thumb.stale = False
        assert step(8) is None and np.all(step(9) == 0.5) and worker.active
        assert "step 9: touch is back" in caplog.text
        # a correction older than the limit is dropped (the worker stopped refreshing: no request for 2.05 s)
        assert worker.correction(50, 0.05 * 50) is None
        assert "ms old (> 2000 ms): the touch worker is behind" in touch_warnings(caplog)[-1].getMessage()
        assert step(51) is None and np.all(step(52) == 0.5)
        n_warnings = len(touch_warnings(caplog))
        assert worker.correction(200, 10.0) is None  # the same cause again: at info, counted
        assert len(touch_warnings(caplog)) == n_warnings and "(2 times so far)" in caplog.text
        # a bug in the refresh: falls back, logged with the exception
        adapter.fail = RuntimeError("boom")
        step(53), step(54), step(55)
        assert worker.correction(56, 0.05 * 56) is None
        bug = touch_warnings(caplog)[-1]
        assert "RuntimeError: boom" in bug.getMessage() and bug.exc_info is not None
        adapter.fail = None
        stats = worker.stats  # refreshed at 0, 2, 8, 51; failed at 4, 6 (stalled) and 53, 55 (the bug)
        assert (stats.fallbacks, stats.refreshes, stats.failed_refreshes) == (4, 4, 4)
        assert stats.adapter_steps + stats.fallback_steps == 18  # every correction() call: steps 0-9, 50-56, 200
    finally:
        worker.close()


def test_a_busy_touch_worker_never_blocks_the_loop():
    policy, adapter = fake_policy(), FakeAdapter()
    policy.correction = adapter
    adapter.delay_s = 0.3  # a refresh longer than the refresh period (2 steps)
    worker = TouchWorker(policy, {"index": FakeReader(), "thumb": FakeReader()}, control_period_s=0.05)
    obs = {"proprio": np.zeros((3, 32), np.float32)}
    try:
        start = time.monotonic()
        for k in range(6):  # refreshes due at 0, 2, 4: the worker is busy with the first one
            worker.correction(k, 0.05 * k)
            worker.refresh_if_due(k, obs, 0.05 * k)
        assert time.monotonic() - start < 0.1  # neither call waited for the 0.3 s refresh
        assert worker.busy and worker.stats.delayed_refreshes == 1  # counted once, started when the worker is free
        settle(worker)
        worker.refresh_if_due(6, obs, 0.3)
        assert worker.busy
        settle(worker)
        assert adapter.calls == 2 and worker.stats.refreshes == 2
    finally:
        worker.close()


def test_touch_worker_smooths_corrections_and_starts_over_after_a_failed_refresh():
    """A bundle's touch_smoothing averages the worker's refreshes as the simulation's delay line does: the first
    correction as it is, each next one keeping that share of the held one; a failed refresh starts the average over."""
    policy, thumb = fake_policy(touch_every=1), FakeReader()
    policy.touch_smoothing = 0.5
    readings = iter([1.0, 3.0, 5.0, 7.0, 9.0])
    policy.correction = lambda windows, obs: np.full((1, 8), next(readings), np.float32)
    worker = TouchWorker(policy, {"index": FakeReader(), "thumb": thumb}, control_period_s=0.05)
    step = stepper(worker)

    try:
        assert step(0) is None  # each step acts with what the refreshes up to the step before gave
        assert np.all(step(1) == 1.0) and np.all(step(2) == 2.0)  # 0.5 * 1 + 0.5 * 3
        thumb.stale = True  # the refreshes of steps 3 and 4 fail
        assert np.all(step(3) == 3.5) and step(4) is None  # 0.5 * 2 + 0.5 * 5, then the student alone
        thumb.stale = False
        assert step(5) is None and np.all(step(6) == 7.0)  # starts over: 7 as it is, not 0.5 * 3.5 + 0.5 * 7
        assert np.all(step(7) == 8.0)
    finally:
        worker.close()
