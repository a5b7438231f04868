"""The servo and torch units of the edge agent: decisions from :mod:`.control`, hardware writes and
publishing in their own named worker threads (a serial microcontroller that answers slowly must never hold
up the control plane, where stop commands are handled).

A driver that cannot open (no I²C bus, no serial port, no library) is logged with its reason and retried
every few seconds; commands are still accepted and reported, with the driver's error in ``reason``.
"""

from __future__ import annotations

import logging
import math
import threading
import time
from typing import Any

import zenoh

from iorthand import keys
from iorthand.protocol import Sequencer, ServoState, TorchState
from iorthand.transport import Worker, publisher
from iorthand_edge.actuators.config import ServosConfig, TorchConfig
from iorthand_edge.actuators.control import AngleHistory, ServoController, ServoOutcome, TorchOutcome, torch_command
from iorthand_edge.actuators.drivers import ActuatorDriver, ActuatorError, make_driver

log = logging.getLogger("iorthand.edge.actuators")

REOPEN_S = 3.0
# A refused command is reported on state/servo or state/torch, at most this often: a flood of refused commands
# (another operator's, 2 600-3 100 a second in a red-team run) was republished one state each to every watcher,
# the recorder included. A command that is carried out is reported at once.
REFUSAL_REPORT_S = 0.1


class _DriverHolder:
    """Opens a driver, remembers why it failed, re-tries now and then."""

    def __init__(self, name: str, driver: ActuatorDriver) -> None:
        self.name = name
        self.driver = driver
        self.ready = False
        self.error = ""
        self._next_try = 0.0

    def ensure(self, now: float) -> bool:
        if self.ready or now < self._next_try:
            return self.ready
        try:
            self.driver.open()
        except ActuatorError as exc:
            if str(exc) != self.error:
                log.error("%s driver unavailable: %s (retrying every %.0f s)", self.name, exc, REOPEN_S)
            self.error = str(exc)
            self._next_try = now + REOPEN_S
            return False
        log.info("%s driver %s ready", self.name, type(self.driver).__name__)
        self.ready, self.error = True, ""
        return True

    def write(self, fn_name: str, channel: int, value: float) -> None:
        try:
            getattr(self.driver, fn_name)(channel, value)
        except ActuatorError as exc:
            if str(exc) != self.error:
                log.error("%s: %s — re-opening the driver", self.name, exc)
            self.error = str(exc)
            self.driver.close()
            self.ready = False
            self._next_try = time.monotonic() + REOPEN_S

    def close(self) -> None:
        self.driver.close()
        self.ready = False


class ServoUnit:
    def __init__(self, config: ServosConfig, driver: ActuatorDriver | None = None) -> None:
        self.config = config
        self.controller = ServoController(config)
        self.history = AngleHistory(config.history_s, self.controller.angles)
        self.driver = _DriverHolder("servo", driver or make_driver(config.driver))
        self._lock = threading.Lock()
        self._outcome = ServoOutcome(*self.controller.angles, clamped=False, reason="")
        self._dirty = True  # publish now (a new command)
        self._refused = False  # a refusal waits to be published (no sooner than REFUSAL_REPORT_S after the last)
        self._wake = threading.Event()  # a command or a rejection for the loop, which sleeps while nothing moves
        self._written: dict[str, float] = {}
        self._seq = Sequencer()
        self._pub: zenoh.Publisher | None = None
        self._worker: Worker | None = None
        self.last_state: ServoState | None = None

    def start(self, session: zenoh.Session | None, robot_keys: keys.RobotKeys, stop: threading.Event) -> None:
        if session is not None:
            self._pub = publisher(session, robot_keys.key(keys.STATE_SERVO))
        self._worker = Worker("edge-servos", self._loop, stop)
        self._worker.start()

    def join(self, timeout: float = 2.0) -> None:
        self._wake.set()
        if self._worker is not None:
            self._worker.join(timeout)
        self.driver.close()

    def command(self, pan: Any = None, tilt: Any = None) -> ServoOutcome:
        """New absolute targets (rad; None keeps an axis). Raises TypeError/ValueError on NaN or a wrong type;
        out-of-range angles are clamped and reported (also on ``state/servo``)."""
        with self._lock:
            outcome = self.controller.command(pan, tilt, time.monotonic())
            self._outcome, self._dirty = outcome, True
        self._wake.set()
        if outcome.clamped:
            log.warning("servo command clamped: %s", outcome.reason)
        return outcome

    def reject(self, reason: str) -> None:
        """Report a refused command on ``state/servo`` (the targets do not change), within REFUSAL_REPORT_S."""
        with self._lock:
            self._outcome = ServoOutcome(self._outcome.pan_target, self._outcome.tilt_target, False, reason)
            wake, self._refused = not self._refused, True
        if wake:  # (one wake-up per report, not per refused command)
            self._wake.set()

    def servo_angles_at(self, t_ns: int) -> tuple[float, float]:
        """(pan, tilt) in rad at wall-clock time ``t_ns`` (for the perception chain)."""
        return self.history.at(t_ns)

    def _loop(self, stop: threading.Event) -> None:
        period = 1.0 / self.config.rate_hz
        last_pub = -math.inf
        while not stop.is_set():
            self._wake.clear()  # before reading: what is commanded after this wakes the rest below at once
            with self._lock:
                now = time.monotonic()
                self.controller.step(now)
                pan, tilt = self.controller.angles
                outcome, dirty, moving = self._outcome, self._dirty, self.controller.moving
                refusal_due = self._refused and now - last_pub >= REFUSAL_REPORT_S
                self._dirty = False
                publishing = dirty or refusal_due or now - last_pub >= 1.0 / self.config.publish_hz
            self.history.add(time.time_ns(), (pan, tilt))
            if self.driver.ensure(now):
                for axis, angle in (("pan", pan), ("tilt", tilt)):
                    if self._written.get(axis) != angle:
                        channel = getattr(self.config, axis).channel
                        self.driver.write("set_angle", channel, math.degrees(angle))
                        if self.driver.ready:
                            self._written[axis] = angle
            moved = self.last_state is not None and (pan, tilt) != (self.last_state.pan, self.last_state.tilt)
            if publishing or moved:
                with self._lock:  # what is published carries the latest refusal's reason
                    self._refused, outcome = False, self._outcome
                last_pub = now
                self._publish(pan, tilt, outcome)
            if moving or not self.driver.ready:
                time.sleep(period)  # not stop.wait: see the force monitor's loop (a stop is seen within a period)
            else:
                # At rest, nothing to step or write until a command: sleep until one, or until the heartbeat
                # (or a refusal's report) is due (50 wake-ups a second less on the control process; join() wakes
                # it to stop).
                due = last_pub + (REFUSAL_REPORT_S if self._refused else 1.0 / self.config.publish_hz)
                self._wake.wait(max(0.0, due - time.monotonic()))

    def _publish(self, pan: float, tilt: float, outcome: ServoOutcome) -> None:
        reason = outcome.reason
        if self.driver.error:
            reason = f"{reason}; driver: {self.driver.error}" if reason else f"driver: {self.driver.error}"
        state = ServoState(
            pan=pan, tilt=tilt, pan_target=outcome.pan_target, tilt_target=outcome.tilt_target,
            clamped=outcome.clamped, reason=ServoState.fit("reason", reason), period=1.0 / self.config.publish_hz,
        ).stamp(self._seq.next())
        self.last_state = state
        if self._pub is not None:
            self._pub.put(state.encode())


