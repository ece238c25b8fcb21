"""Where is the hole? What the insertion demonstrations' inputs say about it while the prong presses on the plate.

While the prong rests on the plate beside the hole, the feel expert steps away from the press (docs/insertion.md);
a policy that imitates it must read from its inputs on which side of the prong the hole lies. This probe asks, on
the pressing steps of a demonstrations folder (socket force above 0.3 N, the tip less than 1 mm into the hole),
how well a ridge regression (and a small MLP) reads the prong tip's offset from the hole's axis (x, y in the
socket's frame, mm) from:

- ``proprio``: the policy's proprioception (wrist target offset and joints, 23);
- ``forces``: the four fingertips' contact forces (normal and shear, sensor frames) at the step, and their change
  since the last step without contact with the socket (24): what the sensors' physics holds, before any rendering
  or encoder; ``normal force change``: only the change of the four normal forces (what each fingertip's pressure
  sensor follows);
- ``touch``: the frozen encoder's per-fingertip mean tokens that the policy reads (4 x D, from a train-il run's
  cache, ``--touch-cache``);
- ``touch change``: those tokens minus the episode's first step's (the grip at rest, before any contact);
- ``touch+proprio``, ``forces+proprio``.

Scores by 5-fold cross-validation grouped by episode: R^2 of the offset, and the share of steps (offset above
0.5 mm) whose predicted offset points within 45 degrees of the true one. With ``--touch-cache``, a second table: how
well the tokens read each fingertip's own contact force over all steps, and the change of it since the last step
without contact with the socket on the pressing steps (what a press on the plate adds).

With ``--encoder NAME``, a third table: the same offset and press change read from each modality's own tokens
(image, audio, IMU, pressure; their mean, and for IMU and pressure also the newest 4 and the maximum; computed
here, about 7 minutes for 100 demonstrations on 2 cores), after a table of how far those tokens move when a
pressure step is added to one window (:func:`step_response`).

    python experiments/tools/insertion_touch_probe.py --demos DEMOS_DIR --touch-cache RUN/touch_..._all_....npz \
        [--encoder sparshx-tinier-sim]
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np

from envs.sensors.digit360 import FIELD, FINGERS
from rotation.data.session_reader import SessionReader

FORCE_FIELDS = ("force_n", "force_x", "force_y")  # (adding the contact points c0_x, y, z made every score worse)


def quat_mat(q: np.ndarray) -> np.ndarray:
    w, x, y, z = q / np.linalg.norm(q)
    return np.array([[1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
                     [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
                     [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)]])


def episode(path: Path) -> dict[str, np.ndarray]:
    with SessionReader(path) as r:
        t = np.asarray(r.stream("actions/wrist").timestamps)
        socket, prong = r.stream("labels/socket").data, r.stream("labels/prong").data
        offset = np.stack([quat_mat(s[3:]).T @ (p[:3] - s[:3]) for s, p in zip(socket, prong, strict=True)])
        forces = []
        for f in FINGERS:
            c = r.stream(f"digit360/{f}/contact")
            k = np.searchsorted(np.asarray(c.timestamps), t, side="right") - 1
            rows = np.asarray(c.data)[np.clip(k, 0, None)]
            forces.append(rows[:, [FIELD[n] for n in FORCE_FIELDS]])
        forces = np.concatenate(forces, axis=1)
        force = r.stream("labels/socket_force").data[:, 0]
        free = np.zeros(len(t), int)  # the last step before each without contact with the socket
        for k in range(1, len(t)):
            free[k] = k if force[k] < 0.1 else free[k - 1]
        proprio = np.concatenate([r.stream("wrist/pose").data, r.stream("joints/position").data], axis=1)
        return {"offset_mm": 1e3 * offset, "force": force, "depth": r.stream("labels/depth").data[:, 0],
                "forces": np.concatenate([forces, forces - forces[free]], axis=1), "proprio": proprio}


def fold_ids(groups: np.ndarray, folds: int) -> np.ndarray:
    """Each sample's cross-validation fold: whole episodes (groups) dealt to ``folds`` folds in a fixed random order."""
    ids = np.unique(groups)
    fold_of = dict(zip(np.random.default_rng(0).permutation(ids), np.arange(len(ids)) % folds, strict=True))
    return np.array([fold_of[g] for g in groups])


def ridge_cv(x: np.ndarray, y: np.ndarray, groups: np.ndarray, alpha: float, folds: int = 5) -> np.ndarray:
    pred = np.zeros_like(y)
    f = fold_ids(groups, folds)
    for k in range(folds):
        tr, te = f != k, f == k
        mu, sd = x[tr].mean(0), x[tr].std(0) + 1e-6
        xt = (x[tr] - mu) / sd
        ym = y[tr].mean(0)
        w = np.linalg.solve(xt.T @ xt + alpha * len(xt) * np.eye(x.shape[1]), xt.T @ (y[tr] - ym))
        pred[te] = ((x[te] - mu) / sd) @ w + ym
    return pred


