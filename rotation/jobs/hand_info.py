"""Print a hand's firmware, serial, temperatures and joint positions (read-only: motors stay off).

    rotate hand-info --hand allegro --can socketcan:can0
    rotate hand-info --hand leap --port /dev/ttyUSB0 --baud 4000000
    rotate hand-info --hand sim-allegro        # emulated hand on a virtual CAN bus, real driver
    rotate hand-info --hand sim-leap           # emulated Dynamixel bus on a pseudo-terminal, real driver
"""

from __future__ import annotations

import contextlib
from dataclasses import dataclass
from typing import Literal

import numpy as np

from envs.errors import JobFailed

HANDS = ("allegro", "leap", "sim-allegro", "sim-leap")


@dataclass(frozen=True)
class Config:
    hand: Literal["allegro", "leap", "sim-allegro", "sim-leap"] = "sim-allegro"
    """Which hand: a real Allegro (CAN) or LEAP (Dynamixel), or its emulator driven through the real driver."""
    can: str = "socketcan:can0"
    """Allegro bus as INTERFACE:CHANNEL (socketcan:can0, pcan:PCAN_USBBUS1, slcan:/dev/ttyACM0)."""
    port: str = "/dev/ttyUSB0"
    """LEAP serial device (U2D2 adapter)."""
    baud: int = 4_000_000
    """LEAP baud rate."""

    def __post_init__(self) -> None:
        from envs.validation import check_types
        from rotation.hardware.leap.dynamixel_protocol import BAUD_CODES

        if self.hand not in HANDS:
            raise ValueError(f"hand: unknown hand {self.hand!r}; choose one of {', '.join(HANDS)}")
        check_types(self)
        if self.baud not in BAUD_CODES:
            raise ValueError(f"baud: {self.baud} is not a Dynamixel baud rate; choose one of {sorted(BAUD_CODES)}")
        if self.hand == "allegro":
            from rotation.hardware.allegro.can_bus import parse_can_spec

            parse_can_spec(self.can)


def _format(info, state) -> str:
    deg = np.rad2deg(state.q)
    lines = [f"hand        {info.kind}", f"firmware    {info.firmware}", f"hardware    {info.hardware}",
             f"serial      {info.serial}"]
    lines += [f"{k:<11s} {v}" for k, v in info.extra.items() if k != "model_numbers"]
    lines.append("joint        q (rad)   q (deg)   temp (C)")
    names = [f"{f}_{j}" for f in ("index", "middle", "ring", "thumb") for j in range(4)]
    for name, q, d, t in zip(names, state.q, deg, info.temperatures, strict=True):
        lines.append(f"{name:<10s} {q:9.4f} {d:9.2f} {t:9.1f}")
    return "\n".join(lines)


def read_info(cfg: Config) -> str:
    """Connect read-only, return the printable report."""
    with contextlib.ExitStack() as stack:
        if cfg.hand in ("allegro", "sim-allegro"):
            from rotation.hardware.allegro.driver import AllegroConfig, AllegroHand

            spec = cfg.can
            if cfg.hand == "sim-allegro":
                from rotation.sim_hardware.allegro_emulator import AllegroEmulator

                spec = stack.enter_context(AllegroEmulator()).spec
            hand = stack.enter_context(AllegroHand(spec, AllegroConfig(enable_motors=False, feedback_timeout_s=1.0)))
        else:
            from rotation.hardware.leap.driver import LeapConfig, LeapHand

            port = cfg.port
            if cfg.hand == "sim-leap":
                from rotation.sim_hardware.leap_emulator import LeapEmulator

                port = stack.enter_context(LeapEmulator()).path
            # the emulator shares this process's CPU and GIL with the busy-polling SDK: allow more retries
            retries = 6 if cfg.hand == "sim-leap" else 3
            hand = stack.enter_context(LeapHand(port, LeapConfig(baudrate=cfg.baud, enable_motors=False,
                                                                 feedback_timeout_s=1.0, max_retries=retries)))
        return _format(hand.info(), hand.read_state())


def run(cfg: Config) -> None:
    import can

    from rotation.hardware.hand import HandFault

    try:
        print(read_info(cfg))
    except (HandFault, can.CanError, OSError) as err:  # no hand answers: one clear line (rotate), not a traceback
        raise JobFailed(str(err)) from err
