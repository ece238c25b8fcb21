"""Fine-tune a tactile adapter (`rotate finetune-adapter`) in simulation or on recorded sessions: regress the frozen
teacher's z.

The student, the touch encoder and the teacher stay frozen; only the adapter learns, on

    MSE(phi(history) + adapter(tokens, phi(history)), z_teacher(priv))

optionally plus ``action_weight`` x the MSE between the frozen student actor's action mean on that latent and on
z_teacher (same proprioception: the action the student would take knowing the teacher's z), over the student's own
rollouts (DAgger): for the first ``student_steps`` env steps the student acts alone, then
the student with the adapter's current correction, so the adapter learns on the states its own corrections lead
to. The env simulates the Digit 360 fingertips under a randomization that emphasizes low friction and heavy
objects. Every ``touch_every`` control steps (the adapter's refresh period, as at run time) the fingertip windows
of every env are rendered and encoded once by the frozen encoder; the tokens (float16), phi's latent and the
teacher's z go to an in-memory buffer (the cached embeddings) from which ``updates`` Adam steps draw minibatches,
so each encoder pass feeds many gradient steps.

    rotate finetune-adapter --student student --teacher teacher --encoder sparshx-tinier-sim --out runs/adapter
    rotate finetune-adapter --out runs/adapter --resume          # continue where it stopped

Exact resume: as in train-student, training is cut into checkpoint intervals that each start from fresh env
resets and an empty buffer, so a resumed run is bit-identical to an uninterrupted one. Ctrl-C / SIGTERM stop after
the current step, save a checkpoint and the adapter bundle (exit status 130 / 143).

The config is adapters.finetune.config, what the paths share adapters.finetune.core. The simulation loop is
adapters.finetune.sim. With ``--sessions`` it trains on recorded sessions instead
(adapters.finetune.sessions; the procedure: docs/adapter.md, "Fine-tuning on your own hand"): sessions of the hand
recorded by ``rotate deploy`` with the measured object properties give the student's observations, the fingertip
windows and the teacher's z (adapters.real_data); the windows are encoded once into the same buffer, then
``epochs`` passes of Adam steps train the adapter, with a held-out share of the sessions for validation::

    rotate finetune-adapter --sessions sessions/ --modalities imu,pressure --out runs/adapter_lab

With ``--refit-head`` (adapters.finetune.refit) it trains nothing by gradient: it rolls an ``--init-from`` adapter out
and solves its last, linear layer in closed form (ridge regression on its own hidden features, the strength chosen
by cross-validation over whole episodes)::

    rotate finetune-adapter --init-from rotation/policies/adapter/members/all_modalities --refit-head \\
        --total-steps 76800 --out runs/adapter_refit
"""

from __future__ import annotations

from adapters.finetune.config import Config, config_from_args  # noqa: F401 (what `rotate finetune-adapter` reads here)
from adapters.finetune.core import Job, Result


def run(cfg: Config) -> Result:
    """Fine-tune the adapter, in simulation or (``cfg.sessions``) on recorded sessions; returns the bundle directory
    and the logged history. Everything is checked before anything in `out` is written."""
    job = Job.start_from(cfg)
    if cfg.sessions:
        from adapters.finetune.sessions import train_on_sessions

        return train_on_sessions(job)
    if cfg.refit_head:
        from adapters.finetune.refit import refit_in_sim

        return refit_in_sim(job)
    from adapters.finetune.sim import train_in_sim

    return train_in_sim(job)
