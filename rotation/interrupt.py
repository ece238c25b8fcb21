"""Stopping long jobs on Ctrl-C or SIGTERM: finish the current step, save everything, then exit 130 / 143.

A training job runs inside :class:`StopSignals`: the first SIGINT or SIGTERM only sets a flag that the job's loop
checks at a safe point (between env steps); the job then saves its checkpoint and outputs and raises
:class:`Interrupted`, which ``rotate`` turns into exit status 128 + the signal number (130 for Ctrl-C, 143 for
SIGTERM), as deploy does. A second signal stops at once (``Interrupted`` raised from the handler).
"""

from __future__ import annotations

import signal
import threading
from types import FrameType, TracebackType

SIGNAL_NAMES = {signal.SIGINT: "SIGINT (Ctrl-C)", signal.SIGTERM: "SIGTERM"}


class Interrupted(KeyboardInterrupt):
    """A job stopped by a signal after saving what it had; ``exit_code`` is 128 + the signal number."""

    def __init__(self, signum: int = signal.SIGINT, message: str = "") -> None:
        self.signum = int(signum)
        self.exit_code = 128 + self.signum
        super().__init__(message or f"interrupted by {SIGNAL_NAMES.get(self.signum, f'signal {signum}')}")


class StopSignals:
    """Context manager: SIGINT / SIGTERM request a stop (``requested``, ``signum``); a second one raises at once.

    Outside the main thread (where Python cannot install handlers) it does nothing and Ctrl-C raises as usual.
    """

    def __init__(self) -> None:
        self.signum: int | None = None
        self._previous: dict[int, object] = {}

    @property
    def requested(self) -> bool:
        return self.signum is not None

    def _handle(self, signum: int, frame: FrameType | None) -> None:
        if self.signum is not None:  # the second signal: stop now
            raise Interrupted(signum)
        self.signum = signum
        print(f"\n{SIGNAL_NAMES.get(signum, signum)}: stopping after this step and saving (send it again to stop "
              "at once)", flush=True)

    def __enter__(self) -> StopSignals:
        if threading.current_thread() is threading.main_thread():
            for sig in (signal.SIGINT, signal.SIGTERM):
                self._previous[sig] = signal.signal(sig, self._handle)
        return self

    def __exit__(self, exc_type: type | None, exc: BaseException | None, tb: TracebackType | None) -> None:
        for sig, handler in self._previous.items():
            signal.signal(sig, handler)  # type: ignore[arg-type]
        self._previous.clear()

    def raise_if_requested(self, message: str = "") -> None:
        """After the job saved its outputs: raise :class:`Interrupted` if a signal asked to stop."""
        if self.signum is not None:
            raise Interrupted(self.signum, message)


def end_loop(stop: StopSignals, *resources) -> None:
    """The ``finally`` of a training loop run under ``stop`` (entered by hand so the loop is not nested once more):
    restore the previous signal handlers, then close each resource (progress bar, TensorBoard writer, env) in order."""
    stop.__exit__(None, None, None)
    for resource in resources:
        resource.close()


def ignore_stop_signals(worker_id: int = 0) -> None:
    """DataLoader ``worker_init_fn``: loader workers ignore SIGINT and SIGTERM.

    Ctrl-C in a terminal and ``timeout``/``kill`` on a process group signal every process of the group. Torch's
    workers die on SIGTERM, and the main process then fails while it saves its checkpoint; ignoring the signals
    leaves the decision to the main process, which stops, saves and shuts its workers down.
    """
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    signal.signal(signal.SIGTERM, signal.SIG_IGN)
