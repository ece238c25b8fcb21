"""The information ladder: how much of the object's friction, mass and centre of mass, and of each fingertip's normal
force and slip, each stage of the touch path still holds, on sessions whose conditions the encoder never saw.

    rotate touch-report --sessions data/touch_report --checkpoint sparshx-tinier-sim --out runs/touch_report
    rotate touch-report --sessions data/touch_report --stages 1 2 --out runs/ladder_physics   # no encoder needed

Samples are moments of the sessions: the four fingertips' windows ending at one image frame (every ``stride``-th).
Sessions are split into training and test sessions (``test_fraction``, by file); a label budget b trains on the
first max(1, round(b n)) of the n training sessions in a seeded order. Every rung is read by the same ridge reader
(rotation.tactile.ladder.fit), so what differs is what the rung keeps:

1. ``contact``: the simulated contact fields over the window (forces, slip, contact points, accelerometer: the
   physics' ceiling);
2. ``streams``: the rendered streams through simple fixed features, each modality alone and all together;
3. ``tokens``: the frozen encoder's tokens, pooled per modality (mean and maximum), each alone and all together
   (``--checkpoint``);
4. ``e2e``: the encoder's structure trained from random weights on the same targets end to end (all modalities),
   the baseline frozen tokens should beat with few labels.

Targets (rotation.tactile.ladder.samples): friction_tercile (accuracy), friction, mass, com, normal_force (R^2)
and slip (F1). The object's properties (friction, mass, centre of mass) are read from each rung's features over the
windows of the last ``history`` seconds (causal), as a policy that keeps a history of touch could: from their mean
(``--friction-reading slip``: friction from a mean that weights each fingertip's windows by the rung's own slip
reading, the coefficient showing only while a contact slides, and its tercile as the cut of that estimate at the
terciles' edges); normal force and slip from the moment's own window.

OUT: results.json (rows of stage, features, target, budget, metric, value and its standard error over the test
sessions, se; the chance rows; the checks), results.md, ladder.png (each target's score per rung at the largest
budget), budgets.png (scores against the label budget), frames.png (one test session's four streams at moments
across it beside the contact force), features_*.npz (reused by a rerun with the same sessions, stride and checkpoint;
an OUT holding the report of others, or of another history or friction reading, is refused unless --overwrite).
Ctrl-C stops after the current piece and keeps what is done.
"""

from __future__ import annotations

import hashlib
import json
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
from tqdm import tqdm

from envs.errors import RequestRefused
from envs.validation import check_int, check_number, check_output_dir, check_seed, check_types
from rotation.configs import save_config
from rotation.data.dataset import check_session_sources, split_sessions
from rotation.interrupt import StopSignals
from rotation.tactile.ladder.fit import budget_sessions, chance, fit_reader, score, session_error, tercile_of
from rotation.tactile.ladder.report import TARGET_CHECKS, checks, write_report
from rotation.tactile.ladder.samples import (
    CLASSIFY,
    FEATURE_VERSION,
    MODALITIES,
    SESSION_TARGETS,
    TARGETS,
    HandSamples,
    contact_features,
    finger_columns,
    history_mean,
    open_samples,
    slip_history,
    targets,
)
from rotation.tactile.loading import session_paths


