"""Pool several `rotate evaluate` reports over disjoint seed sets into one table, with the gap each policy closes.

Evaluations made on different seed sets (say 128 episodes on seeds 800000+ and 128 on 1300000+) measure the same
thing on more episodes. This pools them per (policy, condition): episode-weighted means, standard deviations over
all episodes, and the net rotation rate as total rotation over total time in hand. With --reference and --baseline
it adds, for every other policy, the share of the baseline's gap to the reference that it closes, (policy -
baseline) / (reference - baseline), for ttf and vertical drift: how the tactile adapter's targets are stated; where
every set keeps per-episode values, with a bootstrap standard error (each set's episodes resampled, the same
episodes for the three policies; half the central 68% interval, as a ratio's resamples can be wild). It also
compares each policy's rotation rate with the baseline's episode by episode: the net rate over the episodes that
both kept in hand to the end (reports whose rows keep per-episode values). A policy that saves cups the baseline
drops spends that extra time on hard cups, which lowers its net rate over all episodes; on the cups both kept, a
lower rate means it really turns the cup slower. With --paired-against NAME it adds, for every other policy, its
per-episode difference to NAME in ttf and vertical drift, with the standard error of the mean difference: two
policies judged on the same episodes differ by far less noise than their separate means suggest (one seed set of 128
episodes moves a gap share by 10-30 points, the paired difference much less).

    python experiments/tools/pool_evaluations.py --results runs/eval_seeds_800000 \\
        runs/eval_seeds_1300000 --reference teacher --baseline student --out runs/pooled

Writes results.json (pooled rows, as evaluate's), results.md (table, shares, the seed sets) and plots/bars.png. A
policy evaluated twice on overlapping seeds is refused: the episodes would count twice.
"""

from __future__ import annotations

import json
from collections import defaultdict
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from envs.config import Perturbation
from envs.metrics import METRICS
from rotation.configs import script_main
from rotation.evaluate.report import markdown_table, plot_bars
from rotation.evaluate.suites import make_condition

SHARE_METRICS = {"ttf": "higher", "vertical_drift": "lower"}
"""Metrics whose gap shares are reported, and which direction is better."""


@dataclass
class Config:
    results: tuple[Path, ...] = ()
    """Evaluation report directories (each with results.json), on disjoint seed sets; DIR=NAME[,NAME...] takes only
    those policies from that report (say, one whose other rows belong to another adapter under the same label), and
    LABEL:NAME among them pools that report's NAME rows as LABEL (one policy evaluated under another label there)."""
    out: Path = Path("runs/pooled")
    """Output directory (refused if it already holds a pooled report)."""
    reference: str = ""
    """Policy whose level is the goal (e.g. teacher); with --baseline, adds the gap-share table."""
    baseline: str = ""
    """Policy whose gap to the reference is measured (e.g. student)."""
    policies: tuple[str, ...] = ()
    """Pool only these policies (default: every policy in the reports)."""
    paired_against: str = ""
    """Policy to compare every other one with episode by episode (e.g. the shipped adapter against a candidate):
    mean per-episode difference in ttf and vertical drift and its standard error, on the seed sets where both rows
    keep per-episode values."""


def _source(entry: Path) -> tuple[Path, dict[str, str] | None]:
    """A --results entry: the report directory, and the policies to take from it, each with the label it is pooled
    under (None = all, as labelled)."""
    text = str(entry)
    if "=" in text and not entry.exists():
        directory, _, names = text.rpartition("=")
        chosen = {}
        for item in filter(None, names.split(",")):
            label, _, name = item.rpartition(":")
            chosen[name] = label or name
        if not directory or not chosen or not all(chosen) or len(set(chosen.values())) < len(chosen):
            raise ValueError(f"--results {text!r}: expected DIR or DIR=NAME[,NAME...], a NAME as LABEL:NAME to pool "
                             "it under another label (each label once)")
        return Path(directory), chosen
    return entry, None


