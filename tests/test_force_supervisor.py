"""The force reaction closed loop, deterministic: the simulated robot, the phantom, the level tracker and the
supervisor stepped together on a simulated clock, with the agent's rates and reaction path (sensor 100 Hz
reading the control loop's latest state, control 125 Hz, commands 60 Hz, a level change applied at once)."""

from __future__ import annotations

import math

import numpy as np
import pytest

from iorthand.protocol import ForceLevel, Status, TwistCommand
from iorthand_edge.force.contact import PhantomConfig, contact_wrench
from iorthand_edge.force.levels import LevelConfig, LevelTracker
from iorthand_edge.force.monitor import RETRY_S, ForceMonitor
from iorthand_edge.force.sensors import ForceSensor, SensorError, WrenchSample
from iorthand_edge.robots.config import SimRobotConfig
from iorthand_edge.robots.sim import SimRobot
from iorthand_edge.supervisor import Action, ForceReaction, SafetyConfig, Supervisor
from tests.grants import Grants

START = [0.30, 0.0, 0.20, math.pi, 0.0, 0.0]  # tool pointing down: pressing is −z in the base frame
PHANTOM = PhantomConfig(surface_z=0.199, stiffness=2000.0, damping=20.0)


class Rig:
    def __init__(self, reaction: ForceReaction | None = None, profile: str = "local") -> None:
        self.t = 1000.0
        self.robot = SimRobot(SimRobotConfig(initial_pose=START), clock=lambda: self.t)
        self.robot.connect()
        self.safety = SafetyConfig(auto_arm=True, profile=profile, force=reaction or ForceReaction())
        self.sv = Supervisor(self.safety, period=0.008, force_required=True)
        self.tracker = LevelTracker(LevelConfig())
        self.reading = self.robot.read_state()
        self.commanded = np.zeros(6)
        self.seq = 0
        self.levels: list[tuple[float, int, float, float]] = []  # (t, level, value, depth)
        self.max_depth = 0.0
        self.depths: list[tuple[float, float]] = []  # (t, depth) at each control cycle
        self.danger_depth: float | None = None
        self.twist_cmd = np.zeros(6)
        self.deadman = False
        self.sensor_on = True
        self.grants = Grants()
        assert self.grants.acquire(self.sv, "op", self.t)[0]

    def depth(self) -> float:
        return PHANTOM.depth(self.reading.tcp_pose)

    def drive(self, decision) -> None:
        """The supervisor's action, carried out as the agent does (every decision: its action says what to do)."""
        if decision.action == Action.MOVE:
            self.commanded = self.robot.send_twist(decision.twist, self.safety.max_linear_acceleration)
        elif decision.action == Action.STOP:
            self.robot.stop(self.safety.stop_deceleration)
            self.commanded = np.zeros(6)

    def run(self, seconds: float) -> None:
        steps = round(seconds * 1000)
        for _ in range(steps):
            self.t = round(self.t + 0.001, 6)
            ms = round((self.t - 1000.0) * 1000)
            if ms % 8 == 0:  # control loop
                self.reading = self.robot.read_state()
                self.drive(self.sv.step(self.t, self.reading.tcp_pose))
                self.max_depth = max(self.max_depth, self.depth())
                self.depths.append((self.t, self.depth()))
            if ms % 10 == 0 and self.sensor_on:  # force worker: reads the control loop's latest state
                w = contact_wrench(PHANTOM, self.reading.tcp_pose, self.reading.tcp_speed)
                before = (self.tracker.level, self.tracker.stale(self.t))
                self.tracker.add(w, self.t)
                self.on_level(before)
            elif ms % 10 == 0:
                self.on_level((self.tracker.level, self.tracker.stale(self.t - 0.01)))
            if ms % 17 == 0:  # operator at ~60 Hz
                self.seq += 1
                # The operator's screen shows the control loop's latest state (at most one 8 ms cycle old).
                cmd = TwistCommand(operator="op", linear=self.twist_cmd[:3], angular=self.twist_cmd[3:], deadman=self.deadman,
                                   state_age=0.008)
                cmd.stamp(self.seq, int(self.t * 1e9))
                cmd = self.grants.sign(self.sv, "op", cmd)
                self.drive(self.sv.on_command(cmd, self.t, self.t, self.reading.tcp_pose))

    def on_level(self, before: tuple[int, bool]) -> None:
        state = self.tracker.state(self.t)
        if (state.level, state.stale) != before:
            self.levels.append((self.t, int(state.level), state.value, self.depth()))
            if state.level == ForceLevel.DANGER and self.danger_depth is None:
                self.danger_depth = self.depth()
            self.sv.update_force(state.level, state.stale, self.t)
            self.drive(self.sv.step(self.t, self.reading.tcp_pose))

    def press(self, vz: float) -> None:
        self.twist_cmd = np.array([0.0, 0.0, vz, 0.0, 0.0, 0.0])
        self.deadman = True


