"""Checks shared by the deploy tests (a plain module: pytest collects nothing here)."""

from __future__ import annotations


def assert_done_or_rate_fault(summary: dict) -> None:
    """Done, or (a cold or loaded 2-core machine) the documented rate fault; never another fault; the motors off."""
    rate_fault = summary["fault"] is not None and "could not hold 20 Hz" in summary["fault"]
    assert (summary["exit_code"] == 0 and summary["fault"] is None) or (rate_fault and summary["exit_code"] == 1), \
        summary["fault"]
    assert summary["motors_off"]
