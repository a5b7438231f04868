"""The emulated controller: robot/safety/program state, RTDE registers, the 'real-time' tick.

One :class:`Controller` is shared by every server (RTDE, dashboard, script, fault control). All state is
guarded by one lock; the tick thread advances the arm (:class:`.arm.ArmModel`: TCP and joints) and the running
program at the controller frequency and publishes an immutable :class:`Snapshot` that the RTDE streams encode.

The force/torque sensor measures the wrench injected by fault injection plus, with a ``phantom``
(:class:`iorthand_edge.force.contact.PhantomConfig`), the contact with it at the current TCP pose and speed:
``actual_TCP_force`` in the base frame at the TCP, as a UR reports it, ``ft_raw_wrench`` in the tool frame.
"""

from __future__ import annotations

import logging
import math
import re
import threading
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from enum import IntEnum
from typing import Any

import numpy as np

from iorthand.geometry import rotvec_to_matrix
from iorthand_edge.force.contact import PhantomConfig, contact_force, contact_wrench

from .arm import ArmModel
from .kinematics import MotionMode
from .protocol import N_REGISTERS, register_type

log = logging.getLogger("iorthand_edge.ur_emulator")


class RuntimeState(IntEnum):
    STOPPING = 0
    STOPPED = 1
    PLAYING = 2
    PAUSING = 3
    PAUSED = 4
    RESUMING = 5


class RobotMode(IntEnum):
    NO_CONTROLLER = -1
    DISCONNECTED = 0
    CONFIRM_SAFETY = 1
    BOOTING = 2
    POWER_OFF = 3
    POWER_ON = 4
    IDLE = 5
    BACKDRIVE = 6
    RUNNING = 7


class SafetyMode(IntEnum):
    NORMAL = 1
    REDUCED = 2
    PROTECTIVE_STOP = 3
    RECOVERY = 4
    SAFEGUARD_STOP = 5
    SYSTEM_EMERGENCY_STOP = 6
    ROBOT_EMERGENCY_STOP = 7
    VIOLATION = 8
    FAULT = 9


# Bit positions of safety_status_bits (RTDE guide).
_SAFETY_BITS = {
    SafetyMode.NORMAL: (0,),
    SafetyMode.REDUCED: (1,),
    SafetyMode.PROTECTIVE_STOP: (2,),
    SafetyMode.RECOVERY: (3,),
    SafetyMode.SAFEGUARD_STOP: (4,),
    SafetyMode.SYSTEM_EMERGENCY_STOP: (5, 7),
    SafetyMode.ROBOT_EMERGENCY_STOP: (6, 7),
    SafetyMode.VIOLATION: (8,),
    SafetyMode.FAULT: (9,),
}


@dataclass(frozen=True)
class Snapshot:
    """Everything an output recipe can read, frozen at one tick."""

    timestamp: float
    values: dict[str, object]
    out_int: tuple[int, ...]
    out_double: tuple[float, ...]
    out_bits: int  # 128 bits: output bit registers 0..127
    in_int: tuple[int, ...]
    in_double: tuple[float, ...]
    in_bits: int


@dataclass
class ControllerConfig:
    frequency: float = 500.0  # e-Series control loop rate
    version: tuple[int, int, int, int] = (5, 15, 2, 0)
    serial_number: str = "20235500001"
    robot_model: str = "UR3"
    arm: str = "ur3e"  # kinematics (iorthand.kinematics.MODELS) and joint speeds
    joint_limits: tuple[tuple[float, float], ...] | None = None  # rad, 6 × (min, max); None: the arm's own
    phantom: PhantomConfig | None = None  # a surface the TCP presses on, measured by the F/T sensor
    force_gain: float = 0.005  # force mode admittance, m/s per N of force error
    unlock_delay: float = 5.0  # PolyScope refuses "unlock protective stop" this long after the stop
    stop_deceleration: float = 10.0  # m/s^2 used for protective stops and program stops
    exclusive_inputs: bool = True  # answer IN_USE when a second client claims input registers


@dataclass
class _Faults:
    freeze: str | None = None  # None, "stale" (repeat the frozen state) or "silent" (send nothing)
    frozen: Snapshot | None = None
    hung: bool = False
    link_down: bool = False
    dashboard_silent: bool = False  # the dashboard server reads and never answers (the rest works)


