"""Real-time scheduling for the control threads (Linux).

A PD loop at 333 Hz on a busy 2-core machine misses its slots when it competes with other processes; with
``SCHED_FIFO`` it preempts them. Threads inherit the policy of the thread that creates them, so call this
before starting the hand. Needs root or CAP_SYS_NICE (``setcap cap_sys_nice+ep`` on the interpreter, or
``ulimit -r``); without them it reports why and changes nothing.

The drivers' receive threads are Python threads: whatever holds the interpreter's lock stops them. The longest such
hold in a control process is a full pass of the cyclic garbage collector, which scans every tracked object: with
torch, MuJoCo and a policy loaded that is 0.1-0.5 s, longer than the hands' 0.3 s feedback watchdog, so a pass at
the wrong moment reads as a hand that stopped answering. ``frozen_heap`` keeps those passes short.
"""

from __future__ import annotations

import contextlib
import gc
import logging
import os
import threading
from collections.abc import Iterator

log = logging.getLogger(__name__)


def set_realtime_priority(priority: int) -> str:
    """Put the calling thread under SCHED_FIFO at ``priority`` (1..99); 0 leaves it alone.

    Returns a description of the policy in force (for logs and benchmark reports).
    """
    if priority == 0:
        return "SCHED_OTHER"
    if not 1 <= priority <= 99:
        raise ValueError(f"real-time priority must be 1..99 (or 0 for none), got {priority}")
    if not hasattr(os, "sched_setscheduler"):
        log.warning("SCHED_FIFO is not available on this platform; running unprioritized")
        return "SCHED_OTHER (SCHED_FIFO unavailable)"
    try:
        os.sched_setscheduler(0, os.SCHED_FIFO, os.sched_param(priority))
    except PermissionError as err:
        log.warning("could not set SCHED_FIFO %d (%s); running unprioritized", priority, err)
        return f"SCHED_OTHER (SCHED_FIFO {priority} refused: {err.strerror})"
    return f"SCHED_FIFO {priority}"


_freeze_lock = threading.Lock()
_freeze_depth = 0


@contextlib.contextmanager
def frozen_heap() -> Iterator[int]:
    """Collect once, then hide every surviving object from the cyclic GC until the block ends (``gc.freeze``): the
    passes inside the block scan only what it allocates, in milliseconds. Yields the number of objects frozen.

    Cycles made inside the block are still collected; what the block frees of the frozen objects is reclaimed by
    reference counting as usual, frozen cycles once the block has ended. Blocks nest: only the outermost one gives
    the heap back (``gc.unfreeze`` is global)."""
    global _freeze_depth
    with _freeze_lock:
        if _freeze_depth == 0:
            gc.collect()
            gc.freeze()
        _freeze_depth += 1
    try:
        yield gc.get_freeze_count()
    finally:
        with _freeze_lock:
            _freeze_depth -= 1
            if _freeze_depth == 0:
                gc.unfreeze()
