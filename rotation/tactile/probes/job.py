"""Probe a pretrained touch encoder on labeled sessions: frozen features vs end-to-end training, at label budgets.

    rotate probe --checkpoint runs/pretrain --sessions data/touch --cache data/touch_cache --out runs/probe
    rotate probe --checkpoint d360_sparshx_img_mic_imu_pressure_base.pth --sessions data/real --tasks force slip
    rotate probe --encoder skin --checkpoint runs/pretrain_skin --sessions data/skin --out runs/probe_skin
    rotate probe --checkpoint runs/pretrain --sessions data/shake --tasks shake --out runs/probe_shake

For every variant and label budget, one attentive probe per task (rotation.tactile.models.pooling: a learned query
cross-attends over the encoder's layer-normed tokens, then an MLP head) is trained with Adam on the budget's
share of the training sessions and scored on held-out sessions (docs/reference/sparsh.md "Probes"):

- ``pretrained``: the checkpoint's encoder, frozen (its tokens are computed once per batch for every task);
- ``e2e``: the same architecture from a random initialization (the checkpoint's input statistics), trained with
  each task's probe end to end, one encoder per task;
- ``image_only`` (Sparsh-X): the checkpoint's encoder reading only its image tokens, frozen (or
  ``--image-checkpoint``);
- the touch benchmarks' names (``--tasks shake``: shake_content, shake_fill): ``all`` (= pretrained), ``image``,
  ``audio``, ``imu``, ``pressure`` (the frozen encoder reading that modality's tokens alone) and ``e2e``.

Sparsh-X tasks, from the labels simulated sessions store (rotation.data.session): ``force`` per-fingertip contact
force, along the camera axis and across it (N, sensor frame; RMSE of each); ``contact_force`` the same force split
at the strongest contact, normal and tangential (N; RMSE of each: many of this hand's contacts sit on the side of
the dome, where the camera axis is close to tangent to the contact); ``slip`` whether the fingertip slides
faster than ``slip_threshold`` (balanced accuracy); ``mass`` and ``friction`` of the object (RMSE; from
``labels/priv``).
The shaking benchmark (sessions of `rotate collect --task shake`; those where the hand dropped the bottle are
left out): ``shake_content`` which of pills, rice, lentils, water, oil the bottle holds, ``shake_fill`` which of
three fill levels; object-action-surface (``--task oas``, sessions of `rotate collect --task oas`): ``oas_object``,
``oas_action``, ``oas_surface``, the held object's material, the action and the surface (accuracy and balanced
accuracy; confusion matrices at the largest budget, <task>_confusion.png).
Sparsh-skin tasks (``--encoder skin``, rotation.tactile.probes.skin): ``force`` per pad (instantaneous), ``pose``
and ``joystick`` (temporal: sequences of ``sequence_windows`` windows, a causal transformer block over the pooled
windows). Sessions are split into train and test by file; a budget b trains on the first max(1, round(b n)) of
the n training sessions in a seeded order (nested: 10% within 33% within 100%).

OUT: results.json ``{"rows": [{"task", "variant", "budget", "metric", "value"}, ...], ...}``, results.md (table),
probe.png (metric vs label budget per variant), <task>_over_time.png for temporal tasks (predicted vs true on a
test session, largest budget), config.json, tb/.
The report is rewritten after every (variant, budget) with ``"complete": false`` until the last one; Ctrl-C or
SIGTERM stop after the probe being trained and keep the finished rows. The same command continues a stopped report
(rotation.tactile.probes.resume: only the missing (variant, budget) pairs are trained), and a finished one takes more
variants into the same table (``--variants e2e`` after the frozen ones); a report of other options or another
encoder in OUT is refused, never overwritten.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np
import torch
from torch.utils.data import Dataset, Subset
from tqdm import tqdm

from envs.errors import RequestRefused
from rotation.configs import save_config, to_jsonable
from rotation.data.dataset import split_sessions
from rotation.data.session_reader import SessionReader
from rotation.interrupt import StopSignals
from rotation.runs import summary_writer
from rotation.tactile.loading import open_encoder_windows, session_paths
from rotation.tactile.models.encoders import encoder_kind, kind_of, load_encoder
from rotation.tactile.probes.config import Config
from rotation.tactile.probes.data import (
    ProbeData,
    Task,
    baselines,
    budget_rows,
    open_probe_data,
    target_stats,
)
from rotation.tactile.probes.report import write_confusions, write_report, write_traces
from rotation.tactile.probes.resume import earlier_report, write_traces_file
from rotation.tactile.probes.tokens import fits, frozen_tokens
from rotation.tactile.probes.train import Probes, evaluate, train_probes, variant_encoder
from rotation.tactile.runtime import (
    resolve_device,
    state_digest,
    use_bf16,
)

__all__ = ["Config", "run"]


def _available_tasks(cfg: Config, paths: list[Path]) -> dict[str, Task]:
    """The tasks of a run: those asked for, or (``tasks`` None) every task of the encoder whose label every session
    holds (skin cup sessions: force and pose; joystick sessions: force and joystick)."""
    if cfg.tasks is not None:
        return cfg.task_defs
    have: set[str] | None = None
    for path in paths:
        with SessionReader(path) as r:
            names = {n.split("/", 1)[1] for n in r.names if n.startswith("labels/")}
        have = names if have is None else have & names
    tasks = {n: t for n, t in cfg.task_defs.items() if t.label in (have or set())}
    if not tasks:
        raise RequestRefused(f"probe: no {cfg.encoder} task has its labels in every session of "
                             f"{', '.join(map(str, cfg.sessions))} (labels in all of them: {sorted(have or ())}; "
                             "tasks: " + ", ".join(f"{n} <- labels/{t.label}" for n, t in cfg.task_defs.items())
                             + ")")
    return tasks


def _held(path: Path) -> bool:
    with SessionReader(path) as r:
        return bool(r.meta.properties.get("held", True))


def _prepare(cfg: Config) -> tuple[dict[str, Task], dict[bool, ProbeData]]:
    """The run's tasks, and samples for each kind of task: {False: single windows, True: sequences} (those needed)."""
    paths = session_paths(cfg.sessions)
    if cfg.benchmark:  # an episode whose object left the hand is no sample of what it holds or touches
        held = [p for p in paths if _held(p)]
        if len(held) < len(paths):
            print(f"probe: {len(paths) - len(held)} of {len(paths)} sessions left out: the hand dropped the object")
        paths = held
    if len(paths) < 2:
        raise ValueError(f"probe: need at least 2 session files to split into train and test, found {len(paths)} "
                         f"in {', '.join(map(str, cfg.sessions))}")
    all_tasks = _available_tasks(cfg, paths)
    train_paths, test_paths = split_sessions(paths, cfg.test_fraction, cfg.seed)
    groups: dict[bool, ProbeData] = {}
    for temporal in (False, True):
        tasks = {n: t for n, t in all_tasks.items() if t.temporal == temporal}
        if not tasks:
            continue
        labels = tuple(sorted({t.label for t in tasks.values()}))
        if cfg.cache is not None:
            open_encoder_windows(cfg.encoder, paths, cfg.cache, cfg.fingers, cfg.stride, labels=labels,
                                 progress=cfg.progress, workers=cfg.num_workers)
        groups[temporal] = open_probe_data(cfg.encoder, train_paths, test_paths, cfg.cache, cfg.fingers, cfg.stride,
                                           labels, cfg.sequence_windows if temporal else None)
    return all_tasks, groups


