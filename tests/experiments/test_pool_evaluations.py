"""experiments/tools/pool_evaluations.py: evaluate reports on disjoint seed sets pooled into one, with paired gap
shares."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from envs.metrics import METRICS


@pytest.fixture(scope="module")
def pool(load_script):
    return load_script("pool_evaluations")


def _row(policy: str, ttf: float, drift: float, episodes: int, net: float = 0.4) -> dict:
    row = {"policy": policy, "condition": "friction_0.25", "friction_scale": 0.25, "added_mass": 0.0,
           "com_shift": [0.0, 0.0, 0.0], "episodes": episodes, "net_rotation_rate": net}
    for key in [*METRICS, "reward"]:
        row[key], row[key + "_std"] = 0.1, 0.01
    row["ttf"], row["ttf_std"], row["vertical_drift"] = ttf, 0.2, drift
    return row


def _report(path: Path, seed: int, episodes: int, rows: list[dict]) -> Path:
    path.mkdir(parents=True)
    (path / "results.json").write_text(json.dumps({"rows": rows, "config": {"seed": seed, "episodes": episodes}}))
    return path


def test_pools_disjoint_sets_and_shares_on_the_policys_own_episodes(pool, tmp_path, capsys):
    a = _report(tmp_path / "a", 100, 10, [_row("teacher", 0.8, 0.009, 10), _row("student", 0.4, 0.011, 10),
                                          _row("adapter", 0.6, 0.010, 10, net=0.2)])
    b = _report(tmp_path / "b", 200, 30, [_row("teacher", 0.9, 0.009, 30), _row("student", 0.7, 0.011, 30),
                                          _row("adapter", 0.8, 0.010, 30, net=0.6)])
    c = _report(tmp_path / "c", 200, 30, [_row("other", 0.9, 0.009, 30)])  # only on b's seeds
    out = tmp_path / "pooled"
    assert pool.main(["--results", str(a), str(b), str(c), "--reference", "teacher", "--baseline", "student",
                      "--out", str(out)]) == 0
    report = json.loads((out / "results.json").read_text())
    rows = {r["policy"]: r for r in report["rows"]}
    assert rows["student"]["episodes"] == 40
    assert rows["student"]["ttf"] == pytest.approx((10 * 0.4 + 30 * 0.7) / 40)
    spread = (10 * 0.225**2 + 30 * 0.075**2) / 40  # the sets' means around the pooled mean 0.625
    assert rows["student"]["ttf_std"] == pytest.approx(np.sqrt(0.2**2 + spread))
    # total rotation / total time in hand, each set's time in hand being ttf * episodes
    assert rows["adapter"]["net_rotation_rate"] == pytest.approx((0.2 * 6 + 0.6 * 24) / 30)
    shares = {s["policy"]: s for s in report["shares"]}
    assert shares["adapter"]["ttf"] == pytest.approx((0.75 - 0.625) / (0.875 - 0.625))
    assert shares["adapter"]["vertical_drift"] == pytest.approx(0.5)
    assert shares["other"]["episodes"] == 30  # against b's teacher and student only, not all 40 episodes
    assert shares["other"]["ttf"] == pytest.approx(1.0)
    assert "| friction_0.25 | adapter | 40 | 50% | 50% |" in (out / "results.md").read_text()
    assert (out / "plots" / "bars.png").read_bytes()[:4] == b"\x89PNG"
    picked = tmp_path / "picked"  # DIR=NAME,...: only those policies of that report
    assert pool.main(["--results", f"{a}=teacher,adapter", str(b), "--out", str(picked)]) == 0
    rows = {r["policy"]: r for r in json.loads((picked / "results.json").read_text())["rows"]}
    assert rows["adapter"]["episodes"] == 40 and rows["student"]["episodes"] == 30
    assert pool.main(["--results", f"{a}=oracle", "--out", str(tmp_path / "none")]) == 2
    assert "no rows for ['oracle']" in capsys.readouterr().err
    only = tmp_path / "only"
    assert pool.main(["--results", str(a), str(b), str(c), "--policies", "teacher", "other", "--out", str(only)]) == 0
    assert [r["policy"] for r in json.loads((only / "results.json").read_text())["rows"]] == ["teacher", "other"]
    relabelled = tmp_path / "relabelled"  # LABEL:NAME: c's `other` pooled with a's adapter, as adapter
    assert pool.main(["--results", f"{a}=teacher,student,adapter", f"{c}=adapter:other", "--out",
                      str(relabelled)]) == 0
    report = json.loads((relabelled / "results.json").read_text())
    rows = {r["policy"]: r for r in report["rows"]}
    assert set(rows) == {"teacher", "student", "adapter"}
    assert rows["adapter"]["episodes"] == 40 and rows["adapter"]["ttf"] == pytest.approx((10 * 0.6 + 30 * 0.9) / 40)
    assert "policies adapter (its other)" in (relabelled / "results.md").read_text()
    for bad in (f"{a}=x:teacher,x:student", f"{a}=x:", f"{a}=:"):
        assert pool.main(["--results", bad, "--out", str(tmp_path / "bad")]) == 2
        assert "LABEL:NAME" in capsys.readouterr().err


def test_paired_rates_compare_the_episodes_both_kept(pool, tmp_path):
    def episodes(row: dict, ttf: list[float], rotation: list[float]) -> dict:
        time = [20.0 * t for t in ttf]
        return {**row, "per_episode": {"ttf": ttf, "rotation_total": rotation, "in_hand_time": time,
                                       "vertical_drift": [0.01] * len(ttf)}}

    teacher = _row("teacher", 1.0, 0.009, 4)
    # episode 0: both keep it (student 10 rad, adapter 9 rad); 1: the student drops it; 2: both keep it (12, 12);
    # 3: the adapter drops it. On the two both kept, the adapter turns 21 rad against the student's 22 in 40 s.
    student = episodes(_row("student", 0.75, 0.011, 4), [1.0, 0.25, 1.0, 1.0], [10.0, 2.0, 12.0, 11.0])
    adapter = episodes(_row("adapter", 0.75, 0.010, 4), [1.0, 1.0, 1.0, 0.5], [9.0, 4.0, 12.0, 5.0])
    old = _row("adapter", 0.5, 0.010, 8)  # a report from before per-episode values: left out of the pairing
    a = _report(tmp_path / "a", 100, 4, [teacher, student, adapter])
    b = _report(tmp_path / "b", 200, 8, [_row("teacher", 0.9, 0.009, 8), _row("student", 0.5, 0.011, 8), old])
    out = tmp_path / "pooled"
    assert pool.main(["--results", str(a), str(b), "--reference", "teacher", "--baseline", "student",
                      "--out", str(out)]) == 0
    paired = {p["policy"]: p for p in json.loads((out / "results.json").read_text())["paired_rates"]}
    assert set(paired) == {"adapter"}  # the teacher's row keeps no per-episode values
    assert paired["adapter"]["episodes"] == 4 and paired["adapter"]["kept_by_both"] == 2
    assert paired["adapter"]["net_rotation_rate"] == pytest.approx(21.0 / 40.0)
    assert paired["adapter"]["baseline_net_rotation_rate"] == pytest.approx(22.0 / 40.0)
    assert paired["adapter"]["change"] == pytest.approx(21.0 / 22.0 - 1.0)
    assert "| friction_0.25 | adapter | 4 | 2 | 0.525 | 0.550 | -4.5% |" in (out / "results.md").read_text()


def test_paired_against_differences_episode_by_episode(pool, tmp_path, capsys):
    def episodes(row: dict, ttf: list[float], drift: list[float]) -> dict:
        return {**row, "per_episode": {"ttf": ttf, "rotation_total": [1.0] * len(ttf),
                                       "in_hand_time": [20.0 * t for t in ttf], "vertical_drift": drift}}

    # the candidate's rows come from another report on the same seeds, as when it is evaluated alone later
    a = _report(tmp_path / "a", 100, 4, [episodes(_row("adapter", 0.5, 0.010, 4), [0.5, 0.5, 0.5, 0.5],
                                                   [0.010, 0.010, 0.010, 0.010])])
    b = _report(tmp_path / "b", 100, 4, [episodes(_row("candidate", 0.6, 0.010, 4), [0.5, 0.6, 0.7, 0.6],
                                                   [0.011, 0.010, 0.010, 0.010])])
    c = _report(tmp_path / "c", 300, 4, [_row("candidate", 0.9, 0.010, 4)])  # no per-episode values: left out
    out = tmp_path / "pooled"
    assert pool.main(["--results", str(a), str(b), str(c), "--paired-against", "adapter", "--out", str(out)]) == 0
    (entry,) = json.loads((out / "results.json").read_text())["paired_differences"]
    assert entry["policy"] == "candidate" and entry["episodes"] == 4
    d = np.array([0.0, 0.1, 0.2, 0.1])
    assert entry["ttf"] == pytest.approx(0.1)
    assert entry["ttf_se"] == pytest.approx(d.std(ddof=1) / 2.0)
    assert entry["vertical_drift"] == pytest.approx(0.00025)
    assert "| friction_0.25 | candidate | 4 | +0.100 ± 0.041 | +0.25 ± 0.25 |" in (out / "results.md").read_text()
    assert pool.main(["--results", str(a), "--paired-against", "oracle", "--out", str(tmp_path / "o")]) == 2
    assert "no such policy" in capsys.readouterr().err
    assert not (tmp_path / "o").exists()


def test_gap_shares_carry_a_bootstrap_standard_error_over_the_same_episodes(pool, tmp_path):
    """The share's standard error resamples each set's episodes, the same ones for the three policies: a policy
    exactly half-way between student and teacher on every episode has a share of 50% with no spread whatever the
    episodes' own spread; noisy episodes give the delta method's error to within the resampling noise."""
    rng = np.random.default_rng(1)

    def set_of(path: Path, seed: int, n: int, lift_noise: float) -> Path:
        student = rng.uniform(0.0, 0.6, n)
        teacher = np.clip(student + rng.uniform(0.1, 0.5, n), 0, 1)
        adapter = student + 0.5 * (teacher - student) + lift_noise * rng.standard_normal(n)
        rows = []
        for name, ttf in (("teacher", teacher), ("student", student), ("adapter", adapter)):
            per = {"ttf": ttf.tolist(), "rotation_total": [1.0] * n, "in_hand_time": (20.0 * ttf).tolist(),
                   "vertical_drift": [0.01] * n}
            rows.append({**_row(name, float(ttf.mean()), 0.01, n), "per_episode": per})
        return _report(path, seed, n, rows)

    exact = [set_of(tmp_path / f"e{k}", 1000 * k, 64, 0.0) for k in (1, 2)]
    assert pool.main(["--results", *map(str, exact), "--reference", "teacher", "--baseline", "student",
                      "--out", str(tmp_path / "exact")]) == 0
    (share,) = json.loads((tmp_path / "exact" / "results.json").read_text())["shares"]
    assert share["ttf"] == pytest.approx(0.5) and share["ttf_se"] == pytest.approx(0.0, abs=1e-9)
    assert share["vertical_drift"] is None and share["vertical_drift_se"] is None  # no drift gap: no share
    assert "| friction_0.25 | adapter | 128 | 50% ± 0 | - |" in (tmp_path / "exact" / "results.md").read_text()

    noisy = [set_of(tmp_path / f"n{k}", 1000 * k, 200, 0.3) for k in (1, 2)]
    assert pool.main(["--results", *map(str, noisy), "--reference", "teacher", "--baseline", "student",
                      "--out", str(tmp_path / "noisy")]) == 0
    (share,) = json.loads((tmp_path / "noisy" / "results.json").read_text())["shares"]
    per = [json.loads((d / "results.json").read_text())["rows"] for d in noisy]
    values = {name: np.concatenate([np.asarray(r["per_episode"]["ttf"]) for rows in per for r in rows
                                    if r["policy"] == name]) for name in ("teacher", "student", "adapter")}
    lift, gap = values["adapter"] - values["student"], values["teacher"] - values["student"]
    ratio = lift.mean() / gap.mean()
    delta = np.std(lift - ratio * gap, ddof=1) / np.sqrt(len(gap)) / gap.mean()  # first-order error of a ratio
    assert share["ttf"] == pytest.approx(ratio)
    assert 0.8 * delta < share["ttf_se"] < 1.2 * delta, (share["ttf_se"], delta)


def test_refuses_overlapping_seeds_and_bad_input(pool, tmp_path, capsys):
    a = _report(tmp_path / "a", 100, 10, [_row("student", 0.4, 0.011, 10)])
    b = _report(tmp_path / "b", 105, 10, [_row("student", 0.5, 0.011, 10)])
    assert pool.main(["--results", str(a), str(b), "--out", str(tmp_path / "o1")]) == 2
    assert "count twice" in capsys.readouterr().err
    assert pool.main(["--results", str(tmp_path), "--out", str(tmp_path / "o2")]) == 2
    assert "no results.json" in capsys.readouterr().err
    assert pool.main(["--results", str(a), "--reference", "teacher", "--out", str(tmp_path / "o3")]) == 2
    assert "together" in capsys.readouterr().err
    assert pool.main(["--results", str(a), "--reference", "teacher", "--baseline", "student",
                      "--out", str(tmp_path / "o4")]) == 2
    assert "no policy 'teacher'" in capsys.readouterr().err
    assert not any((tmp_path / f"o{i}").exists() for i in range(1, 5))


def test_a_policy_missing_from_a_condition_has_no_bar_there(pool, tmp_path):
    nominal = {**_row("teacher", 0.9, 0.009, 8), "condition": "nominal", "friction_scale": 1.0}
    a = _report(tmp_path / "a", 100, 8, [nominal, _row("teacher", 0.8, 0.009, 8)])
    b = _report(tmp_path / "b", 100, 8, [_row("oracle", 0.7, 0.009, 8)])  # run on friction x0.25 only
    assert pool.main(["--results", str(a), str(b), "--out", str(tmp_path / "out")]) == 0
    assert (tmp_path / "out" / "plots" / "bars.png").read_bytes()[:4] == b"\x89PNG"
