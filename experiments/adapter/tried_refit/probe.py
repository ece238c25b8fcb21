"""One-off: what a linear last layer on the shipped adapter's own features could do, and where each adapter's
latent sits, on rollouts of the shipped adapter under the three evaluation conditions.

    python probe.py collect CONDITION SEED OUT.npz     # 16 envs x 400 steps of the shipped adapter
    python probe.py ridge FILE.npz [...]                # ridge refits of the zero layer, 4-fold CV over episodes
    python probe.py dims REFIT_BUNDLE FILE.npz [...]    # per latent dimension: mean and MSE to the teacher's z

Files are named probe_CONDITION_SEED.npz; every touch refresh of every env is a sample with the adapter's pooled
fingertip features, the student's latent phi, the adapter's correction and the teacher's z. The ridge here is fit
on the evaluation conditions themselves, so it is a probe of what the features hold, not a candidate.
"""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np
import torch

CONDITIONS = ("nominal", "friction_0.25", "mass_+0.2kg")


def collect(condition: str, seed: int, out: str, steps: int = 400, n: int = 16) -> None:
    from rotation.bundles import load_bundle
    from rotation.evaluate import job
    from rotation.evaluate.suites import get_suite
    from rotation.sim_warp.host import make_vec

    torch.set_num_threads(2)
    policy, teacher = load_bundle("adapter"), load_bundle("teacher")
    cond = get_suite("perturbations", [condition])[0]
    env_cfg = job.env_config(job.Config(policies={"adapter": "adapter"}, seed=seed, num_envs=n), policy,
                             cond.perturb, policy.env_needs)
    env = make_vec("cpu", env_cfg, num_envs=n, seed=seed, nthread=None, device="cpu")
    rows: dict[str, list[np.ndarray]] = {k: [] for k in ("pooled", "phi", "corr", "zt", "env", "ep")}
    episode = np.zeros(n, np.int64)
    correction = np.zeros((n, policy.config.latent_dim), np.float32)
    obs = env.reset(seed=seed)
    for k in range(steps):
        groups = {key: obs[key] for key in policy.config.obs_groups}
        if k % policy.touch_every == 0:
            with torch.no_grad():
                z_student = policy.student_latent(groups)
                pooled = policy.adapter.pooled(policy.tokens(policy.env_windows(obs)))
                correction = policy.adapter.from_pooled(pooled, z_student).numpy()
                z_teacher = teacher.net.extractor.z({key: torch.as_tensor(obs[key])
                                                     for key in teacher.config.obs_groups})
            for key, value in (("pooled", pooled.numpy()), ("phi", z_student.numpy()), ("corr", correction.copy()),
                               ("zt", z_teacher.numpy()), ("env", np.arange(n)), ("ep", episode.copy())):
                rows[key].append(value)
        obs, _, terminated, truncated, _ = env.step(policy.act_batch(groups, correction=correction))
        done = np.flatnonzero(terminated | truncated)
        if len(done):
            obs = env.reset(ids=done)
            episode[done] += 1
            correction[done] = 0.0
    env.close()
    np.savez_compressed(out, **{k: np.concatenate(v) for k, v in rows.items()})


def load(files: list[str]) -> dict[str, np.ndarray]:
    data: dict[str, list[np.ndarray]] = {k: [] for k in ("pooled", "phi", "corr", "zt", "key", "cond")}
    for i, f in enumerate(files):
        z = np.load(f)
        for k in ("pooled", "phi", "corr", "zt"):
            data[k].append(z[k])
        data["key"].append(i * 100_000 + z["env"] * 1000 + z["ep"])  # one id per episode
        data["cond"].append(np.full(len(z["phi"]), Path(f).stem.split("_", 1)[1].rsplit("_", 1)[0]))
    return {k: np.concatenate(v) for k, v in data.items()}


def ridge(files: list[str]) -> None:
    from adapters.bundle import load_adapter

    d = load(files)
    adapter = load_adapter("adapter").adapter
    with torch.no_grad():
        h = adapter.hidden(torch.as_tensor(d["pooled"]), torch.as_tensor(d["phi"])).double().numpy()
    target = d["zt"] - d["phi"]
    ids = np.unique(d["key"])
    order = np.random.default_rng(0).permutation(len(ids))
    fold_of = dict(zip(ids[order].tolist(), (np.arange(len(ids)) % 4).tolist(), strict=True))
    fold = np.array([fold_of[k] for k in d["key"].tolist()])

    def report(name: str, corr: np.ndarray) -> None:
        err = (d["phi"] + corr - d["zt"]) ** 2
        print(f"{name:30s} " + " | ".join(f"{c}: MSE {err[d['cond'] == c].mean():.4f}" for c in CONDITIONS))

    report("student", np.zeros_like(target))
    report("shipped adapter", d["corr"])
    for lam in (1.0, 10.0, 100.0, 1000.0):
        pred = np.empty_like(target)
        for i in range(4):
            tr, te = fold != i, fold == i
            mu, sd = h[tr].mean(0), h[tr].std(0) + 1e-6
            a, ym = (h[tr] - mu) / sd, target[tr].mean(0)
            w = np.linalg.solve(a.T @ a + lam * np.eye(a.shape[1]), a.T @ (target[tr] - ym))
            pred[te] = ((h[te] - mu) / sd) @ w + ym
        report(f"ridge on its features, {lam:g}", pred)


def dims(refit: str, files: list[str]) -> None:
    from adapters.bundle import load_adapter

    d = load(files)
    shipped, other = load_adapter("adapter").adapter, load_adapter(refit).adapter
    for cond in CONDITIONS:
        m = d["cond"] == cond
        pooled, phi, zt = (torch.as_tensor(d[k][m]) for k in ("pooled", "phi", "zt"))
        with torch.no_grad():
            latents = {"teacher": zt, "student": phi, "shipped": phi + shipped.from_pooled(pooled, phi),
                       "refit": phi + other.from_pooled(pooled, phi)}
        print(f"## {cond} ({int(m.sum())} samples)")
        for name, z in latents.items():
            print(f"{name:8s} mean " + " ".join(f"{x:+.2f}" for x in z.mean(0).tolist())
                  + "   MSE per dimension " + " ".join(f"{x:.3f}" for x in ((z - zt) ** 2).mean(0).tolist()))


if __name__ == "__main__":
    what, args = sys.argv[1], sys.argv[2:]
    if what == "collect":
        collect(args[0], int(args[1]), args[2])
    elif what == "ridge":
        ridge(args)
    else:
        dims(args[0], args[1:])
