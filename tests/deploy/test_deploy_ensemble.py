"""`rotate deploy --policy ENSEMBLE`: an adapter ensemble (adapters.ensemble) runs on the emulated hand as an adapter
does: its fingertips start with it, every member's windows are read, and its corrections act.

The members are fresh (zero correction), pressure-only and IMU-only, the cheapest encoder inputs, so that the run
stays short on a loaded machine; the summary's counters show that the touch path ran."""

from __future__ import annotations

import json
import logging

from deploy_checks import again_if_loaded, assert_done_or_load_fault

from adapters.bundle import build_adapted
from rotation.cli import main

ENCODER = "sparshx-tinier-sim"


def test_an_ensemble_on_the_emulated_hand_reads_every_members_touch(tmp_path, policy, capsys, caplog, hand_hook,
                                                                    digit360_emulators):
    caplog.set_level(logging.INFO, logger="rotation")
    pressure = build_adapted(policy, ENCODER, ("pressure",), touch_every=4).save(tmp_path / "pressure")
    imu = build_adapted(policy, ENCODER, ("imu",), touch_every=4).save(tmp_path / "imu")
    assert main(["ensemble-adapters", "--members", str(pressure), str(imu), "--out", str(tmp_path / "ens")]) == 0
    capsys.readouterr()

    def deploy() -> dict:
        code = main(["deploy", "--hand", "sim-allegro", "--policy", str(tmp_path / "ens"), "--duration", "2.5"])
        summary = json.loads(capsys.readouterr().out.strip().splitlines()[-1])
        assert code == summary["exit_code"]
        return summary

    summary = again_if_loaded(deploy, caplog)
    assert_done_or_load_fault(summary)
    assert len(digit360_emulators) == 4  # started by deploy itself
    touch = summary["touch"]
    assert touch["refreshes"] > 0 and touch["adapter_steps"] > 0, touch
    assert touch["adapter_steps"] + touch["fallback_steps"] == summary["steps"]
    assert "tactile adapter: pressure, imu, every 4 steps" in caplog.text