def _read(path: Path) -> tuple[list[dict[str, Any]], range]:
    file = path / "results.json"
    if not file.is_file():
        raise ValueError(f"{path} has no results.json (give directories written by `rotate evaluate`)")
    try:
        report = json.loads(file.read_text())
        rows, config = report["rows"], report["config"]
        return rows, range(int(config["seed"]), int(config["seed"]) + int(config["episodes"]))
    except (json.JSONDecodeError, KeyError, TypeError) as err:
        raise ValueError(f"{file} is not an evaluation report: {err}") from err


def pool_rows(rows: list[dict[str, Any]]) -> dict[str, Any]:
    """One row from rows of the same (policy, condition) on disjoint episodes."""
    n = np.array([r["episodes"] for r in rows], dtype=np.float64)
    pooled = {k: rows[0][k] for k in ("policy", "condition", "friction_scale", "added_mass", "com_shift")}
    pooled["episodes"] = int(n.sum())
    for key in [*METRICS, "reward"]:
        means = np.array([r[key] for r in rows])
        stds = np.array([r[key + "_std"] for r in rows])
        mean = float((n * means).sum() / n.sum())
        pooled[key] = mean
        pooled[key + "_std"] = float(np.sqrt((n * (stds**2 + (means - mean) ** 2)).sum() / n.sum()))
    # net rate = total rotation / total time in hand, and a set's time in hand is proportional to its ttf * episodes
    time = np.array([r["ttf"] for r in rows]) * n
    rate = np.array([r["net_rotation_rate"] for r in rows])
    pooled["net_rotation_rate"] = float((rate * time).sum() / time.sum()) if time.sum() > 0 else 0.0
    return pooled


def gap_shares(groups: dict[tuple[str, str], list[tuple[range, dict[str, Any], Path]]], reference: str,
               baseline: str) -> list[dict[str, Any]]:
    """Per condition and other policy: the share of the baseline's gap to the reference it closes, on the policy's
    own episodes (the reference and baseline pooled over the same seed sets; a policy whose seed sets they do not
    both cover is left out). None where the baseline is already as good as the reference: there is no gap."""
    shares = []
    for (policy, cond), runs in groups.items():
        if policy in (reference, baseline):
            continue
        spans = sorted((s.start, s.stop) for s, _, _ in runs)
        same: list[dict[str, Any]] = []
        for name in (reference, baseline):
            theirs = {(s.start, s.stop): r for s, r, _ in groups.get((name, cond), [])}
            if not all(span in theirs for span in spans):
                break
            same.append(pool_rows([theirs[span] for span in spans]))
        else:
            mine, (ref, base) = pool_rows([r for _, r, _ in runs]), same
            entry: dict[str, Any] = {"policy": policy, "condition": cond, "episodes": mine["episodes"]}
            episodes = _share_episodes(groups, runs, reference, baseline, cond)
            for metric, better in SHARE_METRICS.items():
                gap = ref[metric] - base[metric]
                has_gap = gap > 0 if better == "higher" else gap < 0
                entry[metric] = float((mine[metric] - base[metric]) / gap) if has_gap else None
                entry[metric + "_se"] = share_se(episodes, metric) if has_gap and episodes else None
                entry[metric + "_reference_baseline"] = [ref[metric], base[metric]]
            shares.append(entry)
    return shares


def _share_episodes(groups: dict[tuple[str, str], list[tuple[range, dict[str, Any], Path]]],
                    runs: list[tuple[range, dict[str, Any], Path]], reference: str, baseline: str, cond: str
                    ) -> list[tuple[dict[str, Any], dict[str, Any], dict[str, Any]]]:
    """Per seed set of ``runs``: the per-episode values of the policy, the reference and the baseline; empty unless
    every set keeps them for all three (then a share's standard error can be resampled)."""
    with_ref, with_base = (_episode_pairs(groups, runs, name, cond) for name in (reference, baseline))
    if not len(with_ref) == len(with_base) == len(runs):  # a set without them: no resampling
        return []
    return [(mine, ref, base) for (mine, ref), (_, base) in zip(with_ref, with_base, strict=True)]


