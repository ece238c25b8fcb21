"""The session format shared by simulation and the real hand, and the datasets read from it.

- :mod:`rotation.data.session`: the HDF5 layout (its module docstring is the spec), ``SessionWriter``,
  ``SessionReader``, ``SessionError``.
- :mod:`rotation.data.dataset`: ``TouchWindows`` (Sparsh-X windows per fingertip + labels) and ``split_sessions``.
"""

from rotation.data.session import (
    FORMAT_VERSION,
    STREAMS,
    SessionError,
    SessionMeta,
    SessionReader,
    SessionWriter,
    StreamSetup,
)

__all__ = ["FORMAT_VERSION", "STREAMS", "SessionError", "SessionMeta", "SessionReader", "SessionWriter",
           "StreamSetup"]
