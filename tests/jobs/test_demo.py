"""`rotate demo` exits with the deploy dry run's status: a faulted dry run is not a successful demo.

The evaluation, the video and the deploy run are replaced by stand-ins here (each has its own tests); what is
tested is how the demo reports their outcome.
"""

from __future__ import annotations

from pathlib import Path

import pytest

from rotation.cli import main
from rotation.deploy import job as deploy_job
from rotation.jobs import demo


@pytest.fixture
def stand_ins(monkeypatch):
    """Fast evaluation and video; the deploy summary is whatever the test puts in ``summary``."""
    summary: dict = {}

    def evaluate(cfg):
        (cfg.out / "plots").mkdir(parents=True, exist_ok=True)
        (cfg.out / "results.md").write_text("# Evaluation\n\n| condition | policy |\n")
        return [{"condition": "nominal", "policy": p, "rotation_rate": 0.1, "ttf": 1.0} for p in cfg.policies]

    def view(cfg):
        Path(cfg.out).write_bytes(b"")
        return Path(cfg.out)

    monkeypatch.setattr(demo.evaluate_job, "run", evaluate)
    monkeypatch.setattr(demo.view_job, "run", view)
    monkeypatch.setattr(deploy_job, "run", lambda cfg: dict(summary))
    return summary


def test_demo_fails_when_its_deploy_dry_run_faults(tmp_path, capsys, stand_ins):
    stand_ins.update(exit_code=1, fault="hand fault: allegro: no complete position cycle", motors_off=True)
    assert main(["demo", "--out", str(tmp_path / "demo"), "--deploy-seconds", "1"]) == 1
    report = (tmp_path / "demo" / "README.md").read_text()  # the report is still written, and says it
    assert "**FAILED** (exit status 1): hand fault: allegro" in report
    assert "deploy dry run did not complete" in capsys.readouterr().err


def test_demo_passes_on_the_deploy_status_of_a_stopped_run(tmp_path, stand_ins):
    stand_ins.update(exit_code=130, fault="interrupted (Ctrl-C / SIGINT)")
    assert main(["demo", "--out", str(tmp_path / "demo"), "--deploy-seconds", "1"]) == 130


def test_demo_succeeds_when_everything_completed(tmp_path, stand_ins):
    stand_ins.update(exit_code=0, fault=None, motors_off=True)
    assert main(["demo", "--out", str(tmp_path / "demo"), "--deploy-seconds", "1"]) == 0
    assert "Result: completed" in (tmp_path / "demo" / "README.md").read_text()
    result = demo.run(demo.Config(out=tmp_path / "skip", deploy_seconds=0.0))
    assert result["exit_code"] == 0 and Path(result["report"]).is_file()


def test_an_earlier_demo_evaluation_of_other_policies_is_kept_aside(tmp_path, stand_ins, capsys):
    """Re-running the demo after the shipped policies changed starts a new evaluation and keeps the old one."""
    stand_ins.update(exit_code=0, fault=None, motors_off=True)
    old = tmp_path / "demo" / "evaluation"
    old.mkdir(parents=True)
    (old / "progress.json").write_text('{"config": {"episodes": 1}, "weights": {"teacher": "0000"}}\n')
    (old / "results.json").write_text('{"rows": []}\n')
    assert main(["demo", "--out", str(tmp_path / "demo"), "--deploy-seconds", "0"]) == 0
    kept = [p for p in (tmp_path / "demo").iterdir() if p.name.startswith("evaluation.")]
    assert len(kept) == 1 and (kept[0] / "results.json").read_text() == '{"rows": []}\n'
    assert "kept in" in capsys.readouterr().out


def test_demo_with_a_shipped_adapter_evaluates_it(tmp_path, stand_ins, monkeypatch):
    """With rotation/policies/adapter shipped, the demo adds a student vs adapter evaluation with touch and dry-runs
    deploy with the adapter (its emulated fingertips start with it); without one, both stay with the student."""
    stand_ins.update(exit_code=0, fault=None, motors_off=True)
    evaluated, deployed = [], []
    evaluate = demo.evaluate_job.run

    def record_evaluate(cfg):
        evaluated.append(dict(cfg.policies))
        return evaluate(cfg)

    monkeypatch.setattr(demo.evaluate_job, "run", record_evaluate)
    monkeypatch.setattr(deploy_job, "run", lambda cfg: deployed.append(cfg.policy) or dict(stand_ins))
    monkeypatch.setattr(demo, "shipped_bundles", lambda: ["adapter", "student", "teacher"])
    assert main(["demo", "--out", str(tmp_path / "with"), "--deploy-seconds", "1"]) == 0
    assert evaluated == [{"teacher": "teacher", "student": "student"}, {"student": "student", "adapter": "adapter"}]
    assert deployed == ["adapter"]
    report = (tmp_path / "with" / "README.md").read_text()
    assert "## Student vs student + tactile adapter" in report
    assert "## Deploy dry run (emulated Allegro over CAN; adapter)" in report
    monkeypatch.setattr(demo, "shipped_bundles", lambda: ["student", "teacher"])
    evaluated.clear()
    assert main(["demo", "--out", str(tmp_path / "without"), "--deploy-seconds", "1"]) == 0
    assert len(evaluated) == 1 and deployed == ["adapter", "student"]
