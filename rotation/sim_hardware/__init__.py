"""Emulated hands and sensors that answer the real protocols (MuJoCo-backed; imports mujoco and envs, no torch).

- :mod:`allegro_emulator`: Allegro V4/V5 on a python-can virtual bus, or behind an emulated SLCAN adapter on a
  pseudo-terminal;
- :mod:`leap_emulator`: a Dynamixel Protocol 2.0 servo bus on a pseudo-terminal (talks to the unmodified
  dynamixel-sdk);
- :mod:`digit360_emulator`: a Digit 360 serial stream (COBS-framed protobuf) on a pseudo-terminal; beside an
  emulated hand it senses a fingertip of that hand with the env's simulated Digit 360 (:mod:`digit360_touch`),
  camera and microphones included.

Each has fault-injection switches (``.faults``) used by tests and by users rehearsing failures before powering
the real hand.
"""
