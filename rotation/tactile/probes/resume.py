"""Continuing a probe report: `rotate probe` into a folder that already holds a report of the same options keeps its
finished (variant, budget) rows and trains only the rest.

A stopped run (Ctrl-C, SIGTERM, a closed session) is continued by the same command; a finished one can be extended
with more variants (e.g. the frozen variants first, then ``--variants e2e`` into the same ``--out``): the rows
compare because everything that decides them is the same, which is checked: the options (all but the variants and
the run-time ones, :data:`MAY_DIFFER`) and the encoder's weights (rotation.tactile.runtime.state_digest). A report
of other options is refused, never overwritten. The confusion matrices come back from results.json, the temporal
tasks' traces from traces.npz.
"""

from __future__ import annotations

import json
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from envs.errors import RequestRefused
from rotation.configs import to_jsonable
from rotation.runs import config_differences, save_atomically

MAY_DIFFER = frozenset({"out", "variants", "progress", "num_workers", "device", "torch_threads", "token_cache_gb"})
"""Options that may change between a report and its continuation (which variants run, and run-time options; a
different device gives rows that agree to float precision, not bit for bit)."""
TRACES = "traces.npz"
"""The temporal tasks' traces at the largest budget (task|variant|field -> array), for a continued run's plots."""


@dataclass
class Earlier:
    """What an earlier run of the same options finished."""

    rows: list[dict[str, Any]] = field(default_factory=list)
    confusions: dict[str, dict[str, np.ndarray]] = field(default_factory=dict)
    traces: dict[str, dict[str, dict[str, np.ndarray]]] = field(default_factory=dict)

    @property
    def done(self) -> set[tuple[str, float]]:
        """(variant, budget) pairs with rows (a pair's rows are written once all its tasks are scored)."""
        return {(r["variant"], float(r["budget"])) for r in self.rows}


def earlier_report(cfg: Any, digest: str) -> Earlier:
    """The finished part of the report in ``cfg.out`` (empty if there is none); refused when it was made with
    other options or another encoder, or is not a probe report."""
    path = Path(cfg.out) / "results.json"
    if not path.is_file():
        return Earlier()
    try:
        saved = json.loads(path.read_text())
    except (OSError, UnicodeDecodeError, json.JSONDecodeError) as err:
        raise RequestRefused(f"probe: {path} cannot be read ({err}); give another --out, or move it away") from None
    if not isinstance(saved, dict) or not isinstance(saved.get("rows"), list) or \
            not isinstance(saved.get("config"), dict):
        raise RequestRefused(f"probe: {path} is not a probe report (no rows and config); give another --out")
    differences = config_differences(saved["config"], to_jsonable(cfg), MAY_DIFFER)
    if saved.get("encoder_sha256", digest) != digest:
        differences.append(f"encoder weights: sha256 {saved['encoder_sha256'][:12]}... -> {digest[:12]}...")
    if differences:
        raise RequestRefused(f"probe: {cfg.out} holds a report made with other options ({'; '.join(differences)}); "
                             "its rows would not compare with these. Give another --out, or the report's options "
                             f"(only {', '.join(sorted(MAY_DIFFER))} may change)")
    confusions = {task: {v: np.asarray(m, np.int64) for v, m in by.items()}
                  for task, by in saved.get("confusion", {}).items()}
    return Earlier(list(saved["rows"]), confusions, _read_traces(Path(cfg.out) / TRACES))


def write_traces_file(traces: dict[str, dict[str, dict[str, np.ndarray]]], out: Path) -> None:
    """Keep the traces for a continuation (atomically: a stop while writing leaves the previous file)."""
    if not traces:
        return
    arrays = {f"{task}|{variant}|{name}": np.asarray(value)
              for task, by in traces.items() for variant, trace in by.items() for name, value in trace.items()}
    save_atomically(lambda tmp: np.savez(tmp, **arrays), out / TRACES)


def _read_traces(path: Path) -> dict[str, dict[str, dict[str, np.ndarray]]]:
    traces: dict[str, dict[str, dict[str, np.ndarray]]] = {}
    if not path.is_file():
        return traces
    with np.load(path) as data:
        for key in data.files:
            task, variant, name = key.split("|")
            traces.setdefault(task, {}).setdefault(variant, {})[name] = data[key]
    return traces
