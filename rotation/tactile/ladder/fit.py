"""The ladder's readers: ridge probes on standardized features, one per (stage, feature set, target, label budget).

One simple reader for every stage, so that what differs between rungs is the features, not the learner: ridge
regression (closed form; through the Gram matrix when features outnumber samples) on features standardized with
the training samples' statistics. Features are first squashed by ``asinh`` around their training median in units
of their interquartile spread (at least a twentieth of their standard deviation), so that heavy tails (a dropped
cup's slip speed) do not decide the fit. A classification target is read by ridge on its one-hot code (argmax) or
on its 0/1 value, cut per output where F1 is best on the training samples (a rare event needs its own cut, not
0.5); with ``--friction-reading slip`` the ladder reads the friction tercile as the cut of its friction reading
instead (:func:`tercile_of`). The ridge strength is picked from a fixed grid by cross-validation over the
training sessions (folds by session, so that no fold scores windows of a session it trained on; a binary target's
folds cut the same way).
"""

from __future__ import annotations

import numpy as np

LAMBDAS = (1e-3, 1e-2, 1e-1, 1.0, 1e1, 1e2, 1e3, 1e4)
"""Ridge strengths tried (in units of the standardized features' sum of squares per sample)."""


def _ridge(x: np.ndarray, y: np.ndarray, lam: float) -> np.ndarray:
    """Weights (P, K) minimizing |x w - y|^2 + lam n |w|^2 (x, y centred)."""
    n, p = x.shape
    reg = lam * n
    if p <= n:
        return np.linalg.solve(x.T @ x + reg * np.eye(p), x.T @ y)
    return x.T @ np.linalg.solve(x @ x.T + reg * np.eye(n), y)


class Reader:
    """A fitted ridge reader: standardization, weights and the target's coding."""

    def __init__(self, kind: str, classes: int = 0):
        self.kind, self.classes = kind, classes  # kind: 'r2' | 'accuracy' | 'f1'
        self.threshold = 0.5
        self.lam = float("nan")

    def _code(self, y: np.ndarray) -> np.ndarray:
        if self.kind == "accuracy":
            return np.eye(self.classes)[y[:, 0].astype(int)]
        return y.astype(np.float64)

    def _squash(self, x: np.ndarray) -> np.ndarray:
        return np.arcsinh((x - self.med) / self.spread)

    def fit(self, x: np.ndarray, y: np.ndarray, lam: float) -> Reader:
        q1, self.med, q3 = np.quantile(x, [0.25, 0.5, 0.75], axis=0)
        std = x.std(0)
        spread = np.maximum((q3 - q1) / 1.349, 0.05 * std)  # the floor: a feature constant but for its tail
        # a feature whose spread is float noise (below a millionth of its unit) carries nothing a reader could learn:
        # it is dropped (an infinite scale), not blown up wherever it differs later
        self.spread = np.where(spread > 1e-6 * (1.0 + np.abs(self.med)), spread, np.inf)
        x = self._squash(x)
        self.mx, sx = x.mean(0), x.std(0)
        self.sx = np.where(sx > 1e-9, sx, np.inf)
        code = self._code(y)
        self.my = code.mean(0)
        self.sy = np.maximum(code.std(0), 1e-8) if self.kind == "r2" else np.ones(code.shape[1])
        self.w = _ridge((x - self.mx) / self.sx, (code - self.my) / self.sy, lam)
        return self

    def raw(self, x: np.ndarray) -> np.ndarray:
        return ((self._squash(x) - self.mx) / self.sx) @ self.w * self.sy + self.my

    def predict(self, x: np.ndarray) -> np.ndarray:
        out = self.raw(x)
        if self.kind == "accuracy":
            return out.argmax(1)[:, None].astype(np.float64)
        if self.kind == "f1":
            return (out > self.threshold).astype(np.float64)
        return out


def score(kind: str, pred: np.ndarray, y: np.ndarray) -> float:
    """R^2 (mean over outputs that vary in the test set), accuracy, or F1 pooled over all outputs."""
    if kind == "accuracy":
        return float((pred[:, 0] == y[:, 0]).mean())
    if kind == "f1":
        tp = float(((pred > 0.5) & (y > 0.5)).sum())
        fp, fn = float(((pred > 0.5) & (y <= 0.5)).sum()), float(((pred <= 0.5) & (y > 0.5)).sum())
        return 2 * tp / max(2 * tp + fp + fn, 1.0)
    var = y.var(0)
    keep = var > 1e-12
    if not keep.any():
        return float("nan")
    r2 = 1.0 - ((pred - y) ** 2).mean(0)[keep] / var[keep]
    return float(r2.mean())


def chance(kind: str, y_test: np.ndarray) -> float:
    """The best any reader that ignores the features can score on the test samples: R^2 0 (the test mean), the
    share of the test's most common class, or the better F1 of calling every output positive or every one negative.
    (Strict: such a constant could not know the test set; it bounds what ignoring the features achieves.)"""
    if kind == "accuracy":
        return float(np.bincount(y_test[:, 0].astype(int)).max() / len(y_test))
    if kind == "f1":
        return max(score(kind, np.ones_like(y_test), y_test), score(kind, np.zeros_like(y_test), y_test))
    return 0.0


