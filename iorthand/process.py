"""Child processes that never outlive their parent: Linux's PR_SET_PDEATHSIG and the start of a spawned child,
in one place for every role (the demo's processes, the twin's viewer, the operator's sender, the edge's media
process, the benchmarks' roles)."""

from __future__ import annotations

import contextlib
import ctypes
import os
import signal

_PR_SET_PDEATHSIG = 1


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


__all__ = ["die_with_parent", "enter_child"]
