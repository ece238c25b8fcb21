"""The deploy runtime (``rotate deploy``): the one place where trained models meet hardware.

- :mod:`job`: the command (``Config``, ``run(cfg) -> summary``): checks the options, starts the hand, runs the
  loop, and on every way out leaves the hand with the motors off and the recording closed;
- :mod:`hands`: real Allegro / LEAP drivers, or the MuJoCo emulators (holding the cup at a cached grasp) driven
  through the same drivers over the real protocols;
- :mod:`policy`: the env's observation/target bookkeeping (``envs.observation.ProprioHistory``) and a
  deadline-bounded policy worker;
- :mod:`loop`: the control loop at the bundle's rate, with hold-on-stall, NaN rejection, timing statistics and
  the live status line;
- :mod:`touch`: a tactile adapter policy's touch correction, refreshed on its own thread from the Digit 360
  readers, and the fallback to its student when touch is unusable;
- :mod:`recording`: the session file (rotation.data.session) of a run; :mod:`sensors`: Digit 360 readers.

Imports point one way: deploy -> rotation.policy / adapters (tactile adapter policies) / rotation.hardware /
rotation.sim_hardware (emulated hands only, imported lazily) / envs.
"""
