"""scripts/plot_training.py: one history from curves.jsonl files, and runs overlaid with --compare."""

from __future__ import annotations

import csv
import json
from pathlib import Path

import pytest


@pytest.fixture(scope="module")
def plot(load_script):
    return load_script("plot_training")


def _curves(path: Path, steps: list[int], ttf: float) -> Path:
    path.write_text("".join(json.dumps({"steps": s, "ttf": ttf + 0.01 * i, "l": 100 + i}) + "\n"
                            for i, s in enumerate(steps)))
    return path


def test_curves_files_continue_each_others_steps(plot, tmp_path):
    a = _curves(tmp_path / "a.jsonl", [10, 20], 0.5)
    b = _curves(tmp_path / "b.jsonl", [5, 15], 0.7)
    series = plot.read_curves((a, b), ("ttf", "l", "absent"))
    assert set(series) == {"ttf", "l"}
    assert series["ttf"][0].tolist() == [10, 20, 25, 35]
    assert series["ttf"][1].tolist() == pytest.approx([0.5, 0.51, 0.7, 0.71])


def test_compare_writes_one_line_per_run_and_a_run_column(plot, tmp_path):
    a = _curves(tmp_path / "a.jsonl", list(range(0, 300, 10)), 0.4)
    b = _curves(tmp_path / "b.jsonl", list(range(0, 200, 10)), 0.8)
    out = tmp_path / "out"
    assert plot.main(["--compare", f"overlap={a}", f"no-overlap={b}", "--tags", "ttf", "l", "--out", str(out),
                      "--name", "compare", "--smooth", "5"]) == 0
    assert (out / "compare.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    rows = list(csv.DictReader((out / "compare.csv").open()))
    assert {r["run"] for r in rows} == {"overlap", "no-overlap"}
    b_ttf = [float(r["value"]) for r in rows if r["run"] == "no-overlap" and r["tag"] == "ttf"]
    assert len(b_ttf) == 20 and b_ttf[0] == pytest.approx(0.8)
    assert not (out / "curves.png").exists()  # --name chose the stem


def test_a_curve_too_short_to_smooth_is_drawn_as_the_curve(plot, tmp_path, monkeypatch):
    figures = []
    monkeypatch.setattr(plot.plt, "close", figures.append)  # keep the figure to look at it
    a = _curves(tmp_path / "a.jsonl", [10, 20, 30], 0.5)
    assert plot.main(["--curves", str(a), "--tags", "ttf", "--out", str(tmp_path / "out"), "--smooth", "25"]) == 0
    (line,) = figures[0].axes[0].get_lines()  # one solid line, not a faint raw line without its smoothed one
    assert line.get_ydata().tolist() == pytest.approx([0.5, 0.51, 0.52])
    assert line.get_color() == "C0" and line.get_alpha() is None


@pytest.mark.parametrize("entries, message", [
    (["just-a-path.jsonl"], "NAME=curves.jsonl"),
    (["a=x.jsonl", "a=y.jsonl"], "twice"),
])
def test_compare_rejects_malformed_entries(plot, entries, message):
    with pytest.raises(ValueError, match=message):
        plot.parse_compare(tuple(entries))


def test_compare_names_the_run_missing_a_tag(plot, tmp_path):
    a = _curves(tmp_path / "a.jsonl", [10, 20], 0.5)
    with pytest.raises(ValueError, match="'first'"):
        plot.run(plot.Config(compare=(f"first={a}",), tags=("ttf", "upright"), out=tmp_path / "o"))
    with pytest.raises(ValueError, match="no such curves file"):
        plot.run(plot.Config(compare=(f"gone={tmp_path / 'missing.jsonl'}",), tags=("ttf",), out=tmp_path / "o"))


def test_bad_input_is_one_line_and_status_2(plot, tmp_path, capsys):
    assert plot.main(["--compare", "no-equals-sign", "--out", str(tmp_path)]) == 2
    err = capsys.readouterr().err
    assert ": error: --compare entries are NAME=curves.jsonl" in err and "Traceback" not in err