SHARE_RESAMPLES = 2000
"""Bootstrap resamples behind a gap share's standard error."""


def share_se(episodes: list[tuple[dict[str, Any], dict[str, Any], dict[str, Any]]], metric: str) -> float | None:
    """Bootstrap standard error of (policy - baseline) / (reference - baseline) in ``metric``, pooled over seed sets:
    each set's episodes resampled with replacement, the same episodes for the three policies (episode j of a set is
    one episode for all of them), the share recomputed from the pooled means. A set of 128 episodes moves a share by
    10-30 points, so this says how far a pooled share can be trusted. It is half the width of the resampled shares'
    central 68% interval (the standard error of a normal spread): a ratio's resamples with a gap near zero are
    huge and would swamp a standard deviation. None if a resample has no gap."""
    rng = np.random.default_rng(0)
    sets = [np.stack([np.asarray(v[metric], np.float64) for v in values]) for values in episodes]  # (3, n) each
    lift, gap = np.zeros(SHARE_RESAMPLES), np.zeros(SHARE_RESAMPLES)
    for values in sets:
        idx = rng.integers(0, values.shape[1], (SHARE_RESAMPLES, values.shape[1]))
        mine, ref, base = (values[k][idx].sum(axis=1) for k in range(3))
        lift += mine - base
        gap += ref - base
    if np.any(gap == 0):
        return None
    low, high = np.percentile(lift / gap, [15.87, 84.13])
    return float((high - low) / 2.0)


def _episode_pairs(groups: dict[tuple[str, str], list[tuple[range, dict[str, Any], Path]]],
                   runs: list[tuple[range, dict[str, Any], Path]], other: str, cond: str
                   ) -> list[tuple[dict[str, Any], dict[str, Any]]]:
    """The per-episode values of ``runs`` and of policy ``other`` under ``cond``, one pair per seed set both rows
    cover and keep per-episode values for (episode j of a report is the same episode for every policy)."""
    theirs = {(s.start, s.stop): r for s, r, _ in groups.get((other, cond), [])}
    pairs = []
    for span, row, _ in runs:
        match = theirs.get((span.start, span.stop))
        if match is not None and "per_episode" in row and "per_episode" in match:
            pairs.append((row["per_episode"], match["per_episode"]))
    return pairs


def paired_rates(groups: dict[tuple[str, str], list[tuple[range, dict[str, Any], Path]]], baseline: str
                 ) -> list[dict[str, Any]]:
    """Per condition and other policy: its net rotation rate and the baseline's over the episodes both kept to the
    end (ttf 1), matched episode by episode (episode j of a report is the same episode for every policy). Uses the
    seed sets where both rows keep per-episode values; a policy with none is left out."""
    out = []
    for (policy, cond), runs in groups.items():
        if policy == baseline:
            continue
        rotation, time = np.zeros(2), np.zeros(2)
        episodes = kept = 0
        for mine, other in _episode_pairs(groups, runs, baseline, cond):
            both = (np.asarray(mine["ttf"]) >= 1.0) & (np.asarray(other["ttf"]) >= 1.0)
            for i, values in enumerate((mine, other)):
                rotation[i] += np.asarray(values["rotation_total"])[both].sum()
                time[i] += np.asarray(values["in_hand_time"])[both].sum()
            episodes, kept = episodes + len(both), kept + int(both.sum())
        if episodes and kept:
            rate, base_rate = rotation / time
            out.append({"policy": policy, "condition": cond, "episodes": episodes, "kept_by_both": kept,
                        "net_rotation_rate": float(rate), "baseline_net_rotation_rate": float(base_rate),
                        "change": float(rate / base_rate - 1.0) if base_rate != 0 else None})
    return out


PAIRED_METRICS = ("ttf", "vertical_drift")
"""Per-episode values compared by --paired-against."""


