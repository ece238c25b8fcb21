"""Real-time scheduling for the control threads (Linux).

A PD loop at 333 Hz on a busy 2-core machine misses its slots when it competes with other processes; with
``SCHED_FIFO`` it preempts them. Threads inherit the policy of the thread that creates them, so call this
before starting the hand. Needs root or CAP_SYS_NICE (``setcap cap_sys_nice+ep`` on the interpreter, or
``ulimit -r``); without them it reports why and changes nothing.
"""

from __future__ import annotations

import logging
import os

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