class TorchUnit:
    def __init__(self, config: TorchConfig, driver: ActuatorDriver | None = None) -> None:
        self.config = config
        self.driver = _DriverHolder("torch", driver or make_driver(config.driver))
        self._lock = threading.Lock()
        self._outcome = TorchOutcome(False, 0.0, "")
        self._commanded = False  # a command waits to be carried out and published (at once)
        self._refused = False  # a refusal waits to be published (no sooner than REFUSAL_REPORT_S after the last)
        self._wake = threading.Event()
        self._written: float | None = None
        self._seq = Sequencer()
        self._pub: zenoh.Publisher | None = None
        self._worker: Worker | None = None
        self.last_state: TorchState | None = None

    def start(self, session: zenoh.Session | None, robot_keys: keys.RobotKeys, stop: threading.Event) -> None:
        if session is not None:
            self._pub = publisher(session, robot_keys.key(keys.STATE_TORCH))
        self._stop = stop
        self._worker = Worker("edge-torch", self._loop, stop)
        self._worker.start()

    def join(self, timeout: float = 2.0) -> None:
        self._wake.set()
        if self._worker is not None:
            self._worker.join(timeout)
        self.driver.close()

    def command(self, on: Any, brightness: Any = 1.0) -> TorchOutcome:
        """Raises TypeError/ValueError on a wrong type or NaN; clamps the brightness and says so."""
        outcome = torch_command(self.config, on, brightness)
        with self._lock:
            self._outcome, self._commanded = outcome, True
        if outcome.reason:
            log.warning("torch command: %s", outcome.reason)
        self._wake.set()
        return outcome

    def reject(self, reason: str) -> None:
        with self._lock:
            o = self._outcome
            self._outcome = TorchOutcome(o.on, o.brightness, reason)
            wake, self._refused = not self._refused, True
        if wake:  # (one wake-up per report, not per refused command)
            self._wake.set()

    def _loop(self, stop: threading.Event) -> None:
        last_pub = -math.inf
        while not stop.is_set():
            self._wake.clear()  # before reading: a command after this ends the wait below at once
            now = time.monotonic()
            with self._lock:
                outcome = self._outcome
                # Publish a command's outcome and the heartbeat at once, a refusal once REFUSAL_REPORT_S is up.
                publishing = self._commanded or now - last_pub >= 1.0 / self.config.publish_hz or \
                    (self._refused and now - last_pub >= REFUSAL_REPORT_S)
                if publishing:
                    self._commanded = self._refused = False
            if self.driver.ensure(now) and self._written != outcome.output:
                self.driver.write("set_level", self.config.channel, outcome.output)
                if self.driver.ready:
                    self._written = outcome.output
            if publishing:
                last_pub = now
                self._publish(outcome)
            due = last_pub + (REFUSAL_REPORT_S if self._refused else 1.0 / self.config.publish_hz)
            self._wake.wait(max(0.0, due - time.monotonic()))

    def _publish(self, outcome: TorchOutcome) -> None:
        reason = outcome.reason
        if self.driver.error:
            reason = f"{reason}; driver: {self.driver.error}" if reason else f"driver: {self.driver.error}"
        # Report what the lamp really does: off while the driver is down.
        lit = outcome.on and self.driver.ready
        state = TorchState(on=lit, brightness=outcome.brightness if lit else 0.0, reason=TorchState.fit("reason", reason),
                           period=1.0 / self.config.publish_hz)
        self.last_state = state.stamp(self._seq.next())
        if self._pub is not None:
            self._pub.put(self.last_state.encode())
