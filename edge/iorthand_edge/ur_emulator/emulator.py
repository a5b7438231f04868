"""The emulator as one object: controller + RTDE/dashboard/script/control servers + fault injection."""

from __future__ import annotations

import logging
import threading
from dataclasses import dataclass, field
from typing import Any

from iorthand.config import from_dict
from iorthand_edge.force.contact import PhantomConfig

from .controller import Controller, ControllerConfig, SafetyMode
from .dashboard import handle_dashboard
from .faults import handle_control
from .net import Listener, Registry
from .rtde_server import handle_rtde
from .script_server import handle_script

log = logging.getLogger("iorthand_edge.ur_emulator")

#: Default control (fault-injection) port; not a UR port.
DEFAULT_CONTROL_PORT = 30101


@dataclass
class EmulatorConfig:
    """Where the emulator listens. ur_rtde 1.6.5 hard-codes the ports (RTDE 30004, dashboard 29999, script
    30003), so several emulators coexist by binding different loopback addresses (127.0.0.2, 127.0.0.3, ...)
    rather than different ports."""

    host: str = "127.0.0.1"
    rtde_port: int = 30004
    dashboard_port: int = 29999
    script_ports: tuple[int, ...] = (30002, 30003)
    control_port: int | None = DEFAULT_CONTROL_PORT  # None: no control socket
    controller: ControllerConfig = field(default_factory=ControllerConfig)