def _folds(groups: np.ndarray, folds: int) -> np.ndarray:
    sessions = np.unique(groups)
    fold_of = {g: i % folds for i, g in enumerate(sessions)}
    return np.asarray([fold_of[g] for g in groups])


def fit_reader(kind: str, x_train: np.ndarray, y_train: np.ndarray, groups: np.ndarray, classes: int = 0,
               folds: int = 3) -> Reader:
    """A reader fitted on the training samples, its ridge strength (``reader.lam``) and a binary target's threshold
    picked by session-grouped cross-validation."""
    lam = 10.0
    if len(np.unique(groups)) >= 3:
        f = _folds(groups, folds)
        best = -np.inf
        for cand in LAMBDAS:
            oof = np.zeros((len(y_train), y_train.shape[1] if kind != "accuracy" else classes))
            for k in range(folds):
                tr, va = f != k, f == k
                if tr.any() and va.any():
                    oof[va] = Reader(kind, classes).fit(x_train[tr], y_train[tr], cand).raw(x_train[va])
            cut = _best_threshold(oof, y_train) if kind == "f1" else 0.5
            pred = (oof.argmax(1)[:, None].astype(np.float64) if kind == "accuracy" else
                    (oof > cut).astype(np.float64) if kind == "f1" else oof)
            v = np.mean([score(kind, pred[f == k], y_train[f == k]) for k in range(folds) if (f == k).any()])
            v = v if np.isfinite(v) else -np.inf
            if v > best:
                best, lam = float(v), cand
    reader = Reader(kind, classes).fit(x_train, y_train, lam)
    reader.lam = lam
    if kind == "f1":  # the cut of the final reader's own outputs (a linear reader barely overfits its cut)
        reader.threshold = _best_threshold(reader.raw(x_train), y_train)
    return reader


def fit_and_score(kind: str, x_train: np.ndarray, y_train: np.ndarray, groups: np.ndarray, x_test: np.ndarray,
                  y_test: np.ndarray, classes: int = 0, folds: int = 3) -> tuple[float, float]:
    """Fit a reader on the training samples (:func:`fit_reader`) and score it on the test samples; returns (score,
    the chosen strength)."""
    reader = fit_reader(kind, x_train, y_train, groups, classes, folds)
    return score(kind, reader.predict(x_test), y_test), reader.lam


BOOTSTRAP_DRAWS = 200
"""Resamples of the test sessions behind a score's standard error (:func:`session_error`)."""


def session_error(kind: str, pred: np.ndarray, y: np.ndarray, groups: np.ndarray, draws: int = BOOTSTRAP_DRAWS,
                  seed: int = 0) -> float:
    """The standard error of ``score(kind, pred, y)`` over which test sessions were drawn: its spread over
    ``draws`` resamples of the sessions (``groups``) with replacement, each session's samples kept together (a
    session's moments share its object, so they are not independent). NaN with fewer than two sessions."""
    sessions = np.unique(groups)
    if len(sessions) < 2:
        return float("nan")
    rows = [np.flatnonzero(groups == g) for g in sessions]
    rng = np.random.default_rng([seed, 0x626F6F74])
    values = []
    for _ in range(draws):
        pick = np.concatenate([rows[i] for i in rng.integers(0, len(rows), len(rows))])
        values.append(score(kind, pred[pick], y[pick]))
    values = np.asarray(values, np.float64)
    values = values[np.isfinite(values)]
    return float(values.std(ddof=1)) if len(values) > 1 else float("nan")


def tercile_of(friction: np.ndarray, edges: np.ndarray) -> np.ndarray:
    """(M, 1) friction estimates -> (M, 1) terciles (0, 1, 2) by the training terciles' ``edges``: the tercile read
    as the cut of a friction reading, which keeps the coefficient's order (a classifier of three one-hot codes
    does not)."""
    return np.searchsorted(np.asarray(edges, np.float64), np.asarray(friction)[:, 0], side="right")[:, None].astype(
        np.float64)


def _best_threshold(raw: np.ndarray, y: np.ndarray) -> np.ndarray:
    """Per output, the cut of its continuous predictions that maximizes its F1 against the 0/1 targets."""
    out = np.full(raw.shape[1], 0.5)
    for k in range(raw.shape[1]):
        cuts = np.unique(np.quantile(raw[:, k], np.linspace(0.5, 0.998, 80)))
        if len(cuts):
            f1 = [score("f1", (raw[:, k:k + 1] > c).astype(np.float64), y[:, k:k + 1]) for c in cuts]
            out[k] = cuts[int(np.argmax(f1))]
    return out


def budget_sessions(train_sessions: np.ndarray, budget: float, seed: int) -> np.ndarray:
    """The first max(1, round(budget n)) of the n training sessions in a seeded order (nested budgets)."""
    order = np.random.default_rng([seed, 0x6C6164]).permutation(np.sort(train_sessions))
    return order[: max(1, round(budget * len(order)))]
