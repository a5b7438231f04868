"""systemd's notify protocol (READY=1, WATCHDOG=1) without a dependency: one datagram to $NOTIFY_SOCKET.

:func:`cycle_hook` makes a hook for the edge agent's control loop (``agent.cycle_hooks``): its first call
says READY=1 (the loop runs, so start-up is over) and then it pings the watchdog at most every half
``WATCHDOG_USEC``. Because it runs *inside* the control loop, a control loop that hangs stops the pings and
systemd kills and restarts the agent (``WatchdogSec=`` in deploy/systemd/iorthand-edge.service). Without
``NOTIFY_SOCKET`` (not under systemd, tests) everything here is a no-op.
"""

from __future__ import annotations

import os
import socket
import time
from collections.abc import Callable
from typing import Any


def notify(state: str) -> bool:
    addr = os.environ.get("NOTIFY_SOCKET")
    if not addr:
        return False
    if addr.startswith("@"):
        addr = "\0" + addr[1:]  # abstract namespace
    try:
        with socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM) as s:
            # Never wait: this runs in the control loop, and a full socket (systemd stalled) would stop it there.
            s.sendto(state.encode(), socket.MSG_DONTWAIT, addr)
        return True
    except OSError:
        return False


def watchdog_interval() -> float | None:
    """Half the watchdog period systemd asked for (s), or None when there is no watchdog for this process."""
    usec = os.environ.get("WATCHDOG_USEC")
    pid = os.environ.get("WATCHDOG_PID")
    if not usec or (pid and pid != str(os.getpid())):
        return None
    try:
        return int(usec) / 2e6
    except ValueError:
        return None


def cycle_hook() -> Callable[[Any], None]:
    interval = watchdog_interval()
    state = {"ready": False, "last": 0.0}

    def hook(_reading: Any) -> None:
        if not state["ready"]:
            state["ready"] = True
            notify("READY=1\nSTATUS=control loop running")
        if interval is not None:
            now = time.monotonic()
            if now - state["last"] >= interval:
                state["last"] = now
                notify("WATCHDOG=1")

    return hook
