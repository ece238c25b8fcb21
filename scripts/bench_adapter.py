"""Benchmark: one control step of the student with the tactile adapter on the CPU, from raw fingertip windows.

A touch step is what the policy does when its touch correction is refreshed: the four fingertips' raw windows as
the Digit 360 reader gives them (image frames uint8 (2, 224, 224, 3), audio int16 (2, 27000), IMU (224, 3) g,
pressure (224, 1) hPa; random values, the cost does not depend on them) go through the encoder's preprocessing
(the audio filterbank included) and the frozen tinier Sparsh-X encoder in one batch of four, then the adapter,
then the student acts with the corrected latent. Between refreshes (``touch_every`` steps) the policy is the
student with a held correction.

Figures (medians over ``iters`` timed calls after 2 untimed ones, ``threads`` torch threads, torch.inference_mode):

- ``step_ms``: a touch step with every modality (image, audio, IMU, pressure); the target is under 50 ms on 2 cores;
- ``step_img_ms``: the same with the image-only adapter;
- ``step_imu_pressure_ms``: the same with an IMU + pressure adapter (the streams deploy reads from a real Digit 360);
- ``student_ms``: a step of the student alone (what the steps between refreshes cost);
- ``amortized_ms``: the mean step cost at the adapter's refresh period, (step + (touch_every - 1) x student) /
  touch_every.

With ``--deploy S`` it then measures the touch path's latency where it happens: an S-second ``rotate deploy
--hand sim-allegro`` of the adapter (the given one, else the shipped ``adapter`` where one ships, else the fresh
every-modality adapter of ``step_ms``) with emulated fingertips, in its own process at 20 Hz (the emulated hand and
sensors share the cores, as a lab's machine shares them with its drivers). From its summary:

- ``latency_ms_p50`` / ``latency_ms_p95``: each correction's touch age at its first action, from the newest sensor
  sample of the oldest fingertip window it read to that step's command to the hand;
- ``age_ms_p50`` / ``age_ms_p95``: the touch age of every step acted with a correction (held between refreshes);
- ``read_age_ms_p50``: how old the touch was when the worker had read it (the sensors' and the link's share);
- ``read_ms_p50`` / ``encode_ms_p50`` / ``encode_ms_p95``: a refresh's reading of the windows and its encoding;
- ``delay_steps``: corrections by control steps from the step whose refresh read them to their first step, and
  ``delay_spec``, the same as ``--touch-delay`` text;
- ``delay_steps_no_render`` / ``delay_spec_no_render``: the same had reading the windows cost nothing. An emulated
  fingertip renders its image and audio when its window is read (hundreds of ms for four on 2 cores), a real one
  hands over slices of what its camera and microphones streamed: this is the delay a real hand meets, and what
  adapters.touch_delay.MEASURED_TABLE holds.

The last line printed is a JSON object with every figure.

    python scripts/bench_adapter.py
    python scripts/bench_adapter.py --threads 1 --iters 30 --adapter runs/adapter/bundle
    python scripts/bench_adapter.py --adapter runs/ensemble        # an adapter ensemble (adapters.ensemble)
    python scripts/bench_adapter.py --deploy 60                     # and the latency in an emulated deploy
"""

from __future__ import annotations

import json
import os
import statistics
import subprocess
import sys
import tempfile
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch

from rotation.configs import script_main


@dataclass
class Config:
    """Benchmark settings."""

    adapter: str = ""
    """An adapter bundle or adapter ensemble to time (its student, encoders and modalities); empty: fresh adapters
    for the shipped student and encoder (the cost is the same as a trained one's)."""
    encoder: str = "sparshx-tinier-sim"
    """Encoder of the fresh adapters."""
    threads: int = 2
    """torch intra-op threads."""
    iters: int = 20
    """Timed calls per figure."""
    touch_every: int = 4
    """Refresh period for ``amortized_ms`` (a given adapter bundle's own period overrides it)."""
    seed: int = 0
    """Seed of the random windows and observations."""
    deploy: float = 0.0
    """Seconds of an emulated deploy to measure the touch path's latency in (0: none; see the module docstring)."""


def raw_windows(fingers: tuple[str, ...], rng: np.random.Generator) -> dict[str, dict[str, np.ndarray]]:
    """One batch-of-one raw window per fingertip, shaped as rotation.hardware.digit360.reader's ``window()``
    returns it."""
    return {f: {"image": rng.integers(0, 256, (1, 2, 224, 224, 3), dtype=np.uint8),
                "audio_wave": rng.integers(-2000, 2000, (1, 2, 27000), dtype=np.int16),
                "imu": rng.normal(0.0, 0.05, (1, 224, 3)).astype(np.float32) + np.float32([0, 0, 1]),
                "pressure": (1000.0 + rng.gamma(2.0, 5.0, (1, 224, 1))).astype(np.float32)} for f in fingers}


def _median_ms(fn, iters: int) -> float:
    for _ in range(2):
        fn()
    times = []
    for _ in range(iters):
        t = time.perf_counter()
        fn()
        times.append(1e3 * (time.perf_counter() - t))
    return statistics.median(times)


