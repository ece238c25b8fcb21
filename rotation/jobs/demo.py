"""The end-to-end demo on the shipped defaults: what `make demo` runs.

1. loads the shipped teacher and student bundles (trained by `rotate train-teacher` / `rotate train-student`,
   model cards beside them in rotation/policies/),
2. evaluates both on the cup under nominal conditions, reduced friction and added mass (same seeds for both),
3. with a shipped tactile adapter (rotation/policies/adapter): evaluates student vs student + adapter with the
   simulated Digit 360 fingertips on (``adapter_conditions``; touch costs tens of ms per fingertip, so fewer),
4. renders a video of the student rotating the cup,
5. dry-runs deploy on the emulated Allegro hand (the real CAN driver against a MuJoCo-backed emulator) with the
   shipped adapter, which starts the emulated Digit 360 fingertips itself (the student when no adapter is shipped),
6. writes OUT/README.md with the tables, plots, video and deploy summary.

    rotate demo --out demo_out
    rotate demo --out demo_out --episodes 16 --conditions nominal friction_0.35 mass_+0.1kg
"""

from __future__ import annotations

import json
import sys
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from envs.errors import RequestRefused
from envs.validation import check_int, check_number, check_output_dir, check_seed, check_types
from rotation.bundles import load_bundle
from rotation.evaluate import finished
from rotation.evaluate import job as evaluate_job
from rotation.evaluate.suites import get_suite
from rotation.jobs import view as view_job
from rotation.policy.bundle import shipped_bundles


@dataclass
class Config:
    out: Path = Path("demo_out")
    """Report directory."""
    episodes: int = 8
    """Episodes per policy and condition (20 s each)."""
    conditions: tuple[str, ...] = ("nominal", "friction_0.5", "mass_+0.1kg", "friction_0.5+mass_+0.1kg")
    """Conditions of the `perturbations` suite to run (see `rotate evaluate --help`)."""
    seed: int = 0
    """Evaluation seed (episode j of every condition is seeded seed + j)."""
    adapter_conditions: tuple[str, ...] = ("friction_0.5+mass_+0.1kg",)
    """Conditions of the student vs adapter evaluation (when an adapter is shipped); `none` skips it."""
    video_steps: int = 300
    """Policy steps in the student video (20 per second)."""
    deploy_seconds: float = 5.0
    """Length of the deploy dry run on the emulated Allegro hand (0 skips it)."""

    def __post_init__(self) -> None:
        check_types(self)
        self.out = Path(self.out)
        check_output_dir("out", self.out)
        check_int("episodes", self.episodes, 1, 10_000)
        try:
            get_suite("perturbations", self.conditions)
        except ValueError as err:  # it lists the suite's conditions
            raise ValueError(f"conditions: {err}") from None
        if self.adapter_suite:
            try:
                get_suite("perturbations", self.adapter_suite)
            except ValueError as err:
                raise ValueError(f"adapter_conditions: {err}") from None
        check_seed("seed", self.seed)
        check_int("video_steps", self.video_steps, 1, 100_000)
        check_number("deploy_seconds", self.deploy_seconds, 0.0, 3600.0, unit="s")

    @property
    def adapter_suite(self) -> tuple[str, ...]:
        """The conditions of the adapter evaluation: none when `none` (or nothing) is given."""
        return () if self.adapter_conditions == ("none",) else self.adapter_conditions