@dataclass(frozen=True)
class Config:
    """The information ladder over labeled simulated sessions (`rotate touch-report`)."""

    sessions: tuple[Path, ...] = (Path("touch_sessions"),)
    """Simulated session files or directories from `rotate collect` (randomized friction, mass and centre of mass;
    conditions the encoder was not pretrained on)."""
    out: Path = Path("runs/touch_report")
    """Output directory (created; a rerun reuses its computed features)."""
    checkpoint: Path | None = Path("sparshx-tinier-sim")
    """Sparsh-X encoder for stages 3 and 4: a shipped name, a `rotate pretrain` run or a .safetensors file (the
    shipped encoder by default)."""
    stages: tuple[int, ...] = (1, 2, 3, 4)
    """Rungs to compute (3 and 4 need --checkpoint)."""
    budgets: tuple[float, ...] = (0.1, 0.33, 1.0)
    """Label budgets: shares of the training sessions whose labels the readers see."""
    test_fraction: float = 0.25
    """Share of the sessions held out for scoring (by file)."""
    stride: int = 10
    """Take every stride-th image frame (30 fps) as a sample."""
    e2e_steps: int = 300
    """Adam steps of each end-to-end training (stage 4), one per budget."""
    e2e_batch: int = 4
    """Samples (each four fingertip windows) per end-to-end step."""
    e2e_lr: float = 3e-4
    """Learning rate of the end-to-end training."""
    history: float = 5.0
    """Seconds of windows (ending at the moment, none later) whose features are averaged to read the object's
    friction, mass and centre of mass (end to end: its outputs averaged); 0 reads them from the moment's window
    alone."""
    friction_reading: str = "mean"
    """How friction is read over the history: ``mean``, every window alike, the tercile by a classifier of its own;
    ``slip`` weights each fingertip's windows by how likely the rung's own slip reader finds it sliding (at least
    0.05; the coefficient shows only while a contact slides) and reads the tercile by cutting that friction estimate
    at the terciles' edges (experiments/touch_ladder/v6_slip_reading: higher friction R^2 on fresh sessions, the
    fused tokens' tercile not higher, so not the default)."""
    seed: int = 0
    """Seed of the session split, the budgets' order and the end-to-end training."""
    overwrite: bool = False
    """Replace the report of other sessions, stride or encoder that OUT holds (refused otherwise)."""
    progress: bool = True
    """Show progress bars."""

    def __post_init__(self) -> None:
        check_types(self)
        object.__setattr__(self, "sessions", check_session_sources(self.sessions))
        bad = [s for s in self.stages if s not in (1, 2, 3, 4)]
        if bad or not self.stages:
            raise ValueError(f"stages: choose among 1 2 3 4, got {list(self.stages)}")
        if any(s in (3, 4) for s in self.stages) and self.checkpoint is None:
            raise ValueError("stages 3 and 4 read a touch encoder: give --checkpoint (or --stages 1 2)")
        if not self.budgets or any(not 0 < b <= 1 for b in self.budgets):
            raise ValueError(f"budgets: each in (0, 1], got {list(self.budgets)}")
        check_number("test_fraction", self.test_fraction, 0.0, 1.0, low_open=True, high_open=True)
        check_int("stride", self.stride, 1, 3000)
        check_int("e2e_steps", self.e2e_steps, 1, 10**6)
        check_int("e2e_batch", self.e2e_batch, 1, 1024)
        check_number("e2e_lr", self.e2e_lr, 0.0, 1.0, low_open=True)
        check_number("history", self.history, 0.0, 600.0)
        if self.friction_reading not in ("slip", "mean"):
            raise ValueError(f"friction_reading: slip or mean, got {self.friction_reading!r}")
        check_seed("seed", self.seed)
        check_output_dir("out", self.out)


def _digest(cfg: Config, paths: list[Path]) -> str:
    h = hashlib.sha256(json.dumps([sorted(str(p) for p in paths), cfg.stride, str(cfg.checkpoint),
                                   FEATURE_VERSION]).encode())
    return h.hexdigest()[:16]


def _check_out(cfg: Config, digest: str) -> None:
    """Refuse an OUT that holds the report of other sessions, stride, encoder, history or friction reading, unless
    --overwrite."""
    old = cfg.out / "results.json"
    if not old.exists() or cfg.overwrite:
        return
    try:
        theirs = json.loads(old.read_text())
        theirs = (theirs.get("digest"), float(theirs.get("history", 0.0)), theirs.get("friction_reading", "mean"))
    except (json.JSONDecodeError, UnicodeDecodeError, AttributeError, TypeError, ValueError):
        theirs = None
    if theirs != (digest, float(cfg.history), cfg.friction_reading):
        raise RequestRefused(f"touch-report: {cfg.out} holds the report of other sessions, stride, encoder, history "
                             "or friction reading; use another --out, or --overwrite to replace it")


def _cached(path: Path, digest: str, compute, need: str = "") -> dict[str, np.ndarray]:
    """Features from ``path`` when it was computed for ``digest`` (and holds a key starting with ``need``), else
    computed and saved (atomically)."""
    if path.exists():
        with np.load(path) as z:
            if str(z["digest"]) == digest and any(k.startswith(need) for k in z.files if k != "digest"):
                return {k: z[k] for k in z.files if k != "digest"}
    feats = compute()
    tmp = path.with_suffix(".tmp.npz")
    np.savez(tmp, digest=np.asarray(digest), **feats)
    tmp.replace(path)
    return feats


def run(cfg: Config) -> dict[str, Any]:
    paths = session_paths(cfg.sessions)
    if len(paths) < 2:
        raise RequestRefused(f"touch-report: the ladder needs at least 2 session files (training and test), found "
                             f"{len(paths)}")
    digest = _digest(cfg, paths)
    _check_out(cfg, digest)
    cfg.out.mkdir(parents=True, exist_ok=True)
    save_config(cfg, cfg.out / "config.json")
    with StopSignals() as stop:
        return _run(cfg, paths, digest, stop)


