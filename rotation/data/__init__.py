"""The session format shared by simulation and the real hand, and the datasets read from it.

- :mod:`rotation.data.session`: the HDF5 layout (its module docstring is the spec), ``SessionWriter``,
  ``SessionReader``, ``SessionError``.
- :mod:`rotation.data.dataset`: ``TouchWindows`` (Sparsh-X windows per fingertip + labels) and ``split_sessions``.
- :mod:`rotation.data.skin`: ``SkinWindows`` (Sparsh-skin windows of the whole hand's Xela skin + labels) and the
  skin's baselines.
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
