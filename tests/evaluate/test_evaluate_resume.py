"""An interrupted `rotate evaluate` keeps every condition it finished, continues with the rest, and never mixes the
rows of two different evaluations (other settings, or retrained weights) in one report."""

from __future__ import annotations

import json
import os
import signal

import pytest
import torch

from envs.errors import RequestRefused
from envs.grasp_cache import cache_digest
from envs.sim_identity import LEGACY_HAND
from rotation.cli import main
from rotation.evaluate import finished, job
from rotation.policy.bundle import PolicyBundle
from rotation.policy.bundle_config import BundleConfig

CONDITIONS = ("nominal", "friction_0.5")


@pytest.fixture(scope="module")
def bundles(tmp_path_factory):
    root = tmp_path_factory.mktemp("evaluate_resume")
    torch.manual_seed(0)
    teacher = PolicyBundle(BundleConfig())
    teacher.save(root / "teacher")
    teacher.to_student().save(root / "student")
    return root


def make_cfg(root, out, **kw) -> job.Config:
    base = dict(policies={"teacher": str(root / "teacher"), "student": str(root / "student")}, suite="perturbations",
                conditions=CONDITIONS, episodes=2, episode_steps=6, out=out, num_envs=2, nthread=1, progress=False)
    return job.Config(**{**base, **kw})


def cli_args(root, out) -> list[str]:
    return ["evaluate", "--policy", f"teacher={root / 'teacher'}", "--policy", f"student={root / 'student'}",
            "--suite", "perturbations", "--conditions", *CONDITIONS, "--episodes", "2", "--episode-steps", "6",
            "--num-envs", "2", "--nthread", "1", "--out", str(out), "--no-progress"]


class Calls:
    """Counts run_episodes calls (one per policy and condition); ``stop_at`` interrupts that call."""

    def __init__(self, monkeypatch, stop_at: int | None = None, stop=None):
        self.n, self.stop_at, self.stop = 0, stop_at, stop
        self.real = job.run_episodes
        monkeypatch.setattr(job, "run_episodes", self)

    def __call__(self, *args, **kwargs):
        self.n += 1
        if self.n == self.stop_at:
            self.stop()
        return self.real(*args, **kwargs)


def ctrl_c():
    raise KeyboardInterrupt


@pytest.fixture(scope="module")
def reference(bundles, tmp_path_factory):
    """The rows of an uninterrupted run."""
    return job.run(make_cfg(bundles, tmp_path_factory.mktemp("reference") / "eval"))


def test_interrupted_evaluate_keeps_finished_conditions_and_resumes(bundles, tmp_path, monkeypatch, reference):
    out = tmp_path / "eval"
    Calls(monkeypatch, stop_at=3, stop=ctrl_c)  # the first call of the second condition
    with pytest.raises(KeyboardInterrupt) as stopped:
        job.run(make_cfg(bundles, out))
    assert stopped.value.exit_code == 130 and "1 of 2 conditions are kept" in str(stopped.value)
    kept = json.loads((out / "conditions" / "nominal.json").read_text())
    assert [r["policy"] for r in kept["rows"]] == ["teacher", "student"] and kept["rows"] == reference[:2]
    assert not (out / "conditions" / "friction_0.5.json").exists() and not (out / "results.json").exists()

    calls = Calls(monkeypatch)
    rows = job.run(make_cfg(bundles, out, resume=True))
    assert calls.n == 2  # only the remaining condition ran, for both policies
    assert rows == reference  # and the report is the one an uninterrupted run writes
    assert json.loads((out / "results.json").read_text())["rows"] == reference
    again = Calls(monkeypatch)
    assert job.run(make_cfg(bundles, out)) == reference and again.n == 0  # the same command: nothing left to run


def test_sigterm_exits_143_and_keeps_finished_conditions(bundles, tmp_path, monkeypatch, capsys):
    out = tmp_path / "eval"
    Calls(monkeypatch, stop_at=3, stop=lambda: os.kill(os.getpid(), signal.SIGTERM))
    before = signal.getsignal(signal.SIGTERM)
    assert main(cli_args(bundles, out)) == 143
    assert signal.getsignal(signal.SIGTERM) == before  # the handler is put back
    assert (out / "conditions" / "nominal.json").is_file()
    captured = capsys.readouterr()
    assert "stopped by SIGTERM" in captured.out and "Traceback" not in captured.err
    Calls(monkeypatch, stop_at=1, stop=ctrl_c)
    assert main([*cli_args(bundles, out), "--resume"]) == 130  # Ctrl-C while continuing: 130, still kept
    assert (out / "conditions" / "nominal.json").is_file()