def run(cfg: Config) -> dict:
    from adapters.bundle import build_adapted
    from rotation.bundles import load_bundle
    from rotation.policy.bundle import shipped_bundles

    if cfg.threads < 1 or cfg.iters < 1 or cfg.touch_every < 1:
        raise ValueError(f"threads, iters and touch_every must be >= 1, got {cfg}")
    if not 0 <= cfg.deploy <= 3600:
        raise ValueError(f"deploy must be 0-3600 s (0: no deploy), got {cfg.deploy}")
    torch.set_num_threads(cfg.threads)
    load_before = os.getloadavg()[0]
    rng = np.random.default_rng(cfg.seed)
    if cfg.adapter:
        policies = {"step_ms": load_bundle(cfg.adapter)}
        if not getattr(policies["step_ms"], "touch_every", 0):
            raise ValueError(f"--adapter {cfg.adapter}: not a tactile adapter or adapter ensemble (it reads no touch)")
    else:
        policies = {"step_ms": build_adapted("student", cfg.encoder, ("img", "mic", "imu", "pressure")),
                    "step_img_ms": build_adapted("student", cfg.encoder, ("img",)),
                    "step_imu_pressure_ms": build_adapted("student", cfg.encoder, ("imu", "pressure"))}
    first = next(iter(policies.values()))
    touch_every = first.touch_every if cfg.adapter else cfg.touch_every
    obs = {k: rng.normal(0.0, 0.3, (1, *shape)).astype(np.float32) for k, shape in first.config.obs_groups.items()}
    result: dict = {}
    with torch.inference_mode():
        for name, policy in policies.items():
            raw = raw_windows(policy.fingers, rng)
            windows = {f: {k: v for k, v in w.items() if k.replace("_wave", "") in policy.windows}
                       for f, w in raw.items()}

            def touch_step(policy=policy, windows=windows) -> None:
                policy.act_batch(obs, correction=policy.correction(windows, obs))

            result[name] = round(_median_ms(touch_step, cfg.iters), 2)
            print(f"touch step, {'+'.join(policy.windows)}, 4 fingertips, {cfg.threads} thread(s): "
                  f"{result[name]:.1f} ms (median of {cfg.iters})")
        result["student_ms"] = round(_median_ms(lambda: first.act_batch(obs), cfg.iters), 3)
    result["touch_every"] = touch_every
    result["amortized_ms"] = round((result["step_ms"] + (touch_every - 1) * result["student_ms"]) / touch_every, 2)
    result["threads"] = cfg.threads
    result["loadavg_1min_before"] = round(load_before, 2)
    if cfg.deploy > 0:
        with tempfile.TemporaryDirectory() as tmp:
            if cfg.adapter or "adapter" in shipped_bundles():
                adapter = cfg.adapter or "adapter"
            else:  # no adapter ships (withdrawn until retrained on the current hand model): the fresh one timed above
                adapter = str(first.save(Path(tmp) / "adapter"))
            result.update(deploy_latency(adapter, cfg.deploy))
    print(json.dumps(result))
    return result


def deploy_latency(adapter: str, seconds: float) -> dict:
    """The touch latency figures of an emulated ``rotate deploy`` of ``adapter`` (module docstring)."""
    from adapters.touch_delay import delay_spec, parse_delay

    command = [sys.executable, "-m", "rotation.cli", "deploy", "--hand", "sim-allegro", "--policy", adapter,
               "--duration", f"{seconds:g}", "--status-every-s", "1000"]
    print("deploy:", " ".join(command[2:]), flush=True)
    done = subprocess.run(command, capture_output=True, text=True, check=False)
    try:
        summary = json.loads(done.stdout.strip().splitlines()[-1])
    except (IndexError, json.JSONDecodeError):
        raise RuntimeError(f"the emulated deploy printed no summary (exit {done.returncode}): "
                           f"{done.stderr.strip()[-2000:]}") from None
    touch = summary.get("touch") or {}
    steps = touch.get("first_use_steps") or {}
    if not steps:
        raise RuntimeError(f"the emulated deploy's adapter never acted (fault: {summary.get('fault')}; touch: {touch})")
    def spec_of(counts: dict) -> str:
        return delay_spec(parse_delay(",".join(f"{k}:{v}" for k, v in counts.items())))

    spec, no_render = spec_of(steps), touch["first_use_steps_no_render"]
    figures = {"deploy_s": seconds, "deploy_fault": summary.get("fault"), "deploy_late_steps": summary["late_steps"],
               "latency_ms_p50": touch["first_use_age_ms_p50"], "latency_ms_p95": touch["first_use_age_ms_p95"],
               "age_ms_p50": touch["age_ms_p50"], "age_ms_p95": touch["age_ms_p95"],
               "read_age_ms_p50": touch["read_age_ms_p50"], "refresh_ms_p50": touch["refresh_ms_p50"],
               "read_ms_p50": touch["read_ms_p50"], "encode_ms_p50": touch["encode_ms_p50"],
               "encode_ms_p95": touch["encode_ms_p95"], "delay_steps": steps, "delay_spec": spec,
               "delay_steps_no_render": no_render, "delay_spec_no_render": spec_of(no_render)}
    print(f"touch latency in deploy ({seconds:g} s, {sum(steps.values())} corrections): median "
          f"{figures['latency_ms_p50']:.0f} ms, p95 {figures['latency_ms_p95']:.0f} ms; --touch-delay {spec}; "
          f"without the emulated sensors' rendering (a real hand): --touch-delay {figures['delay_spec_no_render']}")
    return {k: round(v, 2) if isinstance(v, float) else v for k, v in figures.items()}


def main(argv: list[str] | None = None) -> int:
    return script_main(Config, run, __doc__, argv)


if __name__ == "__main__":
    raise SystemExit(main())