def mlp_cv(x: np.ndarray, y: np.ndarray, groups: np.ndarray, folds: int = 5, steps: int = 1500) -> np.ndarray:
    import torch

    torch.manual_seed(0)
    pred = np.zeros_like(y)
    f = fold_ids(groups, folds)
    for k in range(folds):
        tr, te = f != k, f == k
        mu, sd = x[tr].mean(0), x[tr].std(0) + 1e-6
        xt = torch.tensor((x[tr] - mu) / sd, dtype=torch.float32)
        yt = torch.tensor(y[tr], dtype=torch.float32)
        net = torch.nn.Sequential(torch.nn.Linear(x.shape[1], 64), torch.nn.GELU(), torch.nn.Dropout(0.2),
                                  torch.nn.Linear(64, 64), torch.nn.GELU(), torch.nn.Linear(64, y.shape[1]))
        opt = torch.optim.AdamW(net.parameters(), lr=1e-3, weight_decay=1e-2)
        for _ in range(steps):
            loss = torch.nn.functional.mse_loss(net(xt), yt)
            opt.zero_grad()
            loss.backward()
            opt.step()
        net.eval()
        with torch.no_grad():
            pred[te] = net(torch.tensor((x[te] - mu) / sd, dtype=torch.float32)).numpy()
    return pred


def r2_of(p: np.ndarray, y: np.ndarray) -> np.ndarray:
    """R^2 of predictions ``p`` per output column of ``y``."""
    return 1 - ((p - y) ** 2).sum(0) / ((y - y.mean(0)) ** 2).sum(0)


def scores(p: np.ndarray, y: np.ndarray, far: np.ndarray) -> tuple[float, np.ndarray, float]:
    r2 = r2_of(p, y)
    cos = (p[far] * y[far]).sum(1) / (np.linalg.norm(p[far], axis=1) * np.linalg.norm(y[far], axis=1) + 1e-9)
    return r2.mean(), r2, (cos > np.cos(np.pi / 4)).mean()


def group_tokens(paths: list[Path], encoder: str) -> dict[str, np.ndarray]:
    """Pooled tokens of every step's four fingertip windows, (T, 4, D) each: every modality's mean token, and for the
    serial streams (IMU, pressure, whose tokens run in time order) the mean of the newest 4 and the maximum."""
    import torch
    from tqdm import tqdm

    from rotation.il.data import touch_rows, window_batch
    from rotation.il.touch import TouchEmbedder

    enc = TouchEmbedder(encoder, "all").encoder
    names = list(enc.token_interface.names)
    windows, rows = touch_rows(paths)
    width = int(enc.token_interface.width)
    pools = {"mean": lambda t: t.mean(1), "newest 4": lambda t: t[:, -4:].mean(1), "max": lambda t: t.amax(1)}
    out: dict[str, list[np.ndarray]] = {}
    with torch.no_grad():
        for a in tqdm(range(0, len(rows), 16), desc="tokens by modality", mininterval=10):
            tokens = enc(enc.preprocess(dict(window_batch(windows, rows[a:a + 16]))))
            for name in names:
                for pool, fn in pools.items():
                    if pool == "mean" or name in ("imu", "pressure"):
                        out.setdefault(f"{name}, {pool}", []).append(
                            fn(tokens[name]).reshape(-1, len(FINGERS), width).numpy())
    return {k: np.concatenate(v) for k, v in out.items()}


