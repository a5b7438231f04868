"""The systemd notify hook: READY once, then watchdog pings rate-limited to half WATCHDOG_USEC."""

from __future__ import annotations

import os
import socket
from pathlib import Path

import pytest

from iorthand.security import sdnotify


def test_cycle_hook_notifies_ready_then_watchdog(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    path = str(tmp_path / "notify.sock")
    srv = socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM)
    srv.bind(path)
    srv.settimeout(1.0)
    monkeypatch.setenv("NOTIFY_SOCKET", path)
    monkeypatch.setenv("WATCHDOG_USEC", "10000000")  # 10 s: pings at most every 5 s
    monkeypatch.setenv("WATCHDOG_PID", str(os.getpid()))
    hook = sdnotify.cycle_hook()
    for _ in range(100):
        hook(None)
    got = []
    srv.setblocking(False)
    while True:
        try:
            got.append(srv.recv(100).decode())
        except BlockingIOError:
            break
    srv.close()
    assert got[0].startswith("READY=1") and got[1:] == ["WATCHDOG=1"]


def test_no_systemd_no_op(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.delenv("NOTIFY_SOCKET", raising=False)
    assert sdnotify.notify("READY=1") is False
    sdnotify.cycle_hook()(None)


def test_a_notify_socket_nobody_reads_never_blocks_the_control_loop(tmp_path: Path,
                                                                   monkeypatch: pytest.MonkeyPatch) -> None:
    """The watchdog ping runs in the edge's control loop. A datagram to a socket whose queue is full (systemd
    stalled, or a notify socket that no service manager reads) blocked the sender until there was room: the loop
    stopped with it. Now the ping is given up at once (systemd, stalled itself, restarts the agent if it lasts)."""
    import threading

    path = str(tmp_path / "notify.sock")
    srv = socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM)
    srv.bind(path)
    filler = socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM)
    filler.setblocking(False)
    try:
        while True:
            filler.sendto(b"WATCHDOG=1", path)
    except BlockingIOError:
        pass  # the queue is full
    monkeypatch.setenv("NOTIFY_SOCKET", path)
    answered: list[bool] = []
    sender = threading.Thread(target=lambda: answered.append(sdnotify.notify("WATCHDOG=1")), daemon=True)
    sender.start()
    sender.join(5.0)
    srv.close()  # frees a blocked sender (it fails then) so the thread ends
    filler.close()
    assert answered == [False], "notify blocked on a full socket"