class Program:
    """A program executed by the controller, one step per control cycle."""

    name = "<unnamed>"

    def start(self, ctrl: Controller) -> None:
        pass

    def step(self, ctrl: Controller, now: float) -> bool:
        """Run one cycle; return False when the program has ended."""
        raise NotImplementedError


class OpaqueProgram(Program):
    """A URScript program the emulator cannot interpret (e.g. sendCustomScriptFunction).

    It "runs" for ``duration`` seconds; the output-register writes it contains are applied in order (so
    ur_rtde's custom-script handshake — ``write_output_integer_register(0 + offset, 2)`` — completes).
    """

    def __init__(self, name: str, text: str, duration: float = 0.05) -> None:
        self.name = name
        self.duration = duration
        self._writes = [
            (int(sum(int(x) for x in re.findall(r"\d+", idx))), float(val))
            for idx, val in re.findall(
                r"write_output_integer_register\(\s*([\d\s+]+?)\s*,\s*(-?\d+)\s*\)", text
            )
        ]
        self._t0 = 0.0

    def start(self, ctrl: Controller) -> None:
        self._t0 = time.monotonic()
        for idx, val in self._writes:
            ctrl.write_out_int(idx, int(val))

    def step(self, ctrl: Controller, now: float) -> bool:
        return now - self._t0 < self.duration


class DashboardProgram(Program):
    """A program started with the dashboard's ``play`` (a loaded .urp): runs until stopped, does nothing."""

    def __init__(self, name: str) -> None:
        self.name = name

    def step(self, ctrl: Controller, now: float) -> bool:
        return True


