"""Record a labelled session: the policy runs on the hand (as `rotate deploy`) while the fingertips record, and the
session carries the object's measured properties, so that `rotate finetune-adapter` can train on it.

    rotate record --hand allegro --policy student --digit360 D360-A,D360-B,D360-C,D360-D \\
        --object-card objects/mug_tape.json --record sessions/mug_tape_01.h5 --duration 30
    rotate record --hand allegro --policy student --digit360 D360-A,D360-B,D360-C,D360-D --object mug_tape \\
        --properties mass=0.21,friction=0.45,com=0,0,0.01,scale=0.9 --friction-method 'tilt, 5 trials' \\
        --record sessions/mug_tape_02.h5
    rotate record --hand sim-allegro --policy student --digit360 sim --sim-object mass=0.3,friction=0.5 \\
        --record sessions/rehearsal.h5         # emulated: the emulated object's values are the measurement

The object's properties (rotation.data.properties: mass in kg, sliding friction coefficient against the fingertips,
center-of-mass offset in m in the object frame, size relative to the simulated cup) come from an object card (a JSON
file the lab writes once per object, docs/lab.md), from --properties (which overrides the card's values), or, in a
terminal, from questions asked for each one still missing. How the friction was measured (--friction-method, or the
card's ``friction_method``) is stored beside it. An emulated hand's object is known exactly: its values fill what
is not stated, and the method is 'emulator'. Answers typed in a terminal are saved as a card beside the session
(NAME.card.json) for --object-card next time.

Refused before the hand starts, with what to do: a session without all four properties or without the friction
method on a real hand, a run without the Digit 360 fingertips (the adapter learns from their streams), a hand the
student does not run on, a run shorter than MIN_SECONDS. After the run the written session is checked as
`rotate finetune-adapter` would check it, and the last lines say whether it can train an adapter (and on which
windows), or why not; a run that ended in a fault keeps its session up to the fault (marked incomplete). The last
stdout line is deploy's summary (one JSON object) with ``finetune_ready`` added.
"""

from __future__ import annotations

import dataclasses
import json
import logging
import sys
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from envs.constants import FINGERS
from envs.errors import RequestRefused
from rotation.data.properties import PROPERTY_SIZES, PROPERTY_UNITS, check_properties, check_value, parse_properties
from rotation.deploy import config as deploy_config
from rotation.deploy.sensors import parse_digit360

log = logging.getLogger("rotation.record")

MIN_SECONDS = 5.0
"""Shortest labelled run (s): the fingertip windows need 1.12 s of history before the first sample, and a fine-tune
holds out a share of each session's samples for validation."""
QUESTIONS = {
    "mass": "mass in kg, with everything that moves with it (added weights included)",
    "friction": "sliding friction coefficient against the fingertip gel (docs/lab.md: tilt or pull test)",
    "com": "center-of-mass offset from the middle of the body, m, object frame (z up the axis), as X,Y,Z",
    "scale": "size relative to the simulated cup (radius 40 mm, height 85 mm): e.g. 0.8 for radius 32 mm",
}
"""What each property means, as a question (and in the refusal that lists what is missing)."""
CARD_KEYS = (*PROPERTY_SIZES, "object", "friction_method", "notes")


@dataclass(frozen=True)
class Config(deploy_config.Config):
    duration: float = 30.0
    """Run length (s), at least 5; 0 runs until Ctrl-C / SIGTERM (docs/lab.md: 20-60 s per session)."""
    object_card: str = ""
    """JSON file of the object's measurements: object (name), mass, friction, friction_method, com, scale, notes
    (docs/lab.md); --properties, --friction-method and --object override its values."""
    ask: bool = True
    """In a terminal, ask for each property still missing (--no-ask: refuse instead)."""

    def __post_init__(self) -> None:
        super().__post_init__()
        if not self.record:
            raise ValueError("record: give the session file to write (--record sessions/NAME.h5)")
        if self.duration != 0 and self.duration < MIN_SECONDS:
            raise ValueError(f"duration: a labelled session needs at least {MIN_SECONDS:g} s (0: until Ctrl-C), got "
                             f"{self.duration:g}")


REQUIRED = ("hand", "policy", "record")


def add_arguments(parser) -> None:
    from rotation.configs import add_dataclass_arguments

    add_dataclass_arguments(parser, Config)
    for action in parser._actions:
        if action.dest in REQUIRED:
            action.required = True
            action.help = (action.help or "").split(" (default:")[0]


def config_from_args(args) -> Config:
    from rotation.configs import dataclass_from_args

    return dataclass_from_args(Config, args)