def _frozen_splits(encoder: torch.nn.Module, variant: str, groups: dict[bool, ProbeData],
                   all_tasks: dict[str, Task], cfg: Config, device: torch.device, bf16: bool
                   ) -> dict[bool, tuple[Dataset, Dataset]]:
    """For a frozen variant, the single-window group's train and test windows as the encoder's tokens, computed
    once for every budget (rotation.tactile.probes.tokens), when they fit in ``cfg.token_cache_gb``; {} otherwise
    (the encoder then runs in every step)."""
    data = groups.get(False)
    if variant == "e2e" or data is None or cfg.token_cache_gb <= 0:
        return {}
    windows = len(data.train) + len(data.test)
    nbytes = windows * encoder.token_interface.total * encoder.token_interface.width * 4  # float32
    if not fits(nbytes, cfg.token_cache_gb):
        print(f"probe: the {variant} tokens of {windows} windows would take {nbytes / 1e9:.1f} GB, more than "
              f"--token-cache-gb {cfg.token_cache_gb:g}: the encoder runs in every step instead")
        return {}
    labels = tuple(sorted({t.label for t in all_tasks.values() if not t.temporal}))
    with tqdm(total=windows, unit="window", desc=f"probe: {variant} tokens", disable=not cfg.progress,
              dynamic_ncols=True, leave=False) as bar:
        return {False: tuple(frozen_tokens(encoder, split, labels, cfg.batch_size, cfg.num_workers, device, bf16,
                                           bar) for split in (data.train, data.test))}


def run(cfg: Config) -> dict[str, Any]:
    """Train and score every (variant, budget, task) probe; writes the report and returns it."""
    threads = torch.get_num_threads()
    if cfg.torch_threads:
        torch.set_num_threads(cfg.torch_threads)
    try:
        return _run(cfg)
    finally:
        torch.set_num_threads(threads)


