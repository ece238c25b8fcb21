"""Is friction lost in the rendered streams and tokens, or only to the ladder's linear reader? A small MLP on the
ladder's own cached features (its split, 100% of the labels, one seed), per moment and averaged over each test
session's moments, beside the ladder's ridge reader.

    python experiments/touch_ladder/v4_encoder/nonlinear_readers.py REPORT_DIR SESSIONS_DIR
"""

import sys
from pathlib import Path

import numpy as np
import torch

from rotation.tactile.ladder.fit import fit_and_score
from rotation.tactile.ladder.job import prepare
from rotation.tactile.ladder.samples import MODALITIES
from rotation.tactile.loading import session_paths


def r2(pred: np.ndarray, true: np.ndarray) -> float:
    return float(1 - ((pred - true) ** 2).sum() / ((true - true.mean()) ** 2).sum())


def mlp_predict(x_train: np.ndarray, y_train: np.ndarray, x_test: np.ndarray, steps: int = 1500) -> np.ndarray:
    """A 256-64 GELU MLP with dropout on standardized inputs and target (AdamW, batches of 256)."""
    net = torch.nn.Sequential(torch.nn.Linear(x_train.shape[1], 256), torch.nn.GELU(), torch.nn.Dropout(0.2),
                              torch.nn.Linear(256, 64), torch.nn.GELU(), torch.nn.Linear(64, 1))
    opt = torch.optim.AdamW(net.parameters(), 1e-3, weight_decay=1e-2)
    ym, ys = y_train.mean(), y_train.std()
    xs, ytr = torch.from_numpy(x_train), torch.from_numpy((y_train - ym) / ys)
    for _ in range(steps):
        idx = torch.randint(0, len(xs), (256,))
        loss = ((net(xs[idx]) - ytr[idx]) ** 2).mean()
        opt.zero_grad()
        loss.backward()
        opt.step()
    net.eval()
    with torch.no_grad():
        return net(torch.from_numpy(x_test)).numpy()[:, 0] * ys + ym


def main(report: Path, sessions: Path) -> None:
    torch.manual_seed(0)
    torch.set_num_threads(2)
    split = prepare(session_paths([sessions]), 0.25, 15, 0)  # touch-report's defaults, stride 15
    samples, y, is_test = split.samples, split.y, split.is_test
    train = ~is_test
    rendered, contact = dict(np.load(report / "features_rendered.npz")), dict(np.load(report / "features_contact.npz"))
    feats = {"contact": contact["fields"],
             "streams": np.concatenate([rendered[f"stream/{m}"] for m in MODALITIES], 1),
             "tokens": np.concatenate([rendered[f"tokens/{m}"] for m in MODALITIES], 1)}
    sess = samples.session[is_test]
    for name, x in feats.items():
        mu, sd = x[train].mean(0), x[train].std(0) + 1e-6
        xs = ((x - mu) / sd).astype(np.float32)
        for t in ("friction", "mass"):
            yt = y[t].reshape(len(x), -1)[:, :1].astype(np.float32)
            pred, true = mlp_predict(xs[train], yt[train], xs[is_test]), yt[is_test, 0]
            pred_s = np.array([pred[sess == s].mean() for s in np.unique(sess)])  # integrated over a session
            true_s = np.array([true[sess == s][0] for s in np.unique(sess)])
            ridge, _ = fit_and_score("r2", x[train], yt[train], samples.session[train], x[is_test], yt[is_test])
            print(f"{name:8s} {t:8s} ridge {ridge:.3f}  mlp {r2(pred, true):.3f}  mlp session-mean "
                  f"{r2(pred_s, true_s):.3f} ({len(true_s)} sessions)", flush=True)


if __name__ == "__main__":
    main(Path(sys.argv[1]), Path(sys.argv[2]))
