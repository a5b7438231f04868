"""RTDE server (port 30004): protocol negotiation, recipes, streaming and input packages.

Each client connection gets its own session: a reader (this handler's thread) that answers control packages
and applies input data packages, and a sender thread that encodes the newest controller snapshot at the
client's requested frequency. Several clients (RTDEReceiveInterface, RTDEControlInterface, RTDEIOInterface)
can be connected at once, each with its own recipes, as on a real controller.
"""

from __future__ import annotations

import contextlib
import itertools
import logging
import socket
import struct
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass

from . import protocol as p
from .controller import Controller, Snapshot
from .net import set_send_timeout

log = logging.getLogger("iorthand_edge.ur_emulator")

_conn_ids = itertools.count(1)
MAX_FREQUENCY = 500.0


def _getter(name: str) -> Callable[[Snapshot], object]:
    reg = p.register_type(name)
    if reg is not None:
        direction, kind, idx = reg
        if kind == "int":
            return (lambda s: s.out_int[idx]) if direction == "output" else (lambda s: s.in_int[idx])
        if kind == "double":
            return (lambda s: s.out_double[idx]) if direction == "output" else (lambda s: s.in_double[idx])
        return (lambda s: bool(s.out_bits >> idx & 1)) if direction == "output" else (
            lambda s: bool(s.in_bits >> idx & 1))
    if name == "timestamp":
        return lambda s: s.timestamp
    if name == "output_bit_registers0_to_31":
        return lambda s: s.out_bits & 0xFFFFFFFF
    if name == "output_bit_registers32_to_63":
        return lambda s: (s.out_bits >> 32) & 0xFFFFFFFF
    if name == "input_bit_registers0_to_31":
        return lambda s: s.in_bits & 0xFFFFFFFF
    if name == "input_bit_registers32_to_63":
        return lambda s: (s.in_bits >> 32) & 0xFFFFFFFF
    default = _default_for(p.OUTPUT_TYPES[name])
    return lambda s: s.values.get(name, default)


def _default_for(type_name: str) -> object:
    fmt = p.TYPE_FORMATS[type_name]
    if fmt[0].isdigit():
        n = int(fmt[:-1])
        return (0.0,) * n if fmt[-1] == "d" else (0,) * n
    return 0.0 if fmt == "d" else (False if fmt == "?" else 0)


@dataclass
class OutputRecipe:
    recipe_id: int
    names: list[str]
    frequency: float
    struct: struct.Struct
    getters: list[Callable[[Snapshot], object]]
    next_due: float = 0.0

    def encode(self, snap: Snapshot) -> bytes:
        values = p.flatten([g(snap) for g in self.getters])
        return p.pack_message(p.DATA_PACKAGE, self.struct.pack(self.recipe_id, *values))


@dataclass
class InputRecipe:
    recipe_id: int
    names: list[str]
    struct: struct.Struct
    sizes: list[int]  # number of struct items per variable (vectors take several)


