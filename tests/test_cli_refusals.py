"""A request that is well formed but cannot be done ends with one line and status 1, never a traceback, and leaves
the file system as it found it (envs.errors; rotation.cli's exit statuses).

One row per `rotate` subcommand: a request each job must refuse (no grasp fits, nothing to resume, no session to
read, a bundle that names a missing encoder, an output that already holds a bundle, a hand that does not answer).
The command runs in-process in an empty working directory (so an output written to a default path would show);
the test checks the status, that the last line on stderr is the job's one-line refusal, that no traceback was
printed, and that no file under the working directory was created or changed. `--debug` shows the traceback.
"""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import h5py
import pytest

from rotation import cli
from rotation.policy import bundle as policy_bundle


def _member(root: Path) -> str:
    """A fresh pressure-only adapter of the shipped student (built once per working directory)."""
    from adapters.bundle import build_adapted

    path = root / "member"
    if not path.is_dir():
        build_adapted("student", "sparshx-tinier-sim", ("pressure",)).save(path)
    return str(path)


def _adapter_with_a_missing_encoder(root: Path) -> str:
    out = root / "adapter_missing_encoder"
    shutil.copytree(_member(root), out)
    cfg = json.loads((out / "config.json").read_text())
    cfg["encoder"] = "no-such-encoder"
    (out / "config.json").write_text(json.dumps(cfg))
    return str(out)


def _not_a_tty(root: Path) -> str:
    path = root / "not_a_tty"
    path.write_text("not a serial port")
    return str(path)


def _not_a_session(root: Path) -> str:
    path = root / "not_a_session.h5"
    with h5py.File(path, "w") as f:
        f["x"] = [1, 2, 3]
    return str(path)


def _bundle_already_there(root: Path) -> str:
    out = root / "ensemble"
    out.mkdir()
    (out / "config.json").write_text("{}")
    return str(out)


def _other_collection(root: Path) -> str:
    out = root / "collection"
    (out / "shard_0").mkdir(parents=True)
    (out / "shard_0" / "episode_000000.h5").write_bytes(b"kept")
    (out / "collect.json").write_text(json.dumps({"settings": {"seed": 12345}}))
    return str(out)


def _not_a_demo(root: Path) -> str:
    """An output folder whose first episode's path holds a file that is not a session."""
    out = root / "demos"
    (out / "shard_000").mkdir(parents=True)
    (out / "shard_000" / "episode_000000.h5").write_text("my notes")
    return str(out)


