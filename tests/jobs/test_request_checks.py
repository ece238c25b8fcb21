"""Requests are checked before anything is written, and outputs are named as written (issue "Nothing written before
the request is checked"): the cases found by trying the commands as a user would."""

from __future__ import annotations

import pytest

from rotation.cli import main
from rotation.jobs import demo


def test_evaluate_refuses_an_unreadable_grasp_cache_before_its_folder_exists(tmp_path, capsys):
    bad = tmp_path / "bad.npz"
    bad.write_text("not a grasp cache")
    out = tmp_path / "ev1"
    code = main(["evaluate", "--policy", "student", "--grasp-cache", str(bad), "--out", str(out), "--episodes", "1",
                 "--conditions", "nominal", "--no-progress"])
    assert code == 2 and "is not a readable .npz file" in capsys.readouterr().err
    assert not out.exists()  # so the corrected command is not refused as 'another evaluation'


def test_inspect_tactile_refuses_an_output_name_it_would_not_write(tmp_path, capsys):
    session = tmp_path / "s.h5"
    session.write_bytes(b"")
    code = main(["inspect-tactile", str(session), "--out", str(tmp_path / "noext")])
    err = capsys.readouterr().err
    assert code == 2 and "out: " in err and "must end in .png" in err
    assert sorted(p.name for p in tmp_path.iterdir()) == ["s.h5"]


def test_demo_takes_the_none_its_help_documents(capsys):
    with pytest.raises(SystemExit):
        main(["demo", "--help"])
    assert "`none` skips it" in " ".join(capsys.readouterr().out.split())
    assert demo.Config(adapter_conditions=("none",)).adapter_suite == ()
    assert demo.Config().adapter_suite == demo.Config().adapter_conditions
