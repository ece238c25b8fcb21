"""Hardware drivers: Allegro (CAN), LEAP (Dynamixel), Digit 360 (serial/audio/camera), and the safety layer.

Layering (docs/DESIGN "Hardware"): bus -> protocol tables (pure functions, data) -> hand (context manager) ->
safety (one layer every command passes through). This package imports neither torch nor mujoco; the emulated
hands live in :mod:`rotation.sim_hardware`.

Every hand speaks the same small :class:`rotation.hardware.hand.Hand` protocol: joint positions, velocities and
efforts in the Allegro bus order (index 0-3, middle 4-7, ring 8-11, thumb 12-15), radians, Allegro frame.
"""

from rotation.hardware.hand import Hand, HandFault, HandInfo, HandNotResponding, HandState

__all__ = ["Hand", "HandFault", "HandInfo", "HandNotResponding", "HandState"]