@dataclass
class Split:
    """The ladder's samples of a set of sessions, their targets and the split into training and test sessions."""

    samples: HandSamples
    y: dict[str, np.ndarray]
    kinds: dict[str, str]
    train_paths: list[Path]
    test_paths: list[Path]
    train_ids: np.ndarray
    test_ids: np.ndarray
    is_test: np.ndarray
    edges: np.ndarray


def prepare(paths: list[Path], test_fraction: float, stride: int, seed: int) -> Split:
    """Samples every ``stride``-th frame, split the sessions by file, and compute the targets (the friction
    terciles' edges from the training sessions alone): what every reading of a report starts from."""
    train_paths, test_paths = split_sessions(paths, test_fraction, seed)
    samples = open_samples(sorted(paths), stride)
    order = [Path(p) for p in samples.paths]
    test_ids = np.asarray([order.index(p) for p in test_paths])
    train_ids = np.asarray([order.index(p) for p in train_paths])
    edges = np.quantile(samples.friction[train_ids], [1 / 3, 2 / 3])
    return Split(samples, targets(samples, edges), {t: CLASSIFY.get(t, "r2") for t in TARGETS}, train_paths,
                 test_paths, train_ids, test_ids, np.isin(samples.session, test_ids), edges)


def _run(cfg: Config, paths: list[Path], digest: str, stop: StopSignals) -> dict[str, Any]:
    split = prepare(paths, cfg.test_fraction, cfg.stride, cfg.seed)
    samples, y, kinds, is_test, edges = split.samples, split.y, split.kinds, split.is_test, split.edges
    train_ids, test_ids, train_paths, test_paths = split.train_ids, split.test_ids, split.train_paths, split.test_paths
    if not is_test.any() or is_test.all():
        raise RequestRefused("touch-report: the test or the training sessions hold no whole window (each session "
                             "needs 1.12 s of touch); give more or longer sessions")
    print(f"touch-report: {len(samples)} samples of {len(paths)} sessions ({len(train_paths)} training, "
          f"{len(test_paths)} test); friction terciles at {edges[0]:.3f} and {edges[1]:.3f}")

    feats: dict[str, np.ndarray] = {}
    if 1 in cfg.stages:
        feats.update({"contact/fields": _cached(cfg.out / "features_contact.npz", digest,
                                                lambda: {"fields": contact_features(samples)})["fields"]})
    encoder = None
    if cfg.checkpoint is not None and ({3, 4} & set(cfg.stages)):
        from rotation.tactile.models.encoders import load_encoder

        encoder = load_encoder(cfg.checkpoint)
    if {2, 3} & set(cfg.stages) and not stop.requested:
        from rotation.tactile.ladder.encode import rendered_features

        def compute() -> dict[str, np.ndarray]:
            with tqdm(total=len(samples), desc="render", disable=not cfg.progress) as bar:
                return rendered_features(samples, encoder if 3 in cfg.stages else None, progress=bar.update)

        feats.update(_cached(cfg.out / "features_rendered.npz", digest, compute,
                             need="tokens/" if 3 in cfg.stages else "stream/"))
    finger = {k: finger_columns([v.shape[1]]) for k, v in feats.items()}
    for stage in ("stream", "tokens"):
        parts = [f"{stage}/{m}" for m in MODALITIES if f"{stage}/{m}" in feats]
        if len(parts) > 1:
            feats[f"{stage}/all"] = np.concatenate([feats[k] for k in parts], 1)
            finger[f"{stage}/all"] = np.concatenate([finger[k] for k in parts])
    feats = {k.replace("stream/", "streams/"): v for k, v in feats.items()}
    finger = {k.replace("stream/", "streams/"): v for k, v in finger.items()}
    held = {k: history_mean(v, samples.session, samples.frame, cfg.history) for k, v in feats.items()}

    rows: list[dict[str, Any]] = []
    chance_rows = []
    for t in TARGETS:
        chance_rows.append({"target": t, "metric": kinds[t], "value": chance(kinds[t], y[t][is_test])})
    pieces = [(name, b) for name in feats for b in cfg.budgets]
    with tqdm(total=len(pieces), desc="readers", disable=not cfg.progress) as bar:
        for name, b in pieces:
            if stop.requested:
                break
            chosen = budget_sessions(train_ids, b, cfg.seed)
            tr = np.isin(samples.session, chosen)
            stage, fset = name.split("/")
            base = {"stage": stage, "features": fset, "budget": b, "train_sessions": int(len(chosen))}
            for t, value, se, lam in _read(cfg, feats[name], held[name], finger[name], samples, y, kinds, tr,
                                           is_test, edges):
                rows.append({**base, "target": t, "metric": kinds[t], "value": value, "se": se, "ridge": lam})
            bar.update(1)
    if 4 in cfg.stages and encoder is not None and not stop.requested:
        rows += _end_to_end(cfg, encoder, samples, y, kinds, train_ids, is_test, edges, stop)
    result = {"rows": rows, "chance": chance_rows, "samples": len(samples), "sessions": len(paths),
              "train_sessions": [str(p) for p in train_paths], "test_sessions": [str(p) for p in test_paths],
              "friction_tercile_edges": edges.tolist(), "checkpoint": str(cfg.checkpoint) if cfg.checkpoint else None,
              "history": float(cfg.history), "friction_reading": cfg.friction_reading,
              "complete": not stop.requested, "digest": digest}
    result["checks"] = checks(result, max(cfg.budgets), min(cfg.budgets))
    write_report(cfg.out, result, samples, test_ids[0] if len(test_ids) else 0)
    print(f"touch-report: {cfg.out / 'results.md'}")
    for c in result["checks"]:
        print(f"  {'ok  ' if c['ok'] else 'FAIL' if c['ok'] is False else 'n/a '} {c['check']}: {c['detail']}")
    return result


