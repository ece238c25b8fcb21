"""Train the privileged teacher with PPO on the batched env (`rotate train-teacher`).

The teacher sees the normalized proprioception (3 x 32) and a latent z = EnvFactorEncoder(priv) of the privileged
object properties; actor and critic are 512-256-128 ELU MLPs (docs/reference/hora.md). Changes from Hora's GPU recipe,
for a 2-core CPU: 256 envs instead of 16,384 with a horizon of 16 instead of 8 (4,096 transitions per update
instead of 131,072); minibatches of 2,048 instead of 32,768; 3 epochs per update instead of 5 (the updates, not the
physics, bound the step rate on a CPU); a starting learning rate of 1e-3 instead of 5e-3 (smaller batches give
noisier gradients) with the same adaptive-KL schedule (target 0.02); rewards scaled by 0.1 without a value
normalizer (SB3 has none; Hora scaled by 0.01 and normalized values); initial action std 0.6 instead of 1; and in
the env a lighter pose penalty and a fall penalty (envs.config.RewardConfig says why).

    rotate train-teacher --out runs/teacher --total-steps 30000000
    rotate train-teacher --backend warp --hand digit360 --out runs/teacher_gpu   # MuJoCo Warp + rsl_rl PPO on a GPU
    rotate train-teacher --resume runs/teacher/checkpoints/last.zip --total-steps 40000000   # the run's options
    tensorboard --logdir runs/teacher/tb

Writes checkpoints (`checkpoints/step_*.zip`, `checkpoints/last.zip`), `config.json`, TensorBoard logs, the training
curve `curves.jsonl` (flushed with each checkpoint) and the final policy bundle `bundle/` (weights + config, what
evaluation and deploy load). An `--out` holding another run is refused unless `--resume` continues it or
`--overwrite` replaces it; a resume takes the run's options the command line leaves out (and its folder as
`--out`), and refuses options that differ from the run's (but the length and speed ones) and a grasp cache
other than the file the run started from (config.json records its digest), and falls back from a damaged
checkpoint to the previous intact one. The bundle's card gives the run's training wall time over all its legs (each
checkpoint carries it) and, after a resume, the bundle the run started from (`started_from`). Ctrl-C / SIGTERM stop
at the next step, save the checkpoint, curves and bundle, and exit with status 130 / 143.
"""

from __future__ import annotations

import json
import signal
import time
from pathlib import Path

import torch
from stable_baselines3.common.callbacks import CallbackList

from envs.config import EnvConfig
from envs.errors import RequestRefused
from envs.sim_identity import sim_record
from rotation.configs import save_config, to_jsonable
from rotation.interrupt import SIGNAL_NAMES, Interrupted, StopSignals
from rotation.policy.bundle import PolicyBundle, load_policy_bundle
from rotation.runs import (
    GRASPS_KEY,
    CurveLog,
    check_owner,
    check_resume_record,
    check_run_dir,
    clear_outputs,
    config_differences,
    refuse_differences,
    run_id,
    run_record,
    wall_time_fields,
    with_fallback,
)
from rotation.train.ppo import (
    AdaptiveKLPPO,
    Checkpoints,
    EpisodeStats,
    build_model,
    checkpoint_options,
    load_checkpoint,
    older_checkpoints,
)
from rotation.train.teacher_config import (  # Config and config_from_args: what `rotate train-teacher` reads here
    PPO_OPTIONS,
    RESUMABLE_CHANGES,
    RUN_OUTPUTS,
    Config,
    config_from_args,  # noqa: F401
    obs_groups,
    run_dir_of,
)
from rotation.train.vec_env import RotateCupSB3VecEnv


def _role(cfg: Config) -> str:
    return "student" if cfg.student else "teacher"


STARTED_FROM = "started_from"
"""The key, in a resumed run's config.json and its bundle's card, of the bundle its first leg started from
(``--init-from``), which the resume's own options no longer name."""


