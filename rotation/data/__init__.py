"""The session format shared by simulation and the real hand, and the datasets read from it.

- :mod:`rotation.data.session`: the HDF5 layout (its module docstring is the spec) and ``SessionError``;
  :mod:`rotation.data.session_writer` and :mod:`rotation.data.session_reader` write and read it.
- :mod:`rotation.data.dataset`: ``TouchWindows`` (Sparsh-X windows per fingertip + labels) and ``split_sessions``.
- :mod:`rotation.data.skin`: ``SkinWindows`` (Sparsh-skin windows of the whole hand's Xela skin + labels) and the
  skin's baselines.
- :mod:`rotation.data.window_cache`: touch windows pre-rendered into memory-mapped shards.
- :mod:`rotation.data.audio`: the Kaldi log-mel filterbank in torch, the Sparsh-X audio feature.
"""

from rotation.data.session import FORMAT_VERSION, STREAMS, SessionError, SessionMeta, StreamSetup
from rotation.data.session_reader import SessionReader
from rotation.data.session_writer import SessionWriter

__all__ = ["FORMAT_VERSION", "STREAMS", "SessionError", "SessionMeta", "SessionReader", "SessionWriter",
           "StreamSetup"]
