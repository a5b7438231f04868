"""The force worker: samples the sensor, tracks the warning level, publishes, and tells the agent.

Each tick reads the newest sample, updates the :class:`LevelTracker`, publishes ``state/force``, and publishes
``state/force_level`` on every change of level or staleness and at ``level_rate_hz``. Changes go to
``on_change`` (the agent, which passes them to the supervisor) at once. A sensor with a stream of its own (Net
F/T) is ticked by a named thread of its own at ``force.rate_hz`` (each read waits at most half a period); a
sensor paced by the robot (its samples come from the robot state) by the agent's control loop, once per robot
state (:meth:`ForceMonitor.on_robot_state`). A sensor that fails to start or dies is retried every second;
meanwhile it is stale, which the supervisor treats as a stop.
"""

from __future__ import annotations

import logging
import math
import threading
import time
from collections.abc import Callable

import zenoh

from iorthand import keys
from iorthand.protocol import ForceLevelState, ForceSample, Message, Sequencer
from iorthand.transport import Worker, publisher
from iorthand_edge.force.config import ForceConfig
from iorthand_edge.force.levels import LevelState, LevelTracker
from iorthand_edge.force.sensors import ForceSensor, SensorError, WrenchSample

log = logging.getLogger("iorthand.edge.force")

RETRY_S = 1.0
WIRE_LIMIT = 1e5  # N or N·m: the most a force message carries (ForceSample, ForceLevelState); beyond is saturated


def on_the_wire(value: float) -> float | None:
    """``value`` as a force message can carry it: saturated at ±WIRE_LIMIT; None for NaN, which is no measurement
    (the level counts it as danger: see levels.next_level)."""
    if math.isnan(value):
        return None
    return max(-WIRE_LIMIT, min(WIRE_LIMIT, value))


def _level_value(value: float) -> float:
    """The level's quantity on the wire: a NaN (a red level) as the most the wire carries."""
    wire = on_the_wire(value)
    return WIRE_LIMIT if wire is None else wire


def stale_message(silent_s: float, sensor_error: str) -> str:
    """The log line of a stale spell: how long without a sample and, when the sensor said why (a Net F/T that
    froze, garbage, a bad status), its reason."""
    why = f" ({sensor_error})" if sensor_error else ""
    return f"force sensor stale: no sample for {1000 * silent_s:.0f} ms{why} — stopping, contact motion refused"


