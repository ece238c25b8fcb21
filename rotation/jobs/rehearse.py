"""Rehearse the lab's whole workflow on emulated hardware: record labelled sessions of two objects, fine-tune the
tactile adapter on them, deploy the result, with realistic faults on the way; then one page of what happened.

    rotate rehearse --out runs/rehearsal                 # about 3 min: 20 s sessions, 30 epochs
    rotate rehearse --out runs/rehearsal_tiny --tiny     # about 1 min: 5 s sessions, 3 epochs (what CI runs)

The emulated Allegro (or LEAP) speaks its real bus protocol to the real driver, the emulated Digit 360 fingertips
their real serial protocol, everything at the real rates (the hand at 333 Hz, the fingertips at 400 Hz, the policy
at 20 Hz), so each step is the command a lab runs on its own hand (the page lists them). The steps:

1. object cards (objects/): a nominal cup and a slippery, heavy one, with the values the emulator simulates;
2. `rotate record` of the cup; its index fingertip sends corrupt frames, then its thumb is unplugged;
3. `rotate record` of the slippery cup; the hand's joint feedback stops once for 60 ms (LEAP: 30 ms), under the
   drivers' 100 ms limit;
4. `rotate record` of the slippery cup again; the hand reports an error on its bus: the motors go off, the run ends,
   the session is kept up to there (the page says whether it can still train the adapter);
5. `rotate finetune-adapter --sessions` on every usable session (windows: IMU and pressure, which emulated fingertips
   record; a real Digit 360 with --record-media adds the image and the audio);
6. `rotate deploy` of the fine-tuned adapter holding the slippery cup; its middle fingertip is unplugged half way,
   and the student acts alone where touch is missing.

Each step's log is in logs/; the page (also REHEARSAL.md in --out) gives each step's outcome against what it was
meant to show, and where each output is. Exit status 0 when every step behaved as documented (the bus error ending
its run included), 1 otherwise (the page says which step did not); a machine too loaded to hold 20 Hz ends a
run with that fault, which the page reports as such.
"""

from __future__ import annotations

import contextlib
import json
import logging
import shutil
import sys
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Literal

from envs.validation import check_int, check_number, check_output_dir, check_types

FINGERS_UNPLUGGED = {"record": "thumb", "deploy": "middle"}
LATE_S = {"sim-allegro": 0.06, "sim-leap": 0.03}
"""The joint feedback pause of the second session (s), per hand: below the drivers' 0.1 s feedback timeout with
room for what each adds (the LEAP's reads time out and retry after the replies come back: a 60 ms pause was a 92 ms
wait there)."""
SLIPPERY = {"mass": 0.2, "friction": 0.4, "com": [0.0, 0.0, 0.008]}
"""The second object: slippery (friction 0.4 against the nominal 1.0) and heavy (0.2 kg against 0.08 kg), inside the
teacher's training ranges (envs.config: friction 0.3-3.0, mass 0.01-0.25 kg, com +-1 cm)."""


@dataclass(frozen=True)
class Config:
    out: Path = Path("runs/rehearsal")
    """Folder of the rehearsal's outputs (object cards, sessions, adapter, deploy recording, logs, REHEARSAL.md);
    must not exist or be empty (--overwrite replaces an earlier rehearsal's)."""
    hand: Literal["sim-allegro", "sim-leap"] = "sim-allegro"
    """The emulated hand."""
    policy: str = "student"
    """The student the lab runs (a bundle directory or a shipped name)."""
    seconds: float = 20.0
    """Length of each recorded session and of the final deploy (s, >= 5)."""
    epochs: int = 30
    """Fine-tuning epochs over the recorded sessions."""
    tiny: bool = False
    """CI's form: 5 s sessions, 3 epochs (overrides --seconds and --epochs)."""
    overwrite: bool = False
    """Replace the contents of an existing --out."""

    def __post_init__(self) -> None:
        check_types(self)
        if self.hand not in ("sim-allegro", "sim-leap"):
            raise ValueError(f"hand: the rehearsal runs on an emulated hand (sim-allegro, sim-leap), got {self.hand!r}")
        if not self.policy:
            raise ValueError("policy: give a student bundle directory or a shipped name (student)")
        check_output_dir("out", self.out)
        check_number("seconds", self.seconds, 5.0, 3600.0, unit="s")
        check_int("epochs", self.epochs, 1, 10_000)

    @property
    def session_s(self) -> float:
        return 5.0 if self.tiny else self.seconds

    @property
    def n_epochs(self) -> int:
        return 3 if self.tiny else self.epochs


