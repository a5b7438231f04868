"""Child processes that never outlive their parent: Linux's PR_SET_PDEATHSIG and the start of a spawned child,
in one place for every role (the demo's processes, the twin's viewer, the operator's sender, the edge's media
process, the benchmarks' roles); and the real-time priority of the few threads that get one. No Zenoh here: the
UR driver's child process imports this and must start fast."""

from __future__ import annotations

import contextlib
import ctypes
import logging
import os
import signal
import threading

log = logging.getLogger(__name__)

_PR_SET_PDEATHSIG = 1


# The SCHED_FIFO priority of the few threads that get one. A service user needs no root for it: an
# RLIMIT_RTPRIO of at least this much is enough (deploy/systemd/iorthand-edge.service: LimitRTPRIO).
REALTIME_PRIORITY = 10


def raise_priority(realtime: bool, priority: int = REALTIME_PRIORITY) -> str:
    """Best effort SCHED_FIFO at ``priority`` for the calling thread (root, CAP_SYS_NICE or RLIMIT_RTPRIO ≥ it);
    returns what it got. Only for threads that block between short bursts of work (a fixed-rate sender, a control
    loop): a spinning one would starve others, so a process must never run real-time as a whole."""
    if not realtime or not hasattr(os, "sched_setscheduler"):
        return "normal"
    try:
        # SCHED_RESET_ON_FORK: a thread or process this thread starts (the UR driver, restarted by the control
        # loop after a fault) begins at normal priority instead of inheriting real time.
        os.sched_setscheduler(threading.get_native_id(), os.SCHED_FIFO | os.SCHED_RESET_ON_FORK,
                              os.sched_param(priority))
        return "SCHED_FIFO"
    except (PermissionError, OSError) as exc:
        log.debug("thread stays at normal priority: %s", exc)
        return f"normal ({exc.strerror or exc})"


def die_with_parent(sig: int = signal.SIGTERM) -> None:
    """Ask the kernel for ``sig`` when the thread that started this process ends. Linux only: elsewhere nothing
    happens, and callers keep their own parent-pid checks. Usable as ``subprocess``'s ``preexec_fn``."""
    with contextlib.suppress(OSError, AttributeError):
        ctypes.CDLL("libc.so.6", use_errno=True).prctl(_PR_SET_PDEATHSIG, sig)


def enter_child(parent_pid: int, pdeathsig: bool = True) -> None:
    """The first thing a spawned child that works for ``parent_pid`` does: die with it (``pdeathsig``), leave at
    once if it is already gone (it died before the request), ignore Ctrl-C (it reaches the whole process group,
    and the parent stops its children), and leave at once on SIGTERM: the interpreter's own shutdown joins
    Zenoh's threads and can hang, which would leave an orphan."""
    if pdeathsig:
        die_with_parent()
    if os.getppid() != parent_pid:
        os._exit(0)
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    signal.signal(signal.SIGTERM, lambda *_: os._exit(0))


__all__ = ["REALTIME_PRIORITY", "die_with_parent", "enter_child", "raise_priority"]