def step_response(paths: list[Path], encoder: str, amps: tuple[float, ...] = (0.1, 0.4, 1.6)) -> None:
    """How far each modality's mean token, and the pressure's newest 4 tokens, move when a pressure step of ``amps``
    hPa over the last 0.25 s is added to one real window (the first demonstration's index fingertip, before any
    contact), against the token's own norm: whether the encoder sees a press's pressure at all."""
    import torch

    from rotation.il.data import touch_rows, window_batch
    from rotation.il.touch import TouchEmbedder

    enc = TouchEmbedder(encoder, "all").encoder
    windows, rows = touch_rows(paths[:1])
    base = window_batch(windows, rows[5:6, :1])
    with torch.no_grad():
        ref = enc(enc.preprocess(dict(base)))
        print("\n| pressure step (hPa) | " + " | ".join(f"{n} mean token moves" for n in ref)
              + " | pressure's newest 4 tokens move |")
        print("|---" * (len(ref) + 2) + "|")
        for a in amps:
            b = {k: v.clone() for k, v in base.items()}
            b["pressure"][:, -50:, 0] += a  # 50 samples at 200 Hz
            tok = enc(enc.preprocess(dict(b)))
            moves = [float((tok[n][0].mean(0) - ref[n][0].mean(0)).norm() / ref[n][0].mean(0).norm()) for n in ref]
            newest = float((tok["pressure"][0, -4:].mean(0) - ref["pressure"][0, -4:].mean(0)).norm()
                           / ref["pressure"][0, -4:].mean(0).norm())
            print(f"| {a:g} | " + " | ".join(f"{m:.1%}" for m in moves) + f" | {newest:.1%} |")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--demos", required=True, type=Path)
    ap.add_argument("--touch-cache", type=Path, help="a train-il run's touch embedding cache of these demos")
    ap.add_argument("--min-force", type=float, default=0.3)
    ap.add_argument("--encoder", help="also probe each modality's mean token of this Sparsh-X encoder")
    args = ap.parse_args()
    paths = sorted(args.demos.rglob("*.h5"))
    eps = [episode(p) for p in paths]
    cat = {k: np.concatenate([e[k] for e in eps]) for k in eps[0]}
    groups = np.concatenate([np.full(len(e["force"]), i) for i, e in enumerate(eps)])
    feats = {"proprio": cat["proprio"], "forces": cat["forces"],
             "normal force change": cat["forces"][:, [12 + 3 * i for i in range(len(FINGERS))]]}
    if args.touch_cache is not None:
        touch = np.load(args.touch_cache)["touch"]
        if len(touch) != len(groups):
            raise SystemExit(f"{len(touch)} cached steps for {len(groups)} demonstrated steps: not these demos")
        feats["touch"] = touch.reshape(len(touch), -1)
        first = np.concatenate([[0], np.flatnonzero(np.diff(groups)) + 1])[groups]  # each episode's first step
        feats["touch change"] = feats["touch"] - feats["touch"][first]
        feats["touch+proprio"] = np.concatenate([feats["touch"], cat["proprio"]], axis=1)
    feats["forces+proprio"] = np.concatenate([cat["forces"], cat["proprio"]], axis=1)
    press = (cat["force"] > args.min_force) & (cat["depth"] < 0.001)
    y = cat["offset_mm"][press, :2]
    g = groups[press]
    far = np.linalg.norm(y, axis=1) > 0.5
    print(f"{press.sum()} pressing steps in {len(np.unique(g))} of {len(eps)} episodes; offset rms "
          f"{np.sqrt((y ** 2).mean(0)).round(2)} mm; {far.sum()} of them more than 0.5 mm off the axis")
    print("| input | dims | ridge R^2 x, y | ridge direction within 45 deg | MLP R^2 x, y | MLP direction |")
    print("|---|---|---|---|---|---|")
    for name, x in feats.items():
        x = x[press].astype(np.float64)
        best = max((scores(ridge_cv(x, y, g, alpha), y, far) for alpha in (1e-3, 1e-2, 1e-1, 1.0)),
                   key=lambda s: s[0])
        mlp = scores(mlp_cv(x, y, g), y, far)
        print(f"| {name} | {x.shape[1]} | {best[1][0]:.2f}, {best[1][1]:.2f} | {best[2]:.0%} | "
              f"{mlp[1][0]:.2f}, {mlp[1][1]:.2f} | {mlp[2]:.0%} |")
    if "touch" in feats:
        print("\n| fingertip | all steps: force std n, x, y (N) | tokens R^2 | pressing steps: change since contact, "
              "std (N) | tokens R^2 |")
        print("|---|---|---|---|---|")
        for i, finger in enumerate(FINGERS):
            x = touch[:, i].astype(np.float64)
            row = [finger]
            for rows, part in ((slice(None), cat["forces"][:, 3 * i: 3 * i + 3]),
                               (press, cat["forces"][:, 12 + 3 * i: 15 + 3 * i])):
                f = part[rows].astype(np.float64)
                r2 = r2_of(ridge_cv(x[rows], f, groups[rows], 1e-2), f)
                row += [", ".join(f"{v:.2f}" for v in f.std(0)), ", ".join(f"{v:.2f}" for v in r2)]
            print("| " + " | ".join(row) + " |")
    if args.encoder:
        step_response(paths, args.encoder)
        pooled = group_tokens(paths, args.encoder)
        pooled["all four, mean"] = np.concatenate([v for k, v in pooled.items() if k.endswith(", mean")], axis=-1)
        change = cat["forces"][press, 12:].astype(np.float64)
        print("\n| modality's tokens, pooled | offset R^2 x, y | direction within 45 deg | "
              "press change R^2 (mean of 12) |")
        print("|---|---|---|---|")
        for name, tokens in pooled.items():
            x = tokens.reshape(len(tokens), -1)[press].astype(np.float64)
            best = max((scores(ridge_cv(x, y, g, alpha), y, far) for alpha in (1e-2, 1e-1, 1.0)), key=lambda s: s[0])
            r2 = r2_of(ridge_cv(x, change, g, 1e-1), change)
            print(f"| {name} | {best[1][0]:.2f}, {best[1][1]:.2f} | {best[2]:.0%} | {r2.mean():.2f} |")


if __name__ == "__main__":
    main()
