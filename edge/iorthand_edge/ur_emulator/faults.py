"""Fault injection from outside the emulator's process: a JSON-lines control socket and its client.

Protocol: the client sends one JSON object per line, ``{"op": "<name>", ...arguments}``; the server answers
one line ``{"ok": true, "result": ...}`` or ``{"ok": false, "error": "..."}``. The control socket is not
affected by the faults it injects (a link drop or a hang leaves it working), so tests can always undo them.

Operations (see :data:`OPS`): ``status``, ``drop_link`` (``duration`` s, or until ``restore_link``),
``restore_link``, ``freeze`` (``mode`` "stale" | "silent"), ``unfreeze``, ``protective_stop``,
``clear_protective_stop``, ``emergency_stop``, ``release_emergency_stop``, ``set_force`` (``wrench`` [6]),
``hang``, ``unhang``, ``set_dashboard_silent`` (``on``), ``stop_program``, ``set_pose`` (``pose`` [6]), ``set_joints`` (``q`` [6]),
``set_phantom`` (``phantom``: the keys of a PhantomConfig, or null to remove it), ``clear_faults``; and what a
person at the teach pendant does: ``set_speed_slider`` (``fraction`` 0..1), ``set_remote_control`` (``on``),
``set_safety_mode`` (``mode``: SAFEGUARD_STOP, REDUCED, NORMAL, ...), ``set_tcp`` (``offset`` [6]),
``set_payload`` (``mass`` kg, ``cog`` [3]).
"""

from __future__ import annotations

import json
import logging
import socket
from collections.abc import Callable
from typing import TYPE_CHECKING, Any

if TYPE_CHECKING:
    from .emulator import UREmulator

log = logging.getLogger("iorthand_edge.ur_emulator")

OPS = (
    "status", "drop_link", "restore_link", "freeze", "unfreeze", "protective_stop", "clear_protective_stop",
    "emergency_stop", "release_emergency_stop", "set_force", "hang", "unhang", "stop_program", "set_pose",
    "set_joints", "set_phantom", "clear_faults", "set_speed_slider", "set_remote_control", "set_safety_mode",
    "set_tcp", "set_payload", "set_dashboard_silent",
)


def dispatch(emu: UREmulator, request: dict[str, Any]) -> Any:
    op = request.get("op")
    if op not in OPS:
        raise ValueError(f"unknown op {op!r}; expected one of {', '.join(OPS)}")
    args = {k: v for k, v in request.items() if k != "op"}
    return getattr(emu, op)(**args)


def handle_control(emu: UREmulator) -> Callable[[socket.socket, tuple[str, int]], None]:
    def handler(sock: socket.socket, addr: tuple[str, int]) -> None:
        f = sock.makefile("rwb")
        for raw in f:
            try:
                request = json.loads(raw)
                if not isinstance(request, dict):
                    raise ValueError("request must be a JSON object")
                reply = {"ok": True, "result": dispatch(emu, request)}
            except Exception as exc:  # report every failure to the caller instead of dropping the line
                log.warning("control %s: %r failed: %s", addr, raw[:200], exc)
                reply = {"ok": False, "error": f"{type(exc).__name__}: {exc}"}
            f.write((json.dumps(reply) + "\n").encode())
            f.flush()

    return handler


class ControlClient:
    """Talk to a running emulator's control socket (used by the tests and ``--inject``)."""

    def __init__(self, host: str, port: int, timeout: float = 5.0) -> None:
        self.host, self.port, self.timeout = host, port, timeout
        self._sock: socket.socket | None = None
        self._file: Any = None

    def _connect(self) -> None:
        self._sock = socket.create_connection((self.host, self.port), timeout=self.timeout)
        self._file = self._sock.makefile("rwb")

    def call(self, op: str, **args: Any) -> Any:
        if self._sock is None:
            self._connect()
        self._file.write((json.dumps({"op": op, **args}) + "\n").encode())
        self._file.flush()
        line = self._file.readline()
        if not line:
            self.close()
            raise ConnectionError("emulator closed the control connection")
        reply = json.loads(line)
        if not reply.get("ok"):
            raise RuntimeError(f"emulator refused {op}: {reply.get('error')}")
        return reply.get("result")

    def close(self) -> None:
        if self._sock is not None:
            try:
                self._file.close()
                self._sock.close()
            except OSError:
                pass
        self._sock = None
        self._file = None

    def __enter__(self) -> ControlClient:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()
