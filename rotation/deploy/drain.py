"""The thread that moves the sensors' new samples into the recording beside the control loop, so a drain never
delays a control step.
"""

from __future__ import annotations

import logging
import threading

log = logging.getLogger("rotation.deploy.loop")  # the loop's own logger: its messages are the loop's



class Drains:
    """Several sensor drains (Digit 360, skin) behind one ``drain(append)``."""

    def __init__(self, drains: list) -> None:
        self.drains = drains

    def drain(self, append) -> None:
        for d in self.drains:
            d.drain(append)


class DrainThread:
    """Moves the sensors' samples into the recording every ``every_s`` from its own thread, so that the control
    loop never waits for it: a drain of four fingertips' camera frames and audio is a few ms on an idle machine but
    took 250-500 ms on a busy 2-core one (every step of it waits its turn for the interpreter's lock among the
    sensors' threads), and on the loop's thread it cost the run most of its 20 Hz slots. A failed drain (a
    SessionError) is kept and raised by :meth:`check`, which the loop calls every step."""

    def __init__(self, drain: Drains, append, every_s: float) -> None:
        self.drain, self.append, self.every_s = drain, append, every_s
        self.error: BaseException | None = None
        self._drained = False  # the run's samples are all in the recording
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, name="deploy-drain", daemon=True)
        self._thread.start()

    def _run(self) -> None:
        while not self._stop.wait(self.every_s):
            try:
                self.drain.drain(self.append)
            except BaseException as err:  # noqa: BLE001 -- handed to the loop's thread by check()
                self.error = err
                return

    def check(self) -> None:
        """Raise the drain's error, if one ended it."""
        if self.error is not None:
            raise self.error

    def stop(self, final_drain: bool) -> None:
        """Stop. ``final_drain`` (a run that ended well): wait for a drain in progress, then move what came since.
        Otherwise (a fault: the motors go off first) nothing is waited for here; :meth:`drain_rest` moves the
        samples of the run's last moments once the hand is off."""
        self._stop.set()
        if final_drain:
            self._thread.join()
            self.check()
            self.drain.drain(self.append)
            self._drained = True

    def drain_rest(self, timeout_s: float) -> bool:
        """After a fault, once the motors are off: wait up to ``timeout_s`` for a drain in progress, then move the
        samples that came since (the moments before a fault are those a lab most wants to look at). False (logged)
        when they could not be recorded: a drain still busy, or the recording failed."""
        if self._drained:
            return True
        self._stop.set()
        self._thread.join(timeout=timeout_s)
        if self._thread.is_alive():
            log.warning("recording: a drain still busy %.1f s after the run; the sensors' last samples are not in "
                        "the session", timeout_s)
            return False
        if self.error is not None:
            log.warning("recording: the sensors' last samples are not in the session (a drain failed: %s)",
                        self.error)
            return False
        try:
            self.drain.drain(self.append)
        except Exception as err:  # noqa: BLE001 -- the hand is off; the run's outcome is already decided
            log.error("recording: the sensors' last samples could not be recorded: %s", err)
            return False
        self._drained = True
        return True