class Controller:
    def __init__(self, config: ControllerConfig | None = None) -> None:
        self.config = config or ControllerConfig()
        self.lock = threading.RLock()
        self.phantom = self.config.phantom
        self.model = ArmModel(self.config.arm, self.config.joint_limits, wrench=self.measured_wrench)
        self.t0 = time.monotonic()
        self._last_tick = self.t0
        self.in_int = [0] * N_REGISTERS
        self.in_double = [0.0] * N_REGISTERS
        self.in_bits = 0
        self.out_int = [0] * N_REGISTERS
        self.out_double = [0.0] * N_REGISTERS
        self.out_bits = 0
        self.input_updated: dict[str, float] = {}  # input name -> monotonic time of the last package
        self.input_owner: dict[str, int] = {}  # input name -> RTDE connection id that claimed it
        self.external_ft = [0.0] * 6
        self.raw_force = [0.0] * 6  # injected wrench at the TCP (N, N*m)
        self.ft_offset = [0.0] * 6  # set by zeroFtSensor
        self.payload = 0.0
        self.payload_cog = [0.0, 0.0, 0.0]
        self.digital_out = 0
        self.speed_fraction = 1.0  # the pendant's speed slider: every motion runs this much slower
        self.remote_control = True  # False: the pendant took local control; no program from outside may start
        self.robot_mode = RobotMode.RUNNING
        self.safety_mode = SafetyMode.NORMAL
        self.protective_stop_time = 0.0
        self.program: Program | None = None
        self.runtime_state = RuntimeState.STOPPED  # PAUSED: the program stays loaded and does not step
        self.loaded_program: str | None = None
        self.watchdog: tuple[str, float] | None = None  # (input name, min frequency)
        self.faults = _Faults()
        self.events: list[str] = []  # human-readable log of notable things, exposed by status()
        self.counters: dict[str, int] = {}
        self.snapshot = self._build_snapshot(self.t0)
        self._listeners: list[Callable[[Snapshot], None]] = []
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None

    # -- lifecycle -------------------------------------------------------------------------------------

    def start(self) -> None:
        self._stop.clear()
        self._thread = threading.Thread(target=self._run, name="ur-emulator-tick", daemon=True)
        self._thread.start()

    def stop(self) -> None:
        self._stop.set()
        if self._thread is not None:
            self._thread.join(timeout=2.0)

    def add_listener(self, fn: Callable[[Snapshot], None]) -> None:
        with self.lock:
            self._listeners.append(fn)

    def remove_listener(self, fn: Callable[[Snapshot], None]) -> None:
        with self.lock:
            if fn in self._listeners:
                self._listeners.remove(fn)

    def _run(self) -> None:
        period = 1.0 / self.config.frequency
        next_t = time.monotonic()
        while not self._stop.is_set():
            next_t += period
            now = time.monotonic()
            if next_t < now - 10 * period:  # fell far behind (loaded machine): skip cycles, keep real time
                next_t = now + period
            try:
                self.tick(now)
            except Exception:  # a bug in one cycle must not kill the controller
                log.exception("tick failed")
            delay = next_t - time.monotonic()
            if delay > 0:
                self._stop.wait(delay)

    # -- events ---------------------------------------------------------------------------------------

    def event(self, text: str) -> None:
        log.info("%s", text)
        self.events.append(f"{time.monotonic() - self.t0:.3f} {text}")
        del self.events[:-200]

    def count(self, key: str) -> None:
        self.counters[key] = self.counters.get(key, 0) + 1

    # -- the control cycle -----------------------------------------------------------------------------

    def tick(self, now: float) -> None:
        with self.lock:
            dt = min(now - self._last_tick, 0.1)
            self._last_tick = now
            if self.program is not None and self.runtime_state == RuntimeState.PLAYING:
                if self.watchdog is not None:
                    name, freq = self.watchdog
                    last = self.input_updated.get(name, 0.0)
                    if freq > 0 and now - last > 1.0 / freq:
                        self.stop_program(f"RTDE watchdog: no update of {name} for {now - last:.3f} s "
                                          f"(minimum {freq:g} Hz)", decelerate=True)
                program = self.program
                # step() may itself stop the program (triggerProtectiveStop): only end it if still current.
                if program is not None and not program.step(self, now) and self.program is program:
                    self.stop_program(f"program {program.name} ended", decelerate=False)
            self.model.speed_fraction = self.speed_fraction
            self.model.step(dt)
            if self.model.fault is not None:
                # The arm refused a step (out of reach, joint limit, singularity) and stopped where it was.
                reason, self.model.fault = self.model.fault, None
                self.protective_stop(reason)
            snap = self._build_snapshot(now)
            self.snapshot = snap
            if self.faults.freeze == "stale" and self.faults.frozen is not None:
                snap = self.faults.frozen
            elif self.faults.freeze == "silent" or self.faults.hung:
                return
            listeners = list(self._listeners)
        for fn in listeners:
            fn(snap)

    def _build_snapshot(self, now: float) -> Snapshot:
        m = self.model
        force = self.measured_wrench(m.pose, m.twist)
        raw_tool = self._wrench_in_tool(m.pose, m.twist)
        running = self.program is not None and self.runtime_state == RuntimeState.PLAYING  # a paused one is not
        powered = self.robot_mode >= RobotMode.POWER_ON
        values: dict[str, object] = {
            "actual_TCP_pose": tuple(m.pose),
            "actual_TCP_speed": tuple(m.twist),
            "target_TCP_pose": tuple(m.pose),
            "target_TCP_speed": tuple(m.twist),
            "actual_TCP_force": tuple(force),
            "ft_raw_wrench": tuple(raw_tool),
            "tcp_force_scalar": math.sqrt(sum(f * f for f in force[:3])),
            "actual_q": tuple(m.q.tolist()),
            "target_q": tuple(m.q.tolist()),
            "actual_qd": tuple(m.qd.tolist()),
            "target_qd": tuple(m.qd.tolist()),
            "robot_mode": int(self.robot_mode),
            "joint_mode": (253 if self.robot_mode == RobotMode.RUNNING else 251,) * 6,  # RUNNING / IDLE
            "safety_mode": int(self.safety_mode),
            "safety_status": int(self.safety_mode),
            "safety_status_bits": sum(1 << b for b in _SAFETY_BITS[self.safety_mode]),
            "robot_status_bits": (1 if powered else 0) | (2 if running else 0),
            "runtime_state": int(self.runtime_state),
            "speed_scaling": 1.0 if m.mode is not MotionMode.IDLE or running else 0.0,
            "target_speed_fraction": self.speed_fraction,
            "actual_digital_output_bits": self.digital_out,
            "payload": self.payload,
            "payload_cog": tuple(self.payload_cog),
            "tcp_offset": tuple(m.tcp_offset),
            "joint_temperatures": (30.0,) * 6,
            "actual_main_voltage": 48.0,
            "actual_robot_voltage": 48.0 if powered else 0.0,
            "actual_robot_current": 0.5 if powered else 0.0,
            "actual_joint_voltage": (48.0 if powered else 0.0,) * 6,
            "actual_tool_accelerometer": (0.0, 0.0, 9.81),
            "actual_execution_time": 0.2,
        }
        return Snapshot(
            timestamp=now - self.t0,
            values=values,
            out_int=tuple(self.out_int),
            out_double=tuple(self.out_double),
            out_bits=self.out_bits,
            in_int=tuple(self.in_int),
            in_double=tuple(self.in_double),
            in_bits=self.in_bits,
        )

    # -- the force/torque sensor ----------------------------------------------------------------------

    def contact(self, pose: Sequence[float], twist: Sequence[float]) -> list[float]:
        """The phantom's wrench on the tool (base frame, at the TCP); zero without a phantom."""
        if self.phantom is None:
            return [0.0] * 6
        return [*contact_force(self.phantom, pose, twist[:3]).tolist(), 0.0, 0.0, 0.0]

    def measured_wrench(self, pose: Sequence[float], twist: Sequence[float]) -> list[float]:
        """``actual_TCP_force``: contact + injected wrench, base frame at the TCP, minus zeroFtSensor's offset."""
        contact = self.contact(pose, twist)
        return [c + r - o for c, r, o in zip(contact, self.raw_force, self.ft_offset, strict=True)]

    def _wrench_in_tool(self, pose: Sequence[float], twist: Sequence[float]) -> list[float]:
        """``ft_raw_wrench``: the sensor's own reading, in the tool frame, not zeroed."""
        rot_t = rotvec_to_matrix(pose[3:6]).T
        injected = np.concatenate([rot_t @ np.asarray(self.raw_force[:3]), rot_t @ np.asarray(self.raw_force[3:])])
        if self.phantom is not None:
            injected += contact_wrench(self.phantom, pose, twist[:3])
        return injected.tolist()

    # -- registers ------------------------------------------------------------------------------------

    def write_out_int(self, idx: int, value: int) -> None:
        if 0 <= idx < N_REGISTERS:
            self.out_int[idx] = int(value)

    def write_out_double(self, idx: int, value: float) -> None:
        if 0 <= idx < N_REGISTERS:
            self.out_double[idx] = float(value)

    def claim_inputs(self, conn_id: int, names: list[str]) -> set[str]:
        """Claim input names for an RTDE connection; return the ones another connection already holds."""
        with self.lock:
            taken = {n for n in names if self.input_owner.get(n, conn_id) != conn_id}
            if self.config.exclusive_inputs and taken:
                return taken
            for n in names:
                self.input_owner.setdefault(n, conn_id)
            return set()

    def release_inputs(self, conn_id: int) -> None:
        with self.lock:
            for n in [n for n, c in self.input_owner.items() if c == conn_id]:
                del self.input_owner[n]

    def apply_inputs(self, names: list[str], values: list[Any]) -> None:
        """Apply one RTDE input data package: registers take the new values at once (the script reads them at
        its next cycle) and every name counts as updated for the RTDE watchdog."""
        now = time.monotonic()
        data = dict(zip(names, values, strict=True))
        with self.lock:
            for name, value in data.items():
                self.input_updated[name] = now
                reg = register_type(name)
                if reg is not None:
                    _, kind, idx = reg
                    if kind == "int":
                        self.in_int[idx] = int(value)
                    elif kind == "double":
                        self.in_double[idx] = float(value)
                    else:
                        self.in_bits = (self.in_bits | (1 << idx)) if value else (self.in_bits & ~(1 << idx))
                elif name == "input_bit_registers0_to_31":
                    self.in_bits = (self.in_bits & ~0xFFFFFFFF) | int(value)
                elif name == "input_bit_registers32_to_63":
                    self.in_bits = (self.in_bits & ~(0xFFFFFFFF << 32)) | (int(value) << 32)
                elif name == "external_force_torque":
                    self.external_ft = [float(v) for v in value]
                elif name == "speed_slider_fraction":
                    self.speed_fraction = float(value)
                elif name == "standard_digital_output":
                    mask = int(data.get("standard_digital_output_mask", 0xFF))
                    self.digital_out = (self.digital_out & ~mask) | (int(value) & mask)

    # -- programs -------------------------------------------------------------------------------------

    def can_run_programs(self) -> str | None:
        """None if a program may start, else the reason (what PolyScope would show in a popup)."""
        if not self.remote_control:
            return "the controller is in local control (remote control is off on the teach pendant)"
        if self.robot_mode != RobotMode.RUNNING:
            return f"robot mode is {self.robot_mode.name}, not RUNNING (power on and release the brakes)"
        if self.safety_mode not in (SafetyMode.NORMAL, SafetyMode.REDUCED):
            return f"safety mode is {self.safety_mode.name}"
        return None

    def load_program(self, program: Program, source: str) -> bool:
        """A complete program arrived on a script port: it replaces the running one, like on a real UR."""
        with self.lock:
            reason = self.can_run_programs()
            if reason is not None:
                self.event(f"program {program.name} from {source} refused: {reason}")
                return False
            if self.program is not None:
                self.stop_program(f"replaced by {program.name} from {source}", decelerate=True)
            self.program = program
            self.runtime_state = RuntimeState.PLAYING
            self.event(f"program {program.name} from {source} started")
            program.start(self)
            return True

    def stop_program(self, reason: str, decelerate: bool = True) -> None:
        with self.lock:
            if self.program is None:
                return
            self.event(f"program {self.program.name} stopped: {reason}")
            self.program = None
            self.runtime_state = RuntimeState.STOPPED
            # rtde_set_watchdog lives in the program: it disappears with it (a new script must set it again).
            self.watchdog = None
            self.model.end_force_mode()  # force_mode too
            if decelerate or self.model.mode is not MotionMode.IDLE:
                # A stopped program stops the arm; nothing keeps a speedl or a servoj alive.
                self.model.stopl(self.config.stop_deceleration)

    def runtime_exception(self, text: str) -> None:
        """The program failed (e.g. an inverse kinematics without solution): it stops, and so does the arm, as
        PolyScope stops a program on a runtime error. The safety mode stays NORMAL: ur_rtde sees the program stop
        (``isProgramRunning()`` false, the pending command answers False)."""
        with self.lock:
            name = self.program.name if self.program is not None else "<none>"
            self.event(f"runtime exception in program {name}: {text}")
            self.count("runtime_exceptions")
            self.stop_program(f"runtime exception: {text}", decelerate=True)

    # -- safety ---------------------------------------------------------------------------------------

    def protective_stop(self, reason: str) -> None:
        with self.lock:
            self.event(f"protective stop: {reason}")
            self.count("protective_stops")
            self.safety_mode = SafetyMode.PROTECTIVE_STOP
            self.protective_stop_time = time.monotonic()
            self.stop_program("protective stop", decelerate=True)
            self.model.stopl(self.config.stop_deceleration)

    def unlock_protective_stop(self) -> tuple[bool, str]:
        with self.lock:
            if self.safety_mode != SafetyMode.PROTECTIVE_STOP:
                return True, "Protective stop releasing"
            elapsed = time.monotonic() - self.protective_stop_time
            if elapsed < self.config.unlock_delay:
                return False, (
                    f"Cannot unlock protective stop until {self.config.unlock_delay:g}s after occurrence. "
                    "Always inspect cause of protective stop before unlocking"
                )
            self.safety_mode = SafetyMode.NORMAL
            self.event("protective stop unlocked")
            return True, "Protective stop releasing"

    def set_safety_mode(self, mode: SafetyMode, reason: str) -> None:
        """The safety system enters ``mode`` (a safeguard stop from an open guard, reduced mode from a safety plane,
        a violation...).

        A safeguard stop is a category 2 stop that **pauses** the program, as on a UR e-Series (the user manual's
        safety I/O: "Safeguard stop performs a category 2 stop", its reset input "resumes the robot from a
        Safeguard stopped state"; UR's forum: a safeguard stop "pauses the robot program execution"): the arm
        decelerates and stays powered, the program stays loaded (``runtime_state`` PAUSED, the program-running
        bit off, as ur_rtde's ``isProgramRunning`` reads it) and, when the safeguard is reset (back to NORMAL or
        REDUCED: the automatic reset, or the reset input), it **resumes by itself** where it was, reading its
        input registers as it left them: whatever command a client left there runs again. Any other mode that
        forbids motion stops the program and the arm, as a protective stop does."""
        with self.lock:
            self.event(f"safety mode {mode.name}: {reason}")
            self.safety_mode = mode
            if mode == SafetyMode.SAFEGUARD_STOP and self.program is not None:
                if self.runtime_state == RuntimeState.PLAYING:
                    self.runtime_state = RuntimeState.PAUSED
                    self.event(f"program {self.program.name} paused: safeguard stop")
                self.model.end_force_mode()
                self.model.stopl(self.config.stop_deceleration)
            elif mode not in (SafetyMode.NORMAL, SafetyMode.REDUCED):
                self.stop_program(mode.name.lower().replace("_", " "), decelerate=True)
                self.model.stopl(self.config.stop_deceleration)
            elif self.program is not None and self.runtime_state == RuntimeState.PAUSED:
                self.runtime_state = RuntimeState.PLAYING
                # The watchdog counts from the resume: the client could not know when the reset would come.
                if self.watchdog is not None:
                    self.input_updated[self.watchdog[0]] = time.monotonic()
                self.event(f"program {self.program.name} resumed: safeguard reset")

    def emergency_stop(self, reason: str) -> None:
        with self.lock:
            self.event(f"emergency stop: {reason}")
            self.safety_mode = SafetyMode.ROBOT_EMERGENCY_STOP
            self.stop_program("emergency stop", decelerate=False)
            self.model.halt()
            self.robot_mode = RobotMode.IDLE  # brakes engage

    def release_emergency_stop(self) -> None:
        with self.lock:
            if self.safety_mode in (SafetyMode.ROBOT_EMERGENCY_STOP, SafetyMode.SYSTEM_EMERGENCY_STOP):
                self.safety_mode = SafetyMode.NORMAL
                self.event("emergency stop released (robot IDLE: brake release needed)")

    def set_power(self, on: bool) -> None:
        with self.lock:
            if on:
                if self.robot_mode < RobotMode.IDLE:
                    self.robot_mode = RobotMode.IDLE
            else:
                self.stop_program("power off", decelerate=False)
                self.model.halt()
                self.robot_mode = RobotMode.POWER_OFF
            self.event(f"power {'on' if on else 'off'}")

    def brake_release(self) -> None:
        with self.lock:
            if self.robot_mode in (RobotMode.IDLE, RobotMode.POWER_ON):
                self.robot_mode = RobotMode.RUNNING
                self.event("brakes released")

    # -- status ---------------------------------------------------------------------------------------

    def status(self) -> dict[str, object]:
        with self.lock:
            return {
                "timestamp": self.snapshot.timestamp,
                "pose": list(self.model.pose),
                "twist": list(self.model.twist),
                "q": self.model.q.tolist(),
                "qd": self.model.qd.tolist(),
                "tcp_offset": list(self.model.tcp_offset),
                "motion": self.model.mode.value,
                "force_mode": self.model.force is not None,
                "contact": self.contact(self.model.pose, self.model.twist),
                "arm": self.model.arm.name,
                "joint_limits": [[lo, hi] for lo, hi in zip(self.model.lower.tolist(), self.model.upper.tolist(),
                                                            strict=True)],
                "runtime_state": self.runtime_state.name,
                "program": self.program.name if self.program else None,
                "robot_mode": self.robot_mode.name,
                "safety_mode": self.safety_mode.name,
                "speed_fraction": self.speed_fraction,
                "remote_control": self.remote_control,
                "payload": self.payload,
                "watchdog": list(self.watchdog) if self.watchdog else None,
                "force": list(self.raw_force),
                "ft_offset": list(self.ft_offset),
                "faults": {
                    "freeze": self.faults.freeze,
                    "hung": self.faults.hung,
                    "link_down": self.faults.link_down,
                    "dashboard_silent": self.faults.dashboard_silent,
                },
                "out_int": self.out_int[:4],
                "in_int": self.in_int[:4],
                "counters": dict(self.counters),
                "events": list(self.events[-30:]),
            }


@dataclass
class _AsyncProgress:
    """The async progress register protocol of rtde_control.script (output_int_register 2)."""

    wr_count: int = 0
    op_id: int = 0

    def value(self, progress: int) -> int:
        self.wr_count = (self.wr_count + 1) % 128
        if progress == 0:
            self.op_id = (self.op_id + 1) % 128
        reg = self.wr_count * 65536 + self.op_id * 16777216
        if progress >= 0:
            reg += min(progress, 32767) + 32768
        return reg