def fresh_rig(**kwargs) -> Rig:
    rig = Rig(**kwargs)
    rig.run(0.05)  # first samples: the sensor is fresh and SAFE
    assert not rig.sv.force_stale
    rig.levels.clear()  # the stale → fresh change at start
    return rig


@pytest.mark.parametrize("profile", ["local", "remote"])
def test_pressing_raises_levels_at_thresholds_and_stops_within_the_margin(profile: str) -> None:
    rig = fresh_rig(profile=profile)
    rig.press(-0.05)  # faster than any profile: clipped to the profile's speed
    rig.run(3.0)
    levels = [lv for _, lv, _, _ in rig.levels]
    assert levels[:2] == [1, 2], rig.levels  # 0 → 1 → 2, no flicker on the way in
    for _, lv, value, _ in rig.levels[:2]:
        assert value >= LevelConfig().thresholds[lv - 1]
    assert rig.danger_depth is not None
    overshoot = rig.max_depth - rig.danger_depth
    assert overshoot <= rig.safety.force.overshoot_margin, f"{1000 * overshoot:.2f} mm past red"
    assert rig.sv.status in (Status.FORCE_DANGER, Status.FORCE_CAUTION)
    # Still pressing: the tool does not go deeper. Retreat is allowed.
    depth = rig.depth()
    rig.run(0.5)
    assert rig.depth() <= depth + 1e-6
    rig.press(+0.005)
    rig.run(0.5)
    assert rig.depth() < depth - 0.001


def test_danger_retracts_the_configured_distance_even_with_the_deadman_held() -> None:
    rig = fresh_rig(reaction=ForceReaction(retract_distance=0.003, retract_speed=0.01), profile="remote")
    rig.press(-0.008)  # and keeps pressing throughout
    rig.run(1.5)
    assert rig.danger_depth is not None
    t_danger = next(t for t, lv, _, _ in rig.levels if lv == 2)
    after = [d for t, d in rig.depths if t_danger <= t <= t_danger + 0.5]
    assert rig.danger_depth - min(after) > 0.0025  # backed off ~3 mm along the normal
    assert rig.max_depth - rig.danger_depth <= rig.safety.force.overshoot_margin
    assert any(s == Status.FORCE_DANGER and "retract" in r for s, r in rig.sv.interventions)


def test_stale_sensor_stops_until_a_fresh_press_then_refuses_contact_motion_but_allows_retreat() -> None:
    """A silent sensor is a stop: the deadman held through it moves nothing, not even away from contact; after a
    release and a press, only motion that does not press harder moves while the sensor is silent."""
    rig = fresh_rig(profile="remote")
    rig.press(-0.005)
    rig.run(0.2)
    assert np.any(rig.commanded)
    rig.sensor_on = False
    last_sample = rig.tracker.last_sample
    rig.run(0.15)
    stale = [t for t, _, _, _ in rig.levels if rig.tracker.stale(t)]
    assert stale, "never flagged stale"
    assert stale[0] - last_sample <= LevelConfig().stale_after + 0.010 + 1e-9  # 100 ms + one sensor period
    assert any(s == Status.FORCE_STALE for s, _ in rig.sv.interventions)
    z = rig.reading.tcp_pose[2]
    rig.run(0.3)  # operator still pressing down
    assert rig.reading.tcp_pose[2] >= z - 0.0005  # only the braking distance after the stop
    z = rig.reading.tcp_pose[2]
    rig.press(+0.005)  # the deadman still held from before the stop
    rig.run(0.3)
    assert rig.reading.tcp_pose[2] == pytest.approx(z, abs=1e-6)
    assert rig.sv.status == Status.FORCE_STALE and "press it again" in rig.sv.reason
    rig.deadman = False
    rig.run(0.1)
    rig.press(+0.005)
    rig.run(0.3)
    assert rig.reading.tcp_pose[2] > z + 0.001
    z = rig.reading.tcp_pose[2]
    rig.press(-0.005)
    rig.run(0.3)
    assert rig.reading.tcp_pose[2] >= z - 0.0005  # only the braking distance


def test_no_sample_yet_refuses_contact_motion() -> None:
    rig = Rig(profile="remote")
    rig.sensor_on = False
    rig.press(-0.005)
    rig.run(0.3)
    assert rig.reading.tcp_pose[2] == pytest.approx(START[2], abs=1e-9)