@contextlib.contextmanager
def _step_output(path: Path):
    """Everything a step prints or logs goes to ``path`` (the console keeps the rehearsal's own lines)."""
    root = logging.getLogger()
    handlers, level = root.handlers[:], root.level
    pkg = logging.getLogger("rotation")
    pkg_level = pkg.level
    with open(path, "a") as f, contextlib.redirect_stdout(f), contextlib.redirect_stderr(f):
        handler = logging.StreamHandler(f)
        handler.setFormatter(logging.Formatter("%(asctime)s %(levelname)s %(name)s: %(message)s"))
        root.handlers, root.level = [handler], logging.WARNING
        pkg.setLevel(logging.INFO)
        try:
            yield
        finally:
            root.handlers, root.level = handlers, level
            pkg.setLevel(pkg_level)


def _card_values(policy: str) -> dict[str, dict[str, Any]]:
    """The two object cards, with the values the emulator simulates (what a lab measures; docs/lab.md); refuses a
    policy that is not a student (it is what the lab records with and fine-tunes on)."""
    from envs.errors import RequestRefused
    from rotation.bundles import load_bundle, policy_hand
    from rotation.deploy.touch import reads_touch
    from rotation.sim_hardware.hand_physics import HandPhysics

    bundle = load_bundle(policy)
    if reads_touch(bundle):
        raise RequestRefused(f"policy: {policy} is a tactile adapter; the rehearsal records with the student it "
                             "corrects and fine-tunes an adapter for it (give the student)")
    # the emulated body is the policy's own hand model (rotation.deploy.policy.deploy_sim_hand)
    nominal = HandPhysics.at_grasp("cup", 0, hand=policy_hand(bundle)).object_properties()
    return {"cup": {**nominal, "object": "cup", "friction_method": "emulator: the simulated coefficient",
                     "notes": "the emulated hand's nominal cup"},
             "slippery_cup": {**nominal, **SLIPPERY, "object": "slippery_cup",
                              "friction_method": "emulator: the simulated coefficient",
                              "notes": "the nominal cup, slippery and weighted"}}


def _write_cards(out: Path, cards: dict[str, dict[str, Any]]) -> dict[str, Path]:
    paths = {}
    for name, card in cards.items():
        paths[name] = out / "objects" / f"{name}.json"
        paths[name].write_text(json.dumps(card, indent=1) + "\n")
    return paths


def _plan(cfg: Config, cards: dict[str, Path]) -> list[dict[str, Any]]:
    s, out = cfg.session_s, cfg.out
    slippery = f"mass={SLIPPERY['mass']},friction={SLIPPERY['friction']},com=0,0,{SLIPPERY['com'][2]}"
    common = ["--hand", cfg.hand, "--policy", cfg.policy, "--digit360", "sim", "--duration", f"{s:g}",
              "--status-every-s", "5"]

    def rec(name: str, obj: str, sim_object: str, faults: str, expect: str) -> dict[str, Any]:
        args = ["record", *common, "--object-card", str(cards[obj]), "--record", str(out / "sessions" / f"{name}.h5"),
                *(["--sim-object", sim_object] if sim_object else []), "--sim-faults", faults]
        return {"name": name, "kind": "record", "args": args, "expect": expect}

    return [
        rec("cup_1", "cup", "", f"corrupt=index@{0.25 * s:.2f}+5,unplug={FINGERS_UNPLUGGED['record']}@{0.6 * s:.2f}",
            "a usable session; the corrupt frames dropped and counted, the thumb's samples stop at the unplug"),
        rec("slippery_1", "slippery_cup", slippery, f"late={0.4 * s:.2f}+{LATE_S[cfg.hand]:g}",
            "a usable session; the driver sees the joint feedback pause, shorter than its limit, and goes on"),
        rec("slippery_2", "slippery_cup", slippery, f"bus-error={0.5 * s:.2f}",
            "the run ends at the bus error with the motors off (confirmed); the session is kept, incomplete"),
        {"name": "finetune", "kind": "finetune", "expect": "an adapter bundle; its latent error on held-out sessions "
         "reported beside the student's"},
        {"name": "deploy", "kind": "deploy", "sim_object": slippery,
         "faults": f"unplug={FINGERS_UNPLUGGED['deploy']}@{0.5 * s:.2f}",
         "expect": "the adapter acts while touch is whole; with a fingertip unplugged the student acts alone"},
    ]


