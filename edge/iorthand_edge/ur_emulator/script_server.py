"""Script servers (secondary 30002, primary-style 30003): receive URScript programs.

ur_rtde's ScriptClient writes the whole control script to port 30003 without any framing and never reads.
A program is complete when a top-level ``end`` closes the ``def name():`` (or ``sec name():``) that opened
it — the body of ur_rtde's script is indented, so a column-0 ``end`` is the program's end. A complete
program replaces the running one, as on a real controller.
"""

from __future__ import annotations

import logging
import re
import socket
from collections.abc import Callable

from .control_script import ControlScriptProgram
from .controller import Controller, OpaqueProgram

log = logging.getLogger("iorthand_edge.ur_emulator")

_DEF_RE = re.compile(r"^(def|sec)\s+(\w+)\s*\(\s*\)\s*:")


def make_program(name: str, text: str) -> ControlScriptProgram | OpaqueProgram:
    # The ur_rtde control script is recognised by its command loop, whatever the program is called.
    if "def rtde_cmd():" in text and "signal_ready()" in text:
        return ControlScriptProgram(name, text)
    return OpaqueProgram(name, text)


def handle_script(ctrl: Controller, port_name: str) -> Callable[[socket.socket, tuple[str, int]], None]:
    def handler(sock: socket.socket, addr: tuple[str, int]) -> None:
        buf = ""
        current: list[str] | None = None
        name = ""
        while True:
            data = sock.recv(65536)
            if not data:
                return
            if ctrl.faults.hung:
                continue
            buf += data.decode("utf-8", "replace")
            while "\n" in buf:
                line, buf = buf.split("\n", 1)
                if current is None:
                    m = _DEF_RE.match(line)
                    if m:
                        name, current = m.group(2), [line]
                    elif line.strip():
                        # A bare statement would run as a one-line program on a real UR; not emulated.
                        ctrl.event(f"script port {port_name}: statement outside a program ignored: "
                                   f"{line.strip()[:80]!r}")
                    continue
                current.append(line)
                if line.rstrip() == "end":
                    text = "\n".join(current) + "\n"
                    current = None
                    ctrl.count(f"scripts_received_{port_name}")
                    ctrl.load_program(make_program(name, text), f"port {port_name} ({len(text)} bytes)")

    return handler
