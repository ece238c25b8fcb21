"""The options of `rotate deploy` and every check that runs before a motor is switched on (the recording's path,
the sensors).
"""

from __future__ import annotations

import argparse
import math
import tempfile
from dataclasses import dataclass
from pathlib import Path
from typing import Literal

from envs.constants import FINGERS
from envs.validation import check_int, check_number, check_types
from rotation.configs import add_dataclass_arguments, dataclass_from_args
from rotation.data.properties import parse_properties
from rotation.deploy.hands import HANDS
from rotation.deploy.sensors import check_skin, parse_digit360, parse_skin
from rotation.deploy.sim_faults import check_sim_faults, parse_sim_faults


@dataclass(frozen=True)
class Config:
    hand: Literal["allegro", "leap", "sim-allegro", "sim-leap"] = "sim-allegro"
    """Real Allegro (CAN) or LEAP (Dynamixel), or its MuJoCo emulator driven through the real driver and protocol."""
    policy: str = ""
    """Policy bundle: a directory (config.json + model.safetensors) or a shipped name (student); or a tactile adapter
    bundle (a directory with adapter.safetensors, or a shipped name such as adapter), which reads the Digit 360
    fingertips."""
    can: str = "socketcan:can0"
    """Allegro bus as INTERFACE:CHANNEL: socketcan:can0, pcan:PCAN_USBBUS1, slcan:/dev/ttyACM0 (any serial device)."""
    port: str = "/dev/ttyUSB0"
    """LEAP serial device (U2D2 adapter; any serial device path)."""
    baud: int = 4_000_000
    """LEAP baud rate."""
    digit360: str = ""
    """Digit 360 sensors to record (and to read, for a tactile adapter policy): 4 comma-separated serials (the USB
    hub's, as `rotate touch-info` lists them, or the data tty's) in finger order (index,middle,ring,thumb),
    FINGER=SERIAL pairs, tty paths, or 'sim' (emulated sensors that sense the emulated hand, emulated hands only;
    what an adapter policy on an emulated hand starts without this option)."""
    digit360_imu: Literal["acc", "linacc"] = "acc"
    """The accelerometer channel of the real Digit 360 sensors' imu windows: 'acc', the raw accelerometer (gravity
    included, as the simulated sensor and the shipped encoders), or 'linacc', the sensor fusion's linear acceleration
    (gravity removed, what Meta's released Sparsh-X was pretrained on: for an adapter on those weights). Recorded in
    the session; emulated sensors then send it too (their specific force plus gravity in the fingertip's frame)."""
    skin: str = ""
    """Xela skin to record (skin/xela, 100 Hz): the vendor xela_server's WebSocket URL (ws://HOST:5000), or 'sim'
    (a stand-in server, emulated hands only); empty: none. Start with the skin free of contact (baseline)."""
    duration: float = 10.0
    """Run length (s); 0 runs until Ctrl-C / SIGTERM."""
    record: str = ""
    """Session file (.h5) to record to (must not exist unless --overwrite); empty: no recording."""
    overwrite: bool = False
    """Replace an existing --record file."""
    record_media: bool = False
    """Also record each real --digit360 sensor's camera frames and microphones (digit360/<finger>/image, audio;
    about 4.5 MB/s per sensor; needs the hardware extra), whatever the policy reads: what fine-tuning an adapter
    that reads the image or the audio on your sessions needs. A policy that reads them records them anyway."""
    gain_scale: float = 1.0
    """Factor in (0, 1] on the driver's gains (Allegro kp/kd, LEAP position P/D): start a new hand low."""
    object: str = "cup"
    """Object in the hand: recorded as metadata; emulated hands simulate it (needs a shipped grasp cache)."""
    properties: str = ""
    """Measured object properties to store in the recording (its metadata's ``properties``; needs --record), e.g.
    'mass=0.12,friction=0.8,com=0,0,0.01,scale=0.8': kg, friction coefficient against the fingertips, center of
    mass offset (m, object frame), size relative to the simulated cup (rotation.data.properties). Fine-tuning the
    tactile adapter on the recording needs all four. An emulated hand records its simulated values; stated ones
    replace them."""
    friction_method: str = ""
    """How --properties' friction coefficient was measured, stored beside it (e.g. 'tilt: 5 trials on the
    fingertip gel', 'pull: force gauge'; docs/lab.md): `rotate record` asks for it."""
    grasp: int = 0
    """Emulated hands: the row of the shipped grasp cache to start from (nominal scale)."""
    sim_object: str = ""
    """Emulated hands: the emulated object's mass, friction and center of mass, e.g. 'mass=0.3,friction=0.4,
    com=0,0,0.01' (kg, coefficient, m in the object frame; any subset; its scale is the grasp cache's nominal):
    rehearse a heavy or slippery object. The recording stores the emulated values."""
    sim_faults: str = ""
    """Emulated hands: faults to inject while the loop runs, e.g. 'unplug=thumb@4,late=6+0.08,bus-error=9'
    (unplug, corrupt, stall, lag of a fingertip; late feedback or a bus error of the hand;
    rotation.deploy.sim_faults)."""
    sim_transport: Literal["virtual", "slcan"] = "virtual"
    """Emulated Allegro: python-can virtual bus, or an SLCAN serial adapter on a pseudo-terminal."""
    rt_priority: int = 0
    """SCHED_FIFO priority (1..99) for the control threads; 0 leaves scheduling alone (needs CAP_SYS_NICE)."""
    policy_budget: float = 0.6
    """Longest wait for the policy's action, as a fraction of the control period; later = hold the last target."""
    hold_limit_s: float = 1.0
    """Fault (end the run) after this long without a usable action from the policy (s)."""
    status_every_s: float = 1.0
    """Status line period (s)."""
    allow_model_mismatch: bool = False
    """Run a policy on a real hand whose model it was not trained on: one of the older 'digit360' / 'xela' model on a
    real Allegro (whose kinematics differ: its grasps open by 26-50 mm there), or any policy on a real LEAP (no LEAP
    model exists yet). Refused without it; meant for rehearsing the real-hand path against an emulator on a
    virtual bus, or for a lab that knows what it is testing. The summary records it."""

    def __post_init__(self) -> None:
        if self.hand not in HANDS:
            raise ValueError(f"hand: unknown hand {self.hand!r}; choose one of {', '.join(HANDS)}")
        check_types(self)
        if not self.policy:
            raise ValueError("policy: give a bundle directory or a shipped bundle name (--policy student)")
        if not (math.isfinite(self.duration) and self.duration >= 0):
            raise ValueError(f"duration must be >= 0 s (0: until Ctrl-C), got {self.duration}")
        if not (0 < self.gain_scale <= 1):
            raise ValueError(f"gain_scale must be in (0, 1] (a fraction of the driver's gains), got {self.gain_scale}")
        if self.hand == "allegro":
            from rotation.hardware.allegro.can_bus import parse_can_spec

            parse_can_spec(self.can)
        if self.hand == "leap":
            from rotation.hardware.leap.dynamixel_protocol import BAUD_CODES

            if self.baud not in BAUD_CODES:
                raise ValueError(f"baud: {self.baud} is not a Dynamixel baud rate; choose one of {sorted(BAUD_CODES)}")
        digit_specs = parse_digit360(self.digit360, emulated=self.hand.startswith("sim-"))
        parse_skin(self.skin, emulated=self.hand.startswith("sim-"))
        if parse_properties(self.properties) and not self.record:
            raise ValueError("properties: they are stored in the recording; give --record FILE.h5 as well")
        if self.friction_method.strip() and not (parse_properties(self.properties) or self.hand.startswith("sim-")):
            raise ValueError("friction_method: it says how --properties' friction was measured; give --properties")
        if self.friction_method.strip() and not self.record:
            raise ValueError("friction_method: it is stored in the recording; give --record FILE.h5 as well")
        sim_object = parse_properties(self.sim_object, "sim_object")
        if sim_object and not self.hand.startswith("sim-"):
            raise ValueError("sim_object: it sets the emulated object; a real hand holds a real one (--properties "
                             "records what you measured)")
        if "scale" in sim_object:
            raise ValueError("sim_object: the emulated object's scale is the grasp cache's nominal; set mass, "
                             "friction or com")
        sim_fingers = tuple(f for f, v in digit_specs.items() if v == "sim")
        check_sim_faults(parse_sim_faults(self.sim_faults), self.hand.startswith("sim-"),
                         sim_fingers or (FINGERS if not self.digit360.strip() else ()))
        if self.record_media:
            if not self.record:
                raise ValueError("record_media: it records the sensors' cameras and microphones; give --record "
                                 "FILE.h5 as well")
            if not digit_specs or any(v == "sim" for v in digit_specs.values()):
                raise ValueError("record_media: name real Digit 360 sensors with --digit360 (serials or tty paths); "
                                 "emulated sensors render their image and audio only for a window and record none")
        if self.grasp < 0:
            raise ValueError(f"grasp must be >= 0, got {self.grasp}")
        if self.sim_transport not in ("virtual", "slcan"):
            raise ValueError(f"sim_transport must be 'virtual' or 'slcan', got {self.sim_transport!r}")
        if not 0 <= self.rt_priority <= 99:
            raise ValueError(f"rt_priority must be 0..99, got {self.rt_priority}")
        if not 0 < self.policy_budget <= 1:
            raise ValueError(f"policy_budget must be in (0, 1] control periods, got {self.policy_budget}")
        if not (self.hold_limit_s > 0 and self.status_every_s > 0):
            raise ValueError("hold_limit_s and status_every_s must be > 0 s")
        # ceilings that catch typos and unit slips (every option is checked, whether this hand uses it or not)
        from rotation.hardware.leap.dynamixel_protocol import BAUD_CODES

        if self.baud not in BAUD_CODES:
            raise ValueError(f"baud: {self.baud} is not a Dynamixel baud rate; choose one of {sorted(BAUD_CODES)}")
        check_number("duration", self.duration, 0.0, 7 * 24 * 3600.0, unit="s (0: until Ctrl-C)")
        check_int("grasp", self.grasp, 0, 10**6)
        check_number("hold_limit_s", self.hold_limit_s, 0.0, 60.0, low_open=True, unit="s")
        check_number("status_every_s", self.status_every_s, 0.0, 3600.0, low_open=True, unit="s")