def run(cfg: Config) -> dict[str, Any]:
    """Run the demo; returns ``{"report": path, "exit_code": status}``: the status is the deploy dry run's (0 when
    it completed or was skipped, non-zero when it faulted or was stopped), so `rotate demo` fails with it."""
    start = time.time()
    shipped = shipped_bundles()
    missing = [name for name in ("teacher", "student") if name not in shipped]
    if missing:
        raise RequestRefused(f"the demo runs the shipped teacher and student, and this installation ships no "
                             f"{' and no '.join(missing)} bundle (rotation/policies/); reinstall the package")
    bundles = {name: load_bundle(name) for name in ("teacher", "student")}
    cfg.out.mkdir(parents=True, exist_ok=True)
    for name, bundle in bundles.items():
        card = bundle.config.card  # teacher cards: steps/object; student cards: env_steps and their env config
        steps = card.get("steps", card.get("env_steps", "?"))
        obj = card.get("object", card.get("config", {}).get("env", {}).get("object", "?"))
        print(f"[demo] {name}: trained {steps} steps on {obj} ({bundle.config.latent_source} latent; model card "
              f"in rotation/policies/{name}/MODEL_CARD.md)")

    print("[demo] evaluating teacher vs student under perturbations")
    eval_dir = cfg.out / "evaluation"
    eval_cfg = evaluate_job.Config(
        policies={"teacher": "teacher", "student": "student"}, suite="perturbations", conditions=cfg.conditions,
        episodes=cfg.episodes, num_envs=cfg.episodes, seed=cfg.seed, out=eval_dir)
    try:
        finished.check_out(eval_dir, finished.identity(eval_cfg, evaluate_job.policy_paths(eval_cfg)), False)
    except ValueError:  # an earlier demo's evaluation of other policies or settings: keep it aside, start anew
        kept = eval_dir.with_name(f"evaluation.{time.strftime('%Y%m%d-%H%M%S')}")
        eval_dir.rename(kept)
        print(f"[demo] the earlier demo evaluation (other policies or settings) is kept in {kept}")
    rows = evaluate_job.run(eval_cfg)

    adapter = "adapter" in shipped
    adapter_dir = cfg.out / "evaluation_adapter"
    if adapter and cfg.adapter_suite:
        print("[demo] evaluating student vs student + tactile adapter (simulated Digit 360 on)")
        adapter_cfg = evaluate_job.Config(
            policies={"student": "student", "adapter": "adapter"}, suite="perturbations",
            conditions=cfg.adapter_suite, episodes=cfg.episodes, num_envs=cfg.episodes, seed=cfg.seed,
            out=adapter_dir, torch_threads=2)
        try:
            finished.check_out(adapter_dir, finished.identity(adapter_cfg, evaluate_job.policy_paths(adapter_cfg)),
                               False)
        except ValueError:  # an earlier demo's adapter evaluation (another adapter or settings): kept aside
            if adapter_dir.exists():
                kept = adapter_dir.with_name(f"evaluation_adapter.{time.strftime('%Y%m%d-%H%M%S')}")
                adapter_dir.rename(kept)
                print(f"[demo] the earlier adapter evaluation is kept in {kept}")
        evaluate_job.run(adapter_cfg)

    print("[demo] rendering the student rotating the cup")
    video = view_job.run(view_job.Config(out=cfg.out / "student_cup.mp4", object="cup", policy="student",
                                         steps=cfg.video_steps, seed=cfg.seed, width=400, height=400))

    deploy_summary = None
    if cfg.deploy_seconds > 0:
        deploy_policy = "adapter" if adapter else "student"
        print(f"[demo] deploy dry run on the emulated Allegro hand ({deploy_policy})")
        from rotation.deploy import job as deploy_job

        deploy_summary = deploy_job.run(deploy_job.Config(
            hand="sim-allegro", policy=deploy_policy, duration=cfg.deploy_seconds,
            record=str(cfg.out / "deploy_session.h5"), overwrite=True))
    exit_code = int(deploy_summary["exit_code"]) if deploy_summary is not None else 0

    lines = ["# Demo report", "", f"Made by `rotate demo` in {time.time() - start:.0f} s.", "",
             "## Teacher vs student under perturbations", "",
             *[line for line in (eval_dir / "results.md").read_text().strip().splitlines()
               if not line.startswith("# ")], "",
             "Plots: " + ", ".join(f"[{p.stem}](evaluation/plots/{p.name})"
                                   for p in sorted((eval_dir / "plots").glob("*.png"))), "",
             ]
    if (adapter_dir / "results.md").is_file() and adapter and cfg.adapter_suite:
        lines += ["## Student vs student + tactile adapter", "",
                  *[line for line in (adapter_dir / "results.md").read_text().strip().splitlines()
                    if not line.startswith("# ")], "",
                  "Bar charts: [bars](evaluation_adapter/plots/bars.png); the adapter's model card: "
                  "rotation/policies/adapter/MODEL_CARD.md", ""]
    lines += ["## Student rotating the cup", "", f"[{video.name}]({video.name})", ""]
    if deploy_summary is not None:
        outcome = ("completed" if exit_code == 0 else
                   f"**FAILED** (exit status {exit_code}): {deploy_summary.get('fault') or 'motors not confirmed off'}")
        lines += [f"## Deploy dry run (emulated Allegro over CAN; {deploy_policy})", "", f"Result: {outcome}", "",
                  "```",
                  json.dumps(deploy_summary, indent=2, default=str), "```", ""]
    report = cfg.out / "README.md"
    report.write_text("\n".join(lines))
    nominal = [r for r in rows if r["condition"] == "nominal"]
    for r in nominal:
        print(f"[demo] nominal {r['policy']}: rotation_rate {r['rotation_rate']:+.3f} rad/s, ttf {r['ttf']:.2f}")
    print(f"[demo] report: {report}")
    if exit_code != 0:
        # the report is written either way; the status says the demo did not do all it should
        print(f"[demo] the deploy dry run did not complete (exit status {exit_code}): "
              f"{deploy_summary.get('fault') if deploy_summary else ''}", file=sys.stderr)
    return {"report": str(report), "exit_code": exit_code}