class RtdeSession:
    def __init__(self, sock: socket.socket, addr: tuple[str, int], ctrl: Controller) -> None:
        self.sock, self.addr, self.ctrl = sock, addr, ctrl
        self.conn_id = next(_conn_ids)
        self.protocol_version = 2
        self.outputs: list[OutputRecipe] = []
        self.inputs: dict[int, InputRecipe] = {}
        self.started = False
        self._send_lock = threading.Lock()
        self._cond = threading.Condition()
        self._pending: list[bytes] = []
        self._closed = False
        set_send_timeout(sock, 2.0)

    # -- sending ---------------------------------------------------------------------------------------

    def _send(self, data: bytes) -> None:
        with self._send_lock:
            self.sock.sendall(data)

    def _reply(self, msg_type: int, payload: bytes) -> None:
        if self.ctrl.faults.hung:
            return  # a hung controller reads but never answers
        self._send(p.pack_message(msg_type, payload))

    def on_snapshot(self, snap: Snapshot) -> None:
        """Called by the tick thread: queue the packages that are due (encoding happens here, cheaply)."""
        if not self.started:
            return
        now = time.monotonic()
        out = []
        for r in self.outputs:
            if now + 1e-4 >= r.next_due:
                # Schedule on the nominal grid, but never build up a backlog after a stall.
                r.next_due = max(r.next_due + 1.0 / r.frequency, now)
                out.append(r.encode(snap))
        if out:
            with self._cond:
                # Keep only the newest packages if the client is slow: stale state is worthless.
                self._pending = (self._pending + out)[-len(self.outputs) * 2:]
                self._cond.notify()

    def _sender(self) -> None:
        while True:
            with self._cond:
                while not self._pending and not self._closed:
                    self._cond.wait(0.5)
                if self._closed:
                    return
                batch, self._pending = self._pending, []
            try:
                self._send(b"".join(batch))
            except OSError as exc:
                log.info("RTDE %s: send failed (%s), closing", self.addr, exc)
                self._closed = True
                with contextlib.suppress(OSError):
                    self.sock.shutdown(socket.SHUT_RDWR)
                return

    # -- reading ---------------------------------------------------------------------------------------

    def serve(self) -> None:
        log.info("RTDE client %s connected (id %d)", self.addr, self.conn_id)
        sender = threading.Thread(target=self._sender, name="ur-emu-rtde-send", daemon=True)
        sender.start()
        self.ctrl.add_listener(self.on_snapshot)
        try:
            while True:
                msg_type, payload = p.read_message(self.sock)
                self._handle(msg_type, payload)
        finally:
            self.ctrl.remove_listener(self.on_snapshot)
            self.ctrl.release_inputs(self.conn_id)
            with self._cond:
                self._closed = True
                self._cond.notify()
            log.info("RTDE client %s disconnected (id %d)", self.addr, self.conn_id)

    def _handle(self, msg_type: int, payload: bytes) -> None:
        c = self.ctrl
        if msg_type == p.REQUEST_PROTOCOL_VERSION:
            (version,) = struct.unpack(">H", payload[:2])
            # Only protocol 2 is emulated (v1 has no frequency and no recipe ids); clients ask for 2 first.
            ok = version == 2
            if ok:
                self.protocol_version = version
            self._reply(msg_type, struct.pack(">B", 1 if ok else 0))
        elif msg_type == p.GET_URCONTROL_VERSION:
            self._reply(msg_type, struct.pack(">IIII", *c.config.version))
        elif msg_type == p.CONTROL_PACKAGE_SETUP_OUTPUTS:
            self._setup_outputs(payload)
        elif msg_type == p.CONTROL_PACKAGE_SETUP_INPUTS:
            self._setup_inputs(payload)
        elif msg_type == p.CONTROL_PACKAGE_START:
            ok = bool(self.outputs) or bool(self.inputs)
            now = time.monotonic()
            for r in self.outputs:
                r.next_due = now
            self.started = ok
            self._reply(msg_type, struct.pack(">B", 1 if ok else 0))
        elif msg_type == p.CONTROL_PACKAGE_PAUSE:
            self.started = False
            self._reply(msg_type, struct.pack(">B", 1))
        elif msg_type == p.DATA_PACKAGE:
            self._input_package(payload)
        else:
            log.warning("RTDE %s: unknown package type %d ignored", self.addr, msg_type)

    def _setup_outputs(self, payload: bytes) -> None:
        if self.protocol_version >= 2:
            (freq,) = struct.unpack(">d", payload[:8])
            text = payload[8:]
        else:
            freq, text = self.ctrl.config.frequency, payload
        names = [n for n in text.decode("ascii", "replace").split(",") if n]
        types = [p.output_type(n) or "NOT_FOUND" for n in names]
        # e-Series accepts up to 500 Hz. A slower emulator loop still accepts it and sends once per cycle:
        # refusing would leave RTDEReceiveInterface's constructor waiting forever for a first package.
        valid = bool(names) and "NOT_FOUND" not in types and 0 < freq <= MAX_FREQUENCY
        if "NOT_FOUND" in types:
            missing = [n for n, t in zip(names, types, strict=True) if t == "NOT_FOUND"]
            log.warning("RTDE %s: output variables not found: %s", self.addr, missing)
        recipe_id = len(self.outputs) + 1 if valid else 0
        if valid:
            fmt = ">B" + "".join(p.TYPE_FORMATS[t] for t in types)
            self.outputs.append(OutputRecipe(recipe_id, names, freq, struct.Struct(fmt),
                                             [_getter(n) for n in names]))
            log.info("RTDE %s: output recipe %d at %g Hz: %d variables", self.addr, recipe_id, freq, len(names))
        reply = (struct.pack(">B", recipe_id) if self.protocol_version >= 2 else b"") + ",".join(types).encode()
        self._reply(p.CONTROL_PACKAGE_SETUP_OUTPUTS, reply)

    def _setup_inputs(self, payload: bytes) -> None:
        names = [n for n in payload.decode("ascii", "replace").split(",") if n]
        types = [p.input_type(n) or "NOT_FOUND" for n in names]
        known = [n for n, t in zip(names, types, strict=True) if t != "NOT_FOUND"]
        taken = self.ctrl.claim_inputs(self.conn_id, known)
        types = ["IN_USE" if n in taken else t for n, t in zip(names, types, strict=True)]
        valid = bool(names) and all(t not in ("NOT_FOUND", "IN_USE") for t in types)
        recipe_id = 0
        if valid:
            recipe_id = len(self.inputs) + 1
            fmts = [p.TYPE_FORMATS[t] for t in types]
            sizes = [int(f[:-1]) if f[0].isdigit() else 1 for f in fmts]
            self.inputs[recipe_id] = InputRecipe(recipe_id, names, struct.Struct(">" + "".join(fmts)), sizes)
        else:
            log.warning("RTDE %s: input recipe refused: %s", self.addr, dict(zip(names, types, strict=True)))
        self._reply(p.CONTROL_PACKAGE_SETUP_INPUTS, struct.pack(">B", recipe_id) + ",".join(types).encode())

    def _input_package(self, payload: bytes) -> None:
        if not payload:
            return
        recipe = self.inputs.get(payload[0])
        if recipe is None:
            log.warning("RTDE %s: data package for unknown input recipe %d", self.addr, payload[0])
            return
        body = payload[1:]
        if len(body) < recipe.struct.size:
            log.warning("RTDE %s: input package for recipe %d too short (%d < %d bytes)", self.addr,
                        recipe.recipe_id, len(body), recipe.struct.size)
            return
        flat = recipe.struct.unpack(body[: recipe.struct.size])
        values: list[object] = []
        i = 0
        for n in recipe.sizes:
            values.append(flat[i] if n == 1 else list(flat[i:i + n]))
            i += n
        self.ctrl.apply_inputs(recipe.names, values)


def handle_rtde(ctrl: Controller) -> Callable[[socket.socket, tuple[str, int]], None]:
    def handler(sock: socket.socket, addr: tuple[str, int]) -> None:
        RtdeSession(sock, addr, ctrl).serve()

    return handler
