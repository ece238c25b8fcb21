"""PD loop rate and jitter of the Allegro driver against the emulated hand over a virtual CAN bus.

    .venv/bin/python scripts/bench_deploy.py                      # 10 s, SCHED_FIFO 10 if permitted
    .venv/bin/python scripts/bench_deploy.py --duration-s 3 --rt-priority 0

A policy thread commands a slow sine around the home pose at 20 Hz (as ``rotate deploy`` would) while the
driver runs its PD loop on the emulator's 3 ms position stream. Rate = completed PD cycles per second after
the warm-up; jitter = |cycle period - median period|. Prints a table, then as its LAST line one JSON object
(``pd_hz``, ``pd_jitter_p50_ms``, ``pd_jitter_p99_ms``, ...). Targets: pd_hz >= 300, p99 jitter < 1 ms.

Then the policy loop: ``rotate deploy --hand sim-allegro`` (rotation.deploy.job) with a policy bundle (the shipped
student, or a randomly initialised student when none ships: inference cost is the same) for
``policy_duration_s``; its step-start jitter |step period - 1 / control_hz| goes into the same JSON
(``policy_hz``, ``policy_jitter_p50_ms``, ``policy_jitter_p99_ms``, ``policy_late_steps``, ...).
"""

from __future__ import annotations

import contextlib
import io
import json
import logging
import tempfile
import time
from dataclasses import dataclass
from typing import Literal

import numpy as np

from rotation.configs import script_main
from rotation.hardware.allegro.driver import AllegroConfig, AllegroHand
from rotation.hardware.hand import JOINT_LOWER, JOINT_UPPER
from rotation.hardware.realtime import set_realtime_priority
from rotation.sim_hardware.allegro_emulator import AllegroEmulator


@dataclass(frozen=True)
class Config:
    duration_s: float = 10.0
    """Measured time (s), after the warm-up."""
    warmup_s: float = 1.0
    """Time (s) discarded at the start."""
    transport: Literal["virtual", "slcan"] = "virtual"
    """Emulated bus: python-can virtual bus, or the SLCAN adapter on a pty."""
    rt_priority: int = 10
    """SCHED_FIFO priority of the emulator and driver threads (0: normal scheduling)."""
    command_hz: float = 20.0
    """Rate of set_targets calls (the policy rate)."""
    policy: str = ""
    """Bundle for the policy-loop measurement (directory or shipped name); empty: the shipped student if present,
    else a randomly initialised student."""
    policy_duration_s: float | None = None
    """Length (s) of the policy-loop measurement (``rotate deploy --hand sim-allegro``); None: ``duration_s``."""

    def __post_init__(self) -> None:
        if not self.duration_s > 0 or self.warmup_s < 0 or not self.command_hz > 0:
            raise ValueError("duration_s and command_hz must be > 0, warmup_s >= 0")


def run(cfg: Config) -> dict:
    sched = set_realtime_priority(cfg.rt_priority)
    mid = 0.5 * (np.asarray(JOINT_LOWER) + np.asarray(JOINT_UPPER))
    with AllegroEmulator(transport=cfg.transport) as emu, AllegroHand(emu.spec, AllegroConfig()) as hand:
        t0 = time.monotonic()
        q0 = hand.read_state().q
        while (now := time.monotonic()) - t0 < cfg.warmup_s + cfg.duration_s:
            phase = np.sin(2 * np.pi * 0.5 * (now - t0))
            hand.set_targets(q0 + 0.1 * phase * np.sign(mid - q0))
            time.sleep(1.0 / cfg.command_hz)
        times = hand.cycle_times()
        stats = hand.stats()
        overruns = emu.overruns
    times = times[times >= t0 + cfg.warmup_s]
    periods = np.diff(times)
    jitter = np.abs(periods - np.median(periods))
    result = {
        "pd_hz": float(len(periods) / (times[-1] - times[0])),
        "pd_period_p50_ms": float(1e3 * np.median(periods)),
        "pd_period_max_ms": float(1e3 * periods.max()),
        "pd_jitter_p50_ms": float(1e3 * np.percentile(jitter, 50)),
        "pd_jitter_p99_ms": float(1e3 * np.percentile(jitter, 99)),
        "cycles": int(len(periods)),
        "incomplete_cycles": stats["incomplete_cycles"],
        "send_errors": stats["send_errors"],
        "emulator_overruns": overruns,
        "transport": cfg.transport,
        "sched": sched,
        "duration_s": cfg.duration_s,
        **policy_loop(cfg),
    }
    width = max(len(k) for k in result)
    print(f"{'metric':<{width}}  value")
    for k, v in result.items():
        print(f"{k:<{width}}  {v:.3f}" if isinstance(v, float) else f"{k:<{width}}  {v}")
    print(json.dumps(result))
    return result


def policy_loop(cfg: Config) -> dict:
    """Policy-loop rate and jitter of ``rotate deploy`` on the emulated Allegro (virtual CAN), with a bundle."""
    from rotation.deploy.config import Config as DeployConfig
    from rotation.deploy.job import run as deploy
    from rotation.policy.bundle import PolicyBundle, shipped_bundles
    from rotation.policy.bundle_config import BundleConfig

    duration = cfg.duration_s if cfg.policy_duration_s is None else cfg.policy_duration_s
    with tempfile.TemporaryDirectory() as tmp:
        policy = cfg.policy or ("student" if "student" in shipped_bundles() else
                                str(PolicyBundle(BundleConfig(latent_source="adaptation")).save(f"{tmp}/student")))
        with contextlib.redirect_stdout(io.StringIO()):  # deploy prints its own JSON summary; ours is the last line
            summary = deploy(DeployConfig(hand="sim-allegro", policy=policy, duration=duration,
                                          status_every_s=max(duration, 1.0)))
    return {
        "policy_hz": summary["loop_hz"],
        "policy_jitter_p50_ms": summary["jitter_p50_ms"],
        "policy_jitter_p99_ms": summary["jitter_p99_ms"],
        "policy_late_steps": summary["late_steps"],
        "policy_held_steps": summary["held_steps"],
        "policy_steps": summary["steps"],
        "policy_fault": summary["fault"],
        "policy_bundle": cfg.policy or ("student" if policy == "student" else "random-init student"),
    }


def main(argv: list[str] | None = None) -> int:
    logging.basicConfig(level=logging.WARNING, format="%(levelname)s %(name)s: %(message)s")
    return script_main(Config, run, __doc__, argv)


if __name__ == "__main__":
    raise SystemExit(main())