def run(cfg: Config) -> PolicyBundle:
    """Train (or continue) the teacher. Everything is checked before anything is written: a folder holding another
    run, a resume whose options differ from the run's, a checkpoint of another program. Ctrl-C / SIGTERM stop at the
    next step, save the checkpoint, curves and bundle, then raise Interrupted (exit status 130 / 143)."""
    if cfg.backend == "warp":  # MuJoCo Warp worlds and a GPU-resident PPO (rotation.train.teacher_warp)
        from rotation.train.teacher_warp import train as train_warp

        return train_warp(cfg)
    out = cfg.out
    resume_dir = run_dir_of(cfg.resume) if cfg.resume is not None else None
    resuming_here = resume_dir is not None and resume_dir.resolve() == out.resolve()
    check_run_dir(out, RUN_OUTPUTS, overwrite=cfg.overwrite, resuming_here=resuming_here,
                  resume_hint=f"pass --resume {out / 'checkpoints' / 'last.zip'} to continue it")
    record = run_record(cfg)
    if cfg.resume is not None:
        if not cfg.resume.is_file():
            raise RequestRefused(f"--resume {cfg.resume}: no such checkpoint")
        saved = resume_dir / "config.json" if resume_dir is not None else None
        if saved is not None and saved.is_file():
            saved_record = json.loads(saved.read_text())
            check_resume_record(saved_record, record, str(saved), RESUMABLE_CHANGES)
            # the bundle the run started from stays in its record across resumes (a resume has no --init-from)
            started_from = saved_record.get(STARTED_FROM) or saved_record.get("init_from")
            if started_from:
                record[STARTED_FROM] = started_from
    torch.set_num_threads(cfg.torch_threads)
    torch.manual_seed(cfg.seed)
    env_cfg = cfg.env_config()
    env = RotateCupSB3VecEnv(env_cfg, cfg.num_envs, seed=cfg.seed, reward_scale=cfg.reward_scale,
                             obs_groups=obs_groups(cfg), latent_mix=cfg.latent_mix)
    owner = run_id(out, create=False) if resuming_here else None  # RequestRefused for an unreadable run.json
    try:
        resumed_from = None
        if cfg.resume is not None:
            model, resumed_from = with_fallback(cfg.resume, older_checkpoints(cfg.resume),
                                                lambda p: load_checkpoint(p, env, cfg.device))
            # the checkpoint must be one its run folder wrote (a folder from before run ids: any, as before)
            check_owner(resumed_from, run_id(resume_dir, create=False) if resume_dir is not None else None)
            differences = config_differences(checkpoint_options(model), {k: record[k] for k in PPO_OPTIONS}, ())
            refuse_differences(differences, f"recorded in {resumed_from}", RESUMABLE_CHANGES)
            env.seed(cfg.seed + model.num_timesteps)  # fresh, reproducible episodes after a resume
            model.tensorboard_log = str(cfg.out / "tb")  # the checkpoint remembers the folder it was saved from
        else:
            model = build_model(cfg, env)
        model.overlap = cfg.overlap
        if cfg.freeze_encoder:  # (a resumed model is rebuilt with every parameter trainable)
            for p in model.policy.features_extractor.encoder.parameters():
                p.requires_grad_(False)
        # every check passed: only now is anything in `out` written or deleted
        if cfg.overwrite and not resuming_here:
            removed = clear_outputs(out, RUN_OUTPUTS)
            if removed:
                print(f"{_role(cfg)}: --overwrite deleted {', '.join(removed)} in {out}")
        out.mkdir(parents=True, exist_ok=True)
        owner = run_id(out, create=not resuming_here or owner is not None)  # a run from before run ids stays one
        save_config(record, out / "config.json")
        curves = CurveLog(out / "curves.jsonl")
        if resuming_here and (dropped := curves.trim(model.num_timesteps)):
            print(f"{_role(cfg)}: dropped {dropped} curve rows logged after step {model.num_timesteps} (not in the "
                  "checkpoint resumed from)")
        provenance = {k: record[k] for k in (GRASPS_KEY, STARTED_FROM) if k in record}
        return _train(cfg, model, env, env_cfg, curves, resumed_from, provenance, owner)
    finally:
        env.close()


def _train(cfg: Config, model: AdaptiveKLPPO, env: RotateCupSB3VecEnv, env_cfg: EnvConfig, curves: CurveLog,
           resumed_from: Path | None, provenance: dict[str, str], owner: str | None = None) -> PolicyBundle:
    stats = EpisodeStats()
    # the earlier legs' training time, from the checkpoint resumed (None: one saved before checkpoints kept it)
    wall_before = getattr(model, "train_wall_s", None) if resumed_from is not None else 0.0
    with StopSignals() as stop:
        ckpt = Checkpoints(cfg.out / "checkpoints", cfg.checkpoint_every, stats, curves, stop, owner, wall_before)
        remaining = cfg.total_steps - model.num_timesteps
        signum = None
        if remaining > 0:
            try:
                model.learn(remaining, callback=CallbackList([stats, ckpt]), progress_bar=cfg.progress,
                            reset_num_timesteps=cfg.resume is None, tb_log_name=_role(cfg))
            except KeyboardInterrupt as err:  # a second signal, or Ctrl-C where no handler could be installed
                signum = getattr(err, "signum", signal.SIGINT)
        signum = signum or stop.signum
        wall = time.time() - ckpt.started  # this leg's
        # the checkpoint, curves and bundle are written whether training finished or was stopped
        ckpt.model = model
        ckpt.num_timesteps = model.num_timesteps
        ckpt.save()
        steps = int(model.num_timesteps)
        # the run's config as it loads back (a None stays null: adapters.session_checks.teacher_randomization reads it)
        card = {"role": _role(cfg), "object": cfg.object, "steps": steps, "seed": cfg.seed,
                **wall_time_fields(wall, ckpt.model.train_wall_s, resumed_from is not None),
                "train_config": to_jsonable(cfg)}
        card.update(provenance)  # the grasp cache's digest (its path alone does not show a regenerated file); the
        # bundle the run started from, where a resume's own config no longer names it
        if resumed_from is not None:
            card["resumed_from"] = str(resumed_from)
        if cfg.student:  # what the fine-tune started from: the distilled student's own card (teacher, distillation)
            card["finetuned_from"] = {"bundle": cfg.student, "card": load_policy_bundle(cfg.student).config.card}
        if signum:
            card["interrupted"] = f"stopped by {SIGNAL_NAMES.get(signum, signum)} at {steps} of {cfg.total_steps} steps"
        bundle = PolicyBundle.from_sb3(model, control_hz=env_cfg.control_hz, action_scale=env_cfg.action_scale,
                                       card=card, sim=sim_record(env_cfg))
        bundle.save(cfg.out / "bundle")
    last = cfg.out / "checkpoints" / "last.zip"
    if signum:
        message = (f"{_role(cfg)}: interrupted by {SIGNAL_NAMES.get(signum, signum)} at {steps} of {cfg.total_steps} "
                   f"steps; saved {last} and the bundle {cfg.out / 'bundle'}; continue with --resume {last}")
        print(message)
        raise Interrupted(signum, message)
    print(f"{_role(cfg)}: {steps} steps in {wall:.0f} s; bundle at {cfg.out / 'bundle'}")
    return bundle