def read_card(path: str) -> dict[str, Any]:
    """An object card: {object, mass, friction, friction_method, com, scale, notes}, every property it states
    checked; ValueError naming the file and the key."""
    where = f"object card {path}"
    try:
        card = json.loads(Path(path).read_text())
    except OSError as err:
        raise ValueError(f"{where}: cannot read it ({err.strerror or err})") from None
    except json.JSONDecodeError as err:
        raise ValueError(f"{where}: not JSON ({err.msg} at line {err.lineno})") from None
    if not isinstance(card, dict):
        raise ValueError(f"{where}: must hold one JSON object with the keys {', '.join(CARD_KEYS)}")
    unknown = sorted(set(card) - set(CARD_KEYS))
    if unknown:
        raise ValueError(f"{where}: unknown key(s) {', '.join(unknown)}; the keys are {', '.join(CARD_KEYS)}")
    for key in ("object", "friction_method", "notes"):
        if key in card and not isinstance(card[key], str):
            raise ValueError(f"{where}: {key!r} must be text, got {card[key]!r}")
    for key in PROPERTY_SIZES:  # each value stated, checked (the missing ones are asked or refused later)
        if key in card:
            check_value(key, card[key], where)
    return card


def save_card(path: Path, name: str, props: dict[str, Any], method: str) -> None:
    """The answers given in a terminal, as an object card beside the session (for --object-card next time); an
    existing file is left as it is."""
    if path.exists():
        print(f"record: {path} exists; the answers were not saved as a card", file=sys.stderr)
        return
    path.write_text(json.dumps({"object": name, **props, "friction_method": method}, indent=1) + "\n")
    print(f"record: the object's measurements are saved in {path}: reuse them with --object-card {path}",
          file=sys.stderr)


def _spec(props: dict[str, Any]) -> str:
    """{key: value} -> the --properties form."""
    return ",".join(f"{k}={','.join(f'{x:g}' for x in v) if isinstance(v, list) else f'{v:g}'}"
                    for k, v in props.items())


def _ask(key: str, prompt=input) -> float | list[float]:
    """Ask for one property until a valid value is typed (Ctrl-D / Ctrl-C: refused)."""
    unit = f" [{PROPERTY_UNITS[key]}]" if PROPERTY_UNITS[key] else ""
    while True:
        try:
            text = prompt(f"{key}{unit}: {QUESTIONS[key]}? ")
        except EOFError:
            raise RequestRefused(f"record: no value for {key}; nothing was started") from None
        try:
            return parse_properties(f"{key}={text.strip()}", "answer")[key]
        except ValueError as err:
            print(f"  {str(err).split('; give')[0]}; again:", file=sys.stderr)


def resolve_labels(cfg: Config, interactive: bool | None = None, prompt=input,
                   asked: list[str] | None = None) -> tuple[str, dict[str, Any], str]:
    """(object name, stated properties, friction method) from the card, the options and (in a terminal) answers;
    RequestRefused when a real hand's session would lack a property or the method. ``asked`` gets the names of what
    was asked."""
    asked = [] if asked is None else asked
    card = read_card(cfg.object_card) if cfg.object_card else {}
    stated = {k: card[k] for k in PROPERTY_SIZES if k in card}
    stated.update(parse_properties(cfg.properties))
    method = cfg.friction_method.strip() or str(card.get("friction_method", "")).strip()
    emulated = cfg.hand.startswith("sim-")
    # an emulated hand holds the simulated object it names (a shipped grasp cache), whatever the card calls it
    name = cfg.object if emulated or cfg.object != "cup" or "object" not in card else card["object"]
    interactive = sys.stdin.isatty() if interactive is None else interactive
    missing = [k for k in QUESTIONS if k not in stated]
    if missing and not emulated and cfg.ask and interactive:
        print(f"record: measured properties of {name!r} (docs/lab.md says how to measure them):", file=sys.stderr)
        for key in missing:
            stated[key] = _ask(key, prompt)
            asked.append(key)
        missing = []
    if stated and not method and not emulated and cfg.ask and interactive:
        method = prompt("friction_method: how was the friction measured (tilt, pull, ...)? ").strip()
        asked.append("friction_method")
    if missing and not emulated:
        raise RequestRefused(
            f"record: the session would lack the object's {', '.join(missing)} "
            f"({'; '.join(QUESTIONS[k] for k in missing)}), and `rotate finetune-adapter` cannot train on it; give "
            "--object-card FILE or --properties mass=...,friction=...,com=X,Y,Z,scale=... (docs/lab.md), "
            "or run in a terminal to be asked")
    if not method and not emulated:
        raise RequestRefused("record: say how the friction coefficient was measured (--friction-method 'tilt, 5 "
                             "trials' or the card's friction_method; docs/lab.md): a coefficient without its method "
                             "cannot be compared across sessions")
    return name, stated, method or ("emulator" if emulated else "")


