"""Child processes that never outlive their parent: Linux's PR_SET_PDEATHSIG and the start of a spawned child,
in one place for every role (the demo's processes, the twin's viewer, the operator's sender, the edge's media
process, the benchmarks' roles); the real-time priority of the few threads that get one; and the names the
kernel shows for threads (``top -H``, ``ps -L``, ``/proc/<pid>/task/*/comm``). No Zenoh here: the UR driver's
child process imports this and must start fast."""

from __future__ import annotations

import contextlib
import ctypes
import logging
import os
import signal
import subprocess
import threading
from typing import Any

log = logging.getLogger(__name__)

_PR_SET_PDEATHSIG = 1
_PR_SET_NAME = 15
# The kernel keeps 15 bytes of a thread's name (16 with the terminating NUL).
NATIVE_NAME_BYTES = 15


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


def native_thread_name(name: str) -> str:
    """What the kernel can hold of a thread's ``name``: its leading words (``-``-separated) dropped while it is too
    long and more than two are left, so that what tells threads apart stays ("edge-video-ultrasound-send" →
    "ultrasound-send"), then cut ("edge-video-ultrasound-capture" → "ultrasound-capt")."""
    words = name.split("-")
    while len(words) > 2 and len("-".join(words).encode()) > NATIVE_NAME_BYTES:
        words.pop(0)
    return "-".join(words).encode()[:NATIVE_NAME_BYTES].decode(errors="ignore")


def name_thread(name: str) -> None:
    """Give the calling thread ``name`` (shortened by :func:`native_thread_name`) where the kernel shows it, so that
    ``top -H`` says which of a process's threads takes the CPU; Python 3.11's threads are all "python" there.
    Linux only: elsewhere nothing happens."""
    with contextlib.suppress(OSError, AttributeError):
        _libc().prctl(_PR_SET_NAME, ctypes.c_char_p(native_thread_name(name).encode()))


def _libc() -> ctypes.CDLL:
    return ctypes.CDLL("libc.so.6", use_errno=True)


def die_with_parent(sig: int = signal.SIGTERM) -> None:
    """Ask the kernel for ``sig`` when the thread that started this process ends. Linux only: elsewhere nothing
    happens, and callers keep their own parent-pid checks. Usable as ``subprocess``'s ``preexec_fn``."""
    with contextlib.suppress(OSError, AttributeError):
        _libc().prctl(_PR_SET_PDEATHSIG, sig)


def terminate(proc: subprocess.Popen[Any], timeout: float = 5.0) -> None:
    """SIGTERM, then SIGKILL after ``timeout``: the child is gone when this returns."""
    if proc.poll() is None:
        proc.terminate()
        try:
            proc.wait(timeout)
        except subprocess.TimeoutExpired:
            proc.kill()
            proc.wait(timeout)


def exit_reason(exitcode: int | None, said: str = "") -> str:
    """How a child process ended, for a log line or an operator's screen: the signal that killed it, or its exit
    code and what it said before it went (``said``)."""
    if exitcode is not None and exitcode < 0:
        with contextlib.suppress(ValueError):
            return f"was killed by {signal.Signals(-exitcode).name}"
        return f"was killed by signal {-exitcode}"
    return f"exited with code {exitcode}" + (f": {said}" if said else "")


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


__all__ = ["NATIVE_NAME_BYTES", "REALTIME_PRIORITY", "die_with_parent", "enter_child", "exit_reason", "name_thread",
           "native_thread_name", "raise_priority"]