def test_other_settings_are_refused_with_the_differences(bundles, tmp_path, monkeypatch):
    out = tmp_path / "eval"
    Calls(monkeypatch, stop_at=3, stop=ctrl_c)
    with pytest.raises(KeyboardInterrupt):
        job.run(make_cfg(bundles, out))
    with pytest.raises(ValueError, match=r"other settings \(episodes: 2 -> 3\).*use another --out"):
        job.run(make_cfg(bundles, out, episodes=3, resume=True))
    with pytest.raises(ValueError, match=r"seed: 0 -> 1"):
        job.run(make_cfg(bundles, out, seed=1))  # without --resume too: the kept rows are never mixed or replaced
    torch.manual_seed(1)
    PolicyBundle(BundleConfig()).save(bundles / "retrained")
    retrained = {"teacher": str(bundles / "retrained"), "student": str(bundles / "student")}
    with pytest.raises(ValueError, match="the weights of policy 'teacher'"):
        job.run(make_cfg(bundles, out, policies=retrained))
    assert (out / "conditions" / "nominal.json").is_file()  # nothing was touched


def test_a_regenerated_grasp_cache_is_another_evaluation(bundles, tmp_path, monkeypatch):
    """Episodes start from the grasp cache: one regenerated at the same path must not continue the old rows."""
    from envs.grasp_cache import GraspCache, load_default_cache

    shipped = load_default_cache("cup", hand=LEGACY_HAND)  # the hand of the bundles, which record no sim
    cache = tmp_path / "grasps_cup.npz"
    shipped.save(cache)
    out = tmp_path / "eval"
    Calls(monkeypatch, stop_at=3, stop=ctrl_c)
    cfg = make_cfg(bundles, out, grasp_cache=str(cache))
    with pytest.raises(KeyboardInterrupt):
        job.run(cfg)
    assert json.loads((out / "progress.json").read_text())["grasps"]["cache"] == cache_digest(cfg.grasp_cache,
                                                                                               cfg.object)
    GraspCache("cup", shipped.scales, shipped.grasps[:, ::-1], seed=1, hand=shipped.hand).save(cache)
    with pytest.raises(ValueError, match=r"other settings \(the grasp cache: '[0-9a-f]{16}' -> '[0-9a-f]{16}'\)"):
        job.run(make_cfg(bundles, out, grasp_cache=str(cache), resume=True))
    assert (out / "conditions" / "nominal.json").is_file()  # nothing was touched


def test_resume_needs_something_to_continue_and_old_reports_are_not_overwritten(bundles, tmp_path):
    with pytest.raises(ValueError, match="--resume: .* holds no evaluation to continue"):
        job.run(make_cfg(bundles, tmp_path / "empty", resume=True))
    old = tmp_path / "old"
    old.mkdir()
    (old / "results.json").write_text('{"rows": []}')  # a report of an earlier version, without progress.json
    with pytest.raises(ValueError, match="holds the report of an earlier evaluation"):
        job.run(make_cfg(bundles, old))
    assert (old / "results.json").read_text() == '{"rows": []}'


def test_changes_that_do_not_alter_results_may_differ(bundles, tmp_path, monkeypatch):
    out = tmp_path / "eval"
    Calls(monkeypatch, stop_at=3, stop=ctrl_c)
    with pytest.raises(KeyboardInterrupt):
        job.run(make_cfg(bundles, out))
    assert {"out", "progress", "nthread", "resume"} <= finished.RESUMABLE_CHANGES
    calls = Calls(monkeypatch)
    job.run(make_cfg(bundles, out, nthread=2, progress=True, resume=True))
    assert calls.n == 2


def test_a_condition_file_this_evaluation_did_not_write_is_refused_and_left_alone(bundles, tmp_path, monkeypatch):
    """A continued evaluation keeps a finished condition only if the file carries this evaluation's identity digest:
    another evaluation's condition copied in (same policies, other seed), or a forged one, is refused in one line
    naming it, and nothing is written."""
    other, out = tmp_path / "other", tmp_path / "eval"
    job.run(make_cfg(bundles, other, seed=7))
    Calls(monkeypatch, stop_at=3, stop=ctrl_c)
    with pytest.raises(KeyboardInterrupt):
        job.run(make_cfg(bundles, out))  # nominal finished, friction_0.5 not
    foreign = (other / "conditions" / "friction_0.5.json").read_bytes()
    (out / "conditions" / "friction_0.5.json").write_bytes(foreign)
    before = {p: p.read_bytes() for p in out.rglob("*") if p.is_file()}
    with pytest.raises(RequestRefused, match=r"friction_0\.5\.json is not a condition this evaluation wrote.*move it"):
        job.run(make_cfg(bundles, out, resume=True))
    assert {p: p.read_bytes() for p in out.rglob("*") if p.is_file()} == before
    forged = json.loads(foreign)
    forged["identity_sha256"] = "0" * 64
    (out / "conditions" / "friction_0.5.json").write_text(json.dumps(forged))
    with pytest.raises(RequestRefused, match="not a condition this evaluation wrote"):
        job.run(make_cfg(bundles, out, resume=True))
    (out / "conditions" / "friction_0.5.json").unlink()  # moved away: the evaluation continues
    rows = job.run(make_cfg(bundles, out, resume=True))
    assert [r["condition"] for r in rows] == ["nominal", "nominal", "friction_0.5", "friction_0.5"]