def _last_json(log: Path) -> dict[str, Any] | None:
    for line in reversed(log.read_text().splitlines()):
        if line.startswith("{"):
            try:
                return json.loads(line)
            except json.JSONDecodeError:
                return None
    return None


def _run_cli(args: list[str], log: Path, name: str) -> dict[str, Any] | None:
    """Run one `rotate` command in this process, its output into ``log``; its summary (the last JSON line), None
    without one. Ctrl-C or SIGTERM during it stop the rehearsal (the step saved what it had)."""
    from rotation.cli import main
    from rotation.interrupt import Interrupted

    with _step_output(log):
        code = main(args)
    if code in (130, 143):
        raise Interrupted(code - 128, f"stopped during the step {name}; what it wrote is kept (log: {log})")
    return _last_json(log)


def _run_record(step: dict[str, Any], log: Path) -> dict[str, Any]:
    summary = _run_cli(step["args"], log, step["name"])
    if summary is None:
        return {"ok": False, "said": f"no summary: {_tail(log)}"}
    return judge_record(step["name"], summary)


def _load_fault(summary: dict[str, Any]) -> bool:
    """A run ended by what a machine too loaded to run the loop gives (deploy's documented faults): the control rate
    it could not hold, or the policy's actions missing their deadline until the hold limit."""
    fault = summary.get("fault") or ""
    return "could not hold" in fault or fault.startswith("policy fault: no usable action")


def _run_line(summary: dict[str, Any]) -> str:
    rot = summary.get("rotation_rad")
    return (f"{summary['steps']} steps at {summary['loop_hz'] or 0:.1f} Hz (late {summary['late_steps']}, held "
            f"{summary['held_steps']})" + ("" if rot is None else f", cup turned {rot:+.2f} rad"))


def _fault_lines(summary: dict[str, Any]) -> list[str]:
    out = []
    for f in summary.get("sim_faults") or []:
        when = "not applied (the run had ended)" if f["applied_s"] is None else f"applied at {f['applied_s']:.2f} s"
        out.append(f"{f['fault']}: {when}")
    return out


