"""What the touch benchmarks' sessions hold before any encoder: simple readers on the physics and on the streams.

    python experiments/benchmarks/ceiling.py data/shake data/shake_cache content fill
    python experiments/benchmarks/ceiling.py data/oas data/oas_cache object action surface

Sessions are split into train and test as `rotate probe` splits them (the held sessions, split_sessions with seed 0,
a fifth held out). Two readers per label, each a ridge classifier on standardized features and a small MLP (one
hidden layer of 128, dropout 0.2, Adam, one seed):

- **contact** (the physics' ceiling, one sample per session): summary statistics of each fingertip's contact
  fields after the first 0.8 s: normal force (mean, std, 95th percentile), shear (mean, std), shear over normal,
  accelerometer std per axis, the accelerometer's and the normal force's spectra in ten bands;
- **streams** (one sample per window, as the probe reads them, from the window cache): audio log-mel means and stds
  in 16 bands, IMU mean, std and spectrum in 8 bands per axis, pressure mean, std and range, and the fingertip;
  scored per window and per session (the mean of its windows' scores).

Prints accuracy next to the majority class of the test split.
"""

from __future__ import annotations

import json
import sys
from pathlib import Path

import numpy as np
import torch

from envs.sensors.digit360 import FIELD
from rotation.data.dataset import split_sessions
from rotation.data.session_reader import SessionReader

FINGERS = ("index", "middle", "ring", "thumb")


def held_split(sessions: Path) -> tuple[list[Path], list[Path]]:
    held = []
    for p in sorted(sessions.glob("shard_*/*.h5")):
        with SessionReader(p) as r:
            if r.meta.properties.get("held", True):
                held.append(p)
    return split_sessions(held, 0.2, 0)


def contact_features(path: Path, labels: tuple[str, ...]) -> tuple[np.ndarray, list[int]]:
    with SessionReader(path) as r:
        ys = [int(np.asarray(r.stream(f"labels/{name}").data).reshape(-1)[0]) for name in labels]
        f: list[float] = []
        for finger in FINGERS:
            d = r.stream(f"digit360/{finger}/contact").data[400:]
            fn, shear, acc = d[:, FIELD["force_n"]], np.hypot(d[:, FIELD["force_x"]], d[:, FIELD["force_y"]]), d[:, 3:6]
            spec = np.abs(np.fft.rfft(acc - acc.mean(0), axis=0))
            nb = len(spec) // 10
            f += [fn.mean(), fn.std(), np.percentile(fn, 95), shear.mean(), shear.std(),
                  (shear / np.maximum(fn, 1e-3)).mean(), *acc.std(0),
                  *np.log1p(spec[1:1 + 10 * nb].reshape(10, nb, 3).mean(1)).ravel(),
                  *np.log1p(np.abs(np.fft.rfft(fn - fn.mean()))[1:101].reshape(10, 10).mean(1))]
    return np.asarray(f, np.float32), ys


def stream_features(shard: Path, labels: tuple[str, ...]) -> tuple[np.ndarray, np.ndarray]:
    audio = np.load(shard / "audio.npy").astype(np.float32)  # (W, 224, 256) log-mel
    imu, pressure = np.load(shard / "imu.npy"), np.load(shard / "pressure.npy")[..., 0]
    w = len(audio)
    spec = np.abs(np.fft.rfft(imu - imu.mean(1, keepdims=True), axis=1))[:, 1:113]
    f = [audio.reshape(w, 224, 16, 16).mean(axis=(1, 3)), audio.std(axis=1).reshape(w, 16, 16).mean(-1),
         imu.mean(1), imu.std(1), np.log1p(spec.reshape(w, 8, 14, 3).mean(2).reshape(w, -1)),
         pressure.mean(1, keepdims=True) - 1013.0, pressure.std(1, keepdims=True),
         (pressure.max(1) - pressure.min(1))[:, None], np.eye(4)[np.load(shard / "finger.npy")]]
    ys = np.stack([np.load(shard / f"label_{name}.npy").reshape(w, -1)[:, 0] for name in labels], 1)
    return np.concatenate(f, 1), ys.astype(np.int64)


def fit_scores(xtr: np.ndarray, ytr: np.ndarray, xte: np.ndarray, classes: int) -> dict[str, np.ndarray]:
    mu, sd = xtr.mean(0), xtr.std(0) + 1e-6
    a, b = (xtr - mu) / sd, (xte - mu) / sd
    a1, b1 = np.c_[a, np.ones(len(a))], np.c_[b, np.ones(len(b))]
    ridge = b1 @ np.linalg.solve(a1.T @ a1 + 10.0 * np.eye(a1.shape[1]), a1.T @ np.eye(classes)[ytr])
    torch.manual_seed(0)
    net = torch.nn.Sequential(torch.nn.Linear(a.shape[1], 128), torch.nn.ReLU(), torch.nn.Dropout(0.2),
                              torch.nn.Linear(128, classes))
    opt = torch.optim.Adam(net.parameters(), 1e-3, weight_decay=1e-4)
    at, yt = torch.tensor(a, dtype=torch.float32), torch.tensor(ytr)
    for _ in range(1500):
        i = torch.randint(0, len(at), (min(256, len(at)),))
        loss = torch.nn.functional.cross_entropy(net(at[i]), yt[i])
        opt.zero_grad()
        loss.backward()
        opt.step()
    net.eval()
    with torch.no_grad():
        mlp = net(torch.tensor(b, dtype=torch.float32)).numpy()
    return {"ridge": ridge, "mlp": mlp}


def main(sessions: Path, cache: Path, labels: tuple[str, ...]) -> None:
    train, test = held_split(sessions)
    print(f"{sessions}: {len(train)} training and {len(test)} test sessions (held ones)")
    ctr = [contact_features(p, labels) for p in train]
    cte = [contact_features(p, labels) for p in test]
    shards = json.loads((cache / "manifest.json").read_text())["sessions"]
    st = [stream_features(cache / shards[str(p.resolve())], labels) for p in train]
    se = [stream_features(cache / shards[str(p.resolve())], labels) for p in test]
    session_of = np.concatenate([np.full(len(y), i) for i, (_, y) in enumerate(se)])
    for k, name in enumerate(labels):
        ytr = np.array([y[k] for _, y in ctr])
        yte = np.array([y[k] for _, y in cte])
        classes = int(max(ytr.max(), yte.max())) + 1
        majority = np.bincount(yte, minlength=classes).max() / len(yte)
        out = [f"{name}: majority {majority:.3f}"]
        for reader, s in fit_scores(np.stack([x for x, _ in ctr]), ytr, np.stack([x for x, _ in cte]), classes).items():
            out.append(f"contact {reader} {(s.argmax(1) == yte).mean():.3f}")
        xw, yw = np.concatenate([x for x, _ in st]), np.concatenate([y for _, y in st])[:, k]
        xe, ye = np.concatenate([x for x, _ in se]), np.concatenate([y for _, y in se])[:, k]
        for reader, s in fit_scores(xw, yw, xe, classes).items():
            per_session = np.mean([s[session_of == i].mean(0).argmax() == ye[session_of == i][0]
                                   for i in np.unique(session_of)])
            out.append(f"streams {reader} {(s.argmax(1) == ye).mean():.3f} / session {per_session:.3f}")
        print("  " + "; ".join(out), flush=True)


if __name__ == "__main__":
    if len(sys.argv) < 4:
        sys.exit(__doc__)
    main(Path(sys.argv[1]), Path(sys.argv[2]), tuple(sys.argv[3:]))