class UREmulator:
    """A UR e-Series controller that the real ur_rtde library accepts.

    In-process use::

        with UREmulator(EmulatorConfig(host="127.0.0.2")) as emu:
            ...  # RTDEReceiveInterface("127.0.0.2"), RTDEControlInterface("127.0.0.2", 125.0)
            emu.protective_stop()

    Every public fault method is also reachable through the control socket (see :mod:`.faults`).
    """

    def __init__(self, config: EmulatorConfig | None = None) -> None:
        self.config = config or EmulatorConfig()
        self.controller = Controller(self.config.controller)
        self.registry = Registry()
        hung = self._is_hung
        c, host = self.controller, self.config.host
        self.listeners: list[Listener] = [
            Listener("rtde", host, self.config.rtde_port, handle_rtde(c), self.registry, hung),
            Listener("dashboard", host, self.config.dashboard_port, handle_dashboard(c), self.registry, hung),
        ]
        for port in self.config.script_ports:
            self.listeners.append(
                Listener(f"script{port}", host, port, handle_script(c, str(port)), self.registry, hung))
        self._control: Listener | None = None
        if self.config.control_port is not None:
            # The back door has its own registry and never hangs: faults must stay undoable.
            self._control = Listener("control", host, self.config.control_port, handle_control(self),
                                     Registry(), lambda: False)
        self._restore_timer: threading.Timer | None = None
        self._lock = threading.Lock()
        self.running = False

    def _is_hung(self) -> bool:
        return self.controller.faults.hung

    # -- lifecycle -------------------------------------------------------------------------------------

    def start(self) -> UREmulator:
        try:
            for lst in self.listeners:
                lst.bind()
            if self._control is not None:
                self._control.bind()
        except OSError:
            self._unbind_all()
            raise
        self.controller.start()
        self.running = True
        log.info("UR emulator on %s", self.endpoints())
        return self

    def stop(self) -> None:
        if self._restore_timer is not None:
            self._restore_timer.cancel()
        self._unbind_all()
        self.registry.close_all()
        self.controller.stop()
        self.running = False

    def _unbind_all(self) -> None:
        for lst in self.listeners:
            lst.unbind()
        if self._control is not None:
            self._control.unbind()

    def __enter__(self) -> UREmulator:
        return self.start()

    def __exit__(self, *exc: object) -> None:
        self.stop()

    def endpoints(self) -> dict[str, Any]:
        h = self.config.host
        eps: dict[str, Any] = {lst.name: f"{h}:{lst.port}" for lst in self.listeners}
        if self._control is not None:
            eps["control"] = f"{h}:{self._control.port}"
        eps["frequency"] = self.controller.config.frequency
        eps["version"] = ".".join(str(v) for v in self.controller.config.version)
        return eps

    # -- fault injection (also the control socket's operations) ---------------------------------------

    def status(self) -> dict[str, Any]:
        return self.controller.status()

    def drop_link(self, duration: float | None = None) -> dict[str, Any]:
        """Link lost: close every client connection and refuse new ones for ``duration`` seconds (None: until
        :meth:`restore_link`). The robot keeps doing what it was doing, as a real one would."""
        with self._lock:
            if self._restore_timer is not None:
                self._restore_timer.cancel()
                self._restore_timer = None
            for lst in self.listeners:
                lst.unbind()
            closed = self.registry.close_all()
            self.controller.faults.link_down = True
            self.controller.event(f"link dropped ({closed} connections closed), duration {duration}")
            if duration is not None:
                self._restore_timer = threading.Timer(duration, self.restore_link)
                self._restore_timer.daemon = True
                self._restore_timer.start()
        return {"closed": closed}

    def restore_link(self) -> None:
        with self._lock:
            if not self.controller.faults.link_down:
                return
            for lst in self.listeners:
                lst.bind()
            self.controller.faults.link_down = False
            self.controller.event("link restored")

    def freeze(self, mode: str = "stale") -> None:
        """Freeze the output streams: ``stale`` keeps sending the frozen state (timestamps stop, the client stays
        connected and sees old data); ``silent`` sends nothing (ur_rtde's reader times out after 2.5 s and
        drops the connection itself)."""
        if mode not in ("stale", "silent"):
            raise ValueError("mode must be 'stale' or 'silent'")
        with self.controller.lock:
            self.controller.faults.frozen = self.controller.snapshot
            self.controller.faults.freeze = mode
            self.controller.event(f"output stream frozen ({mode})")

    def unfreeze(self) -> None:
        with self.controller.lock:
            self.controller.faults.freeze = None
            self.controller.faults.frozen = None
            self.controller.event("output stream unfrozen")

    def protective_stop(self, reason: str = "injected") -> None:
        self.controller.protective_stop(reason)

    def clear_protective_stop(self) -> None:
        """Clear it regardless of the unlock delay (what an operator does on the pendant)."""
        with self.controller.lock:
            self.controller.protective_stop_time = -1e9
            self.controller.unlock_protective_stop()

    def emergency_stop(self, reason: str = "injected") -> None:
        self.controller.emergency_stop(reason)

    def release_emergency_stop(self) -> None:
        self.controller.release_emergency_stop()

    # -- what a person at the teach pendant does ---------------------------------------------------------

    def set_speed_slider(self, fraction: float) -> None:
        """The pendant's speed slider (0..1): every motion runs at this fraction of its commanded speed."""
        if not 0.0 <= float(fraction) <= 1.0:
            raise ValueError(f"fraction must be within [0, 1], got {fraction!r}")
        with self.controller.lock:
            self.controller.speed_fraction = float(fraction)
            self.controller.event(f"speed slider at {100 * float(fraction):.0f} %")

    def set_remote_control(self, on: bool) -> None:
        """Remote control on or off (local control), as the pendant's switch does. In local control the dashboard
        answers "false" to ``is in remote control`` and no program from outside starts; one already running goes
        on, and RTDE still writes its input registers (RTDE has no bit for it: a client must ask the dashboard)."""
        with self.controller.lock:
            self.controller.remote_control = bool(on)
            self.controller.event(f"{'remote' if on else 'local'} control")

    def set_safety_mode(self, mode: str, reason: str = "injected") -> None:
        """The safety system enters ``mode``, a :class:`.controller.SafetyMode` name (SAFEGUARD_STOP, REDUCED,
        NORMAL, VIOLATION, FAULT, ...); see :meth:`.controller.Controller.set_safety_mode`."""
        try:
            safety = SafetyMode[str(mode).upper()]
        except KeyError:
            raise ValueError(f"unknown safety mode {mode!r}; expected one of {', '.join(SafetyMode.__members__)}") from None
        self.controller.set_safety_mode(safety, reason)

    def set_tcp(self, offset: list[float]) -> None:
        """The installation's active TCP (a UR pose in the flange frame, m and rotation vector)."""
        if len(offset) != 6:
            raise ValueError("offset must have 6 values (x, y, z, rx, ry, rz)")
        with self.controller.lock:
            self.controller.model.set_tcp([float(v) for v in offset])
            self.controller.event(f"TCP offset set to {list(offset)}")

    def set_payload(self, mass: float, cog: list[float] | None = None) -> None:
        """The installation's payload (kg, centre of gravity in m in the flange frame)."""
        if not 0.0 <= float(mass) <= 50.0:
            raise ValueError(f"mass must be within [0, 50] kg, got {mass!r}")
        with self.controller.lock:
            self.controller.payload = float(mass)
            self.controller.payload_cog = [float(v) for v in (cog or [0.0, 0.0, 0.0])]
            self.controller.event(f"payload set to {mass} kg")

    def set_force(self, wrench: list[float]) -> None:
        if len(wrench) != 6:
            raise ValueError("wrench must have 6 values (Fx, Fy, Fz, Tx, Ty, Tz)")
        with self.controller.lock:
            self.controller.raw_force = [float(v) for v in wrench]

    def hang(self) -> None:
        """The controller hangs: new TCP connections are accepted and never answered; open connections get no
        more data and no answers."""
        with self.controller.lock:
            self.controller.faults.hung = True
            self.controller.event("controller hung")

    def unhang(self) -> None:
        with self.controller.lock:
            self.controller.faults.hung = False
            self.controller.event("controller no longer hung")
        self.registry.release_parked()

    def set_dashboard_silent(self, on: bool) -> None:
        """The dashboard server (29999) reads commands and answers none while ``on``; RTDE and the script ports
        go on (a dashboard disabled or stuck while the controller runs)."""
        with self.controller.lock:
            self.controller.faults.dashboard_silent = bool(on)
            self.controller.event(f"dashboard {'silent' if on else 'answering again'}")

    def stop_program(self) -> None:
        self.controller.stop_program("stopped by fault injection", decelerate=True)

    def set_pose(self, pose: list[float]) -> None:
        """Put the arm at rest with its TCP at ``pose``, the joints by inverse kinematics nearest the current ones
        (ValueError when out of reach or beyond the joint limits)."""
        if len(pose) != 6:
            raise ValueError("pose must have 6 values")
        with self.controller.lock:
            self.controller.model.place([float(v) for v in pose])

    def set_joints(self, q: list[float]) -> None:
        """Put the arm at rest at joints ``q`` (rad); ValueError beyond the joint limits."""
        if len(q) != 6:
            raise ValueError("q must have 6 values")
        with self.controller.lock:
            self.controller.model.place_joints([float(v) for v in q])

    def set_phantom(self, phantom: dict[str, Any] | None = None) -> None:
        """Place a phantom (the keys of :class:`iorthand_edge.force.contact.PhantomConfig`, checked like a
        configuration file) for the F/T sensor and force mode to press on; None removes it."""
        config = None if phantom is None else from_dict(phantom, PhantomConfig, source="set_phantom")
        with self.controller.lock:
            self.controller.phantom = config
            self.controller.event(f"phantom {'removed' if config is None else f'set: {config}'}")

    def clear_faults(self) -> None:
        self.restore_link()
        self.unfreeze()
        self.unhang()
        self.set_dashboard_silent(False)
        self.release_emergency_stop()
        self.clear_protective_stop()
        self.set_force([0.0] * 6)
        self.set_speed_slider(1.0)
        self.set_remote_control(True)
