"""The edge's control loop in simulated time, for tests: the real supervisor, previewed moves (GotoController),
simulated robot, phantom and force levels, wired as the agent wires them, on a fake clock: a minute of a sweep
runs in a few seconds, the same every time. What this leaves out (Zenoh, threads, real timing) the live tests
of the same behaviour cover.

The operator holds the deadman with zero twists at 60 Hz (hold-to-run); the force sensor samples at 100 Hz
with white noise, as the simulated sensor does; the levels follow the configured thresholds."""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np

from iorthand import keys
from iorthand.protocol import ForceLevel, TwistCommand
from iorthand_edge.force.config import ForceConfig
from iorthand_edge.force.contact import PhantomConfig, contact_wrench
from iorthand_edge.force.levels import LevelTracker
from iorthand_edge.goto import GotoConfig, GotoController
from iorthand_edge.robots.config import SimRobotConfig
from iorthand_edge.robots.sim import SimRobot
from iorthand_edge.supervisor import Action, SafetyConfig, Supervisor
from tests.grants import Grants

CONTROL_PERIOD = 1 / 125
COMMAND_PERIOD = 1 / 60
SENSOR_PERIOD = 1 / 100


class FakeClock:
    def __init__(self) -> None:
        self.t = 1000.0

    def __call__(self) -> float:
        return self.t


@dataclass
class Trace:
    """What happened, sample by sample: the force along the probe (pressing positive), the level, the goto."""

    t: list[float] = field(default_factory=list)
    force: list[float] = field(default_factory=list)
    peak_level: ForceLevel = ForceLevel.SAFE
    statuses: set[str] = field(default_factory=set)
    progress: list[str] = field(default_factory=list)  # each distinct goto reason, in order


class SimEdge:
    def __init__(self, phantom: PhantomConfig, start: list[float], noise: float = 0.05, seed: int = 3,
                 safety: SafetyConfig | None = None, goto: GotoConfig | None = None) -> None:
        self.clock = FakeClock()
        self.robot = SimRobot(SimRobotConfig(initial_pose=start), clock=self.clock)
        self.robot.connect()
        self.safety = safety or SafetyConfig(auto_arm=True, profile="local")
        self.force_config = ForceConfig()
        self.sv = Supervisor(self.safety, period=CONTROL_PERIOD, force_required=True)
        self.sv.contact_ceiling = self.force_config.levels.caution
        self.goto = GotoController(goto or GotoConfig(), self.safety.workspace.min, self.safety.workspace.max)
        self.phantom = phantom
        self.levels = LevelTracker(self.force_config.levels)
        self.rng = np.random.default_rng(seed)
        self.grants = Grants()
        ok, reason = self.grants.acquire(self.sv, "op1", self.clock.t)
        assert ok, reason
        self.seq = self.grants.seq
        self.trace = Trace()
        self._next_cmd = self._next_sample = self.clock.t
        self.sample(force=True)

    def limits(self):
        p = self.sv.limits
        return self.goto.limits(p.linear, p.angular, self.safety.max_linear_acceleration)

    def sample(self, force: bool = False) -> None:
        """The force sensor at 100 Hz: its level to the supervisor, its axial force to contact mode."""
        if not force and self.clock.t < self._next_sample:
            return
        self._next_sample += SENSOR_PERIOD
        reading = self.robot.read_state()
        wrench = contact_wrench(self.phantom, reading.tcp_pose, reading.tcp_speed)
        wrench = wrench + self.rng.normal(0.0, 0.05, 6) * np.array([1, 1, 1, 0.1, 0.1, 0.1])
        level = self.levels.add(wrench, self.clock.t)
        self.sv.update_force(level, False, self.clock.t)
        pressing = -float(wrench[2])  # the probe's axis is the tool's z; the surface pushes back along -z
        self.sv.update_contact_force(pressing, self.clock.t)
        self.trace.t.append(self.clock.t)
        self.trace.force.append(pressing)
        self.trace.peak_level = max(self.trace.peak_level, level)

    def command(self, deadman: bool = True, twist: list[float] | None = None) -> None:
        self.seq += 1
        tw = twist or [0.0] * 6
        cmd = TwistCommand(operator="op1", deadman=deadman, linear=tw[:3], angular=tw[3:], state_age=0.02)
        cmd.stamp(self.seq, int(self.clock.t * 1e9))
        pose = self.robot.read_state().tcp_pose
        off = self.sv.contact_off_reason
        goto = self.goto.twist(pose, self.clock.t, contact_off=off).tolist() if self.goto.active else None
        decision = self.sv.on_command(self.grants.sign(self.sv, "op1", cmd), self.clock.t, self.clock.t, pose, goto)
        if decision.cancel_goto:
            self.goto.cancel(decision.cancel_goto)
        self._drive(decision)

    def _drive(self, decision) -> None:
        self.trace.statuses.add(str(decision.status))
        if decision.action == Action.MOVE:
            self.robot.send_twist(decision.twist, self.safety.max_linear_acceleration)
        elif decision.action == Action.STOP:
            self.robot.stop(self.safety.stop_deceleration)

    def run(self, seconds: float, until: Callable[[], bool] = lambda: False, deadman: bool = True,
            twist: list[float] | None = None) -> None:
        """Run the loop for ``seconds`` of simulated time (or until ``until()``), the operator holding
        ``deadman`` with ``twist`` (zero: hold-to-run for a previewed move)."""
        end = self.clock.t + seconds
        while self.clock.t < end and not until():
            if self.clock.t >= self._next_cmd:
                self.command(deadman, twist)
                self._next_cmd += COMMAND_PERIOD
            self.sample()
            # The goto's velocity changes with each command (as in the agent); each cycle limits it afresh.
            decision = self.sv.step(self.clock.t, self.robot.read_state().tcp_pose)
            if self.goto.active and decision.status.halts:
                self.goto.cancel(decision.reason)
            self._drive(decision)
            if self.goto.reason and (not self.trace.progress or self.trace.progress[-1] != self.goto.reason):
                self.trace.progress.append(self.goto.reason)
            self.clock.t += CONTROL_PERIOD

    def contact(self, on: bool, target: float | None = None) -> None:
        req = self.grants.request(self.sv, "op1", keys.CONTROL_CONTACT)
        ok, reason = self.sv.set_contact(req, on, target)
        assert ok, reason

    def start(self, name: str, params: dict | None = None) -> None:
        here = self.robot.read_state().tcp_pose
        pv = self.goto.preview(name, "op1", here, self.clock.t, self.limits(), params=params)
        assert pv.ok, pv.plan.reason
        ok, reason = self.goto.start(name, pv.token, "op1", here, self.clock.t, self.limits(),
                                     contact=self.sv.contact_target is not None)
        assert ok, reason


def within(trace: Trace, target: float, since: float, tolerance: float = 1.0) -> tuple[float, float, float]:
    """Share of the samples after ``since`` within ±``tolerance`` N of ``target``, their RMS and max error."""
    held = np.array([f for t, f in zip(trace.t, trace.force, strict=True) if t >= since])
    err = held - target
    return float(np.mean(np.abs(err) <= tolerance)), float(np.sqrt(np.mean(err**2))), float(np.max(np.abs(err)))


CYLINDER = dict(shape="cylinder", axis="x", radius=0.07, axis_height=0.08, x_range=[0.20, 0.40],
                y_range=[-0.10, 0.10], damping=20.0)
# Above the cylinder's top (z 0.15), a little off its crest so that the lanes run across its curvature.
START_ABOVE = [0.27, -0.02, 0.16, math.pi, 0.0, 0.0]