ROWS = {
    # command: argv builder (root -> argv), the words the refusal must contain
    "grasps": (lambda r: ["grasps", "--objects", "cup", "--scales", "3.0", "--per-scale", "1", "--batch-size", "1",
                          "--out", str(r / "g")], "grasps accepted"),
    "view": (lambda r: ["view", "--policy", _adapter_with_a_missing_encoder(r), "--out", str(r / "v.mp4")],
             "cannot be found"),
    "train-teacher": (lambda r: ["train-teacher", "--resume", str(r / "none" / "checkpoints" / "last.zip")],
                      "no such checkpoint"),
    "train-student": (lambda r: ["train-student", "--resume", "--out", str(r)], "no checkpoint"),
    "finetune-student": (lambda r: ["finetune-student", "--resume", str(r / "none.zip")], "no such checkpoint"),
    "evaluate": (lambda r: ["evaluate", "--resume", "--out", str(r), "--episodes", "1"], "no evaluation to continue"),
    "demo": (lambda r: ["demo", "--out", str(r / "demo")], "ships no teacher"),
    "hand-info": (lambda r: ["hand-info", "--hand", "allegro", "--can", "virtual:nobody-answers"], "no reply"),
    "collect": (lambda r: ["collect", "--out", _other_collection(r), "--episodes", "1"], "other settings"),
    "demos": (lambda r: ["demos", "--out", _not_a_demo(r), "--episodes", "1"], "not a demonstration of this run"),
    "inspect-touch": (lambda r: ["inspect-touch", _not_a_session(r), "--out", str(r / "i.png")],
                        "not a session file"),
    "deploy": (lambda r: ["deploy", "--hand", "sim-allegro", "--policy", _adapter_with_a_missing_encoder(r),
                          "--duration", "1"], "cannot be found"),
    "record": (lambda r: ["record", "--hand", "allegro", "--policy", "student", "--record", str(r / "s.h5"),
                          "--no-ask", "--digit360", "a,b,c,d"], "would lack the object's"),
    "touch-info": (lambda r: ["touch-info", "--digit360", _not_a_tty(r), "--seconds", "0.2"],
                   "did not open as a serial port"),
    "rehearse": (lambda r: ["rehearse", "--policy", _adapter_with_a_missing_encoder(r), "--out", str(r / "reh")],
                 "cannot be found"),
    "encoder-info": (lambda r: ["encoder-info", "--checkpoint", _not_a_session(r)], "not a readable torch checkpoint"),
    "cache-touch": (lambda r: ["cache-touch", "--sessions", str(r), "--out", str(r / "cache")], "no session files"),
    "pretrain": (lambda r: ["pretrain", "--sessions", str(r), "--out", str(r / "pretrain")], "no session files"),
    "probe": (lambda r: ["probe", "--checkpoint", "sparshx-tinier-sim", "--sessions", str(r), "--out",
                         str(r / "probe")], "no session files"),
    "touch-report": (lambda r: ["touch-report", "--sessions", str(r), "--stages", "1", "--out", str(r / "report")],
                     "no session files"),
    "train-il": (lambda r: ["train-il", "--demos", str(r), "--out", str(r / "il")], "no demonstration sessions"),
    "finetune-adapter": (lambda r: ["finetune-adapter", "--sessions", str(r), "--out", str(r / "adapter")],
                         "no .h5 session files"),
    "ensemble-adapters": (lambda r: ["ensemble-adapters", "--members", _member(r), _member(r), "--out",
                                     _bundle_already_there(r)], "already holds a bundle"),
}


def _tree(root: Path) -> dict[str, tuple[int, int]]:
    return {str(p.relative_to(root)): (p.stat().st_size, p.stat().st_mtime_ns) for p in sorted(root.rglob("*"))}


def test_every_subcommand_has_a_row():
    assert set(ROWS) == set(cli.COMMANDS)


@pytest.mark.parametrize("command", sorted(ROWS))
def test_an_impossible_request_is_one_line_status_1_and_writes_nothing(command, tmp_path, monkeypatch, capsys):
    root = tmp_path / "work"
    root.mkdir()
    monkeypatch.chdir(root)
    if command == "demo":  # an installation without its shipped policies
        empty = tmp_path / "no_policies"
        empty.mkdir()
        monkeypatch.setattr(policy_bundle, "SHIPPED_DIR", empty)
    build, words = ROWS[command]
    argv = build(root)
    before = _tree(root)
    code = cli.main(argv)
    err = capsys.readouterr().err
    lines = [line for line in err.replace("\r", "\n").splitlines() if line.strip()]
    assert code == 1, err
    assert "Traceback" not in err, err
    assert lines[-1].startswith(f"rotate {command}: ") and words in lines[-1], lines[-1]
    assert sum(line.startswith(f"rotate {command}:") for line in lines) == 1, err
    assert _tree(root) == before, "the refused request changed the files under its working directory"


def test_debug_shows_the_traceback(tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    with pytest.raises(ValueError, match="no session files"):
        cli.main(["cache-touch", "--sessions", str(tmp_path), "--out", str(tmp_path / "cache"), "--debug"])
    monkeypatch.setenv("ROTATE_DEBUG", "1")
    with pytest.raises(ValueError, match="no session files"):
        cli.main(["cache-touch", "--sessions", str(tmp_path), "--out", str(tmp_path / "cache")])


def test_a_bad_option_is_still_status_2(capsys):
    assert cli.main(["grasps", "--per-scale", "0"]) == 2
    assert capsys.readouterr().err.strip().startswith("rotate grasps: error: ")
