"""Fixtures for the emulator tests: every emulator and driver is closed, and no thread or pty may leak."""

from __future__ import annotations

import os
import sys
import threading
import time

import pytest

from rotation.hardware.realtime import frozen_heap
from rotation.sim_hardware.allegro_emulator import AllegroEmulator
from rotation.sim_hardware.digit360_emulator import Digit360Emulator
from rotation.sim_hardware.leap_emulator import LeapEmulator


def _open_fds() -> int:
    return len(os.listdir("/proc/self/fd"))


@pytest.fixture(autouse=True)
def no_leaks():
    """Fail a test that leaves threads running or file descriptors (ptys) open."""
    threads_before = set(threading.enumerate())
    fds_before = _open_fds()
    yield
    deadline = time.monotonic() + 2.0
    while time.monotonic() < deadline:
        extra = [t for t in threading.enumerate() if t not in threads_before and t.is_alive()]
        if not extra and _open_fds() <= fds_before:
            return
        time.sleep(0.02)
    assert not extra, f"leaked threads: {[t.name for t in extra]}"
    assert _open_fds() <= fds_before, f"leaked file descriptors: {_open_fds() - fds_before}"


@pytest.fixture(autouse=True)
def short_gil_switch_interval():
    """The emulators share the process with the drivers, and dynamixel-sdk busy-polls the port while it waits for a
    reply: hand the GIL over every 0.5 ms (instead of 5 ms) so the emulated hardware answers in time."""
    previous = sys.getswitchinterval()
    sys.setswitchinterval(5e-4)
    yield
    sys.setswitchinterval(previous)


@pytest.fixture(autouse=True)
def short_gc_passes():
    """As in `rotate deploy`: the heap the earlier tests built is hidden from the cyclic GC, whose full pass over it
    would stall the drivers' receive threads past their watchdogs (rotation.hardware.realtime.frozen_heap)."""
    with frozen_heap():
        yield


@pytest.fixture
def allegro_emu():
    with AllegroEmulator(transport="virtual") as emu:
        yield emu


@pytest.fixture
def slcan_emu():
    with AllegroEmulator(transport="slcan") as emu:
        yield emu


@pytest.fixture
def leap_emu():
    with LeapEmulator() as emu:
        yield emu


@pytest.fixture
def digit_emu():
    with Digit360Emulator() as emu:
        yield emu