def test_approach_speed_cap_stops_within_the_margin() -> None:
    r = ForceReaction(overshoot_margin=0.002, reaction_time=0.04)
    v = r.approach_speed_cap(0.25)
    assert v * 0.04 + v * v / (2 * 0.25) == pytest.approx(0.002)


class _Silent(ForceSensor):
    def start(self) -> None: ...
    def read(self, timeout: float) -> WrenchSample | None: return None
    def zero(self) -> None: ...
    def close(self) -> None: ...


def test_monitor_flags_stale_at_the_first_tick_past_the_limit() -> None:
    from iorthand_edge.force.config import ForceConfig

    changes = []
    monitor = ForceMonitor(ForceConfig(), _Silent(), changes.append)
    t = 0.0
    monitor.tick(WrenchSample(np.zeros(6), 0), t)
    assert changes and not changes[-1].stale  # fresh after the first sample
    while not monitor.state.stale:
        t = round(t + 0.01, 6)
        monitor.tick(None, t)
    assert 0.1 < t <= 0.1 + 0.01 + 1e-9
    assert changes[-1].stale and monitor.stale_since == t


class _Recorded:
    """Stands in for a Zenoh publisher: keeps the bytes the monitor puts, which the test decodes as a receiver."""

    def __init__(self) -> None:
        self.sent: list[bytes] = []

    def put(self, payload: bytes) -> None:
        self.sent.append(payload)


@pytest.mark.parametrize("reading", [float("nan"), float("inf"), 2e5])
def test_a_reading_beyond_what_the_wire_carries_still_reaches_every_receiver_as_red(reading: float) -> None:
    """A sample with NaN, inf or more than the messages' 1e5 N made both force messages undecodable: the edge
    went red, and every console and the twin dropped the red as malformed."""
    from iorthand.protocol import ForceLevelState, ForceSample
    from iorthand_edge.force.config import ForceConfig

    changes = []
    monitor = ForceMonitor(ForceConfig(), _Silent(), changes.append)
    monitor._pub_force, monitor._pub_level = _Recorded(), _Recorded()
    monitor.tick(WrenchSample(np.array([0.0, 0.0, reading, 0.0, 0.0, 0.0]), 1), 1.0)
    assert changes[-1].level == ForceLevel.DANGER and not changes[-1].stale
    (level,) = [ForceLevelState.decode(b) for b in monitor._pub_level.sent]
    assert level.level == ForceLevel.DANGER and not level.stale and level.value == 1e5
    forces = [ForceSample.decode(b) for b in monitor._pub_force.sent]
    if math.isnan(reading):
        assert forces == []  # not a measurement: not in the stream (the level says red)
    else:
        assert [f.force for f in forces] == [[0.0, 0.0, 1e5]]  # saturated, as a sensor at its range


class _Flaky(ForceSensor):
    """Read from the robot state (paced by the robot); fails to start once, and fails its reads on request."""

    paced_by_robot = True

    def __init__(self) -> None:
        self.starts = self.closed = 0
        self.failing_start, self.failing_read = True, False

    def start(self) -> None:
        self.starts += 1
        if self.failing_start:
            self.failing_start = False
            raise SensorError("no state from the robot driver")

    def read(self, timeout: float) -> WrenchSample | None:
        if self.failing_read:
            raise SensorError("robot link lost")
        return WrenchSample(np.zeros(6), 0)

    def zero(self) -> None: ...

    def close(self) -> None:
        self.closed += 1


def test_a_sensor_paced_by_the_robot_is_started_retried_and_restarted_by_the_control_cycle() -> None:
    from iorthand_edge.force.config import ForceConfig

    sensor = _Flaky()
    monitor = ForceMonitor(ForceConfig(), sensor, [].append)
    assert monitor.paced_by_robot
    monitor.on_robot_state(10.0)  # the start fails: no sample
    assert (sensor.starts, monitor.samples) == (1, 0)
    monitor.on_robot_state(10.0 + RETRY_S / 2)  # not retried before RETRY_S
    assert sensor.starts == 1
    assert not monitor.on_robot_state(10.0 + RETRY_S).stale  # retried: started, sampled
    assert (sensor.starts, monitor.samples) == (2, 1)
    sensor.failing_read = True
    t = 12.0
    monitor.on_robot_state(t)  # the read fails: the sensor is closed, to be restarted
    assert (sensor.closed, monitor.samples) == (1, 1)
    assert monitor.on_robot_state(t + 0.2).stale  # no sample for longer than stale_after: a stop
    sensor.failing_read = False
    monitor.on_robot_state(t + RETRY_S / 2)
    assert sensor.starts == 2
    assert not monitor.on_robot_state(t + RETRY_S).stale and sensor.starts == 3 and monitor.samples == 2