def _run(cfg: Config) -> dict[str, Any]:
    device = resolve_device(cfg.device)
    bf16 = use_bf16(cfg.precision, device)
    pretrained = load_encoder(cfg.checkpoint, device=device)
    if kind_of(pretrained) != cfg.encoder:
        raise ValueError(f"encoder: {cfg.checkpoint} holds a {kind_of(pretrained)} encoder, not {cfg.encoder}; pass "
                         f"--encoder {kind_of(pretrained)}")
    all_tasks, groups = _prepare(cfg)
    out = Path(cfg.out)
    digest = state_digest(pretrained)
    earlier = earlier_report(cfg, digest)
    done = earlier.done
    save_config(cfg, out / "config.json")
    writer = summary_writer(out / "tb", 0)
    rows: list[dict[str, Any]] = list(earlier.rows)
    variants = cfg.variant_names
    todo = [(v, b) for v in variants for b in sorted(cfg.budgets) if (v, float(b)) not in done]
    if done:
        print(f"probe: {out} holds {len(done)} finished (variant, budget) pair(s) of these options: kept; "
              f"{len(todo)} to train")
    bar = tqdm(total=len(todo) * len(groups) * cfg.steps, unit="step", desc="probe", disable=not cfg.progress,
               dynamic_ncols=True)
    first = next(iter(groups.values()))
    sessions_used = {str(b): budget_rows(first, b, cfg.seed)[1] for b in sorted(cfg.budgets)}
    # task -> variant -> trace (temporal tasks) or confusion matrix (multi-class tasks), at the largest budget
    traces: dict[str, dict[str, dict[str, np.ndarray]]] = earlier.traces
    confusions: dict[str, dict[str, np.ndarray]] = earlier.confusions
    fixed = {"baselines": [b for temporal, data in groups.items() for b in baselines(
                 data, {n: t for n, t in all_tasks.items() if t.temporal == temporal}, cfg.slip_threshold)],
             "encoder": encoder_kind(kind_of(pretrained)).describe(pretrained), "checkpoint": str(cfg.checkpoint),
             "encoder_sha256": digest,
             "train_sessions": len(first.train_sessions), "test_sessions": len(first.test_sessions),
             "train_windows": len(first.train), "test_windows": len(first.test), "config": to_jsonable(cfg)}

    def report(complete: bool) -> dict[str, Any]:
        """The report so far, written after every (variant, budget): a stopped run keeps what it finished."""
        out_report = {"rows": rows, "complete": complete, **fixed, "sessions_per_budget": sessions_used}
        if traces:
            write_traces_file(traces, out)
            out_report["trace_plots"] = write_traces(traces, out, budget=max(cfg.budgets))
        if confusions:
            out_report["confusion"] = {t: {v: m.tolist() for v, m in by.items()} for t, by in confusions.items()}
            out_report["confusion_plots"] = write_confusions(confusions, out, max(cfg.budgets))
        write_report(out_report, out)
        return out_report

    try:
        with StopSignals() as stop:
            for variant in variants:
                budgets = [b for b in sorted(cfg.budgets) if (variant, b) in todo]
                if not budgets:
                    continue
                encoder = variant_encoder(variant, pretrained, cfg, device)
                splits = _frozen_splits(encoder, variant, groups, all_tasks, cfg, device, bf16)
                for budget in budgets:
                    for temporal, data in groups.items():
                        tasks = {n: t for n, t in all_tasks.items() if t.temporal == temporal}
                        train_set, test_set = splits.get(temporal, (data.train, data.test))
                        rows_b, _ = budget_rows(data, budget, cfg.seed)
                        stats, pos_weight = target_stats(data, rows_b, tasks, cfg.slip_threshold, device)
                        torch.manual_seed(cfg.seed)
                        probes = Probes(encoder, variant != "e2e", tasks, cfg).to(device)
                        bar.set_postfix(variant=variant, budget=budget)
                        train_probes(probes, Subset(train_set, rows_b.tolist()), tasks, cfg, stats, pos_weight,
                                      device, bf16, bar, writer, f"{variant}/budget_{budget}")
                        scores, task_traces = evaluate(probes, test_set, tasks, cfg, stats, device, bf16)
                        for task, metrics in scores.items():
                            rows += [{"task": task, "variant": variant, "budget": float(budget), "metric": m,
                                      "value": v} for m, v in metrics.items()]
                        if budget == max(cfg.budgets):
                            for task, trace in task_traces.items():
                                if "confusion" in trace:
                                    confusions.setdefault(task, {})[variant] = trace["confusion"]
                                else:
                                    traces.setdefault(task, {})[variant] = trace
                        del probes
                    report(complete=False)
                    stop.raise_if_requested(f"probe: stopped after {variant} at budget {budget:g}; the finished "
                                            f"rows are in {out / 'results.md'}, and the same command continues "
                                            "from them")
    finally:
        bar.close()
        writer.close()
    final = report(complete=True)
    print(f"probe: {len(rows)} results for {len(variants)} variant(s) x {len(cfg.budgets)} budget(s) -> "
          f"{out / 'results.md'}")
    return final