REQUIRED = ("hand", "policy")


def add_arguments(parser: argparse.ArgumentParser) -> None:
    add_dataclass_arguments(parser, Config)
    for action in parser._actions:  # the hand and the policy are never implied
        if action.dest in REQUIRED:
            action.required = True
            action.help = (action.help or "").split(" (default:")[0]


def config_from_args(args: argparse.Namespace) -> Config:
    return dataclass_from_args(Config, args)


def check_record_path(path: Path, overwrite: bool) -> None:
    """ValueError unless a session file can be created at ``path``: never an existing file without ``--overwrite``
    (a recording is never replaced silently), never a directory, and a location this process can write to."""
    if path.is_dir():
        raise ValueError(f"record: {path} is a directory; give a file name such as {path / 'run.h5'}")
    if path.exists() and not overwrite:
        raise ValueError(f"record: {path} exists; choose a new file name, or pass --overwrite to replace it")
    parent = path.parent if str(path.parent) else Path(".")
    existing = next((p for p in (parent, *parent.parents) if p.exists()), Path("."))
    if not existing.is_dir():
        raise ValueError(f"record: cannot create {path}: {existing} is not a directory")
    # try it: permission bits say nothing when running as root or on a read-only file system
    try:
        if path.exists():
            with open(path, "r+b"):
                pass
        else:
            with tempfile.TemporaryFile(dir=existing):
                pass
    except OSError as err:
        raise ValueError(f"record: cannot write {path} ({err.strerror or err} in {existing}); choose a writable "
                         "location") from err


def check_before_start(cfg: Config) -> None:
    """Everything that can be checked without touching the hardware (ValueError: bad input)."""
    if cfg.record:
        check_record_path(Path(cfg.record), cfg.overwrite)
    check_skin(parse_skin(cfg.skin, emulated=cfg.hand.startswith("sim-")))
    if cfg.hand.startswith("sim-"):
        from envs.grasp_cache import load_default_cache

        cache = load_default_cache(cfg.object)
        if cfg.grasp >= cache.grasps.shape[1]:
            raise ValueError(f"grasp {cfg.grasp} out of range: the {cfg.object!r} cache has "
                             f"{cache.grasps.shape[1]} grasps per scale")