def _read(cfg: Config, x: np.ndarray, held: np.ndarray, finger: np.ndarray, samples: HandSamples,
          y: dict[str, np.ndarray], kinds: dict[str, str], tr: np.ndarray, te: np.ndarray,
          edges: np.ndarray) -> list[tuple[str, float, float, float]]:
    """(target, score, its standard error over the test sessions, ridge strength) of one feature set read on the
    training samples ``tr``, scored on ``te``: the moment's targets from ``x``, mass and centre of mass from the
    history mean ``held``, friction per ``cfg.friction_reading``."""
    groups, test_groups = samples.session[tr], samples.session[te]

    def scored(t: str, reader, pred: np.ndarray) -> tuple[str, float, float, float]:
        return (t, score(kinds[t], pred, y[t][te]), session_error(kinds[t], pred, y[t][te], test_groups), reader.lam)

    slip = fit_reader("f1", x[tr], y["slip"][tr], groups)
    out = [scored("slip", slip, slip.predict(x[te]))]
    for t in ("normal_force", "mass", "com"):
        xx = held if t in SESSION_TARGETS else x
        reader = fit_reader(kinds[t], xx[tr], y[t][tr], groups)
        out.append(scored(t, reader, reader.predict(xx[te])))
    if cfg.friction_reading == "mean":  # the history mean, the tercile by its own classifier
        for t in ("friction", "friction_tercile"):
            reader = fit_reader(kinds[t], held[tr], y[t][tr], groups, classes=3)
            out.append(scored(t, reader, reader.predict(held[te])))
        return out
    weights = np.clip(slip.raw(x), 0.0, 1.0)  # each window's own slip reading, per fingertip
    xf = slip_history(x, finger, weights, samples.session, samples.frame, cfg.history)
    reader = fit_reader("r2", xf[tr], y["friction"][tr], groups)
    estimate = reader.predict(xf[te])
    return [*out, scored("friction", reader, estimate), scored("friction_tercile", reader, tercile_of(estimate, edges))]


def _end_to_end(cfg: Config, encoder, samples, y, kinds, train_ids, is_test, edges, stop) -> list[dict[str, Any]]:
    from rotation.tactile.ladder.encode import predict_end_to_end, train_end_to_end

    rows = []
    test_rows = np.flatnonzero(is_test)
    with tqdm(total=cfg.e2e_steps * len(cfg.budgets), desc="e2e", disable=not cfg.progress) as bar:
        for b in cfg.budgets:
            if stop.requested:
                break
            chosen = budget_sessions(train_ids, b, cfg.seed)
            train_rows = np.flatnonzero(np.isin(samples.session, chosen))
            model = train_end_to_end(encoder, samples, train_rows, y, kinds, 3, cfg.e2e_steps, cfg.e2e_batch,
                                     cfg.e2e_lr, cfg.seed, progress=bar.update)
            pred = predict_end_to_end(model, samples, test_rows, kinds, history=cfg.history,
                                      friction_edges=edges if cfg.friction_reading == "slip" else None)
            for t in TARGETS:
                truth = y[t][test_rows]
                rows.append({"stage": "e2e", "features": "all", "target": t, "budget": b, "metric": kinds[t],
                             "value": score(kinds[t], pred[t], truth),
                             "se": session_error(kinds[t], pred[t], truth, samples.session[test_rows]),
                             "train_sessions": int(len(chosen))})
    return rows


__all__ = ["Config", "run", "TARGET_CHECKS"]