def judge_record(name: str, summary: dict[str, Any]) -> dict[str, Any]:
    """Whether a recording step showed what it was meant to (see the module docstring), and what to say."""
    verdict = summary.get("finetune_ready") or {}
    counters = summary.get("digit360") or {}
    said = [_run_line(summary), *_fault_lines(summary)]
    if _load_fault(summary):
        return {"ok": False, "said": "; ".join([f"the machine was too loaded: {summary['fault']}", *said])}
    checks: list[tuple[bool, str]] = []
    if name == "cup_1":
        bad, lost = counters.get("index", {}).get("bad_frames", 0), counters.get("thumb", {}).get("disconnects", 0)
        said.append(f"index: {bad} corrupt frames dropped and counted; thumb: {lost} disconnect counted, its reader "
                    "retrying")
        checks += [(summary["fault"] is None, "the run should end normally"), (bad >= 5, "5 corrupt frames counted"),
                   (lost >= 1, "the thumb's disconnect counted")]
    elif name == "slippery_1":
        gap = (summary.get("hand_bus") or {}).get("longest_gap_ms", 0)
        late = LATE_S.get(summary.get("hand", ""), LATE_S["sim-allegro"])
        said.append(f"the hand's longest wait for its joints' state: {gap} ms (the driver ends a run at 100 ms)")
        checks += [(summary["fault"] is None, "the run should end normally"),
                   (gap >= late * 1e3 * 0.8, f"the {late * 1e3:.0f} ms feedback pause seen by the driver")]
    else:
        fault = summary.get("fault") or ""
        said.append(f"ended: {fault or 'normally'}; motors off "
                    f"{'confirmed' if summary.get('motors_off_confirmed') else 'NOT CONFIRMED'}")
        checks += [("overload" in fault, "the bus error should end the run"),  # Allegro's error frame, LEAP's alert
                   (bool(summary.get("motors_off_confirmed")), "the motors off, confirmed"),
                   (verdict.get("complete") is False, "the session kept, marked incomplete")]
    if verdict.get("usable"):
        said.append(f"session usable for fine-tuning ({verdict['seconds']:.1f} s, windows "
                    f"{', '.join(verdict['windows'])})")
    else:
        said.append(f"session NOT usable: {verdict.get('why')}")
    if name != "slippery_2":
        checks.append((bool(verdict.get("usable")), "a usable session"))
    checks.append((all(f["applied_s"] is not None for f in summary.get("sim_faults") or []), "every fault applied"))
    missed = [what for ok, what in checks if not ok]
    if missed:
        said.append("UNEXPECTED: " + "; ".join(f"expected {m}" for m in missed))
    return {"ok": not missed, "said": "; ".join(said), "record": summary.get("record"),
            "usable": bool(verdict.get("usable"))}


def _run_finetune(cfg: Config, sessions: list[str], log: Path) -> dict[str, Any]:
    from adapters.finetune import job as finetune

    if len(sessions) < 2:
        return {"ok": False, "said": f"only {len(sessions)} usable session(s): a fine-tune holds one out"}
    fcfg = finetune.Config(student=cfg.policy, sessions=tuple(Path(s) for s in sessions), modalities="imu,pressure",
                           out=cfg.out / "adapter", epochs=cfg.n_epochs, progress=False, seed=0,
                           val_fraction=1.0 / len(sessions))
    args = ["finetune-adapter", "--student", cfg.policy, "--sessions", *sessions, "--modalities", "imu,pressure",
            "--out", str(fcfg.out), "--epochs", str(fcfg.epochs), "--val-fraction", f"{fcfg.val_fraction:.3g}"]
    try:
        with _step_output(log):
            result = finetune.run(fcfg)
    except (ValueError, OSError) as err:
        return {"ok": False, "said": f"refused: {' '.join(str(err).split())}", "args": args}
    last = result.history[-1]
    val, student = last.get("val_latent_mse"), last.get("val_student_mse")
    said = (f"{last['epoch']} epochs; latent error on the held-out session {val:.4f} against the student's "
            f"{student:.4f} (x{val / student:.2f})" if val is not None and student else
            f"{last['epoch']} epochs; training latent error {last['latent_mse']:.4f} vs {last['student_mse']:.4f}")
    return {"ok": True, "said": said, "bundle": str(result.bundle_dir), "args": args}


def _run_deploy(cfg: Config, step: dict[str, Any], bundle: str, log: Path) -> dict[str, Any]:
    args = ["deploy", "--hand", cfg.hand, "--policy", bundle, "--duration", f"{cfg.session_s:g}", "--sim-object",
            step["sim_object"], "--sim-faults", step["faults"], "--record", str(cfg.out / "deploy.h5"),
            "--status-every-s", "5"]
    summary = _run_cli(args, log, step["name"])
    if summary is None:
        return {"ok": False, "said": f"no summary: {_tail(log)}", "args": args}
    touch = summary.get("touch") or {}
    said = [_run_line(summary), *_fault_lines(summary),
            f"the adapter acted {touch.get('adapter_steps', 0)} steps, the student alone "
            f"{touch.get('fallback_steps', 0)} (last cause: {touch.get('last_fallback_cause') or 'none'})"]
    if _load_fault(summary):
        return {"ok": False, "said": "; ".join([f"the machine was too loaded: {summary['fault']}", *said]),
                "args": args}
    checks = [(summary["fault"] is None, "the run should end normally"),
              (touch.get("adapter_steps", 0) > 0, "the adapter acting"),
              (touch.get("fallback_steps", 0) > 0, "the student alone after the unplug")]
    missed = [what for ok, what in checks if not ok]
    if missed:
        said.append("UNEXPECTED: " + "; ".join(f"expected {m}" for m in missed))
    return {"ok": not missed, "said": "; ".join(said), "args": args}


