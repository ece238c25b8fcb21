"""`rotate deploy` with a cautious-start student (scripts/cautious_start.py): the loop hands the policy its latent
shift with each of the run's first ``start_steps`` control steps, and nothing after."""

from __future__ import annotations

import json

import numpy as np
from deploy_checks import again_if_loaded, assert_done_or_load_fault

from rotation.bundles import load_bundle
from rotation.cli import main
from rotation.deploy import loop as loop_module

STEPS = 5


def test_the_first_steps_of_a_run_act_with_the_shift(tmp_path, load_script, capsys, hand_hook, monkeypatch):
    script = load_script("cautious_start")
    out = tmp_path / "cautious"
    script.run(script.Config(steps=STEPS, calibration_envs=16, calibration_seed=321, out=out))
    shift = np.float32(load_bundle(out).config.start_shift)
    submitted: list[tuple[int, np.ndarray | None]] = []
    real_submit = loop_module.PolicyWorker.submit

    def submit(self, k, request):
        submitted.append((k, request[1]))
        return real_submit(self, k, request)

    monkeypatch.setattr(loop_module.PolicyWorker, "submit", submit)

    def deploy() -> dict:
        submitted.clear()
        code = main(["deploy", "--hand", "sim-allegro", "--policy", str(out), "--duration", "1.5"])
        summary = json.loads(capsys.readouterr().out.strip().splitlines()[-1])
        assert code == summary["exit_code"]
        return summary

    assert_done_or_load_fault(again_if_loaded(deploy))
    assert submitted[0][0] == -1 and np.array_equal(submitted[0][1], shift)  # the warm-up runs step 0's path
    early = [c for k, c in submitted if 0 <= k < STEPS]
    later = [c for k, c in submitted if k >= STEPS]
    assert early and later  # the run went past the start
    assert all(c is not None and np.array_equal(np.asarray(c).reshape(-1), shift) for c in early)
    assert all(c is None for c in later)  # a student without touch: nothing once the start is over