def _touch_refusal(cfg: Config, specs: dict[str, str]) -> str | None:
    if specs:
        return None
    if cfg.hand.startswith("sim-"):
        return ("record: give --digit360 sim: the emulated fingertips record the streams an adapter fine-tune reads")
    skin = " (a skin-only run records the skin encoder's data: use `rotate deploy --skin ... --record`)" \
        if cfg.skin else ""
    return ("record: give the Digit 360 fingertips (--digit360 SERIAL1,SERIAL2,SERIAL3,SERIAL4): an adapter learns "
            f"from their streams{skin}")


def finetune_verdict(path: str | Path, control_hz: float, media: bool) -> dict[str, Any]:
    """Whether `rotate finetune-adapter` can train on the session (checked as it checks its sessions), on which
    fingertips and windows, or why not."""
    from adapters.session_checks import MEDIA_WINDOWS, SERIAL_WINDOWS, check_session
    from rotation.data.session import SessionError
    from rotation.data.session_reader import SessionReader

    windows = [*SERIAL_WINDOWS, *(MEDIA_WINDOWS if media else ())]
    try:
        with SessionReader(path) as r:
            fingers = [f for f in FINGERS if r.has(f"digit360/{f}/imu")]
            complete = r.complete
            seconds = float(r.stream("joints/position").timestamps[-1]) if len(r.stream("joints/position")) else 0.0
        info = check_session(path, fingers or list(FINGERS), windows, control_hz)
    except (SessionError, OSError, ValueError) as err:
        return {"usable": False, "why": " ".join(str(err).split()), "fingers": [], "windows": []}
    return {"usable": info.steps > 0, "why": None if info.steps else "no control step was recorded",
            "fingers": fingers, "windows": windows, "steps": info.steps, "seconds": round(seconds, 2),
            "complete": complete, "properties": info.properties}


def run(cfg: Config) -> dict[str, Any]:
    from rotation.deploy.job import run as deploy

    asked: list[str] = []
    name, stated, method = resolve_labels(cfg, asked=asked)
    specs = parse_digit360(cfg.digit360, cfg.hand.startswith("sim-"))
    refusal = _touch_refusal(cfg, specs)
    if refusal:
        raise RequestRefused(refusal)
    if len(stated) == len(PROPERTY_SIZES):
        from adapters.session_checks import outside_training_ranges

        for note in outside_training_ranges(check_properties(stated, "properties")):
            log.warning("record: %s is outside the teacher's training ranges: its latent there is an extrapolation "
                        "(docs/lab.md, 'Objects')", note)
    fields = {f.name: getattr(cfg, f.name) for f in dataclasses.fields(deploy_config.Config)}
    dcfg = deploy_config.Config(**{**fields, "object": name, "properties": _spec(stated),
                                   "friction_method": method})
    summary = deploy(dcfg)
    if asked and summary.get("record") is not None:
        save_card(Path(summary["record"]).with_suffix(".card.json"), name, stated, method)
    if summary.get("record") is None:
        summary["finetune_ready"] = {"usable": False, "why": "nothing was recorded (the run did not start)"}
        print(f"record: nothing was recorded: {summary.get('fault')}", file=sys.stderr)
        return summary
    verdict = finetune_verdict(summary["record"], summary["control_hz"], cfg.record_media)
    summary["finetune_ready"] = verdict
    if verdict["usable"]:
        ended = "" if verdict["complete"] else f" (the run ended early: {summary.get('fault')}; kept up to there)"
        lacking = [f for f in FINGERS if f not in verdict["fingers"]]
        fingers = "" if not lacking else f"; without the {', '.join(lacking)} fingertip(s)"
        print(f"record: {summary['record']}: {verdict['seconds']:.1f} s, {verdict['steps']} steps{ended}; usable by "
              f"`rotate finetune-adapter --sessions` on the windows {', '.join(verdict['windows'])}{fingers}",
              file=sys.stderr)
    else:
        print(f"record: {summary['record']} was written but cannot train an adapter: {verdict['why']}",
              file=sys.stderr)
    print(json.dumps(summary))  # deploy's summary line again, with the verdict: the last line is the whole story
    return summary