def paired_differences(groups: dict[tuple[str, str], list[tuple[range, dict[str, Any], Path]]], against: str
                       ) -> list[dict[str, Any]]:
    """Per condition and other policy: mean and standard error of (policy - ``against``) per episode, for each of
    PAIRED_METRICS, over the seed sets where both rows keep per-episode values (a policy with none is left out)."""
    out = []
    for (policy, cond), runs in groups.items():
        if policy == against:
            continue
        diffs: dict[str, list[np.ndarray]] = {m: [] for m in PAIRED_METRICS}
        for mine, other in _episode_pairs(groups, runs, against, cond):
            for m in PAIRED_METRICS:
                diffs[m].append(np.asarray(mine[m], float) - np.asarray(other[m], float))
        if not diffs["ttf"]:
            continue
        entry: dict[str, Any] = {"policy": policy, "condition": cond, "against": against}
        for m, parts in diffs.items():
            d = np.concatenate(parts)
            entry["episodes"] = len(d)
            entry[m] = float(d.mean())
            entry[m + "_se"] = float(d.std(ddof=1) / np.sqrt(len(d))) if len(d) > 1 else None
        out.append(entry)
    return out


def _share_cell(share: dict[str, Any], metric: str) -> str:
    if share[metric] is None:
        return "-"
    se = share.get(metric + "_se")
    return f"{share[metric]:.0%}" + ("" if se is None else f" ± {se * 100:.0f}")


def _paired_markdown(paired: list[dict[str, Any]], against: str) -> str:
    def cell(entry: dict[str, Any], m: str, scale: float, digits: int) -> str:
        se = entry[m + "_se"]
        return f"{entry[m] * scale:+.{digits}f}" + ("" if se is None else f" ± {se * scale:.{digits}f}")

    text = (f"\n## Paired against {against}\n\nPer-episode difference (policy - {against}) on the same episodes, "
            "mean ± standard error of the mean.\n\n| condition | policy | episodes | ttf | vertical drift (mm) |\n"
            "|---|---|---|---|---|\n")
    return text + "".join(f"| {p['condition']} | {p['policy']} | {p['episodes']} | {cell(p, 'ttf', 1.0, 3)} | "
                          f"{cell(p, 'vertical_drift', 1000.0, 2)} |\n" for p in paired)