class ForceMonitor:
    def __init__(self, config: ForceConfig, sensor: ForceSensor, on_change: Callable[[LevelState], None]) -> None:
        self.config = config
        self.sensor = sensor
        self.tracker = LevelTracker(config.levels)
        self.on_change = on_change
        self.period = 1.0 / config.rate_hz
        self.state = self.tracker.state(time.monotonic())
        self.samples = 0
        self.last_wrench = [0.0] * 6
        self.stale_since: float | None = None  # monotonic time the current stale spell was detected
        self._started = False
        self._seq_force = Sequencer()
        self._seq_level = Sequencer()
        self._worker: Worker | None = None
        self._pub_force: zenoh.Publisher | None = None
        self._pub_level: zenoh.Publisher | None = None
        self._last_level_pub = 0.0
        self._reported_errors = 0
        self._errors_at_sample = 0  # the sensor's error count at its last sample: errors since may say why it stopped
        self._not_a_number = False  # the newest sample held a NaN
        self._next_retry = 0.0
        # Signs the level for the owner's client (the agent sets Supervisor.for_owner): the owner believes only
        # the levels this edge published, never a third session's green.
        self.seal: Callable[[str, Message], bytes] | None = None

    def start(self, session: zenoh.Session, robot_keys: keys.RobotKeys, stop: threading.Event) -> None:
        self._pub_force = publisher(session, robot_keys.key(keys.STATE_FORCE))
        self._pub_level = publisher(session, robot_keys.key(keys.STATE_FORCE_LEVEL))
        if not self.paced_by_robot:
            self._worker = Worker("edge-force", self._loop, stop)
            self._worker.start()

    @property
    def paced_by_robot(self) -> bool:
        """Ticked by the agent's control loop at each robot state (:meth:`on_robot_state`), not by a thread."""
        return self.sensor.paced_by_robot

    def join(self, timeout: float = 2.0) -> None:
        if self._worker is not None:
            self._worker.join(timeout)
        self.sensor.close()

    def zero(self) -> None:
        """Bias the sensor (raises SensorError). The caller checks it is safe (see the agent)."""
        self.sensor.zero()

    # ------------------------------------------------------------------ the worker

    def _ensure_started(self, now: float) -> bool:
        if self._started:
            return True
        try:
            self.sensor.start()
        except SensorError as exc:
            log.error("force sensor cannot start: %s — contact motion refused; retrying in %.0f s", exc, RETRY_S)
            return False
        self._started = True
        log.info("force sensor %s started", type(self.sensor).__name__)
        return True

    def on_robot_state(self, now: float) -> LevelState:
        """One tick of a sensor paced by the robot, from the control loop, with the robot state just read."""
        sample = self._read(now, timeout=0.0)
        self._report_errors()
        return self.tick(sample, now)

    def _read(self, now: float, timeout: float) -> WrenchSample | None:
        """The newest sample, starting (or restarting, every RETRY_S) the sensor as needed; None if none."""
        if not self._started and now >= self._next_retry and not self._ensure_started(now):
            self._next_retry = now + RETRY_S
        if not self._started:
            return None
        try:
            return self.sensor.read(timeout=timeout)
        except SensorError as exc:
            log.error("force sensor failed: %s — restarting it in %.0f s", exc, RETRY_S)
            self.sensor.close()
            self._started = False
            self._next_retry = now + RETRY_S
            return None

    def _loop(self, stop: threading.Event) -> None:
        next_tick = time.monotonic()
        while not stop.is_set():
            # Wait at most half a period for a sample so the schedule (and stale detection) holds.
            sample = self._read(time.monotonic(), timeout=self.period / 2)
            self._report_errors()
            self.tick(sample, time.monotonic())
            next_tick += self.period
            delay = next_tick - time.monotonic()
            if delay > 0:
                # A plain sleep, not stop.wait: a stop is seen within a period, and at 100 Hz an Event's Condition
                # (a new lock and a waiter list in Python per wait) cost ~40 µs more CPU a tick on the project's VM.
                time.sleep(delay)
            else:
                next_tick = time.monotonic()

    def _report_errors(self) -> None:
        errors = self.sensor.errors
        if errors != self._reported_errors:
            log.warning("force sensor: %d invalid samples so far, last: %s", errors, self.sensor.last_error)
            self._reported_errors = errors

    def tick(self, sample: WrenchSample | None, now: float) -> LevelState:
        """One cycle with the newest sample (or None); the level sees the peak of its batch, the force stream
        the newest. Public for tests that drive it by hand."""
        if sample is not None:
            self.tracker.add(sample.wrench if sample.batch is None else sample.batch, now)
            self.samples += 1
            self._errors_at_sample = self.sensor.errors
            self.last_wrench = [float(v) for v in sample.wrench]
            wire = [on_the_wire(v) for v in self.last_wrench]
            if (None in wire) != self._not_a_number:
                # Not a measurement: the level is red (and says so on state/force_level); the stream skips it.
                self._not_a_number = None in wire
                if self._not_a_number:
                    log.error("force sensor gives samples that are not numbers (%s): level danger", self.last_wrench)
                else:
                    log.info("force sensor gives numbers again")
            if not self._not_a_number and self._pub_force is not None:
                msg = ForceSample(force=wire[:3], torque=wire[3:])
                self._pub_force.put(msg.stamp(self._seq_force.next(), sample.t_ns).encode())
        state = self.tracker.state(now)
        changed = (state.level, state.stale) != (self.state.level, self.state.stale)
        if changed:
            if state.stale and not self.state.stale:
                self.stale_since = now
                # Only an error since the last sample explains the silence (last_error keeps an old one).
                why = self.sensor.last_error if self.sensor.errors != self._errors_at_sample else ""
                log.error("%s", stale_message(now - state.last_sample, why))
            elif not state.stale and self.state.stale:
                log.info("force sensor fresh again (level %d)", state.level)
            else:
                log.info("force level %d → %d (%.2f N)", self.state.level, state.level, state.value)
        self.state = state
        if changed:
            self.on_change(state)
        if changed or now - self._last_level_pub >= 1.0 / self.config.level_rate_hz:
            self._publish_level(state, now)
        return state

    def _publish_level(self, state: LevelState, now: float) -> None:
        self._last_level_pub = now
        if self._pub_level is None:
            return
        lv = self.config.levels
        msg = ForceLevelState(
            level=int(state.level), stale=state.stale, value=_level_value(state.value), quantity=lv.quantity,
            caution=lv.caution, danger=lv.danger,
        )
        msg.stamp(self._seq_level.next())
        self._pub_level.put(self.seal(keys.STATE_FORCE_LEVEL, msg) if self.seal is not None else msg.encode())