def _tail(log: Path) -> str:
    lines = [ln for ln in log.read_text().splitlines() if ln.strip()]
    return lines[-1] if lines else "(empty log)"


def _prepare(cfg: Config) -> None:
    if cfg.out.exists() and not cfg.out.is_dir():
        raise ValueError(f"out: {cfg.out} is a file; give a folder")
    if cfg.out.exists() and any(cfg.out.iterdir()):
        if not cfg.overwrite:
            raise ValueError(f"out: {cfg.out} is not empty; give a new folder, or --overwrite to replace it")
        shutil.rmtree(cfg.out)
    for sub in ("objects", "sessions", "logs"):
        (cfg.out / sub).mkdir(parents=True, exist_ok=True)


def page(cfg: Config, results: list[dict[str, Any]], wall_s: float) -> str:
    """The one page: each step, what it was meant to show, what happened; where the outputs are."""
    ok = all(r["ok"] for r in results)
    lines = [f"# Rehearsal of the lab workflow on the emulated {cfg.hand.removeprefix('sim-')} hand",
             "", f"{'Every step behaved as documented' if ok else 'SOME STEPS DID NOT BEHAVE AS DOCUMENTED'} "
             f"({wall_s / 60:.1f} min; sessions of {cfg.session_s:g} s, {cfg.n_epochs} fine-tuning epochs).", ""]
    for i, r in enumerate(results, 1):
        lines += [f"{i}. **{r['name']}** ({'as expected' if r['ok'] else 'NOT as expected'}): {r['said']}",
                  f"   - meant to show: {r['expect']}",
                  f"   - command: `rotate {' '.join(r['args'])}`" if r.get("args") else "   - command: (none)",
                  f"   - log: {r['log']}"]
    lines += ["", "Outputs:", f"- object cards: {cfg.out / 'objects'}", f"- sessions: {cfg.out / 'sessions'}",
              f"- adapter bundle: {cfg.out / 'adapter' / 'bundle'}", f"- deploy recording: {cfg.out / 'deploy.h5'}",
              f"- logs: {cfg.out / 'logs'}", "",
              "On a real hand the commands are the same without --sim-object and --sim-faults, with --hand allegro "
              "(or leap) and --digit360 naming the four sensors' serials (docs/lab.md)."]
    return "\n".join(lines) + "\n"


def run(cfg: Config) -> dict[str, Any]:
    t0 = time.monotonic()
    values = _card_values(cfg.policy)  # the policy checked before anything is written
    _prepare(cfg)
    cards = _write_cards(cfg.out, values)
    results: list[dict[str, Any]] = []
    bundle = None
    for step in _plan(cfg, cards):
        log = cfg.out / "logs" / f"{len(results) + 1}_{step['name']}.log"
        print(f"rehearse: {len(results) + 1}. {step['name']} ...", file=sys.stderr, flush=True)
        if step["kind"] == "record":
            r = _run_record(step, log)
        elif step["kind"] == "finetune":
            sessions = [x["record"] for x in results if x.get("usable")]
            r = _run_finetune(cfg, sessions, log)
            bundle = r.get("bundle")
        else:
            r = _run_deploy(cfg, step, bundle, log) if bundle else {"ok": False, "said": "no adapter to deploy"}
        results.append({"args": step.get("args"), **r, "name": step["name"], "expect": step["expect"],
                        "log": str(log)})
        print(f"rehearse:    {'ok' if r['ok'] else 'NOT as expected'}: {r['said']}", file=sys.stderr, flush=True)
    text = page(cfg, results, time.monotonic() - t0)
    (cfg.out / "REHEARSAL.md").write_text(text)
    print(text)
    ok = all(r["ok"] for r in results)
    return {"ok": ok, "steps": results, "page": str(cfg.out / "REHEARSAL.md"), "exit_code": 0 if ok else 1}