def run(cfg: Config) -> Path:
    if not cfg.results:
        raise ValueError("give the evaluation directories to pool with --results")
    if bool(cfg.reference) != bool(cfg.baseline):
        raise ValueError("give --reference and --baseline together")
    if (cfg.out / "results.json").exists():
        raise ValueError(f"{cfg.out} already holds a pooled report; give another --out or remove it")
    groups: dict[tuple[str, str], list[tuple[range, dict[str, Any], Path]]] = defaultdict(list)
    sets = []
    for entry in cfg.results:
        path, chosen = _source(entry)
        rows, span = _read(path)
        if chosen is not None and (missing := set(chosen) - {r["policy"] for r in rows}):
            raise ValueError(f"{path} has no rows for {sorted(missing)}")
        if chosen is not None:
            rows = [{**r, "policy": chosen[r["policy"]]} for r in rows if r["policy"] in chosen]
        rows = [r for r in rows if not cfg.policies or r["policy"] in cfg.policies]
        renamed = {label: name for name, label in (chosen or {}).items() if label != name}
        sets.append(f"- `{path}`: seeds {span.start}-{span.stop - 1}, policies " + ", ".join(
            f"{p} (its {renamed[p]})" if p in renamed else p for p in dict.fromkeys(r["policy"] for r in rows)))
        for r in rows:
            key = (r["policy"], r["condition"])
            for other, _, where in groups[key]:
                if other.start < span.stop and span.start < other.stop:
                    raise ValueError(f"{r['policy']} under {r['condition']} is in both {where} and {path} on "
                                     f"overlapping seeds: its episodes would count twice")
            groups[key].append((span, r, path))
    pooled = [pool_rows([r for _, r, _ in runs]) for runs in groups.values()]
    for name in (cfg.reference, cfg.baseline):
        if name and not any(r["policy"] == name for r in pooled):
            raise ValueError(f"no policy {name!r} in these reports; they have "
                             f"{sorted({r['policy'] for r in pooled})}")
    conditions = [make_condition(Perturbation(friction_scale=r["friction_scale"], added_mass=r["added_mass"],
                                              com_shift=tuple(r["com_shift"])))
                  for r in {r["condition"]: r for r in pooled}.values()]
    policies = list(dict.fromkeys(r["policy"] for r in pooled))
    order = {c.name: i for i, c in enumerate(conditions)}

    def rank(entry: dict[str, Any]) -> tuple[int, int]:  # the reports' order of conditions, then of policies
        return order[entry["condition"]], policies.index(entry["policy"])

    pooled.sort(key=rank)
    shares = sorted(gap_shares(groups, cfg.reference, cfg.baseline), key=rank) if cfg.reference else []
    paired = sorted(paired_rates(groups, cfg.baseline), key=rank) if cfg.baseline else []
    if cfg.paired_against and not any(r["policy"] == cfg.paired_against for r in pooled):
        raise ValueError(f"--paired-against {cfg.paired_against!r}: no such policy in these reports; they have "
                         f"{sorted({r['policy'] for r in pooled})}")
    against = sorted(paired_differences(groups, cfg.paired_against), key=rank) if cfg.paired_against else []

    cfg.out.mkdir(parents=True, exist_ok=True)
    text = markdown_table(pooled).replace("# Evaluation", "# Pooled evaluation", 1)
    if shares:
        text += (f"\n## Share of the {cfg.baseline}'s gap to the {cfg.reference} closed\n\n"
                 f"(policy - {cfg.baseline}) / ({cfg.reference} - {cfg.baseline}), with the {cfg.reference} and the "
                 f"{cfg.baseline} on the policy's own episodes; '-' where the {cfg.baseline} is already as good as "
                 f"the {cfg.reference}.\n\n| condition | policy | episodes | "
                 + " | ".join(SHARE_METRICS) + " |\n|---|---|---|" + "---|" * len(SHARE_METRICS) + "\n")
        text += "".join(f"| {s['condition']} | {s['policy']} | {s['episodes']} | "
                        + " | ".join(_share_cell(s, m) for m in SHARE_METRICS) + " |\n" for s in shares)
        if any(s.get(m + "_se") is not None for s in shares for m in SHARE_METRICS):
            text += ("\n± the bootstrap standard error of the share (each seed set's episodes resampled, the same "
                     "episodes for the three policies; half the central 68% interval of the resampled shares). A "
                     "share whose error is as large as itself has too small a gap to measure on these episodes.\n")
    if paired:
        text += (f"\n## Rotation rate on the episodes both kept\n\nNet rotation rate (rad/s) over the episodes that "
                 f"both the policy and the {cfg.baseline} kept in hand to the end, matched episode by episode.\n\n"
                 f"| condition | policy | episodes | kept by both | policy | {cfg.baseline} | change |\n"
                 "|---|---|---|---|---|---|---|\n")
        text += "".join(f"| {p['condition']} | {p['policy']} | {p['episodes']} | {p['kept_by_both']} | "
                        f"{p['net_rotation_rate']:.3f} | {p['baseline_net_rotation_rate']:.3f} | "
                        + ("-" if p["change"] is None else f"{p['change']:+.1%}") + " |\n" for p in paired)
    if against:
        text += _paired_markdown(against, cfg.paired_against)
    text += "\n## Pooled reports\n\n" + "\n".join(sets) + "\n"
    (cfg.out / "results.md").write_text(text)
    (cfg.out / "results.json").write_text(json.dumps({"rows": pooled, "shares": shares, "paired_rates": paired,
                                                      "paired_differences": against,
                                                      "sources": [str(p) for p in cfg.results]}, indent=2) + "\n")
    plot_bars(cfg.out / "plots" / "bars.png", pooled, conditions)
    print(f"pooled {len(cfg.results)} reports into {len(pooled)} rows -> {cfg.out / 'results.md'}")
    return cfg.out


def main(argv: list[str] | None = None) -> int:
    return script_main(Config, run, __doc__, argv)


if __name__ == "__main__":
    raise SystemExit(main())
