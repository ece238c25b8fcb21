"""Checks shared by the deploy tests (a plain module: pytest collects nothing here)."""

from __future__ import annotations

import logging
from collections.abc import Callable


def load_fault(summary: dict) -> bool:
    """Whether a run ended in one of the documented faults of a machine too loaded to run the loop (a cold or busy
    2-core machine): the 20 Hz it could not hold, or the policy's actions missing their deadline until the hold limit.
    Both switch the motors off and exit 1."""
    fault = summary["fault"] or ""
    late_policy = fault.startswith("policy fault: no usable action") and (
        "no action within" in fault or "the policy is still computing an earlier step" in fault)
    return summary["exit_code"] == 1 and ("could not hold 20 Hz" in fault or late_policy)


def assert_done_or_load_fault(summary: dict) -> None:
    """Done, or a load fault (above); never another fault; the motors off."""
    assert (summary["exit_code"] == 0 and summary["fault"] is None) or load_fault(summary), summary["fault"]
    assert summary["motors_off"]


def again_if_loaded(run_once: Callable[[], dict], caplog=None) -> dict:
    """``run_once()``'s summary, run a second time (its log cleared first) when the first run ended in a load fault:
    what a test checks after a run needs a run the machine let happen. The second run's summary is returned as it is
    (the caller checks it, a load fault included)."""
    summary = run_once()
    if load_fault(summary):
        print(f"the machine was too loaded for this run ({summary['fault']}); running it again")
        if caplog is not None:
            caplog.clear()
        summary = run_once()
    return summary


def touch_warnings(caplog) -> list[logging.LogRecord]:
    """The touch path's fallback warnings (one per cause) among a test's log records."""
    return [r for r in caplog.records if r.name == "rotation.deploy.touch" and r.levelno == logging.WARNING
            and "touch unavailable" in r.getMessage()]
