"""rotation.runs.CurveLog: JSON rows appended a line each; a line cut short by a stop is skipped on reading and does
not swallow the next row appended."""

import json

from rotation.runs import CurveLog


def test_a_row_appended_after_a_cut_line_is_read_back(tmp_path):
    path = tmp_path / "curves.jsonl"
    path.write_text(json.dumps({"steps": 1}) + "\n" + '{"steps": 2, "lo')  # the stop cut the second row
    log = CurveLog(path)
    assert log.rows() == [{"steps": 1}]
    log.append([{"steps": 3}, {"steps": 4}])
    assert log.rows() == [{"steps": 1}, {"steps": 3}, {"steps": 4}]
    log.append([{"steps": 5}])  # a whole last line: nothing added before the row
    assert path.read_text().count("\n") == 5 and log.rows()[-1] == {"steps": 5}
