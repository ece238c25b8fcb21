"""Fixtures for the deploy tests: a policy bundle, hooks on the started hand and its emulated Digit 360 sensors, and
leak checks."""

from __future__ import annotations

import os
import threading
import time

import pytest

from rotation.deploy import job
from rotation.deploy import loop as loop_module
from rotation.policy.bundle import PolicyBundle, shipped_bundles
from rotation.policy.bundle_config import BundleConfig

STUDENT_SHIPPED = "student" in shipped_bundles()
"""The trained student ships in rotation/policies/student (the rotation test needs it)."""


@pytest.fixture(scope="session")
def policy(tmp_path_factory) -> str:
    """The shipped student if present, else a randomly initialised student bundle (only the loop is tested then)."""
    if STUDENT_SHIPPED:
        return "student"
    return str(PolicyBundle(BundleConfig(latent_source="adaptation")).save(tmp_path_factory.mktemp("bundle") / "s"))


@pytest.fixture(scope="session")
def first_hand_policy(tmp_path_factory) -> str:
    """A randomly initialised student bundle without a sim record, so of the first hand model ('digit360'): the
    emulated hand and fingertips then run that model, whose generation-1 touch renders in real time on 2 cores. The
    vendor-kinematics hand's generation-2 fingertips cost about twice the CPU per sample, and four of them beside the
    hand, the loop and an encoder fall behind real time by 0.1-0.25 s on 2 cores (0.5-1.3 s in the LEAP fault test,
    emulator and readers together; the recording still reaches the run's end, DrainThread.settle): tests that time
    the touch path itself use this policy."""
    return str(PolicyBundle(BundleConfig(latent_source="adaptation")).save(tmp_path_factory.mktemp("first") / "s"))


@pytest.fixture(autouse=True)
def no_leaks():
    """A deploy run must leave no thread running and no file descriptor (pty, CAN bus, HDF5 file) open."""
    threads_before = set(threading.enumerate())
    fds_before = len(os.listdir("/proc/self/fd"))
    yield
    deadline = time.monotonic() + 3.0
    while time.monotonic() < deadline:
        extra = [t for t in threading.enumerate() if t not in threads_before and t.is_alive()]
        fds = len(os.listdir("/proc/self/fd"))
        if not extra and fds <= fds_before:
            return
        time.sleep(0.05)
    assert not extra, f"leaked threads: {[t.name for t in extra]}"
    assert fds <= fds_before, f"leaked file descriptors: {fds - fds_before}"


class HandHook:
    """Records the hand ``rotate deploy`` opened and runs ``after(delay_s, fn(opened))`` that long after its control
    loop started (the motors on, the recording open): a fault meant for mid-run never lands in a start that a slow
    machine drew out (reading the hand's firmware, opening the recording)."""

    def __init__(self) -> None:
        self.opened = None
        self.actions: list[tuple[float, object]] = []
        self.timers: list[threading.Timer] = []

    def after(self, delay_s: float, fn) -> None:
        self.actions.append((delay_s, fn))

    def start(self, opened) -> None:
        for delay, fn in self.actions:
            timer = threading.Timer(delay, fn, args=(opened,))
            timer.daemon = True
            timer.start()
            self.timers.append(timer)


@pytest.fixture
def hand_hook(monkeypatch):
    hook = HandHook()
    real_open_hand = job.open_hand

    def open_hand(setup, stack, **kw):
        hook.opened = real_open_hand(setup, stack, **kw)
        return hook.opened

    class HookedLoop(loop_module.ControlLoop):
        def run(self) -> None:
            hook.start(self.opened)
            super().run()

    monkeypatch.setattr(job, "open_hand", open_hand)
    monkeypatch.setattr(loop_module, "ControlLoop", HookedLoop)  # job.run imports it when it runs
    yield hook
    for timer in hook.timers:
        timer.cancel()
        timer.join()


@pytest.fixture
def digit360_emulators(monkeypatch) -> dict:
    """The emulated Digit 360 sensors `rotate deploy` starts ('sim'), by finger, for their fault switches
    (``emulators["thumb"].faults.pause_s = 0.5``); filled as they start."""
    from rotation.sim_hardware import digit360_emulator

    started: dict = {}
    real = digit360_emulator.Digit360Emulator

    class Recorded(real):  # type: ignore[misc, valid-type]
        def __init__(self, *args, **kwargs) -> None:
            super().__init__(*args, **kwargs)
            started[kwargs.get("finger", "index")] = self

    monkeypatch.setattr(digit360_emulator, "Digit360Emulator", Recorded)
    return started
