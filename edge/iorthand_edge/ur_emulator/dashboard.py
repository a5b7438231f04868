"""Dashboard server (port 29999): newline-terminated text commands, one answer line each.

Answers use PolyScope 5's wording, because ur_rtde's DashboardClient compares some of them literally
("Starting program", "Stopped", "Protective stop releasing", ...).
"""

from __future__ import annotations

import logging
import socket
from collections.abc import Callable

from .controller import Controller, DashboardProgram, RuntimeState, SafetyMode

log = logging.getLogger("iorthand_edge.ur_emulator")

WELCOME = "Connected: Universal Robots Dashboard Server"


def answer(ctrl: Controller, line: str) -> tuple[str, bool]:
    """Answer one dashboard command; the flag says whether to close the connection afterwards."""
    cmd = line.strip()
    low = cmd.lower()
    v = ctrl.config.version
    with ctrl.lock:
        if low == "polyscopeversion":
            return f"URSoftware {v[0]}.{v[1]}.{v[2]}.{v[3]} (Jan 01 2024)", False
        if low == "version":
            return f"{v[0]}.{v[1]}.{v[2]}.{v[3]}", False
        if low == "get serial number":
            return ctrl.config.serial_number, False
        if low == "get robot model":
            return ctrl.config.robot_model, False
        if low == "is in remote control":
            return ("true" if ctrl.remote_control else "false"), False
        if low == "robotmode":
            return f"Robotmode: {ctrl.robot_mode.name}", False
        if low == "safetymode":
            return f"Safetymode: {ctrl.safety_mode.name}", False
        if low == "safetystatus":
            return f"Safetystatus: {ctrl.safety_mode.name}", False
        if low == "programstate":
            name = ctrl.program.name if ctrl.program else (ctrl.loaded_program or "<unnamed>")
            # A program paused by a safeguard stop says so (it resumes when the safeguard is reset).
            state = {RuntimeState.PLAYING: "PLAYING", RuntimeState.PAUSED: "PAUSED"}.get(ctrl.runtime_state, "STOPPED")
            return f"{state} {name}", False
        if low == "running":
            playing = ctrl.program is not None and ctrl.runtime_state == RuntimeState.PLAYING
            return f"Program running: {'true' if playing else 'false'}", False
        if low == "isprogramsaved":
            # PolyScope answers lowercase "true <name>"; note ur_rtde's isProgramSaved() looks for "True".
            return f"true {ctrl.loaded_program or '<unnamed>'}", False
        if low.startswith("load ") and not low.startswith("load installation"):
            ctrl.loaded_program = cmd[5:].strip()
            return f"Loading program: {ctrl.loaded_program}", False
        if low == "get loaded program":
            return (f"Loaded program: {ctrl.loaded_program}" if ctrl.loaded_program else "No program loaded"), False
        if low == "play":
            if ctrl.loaded_program is None:
                return "Failed to execute: play", False
            if ctrl.load_program(DashboardProgram(ctrl.loaded_program), "dashboard play"):
                return "Starting program", False
            return "Failed to execute: play", False
        if low == "stop":
            ctrl.stop_program("dashboard stop", decelerate=True)
            return "Stopped", False
        if low == "pause":
            if ctrl.program is None:
                return "Failed to execute: pause", False
            ctrl.stop_program("dashboard pause (the emulator does not resume)", decelerate=True)
            return "Pausing program", False
        if low == "power on":
            ctrl.set_power(True)
            return "Powering on", False
        if low == "power off":
            ctrl.set_power(False)
            return "Powering off", False
        if low == "brake release":
            ctrl.brake_release()
            return "Brake releasing", False
        if low == "unlock protective stop":
            _ok, text = ctrl.unlock_protective_stop()
            return text, False
        if low == "close safety popup":
            return "closing safety popup", False
        if low == "restart safety":
            if ctrl.safety_mode in (SafetyMode.VIOLATION, SafetyMode.FAULT):
                ctrl.safety_mode = SafetyMode.NORMAL
                ctrl.set_power(False)
            return "Restarting safety", False
        if low.startswith("popup "):
            return "showing popup", False
        if low == "close popup":
            return "closing popup", False
        if low.startswith("addtolog "):
            return "Added log message", False
        if low.startswith("setuserrole "):
            return f"Setting user role: {cmd.split(' ', 1)[1]}", False
        if low == "get operational mode":
            return "NONE", False
        if low == "clear operational mode":
            return "No longer controlling the operational mode. Current operational mode: 'automatic'.", False
        if low == "quit":
            return "Disconnected", True
        if low == "shutdown":
            return "Shutting down", True
    log.info("dashboard: unknown command %r", cmd)
    return f"could not understand: '{cmd}'", False


def handle_dashboard(ctrl: Controller) -> Callable[[socket.socket, tuple[str, int]], None]:
    def handler(sock: socket.socket, addr: tuple[str, int]) -> None:
        sock.sendall((WELCOME + "\n").encode())
        buf = b""
        while True:
            data = sock.recv(4096)
            if not data:
                return
            buf += data
            while b"\n" in buf:
                raw, buf = buf.split(b"\n", 1)
                line = raw.decode("utf-8", "replace")
                if ctrl.faults.hung or ctrl.faults.dashboard_silent:
                    continue  # read, never answer
                text, close = answer(ctrl, line)
                log.debug("dashboard %s: %r -> %r", addr, line, text)
                sock.sendall((text + "\n").encode())
                if close:
                    return

    return handler
